"""Catalog paths (issue 25, item 4): recordings are stored relative to the catalog and found
from any working directory; a catalog made before (paths relative to the directory its runs
were started from, or absolute) is still read."""

from __future__ import annotations

import sqlite3
import subprocess
import sys
from contextlib import closing
from pathlib import Path

import pytest

from feedbench.bench import parse_run_config, run_config
from feedbench.daq.catalog import Catalog
from test_catalog_truth import short_sweep
from test_report import friction_steps, record


def stored_files(catalog: Path) -> dict[str, str]:
    """Run id → the file column as the catalog stores it."""
    with closing(sqlite3.connect(catalog)) as connection:
        return dict(connection.execute("SELECT id, file FROM runs"))


def feedbench(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "feedbench.commands.cli", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=120)


def test_commands_from_another_directory_find_a_run_recorded_elsewhere(
        tmp_path: Path, can_channel: str, monkeypatch: pytest.MonkeyPatch) -> None:
    lab, elsewhere = tmp_path / "lab", tmp_path / "elsewhere"
    lab.mkdir(), elsewhere.mkdir()
    monkeypatch.chdir(lab)
    run = run_config(parse_run_config(short_sweep(Path("runs/demo"), can_channel)),
                     progress=False)
    directory = lab / "runs" / "demo"
    assert stored_files(directory / "catalog.sqlite") == {run["id"]: f"{run['id']}.h5"}

    listed = feedbench("runs", "--dir", str(directory), cwd=elsewhere).stdout.split()
    assert [listed[0], listed[1], listed[3]] == [run["id"], run["status"],
                                                 str(directory / f"{run['id']}.h5")]
    assert int(listed[2]) > 0, "samples"
    analyzed = feedbench("analyze", "--dir", str(directory), run["id"][:15], cwd=elsewhere)
    assert (analyzed.returncode, analyzed.stderr) == (0, "")
    assert "no such recording" not in analyzed.stdout
    reported = feedbench("report", "--dir", str(directory), run["id"], "-o", "report.html",
                         cwd=elsewhere)
    assert (reported.returncode, reported.stdout) == (0, "report.html\n"), reported.stderr
    assert run["id"] in (elsewhere / "report.html").read_text(encoding="utf-8")


def test_an_old_catalogs_paths_are_still_found_from_another_directory(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Made before paths were stored relative to it: one path relative to the directory
    the run was started from (`runs/<id>.h5`), one absolute."""
    directory = tmp_path / "lab" / "runs"
    directory.mkdir(parents=True)
    catalog = Catalog(directory / "catalog.sqlite")
    ids = [catalog.new_run_id("friction_sweep") for _ in range(2)]
    old_paths = [f"runs/{ids[0]}.h5", str(directory / f"{ids[1]}.h5")]
    for run_id, old in zip(ids, old_paths):
        record(directory / f"{run_id}.h5", "friction_sweep", friction_steps())
        catalog.add(run_id, "friction_sweep", directory / f"{run_id}.h5", {})
        catalog.finish(run_id, "complete", "", 4940)
        with closing(sqlite3.connect(directory / "catalog.sqlite")) as connection, connection:
            connection.execute("UPDATE runs SET file = ? WHERE id = ?", (old, run_id))

    for cwd, expected in [(tmp_path / "lab", [f"runs/{ids[0]}.h5", old_paths[1]]),
                          (tmp_path, [str(directory / f"{ids[0]}.h5"), old_paths[1]])]:
        monkeypatch.chdir(cwd)
        found = [Catalog(directory / "catalog.sqlite").get(run_id).file for run_id in ids]
        assert found == expected
        assert all(Path(file).is_file() for file in found)
