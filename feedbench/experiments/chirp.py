"""Chirp injection into the drive (Ch. 3.5.1, Fig. 3.18).

A linear or logarithmic chirp is added to the force (torque) offset 0x60B2 or the velocity
offset 0x60B1 while the axis holds position or moves at a feed, repeated and averaged.
Moving keeps friction in its sliding regime so only its viscous part acts (Ch. 5.3.2);
a return move between repetitions keeps every sweep in one direction.
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any, Iterator, Mapping

import numpy as np

from feedbench.analysis.checks import (
    above_floor, averaged, measurable_velocity, peak_checks, slid,
)
from feedbench.analysis.frf import estimate_frf, findings_in_band
from feedbench.config import ConfigError, Field, non_negative, one_of, positive
from feedbench.engine.family import TRUTH_TITLE, Example, Experiment, percent_error
from feedbench.engine.plan import Plan, Segment, Window, recorded_windows
from feedbench.engine.preflight import check_amplitude_below_feed, check_feed
from feedbench.experiments.signals import chirp, integrate_velocity, move_to, ramp_to_feed
from feedbench.protocols.cia402 import CSP
from feedbench.units import MM_PER_MIN
from feedbench.views.frfs import MOTOR_FORCE, MOTOR_VELOCITY, ExchangeFrf, polar
from feedbench.views.panels import Curve, Panel, ResultView, phase_panel
from feedbench.views.sections import (
    MIN_COHERENCE, FrfSeries, Indicator, Plot, RunSection, Table, frf_figure, frf_warnings, png_of,
)

NAME = "chirp"
SIGNS = {"positive": 1.0, "negative": -1.0}

SCHEMA = {
    "type": Field(str, NAME, "experiment family"),
    "inject": Field(str, "force", "where the chirp is added: force or velocity offset",
                    one_of("force", "velocity")),
    "amplitude_N": Field(float, 20.0, "chirp amplitude for inject = force (N)", positive),
    "amplitude_mm_min": Field(float, 60.0, "chirp amplitude for inject = velocity (mm/min)",
                              positive),
    "f_start_Hz": Field(float, 10.0, "start frequency (Hz)", positive),
    "f_stop_Hz": Field(float, 200.0, "stop frequency (Hz)", positive),
    "duration_s": Field(float, 4.0, "duration of one sweep (s)", positive),
    "repetitions": Field(int, 4, "number of sweeps averaged", positive),
    "sweep": Field(str, "linear", "linear or logarithmic", one_of("linear", "logarithmic")),
    "feed_mm_min": Field(float, 500.0, "axis feed during the sweeps (mm/min); 0 holds position",
                         non_negative),
    "direction": Field(str, "positive", "direction of motion during every sweep",
                       one_of("positive", "negative")),
    "return_feed_mm_min": Field(float, 1500.0, "feed of the return move between sweeps (mm/min)",
                                positive),
    "settle_s": Field(float, 0.5, "time at feed before each sweep (s)", positive),
    "tail_s": Field(float, 1.0, "time at feed after each sweep, recorded with it so the "
                    "response rings down inside the record (s)", non_negative),
    "accel_m_s2": Field(float, 1.0, "acceleration of the ramps (m/s²)", positive),
    "band_low_Hz": Field(float, 20.0, "mobility band searched for f_t and f_r: low end (Hz)",
                         positive),
    "band_high_Hz": Field(float, 150.0, "mobility band searched for f_t and f_r: high end (Hz)",
                          positive),
}


def cross_checks(p: Any, cycle_s: float) -> None:
    """The checks across fields of typed parameters `p` for a bus cycle of `cycle_s` s."""
    nyquist = 0.5 / cycle_s
    if p.f_stop_Hz >= nyquist:
        raise ConfigError(
            f"experiment.f_stop_Hz: must be below the bus Nyquist frequency {nyquist:g} Hz "
            f"(got {p.f_stop_Hz:g})"
        )
    if p.f_start_Hz >= p.f_stop_Hz:
        raise ConfigError(
            f"experiment.f_start_Hz: must be below f_stop_Hz ({p.f_stop_Hz:g} Hz)"
        )
    mobility_band(p)
    check_feed("experiment.feed_mm_min", p.feed_mm_min, cycle_s)
    check_sweep_resolves(p)
    if p.inject == "velocity":
        check_amplitude_below_feed("experiment.amplitude_mm_min", p.amplitude_mm_min,
                                   p.feed_mm_min)


MIN_PERIODS = 5
"""Periods of the lowest frequency a sweep record must hold for it to be resolved."""


def check_sweep_resolves(p: Any) -> None:
    """A record (sweep and tail) holding `MIN_PERIODS` periods of ``f_start_Hz``, else a
    `ConfigError` naming ``experiment.duration_s``."""
    record_s = p.duration_s + p.tail_s
    if record_s * p.f_start_Hz < MIN_PERIODS:
        raise ConfigError(
            f"experiment.duration_s = {p.duration_s:g}: a {record_s:g} s record holds "
            f"{record_s * p.f_start_Hz:.2g} periods of f_start_Hz = {p.f_start_Hz:g} Hz; "
            f"it needs {MIN_PERIODS} to resolve the lowest frequency")


def mobility_band(p: Any) -> tuple[float, float]:
    """The band (Hz) searched for f_t and f_r, from typed params ``band_low_Hz`` and
    ``band_high_Hz``; a low end not below the high end is a `ConfigError`."""
    if p.band_low_Hz >= p.band_high_Hz:
        raise ConfigError(
            f"experiment.band_low_Hz: must be below band_high_Hz ({p.band_high_Hz:g} Hz)"
        )
    return p.band_low_Hz, p.band_high_Hz


def build_plan(p: Any, cycle_s: float) -> Plan:
    """Accelerate, settle, sweep, stop, return — `repetitions` times (`p` typed, checked).

    Every sweep runs in the same direction: direction-dependent friction (Fig. 5.11) makes
    the in-motion response direction-dependent, so alternating sweeps would not average.
    """
    if p.inject == "force":
        sweep = chirp(p.amplitude_N, p.f_start_Hz, p.f_stop_Hz, p.duration_s,
                      cycle_s, p.sweep)
    else:
        sweep = chirp(p.amplitude_mm_min * MM_PER_MIN, p.f_start_Hz, p.f_stop_Hz,
                      p.duration_s, cycle_s, p.sweep)
    sweep = np.concatenate([sweep, np.zeros(int(round(p.tail_s / cycle_s)))])
    n_settle = int(round(p.settle_s / cycle_s))
    feed = SIGNS[p.direction] * p.feed_mm_min * MM_PER_MIN
    up = ramp_to_feed(0.0, feed, p.accel_m_s2, cycle_s) if feed else np.zeros(0)
    down = ramp_to_feed(feed, 0.0, p.accel_m_s2, cycle_s) if feed else np.zeros(0)
    cruise = np.full(n_settle + len(sweep), feed)
    path = integrate_velocity(np.concatenate([up, cruise, down]), 0.0, cycle_s)
    back = move_to(float(path[-1]), 0.0, p.return_feed_mm_min * MM_PER_MIN,
                   p.accel_m_s2, cycle_s)
    a, b = len(up), len(up) + n_settle
    c = b + len(sweep)
    offset = {"force_offset" if p.inject == "force" else "velocity_offset": sweep}
    segments: list[Segment] = []
    for rep in range(p.repetitions):
        info = {"repetition": rep, "feed_mm_min": feed / MM_PER_MIN}
        segments += [
            Segment(f"accelerate sweep {rep + 1}", "move", path[:a], info=info),
            Segment(f"settle sweep {rep + 1}", "settle", path[a:b], info=info),
            Segment(f"sweep {rep + 1}", "excite", path[b:c], info=info, **offset),
            Segment(f"stop sweep {rep + 1}", "move", path[c:], info=info),
            Segment(f"return after sweep {rep + 1}", "move", back, info=info),
        ]
    return Plan(NAME, CSP, [s for s in segments if s.n_cycles], asdict(p), cycle_s)


def sweep_records(recording, windows: list[Window]) -> tuple[np.ndarray, np.ndarray]:
    """Motor force (N) and motor velocity (m/s) of every sweep with its ring-down tail,
    each made zero-mean, joined; all records have the length of the shortest."""
    n = min(w.stop - w.start for w in windows)
    force = recording.channels["force"]
    velocity = recording.channels["velocity"]
    f = [force[w.start:w.start + n] - force[w.start:w.start + n].mean() for w in windows]
    v = [velocity[w.start:w.start + n] - velocity[w.start:w.start + n].mean() for w in windows]
    return np.concatenate(f), np.concatenate(v)


def _refined_extremum(f: np.ndarray, magnitude_db: np.ndarray, k: int) -> float:
    """Frequency of the extremum at bin k, refined by a parabola through three bins (Hz).

    Only a local extremum is refined (its parabola's vertex lies within half a bin); a bin
    that is the band's end of a slope stays where it is, so the band-edge check sees it.
    """
    if k <= 0 or k >= len(f) - 1:
        return float(f[k])
    a, b, c = magnitude_db[k - 1 : k + 2]
    shift = 0.5 * (a - c) / (a - 2 * b + c) if (a - 2 * b + c) != 0 else 0.0
    return float(f[k] + shift * (f[1] - f[0])) if abs(shift) <= 0.5 else float(f[k])


def mobility_extrema(f: np.ndarray, H: np.ndarray, band: tuple[float, float]) -> tuple[float, float]:
    """Anti-resonance and resonance (Hz) of a servo mobility in `band`.

    The resonance f_r is the largest |H| in the band (Eq. 4.14); the anti-resonance f_t is
    the smallest |H| below it (the motor-locked tip mode, Eq. 4.13). A bin with |H| = 0 (a
    live estimate from the first, still silent samples) counts as the smallest magnitude
    there is, not as a log10(0) warning; an undefined |H| (NaN: no force recorded) as zero.
    A resonance on the band's first line leaves f_t there too (`analysis.checks.peak_checks`
    then fails the band-edge check).
    """
    db = 20 * np.log10(np.maximum(np.nan_to_num(np.abs(H)), np.finfo(float).tiny))
    inside = np.flatnonzero((f >= band[0]) & (f <= band[1]))
    k_r = inside[np.argmax(db[inside])]
    below = inside[inside < k_r]
    k_t = below[np.argmin(db[below])] if below.size else inside[0]
    return _refined_extremum(f, db, k_t), _refined_extremum(f, db, k_r)


def analyze_recording(recording) -> dict:
    """Servo mobility motor force → motor velocity (H1) averaged over the sweeps.

    Each sweep with its ring-down tail is one record (rectangular window, no overlap: the
    response starts and ends inside it, so nothing leaks); spectra are averaged over the
    records, and the coherence tells how well the repetitions agree. f_t and f_r are
    searched in the configured mobility band; warnings are about the swept band
    (f_start–f_stop) only. Checks (`sweep_checks`): the excitation beat the noise, the axis
    slid, at least two sweeps averaged (one has a coherence of 1 by construction), f_t and
    f_r are modes with a high coherence, not the band's edges.
    """
    p = Chirp.stored_params(recording)
    band = mobility_band(p)
    windows = recorded_windows(recording, "excite", at_least=1)
    force, velocity = sweep_records(recording, windows)
    fs = 1.0 / float(recording.metadata["cycle_s"])
    n = len(force) // len(windows)
    est = estimate_frf(force, velocity, fs, nperseg=n, overlap=0.0, window="boxcar")
    f_t, f_r = mobility_extrema(est.f, est.H1, band)
    inside = (est.f >= band[0]) & (est.f <= band[1])
    warnings, details = findings_in_band(est, (p.f_start_Hz, p.f_stop_Hz))
    checks = [*sweep_checks(recording, p, windows), averaged(len(windows), "sweeps"),
              *peak_checks([(name, f_x, est.f[inside], est.coherence[inside])
                            for name, f_x in (("f_t", f_t), ("f_r", f_r))], MIN_COHERENCE)]
    return {
        "experiment": NAME,
        "antiresonance_hz": f_t,
        "resonance_hz": f_r,
        "band_hz": list(band),
        "min_coherence": float(est.coherence[inside].min()),
        "n_sweeps": len(windows),
        "warnings": warnings,
        "warning_details": details,
        "checks": checks,
        "frf": {"f_hz": est.f[inside].tolist(), "H1_abs": np.abs(est.H1[inside]).tolist(),
                "H1_phase_rad": np.angle(est.H1[inside]).tolist(),
                "coherence": est.coherence[inside].tolist()},
    }


def sweep_checks(recording, p: Any, windows: list[Window]) -> list[dict]:
    """The excitation reached the axis: the motor force of the sweeps not constant (a
    channel read), their motor velocity above the measurable one (the axis moved under the
    excitation), and at a feed the axis slid through every sweep (`slid`)."""
    force, velocity = (np.concatenate([recording.channels[c][w.start:w.stop] for w in windows])
                       for c in ("force", "velocity"))
    slowest = measurable_velocity(float(recording.metadata["cycle_s"]))
    checks = [above_floor("motor force", force, 0.0, "N", "no force was recorded"),
              above_floor("motor velocity", velocity, slowest, "m/s",
                          "the axis did not move under the excitation (stuck in its stiction "
                          "band, or the amplitude too small)")]
    if p.feed_mm_min:
        checks.append(slid(velocity, SIGNS[p.direction] * p.feed_mm_min * MM_PER_MIN,
                           slowest))
    return checks


def band_text(result: Mapping[str, Any]) -> str:
    """``20-150 Hz``: the band the result's extrema and coherence are taken in."""
    low, high = result["band_hz"]
    return f"{low:g}-{high:g} Hz"


def extrema_text(result: Mapping[str, Any], truth: Mapping[str, Any], prefix: str = "") -> str:
    """f_t and f_r of a mobility result beside the model's (Eqs. 4.13, 4.14)."""
    return (f"{prefix}f_t {result['antiresonance_hz']:.2f} Hz (Eq. 4.13: {truth['f_t_hz']:.2f}), "
            f"f_r {result['resonance_hz']:.2f} Hz (Eq. 4.14: {truth['f_r_hz']:.2f})")


class Chirp(Experiment):
    """Chirp injection into the drive: the servo mobility, f_t and f_r (Ch. 3.5.1)."""

    name = NAME
    schema = SCHEMA
    has_frfs = True
    title = "servo mobility of the sweeps so far"
    examples = (Example(NAME, rank=20, required=True),)  # --quick: runs as configured
    live_kinds = ("excite",)
    demo_key = "servo_mobility"

    @classmethod
    def demo_lines(cls, m: Mapping[str, Any]) -> list[str]:
        """The demo's servo mobility: f_t and f_r against the model's, the coherence."""
        return ["Servo mobility (motor force -> motor velocity, H1):",
                f"  anti-resonance {m['antiresonance_hz']:6.2f} Hz   "
                f"(f_t, Eq. 4.13: {m['truth_f_t_hz']:.2f} Hz)",
                f"  resonance      {m['resonance_hz']:6.2f} Hz   "
                f"(f_r, Eq. 4.14: {m['truth_f_r_hz']:.2f} Hz)",
                f"  min coherence {band_text(m)}: {m['min_coherence']:.4f}"]

    @classmethod
    def check(cls, params: Mapping[str, Any], cycle_s: float) -> dict:
        p = super().check(params, cycle_s)
        cross_checks(cls.typed(p), cycle_s)
        return p

    def plan(self) -> Plan:
        return build_plan(self.params, self.cycle_s)

    @classmethod
    def analyze(cls, recording, final: bool = True) -> dict:
        return analyze_recording(recording)

    @classmethod
    def report(cls, recording, result: Mapping[str, Any], section: RunSection) -> None:
        """Servo mobility Bode plot (|H1|, phase, coherence), anti-resonance f_t and
        resonance f_r marked."""
        frf = result["frf"]
        series = [FrfSeries("H1 motor velocity / motor force", np.array(frf["f_hz"]),
                            np.array(frf["H1_abs"]), np.array(frf["H1_phase_rad"]),
                            np.array(frf["coherence"]))]
        marks = [(f"f_t {result['antiresonance_hz']:.1f} Hz", result["antiresonance_hz"]),
                 (f"f_r {result['resonance_hz']:.1f} Hz", result["resonance_hz"])]
        section.plots.append(Plot("servo mobility (H1, Welch): magnitude, phase, coherence",
                                  png_of(frf_figure(series, "|H| ((m/s)/N)", marks=marks))))
        min_coherence = min(frf["coherence"]) if frf["coherence"] else float("nan")
        section.tables.append(Table("servo mobility", ("quantity", "value"), (
            ("anti-resonance f_t (Eq. 4.13)", f"{result['antiresonance_hz']:.2f} Hz"),
            ("resonance f_r (Eq. 4.14)", f"{result['resonance_hz']:.2f} Hz"),
            ("sweeps averaged", str(result["n_sweeps"])),
        )))
        section.quality.append(Indicator(f"min coherence in {band_text(result)}",
                                         f"{min_coherence:.4f}", min_coherence >= MIN_COHERENCE))
        section.quality.append(frf_warnings(result["warnings"], result["warning_details"]))

    @classmethod
    def headline(cls, result: Mapping[str, Any]) -> str:
        """f_t and f_r of the servo mobility."""
        return f"f_t {result['antiresonance_hz']:.1f} Hz, f_r {result['resonance_hz']:.1f} Hz"

    @classmethod
    def live_view(cls, result: Mapping[str, Any]) -> ResultView:
        """|H1| (m/s)/N, its phase and coherence of the sweeps so far, f_t and f_r in the
        summary."""
        frf = result["frf"]
        f = np.asarray(frf["f_hz"])
        panels = (
            Panel("|H1| motor velocity / motor force", "frequency (Hz)", "|H| ((m/s)/N)",
                  (Curve("H1", f, np.asarray(frf["H1_abs"])),), log_y=True),
            phase_panel({"H1": (f, frf["H1_phase_rad"])}),
            Panel("coherence", "frequency (Hz)", "γ²",
                  (Curve("coherence", f, np.asarray(frf["coherence"])),), y_range=(0.0, 1.05)),
        )
        n = result["n_sweeps"]
        summary = (f"{n} sweep{'s' if n > 1 else ''}; f_t {result['antiresonance_hz']:.1f} Hz, "
                   f"f_r {result['resonance_hz']:.1f} Hz, min coherence "
                   f"{result['min_coherence']:.3f}")
        return ResultView(cls.title, panels, summary)

    @classmethod
    def frfs(cls, result: Mapping[str, Any], recording) -> Iterator[ExchangeFrf]:
        """The servo mobility H1, motor velocity over motor force."""
        frf = result["frf"]
        yield ExchangeFrf("chirp: servo mobility H1", f"{result['n_sweeps']} sweeps",
                          np.asarray(frf["f_hz"]), polar(frf, "H1_abs", "H1_phase_rad"),
                          MOTOR_VELOCITY, MOTOR_FORCE, np.asarray(frf["coherence"]))

    @classmethod
    def summary(cls, result: Mapping[str, Any], truth: Mapping[str, Any]) -> dict:
        """The servo mobility's anti-resonance and resonance against Eqs. (4.13, 4.14)."""
        values = {key: result[key] for key in ("antiresonance_hz", "resonance_hz",
                                               "min_coherence", "band_hz", "warnings")}
        return {**values, "truth_f_t_hz": truth["f_t_hz"], "truth_f_r_hz": truth["f_r_hz"],
                "headline": f"{extrema_text(result, truth)}; min coherence "
                            f"{result['min_coherence']:.4f}"}

    @classmethod
    def truth_table(cls, result: Mapping[str, Any], truth: Mapping[str, Any]) -> Table:
        """f_t and f_r of the servo mobility beside the model's (Eqs. 4.13, 4.14)."""
        return Table(TRUTH_TITLE, ("quantity", "identified", "true", "error"), tuple(
            (name, f"{result[key]:.2f} Hz", f"{truth[true]:.2f} Hz",
             f"{percent_error(result[key], truth[true]):+.2f} %")
            for name, key, true in (("anti-resonance f_t (Eq. 4.13)", "antiresonance_hz", "f_t_hz"),
                                    ("resonance f_r (Eq. 4.14)", "resonance_hz", "f_r_hz"))))

    @classmethod
    def details(cls, result: Mapping[str, Any]) -> list[str]:
        """f_t and f_r to 0.01 Hz, the lowest coherence in the band, the FRF warnings."""
        return ([f"  anti-resonance {result['antiresonance_hz']:.2f} Hz, "
                 f"resonance {result['resonance_hz']:.2f} Hz",
                 f"  min coherence {band_text(result)} {result['min_coherence']:.4f}"]
                + [f"  warning: {w}" for w in result["warnings"]])
