"""The closure on real measurements (issue 24.5): the gallery of other labs' recordings
(`tests/data`, listed in `tests/data/gallery.toml`) and the two known machines of
`../shared/data` (EMPS; KUKA joints 1–3, fitted on trajectory A, judged on B).

Per dataset it prints the findings in order, whether the effect its authors document (its
key) is among the first two, the held-out force NRMSE before → after, whether the base and
the final fit are physical (every mass or inertia > 0, every friction level ≥ 0, a mode's
0 < ζ < 1: `analysis.closure.report.unphysical`; the values that are not are listed) —
"yes", "n.d." when the closure declared that model not describing the data, "NO" when an
unphysical model was called describing — and the closure's wall time. The held-out datasets
(nobody tunes on them) come in a table of their own.

Figures (`run()`, and one JSON line at the end when run alone), per dataset `<name>`:
real_<name>_key_first_two (1/0), real_<name>_error_before / _error_after (fractions),
real_<name>_base_physical / _final_physical (1/0), real_<name>_base_honest /
_final_honest (1/0: physical, or declared not describing), real_<name>_seconds; and the
shares of each 1/0 figure over the tuning and the held-out datasets (known machines
included in the tuning set).

Run alone: `python benchmarks/bench_closure_real.py`.
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from feedbench.analysis.closure import report_dict
from feedbench.analysis.closure.report import unphysical
from feedbench.commands.closure import closure_report

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from gallery import datasets  # noqa: E402  (tests/gallery.py)
from prerequisites import SHARED_DATA  # noqa: E402  (tests/prerequisites.py)

from _timing import print_figures  # noqa: E402  (benchmarks/_timing.py)

EMPS = SHARED_DATA / "emps"
KUKA = SHARED_DATA / "kuka-robot"


@dataclass(frozen=True)
class Case:
    """One dataset to close: `close()` runs the closure; key: the effect its authors
    document; source: where the data come from (one short phrase)."""

    name: str
    source: str
    key: str
    held_out: bool
    close: Callable[[], Any]


@dataclass(frozen=True)
class Outcome:
    """What the closure did on one case (a crash recorded, not raised)."""

    case: Case
    findings: tuple[str, ...]
    error_before: float
    error_after: float
    base_flags: tuple[str, ...]
    final_flags: tuple[str, ...]
    seconds: float
    crash: str = ""
    base_describes: bool = False
    final_describes: bool = False

    @property
    def key_first_two(self) -> bool:
        """Whether the authors' effect is the first or the second finding."""
        return self.case.key in self.findings[:2]

    @property
    def base_honest(self) -> bool:
        """The base fit physical, or declared not describing the data (issue 24's bar)."""
        return not self.crash and (not self.base_flags or not self.base_describes)

    @property
    def final_honest(self) -> bool:
        """The final fit physical, or declared not describing the data."""
        return not self.crash and (not self.final_flags or not self.final_describes)


def known_cases() -> list[Case]:
    """EMPS (estimation → PULSES) and KUKA joints 1–3 (A → B), where the shared data are."""
    cases = []
    if (EMPS / "DATA_EMPS.mat").exists():
        cases.append(Case("emps", "EMPS benchmark (Janot et al. 2019)", "coulomb", False,
                          lambda: closure_report(EMPS / "DATA_EMPS.mat", None,
                                                 EMPS / "DATA_EMPS_PULSES.mat")))
    fit, second = KUKA / "recorded_FF_A_08ms.mat", KUKA / "recorded_FF_B_08ms.mat"
    if fit.exists() and second.exists():
        cases += [Case(f"kuka-joint-{axis}", "KUKA KR300 (Weigand)", "coulomb", False,
                       lambda axis=axis: closure_report(fit, None, second, axis=axis))
                  for axis in (1, 2, 3)]
    return cases


def gallery_cases() -> list[Case]:
    """Every dataset of tests/data/gallery.toml."""
    return [Case(d.name, "tests/data", d.key, d.held_out,
                 lambda d=d: closure_report(d.fit, d.model, d.validation))
            for d in datasets()]


def findings(report: dict[str, Any]) -> tuple[str, ...]:
    """The steps of the search in order: an effect's name, or `recalibrate <term.key>`."""
    return tuple(f"recalibrate {step['recalibration']['parameter']}"
                 if step["kind"] == "recalibration" else step["effect"]
                 for step in report["steps"])


def close(case: Case) -> Outcome:
    """Run one case and read its report."""
    start = time.perf_counter()
    try:
        report = report_dict(case.close())
    except Exception as exc:  # a crash is a finding of the benchmark, counted
        return Outcome(case, (), math.nan, math.nan, (), (), time.perf_counter() - start,
                       f"{type(exc).__name__}: {exc}")
    return Outcome(case, findings(report), report["error_before"], report["error_after"],
                   unphysical(report["base_params"]), unphysical(report["final_params"]),
                   time.perf_counter() - start,
                   base_describes=report["base_verdict"]["describes"],
                   final_describes=report["final_verdict"]["describes"])


def _physical(flags: tuple[str, ...], describes: bool) -> str:
    """"yes" (physical, describes), "n.d." (physical or not, declared not describing the
    data), "NO" (not physical yet called describing: the failure the column is for)."""
    if not describes:
        return "n.d."
    return "yes" if not flags else "NO"


def row(outcome: Outcome) -> str:
    """One line of the table, and a second listing the unphysical values, if any."""
    case = outcome.case
    if outcome.crash:
        return f"{case.name:<16s} {case.key:<8s} CRASH {outcome.crash[:90]}"
    line = (f"{case.name:<16s} {case.key:<8s} {', '.join(outcome.findings) or '—':<44.44s} "
            f"{'yes' if outcome.key_first_two else 'MISS':<5s} "
            f"{outcome.error_before:7.2%} → {outcome.error_after:7.2%}  "
            f"{_physical(outcome.base_flags, outcome.base_describes):<4s} "
            f"{_physical(outcome.final_flags, outcome.final_describes):<5s} "
            f"{outcome.seconds:5.1f} s")
    flagged = [f"base {f}" for f in outcome.base_flags] + [
        f"final {f}" for f in outcome.final_flags]
    return line + (f"\n{'':<25s}not physical: {'; '.join(flagged)}" if flagged else "")


def table(title: str, outcomes: list[Outcome]) -> None:
    """Print one table."""
    print(f"-- {title}")
    print(f"{'dataset':<16s} {'key':<8s} {'findings, in order':<44s} {'key≤2':<5s} "
          f"{'held-out before → after':<24s} {'base':<4s} {'final':<5s} time")
    for outcome in outcomes:
        print(row(outcome), flush=True)


def figures_of(outcomes: list[Outcome], group: str) -> dict[str, float]:
    """Per-dataset figures and the group's shares."""
    figures = {}
    for o in outcomes:
        name = f"real_{o.case.name}"
        figures.update({f"{name}_key_first_two": float(o.key_first_two),
                        f"{name}_error_before": o.error_before,
                        f"{name}_error_after": o.error_after,
                        f"{name}_base_physical": float(not o.crash and not o.base_flags),
                        f"{name}_final_physical": float(not o.crash and not o.final_flags),
                        f"{name}_base_honest": float(o.base_honest),
                        f"{name}_final_honest": float(o.final_honest),
                        f"{name}_seconds": o.seconds})
    for figure in ("key_first_two", "base_physical", "final_physical", "base_honest",
                   "final_honest"):
        values = [figures[f"real_{o.case.name}_{figure}"] for o in outcomes]
        figures[f"real_{group}_{figure}"] = sum(values) / len(values) if values else math.nan
    return figures


def run() -> dict[str, float]:
    """Close every case, print both tables and the figures; return the figures."""
    cases = known_cases() + gallery_cases()
    outcomes = [close(case) for case in cases]
    tuning = [o for o in outcomes if not o.case.held_out]
    held_out = [o for o in outcomes if o.case.held_out]
    table("tuning set: known machines and the gallery", tuning)
    table("HELD OUT (nobody tunes on these)", held_out)
    figures = {**figures_of(tuning, "tuning"), **figures_of(held_out, "held_out")}
    print_figures(figures, {name: "" for name in figures}, 44, "9.4f")
    return figures


if __name__ == "__main__":
    print(json.dumps(run()))
