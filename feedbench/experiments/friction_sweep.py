"""Friction sweep (Ch. 5.3.2, Fig. 5.11): constant-feed runs in both directions.

At each feed the axis accelerates, settles, and holds the feed over a measure window;
the mean motor force over that window is the friction force at that velocity, and the
points of each direction are fitted with Andersson's law, Eq. (5.2). On an axis driven by
several drives (the rack-and-pinion master and slave) the force is the sum of the drives'
forces, so an electronic preload cancels out, and the velocity is the first drive's.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from feedbench.analysis.friction import FrictionFit, fit_andersson_directional
from feedbench.config import ConfigError, Field, one_of, positive, validate_table
from feedbench.experiments.family import Experiment
from feedbench.experiments.plan import Plan, Segment, Window, recorded_windows
from feedbench.experiments.signals import constant_feed_move
from feedbench.protocols.cia402 import CSP
from feedbench.units import MIN_PER_MM, MM_PER_MIN

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
    "measure_s": Field(float, 0.5, "measure window at each feed (s)", positive),
    "accel_m_s2": Field(float, 1.0, "acceleration of the ramps (m/s²)", positive),
    "k_tanh_min_mm": Field(float, 0.25, "tanh constant of Eq. (5.2), held in the fit (min/mm)",
                           positive),
}

SIGNS = {"positive": 1.0, "negative": -1.0}
MIN_FEEDS = 5
"""Distinct feeds per direction the analysis needs: Eq. (5.2)'s fit has 4 free parameters
(F_c, F_s, v_s, σ) and needs at least one point more (`analysis.friction`)."""


def _validated(params: Mapping[str, Any]) -> dict:
    """The checked params: what the analysis needs is known before anything moves."""
    p = validate_table(params, SCHEMA, "experiment")
    feeds = len(set(p["feeds_mm_min"]))
    if feeds < MIN_FEEDS:
        raise ConfigError(f"experiment.feeds_mm_min: the Andersson fit (Eq. 5.2) needs at "
                          f"least {MIN_FEEDS} different feeds per direction (got {feeds})")
    if set(p["directions"]) != set(SIGNS):
        raise ConfigError(f"experiment.directions: the analysis fits Eq. (5.2) per direction "
                          f"and needs both positive and negative (got {p['directions']})")
    return p


def build_plan(params: Mapping[str, Any], cycle_s: float) -> Plan:
    """Back-and-forth constant-feed moves, one pair per feed (measured where asked)."""
    p = _validated(params)
    segments: list[Segment] = []
    x = 0.0
    for feed_mm_min in p["feeds_mm_min"]:
        for direction in ("positive", "negative"):
            feed = SIGNS[direction] * feed_mm_min * MM_PER_MIN
            path, cruise_start, cruise_stop = constant_feed_move(
                x, feed, p["accel_m_s2"], p["settle_s"] + p["measure_s"], cycle_s
            )
            settle_stop = cruise_start + int(round(p["settle_s"] / cycle_s))
            measured = direction in p["directions"]
            info = {"feed_mm_min": SIGNS[direction] * feed_mm_min}
            label = f"{direction} {feed_mm_min:g} mm/min"
            segments += [
                Segment(f"accelerate {label}", "move", path[:cruise_start], info=info),
                Segment(f"settle {label}", "settle", path[cruise_start:settle_stop], info=info),
                Segment(
                    f"measure {label}", "measure" if measured else "move",
                    path[settle_stop:cruise_stop], info=info,
                ),
                Segment(f"stop {label}", "move", path[cruise_stop:], info=info),
            ]
            x = float(path[-1])
    return Plan(NAME, CSP, segments, p, cycle_s)


def friction_points(
    velocity: np.ndarray, force: np.ndarray, windows: list[Window]
) -> tuple[np.ndarray, np.ndarray]:
    """Mean velocity (m/s) and mean motor force (N) over each measure window."""
    v = np.array([velocity[w.start:w.stop].mean() for w in windows])
    f = np.array([force[w.start:w.stop].mean() for w in windows])
    return v, f


def _fit_summary(fit: FrictionFit) -> dict:
    p, s = fit.params, fit.std
    return {
        "identified": {"F_c": p.F_c, "F_s": p.F_s, "v_s": p.v_s, "sigma": p.sigma},
        "std": {"F_c": s.F_c, "F_s": s.F_s, "v_s": s.v_s, "sigma": s.sigma},
        "rms_N": fit.rms,
        "r_squared": fit.r_squared,
        "n_points": fit.n_points,
    }


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


def analyze_recording(recording) -> dict:
    """Friction points of every measure window and the Andersson fit per direction (5.2).

    Returns SI values: velocities (m/s), forces (N), F_c, F_s (N), v_s (m/s), σ (N·s/m).
    """
    params = validate_table(recording.config["experiment"], SCHEMA, "experiment")
    windows = recorded_windows(recording, "measure")
    v, f = friction_points(*axis_signals(recording.channels), windows)
    for name, values in (("velocity", v), ("force", f)):
        if not np.all(np.isfinite(values)):
            label = windows[int(np.argmin(np.isfinite(values)))].label
            raise ConfigError(f"{recording.path}: {name}: NaN or inf samples in the measure "
                              f"window {label!r}")
    for direction, sign in SIGNS.items():
        feeds = int(np.sum(np.sign(v) == sign))
        if feeds < MIN_FEEDS:
            raise ConfigError(f"{recording.path}: {feeds} feeds measured in the {direction} "
                              f"direction; the Andersson fit (Eq. 5.2) needs at least {MIN_FEEDS}")
    fit = fit_andersson_directional(v, f, k_tanh=params["k_tanh_min_mm"] * MIN_PER_MM)
    return {
        "experiment": NAME,
        "points": {"velocity_m_s": v.tolist(), "force_N": f.tolist()},
        "positive": _fit_summary(fit.positive),
        "negative": _fit_summary(fit.negative),
    }

class FrictionSweep(Experiment):
    """TRANSITION shell: the module's functions behind the family interface."""

    name = NAME
    schema = SCHEMA

    @classmethod
    def check(cls, params: Mapping[str, Any], cycle_s: float) -> dict:
        return _validated(params)

    def plan(self) -> Plan:
        return build_plan(self.settings, self.cycle_s)

    @classmethod
    def analyze(cls, recording, final: bool = True) -> dict:
        return analyze_recording(recording)
