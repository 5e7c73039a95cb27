"""The rack-and-pinion axis (``[bench] axis = "rack_pinion"``), host side, in one module:
two CiA 402 drives, the axis controller, the per-cycle devices and their kinds, the axis kind.

- The drives' PDO maps and the axis controller (`AXIS_PDOS`, `AxisController`): the
  controller's objects (`protocols.rack_pinion`) answer on the master node and are written
  by SDO between bus cycles; each node's TPDO 3 carries its motor encoder and the linear
  scale, so the host records x_m, x_s and x_load synchronously with the statusword,
  position, velocity and force of both drives.
- The per-cycle devices (`runner.CycleDevice`, each on `devices.PerCycleDevice`: it raises
  on its first failure, the runner aborts the run, and goes silent afterwards, so the
  drives' safe stop never waits on a broken link):
  `AxisSettings`, a plan segment whose commands hold ``coupling`` (coupled, master, slave)
  or ``preload_pct`` (and optionally ``K_Tm``, ``K_Ts``) sets the axis controller by SDO in
  the cycle the segment starts, as the thesis reconfigured its CNC between tests (Ch. 3.4;
  the commands stay in the segment's event, so the recording tells each test's setup);
  `AxisEncoders`, both motor encoders and the linear scale, recorded as
  ``master.motor_position``, ``slave.motor_position``, ``load_position`` (m);
  `LoadCellForce`, the bumper's load cell over Modbus every `every_cycles` (NaN between
  readings, so no value is ever stale), recorded as ``load_cell.force`` (N), a reading
  beyond the amplifier's range aborts the run (`LoadCellOverload`).
- Their device kinds (`devices.Device`: ``axis_settings``, ``encoders``,
  ``load_cell``) and the axis kind (`axes.Axis`, entry point ``rack_pinion`` of
  ``feedbench.axes``): `feedbench.bench.Bench` runs the same steps for every axis kind and
  asks `RackPinionAxis` what differs; its own ``[bench]`` key is ``slave_node_id``.

Its simulated peer is one module too, `sim_backends.rack_pinion` (master and slave nodes on
one bus sharing one world, Ch. 3.2, and the registered peers of the run's devices: the
bumper's load cell on the bench's Modbus server on 127.0.0.1); the physics is
`models.rack_pinion`, the objects both ends share `protocols.rack_pinion`.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

from feedbench.axes import Axis
from feedbench.config import Field, positive
from feedbench.drivers.cia402 import Cia402Drive, DriveError, PdoConfig
from feedbench.drivers.modbus_devices import LoadCellAmplifier
from feedbench.devices import Device, DeviceLinks, PerCycleDevice
from feedbench.engine.plan import Plan
from feedbench.protocols import rack_pinion as objects
from feedbench.protocols.cia402 import (
    CONTROLWORD, CYCLE_COUNTER, FORCE_ACTUAL, POSITION_ACTUAL, STATUSWORD, TARGET_POSITION,
    TARGET_VELOCITY, TORQUE_OFFSET, VELOCITY_ACTUAL, VELOCITY_OFFSET,
)

# -- the drives and the axis controller ------------------------------------------------------

AXIS_PDOS = PdoConfig(
    rpdo={
        1: (CONTROLWORD, TARGET_POSITION, TORQUE_OFFSET),  # torque offset in ‰
        2: (TARGET_VELOCITY, VELOCITY_OFFSET),
    },
    tpdo={
        1: (STATUSWORD, POSITION_ACTUAL, CYCLE_COUNTER),  # position actual: the axis
        2: (VELOCITY_ACTUAL, FORCE_ACTUAL),  # motor velocity, motor force at the rack (mN)
        3: objects.AXIS_TPDO,  # motor encoder at the rack, linear scale (nm)
    },
)
"""PDO maps of both nodes: two full RPDOs per cycle (the mode of operation goes by SDO),
three TPDOs; 11 frames per bus cycle with the SYNC."""


class AxisController:
    """The master–slave coupling of the axis, set through the master node (SDO)."""

    def __init__(self, master: Cia402Drive) -> None:
        self.sdo = master.node.sdo

    def set_coupling(self, coupling: str) -> None:
        """``coupled`` (master–slave with preload), ``master`` or ``slave`` (alone)."""
        if coupling not in objects.COUPLINGS:
            raise DriveError(f"coupling must be one of {', '.join(objects.COUPLINGS)}, "
                             f"got {coupling!r}")
        self.sdo[objects.COUPLING].raw = objects.COUPLINGS[coupling]

    def set_preload(self, fraction: float) -> None:
        """Preload τ_p as a fraction of the motors' rated torque (0x2040 in ‰)."""
        self.sdo[objects.PRELOAD_LEVEL].raw = round(fraction * 1000)

    def set_weights(self, K_Tm: float, K_Ts: float) -> None:
        """Torque weighting factors of master and slave (Fig. 3.2)."""
        self.sdo[objects.WEIGHT_MASTER].raw = K_Tm
        self.sdo[objects.WEIGHT_SLAVE].raw = K_Ts

    def read(self) -> dict[str, float | str]:
        """Coupling, preload fraction and weighting factors as the drive holds them."""
        names = {code: name for name, code in objects.COUPLINGS.items()}
        return {"coupling": names[self.sdo[objects.COUPLING].raw],
                "preload": self.sdo[objects.PRELOAD_LEVEL].raw / 1000,
                "K_Tm": self.sdo[objects.WEIGHT_MASTER].raw,
                "K_Ts": self.sdo[objects.WEIGHT_SLAVE].raw}


def motor_position(drive: Cia402Drive) -> float:
    """The drive's motor encoder at the rack from its latest TPDO (m)."""
    return drive.latest(objects.MOTOR_POSITION) * 1e-9


def load_position(drive: Cia402Drive) -> float:
    """The linear scale from the drive's latest TPDO (m)."""
    return drive.latest(objects.LOAD_POSITION) * 1e-9


# -- the per-cycle devices -----------------------------------------------------------------

SETTING_KEYS = ("coupling", "preload_pct", "K_Tm", "K_Ts")
"""Segment commands of the axis controller: coupling name, preload (% of the rated torque),
torque weighting factors."""


class LoadCellOverload(RuntimeError):
    """The load on the bumper is beyond the load cell's range."""


class AxisSettings(PerCycleDevice):
    """Coupling, preload and weighting factors from the plan, written at segment starts
    (the settings stay as the plan left them)."""

    def __init__(self, controller: AxisController) -> None:
        super().__init__()
        self.controller = controller
        self._settings: dict[int, dict[str, Any]] = {}

    def start(self, plan: Plan, recorder) -> None:
        super().start(plan, recorder)
        self._settings = plan.commands_at(SETTING_KEYS)

    def before_sync(self, index: int | None) -> None:
        found = self._settings.get(index) if index is not None else None
        if found:
            self.guarded(lambda: self._apply(found))

    def _apply(self, settings: Mapping[str, Any]) -> None:
        if "coupling" in settings:
            self.controller.set_coupling(settings["coupling"])
        if "preload_pct" in settings:
            self.controller.set_preload(settings["preload_pct"] / 100.0)
        if "K_Tm" in settings or "K_Ts" in settings:
            self.controller.set_weights(settings.get("K_Tm", 0.5), settings.get("K_Ts", 0.5))


class AxisEncoders(PerCycleDevice):
    """Motor encoders and linear scale of the cycle, from the drives' TPDOs (nothing to
    prepare, send or stop: the values come with every cycle's TPDOs)."""

    channels = ("master.motor_position", "slave.motor_position", "load_position")
    units = dict.fromkeys(channels, "m")

    def __init__(self, drives: Mapping[str, Any]) -> None:
        super().__init__()
        self.master, self.slave = drives["master"], drives["slave"]

    def after_sync(self, cycle: int) -> tuple[float, float, float]:
        return motor_position(self.master), motor_position(self.slave), load_position(self.master)


class LoadCellForce(PerCycleDevice):
    """The load-cell amplifier (`drivers.modbus_devices.LoadCellAmplifier`) read every
    `every_cycles` (nothing to send: the amplifier samples once per bus cycle on its own)."""

    channels = ("load_cell.force",)
    units = {"load_cell.force": "N"}

    def __init__(self, amplifier, every_cycles: int = 1) -> None:
        super().__init__(every_cycles)
        self.amplifier = amplifier

    def after_sync(self, cycle: int) -> tuple[float]:
        reading = self.poll(self.amplifier.reading)
        if reading is None:
            return (math.nan,)
        if reading.overloaded:
            raise LoadCellOverload(f"load cell: {reading.force_N:.0f} N is beyond its range "
                                   f"±{reading.range_N:.0f} N")
        return (reading.force_N,)


# -- the device kinds and the axis kind ----------------------------------------------------

class AxisSettingsDevice(Device):
    """The axis controller's coupling, preload and weights, set by SDO on the master drive
    from the plan's commands (`AxisSettings`)."""

    name = "axis_settings"

    @classmethod
    def open(cls, settings: Mapping[str, Any], links: DeviceLinks) -> AxisSettings:
        return AxisSettings(AxisController(links.drives["master"]))


class EncodersDevice(Device):
    """Both motor encoders and the linear scale from the drives' TPDOs
    (`AxisEncoders`)."""

    name = "encoders"

    @classmethod
    def open(cls, settings: Mapping[str, Any], links: DeviceLinks) -> AxisEncoders:
        return AxisEncoders(links.drives)


class LoadCellDevice(Device):
    """The bumper's load-cell amplifier over Modbus TCP (``address``, unit ``unit_id``),
    read every ``every_cycles`` bus cycles (`LoadCellForce`)."""

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
    reported = True
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
        """Its simulated peer (`sim_backends.rack_pinion.RackPinionBench`): both simulated
        nodes, their world and the registered peers of the devices of `tables` (the load
        cell's at its table's unit id; `listen`: at the tables' address), as the lab axis
        starts them; `close()` stops them."""
        from feedbench.sim_backends.process import LOOPBACK, modbus_listen
        from feedbench.sim_backends.rack_pinion import RackPinionBench

        modbus = modbus_listen(tables) if listen else (LOOPBACK, 0)
        return RackPinionBench(self.cfg, tables, bus_options, modbus)

    @staticmethod
    def addresses(simulated: Any) -> dict[str, str]:
        """Device name → where its simulated peer listens."""
        return simulated.addresses

    @staticmethod
    def truth(world: Mapping[str, Any]) -> dict[str, Any]:
        """The simulated world's truth (`sim_backends.rack_pinion.truth`)."""
        from feedbench.sim_backends.rack_pinion import truth

        return truth(world)
