"""Compiled per-substep loop of the simulated feed drive (numba, cached on disk).

The numerical scheme is explained in `feedbench.models.axis`. The persistent state lives
in flat float64 arrays whose layouts are fixed by the index constants below, so one call
of `run_cycles` advances many bus cycles without returning to Python. Inside a cycle the
state is held in scalars and tuples: helpers on the per-substep path take and return
values, never arrays, which keeps numba from reference-counting arrays in the inner loop.
The friction law, Eq. (5.2), is defined once, in `friction_force`;
`feedbench.models.friction` evaluates it through `friction_forces`.

Speed (`benchmarks/bench_physics.py`): wall time follows the instruction count per
substep (callgrind, code generated for haswell: 403 before the tangent proof below, 279
after; 157 with friction removed altogether). The law with its exp was two thirds, so
the law is evaluated only when it must be: the friction solve starts at the root of the
law's tangent at its latest evaluation, and when a curvature bound proves that root within
the solve's tolerance of the solution, that root is the solution (`proven_tangent_root`;
in steady sliding and slow holds almost always, through reversals and stick–slip rarely;
over the benchmark's run 0.30 evaluations of the law per substep instead of 1.1, 0.6
exp calls instead of 1.6; 1.39× faster in interleaved runs). Besides: Newton
divides by a derivative from the previous evaluation (`implicit_motor_velocity`); the
linear updates are summed as trees (`free_update`); multiply–adds are fused (fastmath
"contract" only: no reassociation, no approximations, IEEE NaN/inf semantics kept); a
whole `simulate` is one loop (`advance_cycle` is inlined into `run_cycles`), the effect
laws are skipped when the world has none, and the per-substep tip-acceleration trace is
computed only where it is kept.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from feedbench.models.effects import E_FORCE_LEVEL, acting_force, effect_forces, has_extra_forces
from feedbench.protocols.cia402 import CSP, CST

# columns of a friction table (rows: 0 for v >= 0, 1 for v < 0); 1/v_s saves a division
F_C, F_S, INVERSE_V_S, SIGMA, K_TANH, DELTA = range(6)

# entries of the parameter vector
P_K_P, P_INVERSE_T_I, P_K_V, P_FORCE_LIMIT, P_CYCLE, P_POSITION_TICKS, P_VELOCITY_TICKS, \
    P_PHYSICS_STEPS, P_FEEDFORWARD = range(9)
PARAMETER_COUNT = 9

# entries of the state vector
S_X_MOT, S_V_MOT, S_X_TIP, S_V_TIP, S_FORCE, S_INTEGRAL, S_PREVIOUS_ERROR, \
    S_PREVIOUS_TARGET, S_HAS_PREVIOUS_TARGET, S_DELAY_INDEX, \
    S_FRICTION_VELOCITY, S_FRICTION_FORCE, S_NEWTON_GAIN, S_TIP_FORCE, S_MEAN_FORCE = range(15)
STATE_SIZE = 15

# rows of the per-cycle input and output tables: one row per quantity, one column per cycle
# (each quantity is contiguous, so `simulate` hands out its rows without copying)
I_TARGET_POSITION, I_TARGET_VELOCITY, I_TARGET_FORCE, I_VELOCITY_OFFSET, \
    I_FORCE_OFFSET, I_TIP_FORCE = range(6)
INPUT_COUNT = 6
O_POSITION, O_VELOCITY, O_FORCE, O_TIP_POSITION, O_TIP_VELOCITY, O_TIP_ACCELERATION, \
    O_MEAN_VELOCITY, O_MEAN_FORCE = range(8)
OUTPUT_COUNT = 8
ACCELERATION_ROW = 4
"""Row of the kernel model holding the tip's continuous equation of motion (see `kernel_model`)."""

NEWTON_TOLERANCE = 1e-9
"""Accept a velocity of the implicit friction solve when the next Newton step would move it
by no more than this (m/s, 6e-5 mm/min): the bound of its error."""
NEWTON_MAX_ITERATIONS = 60
"""Enough for pure bisection of the bracket down to 1e-18 of its width."""
TANH_SATURATION = 19.1
"""Above this |argument| tanh is exactly ±1 in double precision."""
TANH_CURVATURE = 4.0 / (3.0 * math.sqrt(3.0))
"""max |tanh''(x)| = max |2 tanh(x) (1 − tanh²(x))|, reached where tanh² = 1/3."""

_JIT = {"cache": True, "error_model": "numpy",  # numpy: no ZeroDivisionError checks
        "fastmath": {"contract"}}  # fused multiply-add, nothing else
_HOT = {**_JIT, "inline": "always"}  # per-substep helpers: merged into their caller


@njit(**_HOT)
def tanh(x: float) -> float:
    """tanh through one exp: (1 − e)/(1 + e), e = exp(−2|x|); absolute error ≈ 1e-16.

    Hand-written because libm's tanh costs about three exp calls and runs every substep.
    """
    if abs(x) > TANH_SATURATION:
        return math.copysign(1.0, x)
    e = math.exp(-2.0 * abs(x))
    return math.copysign((1.0 - e) / (1.0 + e), x)


@njit(**_JIT)
def friction_side(table: np.ndarray, row: int) -> tuple:
    """One row of a friction table as a tuple (F_c, F_s, 1/v_s, σ, k_tanh, δ)."""
    return (table[row, F_C], table[row, F_S], table[row, INVERSE_V_S], table[row, SIGMA],
            table[row, K_TANH], table[row, DELTA])


@njit(**_HOT)
def friction_force(v: float, positive: tuple, negative: tuple) -> tuple[float, float]:
    """Andersson friction force F (N) and its slope dF/dv (N·s/m) at velocity v (m/s), Eq. (5.2).

    F = [F_c + (F_s − F_c) exp(−(|v|/v_s)^δ)] tanh(k_tanh v) + σ v, with the `positive`
    parameters for v >= 0 and the `negative` ones for v < 0 (tuples from `friction_side`).
    """
    f_c, f_s, inverse_v_s, sigma, k_tanh, delta = positive if v >= 0.0 else negative
    speed = abs(v)
    ratio = speed * inverse_v_s
    if delta == 1.0:  # the thesis's δ: skip the power and its derivative
        shape, shape_slope = ratio, inverse_v_s
    else:
        shape = ratio ** delta
        shape_slope = delta * shape / speed if speed > 0.0 else 0.0
    stribeck = (f_s - f_c) * math.exp(-shape) if f_s != f_c else 0.0
    level = f_c + stribeck
    t = tanh(k_tanh * v)
    force = level * t + sigma * v
    slope = level * k_tanh * (1.0 - t * t) - stribeck * shape_slope * abs(t) + sigma
    return force, slope


@njit(**_JIT)
def friction_forces(v: np.ndarray, table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`friction_force` over a 1-D array of velocities: forces (N) and slopes (N·s/m)."""
    positive, negative = friction_side(table, 0), friction_side(table, 1)
    force = np.empty_like(v)
    slope = np.empty_like(v)
    for i in range(v.size):
        force[i], slope[i] = friction_force(v[i], positive, negative)
    return force, slope


@njit(**_JIT)
def half_curvatures(side: tuple) -> tuple[float, float]:
    """Half the supremum of |F''| (N·s²/m²) of one side's law, Eq. (5.2): where tanh is
    saturated (|k_tanh v| > TANH_SATURATION: F = ±L(v) + σ v) and anywhere on the side.

    L(v) = F_c + ΔF e^(−|v|/v_s) (δ = 1) has |L| <= max(|F_c|, |F_s|), |L'| <= |ΔF|/v_s,
    |L''| <= |ΔF|/v_s²; with T = tanh(k_tanh v), F'' = L'' T + 2 L' k_tanh (1 − T²) +
    L k_tanh² T''. inf (no bound, never used) unless δ = 1.
    """
    f_c, f_s, inverse_v_s, _, k_tanh, delta = side
    if delta != 1.0:
        return math.inf, math.inf
    jump = abs(f_s - f_c)
    saturated = 0.5 * jump * inverse_v_s * inverse_v_s
    anywhere = saturated + jump * inverse_v_s * k_tanh + (
        0.5 * max(abs(f_c), abs(f_s)) * k_tanh * k_tanh * TANH_CURVATURE)
    return saturated, anywhere


@njit(**_JIT)
def minimum_slope(side: tuple) -> float:
    """A lower bound of F' (N·s/m) on one side (δ = 1): F' = L' T + L k_tanh (1 − T²) + σ
    with L' T >= −|ΔF|/v_s (T has the sign of v) and L k_tanh (1 − T²) >= min(0, F_c, F_s)
    k_tanh; −inf unless δ = 1."""
    f_c, f_s, inverse_v_s, sigma, k_tanh, delta = side
    if delta != 1.0:
        return -math.inf
    return sigma - abs(f_s - f_c) * inverse_v_s + min(0.0, f_c, f_s) * k_tanh


@njit(**_JIT)
def side_proof(side: tuple, beta: float, g_min: float) -> tuple[float, float, float]:
    """(e_saturated, e_anywhere, k_tanh) of one side for `proof_coefficients`."""
    saturated, anywhere = half_curvatures(side)
    if g_min <= 0.0:
        return math.inf, math.inf, side[K_TANH]
    return beta * saturated / g_min, beta * anywhere / g_min, side[K_TANH]


@njit(**_JIT)
def proof_coefficients(positive: tuple, negative: tuple, beta: float) -> tuple:
    """Per side (positive, negative): (e_saturated, e_anywhere, k_tanh), e (s/m) such that
    e (v₀ − l)² bounds the distance of the tangent root v₀ from the root of g
    (`proven_tangent_root`): e = β ½ sup|F''| / g_min, g_min = 1 + β min F' over both
    sides; inf where no bound holds (g not provably increasing, or δ != 1)."""
    g_min = 1.0 + beta * min(minimum_slope(positive), minimum_slope(negative))
    return side_proof(positive, beta, g_min), side_proof(negative, beta, g_min)


@njit(**_HOT)
def tangent_root(v_free: float, beta: float, linearisation: tuple) -> float:
    """Root v₀ (m/s) of the tangent of g(v) = v − v_free + β F(v) at the linearisation
    point l: linearisation = (l, F(l), 1/g'(l))."""
    last_v, last_force, gain = linearisation
    return last_v - (last_v - v_free + beta * last_force) * gain


@njit(**_HOT)
def proven_tangent_root(v_free: float, beta: float, linearisation: tuple,
                        proof: tuple) -> tuple[bool, float]:
    """The tangent root v₀ (`tangent_root`) and whether it is proven to lie within
    NEWTON_TOLERANCE of the root v* of g: then the friction law need not be evaluated.

    g(v₀) = β [F(v₀) − F(l) − F'(l)(v₀ − l)], so |g(v₀)| <= β ½ sup|F''| (v₀ − l)²
    (Taylor), and g' >= g_min > 0 gives |v* − v₀| <= |g(v₀)| / g_min. This holds when l
    and v₀ lie on one side of 0 (the law's parameters, and its slope, change at 0), v₀
    lies in the bracket between 0 and v_free, and l was evaluated (1/g'(l) > 0; a state
    after reset holds 0). sup|F''| is taken where tanh is saturated when both ends are
    (there the law is Stribeck + viscous only), else over the whole side. proof:
    `proof_coefficients`.
    """
    last_v, gain = linearisation[0], linearisation[2]
    root = tangent_root(v_free, beta, linearisation)
    if not (gain > 0.0 and min(0.0, v_free) <= root <= max(0.0, v_free)
            and (last_v >= 0.0) == (root >= 0.0)):
        return False, root
    saturated_coefficient, coefficient, k_tanh = proof[0] if root >= 0.0 else proof[1]
    if min(abs(last_v), abs(root)) * k_tanh > TANH_SATURATION:
        coefficient = saturated_coefficient
    step = root - last_v
    return coefficient * step * step <= NEWTON_TOLERANCE, root


@njit(**_HOT)
def implicit_motor_velocity(v_free: float, beta: float, linearisation: tuple,
                            positive: tuple, negative: tuple) -> tuple:
    """Motor velocity v (m/s) at the end of a substep with the friction taken at v itself.

    Solves g(v) = v − v_free + β F(v) = 0 (backward Euler in the friction force), v_free being
    the velocity without friction and β (m/(N·s)) the velocity gained per newton over the
    substep. `linearisation` = (v, F(v), 1/g'(v)) from an earlier evaluation of the law:
    the solve starts at the root of its tangent, so smooth motion needs one evaluation.
    Each Newton step divides by g' from the previous evaluation (a chord step: the division
    leaves the dependency chain; convergence stays fast because g' changes little between
    evaluations). The root lies between 0 and v_free because F has the sign of v; steps
    that leave that bracket are replaced by bisection, so the solve cannot diverge. The
    evaluated v is accepted once the next step would move it by <= NEWTON_TOLERANCE, so
    that is its error bound. Returns (v, linearisation at v).
    """
    low, high = min(0.0, v_free), max(0.0, v_free)
    gain = linearisation[2]
    v = min(max(tangent_root(v_free, beta, linearisation), low), high)
    for _ in range(NEWTON_MAX_ITERATIONS):
        force, slope = friction_force(v, positive, negative)
        g = v - v_free + beta * force
        if g > 0.0:
            high = v
        else:
            low = v
        g_slope = 1.0 + beta * slope
        chord_gain = gain
        gain = 1.0 / g_slope if g_slope > 0.0 else 0.0
        v_next = v - g * chord_gain if chord_gain > 0.0 else 0.5 * (low + high)
        if not low <= v_next <= high:
            v_next = 0.5 * (low + high)
        if abs(v_next - v) <= NEWTON_TOLERANCE:
            break
        v = v_next
    return v, (v, force, gain)


@njit(**_HOT)
def friction_velocity(v_free: float, beta: float, linearisation: tuple, positive: tuple,
                      negative: tuple, proof: tuple) -> tuple:
    """Velocity (m/s) at the end of a substep with the friction taken at it, and the
    linearisation for the next substep: the tangent's root where it is proven close enough
    (`proven_tangent_root`: the law is not evaluated), else `implicit_motor_velocity`."""
    proven, v = proven_tangent_root(v_free, beta, linearisation, proof)
    if proven:
        return v, linearisation
    return implicit_motor_velocity(v_free, beta, linearisation, positive, negative)


def kernel_model(discrete: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The 5 × 7 kernel model from [A_d | B_d] (4 × 6) and the continuous (A, B).

    Rows 0–3: [A_d | B_d | B_d[:, 0] / B_d[1, 0]]; the last column maps the motor-velocity
    drop caused by friction over a substep to the change of every state (saves a division
    per substep). Row 4 (`ACCELERATION_ROW`): [A[3] | B[3] | 0], the tip acceleration
    ẍ_tip = A[3]·x + B[3]·(F_mot, F_tip) of the continuous model.
    """
    rows = np.hstack([discrete, discrete[:, 4:5] / discrete[S_V_MOT, 4]])
    return np.vstack([rows, np.concatenate([a[S_V_TIP], b[S_V_TIP], [0.0]])])


@njit(**_JIT)
def model_row(model: np.ndarray, i: int) -> tuple:
    """Row i of the 5 × 7 kernel model as a tuple (passed by value in the inner loop)."""
    return (model[i, 0], model[i, 1], model[i, 2], model[i, 3], model[i, 4], model[i, 5],
            model[i, 6])


@njit(**_JIT)
def model_rows(model: np.ndarray) -> tuple:
    """The 5 × 7 kernel model as a tuple of row tuples."""
    return (model_row(model, 0), model_row(model, 1), model_row(model, 2), model_row(model, 3),
            model_row(model, ACCELERATION_ROW))


@njit(**_HOT)
def free_update(row: tuple, mechanics: tuple, motor_force: float, tip_force: float) -> float:
    """One state of x⁺ = A_d x + B_d (F_mot, F_tip), without friction; summed as a tree so
    that the last state to arrive waits for two additions, not six."""
    return ((row[0] * mechanics[0] + row[2] * mechanics[2])
            + (row[1] * mechanics[1] + row[3] * mechanics[3])
            + (row[4] * motor_force + row[5] * tip_force))


@njit(**_HOT)
def physics_step(mechanics: tuple, linearisation: tuple, motor_force: float,
                 tip_force: float, rows: tuple, positive: tuple, negative: tuple,
                 proof: tuple) -> tuple:
    """Advance (x_mot, v_mot, x_tip, v_tip) over one physics substep; returns it and the
    friction linearisation for the next substep.

    rows: `model_rows` of the exact zero-order-hold discretisation of the linear axis,
    inputs (motor force, tip force). Friction enters as a motor force held over the substep
    and evaluated at the end-of-substep motor velocity: the root of the law's tangent at
    the latest evaluation when that root is proven close enough (`friction_velocity`).
    """
    v_free = free_update(rows[1], mechanics, motor_force, tip_force)
    x_mot = free_update(rows[0], mechanics, motor_force, tip_force)
    x_tip = free_update(rows[2], mechanics, motor_force, tip_force)
    v_tip = free_update(rows[3], mechanics, motor_force, tip_force)
    v_mot, linearisation = friction_velocity(v_free, rows[1][4], linearisation, positive,
                                             negative, proof)
    drop = v_free - v_mot
    return ((x_mot - rows[0][6] * drop, v_mot, x_tip - rows[2][6] * drop,
             v_tip - rows[3][6] * drop), linearisation)


@njit(**_HOT)
def extra_forces(mechanics: tuple, effects: tuple, active: bool) -> tuple[float, float]:
    """`effect_forces`, or (0, 0) without evaluating it when `active` is False
    (`has_extra_forces` of the effects)."""
    return effect_forces(mechanics, effects) if active else (0.0, 0.0)


@njit(**_HOT)
def tip_acceleration(mechanics: tuple, tip_force: float, rows: tuple, effects: tuple,
                     active: bool) -> float:
    """Tip acceleration (m/s²) in state `mechanics` under `tip_force` (N) and the effects."""
    tip_extra = extra_forces(mechanics, effects, active)[1]
    return free_update(rows[ACCELERATION_ROW], mechanics, 0.0, tip_force + tip_extra)


@njit(**_HOT)
def velocity_pi(error: float, previous_error: float, integral: float, params: tuple,
                force_offset: float) -> tuple[float, float]:
    """Velocity-loop force command (N) and new integral, Eq. (5.4) inner PI, Tustin.

    params = (K_p, 1/T_i, force limit, period h). integral_k = integral_{k-1} +
    h (e_k + e_{k-1}) / 2, F = K_p (e_k + integral_k / T_i) + force offset; the integral
    is frozen while F exceeds the force limit in the direction the integration would push
    it (conditional-integration anti-windup).
    """
    k_p, inverse_t_i, force_limit, period = params
    increment = 0.5 * period * (error + previous_error)
    force = k_p * (error + (integral + increment) * inverse_t_i) + force_offset
    if abs(force) > force_limit and (force > 0.0) == (increment > 0.0):
        return k_p * (error + integral * inverse_t_i) + force_offset, integral
    return force, integral + increment


@njit(**_JIT)
def clear_controller(state: np.ndarray, delay_line: np.ndarray, keep_delay_line: bool) -> None:
    """Forget the velocity-PI memory (and, unless kept, the delay line and the last target)."""
    state[S_INTEGRAL] = 0.0
    state[S_PREVIOUS_ERROR] = 0.0
    if not keep_delay_line:
        delay_line[:] = 0.0
        state[S_FORCE] = 0.0
        state[S_HAS_PREVIOUS_TARGET] = 0.0


@njit(**_HOT)  # merged into run_cycles: no per-cycle call passing ~60 values (measured 1.2–1.6×)
def advance_cycle(state: np.ndarray, delay_line: np.ndarray, rows: tuple, positive: tuple,
                  negative: tuple, proof: tuple, params: np.ndarray, effects: tuple, mode: int,
                  enabled: bool, inputs: tuple, trace: np.ndarray, full_trace: bool) -> None:
    """Advance one bus cycle: position ticks, velocity ticks inside them, physics substeps
    inside those. The force command passes the delay line, then the force limit; the force
    acting on the carriage is the one behind that (reported) force, plus the world's extra
    forces (`effects`: ripple, backlash, see `feedbench.models.effects`).

    inputs: the cycle's column of the input table as a tuple (target position m, target
    velocity m/s, target force N, velocity offset m/s, force offset N, tip force N). The
    tip force ramps from the previous cycle's value to this one's over the cycle
    (first-order hold); each physics substep holds the ramp's value at its midpoint.
    trace (substeps + 1): the tip acceleration (m/s²) at the start of the cycle and at the
    end of every physics substep, under the ramp's value at that instant; without
    `full_trace` only its last point (the end of the cycle) is computed.
    """
    if not enabled:
        clear_controller(state, delay_line, False)
    elif mode == CST:
        clear_controller(state, delay_line, True)
    position_ticks, velocity_ticks = int(params[P_POSITION_TICKS]), int(params[P_VELOCITY_TICKS])
    force_limit, cycle = params[P_FORCE_LIMIT], params[P_CYCLE]
    pi_params = (params[P_K_P], params[P_INVERSE_T_I], force_limit,
                 cycle / (position_ticks * velocity_ticks))
    target = inputs[I_TARGET_POSITION]
    tip_start = state[S_TIP_FORCE]
    tip_step = (inputs[I_TIP_FORCE] - tip_start) / (trace.size - 1)
    start = state[S_PREVIOUS_TARGET] if state[S_HAS_PREVIOUS_TARGET] > 0.0 else target
    feedforward = params[P_FEEDFORWARD] * (target - start) / cycle
    v_command = inputs[I_TARGET_VELOCITY] + inputs[I_VELOCITY_OFFSET]
    mechanics = (state[S_X_MOT], state[S_V_MOT], state[S_X_TIP], state[S_V_TIP])
    linearisation = (state[S_FRICTION_VELOCITY], state[S_FRICTION_FORCE], state[S_NEWTON_GAIN])
    integral, previous_error = state[S_INTEGRAL], state[S_PREVIOUS_ERROR]
    index, applied = int(state[S_DELAY_INDEX]), state[S_FORCE]
    active = has_extra_forces(effects)
    last = trace.size - 1
    if full_trace:
        trace[0] = tip_acceleration(mechanics, tip_start, rows, effects, active)
    substep = 0
    force_sum = 0.0
    for tick in range(position_ticks):
        if mode == CSP:
            reference = start + tick * (target - start) / position_ticks
            v_command = (params[P_K_V] * (reference - mechanics[0]) + feedforward
                         + inputs[I_VELOCITY_OFFSET])
        for _ in range(velocity_ticks):
            if not enabled:
                command = 0.0
            elif mode == CST:
                command = inputs[I_TARGET_FORCE] + inputs[I_FORCE_OFFSET]
            else:
                error = v_command - mechanics[1]
                command, integral = velocity_pi(error, previous_error, integral, pi_params,
                                                inputs[I_FORCE_OFFSET])
                previous_error = error
            delay_line[index] = command
            index = index + 1 if index + 1 < delay_line.size else 0
            applied = min(max(delay_line[index], -force_limit), force_limit)
            acting = acting_force(applied, effects[E_FORCE_LEVEL])
            force_sum += applied
            for _ in range(int(params[P_PHYSICS_STEPS])):
                motor_extra, tip_extra = extra_forces(mechanics, effects, active)
                tip_force = tip_start + (substep + 0.5) * tip_step
                mechanics, linearisation = physics_step(mechanics, linearisation,
                                                        acting + motor_extra,
                                                        tip_force + tip_extra, rows, positive,
                                                        negative, proof)
                substep += 1
                if full_trace or substep == last:
                    trace[substep] = tip_acceleration(
                        mechanics, tip_start + substep * tip_step, rows, effects, active)
    state[S_X_MOT], state[S_V_MOT], state[S_X_TIP], state[S_V_TIP] = mechanics
    state[S_FRICTION_VELOCITY], state[S_FRICTION_FORCE], state[S_NEWTON_GAIN] = linearisation
    state[S_INTEGRAL], state[S_PREVIOUS_ERROR] = integral, previous_error
    state[S_DELAY_INDEX], state[S_FORCE] = index, applied
    state[S_MEAN_FORCE] = force_sum / (position_ticks * velocity_ticks)
    state[S_PREVIOUS_TARGET] = target
    state[S_TIP_FORCE] = inputs[I_TIP_FORCE]
    state[S_HAS_PREVIOUS_TARGET] = 1.0 if enabled and mode == CSP else 0.0


@njit(**_JIT)
def run_cycles(state: np.ndarray, delay_line: np.ndarray, model: np.ndarray,
               table: np.ndarray, params: np.ndarray, effect_vector: np.ndarray,
               modes: np.ndarray, enabled: bool, inputs: np.ndarray, outputs: np.ndarray,
               traces: np.ndarray) -> None:
    """Advance len(modes) bus cycles; column k of `inputs` (INPUT_COUNT × cycles) drives
    cycle k, column k of `outputs` (OUTPUT_COUNT × cycles) gets the state after it (and the
    motor velocity and force averaged over it, as a drive reports them), row k of `traces`
    the tip acceleration through it (see `advance_cycle`). A `traces` of one row (with
    more than one cycle) is a scratch row: cycles before the last compute only its last
    point, the tip acceleration at their end; the last cycle leaves its whole trace."""
    rows = model_rows(model)
    positive, negative = friction_side(table, 0), friction_side(table, 1)
    proof = proof_coefficients(positive, negative, rows[1][4])
    effects = (effect_vector[0], effect_vector[1], effect_vector[2], effect_vector[3],
               effect_vector[4], effect_vector[5], effect_vector[6], effect_vector[7],
               effect_vector[8])
    cycle = params[P_CYCLE]
    keep_traces = traces.shape[0] == modes.size
    for k in range(modes.size):
        trace = traces[k if keep_traces else 0]
        x_start = state[S_X_MOT]
        cycle_inputs = (inputs[0, k], inputs[1, k], inputs[2, k], inputs[3, k], inputs[4, k],
                        inputs[5, k])
        advance_cycle(state, delay_line, rows, positive, negative, proof, params, effects,
                      modes[k], enabled, cycle_inputs, trace, keep_traces or k == modes.size - 1)
        outputs[O_POSITION, k] = state[S_X_MOT]
        outputs[O_VELOCITY, k] = state[S_V_MOT]
        outputs[O_FORCE, k] = state[S_FORCE]
        outputs[O_TIP_POSITION, k] = state[S_X_TIP]
        outputs[O_TIP_VELOCITY, k] = state[S_V_TIP]
        outputs[O_TIP_ACCELERATION, k] = trace[-1]
        outputs[O_MEAN_VELOCITY, k] = (state[S_X_MOT] - x_start) / cycle
        outputs[O_MEAN_FORCE, k] = state[S_MEAN_FORCE]
