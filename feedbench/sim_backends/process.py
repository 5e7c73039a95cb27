"""The whole simulated bench, in the host's process or as its own (`feedbench sim BENCH.toml`).

`SimulatedBench` starts every simulated device of a lab-axis ``[bench]`` table on its real
transport: the CiA 402 drive on its CAN bus, and with the peripherals one Modbus TCP server
on 127.0.0.1 for the spindle inverter (device id 1) and the load-cell amplifier (device id 2),
the streaming DAQ (a pseudo-terminal) and the worlds at the tool tip that feed it: the
milling process (`smfe_world.SmfeWorld`) and/or the exciters with their CiA 401 I/O module
(`structure_world`), summed on the DAQ's inputs (`DaqInputs`), stepped in the drive's SYNC
handler after the axis physics. Virtual time stays lockstep: the host's SYNC advances the
world one bus cycle.

`serve` runs a bench as a separate process that the host reaches only over loopback, exactly
as it would reach hardware: CAN through a socketcand hub (`socketcand_hub.SocketcandHub`,
python-can's ``socketcand`` interface on both sides), Modbus TCP on 127.0.0.1, the DAQ on the
printed pseudo-terminal path. The lab axis serves every device (both worlds on one DAQ);
``axis = "rack_pinion"`` serves the master and slave drives and the bumper's load cell
(`rack_pinion.SimulatedRackPinionAxis`). It prints one JSON line with the addresses, then
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
from typing import Any, TextIO

import numpy as np

from feedbench.protocols.address import LOOPBACK, split_address
from feedbench.sim_backends.bench import start_simulated_axis
from feedbench.sim_backends.modbus_devices import (
    SimulatedLoadCell, SimulatedModbusDevice, SimulatedModbusTcpServer, SimulatedSpindleInverter,
)
from feedbench.sim_backends.rack_pinion import (
    SimulatedRackPinionAxis, build_simulator, load_cell_settings,
)
from feedbench.sim_backends.serial_daq import SimulatedSerialDaq
from feedbench.sim_backends.smfe_world import SmfeWorld, Workpiece, build_process, lanes_from_list
from feedbench.sim_backends.socketcand_hub import SocketcandHub
from feedbench.sim_backends.structure_world import StructureWorld, start_structure_world
from feedbench.sim_backends.world import build_axis, build_sensor_noise

READY = "feedbench-sim ready"
"""First word of the line `serve` prints once every device listens."""


class DaqInputs:
    """The DAQ's 12 inputs fed by several worlds in one bus cycle: each world `push`es its
    samples (SI) as it would to the instrument; `flush()`, the last hook of the cycle, sends
    their sum to `daq` (a `SimulatedSerialDaq`)."""

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
        if self._sum is not None:
            self.daq.push(self._sum)
            self._sum = None


class SimulatedBench:
    """The simulated devices of a validated lab-axis ``[bench]`` table; `close()` stops them.

    `workpiece`: lane tables (mode, a_e_mm, a_p_mm, start_mm, stop_mm) the milling process
    cuts (the SMFE plan's ``workpiece``); `peripherals`: also start the inverter, the load
    cell, the DAQ and the worlds at the tool tip (an experiment on the drive alone does
    without them); `bus_options` go to python-can (``host``, ``port`` of a socketcand server);
    `modbus_address`: where the Modbus server listens (port 0: a free one). `exciter_node`:
    the lab bench's tool-tip exciters (`structure_world`: shaker, inertial actuator, impact
    hammer, commanded by a CiA 401 I/O module at this node id) feed the DAQ; `milling`: the
    milling process feeds it. With both, the accelerometers' noise is the milling table's
    (``noise_m_s2``), once; the structure table's accelerometer noise is not added to it.
    The load cell measures the force the exciters apply to the tool tip (the drive's
    `tip_force`, N), sampled once per bus cycle.
    """

    def __init__(self, bench: Mapping[str, Any], workpiece: Sequence[Mapping[str, Any]] = (),
                 peripherals: bool = True, bus_options: Mapping[str, Any] | None = None,
                 modbus_address: tuple[str, int] = (LOOPBACK, 0),
                 exciter_node: int | None = None, milling: bool = True) -> None:
        self._stack = ExitStack()
        cycle_s = bench["cycle_ms"] * 1e-3
        world = bench["world"]
        self.modbus_address: tuple[str, int] | None = None
        self.daq_port: str | None = None
        self.modbus_devices: list[SimulatedModbusDevice] = []
        self.structure: StructureWorld | None = None
        self.milling: SmfeWorld | None = None
        try:
            simulator = build_axis(world, cycle_s)
            process, milling_table = build_process(world.get("milling", {}))
            lanes = lanes_from_list(workpiece, "experiment.workpiece")
            self.drive = start_simulated_axis(bench["interface"], bench["channel"],
                                              bench["node_id"], simulator,
                                              noise=build_sensor_noise(world),
                                              **(bus_options or {}))
            self._stack.callback(self.drive.close)
            if peripherals:
                self._start_peripherals(cycle_s, modbus_address)
                inputs = DaqInputs(self.daq)
                if exciter_node is not None:
                    self._start_structure(world.get("structure", {}), inputs, exciter_node,
                                          milling, cycle_s)
                if milling:
                    self.milling = SmfeWorld(process, Workpiece(lanes),
                                             lambda: simulator.tip_position, self.inverter,
                                             inputs, cycle_s, milling_table["noise_m_s2"],
                                             milling_table["seed"])
                    self.drive.after_physics.append(self.milling.step)
                self.drive.after_physics.append(inputs.flush)
        except BaseException:
            self._stack.close()
            raise

    def _start_structure(self, table: Mapping[str, Any], inputs: DaqInputs, node_id: int,
                         with_milling: bool, cycle_s: float) -> None:
        """The exciters' world and its I/O module; beside the milling process its
        accelerometer noise is left to the milling world's (counted once)."""
        if with_milling:
            table = {**table, "accelerometer_noise_m_s2": [0.0, 0.0, 0.0]}
        self.structure = start_structure_world(self.drive, inputs, node_id, table, cycle_s)

    def _start_peripherals(self, cycle_s: float, modbus_address: tuple[str, int]) -> None:
        self.inverter = SimulatedSpindleInverter()
        self.load_cell = SimulatedLoadCell(lambda: self.drive.tip_force)
        self.drive.after_physics.append(lambda: self.load_cell.advance(cycle_s))
        self.modbus_devices = [self.inverter, self.load_cell]
        server = SimulatedModbusTcpServer(self.modbus_devices, port=modbus_address[1])
        self.modbus_address = server.start()
        self._stack.callback(server.stop)
        self.daq = SimulatedSerialDaq(cycle_s)
        self._stack.callback(self.daq.close)
        self.daq_port = self.daq.port

    def close(self) -> None:
        """Stop every device (in reverse order of starting)."""
        self._stack.close()

    def __enter__(self) -> SimulatedBench:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def serve(bench: Mapping[str, Any], workpiece: Sequence[Mapping[str, Any]] = (),
          out: TextIO = sys.stdout, stop: threading.Event | None = None) -> None:
    """Run the simulated bench until SIGINT / SIGTERM (or `stop` is set); print its addresses.

    The hub listens on ``bench.socketcand`` and the Modbus server on ``bench.modbus``
    (``host:port``, port 0: a free one); the ready line is ``feedbench-sim ready {json}``
    with ``socketcand``, ``channel``, ``axis``, the node ids, ``modbus`` and the Modbus
    devices served (``modbus_devices``: name → device id), and per axis ``daq_port`` (lab)
    or ``load_cell`` (rack_pinion). Log records go to stderr, one line each, meanwhile.
    """
    hub = SocketcandHub(*split_address(bench["socketcand"], "bench.socketcand", listen=True))
    host, port = hub.start()
    try:
        with one_line_logging(), ExitStack() as stack:
            info = {"socketcand": f"{host}:{port}", "channel": bench["channel"],
                    **_start_bench({**bench, "interface": "socketcand"}, workpiece,
                                   {"host": host, "port": port}, stack)}
            print(f"{READY} {json.dumps(info)}", file=out)
            print(host_bench_table(info), file=out, flush=True)
            _wait_for_stop(stop)
    finally:
        hub.stop()


def _start_bench(bench: Mapping[str, Any], workpiece: Sequence[Mapping[str, Any]],
                 bus_options: Mapping[str, Any], stack: ExitStack) -> dict[str, Any]:
    """Start the bench of ``bench.axis`` (closed by `stack`); what the ready line says of it."""
    modbus = split_address(bench["modbus"], "bench.modbus", listen=True)
    if bench["axis"] == "rack_pinion":
        axis = SimulatedRackPinionAxis(
            build_simulator(bench["world"], bench["cycle_ms"] * 1e-3), bench["interface"],
            bench["channel"], (bench["node_id"], bench["slave_node_id"]),
            load_cell_settings(bench["world"]), modbus_port=modbus[1], **bus_options)
        stack.callback(axis.close)
        address = "{}:{}".format(*axis.modbus_address)
        return {"axis": "rack_pinion", "node_id": bench["node_id"],
                "slave_node_id": bench["slave_node_id"], "modbus": address,
                "modbus_devices": _device_ids([axis.load_cell]), "load_cell": address}
    simulated = stack.enter_context(SimulatedBench(
        bench, workpiece, bus_options=bus_options, modbus_address=modbus,
        exciter_node=bench["io_node_id"], milling=True))
    return {"axis": "lab", "node_id": bench["node_id"], "io_node_id": bench["io_node_id"],
            "modbus": "{}:{}".format(*simulated.modbus_address),
            "modbus_devices": _device_ids(simulated.modbus_devices),
            "daq_port": simulated.daq_port}


def _device_ids(devices: Sequence[SimulatedModbusDevice]) -> dict[str, int]:
    return {device.register_map.device: device.device_id for device in devices}


HOST_KEYS = ("socketcand", "channel", "axis", "node_id", "slave_node_id", "modbus",
             "load_cell", "daq_port")
"""Ready-line keys that are [bench] keys of the host's config, in the order printed."""


def host_bench_table(info: Mapping[str, Any]) -> str:
    """The [bench] table a host config needs to reach this simulated bench (TOML)."""
    lines = ["# host config: reach this simulated bench over loopback, as hardware",
             "[bench]", "simulated = false", 'interface = "socketcand"', 'clock = "lockstep"',
             *(f"{key} = {json.dumps(info[key])}" for key in HOST_KEYS if key in info)]
    if "io_node_id" in info:
        lines.append(f"# tool-tip exciters: [experiment] io_node_id = {info['io_node_id']}")
    return "\n".join(lines)


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


def _wait_for_stop(stop: threading.Event | None) -> None:
    """Until `stop` is set, or (None) until SIGINT / SIGTERM; the previous handlers return."""
    if stop is not None:
        stop.wait()
        return
    stopped = threading.Event()
    previous = {signum: signal.signal(signum, lambda *_: stopped.set())
                for signum in (signal.SIGINT, signal.SIGTERM)}
    try:
        while not stopped.wait(0.5):
            pass
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
