"""The recording file format (HDF5) and its reader.

Layout written by `feedbench.daq.recorder.Recorder`:

- `/cycle` (int64): the bus cycle counter of every sample.
- `/data/<channel>` (float64, SI units in the dataset attribute `units`): one row per sample.
- `/events` (compound cycle int64, kind str, text str): segment boundaries, faults, gaps.
- `/streams/<name>/` (optional): a high-rate stream (e.g. the serial DAQ at 10 kHz) with its own
  rows: `cycle` (int64, the bus cycle each sample belongs to), `sequence` (int64, the
  instrument's sample counter; a step > 1 is a lost sample) and `data/<channel>` (float64, SI,
  attribute `units`); group attributes `rate_hz` and `channels` (JSON list).
- root attributes: `status` (`running` / `complete` / `aborted`), `reason`, `started_at`,
  `stopped_at` (ISO 8601 UTC), `experiment`, `channels` (JSON list, the column order),
  `config` and `versions` (JSON), `n_samples`, `n_gaps`, and every other metadata key as JSON.

The reader opens files in SWMR read mode, so it reads a file that is still being written
(live replay) and a file whose writer crashed (status stays `running`, data up to the last
flushed chunk); it takes no file lock, so no reader ever blocks the writer.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, TypeVar

import h5py
import numpy as np

from feedbench.config import ConfigError
from feedbench.daq.hdf5_check import check_global_heaps

CYCLE = "cycle"
DATA = "data"
EVENTS = "events"
STREAMS = "streams"
SEQUENCE = "sequence"
T = TypeVar("T")
EVENT_DTYPE = np.dtype(
    [("cycle", np.int64), ("kind", h5py.string_dtype()), ("text", h5py.string_dtype())]
)
RESERVED_ATTRS = frozenset(
    {
        "status", "reason", "started_at", "stopped_at", "experiment", "channels",
        "config", "versions", "n_samples", "n_gaps",
    }
)


def utc_now_iso() -> str:
    """Current time as ISO 8601 UTC text, e.g. `2026-11-22T00:15:03.123456+00:00`."""
    return datetime.now(timezone.utc).isoformat()


def to_json(value: Any) -> str:
    """JSON text of `value`; numpy scalars/arrays become lists/numbers, anything else its str."""
    return json.dumps(value, default=_json_fallback, sort_keys=True)


def printable_json(value: Any) -> str:
    """Indented strict JSON of a result for people and tools (`--json`): numpy values become
    numbers and lists, a non-finite number (an unknown σ, a missing coherence) null, which
    jq and browsers read (Python's json writes NaN, which is not JSON)."""
    return json.dumps(_finite(value), indent=2, default=_json_fallback, allow_nan=False)


def _finite(value: Any) -> Any:
    """`value` with every non-finite float replaced by None, containers walked."""
    if isinstance(value, (np.generic, np.ndarray)):
        value = value.tolist()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: _finite(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(item) for item in value]
    return value


def _json_fallback(value: Any) -> Any:
    if isinstance(value, (np.generic, np.ndarray)):
        return value.tolist()
    return str(value)


@dataclass(frozen=True)
class Event:
    """One event marker: the cycle it belongs to, its kind and free text."""

    cycle: int
    kind: str
    text: str


@dataclass(frozen=True)
class Segment:
    """Cycles [start, stop) between one event of a kind and the next, labelled by its text."""

    label: str
    start: int
    stop: int


@dataclass(frozen=True)
class Stream:
    """A high-rate stream of a recording: per sample its bus cycle, counter and values (SI)."""

    rate_hz: float
    cycle: np.ndarray
    sequence: np.ndarray
    channels: dict[str, np.ndarray]
    units: dict[str, str]

    @property
    def n_samples(self) -> int:
        """Number of samples in the stream."""
        return len(self.sequence)

    @property
    def n_dropped(self) -> int:
        """Samples missing from the counter sequence (lost on the link or in the instrument)."""
        return missing_cycles(self.sequence)

    def mask(self, segment: Segment) -> np.ndarray:
        """Boolean mask of the samples that belong to the bus cycles of `segment`."""
        return (self.cycle >= segment.start) & (self.cycle < segment.stop)


@dataclass(frozen=True)
class Recording:
    """One recording read into memory; arrays are read-only."""

    path: Path
    cycle: np.ndarray
    channels: dict[str, np.ndarray]
    units: dict[str, str]
    status: str
    reason: str
    started_at: str
    stopped_at: str
    experiment: str
    config: dict[str, Any]
    versions: dict[str, str | None]
    events: list[Event]
    n_gaps: int
    metadata: dict[str, Any] = field(default_factory=dict)
    streams: dict[str, Stream] = field(default_factory=dict)

    @property
    def n_samples(self) -> int:
        """Number of samples in the file."""
        return len(self.cycle)

    @property
    def rotary(self) -> bool:
        """A rotary axis's recording: its position stored in rad (an imported joint)."""
        return self.units.get("position") == "rad"

    def segments(self, kind: str = "segment") -> list[Segment]:
        """Cycle ranges from each `kind` event to the next one (the last one to the end)."""
        marks = [event for event in self.events if event.kind == kind]
        end = int(self.cycle.max()) + 1 if self.n_samples else 0
        stops = [mark.cycle for mark in marks[1:]] + [end]
        return [
            Segment(mark.text, mark.cycle, max(stop, mark.cycle))
            for mark, stop in zip(marks, stops)
        ]

    def mask(self, segment: Segment) -> np.ndarray:
        """Boolean row mask of the samples whose cycle lies in `segment`."""
        return (self.cycle >= segment.start) & (self.cycle < segment.stop)


@dataclass(frozen=True)
class RecordingSummary:
    """What the run catalog keeps of a recording, read without its data: `n_samples` counts
    the rows on disk (a crashed writer's file: up to its last flushed chunk), `run_id` is the
    id the run was recorded under (the file's stem if the file has none), `timing` a
    real-time run's cycle timing (`daq.timing`; None in lockstep or before its end)."""

    path: Path
    run_id: str
    experiment: str
    status: str
    reason: str
    started_at: str
    stopped_at: str
    n_samples: int
    config: dict[str, Any]
    timing: dict[str, Any] | None = None
    bench: str | None = None
    """The bench and host that recorded it (None: a file written before they were kept)."""
    host: str | None = None


def open_recording(path: str | Path) -> Recording:
    """Read a recording (complete, aborted, still being written or left by a crashed writer).

    A missing, empty, truncated or foreign file raises `ConfigError` naming the file.
    """
    return _checked(Path(path), _read_recording)


def read_summary(path: str | Path) -> RecordingSummary:
    """A recording's status, times and sample count (errors as `open_recording`)."""
    return _checked(Path(path), _read_summary)


def _checked(path: Path, read: Callable[[Path], T]) -> T:
    """`read(path)` with the libraries' errors turned into `ConfigError` naming the file."""
    try:
        return read(path)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such recording") from None
    except (OSError, RuntimeError) as exc:  # h5py: not HDF5, truncated, damaged, unreadable
        raise ConfigError(f"{path}: not a readable HDF5 file ({_first_line(exc)})") from None
    except (KeyError, ValueError) as exc:  # a dataset or attribute missing or of another kind
        raise ConfigError(f"{path}: not a feedbench recording ({_first_line(exc)})") from None


def _first_line(exc: BaseException) -> str:
    """The first line of an exception's message (KeyError: its argument, unquoted)."""
    text = str(exc.args[0] if isinstance(exc, KeyError) and exc.args else exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _open(path: Path) -> h5py.File:
    """The file read-only, by SWMR only while a writer has it open (or died with it open):
    HDF5 retries a SWMR reader's failed metadata reads with growing sleeps, so a damaged
    file opened by SWMR can block for minutes instead of failing. A file whose global heap
    would make libhdf5 loop is rejected before it reads it (`hdf5_check`).

    A reader takes no file lock (``locking=False``): HDF5's shared lock of a reader would
    make the writer's last opening, which writes the final status, fail with "unable to
    lock file" (a run lost to a `feedbench runs` or a live view reading it at that moment)."""
    check_global_heaps(path)
    try:
        return _unlocked(path, swmr=False)
    except OSError as exc:
        if "already open for write" not in str(exc):
            raise
    return _unlocked(path, swmr=True)


def _unlocked(path: Path, swmr: bool) -> h5py.File:
    """The file opened read-only without a lock; a file this process writes itself (a live
    view beside its recorder) with the writer's lock setting, which HDF5 requires to match."""
    try:
        return h5py.File(path, "r", libver="latest", swmr=swmr, locking=False)
    except OSError as exc:
        if "locking flag values don't match" not in str(exc):
            raise
    return h5py.File(path, "r", libver="latest", swmr=swmr)


def _read_summary(path: Path) -> RecordingSummary:
    with _open(path) as file:
        attrs = file.attrs
        return RecordingSummary(
            path=path,
            run_id=json.loads(attrs["run_id"]) if "run_id" in attrs else path.stem,
            experiment=str(attrs["experiment"]),
            status=str(attrs["status"]),
            reason=str(attrs["reason"]),
            started_at=str(attrs["started_at"]),
            stopped_at=str(attrs["stopped_at"]),
            n_samples=_complete_rows(file, json.loads(attrs["channels"])),
            config=json.loads(attrs["config"]),
            timing=json.loads(attrs["timing"]) if "timing" in attrs else None,
            bench=json.loads(attrs["bench"]) if "bench" in attrs else None,
            host=json.loads(attrs["host"]) if "host" in attrs else None,
        )


def _read_recording(path: Path) -> Recording:
    with _open(path) as file:
        attrs = dict(file.attrs)
        names = json.loads(attrs["channels"])
        rows = _complete_rows(file, names)
        cycle = _read_only(file[CYCLE][:rows])
        _check_increasing(cycle)
        return Recording(
            path=path,
            cycle=cycle,
            channels={name: _read_only(file[DATA][name][:rows]) for name in names},
            units={name: str(file[DATA][name].attrs["units"]) for name in names},
            status=str(attrs["status"]),
            reason=str(attrs["reason"]),
            started_at=str(attrs["started_at"]),
            stopped_at=str(attrs["stopped_at"]),
            experiment=str(attrs["experiment"]),
            config=json.loads(attrs["config"]),
            versions=json.loads(attrs["versions"]),
            events=_read_events(file[EVENTS]),
            n_gaps=missing_cycles(cycle),
            metadata={
                key: json.loads(value) for key, value in attrs.items() if key not in RESERVED_ATTRS
            },
            streams={name: _read_stream(group) for name, group in file.get(STREAMS, {}).items()},
        )


def _check_increasing(cycle: np.ndarray) -> None:
    """The bus cycle of every row must follow the one before (raises ValueError)."""
    back = np.flatnonzero(np.diff(cycle) <= 0)
    if back.size:
        row = int(back[0]) + 1
        raise ValueError(f"/{CYCLE} not increasing: row {row} has cycle {cycle[row]} "
                         f"after {cycle[row - 1]}")


def missing_cycles(cycle: np.ndarray) -> int:
    """Number of cycles skipped by a counter that should advance by exactly 1."""
    steps = np.diff(cycle)
    return int(np.sum(steps[steps > 1] - 1))


def _complete_rows(file: h5py.File, names: list[str]) -> int:
    """Rows present in every dataset (a crash between two resizes leaves them unequal)."""
    return min([_rows(file[CYCLE])] + [_rows(file[DATA][name]) for name in names])


def _rows(dataset: h5py.Dataset) -> int:
    """The dataset's rows, if the file can hold them: the recorder writes uncompressed
    chunks, so a dataset's rows fit the file's bytes but for one chunk (resized, not yet
    written when its writer died). A damaged header declaring more is a ValueError, not a
    read that allocates gigabytes of fill values."""
    rows, row_bytes = len(dataset), dataset.dtype.itemsize
    unwritten = dataset.chunks[0] if dataset.chunks else 0
    file_bytes = dataset.file.id.get_filesize()
    if (rows - unwritten) * row_bytes > file_bytes:
        raise ValueError(f"{dataset.name}: {rows} rows of {row_bytes} bytes do not fit in "
                         f"the file's {file_bytes} bytes")
    return rows


def _read_stream(group: h5py.Group) -> Stream:
    names = json.loads(group.attrs["channels"])
    rows = min([_rows(group[CYCLE]), _rows(group[SEQUENCE])]
               + [_rows(group[DATA][n]) for n in names])
    return Stream(
        rate_hz=float(group.attrs["rate_hz"]),
        cycle=_read_only(group[CYCLE][:rows]),
        sequence=_read_only(group[SEQUENCE][:rows]),
        channels={name: _read_only(group[DATA][name][:rows]) for name in names},
        units={name: str(group[DATA][name].attrs["units"]) for name in names},
    )


def _read_events(dataset: h5py.Dataset) -> list[Event]:
    return [
        Event(int(cycle), _text(kind), _text(text))
        for cycle, kind, text in dataset[:_rows(dataset)]
    ]


def _text(value: bytes | str) -> str:
    return value.decode() if isinstance(value, bytes) else value


def _read_only(array: np.ndarray) -> np.ndarray:
    array.setflags(write=False)
    return array
