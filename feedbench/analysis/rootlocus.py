"""Root loci of the P-PI cascade on a rational mobility model and the search for the gains
that maximise the damping of the critical structural mode (thesis Ch. 4.2.3, 4.3.3).

The mobility N(s)/D(s) (m/(N·s)) comes from `polezero.PoleZeroModel.transfer_function` or
`servo.chain_mobility` + `servo.with_delay`; the delay enters as a Padé approximation (4.16).
Roots are in rad/s.
"""

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import optimize, signal

from feedbench.analysis.servo import ComplexArray, pade_delay
from feedbench.models.axis import CascadeGains

Coefficients = NDArray[np.float64]
"""Polynomial coefficients, highest power first; batched along the leading axes."""


def polynomial_roots(coefficients: ArrayLike) -> ComplexArray:
    """Roots of many polynomials at once, shape (..., degree).

    Eigenvalues of batched companion matrices (LAPACK balances them); numpy's `roots` takes
    one polynomial per call, which makes a 2000-gain locus ≈ 7× slower.
    """
    c = np.asarray(coefficients, dtype=float)
    degree = c.shape[-1] - 1
    companion = np.zeros((*c.shape[:-1], degree, degree))
    companion[..., 0, :] = -c[..., 1:] / c[..., :1]
    companion[..., np.arange(1, degree), np.arange(degree - 1)] = 1.0
    return np.linalg.eigvals(companion)


def _padded(polynomial: ArrayLike, length: int) -> Coefficients:
    p = np.atleast_1d(np.asarray(polynomial, dtype=float))
    return np.concatenate([np.zeros(length - p.size), p])


def _combine(terms: list[tuple[NDArray[np.float64], ArrayLike]]) -> Coefficients:
    """Σ weight_i · polynomial_i with weights broadcast over a batch of gain sets."""
    length = max(np.size(p) for _, p in terms)
    return sum(np.asarray(w, float)[..., None] * _padded(p, length) for w, p in terms)


@dataclass(frozen=True)
class RootLocus:
    """Closed-loop roots (rad/s), one row per gain; columns unordered unless matched."""

    gains: NDArray[np.float64]
    roots: ComplexArray


def root_locus(numerator: ArrayLike, denominator: ArrayLike, gains: ArrayLike) -> RootLocus:
    """Roots of D(s) + k N(s) for each gain k: the locus of 1 + k N/D = 0."""
    k = np.asarray(gains, dtype=float)
    characteristic = _combine([(np.ones_like(k), denominator), (k, numerator)])
    return RootLocus(gains=k, roots=polynomial_roots(characteristic))


def match_branches(roots: ArrayLike) -> ComplexArray:
    """Reorder each row's roots so that every column follows one continuous branch.

    Row 0 keeps its order; each later row is assigned to the previous one by the least total
    distance. Each row is first sorted by value, so that ties (a conjugate pair leaving the
    real axis is equidistant from the real root before it) are broken the same way whatever
    order the eigenvalue solver returned the roots in.
    """
    matched = np.array(roots, dtype=complex)
    for row in range(1, matched.shape[0]):
        candidates = np.sort_complex(matched[row])
        distance = np.abs(matched[row - 1][:, None] - candidates[None, :])
        _, order = optimize.linear_sum_assignment(distance)
        matched[row] = candidates[order]
    return matched


def velocity_loop_characteristic(
    mobility: signal.TransferFunction, K_p: ArrayLike, T_i: ArrayLike
) -> Coefficients:
    """T_i s D(s) + K_p (T_i s + 1) N(s): the denominator of Eq. (4.21) for the model N/D."""
    n, d = mobility.num, mobility.den
    return _combine([
        (np.asarray(T_i), np.polymul([1.0, 0.0], d)),
        (np.asarray(K_p) * T_i, np.polymul([1.0, 0.0], n)),
        (np.asarray(K_p), n),
    ])


def cascade_characteristic(
    mobility: signal.TransferFunction,
    K_p: ArrayLike,
    T_i: ArrayLike,
    K_v: ArrayLike,
    position_delay: float = 0.0,
    pade_order: int = 2,
) -> Coefficients:
    """Characteristic polynomial of the P-PI cascade, 1 − H_x,F K = 0 with K of Eq. (4.24).

    T_i s² D P_den + K_p (T_i s + 1) N (s P_den + K_v P_num), with P = P_num/P_den the Padé
    approximation of the position loop's sampling delay (P = 1 when `position_delay` is 0).
    K_p, T_i, K_v broadcast against each other (one polynomial per gain set).
    """
    n, d = mobility.num, mobility.den
    no_delay = signal.TransferFunction(1.0, 1.0)
    pade = pade_delay(position_delay, pade_order) if position_delay > 0 else no_delay
    p_num, p_den = pade.num, pade.den
    k_p, t_i, k_v = np.broadcast_arrays(*(np.asarray(g, dtype=float) for g in (K_p, T_i, K_v)))
    s_p_den_n = np.polymul([1.0, 0.0], np.polymul(p_den, n))
    p_num_n = np.polymul(p_num, n)
    return _combine([
        (t_i, np.polymul([1.0, 0.0, 0.0], np.polymul(d, p_den))),
        (k_p * t_i, np.polymul([1.0, 0.0], s_p_den_n)),
        (k_p, s_p_den_n),
        (k_p * k_v * t_i, np.polymul([1.0, 0.0], p_num_n)),
        (k_p * k_v, p_num_n),
    ])


def velocity_gain_locus(mobility: signal.TransferFunction, T_i: float, K_p: ArrayLike) -> RootLocus:
    """Closed velocity-loop roots as K_p (N·s/m) varies at fixed T_i (s)."""
    k_p = np.asarray(K_p, dtype=float)
    characteristic = velocity_loop_characteristic(mobility, k_p, T_i)
    return RootLocus(gains=k_p, roots=polynomial_roots(characteristic))


def position_gain_locus(
    mobility: signal.TransferFunction,
    gains: CascadeGains,
    K_v: ArrayLike,
    position_delay: float = 0.0,
    pade_order: int = 2,
) -> RootLocus:
    """Closed position-loop roots as K_v (1/s) varies at the velocity loop's K_p and T_i."""
    k_v = np.asarray(K_v, dtype=float)
    characteristic = cascade_characteristic(
        mobility, gains.K_p, gains.T_i, k_v, position_delay, pade_order
    )
    return RootLocus(gains=k_v, roots=polynomial_roots(characteristic))


def damping_ratios(roots: ArrayLike) -> NDArray[np.float64]:
    """ζ = −Re(s)/|s| of each root; 0 for a root at the origin (marginally stable)."""
    r = np.asarray(roots, dtype=complex)
    magnitude = np.abs(r)
    return np.divide(-r.real, magnitude, out=np.zeros(r.shape), where=magnitude > 0)


def _in_band_damping(roots: ComplexArray, band: tuple[float, float]) -> NDArray[np.float64]:
    """ζ of each root whose natural frequency |s|/2π lies in `band` (Hz), +inf elsewhere."""
    natural = np.abs(roots) / (2 * np.pi)
    return np.where((natural >= band[0]) & (natural <= band[1]), damping_ratios(roots), np.inf)


def critical_damping(roots: ArrayLike, band: tuple[float, float]) -> NDArray[np.float64]:
    """Damping of the critical structural mode per row of roots.

    The least-damped root whose natural frequency |s|/2π lies in `band` (Hz); a row with any
    root in the right half-plane gets its most negative damping instead (unstable).
    """
    r = np.asarray(roots, dtype=complex)
    overall_minimum = damping_ratios(r).min(axis=-1)
    return np.where(overall_minimum < 0, overall_minimum, _in_band_damping(r, band).min(axis=-1))


def critical_root(roots: ArrayLike, band: tuple[float, float]) -> ComplexArray:
    """The least-damped root in `band` (Hz) per row (rad/s), NaN where no root lies in it."""
    r = np.asarray(roots, dtype=complex)
    zeta = _in_band_damping(r, band)
    index = np.argmin(zeta, axis=-1)[..., None]
    root = np.take_along_axis(r, index, axis=-1)[..., 0]
    return np.where(np.isfinite(np.take_along_axis(zeta, index, axis=-1)[..., 0]), root, np.nan)


@dataclass(frozen=True)
class DampingOptimum:
    """Gains maximising the critical-mode damping and that damping ratio."""

    gains: CascadeGains
    damping: float


@dataclass(frozen=True)
class GainBounds:
    """Search box (SI): K_p in N·s/m, T_i in s, K_v in 1/s; equal ends fix a gain."""

    K_p: tuple[float, float]
    T_i: tuple[float, float]
    K_v: tuple[float, float]

    def log_box(self) -> NDArray[np.float64]:
        return np.log(np.array([self.K_p, self.T_i, self.K_v], dtype=float))


def critical_damping_of_gains(
    mobility: signal.TransferFunction,
    K_p: ArrayLike,
    T_i: ArrayLike,
    K_v: ArrayLike,
    band: tuple[float, float],
    position_delay: float = 0.0,
    pade_order: int = 2,
) -> NDArray[np.float64]:
    """Critical-mode damping of the closed cascade for each gain set (broadcast arrays)."""
    characteristic = cascade_characteristic(mobility, K_p, T_i, K_v, position_delay, pade_order)
    return critical_damping(polynomial_roots(characteristic), band)


def maximise_critical_damping(
    mobility: signal.TransferFunction,
    band: tuple[float, float],
    bounds: GainBounds,
    position_delay: float = 0.0,
    pade_order: int = 2,
    seed: int = 0,
) -> DampingOptimum:
    """Gains (K_p, T_i, K_v) within `bounds` that maximise the critical-mode damping.

    The objective is a max–min over poles (flat ridges, kinks where two poles trade places),
    so a local method stalls; scipy's differential evolution searches the log-gain box
    globally, each generation evaluated in one batched eigenvalue call. Deterministic for a
    given `seed`.
    """
    box = bounds.log_box()
    free = box[:, 1] > box[:, 0]

    def negative_damping(free_log_gains: NDArray[np.float64]) -> NDArray[np.float64]:
        log_gains = np.repeat(box[:, :1], free_log_gains.shape[-1], axis=1)
        log_gains[free] = free_log_gains
        k_p, t_i, k_v = np.exp(log_gains)
        return -critical_damping_of_gains(mobility, k_p, t_i, k_v, band, position_delay, pade_order)

    result = optimize.differential_evolution(
        negative_damping, box[free], vectorized=True, updating="deferred", popsize=20,
        tol=1e-4, maxiter=1000, polish=False, rng=seed,
    )
    best = box[:, 0].copy()
    best[free] = result.x
    k_p, t_i, k_v = map(float, np.exp(best))
    return DampingOptimum(gains=CascadeGains(K_p=k_p, T_i=t_i, K_v=k_v), damping=-float(result.fun))
