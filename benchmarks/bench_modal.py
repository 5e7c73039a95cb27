"""Modal fit of 3 modes with 1 % noise: `feedbench.analysis.modal.fit_modes` against pyEMA's
LSCF (sdypy-EMA: get_poles('lscf') + select_closest_poles + get_constants, LSFD), on the same
data, measured in the same run (interleaved rounds; per seed the best of 3, then the median).

Data: point receptances on 0–100 Hz at 0.125 Hz with complex Gaussian noise of rms 1 % of |H|
on every line, several noise seeds:
- "separate": 35.7 Hz ζ 3 % 24.4 N/µm (Table 3.1), 61.3 Hz ζ 2 % 30 N/µm, 75 Hz ζ 1.5 % 50 N/µm;
- "close": 32 Hz ζ 2 %, 35.7 Hz ζ 3 %, 36.41 Hz (2 % above) ζ 1.5 %.
pyEMA is given the true natural frequencies as its starting guesses (f_window 4 Hz, polynomial
order 30, band 20–90 Hz); ours is given only the band and the number of modes.
"""

from __future__ import annotations

import contextlib
import io
import statistics
import time
import warnings

import numpy as np
import pyEMA

from feedbench.analysis.modal import fit_modes

SYSTEMS = {
    # f_n (Hz), ζ, modal stiffness (N/m)
    "separate": (np.array([35.7, 61.3, 75.0]), np.array([0.03, 0.02, 0.015]),
                 np.array([24.4e6, 30e6, 50e6])),
    "close": (np.array([32.0, 35.7, 1.02 * 35.7]), np.array([0.02, 0.03, 0.015]),
              np.array([40e6, 24.4e6, 30e6])),
}
F = np.arange(0.0, 100.0 + 1e-9, 0.125)
BAND = (20.0, 90.0)
SEEDS = range(5)
REPEATS = 3
NOISE = 0.01
GOALS = {"separate": {"f": 0.001, "zeta": 0.01}, "close": {"f": 0.005, "zeta": 0.05}}
"""Relative accuracy goals: pyEMA's figures on separate modes (f_n 0.1 %, ζ 1 %); the issue's
test tolerance for modes 2 % apart (f_n 0.5 %, ζ 5 %)."""


def noisy_receptance(f_n, zeta, k, seed: int) -> np.ndarray:
    w = 2 * np.pi * F[:, None]
    m = k / (2 * np.pi * f_n) ** 2
    H = np.sum(1.0 / (k - m * w**2 + 2j * zeta * np.sqrt(k * m) * w), axis=1)
    rng = np.random.default_rng(seed)
    unit = (rng.standard_normal(F.size) + 1j * rng.standard_normal(F.size)) / np.sqrt(2)
    return H + NOISE * np.abs(H) * unit


def ours(H: np.ndarray, f_n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    fit = fit_modes(F, H, BAND, f_n.size)
    return np.array([m.f_n for m in fit.modes]), np.array([m.zeta for m in fit.modes])


def pyema_lscf(H: np.ndarray, f_n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    with warnings.catch_warnings(), contextlib.redirect_stderr(io.StringIO()):
        warnings.simplefilter("ignore")
        model = pyEMA.Model(frf=H[None], freq=F, lower=BAND[0], upper=BAND[1], pol_order_high=30,
                            frf_form="receptance")
        model.get_poles(method="lscf", show_progress=False)
        model.select_closest_poles(list(f_n), f_window=4)
        model.get_constants(whose_poles="own", f_lower=BAND[0], f_upper=BAND[1])
    return np.asarray(model.nat_freq), np.asarray(model.nat_xi)


def compare(system: str) -> dict[str, dict[str, float]]:
    """Per method: median over seeds of the best of REPEATS wall-clock and CPU times (rounds
    alternate the methods so load from other processes hits both alike), and the worst
    relative f_n and ζ errors over seeds and modes."""
    f_n, zeta, k = SYSTEMS[system]
    methods = {"ours": ours, "pyema": pyema_lscf}
    walls = {name: [] for name in methods}
    cpus = {name: [] for name in methods}
    errors = {name: {"f": 0.0, "zeta": 0.0} for name in methods}
    for seed in SEEDS:
        H = noisy_receptance(f_n, zeta, k, seed)
        rounds = {name: [] for name in methods}
        for _ in range(REPEATS):
            for name, method in methods.items():
                wall, cpu = time.perf_counter(), time.process_time()
                found_f, found_zeta = method(H, f_n)
                rounds[name].append((time.perf_counter() - wall, time.process_time() - cpu))
        for name, method in methods.items():
            walls[name].append(min(r[0] for r in rounds[name]))
            cpus[name].append(min(r[1] for r in rounds[name]))
            found_f, found_zeta = method(H, f_n)
            errors[name]["f"] = max(errors[name]["f"], _worst(found_f, f_n))
            errors[name]["zeta"] = max(errors[name]["zeta"], _worst(found_zeta, zeta))
    return {
        name: {"s": statistics.median(walls[name]), "cpu_s": statistics.median(cpus[name]),
               **errors[name]}
        for name in methods
    }


def _verdict(ok: bool) -> str:
    return "met" if ok else "NOT met"


def _worst(found: np.ndarray, truth: np.ndarray) -> float:
    return float(np.max(np.abs(found / truth - 1))) if found.size == truth.size else float("inf")


def run() -> dict[str, float]:
    figures, explanations = {}, {}
    for system in SYSTEMS:
        result = compare(system)
        for name, label in (("ours", "fit_modes"), ("pyema", "pyEMA LSCF")):
            figures[f"modal_{system}_{name}_ms"] = result[name]["s"] * 1e3
            explanations[f"modal_{system}_{name}_ms"] = (
                f"{label}, {system} modes, median over {len(SEEDS)} seeds of the best of {REPEATS}"
            )
            for quantity in ("f", "zeta"):
                key = f"modal_{system}_{name}_max_{quantity}_err_pct"
                figures[key] = result[name][quantity] * 100
                goal = GOALS[system][quantity]
                explanations[key] = (
                    f"{label}: worst relative {quantity} error over seeds and modes, % "
                    f"(goal ≤ {goal * 100:g} %; {_verdict(result[name][quantity] <= goal)})"
                )
        key = f"modal_{system}_pyema_over_ours"
        figures[key] = result["pyema"]["s"] / result["ours"]["s"]
        explanations[key] = (
            f"pyEMA time / our time, wall clock (goal ≥ 1; {_verdict(figures[key] >= 1)})"
        )
        figures[f"{key}_cpu"] = result["pyema"]["cpu_s"] / result["ours"]["cpu_s"]
        explanations[f"{key}_cpu"] = "the same ratio in CPU time (less sensitive to other load)"
    for name, value in figures.items():
        print(f"{name:38s} {value:10.4g}  {explanations[name]}")
    return figures


if __name__ == "__main__":
    run()
