"""The wiring of the rack-and-pinion axis (``[bench] axis = "rack_pinion"``): two CiA 402 drives.

Part of the composition root: `feedbench.bench.Bench` runs the same steps for every axis
kind and asks this class what differs. Simulated (``simulated = true``), the peer is the
simulated axis (master and slave nodes on one bus sharing one world, Ch. 3.2, the bumper's
load cell on a Modbus server on 127.0.0.1); the drives are the master and the slave node,
with the axis's PDO maps; the per-cycle devices are the axis controller's settings, the
encoders and the load cell (`experiments.rack_pinion_io`).
"""

from __future__ import annotations

from contextlib import ExitStack
from typing import Any, Mapping

import canopen

from feedbench.drivers.cia402 import Cia402Drive
from feedbench.drivers.modbus_devices import LoadCellAmplifier, connect_tcp
from feedbench.drivers.rack_pinion import AXIS_PDOS, AxisController
from feedbench.experiments.plan import Plan
from feedbench.experiments.rack_pinion_io import AxisEncoders, AxisSettings, LoadCellForce
from feedbench.protocols.address import split_address

LOAD_CELL_ID = 2
"""Modbus device id of the load-cell amplifier (the simulated one's default)."""


class RackPinionAxis:
    """Master (``node_id``) and slave (``slave_node_id``) drives of the validated ``[bench]``
    table `cfg`, the load cell at ``load_cell`` (host:port) every ``load_cell_every`` cycles;
    the same whatever the `plan` and its experiment's `needs` (taken as by every axis kind
    of `bench.AXES`)."""

    pdo_config = AXIS_PDOS

    def __init__(self, cfg: Mapping[str, Any], plan: Plan | None,
                 needs: Mapping[str, dict]) -> None:
        self.cfg = cfg

    def nodes(self) -> dict[str, int]:
        """Drive name → CANopen node id."""
        return {"master": self.cfg["node_id"], "slave": self.cfg["slave_node_id"]}

    @staticmethod
    def packaged_eds() -> str:
        """The simulated axis's EDS (the drive's objects plus the axis's)."""
        from feedbench.sim_backends.rack_pinion import packaged_eds_path

        return str(packaged_eds_path())

    def start_simulated(self, cycle_s: float, bus_options: Mapping[str, Any]):
        """Both simulated nodes, their world and the load cell's server; `close()` stops them."""
        from feedbench.sim_backends.rack_pinion import (
            SimulatedRackPinionAxis, build_simulator, load_cell_settings,
        )

        cfg = self.cfg
        return SimulatedRackPinionAxis(
            build_simulator(cfg["world"], cycle_s), cfg["interface"], cfg["channel"],
            (cfg["node_id"], cfg["slave_node_id"]),
            {"device_id": LOAD_CELL_ID, **load_cell_settings(cfg["world"])}, **bus_options)

    def devices(self, drives: Mapping[str, Cia402Drive], simulated: Any, stack: ExitStack,
                network: canopen.Network) -> list:
        """Axis settings, encoders and load cell (the simulated axis's server, else the
        configured one); `stack` closes the Modbus client."""
        address = (simulated.modbus_address if simulated is not None
                   else split_address(self.cfg["load_cell"], "bench.load_cell"))
        client = connect_tcp(*address)
        stack.callback(client.close)
        return [AxisSettings(AxisController(drives["master"])), AxisEncoders(drives),
                LoadCellForce(LoadCellAmplifier(client, LOAD_CELL_ID),
                              self.cfg["load_cell_every"])]
