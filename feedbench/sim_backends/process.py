"""The whole simulated bench, in the host's process or as its own (`feedbench sim BENCH.toml`).

`SimulatedBench` starts every simulated device of a ``[bench]`` table on its real transport:
the CiA 402 drive on its CAN bus, and with the peripherals the spindle inverter (a Modbus TCP
server on 127.0.0.1), the streaming DAQ (a pseudo-terminal) and the milling process at the
tool (`smfe_world.SmfeWorld`), stepped in the drive's SYNC handler after the axis physics.
Virtual time stays lockstep: the host's SYNC advances the world one bus cycle.

`serve` runs it as a separate process that the host reaches only over loopback, exactly as
it would reach hardware: CAN through a socketcand hub (`socketcand_hub.SocketcandHub`, python-
can's ``socketcand`` interface on both sides), Modbus TCP on 127.0.0.1, the DAQ on the printed
pseudo-terminal path. It prints one JSON line with the addresses, then serves until SIGINT or
SIGTERM.
"""

from __future__ import annotations

import json
import signal
import sys
import threading
from collections.abc import Mapping, Sequence
from contextlib import ExitStack
from typing import Any, TextIO

from feedbench.sim_backends.bench import start_simulated_axis
from feedbench.sim_backends.modbus_devices import SimulatedModbusTcpServer, SimulatedSpindleInverter
from feedbench.sim_backends.serial_daq import SimulatedSerialDaq
from feedbench.sim_backends.smfe_world import SmfeWorld, Workpiece, build_process, lanes_from_list
from feedbench.sim_backends.socketcand_hub import LOOPBACK, SocketcandHub
from feedbench.sim_backends.structure_world import StructureWorld, start_structure_world
from feedbench.sim_backends.world import build_axis, build_sensor_noise

READY = "feedbench-sim ready"
"""First word of the line `serve` prints once every device listens."""


def split_address(address: str, default_port: int = 0) -> tuple[str, int]:
    """``host:port`` (or ``host``) → (host, port)."""
    host, _, port = address.rpartition(":") if ":" in address else (address, "", "")
    return host or LOOPBACK, int(port) if port else default_port


class SimulatedBench:
    """The simulated devices of a validated ``[bench]`` table; `close()` stops them all.

    `workpiece`: lane tables (mode, a_e_mm, a_p_mm, start_mm, stop_mm) the milling process
    cuts (the SMFE plan's ``workpiece``); `peripherals`: also start the inverter, the DAQ and
    the milling world (an experiment on the drive alone does without them); `bus_options`
    go to python-can (``host``, ``port`` of a socketcand server); `modbus_address`: where the
    Modbus server listens (port 0: a free one). `exciter_node`: instead of the milling world,
    the lab bench's tool-tip devices (`structure_world`: shaker, inertial actuator, impact
    hammer, commanded by a CiA 401 I/O module at this node id) feed the DAQ.
    """

    def __init__(self, bench: Mapping[str, Any], workpiece: Sequence[Mapping[str, Any]] = (),
                 peripherals: bool = True, bus_options: Mapping[str, Any] | None = None,
                 modbus_address: tuple[str, int] = (LOOPBACK, 0),
                 exciter_node: int | None = None) -> None:
        self._stack = ExitStack()
        cycle_s = bench["cycle_ms"] * 1e-3
        world = bench["world"]
        self.modbus_address: tuple[str, int] | None = None
        self.daq_port: str | None = None
        self.world: SmfeWorld | StructureWorld | None = None
        try:
            simulator = build_axis(world, cycle_s)
            process, milling = build_process(world.get("milling", {}))
            lanes = lanes_from_list(workpiece, "experiment.workpiece")
            self.drive = start_simulated_axis(bench["interface"], bench["channel"],
                                              bench["node_id"], simulator,
                                              noise=build_sensor_noise(world),
                                              **(bus_options or {}))
            self._stack.callback(self.drive.close)
            if peripherals and exciter_node is not None:
                self._start_peripherals(cycle_s, modbus_address)
                self.world = start_structure_world(self.drive, self.daq, exciter_node,
                                                   world.get("structure", {}), cycle_s)
            elif peripherals:
                self._start_peripherals(cycle_s, modbus_address)
                self.world = SmfeWorld(process, Workpiece(lanes), lambda: simulator.tip_position,
                                       self.inverter, self.daq, cycle_s, milling["noise_m_s2"],
                                       milling["seed"])
                self.drive.after_physics.append(self.world.step)
        except BaseException:
            self._stack.close()
            raise

    def _start_peripherals(self, cycle_s: float, modbus_address: tuple[str, int]) -> None:
        self.inverter = SimulatedSpindleInverter()
        server = SimulatedModbusTcpServer([self.inverter], port=modbus_address[1])
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
    with ``socketcand``, ``channel``, ``modbus``, ``daq_port`` and ``node_id``.
    """
    hub = SocketcandHub(*split_address(bench["socketcand"]))
    host, port = hub.start()
    try:
        with SimulatedBench({**bench, "interface": "socketcand"}, workpiece,
                            bus_options={"host": host, "port": port},
                            modbus_address=split_address(bench["modbus"])) as simulated:
            modbus_host, modbus_port = simulated.modbus_address
            info = {"socketcand": f"{host}:{port}", "channel": bench["channel"],
                    "modbus": f"{modbus_host}:{modbus_port}", "daq_port": simulated.daq_port,
                    "node_id": bench["node_id"]}
            print(f"{READY} {json.dumps(info)}", file=out)
            print(host_bench_table(info), file=out, flush=True)
            _wait_for_stop(stop)
    finally:
        hub.stop()


def host_bench_table(info: Mapping[str, Any]) -> str:
    """The [bench] table a host config needs to reach this simulated bench (TOML)."""
    return "\n".join([
        "# host config: reach this simulated bench over loopback, as hardware",
        "[bench]", "simulated = false", 'interface = "socketcand"', 'clock = "lockstep"',
        *(f'{key} = {json.dumps(info[key])}' for key in
          ("socketcand", "channel", "node_id", "modbus", "daq_port"))])


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
