"""Linear fractional transformations on measured FRFs (Eq. 3.7) and the tool-tip compliance
under a P-PI controller (Eqs. 4.23–4.26).

FRF matrices are complex arrays of shape (n_freq, n_out, n_in); SISO FRFs are 1-D arrays over
frequency. Compliances in m/N, controllers in N/m. python-control only offers the LFT of
state-space models (`StateSpace.lft`), not of measured frequency data, hence these functions.
"""

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from feedbench.analysis.servo import ComplexArray, laplace, velocity_pi
from feedbench.models.axis import CascadeGains


def _partition(plant: ArrayLike, controller: ArrayLike) -> tuple[ComplexArray, ...]:
    """Split G into G11, G12, G21, G22 by the shape of K (n_p × n_q), Eq. (3.5)."""
    g = np.asarray(plant, dtype=complex)
    n_p, n_q = np.shape(controller)[-2:]
    n_z, n_w = g.shape[-2] - n_q, g.shape[-1] - n_p
    if n_z < 0 or n_w < 0:
        raise ValueError(f"plant shape {g.shape[-2:]} too small for a {n_p}×{n_q} controller")
    return g[..., :n_z, :n_w], g[..., :n_z, n_w:], g[..., n_z:, :n_w], g[..., n_z:, n_w:]


def _closed_loop_gain(g22: ComplexArray, controller: ComplexArray) -> ComplexArray:
    """K (I − G22 K)^-1, the feedback term shared by Eqs. (3.7) and (4.23)."""
    identity = np.eye(g22.shape[-2])
    return controller @ np.linalg.inv(identity - g22 @ controller)


def lower_lft(plant: ArrayLike, controller: ArrayLike) -> ComplexArray:
    """F_l(G, K) = G11 + G12 K (I − G22 K)^-1 G21, Eq. (3.7), frequency by frequency.

    `plant` maps [w; p] to [z; q], shape (n_freq, n_z + n_q, n_w + n_p); `controller` maps
    q to p, shape (n_freq, n_p, n_q). Returns z/w, shape (n_freq, n_z, n_w).
    """
    k = np.asarray(controller, dtype=complex)
    g11, g12, g21, g22 = _partition(plant, k)
    return g11 + g12 @ _closed_loop_gain(g22, k) @ g21


def lft_control_signal(plant: ArrayLike, controller: ArrayLike) -> ComplexArray:
    """Controller output per exogenous input p/w = K (I − G22 K)^-1 G21 (e.g. motor torques)."""
    k = np.asarray(controller, dtype=complex)
    _, _, g21, g22 = _partition(plant, k)
    return _closed_loop_gain(g22, k) @ g21


def pppi_feedback(
    frequency: ArrayLike, gains: CascadeGains, position_delay: float = 0.0
) -> ComplexArray:
    """P-PI cascade as a feedback F_mot = K x_mot, K = −(jω + K_v e^{-jωτ}) K_p (1 + 1/(T_i jω)).

    Eq. (4.24); `position_delay` τ (s) adds the position loop's sampling delay (0 as printed).
    """
    s = laplace(frequency)
    position_error_gain = s + gains.K_v * np.exp(-position_delay * s)
    return -position_error_gain * velocity_pi(frequency, gains.K_p, gains.T_i)


def tool_tip_compliance(
    tip_tip: ArrayLike,
    tip_mot: ArrayLike,
    mot_tip: ArrayLike,
    mot_mot: ArrayLike,
    controller: ArrayLike,
) -> ComplexArray:
    """Closed-loop x_tip/F_tip from the open-loop compliances and K, Eq. (4.23).

    tip_tip = x_tip/F_tip, tip_mot = x_tip/F_mot, mot_tip = x_mot/F_tip, mot_mot = x_mot/F_mot.
    """
    plant = np.stack([np.stack([tip_tip, tip_mot], -1), np.stack([mot_tip, mot_mot], -1)], -2)
    k = np.asarray(controller, dtype=complex)[..., None, None]
    return lower_lft(plant, k)[..., 0, 0]


def predict_tip_by_transmissibility(
    tip_closed_k0: ArrayLike,
    mot_tip_k0: ArrayLike,
    mot_mot: ArrayLike,
    transmissibility: ArrayLike,
    controller: ArrayLike,
) -> ComplexArray:
    """Approach #1, Eq. (4.25): tool-tip compliance under a new controller K.

    From x_tip/F_tip and x_mot/F_tip measured under a very low controller K_0 (taken as open
    loop), the open-loop motor compliance x_mot/F_mot and the transmissibility T = x_tip/x_mot
    measured with motor excitation, which gives x_tip/F_mot ≈ T·x_mot/F_mot.
    """
    k = np.asarray(controller, dtype=complex)
    g = np.asarray(mot_mot, dtype=complex)
    tip_mot = g * np.asarray(transmissibility, dtype=complex)
    feedback = tip_mot * k / (1.0 - g * k) * np.asarray(mot_tip_k0)
    return np.asarray(tip_closed_k0, dtype=complex) + feedback


@dataclass(frozen=True)
class TipTerms:
    """Open-loop tool-tip terms identified from closed-loop data, Eq. (4.26).

    direct = x_tip/F_tip (m/N); cross_product = (x_tip/F_mot)(x_mot/F_tip) (m²/N²);
    residual = largest relative equation residual per frequency (0 for two settings).
    """

    direct: ComplexArray
    cross_product: ComplexArray
    residual: NDArray[np.float64]


def estimate_tip_terms(
    tip_closed: ArrayLike, controllers: ArrayLike, mot_mot: ArrayLike
) -> TipTerms:
    """Approach #2, Eq. (4.26): solve for the direct term and the cross product frequency by
    frequency from n ≥ 2 tool-tip compliances measured under controllers K_1…K_n.

    tip_closed, controllers: shape (n, n_freq); mot_mot: open-loop x_mot/F_mot (n_freq,).
    Least squares (via the pseudo-inverse) when n > 2.
    """
    h = np.asarray(tip_closed, dtype=complex)
    k = np.asarray(controllers, dtype=complex)
    if h.shape[0] < 2 or h.shape != k.shape:
        raise ValueError("tip_closed and controllers need the same shape (n ≥ 2, n_freq)")
    rows = np.stack([1.0 / h, k / (h * (1.0 - np.asarray(mot_mot) * k))], -1).swapaxes(0, 1)
    solution = np.linalg.pinv(rows) @ np.ones((h.shape[1], h.shape[0], 1))
    residual = np.abs(rows @ solution - 1.0).max(axis=1)[:, 0]
    return TipTerms(direct=solution[:, 0, 0], cross_product=solution[:, 1, 0], residual=residual)


def predict_tip_compliance(
    terms: TipTerms, mot_mot: ArrayLike, controller: ArrayLike
) -> ComplexArray:
    """x_tip/F_tip under a new controller K from identified terms, Eq. (4.23)."""
    k = np.asarray(controller, dtype=complex)
    return terms.direct + terms.cross_product * k / (1.0 - np.asarray(mot_mot) * k)
