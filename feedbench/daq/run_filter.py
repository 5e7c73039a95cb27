"""Which runs `feedbench runs` lists: by bench, family, status, start date and any key
parameter (``--where 'chirp.f_stop_Hz>150'``).

The bench, family, status and dates become SQL conditions on the catalog's columns (the same
on SQLite and PostgreSQL: text comparisons, ISO 8601 UTC times sort as text). A `--where`
condition becomes SQL too (`Condition.clause`, through SQLAlchemy Core: SQLite's json_tree,
PostgreSQL's jsonb ``#>`` and jsonb_typeof on the parameters parsed when the row was written),
exact for a number, text, true, false or null and letting an array or object through; a row
read is then checked on its parameters in Python (`Condition.matches`, the definition) unless
SQL has decided alone (`Condition.decided_in_sql`, `Catalog.lines`), so the SQL spares
reading the rows that cannot match. A row whose parameters are not JSON (`damaged`) never
matches: PostgreSQL's parsed parameters are NULL; SQLite refuses to parse them, and
`Catalog.list` then checks the conditions in Python alone (`RunFilter.clauses` with
``in_sql=False``) until `feedbench catalog rebuild`.
"""

from __future__ import annotations

import math
import operator
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import date, datetime, time, timedelta, timezone
from typing import Any

from sqlalchemy import (ColumnElement, Table, and_, case, cast, exists, false, func, literal,
                        literal_column, or_)
from sqlalchemy.dialects.postgresql import ARRAY, JSONB
from sqlalchemy.types import Float, Text

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


    @property
    def decided_in_sql(self) -> bool:
        """Whether `clause` decides alone every run whose value is no array or table (the
        condition's value a finite number; else it lets a number through to `matches`)."""
        return _number(self.value) is not None

    def clause(self, runs: Table, document: Any = None) -> ColumnElement[bool]:
        """The SQL condition on the catalog's `runs` table that selects the rows whose
        parameters meet it (`matches`): exact where the run's value is a number, text, true,
        false or null, true where it is an array or an object (`matches` decides those).
        SQLite: `document` None, the parameters parsed once per row (json_tree); parameters
        that are not JSON (a damaged row) make it refuse the statement (`Catalog.list` then
        lists with `RunFilter.clauses(in_sql=False)`). PostgreSQL: `document` the row's
        parameters as jsonb (`parsed_parameters`: NULL for a damaged row, never matched)."""
        paths = [self.path]
        if len(self.path) > 1:  # led by a family: its runs' own key, others' nested table
            paths.insert(0, self.path[1:])
        compare = OPERATORS[self.op]
        number = _number(self.value)
        if document is None:
            where = [("$" + "".join(f'."{key}"' for key in path)) for path in paths]
            at = where[0] if len(where) == 1 else case(
                (runs.c.experiment == self.path[0], where[0]), else_=where[1])
            node = func.json_tree(runs.c.params, at).table_valued("type", "atom", "parent")
            kind, value, text = node.c.type, node.c.atom, node.c.atom
            numeric, string, integer = ("integer", "real"), "text", ("integer",)
            constants = {"true": "true", "false": "false", "null": "None"}
        else:
            where = [literal(list(path), ARRAY(Text)) for path in paths]
            at = where[0] if len(where) == 1 else case(
                (runs.c.experiment == self.path[0], where[0]), else_=where[1])
            found = document.op("#>")(at)
            kind = func.jsonb_typeof(found)
            value = found.op("#>>", return_type=Text)(literal([], ARRAY(Text)))
            text = value.collate("C")  # code point order, as Python's
            numeric, string, integer = ("number",), "string", ()
            constants = {"null": "None"}
        alternatives = [kind.in_(("array", "object"))]
        if number is not None:  # the cast only on a number (CASE: in that order)
            alternatives.append(case((kind.in_(numeric), compare(cast(value, Float), number)),
                                     else_=false()))
        else:  # a number's text: an integer's the same in SQL, a real's may differ: let through
            alternatives.append(kind.in_([name for name in numeric if name not in integer]))
            if integer:
                alternatives.append(and_(kind.in_(integer), compare(cast(value, Text),
                                                                    self.value)))
        alternatives.append(and_(kind == string, compare(text, self.value)))
        if document is not None:  # a boolean's text is true / false
            alternatives.append(and_(kind == "boolean", compare(text, self.value)))
        alternatives += [kind == name for name, shown in constants.items()
                         if compare(shown, self.value)]
        if document is not None:
            return or_(*alternatives)
        return exists().where(node.c.parent.is_(None), or_(*alternatives))


def parsed_parameters(runs: Table) -> Any:
    """PostgreSQL: the rows' parameters as jsonb for the `Condition.clause` of each
    ``--where``: the catalog's column ``document``, parsed when the row was written, NULL
    where they are no JSON object (a damaged row: never matches; catalog schema version 3)."""
    return literal_column(f"{runs.name}.document", JSONB)


def _number(value: str) -> float | None:
    """The condition's value as a finite number, or None (text, nan, inf: `matches`)."""
    try:
        number = float(value)
    except ValueError:
        return None
    return number if math.isfinite(number) else None


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

    def clauses(self, runs: Table, document: Any = None,
                in_sql: bool = True) -> list[ColumnElement[bool]]:
        """The SQL conditions on the catalog's `runs` table; the `where` conditions in SQL
        (`Condition.clause`; `document`: PostgreSQL's `parsed_parameters` column) unless not
        `in_sql` (then only the rows whose parameters name the key: `matches` checks them)."""
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
        if in_sql:
            clauses += [condition.clause(runs, document) for condition in self.where]
        return clauses

    def matches(self, experiment: str, status: str, params: Mapping[str, Any]) -> bool:
        """Whether a read row meets the conditions SQL cannot check (its status as read: a
        damaged row's; the `where` conditions)."""
        if self.status is not None and status != self.status:
            return False
        return all(condition.matches(experiment, params) for condition in self.where)
