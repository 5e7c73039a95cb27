"""Stiffness, backlash and preload loss (Ch. 3.4) on synthetic dead-zone + spring data
with the rack-and-pinion numbers of DIGEST §3 as truth."""

import numpy as np
import pytest

from feedbench.analysis.stiffness import (
    backlash_from_reversals,
    equivalent_stiffness,
    incremental_stiffness,
    mesh_stiffness,
    mesh_stiffness_bounds,
    preload_loss_force,
    series_stiffness,
    torque_sharing,
)
from feedbench.units import N_PER_UM

K_MASTER = 81.0 * N_PER_UM
K_SLAVE = 100.0 * N_PER_UM
BACKLASH_MASTER = 314e-6
BACKLASH_SLAVE = 363e-6
NOISE_X = 0.3e-6
NOISE_F = 10.0


def play(x_motor: np.ndarray, half_width: float) -> np.ndarray:
    """Load position behind a dead zone: it follows only once |x_motor − x_load| > half_width."""
    x_load = np.empty_like(x_motor)
    current = x_motor[0] - half_width
    for i, x in enumerate(x_motor):
        current = min(max(current, x - half_width), x + half_width)
        x_load[i] = current
    return x_load


def single_motor_loading(rng, k, backlash):
    """One motor pushes the carriage into the bumper: take-up of the dead zone at zero load,
    loading to 10 kN along δ = L_z/2 + F/k, then unloading with 300 N of hysteresis."""
    take_up = np.linspace(-backlash / 2, backlash / 2, 30)
    load_up = np.linspace(0.0, 10e3, 200)
    load_down = np.linspace(10e3, 0.0, 200)[1:]
    force = np.concatenate([np.zeros(take_up.size), load_up, load_down])
    delta = np.concatenate([take_up, backlash / 2 + load_up / k, backlash / 2 + (load_down + 300.0) / k])
    x_load = np.linspace(0.0, 50e-6, force.size) + rng.normal(0.0, NOISE_X, force.size)
    x_motor = x_load + delta + rng.normal(0.0, NOISE_X, force.size)
    return force + rng.normal(0.0, NOISE_F, force.size), x_motor, x_load


@pytest.mark.parametrize("k, backlash", [(K_MASTER, BACKLASH_MASTER), (K_SLAVE, BACKLASH_SLAVE)])
def test_equivalent_stiffness_of_one_motor(k, backlash):
    force, x_motor, x_load = single_motor_loading(np.random.default_rng(1), k, backlash)
    fit = equivalent_stiffness(force, x_motor, x_load)
    assert fit.k == pytest.approx(k, rel=0.01)
    assert 3.0 * fit.k_std < 0.01 * k
    assert fit.offset == pytest.approx(backlash / 2, abs=2e-6)
    assert fit.r_squared > 0.99
    assert fit.force_range[0] >= 1.9e3 and fit.force_range[1] > 9.9e3


def test_equivalent_stiffness_of_a_pushing_load_in_the_negative_direction():
    force, x_motor, x_load = single_motor_loading(np.random.default_rng(2), K_MASTER, BACKLASH_MASTER)
    fit = equivalent_stiffness(-force, -x_motor, -x_load)
    assert fit.k == pytest.approx(K_MASTER, rel=0.01)


def triangle_moves(stroke=1e-3, cycles=3, n=6000):
    """Back-and-forth moves of `stroke` (m), starting upward from zero."""
    phase = np.linspace(0.0, cycles, n)
    return stroke * (1.0 - np.abs(2.0 * (phase % 1.0) - 1.0))


@pytest.mark.parametrize("backlash", [BACKLASH_MASTER, BACKLASH_SLAVE])
def test_backlash_from_pure_dead_zone(backlash):
    rng = np.random.default_rng(4)
    x_motor = triangle_moves()
    x_load = play(x_motor, backlash / 2)
    est = backlash_from_reversals(
        x_motor + rng.normal(0.0, NOISE_X, x_motor.size), x_load + rng.normal(0.0, NOISE_X, x_motor.size)
    )
    assert est.value == pytest.approx(backlash, abs=2e-6)
    assert est.per_reversal.size == 5
    assert est.std < 1e-6


def test_backlash_includes_friction_windup():
    """A spring k behind the dead zone and 200 N of load friction: the load starts once the
    spring carries the friction, so the measured lost motion is L_z + 2 F_f / k."""
    friction = 200.0
    x_motor = triangle_moves()
    x_load = play(x_motor, BACKLASH_MASTER / 2 + friction / K_MASTER)
    est = backlash_from_reversals(x_motor, x_load)
    assert est.value == pytest.approx(BACKLASH_MASTER + 2 * friction / K_MASTER, abs=1e-9)


def test_backlash_needs_a_reversal():
    ramp = np.linspace(0.0, 1e-3, 100)
    with pytest.raises(ValueError, match="reversal"):
        backlash_from_reversals(ramp, ramp)


def coupled_loading(rng, loss_force, k=K_MASTER, backlash=BACKLASH_MASTER, n_crossing=6, noise=1.0):
    """Master and slave in contact, preload P = loss_force / 2 against the load (Eq. 3.1):
    the master carries F/2 − P through k, crosses its dead zone at F = 2P (n_crossing
    samples at constant load), then carries again on the other flank (Fig. 3.11-a)."""
    load_up = np.arange(0.0, 20e3, 50.0)
    delta = (load_up / 2 - loss_force / 2) / k + np.where(load_up < loss_force, -0.5, 0.5) * backlash
    crossing = np.linspace(-0.5, 0.5, n_crossing + 2)[1:-1] * backlash
    force = np.concatenate([load_up[load_up < loss_force], np.full(n_crossing, loss_force),
                            load_up[load_up >= loss_force], np.linspace(20e3, 0.0, 100)])
    delta = np.concatenate([delta[load_up < loss_force], crossing, delta[load_up >= loss_force],
                            np.linspace(delta[-1], delta[0], 100)])
    x_load = rng.normal(0.0, noise * NOISE_X, force.size)
    x_master = x_load + delta + rng.normal(0.0, noise * NOISE_X, force.size)
    return force + rng.normal(0.0, noise * NOISE_F, force.size), x_master, x_load


@pytest.mark.parametrize("loss_force", [1100.0, 5300.0, 6600.0])
def test_preload_loss_force(loss_force):
    force, x_master, x_load = coupled_loading(np.random.default_rng(int(loss_force)), loss_force)
    loss = preload_loss_force(force, x_master, x_load)
    assert loss.force == pytest.approx(loss_force, rel=0.05)
    assert loss.jump == pytest.approx(BACKLASH_MASTER, abs=2e-6)
    assert loss.k_after == pytest.approx(K_MASTER, rel=0.01)
    assert loss.k_before == pytest.approx(K_MASTER, rel=0.1 if loss_force < 2e3 else 0.02)


@pytest.mark.parametrize("loss_force", [1100.0, 5300.0])
def test_preload_loss_force_without_samples_in_the_crossing(loss_force):
    """A fast crossing leaves no sample in the dead zone: the loss is bracketed by the last
    load on the first line and the first on the second (50 N steps here)."""
    force, x_master, x_load = coupled_loading(np.random.default_rng(7), loss_force, n_crossing=0)
    loss = preload_loss_force(force, x_master, x_load)
    assert loss.force == pytest.approx(loss_force, rel=0.05)
    assert loss.jump == pytest.approx(BACKLASH_MASTER, abs=2e-6)


def test_incremental_stiffness_drops_to_zero_at_the_loss():
    """Noise-free: Eq. (3.26) gives k_m on both contact segments and 0 across the dead zone
    (loss at 5300 N: samples 106–111 cross it at constant load)."""
    force, x_master, x_load = coupled_loading(np.random.default_rng(0), 5300.0, noise=0.0)
    k_inc = incremental_stiffness(force, x_master - x_load)
    np.testing.assert_allclose(k_inc[:105], K_MASTER, rtol=1e-9)
    np.testing.assert_allclose(k_inc[106:111], 0.0, atol=1e-9)
    np.testing.assert_allclose(k_inc[112:400], K_MASTER, rtol=1e-9)


def test_torque_sharing_recovers_share_and_preload():
    rng = np.random.default_rng(5)
    tau_ref = np.linspace(-40.0, 120.0, 300)
    tau_master = 0.45 * tau_ref + 7.0 + rng.normal(0.0, 0.1, tau_ref.size)
    tau_slave = tau_ref - tau_master
    sharing = torque_sharing(tau_master, tau_slave)
    assert sharing.share == pytest.approx(0.45, abs=0.002)
    assert sharing.preload == pytest.approx(7.0, abs=0.05)


def test_iso6336_mesh_stiffness_bounds():
    """c' = 13.75 (N/mm)/µm, b = 40 mm: ε_α = 1 and 2 give 550 and 962 N/µm (Ch. 3.4.3)."""
    c_prime = 13.75e9
    low, high = mesh_stiffness_bounds(c_prime, 0.040)
    assert low / N_PER_UM == pytest.approx(550.0, rel=1e-12)
    assert high / N_PER_UM == pytest.approx(962.0, abs=0.5)
    assert mesh_stiffness(c_prime, 1.48, 0.040) / N_PER_UM == pytest.approx(748.0, abs=0.01)


def test_series_stiffness():
    assert series_stiffness(2.0, 2.0) == pytest.approx(1.0)
    assert series_stiffness(K_MASTER, 748.0 * N_PER_UM) == pytest.approx(
        1.0 / (1.0 / K_MASTER + 1.0 / (748.0 * N_PER_UM))
    )
