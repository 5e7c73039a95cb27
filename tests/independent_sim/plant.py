"""The independent plant: an n-mass chain in continuous state space, discretized exactly
(zero-order hold on the forces, `scipy.linalg.expm` of the augmented matrix) at a fine physics
step, closed by a sampled P-PI cascade with its own rates.

Shares no code with feedbench: every force below is written from its physics.

State s = [x_0 … x_{n−1}, v_0 … v_{n−1}] (m, m/s); mass 0 is the motor side, where the drive
force, the encoder and the guide friction act. Springs and dampers join pairs of masses:
M v̇ = −K x − C v + u. One contact element is allowed: a backlash load (optional, the last
mass) that touches the motor through a stiff contact spring only when the play L is used up, or
a play inside a spring from the motor (a dead zone in the drive train, Ch. 3.2.3: its spring
and damper act only beyond ±L/2); the three contact states (free, pushed, pulled) each have
their own exact discretization, the constant ±k L/2 of the contact force entering as a held
force. Forces that are nonlinear in the state (friction, ripple, cubic
stiffening, the load's friction) are held over each physics step: the position-dependent ones
evaluated at the state half a step ahead (first-order extrapolation), which keeps a held cubic
spring from pumping energy into a lightly damped mode; friction at the step's velocity (it only
dissipates, and FRICTION_SMOOTHING keeps it stable). The recorded force is the drive's command
averaged over each 1 kHz cycle (it leads the acting force by the delay); positions are the
encoder's at the cycle's end, or latched a whole number of physics steps before it (a channel
skew).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
from numba import njit

PHYSICS_HZ = 8000.0
"""Physics step rate (Hz): 2 steps per velocity-loop period, 8 per recording cycle."""

VELOCITY_STEPS = 2
POSITION_STEPS = 8
RECORD_STEPS = 8
"""Physics steps per velocity-loop (4 kHz), position-loop and recording period (1 kHz)."""

FRICTION_SMOOTHING = 1e-3
"""Velocity (m/s) over which the Coulomb force turns round: F_c tanh(v / v_ε). Small enough
to be a step above the closure's standstill threshold, large enough that the held friction
force is stable at the physics step (F_c/v_ε · dt / m ≤ 1 for F_c ≤ 200 N, m ≥ 25 kg)."""

CONTACT_HZ = 400.0
CONTACT_ZETA = 0.3
"""Backlash contact: the load on the contact spring rings at 400 Hz with ζ = 0.3."""


@dataclass(frozen=True)
class Spring:
    """A spring k (N/m) and damper c (N·s/m) between masses i and j; cubic stiffening adds
    k3 d³ (N/m³), d = x_j − x_i; a play (m, total width; only with i = 0 and no k3) makes
    both act on d ∓ play/2 beyond ±play/2 and vanish inside it (the dead zone)."""

    i: int
    j: int
    k: float
    c: float
    k3: float = 0.0
    play: float = 0.0


@dataclass(frozen=True)
class Friction:
    """Guide friction on the motor side (N, N·s/m, m/s): σ v + F_c tanh(v/v_ε)
    + (F_s − F_c) exp(−(|v|/v_s)^δ) tanh(v/v_ε) + Δσ⁻ v (v < 0 only)."""

    sigma: float = 0.0
    F_c: float = 0.0
    dF_s: float = 0.0
    v_s: float = 1.0
    delta: float = 2.0
    dsigma_neg: float = 0.0


@dataclass(frozen=True)
class Plant:
    """The axis: masses (kg; 0 = motor), springs, friction, and the motor-side extras.

    offset (N): a constant force on the motor side (gravity, a counterweight);
    ripple (N, m, rad): A sin(2π x / pitch + phase) on the motor side;
    backlash (kg, N, m): a load mass behind a play, with its own Coulomb friction;
    table_coulomb (N): the Coulomb level of mass 1's own guideways (a table on guides).
    """

    masses: tuple[float, ...]
    springs: tuple[Spring, ...]
    friction: Friction = field(default_factory=Friction)
    offset: float = 0.0
    ripple: tuple[float, float, float] = (0.0, 1.0, 0.0)
    backlash: tuple[float, float, float] | None = None
    table_coulomb: float = 0.0

    @property
    def all_masses(self) -> tuple[float, ...]:
        """The masses including the backlash load (kg)."""
        return self.masses + ((self.backlash[0],) if self.backlash else ())

    @property
    def contact(self) -> Spring | None:
        """The one contact element: the backlash load's contact spring (CONTACT_HZ,
        CONTACT_ZETA) or the spring with a play; None if there is none."""
        played = [s for s in self.springs if s.play]
        if self.backlash:
            load = len(self.masses)
            k_c = self.backlash[0] * (2 * math.pi * CONTACT_HZ) ** 2
            c_c = 2 * CONTACT_ZETA * math.sqrt(k_c * self.backlash[0])
            played.append(Spring(0, load, k_c, c_c, play=self.backlash[2]))
        if len(played) > 1 or any(s.i != 0 or s.k3 for s in played):
            raise ValueError("one contact element only, from the motor (mass 0), not cubic")
        return played[0] if played else None

    def coulomb(self) -> np.ndarray:
        """Coulomb level (N) acting on each mass but the motor (whose friction is
        `friction`): the table's guideways' on mass 1, the backlash load's; 0 elsewhere."""
        levels = np.zeros(len(self.all_masses))
        if self.table_coulomb:
            if len(self.masses) < 2:
                raise ValueError("table friction needs a table: a mass 1 on the motor's spring")
            levels[1] = self.table_coulomb
        if self.backlash:
            levels[-1] = self.backlash[1]
        return levels


@dataclass(frozen=True)
class Drive:
    """The drive: P position loop (K_v, 1/s), PI velocity loop (K_p N·s/m, T_i s), force
    limit (N), force delay (s, whole physics steps), force-constant error: the force constant
    saturates with the current and is off by a gain, acting force = command / ((1 + β |command|)
    · gain) (β in 1/N)."""

    K_p: float
    T_i: float
    K_v: float
    force_limit: float
    delay: float
    beta: float = 0.0
    gain: float = 1.0


@dataclass(frozen=True)
class Sensors:
    """Encoder resolution (m) and noise (m RMS), force-reading noise (N RMS), tip
    accelerometer noise (m/s² RMS); position_skew (s, whole physics steps): the recorded
    position is latched this long before the cycle's end, where its time stamp says."""

    resolution: float = 1e-7
    position_noise: float = 2e-8
    force_noise: float = 1.5
    acceleration_noise: float = 0.05
    position_skew: float = 0.0


def _matrices(plant: Plant, contact: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Continuous A (2n×2n), B (2n×n) and the constant force (n) of one contact state
    (0 free, +1 motor pushes the load, −1 motor pulls it)."""
    masses = np.array(plant.all_masses)
    n = masses.size
    K, C, const = np.zeros((n, n)), np.zeros((n, n)), np.zeros(n)
    links = [s for s in plant.springs if not s.play]
    touching = plant.contact
    if touching and contact:
        links.append(touching)
        push = contact * touching.k * 0.5 * touching.play     # the spring acts on d ∓ L/2
        const[touching.j] -= push
        const[0] += push
    for s in links:
        for matrix, value in ((K, s.k), (C, s.c)):
            matrix[s.i, s.i] += value
            matrix[s.j, s.j] += value
            matrix[s.i, s.j] -= value
            matrix[s.j, s.i] -= value
    C[0, 0] += plant.friction.sigma
    inv = np.diag(1.0 / masses)
    A = np.block([[np.zeros((n, n)), np.eye(n)], [-inv @ K, -inv @ C]])
    B = np.vstack([np.zeros((n, n)), inv])
    return A, B, const


def discretize(plant: Plant, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretization of every contact state: Ad (3×2n×2n),
    Bd (3×2n×n), and the held constant force's state increment (3×2n)."""
    Ads, Bds, consts = [], [], []
    for contact in (0, 1, -1):
        A, B, const = _matrices(plant, contact)
        n2, n = B.shape
        augmented = np.zeros((n2 + n, n2 + n))
        augmented[:n2, :n2], augmented[:n2, n2:] = A, B
        phi = scipy.linalg.expm(augmented * dt)
        Ads.append(phi[:n2, :n2])
        Bds.append(phi[:n2, n2:])
        consts.append(phi[:n2, n2:] @ const)
    return np.array(Ads), np.array(Bds), np.array(consts)


def natural_modes(plant: Plant, contact: int = 0) -> list[tuple[float, float]]:
    """(frequency Hz, damping ratio) of every oscillating pole of the free plant (no drive),
    in a contact state (0 free, ±1 in contact)."""
    A, _, _ = _matrices(plant, contact)
    poles = np.linalg.eigvals(A)
    poles = poles[poles.imag > 1e-6]
    return sorted((abs(p) / (2 * math.pi), -p.real / abs(p)) for p in poles)


@dataclass(frozen=True)
class Run:
    """A recording at the recording rate: time (s), encoder position (m), force read (N),
    force without reading noise (N), reference (m), excitation (N), the acceleration of
    mass 1 read by an accelerometer (m/s², None on a rigid axis); and the physics states
    (m, m/s) at the recording instants."""

    time: np.ndarray
    position: np.ndarray
    force: np.ndarray
    force_clean: np.ndarray
    reference: np.ndarray
    excitation: np.ndarray
    tip_acceleration: np.ndarray | None
    states: np.ndarray


def simulate(plant: Plant, drive: Drive, sensors: Sensors, reference: np.ndarray,
             feedforward: np.ndarray, excitation: np.ndarray, seed: int) -> Run:
    """Run the closed loop over physics-rate reference (m), velocity feedforward (m/s) and
    excitation (N) arrays; record at 1 kHz."""
    dt = 1.0 / PHYSICS_HZ
    Ad, Bd, const = discretize(plant, dt)
    steps = (reference.size - 1) // RECORD_STEPS * RECORD_STEPS
    rng = np.random.default_rng(seed)
    encoder_noise = rng.normal(0.0, sensors.position_noise, steps // VELOCITY_STEPS + 1)
    record_noise = rng.normal(0.0, sensors.position_noise, steps // RECORD_STEPS)
    f = plant.friction
    springs = np.array([[s.i, s.j, s.k3] for s in plant.springs if s.k3] or np.zeros((0, 3)))
    touching = plant.contact
    motor = np.array([f.F_c, f.dF_s, f.v_s, f.delta, f.dsigma_neg, plant.offset,
                      *plant.ripple, FRICTION_SMOOTHING])
    control = np.array([drive.K_p, drive.T_i, drive.K_v, drive.force_limit, drive.beta,
                        drive.gain, sensors.resolution])
    timing = np.array([round(drive.delay * PHYSICS_HZ), round(sensors.position_skew * PHYSICS_HZ),
                       touching.j if touching else -1], dtype=np.int64)
    if not 0 <= timing[1] < RECORD_STEPS:
        raise ValueError(f"position_skew must be within one cycle, got {sensors.position_skew}")
    x_rec, f_rec, s_rec = _loop(Ad, Bd, const, springs, motor, control, timing,
                                plant.coulomb(), touching.play if touching else 0.0,
                                reference[:steps], feedforward[:steps], excitation[:steps],
                                encoder_noise, record_noise, dt)
    cycles = steps // RECORD_STEPS
    force_noise = rng.normal(0.0, sensors.force_noise, cycles)
    held = np.repeat(excitation[:steps:VELOCITY_STEPS], VELOCITY_STEPS)   # as the loop adds it
    exc = held.reshape(cycles, RECORD_STEPS).mean(axis=1)
    tip = (None if len(plant.masses) < 2 else tip_acceleration(plant, s_rec)
           + rng.normal(0.0, sensors.acceleration_noise, cycles))
    return Run(np.arange(1, cycles + 1) * RECORD_STEPS * dt, x_rec, f_rec + force_noise, f_rec,
               reference[RECORD_STEPS:steps + 1:RECORD_STEPS], exc, tip, s_rec)


def tip_acceleration(plant: Plant, states: np.ndarray) -> np.ndarray:
    """Acceleration (m/s²) of mass 1 at each state (rows): its springs and dampers in the
    state's contact state and cubic stiffening; nothing else acts on it."""
    n = len(plant.all_masses)
    acceleration = np.zeros(states.shape[0])
    touching = plant.contact
    gap = states[:, 0] - states[:, touching.j] if touching else np.zeros(states.shape[0])
    half = 0.5 * touching.play if touching else 0.0
    for contact, rows in ((0, np.abs(gap) <= half), (1, gap > half), (-1, gap < -half)):
        A, _, const = _matrices(plant, contact)
        acceleration[rows] = states[rows] @ A[n + 1] + const[1] / plant.masses[1]
    for s in plant.springs:
        if 1 in (s.i, s.j):
            d = states[:, s.j] - states[:, s.i]
            acceleration += (1.0 if s.i == 1 else -1.0) * s.k3 * d ** 3 / plant.masses[1]
    return acceleration


@njit(cache=True)
def _motor_force(v: float, x: float, p: np.ndarray) -> float:
    """Friction, offset and ripple acting on the motor side (N), as a force opposing +x."""
    F_c, dF_s, v_s, delta, dsig, offset, A, pitch, phase, v_eps = (
        p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7], p[8], p[9])
    turn = math.tanh(v / v_eps)
    force = (F_c + dF_s * math.exp(-(abs(v) / v_s) ** delta)) * turn + offset
    if v < 0.0:
        force += dsig * v
    return force + A * math.sin(2.0 * math.pi * x / pitch + phase)


@njit(cache=True)
def _loop(Ad, Bd, const, springs, motor, control, timing, coulomb, play, reference,
          feedforward, excitation, encoder_noise, record_noise, dt):
    """The closed loop, physics step by step; timing: force delay and position skew
    (physics steps), the contact element's mass (−1: none); coulomb: Coulomb level (N) on
    each mass but the motor; play (m). Returns encoder position, mean force command per
    recording cycle, and the states at the recording instants."""
    n2 = Ad.shape[1]
    n = n2 // 2
    delay_steps, skew_steps, touching = timing[0], timing[1], timing[2]
    K_p, T_i, K_v, limit, beta, gain, resolution = (
        control[0], control[1], control[2], control[3], control[4], control[5], control[6])
    steps = reference.size
    cycles = steps // RECORD_STEPS
    x_rec = np.zeros(cycles)
    f_rec = np.zeros(cycles)
    s_rec = np.zeros((cycles, n2))
    state = np.zeros(n2)
    for i in range(n):
        state[i] = reference[0]
    fifo = np.zeros(delay_steps + 1)
    u = np.zeros(n)
    T_vel = VELOCITY_STEPS * dt
    v_cmd = 0.0
    integral = 0.0
    command = 0.0
    x_enc = round(reference[0] / resolution) * resolution
    x_prev = x_enc
    force_sum = 0.0
    latched = 0.0
    tick = 0
    for step in range(steps):
        if step % VELOCITY_STEPS == 0:
            x_prev = x_enc
            x_enc = round((state[0] + encoder_noise[tick]) / resolution) * resolution
            tick += 1
            if step % POSITION_STEPS == 0:
                v_cmd = K_v * (reference[step] - x_enc) + feedforward[step]
            error = v_cmd - (x_enc - x_prev) / T_vel if step > 0 else 0.0
            trial = integral + error * T_vel
            command = K_p * (error + trial / T_i) + excitation[step]
            if abs(command) < limit:
                integral = trial
            else:
                command = max(-limit, min(limit, command))
        fifo[step % (delay_steps + 1)] = command
        applied = fifo[(step + 1) % (delay_steps + 1)] if step >= delay_steps else 0.0
        acting = applied / ((1.0 + beta * abs(applied)) * gain)
        for k in range(n):
            u[k] = 0.0
        u[0] = acting - _motor_force(state[n], state[0] + 0.5 * dt * state[n], motor)
        for r in range(springs.shape[0]):
            i, j, k3 = int(springs[r, 0]), int(springs[r, 1]), springs[r, 2]
            d = state[j] - state[i] + 0.5 * dt * (state[n + j] - state[n + i])
            u[i] += k3 * d * d * d
            u[j] -= k3 * d * d * d
        for k in range(1, n):
            u[k] -= coulomb[k] * math.tanh(state[n + k] / motor[9])
        mode = 0
        if touching >= 0:
            gap = state[0] - state[touching]
            if gap > 0.5 * play:
                mode = 1
            elif gap < -0.5 * play:
                mode = 2
        state = Ad[mode] @ state + Bd[mode] @ u + const[mode]
        force_sum += command
        if (step + 1 + skew_steps) % RECORD_STEPS == 0:
            latched = state[0]
        if (step + 1) % RECORD_STEPS == 0:
            c = (step + 1) // RECORD_STEPS - 1
            f_rec[c] = force_sum / RECORD_STEPS
            force_sum = 0.0
            x_rec[c] = round((latched + record_noise[c]) / resolution) * resolution
            s_rec[c] = state
    return x_rec, f_rec, s_rec
