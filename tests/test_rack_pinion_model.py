"""The rack-and-pinion axis model (Ch. 3.2) against its own equations: Eq. (3.3), the preload
split of Eq. (3.1) with weighting factors, the static stiffness and dead zone, the preload
loss at F = 2 τ_p K_tr, the decoupled modes and the bumper."""

from __future__ import annotations

import numpy as np
import pytest

from feedbench.models._kernel import CSP
from feedbench.models.rack_pinion import (
    COUPLED, MASTER_ALONE, SLAVE_ALONE, Bumper, Preload, RackPinionAxis, RackPinionSimulator,
)
from feedbench.models.friction import NO_FRICTION


def staircase(step: float, n: int, plateau: int, hold: int = 1500) -> tuple[np.ndarray, np.ndarray]:
    """Targets (m): `hold` cycles at 0, then n steps of `step` (20-cycle ramps, `plateau`
    cycles each); and the index of the last cycle of each plateau."""
    parts, x = [np.zeros(hold)], 0.0
    for _ in range(n):
        parts += [np.linspace(x, x + step, 21)[1:], np.full(plateau - 20, x + step)]
        x += step
    return np.concatenate(parts), hold + plateau * np.arange(1, n + 1) - 1


def test_equivalent_inertia_and_rated_force_at_the_rack():
    """Eq. (3.3) with DIGEST §3: J_eq = 7500e-6 + 948e-6 kg·m², seen at the rack through
    K_tr = i_red / r = 190 N per N·m."""
    axis = RackPinionAxis()
    assert axis.K_tr == pytest.approx(190.0, rel=1e-12)
    assert axis.J_eq == pytest.approx(8448e-6, rel=1e-12)
    assert axis.m_motor == pytest.approx(8448e-6 * 190.0**2, rel=1e-12)
    assert axis.rated_force == pytest.approx(70.0 * 190.0, rel=1e-12)
    assert RackPinionAxis(J_pinion=0.784).J_eq == pytest.approx(8448e-6 + 0.784 / 28**2)


@pytest.mark.parametrize("K_Tm, K_Ts", [(0.5, 0.5), (0.6, 0.4)])
def test_preload_split_under_a_load_follows_the_weighting(K_Tm, K_Ts):
    """At rest under a constant load F on the carriage: F_m + F_s = −F and
    K_Tm F_m − K_Ts F_s = F_p (Fig. 3.2), i.e. F_m = (F_p − K_Ts F)/(K_Tm + K_Ts) — Eq. (3.1)
    for K_Tm = K_Ts = 1/2."""
    axis = RackPinionAxis(bumper=None, friction=NO_FRICTION)
    sim = RackPinionSimulator(axis, preload=Preload(0.10, K_Tm, K_Ts))
    load = 2000.0
    out = sim.simulate(CSP, np.zeros(6000), load_force=np.r_[np.zeros(2000), np.full(4000, load)])
    f_p = 0.10 * axis.rated_force
    master, slave = out["master_force"][-1], out["slave_force"][-1]
    assert master + slave == pytest.approx(-load, abs=1.0)
    assert master == pytest.approx((f_p - K_Ts * load) / (K_Tm + K_Ts), abs=2.0)
    assert abs(out["load_position"][-1]) < 1e-7, "the position loop holds the scale at 0"


def test_single_motor_statics_are_spring_behind_dead_zone():
    """Master alone pushing into the bumper: at the end of each plateau δ = x_m − x_load =
    −(L_z/2 + F/k_m), the bumper force carried by the spring behind the dead zone (Eqs.
    3.4, 3.26); within 0.2 µm, the load still creeping under the guideway friction."""
    axis = RackPinionAxis()
    sim = RackPinionSimulator(axis)
    sim.coupling = MASTER_ALONE
    targets, ends = staircase(-40e-6, 12, 1500)
    out = sim.simulate(CSP, targets)
    force = out["bumper_force"][ends]
    delta = (out["master_position"] - out["load_position"])[ends]
    loaded = force > 500.0
    assert np.count_nonzero(loaded) >= 4
    np.testing.assert_allclose(-delta[loaded], axis.backlash_master / 2 + force[loaded]
                               / axis.k_master, rtol=0, atol=0.2e-6)
    assert np.all(np.abs(out["slave_force"]) == 0.0), "the slave is off"


def test_preload_is_lost_where_the_master_torque_reaches_zero():
    """Coupled at 4 % and 25 %: the master's force crosses zero at a bumper load of
    2 τ_p K_tr (Eq. 3.1), and its pinion then changes flank: δ_m jumps by L_z,m."""
    axis = RackPinionAxis()
    for level, step in ((0.04, -3e-6), (0.25, -10e-6)):
        sim = RackPinionSimulator(axis, preload=Preload(level))
        targets, ends = staircase(step, int(round(280e-6 / -step)), 600, hold=2500)
        out = sim.simulate(CSP, targets)
        force, master = out["bumper_force"][ends], out["master_force"][ends]
        f_p = level * axis.rated_force
        carrying = (force > 50.0) & (master > 0.2 * f_p)
        slope, intercept = np.polyfit(master[carrying], force[carrying], 1)
        assert slope == pytest.approx(-2.0, rel=0.01), "F_m = F_p − F/2 (Eq. 3.1)"
        loss = intercept
        assert loss == pytest.approx(2 * level * axis.rated_force, rel=0.02)
        delta = (out["master_position"] - out["load_position"])[ends]
        assert master[0] == pytest.approx(f_p, rel=0.01)
        assert delta[0] == pytest.approx(axis.backlash_master / 2 + master[0] / axis.k_master,
                                         abs=0.05e-6)
        assert delta[-1] < -axis.backlash_master / 2, "the master carries on the other flank"


def test_alone_modes_drive_one_motor_and_start_from_the_scale():
    """A coupling change references the new feedback encoder to the linear scale: the
    feedback continues from the scale's value, and only the driving motor produces force."""
    sim = RackPinionSimulator(RackPinionAxis(bumper=None), preload=Preload(0.0))
    sim.simulate(CSP, np.zeros(2000))
    for coupling, driving, off in ((SLAVE_ALONE, "slave", "master"),
                                   (MASTER_ALONE, "master", "slave"), (COUPLED, "master", "")):
        scale = sim.load_position
        sim.coupling = coupling
        out = sim.simulate(CSP, np.r_[np.full(50, scale), np.linspace(scale, 1e-3, 1500)])
        assert abs(out["position_feedback"][0] - scale) < 0.1e-6
        assert np.max(np.abs(out[f"{driving}_force"])) > 100.0
        if off:
            assert np.all(out[f"{off}_force"] == 0.0)
        assert out["position_feedback"][-1] == pytest.approx(1e-3, abs=20e-6)
        sim.simulate(CSP, np.r_[np.linspace(1e-3, 0.0, 1500), np.zeros(1500)])
    np.testing.assert_array_equal(out["position_feedback"], out["load_position"])


def test_bumper_only_pushes_back():
    axis = RackPinionAxis(bumper=Bumper(position=-100e-6))
    sim = RackPinionSimulator(axis)
    away = sim.simulate(CSP, np.linspace(0.0, 2e-3, 2000))
    assert np.all(away["bumper_force"] == 0.0)
    into = sim.simulate(CSP, np.r_[np.linspace(2e-3, -150e-6, 2000), np.full(3000, -150e-6)])
    penetration = axis.bumper.position - into["load_position"][-1]
    assert into["bumper_force"][-1] == pytest.approx(
        axis.bumper.stiffness * penetration - axis.bumper.damping * into["load_velocity"][-1],
        rel=1e-9)
    assert into["bumper_force"][-1] > 1000.0


def test_rejects_unknown_modes_and_couplings():
    sim = RackPinionSimulator()
    with pytest.raises(ValueError, match="mode"):
        sim.step_cycle(7, 0.0)
    with pytest.raises(ValueError, match="coupling"):
        sim.coupling = 5
    with pytest.raises(ValueError, match="bumper position"):
        Bumper(position=0.0)
