"""The bench: reads a run config, reaches the drive (simulated or real), runs a plan.

This is the composition root: the one place that knows both the host side (drivers,
daq, experiments) and, when ``bench.simulated = true``, starts the simulated drive on
the same bus. Everything else stays in its room.
"""

from __future__ import annotations

import json
import math
import shutil
import sys
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Sequence

from feedbench.axes import Axis, axis_kind, axis_schema, default_axis
from feedbench.config import ConfigError, Field, one_of, positive, read_toml, validate_table
from feedbench.daq.clock import LockstepClock, RealtimeClock, one_core
from feedbench.daq.recorder import Recorder, expected_size
from feedbench.daq.recording import open_recording
from feedbench.daq.store import copy_recording, store_problem
from feedbench.protocols.address import split_address
from feedbench.protocols.canbus import disconnect, open_network
from feedbench.drivers.cia402 import Cia402Drive, StopSettings
from feedbench.devices import (
    DeviceLinks, device_tables, hardware_gaps, open_cycle_devices, read_old_keys,
)
from feedbench.engine.family import Experiment, families, family, judged_analysis
from feedbench.engine.limits import Limits
from feedbench.engine.plan import Plan
from feedbench.engine.runner import Observer, ProgressPrinter, Runner, StopRequest
from feedbench.units import MS_TYPOS, kv_to_per_second, typed_in

if TYPE_CHECKING:
    from feedbench.daq.catalog import Catalog

BUS_CYCLE_MS = (0.125, 10.0)
"""Bus cycles (ms) CiA 402 drives run their cyclic synchronous modes at (8 kHz to 100 Hz)."""


def bus_cycle(value: float) -> str | None:
    """Check: a bus cycle > 0 inside `BUS_CYCLE_MS`; outside it the line says which unit the
    value was probably typed in (s or µs)."""
    low, high = BUS_CYCLE_MS
    if not value > 0:
        return positive(value)
    if low <= value <= high:
        return None
    return (f" = {value:g} is outside the {low:g}–{high:g} ms a CiA 402 drive runs its cyclic "
            f"synchronous modes at{typed_in(value, 'ms', low, high, MS_TYPOS)}")


def catalog_problem(text: str) -> str | None:
    """Check: `daq.catalog.url_problem`, the catalog imported when a config names one: its
    SQLAlchemy takes 0.2-0.3 s to import, which a sim or a config without it need not wait."""
    from feedbench.daq.catalog import url_problem

    return url_problem(text)


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
    "cycle_ms": Field(float, 1.0, "bus cycle: SYNC period (ms)", bus_cycle),
    "clock": Field(str, "lockstep", "lockstep (simulation) or realtime (hardware)",
                   one_of("lockstep", "realtime")),
    "timeout_s": Field(float, 1.0,
                       "how long a cycle may wait for its TPDOs (s; lockstep: while the process "
                       "runs)", positive),
    "sync_loss_ms": Field(float, 50.0, "real time: the drives stop when no SYNC came for this "
                          "long (ms; 0x2021 in bus cycles, at most 255; lockstep: off). Keep "
                          "it above the host's scheduling hiccups (docs/realtime.md)",
                          positive),
    "one_core": Field(bool, True, "simulated lockstep bench: its threads on one CPU "
                      "(faster, same results; `feedbench.daq.clock.one_core`)"),
    "one_thread": Field(bool, True, "simulated lockstep bench on the virtual bus, a run "
                        "needing no device besides the drives: each CAN frame handled in its "
                        "sender's thread, no receive threads (faster, same results; "
                        "`protocols.canbus.DirectVirtualBus`); the live window turns it off: "
                        "a run that never waits for its bus leaves the window few chances "
                        "to draw"),
    "eds": Field(str, "", "EDS file of the drive (empty: the packaged simulated drive's)"),
    "name": Field(str, "", "the bench's name in the run catalog and the lab's store (empty: "
                  "$FEEDBENCH_BENCH, else the host's name; the environment's wins: "
                  "docs/catalog.md)"),
    "output_dir": Field(str, "runs", "where recordings and the catalog go"),
    "catalog": Field(str, "", "run catalog: postgresql://user@host/database (no password: "
                     "PGPASSWORD, ~/.pgpass or a service file) or an SQLite file (empty: "
                     "output_dir/catalog.sqlite; docs/catalog.md)", catalog_problem),
    "store": Field(str, "", "the lab's recording store each recording is copied to after its "
                   "run: a directory (NAS mount) or an fsspec URL (empty: none; "
                   "docs/catalog.md)", store_problem),
    "gains": Field(dict, {}, "servo gains written to the drive by SDO before the run"),
    "stop": Field(dict, {}, "what the safe stop needs from the drives and how it is confirmed "
                  "(drivers.cia402.STOP_SCHEMA)"),
    "world": Field(dict, {}, "simulated world (simulated = true only); never read by the host"),
    "socketcand": Field(str, "127.0.0.1:29536", "host:port of the socketcand server "
                        "(interface = socketcand; `feedbench sim` listens there)"),
    "devices": Field(dict, {}, "one [bench.devices.<name>] table per device: kind, address, "
                     "unit id, its own settings (devices.Device.table_schema)"),
}
"""The [bench] keys of every bench; ``axis`` and each registered axis kind's own keys are added
by `bench_schema`."""

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


def bench_schema() -> dict[str, Field]:
    """The [bench] schema: `BENCH_SCHEMA`, ``axis`` (its default the kind that declares
    itself so, `axes.default_axis`, looked up here, not at import) and the keys of the
    registered axis kinds."""
    axis = Field(str, default_axis(), "the axis kind: a name registered under feedbench.axes "
                 "(default: the kind that declares itself the default, one linear drive)")
    return {**BENCH_SCHEMA, "axis": axis, **axis_schema()}


def run_axis(raw: Mapping[str, Any]) -> type[Axis]:
    """The axis kind a run config (`raw`, its tables) names in ``[bench] axis``, the default
    if it names none."""
    return axis_kind(raw.get("bench", {}).get("axis") or default_axis())


def bench_table(table: Mapping[str, Any]) -> dict[str, Any]:
    """A checked ``[bench]`` table, defaults filled in; the keys of earlier versions are
    read into their device's table with a one-line hint (`read_old_keys`)."""
    bench = validate_table(read_old_keys(table), bench_schema(), "bench")
    axis_kind(bench["axis"])
    for name, device in bench["devices"].items():
        if not isinstance(device, dict):
            raise ConfigError(f"bench.devices.{name}: must be a table (got {device!r})")
    return bench


def parse_run_config(raw: Mapping[str, Any]) -> RunConfig:
    """Validate a whole run config (already parsed TOML); raises `ConfigError`."""
    top = validate_table(raw, RUN_SCHEMA, "config")
    if top["experiment"] is None:
        raise ConfigError("config.experiment: required table [experiment] is missing")
    bench = bench_table(top["bench"])
    validate_table(bench["gains"], GAINS_SCHEMA, "bench.gains")
    limits = Limits.from_config(top["limits"])
    cls = family(top["experiment"].get("type"))
    if cls.axes and bench["axis"] not in cls.axes:
        raise ConfigError(f"bench.axis: experiment {cls.name} needs axis = "
                          f"{' or '.join(cls.axes)} (got {bench['axis']!r})")
    experiment = cls(top["experiment"], bench["cycle_ms"] * 1e-3)
    plan = experiment.plan()
    device_tables(bench, axis_kind(bench["axis"])(bench, plan, experiment.devices()).needs)
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
        result = judged_analysis(families()[recording.experiment], recording)
    except ConfigError:
        raise
    except (ValueError, KeyError) as exc:  # the recorded data do not fit the analysis
        reason = f"no {exc.args[0]!r} recorded" if isinstance(exc, KeyError) else exc
        raise ConfigError(f"{path}: {recording.experiment} analysis: {reason}") from exc
    result["run"] = {"file": str(path), "status": recording.status, "reason": recording.reason,
                     "n_samples": recording.n_samples, "n_gaps": recording.n_gaps}
    return result


def sim_config(path: str | Path) -> tuple[dict[str, Any], Plan | None]:
    """`feedbench sim`'s config: the validated [bench] table, its ``devices`` the checked
    tables of those the axis serves (`Axis.served`, the settings of the [experiment]'s
    devices over them, e.g. the exciters' I/O module node), and the plan of the file's
    [experiment] if it has one (which prepares the world: an SMFE plan's workpiece)."""
    raw = read_toml(path)
    if "experiment" in raw:
        config = parse_run_config(raw)
        bench, plan, needs = config.bench, config.plan, config.experiment.devices()
    else:
        bench, plan, needs = bench_table(raw.get("bench", {})), None, {}
    axis = axis_kind(bench["axis"])(bench, plan, needs)
    return {**bench, "devices": device_tables(bench, {**axis.served(), **needs})}, plan


def start_served(bench: Mapping[str, Any], bus_options: Mapping[str, Any], stack: ExitStack,
                 plan: Plan | None = None) -> dict[str, Any]:
    """`feedbench sim`: start the simulated axis of `bench` (from `sim_config`) with its
    peers listening where their tables say (closed by `stack`); what the ready line says of
    it (`sim_backends.process.serve`)."""
    from feedbench.sim_backends.process import modbus_device_ids

    axis = axis_kind(bench["axis"])(bench, plan, {})
    tables = bench["devices"]
    simulated = axis.start_simulated(bench["cycle_ms"] * 1e-3, bus_options, tables, listen=True)
    stack.callback(simulated.close)
    addresses = axis.addresses(simulated)
    modbus = [address for name, address in addresses.items() if "unit_id" in tables[name]]
    devices = {name: _served_entry(table, addresses.get(name)) for name, table in tables.items()}
    return {"axis": bench["axis"], "node_id": bench["node_id"],
            **{key: bench[key] for key in axis.schema},
            **({"modbus": modbus[0]} if modbus else {}),
            "modbus_devices": modbus_device_ids(simulated.modbus_devices),
            "devices": {name: entry for name, entry in devices.items() if entry}}


SERVED_KEYS = ("unit_id", "node_id")
"""Keys of a served device's table the host's table needs besides the address."""


def _served_entry(table: Mapping[str, Any], address: str | None) -> dict[str, Any]:
    """What a host's ``[bench.devices.<name>]`` table needs to reach a served device."""
    return {**({"address": address} if address else {}),
            **{key: table[key] for key in SERVED_KEYS if key in table}}


def host_config(raw: Mapping[str, Any]) -> dict[str, Any]:
    """The config as the host may record it: the simulated world's truth removed."""
    out = json.loads(json.dumps(raw))
    out.get("bench", {}).pop("world", None)
    return out


def _drive_gains(drive) -> dict[str, float] | None:
    """The cascade gains the drive runs with (SDO), for analyses such as Eq. (4.20); None
    for an axis of several drives."""
    return drive.read_gains()._asdict() if isinstance(drive, Cia402Drive) else None


def _drive_stop(drive) -> dict[str, Any]:
    """What each drive's stop depends on, as read at configure (`StopParameters.as_metadata`);
    several drives by name."""
    if isinstance(drive, Cia402Drive):
        return drive.stop_parameters.as_metadata()
    return {name: d.stop_parameters.as_metadata() for name, d in drive.items()}


def gains_si(table: Mapping[str, Any]) -> dict[str, float]:
    """A `[bench.gains]` table in SI, only the gains it gives: K_p (N·s/m), T_i (s), K_v (1/s)."""
    g = validate_table(table, GAINS_SCHEMA, "bench.gains")
    out = {}
    if g["K_p_Ns_m"] is not None:
        out["K_p"] = g["K_p_Ns_m"]
    if g["T_i_ms"] is not None:
        out["T_i"] = g["T_i_ms"] * 1e-3
    if g["K_v_m_min_mm"] is not None:
        out["K_v"] = kv_to_per_second(g["K_v_m_min_mm"])
    return out


def _bus_options(cfg: Mapping[str, Any],
                 devices: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """python-can options beyond interface and channel: a socketcand server's host and port;
    ``direct`` for a simulated lockstep bench on the virtual bus whose run needs no device
    besides the drives (``one_thread``: each frame handled in its sender's thread,
    `protocols.canbus.DirectVirtualBus`). A device's own threads (the DAQ's reader, the
    Modbus server) would get the interpreter only when the cycle's thread is made to give
    it up: an SMFE row of the fault matrix aborted early once in a whole suite."""
    if cfg["interface"] == "virtual":
        return {"direct": True} if (cfg["one_thread"] and cfg["simulated"] and not devices
                                    and cfg["clock"] == "lockstep") else {}
    if cfg["interface"] != "socketcand":
        return {}
    host, port = split_address(cfg["socketcand"], "bench.socketcand")
    return {"host": host, "port": port}


SYNC_LOSS_LIMIT_MAX = 255
"""The largest SYNC loss limit a drive holds (0x2021, UNSIGNED8), in bus cycles."""


def sync_loss_cycles(cfg: Mapping[str, Any]) -> int:
    """Missed SYNCs after which the drives stop (0x2021): ``sync_loss_ms`` in whole bus
    cycles, rounded up, in real time; 0 (off) in lockstep, where time is virtual."""
    if cfg["clock"] != "realtime":
        return 0
    cycles = math.ceil(cfg["sync_loss_ms"] / cfg["cycle_ms"] - 1e-9)
    if cycles > SYNC_LOSS_LIMIT_MAX:
        raise ConfigError(f"bench.sync_loss_ms: {cfg['sync_loss_ms']:g} ms is {cycles} bus "
                          f"cycles of {cfg['cycle_ms']:g} ms; a drive counts at most "
                          f"{SYNC_LOSS_LIMIT_MAX} (0x2021)")
    return cycles


class Bench:
    """An open bench: the CAN network, the drive driver, the clock (and the simulated peer).

    Use as a context manager; `run(config)` executes one plan and returns its record.
    `needs`: the devices besides the drives the plan's experiment needs (`Experiment.devices`).
    `drive` is the axis's only drive, or its drives by name (rack-and-pinion: master, slave).
    """

    def __init__(self, bench: Mapping[str, Any], plan: Plan | None = None,
                 needs: Mapping[str, dict] | None = None) -> None:
        self.config = dict(bench)
        self.plan = plan
        self.needs = dict(needs or {})
        self._stack = ExitStack()
        self.simulated = None
        self.network = None
        self.drive: Cia402Drive | dict[str, Cia402Drive] | None = None
        self.clock = None
        self.devices: list = []

    def __enter__(self) -> Bench:
        """The same steps for every axis kind (`axes.axes`): simulated peer, network, drives
        and gains, clock, the devices the axis needs (at its simulated peers' addresses, else
        the configured ones); what is open is closed again if a step fails. The devices'
        tables and the sync-loss limit are checked before anything opens."""
        cfg = self.config
        cycle_s = cfg["cycle_ms"] * 1e-3
        sync_loss_cycles(cfg)
        axis = axis_kind(cfg["axis"])(cfg, self.plan, self.needs)
        tables = device_tables(cfg, axis.needs)
        try:
            if cfg["one_core"] and cfg["simulated"] and cfg["clock"] == "lockstep":
                self._stack.enter_context(one_core())  # first: every thread below inherits it
            bus_options = _bus_options(cfg, tables)
            if cfg["simulated"]:
                _say_hardware_gaps(tables)
                self.simulated = axis.start_simulated(cycle_s, bus_options, tables)
                self._stack.callback(self.simulated.close)
            self.network = open_network(cfg["interface"], cfg["channel"], cfg["bitrate"],
                                        **bus_options)
            self._stack.callback(disconnect, self.network)
            drives = self._open_drives(axis)
            self.drive = drives[""] if "" in drives else drives
            if cfg["clock"] == "lockstep":
                self.clock = LockstepClock(self.network, list(drives.values()),
                                           timeout_s=cfg["timeout_s"], cycle_s=cycle_s)
            else:
                self.clock = RealtimeClock(self.network, list(drives.values()), period_s=cycle_s,
                                           timeout_s=cfg["timeout_s"])
            self._stack.callback(self.clock.close)
            addresses = axis.addresses(self.simulated) if self.simulated is not None else {}
            links = DeviceLinks(cfg, self.network, drives, self._stack, peers=addresses)
            self.devices = open_cycle_devices(tables, links)
        except BaseException:
            self._stack.close()
            raise
        return self

    def _open_drives(self, axis: Axis) -> dict[str, Cia402Drive]:
        """The axis's drives, each configured by SDO with the bench's gains."""
        eds = self.config["eds"] or axis.packaged_eds()
        gains = gains_si(self.config["gains"]) or None
        stop = StopSettings.from_config(self.config["stop"], axis.stop_margin_s)
        drives = {name: Cia402Drive(self.network, node_id, eds, axis.pdo_config)
                  for name, node_id in axis.nodes().items()}
        for drive in drives.values():
            drive.configure(gains=gains, cycle_s=self.config["cycle_ms"] * 1e-3,
                            sync_loss_cycles=sync_loss_cycles(self.config), stop=stop)
        return drives

    def __exit__(self, *exc) -> None:
        self._stack.close()

    def run(self, config: RunConfig, catalog: Catalog, output_dir: Path,
            observers: Sequence[Observer] = (), progress: bool = True,
            stop: StopRequest | None = None, store: str = "") -> dict:
        """Execute `config.plan`; returns the catalog row as a dict.

        `observers` see the data stream (live window); `stop` lets another thread ask for a
        safe stop. After the run its closed recording is copied to the lab's store, `store`
        (``--store``) or ``bench.store`` (`daq.store.copy_recording`; the record's ``store``:
        where, ``copied`` or ``pending`` and why, sha256).
        """
        from feedbench.daq.catalog import CatalogError

        runner = Runner(self.drive, self.clock, config.limits, stop=stop,
                        observers=[*observers, *([ProgressPrinter()] if progress else [])],
                        devices=self.devices)
        start = runner.read_position()
        runner.absolute_targets(config.plan, start)
        check_free_space(output_dir, FREE_SPACE_MARGIN * expected_size(
            config.plan.n_cycles, config.plan.cycle_s, runner.channels, runner.streams))
        run_id = catalog.new_run_id(config.plan.experiment)
        path = output_dir / f"{run_id}.h5"
        metadata = {"experiment": config.plan.experiment, "run_id": run_id,
                    "config": host_config(config.raw),
                    "cycle_s": config.plan.cycle_s, "drive_gains": _drive_gains(self.drive),
                    "drive_stop": _drive_stop(self.drive), **catalog.recorder_names()}
        catalog.add(run_id, config.plan.experiment, str(path), config.plan.params)
        streams = {name: spec for d in self.devices for name, spec in d.streams.items()}
        recorder = Recorder(path, runner.channels, runner.units, metadata, streams=streams)
        for observer in observers:
            if hasattr(observer, "on_metadata"):  # what the recording's analysis reads
                observer.on_metadata(metadata)
        outcome = runner.run(config.plan, recorder, start)
        reason = outcome.reason
        try:
            catalog.finish(run_id, outcome.status, reason, recorder.n_samples, outcome.timing)
        except CatalogError as exc:  # full disk: `feedbench runs` settles it from the file
            reason = f"{reason}; {exc}" if reason else str(exc)
        record = {"id": run_id, "file": str(path), "status": outcome.status, "reason": reason}
        if outcome.timing:
            record["timing"] = outcome.timing
        if store := store or self.config.get("store", ""):
            copy = copy_recording(run_id, path, store, catalog.bench)
            record["store"] = copy.as_dict()
            try:
                catalog.record_copy(run_id, copy)
            except CatalogError as exc:  # gone since: said once; sync --store records it
                if reason == outcome.reason:
                    record["reason"] = f"{reason}; {exc}" if reason else str(exc)
        return record


def _say_hardware_gaps(tables: Mapping[str, Mapping[str, Any]]) -> None:
    """One line on stderr naming the device addresses this simulated run goes without and
    hardware would need (`devices.hardware_gaps`); nothing if none is missing."""
    gaps = hardware_gaps(tables)
    if gaps:
        print(f"feedbench: simulated bench: {', '.join(gaps)} not given (the simulated peers' "
              "used); hardware needs them", file=sys.stderr)


FREE_SPACE_MARGIN = 1.5
"""A run starts only with this many times its recording's expected size free on disk
(`daq.recorder.expected_size`: the stop ramp, events and HDF5's own metadata besides)."""


def check_free_space(directory: Path, needed: float) -> None:
    """Raise `ConfigError` naming `bench.output_dir` if `directory`'s disk has fewer than
    `needed` bytes free."""
    free = shutil.disk_usage(directory).free
    if free < needed:
        raise ConfigError(f"bench.output_dir: {directory}: the run needs {needed / 1e6:.1f} MB "
                          f"free (its recording with margin), the disk has {free / 1e6:.1f} MB")


def run_config(config: RunConfig, observers: Sequence[Observer] = (),
               progress: bool = True, stop: StopRequest | None = None,
               catalog: str = "", store: str = "") -> dict:
    """Open the bench of `config`, run its plan, close the bench; returns the run record.
    `catalog` (``--catalog``) overrides ``$FEEDBENCH_CATALOG`` and ``bench.catalog``, `store`
    (``--store``) ``bench.store``.

    The output directory and its catalog are made once the bench has opened: a bench that
    cannot be reached leaves nothing behind."""
    from feedbench.daq.catalog import open_catalog

    output_dir = Path(config.bench["output_dir"])
    with Bench(config.bench, config.plan, config.experiment.devices()) as bench:
        output_dir.mkdir(parents=True, exist_ok=True)
        runs = open_catalog(output_dir, catalog, config.bench["catalog"], config.bench["name"])
        runs.reconcile()  # runs a dead process left `running`: crashed, in their files too
        return bench.run(config, runs, output_dir, observers, progress, stop, store)
