"""A recording replayed through the runner's observer calls (``feedbench live RUN``).

`replay` hands a recording's steps, rows and high-rate streams to observers (the live
stream, the live results) as the `Runner` handed them during the run, paced at a chosen
speed; `recorded_plan` rebuilds the plan they see from the recording's segment events.
"""

from __future__ import annotations

import time
from typing import Sequence

import numpy as np

from feedbench.daq.recorder import StreamSpec
from feedbench.engine.plan import Plan, Segment, segment_event
from feedbench.engine.runner import BLOCK_CYCLES, Observer, StopRequest


def recorded_plan(recording) -> tuple[Plan, list[int]]:
    """The plan a recording was made from, rebuilt from its segment events.

    Returns the plan (segments carry label, kind, info, commands and their recorded length;
    their setpoints are not needed to replay) and each segment's first cycle. Enable and
    disable steps are the runner's, not the plan's, and are left out as in a live run.
    """
    segments, starts = [], []
    for seg in recording.segments("segment"):
        label, kind, info, commands = segment_event(seg.label)
        if kind in ("enable", "disable"):
            continue
        length = np.broadcast_to(np.float64(0.0), (seg.stop - seg.start,))
        segments.append(Segment(label, kind, length, info=info, commands=commands))
        starts.append(seg.start)
    cycle_s = float(recording.metadata.get("cycle_s", 1e-3))
    plan = Plan(recording.experiment, 0, segments, recording.config.get("experiment", {}), cycle_s)
    return plan, starts


def replay(recording, observers: Sequence[Observer], speed: float = 1.0,
           stop: StopRequest | None = None, block_rows: int = BLOCK_CYCLES) -> str:
    """Feed a recording to `observers` as the runner fed them, paced at `speed` × real time.

    Stream observers (`on_layout`, `on_stream`) also get the units and each recorded stream,
    its samples up to a block's last cycle handed over before the block (the rest at the
    end). `speed` ≤ 0 replays
    as fast as possible; `stop` (a `StopRequest`) ends it early. Returns the status passed
    to `on_stop`: the recording's own, or ``stopped``.
    """
    plan, starts = recorded_plan(recording)
    names = list(recording.channels)
    rows = np.column_stack([recording.channels[name] for name in names]) if names else np.zeros((0, 0))
    cycles = recording.cycle
    for obs in observers:
        if hasattr(obs, "on_metadata"):
            obs.on_metadata({**recording.metadata, "config": recording.config})
        obs.on_start(plan, names)
        if hasattr(obs, "on_layout"):
            obs.on_layout(recording.units, recorded_streams(recording))
    pace = _Pacer(plan.cycle_s / speed if speed > 0 else 0.0)
    boundaries = np.searchsorted(cycles, starts)
    handed = dict.fromkeys(recording.streams, 0)
    next_segment, status = 0, recording.status
    for begin in range(0, len(cycles), block_rows):
        end = min(begin + block_rows, len(cycles))
        while next_segment < len(starts) and boundaries[next_segment] < end:
            for obs in observers:
                obs.on_segment(next_segment, plan.segments[next_segment], starts[next_segment])
            next_segment += 1
        _replay_streams(recording, observers, handed, int(cycles[end - 1]))
        for obs in observers:
            obs.on_block(cycles[begin:end], rows[begin:end])
        if stop is not None and stop.reason is not None:
            status = "stopped"
            break
        pace.wait(end)
    if status != "stopped":  # samples the instrument sent after the last bus cycle
        _replay_streams(recording, observers, handed, np.iinfo(np.int64).max)
    for obs in observers:
        obs.on_stop(status, stop.reason if status == "stopped" else recording.reason)
    return status


def recorded_streams(recording) -> dict[str, StreamSpec]:
    """The high-rate streams of a recording as the devices declared them."""
    return {name: StreamSpec(tuple(stream.channels), stream.units, stream.rate_hz)
            for name, stream in recording.streams.items()}


def _replay_streams(recording, observers: Sequence[Observer], handed: dict[str, int],
                    last_cycle: int) -> None:
    """Hand each stream's samples up to bus cycle `last_cycle` that were not handed yet."""
    watching = [obs for obs in observers if hasattr(obs, "on_stream")]
    for name, stream in recording.streams.items():
        begin = handed[name]
        end = int(np.searchsorted(stream.cycle, last_cycle, side="right"))
        if end > begin and watching:
            samples = np.column_stack([values[begin:end] for values in stream.channels.values()])
            for obs in watching:
                obs.on_stream(name, stream.cycle[begin:end], stream.sequence[begin:end], samples)
        handed[name] = max(end, begin)


class _Pacer:
    """Sleeps so that sample n is handed over n · dt seconds after the start."""

    def __init__(self, dt: float) -> None:
        self.dt = dt
        self.t0 = time.monotonic()

    def wait(self, n_done: int) -> None:
        delay = self.t0 + n_done * self.dt - time.monotonic()
        if delay > 0:
            time.sleep(delay)
