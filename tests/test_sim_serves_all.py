"""`feedbench sim` serves every device and every bench it documents (issue 12, item 4).

Two sim processes, started once for the module: the lab axis (drive, CiA 401 I/O module of
the exciters, spindle inverter and load cell on one Modbus server, the DAQ fed by the
structure and milling worlds together) and the rack-and-pinion axis (master and slave drives,
the bumper's load cell). Plain clients only: pymodbus reads every register of
docs/modbus_registers.md for every device id, pyserial reads DAQ frames and checks them
against docs/serial_daq_protocol.md, canopen over python-can's socketcand interface SDO-reads
every object of the drives' EDS and the I/O module's objects. Faults are answered with the
protocol's exception and logged as one line each on the sim's stderr, never a traceback.
"""

from __future__ import annotations

import binascii
import io
import json
import logging
import re
import socket
import struct
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import can
import canopen
import pytest
import serial
from canopen.objectdictionary import ODVariable
from canopen.sdo import SdoAbortedError
from pymodbus.client import ModbusTcpClient

from feedbench.bench import sim_config
from feedbench.models.axis import CSV
from feedbench.protocols import cia401
from feedbench.sim_backends.eds import packaged_eds_path
from feedbench.sim_backends.io_module import object_dictionary
from feedbench.sim_backends.modbus_devices import (
    SimulatedModbusTcpServer, SimulatedSpindleInverter,
)
from feedbench.sim_backends.process import READY, one_line_logging
from feedbench.sim_backends.rack_pinion import packaged_eds_path as rack_eds_path
from feedbench.sim_backends.rack_pinion import world_truth
from feedbench.sim_backends.world import build_axis
from test_cia402_sim import NODE_ID, enable, loopback

DOCS = Path(__file__).parents[1] / "docs"
START_TIMEOUT_S = 60.0
IO_NODE = 12
logging.getLogger("can.interfaces.socketcand").setLevel(logging.ERROR)


class SimProcess:
    """A started `feedbench sim`: its ready info and its stderr lines, collected live."""

    def __init__(self, config: Path) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-m", "feedbench.commands.cli", "sim", str(config)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.stderr: list[str] = []
        self._reader = threading.Thread(target=self._read_stderr, daemon=True)
        self._reader.start()
        self.info: dict = {}

    def _read_stderr(self) -> None:
        for line in self.process.stderr:
            self.stderr.append(line.rstrip("\n"))

    def wait_ready(self) -> dict:
        line = self.process.stdout.readline()
        assert line.startswith(READY), "\n".join(self.stderr)
        self.info = json.loads(line[len(READY):])
        return self.info

    def new_stderr(self, since: int, count: int, timeout_s: float = 2.0) -> list[str]:
        """The stderr lines after the first `since`, once there are `count` of them."""
        deadline = time.monotonic() + timeout_s
        while len(self.stderr) < since + count and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.05)  # nothing more should come
        return self.stderr[since:]

    def stop(self) -> int | None:
        """Wait for the exit that `process.terminate()` asked for; the exit status, or None
        if it had to be killed after 20 s (then it is gone all the same)."""
        try:
            self.process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
            return None
        finally:
            self._reader.join(5)
        return self.process.returncode


def _config(path: Path, *lines: str) -> Path:
    path.write_text("\n".join(["[bench]", "simulated = true", 'interface = "socketcand"',
                               'socketcand = "127.0.0.1:0"',
                               f'channel = "sim-{uuid.uuid4().hex[:8]}"', *lines]) + "\n")
    return path


@pytest.fixture(scope="module")
def sims(tmp_path_factory):
    """Both benches, started together (they load in parallel); both must exit 0 on SIGTERM
    with no traceback on stderr."""
    directory = tmp_path_factory.mktemp("sims")
    processes = {"lab": SimProcess(_config(directory / "lab.toml",
                                          f"devices.exciter.node_id = {IO_NODE}")),
                 "rack": SimProcess(_config(directory / "rack.toml", 'axis = "rack_pinion"'))}
    try:
        for process in processes.values():
            process.wait_ready()
        yield processes
    finally:
        for process in processes.values():
            process.process.terminate()
        codes = {name: process.stop() for name, process in processes.items()}
    for name, process in processes.items():
        assert codes[name] == 0, "\n".join(process.stderr)
        assert not any("Traceback" in line for line in process.stderr), process.stderr
        assert all(line.startswith("feedbench-sim: ") for line in process.stderr), \
            process.stderr


@pytest.fixture(scope="module")
def lab(sims):
    return sims["lab"]


@pytest.fixture(scope="module")
def rack(sims):
    return sims["rack"]


class CanClient:
    """A canopen network on python-can's socketcand interface, to a sim's hub."""

    def __init__(self, info: dict) -> None:
        host, port = info["socketcand"].rsplit(":", 1)
        bus = can.Bus(interface="socketcand", channel=info["channel"], host=host,
                      port=int(port), tcp_tune=True)
        self.network = canopen.Network(bus)
        self.network.connect()

    def node(self, node_id: int, od) -> canopen.RemoteNode:
        node = canopen.RemoteNode(node_id, od)
        node.sdo.RESPONSE_TIMEOUT = 2.0
        self.network.add_node(node)
        return node

    def syncs(self, count: int, node: canopen.RemoteNode) -> int:
        """Send `count` SYNCs; returns once the sim has stepped them all (its cycle counter
        0x2020, read by SDO behind them on the same bus, has moved by `count`)."""
        before = node.sdo.upload(0x2020, 0)
        for _ in range(count):
            self.network.sync.transmit()
        start = time.monotonic()
        while time.monotonic() - start < 10.0:
            after = node.sdo.upload(0x2020, 0)
            moved = (int.from_bytes(after, "little") - int.from_bytes(before, "little")) % 2**16
            if moved >= count:
                return moved
        raise AssertionError("the sim did not step its SYNCs")

    def close(self) -> None:
        self.network.disconnect()


@pytest.fixture(scope="module")
def lab_can(lab):
    client = CanClient(lab.info)
    yield client
    client.close()


def _modbus(info: dict) -> ModbusTcpClient:
    host, port = info["modbus"].rsplit(":", 1)
    client = ModbusTcpClient(host, port=int(port), timeout=2)
    assert client.connect()
    return client


def test_sim_configs_name_their_bench(tmp_path):
    """The example sim configs: the lab bench with the SMFE workpiece (3 lanes) and the I/O
    module at node 10, the rack-and-pinion axis; a tool-tip [experiment] in a sim config
    puts the I/O module at its io_node_id."""
    examples = Path(__file__).parents[1] / "feedbench" / "examples"
    bench, plan = sim_config(examples / "bench_sim.toml")
    assert (bench["axis"], bench["devices"]["exciter"]["node_id"],
            len(plan.params["workpiece"])) == ("lab", 10, 3)
    bench, plan = sim_config(examples / "bench_sim_rack_pinion.toml")
    assert (bench["axis"], bench["node_id"], bench["slave_node_id"], plan) == (
        "rack_pinion", 1, 2, None)
    hammer = (examples / "impact_hammer.toml").read_text()
    config = tmp_path / "hammer_sim.toml"
    config.write_text(hammer.replace("io_node_id = 10", "io_node_id = 23"))
    assert sim_config(config)[0]["devices"]["exciter"]["node_id"] == 23


# -- the documented register maps -----------------------------------------------------------

WORDS = {"UINT16": (1, "H"), "INT32": (2, "i"), "UINT32": (2, "I")}


def documented_registers() -> dict[str, list[dict]]:
    """Device name → its register table rows from docs/modbus_registers.md."""
    text = (DOCS / "modbus_registers.md").read_text()
    devices = {}
    for title, device_id, body in re.findall(
            r"^## ([^\n]+?) \(default device id (\d+)\)\n(.*?)(?=^## |\Z)", text, re.M | re.S):
        rows = [line.strip("|").split("|") for line in body.splitlines()
                if re.match(r"\| \d+ \|", line)]
        devices[title] = {"id": int(device_id), "registers": [
            {"address": int(r[0]), "name": r[1].strip(), "type": r[2].strip(),
             "scale": float(r[3]), "access": r[5].strip()} for r in rows]}
    return devices


def decode(words: list[int], datatype: str, scale: float) -> float:
    count, code = WORDS[datatype]
    raw = struct.unpack(">" + code, struct.pack(">" + "H" * count, *words))[0]
    return raw * scale


def read_all(client: ModbusTcpClient, device: dict) -> dict[str, float]:
    """Every documented register read on its own, and the whole block in one request: the
    same values (no SYNC in between)."""
    values = {}
    for r in device["registers"]:
        count = WORDS[r["type"]][0]
        response = client.read_holding_registers(r["address"], count=count,
                                                 device_id=device["id"])
        assert not response.isError(), (device, r, response)
        values[r["name"]] = decode(response.registers, r["type"], r["scale"])
    last = device["registers"][-1]
    end = last["address"] + WORDS[last["type"]][0]
    block = client.read_holding_registers(0, count=end, device_id=device["id"]).registers
    for r in device["registers"]:
        words = block[r["address"]:r["address"] + WORDS[r["type"]][0]]
        assert decode(words, r["type"], r["scale"]) == values[r["name"]]
    return values


def test_the_docs_list_both_modbus_devices_and_the_sims_serve_them(lab, rack):
    devices = documented_registers()
    assert {name: d["id"] for name, d in devices.items()} == {
        "Spindle inverter": 1, "Load-cell amplifier": 2}
    assert sum(len(d["registers"]) for d in devices.values()) == 13
    # the lab sim serves every registered peer: an installed lab package's beside these
    assert lab.info["modbus_devices"].items() >= {"spindle inverter": 1,
                                                  "load-cell amplifier": 2}.items()
    assert rack.info["modbus_devices"] == {"load-cell amplifier": 2}
    assert rack.info["devices"]["load_cell"] == {"address": rack.info["modbus"], "unit_id": 2}


def test_lab_sim_serves_every_register_of_both_devices(lab, lab_can):
    """Power-on values as documented (inverter: stopped, 200 rpm/s, 100 %, 6000 rpm; load
    cell: ±25 000 N, 16 bits, no overload); after 200 SYNCs the load cell has sampled 200
    times: force = counts · 2·RANGE/2^bits is the 2 N noise around the idle tip force 0."""
    devices = documented_registers()
    drive = lab_can.node(lab.info["node_id"], str(packaged_eds_path()))
    client = _modbus(lab.info)
    try:
        inverter = read_all(client, devices["Spindle inverter"])
        assert inverter == {"CONTROL": 0, "STATUS": 0, "SPEED_SETPOINT": 0.0,
                            "SPEED_ACTUAL": 0.0, "RAMP_RATE": 200.0, "FAULT_CODE": 0,
                            "FEED_OVERRIDE": 100.0, "MAX_SPEED": 6000.0}
        forces = []
        for _ in range(40):
            lab_can.syncs(5, drive)
            cell = read_all(client, devices["Load-cell amplifier"])
            forces.append(cell["FORCE_COUNTS"] * 2 * cell["RANGE"] / 2 ** cell["ADC_BITS"])
        assert {k: v for k, v in cell.items() if k != "FORCE_COUNTS"} == {
            "STATUS": 0, "CONTROL": 0, "RANGE": 25000.0, "ADC_BITS": 16}
    finally:
        client.close()
    mean = sum(forces) / len(forces)
    rms = (sum((f - mean) ** 2 for f in forces) / len(forces)) ** 0.5
    assert abs(mean) < 1.5 and 1.2 < rms < 3.0, forces


def test_rack_sim_serves_the_load_cell_and_both_drives(rack):
    """The bumper's load cell (device id 2) with every register; master and slave answer
    SDO reads of every object of rack_pinion.eds; the axis objects hold the world's preload
    (10 % = 100 ‰), weights 0.5, coupled, and the rated force at the rack (0x6076, mN)."""
    device = documented_registers()["Load-cell amplifier"]
    client = _modbus(rack.info)
    try:
        cell = read_all(client, device)
    finally:
        client.close()
    assert cell == {"FORCE_COUNTS": 0, "STATUS": 0, "CONTROL": 0, "RANGE": 25000.0,
                    "ADC_BITS": 16}
    can_client = CanClient(rack.info)
    try:
        nodes = {name: can_client.node(rack.info[key], str(rack_eds_path()))
                 for name, key in (("master", "node_id"), ("slave", "slave_node_id"))}
        values = {name: read_every_object(node) for name, node in nodes.items()}
    finally:
        can_client.close()
    rated_mN = round(world_truth({})["rated_force"] * 1e3)
    master = values["master"]
    assert (master[(0x2040, 0)], master[(0x2041, 0)], master[(0x2042, 0)],
            master[(0x2043, 0)]) == (100, 0.5, 0.5, 0)
    for node in values.values():
        assert node[(0x6076, 0)] == rated_mN
        assert node[(0x6041, 0)] == 0x0240  # switch on disabled, remote
        assert node[(0x2050, 0)] == 0 and node[(0x2051, 0)] == 0


def read_every_object(node: canopen.RemoteNode) -> dict[tuple[int, int], int | float]:
    """SDO upload of every readable variable of the node's object dictionary: each answer
    has exactly the size of its data type (strings: any)."""
    values = {}
    for obj in node.object_dictionary.values():
        members = [obj] if isinstance(obj, ODVariable) else list(obj.values())
        for var in members:
            if not var.readable:
                continue
            data = node.sdo.upload(var.index, var.subindex)
            if var.data_type not in canopen.objectdictionary.datatypes.DATA_TYPES:
                assert len(data) == len(var) // 8, (hex(var.index), var.subindex, data)
            values[(var.index, var.subindex)] = var.decode_raw(data)
    return values


LIVE = {0x2020, 0x6041, 0x6061, 0x6064, 0x606C, 0x2010, 0x6077, 0x60F4}
"""Objects the drive serves from its state (checked one by one), not from the EDS."""


def test_lab_drive_answers_every_object_of_its_eds(lab, lab_can):
    """Every readable object of cia402.eds: parameters hold their EDS value, or the world's
    (gains of the factory tuning, force limit, cycle time 0x1006 = 1000 µs); 0x1000 is a
    CiA 402 servo drive; the statusword is switch on disabled + remote; the cycle counter
    counts SYNCs."""
    drive = lab_can.node(lab.info["node_id"], str(packaged_eds_path()))
    values = read_every_object(drive)
    assert len(values) > 100
    simulator = build_axis({}, 1e-3)
    world = {(0x1006, 0): 1000, (0x2001, 0): simulator.gains.K_p, (0x2002, 0):
             simulator.gains.T_i, (0x2003, 0): simulator.gains.K_v,
             (0x2004, 0): simulator.force_limit}
    for (index, sub), value in values.items():
        var = drive.object_dictionary.get_variable(index, sub)
        if (index, sub) in world:
            assert value == pytest.approx(world[(index, sub)], rel=1e-6), hex(index)
        elif index not in LIVE and var.default is not None:
            assert value == var.default, (hex(index), sub)
    assert values[(0x1000, 0)] == 0x00020192
    assert values[(0x6041, 0)] == 0x0240
    assert values[(0x6502, 0)] & 0x380 == 0x380  # CSP, CSV, CST
    assert lab_can.syncs(3, drive) == 3


def test_lab_io_module_answers_its_objects(lab, lab_can):
    """The CiA 401 I/O module of the exciters at the configured node: device type (profile
    401), error register, the digital output and the four analog outputs, all 0 at rest."""
    assert lab.info["devices"]["exciter"] == {"node_id": IO_NODE}
    module = lab_can.node(IO_NODE, object_dictionary())
    values = read_every_object(module)
    assert values[(0x1000, 0)] == cia401.DEVICE_TYPE
    assert values[(cia401.DIGITAL_OUTPUTS, 0)] == 1
    assert values[(cia401.ANALOG_OUTPUTS, 0)] == cia401.ANALOG_CHANNELS
    assert [values[(cia401.ANALOG_OUTPUTS, s)] for s in range(1, 5)] == [0, 0, 0, 0]
    assert values[(cia401.DIGITAL_OUTPUTS, 1)] == 0


# -- the DAQ frames ----------------------------------------------------------------------------

def crc_ccitt_false(data: bytes) -> int:
    """CRC-16/CCITT-FALSE as the doc states it (poly 0x1021, init 0xFFFF), bit by bit."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = (crc << 1 ^ 0x1021 if crc & 0x8000 else crc << 1) & 0xFFFF
    return crc


def read_frame(port: serial.Serial) -> tuple[int, bytes]:
    """One frame: sync A5 5A, type, length, payload, CRC (little-endian) checked."""
    header = port.read(4)
    assert len(header) == 4 and header[:2] == b"\xa5\x5a", header
    kind, length = header[2], header[3]
    payload = port.read(length)
    crc = port.read(2)
    assert len(payload) == length and len(crc) == 2
    assert int.from_bytes(crc, "little") == crc_ccitt_false(header[2:] + payload)
    return kind, payload


def command(port: serial.Serial, line: bytes) -> str:
    port.write(line + b"\n")
    kind, payload = read_frame(port)
    assert kind == 0x52 and 1 <= len(payload) <= 64
    return payload.decode("ascii")


def test_daq_streams_crc_framed_samples_ten_per_sync(lab, lab_can):
    """*IDN?, then all 12 inputs at 10 kHz: 200 SYNCs give exactly 2000 data frames of
    4 + 36 payload bytes with consecutive counters, valid CRCs; the idle inputs are the
    accelerometer noise of Eq. (6.18) (σ ≈ 0.016 m/s² on x) and ≈ 0 forces."""
    assert crc_ccitt_false(b"123456789") == 0x29B1 == binascii.crc_hqx(b"123456789", 0xFFFF)
    drive = lab_can.node(lab.info["node_id"], str(packaged_eds_path()))
    with serial.Serial(lab.info["devices"]["daq"]["address"], timeout=2) as port:
        assert command(port, b"*IDN?") == "OK FEEDBENCH,SIM-DAQ12,0,1.0"
        assert command(port, b"CHAN 0FFF") == "OK"
        assert command(port, b"RATE 10000") == "OK"
        assert command(port, b"START") == "OK"
        lab_can.syncs(200, drive)
        port.write(b"STOP\n")
        frames = []
        while True:
            kind, payload = read_frame(port)
            if kind == 0x52:
                assert payload == b"OK"
                break
            assert kind == 0x44 and len(payload) == 4 + 3 * 12
            frames.append(payload)
    counters = [int.from_bytes(f[:4], "little") for f in frames]
    assert len(frames) == 2000
    assert all(b - a == 1 for a, b in zip(counters, counters[1:]))
    scale = [500.0] * 6 + [20_000.0, 20_000.0, 40_000.0, 5000.0, 1000.0, 1000.0]
    columns = list(zip(*(
        [int.from_bytes(f[4 + 3 * i:7 + 3 * i], "little", signed=True) * fs / 2 ** 23
         for i, fs in enumerate(scale)] for f in frames)))
    rms = [(sum(v * v for v in column) / len(column)) ** 0.5 for column in columns]
    assert rms[0] == pytest.approx(0.016, rel=0.1)
    assert rms[2] == pytest.approx(0.0014, rel=0.1)
    assert max(rms[6:9]) < 0.01 and max(rms[9:]) < 0.2  # forces: sensor noise only


# -- faults ------------------------------------------------------------------------------------

def test_modbus_faults_get_their_exception_and_one_line(lab):
    """Unknown device id → 0x0B, undocumented address → 2, input registers (function 4) → 1,
    a write the device refuses → 3, a write to a read-only register → 2: each answered,
    each one line on stderr, and the sim keeps serving."""
    client = _modbus(lab.info)
    since = len(lab.stderr)
    try:
        answers = [
            client.read_holding_registers(0, count=2, device_id=7).exception_code,
            client.read_holding_registers(10, count=1, device_id=1).exception_code,
            client.read_input_registers(0, count=1, device_id=2).exception_code,
            client.write_register(6, 0, device_id=1).exception_code,
            client.write_register(1, 5, device_id=1).exception_code,
        ]
        assert client.read_holding_registers(4, count=2, device_id=2).registers == [0, 25000]
    finally:
        client.close()
    assert answers == [0x0B, 2, 1, 3, 2]
    lines = lab.new_stderr(since, 5)
    assert len(lines) == 5, lines
    assert "device id 7: no such device" in lines[0]
    for line, code in zip(lines[1:], (2, 1, 3, 2)):
        assert line.startswith("feedbench-sim: warning: ") and f"exception {code} " in line


def test_daq_and_sdo_faults_get_their_protocol_answer(lab, lab_can):
    """An unknown DAQ command → ``ERR …`` (one line logged); a long non-ASCII line → an ERR
    reply of at most 64 ASCII bytes, and the instrument still answers; an SDO read of an
    object the drive lacks → abort 0x06020000."""
    since = len(lab.stderr)
    with serial.Serial(lab.info["devices"]["daq"]["address"], timeout=2) as port:
        assert command(port, b"BOGUS") == "ERR unknown command 'BOGUS'"
        assert command(port, b"\xff" * 300).startswith("ERR unknown command")
        assert command(port, b"RATE 12345") == "ERR 12345 Hz is not a whole number of " \
            "samples per bench cycle"
        assert command(port, b"*IDN?").startswith("OK FEEDBENCH")
    drive = lab_can.node(lab.info["node_id"], str(packaged_eds_path()))
    with pytest.raises(SdoAbortedError) as aborted:
        drive.sdo.upload(0x5FFF, 0)
    assert aborted.value.code == 0x06020000
    lines = lab.new_stderr(since, 3)
    assert len(lines) == 3 and all("serial DAQ" in line for line in lines), lines


def test_socketcand_faults_get_the_hubs_error_and_one_line(lab):
    """A malformed frame (9 data bytes) and an unknown command to the hub are answered
    ``< error … >`` in socketcand's own syntax, one line logged each."""
    host, port = lab.info["socketcand"].rsplit(":", 1)
    since = len(lab.stderr)
    with socket.create_connection((host, int(port)), timeout=2) as sock:
        replies = [_socketcand(sock, b"")]
        for text in (f"< open {lab.info['channel']} >", "< rawmode >",
                     "< send 123 9 0 1 2 3 4 5 6 7 8 >", "< bogus >"):
            replies.append(_socketcand(sock, text.encode()))
    assert replies == ["< hi >", "< ok >", "< ok >", "< error malformed frame >",
                       "< error unsupported command >"]
    lines = lab.new_stderr(since, 2)
    assert len(lines) == 2 and all("socketcand hub" in line for line in lines), lines


def _socketcand(sock: socket.socket, text: bytes) -> str:
    """Send `text` (if any), return the next ``< … >`` message from the hub."""
    if text:
        sock.sendall(text)
    reply = b""
    while not reply.endswith(b">"):
        reply += sock.recv(1)
    return reply.decode()


class BrokenInverter(SimulatedSpindleInverter):
    """An inverter whose register image cannot be built (a fault inside the device)."""

    def values(self) -> dict[str, float]:
        raise ArithmeticError("register image lost")


def test_an_exception_inside_a_device_is_exception_4_and_one_line():
    """The device's action raises: the host gets exception 4 (server device failure), the
    log one line naming device, function and error, and the next request is served."""
    stream = io.StringIO()
    with one_line_logging(stream), SimulatedModbusTcpServer([BrokenInverter()]) as server:
        client = ModbusTcpClient("127.0.0.1", port=server.port, timeout=2)
        assert client.connect()
        try:
            first = client.read_holding_registers(0, count=2, device_id=1)
            second = client.read_holding_registers(0, count=2, device_id=1)
        finally:
            client.close()
    assert (first.exception_code, second.exception_code) == (4, 4)
    lines = stream.getvalue().splitlines()
    assert len(lines) == 2 and "Traceback" not in stream.getvalue()
    assert lines[0] == ("feedbench-sim: error: feedbench.sim_backends.modbus_devices: modbus: "
                        "spindle inverter (device id 1): function 3 at address 0: "
                        "ArithmeticError: register image lost; answered with exception 4")


TPDO1 = 0x180 + NODE_ID


@pytest.mark.parametrize("hooks", ["before_physics", "after_physics"])
def test_an_exception_inside_the_world_faults_the_drive_with_emcy(can_channel, hooks):
    """A world device raises in the SYNC handler (before the physics, or an instrument after
    the cycle's TPDOs went out): the host's tick still gets one TPDO set per SYNC, never
    two, the statusword shows FAULT, EMCY 0x6100 (internal software) arrives, one line is
    logged; after a fault reset with a healthy world the drive enables again."""
    broken = []

    def world_device() -> None:
        if broken:
            raise FloatingPointError("tool-tip force is NaN")

    stream = io.StringIO()
    with one_line_logging(stream), loopback(can_channel) as bench:
        getattr(bench.device, hooks).append(world_device)
        enable(bench, CSV, velocity=0.0)
        bench.frames()
        broken.append(True)
        for _ in range(3):
            bench.clock.tick()
        cob_ids = [cob_id for cob_id, _ in bench.frames()]
        assert cob_ids.count(TPDO1) == cob_ids.count(0x80) == 3
        assert bench.drive.fault and bench.drive.emcy_code == 0x6100
        broken.clear()
        bench.drive.enable(bench.clock.tick)
        assert bench.drive.is_enabled
    lines = stream.getvalue().splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        "feedbench-sim: error: feedbench.sim_backends.cia402_drive: CiA 402 node 3: fault "
        "inside the simulated world at SYNC "), lines
    assert lines[0].endswith("FloatingPointError: tool-tip force is NaN; EMCY 0x6100")
