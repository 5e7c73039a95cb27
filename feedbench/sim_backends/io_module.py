"""A simulated CiA 401 I/O module: the outputs that drive the tool-tip exciters.

A canopen `LocalNode` (SDO server, NMT slave) on the simulated drive's `canopen.Network`, so
one receive thread handles the module's RPDOs and the drive's SYNC in bus order: outputs
received before a SYNC are the ones the world applies in that bus cycle (synchronous RPDOs,
CiA 301). PDOs are taken only in NMT operational. The predefined connection set and the
wiring are in `feedbench.protocols.cia401`.
"""

from __future__ import annotations

import struct

import canopen
from canopen.objectdictionary import ODArray, ODVariable, ObjectDictionary, datatypes

from feedbench.protocols import cia301, cia401


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


def object_dictionary() -> ObjectDictionary:
    """Device type, error register, heartbeat time (0: none), digital outputs 0x6200 and
    analog outputs 0x6411."""
    od = ObjectDictionary()
    od.device_information.product_name = "Simulated CiA 401 I/O module (exciters)"
    od.add_object(_variable("Device type", cia301.DEVICE_TYPE, 0, datatypes.UNSIGNED32, "ro",
                            cia401.DEVICE_TYPE))
    od.add_object(_variable("Error register", cia301.ERROR_REGISTER, 0, datatypes.UNSIGNED8,
                            "ro", 0))
    od.add_object(_variable("Producer heartbeat time", cia301.HEARTBEAT_TIME, 0,
                            datatypes.UNSIGNED16, "rw", 0))
    od.add_object(_array("Write digital output 8 bit", cia401.DIGITAL_OUTPUTS,
                         datatypes.UNSIGNED8, 1))
    od.add_object(_array("Write analog output 16 bit", cia401.ANALOG_OUTPUTS,
                         datatypes.INTEGER16, cia401.ANALOG_CHANNELS))
    return od


class SimulatedIoModule:
    """The module as node `node_id` on `network` (the simulated drive's network).

    `digital` (bit field) and `analog` (INTEGER16 per channel) hold the outputs received
    last; the world reads them in the drive's SYNC handler. SDO reads of 0x6200 / 0x6411
    return them.
    """

    def __init__(self, network: canopen.Network, node_id: int) -> None:
        self.digital = 0
        self.analog = [0] * cia401.ANALOG_CHANNELS
        self.node = canopen.LocalNode(node_id, object_dictionary())
        network.add_node(self.node)
        self.node.add_read_callback(self._on_sdo_read)
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

    def _on_sdo_read(self, index: int, subindex: int, od: object) -> int | None:
        if index == cia401.DIGITAL_OUTPUTS and subindex == 1:
            return self.digital
        if index == cia401.ANALOG_OUTPUTS and 1 <= subindex <= cia401.ANALOG_CHANNELS:
            return self.analog[subindex - 1]
        return None
