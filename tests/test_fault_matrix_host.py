"""The fault matrix, the host killed (issue 18.4): SIGKILL to `feedbench run` against
`feedbench sim` in its own process, for every experiment family (`tests/fault_matrix.py`).

Nothing of the host is left to stop the drive, so the drive stops itself (its heartbeat
consumer, 3 s, then its fault reaction: a safe state read by SDO from a new connection);
`feedbench runs` afterwards marks the file crashed, in the file itself (issue 18.3), and it
reads back up to its last flushed chunk.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from importlib import resources
from pathlib import Path

import pytest

from feedbench.commands.cli import main
from feedbench.daq.catalog import Catalog
from feedbench.daq.recording import open_recording, read_summary
from feedbench.drivers.cia402 import SAFE_STATES, Cia402Drive, decode_state
from feedbench.protocols.canbus import open_network
from feedbench.protocols.cia402 import STATUSWORD
from feedbench.sim_backends import eds
from feedbench.sim_backends.process import host_bench_table
from fault_matrix import FAMILIES, FAULT, Measured, assert_samples_kept, check_line
from sim_peer import start_sim

CONSUMER_S = 3.0
"""The drives' consumer time of the host's heartbeat (`drivers.cia402.HOST_CONSUMER_MS`)."""
STOPPED_WITHIN_S = CONSUMER_S + 1.5
"""SIGKILL: the drive is in a safe state this long after the kill (consumer time, the fault
reaction's ramp, a loaded machine)."""
RACK = ("backlash_reversal", "stepped_loading")
BENCHES = ("lab", "lab_2", "rack_pinion")
"""The simulated benches of the SIGKILL rows (`sims`): the lab axis twice, so that
consecutive rows are never on the same bench (`schedule`)."""


def schedule() -> list[tuple[str, str]]:
    """(bench, family) of every SIGKILL row in the order they run, one `feedbench run` at a
    time: the lab families alternate between the two lab benches (SMFE, which leaves the
    axis far out, the last of them), the rack-and-pinion ones come between them, so no two
    rows in a row share a bench. A row's drive then stops by itself (3 s consumer time)
    while the next row's run starts on another bench (`killed_rows`), instead of the file
    waiting ≈ 3 s per row with nothing else running; the runs stay one at a time (two at
    once raced a short run's end in the 2-worker suite: e5cce2f)."""
    lab = [family for family in FAMILIES if family not in RACK and family != "smfe"]
    lab.append("smfe")
    rows = [("lab" if i % 2 == 0 else "lab_2", family) for i, family in enumerate(lab)]
    for k, family in enumerate(RACK):
        rows.insert(2 + 3 * k, ("rack_pinion", family))
    assert sorted(family for _, family in rows) == sorted(FAMILIES)
    assert all(a[0] != b[0] for a, b in zip(rows, rows[1:]))
    return rows


def example_text(family: str) -> str:
    """The family's packaged example config, as text."""
    return (resources.files("feedbench") / "examples" / f"{family}.toml").read_text()


def tables_after_bench(text: str) -> str:
    """A config's [limits] and [experiment] tables (everything from [limits] on)."""
    return text[text.index("\n[limits]") + 1:]


FAULTED_OPTIONS = ("--fault", "at_cycle=200", "--fault", "emcy_code=0x2310")
"""`feedbench sim`'s command-line faults of `test_feedbench_sim_injects_the_faults_of_its_
command_line` (its bench, "faulted" in `sims`: the faults count the SYNCs it hears, so it
waits idle for its test)."""


@pytest.fixture(scope="module")
def sims(tmp_path_factory):
    """`feedbench sim` of the lab axis (the SMFE example: its workpiece) twice and of the
    rack-and-pinion axis (`BENCHES`), and the default bench with `FAULTED_OPTIONS`, each in
    its own process, started at once (their start-ups overlap), ended at once."""
    def start(bench: str):
        directory = tmp_path_factory.mktemp(f"sim-{bench}")
        if bench == "faulted":
            return bench, start_sim(directory, options=FAULTED_OPTIONS)
        family = "stepped_loading" if bench == "rack_pinion" else "smfe"
        text = example_text(family).replace(
            'interface = "virtual"',
            'interface = "socketcand"\nsocketcand = "127.0.0.1:0"', 1)
        (directory / "sim.toml").write_text(text)
        return bench, start_sim(directory, config=directory / "sim.toml")

    with ThreadPoolExecutor(len(BENCHES) + 1) as pool:
        futures = [pool.submit(start, bench) for bench in (*BENCHES, "faulted")]
    started = dict(f.result() for f in futures if f.exception() is None)
    failed = [f.exception() for f in futures if f.exception() is not None]
    if failed:  # the sims that did start do not outlive the error
        for process, _ in started.values():
            process.terminate()
        raise failed[0]
    yield started
    for process, _ in started.values():
        process.terminate()
    for process, _ in started.values():
        process.communicate(timeout=20)


def drive_states(info: dict) -> list[str]:
    """The CiA 402 state of each drive of a `feedbench sim`, read by SDO."""
    host, port = info["socketcand"].split(":")
    network = open_network("socketcand", info["channel"], host=host, port=int(port))
    try:
        nodes = [info["node_id"], *([info["slave_node_id"]] if "slave_node_id" in info else [])]
        return [decode_state(Cia402Drive(network, node, eds.packaged_eds_path())
                             .node.sdo[STATUSWORD].raw) for node in nodes]
    finally:
        network.disconnect()


def flushed(directory: Path) -> int:
    """Samples on disk in the one recording of `directory` (0 before it has any)."""
    try:
        [path] = directory.glob("*.h5")
        return read_summary(path).n_samples
    except Exception:  # no file yet, or between flushes
        return 0


def kill_mid_run(family: str, info: dict, directory: Path) -> float:
    """Start `feedbench run` of the family against the simulated bench `info`, SIGKILL it
    once a chunk of samples is on disk; the time of the kill (monotonic s)."""
    config = directory / "run.toml"
    config.write_text(host_bench_table({**info, "directory": directory})
                      + f'\noutput_dir = "{directory}"\n'
                      + tables_after_bench(example_text(family)))
    run = subprocess.Popen([sys.executable, "-m", "feedbench.commands.cli", "run", str(config)],
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 90
    while flushed(directory) < 1000 and time.monotonic() < deadline:
        assert run.poll() is None, run.stderr.read()
        time.sleep(0.02)
    run.send_signal(signal.SIGKILL)
    killed = time.monotonic()
    run.wait(10)
    return killed


def wait_for_stop(family: str, info: dict, killed: float) -> None:
    """The drive reaches a safe state by itself within `STOPPED_WITHIN_S` of the kill."""
    while not all(state in SAFE_STATES for state in drive_states(info)):
        assert time.monotonic() - killed < STOPPED_WITHIN_S, (family, drive_states(info))
        time.sleep(0.1)


@pytest.fixture(scope="module")
def killed_rows(sims, tmp_path_factory) -> dict:
    """Every family's SIGKILL mid-run (`kill_mid_run`, one run at a time, in `schedule`
    order), each drive's stop watched by a thread (`wait_for_stop`) while the next row runs
    on another bench; a bench's next row starts once its watcher is done, also after a row
    whose run failed to start or to record (its drive may still be enabled). family → (its
    directory, None or the exception its row's test raises)."""
    rows: dict[str, tuple[Path, BaseException | None]] = {}
    watchers: dict[str, threading.Thread] = {}

    def watch(family: str, info: dict, killed: float, directory: Path) -> None:
        try:
            wait_for_stop(family, info, killed)
        except BaseException as failed:  # noqa: BLE001  (raised by the row's test)
            if rows[family][1] is None:  # a row that failed before keeps its first failure
                rows[family] = (directory, failed)

    for bench, family in schedule():
        _, info = sims[bench]
        if bench in watchers:
            watchers.pop(bench).join()
        directory = tmp_path_factory.mktemp(f"sigkill-{family}")
        rows[family] = (directory, None)
        try:
            killed = kill_mid_run(family, info, directory)
        except Exception as failed:  # a Ctrl-C ends the fixture, a failure only its row
            rows[family] = (directory, failed)
            killed = time.monotonic()  # its drive is still watched to a stop before the next
        watchers[bench] = threading.Thread(target=watch, args=(family, info, killed, directory))
        watchers[bench].start()
    for watcher in watchers.values():
        watcher.join()
    return rows


@pytest.mark.parametrize("family", FAMILIES)
def test_sigkill_row(family, killed_rows, capsys):
    """SIGKILL mid-run (the lab families share two simulated benches; SMFE, which leaves the
    axis far out, is the last of them): the drive reaches a safe state by itself within the
    consumer time; `feedbench runs` marks the file crashed; every cycle to the last flush is
    in it."""
    directory, failed = killed_rows[family]
    if failed is not None:
        raise failed
    assert main(["runs", "--dir", str(directory)]) == 0
    capsys.readouterr()
    [row] = Catalog(directory / "catalog.sqlite").list()
    recording = open_recording(row.file)
    assert row.status == recording.status == "crashed"
    assert row.n_samples == recording.n_samples >= 1000
    last = int(recording.cycle[-1]) + 1
    before = assert_samples_kept(recording, last)
    check_line(FAULT["sigkill"], family, Measured(
        None, last, f"≤ {STOPPED_WITHIN_S:g} s (heartbeat consumer {CONSUMER_S:g} s)",
        before, recording.reason))


def test_feedbench_sim_injects_the_faults_of_its_command_line(sims):
    """`feedbench sim --fault at_cycle=200 --fault emcy_code=0x2310`: a friction sweep from
    another process aborts on that EMCY, and the drive is in FAULT."""
    _, info = sims["faulted"]
    directory = info["directory"]
    config = directory / "run.toml"
    config.write_text(host_bench_table(info) + f'\noutput_dir = "{directory}"\n'
                      + tables_after_bench(example_text("friction_sweep")))
    run = subprocess.run([sys.executable, "-m", "feedbench.commands.cli", "run", str(config)],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 1, run.stderr
    [row] = Catalog(directory / "catalog.sqlite").list()
    assert row.reason == "drive fault (EMCY 0x2310)"
    assert open_recording(row.file).cycle[-1] < 220
    assert drive_states(info) == ["FAULT"]
