"""The simulated world's extra effects (`models.effects` in the axis kernel) and the
generator of recordings with undeclared effects (`sim_backends.effects`)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from feedbench.config import ConfigError
from feedbench.models.axis import CSP, CST, AxisSimulator, TwoMassAxis
from feedbench.models.effects import AxisEffects, acting_force, reported_force, ripple_force
from feedbench.models.friction import NO_FRICTION
from feedbench.sim_backends.effects import parse_world, simulate_recording

RIGID = TwoMassAxis(m_mot=20.0, m_tip=10.0, k=1e9, c=5e4, friction=NO_FRICTION)


def test_ripple_force_accelerates_a_free_axis_from_rest():
    effects = AxisEffects(ripple_amplitude=6.0, ripple_pitch=0.01, ripple_phase=0.3)
    sim = AxisSimulator(RIGID, effects=effects)
    sim.reset(position=0.0025)
    out = sim.simulate(CST, 0.0, 0.0, np.zeros(5))
    expected = ripple_force(0.0025, 6.0, 0.01, 0.3) / 30.0  # m/s² on the whole rigid pair
    assert out["mean_velocity"][0] / 1e-3 == pytest.approx(0.5 * expected, rel=0.02)
    assert out["velocity"][4] / 5e-3 == pytest.approx(expected, rel=0.02)


def test_force_level_nonlinearity_acts_less_than_it_reports():
    beta = 1.5e-3
    sim = AxisSimulator(RIGID, effects=AxisEffects(force_level=beta))
    out = sim.simulate(CST, 0.0, 0.0, np.full(20, 300.0))
    acting = acting_force(300.0, beta)
    assert reported_force(acting, beta) == pytest.approx(300.0)
    assert out["mean_force"][-1] == pytest.approx(300.0)
    slope = (out["velocity"][-1] - out["velocity"][9]) / 10e-3
    assert slope == pytest.approx(acting / 30.0, rel=1e-3)
    assert acting == pytest.approx(300.0 / 1.3, rel=0.05)


def test_backlash_opens_the_full_play_at_each_reversal():
    width = 100e-6
    axis = TwoMassAxis(m_mot=23.1, m_tip=11.3, k=1e9, c=2 * 0.3 * math.sqrt(1e9 * 7.6),
                       friction=NO_FRICTION)
    sim = AxisSimulator(axis, effects=AxisEffects(backlash=width, load_coulomb=40.0),
                        physics_substeps=50)
    t = np.arange(1, 4001) * 1e-3
    reference = 0.005 * np.sin(2 * np.pi * 0.5 * t)
    sim.reset(position=reference[0])
    out = sim.simulate(CSP, reference, 0.0, 0.0)
    gap = out["position"] - out["tip_position"]
    assert gap.max() == pytest.approx(width / 2, rel=0.05)
    assert gap.min() == pytest.approx(-width / 2, rel=0.05)


def test_sensor_effects_and_delay_shape_only_the_force_reading():
    base = {"duration_s": 3.0, "force_noise_N": 0.0, "seed": 2, "effects": {"coulomb": {}}}
    clean = simulate_recording(base)
    shifted = simulate_recording({**base, "effects": {
        "coulomb": {}, "sensor_gain": {"gain": 1.1}, "sensor_offset": {"offset_N": 4.0},
        "delay": {"tau_ms": 2.0}}})
    np.testing.assert_array_equal(shifted.channels["position"], clean.channels["position"])
    f = clean.channels["force"]
    np.testing.assert_allclose(shifted.channels["force"][:-2], 1.1 * f[2:] + 4.0, atol=1e-9)
    assert clean.force_lag_s == pytest.approx(0.5e-3)
    assert set(clean.channels) == {"time", "x_ref", "position", "velocity", "force",
                                   "force_offset"}


def test_offset_and_inertia_mismatch_change_the_force_the_drive_needs():
    base = {"duration_s": 6.0, "force_noise_N": 0.0, "excitation_N": 0.0, "seed": 2}
    clean = simulate_recording({**base, "effects": {}})
    loaded = simulate_recording({**base, "effects": {"offset": {"offset_N": 15.0}}})
    still = np.abs(clean.channels["velocity"]) < 1e-6
    difference = loaded.channels["force"] - clean.channels["force"]
    assert np.median(difference[still]) == pytest.approx(15.0, rel=0.01)


@pytest.mark.parametrize("table, message", [
    ({"effects": {"gravity": {}}}, "world.effects.gravity: unknown effect"),
    ({"effects": {"stribeck": {}}}, "world.effects.stribeck: needs effects.coulomb"),
    ({"effects": {"ripple": {"pitch_mm": -1.0}}}, "world.effects.ripple.pitch_mm: must be > 0"),
    ({"stroke_mm": 0.0}, "world.stroke_mm: must be > 0"),
])
def test_world_errors_name_the_field(table, message):
    with pytest.raises(ConfigError, match=message):
        parse_world(table)
