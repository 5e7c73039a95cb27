"""SQLite run catalog: one row per run (id, experiment, times, status, file, key parameters).

Every call opens its own connection and runs one short transaction, so one writer (the
runner) and any number of readers (CLI, analysis, live window) can share the file; the
database is in WAL mode so readers never block the writer.
"""

from __future__ import annotations

import json
import re
import sqlite3
from collections.abc import Iterator, Mapping
from contextlib import closing, contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from feedbench.config import ConfigError
from feedbench.daq.recording import to_json, utc_now_iso

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
    params JSON NOT NULL DEFAULT '{}'
)
"""
COLUMNS = "id, experiment, started_at, stopped_at, status, reason, file, n_samples, params"
BUSY_TIMEOUT_S = 10.0


class RunLookupError(ConfigError, KeyError):
    """No run, or more than one run, matches the given id or prefix (a user error: the CLI
    prints it as one line)."""

    def __str__(self) -> str:
        return str(self.args[0])


@dataclass(frozen=True)
class RunRow:
    """One catalog row; times are ISO 8601 UTC text, `params` the run's key parameters."""

    id: str
    experiment: str
    started_at: str | None
    stopped_at: str | None
    status: str
    reason: str
    file: str | None
    n_samples: int | None
    params: dict[str, Any]


class Catalog:
    """The run catalog stored in the SQLite file `path` (created if missing)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self._transaction() as connection:
            connection.execute("PRAGMA journal_mode=WAL")
            connection.execute(SCHEMA)

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
                "INSERT INTO runs (id, experiment, status) VALUES (?, ?, 'created')",
                (run_id, experiment),
            )
        return run_id

    def add(self, run_id: str, experiment: str, file: str | Path, params: Mapping[str, Any]) -> None:
        """Register the start of run `run_id` (status `running`, started now)."""
        with self._transaction() as connection:
            connection.execute(
                "INSERT INTO runs (id, experiment, started_at, status, file, params)"
                " VALUES (?, ?, ?, 'running', ?, ?)"
                " ON CONFLICT(id) DO UPDATE SET experiment = excluded.experiment,"
                " started_at = excluded.started_at, status = excluded.status,"
                " file = excluded.file, params = excluded.params",
                (run_id, experiment, utc_now_iso(), str(file), to_json(dict(params))),
            )

    def finish(self, run_id: str, status: str, reason: str, n_samples: int) -> None:
        """Record the end of run `run_id`: status (complete / aborted), reason, sample count."""
        with self._transaction() as connection:
            updated = connection.execute(
                "UPDATE runs SET stopped_at = ?, status = ?, reason = ?, n_samples = ?"
                " WHERE id = ?",
                (utc_now_iso(), status, reason, int(n_samples), run_id),
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
        return [_run_row(row) for row in rows]

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
        return _run_row(rows[0])

    @contextmanager
    def _transaction(self, immediate: bool = False) -> Iterator[sqlite3.Connection]:
        """One connection, one transaction: committed on success, rolled back on error."""
        with closing(sqlite3.connect(self.path, timeout=BUSY_TIMEOUT_S)) as connection:
            if immediate:
                connection.execute("BEGIN IMMEDIATE")
            with connection:
                yield connection


def _run_row(row: tuple[Any, ...]) -> RunRow:
    *fields, params = row
    return RunRow(*fields, params=json.loads(params))

