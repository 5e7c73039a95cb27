"""The live stream: what a live plot reads while a run acquires, without ever slowing it.

`LiveStream` is a runner observer. The cycle loop hands it blocks of rows, and the cycle
devices' high-rate streams (the serial DAQ's forces and accelerations, `on_stream`) as they
reach the recorder; it copies each into a bounded ring buffer of its own (one column-major
row per channel) and counts them — nothing else, so the producer never waits for a reader
and never allocates. A reader (the live window, on its own timer) asks for a `frame` of a
source (the rows, or a stream by name): the last `span_s` seconds, reduced by min/max
decimation to a few thousand points per channel so a one-sample spike stays visible. The
reader copies before it reduces and drops any bucket the producer overwrote meanwhile, so a
slow reader skips frames, never corrupts them, and the recorder keeps every sample.

`engine.replay` feeds a recording, streams included, through the same observer calls
(``feedbench live RUN``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any, Mapping, Protocol, Sequence

import numpy as np

from feedbench.daq.recorder import StreamSpec

ROWS = ""
"""Source name of the per-cycle rows (streams are named by their recording name, e.g. daq)."""

SLACK = 0.25
"""Extra ring capacity beyond the longest span, so a reader's copy is rarely overwritten."""

UNIT_SUFFIXES = {"_rpm_s": "rpm/s", "_rpm": "rpm", "_mm_min": "mm/min", "_Hz": "Hz", "_hz": "Hz", "_mm": "mm", "_N": "N",
                 "_s": "s"}
"""Info keys carry their engineering unit as a suffix (config convention): feed_mm_min → mm/min."""


class PlanView(Protocol):
    """What the live stream reads of the plan a run executes (`engine.plan.Plan`)."""

    experiment: str
    segments: Sequence[Any]
    n_cycles: int
    cycle_s: float


class SegmentView(Protocol):
    """What it reads of a step of the plan (`engine.plan.Segment`)."""

    label: str
    kind: str
    info: Mapping[str, Any]


class RingBuffer:
    """The latest rows of a stream: one writer thread, any number of lock-free readers.

    Values are stored column-major (channels × capacity) so a reader reduces each channel
    over contiguous memory; `channels` names the rows. `written` counts every row ever written; row `i` lives at
    position ``i % capacity`` until row ``i + capacity`` overwrites it.
    """

    def __init__(self, capacity: int, channels: Sequence[str]) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.capacity = capacity
        self.channels = tuple(channels)
        self.values = np.zeros((len(self.channels), capacity))
        self.cycles = np.zeros(capacity, dtype=np.int64)
        self.written = 0

    def write(self, cycles: np.ndarray, rows: np.ndarray) -> None:
        """Append `rows` (n × channels) with their bus cycles (n,); the oldest rows drop out."""
        n = len(cycles)
        if n > self.capacity:
            cycles, rows, skipped = cycles[-self.capacity:], rows[-self.capacity:], n - self.capacity
        else:
            skipped = 0
        start = (self.written + skipped) % self.capacity
        first = min(len(cycles), self.capacity - start)
        self.values[:, start:start + first] = rows[:first].T
        self.cycles[start:start + first] = cycles[:first]
        rest = len(cycles) - first
        if rest:
            self.values[:, :rest] = rows[first:].T
            self.cycles[:rest] = cycles[first:]
        self.written += n

    def copy_rows(self, start: int, stop: int, channels: Sequence[int]) -> tuple[np.ndarray, np.ndarray, int]:
        """Copy absolute rows [start, stop) of `channels`; returns (cycles, values, first).

        `first` is the first row that is certainly intact: rows the writer may have
        overwritten while they were copied are cut off (the returned arrays start there).
        """
        n = stop - start
        values = np.empty((len(channels), n))
        cycles = np.empty(n, dtype=np.int64)
        for begin, end, offset in self._runs(start, stop):
            cycles[offset:offset + end - begin] = self.cycles[begin:end]
            for row, channel in enumerate(channels):
                values[row, offset:offset + end - begin] = self.values[channel, begin:end]
        first = max(start, self.written - self.capacity)
        return cycles[first - start:], values[:, first - start:], first

    def _runs(self, start: int, stop: int) -> list[tuple[int, int, int]]:
        """Contiguous ring slices (begin, end, offset in the copy) that hold rows [start, stop)."""
        runs, offset = [], 0
        while start < stop:
            begin = start % self.capacity
            end = min(begin + stop - start, self.capacity)
            runs.append((begin, end, offset))
            offset += end - begin
            start += end - begin
        return runs


def bucket_size(n_samples: int, n_buckets: int) -> int:
    """Samples per min/max bucket so that `n_samples` fit in at most `n_buckets` buckets."""
    return max(1, math.ceil(n_samples / max(n_buckets, 1)))


def minmax_buckets(values: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Minimum and maximum of `values` (channels × n) per bucket of `k` samples, NaN (a
    channel not read that cycle, e.g. a load cell read every 5th) left out: NaN only for a
    bucket without a reading. As fast as min/max (`np.fmin`).

    Returns (low, high), each channels × ⌈n/k⌉; the last bucket may be shorter.
    """
    n = values.shape[1]
    full = n // k * k
    shaped = values[:, :full].reshape(len(values), -1, k)
    low, high = np.fmin.reduce(shaped, axis=2), np.fmax.reduce(shaped, axis=2)
    if full < n:
        low = np.hstack([low, np.fmin.reduce(values[:, full:], axis=1, keepdims=True)])
        high = np.hstack([high, np.fmax.reduce(values[:, full:], axis=1, keepdims=True)])
    return low, high


def interleave(t: np.ndarray, low: np.ndarray, high: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bucket start times and (low, high) → drawable points: each bucket's min then max,
    both at its start time, so the envelope keeps every extreme."""
    values = np.empty((len(low), 2 * low.shape[1]))
    values[:, 0::2], values[:, 1::2] = low, high
    return np.repeat(t, 2), values


def minmax_decimate(t: np.ndarray, values: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Min/max decimation of `values` (channels × n, times `t`) in buckets of `k` samples.

    A one-sample spike survives any k. k ≤ 1 returns the samples unchanged; otherwise
    (t, values) have length 2·⌈n/k⌉.
    """
    if k <= 1 or values.shape[1] == 0:
        return t, values
    return interleave(t[::k], *minmax_buckets(values, k))


def info_text(info: dict[str, Any]) -> str:
    """A segment's info for people: ``{"feed_mm_min": 500}`` → ``feed 500 mm/min``."""
    parts = []
    for key, value in info.items():
        name, unit = key, ""
        for suffix, symbol in UNIT_SUFFIXES.items():
            if key.endswith(suffix):
                name, unit = key[: -len(suffix)], " " + symbol
                break
        if isinstance(value, bool):
            shown = "yes" if value else "no"
        else:
            shown = f"{value:g}" if isinstance(value, (int, float)) else str(value)
        parts.append(f"{name.replace('_', ' ')} {shown}{unit}")
    return ", ".join(parts)


@dataclass(frozen=True)
class Timebase:
    """Time of a ring's ticks (bus cycles, or a stream's sample counter), s of bench time:
    t = offset + (tick − origin) · period."""

    origin: int
    period: float
    offset: float = 0.0

    def times(self, ticks: np.ndarray) -> np.ndarray:
        """Bench times (s) of `ticks`."""
        return self.offset + (ticks - self.origin) * self.period


@dataclass(frozen=True)
class LiveState:
    """Where a run stands: experiment step, progress in cycles, status.

    `status` is ``idle`` before the run, ``running``, then the runner's final status
    (``complete`` / ``aborted``) with its `reason`.
    """

    experiment: str = ""
    status: str = "idle"
    reason: str = ""
    segment_index: int = -1
    n_segments: int = 0
    label: str = ""
    kind: str = ""
    info: dict[str, Any] = field(default_factory=dict)
    cycles_done: int = 0
    cycles_total: int = 0
    cycle_s: float = 1e-3
    wall_elapsed_s: float = 0.0

    @property
    def fraction(self) -> float:
        """Share of the plan's cycles done, 0 … 1."""
        return min(self.cycles_done / self.cycles_total, 1.0) if self.cycles_total else 0.0

    @property
    def bench_time_left_s(self) -> float:
        """Bench time (s) the plan still needs."""
        return max(self.cycles_total - self.cycles_done, 0) * self.cycle_s

    @property
    def wall_time_left_s(self) -> float:
        """Wall time (s) left at the rate seen so far (NaN before any progress)."""
        if self.cycles_done <= 0:
            return math.nan
        return self.wall_elapsed_s / self.cycles_done * max(self.cycles_total - self.cycles_done, 0)

    @property
    def step_text(self) -> str:
        """``step 3/52: measure positive 500 mm/min (feed 500 mm/min)``, empty before a step."""
        if self.segment_index < 0:
            return ""
        detail = info_text(self.info)
        return (f"step {self.segment_index + 1}/{self.n_segments}: {self.label}"
                + (f" ({detail})" if detail else ""))


@dataclass(frozen=True)
class LiveFrame:
    """A decimated copy of the last seconds of every requested channel.

    `t` (s of bench time since the first sample) and each `channels[name]` have the same
    length; `samples_per_point` is the bucket size k (1: raw samples, else min/max pairs);
    `n_received` counts every sample the stream has seen; `t_end` is the time of the
    newest sample (s), where a scrolling display puts "now".
    """

    t: np.ndarray
    channels: dict[str, np.ndarray]
    samples_per_point: int
    n_received: int
    t_end: float


class LiveStream:
    """Runner observer feeding bounded ring buffers; readers take decimated frames.

    `span_max_s` is the longest window a reader may ask for (s of bench time); each ring
    (the rows, and every high-rate stream the devices declare) holds that span plus `SLACK`.
    Memory: channels × span_max_s × rate × 8 bytes per ring (9 DAQ channels at 10 kHz,
    60 s: 54 MB).
    """

    def __init__(self, span_max_s: float = 60.0) -> None:
        self.span_max_s = span_max_s
        self._ring = RingBuffer(1, ())
        self._streams: dict[str, RingBuffer] = {}
        self._specs: dict[str, StreamSpec] = {}
        self._stream_timebases: dict[str, Timebase] = {}
        self._units: dict[str, str] = {}
        self._state = LiveState()
        self._first_cycle: int | None = None
        self._plan_start: int | None = None
        self._last_cycle = -1
        self._wall_start = time.monotonic()

    # observer side: called from the cycle loop, never blocks
    def on_start(self, plan: PlanView, channels: Sequence[str]) -> None:
        """Size the ring for the plan's cycle time and reset the state."""
        self._ring = RingBuffer(self._capacity(1.0 / plan.cycle_s), channels)
        self._streams, self._specs, self._stream_timebases, self._units = {}, {}, {}, {}
        self._first_cycle = self._plan_start = None
        self._last_cycle = -1
        self._wall_start = time.monotonic()
        self._state = LiveState(experiment=plan.experiment, status="running",
                                n_segments=len(plan.segments), cycles_total=plan.n_cycles,
                                cycle_s=plan.cycle_s)

    def on_layout(self, units: Mapping[str, str], streams: Mapping[str, StreamSpec]) -> None:
        """Learn the units of the rows and open a ring per high-rate stream."""
        self._units = dict(units)
        for name, spec in streams.items():
            self._units.update({c: spec.units.get(c, "") for c in spec.channels})
            self._specs[name] = spec
            self._streams[name] = RingBuffer(self._capacity(spec.rate_hz), spec.channels)

    def on_segment(self, index: int, segment: SegmentView, cycle: int) -> None:
        """Remember the step; progress counts from the first step's cycle."""
        if self._plan_start is None:
            self._plan_start = cycle
        self._state = replace(self._state, segment_index=index, label=segment.label,
                              kind=segment.kind, info=dict(segment.info))

    def on_block(self, cycles: np.ndarray, block: np.ndarray) -> None:
        """Copy the block into the ring (O(block), no allocation, no lock)."""
        if self._first_cycle is None and len(cycles):
            self._first_cycle = int(cycles[0])
        self._ring.write(cycles, block)
        if len(cycles):
            self._last_cycle = int(cycles[-1])

    def on_stream(self, name: str, cycles: np.ndarray, sequence: np.ndarray,
                  samples: np.ndarray) -> None:
        """Copy a device's block of stream `name` into its ring (ticks: the sample counter)."""
        ring = self._streams.get(name)
        if ring is None or not len(sequence):
            return
        if self._first_cycle is None:
            self._first_cycle = int(cycles[0])
        if name not in self._stream_timebases:
            self._stream_timebases[name] = Timebase(
                int(sequence[0]), 1.0 / self._specs[name].rate_hz,
                (int(cycles[0]) - self._first_cycle) * self._state.cycle_s)
        ring.write(sequence, samples)

    def on_stop(self, status: str, reason: str) -> None:
        """Record the final status."""
        self._state = replace(self._state, status=status, reason=reason)

    def _capacity(self, rate_hz: float) -> int:
        return math.ceil(self.span_max_s * rate_hz * (1.0 + SLACK))

    # reader side
    @property
    def channels(self) -> tuple[str, ...]:
        """Channel names of the rows, in the runner's column order."""
        return self._ring.channels

    @property
    def n_received(self) -> int:
        """Rows received since `on_start`."""
        return self._ring.written

    @property
    def cycle_s(self) -> float:
        """Bus cycle of the current run (s)."""
        return self._state.cycle_s

    @property
    def units(self) -> dict[str, str]:
        """SI unit of every row and stream channel (from `on_layout`; empty without it)."""
        return dict(self._units)

    @property
    def sources(self) -> dict[str, RingBuffer]:
        """The rings by source: `ROWS` and each high-rate stream's name."""
        return {ROWS: self._ring, **self._streams}

    def timebase(self, source: str = ROWS) -> Timebase:
        """How a source's ticks map to bench time (t = 0: the run's first cycle)."""
        if source == ROWS:
            return Timebase(self.first_cycle, self.cycle_s)
        spec = self._specs[source]
        return self._stream_timebases.get(source, Timebase(0, 1.0 / spec.rate_hz))

    def rate_hz(self, source: str = ROWS) -> float:
        """Sample rate of a source (Hz)."""
        return 1.0 / self.cycle_s if source == ROWS else self._specs[source].rate_hz

    def state(self) -> LiveState:
        """A snapshot of the run's state and progress."""
        state = self._state
        done = 0 if self._plan_start is None else self._last_cycle + 1 - self._plan_start
        return replace(state, cycles_done=min(max(done, 0), state.cycles_total),
                       wall_elapsed_s=time.monotonic() - self._wall_start)

    @property
    def ring(self) -> RingBuffer:
        """The current run's ring of rows (a new one at every `on_start`)."""
        return self._ring

    @property
    def first_cycle(self) -> int:
        """Bus cycle of the run's first sample (t = 0 of frames)."""
        return self._first_cycle or 0

    def frame(self, span_s: float, n_buckets: int = 2000,
              channels: Sequence[str] | None = None, source: str = ROWS) -> LiveFrame:
        """The last `span_s` seconds of `channels` (default all) of a source, min/max-
        decimated, once.

        A reader that asks every frame keeps a `Decimator` instead: it reduces each sample
        only once.
        """
        return Decimator(self, span_s, n_buckets, channels, source).frame()


class Decimator:
    """A reader's min/max view of the last `span_s` seconds of a stream, kept up to date.

    Each call to `frame` reduces only the samples that arrived since the last call into
    buckets of k samples (aligned to absolute sample numbers, so the envelope does not
    flicker while it scrolls) and keeps up to `n_buckets` of them; the newest, incomplete
    bucket is reduced afresh each time. A reader that fell more than the ring's capacity
    behind loses the overwritten buckets and starts again from what is intact.
    """

    def __init__(self, stream: LiveStream, span_s: float, n_buckets: int = 2000,
                 channels: Sequence[str] | None = None, source: str = ROWS) -> None:
        self.stream = stream
        self.span_s = min(span_s, stream.span_max_s)
        self.n_buckets = n_buckets
        self.names = tuple(channels) if channels is not None else None
        self.source = source
        self._ring: RingBuffer | None = None

    def _reset(self, ring: RingBuffer) -> None:
        """Size the bucket store for the current run's cycle time and channels."""
        self._ring = ring
        self._names = self.names if self.names is not None else ring.channels
        self._columns = [ring.channels.index(name) for name in self._names]
        span = max(int(round(self.span_s * self.stream.rate_hz(self.source))), 1)
        self.k = bucket_size(span, self.n_buckets)
        self._slots = -(-span // self.k)
        self._t = np.zeros(self._slots)
        self._low = np.zeros((len(self._columns), self._slots))
        self._high = np.zeros((len(self._columns), self._slots))
        self._done = 0
        self._valid_from = 0

    def frame(self) -> LiveFrame:
        """The current decimated window (`samples_per_point` = k)."""
        ring = self.stream.sources[self.source]
        if ring is not self._ring:
            self._reset(ring)
        stop = ring.written
        complete = stop // self.k
        self._reduce_new(ring, max(self._done, complete - self._slots), complete)
        slots = np.arange(max(self._valid_from, complete - self._slots), complete) % self._slots
        t, low, high = self._t[slots], self._low[:, slots], self._high[:, slots]
        if stop > complete * self.k:
            tail = self._reduce(ring, complete * self.k, stop)
            t, low, high = (np.concatenate([t, tail[0]]), np.hstack([low, tail[1]]),
                            np.hstack([high, tail[2]]))
        if self.k > 1:
            t, low = interleave(t, low, high)
        return LiveFrame(t, dict(zip(self._names, low)), self.k, stop, self._newest_time(ring))

    def _newest_time(self, ring: RingBuffer) -> float:
        """Time (s) of the newest sample in the ring (0 before any)."""
        if not ring.written:
            return 0.0
        tick = ring.cycles[(ring.written - 1) % ring.capacity]
        return float(self.stream.timebase(self.source).times(tick))

    def _reduce_new(self, ring: RingBuffer, begin: int, end: int) -> None:
        """Reduce complete buckets [begin, end) into the store."""
        if end <= begin:
            return
        t, low, high = self._reduce(ring, begin * self.k, end * self.k)
        start = end - len(t)
        if start > begin:
            self._valid_from = start
        slots = np.arange(start, end) % self._slots
        self._t[slots], self._low[:, slots], self._high[:, slots] = t, low, high
        self._done = end

    def _reduce(self, ring: RingBuffer, start: int, stop: int) -> tuple[np.ndarray, ...]:
        """Bucket start times, minima and maxima of rows [start, stop) (start on a bucket
        boundary); buckets the writer overwrote while they were copied are left out."""
        cycles, values, first = ring.copy_rows(start, stop, self._columns)
        cut = -(-(first - start) // self.k) * self.k - (first - start)
        cycles, values = cycles[cut:], values[:, cut:]
        t = self.stream.timebase(self.source).times(cycles[:: self.k])
        if self.k == 1:
            return t, values, values
        return (t, *minmax_buckets(values, self.k))
