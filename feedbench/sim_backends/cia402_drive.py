"""A simulated CiA 402 servo drive: a canopen LocalNode whose world is an `AxisSimulator`.

The node is protocol-true: NMT (boot-up, pre-operational / operational, resets), SDO server
on the object dictionary of `cia402.eds`, heartbeat producer (0x1017), EMCY on faults,
PDOs mapped by SDO. canopen's LocalNode does nothing automatic for PDOs, so this class
is the SYNC consumer. Lockstep virtual time: each SYNC
  1. counts the cycle (0x2020),
  2. applies the latest RPDO data (NMT operational only; every transmission type is applied
     at the SYNC, which is what CiA 301 prescribes for the synchronous ones),
  3. advances the CiA 402 state machine on the controlword (`protocols.cia402`: the
     commands the host writes, `command_of`, `TRANSITIONS`),
  4. steps the physics one bus cycle (`AxisSimulator.step_cycle`, servo loops inside),
     after the world's `before_physics` hooks,
  5. publishes the actual values and sends the synchronous TPDOs (types 0–240) and the
     event-driven ones (254/255) whose content changed,
  6. runs the world's `after_physics` hooks (the instruments sample the cycle), still
     inside the cycle's lock: the drive answers as soon as its own values are known, as a
     real drive does not wait for the instruments beside it, and the host's next frames
     and its Modbus requests (`SimulatedBench`: the Modbus devices share this lock) are
     served once the whole cycle is done.
Without SYNC, as a real drive: NMT, SDO, and the state machine on a controlword (and the
mode display on 0x6060) written by SDO or by an asynchronous RPDO (254/255), which takes
effect on reception; event-driven TPDOs report the new state (docs/canopen.md). Watchdogs
(`sim_backends.watchdog`): the heartbeat consumer 0x1016 and SYNC loss 0x2021 × 0x1006; a
loss (EMCY 0x8130 / 0x8100) is the fault reaction: quick-stop ramp, then FAULT, the ramp
run on the drive's own wall clock when SYNC is gone. Modes: profile velocity (0x6083 /
0x6084 ramps, run as CSV) and CSP, CSV, CST.
The host sees the simulated world only through these frames and SDO.

Drive behaviour (CiA 402): the quick stop as its option code 0x605A says (0: power stage
off at once; 1–4: ramp down on 0x6084 / 0x6085 / at the force limit in velocity control,
then switch on disabled once |v| < 0x606D; 5–8: the same ramps, then stay in quick stop
active, stop complete, transition 16 back allowed); a lost heartbeat or SYNC and bus-off
stop as the fault reaction option code 0x605E says (0: straight to FAULT; 1–4: the ramps),
then FAULT; following-error fault in CSP (|0x607A − 0x6064| > 0x6065) with EMCY 0x8611;
any EMCY code written to 0x2030 (write-only) faults the drive at the next SYNC; fault reset
on the rising edge of controlword bit 7. These drive faults go straight to FAULT (their
reaction, "disable drive", takes no time). The STO input (`torque_off`, wired to an I/O
module output) switches the power stage off at once. An exception inside the
simulated world during a SYNC (`world_fault`) faults the drive with EMCY 0x6100 (internal
software), is logged as one line, and the cycle's TPDOs still go out: the host sees the
fault as from a real drive, never a missing cycle.
"""

from __future__ import annotations

import collections
import copy
import dataclasses
from dataclasses import dataclass
import logging
import math
import operator
import struct
import threading
from pathlib import Path
from typing import Callable, Protocol

import can
import canopen
import numpy as np
from canopen.sdo import SdoAbortedError

from feedbench.models.axis import AxisSimulator
from feedbench.protocols import cia301
from feedbench.protocols.canbus import (
    NMT_BYTES, GuardedSdoServer, connect, length_checked, pdo_codec, send_frames)
from feedbench.protocols.cia402 import (
    CONTROLWORD, CSP, CSV, CW_FAULT_RESET, CYCLE_COUNTER, EMCY_FOLLOWING_ERROR, EXTRAPOLATED_CYCLES,
    DRIVE_MODES, EMCY_INTERNAL_SOFTWARE, EMCY_PDO_LENGTH, ERROR_CODE, FAULT, FAULT_INJECTION,
    FAULT_REACTION, PROFILE_ACCELERATION, PROFILE_DECELERATION, PV,
    FOLLOWING_ERROR_ACTUAL, FOLLOWING_ERROR_OFF, FOLLOWING_ERROR_WINDOW, FORCE_ACTUAL, FORCE_LIMIT,
    FORCE_OFFSET_FINE, GAIN_OBJECTS, MODES_OF_OPERATION, MODES_OF_OPERATION_DISPLAY,
    OPERATION_ENABLED, POSITION_ACTUAL, POWERED, QUICK_STOP_ACTIVE, QUICK_STOP_DECELERATION,
    RATED_TORQUE, STATE_BITS, STATUSWORD, SWITCH_ON_DISABLED, SW_FOLLOWING_ERROR,
    SW_FOLLOWS_COMMAND, SW_REMOTE, SW_TARGET_REACHED, TARGET_POSITION, TARGET_TORQUE,
    TARGET_VELOCITY, TORQUE_ACTUAL, TORQUE_OFFSET, TRANSITIONS, VELOCITY_ACTUAL, VELOCITY_OFFSET,
    VELOCITY_WINDOW, FAULT_REACTION_OPTION_CODE, QUICK_STOP_OPTION_CODE, STOP_COAST,
    STOP_QUICK_RAMP, STOP_SLOW_DOWN_RAMP, command_of, quick_stop_holds, quick_stop_ramp,
)
from feedbench.sim_backends import eds
from feedbench.sim_backends.faults import EMCY_BUS_OFF_RECOVERED, NO_FAULTS, Faults
from feedbench.sim_backends.watchdog import Watchdog, check_range, check_subindex

LOGGER = logging.getLogger(__name__)

GAIN_FIELDS = {index: name for name, index in GAIN_OBJECTS.items()}  # → CascadeGains
RAMPING = (QUICK_STOP_ACTIVE, FAULT_REACTION)
"""States that run the quick-stop ramp (0x6085)."""
SETTLE_CYCLES = 200
"""Cycles a fault reaction waits at a zero ramp for |v| < 0x606D before it disables."""
STOP_SETTLE_CYCLES = 20
"""Cycles a quick stop waits at a zero ramp for |v| < 0x606D before it reports the stop
complete (target reached) all the same (a coupled axis may never settle inside it)."""
ASYNCHRONOUS = 254
"""PDO transmission types from here on are event-driven (254 manufacturer, 255 profile)."""
INT16_MAX = 0x7FFF
INT32_MAX = 0x7FFFFFFF


def _int32_wrapped(value: float) -> int:
    """A position in increments as an encoder reports it: INTEGER32, wrapping."""
    return (round(value) + 0x80000000 & 0xFFFFFFFF) - 0x80000000


def _fetcher(indices: tuple[int, ...]) -> Callable[[dict], tuple]:
    """values → the tuple of `indices` (itemgetter returns a bare value for one index)."""
    if len(indices) == 1:
        return lambda values: (values[indices[0]],)
    return operator.itemgetter(*indices)


def _saturated(value: float, limit: int) -> int:
    """`value` rounded to an integer within ±limit (an object's range)."""
    if -limit <= value <= limit:
        return round(value)
    return limit if value > 0 else -limit


class DriveObjects(Protocol):
    """Objects of a drive variant that its world serves (e.g. the rack-and-pinion axis's)."""

    def values(self) -> dict[int, int | float]:
        """Parameter values at power-on / application reset (index → raw value)."""

    def write(self, index: int, value: int | float) -> None:
        """Apply an SDO write to one of its objects (others: nothing); ValueError refuses it."""

    def actual(self) -> dict[int, int]:
        """Process values published every cycle (index → raw value)."""


def _compile_physics(simulator: AxisSimulator) -> None:
    """Step a copy once: numba compiles on the first call (seconds), not on the first SYNC."""
    copy.deepcopy(simulator).step_cycle(CSV, 0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class SensorNoise:
    """Gaussian noise on the drive's reported force (N) and velocity (m/s), one sigma each;
    `seed` makes runs repeatable. Real drives report noisy current and encoder-difference
    velocity: without it, repeated excitations of the deterministic world agree exactly
    and coherence says nothing."""

    force: float = 0.0
    velocity: float = 0.0
    seed: int = 0


NOISE_BLOCK = 4096
"""Noise samples drawn at a time (one generator call per 4 s of bus cycles, not per cycle)."""


class SimulatedCia402Drive:
    """A CiA 402 drive on `bus` (the drive owns it: `close()` shuts it down).

    `simulator` is the axis behind the drive; `tip_force` (N) is the external force the
    simulated world applies to the tool tip during the next cycles. `before_physics` and
    `after_physics` are the world's per-cycle hooks (callables without arguments), run in
    the SYNC handler in every state: `before_physics` before the physics step (a world
    device sets `tip_force` for the cycle), `after_physics` after the cycle's TPDOs went out
    (an instrument samples the cycle; it must not change what the TPDOs report).

    With `network`, the drive joins a network several drives share (`drive_bus`): the
    network's owner consumes the SYNC and calls `begin_cycle` and `end_cycle` around the
    step of their common world; `simulator` is then this drive's port of that world.
    `objects` serves the objects of a drive variant (`DriveObjects`). The owner's `lock`
    serialises its cycles with SDO, NMT and the watchdog (`sim_backends.watchdog`), and
    `free_run` is its cycle without a SYNC (the fault reaction's ramp when SYNC is gone).
    `faults` (`sim_backends.faults`): the EMCY it faults with at a SYNC count, and bus-off
    (fault reaction; EMCY 0x8140 once the bus is back).
    """

    def __init__(self, bus: can.BusABC, node_id: int, simulator: AxisSimulator,
                 eds_path: Path | str | None = None, network: canopen.Network | None = None,
                 objects: DriveObjects | None = None,
                 noise: SensorNoise = SensorNoise(), lock: threading.RLock | None = None,
                 free_run: Callable[[], None] | None = None, faults: Faults = NO_FAULTS) -> None:
        self.simulator = simulator
        self.faults = faults
        self.noise = noise
        self._rng = np.random.default_rng(noise.seed)
        self._noise_block: list[list[float]] = []
        self._objects = objects
        self._owns_network = network is None
        self.tip_force = 0.0
        self.before_physics: list[Callable[[], None]] = []
        self.after_physics: list[Callable[[], None]] = []
        self._received: dict[int, int] = {}
        self.state_log: list[tuple[int, str]] = []
        """(SYNC count, state) of every CiA 402 state the drive entered: what it did, cycle
        by cycle, for a test or a post-mortem."""
        self.lock = lock or threading.RLock()
        self.rejected_frames: collections.Counter[str] = collections.Counter()
        """SDO requests and NMT commands refused as malformed (shorter than CiA 301's; an SDO
        segment outside a transfer, answered with an abort), by reason."""
        self.node = canopen.LocalNode(node_id, eds.load(node_id, eds_path))
        self.network = network if network is not None else canopen.Network(bus)
        GuardedSdoServer(self.node.sdo, self.rejected_frames)
        self.network.add_node(self.node)
        self.node.add_read_callback(self._on_sdo_read)
        self.node.add_write_callback(self._on_sdo_write)
        self.network.unsubscribe(cia301.NMT_COB_ID, self.node.nmt.on_command)
        self.network.subscribe(cia301.NMT_COB_ID,
                               length_checked(self._on_nmt, NMT_BYTES, self.rejected_frames))
        self.watchdog = Watchdog(self.network, self.lock, self._lose_connection,
                                 guards=lambda: self.state in POWERED,
                                 needs_cycles=lambda: self.state == FAULT_REACTION,
                                 free_run=free_run or self._cycle)
        faults.on_bus_off(self._bus_off)
        if self._owns_network:
            self.network.subscribe(cia301.SYNC_COB_ID, self._on_sync)
            _compile_physics(simulator)
            connect(self.network)
        self._boot(application=True)

    # -- boot, NMT, close ----------------------------------------------------------------

    def _boot(self, application: bool) -> None:
        """Power-on / NMT reset: object values back to defaults, boot-up, pre-operational."""
        store = self.node.data_store
        for index in [i for i in store if application or i < cia301.MANUFACTURER_FIRST]:
            del store[index]
        if application:
            self._reset_application()
        self.watchdog.reset()
        self._load_pdo_maps()
        self.node.nmt.state = "INITIALISING"  # sends the boot-up message
        self.node.nmt.state = "PRE-OPERATIONAL"  # starts the heartbeat producer (0x1017)
        self._operational = False

    def _reset_application(self) -> None:
        od = self.node.object_dictionary
        sim = self.simulator
        self.values: dict[int, int | float] = {
            index: od[index].default for index in od
            if index >= cia301.MANUFACTURER_FIRST
            and isinstance(od[index], canopen.objectdictionary.ODVariable)
        }
        self.values.update({cia301.ERROR_REGISTER: 0,
                            cia301.CYCLE_PERIOD: round(sim.timing.cycle * 1e6),
                            FORCE_LIMIT: sim.force_limit})
        self.values.update({index: getattr(sim.gains, name)
                            for name, index in GAIN_OBJECTS.items()})
        if self._objects is not None:
            self.values.update(self._objects.values())
        self.watchdog.cycle_s = sim.timing.cycle
        self.watchdog.sync_limit = self.values.get(cia301.SYNC_LOSS_LIMIT, 0)
        self.state = SWITCH_ON_DISABLED
        self._previous_controlword = 0
        self._following_error = False
        self._stop_velocity = 0.0
        self._forget_setpoints()
        self._stop_complete = False
        self._settling = 0
        self._profile_velocity = 0.0
        self._count = 0
        self._newton_per_mille = self.values[RATED_TORQUE] * 1e-6  # N per ‰ (0x6076: mN)
        sim.enabled = False
        self.values[STATUSWORD] = self._statusword()

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """canopen's NmtSlave applies the command, then the drive follows its state."""
        with self.lock:
            self.node.nmt.on_command(can_id, data, timestamp)
            command, node_id = data[0], data[1]
            if node_id not in (0, self.node.id):
                return
            if self.node.nmt.state == "INITIALISING":  # reset node (0x81) / communication
                self._boot(application=command == cia301.NMT_RESET_NODE)
            elif self._pdo_dirty:
                self._load_pdo_maps()
            self._operational = self.node.nmt.state == "OPERATIONAL"

    def close(self) -> None:
        """Stop the watchdog and the heartbeat, and the receive thread and the bus unless
        they are shared."""
        self.watchdog.close()
        self.node.nmt.stop_heartbeat()
        if self._owns_network:
            self.network.disconnect()

    # -- SDO -----------------------------------------------------------------------------

    def _on_sdo_read(self, index: int, subindex: int,
                     od: canopen.objectdictionary.ODVariable) -> int | float | None:
        """Live process values; None lets canopen answer from its store / EDS default."""
        check_subindex(subindex, od)
        return self.values.get(index) if subindex == 0 else None

    def _on_sdo_write(self, index: int, subindex: int, od: canopen.objectdictionary.ODVariable,
                      data: bytes) -> None:
        """Validate and apply an SDO download (raise SdoAbortedError to refuse it); the
        controlword and the mode take effect at once, as on a real drive (no SYNC needed)."""
        check_subindex(subindex, od)
        check_range(od, od.decode_raw(data))
        if index == MODES_OF_OPERATION and od.decode_raw(data) not in DRIVE_MODES:
            raise SdoAbortedError(cia301.SDO_ABORT_VALUE_RANGE)
        if index == cia301.CONSUMER_HEARTBEAT_TIME and subindex:
            self.watchdog.set_entry(subindex, od.decode_raw(data))
        elif index == cia301.CYCLE_PERIOD:
            if od.decode_raw(data) != self.values[cia301.CYCLE_PERIOD]:
                raise SdoAbortedError(cia301.SDO_ABORT_VALUE_RANGE)  # the axis's cycle is fixed
        elif cia301.RPDO_COMMUNICATION <= index < cia301.PDO_RECORDS_END:
            if (cia301.RPDO_MAPPING <= index < cia301.TPDO_COMMUNICATION
                    or cia301.TPDO_MAPPING <= index):
                self._check_mapping(index, subindex, od.decode_raw(data))
            self._pdo_dirty = True
        elif subindex == 0 and index in self.values:
            with self.lock:
                self._apply_parameter(index, od.decode_raw(data))
                if index in (CONTROLWORD, MODES_OF_OPERATION):
                    self._apply_command()

    def _apply_parameter(self, index: int, value: int | float) -> None:
        if self._objects is not None:
            try:
                self._objects.write(index, value)
            except ValueError:
                raise SdoAbortedError(cia301.SDO_ABORT_VALUE_RANGE) from None
        if index in GAIN_FIELDS:
            try:
                gains = dataclasses.replace(self.simulator.gains, **{GAIN_FIELDS[index]: value})
            except ValueError:  # CascadeGains refuses T_i <= 0, K_p < 0, K_v < 0
                raise SdoAbortedError(cia301.SDO_ABORT_VALUE_RANGE) from None
            self.simulator.set_gains(gains)
        elif index in (FORCE_LIMIT, RATED_TORQUE) and not value > 0:
            raise SdoAbortedError(cia301.SDO_ABORT_VALUE_RANGE)
        if index == FORCE_LIMIT:
            self.simulator.force_limit = value
        elif index == cia301.SYNC_LOSS_LIMIT:
            self.watchdog.sync_limit = value
        self.values[index] = value
        self._newton_per_mille = self.values[RATED_TORQUE] * 1e-6

    def _check_mapping(self, index: int, subindex: int, value: int) -> None:
        """CiA 301 checks of a mapping entry (sub 1–8) or of the number of entries (sub 0):
        only while the PDO is not valid (COB-ID bit 31), an entry only while sub 0 is 0."""
        receive = index < cia301.TPDO_COMMUNICATION
        sdo = self.node.sdo
        cob_id = sdo[index - cia301.RPDO_MAPPING + cia301.RPDO_COMMUNICATION][cia301.PDO_COB_ID]
        if not cob_id.raw & eds.PDO_NOT_VALID or (subindex and sdo[index][0].raw):
            raise SdoAbortedError(cia301.SDO_ABORT_UNSUPPORTED_ACCESS)
        if subindex == 0:
            if value > 8 or sum(self.node.sdo[index][sub].raw & 0xFF
                                for sub in range(1, value + 1)) > 64:
                raise SdoAbortedError(cia301.SDO_ABORT_PDO_LENGTH)
            return
        if value == 0:
            return
        mapped, sub, bits = value >> 16, value >> 8 & 0xFF, value & 0xFF
        od = self.node.object_dictionary.get_variable(mapped, sub)
        if od is None:
            raise SdoAbortedError(cia301.SDO_ABORT_NO_OBJECT)
        allowed = od.writable if receive else od.readable
        if not (od.pdo_mappable and allowed and bits == len(od)):
            raise SdoAbortedError(cia301.SDO_ABORT_NOT_MAPPABLE)

    def _load_pdo_maps(self) -> None:
        """Reload the PDO maps from the SDO store (canopen keeps them apart, STACKS.md).

        RPDO frames are decoded by `_on_rpdo` on reception instead of canopen's
        `PdoMap.on_message` (a Condition and notify_all per frame).
        """
        self.node.rpdo.read(from_od=False)
        self.node.tpdo.read(from_od=False)
        receive = [m for m in self.node.rpdo.map.values() if m.enabled]
        for pdo_map in receive:
            self.network.unsubscribe(pdo_map.cob_id, pdo_map.on_message)
            self.network.subscribe(pdo_map.cob_id, self._on_rpdo)
        self._rpdo_codecs = {m.cob_id: pdo_codec(m) for m in receive}
        self._rpdo_events = {m.cob_id for m in receive if m.trans_type >= ASYNCHRONOUS}
        self._cyclic_target = any(TARGET_POSITION in codec.indices
                                  for cob_id, codec in self._rpdo_codecs.items()
                                  if cob_id not in self._rpdo_events)
        self._received.clear()
        transmit = [(m, pdo_codec(m)) for m in self.node.tpdo.map.values() if m.enabled and m.map]
        self._tpdos = [(m.cob_id, m.trans_type, codec.layout.pack, _fetcher(codec.indices))
                       for m, codec in transmit if m.trans_type <= 240]
        self._event_tpdos = {m.cob_id: (codec.layout.pack, _fetcher(codec.indices))
                             for m, codec in transmit if m.trans_type >= ASYNCHRONOUS}
        self._event_payloads: dict[int, bytes] = {}
        self._pdo_dirty = False

    # -- the cycle -----------------------------------------------------------------------

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """One bus cycle: RPDOs in, state machine, physics, actual values, TPDOs out."""
        with self.lock:
            self.sync_received()
            self._cycle()

    def sync_received(self) -> None:
        """A SYNC came (before its cycle): the heartbeat consumer counts it in virtual time."""
        loss = self.watchdog.on_sync()
        if loss is not None:
            self._lose_connection(*loss)

    def _cycle(self) -> None:
        try:
            self.begin_cycle()
            self.end_cycle()
        except Exception as error:  # answered as a drive fault, never a traceback
            self.world_fault(error)

    def _lose_connection(self, code: int, reason: str) -> None:
        """A lost heartbeat or SYNC (abort connection option code 1): EMCY `code`, and the
        fault reaction (quick-stop ramp, then FAULT) if powered, else FAULT."""
        LOGGER.warning("CiA 402 node %d: %s; EMCY 0x%04X", self.node.id, reason, code)
        if self.state in (FAULT, FAULT_REACTION):
            self.node.emcy.send(code, cia301.ERROR_REGISTER_GENERIC)
        else:
            self._fault(code, reaction=self.state in POWERED)
        self.values[STATUSWORD] = self._statusword()
        self._send_event_tpdos()

    def _bus_off(self, off: bool) -> None:
        """Bus-off (`faults`): the fault reaction, as on a lost connection; once the bus is
        back, the EMCY that could not be sent meanwhile."""
        with self.lock:
            if off:
                self._lose_connection(EMCY_BUS_OFF_RECOVERED, "bus off")
            else:
                self.node.emcy.send(EMCY_BUS_OFF_RECOVERED, cia301.ERROR_REGISTER_GENERIC)

    def world_fault(self, error: Exception, tpdos_sent: bool = False) -> None:
        """The world raised `error` during this SYNC: fault (EMCY 0x6100) and one log line on
        entering the fault; the statusword and the cycle's TPDOs go out all the same, once:
        if they were already out (`tpdos_sent`: an instrument's hook failed after them),
        only the event-driven ones that changed, and the next SYNC's set shows the fault."""
        if self.state != FAULT:
            LOGGER.error("CiA 402 node %d: fault inside the simulated world at SYNC %d: %s: %s;"
                         " EMCY 0x%04X", self.node.id, self._count, type(error).__name__, error,
                         EMCY_INTERNAL_SOFTWARE)
            self._fault(EMCY_INTERNAL_SOFTWARE)
        self.values[STATUSWORD] = self._statusword()
        if self._operational and tpdos_sent:
            self._send_event_tpdos()
        elif self._operational:
            self._send_tpdos()

    def begin_cycle(self) -> None:
        """First half of a SYNC: count, latch the RPDOs, state machine, setpoints to the
        world (an `AxisSimulator` steps here; a shared world's port only latches them)."""
        self._count += 1
        values = self.values
        values[CYCLE_COUNTER] = self._count & 0xFFFF
        if self.faults.emcy_code and self.faults.due():
            values[FAULT_INJECTION] = self.faults.emcy_code
        if self._pdo_dirty:
            self._load_pdo_maps()
        self._latch_setpoints()
        self._advance_state_machine(values[CONTROLWORD], inject=True)
        for hook in self.before_physics:
            hook()
        self._step_physics()

    def end_cycle(self) -> None:
        """Second half of a SYNC, after the world stepped: actual values, TPDOs out."""
        self._finish_quick_stop()
        self._publish_actual_values()
        if self._operational:
            self._send_tpdos()
            self._send_event_tpdos()
        try:
            for hook in self.after_physics:
                hook()
        except Exception as error:  # the cycle's TPDOs are out: not a second set
            self.world_fault(error, tpdos_sent=True)

    def _latch_setpoints(self) -> None:
        """The RPDO data received since the last SYNC; in CSP with the target in a
        synchronous RPDO, the cycle's target as `_cyclic_target_of` says."""
        values = self.values
        ran = values[TARGET_POSITION]
        setpoint = self._received.get(TARGET_POSITION)
        values.update(self._received)
        self._received.clear()
        if self._cyclic_target and values[MODES_OF_OPERATION_DISPLAY] == CSP:
            values[TARGET_POSITION] = self._cyclic_target_of(ran, setpoint)
        else:
            self._forget_setpoints()

    def _forget_setpoints(self) -> None:
        """Start the setpoint stream anew (power-on, a mode without a cyclic target)."""
        self._target_step = 0.0
        self._missed_setpoints = 0
        self._setpoint_lag = 0
        self._last_setpoint: int | None = None

    def _cyclic_target_of(self, ran: int, setpoint: int | None) -> int:
        """CSP: this cycle's target (increments), `ran` the last cycle's, `setpoint` the one
        that came for this SYNC (None: none came).

        No setpoint: the last step again (extrapolated), `EXTRAPOLATED_CYCLES` in a row at
        most, then the target is held. A setpoint after missed cycles may be late on the
        wire: one the host meant for a SYNC the drive already ran, `lag` cycles ago (at most
        the lag before plus the cycles missed since; 0 once one comes on time). The lag is
        the whole number of steps that puts the setpoint nearest the last target plus one
        step, and the drive runs on the setpoint plus `lag` steps. The step is the host's:
        the distance between two setpoints that came for consecutive SYNCs over the cycles
        they were meant for; after missed cycles the one the drive extrapolated with (0 after
        it held), as the host assumes (`engine.runner.SentTargets`); never a distance to
        a target the drive extrapolated. So a host late by some cycles moves the target by
        one step per cycle (within half a step) and never by the cycles it was late."""
        step = self._target_step
        if setpoint is None:
            if self._missed_setpoints >= EXTRAPOLATED_CYCLES:
                return ran
            self._missed_setpoints += 1
            return _int32_wrapped(ran + step)
        missed = self._missed_setpoints
        if missed >= EXTRAPOLATED_CYCLES:
            step = 0.0  # it held: the host goes on from there
        lag = 0
        if step:
            lag = max(0, min(round((ran + step - setpoint) / step), self._setpoint_lag + missed))
        meant = 1 - (lag - self._setpoint_lag)
        if not missed and meant >= 1 and self._last_setpoint is not None:
            step = (setpoint - self._last_setpoint) / meant
        self._target_step = step
        self._last_setpoint, self._setpoint_lag, self._missed_setpoints = setpoint, lag, 0
        return _int32_wrapped(setpoint + lag * step)

    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """Keep a synchronous RPDO's values until the SYNC; an asynchronous one (254/255)
        takes effect at once (NMT operational only; EMCY 0x8210 on a length that does not
        match the mapping)."""
        if not self._operational:
            return
        codec = self._rpdo_codecs.get(can_id)  # None: a COB-ID of an earlier mapping
        if codec is None:
            return
        try:
            values = dict(zip(codec.indices, codec.layout.unpack(data)))
        except struct.error:
            self.node.emcy.send(EMCY_PDO_LENGTH, cia301.ERROR_REGISTER_GENERIC)
            return
        if can_id not in self._rpdo_events:
            self._received.update(values)
            return
        with self.lock:
            self.values.update(values)
            self._apply_command()

    def _apply_command(self) -> None:
        """The controlword and mode as they stand, between SYNCs (SDO, asynchronous RPDO):
        state machine, statusword, event-driven TPDOs."""
        self._advance_state_machine(self.values[CONTROLWORD], inject=False)
        self.values[STATUSWORD] = self._statusword()
        self._send_event_tpdos()

    def _send_event_tpdos(self) -> None:
        """Send each event-driven TPDO (254/255) whose content changed (NMT operational)."""
        if not (self._operational and self._event_tpdos):
            return
        for cob_id, (pack, fetch) in self._event_tpdos.items():
            payload = pack(*fetch(self.values))
            if self._event_payloads.get(cob_id) != payload:
                self._event_payloads[cob_id] = payload
                self.network.send_message(cob_id, payload)

    def _advance_state_machine(self, controlword: int, inject: bool) -> None:
        """Transitions on `controlword`, the mode display; with `inject` (at a SYNC) a fault
        written to 0x2030 too."""
        values = self.values
        fault_reset = controlword & ~self._previous_controlword & CW_FAULT_RESET
        self._previous_controlword = controlword
        if self.state == FAULT:
            if fault_reset:
                self._reset_fault()
        elif inject and values[FAULT_INJECTION]:
            self._fault(values[FAULT_INJECTION])
            values[FAULT_INJECTION] = 0
        else:
            state = self._transition(command_of(controlword))
            if state != self.state:
                self._enter(state)
        mode = values[MODES_OF_OPERATION]
        if mode in DRIVE_MODES:
            values[MODES_OF_OPERATION_DISPLAY] = mode

    def _transition(self, command: str) -> str:
        """The state `command` leads to (`TRANSITIONS`), by the quick-stop option code
        0x605A: code 0 disables at once (the axis coasts); codes 5–8 allow transition 16,
        back to operation enabled from a quick stop."""
        option = self.values[QUICK_STOP_OPTION_CODE]
        if self.state == QUICK_STOP_ACTIVE and command == "ENABLE OPERATION":
            return OPERATION_ENABLED if quick_stop_holds(option) else self.state
        state = TRANSITIONS.get((self.state, command), self.state)
        if state == QUICK_STOP_ACTIVE and quick_stop_ramp(option) == STOP_COAST:
            return SWITCH_ON_DISABLED
        return state

    def _enter(self, state: str) -> None:
        self.state_log.append((self._count, state))
        if state in RAMPING and self.state not in RAMPING:
            self._stop_velocity = self.simulator.velocity
            self._settling = 0
            self._stop_complete = False
        if state == OPERATION_ENABLED:
            self._profile_velocity = self.simulator.velocity
        self.state = state
        powered = state in POWERED
        if self.simulator.enabled != powered:
            self.simulator.enabled = powered

    def torque_off(self) -> None:
        """Safe torque off (the STO input, wired to an I/O module's output): a powered drive
        switches its power stage off at once (switch on disabled; in a fault reaction,
        FAULT), the axis coasting. A drive function beside CiA 402's state machine."""
        if self.state in POWERED:
            self._enter(FAULT if self.state == FAULT_REACTION else SWITCH_ON_DISABLED)

    def _fault(self, code: int, reaction: bool = False) -> None:
        """Fault with EMCY `code`: straight to FAULT, or with `reaction` through the fault
        reaction (the ramp of 0x605E, FAULT once stopped; straight to FAULT for code 0)."""
        reaction = reaction and self.values[FAULT_REACTION_OPTION_CODE] != STOP_COAST
        self._enter(FAULT_REACTION if reaction else FAULT)
        self.values[ERROR_CODE] = code
        self.values[cia301.ERROR_REGISTER] = cia301.ERROR_REGISTER_GENERIC
        self.node.emcy.send(code, cia301.ERROR_REGISTER_GENERIC)

    def _reset_fault(self) -> None:
        self._enter(SWITCH_ON_DISABLED)
        self.values[ERROR_CODE] = 0
        self.values[cia301.ERROR_REGISTER] = 0
        self._following_error = False
        self.node.emcy.reset()

    def _step_physics(self) -> None:
        """One bus cycle of the axis with the setpoints of the current state (SI units)."""
        v = self.values
        per_mille = self._newton_per_mille
        if self.state in RAMPING:
            self._step_quick_stop()
            return
        mode, velocity = v[MODES_OF_OPERATION_DISPLAY], v[TARGET_VELOCITY] * 1e-9
        if mode == PV:
            mode, velocity = CSV, self._step_profile_velocity(velocity)
        self.simulator.step_cycle(
            mode, v[TARGET_POSITION] * 1e-9, velocity,
            v[TARGET_TORQUE] * per_mille, v[VELOCITY_OFFSET] * 1e-9,
            v[TORQUE_OFFSET] * per_mille + v[FORCE_OFFSET_FINE] * 1e-3, self.tip_force)

    def _step_quick_stop(self) -> None:
        """The stop ramp (`_stop_deceleration`) in velocity control."""
        sim = self.simulator
        ramp = self._stop_deceleration() * sim.timing.cycle
        self._stop_velocity = math.copysign(max(0.0, abs(self._stop_velocity) - ramp),
                                            self._stop_velocity)
        sim.step_cycle(CSV, 0.0, self._stop_velocity, 0.0, 0.0, 0.0, self.tip_force)

    def _stop_deceleration(self) -> float:
        """m/s² of this stop: the ramp of 0x605A (quick stop) or 0x605E (fault reaction),
        0x6084 or 0x6085; at the force or voltage limit a zero velocity command at once
        (the velocity loop saturates at 0x2004)."""
        v = self.values
        ramp = (quick_stop_ramp(v[QUICK_STOP_OPTION_CODE]) if self.state == QUICK_STOP_ACTIVE
                else v[FAULT_REACTION_OPTION_CODE])
        if ramp == STOP_SLOW_DOWN_RAMP:
            return v[PROFILE_DECELERATION] * 1e-9
        return v[QUICK_STOP_DECELERATION] * 1e-9 if ramp == STOP_QUICK_RAMP else math.inf

    def _step_profile_velocity(self, target: float) -> float:
        """Profile velocity: this cycle's velocity command (m/s), ramped towards `target` at
        0x6083 when speeding up, 0x6084 when slowing down (nm/s²)."""
        current = self._profile_velocity
        slowing = abs(target) < abs(current) or target * current < 0
        ramp = self.values[PROFILE_DECELERATION if slowing else PROFILE_ACCELERATION]
        step = ramp * 1e-9 * self.simulator.timing.cycle
        self._profile_velocity = current + max(-step, min(step, target - current))
        return self._profile_velocity

    def _finish_quick_stop(self) -> None:
        """Stop complete (ramp at zero, |v| below 0x606D): switch on disabled (0x605A codes
        1–4; 5–8 stay in quick stop, the stop complete), or at the end of a fault reaction
        FAULT; a fault reaction also ends `SETTLE_CYCLES` after its ramp reached zero (a
        coupled axis may never settle inside the window)."""
        if self.state not in RAMPING or self._stop_velocity != 0.0:
            return
        self._settling += 1
        reaction = self.state == FAULT_REACTION
        settled = abs(self.simulator.velocity) * 1e9 < self.values[VELOCITY_WINDOW]
        if reaction and (settled or self._settling >= SETTLE_CYCLES):
            self._enter(FAULT)
        elif settled and quick_stop_holds(self.values[QUICK_STOP_OPTION_CODE]):
            self._stop_complete = True
        elif settled and not reaction:
            self._enter(SWITCH_ON_DISABLED)

    def _next_noise(self) -> tuple[float, float]:
        """This cycle's measurement noise (force N, velocity m/s) from the pre-drawn block."""
        if not self._noise_block:  # drawn in blocks, kept as a reversed list: pop() is O(1)
            scale = (self.noise.force, self.noise.velocity)
            self._noise_block = (self._rng.normal(size=(NOISE_BLOCK, 2)) * scale).tolist()[::-1]
        force, velocity = self._noise_block.pop()
        return force, velocity

    def _publish_actual_values(self) -> None:
        v = self.values
        position, mean_velocity, mean_force = self.simulator.reported()
        force_noise, velocity_noise = self._next_noise()
        force = mean_force + force_noise  # cycle means, as a drive filters them
        v[POSITION_ACTUAL] = position = _int32_wrapped(position * 1e9)
        v[VELOCITY_ACTUAL] = _saturated((mean_velocity + velocity_noise) * 1e9, INT32_MAX)
        v[FORCE_ACTUAL] = _saturated(force * 1e3, INT32_MAX)
        v[TORQUE_ACTUAL] = _saturated(force / self._newton_per_mille, INT16_MAX)
        if self._objects is not None:
            v.update(self._objects.actual())
        v[FOLLOWING_ERROR_ACTUAL] = error = v[TARGET_POSITION] - position
        window = v[FOLLOWING_ERROR_WINDOW]
        if (self.state == OPERATION_ENABLED and v[MODES_OF_OPERATION_DISPLAY] == CSP
                and window != FOLLOWING_ERROR_OFF and abs(error) > window):
            self._following_error = True
            self._fault(EMCY_FOLLOWING_ERROR)
        v[STATUSWORD] = self._statusword()

    def _statusword(self) -> int:
        """0x6041: the state's bits, remote; following the command in operation enabled;
        target reached (bit 10) in quick stop once the ramp has been at zero for
        `STOP_SETTLE_CYCLES` without the axis settling inside 0x606D (the quick stop is complete:
        the host may disable the drive, which a coupled axis that never settles needs; an
        axis that settles switches itself off first)."""
        word = STATE_BITS[self.state] | SW_REMOTE
        if self.state == OPERATION_ENABLED:
            word |= SW_FOLLOWS_COMMAND
        elif (self.state == QUICK_STOP_ACTIVE and self._stop_velocity == 0.0
              and (self._settling >= STOP_SETTLE_CYCLES or self._stop_complete)):
            word |= SW_TARGET_REACHED
        if self._following_error:
            word |= SW_FOLLOWING_ERROR
        return word

    def _send_tpdos(self) -> None:
        """The synchronous TPDOs due at this SYNC, each a new frame (a bus or a listener may
        keep it) sent without canopen's per-frame call (`protocols.canbus.send_frames`)."""
        values = self.values
        count = self._count
        send_frames(self.network, [
            can.Message(arbitration_id=cob_id, is_extended_id=cob_id > 0x7FF,
                        data=pack(*fetch(values)), check=False)
            for cob_id, trans_type, pack, fetch in self._tpdos
            if trans_type <= 1 or count % trans_type == 0])
