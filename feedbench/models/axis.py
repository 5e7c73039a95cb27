"""The simulated feed-drive axis of the laboratory bench (Ch. 5.3, Fig. 5.9; DIGEST §3).

A linear motor carriage (m_mot, with guideway friction Eq. (5.2)) drives a flexure (k, c) to
the tool-tip mass (m_tip), on which a disturbance force may act. A P-PI cascade (Eq. (5.4))
closes the loops: position P at f_position, velocity PI at f_velocity (Tustin, as the
thesis's drives), the force command passing through the drive delay τ_ol and the force
limit before it acts on the carriage.

Numerical scheme (why it is stable and fast)
--------------------------------------------
The friction law is stiff near v = 0: its slope there is F_s·k_tanh ≈ 1.3e6 N·s/m, against
23 kg a time constant of ≈ 18 µs, shorter than the 125 µs velocity-loop period; an explicit
integrator must step below ≈ 20 µs everywhere and still rings through every reversal.
Within one velocity-loop period h the drive force and the tip force are constant (the
controller is sampled, zero-order hold), so the linear two-mass part is advanced EXACTLY:
x⁺ = A_d x + B_d u with A_d = e^{A h}, B_d = ∫₀ʰ e^{A s} ds B, computed once with
`scipy.linalg.expm`. The friction force enters as one more motor force held over the
period and is evaluated at the END-of-period motor velocity (backward Euler in the friction
only): v⁺ = v_free − β F(v⁺), a scalar equation solved to 1e-9 m/s: by the root of the
law's tangent at its latest evaluation where a curvature bound proves that root close
enough (no evaluation at all), else by (chord) Newton from that root with a bisection
safeguard (measured 0.30 evaluations of the law per period over holds, starts and
reversals; `_kernel.proven_tangent_root`). Backward Euler is L-stable, so the stiff
friction mode is damped, never amplified, at any slope and step; the root is bracketed by
0 and v_free, so a reversal cannot overshoot. The error is first order in the friction's
change over one period: nil in steady sliding, largest at break-away. Measured against
Radau (tests): open-loop stick-slip with reversals ≈ 10 µm over 1.5 mm of travel,
closed-loop CSP with reversals ≈ 0.3 µm. `physics_substeps` splits each period into equal
substeps (error ∝ 1/substeps). The loop runs in one compiled numba call per `simulate` or
`step_cycle`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy

from feedbench.models import _kernel
from feedbench.models._cycle_simulator import (
    CycleSimulator, ServoTiming, check_mode, positive, whole_ratio,
)
from feedbench.models.effects import AxisEffects
from feedbench.models.friction import AnderssonFriction, DirectionalFriction, LAB_BENCH_FRICTION
from feedbench.protocols.cia402 import CSP, CST, CSV, MODES

__all__ = [
    "CSP", "CSV", "CST", "MODES", "TwoMassAxis", "CascadeGains", "LAB_BENCH_GAINS", "ServoTiming",
    "AxisSimulator",
]

OUTPUT_NAMES = ("position", "velocity", "force", "tip_position", "tip_velocity",
                "tip_acceleration", "mean_velocity", "mean_force")


@dataclass(frozen=True)
class TwoMassAxis:
    """Motor mass with friction, flexure (k, c) to the tool-tip mass (SI: kg, kg, N/m, N·s/m).

    Defaults: the laboratory bench of Ch. 5.3.2 (M_mot 23.1 kg, M_tip 11.3 kg, k 1.68 N/µm,
    c 104 N·s/m, friction of Fig. 5.11).
    """

    m_mot: float = 23.1
    m_tip: float = 11.3
    k: float = 1.68e6
    c: float = 104.0
    friction: DirectionalFriction | AnderssonFriction = LAB_BENCH_FRICTION

    def __post_init__(self) -> None:
        for name in ("m_mot", "m_tip", "k"):
            positive(name, getattr(self, name))
        if not self.c >= 0.0:
            raise ValueError(f"c must be >= 0, got {self.c}")

    @property
    def f_t(self) -> float:
        """Motor-locked (anti-resonance) frequency (Hz), Eq. (4.13): √(k/M_tip)/2π."""
        return math.sqrt(self.k / self.m_tip) / (2.0 * math.pi)

    @property
    def f_r(self) -> float:
        """Resonance frequency (Hz), Eq. (4.14): √(k (1/M_mot + 1/M_tip))/2π."""
        return math.sqrt(self.k * (1.0 / self.m_mot + 1.0 / self.m_tip)) / (2.0 * math.pi)

    def state_matrices(self) -> tuple[np.ndarray, np.ndarray]:
        """Continuous (A, B) of the linear part, friction excluded.

        State (x_mot, v_mot, x_tip, v_tip) in m, m/s; inputs (motor force, tip force) in N.
        """
        k, c, m1, m2 = self.k, self.c, self.m_mot, self.m_tip
        a = np.array([
            [0.0, 1.0, 0.0, 0.0],
            [-k / m1, -c / m1, k / m1, c / m1],
            [0.0, 0.0, 0.0, 1.0],
            [k / m2, c / m2, -k / m2, -c / m2],
        ])
        b = np.array([[0.0, 0.0], [1.0 / m1, 0.0], [0.0, 0.0], [0.0, 1.0 / m2]])
        return a, b

    def discrete_model(self, step: float) -> np.ndarray:
        """[A_d | B_d] (4 × 6): exact zero-order-hold discretisation over `step` seconds.

        expm([[A, B], [0, 0]] step) = [[A_d, B_d], [0, I]] (Van Loan), valid although A is
        singular (rigid-body mode).
        """
        a, b = self.state_matrices()
        augmented = np.zeros((6, 6))
        augmented[:4, :4], augmented[:4, 4:] = a, b
        return scipy.linalg.expm(augmented * step)[:4, :]


@dataclass(frozen=True)
class CascadeGains:
    """P-PI cascade gains: K_p velocity gain (N·s/m), T_i integral time (s), K_v position
    gain (1/s)."""

    K_p: float
    T_i: float
    K_v: float

    def __post_init__(self) -> None:
        positive("T_i", self.T_i)
        for name in ("K_p", "K_v"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")

    @classmethod
    def standard(cls, M_total: float, f_bw: float) -> CascadeGains:
        """Tuning rule for a velocity bandwidth f_bw (Hz) on a total mass M_total (kg).

        Eq. (4.2) K_p = 2π M f_bw, Eq. (4.8) T_i = 1/(π f_bw), Eq. (4.12) K_v = π f_bw / 2.
        """
        positive("M_total", M_total)
        positive("f_bw", f_bw)
        return cls(K_p=2.0 * math.pi * M_total * f_bw, T_i=1.0 / (math.pi * f_bw),
                   K_v=math.pi * f_bw / 2.0)


LAB_BENCH_GAINS = CascadeGains.standard(34.4, 30.0)
"""Default drive tuning of the laboratory bench: M_total = 34.4 kg, f_bw = 30 Hz."""


class AxisSimulator(CycleSimulator):
    """The drive's inner world: two-mass axis, friction, P-PI cascade, delay, force limit.

    `step_cycle` advances one bus cycle (`timing.cycle`); `simulate` advances many from
    arrays in one compiled call. Both continue from, and update, the same state.

    CSP: the target of a cycle is reached at its end; the position reference runs linearly
    from the previous target to it (sampled at each position-loop tick), v_cmd = K_v
    (x_ref − x_mot) + velocity feed-forward (target increment / cycle) + velocity offset.
    CSV: v_cmd = target velocity + velocity offset. Both: Tustin PI, F = K_p (e + ∫e / T_i)
    + force offset. CST: F = target force + force offset. `enabled` (default True): when
    False the motor force is 0, the PI integral and the delay line are cleared, and the
    axis coasts under friction. Tip force (a hammer, shaker or cutting force on the tool
    tip): the value of a cycle is reached at its end, ramping linearly from the previous
    cycle's value (first-order hold, so a 1 kHz force sequence acts as a smooth force, not
    as a staircase); each physics substep holds the ramp's midpoint value.
    """

    _KERNEL = _kernel

    def __init__(
        self,
        axis: TwoMassAxis = TwoMassAxis(),
        gains: CascadeGains = LAB_BENCH_GAINS,
        timing: ServoTiming = ServoTiming(),
        force_limit: float = 2000.0,
        velocity_feedforward: bool = True,
        physics_substeps: int = 1,
        effects: AxisEffects = AxisEffects(),
    ) -> None:
        """velocity_feedforward: in CSP add the target's increment per cycle / cycle time to
        the velocity command. physics_substeps: physics steps per velocity-loop period.
        effects: what else the world carries (ripple, force-level nonlinearity, backlash)."""
        physics_substeps = whole_ratio("physics_substeps", physics_substeps, 1)
        super().__init__(timing, physics_substeps, velocity_feedforward)
        self._inputs = np.zeros((_kernel.INPUT_COUNT, 1))
        self._outputs = np.zeros((_kernel.OUTPUT_COUNT, 1))
        self.axis = axis
        self.effects = effects
        self._effect_vector = effects.vector(axis.k, axis.c)
        self._model = _kernel.kernel_model(
            axis.discrete_model(timing.velocity_period / physics_substeps), *axis.state_matrices())
        self.substeps_per_cycle = (timing.position_ticks_per_cycle
                                   * timing.velocity_ticks_per_position * physics_substeps)
        """Physics substeps per bus cycle (N): the tip-acceleration trace has N + 1 points."""
        self._friction_table = axis.friction.table()
        self.set_gains(gains)
        self.force_limit = force_limit
        self._delay_line = np.zeros(timing.delay_ticks + 1)
        self._trace = np.zeros((1, self.substeps_per_cycle + 1))
        self._enabled = True
        self.reset()

    # -- configuration -------------------------------------------------------------------

    @property
    def gains(self) -> CascadeGains:
        """The cascade gains in use."""
        return self._gains

    def set_gains(self, gains: CascadeGains) -> None:
        """Use new cascade gains from the next cycle on (the PI integral is kept)."""
        self._gains = gains
        self._params[_kernel.P_K_P] = gains.K_p
        self._params[_kernel.P_INVERSE_T_I] = 1.0 / gains.T_i
        self._params[_kernel.P_K_V] = gains.K_v

    @property
    def enabled(self) -> bool:
        """Power stage on; setting False clears the PI integral, the delay line and the force."""
        return self._enabled

    @enabled.setter
    def enabled(self, value: bool) -> None:
        self._enabled = bool(value)
        if not self._enabled:
            _kernel.clear_controller(self._state, self._delay_line, False)

    # -- state ---------------------------------------------------------------------------

    @property
    def position(self) -> float:
        """Motor (carriage) position x_mot (m)."""
        return float(self._state[_kernel.S_X_MOT])

    @property
    def velocity(self) -> float:
        """Motor velocity (m/s)."""
        return float(self._state[_kernel.S_V_MOT])

    @property
    def force(self) -> float:
        """Force the motor applies to the carriage, after delay and saturation (N)."""
        return float(self._state[_kernel.S_FORCE])

    @property
    def tip_position(self) -> float:
        """Tool-tip position x_tip (m)."""
        return float(self._state[_kernel.S_X_TIP])

    @property
    def tip_velocity(self) -> float:
        """Tool-tip velocity (m/s)."""
        return float(self._state[_kernel.S_V_TIP])

    @property
    def mean_velocity(self) -> float:
        """Motor velocity averaged over the last cycle, Δx_mot / cycle (m/s).

        What a drive reports as velocity actual (a position difference per sample); unlike
        the instantaneous `velocity`, it does not alias the 8 kHz loop's ripple into the
        1 kHz samples.
        """
        return float(self._outputs[_kernel.O_MEAN_VELOCITY, 0])

    @property
    def mean_force(self) -> float:
        """Motor force averaged over the last cycle (N), as a drive's filtered force actual."""
        return float(self._outputs[_kernel.O_MEAN_FORCE, 0])

    def reported(self) -> tuple[float, float, float]:
        """(position m, mean velocity m/s, mean force N) in one call: what a drive publishes
        every cycle (`position`, `mean_velocity`, `mean_force`)."""
        outputs = self._outputs[:, 0].tolist()
        return (float(self._state[_kernel.S_X_MOT]), outputs[_kernel.O_MEAN_VELOCITY],
                outputs[_kernel.O_MEAN_FORCE])

    @property
    def tip_acceleration(self) -> float:
        """Tool-tip acceleration at the end of the last cycle (m/s²)."""
        return float(self._outputs[_kernel.O_TIP_ACCELERATION, 0])

    @property
    def tip_acceleration_trace(self) -> np.ndarray:
        """Tip acceleration through the last cycle (m/s², N + 1 values, a copy).

        Point j is at (cycle start) + j · cycle / N, N = `substeps_per_cycle`: point 0 is
        the end of the previous cycle, points 1…N the ends of the physics substeps, each
        under the tip-force ramp's value at that instant. The tip acceleration is continuous
        (the motor force acts on the carriage, the tip force ramps), so the points may be
        interpolated.
        """
        return self._trace[0].copy()

    def reset(self, position: float = 0.0) -> None:
        """Both masses at rest at `position` (m), flexure unloaded, controller cleared, time 0."""
        self._state[:] = 0.0
        self._state[_kernel.S_X_MOT] = position
        self._state[_kernel.S_X_TIP] = position
        self._delay_line[:] = 0.0
        self._outputs[:] = 0.0
        self._trace[:] = 0.0
        self._cycle_count = 0

    # -- stepping ------------------------------------------------------------------------

    def step_cycle(
        self,
        mode: int,
        target_position: float,
        target_velocity: float,
        target_force: float,
        velocity_offset: float,
        force_offset: float,
        tip_force: float = 0.0,
    ) -> None:
        """Advance one bus cycle in `mode` (CSP, CSV or CST) with these setpoints (SI);
        `tip_force` is the force on the tool tip at the end of the cycle."""
        check_mode(mode)
        self._modes[0] = mode
        self._inputs[:, 0] = (target_position, target_velocity, target_force, velocity_offset,
                              force_offset, tip_force)
        self._run(self._modes, self._inputs, self._outputs, self._trace)

    def simulate(
        self,
        mode: int | np.ndarray,
        target_position: float | np.ndarray,
        target_velocity: float | np.ndarray,
        target_force: float | np.ndarray,
        velocity_offset: float | np.ndarray = 0.0,
        force_offset: float | np.ndarray = 0.0,
        tip_force: float | np.ndarray = 0.0,
        keep_trace: bool = False,
    ) -> dict[str, np.ndarray]:
        """Advance one cycle per array element (scalars broadcast) in one compiled call.

        Returns per-cycle arrays after each cycle: position, velocity, force, tip_position,
        tip_velocity, tip_acceleration, mean_velocity, mean_force, time (s, end of each
        cycle), and with `keep_trace` tip_acceleration_trace (cycles × (N + 1), as
        `tip_acceleration_trace`; 72 bytes per cycle at the default rates, so off unless
        asked for).
        """
        modes, columns = self._per_cycle(mode, target_position, target_velocity, target_force,
                                         velocity_offset, force_offset, tip_force)
        inputs = np.empty((_kernel.INPUT_COUNT, modes.size))
        for row, column in zip(inputs, columns):
            row[:] = column
        outputs = np.empty((_kernel.OUTPUT_COUNT, modes.size))
        traces = (np.empty((modes.size, self.substeps_per_cycle + 1)) if keep_trace
                  else self._trace)
        times = self._end_times(modes.size)
        self._run(modes, inputs, outputs, traces)
        result = dict(zip(OUTPUT_NAMES, outputs))
        result["time"] = times
        if keep_trace:
            result["tip_acceleration_trace"] = traces
        if modes.size:
            self._outputs[:, 0], self._trace[0] = outputs[:, -1], traces[-1]
        return result

    def _run(self, modes: np.ndarray, inputs: np.ndarray, outputs: np.ndarray,
             traces: np.ndarray) -> None:
        _kernel.run_cycles(self._state, self._delay_line, self._model, self._friction_table,
                           self._params, self._effect_vector, modes, self._enabled, inputs,
                           outputs, traces)
        self._cycle_count += modes.size
