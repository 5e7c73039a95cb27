"""Stepped loading and backlash of the rack-and-pinion axis (thesis Ch. 3.4, Figs. 3.8–3.12).

The axis stands near a rigid bumper with a load cell. One run holds a sequence of tests,
each set up by the axis controller's objects at its first segment (`rack_pinion_io`):
- backlash, one motor at a time (the other off): back-and-forth moves of 1 mm away from
  the bumper at a constant feed (Ch. 3.4.2, Fig. 3.9);
- loading, one motor at a time: a stepped position command into the bumper and back
  (Ch. 3.4.1, Fig. 3.8): k_m, k_s by Eq. (3.26);
- loading, master and slave coupled, at each preload level (Ch. 3.4.3, Figs. 3.10–3.12):
  the load at which the master loses contact, the displacement jump (= its backlash), the
  slave's stiffness while it carries alone, and the torque sharing of Eq. (3.1).

Each step is a short ramp, a settle and a measure window; analysis uses the per-cycle
samples of the measure windows only (load cell, both motor encoders, linear scale, both
motor forces), so the transients of the ramps are left out while the slow flank change of
a preload loss is sampled as it happens.
"""

from __future__ import annotations

import math
from collections import defaultdict
from typing import Any, Mapping

import numpy as np

from feedbench.analysis.stiffness import (
    backlash_from_reversals, equivalent_stiffness, preload_loss_force, stiffness_while_lost,
    torque_sharing,
)
from feedbench.config import ConfigError, Field, one_of, positive, validate_table
from feedbench.experiments.family import Experiment
from feedbench.experiments.plan import Plan, Segment, Window, recorded_windows
from feedbench.experiments.signals import constant_feed_move
from feedbench.protocols.cia402 import CSP
from feedbench.units import MM_PER_MIN

NAME = "stepped_loading"
AXES = ("rack_pinion",)
"""The bench axes this experiment runs on (`bench.parse_run_config` checks it)."""
MOTORS = ("master", "slave")

SCHEMA = {
    "type": Field(str, NAME, "experiment family"),
    "backlash": Field(list, ["master", "slave"], "motors whose backlash is measured alone",
                      one_of(*MOTORS)),
    "single_motor": Field(list, ["master", "slave"], "motors loaded alone (k_m, k_s)",
                          one_of(*MOTORS)),
    "preload_pct": Field(list, [4.0, 10.0, 20.0, 25.0], "coupled loading at these preloads "
                         "(% of the rated torque)", positive),
    "direction": Field(str, "negative", "direction of the bumper from the start position",
                       one_of("negative", "positive")),
    "step_um": Field(float, 10.0, "position step (µm)", positive),
    "depth_um": Field(float, 300.0, "coupled loading: deepest command into the bumper (µm)",
                      positive),
    "single_depth_um": Field(float, 500.0, "single-motor loading: deepest command (µm; the "
                             "motor first takes up its backlash)", positive),
    "single_step_um": Field(float, 10.0, "single-motor loading: position step (µm)", positive),
    "unload": Field(bool, True, "step back out of the bumper after loading"),
    "ramp_s": Field(float, 0.02, "ramp of each step (s)", positive),
    "settle_s": Field(float, 0.1, "wait after each ramp (s)", positive),
    "measure_s": Field(float, 0.2, "measure window at each step (s)", positive),
    "setup_s": Field(float, 2.0, "standstill after each change of coupling or preload (s)",
                     positive),
    "stroke_mm": Field(float, 1.0, "backlash: stroke of the back-and-forth moves (mm)",
                       positive),
    "feed_mm_min": Field(float, 200.0, "backlash: feed of the strokes (mm/min)", positive),
    "accel_m_s2": Field(float, 0.2, "backlash: acceleration (m/s²)", positive),
    "strokes": Field(int, 2, "backlash: back-and-forth moves per motor", positive),
    "dwell_s": Field(float, 0.2, "backlash: standstill at each end (s)", positive),
}

QUICK = {"preload_pct": [4.0, 20.0], "unload": False, "settle_s": 0.05, "measure_s": 0.15,
         "depth_um": 250.0, "single_depth_um": 350.0, "single_step_um": 15.0, "strokes": 1,
         "setup_s": 1.5}
"""A short version (35 s of bench time against 162 s): the thesis's low and high preload,
loading without unloading, coarser single-motor steps, one back-and-forth move per motor."""

SIGNS = {"negative": -1.0, "positive": 1.0}
MIN_LEVELS = 3
"""Load levels a staircase needs per direction: the stiffness fits of Eq. (3.26) and of the
contact lines take at least 3 points (`analysis.stiffness`)."""
SHARING_START, SHARING_END = 0.05, 0.8
"""Torque sharing (Eq. 3.1) is fitted on the loading from this fraction of the loss force
until the load first reaches the second: both motors carry and the preload PI is settled."""


def _samples(n_s: float, cycle_s: float) -> int:
    return max(1, int(round(n_s / cycle_s)))


def _setup(test: str, settings: dict[str, Any], p: Mapping[str, Any], x: float,
           cycle_s: float) -> Segment:
    """Hold while the axis controller takes the test's settings (its info carries them)."""
    return Segment(f"setup {test}", "settle", np.full(_samples(p["setup_s"], cycle_s), x),
                   info={"test": test, **settings})


def _staircase(test: str, depth: float, step: float, p: Mapping[str, Any],
               cycle_s: float) -> list[Segment]:
    """Steps of `step` (m) into the bumper to `depth` (m, signed) and, if `unload`, back to 0
    the same way (otherwise one ramp back, not measured)."""
    n = max(1, math.ceil(abs(depth) / step))
    levels = np.linspace(0.0, depth, n + 1)
    path = np.concatenate([levels, levels[-2::-1]]) if p["unload"] else levels
    ramp, settle = _samples(p["ramp_s"], cycle_s), _samples(p["settle_s"], cycle_s)
    measure = _samples(p["measure_s"], cycle_s)
    segments = []
    for i, (start, stop) in enumerate(zip(path[:-1], path[1:])):
        info = {"test": test, "phase": "load" if i < n else "unload",
                "target_um": float(stop * 1e6)}
        segments += [
            Segment(f"{test} step {i + 1}", "move", np.linspace(start, stop, ramp + 1)[1:],
                    info=info),
            Segment(f"{test} settle {i + 1}", "settle", np.full(settle, stop), info=info),
            Segment(f"{test} measure {i + 1}", "measure", np.full(measure, stop), info=info),
        ]
    if not p["unload"]:
        back = _samples(n * p["ramp_s"], cycle_s)
        segments.append(Segment(f"{test} back", "move", np.linspace(depth, 0.0, back + 1)[1:],
                                info={"test": test}))
    return segments


def _strokes(test: str, p: Mapping[str, Any], away: float, cycle_s: float) -> list[Segment]:
    """Back-and-forth moves of `stroke_mm` away from the bumper (measured), dwell at each
    end (not measured: the carriage coasts on while the motor stops)."""
    feed = p["feed_mm_min"] * MM_PER_MIN
    stroke = p["stroke_mm"] * 1e-3
    cruise = stroke / feed - feed / p["accel_m_s2"]
    if cruise <= 0.0:
        raise ConfigError("experiment.stroke_mm: too short to reach feed_mm_min at "
                          "accel_m_s2 (no constant-feed part to measure)")
    segments, x = [], 0.0
    dwell = _samples(p["dwell_s"], cycle_s)
    for i in range(2 * p["strokes"]):
        sign = away if i % 2 == 0 else -away
        path, _, _ = constant_feed_move(x, sign * feed, p["accel_m_s2"], cruise, cycle_s)
        x = float(path[-1])
        info = {"test": test, "stroke": i + 1}
        segments += [Segment(f"{test} stroke {i + 1}", "measure", path, info=info),
                     Segment(f"{test} dwell {i + 1}", "settle", np.full(dwell, x), info=info)]
    return segments


def _validated(params: Mapping[str, Any]) -> dict:
    """The checked params: every staircase the run holds has enough load levels."""
    p = validate_table(params, SCHEMA, "experiment")
    for tests, depth, step in ((p["single_motor"], "single_depth_um", "single_step_um"),
                               (p["preload_pct"], "depth_um", "step_um")):
        levels = math.ceil(p[depth] / p[step])
        if tests and levels < MIN_LEVELS:
            raise ConfigError(f"experiment.{step}: {depth} / {step} gives {levels} load "
                              f"level(s) per direction; the stiffness fit (Eq. 3.26) needs "
                              f"at least {MIN_LEVELS}")
    return p


def build_plan(params: Mapping[str, Any], cycle_s: float) -> Plan:
    """Backlash strokes, single-motor loadings, then coupled loadings per preload level."""
    p = _validated(params)
    toward = SIGNS[p["direction"]]
    segments: list[Segment] = []
    for motor in p["backlash"]:
        test = f"backlash {motor}"
        segments += [_setup(test, {"coupling": motor}, p, 0.0, cycle_s),
                     *_strokes(test, p, -toward, cycle_s)]
    for motor in p["single_motor"]:
        test = f"single {motor}"
        segments += [_setup(test, {"coupling": motor}, p, 0.0, cycle_s),
                     *_staircase(test, toward * p["single_depth_um"] * 1e-6,
                                 p["single_step_um"] * 1e-6, p, cycle_s)]
    for level in p["preload_pct"]:
        test = f"coupled {level:g} %"
        segments += [_setup(test, {"coupling": "coupled", "preload_pct": level}, p, 0.0, cycle_s),
                     *_staircase(test, toward * p["depth_um"] * 1e-6, p["step_um"] * 1e-6,
                                 p, cycle_s)]
    if not segments:
        raise ConfigError("experiment: no test selected (backlash, single_motor, preload_pct "
                          "are all empty)")
    return Plan(NAME, CSP, segments, p, cycle_s)


# -- analysis --------------------------------------------------------------------------


def _test_samples(recording, windows: list[Window], toward: float) -> dict[str, np.ndarray]:
    """The rows of `windows` with a load-cell reading, positions and forces oriented so
    that +x points at the bumper."""
    rows = np.concatenate([np.arange(w.start, w.stop) for w in windows])
    ch = recording.channels
    rows = rows[np.isfinite(ch["load_cell.force"][rows])]
    return {"force": ch["load_cell.force"][rows],
            "master": toward * ch["master.motor_position"][rows],
            "slave": toward * ch["slave.motor_position"][rows],
            "load": toward * ch["load_position"][rows],
            "master_force": toward * ch["master.force"][rows],
            "slave_force": toward * ch["slave.force"][rows]}


def _single(s: Mapping[str, np.ndarray], motor: str) -> dict:
    fit = equivalent_stiffness(s["force"], s[motor], s["load"])
    return {"k_N_m": fit.k, "k_std_N_m": fit.k_std, "r_squared": fit.r_squared,
            "offset_m": fit.offset, "force_range_N": list(fit.force_range),
            "n_points": fit.n_points}


def _coupled(s: Mapping[str, np.ndarray], level: float) -> dict:
    """Preload loss (displacement and torques), jump, stiffnesses, torque sharing; a test
    that did not load far enough past the loss gets an ``error`` instead."""
    try:
        return _preload_loss(s, level)
    except ValueError as exc:
        return {"preload_pct": level, "error": str(exc)}


def _preload_loss(s: Mapping[str, np.ndarray], level: float) -> dict:
    loss = preload_loss_force(s["force"], s["master"], s["load"])
    before = np.arange(s["force"].size) < np.argmax(s["force"] >= SHARING_END * loss.force)
    loaded = before & (s["force"] > SHARING_START * loss.force)
    sharing = torque_sharing(s["master_force"][loaded], s["slave_force"][loaded])
    slave = stiffness_while_lost(s["force"], s["master"], s["slave"], s["load"],
                                 s["master_force"])
    return {"preload_pct": level,
            "loss_force_N": loss.force,
            "loss_force_from_torques_N": -sharing.preload / sharing.share,
            "recovery_force_N": loss.recovery,
            "jump_m": loss.jump,
            "k_master_before_N_m": loss.k_before,
            "k_master_after_N_m": loss.k_after,
            "k_slave_contact_N_m": slave.contact,
            "k_slave_lost_N_m": slave.lost,
            "slave_stiffness_ratio": slave.lost / slave.contact,
            "torque_share": sharing.share,
            "preload_force_N": -sharing.preload,
            "torque_r_squared": sharing.r_squared}


def _backlash(recording, windows: list[Window], motor: str, k: float | None) -> dict:
    """Lost motion at the reversals, Ch. 3.4.2; with the motor's stiffness k (N/m) the
    drive train's wind-up F/k under the guideway friction is taken out of x_motor."""
    rows = np.concatenate([np.arange(w.start, w.stop) for w in windows])
    ch = recording.channels
    x_motor, x_load = ch[f"{motor}.motor_position"][rows], ch["load_position"][rows]
    raw = backlash_from_reversals(x_motor, x_load)
    result = {"uncorrected_m": raw.value, "n_reversals": int(raw.per_reversal.size)}
    if k is None:
        return {**result, "value_m": raw.value, "std_m": raw.std, "corrected": False}
    fixed = backlash_from_reversals(x_motor - ch[f"{motor}.force"][rows] / k, x_load)
    return {**result, "value_m": fixed.value, "std_m": fixed.std, "corrected": True}


def analyze_recording(recording) -> dict:
    """k_m, k_s (Eq. 3.26), backlash per motor, and per preload level the loss force, the
    jump, the slave's stiffness with and without the master, and the torque sharing (3.1).

    SI: N/m, m, N. Tests missing from the run are missing from the result.
    """
    params = validate_table(recording.config["experiment"], SCHEMA, "experiment")
    toward = SIGNS[params["direction"]]
    tests: dict[str, list[Window]] = defaultdict(list)
    for window in recorded_windows(recording, "measure"):
        tests[window.info["test"]].append(window)
    stiffness = {motor: _single(_test_samples(recording, tests[f"single {motor}"], toward), motor)
                 for motor in MOTORS if f"single {motor}" in tests}
    backlash = {motor: _backlash(recording, tests[f"backlash {motor}"], motor,
                                 stiffness.get(motor, {}).get("k_N_m"))
                for motor in MOTORS if f"backlash {motor}" in tests}
    preload = [_coupled(_test_samples(recording, tests[f"coupled {level:g} %"], toward), level)
               for level in params["preload_pct"] if f"coupled {level:g} %" in tests]
    return {"experiment": NAME, "stiffness": stiffness, "backlash": backlash,
            "preload": preload}


def describe(result: Mapping[str, Any]) -> list[str]:
    """Lines of a human-readable summary of `analyze_recording`'s result (µm, N/µm, N)."""
    lines = [f"  k_{motor[0]} {fit['k_N_m'] / 1e6:7.2f} N/µm (Eq. 3.26, "
             f"R² {fit['r_squared']:.6f})" for motor, fit in result["stiffness"].items()]
    lines += [f"  backlash {motor} {b['value_m'] * 1e6:7.1f} µm"
              + ("" if b["corrected"] else " (no stiffness: friction wind-up included)")
              for motor, b in result["backlash"].items()]
    for test in result["preload"]:
        if "error" in test:
            lines.append(f"  preload {test['preload_pct']:g} %: {test['error']}")
            continue
        lines.append(
            f"  preload {test['preload_pct']:4g} %: loss {test['loss_force_N']:7.0f} N "
            f"(torques: {test['loss_force_from_torques_N']:7.0f} N), recovery "
            f"{test['recovery_force_N']:7.0f} N, jump {test['jump_m'] * 1e6:6.1f} µm, slave "
            f"{test['k_slave_contact_N_m'] / 1e6:5.1f} → {test['k_slave_lost_N_m'] / 1e6:5.1f} "
            f"N/µm, share {test['torque_share']:.3f}")
    return lines

class SteppedLoading(Experiment):
    """TRANSITION shell: the module's functions behind the family interface."""

    name = NAME
    schema = SCHEMA
    axes = AXES

    @classmethod
    def check(cls, params: Mapping[str, Any], cycle_s: float) -> dict:
        return _validated(params)

    def plan(self) -> Plan:
        return build_plan(self.settings, self.cycle_s)

    @classmethod
    def analyze(cls, recording, final: bool = True) -> dict:
        return analyze_recording(recording)

    @classmethod
    def describe(cls, result: Mapping[str, Any]) -> list[str]:
        return describe(result)
