"""A late host never steps the axis (issue 26, item 2): in real time the plan follows the
drive's cycles, not the host's wall clock. A cycle whose setpoint did not come runs on the
target the drive extrapolates (CSP, `protocols.cia402.EXTRAPOLATED_CYCLES`); a host behind
(`RealtimeClock.behind`: TPDO sets of cycles that ran wait) takes those sets as rows without
sending and goes on from where the drive extrapolated to, rejoining the plan
(`Runner._caught_up`). Seen before, with a drive that held its last target and a host that
sent the missed setpoints one per queued set: 8 setpoints within 0.1 ms after a 10 ms stall,
a 50 µm step in one 1 ms cycle, 1034 N, a velocity limit trip; and with both CPUs busy (28
Nov), a drive that extrapolated from targets it had extrapolated itself: steps of 30-47 µm,
then 91, 433 and 3025 µm, and velocity trips in 2 of 3 runs of this test.

A real-time chirp at 500 mm/min against the simulated drive in this process (SYNC from
python-can's periodic sender, as on hardware), its host loop asleep 10, 30 and 100 ms
mid-sweep.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from feedbench.bench import Bench, parse_run_config
from feedbench.daq.catalog import Catalog
from feedbench.daq.recording import open_recording
from feedbench.commands.demo import example_config
from feedbench.protocols.cia402 import EXTRAPOLATED_CYCLES

pytestmark = pytest.mark.realtime
"""Run alone (`make test`'s second step). With two CPU burners beside it (29 Nov) the
setpoint and position steps stay within the bound; what can still fail a run on a machine
that busy is the drive's SYNC-loss watchdog (0x8100: python-can's SYNC thread in this
process starved for more than `bench.sync_loss_ms`, 50 ms)."""

RETURN_FEED_MM_MIN = 1500.0
"""The example chirp's return move, the plan's fastest."""
STALL_AT_BLOCK = 15
"""The stall comes after this many 50-cycle blocks (0.75 s: the chirp's sweep)."""


class StallOnce:
    """An observer whose block callback holds the host's cycle loop `stall_s` once."""

    def __init__(self, stall_s: float) -> None:
        self.stall_s = stall_s
        self.blocks = 0

    def on_start(self, plan, channels) -> None: ...

    def on_segment(self, index, segment, cycle) -> None: ...

    def on_block(self, cycles: np.ndarray, block: np.ndarray) -> None:
        self.blocks += 1
        if self.blocks == STALL_AT_BLOCK:
            time.sleep(self.stall_s)

    def on_stop(self, status: str, reason: str) -> None: ...


def _chirp(channel: str, directory, stall_s: float) -> dict:
    """The example chirp, shortened, in real time against the simulated drive in this
    process, its host loop held `stall_s` once mid-sweep."""
    raw = example_config("chirp")
    raw["bench"].update(channel=channel, output_dir=str(directory), clock="realtime")
    raw["experiment"].update(duration_s=1.0, repetitions=1, settle_s=0.3, tail_s=0.3)
    config = parse_run_config(raw)
    with Bench(config.bench, config.plan, config.experiment.devices()) as bench:
        return bench.run(config, Catalog(directory / "catalog.sqlite"), directory,
                         observers=[StallOnce(stall_s)], progress=False)


@pytest.mark.parametrize("stall_ms", [10, 30, 100])
def test_a_stalled_host_never_steps_the_axis(can_channel, tmp_path, stall_ms):
    """10 and 30 ms: the run completes (or, on a machine that holds the host process longer
    than the drive extrapolates, is aborted "host stalled N ms", N ≥ 50), the stall repeated
    cycles (rows the host took without sending) and a ``timing`` event; 100 ms is
    more than the drive extrapolates (50 cycles): the run is aborted "host stalled N ms".
    Never a limit trip; per drive cycle the setpoint and the position move no more than the
    plan's fastest step."""
    row = _chirp(can_channel, tmp_path, stall_ms * 1e-3)
    recording = open_recording(row["file"])
    if stall_ms < EXTRAPOLATED_CYCLES and _held(row):
        pass  # the machine held the host longer than the drive extrapolates: aborted safely
    elif stall_ms < EXTRAPOLATED_CYCLES:
        assert row["status"] == "complete", row["reason"]
        away_ms = [int(e.text.split("(")[1].split()[0]) for e in recording.events
                   if e.kind == "timing"]
        assert max(away_ms) >= stall_ms, away_ms
        timing = recording.metadata["timing"]
        assert timing["missed"] + timing["repeated"] >= 0.8 * stall_ms, timing
    else:
        assert row["status"] == "aborted"
        assert row["reason"].startswith("host stalled ") and row["reason"].endswith(
            "cycles without a setpoint, the plan cannot resume where it is")
        assert int(row["reason"].split()[2]) >= stall_ms
    largest = RETURN_FEED_MM_MIN / 60e3 * 1e-3  # m per 1 ms cycle: the plan's fastest move
    moving = recording.cycle < _stop_cycle(recording)
    cycles = np.diff(recording.cycle[moving])
    for channel in ("x_ref", "position"):
        per_cycle = np.abs(np.diff(recording.channels[channel][moving])) / cycles
        assert per_cycle.max() <= 1.2 * largest, channel


def _held(row: dict) -> bool:
    """The run was aborted "host stalled N ms" with N at least `EXTRAPOLATED_CYCLES` ms:
    on a busy machine (two CPU burners beside it, load ≈ 10) the host process itself can be
    starved that long, beside the deliberate stall; the issue allows that end."""
    words = row["reason"].split()
    return (row["status"] == "aborted" and row["reason"].startswith("host stalled ")
            and int(words[2]) >= EXTRAPOLATED_CYCLES)


def _stop_cycle(recording) -> int:
    """The cycle the safe stop began (its "disable" segment)."""
    return min(e.cycle for e in recording.events
               if e.kind == "segment" and '"disable"' in e.text)
