"""Host driver of a CiA 402 servo drive on canopen's RemoteNode, driven from the cycle loop.

From canopen: the RemoteNode (SDO client, NMT master, heartbeat and EMCY consumers, PDO
mapping by SDO, PDO reception) and, from its p402 profile, the statusword masks, the
transition table and the next-state rule (`State402`); the controlword commands and the
supported-mode bits are `protocols.cia402`'s (the simulated drive decodes the same). Not
from canopen: `BaseNode402`'s state / op-mode setters and fault reset wait on wall-clock
timeouts and busy-wait for the statusword, and its controlword setter does not transmit a
SYNC-type RPDO. In lockstep virtual time the controlword must advance
one step per bus cycle, so `enable_step` / `disable_step` do that here. PDO payloads are
packed and unpacked with one precompiled `struct` per PDO (canopen's per-variable PDO
access costs tens of µs per cycle).

Units on the bus (the simulated drive's EDS, docs/ARCHITECTURE.md): position 1 nm,
velocity 1 nm/s, 0x6071 / 0x6077 / 0x60B2 in per mille of the rated force 0x6076 (mN),
0x2010 / 0x2011 in mN. This API speaks SI: m, m/s, N. The object table is
`protocols.cia402`, shared with the simulated drive.
"""

from __future__ import annotations

import collections
import logging
import math
import struct
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, NamedTuple

import can
import canopen
from canopen.emcy import EmcyError
from canopen.pdo import PdoMap
from canopen.profiles.p402 import State402

from feedbench.config import ConfigError, Field, positive, validate_table
from feedbench.protocols import cia301
from feedbench.protocols.canbus import Receive, pdo_codec, remote_node, send_frames
from feedbench.protocols.cia402 import (
    COMMANDS, CONTROLWORD, CW_FAULT_RESET, CYCLE_COUNTER, DEFAULT_RPDO_MAPS, DEFAULT_TPDO_MAPS,
    FAULT, FAULT_REACTION_OPTION_CODE, FOLLOWING_ERROR_OFF, FOLLOWING_ERROR_WINDOW, FORCE_ACTUAL,
    FORCE_OFFSET_FINE, GAIN_OBJECTS, MODES_OF_OPERATION, NOT_READY, OPERATION_ENABLED,
    POSITION_ACTUAL, PROFILE_DECELERATION, QUICK_STOP_ACTIVE, QUICK_STOP_DECELERATION,
    QUICK_STOP_OPTION_CODE, RATED_TORQUE, STATUSWORD, STOP_COAST, STOP_QUICK_RAMP,
    STOP_SLOW_DOWN_RAMP, SUPPORTED_DRIVE_MODES, SWITCH_ON_DISABLED, SW_FAULT, SW_TARGET_REACHED,
    TARGET_POSITION, TARGET_TORQUE, TARGET_VELOCITY, TORQUE_ACTUAL, TORQUE_OFFSET,
    VELOCITY_ACTUAL, VELOCITY_OFFSET, mode_bit, quick_stop_ramp,
)
from feedbench.units import MM_PER_MIN

Entry = int | tuple[int, int]
"""A mapped object: index (sub-index 0) or (index, sub-index)."""

DISABLED_STATES = (SWITCH_ON_DISABLED, NOT_READY, FAULT)
CW_ENABLE_OPERATION = COMMANDS["ENABLE OPERATION"]
CW_QUICK_STOP = COMMANDS["QUICK STOP"]
CW_DISABLE_VOLTAGE = COMMANDS["DISABLE VOLTAGE"]
CW_DISABLE_OPERATION = COMMANDS["SWITCH ON"]  # 0x07 from operation enabled: transition 5

HOST_CONSUMER_MS = 3000
"""The drives' consumer time of the host's heartbeat (0x1016): they stop without it. In
lockstep it is also how long a live host may stall on the wall clock (a 1 s limit stopped
tests on a 2-core machine at load 15); in real time SYNC loss (0x2021) stops them first."""
HEARTBEAT_LOST_FACTOR = 30
"""The host counts a drive's heartbeat lost after this many of its producer times (3 s at
100 ms: a stalled host must not take its own stall for the drive's)."""
SET_QUEUE = 64
"""Complete TPDO sets held for the host (real time: a host behind by more loses the oldest,
seen as missed cycles)."""
SAFE_STATES = (*DISABLED_STATES, QUICK_STOP_ACTIVE)
"""States that command no motion: de-energised, or ramping down by the drive's own quick stop
(not a stop: the runner confirms one by measured standstill)."""

STOP_SCHEMA = {
    "deceleration_m_s2": Field(float, 0.5, "least deceleration a drive's stop may ramp at (m/s²):"
                               " 0x6085, and 0x6084 where 0x605A or 0x605E ramps on it",
                               positive),
    "following_error_mm": Field(float, 10.0, "largest following-error window 0x6065 (mm)",
                                positive),
    "write": Field(bool, False, "write safe values (ramps of deceleration_m_s2, option codes 2, "
                   "the window following_error_mm) where the drive's are not, instead of "
                   "refusing"),
    "standstill_mm_min": Field(float, 5.0, "|velocity actual| below which the axis stands "
                               "(mm/min)", positive),
    "standstill_cycles": Field(int, 10, "bus cycles the axis must stand before the stop is "
                               "confirmed", positive),
    "margin_s": Field(float, None, "time a stop may take beyond v_max / deceleration (s; "
                      "default: the axis kind's, the time it takes to settle)", positive),
}
"""``[bench.stop]``: what the safe stop relies on in the drives and how it is confirmed."""


@dataclass(frozen=True)
class StopSettings:
    """``[bench.stop]`` in SI: deceleration (m/s²), following error (m), standstill velocity
    (m/s) and cycles, margin (s); `write` safe values instead of refusing."""

    deceleration: float = 0.5
    following_error: float = 0.01
    write: bool = False
    standstill_velocity: float = 5.0 * MM_PER_MIN
    standstill_cycles: int = 10
    margin: float = 0.1

    @classmethod
    def from_config(cls, table: Mapping[str, Any], margin_s: float) -> StopSettings:
        """From a ``[bench.stop]`` table (engineering units), `margin_s` (s) where it gives
        none; `ConfigError` names a bad key."""
        t = validate_table(table, STOP_SCHEMA, "bench.stop")
        margin = margin_s if t["margin_s"] is None else t["margin_s"]
        return cls(t["deceleration_m_s2"], t["following_error_mm"] * 1e-3, t["write"],
                   t["standstill_mm_min"] * MM_PER_MIN, t["standstill_cycles"], margin)


STOP_OBJECTS = (QUICK_STOP_DECELERATION, PROFILE_DECELERATION, QUICK_STOP_OPTION_CODE,
                FAULT_REACTION_OPTION_CODE, FOLLOWING_ERROR_WINDOW)
"""The drive objects a stop depends on, read (and checked) at configure."""


class StopParameters(NamedTuple):
    """What a drive's stop depends on, as read at configure (raw values; None: the drive has
    no such object): 0x6085 / 0x6084 (nm/s²), 0x605A, 0x605E, 0x6065 (nm), and the host
    heartbeat's consumer time in 0x1016 (ms)."""

    raw: dict[int, int | None]
    consumer_ms: int | None

    def ramp(self, option: int | None) -> int | None:
        """The deceleration object (0x6084 / 0x6085) a stop with `STOP_*` ramp `option`
        ramps on (None: no ramp object: at the force limit, or no option code)."""
        return {STOP_SLOW_DOWN_RAMP: PROFILE_DECELERATION,
                STOP_QUICK_RAMP: QUICK_STOP_DECELERATION}.get(option)

    def stop_ramps(self) -> set[int]:
        """The deceleration objects the quick stop and the fault reaction ramp on."""
        option, reaction = self.raw[QUICK_STOP_OPTION_CODE], self.raw[FAULT_REACTION_OPTION_CODE]
        ramps = {self.ramp(None if option is None else quick_stop_ramp(option)),
                 self.ramp(reaction)}
        return {index for index in ramps if index is not None}

    def deceleration(self, least: float) -> float:
        """m/s² the quick stop ramps at: its ramp object's value (at the force limit, or
        without 0x605A: `least`, the least the bench accepts)."""
        option = self.raw[QUICK_STOP_OPTION_CODE]
        index = self.ramp(quick_stop_ramp(option if option is not None else STOP_QUICK_RAMP))
        value = self.raw.get(index) if index is not None else None
        return least if value is None else value * 1e-9

    def problems(self, settings: StopSettings) -> dict[int, str]:
        """Object → the line saying why its value cannot stop the axis as `settings` require."""
        raw = self.raw
        out = {index: f"0x{index:04X} = {raw[index]} nm/s² is below the "
                      f"{settings.deceleration:g} m/s² a stop needs"
               for index in sorted(self.stop_ramps())
               if raw[index] is not None and raw[index] * 1e-9 < settings.deceleration}
        for index, name in ((QUICK_STOP_OPTION_CODE, "quick stop"),
                            (FAULT_REACTION_OPTION_CODE, "fault reaction")):
            if raw[index] is not None and quick_stop_ramp(raw[index]) == STOP_COAST:
                out[index] = f"0x{index:04X} = 0: the {name} lets the axis coast"
        window = raw[FOLLOWING_ERROR_WINDOW]
        if window is not None and window * 1e-9 > settings.following_error:
            out[FOLLOWING_ERROR_WINDOW] = (
                f"0x{FOLLOWING_ERROR_WINDOW:04X} = {window} nm is above the "
                f"{settings.following_error * 1e3:g} mm allowed (0x{FOLLOWING_ERROR_OFF:X}: off)")
        if self.consumer_ms == 0:
            out[cia301.CONSUMER_HEARTBEAT_TIME] = (
                f"0x{cia301.CONSUMER_HEARTBEAT_TIME:04X} does not watch the host's heartbeat")
        return out

    def as_metadata(self) -> dict[str, int | None]:
        """The values by object ("0x6085": raw, …, "0x1016": consumer time in ms)."""
        return {**{f"0x{index:04X}": value for index, value in self.raw.items()},
                f"0x{cia301.CONSUMER_HEARTBEAT_TIME:04X}": self.consumer_ms}


def safe_values(settings: StopSettings) -> dict[int, int]:
    """What `StopSettings.write` writes where a drive's value is refused (raw: nm/s², codes,
    nm)."""
    return {QUICK_STOP_DECELERATION: math.ceil(settings.deceleration * 1e9),
            PROFILE_DECELERATION: math.ceil(settings.deceleration * 1e9),
            QUICK_STOP_OPTION_CODE: STOP_QUICK_RAMP, FAULT_REACTION_OPTION_CODE: STOP_QUICK_RAMP,
            FOLLOWING_ERROR_WINDOW: math.floor(settings.following_error * 1e9)}


@dataclass(frozen=True)
class PdoConfig:
    """PDO maps the host writes by SDO: PDO number → mapped objects; absent numbers are off.

    All mapped PDOs are SYNC-triggered (transmission type 1).
    """

    rpdo: dict[int, tuple[Entry, ...]] = field(default_factory=lambda: dict(DEFAULT_RPDO_MAPS))
    tpdo: dict[int, tuple[Entry, ...]] = field(default_factory=lambda: dict(DEFAULT_TPDO_MAPS))


class Actual(NamedTuple):
    """Latest actual values in SI; `cycle` is the drive's 16-bit cycle counter (0x2020)."""

    cycle: int
    statusword: int
    position: float
    velocity: float
    force: float


class DriveGains(NamedTuple):
    """Cascade gains, Eq. (5.4): K_p (N·s/m), T_i (s), K_v (1/s)."""

    K_p: float
    T_i: float
    K_v: float


class DriveError(RuntimeError):
    """The drive does not answer or cannot be configured as asked."""


class CycleSignal:
    """Set by the receive thread when a cycle's TPDOs are in, awaited by the clock.

    A lock used as a binary semaphore: its calls are C-level, where `threading.Event` runs
    a Python-level Condition (≈ 5 µs less per cycle, measured).
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._lock.acquire()

    def clear(self) -> None:
        self._lock.acquire(blocking=False)

    def set(self) -> None:
        """Only one thread (the receive thread) may call this."""
        if self._lock.locked():
            self._lock.release()

    def wait(self, timeout_s: float) -> bool:
        """True once set (and cleared again for the next cycle), False after `timeout_s`."""
        return self._lock.acquire(timeout=timeout_s)


def decode_state(statusword: int) -> str:
    """CiA 402 state name of a statusword (canopen p402 masks; 'UNKNOWN' if none fits)."""
    for state, (mask, bits) in State402.SW_MASK.items():
        if statusword & mask == bits:
            return state
    return "UNKNOWN"


def controlword_towards(state: str, target: str) -> int:
    """The controlword of one step from `state` towards `target` (p402 transition table)."""
    if (state, target) not in State402.TRANSITIONTABLE:
        target = State402.next_state_indirect(state)
    return State402.TRANSITIONTABLE.get((state, target), CW_DISABLE_VOLTAGE)


def _index_subindex(entry: Entry) -> tuple[int, int]:
    return (entry, 0) if isinstance(entry, int) else entry


class Cia402Drive:
    """One CiA 402 drive on `network`, described by the EDS at `eds_path`.

    `configure()` once (SDO); then each bus cycle `set_targets(...)`, the clock's tick
    (`arm_cycle`, `transmit`, SYNC, `wait_cycle`), and `actual`.
    """

    def __init__(self, network: canopen.Network, node_id: int, eds_path: Path | str,
                 pdo_config: PdoConfig | None = None) -> None:
        self.rejected_frames: collections.Counter[str] = collections.Counter()
        """Frames dropped as malformed (too short for their service, a TPDO whose length is
        not its mapping's), by reason: a dropped TPDO leaves its cycle incomplete."""
        self.node = remote_node(network, node_id, str(eds_path), self.rejected_frames)
        self.network = network
        self.pdo_config = pdo_config or PdoConfig()
        self.emcy_code: int | None = None
        self.node.emcy.add_callback(self._on_emcy)
        self._raw: dict[int, int | float] = {STATUSWORD: 0}
        self._writers: dict[int, tuple[Callable, bytearray, int]] = {}
        self._rpdo_frames: list[can.Message] = []
        """One frame per mapped RPDO, made once: its data is the payload `_put` packs into
        (`transmit` sends them as they are, without canopen's new `can.Message` per frame)."""
        self._tpdo_handlers: list[tuple[int, Callable]] = []
        self._tpdo_count = 0
        self._frames_seen = 0
        self._sets_received = 0
        self._sets: collections.deque[tuple[dict[int, int | float], float, int, int]] = \
            collections.deque(maxlen=SET_QUEUE)
        self._latched_sets = 0
        self.set_time = math.nan
        """Receive timestamp (python-can's ``msg.timestamp``, s) of the last TPDO of the set
        `wait_cycle` returned."""
        self.syncs_sent: Callable[[], int] = lambda: 0
        """The SYNCs the host had sent when a set came (`daq.clock.RealtimeClock` counts
        them); `set_syncs` for the set `wait_cycle` returned: the set answers one of those."""
        self.set_syncs = 0
        self._cycle_complete = CycleSignal()
        self._controlword = 0
        self._newton_per_mille = math.nan
        self._supported_modes = 0
        self._heartbeat_at: float | None = None
        self._heartbeat_lost_s = math.inf
        self.node.nmt.add_heartbeat_callback(self._on_heartbeat)
        self.stop_settings = StopSettings()
        self.stop_parameters = StopParameters(dict.fromkeys(STOP_OBJECTS), None)

    # -- configuration (SDO) -------------------------------------------------------------

    def configure(self, heartbeat_ms: int = 100, timeout_s: float = 2.0,
                  gains: dict[str, float] | None = None, consumer_ms: int = HOST_CONSUMER_MS,
                  sync_loss_cycles: int = 0, cycle_s: float | None = None,
                  stop: StopSettings = StopSettings()) -> None:
        """NMT pre-operational, heartbeat on, watchdogs, PDO maps by SDO, gains, NMT
        operational.

        The drive produces its heartbeat every `heartbeat_ms` (ms; the host counts it lost
        after `HEARTBEAT_LOST_FACTOR` times that) and is told to consume the host's
        (`cia301.HOST_NODE_ID`, lost after `consumer_ms`) and, with `sync_loss_cycles`, to
        stop after that many missed SYNCs (real time; 0: off, for lockstep virtual time),
        where its EDS has the objects (0x1016, 0x2021). With `cycle_s` (s) the drive is told
        the bus cycle (0x1006, µs, where writable): the period it counts missed SYNCs in; a
        drive that runs another cycle refuses it, a `ConfigError` naming ``bench.cycle_ms``.
        What the drive's stop depends on is read and checked against `stop` (`check_stop`).
        """
        node = self.node
        node.nmt.state = "PRE-OPERATIONAL"
        self._first_contact(heartbeat_ms)
        self._wait_for_heartbeat(timeout_s)
        self._heartbeat_lost_s = HEARTBEAT_LOST_FACTOR * heartbeat_ms * 1e-3
        if cycle_s is not None:
            self._write_cycle_period(round(cycle_s * 1e6))
        self._configure_watchdogs(consumer_ms, sync_loss_cycles)
        self.check_stop(stop)
        self._newton_per_mille = node.sdo[RATED_TORQUE].raw * 1e-6
        self._supported_modes = node.sdo[SUPPORTED_DRIVE_MODES].raw
        self._map_pdos()
        self._raw[STATUSWORD] = node.sdo[STATUSWORD].raw  # the state before the first TPDO
        if gains:
            self.write_gains(**gains)
        node.nmt.state = "OPERATIONAL"

    def _first_contact(self, heartbeat_ms: int) -> None:
        """Switch the heartbeat on (0x1017): no answer is a `ConfigError` naming the node id,
        and canopen's log line of the aborted transfer is not printed besides."""
        log = logging.getLogger("canopen.sdo.client")
        log.disabled = True
        try:
            self.node.sdo[cia301.HEARTBEAT_TIME].raw = heartbeat_ms
        except canopen.SdoCommunicationError as exc:
            raise ConfigError(f"bench.node_id: no drive answers as node {self.node.id} "
                              f"({exc})") from None
        finally:
            log.disabled = False

    def _write_cycle_period(self, period_us: int) -> None:
        """0x1006 = `period_us` where the EDS makes it writable."""
        od = self.node.object_dictionary
        if cia301.CYCLE_PERIOD not in od or "w" not in od[cia301.CYCLE_PERIOD].access_type:
            return
        try:
            self.node.sdo[cia301.CYCLE_PERIOD].raw = period_us
        except canopen.SdoAbortedError as exc:
            own = self.node.sdo[cia301.CYCLE_PERIOD].raw
            raise ConfigError(f"bench.cycle_ms: drive node {self.node.id} refuses a bus cycle "
                              f"of {period_us / 1000:g} ms: it runs {own / 1000:g} ms "
                              f"(communication cycle period 0x1006; {exc})") from None

    def _configure_watchdogs(self, consumer_ms: int, sync_loss_cycles: int) -> None:
        """Consumer entry 1 (0x1016) on the host's heartbeat, the SYNC loss limit (0x2021)."""
        od = self.node.object_dictionary
        if cia301.CONSUMER_HEARTBEAT_TIME in od:
            self.node.sdo[cia301.CONSUMER_HEARTBEAT_TIME][1].raw = cia301.consumer_entry(
                cia301.HOST_NODE_ID, consumer_ms)
        if cia301.SYNC_LOSS_LIMIT in od:
            self.node.sdo[cia301.SYNC_LOSS_LIMIT].raw = sync_loss_cycles

    def check_stop(self, settings: StopSettings) -> None:
        """Read what the drive's stop depends on (`StopParameters`) into `stop_parameters`;
        with `settings.write` write `safe_values` over the refused ones and read again. A
        value still refused is a `ConfigError`, one line naming each object and its value."""
        self.stop_settings = settings
        self.stop_parameters = self._read_stop_parameters()
        problems = self.stop_parameters.problems(settings)
        if settings.write and problems:
            safe = safe_values(settings)
            for index in problems.keys() & safe.keys():
                self.node.sdo[index].raw = safe[index]
            self.stop_parameters = self._read_stop_parameters()
            problems = self.stop_parameters.problems(settings)
        if problems:
            raise ConfigError(f"bench.stop: drive node {self.node.id} cannot stop the axis: "
                              + "; ".join(problems.values()))

    def _read_stop_parameters(self) -> StopParameters:
        od = self.node.object_dictionary
        raw = {index: self.node.sdo[index].raw if index in od else None
               for index in STOP_OBJECTS}
        consumer_ms = None
        if cia301.CONSUMER_HEARTBEAT_TIME in od:
            node_id, time_ms = cia301.consumer_of(
                self.node.sdo[cia301.CONSUMER_HEARTBEAT_TIME][1].raw)
            consumer_ms = time_ms if node_id == cia301.HOST_NODE_ID else 0
        return StopParameters(raw, consumer_ms)

    @property
    def stop_deceleration(self) -> float:
        """m/s² the drive's quick stop ramps at (`StopParameters.deceleration`)."""
        return self.stop_parameters.deceleration(self.stop_settings.deceleration)

    def _on_heartbeat(self, state: int) -> None:
        self._heartbeat_at = time.monotonic()

    def heartbeat_lost(self, now: float) -> bool:
        """True once when the drive's heartbeat has been silent for its consumer time at
        `now` (`time.monotonic`, s); again only after a new heartbeat."""
        if self._heartbeat_at is None or now - self._heartbeat_at <= self._heartbeat_lost_s:
            return False
        self._heartbeat_at = None
        return True

    def _wait_for_heartbeat(self, timeout_s: float) -> None:
        nmt = self.node.nmt
        with nmt.state_update:
            if not nmt.state_update.wait_for(lambda: nmt.timestamp is not None, timeout_s):
                raise DriveError(f"node {self.node.id}: no heartbeat within {timeout_s} s")

    def _map_pdos(self) -> None:
        for cob_id, handler in self._tpdo_handlers:
            self.network.unsubscribe(cob_id, handler)
        self._tpdo_handlers.clear()
        self._writers.clear()
        self._rpdo_frames.clear()
        self._raw.clear()
        self._tpdo_count = 0
        for number, pdo_map in self.node.rpdo.map.items():
            if self._save_map(pdo_map, self.pdo_config.rpdo.get(number, ())):
                self._bind_writers(pdo_map)
        pending: dict[int, int | float] = {}
        for number, pdo_map in self.node.tpdo.map.items():
            if self._save_map(pdo_map, self.pdo_config.tpdo.get(number, ())):
                self._bind_reader(pdo_map, pending)
        if CONTROLWORD not in self._writers or STATUSWORD not in self._raw:
            raise DriveError("the cycle loop needs 0x6040 in an RPDO and 0x6041 in a TPDO")

    @staticmethod
    def _save_map(pdo_map: PdoMap, entries: tuple[Entry, ...]) -> bool:
        """Write one PDO's mapping, COB-ID and transmission type by SDO; True if enabled."""
        if pdo_map.predefined_cob_id is None:
            pdo_map.read()
        else:
            pdo_map.cob_id = pdo_map.predefined_cob_id
        pdo_map.clear()
        for entry in entries:
            pdo_map.add_variable(*_index_subindex(entry))
        pdo_map.trans_type = cia301.TRANSMISSION_SYNC
        pdo_map.enabled = bool(entries)
        pdo_map.save()
        return pdo_map.enabled

    def _bind_writers(self, pdo_map: PdoMap) -> None:
        codec = pdo_codec(pdo_map)
        for index, offset, fmt in zip(codec.indices, codec.offsets, codec.formats):
            self._writers[index] = (struct.Struct("<" + fmt).pack_into, pdo_map.data, offset)
        self._rpdo_frames.append(can.Message(arbitration_id=pdo_map.cob_id, data=pdo_map.data,
                                             is_extended_id=pdo_map.cob_id > 0x7FF))

    def _bind_reader(self, pdo_map: PdoMap, pending: dict[int, int | float]) -> None:
        """Decode this TPDO straight from the frame into `pending` (canopen's
        `PdoMap.on_message` takes a Condition and notifies per frame). The set is complete
        when every TPDO arrived; the first-mapped TPDO starts a set (a drive sends them in
        order after the SYNC), so a set that lost a frame is never completed by the next
        one's. A complete set is queued whole with its last frame's timestamp: `wait_cycle`
        hands the host one set at a time, in order, never a mix of two."""
        codec = pdo_codec(pdo_map)
        update = pending.update
        unpack = codec.layout.unpack
        indices = codec.indices
        complete = self._cycle_complete
        size = codec.layout.size
        rejected = self.rejected_frames
        first = self._tpdo_count == 0
        queue = self._sets.append

        def on_tpdo(can_id: int, data: bytearray, timestamp: float) -> None:
            if len(data) != size:
                rejected[f"TPDO 0x{can_id:03X}: {len(data)} data bytes, mapped {size}"] += 1
                return
            update(zip(indices, unpack(data)))
            self._frames_seen = 1 if first else self._frames_seen + 1
            if self._frames_seen == self._tpdo_count:
                self._sets_received += 1
                queue((pending.copy(), timestamp, self._sets_received, self.syncs_sent()))
                complete.set()

        self.network.unsubscribe(pdo_map.cob_id, pdo_map.on_message)
        self.network.subscribe(pdo_map.cob_id, on_tpdo)
        self._tpdo_handlers.append((pdo_map.cob_id, on_tpdo))
        self._raw.update(dict.fromkeys(indices, 0))
        self._tpdo_count += 1

    # -- gains, EMCY (SDO / consumer) ----------------------------------------------------

    def read_gains(self) -> DriveGains:
        """The drive's cascade gains by SDO."""
        return DriveGains(*(self.node.sdo[GAIN_OBJECTS[name]].raw for name in DriveGains._fields))

    def write_gains(self, K_p: float | None = None, T_i: float | None = None,
                    K_v: float | None = None) -> None:
        """Write the given cascade gains by SDO (N·s/m, s, 1/s); None leaves one unchanged."""
        for name, value in (("K_p", K_p), ("T_i", T_i), ("K_v", K_v)):
            if value is not None:
                self.node.sdo[GAIN_OBJECTS[name]].raw = value

    def on_emcy(self, callback: Callable[[EmcyError], None]) -> None:
        """Call `callback(EmcyError)` on every EMCY frame of this node (receive thread)."""
        self.node.emcy.add_callback(callback)

    def _on_emcy(self, error: EmcyError) -> None:
        self.emcy_code = error.code

    # -- state machine, one controlword per cycle ----------------------------------------

    @property
    def statusword(self) -> int:
        """The latest statusword 0x6041 (TPDO)."""
        return self._raw[STATUSWORD]

    @property
    def state(self) -> str:
        """CiA 402 state decoded from the latest statusword."""
        return decode_state(self._raw[STATUSWORD])

    @property
    def is_enabled(self) -> bool:
        return self.state == OPERATION_ENABLED

    @property
    def fault(self) -> bool:
        """Statusword bit 3: fault (or fault reaction) active."""
        return bool(self._raw[STATUSWORD] & SW_FAULT)

    @property
    def controlword(self) -> int:
        """The controlword last written (sent with the next RPDOs)."""
        return self._controlword

    def _write_controlword(self, controlword: int) -> None:
        self._controlword = controlword
        self._put(CONTROLWORD, controlword)

    def enable_step(self) -> bool:
        """Write the next controlword towards operation enabled; True once it is reached.

        Shutdown 0x06 → switch on 0x07 → enable operation 0x0F; from FAULT first a rising
        edge of bit 7 (0x00 then 0x80). Call once per bus cycle, before the tick.
        """
        state = self.state
        if state == FAULT:
            self._write_controlword(CW_DISABLE_VOLTAGE if self._controlword & CW_FAULT_RESET
                                    else CW_FAULT_RESET)
            return False
        if state == OPERATION_ENABLED:
            self._write_controlword(CW_ENABLE_OPERATION)
            return True
        self._write_controlword(controlword_towards(state, OPERATION_ENABLED))
        return False

    def disable_step(self, at_standstill: bool = False, stopped: bool | None = None) -> bool:
        """Write the next controlword towards a de-energised drive; True once it is reached.

        Operation enabled → quick stop 0x02 (the drive ramps down); in quick stop active the
        drive either switches off itself or, once the axis is `stopped`, is sent disable
        voltage 0x00 (`stopped`: the host's measurement; None: the drive's own, bit 10 stop
        complete); any other powered state gets 0x00 directly. With `at_standstill` (the
        host has already ramped its setpoint down) operation enabled holds the setpoint
        (0x0F) until the axis is `stopped`, then gets disable operation 0x07 (transition 5)
        instead of a quick stop.
        """
        state = self.state
        if stopped is None:
            stopped = bool(self._raw[STATUSWORD] & SW_TARGET_REACHED)
        if state in DISABLED_STATES:
            self._write_controlword(CW_DISABLE_VOLTAGE)
            return True
        if state == OPERATION_ENABLED and at_standstill:
            self._write_controlword(CW_DISABLE_OPERATION if stopped else CW_ENABLE_OPERATION)
            return False
        stopping = state == OPERATION_ENABLED or (state == QUICK_STOP_ACTIVE and not stopped)
        self._write_controlword(CW_QUICK_STOP if stopping else CW_DISABLE_VOLTAGE)
        return False

    def quick_stop(self) -> None:
        """Controlword quick stop (0x02) from the next transmit on."""
        self._write_controlword(CW_QUICK_STOP)

    def disable_voltage(self) -> None:
        """Controlword disable voltage (0x00) from the next transmit on: the power stage off
        from any state, the axis left to coast."""
        self._write_controlword(CW_DISABLE_VOLTAGE)

    def stop_by_sdo(self, timeout_s: float, standstill: float,
                    escalate: bool = False) -> tuple[str, float]:
        """One step of a stop by SDO, for when the cycle's PDOs fail: the state (0x6041) and
        velocity actual (0x606C, m/s) read by SDO; then quick stop (0x02) while the drive is
        enabled or in quick stop with |v| ≥ `standstill` (m/s), else (or with `escalate`)
        disable voltage (0x00), by SDO and in the RPDO payload. Returns (state, velocity) as
        read. Raises canopen's or the bus's error if the drive does not answer within
        `timeout_s` (s) per request."""
        sdo = self.node.sdo
        waited, sdo.RESPONSE_TIMEOUT = sdo.RESPONSE_TIMEOUT, timeout_s
        try:
            state = decode_state(sdo[STATUSWORD].raw)
            velocity = sdo[VELOCITY_ACTUAL].raw * 1e-9
            moving = abs(velocity) >= standstill
            quick = not escalate and (state == OPERATION_ENABLED
                                      or (state == QUICK_STOP_ACTIVE and moving))
            self._write_controlword(CW_QUICK_STOP if quick else CW_DISABLE_VOLTAGE)
            sdo[CONTROLWORD].raw = self._controlword
            return state, velocity
        finally:
            sdo.RESPONSE_TIMEOUT = waited

    def state_by_sdo(self, timeout_s: float) -> tuple[int, str]:
        """The statusword 0x6041 read by SDO (waiting up to `timeout_s`, s) and its state."""
        sdo = self.node.sdo
        waited, sdo.RESPONSE_TIMEOUT = sdo.RESPONSE_TIMEOUT, timeout_s
        try:
            word = sdo[STATUSWORD].raw
        finally:
            sdo.RESPONSE_TIMEOUT = waited
        return word, decode_state(word)

    def nmt_stop(self) -> None:
        """NMT stop to the node (unconfirmed: NMT has no answer)."""
        self.node.nmt.state = "STOPPED"

    def enable(self, tick: Callable[[], int], max_cycles: int = 100) -> None:
        """Run `enable_step` and `tick` until operation enabled (DriveError after max_cycles)."""
        self._run_steps(self.enable_step, tick, max_cycles, OPERATION_ENABLED)

    def disable(self, tick: Callable[[], int], max_cycles: int = 5000) -> None:
        """Run `disable_step` and `tick` until the drive is de-energised."""
        self._run_steps(self.disable_step, tick, max_cycles, "disabled")

    def _run_steps(self, step: Callable[[], bool], tick: Callable[[], int],
                   max_cycles: int, goal: str) -> None:
        for _ in range(max_cycles):
            if step():
                return
            tick()
        raise DriveError(f"node {self.node.id}: not {goal} after {max_cycles} cycles "
                         f"(state {self.state})")

    # -- setpoints and actual values (PDO) -----------------------------------------------

    def set_mode(self, mode: int) -> None:
        """Modes of operation 0x6060 (8 CSP, 9 CSV, 10 CST), by RPDO if mapped, else SDO."""
        bit = mode_bit(mode)
        if not bit or not self._supported_modes & bit:
            raise ValueError(f"mode {mode} not supported by node {self.node.id} "
                             f"(0x6502 = 0x{self._supported_modes:04X})")
        if MODES_OF_OPERATION in self._writers:
            self._put(MODES_OF_OPERATION, mode)
        else:
            self.node.sdo[MODES_OF_OPERATION].raw = mode

    def set_targets(self, position: float | None = None, velocity: float | None = None,
                    force: float | None = None, velocity_offset: float | None = None,
                    force_offset: float | None = None) -> None:
        """Setpoints in SI (m, m/s, N) into the RPDO payloads; sent by the next `transmit`.

        `force_offset` goes to 0x2011 (mN) when mapped, else to the torque offset 0x60B2 (‰).
        """
        if position is not None:
            self._put(TARGET_POSITION, round(position * 1e9))
        if velocity is not None:
            self._put(TARGET_VELOCITY, round(velocity * 1e9))
        if force is not None:
            self._put(TARGET_TORQUE, round(force / self._newton_per_mille))
        if velocity_offset is not None:
            self._put(VELOCITY_OFFSET, round(velocity_offset * 1e9))
        if force_offset is not None:
            if FORCE_OFFSET_FINE in self._writers:
                self._put(FORCE_OFFSET_FINE, round(force_offset * 1e3))
            else:
                self._put(TORQUE_OFFSET, round(force_offset / self._newton_per_mille))

    def _put(self, index: int, value: int) -> None:
        try:
            pack_into, payload, offset = self._writers[index]
        except KeyError:
            raise DriveError(f"0x{index:04X} is not mapped in an RPDO of node "
                             f"{self.node.id}") from None
        try:
            pack_into(payload, offset, value)
        except struct.error:
            raise DriveError(f"0x{index:04X}: {value} is out of the object's range") from None

    def transmit(self) -> None:
        """Send every mapped RPDO once (they take effect at the next SYNC): the frames made
        at mapping (`_rpdo_frames`), their data packed in place (`protocols.canbus.send_frames`)."""
        send_frames(self.network, self._rpdo_frames)

    @property
    def actual(self) -> Actual:
        """Latest actual values from the TPDOs, in SI (NaN where an object is not mapped)."""
        raw = self._raw
        force = raw[FORCE_ACTUAL] * 1e-3 if FORCE_ACTUAL in raw else \
            raw.get(TORQUE_ACTUAL, math.nan) * self._newton_per_mille
        return Actual(self.device_cycle, raw[STATUSWORD],
                      raw.get(POSITION_ACTUAL, math.nan) * 1e-9,
                      raw.get(VELOCITY_ACTUAL, math.nan) * 1e-9, force)

    def latest(self, index: int) -> int | float:
        """The latest raw value of an object mapped in a TPDO (KeyError if it is not)."""
        return self._raw[index]

    # -- cycle hand-shake with the bench clock -------------------------------------------

    @property
    def device_cycle(self) -> int:
        """The drive's cycle counter 0x2020 (16 bit); without it, the TPDO sets received."""
        return self._raw.get(CYCLE_COUNTER, self._latched_sets & 0xFFFF)

    @property
    def sets_received(self) -> int:
        """Complete TPDO sets the receive thread has seen since the PDOs were mapped."""
        return self._sets_received

    @property
    def sets_waiting(self) -> int:
        """Complete TPDO sets received and not taken by `wait_cycle` yet."""
        return len(self._sets)

    def arm_cycle(self) -> None:
        """Before the SYNC (lockstep), or when the host starts anew (real time): forget
        the TPDOs received so far."""
        self._frames_seen = 0
        self._sets.clear()
        self._cycle_complete.clear()

    def wait_cycle(self, timeout_s: float, receive: Receive | None = None) -> bool:
        """Take the oldest complete TPDO set not taken yet, waiting up to `timeout_s` for one
        (lockstep: the SYNC's after `arm_cycle`; real time: the next in order, possibly in
        already), as the actual values (`actual`, `statusword`, `device_cycle`,
        `set_time`); False if none came (one that came as the wait timed out is taken).
        `receive`: the frames are read in this thread while it can (`protocols.canbus.
        cycle_reads`), else the receive thread's are awaited."""
        if receive is not None:
            deadline = time.monotonic() + timeout_s
            while not self._sets and (left_s := deadline - time.monotonic()) > 0 \
                    and receive(left_s):
                pass
            timeout_s = max(0.0, deadline - time.monotonic())
        while not self._sets:
            if not self._cycle_complete.wait(timeout_s) and not self._sets:
                return False
        self._raw, self.set_time, self._latched_sets, self.set_syncs = self._sets.popleft()
        return True
