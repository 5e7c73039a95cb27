"""The bench: reads a run config, reaches the drive (simulated or real), runs a plan.

This is the composition root: the one place that knows both the host side (drivers,
daq, experiments) and, when ``bench.simulated = true``, starts the simulated drive on
the same bus. Everything else stays in its room.
"""

from __future__ import annotations

import json
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

from feedbench.config import ConfigError, Field, one_of, positive, read_toml, validate_table
from feedbench.daq.catalog import Catalog
from feedbench.daq.clock import LockstepClock, RealtimeClock, one_core
from feedbench.daq.recorder import Recorder
from feedbench.daq.recording import open_recording
from feedbench.protocols.address import split_address
from feedbench.protocols.canbus import open_network
from feedbench.drivers.cia402 import Cia402Drive
from feedbench.experiments.cycle_io import open_cycle_devices
from feedbench.experiments.family import Experiment, families, family
from feedbench.experiments.limits import Limits
from feedbench.experiments.plan import Plan
from feedbench.experiments.runner import Observer, ProgressPrinter, Runner, StopRequest
from feedbench.units import kv_to_per_second

GAINS_SCHEMA = {
    "K_p_Ns_m": Field(float, None, "velocity-loop gain (N·s/m)", positive),
    "T_i_ms": Field(float, None, "velocity-loop integral time (ms)", positive),
    "K_v_m_min_mm": Field(float, None, "position-loop gain ((m/min)/mm)", positive),
}

BENCH_SCHEMA = {
    "simulated": Field(bool, True, "start the simulated drive on the same bus"),
    "interface": Field(str, "virtual", "python-can interface (virtual, socketcan, socketcand…)"),
    "channel": Field(str, "feedbench", "python-can channel (e.g. can0)"),
    "bitrate": Field(int, 1_000_000, "CAN bitrate (bit/s)", positive),
    "node_id": Field(int, 1, "CANopen node id of the drive", positive),
    "cycle_ms": Field(float, 1.0, "bus cycle: SYNC period (ms)", positive),
    "clock": Field(str, "lockstep", "lockstep (simulation) or realtime (hardware)",
                   one_of("lockstep", "realtime")),
    "timeout_s": Field(float, 1.0, "how long a cycle may wait for its TPDOs (s)", positive),
    "one_core": Field(bool, True, "simulated lockstep bench: its threads on one CPU "
                      "(faster, same results; `feedbench.daq.clock.one_core`)"),
    "eds": Field(str, "", "EDS file of the drive (empty: the packaged simulated drive's)"),
    "output_dir": Field(str, "runs", "where recordings and the catalog go"),
    "gains": Field(dict, {}, "servo gains written to the drive by SDO before the run"),
    "world": Field(dict, {}, "simulated world (simulated = true only); never read by the host"),
    "socketcand": Field(str, "127.0.0.1:29536", "host:port of the socketcand server "
                        "(interface = socketcand; `feedbench sim` listens there)"),
    "modbus": Field(str, "", "host:port of the Modbus TCP server of the spindle inverter "
                    "(simulated: the bench starts one on 127.0.0.1)"),
    "daq_port": Field(str, "", "serial port of the streaming DAQ, e.g. /dev/ttyACM0 "
                      "(simulated: the bench's pseudo-terminal)"),
    "axis": Field(str, "lab", "lab (one linear drive) or rack_pinion (master and slave "
                  "drives, Ch. 3.2)", one_of("lab", "rack_pinion")),
    "slave_node_id": Field(int, 2, "rack_pinion: CANopen node id of the slave drive", positive),
    "load_cell": Field(str, "", "rack_pinion: host:port of the bumper's load-cell amplifier "
                       "(Modbus TCP; simulated: the bench starts one on 127.0.0.1)"),
    "load_cell_every": Field(int, 1, "rack_pinion: read the load cell every n bus cycles",
                             positive),
    "io_node_id": Field(int, 10, "`feedbench sim`: CANopen node id of the tool-tip exciters' "
                        "CiA 401 I/O module (a tool-tip [experiment] in the sim config sets "
                        "it to its io_node_id)", positive),
}

RUN_SCHEMA = {
    "bench": Field(dict, {}, "how to reach the drive"),
    "limits": Field(dict, {}, "limits watched during the run"),
    "experiment": Field(dict, None, "the experiment plan"),
}


@dataclass(frozen=True)
class RunConfig:
    """A validated run config: bench table, limits, the experiment and its plan."""

    bench: dict[str, Any]
    limits: Limits
    plan: Plan
    raw: dict[str, Any]
    experiment: Experiment


def parse_run_config(raw: Mapping[str, Any]) -> RunConfig:
    """Validate a whole run config (already parsed TOML); raises `ConfigError`."""
    top = validate_table(raw, RUN_SCHEMA, "config")
    if top["experiment"] is None:
        raise ConfigError("config.experiment: required table [experiment] is missing")
    bench = validate_table(top["bench"], BENCH_SCHEMA, "bench")
    validate_table(bench["gains"], GAINS_SCHEMA, "bench.gains")
    limits = Limits.from_config(top["limits"])
    cls = family(top["experiment"].get("type"))
    if cls.axes and bench["axis"] not in cls.axes:
        raise ConfigError(f"bench.axis: experiment {cls.name} needs axis = "
                          f"{' or '.join(cls.axes)} (got {bench['axis']!r})")
    experiment = cls(top["experiment"], bench["cycle_ms"] * 1e-3)
    plan = experiment.plan()
    _check_excitation_fits(plan, limits)
    return RunConfig(bench, limits, plan, dict(raw), experiment)


def _check_excitation_fits(plan: Plan, limits: Limits) -> None:
    """An excitation above the force limit is a config error, caught before anything moves."""
    peak = float(abs(plan.concatenated("force_offset")).max(initial=0.0))
    if peak > limits.force:
        raise ConfigError(
            f"experiment.amplitude_N: {peak:g} N exceeds the force limit limits.force_N "
            f"({limits.force:g} N)"
        )
    limits.check_excitation(plan.concatenated("force_offset"),
                            plan.concatenated("velocity_offset"))
    limits.check_excitation(plan.concatenated("excitation"), plan.concatenated("velocity_offset"))


def load_run_config(path: str | Path) -> RunConfig:
    """Read and validate a TOML run config file."""
    return parse_run_config(read_toml(path))


def analyze_file(path: str | Path) -> dict:
    """Open a recording and run its experiment's analysis step; what the data do not fit
    is a `ConfigError` naming the file."""
    recording = open_recording(path)
    if recording.experiment not in families():
        raise ConfigError(f"{path}: no analysis for experiment {recording.experiment!r}")
    try:
        result = families()[recording.experiment].analyze(recording)
    except ConfigError:
        raise
    except (ValueError, KeyError) as exc:  # the recorded data do not fit the analysis
        reason = f"no {exc.args[0]!r} recorded" if isinstance(exc, KeyError) else exc
        raise ConfigError(f"{path}: {recording.experiment} analysis: {reason}") from exc
    result["run"] = {"file": str(path), "status": recording.status, "reason": recording.reason,
                     "n_samples": recording.n_samples, "n_gaps": recording.n_gaps}
    return result


def sim_config(path: str | Path) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """`feedbench sim`'s config: the validated [bench] table and, if the file has an
    [experiment], the workpiece its plan prepares (SMFE lanes; else no workpiece) and the
    node of the I/O module its exciter needs (``bench.io_node_id``)."""
    raw = read_toml(path)
    if "experiment" not in raw:
        return validate_table(raw.get("bench", {}), BENCH_SCHEMA, "bench"), []
    config = parse_run_config(raw)
    exciter = config.experiment.devices().get("exciter", {})
    bench = {**config.bench, "io_node_id": exciter.get("node_id", config.bench["io_node_id"])}
    return bench, list(config.plan.params.get("workpiece", ()))


def host_config(raw: Mapping[str, Any]) -> dict[str, Any]:
    """The config as the host may record it: the simulated world's truth removed."""
    out = json.loads(json.dumps(raw))
    out.get("bench", {}).pop("world", None)
    return out


def _packaged_eds() -> str:
    from feedbench.sim_backends.eds import packaged_eds_path

    return str(packaged_eds_path())


def _drive_gains(drive) -> dict[str, float] | None:
    """The cascade gains the drive runs with (SDO), for analyses such as Eq. (4.20); None
    for an axis of several drives."""
    return drive.read_gains()._asdict() if isinstance(drive, Cia402Drive) else None


def _gains_si(table: Mapping[str, Any]) -> dict[str, float]:
    g = validate_table(table, GAINS_SCHEMA, "bench.gains")
    out = {}
    if g["K_p_Ns_m"] is not None:
        out["K_p"] = g["K_p_Ns_m"]
    if g["T_i_ms"] is not None:
        out["T_i"] = g["T_i_ms"] * 1e-3
    if g["K_v_m_min_mm"] is not None:
        out["K_v"] = kv_to_per_second(g["K_v_m_min_mm"])
    return out


def _device_needs(plan: Plan | None) -> dict[str, dict]:
    """The devices besides the drive the plan's experiment needs (its family's `devices`)."""
    if plan is None:
        return {}
    return family(plan.experiment)(plan.params, plan.cycle_s).devices()


def _bus_options(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """python-can options beyond interface and channel: a socketcand server's host and port."""
    if cfg["interface"] != "socketcand":
        return {}
    host, port = split_address(cfg["socketcand"], "bench.socketcand")
    return {"host": host, "port": port}


class Bench:
    """An open bench: the CAN network, the drive driver, the clock (and the simulated peer).

    Use as a context manager; `run(config)` executes one plan and returns its record.
    """

    def __init__(self, bench: Mapping[str, Any], plan: Plan | None = None) -> None:
        self.config = dict(bench)
        self.plan = plan
        self._stack = ExitStack()
        self.simulated_drive = None
        self.simulated = None
        self.network = None
        self.drive: Cia402Drive | None = None
        self.clock = None
        self.devices: list = []

    def __enter__(self) -> Bench:
        cfg = self.config
        cycle_s = cfg["cycle_ms"] * 1e-3
        try:
            if cfg["one_core"] and cfg["simulated"] and cfg["clock"] == "lockstep":
                self._stack.enter_context(one_core())  # first: every thread below inherits it
            if cfg["axis"] == "rack_pinion":
                self._open_rack_pinion(cycle_s)
                return self
            needs = _device_needs(self.plan)
            if cfg["simulated"]:
                self._start_simulated_peer(cycle_s, needs)
            self.network = open_network(cfg["interface"], cfg["channel"], cfg["bitrate"],
                                        **_bus_options(cfg))
            self._stack.callback(self.network.disconnect)
            eds = cfg["eds"] or _packaged_eds()
            self.drive = Cia402Drive(self.network, cfg["node_id"], eds)
            self.drive.configure()
            gains = _gains_si(cfg["gains"])
            if gains:
                self.drive.write_gains(**gains)
            if cfg["clock"] == "lockstep":
                self.clock = LockstepClock(self.network, [self.drive], timeout_s=cfg["timeout_s"])
            else:
                self.clock = RealtimeClock(self.network, [self.drive], period_s=cycle_s)
            self.devices = open_cycle_devices(needs, *self._device_addresses(), self._stack,
                                              self.network)
        except BaseException:
            self._stack.close()
            raise
        return self

    def _open_rack_pinion(self, cycle_s: float) -> None:
        """Master and slave drives of the rack-and-pinion axis (`rack_pinion_bench`)."""
        from feedbench.rack_pinion_bench import open_rack_pinion

        axis = open_rack_pinion(self.config, cycle_s, _gains_si(self.config["gains"]),
                                self._stack, _bus_options(self.config))
        self.network, self.drive, self.clock = axis.network, axis.drives, axis.clock
        self.devices, self.simulated = axis.devices, axis.simulated

    def _start_simulated_peer(self, cycle_s: float, needs: Mapping[str, Any]) -> None:
        from feedbench.sim_backends.bench import start_simulated_axis
        from feedbench.sim_backends.world import build_axis, build_sensor_noise

        cfg = self.config
        if needs:  # devices besides the drive: the whole simulated bench
            self._start_simulated_bench(needs.get("exciter", {}).get("node_id"))
            return
        simulator = build_axis(cfg["world"], cycle_s)
        self.simulated_drive = start_simulated_axis(
            cfg["interface"], cfg["channel"], cfg["node_id"], simulator,
            noise=build_sensor_noise(cfg["world"]),
        )
        self._stack.callback(self.simulated_drive.close)

    def _start_simulated_bench(self, exciter_node: int | None = None) -> None:
        """Drive, inverter, DAQ and the milling world, the workpiece prepared as planned (with
        `exciter_node`: the tool-tip exciters and their I/O module instead of the milling)."""
        from feedbench.sim_backends.process import SimulatedBench

        self.simulated = SimulatedBench(self.config, self.plan.params.get("workpiece", ()),
                                        bus_options=_bus_options(self.config),
                                        exciter_node=exciter_node,
                                        milling=exciter_node is None)
        self._stack.callback(self.simulated.close)
        self.simulated_drive = self.simulated.drive

    def _device_addresses(self) -> tuple[str, str]:
        """Modbus host:port and DAQ port: the simulated bench's, else the configured ones."""
        if self.simulated is not None:
            host, port = self.simulated.modbus_address
            return f"{host}:{port}", self.simulated.daq_port
        return self.config["modbus"], self.config["daq_port"]

    def __exit__(self, *exc) -> None:
        self._stack.close()

    def run(self, config: RunConfig, catalog: Catalog, output_dir: Path,
            observers: Sequence[Observer] = (), progress: bool = True,
            stop: StopRequest | None = None) -> dict:
        """Execute `config.plan`; returns the catalog row as a dict.

        `observers` see the data stream (live window); `stop` lets another thread ask for a
        safe stop.
        """
        runner = Runner(self.drive, self.clock, config.limits, stop=stop,
                        observers=[*observers, *([ProgressPrinter()] if progress else [])],
                        devices=self.devices)
        start = runner.read_position()
        runner.absolute_targets(config.plan, start)
        run_id = catalog.new_run_id(config.plan.experiment)
        path = output_dir / f"{run_id}.h5"
        metadata = {"experiment": config.plan.experiment, "run_id": run_id,
                    "config": host_config(config.raw),
                    "cycle_s": config.plan.cycle_s, "drive_gains": _drive_gains(self.drive)}
        catalog.add(run_id, config.plan.experiment, str(path), config.plan.params)
        streams = {name: spec for d in self.devices for name, spec in d.streams.items()}
        recorder = Recorder(path, runner.channels, runner.units, metadata, streams=streams)
        for observer in observers:
            if hasattr(observer, "on_metadata"):  # what the recording's analysis reads
                observer.on_metadata(metadata)
        outcome = runner.run(config.plan, recorder, start)
        catalog.finish(run_id, outcome.status, outcome.reason, recorder.n_samples)
        return {"id": run_id, "file": str(path), "status": outcome.status,
                "reason": outcome.reason}


def run_config(config: RunConfig, observers: Sequence[Observer] = (),
               progress: bool = True, stop: StopRequest | None = None) -> dict:
    """Open the bench of `config`, run its plan, close the bench; returns the run record.

    The output directory and its catalog are made once the bench has opened: a bench that
    cannot be reached leaves nothing behind."""
    output_dir = Path(config.bench["output_dir"])
    with Bench(config.bench, config.plan) as bench:
        output_dir.mkdir(parents=True, exist_ok=True)
        catalog = Catalog(output_dir / "catalog.sqlite")
        return bench.run(config, catalog, output_dir, observers, progress, stop)
