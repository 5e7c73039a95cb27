"""The field's exchange formats: FRFs as Universal File Format dataset 58, time traces as CSV
with the closure's sidecar.

UFF58 (written and read by pyuff): one dataset per FRF (function type 4, complex double,
ordinate data type 6) and one per coherence (function type 6, real double) right after it,
frequency abscissa in Hz, SI units. Record 6 names the response and reference node and
direction (node 1 the motor, node 2 the tool tip; direction 1 = +X, the feed axis); records 9
and 10 give the ordinate numerator and denominator as specific data types (8 displacement,
11 velocity, 12 acceleration, 13 excitation force) with their length and force exponents and
unit labels; ID line 1 says what the FRF is, 2 the run, 3 when it was recorded, 4 the
response / reference channels, 5 the condition (feed, amplitude). An FRF on an even grid (every
FFT-based one, a stepped sine without flagged steps) is a binary 58b dataset with even
abscissa: the values are the IEEE doubles themselves (a bit-exact round trip), the abscissa
minimum and increment have record 7's 6 digits. An FRF on an uneven grid is an ASCII dataset
(12 digits; the abscissa values 6): the format's binary uneven case stores the abscissa in
single precision, which pyuff writes as doubles, so strict readers would misread it.

CSV: the recording's drive channels as the closure reads them (`closure_io.read_recording`),
written with its sidecar (`closure_io.write_csv_trace`), so `feedbench closure FILE.csv`
reads an export.
"""

from __future__ import annotations

from dataclasses import replace
from datetime import datetime
from pathlib import Path
from typing import Callable

import numpy as np
import pyuff
import scipy.signal

from feedbench.analysis.frf import convert_frf
from feedbench.analysis.modal import fit_modes
from feedbench.closure_io import read_recording, sidecar_path, write_csv_trace
from feedbench.config import ConfigError
from feedbench.daq.recording import open_recording
from feedbench.engine.family import families
from feedbench.views.frfs import Dof, ExchangeFrf

UFF_SUFFIXES = (".uff", ".unv", ".uf")
FRF, COHERENCE = 4, 6
"""UFF58 function types."""

QUANTITIES = {
    "displacement": (8, 1, 0, "m"),
    "velocity": (11, 1, 0, "m/s"),
    "acceleration": (12, 1, 0, "m/s^2"),
    "force": (13, 0, 1, "N"),
}
"""Quantity → UFF58 specific data type, length and force unit exponents, SI unit label."""

SPEC_QUANTITIES = {spec: quantity for quantity, (spec, *_) in QUANTITIES.items()} | {9: "force"}
"""UFF58 specific data type → quantity (9, reaction force, read as a force too)."""

FORMS = {"displacement": "receptance", "velocity": "mobility", "acceleration": "accelerance"}
"""Response quantity of a force-referenced FRF → its form (`analysis.frf.FRF_FORMS`)."""

UNIT_LABELS = {
    "m": 1.0, "mm": 1e-3, "um": 1e-6, "µm": 1e-6, "m/s": 1.0, "mm/s": 1e-3,
    "m/s^2": 1.0, "m/s2": 1.0, "m/s²": 1.0, "g": 9.80665, "N": 1.0, "kN": 1e3,
}
"""Unit labels read in a UFF58 file, and their SI factor."""

ENTITY_CHARS = 10
"""UFF58 record 6: entity names are at most 10 characters."""

BINARY_START, DATASET_END, HEADER_LINES = b"    -1\n    58b", b"    -1\n", 13
"""How a 58b dataset starts and ends, and its ASCII lines ("    -1", the ID line, 11 records)."""

HEADER_BYTES_FIELD = (38, 12)
"""Offset and width of the byte count in a 58b dataset's ID line: pyuff writes one value's
bytes per point there, for complex or uneven data too, so the count is set afterwards to
the bytes between the ASCII lines and the closing "    -1", as readers that trust it need."""

MAX_MODES = 6
"""`analyze` fits at most this many modes (the most prominent peaks) per FRF."""


def export_uff58(recording_path: str | Path, path: str | Path,
                 analyze: Callable[[str | Path], dict]) -> Path:
    """Write the FRFs of a run to a UFF58 file; `analyze` is its analysis step
    (`bench.analyze_file`), run only for a family with FRFs (`Experiment.has_frfs`)."""
    recording = open_recording(recording_path)
    with_frfs = [name for name, cls in families().items() if cls.has_frfs]
    if recording.experiment not in with_frfs:
        raise ConfigError(f"{recording_path}: a {recording.experiment} run has no FRF to "
                          f"export (FRFs come from {', '.join(with_frfs)})")
    experiment = families()[recording.experiment]
    frfs = list(experiment.frfs(analyze(recording_path), recording))
    started = datetime.fromisoformat(recording.started_at)
    return write_uff58(path, frfs, Path(recording_path).stem,
                       started.strftime("%d-%b-%y %H:%M:%S"))


def export_csv(recording_path: str | Path, path: str | Path) -> Path:
    """Write a recording's drive channels (time s, position and reference mm, force and
    excitation N) as CSV with the sidecar `closure_io.read_csv_trace` reads; returns path."""
    path = Path(path)
    if path.suffix.lower() != ".csv":
        raise ConfigError(f"{path}: a CSV export must end in .csv (its sidecar is "
                          f"{sidecar_path(path.with_suffix('.csv')).name})")
    _make_folder(path)
    write_csv_trace(path, read_recording(recording_path), {})
    return path


def _make_folder(path: Path) -> None:
    """The folder an export is written into; a ConfigError if a file stands in its way."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise ConfigError(f"{path}: its folder {path.parent} is a file, not a folder") from None


def write_uff58(path: str | Path, frfs: list[ExchangeFrf], run: str = "NONE",
                created: str = "NONE") -> Path:
    """Write FRFs (each followed by its coherence) as binary UFF58 datasets; returns path.
    An FRF of fewer than 2 lines (e.g. a sine stream whose steps were all flagged) is left
    out: record 7 needs an increment."""
    path = Path(path)
    frfs = [frf for frf in frfs if np.size(frf.f) >= 2]
    if not frfs:
        raise ConfigError(f"{path}: no FRF of 2 or more frequency lines to write")
    _make_folder(path)
    path.unlink(missing_ok=True)
    number = 0
    for frf in frfs:
        for function, values in ((FRF, frf.H), (COHERENCE, frf.coherence)):
            if values is not None:
                number += 1
                _append_dataset(path, _dataset(frf, function, values, number, run, created))
    return path


def _dataset(frf: ExchangeFrf, function: int, values: np.ndarray, number: int, run: str,
             created: str) -> dict:
    """The pyuff dictionary of one FRF or coherence dataset: binary on an even grid."""
    even = _is_even(frf.f)
    numerator = _axis("ordinate", frf.response.quantity if function == FRF else "")
    denominator = _axis("orddenom", frf.reference.quantity if function == FRF else "")
    return {
        "type": 58, "binary": int(even), "func_type": function, "func_id": number,
        "id1": _id_line(frf.description + (" coherence" if function == COHERENCE else "")),
        "id2": _id_line(run), "id3": _id_line(created),
        "id4": _id_line(f"{frf.response.channel} / {frf.reference.channel}"),
        "id5": _id_line(frf.condition), "load_case_id": 0,
        "rsp_ent_name": frf.response.entity[:ENTITY_CHARS], "rsp_node": frf.response.node,
        "rsp_dir": frf.response.direction,
        "ref_ent_name": frf.reference.entity[:ENTITY_CHARS], "ref_node": frf.reference.node,
        "ref_dir": frf.reference.direction,
        "abscissa_spacing": int(even), "abscissa_spec_data_type": 18,
        "abscissa_axis_lab": "frequency", "abscissa_axis_units_lab": "Hz",
        **numerator, **denominator,
        "data": np.asarray(values, dtype=complex if function == FRF else float),
        "x": np.asarray(frf.f, dtype=float),
    }


def _axis(record: str, quantity: str) -> dict:
    """Record 9 ("ordinate") or 10 ("orddenom") fields of a quantity ("": dimensionless)."""
    spec, length, force, unit = QUANTITIES.get(quantity, (0, 0, 0, "NONE"))
    return {f"{record}_spec_data_type": spec, f"{record}_len_unit_exp": length,
            f"{record}_force_unit_exp": force, f"{record}_axis_lab": quantity or "NONE",
            f"{record}_axis_units_lab": unit}


def _id_line(text: str) -> str:
    """An ID line: at most 80 characters, "NONE" when empty (the format's rule)."""
    return text[:80] or "NONE"


def _append_dataset(path: Path, dataset: dict) -> None:
    """Append one dataset; a binary one gets its header's byte count (HEADER_BYTES_FIELD)."""
    start = path.stat().st_size if path.exists() else 0
    try:
        pyuff.UFF(str(path)).write_sets(dataset, mode="add")
    except Exception as exc:  # pyuff raises bare Exceptions, an OSError among them
        raise ConfigError(f"{path}: cannot write ({exc})") from None
    if dataset["binary"]:
        _set_byte_count(path, start)


def _set_byte_count(path: Path, start: int) -> None:
    """Set the byte count of the 58b dataset written from `start` to what follows its
    ASCII lines up to its closing "    -1"."""
    with path.open("r+b") as fh:
        fh.seek(start)
        block = fh.read()
        if not block.startswith(BINARY_START):
            raise ConfigError(f"{path}: pyuff {pyuff.__version__} did not write a 58b dataset")
        header = 0
        for _ in range(HEADER_LINES):
            header = block.index(b"\n", header) + 1
        offset, width = HEADER_BYTES_FIELD
        fh.seek(start + offset)
        fh.write(b"%*d" % (width, len(block) - header - len(DATASET_END)))


def read_uff58(path: str | Path) -> list[ExchangeFrf]:
    """The FRFs (function type 4) of a UFF file, in SI units, each with the coherence
    (type 6) that follows it for the same nodes; other datasets are left out."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such file")
    try:
        sets = pyuff.UFF(str(path)).read_sets()
    except Exception as exc:  # pyuff raises bare Exceptions for every malformed file
        raise ConfigError(f"{path}: not a readable universal file ({_hidden(exc)})") from None
    frfs: list[ExchangeFrf] = []
    for number, dataset in enumerate(sets if isinstance(sets, list) else [sets], 1):
        if dataset.get("type") != 58 or dataset.get("func_type") not in (FRF, COHERENCE):
            continue
        frf = _frf_of(dataset, f"{path.name} dataset {number}")
        if dataset["func_type"] == FRF:
            frfs.append(frf)
        elif frfs and frfs[-1].coherence is None and _same_dofs(frfs[-1], frf):
            frfs[-1] = replace(frfs[-1], coherence=frf.H.real)
    if not frfs:
        raise ConfigError(f"{path}: no FRF (dataset 58, function type 4) in the file")
    return frfs


def _hidden(exc: BaseException) -> str:
    """pyuff's message and the error behind it: pyuff replaces a failed dataset's error by
    its own ("Error when reading data-set(s)."), keeping it only as the context."""
    cause = exc
    while cause.__context__ is not None:
        cause = cause.__context__
    if cause is exc:
        return str(exc)
    return f"{str(exc).rstrip('.')}: {type(cause).__name__}: {str(cause).strip()[:120]}"


def _frf_of(dataset: dict, where: str) -> ExchangeFrf:
    """An ExchangeFrf of one dataset 58, its ordinate scaled to SI."""
    response = _dof(dataset, "rsp", "ordinate")
    reference = _dof(dataset, "ref", "orddenom")
    scale = 1.0
    if dataset["func_type"] == FRF:
        scale = _si_factor(dataset, "ordinate", where) / _si_factor(dataset, "orddenom", where)
    f, values = _lines(dataset, where)
    return ExchangeFrf(_text(dataset, "id1") or where, _text(dataset, "id5"), f,
                       values * scale, response, reference)


def _lines(dataset: dict, where: str) -> tuple[np.ndarray, np.ndarray]:
    """A dataset's frequencies (Hz) and values, checked: one value per frequency, as many as
    record 7 says, at least 2 lines, every number finite, frequencies increasing."""
    f, values = np.asarray(dataset["x"], dtype=float), np.asarray(dataset["data"])
    if f.ndim != 1 or values.shape != f.shape or f.size < 2:
        raise ConfigError(f"{where}: {values.size} values on {f.size} frequency lines (an "
                          f"FRF needs 2 or more lines, one value each)")
    if dataset.get("num_pts", f.size) != f.size:
        raise ConfigError(f"{where}: record 7 says {dataset['num_pts']} lines, the data "
                          f"holds {f.size}")
    if not (np.all(np.isfinite(f)) and np.all(np.isfinite(values))):
        raise ConfigError(f"{where}: a frequency or value is not a finite number")
    steps = np.flatnonzero(np.diff(f) <= 0)
    if steps.size:
        line = int(steps[0]) + 1
        raise ConfigError(f"{where}: frequency line {line} ({f[line]:g} Hz) does not "
                          f"follow line {line - 1} ({f[line - 1]:g} Hz)")
    return f, values


def _dof(dataset: dict, end: str, record: str) -> Dof:
    quantity = SPEC_QUANTITIES.get(dataset.get(f"{record}_spec_data_type", 0), "")
    entity = _text(dataset, f"{end}_ent_name")
    channels = _text(dataset, "id4").split(" / ")
    channel = channels[end == "ref"].strip() if len(channels) == 2 else entity
    channel = channel or ("reference" if end == "ref" else "response")
    return Dof(channel, entity, int(dataset.get(f"{end}_node", 0)),
               int(dataset.get(f"{end}_dir", 0)), quantity)


def _text(dataset: dict, key: str) -> str:
    """A text field of a dataset, "" for the format's "NONE"."""
    text = str(dataset.get(key, "")).strip()
    return "" if text == "NONE" else text


def _si_factor(dataset: dict, record: str, where: str) -> float:
    label = _text(dataset, f"{record}_axis_units_lab")
    if not label:
        return 1.0
    if label not in UNIT_LABELS:
        raise ConfigError(f"{where}: {record} units {label!r} unknown "
                          f"(known: {', '.join(UNIT_LABELS)})")
    return UNIT_LABELS[label]


def _same_dofs(a: ExchangeFrf, b: ExchangeFrf) -> bool:
    """Same response and reference node and direction, same abscissa."""
    return _ends(a) == _ends(b) and np.array_equal(a.f, b.f)


def _ends(frf: ExchangeFrf) -> tuple[int, int, int, int]:
    return (frf.response.node, frf.response.direction, frf.reference.node,
            frf.reference.direction)


def analyze_uff58(path: str | Path) -> dict:
    """What feedbench identifies from the FRFs of a UFF58 file: per FRF its ends, units,
    band, coherence, resonance peaks, and for force-referenced FRFs on an even grid the
    modes (`analysis.modal.fit_modes` on the receptance: f_n Hz, ζ, k N/m, m kg)."""
    frfs = read_uff58(path)
    return {"experiment": "uff58", "file": str(path), "frfs": [_identified(frf) for frf in frfs]}


def _identified(frf: ExchangeFrf) -> dict:
    positive = frf.f > 0
    f, H = frf.f[positive], frf.H[positive]
    form = FORMS.get(frf.response.quantity) if frf.reference.quantity == "force" else None
    shape = convert_frf(f, H, form, "receptance") if form else H
    peaks = _peaks(np.abs(shape))
    result = {
        "description": frf.description, "condition": frf.condition,
        "response": vars(frf.response), "reference": vars(frf.reference),
        "units": _units(frf), "form": form or "ratio", "n_lines": int(frf.f.size),
        "band_hz": [float(frf.f[0]), float(frf.f[-1])],
        "min_coherence": None if frf.coherence is None else float(np.min(frf.coherence)),
        "peaks": [{"f_hz": float(f[k]), "abs": float(np.abs(H[k]))} for k in peaks],
    }
    if form and peaks.size and _is_even(f):
        try:
            fit = fit_modes(f, shape, (float(f[0]), float(f[-1])), int(peaks.size))
        except ValueError as exc:  # too few lines for the model order
            result["warnings"] = [f"modes not fitted: {exc}"]
            return result
        result["modes"] = [{"f_n_hz": m.f_n, "zeta": m.zeta, "k_N_m": m.modal_stiffness,
                            "m_kg": m.modal_mass} for m in fit.modes]
        result["fit_relative_error"] = fit.relative_error
        result["warnings"] = list(fit.warnings)
    return result


def _peaks(magnitude: np.ndarray) -> np.ndarray:
    """Indices of the resonance peaks of |H|: at least 3 dB prominent, the MAX_MODES most
    prominent, in frequency order."""
    level = 20 * np.log10(np.maximum(magnitude, np.finfo(float).tiny))
    peaks, properties = scipy.signal.find_peaks(level, prominence=3.0)
    strongest = np.argsort(properties["prominences"])[::-1][:MAX_MODES]
    return np.sort(peaks[strongest])


def _is_even(f: np.ndarray) -> bool:
    """Whether f (Hz) is evenly spaced (to 1e-9 of its step, as FFT bins k·fs/n are)."""
    f = np.asarray(f, dtype=float)
    return f.size > 2 and bool(np.allclose(np.diff(f), f[1] - f[0], rtol=1e-9, atol=0.0))


def _units(frf: ExchangeFrf) -> str:
    """The FRF's SI unit, e.g. "(m/s)/N"; "-" for a ratio of like quantities."""
    numerator = QUANTITIES.get(frf.response.quantity, (0, 0, 0, "?"))[3]
    denominator = QUANTITIES.get(frf.reference.quantity, (0, 0, 0, "?"))[3]
    if numerator == denominator:
        return "-"
    return f"({numerator})/{denominator}" if "/" in numerator else f"{numerator}/{denominator}"


def describe_uff58(result: dict) -> str:
    """Human-readable summary of `analyze_uff58`."""
    count = len(result["frfs"])
    lines = [f"uff58: {result['file']} ({count} FRF{'s' * (count != 1)})"]
    for number, frf in enumerate(result["frfs"], 1):
        response, reference = frf["response"], frf["reference"]
        lines.append(f"  {number}. {frf['description']}"
                     + (f" ({frf['condition']})" if frf["condition"] else ""))
        lines.append(f"     {response['channel']} (node {response['node']}, dir "
                     f"{response['direction']}) / {reference['channel']} (node "
                     f"{reference['node']}, dir {reference['direction']}): {frf['form']} in "
                     f"{frf['units']}, {frf['band_hz'][0]:g}-{frf['band_hz'][1]:g} Hz, "
                     f"{frf['n_lines']} lines"
                     + ("" if frf["min_coherence"] is None
                        else f", min coherence {frf['min_coherence']:.3f}"))
        for mode in frf.get("modes", []):
            lines.append(f"     mode {mode['f_n_hz']:.2f} Hz, zeta {100 * mode['zeta']:.2f} %, "
                         f"k {mode['k_N_m'] * 1e-6:.4g} N/um, m {mode['m_kg']:.4g} kg")
        if not frf.get("modes"):
            lines += [f"     peak {p['f_hz']:.2f} Hz, |H| {p['abs']:.4g} {frf['units']}"
                      for p in frf["peaks"]]
        lines += [f"     warning: {w}" for w in frf.get("warnings", [])]
    return "\n".join(lines)
