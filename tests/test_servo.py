"""Servo dynamics, Ch. 4.2–4.3: Eqs. (4.15–4.22) against independent ground truth."""

from math import factorial

import numpy as np
import pytest
from scipy import interpolate, signal

from feedbench.analysis import servo
from feedbench.analysis.tuning import bandwidth_tunings
from feedbench.models.axis import TwoMassAxis

M_MOT, M_TIP, K, C, SIGMA, TAU_OL = 24.9, 9.5, 1.98e6, 104.0, 792.0, 0.75e-3
"""Chapter 4 bench (DIGEST §3), SI."""
VELOCITY_RATE = 8000.0
FREQUENCY = np.linspace(1.0, 300.0, 600)
TUNINGS = bandwidth_tunings(TwoMassAxis(m_mot=M_MOT, m_tip=M_TIP, k=K, c=C))


def _sampled_closed_velocity_loop(K_p: float, T_i: float) -> np.ndarray:
    """ẋ_mot/ẋ_ref of the sampled loop: ZOH plant at 8 kHz, 6-sample (0.75 ms) force delay,
    Tustin PI; the ground truth a CNC's Bode function would measure."""
    mass, damping, stiffness = servo.chain_matrices([M_MOT, M_TIP], [K], [C], SIGMA)
    plant = servo.lumped_state_space(mass, damping, stiffness, [0], [(0, servo.VELOCITY)])
    a, b, c, d, dt = signal.cont2discrete(plant, 1 / VELOCITY_RATE, method="zoh")
    z = np.exp(2j * np.pi * FREQUENCY / VELOCITY_RATE)
    resolvent = z[:, None, None] * np.eye(a.shape[0]) - a
    mobility = (c @ np.linalg.solve(resolvent, np.broadcast_to(b, (z.size, *b.shape))) + d)[:, 0, 0]
    pi_num, pi_den, _ = signal.cont2discrete(([K_p * T_i, K_p], [T_i, 0.0]), dt, method="bilinear")
    _, pi = signal.freqz(pi_num.ravel(), pi_den, worN=2 * np.pi * FREQUENCY / VELOCITY_RATE)
    loop = pi * mobility * z ** -round(TAU_OL * VELOCITY_RATE)
    return loop / (1 + loop)


def test_mobility_from_closed_loop_predicts_another_tuning():
    """Eq. (4.20) on the sampled "optimum" loop, then Eq. (4.21) for the "high" K_p and T_i:
    within 1 % of the sampled loop over 1–300 Hz (the PI's Tustin warping, which changes
    with T_i, is the only error)."""
    measured, target = TUNINGS["optimum"], TUNINGS["high"]
    closed = _sampled_closed_velocity_loop(measured.K_p, measured.T_i)
    mobility = servo.open_loop_mobility(FREQUENCY, closed, measured.K_p, measured.T_i)
    predicted = servo.closed_velocity_loop(FREQUENCY, mobility, target.K_p, target.T_i)
    truth = _sampled_closed_velocity_loop(target.K_p, target.T_i)
    assert np.max(np.abs(predicted / truth - 1)) < 0.01


def test_mobility_prediction_is_exact_for_a_new_k_p():
    """Same T_i, new K_p: everything but K_p sits in the extracted mobility, so exact."""
    t_i = TUNINGS["optimum"].T_i
    closed = _sampled_closed_velocity_loop(TUNINGS["low"].K_p, t_i)
    mobility = servo.open_loop_mobility(FREQUENCY, closed, TUNINGS["low"].K_p, t_i)
    predicted = servo.closed_velocity_loop(FREQUENCY, mobility, TUNINGS["high"].K_p, t_i)
    truth = _sampled_closed_velocity_loop(TUNINGS["high"].K_p, t_i)
    assert np.max(np.abs(predicted / truth - 1)) < 1e-9


def test_extracted_mobility_matches_the_plant_at_low_frequency():
    """Below 20 Hz the sampled mobility × delay differs from the continuous plant by < 1 %."""
    gains = TUNINGS["optimum"]
    closed = _sampled_closed_velocity_loop(gains.K_p, gains.T_i)
    mobility = servo.open_loop_mobility(FREQUENCY, closed, gains.K_p, gains.T_i)
    plant = servo.chain_mobility([M_MOT, M_TIP], [K], [C], SIGMA)
    _, truth = signal.freqresp(plant, 2 * np.pi * FREQUENCY)
    truth = truth * np.exp(-TAU_OL * 2j * np.pi * FREQUENCY)
    low = FREQUENCY < 20
    assert np.max(np.abs(mobility[low] / truth[low] - 1)) < 0.01


def test_closed_position_loop_first_order_with_delay():
    """Ideal velocity loop: x/x_ref = K_v/(s + K_v) e^{-sτ}: −3 dB and −45° − ωτ at ω = K_v."""
    k_v, delay = 70.0, 2e-3
    f_corner = k_v / (2 * np.pi)
    response = servo.closed_position_loop([0.01, f_corner], [1.0, 1.0], k_v, delay)
    assert abs(response[0]) == pytest.approx(1.0, abs=1e-6)
    assert abs(response[1]) == pytest.approx(1 / np.sqrt(2), rel=1e-12)
    assert np.angle(response[1]) == pytest.approx(-np.pi / 4 - k_v * delay, rel=1e-12)


def test_compliance_integrates_mobility():
    """x/F = (ẋ/F)/(jω): a rigid mass m has mobility 1/(jωm) and compliance −1/(mω²)."""
    f = np.array([10.0, 50.0])
    mobility = 1 / (2j * np.pi * f * 30.0)
    compliance = servo.mobility_to_compliance(f, mobility)
    np.testing.assert_allclose(compliance, -1 / (30.0 * (2 * np.pi * f) ** 2))


@pytest.mark.parametrize(
    ("order", "f_max", "bound"), [(2, 200.0, 1e-3), (3, 300.0, 2e-4), (4, 500.0, 1e-4)]
)
def test_pade_error_bound(order, f_max, bound):
    """|P_d(jω) − e^{-jωτ}| for τ = 0.75 ms stays below `bound` up to `f_max`; |P_d| = 1."""
    f = np.linspace(0.0, f_max, 2001)
    _, approx = signal.freqresp(servo.pade_delay(TAU_OL, order), 2 * np.pi * f)
    assert np.max(np.abs(approx - np.exp(-TAU_OL * 2j * np.pi * f))) < bound
    np.testing.assert_allclose(np.abs(approx), 1.0, atol=1e-12)


def test_pade_coefficients_match_scipy_taylor_pade():
    """Eq. (4.16) closed form = scipy's Padé of the Taylor series of e^{-x} (τ = 1)."""
    numerator, denominator = interpolate.pade([(-1.0) ** k / factorial(k) for k in range(7)], 3)
    ours = servo.pade_delay(1.0, 3)
    np.testing.assert_allclose(ours.num, numerator.coeffs / denominator.coeffs[0], rtol=1e-10)
    np.testing.assert_allclose(ours.den, denominator.coeffs / denominator.coeffs[0], rtol=1e-10)


def test_chain_mobility_is_s_times_eq_4_15():
    """Two masses: ẋ_mot/F_mot = (M_tip s² + cs + k)/(M_mot M_tip s³ + (c(M_mot+M_tip) + σM_tip)s²
    + (k(M_mot+M_tip) + σc)s + σk), Eq. (4.15) times s."""
    mobility = servo.chain_mobility([M_MOT, M_TIP], [K], [C], SIGMA)
    numerator = np.array([M_TIP, C, K])
    denominator = np.array([
        M_MOT * M_TIP,
        C * (M_MOT + M_TIP) + SIGMA * M_TIP,
        K * (M_MOT + M_TIP) + SIGMA * C,
        SIGMA * K,
    ])
    lead = denominator[0]
    np.testing.assert_allclose(mobility.num, numerator / lead, rtol=1e-9)
    np.testing.assert_allclose(mobility.den, denominator / lead, rtol=1e-9)


TABLE_4_1 = dict(M_mot=80.0, M_2=130.0, M_tip=10.8, k_1=22e6, k_2=1.75e6, c_1=1069.0, c_2=86.7)


def test_three_dof_matrices_as_eq_4_17():
    p = TABLE_4_1
    a, b, c, d = servo.three_dof_state_space(**p)
    m_mot, m_2, m_tip = p["M_mot"], p["M_2"], p["M_tip"]
    k_1, k_2, c_1, c_2 = p["k_1"], p["k_2"], p["c_1"], p["c_2"]
    np.testing.assert_allclose(a[:3], np.hstack([np.zeros((3, 3)), np.eye(3)]))
    np.testing.assert_allclose(a[3], np.array([-k_1, k_1, 0, -c_1, c_1, 0]) / m_mot)
    np.testing.assert_allclose(a[4], np.array([k_1, -k_1 - k_2, k_2, c_1, -c_1 - c_2, c_2]) / m_2)
    np.testing.assert_allclose(a[5], np.array([0, k_2, -k_2, 0, c_2, -c_2]) / m_tip)
    np.testing.assert_allclose(b.ravel(), [0, 0, 0, 1 / m_mot, 0, 0])
    np.testing.assert_allclose(c.ravel(), [1, 0, 0, 0, 0, 0])
    assert d.item() == 0.0


def test_three_dof_zeros_are_the_motor_locked_frequencies():
    """Undamped: x_mot/F_mot (Eq. 4.19) vanishes at the natural frequencies of M_2 and M_tip
    with the motor clamped."""
    p = {**TABLE_4_1, "c_1": 0.0, "c_2": 0.0}
    k_locked = np.array([[p["k_1"] + p["k_2"], -p["k_2"]], [-p["k_2"], p["k_2"]]])
    mass_inv = np.diag([1 / p["M_2"], 1 / p["M_tip"]])
    f_locked = np.sqrt(np.sort(np.linalg.eigvals(mass_inv @ k_locked).real)) / (2 * np.pi)
    system = servo.three_dof_state_space(**p)
    response = np.abs(servo.state_space_frf(system, np.r_[f_locked, 0.9 * f_locked]))
    assert np.all(response[:2, 0, 0] < 1e-7 * response[2:, 0, 0])


def test_state_space_frf_inverts_the_dynamic_stiffness():
    """C(sI − A)^-1 B of the 3-DOF model = first entry of (−ω²M + jωC + K)^-1."""
    system = servo.three_dof_state_space(**TABLE_4_1, sigma=500.0)
    p = TABLE_4_1
    mass, damping, stiffness = servo.chain_matrices(
        [p["M_mot"], p["M_2"], p["M_tip"]], [p["k_1"], p["k_2"]], [p["c_1"], p["c_2"]], 500.0
    )
    omega = 2 * np.pi * FREQUENCY[:, None, None]
    truth = np.linalg.inv(-(omega**2) * mass + 1j * omega * damping + stiffness)[:, 0, 0]
    np.testing.assert_allclose(servo.state_space_frf(system, FREQUENCY)[:, 0, 0], truth, rtol=1e-9)
