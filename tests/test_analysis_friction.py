"""Friction identification (Eq. 5.2) against the lab-bench truth of Fig. 5.11 (DIGEST §3)."""

import numpy as np
import pytest

from feedbench.analysis.friction import (
    fit_andersson,
    fit_andersson_directional,
    fit_coulomb_viscous,
    invariant_feed,
)
from feedbench.models.friction import AnderssonFriction, DirectionalFriction
from feedbench.units import MIN_PER_MM, MM_PER_MIN, N_MIN_PER_MM

POSITIVE = AnderssonFriction(
    F_c=44.2, F_s=84.0, v_s=387.4 * MM_PER_MIN, sigma=0.0028 * N_MIN_PER_MM,
    k_tanh=0.25 * MIN_PER_MM, delta=1.0,
)
NEGATIVE = AnderssonFriction(
    F_c=38.7, F_s=88.0, v_s=421.0 * MM_PER_MIN, sigma=0.0025 * N_MIN_PER_MM,
    k_tanh=0.25 * MIN_PER_MM, delta=1.0,
)
TRUTH = DirectionalFriction(positive=POSITIVE, negative=NEGATIVE)
FEEDS = np.array([25, 50, 75, 100, 150, 200, 300, 400, 500, 700, 900, 1200, 1500]) * MM_PER_MIN
SWEEP_V = np.concatenate([FEEDS, -FEEDS])
NAMES = ("F_c", "F_s", "v_s", "sigma")
K_P_LAB = 2.0 * np.pi * 34.4 * 30.0
"""Velocity-loop gain of the lab bench, Eq. (4.2): M_total = 34.4 kg, f_bw = 30 Hz (N·s/m)."""


def relative_errors(law: AnderssonFriction, truth: AnderssonFriction) -> np.ndarray:
    return np.array([getattr(law, n) / getattr(truth, n) - 1.0 for n in NAMES])


def test_noise_free_sweep_recovers_both_directions():
    fit = fit_andersson_directional(SWEEP_V, TRUTH.force(SWEEP_V))
    for side, truth in ((fit.positive, POSITIVE), (fit.negative, NEGATIVE)):
        err = np.abs(relative_errors(side.params, truth))
        assert err[[0, 1, 3]].max() < 0.005  # F_c, F_s, σ within 0.5 %
        assert err[2] < 0.01  # v_s within 1 %
        assert side.rms < 1e-6
        assert side.r_squared == pytest.approx(1.0, abs=1e-12)
        assert side.n_points == FEEDS.size
    assert fit.model.force(-0.01) == pytest.approx(TRUTH.force(-0.01), rel=1e-6)


def test_noisy_sweep_errors_match_jacobian_std():
    """0.2 N noise on each mean force, 100 realisations.

    The brief asked for F_c, σ within 2 % and v_s within 5 % at this noise level; with 13
    feeds up to 1500 mm/min the viscous slope and the Stribeck tail are nearly collinear and
    the Cramér–Rao spread of σ is ≈ 30–45 % (F_c ≈ 3–5 %, v_s ≈ 4 %), so no estimator can
    meet that. What is checked instead: F_s within 2 % every time, and the reported Jacobian
    standard deviations agree with the Monte-Carlo spread (within 25 %) and cover the errors.
    """
    rng = np.random.default_rng(12)
    clean = TRUTH.force(SWEEP_V)
    errors, stds = [], []
    for _ in range(100):
        fit = fit_andersson_directional(SWEEP_V, clean + rng.normal(0.0, 0.2, clean.size))
        for side, truth in ((fit.positive, POSITIVE), (fit.negative, NEGATIVE)):
            errors.append(relative_errors(side.params, truth))
            stds.append([getattr(side.std, n) / getattr(truth, n) for n in NAMES])
    errors, stds = np.array(errors), np.array(stds)
    assert np.abs(errors[:, 1]).max() < 0.02
    spread_ratio = stds.mean(axis=0) / errors.std(axis=0)
    assert np.all(np.abs(spread_ratio - 1.0) < 0.25), spread_ratio
    assert np.mean(np.abs(errors) < 3.0 * stds) > 0.97


def test_fit_delta_recovers_shape_factor():
    truth = AnderssonFriction(F_c=40.0, F_s=80.0, v_s=0.005, sigma=150.0, delta=1.4)
    fit = fit_andersson(FEEDS, truth.force(FEEDS), fit_delta=True)
    assert fit.params.delta == pytest.approx(1.4, rel=1e-3)
    assert np.abs(relative_errors(fit.params, truth)).max() < 1e-3


def test_negative_sweep_alone_is_fitted_on_magnitudes():
    fit = fit_andersson(-FEEDS, NEGATIVE.force(-FEEDS))
    assert np.abs(relative_errors(fit.params, NEGATIVE)).max() < 0.01


def test_coulomb_viscous_recovers_reduced_law():
    truth = AnderssonFriction(F_c=44.2, F_s=44.2, v_s=np.inf, sigma=168.0)
    rng = np.random.default_rng(3)
    fit = fit_coulomb_viscous(FEEDS, truth.force(FEEDS) + rng.normal(0.0, 0.2, FEEDS.size))
    assert fit.params.F_c == pytest.approx(44.2, rel=0.01)
    assert fit.params.sigma == pytest.approx(168.0, rel=0.03)
    assert fit.params.F_s == fit.params.F_c
    assert fit.rms == pytest.approx(0.2, rel=0.5)


def test_mixed_directions_are_rejected():
    with pytest.raises(ValueError, match="one sign"):
        fit_andersson(SWEEP_V, TRUTH.force(SWEEP_V))


@pytest.mark.parametrize("law", [POSITIVE, NEGATIVE])
@pytest.mark.parametrize("fraction", [0.05, 0.25])
def test_invariant_feed_matches_closed_form(law, fraction):
    """For δ = 1 and tanh ≈ 1, dF/dv = σ − (ΔF/v_s) exp(−v/v_s); |dF/dv| = f K_p at
    v* = v_s ln(ΔF / (v_s (σ + f K_p)))."""
    closed = law.v_s * np.log((law.F_s - law.F_c) / (law.v_s * (law.sigma + fraction * K_P_LAB)))
    assert invariant_feed(law, K_P_LAB, fraction) == pytest.approx(closed, rel=1e-4)


def test_invariant_feed_of_lab_bench():
    """5 % of K_p gives ≈ 979 (+) / 1135 (−) mm/min; the thesis's ≈ 500 mm/min lies
    near a quarter of K_p (479 / 580 mm/min)."""
    assert invariant_feed(POSITIVE, K_P_LAB) / MM_PER_MIN == pytest.approx(979.2, abs=1.0)
    assert invariant_feed(NEGATIVE, K_P_LAB) / MM_PER_MIN == pytest.approx(1134.9, abs=1.0)
    assert invariant_feed(POSITIVE, K_P_LAB, 0.25) / MM_PER_MIN == pytest.approx(479.2, abs=1.0)


def test_invariant_feed_refuses_dominant_viscous_slope():
    with pytest.raises(ValueError, match="viscous slope"):
        invariant_feed(POSITIVE, K_p=1000.0, fraction=0.05)
