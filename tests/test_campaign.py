"""`feedbench campaign` (issue 15 item 2): simulated runs as Dask tasks on a LocalCluster of
two worker processes, results in the run catalog and the summary table, a failed task
reported and the others kept, bad campaign configs refused in one line."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
import tomllib

import pytest
from dask.distributed import Client

from feedbench.axes.lab import LabAxis
from feedbench.commands.campaign import (dask_client, describe_campaign, parse_campaign,
                                          run_campaign, run_task, write_summary)
from feedbench.config import ConfigError
from feedbench.daq.catalog import Catalog

F_C = "bench.world.friction.positive.F_c_N"
F_S = "bench.world.friction.positive.F_s_N"

BASE = """
[bench]
output_dir = "{out}"

[bench.world.friction.positive]
F_c_N = 44.2
F_s_N = 84.0

[limits]
position_mm = [-250.0, 250.0]
velocity_mm_min = 3000.0
force_N = 1500.0

[experiment]
type = "friction_sweep"
feeds_mm_min = [25, 50, 100, 200, 400, 800, 1500]
settle_s = 0.2
measure_s = 0.15
"""

MONTE_CARLO = """
[campaign]
kind = "montecarlo"
seeds = [1]
n = 4

[campaign.spread]
"bench.world.friction.positive.F_c_N" = 0.1
"bench.world.friction.positive.F_s_N" = 0.1
""" + BASE

GRID_WITH_A_FAILING_RUN = """
[campaign]
seeds = [3]

[campaign.grid]
"bench.world.friction.positive.F_c_N" = [40.0, -1.0]
""" + BASE


def campaign_of(text: str, out) -> dict:
    return tomllib.loads(text.format(out=out))


@pytest.fixture(scope="module")
def scheduler():
    """The address of the command's default cluster: a LocalCluster of two worker processes."""
    with dask_client(None, 2) as client:
        pids = client.run(os.getpid)
        assert len(set(pids.values())) == 2 and os.getpid() not in pids.values()
        yield client.scheduler.address


def test_monte_carlo_friction_on_two_workers(scheduler, tmp_path):
    campaign = parse_campaign(campaign_of(MONTE_CARLO, tmp_path))
    assert len(campaign.tasks) == 4
    in_process = run_task(campaign.tasks[0], campaign.id)  # also compiles the physics once
    seen = []
    summary = run_campaign(campaign, scheduler=scheduler,
                           progress=lambda done, total, row: seen.append((done, total)))
    assert seen == [(1, 4), (2, 4), (3, 4), (4, 4)]
    runs = summary["runs"]
    assert [row["index"] for row in runs] == [0, 1, 2, 3]
    assert summary["complete"] == 4 and summary["scheduler"] == scheduler
    assert len({row["params"][F_C] for row in runs}) == 4  # each run its own draw
    assert len({row["params"][LabAxis.noise_seed] for row in runs}) == 4
    for row in runs:
        assert row["status"] == "complete"
        r = row["results"]
        assert r["positive.truth.F_c"] == pytest.approx(row["params"][F_C])
        assert r["positive.truth.F_s"] == pytest.approx(row["params"][F_S])
        assert abs(r["positive.error_pct.F_c"]) < 3.0  # Eq. (5.2) fit against this run's truth
        assert abs(r["positive.error_pct.F_s"]) < 0.5
        assert abs(r["negative.error_pct.F_c"]) < 3.0
    # a worker process gives the numbers the test process gives for the same task
    assert runs[0]["results"] == in_process["results"]

    rows = {row.id: row for row in Catalog(tmp_path / "catalog.sqlite").list()}
    assert len(rows) == 5
    for row in runs:
        tag = rows[row["run_id"]].params["campaign"]
        assert tag == {"id": campaign.id, "index": row["index"], "params": row["params"]}
        assert rows[row["run_id"]].status == "complete"

    json_path, csv_path = write_summary(summary, tmp_path)
    assert json.loads(json_path.read_text())["runs"][2]["results"] == runs[2]["results"]
    with csv_path.open() as file:
        table = list(csv.DictReader(file))
    assert [int(t["index"]) for t in table] == [0, 1, 2, 3]
    assert float(table[1][F_C]) == runs[1]["params"][F_C]
    assert float(table[1]["positive.identified.F_c"]) == runs[1]["results"][
        "positive.identified.F_c"]
    lines = describe_campaign(summary).splitlines()
    assert lines[0].split() == ["#", "F_c_N", "F_s_N", "noise_seed", "status", "result"]
    assert all("complete  Eq. 5.2: F_c" in line for line in lines[1:5])
    assert lines[5].startswith(f"friction_sweep campaign {campaign.id}: 4 of 4 runs complete")


def test_cli_reports_a_failed_run_and_keeps_the_others(scheduler, tmp_path):
    """The command with --scheduler: the world the simulator refuses fails its task,
    reported in one progress line; the other run completes; status 1."""
    config = tmp_path / "campaign.toml"
    config.write_text(GRID_WITH_A_FAILING_RUN.format(out=tmp_path / "runs"))
    done = subprocess.run([sys.executable, "-m", "feedbench.commands.cli", "campaign", str(config),
                           "--scheduler", scheduler],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 1, done.stderr
    progress = done.stderr.splitlines()
    assert len(progress) == 2, done.stderr
    assert [line[:6] for line in progress] == ["[1/2] ", "[2/2] "]
    failed = next(line for line in progress if "run 1 " in line)
    assert failed.endswith("(F_c_N=-1, noise_seed=3): failed (ConfigError: "
                           "bench.world.friction.positive.F_c_N: must be > 0 (got -1.0))")
    table = done.stdout.splitlines()
    assert table[1].split()[:4] == ["0", "40", "3", "complete"]
    assert table[2].split()[:4] == ["1", "-1", "3", "failed"]
    assert "1 of 2 runs complete" in table[3] and scheduler in table[3]
    summary = json.loads(next((tmp_path / "runs").glob("campaign-*.json")).read_text())
    good, bad = summary["runs"]
    assert abs(good["results"]["positive.error_pct.F_c"]) < 3.0
    assert bad["status"] == "failed" and bad["run_id"] == "" and bad["results"] == {}
    assert [row.status for row in Catalog(tmp_path / "runs" / "catalog.sqlite").list()] == [
        "complete"]


def test_ctrl_c_cancels_the_futures_with_one_line(scheduler, tmp_path):
    config = tmp_path / "campaign.toml"
    config.write_text(MONTE_CARLO.replace("n = 4", "n = 3").format(out=tmp_path))
    command = subprocess.Popen([sys.executable, "-m", "feedbench.commands.cli", "campaign", str(config),
                                "--scheduler", scheduler],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    first = command.stderr.readline()
    assert first.startswith("[1/3] run ")
    command.send_signal(signal.SIGINT)
    out, err = command.communicate(timeout=60)
    assert command.returncode == 130 and out == ""
    assert err.splitlines()[-1] == "feedbench: error: interrupted"
    assert all(line.startswith("[") for line in err.splitlines()[:-1])
    with Client(scheduler) as client:  # nothing left on the scheduler
        deadline = time.monotonic() + 30.0
        while client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.tasks)):
            assert time.monotonic() < deadline
            time.sleep(0.2)
    assert not list(tmp_path.glob("campaign-*"))  # no summary of an interrupted campaign


def test_grid_points_and_draws(tmp_path):
    raw = campaign_of(BASE, tmp_path)
    grid = parse_campaign({**raw, "campaign": {"seeds": [0, 1], "grid": {
        "bench": {"gains": {"K_p_Ns_m": [8000.0, 9000.0, 10000.0], "T_i_ms": [4.0, 8.0]}}}}})
    assert len(grid.tasks) == 12
    assert grid.tasks[7].params == {"bench.gains.K_p_Ns_m": 9000.0, "bench.gains.T_i_ms": 8.0,
                                    LabAxis.noise_seed: 1}
    assert grid.tasks[7].raw["bench"]["gains"] == {"K_p_Ns_m": 9000.0, "T_i_ms": 8.0}
    monte_carlo = campaign_of(MONTE_CARLO, tmp_path)
    draws = [parse_campaign(monte_carlo).tasks for _ in range(2)]
    assert [t.params for t in draws[0]] == [t.params for t in draws[1]]  # seeded draws
    assert draws[0][2].raw["bench"]["world"]["friction"]["positive"]["F_c_N"] == \
        draws[0][2].params[F_C]


@pytest.mark.parametrize("campaign, message", [
    ({"kind": "sweep"}, "campaign.kind: must be one of"),
    ({"n_runs": 3}, "campaign.n_runs: unknown key"),
    ({"seeds": [-1]}, "campaign.seeds: must be a non-empty list of integers ≥ 0"),
    ({"spread": {"bench.world.m_tip_kg": 0.1}}, "campaign.spread: only with kind = "),
    ({"kind": "montecarlo", "spread": {"bench.world.m_tip_kg": 0.1}},
     "campaign.spread.bench.world.m_tip_kg: the run config gives no number to spread"),
    ({"grid": {"bench.gains.K_p_Ns_m": 9000.0}},
     "campaign.grid.bench.gains.K_p_Ns_m: must be a non-empty list of values"),
    ({"grid": {"bench.gains.K_p_Ns_m": [9000.0, -1.0]}},
     "campaign run 1 (K_p_Ns_m=-1, noise_seed=0): bench.gains.K_p_Ns_m: must be > 0"),
    ({"grid": {"experiment.feeds_mm_min": [[100, 200]]}},
     "campaign run 0 (feeds_mm_min=[100, 200], noise_seed=0): experiment.feeds_mm_min: "),
])
def test_bad_campaign_configs_are_one_line(tmp_path, campaign, message):
    with pytest.raises(ConfigError) as refused:
        parse_campaign({**campaign_of(BASE, tmp_path), "campaign": campaign})
    assert str(refused.value).startswith(message)
    assert "\n" not in str(refused.value)
