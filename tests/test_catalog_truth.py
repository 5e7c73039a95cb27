"""The catalog tells the truth about the recordings (issue 18, item 3): a run whose process
was killed is listed `crashed` with the samples its file holds, a corrupt catalog is moved
aside and rebuilt from the recordings without blocking a run, `feedbench catalog rebuild`
recreates it, and a catalog on a disk that cannot be written ends `feedbench runs` in one
line."""

from __future__ import annotations

import ctypes
import json
import os
import resource
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import tempfile
import textwrap
import time
from contextlib import closing
from importlib import resources
from pathlib import Path

import pytest

import feedbench
from feedbench.bench import parse_run_config, run_config
from feedbench.commands.cli import main
from feedbench.config import ConfigError
from feedbench.daq.catalog import Catalog
from feedbench.daq.recording import open_recording, read_summary
from feedbench.commands.demo import example_config
from test_report import friction_steps, record

CHUNK_ROWS = 100
CHUNKS_BEFORE_READY = 7
WRITER = textwrap.dedent("""
    import sys, time
    import numpy as np
    from feedbench.daq.catalog import Catalog
    from feedbench.daq.recorder import Recorder
    from feedbench.engine.runner import CHANNELS, UNITS

    directory, chunk, ready_after = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    catalog = Catalog(f"{directory}/catalog.sqlite")
    run_id = catalog.new_run_id("friction_sweep")
    path = f"{directory}/{run_id}.h5"
    catalog.add(run_id, "friction_sweep", path, {"feeds": 13})
    recorder = Recorder(path, CHANNELS, UNITS, {"experiment": "friction_sweep",
                        "run_id": run_id, "config": {"experiment": {"type": "friction_sweep"}}},
                        chunk_rows=chunk)
    cycle = 0
    while True:  # records until it is killed
        recorder.append_block(np.arange(cycle, cycle + chunk),
                              np.zeros((chunk, len(CHANNELS))))
        cycle += chunk
        if cycle == chunk * ready_after:
            print(run_id, flush=True)
        time.sleep(0.002)
""")


def runs_json(directory: Path, capsys) -> list[dict]:
    """`feedbench runs --dir DIRECTORY --json`: the rows."""
    assert main(["runs", "--dir", str(directory), "--json"]) == 0
    return json.loads(capsys.readouterr().out)["runs"]


def test_a_run_killed_mid_recording_is_listed_crashed_with_the_samples_of_its_file(
        tmp_path, capsys):
    writer = subprocess.Popen([sys.executable, "-c", WRITER, str(tmp_path), str(CHUNK_ROWS),
                               str(CHUNKS_BEFORE_READY)], stdout=subprocess.PIPE, text=True)
    try:
        run_id = writer.stdout.readline().strip()
        [live] = runs_json(tmp_path, capsys)
        assert (live["id"], live["status"], live["pid"], live["host"]) == (
            run_id, "running", writer.pid, socket.gethostname()), "a live writer's run stays"
    finally:
        writer.send_signal(signal.SIGKILL)
        writer.wait(10)
    assert writer.returncode == -signal.SIGKILL
    in_file = open_recording(tmp_path / f"{run_id}.h5")
    assert in_file.status == "running", "the killed writer never closed its file"
    assert in_file.n_samples >= CHUNK_ROWS * CHUNKS_BEFORE_READY
    assert in_file.n_samples % CHUNK_ROWS == 0, "whole flushed chunks"

    [row] = runs_json(tmp_path, capsys)
    assert (row["id"], row["status"], row["n_samples"]) == (run_id, "crashed",
                                                            in_file.n_samples)
    assert row["reason"] == (f"process {writer.pid} on {socket.gethostname()} ended without "
                             "finishing the run")
    marked = open_recording(tmp_path / f"{run_id}.h5")
    assert (marked.status, marked.reason, marked.n_samples) == (
        "crashed", row["reason"], in_file.n_samples), "the file says so too"
    assert (marked.cycle == in_file.cycle).all()
    assert main(["runs", "--dir", str(tmp_path)]) == 0
    line = capsys.readouterr().out.splitlines()[0].split()
    assert line[:3] == [run_id, "crashed", str(in_file.n_samples)]


def test_the_scripting_session_marks_a_killed_writers_run_crashed_as_it_opens(
        tmp_path, can_channel):
    """`feedbench.open_bench` settles the catalog as `feedbench run` does: a run a dead
    process left `running` is `crashed`, in its file too, before the session records."""
    writer = subprocess.Popen([sys.executable, "-c", WRITER, str(tmp_path), str(CHUNK_ROWS),
                               "1"], stdout=subprocess.PIPE, text=True)
    try:
        run_id = writer.stdout.readline().strip()
    finally:
        writer.send_signal(signal.SIGKILL)
        writer.wait(10)
    assert open_recording(tmp_path / f"{run_id}.h5").status == "running"
    with feedbench.open_bench({"bench": {"channel": can_channel,
                                         "output_dir": str(tmp_path)}}):
        marked = open_recording(tmp_path / f"{run_id}.h5")
    assert (marked.status, marked.n_samples % CHUNK_ROWS) == ("crashed", 0)
    assert marked.n_samples >= CHUNK_ROWS


def _flushed(directory: Path, at_least: int) -> bool:
    """Whether the recording being written in `directory` holds `at_least` samples."""
    try:
        [path] = directory.glob("*.h5")
        return read_summary(path).n_samples >= at_least
    except (ValueError, ConfigError):  # no file yet, or not readable yet
        return False


def test_a_simulated_run_killed_mid_run_is_listed_crashed(tmp_path, can_channel, capsys):
    """`feedbench run` (bench, runner, recorder in one process) killed with SIGKILL."""
    text = (resources.files("feedbench") / "examples" / "friction_sweep.toml").read_text()
    config = tmp_path / "sweep.toml"
    config.write_text(text.replace('output_dir = "runs"', f'output_dir = "{tmp_path}"')
                      .replace('channel = "feedbench-demo"', f'channel = "{can_channel}"'))
    run = subprocess.Popen([sys.executable, "-m", "feedbench.commands.cli", "run", str(config)],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while not _flushed(tmp_path, at_least=2000) and time.monotonic() < deadline:
        time.sleep(0.05)
    run.send_signal(signal.SIGKILL)
    run.wait(10)
    [row] = runs_json(tmp_path, capsys)
    in_file = open_recording(row["file"])
    assert in_file.status == "crashed" and in_file.n_samples >= 2000, in_file.n_samples
    assert (row["status"], row["n_samples"], row["pid"]) == ("crashed", in_file.n_samples,
                                                             run.pid)


def test_a_finished_file_settles_its_row_and_a_row_without_a_file_crashes(tmp_path):
    """A process that closed its recording but died before the catalog's `finish`: the
    row takes the file's status; one that died before recording anything: crashed, 0."""
    catalog = Catalog(tmp_path / "catalog.sqlite")
    closed = catalog.new_run_id("friction_sweep")
    record(tmp_path / f"{closed}.h5", "friction_sweep", friction_steps(), status="aborted",
           reason="limit tripped: |force|")
    catalog.add(closed, "friction_sweep", tmp_path / f"{closed}.h5", {})
    never = catalog.new_run_id("chirp")
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    with sqlite3.connect(tmp_path / "catalog.sqlite") as connection:  # as that process left it
        connection.execute("UPDATE runs SET pid = ?", (int(dead.stdout),))
    assert sorted(catalog.reconcile()) == sorted([closed, never])
    rows = {row.id: row for row in catalog.list()}
    assert (rows[closed].status, rows[closed].reason, rows[closed].n_samples) == (
        "aborted", "limit tripped: |force|", open_recording(tmp_path / f"{closed}.h5").n_samples)
    assert rows[closed].stopped_at == open_recording(tmp_path / f"{closed}.h5").stopped_at
    assert (rows[never].status, rows[never].n_samples) == ("crashed", 0)
    assert rows[never].reason.endswith("ended without finishing the run (no recording started)")
    assert catalog.reconcile() == [], "settled once"


def short_sweep(directory: Path, channel: str) -> dict:
    raw = example_config("friction_sweep")
    raw["bench"].update(output_dir=str(directory), channel=channel)
    raw["experiment"].update(feeds_mm_min=[100, 200, 300, 400, 500], settle_s=0.1,
                             measure_s=0.1)
    return raw


def test_a_corrupt_catalog_is_moved_aside_and_rebuilt_and_the_next_run_works(
        tmp_path, can_channel, caplog):
    first = run_config(parse_run_config(short_sweep(tmp_path, can_channel)), progress=False)
    old = Catalog(tmp_path / "catalog.sqlite").get(first["id"])
    (tmp_path / "catalog.sqlite").write_bytes(b"\x8f garbage \x00" * 700)

    second = run_config(parse_run_config(short_sweep(tmp_path, can_channel)), progress=False)

    assert second["status"] == "complete"
    [aside] = tmp_path.glob("catalog.sqlite.corrupt-*")
    assert aside.read_bytes() == b"\x8f garbage \x00" * 700
    [warning] = [r.getMessage() for r in caplog.records if r.name == "feedbench.daq.catalog"]
    assert warning == (f"{tmp_path / 'catalog.sqlite'}: corrupt run catalog (file is not a "
                       f"database) moved to {aside.name}; rebuilt from 1 recording(s)")
    rows = {row.id: row for row in Catalog(tmp_path / "catalog.sqlite").list()}
    assert list(rows) == [second["id"], first["id"]], "newest first"
    rebuilt = rows[first["id"]]
    assert (rebuilt.status, rebuilt.file, rebuilt.n_samples) == ("complete", old.file,
                                                                 old.n_samples)
    assert rebuilt.started_at == open_recording(old.file).started_at, "the file's own time"
    assert rebuilt.params["feeds_mm_min"] == [100, 200, 300, 400, 500]
    assert (rows[second["id"]].status, rows[second["id"]].n_samples) == (
        "complete", open_recording(second["file"]).n_samples)


def test_runs_on_a_corrupt_catalog_says_so_in_one_line_and_lists_the_recordings(
        tmp_path, capsys):
    record(tmp_path / "20261125-101010-friction_sweep-1.h5", "friction_sweep", friction_steps())
    (tmp_path / "other.h5").write_bytes(b"not hdf5")
    (tmp_path / "catalog.sqlite").write_text("not a database\n" * 20)
    proc = subprocess.run([sys.executable, "-m", "feedbench.commands.cli", "runs", "--dir", str(tmp_path)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0
    [aside] = tmp_path.glob("catalog.sqlite.corrupt-*")
    assert proc.stderr == (f"{tmp_path / 'catalog.sqlite'}: corrupt run catalog (file is not a "
                           f"database) moved to {aside.name}; rebuilt from 1 recording(s), "
                           "1 file(s) skipped\n")
    assert proc.stdout.split()[:3] == ["20261125-101010-friction_sweep-1", "complete", "4940"]


def test_processes_finding_the_catalog_corrupt_at_once_replace_it_once(tmp_path):
    record(tmp_path / "20261125-101010-friction_sweep-1.h5", "friction_sweep", friction_steps())
    (tmp_path / "catalog.sqlite").write_text("not a database\n" * 20)
    opening = ("import sys; from feedbench.daq.catalog import Catalog; "
               "print(len(Catalog(sys.argv[1]).list()))")
    processes = [subprocess.Popen([sys.executable, "-c", opening, str(tmp_path / "catalog.sqlite")],
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                 for _ in range(4)]
    outputs = [process.communicate(timeout=60) for process in processes]
    assert [(process.returncode, out) for process, (out, _) in zip(processes, outputs)] == [
        (0, "1\n")] * 4
    assert len(list(tmp_path.glob("catalog.sqlite.corrupt-*"))) == 1
    assert sorted(err.count("corrupt run catalog") for _, err in outputs) == [0, 0, 0, 1]


def test_catalog_rebuild_recreates_the_rows_from_the_recordings(tmp_path, capsys):
    catalog = Catalog(tmp_path / "catalog.sqlite")
    ids = [catalog.new_run_id("friction_sweep") for _ in range(2)]
    for run_id, status in zip(ids, ("complete", "aborted")):
        record(tmp_path / f"{run_id}.h5", "friction_sweep", friction_steps(), status=status,
               reason="SIGINT" if status == "aborted" else "",
               config={"type": "friction_sweep", "feeds_mm_min": [1, 2]})
        catalog.add(run_id, "friction_sweep", tmp_path / f"{run_id}.h5", {})
    catalog.finish(ids[0], "complete", "", 4940)
    stray = catalog.new_run_id("chirp")  # no recording and no longer written by anyone
    with sqlite3.connect(tmp_path / "catalog.sqlite") as connection:
        connection.execute("UPDATE runs SET pid = NULL WHERE id = ?", (stray,))
    (tmp_path / "foreign.h5").write_bytes(b"")

    assert main(["catalog", "rebuild", "--dir", str(tmp_path), "--debug"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out == [f"skipped {tmp_path / 'foreign.h5'}: not a readable HDF5 file "
                   "(Unable to synchronously open file (file signature not found))",
                   f"{tmp_path / 'catalog.sqlite'}: rebuilt from 2 recording(s)"]
    rows = Catalog(tmp_path / "catalog.sqlite").list()
    assert [(r.id, r.status, r.reason, r.n_samples, r.params) for r in rows] == [
        (ids[1], "aborted", "SIGINT", 4940, {"type": "friction_sweep", "feeds_mm_min": [1, 2]}),
        (ids[0], "complete", "", 4940, {"type": "friction_sweep", "feeds_mm_min": [1, 2]}),
    ]


def test_rebuild_keeps_a_live_writer_running_and_marks_a_killed_ones_file_crashed(tmp_path):
    writers = [subprocess.Popen([sys.executable, "-c", WRITER, str(tmp_path), str(CHUNK_ROWS),
                                 "1"], stdout=subprocess.PIPE, text=True) for _ in range(2)]
    try:
        live_id, killed_id = (writer.stdout.readline().strip() for writer in writers)
        writers[1].send_signal(signal.SIGKILL)
        writers[1].wait(10)
        (tmp_path / "catalog.sqlite").unlink()
        catalog = Catalog(tmp_path / "catalog.sqlite")
        assert catalog.rebuild() == (2, [])
        rows = {row.id: row for row in catalog.list()}
        assert (rows[live_id].status, rows[live_id].pid) == ("running", writers[0].pid)
        assert (rows[killed_id].status, rows[killed_id].reason, rows[killed_id].pid) == (
            "crashed", "no process writes it any more", None)
        assert rows[killed_id].n_samples == open_recording(rows[killed_id].file).n_samples
    finally:
        writers[0].send_signal(signal.SIGKILL)
        writers[0].wait(10)


PR_CAPBSET_DROP = 24
CAP_DAC_OVERRIDE, CAP_DAC_READ_SEARCH = 1, 2


def _without_root_file_access() -> None:
    """Root (as CI runs) ignores file modes; without these capabilities it obeys them."""
    if os.geteuid() == 0:
        libc = ctypes.CDLL(None, use_errno=True)
        for capability in (CAP_DAC_OVERRIDE, CAP_DAC_READ_SEARCH):
            if libc.prctl(PR_CAPBSET_DROP, capability, 0, 0, 0):
                raise OSError(ctypes.get_errno(), "prctl(PR_CAPBSET_DROP)")


def test_runs_on_a_read_only_directory_is_one_line(capsys):
    directory = Path(tempfile.mkdtemp(prefix="feedbench-ro-"))
    try:
        catalog = Catalog(directory / "catalog.sqlite")
        catalog.add(catalog.new_run_id("chirp"), "chirp", directory / "gone.h5", {})
        for path in (directory / "catalog.sqlite-wal", directory / "catalog.sqlite-shm"):
            path.unlink(missing_ok=True)
        directory.chmod(0o555)
        (directory / "catalog.sqlite").chmod(0o444)
        proc = subprocess.run([sys.executable, "-m", "feedbench.commands.cli", "runs", "--dir",
                               str(directory)], capture_output=True, text=True, timeout=60,
                              preexec_fn=_without_root_file_access)
    finally:
        directory.chmod(0o755)
        shutil.rmtree(directory)
    assert proc.returncode == 2
    assert proc.stderr == (f"feedbench: error: {directory / 'catalog.sqlite'}: cannot use the "
                           "run catalog (attempt to write a readonly database)\n")


def _file_size_limit() -> None:
    """A full disk for this process: no file may grow beyond what it is."""
    resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))


def test_runs_on_a_full_disk_is_one_line(tmp_path):
    catalog = Catalog(tmp_path / "catalog.sqlite")
    for _ in range(20):  # crashed runs to settle: `runs` has to write
        catalog.add(catalog.new_run_id("chirp"), "chirp", tmp_path / "gone.h5", {})
    with sqlite3.connect(tmp_path / "catalog.sqlite") as connection:
        connection.execute("UPDATE runs SET pid = NULL, file = ?", (str(tmp_path / "gone.h5"),))
    proc = subprocess.run([sys.executable, "-m", "feedbench.commands.cli", "runs", "--dir",
                           str(tmp_path)], capture_output=True, text=True, timeout=60,
                          preexec_fn=_file_size_limit)
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1
    assert proc.stderr.startswith(f"feedbench: error: {tmp_path / 'catalog.sqlite'}: cannot use "
                                  "the run catalog ("), proc.stderr
    assert "Traceback" not in proc.stderr


def test_a_run_whose_process_is_alive_is_left_alone(tmp_path):
    """The owner finishes its run: `reconcile` does not settle its row from the file even
    when the file says how it ended (reading it at the wrong moment cost a writer its final
    status)."""
    catalog = Catalog(tmp_path / "catalog.sqlite")
    closed = catalog.new_run_id("friction_sweep")
    record(tmp_path / f"{closed}.h5", "friction_sweep", friction_steps(), status="aborted",
           reason="limit tripped: |force|")
    catalog.add(closed, "friction_sweep", tmp_path / f"{closed}.h5", {})
    assert catalog.reconcile() == []
    assert [(row.id, row.status) for row in catalog.list()] == [(closed, "running")]


def two_recordings(directory: Path) -> list[str]:
    """Two recordings of finished runs in `directory`, with no catalog row: their ids."""
    ids = ["20261125-101010-friction_sweep-1", "20261125-101011-friction_sweep-1"]
    for run_id in ids:
        record(directory / f"{run_id}.h5", "friction_sweep", friction_steps())
    return ids


def feedbench_runs(directory: Path, stdout: int = subprocess.PIPE) -> subprocess.CompletedProcess:
    """`feedbench runs --dir DIRECTORY` in a process of its own, its output into `stdout`."""
    return subprocess.run([sys.executable, "-m", "feedbench.commands.cli", "runs", "--dir",
                           str(directory)], stdout=stdout, stderr=subprocess.PIPE, text=True,
                          timeout=60)


def empty_file(path: Path) -> None:
    path.write_bytes(b"")


def sqlite_without_runs(path: Path) -> None:
    with closing(sqlite3.connect(path)) as connection, connection:
        connection.execute("CREATE TABLE notes (text TEXT)")


@pytest.mark.parametrize("make_catalog", [empty_file, sqlite_without_runs])
def test_a_catalog_without_runs_table_beside_recordings_is_rebuilt_in_one_line(
        tmp_path, make_catalog):
    ids = two_recordings(tmp_path)
    make_catalog(tmp_path / "catalog.sqlite")
    listed = feedbench_runs(tmp_path)
    assert (listed.returncode, listed.stderr) == (0, (
        f"{tmp_path / 'catalog.sqlite'}: run catalog had no runs table (an empty file?) "
        "with recordings beside it; rebuilt from 2 recording(s)\n"))
    assert [line.split()[:4] for line in listed.stdout.splitlines()] == [
        [run_id, "complete", "4940", str(tmp_path / f"{run_id}.h5")] for run_id in ids[::-1]]
    assert feedbench_runs(tmp_path).stderr == "", "said once"


@pytest.mark.parametrize("column, value, problem", [
    ("timing", "{not json", "timing is not JSON (Expecting property name enclosed in double "
                            "quotes: line 1 column 2 (char 1))"),
    ("params", "[1, 2]", "params is not a JSON object (got list)"),
])
def test_a_bad_row_is_listed_damaged_with_its_file_and_the_others_as_they_are(
        tmp_path, capsys, column, value, problem):
    catalog = Catalog(tmp_path / "catalog.sqlite")
    ids = two_recordings(tmp_path)
    for run_id in ids:
        catalog.add(run_id, "friction_sweep", tmp_path / f"{run_id}.h5", {"feeds": 2})
        catalog.finish(run_id, "complete", "", 4940)
    with closing(sqlite3.connect(tmp_path / "catalog.sqlite")) as connection, connection:
        connection.execute(f"UPDATE runs SET {column} = ? WHERE id = ?", (value, ids[0]))

    rows = {row["id"]: row for row in runs_json(tmp_path, capsys)}
    assert (rows[ids[0]]["status"], rows[ids[0]]["file"], rows[ids[0]]["reason"]) == (
        "damaged", str(tmp_path / f"{ids[0]}.h5"), f"catalog row damaged: {problem} "
        "(feedbench catalog rebuild recreates it from its file)")
    assert (rows[ids[1]]["status"], rows[ids[1]]["params"]) == ("complete", {"feeds": 2})
    assert main(["runs", "--dir", str(tmp_path)]) == 0
    assert [line.split()[1] for line in capsys.readouterr().out.splitlines()] == [
        "complete", "damaged"]
    assert main(["catalog", "rebuild", "--dir", str(tmp_path)]) == 0
    assert {row.id: row.status for row in catalog.list()} == dict.fromkeys(ids, "complete")


def test_runs_into_a_pipe_closed_early_ends_quietly(tmp_path):
    """`feedbench runs | head`: the reader goes before the listing is written."""
    two_recordings(tmp_path)
    catalog = Catalog(tmp_path / "catalog.sqlite")
    assert catalog.list() == [], "a new catalog file is not rebuilt by itself"
    assert catalog.rebuild() == (2, [])
    read_end, write_end = os.pipe()
    os.close(read_end)
    listed = feedbench_runs(tmp_path, stdout=write_end)
    os.close(write_end)
    assert (listed.returncode, listed.stderr) == (141, "")
