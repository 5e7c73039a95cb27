"""NI TDMS files (LabVIEW, SignalExpress, DAQmx logging) read by npTDMS: every numeric
channel, DAQmx raw data scaled, times from the waveform properties."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any, ClassVar, Collection

import numpy as np

from feedbench.config import ConfigError
from feedbench.daq.importers import ForeignChannel, ForeignFile, library_quiet

TIME_NAMES = ("time", "Time", "TIME", "t", "Zeit")
"""A group's time channel (s), used for its channels that carry no waveform timing."""


class Tdms:
    """TDMS files (.tdms): a channel is `group/channel`, or its name alone when no other
    group has a channel of that name. Times: `wf_start_offset` + i · `wf_increment` (s), or
    the group's time channel (`TIME_NAMES`) for channels without waveform timing."""

    name: ClassVar[str] = "tdms"
    suffixes: ClassVar[tuple[str, ...]] = (".tdms",)

    @classmethod
    def read(cls, path: Path, names: Collection[str] | None = None) -> ForeignFile:
        """Every numeric channel of every group (of `names` only, when given: the file is
        opened, not read whole), physical values (DAQmx scaling applied)."""
        from nptdms import TdmsFile

        with library_quiet("nptdms") as heard:
            try:
                with TdmsFile.open(path) as tdms:
                    found = _read(path, tdms, names)
            except Exception as exc:  # npTDMS raises many kinds for a foreign or damaged file
                text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
                raise ConfigError(f"{path}: not a readable TDMS file ({type(exc).__name__}"
                                  f"{': ' + text if text else ''})") from None
        if not found.listing:
            said = f" (npTDMS: {heard[0]})" if heard else ""
            raise ConfigError(f"{path}: no channel in the file{said}")
        return found


def _read(path: Path, tdms: Any, names: Collection[str] | None) -> ForeignFile:
    counts: dict[str, int] = {}
    for group in tdms.groups():
        for channel in group.channels():
            counts[channel.name] = counts.get(channel.name, 0) + 1
    channels: dict[str, ForeignChannel] = {}
    skipped: dict[str, str] = {}
    listing = []
    for group in tdms.groups():
        by_name = {channel.name: channel for channel in group.channels()}
        clock = next((by_name[n] for n in TIME_NAMES if n in by_name), None)
        for name, channel in by_name.items():
            keys = [f"{group.name}/{name}"] + ([name] if counts[name] == 1 else [])
            listing += keys
            if names is not None and not set(keys) & set(names):
                continue
            read = _channel(channel, clock)
            for key in keys:
                if isinstance(read, str):
                    skipped[key] = read
                else:
                    channels[key] = ForeignChannel(key, read.time, read.values, read.unit,
                                                   read.increment, read.origin)
    metadata = {key: _plain(value) for key, value in tdms.properties.items()}
    times = [(key, _utc(value)) for key, value in tdms.properties.items()
             if _utc(value) is not None]
    origin, source = (times[0][1], f"TDMS file property {times[0][0]}") if times else (None, "")
    return ForeignFile(path, Tdms.name, channels, metadata, skipped, tuple(listing), origin,
                       source)


def _channel(channel: Any, clock: Any) -> ForeignChannel | str:
    """The channel with its times (s), or why it cannot be offered."""
    values = np.asarray(channel[:])
    if values.ndim != 1 or values.dtype.kind not in "biuf":
        return f"{values.dtype} samples"
    properties = channel.properties
    unit = str(properties.get("unit_string", "") or "")
    if "wf_increment" in properties:
        step = float(properties["wf_increment"])
        if not step > 0.0:
            return f"wf_increment {step:g} s is not > 0"
        start = float(properties.get("wf_start_offset", 0.0))
        return ForeignChannel(channel.name, start + np.arange(len(values)) * step,
                              values.astype(np.float64), unit, increment=step,
                              origin=_utc(properties.get("wf_start_time")))
    if clock is None or clock is channel:
        return "no waveform timing (wf_increment) and no time channel in its group"
    time = np.asarray(clock[:], dtype=np.float64)
    if len(time) != len(values):
        return f"{len(values)} samples beside the group's {len(time)} times"
    return ForeignChannel(channel.name, time, values.astype(np.float64), unit)


def _utc(value: Any) -> datetime | None:
    """A TDMS time (npTDMS: numpy datetime64, UTC) as a UTC datetime; None for anything
    else, and for LabVIEW's zero time (1904-01-01: no time set)."""
    if isinstance(value, datetime):
        moment = value if value.tzinfo else value.replace(tzinfo=timezone.utc)
    elif isinstance(value, np.datetime64) and not np.isnat(value):
        microseconds = int(value.astype("datetime64[us]").astype(np.int64))
        moment = datetime(1970, 1, 1, tzinfo=timezone.utc) + timedelta(
            microseconds=microseconds)
    else:
        return None
    return moment if moment.year > 1904 else None


def _plain(value: Any) -> Any:
    """A TDMS property as JSON-able text or number."""
    if isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, np.generic) and value.dtype.kind in "biuf":
        return value.item()
    return str(value)
