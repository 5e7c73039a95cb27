"""The host side of the ``linear_scale`` device kind: a linear-scale reader over Modbus TCP.

`LinearScaleDevice` is the kind (`feedbench.devices.Device`): the schema of its
own ``[bench.devices.<name>]`` table and how to open it. `ScaleReading` is the runner's
per-cycle device: it derives from `PerCycleDevice`, so it reads every ``every_cycles`` bus
cycles (NaN between) and follows feedbench's failure rule (its first failure is raised and
aborts the run, afterwards it is silent) without writing a line of it. It records one
channel, ``<name>.position`` (m). This module never imports feedbench's `sim_backends`:
the same class reads the simulated reader and a real one.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

from feedbench.config import Field, positive
from feedbench.drivers.modbus_devices import ModbusDevice
from feedbench.devices import Device, DeviceLinks, PerCycleDevice

from lab_extension.protocol import SCALE_MAP, STATUS_SIGNAL_OK


class ScaleSignalLost(RuntimeError):
    """The reader says the scale's signal is out of its limits: its count is not valid."""


class ScaleReading(PerCycleDevice):
    """The scale's position every `every_cycles` bus cycles (NaN between readings)."""

    def __init__(self, device: ModbusDevice, name: str, every_cycles: int = 1) -> None:
        super().__init__(every_cycles)
        self.device = device
        self.channels = (f"{name}.position",)
        self.units = {self.channels[0]: "m"}

    def _read(self) -> float:
        values = self.device.read_all()  # position and status in one request
        if not int(values["STATUS"]) & STATUS_SIGNAL_OK:
            raise ScaleSignalLost(f"{self.channels[0]}: the scale's signal is lost")
        return values["POSITION"]

    def after_sync(self, cycle: int) -> tuple[float]:
        position = self.poll(self._read)
        return (math.nan if position is None else position,)


class LinearScaleDevice(Device):
    """A linear-scale reader on Modbus TCP (``address``, unit ``unit_id``), read every
    ``every_cycles`` bus cycles."""

    name = "linear_scale"
    address_doc = "host:port of the linear-scale reader's Modbus TCP server"
    unit_id = 11
    schema = {"every_cycles": Field(int, 1, "read the scale every n bus cycles", positive)}

    @classmethod
    def open(cls, settings: Mapping[str, Any], links: DeviceLinks) -> ScaleReading:
        device = ModbusDevice(cls.modbus_client(settings, links), settings["unit_id"], SCALE_MAP)
        return ScaleReading(device, settings["name"], settings["every_cycles"])
