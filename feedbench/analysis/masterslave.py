"""Master–slave rack-and-pinion drive with electronic preload in the frequency domain
(thesis Ch. 3.3): the velocity-loop controller matrix (3.11–3.18), the velocity- and
position-loop LFTs (3.19, 3.20) and the pseudo-open-loop extraction (3.21–3.25).

Signals: exogenous w = [F_tip, ẋ_ref, τ_p]; controller outputs p = [τ_m, τ_s]; controller
inputs q = [ẋ_ref, τ_p, φ̇_m, φ̇_s]. FRF matrices have shape (n_freq, n_out, n_in).
"""

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from feedbench.analysis.lft import lft_control_signal, lower_lft
from feedbench.analysis.servo import ComplexArray, laplace

EXOGENOUS_INPUTS = ("F_tip", "x_ref_dot", "tau_p")
CONTROLLER_INPUTS = ("x_ref_dot", "tau_p", "phi_m_dot", "phi_s_dot")
TORQUES = ("tau_m", "tau_s")


@dataclass(frozen=True)
class PIController:
    """K_p (1 + 1/(T_i s)), Eqs. (3.8–3.10); T_i = inf gives a P controller."""

    K_p: float
    T_i: float = np.inf

    def response(self, s: ComplexArray) -> ComplexArray:
        return self.K_p * (1.0 + (1.0 / self.T_i) / s)


@dataclass(frozen=True)
class MasterSlaveController:
    """The three velocity-loop PIs, the torque weighting factors and the loop's sample rate (Hz).

    K_Tm = K_Ts = 0.5 shares the load equally between identical motors (Ch. 3.2).
    """

    master: PIController
    slave: PIController
    preload: PIController
    K_Tm: float = 0.5
    K_Ts: float = 0.5
    sample_rate: float = 8000.0


def tustin_laplace(frequency: ArrayLike, sample_rate: float) -> ComplexArray:
    """The s at which a continuous controller, Tustin-discretised at `sample_rate`, is evaluated.

    Tustin maps z = e^{jωT} to s = (2/T) j tan(ωT/2); substituting it into the continuous law
    gives the discretised controller's frequency response exactly.
    """
    f = np.asarray(frequency, dtype=float)
    return 2j * sample_rate * np.tan(np.pi * f / sample_rate)


def velocity_controller_matrix(
    frequency: ArrayLike, controller: MasterSlaveController
) -> ComplexArray:
    """K_vel: [τ_m, τ_s] per [ẋ_ref, τ_p, φ̇_m, φ̇_s], shape (n_freq, 2, 4), Eqs. (3.11–3.18).

    Solves the loop τ_m = PI_master (ẋ_ref − φ̇_m + u), τ_s = PI_slave (ẋ_ref − φ̇_s − u) with
    the torque-equalisation correction u = PI_preload (τ_p − K_Tm τ_m + K_Ts τ_s), which at
    steady state gives τ_m = τ_ref/2 + τ_p, τ_s = τ_ref/2 − τ_p (Eq. 3.1). The printed
    (3.11–3.18) are these expressions with the master and slave labels of τ and φ̇ exchanged,
    without the minus of τ_s/τ_p, and with K_Ts for K_Tm in the denominator of (3.17).
    """
    s = tustin_laplace(frequency, controller.sample_rate)
    a, b, p = (pi.response(s) for pi in (controller.master, controller.slave, controller.preload))
    master_loop, slave_loop = controller.K_Tm * a * p, controller.K_Ts * b * p
    den = 1.0 + master_loop + slave_loop
    rows = [
        [a * (2 * slave_loop + 1), a * p, -a * (slave_loop + 1), -a * slave_loop],
        [b * (2 * master_loop + 1), -b * p, -b * master_loop, -b * (master_loop + 1)],
    ]
    return np.moveaxis(np.array(rows) / den, -1, 0)


def velocity_loop_plant(structure: ArrayLike) -> ComplexArray:
    """Generalised plant G of Fig. 3.5 from the open-loop structural FRFs.

    `structure`: outputs [z_1 … z_n, φ̇_m, φ̇_s] per inputs [F_tip, τ_m, τ_s], shape
    (n_freq, n + 2, 3). Returns [z; q] per [w; p], shape (n_freq, n + 4, 5).
    """
    h = np.asarray(structure, dtype=complex)
    n_freq, n_z = h.shape[0], h.shape[1] - 2
    g = np.zeros((n_freq, n_z + 4, 5), dtype=complex)
    g[:, :n_z, 0], g[:, :n_z, 3:] = h[:, :n_z, 0], h[:, :n_z, 1:]
    g[:, n_z, 1] = g[:, n_z + 1, 2] = 1.0
    g[:, n_z + 2:, 0], g[:, n_z + 2:, 3:] = h[:, n_z:, 0], h[:, n_z:, 1:]
    return g


@dataclass(frozen=True)
class VelocityLoop:
    """Closed velocity loop, Eq. (3.19): outputs z and torques per w = [F_tip, ẋ_ref, τ_p]."""

    outputs: ComplexArray
    torques: ComplexArray


def velocity_loop(
    frequency: ArrayLike, structure: ArrayLike, controller: MasterSlaveController
) -> VelocityLoop:
    """F_l(G, K_vel), Eq. (3.19), and the motor torques it commands (see `velocity_loop_plant`)."""
    plant = velocity_loop_plant(structure)
    k_vel = velocity_controller_matrix(frequency, controller)
    return VelocityLoop(outputs=lower_lft(plant, k_vel), torques=lft_control_signal(plant, k_vel))


def position_loop(
    frequency: ArrayLike,
    velocity_outputs: ArrayLike,
    load_index: int,
    K_v: float,
    delay: float = 2e-3,
) -> ComplexArray:
    """F_l(R, K_pos), Eq. (3.20): outputs z per w' = [F_tip, x_ref, τ_p].

    `velocity_outputs` is `VelocityLoop.outputs`; row `load_index` must be x_load (m), the
    position feedback. K_pos = K_v e^{-jωτ} [1, −1] with K_v in 1/s and the position loop's
    sampling delay τ in s (default twice a 1 kHz period, as for Eq. 4.22).
    """
    r = np.asarray(velocity_outputs, dtype=complex)
    n_freq, n_z = r.shape[:2]
    plant = np.zeros((n_freq, n_z + 2, 4), dtype=complex)
    plant[:, :n_z, [0, 2, 3]] = r[:, :, [0, 2, 1]]
    plant[:, n_z, 1] = 1.0
    plant[:, n_z + 1, [0, 2, 3]] = r[:, load_index, [0, 2, 1]]
    gain = K_v * np.exp(-delay * laplace(frequency))
    k_pos = np.stack([gain, -gain], -1)[:, None, :]
    return lower_lft(plant, k_pos)


def pseudo_open_loop(output: ArrayLike, tau_m: ArrayLike, tau_s: ArrayLike) -> ComplexArray:
    """O/τ_m ≈ O/τ_s ≈ O/τ_ref with τ_ref = τ_m + τ_s, Eqs. (3.24–3.25).

    All three FRFs per the same excitation (e.g. a velocity offset). Exact only for identical
    motors and controllers on a structure symmetric to both pinions.
    """
    return np.asarray(output, dtype=complex) / (np.asarray(tau_m) + np.asarray(tau_s))


@dataclass(frozen=True)
class MotorResponses:
    """O/τ_m and O/τ_s separated by Eq. (3.23), with the condition number of U per frequency."""

    per_master: ComplexArray
    per_slave: ComplexArray
    condition: NDArray[np.float64]


def decouple_motor_responses(
    outputs: ArrayLike, tau_m: ArrayLike, tau_s: ArrayLike
) -> MotorResponses:
    """G = X U^-1, Eqs. (3.22–3.23), from n ≥ 2 measurements under different velocity PIs.

    Arrays of shape (n, n_freq): the output O and the two torques per excitation in each
    measurement. Least squares (pseudo-inverse) when n > 2; a large `condition` flags the
    ill-conditioning the thesis warns about (nearly proportional torque pairs).
    """
    x = np.asarray(outputs, dtype=complex).T[:, None, :]
    u = np.stack([np.asarray(tau_m, dtype=complex).T, np.asarray(tau_s, dtype=complex).T], axis=1)
    if u.shape[-1] < 2:
        raise ValueError("need at least two measurements with different controllers")
    g = x @ np.linalg.pinv(u)
    return MotorResponses(per_master=g[:, 0, 0], per_slave=g[:, 0, 1], condition=np.linalg.cond(u))
