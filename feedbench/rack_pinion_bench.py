"""The bench's rack-and-pinion axis (``[bench] axis = "rack_pinion"``): two CiA 402 drives.

Part of the composition root (`feedbench.bench`): with ``simulated = true`` it starts the
simulated axis (master and slave nodes on one bus sharing one world, the bumper's load
cell on a Modbus server on 127.0.0.1); then, as against hardware, it configures both
drives by SDO, builds one clock over both and opens the axis devices the runner serves
every cycle: the axis controller's settings, the encoders and the load cell.
"""

from __future__ import annotations

from contextlib import ExitStack
from dataclasses import dataclass, field
from typing import Any, Mapping

import canopen

from feedbench.daq.clock import LockstepClock, RealtimeClock
from feedbench.drivers.cia402 import Cia402Drive
from feedbench.drivers.modbus_devices import LoadCellAmplifier, connect_tcp
from feedbench.drivers.rack_pinion import AXIS_PDOS, AxisController
from feedbench.experiments.rack_pinion_io import AxisEncoders, AxisSettings, LoadCellForce
from feedbench.protocols.address import split_address
from feedbench.protocols.canbus import open_network

LOAD_CELL_ID = 2
"""Modbus device id of the load-cell amplifier (the simulated one's default)."""


@dataclass
class RackPinionBench:
    """What the bench holds for the axis: network, drives by name, clock, per-cycle devices."""

    network: canopen.Network
    drives: dict[str, Cia402Drive]
    clock: LockstepClock | RealtimeClock
    devices: list = field(default_factory=list)
    simulated: Any = None


def _start_simulated(cfg: Mapping[str, Any], cycle_s: float, stack: ExitStack,
                     bus_options: Mapping[str, Any]):
    from feedbench.sim_backends.rack_pinion import (
        SimulatedRackPinionAxis, build_simulator, load_cell_settings,
    )

    simulated = SimulatedRackPinionAxis(
        build_simulator(cfg["world"], cycle_s), cfg["interface"], cfg["channel"],
        (cfg["node_id"], cfg["slave_node_id"]),
        {"device_id": LOAD_CELL_ID, **load_cell_settings(cfg["world"])}, **bus_options)
    stack.callback(simulated.close)
    return simulated


def _packaged_eds() -> str:
    from feedbench.sim_backends.rack_pinion import packaged_eds_path

    return str(packaged_eds_path())


def open_rack_pinion(cfg: Mapping[str, Any], cycle_s: float, gains: Mapping[str, float],
                     stack: ExitStack, bus_options: Mapping[str, Any]) -> RackPinionBench:
    """Open the axis of the validated ``[bench]`` table `cfg`; `stack` closes everything."""
    simulated = _start_simulated(cfg, cycle_s, stack, bus_options) if cfg["simulated"] else None
    network = open_network(cfg["interface"], cfg["channel"], cfg["bitrate"], **bus_options)
    stack.callback(network.disconnect)
    eds = cfg["eds"] or _packaged_eds()
    drives = {name: Cia402Drive(network, node_id, eds, AXIS_PDOS)
              for name, node_id in (("master", cfg["node_id"]), ("slave", cfg["slave_node_id"]))}
    for drive in drives.values():
        drive.configure(gains=dict(gains) or None)
    if cfg["clock"] == "lockstep":
        clock = LockstepClock(network, list(drives.values()), timeout_s=cfg["timeout_s"])
    else:
        clock = RealtimeClock(network, list(drives.values()), period_s=cycle_s)
    address = (simulated.modbus_address if simulated is not None
               else split_address(cfg["load_cell"], "bench.load_cell"))
    client = connect_tcp(*address)
    stack.callback(client.close)
    devices = [AxisSettings(AxisController(drives["master"])), AxisEncoders(drives),
               LoadCellForce(LoadCellAmplifier(client, LOAD_CELL_ID), cfg["load_cell_every"])]
    return RackPinionBench(network, drives, clock, devices, simulated)
