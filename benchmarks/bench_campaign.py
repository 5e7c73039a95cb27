"""A gain map as a Dask campaign (`feedbench campaign`, issue 15): 2 workers against 1.

The map is a short closed velocity-loop Bode (20–120 Hz in 10 Hz steps, 4 cycles each) at
every K_p × T_i of `GAINS`, `N_RUNS` runs (200, the issue's figure, about 5 min on 2
cores; ``FEEDBENCH_CAMPAIGN_RUNS`` overrides). Each campaign runs on its own LocalCluster of
worker processes, timed whole as a user waits for it (cluster start and the workers' imports
included); the baseline is the same map on one worker. Printed: both wall times, the speedup, and whether
every run's parameters and results (bandwidth, f_t, f_r, R² …) are identical either way.
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from feedbench.commands.campaign import parse_campaign, run_campaign
from feedbench.commands.demo import example_config

N_RUNS = int(os.environ.get("FEEDBENCH_CAMPAIGN_RUNS", "200"))
SHORT_BODE = {"f_start_Hz": 20.0, "f_stop_Hz": 120.0, "f_step_Hz": 10.0,
              "cycles_per_frequency": 4, "settle_cycles": 2}


def gain_map(n_runs: int, output_dir: Path) -> dict:
    """A campaign config: K_p (N·s/m) × T_i (ms) around the lab bench's standard tuning,
    8 T_i values per K_p, n_runs rounded down to a multiple of 8 (at least 8)."""
    raw = example_config("closed_loop_bode")
    raw["bench"]["output_dir"] = str(output_dir)
    raw["experiment"].update(SHORT_BODE)
    n_ti = 8
    n_kp = max(1, n_runs // n_ti)
    k_p = np.linspace(6000.0, 14000.0, n_kp).round(1).tolist()
    t_i = np.linspace(4.0, 16.0, n_ti).round(3).tolist()
    raw["campaign"] = {"grid": {"bench.gains.K_p_Ns_m": k_p, "bench.gains.T_i_ms": t_i}}
    return raw


def timed(raw: dict, workers: int) -> tuple[float, list[dict]]:
    """Wall time (s) of the whole campaign on `workers` local worker processes, its rows."""
    campaign = parse_campaign(raw)
    t0 = time.perf_counter()
    summary = run_campaign(campaign, workers=workers)
    seconds = time.perf_counter() - t0
    failed = [row for row in summary["runs"] if row["status"] != "complete"]
    assert not failed, failed[0]
    return seconds, summary["runs"]


def differences(rows_one: list[dict], rows_two: list[dict]) -> list[tuple]:
    """(run index, key, value on 1 worker, on 2) of every parameter or result that differs."""
    out = []
    for a, b in zip(rows_one, rows_two, strict=True):
        for part in ("params", "results"):
            out += [(a["index"], key, a[part].get(key), b[part].get(key))
                    for key in sorted(set(a[part]) | set(b[part]))
                    if not same(a[part].get(key), b[part].get(key))]
    return out


def same(a: object, b: object) -> bool:
    """Equal, or both NaN (a bandwidth the band does not reach)."""
    return a == b or all(isinstance(v, float) and math.isnan(v) for v in (a, b))


def run() -> dict[str, float]:
    with tempfile.TemporaryDirectory() as directory:
        raw = gain_map(N_RUNS, Path(directory))
        one, rows_one = timed(raw, 1)
        two, rows_two = timed(raw, 2)
    n_runs = len(rows_one)
    differ = differences(rows_one, rows_two)
    identical = not differ
    bandwidth = np.array([row["results"]["bandwidth_hz"] for row in rows_two])
    print(f"gain map, {n_runs} closed-loop Bode runs: 1 worker {one:.1f} s, 2 workers "
          f"{two:.1f} s: speedup {one / two:.2f} (issue: >= 1.7 for 200 runs)")
    print(f"  per run: {one / n_runs:.2f} s on 1 worker, {two / n_runs:.2f} s on 2; "
          f"-3 dB bandwidth over the map {np.nanmin(bandwidth):.1f}-{np.nanmax(bandwidth):.1f} Hz"
          f" ({np.isnan(bandwidth).sum()} runs above the 120 Hz band)")
    print(f"  every run's parameters and results identical either way: {identical}")
    for index, key, a, b in differ[:5]:
        print(f"    run {index} {key}: {a!r} on 1 worker, {b!r} on 2")
    return {"campaign_gain_map_runs": float(n_runs), "campaign_1_worker_s": one,
            "campaign_2_workers_s": two, "campaign_speedup": one / two,
            "campaign_identical": float(identical)}


if __name__ == "__main__":
    run()
