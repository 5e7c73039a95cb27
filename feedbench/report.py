"""The campaign report: one self-contained HTML file a person would rather look at than read.

Per run: its configuration, the key time traces (min/max-decimated so spikes stay), the
experiment's results (plots and a table in engineering units) and the quality indicators
(status, gaps, limit headroom, fit and coherence quality). Plots are PNGs drawn with
matplotlib's Agg canvas (no pyplot state, no display) and embedded as base64, so the file
needs no network and no other file to be viewed.

Results come from each experiment's `analyze_recording`; how they are drawn is a registry
keyed by experiment name (`REPORT_RESULTS`), like the live window's, so new experiment
families (sine-stream, hammer, stepped loading, SMFE, stability lobes, closure) add one
function with ``@report_result("name")``.
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

from feedbench.daq.live import bucket_size, minmax_decimate
from feedbench.daq.recording import Recording, open_recording
from feedbench.experiments.limits import Limits
from feedbench.experiments.plan import recorded_windows
from feedbench.models.friction import AnderssonFriction
from feedbench.units import MM_PER_MIN, N_MIN_PER_MM

TRACE_POINTS = 3000
"""Min/max buckets per trace: enough for a 1000-pixel-wide plot at any run length."""

MIN_COHERENCE = 0.9
"""Coherence below this in the analysed band is flagged (Ch. 3.5.1)."""

MIN_R_SQUARED = 0.99
"""A friction fit with a lower R² is flagged."""

SHADED_KINDS = {"measure": "#2ca02c", "excite": "#ff7f0e"}


@dataclass(frozen=True)
class Plot:
    """A titled PNG image."""

    title: str
    png: bytes


@dataclass(frozen=True)
class Table:
    """A titled table: header and rows of text."""

    title: str
    header: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]


@dataclass(frozen=True)
class Indicator:
    """One quality indicator; `ok` None means informative only."""

    name: str
    value: str
    ok: bool | None = None


@dataclass
class RunSection:
    """Everything the report shows about one run."""

    run_id: str
    experiment: str
    status: str
    plots: list[Plot] = field(default_factory=list)
    tables: list[Table] = field(default_factory=list)
    quality: list[Indicator] = field(default_factory=list)
    headline: str = ""


REPORT_RESULTS: dict[str, Callable[[Recording, dict, RunSection], None]] = {}


def report_result(name: str):
    """Decorator: register how experiment `name`'s results are drawn into its section."""

    def register(draw: Callable[[Recording, dict, RunSection], None]):
        REPORT_RESULTS[name] = draw
        return draw

    return register


# figures

def new_figure(width_in: float = 10.0, height_in: float = 4.0) -> MplFigure:
    """A matplotlib figure on an Agg canvas (no pyplot global state)."""
    figure = MplFigure(figsize=(width_in, height_in), dpi=100, layout="constrained")
    FigureCanvasAgg(figure)
    return figure


def png_of(figure: MplFigure) -> bytes:
    """The figure rendered as PNG bytes."""
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    return buffer.getvalue()


def trace_plot(recording: Recording) -> Plot:
    """Positions (mm), velocities (mm/min) and forces (N) over the run, measure and
    excite windows shaded."""
    cycle_s = float(recording.metadata.get("cycle_s", 1e-3))
    t = (recording.cycle - (recording.cycle[0] if recording.n_samples else 0)) * cycle_s
    panels = (("position (mm)", ("x_ref", "position"), 1e3),
              ("velocity (mm/min)", ("velocity", "velocity_offset"), 1.0 / MM_PER_MIN),
              ("force (N)", ("force", "force_offset"), 1.0))
    figure = new_figure(10.0, 7.0)
    axes = figure.subplots(len(panels), 1, sharex=True)
    k = bucket_size(recording.n_samples, TRACE_POINTS)
    for ax, (label, names, scale) in zip(axes, panels):
        for name in (n for n in names if n in recording.channels):
            t_d, y_d = minmax_decimate(t, recording.channels[name][None, :] * scale, k)
            ax.plot(t_d, y_d[0], lw=0.7, label=name)
        _shade_windows(ax, recording, t, cycle_s)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("time (s)")
    return Plot("key time traces", png_of(figure))


def _shade_windows(ax, recording: Recording, t: np.ndarray, cycle_s: float) -> None:
    for kind, color in SHADED_KINDS.items():
        for w in recorded_windows(recording, kind):
            ax.axvspan(t[w.start], t[w.stop - 1] + cycle_s, color=color, alpha=0.12, lw=0)


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
    ]
    try:
        limits = Limits.from_config(recording.config.get("limits", {}))
    except ValueError:
        return out
    return out + headroom(recording, limits)


def headroom(recording: Recording, limits: Limits) -> list[Indicator]:
    """Peak |force|, peak |velocity| and position range against the watched limits."""
    ch = recording.channels
    if not recording.n_samples:
        return []
    peak_force = float(np.max(np.abs(ch["force"])))
    peak_velocity = float(np.max(np.abs(ch["velocity"])))
    low, high = float(ch["position"].min()), float(ch["position"].max())
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


@report_result("chirp")
def chirp_results(recording: Recording, result: dict, section: RunSection) -> None:
    """Servo mobility |H1| with coherence, anti-resonance f_t and resonance f_r marked."""
    frf = result["frf"]
    f = np.array(frf["f_hz"])
    figure = new_figure(8.0, 5.5)
    magnitude, coherence = figure.subplots(2, 1, sharex=True, height_ratios=(2, 1))
    magnitude.semilogy(f, frf["H1_abs"], lw=1.2, label="|H1| motor velocity / motor force")
    for key, name in (("antiresonance_hz", "f_t"), ("resonance_hz", "f_r")):
        magnitude.axvline(result[key], color="k", ls="--", lw=0.8)
        magnitude.annotate(f"{name} {result[key]:.1f} Hz", (result[key], 1.0),
                           xycoords=("data", "axes fraction"), ha="left", va="top", fontsize=8)
    magnitude.set_ylabel("|H| ((m/s)/N)")
    magnitude.grid(alpha=0.3, which="both")
    magnitude.legend(fontsize=8, loc="lower left")
    coherence.plot(f, frf["coherence"], lw=1.0, color="C2")
    coherence.axhline(MIN_COHERENCE, color="r", ls=":", lw=0.8)
    coherence.set_ylim(0.0, 1.05)
    coherence.set_ylabel("coherence γ²")
    coherence.set_xlabel("frequency (Hz)")
    coherence.grid(alpha=0.3)
    section.plots.append(Plot("servo mobility (H1, Welch) with coherence", png_of(figure)))
    min_coherence = min(frf["coherence"]) if frf["coherence"] else float("nan")
    section.tables.append(Table("servo mobility", ("quantity", "value"), (
        ("anti-resonance f_t (Eq. 4.13)", f"{result['antiresonance_hz']:.2f} Hz"),
        ("resonance f_r (Eq. 4.14)", f"{result['resonance_hz']:.2f} Hz"),
        ("sweeps averaged", str(result["n_sweeps"])),
    )))
    section.quality.append(Indicator("min coherence in the band", f"{min_coherence:.4f}",
                                     min_coherence >= MIN_COHERENCE))
    section.quality.append(Indicator("FRF warnings", "; ".join(result["warnings"]) or "none",
                                     not result["warnings"]))
    section.headline = f"f_t {result['antiresonance_hz']:.1f} Hz, f_r {result['resonance_hz']:.1f} Hz"


# assembly

def analyze(recording: Recording) -> dict:
    """The experiment's own analysis of the recording (`analyze_recording`)."""
    from feedbench.bench import EXPERIMENTS

    return EXPERIMENTS[recording.experiment].analyze_recording(recording)


def run_section(recording: Recording) -> RunSection:
    """Configuration, traces, results and quality of one recorded run."""
    section = RunSection(recording.metadata.get("run_id", recording.path.stem),
                         recording.experiment, recording.status)
    section.quality += run_quality(recording)
    section.plots.append(trace_plot(recording))
    draw = REPORT_RESULTS.get(recording.experiment)
    if draw is None:
        section.quality.append(Indicator("results", "no report drawing for this experiment"))
    else:
        try:
            draw(recording, analyze(recording), section)
        except Exception as exc:  # an aborted run may be too short to analyse: say so
            section.quality.append(Indicator("analysis", f"failed: {type(exc).__name__}: {exc}",
                                             False))
    section.tables.append(config_table(recording))
    return section


def write_report(runs: Sequence[str | Path], path: str | Path,
                 title: str = "feedbench campaign report") -> Path:
    """Write the HTML report of recordings `runs` to `path`; returns the path."""
    sections = [run_section(open_recording(run)) for run in runs]
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
    out = [f"<h2 id='{html.escape(section.run_id)}'>{html.escape(section.run_id)} — "
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

