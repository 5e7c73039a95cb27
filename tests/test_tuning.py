"""Standard P-PI tuning (Eqs. 4.2, 4.8, 4.12) and f_t, f_r (4.13, 4.14) against thesis numbers."""

import pytest

from feedbench.analysis.tuning import (
    bandwidth_tunings,
    engineering_gains,
    optimum_bandwidth,
    standard_gains,
    total_mass,
)
from feedbench.models.axis import TwoMassAxis

CHAPTER4_BENCH = TwoMassAxis(m_mot=24.9, m_tip=9.5, k=1.98e6, c=104.0)
"""Ch. 4.2.3 bench (DIGEST §3)."""


def test_table_4_1_controller_c1_from_45_hz():
    """M_total = 80 + 130 + 10.8 kg at 45 Hz: K_p 62.4 kN·s/m, T_i 7.07 ms, K_v 4.24 (m/min)/mm."""
    gains = engineering_gains(standard_gains(80.0 + 130.0 + 10.8, 45.0))
    assert gains.K_p == pytest.approx(62.4e3, rel=5e-3)
    assert gains.T_i_ms == pytest.approx(7.07, abs=0.005)
    assert gains.K_v_m_min_per_mm == pytest.approx(4.24, abs=0.005)


def test_k_v_unit_conversion():
    """K_v = π·45/2 = 70.69 1/s; 1 (m/min)/mm = 16.67 1/s."""
    gains = standard_gains(220.8, 45.0)
    assert gains.K_v == pytest.approx(70.69, abs=0.01)
    assert gains.K_v / engineering_gains(gains).K_v_m_min_per_mm == pytest.approx(16.667, abs=1e-3)


def test_lab_bench_characteristic_frequencies():
    """Ch. 5.3.2 bench: f_t = 61.4 Hz, f_r = 74.9 Hz (DIGEST §3 check values)."""
    axis = TwoMassAxis()
    assert axis.f_t == pytest.approx(61.4, abs=0.05)
    assert axis.f_r == pytest.approx(74.9, abs=0.05)


def test_chapter4_tunings():
    """Low 15 Hz, high 87 Hz, optimum 58 Hz = 80 % of f_t on M_total = 34.4 kg."""
    assert total_mass(CHAPTER4_BENCH) == pytest.approx(34.4)
    assert optimum_bandwidth(CHAPTER4_BENCH) == pytest.approx(58.0, abs=0.5)
    tunings = bandwidth_tunings(CHAPTER4_BENCH)
    assert tunings["high"].K_p == pytest.approx(2 * 3.141592653589793 * 34.4 * 87.0)
    assert tunings["low"].T_i == pytest.approx(1.0 / (3.141592653589793 * 15.0))
    assert tunings["optimum"].K_v == pytest.approx(3.141592653589793 * 58.13 / 2, rel=1e-3)
