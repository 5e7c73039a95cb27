"""Plumbing shared by the simulators whose numba kernel advances whole bus cycles
(`axis.AxisSimulator`, `rack_pinion.RackPinionSimulator`).

Both kernels read their settings from one parameter vector and name the shared entries
alike (P_CYCLE, P_FORCE_LIMIT, …), so filling them, the force limit, the cycle clock and
the checks of per-cycle arrays are written once here.
"""

from __future__ import annotations

from types import ModuleType
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from feedbench.models._kernel import CSP, CST, CSV

if TYPE_CHECKING:
    from feedbench.models.axis import ServoTiming

MODES = (CSP, CSV, CST)


def positive(name: str, value: float) -> None:
    """Raise a ValueError naming the field unless `value` > 0."""
    if not value > 0.0:
        raise ValueError(f"{name} must be > 0, got {value}")


def check_mode(mode: int) -> None:
    """Raise a ValueError unless `mode` is CSP, CSV or CST."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES} (CSP, CSV, CST), got {mode}")


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
