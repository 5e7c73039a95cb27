"""Fault injection in the simulated peers: what a real bench does wrong, protocol-true.

A ``[bench.world.faults]`` table (or `feedbench sim --fault KEY=VALUE`) switches faults on
from the SYNC count `at_cycle` (virtual time: the same cycle in every run of a plan):

- CAN, on the simulated nodes' own bus (`FaultyBus`, between their canopen network and the
  wire, so a lost frame is not sent and a deaf node does not hear it): ``can_loss_share``
  (that share of the frames they send lost, drawn per frame from the seed),
  ``can_burst_s`` (every frame they send lost for that long, wall clock),
  ``sync_timeout_s`` (they hear no SYNC for that long: their TPDOs stop), ``pdo_timeout_s``
  (they send no PDO for that long, hearing everything), ``bus_off_s`` (bus-off: nothing
  sent or heard for that long, the drives run their fault reaction, EMCY 0x8140 after the
  recovery);
- the drive: ``emcy_code`` (a real EMCY frame and FAULT at that SYNC, through the drive's
  own fault injection object 0x2030);
- Modbus (every simulated Modbus device): ``modbus = "timeout"`` (requests unanswered) or
  ``"exception"`` (answered with exception ``modbus_exception_code``);
- the serial DAQ: ``serial = "crc"`` (``serial_frames`` data frames with a flipped byte),
  ``"desync"`` (that many frames cut in half: the parser resynchronises on the next sync
  word) or ``"unplug"`` (the device vanishes).

Host-side faults (SIGINT, SIGKILL, a full disk) are not the peers' to inject: the fault
matrix (tests/test_fault_matrix*.py, docs/faults.md) sends the signals and limits the file
size itself.
"""

from __future__ import annotations

import random
import threading
import time
import tomllib
from typing import Any, Callable, Mapping

import can

from feedbench.config import ConfigError, Field, non_negative, one_of, validate_table
from feedbench.protocols.cia301 import SYNC_COB_ID

EMCY_BUS_OFF_RECOVERED = 0x8140
"""CiA 301 EMCY error code: recovered from bus-off."""


EXCEPTION_CODES = (1, 2, 3, 4, 5, 6, 8, 10, 11)
"""The exception codes of the Modbus application protocol."""


def share(value: Any) -> str | None:
    """Check: a number within [0, 1]."""
    return None if 0.0 <= value <= 1.0 else f": must be within 0..1 (got {value})"


FAULT_SCHEMA = {
    "at_cycle": Field(int, 0, "SYNC count from which the faults below act (0: no fault)",
                      non_negative),
    "seed": Field(int, 0, "seed of the random frame loss", non_negative),
    "can_loss_share": Field(float, 0.0, "share of the simulated nodes' CAN frames lost "
                            "(0..1)", share),
    "can_burst_s": Field(float, 0.0, "every frame the nodes send lost for this long (wall s)",
                         non_negative),
    "sync_timeout_s": Field(float, 0.0, "the nodes hear no SYNC for this long (wall s)",
                            non_negative),
    "pdo_timeout_s": Field(float, 0.0, "the nodes send no PDO for this long (wall s)",
                           non_negative),
    "bus_off_s": Field(float, 0.0, "the nodes are bus-off for this long (wall s): fault "
                       "reaction, EMCY 0x8140 after the recovery", non_negative),
    "emcy_code": Field(int, 0, "EMCY error code the drive faults with (0: none)",
                       non_negative),
    "modbus": Field(str, "", "Modbus devices: timeout (no answer) or exception",
                    one_of("", "timeout", "exception")),
    "modbus_exception_code": Field(int, 4, "exception code answered (modbus = exception)",
                                   lambda code: None if code in EXCEPTION_CODES else
                                   f": must be a Modbus exception code {EXCEPTION_CODES}"),
    "serial": Field(str, "", "serial DAQ: crc (flipped bytes), desync (frames cut in half) "
                    "or unplug", one_of("", "crc", "desync", "unplug")),
    "serial_frames": Field(int, 1, "data frames damaged (serial = crc or desync)",
                           non_negative),
}


TRIGGERS = ("can_loss_share", "can_burst_s", "sync_timeout_s", "pdo_timeout_s",
            "bus_off_s", "emcy_code", "modbus", "serial")
"""The keys that switch a fault on (the others say when and how)."""


class Faults:
    """The faults of a ``[bench.world.faults]`` table (validated here, errors name the field)
    and the shared count of SYNCs the simulated nodes heard (`cycle`), which times them."""

    def __init__(self, table: Mapping[str, Any] | None = None,
                 path: str = "bench.world.faults") -> None:
        self.settings = validate_table(table or {}, FAULT_SCHEMA, path)
        active = [key for key in TRIGGERS if self.settings[key]]
        if active and not self.settings["at_cycle"]:
            raise ConfigError(f"{path}.at_cycle: {active[0]} needs the SYNC count it starts at")
        self.active = active
        self.cycle = 0
        self._sent_in_cycle: dict[int, int] = {}
        self._until = {key: 0.0 for key in ("can_burst_s", "sync_timeout_s", "pdo_timeout_s",
                                            "bus_off_s")}
        self._bus_off_listeners: list[Callable[[bool], None]] = []
        self._recovery: threading.Timer | None = None
        self._armed = False

    def __getattr__(self, key: str) -> Any:
        try:
            return self.__dict__["settings"][key]
        except KeyError:
            raise AttributeError(key) from None

    def started(self) -> bool:
        """True from the SYNC `at_cycle` on (never without a fault)."""
        return bool(self.active) and self.cycle >= self.at_cycle

    def due(self) -> bool:
        """True in the SYNC cycle `at_cycle` itself."""
        return bool(self.active) and self.cycle == self.at_cycle

    def bus(self, bus: can.BusABC) -> can.BusABC:
        """`bus` as the simulated nodes see it: a `FaultyBus` (which counts the SYNCs that
        time every fault) if any fault is set."""
        return FaultyBus(bus, self) if self.active else bus

    def on_bus_off(self, listener: Callable[[bool], None]) -> None:
        """Call `listener(True)` when the bus goes off, `listener(False)` once recovered."""
        self._bus_off_listeners.append(listener)

    # -- CAN: decided per frame by `FaultyBus` -------------------------------------------

    def heard(self, msg: can.Message) -> bool:
        """Whether the nodes receive `msg`. The SYNC `at_cycle` starts the timed faults (it
        is the first one a deaf or bus-off node misses); a SYNC heard counts the cycle."""
        now = time.monotonic()
        is_sync = msg.arbitration_id == SYNC_COB_ID
        if is_sync and self.cycle + 1 == self.at_cycle and not self._armed:
            self._start_timers(now)
        if self._timed("bus_off_s", now) or is_sync and self._timed("sync_timeout_s", now):
            return False
        if is_sync:
            self.cycle += 1
            self._sent_in_cycle.clear()
        return True

    def sent(self, msg: can.Message) -> bool:
        """Whether a frame the nodes send reaches the wire."""
        now = time.monotonic()
        if self._timed("bus_off_s", now):
            return False
        if not self.started():
            return True
        if self._timed("can_burst_s", now):
            return False
        if self._timed("pdo_timeout_s", now) and _is_pdo(msg.arbitration_id):
            return False
        return not (self.can_loss_share and self._chance(msg.arbitration_id) < self.can_loss_share)

    def _chance(self, can_id: int) -> float:
        """A number in [0, 1) drawn for one frame: the same for the same seed, SYNC count,
        COB-ID and count of that COB-ID's frames in the cycle, whatever the order the nodes'
        threads send in (a run loses the same frames; a repeated SDO answer is drawn anew)."""
        nth = self._sent_in_cycle[can_id] = self._sent_in_cycle.get(can_id, 0) + 1
        return random.Random(f"{self.seed}:{self.cycle}:{can_id}:{nth}").random()

    def _timed(self, key: str, now: float) -> bool:
        return now < self._until[key]

    def _start_timers(self, now: float) -> None:
        """At `at_cycle`: the timed faults begin (bus-off tells its listeners)."""
        self._armed = True
        for key in self._until:
            if self.settings[key]:
                self._until[key] = now + self.settings[key]
        if self.bus_off_s:
            self._bus_off(True)
            self._recovery = threading.Timer(self.bus_off_s, self._bus_off, (False,))
            self._recovery.daemon = True
            self._recovery.start()

    def _bus_off(self, off: bool) -> None:
        for listener in self._bus_off_listeners:
            listener(off)

    # -- Modbus and the serial DAQ -------------------------------------------------------

    def modbus_answer(self) -> str:
        """What the Modbus devices do with a request now: "" (answer), timeout, exception."""
        return self.modbus if self.started() else ""

    def serial_damage(self) -> str:
        """What happens to this cycle's DAQ frames: "" or crc, desync, unplug."""
        if not self.serial or not self.started():
            return ""
        if self.serial == "unplug":
            return "unplug" if self.due() else ""
        return self.serial if self.cycle < self.at_cycle + self.serial_frames else ""

    def close(self) -> None:
        """Cancel a pending bus-off recovery."""
        if self._recovery is not None:
            self._recovery.cancel()


NO_FAULTS = Faults()
"""A world without faults."""


def world_faults(world: Mapping[str, Any]) -> Faults:
    """The faults of a ``[bench.world]`` table (its ``faults`` table; none without one)."""
    return Faults(world.get("faults", {})) if world.get("faults") else NO_FAULTS


def _is_pdo(can_id: int) -> bool:
    """A PDO COB-ID (CiA 301 predefined set: 0x180–0x57F)."""
    return 0x180 <= can_id < 0x580


class FaultyBus(can.BusABC):
    """A python-can bus between the simulated nodes' network and `bus` that loses the frames
    `faults` says are lost, in both directions (`Faults.sent`, `Faults.heard`)."""

    def __init__(self, bus: can.BusABC, faults: Faults) -> None:
        self.bus = bus
        self.faults = faults
        super().__init__(channel=bus.channel_info)
        self.channel_info = f"{bus.channel_info} with faults"

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.faults.sent(msg):
            self.bus.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        msg = self.bus.recv(timeout)
        if msg is not None and not self.faults.heard(msg):
            return None, False
        return msg, False

    def shutdown(self) -> None:
        self.faults.close()
        self.bus.shutdown()
        super().shutdown()


def with_fault_options(bench: Mapping[str, Any], options: list[str]) -> dict[str, Any]:
    """A ``[bench]`` table with `feedbench sim --fault KEY=VALUE` options added to its
    world's faults (checked: a bad one is a `ConfigError` naming ``--fault KEY``)."""
    world = dict(bench["world"])
    world["faults"] = {**world.get("faults", {}), **parse_fault_options(options)}
    Faults(world["faults"], "--fault")
    return {**bench, "world": world}


def parse_fault_options(options: list[str]) -> dict[str, Any]:
    """`feedbench sim --fault KEY=VALUE` options as a faults table (values as TOML)."""
    table: dict[str, Any] = {}
    for option in options:
        key, sep, value = option.partition("=")
        if not sep:
            raise ConfigError(f"--fault {option}: give KEY=VALUE (keys: "
                              f"{', '.join(FAULT_SCHEMA)})")
        try:
            table[key.strip()] = tomllib.loads(f"v = {value.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            table[key.strip()] = value.strip()
    return table
