"""SMFE: the cutting simulation and the MIMO estimate, each against a baseline in the same run.

Set-up of DIGEST §3b: Z = 2, D = 80 mm, κ = 45°, a_p = 2 mm, a_e = 12 mm, spindle 600 rpm
+ 1.5 rad/s² for 65 s at 10 kHz (650 000 samples per cut), Table 6.1/6.2, sensor noise.

- Simulation: `simulate_smfe_cut` (numba-compiled kernel) against the same kernel interpreted
  by Python (NUMBA_DISABLE_JIT=1 in a subprocess, on the first 0.5 s of the cut, scaled).
- Estimate: `smfe_estimate` (one rfft per channel, all cross-spectra from it) against
  scipy.signal.csd / coherence called per channel pair; same Hann 40 000-sample segments,
  80 % overlap, no detrend; the two receptance matrices are compared.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import scipy.signal

from feedbench.analysis.smfe import smfe_estimate
from feedbench.models.milling import (
    MILLING_MODES,
    SMFE_SENSOR_NOISE,
    SMFE_TOOL,
    TABLE_6_1,
    simulate_smfe_cut,
    spindle_ramp,
)
from feedbench.models.structure import SMFE_TOOL_STRUCTURE

FS = 10_000.0
DURATION = 65.0
INTERPRETED_DURATION = 0.5
NFFT, NOVERLAP, F_MAX = 40_000, 32_000, 150.0
REPEATS = 3

_INTERPRETED = f"""
import time
from feedbench.models.milling import *
from feedbench.models.structure import SMFE_TOOL_STRUCTURE
rpm = spindle_ramp(600.0, 1.5, {INTERPRETED_DURATION}, {FS})
t0 = time.perf_counter()
simulate_smfe_cut(SMFE_TOOL_STRUCTURE, SMFE_TOOL, TABLE_6_1, 2e-3, 12e-3, "down", rpm, {FS})
print(time.perf_counter() - t0)
"""


def simulate_cuts() -> list[dict[str, np.ndarray]]:
    rpm = spindle_ramp(600.0, 1.5, DURATION, FS)
    return [simulate_smfe_cut(SMFE_TOOL_STRUCTURE, SMFE_TOOL, TABLE_6_1, 2e-3, 12e-3, mode, rpm, FS,
                              SMFE_SENSOR_NOISE, seed) for seed, mode in enumerate(MILLING_MODES)]


def interpreted_seconds_per_simulated_second() -> float:
    """Wall time of the pure-Python kernel per simulated second (subprocess, JIT disabled)."""
    env = {**os.environ, "NUMBA_DISABLE_JIT": "1"}
    out = subprocess.run([sys.executable, "-c", _INTERPRETED], env=env, check=True,
                         capture_output=True, text=True).stdout
    return float(out.strip().splitlines()[-1]) / INTERPRETED_DURATION


def scipy_estimate(cuts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Eq. (6.13) with scipy.signal.csd per pair; coherence per pair with scipy.signal.coherence."""
    options = {"fs": FS, "window": "hann", "nperseg": NFFT, "noverlap": NOVERLAP, "detrend": False}
    force_columns, response_columns, coherences = [], [], []
    for force, acc in cuts:
        f, S_F = scipy.signal.csd(force[0], force, **options)
        _, S_a = scipy.signal.csd(force[0], acc, **options)
        coherences.append(scipy.signal.coherence(force[None, :, :], acc[:, None, :], **options)[1])
        force_columns.append(S_F.T)
        response_columns.append(S_a.T)
    band = (f > 0) & (f <= F_MAX)
    S_FF = np.stack(force_columns, axis=-1)[band]
    S_aF = np.stack(response_columns, axis=-1)[band]
    accelerance = np.swapaxes(np.linalg.solve(np.swapaxes(S_FF, 1, 2), np.swapaxes(S_aF, 1, 2)), 1, 2)
    return f[band], accelerance / ((2j * np.pi * f[band]) ** 2)[:, None, None]


def _best_of(job, repeats: int) -> tuple[float, object]:
    best, result = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = job()
        best = min(best, time.perf_counter() - t0)
    return best, result


def run() -> dict[str, float]:
    simulate_cuts()  # compile (or load the numba cache) outside the timing
    sim_s, runs = _best_of(simulate_cuts, REPEATS)
    per_cut = sim_s / len(MILLING_MODES)
    interpreted = interpreted_seconds_per_simulated_second() * DURATION
    cuts = [(run_["F"], run_["acc"]) for run_ in runs]
    ours_s, ours = _best_of(lambda: smfe_estimate(cuts, FS, NFFT, NOVERLAP / NFFT, F_MAX), REPEATS)
    scipy_s, (f, phi_scipy) = _best_of(lambda: scipy_estimate(cuts), 1)
    band = (f >= 20.0) & (f <= 100.0)
    difference = np.abs(ours.Phi[band] - phi_scipy[band]).max() / np.abs(phi_scipy[band]).max()
    figures = {
        "smfe_simulate_cut_s": per_cut,
        "smfe_simulate_realtime_factor": DURATION / per_cut,
        "smfe_simulate_speedup_vs_interpreted": interpreted / per_cut,
        "smfe_estimate_s": ours_s,
        "smfe_estimate_speedup_vs_scipy_pairs": scipy_s / ours_s,
        "smfe_estimate_max_rel_difference_vs_scipy": difference,
    }
    print(f"simulate one 65 s cut (650 000 steps): {per_cut:.3f} s = "
          f"{DURATION / per_cut:.0f}× real time; pure Python ≈ {interpreted:.0f} s "
          f"(from {INTERPRETED_DURATION} s, scaled): {interpreted / per_cut:.0f}× faster")
    print(f"estimate from 3 cuts (Φ, cond, 9 coherences per cut): {ours_s:.2f} s; "
          f"scipy csd/coherence per pair {scipy_s:.2f} s: {scipy_s / ours_s:.1f}× faster")
    print(f"receptance, ours vs scipy-per-pair over 20–100 Hz: max difference "
          f"{difference:.1e} of max |Φ| (same Welch settings, should be rounding)")
    return figures


if __name__ == "__main__":
    run()
