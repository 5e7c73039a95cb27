"""The closure on real measurements (issue 24.5): the gallery of other labs' recordings
(`tests/data`, listed in `tests/data/gallery.toml`) and the two known machines of
`../shared/data` (EMPS; KUKA joints 1–3, fitted on trajectory A, judged on B).

Per dataset it prints the findings in order, whether the effect its authors document (its
key) is among the first two, the held-out force NRMSE before → after, whether the base and
the final fit are physical (every mass or inertia > 0, every friction level ≥ 0,
0 < ζ < 1; the values that are not are listed) and the closure's wall time. The held-out
datasets (nobody tunes on them) come in a table of their own.

Figures (`run()`, and one JSON line at the end when run alone), per dataset `<name>`:
real_<name>_key_first_two (1/0), real_<name>_error_before / _error_after (fractions),
real_<name>_base_physical / _final_physical (1/0), real_<name>_seconds; and the shares
real_tuning_key_first_two, real_held_out_key_first_two, real_*_base_physical,
real_*_final_physical over the tuning and the held-out datasets (known machines included in
the tuning set).

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
from feedbench.closure_command import closure_report

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from gallery import datasets  # noqa: E402  (tests/gallery.py)
from prerequisites import SHARED_DATA  # noqa: E402  (tests/prerequisites.py)

from _timing import print_figures  # noqa: E402  (benchmarks/_timing.py)

POSITIVE = frozenset({"M_kg", "m_kg", "m_load_kg"})
"""Masses and inertias (kg, kg·m², or the dataset's force unit · s²/m): must be > 0."""
NON_NEGATIVE = frozenset({"F_v_Ns_m", "F_c_N", "dF_s_N", "friction_N_kg"})
"""Friction levels (viscous, Coulomb, Stribeck excess, a load's friction): must be ≥ 0."""
DAMPING = frozenset({"zeta", "zeta_contact"})
"""Damping ratios: must lie in (0, 1)."""

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

    @property
    def key_first_two(self) -> bool:
        """Whether the authors' effect is the first or the second finding."""
        return self.case.key in self.findings[:2]


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


def unphysical(params: dict[str, dict[str, dict[str, Any]]]) -> tuple[str, ...]:
    """`term.key = value` of every mass ≤ 0, friction level < 0 or ζ outside (0, 1)."""
    flags = []
    for term, values in params.items():
        for key, entry in values.items():
            value = entry["value"]
            bad = ((key in POSITIVE and not value > 0.0)
                   or (key in NON_NEGATIVE and not value >= 0.0)
                   or (key in DAMPING and not 0.0 < value < 1.0))
            if bad:
                flags.append(f"{term}.{key} = {value:.4g}")
    return tuple(flags)


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
                   time.perf_counter() - start)


def _physical(flags: tuple[str, ...]) -> str:
    return "yes" if not flags else "NO"


def row(outcome: Outcome) -> str:
    """One line of the table, and a second listing the unphysical values, if any."""
    case = outcome.case
    if outcome.crash:
        return f"{case.name:<16s} {case.key:<8s} CRASH {outcome.crash[:90]}"
    line = (f"{case.name:<16s} {case.key:<8s} {', '.join(outcome.findings) or '—':<44.44s} "
            f"{'yes' if outcome.key_first_two else 'MISS':<5s} "
            f"{outcome.error_before:7.2%} → {outcome.error_after:7.2%}  "
            f"{_physical(outcome.base_flags):<4s} {_physical(outcome.final_flags):<4s} "
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
                        f"{name}_seconds": o.seconds})
    for figure in ("key_first_two", "base_physical", "final_physical"):
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
