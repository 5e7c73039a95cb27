"""The lab's recording store: where each recording is copied once its run has ended, so that
every bench's recordings are found in one place (a NAS mount, or any fsspec URL).

A run records to the local disk (the cycle loop never waits on the network); after the run
`copy_recording` copies the closed file to ``<store>/<bench>/<file name>``, reads the copy
back and compares its sha256 with the local file's, and the catalog records both places
(`Catalog.record_copy`: the store copy's location, ``copied`` or ``pending`` and why, the
sha256). A copy that fails (the store unreachable or read-only, a checksum that differs)
keeps the local file and says so in one line; `sync_copies` (``feedbench catalog sync``)
retries the copies still pending. `recording_file` gives the file to read: the local one,
else the store's copy (a directory or ``file://`` store read in place, any other store's
copy fetched once into the cache, ``$XDG_CACHE_HOME/feedbench/store``, its checksum checked).

fsspec rather than shutil alone: one interface over a mounted directory, ``file://``,
``memory://`` and whatever the lab's fsspec installs (``sftp://``, ``s3://``, ``smb://``…),
without feedbench knowing any of them; a directory path is fsspec's local file system too.
"""

from __future__ import annotations

import hashlib
import os
import socket
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from feedbench.config import ConfigError

if TYPE_CHECKING:
    from feedbench.daq.catalog import Catalog, RunRow

COPIED = "copied"
PENDING = "pending"
CHUNK_BYTES = 1 << 20
"""Bytes read at a time to compute a checksum."""
CACHE_ENV = "XDG_CACHE_HOME"


class StoreError(ConfigError):
    """The recording could not be copied to the store, or its copy not read."""


def store_problem(text: str) -> str | None:
    """Check (a `config.Field`'s): why `text` is no recording store (a URL of a protocol
    fsspec does not know or cannot load, a URL with a password), or None. A directory path is
    one (whether it is reachable is found when a recording is copied)."""
    if "://" not in text:
        return None
    import fsspec
    from fsspec.core import split_protocol
    from fsspec.utils import infer_storage_options

    protocol = split_protocol(text)[0]
    try:
        fsspec.get_filesystem_class(protocol)
    except ValueError:
        return f": {protocol}:// is no file system fsspec knows (a directory or e.g. file://…)"
    except ImportError as exc:
        return f": {protocol}:// needs a package that is not installed ({exc})"
    if infer_storage_options(text).get("password"):
        return (": the URL holds a password; give it to the file system's own configuration "
                "instead (its environment variables or config file)")
    return None


@dataclass(frozen=True)
class Copy:
    """Where a recording's store copy is (`url`: a path or fsspec URL), `status` (`COPIED`,
    `PENDING`), why it is pending (`reason`) and the recording's `sha256`."""

    url: str
    status: str
    reason: str
    sha256: str

    def as_dict(self) -> dict[str, str]:
        return {"url": self.url, "status": self.status, "reason": self.reason,
                "sha256": self.sha256}


def sha256_of(file: Any) -> str:
    """The sha256 (hex) of an open binary file or a path, read a chunk at a time."""
    if isinstance(file, (str, Path)):
        with open(file, "rb") as opened:
            return sha256_of(opened)
    digest = hashlib.sha256()
    while chunk := file.read(CHUNK_BYTES):
        digest.update(chunk)
    return digest.hexdigest()


def copy_url(store: str, bench: str | None, name: str) -> str:
    """The location of recording `name` of `bench` in `store` (a directory: absolute)."""
    folder = bench or socket.gethostname()
    if "://" in store:
        return "/".join([store.rstrip("/"), folder, name])
    return os.path.join(os.path.abspath(store), folder, name)


def _filesystem(url: str) -> tuple[Any, str]:
    from fsspec.core import url_to_fs

    return url_to_fs(url)


def copy_file(local: str | Path, url: str, sha256: str | None = None) -> str:
    """Copy `local` to `url` (a path or fsspec URL) through a temporary name beside it, read
    the copy back and compare checksums, then give it its name; a copy already there with
    the same sha256 is kept. Returns the sha256; raises `StoreError` (one line: unreachable,
    not writable, checksum mismatch, another file of that name there)."""
    sha256 = sha256 or sha256_of(local)
    try:
        fs, path = _filesystem(url)
        if fs.exists(path):
            with fs.open(path, "rb") as there:
                if sha256_of(there) == sha256:
                    return sha256
            raise StoreError(f"{url}: another file of that name is in the store")
        parent = path.rsplit("/", 1)[0]
        fs.makedirs(parent, exist_ok=True)
        partial = f"{path}.partial-{socket.gethostname()}-{os.getpid()}"
        fs.put_file(str(local), partial)
        with fs.open(partial, "rb") as copied:
            found = sha256_of(copied)
        if found != sha256:
            fs.rm_file(partial)
            raise StoreError(f"{url}: checksum mismatch after the copy (sha256 {found[:12]}… "
                             f"in the store, {sha256[:12]}… here)")
        fs.mv(partial, path)
    except StoreError:
        raise
    except Exception as exc:  # the store's own errors: OSError, a remote's exceptions
        problem = " ".join(str(exc).split()) or type(exc).__name__
        raise StoreError(f"{url}: cannot copy to the store ({problem})") from exc
    return sha256


def copy_recording(run_id: str, local: str | Path, store: str, bench: str | None) -> Copy:
    """Copy the recording of run `run_id` (of `bench`) to `store`; a copy that fails keeps
    the local file, is `PENDING` with why, and is said in one line on stderr. The catalog
    records the result (`Catalog.record_copy`)."""
    url = copy_url(store, bench, Path(local).name)
    sha256 = sha256_of(local)
    try:
        copy_file(local, url, sha256)
    except StoreError as exc:
        print(f"feedbench: {run_id}: not copied to the store, kept in {local} ({exc}); "
              "feedbench catalog sync copies it", file=sys.stderr)
        return Copy(url, PENDING, str(exc), sha256)
    return Copy(url, COPIED, "", sha256)


def sync_copies(catalog: Catalog, store: str = "") -> tuple[list[str], list[str]]:
    """Retry the copies still pending of the recordings on this host, and with `store`
    (``--store``) copy there every finished recording of the catalog's directory that has no
    store copy yet (one recorded while the catalog was unreachable: already in the store, it
    is only recorded). Returns the ids copied and one line per copy that failed again."""
    from feedbench.daq.catalog import UNFINISHED

    directory = Path(os.path.abspath(catalog.directory))
    copied, failed = [], []
    for row in catalog.list():
        if row.file is None or row.status in UNFINISHED or not os.path.isfile(row.file):
            continue
        if row.store_status == PENDING and row.host in (None, socket.gethostname()):
            url = row.store
        elif (store and row.store_status is None
              and Path(os.path.abspath(row.file)).parent == directory):
            url = copy_url(store, row.bench, Path(row.file).name)
        else:
            continue
        sha256 = sha256_of(row.file)
        try:
            copy_file(row.file, url, sha256)
        except StoreError as exc:
            catalog.record_copy(row.id, Copy(url, PENDING, str(exc), sha256))
            failed.append(f"{row.id}: not copied ({exc})")
            continue
        catalog.record_copy(row.id, Copy(url, COPIED, "", sha256))
        copied.append(row.id)
    return copied, failed


def run_recording(run: str, directory: str | Path, location: str = "") -> str | None:
    """The recording to read of run id (or unique id prefix) `run` in the catalog of
    `directory` (`catalog.open_catalog`; `location`: ``--catalog``): `recording_file`."""
    from feedbench.daq.catalog import open_catalog

    return recording_file(open_catalog(directory, location).get(run))


def recording_file(row: RunRow) -> str | None:
    """The file to read run `row`'s recording from: the local one if it is there, else its
    store copy (a directory or ``file://`` store: read in place; any other: fetched into the
    cache once, `fetched`); a run without either: its local path (the reader says it is
    missing)."""
    if row.file is not None and os.path.exists(row.file):
        return row.file
    if row.store_status != COPIED or not row.store:
        return row.file
    return fetched(row.store, row.sha256)


def fetched(url: str, sha256: str | None) -> str:
    """A local path of store copy `url`: the path itself on a local file system, else a copy
    in the cache (``$XDG_CACHE_HOME/feedbench/store``, else ``~/.cache/…``) whose sha256 is
    checked against the catalog's; raises `StoreError` in one line."""
    from fsspec.implementations.local import LocalFileSystem

    try:
        fs, path = _filesystem(url)
        if isinstance(fs, LocalFileSystem):
            if not os.path.exists(path):
                raise StoreError(f"{url}: the store copy is missing too")
            return path
        cache = Path(os.environ.get(CACHE_ENV) or Path.home() / ".cache") / "feedbench" / "store"
        target = cache / f"{(sha256 or 'unknown')[:16]}-{path.rsplit('/', 1)[-1]}"
        if target.exists() and sha256 is not None:
            return str(target)
        cache.mkdir(parents=True, exist_ok=True)
        partial = target.with_name(f"{target.name}.partial-{os.getpid()}")
        fs.get_file(path, str(partial))
    except StoreError:
        raise
    except Exception as exc:
        problem = " ".join(str(exc).split()) or type(exc).__name__
        raise StoreError(f"{url}: cannot read the store copy ({problem})") from exc
    found = sha256_of(partial)
    if sha256 is not None and found != sha256:
        partial.unlink()
        raise StoreError(f"{url}: the store copy's sha256 ({found[:12]}…) is not the "
                         f"recording's ({sha256[:12]}…)")
    partial.replace(target)
    return str(target)

