"""Live = offline (issue 14): the live window runs the family's own analysis.

Every family's recording (the report tests' recordings, whose truth is known, and a real
run on the simulated bench) is replayed through `LiveAnalysis` as the runner feeds a live
window; its result over the completed segments must equal `feedbench analyze`'s on the file,
value for value, and its live view must draw without a failure (`feedbench.testing`'s
`assert_live_equals_offline`, the check a lab's family takes too).
"""

from __future__ import annotations

import json

import pytest

from feedbench.bench import analyze_file
from feedbench.config import OWN_DISTRIBUTION
from feedbench.daq.recording import open_recording
from feedbench.commands.demo import example_config
from feedbench.engine.family import families
from feedbench.engine.incremental import LiveAnalysis
from feedbench.testing import assert_live_equals_offline, same
from test_report import (
    K_P, T_I, bode_steps, chirp_steps, friction_steps, hammer_steps, record,
    record_with_daq, shaker_chirp_steps, sine_stream_steps, smfe_steps,
)
from feedbench.experiments import smfe

RECORDINGS = {
    "friction_sweep": lambda path: record(path, "friction_sweep", friction_steps()),
    "chirp": lambda path: record(path, "chirp", chirp_steps()),
    "impact_hammer": lambda path: record_with_daq(path, {"type": "impact_hammer"},
                                                  hammer_steps(), ("hammer_force", "acc_tool_x")),
    "sine_stream": lambda path: record_with_daq(
        path, {"type": "sine_stream", "amplitudes_N": [20.0]}, sine_stream_steps(),
        ("actuator_force", "acc_tool_x")),
    "shaker_chirp": lambda path: record_with_daq(
        path, {"type": "shaker_chirp", "f_start_Hz": 20.0, "f_stop_Hz": 100.0},
        shaker_chirp_steps(), ("shaker_force", "acc_tool_x")),
    "closed_loop_bode": lambda path: record(
        path, "closed_loop_bode", bode_steps(),
        config={"type": "closed_loop_bode", "f_start_Hz": 20.0, "f_stop_Hz": 120.0},
        metadata={"drive_gains": {"K_p": K_P, "T_i": T_I}}),
    "smfe": lambda path: record_with_daq(path, {"type": "smfe", "segment_s": 2.0, "ramp_s": 12.0},
                                         smfe_steps(), smfe.DAQ_CHANNELS),
}
"""Families whose synthetic recordings `test_report` builds (stepped loading and the
backlash reversal run on the simulated rack-and-pinion axis in their own tests)."""


@pytest.mark.parametrize("name", sorted(RECORDINGS))
def test_live_analysis_of_a_recording_equals_the_offline_analysis(name, tmp_path):
    path = tmp_path / f"{name}.h5"
    RECORDINGS[name](path)
    live = assert_live_equals_offline(path)
    kinds = families()[name].live_kinds
    recording = open_recording(path)
    assert live.version == sum(1 for s in recording.segments()
                               if json.loads(s.label)["kind"] in kinds)


def test_every_family_with_a_synthetic_recording_is_covered_here():
    on_the_axis = {"stepped_loading", "backlash_reversal"}
    assert set(RECORDINGS) | on_the_axis == set(families(OWN_DISTRIBUTION))


def test_a_live_chirp_on_the_simulated_bench_ends_with_the_offline_result(simulated_bench):
    """The chirp through the real driver and runner: the live analysis the window would show
    after the last sweep is the file's analysis, value for value (metadata, config and
    cycle time handed over by the bench as recorded)."""
    raw = example_config("chirp")
    raw["experiment"].update(repetitions=2, duration_s=1.0, tail_s=0.3, settle_s=0.2,
                             f_start_Hz=20.0, f_stop_Hz=150.0)
    live = LiveAnalysis(families()["chirp"])
    row = simulated_bench.run(raw, observers=[live])
    assert row["status"] == "complete", row["reason"]
    assert live.version == 2
    offline = analyze_file(row["file"])
    offline.pop("run")
    assert same(live.result(final=True), offline)
    assert live.view().summary.startswith("2 sweeps; f_t")
