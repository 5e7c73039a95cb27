"""Sine-stream (stepped sine) at the tool tip, Ch. 5.5.3 (Figs. 5.20–5.22).

An inertial actuator (or the shaker) on the tool tip holds a sine at each frequency from
`f_start_Hz` to `f_stop_Hz` in steps of `f_step_Hz` for `settle_cycles` + `cycles_per_step`
periods, phase-continuous, at each force amplitude and each axis feed. The force amplitude is
held per frequency where the actuator allows: the command is the wanted force over the
actuator's force transfer (its datasheet values in this config, `models.exciters`), capped by
its coil force and stroke; such a step is marked `limited`.

Analysis: per step a sine at the known frequency is fitted to the force and the tool-tip
acceleration after the settle cycles (`analysis.sinefit`); the FRF point is the ratio of the
phasors, R² the quality indicator the thesis uses. Quality gate: a repetition with
R² < `r_squared_min`, an overloaded DAQ channel or lost samples is not used; the step's FRF
is the mean of its good repetitions (`repeats_per_step`), and a step with none is flagged and
left out, never silently used. The measured force amplitude is checked against the wanted one.
"""

from __future__ import annotations

from typing import Any, Iterator, Mapping

import numpy as np

from feedbench.analysis.checks import check, peak_checks
from feedbench.analysis.frf import accelerance_to_receptance
from feedbench.analysis.sinefit import stepped_sine_frf
from feedbench.config import ConfigError, Field, one_of, positive
from feedbench.engine.family import Example, Experiment, demo_examples, headline
from feedbench.engine.preflight import check_feeds
from feedbench.engine.plan import Plan, Window, recorded_windows
from feedbench.experiments.tool_tip import (
    COMPLIANCE_LABEL, FEEDS_FIELD, FORCE_CHANNELS, MOTION_SCHEMA, RESPONSE_CHANNEL,
    TIP_ACCELERATION, ExcitationWindow, daq_needs, feed_label, feed_text,
    overloaded, plan_over_feeds, records_check, tip_force, window_samples,
)
from feedbench.experiments.shaker_chirp import ShakerChirp
from feedbench.models.exciters import ExciterDynamics, InertialActuator, shaker
from feedbench.protocols.cia402 import CSP
from feedbench.views.frfs import ExchangeFrf, polar
from feedbench.views.panels import ResultView, point_frf_panels
from feedbench.views.sections import (
    FrfSeries, Indicator, Plot, RunSection, Table, frf_figure, png_of,
)

NAME = "sine_stream"

SCHEMA = {
    "type": Field(str, NAME, "experiment family"),
    "exciter": Field(str, "actuator", "inertial actuator (Fig. 5.20) or shaker",
                     one_of("actuator", "shaker")),
    "feeds_mm_min": Field(list, [0.0, 100.0, 1000.0], FEEDS_FIELD.doc, FEEDS_FIELD.check),
    "amplitudes_N": Field(list, [10.0, 20.0, 40.0], "force amplitudes (N)", positive),
    "f_start_Hz": Field(float, 20.0, "first frequency (Hz)", positive),
    "f_stop_Hz": Field(float, 80.0, "last frequency (Hz)", positive),
    "f_step_Hz": Field(float, 0.25, "frequency step (Hz)", positive),
    "cycles_per_step": Field(int, 5, "periods fitted per step", positive),
    "settle_cycles": Field(int, 5, "periods before the fit at each step", positive),
    "repeats_per_step": Field(int, 1, "repetitions of each step (good ones are averaged)",
                              positive),
    "r_squared_min": Field(float, 0.99, "quality gate: least R² of force and response fits",
                           positive),
    "amplitude_tolerance": Field(float, 0.05, "force amplitude held within this share",
                                 positive),
    "actuator_mass_kg": Field(float, 2.0, "actuator datasheet: reaction mass (kg)", positive),
    "actuator_f_Hz": Field(float, 15.0, "actuator datasheet: suspension frequency (Hz)",
                           positive),
    "actuator_zeta": Field(float, 0.3, "actuator datasheet: suspension damping", positive),
    "actuator_limit_N": Field(float, 300.0, "actuator datasheet: coil force (N)", positive),
    "actuator_stroke_mm": Field(float, 5.0, "actuator datasheet: stroke ± (mm)", positive),
    "shaker_corner_Hz": Field(float, 160.0, "shaker datasheet: force fall-off corner (Hz)",
                              positive),
    "shaker_limit_N": Field(float, 500.0, "shaker datasheet: largest command (N)", positive),
    **MOTION_SCHEMA,
}


def frequencies(p: Any) -> np.ndarray:
    """The step frequencies (Hz), start to stop inclusive."""
    count = int(np.floor((p.f_stop_Hz - p.f_start_Hz) / p.f_step_Hz + 1e-9)) + 1
    return p.f_start_Hz + p.f_step_Hz * np.arange(count)


def exciter_model(p: Any) -> tuple[ExciterDynamics, Any]:
    """The exciter's force transfer and its force capability f → largest amplitude (N)."""
    if p.exciter == "shaker":
        dynamics = shaker(p.shaker_corner_Hz, p.shaker_limit_N)
        return dynamics, lambda f: p.shaker_limit_N * np.abs(dynamics.response(f))
    actuator = InertialActuator(p.actuator_mass_kg, p.actuator_f_Hz, p.actuator_zeta,
                                p.actuator_limit_N, p.actuator_stroke_mm * 1e-3)
    return actuator.dynamics(), actuator.max_force


def fade_in(n_cycles: int, n_total: int) -> np.ndarray:
    """Gain 0 → 1 over the first n_cycles of n_total (raised cosine), then 1: the stream
    starts without a force step, which would ring the lightly damped idle structure."""
    gain = np.ones(n_total)
    gain[:n_cycles] = 0.5 * (1.0 - np.cos(np.pi * np.arange(1, n_cycles + 1) / n_cycles))
    return gain


def step_windows(p: Any, amplitude: float, cycle_s: float) -> list[ExcitationWindow]:
    """The phase-continuous stream at one force amplitude: a window per step (and repeat);
    the first step fades in over its settle periods."""
    dynamics, capability = exciter_model(p)
    windows, phase = [], 0.0
    periods = p.settle_cycles + p.cycles_per_step
    for i, f in enumerate(frequencies(p)):
        force = min(amplitude, float(capability(f)))
        command_amplitude = force / float(np.abs(dynamics.response(f)))
        n = int(round(periods / (f * cycle_s)))
        for repeat in range(p.repeats_per_step):
            t = np.arange(1, n + 1) * cycle_s
            command = command_amplitude * np.sin(phase + 2.0 * np.pi * f * t)
            if not windows:
                command *= fade_in(int(round(p.settle_cycles / (f * cycle_s))), n)
            phase += 2.0 * np.pi * f * n * cycle_s
            info = {"step": i, "repeat": repeat, "frequency_hz": float(f),
                    "amplitude_N": amplitude, "held_N": force, "limited": force < amplitude}
            windows.append(ExcitationWindow(f"{f:g} Hz, {amplitude:g} N", command, info))
    return windows


def fit_step(recording, window: Window, force_channel: str, fs: float, settle_cycles: int,
             r_squared_min: float) -> dict:
    """Sine fits of one recorded step: FRF point (m/s² per N), R², force amplitude, verdict."""
    channels = (force_channel, RESPONSE_CHANNEL)
    samples, lost = window_samples(recording, window, channels)
    f = float(window.info["frequency_hz"])
    fit = stepped_sine_frf(samples[0], samples[1], fs, [(f, 0, samples.shape[1])],
                           settle_cycles)
    reasons = list(lost)
    if overloaded(samples, channels):
        reasons.append("overloaded channel")
    if fit.r_squared[0] < r_squared_min:
        reasons.append(f"R² {fit.r_squared[0]:.4f} < {r_squared_min}")
    return {"H": complex(fit.H[0]), "r_squared": float(fit.r_squared[0]),
            "force_amplitude_N": float(fit.force_amplitude[0]), "drift": float(fit.drift[0]),
            "reasons": reasons}


def fitted_steps(recording, force_channel: str, fs: float, settle_cycles: int,
                 r_squared_min: float) -> tuple[list[tuple[dict, dict]], list[str]]:
    """Each recorded step's fit (`fit_step`) with its info, and notes: in a run that did not
    complete, the last step, cut by the stop too short to fit, is left out and named."""
    windows = recorded_windows(recording, "excite")
    fits, notes = [], []
    for k, window in enumerate(windows):
        try:
            fits.append((fit_step(recording, window, force_channel, fs, settle_cycles,
                                  r_squared_min), window.info))
        except ValueError:
            if recording.status == "complete" or k < len(windows) - 1:
                raise
            notes.append(f"{window.label}: cut short by the stop after "
                         f"{window.stop - window.start} cycle(s), left out")
    return fits, notes


def _combine_repeats(fits: list[dict], info: dict, tolerance: float) -> dict:
    """One step's result from its repetitions: the mean FRF of the good ones, or flagged
    (`H_fitted`, the mean of every repetition, shows a flagged step; it is never used)."""
    good = [fit for fit in fits if not fit["reasons"]]
    step = {"frequency_hz": info["frequency_hz"], "limited": bool(info["limited"]),
            "held_N": info["held_N"], "repeats": len(fits), "good_repeats": len(good),
            "r_squared": min(fit["r_squared"] for fit in fits),
            "H_fitted": complex(np.mean([fit["H"] for fit in fits])),
            "flagged": not good, "reasons": sorted({r for fit in fits for r in fit["reasons"]})}
    if good:
        H = np.mean([fit["H"] for fit in good])
        force = float(np.mean([fit["force_amplitude_N"] for fit in good]))
        step.update(H=H, force_amplitude_N=force,
                    amplitude_held=abs(force - info["held_N"]) <= tolerance * info["held_N"])
    return step


def _stream_summary(feed: float, amplitude: float, steps: list[dict]) -> dict:
    """FRF arrays of one (feed, amplitude) stream from its used steps, and its quality."""
    used = [s for s in steps if not s["flagged"]]
    f = np.array([s["frequency_hz"] for s in used])
    H = np.array([s["H"] for s in used])
    compliance = accelerance_to_receptance(f, H) if used else np.zeros(0, complex)
    return {
        "feed_mm_min": feed, "amplitude_N": amplitude,
        "steps": len(steps), "steps_used": len(used),
        "flagged": [_flagged_point(s) for s in steps if s["flagged"]],
        "limited_hz": [s["frequency_hz"] for s in steps if s["limited"]],
        "not_held_hz": [s["frequency_hz"] for s in used if not s["amplitude_held"]],
        "min_r_squared": min((s["r_squared"] for s in used), default=float("nan")),
        "peak_hz": float(f[np.argmax(np.abs(compliance))]) if used else float("nan"),
        "frf": {"f_hz": f.tolist(), "accelerance_abs": np.abs(H).tolist(),
                "accelerance_phase_rad": np.angle(H).tolist(),
                "compliance_abs": np.abs(compliance).tolist(),
                "compliance_phase_rad": np.angle(compliance).tolist(),
                "r_squared": [s["r_squared"] for s in used],
                "force_amplitude_N": [s["force_amplitude_N"] for s in used]},
    }


def _flagged_point(step: dict) -> dict:
    """A flagged step: why, its least R² and the compliance (m/N) its fits gave, to show."""
    compliance = complex(accelerance_to_receptance(np.array([step["frequency_hz"]]),
                                                   np.array([step["H_fitted"]]))[0])
    return {"frequency_hz": step["frequency_hz"], "reasons": step["reasons"],
            "r_squared": step["r_squared"], "compliance_abs": abs(compliance),
            "compliance_phase_rad": float(np.angle(compliance))}


def amplitude_spread(streams: list[dict]) -> float:
    """Largest spread of |compliance| between the amplitudes of one feed, relative to its
    peak, over the frequencies all of them kept (0 for one amplitude): the linearity of
    Fig. 5.22."""
    common = set.intersection(*(set(s["frf"]["f_hz"]) for s in streams)) if streams else set()
    if len(streams) < 2 or not common:
        return 0.0
    keep = sorted(common)
    table = np.array([[dict(zip(s["frf"]["f_hz"], s["frf"]["compliance_abs"]))[f] for f in keep]
                      for s in streams])
    return float(np.max(table.max(axis=0) - table.min(axis=0)) / table.max())


def spread_text(result: Mapping[str, Any]) -> str:
    """``1000 mm/min: 2.1 %``: the spread between amplitudes (`amplitude_spread`) of each
    feed measured at two or more force amplitudes; with one there is no spread to give."""
    feeds = [f"{x['feed_mm_min']:g}" for x in result["streams"]]
    return ", ".join(f"{feed} mm/min: {100 * value:.1f} %"
                     for feed, value in result["amplitude_spread"].items()
                     if feeds.count(feed) > 1) or "not measured: one force amplitude per feed"


def stream_label(stream: Mapping[str, Any]) -> str:
    """``1000 mm/min, 20 N``: one stream's feed and force amplitude."""
    return f"{feed_label(stream['feed_mm_min'])}, {stream['amplitude_N']:g} N"


def stream_points(stream: Mapping[str, Any]) -> list[tuple[float, complex, float]]:
    """(f Hz, compliance m/N, R²) of every step of a stream, used and flagged, by frequency."""
    frf = stream["frf"]
    used = zip(frf["f_hz"], np.multiply(frf["compliance_abs"],
                                        np.exp(1j * np.asarray(frf["compliance_phase_rad"]))),
               frf["r_squared"])
    flagged = ((x["frequency_hz"], x["compliance_abs"] * np.exp(1j * x["compliance_phase_rad"]),
                x["r_squared"]) for x in stream["flagged"])
    return sorted((float(f), complex(H), float(r2)) for f, H, r2 in [*used, *flagged])


def _hz_list(values: list[float]) -> str:
    return ", ".join(f"{v:g}" for v in values) or "none"


def stream_checks(streams: list[dict], gate: float) -> list[dict]:
    """No step below the quality gate (each flagged one named with why), the lowest R² of the
    steps used at least `gate`, and every stream's compliance peak a mode inside the swept
    band with a good fit there (`analysis.checks.peak_checks`)."""
    flagged = [f"{x['frequency_hz']:g} Hz ({stream_label(s)}): {', '.join(x['reasons'])}"
               for s in streams for x in s["flagged"]]
    low = min((s["min_r_squared"] for s in streams), default=float("nan"))
    used = [s for s in streams if s["steps_used"]]
    return [check("steps flagged (quality gate)", str(len(flagged)), not flagged,
                  "; ".join(flagged)),
            check("min R² of the steps used", f"{low:.5f}", low >= gate,
                  f"below {gate:g}: the response is not a sine at the excitation's frequency "
                  "(noise, a loose sensor, too small a force)"),
            *(peak_checks([(stream_label(s), s["peak_hz"], s["frf"]["f_hz"],
                            s["frf"]["r_squared"]) for s in used], gate, "R²") if used else [])]


def sine_stream_vs_chirp(stream: dict, chirp: dict, feed: float, amplitude: float) -> dict:
    """Largest |a/F| deviation of the sine-stream from the shaker chirp's H1 in the
    half-power band of the resonance (|H| ≥ max/√2), at the chirp's feed and amplitude."""
    steps = next(s for s in stream["streams"]
                 if s["feed_mm_min"] == feed and s["amplitude_N"] == amplitude)
    h1 = next(f for f in chirp["feeds"] if f["feed_mm_min"] == feed)["frf"]
    f = np.asarray(steps["frf"]["f_hz"])
    sine = np.asarray(steps["frf"]["accelerance_abs"])
    band = sine >= sine.max() / np.sqrt(2.0)
    deviation = np.abs(sine[band] / np.interp(f[band], h1["f_hz"], h1["H1_abs"]) - 1.0)
    return {"feed_mm_min": feed, "amplitude_N": amplitude,
            "band_hz": [float(f[band].min()), float(f[band].max())],
            "n_points": int(band.sum()), "max_deviation": float(deviation.max())}


class SineStream(Experiment):
    """Sine-stream at the tool tip (Ch. 5.5.3, Figs. 5.20–5.22): per step the sine fits of
    force and tool-tip acceleration give one FRF point with its R² (`analysis.sinefit`);
    compliance x/F = (a/F)/(jω)² per feed and force amplitude, the quality gate and the
    spread between amplitudes (the linearity of Fig. 5.22)."""

    name = NAME
    schema = SCHEMA
    has_frfs = True
    title = "sine-stream FRF point by point"
    examples = (
        # --quick: one feed and amplitude (the shaker chirp's), 40–60 Hz in 0.5 Hz steps:
        # the resonance for the comparison with the chirp's H1.
        Example(NAME, {"experiment": {"feeds_mm_min": [1000.0], "amplitudes_N": [20.0],
                                      "f_start_Hz": 40.0, "f_stop_Hz": 60.0,
                                      "f_step_Hz": 0.5}}, rank=60),
    )
    live_kinds = ("excite",)

    @classmethod
    def demo_compare(cls, entries: dict[str, dict], configs: Mapping[str, Mapping]) -> None:
        """Its example against the shaker chirp's (Ch. 5.5.3), when both completed and share
        a feed: ``vs_shaker_chirp`` in its summary (`sine_stream_vs_chirp`), a part of its
        headline."""
        pair = [next(iter(demo_examples(configs, name)), None)
                for name in (cls.name, ShakerChirp.name)]
        if None in pair or any(entries[n]["run"]["status"] != "complete" for n in pair):
            return
        stream_name, chirp_name = pair
        chirp = configs[chirp_name]["experiment"]
        feeds = (set(chirp["feeds_mm_min"])
                 & set(configs[stream_name]["experiment"]["feeds_mm_min"]))
        if not feeds:
            return
        stream = entries[stream_name]
        comparison = sine_stream_vs_chirp(stream["analysis"], entries[chirp_name]["analysis"],
                                          max(feeds), chirp["amplitude_N"])
        stream["summary"]["vs_shaker_chirp"] = comparison
        stream["headline"] = headline(
            stream["headline"],
            f"vs shaker-chirp H1 at {feed_text(comparison['feed_mm_min'])}, "
            f"{comparison['amplitude_N']:g} N: {100 * comparison['max_deviation']:.2f} % in "
            f"{comparison['band_hz'][0]:g}–{comparison['band_hz'][1]:g} Hz (half-power band)")

    @classmethod
    def check(cls, params: Mapping[str, Any], cycle_s: float) -> dict:
        """The schema's checks, measurable feeds, a stop not below the start, 4 commands per
        period at the bus cycle and a quality gate below 1."""
        p = super().check(params, cycle_s)
        check_feeds("experiment.feeds_mm_min", p["feeds_mm_min"], cycle_s)
        if p["f_stop_Hz"] < p["f_start_Hz"]:
            raise ConfigError("experiment.f_stop_Hz: must not be below f_start_Hz")
        if p["f_stop_Hz"] >= 0.25 / cycle_s:
            raise ConfigError(f"experiment.f_stop_Hz: must be below {0.25 / cycle_s:g} Hz "
                              "(4 commands per period at the bus cycle)")
        if not p["r_squared_min"] < 1.0:
            raise ConfigError("experiment.r_squared_min: must be below 1")
        return p

    def plan(self) -> Plan:
        """The stream at every amplitude at each feed in turn (CSP)."""
        p, cycle_s = self.params, self.cycle_s
        streams = [w for a in p.amplitudes_N for w in step_windows(p, a, cycle_s)]
        return plan_over_feeds(NAME, CSP, p.feeds_mm_min, lambda feed: streams, p, cycle_s,
                               p.exciter)

    def devices(self) -> dict[str, dict[str, Any]]:
        """The DAQ (exciter force, tool-tip acceleration) and the I/O module driving the
        exciter."""
        return daq_needs(self.params, self.params.exciter)

    @classmethod
    def analyze(cls, recording, final: bool = True) -> dict:
        """FRF per feed and amplitude with the quality gate, and the amplitude spread per
        feed, of the steps recorded (live: those completed so far).

        SI: accelerance (m/s²)/N, compliance m/N, frequencies Hz; feeds mm/min, amplitudes N.
        """
        p = cls.stored_params(recording)
        fs = recording.streams["daq"].rate_hz
        force_channel = FORCE_CHANNELS[p.exciter]
        grouped: dict[tuple[float, float, int], list[tuple[dict, dict]]] = {}
        fits, notes = fitted_steps(recording, force_channel, fs, p.settle_cycles,
                                   p.r_squared_min)
        for fit, info in fits:
            key = (abs(float(info["feed_mm_min"])), float(info["amplitude_N"]),
                   int(info["step"]))
            grouped.setdefault(key, []).append((fit, info))
        streams: dict[tuple[float, float], list[dict]] = {}
        for (feed, amplitude, _), repeats in sorted(grouped.items()):
            step = _combine_repeats([fit for fit, _ in repeats], repeats[0][1],
                                    p.amplitude_tolerance)
            streams.setdefault((feed, amplitude), []).append(step)
        summaries = [_stream_summary(feed, amplitude, steps)
                     for (feed, amplitude), steps in streams.items()]
        feeds = sorted({s["feed_mm_min"] for s in summaries})
        return {
            "experiment": NAME,
            "streams": summaries,
            "amplitude_spread": {f"{feed:g}": amplitude_spread(
                [s for s in summaries if s["feed_mm_min"] == feed]) for feed in feeds},
            "steps_flagged": sum(len(s["flagged"]) for s in summaries),
            "steps_planned": (len(frequencies(p)) * len(p.amplitudes_N)
                              * len(p.feeds_mm_min)),
            "r_squared_min": p.r_squared_min,
            "min_r_squared": min((s["min_r_squared"] for s in summaries), default=float("nan")),
            "notes": notes,
            "checks": [*stream_checks(summaries, p.r_squared_min),
                       records_check("steps", len(fits), notes),
                       check("notes", "; ".join(notes) or "none", not notes,
                             "a step was left out: the FRF lacks its frequency")],
        }

    @classmethod
    def report(cls, recording, result: Mapping[str, Any], section: RunSection) -> None:
        """FRF points per feed and force amplitude with the R² of each step (Figs. 5.21,
        5.22), the quality gate and the spread between amplitudes."""
        gate = result["r_squared_min"]
        streams = result["streams"]
        series = [FrfSeries(stream_label(x), np.array(x["frf"]["f_hz"]),
                            np.array(x["frf"]["compliance_abs"]),
                            np.array(x["frf"]["compliance_phase_rad"]),
                            np.array(x["frf"]["r_squared"]))
                  for x in streams]
        section.plots.append(Plot(
            "sine-stream compliance points: magnitude, phase, R² of each step",
            png_of(frf_figure(series, COMPLIANCE_LABEL, "R² of the sine fits", gate,
                              points=True))))
        section.tables.append(Table("sine-stream per feed and amplitude", (
            "feed (mm/min)", "amplitude (N)", "steps used", "peak (Hz)", "min R²",
            "force limited at (Hz)", "force not held at (Hz)"), tuple(
            (f"{x['feed_mm_min']:g}", f"{x['amplitude_N']:g}",
             f"{x['steps_used']} of {x['steps']}", f"{x['peak_hz']:.2f}",
             f"{x['min_r_squared']:.4f}", _hz_list(x["limited_hz"]), _hz_list(x["not_held_hz"]))
            for x in streams)))
        section.quality.append(Indicator("spread between amplitudes (of the peak)",
                                         spread_text(result)))

    @classmethod
    def headline(cls, result: Mapping[str, Any]) -> str:
        """The compliance peak of every stream (feed, force amplitude)."""
        return "; ".join(f"{stream_label(x)}: peak {x['peak_hz']:.2f} Hz"
                         for x in result["streams"])

    @classmethod
    def details(cls, result: Mapping[str, Any]) -> list[str]:
        """The steps used and flagged, the lowest R² measured, the spread between amplitudes."""
        used = sum(x["steps_used"] for x in result["streams"])
        return [f"  {used} steps used, {result['steps_flagged']} flagged, min R² measured "
                f"{result['min_r_squared']:.4f}",
                f"  spread between amplitudes (Fig. 5.22): {spread_text(result)}"]

    @classmethod
    def live_view(cls, result: Mapping[str, Any]) -> ResultView:
        """|x/F| (m/N), phase and R² of every step so far, one series per feed and amplitude,
        the steps below the quality gate again in red; the latest stream in the summary."""
        gate = result["r_squared_min"]
        series = {stream_label(x): stream_points(x) for x in result["streams"]}
        every = [r2 for points in series.values() for _, _, r2 in points]
        latest = result["streams"][-1]
        peak = max(latest["frf"]["compliance_abs"], default=float("nan"))
        summary = (f"step {len(every)} of {result['steps_planned']}; {stream_label(latest)}: "
                   f"{latest['steps']} points, peak {peak:.3g} m/N at {latest['peak_hz']:g} Hz; "
                   f"min R² {min(every):.4f}, {sum(r2 < gate for r2 in every)} below {gate:g}")
        return ResultView(cls.title, point_frf_panels(series, COMPLIANCE_LABEL, gate), summary)

    @classmethod
    def frfs(cls, result: Mapping[str, Any], recording) -> Iterator[ExchangeFrf]:
        """The tool-tip accelerance of each stream (feed, amplitude), from the sine fits."""
        force = tip_force(FORCE_CHANNELS[cls.stored_params(recording).exciter])
        for stream in result["streams"]:
            frf = stream["frf"]
            yield ExchangeFrf("sine_stream: tool-tip accelerance (sine fits)",
                              f"feed {stream['feed_mm_min']:g} mm/min, "
                              f"{stream['amplitude_N']:g} N", np.asarray(frf["f_hz"]),
                              polar(frf, "accelerance_abs", "accelerance_phase_rad"),
                              TIP_ACCELERATION, force)

    @classmethod
    def summary(cls, result: Mapping[str, Any], truth: Mapping[str, Any]) -> dict:
        """Quality gate and linearity of the streams (the demo adds the comparison with the
        shaker chirp)."""
        streams = result["streams"]
        min_r2 = min(s["min_r_squared"] for s in streams)
        spread = result["amplitude_spread"]
        return {"streams": len(streams), "steps": sum(s["steps"] for s in streams),
                "steps_flagged": result["steps_flagged"], "min_r_squared": min_r2,
                "amplitude_spread": spread,
                "headline": headline(
                    f"{sum(s['steps_used'] for s in streams)} steps used, "
                    f"{result['steps_flagged']} flagged, min R² {min_r2:.4f}",
                    f"amplitude spread (Fig. 5.22) {spread_text(result)}")}
