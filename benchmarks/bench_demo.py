"""The quick demo as a user waits for it (`feedbench demo --quick`, issue 29): its examples on
one worker process per CPU against the same demo one after the other (``--workers 1``).

Each demo is the command in a subprocess, timed whole (imports, runs, analyses, report);
both write into fresh directories. Printed: both wall times and their ratio, each one's CPU
time (on a shared machine the wall time shows the other jobs too), where the concurrent
demo's time went (its summary's ``timing``), the machine's load, and whether every number of
the two summaries is identical (`demo.numbers_of`: all but run ids, files, times).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile

from _timing import best_of, children_cpu_s  # benchmarks/_timing.py
from feedbench.commands.demo import numbers_of

TARGET_S = 25.0
"""The issue's goal for the quick demo on 2 cores."""
REPEATS = int(os.environ.get("FEEDBENCH_DEMO_REPEATS", "1"))
"""Demos per setting (best of): one takes 25–60 s."""


def demo(workers: int | None) -> tuple[dict, float]:
    """`feedbench demo --quick --json` in a fresh directory (`workers`: None, the default):
    its summary and the CPU time (s, user + system) of its processes."""
    before = children_cpu_s()
    with tempfile.TemporaryDirectory() as directory:
        extra = ["--workers", str(workers)] if workers else []
        proc = subprocess.run([sys.executable, "-m", "feedbench.commands.cli", "demo", "--quick", "--json",
                               "--dir", directory, *extra],
                              capture_output=True, text=True, check=True)
    return json.loads(proc.stdout), children_cpu_s() - before


def run() -> dict[str, float]:
    load = os.getloadavg()[0]
    sequential, (one, one_cpu) = best_of(lambda: demo(1), REPEATS)
    concurrent, (result, cpu) = best_of(lambda: demo(None), REPEATS)
    identical = numbers_of(one) == numbers_of(result)
    timing = result["timing"]
    print(f"quick demo: one after the other {sequential:.1f} s, on {timing['workers']} workers "
          f"{concurrent:.1f} s: {concurrent / sequential:.2f} of the sequential demo "
          f"(issue: <= {TARGET_S:g} s on 2 cores); load before {load:.2f}")
    print(f"  CPU time: {one_cpu:.1f} s one after the other, {cpu:.1f} s on "
          f"{timing['workers']} workers")
    print(f"  where: set-up {timing['setup_s']:.1f} s, runs {timing['runs_s']:.1f} s, report "
          f"{timing['report_s']:.1f} s; worker time: measuring {timing['elapsed_worker_s']:.1f}"
          f" s, analysis {timing['analysis_worker_s']:.1f} s, report sections "
          f"{timing['report_worker_s']:.1f} s")
    print(f"  every number of the two summaries identical: {identical}")
    return {"demo_sequential_s": sequential, "demo_s": concurrent,
            "demo_over_sequential": concurrent / sequential,
            "demo_sequential_cpu_s": one_cpu, "demo_cpu_s": cpu,
            "demo_setup_s": timing["setup_s"], "demo_runs_s": timing["runs_s"],
            "demo_identical": float(identical)}


if __name__ == "__main__":
    run()
