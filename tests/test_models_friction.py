"""Andersson friction, Eq. (5.2), with the lab-bench parameters of Fig. 5.11 (DIGEST §3)."""

import math

import numpy as np
import pytest

from feedbench.models.friction import LAB_BENCH_FRICTION, AnderssonFriction, DirectionalFriction
from feedbench.units import MM_PER_MIN

POSITIVE = LAB_BENCH_FRICTION.positive
NEGATIVE = LAB_BENCH_FRICTION.negative


@pytest.mark.parametrize(
    "feed_mm_min, expected_N",
    [
        # 44.2 + 39.8 e^(−500/387.4) + 0.0028·500 (tanh(0.25·500) = 1)
        (500.0, 56.54859633234448),
        # (44.2 + 39.8 e^(−1/387.4)) tanh(0.25·1) + 0.0028·1
        (1.0, 20.55083807924576),
        # −(38.7 + 49.3 e^(−1000/421)) − 0.0025·1000
        (-1000.0, -45.784252995751025),
        (0.0, 0.0),
    ],
)
def test_lab_bench_law_matches_hand_computed_values(feed_mm_min, expected_N):
    force = LAB_BENCH_FRICTION.force(feed_mm_min * MM_PER_MIN)
    assert force == pytest.approx(expected_N, rel=1e-12)


def test_stribeck_shape_exponent_and_negative_side():
    law = AnderssonFriction.from_engineering(38.7, 88.0, 421.0, 0.0025, 0.25, delta=0.5)
    # (38.7 + 49.3 e^(−(20/421)^0.5)) tanh(−0.25·20) − 0.0025·20
    assert law.force(-20.0 * MM_PER_MIN) == pytest.approx(-78.38791333859025, rel=1e-12)


def test_direction_selects_parameter_set():
    v = 1500.0 * MM_PER_MIN
    assert LAB_BENCH_FRICTION.force(v) == pytest.approx(POSITIVE.force(v), rel=1e-15)
    assert LAB_BENCH_FRICTION.force(-v) == pytest.approx(NEGATIVE.force(-v), rel=1e-15)
    # 44.2 + 39.8 e^(−1500/387.4) + 4.2  vs  −(38.7 + 49.3 e^(−1500/421) + 3.75)
    assert LAB_BENCH_FRICTION.force(v) == pytest.approx(
        44.2 + 39.8 * math.exp(-1500 / 387.4) + 4.2, rel=1e-12)
    assert LAB_BENCH_FRICTION.force(-v) == pytest.approx(
        -(38.7 + 49.3 * math.exp(-1500 / 421) + 3.75), rel=1e-12)
    # just below zero the negative side's F_s = 88 N acts: −88 tanh(15000 · 1e-9) − 150 · 1e-9
    assert LAB_BENCH_FRICTION.force(-1e-9) == pytest.approx(
        -88.0 * math.tanh(15e-6) - 150e-9, rel=1e-6)


def test_engineering_constructor_matches_si():
    si = AnderssonFriction(F_c=44.2, F_s=84.0, v_s=387.4 / 60000.0, sigma=0.0028 * 60000.0,
                           k_tanh=0.25 * 60000.0, delta=1.0)
    for name in ("F_c", "F_s", "v_s", "sigma", "k_tanh", "delta"):
        assert getattr(POSITIVE, name) == pytest.approx(getattr(si, name), rel=1e-12)
    assert NEGATIVE.v_s == pytest.approx(421.0 / 60000.0, rel=1e-12)
    assert NEGATIVE.sigma == pytest.approx(150.0, rel=1e-12)  # 0.0025 N·min/mm


def test_coulomb_viscous_limit_without_stribeck():
    law = AnderssonFriction(F_c=40.0, F_s=40.0, v_s=np.inf, sigma=150.0)
    v = np.array([-0.01, 1e-5, 0.02])
    np.testing.assert_allclose(law.force(v), 40.0 * np.tanh(15000.0 * v) + 150.0 * v, rtol=1e-13)


def test_slope_is_the_derivative_of_force():
    v = np.array([-0.02, -3e-4, -1e-6, 2e-6, 1e-4, 0.005, 0.05])
    h = 1e-7 * np.maximum(np.abs(v), 1e-6)
    numeric = (LAB_BENCH_FRICTION.force(v + h) - LAB_BENCH_FRICTION.force(v - h)) / (2 * h)
    np.testing.assert_allclose(LAB_BENCH_FRICTION.slope(v), numeric, rtol=1e-5)
    # at standstill the slope is F_s k_tanh + σ: 84 N · 15000 s/m + 168 N·s/m
    assert POSITIVE.slope(0.0) == pytest.approx(84.0 * 15000.0 + 168.0, rel=1e-12)


def test_shapes_and_scalars():
    grid = np.linspace(-0.01, 0.01, 12).reshape(3, 4)
    assert LAB_BENCH_FRICTION.force(grid).shape == (3, 4)
    assert isinstance(POSITIVE.force(0.001), float)
    assert isinstance(DirectionalFriction(POSITIVE, NEGATIVE).force(0.0), float)


@pytest.mark.parametrize("field, value", [("F_c", -1.0), ("v_s", 0.0), ("k_tanh", -5.0),
                                          ("sigma", float("nan"))])
def test_invalid_parameters_are_rejected(field, value):
    params = dict(F_c=40.0, F_s=80.0, v_s=0.005, sigma=150.0)
    params[field] = value
    with pytest.raises(ValueError, match=field):
        AnderssonFriction(**params)
