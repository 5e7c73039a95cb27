"""Run catalog: one row per run (id, experiment, times, status, file, key parameters, the
bench, pid and host of the process that records it), in an SQLite file beside the recordings
(the default, ``runs/catalog.sqlite``) or in a PostgreSQL database a lab's benches share.

Which one: `open_catalog` takes ``--catalog URL``, else ``$FEEDBENCH_CATALOG``, else
``[bench] catalog``, else ``<output_dir>/catalog.sqlite``. A URL that holds a password is
refused in one line naming where it came from: the password comes from libpq's own
conventions (``PGPASSWORD``, ``~/.pgpass``, a service file: ``postgresql:///?service=lab``),
so it never lands in a recording's config, the catalog, a log, a report or ``--json``. A run's
bench is ``$FEEDBENCH_BENCH``, else its host's name.

SQLAlchemy Core rather than psycopg alone: one table definition and one set of statements
compiled for both databases (parameter styles, DDL, the auto-increment key), and URLs parsed
and shown without a password; psycopg 3 underneath is libpq, so PGPASSWORD, ~/.pgpass and
service files work as in psql. No ORM: rows are tuples.

Schema versions: a small numbered migration runner (`MIGRATIONS`), not alembic: a catalog
upgrades itself in place when any command opens it, under the catalog's write lock, with no
``alembic upgrade`` step for a bench's user and no script directory or env.py shipped in the
package for a few statements.

Every call opens its own connection and runs one short transaction, so any number of writers
(runners) and readers (CLI, analysis, live window) share the catalog; an SQLite file is in WAL
mode so readers never block the writer. What must see every write before it (a new run id, a
migration) holds the catalog's write lock: SQLite's ``BEGIN IMMEDIATE``, a PostgreSQL
transaction-level advisory lock.

The recordings are the source of truth, the catalog an index of them: `reconcile` marks
`crashed` a run whose process ended without finishing it (samples counted from its file),
`rebuild` recreates the rows of the recordings in the output directory, and a catalog file
that SQLite finds corrupt is moved aside (``catalog.sqlite.corrupt-<UTC time>``) and rebuilt
when it is opened, with one warning line; so is an existing empty file or one without the runs
table when recordings sit beside it. A row that cannot be read (a JSON column that is not a
JSON object) is listed with status `damaged`, its file and why; the other rows as they are. A
catalog that cannot be read or written (read-only or full disk, a server that is down) raises
`CatalogError`, one line.

Recording paths in an SQLite catalog are stored relative to its directory and given back as
paths from the current directory, so every command finds them from anywhere; a catalog made
before (paths relative to the directory its runs were started from, or absolute) is still
read. A PostgreSQL catalog stores absolute paths: each bench's recordings are on its host.
"""

from __future__ import annotations

import fcntl
import gc
import json
import logging
import os
import re
import socket
import sqlite3
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager, nullcontext, suppress
from dataclasses import dataclass
from functools import cached_property
from datetime import datetime, timezone
from itertools import islice
from pathlib import Path
from typing import Any, NamedTuple

from sqlalchemy import (BigInteger, Column, Integer, MetaData, Table, Text, bindparam,
                        create_engine, event, func, inspect, select, text)
from sqlalchemy.engine import URL, Connection, Engine, make_url
from sqlalchemy.exc import ArgumentError, DBAPIError
from sqlalchemy.pool import NullPool

from feedbench.config import ConfigError
from feedbench.daq.recorder import mark_crashed
from feedbench.daq.recording import RecordingSummary, read_summary, to_json, utc_now_iso
from feedbench.daq.run_filter import DAMAGED, RunFilter, parsed_parameters

METADATA = MetaData()
RUNS = Table(
    "runs", METADATA,
    Column("seq", Integer, primary_key=True, autoincrement=True),  # the order of listing
    Column("id", Text, nullable=False, unique=True),
    Column("experiment", Text, nullable=False),
    Column("started_at", Text),
    Column("stopped_at", Text),
    Column("status", Text, nullable=False),
    Column("reason", Text, nullable=False, server_default=""),
    Column("file", Text),
    Column("n_samples", BigInteger),
    Column("params", Text, nullable=False, server_default="{}"),  # JSON text
    Column("pid", Integer),
    Column("host", Text),
    Column("timing", Text),  # JSON text
    Column("bench", Text),
    Column("store", Text),  # the store copy's location (a path or fsspec URL: daq.store)
    Column("store_status", Text),  # copied, pending (None: no store)
    Column("store_reason", Text),  # why a copy is pending
    Column("sha256", Text),  # the recording's checksum, checked after the copy
)
SCHEMA = Table("catalog_schema", METADATA, Column("version", Integer, nullable=False))
COLUMN_NAMES = ("id", "experiment", "started_at", "stopped_at", "status", "reason", "file",
                "n_samples", "params", "pid", "host", "timing", "bench", "store", "store_status",
                "store_reason", "sha256")
STORE_COLUMNS = ("store", "store_status", "store_reason", "sha256")
"""The columns of a recording's store copy (`daq.store`), kept when its row is rebuilt."""
COLUMNS = ", ".join(COLUMN_NAMES)
UNFINISHED = ("created", "running")
"""Statuses of a run whose process has not finished it (yet)."""
JSON_COLUMNS = {"params": {}, "timing": None}
"""The JSON columns and what a row without a value has."""
SQLITE_CORRUPT = (sqlite3.SQLITE_NOTADB, sqlite3.SQLITE_CORRUPT)
BUSY_TIMEOUT_S = 10.0
CONNECT_TIMEOUT_S = 10
LOCK_KEY = 0x0FEEDBE4C
"""PostgreSQL advisory lock id of the catalog's write lock."""
DEFAULT_NAME = "catalog.sqlite"
CATALOG_ENV = "FEEDBENCH_CATALOG"
BENCH_ENV = "FEEDBENCH_BENCH"
BACKENDS = ("sqlite", "postgresql")
DELETE_BATCH = 500
INVALID_TEXT = "22P02"
"""PostgreSQL's SQLSTATE for text a cast refuses (parameters that are not JSON; SQLite says
"malformed JSON")."""
LOGGER = logging.getLogger(__name__)


class CatalogError(ConfigError):
    """The catalog cannot be read or written (read-only or full disk, not SQLite, a server
    that is down or refuses the connection)."""


class RunLookupError(ConfigError, KeyError):
    """No run, or more than one run, matches the given id or prefix (a user error: the CLI
    prints it as one line)."""

    def __str__(self) -> str:
        return str(self.args[0])


@dataclass(frozen=True)
class RunRow:
    """One catalog row; times are ISO 8601 UTC text, `params` the run's key parameters,
    `timing` a real-time run's cycle timing (`daq.timing.CycleTiming.as_dict`: missed,
    repeated and late cycles, lateness histogram in µs; None in lockstep), `bench` the name
    of the bench that recorded it; `store` where the recording's copy in the lab's store is
    (a path or fsspec URL), `store_status` ``copied`` or ``pending`` (`store_reason`: why;
    None: no store), `sha256` the recording's checksum (`daq.store`)."""

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
    bench: str | None = None
    store: str | None = None
    store_status: str | None = None
    store_reason: str | None = None
    sha256: str | None = None


class ListedRun(NamedTuple):
    """What a line of `feedbench runs` shows of a run (`Catalog.lines`): as its `RunRow`."""

    id: str
    status: str
    n_samples: int | None
    file: str | None
    reason: str


LINE_COLUMNS = ("id", "experiment", "status", "reason", "file", "n_samples", "params",
                "timing")
"""The columns `Catalog.lines` reads."""


def url_problem(text: str) -> str | None:
    """Check (a `config.Field`'s): why `text` is no catalog location (a URL with a password,
    another database than SQLite or PostgreSQL, not a URL), or None. Never shows the URL."""
    if "://" not in text:
        return None  # an SQLite file's path
    try:
        url = make_url(text)
    except ArgumentError:
        return ": not a database URL (postgresql://user@host/database or an SQLite file)"
    if url.password is not None or "password" in url.query:
        return (": the URL holds a password; give it to libpq instead (PGPASSWORD, ~/.pgpass "
                "or a service file)")
    if url.get_backend_name() not in BACKENDS:
        return f": the catalog is SQLite or PostgreSQL (got {url.get_backend_name()!r})"
    if url.get_backend_name() == "sqlite" and not url.database:
        return ": an SQLite catalog needs a file (sqlite:///path/catalog.sqlite)"
    return None


def catalog_url(text: str | Path, field: str) -> URL:
    """The catalog location `text` (a URL or an SQLite file's path) as a URL; one that
    `url_problem` rejects raises `ConfigError` naming `field`."""
    if problem := url_problem(str(text)):
        raise ConfigError(f"{field}{problem}")
    if "://" not in str(text):
        return URL.create("sqlite", database=str(text))
    return make_url(str(text))


def open_catalog(output_dir: str | Path, option: str = "", setting: str = "",
                 bench: str = "") -> Catalog:
    """The run catalog of the runs in `output_dir`: at `option` (``--catalog``), else
    ``$FEEDBENCH_CATALOG``, else `setting` (``[bench] catalog``), else
    ``<output_dir>/catalog.sqlite``; a location with a password raises `ConfigError` naming
    the one it came from. The runs this process records are `bench`'s (``[bench] name``)
    unless ``$FEEDBENCH_BENCH`` names another, as the catalog's location: the environment
    over the config (empty both: the host's name)."""
    name = os.environ.get(BENCH_ENV) or bench or None
    for field, location in (("--catalog", option), (CATALOG_ENV, os.environ.get(CATALOG_ENV)),
                            ("bench.catalog", setting)):
        if location:
            return Catalog(catalog_url(location, field), directory=output_dir, bench=name)
    return Catalog(Path(output_dir) / DEFAULT_NAME, directory=output_dir, bench=name)


class Catalog:
    """The run catalog at `location`: an SQLite file's path or URL, or a PostgreSQL URL
    (made if missing, an old one upgraded in place: `MIGRATIONS`). `directory` holds the
    recordings `rebuild` reads (default: an SQLite file's directory, else ``runs``); `bench`
    names the bench whose runs this process records (default: ``$FEEDBENCH_BENCH``, else the
    host's name). A corrupt SQLite file is moved aside and rebuilt from the recordings beside
    it, an existing empty file or one without the runs table rebuilt from them unless
    `rebuild_empty` is False; a new catalog is not: `rebuild` makes it list recordings made
    before it."""

    def __init__(self, location: str | Path | URL, *, directory: str | Path | None = None,
                 bench: str | None = None, rebuild_empty: bool = True) -> None:
        self.url = location if isinstance(location, URL) else catalog_url(location, "catalog")
        sqlite = self.url.get_backend_name() == "sqlite"
        self.path = Path(self.url.database) if sqlite else None
        """The SQLite file (None: PostgreSQL)."""
        self.name = str(self.path) if sqlite else self.url.render_as_string(hide_password=True)
        """Where the catalog is, as messages name it (never with a password)."""
        self.directory = Path(directory if directory is not None else
                              self.path.parent if self.path else "runs")
        self.bench = bench or os.environ.get(BENCH_ENV) or socket.gethostname()
        self._engine = _engine(self.url)
        existed, self._made_table = False, False
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            existed = self.path.exists()
        if self._problems():
            with _file_lock(self.path):  # one process replaces it, the others wait
                if problems := self._problems(locked=True):  # and then find the new one sound
                    self._replace_corrupt("; ".join(problems[:3]))
        elif existed and self._made_table and rebuild_empty and any(
                self.directory.glob("*.h5")):
            self._rebuild_empty()

    def _problems(self, locked: bool = False) -> list[str]:
        """`_create`, and what makes the file a corrupt SQLite catalog (nothing: an empty
        list); `locked`: this process holds the file's lock (`_file_lock`)."""
        try:
            return self._create(locked)
        except CatalogError as exc:
            if getattr(exc.__cause__, "sqlite_errorcode", None) not in SQLITE_CORRUPT:
                raise
            return [str(exc.__cause__)]

    def _create(self, locked: bool) -> list[str]:
        """Make the tables, or bring an old catalog to the current schema version (under the
        write lock, so that processes opening it at once upgrade it once); returns what
        SQLite's integrity check finds wrong (nothing: an empty list). An SQLite file not in
        WAL mode yet is switched under its file lock: two processes switching a new file at
        once find it locked, busy timeout or not."""
        if self.path is not None and _not_in_wal_mode(self.path):
            with (nullcontext() if locked else _file_lock(self.path),
                  self._transaction(begin="") as connection):  # not within a transaction
                connection.exec_driver_sql("PRAGMA journal_mode=WAL")
        with self._transaction(lock=True) as connection:
            self._made_table = _upgrade(connection, self.name)
            if self.path is None:
                return []
            return [row[0] for row in connection.exec_driver_sql("PRAGMA quick_check")
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
        added, skipped = Catalog(fresh, directory=self.directory, bench=self.bench,
                                 rebuild_empty=False).rebuild()
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

        `n` counts the ids reserved in the same second (by every bench of the catalog); the
        row is created with status `created` under the write lock, so two calls never
        return the same id.
        """
        stamp = datetime.now(timezone.utc).strftime("%Y%m%d-%H%M%S")
        name = re.sub(r"[^A-Za-z0-9_]+", "_", experiment)
        with self._transaction(lock=True) as connection:
            taken = connection.execute(
                text("SELECT COUNT(*) FROM runs WHERE substr(id, 1, :n) = :prefix"),
                {"n": len(stamp) + 1, "prefix": stamp + "-"},
            ).scalar_one()
            run_id = f"{stamp}-{name}-{taken + 1}"
            connection.execute(
                text("INSERT INTO runs (id, experiment, status, pid, host, bench)"
                     " VALUES (:id, :experiment, 'created', :pid, :host, :bench)"),
                {"id": run_id, "experiment": experiment, **self._recorder()},
            )
        return run_id

    def add(self, run_id: str, experiment: str, file: str | Path,
            params: Mapping[str, Any], started_at: str | None = None) -> None:
        """Register the start of run `run_id` (status `running`, started now or at
        `started_at`: an imported recording's own start, recorded by this process on this
        host for this bench)."""
        with self._transaction() as connection:
            connection.execute(
                text("INSERT INTO runs (id, experiment, started_at, status, file, params, pid,"
                     " host, bench) VALUES (:id, :experiment, :started_at, 'running', :file,"
                     " :params, :pid, :host, :bench)"
                     " ON CONFLICT(id) DO UPDATE SET experiment = excluded.experiment,"
                     " started_at = excluded.started_at, status = excluded.status,"
                     " file = excluded.file, params = excluded.params, pid = excluded.pid,"
                     " host = excluded.host, bench = excluded.bench"),
                {"id": run_id, "experiment": experiment,
                 "started_at": started_at or utc_now_iso(),
                 "file": self._stored(file), "params": to_json(dict(params)),
                 **self._recorder()},
            )

    def _recorder(self) -> dict[str, Any]:
        """The pid, host and bench columns of a run this process records."""
        return {"pid": os.getpid(), **self.recorder_names()}

    def recorder_names(self) -> dict[str, str]:
        """The bench and host of a run this process records, as its catalog row and its
        recording keep them (`rebuild` and `sync` read them back from the file)."""
        return {"bench": self.bench, "host": socket.gethostname()}

    def finish(self, run_id: str, status: str, reason: str, n_samples: int,
               timing: Mapping[str, Any] | None = None, stopped_at: str | None = None) -> None:
        """Record the end of run `run_id` (now, or `stopped_at`: an imported recording's own
        end): status (complete / aborted), reason, sample count, a real-time run's cycle
        timing. A catalog gone since the run started (a server
        stopped) raises `CatalogError` saying that the run is kept in its recording and
        `feedbench catalog sync` registers it once the catalog is back."""
        try:
            with self._transaction() as connection:
                updated = connection.execute(
                    text("UPDATE runs SET stopped_at = :stopped_at, status = :status,"
                         " reason = :reason, n_samples = :n_samples, timing = :timing"
                         " WHERE id = :id"),
                    {"stopped_at": stopped_at or utc_now_iso(), "status": status,
                     "reason": reason, "n_samples": int(n_samples),
                     "timing": _timing_json(timing),
                     "id": run_id},
                ).rowcount
        except CatalogError as exc:
            raise CatalogError(f"run {run_id} {status}, kept in its recording but not in the "
                               f"catalog ({exc}); feedbench catalog sync registers it once "
                               "the catalog is back") from exc.__cause__
        if not updated:
            raise RunLookupError(f"no run with id {run_id!r} in {self.name}")

    def record_copy(self, run_id: str, copy: Any) -> None:
        """Record where run `run_id`'s recording is in the lab's store (a `daq.store.Copy`:
        location, ``copied`` or ``pending`` and why, sha256)."""
        with self._transaction() as connection:
            connection.execute(
                text("UPDATE runs SET store = :store, store_status = :status,"
                     " store_reason = :reason, sha256 = :sha256 WHERE id = :id"),
                {"store": copy.url, "status": copy.status, "reason": copy.reason,
                 "sha256": copy.sha256, "id": run_id})

    def list(self, limit: int | None = None, where: RunFilter | None = None) -> list[RunRow]:
        """Runs newest first (in the order their ids were created), those `where` selects,
        at most `limit` (`listing`, every row built)."""
        with _collector_paused():
            return list(self.listing(limit, where))

    def listing(self, limit: int | None = None,
                where: RunFilter | None = None) -> Iterator[RunRow]:
        """The rows of `list`, each built (`_row`) as it is taken: the database is read
        first (a damaged row's parameters may make it refuse the statement part-way), a
        listing that prints its rows holds one at a time."""
        where = where or RunFilter()
        rows, _ = self._read(where, limit, COLUMN_NAMES)
        read = map(self._row, rows)
        if not where.where and where.status is None:  # SQL has decided alone
            return iter(read)
        return islice((row for row in read if where.matches(row.experiment, row.status,
                                                             row.params)), limit)

    def lines(self, limit: int | None = None,
              where: RunFilter | None = None) -> Iterator[ListedRun]:
        """What a line of `feedbench runs` shows of each run `listing` gives, in its order,
        read without what the line does not need: five columns and the two JSON ones, whose
        text is decoded only to tell a damaged row (`_row`) or to check a ``--where``
        condition SQL has left to Python. Where SQL has evaluated the conditions, every row
        it gives has parameters it parsed as a JSON object, so those are decoded only if a
        condition's value is no number or the parameters hold an array or a table (what the
        SQL lets through: `Condition.clause`); a timing only if there is one."""
        where = where or RunFilter()
        rows, in_sql = self._read(where, limit, LINE_COLUMNS)
        parsed = in_sql and bool(where.where)  # every row's parameters a JSON object
        decided = parsed and all(condition.decided_in_sql for condition in where.where)
        resolved = self._resolved
        taken = 0
        for run_id, experiment, status, reason, file, n_samples, params, timing in rows:
            decode = not (decided and _flat(params))  # else SQL has decided the conditions
            value, problem = _json_column("params", params, {}) if decode else ({}, "")
            problems = [found for found in (
                problem, timing and _json_column("timing", timing, None)[1]) if found]
            if problems:
                status, reason = DAMAGED, _damaged(problems)
            if where.status is not None and status != where.status:
                continue
            if decode and not all(condition.matches(experiment, value)
                                  for condition in where.where):
                continue
            yield ListedRun(run_id, status, n_samples, resolved(file), reason)
            taken += 1
            if taken == limit:
                return

    def _read(self, where: RunFilter, limit: int | None,
              columns: tuple[str, ...]) -> tuple[list[tuple[Any, ...]], bool]:
        """The `columns` of the rows `_select` gives, and whether its SQL evaluated the
        ``--where`` conditions (not where a damaged row's parameters make the database
        refuse them)."""
        try:
            return self._select(where, limit, columns=columns), True
        except CatalogError as exc:  # a damaged row's parameters are not JSON
            cause = exc.__cause__
            if (getattr(cause, "sqlstate", None) != INVALID_TEXT
                    and "malformed JSON" not in str(cause)):
                raise
            return self._select(where, limit, in_sql=False, columns=columns), False

    def _select(self, where: RunFilter, limit: int | None, in_sql: bool = True,
                columns: tuple[str, ...] = COLUMN_NAMES) -> list[tuple[Any, ...]]:
        """The `columns` of the rows `where`'s SQL selects (`RunFilter.clauses`; `in_sql`
        False: its `--where` conditions left to `RunFilter.matches`), newest first, at most
        `limit` when SQL decides alone."""
        query = select(*(RUNS.c[name] for name in columns))
        document = None
        if where.where and in_sql and self.path is None:  # PostgreSQL: parsed once a row
            document = parsed_parameters(RUNS)
        query = query.where(*where.clauses(RUNS, document, in_sql)).order_by(RUNS.c.seq.desc())
        if limit is not None and where.status is None and not where.where:
            query = query.limit(limit)
        with self._transaction() as connection, _collector_paused():
            return connection.execute(query).cursor.fetchall()  # tuples: no Row objects

    def get(self, run_id_or_prefix: str) -> RunRow:
        """The run with this exact id, else the only run whose id starts with it."""
        with self._transaction() as connection:
            rows = connection.execute(
                text(f"SELECT {COLUMNS} FROM runs WHERE id = :id"), {"id": run_id_or_prefix}
            ).fetchall() or connection.execute(
                text(f"SELECT {COLUMNS} FROM runs WHERE substr(id, 1, :n) = :prefix"
                     " ORDER BY id"),
                {"n": len(run_id_or_prefix), "prefix": run_id_or_prefix},
            ).fetchall()
        if not rows:
            raise RunLookupError(f"no run id starts with {run_id_or_prefix!r} in {self.name}")
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
                text("SELECT id, file, pid, host FROM runs WHERE status IN (:a, :b)"),
                dict(zip("ab", UNFINISHED)),
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
        """Recreate the rows of the recordings (``*.h5``) in `directory`: one row per
        recording (its key parameters: the recorded `[experiment]` table; this catalog's
        bench); a file still `running` keeps that status if a process on this host has it
        open for writing (its pid), else it is `crashed`. The rows replaced are the
        directory's (`_in_directory`): other directories' and other benches' rows of a shared
        catalog stay, and so does a row whose recording is only in the lab's store (`daq.store`;
        a rebuilt row keeps where its copy is). The row of a run in progress is kept until its
        file says how it ended. Rows are in the order the runs started. Returns the number of
        recordings read and one line per file skipped (not a feedbench recording)."""
        rows, skipped = {}, []
        for path in sorted(self.directory.glob("*.h5")):
            summary, why = _summary(str(path))
            if summary is None:
                skipped.append(why)
            else:
                rows[summary.run_id] = _rebuilt_row(summary, self._stored(path), self.bench)
        added = len(rows)
        with self._transaction(lock=True) as connection:
            replaced = []
            for row in connection.execute(text(f"SELECT {COLUMNS} FROM runs")).fetchall():
                live = dict(zip(COLUMN_NAMES, row))
                if not self._in_directory(live) and live["id"] not in rows:
                    continue
                if live["id"] not in rows and live["store_status"] == "copied":
                    continue  # its recording is in the lab's store only (daq.store): kept
                replaced.append(live["id"])
                in_file = dict(zip(COLUMN_NAMES, rows.get(live["id"], row)))
                if (live["status"] in UNFINISHED and in_file["status"] in UNFINISHED
                        and not _ended(live["pid"], live["host"], self._resolved(live["file"]))):
                    rows[live["id"]] = tuple(row)
                elif live["id"] in rows and live["store"] is not None:  # the copy stays known
                    in_file.update({name: live[name] for name in STORE_COLUMNS})
                    rows[live["id"]] = tuple(in_file[name] for name in COLUMN_NAMES)
            _delete(connection, replaced)
            _insert(connection, list(rows.values()))
        return added, skipped

    def sync(self) -> tuple[list[str], list[str]]:
        """Register what the recordings in `directory` say and the catalog does not know (runs
        recorded while it was unreachable): a recording without a row gets one (as `rebuild`
        makes it), a row left unfinished takes its file's final status. Nothing else changes.
        Returns the ids registered and the ids settled."""
        found = {}
        for path in sorted(self.directory.glob("*.h5")):
            summary, _ = _summary(str(path))
            if summary is not None:
                found[summary.run_id] = summary
        with self._transaction(lock=True) as connection:
            known = dict(connection.execute(text("SELECT id, status FROM runs")).fetchall())
            added = [_rebuilt_row(summary, self._stored(summary.path), self.bench)
                     for run_id, summary in found.items() if run_id not in known]
            _insert(connection, added)
        settled = [run_id for run_id, summary in found.items()
                   if known.get(run_id) in UNFINISHED and summary.status not in UNFINISHED]
        for run_id in settled:
            summary = found[run_id]
            self._settle(run_id, summary.status, summary.reason, summary.n_samples,
                         summary.stopped_at, summary.timing)
        return [row[0] for row in added], settled

    def _in_directory(self, row: Mapping[str, Any]) -> bool:
        """Whether a row is one of `directory`'s runs: its recording is there, or it has
        none and was made on this host (or before hosts were recorded)."""
        if row["file"] is None:
            return row["host"] in (None, socket.gethostname())
        file = Path(os.path.abspath(self._resolved(row["file"])))
        return file.parent == Path(os.path.abspath(self.directory))

    def _stored(self, file: str | Path) -> str:
        """A recording's path as the catalog stores it: relative to an SQLite catalog's
        directory, else absolute."""
        if self.path is None:
            return os.path.abspath(file)
        return os.path.relpath(Path(file).absolute(), self.path.parent.absolute())

    def _resolved(self, stored: str | None) -> str | None:
        """A stored recording path as a path from the current directory: relative to an
        SQLite catalog's directory (or absolute); an old catalog's path relative to the
        directory its run was started from if it names a file from here, else the file of
        that name beside the catalog."""
        if stored is None or self.path is None:
            return stored
        if os.sep not in stored:  # a name: beside the catalog (os.path.join's, 1/5 the time)
            return self._beside + stored
        parent = self._parent
        beside = os.path.join(parent, stored)
        if os.sep not in stored or os.path.exists(beside):  # a name: as stored since then
            return beside
        for old in (stored, os.path.join(parent, os.path.basename(stored))):
            if os.path.exists(old):
                return old
        return beside

    @cached_property
    def _parent(self) -> str:
        """An SQLite catalog's directory as a path from the current directory ('': here)."""
        return "" if self.path.parent == Path(".") else str(self.path.parent)

    @cached_property
    def _beside(self) -> str:
        """What leads a file name beside an SQLite catalog (`_parent` and a separator)."""
        return os.path.join(self._parent, "")

    def _row(self, row: tuple[Any, ...]) -> RunRow:
        """A catalog row as a `RunRow`, its file resolved (`_resolved`); a row whose JSON
        columns cannot be read is `damaged`, the reason names the column and why."""
        values = dict(zip(COLUMN_NAMES, row))
        values["file"] = self._resolved(values["file"])
        problems = []
        for name, empty in JSON_COLUMNS.items():
            if values[name]:
                values[name], problem = _json_column(name, values[name], empty)
                if problem:
                    problems.append(problem)
            else:
                values[name] = empty
        if problems:
            values.update(status=DAMAGED, reason=_damaged(problems))
        listed = object.__new__(RunRow)  # every field: a frozen __init__ costs 4 µs a row
        object.__setattr__(listed, "__dict__", values)
        return listed

    def _settle(self, run_id: str, status: str, reason: str, n_samples: int,
                stopped_at: str | None, timing: Mapping[str, Any] | None = None) -> None:
        with self._transaction() as connection:
            connection.execute(
                text("UPDATE runs SET stopped_at = :stopped_at, status = :status,"
                     " reason = :reason, n_samples = :n_samples, timing = :timing"
                     " WHERE id = :id AND status IN (:a, :b)"),
                {"stopped_at": stopped_at or None, "status": status, "reason": reason,
                 "n_samples": n_samples, "timing": _timing_json(timing), "id": run_id,
                 **dict(zip("ab", UNFINISHED))},
            )

    @contextmanager
    def _transaction(self, lock: bool = False, begin: str = "BEGIN") -> Iterator[Connection]:
        """One connection, one transaction: committed on success, rolled back on error;
        `lock`: under the catalog's write lock (SQLite: ``BEGIN IMMEDIATE``, PostgreSQL: an
        advisory lock); SQLite's `begin` '': no transaction (a PRAGMA that needs none). A
        database error (read-only or full disk, not a database, no server) raises
        `CatalogError`, one line."""
        try:
            with self._engine.connect() as connection:
                connection.execution_options(sqlite_begin="BEGIN IMMEDIATE" if lock else begin)
                with connection.begin():
                    if lock and self.path is None:
                        connection.execute(select(func.pg_advisory_xact_lock(LOCK_KEY)))
                    yield connection
        except DBAPIError as exc:
            problem = " ".join(str(exc.orig).split())
            raise CatalogError(f"{self.name}: cannot use the run catalog ({problem})"
                               ) from exc.orig


@contextmanager
def _collector_paused() -> Iterator[None]:
    """Python's cyclic garbage collector off while a listing builds its rows (tens of
    thousands of tuples, dicts and RunRows, none in a cycle, each allocation counting
    towards a collection that walks every object of the process: 100 000 runs listed took a
    third longer with it on); on again after, as it was."""
    was_on = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_on:
            gc.enable()


def _not_in_wal_mode(path: Path) -> bool:
    """Whether `path` is no SQLite file in WAL mode yet (missing, empty, in rollback mode, not
    SQLite: its header's bytes 18-19 are not 2, sqlite.org/fileformat.html); a directory is
    no catalog and is left to fail when opened."""
    if path.is_dir():
        return False
    try:
        with open(path, "rb") as file:
            return file.read(20)[18:20] != b"\x02\x02"
    except FileNotFoundError:
        return True


@contextmanager
def _file_lock(path: Path) -> Iterator[None]:
    """The exclusive lock of an SQLite catalog's file (``<file>.lock``), across processes."""
    with open(f"{path}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


def _engine(url: URL) -> Engine:
    """An engine that connects anew for each transaction (no pool: a replaced SQLite file or
    a restarted server is found by the next call); SQLite begins its transactions itself
    (`_sqlite_begin`)."""
    if url.get_backend_name() == "sqlite":
        engine = create_engine(url.set(drivername="sqlite+pysqlite"), poolclass=NullPool,
                               connect_args={"timeout": BUSY_TIMEOUT_S})
        event.listen(engine, "connect", _sqlite_connected)
        event.listen(engine, "begin", _sqlite_begin)
        return engine
    return create_engine(url.set(drivername="postgresql+psycopg"), poolclass=NullPool,
                         connect_args={"connect_timeout": CONNECT_TIMEOUT_S})


def _sqlite_connected(dbapi_connection: sqlite3.Connection, _record: object) -> None:
    """Leave transactions to `_sqlite_begin` (pysqlite's own BEGIN is deferred and late)."""
    dbapi_connection.isolation_level = None


def _sqlite_begin(connection: Connection) -> None:
    """Begin as the transaction asks (``sqlite_begin``: BEGIN, BEGIN IMMEDIATE or none)."""
    if begin := connection.get_execution_options().get("sqlite_begin", "BEGIN"):
        connection.exec_driver_sql(begin)


def _delete(connection: Connection, ids: list[str]) -> None:
    """Delete the rows of `ids`, a batch at a time."""
    statement = text("DELETE FROM runs WHERE id IN :ids").bindparams(
        bindparam("ids", expanding=True))
    for start in range(0, len(ids), DELETE_BATCH):
        connection.execute(statement, {"ids": ids[start:start + DELETE_BATCH]})


def _insert(connection: Connection, rows: list[tuple[Any, ...]]) -> None:
    """Insert whole rows (`COLUMN_NAMES` order) in the order their runs started (a run not
    started yet last)."""
    started = COLUMN_NAMES.index("started_at")
    if rows:
        connection.execute(text(f"INSERT INTO runs ({COLUMNS}) VALUES "
                                f"({', '.join(':' + name for name in COLUMN_NAMES)})"),
                           [dict(zip(COLUMN_NAMES, row))
                            for row in sorted(rows, key=lambda row: row[started] or "~")])


def _upgrade(connection: Connection, name: str) -> bool:
    """Bring the catalog to `SCHEMA_VERSION`: make its tables if it has none (returns True),
    else run the migrations after its version (none recorded: 0, a catalog made before
    versions). A catalog made by a newer feedbench raises `CatalogError`."""
    tables = set(inspect(connection).get_table_names())
    if "runs" not in tables:
        METADATA.create_all(connection)
        _version_3(connection)  # what the table definition does not hold
        connection.execute(SCHEMA.insert().values(version=SCHEMA_VERSION))
        return True
    if "catalog_schema" not in tables:
        SCHEMA.create(connection)
        connection.execute(SCHEMA.insert().values(version=0))
    version = connection.execute(select(SCHEMA.c.version)).scalar_one()
    if version > SCHEMA_VERSION:
        raise CatalogError(f"{name}: run catalog of schema version {version}, made by a newer "
                           f"feedbench (this one reads up to {SCHEMA_VERSION}): upgrade it")
    for number in range(version + 1, SCHEMA_VERSION + 1):
        MIGRATIONS[number](connection)
        connection.execute(SCHEMA.update().values(version=number))
        LOGGER.info("%s: run catalog upgraded to schema version %d", name, number)
    return False


def _version_1(connection: Connection) -> None:
    """From a catalog made before schema versions (an SQLite file: `id` its primary key, its
    rowid the order of listing, `pid`, `host` and `timing` possibly missing): the table made
    anew with `seq` (from the rowid) and `bench`, every row copied."""
    present = {column["name"] for column in inspect(connection).get_columns("runs")}
    kept = ", ".join(name for name in COLUMN_NAMES if name in present)
    connection.execute(text("ALTER TABLE runs RENAME TO runs_unversioned"))
    RUNS.create(connection)
    connection.execute(text(f"INSERT INTO runs (seq, {kept}) SELECT rowid, {kept}"
                            " FROM runs_unversioned ORDER BY rowid"))
    connection.execute(text("DROP TABLE runs_unversioned"))


def _version_2(connection: Connection) -> None:
    """The columns of a recording's copy in the lab's store (`STORE_COLUMNS`, empty for the
    runs before; a table made anew by `_version_1` has them already)."""
    present = {column["name"] for column in inspect(connection).get_columns("runs")}
    for name in STORE_COLUMNS:
        if name not in present:
            connection.execute(text(f"ALTER TABLE runs ADD COLUMN {name} TEXT"))


PARAMETERS_FUNCTION = """
CREATE OR REPLACE FUNCTION feedbench_parameters(params text) RETURNS jsonb
LANGUAGE plpgsql IMMUTABLE PARALLEL SAFE AS $$
DECLARE
    document jsonb;
BEGIN
    document := params::jsonb;
    RETURN CASE WHEN jsonb_typeof(document) = 'object' THEN document END;
EXCEPTION WHEN others THEN
    RETURN NULL;
END $$"""
"""PostgreSQL: a run's parameters (JSON text) as jsonb, NULL where they are no JSON object
(a damaged row: never raises, so a row is always written)."""


def _version_3(connection: Connection) -> None:
    """PostgreSQL: the runs' parameters parsed once, when a row is written (the generated
    column ``document``, jsonb: `feedbench_parameters`), for ``--where`` in SQL
    (`run_filter.parsed_parameters`): parsing them in each listing took three quarters of
    the time of ``--where`` over 100 000 runs. SQLite parses them as fast as it reads them
    (json_tree): nothing."""
    if connection.dialect.name != "postgresql":
        return
    connection.exec_driver_sql(PARAMETERS_FUNCTION)
    connection.exec_driver_sql("ALTER TABLE runs ADD COLUMN IF NOT EXISTS document jsonb"
                               " GENERATED ALWAYS AS (feedbench_parameters(params)) STORED")


MIGRATIONS: dict[int, Callable[[Connection], None]] = {1: _version_1, 2: _version_2,
                                                       3: _version_3}
"""Schema version → the migration that brings the version before it there (one transaction
with the version's update). Versions before 1 exist only in SQLite files."""
SCHEMA_VERSION = max(MIGRATIONS)



_DECODE = json.JSONDecoder().decode
"""`json.loads` of a str without its checks (a listing decodes 100 000 rows)."""


def _json_column(name: str, text: str | None, empty: Any) -> tuple[Any, str]:
    """The value of JSON column `name` (`empty` for none) and '' or why it cannot be read
    (not JSON, or not a JSON object)."""
    if not text:
        return empty, ""
    try:
        value = _DECODE(text)
    except (TypeError, ValueError) as exc:
        return empty, f"{name} is not JSON ({exc})"
    if not isinstance(value, dict):
        return empty, f"{name} is not a JSON object (got {type(value).__name__})"
    return value, ""


def _damaged(problems: list[str]) -> str:
    """The reason of a damaged row, from what is wrong with its JSON columns."""
    return (f"catalog row damaged: {'; '.join(problems)} (feedbench catalog rebuild recreates "
            "it from its file)")


def _flat(params: str) -> bool:
    """Whether a run's parameters (JSON object text) can hold no array and no table: no
    ``[`` and one ``{`` anywhere (in a string too: then read as if it held one)."""
    return "[" not in params and params.count("{") == 1


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


def _rebuilt_row(summary: RecordingSummary, file: str, bench: str) -> tuple[Any, ...]:
    """The catalog row of a recording found on disk as `file` by `bench` (see
    `Catalog.rebuild`): the bench and host that recorded it as the file says (a file
    written before it said: `bench`, no host)."""
    status, pid, host = summary.status, None, summary.host
    if status in UNFINISHED:
        pid = _writing_process(summary.path)
        status, host = ("running", socket.gethostname()) if pid else ("crashed", host)
    reason = summary.reason or ("no process writes it any more" if status == "crashed" else "")
    return (summary.run_id, summary.experiment, summary.started_at, summary.stopped_at or None,
            status, reason, file, summary.n_samples,
            to_json(summary.config.get("experiment", {})), pid, host,
            _timing_json(summary.timing), summary.bench or bench, None, None, None, None)


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

