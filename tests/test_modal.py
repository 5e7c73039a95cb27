"""Modal parameters (Table 3.1 style) from synthetic systems with known truth: closely spaced
modes, several outputs, Welch leakage, hammer windows."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal

from feedbench.analysis.frf import estimate_frf, quasi_frf
from feedbench.analysis.modal import fit_modes, remove_window_decay, synthesize_receptance

# Three modes; the middle one is Table 3.1's (35.7 Hz, ζ = 3 %, 24.4 N/µm → m ≈ 485 kg) and the
# third lies 2 % above it.
F_N = np.array([32.0, 35.7, 1.02 * 35.7])
ZETA = np.array([0.02, 0.03, 0.015])
K = np.array([40e6, 24.4e6, 30e6])
MASS = K / (2 * np.pi * F_N) ** 2
BAND = (25.0, 45.0)
SHAPES = np.array([[1.0, 1.0, 1.0], [0.8, -0.5, 0.3], [0.3, 0.9, -0.7]])  # outputs × modes


def modal_receptance(f, shapes=SHAPES[:1]):
    """Ground truth H_o(f) = Σ_i φ_oi φ_0i / (k_i − m_i ω² + j c_i ω), force at output 0 (m/N)."""
    w = 2 * np.pi * np.asarray(f)[None, :, None]
    modal = 1.0 / (K - MASS * w**2 + 2j * ZETA * np.sqrt(K * MASS) * w)
    return np.sum(shapes[:, None, :] * shapes[0] * modal, axis=-1)


def modal_filter(force, fs):
    """Point response (m) to force (N), each mode by its impulse-invariant discrete filter."""
    T, total = 1.0 / fs, np.zeros_like(force)
    for f_n, zeta, m in zip(F_N, ZETA, MASS):
        w_n = 2 * np.pi * f_n
        sigma, w_d = zeta * w_n, w_n * np.sqrt(1 - zeta**2)
        b = [0.0, T * np.exp(-sigma * T) * np.sin(w_d * T) / (m * w_d)]
        a = [1.0, -2 * np.exp(-sigma * T) * np.cos(w_d * T), np.exp(-2 * sigma * T)]
        total += scipy.signal.lfilter(b, a, force)
    return total


def with_noise(H, level, seed):
    """Complex Gaussian noise of rms `level` × |H| on every line."""
    rng = np.random.default_rng(seed)
    unit = (rng.standard_normal(H.shape) + 1j * rng.standard_normal(H.shape)) / np.sqrt(2)
    return H + level * np.abs(H) * unit


def relative_errors(modes):
    """|relative error| of f_n, ζ, modal stiffness and modal mass, one row per mode."""
    found = np.array([[m.f_n, m.zeta, m.modal_stiffness, m.modal_mass] for m in modes])
    return np.abs(found / np.column_stack([F_N, ZETA, K, MASS]) - 1)


def test_point_frf_with_noise_three_modes_two_2_percent_apart():
    f = np.arange(0.0, 100.0, 0.05)
    fit = fit_modes(f, with_noise(modal_receptance(f)[0], 0.01, seed=11), BAND, 3)
    errors = relative_errors(fit.modes)
    assert np.all(errors[:, 0] < 0.005), errors
    assert np.all(errors[:, 1] < 0.05), errors
    assert np.all(errors[1, 2:] < 0.08), errors  # Table 3.1 mode: k ≈ 24.4 N/µm, m ≈ 485 kg
    assert fit.relative_error == pytest.approx(0.01, abs=0.003)  # the noise, nothing more
    assert not fit.warnings


def test_three_outputs_pin_the_close_modes_and_their_shapes():
    f = np.arange(0.0, 100.0, 0.125)
    H = with_noise(modal_receptance(f, SHAPES), 0.01, seed=12)
    fit = fit_modes(f, H, BAND, 3, driving_point=0)
    errors = relative_errors(fit.modes)
    assert np.all(errors[:, 0] < 0.001) and np.all(errors[:, 1] < 0.02), errors
    assert np.all(errors[:, 2:] < 0.03), errors
    for i, mode in enumerate(fit.modes):
        shape = (mode.residue / mode.residue[0]).real
        np.testing.assert_allclose(shape, SHAPES[:, i], atol=0.03)


def test_noise_free_mode_reproduces_the_documented_mass_and_residue():
    """H = r/(jω − λ) + c.c. with r = 1/(2j m ω_d): the fit returns m, k and r of the truth."""
    f = np.arange(0.0, 100.0, 0.1)
    H = modal_receptance(f)[0]
    fit = fit_modes(f, H, BAND, 3)
    errors = relative_errors(fit.modes)
    assert np.all(errors < 1e-4), errors
    table_mode = fit.modes[1]
    w_d = 2 * np.pi * F_N[1] * np.sqrt(1 - ZETA[1] ** 2)
    assert complex(table_mode.residue) == pytest.approx(1 / (2j * MASS[1] * w_d), rel=1e-4)
    assert table_mode.modal_mass == pytest.approx(485.0, rel=0.01)
    inside = (f >= BAND[0]) & (f <= BAND[1])
    rebuilt = synthesize_receptance(f[inside], fit.modes, fit.lower_residual, fit.upper_residual)
    np.testing.assert_allclose(rebuilt, H[inside], rtol=1e-4)
    np.testing.assert_allclose(fit.H_model, H[inside], rtol=1e-4)


def test_stabilization_diagram_holds_every_mode():
    f = np.arange(0.0, 100.0, 0.05)
    fit = fit_modes(f, with_noise(modal_receptance(f)[0], 0.01, seed=13), BAND, 3)
    diagram = fit.stabilization
    stable_f = diagram.f[diagram.stable]
    for f_n, zeta in zip(F_N, ZETA):
        near = np.abs(stable_f - f_n * np.sqrt(1 - zeta**2)) < 0.005 * f_n
        assert near.sum() >= 10
    assert diagram.order.min() == 3 and diagram.order.max() == 3 * 2 + 24


@pytest.fixture(scope="module")
def leaky_welch():
    """Random force, 2 % output noise, 0.25 Hz resolution: the 1.5 % mode is 4.4 bins wide."""
    fs, rng = 256.0, np.random.default_rng(0)
    force = 100.0 * rng.standard_normal(2**19)
    response = modal_filter(force, fs)
    response += 0.02 * response.std() * rng.standard_normal(force.size)
    return estimate_frf(force, response, fs, nperseg=1024)


def test_leakage_is_reported_and_the_lag_window_model_is_not_fooled(leaky_welch):
    est = leaky_welch
    assert est.leakage_suspected and any("leakage" in w for w in est.warnings)
    naive = fit_modes(est.f, est.H1, BAND, 3, coherence=est.coherence)
    assert any("leakage" in w and "biased low" in w for w in naive.warnings)
    assert relative_errors(naive.modes)[2, 1] > 0.1  # ζ of the 1.5 % mode biased high
    fit = fit_modes(est.f, est.H1, BAND, 3, coherence=est.coherence, lag_window=est.lag_window)
    errors = relative_errors(fit.modes)
    assert np.all(errors[:, 0] < 0.005) and np.all(errors[:, 1] < 0.05), errors
    assert np.all(errors[:, 2:] < 0.05), errors
    assert any("corrected" in w for w in fit.warnings)


def test_hammer_quasi_frf_fit_with_exponential_window_removed():
    """4 hits (Ch. 5.5.1), τ = 1 s exponential window: its added decay is taken off the poles."""
    fs, n = 1024.0, 8192
    t = np.arange(n) / fs
    forces = np.zeros((4, n))
    for i in range(4):
        inside = (t >= 0.05 + 0.003 * i) & (t < 0.052 + 0.003 * i)
        forces[i, inside] = (500.0 + 20 * i) * np.sin(np.pi * (t[inside] - 0.05 - 0.003 * i) / 2e-3)
    responses = np.stack([modal_filter(force, fs) for force in forces])
    noise = np.random.default_rng(1).standard_normal(responses.shape)
    responses += 0.005 * np.abs(responses).max() * noise
    hammer = quasi_frf(forces, responses, fs, force_window_s=0.01, exp_decay=1.0)
    windowed = fit_modes(hammer.estimate.f, hammer.estimate.H1, BAND, 3)
    assert windowed.modes[0].zeta == pytest.approx(ZETA[0] + 1.0 / (2 * np.pi * F_N[0]), rel=0.05)
    errors = relative_errors(remove_window_decay(windowed.modes, hammer.window_decay_rate))
    assert np.all(errors[:, 0] < 0.005) and np.all(errors[:, 1] < 0.05), errors
    assert np.all(errors[:, 2:] < 0.05), errors


def test_bad_band_and_order_name_the_field():
    f = np.arange(0.0, 100.0, 1.0)
    H = modal_receptance(f)[0]
    with pytest.raises(ValueError, match="band"):
        fit_modes(f, H, (30.0, 33.0), 1)
    with pytest.raises(ValueError, match="max_order"):
        fit_modes(f, H, BAND, 3, max_order=40)
    with pytest.raises(ValueError, match="lag_window"):
        fit_modes(f + 0.3, H, BAND, 3, lag_window=np.ones(256))
