"""Shared by the tool-tip experiments (impact hammer, sine-stream, shaker chirp; Ch. 3.5.1, 5.3,
5.5.3): excitation windows laid out in passes at a constant feed, the exciter commanded from
the plan through the CiA 401 I/O module, the DAQ samples of a recorded window, how a
tool-tip FRF per feed is shown (live panels, report plot and indicators, labels) and the
stability lobes it predicts.

A window is a stretch of cycles with an exciter command (a hit, a sine step, a sweep). At a
feed the axis accelerates, settles, runs windows back to back while the pass fits the stroke,
and stops; the next pass goes the other way. Idle (feed 0) the axis holds position. Windows
are never split by a reversal.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from feedbench.analysis.checks import check, peak_checks
from feedbench.analysis.stability import Lobes, zoa_lobes
from feedbench.config import Field, non_negative, positive
from feedbench.engine.plan import Plan, Segment, Window, recorded_windows
from feedbench.experiments.signals import integrate_velocity, ramp_to_feed
from feedbench.models.milling import engagement_angles
from feedbench.protocols.serial_frames import CHANNEL_INDEX, CHANNELS
from feedbench.units import MM_PER_MIN
from feedbench.views.frfs import Dof
from feedbench.views.panels import Curve, Panel, phase_panel
from feedbench.views.sections import (
    MIN_COHERENCE, FrfSeries, Plot, RunSection, Table, frf_figure, new_figure, png_of,
)

DAQ_STREAM = "daq"
RESPONSE_CHANNEL = "acc_tool_x"
"""The tool-side accelerometer along the feed (the flexure's direction)."""
FORCE_CHANNELS = {"shaker": "shaker_force", "actuator": "actuator_force",
                  "hammer": "hammer_force"}
TIP_ACCELERATION = Dof(RESPONSE_CHANNEL, "tool_tip", 2, 1, "acceleration")
"""The accelerometer's end of a tool-tip FRF (node 2, +X along the feed) for export."""


def tip_force(channel: str) -> Dof:
    """The exciter's force end of a tool-tip FRF (node 2, +X)."""
    return Dof(channel, "tool_tip", 2, 1, "force")


COMPLIANCE_LABEL = "|x/F| (m/N)"
"""Axis label of the tool-tip compliance x_tip / F_tip, live and in the report."""

MOTION_SCHEMA = {
    "stroke_mm": Field(float, 200.0, "longest travel of one pass at feed (mm)", positive),
    "settle_s": Field(float, 0.5, "time at feed (or holding) before the first window (s)",
                      positive),
    "accel_m_s2": Field(float, 1.0, "acceleration of the ramps (m/s²)", positive),
    "daq_rate_Hz": Field(int, 10_000, "DAQ sample rate (Hz), a whole number per bus cycle",
                         positive),
    "io_node_id": Field(int, 10, "CANopen node of the CiA 401 I/O module driving the exciter",
                        positive),
}
"""Keys every tool-tip experiment shares (engineering units)."""

FEEDS_FIELD = Field(list, [0.0, 500.0, 1000.0], "axis feeds (mm/min); 0 holds position",
                    non_negative)


@dataclass(frozen=True)
class ExcitationWindow:
    """Cycles of one excitation: the exciter command (N) per cycle, label, info for analysis."""

    label: str
    command: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def n_cycles(self) -> int:
        return len(self.command)


def windows_at_feed(windows: Sequence[ExcitationWindow], feed_mm_min: float, x0: float,
                    p: Any, cycle_s: float, direction: float = 1.0
                    ) -> tuple[list[Segment], float, float]:
    """Segments running `windows` at a feed (mm/min) from position x0 (m); `p`: typed
    parameters with `MOTION_SCHEMA`'s ``settle_s``, ``stroke_mm``, ``accel_m_s2``.

    Returns the segments, the end position and the direction of the next pass. Each pass:
    accelerate, settle, windows (kind ``excite``, info with ``feed_mm_min``), stop.
    """
    speed = feed_mm_min * MM_PER_MIN
    n_settle = int(round(p.settle_s / cycle_s))
    segments: list[Segment] = []
    for group in _passes(windows, speed * cycle_s, p.stroke_mm * 1e-3, n_settle):
        velocity = direction * speed
        up = ramp_to_feed(0.0, velocity, p.accel_m_s2, cycle_s) if speed else np.zeros(0)
        down = ramp_to_feed(velocity, 0.0, p.accel_m_s2, cycle_s) if speed else np.zeros(0)
        cruise = np.full(n_settle + sum(w.n_cycles for w in group), velocity)
        path = integrate_velocity(np.concatenate([up, cruise, down]), x0, cycle_s)
        info = {"feed_mm_min": direction * feed_mm_min}
        label = f"{feed_mm_min:g} mm/min"
        cuts = np.cumsum([0, len(up), n_settle] + [w.n_cycles for w in group])
        segments.append(Segment(f"accelerate {label}", "move", path[:cuts[1]], info=info))
        segments.append(Segment(f"settle {label}", "settle", path[cuts[1]:cuts[2]], info=info))
        for w, a, b in zip(group, cuts[2:-1], cuts[3:]):
            segments.append(Segment(f"{w.label} at {label}", "excite", path[a:b],
                                    info={**info, **w.info}, excitation=w.command))
        segments.append(Segment(f"stop {label}", "move", path[cuts[-1]:], info=info))
        x0 = float(path[-1]) if path.size else x0
        direction = -direction if speed else direction
    return [s for s in segments if s.n_cycles], x0, direction


def _passes(windows: Sequence[ExcitationWindow], step: float, stroke: float,
            n_settle: int) -> list[list[ExcitationWindow]]:
    """Windows grouped into passes whose settle + windows travel at most `stroke` (m) at
    `step` (m per cycle); a window longer than a pass gets a pass of its own."""
    groups: list[list[ExcitationWindow]] = [[]]
    used = n_settle * step
    for window in windows:
        travel = window.n_cycles * step
        if groups[-1] and used + travel > stroke:
            groups.append([])
            used = n_settle * step
        groups[-1].append(window)
        used += travel
    return [g for g in groups if g]


def plan_over_feeds(name: str, mode: int, feeds: Sequence[float],
                    windows_of_feed, p: Any, cycle_s: float, exciter: str) -> Plan:
    """A plan running `windows_of_feed(feed)` at each feed in turn, passes alternating (`p`
    typed; the plan's `Plan.params` its dict)."""
    segments: list[Segment] = []
    x, direction = 0.0, 1.0
    for feed in feeds:
        more, x, direction = windows_at_feed(windows_of_feed(feed), feed, x, p, cycle_s,
                                             direction)
        segments += more
    return Plan(name, mode, segments, asdict(p), cycle_s, exciter=exciter)


def daq_needs(p: Any, exciter: str) -> dict[str, dict[str, Any]]:
    """The devices a tool-tip experiment needs (`p` typed): the DAQ (response and exciter
    force) and the I/O module commanding the exciter."""
    return {"daq": {"channels": [RESPONSE_CHANNEL, FORCE_CHANNELS[exciter]],
                    "rate_hz": p.daq_rate_Hz},
            "exciter": {"node_id": p.io_node_id}}


def window_samples(recording, window: Window, channels: Sequence[str]
                   ) -> tuple[np.ndarray, list[str]]:
    """DAQ samples (channels × n) of a recorded window and notes on their quality.

    The stream's samples whose bus cycle lies in the window; a gap in the sample counter
    inside the window is noted (the window should not be used as a record).
    """
    stream = recording.streams[DAQ_STREAM]
    first, last = int(recording.cycle[window.start]), int(recording.cycle[window.stop - 1])
    inside = (stream.cycle >= first) & (stream.cycle <= last)
    notes = []
    if np.any(np.diff(stream.sequence[inside]) != 1):
        notes.append(f"{window.label}: DAQ samples lost inside the window")
    return np.vstack([stream.channels[c][inside] for c in channels]), notes


def whole_windows(recording, kind: str = "excite") -> tuple[list[Window], list[str]]:
    """The recorded windows of `kind` spanning as many bus cycles as the longest (every
    record of a hammer or shaker plan does) and notes on the others: cut short by a stop
    (an aborted run's last window), they are left out."""
    windows = recorded_windows(recording, kind)
    spans = [int(recording.cycle[w.stop - 1]) - int(recording.cycle[w.start]) + 1
             for w in windows]
    whole = max(spans, default=0)
    notes = [f"{w.label}: cut short by the stop ({n} of {whole} cycles), left out"
             for w, n in zip(windows, spans) if n < whole]
    return [w for w, n in zip(windows, spans) if n == whole], notes


def records_check(what: str, count: int, notes: Sequence[str]) -> dict:
    """At least one record (`what`: "hits", "sweeps") analysed; none (a run stopped before
    its first whole one, or every one left out) leaves nothing to analyse."""
    return check(f"{what} analysed", str(count), count > 0,
                 f"no usable {what} recorded ({'; '.join(notes) or 'no excite segment'}): "
                 "nothing to analyse")


def overloaded(samples: np.ndarray, channels: Sequence[str], share: float = 0.98) -> bool:
    """True when any channel reaches `share` of its full scale (the ADC clips there)."""
    scale = np.array([CHANNELS[CHANNEL_INDEX[c]].full_scale for c in channels])
    return bool(np.any(np.abs(samples).max(axis=1, initial=0.0) >= share * scale))


def full_scale(channel: str) -> float:
    """The DAQ input's full scale (SI)."""
    return CHANNELS[CHANNEL_INDEX[channel]].full_scale


# a tool-tip FRF per feed (the hammer's and the shaker chirp's results: each feed's
# ``feed_mm_min``, ``peak_hz``, ``min_coherence`` and ``frf`` with ``f_hz``,
# ``compliance_abs``, ``coherence``), as the live window, the report and the demo show it

def feed_label(feed_mm_min: float) -> str:
    """``500 mm/min`` (|feed|: both directions of a feed are one series)."""
    return f"{abs(float(feed_mm_min)):g} mm/min"


def feed_text(feed_mm_min: float | None) -> str:
    """A feed in a headline; None (no feed from which the FRF is invariant): the highest."""
    return "only the highest feed" if feed_mm_min is None else feed_label(feed_mm_min)


def feed_frf_panels(feeds: Sequence[Mapping[str, Any]]) -> tuple[Panel, Panel, Panel]:
    """Live panels: compliance |x/F| (m/N, log), its phase (°) and coherence γ², one curve
    per feed."""
    def curves(key: str) -> tuple[Curve, ...]:
        return tuple(Curve(feed_label(x["feed_mm_min"]), np.asarray(x["frf"]["f_hz"]),
                           np.asarray(x["frf"][key])) for x in feeds)

    return (Panel("tool-tip compliance", "frequency (Hz)", COMPLIANCE_LABEL,
                  curves("compliance_abs"), log_y=True),
            phase_panel({feed_label(x["feed_mm_min"]): (x["frf"]["f_hz"],
                                                        x["frf"]["compliance_phase_rad"])
                         for x in feeds}),
            Panel("coherence", "frequency (Hz)", "γ²", curves("coherence"),
                  y_range=(0.0, 1.05)))


def feed_frf_summary(feeds: Sequence[Mapping[str, Any]], used: str, recorded: str, unit: str,
                     notes: Sequence[str]) -> str:
    """Live summary: per feed the records `used` of those `recorded` (result keys), the
    compliance peak (Hz) and the lowest coherence in the band; then the latest note."""
    if not feeds:
        return "waiting for the first record" + (f" ({notes[-1]})" if notes else "")
    parts = [f"{feed_label(x['feed_mm_min'])}: {x[used]} of {x[recorded]} {unit}, peak "
             f"{x['peak_hz']:.2f} Hz, min γ² {x['min_coherence']:.3f}" for x in feeds]
    return "; ".join(parts + list(notes[-1:]))


def compliance_plot(feeds: Sequence[Mapping[str, Any]], estimate: str) -> Plot:
    """Report plot: |x/F| (m/N), phase and coherence per feed, each feed's peak marked;
    `estimate` names the FRF."""
    series = [FrfSeries(feed_label(x["feed_mm_min"]), np.array(x["frf"]["f_hz"]),
                        np.array(x["frf"]["compliance_abs"]),
                        np.array(x["frf"]["compliance_phase_rad"]), np.array(x["frf"]["coherence"]))
              for x in feeds]
    marks = [(f"{feed_label(x['feed_mm_min'])}: {x['peak_hz']:.1f} Hz", x["peak_hz"])
             for x in feeds]
    return Plot(f"tool-tip compliance per feed ({estimate}): magnitude, phase, coherence",
                png_of(frf_figure(series, COMPLIANCE_LABEL, marks=marks)))


def feed_lobes(feeds: Sequence[Mapping[str, Any]],
               compliance: Callable[[Mapping[str, Any]], np.ndarray], section: RunSection) -> None:
    """Report: the stability lobes (`lobes_results`) of the lowest and the highest feed
    (Fig. 5.25); `compliance(feed)` gives a feed's complex x/F (m/N) at its ``f_hz``."""
    lobes_results(extreme_feeds({feed_label(x["feed_mm_min"]): (np.array(x["frf"]["f_hz"]),
                                                                compliance(x))
                                 for x in feeds}), section)


def feed_checks(feeds: Sequence[Mapping[str, Any]], notes: Sequence[str],
                *more: dict) -> list[dict]:
    """A tool-tip result's checks: the lowest coherence of the feeds in the band (gate
    `MIN_COHERENCE`), each feed's compliance peak a mode inside the band with a high
    coherence (`analysis.checks.peak_checks`), `more`, and the records left out (notes)."""
    worst = min(feeds, key=lambda x: x["min_coherence"] if np.isfinite(x["min_coherence"])
                else -1.0)  # an undefined coherence (a constant channel) is the worst
    low, where = worst["min_coherence"], feed_label(worst["feed_mm_min"])
    reason = (f"no coherence at {where}: a channel is constant (unplugged?)"
              if not np.isfinite(low) else
              f"γ² {low:.3f} at {where}, below {MIN_COHERENCE:g}: the response is not all "
              "from this excitation (noise, a loose sensor, nonlinearity)")
    peaks = [(feed_label(x["feed_mm_min"]), x["peak_hz"], x["frf"]["f_hz"],
              x["frf"]["coherence"]) for x in feeds]
    return [check("min coherence in the band", f"{low:.4f}", low >= MIN_COHERENCE, reason),
            *peak_checks(peaks, MIN_COHERENCE), *more,
            check("notes", "; ".join(notes) or "none", not notes,
                  "records were left out: the averages hold fewer of them")]


# stability lobes from a measured tool-tip FRF (drawn in the hammer's and the shaker chirp's
# report sections)

@dataclass(frozen=True)
class CuttingTest:
    """A milling operation for stability lobes (ZOA): tool diameter D (m), teeth Z, radial
    engagement a_e (m) in `mode`, cutting coefficients K_tc, K_rc (N/m²)."""

    D: float
    Z: int
    a_e: float
    mode: str
    K_tc: float
    K_rc: float


TABLE_5_1 = CuttingTest(D=40e-3, Z=4, a_e=32e-3, mode="down", K_tc=1885e6, K_rc=749e6)
"""Tables 4.2 / 5.1: Walter F4042 (D 40 mm, Z 4, κ 90°), a_e 32 mm down-milling, C45 steel:
the cut the thesis predicts the lobes of from idle and in-motion FRFs (Fig. 5.25)."""

LOBE_SPEEDS_RPM = np.linspace(400.0, 2000.0, 801)
"""Spindle speeds of the lobes (Fig. 5.25: 400–1500 rpm; up to 2000 for lobe 0 of a
47–61 Hz mode with 4 teeth)."""


def tool_tip_lobes(f: np.ndarray, compliance: np.ndarray,
                   cut: CuttingTest = TABLE_5_1) -> Lobes:
    """ZOA stability lobes (Altintas & Budak; Ch. 5.5.6) of `cut` from the tool-tip
    compliance x/F (m/N) measured along the feed. The lab bench's flexure moves along the
    feed only, so the y direction is taken as rigid: Φ = [[Φ_xx, 0], [0, 0]]."""
    phi = np.zeros((len(f), 2, 2), dtype=complex)
    phi[:, 0, 0] = compliance
    start, stop = engagement_angles(cut.a_e, cut.D, cut.mode)
    return zoa_lobes(np.asarray(f, dtype=float), phi, LOBE_SPEEDS_RPM, cut.Z, cut.K_tc,
                     cut.K_rc / cut.K_tc, start, stop)


LOBE_DEPTH_SPAN = 4.0
"""The lobes are drawn up to this many times the largest absolute limit (min a_lim) of the
FRFs: the region a cut is planned in; higher lobe tips are clipped (and said so)."""


def lobes_results(compliances: dict[str, tuple[np.ndarray, np.ndarray]],
                  section: RunSection) -> None:
    """Stability lobes of each named compliance (Table 5.1's cut) as a plot and a table,
    the depth axis clipped to `LOBE_DEPTH_SPAN` × the largest min a_lim, and the speeds
    without a lobe (its chatter frequency outside the measured band) shaded and listed."""
    figure = new_figure(8.0, 4.5)
    ax = figure.subplots()
    lobes = {label: tool_tip_lobes(f, compliance) for label, (f, compliance) in compliances.items()}
    top = LOBE_DEPTH_SPAN * max(x.min_depth for x in lobes.values()) * 1e3
    rows = []
    for label, x in lobes.items():
        line, = ax.plot(x.spindle_rpm, x.depth * 1e3, lw=1.2, label=label)
        gaps = _gaps(x.spindle_rpm, ~np.isfinite(x.depth))
        for low, high in gaps:
            ax.axvspan(low, high, color=line.get_color(), alpha=0.12, lw=0)
        k = int(np.argmin(x.depth))
        rows.append((label, f"{x.min_depth * 1e3:.3f}", f"{x.spindle_rpm[k]:.0f}",
                     f"{x.chatter_frequency[k]:.1f}",
                     ", ".join(f"{low:.0f}–{high:.0f}" for low, high in gaps) or "none"))
    ax.set_ylim(0.0, top)
    ax.set_xlabel("spindle speed (rpm)")
    ax.set_ylabel(f"critical depth a_lim (mm), clipped at {top:.1f}")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    cut = TABLE_5_1
    ax.set_title(f"ZOA, Table 5.1: D {cut.D * 1e3:g} mm, Z {cut.Z}, a_e {cut.a_e * 1e3:g} mm "
                 f"{cut.mode}-milling, K_tc {cut.K_tc * 1e-6:g}, K_rc {cut.K_rc * 1e-6:g} N/mm²\n"
                 "shaded: no lobe (its chatter frequency outside the measured band)", fontsize=8)
    section.plots.append(Plot("stability lobes from the measured tool-tip FRF", png_of(figure)))
    section.tables.append(Table("stability lobes (Table 5.1 cut, y taken rigid)",
                                ("FRF", "min a_lim (mm)", "at (rpm)", "chatter (Hz)",
                                 "no lobe at (rpm): chatter frequency outside the FRF's band"),
                                tuple(rows)))


def _gaps(x: np.ndarray, mask: np.ndarray) -> list[tuple[float, float]]:
    """(first, last) x of each run of True in `mask`."""
    edges = np.diff(np.r_[0, mask.astype(int), 0])
    return [(float(x[a]), float(x[b - 1])) for a, b in zip(np.flatnonzero(edges == 1),
                                                           np.flatnonzero(edges == -1))]


def extreme_feeds(compliances: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict:
    """The lowest and the highest feed's compliance (idle and in motion, Fig. 5.25)."""
    labels = list(compliances)
    return {labels[i]: compliances[labels[i]] for i in sorted({0, len(labels) - 1})}
