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
import time
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


def example_text(family: str) -> str:
    """The family's packaged example config, as text."""
    return (resources.files("feedbench") / "examples" / f"{family}.toml").read_text()


def tables_after_bench(text: str) -> str:
    """A config's [limits] and [experiment] tables (everything from [limits] on)."""
    return text[text.index("\n[limits]") + 1:]


@pytest.fixture(scope="module")
def sims(tmp_path_factory):
    """`feedbench sim` of the lab axis (the SMFE example: its workpiece) and of the
    rack-and-pinion axis, each in its own process."""
    started = {}
    for axis, family in (("lab", "smfe"), ("rack_pinion", "stepped_loading")):
        directory = tmp_path_factory.mktemp(f"sim-{axis}")
        text = example_text(family).replace(
            'interface = "virtual"',
            'interface = "socketcand"\nsocketcand = "127.0.0.1:0"', 1)
        (directory / "sim.toml").write_text(text)
        started[axis] = start_sim(directory, config=directory / "sim.toml")
    yield started
    for process, _ in started.values():
        process.terminate()
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


@pytest.mark.parametrize("family", FAMILIES)
def test_sigkill_row(family, sims, tmp_path, capsys):
    """SIGKILL mid-run (the lab families share one simulated bench; SMFE, which leaves the
    axis far out, is the last of them): the drive reaches a safe state by itself within the
    consumer time; `feedbench runs` marks the file crashed; every cycle to the last flush is
    in it."""
    _, info = sims["rack_pinion" if family in RACK else "lab"]
    directory = tmp_path
    killed = kill_mid_run(family, info, directory)
    while not all(state in SAFE_STATES for state in drive_states(info)):
        assert time.monotonic() - killed < STOPPED_WITHIN_S, (family, drive_states(info))
        time.sleep(0.1)
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


def test_feedbench_sim_injects_the_faults_of_its_command_line(tmp_path):
    """`feedbench sim --fault at_cycle=200 --fault emcy_code=0x2310`: a friction sweep from
    another process aborts on that EMCY, and the drive is in FAULT."""
    process, info = start_sim(tmp_path, options=("--fault", "at_cycle=200",
                                                 "--fault", "emcy_code=0x2310"))
    try:
        config = tmp_path / "run.toml"
        config.write_text(host_bench_table(info) + f'\noutput_dir = "{tmp_path}"\n'
                          + tables_after_bench(example_text("friction_sweep")))
        run = subprocess.run([sys.executable, "-m", "feedbench.commands.cli", "run", str(config)],
                             capture_output=True, text=True, timeout=120)
        assert run.returncode == 1, run.stderr
        [row] = Catalog(tmp_path / "catalog.sqlite").list()
        assert row.reason == "drive fault (EMCY 0x2310)"
        assert open_recording(row.file).cycle[-1] < 220
        assert drive_states(info) == ["FAULT"]
    finally:
        process.terminate()
        process.communicate(timeout=20)
