"""The fault matrix (issue 18.4): each fault x each experiment family, and its table.

Shared by tests/test_fault_matrix.py and tests/test_fault_matrix_devices.py (the faults
injected in the simulated peers, a full disk and SIGINT, run in this process in lockstep)
and tests/test_fault_matrix_host.py (SIGKILL of the host process). Every row measures where
the host detected the fault (the run's ``abort`` event, in bus cycles after the fault's
cycle), when the drive left operation enabled (the simulated drive's `state_log`; SIGKILL:
its state read by SDO), the samples the file keeps and its reason. `row_line` formats a
row of docs/faults.md; each row test compares its line with the committed one
(`committed_line`), so the table stays true, and with ``FEEDBENCH_WRITE_FAULT_TABLE=1``
writes its line there instead (`write_line`). The in-process rows of a file are measured
`ROW_PROCESSES` at a time in forked processes (`measure_rows`), each row's test checks what
its row measured (`row_test`).
"""

from __future__ import annotations

import fcntl
import multiprocessing
import os
import re
import resource
import signal
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import numpy as np
import pytest

from feedbench.axes import axis_kind
from feedbench.bench import Bench, parse_run_config
from feedbench.config import OWN_DISTRIBUTION
from feedbench.daq.catalog import Catalog
from feedbench.daq.recording import Recording, open_recording
from feedbench.commands.demo import campaign_config
from feedbench.engine.family import families
from feedbench.protocols.cia402 import CYCLE_COUNTER, OPERATION_ENABLED
from feedbench.testing import virtual_channel

DOC = Path(__file__).parents[1] / "docs" / "faults.md"
HEADER = ("| fault | family | detected after | stop after | samples kept | reason |\n"
          "|---|---|---|---|---|---|")
AT_CYCLE = 300
"""The SYNC count at which the injected faults start: mid-run in every family (the drive is
enabled by cycle 10)."""
TIMEOUT_S = 0.5
"""The host's bus timeout in the matrix (`bench.timeout_s`; 1 s by default)."""
ASYNC_CYCLES = 5000
"""A fault the host notices on its own time (the DAQ's reader thread) is noticed within this
many bus cycles: lockstep cycles run several times faster than real time and the reader
thread lags on a loaded machine (measured up to 1557 cycles, typically 1–20)."""
FILE_LIMIT_BYTES = 1_250_000
"""The disk-full rows' file-size limit: the recorder's 1 MiB reserve and ≈ 150 kB of samples."""
ROW_PROCESSES = 8
"""Rows measured at once, each in a forked process (`measure_rows`): a row is ≈ 15 % CPU
(≈ 0.35 of its 2.4 s; the rest waits on the host's 0.5 s bus timeout and the safe stop's
SDO timeouts), so eight at once keep about one core busy (test_fault_matrix.py: 98 s one
after the other, 33 s four at once, 22 s eight at once, the same CPU; 29 Nov, load 4). The
rows count bus cycles, which the lockstep clock makes independent of the machine's load."""
MODBUS_KINDS = {"spindle", "load_cell"}
SERIAL_KINDS = {"daq"}


@dataclass(frozen=True)
class Fault:
    """One column of the matrix: the ``[bench.world.faults]`` table that injects it (None for
    the host's own faults), the device kinds it needs (empty: every family), the words the
    abort reason must hold, and whether the host notices it on its own time (a serial link
    read by a thread; a signal), so that its cycle counts vary from run to run."""

    name: str
    table: dict[str, Any] | None
    needs: frozenset[str]
    reason: str
    asynchronous: bool = False
    what: str = ""
    racing: frozenset[str] = frozenset()
    """Device kinds beside which the fault is noticed on the host's own time (a full disk
    found by the DAQ stream's writes, which its reader thread times)."""


FAULTS = (
    Fault("can_loss", {"can_loss_share": 0.05, "seed": 3}, frozenset(), "BusTimeout",
          what="5 % of the drives' frames lost (seeded)"),
    Fault("can_burst", {"can_burst_s": 2.0}, frozenset(), "BusTimeout",
          what="every frame the drives send lost for 2 s"),
    Fault("sync_timeout", {"sync_timeout_s": 3.0}, frozenset(), "BusTimeout",
          what="the drives hear no SYNC for 3 s"),
    Fault("pdo_timeout", {"pdo_timeout_s": 3.0}, frozenset(), "BusTimeout",
          what="the drives send no PDO for 3 s"),
    Fault("emcy", {"emcy_code": 0x2310}, frozenset(), "drive fault (EMCY 0x2310)",
          what="EMCY 0x2310 (over-current) and FAULT"),
    Fault("bus_off", {"bus_off_s": 2.0}, frozenset(), "BusTimeout",
          what="the drives bus-off for 2 s (fault reaction, EMCY 0x8140)"),
    Fault("modbus_timeout", {"modbus": "timeout"}, frozenset(MODBUS_KINDS), "No response",
          what="the Modbus devices stop answering"),
    Fault("modbus_exception", {"modbus": "exception"}, frozenset(MODBUS_KINDS),
          "Modbus exception 4", what="the Modbus devices answer exception 4"),
    Fault("serial_crc", {"serial": "crc"}, frozenset(SERIAL_KINDS), "CRC errors", True,
          what="a DAQ frame with a flipped byte"),
    Fault("serial_desync", {"serial": "desync"}, frozenset(SERIAL_KINDS), "frames dropped", True,
          what="a DAQ frame cut in half (the parser resynchronises)"),
    Fault("serial_unplug", {"serial": "unplug"}, frozenset(SERIAL_KINDS), "went away", True,
          what="the DAQ unplugged"),
    Fault("disk_full", None, frozenset(), "File too large",
          what=f"the recording's file-size limit at {FILE_LIMIT_BYTES} bytes",
          racing=frozenset(SERIAL_KINDS)),
    Fault("sigint", None, frozenset(), "interrupted by SIGINT", True,
          what="Ctrl-C to the process running the bench"),
    Fault("sigkill", None, frozenset(), "ended without finishing the run", True,
          what="SIGKILL to `feedbench run` against `feedbench sim`"),
)
FAULT = {fault.name: fault for fault in FAULTS}
FAMILIES = tuple(sorted(families(OWN_DISTRIBUTION)))


def family_config(family: str, directory: Path, faults: dict[str, Any] | None = None,
                  channel: str = "") -> dict:
    """The family's example, shortened as the demo's --quick does, recording to `directory`
    with the matrix's bus timeout and `faults` in its simulated world."""
    raw = campaign_config(family, directory, quick=True)
    raw["bench"].update(timeout_s=TIMEOUT_S, **({"channel": channel} if channel else {}))
    if faults:
        raw["bench"].setdefault("world", {})["faults"] = {"at_cycle": AT_CYCLE, **faults}
    return raw


def device_kinds(family: str) -> set[str]:
    """The device kinds a run of the family opens besides its drives."""
    config = parse_run_config(family_config(family, Path("runs")))
    return set(axis_kind(config.bench["axis"])(config.bench, config.plan,
                                               config.experiment.devices()).needs)


def applies(fault: Fault, family: str) -> bool:
    """Whether the family uses a device the fault needs."""
    return not fault.needs or bool(fault.needs & device_kinds(family))


def asynchronous(fault: Fault, family: str) -> bool:
    """Whether the host notices the fault on its own time in this family: its cycle counts
    vary from run to run."""
    return fault.asynchronous or bool(fault.racing & device_kinds(family))


def not_applicable(fault: Fault) -> str:
    """The table's text for a family without the fault's device."""
    return f"n/a: no {' or '.join(sorted(fault.needs))} device"


@dataclass(frozen=True)
class Measured:
    """What a row measured: the cycle the fault started in (None: a signal, a full disk),
    the abort event's cycle, the cycle the drive was out of operation enabled, the samples
    recorded before the fault (all of them: `assert_samples_kept`) and the file's reason."""

    fault_cycle: int | None
    abort_cycle: int
    stop_cycle: int | str
    before: int
    reason: str


def abort_cycle(recording: Recording) -> int:
    """The cycle of the run's abort event; without one (the recording failed first) the
    cycle after its last sample."""
    aborts = [event.cycle for event in recording.events if event.kind == "abort"]
    return aborts[0] if aborts else int(recording.cycle[-1]) + 1


def left_operation(state_log: list[tuple[int, str]], after: int) -> int:
    """The SYNC count at which a simulated drive last left operation enabled before or at
    `after` + 2 (its `state_log`)."""
    entered = [(count, state) for count, state in state_log if count <= after + 2]
    left = [count for (count, state), (_, previous) in zip(entered[1:], entered)
            if previous == OPERATION_ENABLED and state != OPERATION_ENABLED]
    assert entered and entered[-1][1] != OPERATION_ENABLED, entered[-3:]
    return left[-1]


def assert_samples_kept(recording: Recording, before: int) -> int:
    """Every cycle from the first recorded to `before` - 1 is in the file, in order, and the
    file's sample count is its rows; returns how many cycles that is."""
    cycles = recording.cycle
    assert recording.n_samples == len(cycles)
    head = cycles[cycles < before]
    assert np.array_equal(head, np.arange(cycles[0], before)), (cycles[0], before, len(head))
    return len(head)


def normalized(reason: str, asynchronous: bool) -> str:
    """The reason as the table shows it: the file's path and the pseudo-terminal's number
    left out; for a fault noticed on the host's own time, its cycle numbers too."""
    reason = re.sub(r"/dev/pts/\d+", "/dev/pts/N", reason)
    reason = re.sub(r"process \d+ on \S+", "process N on HOST", reason)
    reason = re.sub(r"/\S+\.h5", "<file>", reason)
    if asynchronous:
        reason = re.sub(r"\d+ bus cycles|cycle \d+", lambda m: re.sub(r"\d+", "N", m[0]),
                        reason)
    return reason.replace("|", "/")


def row_line(fault: Fault, family: str, measured: Measured | None) -> str:
    """The table row of `fault` x `family`: detected after (cycles from the fault to the
    host's abort event), stop after (cycles from the last cycle the host completed to the
    drive out of operation enabled; <= 0: the drive stopped first), samples kept (every
    cycle before the fault; those of the stop besides), reason. A fault noticed on the
    host's own time shows the bounds its test asserts."""
    if measured is None:
        return f"| {fault.name} | {family} | — | — | — | {not_applicable(fault)} |"
    racing = asynchronous(fault, family)
    reason = normalized(measured.reason, racing)
    stop = (measured.stop_cycle if isinstance(measured.stop_cycle, str)
            else f"{measured.stop_cycle - (measured.abort_cycle - 1)} cycles")
    if measured.fault_cycle is None:
        detected = {"disk_full": "at the failing write",
                    "sigkill": "by the drive (heartbeat)"}[fault.name]
    else:
        detected = (f"≤ {ASYNC_CYCLES} cycles" if racing
                    else f"{measured.abort_cycle - measured.fault_cycle} cycles")
    kept = ("all before the detection" if racing or measured.fault_cycle is None
            else f"all {measured.before} before the fault")
    return f"| {fault.name} | {family} | {detected} | {stop} | {kept} | {reason} |"


def committed_line(fault: Fault, family: str) -> str:
    """The committed table's row of `fault` x `family` ('' if it has none)."""
    prefix = f"| {fault.name} | {family} |"
    lines = [line for line in DOC.read_text().splitlines() if line.startswith(prefix)]
    return lines[0] if lines else ""


def write_line(line: str, fault: Fault, family: str) -> None:
    """Put `line` in docs/faults.md as the row of `fault` x `family` (rows in matrix order;
    several test workers at once: the file is locked)."""
    with open(DOC, "r+") as doc:
        fcntl.flock(doc, fcntl.LOCK_EX)
        head, _, table = doc.read().partition(HEADER + "\n")
        rows = {tuple(cell.strip() for cell in line.split("|")[1:3]): line
                for line in table.splitlines() if line.startswith("|")}
        rows[(fault.name, family)] = line
        order = {(f.name, name): i for i, (f, name) in
                 enumerate((f, name) for f in FAULTS for name in FAMILIES)}
        body = "\n".join(rows[key] for key in sorted(rows, key=lambda k: order.get(k, 1e9)))
        doc.seek(0)
        doc.write(f"{head}{HEADER}\n{body}\n")
        doc.truncate()


def check_line(fault: Fault, family: str, measured: Measured | None) -> None:
    """The row as measured is the committed one (or, FEEDBENCH_WRITE_FAULT_TABLE=1, is
    written there)."""
    line = row_line(fault, family, measured)
    if os.environ.get("FEEDBENCH_WRITE_FAULT_TABLE") == "1":
        write_line(line, fault, family)
    else:
        committed = committed_line(fault, family)
        assert committed == line, f"\ncommitted: {committed}\nmeasured:  {line}"


@contextmanager
def file_size_limit(limit: int) -> Iterator[None]:
    """Files this process writes may grow to `limit` bytes (RLIMIT_FSIZE, soft), a longer
    write fails with EFBIG (SIGXFSZ ignored meanwhile)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    previous = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, previous)


def simulated_drives(bench: Bench) -> list:
    """The simulated drives behind an open simulated bench (lab: one; rack-and-pinion: two)."""
    simulated = bench.simulated
    return list(simulated.drives.values()) if hasattr(simulated, "drives") else [simulated.drive]


def run_with_fault(fault: Fault, family: str, directory: Path, channel: str) -> Measured:
    """Run the family with the fault on the simulated bench in this process; assert the safe
    stop, the samples and the file; what was measured."""
    config = parse_run_config(family_config(family, directory, fault.table, channel))
    with Bench(config.bench, config.plan, config.experiment.devices()) as bench:
        catalog = Catalog(directory / "catalog.sqlite")
        drives = simulated_drives(bench)
        bench.clock.tick()  # the first cycle, its slowest (daq.clock.FIRST_CYCLE_TIMEOUT_S)
        if fault.name == "sigint":
            interrupt_at(drives[0], AT_CYCLE)
        with file_size_limit(FILE_LIMIT_BYTES) if fault.name == "disk_full" else nullcontext():
            record = bench.run(config, catalog, directory, progress=False)
        logs = [drive.state_log for drive in drives]
    recording = open_recording(record["file"])
    assert record["status"] == recording.status == "aborted"
    assert fault.reason in recording.reason and recording.reason in record["reason"]
    assert "drive state unknown" not in recording.reason
    detected = abort_cycle(recording)
    stop = max(left_operation(log, detected - 1) for log in logs)
    assert stop <= detected + 1, "the drive left operation enabled within 2 cycles"
    fault_cycle = None if fault.name == "disk_full" else AT_CYCLE
    before = assert_samples_kept(recording, fault_cycle or detected)
    [row] = catalog.list()
    assert row.n_samples == recording.n_samples and row.status == "aborted"
    return Measured(fault_cycle, detected, stop, before, recording.reason)


def interrupt_at(drive, cycle: int) -> None:
    """Ctrl-C to this process (a real SIGINT, which the runner's handler takes) once the
    simulated `drive` has run SYNC `cycle`."""
    def hook() -> None:
        if drive.values[CYCLE_COUNTER] == cycle:
            os.kill(os.getpid(), signal.SIGINT)

    drive.after_physics.append(hook)


def _measure_row(fault: Fault, family: str, directory: Path) -> Measured | Exception:
    """`run_with_fault` in a pool process on its own virtual bus: what the row measured, or
    what it raised (its test raises it)."""
    try:
        return run_with_fault(fault, family, directory, virtual_channel())
    except Exception as exc:  # an assertion of the row too: its test reports it
        return exc


def measure_rows(faults: Sequence[Fault], directory: Path
                 ) -> dict[tuple[str, str], Measured | Exception]:
    """Every applicable row of `faults` x `FAMILIES`, each in its own directory under
    `directory`, measured `ROW_PROCESSES` at a time in forked processes (the fault's name,
    the family) → what it measured or raised."""
    rows = [(fault, family) for fault in faults for family in FAMILIES if applies(fault, family)]
    context = multiprocessing.get_context("fork")
    with ProcessPoolExecutor(ROW_PROCESSES, mp_context=context) as pool:
        futures = {(fault.name, family): pool.submit(_measure_row, fault, family,
                                                     directory / f"{fault.name}-{family}")
                   for fault, family in rows}
    return {key: future.result() for key, future in futures.items()}


def measured_rows(faults: Sequence[Fault]) -> Any:
    """A module-scoped fixture ``measured``: `measure_rows` of `faults`, for `row_test`."""
    @pytest.fixture(scope="module")
    def measured(tmp_path_factory: pytest.TempPathFactory) -> dict:
        return measure_rows(faults, tmp_path_factory.mktemp("rows"))
    return measured


def row_test(fault: Fault, family: str,
             measured: Mapping[tuple[str, str], Measured | Exception]) -> None:
    """One row of the matrix as `measure_rows` measured it: check it, or its "n/a" line."""
    if not applies(fault, family):
        check_line(fault, family, None)
        return
    measured = measured[(fault.name, family)]
    if isinstance(measured, Exception):
        raise measured
    if asynchronous(fault, family) and measured.fault_cycle is not None:
        late = measured.abort_cycle - measured.fault_cycle
        assert 0 <= late <= ASYNC_CYCLES, f"detected {late} cycles after the fault"
    check_line(fault, family, measured)
