"""A foreign recording as a feedbench run: the mapping file, one time base, the HDF5 file.

The mapping (TOML; `FILE.toml` beside the recording, or ``--mapping``) says which channel
of the file is which channel of the run and in what unit, as the closure's CSV sidecar does
(docs/import.md):

    name = "X axis chirp, dSPACE"
    rate_Hz = 1000.0            # the run's time base; default: the position channel's rate
    segment_kind = "excite"     # the one segment over the whole file, without [[segments]]
    force_lag_ms = 0.0          # as in the sidecar, with [sampling] and [controller]
    [channels]                  # run channel = the file's channel (`mdf4`/`tdms` naming)
    position = "X_pos"
    force = "Group/F_motor"
    [units]                     # unit of a channel where the file gives none or a wrong one
    position = "mm"
    [scale]                     # factor before the unit (a sensor's N/V on a voltage)
    force = 100.0
    [streams.daq]               # high-rate channels kept at their own rate (tool tip, hammer)
    acc_tool_x = "Accel_X"
    [experiment]                # the family and its parameters, as in a run config
    type = "chirp"
    [[segments]]                # optional: label, kind, start_s, stop_s (from the first sample)

Per-cycle channels meet on one time base (`rate_Hz`, from the latest first sample to the
earliest last one): a channel at that rate whose samples fall on it is taken as it is
(bit-exact); a slower one is interpolated linearly; a faster one is low-passed below the
base's Nyquist frequency (zero phase) and then taken at the base's times. Stream channels
keep their own samples and get the bus cycle each falls in, as the serial DAQ's stream does.
A channel with a gap (a sample period > `GAP_FACTOR` × its median), times that do not
increase, or a NaN/inf sample is refused with one line naming it.
"""

from __future__ import annotations

import json
import math
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from fractions import Fraction
from pathlib import Path
from typing import Any, Iterator, Mapping, NoReturn

import h5py
import numpy as np
import scipy.signal

from feedbench.config import (
    REQUIRED, ConfigError, Field, non_negative, positive, read_toml, validate_table,
)
from feedbench.daq.importers import ForeignChannel, ForeignFile, read_foreign
from feedbench.daq.recorder import Recorder, StreamSpec
from feedbench.daq.recording import to_json, utc_now_iso
from feedbench.units import SI_UNITS

GAP_FACTOR = 1.5
"""A step between two samples longer than this many median sample periods is a gap."""
ON_GRID = 1e-6
"""A sample lies on the time base when it is within this share of a base period of it."""

SI_UNIT_OF = {"length": "m", "angle": "rad", "velocity": "m/s", "angular velocity": "rad/s",
              "force": "N", "torque": "N·m", "acceleration": "m/s2",
              "angular acceleration": "rad/s2", "time": "s"}
"""The SI unit an imported channel is stored in, by the quantity its unit measures (a rotary
axis's position in rad, its force in N·m)."""

RUN_CHANNELS = {
    "position": ("position", "m", ("length", "angle")),
    "velocity": ("velocity", "m/s", ("velocity", "angular velocity")),
    "force": ("force", "N", ("force", "torque")),
    "reference": ("x_ref", "m", ("length", "angle")),
    "excitation": ("force_offset", "N", ("force", "torque")),
    "external_force": ("external_force", "N", ("force", "torque")),
    "tip_acceleration": ("tip_acceleration", "m/s2", ("acceleration", "angular acceleration")),
}
"""Mapping channel → (recording channel, its SI unit on a linear axis, the quantities its
unit may measure; an angle is stored in rad, a torque in N·m: `SI_UNIT_OF`)."""

STREAM_QUANTITIES = {"acc": ("acceleration",), "force": ("force",)}
"""A stream channel whose name contains the key must be in a unit of these quantities."""

MAPPING_SCHEMA = {
    "name": Field(str, "", "what the recording is"),
    "format": Field(str, "", "the file's format (default: by its suffix)"),
    "rate_Hz": Field(float, 0.0, "the run's time base (Hz); 0: the position channel's rate",
                     non_negative),
    "segment_kind": Field(str, "measure", "kind of the one segment over the whole file when "
                          "there are no [[segments]] (measure, excite, …)"),
    "force_lag_ms": Field(float, 0.0, "lag of the force samples behind the position (ms)"),
    "channels": Field(dict, None, "run channel → the file's channel"),
    "units": Field(dict, {}, "run or stream channel → unit of the file's channel"),
    "scale": Field(dict, {}, "run or stream channel → factor before the unit"),
    "streams": Field(dict, {}, "stream name → {its channel → the file's channel}"),
    "experiment": Field(dict, {}, "the experiment family and its parameters"),
    "controller": Field(dict, {}, "the drive's controller, as in a model config"),
    "sampling": Field(dict, {}, "how each channel was sampled (cycle, mean, latch)"),
}

SEGMENT_SCHEMA = {
    "label": Field(str, "", "the segment's label"),
    "kind": Field(str, REQUIRED, "measure, excite, settle, move…"),
    "start_s": Field(float, 0.0, "start from the run's first sample (s)", non_negative),
    "stop_s": Field(float, math.inf, "end from the run's first sample (s)", positive),
    "info": Field(dict, {}, "labels the analysis reads (feed, frequency, test…)"),
}


@dataclass(frozen=True)
class ImportedRun:
    """A foreign recording on one time base, SI inside: per-cycle channels (n samples at
    `cycle_s`, the first at `t0_s` of the file's clock), streams at their own rates with the
    cycle each sample falls in, segments as (cycle, JSON text) events, and what the
    recording's metadata keeps (mapping, source file, resampling done)."""

    name: str
    cycle_s: float
    t0_s: float
    channels: dict[str, np.ndarray]
    units: dict[str, str]
    streams: dict[str, tuple[StreamSpec, np.ndarray, np.ndarray, dict[str, np.ndarray]]]
    segments: list[tuple[int, str]]
    experiment: str
    config: dict[str, Any]
    metadata: dict[str, Any] = field(default_factory=dict)
    controller: dict[str, Any] = field(default_factory=dict)

    @property
    def n_samples(self) -> int:
        """Samples on the time base."""
        return len(next(iter(self.channels.values())))


def mapping_path(source: str | Path) -> Path:
    """The mapping beside a foreign file: same stem, .toml."""
    return Path(source).with_suffix(".toml")


def read_mapping(path: str | Path) -> dict[str, Any]:
    """A mapping file, validated (unknown keys and channels refused with their field)."""
    return check_mapping(read_toml(path))


def check_mapping(raw: Mapping[str, Any]) -> dict[str, Any]:
    """The mapping table validated: its channels known, position and force required, each
    stream a table of file channel names."""
    raw = dict(raw)
    segments = raw.pop("segments", [])  # a list of tables: checked one by one below
    if not isinstance(segments, list):
        raise ConfigError("mapping.segments: a list of tables ([[segments]])")
    side = validate_table(raw, MAPPING_SCHEMA, "mapping")
    channels = validate_table(side["channels"] or {}, {
        key: Field(str, "", f"the file's channel of the run's {key} ({unit})")
        for key, (_, unit, _) in RUN_CHANNELS.items()}, "mapping.channels")
    for required in ("position", "force"):
        if not channels[required]:
            raise ConfigError(f"mapping.channels.{required}: required (the file's channel "
                              "holding it)")
    side["channels"] = {key: name for key, name in channels.items() if name}
    for stream, table in side["streams"].items():
        if not isinstance(table, dict) or not table or not all(
                isinstance(v, str) and v for v in table.values()):
            raise ConfigError(f"mapping.streams.{stream}: a table of channel = \"the file's "
                              "channel\"")
    known = set(side["channels"]) | {c for t in side["streams"].values() for c in t}
    for table in ("units", "scale"):
        for key, value in side[table].items():
            if key not in known:
                raise ConfigError(f"mapping.{table}.{key}: no such mapped channel "
                                  f"(mapped: {', '.join(sorted(known))})")
            if table == "scale" and not (isinstance(value, (int, float))
                                         and not isinstance(value, bool)
                                         and math.isfinite(value) and value != 0.0):
                raise ConfigError(f"mapping.scale.{key}: must be a finite non-zero number "
                                  f"(got {value!r})")
    side["segments"] = [validate_table(s, SEGMENT_SCHEMA, f"mapping.segments[{i}]")
                        if isinstance(s, dict) else _not_table(i)
                        for i, s in enumerate(segments)]
    if side["experiment"] and not isinstance(side["experiment"].get("type"), str):
        raise ConfigError("mapping.experiment.type: required (the experiment family)")
    return side


def _not_table(index: int) -> NoReturn:
    raise ConfigError(f"mapping.segments[{index}]: a table (label, kind, start_s, stop_s)")


def load_run(source: str | Path, mapping: str | Path | Mapping[str, Any] | None = None
             ) -> ImportedRun:
    """Read a foreign file and its mapping (a path, a table, or None: `mapping_path`)."""
    if mapping is None or isinstance(mapping, (str, Path)):
        path = Path(mapping) if mapping is not None else mapping_path(source)
        if not path.is_file():
            raise ConfigError(f"{path}: no mapping (which channel is which: docs/import.md; "
                              "give --mapping M.toml)")
        side = read_mapping(path)
    else:
        side = check_mapping(mapping)
    wanted = {*side["channels"].values(), *(name for table in side["streams"].values()
                                            for name in table.values())}
    return build_run(read_foreign(source, side["format"], wanted), side)


def build_run(foreign: ForeignFile, side: Mapping[str, Any]) -> ImportedRun:
    """The run of a read file under a checked mapping (`check_mapping`)."""
    picked = {key: _checked(foreign.channel(name, f"mapping.channels.{key}"),
                            f"mapping.channels.{key}")
              for key, name in side["channels"].items()}
    period = 1.0 / side["rate_Hz"] if side["rate_Hz"] else picked["position"].period
    rate = 1.0 / period
    t0 = max(float(c.time[0]) for c in picked.values())
    t1 = min(float(c.time[-1]) for c in picked.values())
    n = int(math.floor((t1 - t0) / period + ON_GRID)) + 1 if t1 >= t0 else 0
    if n < 2:
        raise ConfigError(f"mapping.channels: the mapped channels of {foreign.path.name} do "
                          f"not overlap in time ({_spans(picked)})")
    base = t0 + np.arange(n) * period
    channels, units, notes = {}, {}, {}
    for key, channel in picked.items():
        target, _, quantities = RUN_CHANNELS[key]
        factor = _factor(side, key, channel, quantities)
        values, how = _on_base(channel, base, rate)
        channels[target] = values * factor if factor != 1.0 else values
        units[target] = SI_UNIT_OF[_quantity(side, key, channel)]
        notes[key] = {"file_channel": channel.name, "file_unit": channel.unit,
                      "rate_Hz": channel.rate_hz, "resampled": how}
    if "velocity" not in channels:
        channels["velocity"] = np.gradient(channels["position"], 1.0 / rate)
        units["velocity"] = "rad/s" if units["position"] == "rad" else "m/s"
        notes["velocity"] = {"resampled": "central differences of the position"}
    streams = {name: _stream(foreign, name, table, side, t0, base[-1], rate, notes)
               for name, table in side["streams"].items()}
    cycle_s = period
    experiment = side["experiment"].get("type", "imported") if side["experiment"] else "imported"
    config = {"experiment": dict(side["experiment"]) or {"type": "imported"},
              "import": {"source": foreign.path.name, "format": foreign.format,
                         "channels": dict(side["channels"]),
                         "streams": {k: dict(v) for k, v in side["streams"].items()}}}
    started, started_from = _started(foreign, picked["position"], t0)
    metadata = {"cycle_s": cycle_s, "source_file": str(foreign.path),
                "source_format": foreign.format, "source_t0_s": t0,
                "source_started_at": started, "source_started_from": started_from,
                "source_metadata": foreign.metadata, "import_channels": notes,
                "force_lag_s": side["force_lag_ms"] * 1e-3, "sampling": dict(side["sampling"]),
                "import_versions": _versions()}
    return ImportedRun(side["name"] or foreign.path.name, cycle_s, t0, channels, units,
                       streams, _segments(side, n, rate), experiment, config, metadata,
                       dict(side["controller"]))


def _started(foreign: ForeignFile, position: ForeignChannel, t0: float) -> tuple[str, str]:
    """When the run's first sample was taken, as ISO 8601 UTC text, and what said so: the
    time 0 of the position channel's clock (an MDF4 header's start time, its TDMS
    wf_start_time), else the file's own time (a TDMS file property), moved on by the first
    sample's time `t0`; ('', why) when the file says none (the run then starts when it is
    imported)."""
    if position.origin is not None:
        origin = position.origin
        said = ("MDF header start time" if foreign.format == "mdf4" else
                f"wf_start_time of {position.name}" if foreign.format == "tdms" else
                f"time 0 of {position.name}")
    elif foreign.origin is not None:
        origin, said = foreign.origin, foreign.origin_source or "the file's time"
    else:
        return "", f"no start time in {foreign.path.name}: the time of import"
    return (origin + timedelta(seconds=t0)).isoformat(), f"{said} + {t0:.6g} s"


def _spans(picked: Mapping[str, ForeignChannel]) -> str:
    return ", ".join(f"{k} {c.time[0]:.6g}–{c.time[-1]:.6g} s" for k, c in picked.items())


def _checked(channel: ForeignChannel, field_name: str) -> ForeignChannel:
    """The channel if its times increase without a gap and its values are finite; else one
    line naming it (`field_name`, the file's channel) and where."""
    time, values = channel.time, channel.values
    where = f"{field_name}: channel {channel.name!r}"
    if len(time) < 2:
        raise ConfigError(f"{where} has {len(time)} sample(s)")
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        raise ConfigError(f"{where} has {bad.size} NaN or infinite sample(s), the first at "
                          f"t = {time[bad[0]]:.6g} s")
    steps = np.diff(time)
    back = np.flatnonzero(~(steps > 0.0))
    if back.size:
        raise ConfigError(f"{where}: time does not increase at t = {time[back[0]]:.6g} s "
                          f"(sample {back[0] + 1})")
    period = float(np.median(steps))
    gaps = np.flatnonzero(steps > GAP_FACTOR * period)
    if gaps.size:
        first = gaps[0]
        raise ConfigError(f"{where} has {gaps.size} gap(s): the first {steps[first]:.6g} s "
                          f"long at t = {time[first]:.6g} s (sample period {period:.6g} s); "
                          "gaps are refused (cut the file or map another channel)")
    return channel


def _factor(side: Mapping[str, Any], key: str, channel: ForeignChannel,
            quantities: tuple[str, ...]) -> float:
    """SI factor of a mapped channel: [scale] × the unit's factor; the unit ([units], else the
    file's) must be known and measure one of `quantities`."""
    unit = _unit(side, key, channel)
    where = f"mapping.units.{key}"
    if not unit:
        raise ConfigError(f"{where}: channel {channel.name!r} has no unit in the file; give "
                          f"it (one of {', '.join(_units_of(quantities))})")
    if unit not in SI_UNITS:
        source = "" if key in side["units"] else f" (the file's unit of {channel.name!r})"
        raise ConfigError(f"{where}: unknown unit {unit!r}{source}; give the unit after "
                          f"[scale] (one of {', '.join(_units_of(quantities))})")
    factor, quantity = SI_UNITS[unit]
    if quantity not in quantities:
        raise ConfigError(f"{where}: {unit!r} is a unit of {quantity}, the run's {key} is a "
                          f"{' or '.join(quantities)} (one of {', '.join(_units_of(quantities))})")
    return float(side["scale"].get(key, 1.0)) * factor


def _unit(side: Mapping[str, Any], key: str, channel: ForeignChannel) -> str:
    """A mapped channel's unit: the mapping's [units], else the file's."""
    return side["units"].get(key) or channel.unit.strip()


def _quantity(side: Mapping[str, Any], key: str, channel: ForeignChannel) -> str:
    """What a mapped channel's unit measures (its unit checked known by `_factor`)."""
    return SI_UNITS[_unit(side, key, channel)][1]


def _units_of(quantities: tuple[str, ...]) -> list[str]:
    return [u for u, (_, q) in SI_UNITS.items() if q in quantities]


def _on_base(channel: ForeignChannel, base: np.ndarray, rate: float) -> tuple[np.ndarray, str]:
    """The channel's values at the base's times and how they were got: the samples themselves
    (same rate, on the grid: bit-exact), linear interpolation (slower), or a zero-phase
    low-pass below the base's Nyquist frequency, then interpolation (faster)."""
    time, values = channel.time, channel.values
    own = channel.rate_hz
    tolerance = ON_GRID / rate
    if abs(own - rate) <= ON_GRID * rate:
        start = int(np.searchsorted(time, base[0] - tolerance))
        stop = start + len(base)
        if stop <= len(time) and np.all(np.abs(time[start:stop] - base) <= tolerance * 1e3):
            return values[start:stop].copy(), "none (on the time base)"
    if own <= rate * (1.0 + ON_GRID):
        return np.interp(base, time, values), f"linear interpolation from {own:.6g} Hz"
    ratio = Fraction(rate / own).limit_denominator(1000)  # up / down
    if abs(float(ratio) - rate / own) <= ON_GRID * rate / own:
        up, down = ratio.numerator, ratio.denominator
        filtered = scipy.signal.resample_poly(values, up, down)  # Kaiser FIR, delay removed
        times = time[0] + np.arange(len(filtered)) * (down / (up * own))
        return np.interp(base, times, filtered), \
            f"polyphase FIR resampling by {up}/{down} from {own:.6g} Hz"
    sos = scipy.signal.butter(8, 0.4 * rate, fs=own, output="sos")
    filtered = scipy.signal.sosfiltfilt(sos, values)
    return np.interp(base, time, filtered), \
        f"zero-phase low-pass at {0.4 * rate:.6g} Hz, interpolated from {own:.6g} Hz"


def _stream(foreign: ForeignFile, name: str, table: Mapping[str, str], side: Mapping[str, Any],
            t0: float, t_end: float, rate: float, notes: dict[str, Any]
            ) -> tuple[StreamSpec, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """A stream: its channels (which must share one clock), the samples inside the run's
    span, each with the bus cycle it falls in and its counter."""
    picked = {key: _checked(foreign.channel(src, f"mapping.streams.{name}.{key}"),
                            f"mapping.streams.{name}.{key}") for key, src in table.items()}
    first = next(iter(picked.values()))
    for key, channel in picked.items():
        if len(channel.time) != len(first.time) or not np.array_equal(channel.time, first.time):
            raise ConfigError(f"mapping.streams.{name}.{key}: channel {channel.name!r} is not "
                              f"sampled with {first.name!r} (a stream's channels share one "
                              "clock; map it as its own stream)")
    period = 1.0 / rate
    inside = (first.time >= t0 - ON_GRID * period) & (first.time < t_end + period)
    cycle = np.floor((first.time[inside] - t0) / period + ON_GRID).astype(np.int64)
    sequence = np.flatnonzero(inside).astype(np.int64)
    values, units = {}, {}
    for key, channel in picked.items():
        quantities = next((q for part, q in STREAM_QUANTITIES.items() if part in key),
                          tuple({q for _, q in SI_UNITS.values()}))
        factor = _factor(side, key, channel, quantities)
        values[key] = channel.values[inside] * factor
        units[key] = SI_UNIT_OF.get(_quantity(side, key, channel), "")
        notes[f"{name}.{key}"] = {"file_channel": channel.name, "file_unit": channel.unit,
                                  "rate_Hz": channel.rate_hz, "resampled": "none (a stream)"}
    spec = StreamSpec(tuple(picked), units, first.rate_hz)
    return spec, cycle, sequence, values


def _segments(side: Mapping[str, Any], n: int, rate: float) -> list[tuple[int, str]]:
    """The segment events: (cycle, JSON text as the runner writes it: label, kind, info)."""
    tables = side["segments"] or [{"label": "imported", "kind": side["segment_kind"],
                                   "start_s": 0.0, "stop_s": math.inf, "info": {}}]
    events, end = [], 0
    for i, seg in enumerate(sorted(tables, key=lambda s: s["start_s"])):
        start = int(round(seg["start_s"] * rate))
        if start >= n:
            raise ConfigError(f"mapping.segments[{i}].start_s: {seg['start_s']:g} s lies after "
                              f"the run's {(n - 1) / rate:.6g} s")
        if events and start < end:
            raise ConfigError(f"mapping.segments[{i}].start_s: overlaps the segment before")
        if not seg["stop_s"] > seg["start_s"]:
            raise ConfigError(f"mapping.segments[{i}].stop_s: {seg['stop_s']:g} s is not after "
                              f"its start_s {seg['start_s']:g} s")
        if events and start > end:  # a hole between two segments: a segment of its own
            events.append((end, json.dumps({"label": "between", "kind": "settle"})))
        text = json.dumps({"label": seg["label"] or f"segment {i + 1}", "kind": seg["kind"],
                           **seg["info"]})
        events.append((start, text))
        end = min(n, int(round(seg["stop_s"] * rate)) if math.isfinite(seg["stop_s"]) else n)
    if end < n:
        events.append((end, json.dumps({"label": "after", "kind": "settle"})))
    return events


def write_recording(run: ImportedRun, path: str | Path, run_id: str = "",
                    recorder: Mapping[str, str] | None = None) -> Path:
    """Write `run` as a feedbench recording (the `Recorder`'s HDF5 layout), status
    ``complete``, with the bench and host that import it (`recorder`:
    `Catalog.recorder_names`); returns the path."""
    path = Path(path)
    names = tuple(run.channels)
    metadata = {"experiment": run.experiment, "config": run.config,
                "run_id": run_id or path.stem, **run.metadata,
                "imported_name": run.name, **(recorder or {})}
    if run.controller:
        metadata["controller"] = run.controller
    specs = {name: spec for name, (spec, *_rest) in run.streams.items()}
    cycles = np.arange(run.n_samples, dtype=np.int64)
    with Recorder(path, names, run.units, metadata, streams=specs) as recorder:
        events = iter(run.segments)
        pending = next(events, None)
        start = 0
        while pending is not None:
            cycle, text = pending
            if cycle > start:
                recorder.append_block(cycles[start:cycle],
                                      np.column_stack([run.channels[c][start:cycle]
                                                       for c in names]))
                start = cycle
            recorder.event(cycle, "segment", text)
            pending = next(events, None)
        recorder.append_block(cycles[start:], np.column_stack([run.channels[c][start:]
                                                               for c in names]))
        for name, (spec, cycle, sequence, values) in run.streams.items():
            recorder.append_stream(name, cycle, sequence,
                                   np.column_stack([values[c] for c in spec.channels]))
    with h5py.File(path, "r+") as file:  # the recording's own times; the import's apart
        imported_at = str(file.attrs["started_at"])
        started, stopped = recorded_times(run, imported_at)
        file.attrs.update(started_at=started, stopped_at=stopped,
                          imported_at=to_json(imported_at))
    return path


def recorded_times(run: ImportedRun, imported_at: str) -> tuple[str, str]:
    """The start and end (ISO 8601 UTC) of what `run` recorded: from its file's start time
    (`_started`) over its samples; without one, from `imported_at` on."""
    started = run.metadata.get("source_started_at") or imported_at
    stopped = datetime.fromisoformat(started) + timedelta(seconds=run.n_samples * run.cycle_s)
    return started, stopped.isoformat()


def _versions() -> dict[str, str | None]:
    """The versions of the libraries that read the file (the recorder adds its own)."""
    from importlib import metadata as importlib_metadata

    found: dict[str, str | None] = {}
    for name in ("asammdf", "npTDMS"):
        try:
            found[name] = importlib_metadata.version(name)
        except importlib_metadata.PackageNotFoundError:
            found[name] = None
    return found


def import_recording(run: ImportedRun, directory: str | Path, catalog: Any,
                     params: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Write `run` as a recording in `directory` under a new run id of `catalog`
    (`daq.catalog.Catalog`) and register it there as complete, so that it is listed, reported
    and analysed like a measured run; returns its row (id, file, status, n_samples)."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    run_id = catalog.new_run_id(run.experiment)
    path = directory / f"{run_id}.h5"
    started, stopped = recorded_times(run, utc_now_iso())
    catalog.add(run_id, run.experiment, str(path), dict(params or {}), started_at=started)
    try:
        write_recording(run, path, run_id, catalog.recorder_names())
    except BaseException as exc:
        catalog.finish(run_id, "aborted", f"import failed: {exc}", 0)
        raise
    catalog.finish(run_id, "complete", "", run.n_samples, stopped_at=stopped)
    return {"id": run_id, "file": str(path), "status": "complete", "reason": "",
            "started_at": started, "stopped_at": stopped,
            "n_samples": run.n_samples, "experiment": run.experiment,
            "rate_Hz": 1.0 / run.cycle_s,
            "channels": {k: v.get("resampled", "") for k, v in
                         run.metadata["import_channels"].items()}}


@contextmanager
def imported_copy(source: str | Path, mapping: str | Path | None = None) -> Iterator[Path]:
    """A foreign file as a feedbench recording in a temporary directory (not catalogued),
    for `feedbench analyze` and `report` on the file itself; removed afterwards."""
    run = load_run(source, mapping)
    with tempfile.TemporaryDirectory(prefix="feedbench-import-") as directory:
        yield write_recording(run, Path(directory) / f"{Path(source).stem}.h5",
                              Path(source).stem)
