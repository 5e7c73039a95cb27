"""The rack-and-pinion axis on the bus: two simulated drives stepping one shared world once
per SYNC, the axis controller's objects by SDO, the friction sweep on this axis, and the
runner's safe stop of both drives."""

from __future__ import annotations

import canopen
import numpy as np
import pytest

from feedbench.bench import analyze_file, parse_run_config, run_config
from feedbench.daq.clock import LockstepClock
from feedbench.daq.recording import open_recording
from feedbench.commands.demo import example_config
from feedbench.drivers.cia402 import Cia402Drive
from feedbench.axes.rack_pinion import AXIS_PDOS, AxisController, load_position, motor_position
from feedbench.models.axis import CSP
from feedbench.protocols.canbus import open_network
from feedbench.sim_backends.rack_pinion import (
    SimulatedRackPinionAxis, build_simulator, packaged_eds_path,
)


@pytest.fixture
def axis(can_channel):
    """The simulated axis (no bumper) and the host's two drives with one clock over both."""
    simulated = SimulatedRackPinionAxis(build_simulator({"bumper_mm": 0.0}, 1e-3), "virtual",
                                        can_channel)
    network = open_network("virtual", can_channel)
    drives = {name: Cia402Drive(network, node_id, packaged_eds_path(), AXIS_PDOS)
              for name, node_id in (("master", 1), ("slave", 2))}
    for drive in drives.values():
        drive.configure()
    clock = LockstepClock(network, list(drives.values()))
    yield simulated, drives, clock
    network.disconnect()
    simulated.close()


def test_one_world_step_per_sync_after_both_nodes_latched(axis):
    """Both nodes answer every SYNC with the same cycle count, the world advanced exactly
    once per SYNC, and a target sent to the master in cycle k is in the world's step k."""
    simulated, drives, clock = axis
    for drive in drives.values():
        drive.set_mode(CSP)
        drive.enable(clock.tick)
    start = simulated.world.simulator.cycle_count
    targets = np.linspace(0.0, 50e-6, 200)
    for target in targets:
        for drive in drives.values():
            drive.set_targets(position=target, velocity=0.0, velocity_offset=0.0,
                              force_offset=0.0)
        clock.tick()
        assert simulated.world.ports["master"].command.target_position == pytest.approx(
            target, abs=1e-9)
    assert simulated.world.simulator.cycle_count - start == targets.size
    assert clock.cycles[0] == clock.cycles[1] and clock.gaps == 0
    master = drives["master"]
    assert load_position(master) == pytest.approx(simulated.world.simulator.load_position,
                                                  abs=1e-9)
    assert motor_position(drives["slave"]) == pytest.approx(
        simulated.world.simulator.motor_position("slave"), abs=1e-9)
    assert master.actual.position == pytest.approx(50e-6, abs=5e-6)


def test_axis_objects_set_the_coupling_preload_and_weights(axis):
    simulated, drives, _ = axis
    controller = AxisController(drives["master"])
    controller.set_coupling("slave")
    controller.set_preload(0.25)
    controller.set_weights(0.6, 0.4)
    sim = simulated.world.simulator
    assert sim.coupling == 2 and sim.preload.level == pytest.approx(0.25)
    assert (sim.preload.K_Tm, sim.preload.K_Ts) == pytest.approx((0.6, 0.4))
    assert controller.read() == pytest.approx({"coupling": "slave", "preload": 0.25,
                                               "K_Tm": 0.6, "K_Ts": 0.4})
    rated = drives["master"].node.sdo[0x6076].raw * 1e-3
    assert rated == pytest.approx(70.0 * 190.0, rel=1e-6), "0x6076: rated torque at the rack"
    with pytest.raises(canopen.SdoAbortedError):
        controller.set_weights(0.0, 0.5)  # a weighting factor must be > 0
    assert sim.preload.K_Tm == pytest.approx(0.6)


def test_friction_sweep_on_the_rack_pinion_axis(tmp_path, can_channel):
    """The coupled, preloaded axis: the summed motor forces give the guideway friction of
    the example world (Eq. 5.2) plus the motors' viscous drag (2 × 2000 N·s/m)."""
    raw = example_config("friction_sweep_rack_pinion")
    raw["bench"].update(output_dir=str(tmp_path), channel=can_channel)
    raw["experiment"].update(feeds_mm_min=[25, 50, 100, 200, 400, 800, 1500], settle_s=0.4,
                             measure_s=0.3)
    row = run_config(parse_run_config(raw), progress=False)
    assert row["status"] == "complete", row["reason"]
    result = analyze_file(row["file"])
    for direction in ("positive", "negative"):
        fit = result[direction]["identified"]
        assert fit["F_c"] == pytest.approx(600.0, rel=0.01)
        assert fit["F_s"] == pytest.approx(900.0, rel=0.01)
        assert fit["v_s"] == pytest.approx(300.0 / 60e3, rel=0.03)
        assert fit["sigma"] == pytest.approx(0.1 * 60e3 + 2 * 2000.0, rel=0.02)


def test_a_limit_trip_stops_and_disables_both_drives(tmp_path, can_channel):
    """Coupled loading into the bumper with a 2 kN motor-force limit: the run aborts naming
    the drive that tripped, ramps down and leaves both drives disabled; every sample kept."""
    raw = example_config("stepped_loading")
    raw["bench"].update(output_dir=str(tmp_path), channel=can_channel)
    raw["bench"]["devices"]["load_cell"]["every_cycles"] = 5
    raw["limits"]["force_N"] = 2000.0
    raw["experiment"].update(backlash=[], single_motor=[], preload_pct=[4.0], setup_s=1.0)
    row = run_config(parse_run_config(raw), progress=False)
    assert row["status"] == "aborted"
    assert row["reason"].startswith("limit tripped: slave: |force|")
    recording = open_recording(row["file"])
    assert recording.n_gaps == 0
    for drive in ("master", "slave"):
        statusword = recording.channels[f"{drive}.statusword"].astype(int)
        assert any(statusword & 0x6F == 0x27), f"{drive} ran"
        assert statusword[-1] & 0x6F != 0x27, f"{drive} is disabled at the end"
