"""Friction sweep (Ch. 5.3.2, Fig. 5.11; Ch. 5.5.2, Fig. 5.19): constant-feed runs in both
directions, the friction curve and Andersson's law, Eq. (5.2), per direction.

At each feed the axis accelerates, settles, and holds the feed over a measure window;
the mean motor force over that window is the friction force at that velocity, and the
points of each direction are fitted with Eq. (5.2). On an axis driven by several drives
(the rack-and-pinion master and slave, Ch. 3.2) the force is the sum of the drives' forces,
so an electronic preload cancels out, and the velocity is the first drive's.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from feedbench.analysis.checks import check, positive_parameters
from feedbench.analysis.friction import FrictionFit, fit_andersson
from feedbench.config import ConfigError, Field, non_negative, one_of, positive
from feedbench.engine.family import TRUTH_TITLE, Example, Experiment, headline, percent_error
from feedbench.engine.plan import Plan, Segment, Window, recorded_windows
from feedbench.engine.preflight import check_feeds
from feedbench.experiments.signals import constant_feed_move
from feedbench.models.friction import AnderssonFriction
from feedbench.protocols.cia402 import CSP
from feedbench.units import MIN_PER_MM, MM_PER_MIN, N_MIN_PER_MM
from feedbench.views.panels import Curve, Panel, ResultView
from feedbench.views.sections import (
    MIN_R_SQUARED, Plot, RunSection, Table, new_figure, png_of,
)

NAME = "friction_sweep"

SCHEMA = {
    "type": Field(str, NAME, "experiment family"),
    "feeds_mm_min": Field(
        list,
        [25.0, 50.0, 75.0, 100.0, 150.0, 200.0, 300.0, 400.0, 500.0, 700.0, 900.0, 1200.0, 1500.0],
        "feeds to measure at (mm/min)",
        positive,
    ),
    "directions": Field(
        list, ["positive", "negative"], "directions to measure", one_of("positive", "negative")
    ),
    "settle_s": Field(float, 1.0, "time at feed before measuring (s)", positive),
    "settle_mm": Field(float, 0.0, "distance at feed before measuring (mm): each feed settles "
                       "for the longer of settle_s and settle_mm / feed", non_negative),
    "measure_s": Field(float, 0.5, "measure window at each feed (s)", positive),
    "accel_m_s2": Field(float, 1.0, "acceleration of the ramps (m/s²)", positive),
    "k_tanh_min_mm": Field(float, 0.25, "tanh constant of Eq. (5.2), held in the fit (min/mm)",
                           positive),
}

SIGNS = {"positive": 1.0, "negative": -1.0}
MIN_FEEDS = 5
"""Feeds per direction Eq. (5.2)'s fit needs: it has 4 free parameters (F_c, F_s, v_s, σ)
and needs at least one point more (`analysis.friction`); the live view fits a direction
once it has them."""

UNITS = {"F_c": ("N", 1.0, 2), "F_s": ("N", 1.0, 2), "v_s": ("mm/min", MM_PER_MIN, 1),
         "sigma": ("N·min/mm", N_MIN_PER_MM, 5)}
"""Eq. (5.2)'s fitted parameters in the units of Fig. 5.11: unit, its size in SI, decimals."""

STEADY_TOLERANCE = 0.02
"""A measure window is at steady state when its mean velocity is within this fraction of the
commanded feed and its mean force changes by less than this fraction between its halves;
a window that is not is flagged and left out of the fit."""

CURVE_POINTS = 300
"""Points of a fitted law drawn over the range of its direction's feeds."""


def friction_points(
    velocity: np.ndarray, force: np.ndarray, windows: list[Window]
) -> tuple[np.ndarray, np.ndarray]:
    """Mean velocity (m/s) and mean motor force (N) over each measure window."""
    v = np.array([velocity[w.start:w.stop].mean() for w in windows])
    f = np.array([force[w.start:w.stop].mean() for w in windows])
    return v, f


def steady_windows(velocity: np.ndarray, force: np.ndarray, windows: list[Window]) -> np.ndarray:
    """Per measure window whether it is at steady state (`STEADY_TOLERANCE`): mean velocity
    (m/s) at the commanded feed (the window's ``feed_mm_min``) and no drift of the mean force
    (N) between its first and second half."""
    steady = []
    for w in windows:
        feed = w.info["feed_mm_min"] * MM_PER_MIN
        f = force[w.start:w.stop]
        half = len(f) // 2
        drift = abs(f[half:].mean() - f[:half].mean()) if half else 0.0
        steady.append(abs(velocity[w.start:w.stop].mean() - feed) <= STEADY_TOLERANCE * abs(feed)
                      and drift <= STEADY_TOLERANCE * abs(f.mean()))
    return np.array(steady, dtype=bool)


def settle_cycles(p: Any, feed_mm_min: float, cycle_s: float) -> int:
    """Bus cycles at a feed before its measure window: the longer of ``settle_s`` and
    ``settle_mm`` travelled at the feed."""
    return int(round(max(p.settle_s, p.settle_mm / feed_mm_min * 60.0) / cycle_s))


def axis_signals(channels: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Velocity (m/s) and force (N) of the axis: the drive's, or with several drives (named
    channels ``name.velocity``, ``name.force``, see `runner.drive_channels`) the first
    drive's velocity and the sum of their forces."""
    if "force" in channels:
        return channels["velocity"], channels["force"]
    drives = [c.removesuffix(".statusword") for c in channels if c.endswith(".statusword")]
    if not drives:
        raise ValueError("no drive channels recorded (force, or <drive>.statusword and "
                         "<drive>.force)")
    return (channels[f"{drives[0]}.velocity"],
            np.sum([channels[f"{d}.force"] for d in drives], axis=0))


def _fit_summary(fit: FrictionFit) -> dict:
    p, s = fit.params, fit.std
    return {
        "identified": {"F_c": p.F_c, "F_s": p.F_s, "v_s": p.v_s, "sigma": p.sigma},
        "std": {"F_c": s.F_c, "F_s": s.F_s, "v_s": s.v_s, "sigma": s.sigma},
        "rms_N": fit.rms,
        "r_squared": fit.r_squared,
        "n_points": fit.n_points,
    }


def fit_checks(result: Mapping[str, Any]) -> list[dict]:
    """Per fitted direction: R² of Eq. (5.2) over its points at least `MIN_R_SQUARED`, and
    F_c, F_s, v_s > 0; every point's force along its velocity (friction opposes the motion,
    so a flipped force sign fails); the windows not at steady state (left out of the fit)."""
    checks = []
    for direction in (d for d in SIGNS if d in result):
        fit = result[direction]
        checks += [
            check(f"R² of the {direction} fit",
                  f"{fit['r_squared']:.5f} (rms {fit['rms_N']:.2f} N) over its "
                  f"{fit['n_points']} points", fit["r_squared"] >= MIN_R_SQUARED,
                  f"below {MIN_R_SQUARED:g}: Eq. (5.2) does not describe the {direction} points"),
            positive_parameters(f"{direction} fit", {
                k: (fit["identified"][k] / UNITS[k][1], UNITS[k][0])
                for k in ("F_c", "F_s", "v_s")}),
        ]
    points = result["points"]
    v, f = np.asarray(points["velocity_m_s"]), np.asarray(points["force_N"])
    against = [f"{x / MM_PER_MIN:g}" for x in v[np.sign(f) != np.sign(v)]]
    checks.append(check("motor force along the motion", f"{len(v) - len(against)} of {len(v)} "
                        "points", not against,
                        f"at {', '.join(against)} mm/min the drive pulled against the motion: "
                        "the force's sign is flipped (sensor or drive polarity), friction only "
                        "ever needs a push along it"))
    left_out = [f"{x / MM_PER_MIN:g}" for x, ok in zip(points["velocity_m_s"], points["steady"])
                if not ok]
    checks.append(check("windows not at steady state (left out of the fit)",
                        f"{len(left_out)}" + (f": at {', '.join(left_out)} mm/min"
                                              if left_out else ""), not left_out,
                        "the velocity was off the feed or the force still drifting: raise "
                        "settle_s or settle_mm"))
    return checks


def _check_finite(recording, windows: list[Window], v: np.ndarray, f: np.ndarray) -> None:
    """A NaN or inf in a measure window is a `ConfigError` naming the first such window."""
    for name, values in (("velocity", v), ("force", f)):
        if not np.all(np.isfinite(values)):
            label = windows[int(np.argmin(np.isfinite(values)))].label
            raise ConfigError(f"{recording.path}: {name}: NaN or inf samples in the measure "
                              f"window {label!r}")


def _check_feeds(recording, sides: Mapping[str, np.ndarray]) -> None:
    """Fewer than `MIN_FEEDS` points in a direction is a `ConfigError` naming it."""
    for direction, side in sides.items():
        feeds = int(side.sum())
        if feeds < MIN_FEEDS:
            raise ConfigError(f"{recording.path}: {feeds} feeds measured in the {direction} "
                              f"direction; the Andersson fit (Eq. 5.2) needs at least {MIN_FEEDS}")


def law(result: Mapping[str, Any], direction: str) -> AnderssonFriction:
    """The Eq. (5.2) law identified in `direction`, with the tanh constant it was fitted at."""
    return AnderssonFriction(**result[direction]["identified"], k_tanh=result["k_tanh_s_m"])


def fitted_curve(result: Mapping[str, Any], direction: str) -> tuple[np.ndarray, np.ndarray]:
    """Feed (mm/min) and force (N) of the law fitted in `direction`, over its points' range."""
    sign = SIGNS[direction]
    v = np.asarray(result["points"]["velocity_m_s"])
    speed = np.abs(v[np.sign(v) == sign])
    speed = np.linspace(speed.min(), speed.max(), CURVE_POINTS)
    return sign * speed / MM_PER_MIN, sign * law(result, direction).force(speed)


def display(key: str, value: float) -> str:
    """A fitted parameter (SI) in the units of Fig. 5.11 (`UNITS`), 8 characters wide."""
    unit, size, decimals = UNITS[key]
    return f"{value / size:8.{decimals}f} {unit}"


def comparison(result: Mapping[str, Any], truth: Mapping[str, Any]) -> dict:
    """Per direction: the identified parameters, the world's, the error (%) and the std."""
    out = {}
    for direction in SIGNS:
        identified = result[direction]["identified"]
        true = {k: truth["friction"][direction][k] for k in UNITS}
        out[direction] = {
            "identified": identified,
            "truth": true,
            "error_pct": {k: percent_error(identified[k], true[k]) for k in UNITS},
            "std": result[direction]["std"],
        }
    return out


def comparison_lines(compared: Mapping[str, Any]) -> list[str]:
    """`comparison`'s parameters beside the truth with the error, a line each (Fig. 5.11 units)."""
    lines = []
    for direction, comp in compared.items():
        lines.append(f"  {direction}:")
        lines += [f"    {k:<6s} {display(k, comp['identified'][k])}   truth "
                  f"{display(k, comp['truth'][k])}   error {comp['error_pct'][k]:+6.2f} %"
                  for k in UNITS]
    return lines


def parameter_table(result: Mapping[str, Any]) -> Table:
    """Identified parameters ± one standard deviation, in the units of Fig. 5.11."""
    rows = []
    for name, (unit, size, _) in UNITS.items():
        cells = [f"{name} ({unit})"]
        for direction in SIGNS:
            value = result[direction]["identified"][name] / size
            std = result[direction]["std"][name] / size
            cells.append(f"{value:.5g} ± {std:.2g}")
        rows.append(tuple(cells))
    return Table("identified friction parameters", ("parameter", "positive", "negative"),
                 tuple(rows))


def curve_figure(result: Mapping[str, Any]):
    """The friction points and the fitted law per direction, feed (mm/min) against N."""
    v = np.array(result["points"]["velocity_m_s"]) / MM_PER_MIN
    force = np.array(result["points"]["force_N"])
    steady = np.array(result["points"]["steady"], dtype=bool)
    figure = new_figure(8.0, 4.5)
    ax = figure.subplots()
    ax.plot(v[steady], force[steady], "o", ms=4, label="measured (mean of each window), fitted")
    if not steady.all():
        ax.plot(v[~steady], force[~steady], "x", ms=7, color="C3",
                label="not at steady state: left out of the fit")
    for direction in SIGNS:
        ax.plot(*fitted_curve(result, direction), lw=1.5, label=f"Andersson fit, {direction}")
    ax.set_xlabel("feed (mm/min)")
    ax.set_ylabel("motor force (N)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return figure


class FrictionSweep(Experiment):
    """Friction sweep: the friction curve and Eq. (5.2) per direction (Ch. 5.3.2, Fig. 5.11).

    Also on the rack-and-pinion axis (``master.*``/``slave.*`` channels, `axis_signals`).
    """

    name = NAME
    schema = SCHEMA
    title = "friction curve, Eq. (5.2)"
    examples = (
        # --quick: 13 feeds per direction with shorter plateaus (the drive settles in ≈ 50
        # ms): the Eq. (5.2) fit still within 0.3 % of the truth.
        Example(NAME, {"experiment": {"settle_s": 0.4, "measure_s": 0.3}}, rank=10,
                required=True),
        # --quick: 7 feeds instead of 13, shorter plateaus: the Eq. (5.2) fit within 1–3 %.
        Example(f"{NAME}_rack_pinion", {"experiment": {
            "feeds_mm_min": [25, 50, 100, 200, 400, 800, 1500], "settle_s": 0.4,
            "measure_s": 0.3}}, rank=100),
    )
    live_kinds = ("measure",)
    demo_key = "friction"

    @classmethod
    def demo_part(cls, summary: Mapping[str, Any]) -> dict:
        """The demo's ``friction``: Eq. (5.2) per direction against the world's."""
        return {direction: summary[direction] for direction in SIGNS}

    @classmethod
    def demo_lines(cls, part: Mapping[str, Any]) -> list[str]:
        return ["Friction (Andersson, Eq. 5.2): identified vs simulator truth",
                *comparison_lines(part)]

    @classmethod
    def check(cls, params: Mapping[str, Any], cycle_s: float) -> dict:
        """The schema's checks, then what the analysis needs, before anything moves: every
        feed measurable (`preflight.check_feeds`), at least `MIN_FEEDS` different feeds and
        both directions."""
        p = super().check(params, cycle_s)
        check_feeds("experiment.feeds_mm_min", p["feeds_mm_min"], cycle_s)
        feeds = len(set(p["feeds_mm_min"]))
        if feeds < MIN_FEEDS:
            raise ConfigError(f"experiment.feeds_mm_min: the Andersson fit (Eq. 5.2) needs at "
                              f"least {MIN_FEEDS} different feeds per direction (got {feeds})")
        if set(p["directions"]) != set(SIGNS):
            raise ConfigError(f"experiment.directions: the analysis fits Eq. (5.2) per "
                              f"direction and needs both positive and negative (got "
                              f"{p['directions']})")
        return p

    def plan(self) -> Plan:
        """Back-and-forth constant-feed moves, one pair per feed, each measured after settling."""
        p, cycle_s = self.params, self.cycle_s
        segments: list[Segment] = []
        x = 0.0
        for feed_mm_min in p.feeds_mm_min:
            settle = settle_cycles(p, feed_mm_min, cycle_s)
            for direction, sign in SIGNS.items():
                path, cruise_start, cruise_stop = constant_feed_move(
                    x, sign * feed_mm_min * MM_PER_MIN, p.accel_m_s2,
                    settle * cycle_s + p.measure_s, cycle_s)
                settle_stop = cruise_start + settle
                info = {"feed_mm_min": sign * feed_mm_min}
                label = f"{direction} {feed_mm_min:g} mm/min"
                segments += [
                    Segment(f"accelerate {label}", "move", path[:cruise_start], info=info),
                    Segment(f"settle {label}", "settle", path[cruise_start:settle_stop],
                            info=info),
                    Segment(f"measure {label}", "measure", path[settle_stop:cruise_stop],
                            info=info),
                    Segment(f"stop {label}", "move", path[cruise_stop:], info=info),
                ]
                x = float(path[-1])
        return Plan(NAME, CSP, segments, self.settings, cycle_s)

    @classmethod
    def analyze(cls, recording, final: bool = True) -> dict:
        """Friction points of every measure window and the Eq. (5.2) fit per direction.

        SI values: velocities (m/s), forces (N), F_c, F_s (N), v_s (m/s), σ (N·s/m), the
        tanh constant held in the fits (s/m). Only windows at steady state (`steady_windows`)
        are fitted; ``points.steady`` tells which; R² is over the points fitted. `final` False
        (live): a direction with fewer than `MIN_FEEDS` points is left out instead of refused.
        """
        p = cls.stored_params(recording)
        windows = recorded_windows(recording, "measure")
        signals = axis_signals(recording.channels)
        v, f = friction_points(*signals, windows)
        _check_finite(recording, windows, v, f)
        steady = steady_windows(*signals, windows)
        sides = {direction: (np.sign(v) == sign) & steady for direction, sign in SIGNS.items()}
        if final:
            _check_feeds(recording, sides)
        k_tanh = p.k_tanh_min_mm * MIN_PER_MM
        fits = {direction: _fit_summary(fit_andersson(v[side], f[side], k_tanh=k_tanh))
                for direction, side in sides.items() if side.sum() >= MIN_FEEDS}
        result = {"experiment": NAME, "points": {"velocity_m_s": v.tolist(), "force_N": f.tolist(),
                                                 "steady": steady.tolist()},
                  "k_tanh_s_m": k_tanh, **fits}
        return {**result, "checks": fit_checks(result)}

    @classmethod
    def report(cls, recording, result: Mapping[str, Any], section: RunSection) -> None:
        """Friction points and the fitted law per direction (Fig. 5.11), the parameters ± σ,
        the R² of each fit (over the points it used) and the windows left out."""
        section.plots.append(Plot("friction curve and fitted model, Eq. (5.2)",
                                  png_of(curve_figure(result))))
        section.tables.append(parameter_table(result))

    @classmethod
    def headline(cls, result: Mapping[str, Any]) -> str:
        """F_c and F_s of the positive direction."""
        p = result["positive"]["identified"]
        return f"F_c {p['F_c']:.1f} N, F_s {p['F_s']:.1f} N (positive)"

    @classmethod
    def live_view(cls, result: Mapping[str, Any]) -> ResultView:
        """The points so far (feed mm/min, motor force N) and each direction's fit once it
        has `MIN_FEEDS` points."""
        v = np.asarray(result["points"]["velocity_m_s"])
        curves = [Curve("measured", v / MM_PER_MIN, np.asarray(result["points"]["force_N"]),
                        points=True)]
        notes = [f"{len(v)} points"]
        for direction in (d for d in SIGNS if d in result):
            fit = result[direction]
            curves.append(Curve(f"fit {direction}", *fitted_curve(result, direction)))
            notes.append(f"{direction}: F_c {fit['identified']['F_c']:.1f} N, F_s "
                         f"{fit['identified']['F_s']:.1f} N, R² {fit['r_squared']:.4f}")
        panel = Panel("friction force vs feed", "feed (mm/min)", "motor force (N)", tuple(curves))
        return ResultView(cls.title, (panel,), "; ".join(notes))

    @classmethod
    def summary(cls, result: Mapping[str, Any], truth: Mapping[str, Any]) -> dict:
        """Eq. (5.2) per direction against the world's friction (`truth["friction"]`)."""
        compared = comparison(result, truth)
        worst = max((abs(c["error_pct"][k]), k, d) for d, c in compared.items() for k in UNITS)
        pos, neg = compared["positive"]["identified"], compared["negative"]["identified"]
        return {**compared, "max_abs_error_pct": worst[0],
                "headline": headline(f"Eq. 5.2: F_c {pos['F_c']:.1f} / {neg['F_c']:.1f} N, F_s "
                                     f"{pos['F_s']:.1f} / {neg['F_s']:.1f} N (+/−)",
                                     f"largest error vs truth {worst[0]:.2f} % ({worst[1]}, "
                                     f"{worst[2]})")}

    @classmethod
    def truth_table(cls, result: Mapping[str, Any], truth: Mapping[str, Any]) -> Table:
        """Eq. (5.2)'s parameters per direction beside the world's, in Fig. 5.11's units."""
        return Table(TRUTH_TITLE, ("direction", "parameter", "identified", "true", "error"),
                     tuple((direction, key, display(key, c["identified"][key]).strip(),
                            display(key, c["truth"][key]).strip(), f"{c['error_pct'][key]:+.2f} %")
                           for direction, c in comparison(result, truth).items() for key in UNITS))

    @classmethod
    def details(cls, result: Mapping[str, Any]) -> list[str]:
        """Per direction the fit's R² and rms, then its parameters in Fig. 5.11's units."""
        lines = []
        for direction in SIGNS:
            fit = result[direction]
            lines.append(f"  {direction}: R² {fit['r_squared']:.5f}, rms {fit['rms_N']:.3f} N")
            lines += [f"    {k:<6s} {display(k, fit['identified'][k])}" for k in UNITS]
        return lines
