"""ZOA stability lobes at 2000 spindle speeds: `zoa_lobes` against a per-speed Python loop.

Both solve det(I − a (1 − e^{−iωT}) A0 Φ(ω)) = 0 for the same 2-D receptance with cross
terms (two modes 37° off the axes, 0.05 Hz grid from 10 to 200 Hz), down-milling slot,
Z = 2, Table 6.1 coefficients. `zoa_lobes` maps every (frequency, eigenvalue, lobe) to a
speed once and reduces over the speeds with array operations; the baseline loops over the
speeds and, at each, takes the eigenvalues of the loop matrix on the whole frequency grid
and interpolates where the depth a = 1/μ turns real.
"""

from __future__ import annotations

import numpy as np

from feedbench.analysis.stability import directional_matrix, zoa_lobes
from feedbench.models.structure import ModalStructure

from _timing import best_of, print_figures  # benchmarks/_timing.py

STRUCTURE = ModalStructure(
    f_n=[48.0, 61.0], zeta=[0.03, 0.04], k=[30e6, 40e6], shapes=[[0.8, -0.6], [0.6, 0.8]],
)
FREQUENCIES = np.arange(10.0, 200.0, 0.05)
SPEEDS = np.linspace(500.0, 1600.0, 2000)
N_TEETH, K_T, K_R = 2, 1889e6, 806.0 / 1889.0
PHI_ST, PHI_EX = 0.0, np.pi
N_LOBES = 20
REPEATS = 5
LOOP_STRIDE = 10
"""The baseline runs on every 10th speed (200) and is scaled to 2000: it costs ≈ 17 ms a speed."""


def per_speed_loop(f: np.ndarray, Phi: np.ndarray, speeds: np.ndarray) -> np.ndarray:
    """Baseline: for each speed, eigenvalues μ of (1 − e^{−iωT}) A0 Φ on the grid; the depth
    is where a = 1/μ crosses the real axis with a > 0 (linear interpolation in ω)."""
    A0Phi = N_TEETH * K_T / (4.0 * np.pi) * directional_matrix(K_R, PHI_ST, PHI_EX) @ Phi
    depth = np.full(speeds.size, np.inf)
    for index, rpm in enumerate(speeds):
        regeneration = 1.0 - np.exp(-2j * np.pi * f * 60.0 / (N_TEETH * rpm))
        with np.errstate(divide="ignore", invalid="ignore"):
            a = 1.0 / np.linalg.eigvals(regeneration[:, None, None] * A0Phi)
        start, end = a[:-1], a[1:]
        swap = np.abs(start - end[:, ::-1]).sum(axis=1) < np.abs(start - end).sum(axis=1)
        end = np.where(swap[:, None], end[:, ::-1], end)
        real_axis = (start.imag * end.imag <= 0.0) & (start.real > 0.0) & (end.real > 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = start.imag / (start.imag - end.imag)
        candidates = (start.real + t * (end.real - start.real))[real_axis & np.isfinite(t)]
        if candidates.size:
            depth[index] = candidates.min()
    return depth


def run() -> dict[str, float]:
    Phi = STRUCTURE.receptance(FREQUENCIES)
    zoa_s, lobes = best_of(lambda: zoa_lobes(
        FREQUENCIES, Phi, SPEEDS, N_TEETH, K_T, K_R, PHI_ST, PHI_EX, N_LOBES), REPEATS)
    subset = SPEEDS[::LOOP_STRIDE]
    loop_s, loop_depth = best_of(lambda: per_speed_loop(FREQUENCIES, Phi, subset), 1)
    loop_s *= SPEEDS.size / subset.size
    zoa_depth = lobes.depth[::LOOP_STRIDE]
    both = np.isfinite(zoa_depth) & np.isfinite(loop_depth)
    figures = {
        "zoa_2000_speeds_ms": zoa_s * 1e3,
        "per_speed_loop_ms": loop_s * 1e3,
        "per_speed_loop_over_zoa": loop_s / zoa_s,
        "zoa_vs_loop_max_rel_diff": float(np.max(np.abs(zoa_depth[both] / loop_depth[both] - 1.0))),
        "zoa_min_depth_mm": lobes.min_depth * 1e3,
    }
    explanations = {
        "zoa_2000_speeds_ms": f"zoa_lobes, {SPEEDS.size} speeds × {FREQUENCIES.size} frequencies "
        f"× {N_LOBES} lobes, best of {REPEATS} (goal < 100 ms)",
        "per_speed_loop_ms": f"baseline: Python loop over the speeds, eigvals on the grid at "
        f"each; timed on {subset.size} speeds, scaled to {SPEEDS.size}",
        "per_speed_loop_over_zoa": "baseline time / zoa_lobes time",
        "zoa_vs_loop_max_rel_diff": f"largest relative depth difference over the "
        f"{int(both.sum())} speeds both resolve (interpolation in speed vs in frequency)",
        "zoa_min_depth_mm": "absolute stability limit over the speeds (mm), for reference",
    }
    print_figures(figures, explanations, 28, "12.4g")
    return figures


if __name__ == "__main__":
    run()
