"""Run catalog: ids, add/finish (with the recording process's pid and host), list order,
lookup by unique prefix, concurrent readers, a catalog made before pids were recorded."""

from __future__ import annotations

import os
import re
import socket
import sqlite3
import subprocess
import sys
from contextlib import closing
from pathlib import Path

import numpy as np
import pytest

from feedbench.daq.catalog import SCHEMA_VERSION, Catalog, RunLookupError, RunRow


def test_ids_are_unique_and_formatted_when_created_in_the_same_second(tmp_path: Path) -> None:
    catalog = Catalog(tmp_path / "runs.sqlite")
    ids = [catalog.new_run_id("friction sweep") for _ in range(12)]
    assert len(set(ids)) == 12
    for run_id in ids:
        assert re.fullmatch(r"\d{8}-\d{6}-friction_sweep-\d+", run_id)
    same_second = [run_id for run_id in ids if run_id[:15] == ids[0][:15]]
    assert [int(run_id.rsplit("-", 1)[1]) for run_id in same_second] == list(
        range(1, len(same_second) + 1)
    )
    assert Catalog(tmp_path / "runs.sqlite").new_run_id("friction sweep") not in ids


def test_add_finish_list_get(tmp_path: Path) -> None:
    catalog = Catalog(tmp_path / "runs.sqlite")
    first = catalog.new_run_id("friction_sweep")
    catalog.add(first, "friction_sweep", tmp_path / "a.h5", {"feed_mm_min": np.float64(100.0)})
    second = catalog.new_run_id("frf")
    catalog.add(second, "frf", tmp_path / "b.h5", {"amplitude_N": 50, "f_max_Hz": [1.0, 500.0]})

    running = catalog.get(first)
    assert (running.status, running.stopped_at, running.n_samples) == ("running", None, None)
    assert running.started_at.endswith("+00:00")

    catalog.finish(first, "complete", "", 25_003)
    catalog.finish(second, "aborted", "limit: position", 1_234)

    assert catalog.get(first) == RunRow(
        id=first,
        experiment="friction_sweep",
        started_at=running.started_at,
        stopped_at=catalog.get(first).stopped_at,
        status="complete",
        reason="",
        file=str(tmp_path / "a.h5"),
        n_samples=25_003,
        params={"feed_mm_min": 100.0},
        pid=os.getpid(),
        host=socket.gethostname(),
        bench=socket.gethostname(),
    )
    rows = catalog.list()
    assert [row.id for row in rows] == [second, first]
    assert [row.status for row in rows] == ["aborted", "complete"]
    assert rows[0].reason == "limit: position"
    assert rows[0].params == {"amplitude_N": 50, "f_max_Hz": [1.0, 500.0]}
    assert [row.id for row in catalog.list(limit=1)] == [second]
    assert catalog.get(first.split("friction")[0] + "fric").id == first
    assert catalog.get(second.rsplit("-", 1)[0]).id == second


def test_prefix_lookup_errors_name_the_id(tmp_path: Path) -> None:
    catalog = Catalog(tmp_path / "runs.sqlite")
    first = catalog.new_run_id("frf")
    second = catalog.new_run_id("frf")
    stamp = first[:8]

    with pytest.raises(RunLookupError, match="ambiguous") as ambiguous:
        catalog.get(stamp)
    assert first in str(ambiguous.value) and second in str(ambiguous.value)
    assert isinstance(ambiguous.value, KeyError)

    with pytest.raises(KeyError, match="no run id starts with '19990101'"):
        catalog.get("19990101")
    with pytest.raises(KeyError, match="no run with id 'missing'"):
        catalog.finish("missing", "complete", "", 0)
    assert catalog.get(first).id == first


def test_underscore_in_prefix_is_not_a_wildcard(tmp_path: Path) -> None:
    catalog = Catalog(tmp_path / "runs.sqlite")
    run_id = catalog.new_run_id("a_b")
    catalog.new_run_id("axb")
    assert catalog.get(run_id[:-2]).id == run_id


def test_reader_sees_committed_rows_while_writer_runs(tmp_path: Path) -> None:
    path = tmp_path / "runs.sqlite"
    writer = Catalog(path)
    run_id = writer.new_run_id("frf")
    writer.add(run_id, "frf", "x.h5", {})
    with sqlite3.connect(path) as reader:
        assert reader.execute("PRAGMA journal_mode").fetchone() == ("wal",)
        reader.execute("BEGIN")
        assert reader.execute("SELECT status FROM runs").fetchall() == [("running",)]
        writer.finish(run_id, "complete", "", 10)
        assert reader.execute("SELECT status FROM runs").fetchall() == [("running",)]
        reader.execute("COMMIT")
        assert reader.execute("SELECT status, n_samples FROM runs").fetchall() == [
            ("complete", 10)
        ]


def test_a_catalog_made_before_pids_gets_the_columns_and_keeps_its_rows(tmp_path: Path) -> None:
    path = tmp_path / "catalog.sqlite"
    with sqlite3.connect(path) as old:
        old.execute("CREATE TABLE runs (id TEXT PRIMARY KEY, experiment TEXT NOT NULL,"
                    " started_at TEXT, stopped_at TEXT, status TEXT NOT NULL,"
                    " reason TEXT NOT NULL DEFAULT '', file TEXT, n_samples INTEGER,"
                    " params JSON NOT NULL DEFAULT '{}')")
        old.execute("INSERT INTO runs (id, experiment, status, n_samples) VALUES"
                    " ('20260101-000000-frf-1', 'frf', 'complete', 12)")
    catalog = Catalog(path)
    [row] = catalog.list()
    assert (row.id, row.status, row.n_samples, row.pid, row.host) == (
        "20260101-000000-frf-1", "complete", 12, None, None)
    catalog.add(run_id := catalog.new_run_id("frf"), "frf", tmp_path / "x.h5", {})
    assert (catalog.get(run_id).pid, catalog.get(run_id).host) == (os.getpid(),
                                                                   socket.gethostname())


OPEN_AND_ADD = """
import sys
from feedbench.daq.catalog import Catalog
catalog = Catalog(sys.argv[1])
catalog.add(catalog.new_run_id("frf"), "frf", "x.h5", {})
"""


def test_processes_opening_an_old_catalog_at_once_all_add_their_run(tmp_path: Path) -> None:
    path = tmp_path / "catalog.sqlite"
    with sqlite3.connect(path) as old:
        old.execute("CREATE TABLE runs (id TEXT PRIMARY KEY, experiment TEXT NOT NULL,"
                    " started_at TEXT, stopped_at TEXT, status TEXT NOT NULL,"
                    " reason TEXT NOT NULL DEFAULT '', file TEXT, n_samples INTEGER,"
                    " params JSON NOT NULL DEFAULT '{}')")
    processes = [subprocess.Popen([sys.executable, "-c", OPEN_AND_ADD, str(path)],
                                  stderr=subprocess.PIPE, text=True) for _ in range(4)]
    errors = [process.communicate(timeout=60)[1] for process in processes]
    assert [process.returncode for process in processes] == [0] * 4, errors
    rows = Catalog(path).list()
    assert sorted(row.pid for row in rows) == sorted(process.pid for process in processes)


UNVERSIONED = Path(__file__).parent / "data" / "catalog-unversioned.sqlite"
"""A catalog written by the code before schema versions (issue 28: commit 92b4afd's
`Catalog`): three finished runs, recorded by pid 4242 on host bench-pc."""


def test_a_catalog_made_before_schema_versions_upgrades_in_place_and_lists_the_same_runs(
        tmp_path: Path) -> None:
    path = tmp_path / "catalog.sqlite"
    path.write_bytes(UNVERSIONED.read_bytes())
    catalog = Catalog(path)
    assert [(row.id, row.experiment, row.status, row.reason, row.n_samples, row.params,
             row.timing, row.pid, row.host, row.bench, row.file) for row in catalog.list()] == [
        ("20261128-094414-chirp-3", "chirp", "complete", "", 8000,
         {"type": "chirp", "f_start_Hz": 5.0, "f_stop_Hz": 120.0}, None, 4242, "bench-pc", None,
         str(tmp_path / "20261128-094414-chirp-3.h5")),
        ("20261128-094414-chirp-2", "chirp", "aborted", "limit tripped: |force|", 1234,
         {"type": "chirp", "f_start_Hz": 5.0, "f_stop_Hz": 200.0}, {"missed": 0, "late": 2},
         4242, "bench-pc", None, str(tmp_path / "20261128-094414-chirp-2.h5")),
        ("20261128-094414-friction_sweep-1", "friction_sweep", "complete", "", 4940,
         {"type": "friction_sweep", "feeds_mm_min": [100, 200]}, None, 4242, "bench-pc", None,
         str(tmp_path / "20261128-094414-friction_sweep-1.h5")),
    ]
    with closing(sqlite3.connect(path)) as connection:
        assert connection.execute("SELECT version FROM catalog_schema").fetchall() == [
            (SCHEMA_VERSION,)]
        assert connection.execute("SELECT seq, id FROM runs ORDER BY seq").fetchall() == [
            (1, "20261128-094414-friction_sweep-1"), (2, "20261128-094414-chirp-2"),
            (3, "20261128-094414-chirp-3")]
    newest = catalog.new_run_id("chirp")
    assert [row.id for row in Catalog(path).list(limit=2)] == [newest,
                                                               "20261128-094414-chirp-3"]
