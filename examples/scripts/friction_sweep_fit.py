"""Friction sweep on the bench, then the Andersson law (Eq. 5.2) fitted per direction.

The sweep's own analysis fits Eq. (5.2) with δ = 1; this script refits the measured
points with δ free as well, and prints both (F_c, F_s in N, v_s in mm/min, σ in N·min/mm)::

    python examples/scripts/friction_sweep_fit.py [--config BENCH.toml] [--settle-s 0.4]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import feedbench
from feedbench.analysis.friction import fit_andersson
from feedbench.units import MM_PER_MIN, N_MIN_PER_MM

HERE = Path(__file__).parent
FEEDS_MM_MIN = [25, 50, 75, 100, 150, 200, 300, 400, 500, 700, 900, 1200, 1500]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default=HERE / "lab_bench.toml", help="bench config (TOML)")
    parser.add_argument("--feeds", type=float, nargs="+", default=FEEDS_MM_MIN,
                        help="feeds per direction (mm/min)")
    parser.add_argument("--settle-s", type=float, default=1.0, help="settle time per feed (s)")
    parser.add_argument("--measure-s", type=float, default=0.5, help="measure window (s)")
    args = parser.parse_args()

    with feedbench.open_bench(args.config) as bench:
        bench.drive.enable()
        bench.drive.move_to(0.0, feed_mm_min=1000.0)
        sweep = bench.run("friction_sweep", feeds_mm_min=args.feeds, settle_s=args.settle_s,
                          measure_s=args.measure_s)
    print(f"run = {sweep.id} ({sweep.status}, {sweep.path})")
    v = np.asarray(sweep.result["points"]["velocity_m_s"])
    force = np.asarray(sweep.result["points"]["force_N"])
    for direction, sign in (("positive", 1.0), ("negative", -1.0)):
        fixed = sweep.result[direction]["identified"]
        free = fit_andersson(v[np.sign(v) == sign], force[np.sign(v) == sign], fit_delta=True)
        print(f"{direction}.F_c_N = {fixed['F_c']:.3f}")
        print(f"{direction}.F_s_N = {fixed['F_s']:.3f}")
        print(f"{direction}.v_s_mm_min = {fixed['v_s'] / MM_PER_MIN:.2f}")
        print(f"{direction}.sigma_N_min_mm = {fixed['sigma'] / N_MIN_PER_MM:.6f}")
        print(f"{direction}.r_squared = {sweep.result[direction]['r_squared']:.6f}")
        print(f"{direction}.delta_free.delta = {free.params.delta:.3f}")
        print(f"{direction}.delta_free.F_c_N = {free.params.F_c:.3f}")
        print(f"{direction}.delta_free.r_squared = {free.r_squared:.6f}")


if __name__ == "__main__":
    main()
