"""Simulated Modbus devices: a spindle inverter and a load-cell amplifier, served by pymodbus.

Each device is a small state machine in virtual time: the simulated world calls
`advance(dt_s)` once per bus cycle; nothing here reads the wall clock. Its registers follow
`docs/modbus_registers.md` (the maps in `feedbench.drivers.modbus_devices`). The Modbus side
is pymodbus's simulator API: one `SimDevice` per device whose action runs under the device
lock on every request: a write is decoded and applied to the state machine (or refused with
exception 3), then every register is refreshed from the state, so a read always returns the
state after the latest `advance`.

Servers run pymodbus's asyncio server in a background thread, so the synchronous bench owns
them: `SimulatedModbusTcpServer` listens on 127.0.0.1 only (port 0 = a free port);
`SimulatedModbusRtuServer` serves RTU on one end of a pseudo-terminal null modem and hands
out the other end's path, which a host opens exactly like ``/dev/ttyUSB0``.

Faults are answered with Modbus exceptions and logged as one line each (`AnsweringContext`):
a request to a device id no device has → exception 0x0B (gateway target device failed to
respond), an exception inside a device → 4 (server device failure); the exceptions the
register maps prescribe (1, 2, 3) are logged too. pymodbus itself would answer the first two
with a traceback on stderr. Only the documented function codes reach the devices
(`DocumentedFunctions`): pymodbus would answer diagnostics, device identification and the
like itself, and an unknown code with function byte 0x80.
"""

from __future__ import annotations

import abc
import asyncio
import concurrent.futures
import logging
import os
import pty
import select
import struct
import threading
import tty
from contextlib import AbstractContextManager
from typing import Any, Awaitable, Callable, Sequence

import numpy as np
from pymodbus.constants import ExcCodes
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.pdu.decoders import DecodePDU
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.server.base import ModbusBaseServer
from pymodbus.simulator import DataType, SimData, SimDevice

from feedbench.protocols.address import LOOPBACK
from feedbench.sim_backends.faults import NO_FAULTS, Faults
from feedbench.protocols.modbus_registers import (
    FUNCTION_CODES,
    INVERTER_CONTROL_FAULT_RESET,
    INVERTER_CONTROL_RUN,
    INVERTER_MAP,
    INVERTER_STATUS_AT_SPEED,
    INVERTER_STATUS_FAULT,
    INVERTER_STATUS_RUN_COMMANDED,
    INVERTER_STATUS_RUNNING,
    LOAD_CELL_CONTROL_CLEAR_OVERLOAD,
    LOAD_CELL_MAP,
    LOAD_CELL_STATUS_OVERLOAD,
    LOAD_CELL_STATUS_OVERLOAD_LATCHED,
    InverterFault,
    RegisterMap,
    load_cell_resolution,
)
from feedbench.units import RPM

LOGGER = logging.getLogger(__name__)
THREAD_TIMEOUT_S = 5.0
NOISE_BLOCK = 4096
NANO_PER_RPM = 10**9
"""The inverter holds speeds as integer nano-rpm: the ramp's sums are exact, so the actual
speed lands on the setpoint on the cycle the ramp law says (the registers resolve 0.01 rpm
and 0.1 rpm/s, both whole numbers of nano-rpm per 1 µs of cycle)."""


class InvalidWrite(ValueError):
    """A host write the device refuses (answered with Modbus exception 3)."""


class SimulatedModbusDevice(abc.ABC):
    """Base of a simulated device: register image ↔ state, guarded by one lock."""

    register_map: RegisterMap

    def __init__(self, device_id: int):
        self.device_id = device_id
        self.lock: AbstractContextManager[Any] = threading.Lock()

    def answer_between_cycles(self, cycle_lock: AbstractContextManager[Any]) -> None:
        """Guard the device with the bus cycle's lock (the simulated drive's): a request is
        answered before or after a cycle, never while the cycle's hooks still advance it."""
        self.lock = cycle_lock

    @abc.abstractmethod
    def advance(self, dt_s: float) -> None:
        """Advance the device by one bus cycle of `dt_s` seconds of virtual time."""

    @abc.abstractmethod
    def values(self) -> dict[str, float]:
        """Every register's engineering value (called under the lock)."""

    @abc.abstractmethod
    def apply(self, name: str, value: float) -> None:
        """A host write to register `name` (under the lock); may raise `InvalidWrite`."""

    def sim_device(self) -> SimDevice:
        """The pymodbus simulator device: one block of holding registers, this action."""
        simdata = [SimData(register.address, datatype=DataType[register.datatype],
                           readonly=not register.writable)
                   for register in self.register_map.registers]
        return SimDevice(self.device_id, simdata=simdata, action=self._on_request)

    async def _on_request(self, function_code: int, start: int, address: int, _count: int,
                          registers: list[int], written: list[int] | None) -> ExcCodes | None:
        """pymodbus action (function codes 3, 6, 16 only: `DocumentedFunctions`): apply a
        write, refresh the image."""
        with self.lock:
            if written is not None:
                try:
                    self._apply_words(address, written)
                except InvalidWrite:
                    return ExcCodes.ILLEGAL_VALUE
            self._refresh(registers, start)
        return None

    def _apply_words(self, address: int, written: list[int]) -> None:
        """Overlay the written words on the current image; apply each register they touch."""
        image = [0] * self.register_map.end
        self._refresh(image, 0)
        image[address:address + len(written)] = written
        for register in self.register_map.registers:
            if register.address < address + len(written) and \
                    address < register.address + register.count:
                self.apply(register.name, register.decode(
                    image[register.address:register.address + register.count]))

    def _refresh(self, registers: list[int], start: int) -> None:
        values = self.values()
        for register in self.register_map.registers:
            offset = register.address - start
            registers[offset:offset + register.count] = register.encode(
                values[register.name], saturate=True)


class SimulatedSpindleInverter(SimulatedModbusDevice):
    """Spindle inverter: the actual speed follows the setpoint at the ramp limit.

    Running: target = setpoint, else 0; per `advance(dt)` the actual speed moves towards the
    target by at most ramp·dt, in exact integer steps (`NANO_PER_RPM`): AT_SPEED rises on
    the cycle the ramp reaches the setpoint. A setpoint above `max_speed_rpm` trips
    OVERSPEED_SETPOINT: the run command drops, the setpoint keeps its old value, the spindle
    ramps down. The feed override is only held here: the simulated CNC reads `feed_override`.
    """

    register_map = INVERTER_MAP

    def __init__(self, device_id: int = 1, max_speed_rpm: float = 6000.0,
                 ramp_rpm_s: float = 200.0):
        super().__init__(device_id)
        self.max_speed_rpm = max_speed_rpm
        self.ramp_rpm_s = ramp_rpm_s
        self._setpoint_nrpm = 0
        self._actual_nrpm = 0
        self.run_commanded = False
        self.fault = InverterFault.NONE
        self.feed_override = 1.0

    @property
    def setpoint_rpm(self) -> float:
        """Speed setpoint (rpm)."""
        return self._setpoint_nrpm / NANO_PER_RPM

    @property
    def actual_rpm(self) -> float:
        """Actual spindle speed (rpm)."""
        return self._actual_nrpm / NANO_PER_RPM

    @property
    def speed_rad_s(self) -> float:
        """Actual spindle speed in rad/s (for the milling process)."""
        return self.actual_rpm * RPM

    def advance(self, dt_s: float) -> None:
        """Move the actual speed towards the target by at most ramp·dt."""
        with self.lock:
            target = self._setpoint_nrpm if self.run_commanded else 0
            step = round(self.ramp_rpm_s * dt_s * NANO_PER_RPM)
            gap = target - self._actual_nrpm
            self._actual_nrpm = target if abs(gap) <= step else self._actual_nrpm + (
                step if gap > 0 else -step)

    def trip(self, fault: InverterFault) -> None:
        """Fault the inverter (bench fault injection): run command off, ramp down."""
        with self.lock:
            self._trip(fault)

    def _trip(self, fault: InverterFault) -> None:
        self.fault = fault
        self.run_commanded = False

    def values(self) -> dict[str, float]:
        return {
            "CONTROL": INVERTER_CONTROL_RUN if self.run_commanded else 0,
            "STATUS": self._status_word(),
            "SPEED_SETPOINT": self.setpoint_rpm,
            "SPEED_ACTUAL": self.actual_rpm,
            "RAMP_RATE": self.ramp_rpm_s,
            "FAULT_CODE": int(self.fault),
            "FEED_OVERRIDE": 100.0 * self.feed_override,
            "MAX_SPEED": self.max_speed_rpm,
        }

    def _status_word(self) -> int:
        running = self._actual_nrpm != 0
        at_speed = self.run_commanded and self._actual_nrpm == self._setpoint_nrpm
        return ((INVERTER_STATUS_RUNNING if running else 0)
                | (INVERTER_STATUS_AT_SPEED if at_speed else 0)
                | (INVERTER_STATUS_RUN_COMMANDED if self.run_commanded else 0)
                | (INVERTER_STATUS_FAULT if self.fault else 0))

    def apply(self, name: str, value: float) -> None:
        if name == "CONTROL":
            self._control(int(value))
        elif name == "SPEED_SETPOINT":
            self._setpoint(value)
        elif name == "RAMP_RATE":
            self.ramp_rpm_s = _positive(value, name)
        elif name == "FEED_OVERRIDE":
            self.feed_override = _within(value, 0.0, 200.0, name) / 100.0

    def _control(self, word: int) -> None:
        """Bit 7 resets a fault (self-clearing); bit 0 runs, refused while in fault."""
        if word & INVERTER_CONTROL_FAULT_RESET:
            self.fault = InverterFault.NONE
        self.run_commanded = bool(word & INVERTER_CONTROL_RUN) and not self.fault

    def _setpoint(self, speed_rpm: float) -> None:
        if speed_rpm > self.max_speed_rpm:
            self._trip(InverterFault.OVERSPEED_SETPOINT)
        else:
            self._setpoint_nrpm = round(speed_rpm * NANO_PER_RPM)


class SimulatedLoadCell(SimulatedModbusDevice):
    """Load-cell amplifier: samples `force_source()` (N) once per `advance`.

    Sample = force + Gaussian noise (std `noise_std_N`, seeded), quantised by a bipolar
    `adc_bits` ADC over ±range (step 2·range/2^bits), counts clipped to the ADC's limits.
    OVERLOAD flags a sample beyond ±range; the latched flag holds until the host clears it.
    """

    register_map = LOAD_CELL_MAP

    def __init__(self, force_source: Callable[[], float], device_id: int = 2,
                 range_N: float = 25000.0, adc_bits: int = 16, noise_std_N: float = 2.0,
                 seed: int = 0):
        super().__init__(device_id)
        self.force_source = force_source
        self.range_N = range_N
        self.adc_bits = adc_bits
        self.noise_std_N = noise_std_N
        self._rng = np.random.default_rng(seed)
        self._noise_block = np.empty(0)
        self._noise_index = 0
        self.counts = 0
        self.overloaded = False
        self.overload_latched = False

    @property
    def resolution_N(self) -> float:
        return load_cell_resolution(self.range_N, self.adc_bits)

    def advance(self, dt_s: float) -> None:
        """Take one sample (sample-and-hold for the bus cycle; `dt_s` sets no filter)."""
        force = self.force_source() + self.noise_std_N * self._standard_normal()
        with self.lock:
            self._sample(force)

    def _standard_normal(self) -> float:
        """Next N(0, 1) draw from pre-drawn blocks (≈ 0.8 µs; one numpy call each ≈ 2 µs)."""
        if self._noise_index == len(self._noise_block):
            self._noise_block = self._rng.standard_normal(NOISE_BLOCK)
            self._noise_index = 0
        self._noise_index += 1
        return float(self._noise_block[self._noise_index - 1])

    def _sample(self, force_N: float) -> None:
        limit = 2 ** (self.adc_bits - 1)
        self.counts = min(max(round(force_N / self.resolution_N), -limit), limit - 1)
        self.overloaded = abs(force_N) > self.range_N
        self.overload_latched |= self.overloaded

    def values(self) -> dict[str, float]:
        status = ((LOAD_CELL_STATUS_OVERLOAD if self.overloaded else 0)
                  | (LOAD_CELL_STATUS_OVERLOAD_LATCHED if self.overload_latched else 0))
        return {"FORCE_COUNTS": self.counts, "STATUS": status, "CONTROL": 0,
                "RANGE": self.range_N, "ADC_BITS": self.adc_bits}

    def apply(self, name: str, value: float) -> None:
        if name == "CONTROL" and int(value) & LOAD_CELL_CONTROL_CLEAR_OVERLOAD:
            self.overload_latched = self.overloaded
        elif name == "RANGE":
            self.range_N = _positive(value, name)


def _positive(value: float, name: str) -> float:
    if value <= 0:
        raise InvalidWrite(f"{name} must be > 0, got {value}")
    return value


def _within(value: float, low: float, high: float, name: str) -> float:
    if not low <= value <= high:
        raise InvalidWrite(f"{name} must be within {low}…{high}, got {value}")
    return value


class _ServerThread:
    """Runs one pymodbus server on its own asyncio loop in a daemon thread."""

    def __init__(self, make_server: Callable[[], ModbusBaseServer], name: str):
        self._make_server = make_server
        self._name = name
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self.server: ModbusBaseServer | None = None

    def start(self) -> ModbusBaseServer:
        """Start listening; returns once the server listens (or raises why it cannot)."""
        listening: concurrent.futures.Future = concurrent.futures.Future()
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._run, args=(listening,), name=self._name,
                                        daemon=True)
        self._thread.start()
        self.server = listening.result(THREAD_TIMEOUT_S)
        return self.server

    def _run(self, listening: concurrent.futures.Future) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            server = self._loop.run_until_complete(self._listen())
        except Exception as error:  # re-raised by `start` in the starting thread
            self._loop.close()
            listening.set_exception(error)
            return
        listening.set_result(server)
        try:
            self._loop.run_forever()
        finally:
            self._loop.close()

    async def _listen(self) -> ModbusBaseServer:
        server = self._make_server()
        await server.serve_forever(background=True)
        return server

    def stop(self) -> None:
        """Close the server and its connections, end the loop and the thread."""
        if self._thread is None or not self._thread.is_alive():
            return
        asyncio.run_coroutine_threadsafe(self._shutdown(), self._loop).result(THREAD_TIMEOUT_S)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(THREAD_TIMEOUT_S)

    async def _shutdown(self) -> None:
        await self.server.shutdown()
        others = [task for task in asyncio.all_tasks() if task is not asyncio.current_task()]
        for task in others:
            task.cancel()
        await asyncio.gather(*others, return_exceptions=True)


class RefusedRequest(ModbusPDU):
    """A request the devices do not serve, answered with `answer` under its own function
    code | 0x80 (pymodbus would answer an unknown code with function byte 0x80)."""

    def __init__(self, function_code: int, answer: ExcCodes) -> None:
        super().__init__()
        self.function_code = function_code
        self.answer = answer

    async def datastore_update(self, context: AnsweringContext,
                               device_id: int) -> ExceptionResponse:
        """The exception response (0x0B instead for a device id no device has)."""
        return ExceptionResponse(self.function_code,
                                 await context.refuse(device_id, self.function_code, self.answer))


class DocumentedFunctions(DecodePDU):
    """The servers' request decoder: the documented function codes (`FUNCTION_CODES`) as
    pymodbus decodes them, a malformed one of them → exception 3 (ILLEGAL DATA VALUE), any
    other code → exception 1 (ILLEGAL FUNCTION). On RTU a code pymodbus does not know has
    no length it could frame, so it gets no answer (the host times out)."""

    def __init__(self) -> None:
        super().__init__(is_server=True)

    def decode(self, frame: bytes) -> ModbusPDU:
        """The request in `frame` (function code, then data; never empty). Decoded here, not
        by `DecodePDU.decode`, which would log a malformed request a second time."""
        function_code = frame[0]
        if function_code not in FUNCTION_CODES:
            return RefusedRequest(function_code, ExcCodes.ILLEGAL_FUNCTION)
        request = self.pdu_table[function_code][self.pdu_inx]()
        try:
            request.decode(frame[1:])
        except (ValueError, IndexError, struct.error):  # too short, a count out of range
            return RefusedRequest(function_code, ExcCodes.ILLEGAL_VALUE)
        return request


def _sim_devices(devices: Sequence[SimulatedModbusDevice]) -> list[SimDevice]:
    return [device.sim_device() for device in devices]


class AnsweringContext:
    """pymodbus's simulator context (`SimCore`) with every fault answered by a Modbus exception
    and logged as one line (module logger): an unknown device id → 0x0B, an exception raised
    inside a device → 4; exception answers of the devices (1, 2, 3) are logged as warnings.
    `faults` (`sim_backends.faults`): requests left unanswered, or answered with an
    exception, from a SYNC count on."""

    def __init__(self, core, devices: Sequence[SimulatedModbusDevice],
                 faults: Faults = NO_FAULTS) -> None:
        self._core = core
        self._names = {device.device_id: device.register_map.device for device in devices}
        self._faults = faults

    def device_ids(self) -> list[int]:
        """The device ids served (pymodbus asks for broadcasts)."""
        return list(self._names)

    async def async_getValues(self, device_id: int, func_code: int, address: int,
                              count: int = 1) -> list[int] | list[bool] | ExcCodes:
        """A read (or the read-back of a write): the values, or the exception to answer."""
        return await self._answer(device_id, func_code, address, lambda: self._core
                                  .async_getValues(device_id, func_code, address, count))

    async def async_setValues(self, device_id: int, func_code: int, address: int,
                              values: list[int] | list[bool]) -> ExcCodes | None:
        """A write: None, or the exception to answer."""
        return await self._answer(device_id, func_code, address, lambda: self._core
                                  .async_setValues(device_id, func_code, address, values))

    async def refuse(self, device_id: int, func_code: int, answer: ExcCodes) -> ExcCodes:
        """A request the devices do not serve (`DocumentedFunctions`): `answer`, logged."""
        async def refused() -> ExcCodes:
            return answer
        return await self._answer(device_id, func_code, None, refused)

    async def _answer(self, device_id: int, func_code: int, address: int | None,
                      request: Callable[[], Awaitable]):
        if device_id not in self._names:
            LOGGER.warning("modbus: device id %d: no such device (served: %s); function %d "
                           "answered with exception 0x0B", device_id,
                           ", ".join(map(str, self._names)), func_code)
            return ExcCodes.GATEWAY_NO_RESPONSE
        where = (f"modbus: {self._names[device_id]} (device id {device_id}): function "
                 f"{func_code}" + ("" if address is None else f" at address {address}"))
        fault = self._faults.modbus_answer()
        if fault == "timeout":  # injected: never answered, the host's request times out
            await asyncio.Event().wait()
        if fault == "exception":
            answer = ExcCodes(self._faults.modbus_exception_code)
            LOGGER.warning("%s: answered with exception %d (injected fault)", where, answer)
            return answer
        try:
            result = await request()
        except Exception as error:  # a fault inside the device: answered, never a traceback
            LOGGER.error("%s: %s: %s; answered with exception 4", where,
                         type(error).__name__, error)
            return ExcCodes.DEVICE_FAILURE
        if isinstance(result, ExcCodes):
            LOGGER.warning("%s: answered with exception %d (%s)", where, result, result.name)
        return result


def _answering(server: ModbusBaseServer, devices: Sequence[SimulatedModbusDevice],
               faults: Faults = NO_FAULTS) -> ModbusBaseServer:
    """`server` with its simulator context wrapped in `AnsweringContext`, decoding only the
    documented function codes (`DocumentedFunctions`)."""
    server.context = AnsweringContext(server.context, devices, faults)
    server.decoder = DocumentedFunctions()
    return server


class SimulatedModbusTcpServer:
    """Modbus TCP server on 127.0.0.1 for `devices` (each at its own device id), with the
    Modbus `faults` of `sim_backends.faults`."""

    def __init__(self, devices: Sequence[SimulatedModbusDevice], port: int = 0,
                 faults: Faults = NO_FAULTS):
        self.devices = list(devices)
        self.port = port
        self.faults = faults
        self._thread = _ServerThread(self._make_server, "modbus-tcp-sim")

    def _make_server(self) -> ModbusTcpServer:
        return _answering(ModbusTcpServer(_sim_devices(self.devices),
                                          address=(LOOPBACK, self.port)), self.devices,
                          self.faults)

    def start(self) -> tuple[str, int]:
        """Listen; returns (host, port), the port chosen by the OS if 0 was asked."""
        server = self._thread.start()
        self.port = server.transport.sockets[0].getsockname()[1]
        return LOOPBACK, self.port

    def stop(self) -> None:
        self._thread.stop()

    def __enter__(self) -> SimulatedModbusTcpServer:
        self.start()
        return self

    def __exit__(self, *exc_info) -> None:
        self.stop()


class PtyNullModem:
    """Two pseudo-terminals joined by a relay thread: a null-modem cable between two paths.

    Hand-written: a pty has one path (the slave) and an unnamed master, so two programs that
    both open a path need two ptys whose masters exchange bytes (what ``socat`` does).
    """

    def __init__(self):
        self._pairs = [pty.openpty() for _ in range(2)]
        for _, slave in self._pairs:
            tty.setraw(slave)
        self.paths = tuple(os.ttyname(slave) for _, slave in self._pairs)
        self._stop_read, self._stop_write = os.pipe()
        self._thread = threading.Thread(target=self._relay, name="pty-null-modem", daemon=True)
        self._thread.start()

    def _relay(self) -> None:
        (master_a, _), (master_b, _) = self._pairs
        peer = {master_a: master_b, master_b: master_a}
        while True:
            ready, _, _ = select.select([master_a, master_b, self._stop_read], [], [])
            if self._stop_read in ready:
                return
            for master in ready:
                os.write(peer[master], os.read(master, 4096))

    def close(self) -> None:
        """Stop the relay and close both ptys."""
        os.write(self._stop_write, b"\0")
        self._thread.join(THREAD_TIMEOUT_S)
        for fd in (*(fd for pair in self._pairs for fd in pair), self._stop_read,
                   self._stop_write):
            os.close(fd)


class SimulatedModbusRtuServer:
    """Modbus RTU server for `devices` behind a pty null modem (one RS-485 line)."""

    def __init__(self, devices: Sequence[SimulatedModbusDevice], baudrate: int = 115200):
        self.devices = list(devices)
        self.baudrate = baudrate
        self.modem: PtyNullModem | None = None
        self._thread = _ServerThread(self._make_server, "modbus-rtu-sim")

    def _make_server(self) -> ModbusSerialServer:
        return _answering(ModbusSerialServer(_sim_devices(self.devices),
                                             port=self.modem.paths[0],
                                             baudrate=self.baudrate), self.devices)

    def start(self) -> str:
        """Serve; returns the host-side device path (open it as a serial port, 8N1)."""
        self.modem = PtyNullModem()
        try:
            self._thread.start()
        except BaseException:
            self.modem.close()
            raise
        return self.modem.paths[1]

    def stop(self) -> None:
        self._thread.stop()
        if self.modem is not None:
            self.modem.close()
            self.modem = None

    def __enter__(self) -> SimulatedModbusRtuServer:
        self.start()
        return self

    def __exit__(self, *exc_info) -> None:
        self.stop()
