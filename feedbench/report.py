"""The campaign report: one self-contained HTML file a person would rather look at than read.

Per run: its configuration, the key time traces (min/max-decimated so spikes stay), the
experiment's results (plots and a table in engineering units) and the quality indicators
(status, gaps, limit headroom, fit and coherence quality). Plots are PNGs drawn with
matplotlib's Agg canvas (no pyplot state, no display) and embedded as base64, so the file
needs no network and no other file to be viewed.

Each run's results are its experiment family's: `Experiment.analyze` computes them and
`Experiment.report` draws them into the run's section (`feedbench.engine.family`); this
module lays the sections out and knows no family by name. A closure result (`feedbench closure …
--report FILE`) gets a section of its own (`closure_section`): held-out residual before and
after, the effects found, the replay errors.
"""

from __future__ import annotations

import base64
import html
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Sequence

import numpy as np

from feedbench.analysis.closure.units import axis_unit
from feedbench.daq.live import bucket_size, minmax_decimate
from feedbench.daq.recording import Recording, open_recording
from feedbench.daq.timing import MISSED_TARGET, CycleTiming, recorded_timing
from feedbench.engine.family import families, judged_analysis
from feedbench.engine.limits import Limits
from feedbench.engine.plan import recorded_windows
from feedbench.units import MM_PER_MIN, RPM
from feedbench.views.sections import (
    LEGEND_BESIDE, Indicator, Plot, RunSection, Table, new_figure, png_of,
)

if TYPE_CHECKING:
    from matplotlib.figure import Figure as MplFigure

TRACE_POINTS = 3000
"""Min/max buckets per trace: enough for a 1000-pixel-wide plot at any run length."""

SHADED_KINDS = {"measure": "#2ca02c", "excite": "#ff7f0e"}

TRACE_PANELS = (
    ("position", "mm", ("x_ref", "position", "load_position"), 1e3),
    ("velocity", "mm/min", ("velocity", "velocity_offset"), 1.0 / MM_PER_MIN),
    ("force", "N", ("force", "force_offset", "excitation", "load_cell.force"), 1.0),
    ("spindle speed", "rpm", ("spindle_speed",), 1.0 / RPM),
)
"""Per-cycle panels of the key traces: quantity, unit on a linear axis (a rotary axis's at
the same scale, `axis_unit`: mrad, mrad/min, N·m), channels by name (a drive's also as
``drive.name``), scale from the stored SI unit to the one shown."""

ROTARY_QUANTITIES = {"position": "angle", "velocity": "angular velocity", "force": "torque"}
"""A trace panel's quantity on a rotary axis."""

STREAM_PANELS = (("DAQ forces", "N", "N"), ("accelerations", "m/s^2", "m/s²"))
"""Panels of the high-rate streams' channels: title, unit as recorded, unit as shown."""

SMALL_MULTIPLES = 3
"""A stream panel with more channels than this is drawn as one panel per channel."""


# figures

PanelTrace = tuple[np.ndarray, np.ndarray, str]
"""One line of a panel: time (s), values as shown, channel name."""


def cycle_times(recording: Recording) -> tuple[np.ndarray, float]:
    """Each recorded cycle's time from the run's first (s), and the bus cycle (s)."""
    cycle_s = float(recording.metadata.get("cycle_s", 1e-3))
    first = recording.cycle[0] if recording.n_samples else 0
    return (recording.cycle - first) * cycle_s, cycle_s


def trace_panels(recording: Recording) -> list[tuple[str, list[PanelTrace]]]:
    """The panels of `trace_plot`, those with a trace: (y label, traces). A rotary axis's
    (`Recording.rotary`: an imported joint) as angle (mrad), angular velocity (mrad/min)
    and torque (N·m)."""
    t, _ = cycle_times(recording)
    rotary = recording.rotary
    panels = [(f"{ROTARY_QUANTITIES.get(quantity, quantity) if rotary else quantity} "
               f"({axis_unit(unit, rotary)})",
               [(t, recording.channels[n] * scale, n) for n in drive_channels(recording, names)])
              for quantity, unit, names, scale in TRACE_PANELS]
    for title, unit, shown in STREAM_PANELS:
        traces = stream_traces(recording, unit)
        panels += ([(shown, [trace]) for trace in traces]  # the channel named in its legend
                   if len(traces) > SMALL_MULTIPLES else [(f"{title} ({shown})", traces)])
    return [(label, traces) for label, traces in panels if traces]


def trace_plot(recording: Recording) -> Plot:
    """Positions (mm), velocities (mm/min), forces (N) (a rotary axis's in mrad, mrad/min,
    N·m), spindle speed (rpm) and the DAQ's forces and accelerations over the run (more
    than `SMALL_MULTIPLES` channels of a unit: a panel each; `trace_panels`), measure and
    excite windows shaded."""
    t, cycle_s = cycle_times(recording)
    panels = trace_panels(recording)
    figure = new_figure(10.0, 7.0 if len(panels) <= 3 else max(9.5, 1.4 * len(panels)),
                        layout="column")
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
        ax.legend(loc="upper left", bbox_to_anchor=LEGEND_BESIDE, fontsize=8)
    axes[-1].set_xlabel("time (s)")
    return Plot("key time traces", png_of(figure))


def timing_plot(timing: CycleTiming) -> Plot:
    """A real-time run's lateness histogram (µs; `daq.timing`), log count axis."""
    edges = np.asarray(timing.histogram_edges_us)
    figure = new_figure(10.0, 3.2)
    ax = figure.subplots()
    ax.stairs(timing.histogram_counts, edges, fill=True, alpha=0.6)
    ax.axvline(timing.lateness_p99_us, color="k", ls="--", lw=0.8,
               label=f"p99 {timing.lateness_p99_us:.0f} µs")
    ax.set_yscale("log")
    ax.set_xlabel("lateness of the cycle's TPDOs behind the run's fastest answer (µs)")
    ax.set_ylabel("cycles")
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(alpha=0.3)
    return Plot(f"cycle timing: lateness histogram ({timing.received} cycles, "
                f"{1e-3 / timing.cycle_s:g} kHz)", png_of(figure))


def drive_channels(recording: Recording, names: Sequence[str]) -> list[str]:
    """The recording's channels among `names`, a drive's as ``name`` or ``drive.name`` (a
    drive: a prefix with its own statusword, e.g. master and slave of a rack-and-pinion
    axis)."""
    drives = {c.rsplit(".", 1)[0] for c in recording.channels if c.endswith(".statusword")}
    return [c for c in recording.channels
            if c in names or ("." in c and c.split(".", 1)[0] in drives
                              and c.split(".", 1)[1] in names)]


def stream_traces(recording: Recording, unit: str) -> list[PanelTrace]:
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
    return Table("configuration", ("key", "value"), rows, folded=True)


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


def timing_quality(timing: CycleTiming) -> list[Indicator]:
    """A real-time run's cycles: missed, repeated, late (`daq.timing`), lateness."""
    share = 100.0 / max(timing.expected, 1)
    return [
        Indicator("bus cycles (real time)", f"{timing.received} of {timing.expected} received, "
                  f"{timing.missed} missed ({share * timing.missed:.3f} %)",
                  timing.missed_share <= MISSED_TARGET),
        Indicator("repeated / late cycles", f"{timing.repeated} ({share * timing.repeated:.3f} "
                  f"%) / {timing.late} ({share * timing.late:.3f} %)"),
        Indicator("lateness", f"p50 {timing.lateness_p50_us:.0f} µs, p99 "
                  f"{timing.lateness_p99_us:.0f} µs, max {timing.lateness_max_us:.0f} µs"),
    ]


def stream_quality(recording: Recording) -> list[Indicator]:
    """Samples and lost samples of every high-rate stream (the DAQ's counter)."""
    return [Indicator(f"{name} stream", f"{stream.n_samples} samples at {stream.rate_hz:g} Hz, "
                      f"{stream.n_dropped} lost", stream.n_dropped == 0)
            for name, stream in recording.streams.items()]


# assembly

def run_section(recording: Recording, truth: Mapping[str, Any] | None = None,
                result: Mapping[str, Any] | None = None) -> RunSection:
    """Configuration, traces, results and quality of one recorded run; the results drawn by
    the recording's experiment family (`Experiment.report`) from its `result`
    (`judged_analysis`: computed here unless given); with the simulated world's `truth` (the
    run's config knows it, the recording does not) also the family's identified-vs-true
    table (`Experiment.truth_table`)."""
    section = RunSection(recording.metadata.get("run_id", recording.path.stem),
                         recording.experiment, recording.status)
    section.quality += run_quality(recording)
    section.plots.append(trace_plot(recording))
    timing = recorded_timing(recording)
    if timing is not None and timing.received:
        section.quality += timing_quality(timing)
        section.plots.append(timing_plot(timing))
    experiment = families().get(recording.experiment)
    if experiment is None:
        section.quality.append(Indicator("results", "no analysis for this experiment"))
    else:
        try:
            result = result or judged_analysis(experiment, recording)
            section.headline = experiment.headline(result)
            section.quality = with_checks(section.quality, result["checks"])
            experiment.report(recording, result, section)
            if truth is not None:
                section.tables.insert(0, experiment.truth_table(result, truth))
        except Exception as exc:  # an aborted run may be too short to analyse: say so
            section.quality.append(Indicator("analysis", f"failed: {type(exc).__name__}: {exc}",
                                             False))
    section.tables.append(config_table(recording))
    return section


def with_checks(shown: Sequence[Indicator], checks: Sequence[Mapping[str, Any]]
                ) -> list[Indicator]:
    """The quality rows `shown` with a result's checks (`analysis.checks`), a failed one's
    reason beside its value: a check of a row already shown (the run's status, gaps) takes
    its place, the others follow."""
    rows = {c["name"]: Indicator(c["name"], c["value"] + (f" — {c['reason']}" if c["reason"]
                                                           else ""), c["ok"]) for c in checks}
    names = {ind.name for ind in shown}
    return ([rows.get(ind.name, ind) for ind in shown]
            + [row for name, row in rows.items() if name not in names])


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
            (name, *(text(replay[when][key]) for when in ("before", "after")))
            for name, key, text in REPLAY_ROWS)))
    section.quality += [
        Indicator("held-out force NRMSE before → after",
                  f"{100 * data['error_before']:.2f} % → {100 * data['error_after']:.2f} %",
                  data["error_after"] <= data["error_before"]),
        Indicator("fit on / judged on", f"{data['fit_data']} / {data['holdout_data']}"),
        Indicator("why the search stopped", data["stopped"]),
    ]
    if data["tip_error_before"] is not None:
        section.quality.insert(1, Indicator(
            "held-out tip acceleration NRMSE before → after",
            f"{100 * data['tip_error_before']:.2f} % → {100 * data['tip_error_after']:.2f} %",
            data["tip_error_after"] <= data["tip_error_before"]))
    section.headline = (f"{findings}: "
                        f"{100 * data['error_before']:.2f} % → {100 * data['error_after']:.2f} %")
    return section


REPLAY_ROWS = (
    ("force NRMSE", "force", lambda x: f"{100 * x:.2f} %"),
    ("position NRMSE", "position", lambda x: f"{100 * x:.2f} %"),
    ("tracking error NRMSE", "tracking", lambda x: f"{100 * x:.2f} %"),
    ("FRF |H| error (dB RMS)", "frf_magnitude_db", lambda x: f"{x:.2f} dB"),
    ("FRF phase error (° RMS)", "frf_phase_deg", lambda x: f"{x:.1f}°"),
)
"""Rows of the closed-loop replay table: NRMSEs in % (as everywhere in the report)."""

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
    ax.plot(time_s, before, ".", ms=1.5,
            label=f"before: NRMSE {100 * result.error_before:.2f} %")
    ax.plot(time_s, after, ".", ms=1.5,
            label=f"after ({findings}): NRMSE {100 * result.error_after:.2f} %")
    ax.set_xlabel("time in the held-out data (s)")
    ax.set_ylabel("force residual (N)")
    ax.grid(alpha=0.3)
    ax.legend(markerscale=6, fontsize=8)
    return figure


def write_report(runs: Sequence[str | Path], path: str | Path,
                 title: str = "feedbench campaign report", closures: Sequence[Any] = (),
                 truths: Mapping[str, Mapping[str, Any]] | None = None) -> Path:
    """Write the HTML report of recordings `runs` (and of `closures`, closure results) to
    `path`; returns the path. `truths`: per run (as given in `runs`, a str) the simulated
    world's truth, for the identified-vs-true tables (`feedbench demo` passes its
    `demo.example_truth`; the recording holds no truth: the host never reads [bench.world])."""
    truths = truths or {}
    sections = [run_section(open_recording(run), truths.get(str(run))) for run in runs]
    sections += [closure_section(report) for report in closures]
    return write_sections(sections, path, title)


def write_sections(sections: Sequence[RunSection], path: str | Path, title: str) -> Path:
    """Write the HTML report of sections drawn already (`feedbench demo` draws each run's in
    the worker process that ran it) to `path`; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(render_html(sections, title), encoding="utf-8")
    return path


STYLE = """
body{font-family:system-ui,sans-serif;margin:2em auto;max-width:1100px;color:#222}
h1{border-bottom:2px solid #444}h2{margin-top:2em;border-bottom:1px solid #aaa}
table{border-collapse:collapse;margin:0.8em 0}td,th{border:1px solid #ccc;padding:3px 8px;
text-align:left;font-size:0.9em;vertical-align:top}th{background:#eee}.ok{color:#1a7f37}
.bad{color:#c0392b;font-weight:bold}img{max-width:100%;display:block;margin:0.5em 0}
figure{margin:1em 0}figcaption{font-size:0.9em;color:#555}details{margin:0.4em 0}
summary{cursor:pointer;color:#444}a.top{font-size:0.8em;margin-left:1em;font-weight:normal}
"""

MARKS = {True: "<span class='ok'>✔</span>", False: "<span class='bad'>✘</span>", None: ""}
"""The verdict of a checked row: passed, failed; an informative row has none."""


def render_html(sections: Sequence[RunSection], title: str) -> str:
    """The whole report as one HTML document (no external resources): the contents (per
    run what it measured and whether every check passed, linked to its section), then the
    sections."""
    parts = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
             f"<title>{html.escape(title)}</title><style>{STYLE}</style></head><body>",
             f"<h1 id='contents'>{html.escape(title)}</h1>", _contents_html(sections)]
    parts += [_section_html(s) for s in sections]
    parts.append("</body></html>")
    return "\n".join(parts)


def verdict(section: RunSection) -> tuple[bool, str]:
    """Whether every checked quality row of a section passed, and the failed ones named."""
    failed = [ind.name for ind in section.quality if ind.ok is False]
    checked = sum(ind.ok is not None for ind in section.quality)
    if failed:
        return False, f"{len(failed)} of {checked} checks failed: {', '.join(failed)}"
    return True, f"all {checked} checks passed"


def _anchor(section: RunSection) -> str:
    return "-".join(section.run_id.split())  # an HTML id has no white space


def _contents_html(sections: Sequence[RunSection]) -> str:
    """The first screen: a row per run, linked to its section."""
    rows = []
    for s in sections:
        ok, text = verdict(s)
        rows.append(f"<tr><td><a href='#{html.escape(_anchor(s))}'>{html.escape(s.run_id)}</a>"
                    f"</td><td>{html.escape(s.experiment)}</td><td>{html.escape(s.status)}</td>"
                    f"<td>{html.escape(s.headline)}</td><td>{MARKS[ok]} {html.escape(text)}</td>"
                    "</tr>")
    head = "".join(f"<th>{h}</th>" for h in ("run", "experiment", "status", "what it measured",
                                             "is it good"))
    return (f"<h2>contents</h2><table><tr>{head}</tr>{''.join(rows)}</table>")


def _section_html(section: RunSection) -> str:
    out = [f"<h2 id='{html.escape(_anchor(section))}'>{html.escape(section.run_id)} — "
           f"{html.escape(section.experiment)}<a class='top' href='#contents'>contents</a></h2>",
           "<h3>quality</h3>", _quality_html(section.quality)]
    for plot in section.plots:
        data = base64.b64encode(plot.png).decode("ascii")
        out.append(f"<figure><img alt='{html.escape(plot.title)}' "
                   f"src='data:image/png;base64,{data}'><figcaption>{html.escape(plot.title)}"
                   "</figcaption></figure>")
    out += [_table_html(table) for table in section.tables]
    return "\n".join(out)


def _lines_html(text: str) -> str:
    return "<br>".join(html.escape(line) for line in text.split("\n"))


def _quality_html(indicators: Sequence[Indicator]) -> str:
    rows = []
    for ind in indicators:
        details = ("" if not ind.details else
                   f"<details><summary>details ({len(ind.details)})</summary><ul>"
                   + "".join(f"<li>{html.escape(d)}</li>" for d in ind.details)
                   + "</ul></details>")
        rows.append(f"<tr><td>{MARKS[ind.ok]}</td><td>{html.escape(ind.name)}</td>"
                    f"<td>{_lines_html(ind.value)}{details}</td></tr>")
    return "<table>" + "".join(rows) + "</table>"


def _table_html(table: Table) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in table.header)
    body = "".join("<tr>" + "".join(f"<td>{_lines_html(c)}</td>" for c in row) + "</tr>"
                   for row in table.rows)
    if table.folded:
        return (f"<details><summary>{html.escape(table.title)} ({len(table.rows)} rows)"
                f"</summary><table><tr>{head}</tr>{body}</table></details>")
    return f"<h3>{html.escape(table.title)}</h3><table><tr>{head}</tr>{body}</table>"
