"""The campaign report: one self-contained HTML file a person would rather look at than read.

Per run: its configuration, the key time traces (min/max-decimated so spikes stay), the
experiment's results (plots and a table in engineering units) and the quality indicators
(status, gaps, limit headroom, fit and coherence quality). Plots are PNGs drawn with
matplotlib's Agg canvas (no pyplot state, no display) and embedded as base64, so the file
needs no network and no other file to be viewed.

Each run's results are its experiment family's: `Experiment.analyze` computes them and
`Experiment.report` draws them into the run's section (`feedbench.experiments.family`); this
module lays the sections out and knows no family by name. A closure result (`feedbench closure …
--report FILE`) gets a section of its own (`closure_section`): held-out residual before and
after, the effects found, the replay errors.
"""

from __future__ import annotations

import base64
import html
import io
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure as MplFigure

from feedbench.analysis.stability import Lobes, zoa_lobes
from feedbench.config import validate_table
from feedbench.daq.live import bucket_size, minmax_decimate
from feedbench.daq.recording import Recording, open_recording
from feedbench.experiments.family import families
from feedbench.experiments.limits import Limits
from feedbench.experiments.plan import recorded_windows
from feedbench.models.friction import AnderssonFriction
from feedbench.models.milling import engagement_angles
from feedbench.units import MM_PER_MIN, N_MIN_PER_MM, RPM

TRACE_POINTS = 3000
"""Min/max buckets per trace: enough for a 1000-pixel-wide plot at any run length."""

SHADED_KINDS = {"measure": "#2ca02c", "excite": "#ff7f0e"}

TRACE_PANELS = (
    ("position (mm)", ("x_ref", "position", "load_position"), 1e3),
    ("velocity (mm/min)", ("velocity", "velocity_offset"), 1.0 / MM_PER_MIN),
    ("force (N)", ("force", "force_offset", "excitation", "load_cell.force"), 1.0),
    ("spindle speed (rpm)", ("spindle_speed",), 1.0 / RPM),
)
"""Per-cycle panels of the key traces: channels by name, a drive's also as ``drive.name``."""

STREAM_PANELS = (("DAQ forces (N)", "N"), ("accelerations (m/s²)", "m/s^2"))
"""Panels of the high-rate streams' channels, by unit."""


from feedbench.views.sections import *  # noqa  TRANSITION: removed when every family draws its own

REPORT_RESULTS: dict[str, Callable[[Recording, dict, RunSection], None]] = {}


def report_result(name: str):
    """Decorator: register how experiment `name`'s results are drawn into its section."""

    def register(draw: Callable[[Recording, dict, RunSection], None]):
        REPORT_RESULTS[name] = draw
        return draw

    return register


# figures

def trace_plot(recording: Recording) -> Plot:
    """Positions (mm), velocities (mm/min), forces (N), spindle speed (rpm) and the DAQ's
    forces and accelerations over the run, measure and excite windows shaded."""
    cycle_s = float(recording.metadata.get("cycle_s", 1e-3))
    t = (recording.cycle - (recording.cycle[0] if recording.n_samples else 0)) * cycle_s
    panels = [(label, [(t, recording.channels[n] * scale, n)
                       for n in drive_channels(recording, names)])
              for label, names, scale in TRACE_PANELS]
    panels += [(label, stream_traces(recording, unit)) for label, unit in STREAM_PANELS]
    panels = [(label, traces) for label, traces in panels if traces]
    figure = new_figure(10.0, 7.0 if len(panels) <= 3 else 9.5)
    axes = np.atleast_1d(figure.subplots(len(panels), 1, sharex=True))
    spans = _shaded_spans(recording, t, cycle_s)
    for ax, (label, traces) in zip(axes, panels):
        for time_s, values, name in traces:
            read = np.isfinite(values)  # e.g. a load cell read every few cycles
            k = bucket_size(int(read.sum()), TRACE_POINTS)
            t_d, y_d = minmax_decimate(time_s[read], values[read][None, :], k)
            ax.plot(t_d, y_d[0], lw=0.7, label=name)
        _shade_windows(ax, spans)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8)  # beside the data
    axes[-1].set_xlabel("time (s)")
    return Plot("key time traces", png_of(figure))


def drive_channels(recording: Recording, names: Sequence[str]) -> list[str]:
    """The recording's channels among `names`, a drive's as ``name`` or ``drive.name`` (a
    drive: a prefix with its own statusword, e.g. master and slave of a rack-and-pinion
    axis)."""
    drives = {c.rsplit(".", 1)[0] for c in recording.channels if c.endswith(".statusword")}
    return [c for c in recording.channels
            if c in names or ("." in c and c.split(".", 1)[0] in drives
                              and c.split(".", 1)[1] in names)]


def stream_traces(recording: Recording, unit: str) -> list[tuple[np.ndarray, np.ndarray, str]]:
    """(time s, values, name) of every high-rate stream channel in `unit`; a sample's time
    from its counter, t = 0 at the run's first cycle."""
    if not recording.n_samples:
        return []
    cycle_s = float(recording.metadata.get("cycle_s", 1e-3))
    out = []
    for stream in recording.streams.values():
        if not stream.n_samples:
            continue
        t = ((stream.cycle[0] - recording.cycle[0]) * cycle_s
             + (stream.sequence - stream.sequence[0]) / stream.rate_hz)
        out += [(t, values, name) for name, values in stream.channels.items()
                if stream.units.get(name) == unit]
    return out


def _shaded_spans(recording: Recording, t: np.ndarray,
                  cycle_s: float) -> dict[str, list[tuple[float, float]]]:
    """(start s, width s) of the measure and excite windows, by colour."""
    return {color: [(t[w.start], t[w.stop - 1] + cycle_s - t[w.start])
                    for w in recorded_windows(recording, kind)]
            for kind, color in SHADED_KINDS.items()}


def _shade_windows(ax, spans: dict[str, list[tuple[float, float]]]) -> None:
    """One collection per colour over the full height (hundreds of windows stay cheap)."""
    for color, ranges in spans.items():
        if ranges:
            ax.broken_barh(ranges, (0.0, 1.0), transform=ax.get_xaxis_transform(),
                           color=color, alpha=0.12, lw=0)


# common tables and indicators

def config_table(recording: Recording) -> Table:
    """The run's recorded configuration, flattened to dotted keys (engineering units)."""
    rows = tuple((key, _text(value)) for key, value in _flatten(recording.config))
    return Table("configuration", ("key", "value"), rows)


def _flatten(table: dict, prefix: str = "") -> list[tuple[str, Any]]:
    out = []
    for key, value in table.items():
        name = f"{prefix}{key}"
        out += _flatten(value, name + ".") if isinstance(value, dict) else [(name, value)]
    return out


def _text(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, list):
        return ", ".join(_text(v) for v in value)
    return str(value)


def run_quality(recording: Recording) -> list[Indicator]:
    """Status, completeness and limit headroom of a run."""
    cycle_s = float(recording.metadata.get("cycle_s", 1e-3))
    status = recording.status + (f" ({recording.reason})" if recording.reason else "")
    out = [
        Indicator("status", status, recording.status == "complete"),
        Indicator("samples", f"{recording.n_samples} ({recording.n_samples * cycle_s:.2f} s)"),
        Indicator("missing samples (gaps)", str(recording.n_gaps), recording.n_gaps == 0),
        *stream_quality(recording),
    ]
    try:
        limits = Limits.from_config(recording.config.get("limits", {}))
    except ValueError:
        return out
    return out + headroom(recording, limits)


def headroom(recording: Recording, limits: Limits) -> list[Indicator]:
    """Peak |force|, peak |velocity| and position range of the drives against the watched
    limits."""
    if not recording.n_samples:
        return []
    peak_force, peak_velocity = (
        max(float(np.max(np.abs(recording.channels[c]))) for c in drive_channels(recording, (q,)))
        for q in ("force", "velocity"))
    positions = np.concatenate([recording.channels[c]
                                for c in drive_channels(recording, ("position",))])
    low, high = float(positions.min()), float(positions.max())
    return [
        Indicator("peak |force|", f"{peak_force:.1f} N = {100 * peak_force / limits.force:.0f} % "
                  "of the limit", peak_force < limits.force),
        Indicator("peak |velocity|", f"{peak_velocity / MM_PER_MIN:.0f} mm/min = "
                  f"{100 * peak_velocity / limits.velocity:.0f} % of the limit",
                  peak_velocity < limits.velocity),
        Indicator("position range", f"{low * 1e3:.1f} … {high * 1e3:.1f} mm (limits "
                  f"{limits.position[0] * 1e3:g} … {limits.position[1] * 1e3:g} mm)",
                  limits.position[0] <= low and high <= limits.position[1]),
    ]


def stream_quality(recording: Recording) -> list[Indicator]:
    """Samples and lost samples of every high-rate stream (the DAQ's counter)."""
    return [Indicator(f"{name} stream", f"{stream.n_samples} samples at {stream.rate_hz:g} Hz, "
                      f"{stream.n_dropped} lost", stream.n_dropped == 0)
            for name, stream in recording.streams.items()]


# per-experiment results

@report_result("friction_sweep")
def friction_results(recording: Recording, result: dict, section: RunSection) -> None:
    """Friction points and the fitted Andersson law per direction, Eq. (5.2), Fig. 5.11."""
    v = np.array(result["points"]["velocity_m_s"])
    force = np.array(result["points"]["force_N"])
    figure = new_figure(8.0, 4.5)
    ax = figure.subplots()
    ax.plot(v / MM_PER_MIN, force, "o", ms=4, label="measured (mean of each window)")
    for direction, sign in (("positive", 1.0), ("negative", -1.0)):
        side = np.sign(v) == sign
        if not side.any():
            continue
        law = AnderssonFriction(**result[direction]["identified"])
        speed = np.linspace(np.abs(v[side]).min(), np.abs(v[side]).max(), 300)
        ax.plot(sign * speed / MM_PER_MIN, sign * law.force(speed), lw=1.5,
                label=f"Andersson fit, {direction}")
    ax.set_xlabel("feed (mm/min)")
    ax.set_ylabel("motor force (N)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    section.plots.append(Plot("friction curve and fitted model, Eq. (5.2)", png_of(figure)))
    section.tables.append(friction_table(result))
    for direction in ("positive", "negative"):
        r2 = result[direction]["r_squared"]
        section.quality.append(Indicator(f"R² of the {direction} fit",
                                         f"{r2:.5f} (rms {result[direction]['rms_N']:.2f} N)",
                                         r2 >= MIN_R_SQUARED))
    p = result["positive"]["identified"]
    section.headline = f"F_c {p['F_c']:.1f} N, F_s {p['F_s']:.1f} N (positive)"


FRICTION_ROWS = (("F_c", "N", 1.0), ("F_s", "N", 1.0), ("v_s", "mm/min", 1.0 / MM_PER_MIN),
                 ("sigma", "N·min/mm", 1.0 / N_MIN_PER_MM))


def friction_table(result: dict) -> Table:
    """Identified parameters ± one standard deviation, in the units of Fig. 5.11."""
    rows = []
    for name, unit, scale in FRICTION_ROWS:
        cells = [f"{name} ({unit})"]
        for direction in ("positive", "negative"):
            value = result[direction]["identified"][name] * scale
            std = result[direction]["std"][name] * scale
            cells.append(f"{value:.5g} ± {std:.2g}")
        rows.append(tuple(cells))
    return Table("identified friction parameters", ("parameter", "positive", "negative"),
                 tuple(rows))


@report_result("impact_hammer")
def hammer_results(recording: Recording, result: dict, section: RunSection) -> None:
    """Quasi-FRF per feed (Eq. 5.3) as compliance with coherence, the feed comparison
    (Fig. 5.12) and the stability lobes of the lowest and highest feed (Fig. 5.25)."""
    feeds = result["feeds"]
    series = [FrfSeries(f"{x['feed_mm_min']:g} mm/min", np.array(x["frf"]["f_hz"]),
                        np.array(x["frf"]["compliance_abs"]), np.array(x["frf"]["coherence"]))
              for x in feeds]
    section.plots.append(Plot("tool-tip compliance per feed (quasi-FRF, Eq. 5.3) with "
                              "coherence", png_of(frf_figure(series, "|x/F| (m/N)"))))
    section.tables.append(Table("impact hammer per feed", (
        "feed (mm/min)", "peak (Hz)", "peak |x/F| (µm/N)", "hits used", "min coherence",
        "distance to highest feed"), tuple(
        (f"{x['feed_mm_min']:g}", f"{x['peak_hz']:.2f}", f"{x['peak_compliance_m_N'] * 1e6:.3f}",
         f"{x['hits_used']} of {x['hits']}", f"{x['min_coherence']:.4f}",
         f"{100 * x['distance_to_highest_feed']:.0f} %") for x in feeds)))
    compliances = {s.label: (s.f, np.array(x["frf"]["compliance_abs"])
                             * np.exp(1j * np.array(x["frf"]["compliance_phase_rad"])))
                   for s, x in zip(series, feeds)}
    lobes_results(_extremes(compliances), section)
    low = min((x["min_coherence"] for x in feeds), default=float("nan"))
    section.quality += [
        Indicator("min coherence in the band", f"{low:.4f}", low >= MIN_COHERENCE),
        Indicator("hits left out", str(sum(x["hits"] - x["hits_used"] for x in feeds)),
                  all(x["hits"] == x["hits_used"] for x in feeds)),
        Indicator("notes", "; ".join(result["notes"]) or "none", not result["notes"]),
    ]
    invariant = result["invariant_from_mm_min"]
    section.headline = (f"invariant from {invariant:g} mm/min" if invariant is not None
                        else "no feed range invariant")


@report_result("shaker_chirp")
def shaker_chirp_results(recording: Recording, result: dict, section: RunSection) -> None:
    """Tool-tip compliance per feed (H1 over the sweeps) with coherence, and its lobes."""
    feeds = result["feeds"]
    series, compliances = [], {}
    for x in feeds:
        f = np.array(x["frf"]["f_hz"])
        accelerance = np.array(x["frf"]["H1_abs"]) * np.exp(1j * np.array(x["frf"]["H1_phase_rad"]))
        label = f"{x['feed_mm_min']:g} mm/min"
        compliances[label] = (f, -accelerance / (2 * np.pi * f) ** 2)
        series.append(FrfSeries(label, f, np.array(x["frf"]["compliance_abs"]),
                                np.array(x["frf"]["coherence"])))
    section.plots.append(Plot("tool-tip compliance per feed (H1 over the sweeps) with coherence",
                              png_of(frf_figure(series, "|x/F| (m/N)"))))
    section.tables.append(Table("shaker chirp per feed", (
        "feed (mm/min)", "sweeps averaged", "peak (Hz)", "min coherence", "warnings"), tuple(
        (f"{x['feed_mm_min']:g}", str(x["n_averages"]), f"{x['peak_hz']:.2f}",
         f"{x['min_coherence']:.4f}", "; ".join(x["warnings"]) or "none") for x in feeds)))
    lobes_results(_extremes(compliances), section)
    low = min((x["min_coherence"] for x in feeds), default=float("nan"))
    section.quality += [
        Indicator("min coherence in the band", f"{low:.4f}", low >= MIN_COHERENCE),
        Indicator("FRF warnings", "; ".join(w for x in feeds for w in x["warnings"]) or "none",
                  not any(x["warnings"] for x in feeds)),
        Indicator("notes", "; ".join(result["notes"]) or "none", not result["notes"]),
    ]
    section.headline = ", ".join(f"{x['feed_mm_min']:g} mm/min: peak {x['peak_hz']:.1f} Hz"
                                 for x in feeds)


@report_result("sine_stream")
def sine_stream_results(recording: Recording, result: dict, section: RunSection) -> None:
    """Sine-stream FRF points per feed and force amplitude with the R² of each step
    (Figs. 5.21, 5.22), the quality gate and the spread between amplitudes."""
    gate = float(recording.config["experiment"].get("r_squared_min", 0.99))
    streams = result["streams"]
    series = [FrfSeries(f"{x['feed_mm_min']:g} mm/min, {x['amplitude_N']:g} N",
                        np.array(x["frf"]["f_hz"]), np.array(x["frf"]["compliance_abs"]),
                        np.array(x["frf"]["r_squared"])) for x in streams]
    section.plots.append(Plot("sine-stream compliance points with the R² of each step",
                              png_of(frf_figure(series, "|x/F| (m/N)", "R² of the sine fits",
                                                gate, points=True))))
    section.tables.append(Table("sine-stream per feed and amplitude", (
        "feed (mm/min)", "amplitude (N)", "steps used", "peak (Hz)", "min R²",
        "force limited at (Hz)", "force not held at (Hz)"), tuple(
        (f"{x['feed_mm_min']:g}", f"{x['amplitude_N']:g}", f"{x['steps_used']} of {x['steps']}",
         f"{x['peak_hz']:.2f}", f"{x['min_r_squared']:.4f}", _hz_list(x["limited_hz"]),
         _hz_list(x["not_held_hz"])) for x in streams)))
    low = min((x["min_r_squared"] for x in streams), default=float("nan"))
    spread = result["amplitude_spread"]
    section.quality += [
        Indicator("steps flagged (quality gate)", str(result["steps_flagged"]),
                  result["steps_flagged"] == 0),
        Indicator("min R² of the steps used", f"{low:.5f}", low >= gate),
        Indicator("spread between amplitudes (of the peak)", ", ".join(
            f"{feed} mm/min: {100 * value:.1f} %" for feed, value in spread.items())),
    ]
    section.headline = "; ".join(f"{s.label}: peak {x['peak_hz']:.2f} Hz"
                                 for s, x in zip(series, streams))


def _hz_list(values: Sequence[float]) -> str:
    return ", ".join(f"{v:g}" for v in values) or "none"


@report_result("closed_loop_bode")
def closed_loop_bode_results(recording: Recording, result: dict, section: RunSection) -> None:
    """Closed-loop FRF points with R² and −3 dB bandwidth; for the velocity loop the
    open-loop mobility of Eq. (4.20) with f_t and f_r (Eqs. 4.13, 4.14)."""
    frf = result["frf"]
    f = np.array(frf["f_hz"])
    gate = float(recording.config["experiment"].get("r_squared_min", 0.99))
    series = [FrfSeries(f"{result['loop']} loop at {result['feed_mm_min']:g} mm/min", f,
                        np.array(frf["abs"]), np.array(frf["r_squared"]))]
    section.plots.append(Plot(f"closed {result['loop']} loop: points with R²", png_of(
        frf_figure(series, "|H| closed loop (–)", "R² of the sine fits", gate, points=True))))
    rows = [("−3 dB bandwidth", f"{result['bandwidth_hz']:.1f} Hz"),
            ("frequencies flagged (R²)", str(len(result["flagged"])))]
    mobility = result.get("mobility")
    if mobility:
        section.plots.append(Plot("open-loop mobility by Eq. (4.20)", png_of(
            _mobility_figure(f, np.array(mobility["abs"]), mobility))))
        rows += [("anti-resonance f_t (Eq. 4.13)", f"{mobility['antiresonance_hz']:.2f} Hz"),
                 ("resonance f_r (Eq. 4.14)", f"{mobility['resonance_hz']:.2f} Hz")]
        section.headline = (f"f_t {mobility['antiresonance_hz']:.1f} Hz, "
                            f"f_r {mobility['resonance_hz']:.1f} Hz")
    else:
        section.headline = f"bandwidth {result['bandwidth_hz']:.1f} Hz"
    section.tables.append(Table(f"closed {result['loop']} loop", ("quantity", "value"),
                                tuple(rows)))
    low = result["min_r_squared"]
    section.quality += [
        Indicator("min R² of the points used", "none" if low is None else f"{low:.5f}",
                  low is not None and low >= gate),
        Indicator("frequencies flagged", ", ".join(f"{x['frequency_hz']:g} Hz"
                                                   for x in result["flagged"]) or "none",
                  not result["flagged"]),
    ]


def _mobility_figure(f: np.ndarray, magnitude: np.ndarray, mobility: dict) -> MplFigure:
    figure = new_figure(8.0, 4.0)
    ax = figure.subplots()
    ax.semilogy(f, magnitude, "o-", ms=3, lw=0.8, label="|G| open-loop mobility")
    for key, name in (("antiresonance_hz", "f_t"), ("resonance_hz", "f_r")):
        ax.axvline(mobility[key], color="k", ls="--", lw=0.8)
        ax.annotate(f"{name} {mobility[key]:.1f} Hz", (mobility[key], 1.0),
                    xycoords=("data", "axes fraction"), ha="left", va="top", fontsize=8)
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel("|G| ((m/s)/N)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="lower left")
    return figure


# stepped loading (rack-and-pinion axis)

@report_result("stepped_loading")
def stepped_loading_results(recording: Recording, result: dict, section: RunSection) -> None:
    """Load against displacement with the fitted stiffness (Eq. 3.26, Fig. 3.8), the
    backlash strokes (Fig. 3.9), the coupled loadings with the preload loss per level
    (Figs. 3.10–3.11) and their table."""
    from feedbench.experiments import stepped_loading

    params = validate_table(recording.config["experiment"], stepped_loading.SCHEMA,
                            "experiment")
    toward = stepped_loading.SIGNS[params["direction"]]
    tests: dict[str, list] = {}
    for window in recorded_windows(recording, "measure"):
        tests.setdefault(window.info["test"], []).append(window)

    def samples(test: str) -> dict[str, np.ndarray]:
        # the analysis's own selection of the rows (measure windows, load cell read)
        return stepped_loading._test_samples(recording, tests[test], toward)

    if result["stiffness"] or result["backlash"]:
        section.plots.append(Plot("single-motor loading and backlash", png_of(
            _single_motor_figure(recording, result, tests, samples))))
    if result["preload"]:
        section.plots.append(Plot("coupled loading per preload level: master displacement "
                                  "against load", png_of(_coupled_figure(result, samples))))
    section.tables += _stepped_loading_tables(result)
    r2 = [x["r_squared"] for x in result["stiffness"].values()]
    failed = [t for t in result["preload"] if "error" in t]
    section.quality += [
        Indicator("min R² of the stiffness fits", f"{min(r2, default=float('nan')):.5f}",
                  all(v >= MIN_R_SQUARED for v in r2)),
        Indicator("preload levels analysed", f"{len(result['preload']) - len(failed)} of "
                  f"{len(result['preload'])}" + "".join(f"; {t['preload_pct']:g} %: {t['error']}"
                                                        for t in failed), not failed),
    ]
    section.headline = ", ".join(f"k_{m[0]} {x['k_N_m'] / 1e6:.1f} N/µm"
                                 for m, x in result["stiffness"].items())


def _single_motor_figure(recording: Recording, result: dict, tests: dict, samples) -> MplFigure:
    """Left: load against δ = x_motor − x_load per motor with the line of Eq. (3.26);
    right: δ against the motor position in the backlash strokes (lost motion)."""
    figure = new_figure(10.0, 4.5)
    loading, strokes = figure.subplots(1, 2)
    for motor, fit in result["stiffness"].items():
        s = samples(f"single {motor}")
        delta = s[motor] - s["load"]
        loading.plot(delta * 1e6, s["force"], ".", ms=2, label=f"{motor} alone")
        force = np.linspace(*fit["force_range_N"], 50)
        loading.plot((force / fit["k_N_m"] + fit["offset_m"]) * 1e6, force, lw=1.2,
                     label=f"k {fit['k_N_m'] / 1e6:.1f} N/µm (R² {fit['r_squared']:.4f})")
    loading.set_xlabel("δ = x_motor − x_load (µm)")
    loading.set_ylabel("load cell (N)")
    for motor, backlash in result["backlash"].items():
        rows = np.concatenate([np.arange(w.start, w.stop) for w in tests[f"backlash {motor}"]])
        x_motor = recording.channels[f"{motor}.motor_position"][rows]
        delta = x_motor - recording.channels["load_position"][rows]
        strokes.plot(x_motor * 1e3, delta * 1e6, ".", ms=1.5,
                     label=f"{motor}: backlash {backlash['value_m'] * 1e6:.1f} µm")
    strokes.set_xlabel("motor position (mm)")
    strokes.set_ylabel("δ = x_motor − x_load (µm)")
    for ax in (loading, strokes):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    return figure


def _coupled_figure(result: dict, samples) -> MplFigure:
    """Per preload level δ_m = x_master − x_load against the load, the loss and the
    recovery force marked (Fig. 3.11-a)."""
    levels = result["preload"]
    figure = new_figure(10.0, 4.0)
    axes = np.atleast_1d(figure.subplots(1, len(levels), sharey=True))
    for ax, level in zip(axes, levels):
        s = samples(f"coupled {level['preload_pct']:g} %")
        ax.plot(s["force"], (s["master"] - s["load"]) * 1e6, ".", ms=2)
        if "error" not in level:
            for key, style in (("loss_force_N", "--"), ("recovery_force_N", ":")):
                ax.axvline(level[key], color="r", ls=style, lw=0.8)
            ax.set_title(f"{level['preload_pct']:g} %: loss {level['loss_force_N']:.0f} N, "
                         f"jump {level['jump_m'] * 1e6:.0f} µm", fontsize=9)
        ax.set_xlabel("load (N)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("δ_m = x_master − x_load (µm)")
    return figure


def _stepped_loading_tables(result: dict) -> list[Table]:
    motors = [m for m in ("master", "slave") if m in result["stiffness"] or m in result["backlash"]]
    stiffness = Table("drive-train stiffness (Eq. 3.26) and backlash", (
        "motor", "k (N/µm)", "R²", "backlash (µm)", "friction wind-up taken out"),
        tuple((motor, *_stiffness_cells(result["stiffness"].get(motor)),
               *_backlash_cells(result["backlash"].get(motor))) for motor in motors))
    preload = Table("preload loss per level (Ch. 3.4.3)", (
        "preload (%)", "loss (N)", "loss from torques (N)", "recovery (N)", "jump (µm)",
        "slave k contact → lost (N/µm)", "torque share"), tuple(
        (f"{t['preload_pct']:g}", *(("—",) * 6)) if "error" in t else
        (f"{t['preload_pct']:g}", f"{t['loss_force_N']:.0f}",
         f"{t['loss_force_from_torques_N']:.0f}", f"{t['recovery_force_N']:.0f}",
         f"{t['jump_m'] * 1e6:.1f}",
         f"{t['k_slave_contact_N_m'] / 1e6:.1f} → {t['k_slave_lost_N_m'] / 1e6:.1f}",
         f"{t['torque_share']:.3f}") for t in result["preload"]))
    return [stiffness, preload]


def _stiffness_cells(fit: dict | None) -> tuple[str, str]:
    if fit is None:
        return "—", "—"
    return (f"{fit['k_N_m'] / 1e6:.2f} ± {fit['k_std_N_m'] / 1e6:.2f}",
            f"{fit['r_squared']:.5f}")


def _backlash_cells(backlash: dict | None) -> tuple[str, str]:
    if backlash is None:
        return "—", "—"
    return f"{backlash['value_m'] * 1e6:.1f}", str(backlash["corrected"])


# SMFE

@report_result("smfe")
def smfe_results(recording: Recording, result: dict, section: RunSection) -> None:
    """Direct receptances Φ_tt and Φ_ww (Eq. 6.13), the condition number of the measured
    force-spectrum matrix (Eq. 6.14) against the planned C_th, and the coherence of every
    direct response/force pair per cut (Eq. 6.15)."""
    f = np.array(result["f_hz"])
    figure = new_figure(10.0, 4.5)
    for ax, side, name in zip(figure.subplots(1, 2, sharey=True), ("tool", "workpiece"),
                              ("Φ_tt", "Φ_ww")):
        for axis, magnitude in result[side]["abs_m_N"].items():
            ax.semilogy(f, magnitude, lw=1.0, label=f"|{name},{axis}{axis}|")
        ax.set_xlabel("frequency (Hz)")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    figure.axes[0].set_ylabel("receptance (m/N)")
    section.plots.append(Plot("SMFE direct receptances at the tool and the workpiece",
                              png_of(figure)))
    section.plots.append(Plot("condition number (Eq. 6.14) and coherence (Eq. 6.15)",
                              png_of(_smfe_quality_figure(recording, result))))
    section.tables.append(Table("SMFE peaks", ("side", "direction", "peak (Hz)", "|Φ| (m/N)",
                                               "min coherence at the peak"), tuple(
        (side, f"{axis}{axis}", f"{p['f_hz']:.2f}", f"{p['abs_m_N']:.3g}",
         f"{p['coherence_min']:.3f}")
        for side in ("tool", "workpiece") for axis, p in result[side]["peaks"].items())))
    cond = result["condition_number"]
    coherence = min(p["coherence_min"] for side in ("tool", "workpiece")
                    for p in result[side]["peaks"].values())
    section.quality += [
        Indicator("condition number (median / max / planned C_th)",
                  f"{cond['median']:.1f} / {cond['max']:.1f} / {cond['planned_C_th']:.1f}"),
        Indicator("min coherence at the peaks", f"{coherence:.3f}", coherence >= MIN_COHERENCE),
        Indicator("warnings", "; ".join(result["warnings"]) or "none", not result["warnings"]),
    ]
    section.headline = "Φ_tt peaks " + ", ".join(
        f"{axis}{axis} {p['f_hz']:.1f} Hz" for axis, p in result["tool"]["peaks"].items())


def _smfe_quality_figure(recording: Recording, result: dict) -> MplFigure:
    """C(f) with the planned C_th, and per direction the lowest coherence over the cuts of
    the direct pair at the tool, over the analysis band (recomputed with the analysis's
    records and Welch settings)."""
    from feedbench.analysis.smfe import OVERLAP, smfe_estimate
    from feedbench.experiments import smfe

    p = validate_table(recording.config["experiment"], smfe.SCHEMA, "experiment")
    fs = recording.streams["daq"].rate_hz
    forces, tools, _, _ = smfe.cut_records(recording, len(p["cuts"]))
    band = result["band_hz"]
    est = smfe_estimate(list(zip(forces, tools)), fs, int(round(p["segment_s"] * fs)), OVERLAP,
                        f_max=band[1])
    inside = (est.f >= band[0]) & (est.f <= band[1])
    figure = new_figure(10.0, 4.0)
    condition, coherence = figure.subplots(1, 2)
    condition.semilogy(est.f[inside], est.condition_number[inside], lw=1.0)
    condition.axhline(result["condition_number"]["planned_C_th"], color="r", ls="--", lw=0.8,
                      label="planned C_th")
    condition.set_ylabel("condition number C")
    for i, axis in enumerate("xyz"[:est.Phi.shape[1]]):
        coherence.plot(est.f[inside], est.coherence[:, inside, i, i].min(axis=0), lw=1.0,
                       label=f"γ²_{axis}{axis}")
    coherence.axhline(MIN_COHERENCE, color="r", ls=":", lw=0.8)
    coherence.set_ylim(0.0, 1.05)
    coherence.set_ylabel("coherence, lowest over the cuts")
    for ax in (condition, coherence):
        ax.set_xlabel("frequency (Hz)")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    return figure


# assembly

def run_section(recording: Recording) -> RunSection:
    """Configuration, traces, results and quality of one recorded run; the results drawn by
    the recording's experiment family (`Experiment.report`)."""
    section = RunSection(recording.metadata.get("run_id", recording.path.stem),
                         recording.experiment, recording.status)
    section.quality += run_quality(recording)
    section.plots.append(trace_plot(recording))
    experiment = families().get(recording.experiment)
    if experiment is None:
        section.quality.append(Indicator("results", "no analysis for this experiment"))
    else:
        try:
            experiment.report(recording, experiment.analyze(recording), section)
        except Exception as exc:  # an aborted run may be too short to analyse: say so
            section.quality.append(Indicator("analysis", f"failed: {type(exc).__name__}: {exc}",
                                             False))
    section.tables.append(config_table(recording))
    return section


def closure_section(report: Any) -> RunSection:
    """A closure result (`analysis.closure.ClosureReport`) as a section: the held-out force
    residual before and after, the findings (effects added, declared values recalibrated)
    with their evidence and parameters, the error before/after and the closed-loop replay
    errors."""
    from feedbench.analysis.closure import report_dict

    data = report_dict(report)
    findings = ", ".join(_finding_summary(step) for step in data["steps"]) or "nothing found"
    section = RunSection(f"closure: {report.name or 'model'}", "closure", findings)
    section.plots.append(Plot("held-out force residual before and after",
                              png_of(_residual_figure(report, findings))))
    section.tables.append(Table("findings", (
        "finding", "kind", "evidence", "ΔBIC", "explained", "held-out error", "parameters"),
        tuple((step["effect"], FINDING_KINDS[step["kind"]], step["evidence"],
               f"{step['delta_bic']:.0f}", f"{100 * step['explained']:.1f} %",
               f"{100 * step['error_before']:.2f} → {100 * step['error_after']:.2f} %",
               _finding_parameters(step))
              for step in data["steps"])))
    replay = data["replay"]
    if replay is not None:
        section.tables.append(Table("closed-loop replay on the held-out data", (
            "quantity", "before", "after"), tuple(
            (name, f"{replay['before'][key]:.4g}", f"{replay['after'][key]:.4g}")
            for name, key in (("force NRMSE", "force"), ("position NRMSE", "position"),
                              ("tracking error NRMSE", "tracking"),
                              ("FRF |H| error (dB RMS)", "frf_magnitude_db"),
                              ("FRF phase error (° RMS)", "frf_phase_deg")))))
    section.quality += [
        Indicator("held-out force NRMSE before → after",
                  f"{100 * data['error_before']:.2f} % → {100 * data['error_after']:.2f} %",
                  data["error_after"] <= data["error_before"]),
        Indicator("fit on / judged on", f"{data['fit_data']} / {data['holdout_data']}"),
        Indicator("stopped", data["stopped"]),
    ]
    if data["tip_error_before"] is not None:
        section.quality.insert(1, Indicator(
            "held-out tip acceleration NRMSE before → after",
            f"{100 * data['tip_error_before']:.2f} % → {100 * data['tip_error_after']:.2f} %",
            data["tip_error_after"] <= data["tip_error_before"]))
    section.headline = (f"{findings}: "
                        f"{100 * data['error_before']:.2f} % → {100 * data['error_after']:.2f} %")
    return section


FINDING_KINDS = {"effect": "effect added", "recalibration": "declared value recalibrated"}


def _finding_summary(step: dict) -> str:
    """"ripple added" or "delay.tau_ms recalibrated"."""
    return f"{step['effect']} {'recalibrated' if step['kind'] == 'recalibration' else 'added'}"


def _finding_parameters(step: dict) -> str:
    """An effect's fitted parameters, or a recalibration's declared → fitted ± σ."""
    if step["kind"] == "recalibration":
        return step["description"]
    return ", ".join(f"{key} {p['value']:.4g}" for key, p in step["params"].items())


def _residual_figure(report: Any, findings: str) -> MplFigure:
    """Held-out force residual (N) of the base and the final model over time."""
    time_s, before, after = report.held_out_residuals()
    result = report.result
    figure = new_figure(10.0, 4.5)
    ax = figure.subplots()
    ax.plot(time_s, before, ".", ms=1.5, label=f"before: NRMSE {result.error_before:.2%}")
    ax.plot(time_s, after, ".", ms=1.5, label=f"after ({findings}): NRMSE {result.error_after:.2%}")
    ax.set_xlabel("time in the held-out data (s)")
    ax.set_ylabel("force residual (N)")
    ax.grid(alpha=0.3)
    ax.legend(markerscale=6, fontsize=8)
    return figure


def write_report(runs: Sequence[str | Path], path: str | Path,
                 title: str = "feedbench campaign report", closures: Sequence[Any] = ()) -> Path:
    """Write the HTML report of recordings `runs` (and of `closures`, closure results) to
    `path`; returns the path."""
    sections = [run_section(open_recording(run)) for run in runs]
    sections += [closure_section(report) for report in closures]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(render_html(sections, title), encoding="utf-8")
    return path


STYLE = """
body{font-family:system-ui,sans-serif;margin:2em auto;max-width:1100px;color:#222}
h1{border-bottom:2px solid #444}h2{margin-top:2em;border-bottom:1px solid #aaa}
table{border-collapse:collapse;margin:0.8em 0}td,th{border:1px solid #ccc;padding:3px 8px;
text-align:left;font-size:0.9em}th{background:#eee}.ok{color:#1a7f37}.bad{color:#c0392b;
font-weight:bold}img{max-width:100%;display:block;margin:0.5em 0}figure{margin:1em 0}
figcaption{font-size:0.9em;color:#555}
"""


def render_html(sections: Sequence[RunSection], title: str) -> str:
    """The whole report as one HTML document (no external resources)."""
    summary = Table("runs", ("run", "experiment", "status", "result"), tuple(
        (s.run_id, s.experiment, s.status, s.headline) for s in sections))
    parts = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
             f"<title>{html.escape(title)}</title><style>{STYLE}</style></head><body>",
             f"<h1>{html.escape(title)}</h1>", _table_html(summary)]
    parts += [_section_html(s) for s in sections]
    parts.append("</body></html>")
    return "\n".join(parts)


def _section_html(section: RunSection) -> str:
    anchor = "-".join(section.run_id.split())  # an HTML id has no white space
    out = [f"<h2 id='{html.escape(anchor)}'>{html.escape(section.run_id)} — "
           f"{html.escape(section.experiment)}</h2>", "<h3>quality</h3>",
           _quality_html(section.quality)]
    for plot in section.plots:
        data = base64.b64encode(plot.png).decode("ascii")
        out.append(f"<figure><img alt='{html.escape(plot.title)}' "
                   f"src='data:image/png;base64,{data}'><figcaption>{html.escape(plot.title)}"
                   "</figcaption></figure>")
    out += [_table_html(table) for table in section.tables]
    return "\n".join(out)


def _quality_html(indicators: Sequence[Indicator]) -> str:
    rows = []
    for ind in indicators:
        mark = {True: "<span class='ok'>✔</span>", False: "<span class='bad'>✘</span>",
                None: ""}[ind.ok]
        rows.append(f"<tr><td>{mark}</td><td>{html.escape(ind.name)}</td>"
                    f"<td>{html.escape(ind.value)}</td></tr>")
    return "<table>" + "".join(rows) + "</table>"


def _table_html(table: Table) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in table.header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in row) + "</tr>"
                   for row in table.rows)
    return f"<h3>{html.escape(table.title)}</h3><table><tr>{head}</tr>{body}</table>"

