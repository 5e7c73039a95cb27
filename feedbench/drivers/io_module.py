"""Host driver of the CiA 401 I/O module that drives the tool-tip exciters.

The outputs go out by RPDO before the SYNC (`transmit`), so a command takes effect in the
same bus cycle as the drive's setpoints; a PDO is sent when its content changed (the module
keeps applying the last one it received). Wiring and scaling: `feedbench.protocols.cia401`.
"""

from __future__ import annotations

import canopen

from feedbench.drivers.cia402 import HOST_CONSUMER_MS
from feedbench.protocols import cia301, cia401
from feedbench.protocols.canbus import remote_node


class IoModuleError(RuntimeError):
    """The module did not answer or is not a CiA 401 device."""


class IoModule:
    """Node `node_id` on `network`; `configure()` checks it and starts it (NMT operational)."""

    def __init__(self, network: canopen.Network, node_id: int) -> None:
        self.network = network
        self.node = remote_node(network, node_id, canopen.ObjectDictionary())
        self._analog = [0] * cia401.ANALOG_CHANNELS
        self._digital = 0
        self._torque_off = 0
        self._sent: dict[int, bytes] = {}

    def configure(self) -> None:
        """Read the device type by SDO (profile 401 expected), tell the module to watch the
        host's heartbeat (0x1016 entry 1, `HOST_CONSUMER_MS`; a module without the object
        is left as it is), then NMT operational."""
        try:
            raw = self.node.sdo.upload(cia301.DEVICE_TYPE, 0)
        except (canopen.SdoCommunicationError, canopen.SdoAbortedError) as error:
            raise IoModuleError(f"I/O module node {self.node.id}: {error}") from error
        device_type = int.from_bytes(raw, "little")
        if device_type & 0xFFFF != cia401.PROFILE:
            raise IoModuleError(f"node {self.node.id} is not a CiA 401 device "
                                f"(device type 0x{device_type:08X})")
        entry = cia301.consumer_entry(cia301.HOST_NODE_ID, HOST_CONSUMER_MS)
        try:
            self.node.sdo.download(cia301.CONSUMER_HEARTBEAT_TIME, 1, entry.to_bytes(4, "little"))
        except canopen.SdoAbortedError:
            pass  # no consumer heartbeat on this module
        self.node.nmt.state = "OPERATIONAL"

    def set_force(self, channel: int, force: float) -> None:
        """Command `force` (N) on analog output `channel` (saturates at ±10 V)."""
        self._analog[channel] = cia401.analog_counts(force, channel)

    def set_digital(self, bits: int) -> None:
        """The eight digital outputs as a bit field."""
        self._digital = bits & 0xFF

    def transmit(self, every: bool = False) -> None:
        """Send the RPDOs whose content changed since they were last sent (`every`: all),
        applied by the module at the next SYNC."""
        node_id = self.node.id
        digital = self._digital | self._torque_off
        frames = {cia401.RPDO_DIGITAL + node_id: cia401.DIGITAL_LAYOUT.pack(digital),
                  cia401.RPDO_ANALOG + node_id: cia401.ANALOG_LAYOUT.pack(*self._analog)}
        for cob_id, data in frames.items():
            if every or self._sent.get(cob_id) != data:
                self.network.send_message(cob_id, data)
                self._sent[cob_id] = data

    def safe_torque_off(self) -> str:
        """Set the drives' safe-torque-off output (`cia401.SAFE_TORQUE_OFF`) at once, held
        whatever the other outputs do from now on; what was set, for a line."""
        self._torque_off = cia401.SAFE_TORQUE_OFF
        self.transmit(every=True)
        return f"I/O module node {self.node.id} (digital output 0x{cia401.SAFE_TORQUE_OFF:02X})"

    def zero(self) -> None:
        """All outputs off, sent at once."""
        self._analog = [0] * cia401.ANALOG_CHANNELS
        self._digital = 0
        self.transmit(every=True)
