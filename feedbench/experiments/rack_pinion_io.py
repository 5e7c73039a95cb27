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
so the drives' safe stop never waits on a broken link.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Mapping

from feedbench.drivers.rack_pinion import AxisController, load_position, motor_position
from feedbench.experiments.plan import Plan

SETTING_KEYS = ("coupling", "preload_pct", "K_Tm", "K_Ts")
"""Segment commands of the axis controller: coupling name, preload (% of the rated torque),
torque weighting factors."""


class LoadCellOverload(RuntimeError):
    """The load on the bumper is beyond the load cell's range."""


class _Guard:
    """Runs actions until the first failure, which is raised; afterwards does nothing."""

    def __init__(self) -> None:
        self.failed = False

    def __call__(self, action: Callable[[], Any]) -> Any:
        if self.failed:
            return None
        try:
            return action()
        except Exception:
            self.failed = True
            raise


class AxisSettings:
    """Coupling, preload and weighting factors from the plan, written at segment starts."""

    channels: tuple[str, ...] = ()
    units: dict[str, str] = {}
    streams: dict = {}

    def __init__(self, controller: AxisController) -> None:
        self.controller = controller
        self._settings: dict[int, dict[str, Any]] = {}
        self._guard = _Guard()

    def start(self, plan: Plan, recorder) -> None:
        self._settings = plan.commands_at(SETTING_KEYS)

    def before_sync(self, index: int | None) -> None:
        found = self._settings.get(index) if index is not None else None
        if found:
            self._guard(lambda: self._apply(found))

    def after_sync(self, cycle: int) -> tuple[()]:
        return ()

    def stop(self, recorder) -> None:
        """The settings stay as the plan left them."""

    def _apply(self, settings: Mapping[str, Any]) -> None:
        if "coupling" in settings:
            self.controller.set_coupling(settings["coupling"])
        if "preload_pct" in settings:
            self.controller.set_preload(settings["preload_pct"] / 100.0)
        if "K_Tm" in settings or "K_Ts" in settings:
            self.controller.set_weights(settings.get("K_Tm", 0.5), settings.get("K_Ts", 0.5))


class AxisEncoders:
    """Motor encoders and linear scale of the cycle, from the drives' TPDOs."""

    channels = ("master.motor_position", "slave.motor_position", "load_position")
    units = dict.fromkeys(channels, "m")
    streams: dict = {}

    def __init__(self, drives: Mapping[str, Any]) -> None:
        self.master, self.slave = drives["master"], drives["slave"]

    def start(self, plan: Plan, recorder) -> None:
        """Nothing to prepare: the values come with every cycle's TPDOs."""

    def before_sync(self, index: int | None) -> None:
        """Nothing to send."""

    def after_sync(self, cycle: int) -> tuple[float, float, float]:
        return motor_position(self.master), motor_position(self.slave), load_position(self.master)

    def stop(self, recorder) -> None:
        """Nothing to stop."""


class LoadCellForce:
    """The load-cell amplifier (`drivers.modbus_devices.LoadCellAmplifier`) read per cycle."""

    channels = ("load_cell.force",)
    units = {"load_cell.force": "N"}
    streams: dict = {}

    def __init__(self, amplifier, every_cycles: int = 1) -> None:
        self.amplifier = amplifier
        self.every_cycles = every_cycles
        self._count = 0
        self._guard = _Guard()

    def start(self, plan: Plan, recorder) -> None:
        self._count = 0

    def before_sync(self, index: int | None) -> None:
        """Nothing to send: the amplifier samples once per bus cycle on its own."""

    def after_sync(self, cycle: int) -> tuple[float]:
        due = self._count % self.every_cycles == 0
        self._count += 1
        if not due:
            return (math.nan,)
        reading = self._guard(self.amplifier.reading)
        if reading is None:
            return (math.nan,)
        if reading.overloaded:
            raise LoadCellOverload(f"load cell: {reading.force_N:.0f} N is beyond its range "
                                   f"±{reading.range_N:.0f} N")
        return (reading.force_N,)

    def stop(self, recorder) -> None:
        """Nothing to stop."""
