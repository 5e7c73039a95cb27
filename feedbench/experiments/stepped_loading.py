"""Stepped loading and backlash of the rack-and-pinion axis (thesis Ch. 3.4, Figs. 3.8–3.12).

The axis stands near a rigid bumper with a load cell. One run holds a sequence of tests,
each set up by the axis controller's objects at its first segment (`axes.rack_pinion.AxisSettings`):
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
from functools import partial
from typing import Any, Callable, Mapping

import numpy as np

from feedbench.analysis.checks import check, positive_parameters
from feedbench.analysis.stiffness import (
    backlash_from_reversals, equivalent_stiffness, preload_loss_force, stiffness_while_lost,
    torque_sharing,
)
from feedbench.config import ConfigError, Field, one_of, positive
from feedbench.engine.family import Example, Experiment, headline
from feedbench.engine.plan import Plan, Segment, Window, recorded_windows
from feedbench.experiments.signals import constant_feed_move
from feedbench.protocols.cia402 import CSP
from feedbench.units import MM_PER_MIN, N_PER_UM
from feedbench.views.panels import Curve, Panel, ResultView
from feedbench.views.sections import (
    MIN_R_SQUARED, Plot, RunSection, Table, new_figure, png_of,
)

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


def _setup(test: str, settings: dict[str, Any], p: Any, x: float,
           cycle_s: float) -> Segment:
    """Hold while the axis controller takes the test's settings (the segment's commands,
    `axes.rack_pinion.AxisSettings`)."""
    return Segment(f"setup {test}", "settle", np.full(_samples(p.setup_s, cycle_s), x),
                   info={"test": test}, commands=settings)


def _staircase(test: str, depth: float, step: float, p: Any,
               cycle_s: float) -> list[Segment]:
    """Steps of `step` (m) into the bumper to `depth` (m, signed) and, if `unload`, back to 0
    the same way (otherwise one ramp back, not measured)."""
    n = max(1, math.ceil(abs(depth) / step))
    levels = np.linspace(0.0, depth, n + 1)
    path = np.concatenate([levels, levels[-2::-1]]) if p.unload else levels
    ramp, settle = _samples(p.ramp_s, cycle_s), _samples(p.settle_s, cycle_s)
    measure = _samples(p.measure_s, cycle_s)
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
    if not p.unload:
        back = _samples(n * p.ramp_s, cycle_s)
        segments.append(Segment(f"{test} back", "move", np.linspace(depth, 0.0, back + 1)[1:],
                                info={"test": test}))
    return segments


def _strokes(test: str, p: Any, away: float, cycle_s: float) -> list[Segment]:
    """Back-and-forth moves of `stroke_mm` away from the bumper (measured), dwell at each
    end (not measured: the carriage coasts on while the motor stops)."""
    feed = p.feed_mm_min * MM_PER_MIN
    stroke = p.stroke_mm * 1e-3
    cruise = stroke / feed - feed / p.accel_m_s2
    if cruise <= 0.0:
        raise ConfigError("experiment.stroke_mm: too short to reach feed_mm_min at "
                          "accel_m_s2 (no constant-feed part to measure)")
    segments, x = [], 0.0
    dwell = _samples(p.dwell_s, cycle_s)
    for i in range(2 * p.strokes):
        sign = away if i % 2 == 0 else -away
        path, _, _ = constant_feed_move(x, sign * feed, p.accel_m_s2, cruise, cycle_s)
        x = float(path[-1])
        info = {"test": test, "stroke": i + 1}
        segments += [Segment(f"{test} stroke {i + 1}", "measure", path, info=info),
                     Segment(f"{test} dwell {i + 1}", "settle", np.full(dwell, x), info=info)]
    return segments


def _segments(p: Any, cycle_s: float) -> list[Segment]:
    """Backlash strokes, single-motor loadings, then coupled loadings per preload level
    (`p` typed, checked)."""
    toward = SIGNS[p.direction]
    segments: list[Segment] = []
    for motor in p.backlash:
        test = f"backlash {motor}"
        segments += [_setup(test, {"coupling": motor}, p, 0.0, cycle_s),
                     *_strokes(test, p, -toward, cycle_s)]
    for motor in p.single_motor:
        test = f"single {motor}"
        segments += [_setup(test, {"coupling": motor}, p, 0.0, cycle_s),
                     *_staircase(test, toward * p.single_depth_um * 1e-6,
                                 p.single_step_um * 1e-6, p, cycle_s)]
    for level in p.preload_pct:
        test = f"coupled {level:g} %"
        segments += [_setup(test, {"coupling": "coupled", "preload_pct": level}, p, 0.0, cycle_s),
                     *_staircase(test, toward * p.depth_um * 1e-6, p.step_um * 1e-6,
                                 p, cycle_s)]
    return segments


# -- analysis --------------------------------------------------------------------------

SIGNALS = {"force": "load_cell.force", "master": "master.motor_position",
           "slave": "slave.motor_position", "load": "load_position",
           "master_force": "master.force", "slave_force": "slave.force"}
"""The analysis's signals by name and their channels."""


def _tests(recording) -> dict[str, list[Window]]:
    """The measure windows of the recording by test (``single master``, ``coupled 20 %`` …)."""
    tests: dict[str, list[Window]] = defaultdict(list)
    for window in recorded_windows(recording, "measure"):
        tests[window.info["test"]].append(window)
    return tests


def _test_samples(recording, windows: list[Window], toward: float,
                  signals: tuple[str, ...] = tuple(SIGNALS)) -> dict[str, np.ndarray]:
    """`signals` of the rows of `windows` with a load-cell reading, positions and motor
    forces oriented so that +x points at the bumper."""
    rows = np.concatenate([np.arange(w.start, w.stop) for w in windows])
    ch = recording.channels
    rows = rows[np.isfinite(ch[SIGNALS["force"]][rows])]
    return {name: (1.0 if name == "force" else toward) * ch[SIGNALS[name]][rows]
            for name in signals}


def loaded_motor(test: str) -> str:
    """The motor whose δ a loading test measures: the slave alone, else the master."""
    return "slave" if test == "single slave" else "master"


def _step_points(recording, windows: list[Window], motor: str, toward: float) -> dict:
    """Per measure step with load-cell readings its mean load (N) and mean
    δ = x_motor − x_load (m, towards the bumper): the points of Fig. 3.8."""
    delta, force = [], []
    for window in windows:
        s = _test_samples(recording, [window], toward, ("force", motor, "load"))
        if s["force"].size:
            force.append(float(s["force"].mean()))
            delta.append(float((s[motor] - s["load"]).mean()))
    return {"delta_m": delta, "force_N": force}


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


def _fitted(fits: Mapping[str, Callable[[], dict]], final: bool) -> dict[str, dict]:
    """Each fit by name; while the run goes on (`final` False) those whose data do not
    allow one yet (`ValueError`) are left out."""
    done = {}
    for name, fit in fits.items():
        try:
            done[name] = fit()
        except ValueError:
            if final:
                raise
    return done


# -- report, live view, summary ------------------------------------------------------------

THESIS_PRELOAD_LOSS_N = {4.0: 1100.0, 20.0: 5300.0, 25.0: 6600.0}
"""Ch. 3.4.3: preload lost at ≈ 1100 N (4 %), ≈ 5300 N (20 %), ≈ 6600 N (25 %)."""


def _fit_line(fit: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """The line of Eq. (3.26) over the fitted load range: δ (µm) and load (N)."""
    force = np.linspace(*fit["force_range_N"], 50)
    return (force / fit["k_N_m"] + fit["offset_m"]) * 1e6, force


def _single_motor_figure(recording, result: Mapping[str, Any], tests: Mapping[str, list],
                         toward: float):
    """Left: load against δ = x_motor − x_load per motor with the line of Eq. (3.26);
    right: δ against the motor position in the backlash strokes (lost motion)."""
    figure = new_figure(10.0, 4.5)
    loading, strokes = figure.subplots(1, 2)
    for motor, fit in result["stiffness"].items():
        s = _test_samples(recording, tests[f"single {motor}"], toward)
        delta = s[motor] - s["load"]
        loading.plot(delta * 1e6, s["force"], ".", ms=2, label=f"{motor} alone")
        loading.plot(*_fit_line(fit), lw=1.2,
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


def _coupled_figure(recording, result: Mapping[str, Any], tests: Mapping[str, list],
                    toward: float):
    """Per preload level δ_m = x_master − x_load against the load, the loss and the
    recovery force marked (Fig. 3.11-a)."""
    levels = result["preload"]
    figure = new_figure(10.0, 4.0)
    axes = np.atleast_1d(figure.subplots(1, len(levels), sharey=True))
    for ax, level in zip(axes, levels):
        s = _test_samples(recording, tests[f"coupled {level['preload_pct']:g} %"], toward)
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


def _tables(result: Mapping[str, Any]) -> list[Table]:
    """Stiffness and backlash per motor; the preload loss per level (Ch. 3.4.3)."""
    motors = [m for m in MOTORS if m in result["stiffness"] or m in result["backlash"]]
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


def _stiffness_cells(fit: Mapping[str, Any] | None) -> tuple[str, str]:
    if fit is None:
        return "—", "—"
    return (f"{fit['k_N_m'] / 1e6:.2f} ± {fit['k_std_N_m'] / 1e6:.2f}",
            f"{fit['r_squared']:.5f}")


def _backlash_cells(backlash: Mapping[str, Any] | None) -> tuple[str, str]:
    if backlash is None:
        return "—", "—"
    return f"{backlash['value_m'] * 1e6:.1f}", str(backlash["corrected"])


def _stiffness_text(result: Mapping[str, Any]) -> str:
    """``k_m 81.0 N/µm, k_s 100.0 N/µm``: the stiffness fits so far (Eq. 3.26)."""
    return ", ".join(f"k_{m[0]} {x['k_N_m'] / 1e6:.1f} N/µm"
                     for m, x in result["stiffness"].items())


def _preload_level(test: Mapping[str, Any], truth: Mapping[str, Any]) -> dict:
    """One coupled test's loss force beside the thesis's and 2 τ_p K_tr (Eq. 3.1)."""
    level = test["preload_pct"]
    keys = ("loss_force_N", "loss_force_from_torques_N", "jump_m", "error")
    return {"preload_pct": level, **{k: test.get(k) for k in keys},
            "thesis_loss_force_N": THESIS_PRELOAD_LOSS_N.get(level),
            "eq_3_1_loss_force_N": 2.0 * level / 100.0 * truth["rated_force"]}


def _loss_text(level: Mapping[str, Any]) -> str:
    if level["error"]:
        return f"{level['preload_pct']:g} %: {level['error']}"
    thesis = level["thesis_loss_force_N"]
    return (f"loss {level['loss_force_N']:.0f} N at {level['preload_pct']:g} % "
            + (f"(thesis ≈ {thesis:.0f})" if thesis else "(thesis: –)"))


def loading_checks(result: Mapping[str, Any]) -> list[dict]:
    """The stiffness fits' R² at least `MIN_R_SQUARED`, the stiffnesses and backlashes > 0
    (a flipped load-cell or encoder sign fails), every preload level analysed."""
    r2 = {motor: x["r_squared"] for motor, x in result["stiffness"].items()}
    low = [f"{motor} R² {v:.4f}" for motor, v in r2.items() if not v >= MIN_R_SQUARED]
    failed = [t for t in result["preload"] if "error" in t]
    checks = [
        check("min R² of the stiffness fits", f"{min(r2.values(), default=float('nan')):.5f}",
              not low, ", ".join(low) + f" below {MIN_R_SQUARED:g}: load and δ are not on a "
              "line (no contact with the bumper, or a sensor not reading)"),
        check("preload levels analysed", f"{len(result['preload']) - len(failed)} of "
              f"{len(result['preload'])}", not failed,
              "; ".join(f"{t['preload_pct']:g} %: {t['error']}" for t in failed)),
    ]
    values = {**{f"k_{m[0]}": (x["k_N_m"] / N_PER_UM, "N/µm")
                 for m, x in result["stiffness"].items()},
              **{f"backlash {m}": (b["value_m"] * 1e6, "µm")
                 for m, b in result["backlash"].items()}}
    if values:
        checks.append(positive_parameters("stiffness and backlash", values))
    return checks


class SteppedLoading(Experiment):
    """Stepped loading and backlash of the rack-and-pinion axis (Ch. 3.4): k_m, k_s by
    Eq. (3.26), backlash from reversals (Fig. 3.9), per preload level the loss of contact,
    the jump and the torque sharing of Eq. (3.1) (Figs. 3.10–3.12)."""

    name = NAME
    schema = SCHEMA
    axes = AXES
    title = "load against displacement, Eq. (3.26)"
    examples = (
        # --quick: the test's short version (`QUICK`) with 0.1 s measure windows and 1 s
        # set-ups, the load cell read every 5th cycle (a Modbus read per cycle costs ⅓ of
        # the wall time): k_m, k_s within 1 %, backlash within 2 µm, both loss forces within
        # 5 % of the thesis's.
        Example(NAME, {"bench": {"devices": {"load_cell": {"every_cycles": 5}}},
                       "experiment": {**QUICK, "setup_s": 1.0, "measure_s": 0.1}}, rank=80),
    )
    live_kinds = ("measure",)

    @classmethod
    def check(cls, params: Mapping[str, Any], cycle_s: float) -> dict:
        """Every staircase the run holds has at least `MIN_LEVELS` load levels."""
        p = super().check(params, cycle_s)
        if not (p["backlash"] or p["single_motor"] or p["preload_pct"]):
            raise ConfigError("experiment: no test selected (backlash, single_motor, "
                              "preload_pct are all empty)")
        for tests, depth, step in ((p["single_motor"], "single_depth_um", "single_step_um"),
                                   (p["preload_pct"], "depth_um", "step_um")):
            levels = math.ceil(p[depth] / p[step])
            if tests and levels < MIN_LEVELS:
                raise ConfigError(f"experiment.{step}: {depth} / {step} gives {levels} load "
                                  f"level(s) per direction; the stiffness fit (Eq. 3.26) needs "
                                  f"at least {MIN_LEVELS}")
        return p

    def plan(self) -> Plan:
        return Plan(NAME, CSP, _segments(self.params, self.cycle_s), self.settings,
                    self.cycle_s)

    @classmethod
    def analyze(cls, recording, final: bool = True) -> dict:
        """k_m, k_s (Eq. 3.26), backlash per motor, and per preload level the loss force, the
        jump, the slave's stiffness with and without the master, and the torque sharing
        (3.1); per loading test the mean load and δ of each measure step (``steps``).

        SI: N/m, m, N. Tests missing from the run are missing from the result; while the run
        goes on (`final` False), so are the fits its steps do not allow yet and the stiffness
        fits below `MIN_R_SQUARED` (the backlash take-up: no load yet).
        """
        p = cls.stored_params(recording)
        toward = SIGNS[p.direction]
        tests = _tests(recording)
        steps = {test: _step_points(recording, windows, loaded_motor(test), toward)
                 for test, windows in tests.items() if "phase" in windows[0].info}
        stiffness = _fitted({motor: partial(_single, _test_samples(
            recording, tests[f"single {motor}"], toward, ("force", motor, "load")), motor)
            for motor in MOTORS if f"single {motor}" in tests}, final)
        if not final:  # a stiffness (and the backlash corrected by it) once the fit is good
            stiffness = {motor: fit for motor, fit in stiffness.items()
                         if fit["r_squared"] >= MIN_R_SQUARED}
        backlash = _fitted({motor: partial(_backlash, recording, tests[f"backlash {motor}"],
                                           motor, stiffness.get(motor, {}).get("k_N_m"))
                            for motor in MOTORS if f"backlash {motor}" in tests}, final)
        preload = [_coupled(_test_samples(recording, tests[f"coupled {level:g} %"], toward),
                            level)
                   for level in p.preload_pct if f"coupled {level:g} %" in tests]
        result = {"experiment": NAME, "stiffness": stiffness, "backlash": backlash,
                  "preload": preload, "steps": steps}
        return {**result, "checks": loading_checks(result)}

    @classmethod
    def report(cls, recording, result: Mapping[str, Any], section: RunSection) -> None:
        """Load against displacement with the fitted stiffness (Eq. 3.26, Fig. 3.8), the
        backlash strokes (Fig. 3.9), the coupled loadings with the preload loss per level
        (Figs. 3.10–3.11) and their table."""
        toward = SIGNS[cls.stored_params(recording).direction]
        tests = _tests(recording)
        if result["stiffness"] or result["backlash"]:
            section.plots.append(Plot("single-motor loading and backlash", png_of(
                _single_motor_figure(recording, result, tests, toward))))
        if result["preload"]:
            section.plots.append(Plot("coupled loading per preload level: master displacement "
                                      "against load",
                                      png_of(_coupled_figure(recording, result, tests, toward))))
        section.tables += _tables(result)

    @classmethod
    def headline(cls, result: Mapping[str, Any]) -> str:
        """k_m, k_s (Eq. 3.26) and the backlash per motor."""
        return _stiffness_text(result)

    @classmethod
    def live_view(cls, result: Mapping[str, Any]) -> ResultView:
        """Per loading test the mean load (N) against the mean δ (µm) of each completed
        measure step (Fig. 3.8), with the lines of Eq. (3.26) once fitted."""
        curves = [Curve(test, np.array(s["delta_m"]) * 1e6, np.array(s["force_N"]), points=True)
                  for test, s in result["steps"].items() if s["force_N"]]
        lines = [Curve(f"fit {motor}", *_fit_line(fit))
                 for motor, fit in result["stiffness"].items()]
        panel = Panel("load cell against δ = x_motor − x_load", "δ (µm)", "load (N)",
                      tuple(curves + lines))
        n = sum(len(c.x) for c in curves)
        if not n:
            return ResultView(cls.title, (panel,), "waiting for the first loading step")
        summary = f"{n} steps; " + ", ".join(f"{c.name}: {c.y.max():.0f} N at "
                                             f"{c.x[np.argmax(c.y)]:.1f} µm" for c in curves)
        fits = _stiffness_text(result)
        return ResultView(cls.title, (panel,), summary + (f"; {fits}" if fits else ""))

    @classmethod
    def summary(cls, result: Mapping[str, Any], truth: Mapping[str, Any]) -> dict:
        """k_m, k_s (Eq. 3.26) and backlash against the world; preload-loss forces against
        the thesis (Ch. 3.4.3) and 2 τ_p K_tr (Eq. 3.1)."""
        k = {m: s["k_N_m"] for m, s in result["stiffness"].items()}
        backlash = {m: b["value_m"] for m, b in result["backlash"].items()}
        levels = [_preload_level(test, truth) for test in result["preload"]]
        return {"k_N_m": k, "truth_k_N_m": {m: truth[f"k_{m}"] for m in k},
                "backlash_m": backlash, "truth_backlash_m": {m: truth[f"backlash_{m}"]
                                                             for m in backlash},
                "preload": levels,
                "headline": headline(
                    ", ".join(f"k_{m[0]} {v / N_PER_UM:.2f} N/µm "
                              f"({truth[f'k_{m}'] / N_PER_UM:g})" for m, v in k.items()),
                    "backlash " + ", ".join(
                        f"{m} {v * 1e6:.1f} µm ({truth[f'backlash_{m}'] * 1e6:g})"
                        for m, v in backlash.items()),
                    ", ".join(_loss_text(level) for level in levels))}

    @classmethod
    def details(cls, result: Mapping[str, Any]) -> list[str]:
        """Lines of a human-readable summary of the result (µm, N/µm, N)."""
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
                f"{test['recovery_force_N']:7.0f} N, jump {test['jump_m'] * 1e6:6.1f} µm, "
                f"slave {test['k_slave_contact_N_m'] / 1e6:5.1f} → "
                f"{test['k_slave_lost_N_m'] / 1e6:5.1f} N/µm, share {test['torque_share']:.3f}")
        return lines
