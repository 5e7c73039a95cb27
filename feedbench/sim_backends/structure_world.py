"""The devices at the tool tip of the simulated lab-bench axis, stepped in the drive's SYNC
handler (Ch. 3.5.1, 5.3, 5.5.3): a shaker, an inertial actuator and an impact hammer,
commanded through the CiA 401 I/O module, and the instruments the streaming DAQ samples:
the tool-side accelerometer (Gaussian noise, Eq. (6.18)) and the exciters' force sensors.

Per bus cycle (`StructureWorld.before_physics` / `after_physics`, the drive's hooks):
  1. the outputs the I/O module latched at this SYNC command the exciters; each advances one
     cycle (its force at the end of the cycle, `ForceExciter`, `ImpactHammer`) and their sum
     is the drive's `tip_force`, which the axis ramps to over the cycle (first-order hold);
  2. after the physics, the cycle's samples go to the DAQ (`SimulatedSerialDaq.push`):
     sample i of the cycle is taken at (cycle start) + i / rate. The accelerometer
     interpolates the axis's tip-acceleration trace (physics substeps, 8 kHz) linearly in
     time, exact when the rate divides the substep rate (8 kHz); at 10 kHz the error is of
     the order (π f / 8 kHz)² / 2 ≈ 4e-4 at 75 Hz. The forces follow the same ramp the
     axis applies. So the sample counter c · samples_per_cycle + i is bench time.

The truth (`[bench.world.structure]`) stays here: the host knows only what its config says
about the exciters (datasheet values) and what the DAQ measures.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from feedbench.config import ConfigError, Field, interval, non_negative, positive, validate_table
from feedbench.models.exciters import (
    ExciterDynamics, InertialActuator, half_sine_pulse, shaker,
)
from feedbench.models.milling import SMFE_SENSOR_NOISE
from feedbench.protocols import cia401
from feedbench.protocols.serial_frames import CHANNEL_INDEX, CHANNELS
from feedbench.sim_backends.io_module import SimulatedIoModule

STRUCTURE_SCHEMA = {
    "accelerometer_noise_m_s2": Field(list, list(SMFE_SENSOR_NOISE),
                                      "accelerometer noise std x (feed), y, z (m/s²), Eq. (6.18)",
                                      non_negative),
    "force_noise_N": Field(float, 0.05, "noise std of the force sensors (N)", non_negative),
    "shaker_corner_Hz": Field(float, 160.0, "shaker force fall-off corner (Hz)", positive),
    "shaker_limit_N": Field(float, 500.0, "largest shaker force command (N)", positive),
    "actuator_mass_kg": Field(float, 2.0, "inertial actuator reaction mass (kg)", positive),
    "actuator_f_Hz": Field(float, 15.0, "inertial actuator suspension frequency (Hz)", positive),
    "actuator_zeta": Field(float, 0.3, "inertial actuator suspension damping ratio", positive),
    "actuator_limit_N": Field(float, 300.0, "largest actuator coil force (N)", positive),
    "hammer_contact_ms": Field(float, 4.0, "hammer contact time (ms), soft rubber tip", positive),
    "hammer_scatter": Field(float, 0.1, "relative std of the hit level", non_negative),
    "double_hit_probability": Field(float, 0.05, "chance that a hit bounces (0..1)",
                                    non_negative),
    "double_hit_delay_ms": Field(list, [4.0, 12.0], "range of the bounce delay (ms)", interval),
    "double_hit_ratio": Field(list, [0.2, 0.5], "range of the bounce level / hit level",
                              interval),
    "seed": Field(int, 0, "seed of the noise, the hit levels and the bounces"),
}

ACCELEROMETER_COLUMNS = np.array([CHANNEL_INDEX[name] for name in (
    "acc_tool_x", "acc_tool_y", "acc_tool_z", "acc_work_x", "acc_work_y", "acc_work_z")])
FORCE_COLUMNS = {name: CHANNEL_INDEX[f"{name}_force"] for name in ("shaker", "actuator",
                                                                   "hammer")}
TIP_ACCELERATION_COLUMN = CHANNEL_INDEX["acc_tool_x"]
FORCE_ORDER = tuple(sorted(FORCE_COLUMNS, key=FORCE_COLUMNS.get))
FORCE_SLICE = slice(FORCE_COLUMNS[FORCE_ORDER[0]], FORCE_COLUMNS[FORCE_ORDER[-1]] + 1)
"""The exciters' force inputs are adjacent DAQ inputs, in `FORCE_ORDER`."""
NOISE_BLOCK_CYCLES = 1000


def parse_structure(table: Mapping[str, Any]) -> dict[str, Any]:
    """Validate a ``[bench.world.structure]`` table; defaults filled in."""
    t = validate_table(table, STRUCTURE_SCHEMA, "bench.world.structure")
    if len(t["accelerometer_noise_m_s2"]) != 3:
        raise ConfigError("bench.world.structure.accelerometer_noise_m_s2: expected 3 "
                          "standard deviations (x, y, z)")
    if not t["double_hit_probability"] <= 1.0:
        raise ConfigError("bench.world.structure.double_hit_probability: must be <= 1")
    return t


class ForceExciter:
    """An exciter stepped once per bus cycle: the force sequence answers the command
    sequence through the exciter's discretised dynamics (`ExciterDynamics.discrete`);
    commands beyond the amplifier's `command_limit` saturate. Stepped with plain floats (one
    or two states): numpy's call overhead would cost more than the arithmetic."""

    def __init__(self, dynamics: ExciterDynamics, cycle_s: float) -> None:
        self.limit = dynamics.command_limit
        a, b, c, d = dynamics.discrete(cycle_s)
        self._a = tuple(tuple(map(float, row)) for row in a)
        self._b, self._c = tuple(map(float, b[:, 0])), tuple(map(float, c[0]))
        self._d = float(d[0, 0])
        self._state = (0.0,) * len(self._b)
        self.force = 0.0

    def step(self, command: float) -> float:
        """Advance one cycle under `command` (N); returns the cycle's force (N)."""
        u = min(max(command, -self.limit), self.limit)
        x = self._state
        if u == 0.0 and self.force == 0.0 and not any(x):
            return 0.0  # at rest (the other exciters of a run): nothing to integrate
        self.force = sum(c_i * x_i for c_i, x_i in zip(self._c, x)) + self._d * u
        self._state = tuple(sum(a_ij * x_j for a_ij, x_j in zip(row, x)) + b_i * u
                            for row, b_i in zip(self._a, self._b))
        return self.force


class ImpactHammer:
    """An automatic impact hammer: fired on a rising edge, it hits with a half-sine pulse of
    the commanded peak × (1 + scatter · N(0, 1)); with `double_hit_probability` the tip
    bounces and hits again `double_hit_delay` later at `double_hit_ratio` of the level."""

    def __init__(self, params: Mapping[str, Any], cycle_s: float,
                 rng: np.random.Generator) -> None:
        self.params = params
        self.cycle_s = cycle_s
        self.rng = rng
        self._queue = np.zeros(0)
        self._fired = False
        self.force = 0.0
        self.hits = 0
        self.bounces = 0

    def step(self, fire: bool, level: float) -> float:
        """Advance one cycle; returns the force at its end (N)."""
        if fire and not self._fired:
            self._strike(level)
        self._fired = fire
        self.force = float(self._queue[0]) if self._queue.size else 0.0
        self._queue = self._queue[1:]
        return self.force

    def _strike(self, level: float) -> None:
        p = self.params
        contact = p["hammer_contact_ms"] * 1e-3
        peak = level * max(0.0, 1.0 + p["hammer_scatter"] * self.rng.standard_normal())
        pulse = half_sine_pulse(peak, contact, self.cycle_s)
        if self.rng.random() < p["double_hit_probability"]:
            delay = int(round(self.rng.uniform(*p["double_hit_delay_ms"]) * 1e-3 / self.cycle_s))
            bounce = half_sine_pulse(peak * self.rng.uniform(*p["double_hit_ratio"]), contact,
                                     self.cycle_s)
            pulse = np.concatenate([pulse, np.zeros(delay), bounce])
            self.bounces += 1
        self.hits += 1
        self._queue = _added(self._queue, pulse)


def _added(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Element-wise sum of two sequences, the shorter padded with zeros."""
    out = np.zeros(max(a.size, b.size))
    out[:a.size] += a
    out[:b.size] += b
    return out


def interpolation_weights(substeps: int, samples_per_cycle: int) -> np.ndarray:
    """(samples, substeps + 1) weights: sample i at i / samples_per_cycle of the cycle,
    linear in time between the trace points j / substeps."""
    position = np.arange(samples_per_cycle) * substeps / samples_per_cycle
    left = np.floor(position).astype(int)
    weights = np.zeros((samples_per_cycle, substeps + 1))
    rows = np.arange(samples_per_cycle)
    weights[rows, left] = 1.0 - (position - left)
    weights[rows, np.minimum(left + 1, substeps)] += position - left
    return weights


class StructureWorld:
    """The exciters and instruments at the tool tip of `drive` (a `SimulatedCia402Drive`).

    `io`: the `SimulatedIoModule` whose outputs command the exciters; `daq`: the
    `SimulatedSerialDaq` the cycle's samples go to (None: no instrument); `params`: a
    validated ``[bench.world.structure]`` table. `attach()` hooks it into the drive.
    """

    def __init__(self, drive, io, daq, params: Mapping[str, Any], cycle_s: float) -> None:
        self.drive = drive
        self.io = io
        self.daq = daq
        self.cycle_s = cycle_s
        hammer_rng, self._rng = np.random.default_rng(params["seed"]).spawn(2)
        self.shaker = ForceExciter(shaker(params["shaker_corner_Hz"], params["shaker_limit_N"]),
                                   cycle_s)
        actuator = InertialActuator(params["actuator_mass_kg"], params["actuator_f_Hz"],
                                    params["actuator_zeta"], params["actuator_limit_N"])
        self.actuator = ForceExciter(actuator.dynamics(), cycle_s)
        self.hammer = ImpactHammer(params, cycle_s, hammer_rng)
        self._noise = np.zeros(len(CHANNELS))
        self._noise[ACCELEROMETER_COLUMNS] = np.tile(params["accelerometer_noise_m_s2"], 2)
        self._noise[FORCE_SLICE] = params["force_noise_N"]
        self._forces = np.zeros(len(FORCE_COLUMNS))
        self._previous_forces = np.zeros(len(FORCE_COLUMNS))
        self._weights: np.ndarray | None = None
        self._ramp = np.zeros((0, 1))
        self._noise_block = np.zeros((0, len(CHANNELS)))
        self._noise_used = 0

    def attach(self) -> StructureWorld:
        """Run in the drive's SYNC handler from now on."""
        self.drive.before_physics.append(self.before_physics)
        self.drive.after_physics.append(self.after_physics)
        return self

    def before_physics(self) -> None:
        """Step the exciters under the latched outputs; their sum acts on the tool tip. The
        safe-torque-off output wired to the drive turns its power stage off."""
        io = self.io
        if io.digital & cia401.SAFE_TORQUE_OFF:
            self.drive.torque_off()
        forces = {
            "shaker": self.shaker.step(io.analog_force(cia401.SHAKER)),
            "actuator": self.actuator.step(io.analog_force(cia401.ACTUATOR)),
            "hammer": self.hammer.step(bool(io.digital & cia401.HAMMER_FIRE),
                                       io.analog_force(cia401.HAMMER_LEVEL)),
        }
        self._previous_forces = self._forces
        self._forces = np.array([forces[name] for name in FORCE_ORDER])
        self.drive.tip_force = sum(forces.values())

    def after_physics(self) -> None:
        """The cycle's samples of every DAQ input, with sensor noise, to the instrument."""
        if self.daq is not None:
            self.daq.push(self.samples(self.daq.samples_per_cycle))

    def samples(self, samples_per_cycle: int) -> np.ndarray:
        """(samples_per_cycle, 12) DAQ inputs of the cycle just simulated (SI)."""
        trace = self.drive.simulator.tip_acceleration_trace
        if self._weights is None or self._weights.shape != (samples_per_cycle, trace.size):
            self._weights = interpolation_weights(trace.size - 1, samples_per_cycle)
            self._ramp = np.arange(samples_per_cycle)[:, None] / samples_per_cycle
        out = self._noise_rows(samples_per_cycle)
        out[:, TIP_ACCELERATION_COLUMN] += self._weights @ trace
        forces = self._previous_forces + (self._forces - self._previous_forces) * self._ramp
        out[:, FORCE_SLICE] += forces
        return out

    def _noise_rows(self, n: int) -> np.ndarray:
        """The sensor noise of the next n samples (drawn NOISE_BLOCK_CYCLES cycles at a time:
        one generator call per cycle would cost more than the samples)."""
        if self._noise_used + n > len(self._noise_block):
            self._noise_block = self._rng.standard_normal(
                (NOISE_BLOCK_CYCLES * n, len(CHANNELS))) * self._noise
            self._noise_used = 0
        rows = self._noise_block[self._noise_used:self._noise_used + n].copy()
        self._noise_used += n
        return rows


def start_structure_world(drive, daq, io_node_id: int, table: Mapping[str, Any],
                          cycle_s: float) -> StructureWorld:
    """The I/O module as node `io_node_id` on the drive's network and the world at its tool
    tip, attached to the drive's SYNC handler (`table`: ``[bench.world.structure]``)."""
    io = SimulatedIoModule(drive.network, io_node_id, cycle_s)
    return StructureWorld(drive, io, daq, parse_structure(table), cycle_s).attach()
