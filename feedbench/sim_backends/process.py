"""The whole simulated bench, in the host's process or as its own (`feedbench sim BENCH.toml`).

`SimulatedBench` starts the CiA 402 drive of a lab-axis ``[bench]`` table on its CAN bus
and the simulated peer of each device a run needs (`SimulatedPeer`, entry points
``feedbench.sim_devices``, the kind's name: `devices`), each on its real
transport with the settings of its ``[bench.devices.<name>]`` table: the Modbus devices
(spindle inverter, load-cell amplifier, each at its table's unit id) on one Modbus TCP
server on 127.0.0.1, the streaming DAQ on a pseudo-terminal, the exciters'
CiA 401 I/O module on the drive's bus. The worlds at the tool tip feed the DAQ: the
milling process (`smfe_world.SmfeWorld`, spindle and DAQ) and/or the exciters
(`structure_world`), summed on the DAQ's inputs (`DaqInputs`), stepped in the drive's SYNC
handler after the axis physics. Virtual time stays lockstep: the host's SYNC advances the
world one bus cycle.

`serve` runs a bench as a separate process that the host reaches only over loopback, exactly
as it would reach hardware: CAN through a socketcand hub (`socketcand_hub.SocketcandHub`;
the host uses python-can's ``socketcand`` interface, the bench's own nodes join the hub in
process through its `HubPort`, interface ``feedbench_hub``), Modbus TCP on 127.0.0.1, the
DAQ on the printed pseudo-terminal path. The axis kind starts its own simulated peer
(`axes.Axis.start_simulated`: the lab axis serves every device, both worlds on one DAQ;
each peer listens where its ``[bench.devices.<name>]`` table says, `modbus_listen`). It
prints one JSON line with the addresses, then
serves until SIGINT or SIGTERM; every log record, and any exception a thread does not catch,
is one line on stderr (`one_line_logging`), never a traceback.
"""

from __future__ import annotations

import json
import logging
import signal
import sys
import threading
from collections.abc import Iterator, Mapping, Sequence
from contextlib import ExitStack, contextmanager
from typing import Any, Callable, ClassVar, TextIO

import numpy as np

from feedbench.config import (
    ConfigError, Field, non_negative, positive, registered, validate_table,
)
from feedbench.protocols.address import LOOPBACK, split_address
from feedbench.protocols.canbus import frozen_heap
from feedbench.protocols.serial_frames import CHANNELS
from feedbench.sim_backends.bench import start_simulated_axis
from feedbench.sim_backends.faults import world_faults
from feedbench.sim_backends.modbus_devices import (
    SimulatedLoadCell, SimulatedModbusDevice, SimulatedModbusTcpServer, SimulatedSpindleInverter,
)
from feedbench.sim_backends.serial_daq import SimulatedSerialDaq
from feedbench.sim_backends.smfe_world import SmfeWorld, Workpiece, build_process, lanes_from_list
from feedbench.sim_backends.socketcand_hub import SocketcandHub
from feedbench.sim_backends.structure_world import StructureWorld, start_structure_world
from feedbench.sim_backends.world import build_axis, build_sensor_noise

READY = "feedbench-sim ready"
"""First word of the line `serve` prints once every device listens."""


SIM_PEER_GROUP = "feedbench.sim_devices"
"""Entry-point group of the simulated peers, one per device kind, by the kind's name."""


class DaqInputs:
    """The DAQ's 12 inputs fed by several worlds in one bus cycle: each world `push`es its
    samples (SI) as it would to the instrument; `flush()`, the last hook of the cycle, sends
    their sum to `daq` (a `SimulatedSerialDaq`); inputs no world drives read 0."""

    def __init__(self, daq: SimulatedSerialDaq) -> None:
        self.daq = daq
        self._sum: np.ndarray | None = None

    @property
    def samples_per_cycle(self) -> int:
        """Samples per bench cycle at the instrument's rate."""
        return self.daq.samples_per_cycle

    def push(self, samples: np.ndarray) -> None:
        """Add one world's samples of this cycle ((samples_per_cycle, 12), SI)."""
        self._sum = samples if self._sum is None else self._sum + samples

    def flush(self) -> None:
        """The cycle's summed samples to the instrument."""
        if self._sum is None:
            self._sum = np.zeros((self.samples_per_cycle, len(CHANNELS)))
        self.daq.push(self._sum)
        self._sum = None


class SimulatedPeer:
    """The simulated peer of one device kind (`devices.Device` of the same
    `name`), registered under that name in the entry-point group ``feedbench.sim_devices``.

    `SimulatedBench` constructs the peer of each device a run needs (`settings`: its checked
    ``[bench.devices.<name>]`` table with the family's settings over it, ``name`` included,
    `devices.device_table`) on the bench `sim`: it starts its device and
    transport there (`SimulatedBench.serve_modbus`, a pseudo-terminal, a node on
    `sim.drive`'s network) and puts its address under the device's name in `sim.addresses`.
    Once every peer exists, `attach()` hooks it into the world (the drive's `before_physics`
    / `after_physics`; a world two peers share looks the other up in `sim.peers`);
    `end_of_cycle`, if set, runs after every peer's hooks. `world`: its own
    ``[bench.world.<name>]`` table, checked against `world_schema` (`SimulatedBench`).
    """

    name: ClassVar[str]
    world_schema: ClassVar[Mapping[str, Field]] = {}
    """Its ``[bench.world.<name>]`` table: the simulated device's constants (engineering
    units), never read by the host."""
    old_world_keys: ClassVar[Mapping[str, str]] = {}
    """``[bench.world]`` keys of earlier versions that were its own → its table's key
    (`read_old_world_keys`)."""
    end_of_cycle: Callable[[], None] | None = None

    def __init__(self, sim: SimulatedBench, settings: Mapping[str, Any]) -> None:
        self.sim = sim
        self.settings = settings
        self.world = sim.peer_worlds[settings["name"]]

    def attach(self) -> None:
        """Hook into the world; nothing by default."""


def simulated_peers(distribution: str | None = None) -> dict[str, type[SimulatedPeer]]:
    """Every registered simulated peer by device kind (entry points of `SIM_PEER_GROUP`; of
    that installed `distribution` only, if given)."""
    return registered(SIM_PEER_GROUP, SimulatedPeer, distribution)


def read_old_world_keys(world: Mapping[str, Any], say: bool = True) -> dict[str, Any]:
    """A ``[bench.world]`` table with the keys of earlier versions (each a peer's
    `old_world_keys`) moved into ``<peer>``'s table; `say`: one line on stderr for each
    saying what to write instead."""
    out = {key: dict(value) if isinstance(value, dict) else value
           for key, value in world.items()}
    for name, peer in simulated_peers().items():
        for old, new in peer.old_world_keys.items():
            if old in out:
                value = out.pop(old)
                out.setdefault(name, {}).setdefault(new, value)
                if say:
                    print(f"feedbench: bench.world.{old} is read as bench.world.{name}.{new}; "
                          f"write [bench.world.{name}] {new} = {json.dumps(value)}",
                          file=sys.stderr)
    return out


def peer_worlds(world: Mapping[str, Any],
                tables: Mapping[str, Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """The ``[bench.world.<name>]`` tables of the simulated peers, each checked against its
    peer's `world_schema` (defaults filled in): one per registered peer kind and per device
    of `tables` (name → checked device table) whose kind has a peer."""
    known = simulated_peers()
    kinds = {**{kind: kind for kind in known},
             **{name: table["kind"] for name, table in tables.items() if table["kind"] in known}}
    return {name: validate_table(world.get(name, {}), known[kind].world_schema,
                                 f"bench.world.{name}") for name, kind in kinds.items()}


def milling_runs(peers: Mapping[str, SimulatedPeer]) -> bool:
    """The milling process runs where the spindle turns and the DAQ records its forces."""
    return "spindle" in peers and "daq" in peers


class SpindlePeer(SimulatedPeer):
    """The spindle inverter (Modbus, at its table's ``unit_id``); with the DAQ, the
    milling process it drives (`smfe_world.SmfeWorld`: the ``[bench.world.milling]`` table,
    cutting `sim.workpiece`), else the inverter's own speed ramp alone."""

    name = "spindle"
    world_schema = {"max_speed_rpm": Field(float, 6000.0, "overspeed trip (rpm)", positive),
                    "ramp_rpm_s": Field(float, 200.0, "ramp limit at power-up (rpm/s)",
                                        positive)}

    def __init__(self, sim: SimulatedBench, settings: Mapping[str, Any]) -> None:
        super().__init__(sim, settings)
        self.inverter = SimulatedSpindleInverter(settings["unit_id"], **self.world)
        self.milling: SmfeWorld | None = None
        sim.serve_modbus(self.inverter, settings["name"])

    def attach(self) -> None:
        sim = self.sim
        if not milling_runs(sim.peers):
            sim.drive.after_physics.append(lambda: self.inverter.advance(sim.cycle_s))
            return
        process, table = build_process(sim.world.get("milling", {}))
        lanes = lanes_from_list(sim.workpiece, "experiment.workpiece")
        self.milling = SmfeWorld(process, Workpiece(lanes),
                                 lambda: sim.drive.simulator.tip_position, self.inverter,
                                 sim.peers["daq"].inputs, sim.cycle_s, table["noise_m_s2"],
                                 table["seed"])
        sim.drive.after_physics.append(self.milling.step)


class LoadCellPeer(SimulatedPeer):
    """The load-cell amplifier (Modbus, at its table's ``unit_id``): the external force on
    the axis where the load cell sits (the drive's `tip_force`, N: on the lab axis what the
    exciters apply to the tool tip, on the rack-and-pinion axis the bumper's), sampled once
    per bus cycle."""

    name = "load_cell"
    world_schema = {"range_N": Field(float, 25000.0, "amplifier range (N)", positive),
                    "noise_std_N": Field(float, 2.0, "noise std (N)", non_negative)}
    old_world_keys = {"load_cell_range_N": "range_N", "load_cell_noise_N": "noise_std_N"}

    def __init__(self, sim: SimulatedBench, settings: Mapping[str, Any]) -> None:
        super().__init__(sim, settings)
        self.load_cell = SimulatedLoadCell(lambda: sim.drive.tip_force, settings["unit_id"],
                                           **self.world)
        sim.serve_modbus(self.load_cell, settings["name"])
        sim.drive.after_physics.append(lambda: self.load_cell.advance(sim.cycle_s))


CORRUPTION = {"crc": "flip", "desync": "truncate"}
"""The wire damage (`SimulatedSerialDaq.corrupt_next_frame`) of each serial fault."""


class DaqPeer(SimulatedPeer):
    """The streaming DAQ on a pseudo-terminal (its address); the worlds push their
    samples to `inputs`, summed and sent at the end of each cycle."""

    name = "daq"

    def __init__(self, sim: SimulatedBench, settings: Mapping[str, Any]) -> None:
        super().__init__(sim, settings)
        self.daq = SimulatedSerialDaq(sim.cycle_s)
        self.daq.answer_between_cycles(sim.drive.lock)  # samples pushed after the TPDOs
        sim.stack.callback(self.daq.close)
        sim.addresses[settings["name"]] = self.daq.port
        self.inputs = DaqInputs(self.daq)
        self.end_of_cycle = self._send

    def _send(self) -> None:
        """The cycle's samples to the host, through the serial faults of this cycle."""
        damage = self.sim.faults.serial_damage()
        if damage == "unplug":
            self.daq.unplug()
        elif damage:
            self.daq.corrupt_next_frame(CORRUPTION[damage])
        self.inputs.flush()


class ExciterPeer(SimulatedPeer):
    """The tool-tip exciters (`structure_world`: shaker, inertial actuator, impact hammer)
    commanded by a CiA 401 I/O module at node ``node_id`` (its table's), feeding the DAQ if
    there is one. Beside the milling process the accelerometers' noise is the milling
    table's (``noise_m_s2``), counted once: the structure table's accelerometer noise is not
    added to it."""

    name = "exciter"

    def __init__(self, sim: SimulatedBench, settings: Mapping[str, Any]) -> None:
        super().__init__(sim, settings)
        self.structure: StructureWorld | None = None

    def attach(self) -> None:
        sim = self.sim
        table = sim.world.get("structure", {})
        if milling_runs(sim.peers):
            table = {**table, "accelerometer_noise_m_s2": [0.0, 0.0, 0.0]}
        daq = sim.peers.get("daq")
        self.structure = start_structure_world(
            sim.drive, daq.inputs if daq is not None else None,
            self.settings["node_id"], table, sim.cycle_s)


class SimulatedBench:
    """The simulated axis of a validated ``[bench]`` table (the lab axis; another kind
    overrides `start_axis`) and the simulated peers of the devices a run needs (`tables`:
    name → checked table, `devices.device_table`;
    kinds without a registered peer are left to the drive); `close()` stops them.

    The drive (CiA 402 on its CAN bus, `bus_options` to python-can: ``host``, ``port`` of a
    socketcand server, or ``hub``, the `SocketcandHub` a ``feedbench_hub`` port joins)
    starts first, then each peer (`SimulatedPeer`); the peers on Modbus
    share one server on 127.0.0.1 at port ``modbus_address[1]`` (0: a free one). `addresses`:
    device name → where its peer is reached, as the host config would give it.
    `workpiece`: lane tables (mode, a_e_mm, a_p_mm, start_mm, stop_mm) a milling process
    cuts (the SMFE plan's ``workpiece``). `faults`: the world's ``faults`` table
    (`sim_backends.faults`), injected on the drive's bus, the Modbus server and the DAQ.
    """

    def __init__(self, bench: Mapping[str, Any], tables: Mapping[str, Mapping[str, Any]],
                 workpiece: Sequence[Mapping[str, Any]] = (),
                 bus_options: Mapping[str, Any] | None = None,
                 modbus_address: tuple[str, int] = (LOOPBACK, 0)) -> None:
        self.stack = ExitStack()
        self.bench = bench
        self.cycle_s = bench["cycle_ms"] * 1e-3
        self.world = read_old_world_keys(bench["world"])
        self.workpiece = workpiece
        self.addresses: dict[str, str] = {}
        self.modbus_devices: list[SimulatedModbusDevice] = []
        self._modbus_keys: set[str] = set()
        self.peers: dict[str, SimulatedPeer] = {}
        self.peer_worlds = peer_worlds(self.world, tables)
        axis_world = {key: table for key, table in self.world.items()
                      if key not in self.peer_worlds}
        try:
            self.faults = world_faults(axis_world)
            self.drive = self.start_axis(axis_world, bus_options or {})
            self.stack.callback(self.drive.close)
            self._answer_before_the_world(bus_options or {})
            self._start_peers(tables, modbus_address)
        except BaseException:
            self.stack.close()
            raise

    def start_axis(self, world: Mapping[str, Any], bus_options: Mapping[str, Any]) -> Any:
        """The simulated drives of the axis and its physics (`world`: the ``[bench.world]``
        keys no peer owns) on the bench's bus, with `self.faults`: what the peers see as
        `drive` (`lock`, `before_physics` / `after_physics` hooks, `tip_force`, `close()`).
        The lab axis: one CiA 402 drive; another axis kind's peer overrides it
        (`sim_backends.rack_pinion.RackPinionBench`)."""
        bench = self.bench
        return start_simulated_axis(bench["interface"], bench["channel"], bench["node_id"],
                                    build_axis(world, self.cycle_s),
                                    noise=build_sensor_noise(world), faults=self.faults,
                                    **bus_options)

    def _answer_before_the_world(self, bus_options: Mapping[str, Any]) -> None:
        """On a socketcand hub (``hub`` in `bus_options`), its frames held back in the
        drive's SYNC (`SocketcandHub.flush`) go out as the first of the drive's
        `after_physics` hooks: the cycle's TPDOs reach the host in one write, before the
        world steps."""
        hub = bus_options.get("hub")
        if hub is not None:
            self.drive.after_physics.insert(0, hub.flush)

    def _start_peers(self, tables: Mapping[str, Mapping[str, Any]],
                     modbus_address: tuple[str, int]) -> None:
        """Each needed device's peer, the Modbus server they share, their world hooks."""
        known = simulated_peers()
        for name, settings in tables.items():
            if settings["kind"] in known:
                self.peers[name] = known[settings["kind"]](self, settings)
        for device in self.modbus_devices:  # advanced by the drive's hooks, after its TPDOs
            device.answer_between_cycles(self.drive.lock)
        if self.modbus_devices:
            server = SimulatedModbusTcpServer(self.modbus_devices, port=modbus_address[1],
                                              faults=self.faults)
            address = "{}:{}".format(*server.start())
            self.stack.callback(server.stop)
            self.addresses.update(dict.fromkeys(self._modbus_keys, address))
        for peer in self.peers.values():
            peer.attach()
        self.drive.after_physics.extend(peer.end_of_cycle for peer in self.peers.values()
                                        if peer.end_of_cycle is not None)

    def serve_modbus(self, device: SimulatedModbusDevice, name: str) -> None:
        """Serve `device` (at its own device id) on the bench's Modbus server, whose address
        goes under the device's `name` in `addresses`."""
        self.modbus_devices.append(device)
        self._modbus_keys.add(name)

    def close(self) -> None:
        """Stop every device (in reverse order of starting)."""
        self.stack.close()

    def __enter__(self) -> SimulatedBench:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


StartBench = Callable[[Mapping[str, Any], Mapping[str, Any], ExitStack], dict[str, Any]]
"""Starts the simulated axis of a ``[bench]`` table with python-can options (closed by the
stack) and returns what the ready line says of it (`bench.start_served`)."""


def serve(bench: Mapping[str, Any], start: StartBench, out: TextIO = sys.stdout,
          stop: threading.Event | None = None) -> None:
    """Run the simulated bench until SIGINT / SIGTERM (or `stop` is set); print its addresses.

    The hub listens on ``bench.socketcand`` (``host:port``, port 0: a free one); `start`
    starts the axis and its peers on it. The ready line is ``feedbench-sim ready {json}``
    with ``socketcand``, ``channel`` and what `start` says: ``axis``, its node ids, ``modbus``
    (the peers' Modbus server), the Modbus devices served (``modbus_devices``: name →
    device id) and ``devices`` (name → what the host's table needs: address, unit id, node
    id). Log records go to stderr, one line each, meanwhile.
    """
    hub = SocketcandHub(*split_address(bench["socketcand"], "bench.socketcand", listen=True))
    host, port = hub.start()
    try:
        with one_line_logging(), ExitStack() as stack, _stop_requests(stop) as stopped:
            info = {"socketcand": f"{host}:{port}", "channel": bench["channel"],
                    **start({**bench, "interface": "feedbench_hub"}, {"hub": hub}, stack)}
            stack.callback(hub.stop)  # on exit first: no frame reaches a device as it closes
            print(f"{READY} {json.dumps(info)}", file=out)
            print(host_bench_table(info), file=out, flush=True)
            with frozen_heap():  # no 0.1 s full collection in the middle of the cycles
                while not stopped.wait(0.5):
                    pass
    finally:
        hub.stop()


def modbus_listen(tables: Mapping[str, Mapping[str, Any]]) -> tuple[str, int]:
    """Where `feedbench sim`'s one Modbus server listens: the address the Modbus devices'
    tables (those with a ``unit_id``) give, 127.0.0.1 on a free port if none does; two
    different ones are a `ConfigError` naming both fields."""
    given = {name: table["address"] for name, table in tables.items()
             if "unit_id" in table and table.get("address")}
    if len(set(given.values())) > 1:
        (first, a), (second, b) = sorted(given.items())[:2]
        raise ConfigError(f"bench.devices.{second}.address: {b} differs from "
                          f"bench.devices.{first}.address ({a}); the simulated bench serves "
                          "its Modbus devices on one server")
    if not given:
        return LOOPBACK, 0
    name, address = next(iter(given.items()))
    return split_address(address, f"bench.devices.{name}.address", listen=True)


def modbus_device_ids(devices: Sequence[SimulatedModbusDevice]) -> dict[str, int]:
    """The ready line's ``modbus_devices``: each device's register map name → device id."""
    return {device.register_map.device: device.device_id for device in devices}


HOST_KEYS = ("socketcand", "channel", "axis")
"""Ready-line keys that are [bench] keys of the host's config, printed first; then the
axis's node ids (the ready line's keys ending in ``node_id``) and its ``devices``."""


def host_bench_table(info: Mapping[str, Any]) -> str:
    """The [bench] table a host config needs to reach this simulated bench (TOML; the
    devices' tables as dotted keys, so that keys appended to it stay in [bench])."""
    nodes = [key for key in info if key.endswith("node_id")]
    devices = [f"devices.{name}.{key} = {json.dumps(value)}"
               for name, table in info.get("devices", {}).items() for key, value in table.items()]
    return "\n".join(["# host config: reach this simulated bench over loopback, as hardware",
                      "[bench]", "simulated = false", 'interface = "socketcand"',
                      'clock = "lockstep"',
                      *(f"{key} = {json.dumps(info[key])}" for key in (*HOST_KEYS, *nodes)
                        if key in info), *devices])


class OneLineFormatter(logging.Formatter):
    """A log record as one line: ``feedbench-sim: <level>: <logger>: <first line>``, an
    exception as its type and message (no traceback)."""

    def format(self, record: logging.LogRecord) -> str:
        text = record.getMessage()
        if record.exc_info and record.exc_info[1] is not None:
            error = record.exc_info[1]
            text = f"{text} ({type(error).__name__}: {error})"
        first = (text.strip().splitlines() or [""])[0]
        return f"feedbench-sim: {record.levelname.lower()}: {record.name}: {first}"


@contextmanager
def one_line_logging(stream: TextIO | None = None) -> Iterator[logging.Handler]:
    """While inside: warnings and errors of every logger, and exceptions no thread caught,
    as one line each on `stream` (stderr); the previous setup returns afterwards."""
    handler = logging.StreamHandler(stream or sys.stderr)
    handler.setLevel(logging.WARNING)
    handler.setFormatter(OneLineFormatter())
    root = logging.getLogger()
    previous_hook = threading.excepthook
    root.addHandler(handler)
    threading.excepthook = _log_thread_exception
    try:
        yield handler
    finally:
        threading.excepthook = previous_hook
        root.removeHandler(handler)


def _log_thread_exception(args: threading.ExceptHookArgs) -> None:
    """An exception that ended a thread: one error line, no traceback."""
    name = args.thread.name if args.thread is not None else "?"
    logging.getLogger(__name__).error("thread %s stopped: %s: %s", name,
                                      args.exc_type.__name__, args.exc_value)


@contextmanager
def _stop_requests(stop: threading.Event | None) -> Iterator[threading.Event]:
    """While inside: `stop`, or (None) an event that SIGINT / SIGTERM set (from before the
    ready line, so a stop asked for as soon as it is read is a clean exit); the previous
    handlers return."""
    if stop is not None:
        yield stop
        return
    stopped = threading.Event()
    previous = {signum: signal.signal(signum, lambda *_: stopped.set())
                for signum in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stopped
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
