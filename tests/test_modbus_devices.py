"""Modbus drivers against their simulated peers over real transports (TCP loopback, RTU on a pty).

Ground truth: the ramp law (setpoint / ramp seconds from standstill), the ADC step
2·range / 2^bits, the configured noise, the register maps in docs/modbus_registers.md.
"""

from __future__ import annotations

import math
import re
import socket
import struct
from contextlib import contextmanager
from fractions import Fraction
from pathlib import Path
from typing import Iterator, NamedTuple

import numpy as np
import pytest

from feedbench.drivers.modbus_devices import (
    INVERTER_MAP,
    LOAD_CELL_MAP,
    DeviceError,
    InverterFault,
    InverterFaultError,
    LoadCellAmplifier,
    Register,
    SpindleInverter,
    connect_rtu,
    connect_tcp,
)
from feedbench.protocols.modbus_registers import FUNCTION_CODES, INVERTER_STATUS_AT_SPEED
from feedbench.sim_backends.modbus_devices import (
    SimulatedLoadCell,
    SimulatedModbusRtuServer,
    SimulatedModbusTcpServer,
    SimulatedSpindleInverter,
)

CYCLE_S = 1e-3
REGISTER_DOC = Path(__file__).resolve().parents[1] / "docs" / "modbus_registers.md"


class Bench(NamedTuple):
    inverter_sim: SimulatedSpindleInverter
    load_cell_sim: SimulatedLoadCell
    inverter: SpindleInverter
    load_cell: LoadCellAmplifier
    force: list[float]  # force_source reads force[0]


@contextmanager
def tcp_bench(noise_std_N: float = 0.0, **load_cell_options) -> Iterator[Bench]:
    """Both simulated devices on one TCP server (random port), both drivers on one client."""
    force = [0.0]
    inverter_sim = SimulatedSpindleInverter(max_speed_rpm=6000.0)
    load_cell_sim = SimulatedLoadCell(lambda: force[0], noise_std_N=noise_std_N, seed=1,
                                      **load_cell_options)
    with SimulatedModbusTcpServer([inverter_sim, load_cell_sim]) as server:
        client = connect_tcp("127.0.0.1", server.port)
        try:
            yield Bench(inverter_sim, load_cell_sim, SpindleInverter(client, 1),
                        LoadCellAmplifier(client, 2), force)
        finally:
            client.close()


def advance(bench: Bench, cycles: int) -> None:
    for _ in range(cycles):
        bench.inverter_sim.advance(CYCLE_S)
        bench.load_cell_sim.advance(CYCLE_S)


def test_tcp_server_listens_on_loopback_port_and_releases_it():
    server = SimulatedModbusTcpServer([SimulatedSpindleInverter()])
    host, port = server.start()
    assert host == "127.0.0.1" and port > 0
    client = connect_tcp(host, port)
    assert SpindleInverter(client).status().max_speed_rpm == 6000
    client.close()
    server.stop()
    with pytest.raises(OSError):
        socket.create_connection((host, port), timeout=1.0)
    with pytest.raises(DeviceError, match=f"127.0.0.1:{port}"):
        connect_tcp(host, port)


def test_lost_server_becomes_device_error():
    server = SimulatedModbusTcpServer([SimulatedSpindleInverter()])
    inverter = SpindleInverter(connect_tcp(*server.start()))
    assert inverter.actual_speed_rpm == 0.0
    server.stop()
    with pytest.raises(DeviceError, match=r"read of SPEED_ACTUAL \(holding register 4\) failed"):
        _ = inverter.actual_speed_rpm
    inverter.client.close()


def test_speed_ramp_reaches_setpoint_after_setpoint_over_ramp_seconds():
    setpoint, ramp = 1200.0, 100.0  # rpm, rpm/s → 12 s = 12000 cycles
    expected_cycles = round(setpoint / ramp / CYCLE_S)
    with tcp_bench() as bench:
        bench.inverter.set_ramp_rpm_s(ramp)
        bench.inverter.set_speed_rpm(setpoint)
        bench.inverter.run()
        advance(bench, expected_cycles // 2)
        assert bench.inverter.actual_speed_rpm == pytest.approx(setpoint / 2, abs=0.01)
        advance(bench, expected_cycles // 2 - 1)
        assert not bench.inverter.status().at_speed, "one cycle before the ramp's end"
        advance(bench, 1)
        assert bench.inverter.status().at_speed, "on the cycle the ramp ends, not one late"
        assert bench.inverter.actual_speed_rpm == setpoint


@pytest.mark.parametrize("setpoint, ramp, cycle_s", [(1000.0, 200.0, 1e-3),
                                                     (1234.56, 0.1, 0.125),
                                                     (1592.5, 50.0, 2e-3),
                                                     (480.2, 100.0, 2e-3),
                                                     (791.35, 200.0, 2.5e-4),
                                                     (718.35, 50.0, 1e-3)])
def test_at_speed_rises_on_the_cycle_the_ramp_law_reaches_the_setpoint(setpoint, ramp,
                                                                        cycle_s):
    """AT_SPEED on cycle ceil(setpoint / (ramp · cycle)) exactly, that count computed in
    exact decimal arithmetic. The last four rose one SYNC late with the float ramp of
    before (the sum of the float steps fell short of the setpoint by a rounding error)."""
    expected = math.ceil(Fraction(str(setpoint))
                         / (Fraction(str(ramp)) * Fraction(str(cycle_s))))
    with tcp_bench() as bench:
        bench.inverter.set_ramp_rpm_s(ramp)
        bench.inverter.set_speed_rpm(setpoint)
        bench.inverter.run()
        at_speed = []
        for _ in range(expected + 1):
            bench.inverter_sim.advance(cycle_s)
            at_speed.append(bool(bench.inverter_sim.values()["STATUS"]
                                 & INVERTER_STATUS_AT_SPEED))
        assert at_speed.index(True) + 1 == expected
        assert at_speed[expected - 1:] == [True, True]
        status = bench.inverter.status()
        assert status.at_speed and status.actual_rpm == pytest.approx(setpoint, abs=1e-9)


def test_run_and_stop():
    with tcp_bench() as bench:
        bench.inverter.set_ramp_rpm_s(500.0)
        bench.inverter.set_speed_rpm(1000.0)
        advance(bench, 100)
        idle = bench.inverter.status()
        assert (idle.running, idle.run_commanded, idle.actual_rpm) == (False, False, 0.0)
        bench.inverter.run()
        advance(bench, 2000)  # 2 s ≥ 1000 / 500 s
        running = bench.inverter.status()
        assert (running.running, running.at_speed, running.run_commanded) == (True, True, True)
        assert bench.inverter_sim.speed_rad_s == pytest.approx(1000.0 * 2 * np.pi / 60, rel=1e-12)
        bench.inverter.stop()
        advance(bench, 1000)
        assert bench.inverter.actual_speed_rpm == pytest.approx(500.0, abs=0.01)
        advance(bench, 1001)
        stopped = bench.inverter.status()
        assert (stopped.running, stopped.run_commanded, stopped.actual_rpm) == (False, False, 0.0)


def test_overspeed_setpoint_faults_and_reset_clears_it():
    with tcp_bench() as bench:
        bench.inverter.set_speed_rpm(1500.0)
        bench.inverter.run()
        advance(bench, 1000)  # 200 rpm/s default ramp → 200 rpm
        with pytest.raises(InverterFaultError, match="code 1 OVERSPEED_SETPOINT") as fault:
            bench.inverter.set_speed_rpm(6500.0)
        assert fault.value.fault_code == InverterFault.OVERSPEED_SETPOINT
        status = bench.inverter.status()
        assert (status.fault_code, status.run_commanded, status.setpoint_rpm) == (1, False, 1500.0)
        with pytest.raises(InverterFaultError):
            bench.inverter.run()  # refused while in fault
        advance(bench, 1001)
        assert bench.inverter.actual_speed_rpm == 0.0  # ramped down from 200 rpm
        bench.inverter.reset_fault()
        assert bench.inverter.fault_code == 0
        bench.inverter.run()
        advance(bench, 1000)
        assert bench.inverter.actual_speed_rpm == pytest.approx(200.0, abs=0.01)


def test_external_trip_is_reported():
    with tcp_bench() as bench:
        bench.inverter_sim.trip(InverterFault.EXTERNAL)
        with pytest.raises(InverterFaultError, match="code 2 EXTERNAL"):
            bench.inverter.check_fault()


def test_feed_override_round_trip_and_refused_value():
    with tcp_bench() as bench:
        assert bench.inverter.feed_override == 1.0
        bench.inverter.feed_override = 0.853
        assert bench.inverter_sim.feed_override == pytest.approx(0.853, abs=1e-12)
        assert bench.inverter.feed_override == pytest.approx(0.853, abs=1e-12)
        with pytest.raises(DeviceError, match="FEED_OVERRIDE.*exception 3 ILLEGAL_VALUE") as error:
            bench.inverter.feed_override = 2.5
        assert error.value.exception_code == 3
        assert bench.inverter_sim.feed_override == pytest.approx(0.853, abs=1e-12)


def test_load_cell_quantisation_step_is_range_over_two_to_the_bits():
    range_N, bits = 20000.0, 16
    step = 2 * range_N / 2**bits  # 0.6103515625 N
    with tcp_bench(range_N=range_N, adc_bits=bits) as bench:
        readings = []
        for force in np.arange(1000.0, 1005.0, 0.05):
            bench.force[0] = force
            advance(bench, 1)
            reading = bench.load_cell.reading()
            assert reading.force_N == round(force / step) * step  # exact: counts × step
            readings.append(reading.force_N)
        assert reading.resolution_N == step
        assert np.diff(np.unique(readings)) == pytest.approx(step, rel=1e-12)


def test_range_switch_changes_the_step():
    with tcp_bench(range_N=20000.0, adc_bits=16) as bench:
        bench.load_cell.range = 5000.0
        bench.force[0] = 1234.0
        advance(bench, 1)
        step = 2 * 5000.0 / 2**16
        assert bench.load_cell.range == 5000.0
        assert bench.load_cell.force_N == round(1234.0 / step) * step
        with pytest.raises(DeviceError, match="RANGE.*exception 3"):
            bench.load_cell.range = 0.0


def test_load_cell_noise_std_matches_configuration():
    noise, force = 5.0, 1234.5
    with tcp_bench(noise_std_N=noise, range_N=20000.0, adc_bits=16) as bench:
        bench.force[0] = force
        samples = []
        for _ in range(2000):
            advance(bench, 1)
            samples.append(bench.load_cell.force_N)
    assert np.std(samples, ddof=1) == pytest.approx(noise, rel=0.10)
    assert np.mean(samples) == pytest.approx(force, abs=4 * noise / np.sqrt(2000))


def test_overload_flag_above_range_latches_until_cleared():
    range_N, bits = 20000.0, 16
    full_scale = (2 ** (bits - 1) - 1) * 2 * range_N / 2**bits
    with tcp_bench(range_N=range_N, adc_bits=bits) as bench:
        bench.force[0] = 0.99 * range_N
        advance(bench, 1)
        assert not bench.load_cell.overloaded
        bench.force[0] = 1.1 * range_N
        advance(bench, 1)
        reading = bench.load_cell.reading()
        assert (reading.overloaded, reading.overload_latched) == (True, True)
        assert reading.force_N == full_scale  # counts clipped at the ADC limit
        bench.force[0] = -1.1 * range_N
        advance(bench, 1)
        assert bench.load_cell.force_N == -range_N  # −2^(bits−1) counts
        bench.force[0] = 0.5 * range_N
        advance(bench, 1)
        assert (bench.load_cell.overloaded, bench.load_cell.overload_latched) == (False, True)
        bench.load_cell.clear_overload()
        assert not bench.load_cell.overload_latched


def test_illegal_address_becomes_device_error_naming_register_and_code():
    with tcp_bench() as bench:
        with pytest.raises(DeviceError) as error:
            bench.inverter.read(Register("NOT_MAPPED", 40))
        assert error.value.exception_code == 2
        assert str(error.value) == ("spindle inverter (id 1): read of NOT_MAPPED (holding "
                                    "register 40) failed: Modbus exception 2 ILLEGAL_ADDRESS")
        with pytest.raises(DeviceError, match="write of SPEED_ACTUAL.*exception 2") as error:
            bench.inverter.write(INVERTER_MAP["SPEED_ACTUAL"], 100.0)  # read-only
        assert error.value.exception_code == 2
        # the inverter driver pointed at the load cell: its map ends at register 7
        with pytest.raises(DeviceError, match=r"\(id 2\): read of MAX_SPEED.*exception 2"):
            SpindleInverter(bench.inverter.client, 2).read(INVERTER_MAP["MAX_SPEED"])


UNDOCUMENTED_PDUS = {
    0x01: bytes.fromhex("0000 0001"),  # read coils
    0x02: bytes.fromhex("0000 0001"),  # read discrete inputs
    0x04: bytes.fromhex("0000 0002"),  # read input registers
    0x05: bytes.fromhex("0000 ff00"),  # write single coil
    0x07: b"",  # read exception status
    0x08: bytes.fromhex("0000 1234"),  # diagnostics, return query data
    0x0B: b"",  # get comm event counter
    0x0C: b"",  # get comm event log
    0x0F: bytes.fromhex("0000 0001 01 01"),  # write multiple coils
    0x11: b"",  # report server id
    0x14: bytes.fromhex("07 06 0001 0000 0001"),  # read file record
    0x16: bytes.fromhex("0000 ffff 0000"),  # mask write register
    0x17: bytes.fromhex("0000 0001 0000 0001 02 0000"),  # read/write multiple registers
    0x18: bytes.fromhex("0000"),  # read FIFO queue
    0x2B: bytes.fromhex("0e 01 00"),  # read device identification
    0x41: bytes.fromhex("0102"),  # user-defined
    0x64: b"",  # user-defined
    0x83: bytes.fromhex("02"),  # an exception response sent as a request
}


def ask(connection: socket.socket, transaction: int, device_id: int, pdu: bytes) -> bytes:
    """One Modbus TCP request (MBAP header + `pdu`); returns the answer's PDU after checking
    its MBAP header echoes the request's."""
    connection.sendall(struct.pack(">HHHB", transaction, 0, len(pdu) + 1, device_id) + pdu)
    header = b""
    while len(header) < 7:
        header += connection.recv(7 - len(header))
    echoed, protocol, length, answered_id = struct.unpack(">HHHB", header)
    assert (echoed, protocol, answered_id) == (transaction, 0, device_id)
    body = b""
    while len(body) < length - 1:
        body += connection.recv(length - 1 - len(body))
    return body


def test_only_the_documented_function_codes_are_served_raw_tcp(caplog):
    """A third-party client reading only the docs: every other function code (ones pymodbus
    knows and ones nobody does) → exception 1, function byte = code | 0x80; a malformed
    request of a documented code → exception 3; an unknown device id → 0x0B. Each exception
    answered is one log line of the server's, none of pymodbus's."""
    with tcp_bench() as bench, socket.create_connection(
            ("127.0.0.1", bench.inverter.client.comm_params.port), timeout=5.0) as raw:
        for transaction, (code, data) in enumerate(UNDOCUMENTED_PDUS.items(), start=1):
            for device_id in (1, 2):
                assert ask(raw, transaction, device_id, bytes([code]) + data) == bytes(
                    [code | 0x80, 0x01]), f"function 0x{code:02X}, device {device_id}"
        assert ask(raw, 100, 1, bytes.fromhex("03 0000 0002")) == bytes.fromhex("03 04 0000 0000")
        assert ask(raw, 101, 2, bytes.fromhex("10 0004 0002 04 0000 61a8")) == bytes.fromhex(
            "10 0004 0002")
        assert bench.load_cell_sim.range_N == 25000.0
        assert ask(raw, 102, 1, bytes.fromhex("06 0006 07d0")) == bytes.fromhex("06 0006 07d0")
        assert bench.inverter_sim.ramp_rpm_s == pytest.approx(200.0)
        assert ask(raw, 103, 1, bytes.fromhex("03 00")) == bytes.fromhex("83 03"), "truncated"
        assert ask(raw, 104, 1, bytes.fromhex("03 0000 0000")) == bytes.fromhex("83 03")
        assert ask(raw, 105, 1, bytes.fromhex("03 0028 0001")) == bytes.fromhex("83 02")
        assert ask(raw, 106, 1, bytes.fromhex("06 0006 0000")) == bytes.fromhex("86 03")
        assert ask(raw, 107, 9, bytes.fromhex("41 00")) == bytes.fromhex("c1 0b")
        assert ask(raw, 108, 9, bytes.fromhex("03 0000 0001")) == bytes.fromhex("83 0b")
    answered = [r for r in caplog.records if r.name == "feedbench.sim_backends.modbus_devices"]
    assert len(answered) == 2 * len(UNDOCUMENTED_PDUS) + 6
    messages = [r.getMessage() for r in answered]
    for device in ("spindle inverter (device id 1)", "load-cell amplifier (device id 2)"):
        assert (f"modbus: {device}: function 65: answered with exception 1 (ILLEGAL_FUNCTION)"
                in messages)
    assert not [r for r in caplog.records if r.name.startswith("pymodbus")]


def test_undocumented_function_codes_through_the_pymodbus_client():
    """pymodbus's own client calls for what the devices do not serve, TCP and RTU."""
    calls = {
        0x01: lambda client: client.read_coils(0, count=1, device_id=1),
        0x04: lambda client: client.read_input_registers(0, count=2, device_id=1),
        0x07: lambda client: client.read_exception_status(device_id=1),
        0x08: lambda client: client.diag_read_diagnostic_register(device_id=1),
        0x0B: lambda client: client.diag_get_comm_event_counter(device_id=1),
        0x11: lambda client: client.report_device_id(device_id=1),
        0x17: lambda client: client.readwrite_registers(read_address=0, read_count=1,
                                                        write_address=0, values=[0],
                                                        device_id=1),
        0x18: lambda client: client.read_fifo_queue(address=0, device_id=1),
        0x2B: lambda client: client.read_device_information(device_id=1),
    }
    with tcp_bench() as bench:
        for code, call in calls.items():
            response = call(bench.inverter.client)
            assert (response.function_code, response.exception_code) == (code | 0x80, 1), code
    server = SimulatedModbusRtuServer([SimulatedSpindleInverter()])
    client = connect_rtu(server.start())
    try:
        for code in (0x07, 0x08, 0x11, 0x2B):
            response = calls[code](client)
            assert (response.function_code, response.exception_code) == (code | 0x80, 1), code
        assert SpindleInverter(client, 1).status().max_speed_rpm == 6000, "still in step"
    finally:
        client.close()
        server.stop()


def test_function_codes_doc_matches_code():
    """docs/modbus_registers.md lists exactly the function codes the devices serve."""
    rows = re.findall(r"^\s*\| 0x([0-9A-F]{2}) \((\d+)\) \|", REGISTER_DOC.read_text(), re.M)
    assert [(int(hexa, 16), int(decimal)) for hexa, decimal in rows] == [
        (code, code) for code in FUNCTION_CODES]


def test_rtu_over_pty_null_modem():
    force = [4321.0]
    inverter_sim = SimulatedSpindleInverter()
    load_cell_sim = SimulatedLoadCell(lambda: force[0], noise_std_N=0.0, range_N=20000.0,
                                      adc_bits=16)
    server = SimulatedModbusRtuServer([inverter_sim, load_cell_sim])
    path = server.start()
    assert path.startswith("/dev/pts/")
    client = connect_rtu(path)
    try:
        inverter, load_cell = SpindleInverter(client, 1), LoadCellAmplifier(client, 2)
        inverter.set_speed_rpm(300.0)
        inverter.run()
        for _ in range(500):
            inverter_sim.advance(CYCLE_S)
            load_cell_sim.advance(CYCLE_S)
        assert inverter.actual_speed_rpm == pytest.approx(100.0, abs=0.01)
        step = 2 * 20000.0 / 2**16
        assert load_cell.force_N == round(4321.0 / step) * step
        with pytest.raises(DeviceError, match="exception 2 ILLEGAL_ADDRESS"):
            inverter.read(Register("NOT_MAPPED", 40))
    finally:
        client.close()
        server.stop()


def _documented_maps() -> dict[str, list[tuple]]:
    """Register rows per device section of docs/modbus_registers.md."""
    sections: dict[str, list[tuple]] = {}
    current = None
    for line in REGISTER_DOC.read_text().splitlines():
        if heading := re.match(r"## (.+) \(default device id \d+\)", line):
            current = sections.setdefault(heading.group(1).lower(), [])
        elif current is not None and re.match(r"\| \d+ \|", line):
            address, name, datatype, scale, unit, access = (
                cell.strip() for cell in line.strip("|").split("|")[:6])
            current.append((int(address), name, datatype, float(scale), unit, access == "RW"))
    return sections


def test_register_doc_matches_code_maps():
    documented = _documented_maps()
    for register_map in (INVERTER_MAP, LOAD_CELL_MAP):
        in_code = [(r.address, r.name, r.datatype, float(r.scale), r.unit, r.writable)
                   for r in register_map.registers]
        assert documented[register_map.device] == in_code
