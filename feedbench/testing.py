"""The testing kit: what feedbench's own tests use, for a lab's package to test its family
and device kind the same way (docs/ARCHITECTURE.md, "Extending feedbench: the testing kit").

- The live = offline check: `assert_live_equals_offline(path)` replays a recording through
  its family's live analysis (`live_replay`, as a run feeds the live window) and asserts the
  result after the last segment equals `feedbench analyze`'s, value for value (`same`: NaN
  equals NaN), and that the live view draws.
- A synthetic recording: `synthetic_recording(path, experiment, steps)` writes what the runner
  would, one `Step` (a plan segment with its per-cycle rows, `cycle_rows`, and optionally its
  DAQ samples) after the other, from signals whose truth the test knows.
- The simulated bench: the pytest fixture `simulated_bench` (a `SimulatedBench` on its own
  virtual CAN channel, recording to the test's ``tmp_path``) runs or opens a run config in
  this process, against the simulated peers, through the real drivers.

A lab's ``conftest.py`` gets the fixture with ``from feedbench.testing import
simulated_bench``. The per-cycle device base (failure rule, every-n-cycles reading) is
`devices.PerCycleDevice`.
"""

from __future__ import annotations

import copy
import json
import math
import os
import uuid
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping, NamedTuple, Sequence

import numpy as np
import pytest

from feedbench.bench import Bench, RunConfig, analyze_file, parse_run_config, run_config
from feedbench.daq.recorder import Recorder, StreamSpec
from feedbench.daq.recording import open_recording
from feedbench.devices.cycle_io import DaqDevice
from feedbench.engine.family import families
from feedbench.engine.incremental import LiveAnalysis
from feedbench.engine.replay import replay
from feedbench.engine.runner import CHANNELS, UNITS
from feedbench.protocols.serial_frames import CHANNEL_INDEX
from feedbench.protocols.serial_frames import CHANNELS as DAQ_CHANNELS

# -- live = offline --------------------------------------------------------------------------


def same(a: Any, b: Any) -> bool:
    """Equal JSON-like values (dicts, lists, tuples, arrays, numbers), NaN equal to NaN."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(a, b, equal_nan=True)
    return a == b


def live_replay(path: str | Path) -> LiveAnalysis:
    """The recording at `path` fed to its family's live analysis as a run would feed it."""
    recording = open_recording(path)
    live = LiveAnalysis(families()[recording.experiment])
    assert replay(recording, [live], speed=0.0) == recording.status
    return live


def assert_live_equals_offline(path: str | Path) -> LiveAnalysis:
    """Assert that the live result after the last segment is `feedbench analyze`'s of the
    file at `path` and that the live view draws; returns the live analysis."""
    live = live_replay(path)
    offline = analyze_file(path)
    offline.pop("run")
    assert same(live.result(final=True), offline)
    view = live.view()
    assert not view.summary.startswith("waiting"), view.summary
    return live


# -- synthetic recordings --------------------------------------------------------------------

CYCLE_S = 1e-3
"""The bus cycle of a synthetic recording by default (s)."""

LIMITS = {"position_mm": [-250.0, 250.0], "velocity_mm_min": 3000.0, "force_N": 1500.0}
"""The ``[limits]`` a synthetic recording's config holds by default."""

GAP_CYCLES = 5
"""Cycles a synthetic recording drops at its `gap_after` cycle."""


class Step(NamedTuple):
    """One plan segment of a synthetic recording: its event's `label`, `kind` and `info`
    (`engine.plan.Segment`), its per-cycle `rows` (n × `runner.CHANNELS`, `cycle_rows`)
    and, with a DAQ stream, its samples (n·samples-per-cycle × DAQ channels)."""

    label: str
    kind: str
    info: Mapping[str, Any]
    rows: np.ndarray
    daq: np.ndarray | None = None


def cycle_rows(n: int, **columns: Any) -> np.ndarray:
    """`n` rows of the runner's per-cycle channels (`runner.CHANNELS`, SI), zero but for
    `columns` (channel name → value or n values)."""
    rows = np.zeros((n, len(CHANNELS)))
    for name, values in columns.items():
        rows[:, CHANNELS.index(name)] = values
    return rows


def _daq_spec(channels: Sequence[str], rate_hz: float) -> StreamSpec:
    """The DAQ stream of `channels` (names of `protocols.serial_frames.CHANNELS`)."""
    units = {c: DAQ_CHANNELS[CHANNEL_INDEX[c]].unit for c in channels}
    return StreamSpec(tuple(channels), units, rate_hz)


def _cycles(first: int, n: int, gap_after: int | None) -> np.ndarray:
    """The bus cycles of `n` rows from `first`, `GAP_CYCLES` dropped at `gap_after`."""
    cycles = first + np.arange(n)
    if gap_after is not None and first <= gap_after < cycles[-1]:
        cycles[cycles >= gap_after] += GAP_CYCLES
    return cycles


def synthetic_recording(path: str | Path, experiment: Mapping[str, Any],
                        steps: Iterable[Sequence], *, cycle_s: float = CYCLE_S,
                        limits: Mapping[str, Any] = LIMITS,
                        metadata: Mapping[str, Any] | None = None,
                        daq_channels: Sequence[str] = (), daq_rate_hz: float = 10_000.0,
                        status: str = "complete", reason: str = "",
                        gap_after: int | None = None) -> Path:
    """Write the recording a run of `experiment` (its ``[experiment]`` table, ``type`` the
    family) would leave at `path`: each of `steps` (`Step`s or tuples of its fields) one
    segment event and its rows from bus cycle 1 on, a cycle of `cycle_s` s; with
    `daq_channels`, a DAQ stream at `daq_rate_hz` (samples/s, a whole number per cycle).
    `status`/`reason` other than complete: the run aborted; `gap_after`: `GAP_CYCLES`
    cycles lost there. `metadata` adds to (or replaces) what the runner records."""
    path = Path(path)
    meta = {"experiment": experiment["type"], "cycle_s": cycle_s, "run_id": path.stem,
            "config": {"limits": dict(limits), "experiment": dict(experiment)},
            **(metadata or {})}
    per_cycle = round(daq_rate_hz * cycle_s)
    streams = {DaqDevice.name: _daq_spec(daq_channels, daq_rate_hz)} if daq_channels else None
    with Recorder(path, CHANNELS, UNITS, meta, streams=streams) as recorder:
        cycle, sample = 1, 0
        for step in (Step(*fields) for fields in steps):
            recorder.event(cycle, "segment",
                           json.dumps({"label": step.label, "kind": step.kind, **step.info}))
            cycles = _cycles(cycle, len(step.rows), gap_after)
            recorder.append_block(cycles, step.rows)
            if step.daq is not None:
                recorder.append_stream(DaqDevice.name, np.repeat(cycles, per_cycle),
                                       sample + np.arange(len(step.daq)), step.daq)
                sample += len(step.daq)
            cycle = int(cycles[-1]) + 1
        if status != "complete":
            recorder.close(status, reason)
    return path


# -- the simulated bench ---------------------------------------------------------------------


def virtual_channel(prefix: str = "fb-test") -> str:
    """A python-can ``virtual`` channel name no other bench in this machine uses."""
    return f"{prefix}-{os.getpid()}-{uuid.uuid4().hex[:12]}"


@dataclass
class SimulatedBench:
    """feedbench's simulated bench in this process on its own virtual CAN `channel`,
    recording to `directory`: `run` a run config (an `Example.config()`, a dict of its
    tables) or `open` its bench."""

    directory: Path
    channel: str = field(default_factory=virtual_channel)

    def config(self, raw: Mapping[str, Any]) -> RunConfig:
        """`raw` (not changed) on this bench: simulated, this channel and directory; checked."""
        raw = copy.deepcopy(dict(raw))
        raw["bench"].update(simulated=True, output_dir=str(self.directory),
                            channel=self.channel)
        return parse_run_config(raw)

    def run(self, raw: Mapping[str, Any], observers: Sequence = ()) -> dict[str, Any]:
        """Run `raw` here (`observers` see the data stream); the run record: id, file,
        status, reason."""
        return run_config(self.config(raw), observers, progress=False)

    @contextmanager
    def open(self, raw: Mapping[str, Any]) -> Iterator[Bench]:
        """The open bench of `raw` here (drives enabled by a run only), closed on exit."""
        config = self.config(raw)
        with Bench(config.bench, config.plan, config.experiment.devices()) as bench:
            yield bench


@pytest.fixture
def simulated_bench(tmp_path: Path) -> SimulatedBench:
    """A `SimulatedBench` recording to the test's `tmp_path`."""
    return SimulatedBench(tmp_path)
