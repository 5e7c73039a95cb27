"""The simulated peer of the rack-and-pinion axis (`axes.rack_pinion.RackPinionAxis`): two
CiA 402 drives on the bus, one world, and the registered peers of the devices a run needs.

`RackPinionWorld` holds the `RackPinionSimulator` and one `MotorPort` per motor: each
port looks to its `SimulatedCia402Drive` like the lab bench's `AxisSimulator` (gains, force
limit, power stage, actual values), but `step_cycle` only latches that node's setpoints;
the world steps once per SYNC after both nodes latched (`drive_bus.SimulatedDriveBus`).
The axis controller's objects (preload level, weighting factors, coupling, preload PI)
answer on the master node (`AxisObjects`); each node reports its motor encoder and the
linear scale (`protocols.rack_pinion`). `RackPinionBench` is the axis's simulated bench:
`process.SimulatedBench` with this axis in place of the lab's, so it starts the registered
peers of the run's devices as the lab axis does (the bumper's load cell: `LoadCellPeer`,
reading the bumper's force, on the bench's Modbus server on 127.0.0.1).

`python -m feedbench.sim_backends.rack_pinion` regenerates `rack_pinion.eds`.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

from feedbench.config import ConfigError, Field, non_negative, one_of, positive, validate_table
from feedbench.models.axis import CascadeGains, ServoTiming
from feedbench.models.friction import AnderssonFriction, DirectionalFriction
from feedbench.models.rack_pinion import (
    K_TR_THESIS, MOTORS, RACK_PINION_GAINS, SLAVE_ALONE, Bumper, Preload, RackPinionAxis,
    RackPinionSimulator, TorqueEqualisation,
)
from feedbench.protocols import rack_pinion as objects
from feedbench.protocols.canbus import open_bus
from feedbench.protocols.cia402 import CSP, RATED_TORQUE
from feedbench.sim_backends import eds
from feedbench.sim_backends.drive_bus import SimulatedDriveBus
from feedbench.sim_backends.faults import NO_FAULTS, Faults
from feedbench.sim_backends.process import (
    LOOPBACK, SimulatedBench, read_old_world_keys, simulated_peers,
)
from feedbench.sim_backends.world import FRICTION_SCHEMA, servo_timing
from feedbench.units import MIN_PER_MM, MM_PER_MIN, N_MIN_PER_MM, N_PER_UM

EDS_FILE = "rack_pinion.eds"
PRODUCT_NAME = "Simulated rack-and-pinion axis drive (CiA 402, master-slave)"

OBJECTS = (
    eds.Entry(objects.PRELOAD_LEVEL, "Preload level", eds.U16, "rw", False, 100,
              "permille of 0x6076", "tension torque tau_p of the master-slave coupling"),
    eds.Entry(objects.WEIGHT_MASTER, "Torque weighting master K_Tm", eds.F32, "rw",
              default=0.5),
    eds.Entry(objects.WEIGHT_SLAVE, "Torque weighting slave K_Ts", eds.F32, "rw", default=0.5),
    eds.Entry(objects.COUPLING, "Coupling", eds.U8, "rw", False, 0, "",
              "0 master-slave with preload, 1 master alone, 2 slave alone"),
    eds.Entry(objects.PRELOAD_GAIN, "Preload PI gain", eds.F32, "rw",
              default=TorqueEqualisation.K_p, unit="(m/s)/N"),
    eds.Entry(objects.PRELOAD_INTEGRAL_TIME, "Preload PI integral time", eds.F32, "rw",
              default=TorqueEqualisation.T_i, unit="s"),
    eds.Entry(objects.LOAD_POSITION, "Load position (linear scale)", eds.I32, "ro", True, 0,
              "nm"),
    eds.Entry(objects.MOTOR_POSITION, "Motor position at the rack", eds.I32, "ro", True, 0,
              "nm", "motor encoder x r_pinion / i_red"),
)


WORLD_SCHEMA = {
    "m_load_kg": Field(float, 8500.0, "driven load (kg)", positive),
    "J_motor_kgm2": Field(float, 7500e-6, "motor inertia (kg·m²)", positive),
    "J_gearbox_kgm2": Field(float, 948e-6, "gearbox inertia, motor side (kg·m²)",
                            non_negative),
    "J_pinion_kgm2": Field(float, 0.0, "pinion inertia (kg·m²)", non_negative),
    "i_red": Field(float, 28.0, "gearbox reduction", positive),
    "pinion_radius_mm": Field(float, 28e3 / K_TR_THESIS, "pinion pitch radius (mm)", positive),
    "k_master_N_um": Field(float, 81.0, "master drive-train stiffness at the rack (N/µm)",
                           positive),
    "k_slave_N_um": Field(float, 100.0, "slave drive-train stiffness at the rack (N/µm)",
                          positive),
    "backlash_master_um": Field(float, 314.0, "master backlash at the rack (µm)",
                                non_negative),
    "backlash_slave_um": Field(float, 363.0, "slave backlash at the rack (µm)", non_negative),
    "damping_ratio": Field(float, 0.05, "damping ratio of a motor on its drive train",
                           non_negative),
    "motor_damping_Ns_m": Field(float, 2000.0, "viscous drag of motor + gearbox at the rack",
                                non_negative),
    "rated_torque_Nm": Field(float, 70.0, "motor rated torque (N·m)", positive),
    "torque_limit": Field(float, 3.0, "peak torque / rated torque", positive),
    "bumper_mm": Field(float, -0.05, "bumper face from the start position (mm; sign = the "
                       "side it stops; 0: no bumper)"),
    "bumper_N_um": Field(float, 66.7, "bumper stiffness (N/µm)", positive),
    "bumper_Ns_m": Field(float, 7.5e4, "bumper damping (N·s/m)", non_negative),
    "K_p_Ns_m": Field(float, RACK_PINION_GAINS.K_p, "each motor's velocity-PI gain at the rack "
                      "(N·s/m)", positive),
    "T_i_ms": Field(float, RACK_PINION_GAINS.T_i * 1e3, "velocity-PI integral time (ms)",
                    positive),
    "K_v_per_s": Field(float, RACK_PINION_GAINS.K_v, "position-loop gain (1/s)", positive),
    "preload_pct": Field(float, 10.0, "preload, % of the rated torque", non_negative),
    "K_Tm": Field(float, 0.5, "torque weighting, master", positive),
    "K_Ts": Field(float, 0.5, "torque weighting, slave", positive),
    "preload_K_p_m_s_N": Field(float, TorqueEqualisation.K_p, "preload-PI gain ((m/s)/N)",
                               non_negative),
    "preload_T_i_ms": Field(float, TorqueEqualisation.T_i * 1e3, "preload-PI integral time "
                            "(ms)", positive),
    "coupling": Field(str, "coupled", "coupled, master (alone) or slave (alone)",
                      one_of(*objects.COUPLINGS)),
    "delay_ms": Field(float, 0.25, "drive force delay (ms)", non_negative),
    "f_velocity_Hz": Field(float, 8000.0, "velocity-loop rate (Hz)", positive),
    "f_position_Hz": Field(float, 1000.0, "position-loop rate (Hz)", positive),
    "friction": Field(dict, {}, "guideway friction per direction, Eq. (5.2)"),
    "faults": Field(dict, {}, "fault injection: feedbench.sim_backends.faults.FAULT_SCHEMA"),
}

CARRIAGE_FRICTION = {"F_c_N": 600.0, "F_s_N": 900.0, "v_s_mm_min": 300.0,
                     "sigma_N_min_mm": 0.1, "k_tanh_min_mm": 0.0125}
"""Default guideway friction of the 8500 kg carriage, both directions (see
`models.rack_pinion.RACK_PINION_FRICTION`)."""


def _friction(table: Mapping[str, Any]) -> DirectionalFriction:
    unknown = sorted(set(table) - {"positive", "negative"})
    if unknown:
        raise ConfigError(f"bench.world.friction.{unknown[0]}: unknown key "
                          "(known: negative, positive)")
    sides = []
    for direction in ("positive", "negative"):
        f = validate_table({**CARRIAGE_FRICTION, **table.get(direction, {})}, FRICTION_SCHEMA,
                           f"bench.world.friction.{direction}")
        sides.append(AnderssonFriction(
            F_c=f["F_c_N"], F_s=f["F_s_N"], v_s=f["v_s_mm_min"] * MM_PER_MIN,
            sigma=f["sigma_N_min_mm"] * N_MIN_PER_MM, k_tanh=f["k_tanh_min_mm"] * MIN_PER_MM,
            delta=f["delta"]))
    return DirectionalFriction(*sides)


def _axis(w: Mapping[str, Any]) -> RackPinionAxis:
    bumper = (Bumper(w["bumper_mm"] * 1e-3, w["bumper_N_um"] * N_PER_UM, w["bumper_Ns_m"])
              if w["bumper_mm"] != 0.0 else None)
    return RackPinionAxis(
        m_load=w["m_load_kg"], J_motor=w["J_motor_kgm2"], J_gearbox=w["J_gearbox_kgm2"],
        J_pinion=w["J_pinion_kgm2"], i_red=w["i_red"], pinion_radius=w["pinion_radius_mm"] * 1e-3,
        k_master=w["k_master_N_um"] * N_PER_UM, k_slave=w["k_slave_N_um"] * N_PER_UM,
        backlash_master=w["backlash_master_um"] * 1e-6,
        backlash_slave=w["backlash_slave_um"] * 1e-6, damping_ratio=w["damping_ratio"],
        motor_damping=w["motor_damping_Ns_m"], rated_torque=w["rated_torque_Nm"],
        friction=_friction(w["friction"]), bumper=bumper)


def build_simulator(table: Mapping[str, Any], cycle_s: float) -> RackPinionSimulator:
    """The simulated rack-and-pinion axis from a ``[bench.world]`` table (engineering units)."""
    w = validate_table(table, WORLD_SCHEMA, "bench.world")
    timing = servo_timing(w, cycle_s)
    try:
        gains = CascadeGains(w["K_p_Ns_m"], w["T_i_ms"] * 1e-3, w["K_v_per_s"])
        simulator = RackPinionSimulator(
            _axis(w), gains, gains,
            TorqueEqualisation(w["preload_K_p_m_s_N"], w["preload_T_i_ms"] * 1e-3),
            Preload(w["preload_pct"] / 100.0, w["K_Tm"], w["K_Ts"]), timing,
            torque_limit=w["torque_limit"])
    except ValueError as exc:
        raise ConfigError(f"bench.world: {exc}") from None
    simulator.coupling = objects.COUPLINGS[w["coupling"]]
    return simulator


def world_truth(table: Mapping[str, Any]) -> dict[str, float]:
    """The true values the stepped-loading experiment identifies, SI (for the demo)."""
    axis = build_simulator(table, 1e-3).axis
    return {"k_master": axis.k_master, "k_slave": axis.k_slave,
            "backlash_master": axis.backlash_master, "backlash_slave": axis.backlash_slave,
            "rated_force": axis.rated_force, "K_tr": axis.K_tr}


def truth(world: Mapping[str, Any]) -> dict[str, Any]:
    """The world's truth the demo and a campaign summarise against (`world_truth`), with the
    friction the summed motor forces show: the guideway's Eq. (5.2) plus both motors'
    viscous drag in σ (`axes.Axis.truth`)."""
    world = _axis_world(read_old_world_keys(world, say=False))
    axis = build_simulator(world, 1e-3).axis
    friction = {d: dataclasses.asdict(getattr(axis.friction, d))
                for d in ("positive", "negative")}
    for side in friction.values():
        side["sigma"] += 2.0 * axis.motor_damping
    return {**world_truth(world), "friction": friction}


def _axis_world(world: Mapping[str, Any]) -> dict[str, Any]:
    """The axis's own ``[bench.world]`` keys: the peers' tables (``load_cell``) left out."""
    return {key: value for key, value in world.items() if key not in simulated_peers()}


def packaged_eds_path() -> Path:
    """The rack-and-pinion drives' EDS shipped in the package."""
    return eds.packaged_eds_path(EDS_FILE)


@dataclass
class MotorCommand:
    """One node's setpoints of the current cycle (SI), latched at its SYNC."""

    mode: int = CSP
    target_position: float = 0.0
    target_velocity: float = 0.0
    target_force: float = 0.0
    velocity_offset: float = 0.0
    force_offset: float = 0.0


class MotorPort:
    """One motor's view of the shared axis, with the interface `SimulatedCia402Drive` uses.

    position: the axis position the position loop closes on (0x6064, the linear scale
    when coupled); velocity, force: this motor's, at the rack, at the end of the cycle
    (they also serve as the cycle means the drive publishes).
    """

    def __init__(self, world: RackPinionWorld, motor: str) -> None:
        self.world = world
        self.motor = motor
        self.command = MotorCommand()

    @property
    def timing(self) -> ServoTiming:
        return self.world.simulator.timing

    @property
    def gains(self) -> CascadeGains:
        return self.world.simulator.gains(self.motor)

    def set_gains(self, gains: CascadeGains) -> None:
        self.world.simulator.set_gains(self.motor, gains)

    @property
    def force_limit(self) -> float:
        return self.world.simulator.force_limit

    @force_limit.setter
    def force_limit(self, value: float) -> None:
        self.world.simulator.force_limit = value

    @property
    def enabled(self) -> bool:
        return self.world.simulator.enabled(self.motor)

    @enabled.setter
    def enabled(self, on: bool) -> None:
        self.world.simulator.set_enabled(self.motor, on)

    @property
    def position(self) -> float:
        return self.world.simulator.position_feedback

    @property
    def velocity(self) -> float:
        return self.world.simulator.motor_velocity(self.motor)

    @property
    def force(self) -> float:
        return self.world.simulator.motor_force(self.motor)

    mean_velocity = velocity
    mean_force = force

    def reported(self) -> tuple[float, float, float]:
        """(position, velocity, force) as the drive publishes them (see the class)."""
        return self.position, self.velocity, self.force

    def step_cycle(self, mode: int, target_position: float, target_velocity: float,
                   target_force: float, velocity_offset: float, force_offset: float,
                   tip_force: float = 0.0) -> None:
        """Latch this node's setpoints; the world steps once both nodes latched."""
        self.command = MotorCommand(mode, target_position, target_velocity, target_force,
                                    velocity_offset, force_offset)


class RackPinionWorld:
    """The axis behind both drives; `before_physics` and `after_physics`: the per-cycle
    hooks of the peers sampled with it (the load cell), run around each step.

    A copy of the simulator is stepped once here: numba compiles (or loads its cache) on
    the first call, which must not happen in the first SYNC the host waits for.
    """

    def __init__(self, simulator: RackPinionSimulator) -> None:
        copy.deepcopy(simulator).step_cycle(CSP, 0.0)
        self.simulator = simulator
        self.ports = {motor: MotorPort(self, motor) for motor in MOTORS}
        self.before_physics: list[Callable[[], None]] = []
        self.after_physics: list[Callable[[], None]] = []

    def driving_port(self) -> MotorPort:
        """The node whose mode and targets run the axis: the slave's when it drives alone."""
        return self.ports["slave" if self.simulator.coupling == SLAVE_ALONE else "master"]

    def step(self) -> None:
        """One bus cycle with the latched setpoints of both nodes, between the hooks."""
        for hook in self.before_physics:
            hook()
        drive = self.driving_port().command
        master, slave = (self.ports[m].command for m in MOTORS)
        self.simulator.step_cycle(
            drive.mode, drive.target_position, drive.target_velocity, drive.velocity_offset,
            (master.target_force, slave.target_force), (master.force_offset, slave.force_offset))
        for hook in self.after_physics:
            hook()


def _nm(value: float) -> int:
    return round(value * 1e9)


class MotorObjects:
    """A node's world objects: its motor encoder and the linear scale (TPDO-mappable)."""

    def __init__(self, world: RackPinionWorld, motor: str) -> None:
        self.world = world
        self.motor = motor

    def values(self) -> dict[int, int | float]:
        """Parameters at power-on: 0x6076 is the rated torque as a force at the rack (mN)."""
        return {RATED_TORQUE: round(self.world.simulator.axis.rated_force * 1e3)}

    def write(self, index: int, value: int | float) -> None:
        """A node without axis objects: nothing to apply."""

    def actual(self) -> dict[int, int]:
        sim = self.world.simulator
        return {objects.MOTOR_POSITION: _nm(sim.motor_position(self.motor)),
                objects.LOAD_POSITION: _nm(sim.load_position)}


class AxisObjects(MotorObjects):
    """The master node: its encoder, the scale and the axis controller's objects."""

    def values(self) -> dict[int, int | float]:
        sim = self.world.simulator
        return {**super().values(),
                objects.PRELOAD_LEVEL: round(sim.preload.level * 1000),
                objects.WEIGHT_MASTER: sim.preload.K_Tm,
                objects.WEIGHT_SLAVE: sim.preload.K_Ts,
                objects.COUPLING: sim.coupling,
                objects.PRELOAD_GAIN: sim.equalisation.K_p,
                objects.PRELOAD_INTEGRAL_TIME: sim.equalisation.T_i}

    def write(self, index: int, value: int | float) -> None:
        """Apply an axis object (ValueError refuses it: SDO abort value range)."""
        sim = self.world.simulator
        preload_fields = {objects.PRELOAD_LEVEL: ("level", value / 1000),
                          objects.WEIGHT_MASTER: ("K_Tm", value),
                          objects.WEIGHT_SLAVE: ("K_Ts", value)}
        pi_fields = {objects.PRELOAD_GAIN: "K_p", objects.PRELOAD_INTEGRAL_TIME: "T_i"}
        if index in preload_fields:
            name, field_value = preload_fields[index]
            sim.preload = dataclasses.replace(sim.preload, **{name: field_value})
        elif index in pi_fields:
            sim.equalisation = dataclasses.replace(sim.equalisation, **{pi_fields[index]: value})
        elif index == objects.COUPLING:
            sim.coupling = int(value)


class SimulatedRackPinionAxis:
    """Master and slave drives on one bus channel and their world; what the peers see as the
    bench's `drive` (`process.SimulatedBench.start_axis`): the cycle's `lock`, the world's
    `before_physics` / `after_physics` hooks and `tip_force`, the external force on the axis
    where its load cell sits (the bumper's, N).

    `faults` (`sim_backends.faults`) act on the drives' bus. `close()` stops the drives.
    """

    def __init__(self, simulator: RackPinionSimulator, interface: str = "virtual",
                 channel: str = "feedbench", node_ids: tuple[int, int] = (1, 2),
                 faults: Faults = NO_FAULTS, **bus_options: Any) -> None:
        self.world = RackPinionWorld(simulator)
        self.bus = SimulatedDriveBus(faults.bus(open_bus(interface, channel, **bus_options)),
                                     self.world.step, faults)
        try:
            self.drives = {
                motor: self.bus.add_drive(node_id, self.world.ports[motor], packaged_eds_path(),
                                          (AxisObjects if motor == "master" else MotorObjects)(
                                              self.world, motor))
                for motor, node_id in zip(MOTORS, node_ids)}
        except BaseException:
            self.close()
            raise
        self.lock = self.bus.lock
        self.before_physics = self.world.before_physics
        self.after_physics = self.world.after_physics

    @property
    def tip_force(self) -> float:
        """The bumper's force on the carriage (N): what the load cell in it reads."""
        return self.world.simulator.bumper_force

    def close(self) -> None:
        self.bus.close()


class RackPinionBench(SimulatedBench):
    """The simulated rack-and-pinion axis of a validated ``[bench]`` table (master at
    ``node_id``, slave at ``slave_node_id``; the world: `WORLD_SCHEMA`, the keys of earlier
    versions read, `process.read_old_world_keys`) and the registered peers of the devices of
    `tables`, started as on the lab axis (`process.SimulatedBench`)."""

    def __init__(self, bench: Mapping[str, Any], tables: Mapping[str, Mapping[str, Any]],
                 bus_options: Mapping[str, Any] | None = None,
                 modbus_address: tuple[str, int] = (LOOPBACK, 0)) -> None:
        super().__init__(bench, tables, (), bus_options, modbus_address)

    @property
    def drives(self) -> dict[str, Any]:
        """The simulated master and slave drives (`SimulatedCia402Drive`) by name."""
        return self.drive.drives

    def start_axis(self, world: Mapping[str, Any],
                   bus_options: Mapping[str, Any]) -> SimulatedRackPinionAxis:
        bench = self.bench
        return SimulatedRackPinionAxis(build_simulator(world, self.cycle_s), bench["interface"],
                                       bench["channel"],
                                       (bench["node_id"], bench["slave_node_id"]),
                                       faults=self.faults, **bus_options)


if __name__ == "__main__":
    eds.export(packaged_eds_path(), OBJECTS, PRODUCT_NAME)
    print(packaged_eds_path())
