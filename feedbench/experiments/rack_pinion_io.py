"""Per-cycle host devices of the rack-and-pinion axis (`runner.CycleDevice`).

- `AxisSettings`: a plan segment whose commands hold ``coupling`` (coupled, master, slave)
  or ``preload_pct`` (and optionally ``K_Tm``, ``K_Ts``) sets the axis controller by SDO in
  the cycle the segment starts, as the thesis reconfigured its CNC between tests (Ch. 3.4).
  The commands stay in the segment's event, so the recording tells each test's setup.
- `AxisEncoders`: both motor encoders and the linear scale from the drives' TPDO 3,
  recorded as ``master.motor_position``, ``slave.motor_position``, ``load_position`` (m).
- `LoadCellForce`: the bumper's load cell over Modbus every `every_cycles` (NaN between
  readings, so no value is ever stale), recorded as ``load_cell.force`` (N); a reading
  beyond the amplifier's range aborts the run (`LoadCellOverload`).

Each raises on its first failure (the runner aborts the run) and goes silent afterwards,
so the drives' safe stop never waits on a broken link (`devices.PerCycleDevice`).
"""

from __future__ import annotations

import math
from typing import Any, Mapping

from feedbench.drivers.rack_pinion import AxisController, load_position, motor_position
from feedbench.experiments.devices import PerCycleDevice
from feedbench.experiments.plan import Plan

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
