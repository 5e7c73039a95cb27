"""A bus behind the host (issue 26, items 1 and 2): in real time against `feedbench sim` under
full load the socketcand hub worked through the host's frames up to ≈ 330 cycles late, so the
drive ran setpoints already in the stream when the quick stop went out, and the stop's bound
(`Runner._stop_bound`, 285 cycles) ran out before the stop had reached it: "not stopped
within 0.285 s … disable voltage" for a stop the drive had not been sent yet, and limit
checks on data that old.

Here the simulated drive in this process sits behind a relay that forwards the host's frames
(SYNC, setpoints, controlwords, heartbeat) in order but later and later: from the plan's
first segment each frame waits `RAMP` × the time since, up to `LAG_S` (400 cycles at 1 ms,
more than the stop bound); the drive's frames come back at once. The host counts its SYNCs
(`daq.clock.SyncSender`), so it measures the backlog (`Runner.backlog`): the run is aborted
"bus N cycles behind" once it exceeds the stop bound, and the stop's bound counts from the
drive cycle that has the stop, "stop reached the drive N cycles after it was sent"."""

from __future__ import annotations

import collections
import threading
import time
import uuid

import numpy as np
import pytest

from feedbench.bench import Bench, parse_run_config
from feedbench.commands.demo import example_config
from feedbench.daq.catalog import Catalog
from feedbench.daq.recording import open_recording
from feedbench.protocols.canbus import LocalVirtualBus
from feedbench.protocols.cia402 import EXTRAPOLATED_CYCLES
from feedbench.sim_backends.process import SimulatedBench

pytestmark = pytest.mark.realtime

LAG_S = 0.4
"""The relay's largest delay of the host's frames (s): 400 cycles at 1 ms."""
RAMP = 0.5
"""How fast the delay grows (s per s): the drive then gets a SYNC every 1.5 ms, no SYNC loss."""
SYNC_LOSS_MS = 250.0
"""The drive's SYNC-loss watchdog (0x2021): on a loaded machine this process's SYNC thread or
the relay can be starved for more than the default 50 ms (EMCY 0x8100), not what is tested."""
STOP_BOUND = 285
"""The chirp's stop bound (cycles): 3000 mm/min / 2 m/s² + 0.25 s + 10 (docs/faults.md)."""


class LateRelay:
    """Forwards every frame of channel `host` to channel `drive`, in order, each after the
    delay of when it came (`delay`: 0 until `start`), and every frame of `drive` to `host`
    at once."""

    def __init__(self, host: str, drive: str, lag_s: float = LAG_S) -> None:
        self.lag_s = lag_s
        self.host = LocalVirtualBus(channel=host)
        self.drive = LocalVirtualBus(channel=drive)
        self.started: float | None = None
        self.done = threading.Event()
        self.threads = [threading.Thread(target=self._forward, daemon=True),
                        threading.Thread(target=self._back, daemon=True)]
        for thread in self.threads:
            thread.start()

    def start(self) -> None:
        if self.started is None:
            self.started = time.perf_counter()

    def delay(self, now: float) -> float:
        return 0.0 if self.started is None else min(self.lag_s, RAMP * (now - self.started))

    def _forward(self) -> None:
        waiting: collections.deque = collections.deque()
        last = 0.0
        while not self.done.is_set():
            now = time.perf_counter()
            wait = 0.01 if not waiting else max(0.0, min(0.01, waiting[0][0] - now))
            msg = self.host.recv(timeout=wait)
            now = time.perf_counter()
            if msg is not None:
                last = max(last, now + self.delay(now))
                waiting.append((last, msg))
            while waiting and waiting[0][0] <= now:
                self.drive.send(waiting.popleft()[1])

    def _back(self) -> None:
        while not self.done.is_set():
            msg = self.drive.recv(timeout=0.01)
            if msg is not None:
                self.host.send(msg)

    def close(self) -> None:
        self.done.set()
        for thread in self.threads:
            thread.join()
        self.host.shutdown()
        self.drive.shutdown()


class LagFromFirstSegment:
    """An observer that starts the relay's delay when the plan's first segment starts."""

    def __init__(self, relay: LateRelay) -> None:
        self.relay = relay

    def on_start(self, plan, channels) -> None: ...

    def on_segment(self, index, segment, cycle) -> None:
        self.relay.start()

    def on_block(self, cycles, block) -> None: ...

    def on_stop(self, status: str, reason: str) -> None: ...


def _chirp_behind(tmp_path, lag_s: float) -> dict:
    """The example chirp, shortened, in real time against the simulated drive behind a
    `LateRelay` of `lag_s`; its catalog row."""
    host, drive = (f"fb-backlog-{side}-{uuid.uuid4().hex[:8]}" for side in ("host", "drive"))
    raw = example_config("chirp")
    raw["bench"].update(channel=host, output_dir=str(tmp_path), clock="realtime",
                        simulated=False, sync_loss_ms=SYNC_LOSS_MS)
    raw["experiment"].update(duration_s=1.0, repetitions=1, settle_s=0.3, tail_s=0.3)
    config = parse_run_config(raw)
    relay = LateRelay(host, drive, lag_s)
    simulated = SimulatedBench({**config.bench, "channel": drive}, {})
    try:
        with Bench(config.bench, config.plan, config.experiment.devices()) as bench:
            return bench.run(config, Catalog(tmp_path / "catalog.sqlite"), tmp_path,
                             observers=[LagFromFirstSegment(relay)], progress=False)
    finally:
        simulated.stack.close()
        relay.close()


def test_a_bus_behind_aborts_the_run_and_the_stop_counts_from_the_drive(tmp_path):
    """Aborted "bus N cycles behind" (N past the stop bound) instead of running on data
    older than a stop takes; the stop is confirmed by motion and the statusword without an
    escalation, its event naming how many cycles after it was sent it reached the drive
    (at least the backlog); every row up to the end is recorded. Before: the run went on,
    its stop ran out of its bound before the drive had it and its SDO reads (0.3 s) out of
    time behind the relay: "drive state unknown"."""
    row = _chirp_behind(tmp_path, LAG_S)
    reason = row["reason"]
    stop = _stopped_without_escalation(row)
    _skip_if_host_stalled(reason)
    assert row["status"] == "aborted", reason
    assert reason.startswith("bus ") and " cycles behind (the TPDO set of SYNC " in reason, reason
    behind = int(reason.split()[1])
    assert behind > STOP_BOUND, reason
    assert reason.endswith(f"the limits would act on data older than a stop takes "
                           f"({STOP_BOUND} cycles)"), reason
    transit = int(stop.text.split("stop reached the drive ")[1].split()[0])
    assert transit >= behind - 5, stop.text  # and the SYNCs sent until the stop went


def test_a_plan_completed_behind_the_bus_stops_without_escalation(tmp_path):
    """A bus 200 cycles behind, less than the stop bound: the plan completes, and its stop
    (setpoint held until standstill, disable operation, disable voltage: each after the
    host saw the state before, a way there and back) is counted while the drive has each
    command, the event naming the cycles before. Before: "not stopped within 0.285 s …
    disable voltage" for a drive that stood and had not been sent the commands yet."""
    row = _chirp_behind(tmp_path, 0.2)
    stop = _stopped_without_escalation(row)
    _skip_if_host_stalled(row["reason"])
    assert row["status"] == "complete", row["reason"]
    words = stop.text.split("stop reached the drive ")[1].split()
    assert 190 <= int(words[0]), stop.text
    assert words[5:10] == ["sent,", "commands", "on", "their", "way"], stop.text
    assert int(words[10]) >= 3 * 190, stop.text  # hold, disable operation, disable voltage


def _stopped_without_escalation(row: dict):
    """The run's stop event, asserted: confirmed by standstill and the statusword, its
    cycles counted from the drive ("stop reached the drive N cycles …"), no escalation;
    the rows recorded up to it, in order."""
    assert not any(word in row["reason"] for word in ("not stopped", "disable voltage",
                                                       "drive state unknown")), row["reason"]
    recording = open_recording(row["file"])
    [stop] = [e for e in recording.events if e.kind == "stop"]
    assert stop.text.startswith("axis stopped, power stage off after "), stop.text
    assert "stop reached the drive " in stop.text, stop.text
    assert stop.text.endswith("0x6041 = 0x0240 SWITCH ON DISABLED)"), stop.text
    assert np.all(np.diff(recording.cycle) > 0) and recording.cycle[-1] >= stop.cycle - 1
    return stop


def _skip_if_host_stalled(reason: str) -> None:
    """Aborted "host stalled N ms": on a loaded machine this process (host, relay and drive
    share it) can be starved that long (`tests/test_late_host.py` allows that end too); the
    stop was checked, the backlog was not: a skip, so the gap shows."""
    if reason.startswith("host stalled "):
        pytest.skip(f"the run ended '{reason}' before the backlog could be judged (stop checked)")
