"""Reading the recordings other DAQ systems wrote (ASAM MDF4, NI TDMS, …): one seam.

A format is one module with one `Format` class: the file suffixes it reads and `read(path)`,
which returns every numeric channel of the file as a `ForeignChannel` (sample times in s,
values as the file's physical values, the file's unit text). What a channel *is* (motor
position, force, …), its unit when the file has none, and how channels at different rates
meet on one time base is the mapping's business (`importers.mapping`), never the format's.

The built-in formats are listed in `BUILTIN`; a lab adds one from its own package with an
entry point in the group ``feedbench.importers`` (name = the format's name), as it adds an
experiment family: a third format is one file.
"""

from __future__ import annotations

import gc
import importlib
import logging
import sys
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime
from functools import cache
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import Any, ClassVar, Collection, Iterator, Protocol

import numpy as np

from feedbench.config import ConfigError

ENTRY_POINT_GROUP = "feedbench.importers"
BUILTIN = {"mdf4": "feedbench.daq.importers.mdf4:Mdf4",
           "tdms": "feedbench.daq.importers.tdms:Tdms"}
"""The formats feedbench reads itself: name → ``module:class``."""


@dataclass(frozen=True)
class ForeignChannel:
    """One channel of a foreign file: sample times (s, increasing, float64), physical
    values (float64) and the unit text the file gives ('' if none); `regular` is True when
    the file declares a constant sample period `increment` (s; a TDMS waveform's: times =
    start + i · increment); `origin` the moment (UTC) its time 0 is, where the file says
    (an MDF4 header's start time, a TDMS waveform's wf_start_time)."""

    name: str
    time: np.ndarray
    values: np.ndarray
    unit: str = ""
    increment: float = 0.0
    origin: datetime | None = None

    @property
    def period(self) -> float:
        """Sample period (s): the declared increment, else the mean over the channel to 12
        significant digits (a clock's 1 ms stays 1 ms, not 0.9999999999999998 ms); 0 for
        fewer than two samples."""
        if self.increment:
            return self.increment
        if len(self.time) < 2 or self.time[-1] <= self.time[0]:
            return 0.0
        return float(f"{float(self.time[-1] - self.time[0]) / (len(self.time) - 1):.12g}")

    @property
    def rate_hz(self) -> float:
        """Sample rate (Hz), 1 / `period`; 0 for fewer than two samples."""
        return 1.0 / self.period if self.period else 0.0


@dataclass(frozen=True)
class ForeignFile:
    """What a format read from a file: its channels by name (the name the mapping uses) and
    what the file says about itself (start time, comment, writer…; JSON-able)."""

    path: Path
    format: str
    channels: dict[str, ForeignChannel]
    metadata: dict[str, Any] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    """Channels the format could not offer as numbers, with why (text, arrays, …)."""
    listing: tuple[str, ...] = ()
    """Every channel name of the file, read or not (`Format.read`'s `names`)."""
    origin: datetime | None = None
    """The file's own time (UTC) of time 0 where its channels give none (a TDMS file's
    time property), and what said so (`origin_source`)."""
    origin_source: str = ""

    def channel(self, name: str, field_name: str) -> ForeignChannel:
        """The channel `name`; one missing is a ConfigError naming `field_name`, the file and
        the channels it has."""
        if name in self.channels:
            return self.channels[name]
        if name in self.skipped:
            raise ConfigError(f"{field_name}: channel {name!r} of {self.path.name} is not "
                              f"numeric ({self.skipped[name]})")
        names = sorted(self.listing or self.channels)
        listed = ", ".join(names[:12]) + (f", … ({len(names)} in all)" if len(names) > 12 else "")
        raise ConfigError(f"{field_name}: no channel {name!r} in {self.path.name} "
                          f"(channels: {listed})")


class Format(Protocol):
    """A foreign file format: its name, the suffixes it reads, and its reader."""

    name: ClassVar[str]
    suffixes: ClassVar[tuple[str, ...]]

    @classmethod
    def read(cls, path: Path, names: Collection[str] | None = None) -> ForeignFile:
        """The file's channels (those of `names` only, when given: the others' samples are
        not read, their names listed); a file the library cannot read is a ConfigError
        naming it."""


@cache
def formats() -> dict[str, type[Format]]:
    """The registered formats by name: the built-in ones and the entry points of
    ``feedbench.importers``."""
    found: dict[str, type[Format]] = {}
    targets = dict(BUILTIN)
    for point in importlib_metadata.entry_points(group=ENTRY_POINT_GROUP):
        targets[point.name] = point.value
    for name, target in targets.items():
        module, _, attribute = target.partition(":")
        kind = getattr(importlib.import_module(module), attribute)
        if kind.name != name:
            raise ConfigError(f"{ENTRY_POINT_GROUP}: entry point {name!r} names a format "
                              f"called {kind.name!r}")
        found[name] = kind
    return found


class Heard(list):
    """The log lines a library said inside `library_quiet`; `failed`: the block ended by an
    error, or the reader caught the library's error inside it."""

    failed: bool = False


@contextmanager
def library_quiet(logger: str) -> Iterator[Heard]:
    """Inside the block, the library's log lines (`logger`) are collected in the list given,
    not printed, and what its objects' ``__del__`` raises is dropped (asammdf's half-built
    file object fails in its ``__del__`` after a failed open): an error stays one line. After
    a failure (`Heard.failed`) the garbage is collected before the block ends, so that such
    an object goes while its ``__del__`` is quiet (only then: a full collection of a test
    worker's heap took ≈ 0.1 s, 4 s of the suite)."""
    heard = Heard()
    handler = logging.Handler(logging.WARNING)
    handler.emit = lambda record: heard.append(record.getMessage())  # type: ignore[method-assign]
    names = [logger] + [name for name in logging.root.manager.loggerDict
                        if name.startswith(logger + ".")]
    logs = [logging.getLogger(name) for name in names]
    saved = [(log.handlers, log.propagate) for log in logs]
    previous_hook = sys.unraisablehook

    def unraisable(info: Any) -> None:
        module = getattr(getattr(info, "object", None), "__module__", "") or ""
        if not module.startswith(logger):
            previous_hook(info)

    for log in logs:
        log.handlers, log.propagate = [handler], False
    sys.unraisablehook = unraisable
    try:
        yield heard
    except BaseException:
        heard.failed = True
        raise
    finally:
        if heard.failed:
            gc.collect()  # a half-built object of the library goes now, its __del__ quiet
        for log, (handlers, propagate) in zip(logs, saved):
            log.handlers, log.propagate = handlers, propagate
        sys.unraisablehook = previous_hook


def suffixes() -> dict[str, str]:
    """Each file suffix a registered format reads (lower case, with the dot) → its name."""
    return {suffix: name for name, kind in formats().items() for suffix in kind.suffixes}


def is_foreign(path: str | Path) -> bool:
    """True when `path`'s suffix is one a registered format reads."""
    return Path(path).suffix.lower() in suffixes()


def read_foreign(path: str | Path, format_name: str = "",
                 names: Collection[str] | None = None) -> ForeignFile:
    """Read `path` with the format its suffix (or `format_name`) names, the channels of
    `names` only if given; a missing file, an unknown suffix or format is a ConfigError."""
    path = Path(path)
    known = suffixes()
    name = format_name or known.get(path.suffix.lower(), "")
    if not name:
        raise ConfigError(f"{path}: no format reads {path.suffix or 'a file without suffix'!r}"
                          f" (known: {', '.join(sorted(known))})")
    if name not in formats():
        raise ConfigError(f"mapping.format: unknown format {name!r} "
                          f"(known: {', '.join(sorted(formats()))})")
    if not path.is_file():
        raise ConfigError(f"{path}: no such file")
    return formats()[name].read(path, names)
