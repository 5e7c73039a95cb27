"""The electronically preloaded rack-and-pinion feed axis (thesis Ch. 3.2, Fig. 3.2).

Two motors (master and slave) each drive the load through a gearbox, a pinion and the
rack. Everything is expressed at the rack (linear): a motor's equivalent inertia J_eq
(Eq. 3.3) becomes the mass J_eq·K_tr², a motor torque τ the force τ·K_tr, with the
linear-rotary conversion factor K_tr = i_red / r_pinion (N per N·m). Each drive train is
a spring k (Eq. 3.4, the series stiffness of coupling, gearbox, shaft and mesh) with a
damper, behind a dead zone of total width L_z (backlash, Ch. 3.2.3). The load (m_load)
runs on guideways with Andersson friction (Eq. 5.2) and may be pushed against a bumper
(a one-sided spring-damper whose force a load cell reads).

The simulated axis controller is what a CNC runs for such an axis (Fig. 3.2): the position
loop (P, K_v, at f_position) on the linear scale, a velocity PI per motor on its own
motor velocity (Eqs. 3.8, 3.9, Tustin, at f_velocity) and the torque-equalisation PI
(Eq. 3.10) that adds a velocity correction u to the master and subtracts it from the
slave until K_Tm τ_m − K_Ts τ_s = τ_p: at rest τ_m = τ_ref/2 + τ_p, τ_s = τ_ref/2 − τ_p
(Eq. 3.1). The preload τ_p is a fraction of the motors' rated torque. For identification
the coupling can be removed (Ch. 3.4): one motor then closes both loops on its own encoder
and the other is off.

Sign convention: the master pushes towards +x, the slave towards −x (τ_p > 0). A load that
pushes the carriage towards +x (a bumper on the −x side) unloads the master first: it
loses contact at F = 2 τ_p K_tr (Ch. 3.4.3, Fig. 3.11).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from feedbench.models import _rack_kernel as kernel
from feedbench.models._cycle_simulator import CycleSimulator, check_mode, positive
from feedbench.models.axis import CascadeGains, ServoTiming
from feedbench.models.friction import AnderssonFriction, DirectionalFriction

__all__ = [
    "COUPLED", "MASTER_ALONE", "SLAVE_ALONE", "MOTORS", "Bumper", "RackPinionAxis",
    "Preload", "TorqueEqualisation", "RackPinionSimulator", "RACK_PINION_FRICTION",
    "RACK_PINION_GAINS", "RACK_PINION_TIMING",
]

COUPLED, MASTER_ALONE, SLAVE_ALONE = kernel.COUPLED, kernel.MASTER_ALONE, kernel.SLAVE_ALONE
COUPLINGS = (COUPLED, MASTER_ALONE, SLAVE_ALONE)
MOTORS = ("master", "slave")
OUTPUT_COLUMNS = {
    "master_position": kernel.O_X_M, "master_velocity": kernel.O_V_M,
    "master_force": kernel.O_F_M, "slave_position": kernel.O_X_S,
    "slave_velocity": kernel.O_V_S, "slave_force": kernel.O_F_S,
    "load_position": kernel.O_X_L, "load_velocity": kernel.O_V_L,
    "bumper_force": kernel.O_BUMPER_FORCE, "position_feedback": kernel.O_FEEDBACK,
}

K_TR_THESIS = 190.0
"""Linear-rotary conversion factor (N per N·m) behind the thesis's preload-loss forces:
F_loss = 2 τ_p K_tr gives 1064 N at 4 %, 5320 N at 20 % and 6650 N at 25 % of 70 N·m
(measured ≈ 1100, 5300, 6600 N, Ch. 3.4.3). The thesis does not print the pinion radius."""


def _non_negative(name: str, value: float) -> None:
    if not value >= 0.0:
        raise ValueError(f"{name} must be >= 0, got {value}")


@dataclass(frozen=True)
class Bumper:
    """A rigid stop with a load cell: one-sided spring (N/m) and damper (N·s/m).

    `position` (m) is where the load touches it; its sign is the side it stops: a bumper at
    x < 0 stops motion towards −x. The default stiffness, 66.7 N/µm, is the thesis's
    machine with its bumper: ≈ 20 kN for the 300 µm command of Ch. 3.4.3.
    """

    position: float = -50e-6
    stiffness: float = 66.7e6
    damping: float = 7.5e4

    def __post_init__(self) -> None:
        if self.position == 0.0:
            raise ValueError("bumper position must be != 0: its sign gives the side it stops")
        positive("stiffness", self.stiffness)
        _non_negative("damping", self.damping)

    @property
    def side(self) -> float:
        """−1: stops motion towards −x; +1: towards +x."""
        return math.copysign(1.0, self.position)


RACK_PINION_FRICTION = DirectionalFriction(
    positive=AnderssonFriction.from_engineering(600.0, 900.0, 300.0, 0.1, 0.05, 1.0),
    negative=AnderssonFriction.from_engineering(600.0, 900.0, 300.0, 0.1, 0.05, 1.0),
)
"""Guideway friction of the 8500 kg carriage (Eq. 5.2; not in the thesis: F_c ≈ 0.7 % of
its weight, F_s 900 N, v_s 300 mm/min, σ 0.1 N·min/mm). k_tanh 0.05 min/mm (the lab bench's
0.25 / 5): at rest the tanh law creeps like a damper F_s·k_tanh ≈ 2.7e6 N·s/m, so a static
load relaxes within a bus step's settling instead of holding a friction force."""


@dataclass(frozen=True)
class RackPinionAxis:
    """Mechanics of the axis (SI; DIGEST §3, Ch. 3.4).

    m_load (kg); J_motor, J_gearbox (motor side), J_pinion (kg·m²); i_red; pinion_radius
    (m); k_master, k_slave: drive-train stiffness at the rack (N/m, Eq. 3.4);
    backlash_master, backlash_slave: dead-zone width at the rack (m); damping_ratio of each
    motor on its drive train; motor_damping: viscous drag of motor and gearbox at the rack
    (N·s/m); rated_torque (N·m); friction of the guideways; bumper (None: free travel).
    """

    m_load: float = 8500.0
    J_motor: float = 7500e-6
    J_gearbox: float = 948e-6
    J_pinion: float = 0.0
    i_red: float = 28.0
    pinion_radius: float = 28.0 / K_TR_THESIS
    k_master: float = 81e6
    k_slave: float = 100e6
    backlash_master: float = 314e-6
    backlash_slave: float = 363e-6
    damping_ratio: float = 0.05
    motor_damping: float = 2000.0
    rated_torque: float = 70.0
    friction: DirectionalFriction | AnderssonFriction = RACK_PINION_FRICTION
    bumper: Bumper | None = Bumper()

    def __post_init__(self) -> None:
        for name in ("m_load", "J_motor", "i_red", "pinion_radius", "k_master", "k_slave",
                     "rated_torque"):
            positive(name, getattr(self, name))
        for name in ("J_gearbox", "J_pinion", "backlash_master", "backlash_slave",
                     "damping_ratio", "motor_damping"):
            _non_negative(name, getattr(self, name))

    @property
    def K_tr(self) -> float:
        """Linear-rotary conversion factor i_red / r_pinion (N per N·m, 1/m)."""
        return self.i_red / self.pinion_radius

    @property
    def J_eq(self) -> float:
        """Equivalent inertia of one motor, Eq. (3.3): J_motor + J_gearbox + J_pinion/i_red²."""
        return self.J_motor + self.J_gearbox + self.J_pinion / self.i_red**2

    @property
    def m_motor(self) -> float:
        """One motor's equivalent inertia as a mass at the rack, J_eq·K_tr² (kg)."""
        return self.J_eq * self.K_tr**2

    @property
    def rated_force(self) -> float:
        """The rated torque as a force at the rack (N)."""
        return self.rated_torque * self.K_tr

    def drive_train_damping(self, motor: str) -> float:
        """Damper of a drive train (N·s/m): 2 ζ √(k m_motor)."""
        k = self.k_master if motor == "master" else self.k_slave
        return 2.0 * self.damping_ratio * math.sqrt(k * self.m_motor)

    def mechanics_vector(self) -> np.ndarray:
        """The kernel's mechanics vector."""
        vector = np.zeros(kernel.MECHANICS_COUNT)
        vector[kernel.M_MOTOR] = self.m_motor
        vector[kernel.M_LOAD] = self.m_load
        vector[kernel.M_K_M], vector[kernel.M_K_S] = self.k_master, self.k_slave
        vector[kernel.M_C_M] = self.drive_train_damping("master")
        vector[kernel.M_C_S] = self.drive_train_damping("slave")
        vector[kernel.M_BACKLASH_M] = self.backlash_master
        vector[kernel.M_BACKLASH_S] = self.backlash_slave
        vector[kernel.M_MOTOR_DAMPING] = self.motor_damping
        if self.bumper is not None:
            vector[kernel.M_BUMPER_POSITION] = self.bumper.position
            vector[kernel.M_BUMPER_SIDE] = self.bumper.side
            vector[kernel.M_BUMPER_K] = self.bumper.stiffness
            vector[kernel.M_BUMPER_C] = self.bumper.damping
        return vector


@dataclass(frozen=True)
class Preload:
    """Electronic preload: level τ_p as a fraction of the rated torque, weighting factors
    K_Tm, K_Ts (Fig. 3.2; 0.5 each for identical motors)."""

    level: float = 0.10
    K_Tm: float = 0.5
    K_Ts: float = 0.5

    def __post_init__(self) -> None:
        if not 0.0 <= self.level <= 1.0:
            raise ValueError(f"preload level must be within 0…1 of the rated torque, "
                             f"got {self.level}")
        for name in ("K_Tm", "K_Ts"):
            positive(name, getattr(self, name))


@dataclass(frozen=True)
class TorqueEqualisation:
    """The preload PI, Eq. (3.10): K_p ((m/s)/N at the rack), T_i (s), and the largest
    velocity correction it may add (m/s).

    K_p acts through each motor's velocity PI: K_p · K_p,velocity is the loop gain of the
    equalisation (0.4 with the default gains; it must stay below 1). The long T_i makes the
    flank change after a preload loss slow, as measured (Ch. 3.4.3: "the pinion flank
    contact transition is not fast enough to be neglected").
    """

    K_p: float = 1.67e-6
    T_i: float = 0.5
    limit: float = 0.01

    def __post_init__(self) -> None:
        _non_negative("K_p", self.K_p)
        positive("T_i", self.T_i)
        positive("limit", self.limit)


RACK_PINION_GAINS = CascadeGains(K_p=2.4e5, T_i=0.04, K_v=10.0)
"""Each motor's velocity PI (at the rack) and the position gain. K_p puts the crossover on a
motor's own inertia (above the drive-train mode, where the load is decoupled) at ≈ 125 Hz;
on the whole axis it gives ≈ 8 Hz coupled (Eq. 4.2 with M = 9110 kg over two motors),
with T_i and K_v near Eqs. (4.8, 4.12) for that bandwidth."""

RACK_PINION_TIMING = ServoTiming(f_velocity=8000.0, f_position=1000.0, delay=0.25e-3,
                                 cycle=1e-3)
"""8 kHz velocity loops, 1 kHz position loop (Ch. 3.3), 0.25 ms current-loop delay."""


class RackPinionSimulator(CycleSimulator):
    """The axis and its master–slave controller, advanced one bus cycle at a time.

    `step_cycle` advances one cycle (`timing.cycle`), `simulate` many from arrays in one
    compiled call; both continue from, and update, the same state. The driving node's
    mode and targets run the axis (the master's when coupled); each motor adds its own
    force offset, and in CST applies its own target force (no preload then).
    """

    _KERNEL = kernel

    def __init__(
        self,
        axis: RackPinionAxis = RackPinionAxis(),
        master: CascadeGains = RACK_PINION_GAINS,
        slave: CascadeGains = RACK_PINION_GAINS,
        equalisation: TorqueEqualisation = TorqueEqualisation(),
        preload: Preload = Preload(),
        timing: ServoTiming = RACK_PINION_TIMING,
        torque_limit: float = 3.0,
        physics_substeps: int = 1,
        velocity_feedforward: bool = True,
    ) -> None:
        """torque_limit: the drives' peak torque as a multiple of the rated torque."""
        positive("physics_substeps", physics_substeps)
        super().__init__(timing, int(physics_substeps), velocity_feedforward)
        self._inputs = np.zeros((1, kernel.INPUT_COLUMNS))
        self._outputs = np.zeros((1, kernel.OUTPUT_COLUMNS))
        self.axis = axis
        self._mechanics = axis.mechanics_vector()
        self._friction_table = axis.friction.table()
        self._params[kernel.P_ENABLED_M] = self._params[kernel.P_ENABLED_S] = 1.0
        self._gains = {"master": master, "slave": slave}
        for motor in MOTORS:
            self.set_gains(motor, self._gains[motor])
        self.equalisation = equalisation
        self.preload = preload
        self.force_limit = torque_limit * axis.rated_force
        self._delay_lines = np.zeros((2, timing.delay_ticks + 1))
        self._coupling = COUPLED
        self.reset()

    # -- configuration -------------------------------------------------------------------

    def gains(self, motor: str) -> CascadeGains:
        """Velocity PI and position gain of `motor` ("master" or "slave")."""
        return self._gains[motor]

    def set_gains(self, motor: str, gains: CascadeGains) -> None:
        """Use new gains for `motor` from the next cycle on (its PI integral is kept)."""
        k_p, inverse_t_i, k_v = ((kernel.P_K_P_M, kernel.P_INV_T_I_M, kernel.P_K_V_M)
                                 if _motor_index(motor) == 0
                                 else (kernel.P_K_P_S, kernel.P_INV_T_I_S, kernel.P_K_V_S))
        self._gains[motor] = gains
        self._params[k_p], self._params[inverse_t_i] = gains.K_p, 1.0 / gains.T_i
        self._params[k_v] = gains.K_v

    @property
    def preload(self) -> Preload:
        """Preload level and weighting factors in use."""
        return self._preload

    @preload.setter
    def preload(self, preload: Preload) -> None:
        self._preload = preload
        self._params[kernel.P_PRELOAD_FORCE] = preload.level * self.axis.rated_force
        self._params[kernel.P_K_TM], self._params[kernel.P_K_TS] = preload.K_Tm, preload.K_Ts

    @property
    def equalisation(self) -> TorqueEqualisation:
        """The torque-equalisation PI in use."""
        return self._equalisation

    @equalisation.setter
    def equalisation(self, equalisation: TorqueEqualisation) -> None:
        self._equalisation = equalisation
        self._params[kernel.P_K_P_PRELOAD] = equalisation.K_p
        self._params[kernel.P_INV_T_I_PRELOAD] = 1.0 / equalisation.T_i
        self._params[kernel.P_PRELOAD_LIMIT] = equalisation.limit

    @property
    def coupling(self) -> int:
        """COUPLED, MASTER_ALONE or SLAVE_ALONE."""
        return self._coupling

    @coupling.setter
    def coupling(self, coupling: int) -> None:
        """Change the coupling: the controllers' memories are cleared and the new feedback
        encoder is referenced to the linear scale, so the axis position is the scale's
        value at the change (from coupled, the feedback does not jump)."""
        if coupling not in COUPLINGS:
            raise ValueError(f"coupling must be one of {COUPLINGS}, got {coupling}")
        if coupling == self._coupling:
            return
        s = self._state
        kernel.reference_feedback(s, coupling)
        for memory in (kernel.S_INTEGRAL_M, kernel.S_ERROR_M, kernel.S_INTEGRAL_S,
                       kernel.S_ERROR_S, kernel.S_INTEGRAL_P, kernel.S_ERROR_P):
            s[memory] = 0.0
        s[kernel.S_HAS_PREVIOUS_TARGET] = 0.0
        self._coupling = coupling
        self._params[kernel.P_COUPLING] = coupling

    def enabled(self, motor: str) -> bool:
        """Whether `motor`'s power stage is on."""
        return bool(self._params[_enabled_index(motor)] > 0.0)

    def set_enabled(self, motor: str, on: bool) -> None:
        """Power stage of `motor` on or off (off: no force, its PI memory cleared)."""
        self._params[_enabled_index(motor)] = 1.0 if on else 0.0

    # -- state ---------------------------------------------------------------------------

    def _value(self, column: int) -> float:
        return float(self._outputs[-1, column])

    def motor_position(self, motor: str) -> float:
        """Motor position at the rack (m): its encoder angle × r_pinion / i_red."""
        return self._value(kernel.O_X_M if _motor_index(motor) == 0 else kernel.O_X_S)

    def motor_velocity(self, motor: str) -> float:
        """Motor velocity at the rack (m/s)."""
        return self._value(kernel.O_V_M if _motor_index(motor) == 0 else kernel.O_V_S)

    def motor_force(self, motor: str) -> float:
        """Force the motor applies at the rack, after delay and saturation (N): τ·K_tr."""
        return self._value(kernel.O_F_M if _motor_index(motor) == 0 else kernel.O_F_S)

    @property
    def load_position(self) -> float:
        """Load position on the linear scale (m)."""
        return self._value(kernel.O_X_L)

    @property
    def load_velocity(self) -> float:
        """Load velocity (m/s)."""
        return self._value(kernel.O_V_L)

    @property
    def bumper_force(self) -> float:
        """Compression of the bumper's load cell (N, ≥ 0)."""
        return self._value(kernel.O_BUMPER_FORCE)

    @property
    def position_feedback(self) -> float:
        """What the position loop closes on (m): the scale when coupled, the driving motor's
        encoder, referenced to the scale at the last coupling change, when alone."""
        return self._value(kernel.O_FEEDBACK)

    def reset(self, position: float = 0.0) -> None:
        """Load and motors at rest at `position` (m), pinions centred in their play,
        controllers cleared, coupling kept, time 0."""
        s = self._state
        s[:] = 0.0
        s[kernel.S_X_M] = s[kernel.S_X_S] = s[kernel.S_X_L] = position
        self._delay_lines[:] = 0.0
        self._cycle_count = 0
        self._outputs[-1] = 0.0
        for column in (kernel.O_X_M, kernel.O_X_S, kernel.O_X_L, kernel.O_FEEDBACK):
            self._outputs[-1, column] = position

    # -- stepping ------------------------------------------------------------------------

    def step_cycle(self, mode: int, target_position: float, target_velocity: float = 0.0,
                   velocity_offset: float = 0.0, target_force: tuple[float, float] = (0.0, 0.0),
                   force_offset: tuple[float, float] = (0.0, 0.0),
                   load_force: float = 0.0) -> None:
        """Advance one bus cycle in `mode` (CSP, CSV, CST); forces per (master, slave) (N)."""
        check_mode(mode)
        self._modes[0] = mode
        self._inputs[0] = (target_position, target_velocity, velocity_offset, target_force[0],
                           force_offset[0], target_force[1], force_offset[1], load_force)
        self._run(self._modes, self._inputs, self._outputs)

    def simulate(self, mode: int | np.ndarray, target_position: float | np.ndarray,
                 target_velocity: float | np.ndarray = 0.0,
                 velocity_offset: float | np.ndarray = 0.0,
                 load_force: float | np.ndarray = 0.0) -> dict[str, np.ndarray]:
        """Advance one cycle per array element (scalars broadcast) in one compiled call.

        Returns per-cycle arrays after each cycle, keyed as `OUTPUT_COLUMNS`, and time (s).
        """
        modes, (position, velocity, offset, load) = self._per_cycle(
            mode, target_position, target_velocity, velocity_offset, load_force)
        inputs = np.zeros((modes.size, kernel.INPUT_COLUMNS))
        inputs[:, kernel.I_TARGET_POSITION] = position
        inputs[:, kernel.I_TARGET_VELOCITY] = velocity
        inputs[:, kernel.I_VELOCITY_OFFSET] = offset
        inputs[:, kernel.I_LOAD_FORCE] = load
        outputs = np.zeros((modes.size, kernel.OUTPUT_COLUMNS))
        times = self._end_times(modes.size)
        self._run(modes, inputs, outputs)
        if modes.size:
            self._outputs[-1] = outputs[-1]
        result = {name: outputs[:, column] for name, column in OUTPUT_COLUMNS.items()}
        result["time"] = times
        return result

    def _run(self, modes: np.ndarray, inputs: np.ndarray, outputs: np.ndarray) -> None:
        kernel.run_cycles(self._state, self._delay_lines, self._params, self._mechanics,
                          self._friction_table, modes, inputs, outputs)
        self._cycle_count += modes.size


def _motor_index(motor: str) -> int:
    if motor not in MOTORS:
        raise ValueError(f"motor must be one of {MOTORS}, got {motor!r}")
    return MOTORS.index(motor)


def _enabled_index(motor: str) -> int:
    return kernel.P_ENABLED_M if _motor_index(motor) == 0 else kernel.P_ENABLED_S
