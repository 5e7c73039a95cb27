"""Compiled per-cycle loop of the rack-and-pinion master–slave axis (`models.rack_pinion`).

Layout of the state, parameter, mechanics, input and output vectors is fixed by the index
constants below so one call of `run_cycles` advances many bus cycles without returning to
Python. The friction law and the velocity PI are the lab-bench kernel's (`models._kernel`),
the dead zone is `models.effects.dead_zone`: one definition of each law.

Physics per substep h (semi-implicit Euler): spring and bumper forces from the positions at
the start of the substep, motor velocities from them (the motor's viscous drag implicit),
the load velocity with the guideway friction taken at the end-of-substep velocity (backward
Euler, `friction_velocity`), then positions from the new velocities. The scheme's
fixed point is the exact static equilibrium, so the static stiffness, backlash and preload
figures carry no discretisation error; the highest mode (a motor on its drive train,
≈ 80 Hz by default) is resolved with ω h ≈ 0.06 at 8 kHz.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from feedbench.models._kernel import (
    friction_side,
    friction_velocity,
    proof_coefficients,
    velocity_pi,
)
from feedbench.models.effects import dead_zone
from feedbench.protocols.cia402 import CSP, CST

COUPLED, MASTER_ALONE, SLAVE_ALONE = 0, 1, 2
"""Coupling modes: master–slave with preload; one motor drives, the other is off."""

# controller parameters
P_K_P_M, P_INV_T_I_M, P_K_V_M, P_K_P_S, P_INV_T_I_S, P_K_V_S, P_K_P_PRELOAD, \
    P_INV_T_I_PRELOAD, P_PRELOAD_FORCE, P_K_TM, P_K_TS, P_FORCE_LIMIT, P_PRELOAD_LIMIT, \
    P_CYCLE, P_POSITION_TICKS, P_VELOCITY_TICKS, P_PHYSICS_STEPS, P_FEEDFORWARD, \
    P_COUPLING, P_ENABLED_M, P_ENABLED_S = range(21)
PARAMETER_COUNT = 21

# mechanics (all at the rack)
M_MOTOR, M_LOAD, M_K_M, M_K_S, M_C_M, M_C_S, M_BACKLASH_M, M_BACKLASH_S, M_MOTOR_DAMPING, \
    M_BUMPER_POSITION, M_BUMPER_SIDE, M_BUMPER_K, M_BUMPER_C = range(13)
MECHANICS_COUNT = 13

# state
S_X_M, S_V_M, S_X_S, S_V_S, S_X_L, S_V_L, S_F_M, S_F_S, S_COMMAND_M, S_COMMAND_S, \
    S_INTEGRAL_M, S_ERROR_M, S_INTEGRAL_S, S_ERROR_S, S_INTEGRAL_P, S_ERROR_P, \
    S_PREVIOUS_TARGET, S_HAS_PREVIOUS_TARGET, S_DELAY_INDEX, S_FRICTION_VELOCITY, \
    S_FRICTION_FORCE, S_NEWTON_GAIN, S_FEEDBACK_OFFSET = range(23)
STATE_SIZE = 23

# per-cycle inputs (the driving node's targets; each motor's own force target and offset)
I_TARGET_POSITION, I_TARGET_VELOCITY, I_VELOCITY_OFFSET, I_TARGET_FORCE_M, I_FORCE_OFFSET_M, \
    I_TARGET_FORCE_S, I_FORCE_OFFSET_S, I_LOAD_FORCE = range(8)
INPUT_COLUMNS = 8

# per-cycle outputs
O_X_M, O_V_M, O_F_M, O_X_S, O_V_S, O_F_S, O_X_L, O_V_L, O_BUMPER_FORCE, O_FEEDBACK = range(10)
OUTPUT_COLUMNS = 10

_JIT = {"cache": True, "error_model": "numpy"}
_HOT = {**_JIT, "inline": "always"}


@njit(**_HOT)
def coupling_force(gap: float, relative_velocity: float, k: float, c: float,
                   backlash: float) -> float:
    """Force (N) a drive train transmits from motor to load: k·dz(gap) + c·Δv in contact.

    gap = x_motor − x_load (m); dead zone of total width `backlash` (Ch. 3.2.3); the damper
    acts only while the flanks touch.
    """
    deflection = dead_zone(gap, backlash)
    if deflection == 0.0:
        return 0.0
    return k * deflection + c * relative_velocity


@njit(**_HOT)
def bumper_force(x_load: float, v_load: float, mechanics: tuple) -> float:
    """Force (N) of the bumper on the load: a one-sided spring-damper, it only pushes back.

    The bumper face is at `M_BUMPER_POSITION`; side −1 stops motion towards −x, +1 towards
    +x, 0 means no bumper.
    """
    side = mechanics[M_BUMPER_SIDE]
    if side == 0.0:
        return 0.0
    penetration = side * (x_load - mechanics[M_BUMPER_POSITION])
    if penetration <= 0.0:
        return 0.0
    push = mechanics[M_BUMPER_K] * penetration + mechanics[M_BUMPER_C] * side * v_load
    return -side * push if push > 0.0 else 0.0


@njit(**_HOT)
def physics_step(bodies: tuple, linearisation: tuple, force_m: float, force_s: float,
                 load_force: float, mechanics: tuple, h: float, positive: tuple,
                 negative: tuple, proof: tuple) -> tuple:
    """Advance (x_m, v_m, x_s, v_s, x_l, v_l) by one substep h (s); returns it and the
    friction linearisation. force_m, force_s: motor forces at the rack (N)."""
    x_m, v_m, x_s, v_s, x_l, v_l = bodies
    spring_m = coupling_force(x_m - x_l, v_m - v_l, mechanics[M_K_M], mechanics[M_C_M],
                              mechanics[M_BACKLASH_M])
    spring_s = coupling_force(x_s - x_l, v_s - v_l, mechanics[M_K_S], mechanics[M_C_S],
                              mechanics[M_BACKLASH_S])
    beta_motor = h / mechanics[M_MOTOR]
    drag = 1.0 + beta_motor * mechanics[M_MOTOR_DAMPING]
    v_m = (v_m + beta_motor * (force_m - spring_m)) / drag
    v_s = (v_s + beta_motor * (force_s - spring_s)) / drag
    beta_load = h / mechanics[M_LOAD]
    v_free = v_l + beta_load * (spring_m + spring_s + bumper_force(x_l, v_l, mechanics)
                                + load_force)
    v_l, linearisation = friction_velocity(v_free, beta_load, linearisation, positive, negative,
                                           proof)
    return (x_m + h * v_m, v_m, x_s + h * v_s, v_s, x_l + h * v_l, v_l), linearisation


@njit(**_HOT)
def feedback_source(bodies: tuple, coupling: int) -> float:
    """The encoder the position loop closes on (m): the linear scale when coupled, the
    driving motor's encoder when alone."""
    if coupling == MASTER_ALONE:
        return bodies[0]
    if coupling == SLAVE_ALONE:
        return bodies[2]
    return bodies[4]


@njit(**_HOT)
def position_feedback(bodies: tuple, coupling: int, offset: float) -> float:
    """The position feedback (m): the source encoder minus the reference offset set when
    the coupling last changed (`reference_feedback`; 0 for the scale)."""
    return feedback_source(bodies, coupling) - offset


@njit(**_JIT)
def reference_feedback(state: np.ndarray, coupling: int) -> None:
    """Reference the feedback of `coupling` to the linear scale: the new source starts
    from the scale's value, as a CNC sets the axis position when it changes encoders."""
    bodies = (state[S_X_M], state[S_V_M], state[S_X_S], state[S_V_S], state[S_X_L], state[S_V_L])
    state[S_FEEDBACK_OFFSET] = feedback_source(bodies, coupling) - state[S_X_L]


@njit(**_JIT)
def clear_motor(state: np.ndarray, delay_lines: np.ndarray, motor: int) -> None:
    """Forget one motor's velocity-PI memory, its delay line and its force (power off)."""
    integral, error, force, command = ((S_INTEGRAL_M, S_ERROR_M, S_F_M, S_COMMAND_M) if motor == 0
                                       else (S_INTEGRAL_S, S_ERROR_S, S_F_S, S_COMMAND_S))
    state[integral] = state[error] = state[force] = state[command] = 0.0
    delay_lines[motor, :] = 0.0


@njit(**_JIT)
def clear_preload(state: np.ndarray) -> None:
    """Forget the torque-equalisation PI's memory."""
    state[S_INTEGRAL_P] = 0.0
    state[S_ERROR_P] = 0.0


@njit(**_HOT)
def motor_active(params: np.ndarray, motor: int) -> bool:
    """Whether a motor produces force: its power stage on and not switched off by the coupling."""
    coupling = int(params[P_COUPLING])
    if motor == 0:
        return params[P_ENABLED_M] > 0.0 and coupling != SLAVE_ALONE
    return params[P_ENABLED_S] > 0.0 and coupling != MASTER_ALONE


@njit(**_HOT)
def preload_correction(state_p: tuple, command_m: float, command_s: float, params: np.ndarray,
                       period: float) -> tuple:
    """Torque-equalisation PI (Eq. 3.10, Fig. 3.2): velocity correction u (m/s) and its memory.

    Error e = F_p − K_Tm F_m + K_Ts F_s on the last force commands (N at the rack), so that at
    rest F_m = F_ref/2 + F_p and F_s = F_ref/2 − F_p for K_Tm = K_Ts = 1/2 (Eq. 3.1); u is
    added to the master's velocity command and subtracted from the slave's.
    """
    integral, previous = state_p
    error = (params[P_PRELOAD_FORCE] - params[P_K_TM] * command_m + params[P_K_TS] * command_s)
    u, integral = velocity_pi(error, previous, integral,
                              (params[P_K_P_PRELOAD], params[P_INV_T_I_PRELOAD],
                               params[P_PRELOAD_LIMIT], period), 0.0)
    return u, (integral, error)


@njit(**_JIT)
def advance_cycle(state: np.ndarray, delay_lines: np.ndarray, params: np.ndarray,
                  mechanics: tuple, positive: tuple, negative: tuple, mode: int,
                  inputs: np.ndarray) -> None:
    """One bus cycle: position ticks (P on the feedback, CSP reference interpolated, velocity
    feed-forward), velocity ticks (each motor's Tustin PI on its own velocity, the preload PI
    coupling them when coupled), the force commands through the delay lines and the force
    limit, physics substeps."""
    coupling = int(params[P_COUPLING])
    active_m, active_s = motor_active(params, 0), motor_active(params, 1)
    if not active_m:
        clear_motor(state, delay_lines, 0)
    if not active_s:
        clear_motor(state, delay_lines, 1)
    preloading = coupling == COUPLED and active_m and active_s and mode != CST
    if not preloading:
        clear_preload(state)
    driving = active_s if coupling == SLAVE_ALONE else active_m
    position_ticks, velocity_ticks = int(params[P_POSITION_TICKS]), int(params[P_VELOCITY_TICKS])
    steps, cycle = int(params[P_PHYSICS_STEPS]), params[P_CYCLE]
    period = cycle / (position_ticks * velocity_ticks)
    h = period / steps
    proof = proof_coefficients(positive, negative, h / mechanics[M_LOAD])
    limit = params[P_FORCE_LIMIT]
    pi_m = (params[P_K_P_M], params[P_INV_T_I_M], limit, period)
    pi_s = (params[P_K_P_S], params[P_INV_T_I_S], limit, period)
    k_v = params[P_K_V_S] if coupling == SLAVE_ALONE else params[P_K_V_M]
    target = inputs[I_TARGET_POSITION]
    start = state[S_PREVIOUS_TARGET] if state[S_HAS_PREVIOUS_TARGET] > 0.0 else target
    feedforward = params[P_FEEDFORWARD] * (target - start) / cycle
    v_command = inputs[I_TARGET_VELOCITY] + inputs[I_VELOCITY_OFFSET]
    bodies = (state[S_X_M], state[S_V_M], state[S_X_S], state[S_V_S], state[S_X_L], state[S_V_L])
    linearisation = (state[S_FRICTION_VELOCITY], state[S_FRICTION_FORCE], state[S_NEWTON_GAIN])
    memory_m = (state[S_INTEGRAL_M], state[S_ERROR_M])
    memory_s = (state[S_INTEGRAL_S], state[S_ERROR_S])
    memory_p = (state[S_INTEGRAL_P], state[S_ERROR_P])
    command_m, command_s = state[S_COMMAND_M], state[S_COMMAND_S]
    index, applied_m, applied_s = int(state[S_DELAY_INDEX]), state[S_F_M], state[S_F_S]
    for tick in range(position_ticks):
        if mode == CSP:
            reference = start + tick * (target - start) / position_ticks
            feedback = position_feedback(bodies, coupling, state[S_FEEDBACK_OFFSET])
            v_command = k_v * (reference - feedback) + feedforward + inputs[I_VELOCITY_OFFSET]
        for _ in range(velocity_ticks):
            u = 0.0
            if preloading:
                u, memory_p = preload_correction(memory_p, command_m, command_s, params, period)
            if mode == CST:
                command_m = inputs[I_TARGET_FORCE_M] + inputs[I_FORCE_OFFSET_M]
                command_s = inputs[I_TARGET_FORCE_S] + inputs[I_FORCE_OFFSET_S]
            else:
                error = v_command + u - bodies[1]
                command_m, integral = velocity_pi(error, memory_m[1], memory_m[0], pi_m,
                                                  inputs[I_FORCE_OFFSET_M])
                memory_m = (integral, error)
                error = v_command - u - bodies[3]
                command_s, integral = velocity_pi(error, memory_s[1], memory_s[0], pi_s,
                                                  inputs[I_FORCE_OFFSET_S])
                memory_s = (integral, error)
            if not active_m:
                command_m, memory_m = 0.0, (0.0, 0.0)
            if not active_s:
                command_s, memory_s = 0.0, (0.0, 0.0)
            delay_lines[0, index] = command_m
            delay_lines[1, index] = command_s
            index = index + 1 if index + 1 < delay_lines.shape[1] else 0
            applied_m = min(max(delay_lines[0, index], -limit), limit)
            applied_s = min(max(delay_lines[1, index], -limit), limit)
            for _ in range(steps):
                bodies, linearisation = physics_step(bodies, linearisation, applied_m, applied_s,
                                                     inputs[I_LOAD_FORCE], mechanics, h,
                                                     positive, negative, proof)
    (state[S_X_M], state[S_V_M], state[S_X_S], state[S_V_S], state[S_X_L],
     state[S_V_L]) = bodies
    state[S_FRICTION_VELOCITY], state[S_FRICTION_FORCE], state[S_NEWTON_GAIN] = linearisation
    state[S_INTEGRAL_M], state[S_ERROR_M] = memory_m
    state[S_INTEGRAL_S], state[S_ERROR_S] = memory_s
    state[S_INTEGRAL_P], state[S_ERROR_P] = memory_p
    state[S_COMMAND_M], state[S_COMMAND_S] = command_m, command_s
    state[S_DELAY_INDEX], state[S_F_M], state[S_F_S] = index, applied_m, applied_s
    state[S_PREVIOUS_TARGET] = target
    state[S_HAS_PREVIOUS_TARGET] = 1.0 if driving and mode == CSP else 0.0


@njit(**_JIT)
def mechanics_tuple(vector: np.ndarray) -> tuple:
    """The mechanics vector as a tuple (passed by value in the inner loop)."""
    return (vector[0], vector[1], vector[2], vector[3], vector[4], vector[5], vector[6],
            vector[7], vector[8], vector[9], vector[10], vector[11], vector[12])


@njit(**_JIT)
def run_cycles(state: np.ndarray, delay_lines: np.ndarray, params: np.ndarray,
               mechanics_vector: np.ndarray, table: np.ndarray, modes: np.ndarray,
               inputs: np.ndarray, outputs: np.ndarray) -> None:
    """Advance len(modes) bus cycles; row k of `outputs` gets the state after cycle k."""
    mechanics = mechanics_tuple(mechanics_vector)
    positive, negative = friction_side(table, 0), friction_side(table, 1)
    coupling = int(params[P_COUPLING])
    for k in range(modes.size):
        advance_cycle(state, delay_lines, params, mechanics, positive, negative, modes[k],
                      inputs[k])
        outputs[k, O_X_M], outputs[k, O_V_M], outputs[k, O_F_M] = \
            state[S_X_M], state[S_V_M], state[S_F_M]
        outputs[k, O_X_S], outputs[k, O_V_S], outputs[k, O_F_S] = \
            state[S_X_S], state[S_V_S], state[S_F_S]
        outputs[k, O_X_L], outputs[k, O_V_L] = state[S_X_L], state[S_V_L]
        outputs[k, O_BUMPER_FORCE] = -mechanics[M_BUMPER_SIDE] * bumper_force(
            state[S_X_L], state[S_V_L], mechanics)
        bodies = (state[S_X_M], state[S_V_M], state[S_X_S], state[S_V_S], state[S_X_L],
                  state[S_V_L])
        outputs[k, O_FEEDBACK] = position_feedback(bodies, coupling, state[S_FEEDBACK_OFFSET])
