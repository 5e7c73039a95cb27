"""The run catalog on PostgreSQL (issue 28, item 1), against a real throw-away server
(`pg_server`): the same catalog as SQLite's (reconcile, damaged rows, rebuild from files, each
test on both), runs carrying their bench and host, `feedbench runs` filters, and a password
that never lands anywhere a run writes."""

from __future__ import annotations

import json
import logging
import os
import socket
import subprocess
import sys
import uuid
from pathlib import Path

import pytest
from sqlalchemy import text

from feedbench.bench import parse_run_config, run_config
from feedbench.commands.cli import main
from feedbench.config import ConfigError
from feedbench.daq.catalog import Catalog, RunRow, open_catalog
from feedbench.daq.recording import open_recording
from feedbench.daq.run_filter import Condition, RunFilter
from pg_server import BINARIES, postgres_url, server  # noqa: F401  (fixtures)
from prerequisites import requires
from test_catalog_truth import short_sweep
from test_report import friction_steps, record

needs_postgres = requires(BINARIES is not None, "PostgreSQL's server programs (Debian package "
                          "postgresql; .ci/run installs it)")
SECRET_URL = "postgresql://lab:{password}@127.0.0.1:5432/runs"


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=needs_postgres)])
def location(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """The catalog of the runs in `tmp_path`: its SQLite file, or a PostgreSQL database."""
    if request.param == "sqlite":
        return str(tmp_path / "catalog.sqlite")
    return request.getfixturevalue("postgres_url")


def execute(catalog: Catalog, statement: str, **params: object) -> None:
    """Change the catalog behind its back (as a crash or a damaged disk leaves it)."""
    with catalog._engine.begin() as connection:
        connection.execute(text(statement), params)


def dead_pid() -> int:
    """The pid of a process that has ended."""
    return int(subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                              capture_output=True, text=True, check=True).stdout)


@needs_postgres
def test_runs_carry_bench_and_host_and_list_newest_first(postgres_url, tmp_path):
    rig = Catalog(postgres_url, directory=tmp_path / "rig", bench="rack-pinion-rig")
    first = rig.new_run_id("friction_sweep")
    rig.add(first, "friction_sweep", tmp_path / "rig" / f"{first}.h5", {"feeds": 2})
    second = Catalog(postgres_url, bench="feed-drive").new_run_id("friction_sweep")
    rig.finish(first, "complete", "", 4940, {"missed": 0})

    row = rig.get(first)
    assert row == RunRow(id=first, experiment="friction_sweep", started_at=row.started_at,
                         stopped_at=row.stopped_at, status="complete", reason="",
                         file=str(tmp_path / "rig" / f"{first}.h5"), n_samples=4940,
                         params={"feeds": 2}, pid=os.getpid(), host=socket.gethostname(),
                         timing={"missed": 0}, bench="rack-pinion-rig")
    assert row.started_at < row.stopped_at
    assert second != first, "ids unique across the catalog's benches"
    assert [(r.id, r.bench, r.status) for r in rig.list()] == [
        (second, "feed-drive", "created"), (first, "rack-pinion-rig", "complete")]
    assert (rig.get(second).bench, rig.get(second).file) == ("feed-drive", None)
    assert rig.name == postgres_url


def some_runs(catalog: Catalog) -> dict[str, str]:
    """Four finished runs of two families on two benches: label → id."""
    runs = {}
    for label, family, bench, params, status in [
            ("low", "chirp", "rig", {"f_stop_Hz": 120.0}, "complete"),
            ("high", "chirp", "rig", {"f_stop_Hz": 200.0}, "aborted"),
            ("other", "chirp", "feed", {"f_stop_Hz": 500.0}, "complete"),
            ("sweep", "friction_sweep", "rig", {"f_stop_Hz": 900, "feeds": [1, 2]},
             "complete")]:
        catalog.bench = bench
        runs[label] = catalog.new_run_id(family)
        catalog.add(runs[label], family, f"{runs[label]}.h5", params)
        catalog.finish(runs[label], status, "", 10)
    return runs


@pytest.mark.parametrize("where, expected", [
    (RunFilter(bench="rig"), ["sweep", "high", "low"]),
    (RunFilter(experiment="chirp", status="complete"), ["other", "low"]),
    (RunFilter(where=(Condition.parse("chirp.f_stop_Hz>150"),)), ["other", "high"]),
    (RunFilter(where=(Condition.parse("f_stop_Hz>150"),)), ["sweep", "other", "high"]),
    (RunFilter(experiment="chirp", where=(Condition.parse("f_stop_Hz <= 200"),)),
     ["high", "low"]),
    (RunFilter(where=(Condition.parse("friction_sweep.feeds=[1, 2]"),)), ["sweep"]),
    (RunFilter(since="2000-01-01", until="2001-01-01"), []),
])
def test_filters_select_the_same_runs_on_both(location, tmp_path, where, expected):
    catalog = Catalog(location, directory=tmp_path)
    runs = some_runs(catalog)
    assert [row.id for row in catalog.list(where=where)] == [runs[label] for label in expected]
    assert len(catalog.list(limit=2, where=RunFilter(bench="rig"))) == 2


@needs_postgres
def test_feedbench_runs_filters_on_postgresql(postgres_url, tmp_path, capsys, monkeypatch):
    runs = some_runs(Catalog(postgres_url, directory=tmp_path))
    today = runs["low"][:4] + "-" + runs["low"][4:6] + "-" + runs["low"][6:8]
    monkeypatch.setenv("FEEDBENCH_CATALOG", postgres_url)
    assert main(["runs", "--json", "--bench", "rig", "--where", "chirp.f_stop_Hz>150",
                 "--since", today, "--until", today]) == 0
    listed = json.loads(capsys.readouterr().out)["runs"]
    assert [(row["id"], row["bench"], row["host"]) for row in listed] == [
        (runs["high"], "rig", socket.gethostname())]
    assert main(["runs", "--catalog", postgres_url, "--family", "chirp", "--status",
                 "complete"]) == 0
    assert [line.split()[:2] for line in capsys.readouterr().out.splitlines()] == [
        [runs["other"], "complete"], [runs["low"], "complete"]]
    assert main(["runs", "--where", "f_stop_Hz"]) == 2
    assert capsys.readouterr().err.startswith("feedbench: error: --where: 'f_stop_Hz' is not "
                                              "PATH OP VALUE")


def test_reconcile_settles_runs_a_dead_process_left_the_same_on_both(location, tmp_path):
    catalog = Catalog(location, directory=tmp_path)
    closed = catalog.new_run_id("friction_sweep")
    record(tmp_path / f"{closed}.h5", "friction_sweep", friction_steps(), status="aborted",
           reason="limit tripped: |force|")
    catalog.add(closed, "friction_sweep", tmp_path / f"{closed}.h5", {})
    never = catalog.new_run_id("chirp")
    assert catalog.reconcile() == [], "its process (this one) is alive"
    execute(catalog, "UPDATE runs SET pid = :pid", pid=dead_pid())

    assert sorted(catalog.reconcile()) == sorted([closed, never])
    rows = {row.id: row for row in catalog.list()}
    in_file = open_recording(tmp_path / f"{closed}.h5")
    assert (rows[closed].status, rows[closed].reason, rows[closed].n_samples,
            rows[closed].stopped_at) == ("aborted", "limit tripped: |force|", in_file.n_samples,
                                         in_file.stopped_at)
    assert (rows[never].status, rows[never].n_samples) == ("crashed", 0)
    assert rows[never].reason.endswith("ended without finishing the run (no recording started)")
    assert catalog.reconcile() == [], "settled once"


def test_a_damaged_row_is_listed_damaged_and_rebuilt_from_its_file_on_both(location, tmp_path):
    catalog = Catalog(location, directory=tmp_path)
    ids = ["20261125-101010-friction_sweep-1", "20261125-101011-friction_sweep-1"]
    for run_id in ids:
        record(tmp_path / f"{run_id}.h5", "friction_sweep", friction_steps(),
               config={"type": "friction_sweep", "feeds_mm_min": [1, 2]})
        catalog.add(run_id, "friction_sweep", tmp_path / f"{run_id}.h5", {"feeds": 2})
        catalog.finish(run_id, "complete", "", 4940)
    execute(catalog, "UPDATE runs SET params = '[1, 2]' WHERE id = :id", id=ids[0])

    rows = {row.id: row for row in catalog.list()}
    assert (rows[ids[0]].status, rows[ids[0]].file, rows[ids[0]].reason) == (
        "damaged", str(tmp_path / f"{ids[0]}.h5"), "catalog row damaged: params is not a JSON "
        "object (got list) (feedbench catalog rebuild recreates it from its file)")
    assert [row.id for row in catalog.list(where=RunFilter(status="damaged"))] == [ids[0]]
    assert catalog.rebuild() == (2, [])
    assert [(row.id, row.status, row.n_samples, row.params) for row in catalog.list()] == [
        (run_id, "complete", 4940, {"type": "friction_sweep", "feeds_mm_min": [1, 2]})
        for run_id in ids[::-1]]


def test_sync_registers_what_the_recordings_say_and_changes_nothing_else_on_both(
        location, tmp_path):
    """Runs recorded while the catalog was unreachable: one it never heard of, one whose
    process (alive: `reconcile` leaves it) could not write its end."""
    catalog = Catalog(location, directory=tmp_path)
    unfinished = catalog.new_run_id("friction_sweep")
    catalog.add(unfinished, "friction_sweep", tmp_path / f"{unfinished}.h5", {})
    other = catalog.new_run_id("chirp")
    catalog.add(other, "chirp", tmp_path / "elsewhere.h5", {"f_stop_Hz": 200.0})
    unknown = "20261125-101010-friction_sweep-1"
    for run_id, status in ((unfinished, "aborted"), (unknown, "complete")):
        record(tmp_path / f"{run_id}.h5", "friction_sweep", friction_steps(), status=status,
               reason="SIGINT" if status == "aborted" else "")
    assert catalog.reconcile() == []

    assert catalog.sync() == ([unknown], [unfinished])
    rows = {row.id: row for row in catalog.list()}
    assert [(rows[i].status, rows[i].reason, rows[i].n_samples, rows[i].bench) for i in (
        unfinished, unknown)] == [("aborted", "SIGINT", 4940, catalog.bench),
                                  ("complete", "", 4940, catalog.bench)]
    assert (rows[other].status, rows[other].params) == ("running", {"f_stop_Hz": 200.0})
    assert catalog.sync() == ([], []), "once"


@needs_postgres
def test_rebuild_replaces_its_directorys_rows_and_keeps_the_other_benches(postgres_url,
                                                                          tmp_path):
    """Two benches, two directories, one catalog: rebuilding one leaves the other's runs."""
    mine, theirs = tmp_path / "mine", tmp_path / "theirs"
    mine.mkdir(), theirs.mkdir()
    other = Catalog(postgres_url, directory=theirs, bench="feed-drive")
    kept = other.new_run_id("chirp")
    other.add(kept, "chirp", theirs / f"{kept}.h5", {"f_stop_Hz": 200.0})
    other.finish(kept, "complete", "", 7)
    catalog = Catalog(postgres_url, directory=mine, bench="rig")
    gone = catalog.new_run_id("chirp")  # no recording, its process gone
    execute(catalog, "UPDATE runs SET pid = NULL WHERE id = :id", id=gone)
    found = "20261125-101010-friction_sweep-1"
    record(mine / f"{found}.h5", "friction_sweep", friction_steps())

    assert catalog.rebuild() == (1, [])
    rows = {row.id: row for row in catalog.list()}
    assert sorted(rows) == sorted([kept, found])
    assert (rows[kept].bench, rows[kept].n_samples, rows[kept].file) == (
        "feed-drive", 7, str(theirs / f"{kept}.h5"))
    assert (rows[found].bench, rows[found].status, rows[found].file) == (
        "rig", "complete", str(mine / f"{found}.h5"))


@pytest.mark.parametrize("field, open_it", [
    ("bench.catalog", lambda url, tmp, _: parse_run_config(
        {**short_sweep(tmp, "x"), "bench": {"catalog": url}})),
    ("--catalog", lambda url, tmp, _: open_catalog(tmp, option=url)),
    ("FEEDBENCH_CATALOG", lambda url, tmp, environ: (
        environ.setenv("FEEDBENCH_CATALOG", url), open_catalog(tmp))),
])
def test_a_url_with_a_password_is_refused_naming_its_field(tmp_path, monkeypatch, field,
                                                            open_it):
    monkeypatch.delenv("FEEDBENCH_CATALOG", raising=False)
    password = "hunter2-" + uuid.uuid4().hex
    for url in (SECRET_URL.format(password=password),
                f"postgresql://lab@127.0.0.1/runs?password={password}"):
        with pytest.raises(ConfigError) as refused:
            open_it(url, tmp_path, monkeypatch)
        assert str(refused.value) == (f"{field}: the URL holds a password; give it to libpq "
                                      "instead (PGPASSWORD, ~/.pgpass or a service file)")


def test_the_command_line_refuses_a_password_in_one_line(tmp_path, capsys):
    password = "hunter2-" + uuid.uuid4().hex
    assert main(["runs", "--catalog", SECRET_URL.format(password=password)]) == 2
    assert capsys.readouterr().err == ("feedbench: error: --catalog: the URL holds a password; "
                                       "give it to libpq instead (PGPASSWORD, ~/.pgpass or a "
                                       "service file)\n")


def every_byte(directory: Path) -> dict[str, bytes]:
    """Every file under `directory`: path → its bytes."""
    return {str(path): path.read_bytes() for path in directory.rglob("*") if path.is_file()}


@needs_postgres
def test_a_run_writes_its_catalogs_password_nowhere(postgres_url, server, tmp_path, can_channel,
                                                    capsys, caplog):
    """A simulated run catalogued in PostgreSQL with the password in PGPASSWORD, then
    `runs --json`, `analyze --json` and `report`: neither the recording, the report, the
    catalog's rows, the logs nor any output holds the password."""
    caplog.set_level(logging.DEBUG)
    raw = short_sweep(tmp_path / "runs", can_channel)
    raw["bench"]["catalog"] = postgres_url
    row = run_config(parse_run_config(raw), progress=True)
    assert row["status"] == "complete"
    assert open_recording(row["file"]).config["bench"]["catalog"] == postgres_url
    assert main(["runs", "--json", "--catalog", postgres_url]) == 0
    outputs = [capsys.readouterr()]
    [listed] = json.loads(outputs[0].out)["runs"]
    assert (listed["id"], listed["host"], listed["file"]) == (row["id"], socket.gethostname(),
                                                              row["file"])
    for command in (["analyze", row["id"], "--json"],
                    ["report", row["id"], "-o", str(tmp_path / "runs" / "report.html")]):
        assert main([*command, "--catalog", postgres_url]) == 0
        outputs.append(capsys.readouterr())
    with Catalog(postgres_url)._engine.connect() as connection:
        catalog_text = json.dumps([list(map(str, r)) for table in ("runs", "catalog_schema")
                                   for r in connection.execute(text(f"SELECT * FROM {table}"))])
    assert row["id"] in catalog_text

    written = {**every_byte(tmp_path), "catalog": catalog_text.encode(),
               "output": "".join(map("".join, outputs)).encode(), "log": caplog.text.encode()}
    assert {f"{tmp_path / 'runs'}/{row['id']}.h5", str(tmp_path / "runs" / "report.html")} <= set(
        written)
    assert [name for name, data in written.items() if server.password.encode() in data] == []
