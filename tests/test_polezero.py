"""Pole–zero product model with rigid body and delay, Eq. (4.27): evaluation and fit."""

import numpy as np
import pytest
from scipy import signal

from feedbench.analysis import servo
from feedbench.analysis.polezero import PoleZeroModel, VibratoryMode, fit_pole_zero
from feedbench.models.axis import TwoMassAxis

TRUTH = PoleZeroModel(
    m_total=34.4,
    sigma=792.0,
    delay=0.75e-3,
    modes=(VibratoryMode(85.3, 0.03, 72.6, 0.02), VibratoryMode(160.0, 0.02, 140.0, 0.015)),
)
"""Chapter 4 bench rigid body, σ and delay (DIGEST §3) with its 2-DOF mode plus a second mode."""
FREQUENCY = np.linspace(5.0, 300.0, 600)


def test_two_mass_mobility_is_a_pole_zero_product():
    """Eq. (4.15)·s (σ = 0) = Eq. (4.27) with one mode: zero at f_t (4.13), pole at f_r (4.14)."""
    axis = TwoMassAxis(m_mot=24.9, m_tip=9.5, k=1.98e6, c=0.0)
    mode = VibratoryMode(axis.f_r, 0.0, axis.f_t, 0.0)
    model = PoleZeroModel(axis.m_mot + axis.m_tip, 0.0, 0.0, (mode,))
    two_mass = servo.chain_mobility([axis.m_mot, axis.m_tip], [axis.k], [axis.c])
    _, truth = signal.freqresp(two_mass, 2 * np.pi * FREQUENCY)
    np.testing.assert_allclose(model.mobility(FREQUENCY), truth, rtol=1e-8)


def test_transfer_function_matches_mobility_below_the_pade_limit():
    """Rational model with a 4th-order Padé delay vs the exact delay: < 1e-5 relative to 300 Hz."""
    _, rational = signal.freqresp(TRUTH.transfer_function(pade_order=4), 2 * np.pi * FREQUENCY)
    assert np.max(np.abs(rational / TRUTH.mobility(FREQUENCY) - 1)) < 1e-5


def _relative_errors(fitted: PoleZeroModel) -> dict[str, float]:
    def rel(a: float, b: float) -> float:
        return abs(a / b - 1)

    errors = {
        "m_total": rel(fitted.m_total, TRUTH.m_total),
        "sigma": rel(fitted.sigma, TRUTH.sigma),
        "delay": rel(fitted.delay, TRUTH.delay),
    }
    for i, (fit, true) in enumerate(zip(fitted.modes, TRUTH.modes)):
        for field in ("pole_frequency", "zero_frequency", "pole_damping", "zero_damping"):
            errors[f"{field}{i}"] = rel(getattr(fit, field), getattr(true, field))
    return errors


def test_fit_recovers_noise_free_model():
    """No noise: every parameter within 1e-6 relative, from the automatic starting point."""
    fit = fit_pole_zero(FREQUENCY, TRUTH.mobility(FREQUENCY), n_modes=2)
    assert max(_relative_errors(fit.model).values()) < 1e-6
    assert fit.rms_log_error < 1e-9


def test_fit_with_one_percent_noise():
    """1 % complex noise: frequencies within 0.1 %, damping ratios within 3 %, delay, mass and
    σ within 2 %; RMS log error ≈ the noise level."""
    rng = np.random.default_rng(3)
    noise = np.array([1.0, 1j]) @ rng.standard_normal((2, FREQUENCY.size)) / np.sqrt(2)
    fit = fit_pole_zero(FREQUENCY, TRUTH.mobility(FREQUENCY) * (1 + 0.01 * noise), n_modes=2)
    errors = _relative_errors(fit.model)
    assert max(v for k, v in errors.items() if "frequency" in k) < 1e-3
    assert max(v for k, v in errors.items() if "damping" in k) < 0.03
    assert max(errors["delay"], errors["m_total"], errors["sigma"]) < 0.02
    assert fit.rms_log_error == pytest.approx(0.01, rel=0.2)


def test_fit_rejects_too_many_modes():
    with pytest.raises(ValueError, match="modes requested"):
        fit_pole_zero(FREQUENCY, TRUTH.mobility(FREQUENCY), n_modes=5)
