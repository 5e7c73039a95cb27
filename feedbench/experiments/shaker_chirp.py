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

from typing import Any, Mapping

import numpy as np

from feedbench.analysis.frf import FrfEstimate, accelerance_to_receptance, estimate_frf
from feedbench.config import ConfigError, Field, one_of, positive, validate_table
from feedbench.experiments.family import Experiment
from feedbench.experiments.plan import Plan, recorded_windows
from feedbench.experiments.signals import chirp
from feedbench.experiments.tool_tip import (
    FEEDS_FIELD, FORCE_CHANNELS, MOTION_SCHEMA, RESPONSE_CHANNEL, ExcitationWindow, daq_needs,
    overloaded, plan_over_feeds, window_samples,
)
from feedbench.protocols.cia402 import CSP

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

def _validated(params: Mapping[str, Any], cycle_s: float) -> dict:
    p = validate_table(params, SCHEMA, "experiment")
    if not p["f_start_Hz"] < p["f_stop_Hz"] < 0.25 / cycle_s:
        raise ConfigError(f"experiment.f_stop_Hz: must lie above f_start_Hz and below "
                          f"{0.25 / cycle_s:g} Hz (4 commands per period at the bus cycle)")
    return p


def build_plan(params: Mapping[str, Any], cycle_s: float) -> Plan:
    """`repetitions` sweeps at each feed (CSP), passes within the stroke."""
    p = _validated(params, cycle_s)
    sweep = chirp(p["amplitude_N"], p["f_start_Hz"], p["f_stop_Hz"], p["duration_s"], cycle_s,
                  p["sweep"])
    sweep = np.concatenate([sweep, np.zeros(int(round(p["tail_s"] / cycle_s)))])
    windows = [ExcitationWindow(f"sweep {i + 1}", sweep, {"repetition": i})
               for i in range(p["repetitions"])]
    return plan_over_feeds(NAME, CSP, p["feeds_mm_min"], lambda feed: windows, p, cycle_s,
                           p["exciter"])


def devices(p: Mapping[str, Any], cycle_s: float) -> dict[str, dict[str, Any]]:
    """The DAQ (exciter force, tool-tip acceleration) and the I/O module driving the exciter."""
    return daq_needs(p, p["exciter"])


def sweep_records(recording, force_channel: str) -> tuple[dict[float, np.ndarray], list[str]]:
    """|feed| (mm/min) → its sweeps as records × (force, acceleration) × n, each record
    zero-mean and cut to the shortest; sweeps with an overloaded channel or lost samples are
    left out (noted)."""
    grouped: dict[float, list[np.ndarray]] = {}
    notes: list[str] = []
    channels = (force_channel, RESPONSE_CHANNEL)
    for window in recorded_windows(recording, "excite"):
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


def warnings_in_band(est: FrfEstimate, band: tuple[float, float]) -> list[str]:
    """The estimate's leakage warnings about resonances inside `band` (Hz); outside the
    swept range the coherence is noise and its 'peaks' are not modes."""
    peaks = [f for f in est.leaky_peaks if band[0] <= f <= band[1]]
    return [w for w in est.warnings if any(f"near {f:.2f} Hz" in w for f in peaks)]


def analyze_recording(recording, band: tuple[float, float] | None = None) -> dict:
    """Tool-tip FRF per feed: H1, H2 (accelerance), compliance, coherence in `band` (Hz;
    default the swept range)."""
    p = validate_table(recording.config["experiment"], SCHEMA, "experiment")
    band = band or (p["f_start_Hz"], p["f_stop_Hz"])
    fs = recording.streams["daq"].rate_hz
    records, notes = sweep_records(recording, FORCE_CHANNELS[p["exciter"]])
    feeds = []
    for feed, sweeps in sorted(records.items()):
        force, response = np.concatenate(sweeps, axis=1)
        est = estimate_frf(force, response, fs, nperseg=sweeps.shape[2], overlap=0.0,
                           window="boxcar")
        inside = (est.f >= band[0]) & (est.f <= band[1])
        f = est.f[inside]
        compliance = accelerance_to_receptance(f, est.H1[inside])
        feeds.append({
            "feed_mm_min": feed,
            "n_averages": est.n_averages,
            "peak_hz": float(f[np.argmax(np.abs(compliance))]),
            "min_coherence": float(est.coherence[inside].min()),
            "warnings": warnings_in_band(est, band),
            "frf": {"f_hz": f.tolist(), "H1_abs": np.abs(est.H1[inside]).tolist(),
                    "H1_phase_rad": np.angle(est.H1[inside]).tolist(),
                    "H2_abs": np.abs(est.H2[inside]).tolist(),
                    "compliance_abs": np.abs(compliance).tolist(),
                    "coherence": est.coherence[inside].tolist()},
        })
    return {"experiment": NAME, "feeds": feeds, "notes": notes}

class ShakerChirp(Experiment):
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
