"""CiA 401 generic I/O module that drives the bench's tool-tip exciters, shared by both ends.

The module (a CANopen node, profile 401) uses the predefined connection set, synchronous:
an output received by RPDO is applied at the next SYNC, in the same bus cycle as the drive's
setpoints. Wiring of the bench:

- RPDO1 (0x200 + node): 0x6200 sub 1, UNSIGNED8, the digital outputs; bit 0 fires the
  impact hammer (rising edge), bit 7 is the drives' safe torque off (set: torque off).
- RPDO2 (0x300 + node): 0x6411 sub 1–4, INTEGER16, the analog outputs (±10 V = ±32767):
  1 shaker amplifier, 2 inertial-actuator amplifier, 3 hammer level, 4 spare.

Amplifier gains: 10 V is `FULL_SCALE_N` of each output (shaker and actuator: force command,
hammer: peak force of the next hit).
"""

from __future__ import annotations

import struct

from feedbench.protocols import cia301

DEVICE_TYPE = 0x000F0191
"""0x1000: profile 401 (0x0191), digital inputs and outputs, analog inputs and outputs."""
PROFILE = 0x0191
RPDO_DIGITAL = cia301.RPDO_COB_BASE
RPDO_ANALOG = cia301.RPDO_COB_BASE + 0x100
"""COB-IDs of RPDO 1 and 2 without the node id."""
DIGITAL_OUTPUTS = 0x6200
ANALOG_OUTPUTS = 0x6411
ANALOG_CHANNELS = 4
ANALOG_MAX = 32767
HAMMER_FIRE = 0x01
"""Digital output bit that fires the impact hammer (rising edge)."""
SAFE_TORQUE_OFF = 0x80
"""Digital output bit wired to the drives' safe-torque-off input: while set, their power
stage is off whatever their controlword (the last step of an escalated safe stop)."""

SHAKER, ACTUATOR, HAMMER_LEVEL = 0, 1, 2
"""Analog output channels (0-based; object sub-index = channel + 1)."""
EXCITER_CHANNELS = {"shaker": SHAKER, "actuator": ACTUATOR, "hammer": HAMMER_LEVEL}
FULL_SCALE_N = {SHAKER: 500.0, ACTUATOR: 500.0, HAMMER_LEVEL: 2000.0}
"""Force (N) at +10 V on each analog output."""

ANALOG_LAYOUT = struct.Struct("<4h")
DIGITAL_LAYOUT = struct.Struct("<B")


def analog_counts(force: float, channel: int) -> int:
    """The INTEGER16 value of an analog output that commands `force` (N), saturated."""
    counts = round(force / FULL_SCALE_N[channel] * ANALOG_MAX)
    return max(-ANALOG_MAX, min(ANALOG_MAX, counts))


def analog_force(counts: int, channel: int) -> float:
    """The force (N) an analog output value commands."""
    return counts / ANALOG_MAX * FULL_SCALE_N[channel]
