"""The wiring of the rack-and-pinion axis (``[bench] axis = "rack_pinion"``): two CiA 402 drives.

The axis kind (`axes.Axis`, entry point ``rack_pinion`` of ``feedbench.axes``):
`feedbench.bench.Bench` runs the same steps for every axis kind and asks this class what
differs; its own ``[bench]`` key is ``slave_node_id``. Simulated (``simulated = true``), the
peer is the simulated axis (master and slave nodes on one bus sharing one world, Ch. 3.2,
the bumper's load cell on a Modbus server on 127.0.0.1); the drives are the master and the
slave node, with the axis's PDO maps; the per-cycle devices are the axis controller's
settings, the encoders and the load cell (`experiments.rack_pinion_io`), whose device kinds
(`experiments.devices.Device`: ``axis_settings``, ``encoders``, ``load_cell``) are here.
"""

from __future__ import annotations

from typing import Any, Mapping

from feedbench.axes import Axis
from feedbench.config import Field, positive
from feedbench.drivers.modbus_devices import LoadCellAmplifier
from feedbench.drivers.rack_pinion import AXIS_PDOS, AxisController
from feedbench.experiments.devices import Device, DeviceLinks
from feedbench.experiments.rack_pinion_io import AxisEncoders, AxisSettings, LoadCellForce


class AxisSettingsDevice(Device):
    """The axis controller's coupling, preload and weights, set by SDO on the master drive
    from the plan's commands (`rack_pinion_io.AxisSettings`)."""

    name = "axis_settings"

    @classmethod
    def open(cls, settings: Mapping[str, Any], links: DeviceLinks) -> AxisSettings:
        return AxisSettings(AxisController(links.drives["master"]))


class EncodersDevice(Device):
    """Both motor encoders and the linear scale from the drives' TPDOs
    (`rack_pinion_io.AxisEncoders`)."""

    name = "encoders"

    @classmethod
    def open(cls, settings: Mapping[str, Any], links: DeviceLinks) -> AxisEncoders:
        return AxisEncoders(links.drives)


class LoadCellDevice(Device):
    """The bumper's load-cell amplifier over Modbus TCP (``address``, unit ``unit_id``),
    read every ``every_cycles`` bus cycles (`rack_pinion_io.LoadCellForce`)."""

    name = "load_cell"
    address_doc = "host:port of the load-cell amplifier's Modbus TCP server"
    unit_id = 2
    schema = {"every_cycles": Field(int, 1, "read the load cell every n bus cycles",
                                    positive)}
    old_keys = {"load_cell": "address", "load_cell_every": "every_cycles"}

    @classmethod
    def open(cls, settings: Mapping[str, Any], links: DeviceLinks) -> LoadCellForce:
        amplifier = LoadCellAmplifier(cls.modbus_client(settings, links), settings["unit_id"])
        return LoadCellForce(amplifier, settings["every_cycles"])


class RackPinionAxis(Axis):
    """Master (``node_id``) and slave (``slave_node_id``) drives of the validated ``[bench]``
    table `cfg`; its devices: the axis settings, the encoders and the load cell
    (``[bench.devices.load_cell]``), whatever the family, and the devices the plan's
    experiment needs besides."""

    name = "rack_pinion"
    schema = {"slave_node_id": Field(int, 2, "rack_pinion: CANopen node id of the slave "
                                     "drive", positive)}
    devices = {"axis_settings": {}, "encoders": {}, "load_cell": {}}
    pdo_config = AXIS_PDOS
    stop_margin_s = 2.0
    """Default ``[bench.stop] margin_s`` (s): the coupled axis held at its setpoint after a
    1 m/s² stop from 1500 mm/min stood (|v| < 5 mm/min for 10 cycles) after 1.05 s; quick
    stopped from 50 mm/min after 0.79 s."""

    def nodes(self) -> dict[str, int]:
        """Drive name → CANopen node id."""
        return {"master": self.cfg["node_id"], "slave": self.cfg["slave_node_id"]}

    @staticmethod
    def packaged_eds() -> str:
        """The simulated axis's EDS (the drive's objects plus the axis's)."""
        from feedbench.sim_backends.rack_pinion import packaged_eds_path

        return str(packaged_eds_path())

    def start_simulated(self, cycle_s: float, bus_options: Mapping[str, Any],
                        tables: Mapping[str, Mapping[str, Any]], listen: bool = False):
        """Both simulated nodes, their world and the load cell's server (at the unit id of
        `tables`' load cell; `listen`: at its address); `close()` stops them."""
        from feedbench.sim_backends.faults import world_faults
        from feedbench.sim_backends.process import modbus_listen
        from feedbench.sim_backends.rack_pinion import (
            SimulatedRackPinionAxis, build_simulator, load_cell_settings,
        )

        cfg = self.cfg
        return SimulatedRackPinionAxis(
            build_simulator(cfg["world"], cycle_s), cfg["interface"], cfg["channel"],
            (cfg["node_id"], cfg["slave_node_id"]),
            {"device_id": tables["load_cell"]["unit_id"], **load_cell_settings(cfg["world"])},
            modbus_port=modbus_listen(tables)[1] if listen else 0,
            faults=world_faults(cfg["world"]), **bus_options)

    @staticmethod
    def addresses(simulated: Any) -> dict[str, str]:
        """Device name → where the simulated axis listens (its load cell)."""
        return {"load_cell": "{}:{}".format(*simulated.modbus_address)}
