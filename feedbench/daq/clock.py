"""The bench clock: one tick = one bus cycle (RPDOs out, SYNC, the cycle's TPDOs in).

`LockstepClock` (simulation): the simulated drives step their physics on the SYNC, so
virtual time advances exactly one cycle per tick, as fast as the bus allows; a missing
answer is an error (`BusTimeout`), timed in the time the process ran (`wait_awake`:
a loaded machine or a paused process is not a silent peer). `RealtimeClock` (hardware,
or `feedbench sim` in its own process): SYNC every cycle from python-can's periodic sender
(canopen's `network.sync`: the kernel's broadcast manager on SocketCAN, the adapter where
the interface has it, a thread otherwise), and a tick is the arrival of the next complete
TPDO set: nothing sleeps to a deadline. Each tick's setpoints go out at once and take
effect at the next SYNC. Its per-cycle times (`TIMING_CHANNELS`: setpoints sent, TPDOs
received) are recorded, and the run's missed, repeated and late cycles and lateness follow
from them (`daq.timing`).

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
cheaper (see there). A real-time run's cycles run in `protocols.canbus.frozen_heap()`: no
full garbage collection (≈ 0.1 s without any thread running) in the middle of them.
"""

from __future__ import annotations

import fcntl
import math
import os
import tempfile
import threading
import time
from array import array
from contextlib import AbstractContextManager, contextmanager, nullcontext
from functools import partial
from pathlib import Path
from typing import Callable, Iterator, Protocol, Sequence

import can
import canopen
import numpy as np
from can.broadcastmanager import ThreadBasedCyclicSendTask

from feedbench.daq.timing import TIMING_CHANNELS, TIMING_UNITS, cycle_timing
from feedbench.protocols.canbus import Receive, batched_sends, cycle_reads, frozen_heap
from feedbench.protocols.cia301 import (
    HEARTBEAT_COB_BASE, HEARTBEAT_OPERATIONAL, HOST_NODE_ID, SYNC_COB_ID,
)

COUNTER_MODULO = 0x10000
HEARTBEAT_S = 0.1
"""The host's heartbeat producer time (s), below the drives' consumer time
(`drivers.cia402.HOST_CONSUMER_MS`)."""
HEARTBEAT_CHECK_TICKS = 32
"""Ticks between two checks of the drives' heartbeats."""
HOST_HEARTBEAT = (HEARTBEAT_COB_BASE + HOST_NODE_ID, bytes([HEARTBEAT_OPERATIONAL]))
"""The host's heartbeat frame: COB-ID and payload (NMT state operational)."""


class BusTimeout(RuntimeError):
    """A drive's TPDOs of a cycle did not arrive in time."""


class HostStalled(RuntimeError):
    """The host's cycle loop stopped ticking during a run (real time): SYNC and the host's
    heartbeat were stopped so that the drives' own watchdogs stop the axis."""


class NodeLost(RuntimeError):
    """A drive's heartbeat stopped; the text is the run's abort reason."""


class SyncSender:
    """SYNC every `period_s` from python-can's thread-based periodic sender (the sender
    python-can uses on `virtual`, `socketcand` and every interface without cyclic
    transmission of its own), counted as it goes onto the bus: `sent` SYNCs so far.

    Each SYNC is sent and counted under `lock`; frames sent under it too
    (`RealtimeClock.tick`'s setpoints) come after SYNC `sent` and before SYNC `sent + 1` in
    the one order of the bus (a CAN controller's queue, a socketcand TCP stream), however
    far behind the receiver works through that order: a drive applies them at SYNC
    `sent + 1`, the one they were computed for. A host that counted the drive's TPDO sets
    instead took the next SYNC to be the one after the newest set: with the SYNC thread
    starved and catching up in bursts, or the peer working through a backlog, 20 setpoints
    landed between two SYNCs (the drive took the last: a 175 µm step in one cycle) or none
    between several."""

    def __init__(self, bus: can.BusABC, period_s: float) -> None:
        self.lock = threading.Lock()
        self.sent = 0
        self.period_s = period_s
        self._bus = bus
        self._task: ThreadBasedCyclicSendTask | None = None

    def start(self) -> None:
        """SYNC from now on (the count goes on from where it was)."""
        self._task = ThreadBasedCyclicSendTask(
            self, threading.Lock(), can.Message(arbitration_id=SYNC_COB_ID, data=b"",
                                                is_extended_id=False), self.period_s)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """The periodic sender's send: counted, then on the bus (a TPDO set answering it
        can never be seen before its count)."""
        with self.lock:
            self.sent += 1
            self._bus.send(msg, timeout)

    def stop(self) -> None:
        if self._task is not None:
            self._task.stop()


def counts_syncs(bus: can.BusABC) -> bool:
    """True where python-can would send SYNC from its thread-based periodic sender (the
    `SyncSender` counts them); False where the kernel (SocketCAN's broadcast manager) or the
    adapter sends periodic frames itself (canopen's `network.sync`, SYNCs not counted)."""
    return type(bus)._send_periodic_internal is can.BusABC._send_periodic_internal


class CycleDrive(Protocol):
    """What the clock needs of a drive (`feedbench.drivers.cia402.Cia402Drive`)."""

    node: canopen.RemoteNode

    set_time: float

    @property
    def device_cycle(self) -> int: ...

    def arm_cycle(self) -> None: ...

    def transmit(self) -> None: ...

    def wait_cycle(self, timeout_s: float, receive: Receive | None = None) -> bool: ...

    @property
    def sets_waiting(self) -> int: ...

    def heartbeat_lost(self, now: float) -> bool: ...

    syncs_sent: Callable[[], int]

    set_syncs: int


class _BenchClock:
    """Shared part: SYNC, per-drive unwrapped cycle counters, gap count.

    `channels` / `units`: what the clock adds to each recorded row, `cycle_values` after
    each tick (lockstep: nothing); `timing()`: the cycle timing of the ticks since
    `reset_timing()` as a dict (lockstep: None, virtual time has none)."""

    channels: tuple[str, ...] = ()
    units: dict[str, str] = {}
    cycle_values: tuple[float, ...] = ()
    transmitted = True
    """Whether the last tick sent the setpoints (real time: not when asked not to, or when
    the SYNC they were computed for had gone)."""

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

    def reset_timing(self) -> None:
        """Start counting the cycle timing of a run (nothing to count here)."""

    def timing(self) -> dict | None:
        """The cycle timing since `reset_timing` (None: virtual time)."""
        return None

    def raise_if_stalled(self) -> None:
        """Nothing stalls in lockstep (see `RealtimeClock`)."""

    def behind(self) -> bool:
        """Before a cycle's setpoints: True if TPDO sets of cycles that already ran wait for
        the host (real time; lockstep: never)."""
        return False

    def since_tick_s(self) -> float:
        """Wall time (s) since the last tick ended (lockstep: 0)."""
        return 0.0

    def next_sync(self) -> int | None:
        """The number of the SYNC that setpoints sent now precede (real time where the SYNCs
        are counted, `SyncSender`; None: lockstep, where each tick sends its own, or SYNC
        from the kernel or the adapter)."""
        return None

    def sync_offset_bound(self) -> int | None:
        """See `RealtimeClock` (None: SYNCs not counted)."""
        return None

    def answer_age_s(self) -> float:
        """Wall time (s) since the drives answered the last tick's cycle (lockstep: 0)."""
        return 0.0

    def pace_hz(self) -> float | None:
        """See `RealtimeClock` (None: virtual time)."""
        return None

    def guarded(self) -> AbstractContextManager[None]:
        """While a run's cycles go: what keeps a hung host from holding the drives enabled
        (lockstep: nothing needed, a hung host sends no SYNC)."""
        return nullcontext()

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

    def _start_cycle(self) -> None:
        """Arm the drives, send their RPDOs, then SYNC, in one write where the bus can
        (`batched_sends`: a socketcand connection)."""
        with batched_sends(self.network):
            for drive in self.drives:
                drive.arm_cycle()
                drive.transmit()
            self.network.send_message(SYNC_COB_ID, b"")

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


PACE_TICKS = 200
"""Ticks over which `RealtimeClock.pace_hz` measures the drives' pace."""
FIRST_CYCLE_TIMEOUT_S = 10.0
"""Lockstep: how long the first cycle may wait for its TPDOs (s) at least. A simulated bench's
first cycle is its slowest (kernels its warm-up did not load, the first SYNC of a process):
on a loaded 2-core machine a test run aborted "no TPDOs 1.0 s after SYNC (after device cycle
0)"; the cycles after it keep `timeout_s`, so a peer gone mid-run is still found at once."""


WAIT_SLICE_S = 0.05
"""Lockstep: the wait for a cycle's TPDOs is cut into slices this long (s), each timed
(`wait_awake`)."""


def wait_awake(wait: Callable[[float], bool], timeout_s: float, limit_s: float) -> bool:
    """`wait(slice)` until it returns True or this process has been awake through `timeout_s`
    (s) of waiting: a slice that returns later than asked counts as only what was asked, the
    rest being time in which the process did not run (a loaded machine, the whole process
    stopped) and so neither did an in-process peer. A peer that is slow or gone while the
    process runs still times out after `timeout_s`; `limit_s` (s) of wall time at most."""
    start = time.perf_counter()
    slices = max(1, math.ceil(timeout_s / WAIT_SLICE_S))
    for _ in range(slices):
        if wait(timeout_s / slices):
            return True
        if time.perf_counter() - start >= limit_s:
            return False
    return False


class LockstepClock(_BenchClock):
    """Simulation clock: each tick sends SYNC and waits for every drive's TPDOs of it, reading
    them in the tick's own thread where the bus lets it (`protocols.canbus.cycle_reads`: a
    `feedbench sim` over socketcand)."""

    def __init__(self, network: canopen.Network, drives: Sequence[CycleDrive],
                 timeout_s: float = 0.5, cycle_s: float = 1e-3,
                 heartbeat_s: float = HEARTBEAT_S) -> None:
        super().__init__(network, drives)
        self.timeout_s = timeout_s
        self._beat_every = max(1, round(heartbeat_s / cycle_s))

    def tick(self, transmit: bool = True, sync: int | None = None) -> int:
        """One bus cycle; returns the unwrapped device cycle counter (BusTimeout if silent,
        NodeLost if a drive's heartbeat is). The host's heartbeat goes out before the SYNC
        of every `heartbeat_s / cycle_s`-th tick, the first one included. (`transmit`,
        `sync`: always sent, the real-time clock's arguments.)"""
        if self._ticks % self._beat_every == 0:
            self.network.send_message(*HOST_HEARTBEAT)
        first = self._ticks == 0
        timeout_s = max(self.timeout_s, FIRST_CYCLE_TIMEOUT_S) if first else self.timeout_s
        limit_s = max(timeout_s, FIRST_CYCLE_TIMEOUT_S)
        with cycle_reads(self.network) as receive:
            self._start_cycle()
            for drive in self.drives:
                wait = drive.wait_cycle if receive is None else partial(drive.wait_cycle,
                                                                        receive=receive)
                if not wait_awake(wait, timeout_s, limit_s):
                    raise BusTimeout(f"node {drive.node.id}: no TPDOs {timeout_s} s after "
                                     f"SYNC (after device cycle {self.cycle})")
        self._check_heartbeats()
        return self._count_cycles()


class RealtimeClock(_BenchClock):
    """Hardware clock: SYNC every `period_s` by python-can's periodic sender, ticks paced by
    the drives' TPDO sets.

    A tick sends the setpoints (RPDOs, for the next SYNC) and returns with the next complete
    TPDO set of every drive that the host has not seen yet: at once if it came while the host
    was busy (the sets in between are missed cycles, a gap), else when it arrives.
    `timeout_s`: BusTimeout when a drive sends no new set for this long, and HostStalled
    when the host loop does not tick for this long during a run (`guarded`).
    """

    channels = TIMING_CHANNELS
    units = TIMING_UNITS

    def __init__(self, network: canopen.Network, drives: Sequence[CycleDrive],
                 period_s: float, timeout_s: float = 0.5,
                 heartbeat_s: float = HEARTBEAT_S) -> None:
        super().__init__(network, drives)
        self.period_s = period_s
        self.timeout_s = timeout_s
        self.cycle_values = (float("nan"), float("nan"))
        """(rpdo_time, tpdo_time) of the last tick (s, wall clock; `daq.timing`)."""
        self.heartbeat_s = heartbeat_s
        self._sync = (SyncSender(network.bus, period_s) if counts_syncs(network.bus)
                      else None)
        if self._sync is not None:
            for drive in self.drives:
                drive.syncs_sent = self._syncs_sent
        self._start_senders()
        self._last_tick = time.perf_counter()
        self._stalled = threading.Event()
        self.reset_timing()

    def tick(self, transmit: bool = True, sync: int | None = None) -> int:
        """Setpoints out, then the next unseen TPDO set of each drive; returns the unwrapped
        device cycle (BusTimeout if a drive stays silent, NodeLost if its heartbeat does,
        HostStalled if `guarded` found the host loop stalled). Without `transmit` (the host
        `behind`) nothing goes out: the row's `rpdo_time` is NaN, the cycle ran without the
        host's setpoints (`daq.timing`: repeated). With `sync` (`next_sync` when the
        setpoints were computed) they go out only if they still precede that SYNC, in one
        step with the count (`SyncSender.lock`); else not (`transmitted` False)."""
        self.raise_if_stalled()
        rpdo_time = math.nan
        if transmit:
            with self._sync.lock if self._sync is not None else nullcontext():
                if sync is None or self.next_sync() == sync:
                    rpdo_time = time.time()
                    for drive in self.drives:
                        drive.transmit()
        self.transmitted = not math.isnan(rpdo_time)
        for i, drive in enumerate(self.drives):
            self._wait_new_set(i, drive)
        self._check_heartbeats()
        cycle = self._count_cycles()
        tpdo_time = max(drive.set_time for drive in self.drives)
        self.cycle_values = (rpdo_time, tpdo_time)
        self._cycle_log.append(cycle)
        self._rpdo_log.append(rpdo_time)
        self._tpdo_log.append(tpdo_time)
        self._last_tick = time.perf_counter()
        return cycle

    def _wait_new_set(self, i: int, drive: CycleDrive) -> None:
        """Until drive `i` has a set with a counter the host has not seen (a set that
        completed while the host read the one before repeats it)."""
        deadline = time.perf_counter() + self.timeout_s
        while True:
            if not drive.wait_cycle(max(0.0, deadline - time.perf_counter())):
                raise BusTimeout(f"node {drive.node.id}: no new TPDO set for {self.timeout_s} s "
                                 f"(after device cycle {self.cycles[i]})")
            if drive.device_cycle != self._last_raw[i]:
                return

    def behind(self) -> bool:
        """True if a TPDO set the host has not taken waits: its SYNC ran, and any setpoint
        sent now comes after it (whether the host was away or the sets came in a burst: the
        host sent one setpoint per set it took, so a cycle whose set was still waiting ran
        without one). The runner then takes the waiting sets without sending
        (`Runner._caught_up`). A set still on its way (a receive path behind) is not
        waited for: that would leave the drive without setpoints for as long as the receive
        path stays a cycle behind (measured: 86 and 111 cycles with both CPUs busy); the
        setpoint then comes late, which the drive takes as the stale one it is."""
        return any(drive.sets_waiting for drive in self.drives)

    def since_tick_s(self) -> float:
        """Wall time (s) since the last tick ended."""
        return time.perf_counter() - self._last_tick

    def next_sync(self) -> int | None:
        """The number of the SYNC that setpoints sent now precede: one after those the
        `SyncSender` has put on the bus (None where the kernel or the adapter sends SYNC)."""
        return self._sync.sent + 1 if self._sync is not None else None

    def _syncs_sent(self) -> int:
        return self._sync.sent

    def sync_offset_bound(self) -> int | None:
        """A lower bound of the first drive's cycle counter less the number of the SYNC its
        last set answered: that set cannot answer a SYNC not sent when it came (exact when
        it came before the next SYNC went; None where SYNCs are not counted)."""
        if self._sync is None:
            return None
        return self.cycles[0] - self.drives[0].set_syncs

    def answer_age_s(self) -> float:
        """Wall time (s) since the drives answered the cycle of the last tick (its TPDOs'
        timestamps, on the wall clock as `daq.timing` assumes); more than a cycle: the next
        set is on its way."""
        return time.time() - self.cycle_values[1]

    def pace_hz(self, ticks: int = PACE_TICKS) -> float | None:
        """Drive cycles per second over the last `ticks` ticks, from their TPDO sets' receive
        timestamps (None before two): below 1 / `period_s` the drives, or the path to them,
        work through the host's frames slower than the SYNCs go, and frames sent now wait
        longer than the backlog's cycles of `period_s` (`Runner._sdo_timeout_s`)."""
        n = len(self._cycle_log)
        first = max(0, n - ticks)
        if n < 2 or not self._tpdo_log[n - 1] > self._tpdo_log[first]:
            return None
        return ((self._cycle_log[n - 1] - self._cycle_log[first])
                / (self._tpdo_log[n - 1] - self._tpdo_log[first]))

    def reset_timing(self) -> None:
        """Forget the cycles ticked so far and the TPDO sets queued meanwhile (the host was
        elsewhere, e.g. between plans): the timing of a run starts with the next set."""
        for drive in self.drives:
            drive.arm_cycle()
        self._cycle_log = array("q")
        self._rpdo_log = array("d")
        self._tpdo_log = array("d")

    def timing(self) -> dict:
        """`daq.timing.cycle_timing` of the ticks since `reset_timing`, as a dict."""
        return cycle_timing(np.frombuffer(self._cycle_log, dtype=np.int64),
                            np.frombuffer(self._tpdo_log), np.frombuffer(self._rpdo_log),
                            self.period_s).as_dict()

    def close(self) -> None:
        """Stop SYNC and the host's heartbeat."""
        self._stop_sync()
        self._heartbeat.stop()

    def raise_if_stalled(self) -> None:
        """HostStalled if `guarded` found the host loop stalled (the cause of whatever the
        drives did meanwhile: their SYNC-loss fault)."""
        if self._stalled.is_set():
            raise HostStalled(f"host cycle loop stalled for more than {self.timeout_s:g} s: "
                              "SYNC and heartbeat stopped, the drives' watchdogs stop the axis")

    @contextmanager
    def guarded(self) -> Iterator[None]:
        """SYNC and the heartbeat come from periodic senders that run on whatever the host
        loop does; while a run's cycles go, a thread stops both when no tick came for
        `timeout_s` (a hung host: the drives' SYNC-loss watchdog, 0x2021, then stops the
        axis, and the heartbeat consumer, 0x1016, if SYNC loss is off). The next tick raises
        HostStalled; on exit both run again, for the safe stop."""
        done = threading.Event()
        self._last_tick = time.perf_counter()
        watch = threading.Thread(target=self._watch_ticks, args=(done,), daemon=True,
                                 name="feedbench host stall watchdog")
        watch.start()
        try:
            with frozen_heap():
                yield
        finally:
            done.set()
            watch.join()
            if self._stalled.is_set():
                self._stalled.clear()
                self._start_senders()

    def _start_senders(self) -> None:
        """The host's heartbeat and SYNC, each from python-can's periodic sender."""
        self._heartbeat = self.network.send_periodic(*HOST_HEARTBEAT, self.heartbeat_s)
        if self._sync is not None:
            self._sync.start()
        else:
            self.network.sync.start(self.period_s)

    def _stop_sync(self) -> None:
        if self._sync is not None:
            self._sync.stop()
        else:
            self.network.sync.stop()

    def _watch_ticks(self, done: threading.Event) -> None:
        """Until `done`: stop SYNC and heartbeat once the last tick is `timeout_s` old."""
        while not done.wait(self.timeout_s / 4):
            if time.perf_counter() - self._last_tick > self.timeout_s:
                self._stalled.set()
                self._stop_sync()
                self._heartbeat.stop()
                return


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
