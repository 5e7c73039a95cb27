"""The runner: executes a plan cycle by cycle, watches limits, stops safely.

Before anything moves the runner reads where the axis stands, turns the plan's relative
trajectory into absolute targets and checks every limit on it. During the run it checks
the measured position, velocity and force every cycle, watches the drive's fault state
and the bus; a trip, a fault, a bus timeout or a stop request (Ctrl-C, the live window's
Stop button) removes the excitation, quick-stops the drive in the next cycle (CiA 402: out
of operation enabled at once, the drive ramps down at its own quick-stop deceleration and
switches off), holds the setpoint and closes the recording as aborted with the reason.
Every sample up to the stop stays on disk.

Safe means stopped: a stop is confirmed by motion, every drive's velocity actual below the
standstill velocity for `StopSettings.standstill_cycles` and its power stage off (the
statusword of the TPDOs, then 0x6041 read by SDO), within a bound computed from the limits
(`_stop_bound`: v_max / the drives' quick-stop deceleration + margin). An axis not stopped
within it is escalated: disable voltage (the power stage off), then safe torque off by a
device that has it; each step is an event in the file and a part of the run's reason.

A bus behind (issue 26, items 1 and 2): in real time where the host counts its SYNCs
(`daq.clock.SyncSender`) it knows, for each TPDO set, how many SYNCs it had sent beyond the
one the set answers (`Runner.backlog`: the drive's cycle counter against the SYNC count,
nothing the drive does not report). Both follow from it:

- the stop's bound counts from the drive cycle that can have the stop (`_stop_due`: the
  SYNC the command precedes, as the drive counts it), not from when the host sent it, and
  likewise for each later command of the stop (`_run_stop`); the cycles between, which the
  drive ran on what was already on its way, are stated: "stop reached the drive N cycles
  after it was sent". Escalating earlier would not help: disable voltage goes the same
  way, behind the same frames; the stop's SDO reads wait for the backlog too
  (`_sdo_timeout_s`). Where the SYNCs are not
  counted (the kernel or the adapter sends them: SocketCAN) the backlog is not measurable
  and the bound counts from the send, as before;
- a run whose backlog exceeds the stop bound is aborted, "bus N cycles behind": its limit
  checks would act on data older than a whole stop takes, and a stop sent then would reach
  the drive only after more than a stop's worth of queued setpoints. Counting from the
  drive alone (without the abort) would leave the host watching the axis hundreds of ms
  late; the abort alone would still blame the drive for a stop that had not reached it.

The safe stop depends on nothing but the bus: a recording that fails (full disk) aborts the
run like any fault, and the stop goes on without it; the file is finalized after the drives
are stopped. If the bus fails during the stop, the host keeps trying for `STOP_RETRY_S`
(stop by SDO and a bus cycle, then NMT stop) and, if no safe state is confirmed,
says so in the run's reason: "drive state unknown".
"""

from __future__ import annotations

import json
import math
import signal
import sys
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Mapping, Protocol, Sequence

import numpy as np

from feedbench.daq.clock import HostStalled, NodeLost
from feedbench.daq.recorder import RecordingError
from feedbench.drivers.cia402 import DISABLED_STATES, Actual
from feedbench.engine.limits import Limits
from feedbench.engine.plan import Plan, Segment
from feedbench.protocols.canbus import StackLog
from feedbench.protocols.cia402 import EXTRAPOLATED_CYCLES
from feedbench.units import MM_PER_MIN

CHANNELS = ("x_ref", "position", "velocity", "force", "force_offset", "velocity_offset",
            "statusword")
UNITS = {"x_ref": "m", "position": "m", "velocity": "m/s", "force": "N", "force_offset": "N",
         "velocity_offset": "m/s", "statusword": ""}
DRIVE_CHANNELS = ("position", "velocity", "force")
MEASURED = slice(Actual._fields.index(DRIVE_CHANNELS[0]),
                 Actual._fields.index(DRIVE_CHANNELS[-1]) + 1)
"""The fields of a drive's `Actual` recorded as DRIVE_CHANNELS, as one slice."""

ENABLE_TIMEOUT_CYCLES = 200
ENABLE_TIMEOUT_S = 2.0
"""At short cycles the enable may take this long (s) rather than ENABLE_TIMEOUT_CYCLES: a
real drive releasing its brake takes a few hundred ms, and a real-time host behind the
drive's TPDO sets sees each state change some cycles late."""
BLOCK_CYCLES = 50
"""Cycles per block handed to observers (live plot, progress); the recorder gets every row."""
STOP_RETRY_S = 5.0
"""How long the host keeps trying to stop the drives after the stop sequence failed (s)."""
SDO_STOP_TIMEOUT_S = 0.3
"""How long each SDO request of the stop waits for its answer (s), plus the time of the bus
backlog measured last (`Runner._sdo_timeout_s`): the answer comes after the frames queued
ahead of it."""


class StopRequest:
    """A safe-stop request shared with whoever may ask for one (Ctrl-C, a Stop button).

    `request` only writes an attribute, so any thread may call it; the runner checks
    `reason` once per cycle.
    """

    def __init__(self) -> None:
        self.reason: str | None = None

    def request(self, reason: str = "stop requested") -> None:
        """Ask the runner to ramp down and stop at its next cycle."""
        if self.reason is None:
            self.reason = reason


class Standstill:
    """Counts the bus cycles in a row in which every drive's |velocity actual| stayed below
    `velocity` (m/s); the axis stands after `cycles` of them. `reached`: it stood once (a
    stop that holds the setpoint goes on from there: one noisy sample above the threshold
    afterwards must not send enable operation again behind the disable operation already
    on its way). A stop counts only cycles in which the drive had its command
    (`Runner._run_stop`), never the queued setpoints' motion before it."""

    def __init__(self, velocity: float, cycles: int) -> None:
        self.velocity = velocity
        self.cycles = cycles
        self.count = 0
        self.reached = False

    def update(self, velocities: Sequence[float]) -> None:
        """One bus cycle's measured velocities (m/s; NaN never stands)."""
        still = all(abs(v) < self.velocity for v in velocities)
        self.count = self.count + 1 if still else 0
        self.reached = self.reached or self.stopped

    @property
    def stopped(self) -> bool:
        return self.count >= self.cycles

    def describe(self) -> str:
        """The rule, for a line: "|v| < 1 mm/min for 10 cycles"."""
        return f"|v| < {self.velocity / MM_PER_MIN:g} mm/min for {self.cycles} cycles"


REJOIN_SHARE = 0.02
"""After the host fell behind (real time), the offset by which the targets rejoin the plan
moves at most about this share of the velocity limit's step per cycle (`Rejoin`)."""
REJOIN_NOTED = 1e-6
"""A catch-up is an event in the file (``timing``) when the host loop was away for at least
half the cycles it missed, or the plan is rejoined from further than this (m); the other
ones (TPDO sets that came in a burst) are counted in the run's timing as repeated cycles."""
REJOIN_HORIZON = 5.0
"""Cycles over which a difference of steps counts as much as a distance when the plan
index to go on from is chosen (`nearest_index`)."""
REJOIN_RATE = 0.1
"""The rejoin's natural frequency at most (rad per cycle): a small offset is gone within
about 60 cycles (at 0.2 the axis overshot the rejoining targets by 5 µm per cycle)."""


class Rejoin:
    """An offset added to the plan's position targets after the host fell behind: it starts
    at `offset` (m) and `rate` (m per cycle; where and at what step the drive extrapolated
    to, less the plan's) and decays to zero as a critically damped second-order system,
    e(t) = (e0 + (r0 + w e0) t) exp(-w t), so the targets go on from where the drive is at
    its speed and reach the plan at a bounded extra speed and acceleration. The natural
    frequency w (per cycle) is chosen so that the offset's own step stays near `bound` (m per
    cycle; the peak of w e0 t exp(-w t) is w e0 / e), at most `REJOIN_RATE`."""

    def __init__(self, offset: float, rate: float, bound: float) -> None:
        self.offset = offset
        self.rate = rate
        self.w = min(REJOIN_RATE, math.e * bound / abs(offset)) if offset else REJOIN_RATE

    def next(self) -> float:
        """This cycle's offset (m); the next one is a cycle on."""
        offset, w = self.offset, self.w
        self.rate -= w * w * offset + 2 * w * self.rate
        self.offset += self.rate
        return offset

    @property
    def done(self) -> bool:
        """The offset and its step are below a nanometre: the plan's targets again."""
        return abs(self.offset) < 1e-9 and abs(self.rate) < 1e-9


HISTORY_KEPT = 4096
"""Targets sent that `SentTargets.at` keeps behind the last one asked about, at least half."""


class SentTargets:
    """The position targets (m) the host sent in real time, as the drive runs on them: the
    last one and its step (what the drive extrapolates from when none comes,
    `protocols.cia402.EXTRAPOLATED_CYCLES` at most), and after the host fell behind the
    `Rejoin` of the plan."""

    def __init__(self, start: float) -> None:
        self.start = start
        self.last = start
        self.step = 0.0
        self.rejoin: Rejoin | None = None
        self.sync: int | None = None
        """The SYNC the last target went out for (`RealtimeClock.next_sync`; None: before
        the plan's first, or SYNCs not counted)."""
        self.due: int | None = None
        """The SYNC the last catch-up (`Runner._caught_up`) planned the next target for."""
        self.index = 0
        """The plan index after the last target sent (a catch-up counts from there)."""
        self.history: list[tuple[int, float, float]] = []
        """(SYNC, target, step) of the targets sent for counted SYNCs, for `at`."""
        self._at = 0

    def next(self, planned: float) -> float:
        """The target to send for the plan's `planned` one (the rejoin's offset added)."""
        if self.rejoin is None:
            return planned
        offset = self.rejoin.next()
        if self.rejoin.done:
            self.rejoin = None
        return planned + offset

    def sent(self, target: float, sync: int | None = None) -> None:
        """`target` went out for the next SYNC (number `sync` where they are counted). Its
        step is the drive's (`protocols.cia402`, `_cyclic_target_of`): the distance from
        the last one if that went out for the SYNC before; after SYNCs without one the
        step the drive extrapolated with stays (0 once it held)."""
        gap = sync - self.sync if sync is not None and self.sync is not None else 1
        if gap == 1:
            self.step = target - self.last
        elif gap > EXTRAPOLATED_CYCLES:
            self.step = 0.0
        self.last = target
        self.sync = sync
        if sync is not None:
            self.history.append((sync, target, self.step))

    def at(self, sync: int) -> float:
        """The target the drive ran at SYNC `sync`: the one sent for it, else the last one
        before it extrapolated (`EXTRAPOLATED_CYCLES` at most); before the first one sent
        the hold at `start`. Asked about nearly in order (the drive's cycles): a cursor
        walks from the last answer; the history before it is dropped now and then."""
        history, k = self.history, self._at
        while k + 1 < len(history) and history[k + 1][0] <= sync:
            k += 1
        while k and history[k][0] > sync:
            k -= 1
        if k > HISTORY_KEPT:
            del history[:k - HISTORY_KEPT // 2]
            k = HISTORY_KEPT // 2
        self._at = k
        if not history or history[k][0] > sync:
            return self.start
        first, target, step = history[k]
        return target + min(sync - first, EXTRAPOLATED_CYCLES) * step

    def behind(self, sync: int | None) -> bool:
        """SYNCs ran, or will before SYNC `sync`, without a setpoint, and no catch-up
        planned for `sync` yet."""
        return self.unsent(sync) > 0 and sync != self.due

    def unsent(self, sync: int | None) -> int:
        """SYNCs that run without a setpoint before SYNC `sync` (the next one): 0 where the
        SYNCs are not counted or before the plan's first target; -1 when the last target
        went out for `sync` itself (no SYNC since)."""
        if sync is None or self.sync is None:
            return 0
        return sync - self.sync - 1

    def extrapolated(self, cycles: int) -> float:
        """The drive's target `cycles` cycles after the last one sent, none sent since."""
        return self.last + min(cycles, EXTRAPOLATED_CYCLES) * self.step


class RunAborted(RuntimeError):
    """Raised inside the cycle loop to leave it; carries the reason recorded in the file."""


class Observer(Protocol):
    """What watches a run (progress printer, live stream): called from the cycle loop."""

    def on_start(self, plan: Plan, channels: Sequence[str]) -> None: ...

    def on_segment(self, index: int, segment: Segment, cycle: int) -> None: ...

    def on_block(self, cycles: np.ndarray, block: np.ndarray) -> None: ...

    def on_stop(self, status: str, reason: str) -> None: ...


class StreamObserver(Observer, Protocol):
    """An observer that also watches what the cycle devices acquire (live window, live
    results): `on_layout` right after `on_start` with every row channel's unit and the
    devices' high-rate streams (name → `StreamSpec`), then `on_stream` with each block a
    device records (bus cycles, sample counters, n × channels samples; not to be modified).
    """

    def on_layout(self, units: Mapping[str, str], streams: Mapping[str, Any]) -> None: ...

    def on_stream(self, name: str, cycles: np.ndarray, sequence: np.ndarray,
                  samples: np.ndarray) -> None: ...


class StreamTap:
    """The recorder as the cycle devices see it: each high-rate block goes to the recorder
    first, unchanged, then to the stream observers; everything else is the recorder's.

    An observer that raises is dropped with a ``fault`` event: a watcher never stops the
    acquisition."""

    def __init__(self, recorder, observers: Sequence[StreamObserver]) -> None:
        self.recorder = recorder
        self.observers = list(observers)

    def append_stream(self, name: str, cycles: np.ndarray, sequence: np.ndarray,
                      samples: np.ndarray) -> None:
        """Record the block, then hand it to every stream observer."""
        self.recorder.append_stream(name, cycles, sequence, samples)
        for obs in list(self.observers):
            try:
                obs.on_stream(name, cycles, sequence, samples)
            except Exception as exc:  # a broken watcher must not abort the measurement
                self.observers.remove(obs)
                self.recorder.event(int(cycles[-1]), "fault", f"{type(obs).__name__} stopped "
                                    f"watching stream {name}: {type(exc).__name__}: {exc}")

    def __getattr__(self, name: str) -> Any:
        return getattr(self.recorder, name)


def devices_recorder(recorder, observers: Sequence[Observer]):
    """What the devices write to: a `StreamTap` if an observer watches streams, else the
    recorder itself."""
    watching = [obs for obs in observers if hasattr(obs, "on_stream")]
    return StreamTap(recorder, watching) if watching else recorder


class CycleDevice(Protocol):
    """A device besides the drive that the runner serves every bus cycle (Modbus, serial DAQ).

    `channels` / `units`: the per-cycle values it adds to each recorded row (`after_sync`);
    `streams`: the high-rate streams it writes with `Recorder.append_stream`, declared before
    the file is created (name → `feedbench.daq.recorder.StreamSpec`). A device raises on its
    first failure (the run aborts) and answers NaN without I/O afterwards, so the safe stop
    of the drive never waits on a broken link.
    """

    channels: tuple[str, ...]
    units: dict[str, str]
    streams: dict

    def start(self, plan: Plan, recorder) -> None: ...

    def before_sync(self, index: int | None) -> None: ...

    def after_sync(self, cycle: int) -> Sequence[float]: ...

    def stop(self, recorder) -> None: ...


@dataclass(frozen=True)
class RunOutcome:
    """How a run ended."""

    status: str
    reason: str
    n_cycles: int
    start_position: float
    timing: dict | None = None
    """Real time: the run's cycle timing (`daq.timing.CycleTiming.as_dict`); else None."""


class Runner:
    """Runs plans on one CiA 402 drive, or on several that move one axis, with a bench clock.

    `drive` is a `feedbench.drivers.cia402.Cia402Drive`, or a mapping name → drive (e.g.
    master and slave of a rack-and-pinion axis): then each drive follows the plan from
    where it stood at `read_position`, every drive is enabled, watched and disabled, and
    the channels are named per drive (`drive_channels`). `clock` is a `LockstepClock` or
    `RealtimeClock` from `feedbench.daq.clock`; the safe stop waits for the drives' own
    quick stop as long as `Cia402Drive.stop_deceleration` takes from the velocity limit
    (`_stop_bound`). `devices` are
    served every cycle: `before_sync(plan index)` before the SYNC (None outside the plan:
    enable, disable, stop), `after_sync` after it (a device that raises there: its
    channels NaN in that cycle's row, which is recorded), their
    values appended to the row; `start` before the enable sequence, `stop` at the end of
    every run (complete or aborted), after the drive is disabled.
    """

    def __init__(self, drive, clock, limits: Limits,
                 observers: Sequence[Observer] = (), stop: StopRequest | None = None,
                 devices: Sequence[CycleDevice] = ()) -> None:
        self.drives = dict(drive) if isinstance(drive, Mapping) else {"": drive}
        self.drive = next(iter(self.drives.values()))
        self.clock = clock
        self.limits = limits
        self.observers = list(observers)
        self.stop = stop or StopRequest()
        self.devices = list(devices)
        own_channels, own_units = drive_channels(tuple(self.drives))
        self.channels = (own_channels + clock.channels
                         + tuple(c for d in self.devices for c in d.channels))
        self.units = {**own_units, **clock.units,
                      **{c: u for d in self.devices for c, u in d.units.items()}}
        self.streams = {name: spec for d in self.devices for name, spec in d.streams.items()}
        self._offsets = [0.0] * len(self.drives)
        self._block = np.zeros((BLOCK_CYCLES, len(self.channels)))
        self._block_cycles = np.zeros(BLOCK_CYCLES, dtype=np.int64)
        self._block_fill = 0
        self._sent: SentTargets | None = None
        """While a plan's cycles go in real time with the SYNCs counted: the targets sent,
        by SYNC (a row's x_ref is the one the drive ran in its cycle)."""
        self._sync_offset: int | None = None
        """The first drive's cycle counter less the number of the SYNC it answered: the
        largest `clock.sync_offset_bound` so far (exact once a set came before the next
        SYNC went; a peer that stays behind by the same backlog throughout hides it)."""
        self.backlog: int | None = None
        """Real time with the SYNCs counted: how many SYNCs the host had sent beyond the one
        the newest TPDO set answers, when that set came (`_sync_offset` less
        `clock.sync_offset_bound`): the bus, the drive and the host's receive path together
        that many cycles behind (None: not measurable, lockstep or SYNC from the kernel or
        the adapter)."""
        self._stop_dt = 0.0
        """The cycle (s) of the stop under way (`_sdo_timeout_s`)."""
        self._backlog_limit: int | None = None
        """From the enable to the plan's end: the backlog (cycles) that aborts the run, the
        stop bound (`_raise_if_behind`)."""
        self.stack_log = StackLog()
        """python-can's and canopen's log lines during a run, recorded as ``log`` events."""

    def read_position(self) -> float:
        """Run one cycle with the drives as they are; the first one's measured position (m).

        Every other drive keeps its offset from it: the plan moves each from where it stands.
        """
        self.clock.tick()
        positions = [d.actual.position for d in self.drives.values()]
        self._offsets = [p - positions[0] for p in positions]
        return positions[0]

    def absolute_targets(self, plan: Plan, start: float) -> np.ndarray:
        """The plan's targets shifted to the start position, checked against the limits."""
        targets = start + plan.concatenated("target_position")
        for offset in self._offsets:
            self.limits.check_trajectory(np.concatenate([[start], targets]) + offset,
                                         plan.cycle_s)
        self.limits.check_excitation(
            np.concatenate([plan.concatenated("force_offset"), plan.concatenated("excitation")]),
            plan.concatenated("velocity_offset"),
        )
        return targets

    def run(self, plan: Plan, recorder, start: float) -> RunOutcome:
        """Enable, execute every segment, disable; the recorder is closed with the status."""
        # Python floats: the cycle loop indexes them and does scalar arithmetic on them,
        # several times faster than on numpy scalars
        targets = self.absolute_targets(plan, start).tolist()
        force_offsets = plan.concatenated("force_offset").tolist()
        velocity_offsets = plan.concatenated("velocity_offset").tolist()
        target_velocities = plan.concatenated("target_velocity").tolist()
        for obs in self.observers:
            obs.on_start(plan, self.channels)
            if hasattr(obs, "on_layout"):
                obs.on_layout(self.units, self.streams)
        device_recorder = devices_recorder(recorder, self.observers)
        status, reason = "complete", ""
        self.clock.reset_timing()
        sent = SentTargets(start)
        i = 0
        with self._interrupts_request_stop(), self.stack_log.capture():
            try:
                for device in self.devices:
                    device.start(plan, device_recorder)
                self._backlog_limit = self._stop_bound(plan.cycle_s)
                self._enable(plan.mode, start, recorder, plan.cycle_s)
                self._sent = sent
                with self.clock.guarded():
                    starts = segment_starts(plan)
                    segment = 0
                    while True:
                        if i < len(targets) and (
                                self.clock.behind() or sent.behind(self.clock.next_sync())):
                            i = self._caught_up(recorder, targets, i, sent, force_offsets,
                                                velocity_offsets, target_velocities,
                                                plan.cycle_s)
                        while segment < len(starts) and starts[segment] <= i:
                            self._segment_started(recorder, plan, segment)
                            segment += 1
                        if i == len(targets):
                            break
                        sync = self.clock.next_sync()
                        if sent.behind(sync):  # SYNCs went meanwhile: caught up for them first
                            continue
                        if sent.unsent(sync) < 0:  # none since the last target: it is out
                            self._cycle(recorder, sent.last, force_offsets[i - 1],
                                        velocity_offsets[i - 1],
                                        velocity=target_velocities[i - 1], transmit=False)
                            continue
                        target = sent.next(targets[i])
                        self._cycle(recorder, target, force_offsets[i],
                                    velocity_offsets[i], index=i,
                                    velocity=target_velocities[i], sync=sync)
                        if self.clock.transmitted:  # else its SYNC went first: caught up
                            sent.sent(target, sync)
                            i += 1
                            sent.index = i
            except (RunAborted, NodeLost, HostStalled) as exc:
                status, reason = "aborted", str(exc)
            except Exception as exc:  # bus timeout, driver error, full disk: still stop safely
                status, reason = "aborted", f"{type(exc).__name__}: {exc}"
            self._sent = None
            self._backlog_limit = None
            quick = status == "aborted"
            if quick:
                self._note(recorder, "abort", reason)
            escalated = self._safe_stop(recorder, sent.last, plan.cycle_s, quick)
            if escalated:
                status, reason = "aborted", f"{reason}; {escalated}" if reason else escalated
            self._stop_devices(device_recorder)
            self._record_stack_log(recorder)
        self._flush_block()
        timing = self.clock.timing()
        status, reason = _finalize(recorder, status, reason, {"timing": timing} if timing else {})
        for obs in self.observers:
            obs.on_stop(status, reason)
        return RunOutcome(status, reason, i, start, timing)

    def _segment_started(self, recorder, plan: Plan, index: int) -> None:
        """The event and the observers' call of segment `index` starting at the next cycle."""
        segment = plan.segments[index]
        recorder.event(self._next_cycle(), "segment", segment_text(segment))
        for obs in self.observers:
            obs.on_segment(index, segment, self._next_cycle())

    def _caught_up(self, recorder, targets: list[float], i: int, sent: SentTargets,
                   force_offsets: list[float], velocity_offsets: list[float],
                   velocities: list[float], cycle_s: float) -> int:
        """The host is behind (real time, `clock.behind`): the TPDO sets of cycles that ran
        without its setpoints wait. Each becomes a row without sending anything (the drive
        ran it on the target it extrapolates from the last two, `EXTRAPOLATED_CYCLES` at
        most, then held: `SentTargets.extrapolated`, recorded as x_ref; the offsets it last
        got); a host loop that was away also waits for the sets of its absence still on
        their way (at most one per cycle it was away, and only while the last one taken is
        more than a cycle old). Then the plan goes on from where and at the step the drive
        extrapolated to: at the plan index nearest that target within the cycles missed
        either side of the one the drive's cycle count gives (`nearest_index`: an
        accelerating plan waits for a drive that extrapolated too slowly instead of being
        caught up at more than its own speed, a standing one starts where it was; the
        commands of skipped indices served), the rest rejoined by a decaying offset
        (`Rejoin`) instead of a step (behind before the plan's first target: the plan starts
        after those rows). A drive that had to hold its target further from the plan than
        the velocity limit allows in one cycle: "host stalled N ms". Returns the plan index
        to send next.

        The cycles the drive ran without a setpoint are the SYNCs sent since the last one
        went out (`RealtimeClock.next_sync`, counted as they go onto the bus), not the TPDO
        sets taken: a peer working through a backlog of the host's frames (`feedbench sim`'s
        hub up to ≈ 30 ms behind under load) answers SYNCs long after they were sent, and a
        starved SYNC thread sends them in bursts. Where SYNCs are not counted (the kernel or
        the adapter sends them), the sets taken say (a drive takes a setpoint late on the
        wire as the stale one it is).

        Sending the missed setpoints one per waiting set instead (before) put several of
        them between two SYNCs; the drive took the last, and stepped."""
        since_s = self.clock.since_tick_s()
        first = self.clock.cycle
        force, velocity_offset, velocity = ((force_offsets[i - 1], velocity_offsets[i - 1],
                                             velocities[i - 1]) if i else (0.0, 0.0, 0.0))
        away = int(since_s / cycle_s)
        rows = 0
        while self.clock.behind() or (rows < away and self.clock.answer_age_s() > cycle_s):
            since_s = max(since_s, self.clock.since_tick_s())  # an observer may hold a row
            away = int(since_s / cycle_s)
            rows += 1
            self._cycle(recorder, sent.extrapolated(rows), force, velocity_offset,
                        velocity=velocity, transmit=False)
        if not i:  # cycles of the hold before the plan: it starts now
            return 0
        sync = self.clock.next_sync()
        if sync is None or sent.sync is None:  # SYNCs not counted: the sets taken say
            late = self.clock.cycle - first
        else:  # the SYNCs that went without a setpoint, whatever the TPDO sets say
            late = sent.unsent(sync)
            if late <= 0 or sync == sent.due:  # none, or planned already: the plan goes on
                return i
            sent.due, i = sync, sent.index  # from the last one sent (again if it raced one)
        resume = min(i + late, len(targets))
        drive_at = sent.extrapolated(late + 1)
        drive_step = drive_at - sent.extrapolated(late)
        if sync is None or sent.sync is None:  # the next one's step counts from here
            sent.last, sent.step = sent.extrapolated(late), drive_step
        if resume == len(targets):
            return resume
        too_far = self.limits.velocity * cycle_s
        if late + 1 > EXTRAPOLATED_CYCLES and abs(drive_at - targets[resume]) > too_far:
            stalled_ms = max(since_s, late * cycle_s) * 1e3  # away, or starved of its sets
            raise HostStalled(f"host stalled {stalled_ms:.0f} ms: the drive ran {late} "
                              "cycles without a setpoint, the plan cannot resume where it is")
        resume = nearest_index(targets, drive_at, drive_step, i, resume, resume + late)
        for index in range(i, resume):  # the skipped commands, the last of each kind wins
            for device in self.devices:
                device.before_sync(index)
        offset = drive_at - targets[resume]
        planned_step = targets[resume] - targets[resume - 1] if resume else 0.0
        sent.rejoin = Rejoin(offset, drive_step - planned_step,
                             REJOIN_SHARE * self.limits.velocity * cycle_s)
        if late > 1 and (since_s > late * cycle_s / 2 or abs(offset) > REJOIN_NOTED):
            self._note(recorder, "timing", f"host late by {late} drive cycles "
                       f"({since_s * 1e3:.0f} ms): the plan goes on where the drive is, "
                       f"{offset * 1e6:+.1f} µm from it, rejoining it")
        return resume

    def _next_cycle(self) -> int:
        return self.clock.cycle + 1

    def _cycle(self, recorder, target: float, force_offset: float, velocity_offset: float,
               watch: bool = True, index: int | None = None, velocity: float = 0.0,
               transmit: bool = True, sync: int | None = None) -> None:
        """One bus cycle: setpoints out, SYNC, actual values in, limits, record.

        `velocity` is the target velocity (CSV; CSP follows `target` and ignores it); without
        `transmit` (real time, the host behind) nothing is sent, the row records the cycle
        of the next waiting TPDO set; with `sync` (real time, SYNCs counted) the setpoints
        go out only if they still precede that SYNC (`clock.transmitted`).
        Runs once per bus cycle beside the bus stack's own work: kept to list operations."""
        for drive, offset in zip(self.drives.values(), self._offsets):
            drive.set_targets(position=target + offset, velocity=velocity,
                              force_offset=force_offset, velocity_offset=velocity_offset)
        for device in self.devices:
            device.before_sync(index)
        cycle = self.clock.tick(transmit, sync)
        actual = [drive.actual for drive in self.drives.values()]
        row = [target]
        bound = self.clock.sync_offset_bound()
        if bound is not None:  # real time: x_ref the target of the drive's cycle
            if self._sync_offset is None or bound > self._sync_offset:
                self._sync_offset = bound
            self.backlog = self._sync_offset - bound
            if self._sent is not None:
                row[0] = self._sent.at(cycle - self._sync_offset)
        for a in actual:
            row += a[MEASURED]
        row += (force_offset, velocity_offset)
        row += [a.statusword for a in actual]
        row += self.clock.cycle_values
        try:
            for device in self.devices:
                row += device.after_sync(cycle)
        except Exception:  # the drives' values of this cycle are kept; the devices' NaN
            recorder.append(cycle, row + [math.nan] * (len(self.channels) - len(row)))
            raise
        recorder.append(cycle, row)
        if self.stack_log.lines:
            self._record_stack_log(recorder)
        if self.observers:
            self._to_block(cycle, row)
        if not watch:
            self._raise_if_behind(cycle, bound)  # the enable: a drive enabled on stale data
            return
        self.clock.raise_if_stalled()  # an observer that held the loop: the cause comes first
        if self.stop.reason is not None:
            raise RunAborted(self.stop.reason)
        for (name, drive), a in zip(self.drives.items(), actual):
            self._watch(name, drive, a)
        self._raise_if_behind(cycle, bound)  # a fault or trip seen comes first

    def _raise_if_behind(self, cycle: int, bound: int | None) -> None:
        """From the enable to the plan's end (`_backlog_limit`, the stop bound): abort when
        the backlog (`backlog`) exceeds it, "bus N cycles behind"; `bound` is this cycle's
        `clock.sync_offset_bound`."""
        if self._backlog_limit is not None and self.backlog is not None \
                and bound is not None and self.backlog > self._backlog_limit:
            raise RunAborted(f"bus {self.backlog} cycles behind (the TPDO set of SYNC "
                             f"{cycle - self._sync_offset} came after SYNC {cycle - bound}): "
                             "the limits would act on data older than a stop takes "
                             f"({self._backlog_limit} cycles)")

    def _watch(self, name: str, drive, a) -> None:
        """Abort on a drive fault or a limit trip (the drive's name in the reason)."""
        if drive.fault:
            raise RunAborted(f"{_where(name)}drive fault (EMCY 0x{drive.emcy_code or 0:04X})")
        trip = self.limits.violation(a.position, a.velocity, a.force)
        if trip:
            raise RunAborted(f"limit tripped: {_where(name)}{trip}")

    def _to_block(self, cycle: int, row: list[float]) -> None:
        self._block[self._block_fill] = row
        self._block_cycles[self._block_fill] = cycle
        self._block_fill += 1
        if self._block_fill == BLOCK_CYCLES:
            self._flush_block()

    def _flush_block(self) -> None:
        if self._block_fill and self.observers:
            cycles = self._block_cycles[: self._block_fill].copy()
            block = self._block[: self._block_fill].copy()
            for obs in self.observers:
                obs.on_block(cycles, block)
        self._block_fill = 0

    def _enable(self, mode: int, hold: float, recorder, cycle_s: float) -> None:
        """Walk the CiA 402 state machine to operation enabled, one controlword per cycle
        (`cycle_s`, s), for ENABLE_TIMEOUT_CYCLES or ENABLE_TIMEOUT_S, whichever is longer."""
        recorder.event(self._next_cycle(), "segment", segment_text(None, "enable"))
        for drive in self.drives.values():
            drive.set_mode(mode)
        for _ in range(max(ENABLE_TIMEOUT_CYCLES, math.ceil(ENABLE_TIMEOUT_S / cycle_s))):
            if all([drive.enable_step() for drive in self.drives.values()]):
                return
            self._cycle(recorder, hold, 0.0, 0.0, watch=False)
        states = ", ".join(drive.state for drive in self.drives.values())
        raise RunAborted(f"drive did not reach operation enabled (state {states})")

    def _safe_stop(self, recorder, x: float, dt: float, quick: bool) -> str:
        """Stop the drives with the setpoint held at `x` (m) and the excitation off, the stop
        confirmed by motion (`_stop_by_motion`); if the controlword sequence fails,
        `_stop_by_sdo`. Returns "" for a stop as planned, else the line the run's reason
        gets: how the stop was escalated, or that the drive state is unknown."""
        bound = self._stop_bound(dt)
        self._stop_dt = dt
        try:
            return self._stop_by_motion(recorder, x, bound, dt, quick)
        except Exception as exc:  # the bus may be gone: record why the stop ended early
            why = f"{type(exc).__name__}: {exc}"
        self._note(recorder, "fault", f"safe stop incomplete: {why}")
        unknown, motion = self._stop_by_sdo(why, bound * dt)
        self._note(recorder, "fault", unknown or "drives in a safe state by SDO quick stop "
                   f"(power stage off; {motion} when last read)")
        return unknown

    def _stop_bound(self, dt: float) -> int:
        """Bus cycles (of `dt` s) a stop may take: from the velocity limit at the slowest
        drive's quick-stop deceleration, plus `StopSettings.margin` and the standstill cycles;
        counted from the cycle the drive can have the stop (`_stop_due`). Also the largest
        bus backlog a plan runs with (`backlog`): more, and the limits act on data older
        than a stop takes (the run is aborted "bus N cycles behind")."""
        settings = self.drive.stop_settings
        deceleration = min(drive.stop_deceleration for drive in self.drives.values())
        return (math.ceil((self.limits.velocity / deceleration + settings.margin) / dt)
                + settings.standstill_cycles)

    def _stop_by_motion(self, recorder, hold: float, bound: int, dt: float, quick: bool) -> str:
        """The controlword sequence (`_run_stop`) until every drive is de-energised and the
        axis stood still for `StopSettings.standstill_cycles`, within `bound` cycles of `dt`
        (s) while the drive has the stop's commands (`_run_stop`); then 0x6041 read by SDO.
        Not stopped within the bound: escalate (`_escalate`)."""
        settings = self.drive.stop_settings
        standstill = Standstill(settings.standstill_velocity, settings.standstill_cycles)
        self._note(recorder, "segment", segment_text(None, "disable"))
        cycles, transit = self._run_stop(
            recorder, hold, bound, standstill,
            lambda drive: drive.disable_step(not quick, standstill.stopped if quick
                                              else standstill.reached))
        if cycles is None:
            return self._escalate(recorder, hold, bound, dt, standstill, transit)
        self._note(recorder, "stop", f"axis stopped, power stage off after {cycles} cycles "
                   f"({_reached(transit)}{standstill.describe()}; {self._confirm_off()})")
        return ""

    def _stop_due(self) -> int | None:
        """The drive cycle from which a command sent now is in effect: the SYNC it precedes
        (`clock.next_sync`) as the drive counts it (`_sync_offset`); None where not known
        (lockstep: the next cycle; SYNC from the kernel or the adapter). The offset is a
        lower bound: the cycle is never later than the true one, so the stop's bound never
        starts late."""
        sync = self.clock.next_sync()
        if sync is None or self._sync_offset is None:
            return None
        return sync + self._sync_offset

    def _escalate(self, recorder, hold: float, bound: int, dt: float,
                  standstill: Standstill, transit: Sequence[int] = ()) -> str:
        """The stop did not end within `bound` cycles of `dt` (s) counted while the drive had
        its commands (`transit`: per command, the cycles before; `_run_stop`): disable
        voltage, then safe torque off by every device that has it, and `bound` cycles more
        (counted the same way) for the axis to stand; each step an event and a part of the
        returned line."""
        late = f"not stopped within {bound * dt:.3g} s"
        if transit:
            late += f" of reaching the drive {_transit(transit)}"
        steps = [f"{late} ({self._motion()}): disable voltage"]
        self._note(recorder, "fault", f"safe stop: {steps[0]}")
        for drive in self.drives.values():
            drive.disable_voltage()
        for device in self.devices:
            if hasattr(device, "safe_torque_off"):
                steps.append(f"safe torque off by {device.safe_torque_off()}")
                self._note(recorder, "fault", f"safe stop: {steps[-1]}")
        cycles, transit = self._run_stop(recorder, hold, bound, standstill,
                                         lambda drive: drive.disable_step(stopped=True))
        if not all(drive.state in DISABLED_STATES for drive in self.drives.values()):
            raise RuntimeError(f"not disabled by the controlword sequence ({self._motion()})")
        if cycles is None:
            steps.append(f"axis still moving ({self._motion()})")
        else:
            steps.append(f"axis stopped after {cycles} more cycles "
                         f"({_reached(transit)}{self._confirm_off()})")
        self._note(recorder, "fault", f"safe stop: {steps[-1]}")
        return "; ".join(steps)

    def _run_stop(self, recorder, hold: float, cycles: int, standstill: Standstill,
                  step: Callable[[Any], bool]) -> tuple[int | None, list[int]]:
        """Up to `cycles` bus cycles of `step(drive)` (True: de-energised) with the setpoint
        held at `hold`, each counted only once the drive can have the controlwords last sent
        (`_stop_due` of each new command: the cycles before it the drive ran on what was
        already on its way, as many as the backlog when the command went, known then; each
        state change the host waits for costs the way there and back). Returns the cycles
        counted until every drive was de-energised and `standstill` confirmed (else None)
        and, per command, the cycles before the drive could have it (empty where not
        measurable); the cycles in transit count too beyond `TRANSIT_ALLOWANCE` bounds."""
        drives = self.drives.values()
        n = 0
        transit: list[int] = []
        due = words = None
        while n < cycles and n + sum(transit) < (1 + TRANSIT_ALLOWANCE) * cycles:
            if all([step(drive) for drive in drives]) and standstill.stopped:
                return n, transit
            sent = tuple(drive.controlword for drive in drives)
            if sent != words:  # a new command: in effect from the SYNC it precedes
                words, due = sent, self._stop_due()
                if due is not None:
                    transit.append(0)
            self._stop_cycle(recorder, hold)
            if due is not None and self.clock.cycle < due:  # the drive runs what came before
                transit[-1] += 1
            else:  # the axis as the drive moves it with the command: standstill counts
                standstill.update([drive.actual.velocity for drive in drives])
                n += 1
        return None, transit

    def _motion(self) -> str:
        """Each drive's state and |velocity actual| (mm/min), for a line."""
        return ", ".join(f"{_where(name)}{drive.state} at "
                         f"{abs(drive.actual.velocity) / MM_PER_MIN:.3g} mm/min"
                         for name, drive in self.drives.items())

    def _confirm_off(self) -> str:
        """Each drive's statusword read by SDO: "0x6041 = 0x0250 SWITCH ON DISABLED"; raises
        if one is not de-energised."""
        words = []
        for name, drive in self.drives.items():
            word, state = drive.state_by_sdo(self._sdo_timeout_s())
            if state not in DISABLED_STATES:
                raise RuntimeError(f"{_where(name)}0x6041 = 0x{word:04X}: {state}")
            words.append(f"{_where(name)}0x6041 = 0x{word:04X} {state}")
        return ", ".join(words)

    def _sdo_timeout_s(self) -> float:
        """`SDO_STOP_TIMEOUT_S` plus the time the bus backlog measured last takes: its cycles
        at the pace the drive works through them (`clock.pace_hz`; at most one per cycle
        of the stop). Against `feedbench sim` under full load 7 of 10 stops had their 0x6041
        read time out at 0.3 s + the backlog's cycles of 1 ms: the hub fell further behind
        while the request waited. At most a sixth of `STOP_RETRY_S`: canopen tries each
        request twice, and the SDO stop must keep time for its disable voltage."""
        pace = self.clock.pace_hz()
        per_cycle = self._stop_dt if not pace else max(self._stop_dt, 1.0 / pace)
        return min(SDO_STOP_TIMEOUT_S + (self.backlog or 0) * per_cycle, STOP_RETRY_S / 6)

    def _stop_by_sdo(self, why: str, bound_s: float) -> tuple[str, str]:
        """A stop by SDO to every drive (`Cia402Drive.stop_by_sdo`: quick stop while it
        moves, disable voltage once it stands or after `bound_s` (s) counted from when the
        first request can reach the drive behind the bus backlog (`_sdo_timeout_s`),
        escalated) and a bus cycle, again until each is de-energised, for at most
        `STOP_RETRY_S`; else NMT stop.
        Returns ("", the states and velocities last read) once confirmed, else ("drive state
        unknown (…)" with the last answer or error, ""). A bus that fails the PDOs may lose
        the SYNCs too: standstill over cycles is the PDO stop's to confirm."""
        start = time.monotonic()
        last = why
        standstill = self.drive.stop_settings.standstill_velocity
        behind_s = self._sdo_timeout_s() - SDO_STOP_TIMEOUT_S  # 0 where no backlog is known
        while time.monotonic() < start + STOP_RETRY_S:
            escalate = time.monotonic() > start + behind_s + bound_s
            try:
                reads = [d.stop_by_sdo(self._sdo_timeout_s(), standstill, escalate)
                         for d in self.drives.values()]
                last = ", ".join(f"{_where(name)}{state} at {abs(v) / MM_PER_MIN:.3g} mm/min"
                                 for name, (state, v) in zip(self.drives, reads))
                if all(state in DISABLED_STATES for state, _ in reads):
                    return "", last
                self.clock.tick()  # a drive that acts on the SYNC (lockstep) acts now
            except Exception as exc:  # no answer (yet): a hung peer may come back
                last = f"{type(exc).__name__}: {exc}"
                time.sleep(SDO_STOP_TIMEOUT_S / 3)
        for drive in self.drives.values():
            try:
                drive.nmt_stop()
            except Exception as exc:  # the bus is gone: nothing more the host can send
                last = f"{last}; NMT stop not sent: {type(exc).__name__}"
        return (f"drive state unknown: no safe state confirmed within {STOP_RETRY_S:g} s "
                f"({' '.join(last.split())})"), ""

    def _stop_cycle(self, recorder, x: float, velocity: float = 0.0) -> None:
        """One cycle of the stop (setpoint `x` m, `velocity` m/s, no excitation): a
        recording failure, raised once, does not end the stop (the cycle has run)."""
        try:
            self._cycle(recorder, x, 0.0, 0.0, watch=False, velocity=velocity)
        except RecordingError:  # kept in the recorder's `failure`
            pass

    def _record_stack_log(self, recorder) -> None:
        """python-can's and canopen's log lines since the last call as ``log`` events."""
        for line in self.stack_log.take():
            self._note(recorder, "log", line)

    def _note(self, recorder, kind: str, text: str) -> None:
        """An event at the next cycle; a recording failure does not stop the caller."""
        try:
            recorder.event(self._next_cycle(), kind, text)
        except RecordingError:  # kept in the recorder's `failure`
            pass

    def _stop_devices(self, recorder) -> None:
        """Every device's `stop` (spindle off, stream drained); a failure is recorded."""
        for device in self.devices:
            try:
                device.stop(recorder)
            except Exception as exc:  # the link may be gone: the run still closes its file
                self._note(recorder, "fault", f"{type(device).__name__} stop failed: {exc}")

    @contextmanager
    def _interrupts_request_stop(self) -> Iterator[None]:
        """While running, Ctrl-C (SIGINT) and SIGTERM ask for a safe stop instead of killing."""
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        def handler(signum: int, frame: object) -> None:
            self.stop.request(f"interrupted by {signal.Signals(signum).name}")

        previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            yield
        finally:
            for s, h in previous.items():
                signal.signal(s, h)


def _finalize(recorder, status: str, reason: str,
              attrs: Mapping[str, Any]) -> tuple[str, str]:
    """Close the recording with the run's status and `attrs` (the cycle timing), after the
    drives are stopped; returns the status and reason of the run (`Recorder.close`: a
    failed recording is aborted; a file whose status cannot be written says so in the
    reason)."""
    try:
        return recorder.close(status, reason, attrs)
    except RecordingError as exc:
        return "aborted", f"{reason}; {exc}" if reason else str(exc)


TRANSIT_ALLOWANCE = 3
"""Stop bounds that a stop's commands may spend on their way to the drive in all, one per
command of a complete run's stop (hold, disable operation, disable voltage); beyond it the
cycles count whatever is in transit: a command that keeps changing (a standstill check
flickering at its threshold restarts the transit each time) cannot put the stop off
without end."""


def _reached(transit: Sequence[int]) -> str:
    """Where measured (`Runner._run_stop`): "stop reached the drive `_transit`; "."""
    return f"stop reached the drive {_transit(transit)}; " if transit else ""


def _transit(transit: Sequence[int]) -> str:
    """"N cycles after it was sent", with ", commands on their way M cycles in all" where
    later commands waited too (each after a state change the host saw: a way there and
    back)."""
    text = f"{transit[0]} cycles after it was sent"
    if sum(transit) > transit[0]:
        text += f", commands on their way {sum(transit)} cycles in all"
    return text


def drive_channels(names: Sequence[str]) -> tuple[tuple[str, ...], dict[str, str]]:
    """The runner's own channels and units for drives `names` ("" alone: `CHANNELS`).

    Several drives: x_ref, each drive's position, velocity, force as ``name.position``…,
    the offsets, each drive's ``name.statusword``.
    """
    if tuple(names) == ("",):
        return CHANNELS, dict(UNITS)
    measured = tuple(f"{n}.{c}" for n in names for c in DRIVE_CHANNELS)
    status = tuple(f"{n}.statusword" for n in names)
    channels = ("x_ref", *measured, "force_offset", "velocity_offset", *status)
    units = {c: UNITS[c.rsplit(".", 1)[-1]] for c in channels}
    return channels, units


def _where(name: str) -> str:
    """Prefix naming a drive in an abort reason ("" for the only drive)."""
    return f"{name}: " if name else ""


def nearest_index(targets: Sequence[float], x: float, step: float, first: int, due: int,
                  last: int) -> int:
    """The index in `first`…`last` (clipped to `targets`) whose target is nearest `x` moving
    by `step` per cycle: the distance plus `REJOIN_HORIZON` cycles of the difference of the
    steps (so a plan that turns back is not joined on its way back); of equally near ones
    the one nearest `due`."""
    last = min(last, len(targets) - 1)

    def cost(j: int) -> tuple[float, int]:
        planned = targets[j] - targets[j - 1] if j else 0.0
        return abs(targets[j] - x) + REJOIN_HORIZON * abs(planned - step), abs(j - due)

    return min(range(first, last + 1), key=cost)


def segment_starts(plan: Plan) -> list[int]:
    """The plan index each segment starts at."""
    starts, start = [], 0
    for segment in plan.segments:
        starts.append(start)
        start += segment.n_cycles
    return starts


def segment_text(segment: Segment | None, label: str = "") -> str:
    """Event text of a segment start: JSON with label, kind, the segment's info and, if it
    has any, its commands under ``commands`` (read back by `plan.segment_event`)."""
    if segment is None:
        return json.dumps({"label": label, "kind": label})
    commands = {"commands": segment.commands} if segment.commands else {}
    return json.dumps({"label": segment.label, "kind": segment.kind, **segment.info, **commands})


class ProgressPrinter:
    """Prints one line per wall second to stderr: segment, percent done, bench time left."""

    def __init__(self, stream=sys.stderr, every_s: float = 1.0) -> None:
        self.stream = stream
        self.every_s = every_s
        self._label = ""
        self._done = 0
        self._total = 1
        self._cycle_s = 1e-3
        self._last = 0.0

    def on_start(self, plan: Plan, channels: Sequence[str]) -> None:
        self._total = max(plan.n_cycles, 1)
        self._cycle_s = plan.cycle_s
        self._last = time.monotonic()
        print(f"{plan.experiment}: {plan.n_cycles} cycles ({plan.duration_s:.1f} s bench time)",
              file=self.stream)

    def on_segment(self, index: int, segment: Segment, cycle: int) -> None:
        self._label = segment.label

    def on_block(self, cycles: np.ndarray, block: np.ndarray) -> None:
        self._done += len(cycles)
        now = time.monotonic()
        if now - self._last >= self.every_s:
            self._last = now
            left = max(self._total - self._done, 0) * self._cycle_s
            pct = 100.0 * min(self._done / self._total, 1.0)
            print(f"  {pct:5.1f} %  {self._label:<32s} {left:6.1f} s left", file=self.stream)

    def on_stop(self, status: str, reason: str) -> None:
        print(f"  {status}{': ' + reason if reason else ''}", file=self.stream)
