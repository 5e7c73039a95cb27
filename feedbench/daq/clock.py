"""The bench clock: one tick = one bus cycle (RPDOs out, SYNC, the cycle's TPDOs in).

`LockstepClock` (simulation): the simulated drives step their physics on the SYNC, so
virtual time advances exactly one cycle per tick, as fast as the bus allows; a missing
answer is an error (`BusTimeout`). `RealtimeClock` (hardware): SYNC at the cycle period on
`time.perf_counter` (sleep, then a short spin), lateness of each SYNC recorded as jitter;
a cycle whose TPDOs miss their slot is counted in `missed` and the run goes on.

Every tick returns the first drive's cycle counter (0x2020, 16 bit), unwrapped to a
monotonic integer; `gaps` counts ticks where a drive's counter did not advance by exactly
one (a SYNC the drive processed without the host seeing its TPDOs, or a lost SYNC).

Heartbeats (CiA 301; docs/canopen.md): the host is a heartbeat producer
(`cia301.HOST_NODE_ID`, every `heartbeat_s`), which the drives consume (their 0x1016 entry,
written by the driver). In lockstep the clock sends it every `heartbeat_s / cycle` ticks
(virtual time, as the drives count it); in real time python-can's periodic sender sends it
on the wall clock (`close()` stops it). The host consumes the drives' heartbeats on the wall
clock: a drive silent for its consumer time raises `NodeLost` ("node N heartbeat lost").

`one_core()` runs a simulated bench's threads on one CPU, which makes lockstep cycles
cheaper (see there).
"""

from __future__ import annotations

import fcntl
import os
import tempfile
import time
from array import array
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Protocol, Sequence

import canopen
import numpy as np

from feedbench.protocols.cia301 import (
    HEARTBEAT_COB_BASE, HEARTBEAT_OPERATIONAL, HOST_NODE_ID, SYNC_COB_ID,
)

COUNTER_MODULO = 0x10000
SPIN_S = 0.5e-3
"""The real-time loop sleeps until this long before the SYNC slot, then spins."""
RESPONSE_SHARE = 0.9
"""The real-time loop waits for TPDOs during this share of the cycle period."""
HEARTBEAT_S = 0.1
"""The host's heartbeat producer time (s), below the drives' consumer time
(`drivers.cia402.HOST_CONSUMER_MS`)."""
HEARTBEAT_CHECK_TICKS = 32
"""Ticks between two checks of the drives' heartbeats."""
HOST_HEARTBEAT = (HEARTBEAT_COB_BASE + HOST_NODE_ID, bytes([HEARTBEAT_OPERATIONAL]))
"""The host's heartbeat frame: COB-ID and payload (NMT state operational)."""


class BusTimeout(RuntimeError):
    """A drive's TPDOs of a cycle did not arrive in time."""


class NodeLost(RuntimeError):
    """A drive's heartbeat stopped; the text is the run's abort reason."""


class CycleDrive(Protocol):
    """What the clock needs of a drive (`feedbench.drivers.cia402.Cia402Drive`)."""

    node: canopen.RemoteNode

    @property
    def device_cycle(self) -> int: ...

    def arm_cycle(self) -> None: ...

    def transmit(self) -> None: ...

    def wait_cycle(self, timeout_s: float) -> bool: ...

    def heartbeat_lost(self, now: float) -> bool: ...


class _BenchClock:
    """Shared part: SYNC, per-drive unwrapped cycle counters, gap count."""

    def __init__(self, network: canopen.Network, drives: Sequence[CycleDrive]) -> None:
        if not drives:
            raise ValueError("the clock needs at least one drive")
        self.network = network
        self.drives = list(drives)
        self.cycles = [0] * len(self.drives)
        """Unwrapped device cycle counter per drive, after the last tick."""
        self.gaps = 0
        self.gap_cycles: list[int] = []
        """First drive's unwrapped cycle at each tick with a gap (any drive)."""
        self._last_raw: list[int | None] = [None] * len(self.drives)
        self._ticks = 0

    def close(self) -> None:
        """Stop what the clock sends on its own (nothing here)."""

    def _check_heartbeats(self) -> None:
        """Every `HEARTBEAT_CHECK_TICKS` ticks: NodeLost if a drive's heartbeat is silent."""
        self._ticks += 1
        if self._ticks % HEARTBEAT_CHECK_TICKS:
            return
        now = time.monotonic()
        for drive in self.drives:
            if drive.heartbeat_lost(now):
                raise NodeLost(f"node {drive.node.id} heartbeat lost")

    @property
    def cycle(self) -> int:
        """The first drive's unwrapped cycle counter after the last tick (0 before any)."""
        return self.cycles[0]

    def _start_cycle(self) -> float:
        """Arm the drives, send their RPDOs, then SYNC; returns the perf_counter time of SYNC."""
        for drive in self.drives:
            drive.arm_cycle()
            drive.transmit()
        sync_time = time.perf_counter()
        self.network.send_message(SYNC_COB_ID, b"")
        return sync_time

    def _count_cycles(self) -> int:
        """Unwrap each drive's 16-bit counter; count the ticks where one skipped or stalled."""
        gap = False
        for i, drive in enumerate(self.drives):
            raw = drive.device_cycle
            last = self._last_raw[i]
            if last is None:
                self.cycles[i] = raw
            else:
                step = (raw - last) % COUNTER_MODULO
                self.cycles[i] += step
                gap = gap or step != 1
            self._last_raw[i] = raw
        if gap:
            self.gaps += 1
            self.gap_cycles.append(self.cycles[0])
        return self.cycles[0]


class LockstepClock(_BenchClock):
    """Simulation clock: each tick sends SYNC and waits for every drive's TPDOs of it."""

    def __init__(self, network: canopen.Network, drives: Sequence[CycleDrive],
                 timeout_s: float = 0.5, cycle_s: float = 1e-3,
                 heartbeat_s: float = HEARTBEAT_S) -> None:
        super().__init__(network, drives)
        self.timeout_s = timeout_s
        self._beat_every = max(1, round(heartbeat_s / cycle_s))

    def tick(self) -> int:
        """One bus cycle; returns the unwrapped device cycle counter (BusTimeout if silent,
        NodeLost if a drive's heartbeat is). The host's heartbeat goes out before the SYNC
        of every `heartbeat_s / cycle_s`-th tick, the first one included."""
        if self._ticks % self._beat_every == 0:
            self.network.send_message(*HOST_HEARTBEAT)
        self._start_cycle()
        for drive in self.drives:
            if not drive.wait_cycle(self.timeout_s):
                raise BusTimeout(f"node {drive.node.id}: no TPDOs {self.timeout_s} s after "
                                 f"SYNC (after device cycle {self.cycle})")
        self._check_heartbeats()
        return self._count_cycles()


class RealtimeClock(_BenchClock):
    """Hardware clock: SYNC every `period_s` on the wall clock, jitter recorded.

    `timeout_s`: BusTimeout when no complete TPDO set arrived for this long.
    """

    def __init__(self, network: canopen.Network, drives: Sequence[CycleDrive],
                 period_s: float, timeout_s: float = 0.5,
                 heartbeat_s: float = HEARTBEAT_S) -> None:
        super().__init__(network, drives)
        self._heartbeat = network.send_periodic(*HOST_HEARTBEAT, heartbeat_s)
        self.period_s = period_s
        self.timeout_s = timeout_s
        self.missed = 0
        """Ticks whose TPDOs did not arrive within their slot."""
        self.overruns = 0
        """SYNC slots skipped because a tick started after its slot had passed."""
        self._lateness = array("d")
        self._next_sync: float | None = None
        self._last_answer = time.perf_counter()

    def tick(self) -> int:
        """Wait for the next SYNC slot, run the cycle, return the unwrapped device cycle."""
        now = time.perf_counter()
        if self._next_sync is None:
            self._next_sync = self._last_answer = now
        elif now > self._next_sync + self.period_s:
            skipped = int((now - self._next_sync) // self.period_s)
            self.overruns += skipped
            self._next_sync += skipped * self.period_s
        slot = self._next_sync
        _sleep_until(slot)
        sent = self._start_cycle()
        self._lateness.append(sent - slot)
        self._next_sync = slot + self.period_s
        answer_by = slot + RESPONSE_SHARE * self.period_s
        if all(drive.wait_cycle(max(0.0, answer_by - time.perf_counter()))
               for drive in self.drives):
            self._last_answer = sent
            self._check_heartbeats()
            return self._count_cycles()
        self.missed += 1
        if sent - self._last_answer > self.timeout_s:
            raise BusTimeout(f"no complete TPDO set for {sent - self._last_answer:.3f} s")
        return self.cycle

    def close(self) -> None:
        """Stop the host's heartbeat."""
        self._heartbeat.stop()

    def jitter_stats(self) -> dict[str, float]:
        """Lateness of the SYNCs behind their slots (µs): mean, max, std; n SYNCs sent.

        The slot starts with the RPDOs, so the mean includes their send time; the std is the
        jitter of the cycle.
        """
        late = np.frombuffer(self._lateness, dtype=float) * 1e6
        if late.size == 0:
            return {"n": 0, "mean_us": float("nan"), "max_us": float("nan"),
                    "std_us": float("nan")}
        return {"n": int(late.size), "mean_us": float(late.mean()), "max_us": float(late.max()),
                "std_us": float(late.std())}


def _sleep_until(deadline: float) -> None:
    """Sleep until SPIN_S before `deadline`, then spin (yielding the GIL) until it."""
    remaining = deadline - time.perf_counter()
    if remaining > SPIN_S:
        time.sleep(remaining - SPIN_S)
    while time.perf_counter() < deadline:
        time.sleep(0)


@contextmanager
def one_core() -> Iterator[int | None]:
    """Run the calling thread, and every thread it starts meanwhile, on one CPU: the one it
    runs on now, unless another simulated bench on this machine holds it (`_claimed_cpu`).
    Restores the thread's CPUs on exit; yields the CPU, or None where nothing changes (not
    Linux, one CPU allowed).

    A lockstep cycle hands the GIL from the host to the device's receive thread to the
    host's receive thread and back, so the threads never run at once; across two cores each
    hand-over is a cross-core wake-up. On one core the quick demo campaign took 98 s instead
    of 161 s (40 % less CPU) with identical results, on this 2-core VM. Two benches at once
    (a campaign's workers, two test workers) each get a CPU of their own: pinned to the same
    one they would share it for the whole run while the other CPU idles.
    """
    cpu = _current_cpu()
    allowed = os.sched_getaffinity(0) if cpu is not None else set()
    if len(allowed) < 2 or cpu not in allowed:
        yield None
        return
    with _claimed_cpu(sorted(allowed, key=lambda candidate: candidate != cpu)) as claimed:
        os.sched_setaffinity(0, {claimed})
        try:
            yield claimed
        finally:
            os.sched_setaffinity(0, allowed)


CPU_LOCKS = Path(tempfile.gettempdir())
"""Where the lock files that mark a CPU as held by a simulated bench live (any process)."""


def _cpu_lock(cpu: int) -> Path:
    """The lock file of `cpu` in `CPU_LOCKS`."""
    return CPU_LOCKS / f"feedbench-cpu-{cpu}.lock"


@contextmanager
def _claimed_cpu(candidates: Sequence[int]) -> Iterator[int]:
    """The first of `candidates` that no other bench holds, held until exit: an exclusive
    `flock` on its lock file, which the kernel releases when the holder exits or dies. The
    first candidate, unclaimed, when every one is held."""
    for cpu in candidates:
        try:
            handle = os.open(_cpu_lock(cpu), os.O_RDONLY | os.O_CREAT, 0o666)
        except OSError:
            continue
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(handle)
            continue
        try:
            yield cpu
        finally:
            os.close(handle)
        return
    yield candidates[0]


def _current_cpu() -> int | None:
    """The CPU the calling thread last ran on (Linux: field 39 of /proc/thread-self/stat)."""
    try:
        with open("/proc/thread-self/stat") as stat:
            return int(stat.read().rsplit(")", 1)[1].split()[36])
    except (OSError, IndexError, ValueError):
        return None
