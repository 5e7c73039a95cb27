"""The analysis of a run while it acquires: the family's own `analyze`, chunk by chunk.

`RecordingBuilder` is a runner observer that keeps the rows, segment starts and high-rate
stream blocks it is handed (from the cycle loop: a copy and a list append per block,
nothing else) and assembles them on request into the same `daq.recording.Recording` the
HDF5 file reads back as. `LiveAnalysis` runs the family's `Experiment.analyze` on that
recording, cut at the end of the last completed segment, each time a segment of the
family's `live_kinds` has completed, and gives the family's `live_view` of the result.
So the live window and `feedbench analyze` run one analysis: replaying a recording through
a `LiveAnalysis` gives the offline result bit for bit (tests/test_live_offline.py).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from feedbench.analysis.checks import verdict_line
from feedbench.config import ConfigError
from feedbench.daq.recording import Event, Recording, Stream, missing_cycles
from feedbench.engine.family import Experiment, judged_analysis
from feedbench.engine.plan import Plan, Segment
from feedbench.engine.runner import segment_text
from feedbench.views.panels import ResultView

END_OF_PLAN = segment_text(None, "disable")
"""The segment event the runner writes after the plan (the disable sequence)."""


@dataclass(frozen=True)
class _PlannedSegment:
    start: int
    stop: int
    kind: str
    text: str


class RecordingBuilder:
    """A recording built up from the runner's observer calls (see module docstring)."""

    def __init__(self, name: str = "live") -> None:
        self.name = name
        self.experiment = ""
        self.cycle_s = 1e-3
        self.channels: tuple[str, ...] = ()
        self.units: dict[str, str] = {}
        self.metadata: dict[str, Any] = {}
        self.config: dict[str, Any] = {}
        self.status, self.reason = "running", ""
        self.planned: list[_PlannedSegment] = []
        self.completed = 0
        """Plan segments whose every row has arrived."""
        self._rows: list[tuple[np.ndarray, np.ndarray]] = []
        self._specs: dict[str, Any] = {}
        self._streams: dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}

    def on_metadata(self, metadata: Mapping[str, Any]) -> None:
        """The run's metadata as recorded (cycle time, config, drive gains), before the start."""
        self.metadata = dict(metadata)
        self.config = dict(metadata.get("config", {}))

    def on_start(self, plan: Plan, channels: Sequence[str]) -> None:
        self.experiment, self.cycle_s, self.channels = plan.experiment, plan.cycle_s, tuple(channels)
        self.metadata = {"experiment": plan.experiment, "cycle_s": plan.cycle_s, **self.metadata}
        self.config = self.config or {"experiment": {"type": plan.experiment, **plan.params}}

    def on_layout(self, units: Mapping[str, str], streams: Mapping[str, Any]) -> None:
        self.units = dict(units)
        self._specs = dict(streams)
        self._streams = {name: [] for name in streams}

    def on_segment(self, index: int, segment: Segment, cycle: int) -> None:
        self.planned.append(_PlannedSegment(cycle, cycle + segment.n_cycles, segment.kind,
                                            segment_text(segment)))

    def on_block(self, cycles: np.ndarray, block: np.ndarray) -> None:
        self._rows.append((cycles.copy(), block.copy()))
        self._complete_up_to(int(cycles[-1]) + 1)

    def on_stream(self, name: str, cycles: np.ndarray, sequence: np.ndarray,
                  samples: np.ndarray) -> None:
        self._streams[name].append((cycles.copy(), sequence.copy(), samples.copy()))

    def on_stop(self, status: str, reason: str) -> None:
        self.status, self.reason = status, reason

    def _complete_up_to(self, end_cycle: int) -> None:
        """Count the plan segments that end by `end_cycle`; `on_segment_complete` each."""
        while self.completed < len(self.planned) and self.planned[self.completed].stop <= end_cycle:
            self.completed += 1
            self.on_segment_complete(self.planned[self.completed - 1].kind)

    def on_segment_complete(self, kind: str) -> None:
        """A plan segment of `kind` has all its rows (cycle loop thread)."""

    def recording(self) -> Recording:
        """The completed segments as a `Recording`: rows, events and stream samples up to the
        end of the last completed segment (any thread)."""
        completed = self.completed
        end = self.planned[completed - 1].stop if completed else 0
        cycle, rows = _joined(list(self._rows), len(self.channels))
        keep = cycle < end
        events = [Event(s.start, "segment", s.text) for s in self.planned[:completed]]
        events.append(Event(end, "segment", END_OF_PLAN))
        return Recording(
            path=Path(self.name), cycle=cycle[keep],
            channels={name: rows[keep, i] for i, name in enumerate(self.channels)},
            units=self.units, status=self.status, reason=self.reason, started_at="",
            stopped_at="", experiment=self.experiment, config=self.config, versions={},
            events=events, n_gaps=missing_cycles(cycle[keep]), metadata=self.metadata,
            streams={name: self._stream(name, end) for name in self._specs})

    def _stream(self, name: str, end: int) -> Stream:
        spec = self._specs[name]
        parts = list(self._streams[name])
        cycle = np.concatenate([p[0] for p in parts]) if parts else np.zeros(0, np.int64)
        sequence = np.concatenate([p[1] for p in parts]) if parts else np.zeros(0, np.int64)
        samples = (np.concatenate([p[2] for p in parts]) if parts
                   else np.zeros((0, len(spec.channels))))
        keep = cycle < end
        return Stream(spec.rate_hz, cycle[keep], sequence[keep],
                      {c: samples[keep, i] for i, c in enumerate(spec.channels)},
                      dict(spec.units))


def _joined(parts: list[tuple[np.ndarray, np.ndarray]], width: int) -> tuple[np.ndarray, np.ndarray]:
    if not parts:
        return np.zeros(0, np.int64), np.zeros((0, width))
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


class LiveAnalysis(RecordingBuilder):
    """The family's analysis of the segments completed so far, and its live view.

    `version` counts completed segments of the family's `live_kinds`; `view()` (reader
    thread) recomputes only when it changed. While the completed windows do not allow a
    result yet (the family raises `ConfigError` or `ValueError`), the view says what it
    waits for.
    """

    def __init__(self, family: type[Experiment], name: str = "live") -> None:
        super().__init__(name)
        self.family = family
        self.version = 0
        self._cached: tuple[int, ResultView] | None = None

    def on_segment_complete(self, kind: str) -> None:
        if kind in self.family.live_kinds:
            self.version += 1

    def result(self, final: bool = False) -> dict[str, Any]:
        """The family's judged result of what has completed (`final`: as the offline
        analysis, `family.judged_analysis`)."""
        return judged_analysis(self.family, self.recording(), final=final)

    def view(self) -> ResultView:
        """The live panels of the current result, rebuilt when `version` changed."""
        version = self.version
        if self._cached is None or self._cached[0] != version:
            self._cached = (version, self._build())
        return self._cached[1]

    def _build(self) -> ResultView:
        title = self.family.title or self.family.name
        if not self.version:
            return ResultView(title, (), "waiting for the first completed step")
        try:
            result = self.result()
            view = self.family.live_view(result)
        except (ConfigError, ValueError) as exc:
            return ResultView(title, (), f"waiting: {exc}")
        if result["valid"]:
            return view
        return replace(view, summary=f"{verdict_line(result)} | {view.summary}")
