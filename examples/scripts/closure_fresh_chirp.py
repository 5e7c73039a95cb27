"""A fresh chirp recording, then the closure: what does the rigid-body model miss?

Runs a chirp into the drive while the axis moves, and closes the loop on that recording
against a rigid body with Coulomb and viscous friction (`docs/closure.md`): the closure
names the effects the model lacks, adds them and reports the held-out force error before
and after (fractions), and the parameters it fitted (SI)::

    python examples/scripts/closure_fresh_chirp.py [--repetitions 4] [--report out.html]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import feedbench
from feedbench.analysis.closure import report_dict
from feedbench.commands.closure import closure_report

HERE = Path(__file__).parent
MODEL = HERE.parents[1] / "feedbench" / "examples" / "closure" / "bench_coulomb_viscous.toml"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default=HERE / "lab_bench.toml", help="bench config (TOML)")
    parser.add_argument("--model", default=MODEL, help="model config of the closure (TOML)")
    parser.add_argument("--duration-s", type=float, default=4.0, help="one sweep (s)")
    parser.add_argument("--repetitions", type=int, default=4, help="sweeps")
    args = parser.parse_args()

    with feedbench.open_bench(args.config) as bench:
        bench.drive.enable()
        run = bench.run("chirp", duration_s=args.duration_s, repetitions=args.repetitions)
    print(f"run = {run.id} ({run.status}, {run.path})")
    closure = report_dict(closure_report(run.path, args.model))
    print(f"effects = {','.join(closure['effects'])}")
    print(f"error_before = {closure['error_before']:.4f}")
    print(f"error_after = {closure['error_after']:.4f}")
    for effect, params in closure["params"].items():
        for key, value in params.items():
            print(f"{effect}.{key} = {value['value']:.6g}")


if __name__ == "__main__":
    main()
