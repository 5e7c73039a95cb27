"""NI TDMS files (LabVIEW, SignalExpress, DAQmx logging) read by npTDMS: every numeric
channel, DAQmx raw data scaled, times from the waveform properties."""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

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
    def read(cls, path: Path) -> ForeignFile:
        """Every numeric channel of every group (physical values: DAQmx scaling applied)."""
        from nptdms import TdmsFile

        with library_quiet("nptdms") as heard:
            try:
                tdms = TdmsFile.read(path)
            except Exception as exc:  # npTDMS raises many kinds for a foreign or damaged file
                text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
                raise ConfigError(f"{path}: not a readable TDMS file ({type(exc).__name__}"
                                  f"{': ' + text if text else ''})") from None
            found = _read(path, tdms)
        if not found.channels:
            said = f" (npTDMS: {heard[0]})" if heard else ""
            raise ConfigError(f"{path}: no numeric channel in the file{said}")
        return found


def _read(path: Path, tdms: Any) -> ForeignFile:
    found: list[tuple[str, str, ForeignChannel | str]] = []
    for group in tdms.groups():
        by_name = {channel.name: channel for channel in group.channels()}
        clock = next((by_name[n] for n in TIME_NAMES if n in by_name), None)
        for channel in group.channels():
            found.append((group.name, channel.name, _channel(channel, clock)))
    counts: dict[str, int] = {}
    for _, name, _ in found:
        counts[name] = counts.get(name, 0) + 1
    channels: dict[str, ForeignChannel] = {}
    skipped: dict[str, str] = {}
    for group, name, read in found:
        for key in [f"{group}/{name}"] + ([name] if counts[name] == 1 else []):
            if isinstance(read, str):
                skipped[key] = read
            else:
                channels[key] = ForeignChannel(key, read.time, read.values, read.unit,
                                               read.increment)
    metadata = {key: _plain(value) for key, value in tdms.properties.items()}
    return ForeignFile(path, Tdms.name, channels, metadata, skipped)


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
                              values.astype(np.float64), unit, increment=step)
    if clock is None or clock is channel:
        return "no waveform timing (wf_increment) and no time channel in its group"
    time = np.asarray(clock[:], dtype=np.float64)
    if len(time) != len(values):
        return f"{len(values)} samples beside the group's {len(time)} times"
    return ForeignChannel(channel.name, time, values.astype(np.float64), unit)


def _plain(value: Any) -> Any:
    """A TDMS property as JSON-able text or number."""
    if isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, np.generic) and value.dtype.kind in "biuf":
        return value.item()
    return str(value)
