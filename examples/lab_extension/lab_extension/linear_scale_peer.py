"""The simulated side of the ``linear_scale`` device kind: a Modbus linear-scale reader whose
scale is mounted at the simulated lab axis's tool tip.

`SimulatedScaleReader` is the protocol-true device (a `SimulatedModbusDevice`: register image
↔ state, answered by the bench's Modbus TCP server); `LinearScalePeer` is the registered
peer (`SimulatedPeer`, the kind's name): it owns the ``[bench.world.linear_scale]`` table
(the scale's resolution and noise, never read by the host), serves the reader at its
table's unit id and samples the world once per bus cycle, after the physics. This module
never imports feedbench's `drivers` or `experiments`.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping

import numpy as np

from feedbench.config import Field, non_negative, positive
from feedbench.sim_backends.modbus_devices import InvalidWrite, SimulatedModbusDevice
from feedbench.sim_backends.process import SimulatedBench, SimulatedPeer

from lab_extension.protocol import SCALE_MAP, STATUS_SIGNAL_OK


class SimulatedScaleReader(SimulatedModbusDevice):
    """Samples `position()` (m) once per `advance`: + Gaussian noise (std `noise_m`,
    seeded), quantised to the scale's `resolution_m`."""

    register_map = SCALE_MAP

    def __init__(self, position: Callable[[], float], device_id: int, resolution_m: float,
                 noise_m: float, seed: int = 0) -> None:
        super().__init__(device_id)
        self.position = position
        self.resolution_m = resolution_m
        self.noise_m = noise_m
        self._rng = np.random.default_rng(seed)
        self.reading_m = 0.0

    def advance(self, dt_s: float) -> None:
        x = self.position() + self.noise_m * float(self._rng.standard_normal())
        self.reading_m = round(x / self.resolution_m) * self.resolution_m

    def values(self) -> dict[str, float]:
        return {"POSITION": self.reading_m, "STATUS": STATUS_SIGNAL_OK}

    def apply(self, name: str, value: float) -> None:
        raise InvalidWrite(f"{name} is read-only")


class LinearScalePeer(SimulatedPeer):
    """The reader of a scale at the lab axis's tool tip (`AxisSimulator.tip_position`),
    on the bench's Modbus server."""

    name = "linear_scale"
    world_schema = {
        "resolution_nm": Field(float, 50.0, "the scale's resolution (nm)", positive),
        "noise_nm": Field(float, 20.0, "the reading's noise std (nm)", non_negative),
        "seed": Field(int, 0, "seed of the noise", non_negative),
    }

    def __init__(self, sim: SimulatedBench, settings: Mapping[str, Any]) -> None:
        super().__init__(sim, settings)
        w = self.world
        self.reader = SimulatedScaleReader(lambda: sim.drive.simulator.tip_position,
                                           settings["unit_id"], w["resolution_nm"] * 1e-9,
                                           w["noise_nm"] * 1e-9, w["seed"])
        sim.serve_modbus(self.reader, settings["name"])
        sim.drive.after_physics.append(lambda: self.reader.advance(sim.cycle_s))
