"""Judging a closure report (the `feedbench closure --json` dictionary) against a case:
the targets of issue 13, from the report's data only."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

HALVED = 0.5
"""Error after / before at most this for an effect or a recalibration to count as halved."""

AT_THE_FLOOR = 1.5
"""Held-out error after at most this many times the case's noise floor: as good as the
exact model gets on a clean recording (issue 13's own target for the clean cases), so fixed
even where halving would need an error below the noise."""

SAME_PHYSICS = {"recalibrate:inertia.M_kg": "inertia_mismatch",
                "recalibrate:delay.tau_ms": "delay"}
"""Findings that name an injected effect of the simulator: a mass the declared model does not
know is the recalibration of the declared mass; an undeclared timing skew between the
channels is a timing finding, an added `delay` or the declared delay moved."""


def findings(report: Mapping[str, Any]) -> list[str]:
    """What the closure found, in order: effect names, and "recalibrate:<term>.<key>" for a
    recalibrated declared parameter."""
    steps = report.get("steps")
    if steps is None:
        return list(report["effects"])
    return [f"recalibrate:{s['recalibration']['parameter']}" if s.get("kind") == "recalibration"
            else s["effect"] for s in steps]


@dataclass(frozen=True)
class Verdict:
    """One case judged: kind, what was injected and found, held-out errors and the
    validation record's noise floor (fractions), whether it crashed (the exception's line,
    else None), and the targets met."""

    kind: str
    injected: str | None
    found: tuple[str, ...]
    error_before: float
    error_after: float
    noise_floor: float = math.nan
    crash: str | None = None

    @property
    def named_first(self) -> bool:
        """The injected effect (or recalibration) is the first finding, or a finding of the
        same physics (`SAME_PHYSICS`)."""
        return (self.crash is None and bool(self.found)
                and self.injected in (self.found[0], SAME_PHYSICS.get(self.found[0])))

    @property
    def one_finding(self) -> bool:
        """Exactly one finding: one injected effect (or wrong parameter) is explained once,
        not by a second effect besides it (parsimony, issue 13.7)."""
        return self.crash is None and len(self.found) == 1

    @property
    def halved(self) -> bool:
        """The held-out error at least halved."""
        return self.crash is None and self.error_after <= HALVED * self.error_before

    @property
    def fixed(self) -> bool:
        """Halved, or within AT_THE_FLOOR × the noise floor."""
        return self.halved or (self.crash is None
                               and self.error_after <= AT_THE_FLOOR * self.noise_floor)

    @property
    def untouched(self) -> bool:
        """Nothing found (the target of a clean case)."""
        return self.crash is None and not self.found

    @property
    def passed(self) -> bool:
        """Every target of its kind met: clean untouched; otherwise named first and fixed."""
        return self.untouched if self.kind == "clean" else self.named_first and self.fixed


def judge(report: Mapping[str, Any], kind: str, injected: str | None,
          noise_floor: float = math.nan) -> Verdict:
    """The verdict on a closure report of a case of `kind` with `injected`, whose validation
    record has `noise_floor` (fraction)."""
    return Verdict(kind, injected, tuple(findings(report)), float(report["error_before"]),
                   float(report["error_after"]), noise_floor)
