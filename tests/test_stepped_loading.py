"""Stepped loading and backlash of the rack-and-pinion axis end to end (thesis Ch. 3.4):
two CiA 402 drives on the virtual CAN bus sharing one simulated world, the bumper's load
cell over Modbus TCP, the run through the generalised runner, the analysis from the
recording. Checked against the simulator's truth and the thesis's figures (DIGEST §3).

Shortened against the example config by `stepped_loading.QUICK` (same step and plateau
logic): two preload levels, the thesis's low (4 %) and high (20 %) ones, loading without
the unloading stage, coarser single-motor steps, one back-and-forth move per motor,
shorter plateaus.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from feedbench.bench import analyze_file, parse_run_config, run_config
from feedbench.config import ConfigError
from feedbench.daq.recording import open_recording
from feedbench.commands.demo import example_config
from feedbench.experiments import stepped_loading
from feedbench.engine.plan import segment_event
from feedbench.testing import assert_live_equals_offline

K_MASTER, K_SLAVE = 81e6, 100e6
BACKLASH_MASTER, BACKLASH_SLAVE = 314e-6, 363e-6
RATED_FORCE = 70.0 * 190.0  # rated torque × K_tr (N at the rack)
THESIS_LOSS = {4.0: 1100.0, 20.0: 5300.0}


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> tuple[dict, dict]:
    raw = example_config("stepped_loading")
    raw["bench"].update(output_dir=str(tmp_path_factory.mktemp("stepped")),
                        channel=f"stepped-loading-{os.getpid()}")
    raw["bench"]["devices"]["load_cell"]["every_cycles"] = 5
    raw["experiment"].update(stepped_loading.QUICK)
    row = run_config(parse_run_config(raw), progress=False)
    assert row["status"] == "complete", row["reason"]
    return row, analyze_file(row["file"])


def test_single_motor_stiffness_within_1_percent(run):
    stiffness = run[1]["stiffness"]
    assert stiffness["master"]["k_N_m"] == pytest.approx(K_MASTER, rel=0.01)
    assert stiffness["slave"]["k_N_m"] == pytest.approx(K_SLAVE, rel=0.01)
    assert stiffness["master"]["offset_m"] == pytest.approx(BACKLASH_MASTER / 2, abs=2e-6)


def test_backlash_within_2_um_and_friction_windup_taken_out(run):
    backlash = run[1]["backlash"]
    for motor, truth, k in (("master", BACKLASH_MASTER, K_MASTER), ("slave", BACKLASH_SLAVE,
                                                                     K_SLAVE)):
        assert backlash[motor]["corrected"]
        assert backlash[motor]["value_m"] == pytest.approx(truth, abs=2e-6)
        windup = backlash[motor]["uncorrected_m"] - truth  # 2 F_friction / k, F ≈ 600 N
        assert 2 * 500.0 / k < windup < 2 * 900.0 / k


def test_preload_loss_force_rises_with_preload_as_in_the_thesis(run):
    """≈ 1100 N at 4 % against ≈ 5300 N at 20 %, each within 20 % (Ch. 3.4.3); the load
    where the master's torque reaches zero is 2 τ_p K_tr (Eq. 3.1) within 2 %."""
    levels = {p["preload_pct"]: p for p in run[1]["preload"]}
    for level, thesis in THESIS_LOSS.items():
        assert levels[level]["loss_force_N"] == pytest.approx(thesis, rel=0.2)
        assert levels[level]["loss_force_from_torques_N"] == pytest.approx(
            2 * level / 100 * RATED_FORCE, rel=0.02)
    assert levels[20.0]["loss_force_N"] > 4 * levels[4.0]["loss_force_N"]


def test_jump_between_loss_and_recovery_equals_the_backlash(run):
    for test in run[1]["preload"]:
        assert test["jump_m"] == pytest.approx(BACKLASH_MASTER, abs=2e-6)
        assert test["recovery_force_N"] > test["loss_force_N"]
        assert test["k_master_before_N_m"] == pytest.approx(K_MASTER, rel=0.05)


def test_slave_stiffness_halves_while_the_master_has_lost_contact(run):
    for test in run[1]["preload"]:
        assert test["k_slave_contact_N_m"] == pytest.approx(K_SLAVE, rel=0.03)
        assert test["slave_stiffness_ratio"] == pytest.approx(0.5, abs=0.05)


def test_torque_sharing_follows_the_weighting_and_preload(run):
    """Eq. (3.1) with K_Tm = K_Ts = 0.5: τ_m = τ_ref/2 + τ_p."""
    for test in run[1]["preload"]:
        assert test["torque_share"] == pytest.approx(0.5, abs=0.01)
        assert test["preload_force_N"] == pytest.approx(test["preload_pct"] / 100 * RATED_FORCE,
                                                        rel=0.02)


def test_recording_has_both_drives_the_encoders_and_the_load_cell(run):
    recording = open_recording(run[0]["file"])
    channels = recording.channels
    for name in ("master.position", "slave.force", "master.motor_position",
                 "slave.motor_position", "load_position", "load_cell.force"):
        assert name in channels
    assert recording.n_gaps == 0
    readings = np.isfinite(channels["load_cell.force"])
    assert readings.mean() == pytest.approx(0.2, abs=0.01), "read every fifth cycle"
    steps = [segment_event(e.text) for e in recording.events if e.kind == "segment"]
    settings = [commands for _, _, _, commands in steps if "coupling" in commands]
    assert len(settings) == 6  # backlash ×2, single ×2, coupled ×2
    assert settings[-1] == {"coupling": "coupled", "preload_pct": 20.0}
    assert not any("coupling" in info for _, _, info, _ in steps), "commands apart from info"


def test_live_analysis_ends_with_the_offline_result_and_draws_every_step(run):
    """The run replayed through the live analysis (issue 14): after the last step it is the
    file's analysis, value for value; the view draws each loading step's mean load and δ
    (the master alone, then the slave alone, then coupled per preload level) and the lines
    of Eq. (3.26)."""
    live = assert_live_equals_offline(run[0]["file"])
    panel = live.view().panels[0]
    steps = run[1]["steps"]
    assert [c.name for c in panel.curves] == [*steps, "fit master", "fit slave"]
    for curve, test in zip(panel.curves, steps.values()):
        np.testing.assert_array_equal(curve.y, test["force_N"])
        np.testing.assert_allclose(curve.x, np.array(test["delta_m"]) * 1e6, rtol=1e-12)
    single = steps["single master"]
    loaded = np.array(single["force_N"]) > 0.2 * max(single["force_N"])
    k = np.polyfit(np.array(single["delta_m"])[loaded], np.array(single["force_N"])[loaded], 1)[0]
    assert k == pytest.approx(K_MASTER, rel=0.02)  # the step means lie on Eq. (3.26)'s line
    assert live.view().summary.endswith(
        f"k_m {run[1]['stiffness']['master']['k_N_m'] / 1e6:.1f} N/µm, "
        f"k_s {run[1]['stiffness']['slave']['k_N_m'] / 1e6:.1f} N/µm")


def test_stepped_loading_needs_the_rack_pinion_axis():
    raw = example_config("stepped_loading")
    raw["bench"]["axis"] = "lab"
    with pytest.raises(ConfigError, match="bench.axis: experiment stepped_loading needs"):
        parse_run_config(raw)
