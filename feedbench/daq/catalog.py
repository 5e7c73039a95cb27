"""SQLite run catalog: one row per run (id, experiment, times, status, file, key parameters,
the pid and host of the process that records it).

Every call opens its own connection and runs one short transaction, so one writer (the
runner) and any number of readers (CLI, analysis, live window) can share the file; the
database is in WAL mode so readers never block the writer.

The recordings are the source of truth, the catalog an index of them: `reconcile` marks
`crashed` a run whose process ended without finishing it (samples counted from its file),
`rebuild` recreates the rows from the recordings in the catalog's directory, and a catalog
file that SQLite finds corrupt is moved aside (``catalog.sqlite.corrupt-<UTC time>``) and
rebuilt when it is opened, with one warning line; so is an existing empty file or one
without the runs table when recordings sit beside it. A row that cannot be read (a JSON
column that is not a JSON object) is listed with status `damaged`, its file and why; the
other rows as they are. A catalog that cannot be read or written (read-only or full disk)
raises `CatalogError`, one line.

Recording paths are stored relative to the catalog's directory and given back as paths from
the current directory, so every command finds them from anywhere; a catalog made before
(paths relative to the directory its runs were started from, or absolute) is still read.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import re
import socket
import sqlite3
from collections.abc import Iterator, Mapping
from contextlib import closing, contextmanager, suppress
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from feedbench.config import ConfigError
from feedbench.daq.recorder import mark_crashed
from feedbench.daq.recording import RecordingSummary, read_summary, to_json, utc_now_iso

SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    id TEXT PRIMARY KEY,
    experiment TEXT NOT NULL,
    started_at TEXT,
    stopped_at TEXT,
    status TEXT NOT NULL,
    reason TEXT NOT NULL DEFAULT '',
    file TEXT,
    n_samples INTEGER,
    params JSON NOT NULL DEFAULT '{}',
    pid INTEGER,
    host TEXT,
    timing JSON
)
"""
ADDED_COLUMNS = {"pid": "INTEGER", "host": "TEXT", "timing": "JSON"}
"""Columns a catalog made before them gets when it is opened."""
COLUMN_NAMES = ("id", "experiment", "started_at", "stopped_at", "status", "reason", "file",
                "n_samples", "params", "pid", "host", "timing")
COLUMNS = ", ".join(COLUMN_NAMES)
UNFINISHED = ("created", "running")
"""Statuses of a run whose process has not finished it (yet)."""
DAMAGED = "damaged"
"""Status of a row the catalog cannot read (its file and why in the reason)."""
JSON_COLUMNS = {"params": {}, "timing": None}
"""The JSON columns and what a row without a value has."""
CORRUPT = (sqlite3.SQLITE_NOTADB, sqlite3.SQLITE_CORRUPT)
BUSY_TIMEOUT_S = 10.0
LOGGER = logging.getLogger(__name__)


class CatalogError(ConfigError):
    """The catalog file cannot be read or written (read-only or full disk, not SQLite)."""


class RunLookupError(ConfigError, KeyError):
    """No run, or more than one run, matches the given id or prefix (a user error: the CLI
    prints it as one line)."""

    def __str__(self) -> str:
        return str(self.args[0])


@dataclass(frozen=True)
class RunRow:
    """One catalog row; times are ISO 8601 UTC text, `params` the run's key parameters,
    `timing` a real-time run's cycle timing (`daq.timing.CycleTiming.as_dict`: missed,
    repeated and late cycles, lateness histogram in µs; None in lockstep)."""

    id: str
    experiment: str
    started_at: str | None
    stopped_at: str | None
    status: str
    reason: str
    file: str | None
    n_samples: int | None
    params: dict[str, Any]
    pid: int | None = None
    host: str | None = None
    timing: dict[str, Any] | None = None


class Catalog:
    """The run catalog stored in the SQLite file `path` (created if missing; a corrupt one
    is moved aside and rebuilt from the recordings beside it, an existing empty file or one
    without the runs table rebuilt from them unless `rebuild_empty` is False; a new file is
    not: `rebuild` makes it list recordings made before it)."""

    def __init__(self, path: str | Path, *, rebuild_empty: bool = True) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        existed, self._made_table = self.path.exists(), False
        if self._problems():
            with open(f"{self.path}.lock", "w") as lock:
                fcntl.flock(lock, fcntl.LOCK_EX)  # one process replaces it, the others wait
                if problems := self._problems():  # and then find the new one sound
                    self._replace_corrupt("; ".join(problems[:3]))
        elif existed and self._made_table and rebuild_empty and any(
                self.path.parent.glob("*.h5")):
            self._rebuild_empty()

    def _problems(self) -> list[str]:
        """`_create`, and what makes the file a corrupt catalog (nothing: an empty list)."""
        try:
            return self._create()
        except CatalogError as exc:
            if getattr(exc.__cause__, "sqlite_errorcode", None) not in CORRUPT:
                raise
            return [str(exc.__cause__)]

    def _create(self) -> list[str]:
        """Make the table (and the columns added since a catalog was made: under the write
        lock, so that processes opening it at once add them once); returns what SQLite's
        integrity check finds wrong (nothing: an empty list)."""
        with self._transaction() as connection:
            connection.execute("PRAGMA journal_mode=WAL")
        with self._transaction(immediate=True) as connection:
            self._made_table = not connection.execute(
                "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'runs'").fetchone()
            connection.execute(SCHEMA)
            present = {row[1] for row in connection.execute("PRAGMA table_info(runs)")}
            for name, kind in ADDED_COLUMNS.items():
                if name not in present:
                    connection.execute(f"ALTER TABLE runs ADD COLUMN {name} {kind}")
            return [row[0] for row in connection.execute("PRAGMA quick_check")
                    if row[0] != "ok"]

    def _replace_corrupt(self, problem: str) -> None:
        """Rebuild the catalog from the recordings in a new file, keep the corrupt one under
        another name, put the new one in its place, say so in one line. The replacement is
        one rename: no process ever finds the catalog missing or not yet rebuilt."""
        stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")
        aside = self.path.with_name(f"{self.path.name}.corrupt-{stamp}")
        fresh = self.path.with_name(f"{self.path.name}.rebuilding")
        for suffix in ("", "-wal", "-shm"):  # what a rebuild cut short left
            Path(f"{fresh}{suffix}").unlink(missing_ok=True)
        added, skipped = Catalog(fresh, rebuild_empty=False).rebuild()
        os.link(self.path, aside)
        for suffix in ("-wal", "-shm"):  # the corrupt file's: never the new one's
            with suppress(FileNotFoundError):
                Path(f"{self.path}{suffix}").rename(f"{aside}{suffix}")
        fresh.replace(self.path)
        LOGGER.warning("%s: corrupt run catalog (%s) moved to %s; rebuilt from %d recording(s)"
                       "%s", self.path, problem, aside.name, added,
                       f", {len(skipped)} file(s) skipped" if skipped else "")

    def _rebuild_empty(self) -> None:
        """Rebuild a catalog file that had no runs table (an empty file, or another SQLite
        file) from the recordings beside it; say so in one line."""
        added, skipped = self.rebuild()
        LOGGER.warning("%s: run catalog had no runs table (an empty file?) with recordings "
                       "beside it; rebuilt from %d recording(s)%s", self.path, added,
                       f", {len(skipped)} file(s) skipped" if skipped else "")

    def new_run_id(self, experiment: str) -> str:
        """Reserve a unique, time-sortable id `YYYYMMDD-HHMMSS-<experiment>-<n>` (UTC).

        `n` counts the ids reserved in the same second; the row is created with status
        `created` so two calls never return the same id.
        """
        stamp = datetime.now(timezone.utc).strftime("%Y%m%d-%H%M%S")
        name = re.sub(r"[^A-Za-z0-9_]+", "_", experiment)
        with self._transaction(immediate=True) as connection:
            (taken,) = connection.execute(
                "SELECT COUNT(*) FROM runs WHERE substr(id, 1, ?) = ?",
                (len(stamp) + 1, stamp + "-"),
            ).fetchone()
            run_id = f"{stamp}-{name}-{taken + 1}"
            connection.execute(
                "INSERT INTO runs (id, experiment, status, pid, host)"
                " VALUES (?, ?, 'created', ?, ?)",
                (run_id, experiment, os.getpid(), socket.gethostname()),
            )
        return run_id

    def add(self, run_id: str, experiment: str, file: str | Path,
            params: Mapping[str, Any]) -> None:
        """Register the start of run `run_id` (status `running`, started now, recorded by
        this process on this host)."""
        with self._transaction() as connection:
            connection.execute(
                "INSERT INTO runs (id, experiment, started_at, status, file, params, pid, host)"
                " VALUES (?, ?, ?, 'running', ?, ?, ?, ?)"
                " ON CONFLICT(id) DO UPDATE SET experiment = excluded.experiment,"
                " started_at = excluded.started_at, status = excluded.status,"
                " file = excluded.file, params = excluded.params, pid = excluded.pid,"
                " host = excluded.host",
                (run_id, experiment, utc_now_iso(), self._stored(file), to_json(dict(params)),
                 os.getpid(), socket.gethostname()),
            )

    def finish(self, run_id: str, status: str, reason: str, n_samples: int,
               timing: Mapping[str, Any] | None = None) -> None:
        """Record the end of run `run_id`: status (complete / aborted), reason, sample count,
        a real-time run's cycle timing."""
        with self._transaction() as connection:
            updated = connection.execute(
                "UPDATE runs SET stopped_at = ?, status = ?, reason = ?, n_samples = ?,"
                " timing = ? WHERE id = ?",
                (utc_now_iso(), status, reason, int(n_samples), _timing_json(timing), run_id),
            ).rowcount
        if not updated:
            raise RunLookupError(f"no run with id {run_id!r} in {self.path}")

    def list(self, limit: int | None = None) -> list[RunRow]:
        """Runs newest first (in the order their ids were created), at most `limit`."""
        with self._transaction() as connection:
            rows = connection.execute(
                f"SELECT {COLUMNS} FROM runs ORDER BY rowid DESC LIMIT ?",
                (-1 if limit is None else limit,),
            ).fetchall()
        return [self._row(row) for row in rows]

    def get(self, run_id_or_prefix: str) -> RunRow:
        """The run with this exact id, else the only run whose id starts with it."""
        with self._transaction() as connection:
            rows = connection.execute(
                f"SELECT {COLUMNS} FROM runs WHERE id = ?", (run_id_or_prefix,)
            ).fetchall() or connection.execute(
                f"SELECT {COLUMNS} FROM runs WHERE substr(id, 1, ?) = ? ORDER BY id",
                (len(run_id_or_prefix), run_id_or_prefix),
            ).fetchall()
        if not rows:
            raise RunLookupError(f"no run id starts with {run_id_or_prefix!r} in {self.path}")
        if len(rows) > 1:
            matches = ", ".join(row[0] for row in rows)
            raise RunLookupError(f"run id prefix {run_id_or_prefix!r} is ambiguous: {matches}")
        return self._row(rows[0])

    def reconcile(self) -> list[str]:
        """Settle the runs left `created` or `running` by a process that has ended: the
        recording's own final status if it has one, else `crashed` with the samples its file
        holds, which the file then says too (`recorder.mark_crashed`). A run whose process
        still runs, or runs on another host, is left alone, its file not even opened: its
        process finishes it. Returns the ids changed."""
        with self._transaction() as connection:
            rows = connection.execute(
                "SELECT id, file, pid, host FROM runs WHERE status IN (?, ?)", UNFINISHED
            ).fetchall()
        changed = []
        for run_id, file, pid, host in rows:
            file = self._resolved(file)
            if not _ended(pid, host, file):
                continue
            summary, why = _summary(file)
            if summary is not None and summary.status not in UNFINISHED:
                self._settle(run_id, summary.status, summary.reason, summary.n_samples,
                             summary.stopped_at, summary.timing)
            else:
                reason = (f"process {pid} on {host} ended without finishing the run"
                          f"{f' ({why})' if why else ''}")
                if summary is not None:
                    _mark_file(file, reason, summary.n_samples)
                self._settle(run_id, "crashed", reason,
                             summary.n_samples if summary else 0, None)
            changed.append(run_id)
        return changed

    def rebuild(self) -> tuple[int, list[str]]:
        """Recreate the rows from the recordings (``*.h5``) in the catalog's directory: one
        row per recording (its key parameters: the recorded `[experiment]` table); a file
        still `running` keeps that status if a process on this host has it open for writing
        (its pid), else it is `crashed`. The row of a run in progress is kept until its file
        says how it ended. Rows are in the order the runs started. Returns the number of
        recordings read and one line per file skipped (not a feedbench recording)."""
        rows, skipped = {}, []
        for path in sorted(self.path.parent.glob("*.h5")):
            summary, why = _summary(str(path))
            if summary is None:
                skipped.append(why)
            else:
                rows[summary.run_id] = _rebuilt_row(summary, self._stored(path))
        added = len(rows)
        with self._transaction(immediate=True) as connection:
            for row in connection.execute(
                    f"SELECT {COLUMNS} FROM runs WHERE status IN (?, ?)", UNFINISHED).fetchall():
                live = dict(zip(COLUMN_NAMES, row))
                in_file = dict(zip(COLUMN_NAMES, rows.get(live["id"], row)))
                if (not _ended(live["pid"], live["host"], self._resolved(live["file"]))
                        and in_file["status"] in UNFINISHED):
                    rows[live["id"]] = row
            connection.execute("DELETE FROM runs")
            connection.executemany(
                f"INSERT INTO runs ({COLUMNS}) VALUES ({', '.join('?' * len(COLUMN_NAMES))})",
                sorted(rows.values(), key=lambda row: row[COLUMN_NAMES.index("started_at")]
                       or "~"))  # a run not started yet: last
        return added, skipped

    def _stored(self, file: str | Path) -> str:
        """A recording's path as the catalog stores it: relative to its directory."""
        return os.path.relpath(Path(file).absolute(), self.path.parent.absolute())

    def _resolved(self, stored: str | None) -> str | None:
        """A stored recording path as a path from the current directory: relative to the
        catalog's directory (or absolute); an old catalog's path relative to the directory
        its run was started from if it names a file from here, else the file of that name
        beside the catalog."""
        if stored is None:
            return None
        beside = self.path.parent / stored
        if not beside.exists():
            for old in (Path(stored), self.path.parent / Path(stored).name):
                if old.exists():
                    return str(old)
        return str(beside)

    def _row(self, row: tuple[Any, ...]) -> RunRow:
        """A catalog row as a `RunRow`, its file resolved (`_resolved`); a row whose JSON
        columns cannot be read is `damaged`, the reason names the column and why."""
        values = dict(zip(COLUMN_NAMES, row))
        values["file"] = self._resolved(values["file"])
        problems = []
        for name, empty in JSON_COLUMNS.items():
            values[name], problem = _json_column(name, values[name], empty)
            if problem:
                problems.append(problem)
        if problems:
            values.update(status=DAMAGED, reason=f"catalog row damaged: {'; '.join(problems)} "
                          "(feedbench catalog rebuild recreates it from its file)")
        return RunRow(**values)

    def _settle(self, run_id: str, status: str, reason: str, n_samples: int,
                stopped_at: str | None, timing: Mapping[str, Any] | None = None) -> None:
        with self._transaction() as connection:
            connection.execute(
                "UPDATE runs SET stopped_at = ?, status = ?, reason = ?, n_samples = ?,"
                " timing = ? WHERE id = ? AND status IN (?, ?)",
                (stopped_at or None, status, reason, n_samples, _timing_json(timing), run_id,
                 *UNFINISHED),
            )

    @contextmanager
    def _transaction(self, immediate: bool = False) -> Iterator[sqlite3.Connection]:
        """One connection, one transaction: committed on success, rolled back on error; an
        SQLite error (read-only or full disk, not a database) raises `CatalogError`."""
        try:
            with closing(sqlite3.connect(self.path, timeout=BUSY_TIMEOUT_S)) as connection:
                if immediate:
                    connection.execute("BEGIN IMMEDIATE")
                with connection:
                    yield connection
        except sqlite3.DatabaseError as exc:
            raise CatalogError(f"{self.path}: cannot use the run catalog ({exc})") from exc


def _json_column(name: str, text: str | None, empty: Any) -> tuple[Any, str]:
    """The value of JSON column `name` (`empty` for none) and '' or why it cannot be read
    (not JSON, or not a JSON object)."""
    if not text:
        return empty, ""
    try:
        value = json.loads(text)
    except (TypeError, ValueError) as exc:
        return empty, f"{name} is not JSON ({exc})"
    if not isinstance(value, dict):
        return empty, f"{name} is not a JSON object (got {type(value).__name__})"
    return value, ""


def _timing_json(timing: Mapping[str, Any] | None) -> str | None:
    return to_json(dict(timing)) if timing else None


def _summary(file: str | None) -> tuple[RecordingSummary | None, str]:
    """The recording's summary, or None and why it cannot be read."""
    if file is None:
        return None, "no recording started"
    try:
        return read_summary(file), ""
    except ConfigError as exc:
        return None, str(exc)


def _mark_file(file: str, reason: str, n_samples: int) -> None:
    """The recording of a run whose process has ended says so too (`mark_crashed`); a file
    that cannot be written (read-only medium) keeps its status, the catalog row is settled."""
    try:
        mark_crashed(file, reason, n_samples)
    except (OSError, RuntimeError) as exc:
        LOGGER.warning("%s: not marked crashed (%s)", file, exc)


def _ended(pid: int | None, host: str | None, file: str | None) -> bool:
    """True if the process that records a run is gone: process `pid` was on this host and
    has ended (another host: False; a pid the system has given to a new process keeps the
    run `running` until that one ends); a row made before pids were recorded: no process on
    this host has its file (if any) open for writing."""
    if pid is None:
        return file is None or _writing_process(Path(file)) is None
    if host != socket.gethostname():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:  # alive, another user's
        return False
    return False


def _rebuilt_row(summary: RecordingSummary, file: str) -> tuple[Any, ...]:
    """The catalog row of a recording found on disk as `file` (see `Catalog.rebuild`)."""
    status, pid, host = summary.status, None, None
    if status in UNFINISHED:
        pid = _writing_process(summary.path)
        status, host = ("running", socket.gethostname()) if pid else ("crashed", None)
    reason = summary.reason or ("no process writes it any more" if status == "crashed" else "")
    return (summary.run_id, summary.experiment, summary.started_at, summary.stopped_at or None,
            status, reason, file, summary.n_samples,
            to_json(summary.config.get("experiment", {})), pid, host,
            _timing_json(summary.timing))


def _writing_process(path: Path) -> int | None:
    """The pid of a process on this host that has `path` open for writing (Linux: /proc),
    None if there is none or it cannot be told."""
    target = str(path.resolve())
    for link in Path("/proc").glob("[0-9]*/fd/*"):
        with suppress(OSError):  # the process or descriptor went away, or is not ours
            if os.readlink(link) == target and _open_for_writing(link):
                return int(link.parts[2])
    return None


def _open_for_writing(link: Path) -> bool:
    """Whether the descriptor `/proc/<pid>/fd/<n>` is open for writing (its fdinfo flags)."""
    info = Path(f"/proc/{link.parts[2]}/fdinfo/{link.name}").read_text()
    flags = int(info.split("flags:")[1].split()[0], 8)
    return flags & os.O_ACCMODE != os.O_RDONLY

