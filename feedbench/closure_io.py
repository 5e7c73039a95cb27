"""Reading traces for the closure (CSV + sidecar, EMPS .mat, feedbench HDF5) and plotting
its report. The analysis itself (`feedbench.analysis.closure`) does no I/O.

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
    [units]                      # unit of each channel's column (default: SI)
    time = "s"
    position = "mm"
    force = "N"
    [controller]                 # optional: the drive's controller, keys as in a model config
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import scipy.io

from feedbench.analysis.closure.trace import Trace, lowpass
from feedbench.config import ConfigError, Field, read_toml, validate_table

UNITS_TO_SI = {
    "s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6,
    "m": 1.0, "mm": 1e-3, "um": 1e-6, "µm": 1e-6, "nm": 1e-9, "rad": 1.0,
    "deg": math.pi / 180.0, "N": 1.0, "kN": 1e3, "Nm": 1.0, "N·m": 1.0, "kNm": 1e3,
}
"""Units a sidecar may name, and their SI factor (m, rad, N, N·m, s)."""

CHANNELS = ("time", "position", "force", "reference", "excitation")

SIDECAR_SCHEMA = {
    "name": Field(str, "", "what the trace is"),
    "sample_rate_Hz": Field(float, 0.0, "sample rate when there is no time column (Hz)"),
    "force_lag_ms": Field(float, 0.0, "lag of the force samples behind the position (ms)"),
    "delimiter": Field(str, ",", "column separator"),
    "decimal": Field(str, ".", "decimal separator"),
    "columns": Field(dict, None, "channel → CSV column"),
    "units": Field(dict, {}, "channel → unit of its column"),
    "controller": Field(dict, {}, "the drive's controller, as in a model config"),
}

EMPS_GAIN_KEY = "gtau"
"""EMPS: drive gain (N/V); force = gtau · vir, the excitation pulses are in volts too."""


def sidecar_path(csv_path: str | Path) -> Path:
    """The sidecar of a CSV file: same stem, .toml."""
    return Path(csv_path).with_suffix(".toml")


def read_csv_trace(path: str | Path, sidecar: Mapping[str, Any] | None = None
                   ) -> tuple[Trace, dict[str, Any]]:
    """A CSV trace and the controller table of its sidecar (read next to it if not given)."""
    path = Path(path)
    raw = read_toml(sidecar_path(path)) if sidecar is None else dict(sidecar)
    side = validate_table(raw, SIDECAR_SCHEMA, "sidecar")
    columns = validate_table(side["columns"] or {}, {
        "time": Field(str, "", "time column (s)"),
        "position": Field(str, None, "motor position column"),
        "force": Field(str, None, "motor force or torque column"),
        "reference": Field(str, "", "commanded position column"),
        "excitation": Field(str, "", "excitation force column"),
    }, "sidecar.columns")
    for required in ("position", "force"):
        if not columns[required]:
            raise ConfigError(f"sidecar.columns.{required}: required (the CSV column holding it)")
    header, data = _read_table(path, side["delimiter"], side["decimal"])
    signals = {}
    for channel in CHANNELS:
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
    trace = Trace(time, signals["position"], signals["force"], signals.get("reference"),
                  signals.get("excitation"), side["name"] or path.name,
                  side["force_lag_ms"] * 1e-3)
    return trace, side["controller"]


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
    lines = text.splitlines()
    header = [h.strip() for h in next(csv.reader([lines[0]], delimiter=delimiter))]
    body = "\n".join(lines[1:])
    if decimal != ".":
        body = body.replace(decimal, ".")
    try:
        data = np.loadtxt(io.StringIO(body), delimiter=delimiter, ndmin=2)
    except ValueError as exc:
        raise ConfigError(f"{path}: not a numeric table after the header ({exc})") from None
    if data.shape[1] != len(header):
        raise ConfigError(f"{path}: {len(header)} header names but {data.shape[1]} columns")
    return header, data


def write_csv_trace(path: str | Path, trace: Trace, sidecar_extra: Mapping[str, Any]) -> None:
    """Write `trace` as CSV (mm, N, s) with its sidecar; `sidecar_extra` adds TOML tables
    (e.g. the controller) as ready-made text lines under their header."""
    path = Path(path)
    names = {"time": "t_s", "position": "x_mm", "force": "F_N", "reference": "x_ref_mm",
             "excitation": "excitation_N"}
    scale = {"time": 1.0, "position": 1e3, "force": 1.0, "reference": 1e3, "excitation": 1.0}
    present = [c for c in CHANNELS if getattr(trace, c) is not None]
    table = np.column_stack([getattr(trace, c) * scale[c] for c in present])
    np.savetxt(path, table, delimiter=",", header=",".join(names[c] for c in present),
               comments="", fmt="%.9g")
    units = {"time": "s", "position": "mm", "force": "N", "reference": "mm", "excitation": "N"}
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
    try:
        raw = scipy.io.loadmat(path)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    data = {k: np.asarray(v, dtype=float).ravel() for k, v in raw.items() if not k.startswith("__")}
    missing = [k for k in ("t", "qm", "qg", "vir", EMPS_GAIN_KEY) if k not in data]
    if missing:
        raise ConfigError(f"{path}: not an EMPS file (missing {', '.join(missing)})")
    gain = float(data[EMPS_GAIN_KEY][0])
    excitation = gain * data["pulses_N"] if "pulses_N" in data else None
    return Trace(data["t"], data["qm"], gain * data["vir"], data["qg"], excitation, path.name)


def read_recording(path: str | Path) -> Trace:
    """A feedbench HDF5 recording (the runner's channels) as a trace.

    The drive's force actual is its force averaged over each cycle (what the simulated
    drive publishes), so the force samples lag the position samples by half a cycle.
    """
    from feedbench.daq.recording import open_recording

    recording = open_recording(path)
    channels = recording.channels
    cycle = float(recording.metadata.get("cycle_s", 1e-3))
    return Trace(recording.cycle * cycle, channels["position"], channels["force"],
                 channels.get("x_ref"), channels.get("force_offset"), Path(path).name,
                 0.5 * cycle)


def read_trace(path: str | Path) -> tuple[Trace, dict[str, Any]]:
    """Any supported trace by its suffix (.csv, .mat, .h5), with the controller table it
    carries (CSV sidecars only; empty otherwise)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".csv":
        return read_csv_trace(path)
    if suffix == ".mat":
        return read_emps(path), {}
    if suffix in (".h5", ".hdf5"):
        return read_recording(path), {}
    raise ConfigError(f"{path}: unknown trace format {suffix!r} (.csv + .toml sidecar, .mat, .h5)")


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
    ax.set_ylabel("force residual (N)")
    ax.set_title(f"{report.name}\nheld-out residual, {report.holdout_source}", fontsize=10)
    ax.legend(markerscale=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


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
    band = (frf.f > 0) & (frf.f <= report.bandwidth)
    fig, (mag, phase) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    for row, label in enumerate(("measured", "model before", "model after")):
        mag.semilogy(frf.f[band], np.abs(frf.H1[row, band]), label=label)
        phase.plot(frf.f[band], np.degrees(np.angle(frf.H1[row, band])), label=label)
    mag.set_ylabel("|v / excitation| (m/(N·s))")
    phase.set_ylabel("phase (deg)")
    phase.set_xlabel("frequency (Hz)")
    mag.legend()
    mag.set_title(f"{report.name}\nFRF velocity / excitation, {report.holdout_source}",
                  fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
