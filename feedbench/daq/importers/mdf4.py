"""ASAM MDF (MDF4, also MDF3) files as written by CANape, INCA, dSPACE, Vector and asammdf,
read by asammdf: every numeric channel with the time of its channel group's master."""

from __future__ import annotations

import warnings
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, ClassVar, Collection

import numpy as np

from feedbench.config import ConfigError
from feedbench.daq.importers import ForeignChannel, ForeignFile, library_quiet


class Mdf4:
    """MDF files (.mf4, .mdf, .dat): channel names as the file spells them; a name that
    occurs in several channel groups is `name@<group index>` for each."""

    name: ClassVar[str] = "mdf4"
    suffixes: ClassVar[tuple[str, ...]] = (".mf4", ".mdf")

    @classmethod
    def read(cls, path: Path, names: Collection[str] | None = None) -> ForeignFile:
        """Every numeric 1-D channel of every group (of `names` only, when given), values
        with the file's conversion applied (physical), time from the group's master (s)."""
        from asammdf import MDF

        problem = ""
        with library_quiet("asammdf") as heard, warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                mdf = MDF(path)
                try:
                    return _read(path, mdf, names)
                finally:
                    mdf.close()
            except ConfigError:
                raise
            except Exception as exc:  # asammdf raises many kinds for a foreign or damaged file
                heard.failed = True
                text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
                problem = f"{type(exc).__name__}{': ' + text if text else ''}"
        raise ConfigError(f"{path}: not a readable MDF file ({problem})")


def _read(path: Path, mdf: Any, names: Collection[str] | None) -> ForeignFile:
    occurrences: dict[str, list[tuple[int, int]]] = {}
    for group_index, group in enumerate(mdf.groups):
        master = mdf.masters_db.get(group_index)
        for index, channel in enumerate(group.channels):
            if index != master:
                occurrences.setdefault(channel.name, []).append((group_index, index))
    channels: dict[str, ForeignChannel] = {}
    skipped: dict[str, str] = {}
    listing = []
    header = mdf.header
    origin = _utc(getattr(header, "start_time", None))  # the masters' time 0
    for name, places in occurrences.items():
        for group_index, index in places:
            key = name if len(places) == 1 else f"{name}@{group_index}"
            listing.append(key)
            if names is not None and key not in names:
                continue
            signal = mdf.get(name, group=group_index, index=index, raw=False)
            samples = np.asarray(signal.samples)
            if samples.ndim != 1 or samples.dtype.kind not in "biuf":
                skipped[key] = f"{samples.dtype} samples of shape {samples.shape[1:] or '()'}"
                continue
            channels[key] = ForeignChannel(key, np.asarray(signal.timestamps, dtype=np.float64),
                                           samples.astype(np.float64), str(signal.unit or ""),
                                           origin=origin)
    metadata = {"version": str(mdf.version),
                "start_time": str(getattr(header, "start_time", "")),
                "comment": str(getattr(header, "comment", "") or "")[:2000]}
    return ForeignFile(path, Mdf4.name, channels, metadata, skipped, tuple(listing),
                       origin, "MDF header start time" if origin else "")


def _utc(moment: Any) -> datetime | None:
    """An MDF header's start time in UTC (one without zone: UTC, as MDF4 stores it)."""
    if not isinstance(moment, datetime):
        return None
    if moment.tzinfo is None:
        return moment.replace(tzinfo=timezone.utc)
    return moment.astimezone(timezone.utc)
