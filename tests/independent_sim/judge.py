"""Judging a closure report (the `feedbench closure --json` dictionary) against a case:
the targets of issue 13, from the report's data only."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

HALVED = 0.5
"""Error after / before at most this for an effect or a recalibration to count as fixed."""


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
    """One case judged: kind, what was injected and found, held-out errors (fractions),
    whether it crashed (the exception's line, else None), and the targets met."""

    kind: str
    injected: str | None
    found: tuple[str, ...]
    error_before: float
    error_after: float
    crash: str | None = None

    @property
    def named_first(self) -> bool:
        """The injected effect (or recalibration) is the first finding."""
        return self.crash is None and bool(self.found) and self.found[0] == self.injected

    @property
    def halved(self) -> bool:
        """The held-out error at least halved."""
        return self.crash is None and self.error_after <= HALVED * self.error_before

    @property
    def untouched(self) -> bool:
        """Nothing found (the target of a clean case)."""
        return self.crash is None and not self.found

    @property
    def passed(self) -> bool:
        """Every target of its kind met: clean untouched; otherwise named first and halved."""
        return self.untouched if self.kind == "clean" else self.named_first and self.halved


def judge(report: Mapping[str, Any], kind: str, injected: str | None) -> Verdict:
    """The verdict on a closure report of a case of `kind` with `injected`."""
    return Verdict(kind, injected, tuple(findings(report)), float(report["error_before"]),
                   float(report["error_after"]))
