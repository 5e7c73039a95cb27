"""World side of the structure experiments: tip acceleration of the axis kernel, exciters,
impact hammer, accelerometer noise and the DAQ samples the world pushes per bus cycle."""

import time
import warnings

import numpy as np
import pytest

from feedbench.analysis.frf import quasi_frf
from feedbench.drivers.io_module import IoModule, IoModuleError
from feedbench.models.axis import CSP, CSV, AxisSimulator, TwoMassAxis
from feedbench.models.exciters import ExciterDynamics, InertialActuator, half_sine_pulse, shaker
from feedbench.protocols import cia401
from feedbench.protocols.canbus import open_network
from feedbench.protocols.serial_frames import CHANNEL_INDEX
from feedbench.sim_backends.bench import start_simulated_axis
from feedbench.sim_backends.io_module import SimulatedIoModule
from feedbench.sim_backends.structure_world import (
    ForceExciter, ImpactHammer, StructureWorld, interpolation_weights, parse_structure,
)


def test_tip_acceleration_trace_integrates_to_the_tip_velocity_change():
    """Trapezoid rule over the N + 1 trace points = Δ tip velocity of each cycle (exact for
    a linear acceleration; the trace is smooth at 8 kHz, so within 0.05 % of the largest)."""
    sim = AxisSimulator()
    tip_force = np.random.default_rng(1).normal(0.0, 30.0, 2000)
    out = sim.simulate(CSV, 0.0, 0.01, 0.0, tip_force=tip_force, keep_trace=True)
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
    batch = AxisSimulator().simulate(CSP, 0.0, 0.0, 0.0, tip_force=tip_force,
                                     keep_trace=True)
    stepped = AxisSimulator()
    traces = []
    for value in tip_force:
        stepped.step_cycle(CSP, 0.0, 0.0, 0.0, 0.0, 0.0, float(value))
        traces.append(stepped.tip_acceleration_trace)
    np.testing.assert_array_equal(np.array(traces), batch["tip_acceleration_trace"])
    assert stepped.tip_acceleration == batch["tip_acceleration"][-1]


# -- exciter laws (models.exciters) -------------------------------------------------------

def test_shaker_force_falls_from_70_to_about_60_N_over_25_to_100_Hz():
    """Ch. 3.5.1: '~70 N falling to ~60 N' over the 25–100 Hz chirp at a constant command."""
    response = shaker(160.0).response([25.0, 100.0])
    force = 70.0 / abs(response[0]) * np.abs(response)
    assert force[0] == pytest.approx(70.0)
    assert force[1] == pytest.approx(61.0, abs=1.0)


def test_inertial_actuator_force_capability():
    """Above its suspension it transmits the coil force (|F/u| → 1); at low frequency the
    stroke bounds it: F ≤ m ω² stroke (2 kg, ±5 mm at 10 Hz: 39.5 N)."""
    actuator = InertialActuator(mass=2.0, f_n=15.0, zeta=0.3, command_limit=300.0, stroke=5e-3)
    assert abs(actuator.dynamics().response(500.0)) == pytest.approx(1.0, abs=1e-3)
    assert actuator.max_force(10.0) == pytest.approx(2.0 * (2 * np.pi * 10.0) ** 2 * 5e-3)
    coil = 300.0 * abs(actuator.dynamics().response(80.0))
    assert actuator.max_force(80.0) == pytest.approx(coil)
    assert actuator.stroke_amplitude(50.0, 40.0) == pytest.approx(40.0 / (2 * (100 * np.pi) ** 2))


def test_half_sine_pulse_at_cycle_ends():
    np.testing.assert_allclose(half_sine_pulse(100.0, 4e-3, 1e-3),
                               [100 * np.sqrt(0.5), 100.0, 100 * np.sqrt(0.5), 0.0])


def test_force_exciter_steady_state_matches_the_transfer_function():
    """Stepped per cycle (Tustin), a 50 Hz sine command gives a force of amplitude |F/u(50 Hz)|
    within the frequency warping (< 0.5 % here)."""
    dynamics = InertialActuator().dynamics()
    exciter = ForceExciter(dynamics, 1e-3)
    t = np.arange(1, 2001) * 1e-3
    force = np.array([exciter.step(10.0 * np.sin(2 * np.pi * 50.0 * tk)) for tk in t])
    amplitude = np.abs(np.fft.rfft(force[1000:]))[50] * 2 / 1000
    assert amplitude == pytest.approx(10.0 * abs(dynamics.response(50.0)), rel=5e-3)


@pytest.mark.parametrize("dynamics", [
    shaker(160.0), shaker(1e3, 10.0), InertialActuator().dynamics(),
    InertialActuator(0.2, 40.0, 1.0).dynamics(),
    ExciterDynamics((2.0, 3.0), (4.0, 5.0, 6.0), 1.0),  # den[0] != 1, a strictly proper one
    ExciterDynamics((0.0, 1.0), (1.0, 2.0), 1.0),  # a leading zero: scipy.signal's own
    ExciterDynamics((3.0,), (2.0,), 1.0),  # a gain
])
@pytest.mark.parametrize("cycle_s", [1e-3, 1.25e-4, 1e-2])
def test_exciter_discretisation_is_scipy_signals_to_the_last_bit(dynamics, cycle_s):
    """`ExciterDynamics.discrete` without scipy.signal (its import: 0.6 s of a sim's start)
    gives tf2ss + cont2discrete's bilinear matrices exactly."""
    import scipy.signal

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # scipy.signal's BadCoefficients for the leading zero
        a, b, c, d = scipy.signal.tf2ss(dynamics.numerator, dynamics.denominator)
        want = scipy.signal.cont2discrete((a, b, c, d), cycle_s, method="bilinear")[:4]
        got = dynamics.discrete(cycle_s)
    for g, w in zip(got, want, strict=True):
        assert g.shape == w.shape and g.dtype == w.dtype and np.array_equal(g, w)


def test_force_exciter_saturates_at_its_command_limit():
    exciter = ForceExciter(shaker(160.0, command_limit=50.0), 1e-3)
    for _ in range(200):
        exciter.step(1e4)
    assert exciter.force == pytest.approx(50.0, rel=1e-6)


# -- impact hammer and DAQ samples (sim_backends.structure_world) -------------------------

def _params(**overrides):
    return parse_structure(overrides)


def test_hammer_hits_on_rising_edges_only_and_bounces_are_flagged_by_quasi_frf():
    """A bounce (double hit) shows in the force record and `quasi_frf` leaves it out (5.3)."""
    p = _params(double_hit_probability=1.0, hammer_scatter=0.0)
    hammer = ImpactHammer(p, 1e-3, np.random.default_rng(0))
    fire = np.zeros(300, bool)
    fire[10:13] = True  # held for three cycles: one hit
    force = np.array([hammer.step(bool(f), 50.0) for f in fire])
    assert hammer.hits == 1 and hammer.bounces == 1
    assert force.max() == pytest.approx(50.0)
    clean = ImpactHammer(_params(double_hit_probability=0.0, hammer_scatter=0.0), 1e-3,
                         np.random.default_rng(0))
    single = np.array([clean.step(bool(f), 50.0) for f in fire])
    records = np.stack([force, single])
    frf = quasi_frf(records, records, 1000.0, 0.01, 0.1)
    assert [h.double_hit for h in frf.hits] == [True, False]
    assert frf.used_hits == (1,)


def test_interpolation_weights_sample_the_trace_linearly_in_time():
    trace = np.linspace(0.0, 8.0, 9)  # a ramp over the 8 substeps: value = substep index
    weights = interpolation_weights(8, 10)
    np.testing.assert_allclose(weights @ trace, np.arange(10) * 0.8)
    np.testing.assert_array_equal(interpolation_weights(8, 8) @ trace, np.arange(8.0))


class _Io:
    """The I/O module's latched outputs as the world reads them."""

    def __init__(self, shaker_N=0.0):
        self.digital = 0
        self.forces = {cia401.SHAKER: shaker_N, cia401.ACTUATOR: 0.0, cia401.HAMMER_LEVEL: 0.0}

    def analog_force(self, channel):
        return self.forces[channel]


class _Drive:
    def __init__(self):
        self.simulator = AxisSimulator()
        self.tip_force = 0.0
        self.before_physics, self.after_physics = [], []


def test_world_sets_the_tip_force_and_samples_it_with_the_acceleration():
    """The DAQ block of a cycle: the shaker force ramping as the axis applies it, the tip
    acceleration interpolated from the trace; noise off to compare exactly."""
    drive = _Drive()
    world = StructureWorld(drive, _Io(shaker_N=40.0), None,
                           _params(accelerometer_noise_m_s2=[0.0, 0.0, 0.0], force_noise_N=0.0),
                           1e-3)
    blocks, forces = [], [0.0]
    for _ in range(3):
        world.before_physics()
        drive.simulator.step_cycle(CSP, 0.0, 0.0, 0.0, 0.0, 0.0, drive.tip_force)
        blocks.append(world.samples(10))
        forces.append(world.shaker.force)
    assert drive.tip_force == forces[-1] > 0.0
    ramp = forces[-2] + (forces[-1] - forces[-2]) * np.arange(10) / 10
    np.testing.assert_allclose(blocks[-1][:, CHANNEL_INDEX["shaker_force"]], ramp)
    trace = drive.simulator.tip_acceleration_trace
    np.testing.assert_allclose(blocks[-1][:, CHANNEL_INDEX["acc_tool_x"]],
                               interpolation_weights(8, 10) @ trace)


def test_accelerometer_noise_has_the_eq_6_18_standard_deviations():
    drive = _Drive()
    world = StructureWorld(drive, _Io(), None, _params(seed=3), 1e-3)
    samples = np.vstack([world.samples(10) for _ in range(3000)])
    columns = [CHANNEL_INDEX[c] for c in ("acc_tool_y", "acc_tool_z", "acc_work_x")]
    np.testing.assert_allclose(samples[:, columns].std(axis=0), [0.012, 0.0014, 0.016], rtol=0.03)


# -- the I/O module over the CAN bus (drivers.io_module against sim_backends.io_module) -----

def test_io_module_outputs_reach_the_world_at_the_sync_they_precede():
    """Outputs sent before a SYNC are the ones applied in that cycle (synchronous RPDOs)."""
    drive = start_simulated_axis("virtual", "io-module-test")
    network = open_network("virtual", "io-module-test")
    try:
        module = SimulatedIoModule(drive.network, 10)
        seen = []
        drive.before_physics.append(
            lambda: seen.append((module.digital, round(module.analog_force(cia401.SHAKER), 2))))
        host = IoModule(network, 10)
        assert not module.operational
        host.configure()
        deadline = time.monotonic() + 2.0
        while not module.operational and time.monotonic() < deadline:
            time.sleep(0.005)
        for k in range(3):
            host.set_force(cia401.SHAKER, 10.0 * (k + 1))
            host.set_digital(cia401.HAMMER_FIRE * (k % 2))
            host.transmit()
            network.send_message(0x80, b"")
        deadline = time.monotonic() + 2.0
        while len(seen) < 3 and time.monotonic() < deadline:
            time.sleep(0.005)
        assert seen == [(0, 9.99), (1, 20.0), (0, 30.0)]  # 500 N full scale, 16 bit
        with pytest.raises(IoModuleError, match="not a CiA 401"):
            IoModule(network, 1).configure()  # node 1 is the drive (profile 402)
    finally:
        network.disconnect()
        drive.close()


def test_simulate_keeps_the_trace_only_when_asked_and_ends_in_the_same_state():
    """Without keep_trace no per-cycle trace is returned, yet every output and the last
    cycle's trace are those of the run that keeps it."""
    tip_force = np.random.default_rng(2).normal(0.0, 30.0, 300)
    kept_sim, lean_sim = AxisSimulator(), AxisSimulator()
    kept = kept_sim.simulate(CSV, 0.0, 0.01, 0.0, tip_force=tip_force, keep_trace=True)
    lean = lean_sim.simulate(CSV, 0.0, 0.01, 0.0, tip_force=tip_force)
    assert "tip_acceleration_trace" not in lean
    for name in ("position", "velocity", "force", "tip_acceleration", "mean_force"):
        np.testing.assert_array_equal(lean[name], kept[name])
    np.testing.assert_array_equal(lean_sim.tip_acceleration_trace,
                                  kept["tip_acceleration_trace"][-1])
