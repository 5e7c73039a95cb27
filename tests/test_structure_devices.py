"""World side of the structure experiments: tip acceleration of the axis kernel, exciters,
impact hammer, accelerometer noise and the DAQ samples the world pushes per bus cycle."""

import numpy as np
import pytest

from feedbench.models.axis import CSP, CSV, AxisSimulator, TwoMassAxis


def test_tip_acceleration_trace_integrates_to_the_tip_velocity_change():
    """Trapezoid rule over the N + 1 trace points = Δ tip velocity of each cycle (exact for
    a linear acceleration; the trace is smooth at 8 kHz, so within 0.05 % of the largest)."""
    sim = AxisSimulator()
    tip_force = np.random.default_rng(1).normal(0.0, 30.0, 2000)
    out = sim.simulate(CSV, 0.0, 0.01, 0.0, tip_force=tip_force)
    dv = np.diff(out["tip_velocity"], prepend=0.0)
    integral = np.trapezoid(out["tip_acceleration_trace"], dx=1e-3 / sim.substeps_per_cycle,
                            axis=1)
    assert np.max(np.abs(dv - integral)) < 5e-4 * np.max(np.abs(dv))
    np.testing.assert_array_equal(out["tip_acceleration"], out["tip_acceleration_trace"][:, -1])


def test_tip_force_ramps_over_the_first_cycle_and_deflects_the_flexure_statically():
    """First-order hold: from rest the tip force rises linearly over the cycle, so the
    acceleration starts at 0 and reaches ≈ F/m_tip at the cycle's end (the flexure has
    barely moved); held, the flexure deflects by F/k (1.68 N/µm) with the motor in CSP."""
    axis = TwoMassAxis()
    sim = AxisSimulator(axis)
    sim.step_cycle(CSP, 0.0, 0.0, 0.0, 0.0, 0.0, tip_force=10.0)
    trace = sim.tip_acceleration_trace
    assert trace.shape == (sim.substeps_per_cycle + 1,) == (9,)
    assert trace[0] == 0.0
    assert trace[-1] == pytest.approx(10.0 / axis.m_tip, rel=0.03)
    assert np.all(np.diff(trace) > 0.0)
    sim.simulate(CSP, 0.0, 0.0, 0.0, tip_force=np.full(3000, 10.0))
    assert sim.tip_position - sim.position == pytest.approx(10.0 / axis.k, rel=1e-3)
    assert abs(sim.tip_acceleration) < 1e-3


def test_step_cycle_and_simulate_give_the_same_tip_acceleration():
    tip_force = np.random.default_rng(2).normal(0.0, 20.0, 200)
    batch = AxisSimulator().simulate(CSP, 0.0, 0.0, 0.0, tip_force=tip_force)
    stepped = AxisSimulator()
    traces = []
    for value in tip_force:
        stepped.step_cycle(CSP, 0.0, 0.0, 0.0, 0.0, 0.0, float(value))
        traces.append(stepped.tip_acceleration_trace)
    np.testing.assert_array_equal(np.array(traces), batch["tip_acceleration_trace"])
    assert stepped.tip_acceleration == batch["tip_acceleration"][-1]
