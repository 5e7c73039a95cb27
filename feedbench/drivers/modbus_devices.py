"""Host drivers of the Modbus devices: a spindle inverter and a load-cell amplifier.

Both speak Modbus over pymodbus's synchronous client (TCP, or RTU on a serial line), one
client per connection shared by the devices behind it (each has its own device id). The
register maps below are the code form of `docs/modbus_registers.md`, the one place they are
documented (a test checks that the two agree). Both devices use holding registers only:
function code 3 reads, 6 / 16 write, 32-bit values span two registers, high word first.

Every failed request raises `DeviceError` naming the device, the register and the Modbus
exception code; an inverter fault raises `InverterFaultError` with the fault code.
Engineering units on this API are the devices' own (rpm, rpm/s, N); the feed override is a
fraction (1.0 = 100 %).
"""

from __future__ import annotations

import enum
from typing import Callable, NamedTuple, Sequence

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.client.base import ModbusBaseSyncClient
from pymodbus.constants import ExcCodes
from pymodbus.exceptions import ModbusException
from pymodbus.framer import FramerType
from pymodbus.pdu import ModbusPDU

from feedbench.protocols.modbus_registers import (  # noqa: F401  (re-exported API)
    INTEGER_LIMITS,
    INVERTER_CONTROL_FAULT_RESET,
    INVERTER_CONTROL_RUN,
    INVERTER_MAP,
    INVERTER_STATUS_AT_SPEED,
    INVERTER_STATUS_FAULT,
    INVERTER_STATUS_RUNNING,
    INVERTER_STATUS_RUN_COMMANDED,
    InverterFault,
    LOAD_CELL_CONTROL_CLEAR_OVERLOAD,
    LOAD_CELL_MAP,
    LOAD_CELL_STATUS_OVERLOAD,
    LOAD_CELL_STATUS_OVERLOAD_LATCHED,
    Register,
    RegisterMap,
    load_cell_resolution,
)


def _code_name(codes: type[enum.IntEnum], code: int) -> str:
    try:
        return codes(code).name
    except ValueError:
        return "unknown"


class DeviceError(RuntimeError):
    """A Modbus request failed; `exception_code` is the device's answer (None: no answer)."""

    def __init__(self, message: str, exception_code: int | None = None):
        super().__init__(message)
        self.exception_code = exception_code


class InverterFaultError(DeviceError):
    """The inverter is in fault; `fault_code` is its FAULT_CODE register."""

    def __init__(self, device_id: int, fault_code: int):
        super().__init__(f"spindle inverter (id {device_id}) in fault: "
                         f"code {fault_code} {_code_name(InverterFault, fault_code)}")
        self.fault_code = fault_code


MODBUS_TIMEOUT_S = 1.0
"""How long a Modbus connect and each request wait for the server (s); no retries."""


def connect_tcp(host: str, port: int, timeout_s: float = MODBUS_TIMEOUT_S) -> ModbusTcpClient:
    """A connected Modbus TCP client (e.g. ``127.0.0.1``, 502)."""
    return _connected(ModbusTcpClient(host, port=port, timeout=timeout_s, retries=0),
                      f"{host}:{port}")


def connect_rtu(port: str, baudrate: int = 115200,
                timeout_s: float = MODBUS_TIMEOUT_S) -> ModbusSerialClient:
    """A connected Modbus RTU client on a serial device (``/dev/ttyUSB0``, 8N1)."""
    return _connected(ModbusSerialClient(port, framer=FramerType.RTU, baudrate=baudrate,
                                         timeout=timeout_s, retries=0), port)


def _connected(client: ModbusBaseSyncClient, where: str) -> ModbusBaseSyncClient:
    if not client.connect():
        raise DeviceError(f"cannot connect to the Modbus server at {where}")
    return client


class ModbusDevice:
    """A device behind `client` at `device_id`, described by `register_map`."""

    def __init__(self, client: ModbusBaseSyncClient, device_id: int, register_map: RegisterMap):
        self.client = client
        self.device_id = device_id
        self.register_map = register_map

    def read(self, register: Register) -> float:
        """One register's value in its engineering unit."""
        response = self._checked(f"read of {register.name}", register.address,
                                 lambda: self.client.read_holding_registers(
                                     register.address, count=register.count,
                                     device_id=self.device_id))
        return register.decode(response.registers)

    def write(self, register: Register, value: float) -> None:
        """Write one register (function code 16, also for single-word registers)."""
        words = register.encode(value)
        self._checked(f"write of {register.name}", register.address,
                      lambda: self.client.write_registers(register.address, words,
                                                          device_id=self.device_id))

    def read_all(self) -> dict[str, float]:
        """Every register of the map in one request (a consistent snapshot)."""
        first, count = self.register_map.first, self.register_map.end - self.register_map.first
        response = self._checked("read of the register block", first,
                                 lambda: self.client.read_holding_registers(
                                     first, count=count, device_id=self.device_id))
        return self.register_map.decode_block(response.registers)

    def _checked(self, what: str, address: int, send: Callable[[], ModbusPDU]) -> ModbusPDU:
        """The response of `send()`; a lost request or an exception response → DeviceError."""
        where = (f"{self.register_map.device} (id {self.device_id}): {what} "
                 f"(holding register {address})")
        try:
            response = send()
        except ModbusException as error:
            raise DeviceError(f"{where} failed: {error}") from error
        if response.isError():
            code = response.exception_code
            raise DeviceError(f"{where} failed: Modbus exception {code} "
                              f"{_code_name(ExcCodes, code)}", code)
        return response


class InverterStatus(NamedTuple):
    """One snapshot of the inverter (speeds in rpm, feed override as a fraction)."""

    running: bool
    at_speed: bool
    run_commanded: bool
    fault_code: int
    setpoint_rpm: float
    actual_rpm: float
    ramp_rpm_s: float
    feed_override: float
    max_speed_rpm: float


class SpindleInverter(ModbusDevice):
    """Spindle inverter: run / stop, speed setpoint with ramp limit, fault, feed override."""

    def __init__(self, client: ModbusBaseSyncClient, device_id: int = 1):
        super().__init__(client, device_id, INVERTER_MAP)

    def run(self) -> None:
        """Start the spindle towards the setpoint; raises `InverterFaultError` if in fault."""
        self.write(INVERTER_MAP["CONTROL"], INVERTER_CONTROL_RUN)
        self.check_fault()

    def stop(self) -> None:
        """Ramp the spindle down to standstill."""
        self.write(INVERTER_MAP["CONTROL"], 0)

    def set_speed_rpm(self, speed_rpm: float) -> None:
        """New setpoint (rpm); above MAX_SPEED the inverter faults → `InverterFaultError`."""
        self.write(INVERTER_MAP["SPEED_SETPOINT"], speed_rpm)
        self.check_fault()

    def set_ramp_rpm_s(self, ramp_rpm_s: float) -> None:
        """Ramp limit (rpm/s) of the actual speed; 0 is refused (Modbus exception 3)."""
        self.write(INVERTER_MAP["RAMP_RATE"], ramp_rpm_s)

    def reset_fault(self) -> None:
        """Clear the fault; the spindle stays stopped until `run()`."""
        self.write(INVERTER_MAP["CONTROL"], INVERTER_CONTROL_FAULT_RESET)

    def check_fault(self) -> None:
        """Raise `InverterFaultError` if the inverter reports a fault."""
        if code := self.fault_code:
            raise InverterFaultError(self.device_id, code)

    @property
    def actual_speed_rpm(self) -> float:
        return self.read(INVERTER_MAP["SPEED_ACTUAL"])

    @property
    def fault_code(self) -> int:
        return int(self.read(INVERTER_MAP["FAULT_CODE"]))

    @property
    def feed_override(self) -> float:
        """Feed override the CNC applies (fraction, 1.0 = 100 %; 0 … 2.0)."""
        return self.read(INVERTER_MAP["FEED_OVERRIDE"]) / 100.0

    @feed_override.setter
    def feed_override(self, fraction: float) -> None:
        self.write(INVERTER_MAP["FEED_OVERRIDE"], 100.0 * fraction)

    def status(self) -> InverterStatus:
        """Everything in one request."""
        values = self.read_all()
        status = int(values["STATUS"])
        return InverterStatus(
            running=bool(status & INVERTER_STATUS_RUNNING),
            at_speed=bool(status & INVERTER_STATUS_AT_SPEED),
            run_commanded=bool(status & INVERTER_STATUS_RUN_COMMANDED),
            fault_code=int(values["FAULT_CODE"]),
            setpoint_rpm=values["SPEED_SETPOINT"],
            actual_rpm=values["SPEED_ACTUAL"],
            ramp_rpm_s=values["RAMP_RATE"],
            feed_override=values["FEED_OVERRIDE"] / 100.0,
            max_speed_rpm=values["MAX_SPEED"],
        )


class LoadCellReading(NamedTuple):
    """One snapshot of the amplifier: force and resolution in N, range ±`range_N`."""

    force_N: float
    overloaded: bool
    overload_latched: bool
    range_N: float
    resolution_N: float


class LoadCellAmplifier(ModbusDevice):
    """Load-cell amplifier: ADC counts scaled by the range, overload flags, range switching."""

    def __init__(self, client: ModbusBaseSyncClient, device_id: int = 2):
        super().__init__(client, device_id, LOAD_CELL_MAP)

    def reading(self) -> LoadCellReading:
        """Force, flags and scaling from one request (so they belong to the same sample)."""
        values = self.read_all()
        resolution = load_cell_resolution(values["RANGE"], int(values["ADC_BITS"]))
        status = int(values["STATUS"])
        return LoadCellReading(
            force_N=values["FORCE_COUNTS"] * resolution,
            overloaded=bool(status & LOAD_CELL_STATUS_OVERLOAD),
            overload_latched=bool(status & LOAD_CELL_STATUS_OVERLOAD_LATCHED),
            range_N=values["RANGE"],
            resolution_N=resolution,
        )

    @property
    def force_N(self) -> float:
        return self.reading().force_N

    @property
    def overloaded(self) -> bool:
        """The latest sample is beyond ±range."""
        return self.reading().overloaded

    @property
    def overload_latched(self) -> bool:
        """A sample was beyond ±range since the last `clear_overload()`."""
        return self.reading().overload_latched

    def clear_overload(self) -> None:
        self.write(LOAD_CELL_MAP["CONTROL"], LOAD_CELL_CONTROL_CLEAR_OVERLOAD)

    @property
    def range(self) -> float:
        """Measuring range ±N (full scale of the ADC)."""
        return self.read(LOAD_CELL_MAP["RANGE"])

    @range.setter
    def range(self, range_N: float) -> None:
        self.write(LOAD_CELL_MAP["RANGE"], range_N)
