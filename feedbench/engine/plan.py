"""Experiment plans: per-cycle setpoints computed before anything moves.

A plan is a list of segments. Each segment carries, for every bus cycle, the target
position relative to where the axis stands when the run starts (m), and optional force
and velocity offsets (N, m/s) where excitation is injected (0x60B2 / 0x60B1). Because the
whole trajectory exists before the run, the runner checks every limit on it first.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from feedbench.config import ConfigError


@dataclass(frozen=True)
class Segment:
    """A labelled stretch of cycles; `kind` tells analysis what it is for.

    kinds: ``move`` (ramps), ``settle`` (wait for steady state), ``measure`` (the window
    analysis averages), ``excite`` (excitation on). `info` labels the step for analysis
    (feed, frequency, test name); `commands` is what the bench's devices set in the cycle
    the segment starts (spindle speed and ramp, the axis controller's settings), recorded
    with the segment's event. `target_velocity` (m/s) is the CSV setpoint 0x60FF;
    `excitation` (N) the command to the plan's tool-tip exciter (`Plan.exciter`: shaker or
    actuator force; for the hammer, the level of a hit fired in that cycle, 0 for none).
    """

    label: str
    kind: str
    target_position: np.ndarray
    force_offset: np.ndarray | None = None
    velocity_offset: np.ndarray | None = None
    info: dict[str, float] = field(default_factory=dict)
    target_velocity: np.ndarray | None = None
    excitation: np.ndarray | None = None
    commands: dict[str, Any] = field(default_factory=dict)

    @property
    def n_cycles(self) -> int:
        """Number of bus cycles in the segment."""
        return len(self.target_position)


@dataclass(frozen=True)
class Plan:
    """What the runner executes: segments in order, in one CiA 402 mode of operation.

    `exciter`: the tool-tip exciter the segments' `excitation` drives (``shaker``,
    ``actuator``, ``hammer``), None if the plan has none.
    """

    experiment: str
    mode: int
    segments: list[Segment]
    params: dict[str, Any]
    cycle_s: float
    exciter: str | None = None

    @property
    def n_cycles(self) -> int:
        """Total number of bus cycles."""
        return sum(s.n_cycles for s in self.segments)

    @property
    def duration_s(self) -> float:
        """Planned duration in seconds of bench time."""
        return self.n_cycles * self.cycle_s

    def commands_at(self, keys: tuple[str, ...]) -> dict[int, dict[str, Any]]:
        """Plan cycle index → the commands among `keys` of the segment that starts there
        (segments with none of them left out): what one device acts on."""
        found, first = {}, 0
        for segment in self.segments:
            picked = {k: segment.commands[k] for k in keys if k in segment.commands}
            if picked:
                found[first] = picked
            first += segment.n_cycles
        return found

    def concatenated(self, name: str) -> np.ndarray:
        """One per-cycle array over the whole plan (zeros where a segment has none)."""
        parts = []
        for s in self.segments:
            value = getattr(s, name)
            parts.append(np.zeros(s.n_cycles) if value is None else value)
        return np.concatenate(parts) if parts else np.zeros(0)


@dataclass(frozen=True)
class Window:
    """Sample indices [start, stop) of one recorded segment, with the segment's info."""

    start: int
    stop: int
    label: str
    kind: str
    info: dict[str, Any]


def segment_event(text: str) -> tuple[str, str, dict[str, Any], dict[str, Any]]:
    """Label, kind, info and commands of a segment event's JSON text (`runner.segment_text`:
    the info's keys beside ``label`` and ``kind``, the commands under ``commands``).
    Recordings made before segments had commands carry them in the info."""
    info = json.loads(text)
    label, kind = info.pop("label"), info.pop("kind")
    return label, kind, info, info.pop("commands", {})


def recorded_windows(recording, kind: str, at_least: int = 0) -> list[Window]:
    """The recorded segments of one `kind` (``measure``, ``excite``…) as sample windows.

    `recording` is a `feedbench.daq.recording.Recording`; segment events carry JSON text
    (`segment_event`). Fewer than `at_least` of them raise `ConfigError` naming the file
    (what the analysis needs).
    """
    windows = []
    for seg in recording.segments("segment"):
        label, recorded_kind, info, _ = segment_event(seg.label)
        if recorded_kind != kind:
            continue
        rows = np.flatnonzero(recording.mask(seg))
        if len(rows):
            windows.append(Window(int(rows[0]), int(rows[-1]) + 1, label, kind, info))
    if len(windows) < at_least:
        raise ConfigError(f"{recording.path}: {len(windows)} {kind} segment(s) recorded, the "
                          f"analysis needs at least {at_least}")
    return windows
