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
number of the measured force-spectrum matrix (Eq. 6.14) and the coherence (Eq. 6.15). The
sweep the cuts excite the structure with is part of the result too, from the first segment
on (the live window shows it while the cuts run, Ch. 6.4.1): the spindle speed read back from
the inverter and the spectrogram of the dynamometer force, with the tooth-passing harmonics
k·Z·N/60 over it.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import asdict
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np
import scipy

from feedbench.analysis.checks import check, peak_checks
from feedbench.analysis.smfe import (
    OVERLAP,
    SmfeResult,
    cut_set_condition_number,
    optimal_radial_engagement,
    smfe_estimate,
)
from feedbench.config import ConfigError, Field, one_of, positive
from feedbench.engine.family import Example, Experiment, headline, percent_error
from feedbench.engine.plan import Plan, Segment, recorded_windows
from feedbench.experiments.signals import integrate_velocity, ramp_to_feed
from feedbench.models.milling import (
    MAX_STEP_ROTATION,
    MILLING_MODES,
    TABLE_6_1,
    CuttingCoefficients,
    Tool,
)
from feedbench.models.structure import POINT_DOF, ModalStructure
from feedbench.protocols.cia402 import CSP
from feedbench.units import MM_PER_MIN, RPM
from feedbench.views.panels import Curve, Image, Panel, ResultView, phase_panel
from feedbench.views.sections import (
    MIN_COHERENCE, FrfSeries, Plot, RunSection, Table, frf_figure, new_figure, png_of,
)

if TYPE_CHECKING:
    from matplotlib.figure import Figure as MplFigure

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
DYNAMOMETER = DAQ_CHANNELS[:3]

SIDES = ("tool", "workpiece")
SIDE_NAMES = ("Φ_tt", "Φ_ww")
"""The two sides of the cut and their direct receptances (Eq. 6.13)."""

SPEED_TRACE_CYCLES = 50
"""Bus cycles averaged into one point of the spindle-speed trace (the runner's block)."""

SPECTROGRAM_SEGMENT_S = 0.5
SPECTROGRAM_HOP_S = 0.25
"""Hann segments of the force spectrogram (2 Hz resolution) and their spacing (s)."""

SPECTROGRAM_HARMONICS = (1, 2)
"""Tooth-passing harmonics k·Z·N/60 drawn over the spectrogram (the analysis band is the
second's); the spectrogram reaches half a harmonic above the last at N1."""

SPECTROGRAM_DB_DECIMALS = 1
"""The spectrogram is kept to 0.1 dB: a picture of the sweep, not a measurement."""

SPECTROGRAM_RANGE_DB = 60.0
"""Colour range below the loudest bin."""

SPECTROGRAM_TITLE = "force spectrogram, Σ PSD (dB re 1 N²/Hz)"


class SmfePlanningWarning(UserWarning):
    """The planned set of cuts is badly conditioned (C_th above `max_condition_number`)."""


def planned_tool(p: Any) -> Tool:
    """The tool of the validated parameters."""
    return Tool(D=p.tool_diameter_mm * 1e-3, Z=p.teeth,
                kappa=math.radians(p.lead_angle_deg))


def planned_coefficients(p: Any) -> CuttingCoefficients:
    """The cutting coefficients the plan expects (SI), Eq. (6.3)."""
    return CuttingCoefficients(
        K_tc=p.K_tc_N_mm2 * 1e6, K_rc=p.K_rc_N_mm2 * 1e6, K_ac=p.K_ac_N_mm2 * 1e6,
        K_te=p.K_te_N_mm * 1e3, K_re=p.K_re_N_mm * 1e3, K_ae=p.K_ae_N_mm * 1e3)


def plan_engagement(p: Any) -> dict[str, Any]:
    """The planning step: radial engagements (mm) and the set's C_th, Sec. 6.3.1.

    Given engagements are checked; none given: `optimal_radial_engagement` with one
    engagement for every cut (Fig. 6.7). Raises `ConfigError` for a singular set, warns
    (`SmfePlanningWarning`) above `max_condition_number`.
    """
    tool, coeffs, cuts = planned_tool(p), planned_coefficients(p), tuple(p.cuts)
    optimum = optimal_radial_engagement(tool, coeffs, cuts, p.f_z_mm * 1e-3)
    if p.a_e_mm:
        a_e = np.broadcast_to(np.asarray(p.a_e_mm, dtype=float) * 1e-3, (len(cuts),))
        condition = cut_set_condition_number(tuple(a_e / tool.D), tool, coeffs, cuts,
                                             p.f_z_mm * 1e-3)
    else:
        a_e = np.asarray(optimum.a_e_over_D) * tool.D
        condition = optimum.condition_number
    if condition > SINGULAR_CONDITION_NUMBER:
        raise ConfigError(f"experiment.cuts: {cuts} with a_e {np.round(a_e * 1e3, 2).tolist()} mm "
                          f"give dependent equations (C_th = {condition:.3g}); use different cuts")
    planning = {"a_e_mm": (a_e * 1e3).tolist(), "condition_number": condition,
                "optimal_a_e_mm": (np.asarray(optimum.a_e_over_D) * tool.D * 1e3).tolist(),
                "optimal_condition_number": optimum.condition_number, "warnings": []}
    if condition > p.max_condition_number:
        message = (f"SMFE cuts {cuts} at a_e {np.round(a_e * 1e3, 2).tolist()} mm: C_th = "
                   f"{condition:.1f} > {p.max_condition_number:g}; the search gives "
                   f"{planning['optimal_a_e_mm'][0]:.1f} mm (C_th {optimum.condition_number:.1f})")
        planning["warnings"].append(message)
        warnings.warn(message, SmfePlanningWarning, stacklevel=3)
    return planning


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


def build_plan(p: Any, cycle_s: float) -> Plan:
    """Spindle start, then per cut: approach, ramp cut, stop, spindle back; spindle stop,
    return (`p` validated)."""
    planning = plan_engagement(p)
    f_z, Z = p.f_z_mm * 1e-3, p.teeth
    n0, n1 = p.spindle_rpm_start, p.spindle_rpm_stop
    accel, spin = p.accel_m_s2, p.spindle_accel_rpm_s
    segments = [Segment("spindle start", "settle", _hold(0.0, n0 / spin + 0.5, cycle_s),
                        commands={"spindle_rpm": n0, "spindle_ramp_rpm_s": spin})]
    workpiece, x = [], 0.0
    for k, (mode, a_e) in enumerate(zip(p.cuts, planning["a_e_mm"])):
        info = {"cut": k, "mode": mode, "a_e_mm": a_e}
        v0 = feed_for_speed(n0, f_z, Z)
        up = ramp_to_feed(0.0, v0, accel, cycle_s)
        cruise = np.full(int(round(p.approach_mm * 1e-3 / v0 / cycle_s)), v0)
        approach = integrate_velocity(np.concatenate([up, cruise]), x, cycle_s)
        n_ramp = int(round(p.ramp_s / cycle_s))
        rpm = n0 + (n1 - n0) * np.arange(1, n_ramp + 1) / n_ramp
        cut = integrate_velocity(feed_for_speed(rpm, f_z, Z), float(approach[-1]), cycle_s)
        stop = integrate_velocity(ramp_to_feed(feed_for_speed(n1, f_z, Z), 0.0, accel, cycle_s),
                                  float(cut[-1]), cycle_s)
        workpiece.append({"mode": mode, "a_e_mm": a_e, "a_p_mm": p.a_p_mm,
                          "start_mm": float(approach[-1]) * 1e3, "stop_mm": float(cut[-1]) * 1e3})
        ramp = {"spindle_rpm": n1, "spindle_ramp_rpm_s": (n1 - n0) / p.ramp_s}
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
        x, 0.0, p.return_feed_mm_min * MM_PER_MIN, accel, cycle_s),
        commands={"spindle_rpm": 0.0, "spindle_ramp_rpm_s": spin}))
    return Plan(NAME, CSP, segments, {**asdict(p), "planning": planning, "workpiece": workpiece},
                cycle_s)


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


def cuts_check(recording, p: Any) -> dict[str, Any]:
    """Every planned cut recorded (the receptances, Eq. 6.13, solve one equation per
    direction), each at least one Welch segment of `segment_s` long (`p` validated)."""
    stream = recording.streams["daq"]
    lengths = [int(np.count_nonzero((stream.cycle >= recording.cycle[w.start])
                                    & (stream.cycle <= recording.cycle[w.stop - 1])))
               for w in recorded_windows(recording, "measure")]
    d, shortest = len(p.cuts), min(lengths, default=0) / stream.rate_hz
    return check("cuts recorded", f"{len(lengths)} of {d}"
                 + (f", the shortest {shortest:.2f} s" if lengths else ""),
                 len(lengths) == d and shortest >= p.segment_s,
                 f"the receptances (Eq. 6.13) need all {d} cuts (one per direction), each at "
                 f"least one Welch segment of {p.segment_s:g} s: none computed")


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
    """One side's direct peaks, |Φ_ii| (m/N), its phase (rad) and the lowest coherence over
    the cuts of each direct pair (Eq. 6.15) in `band`."""
    inside = (result.f >= band[0]) & (result.f <= band[1])
    axes = "xyz"[:result.Phi.shape[1]]
    return {"peaks": dict(zip(axes, _direct_peaks(result, band))),
            "abs_m_N": {a: np.abs(result.Phi[inside, i, i]).tolist() for i, a in enumerate(axes)},
            "phase_rad": {a: np.angle(result.Phi[inside, i, i]).tolist()
                          for i, a in enumerate(axes)},
            "coherence_min": {a: result.coherence[:, inside, i, i].min(axis=0).tolist()
                              for i, a in enumerate(axes)}}


def analysis_band(p: Any) -> tuple[float, float]:
    """Where the second harmonic of the tooth-passing frequency swept, 2·Z·N0/60 … 2·Z·N1/60
    (Hz; the first harmonic covers its lower half): below it only the start of the first
    harmonic excites."""
    return (2.0 * p.teeth * p.spindle_rpm_start / 60.0,
            2.0 * p.teeth * p.spindle_rpm_stop / 60.0)


def receptances(recording, p: Any) -> dict[str, Any]:
    """Φ_tt, Φ_ww (Eq. 6.13), condition number (6.14) per frequency and coherence (6.15) of
    the recorded cuts in the analysis band (SI: m/N, Hz); `ConfigError` unless every cut
    was recorded."""
    fs = recording.streams["daq"].rate_hz
    forces, tools, works, notes = cut_records(recording, len(p.cuts))
    nfft = int(round(p.segment_s * fs))
    band = analysis_band(p)
    tool = smfe_estimate(list(zip(forces, tools)), fs, nfft, OVERLAP, f_max=band[1])
    workpiece = smfe_estimate([(-f, a) for f, a in zip(forces, works)], fs, nfft, OVERLAP,
                              f_max=band[1])
    inside = (tool.f >= band[0]) & (tool.f <= band[1])
    planning = plan_engagement_quietly(p)
    return {
        "f_hz": tool.f[inside].tolist(),
        "tool": _side(tool, band),
        "workpiece": _side(workpiece, band),
        "condition_number": {"median": float(np.median(tool.condition_number[inside])),
                             "max": float(tool.condition_number[inside].max()),
                             "planned_C_th": planning["condition_number"],
                             "per_f": tool.condition_number[inside].tolist()},
        "a_e_mm": planning["a_e_mm"],
        "n_averages": tool.n_averages,
        "samples_per_cut": int(forces[0].shape[1]),
        "dropped_samples": recording.streams["daq"].n_dropped,
        "warnings": notes + planning["warnings"],
    }


def plan_engagement_quietly(p: Any) -> dict[str, Any]:
    """`plan_engagement` without re-issuing its warning (the analysis reports it in its result)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SmfePlanningWarning)
        return plan_engagement(p)


# the sweep the cuts excite the structure with: spindle speed and force spectrogram

def spindle_trace(recording) -> dict[str, list[float]]:
    """The inverter's read-back speed (rpm), the mean of every `SPEED_TRACE_CYCLES` cycles
    that read it, at each bucket's middle cycle (s from the first); empty without it."""
    speed = recording.channels.get("spindle_speed")
    if speed is None or not len(speed):
        return {"t_s": [], "rpm": []}
    starts = np.arange(0, len(speed), SPEED_TRACE_CYCLES)
    read = np.isfinite(speed)
    sums = np.add.reduceat(np.where(read, speed, 0.0), starts)
    counts = np.add.reduceat(read, starts)
    middles = starts + (np.minimum(starts + SPEED_TRACE_CYCLES, len(speed)) - starts) // 2
    t = (recording.cycle[middles] - recording.cycle[0]) * float(recording.metadata["cycle_s"])
    keep = counts > 0
    return {"t_s": t[keep].tolist(), "rpm": (sums[keep] / counts[keep] / RPM).tolist()}


def force_spectrogram(recording, p: Any) -> dict[str, Any]:
    """Σ PSD of the dynamometer's F_x, F_y, F_z (dB re 1 N²/Hz, `SPECTROGRAM_DB_DECIMALS`) over
    the run: Hann segments of `SPECTROGRAM_SEGMENT_S` every `SPECTROGRAM_HOP_S`
    (`scipy.signal.spectrogram`), bins 0 < f ≤ (last harmonic + ½)·Z·N1/60. Column k (one
    row of ``db``) is centred at t0_s + k·dt_s (s from the first cycle), bin j at
    f0_hz + j·df_hz."""
    stream = recording.streams["daq"]
    fs = stream.rate_hz
    n_segment, hop = int(round(SPECTROGRAM_SEGMENT_S * fs)), int(round(SPECTROGRAM_HOP_S * fs))
    f = np.fft.rfftfreq(n_segment, 1.0 / fs)
    f_max = (max(SPECTROGRAM_HARMONICS) + 0.5) * p.teeth * p.spindle_rpm_stop / 60.0
    keep = (f > 0) & (f <= f_max)
    grid = {"dt_s": hop / fs, "f0_hz": float(f[1]), "df_hz": float(f[1]), "f_max_hz": f_max}
    if len(stream.cycle) < n_segment:
        return {**grid, "t0_s": 0.0, "db": []}
    psd = sum(scipy.signal.spectrogram(stream.channels[c], fs, window="hann",
                                       nperseg=n_segment, noverlap=n_segment - hop,
                                       detrend=False)[2][keep] for c in DYNAMOMETER)
    db = np.round(10.0 * np.log10(np.maximum(psd.T, 1e-30)), SPECTROGRAM_DB_DECIMALS)
    t0 = (stream.cycle[n_segment // 2] - recording.cycle[0]) * float(recording.metadata["cycle_s"])
    return {**grid, "t0_s": float(t0), "db": db.tolist()}


def sweep_panels(result: Mapping[str, Any]) -> tuple[Panel, Panel]:
    """Live panels: the spindle speed (rpm), and the force spectrogram with the
    tooth-passing harmonics k·Z·N/60 over it."""
    t, rpm = np.asarray(result["spindle"]["t_s"]), np.asarray(result["spindle"]["rpm"])
    harmonics = tuple(Curve(f"{k}·Z·N/60", t, k * result["teeth"] * rpm / 60.0)
                      for k in SPECTROGRAM_HARMONICS)
    grid = result["spectrogram"]
    db = np.asarray(grid["db"])
    image = Image(db, grid["t0_s"] - 0.5 * grid["dt_s"], grid["dt_s"],
                  grid["f0_hz"] - 0.5 * grid["df_hz"], grid["df_hz"],
                  (float(db.max()) - SPECTROGRAM_RANGE_DB, float(db.max()))) if db.size else None
    return (Panel("spindle speed", "time (s)", "N (rpm)", (Curve("spindle speed", t, rpm),)),
            Panel(SPECTROGRAM_TITLE, "time (s)", "frequency (Hz)", harmonics,
                  y_range=(0.0, grid["f_max_hz"]), image=image))


def speed_text(result: Mapping[str, Any]) -> str:
    """The latest spindle speed (rpm) read back and its tooth-passing frequency Z·N/60 (Hz)."""
    rpm = result["spindle"]["rpm"]
    if not rpm:
        return "no spindle speed read back"
    return f"spindle {rpm[-1]:.0f} rpm, tooth passing {result['teeth'] * rpm[-1] / 60.0:.1f} Hz"


def receptance_panels(result: Mapping[str, Any]) -> tuple[Panel, Panel]:
    """Live panels: |Φ_tt,ii| and |Φ_ww,ii| (m/N, log) over the band, and their phase (°)."""
    f = np.asarray(result["f_hz"])
    names = [(side, name, axis) for side, name in zip(SIDES, SIDE_NAMES)
             for axis in result[side]["abs_m_N"]]
    return (Panel("direct receptances", "frequency (Hz)", "receptance (m/N)", tuple(
                Curve(f"|{name},{axis}{axis}|", f, np.asarray(result[side]["abs_m_N"][axis]))
                for side, name, axis in names), log_y=True),
            phase_panel({f"{name},{axis}{axis}": (f, result[side]["phase_rad"][axis])
                         for side, name, axis in names}))


def sweep_figure(result: Mapping[str, Any]) -> MplFigure:
    """Report figure: the spindle speed (rpm), and the force spectrogram with the
    tooth-passing harmonics over it."""
    speed_panel, spectrogram_panel = sweep_panels(result)
    figure = new_figure(10.0, 4.5)
    speed, spectrogram = figure.subplots(1, 2, width_ratios=(1, 2))
    for ax, panel in ((speed, speed_panel), (spectrogram, spectrogram_panel)):
        for curve in panel.curves:
            ax.plot(curve.x, curve.y, lw=1.0, label=curve.name)
        ax.set_title(panel.title, fontsize=9)
        ax.set_xlabel(panel.x_label)
        ax.set_ylabel(panel.y_label)
        ax.grid(alpha=0.3)
    image = spectrogram_panel.image
    if image is not None:
        extent = (image.x0, image.x0 + image.dx * image.z.shape[0],
                  image.y0, image.y0 + image.dy * image.z.shape[1])
        mesh = spectrogram.imshow(image.z.T, origin="lower", aspect="auto", extent=extent,
                                  vmin=image.levels[0], vmax=image.levels[1], cmap="viridis")
        figure.colorbar(mesh, ax=spectrogram, label="dB re 1 N²/Hz")
    spectrogram.set_ylim(*spectrogram_panel.y_range)
    spectrogram.legend(fontsize=8, loc="upper left")
    return figure


def condition_figure(result: Mapping[str, Any]) -> MplFigure:
    """Report figure: C(f) (Eq. 6.14) of the measured force spectra with the planned C_th."""
    f = np.array(result["f_hz"])
    cond = result["condition_number"]
    figure = new_figure(8.0, 3.0)
    condition = figure.subplots()
    condition.semilogy(f, cond["per_f"], lw=1.0, label="measured C(f)")
    condition.axhline(cond["planned_C_th"], color="r", ls="--", lw=0.8,
                      label=f"planned C_th {cond['planned_C_th']:.1f}")
    condition.set_ylabel("condition number C")
    condition.set_xlabel("frequency (Hz)")
    condition.grid(alpha=0.3, which="both")
    condition.legend(fontsize=8)
    return figure


def receptance_plot(result: Mapping[str, Any], side: str, name: str) -> Plot:
    """Report plot: one side's direct receptances Φ_ii (m/N): magnitude, phase and the
    lowest coherence over the cuts (Eq. 6.15), one colour per direction, its peaks marked."""
    f = np.array(result["f_hz"])
    data = result[side]
    series = [FrfSeries(f"{name},{axis}{axis}", f, np.array(data["abs_m_N"][axis]),
                        np.array(data["phase_rad"][axis]), np.array(data["coherence_min"][axis]))
              for axis in data["abs_m_N"]]
    marks = [(f"{axis}{axis} {p['f_hz']:.1f} Hz", p["f_hz"]) for axis, p in data["peaks"].items()]
    return Plot(f"SMFE direct receptances {name} at the {side} (Eq. 6.13): magnitude, phase, "
                "coherence (Eq. 6.15, lowest over the cuts)",
                png_of(frf_figure(series, "receptance (m/N)", "coherence, lowest over the cuts",
                                  marks=marks)))


def peaks_text(result: Mapping[str, Any]) -> str:
    """``Φ_tt peaks xx 51.2 Hz, …``: where the tool's direct receptances peak."""
    return "Φ_tt peaks " + ", ".join(f"{axis}{axis} {p['f_hz']:.1f} Hz"
                                     for axis, p in result["tool"]["peaks"].items())


# the demo's summary against the simulated world's modal structure

def _truth_peak(structure: ModalStructure, row: int, f: np.ndarray) -> tuple[float, float]:
    """Largest analytic |Φ_ii| (m/N) over f's span on a 0.01 Hz grid, and its frequency."""
    fine = np.arange(f[0], f[-1], 0.01)
    magnitude = np.abs(structure.receptance(fine)[:, row, row])
    return float(magnitude.max()), float(fine[np.argmax(magnitude)])


def _peaks_against_truth(result: Mapping[str, Any], side: str, structure: ModalStructure,
                         first_row: int) -> dict:
    """Each direct peak of one side beside the truth's largest |Φ_ii| in the band."""
    f = np.asarray(result["f_hz"])
    out = {}
    for row, (axis, peak) in enumerate(result[side]["peaks"].items(), start=first_row):
        truth_abs, truth_f = _truth_peak(structure, row, f)
        out[axis] = {**peak, "truth_abs_m_N": truth_abs, "truth_f_hz": truth_f,
                     "error_pct": percent_error(peak["abs_m_N"], truth_abs)}
    return out


def _side_text(side: str, peaks: Mapping[str, dict]) -> str:
    worst = max(abs(p["error_pct"]) for p in peaks.values())
    return (f"Φ_{side[0] * 2} peaks "
            + ", ".join(f"{axis * 2} {p['f_hz']:.2f} Hz" for axis, p in peaks.items())
            + f": |Φ| within {worst:.1f} % of the truth")


def receptance_checks(result: Mapping[str, Any]) -> list[dict]:
    """The cuts' force spectra independent enough (median condition number, Eq. 6.14, at
    most the planned C_th), every direct peak a mode inside the band with its coherence
    (Eq. 6.15) at least `MIN_COHERENCE`, and no warning."""
    cond = result["condition_number"]
    peaks = [(f"{side} {axis}{axis}", p["f_hz"], result["f_hz"],
              result[side]["coherence_min"][axis])
             for side in SIDES for axis, p in result[side]["peaks"].items()]
    return [check("condition number (median / max / planned C_th)",
                  f"{cond['median']:.1f} / {cond['max']:.1f} / {cond['planned_C_th']:.1f}",
                  cond["median"] <= cond["planned_C_th"],
                  "the cuts' force spectra are nearly dependent: choose engagements that load "
                  "the directions differently (Eq. 6.16)"),
            *peak_checks(peaks, MIN_COHERENCE),
            check("warnings", "; ".join(result["warnings"]) or "none", not result["warnings"],
                  "see the warnings")]


class Smfe(Experiment):
    """SMFE spindle ramp (Ch. 6.2.3, 6.4.1, Fig. 6.12): the direct receptances at the tool
    and the workpiece from the cutting forces of 2 or 3 cuts (Eqs. 6.12–6.13), the condition
    number of the measured force spectra (6.14) and the coherence (6.15); while it runs, the
    spindle speed and the force spectrogram with the tooth-passing harmonics it sweeps."""

    name = NAME
    schema = SCHEMA
    title = "SMFE: spindle speed and force spectrogram"
    examples = (
        # --quick: 8 s ramps (300 → 1500 rpm) give 6 Welch averages of 4 s: peaks within 5 %
        # of the truth.
        Example(NAME, {"experiment": {"ramp_s": 8.0, "spindle_accel_rpm_s": 3000.0,
                                      "approach_mm": 0.3, "return_feed_mm_min": 2500.0}},
                rank=70),
    )
    live_kinds = ("settle", "move", "measure")

    @classmethod
    def check(cls, params: Mapping[str, Any], cycle_s: float) -> dict[str, Any]:
        """The schema's checks, 2 or 3 cuts with their engagements, a rising ramp, at most
        `MAX_STEP_ROTATION` per DAQ sample, a Welch segment within a cut's record, whole DAQ
        samples per bus cycle."""
        p = super().check(params, cycle_s)
        if len(p["cuts"]) not in (2, 3):
            raise ConfigError(f"experiment.cuts: give 2 or 3 cuts (one per direction), "
                              f"got {p['cuts']}")
        if len(p["a_e_mm"]) not in (0, 1, len(p["cuts"])):
            raise ConfigError(f"experiment.a_e_mm: give none, one, or one per cut "
                              f"({len(p['cuts'])})")
        if any(a > p["tool_diameter_mm"] for a in p["a_e_mm"]):
            raise ConfigError("experiment.a_e_mm: must not exceed tool_diameter_mm")
        if not p["spindle_rpm_start"] < p["spindle_rpm_stop"]:
            raise ConfigError("experiment.spindle_rpm_stop: must be above spindle_rpm_start")
        rotation = p["spindle_rpm_stop"] * RPM / p["daq_rate_Hz"]
        if rotation > MAX_STEP_ROTATION:
            raise ConfigError(
                f"experiment.daq_rate_Hz: {p['daq_rate_Hz']} Hz gives "
                f"{math.degrees(rotation):.1f}° of spindle rotation per sample at "
                f"{p['spindle_rpm_stop']:g} rpm (at most {math.degrees(MAX_STEP_ROTATION):.0f}°)")
        if p["segment_s"] > p["ramp_s"]:
            raise ConfigError("experiment.segment_s: must not exceed ramp_s (one cut's record)")
        if abs(p["daq_rate_Hz"] * cycle_s - round(p["daq_rate_Hz"] * cycle_s)) > 1e-9:
            raise ConfigError("experiment.daq_rate_Hz: must give whole samples per bus cycle")
        return p

    def plan(self) -> Plan:
        return build_plan(self.params, self.cycle_s)

    def devices(self) -> dict[str, dict[str, Any]]:
        """The spindle inverter (read back every `spindle_readback_ms`) and the DAQ."""
        p = self.params
        readback = max(1, round(p.spindle_readback_ms * 1e-3 / self.cycle_s))
        return {"spindle": {"readback_cycles": readback},
                "daq": {"channels": DAQ_CHANNELS, "rate_hz": p.daq_rate_Hz}}

    @classmethod
    def analyze(cls, recording, final: bool = True) -> dict:
        """The spindle speed and force spectrogram of the run, and once every cut is
        recorded the receptances (`receptances`; `final`: `ConfigError` before that, but a
        run stopped before its cuts were recorded gives the sweep, not valid: `cuts_check`).
        SI (m/N, Hz, s), speeds rpm."""
        p = cls.stored_params(recording)
        cuts = len(recorded_windows(recording, "measure"))
        sweep = {"experiment": NAME, "cuts": list(p.cuts), "cuts_recorded": cuts,
                 "band_hz": list(analysis_band(p)), "teeth": p.teeth,
                 "spindle": spindle_trace(recording),
                 "spectrogram": force_spectrogram(recording, p)}
        if not final and cuts < len(p.cuts):
            return sweep
        recorded = cuts_check(recording, p)
        if not recorded["ok"] and recording.status != "complete":  # stopped before the end
            return {**sweep, "checks": [recorded]}
        result = {**sweep, **receptances(recording, p)}
        return {**result, "checks": receptance_checks(result)}

    @classmethod
    def report(cls, recording, result: Mapping[str, Any], section: RunSection) -> None:
        """Direct receptances Φ_tt and Φ_ww (Eq. 6.13), the condition number of the measured
        force-spectrum matrix (Eq. 6.14) against the planned C_th, the coherence of every
        direct response/force pair per cut (Eq. 6.15), and the sweep: spindle speed and
        force spectrogram."""
        sweep = Plot("spindle speed and force spectrogram with the tooth-passing harmonics",
                     png_of(sweep_figure(result)))
        if "f_hz" not in result:  # a run stopped before its cuts were recorded: the sweep
            section.plots.append(sweep)
            return
        section.plots += [
            *(receptance_plot(result, side, name) for side, name in zip(SIDES, SIDE_NAMES)),
            Plot("condition number (Eq. 6.14) against the planned C_th",
                 png_of(condition_figure(result))),
            sweep,
        ]
        section.tables.append(Table("SMFE peaks", ("side", "direction", "peak (Hz)",
                                                   "|Φ| (m/N)", "min coherence at the peak"),
                                    tuple((side, f"{axis}{axis}", f"{p['f_hz']:.2f}",
                                           f"{p['abs_m_N']:.3g}", f"{p['coherence_min']:.3f}")
                                          for side in SIDES
                                          for axis, p in result[side]["peaks"].items())))

    @classmethod
    def headline(cls, result: Mapping[str, Any]) -> str:
        """The direct receptance peaks of both sides."""
        if "f_hz" not in result:
            return f"{result['cuts_recorded']} of {len(result['cuts'])} cuts: no receptances"
        return peaks_text(result)

    @classmethod
    def live_view(cls, result: Mapping[str, Any]) -> ResultView:
        """Spindle speed and force spectrogram so far; with every cut recorded, also the
        direct receptances |Φ_tt,ii| and |Φ_ww,ii| (m/N)."""
        parts = [speed_text(result),
                 f"{len(result['spectrogram']['db'])} spectra of {SPECTROGRAM_SEGMENT_S:g} s",
                 f"{result['cuts_recorded']} of {len(result['cuts'])} cuts"]
        panels = sweep_panels(result)
        if "f_hz" in result:
            panels += receptance_panels(result)
            parts.append(peaks_text(result))
        return ResultView(cls.title, panels, "; ".join(parts))

    @classmethod
    def summary(cls, result: Mapping[str, Any], truth: Mapping[str, Any]) -> dict:
        """Direct receptance peaks of Φ_tt and Φ_ww (Eq. 6.13) against the world's modal
        structure, condition number (6.14) against the planned C_th."""
        structure = truth["milling_structure"]
        sides = {"tool": _peaks_against_truth(result, "tool", structure, 0)}
        if structure.n_dof > POINT_DOF:
            sides["workpiece"] = _peaks_against_truth(result, "workpiece", structure, POINT_DOF)
        cond = {k: result["condition_number"][k] for k in ("median", "max", "planned_C_th")}
        return {**sides, "condition_number": cond, "warnings": result["warnings"],
                "headline": headline(
                    *(_side_text(side, peaks) for side, peaks in sides.items()),
                    f"condition number (Eq. 6.14) median {cond['median']:.1f}, max "
                    f"{cond['max']:.1f} (planned C_th {cond['planned_C_th']:.2f})")}

    @classmethod
    def details(cls, result: Mapping[str, Any]) -> list[str]:
        """Peaks, condition number and warnings of an SMFE analysis."""
        if "f_hz" not in result:
            return []
        lines = [f"  cuts {', '.join(result['cuts'])} at a_e "
                 f"{', '.join(f'{a:.1f}' for a in result['a_e_mm'])} mm, band "
                 f"{result['band_hz'][0]:g}-{result['band_hz'][1]:g} Hz, "
                 f"{result['n_averages']} averages"]
        for side, name in zip(SIDES, SIDE_NAMES):
            peaks = result[side]["peaks"]
            lines.append(f"  {name} peaks: " + ", ".join(
                f"{axis}{axis} {p['abs_m_N']:.3g} m/N at {p['f_hz']:.2f} Hz "
                f"(γ² ≥ {p['coherence_min']:.3f})" for axis, p in peaks.items()))
        cond = result["condition_number"]
        lines.append(f"  condition number (Eq. 6.14): median {cond['median']:.1f}, "
                     f"max {cond['max']:.1f}; planned C_th {cond['planned_C_th']:.1f}")
        lines += [f"  warning: {w}" for w in result["warnings"]]
        return lines
