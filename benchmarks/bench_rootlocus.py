"""Root locus of a 12th-order velocity loop at 2000 gains: batched companion eigenvalues
(`feedbench.analysis.rootlocus.root_locus`) against python-control's `root_locus_map` and a
per-gain `numpy.roots` loop, measured in the same run (interleaved rounds, best of each);
the roots are matched gain by gain (Hungarian assignment) and compared.

The loop: K_p (1 + 1/(T_i s)) times a pole–zero mobility (Eq. 4.27) with three modes and a
4th-order Padé delay (Eq. 4.16): 1 + 7 + 4 = 12 poles.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import control
import numpy as np
from scipy.optimize import linear_sum_assignment

from feedbench.analysis.polezero import PoleZeroModel, VibratoryMode
from feedbench.analysis.rootlocus import root_locus

MODEL = PoleZeroModel(
    m_total=34.4, sigma=792.0, delay=0.75e-3,
    modes=(VibratoryMode(85.3, 0.03, 72.6, 0.02), VibratoryMode(160.0, 0.02, 140.0, 0.015),
           VibratoryMode(310.0, 0.02, 290.0, 0.02)),
)
T_I = 5.5e-3
GAINS = np.geomspace(1e2, 1e5, 2000)
REPEATS = 5
ROOT_TOLERANCE = 1e-6
"""Stated tolerance: |ours − control| / max(|root|, 1 rad/s) for every matched root."""


def loop_polynomials() -> tuple[np.ndarray, np.ndarray]:
    """(T_i s + 1) N(s) and T_i s D(s): 1 + K_p N'/D' = 0 is the closed velocity loop."""
    mobility = MODEL.transfer_function(pade_order=4)
    return np.polymul([T_I, 1.0], mobility.num), np.polymul([T_I, 0.0], mobility.den)


def interleaved_best(
    jobs: dict[str, Callable[[], np.ndarray]],
) -> dict[str, tuple[float, np.ndarray]]:
    """Best time and last result of each job; rounds alternate the jobs so that load from other
    processes hits them alike."""
    times: dict[str, list[float]] = {name: [] for name in jobs}
    results: dict[str, np.ndarray] = {}
    for _ in range(REPEATS):
        for name, job in jobs.items():
            start = time.perf_counter()
            results[name] = job()
            times[name].append(time.perf_counter() - start)
    return {name: (min(times[name]), results[name]) for name in jobs}


def per_gain_numpy_roots(numerator: np.ndarray, denominator: np.ndarray) -> np.ndarray:
    return np.array([np.roots(np.polyadd(denominator, k * numerator)) for k in GAINS])


def matched_errors(ours: np.ndarray, theirs: np.ndarray) -> np.ndarray:
    """Relative distance of each root to its partner in the other set, gain by gain."""
    errors = np.empty(ours.shape)
    for row, (a, b) in enumerate(zip(ours, theirs)):
        distance = np.abs(a[:, None] - b[None, :])
        i, j = linear_sum_assignment(distance)
        errors[row] = distance[i, j] / np.maximum(np.abs(b[j]), 1.0)
    return errors


def run() -> dict[str, float]:
    numerator, denominator = loop_polynomials()
    system = control.tf(numerator, denominator)
    timed = interleaved_best({
        "batched": lambda: root_locus(numerator, denominator, GAINS).roots,
        "control": lambda: control.root_locus_map(system, gains=GAINS).loci,
        "numpy": lambda: per_gain_numpy_roots(numerator, denominator),
    })
    (batched_s, ours), (control_s, theirs), (numpy_s, _) = timed.values()
    errors = matched_errors(ours, theirs)
    figures = {
        "rootlocus_batched_ms": batched_s * 1e3,
        "rootlocus_control_ms": control_s * 1e3,
        "rootlocus_numpy_roots_ms": numpy_s * 1e3,
        "rootlocus_control_over_batched": control_s / batched_s,
        "rootlocus_max_rel_root_diff": float(errors.max()),
    }
    explanations = {
        "rootlocus_batched_ms": f"root_locus, order {denominator.size - 1}, {GAINS.size} gains, "
        f"best of {REPEATS}",
        "rootlocus_control_ms": "baseline: python-control root_locus_map, same loop and gains",
        "rootlocus_numpy_roots_ms": "baseline: numpy.roots once per gain",
        "rootlocus_control_over_batched": "baseline time / batched time (goal ≥ 5)",
        "rootlocus_max_rel_root_diff": f"largest matched root difference vs control, relative "
        f"(stated tolerance {ROOT_TOLERANCE:g}; "
        f"{'within' if errors.max() < ROOT_TOLERANCE else 'OUTSIDE'})",
    }
    for name, value in figures.items():
        print(f"{name:34s} {value:12.4g}  {explanations[name]}")
    return figures


if __name__ == "__main__":
    run()
