"""`feedbench tune CONFIG`: the thesis's tuning procedure as one guided workflow (Ch. 4, issue 15).

    feedbench tune CONFIG                 measure, predict, report, write the tune result
    feedbench tune CONFIG --apply NAME    write candidate NAME's gains, measure again,
                                          print predicted beside measured
    feedbench tune CONFIG --rollback      write the gains the tune measured at back

Steps (a progress line each): the closed velocity-loop Bode at the present gains (family
``closed_loop_bode``, run through `api.open_bench` so it is recorded and catalogued) → the
open-loop mobility (Eq. 4.20); the tool-tip FRF with the shaker (family ``shaker_chirp``) at
the present gains and at each ``measure_gains`` setting; a pole–zero fit (Eq. 4.27); root loci
over K_p and T_i; the candidates (standard tuning, Eqs. 4.2, 4.8, 4.12; maximum damping of the
critical mode; the user's) and their predictions (`analysis.tuning`: critical mode, tool-tip
compliance by LFT approach #2, Eqs. 4.26 and 4.23, ZOA lobes, contour and tracking errors of
a circle and a corner, Table 4.3); an HTML report and a JSON tune result.

The config is a run config's ``[bench]`` and ``[limits]`` (with ``[limits.gains]``: the ranges
``--apply`` may write) and a ``[tune]`` table (`TUNE_SCHEMA`); everything is checked before
anything moves.
"""

from __future__ import annotations

import contextlib
import json
import signal
import threading
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import TransferFunction

from feedbench.analysis import rootlocus, tuning
from feedbench.analysis.contour import ContourSpec, Feedforward
from feedbench.analysis.polezero import PoleZeroFit, fit_pole_zero
from feedbench.analysis.servo import closed_velocity_loop, laplace
from feedbench.api import BenchSession, check_gains
from feedbench.bench import GAINS_SCHEMA, parse_run_config
from feedbench.config import ConfigError, Field, interval, non_negative, positive, read_toml
from feedbench.config import validate_table
from feedbench.daq.recording import printable_json
from feedbench.experiments.closed_loop_bode import ClosedLoopBode, bandwidth_and_reason
from feedbench.experiments.shaker_chirp import ShakerChirp
from feedbench.experiments.tool_tip import (
    COMPLIANCE_LABEL, LOBE_SPEEDS_RPM, TABLE_5_1, lobes_results,
)
from feedbench.models.axis import CascadeGains
from feedbench.models.milling import engagement_angles
from feedbench.report import render_html
from feedbench.units import MM_PER_MIN, kv_to_m_min_per_mm, kv_to_per_second
from feedbench.views.sections import (
    FrfSeries, Indicator, Plot, RunSection, Table, frf_figure, new_figure, png_of,
)

CONTOUR_SCHEMA = {
    "radius_mm": Field(float, 20.0, "circle radius (mm)", positive),
    "feed_mm_min": Field(float, 2000.0, "contour feed (mm/min)", positive),
    "acceleration_m_s2": Field(float, 1.0, "peak path acceleration (m/s²)", positive),
    "corner_leg_mm": Field(float, 20.0, "corner leg length (mm)", positive),
}
FEEDFORWARD_SCHEMA = {
    "K_ffv": Field(float, 1.0, "velocity feed-forward gain (–)", non_negative),
    "tau_BF_ms": Field(float, 1.0, "balancing filter time constant (ms), 0: none",
                       non_negative),
}
TUNE_SCHEMA = {
    "feed_mm_min": Field(float, 1500.0, "axis feed of every measurement (mm/min): friction "
                         "sliding, in its viscous regime", positive),
    "move_feed_mm_min": Field(float, 2500.0, "feed of the moves back to the start between "
                              "the measurements (mm/min)", positive),
    "bandwidth_Hz": Field(float, 60.0, "velocity bandwidth of the standard tuning (Hz), "
                          "Eqs. 4.2, 4.8, 4.12", positive),
    "search_Hz": Field(list, [15.0, 87.0], "bandwidths whose standard tunings bound the "
                       "maximum-damping search (Hz)", interval),
    "band_Hz": Field(list, [20.0, 120.0], "band of the critical structural mode (Hz)",
                     interval),
    "modes": Field(int, 1, "pole/zero pairs of the mobility fit, Eq. 4.27", positive),
    "position_delay_ms": Field(float, 0.5, "position-loop delay (ms): the zero-order hold of "
                               "its sampling, half its period", non_negative),
    "pade_order": Field(int, 2, "Padé order of the delays, Eq. 4.16 (at most 6: higher "
                        "orders are ill-conditioned)", positive),
    "seed": Field(int, 0, "seed of the maximum-damping search", non_negative),
    "result": Field(str, "", "tune result file (JSON); empty: <bench.output_dir>/tune.json"),
    "report": Field(str, "", "HTML report; empty: <bench.output_dir>/tune.html"),
    "bode": Field(dict, {}, "closed_loop_bode keys (velocity loop at feed_mm_min)"),
    "tool_tip": Field(dict, None, "shaker_chirp keys (at feed_mm_min); absent: no tool-tip "
                      "FRF"),
    "measure_gains": Field(dict, {}, "further gain sets by name ([bench.gains] keys) the "
                           "tool-tip FRF is measured at: approach #2 (Eq. 4.26) needs one"),
    "candidates": Field(dict, {}, "the user's gain sets by name ([bench.gains] keys, all "
                        "three)"),
    "contour": Field(dict, {}, "test contour (CONTOUR_SCHEMA)"),
    "feedforward": Field(dict, {}, "feed-forward of the contour simulation "
                         "(FEEDFORWARD_SCHEMA)"),
}
COMPUTED = ("present", "standard", "max_damping")
"""Candidate names the tune gives itself; the user's may not take them."""

TABLE_4_3 = {"standard (thesis)": (9.4, 2.42, 31.7, 12.1),
             "optimum damping (thesis)": (110.5, 23.8, 212.9, 75.5)}
"""Table 4.3 (ram-type machine): contour max, RMS, tracking max, RMS (µm)."""

Say = Callable[[str], None]


@dataclass(frozen=True)
class TuneConfig:
    """A checked tune config: the bench session's tables (`raw`), the ``[tune]`` table,
    the families' checked parameters, and where the result and the report go."""

    raw: dict[str, Any]
    tune: dict[str, Any]
    bode: dict[str, Any]
    tool_tip: dict[str, Any] | None
    measure_gains: tuple[dict[str, float], ...]
    candidates: dict[str, dict[str, float]]
    result_path: Path
    report_path: Path
    source: str = "config"


def _gain_table(table: Any, where: str, complete: bool) -> dict[str, float]:
    """A ``[bench.gains]``-style table (CNC units) checked; `complete`: all three given."""
    if not isinstance(table, Mapping):
        raise ConfigError(f"{where}: must be a table of K_p_Ns_m, T_i_ms, K_v_m_min_mm")
    gains = {k: v for k, v in validate_table(table, GAINS_SCHEMA, where).items() if v is not None}
    missing = [key for key in GAINS_SCHEMA if key not in gains]
    if complete and missing:
        raise ConfigError(f"{where}.{missing[0]}: required")
    if not gains:
        raise ConfigError(f"{where}: give at least one of {', '.join(GAINS_SCHEMA)}")
    return gains


def _family_settings(name: str, table: Mapping[str, Any], where: str,
                     session: Mapping[str, Any], **fixed: Any) -> dict[str, Any]:
    """A family's keys checked as `feedbench run` checks them (the family's `check`, its plan
    against the excitation limits), with the keys the tune sets itself (`fixed`: the loop,
    the feed) refused if given."""
    for key in ("type", *fixed):
        if key in table:
            raise ConfigError(f"{where}.{key}: set by the tune"
                              + (" (tune.feed_mm_min)" if "feed" in key else ""))
    try:
        return parse_run_config({**session, "experiment": {**table, "type": name, **fixed}}
                                ).experiment.settings
    except ConfigError as exc:  # the family names its fields experiment.<key>
        text = str(exc)
        raise ConfigError(where + text[len("experiment"):] if text.startswith("experiment.")
                          else text) from None


def check_position_delay(delay_ms: float, pade_order: int, band_top_Hz: float) -> None:
    """The Padé approximant of order n (Eq. 4.16) follows e^(-sτ) up to ωτ ≈ n: a position
    delay beyond that at the top of the band (a delay in µs typed as ms, a slow position
    loop) would rank the candidates on a wrong phase. ConfigError naming the field."""
    limit_ms = pade_order / (2 * np.pi * band_top_Hz) * 1e3
    if delay_ms > limit_ms:
        raise ConfigError(f"tune.position_delay_ms: {delay_ms:g} ms is more than a Padé order "
                          f"{pade_order} follows at {band_top_Hz:g} Hz (at most {limit_ms:.3g} "
                          "ms; raise tune.pade_order or lower tune.band_Hz)")


def parse_tune_config(raw: Mapping[str, Any], source: str = "config") -> TuneConfig:
    """Check a whole tune config; every error is a `ConfigError` naming the field."""
    session_tables = {key: raw[key] for key in ("bench", "limits") if key in raw}
    session = BenchSession(session_tables, source)  # checks [bench], [limits], [limits.gains]
    unknown = sorted(set(raw) - {"bench", "limits", "tune"})
    if unknown:
        raise ConfigError(f"{source}.{unknown[0]}: unknown table (bench, limits, tune)")
    if not isinstance(raw.get("tune", {}), Mapping):
        raise ConfigError("tune: must be a table")
    t = validate_table(raw.get("tune", {}), TUNE_SCHEMA, "tune")
    t["contour"] = validate_table(t["contour"], CONTOUR_SCHEMA, "tune.contour")
    t["feedforward"] = validate_table(t["feedforward"], FEEDFORWARD_SCHEMA, "tune.feedforward")
    check_contour(t["contour"])
    if t["pade_order"] > 6:
        raise ConfigError(f"tune.pade_order: at most 6 (got {t['pade_order']}): higher orders "
                          "are ill-conditioned")
    for key in ("band_Hz", "search_Hz"):
        if not 0 < t[key][0]:
            raise ConfigError(f"tune.{key}: must lie above 0 Hz")
    check_position_delay(t["position_delay_ms"], t["pade_order"], t["band_Hz"][1])
    for key in ("feed_mm_min", "move_feed_mm_min"):
        if t[key] * MM_PER_MIN > 0.95 * session.limits.velocity:
            raise ConfigError(f"tune.{key}: {t[key]:g} mm/min must stay below 95 % of "
                              "limits.velocity_mm_min")
    feed = t["feed_mm_min"]
    run_tables = {"bench": session.bench_config, "limits": session.limits_config}
    bode = _family_settings(ClosedLoopBode.name, t["bode"], "tune.bode", run_tables,
                            loop="velocity", feed_mm_min=feed)
    tool_tip = None if t["tool_tip"] is None else _family_settings(
        ShakerChirp.name, t["tool_tip"], "tune.tool_tip", run_tables, feeds_mm_min=[feed])
    measure = tuple(_gain_table(g, f"tune.measure_gains.{name}", False)
                    for name, g in t["measure_gains"].items())
    for name, gains in zip(t["measure_gains"], measure):
        check_gains(gains, session.gain_limits, f"tune.measure_gains.{name}")
    candidates = {}
    for name, table in t["candidates"].items():
        if name in COMPUTED:
            raise ConfigError(f"tune.candidates.{name}: a name the tune gives its own "
                              f"candidates ({', '.join(COMPUTED)})")
        candidates[name] = _gain_table(table, f"tune.candidates.{name}", True)
    out = Path(session.bench_config["output_dir"])
    paths = {key: Path(t[key] or out / f"tune.{suffix}")
             for key, suffix in (("result", "json"), ("report", "html"))}
    for key, path in paths.items():
        if path.is_dir():
            raise ConfigError(f"tune.{key}: {path} is a directory (give a file)")
    return TuneConfig(dict(raw), t, bode, tool_tip, measure, candidates, paths["result"],
                      paths["report"], source)


CONTOUR_MAX_S = 60.0
"""Longest test contour the tune simulates (s of path time, each candidate and contour)."""


def move_time(distance: float, speed: float, acceleration: float) -> float:
    """Duration (s) of a rest-to-rest move over `distance` (m) with sin² ramps of peak
    `acceleration` (m/s²) to `speed` (m/s), or the speed they reach (`contour.ramp_profile`)."""
    speed = min(speed, np.sqrt(2.0 * distance * acceleration / np.pi))
    return distance / speed + np.pi * speed / (2.0 * acceleration)


def check_contour(c: Mapping[str, float]) -> None:
    """The test contour (`CONTOUR_SCHEMA`) simulable: the circle's centripetal acceleration
    v²/R within the acceleration, circle and corner at most `CONTOUR_MAX_S` long."""
    speed, radius, a = c["feed_mm_min"] * MM_PER_MIN, c["radius_mm"] * 1e-3, c["acceleration_m_s2"]
    if speed**2 / radius > a:
        raise ConfigError(f"tune.contour.feed_mm_min: {c['feed_mm_min']:g} mm/min on the "
                          f"{c['radius_mm']:g} mm circle needs {speed**2 / radius:.3g} m/s² "
                          "centripetal, above tune.contour.acceleration_m_s2")
    circle = move_time(2 * np.pi * radius + np.pi * speed**2 / (2 * a), speed, a)
    corner = 2 * move_time(c["corner_leg_mm"] * 1e-3, speed, a)
    if max(circle, corner) > CONTOUR_MAX_S:
        raise ConfigError(f"tune.contour: the test contour lasts {max(circle, corner):.3g} s, "
                          f"more than {CONTOUR_MAX_S:g} s (raise feed_mm_min or "
                          "acceleration_m_s2, or shorten it)")


def load_tune_config(path: str | Path) -> TuneConfig:
    """Read and check a tune config file."""
    return parse_tune_config(read_toml(path), str(path))


def _session_config(config: TuneConfig) -> dict[str, Any]:
    return {key: config.raw[key] for key in ("bench", "limits") if key in config.raw}


# -- units ---------------------------------------------------------------------------------

def gains_si(gains: Mapping[str, float]) -> CascadeGains:
    """CNC-unit gains (K_p N·s/m, T_i ms, K_v (m/min)/mm) → `CascadeGains` in SI."""
    return CascadeGains(K_p=float(gains["K_p_Ns_m"]), T_i=float(gains["T_i_ms"]) * 1e-3,
                        K_v=kv_to_per_second(float(gains["K_v_m_min_mm"])))


def gains_cnc(gains: CascadeGains) -> dict[str, float]:
    """SI gains → the CNC's units: K_p (N·s/m), T_i (ms), K_v ((m/min)/mm)."""
    return {"K_p_Ns_m": float(gains.K_p), "T_i_ms": float(gains.T_i * 1e3),
            "K_v_m_min_mm": float(kv_to_m_min_per_mm(gains.K_v))}


def gains_text(gains: Mapping[str, float]) -> str:
    """``K_p 12968 N·s/m, T_i 5.31 ms, K_v 5.65 (m/min)/mm``."""
    return (f"K_p {gains['K_p_Ns_m']:.0f} N·s/m, T_i {gains['T_i_ms']:.2f} ms, "
            f"K_v {gains['K_v_m_min_mm']:.2f} (m/min)/mm")


def change_text(old: Mapping[str, float], new: Mapping[str, float]) -> str:
    """Old → new per gain in CNC units."""
    return (f"K_p {old['K_p_Ns_m']:.0f} → {new['K_p_Ns_m']:.0f} N·s/m, "
            f"T_i {old['T_i_ms']:.2f} → {new['T_i_ms']:.2f} ms, "
            f"K_v {old['K_v_m_min_mm']:.2f} → {new['K_v_m_min_mm']:.2f} (m/min)/mm")


# -- measurements --------------------------------------------------------------------------

class StepProgress:
    """Progress lines: one when a step starts, then at each quarter of its plan."""

    def __init__(self, say: Say, total: int) -> None:
        self.say, self.total, self.step, self._quarter = say, total, 0, -1

    def start(self, text: str) -> None:
        self.step += 1
        self._quarter = -1
        self.say(f"[{self.step}/{self.total}] {text}")

    def __call__(self, done: float, label: str) -> None:
        quarter = int(done * 4)
        if quarter != self._quarter and done < 1.0:
            self._quarter = quarter
            self.say(f"      {100 * done:3.0f} %  {label}")


def _polar(table: Mapping[str, Any], magnitude: str, phase: str) -> np.ndarray:
    return np.asarray(table[magnitude]) * np.exp(1j * np.asarray(table[phase]))


def measure_bode(session: BenchSession, config: TuneConfig, progress: StepProgress) -> dict:
    """The closed velocity-loop Bode at the drive's gains: run id, f (Hz), closed loop,
    open-loop mobility (Eq. 4.20, m/(N·s)) and −3 dB bandwidth (Hz)."""
    progress.start(f"closed velocity-loop Bode at {gains_text(session.drive.gains)}")
    run = session.run(ClosedLoopBode.name, progress=progress, **config.bode)
    frf = run.result["frf"]
    return {"run": run.id, "file": str(run.path), "f_hz": frf["f_hz"],
            "closed": {"abs": frf["abs"], "phase_rad": frf["phase_rad"]},
            "r_squared": frf["r_squared"],
            "mobility": {"abs": run.result["mobility"]["abs"],
                         "phase_rad": run.result["mobility"]["phase_rad"]},
            "bandwidth_hz": run.result["bandwidth_hz"],
            "bandwidth_note": run.result["bandwidth_note"]}


def measure_tip(session: BenchSession, config: TuneConfig, progress: StepProgress,
                home_mm: float) -> dict:
    """The tool-tip FRF with the shaker at the drive's gains (from `home_mm`): run id, gains
    (CNC units), f (Hz) and compliance x_tip/F_tip (m/N)."""
    gains = session.drive.gains
    progress.start(f"tool-tip FRF (shaker) at {gains_text(gains)}")
    session.drive.move_to(home_mm, config.tune["move_feed_mm_min"])
    run = session.run(ShakerChirp.name, progress=progress, **config.tool_tip)
    feed = run.result["feeds"][0]
    return {"run": run.id, "file": str(run.path), "gains": gains, "f_hz": feed["frf"]["f_hz"],
            "compliance": {"abs": feed["frf"]["compliance_abs"],
                           "phase_rad": feed["frf"]["compliance_phase_rad"]},
            "min_coherence": feed["min_coherence"]}


def measure(config: TuneConfig, say: Say) -> dict:
    """Every measurement of the tune at the present gains (and the tool-tip FRF at each
    ``measure_gains``, the present gains written back after them)."""
    settings = len(config.measure_gains) + 1 if config.tool_tip else 0
    progress = StepProgress(say, 1 + settings + 1)
    with BenchSession(_session_config(config)) as session:
        session.drive.enable()
        present = session.drive.gains
        if config.measure_gains:
            check_gains(present, session.gain_limits, "present gains")
        home = session.drive.read().position_mm
        bode = measure_bode(session, config, progress)
        tips = []
        try:
            for setting in ({},) + config.measure_gains if config.tool_tip else ():
                if setting:
                    session.drive.set_gains(**setting)
                tips.append(measure_tip(session, config, progress, home))
        finally:  # a failed or stopped measurement leaves the present gains too
            if config.measure_gains:
                with interrupts_deferred():
                    session.drive.set_gains(**present)
        session.drive.move_to(home, config.tune["move_feed_mm_min"])
    return {"present_gains": present, "bode": bode, "tool_tip": tips, "progress": progress}


# -- predictions ---------------------------------------------------------------------------

def cutting() -> tuning.CuttingParameters:
    """Table 5.1's cut for the lobes, y taken rigid (the lab flexure moves along the feed),
    as the tool-tip families draw them (`experiments.tool_tip.tool_tip_lobes`)."""
    start, stop = engagement_angles(TABLE_5_1.a_e, TABLE_5_1.D, TABLE_5_1.mode)
    return tuning.CuttingParameters(LOBE_SPEEDS_RPM, TABLE_5_1.Z, TABLE_5_1.K_tc,
                                    TABLE_5_1.K_rc / TABLE_5_1.K_tc, start, stop,
                                    y_compliance=0.0)


def setup_of(config: TuneConfig, measured: Mapping[str, Any], fit: PoleZeroFit
             ) -> tuning.TuningSetup:
    """What every candidate is judged by: the band, the contour, the feed-forward, the
    position-loop delay and the tool-tip measurements (approach #2 from ≥ 2 settings)."""
    t = config.tune
    c, ff = t["contour"], t["feedforward"]
    tip = None
    tips = measured["tool_tip"]
    if tips:
        f = np.asarray(tips[0]["f_hz"])
        tip = tuning.TipMeasurements(
            frequency=f, mot_mot=fit.model.mobility(f) / laplace(f),
            tip_closed=tuple(_polar(x["compliance"], "abs", "phase_rad") for x in tips)
            if len(tips) >= 2 else (),
            measured_gains=tuple(gains_si(x["gains"]) for x in tips) if len(tips) >= 2 else ())
    return tuning.TuningSetup(band=tuple(t["band_Hz"]), contour=ContourSpec(**c),
                              feedforward=Feedforward(ff["K_ffv"], ff["tau_BF_ms"] * 1e-3),
                              position_delay=t["position_delay_ms"] * 1e-3,
                              pade_order=t["pade_order"], tip=tip,
                              cutting=cutting() if tip is not None else None)


def fit_mobility(config: TuneConfig, bode: Mapping[str, Any]) -> PoleZeroFit:
    """Eq. (4.27) with `tune.modes` pole/zero pairs fitted to the measured open-loop mobility
    (Eq. 4.20, m/(N·s)) over the Bode's frequencies."""
    f = np.asarray(bode["f_hz"])
    return fit_pole_zero(f, _polar(bode["mobility"], "abs", "phase_rad"), config.tune["modes"])


def velocity_bandwidth(fit: PoleZeroFit, gains: CascadeGains, f: np.ndarray
                       ) -> tuple[float, str]:
    """−3 dB bandwidth (Hz) of the closed velocity loop the fit predicts, Eq. (4.21), at the
    measured Bode's frequencies `f` (Hz): the measured one's definition on the same grid
    (`closed_loop_bode.bandwidth_and_reason`); NaN with the reason where it is not defined."""
    closed = closed_velocity_loop(f, fit.model.mobility(f), gains.K_p, gains.T_i)
    return bandwidth_and_reason(f, closed)


MODE_BAND = 0.6
"""Half-width of the band, relative to the peak frequency, a tool-tip mode is fitted in: a
40 %-damped mode's flat top and both flanks (at ±40 % the fit of the maximum-damping tuning's
mode moved 2 % between prediction and measurement, at ±60 % 0.8 %)."""

MODE_FIT_MAX_ERROR = 0.05
"""Highest relative RMS error of the one-mode fit for its f_n and ζ to stand."""


@dataclass(frozen=True)
class ToolTipMode:
    """The mode under a compliance peak: f_n (Hz, undamped), ζ (–), the relative RMS error
    of the fit, and why it does not stand ('' when it does)."""

    f_n_hz: float
    zeta: float
    fit_error: float
    not_valid: str = ""


def _mode_basis(omega: np.ndarray, omega_n: float, zeta: float) -> np.ndarray:
    """Columns of the one-mode model at ω (rad/s): the mode 1/(ω_n² − ω² + 2jζω_nω) and a
    constant (the other modes' share, nearly flat across the band)."""
    return np.column_stack([1.0 / (omega_n**2 - omega**2 + 2j * zeta * omega_n * omega),
                            np.ones_like(omega)])


def fit_tool_tip_mode(f: np.ndarray, compliance: np.ndarray) -> ToolTipMode:
    """f_n and ζ of the mode under the compliance peak: H(ω) = A/(ω_n² − ω² + 2jζω_nω) + B
    (A, B complex, solved linearly for each ω_n, ζ; those by `scipy.optimize.least_squares`
    on the relative error) over ±`MODE_BAND` of the peak frequency.

    One fitted pole gives f_n and ζ together. Neither the peak frequency (f_n √(1 − 2ζ²) for
    one mode: 12 % below f_n at ζ 0.34) nor the −90° phase crossing (moved 8 Hz up by a
    second closed-loop mode at 88 Hz in the standard tuning's compliance) is f_n, and
    `analysis.modal.fit_modes` takes no pole above ζ 0.3 (a servo-damped mode here is 0.4)."""
    k = int(np.argmax(np.abs(compliance)))
    inside = np.abs(f - f[k]) <= MODE_BAND * f[k]
    omega, H = 2 * np.pi * np.asarray(f)[inside], np.asarray(compliance)[inside]

    def coefficients(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        basis = _mode_basis(omega, *p)
        return basis, np.linalg.lstsq(basis, H, rcond=None)[0]

    def residual(p: np.ndarray) -> np.ndarray:
        basis, c = coefficients(p)
        error = (basis @ c - H) / np.abs(H)
        return np.concatenate([error.real, error.imag])

    solution = least_squares(residual, [2 * np.pi * f[k], 0.2],
                             bounds=([0.5 * omega[0], 1e-4], [2.0 * omega[-1], 0.99]))
    omega_n, zeta = solution.x
    (A, B) = coefficients(solution.x)[1]
    error = float(np.sqrt(2.0 * np.mean(solution.fun**2)))
    f_n = float(omega_n / (2 * np.pi))
    reasons = (
        (error > MODE_FIT_MAX_ERROR, f"one mode does not describe the peak (fit error "
                                     f"{100 * error:.1f} %)"),
        (not omega[0] <= omega_n <= omega[-1], f"f_n {f_n:.1f} Hz outside the fitted band"),
        (abs(A) / (2 * zeta * omega_n**2) < abs(B), "no resonance under the peak (the mode "
                                                   "is smaller than the flat rest)"))
    return ToolTipMode(f_n, float(zeta), error, next((why for bad, why in reasons if bad), ""))


def compliance_mode(f: np.ndarray, compliance: np.ndarray) -> dict[str, Any]:
    """Peak |x/F| (µm/N) and its frequency (Hz); f_n (Hz) and ζ of the mode under the peak
    (`fit_tool_tip_mode`), with the fit's relative error and why it does not stand, if so."""
    k = int(np.argmax(np.abs(compliance)))
    mode = fit_tool_tip_mode(f, compliance)
    return {"peak_um_per_N": float(np.abs(compliance[k]) * 1e6), "peak_hz": float(f[k]),
            "f_n_hz": mode.f_n_hz, "zeta": mode.zeta, "mode_fit_error": mode.fit_error,
            "mode_not_valid": mode.not_valid}


def tip_curves(setup: tuning.TuningSetup, gains: CascadeGains) -> dict[str, np.ndarray]:
    """Predicted x_tip/F_tip (m/N) by each approach the measurements allow."""
    if setup.tip is None:
        return {}
    return tuning.predict_tip(setup.tip, gains, setup.position_delay)


def predict(config: TuneConfig, measured: Mapping[str, Any], say: Say) -> dict:
    """Fit, root loci, candidates and their predictions; the tune result (JSON-able) with the
    objects the report draws (under ``_draw``)."""
    progress = measured["progress"]
    progress.start("open-loop mobility (Eq. 4.20) → pole–zero fit (Eq. 4.27), root loci over "
                   "K_p and T_i, candidates, predictions")
    t = config.tune
    fit = fit_mobility(config, measured["bode"])
    mobility = fit.model.transfer_function(t["pade_order"])
    setup = setup_of(config, measured, fit)
    present = gains_si(measured["present_gains"])
    listed = {"present": present, **{k: gains_si(v) for k, v in config.candidates.items()}}
    candidates = tuning.candidate_gains(
        mobility, setup, fit.model.m_total, t["bandwidth_Hz"],
        tuning.bandwidth_bounds(fit.model.m_total, *t["search_Hz"]), listed, t["seed"])
    rows = tuning.predict_candidates(candidates, mobility, setup)
    recommendation = tuning.recommend(rows)
    limits = BenchSession(_session_config(config)).gain_limits
    result = {"config": config.source, "present_gains": measured["present_gains"],
              "runs": {"bode": measured["bode"]["run"],
                       "tool_tip": [x["run"] for x in measured["tool_tip"]]},
              "bode": measured["bode"], "tool_tip": measured["tool_tip"],
              "fit": {**asdict(fit.model), "rms_log_error": fit.rms_log_error},
              "candidates": {row.name: candidate_entry(row, fit, setup, limits,
                                                       np.asarray(measured["bode"]["f_hz"]))
                             for row in rows},
              "recommendation": asdict(recommendation),
              "approach": "settings (approach #2, Eqs. 4.26, 4.23)" if setup.tip and
              setup.tip.tip_closed else "none (approach #2 needs tune.measure_gains)"}
    result["_draw"] = {"fit": fit, "mobility": mobility, "setup": setup}
    say(f"      fit: m_total {fit.model.m_total:.2f} kg, delay {fit.model.delay * 1e3:.2f} ms, "
        f"RMS log error {fit.rms_log_error:.4f}; {len(rows)} candidates")
    return result


def candidate_entry(row: tuning.CandidatePrediction, fit: PoleZeroFit,
                    setup: tuning.TuningSetup, gain_limits: Mapping[str, Any],
                    f_bode: np.ndarray) -> dict:
    """One candidate of the tune result: gains (CNC units), whether ``--apply`` may write
    them, the critical mode, the tool-tip predictions (peak, lobes; the curve and its mode
    by the preferred approach), the motion errors and the velocity bandwidth (at the
    Bode's frequencies `f_bode`, Hz, or why it is not defined there)."""
    gains = gains_cnc(row.gains)
    try:
        check_gains(gains, gain_limits, f"candidate {row.name}")
        allowed = ""
    except ConfigError as exc:
        allowed = str(exc)
    entry = {"gains": gains, "outside_limits": allowed, "critical": asdict(row.critical),
             "tip": {k: asdict(v) for k, v in row.tip.items()},
             "motion": {k: asdict(v) for k, v in row.motion.items()},
             **dict(zip(("velocity_bandwidth_hz", "velocity_bandwidth_note"),
                        velocity_bandwidth(fit, row.gains, f_bode)))}
    curves = tip_curves(setup, row.gains)
    approach = next((a for a in tuning.PREFERRED_APPROACH if a in curves), None)
    if approach is not None:
        f = setup.tip.frequency
        entry["compliance"] = {"approach": approach, "f_hz": f.tolist(),
                               "abs": np.abs(curves[approach]).tolist(),
                               "phase_rad": np.angle(curves[approach]).tolist(),
                               **compliance_mode(f, curves[approach])}
    return entry


# -- the report ----------------------------------------------------------------------------

def tip_mode_text(tip: Mapping[str, Any] | None, separator: str = ", ") -> str:
    """``peak 2.16 µm/N at 34.4 Hz, f_n 37.4 Hz, ζ 34.7 %`` of a `compliance_mode` (the
    peak and the mode joined by `separator`), the reason after it where the mode fit does
    not stand; the terminal's numbers (`--apply`)."""
    if not tip:
        return "none (no tool-tip measurement)"
    text = (f"peak {tip['peak_um_per_N']:.2f} µm/N at {tip['peak_hz']:.1f} Hz{separator}f_n "
            f"{tip['f_n_hz']:.2f} Hz, ζ {100 * tip['zeta']:.2f} %")
    return text + (f" (not valid: {tip['mode_not_valid']})" if tip["mode_not_valid"] else "")


BANDWIDTH_ROW = "velocity-loop bandwidth (predicted)"
"""The report's quality row that says why a candidate's bandwidth is not defined."""


def bandwidth_text(candidate: Mapping[str, Any]) -> str:
    """A candidate's predicted velocity bandwidth (Hz) for the table, or that it is not
    defined (the reason: `bandwidth_notes`, in the quality row `BANDWIDTH_ROW`)."""
    if candidate["velocity_bandwidth_note"]:
        return "not defined (why: quality, above)"
    return f"{candidate['velocity_bandwidth_hz']:.1f}"


def bandwidth_notes(result: Mapping[str, Any]) -> list[Indicator]:
    """The quality row giving, per candidate, why its predicted bandwidth is not defined
    (none when every one is)."""
    notes = [f"{name}: not defined: {c['velocity_bandwidth_note']}"
             for name, c in result["candidates"].items() if c["velocity_bandwidth_note"]]
    return [Indicator(BANDWIDTH_ROW, "\n".join(notes))] if notes else []


def _fmt(value: float | None, digits: int = 2) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def candidate_table(result: Mapping[str, Any]) -> Table:
    """Candidate × (gains, critical mode f and ζ, predicted tool-tip peak and mode, min
    stable depth, contour and tracking max/RMS of circle and corner)."""
    rows = []
    for name, c in result["candidates"].items():
        g, crit = c["gains"], c["critical"]
        tip = c.get("compliance")
        depth = min_stable_depth(c)
        motion = "\n".join(f"{k}: {m['contour_max_um']:.1f} / {m['contour_rms_um']:.2f}"
                           for k, m in c["motion"].items())
        tracking = "\n".join(f"{k}: {m['tracking_max_um']:.1f} / {m['tracking_rms_um']:.2f}"
                             for k, m in c["motion"].items())
        rows.append((name, f"{g['K_p_Ns_m']:.0f}", f"{g['T_i_ms']:.2f}",
                     f"{g['K_v_m_min_mm']:.2f}", f"{crit['frequency_hz']:.1f}",
                     f"{100 * crit['damping']:.2f}" + ("" if crit["stable"] else " unstable"),
                     tip_mode_text(tip, "\n"), _fmt(depth, 3), motion, tracking,
                     bandwidth_text(c), c["outside_limits"] or "yes"))
    return Table("candidates: critical mode (root locus), predicted tool tip, motion errors",
                 ("candidate", "K_p (N·s/m)", "T_i (ms)", "K_v ((m/min)/mm)",
                  "critical mode f (Hz)", "critical mode ζ (%)",
                  "tool-tip compliance (predicted)", "min stable depth (mm)",
                  "contour max / RMS (µm)", "tracking max / RMS (µm)",
                  "velocity bandwidth (Hz)", "gains within limits"), tuple(rows))


def table_4_3(result: Mapping[str, Any]) -> Table:
    """Table 4.3 of the thesis beside the simulated standard and max-damping tunings."""
    rows = [(name, *(f"{v:g}" for v in values)) for name, values in TABLE_4_3.items()]
    ratio = {}
    for name in ("standard", "max_damping"):
        for contour, m in result["candidates"][name]["motion"].items():
            values = (m["contour_max_um"], m["contour_rms_um"], m["tracking_max_um"],
                      m["tracking_rms_um"])
            ratio.setdefault(contour, []).append(values)
            rows.append((f"{name}, {contour} (simulated)", *(f"{v:.2f}" for v in values)))
    rows.append(("optimum / standard (thesis)", *(
        f"{b / a:.1f}×" for a, b in zip(*TABLE_4_3.values()))))
    for contour, (standard, damped) in ratio.items():
        rows.append((f"max_damping / standard, {contour}", *(
            f"{b / a:.1f}×" for a, b in zip(standard, damped))))
    return Table("Table 4.3: the price of damping in contour error (thesis: ram-type machine)",
                 ("tuning", "contour max (µm)", "contour RMS (µm)", "tracking max (µm)",
                  "tracking RMS (µm)"), tuple(rows))


def bode_plots(result: Mapping[str, Any], fit: PoleZeroFit) -> list[Plot]:
    """The measured closed velocity loop beside the fit's (Eq. 4.21 at the present gains),
    and the open-loop mobility (Eq. 4.20) beside the pole–zero fit (Eq. 4.27)."""
    bode = result["bode"]
    f = np.asarray(bode["f_hz"])
    r2 = np.asarray(bode["r_squared"])
    dense = np.linspace(f[0], f[-1], 800)
    present = gains_si(result["present_gains"])
    model = fit.model.mobility(dense)
    no_quality = np.full(dense.size, np.nan)
    plots = []
    for title, measured, fitted, label in (
            ("closed velocity loop ẋ_mot/ẋ_ref: measured, and the fit by Eq. (4.21)",
             bode["closed"], closed_velocity_loop(dense, model, present.K_p, present.T_i),
             "|H| closed loop (–)"),
            ("open-loop mobility: measured by Eq. (4.20), and the pole–zero fit (Eq. 4.27)",
             bode["mobility"], model, "|G| ((m/s)/N)")):
        series = [FrfSeries("measured", f, np.asarray(measured["abs"]),
                            np.asarray(measured["phase_rad"]), r2),
                  FrfSeries("pole–zero fit", dense, np.abs(fitted), np.angle(fitted), no_quality)]
        figure = frf_figure(series, label, "R² of the sine fits", 0.99)
        for ax in figure.axes:
            for line in ax.get_lines()[:1]:
                line.set(marker="o", ms=3, lw=0)
        plots.append(Plot(title, png_of(figure)))
    return plots


def root_locus_plot(result: Mapping[str, Any], mobility: TransferFunction,
                    setup: tuning.TuningSetup) -> Plot:
    """Closed-cascade roots as K_p (0.1–3× present) and T_i (0.2–5× present) vary, the
    others at the present gains; each candidate's critical root marked."""
    present = gains_si(result["present_gains"])
    figure = new_figure(10.0, 4.5)
    axes = figure.subplots(1, 2, sharey=True)
    sweeps = (("K_p", present.K_p * np.geomspace(0.1, 3.0, 300)),
              ("T_i", present.T_i * np.geomspace(0.2, 5.0, 300)))
    top = 1.5 * setup.band[1]
    for ax, (name, values) in zip(axes, sweeps):
        gains = {"K_p": present.K_p, "T_i": present.T_i, "K_v": present.K_v, name: values}
        roots = rootlocus.polynomial_roots(rootlocus.cascade_characteristic(
            mobility, gains["K_p"], gains["T_i"], gains["K_v"], setup.position_delay,
            setup.pade_order)) / (2 * np.pi)
        shown = (np.abs(roots.imag) <= top) & (roots.real > -top) & (roots.imag >= 0)
        colour = np.broadcast_to(np.log10(values)[:, None], roots.shape)
        points = ax.scatter(roots.real[shown], roots.imag[shown], c=colour[shown], s=3,
                            cmap="viridis")
        figure.colorbar(points, ax=ax, label=f"log10 {name} ({'N·s/m' if name == 'K_p' else 's'})")
        for label, c in result["candidates"].items():
            crit = c["critical"]
            w, z = crit["frequency_hz"], crit["damping"]
            ax.plot(-z * w, w * np.sqrt(max(1 - z * z, 0.0)), "x", ms=8, mew=2, label=label)
        ax.axvline(0.0, color="k", lw=0.6)
        ax.set_xlabel("Re(s)/2π (Hz)")
        ax.set_title(f"{name} varied, other gains as present", fontsize=9)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("Im(s)/2π (Hz)")
    axes[1].legend(fontsize=8)
    return Plot("root locus of the P-PI cascade on the fitted mobility (Eq. 4.24, Padé delays "
                "Eq. 4.16); ×: each candidate's critical mode", png_of(figure))


def compliance_plot(result: Mapping[str, Any]) -> Plot:
    """Measured tool-tip compliance at each measured setting and the predicted one of each
    candidate (approach #2, Eqs. 4.26 and 4.23); the legend (peak and mode of each) under it."""
    figure = new_figure(9.0, 6.0)
    ax = figure.subplots()
    for tip in result["tool_tip"]:
        ax.semilogy(tip["f_hz"], tip["compliance"]["abs"], lw=2.5, alpha=0.35,
                    label=f"measured at K_p {tip['gains']['K_p_Ns_m']:.0f} N·s/m")
    for name, c in result["candidates"].items():
        if "compliance" in c:
            ax.semilogy(c["compliance"]["f_hz"], c["compliance"]["abs"], lw=1.0,
                        label=f"{name}: predicted, {tip_mode_text(c['compliance'])}")
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel(COMPLIANCE_LABEL)
    ax.grid(alpha=0.3, which="both")
    figure.legend(loc="outside lower center", fontsize=8)
    return Plot("tool-tip compliance x_tip/F_tip: measured (wide) and predicted per candidate",
                png_of(figure))


def contour_plot(result: Mapping[str, Any], mobility: TransferFunction,
                 setup: tuning.TuningSetup) -> Plot:
    """Contour error along the circle and the corner of each candidate, and the paths at the
    corner (time simulation of the cascade on the fitted mobility, `analysis.contour.follow`)."""
    figure = new_figure(12.0, 4.5)
    axes = figure.subplots(1, 3)
    spec = setup.contour
    titles = {"circle": f"circle R {spec.radius_mm:g} mm", "corner": f"90° corner, legs "
              f"{spec.corner_leg_mm:g} mm"}
    corner = (spec.corner_leg_mm * 1e-3, 0.0)
    drawn = {name: c for name, c in result["candidates"].items()  # a diverging loop: "inf"
             if all(np.isfinite(m["contour_max_um"]) for m in c["motion"].values())}
    for name, c in drawn.items():
        runs = tuning.contour_runs(mobility, gains_si(c["gains"]), setup)
        for ax, run in zip(axes, runs.values()):
            ax.plot(run.path.time, run.contour_error * 1e6, lw=0.9,
                    label=f"{name}: max {run.errors.contour_max_um:.1f} µm")
        axes[2].plot((runs["corner"].actual[:, 0] - corner[0]) * 1e6,
                     (runs["corner"].actual[:, 1] - corner[1]) * 1e6, lw=0.9)
    for ax, contour in zip(axes, ("circle", "corner")):
        ax.set_xlabel("time along the path (s)")
        ax.set_ylabel("contour error (µm)")
        ax.set_title(f"{titles[contour]} at {spec.feed_mm_min:g} mm/min", fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    span = 2.0 * max(c["motion"]["corner"]["contour_max_um"] for c in drawn.values())
    axes[2].plot([-10 * span, 0.0, 0.0], [0.0, 0.0, 10 * span], "k--", lw=0.8, label="reference")
    axes[2].set(xlim=(-span, span), ylim=(-span, span), aspect="equal",
                xlabel="x − corner (µm)", ylabel="y − corner (µm)")
    axes[2].set_title("paths at the corner", fontsize=9)
    axes[2].grid(alpha=0.3)
    axes[2].legend(fontsize=8)
    return Plot("test contours per candidate: contour error along the circle and the corner, "
                f"paths at the corner (K_ffv {setup.feedforward.K_ffv:g}, τ_BF "
                f"{setup.feedforward.tau_BF * 1e3:g} ms)", png_of(figure))


def min_stable_depth(candidate: Mapping[str, Any]) -> float | None:
    """A candidate's minimum stable depth of cut (mm) by the preferred tool-tip approach
    (`tuning.PREFERRED_APPROACH`); None without tool-tip predictions."""
    return next((candidate["tip"][a]["min_stable_depth_mm"] for a in tuning.PREFERRED_APPROACH
                 if a in candidate["tip"]), None)


def contour_max(candidate: Mapping[str, Any]) -> float | None:
    """A candidate's largest contour error (µm) over the test contours (what finishing is
    chosen by, `tuning.recommend`); None for an unstable one."""
    errors = [m["contour_max_um"] for m in candidate["motion"].values()]
    return None if None in errors else max(errors)


@dataclass(frozen=True)
class Trade:
    """One quantity a recommendation trades against the present gains, in plain words."""

    better: str
    worse: str
    quantity: str
    unit: str
    value: Callable[[Mapping[str, Any]], float | None]
    higher_is_better: bool


TRADES = (
    Trade("deeper chatter-free cuts", "shallower chatter-free cuts", "min stable depth", "mm",
          min_stable_depth, True),
    Trade("a better damped critical mode", "a less damped critical mode", "ζ", "%",
          lambda c: 100 * c["critical"]["damping"], True),
    Trade("a smaller contour error", "a larger contour error", "max", "µm", contour_max, False),
)
"""What roughing (depth, damping) and finishing (contour error) are chosen by, Table 4.3."""

CHOSEN_FOR = {"min stable depth": TRADES[0].better, "critical damping": TRADES[1].better,
              "contour error": TRADES[2].better}
"""`tuning.Recommendation`'s ``*_by`` (without its approach) → what it buys, in words."""


def _and(parts: Sequence[str]) -> str:
    """``a``, ``a and b``, ``a, b and c``."""
    return ", ".join(parts[:-1]) + (" and " if len(parts) > 1 else "") + parts[-1]


def trades(chosen: Mapping[str, Any], present: Mapping[str, Any]) -> tuple[list[str], list[str]]:
    """What `chosen` gains and what it gives up against `present` (`TRADES`, each with both
    values, e.g. ``a less damped critical mode (ζ 8.1 vs 17.9 %)``); equal ones left out."""
    gained, given = [], []
    for trade in TRADES:
        new, old = trade.value(chosen), trade.value(present)
        digits = 2 if trade.unit == "mm" else 1
        if new is None or old is None or f"{new:.{digits}f}" == f"{old:.{digits}f}":
            continue
        better = (new > old) == trade.higher_is_better
        (gained if better else given).append(
            f"{trade.better if better else trade.worse} ({trade.quantity} {new:.{digits}f} vs "
            f"{old:.{digits}f} {trade.unit})")
    return gained, given


def use_text(use: str, result: Mapping[str, Any]) -> str:
    """One sentence: the candidate for `use` (roughing, finishing), its gains and what it
    trades against the present gains."""
    name = result["recommendation"][use]
    by = CHOSEN_FOR[result["recommendation"][f"{use}_by"].split(" (")[0]]
    chosen = result["candidates"][name]
    if name == "present":
        return (f"For {use}, keep the present gains ({gains_text(chosen['gains'])}): no "
                f"candidate gives {by}.")
    gained, given = trades(chosen, result["candidates"]["present"])
    return (f"For {use}, apply {name} ({gains_text(chosen['gains'])}): against the present "
            f"gains it gives {_and(gained or [by])}"
            + (f", at the price of {_and(given)}." if given else ", giving up nothing."))


def commands_text(result: Mapping[str, Any]) -> str:
    """The commands that apply each recommended candidate and the one that rolls back."""
    config = result["config"]
    uses: dict[str, list[str]] = {}
    for use in ("roughing", "finishing"):
        uses.setdefault(result["recommendation"][use], []).append(use)
    uses.pop("present", None)
    width = max(map(len, uses), default=0)
    lines = [f"  feedbench tune {config} --apply {name:{width}s}   ({', '.join(names)})"
             + (f": refused, {refusal}" if (refusal := result["candidates"][name]
                                            ["outside_limits"]) else "")
             for name, names in uses.items()]
    back = f"Back to the present gains: feedbench tune {config} --rollback"
    return "\n".join(["To apply:", *lines, back] if lines else [back])


def recommendation_text(result: Mapping[str, Any]) -> str:
    """The recommendation for roughing and for finishing, a sentence each, then the commands."""
    return "\n".join([use_text("roughing", result), use_text("finishing", result),
                      commands_text(result)])


def damping_text(result: Mapping[str, Any]) -> str:
    """The maximum-damping tuning against the standard one: critical-mode ζ and the circle's
    contour error (thesis, ram-type machine: +44 % damping for ≈ 10× the contour error)."""
    damped, standard = (result["candidates"][k] for k in ("max_damping", "standard"))
    zeta = [c["critical"]["damping"] for c in (damped, standard)]
    contour = [c["motion"]["circle"]["contour_max_um"] for c in (damped, standard)]
    return (f"max_damping: ζ {100 * zeta[0]:.1f} % vs {100 * zeta[1]:.1f} % for standard "
            f"({100 * (zeta[0] / zeta[1] - 1):+.0f} %), circle contour error max "
            f"{contour[0]:.2f} vs {contour[1]:.2f} µm ({contour[0] / contour[1]:.1f}×); "
            "thesis: +44 %, ≈ 10×")


def tune_section(result: Mapping[str, Any]) -> RunSection:
    """The tune's report section: recommendation, candidate table, Table 4.3, and the plots."""
    draw = result["_draw"]
    fit, mobility, setup = draw["fit"], draw["mobility"], draw["setup"]
    section = RunSection("tune", "tune", "complete",
                         headline=" ".join(use_text(use, result)
                                           for use in ("roughing", "finishing")))
    section.quality += [
        Indicator("recommendation", recommendation_text(result)),
        Indicator("pole–zero fit (Eq. 4.27)", f"RMS complex-log error {fit.rms_log_error:.4f}",
                  fit.rms_log_error < 0.1),
        Indicator("tool-tip prediction", result["approach"], bool(setup.tip and
                                                                  setup.tip.tip_closed)),
        Indicator("price of damping (Table 4.3)", damping_text(result)),
        *bandwidth_notes(result),
    ]
    section.tables += [candidate_table(result), table_4_3(result), measurements_table(result)]
    section.plots += bode_plots(result, fit) + [root_locus_plot(result, mobility, setup)]
    if result["tool_tip"]:
        section.plots.append(compliance_plot(result))
        compliances = {name: (np.asarray(c["compliance"]["f_hz"]),
                              _polar(c["compliance"], "abs", "phase_rad"))
                       for name, c in result["candidates"].items() if "compliance" in c}
        if compliances:
            lobes_results(compliances, section)
            section.plots[-1] = replace(section.plots[-1], title="stability lobes of each "
                                        "candidate's predicted tool-tip compliance")
    section.plots.append(contour_plot(result, mobility, setup))
    return section


def measurements_table(result: Mapping[str, Any]) -> Table:
    """The recorded runs the tune measured (their own report: ``feedbench report RUN…``)."""
    bode = result["bode"]
    rows = [(bode["run"], "closed velocity-loop Bode", gains_text(result["present_gains"]),
             f"min R² {min(bode['r_squared']):.5f}", bode["file"])]
    rows += [(x["run"], "tool-tip FRF (shaker)", gains_text(x["gains"]),
              f"min coherence {x['min_coherence']:.4f}", x["file"]) for x in result["tool_tip"]]
    return Table("measurements (recorded and catalogued; feedbench report RUN… shows each)",
                 ("run", "what", "at gains", "quality", "file"), tuple(rows))


def write_outputs(config: TuneConfig, result: dict) -> None:
    """The HTML report (the tune's section) and the tune result."""
    config.report_path.parent.mkdir(parents=True, exist_ok=True)
    config.report_path.write_text(render_html([tune_section(result)], "feedbench tune"),
                                  encoding="utf-8")
    save_result(config.result_path, result)


def save_result(path: Path, result: Mapping[str, Any]) -> None:
    """The tune result as JSON (the report's drawing objects left out)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(printable_json({k: v for k, v in result.items() if k != "_draw"}) + "\n",
                    encoding="utf-8")


def read_result(path: Path) -> dict:
    """A tune result file; missing or not one: `ConfigError` naming it."""
    try:
        result = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: no tune result (run feedbench tune CONFIG first)") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: not a tune result ({exc})") from None
    if not isinstance(result, dict) or "candidates" not in result:
        raise ConfigError(f"{path}: not a tune result (no candidates)")
    return result


def run_tune(config: TuneConfig, say: Say) -> dict:
    """Measure, predict, write the report and the result; returns the result."""
    measured = measure(config, say)
    result = predict(config, measured, say)
    write_outputs(config, result)
    return result


# -- apply and roll back -------------------------------------------------------------------

@contextlib.contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Ctrl-C inside the block is held until the block ends, then raised: a gain write is
    never cut in half (the old gains stay unless the write completed)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    seen: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: seen.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if seen:
        raise KeyboardInterrupt


def write_gains(session: BenchSession, new: Mapping[str, float], say: Say) -> dict[str, float]:
    """Show old → new (CNC units), write `new` by SDO (within ``[limits.gains]``, Ctrl-C
    held until the write is complete); returns the old gains."""
    old = session.drive.gains
    say(f"gains: {change_text(old, new)}")
    with interrupts_deferred():
        session.drive.set_gains(**new)
    say("gains written by SDO")
    return old


COMPARED = {"peak_um_per_N": ("tool-tip peak |x/F|", "µm/N", 1.0, 3),
            "peak_hz": ("tool-tip peak at", "Hz", 1.0, 2),
            "f_n_hz": ("tool-tip mode f_n", "Hz", 1.0, 2),
            "zeta": ("tool-tip mode ζ", "%", 100.0, 2),
            "velocity_bandwidth_hz": ("velocity-loop bandwidth", "Hz", 1.0, 1)}
"""What `--apply` compares: key → (label, unit, display scale, decimals)."""

NOTES = {"f_n_hz": "mode_not_valid", "zeta": "mode_not_valid",
         "velocity_bandwidth_hz": "velocity_bandwidth_note"}
"""A compared quantity → the key of why it does not stand (the tool-tip mode's fit,
`fit_tool_tip_mode`; the bandwidth, `closed_loop_bode.bandwidth_and_reason`)."""


def compare(predicted: Mapping[str, Any], measured: Mapping[str, Any]) -> dict:
    """Predicted beside measured for each of `COMPARED` both have: value, relative error of
    the prediction (NaN where either is not defined) and why either does not stand, where
    one of them has such a reason (`NOTES`: ``predicted: why``, ``measured: why``)."""
    rows = {}
    for key in COMPARED:
        if key in predicted and key in measured:
            p, m = (np.nan if v is None else float(v) for v in (predicted[key], measured[key]))
            notes = [f"{side}: {values[NOTES[key]]}" for side, values in
                     (("predicted", predicted), ("measured", measured))
                     if values.get(NOTES.get(key, ""))]
            rows[key] = {"predicted": p, "measured": m,
                         "error": p / m - 1.0 if np.isfinite(p * m) and m else np.nan,
                         "not_valid": notes}
    return rows


def comparison_text(rows: Mapping[str, Mapping[str, Any]]) -> str:
    """The comparison as aligned lines; a value that is not defined says so in its column,
    and a value that does not stand gives its reason on the lines under it."""

    def number(value: float, width: int, form: str) -> str:
        return (f"{value:{form}}" if np.isfinite(value) else "not defined").rjust(width)

    lines = [f"{'':26s}{'predicted':>12s}{'measured':>12s}{'error':>9s}"]
    for key, row in rows.items():
        label, unit, scale, digits = COMPARED[key]
        error = 100 * row["error"]
        lines.append(f"{label:26s}{number(row['predicted'] * scale, 12, f'.{digits}f')}"
                     f"{number(row['measured'] * scale, 12, f'.{digits}f')}"
                     f"{f'{error:+.1f}%' if np.isfinite(error) else '':>9s}  {unit}")
        lines += [f"    not valid, {note}" for note in row["not_valid"]]
    return "\n".join(lines)


def remeasure(session: BenchSession, config: TuneConfig, progress: StepProgress) -> dict:
    """The tool-tip FRF (where the config has one: its peak, f_n, ζ by `compliance_mode`) and
    the closed velocity-loop Bode (its −3 dB bandwidth) at the gains the drive has now."""
    home = session.drive.read().position_mm
    measured: dict[str, Any] = {}
    if config.tool_tip:
        tip = measure_tip(session, config, progress, home)
        measured = {**compliance_mode(np.asarray(tip["f_hz"]),
                                      _polar(tip["compliance"], "abs", "phase_rad")),
                    "run_tool_tip": tip["run"]}
    session.drive.move_to(home, config.tune["move_feed_mm_min"])
    bode = measure_bode(session, config, progress)
    session.drive.move_to(home, config.tune["move_feed_mm_min"])
    return {**measured, "velocity_bandwidth_hz": bode["bandwidth_hz"],
            "velocity_bandwidth_note": bode["bandwidth_note"], "run_bode": bode["run"]}


def apply_candidate(config: TuneConfig, name: str, say: Say) -> dict:
    """Write candidate `name`'s gains, measure the tool-tip FRF and the closed velocity-loop
    Bode again, and compare with the prediction; the tune result gets ``applied``."""
    result = read_result(config.result_path)
    if name not in result["candidates"]:
        raise ConfigError(f"--apply: no candidate {name!r} in {config.result_path} (have: "
                          f"{', '.join(result['candidates'])})")
    candidate = result["candidates"][name]
    if not candidate["critical"]["stable"]:
        raise ConfigError(f"--apply {name}: the tune predicts an unstable closed loop "
                          f"(critical mode {candidate['critical']['frequency_hz']:.1f} Hz)")
    session = BenchSession(_session_config(config))
    check_gains(candidate["gains"], session.gain_limits, f"--apply {name}")
    progress = StepProgress(say, 2 + bool(config.tool_tip))
    with session:
        session.drive.enable()
        progress.start(f"write the gains of {name}")
        old = write_gains(session, candidate["gains"], say)
        applied = {"name": name, "old": old, "new": session.drive.gains, "measured": None}
        save_result(config.result_path, {**result, "applied": applied})
        measured = remeasure(session, config, progress)
    predicted = {key: value for key, value in candidate.get("compliance", {}).items()
                 if key not in ("f_hz", "abs", "phase_rad")}
    predicted.update({key: candidate[key] for key in ("velocity_bandwidth_hz",
                                                      "velocity_bandwidth_note")})
    applied["measured"] = measured
    applied["comparison"] = compare(predicted, measured)
    save_result(config.result_path, {**result, "applied": applied})
    say(comparison_text(applied["comparison"]))
    say(f"Back to the gains before: feedbench tune {config.source} --rollback")
    return applied


def rollback(config: TuneConfig, say: Say) -> dict[str, float]:
    """Write back the gains the tune measured at (the result's ``present_gains``)."""
    result = read_result(config.result_path)
    session = BenchSession(_session_config(config))
    check_gains(result["present_gains"], session.gain_limits, "--rollback")
    with session:
        write_gains(session, result["present_gains"], say)
        gains = session.drive.gains
    save_result(config.result_path, {**result, "applied": None})
    return gains
