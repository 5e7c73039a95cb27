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
from typing import Any, Mapping

import numpy as np

from feedbench.analysis.frf import HammerFrf, accelerance_to_receptance, quasi_frf
from feedbench.config import ConfigError, Field, positive, validate_table
from feedbench.experiments.family import Experiment
from feedbench.experiments.plan import Plan, recorded_windows
from feedbench.experiments.tool_tip import (
    FEEDS_FIELD, FORCE_CHANNELS, MOTION_SCHEMA, RESPONSE_CHANNEL, ExcitationWindow, daq_needs,
    full_scale, overloaded, plan_over_feeds, window_samples,
)
from feedbench.protocols.cia402 import CSP

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
    **MOTION_SCHEMA,
}

DEFAULT_BAND_HZ = (20.0, 150.0)
MIN_BAND_LINES = 3
"""Frequency lines (1/record_s apart) the analysis needs in `DEFAULT_BAND_HZ` for a peak."""
INVARIANCE_TOLERANCE = 0.3
"""'Invariant': every |compliance| within 30 % of the reference's peak (≈ 2.3 dB at the peak,
where idle lies 13 dB away on the lab bench)."""


def _validated(params: Mapping[str, Any]) -> dict:
    p = validate_table(params, SCHEMA, "experiment")
    if p["pretrigger_s"] >= p["record_s"]:
        raise ConfigError("experiment.pretrigger_s: must be shorter than record_s")
    if not p["feeds_mm_min"]:
        raise ConfigError("experiment.feeds_mm_min: at least one feed")
    low, high = DEFAULT_BAND_HZ
    lines = math.floor(high * p["record_s"]) - math.ceil(low * p["record_s"]) + 1
    if lines < MIN_BAND_LINES:
        raise ConfigError(f"experiment.record_s: {p['record_s']:g} s gives {lines} frequency "
                          f"lines in the {low:g}–{high:g} Hz the quasi-FRF (Eq. 5.3) is read "
                          f"in; it needs at least {MIN_BAND_LINES}")
    return p


def hit_windows(p: Mapping[str, Any], cycle_s: float) -> list[ExcitationWindow]:
    """One record per hit: the hit fires `pretrigger_s` after the record starts."""
    n = int(round(p["record_s"] / cycle_s))
    fire = int(round(p["pretrigger_s"] / cycle_s))
    command = np.zeros(n)
    command[fire] = p["hit_force_N"]
    return [ExcitationWindow(f"hit {i + 1}", command, {"hit": i})
            for i in range(p["hits_per_feed"])]


def build_plan(params: Mapping[str, Any], cycle_s: float) -> Plan:
    """Hits at each feed in turn (CSP), passes within the stroke."""
    p = _validated(params)
    windows = hit_windows(p, cycle_s)
    return plan_over_feeds(NAME, CSP, p["feeds_mm_min"], lambda feed: windows, p, cycle_s,
                           EXCITER)


def devices(p: Mapping[str, Any], cycle_s: float) -> dict[str, dict[str, Any]]:
    """The DAQ (hammer force, tool-tip acceleration) and the I/O module firing the hammer."""
    return daq_needs(p, EXCITER)


def feed_records(recording) -> tuple[dict[float, tuple[np.ndarray, np.ndarray]], list[str]]:
    """|feed| (mm/min) → (forces, accelerations), hits × samples; records with an overloaded
    accelerometer or lost samples are left out (noted)."""
    grouped: dict[float, list[np.ndarray]] = {}
    notes: list[str] = []
    for window in recorded_windows(recording, "excite"):
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
    `reference`: max ||H_other| − |H_ref|| / max |H_ref|."""
    reference, other = np.abs(reference), np.abs(other)
    return float(np.max(np.abs(other - reference)) / np.max(reference))


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
        "peak_forces_N": [h.peak_force for h in frf.hits],
        "warnings": list(est.warnings),
        "frf": {"f_hz": est.f[inside].tolist(), "compliance_abs": np.abs(compliance).tolist(),
                "compliance_phase_rad": np.angle(compliance).tolist(),
                "coherence": est.coherence[inside].tolist()},
    }


def invariant_from(feeds: list[float], distances: list[float], tolerance: float) -> float | None:
    """The lowest feed from which every higher feed's FRF lies within `tolerance` of the
    highest feed's (None when only the highest feed does)."""
    start = None
    for feed, distance in sorted(zip(feeds, distances), reverse=True):
        if distance > tolerance:
            break
        start = feed
    return start


def analyze_recording(recording, force_window_s: float = 0.01, exp_decay_s: float = 0.5,
                      band: tuple[float, float] = DEFAULT_BAND_HZ,
                      invariance_tolerance: float = INVARIANCE_TOLERANCE) -> dict:
    """Quasi-FRF per feed (Eq. 5.3), its compliance, coherence, and the feed comparison.

    SI: frequencies Hz, compliance m/N, feeds in mm/min (as configured).
    """
    fs = recording.streams["daq"].rate_hz
    records, notes = feed_records(recording)
    summaries = []
    compliances = {}
    for feed in sorted(records):
        forces, responses = records[feed]
        try:
            frf = quasi_frf(forces, responses, fs, force_window_s, exp_decay_s,
                            force_range=full_scale(FORCE_CHANNEL))
        except ValueError as error:  # every hit of the feed flagged
            notes.append(f"{feed:g} mm/min: {error}")
            continue
        summaries.append(_feed_summary(feed, frf, band))
        compliances[feed] = np.array(summaries[-1]["frf"]["compliance_abs"])
    feeds = sorted(compliances)
    if not feeds:
        raise ConfigError(f"{recording.path}: no usable hammer hit recorded "
                          f"({'; '.join(notes) or 'no excite segment'})")
    reference, idle = compliances[feeds[-1]], compliances[feeds[0]]
    to_reference = [frf_distance(reference, compliances[f]) for f in feeds]
    for summary, distance in zip(summaries, to_reference):
        summary["distance_to_highest_feed"] = distance
        summary["distance_to_lowest_feed"] = frf_distance(idle, compliances[summary["feed_mm_min"]])
    return {
        "experiment": NAME,
        "feeds": summaries,
        "reference_feed_mm_min": feeds[-1],
        "invariance_tolerance": invariance_tolerance,
        "invariant_from_mm_min": invariant_from(feeds, to_reference, invariance_tolerance),
        "notes": notes,
    }

class ImpactHammer(Experiment):
    """TRANSITION shell: the module's functions behind the family interface."""

    name = NAME
    schema = SCHEMA

    @classmethod
    def check(cls, params: Mapping[str, Any], cycle_s: float) -> dict:
        return _validated(params)

    def plan(self) -> Plan:
        return build_plan(self.settings, self.cycle_s)

    def devices(self) -> dict[str, dict[str, Any]]:
        return devices(self.settings, self.cycle_s)

    @classmethod
    def analyze(cls, recording, final: bool = True) -> dict:
        return analyze_recording(recording)
