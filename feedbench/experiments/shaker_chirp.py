"""Chirp injection with a shaker at the tool tip (Ch. 3.5.1, Fig. 3.17).

The shaker (or the inertial actuator) sweeps `f_start_Hz` → `f_stop_Hz` in `duration_s`,
`repetitions` times at each feed, each sweep followed by `tail_s` without excitation; the DAQ
records its force (load cell at the stinger) and the tool-tip acceleration. Analysis per feed:
each sweep with its ring-down is one record (rectangular window, no overlap: both signals
start and end near zero, so the records are leakage-free, unlike Welch segments cutting a
chirp); H1, H2 and coherence over the records (`analysis.frf.estimate_frf`), and the
compliance x_tip / F_tip = H1 / (jω)². The drive-offset chirp is `experiments.chirp`.
"""

from __future__ import annotations

from typing import Any, Iterator, Mapping

import numpy as np

from feedbench.analysis.checks import averaged
from feedbench.analysis.frf import accelerance_to_receptance, estimate_frf, findings_in_band
from feedbench.config import ConfigError, Field, one_of, positive
from feedbench.engine.family import Example, Experiment, headline
from feedbench.engine.preflight import check_feeds
from feedbench.engine.plan import Plan
from feedbench.experiments.signals import chirp
from feedbench.experiments.tool_tip import (
    FEEDS_FIELD, FORCE_CHANNELS, MOTION_SCHEMA, RESPONSE_CHANNEL, TIP_ACCELERATION,
    ExcitationWindow, tip_force,
    compliance_plot, daq_needs, feed_frf_panels, feed_frf_summary, feed_lobes,
    feed_checks, feed_text, overloaded, plan_over_feeds, records_check, whole_windows,
    window_samples,
)
from feedbench.protocols.cia402 import CSP
from feedbench.views.frfs import ExchangeFrf, polar
from feedbench.views.panels import ResultView
from feedbench.views.sections import RunSection, Table, frf_warnings

NAME = "shaker_chirp"

SCHEMA = {
    "type": Field(str, NAME, "experiment family"),
    "exciter": Field(str, "shaker", "shaker (Fig. 3.17) or inertial actuator",
                     one_of("shaker", "actuator")),
    "feeds_mm_min": Field(list, [1000.0], FEEDS_FIELD.doc, FEEDS_FIELD.check),
    "amplitude_N": Field(float, 20.0, "chirp command amplitude (N)", positive),
    "f_start_Hz": Field(float, 20.0, "start frequency (Hz)", positive),
    "f_stop_Hz": Field(float, 100.0, "stop frequency (Hz)", positive),
    "duration_s": Field(float, 8.0, "duration of one sweep (s)", positive),
    "tail_s": Field(float, 0.5, "ring-down after each sweep, recorded with it (s)", positive),
    "repetitions": Field(int, 4, "sweeps averaged per feed", positive),
    "sweep": Field(str, "linear", "linear or logarithmic", one_of("linear", "logarithmic")),
    **MOTION_SCHEMA,
}


def sweep_records(recording, force_channel: str) -> tuple[dict[float, np.ndarray], list[str]]:
    """|feed| (mm/min) → its sweeps as records × (force, acceleration) × n, each record
    zero-mean and cut to the shortest; sweeps with an overloaded channel or lost samples, or
    cut short by a stop (`whole_windows`), are left out (noted)."""
    grouped: dict[float, list[np.ndarray]] = {}
    windows, notes = whole_windows(recording)
    channels = (force_channel, RESPONSE_CHANNEL)
    for window in windows:
        samples, lost = window_samples(recording, window, channels)
        notes += lost
        if overloaded(samples, channels):
            notes.append(f"{window.label}: overloaded channel, sweep left out")
        elif not lost:
            grouped.setdefault(abs(float(window.info["feed_mm_min"])), []).append(samples)
    records = {}
    for feed, parts in grouped.items():
        n = min(part.shape[1] for part in parts)
        records[feed] = np.stack([part[:, :n] - part[:, :n].mean(axis=1, keepdims=True)
                                  for part in parts])
    return records, notes


def feed_frf(feed: float, sweeps: np.ndarray, fs: float, band: tuple[float, float]) -> dict:
    """One feed's tool-tip FRF from its sweeps (records × (force, acceleration) × n, fs Hz):
    H1, H2 (accelerance, (m/s²)/N), compliance H1 / (jω)² (m/N) and coherence in `band`;
    `ValueError` when records that short hold no frequency line in it."""
    force, response = np.concatenate(sweeps, axis=1)
    est = estimate_frf(force, response, fs, nperseg=sweeps.shape[2], overlap=0.0,
                       window="boxcar")
    inside = (est.f >= band[0]) & (est.f <= band[1])
    if not inside.any():
        raise ValueError(f"records of {sweeps.shape[2] / fs:.3g} s hold no frequency line in "
                         f"{band[0]:g}–{band[1]:g} Hz, sweeps left out")
    f = est.f[inside]
    compliance = accelerance_to_receptance(f, est.H1[inside])
    warnings, details = findings_in_band(est, band)
    return {
        "feed_mm_min": feed,
        "n_averages": est.n_averages,
        "peak_hz": float(f[np.argmax(np.abs(compliance))]),
        "min_coherence": float(est.coherence[inside].min()),
        "warnings": warnings,
        "warning_details": details,
        "frf": {"f_hz": f.tolist(), "H1_abs": np.abs(est.H1[inside]).tolist(),
                "H1_phase_rad": np.angle(est.H1[inside]).tolist(),
                "H2_abs": np.abs(est.H2[inside]).tolist(),
                "compliance_abs": np.abs(compliance).tolist(),
                "compliance_phase_rad": np.angle(compliance).tolist(),
                "coherence": est.coherence[inside].tolist()},
    }


def _compliance(feed: Mapping[str, Any]) -> np.ndarray:
    """A feed's complex compliance x/F = H1 / (jω)² (m/N) from its accelerance H1."""
    frf = feed["frf"]
    f = np.array(frf["f_hz"])
    accelerance = np.array(frf["H1_abs"]) * np.exp(1j * np.array(frf["H1_phase_rad"]))
    return -accelerance / (2 * np.pi * f) ** 2


class ShakerChirp(Experiment):
    """Chirp with a shaker (or the inertial actuator) at the tool tip (Ch. 3.5.1, Fig. 3.17):
    per feed H1, H2 and coherence over the sweeps, each sweep with its ring-down one
    leakage-free record, and the compliance x_tip / F_tip = H1 / (jω)²; the stability lobes
    of the lowest and the highest feed (Ch. 5.5.6)."""

    name = NAME
    schema = SCHEMA
    has_frfs = True
    title = "shaker chirp: tool-tip FRF of the sweeps so far"
    examples = (
        # --quick: 2 sweeps of 4 s over 30–70 Hz cover the resonance's half-power band
        # (≈ 43–60 Hz) with coherence > 0.99.
        Example(NAME, {"experiment": {"f_start_Hz": 30.0, "f_stop_Hz": 70.0,
                                      "duration_s": 4.0, "repetitions": 2}}, rank=50),
    )
    live_kinds = ("excite",)

    @classmethod
    def check(cls, params: Mapping[str, Any], cycle_s: float) -> dict:
        """The schema's checks, measurable feeds and a sweep of at least 4 commands per
        period."""
        p = super().check(params, cycle_s)
        check_feeds("experiment.feeds_mm_min", p["feeds_mm_min"], cycle_s)
        if not p["f_start_Hz"] < p["f_stop_Hz"] < 0.25 / cycle_s:
            raise ConfigError(f"experiment.f_stop_Hz: must lie above f_start_Hz and below "
                              f"{0.25 / cycle_s:g} Hz (4 commands per period at the bus cycle)")
        return p

    def plan(self) -> Plan:
        """`repetitions` sweeps, each followed by `tail_s` at zero, at each feed (CSP),
        passes within the stroke."""
        p = self.params
        sweep = chirp(p.amplitude_N, p.f_start_Hz, p.f_stop_Hz, p.duration_s,
                      self.cycle_s, p.sweep)
        sweep = np.concatenate([sweep, np.zeros(int(round(p.tail_s / self.cycle_s)))])
        windows = [ExcitationWindow(f"sweep {i + 1}", sweep, {"repetition": i})
                   for i in range(p.repetitions)]
        return plan_over_feeds(NAME, CSP, p.feeds_mm_min, lambda feed: windows, p,
                               self.cycle_s, p.exciter)

    def devices(self) -> dict[str, dict[str, Any]]:
        """The DAQ (exciter force, tool-tip acceleration) and the I/O module driving the
        exciter."""
        return daq_needs(self.params, self.params.exciter)

    @classmethod
    def analyze(cls, recording, final: bool = True) -> dict:
        """Tool-tip FRF per feed (`feed_frf`) in the swept range; the sweeps so far (live)
        are analysed the same way; none usable (a run stopped before its first whole sweep):
        a result without feeds, not valid (`records_check`)."""
        p = cls.stored_params(recording)
        band = (p.f_start_Hz, p.f_stop_Hz)
        fs = recording.streams["daq"].rate_hz
        records, notes = sweep_records(recording, FORCE_CHANNELS[p.exciter])
        feeds = []
        for feed, sweeps in sorted(records.items()):
            try:
                feeds.append(feed_frf(feed, sweeps, fs, band))
            except ValueError as error:  # the only sweep was cut short by a stop
                notes.append(f"{feed:g} mm/min: {error}")
        checks = feed_checks(feeds, notes, averaged(min(x["n_averages"] for x in feeds),
                                                    "sweeps")) if feeds else [
            records_check("sweeps", 0, notes)]
        return {"experiment": NAME, "feeds": feeds, "notes": notes, "checks": checks}

    @classmethod
    def report(cls, recording, result: Mapping[str, Any], section: RunSection) -> None:
        """Tool-tip compliance per feed (H1 over the sweeps) with coherence, and its lobes."""
        feeds = result["feeds"]
        if not feeds:  # a run stopped before its first usable sweep: its checks say so
            return
        section.plots.append(compliance_plot(feeds, "H1 over the sweeps"))
        section.tables.append(Table("shaker chirp per feed", (
            "feed (mm/min)", "sweeps averaged", "peak (Hz)", "min coherence", "warnings"), tuple(
            (f"{x['feed_mm_min']:g}", str(x["n_averages"]), f"{x['peak_hz']:.2f}",
             f"{x['min_coherence']:.4f}", "; ".join(x["warnings"]) or "none") for x in feeds)))
        feed_lobes(feeds, _compliance, section)
        section.quality.append(frf_warnings([w for x in feeds for w in x["warnings"]],
                                            [d for x in feeds for d in x["warning_details"]]))

    @classmethod
    def headline(cls, result: Mapping[str, Any]) -> str:
        """The compliance peak of each feed."""
        return ", ".join(f"{x['feed_mm_min']:g} mm/min: peak {x['peak_hz']:.1f} Hz"
                         for x in result["feeds"]) or "no sweep analysed"

    @classmethod
    def live_view(cls, result: Mapping[str, Any]) -> ResultView:
        """Compliance |x/F| (m/N) and coherence of each feed's sweeps so far; per feed the
        sweeps averaged, the peak and the lowest coherence in the summary."""
        feeds = result["feeds"]
        return ResultView(cls.title, feed_frf_panels(feeds), feed_frf_summary(
            feeds, "n_averages", "n_averages", "sweeps", result["notes"]))

    @classmethod
    def frfs(cls, result: Mapping[str, Any], recording) -> Iterator[ExchangeFrf]:
        """The tool-tip accelerance H1 of each feed, over the exciter's force."""
        force = tip_force(FORCE_CHANNELS[cls.stored_params(recording).exciter])
        for feed in result["feeds"]:
            frf = feed["frf"]
            yield ExchangeFrf("shaker_chirp: tool-tip accelerance H1",
                              f"feed {feed['feed_mm_min']:g} mm/min", np.asarray(frf["f_hz"]),
                              polar(frf, "H1_abs", "H1_phase_rad"), TIP_ACCELERATION, force,
                              np.asarray(frf["coherence"]))

    @classmethod
    def summary(cls, result: Mapping[str, Any], truth: Mapping[str, Any]) -> dict:
        """Tool-tip FRF per feed: compliance peak and coherence."""
        feeds = [{k: feed[k] for k in ("feed_mm_min", "peak_hz", "min_coherence", "n_averages")}
                 for feed in result["feeds"]]
        return {"feeds": feeds, "headline": headline(*(
            f"{feed_text(f['feed_mm_min'])}: compliance peak {f['peak_hz']:.2f} Hz, "
            f"min coherence {f['min_coherence']:.4f}" for f in feeds))}
