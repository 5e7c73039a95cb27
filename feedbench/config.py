"""TOML configuration: schema, validation, one-line errors that name the field.

A config file has three tables: ``[bench]`` (how to reach the drive, and for a simulated
bench the world it simulates), ``[limits]`` (what the runner watches) and ``[experiment]``
(the plan; its keys depend on ``experiment.type``). Every value is in the engineering
units its key names (``_mm``, ``_mm_min``, ``_N``, ``_Hz``, ``_s``); `load_config` checks
every key before anything moves and raises `ConfigError` with the dotted field name and
the reason.
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass
from functools import cache
from importlib.metadata import EntryPoint, entry_points
from pathlib import Path
from typing import Any, Callable, Mapping


class ConfigError(ValueError):
    """A config value is unknown, of the wrong type or out of range; the message names it."""


Check = Callable[[Any], str | None]


@dataclass(frozen=True)
class Field:
    """One config key: its type, default (``REQUIRED`` if none), check and meaning."""

    kind: type | tuple[type, ...]
    default: Any
    doc: str
    check: Check | None = None


REQUIRED = object()
TABLE = object()
"""Marks a nested table whose own keys are validated by a sub-schema."""


def positive(value: Any) -> str | None:
    """Check: a number > 0."""
    values = value if isinstance(value, list) else [value]
    for i, v in enumerate(values):
        if not v > 0:
            where = f"[{i}]" if isinstance(value, list) else ""
            return f"{where}: must be > 0 (got {v})"
    return None


def non_negative(value: Any) -> str | None:
    """Check: a number >= 0 (or a list of them)."""
    values = value if isinstance(value, list) else [value]
    for i, v in enumerate(values):
        if not v >= 0:
            where = f"[{i}]" if isinstance(value, list) else ""
            return f"{where}: must be >= 0 (got {v})"
    return None


def one_of(*choices: str) -> Check:
    """Check: one of the given strings (or a list of them)."""

    def check(value: Any) -> str | None:
        values = value if isinstance(value, list) else [value]
        bad = [v for v in values if v not in choices]
        return f": must be one of {', '.join(choices)} (got {bad[0]!r})" if bad else None

    return check


def interval(value: Any) -> str | None:
    """Check: a [low, high] pair with low < high."""
    if len(value) != 2 or not value[0] < value[1]:
        return f": must be [low, high] with low < high (got {value})"
    return None


def _type_name(kind: type | tuple[type, ...]) -> str:
    kinds = kind if isinstance(kind, tuple) else (kind,)
    names = {float: "number", int: "integer", str: "string", bool: "true/false", list: "list"}
    return " or ".join(names.get(k, k.__name__) for k in kinds)


def _is_kind(value: Any, kind: type | tuple[type, ...]) -> bool:
    kinds = kind if isinstance(kind, tuple) else (kind,)
    if isinstance(value, bool):
        return bool in kinds
    if isinstance(value, int) and float in kinds:
        return True
    return isinstance(value, kinds)


def _list_items_are_numbers(value: list) -> bool:
    return all(_is_kind(v, float) and math.isfinite(v) for v in value)


def validate_table(table: Mapping[str, Any], schema: Mapping[str, Field], path: str) -> dict:
    """Check `table` against `schema`; return it with defaults filled in.

    Raises `ConfigError` naming ``path.key`` for an unknown key, a missing required key,
    a wrong type or a value its check rejects.
    """
    unknown = sorted(set(table) - set(schema))
    if unknown:
        raise ConfigError(f"{path}.{unknown[0]}: unknown key (known: {', '.join(sorted(schema))})")
    out: dict[str, Any] = {}
    for key, spec in schema.items():
        name = f"{path}.{key}"
        if key not in table:
            if spec.default is REQUIRED:
                raise ConfigError(f"{name}: required key is missing ({spec.doc})")
            out[key] = spec.default
            continue
        value = table[key]
        if not _is_kind(value, spec.kind):
            raise ConfigError(f"{name}: must be a {_type_name(spec.kind)} (got {value!r})")
        if isinstance(value, list) and spec.kind is list and not _list_items_are_numbers(value):
            if not all(isinstance(v, str) for v in value):
                raise ConfigError(f"{name}: must be a list of numbers (got {value!r})")
        if isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(f"{name}: must be finite (got {value})")
        problem = spec.check(value) if spec.check else None
        if problem:
            raise ConfigError(f"{name}{problem}")
        out[key] = value
    return out


def read_toml(path: str | Path) -> dict:
    """Parse a TOML file; a missing file or a syntax error becomes a `ConfigError`."""
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:  # TOML is UTF-8 text
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None


OWN_DISTRIBUTION = "feedbench"
"""The distribution that registers feedbench's own families, devices and peers."""


def distribution_name(name: str) -> str:
    """A distribution's name as PEP 503 compares it (``My_Lab.x`` → ``my-lab-x``)."""
    return re.sub(r"[-_.]+", "-", name).lower()


def _installed_by(point: EntryPoint, distribution: str | None) -> bool:
    """Whether `point` belongs to `distribution` (None: to any)."""
    if distribution is None:
        return True
    return point.dist is not None and \
        distribution_name(point.dist.name) == distribution_name(distribution)


@cache
def registered(group: str, base: type, distribution: str | None = None) -> dict[str, type]:
    """The classes registered under the entry-point `group`, by entry-point name: each a
    subclass of `base` whose ``name`` is that name (what a config calls it: an
    ``experiment.type``, a device a family needs). A lab's own package adds to a group
    with one line in its pyproject.toml, as python-can finds its bus interfaces.
    `distribution`: only the entry points of that installed distribution (feedbench's own:
    `OWN_DISTRIBUTION`), so feedbench's tests see feedbench's things whatever else is
    installed."""
    found: dict[str, type] = {}
    for point in entry_points(group=group):
        if not _installed_by(point, distribution):
            continue
        cls = point.load()
        if not (isinstance(cls, type) and issubclass(cls, base)) or cls.name != point.name:
            raise TypeError(f"entry point {point.name} = {point.value}: not a {base.__name__} "
                            "subclass of that name")
        found[point.name] = cls
    return found
