"""The scripting API (feedbench.api, issue 17) on the simulated bench: moves and jogs as
checked plans, gains within their declared ranges, progress, ad-hoc records; its reference
builds with Sphinx -W, and every public name says what it is in which unit."""

from __future__ import annotations

import inspect
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import feedbench
from feedbench import api
from feedbench.engine.family import family
from feedbench.units import MM_PER_MIN

ROOT = Path(__file__).parents[1]
CONFIG = {"bench": {"simulated": True, "channel": "test-api", "name": "api-rig"},
          "limits": {"position_mm": [-50.0, 50.0], "gains": {"K_p_Ns_m": [4000.0, 16000.0]}}}


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    config = {**CONFIG, "bench": {**CONFIG["bench"],
                                  "output_dir": str(tmp_path_factory.mktemp("runs"))}}
    with feedbench.open_bench(config) as session:
        yield session


def test_nothing_moves_before_the_drive_is_enabled(bench):
    with pytest.raises(feedbench.ConfigError, match="drive: not enabled"):
        bench.record(0.1)
    assert bench.drive.state == "SWITCH ON DISABLED"


def test_move_jog_and_record_are_recorded_plans(bench):
    bench.drive.enable()
    steps = []
    move = bench.drive.move_to(12.0, feed_mm_min=1200.0,
                               progress=lambda done, step: steps.append((done, step)))
    assert move.complete and move.recording.experiment == "sequence"
    assert abs(bench.drive.read().position_mm - 12.0) < 0.01  # within 10 µm
    assert steps[0] == (0.0, "enable") and steps[-1] == (1.0, "complete")
    assert [d for d, _ in steps] == sorted(d for d, _ in steps)
    jog = bench.drive.jog(-900.0, seconds=0.5)
    window = next(s for s in jog.recording.segments() if "jog -900 mm/min" in s.label)
    velocity = jog.recording.channels["velocity"][jog.recording.mask(window)]
    assert abs(velocity.mean() / MM_PER_MIN + 900.0) < 9.0  # mean feed within 1 %
    ramps_mm = 2 * 0.015 ** 2 / (2 * 1.0) * 1e3  # up and down at 1 m/s²: v² / 2a each
    expected = 12.0 - 0.5 * 15.0 - ramps_mm  # 0.5 s at 15 mm/s between the ramps
    assert abs(bench.drive.read().position_mm - expected) < 0.05  # within 50 µm
    rest = bench.record(0.25, label="at rest")
    assert rest.recording.n_samples >= 250 and rest.result == {}
    assert np.abs(rest.recording.channels["velocity"]).max() < 1e-3  # m/s: standing still
    assert bench.drive.state == "SWITCH ON DISABLED"  # disabled between plans


def test_a_plan_past_a_limit_is_refused_before_anything_moves(bench):
    bench.drive.enable()
    before = sorted(bench.output_dir.glob("*.h5"))
    with pytest.raises(feedbench.LimitError, match="limits.position_mm"):
        bench.drive.move_to(60.0, feed_mm_min=1000.0)  # the range ends at 50 mm
    with pytest.raises(feedbench.LimitError, match="limits.excitation_N"):
        bench.run("chirp", amplitude_N=400.0)  # above the 300 N excitation limit
    assert sorted(bench.output_dir.glob("*.h5")) == before


def test_a_stop_request_ramps_down_disables_and_raises(bench):
    bench.drive.enable()

    def stop_at_a_third(done: float, step: str) -> None:
        if done > 0.3:
            bench.stop("enough")

    start = bench.drive.read().position_mm
    with pytest.raises(feedbench.RunStopped) as stopped:
        bench.drive.jog(600.0, seconds=2.0, progress=stop_at_a_third)
    run = stopped.value.run
    assert (run.status, run.reason, run.result) == ("aborted", "enough", {})
    assert (run.recording.status, run.recording.reason) == ("aborted", "enough")
    assert [e.text for e in run.recording.events if e.kind == "abort"] == ["enough"]
    assert abs(run.recording.channels["velocity"][-1]) < 1e-3  # m/s: ramped down to rest
    assert bench.drive.state == "SWITCH ON DISABLED"
    assert bench.drive.read().position_mm - start < 12.0  # well short of the 20 mm planned


def test_gains_within_the_declared_ranges_only(bench):
    bench.drive.set_gains(K_p_Ns_m=8000.0)
    assert bench.drive.gains["K_p_Ns_m"] == pytest.approx(8000.0)
    with pytest.raises(feedbench.ConfigError,
                       match=r"^set_gains.K_p_Ns_m: 20000 outside limits.gains.K_p_Ns_m "
                             r"\[4000, 16000\]$"):
        bench.drive.set_gains(K_p_Ns_m=20000.0)
    with pytest.raises(feedbench.ConfigError, match="^limits.gains.T_i_ms: no range declared"):
        bench.drive.set_gains(T_i_ms=5.0)
    assert bench.drive.gains["K_p_Ns_m"] == pytest.approx(8000.0)  # nothing written


def test_an_experiment_instance_runs_with_its_settings(bench):
    bench.drive.enable()
    chirp = family("chirp")({"duration_s": 1.0, "repetitions": 1, "f_start_Hz": 20.0,
                             "f_stop_Hz": 150.0, "feed_mm_min": 300.0}, bench.cycle_s)
    run = bench.run(chirp)
    assert run.complete and run.result["n_sweeps"] == 1
    assert run.recording.config["experiment"]["duration_s"] == 1.0
    assert run.recording.metadata["drive_gains"]["K_p"] == pytest.approx(8000.0)
    assert bench.devices == ()  # the lab bench has the drive alone


PUBLIC = [getattr(api, name) for name in api.__all__]


def test_the_sessions_runs_are_catalogued_and_recorded_under_its_bench_name(bench):
    """`[bench] name` names the bench of a scripting session's runs as of `feedbench run`'s
    (the runs of the tests above)."""
    from feedbench.daq.catalog import Catalog
    from feedbench.daq.recording import read_summary

    rows = Catalog(bench.output_dir / "catalog.sqlite").list()
    assert len(rows) >= 3
    assert {row.bench for row in rows} == {read_summary(row.file).bench for row in rows} == {
        "api-rig"}


def test_every_public_name_and_member_has_a_docstring():
    missing = [f"{obj.__qualname__}.{name}" for obj in PUBLIC if inspect.isclass(obj)
               for name, member in vars(obj).items()
               if not name.startswith("_") and (callable(member) or isinstance(member, property))
               if not (inspect.getdoc(member) or "").strip()]
    missing += [name for name, obj in zip(api.__all__, PUBLIC)
                if (inspect.isclass(obj) or inspect.isfunction(obj)) and not inspect.getdoc(obj)]
    assert missing == []
    assert "(mm)" in api.Drive.move_to.__doc__ and "(mm/min," in api.Drive.jog.__doc__
    assert "(N·s/m)" in api.Drive.set_gains.__doc__ and "(N)" in api.Reading.__doc__


def test_the_reference_builds_without_warnings(tmp_path):
    built = subprocess.run([sys.executable, "-m", "sphinx", "-W", "-q", "-b", "html",
                            str(ROOT / "docs" / "api"), str(tmp_path)],
                           capture_output=True, text=True)
    assert built.returncode == 0, built.stderr
    page = (tmp_path / "index.html").read_text(encoding="utf-8")
    for name in ("open_bench", "BenchSession", "move_to", "set_gains", "RunStopped"):
        assert name in page
