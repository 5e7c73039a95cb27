"""A simulated CiA 401 I/O module: the outputs that drive the tool-tip exciters.

A canopen `LocalNode` (SDO server, NMT slave) on the simulated drive's `canopen.Network`, so
one receive thread handles the module's RPDOs and the drive's SYNC in bus order: outputs
received before a SYNC are the ones the world applies in that bus cycle (synchronous RPDOs,
CiA 301). PDOs are taken only in NMT operational. The predefined connection set and the
wiring are in `feedbench.protocols.cia401`. Its watchdog (`sim_backends.watchdog`: heartbeat
consumer 0x1016, SYNC loss 0x2021 × 0x1006) guards the outputs while any is set: a loss
sets them all to 0 (the exciters stop) and sends the EMCY.
"""

from __future__ import annotations

import struct
import threading

import canopen
from canopen.objectdictionary import ODArray, ODVariable, ObjectDictionary, datatypes

from feedbench.protocols import cia301, cia401
from feedbench.sim_backends.eds import consumer_heartbeat
from feedbench.sim_backends.watchdog import Watchdog, check_subindex


def _variable(name: str, index: int, subindex: int, data_type: int, access: str,
              default: int) -> ODVariable:
    var = ODVariable(name, index, subindex)
    var.data_type, var.access_type, var.default = data_type, access, default
    var.pdo_mappable = index >= cia301.PROFILE_FIRST
    return var


def _array(name: str, index: int, data_type: int, count: int) -> ODArray:
    array = ODArray(name, index)
    array.add_member(_variable("Number of entries", index, 0, datatypes.UNSIGNED8, "ro", count))
    for sub in range(1, count + 1):
        array.add_member(_variable(f"{name} {sub}", index, sub, data_type, "rw", 0))
    return array


def object_dictionary(cycle_s: float = 1e-3) -> ObjectDictionary:
    """Device type, error register, cycle period (`cycle_s`), consumer heartbeat entries,
    heartbeat time (0: none), SYNC loss limit (0: off), digital outputs 0x6200 and analog
    outputs 0x6411."""
    od = ObjectDictionary()
    od.device_information.product_name = "Simulated CiA 401 I/O module (exciters)"
    od.add_object(_variable("Device type", cia301.DEVICE_TYPE, 0, datatypes.UNSIGNED32, "ro",
                            cia401.DEVICE_TYPE))
    od.add_object(_variable("Error register", cia301.ERROR_REGISTER, 0, datatypes.UNSIGNED8,
                            "ro", 0))
    od.add_object(_variable("Communication cycle period", cia301.CYCLE_PERIOD, 0,
                            datatypes.UNSIGNED32, "ro", round(cycle_s * 1e6)))
    consumer_heartbeat(od)
    od.add_object(_variable("Producer heartbeat time", cia301.HEARTBEAT_TIME, 0,
                            datatypes.UNSIGNED16, "rw", 0))
    od.add_object(_variable("SYNC loss limit", cia301.SYNC_LOSS_LIMIT, 0, datatypes.UNSIGNED8,
                            "rw", 0))
    od.add_object(_array("Write digital output 8 bit", cia401.DIGITAL_OUTPUTS,
                         datatypes.UNSIGNED8, 1))
    od.add_object(_array("Write analog output 16 bit", cia401.ANALOG_OUTPUTS,
                         datatypes.INTEGER16, cia401.ANALOG_CHANNELS))
    return od


class SimulatedIoModule:
    """The module as node `node_id` on `network` (the simulated drive's network).

    `digital` (bit field) and `analog` (INTEGER16 per channel) hold the outputs received
    last; the world reads them in the drive's SYNC handler. SDO reads of 0x6200 / 0x6411
    return them. `cycle_s`: the bus cycle (0x1006, s).
    """

    def __init__(self, network: canopen.Network, node_id: int, cycle_s: float = 1e-3) -> None:
        self.digital = 0
        self.analog = [0] * cia401.ANALOG_CHANNELS
        self.node = canopen.LocalNode(node_id, object_dictionary(cycle_s))
        network.add_node(self.node)
        self.node.add_read_callback(self._on_sdo_read)
        self.node.add_write_callback(self._on_sdo_write)
        self.watchdog = Watchdog(network, threading.RLock(), self._lose_connection,
                                 guards=lambda: bool(self.digital or any(self.analog)))
        self.watchdog.cycle_s = cycle_s
        network.subscribe(cia301.SYNC_COB_ID, self._on_sync)
        network.subscribe(cia401.RPDO_DIGITAL + node_id, self._on_digital)
        network.subscribe(cia401.RPDO_ANALOG + node_id, self._on_analog)
        self.node.nmt.state = "PRE-OPERATIONAL"

    @property
    def operational(self) -> bool:
        """NMT operational: PDOs are taken."""
        return self.node.nmt.state == "OPERATIONAL"

    def analog_force(self, channel: int) -> float:
        """The force (N) analog output `channel` commands (the amplifier's gain applied)."""
        return cia401.analog_force(self.analog[channel], channel)

    def _on_digital(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.operational and len(data) == cia401.DIGITAL_LAYOUT.size:
            (self.digital,) = cia401.DIGITAL_LAYOUT.unpack(data)

    def _on_analog(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.operational:
            try:
                self.analog = list(cia401.ANALOG_LAYOUT.unpack(data))
            except struct.error:
                pass  # a frame of the wrong length is ignored, as by the hardware

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self.watchdog.lock:
            loss = self.watchdog.on_sync()
            if loss is not None:
                self._lose_connection(*loss)

    def _lose_connection(self, code: int, reason: str) -> None:
        """A lost heartbeat or SYNC: every output to 0, EMCY `code`."""
        self.digital = 0
        self.analog = [0] * cia401.ANALOG_CHANNELS
        self.node.emcy.send(code, cia301.ERROR_REGISTER_GENERIC)

    def _on_sdo_write(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        check_subindex(subindex, od)
        if index == cia301.CONSUMER_HEARTBEAT_TIME and subindex:
            self.watchdog.set_entry(subindex, od.decode_raw(data))
        elif index == cia301.SYNC_LOSS_LIMIT:
            self.watchdog.sync_limit = od.decode_raw(data)

    def _on_sdo_read(self, index: int, subindex: int, od: ODVariable) -> int | None:
        check_subindex(subindex, od)
        if index == cia401.DIGITAL_OUTPUTS and subindex == 1:
            return self.digital
        if index == cia401.ANALOG_OUTPUTS and 1 <= subindex <= cia401.ANALOG_CHANNELS:
            return self.analog[subindex - 1]
        return None
