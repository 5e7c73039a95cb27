"""Milling force model (Eqs. 6.1–6.5) and the regenerative cutting simulation (Ch. 6.3.2)."""

import math

import numpy as np
import pytest

from feedbench.models.milling import (
    MILLING_MODES,
    SMFE_SENSOR_NOISE,
    SMFE_TOOL,
    TABLE_6_1,
    Tool,
    cutting_forces,
    engagement_angles,
    simulate_smfe_cut,
    spindle_ramp,
    stationary_forces,
)
from feedbench.models.structure import ModalStructure

A_P, A_E, FS = 2e-3, 12e-3, 10_000.0


@pytest.mark.parametrize(
    ("mode", "entry_deg", "exit_deg"),
    [("down", 134.4, 180.0), ("up", 0.0, 45.6), ("central", 81.4, 98.6)],
)
def test_engagement_angles_of_the_smfe_cuts(mode, entry_deg, exit_deg):
    """DIGEST §3b: a_e = 12 mm on D = 80 mm."""
    phi_en, phi_ex = engagement_angles(A_E, SMFE_TOOL.D, mode)
    assert math.degrees(phi_en) == pytest.approx(entry_deg, abs=0.05)
    assert math.degrees(phi_ex) == pytest.approx(exit_deg, abs=0.05)


def _mean_force_closed_form(a_p, a_e, mode, tool, k, f_z):
    """Revolution-averaged force, Eqs. (6.1, 6.3–6.5) integrated by hand over the engaged arc.

    For κ = 90° this is the classic average-force expression (Altintas, Manufacturing Automation).
    """
    en, ex = engagement_angles(a_e, tool.D, mode)
    s_k, c_k = math.sin(tool.kappa), math.cos(tool.kappa)

    def arc(g):
        return g(ex) - g(en)

    I_sc = arc(lambda p: math.sin(p) ** 2 / 2)  # ∫ sin cos
    I_ss = arc(lambda p: p / 2 - math.sin(2 * p) / 4)  # ∫ sin²
    I_c = arc(math.sin)  # ∫ cos
    I_s = arc(lambda p: -math.cos(p))  # ∫ sin
    h0 = f_z * s_k
    radial_shear = s_k * k.K_rc + c_k * k.K_ac
    radial_edge = s_k * k.K_re + c_k * k.K_ae
    fx = -k.K_tc * h0 * I_sc - k.K_te * I_c - radial_shear * h0 * I_ss - radial_edge * I_s
    fy = k.K_tc * h0 * I_ss + k.K_te * I_s - radial_shear * h0 * I_sc - radial_edge * I_c
    fz = (c_k * k.K_rc - s_k * k.K_ac) * h0 * I_s + (c_k * k.K_re - s_k * k.K_ae) * (ex - en)
    return tool.Z * a_p / s_k / (2 * math.pi) * np.array([fx, fy, fz])


@pytest.mark.parametrize("mode", MILLING_MODES)
@pytest.mark.parametrize("tool", [SMFE_TOOL, Tool(D=0.040, Z=4, kappa=math.pi / 2)])
def test_mean_force_matches_the_hand_integrated_model(mode, tool):
    theta = np.arange(36_000) * 2 * np.pi / 36_000
    a_e = 0.3 * tool.D
    mean = stationary_forces(theta, A_P, a_e, mode, tool, TABLE_6_1).mean(axis=0)
    expected = _mean_force_closed_form(A_P, a_e, mode, tool, TABLE_6_1, 0.1e-3)
    np.testing.assert_allclose(mean, expected, rtol=1e-3, atol=0.05)


def test_teeth_outside_the_engagement_carry_no_force():
    """Screen function, Eq. (6.4): only teeth with φ_en < φ mod 2π < φ_ex cut."""
    phi_en, phi_ex = engagement_angles(A_E, SMFE_TOOL.D, "up")
    outside = np.array([[math.radians(200.0), math.radians(380.0 + 45.7)]])  # 200°, 65.7° mod 360
    inside = np.array([[math.radians(20.0), math.radians(200.0)]])
    h = np.full((1, 2), 0.05e-3)
    assert np.all(cutting_forces(outside, h, A_P, SMFE_TOOL, TABLE_6_1, phi_en, phi_ex) == 0.0)
    one_tooth = cutting_forces(inside[:, :1], h[:, :1], A_P, SMFE_TOOL, TABLE_6_1, phi_en, phi_ex)
    both = cutting_forces(inside, h, A_P, SMFE_TOOL, TABLE_6_1, phi_en, phi_ex)
    np.testing.assert_array_equal(both, one_tooth)


def test_rigid_machine_cut_gives_the_stationary_force():
    """k = 10⁵ N/µm: deflections ≈ 3 nm ≪ f_z, so the simulated force is the stationary one."""
    rigid = ModalStructure((400.0,) * 3, (0.05,) * 3, (1e11,) * 3, np.eye(3))
    rpm = np.full(5_000, 600.0)
    cut = simulate_smfe_cut(rigid, SMFE_TOOL, TABLE_6_1, A_P, A_E, "down", rpm, FS)
    np.testing.assert_allclose(cut["theta"], 600.0 * 2 * np.pi / 60 * cut["t"], rtol=1e-12)
    expected = stationary_forces(cut["theta"], A_P, A_E, "down", SMFE_TOOL, TABLE_6_1).T
    assert np.max(np.abs(cut["F"] - expected)) < 1e-3 * np.max(np.abs(expected))


@pytest.mark.parametrize("mode", MILLING_MODES)
def test_regeneration_cancels_a_static_deflection(mode):
    """Eq. (6.2): a slowly moving tool (3 Hz modes, k = 2 N/µm, far below tooth passing) is
    deflected statically by ≈ 20–50 µm, but the surface left by the previous tooth moved with it,
    so the chip and the mean force stay the rigid ones (within 3 %, measured ≤ 2.3 %). Had the
    chip seen the deflection itself, it would change by > 20 % of f_z."""
    soft = ModalStructure((3.0,) * 3, (0.5,) * 3, (2e6,) * 3, np.eye(3))
    cut = simulate_smfe_cut(soft, SMFE_TOOL, TABLE_6_1, A_P, A_E, mode, np.full(60_000, 600.0), FS)
    settled = cut["F"][:, -20_000:].mean(axis=1)
    theta = np.arange(3_600) * 2 * np.pi / 3_600
    rigid = stationary_forces(theta, A_P, A_E, mode, SMFE_TOOL, TABLE_6_1).mean(axis=0)
    np.testing.assert_allclose(settled, rigid, rtol=0.03, atol=0.03 * np.abs(rigid).max())
    phi_mid = np.mean(engagement_angles(A_E, SMFE_TOOL.D, mode))
    u = np.array([math.sin(phi_mid) * math.sin(SMFE_TOOL.kappa),
                  math.cos(phi_mid) * math.sin(SMFE_TOOL.kappa), -math.cos(SMFE_TOOL.kappa)])
    assert abs(u @ settled / 2e6) > 0.2 * 0.1e-3


def test_spindle_ramp_of_the_author_setup():
    """DIGEST §3b: 600 rpm + 1.5 rad/s² for 65 s ≈ 600 → 1531 rpm, tooth passing ≈ 20 → 51 Hz."""
    rpm = spindle_ramp(600.0, 1.5, 65.0, FS)
    assert rpm.size == 650_000
    assert rpm[0] == 600.0
    assert rpm[-1] == pytest.approx(600.0 + 1.5 * 65.0 * 60 / (2 * math.pi), abs=0.01)
    assert rpm[-1] == pytest.approx(1531.0, abs=0.5)
    assert (rpm[0] * SMFE_TOOL.Z / 60, rpm[-1] * SMFE_TOOL.Z / 60) == pytest.approx((20.0, 51.0), abs=0.1)


def test_sensor_noise_has_the_requested_standard_deviation():
    """Eq. (6.18): zero-mean Gaussian noise of σ = 0.016, 0.012, 0.0014 m/s² on x, y, z."""
    structure = ModalStructure((58.6,), (0.03,), (36.7e6,), np.ones((3, 1)))
    rpm = np.full(100_000, 900.0)
    clean = simulate_smfe_cut(structure, SMFE_TOOL, TABLE_6_1, A_P, A_E, "up", rpm, FS)
    noisy = simulate_smfe_cut(structure, SMFE_TOOL, TABLE_6_1, A_P, A_E, "up", rpm, FS,
                              noise_std=SMFE_SENSOR_NOISE, seed=7)
    noise = noisy["acc"] - clean["acc"]
    np.testing.assert_allclose(noise.std(axis=1), SMFE_SENSOR_NOISE, rtol=0.02)
    assert np.all(np.abs(noise.mean(axis=1)) < 4 * np.array(SMFE_SENSOR_NOISE) / math.sqrt(rpm.size))
    np.testing.assert_array_equal(noisy["F"], clean["F"])


@pytest.mark.parametrize(
    ("overrides", "field"),
    [
        ({"mode": "climb"}, "mode"),
        ({"a_e": 0.1}, "a_e"),
        ({"a_p": 0.0}, "a_p"),
        ({"fs": 2_000.0}, "fs"),
        ({"noise_std": (0.01, 0.01)}, "noise_std"),
    ],
)
def test_bad_cut_inputs_name_the_field(overrides, field):
    structure = ModalStructure((58.6,), (0.03,), (36.7e6,), np.ones((3, 1)))
    arguments = {"structure": structure, "tool": SMFE_TOOL, "coeffs": TABLE_6_1, "a_p": A_P,
                 "a_e": A_E, "mode": "down", "rpm_profile": np.full(100, 1500.0), "fs": FS}
    with pytest.raises(ValueError, match=field):
        simulate_smfe_cut(**{**arguments, **overrides})
