"""A throw-away PostgreSQL server for the catalog's tests: Debian's `postgresql` package
(`initdb` + `pg_ctl`), a data directory in a temporary directory, 127.0.0.1 on a free port,
password authentication (scram-sha-256) for one user; started and stopped by the tests.

PostgreSQL refuses to run as root: as root (CI) the server runs as `nobody` (`runuser`)."""

from __future__ import annotations

import glob
import os
import secrets
import shutil
import socket
import subprocess
import tempfile
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import psycopg
import pytest

USER = "feedbench"
DATABASE = "postgres"


def _binaries() -> Path | None:
    """The directory of Debian's PostgreSQL server programs (the newest), or of `initdb`
    on the PATH; None without them."""
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/pg_ctl"),
                   key=lambda path: int(Path(path).parts[-3]))
    if found:
        return Path(found[-1]).parent
    initdb = shutil.which("initdb")
    return Path(initdb).resolve().parent if initdb else None


BINARIES = _binaries()
"""Where `initdb` and `pg_ctl` are (None: not installed; `.ci/run` installs `postgresql`)."""


def free_port() -> int:
    """A TCP port nobody listens on at 127.0.0.1 (now)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@dataclass
class PostgresServer:
    """A running throw-away server: `url` (no password in it), the `password` of its user
    (for `PGPASSWORD`), its data `directory`."""

    directory: Path
    port: int
    password: str

    @property
    def url(self) -> str:
        return f"postgresql://{USER}@127.0.0.1:{self.port}/{DATABASE}"

    def pg_ctl(self, *args: str) -> None:
        """Run `pg_ctl` on the server's data directory (as its owner)."""
        _as_owner([str(BINARIES / "pg_ctl"), "-D", str(self.directory / "data"), "-w",
                   "-l", str(self.directory / "server.log"), *args])

    def start(self) -> None:
        self.pg_ctl("-o", f"-p {self.port} -c listen_addresses=127.0.0.1 "
                    f"-k {self.directory} -c fsync=off -c max_connections=60", "start")

    def stop(self) -> None:
        self.pg_ctl("-m", "immediate", "stop")


def _as_owner(command: list[str]) -> None:
    """Run `command`, as `nobody` when this process is root (PostgreSQL refuses root)."""
    prefix = ["runuser", "-u", "nobody", "--"] if os.geteuid() == 0 else []
    subprocess.run(prefix + command, check=True, capture_output=True, timeout=60)


def start_server() -> PostgresServer:
    """Make a data directory with user `USER` (a random password) and start the server."""
    directory = Path(tempfile.mkdtemp(prefix="feedbench-pg-"))
    password = "pw-" + secrets.token_hex(12)
    (directory / "password").write_text(password + "\n")
    if os.geteuid() == 0:
        shutil.chown(directory, "nobody")
        shutil.chown(directory / "password", "nobody")
    _as_owner([str(BINARIES / "initdb"), "-D", str(directory / "data"), "-U", USER,
               "--pwfile", str(directory / "password"), "--auth", "scram-sha-256",
               "-E", "UTF8", "--no-locale", "--no-sync"])
    (directory / "password").unlink()
    server = PostgresServer(directory, free_port(), password)
    server.start()
    return server


def remove_server(server: PostgresServer) -> None:
    """Stop the server and delete its data directory."""
    try:
        server.stop()
    finally:
        shutil.rmtree(server.directory, ignore_errors=True)


def running_server() -> Iterator[PostgresServer]:
    """A server started, then stopped and removed."""
    started = start_server()
    try:
        yield started
    finally:
        remove_server(started)


@pytest.fixture(scope="module")
def server() -> Iterator[PostgresServer]:
    """One throw-away server for a test module (each test makes its own database)."""
    yield from running_server()


@pytest.fixture
def own_server() -> Iterator[PostgresServer]:
    """A server of the test's own (to stop and start again)."""
    yield from running_server()


@pytest.fixture
def postgres_url(server: PostgresServer, monkeypatch: pytest.MonkeyPatch) -> str:
    """A new, empty database on the server; its password only in `PGPASSWORD`."""
    return new_database(server, monkeypatch)


def new_database(server: PostgresServer, monkeypatch: pytest.MonkeyPatch) -> str:
    """The URL of a new, empty database on `server`, its password set in `PGPASSWORD` for
    as long as `monkeypatch` holds."""
    monkeypatch.setenv("PGPASSWORD", server.password)
    name = f"catalog_{uuid.uuid4().hex[:12]}"
    with psycopg.connect(server.url, autocommit=True) as connection:
        connection.execute(f"CREATE DATABASE {name}")
    return server.url.rsplit("/", 1)[0] + "/" + name
