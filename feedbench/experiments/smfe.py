"""SMFE spindle ramp (Ch. 6.2.3, 6.4.1, Fig. 6.12): receptances from cutting forces.

Planning, before anything moves: the radial engagement of the set of cuts (down-, up- and
central milling) is the one that minimises the theoretical condition number C_th of the
force-spectrum matrix (Sec. 6.3.1, Figs. 6.7–6.8; `analysis.smfe.optimal_radial_engagement`)
unless `a_e_mm` gives it; a set whose C_th exceeds `max_condition_number` is warned about
(`SmfePlanningWarning`) and a singular set (the same cut twice) is refused.

The plan: the spindle starts through the inverter (Modbus); per cut, the axis approaches its
workpiece lane at the start feed, then the inverter ramps the spindle N0 → N1 over `ramp_s`
while the CiA 402 axis feeds at f_z·Z·N(t) (the feed per tooth stays f_z), the axis stops and
the spindle returns to N0; at the end the spindle stops and the axis returns to the start.
The streaming DAQ records the dynamometer (force on the workpiece, −F) and the tool- and
workpiece-side accelerometers at `daq_rate_Hz`.

Analysis (`analysis.smfe.smfe_estimate`, Eqs. 6.12–6.15): Φ_tt from the force on the tool and
the tool accelerations, Φ_ww from the force on the workpiece and its accelerations, Welch with
Hann segments of `segment_s` (4 s: 0.25 Hz), 80 % overlap, F_x as reference; the condition
number of the measured force-spectrum matrix (Eq. 6.14) and the coherence (Eq. 6.15).
"""

from __future__ import annotations

import math
import warnings
from typing import Any, Mapping

import numpy as np

from feedbench.analysis.smfe import (
    OVERLAP,
    SmfeResult,
    cut_set_condition_number,
    optimal_radial_engagement,
    smfe_estimate,
)
from feedbench.config import ConfigError, Field, one_of, positive, validate_table
from feedbench.experiments.family import Experiment
from feedbench.experiments.plan import Plan, Segment, recorded_windows
from feedbench.experiments.signals import integrate_velocity, ramp_to_feed
from feedbench.models.milling import (
    MAX_STEP_ROTATION,
    MILLING_MODES,
    TABLE_6_1,
    CuttingCoefficients,
    Tool,
)
from feedbench.protocols.cia402 import CSP
from feedbench.units import MM_PER_MIN, RPM

NAME = "smfe"

SINGULAR_CONDITION_NUMBER = 1e6
"""C_th above this: the cuts do not give independent equations (e.g. the same cut twice)."""

SCHEMA = {
    "type": Field(str, NAME, "experiment family"),
    "cuts": Field(list, list(MILLING_MODES), "cutting operations, one per direction",
                  one_of(*MILLING_MODES)),
    "a_e_mm": Field(list, [], "radial engagement per cut or one for all (mm); empty: the "
                    "condition-number search picks it", positive),
    "a_p_mm": Field(float, 2.0, "axial depth of cut (mm)", positive),
    "f_z_mm": Field(float, 0.1, "feed per tooth (mm)", positive),
    "tool_diameter_mm": Field(float, 80.0, "tool diameter D (mm)", positive),
    "teeth": Field(int, 2, "number of teeth Z", positive),
    "lead_angle_deg": Field(float, 45.0, "lead angle κ (deg)", positive),
    "K_tc_N_mm2": Field(float, TABLE_6_1.K_tc * 1e-6, "expected tangential shear coefficient "
                        "(N/mm²), for planning"),
    "K_rc_N_mm2": Field(float, TABLE_6_1.K_rc * 1e-6, "expected radial shear coefficient"),
    "K_ac_N_mm2": Field(float, TABLE_6_1.K_ac * 1e-6, "expected axial shear coefficient"),
    "K_te_N_mm": Field(float, TABLE_6_1.K_te * 1e-3, "expected tangential edge coefficient"),
    "K_re_N_mm": Field(float, TABLE_6_1.K_re * 1e-3, "expected radial edge coefficient"),
    "K_ae_N_mm": Field(float, TABLE_6_1.K_ae * 1e-3, "expected axial edge coefficient"),
    "max_condition_number": Field(float, 20.0, "warn when the planned C_th is above this "
                                  "(the 3-cut optimum of Table 6.1 is ≈ 9)", positive),
    "spindle_rpm_start": Field(float, 300.0, "spindle speed at the start of each ramp (rpm)",
                               positive),
    "spindle_rpm_stop": Field(float, 1500.0, "spindle speed at the end of each ramp (rpm)",
                              positive),
    "ramp_s": Field(float, 65.0, "duration of each spindle ramp (s)", positive),
    "spindle_accel_rpm_s": Field(float, 1000.0, "inverter ramp limit outside the cuts (rpm/s)",
                                 positive),
    "approach_mm": Field(float, 1.0, "travel at the start feed before each lane (mm)", positive),
    "accel_m_s2": Field(float, 0.5, "acceleration of the feed changes (m/s²)", positive),
    "return_feed_mm_min": Field(float, 2000.0, "feed of the return to the start (mm/min)",
                                positive),
    "daq_rate_Hz": Field(int, 10_000, "DAQ sample rate (Hz)", positive),
    "segment_s": Field(float, 4.0, "Welch segment length of the analysis (s)", positive),
    "spindle_readback_ms": Field(float, 10.0, "period of the inverter speed read-back (ms)",
                                 positive),
}

DAQ_CHANNELS = ("dyn_fx", "dyn_fy", "dyn_fz", "acc_tool_x", "acc_tool_y", "acc_tool_z",
                "acc_work_x", "acc_work_y", "acc_work_z")
"""What the DAQ records: the dynamometer under the workpiece and both triaxial accelerometers."""


class SmfePlanningWarning(UserWarning):
    """The planned set of cuts is badly conditioned (C_th above `max_condition_number`)."""


def planned_tool(p: Mapping[str, Any]) -> Tool:
    """The tool of the validated parameters."""
    return Tool(D=p["tool_diameter_mm"] * 1e-3, Z=p["teeth"],
                kappa=math.radians(p["lead_angle_deg"]))


def planned_coefficients(p: Mapping[str, Any]) -> CuttingCoefficients:
    """The cutting coefficients the plan expects (SI), Eq. (6.3)."""
    return CuttingCoefficients(
        K_tc=p["K_tc_N_mm2"] * 1e6, K_rc=p["K_rc_N_mm2"] * 1e6, K_ac=p["K_ac_N_mm2"] * 1e6,
        K_te=p["K_te_N_mm"] * 1e3, K_re=p["K_re_N_mm"] * 1e3, K_ae=p["K_ae_N_mm"] * 1e3)


def plan_engagement(p: Mapping[str, Any]) -> dict[str, Any]:
    """The planning step: radial engagements (mm) and the set's C_th, Sec. 6.3.1.

    Given engagements are checked; none given: `optimal_radial_engagement` with one
    engagement for every cut (Fig. 6.7). Raises `ConfigError` for a singular set, warns
    (`SmfePlanningWarning`) above `max_condition_number`.
    """
    tool, coeffs, cuts = planned_tool(p), planned_coefficients(p), tuple(p["cuts"])
    optimum = optimal_radial_engagement(tool, coeffs, cuts, p["f_z_mm"] * 1e-3)
    if p["a_e_mm"]:
        a_e = np.broadcast_to(np.asarray(p["a_e_mm"], dtype=float) * 1e-3, (len(cuts),))
        condition = cut_set_condition_number(tuple(a_e / tool.D), tool, coeffs, cuts,
                                             p["f_z_mm"] * 1e-3)
    else:
        a_e = np.asarray(optimum.a_e_over_D) * tool.D
        condition = optimum.condition_number
    if condition > SINGULAR_CONDITION_NUMBER:
        raise ConfigError(f"experiment.cuts: {cuts} with a_e {np.round(a_e * 1e3, 2).tolist()} mm "
                          f"give dependent equations (C_th = {condition:.3g}); use different cuts")
    planning = {"a_e_mm": (a_e * 1e3).tolist(), "condition_number": condition,
                "optimal_a_e_mm": (np.asarray(optimum.a_e_over_D) * tool.D * 1e3).tolist(),
                "optimal_condition_number": optimum.condition_number, "warnings": []}
    if condition > p["max_condition_number"]:
        message = (f"SMFE cuts {cuts} at a_e {np.round(a_e * 1e3, 2).tolist()} mm: C_th = "
                   f"{condition:.1f} > {p['max_condition_number']:g}; the search gives "
                   f"{planning['optimal_a_e_mm'][0]:.1f} mm (C_th {optimum.condition_number:.1f})")
        planning["warnings"].append(message)
        warnings.warn(message, SmfePlanningWarning, stacklevel=3)
    return planning


def _validated(params: Mapping[str, Any], cycle_s: float) -> dict[str, Any]:
    p = validate_table(params, SCHEMA, "experiment")
    if len(p["cuts"]) not in (2, 3):
        raise ConfigError(f"experiment.cuts: give 2 or 3 cuts (one per direction), got {p['cuts']}")
    if len(p["a_e_mm"]) not in (0, 1, len(p["cuts"])):
        raise ConfigError(f"experiment.a_e_mm: give none, one, or one per cut ({len(p['cuts'])})")
    if any(a > p["tool_diameter_mm"] for a in p["a_e_mm"]):
        raise ConfigError("experiment.a_e_mm: must not exceed tool_diameter_mm")
    if not p["spindle_rpm_start"] < p["spindle_rpm_stop"]:
        raise ConfigError("experiment.spindle_rpm_stop: must be above spindle_rpm_start")
    rotation = p["spindle_rpm_stop"] * RPM / p["daq_rate_Hz"]
    if rotation > MAX_STEP_ROTATION:
        raise ConfigError(
            f"experiment.daq_rate_Hz: {p['daq_rate_Hz']} Hz gives {math.degrees(rotation):.1f}° "
            f"of spindle rotation per sample at {p['spindle_rpm_stop']:g} rpm (at most "
            f"{math.degrees(MAX_STEP_ROTATION):.0f}°)")
    if p["segment_s"] > p["ramp_s"]:
        raise ConfigError("experiment.segment_s: must not exceed ramp_s (one cut's record)")
    if abs(p["daq_rate_Hz"] * cycle_s - round(p["daq_rate_Hz"] * cycle_s)) > 1e-9:
        raise ConfigError("experiment.daq_rate_Hz: must give whole samples per bus cycle")
    return p


def feed_for_speed(rpm: np.ndarray | float, f_z: float, Z: int) -> np.ndarray | float:
    """Feed (m/s) that keeps the feed per tooth f_z (m) at spindle speed N (rpm): f_z·Z·N/60."""
    return f_z * Z * np.asarray(rpm) / 60.0


def _hold(x: float, seconds: float, cycle_s: float) -> np.ndarray:
    return np.full(max(1, int(round(seconds / cycle_s))), x)


def _point_to_point(x0: float, x1: float, v_max: float, accel: float, cycle_s: float) -> np.ndarray:
    """Trapezoidal (or triangular) move from x0 to x1 (m), ending exactly at x1."""
    distance = abs(x1 - x0)
    v_peak = min(v_max, math.sqrt(distance * accel))
    t_acc = v_peak / accel
    t_total = distance / v_peak + t_acc if v_peak > 0 else cycle_s
    t = np.arange(1, max(1, int(math.ceil(t_total / cycle_s))) + 1) * cycle_s
    t = np.minimum(t, t_total)
    covered = np.where(t < t_acc, 0.5 * accel * t**2,
                       np.where(t <= t_total - t_acc, v_peak * (t - 0.5 * t_acc),
                                distance - 0.5 * accel * (t_total - t) ** 2))
    return x0 + math.copysign(1.0, x1 - x0) * covered


def build_plan(params: Mapping[str, Any], cycle_s: float) -> Plan:
    """Spindle start, then per cut: approach, ramp cut, stop, spindle back; spindle stop, return."""
    p = _validated(params, cycle_s)
    planning = plan_engagement(p)
    f_z, Z = p["f_z_mm"] * 1e-3, p["teeth"]
    n0, n1 = p["spindle_rpm_start"], p["spindle_rpm_stop"]
    accel, spin = p["accel_m_s2"], p["spindle_accel_rpm_s"]
    segments = [Segment("spindle start", "settle", _hold(0.0, n0 / spin + 0.5, cycle_s),
                        commands={"spindle_rpm": n0, "spindle_ramp_rpm_s": spin})]
    workpiece, x = [], 0.0
    for k, (mode, a_e) in enumerate(zip(p["cuts"], planning["a_e_mm"])):
        info = {"cut": k, "mode": mode, "a_e_mm": a_e}
        v0 = feed_for_speed(n0, f_z, Z)
        up = ramp_to_feed(0.0, v0, accel, cycle_s)
        cruise = np.full(int(round(p["approach_mm"] * 1e-3 / v0 / cycle_s)), v0)
        approach = integrate_velocity(np.concatenate([up, cruise]), x, cycle_s)
        n_ramp = int(round(p["ramp_s"] / cycle_s))
        rpm = n0 + (n1 - n0) * np.arange(1, n_ramp + 1) / n_ramp
        cut = integrate_velocity(feed_for_speed(rpm, f_z, Z), float(approach[-1]), cycle_s)
        stop = integrate_velocity(ramp_to_feed(feed_for_speed(n1, f_z, Z), 0.0, accel, cycle_s),
                                  float(cut[-1]), cycle_s)
        workpiece.append({"mode": mode, "a_e_mm": a_e, "a_p_mm": p["a_p_mm"],
                          "start_mm": float(approach[-1]) * 1e3, "stop_mm": float(cut[-1]) * 1e3})
        ramp = {"spindle_rpm": n1, "spindle_ramp_rpm_s": (n1 - n0) / p["ramp_s"]}
        segments += [
            Segment(f"approach {mode}", "move", approach, info=info),
            Segment(f"{mode} milling ramp", "measure", cut, info=info, commands=ramp),
            Segment(f"stop {mode}", "move", stop, info=info),
            Segment(f"spindle back {mode}", "settle", _hold(float(stop[-1]), (n1 - n0) / spin + 0.2,
                                                            cycle_s),
                    info=info, commands={"spindle_rpm": n0, "spindle_ramp_rpm_s": spin}),
        ]
        x = float(stop[-1])
    segments.append(Segment("return", "move", _point_to_point(
        x, 0.0, p["return_feed_mm_min"] * MM_PER_MIN, accel, cycle_s),
        commands={"spindle_rpm": 0.0, "spindle_ramp_rpm_s": spin}))
    return Plan(NAME, CSP, segments, {**p, "planning": planning, "workpiece": workpiece}, cycle_s)


def devices(p: Mapping[str, Any], cycle_s: float) -> dict[str, dict[str, Any]]:
    """The devices besides the drive this experiment needs, with their settings (from the
    plan's validated parameters)."""
    readback = max(1, round(p["spindle_readback_ms"] * 1e-3 / cycle_s))
    return {"spindle": {"readback_cycles": readback},
            "daq": {"channels": DAQ_CHANNELS, "rate_hz": p["daq_rate_Hz"]}}


Records = list[np.ndarray]


def cut_records(recording, d: int) -> tuple[Records, Records, Records, list[str]]:
    """Per measured cut: force on the tool (d × n, N), tool and workpiece accelerations.

    d: cuts planned = directions solved (3: x, y, z; 2: x, y). The dynamometer measures the
    force on the workpiece, so F_tool = −dyn. Every cut is cut to the shortest one's length
    (`smfe_estimate` needs equal records). Returns the lists and the warnings (lost samples,
    a cut without cutting force).
    """
    windows = recorded_windows(recording, "measure")
    if "daq" not in recording.streams or len(windows) != d:
        raise ConfigError(f"{recording.path}: {len(windows)} of {d} cuts recorded, "
                          f"{'a' if 'daq' in recording.streams else 'no'} DAQ stream "
                          "(was the run aborted?)")
    stream = recording.streams["daq"]
    forces, tools, works, notes = [], [], [], []
    for window in windows:
        first, last = int(recording.cycle[window.start]), int(recording.cycle[window.stop - 1])
        inside = (stream.cycle >= first) & (stream.cycle <= last)
        if stream.n_dropped and np.any(np.diff(stream.sequence[inside]) != 1):
            notes.append(f"{window.label}: samples lost inside the cut")
        channel = {name: stream.channels[name][inside] for name in DAQ_CHANNELS}
        force = -np.vstack([channel[f"dyn_f{a}"] for a in "xyz"[:d]])
        if np.abs(force).max(initial=0.0) < 1.0:
            notes.append(f"{window.label}: no cutting force recorded (tool not in the workpiece?)")
        forces.append(force)
        tools.append(np.vstack([channel[f"acc_tool_{a}"] for a in "xyz"[:d]]))
        works.append(np.vstack([channel[f"acc_work_{a}"] for a in "xyz"[:d]]))
    n = min(f.shape[1] for f in forces)
    return ([f[:, :n] for f in forces], [a[:, :n] for a in tools], [a[:, :n] for a in works],
            notes)


def _direct_peaks(result: SmfeResult, band: tuple[float, float]) -> list[dict[str, float]]:
    """Largest |Φ_ii| in `band` and its frequency, per direction."""
    inside = (result.f >= band[0]) & (result.f <= band[1])
    peaks = []
    for axis in range(result.Phi.shape[1]):
        magnitude = np.abs(result.Phi[inside, axis, axis])
        k = int(np.argmax(magnitude))
        peaks.append({"f_hz": float(result.f[inside][k]), "abs_m_N": float(magnitude[k]),
                      "coherence_min": float(result.coherence[:, np.flatnonzero(inside)[k],
                                                              axis, axis].min())})
    return peaks


def _side(result: SmfeResult, band: tuple[float, float]) -> dict[str, Any]:
    inside = (result.f >= band[0]) & (result.f <= band[1])
    axes = "xyz"[:result.Phi.shape[1]]
    return {"peaks": dict(zip(axes, _direct_peaks(result, band))),
            "abs_m_N": {a: np.abs(result.Phi[inside, i, i]).tolist() for i, a in enumerate(axes)}}


def analyze_recording(recording) -> dict:
    """Φ_tt, Φ_ww (Eq. 6.13), condition number (6.14), coherence (6.15) of the recorded cuts.

    The band is where the second harmonic of the tooth-passing frequency swept,
    2·Z·N0/60 … 2·Z·N1/60 (Hz; the first harmonic covers its lower half): below it only the
    start of the first harmonic excites. Results in SI (m/N, Hz).
    """
    p = validate_table(recording.config["experiment"], SCHEMA, "experiment")
    fs = recording.streams["daq"].rate_hz
    forces, tools, works, notes = cut_records(recording, len(p["cuts"]))
    nfft = int(round(p["segment_s"] * fs))
    band = (2.0 * p["teeth"] * p["spindle_rpm_start"] / 60.0,
            2.0 * p["teeth"] * p["spindle_rpm_stop"] / 60.0)
    tool = smfe_estimate(list(zip(forces, tools)), fs, nfft, OVERLAP, f_max=band[1])
    workpiece = smfe_estimate([(-f, a) for f, a in zip(forces, works)], fs, nfft, OVERLAP,
                              f_max=band[1])
    inside = (tool.f >= band[0]) & (tool.f <= band[1])
    planning = plan_engagement_quietly(p)
    return {
        "experiment": NAME,
        "cuts": list(p["cuts"]),
        "band_hz": list(band),
        "f_hz": tool.f[inside].tolist(),
        "tool": _side(tool, band),
        "workpiece": _side(workpiece, band),
        "condition_number": {"median": float(np.median(tool.condition_number[inside])),
                             "max": float(tool.condition_number[inside].max()),
                             "planned_C_th": planning["condition_number"]},
        "a_e_mm": planning["a_e_mm"],
        "n_averages": tool.n_averages,
        "samples_per_cut": int(forces[0].shape[1]),
        "dropped_samples": recording.streams["daq"].n_dropped,
        "warnings": notes + planning["warnings"],
    }


def plan_engagement_quietly(p: Mapping[str, Any]) -> dict[str, Any]:
    """`plan_engagement` without re-issuing its warning (the analysis reports it in its result)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SmfePlanningWarning)
        return plan_engagement(p)


def describe(result: dict) -> list[str]:
    """Text lines of an SMFE analysis (`feedbench analyze`): peaks, condition number, warnings."""
    lines = [f"  cuts {', '.join(result['cuts'])} at a_e "
             f"{', '.join(f'{a:.1f}' for a in result['a_e_mm'])} mm, band "
             f"{result['band_hz'][0]:g}-{result['band_hz'][1]:g} Hz, "
             f"{result['n_averages']} averages"]
    for side, name in (("tool", "Φ_tt"), ("workpiece", "Φ_ww")):
        peaks = result[side]["peaks"]
        lines.append(f"  {name} peaks: " + ", ".join(
            f"{axis}{axis} {p['abs_m_N']:.3g} m/N at {p['f_hz']:.2f} Hz "
            f"(γ² ≥ {p['coherence_min']:.3f})" for axis, p in peaks.items()))
    cond = result["condition_number"]
    lines.append(f"  condition number (Eq. 6.14): median {cond['median']:.1f}, "
                 f"max {cond['max']:.1f}; planned C_th {cond['planned_C_th']:.1f}")
    lines += [f"  warning: {w}" for w in result["warnings"]]
    return lines

class Smfe(Experiment):
    """TRANSITION shell: the module's functions behind the family interface."""

    name = NAME
    schema = SCHEMA

    @classmethod
    def check(cls, params: Mapping[str, Any], cycle_s: float) -> dict:
        return _validated(params, cycle_s)

    def plan(self) -> Plan:
        return build_plan(self.settings, self.cycle_s)

    def devices(self) -> dict[str, dict[str, Any]]:
        return devices(self.settings, self.cycle_s)

    @classmethod
    def analyze(cls, recording, final: bool = True) -> dict:
        return analyze_recording(recording)

    @classmethod
    def describe(cls, result: Mapping[str, Any]) -> list[str]:
        return describe(result)
