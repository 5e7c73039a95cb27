"""Incremental HDF5 recorder: one row per bus cycle, written chunk by chunk.

The recorder holds at most `chunk_rows` rows in memory. When the buffer is full it extends
the datasets, writes the rows and flushes, so the file on disk always holds every completed
chunk. The file is in SWMR mode (single writer, multiple readers): a live plot can read it
while it is written, and a writer killed mid-run leaves a readable file with status
`running`. The layout is described in `feedbench.daq.recording`.
"""

from __future__ import annotations

import json
import platform
from collections.abc import Mapping, Sequence
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
"""Rows of a high-rate stream held in memory before they are written (1 s at 10 kHz)."""


class StreamSpec(NamedTuple):
    """A high-rate stream to record beside the per-cycle rows: channel names, units, rate (Hz)."""

    channels: tuple[str, ...]
    units: Mapping[str, str]
    rate_hz: float


def software_versions() -> dict[str, str | None]:
    """Versions of Python, HDF5 and the libraries a recording depends on (None if missing)."""
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
        self._file = self._create_file(units, metadata, streams or {})
        self._streams = {name: _StreamWriter(self._file[STREAMS][name], len(spec.channels))
                         for name, spec in (streams or {}).items()}
        self._cycle_set = self._file[CYCLE]
        self._data_sets = [self._file[DATA][name] for name in self.channels]
        self._event_set = self._file[EVENTS]

    @property
    def n_samples(self) -> int:
        """Samples appended so far (on disk plus buffered)."""
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
        row = len(self._event_set)
        self._event_set.resize((row + 1,))
        self._event_set[row] = (cycle, kind, text)
        self._file.flush()

    def close(self, status: str = "complete", reason: str = "") -> None:
        """Write the buffered rows and the final status; a second call does nothing."""
        if self._closed:
            return
        self._write_buffer()
        for stream in self._streams.values():
            stream.write()
        self._file.close()
        self._closed = True
        # Final attributes are written outside SWMR mode: SWMR writers must not modify attributes.
        with h5py.File(self.path, "r+") as file:
            file.attrs.update(
                status=status,
                reason=reason,
                stopped_at=utc_now_iso(),
                n_samples=self._written,
                n_gaps=self.gaps,
            )

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
        count = self._buffered
        if not count:
            return
        for column, dataset in enumerate(self._data_sets):
            _write_rows(dataset, self._written, self._values[:count, column])
        _write_rows(self._cycle_set, self._written, self._cycles[:count])
        self._file.flush()
        self._written += count
        self._buffered = 0

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
    """Buffers one stream's samples and writes them in chunks of `STREAM_CHUNK_ROWS`."""

    def __init__(self, group: h5py.Group, n_channels: int) -> None:
        self._cycle_set, self._sequence_set = group[CYCLE], group[SEQUENCE]
        self._data_sets = [group[DATA][name] for name in json.loads(group.attrs["channels"])]
        self._cycles: list[np.ndarray] = []
        self._sequences: list[np.ndarray] = []
        self._samples: list[np.ndarray] = []
        self._buffered = 0
        self._written = 0
        self._n_channels = n_channels

    def append(self, cycles: np.ndarray, sequence: np.ndarray, samples: np.ndarray) -> None:
        samples = np.asarray(samples, dtype=np.float64)
        if samples.shape != (len(sequence), self._n_channels) or len(cycles) != len(sequence):
            raise ValueError(f"stream samples {samples.shape}, {len(cycles)} cycles and "
                             f"{len(sequence)} counters do not match {self._n_channels} channels")
        self._cycles.append(np.asarray(cycles, dtype=np.int64))
        self._sequences.append(np.asarray(sequence, dtype=np.int64))
        self._samples.append(samples)
        self._buffered += len(sequence)
        if self._buffered >= STREAM_CHUNK_ROWS:
            self.write()

    def write(self) -> None:
        """Write the buffered samples and flush (SWMR readers then see them)."""
        if not self._buffered:
            return
        samples = np.concatenate(self._samples)
        for column, dataset in enumerate(self._data_sets):
            _write_rows(dataset, self._written, np.ascontiguousarray(samples[:, column]))
        _write_rows(self._sequence_set, self._written, np.concatenate(self._sequences))
        _write_rows(self._cycle_set, self._written, np.concatenate(self._cycles))
        self._cycle_set.file.flush()
        self._written += self._buffered
        self._cycles, self._sequences, self._samples, self._buffered = [], [], [], 0


def _create_streams(group: h5py.Group, streams: Mapping[str, StreamSpec]) -> None:
    extendable = dict(shape=(0,), maxshape=(None,), chunks=(STREAM_CHUNK_ROWS,))
    for name, spec in streams.items():
        stream = group.create_group(name)
        stream.attrs.update(rate_hz=float(spec.rate_hz), channels=to_json(list(spec.channels)))
        stream.create_dataset(CYCLE, dtype=np.int64, **extendable)
        stream.create_dataset(SEQUENCE, dtype=np.int64, **extendable)
        data = stream.create_group(DATA)
        for channel in spec.channels:
            dataset = data.create_dataset(channel, dtype=np.float64, fillvalue=np.nan, **extendable)
            dataset.attrs["units"] = spec.units.get(channel, "")


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
