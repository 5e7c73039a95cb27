"""Impact hammer at a list of feeds (Ch. 5.3.1–5.3.2, Fig. 5.12; Ch. 5.5.1): idle vs in-motion.

At every feed (0: the axis holds position, enabled) the automatic hammer hits the tool tip
`hits_per_feed` times, one record of `record_s` each; the DAQ records the hammer force and the
tool-tip acceleration. Analysis: the quasi-FRF of each feed, Eq. (5.3) Φ = S_aF / S_FF over its
hits, with coherence; double hits and overloads are left out (`analysis.frf.quasi_frf`), a
record with an overloaded accelerometer or lost samples too. The compliance x_tip/F_tip =
Φ / (jω)² is compared across feeds: how far each feed's FRF lies from the highest feed's
(the in-motion reference) and from the idle one, and from which feed on it stays within
`invariance_tolerance` of the reference ("invariant", Fig. 5.12: ≈ 500 mm/min).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any, Iterator, Mapping

import numpy as np

from feedbench.analysis.checks import averaged, check
from feedbench.analysis.frf import HammerFrf, accelerance_to_receptance, quasi_frf
from feedbench.config import ConfigError, Field, positive
from feedbench.engine.family import Example, Experiment, headline
from feedbench.engine.preflight import check_feeds
from feedbench.engine.plan import Plan
from feedbench.experiments.tool_tip import (
    FEEDS_FIELD, FORCE_CHANNELS, MOTION_SCHEMA, RESPONSE_CHANNEL, TIP_ACCELERATION,
    ExcitationWindow, compliance_plot, daq_needs, feed_frf_panels, feed_frf_summary,
    feed_checks, feed_lobes, feed_text, full_scale, overloaded, plan_over_feeds, records_check,
    tip_force, whole_windows, window_samples,
)
from feedbench.protocols.cia402 import CSP
from feedbench.views.frfs import ExchangeFrf, polar
from feedbench.views.panels import ResultView
from feedbench.views.sections import RunSection, Table

NAME = "impact_hammer"
EXCITER = "hammer"
FORCE_CHANNEL = FORCE_CHANNELS[EXCITER]

SCHEMA = {
    "type": Field(str, NAME, "experiment family"),
    "feeds_mm_min": Field(list, [0.0, 25.0, 50.0, 100.0, 250.0, 500.0, 1000.0],
                          FEEDS_FIELD.doc, FEEDS_FIELD.check),
    "hits_per_feed": Field(int, 4, "hammer hits averaged per feed", positive),
    "hit_force_N": Field(float, 25.0, "peak force of a hit (N), Fig. 5.12's 25 N", positive),
    "record_s": Field(float, 2.0, "record per hit (s)", positive),
    "pretrigger_s": Field(float, 0.05, "record before the hit (s)", positive),
    "force_window_s": Field(float, 0.01, "force window: hammer force kept after the trigger, "
                            "zero after (s)", positive),
    "exp_decay_s": Field(float, 0.5, "time constant of the exponential window on the "
                         "acceleration after the trigger (s)", positive),
    "band_low_Hz": Field(float, 20.0, "band the quasi-FRF (Eq. 5.3) is read and the feeds "
                         "compared in: low end (Hz)", positive),
    "band_high_Hz": Field(float, 150.0, "band the quasi-FRF (Eq. 5.3) is read and the feeds "
                          "compared in: high end (Hz)", positive),
    "invariance_tolerance": Field(float, 0.3, "'invariant': every |compliance| within this "
                                  "share of the highest feed's peak (0.3 ≈ 2.3 dB at the "
                                  "peak, where idle lies 13 dB away on the lab bench)",
                                  positive),
    **MOTION_SCHEMA,
}

MIN_BAND_LINES = 3
"""Frequency lines (1/record_s apart) the analysis needs in the band for a peak."""
THESIS_INVARIANT_FEED_MM_MIN = 500.0
"""Fig. 5.12: the in-motion FRF becomes invariant above ≈ 500 mm/min (DIGEST §3)."""


def hit_windows(p: Any, cycle_s: float) -> list[ExcitationWindow]:
    """One record per hit: the hit fires `pretrigger_s` after the record starts."""
    n = int(round(p.record_s / cycle_s))
    fire = int(round(p.pretrigger_s / cycle_s))
    command = np.zeros(n)
    command[fire] = p.hit_force_N
    return [ExcitationWindow(f"hit {i + 1}", command, {"hit": i})
            for i in range(p.hits_per_feed)]


def feed_records(recording) -> tuple[dict[float, tuple[np.ndarray, np.ndarray]], list[str]]:
    """|feed| (mm/min) → (forces, accelerations), hits × samples; records with an overloaded
    accelerometer or lost samples, or cut short by a stop (`whole_windows`), are left out
    (noted)."""
    grouped: dict[float, list[np.ndarray]] = {}
    windows, notes = whole_windows(recording)
    for window in windows:
        samples, lost = window_samples(recording, window, (FORCE_CHANNEL, RESPONSE_CHANNEL))
        notes += lost
        if overloaded(samples[1:], (RESPONSE_CHANNEL,)):
            notes.append(f"{window.label}: accelerometer overload, record left out")
        elif not lost:
            grouped.setdefault(abs(float(window.info["feed_mm_min"])), []).append(samples)
    records = {}
    for feed, hits in grouped.items():
        n = min(h.shape[1] for h in hits)
        stacked = np.stack([h[:, :n] for h in hits])
        records[feed] = (stacked[:, 0], stacked[:, 1])
    return records, notes


def frf_distance(reference: np.ndarray, other: np.ndarray) -> float:
    """Largest magnitude difference between two FRFs over a band, relative to the peak of
    `reference`: max ||H_other| − |H_ref|| / max |H_ref|; NaN when the reference is zero
    (its accelerometer read nothing)."""
    reference, other = np.abs(reference), np.abs(other)
    peak = float(np.max(reference))
    return float(np.max(np.abs(other - reference)) / peak) if peak > 0.0 else float("nan")


def _feed_summary(feed: float, frf: HammerFrf, band: tuple[float, float]) -> dict:
    est = frf.estimate
    inside = (est.f >= band[0]) & (est.f <= band[1])
    compliance = accelerance_to_receptance(est.f[inside], est.H1[inside])
    k = int(np.argmax(np.abs(compliance)))
    return {
        "feed_mm_min": feed,
        "peak_hz": float(est.f[inside][k]),
        "peak_compliance_m_N": float(np.abs(compliance[k])),
        "min_coherence": float(np.min(est.coherence[inside])),
        "hits": len(frf.hits),
        "hits_used": len(frf.used_hits),
        "left_out": [f"{feed:g} mm/min: hit {h.index} at {h.trigger_time:.3f} s: {h.reason}"
                     for h in frf.hits if h.index not in frf.used_hits],
        "peak_forces_N": [h.peak_force for h in frf.hits],
        "warnings": list(est.warnings),
        "frf": {"f_hz": est.f[inside].tolist(), "compliance_abs": np.abs(compliance).tolist(),
                "compliance_phase_rad": np.angle(compliance).tolist(),
                "coherence": est.coherence[inside].tolist()},
    }


def feed_summaries(recording, p: Any) -> tuple[list[dict], list[str]]:
    """The quasi-FRF (Eq. 5.3) of each feed's hits, lowest feed first, read in the band of
    `p` (validated parameters); feeds whose every hit is flagged are noted instead."""
    fs = recording.streams["daq"].rate_hz
    band = (p.band_low_Hz, p.band_high_Hz)
    records, notes = feed_records(recording)
    summaries = []
    for feed in sorted(records):
        forces, responses = records[feed]
        try:
            frf = quasi_frf(forces, responses, fs, p.force_window_s, p.exp_decay_s,
                            force_range=full_scale(FORCE_CHANNEL))
        except ValueError as error:  # every hit of the feed flagged
            notes.append(f"{feed:g} mm/min: {error}")
            continue
        summaries.append(_feed_summary(feed, frf, band))
    return summaries, notes


def hits_check(feeds: list[dict]) -> dict:
    """The hits left out of the feeds' averages (double hit, force overload), each named
    with its time in its record and why."""
    left_out = [hit for x in feeds for hit in x["left_out"]]
    return check("hits left out", str(len(left_out)), not left_out, "; ".join(left_out))


def invariant_from(feeds: list[float], distances: list[float], tolerance: float) -> float | None:
    """The lowest feed from which every higher feed's FRF lies within `tolerance` of the
    highest feed's (None when only the highest feed does)."""
    start = None
    for feed, distance in sorted(zip(feeds, distances), reverse=True):
        if distance > tolerance:
            break
        start = feed
    return start


def _compliance(feed: Mapping[str, Any]) -> np.ndarray:
    """A feed's complex compliance x/F (m/N) from its magnitude and phase."""
    frf = feed["frf"]
    return np.array(frf["compliance_abs"]) * np.exp(1j * np.array(frf["compliance_phase_rad"]))


class ImpactHammer(Experiment):
    """Impact hammer at a list of feeds (Ch. 5.3.1–5.3.2, Fig. 5.12): the quasi-FRF of each
    feed's hits, Eq. (5.3) Φ = S_aF / S_FF, its compliance Φ / (jω)², and the feed from
    which it stays within `invariance_tolerance` of the highest feed's; the stability lobes
    of the lowest and the highest feed (Fig. 5.25)."""

    name = NAME
    schema = SCHEMA
    has_frfs = True
    title = "impact hammer: quasi-FRF of the hits so far"
    examples = (
        # --quick: idle, slow, at and above Fig. 5.12's 500 mm/min, 3 hits each: the FRF
        # still changes with feed and is invariant from 500 mm/min.
        Example(NAME, {"experiment": {"feeds_mm_min": [0.0, 100.0, 500.0, 1000.0],
                                      "hits_per_feed": 3, "record_s": 1.5}}, rank=40),
    )
    live_kinds = ("excite",)

    @classmethod
    def check(cls, params: Mapping[str, Any], cycle_s: float) -> dict:
        """The schema's checks, measurable feeds, a pre-trigger inside the record, a feed,
        and enough frequency lines (1/record_s apart) in the band for a peak."""
        p = super().check(params, cycle_s)
        check_feeds("experiment.feeds_mm_min", p["feeds_mm_min"], cycle_s)
        if p["pretrigger_s"] >= p["record_s"]:
            raise ConfigError("experiment.pretrigger_s: must be shorter than record_s")
        if not p["feeds_mm_min"]:
            raise ConfigError("experiment.feeds_mm_min: at least one feed")
        low, high = p["band_low_Hz"], p["band_high_Hz"]
        if low >= high:
            raise ConfigError(f"experiment.band_low_Hz: must be below band_high_Hz ({high:g} Hz)")
        lines = math.floor(high * p["record_s"]) - math.ceil(low * p["record_s"]) + 1
        if lines < MIN_BAND_LINES:
            raise ConfigError(f"experiment.record_s: {p['record_s']:g} s gives {lines} frequency "
                              f"lines in the {low:g}–{high:g} Hz the quasi-FRF (Eq. 5.3) is read "
                              f"in; it needs at least {MIN_BAND_LINES}")
        return p

    def plan(self) -> Plan:
        """Hits at each feed in turn (CSP), passes within the stroke."""
        windows = hit_windows(self.params, self.cycle_s)
        return plan_over_feeds(NAME, CSP, self.params.feeds_mm_min, lambda feed: windows,
                               self.params, self.cycle_s, EXCITER)

    def devices(self) -> dict[str, dict[str, Any]]:
        """The DAQ (hammer force, tool-tip acceleration) and the I/O module firing the hammer."""
        return daq_needs(self.params, EXCITER)

    @classmethod
    def analyze(cls, recording, final: bool = True) -> dict:
        """Quasi-FRF per feed (Eq. 5.3), its compliance, coherence, and the feed comparison:
        each feed's distance to the highest feed's compliance (the in-motion reference) and to
        the lowest's (idle). SI: frequencies Hz, compliance m/N; feeds in mm/min (as
        configured). The hits so far (live) are analysed the same way; a run stopped before
        its first usable hit gives a result without feeds, not valid (`records_check`), a
        complete one a `ConfigError`."""
        p = cls.stored_params(recording)
        summaries, notes = feed_summaries(recording, p)
        if not summaries and (not final or recording.status == "complete"):
            raise ConfigError(f"{recording.path}: no usable hammer hit recorded "
                              f"({'; '.join(notes) or 'no excite segment'})")
        compliances = [np.array(x["frf"]["compliance_abs"]) for x in summaries]
        for summary, compliance in zip(summaries, compliances):
            summary["distance_to_highest_feed"] = frf_distance(compliances[-1], compliance)
            summary["distance_to_lowest_feed"] = frf_distance(compliances[0], compliance)
        feeds = [x["feed_mm_min"] for x in summaries]
        tolerance = p.invariance_tolerance
        return {
            "experiment": NAME,
            "feeds": summaries,
            "reference_feed_mm_min": feeds[-1] if feeds else None,
            "invariance_tolerance": tolerance,
            "invariant_from_mm_min": invariant_from(
                feeds, [x["distance_to_highest_feed"] for x in summaries], tolerance),
            "notes": notes,
            "checks": feed_checks(summaries, notes, hits_check(summaries),
                                  averaged(min(x["hits_used"] for x in summaries), "hits"))
            if summaries else [records_check("hits", 0, notes)],
        }

    @classmethod
    def report(cls, recording, result: Mapping[str, Any], section: RunSection) -> None:
        """Quasi-FRF per feed (Eq. 5.3) as compliance with coherence, the feed comparison
        (Fig. 5.12) and the stability lobes of the lowest and highest feed (Fig. 5.25)."""
        feeds = result["feeds"]
        if not feeds:  # a run stopped before its first usable hit: its checks say so
            return
        section.plots.append(compliance_plot(feeds, "quasi-FRF, Eq. 5.3"))
        section.tables.append(Table("impact hammer per feed", (
            "feed (mm/min)", "peak (Hz)", "peak |x/F| (µm/N)", "hits used", "min coherence",
            "distance to highest feed"), tuple(
            (f"{x['feed_mm_min']:g}", f"{x['peak_hz']:.2f}",
             f"{x['peak_compliance_m_N'] * 1e6:.3f}", f"{x['hits_used']} of {x['hits']}",
             f"{x['min_coherence']:.4f}", f"{100 * x['distance_to_highest_feed']:.0f} %")
            for x in feeds)))
        feed_lobes(feeds, _compliance, section)

    @classmethod
    def headline(cls, result: Mapping[str, Any]) -> str:
        """The feed from which the FRF is invariant."""
        if not result["feeds"]:
            return "no hit analysed"
        invariant = result["invariant_from_mm_min"]
        return (f"invariant from {invariant:g} mm/min" if invariant is not None
                else "no feed range invariant")

    @classmethod
    def details(cls, result: Mapping[str, Any]) -> list[str]:
        """Per feed: the compliance peak, the hits used and the distance to the highest feed."""
        return [f"  {x['feed_mm_min']:g} mm/min: peak {x['peak_hz']:.2f} Hz, "
                f"{x['peak_compliance_m_N'] * 1e6:.3f} µm/N, {x['hits_used']} of {x['hits']} "
                f"hits, {100 * x['distance_to_highest_feed']:.0f} % from the highest feed"
                for x in result["feeds"]]

    @classmethod
    def live_view(cls, result: Mapping[str, Any]) -> ResultView:
        """Compliance |x/F| (m/N) and coherence of each feed's hits so far; per feed the hits
        used, the peak and the lowest coherence in the summary."""
        feeds = result["feeds"]
        return ResultView(cls.title, feed_frf_panels(feeds),
                          feed_frf_summary(feeds, "hits_used", "hits", "hits", result["notes"]))

    @classmethod
    def frfs(cls, result: Mapping[str, Any], recording) -> Iterator[ExchangeFrf]:
        """The tool-tip compliance (Eq. 5.3) of each feed, over the hammer's force."""
        for feed in result["feeds"]:
            frf = feed["frf"]
            yield ExchangeFrf("impact_hammer: tool-tip compliance (Eq. 5.3)",
                              f"feed {feed['feed_mm_min']:g} mm/min", np.asarray(frf["f_hz"]),
                              polar(frf, "compliance_abs", "compliance_phase_rad"),
                              replace(TIP_ACCELERATION, quantity="displacement"),
                              tip_force(FORCE_CHANNEL), np.asarray(frf["coherence"]))

    @classmethod
    def summary(cls, result: Mapping[str, Any], truth: Mapping[str, Any]) -> dict:
        """The feed from which the quasi-FRF (Eq. 5.3) is invariant, against Fig. 5.12; the
        idle peak against the motor-locked f_t (Eq. 4.13)."""
        feeds = [{k: feed[k] for k in ("feed_mm_min", "peak_hz", "peak_compliance_m_N",
                                       "distance_to_highest_feed", "min_coherence", "hits_used")}
                 for feed in result["feeds"]]
        idle, top = feeds[0], feeds[-1]
        invariant = result["invariant_from_mm_min"]
        return {"invariant_from_mm_min": invariant,
                "thesis_invariant_mm_min": THESIS_INVARIANT_FEED_MM_MIN,
                "truth_f_t_hz": truth["f_t_hz"], "feeds": feeds,
                "headline": headline(
                    f"invariant from {feed_text(invariant)} "
                    f"(Fig. 5.12: ≈ {feed_text(THESIS_INVARIANT_FEED_MM_MIN)})",
                    f"peak {idle['peak_hz']:.1f} Hz at {feed_text(idle['feed_mm_min'])} "
                    f"(f_t {truth['f_t_hz']:.1f}), {top['peak_hz']:.1f} Hz at "
                    f"{feed_text(top['feed_mm_min'])}",
                    "distance to the highest feed "
                    + ", ".join(f"{100 * f['distance_to_highest_feed']:.0f} %" for f in feeds))}
