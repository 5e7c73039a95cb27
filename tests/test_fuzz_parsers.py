"""Parsers that never fall over (issue 18.5): every parser that reads bytes from outside,
fed malformed input by hypothesis (mutated valid input and raw bytes).

Each parser's contract, checked per input by `Target.outcome`:
- CANopen frames to the host driver and to the simulated drive, serial DAQ frames, raw Modbus
  TCP (MBAP) frames to the simulated devices: never raise; a bad frame is dropped, counted or
  answered (SDO abort, EMCY, Modbus exception), and that answer is its rejection reason.
- CSV + sidecar, EMPS and KUKA .mat, feedbench HDF5, UFF58 files (read, analysed and
  described as `feedbench analyze FILE.uff` does): a `ConfigError` "<file or field>: <reason>"
  and nothing else; an HDF5 file libhdf5 would read forever is rejected before it reads it.
Any other exception, or a traceback logged by a library on the way, is a crash.
`benchmarks/bench_fuzz.py` runs the same targets with ≥ 10⁵ inputs each.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import random
import re
import socket
import struct
import subprocess
import sys
import uuid
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Sequence

import h5py
import numpy as np
import pytest
import scipy.io
from hypothesis import HealthCheck, given, settings, strategies as st
from pymodbus.exceptions import ModbusIOException
from pymodbus.pdu import ExceptionResponse
from pymodbus.server import ModbusTcpServer

from feedbench.config import ConfigError
from feedbench.closure_io import read_csv_trace, read_mat
from feedbench.daq.hdf5_check import DamagedHdf5, check_global_heaps
from feedbench.daq.recorder import Recorder
from feedbench.daq.recording import open_recording
from feedbench.drivers.serial_daq import FrameParser
from feedbench.commands.exchange import analyze_uff58, describe_uff58, write_uff58
from feedbench.protocols import cia301
from feedbench.protocols.serial_frames import TYPE_REPLY, data_frame_bytes
from feedbench.sim_backends.modbus_devices import (
    SimulatedLoadCell, SimulatedModbusTcpServer, SimulatedSpindleInverter)
from feedbench.sim_backends.serial_daq import encode_data_frames, encode_frame
from feedbench.views.frfs import Dof, ExchangeFrf
from test_cia402_sim import NODE_ID, loopback
from test_modbus_devices import ask

OK = "ok"
SDO_RX, SDO_TX, EMCY = 0x600 + NODE_ID, 0x580 + NODE_ID, 0x80 + NODE_ID
"""COB-IDs of the simulated drive's SDO server and EMCY producer (CiA 301)."""
SIDECAR_SEPARATOR = b"\n##sidecar##\n"
"""Splits a CSV target's input into the CSV text and its sidecar's TOML."""


def mutate(seed: bytes, operations: Sequence[tuple[int, int, int]]) -> bytes:
    """`seed` after each (kind, position, value): 0 xor a byte with value, 1 truncate,
    2 insert value, 3 delete a byte (positions modulo the current length)."""
    data = bytearray(seed)
    for kind, position, value in operations:
        at = position % (len(data) + 1)
        if kind == 0 and at < len(data):
            data[at] ^= value or 1
        elif kind == 1:
            del data[at:]
        elif kind == 2:
            data.insert(at, value)
        elif kind == 3 and at < len(data):
            del data[at]
    return bytes(data)


def random_operations(rng: random.Random, size: int) -> list[tuple[int, int, int]]:
    """1–8 random mutations for a seed of `size` bytes (the benchmark's generator)."""
    return [(rng.randrange(4), rng.randrange(size + 1), rng.randrange(256))
            for _ in range(rng.randint(1, 8))]


def reason_key(reason: str) -> str:
    """A rejection reason with its numbers and quoted values blanked, to group by."""
    text = re.sub(r"'[^']*'|\"[^\"]*\"", "'…'", reason)
    return re.sub(r"0x[0-9A-Fa-f]+|\d+(\.\d+)?(e-?\d+)?", "#", text)[:90]


class LoggedTraceback(logging.Handler):
    """Collects every log record that carries a traceback (a library caught a crash)."""

    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.exc_info or "Traceback" in record.getMessage():
            self.records.append(record)


@dataclass
class Target:
    """One parser: valid `seeds`, and `parse(data) -> "ok" | "rejected: <reason>"`, which
    raises only for a crash (a documented error is turned into its rejection by `parse`)."""

    name: str
    seeds: list[bytes]
    parse: Callable[[bytes], str]
    tracebacks: LoggedTraceback
    cob_ids: Sequence[int] = ()
    """CAN targets: the COB-IDs byte 0 of an input picks from (`can_frame`)."""

    def outcome(self, data: bytes) -> str:
        """The parse's result; AssertionError if it crashed (raised or logged a traceback)."""
        before = len(self.tracebacks.records)
        try:
            result = self.parse(data)
        except Exception as exc:
            raise AssertionError(f"{self.name}: {data!r} crashed: {type(exc).__name__}: "
                                 f"{exc}") from exc
        logged = self.tracebacks.records[before:]
        assert not logged, f"{self.name}: {data!r} logged a traceback: {logged[0].getMessage()}"
        assert result == OK or result.startswith("rejected: "), result
        return result


def rejected(reason: str) -> str:
    return f"rejected: {reason}"


def config_error(read: Callable[[], object], path: Path) -> str:
    """`read()`'s outcome: ok, or the reason of its ConfigError (the file name left out)."""
    try:
        read()
    except ConfigError as exc:
        message = str(exc).replace(f"{path.parent}/", "")
        assert ": " in message, message
        return rejected(message)
    return OK


# -- CANopen -------------------------------------------------------------------------------


def can_frame(data: bytes, cob_ids: Sequence[int]) -> tuple[int, bytearray]:
    """An input as one CAN frame: byte 0 picks the COB-ID, at most 8 data bytes follow."""
    return cob_ids[data[0] % len(cob_ids)] if data else cob_ids[0], bytearray(data[1:9])


def dropped(counter: collections.Counter[str], before: collections.Counter[str]) -> str:
    """The reason a frame was just dropped for (counted in `counter`), or "ok"."""
    new = counter - before
    return rejected(next(iter(new))) if new else OK


def host_can_target(bench, tracebacks: LoggedTraceback) -> Target:
    """Frames to the host driver: TPDOs, EMCY, heartbeat, SDO responses, SYNC."""
    drive = bench.drive
    network = drive.network
    cob_ids = sorted(network.subscribers)

    def parse(data: bytes) -> str:
        before = drive.rejected_frames.copy()
        network.notify(*can_frame(data, cob_ids), 0.0)
        return dropped(drive.rejected_frames, before)

    seeds = [bytes([i]) + bytes(8) for i in range(len(cob_ids))]
    return Target("can_host", seeds, parse, tracebacks, cob_ids)


def sim_can_target(bench, tracebacks: LoggedTraceback) -> Target:
    """Frames to the simulated drive: NMT, SYNC, RPDOs, SDO requests; its answers (SDO
    abort, EMCY) and the frames it drops are the rejections."""
    device, listener = bench.device, bench.listener
    network = device.network
    cob_ids = sorted(network.subscribers)

    def parse(data: bytes) -> str:
        before = device.rejected_frames.copy()
        network.notify(*can_frame(data, cob_ids), 0.0)
        result = dropped(device.rejected_frames, before)
        while (message := listener.recv(0)) is not None:
            if message.arbitration_id == SDO_TX and message.data[0] == 0x80:
                result = rejected("SDO abort 0x%08X" % struct.unpack_from("<I", message.data, 4))
            elif message.arbitration_id == EMCY:
                result = rejected("EMCY 0x%04X" % struct.unpack_from("<H", message.data))
        return result

    sdo_rx = cob_ids.index(SDO_RX)
    seeds = [bytes([sdo_rx, 0x40, 0x41, 0x60, 0, 0, 0, 0, 0]),  # upload of the statusword
             bytes([sdo_rx, 0x2B, 0x40, 0x60, 0, 0x06, 0, 0, 0]),  # controlword 6
             bytes([cob_ids.index(cia301.NMT_COB_ID), 0x01, NODE_ID])]
    return Target("can_sim", seeds, parse, tracebacks, cob_ids)


# -- serial DAQ ----------------------------------------------------------------------------


def serial_daq_target(tracebacks: LoggedTraceback) -> Target:
    """A byte stream to the DAQ's frame parser (3 channels); counted CRC errors and skipped
    bytes are its rejections, and every frame it returns is well formed."""
    counts = np.array([[1, -2, 2**23 - 1], [0, 5, -2**23]] * 3, dtype=np.int32)
    stream = encode_data_frames(np.arange(6, dtype=np.uint32), counts).tobytes()
    middle = 3 * data_frame_bytes(3)
    seed = stream[:middle] + encode_frame(TYPE_REPLY, b"OK 1000") + stream[middle:]

    def parse(data: bytes) -> str:
        parser = FrameParser(3)
        block, _replies = parser.feed(data)
        assert block.samples.shape == (len(block.sequence), 3)
        assert np.all(np.abs(block.samples) <= 2**23) and np.all(np.diff(block.sequence) > 0)
        if parser.crc_errors:
            return rejected("CRC error")
        return rejected("bytes skipped before a sync word") if parser.skipped_bytes else OK

    return Target("serial_daq", [seed], parse, tracebacks)


# -- Modbus TCP ----------------------------------------------------------------------------


def modbus_target(tracebacks: LoggedTraceback, loop: asyncio.AbstractEventLoop) -> Target:
    """Raw MBAP bytes to the simulated inverter and load cell, handled as the TCP server
    handles them (pymodbus's socket framer, `DocumentedFunctions`, `AnsweringContext`);
    each exception answer or an incomplete frame is a rejection."""
    async def make_server() -> ModbusTcpServer:  # pymodbus builds it in a running loop
        devices = [SimulatedSpindleInverter(), SimulatedLoadCell(lambda: 0.0)]
        return SimulatedModbusTcpServer(devices)._make_server()

    server = loop.run_until_complete(make_server())
    framer = server.framer(server.decoder)

    def parse(data: bytes) -> str:
        try:
            used, request = framer.handleFrame(data, 0, 0)
        except ModbusIOException:  # the server answers exception 1
            return rejected("undecodable request: exception 1")
        if request is None:
            return rejected("incomplete or foreign frame: no answer") if data else OK
        response = loop.run_until_complete(request.datastore_update(server.context,
                                                                    request.dev_id))
        framer.buildFrame(response)
        if isinstance(response, ExceptionResponse):
            return rejected(f"function {response.function_code:#x}: exception "
                            f"{response.exception_code}")
        return OK

    def request(device: int, pdu: bytes) -> bytes:
        return struct.pack(">HHHB", 7, 0, len(pdu) + 1, device) + pdu

    seeds = [request(1, bytes.fromhex("0300000004")), request(2, bytes.fromhex("0600030000")),
             request(1, bytes.fromhex("1000020002040000" "03e8"))]
    return Target("modbus_tcp", seeds, parse, tracebacks)


# -- files ---------------------------------------------------------------------------------


def csv_target(directory: Path, tracebacks: LoggedTraceback) -> Target:
    """A CSV trace and its sidecar (one input: CSV, `SIDECAR_SEPARATOR`, TOML; without the
    separator the seed's sidecar)."""
    path = directory / "trace.csv"
    csv_text = b"t,x_mm,F_N\n" + b"".join(b"%g,%g,%g\n" % (i * 1e-3, i * 0.01, 2.0 - i)
                                           for i in range(20))
    sidecar = (b'name = "fuzz"\nforce_lag_ms = 0\n[columns]\ntime = "t"\nposition = "x_mm"\n'
               b'force = "F_N"\n[units]\nposition = "mm"\n')

    def parse(data: bytes) -> str:
        table, separated, toml = data.partition(SIDECAR_SEPARATOR)
        path.write_bytes(table)
        toml = toml if separated else sidecar  # cut before the sidecar: the seed's
        path.with_suffix(".toml").write_bytes(toml)
        return config_error(lambda: read_csv_trace(path), path)

    return Target("csv_sidecar", [csv_text + SIDECAR_SEPARATOR + sidecar], parse, tracebacks)


def file_target(name: str, path: Path, seed: bytes, read: Callable[[Path], object],
                tracebacks: LoggedTraceback) -> Target:
    """A reader of whole files: the input is the file's content."""
    def parse(data: bytes) -> str:
        path.write_bytes(data)
        return config_error(lambda: read(path), path)

    return Target(name, [seed], parse, tracebacks)


def emps_seed(path: Path) -> bytes:
    n = 16
    scipy.io.savemat(path, {"t": np.arange(n) * 1e-3, "qm": np.linspace(0, 1, n),
                            "qg": np.linspace(0, 1, n), "vir": np.ones(n), "gtau": 35.0,
                            "pulses_N": np.zeros(n)})
    return path.read_bytes()


def kuka_seed(path: Path) -> bytes:
    n, axes = 20, 2
    rows = np.ones((axes, n))
    scipy.io.savemat(path, {
        "rec": {"time_cont": np.arange(n) * 1e-3, "act_pos_mot_deg": rows,
                "act_torque_abs_nm": rows, "ref_pos_deg": rows},
        "para": {"u": np.full(axes, 100.0)}, "n_axis": axes, "m_all": np.ones(axes),
        "ref_kin": {"phi_r_all_d2": np.ones((n, axes))}, "tau_a_all": rows,
        "tau_c_all": rows, "tau_g_all": rows, "tau_g_init": np.zeros(axes)})
    return path.read_bytes()


def hdf5_seed(path: Path) -> bytes:
    with Recorder(path, ["position", "force"], {"position": "m", "force": "N"},
                  {"experiment": "fuzz", "config": {}, "cycle_s": 1e-3}, chunk_rows=4) as rec:
        for cycle in range(6):
            rec.append(cycle, [cycle * 1e-6, 1.0])
        rec.event(3, "note", "fuzz")
    return path.read_bytes()


def uff_seed(path: Path) -> bytes:
    f = np.linspace(0.0, 100.0, 4)
    frf = ExchangeFrf("fuzz", "none", f, (1 + 1j) * np.ones(4),
                      Dof("acc", "tool", 1, 1, "acceleration"), Dof("F", "tool", 1, 1, "force"),
                      np.ones(4))
    return write_uff58(path, [frf]).read_bytes()


def file_targets(directory: Path, tracebacks: LoggedTraceback) -> list[Target]:
    """CSV + sidecar, EMPS .mat, KUKA .mat (axis 1), HDF5 recording, UFF58 (analysed)."""
    seeds = directory / "seeds"
    seeds.mkdir()
    return [csv_target(directory, tracebacks),
            file_target("emps_mat", directory / "emps.mat", emps_seed(seeds / "emps.mat"),
                        read_mat, tracebacks),
            file_target("kuka_mat", directory / "kuka.mat", kuka_seed(seeds / "kuka.mat"),
                        lambda path: read_mat(path, 1), tracebacks),
            file_target("hdf5_recording", directory / "run.h5", hdf5_seed(seeds / "run.h5"),
                        open_recording, tracebacks),
            file_target("uff58", directory / "frf.uff", uff_seed(seeds / "frf.uff"),
                        lambda path: describe_uff58(analyze_uff58(path)), tracebacks)]


@contextmanager
def targets(directory: Path) -> Iterator[dict[str, Target]]:
    """Every fuzz target, its peers running (a simulated drive and host on a virtual CAN
    bus, the Modbus devices); log records with a traceback are collected meanwhile."""
    tracebacks = LoggedTraceback()
    logging.getLogger().addHandler(tracebacks)
    with ExitStack() as stack:
        stack.callback(logging.getLogger().removeHandler, tracebacks)
        bench = stack.enter_context(loopback(f"fuzz-{uuid.uuid4().hex[:8]}"))
        loop = asyncio.new_event_loop()
        stack.callback(loop.close)
        found = [host_can_target(bench, tracebacks), sim_can_target(bench, tracebacks),
                 serial_daq_target(tracebacks), modbus_target(tracebacks, loop),
                 *file_targets(directory, tracebacks)]
        for target in found:
            for seed in target.seeds:
                assert target.outcome(seed) == OK, (target.name, target.outcome(seed))
        yield {target.name: target for target in found}


# -- the suite -----------------------------------------------------------------------------

EXAMPLES = {"can_host": 500, "can_sim": 500, "serial_daq": 500, "modbus_tcp": 500,
            "csv_sidecar": 250, "emps_mat": 250, "kuka_mat": 250, "hdf5_recording": 200,
            "uff58": 200}


@pytest.fixture(scope="module")
def fuzz_targets(tmp_path_factory) -> Iterator[dict[str, Target]]:
    with targets(tmp_path_factory.mktemp("fuzz")) as found:
        yield found


def malformed(seeds: list[bytes]) -> st.SearchStrategy[bytes]:
    """Raw bytes, or a seed after 1–8 mutations (`mutate`)."""
    operation = st.tuples(st.integers(0, 3), st.integers(0, 2**16), st.integers(0, 255))
    return st.one_of(st.binary(max_size=80),
                     st.builds(mutate, st.sampled_from(seeds),
                               st.lists(operation, min_size=1, max_size=8)))


@pytest.mark.parametrize("name", list(EXAMPLES))
def test_malformed_input_is_rejected_with_its_reason_never_a_crash(fuzz_targets, name):
    target = fuzz_targets[name]
    reasons: set[str] = set()

    @settings(max_examples=EXAMPLES[name], derandomize=True, deadline=None, database=None,
              suppress_health_check=list(HealthCheck))
    @given(malformed(target.seeds))
    def fuzz(data: bytes) -> None:
        result = target.outcome(data)
        if result != OK:
            reasons.add(reason_key(result))

    fuzz()
    assert reasons, f"{name}: no input rejected"


def frame(target: Target, cob_id: int, data: bytes) -> bytes:
    """The input `can_frame` turns into (`cob_id`, `data`)."""
    return bytes([list(target.cob_ids).index(cob_id)]) + data


def emps_with(seed: bytes, marker: bytes, offset: int, value: int) -> bytes:
    """The EMPS seed with the byte at `offset` from `marker` or'ed with `value`."""
    data = bytearray(seed)
    data[seed.index(marker) + offset] |= value
    return bytes(data)


def test_the_crashes_fuzzing_found_are_rejections_with_their_reason(tmp_path):
    with targets(tmp_path) as fresh:  # peers in their first state, not the fuzzed one
        check_found_crashes(fresh)


def check_found_crashes(fuzz_targets: dict[str, Target]) -> None:
    host, sim = fuzz_targets["can_host"], fuzz_targets["can_sim"]
    emps, csv_text = fuzz_targets["emps_mat"].seeds[0], fuzz_targets["csv_sidecar"].seeds[0]
    uff = fuzz_targets["uff58"]
    record7 = b"         6         4         1"  # the FRF's record 7: type, lines, even
    data_end = uff.seeds[0].index(b"    -1\n", uff.seeds[0].index(b"58b"))
    tpdo = cia301.TPDO_COB_BASE + NODE_ID
    cases = [  # target, input, reason (before: the crash)
        (sim, frame(sim, SDO_RX, bytes([0x60]) + bytes(7)),  # TypeError logged by canopen
         "SDO abort 0x05040001"),
        (sim, frame(sim, cia301.NMT_COB_ID, b"\x01"),  # struct.error from canopen's NmtSlave
         "COB-ID 0x000: 1 data bytes, the service needs 2"),
        (host, frame(host, EMCY, b"\x10\x81"),  # struct.error from canopen's EMCY consumer
         f"COB-ID 0x{EMCY:03X}: 2 data bytes, the service needs 8"),
        (host, frame(host, 0x700 + NODE_ID, b"\x6d"),  # KeyError 109 at the next NMT command
         f"COB-ID 0x{0x700 + NODE_ID:03X}: heartbeat state 109 unknown"),
        (host, frame(host, tpdo, b"\x37"),  # struct.error in the driver's TPDO decoding
         f"TPDO 0x{tpdo:03X}: 1 data bytes, mapped 8"),
        (fuzz_targets["emps_mat"], emps_with(emps, b"vir\x00", 5, 0x04),  # SIGBUS in scipy
         "emps.mat: not a readable MATLAB file (a data element of unknown type 1033)"),
        (fuzz_targets["emps_mat"], emps_with(emps, b"gtau", -27, 0x08),  # SIGSEGV in scipy
         "emps.mat: not a readable MATLAB file (a matrix of class 6 with 4 of its 5 elements)"),
        (fuzz_targets["hdf5_recording"], fuzz_targets["hdf5_recording"].seeds[0][:-2],  # hang
         "run.h5: not a readable HDF5 file (Unable to synchronously open file (truncated "
         "file: eof = "),
        (fuzz_targets["csv_sidecar"], csv_text.replace(b"0.002", b"0.\xff02"),
         "trace.csv: not a text file ('utf-8' codec can't decode byte 0xff"),
        (fuzz_targets["csv_sidecar"], csv_text[:11] + csv_text[csv_text.index(b"0.009"):],
         "trace.csv: time: need at least 16 samples, got 11"),  # Trace's ValueError
        (uff, uff.seeds[0][:data_end - 1] + uff.seeds[0][data_end:],  # IndexError in analyze
         "frf.uff dataset 1: 3 values on 4 frequency lines"),
        (uff, uff.seeds[0].replace(record7, record7.replace(b"4", b"3")),  # was read as 4
         "frf.uff dataset 1: record 7 says 3 lines, the data holds 4"),
        (uff, uff.seeds[0].replace(record7, record7.replace(b"4", b"x")),  # pyuff's own words
         "frf.uff: not a readable universal file (Error when reading data-set(s): ValueError: "
         "invalid literal for int() with base 10: 'x')"),
    ]
    for target, data, reason in cases:
        assert target.outcome(data).startswith(rejected(reason)), (target.name, reason)


def test_the_modbus_tcp_server_answers_after_malformed_frames_on_the_socket(fuzz_targets):
    """The served path itself: each malformed MBAP frame on its own connection to a running
    server, which still answers a valid read with the inverter's 10 registers."""
    devices = [SimulatedSpindleInverter(), SimulatedLoadCell(lambda: 0.0)]
    tracebacks = fuzz_targets["modbus_tcp"].tracebacks.records
    logged = len(tracebacks)
    with SimulatedModbusTcpServer(devices) as server:
        address = ("127.0.0.1", server.port)

        @settings(max_examples=40, derandomize=True, deadline=None, database=None,
                  suppress_health_check=list(HealthCheck))
        @given(malformed(fuzz_targets["modbus_tcp"].seeds))
        def send(data: bytes) -> None:
            with socket.create_connection(address, timeout=1.0) as raw:
                raw.sendall(data)

        send()
        with socket.create_connection(address, timeout=5.0) as raw:
            answer = ask(raw, 1, 1, bytes.fromhex("03 0000 000a"))
    assert answer[:2] == bytes.fromhex("03 14") and len(answer) == 22
    assert tracebacks[logged:] == []


READ_EACH = """
import sys
from feedbench.config import ConfigError
from feedbench.daq.recording import open_recording
for path in sys.argv[1:]:
    try:
        print(open_recording(path).status)
    except ConfigError as exc:
        print(exc)
"""
"""Prints each recording's status or the reason it is rejected (run in a child process)."""


def heap_object(data: bytes, index: int) -> int:
    """Where object `index` of the first global heap collection in `data` starts (objects:
    index u16, references u16, reserved 4 bytes, size u64, data padded to 8 bytes)."""
    at = data.index(b"GCOL") + 16
    while struct.unpack_from("<H", data, at)[0] != index:
        at += 16 + -(-struct.unpack_from("<Q", data, at + 8)[0] // 8) * 8
    return at


def with_heap_object_size(data: bytes, index: int, size: int) -> bytes:
    """`data` with the size of object `index` of its first global heap collection set."""
    changed = bytearray(data)
    struct.pack_into("<Q", changed, heap_object(data, index) + 8, size)
    return bytes(changed)


def with_heap_byte_moved(data: bytes, index: int) -> bytes:
    """`data` with a byte inserted into object `index`'s data and a zero byte of the free
    space (object 0) deleted, so all behind the collection stays in place: the damage
    bench_fuzz found (object 8, the versions; libhdf5 reads object 9 one byte late, with a
    size of 1280, which steps into the zeros of the free space)."""
    at, free = heap_object(data, index) + 16, heap_object(data, 0) + 16
    return data[:at] + b"\x8d" + data[at:free] + data[free + 1:]


def test_an_hdf5_file_libhdf5_would_read_forever_is_rejected_in_bounded_time(tmp_path):
    """Each file read in a child process with a time limit (libhdf5's loop holds the GIL:
    in this process it would hang the suite). Without the pre-check h5py hangs on the first
    three, and on the fourth when it opens it by SWMR (a writer died with it open)."""
    seed = hdf5_seed(tmp_path / "seed.h5")
    heap = seed.index(b"GCOL")
    cases = {
        with_heap_byte_moved(seed, 8): f"global heap at byte {heap}: object 0 at byte 1720 "
                                       f"has size 0: a step of 0, HDF5 would read it forever",
        with_heap_object_size(seed, 0, 0): "object 0 at byte 496 has size 0: a step of 0",
        with_heap_object_size(seed, 1, 2**64 - 16):  # 16 + 2^64 - 16 wraps to 0
            "object 1 at byte 16 has size 18446744073709551600: a step of 0",
        seed[:heap + 100]:  # what SWMR reads past the end of a file a dead writer left
            "object 0 at byte 104 (past the file's end: zeros) has size 0: a step of 0",
        with_heap_object_size(seed, 1, 5000): "object 1 at byte 16 has size 5000, past the "
                                              "collection's 4096 bytes",
        seed: "complete",
    }
    paths = [tmp_path / f"case{number}.h5" for number in range(len(cases))]
    for path, data in zip(paths, cases):
        path.write_bytes(data)
    child = subprocess.run([sys.executable, "-c", READ_EACH, *map(str, paths)],
                           capture_output=True, text=True, timeout=60)
    lines = child.stdout.splitlines()
    assert len(lines) == len(cases), child.stderr
    for line, reason in zip(lines, cases.values()):
        assert reason in line, (line, reason)
    assert all(": not a readable HDF5 file (global heap at byte " in line for line in lines[:-1])


def test_heap_signatures_in_recorded_samples_are_not_heaps(tmp_path):
    """A channel whose samples spell a global heap's signature and a size no file holds
    reads back (the pre-check walks only collections inside the file's address space)."""
    words = np.frombuffer(b"GCOL\x01\x00\x00\x00" + struct.pack("<Q", 2**62), dtype=float)
    path = tmp_path / "signature.h5"
    with Recorder(path, ["position"], {"position": "m"},
                  {"experiment": "fuzz", "config": {}, "cycle_s": 1e-3}, chunk_rows=4) as rec:
        for cycle, value in enumerate([*words, 0.0, 0.0]):
            rec.append(cycle, [value])
    assert words.tobytes() in path.read_bytes()  # as written: the file holds the signature
    assert np.array_equal(open_recording(path).channels["position"][:2], words)


@pytest.mark.parametrize("libver, userblock", [("earliest", 0), ("latest", 0), ("latest", 1024)])
def test_the_heap_check_reads_each_superblock(tmp_path, libver, userblock):
    """Superblock version 0 and 3, with and without a userblock: an intact file passes, a
    free-space object of size 0 is found where it is."""
    path = tmp_path / "any.h5"
    with h5py.File(path, "w", libver=libver, userblock_size=userblock) as file:
        file.attrs["text"] = "hello"
    check_global_heaps(path)
    path.write_bytes(with_heap_object_size(path.read_bytes(), 0, 0))
    with pytest.raises(DamagedHdf5, match=f"global heap at byte {2048 + userblock}: object 0 "
                                          f"at byte 40 has size 0: a step of 0"):
        check_global_heaps(path)
