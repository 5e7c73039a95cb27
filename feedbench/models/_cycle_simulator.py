"""Plumbing shared by the simulators whose numba kernel advances whole bus cycles
(`axis.AxisSimulator`, `rack_pinion.RackPinionSimulator`).

Both kernels read their settings from one parameter vector and name the shared entries
alike (P_CYCLE, P_FORCE_LIMIT, …), so filling them, the loop rates and bus cycle
(`ServoTiming`), the force limit, the cycle clock and the checks of per-cycle arrays are
written once here.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType
from typing import ClassVar

import numpy as np

from feedbench.protocols.cia402 import CSP, CST, CSV, MODES


def positive(name: str, value: float) -> None:
    """Raise a ValueError naming the field unless `value` > 0."""
    if not value > 0.0:
        raise ValueError(f"{name} must be > 0, got {value}")


def check_mode(mode: int) -> None:
    """Raise a ValueError unless `mode` is CSP, CSV or CST."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES} (CSP, CSV, CST), got {mode}")


def whole_ratio(name: str, ratio: float, minimum: int) -> int:
    """`ratio` as an integer >= minimum, or a ValueError naming the field."""
    count = round(ratio)
    if count < minimum or abs(ratio - count) > 1e-6 * max(1.0, ratio):
        raise ValueError(f"{name} must be a whole number >= {minimum}, got {ratio:.6g}")
    return count


@dataclass(frozen=True)
class ServoTiming:
    """Loop rates (Hz), drive force delay τ_ol (s) and bus cycle (s).

    Each loop period must divide the next slower one, and the delay must be a whole number
    of velocity-loop periods (default 0.75 ms = 6 × 125 µs, τ_ol of Ch. 5.3.2).
    """

    f_velocity: float = 8000.0
    f_position: float = 1000.0
    delay: float = 0.75e-3
    cycle: float = 1e-3

    def __post_init__(self) -> None:
        for name in ("f_velocity", "f_position", "cycle"):
            positive(name, getattr(self, name))
        for derived in ("velocity_ticks_per_position", "position_ticks_per_cycle", "delay_ticks"):
            getattr(self, derived)  # raises ValueError unless a whole number

    @property
    def velocity_period(self) -> float:
        """h = 1/f_velocity (s)."""
        return 1.0 / self.f_velocity

    @property
    def velocity_ticks_per_position(self) -> int:
        """Velocity-loop periods per position-loop period."""
        return whole_ratio("f_velocity / f_position", self.f_velocity / self.f_position, 1)

    @property
    def position_ticks_per_cycle(self) -> int:
        """Position-loop periods per bus cycle."""
        return whole_ratio("f_position · cycle", self.f_position * self.cycle, 1)

    @property
    def delay_ticks(self) -> int:
        """The delay in velocity-loop periods."""
        return whole_ratio("delay · f_velocity", self.delay * self.f_velocity, 0)


class CycleSimulator:
    """Parameter vector, state, force limit and cycle clock of a simulator run by the kernel
    module `_KERNEL` (set by each subclass; a class attribute, so instances stay copyable)."""

    _KERNEL: ClassVar[ModuleType]

    def __init__(self, timing: ServoTiming, physics_substeps: int,
                 velocity_feedforward: bool) -> None:
        """physics_substeps: physics steps per velocity-loop period (validated by the caller)."""
        kernel = self._KERNEL
        self.timing = timing
        self._params = np.zeros(kernel.PARAMETER_COUNT)
        self._params[kernel.P_CYCLE] = timing.cycle
        self._params[kernel.P_POSITION_TICKS] = timing.position_ticks_per_cycle
        self._params[kernel.P_VELOCITY_TICKS] = timing.velocity_ticks_per_position
        self._params[kernel.P_PHYSICS_STEPS] = physics_substeps
        self._params[kernel.P_FEEDFORWARD] = 1.0 if velocity_feedforward else 0.0
        self._state = np.zeros(kernel.STATE_SIZE)
        self._modes = np.zeros(1, dtype=np.int64)
        self._cycle_count = 0

    @property
    def force_limit(self) -> float:
        """Saturation of the force each motor applies, ±force_limit (N)."""
        return float(self._params[self._KERNEL.P_FORCE_LIMIT])

    @force_limit.setter
    def force_limit(self, value: float) -> None:
        positive("force_limit", value)
        self._params[self._KERNEL.P_FORCE_LIMIT] = value

    @property
    def cycle_count(self) -> int:
        """Bus cycles advanced since the last reset."""
        return self._cycle_count

    @property
    def time(self) -> float:
        """Simulated time since the last reset (s)."""
        return self._cycle_count * self.timing.cycle

    def _per_cycle(self, mode: int | np.ndarray,
                   *values: float | np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        """`mode` (int64, checked) and `values` broadcast to one entry per cycle."""
        modes, *columns = np.broadcast_arrays(mode, *values)
        if modes.ndim != 1:
            raise ValueError("simulate needs 1-D per-cycle arrays (at least one of them)")
        modes = np.ascontiguousarray(modes, dtype=np.int64)
        known = (modes == CSP) | (modes == CSV) | (modes == CST)
        if not known.all():
            check_mode(int(modes[np.argmin(known)]))
        return modes, columns

    def _end_times(self, cycles: int) -> np.ndarray:
        """End times (s) of the next `cycles` cycles."""
        return (self._cycle_count + 1 + np.arange(cycles)) * self.timing.cycle
