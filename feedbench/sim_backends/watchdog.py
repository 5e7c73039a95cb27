"""The watchdogs of a simulated CANopen node: heartbeat consumer (0x1016) and SYNC loss
(communication cycle period 0x1006 × missed SYNCs 0x2021), shared by the simulated drives
and the CiA 401 I/O module; and the sub-index check every simulated SDO server makes.

Two time bases (docs/canopen.md). At each SYNC a consumed heartbeat's age is counted in
virtual time: SYNCs since the heartbeat × the cycle period (lockstep: the host produces its
heartbeat every so many cycles, so a run is deterministic; real time: SYNC count × period is
the wall clock). Between SYNCs nothing in lockstep counts, so a dead host would never be
noticed there: a thread watches the wall clock too, while the node `guards` something (a
powered drive, outputs set): a producer silent (neither its heartbeat nor a SYNC) for its
consumer time is lost, and SYNC is lost after 0x2021 periods without one. A lockstep host
that is alive sends SYNCs far more often than any consumer time, and between plans the
drive is disabled, so the wall clock never stops a live lockstep run. After a loss the
node may need cycles without SYNC (a drive's fault reaction ramps down): `free_run` is
called once per cycle period on the wall clock while `needs_cycles()` and SYNC is gone
(the wall clock found the loss, or no SYNC for `SILENT_S`); a live host's SYNCs run them
otherwise, so a loss in virtual time stays deterministic.
The thread starts when the first entry or SYNC limit is set (a node nobody told to watch
costs nothing) and ends with `close()` or when its network is disconnected.
"""

from __future__ import annotations

import threading
import time
from typing import Callable

import canopen
from canopen.objectdictionary import ODVariable
from canopen.sdo import SdoAbortedError

from feedbench.protocols import cia301

POLL_S = 0.02
"""Wall-clock period of the watchdog thread's checks."""
SILENT_S = 0.1
"""No SYNC for this long (s) while the node needs cycles: it runs them itself."""

Loss = tuple[int, str]
"""(EMCY code, reason) of a detected loss."""


def check_subindex(subindex: int, od: ODVariable) -> None:
    """Abort 0x06090011 for a sub-index a plain variable does not have (canopen's SDO
    server ignores the sub-index of a VAR)."""
    if subindex != od.subindex:
        raise SdoAbortedError(cia301.SDO_ABORT_NO_SUBINDEX)


def check_range(od: ODVariable, value: int | float) -> None:
    """Abort 0x06090031 / 0x06090032 for a value above the object's HighLimit / below its
    LowLimit (canopen's SDO server does not check them)."""
    if od.max is not None and value > od.max:
        raise SdoAbortedError(cia301.SDO_ABORT_VALUE_TOO_HIGH)
    if od.min is not None and value < od.min:
        raise SdoAbortedError(cia301.SDO_ABORT_VALUE_TOO_LOW)


class Watchdog:
    """Heartbeat consumer and SYNC-loss monitor of one node on `network`.

    `lock` serialises the node's cycle with this thread; `on_loss(code, reason)` is the
    node's reaction, `guards()` says whether a silence on the wall clock matters now,
    `needs_cycles()` / `free_run()` run the node's cycles while SYNC is gone. `cycle_s`
    (0x1006, s) and `sync_limit` (0x2021, SYNCs) are the owner's to set; entries come from
    0x1016 writes (`set_entry`).
    """

    def __init__(self, network: canopen.Network, lock: threading.RLock,
                 on_loss: Callable[[int, str], None], guards: Callable[[], bool],
                 needs_cycles: Callable[[], bool] = lambda: False,
                 free_run: Callable[[], None] = lambda: None) -> None:
        self.network = network
        self.lock = lock
        self.cycle_s = 1e-3
        self._sync_limit = 0
        self._on_loss, self._guards = on_loss, guards
        self._needs_cycles, self._free_run = needs_cycles, free_run
        self._entries: dict[int, tuple[int, float]] = {}  # sub → (producer, consumer time s)
        self._beat_sync: dict[int, int] = {}  # producer → SYNC count at its last heartbeat
        self._beat_wall: dict[int, float] = {}
        self._syncs = 0
        self._sync_wall: float | None = None
        self._gone = False  # the wall clock found a loss; until the next SYNC
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def sync_limit(self) -> int:
        """SYNCs missed in a row (0x2021) after which SYNC is lost; 0: off."""
        return self._sync_limit

    @sync_limit.setter
    def sync_limit(self, value: int) -> None:
        self._sync_limit = value
        if value:
            self._start()

    def _start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="canopen-watchdog",
                                            daemon=True)
            self._thread.start()

    def set_entry(self, subindex: int, entry: int) -> None:
        """A 0x1016 write: watch the producer it names (time 0 or node 0: the entry is off)."""
        producer, time_ms = cia301.consumer_of(entry)
        with self.lock:
            self._entries.pop(subindex, None)
            if producer and time_ms:
                self._entries[subindex] = (producer, time_ms * 1e-3)
                self.network.subscribe(cia301.HEARTBEAT_COB_BASE + producer, self._on_heartbeat)
                self._start()

    def reset(self) -> None:
        """NMT reset: no entries, nothing armed (0x1016 back to its defaults)."""
        with self.lock:
            self._entries.clear()
            self._beat_sync.clear()
            self._beat_wall.clear()
            self._sync_wall = None

    def _on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """A heartbeat arms (or re-arms) its producer's monitoring (CiA 301)."""
        producer = can_id - cia301.HEARTBEAT_COB_BASE
        self._beat_sync[producer] = self._syncs
        self._beat_wall[producer] = time.monotonic()

    def on_sync(self) -> Loss | None:
        """Count a SYNC (called in the node's SYNC handler, under `lock`); the loss of a
        heartbeat older than its consumer time in virtual time, if one is."""
        self._syncs += 1
        self._sync_wall = time.monotonic()
        self._gone = False
        for producer, limit_s in self._entries.values():
            beat = self._beat_sync.get(producer)
            if beat is not None and (self._syncs - beat) * self.cycle_s > limit_s:
                return self._lose(producer)
        return None

    def _lose(self, producer: int) -> Loss:
        del self._beat_sync[producer]
        self._beat_wall.pop(producer, None)
        return cia301.EMCY_HEARTBEAT, f"node {producer} heartbeat lost"

    def wall_check(self, now: float) -> Loss | None:
        """The loss the wall clock shows at `now` (monotonic s), if any (under `lock`)."""
        last_sync = self._sync_wall or 0.0
        for producer, limit_s in self._entries.values():
            beat = self._beat_wall.get(producer)
            if beat is not None and now - max(beat, last_sync) > limit_s:
                return self._lose(producer)
        if (self._sync_limit and self._sync_wall is not None
                and now - self._sync_wall > self._sync_limit * self.cycle_s):
            self._sync_wall = None  # re-armed by the next SYNC
            return cia301.EMCY_COMMUNICATION, "SYNC lost"
        return None

    def _run(self) -> None:
        while not self._stop.wait(min(POLL_S, self.cycle_s) if self._needs_cycles()
                                  else POLL_S):
            if self.network.bus is None:  # disconnected: the node is gone
                return
            with self.lock:
                now = time.monotonic()
                loss = self.wall_check(now) if self._guards() else None
                if loss is not None:
                    self._gone = True
                    self._on_loss(*loss)
                silent = now - (self._sync_wall or 0.0)
                if self._needs_cycles() and (self._gone or silent > SILENT_S):
                    self._free_run()

    def close(self) -> None:
        """Stop the thread."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)
