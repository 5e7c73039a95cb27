"""Modbus register maps of the spindle inverter and the load-cell amplifier.

The code form of `docs/modbus_registers.md`, the one place they are documented (a test
checks that the two agree); shared by the host drivers and the simulated devices. Both
devices use holding registers only; 32-bit values span two registers, high word first.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Sequence

from pymodbus.client.mixin import ModbusClientMixin

READ_HOLDING_REGISTERS = 0x03
WRITE_SINGLE_REGISTER = 0x06
WRITE_MULTIPLE_REGISTERS = 0x10
FUNCTION_CODES = (READ_HOLDING_REGISTERS, WRITE_SINGLE_REGISTER, WRITE_MULTIPLE_REGISTERS)
"""The function codes both devices serve; any other is answered with exception 1 (ILLEGAL
FUNCTION), its function byte the code | 0x80."""

INTEGER_LIMITS = {
    "UINT16": (0, 2**16 - 1),
    "INT16": (-(2**15), 2**15 - 1),
    "UINT32": (0, 2**32 - 1),
    "INT32": (-(2**31), 2**31 - 1),
}
"""Raw value range of each register type (the device saturates, the host refuses)."""


@dataclass(frozen=True)
class Register:
    """One value in a device's holding registers: value = raw · `scale` in `unit`."""

    name: str
    address: int
    datatype: str = "UINT16"
    scale: float = 1.0
    unit: str = "-"
    writable: bool = False

    @property
    def count(self) -> int:
        """Number of 16-bit registers the value spans."""
        return ModbusClientMixin.DATATYPE[self.datatype].value[1]

    def to_raw(self, value: float, saturate: bool = False) -> int:
        """Engineering value → raw integer; out of range: clipped if `saturate`, else error."""
        raw = round(value / self.scale)
        low, high = INTEGER_LIMITS[self.datatype]
        if saturate:
            return min(max(raw, low), high)
        if not low <= raw <= high:
            raise ValueError(f"{self.name}: {value} {self.unit} outside "
                             f"{low * self.scale}…{high * self.scale} {self.unit}")
        return raw

    def encode(self, value: float, saturate: bool = False) -> list[int]:
        """Engineering value → register words (high word first)."""
        return ModbusClientMixin.convert_to_registers(
            self.to_raw(value, saturate), ModbusClientMixin.DATATYPE[self.datatype])

    def decode(self, words: Sequence[int]) -> float:
        """Register words (high word first) → engineering value."""
        raw = ModbusClientMixin.convert_from_registers(
            list(words), ModbusClientMixin.DATATYPE[self.datatype])
        return raw * self.scale


@dataclass(frozen=True)
class RegisterMap:
    """A device's registers, contiguous from `first` to `end` (exclusive)."""

    device: str
    registers: tuple[Register, ...]

    def __getitem__(self, name: str) -> Register:
        for register in self.registers:
            if register.name == name:
                return register
        raise KeyError(f"{self.device} has no register {name}")

    @property
    def first(self) -> int:
        """Lowest address."""
        return min(register.address for register in self.registers)

    @property
    def end(self) -> int:
        """One past the highest address."""
        return max(register.address + register.count for register in self.registers)

    def decode_block(self, words: Sequence[int]) -> dict[str, float]:
        """All values from the words of the whole block (`first` … `end`)."""
        return {register.name: register.decode(
            words[register.address - self.first:register.address - self.first + register.count])
            for register in self.registers}


class InverterFault(enum.IntEnum):
    """Codes in the inverter's FAULT_CODE register."""

    NONE = 0
    OVERSPEED_SETPOINT = 1  # a speed setpoint above MAX_SPEED was written
    EXTERNAL = 2  # tripped from outside (the simulated bench's fault injection)


INVERTER_CONTROL_RUN = 0x0001
INVERTER_CONTROL_FAULT_RESET = 0x0080  # self-clearing
INVERTER_STATUS_RUNNING = 0x0001  # actual speed ≠ 0
INVERTER_STATUS_AT_SPEED = 0x0002  # running and actual speed = setpoint
INVERTER_STATUS_RUN_COMMANDED = 0x0004
INVERTER_STATUS_FAULT = 0x0008

INVERTER_MAP = RegisterMap("spindle inverter", (
    Register("CONTROL", 0, "UINT16", writable=True),
    Register("STATUS", 1, "UINT16"),
    Register("SPEED_SETPOINT", 2, "UINT32", 0.01, "rpm", writable=True),
    Register("SPEED_ACTUAL", 4, "INT32", 0.01, "rpm"),
    Register("RAMP_RATE", 6, "UINT16", 0.1, "rpm/s", writable=True),
    Register("FAULT_CODE", 7, "UINT16"),
    Register("FEED_OVERRIDE", 8, "UINT16", 0.1, "%", writable=True),
    Register("MAX_SPEED", 9, "UINT16", 1.0, "rpm"),
))

LOAD_CELL_STATUS_OVERLOAD = 0x0001  # the latest sample is beyond ±RANGE
LOAD_CELL_STATUS_OVERLOAD_LATCHED = 0x0002  # a sample was beyond ±RANGE since the last clear
LOAD_CELL_CONTROL_CLEAR_OVERLOAD = 0x0001  # self-clearing

LOAD_CELL_MAP = RegisterMap("load-cell amplifier", (
    Register("FORCE_COUNTS", 0, "INT32", 1.0, "count"),
    Register("STATUS", 2, "UINT16"),
    Register("CONTROL", 3, "UINT16", writable=True),
    Register("RANGE", 4, "UINT32", 1.0, "N", writable=True),
    Register("ADC_BITS", 6, "UINT16", 1.0, "bit"),
))


def load_cell_resolution(range_N: float, adc_bits: int) -> float:
    """ADC step in N: a bipolar `adc_bits` converter spans −range … +range."""
    return 2.0 * range_N / 2**adc_bits
