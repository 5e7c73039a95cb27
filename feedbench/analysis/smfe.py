"""Sweep Milling Force Excitation: receptance identification from cuts (Ch. 6.2.4–6.3.1).

- `smfe_estimate`: the MIMO estimate Φ = S_rF S_FF⁻¹ from three cuts (down-, up-, central
  milling) with Welch cross-spectra against the single reference F_x (Eqs. 6.12, 6.13), the
  condition number of the force-spectrum matrix per frequency (Eq. 6.14) and the ordinary
  coherence of every response/force pair per cut (Eq. 6.15, see `SmfeResult`).
- `cut_set_condition_number`, `optimal_radial_engagement`: the theoretical condition number
  C_th of a set of cuts from the stationary force's tooth-passing harmonic (no machine
  dynamics, Sec. 6.3.1, Figs. 6.6–6.8), and the search for the radial engagement that
  minimises it; `optimal_engagement_eq616` / `_eq617` are the thesis's fitted closed forms.

Spectra convention: S_{K,Fx} = mean over segments of conj(F_x)·K, so that S_rFx = Φ S_FFx
holds for r = Φ F (the thesis prints conj(K)·F_x, which would give conj(Φ)); this is
scipy.signal.csd(F_x, K) and the author's MATLAB cpsd(K, F_x).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import ArrayLike

from feedbench.models.milling import (
    SMFE_FEED_PER_TOOTH,
    CuttingCoefficients,
    Tool,
    cutting_forces,
    engagement_angles,
    static_chip_thickness,
)

FREQUENCY_RESOLUTION = 0.25
"""Welch resolution of the author's SMFE processing (Hz): nfft = fs / 0.25 Hz."""

OVERLAP = 0.8
"""Welch segment overlap of the author's SMFE processing (32 000 of 40 000 samples)."""

ENGAGEMENT_BOUNDS = (0.02, 0.40)
"""a_e/D range searched for the optimum; the thesis recommends 5–30 % of D (Sec. 6.3.1)."""

_GAUSS_NODES, _GAUSS_WEIGHTS = np.polynomial.legendre.leggauss(64)
"""Gauss–Legendre rule over the engaged arc: exact to rounding for the smooth tooth force."""

_SEGMENTS_PER_BLOCK = 8
"""Welch segments transformed at once (bounds memory at 8 × channels × nfft samples)."""


@dataclass(frozen=True)
class SmfeResult:
    """SMFE estimate at frequencies f (Hz, DC left out).

    Phi: receptance (m/N), n_f × d × d, Φ[f, i, j] = response i per force j (Eq. 6.13).
    condition_number: C = ν_max/ν_min of the force-spectrum matrix S_FFx per frequency (Eq. 6.14).
    coherence: ordinary coherence of response i with force j in cut c, n_cuts × n_f × d × d.
    (Eq. 6.15 as printed divides |S_iF|² sums by |S_FF|² sums, which is not dimensionless;
    the author's code computes the ordinary coherence per pair and cut, as here.)
    n_averages: Welch segments per cut.
    """

    f: np.ndarray
    Phi: np.ndarray
    condition_number: np.ndarray
    coherence: np.ndarray
    n_averages: int


@dataclass(frozen=True)
class EngagementOptimum:
    """Radial engagements a_e/D (one per cut, in the order of `modes`) minimising C_th."""

    a_e_over_D: tuple[float, ...]
    condition_number: float


def smfe_estimate(
    cuts: Sequence[tuple[ArrayLike, ArrayLike]],
    fs: float,
    nfft: int | None = None,
    overlap: float = OVERLAP,
    f_max: float | None = None,
) -> SmfeResult:
    """Receptance matrix from d cuts of d-direction force F (N) and acceleration (m/s²), Eq. (6.13).

    cuts: (F, acc) per cut, each d × n samples (d = 3: DM, UM, CM; d = 2 for a planar case).
    Welch with a Hann window of nfft samples (default fs / 0.25 Hz), `overlap` fraction, no
    detrending. Per frequency the d cuts are stacked into S_FFx (forces × cuts) and S_aFx
    (responses × cuts) and solved for the accelerance S_aFx S_FFx⁻¹, then divided by (j2πf)².
    f_max (Hz): keep only frequencies up to it (default: up to fs/2).
    """
    signals = _stacked_cuts(cuts)
    n, d = signals.shape[-1], len(signals)
    nfft = int(round(fs / FREQUENCY_RESOLUTION)) if nfft is None else int(nfft)
    if not 2 <= nfft <= n:
        raise ValueError(f"nfft: must be within 2..{n} samples (the cut length), got {nfft}")
    step = nfft - int(round(overlap * nfft))
    if not 0.0 <= overlap < 1.0 or step < 1:
        raise ValueError(
            f"overlap: must be a fraction in [0, 1) leaving ≥ 1 sample between segments, got {overlap}")
    f = scipy.fft.rfftfreq(nfft, 1.0 / fs)
    bins = np.flatnonzero((f > 0) & (f <= (np.inf if f_max is None else f_max)))  # DC: no receptance
    if bins.size == 0:
        raise ValueError(f"f_max: no frequency bin in (0, {f_max}] Hz at {fs / nfft} Hz resolution")
    spectra = np.stack([_cross_spectral_matrix(channels, nfft, step, bins) for channels in signals])
    receptance, condition_number = _mimo_receptance(spectra, f[bins])
    return SmfeResult(
        f=f[bins],
        Phi=receptance,
        condition_number=condition_number,
        coherence=_pair_coherence(spectra, d),
        n_averages=(n - nfft) // step + 1,
    )


def cut_set_condition_number(
    a_e_over_D: float | Sequence[float],
    tool: Tool,
    coeffs: CuttingCoefficients,
    modes: Sequence[str] = ("up", "down"),
    f_z: float = SMFE_FEED_PER_TOOTH,
    harmonic: int = 1,
) -> float:
    """Theoretical condition number C_th of a set of cuts (Sec. 6.3.1, Eq. 6.14 without dynamics).

    One cut per entry of `modes` (2 cuts: x, y forces; 3 cuts: x, y, z), each at a_e/D (one
    value for all, or one per cut). Per cut the stationary force's complex amplitude F at
    `harmonic` × the tooth-passing frequency gives the column conj(F_x)·F of S_FFx (Eq. 6.12);
    C_th = ν_max/ν_min of that matrix. It does not depend on the spindle speed or on a_p.
    """
    return float(np.linalg.cond(_force_spectrum_matrix(
        _harmonics_per_cut(a_e_over_D, tool, coeffs, modes, f_z, harmonic))))


def condition_number_curve(
    a_e_over_D: ArrayLike,
    tool: Tool,
    coeffs: CuttingCoefficients,
    modes: Sequence[str] = ("up", "down"),
    f_z: float = SMFE_FEED_PER_TOOTH,
    harmonic: int = 1,
) -> np.ndarray:
    """C_th at each a_e/D with equal engagement in every cut (the curves of Fig. 6.7)."""
    return np.array([cut_set_condition_number(float(a), tool, coeffs, modes, f_z, harmonic)
                     for a in np.atleast_1d(a_e_over_D)])


def optimal_radial_engagement(
    tool: Tool,
    coeffs: CuttingCoefficients,
    modes: Sequence[str] = ("up", "down"),
    f_z: float = SMFE_FEED_PER_TOOTH,
    equal: bool = True,
    bounds: tuple[float, float] = ENGAGEMENT_BOUNDS,
    n_grid: int = 77,
) -> EngagementOptimum:
    """Radial engagement(s) a_e/D within `bounds` that minimise C_th (Figs. 6.7, 6.8).

    equal=True: one engagement for all cuts (Fig. 6.7, Eq. 6.16); equal=False: one per cut
    (the global optimum of Fig. 6.8-b, Eq. 6.17). A grid of n_grid points per cut, then a
    local refinement (scipy.optimize) from the best grid point.
    """
    grid = np.linspace(*bounds, n_grid)
    if equal:
        best = int(np.argmin(condition_number_curve(grid, tool, coeffs, modes, f_z)))
        result = scipy.optimize.minimize_scalar(
            lambda a: cut_set_condition_number(a, tool, coeffs, modes, f_z),
            bounds=(grid[max(best - 1, 0)], grid[min(best + 1, n_grid - 1)]),
            method="bounded", options={"xatol": 1e-5},
        )
        return EngagementOptimum((float(result.x),) * len(modes), float(result.fun))
    start = _best_grid_combination(grid, tool, coeffs, modes, f_z)
    result = scipy.optimize.minimize(
        lambda a: cut_set_condition_number(np.clip(a, *bounds), tool, coeffs, modes, f_z),
        start, method="Nelder-Mead", options={"xatol": 1e-5, "fatol": 1e-9},
    )
    return EngagementOptimum(tuple(float(a) for a in np.clip(result.x, *bounds)), float(result.fun))


def optimal_engagement_eq616(K_r: float) -> float:
    """Optimal equal engagement a_e/D of down- and up-milling for Z = 2, Eq. (6.16).

    (21.65 K_r² − 15.75 K_r + 3.557) / (K_r² − 0.5749 K_r + 0.118) % of D; the printed
    denominator lacks the K_r of its middle term (DIGEST §2). Fitted without edge forces.
    """
    return (21.65 * K_r**2 - 15.75 * K_r + 3.557) / (K_r**2 - 0.5749 * K_r + 0.118) / 100.0


def optimal_engagement_eq617(K_r: float) -> tuple[float, float]:
    """Global optimum (a_e/D of up-milling, of down-milling) for Z = 2, Eq. (6.17)."""
    up = (14.24 * K_r**2 - 17.26 * K_r + 25.25) / (K_r**2 - 1.439 * K_r + 1.173)
    down = (23.81 * K_r**2 - 30.67 * K_r + 16.58) / (K_r**2 - 1.049 * K_r + 0.7809)
    return up / 100.0, down / 100.0


def _stacked_cuts(cuts: Sequence[tuple[ArrayLike, ArrayLike]]) -> np.ndarray:
    """cuts × (forces, responses) × samples; d cuts of d forces and d responses each."""
    stacked = [np.concatenate([np.atleast_2d(np.asarray(F, dtype=float)),
                               np.atleast_2d(np.asarray(a, dtype=float))]) for F, a in cuts]
    d = len(stacked)
    if d not in (2, 3):
        raise ValueError(f"cuts: expected 2 or 3 cuts (one per direction), got {d}")
    for i, (channels, (F, a)) in enumerate(zip(stacked, cuts)):
        if np.shape(F) != np.shape(a) or np.shape(F)[0] != d or channels.shape[1:] != stacked[0].shape[1:]:
            raise ValueError(
                f"cuts[{i}]: expected F and acc of equal shape {d} × n (n equal in every cut), "
                f"got {np.shape(F)} and {np.shape(a)}")
    return np.stack(stacked)


def _cross_spectral_matrix(channels: np.ndarray, nfft: int, step: int, bins: np.ndarray) -> np.ndarray:
    """Welch cross-spectra G[f, i, k] = mean over segments of conj(X_i) X_k at rfft `bins`.

    Hann window of nfft samples, segments `step` apart, no detrending; unscaled (every use is a
    ratio). Written out so that each channel is transformed once for all channel pairs
    (scipy.signal.csd transforms both signals again for every pair).
    """
    window = scipy.signal.get_window("hann", nfft)
    segments = sliding_window_view(channels, nfft, axis=-1)[:, ::step]
    total = np.zeros((bins.size, channels.shape[0], channels.shape[0]), dtype=complex)
    for first in range(0, segments.shape[1], _SEGMENTS_PER_BLOCK):
        X = scipy.fft.rfft(segments[:, first:first + _SEGMENTS_PER_BLOCK] * window, axis=-1)
        X = np.ascontiguousarray(np.moveaxis(X[..., bins], -1, 0))  # f × channels × segments
        total += X.conj() @ np.swapaxes(X, -1, -2)
    return total / segments.shape[1]


def _mimo_receptance(spectra: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Receptance Φ = S_aFx S_FFx⁻¹ / (j2πf)² and cond(S_FFx) per frequency, Eqs. (6.13, 6.14).

    spectra: cuts × f × channels × channels (forces first, then responses); row 0 is F_x.
    """
    d = spectra.shape[0]
    force_spectra = np.moveaxis(spectra[:, :, 0, :d], 0, -1)  # f × forces × cuts, S_{F,Fx}
    response_spectra = np.moveaxis(spectra[:, :, 0, d:], 0, -1)  # f × responses × cuts, S_{a,Fx}
    # Φ S_FFx = S_aFx  ⇔  S_FFxᵀ Φᵀ = S_aFxᵀ
    accelerance = np.swapaxes(np.linalg.solve(np.swapaxes(force_spectra, -1, -2),
                                              np.swapaxes(response_spectra, -1, -2)), -1, -2)
    receptance = accelerance / ((2j * np.pi * f) ** 2)[:, None, None]
    return receptance, np.linalg.cond(force_spectra)


def _pair_coherence(spectra: np.ndarray, d: int) -> np.ndarray:
    """γ²[c, f, i, j] = |S_{a_i F_j}|² / (S_{F_j F_j} S_{a_i a_i}) for each cut c."""
    cross = spectra[:, :, :d, d:]  # c × f × force j × response i
    force_power = np.real(np.einsum("cfjj->cfj", spectra[:, :, :d, :d]))
    response_power = np.real(np.einsum("cfii->cfi", spectra[:, :, d:, d:]))
    with np.errstate(divide="ignore", invalid="ignore"):
        gamma2 = np.abs(cross) ** 2 / (force_power[..., :, None] * response_power[..., None, :])
    return np.swapaxes(gamma2, -1, -2)


def _force_harmonic(a_e: float, mode: str, tool: Tool, coeffs: CuttingCoefficients,
                    f_z: float, harmonic: int) -> np.ndarray:
    """Complex Fourier coefficient (N per unit a_p) of the stationary force at harmonic·Z·Ω.

    (Z/2π) ∫ F_tooth(φ) e^{−j·harmonic·Z·φ} dφ over the engaged arc: the Z teeth add up
    in phase at multiples of the tooth-passing frequency.
    """
    phi_en, phi_ex = engagement_angles(a_e, tool.D, mode)
    half = 0.5 * (phi_ex - phi_en)
    phi = phi_en + half * (_GAUSS_NODES + 1.0)
    force = cutting_forces(phi[:, None], static_chip_thickness(phi, f_z, tool.kappa)[:, None],
                           1.0, tool, coeffs, phi_en, phi_ex)
    kernel = np.exp(-1j * harmonic * tool.Z * phi) * _GAUSS_WEIGHTS * half
    return tool.Z / (2.0 * np.pi) * (kernel @ force)


def _harmonics_per_cut(a_e_over_D, tool, coeffs, modes, f_z, harmonic) -> np.ndarray:
    """Force harmonics of the first len(modes) directions, directions × cuts."""
    d = len(modes)
    if d not in (2, 3):
        raise ValueError(f"modes: expected 2 or 3 cuts, got {modes}")
    engagements = np.broadcast_to(np.asarray(a_e_over_D, dtype=float), (d,))
    return np.stack([_force_harmonic(a * tool.D, mode, tool, coeffs, f_z, harmonic)[:d]
                     for a, mode in zip(engagements, modes)], axis=-1)


def _force_spectrum_matrix(harmonics: np.ndarray) -> np.ndarray:
    """S_FFx of periodic cuts: column c is conj(F_x,c)·F_c (Eq. 6.12); harmonics: ... × d × cuts."""
    return np.conj(harmonics[..., :1, :]) * harmonics


def _best_grid_combination(grid, tool, coeffs, modes, f_z) -> np.ndarray:
    """Grid point (one engagement per cut) with the smallest C_th."""
    d = len(modes)
    per_cut = [np.stack([_force_harmonic(a * tool.D, mode, tool, coeffs, f_z, 1)[:d] for a in grid])
               for mode in modes]
    combinations = np.array(list(itertools.product(range(grid.size), repeat=d)))
    harmonics = np.stack([per_cut[c][combinations[:, c]] for c in range(d)], axis=-1)
    best = combinations[int(np.argmin(np.linalg.cond(_force_spectrum_matrix(harmonics))))]
    return grid[best]
