"""Per-experiment results that build up while a run acquires (no Qt here).

Each result is a runner observer: from the cycle loop it only sorts incoming rows into the
plan's steps and accumulates (sums, copies of excited stretches) — O(block), nothing to
fit. The live window calls `view()` on its own timer; the fit or FRF is computed there, once
per completed step, and handed over as plain arrays (`ResultView`), so the window draws any
experiment the same way.

Results of experiments whose signals come through the serial DAQ also watch the devices'
high-rate streams (`on_layout`, `on_stream`, see `experiments.runner.StreamObserver`): the
cycle loop copies the samples they need and hands completed records to the reader through a
bounded queue (`RecordQueue`).

The registry `LIVE_RESULTS` maps an experiment name to its result class; a new experiment
family adds one class with ``@live_result("name")``. Here, the drive-side families:
``chirp`` (servo mobility FRF of the sweeps so far, H1 with coherence).
"""

from __future__ import annotations

from bisect import bisect_right
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np

from feedbench.analysis.frf import estimate_frf
from feedbench.experiments.chirp import mobility_extrema
from feedbench.experiments.plan import Plan, Segment
from feedbench.views.panels import *  # noqa TRANSITION

FRF_NPERSEG = 2048
"""Welch segment length of the live FRF, as `experiments.chirp.analyze_recording` uses."""

MOBILITY_BAND_HZ = (20.0, 150.0)
"""Band searched for the servo mobility's anti-resonance and resonance (as the analysis)."""

MAX_QUEUED_VALUES = 4_000_000
"""Values (32 MB) completed records may hold while the reader has not taken them; beyond,
the oldest record is dropped (a window that falls behind skips results, never samples)."""


class StepTracker:
    """Which plan step each bus cycle belongs to.

    Blocks reach observers every 50 cycles and may straddle a step boundary; the runner
    announces each step with the cycle it starts at, so rows are sorted by cycle.
    """

    def __init__(self) -> None:
        self.starts: list[int] = []
        self.steps: list[tuple[int, Segment]] = []

    def begin(self, index: int, segment: Segment, cycle: int) -> None:
        """A step starts at `cycle`."""
        self.starts.append(cycle)
        self.steps.append((index, segment))

    def split(self, cycles: np.ndarray) -> Iterator[tuple[int, Segment, slice]]:
        """(step index, step, row slice) of every step present in `cycles` (ascending)."""
        if not len(cycles) or not self.starts:
            return
        first = bisect_right(self.starts, int(cycles[0])) - 1
        for k in range(max(first, 0), len(self.starts)):
            lo = int(np.searchsorted(cycles, self.starts[k]))
            hi = (int(np.searchsorted(cycles, self.starts[k + 1]))
                  if k + 1 < len(self.starts) else len(cycles))
            if hi > lo:
                index, segment = self.steps[k]
                yield index, segment, slice(lo, hi)
            if hi >= len(cycles):
                return


class RecordQueue:
    """Completed records from the cycle loop to the reader, bounded by `max_values`.

    One producer (`put`, never blocks: beyond the bound it drops the oldest record and
    counts it in `dropped`) and one reader (`take`). Both use only `deque.append` /
    `popleft`, which are atomic, and counters each side writes alone.
    """

    def __init__(self, max_values: int = MAX_QUEUED_VALUES) -> None:
        self.max_values = max_values
        self.dropped = 0
        self._records: deque[tuple[Any, np.ndarray]] = deque()
        self._put_values = 0
        self._dropped_values = 0
        self._taken_values = 0

    def put(self, key: Any, record: np.ndarray) -> None:
        """Queue a record (producer)."""
        self._records.append((key, record))
        self._put_values += record.size
        while (self._put_values - self._dropped_values - self._taken_values > self.max_values
               and len(self._records) > 1):
            try:
                _, old = self._records.popleft()
            except IndexError:  # the reader took it meanwhile
                break
            self._dropped_values += old.size
            self.dropped += 1

    def take(self) -> list[tuple[Any, np.ndarray]]:
        """Every queued record, oldest first (reader)."""
        out = []
        while True:
            try:
                out.append(self._records.popleft())
            except IndexError:
                break
            self._taken_values += out[-1][1].size
        return out


class LiveResult:
    """Base of every building-up result: observer plumbing, per-step rows, cached view.

    Subclasses implement `collect` (cycle loop thread: cheap accumulation, bump `version`
    when something new is complete) and `build` (reader thread: fits, FRFs); results that
    use a device's high-rate stream also `collect_stream`. `params` are the plan's (in a
    replay: the recorded experiment config, defaults not filled in: use `param`).
    """

    title = ""
    SCHEMA: Mapping[str, Any] = {}
    """The family's config schema, for the defaults of `param`."""

    def __init__(self) -> None:
        self.version = 0
        self.cycle_s = 1e-3
        self.params: dict[str, Any] = {}
        self.segments: list[Segment] = []
        self.columns: dict[str, int] = {}
        self.streams: dict[str, Any] = {}
        self.origin_cycle: int | None = None
        self.steps = StepTracker()
        self._parts: dict[int, list[np.ndarray]] = {}
        self._cached: tuple[int, ResultView] | None = None

    def on_start(self, plan: Plan, channels: Sequence[str]) -> None:
        """Learn the cycle time, the plan and the column of each channel."""
        self.cycle_s = plan.cycle_s
        self.params = dict(plan.params)
        self.segments = list(plan.segments)
        self.columns = {name: i for i, name in enumerate(channels)}

    def on_layout(self, units: Mapping[str, str], streams: Mapping[str, Any]) -> None:
        """Learn the devices' high-rate streams (name → `StreamSpec`)."""
        self.streams = dict(streams)

    def on_segment(self, index: int, segment: Segment, cycle: int) -> None:
        """Remember where the step starts."""
        self.steps.begin(index, segment, cycle)

    def on_block(self, cycles: np.ndarray, block: np.ndarray) -> None:
        """Hand each step's rows of the block to `collect`."""
        self._origin(cycles)
        for index, segment, rows in self.steps.split(cycles):
            self.collect(index, segment, block[rows])

    def on_stream(self, name: str, cycles: np.ndarray, sequence: np.ndarray,
                  samples: np.ndarray) -> None:
        """Hand a device's block of stream `name` to `collect_stream`."""
        self._origin(cycles)
        self.collect_stream(name, cycles, samples)

    def on_stop(self, status: str, reason: str) -> None:
        """Nothing to finish: only completed steps count."""

    def _origin(self, cycles: np.ndarray) -> None:
        if self.origin_cycle is None and len(cycles):
            self.origin_cycle = int(cycles[0])

    def time_of(self, cycles: np.ndarray | int) -> np.ndarray | float:
        """Bench time (s) of bus cycles, from the run's first cycle."""
        return (np.asarray(cycles) - (self.origin_cycle or 0)) * self.cycle_s

    def param(self, key: str) -> Any:
        """A plan parameter, or its schema default."""
        return self.params.get(key, self.SCHEMA[key].default if key in self.SCHEMA else None)

    def collect_stream(self, name: str, cycles: np.ndarray, samples: np.ndarray) -> None:
        """Accumulate a stream block (cycle loop); results that need no stream ignore it."""

    def column(self, rows: np.ndarray, name: str) -> np.ndarray:
        """One channel of a block of rows."""
        return rows[:, self.columns[name]]

    def gather(self, index: int, segment: Segment, rows: np.ndarray,
               names: Sequence[str]) -> np.ndarray | None:
        """Collect channels `names` of a step's rows; the whole step (n × len(names)) once
        its last row arrived, else None."""
        parts = self._parts.setdefault(index, [])
        parts.append(rows[:, [self.columns[name] for name in names]].copy())
        if sum(len(p) for p in parts) < segment.n_cycles:
            return None
        del self._parts[index]
        return np.concatenate(parts)

    def collect(self, index: int, segment: Segment, rows: np.ndarray) -> None:
        """Accumulate the rows of one step (called from the cycle loop)."""
        raise NotImplementedError

    def build(self) -> ResultView:
        """The result from what is complete so far (called from the reader)."""
        raise NotImplementedError

    def view(self) -> ResultView:
        """The current result; rebuilt only when `version` changed."""
        version = self.version
        if self._cached is None or self._cached[0] != version:
            self._cached = (version, self.build())
        return self._cached[1]


LIVE_RESULTS: dict[str, type[LiveResult]] = {}


def live_result(name: str) -> Callable[[type[LiveResult]], type[LiveResult]]:
    """Class decorator: register the building-up result of experiment `name`."""

    def register(cls: type[LiveResult]) -> type[LiveResult]:
        LIVE_RESULTS[name] = cls
        return cls

    return register


def live_result_for(experiment: str) -> LiveResult | None:
    """A fresh result for `experiment`, or None if the family has none registered."""
    cls = LIVE_RESULTS.get(experiment)
    return cls() if cls else None


@live_result("chirp")
class ChirpMobility(LiveResult):
    """Servo mobility motor force → motor velocity (H1, Welch) of the sweeps completed so
    far, with its coherence; anti-resonance f_t and resonance f_r (Eqs. 4.13, 4.14)."""

    title = "servo mobility of the sweeps so far"

    def __init__(self) -> None:
        super().__init__()
        self.sweeps: list[np.ndarray] = []

    def collect(self, index: int, segment: Segment, rows: np.ndarray) -> None:
        if segment.kind != "excite":
            return
        sweep = self.gather(index, segment, rows, ("force", "velocity"))
        if sweep is not None:
            self.sweeps.append(sweep - sweep.mean(axis=0))
            self.version += 1

    def build(self) -> ResultView:
        sweeps = list(self.sweeps)
        if not sweeps:
            return ResultView(self.title, _empty_frf_panels(), "waiting for the first sweep")
        force, velocity = np.concatenate(sweeps).T
        est = estimate_frf(force, velocity, 1.0 / self.cycle_s, nperseg=welch_length(len(force)))
        inside = (est.f >= MOBILITY_BAND_HZ[0]) & (est.f <= MOBILITY_BAND_HZ[1])
        panels = _frf_panels(est.f[inside], est.H1[inside], est.coherence[inside])
        summary = (f"{len(sweeps)} sweep{'s' if len(sweeps) > 1 else ''} "
                   f"({est.n_averages} Welch averages); {_extrema_text(est.f, est.H1)}"
                   f"min coherence {est.coherence[inside].min():.3f}")
        return ResultView(self.title, panels, summary)


def welch_length(n_samples: int) -> int:
    """Welch segment length: the analysis's, or a power of two short enough for at least
    three averages while little is recorded (one segment would make coherence 1 trivially)."""
    return int(min(FRF_NPERSEG, 2 ** np.floor(np.log2(max(n_samples // 2, 8)))))


def _extrema_text(f: np.ndarray, H: np.ndarray) -> str:
    """``f_t … Hz, f_r … Hz, `` or nothing while the resolution cannot separate them yet."""
    try:
        f_t, f_r = mobility_extrema(f, H, MOBILITY_BAND_HZ)
    except ValueError:
        return ""
    return f"f_t {f_t:.1f} Hz, f_r {f_r:.1f} Hz, "


def _frf_panels(f: np.ndarray, H: np.ndarray, coherence: np.ndarray) -> tuple[Panel, Panel]:
    """|H| in (m/s)/N and the coherence over frequency (Hz)."""
    return (
        Panel("|H1| motor velocity / motor force", "frequency (Hz)", "|H| ((m/s)/N)",
              (Curve("H1", f, np.abs(H)),), log_y=True),
        Panel("coherence", "frequency (Hz)", "γ²", (Curve("coherence", f, coherence),),
              y_range=(0.0, 1.05)),
    )


def _empty_frf_panels() -> tuple[Panel, Panel]:
    empty = np.zeros(0)
    return _frf_panels(empty, empty.astype(complex), empty)

