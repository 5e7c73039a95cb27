"""Incremental HDF5 recorder: one row per bus cycle, written chunk by chunk.

The recorder holds at most `chunk_rows` rows in memory. When the buffer is full it extends
the datasets, writes the rows and flushes, so the file on disk always holds every completed
chunk. The file is in SWMR mode (single writer, multiple readers): a live plot can read it
while it is written, and a writer killed mid-run leaves a readable file with status
`running`. The layout is described in `feedbench.daq.recording`.

A full disk (or a file-size limit) is found before HDF5 writes: the recorder keeps
`RESERVE_BYTES` allocated ahead of what the file has used, so a write that cannot get its
space raises `RecordingError` while the file is still whole; it can then be closed and
marked `aborted` with the reason. The reserve still holds the block that found the failure
and what comes after it (the rows in memory, the safe stop's rows and events): they are
written while they fit, and what no longer fits is dropped without an error, so no sample
given before the failure is lost and the safe stop of the drive never waits on the file.

The final status is written in a second opening of the file, which needs its lock: feedbench's
readers take none (`recording`), but another program may hold one (h5py and HDFView lock by
default). The recorder then retries for up to `STATUS_LOCK_WAIT_S` and says so: a warning
line and the attribute `status_wait` (attempts, waited_s) in the file.
"""

from __future__ import annotations

import functools
import json
import logging
import os
import platform
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager, suppress
from importlib import metadata as importlib_metadata
from pathlib import Path
from types import TracebackType
from typing import Any, NamedTuple

import h5py
from h5py import h5s
import numpy as np

from feedbench.daq.recording import (
    CYCLE, DATA, EVENT_DTYPE, EVENTS, RESERVED_ATTRS, SEQUENCE, STREAMS, to_json, utc_now_iso,
)

VERSIONED_DISTRIBUTIONS = (
    "feedbench", "numpy", "scipy", "h5py", "canopen", "python-can", "pymodbus", "pyserial",
)
EVENTS_CHUNK_ROWS = 64
STREAM_CHUNK_ROWS = 10_000
"""Rows of a high-rate stream held in memory before they are written (1 s at 10 kHz), at
most (`stream_chunk_rows`)."""
RESERVE_BYTES = 1 << 20
"""Disk space (bytes) held allocated beyond what the file has used: HDF5's own writes
(chunks, metadata, the final flush and status) land in space already held."""
RESERVE_STEP_BYTES = 1 << 16
"""The reserve is topped up in steps of this many bytes (64 KiB)."""
CLOSE_BYTES = RESERVE_BYTES // 4
"""Of the reserve, what is kept for HDF5's own writes when the file is closed (metadata,
chunk indices) once it can no longer be topped up."""
STREAM_CHUNK_BYTES = RESERVE_BYTES // 8
"""A stream's chunk is at most this big: the block that finds a full disk still leaves most
of the reserve for the rows and events after it."""
WRITE_OVERHEAD_BYTES = 4096
"""Metadata HDF5 may add per write (chunk index, dataset extents), counted generously."""
STATUS_LOCK_WAIT_S = 10.0
"""How long (s) the opening that writes the final status is retried while another process
holds a lock on the file."""
STATUS_RETRY_FIRST_S = 0.01
"""The first pause (s) before that opening is tried again; each next pause doubles."""
STATUS_RETRY_MAX_S = 0.5
"""The longest pause (s) between two tries."""
LOGGER = logging.getLogger(__name__)


class RecordingError(RuntimeError):
    """The recording cannot be written (disk full, file-size limit): raised once, by the
    write that found it; the recorder goes on writing into its reserve while that holds."""


class _NoRoom(Exception):
    """A block that no longer fits in the reserve after the failure: dropped."""


class StreamSpec(NamedTuple):
    """A high-rate stream to record beside the per-cycle rows: channel names, units, rate (Hz)."""

    channels: tuple[str, ...]
    units: Mapping[str, str]
    rate_hz: float


def expected_size(n_cycles: int, cycle_s: float, channels: Sequence[str],
                  streams: Mapping[str, StreamSpec]) -> int:
    """Bytes of a recording of `n_cycles` bus cycles of `cycle_s` (s) with `channels` and
    the `streams`: 8 bytes per value, per row the cycle counter besides, per stream sample
    its bus cycle and counter besides; plus the disk space the recorder holds in reserve."""
    row_values = n_cycles * (len(channels) + 1)
    stream_values = sum(round(spec.rate_hz * n_cycles * cycle_s) * (len(spec.channels) + 2)
                        for spec in streams.values())
    return 8 * (row_values + stream_values) + 2 * RESERVE_BYTES


def software_versions() -> dict[str, str | None]:
    """Versions of Python, HDF5 and the libraries a recording depends on (None if missing):
    those this process runs, read once (reading the installed packages' metadata took
    9 ms per recording, measured)."""
    return dict(_read_versions())


@functools.cache
def _read_versions() -> dict[str, str | None]:
    versions: dict[str, str | None] = {
        "python": platform.python_version(),
        "hdf5": h5py.version.hdf5_version,
    }
    for name in VERSIONED_DISTRIBUTIONS:
        try:
            versions[name] = importlib_metadata.version(name)
        except importlib_metadata.PackageNotFoundError:
            versions[name] = None
    return versions


class Recorder:
    """Write one run to an HDF5 file incrementally; use as a context manager.

    `metadata` keys: `experiment` (name), `config` (experiment + bench config, stored as
    JSON), any other key is stored as its own JSON attribute. `streams` declares the
    high-rate streams (`append_stream`); SWMR files cannot grow new datasets later.
    """

    def __init__(
        self,
        path: str | Path,
        channels: Sequence[str],
        units: Mapping[str, str],
        metadata: Mapping[str, Any],
        chunk_rows: int = 1000,
        streams: Mapping[str, StreamSpec] | None = None,
    ) -> None:
        if chunk_rows < 1:
            raise ValueError(f"chunk_rows must be >= 1, got {chunk_rows}")
        _check_metadata_keys(metadata)
        self.path = Path(path)
        self.channels = tuple(channels)
        self.gaps = 0
        self._chunk_rows = chunk_rows
        self._cycles = np.empty(chunk_rows, dtype=np.int64)
        self._values = np.empty((chunk_rows, len(self.channels)), dtype=np.float64, order="F")
        self._buffered = 0
        self._written = 0
        self._next_cycle: int | None = None
        self._closed = False
        self.failure = ""
        """Why the recording stopped being written ('' while it is written)."""
        self._file = self._create_file(units, metadata, streams or {})
        self._space = _DiskSpace(self._file)
        self._streams = {name: _StreamWriter(self, self._file[STREAMS][name],
                                             len(spec.channels))
                         for name, spec in (streams or {}).items()}
        self._cycle_set = self._file[CYCLE]
        self._data_sets = [self._file[DATA][name] for name in self.channels]
        self._event_set = self._file[EVENTS]

    @property
    def n_samples(self) -> int:
        """Samples appended so far (on disk plus buffered; once closed: on disk)."""
        return self._written + self._buffered

    @property
    def buffer_rows(self) -> int:
        """Capacity of the in-memory buffer in rows (= chunk_rows)."""
        return len(self._cycles)

    @property
    def closed(self) -> bool:
        """True once `close` has run."""
        return self._closed

    def append(self, cycle: int, values: Sequence[float]) -> None:
        """Add one sample (values in channel order); flushes when a chunk is full."""
        if self._closed:  # `_require_open` inlined: this runs every bus cycle
            self._require_open()
        if cycle != self._next_cycle:
            self._check_step(cycle)
        row = self._buffered
        self._cycles[row] = cycle
        self._values[row] = values
        self._next_cycle = cycle + 1
        self._buffered = row + 1
        if self._buffered == self._chunk_rows:
            self._write_buffer()

    def append_block(self, cycles: np.ndarray, values: np.ndarray) -> None:
        """Add n samples at once: `cycles` (n,), `values` (n × channels)."""
        self._require_open()
        cycles = np.asarray(cycles, dtype=np.int64)
        values = np.asarray(values, dtype=np.float64)
        if values.shape != (len(cycles), len(self.channels)):
            raise ValueError(
                f"values shape {values.shape} != ({len(cycles)}, {len(self.channels)})"
            )
        if not len(cycles):
            return
        self._check_block_steps(cycles)
        start = 0
        while start < len(cycles):
            take = min(len(cycles) - start, self._chunk_rows - self._buffered)
            rows = slice(self._buffered, self._buffered + take)
            self._cycles[rows] = cycles[start:start + take]
            self._values[rows] = values[start:start + take]
            self._buffered += take
            start += take
            if self._buffered == self._chunk_rows:
                self._write_buffer()
        self._next_cycle = int(cycles[-1]) + 1

    def append_stream(self, name: str, cycles: np.ndarray, sequence: np.ndarray,
                      samples: np.ndarray) -> None:
        """Add n samples to stream `name`: bus cycle and counter (n,) and values (n × channels)."""
        self._require_open()
        self._streams[name].append(cycles, sequence, samples)

    def event(self, cycle: int, kind: str, text: str = "") -> None:
        """Write an event marker and flush it at once (kinds: segment, fault, limit, abort,
        gap, info)."""
        self._require_open()
        with suppress(_NoRoom), self.writing(WRITE_OVERHEAD_BYTES):
            row = len(self._event_set)
            self._event_set.resize((row + 1,))
            self._event_set[row] = (cycle, kind, text)
            self._file.flush()

    @contextmanager
    def writing(self, n_bytes: int) -> Iterator[None]:
        """Hold `n_bytes` (+ the reserve) on disk, then run the block's HDF5 writes. The first
        failure (the reserve cannot be topped up, a write fails) becomes `failure` and one
        `RecordingError`, raised after the block if the reserve still held it; after it, a
        block that does not fit raises `_NoRoom` for its caller to drop it."""
        try:
            short = self._space.hold(n_bytes + WRITE_OVERHEAD_BYTES)
        except OSError as exc:
            self._fail(exc)
            raise _NoRoom from None
        try:
            yield
        except (OSError, RuntimeError) as exc:  # h5py reports a failed write as either
            self._fail(exc)
            raise _NoRoom from None
        if short is not None:
            self._fail(short)

    def _fail(self, exc: Exception) -> None:
        """The first failure: kept in `failure`, raised as `RecordingError`; later: nothing."""
        if not self.failure:
            self.failure = f"recording failed: {' '.join(str(exc).split())[:200]}"
            raise RecordingError(f"{self.path}: {self.failure}") from None

    def close(self, status: str = "complete", reason: str = "",
              attrs: Mapping[str, Any] | None = None) -> tuple[str, str]:
        """Write the buffered rows, the final status and `attrs` (more metadata known only
        at the end, e.g. the cycle timing: JSON attributes); returns the status and reason
        written: ``aborted`` with the failure if the recording failed (a complete run whose
        last rows could not be written is not complete). A second call does nothing.

        The status is written in a second opening of the file (outside SWMR mode: SWMR
        writers must not modify attributes), after HDF5 has given back the reserve, retried
        while another process holds a lock on the file (`STATUS_LOCK_WAIT_S`, said in a
        warning and the file's `status_wait`); if that fails too, `RecordingError` says so
        and the file keeps status `running`."""
        if self._closed:
            return status, reason
        with suppress(RecordingError):  # kept in `failure`
            self._write_buffer()
            for stream in self._streams.values():
                stream.write()
        try:
            self._file.close()
        except (OSError, RuntimeError) as exc:  # HDF5's own last writes did not fit
            with suppress(RecordingError):
                self._fail(exc)
        self._closed = True
        if self.failure:
            status, reason = "aborted", reason or self.failure
            if self.failure not in reason:
                reason = f"{reason}; {self.failure}"
        attrs = {key: to_json(value) for key, value in (attrs or {}).items()}
        try:
            file, waited = _open_to_finish(self.path)
            with file:
                file.attrs.update(status=status, reason=reason, stopped_at=utc_now_iso(),
                                  n_samples=self._written, n_gaps=self.gaps, **attrs,
                                  **({"status_wait": to_json(waited)} if waited else {}))
        except (OSError, RuntimeError) as exc:
            raise RecordingError(f"{self.path}: status {status} not written ({exc})") from None
        if waited:
            LOGGER.warning("%s: status %s written after %d attempts in %.2f s (another process "
                           "held a lock on the file)", self.path, status, waited["attempts"],
                           waited["waited_s"])
        return status, reason

    def __enter__(self) -> Recorder:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        if exc is None:
            self.close()
        else:
            self.close("aborted", str(exc) or exc_type.__name__)

    def _require_open(self) -> None:
        if self._closed:
            raise RuntimeError(f"recorder for {self.path} is closed")

    def _create_file(self, units: Mapping[str, str], metadata: Mapping[str, Any],
                     streams: Mapping[str, StreamSpec]) -> h5py.File:
        """Create every dataset and attribute, then switch to SWMR mode."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        file = h5py.File(self.path, "w", libver="latest")
        file.attrs.update(
            status="running",
            reason="",
            started_at=utc_now_iso(),
            stopped_at="",
            experiment=str(metadata.get("experiment", "")),
            channels=to_json(list(self.channels)),
            config=to_json(metadata.get("config", {})),
            versions=to_json(software_versions()),
            n_samples=0,
            n_gaps=0,
        )
        for key, value in metadata.items():
            if key not in RESERVED_ATTRS:
                file.attrs[key] = to_json(value)
        self._create_datasets(file, units)
        _create_streams(file.create_group(STREAMS), streams)
        file.swmr_mode = True
        return file

    def _create_datasets(self, file: h5py.File, units: Mapping[str, str]) -> None:
        extendable = dict(shape=(0,), maxshape=(None,), chunks=(self._chunk_rows,))
        file.create_dataset(CYCLE, dtype=np.int64, **extendable)
        group = file.create_group(DATA)
        for name in self.channels:
            dataset = group.create_dataset(name, dtype=np.float64, fillvalue=np.nan, **extendable)
            dataset.attrs["units"] = units.get(name, "")
        file.create_dataset(
            EVENTS, shape=(0,), maxshape=(None,), chunks=(EVENTS_CHUNK_ROWS,), dtype=EVENT_DTYPE
        )

    def _write_buffer(self) -> None:
        """Extend every dataset by the buffered rows, write them and flush."""
        count, self._buffered = self._buffered, 0
        if not count:
            return
        with suppress(_NoRoom), self.writing(count * (len(self._data_sets) + 1) * 8):
            for column, dataset in enumerate(self._data_sets):
                _write_rows(dataset, self._written, self._values[:count, column])
            _write_rows(self._cycle_set, self._written, self._cycles[:count])
            self._file.flush()
            self._written += count

    def _check_step(self, cycle: int) -> None:
        """Called when `cycle` is not the expected next one (or for the first sample)."""
        if self._next_cycle is not None:
            self._report_step(self._next_cycle - 1, cycle)

    def _check_block_steps(self, cycles: np.ndarray) -> None:
        if self._next_cycle is not None:
            cycles = np.concatenate(([self._next_cycle - 1], cycles))
        for index in np.flatnonzero(np.diff(cycles) != 1):
            self._report_step(int(cycles[index]), int(cycles[index + 1]))

    def _report_step(self, last: int, cycle: int) -> None:
        """Record a counter step other than +1: a gap event naming the missing cycles."""
        if cycle > last + 1:
            missing = cycle - last - 1
            self.gaps += missing
            text = f"missing cycles {last + 1}-{cycle - 1} ({missing})"
        else:
            text = f"cycle counter went from {last} to {cycle} (not advancing)"
        self.event(cycle, "gap", text)


class _StreamWriter:
    """Buffers one stream's samples and writes them in chunks of `stream_chunk_rows`."""

    def __init__(self, recorder: Recorder, group: h5py.Group, n_channels: int) -> None:
        self._recorder = recorder
        self._cycle_set, self._sequence_set = group[CYCLE], group[SEQUENCE]
        self._data_sets = [group[DATA][name] for name in json.loads(group.attrs["channels"])]
        self._cycles: list[np.ndarray] = []
        self._sequences: list[np.ndarray] = []
        self._samples: list[np.ndarray] = []
        self._buffered = 0
        self._written = 0
        self._n_channels = n_channels
        self._chunk_rows = stream_chunk_rows(n_channels)

    def append(self, cycles: np.ndarray, sequence: np.ndarray, samples: np.ndarray) -> None:
        samples = np.asarray(samples, dtype=np.float64)
        if samples.shape != (len(sequence), self._n_channels) or len(cycles) != len(sequence):
            raise ValueError(f"stream samples {samples.shape}, {len(cycles)} cycles and "
                             f"{len(sequence)} counters do not match {self._n_channels} channels")
        self._cycles.append(np.asarray(cycles, dtype=np.int64))
        self._sequences.append(np.asarray(sequence, dtype=np.int64))
        self._samples.append(samples)
        self._buffered += len(sequence)
        if self._buffered >= self._chunk_rows:
            self.write()

    def write(self) -> None:
        """Write the buffered samples and flush (SWMR readers then see them); after the
        recorder's failure, while its reserve holds them."""
        samples, sequences, cycles = self._samples, self._sequences, self._cycles
        count = self._buffered
        self._cycles, self._sequences, self._samples, self._buffered = [], [], [], 0
        if not count:
            return
        samples = np.concatenate(samples)
        with suppress(_NoRoom), self._recorder.writing(count * (self._n_channels + 2) * 8):
            for column, dataset in enumerate(self._data_sets):
                _write_rows(dataset, self._written, np.ascontiguousarray(samples[:, column]))
            _write_rows(self._sequence_set, self._written, np.concatenate(sequences))
            _write_rows(self._cycle_set, self._written, np.concatenate(cycles))
            self._cycle_set.file.flush()
            self._written += count


class _DiskSpace:
    """Keeps `RESERVE_BYTES` of disk allocated beyond what an HDF5 file has used (an
    estimate from the bytes written, counted generously), in steps of `RESERVE_STEP_BYTES`.

    ``posix_fallocate`` raises `OSError` (ENOSPC, EFBIG) when the space is not there, before
    HDF5 writes into it; HDF5 truncates the file to its used size when it is closed.
    """

    def __init__(self, file: h5py.File) -> None:
        self._fd = file.id.get_vfd_handle()
        self._used = file.id.get_filesize()
        self._held = self._used
        if (short := self.hold(0)) is not None:
            raise short

    def hold(self, n_bytes: int) -> OSError | None:
        """Count `n_bytes` as used and make sure the reserve beyond them is allocated. If it
        cannot be, the error is returned while the bytes fit in what is held (`CLOSE_BYTES`
        kept back: the caller writes them), else raised."""
        self._used += n_bytes
        if self._used + RESERVE_BYTES > self._held:
            target = self._used + RESERVE_BYTES + RESERVE_STEP_BYTES
            try:
                os.posix_fallocate(self._fd, self._held, target - self._held)
            except OSError as exc:
                if self._used > self._held - CLOSE_BYTES:
                    raise
                return exc
            self._held = target
        return None


def stream_chunk_rows(n_channels: int) -> int:
    """Rows per written chunk of a stream of `n_channels`: `STREAM_CHUNK_ROWS`, fewer if
    that would exceed `STREAM_CHUNK_BYTES` (its counters and bus cycles counted)."""
    return max(1, min(STREAM_CHUNK_ROWS, STREAM_CHUNK_BYTES // ((n_channels + 2) * 8)))


def _create_streams(group: h5py.Group, streams: Mapping[str, StreamSpec]) -> None:
    for name, spec in streams.items():
        extendable = dict(shape=(0,), maxshape=(None,),
                          chunks=(stream_chunk_rows(len(spec.channels)),))
        stream = group.create_group(name)
        stream.attrs.update(rate_hz=float(spec.rate_hz), channels=to_json(list(spec.channels)))
        stream.create_dataset(CYCLE, dtype=np.int64, **extendable)
        stream.create_dataset(SEQUENCE, dtype=np.int64, **extendable)
        data = stream.create_group(DATA)
        for channel in spec.channels:
            dataset = data.create_dataset(channel, dtype=np.float64, fillvalue=np.nan, **extendable)
            dataset.attrs["units"] = spec.units.get(channel, "")


def _open_to_finish(path: Path) -> tuple[h5py.File, dict[str, float]]:
    """`path` opened to write its final status, tried again with growing pauses while
    another process holds a lock on it, for up to `STATUS_LOCK_WAIT_S`; returns the file
    and, if it had to wait, the attempts and the wait (s)."""
    started, pause, attempts = time.monotonic(), STATUS_RETRY_FIRST_S, 1
    while True:
        try:
            file = h5py.File(path, "r+")
            break
        except BlockingIOError as exc:
            waited = time.monotonic() - started
            if waited + pause > STATUS_LOCK_WAIT_S:
                raise BlockingIOError(exc.errno, f"{exc.strerror}; locked by another process "
                                      f"through {attempts} attempts in {waited:.1f} s") from None
            time.sleep(pause)
            pause, attempts = min(2 * pause, STATUS_RETRY_MAX_S), attempts + 1
    if attempts == 1:
        return file, {}
    return file, {"attempts": attempts, "waited_s": round(time.monotonic() - started, 3)}


def _write_rows(dataset: h5py.Dataset, start: int, rows: np.ndarray) -> None:
    """Extend a 1-D `dataset` and write the contiguous `rows` from index `start`.

    h5py's low-level calls: slice assignment costs ~3x more per chunk (~150 vs ~50 µs).
    """
    dataset.id.set_extent((start + len(rows),))
    file_space = dataset.id.get_space()
    file_space.select_hyperslab((start,), (len(rows),))
    dataset.id.write(h5s.create_simple((len(rows),)), file_space, rows)


def _check_metadata_keys(metadata: Mapping[str, Any]) -> None:
    clashing = set(metadata) & (RESERVED_ATTRS - {"experiment", "config"})
    if clashing:
        raise ValueError(f"metadata keys {sorted(clashing)} are reserved by the recorder")


SUPERBLOCK_SIGNATURE = b"\x89HDF\r\n\x1a\n"
"""The HDF5 format signature the superblock starts with."""


def mark_crashed(path: str | Path, reason: str, n_samples: int) -> None:
    """Mark a recording whose writer died (SIGKILL, power loss) with status `crashed`, the
    `reason` and its `n_samples` rows on disk, in the file itself: what feedbench does at
    its next start for a run whose process has ended (`Catalog.reconcile`). Only for a
    file no process writes any more: its SWMR writer's consistency flags are cleared first
    (what HDF5's h5clear does; h5py has no call for it), which a live writer needs."""
    _clear_consistency_flags(Path(path))
    with h5py.File(path, "r+") as file:
        file.attrs.update(status="crashed", reason=reason, n_samples=n_samples)


def _clear_consistency_flags(path: Path) -> None:
    """Zero the file consistency flags of a version 2/3 superblock (at offset 0) and write
    its checksum again (Jenkins lookup3, as HDF5 computes it)."""
    with open(path, "r+b") as file:
        head = bytearray(file.read(12))
        if head[:8] != SUPERBLOCK_SIGNATURE or head[8] < 2 or not head[11]:
            return
        offsets = head[9]
        body = head + file.read(4 * offsets)
        body[11] = 0
        file.seek(0)
        file.write(bytes(body) + _lookup3(bytes(body)).to_bytes(4, "little"))


def _lookup3(data: bytes, initval: int = 0) -> int:
    """Bob Jenkins' lookup3 `hashlittle` of `data`, byte by byte (HDF5's H5_checksum_lookup3)."""
    mask = 0xFFFFFFFF

    def rot(x: int, k: int) -> int:
        return ((x << k) | (x >> (32 - k))) & mask

    a = b = c = (0xDEADBEEF + len(data) + initval) & mask
    words = [int.from_bytes(data[i:i + 4].ljust(4, b"\0"), "little")
             for i in range(0, len(data), 4)]
    rest = len(data)
    while rest > 12:
        i = (len(data) - rest) // 4
        a, b, c = (a + words[i]) & mask, (b + words[i + 1]) & mask, (c + words[i + 2]) & mask
        a = (a - c) & mask ^ rot(c, 4); c = (c + b) & mask
        b = (b - a) & mask ^ rot(a, 6); a = (a + c) & mask
        c = (c - b) & mask ^ rot(b, 8); b = (b + a) & mask
        a = (a - c) & mask ^ rot(c, 16); c = (c + b) & mask
        b = (b - a) & mask ^ rot(a, 19); a = (a + c) & mask
        c = (c - b) & mask ^ rot(b, 4); b = (b + a) & mask
        rest -= 12
    if rest == 0:
        return c
    i = (len(data) - rest) // 4
    tail = words[i:i + 3] + [0, 0, 0]
    a, b, c = (a + tail[0]) & mask, (b + tail[1]) & mask, (c + tail[2]) & mask
    c = (c ^ b) - rot(b, 14) & mask
    a = (a ^ c) - rot(c, 11) & mask
    b = (b ^ a) - rot(a, 25) & mask
    c = (c ^ b) - rot(b, 16) & mask
    a = (a ^ c) - rot(c, 4) & mask
    b = (b ^ a) - rot(a, 14) & mask
    c = (c ^ b) - rot(b, 24) & mask
    return c
