"""Reading traces for the closure (CSV + sidecar, EMPS and KUKA .mat, feedbench HDF5) and
plotting its report. The analysis itself (`feedbench.analysis.closure`) does no I/O.

CSV + sidecar: a header row of channel names, one row per sample, a time column or a sample
rate; the sidecar (TOML, same stem) says which column is which channel and its unit:

    name = "X axis, reversal test"
    sample_rate_Hz = 1000.0      # used when there is no time column
    force_lag_ms = 0.0           # force samples lag the position samples by this much
    delimiter = ","              # ";" for many CNC scope exports
    decimal = "."                # "," for a decimal comma
    [columns]                    # channel = CSV column; position and force are required
    time = "t"
    position = "x_mm"
    force = "F_N"
    reference = "x_ref_mm"       # optional: commanded position (needed for the replay)
    excitation = "exc_N"         # optional: force added to the controller's output
    external_force = "F_ext_N"   # optional: known force the motor works against (gravity…)
    tip_acceleration = "a_tip"   # optional: load-side acceleration (m/s², unit "m/s2")
    [units]                      # unit of each channel's column (default: SI)
    time = "s"
    position = "mm"              # an angle (rad, deg): a rotary axis (force in N·m)
    force = "N"
    [controller]                 # optional: the drive's controller, keys as in a model config
    [sampling]                   # optional: how the channels were sampled (declared, never
    cycle_ms = 1.0               #   found): the drive's cycle (default: the sample period)
    force = "cycle_mean"         # "instantaneous" (default) or the mean over the cycle that
                                 #   ends at the time stamp (lags half a cycle)
    force_is = "command"         # "actual" (default) or the current command, which leads the
    current_loop_delay_ms = 0.25 #   actual force by the current loop's delay
    position = "cycle_start"     # "cycle_end" (default: at the time stamp) or latched one
    position_latch_cycles = 0.0  #   cycle earlier; or latched this many cycles early

The sampling conventions add up to one lag of the force behind the position (with
`force_lag_ms`), which the base model applies exactly: a sub-cycle skew that is declared is
not a finding; one that is not is found as a timing finding (`delay`), never as a gain.
"""

from __future__ import annotations

import csv
import io
import math
import struct
import zlib
from pathlib import Path
from typing import Any, Callable, Mapping, TypeVar

import numpy as np
import scipy.io
import scipy.signal

from feedbench.analysis.closure.trace import SIGNALS, Trace, lowpass
from feedbench.analysis.closure.units import axis_unit
from feedbench.config import (
    ConfigError, Field, non_negative, one_of, read_toml, validate_table,
)
from feedbench.units import SI_UNITS, UNITS_TO_SI  # the units a sidecar may name, SI factor

SIDECAR_SCHEMA = {
    "name": Field(str, "", "what the trace is"),
    "sample_rate_Hz": Field(float, 0.0, "sample rate when there is no time column (Hz)"),
    "force_lag_ms": Field(float, 0.0, "lag of the force samples behind the position (ms)"),
    "delimiter": Field(str, ",", "column separator"),
    "decimal": Field(str, ".", "decimal separator"),
    "columns": Field(dict, None, "channel → CSV column"),
    "units": Field(dict, {}, "channel → unit of its column"),
    "controller": Field(dict, {}, "the drive's controller, as in a model config"),
    "sampling": Field(dict, {}, "how each channel was sampled (cycle, mean, latch)"),
}


SAMPLING_SCHEMA = {
    "cycle_ms": Field(float, 0.0, "the drive's cycle (ms); 0: the sample period",
                      non_negative),
    "force": Field(str, "instantaneous", "instantaneous, or cycle_mean (the mean over the "
                   "cycle ending at the time stamp)", one_of("instantaneous", "cycle_mean")),
    "force_is": Field(str, "actual", "actual force, or the command (leads it by the current "
                      "loop's delay)", one_of("actual", "command")),
    "current_loop_delay_ms": Field(float, 0.0, "how long the actual force follows the "
                                   "command (ms)", non_negative),
    "position": Field(str, "cycle_end", "cycle_end (at the time stamp) or cycle_start (one "
                      "cycle earlier)", one_of("cycle_end", "cycle_start")),
    "position_latch_cycles": Field(float, 0.0, "the position is latched this many cycles "
                                   "before its time stamp (besides cycle_start)"),
}


def declared_force_lag(sampling: Mapping[str, Any], sample_period: float) -> float:
    """Lag (s) of the force samples behind the position samples that the sidecar's
    [sampling] conventions declare: + half a cycle for a cycle mean, − the current loop's
    delay for a command, − the position's latch (a cycle for cycle_start, plus
    position_latch_cycles): a position latched early is older than its time stamp, so the
    force leads it."""
    if not sampling:
        return 0.0
    side = validate_table(sampling, SAMPLING_SCHEMA, "sidecar.sampling")
    cycle = side["cycle_ms"] * 1e-3 or sample_period
    latch = side["position_latch_cycles"] + (1.0 if side["position"] == "cycle_start" else 0.0)
    mean = 0.5 if side["force"] == "cycle_mean" else 0.0
    command = side["current_loop_delay_ms"] * 1e-3 if side["force_is"] == "command" else 0.0
    return (mean - latch) * cycle - command

T = TypeVar("T")

MAT_MATRIX, MAT_COMPRESSED = 14, 15
MAT_V5_TYPES = frozenset({1, 2, 3, 4, 5, 6, 7, 9, 12, 13, MAT_MATRIX, MAT_COMPRESSED, 16, 17, 18})
"""The data-element types of a MATLAB v5 file (miINT8 … miUTF32)."""
MAT_NUMERIC_CLASSES = frozenset(range(6, 16))  # mxDOUBLE … mxUINT64
MAT_CELL, MAT_STRUCT, MAT_CHAR = 1, 2, 4
MAT_COMPLEX = 0x800

EMPS_GAIN_KEY = "gtau"
"""EMPS: drive gain (N/V); force = gtau · vir, the excitation pulses are in volts too."""


def sidecar_path(csv_path: str | Path) -> Path:
    """The sidecar of a CSV file: same stem, .toml."""
    return Path(csv_path).with_suffix(".toml")


def read_csv_trace(path: str | Path, sidecar: Mapping[str, Any] | None = None
                   ) -> tuple[Trace, dict[str, Any]]:
    """A CSV trace and the controller table of its sidecar (read next to it if not given)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such file")
    raw = read_toml(sidecar_path(path)) if sidecar is None else dict(sidecar)
    side = validate_table(raw, SIDECAR_SCHEMA, "sidecar")
    columns = validate_table(side["columns"] or {}, {
        "time": Field(str, "", "time column (s)"),
        "position": Field(str, None, "motor position column"),
        "force": Field(str, None, "motor force or torque column"),
        "reference": Field(str, "", "commanded position column"),
        "excitation": Field(str, "", "excitation force column"),
        "external_force": Field(str, "", "known external force column"),
        "tip_acceleration": Field(str, "", "load-side acceleration column"),
    }, "sidecar.columns")
    for required in ("position", "force"):
        if not columns[required]:
            raise ConfigError(f"sidecar.columns.{required}: required (the CSV column holding it)")
    header, data = _read_table(path, side["delimiter"], side["decimal"])
    signals = {}
    for channel in SIGNALS:
        name = columns[channel]
        if not name:
            continue
        if name not in header:
            raise ConfigError(f"sidecar.columns.{channel}: no column {name!r} in {path.name} "
                              f"(columns: {', '.join(header)})")
        signals[channel] = data[:, header.index(name)] * _unit(side["units"], channel)
    time = signals.get("time")
    if time is None:
        if not side["sample_rate_Hz"] > 0.0:
            raise ConfigError("sidecar.sample_rate_Hz: required when there is no time column")
        time = np.arange(data.shape[0]) / side["sample_rate_Hz"]
    trace = _trace(path, time, signals["position"], signals["force"], signals.get("reference"),
                   signals.get("excitation"), side["name"] or path.name,
                   side["force_lag_ms"] * 1e-3
                   + declared_force_lag(side["sampling"], float(np.median(np.diff(time)))),
                   signals.get("external_force"),
                   signals.get("tip_acceleration"), rotary=_rotary(side["units"]))
    return trace, side["controller"]


def _rotary(units: Mapping[str, Any]) -> bool:
    """Whether a sidecar's position unit is an angle (rad, deg, rev): a rotary axis."""
    return SI_UNITS.get(units.get("position", ""), (1.0, "length"))[1] == "angle"


def _trace(path: Path, *args: Any, **options: Any) -> Trace:
    """A Trace of what `path` holds; a check of the Trace failing (too few samples, NaN,
    uneven time) is a ConfigError naming the file."""
    try:
        return Trace(*args, **options)
    except ValueError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def _parsed(path: Path, kind: str, read: Callable[[], T]) -> T:
    """`read()`; a variable of a .mat file missing or of another type or shape is a
    ConfigError "<path>: not <kind> (<what failed>)"."""
    try:
        return read()
    except ConfigError:
        raise
    except (AttributeError, IndexError, KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"{path}: not {kind} ({type(exc).__name__}: {exc})") from None


def _unit(units: Mapping[str, Any], channel: str) -> float:
    unit = units.get(channel, "s" if channel == "time" else "")
    if unit == "":
        return 1.0
    if unit not in UNITS_TO_SI:
        raise ConfigError(f"sidecar.units.{channel}: unknown unit {unit!r} "
                          f"(known: {', '.join(UNITS_TO_SI)})")
    return UNITS_TO_SI[unit]


def _read_table(path: Path, delimiter: str, decimal: str) -> tuple[list[str], np.ndarray]:
    """Header names and the numeric rows of a CSV file."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not a text file ({exc})") from None
    lines = text.splitlines()
    if len(lines) < 2:
        raise ConfigError(f"{path}: no data rows (a header row of column names, then one row "
                          f"per sample)")
    header = [h.strip() for h in next(csv.reader([lines[0]], delimiter=delimiter))]
    body = "\n".join(lines[1:])
    if decimal != ".":
        body = body.replace(decimal, ".")
    try:
        data = np.loadtxt(io.StringIO(body), delimiter=delimiter, ndmin=2)
    except ValueError:
        raise ConfigError(f"{path}: {_bad_row(body.splitlines(), delimiter, len(header))}"
                          ) from None
    if data.shape[1] != len(header):
        raise ConfigError(f"{path}: {len(header)} header names but {data.shape[1]} columns")
    return header, data


def _bad_row(rows: list[str], delimiter: str, width: int) -> str:
    """What is wrong with the first row of a CSV body that is not a numeric table."""
    for number, row in enumerate(rows, 2):
        cells = row.split(delimiter)
        if len(cells) != width:
            return f"row {number} has {len(cells)} values, the header {width} names"
        for cell in cells:
            try:
                float(cell)
            except ValueError:
                return f"row {number}: {cell.strip()!r} is not a number"
    return "not a numeric table after the header"


def write_csv_trace(path: str | Path, trace: Trace, sidecar_extra: Mapping[str, Any]) -> None:
    """Write `trace` as CSV (mm, N, s; a rotary axis's position in rad, its forces in N·m)
    with its sidecar; `sidecar_extra` adds TOML tables (e.g. the controller) as ready-made
    text lines under their header."""
    path = Path(path)
    length, to_length = ("rad", 1.0) if trace.rotary else ("mm", 1e3)
    force = "Nm" if trace.rotary else "N"
    names = {"time": "t_s", "position": f"x_{length}", "force": f"F_{force}",
             "reference": f"x_ref_{length}", "excitation": f"excitation_{force}",
             "external_force": f"external_{force}", "tip_acceleration": "a_tip_m_s2"}
    scale = {"time": 1.0, "position": to_length, "force": 1.0, "reference": to_length,
             "excitation": 1.0, "external_force": 1.0, "tip_acceleration": 1.0}
    present = [c for c in SIGNALS if getattr(trace, c) is not None]
    table = np.column_stack([getattr(trace, c) * scale[c] for c in present])
    np.savetxt(path, table, delimiter=",", header=",".join(names[c] for c in present),
               comments="", fmt="%.9g")
    units = {"time": "s", "position": length, "force": force, "reference": length,
             "excitation": force, "external_force": force, "tip_acceleration": "m/s2"}
    lines = [f'name = "{trace.name}"', f"force_lag_ms = {trace.force_lag * 1e3:g}", "",
             "[columns]"] + [f'{c} = "{names[c]}"' for c in present] + ["", "[units]"]
    lines += [f'{c} = "{units[c]}"' for c in present]
    for table_name, body in sidecar_extra.items():
        lines += ["", f"[{table_name}]"] + [f"{k} = {_toml_value(v)}" for k, v in body.items()]
    sidecar_path(path).write_text("\n".join(lines) + "\n")


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    return f"{value:g}"


def read_emps(path: str | Path) -> Trace:
    """An EMPS benchmark file (`DATA_EMPS.mat`, `DATA_EMPS_PULSES.mat`) as a trace.

    force = gtau · vir (N); the excitation of the PULSES file is gtau · pulses_N: the
    recorded vir jumps by 5 V at every pulse edge, so the pulses are volts added to the
    controller's output (5 V ≈ 176 N), whatever their name says.
    """
    path = Path(path)
    raw = _load_mat(path)
    return _parsed(path, "an EMPS file", lambda: _emps_trace(path, raw))


def _emps_trace(path: Path, raw: dict[str, Any]) -> Trace:
    data = {k: np.asarray(v, dtype=float).ravel() for k, v in raw.items() if not k.startswith("__")}
    missing = [k for k in ("t", "qm", "qg", "vir", EMPS_GAIN_KEY) if k not in data]
    if missing:
        raise ConfigError(f"{path}: not an EMPS file (missing {', '.join(missing)})")
    gain = float(data[EMPS_GAIN_KEY][0])
    excitation = gain * data["pulses_N"] if "pulses_N" in data else None
    return _trace(path, data["t"], data["qm"], gain * data["vir"], data["qg"], excitation,
                  path.name)


def read_kuka(path: str | Path, axis: int) -> Trace:
    """One joint (1–6) of a KUKA robot recording (Weigand, Robot_Identification: struct
    `rec`, `para`, the torques precomputed along the trajectory) as a link-side trace.

    position and reference: the motor encoder and the reference, both in link degrees
    (`act_pos_mot_deg`, `ref_pos_deg`), as rad; force: the motor torque times the gear
    ratio u (`act_torque_abs_nm` · `para.u`, link-side N·m, the unit of `para`'s friction);
    external force: the link-side torques the authors computed along the reference —
    `m_all` · q̈_r (the joint's own link inertia), `tau_a_all` (inertia coupling from the
    other joints), `tau_c_all` (Coriolis and centrifugal), `tau_g_all` + `tau_g_init`
    (gravity with the counterbalance; the recorded series starts at 0). What is left for the
    model: the motor's inertia J_mr u² and the friction of `para`.
    """
    path = Path(path)
    raw = _load_mat(path, squeeze_me=True, struct_as_record=False)
    return _parsed(path, "a KUKA recording", lambda: _kuka_trace(path, raw, axis))


def _kuka_trace(path: Path, raw: dict[str, Any], axis: int) -> Trace:
    rec, para = raw["rec"], raw["para"]
    count = int(raw["n_axis"])
    if not 1 <= axis <= count:
        raise ConfigError(f"{path}: axis must lie in 1–{count} (got {axis})")
    i, ratio = axis - 1, float(para.u[axis - 1])
    deg = math.pi / 180.0
    external = (raw["m_all"][i] * raw["ref_kin"].phi_r_all_d2[:, i] + raw["tau_a_all"][i]
                + raw["tau_c_all"][i] + raw["tau_g_all"][i] + raw["tau_g_init"][i])
    return _trace(path, rec.time_cont, deg * rec.act_pos_mot_deg[i],
                  ratio * rec.act_torque_abs_nm[i], deg * rec.ref_pos_deg[i], None,
                  f"{path.name} axis {axis}", external_force=external, rotary=True)


def kuka_parameters(path: str | Path, axis: int) -> dict[str, float]:
    """The authors' own parameters of one joint (`para`), link side: friction f_coul,
    f_vis, f_asym, f_a (N·m, N·m·s/rad, N·m, N·m), the tanh constants f_b and s_f_ff
    (s/rad), stiffness c_rad_ff (N·m/rad), backlash q_back (rad), gear ratio u, motor
    inertia J_mr (kg·m², motor side)."""
    para = _load_mat(Path(path), squeeze_me=True, struct_as_record=False)["para"]
    keys = ("f_coul", "f_vis", "f_asym", "f_a", "f_b", "s_f_ff", "c_rad_ff", "q_back", "u",
            "J_mr")
    return {k: float(getattr(para, k)[axis - 1]) for k in keys}


def _load_mat(path: Path, **options: Any) -> dict[str, Any]:
    """The variables of a MATLAB file; a missing or unreadable file is a one-line
    ConfigError (a v5 file is checked by `_mat_v5_problem` first)."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    header = data[124:128].ljust(4, b"\x00")  # version, byte order (as scipy reads them)
    if header[1 if header[2:3] == b"I" else 0] == 1:  # major version 1: a v5 file
        problem = _mat_v5_problem(data[128:], "<" if header[2:] == b"IM" else ">")
        if problem:
            raise ConfigError(f"{path}: not a readable MATLAB file ({problem})")
    try:
        return scipy.io.loadmat(io.BytesIO(data), **options)
    except Exception as exc:  # scipy raises many kinds for a damaged or foreign file
        raise ConfigError(f"{path}: not a readable MATLAB file ({type(exc).__name__}: "
                          f"{exc})") from None


def _mat_v5_problem(elements: bytes, order: str) -> str | None:
    """What is wrong with the data elements of a MATLAB v5 file (`order`: struct byte
    order), looking into matrices and compressed elements; None if every tag is sound.
    scipy's reader trusts the tags and crashes the process (SIGSEGV/SIGBUS) on a data
    element of an unknown type."""
    pos = 0
    while pos < len(elements):
        if pos + 8 > len(elements):
            return f"a data element tag cut after {len(elements) - pos} bytes"
        mdtype, nbytes = struct.unpack_from(order + "II", elements, pos)
        if mdtype >> 16:  # small data element: size and type in 4 bytes, data in the next 4
            mdtype, nbytes, start, step = mdtype & 0xFFFF, mdtype >> 16, pos + 4, 8
            if nbytes > 4:
                return f"a small data element of {nbytes} bytes (at most 4)"
        else:
            start = pos + 8
            step = 8 + nbytes + (0 if mdtype == MAT_COMPRESSED else -nbytes % 8)
        body = elements[start:start + nbytes]
        if mdtype not in MAT_V5_TYPES:
            return f"a data element of unknown type {mdtype}"
        if len(body) < nbytes:
            return f"a data element of {nbytes} bytes with {len(body)} left in the file"
        if mdtype == MAT_COMPRESSED:
            try:
                body = zlib.decompress(body)
            except zlib.error as exc:
                return f"a compressed element that does not decompress ({exc})"
        if mdtype in (MAT_MATRIX, MAT_COMPRESSED) and (problem := _mat_v5_problem(body, order)
                                                       or _matrix_problem(mdtype, body, order)):
            return problem
        pos += step
    return None


def _matrix_problem(mdtype: int, body: bytes, order: str) -> str | None:
    """A matrix whose elements are fewer than its class needs: flags, dimensions, name, then
    a numeric or char array's real (and if complex imaginary) part, a cell's n cells, a
    struct's field-name length, names and n × fields values (scipy reads them blindly)."""
    if mdtype != MAT_MATRIX:
        return None
    elements = _elements(body, order)
    if len(elements) < 3 or len(elements[0]) < 4:
        return "a matrix without its flags, dimensions and name"
    flags = struct.unpack_from(order + "I", elements[0])[0]
    cells = math.prod(struct.unpack(order + f"{len(elements[1]) // 4}i",
                                    elements[1][:len(elements[1]) // 4 * 4]))
    kind = flags & 0xFF
    if kind in MAT_NUMERIC_CLASSES or kind == MAT_CHAR:
        needed = 4 + bool(flags & MAT_COMPLEX)
    elif kind == MAT_CELL:
        needed = 3 + cells
    elif kind == MAT_STRUCT and len(elements) >= 5 and len(elements[3]) >= 4:
        name_length = struct.unpack_from(order + "i", elements[3])[0]
        needed = 5 + cells * (len(elements[4]) // name_length if name_length > 0 else 0)
    else:
        return None
    if len(elements) < needed:
        return f"a matrix of class {kind} with {len(elements)} of its {needed} elements"
    return None


def _elements(elements: bytes, order: str) -> list[bytes]:
    """The data of the data elements that follow each other in `elements` (tags checked
    before by `_mat_v5_problem`)."""
    found, pos = [], 0
    while pos + 8 <= len(elements):
        mdtype, nbytes = struct.unpack_from(order + "II", elements, pos)
        if mdtype >> 16:
            found.append(elements[pos + 4:pos + 4 + (mdtype >> 16)])
            pos += 8
        else:
            found.append(elements[pos + 8:pos + 8 + nbytes])
            pos += 8 + nbytes + -nbytes % 8
    return found


def read_mat(path: str | Path, axis: int | None = None) -> Trace:
    """A .mat trace: a KUKA robot recording (needs `axis`) or an EMPS benchmark file."""
    if {"rec", "para"} <= set(_load_mat(Path(path), variable_names=("rec", "para"))):
        if axis is None:
            raise ConfigError(f"{path}: a multi-axis KUKA recording; give the axis (--axis 1–6)")
        return read_kuka(path, axis)
    if axis is not None:
        raise ConfigError(f"{path}: a single-axis file; --axis is for the KUKA recordings")
    return read_emps(path)


def read_recording(path: str | Path) -> Trace:
    """A feedbench HDF5 recording (the runner's channels) as a trace.

    The drive's force actual is its force averaged over each cycle (what the simulated
    drive publishes), so the force samples lag the position samples by half a cycle; an
    imported recording's lag is the one its mapping declared (`force_lag_s`, [sampling]).
    """
    from feedbench.daq.recording import open_recording

    return _recording_trace(open_recording(path))


def _recording_trace(recording: Any) -> Trace:
    """The trace of an open `daq.recording.Recording` (`read_recording`)."""
    channels, metadata = recording.channels, recording.metadata
    cycle = float(metadata.get("cycle_s", 1e-3))
    lag = 0.5 * cycle
    if "force_lag_s" in metadata:  # an imported recording: the lag its mapping declares
        lag = float(metadata["force_lag_s"]) + declared_force_lag(metadata.get("sampling", {}),
                                                                  cycle)
    return Trace(recording.cycle * cycle, channels["position"], channels["force"],
                 channels.get("x_ref"), channels.get("force_offset"), recording.path.name,
                 lag, channels.get("external_force"), channels.get("tip_acceleration"),
                 rotary=recording.rotary)


def read_foreign_trace(path: str | Path, mapping: str | Path | None = None
                       ) -> tuple[Trace, dict[str, Any]]:
    """Another DAQ system's recording (MDF4, TDMS: `daq.importers`) as a trace, with the
    controller table of its mapping (`mapping`, else the .toml beside it)."""
    from feedbench.daq.importers.mapping import load_run

    run = load_run(path, mapping)
    channels, cycle = run.channels, run.cycle_s
    lag = run.metadata["force_lag_s"] + declared_force_lag(run.metadata["sampling"], cycle)
    trace = _trace(Path(path), np.arange(run.n_samples) * cycle, channels["position"],
                   channels["force"], channels.get("x_ref"), channels.get("force_offset"),
                   run.name, lag, channels.get("external_force"),
                   channels.get("tip_acceleration"), rotary=run.units["position"] == "rad")
    return trace, run.controller


def read_trace(path: str | Path, axis: int | None = None, mapping: str | Path | None = None
               ) -> tuple[Trace, dict[str, Any]]:
    """Any supported trace by its suffix (.csv, .mat, .h5, a foreign format's: .mf4,
    .tdms…), with the controller table it carries (CSV sidecars and import mappings; empty
    otherwise); axis: the joint of a KUKA .mat file; mapping: a foreign file's."""
    from feedbench.daq.importers import is_foreign

    suffix = Path(path).suffix.lower()
    if mapping is not None and not is_foreign(path):
        raise ConfigError(f"{path}: --mapping is for the recordings of other DAQ systems "
                          "(.mf4, .tdms)")
    if is_foreign(path):
        if axis is not None:
            raise ConfigError(f"{path}: --axis is for the KUKA .mat recordings")
        return read_foreign_trace(path, mapping)
    if axis is not None and suffix != ".mat":
        raise ConfigError(f"{path}: --axis is for the KUKA .mat recordings")
    if suffix == ".csv":
        return read_csv_trace(path)
    if suffix == ".mat":
        return read_mat(path, axis), {}
    if suffix in (".h5", ".hdf5"):  # an imported run keeps its mapping's [controller]
        from feedbench.daq.recording import open_recording

        recording = open_recording(path)
        return _recording_trace(recording), dict(recording.metadata.get("controller", {}))
    raise ConfigError(f"{path}: unknown trace format {suffix!r} (.csv + .toml sidecar, .mat, .h5, "
                      ".mf4 or .tdms + .toml mapping)")


def save_plots(report: Any, directory: str | Path) -> list[Path]:
    """PNG plots of a `ClosureReport`: held-out residual before/after, and for excitation
    experiments the FRF velocity/excitation measured vs model. Returns the files."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    files = [_residual_plot(plt, report, directory / "closure_residual.png")]
    frf = _frf_plot(plt, report, directory / "closure_frf.png")
    return files + ([frf] if frf else [])


def _residual_plot(plt: Any, report: Any, path: Path) -> Path:
    time, before, after = report.held_out_residuals()
    result = report.result
    fig, ax = plt.subplots(figsize=(10, 4.5))
    ax.plot(time, before, ".", ms=1.5, label=f"before: NRMSE {result.error_before:.2%}")
    ax.plot(time, after, ".", ms=1.5,
            label=f"after (+ {', '.join(result.effects) or 'nothing'}): "
                  f"NRMSE {result.error_after:.2%}")
    ax.set_xlabel("time in the held-out data (s)")
    ax.set_ylabel(f"force residual ({axis_unit('N', report.rotary)})")
    ax.set_title(f"{report.name}\nheld-out residual, {report.holdout_source}", fontsize=10)
    ax.legend(markerscale=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


FRF_STYLES = {"measured": {"color": "k", "lw": 2.2, "alpha": 0.6},
              "model before": {"color": "C1", "lw": 1.2, "ls": "--"},
              "model after": {"color": "C2", "lw": 1.2, "ls": ":"}}
"""Measured under the models: the models' lines stay visible where they match it."""

EXCITED_DB = 20.0
"""A frequency is excited where the excitation's PSD is within this of its peak (dB)."""


def excited_band(excitation: np.ndarray, fs: float, nperseg: int,
                 bandwidth: float) -> np.ndarray:
    """Mask of the Welch frequencies (Hz) the excitation drives, within `EXCITED_DB` of its
    peak PSD, up to the closure's scoring `bandwidth` (Hz): where the FRF means something."""
    f, psd = scipy.signal.welch(excitation, fs, nperseg=nperseg)
    return (f > 0) & (f <= bandwidth) & (psd >= psd.max() * 10 ** (-EXCITED_DB / 10))


def _frf_plot(plt: Any, report: Any, path: Path) -> Path | None:
    from feedbench.analysis.frf import estimate_frf

    trace, replays = report.holdout.trace, report.replays
    if replays is None or trace.excitation is None or not np.any(trace.excitation):
        return None
    dt = 1.0 / trace.sample_rate
    window = slice(report.holdout.start, report.holdout.stop)
    velocities = np.vstack([lowpass(p, report.bandwidth, dt, 1)[window]
                            for p in (trace.position, replays[0].position, replays[1].position)])
    nperseg = int(min(velocities.shape[1] // 4, 2 ** round(math.log2(2.0 / dt))))
    frf = estimate_frf(trace.excitation[window], velocities, 1.0 / dt, nperseg)
    band = excited_band(trace.excitation[window], 1.0 / dt, nperseg, report.bandwidth)
    fig, (mag, phase) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    for row, (label, style) in enumerate(FRF_STYLES.items()):
        mag.semilogy(frf.f[band], np.abs(frf.H1[row, band]), label=label, **style)
        phase.plot(frf.f[band], np.degrees(np.angle(frf.H1[row, band])), label=label, **style)
    mag.set_ylabel(f"|v / excitation| ({axis_unit('m/(N·s)', report.rotary)})")
    phase.set_ylabel("phase (deg)")
    phase.set_xlabel("frequency (Hz)")
    mag.legend()
    mag.set_title(f"{report.name}\nFRF velocity / excitation, {report.holdout_source}",
                  fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
