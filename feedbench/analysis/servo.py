"""Servo dynamics of a P-PI cascade on a flexible axis (thesis Ch. 4.2–4.3).

Frequency-domain functions take frequencies in Hz and return complex arrays; state-space
functions return the matrices (A, B, C, D). SI units throughout: N, m, s, kg.
"""

from __future__ import annotations

from collections.abc import Sequence
from math import comb, factorial

import numpy as np
import scipy
from numpy.typing import ArrayLike, NDArray

ComplexArray = NDArray[np.complex128]
RealArray = NDArray[np.float64]
StateSpace = tuple[RealArray, RealArray, RealArray, RealArray]

POSITION, VELOCITY, ACCELERATION = 0, 1, 2
"""Derivative order of an output in `lumped_state_space`."""


def laplace(frequency: ArrayLike) -> ComplexArray:
    """s = j·2πf for frequencies in Hz."""
    return 2j * np.pi * np.asarray(frequency, dtype=float)


def velocity_pi(frequency: ArrayLike, K_p: float, T_i: float) -> ComplexArray:
    """Velocity PI K_p (1 + 1/(T_i jω)) in N/(m/s), Eqs. (4.20, 4.21); T_i = inf gives P only."""
    return K_p * (1.0 + (1.0 / T_i) / laplace(frequency))


def open_loop_mobility(
    frequency: ArrayLike, closed_velocity: ArrayLike, K_p: float, T_i: float
) -> ComplexArray:
    """Open-loop mobility ẋ_mot/F_mot (m/(N·s)) from a closed velocity loop ẋ_mot/ẋ_ref, Eq. (4.20).

    Whatever the loop contains besides the PI (current loop, filters, sampling delay) stays
    inside the returned mobility.
    """
    closed = np.asarray(closed_velocity, dtype=complex)
    return closed / (velocity_pi(frequency, K_p, T_i) * (1.0 - closed))


def closed_velocity_loop(
    frequency: ArrayLike, mobility: ArrayLike, K_p: float, T_i: float
) -> ComplexArray:
    """Closed velocity loop ẋ_mot/ẋ_ref for new gains K_p (N·s/m), T_i (s), Eq. (4.21)."""
    open_loop = np.asarray(mobility, dtype=complex) * velocity_pi(frequency, K_p, T_i)
    return open_loop / (1.0 + open_loop)


def closed_position_loop(
    frequency: ArrayLike, closed_velocity: ArrayLike, K_v: float, delay: float = 2e-3
) -> ComplexArray:
    """Closed position loop x_mot/x_ref, Eq. (4.22).

    K_v in 1/s; `delay` τ_cl in s, twice the position-loop period (default: 1 kHz loop).
    """
    s = laplace(frequency)
    forward = K_v * np.asarray(closed_velocity, dtype=complex)
    return forward / (s + forward) * np.exp(-delay * s)


def mobility_to_compliance(frequency: ArrayLike, mobility: ArrayLike) -> ComplexArray:
    """Compliance x/F (m/N) from mobility ẋ/F: integrate once in time, divide by jω."""
    return np.asarray(mobility, dtype=complex) / laplace(frequency)


def pade_delay(delay: float, order: int) -> scipy.signal.TransferFunction:
    """Padé approximation P_d(s) of e^{-τs} of order L, Eq. (4.16).

    Closed-form diagonal coefficients a_k = (2L−k)! L! / ((2L)! k! (L−k)!) τ^k; scipy only
    offers `interpolate.pade` from Taylor series, which loses accuracy at high order.
    """
    a = np.array([
        comb(order, k) / comb(2 * order, k) * delay**k / factorial(k) for k in range(order + 1)
    ])
    alternating = a * (-1.0) ** np.arange(order + 1)
    return scipy.signal.TransferFunction(alternating[::-1], a[::-1])


def with_delay(
    system: scipy.signal.TransferFunction, delay: float, order: int
) -> scipy.signal.TransferFunction:
    """system(s)·P_d(s): a rational model of a delayed system for root loci, Eq. (4.16)."""
    pade = pade_delay(delay, order)
    return scipy.signal.TransferFunction(
        np.polymul(system.num, pade.num), np.polymul(system.den, pade.den)
    )


def chain_matrices(
    masses: Sequence[float],
    stiffnesses: Sequence[float],
    dampings: Sequence[float],
    ground_damping: float = 0.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Mass, damping and stiffness matrices (M, C, K) of a serial mass–spring chain.

    Spring i (N/m) and damper i (N·s/m) join mass i and mass i+1 (kg); mass 0 is the motor
    and carries the viscous guideway friction σ = `ground_damping` (N·s/m), as in Eq. (4.15).
    """
    n = len(masses)
    if len(stiffnesses) != n - 1 or len(dampings) != n - 1:
        raise ValueError("stiffnesses and dampings need one value per link (len(masses) - 1)")
    link = np.zeros((n - 1, n))
    link[np.arange(n - 1), np.arange(n - 1)] = 1.0
    link[np.arange(n - 1), np.arange(1, n)] = -1.0
    stiffness = link.T @ np.diag(stiffnesses) @ link
    damping = link.T @ np.diag(dampings) @ link
    damping[0, 0] += ground_damping
    return np.diag(np.asarray(masses, dtype=float)), damping, stiffness


def lumped_state_space(
    mass: ArrayLike,
    damping: ArrayLike,
    stiffness: ArrayLike,
    force_dofs: Sequence[int],
    outputs: Sequence[tuple[int, int]],
) -> StateSpace:
    """State space of M ẍ + C ẋ + K x = B_f F with state [x, ẋ], Eq. (4.17) in general form.

    `force_dofs`: the DOF each input force acts on. `outputs`: (dof, derivative) pairs with
    derivative POSITION, VELOCITY or ACCELERATION.
    """
    mass_inv = np.linalg.inv(np.asarray(mass, dtype=float))
    n = mass_inv.shape[0]
    force_map = np.zeros((n, len(force_dofs)))
    force_map[list(force_dofs), np.arange(len(force_dofs))] = 1.0
    a = np.block([
        [np.zeros((n, n)), np.eye(n)],
        [-mass_inv @ np.asarray(stiffness, float), -mass_inv @ np.asarray(damping, float)],
    ])
    b = np.vstack([np.zeros((n, len(force_dofs))), mass_inv @ force_map])
    c = np.zeros((len(outputs), 2 * n))
    d = np.zeros((len(outputs), len(force_dofs)))
    for row, (dof, derivative) in enumerate(outputs):
        if derivative == ACCELERATION:
            c[row], d[row] = a[n + dof], b[n + dof]
        else:
            c[row, derivative * n + dof] = 1.0
    return a, b, c, d


def three_dof_state_space(
    M_mot: float,
    M_2: float,
    M_tip: float,
    k_1: float,
    k_2: float,
    c_1: float,
    c_2: float,
    sigma: float = 0.0,
) -> StateSpace:
    """3-DOF feed drive x_mot/F_mot, Eqs. (4.17–4.19): motor–k_1,c_1–M_2–k_2,c_2–tip.

    State [x_mot, x_2, x_tip, ẋ_mot, ẋ_2, ẋ_tip]; input F_mot (N); output x_mot (m).
    """
    m, c, k = chain_matrices([M_mot, M_2, M_tip], [k_1, k_2], [c_1, c_2], sigma)
    return lumped_state_space(m, c, k, force_dofs=[0], outputs=[(0, POSITION)])


def state_space_frf(system: StateSpace, frequency: ArrayLike) -> ComplexArray:
    """C (sI − A)^-1 B + D at every frequency (Hz), shape (n_freq, n_out, n_in), Eq. (4.19).

    scipy.signal.freqresp handles SISO systems only; this solves all frequencies at once.
    """
    a, b, c, d = system
    s = laplace(np.atleast_1d(frequency))
    resolvent = s[:, None, None] * np.eye(a.shape[0]) - a
    return c @ np.linalg.solve(resolvent, np.broadcast_to(b, (s.size, *b.shape))) + d


def chain_mobility(
    masses: Sequence[float],
    stiffnesses: Sequence[float],
    dampings: Sequence[float],
    ground_damping: float = 0.0,
) -> scipy.signal.TransferFunction:
    """Rational motor mobility ẋ_mot/F_mot (m/(N·s)) of a serial chain (see `chain_matrices`).

    Realised on link deflections and velocities, so the rigid-body position mode that
    s·X_mot/F_mot would cancel never appears; for two masses this is s times Eq. (4.15)
    without the delay.
    """
    mass, damping, _ = chain_matrices(masses, stiffnesses, dampings, ground_damping)
    n = mass.shape[0]
    link = np.eye(n - 1, n) - np.eye(n - 1, n, k=1)
    mass_inv = np.linalg.inv(mass)
    a = np.block([
        [np.zeros((n - 1, n - 1)), link],
        [-mass_inv @ link.T @ np.diag(stiffnesses), -mass_inv @ damping],
    ])
    b = np.concatenate([np.zeros(n - 1), mass_inv[:, 0]])[:, None]
    c = np.eye(1, 2 * n - 1, n - 1)
    numerator, denominator = scipy.signal.ss2tf(a, b, c, np.zeros((1, 1)))
    return scipy.signal.TransferFunction(np.trim_zeros(numerator[0], "f"), denominator)
