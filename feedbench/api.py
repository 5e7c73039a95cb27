"""The bench as a library: experiment scripts in Python (issue 17).

``feedbench.open_bench(config)`` opens the bench a config describes, simulated or real (its
``[bench]`` table decides, as for ``feedbench run``), and returns a `BenchSession`::

    import feedbench

    with feedbench.open_bench("bench.toml") as bench:
        bench.drive.enable()
        bench.drive.move_to(10.0, feed_mm_min=1000.0)
        sweep = bench.run("friction_sweep", feeds_mm_min=[50, 100, 200, 400, 800])
        print(sweep.result["positive"]["identified"]["F_c"])

Everything that moves is a plan run by the CLI's `engine.runner.Runner` (through
`bench.Bench.run`): a move, a jog and an ad-hoc `BenchSession.record` as much as an
experiment, so the limits are checked on the whole trajectory before the drive is enabled,
every sample is recorded to HDF5 and catalogued, and a limit trip, a drive fault, a bus
timeout or Ctrl-C ramps the axis down, disables the drive and closes the recording as
``aborted``. The drive's power stage is enabled by each plan and disabled at its end: between
plans, and after the ``with`` block, it is disabled.

Units are the config's and the CLI's: positions in mm, feeds in mm/min, forces in N, gains
as in ``[bench.gains]``; results (`Run.result`) are the families' own, in SI.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from feedbench.bench import (
    GAINS_SCHEMA, RUN_SCHEMA, Bench, RunConfig, analyze_file, bench_table, gains_si,
    parse_run_config,
)
from feedbench.config import ConfigError, Field, interval, read_toml, validate_table
from feedbench.daq.catalog import Catalog, open_catalog
from feedbench.daq.recording import Recording, open_recording
from feedbench.engine.family import Experiment, families
from feedbench.engine.limits import LimitError, Limits
from feedbench.engine.plan import Plan, Segment
from feedbench.engine.runner import StopRequest
from feedbench.experiments.signals import constant_feed_move, move_to
from feedbench.protocols.cia402 import CSP
from feedbench.report import write_report
from feedbench.units import M_PER_MIN_PER_MM, MM_PER_MIN

Progress = Callable[[float, str], None]
"""A progress callback: called with the fraction of the plan done (0 … 1) and the label of
the step it is in (e.g. ``"sweep 2"``), from the cycle loop about every 50 bus cycles."""

GAIN_LIMITS_SCHEMA = {
    "K_p_Ns_m": Field(list, None, "range of the velocity-loop gain set_gains accepts (N·s/m)",
                      interval),
    "T_i_ms": Field(list, None, "range of the velocity-loop integral time (ms)", interval),
    "K_v_m_min_mm": Field(list, None, "range of the position-loop gain ((m/min)/mm)", interval),
}
"""``[limits.gains]``: the ranges `Drive.set_gains` accepts; a gain without one is refused."""

SETTLE_S = 0.1
"""Standstill recorded at the end of a move or a jog (s): the axis comes to rest in the plan."""


class RunError(RuntimeError):
    """A run ended ``aborted`` (limit trip, drive fault, bus timeout); `run` is its record.

    The drive was ramped down and disabled and the recording keeps every sample."""

    def __init__(self, run: Run) -> None:
        super().__init__(f"{run.id}: aborted: {run.reason}")
        self.run = run


class RunStopped(KeyboardInterrupt):
    """A stop request (Ctrl-C, SIGTERM, `BenchSession.stop`) arrived during a run: the axis
    was ramped down, the drive disabled and the recording closed ``aborted`` (``complete``
    if the plan had just finished); `run` is its record. A `KeyboardInterrupt`, so an
    unhandled one ends the script as Ctrl-C does."""

    def __init__(self, run: Run) -> None:
        super().__init__(f"{run.id}: {run.reason}")
        self.run = run


@dataclass(frozen=True)
class Reading:
    """The drive's actual values of one bus cycle: motor position (mm), velocity (mm/min),
    motor force (N)."""

    position_mm: float
    velocity_mm_min: float
    force_N: float


@dataclass(frozen=True)
class Run:
    """One recorded plan: catalog `id`, HDF5 `path`, `status` (``complete`` or ``aborted``)
    and its `reason`, the family's `result` (its ``analyze`` output, SI units; empty for an
    ad-hoc sequence and for an aborted run) and the `recording` (channels in SI)."""

    id: str
    path: Path
    status: str
    reason: str
    result: dict[str, Any]
    recording: Recording

    @property
    def complete(self) -> bool:
        """True when every segment of the plan ran."""
        return self.status == "complete"


@dataclass(frozen=True)
class DeviceView:
    """A device the open bench serves every bus cycle besides the drive (spindle inverter,
    streaming DAQ, load cell, …), read-only: its `kind` (class name), the `channels` it adds
    to each recorded row, their `units` (SI) and its high-rate `streams` (names)."""

    kind: str
    channels: tuple[str, ...]
    units: dict[str, str]
    streams: tuple[str, ...]


class ProgressCallback:
    """A runner observer that hands (fraction done, step label) to a `Progress` callable."""

    def __init__(self, callback: Progress) -> None:
        self.callback = callback
        self._total = 1
        self._done = 0
        self._label = ""

    def on_start(self, plan: Plan, channels: Sequence[str]) -> None:
        self._total = max(plan.n_cycles, 1)
        self._done = 0
        self.callback(0.0, "enable")

    def on_segment(self, index: int, segment: Segment, cycle: int) -> None:
        self._label = segment.label
        self.callback(self._fraction(), self._label)

    def on_block(self, cycles: np.ndarray, block: np.ndarray) -> None:
        self._done += len(cycles)
        self.callback(self._fraction(), self._label)

    def on_stop(self, status: str, reason: str) -> None:
        self.callback(1.0 if status == "complete" else self._fraction(), status)

    def _fraction(self) -> float:
        return min(self._done / self._total, 1.0)


class AdHocSequence(Experiment):
    """An ad-hoc plan of a script (a move, a jog, `BenchSession.record`): recorded and
    catalogued as experiment ``sequence`` with its `label`; it has no analysis."""

    name = "sequence"
    schema = {"type": Field(str, "sequence", "experiment family"),
              "label": Field(str, "sequence", "what the script calls the sequence")}

    def __init__(self, label: str, segments: Iterable[Segment], cycle_s: float) -> None:
        super().__init__({"type": self.name, "label": label}, cycle_s)
        self.segments = list(segments)

    def plan(self) -> Plan:
        return Plan(self.name, CSP, self.segments, self.settings, self.cycle_s)


class Drive:
    """The axis's drive (the master of a rack-and-pinion axis) as a script sees it.

    `enable` allows motion (moves, jogs, records, experiments), `disable` refuses it; the
    power stage itself is enabled by each plan and disabled at its end (`state`).
    """

    def __init__(self, session: BenchSession) -> None:
        self._session = session
        self._enabled = False

    @property
    def enabled(self) -> bool:
        """True between `enable` and `disable`: the session may run plans."""
        return self._enabled

    def enable(self) -> None:
        """Allow the session to move the axis."""
        self._enabled = True

    def disable(self) -> None:
        """Refuse every further plan until `enable` (the drive is already disabled between
        plans)."""
        self._enabled = False

    @property
    def state(self) -> str:
        """The CiA 402 state of the latest statusword (``switch on disabled`` between plans)."""
        return self._session._first_drive().state

    def read(self) -> Reading:
        """Run one bus cycle and return the measured position (mm), velocity (mm/min) and
        motor force (N)."""
        self._session._current_bench().clock.tick()
        actual = self._session._first_drive().actual
        return Reading(actual.position * 1e3, actual.velocity / MM_PER_MIN, actual.force)

    def move_to(self, position_mm: float, feed_mm_min: float, accel_m_s2: float = 1.0,
                progress: Progress | None = None) -> Run:
        """Move to the absolute motor position `position_mm` (mm) at up to `feed_mm_min`
        (mm/min), accelerating at `accel_m_s2` (m/s²), then rest `SETTLE_S`; one recorded
        plan, its limits checked before anything moves."""
        if feed_mm_min <= 0:
            raise ConfigError(f"move_to.feed_mm_min: must be > 0 (got {feed_mm_min:g})")
        cycle_s = self._session.cycle_s
        distance = (position_mm - self.read().position_mm) * 1e-3
        path = move_to(0.0, distance, feed_mm_min * MM_PER_MIN, accel_m_s2, cycle_s)
        rest = np.full(int(round(SETTLE_S / cycle_s)), distance)
        return self._session.record([Segment(f"move to {position_mm:g} mm", "move", path),
                                     Segment("rest", "settle", rest)],
                                    label=f"move to {position_mm:g} mm", progress=progress)

    def jog(self, feed_mm_min: float, seconds: float, accel_m_s2: float = 1.0,
            progress: Progress | None = None) -> Run:
        """Move at `feed_mm_min` (mm/min, the sign is the direction) for `seconds` (s) of
        cruise between ramps of `accel_m_s2` (m/s²), then rest `SETTLE_S`; the cruise is
        recorded as a ``measure`` segment."""
        cycle_s = self._session.cycle_s
        path, a, b = constant_feed_move(0.0, feed_mm_min * MM_PER_MIN, accel_m_s2, seconds,
                                        cycle_s)
        rest = np.full(int(round(SETTLE_S / cycle_s)), path[-1] if len(path) else 0.0)
        info = {"feed_mm_min": float(feed_mm_min)}
        return self._session.record([Segment("accelerate", "move", path[:a], info=info),
                                     Segment(f"jog {feed_mm_min:g} mm/min", "measure",
                                             path[a:b], info=info),
                                     Segment("stop", "move", path[b:], info=info),
                                     Segment("rest", "settle", rest)],
                                    label=f"jog {feed_mm_min:g} mm/min", progress=progress)

    @property
    def gains(self) -> dict[str, float]:
        """The cascade gains the drive runs with (by SDO): ``K_p_Ns_m`` (N·s/m), ``T_i_ms``
        (ms), ``K_v_m_min_mm`` ((m/min)/mm)."""
        g = self._session._first_drive().read_gains()
        return {"K_p_Ns_m": g.K_p, "T_i_ms": g.T_i * 1e3, "K_v_m_min_mm": g.K_v / M_PER_MIN_PER_MM}

    def set_gains(self, K_p_Ns_m: float | None = None, T_i_ms: float | None = None,
                  K_v_m_min_mm: float | None = None) -> None:
        """Write cascade gains to every drive of the axis by SDO (None keeps one): velocity
        gain `K_p_Ns_m` (N·s/m), integral time `T_i_ms` (ms), position gain `K_v_m_min_mm`
        ((m/min)/mm). Each must lie in its ``[limits.gains]`` range; one outside, or without
        a declared range, is a `ConfigError` and nothing is written."""
        given = {key: value for key, value in (("K_p_Ns_m", K_p_Ns_m), ("T_i_ms", T_i_ms),
                                               ("K_v_m_min_mm", K_v_m_min_mm))
                 if value is not None}
        check_gains(given, self._session.gain_limits)
        self._session._set_gains(given)


def check_gains(given: Mapping[str, float], gain_limits: Mapping[str, Any],
                source: str = "set_gains") -> None:
    """Gains in CNC units (``K_p_Ns_m``, ``T_i_ms``, ``K_v_m_min_mm``) against their
    ``[limits.gains]`` ranges; one outside, or without a declared range, is a `ConfigError`
    naming it (`source`: what asked for them)."""
    validate_table(given, GAINS_SCHEMA, source)
    for key, value in given.items():
        allowed = gain_limits[key]
        if allowed is None:
            raise ConfigError(f"limits.gains.{key}: no range declared, {source} refuses "
                              f"{key} = {value:g}")
        low, high = allowed
        if not low <= value <= high:
            raise ConfigError(f"{source}.{key}: {value:g} outside limits.gains.{key} "
                              f"[{low:g}, {high:g}]")


class BenchSession:
    """An open bench (`open_bench`): its `drive`, the per-cycle `devices`, and the plans a
    script runs: `run` (an experiment family), `record` (ad-hoc segments), `report`.

    A context manager: leaving the ``with`` block (normally, by an exception or Ctrl-C)
    closes the bench; a plan that is running when an exception or Ctrl-C arrives is ramped
    down by its runner, the drive disabled and the recording closed ``aborted``.
    The bench is opened for the devices an experiment needs (`Experiment.devices`); an
    experiment needing others reopens it (on the simulated bench: the world restarts at rest).
    """

    def __init__(self, config: Mapping[str, Any], source: str = "config") -> None:
        top = validate_table(config, {**RUN_SCHEMA, "experiment": Field(dict, {}, "unused")},
                             source)
        self.bench_config = bench_table(top["bench"])
        validate_table(self.bench_config["gains"], GAINS_SCHEMA, "bench.gains")
        limits = dict(top["limits"])
        self.gain_limits = validate_table(limits.pop("gains", {}), GAIN_LIMITS_SCHEMA,
                                          "limits.gains")
        self.limits_config = limits
        self.limits = Limits.from_config(limits)
        self.output_dir = Path(self.bench_config["output_dir"])
        self.cycle_s = self.bench_config["cycle_ms"] * 1e-3
        self.drive = Drive(self)
        self._stop = StopRequest()
        self._bench: Bench | None = None
        self._needs: Any = None
        self._catalog: Catalog | None = None

    # -- the open bench --------------------------------------------------------------------

    def __enter__(self) -> BenchSession:
        self._open_bench()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Refuse further plans (`Drive.disable`) and close the bench (bus, simulated peer);
        the drive is disabled between plans already."""
        self.drive.disable()
        self.close_bench()

    def _open_bench(self, plan: Plan | None = None, needs: Mapping[str, Any] | None = None
                    ) -> Bench:
        """The bench open with the devices `needs` (a family's `devices()`): reopened when
        they differ from those it is open with."""
        key = (dict(needs or {}), plan.params.get("workpiece") if plan and needs else None)
        if self._bench is not None and key == self._needs:
            return self._bench
        self.close_bench()
        bench = Bench(self.bench_config, plan if needs else None, needs)
        bench.__enter__()
        self._bench, self._needs = bench, key
        self.output_dir.mkdir(parents=True, exist_ok=True)
        if self._catalog is None:
            self._catalog = open_catalog(self.output_dir, setting=self.bench_config["catalog"],
                                         bench=self.bench_config["name"])
            self._catalog.reconcile()  # runs a dead process left `running`: crashed, files too
        return bench

    def close_bench(self) -> None:
        """Close the open bench and keep the session (the next plan opens it again)."""
        if self._bench is not None:
            bench, self._bench = self._bench, None
            bench.__exit__(None, None, None)

    def _current_bench(self) -> Bench:
        """The bench as it is open (with whatever devices), else opened with the drive only."""
        return self._bench if self._bench is not None else self._open_bench()

    def _first_drive(self):
        drive = self._current_bench().drive
        return next(iter(drive.values())) if isinstance(drive, Mapping) else drive

    def _set_gains(self, given: Mapping[str, float]) -> None:
        self.bench_config["gains"] = {**self.bench_config["gains"], **given}
        drive = self._current_bench().drive
        for each in (drive.values() if isinstance(drive, Mapping) else [drive]):
            each.write_gains(**gains_si(given))

    @property
    def devices(self) -> tuple[DeviceView, ...]:
        """The devices the open bench serves besides the drive (none on a drive-only bench)."""
        return tuple(DeviceView(type(d).__name__, tuple(d.channels), dict(d.units),
                                tuple(d.streams)) for d in self._current_bench().devices)

    # -- plans -----------------------------------------------------------------------------

    def run(self, experiment: str | Experiment, progress: Progress | None = None,
            **params: Any) -> Run:
        """Run an experiment: a family name (``"chirp"``) with its config keys as `params`
        (units in the names, as in ``[experiment]``; defaults filled in), or an `Experiment`
        instance. Checked like ``feedbench run`` before anything moves (`ConfigError`,
        `LimitError`); returns the `Run` with the family's result. An aborted run raises
        `RunError`, a stopped one `RunStopped`."""
        if isinstance(experiment, Experiment):
            if params:
                raise ConfigError(f"run: params {sorted(params)} given with an Experiment "
                                  "instance (set them on the instance)")
            params = {**experiment.settings, "type": experiment.name}
        else:
            params = {**params, "type": experiment}
        config = parse_run_config({"bench": self.bench_config, "limits": self.limits_config,
                                   "experiment": params})
        needs = config.experiment.devices()
        return self._execute(config, self._open_bench(config.plan, needs), progress)

    def record(self, what: float | Sequence[Segment], label: str = "record",
               progress: Progress | None = None) -> Run:
        """Record an ad-hoc sequence: `what` seconds (s) at standstill (one ``measure``
        segment), or segments (`feedbench.Segment`: per-cycle target positions in m relative
        to where the axis stands, optional force and velocity offsets) run in order in
        cyclic synchronous position mode. Catalogued as ``sequence`` with `label`."""
        if isinstance(what, (int, float)):
            if what <= 0:
                raise ConfigError(f"record.seconds: must be > 0 (got {what:g})")
            what = [Segment(label, "measure", np.zeros(int(round(what / self.cycle_s))))]
        if not what:
            raise ConfigError("record.segments: no segment given")
        sequence = AdHocSequence(label, what, self.cycle_s)
        raw = {"bench": self.bench_config, "limits": self.limits_config,
               "experiment": sequence.settings}
        config = RunConfig(self.bench_config, self.limits, sequence.plan(), raw, sequence)
        return self._execute(config, self._current_bench(), progress)

    def stop(self, reason: str = "stop requested") -> None:
        """Ask the running plan for its safe stop (any thread may call it); it ends with
        `RunStopped`."""
        self._stop.request(reason)

    def _execute(self, config: RunConfig, bench: Bench, progress: Progress | None) -> Run:
        if not self.drive.enabled:
            raise ConfigError("drive: not enabled (call bench.drive.enable() first)")
        self._stop = StopRequest()
        observers = [ProgressCallback(progress)] if progress else []
        row = bench.run(config, self._catalog, self.output_dir, observers, progress=False,
                        stop=self._stop)
        path = Path(row["file"])
        complete = row["status"] == "complete"
        result = (analyze_file(path) if complete and config.plan.experiment in families()
                  else {})
        run = Run(row["id"], path, row["status"], row["reason"], result, open_recording(path))
        if self._stop.reason is not None:  # Ctrl-C lands in the runner: the script stops too
            raise RunStopped(run)
        if not complete:
            raise RunError(run)
        return run

    def report(self, runs: Sequence[Run | str | Path], path: str | Path | None = None,
               title: str = "feedbench script report") -> Path:
        """One self-contained HTML report of `runs` (``report.html`` in the output directory
        unless `path`); returns its path."""
        files = [run.path if isinstance(run, Run) else Path(run) for run in runs]
        return write_report(files, path or self.output_dir / "report.html", title)


def open_bench(config: str | Path | Mapping[str, Any]) -> BenchSession:
    """Open the bench `config` describes: a TOML file or a dict with the tables ``[bench]``
    (how to reach the drive; ``simulated = true`` starts the simulated bench), ``[limits]``
    (mm, mm/min, N; ``[limits.gains]``: the ranges `Drive.set_gains` accepts) and,
    optionally, an ``[experiment]`` the session ignores (a run config serves as a bench
    config). Bad input is a `ConfigError` naming the field. Use the result as a context
    manager; in a notebook, where a ``with`` block cannot span cells, the bench opens on first
    use and `BenchSession.close` closes it."""
    if isinstance(config, Mapping):
        return BenchSession(config)
    return BenchSession(read_toml(config), str(config))


__all__ = ["BenchSession", "ConfigError", "DeviceView", "Drive", "LimitError", "Progress",
           "Reading", "Run", "RunError", "RunStopped", "Segment", "open_bench"]
