"""The closure on data its own models did not make (issue 13): every case of the independent
simulator (`tests/independent_sim`: an exactly discretized n-mass chain under a 4 kHz / 1 kHz
P-PI cascade, one undeclared effect, a wrongly declared parameter, or nothing per case), fitted
on one recording and judged on a second (other seed, other feeds), in two variants: the exact
model declared, and mass and viscous friction left free.

Prints one row per case (injected, found, held-out force NRMSE before → after, the validation
record's noise floor, whether the error halved and whether it is fixed, closure wall time,
verdict) and the totals. Figures, per variant (`exact`, `free`), with the targets:
- independent_<variant>_named_first: share of effect cases whose effect is the first finding
  (≥ 0.9); a recalibration of inertia.M_kg names the `inertia_mismatch` cases (the same
  physics: a mass the declared model does not know).
- independent_<variant>_halved: share of effect and recalibration cases whose held-out error
  is at least halved (issue 13's criterion as written), printed for comparison.
- independent_<variant>_fixed: share of effect and recalibration cases whose held-out error is
  at least halved **or within 1.5× the noise floor** (≥ 0.9). This is the criterion the
  verdicts use, changed from "halved": a case that starts within about twice the noise floor
  cannot halve (the exact model itself ends at 0.65–1.04× the floor on clean recordings), and
  1.5× the floor is the issue's own target for a clean recording with the exact model.
- independent_<variant>_one_finding: share of effect and recalibration cases with exactly one
  finding: the injected effect explained once, no second effect beside it (issue 13.7's
  parsimony; 1.0).
- independent_<variant>_clean_untouched: share of clean cases where nothing is found (1.0).
- independent_<variant>_recalibrated: share of recalibration cases whose first finding is the
  recalibration of the wrongly declared parameter (≥ 0.8).
- independent_<variant>_crashes: cases where the closure raised (0).
- independent_<variant>_median_s: median closure wall time per case (≤ 10 s on 2 cores).

Run alone: `python benchmarks/bench_closure_independent.py [--cases NAME,...]
[--variants exact,free] [CASE ...]` (default: every case, both variants).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

from feedbench.analysis.closure import report_dict
from feedbench.commands.closure import closure_report

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from independent_sim import CASES, write_case  # noqa: E402  (tests/independent_sim)
from independent_sim.judge import Verdict, judge  # noqa: E402

from _timing import print_figures  # noqa: E402  (benchmarks/_timing.py)

VARIANTS = {"exact": False, "free": True}


def close_case(name: str, directory: Path, free: bool) -> tuple[Verdict, float]:
    """The closure on one case; its verdict (a crash recorded, not raised) and wall time."""
    files = write_case(name, directory, free)
    injected, kind = CASES[name].expected(free)
    start = time.perf_counter()
    try:
        report = closure_report(files.data_csv, files.model_toml, files.validation_csv)
        verdict = judge(report_dict(report), kind, injected, files.noise_floor)
    except Exception as exc:  # a crash is a finding of the benchmark, counted
        verdict = Verdict(kind, injected, (), float("nan"), float("nan"), files.noise_floor,
                          f"{type(exc).__name__}: {exc}")
    return verdict, time.perf_counter() - start


def _row(name: str, verdict: Verdict, seconds: float) -> str:
    if verdict.crash:
        outcome = f"CRASH {verdict.crash[:60]}"
    else:
        marks = "" if verdict.kind == "clean" else (
            f"{'halved' if verdict.halved else '':<6s} {'fixed' if verdict.fixed else '':<5s}")
        outcome = (f"{', '.join(verdict.found) or '—':<40.40s} {verdict.error_before:7.2%} → "
                   f"{verdict.error_after:6.2%} {verdict.noise_floor:6.2%} {marks:<12s}")
    mark = "ok" if verdict.passed else "MISS"
    return f"{name:<30s} {verdict.injected or '—':<36s} {outcome} {seconds:5.1f} s  {mark}"


def totals(verdicts: list[Verdict], seconds: list[float]) -> dict[str, float]:
    """The variant's shares, crash count and median time."""
    def share(kinds: tuple[str, ...], target: str) -> float:
        chosen = [v for v in verdicts if v.kind in kinds]
        return sum(getattr(v, target) for v in chosen) / len(chosen) if chosen else float("nan")

    return {"named_first": share(("effect",), "named_first"),
            "halved": share(("effect", "recalibration"), "halved"),
            "fixed": share(("effect", "recalibration"), "fixed"),
            "one_finding": share(("effect", "recalibration"), "one_finding"),
            "clean_untouched": share(("clean",), "untouched"),
            "recalibrated": share(("recalibration",), "named_first"),
            "crashes": float(sum(v.crash is not None for v in verdicts)),
            "median_s": statistics.median(seconds)}


def run(names: list[str] | None = None, variants: list[str] | None = None
        ) -> dict[str, float]:
    """Measure, print and return the figures of the cases `names` (default: all) in the
    `variants` (default: both)."""
    names = names or list(CASES)
    chosen = {variant: VARIANTS[variant] for variant in variants or VARIANTS}
    figures, notes = {}, {}
    targets = {"named_first": "≥ 0.9", "halved": "(as written)", "fixed": "≥ 0.9",
               "one_finding": "1.0", "clean_untouched": "1.0",
               "recalibrated": "≥ 0.8", "crashes": "0", "median_s": "≤ 10 s"}
    with tempfile.TemporaryDirectory() as directory:
        for variant, free in chosen.items():
            print(f"-- {variant}: {'mass and viscous free' if free else 'exact model declared'}")
            print(f"{'case':<30s} {'injected':<36s} {'found':<40s} before → after   floor")
            verdicts, seconds = [], []
            for name in names:
                verdict, wall = close_case(name, Path(directory), free)
                print(_row(name, verdict, wall), flush=True)
                verdicts.append(verdict)
                seconds.append(wall)
            for key, value in totals(verdicts, seconds).items():
                figures[f"independent_{variant}_{key}"] = value
                notes[f"independent_{variant}_{key}"] = f"target {targets[key]}"
    print_figures(figures, notes, 40, "8.3f")
    return figures


def _arguments(argv: list[str]) -> argparse.Namespace:
    """--cases NAME,... and --variants exact,free (both checked), or case names alone."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", metavar="CASE")
    parser.add_argument("--cases", default="", help="comma-separated case names")
    parser.add_argument("--variants", default=",".join(VARIANTS), help="exact,free")
    arguments = parser.parse_args(argv)
    arguments.names += [name for name in arguments.cases.split(",") if name]
    arguments.variants = [v for v in arguments.variants.split(",") if v]
    for name in arguments.names:
        if name not in CASES:
            parser.error(f"unknown case {name!r}")
    for variant in arguments.variants:
        if variant not in VARIANTS:
            parser.error(f"unknown variant {variant!r} (exact, free)")
    return arguments


if __name__ == "__main__":
    parsed = _arguments(sys.argv[1:])
    run(parsed.names, parsed.variants)
