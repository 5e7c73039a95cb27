"""Backlash reversal test of the rack-and-pinion axis (thesis Ch. 3.4.2, Fig. 3.9).

Each selected motor drives the axis alone, the master–slave coupling removed as the
thesis does it: coupled, the preload (Eq. 3.1) holds the two pinions on opposite flanks,
so the load follows every reversal and the backlash stays hidden. Without load the motor
moves slowly one way, dwells, reverses, dwells, `reversals` times. At each reversal the
motor travels through its dead zone before the load follows: that lost motion is the
equivalent backlash L_z of its drive train, the jump of δ = x_motor − x_load between the
strokes (`analysis.stiffness.backlash_from_reversals`). It includes the friction wind-up
2 F_friction / k of the drive train (Eq. 3.26); with the drive train's stiffness k given
(e.g. stepped loading's k_m, k_s) the wind-up F/k is taken out of x_motor first.

The file is the worked example of docs/ARCHITECTURE.md "Adding an experiment family".
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from feedbench.analysis.checks import check, positive_parameters
from feedbench.analysis.stiffness import backlash_from_reversals
from feedbench.config import ConfigError, Field, non_negative, one_of, positive
from feedbench.engine.family import Example, Experiment, headline, percent_error
from feedbench.engine.plan import Plan, Segment, Window, recorded_windows
from feedbench.experiments.signals import constant_feed_move
from feedbench.protocols.cia402 import CSP
from feedbench.units import MM_PER_MIN, N_PER_UM
from feedbench.views.panels import Curve, Panel, ResultView
from feedbench.views.sections import Plot, RunSection, Table, new_figure, png_of

NAME = "backlash_reversal"
MOTORS = ("master", "slave")
SIGNS = {"negative": -1.0, "positive": 1.0}

SCHEMA = {
    "type": Field(str, NAME, "experiment family"),
    "motors": Field(list, ["master", "slave"], "motors tested, each alone (the other off)",
                    one_of(*MOTORS)),
    "stroke_um": Field(float, 1000.0, "stroke between reversals (µm; more than twice the "
                       "backlash, so the load follows for the second half of it)", positive),
    "feed_mm_min": Field(float, 200.0, "feed of the strokes (mm/min)", positive),
    "accel_m_s2": Field(float, 0.2, "acceleration of the strokes (m/s²)", positive),
    "dwell_s": Field(float, 0.2, "standstill at each end of a stroke (s)", positive),
    "reversals": Field(int, 3, "direction reversals per motor (reversals + 1 strokes)",
                       positive),
    "direction": Field(str, "positive", "direction of the first stroke",
                       one_of("positive", "negative")),
    "setup_s": Field(float, 1.0, "standstill after changing the coupling (s)", positive),
    "k_master_N_um": Field(float, 0.0, "master drive-train stiffness at the rack (N/µm), to "
                           "take the friction wind-up out; 0: not taken out", non_negative),
    "k_slave_N_um": Field(float, 0.0, "slave drive-train stiffness at the rack (N/µm), to "
                          "take the friction wind-up out; 0: not taken out", non_negative),
}


def _cycles(duration_s: float, cycle_s: float) -> int:
    return max(1, int(round(duration_s / cycle_s)))


def _result_of_motor(recording, windows: list[Window], motor: str, k: float,
                     final: bool) -> dict:
    """Lost motion per reversal of one motor's strokes (m) and the loop it was taken from;
    live (`final` False) a motor without a reversal yet gives its loop and what it waits for."""
    rows = np.concatenate([np.arange(w.start, w.stop) for w in windows])
    ch = recording.channels
    x_motor, x_load = ch[f"{motor}.motor_position"][rows], ch["load_position"][rows]
    loop = {"motor_m": x_motor.tolist(), "load_m": x_load.tolist()}
    try:
        raw = backlash_from_reversals(x_motor, x_load)
    except ValueError as exc:
        if final:
            raise ConfigError(f"{recording.path}: backlash of the {motor}: {exc}") from exc
        return {"n_reversals": 0, "waiting": str(exc), "loop": loop}
    fixed = backlash_from_reversals(x_motor - ch[f"{motor}.force"][rows] / k, x_load) if k else raw
    return {"value_m": fixed.value, "std_m": fixed.std,
            "per_reversal_m": fixed.per_reversal.tolist(), "uncorrected_m": raw.value,
            "corrected": bool(k), "n_reversals": int(fixed.per_reversal.size), "loop": loop}


def _motor_text(motor: str, b: Mapping[str, Any]) -> str:
    """``master 313.9 ± 0.02 µm (3 reversals)``, or that a motor waits for its first."""
    if not b["n_reversals"]:
        return f"{motor}: no reversal yet"
    return (f"{motor} {b['value_m'] * 1e6:.1f} ± {b['std_m'] * 1e6:.2f} µm "
            f"({b['n_reversals']} reversal{'s' if b['n_reversals'] > 1 else ''}"
            + ("" if b["corrected"] else ", friction wind-up included") + ")")


AGREEMENT = 0.1
"""The reversals of a motor agree when their spread is at most this share of their mean."""


def backlash_checks(found: Mapping[str, Mapping[str, Any]]) -> list[dict]:
    """Each motor's backlash > 0 (a flipped or unplugged scale fails) and its reversals
    agreeing within `AGREEMENT`; live, of the motors with a reversal so far."""
    motors = {m: b for m, b in found.items() if b["n_reversals"]}
    if not motors:
        return []
    spread = [f"{m} ± {b['std_m'] * 1e6:.2f} µm on {b['value_m'] * 1e6:.1f} µm"
              for m, b in motors.items() if not b["std_m"] <= AGREEMENT * abs(b["value_m"])]
    return [positive_parameters("backlash", {m: (b["value_m"] * 1e6, "µm")
                                             for m, b in motors.items()}),
            check("reversals agree", ", ".join(f"{m} ± {b['std_m'] * 1e6:.2f} µm"
                                               for m, b in motors.items()), not spread,
                  "; ".join(spread) + f": more than {100 * AGREEMENT:g} % apart (a slipping "
                  "scale, or the stroke too short to take the backlash up)")]


class BacklashReversal(Experiment):
    """Equivalent backlash L_z of each motor's drive train from reversals without load
    (Ch. 3.4.2, Fig. 3.9): mean and spread of the lost motion (m)."""

    name = NAME
    schema = SCHEMA
    title = "backlash: load against motor position"
    examples = (Example(NAME, rank=90),)  # --quick: runs as configured
    axes = ("rack_pinion",)
    live_kinds = ("measure",)

    @classmethod
    def check(cls, params: Mapping[str, Any], cycle_s: float) -> dict:
        """The schema's checks, at least one motor, and a stroke that reaches the feed."""
        p = super().check(params, cycle_s)
        if not p["motors"]:
            raise ConfigError("experiment.motors: must name at least one of master, slave")
        if cls._cruise_s(cls.typed(p)) <= 0.0:
            raise ConfigError("experiment.stroke_um: too short to reach feed_mm_min at "
                              "accel_m_s2 (no constant-feed part)")
        return p

    @staticmethod
    def _cruise_s(p: Any) -> float:
        """Time at constant feed in one stroke (s) of the typed parameters `p`."""
        feed = p.feed_mm_min * MM_PER_MIN
        return p.stroke_um * 1e-6 / feed - feed / p.accel_m_s2

    def plan(self) -> Plan:
        """Per motor: uncouple (the segment's ``coupling`` command sets the axis controller,
        `axes.rack_pinion.AxisSettings`), then strokes (measured) and dwells, alternating."""
        p, dt = self.params, self.cycle_s
        segments: list[Segment] = []
        for motor in p.motors:
            segments.append(Segment(f"setup {motor}", "settle",
                                    np.zeros(_cycles(p.setup_s, dt)),
                                    info={"motor": motor}, commands={"coupling": motor}))
            segments += self._strokes(motor)
        return Plan(NAME, CSP, segments, self.settings, dt)

    def _strokes(self, motor: str) -> list[Segment]:
        p, dt = self.params, self.cycle_s
        feed = SIGNS[p.direction] * p.feed_mm_min * MM_PER_MIN
        segments, x = [], 0.0
        for i in range(p.reversals + 1):
            path, _, _ = constant_feed_move(x, feed if i % 2 == 0 else -feed, p.accel_m_s2,
                                            self._cruise_s(p), dt)
            x = float(path[-1])
            info = {"motor": motor, "stroke": i + 1}
            segments += [Segment(f"{motor} stroke {i + 1}", "measure", path, info=info),
                         Segment(f"{motor} dwell {i + 1}", "settle",
                                 np.full(_cycles(p.dwell_s, dt), x), info=info)]
        return segments

    @classmethod
    def analyze(cls, recording, final: bool = True) -> dict:
        """Backlash per motor: per reversal, mean and spread (m), and the strokes' loop of
        load against motor position (m). Live, the reversals completed so far."""
        p = cls.stored_params(recording)
        windows = recorded_windows(recording, "measure", at_least=1 if final else 0)
        motors = {motor: [w for w in windows if w.info["motor"] == motor]
                  for motor in p.motors}
        result = {motor: _result_of_motor(recording, found, motor,
                                          getattr(p, f"k_{motor}_N_um") * N_PER_UM, final)
                  for motor, found in motors.items() if found}
        return {"experiment": NAME, "motors": result, "checks": backlash_checks(result)}

    @classmethod
    def report(cls, recording, result: Mapping[str, Any], section: RunSection) -> None:
        """The hysteresis loop (load against motor position, mm) and the backlash table."""
        figure = new_figure(7.0, 5.0)
        axes = figure.subplots()
        for motor, b in result["motors"].items():
            axes.plot(np.array(b["loop"]["motor_m"]) * 1e3, np.array(b["loop"]["load_m"]) * 1e3,
                      lw=1.0, label=motor)
        axes.set_xlabel("motor position at the rack (mm)")
        axes.set_ylabel("load position, linear scale (mm)")
        axes.grid(alpha=0.3)
        axes.legend(fontsize=8)
        section.plots.append(Plot("backlash reversals: load against motor position",
                                  png_of(figure)))
        section.tables.append(Table("equivalent backlash L_z (Ch. 3.4.2)", (
            "motor", "mean (µm)", "spread (µm)", "per reversal (µm)", "friction wind-up"),
            tuple(cls._table_row(motor, b) for motor, b in result["motors"].items())))

    @classmethod
    def headline(cls, result: Mapping[str, Any]) -> str:
        """Each motor's backlash, mean ± spread of its reversals."""
        return ", ".join(_motor_text(m, b) for m, b in result["motors"].items())

    @staticmethod
    def _table_row(motor: str, b: Mapping[str, Any]) -> tuple[str, ...]:
        """One motor's backlash (µm) as the report's table shows it."""
        return (motor, f"{b['value_m'] * 1e6:.1f}", f"{b['std_m'] * 1e6:.2f}",
                ", ".join(f"{v * 1e6:.1f}" for v in b["per_reversal_m"]),
                "taken out" if b["corrected"] else
                f"included ({b['uncorrected_m'] * 1e6:.1f} µm uncorrected)")

    @classmethod
    def live_view(cls, result: Mapping[str, Any]) -> ResultView:
        """The loop so far (mm) and the backlash of the reversals completed so far."""
        curves = tuple(Curve(motor, np.array(b["loop"]["motor_m"]) * 1e3,
                             np.array(b["loop"]["load_m"]) * 1e3)
                       for motor, b in result["motors"].items())
        panel = Panel("load against motor position", "motor position (mm)",
                      "load position (mm)", curves)
        return ResultView(cls.title, (panel,),
                          "; ".join(_motor_text(m, b) for m, b in result["motors"].items()))

    @classmethod
    def summary(cls, result: Mapping[str, Any], truth: Mapping[str, Any]) -> dict:
        """Each motor's backlash against the world's dead zone (m, % error)."""
        motors = {motor: {"value_m": b["value_m"], "std_m": b["std_m"],
                          "truth_m": truth[f"backlash_{motor}"],
                          "error_pct": percent_error(b["value_m"], truth[f"backlash_{motor}"])}
                  for motor, b in result["motors"].items()}
        return {"motors": motors, "headline": headline(*(
            f"backlash {motor} {m['value_m'] * 1e6:.1f} ± {m['std_m'] * 1e6:.2f} µm "
            f"(truth {m['truth_m'] * 1e6:g}, {m['error_pct']:+.2f} %)"
            for motor, m in motors.items()))}
