"""Laws of the effects a first feed-drive model often lacks, shared by the simulated world and
the closure's models (`feedbench.analysis.closure`). One definition of each law.

- force ripple periodic in position (cogging, screw or pinion pitch),
- force-level (amplitude) nonlinearity of the drive's force reading,
- backlash: the dead zone of width L_z between motor and load position (Ch. 3.2, Moradi),
- the tip transmissibility x_tip/x_mot of a mass on a spring-damper (Eqs. 4.13, 4.25).

The scalar laws are numba functions so that the compiled axis kernel can call them per
substep (`effect_forces`, `acting_force`); the array forms wrap them for analysis.
numba's disk cache does not follow calls into other modules: after editing a law here,
delete `feedbench/models/__pycache__/_kernel.*.nb*` so that the kernel is recompiled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

_JIT = {"cache": True, "error_model": "numpy"}
_HOT = {**_JIT, "inline": "always"}

# entries of the effect vector the axis kernel reads (`AxisEffects.vector`)
E_RIPPLE_AMPLITUDE, E_RIPPLE_PITCH, E_RIPPLE_PHASE, E_FORCE_LEVEL, E_BACKLASH, E_COUPLING_K, \
    E_COUPLING_C, E_LOAD_COULOMB, E_LOAD_K_TANH = range(9)
EFFECT_COUNT = 9


@dataclass(frozen=True)
class AxisEffects:
    """What the simulated axis carries beyond friction, flexure and delay (SI; 0: absent).

    ripple_amplitude (N), ripple_pitch (m), ripple_phase (rad): `ripple_force` on the
    carriage; force_level (1/N): β of `reported_force`, the drive reports F (1 + β|F|) while
    F acts; backlash (m): total play of the motor–tip coupling (`dead_zone`);
    load_coulomb (N), load_k_tanh (s/m): Coulomb friction F tanh(k v_tip) on the tip (the
    load behind a play rests on its own guideways); explicit, so it needs substeps shorter
    than 2 m_tip / (load_coulomb · load_k_tanh).
    """

    ripple_amplitude: float = 0.0
    ripple_pitch: float = 1.0
    ripple_phase: float = 0.0
    force_level: float = 0.0
    backlash: float = 0.0
    load_coulomb: float = 0.0
    load_k_tanh: float = 1500.0

    def __post_init__(self) -> None:
        if not self.ripple_pitch > 0.0:
            raise ValueError(f"ripple_pitch must be > 0, got {self.ripple_pitch}")
        if not self.backlash >= 0.0:
            raise ValueError(f"backlash must be >= 0, got {self.backlash}")
        if not (self.load_coulomb >= 0.0 and self.load_k_tanh > 0.0):
            raise ValueError("load_coulomb must be >= 0 and load_k_tanh > 0")
        if not self.force_level >= 0.0:
            raise ValueError(f"force_level must be >= 0 (saturating force constant), "
                             f"got {self.force_level}")

    def vector(self, k: float, c: float) -> np.ndarray:
        """The kernel's effect vector; k (N/m), c (N·s/m): the coupling the play sits in."""
        vector = np.zeros(EFFECT_COUNT)
        vector[:] = (self.ripple_amplitude, self.ripple_pitch, self.ripple_phase,
                     self.force_level, self.backlash, k, c, self.load_coulomb, self.load_k_tanh)
        return vector


@njit(**_HOT)
def ripple_force(x: float, amplitude: float, pitch: float, phase: float) -> float:
    """Force ripple (N) at position x (m): amplitude · sin(2π x / pitch + phase).

    amplitude in N, pitch in m (cogging pitch, screw lead, pinion circumference / teeth),
    phase in rad. Acts on the carriage like an external force.
    """
    return amplitude * math.sin(2.0 * math.pi * x / pitch + phase)


@njit(**_HOT)
def reported_force(acting: float, beta: float) -> float:
    """Force the drive reports (N) while `acting` (N) acts: F (1 + β |F|), β in 1/N.

    A force constant that falls with the current (magnetic saturation) makes the drive report
    more force than it delivers at high force levels (β > 0).
    """
    return acting * (1.0 + beta * abs(acting))


@njit(**_HOT)
def acting_force(reported: float, beta: float) -> float:
    """Exact inverse of `reported_force`: the acting force (N) behind a reported one."""
    if beta == 0.0:
        return reported
    magnitude = 2.0 * abs(reported) / (1.0 + math.sqrt(1.0 + 4.0 * beta * abs(reported)))
    return math.copysign(magnitude, reported)


@njit(**_HOT)
def dead_zone(gap: float, width: float) -> float:
    """Spring deflection (m) of a coupling with total play `width` (m) at relative position
    `gap` = x_mot − x_load (m): zero inside ±width/2 (Ch. 3.2, dead-zone backlash)."""
    half = 0.5 * width
    if gap > half:
        return gap - half
    if gap < -half:
        return gap + half
    return 0.0


@njit(**_HOT)
def has_extra_forces(effects: tuple) -> bool:
    """True if `effect_forces` can be non-zero for this effect tuple (the kernel skips it
    otherwise)."""
    return (effects[E_LOAD_COULOMB] != 0.0 or effects[E_RIPPLE_AMPLITUDE] != 0.0
            or effects[E_BACKLASH] > 0.0)


@njit(**_HOT)
def effect_forces(mechanics: tuple, effects: tuple) -> tuple[float, float]:
    """Extra forces (N) on carriage and tip for the state (x_mot, v_mot, x_tip, v_tip).

    effects: the `AxisEffects.vector` as a tuple. Ripple acts on the carriage, load friction
    on the tip. Backlash is applied as the difference between the dead-zone coupling and the
    linear one the discretised axis already contains: k (Δx − dz(Δx)), plus c Δv while the
    play is open, on the carriage, the opposite on the tip (Δx = x_mot − x_tip). All are
    held over the substep (explicit).
    """
    motor, tip = 0.0, 0.0
    if effects[E_LOAD_COULOMB] != 0.0:
        tip -= effects[E_LOAD_COULOMB] * math.tanh(effects[E_LOAD_K_TANH] * mechanics[3])
    if effects[E_RIPPLE_AMPLITUDE] != 0.0:
        motor += ripple_force(mechanics[0], effects[E_RIPPLE_AMPLITUDE],
                              effects[E_RIPPLE_PITCH], effects[E_RIPPLE_PHASE])
    if effects[E_BACKLASH] > 0.0:
        gap = mechanics[0] - mechanics[2]
        deflection = dead_zone(gap, effects[E_BACKLASH])
        correction = effects[E_COUPLING_K] * (gap - deflection)
        if deflection == 0.0:
            correction += effects[E_COUPLING_C] * (mechanics[1] - mechanics[3])
        motor += correction
        tip -= correction
    return motor, tip


@njit(**_JIT)
def _play(x: np.ndarray, width: float, start: float) -> np.ndarray:
    half = 0.5 * width
    out = np.empty_like(x)
    load = start
    for i in range(x.size):
        load = min(max(load, x[i] - half), x[i] + half)
        out[i] = load
    return out


def play(x: np.ndarray, width: float) -> np.ndarray:
    """Load position (m) dragged by motor position x (m) through a play of `width` (m).

    The rigid limit of `dead_zone` backlash: the load stays put until the motor has crossed
    the play, then follows at ±width/2 (the play operator). Starts centred on x[0].
    Hand-written (numba) because the operator is sequential and no library provides it.
    """
    x = np.ascontiguousarray(x, dtype=float)
    if not width >= 0.0:
        raise ValueError(f"width must be >= 0, got {width}")
    return _play(x, float(width), float(x[0]) if x.size else 0.0)


def tip_transmissibility(f_n: float, zeta: float) -> tuple[np.ndarray, np.ndarray]:
    """Continuous transfer function x_tip/x_mot = (c s + k)/(m s² + c s + k), Eq. (4.25)'s T.

    Returned as (numerator, denominator) in s for f_n = √(k/m)/2π (Hz, the motor-locked
    frequency of Eq. 4.13) and ζ = c / (2 √(k m)).
    """
    if not (f_n > 0.0 and zeta >= 0.0):
        raise ValueError(f"need f_n > 0 and zeta >= 0, got {f_n}, {zeta}")
    omega = 2.0 * math.pi * f_n
    return (np.array([2.0 * zeta * omega, omega**2]),
            np.array([1.0, 2.0 * zeta * omega, omega**2]))


@njit(**_JIT)
def _ripple_forces(x: np.ndarray, amplitude: float, pitch: float, phase: float) -> np.ndarray:
    out = np.empty_like(x)
    for i in range(x.size):
        out[i] = ripple_force(x[i], amplitude, pitch, phase)
    return out


@njit(**_JIT)
def _reported_forces(acting: np.ndarray, beta: float) -> np.ndarray:
    out = np.empty_like(acting)
    for i in range(acting.size):
        out[i] = reported_force(acting[i], beta)
    return out


@njit(**_JIT)
def _acting_forces(reported: np.ndarray, beta: float) -> np.ndarray:
    out = np.empty_like(reported)
    for i in range(reported.size):
        out[i] = acting_force(reported[i], beta)
    return out


def _flat(values: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(values, dtype=float).ravel()


def ripple_forces(x: np.ndarray, amplitude: float, pitch: float, phase: float) -> np.ndarray:
    """`ripple_force` over an array of positions (m), shaped like x."""
    return _ripple_forces(_flat(x), amplitude, pitch, phase).reshape(np.shape(x))


def reported_forces(acting: np.ndarray, beta: float) -> np.ndarray:
    """`reported_force` over an array of acting forces (N), shaped like it."""
    return _reported_forces(_flat(acting), beta).reshape(np.shape(acting))


def acting_forces(reported: np.ndarray, beta: float) -> np.ndarray:
    """`acting_force` over an array of reported forces (N), shaped like it."""
    return _acting_forces(_flat(reported), beta).reshape(np.shape(reported))
