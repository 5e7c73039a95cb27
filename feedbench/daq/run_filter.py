"""Which runs `feedbench runs` lists: by bench, family, status, start date and any key
parameter (``--where 'chirp.f_stop_Hz>150'``).

The bench, family, status and dates become SQL conditions on the catalog's columns (the same
on SQLite and PostgreSQL: text comparisons, ISO 8601 UTC times sort as text); a `--where`
condition reads in SQL only the rows whose parameters' text names its key, and is checked on
each one's parameters once read, so a row whose parameters cannot be read (`damaged`) is never
compared and no database has to parse JSON it may not be able to.
"""

from __future__ import annotations

import operator
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import date, datetime, time, timedelta, timezone
from typing import Any

from sqlalchemy import ColumnElement, Table

from feedbench.config import ConfigError

OPERATORS: dict[str, Callable[[Any, Any], bool]] = {
    ">=": operator.ge, "<=": operator.le, "!=": operator.ne, "==": operator.eq,
    "=": operator.eq, ">": operator.gt, "<": operator.lt,
}
DAMAGED = "damaged"
"""The status of a row the catalog cannot read (`feedbench.daq.catalog.DAMAGED`)."""
CONDITION = re.compile(r"^\s*([A-Za-z_][\w.]*)\s*(>=|<=|!=|==|=|>|<)\s*(.+?)\s*$")


@dataclass(frozen=True)
class Condition:
    """One ``--where`` condition: a dotted path into a run's parameters, led by its family's
    name (``chirp.f_stop_Hz``) or not (``f_stop_Hz``: any family), an operator, a value
    (compared as a number when both sides are numbers, else as text)."""

    path: tuple[str, ...]
    op: str
    value: str

    @classmethod
    def parse(cls, text: str) -> Condition:
        """``PATH OP VALUE``; anything else raises `ConfigError` naming ``--where``."""
        match = CONDITION.match(text)
        if not match:
            raise ConfigError(f"--where: {text!r} is not PATH OP VALUE (e.g. "
                              f"'chirp.f_stop_Hz>150'; operators {' '.join(OPERATORS)})")
        path, op, value = match.groups()
        return cls(tuple(path.split(".")), op, value.strip("'\""))

    def matches(self, experiment: str, params: Mapping[str, Any]) -> bool:
        """Whether a run of family `experiment` with key parameters `params` meets it (a run
        without the parameter: no)."""
        path = self.path[1:] if len(self.path) > 1 and self.path[0] == experiment else self.path
        found: Any = params
        for key in path:
            if not isinstance(found, Mapping) or key not in found:
                return False
            found = found[key]
        left, right = _comparable(found, self.value)
        try:
            return OPERATORS[self.op](left, right)
        except TypeError:  # text against a number
            return False


def _comparable(found: Any, value: str) -> tuple[Any, Any]:
    """The run's value and the condition's, both numbers if both read as numbers, else text."""
    if isinstance(found, (int, float)) and not isinstance(found, bool):
        try:
            return float(found), float(value)
        except ValueError:
            pass
    return str(found).lower() if isinstance(found, bool) else str(found), value


def day_bound(text: str, field: str, end: bool = False) -> str:
    """`text` (an ISO date or time; a time without zone is UTC) as the ISO 8601 UTC text the
    catalog's times compare with; a date's `end` bound is the start of the next day."""
    try:
        moment = datetime.fromisoformat(text)
    except ValueError:
        raise ConfigError(f"{field}: {text!r} is not a date (YYYY-MM-DD) or an ISO time")
    if len(text.strip()) == 10:  # a date: the whole day
        day = date.fromisoformat(text) + timedelta(days=1 if end else 0)
        moment = datetime.combine(day, time(), timezone.utc)
    elif moment.tzinfo is None:
        moment = moment.replace(tzinfo=timezone.utc)
    return moment.astimezone(timezone.utc).isoformat()


@dataclass(frozen=True)
class RunFilter:
    """The runs to list: each given criterion must hold (`since`/`until`: ISO 8601 UTC
    bounds of the start time, `until` exclusive; see `day_bound`)."""

    bench: str | None = None
    experiment: str | None = None
    status: str | None = None
    since: str | None = None
    until: str | None = None
    where: tuple[Condition, ...] = ()

    def clauses(self, runs: Table) -> list[ColumnElement[bool]]:
        """The SQL conditions on the catalog's `runs` table (all but `where`)."""
        status = None if self.status == DAMAGED else self.status  # a status read, not stored
        clauses = [runs.c[name] == value for name, value in (
            ("bench", self.bench), ("experiment", self.experiment), ("status", status))
            if value is not None]
        if self.since is not None:
            clauses.append(runs.c.started_at >= self.since)
        if self.until is not None:
            clauses.append(runs.c.started_at < self.until)
        clauses += [runs.c.params.contains(f'"{condition.path[-1]}"', autoescape=True)
                    for condition in self.where]  # only rows that name the key: fewer to read
        return clauses

    def matches(self, experiment: str, status: str, params: Mapping[str, Any]) -> bool:
        """Whether a read row meets the conditions SQL cannot check (its status as read: a
        damaged row's; the `where` conditions)."""
        if self.status is not None and status != self.status:
            return False
        return all(condition.matches(experiment, params) for condition in self.where)
