"""Master–slave rack-and-pinion velocity and position loops (Eqs. 3.11–3.25) on a linear
lumped model: two motors (linear-equivalent mass) on pinion stiffnesses k_m, k_s to the load
(8500 kg, Ch. 3.4), a 60 Hz tool-tip mode on the load."""

import numpy as np
import pytest
from scipy import signal

from feedbench.analysis import masterslave as ms
from feedbench.analysis import servo

FREQUENCY = np.linspace(5.0, 150.0, 291)
M_MOTOR, M_LOAD, M_TIP = 1840.0, 8500.0, 500.0
"""Motor: J_eq = 8.45e-3 kg·m² × 28² / (0.06 m)² as a linear mass; tool tip on the load."""
K_TIP = M_TIP * (2 * np.pi * 60.0) ** 2
PI = ms.PIController(K_p=8e5, T_i=1 / (np.pi * 20.0))
PRELOAD = ms.PIController(K_p=2e-6, T_i=0.05)


def structure(k_m: float, k_s: float) -> np.ndarray:
    """Open-loop FRFs [x_load, ẍ_tip, φ̇_m, φ̇_s] per [F_tip, τ_m, τ_s], shape (n_freq, 4, 3)."""
    mass = np.diag([M_MOTOR, M_MOTOR, M_LOAD, M_TIP])
    stiffness = np.zeros((4, 4))
    for i, j, k in ((0, 2, k_m), (1, 2, k_s), (2, 3, K_TIP)):
        stiffness[np.ix_([i, j], [i, j])] += k * np.array([[1.0, -1.0], [-1.0, 1.0]])
    damping = 2e-4 * stiffness + np.diag([0.0, 0.0, 2e4, 0.0])
    outputs = [
        (2, servo.POSITION), (3, servo.ACCELERATION), (0, servo.VELOCITY), (1, servo.VELOCITY),
    ]
    system = servo.lumped_state_space(mass, damping, stiffness, [3, 0, 1], outputs)
    return servo.state_space_frf(system, FREQUENCY)


SYMMETRIC = structure(90e6, 90e6)
ASYMMETRIC = structure(81e6, 100e6)


def controller(**changes) -> ms.MasterSlaveController:
    settings = dict(master=PI, slave=PI, preload=PRELOAD, K_Tm=0.5, K_Ts=0.5)
    return ms.MasterSlaveController(**{**settings, **changes})


def test_tustin_matches_scipy_bilinear_discretisation():
    """PI at the Tustin s = freqz of scipy's bilinear cont2discrete at 8 kHz, up to 3 kHz."""
    f = np.linspace(1.0, 3000.0, 500)
    continuous = ([PI.K_p * PI.T_i, PI.K_p], [PI.T_i, 0.0])
    numerator, denominator, _ = signal.cont2discrete(continuous, 1 / 8000, method="bilinear")
    _, truth = signal.freqz(numerator.ravel(), denominator, worN=2 * np.pi * f / 8000)
    np.testing.assert_allclose(PI.response(ms.tustin_laplace(f, 8000.0)), truth, rtol=1e-9)


def test_controller_matrix_solves_the_block_diagram():
    """Eqs. (3.11–3.18) = a numerical solve of τ_m = A(ẋ_ref − φ̇_m + u), τ_s = B(ẋ_ref − φ̇_s − u),
    u = P(τ_p − K_Tm τ_m + K_Ts τ_s) for different PIs and weights 0.3 / 0.7."""
    ctrl = controller(
        slave=ms.PIController(5e5, 0.02), preload=ms.PIController(7e-6, 0.01), K_Tm=0.3, K_Ts=0.7
    )
    k_vel = ms.velocity_controller_matrix(FREQUENCY, ctrl)
    s = ms.tustin_laplace(FREQUENCY, 8000.0)
    for index, s_i in enumerate(s):
        a, b, p = (pi.response(s_i) for pi in (ctrl.master, ctrl.slave, ctrl.preload))
        equations = np.array([[1, 0, -a], [0, 1, b], [p * ctrl.K_Tm, -p * ctrl.K_Ts, 1]])
        # right-hand sides for unit inputs ẋ_ref, τ_p, φ̇_m, φ̇_s
        rhs = np.array([[a, 0, -a, 0], [b, 0, 0, -b], [0, p, 0, 0]])
        truth = np.linalg.solve(equations, rhs)[:2]
        np.testing.assert_allclose(k_vel[index], truth, rtol=1e-12, atol=1e-9)


def test_controller_reduces_to_single_motor_pi_without_preload_controller():
    """PI_preload = 0, K_Tm = K_Ts = 0.5: τ_m = PI (ẋ_ref − φ̇_m), τ_s = PI (ẋ_ref − φ̇_s)."""
    k_vel = ms.velocity_controller_matrix(FREQUENCY, controller(preload=ms.PIController(0.0)))
    pi = PI.response(ms.tustin_laplace(FREQUENCY, 8000.0))
    zero = np.zeros_like(pi)
    master_row = np.stack([pi, zero, -pi, zero], -1)
    slave_row = np.stack([pi, zero, zero, -pi], -1)
    expected = np.stack([master_row, slave_row], -2)
    np.testing.assert_allclose(k_vel, expected, rtol=1e-14, atol=0)


def test_preload_splits_the_torques_at_steady_state():
    """Eq. (3.1): at 1 mHz τ_m/τ_p → +1 and τ_s/τ_p → −1; ẋ_ref reaches both motors equally."""
    k_vel = ms.velocity_controller_matrix([1e-3], controller())[0]
    assert k_vel[0, 1].real == pytest.approx(1.0, abs=1e-3)
    assert k_vel[1, 1].real == pytest.approx(-1.0, abs=1e-3)
    assert k_vel[0, 0] / k_vel[1, 0] == pytest.approx(1.0, abs=1e-12)


def test_pseudo_open_loop_recovers_the_symmetric_structure():
    """Identical motors and PIs, symmetric structure, velocity-command excitation: O/(τ_m + τ_s)
    equals the open-loop O/τ_m used to build the loop for x_load and ẍ_tip (rtol 1e-9). For the
    motor velocity it is the mean of drive-point and transfer mobility, (φ̇_m/τ_m + φ̇_m/τ_s)/2."""
    loop = ms.velocity_loop(FREQUENCY, SYMMETRIC, controller())
    tau_m, tau_s = loop.torques[:, 0, 1], loop.torques[:, 1, 1]
    np.testing.assert_allclose(tau_m, tau_s, rtol=1e-9)
    for row in (0, 1):
        pseudo = ms.pseudo_open_loop(loop.outputs[:, row, 1], tau_m, tau_s)
        np.testing.assert_allclose(pseudo, SYMMETRIC[:, row, 1], rtol=1e-9)
    phi_m = SYMMETRIC[:, 2, 1] * tau_m + SYMMETRIC[:, 2, 2] * tau_s
    mean_mobility = SYMMETRIC[:, 2, 1:].mean(axis=1)
    np.testing.assert_allclose(ms.pseudo_open_loop(phi_m, tau_m, tau_s), mean_mobility, rtol=1e-9)


def test_two_controller_settings_decouple_an_asymmetric_drive():
    """k_m = 81, k_s = 100 N/µm: Eq. (3.23) from two settings (slave K_p halved) recovers
    x_load/τ_m and x_load/τ_s (rtol 1e-7), where the pseudo-open loop is off by > 1 %."""
    settings = [controller(), controller(slave=ms.PIController(PI.K_p / 2, PI.T_i))]
    loops = [ms.velocity_loop(FREQUENCY, ASYMMETRIC, c) for c in settings]
    output = np.array([lp.outputs[:, 0, 1] for lp in loops])
    tau_m, tau_s = (np.array([lp.torques[:, i, 1] for lp in loops]) for i in (0, 1))
    responses = ms.decouple_motor_responses(output, tau_m, tau_s)
    np.testing.assert_allclose(responses.per_master, ASYMMETRIC[:, 0, 1], rtol=1e-7)
    np.testing.assert_allclose(responses.per_slave, ASYMMETRIC[:, 0, 2], rtol=1e-7)
    pseudo = ms.pseudo_open_loop(output[0], tau_m[0], tau_s[0])
    assert np.max(np.abs(pseudo / ASYMMETRIC[:, 0, 1] - 1)) > 0.01


def test_symmetric_velocity_loop_is_eq_4_21_with_both_motors():
    """Symmetric drive, near-continuous PIs (1 GHz): φ̇_m/ẋ_ref = Eq. (4.21) with the mean
    mobility per τ_ref and the two motors' PIs summed (2 K_p)."""
    loop = ms.velocity_loop(FREQUENCY, SYMMETRIC, controller(sample_rate=1e9))
    mobility = SYMMETRIC[:, 2, 1:].mean(axis=1)
    predicted = servo.closed_velocity_loop(FREQUENCY, mobility, 2 * PI.K_p, PI.T_i)
    phi_m = (SYMMETRIC[:, 2, 1:] * loop.torques[:, :, 1]).sum(axis=1)
    np.testing.assert_allclose(phi_m, predicted, rtol=1e-6)


def _direct_closed_loop(
    h: np.ndarray, ctrl: ms.MasterSlaveController, k_v: float, delay: float
) -> np.ndarray:
    """z per [F_tip, x_ref, τ_p] solving structure, both PIs, preload PI and position P at once.

    Unknowns [x_load, ẍ_tip, φ̇_m, φ̇_s, τ_m, τ_s, u, v] per frequency."""
    s_tustin = ms.tustin_laplace(FREQUENCY, ctrl.sample_rate)
    position_gain = k_v * np.exp(-delay * servo.laplace(FREQUENCY))
    result = np.zeros((FREQUENCY.size, 2, 3), dtype=complex)
    for i in range(FREQUENCY.size):
        a, b, p = (pi.response(s_tustin[i]) for pi in (ctrl.master, ctrl.slave, ctrl.preload))
        m = np.zeros((8, 8), dtype=complex)
        m[:4, :4], m[:4, 4:6] = np.eye(4), -h[i, :, 1:]
        m[4, [4, 2, 6, 7]] = [1, a, -a, -a]
        m[5, [5, 3, 6, 7]] = [1, b, b, -b]
        m[6, [6, 4, 5]] = [1, p * ctrl.K_Tm, -p * ctrl.K_Ts]
        m[7, [7, 0]] = [1, position_gain[i]]
        rhs = np.zeros((8, 3), dtype=complex)
        rhs[:4, 0] = h[i, :, 0]
        rhs[7, 1] = position_gain[i]
        rhs[6, 2] = p
        result[i] = np.linalg.solve(m, rhs)[:2]
    return result


def test_velocity_then_position_lft_equals_the_direct_closed_loop():
    """Eq. (3.19) then Eq. (3.20) (K_v = 30 1/s, 2 ms delay) = one direct solve of the whole
    loop, asymmetric drive, different PIs: x_load and ẍ_tip per F_tip, x_ref, τ_p."""
    ctrl = controller(slave=ms.PIController(6e5, 0.03), K_Tm=0.4, K_Ts=0.6)
    velocity = ms.velocity_loop(FREQUENCY, ASYMMETRIC, ctrl)
    closed = ms.position_loop(FREQUENCY, velocity.outputs, load_index=0, K_v=30.0, delay=2e-3)
    np.testing.assert_allclose(closed, _direct_closed_loop(ASYMMETRIC, ctrl, 30.0, 2e-3), rtol=1e-8)
