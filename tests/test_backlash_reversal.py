"""The backlash reversal test (thesis Ch. 3.4.2, Fig. 3.9) on the simulated rack-and-pinion
axis: both drives over the virtual CAN bus, each motor alone, 3 reversals each (≈ 6 s of
bench time). The identified backlash against the simulated world's dead zones, the live
analysis against the offline one, and the checks of its parameters.
"""

from __future__ import annotations

import os

import pytest

from feedbench.bench import analyze_file, parse_run_config, run_config
from feedbench.config import ConfigError
from feedbench.daq.recording import open_recording
from feedbench.commands.demo import example_config, example_truth
from feedbench.engine.family import families
from feedbench.engine.incremental import LiveAnalysis
from feedbench.engine.replay import replay
from feedbench.report import run_section
from feedbench.testing import assert_live_equals_offline

TOLERANCE_M = 2e-6
"""Identified backlash against the world's dead zone, friction wind-up taken out (as the
stepped-loading test's backlash; measured: within 0.1 µm)."""


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> tuple[dict, dict, dict]:
    """The example config's run (k_m, k_s given), its analysis and its world's truth."""
    raw = example_config("backlash_reversal")
    raw["bench"].update(output_dir=str(tmp_path_factory.mktemp("backlash")),
                        channel=f"backlash-reversal-{os.getpid()}")
    row = run_config(parse_run_config(raw), progress=False)
    assert row["status"] == "complete", row["reason"]
    return row, analyze_file(row["file"]), example_truth(raw)


def test_backlash_of_each_motor_within_2_um_of_the_world(run):
    _, result, truth = run
    for motor in ("master", "slave"):
        b = result["motors"][motor]
        assert b["corrected"] and b["n_reversals"] == 3
        assert b["value_m"] == pytest.approx(truth[f"backlash_{motor}"], abs=TOLERANCE_M), motor
        assert b["per_reversal_m"] == pytest.approx([truth[f"backlash_{motor}"]] * 3,
                                                    abs=TOLERANCE_M)
        assert b["std_m"] < 0.1e-6


def test_uncorrected_lost_motion_holds_the_friction_wind_up(run):
    """Without k the lost motion is L_z + 2 F_friction / k, F_friction ≈ 600 N (Eq. 5.2)."""
    _, result, truth = run
    for motor in ("master", "slave"):
        windup = result["motors"][motor]["uncorrected_m"] - truth[f"backlash_{motor}"]
        k = truth[f"k_{motor}"]
        assert 2 * 500.0 / k < windup < 2 * 900.0 / k, motor


def test_summary_and_text_against_the_truth(run):
    _, result, truth = run
    family = families()["backlash_reversal"]
    summary = family.summary(result, truth)
    assert abs(summary["motors"]["master"]["error_pct"]) < 100 * TOLERANCE_M / 314e-6
    assert summary["headline"].startswith("backlash master 313.9 ± ")
    lines = family.describe(result)
    assert lines[0].startswith("  master 313.9 ± ") and ", slave 362.9 ± " in lines[0]
    assert lines[1].startswith("  ✔ backlash parameters > 0: master 313.9 µm, slave 362.9 µm")
    assert lines[2].startswith("  ✔ reversals agree: master ± ")


def test_report_draws_the_loop_and_the_backlash_table(run):
    section = run_section(open_recording(run[0]["file"]))
    assert "backlash reversals: load against motor position" in [p.title for p in section.plots]
    table = next(t for t in section.tables if t.title.startswith("equivalent backlash"))
    assert [row[:2] for row in table.rows] == [("master", "313.9"), ("slave", "362.9")]
    assert all(row[4] == "taken out" for row in table.rows)
    assert section.headline.startswith("master 313.9 ± ")


def test_live_analysis_equals_the_offline_one(run):
    live = assert_live_equals_offline(run[0]["file"])
    assert live.version == 8  # 4 strokes per motor
    assert live.view().summary.startswith("master 313.9 ± ")


class _EveryStroke(LiveAnalysis):
    """The live result after each completed stroke, as the window would show it."""

    def __init__(self) -> None:
        super().__init__(families()["backlash_reversal"])
        self.results: list[dict] = []

    def on_segment_complete(self, kind: str) -> None:
        super().on_segment_complete(kind)
        if kind == "measure":
            self.results.append(self.result())


def test_live_shows_the_loop_first_then_the_reversals_completed_so_far(run):
    _, offline, _ = run
    live = _EveryStroke()
    replay(open_recording(run[0]["file"]), [live], speed=0.0)
    first, second = live.results[0]["motors"]["master"], live.results[1]["motors"]["master"]
    assert first["n_reversals"] == 0 and len(first["loop"]["motor_m"]) > 100
    view = families()["backlash_reversal"].live_view(live.results[0])
    assert view.summary == "master: no reversal yet"
    assert second["n_reversals"] == 1
    assert second["per_reversal_m"][0] == pytest.approx(
        offline["motors"]["master"]["per_reversal_m"][0], abs=1e-9)
    assert [r["motors"].keys() for r in live.results[3:5]] == [{"master"}, {"master", "slave"}]


@pytest.mark.parametrize("change, message", [
    ({"motors": []}, "experiment.motors: must name at least one of master, slave"),
    ({"motors": ["both"]}, "experiment.motors: must be one of master, slave (got 'both')"),
    ({"stroke_um": 20.0}, "experiment.stroke_um: too short to reach feed_mm_min"),
    ({"reversals": 0}, "experiment.reversals: must be > 0 (got 0)"),
    ({"feed_mm_min": -200.0}, "experiment.feed_mm_min: must be > 0 (got -200.0)"),
    ({"k_master_N_um": -81.0}, "experiment.k_master_N_um: must be >= 0 (got -81.0)"),
    ({"dwell_ms": 200.0}, "experiment.dwell_ms: unknown key"),
])
def test_bad_parameters_raise_one_line_errors_naming_the_field(change, message):
    raw = example_config("backlash_reversal")
    raw["experiment"].update(change)
    with pytest.raises(ConfigError) as error:
        parse_run_config(raw)
    assert str(error.value).startswith(message) and "\n" not in str(error.value)


def test_backlash_reversal_needs_the_rack_pinion_axis():
    raw = example_config("backlash_reversal")
    raw["bench"]["axis"] = "lab"
    with pytest.raises(ConfigError, match="bench.axis: experiment backlash_reversal needs"):
        parse_run_config(raw)
