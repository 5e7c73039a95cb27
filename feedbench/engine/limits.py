"""Limits the runner checks on the plan before anything moves and watches every cycle."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from feedbench.config import Field, interval, positive, validate_table
from feedbench.units import MM_PER_MIN

LIMITS_SCHEMA = {
    "position_mm": Field(list, [-250.0, 250.0], "allowed motor position range (mm)", interval),
    "velocity_mm_min": Field(float, 3000.0, "largest |velocity| (mm/min)", positive),
    "force_N": Field(float, 1500.0, "largest |motor force| (N)", positive),
    "excitation_N": Field(float, 300.0, "largest injected force amplitude (N)", positive),
    "excitation_velocity_mm_min": Field(
        float, 600.0, "largest injected velocity-offset amplitude (mm/min)", positive
    ),
}


class LimitError(ValueError):
    """A plan would break a limit; raised before anything moves."""


@dataclass(frozen=True)
class Limits:
    """Watched limits in SI: position range (m), |velocity| (m/s), |force| (N)."""

    position: tuple[float, float]
    velocity: float
    force: float
    excitation_force: float
    excitation_velocity: float

    @classmethod
    def from_config(cls, table: Mapping[str, Any]) -> Limits:
        """Build from the validated ``[limits]`` table (engineering units)."""
        t = validate_table(table, LIMITS_SCHEMA, "limits")
        low, high = t["position_mm"]
        return cls(
            position=(low * 1e-3, high * 1e-3),
            velocity=t["velocity_mm_min"] * MM_PER_MIN,
            force=t["force_N"],
            excitation_force=t["excitation_N"],
            excitation_velocity=t["excitation_velocity_mm_min"] * MM_PER_MIN,
        )

    def check_trajectory(self, target_position: np.ndarray, dt: float) -> None:
        """Raise `LimitError` if absolute targets (m) leave the range or move too fast."""
        low, high = self.position
        if len(target_position) == 0:
            return
        lo, hi = float(target_position.min()), float(target_position.max())
        if lo < low or hi > high:
            raise LimitError(
                f"limits.position_mm: the plan reaches {lo * 1e3:.1f} … {hi * 1e3:.1f} mm, "
                f"outside [{low * 1e3:.1f}, {high * 1e3:.1f}] mm"
            )
        v = np.abs(np.diff(target_position)).max(initial=0.0) / dt
        if v > self.velocity * 1.0001:
            raise LimitError(
                f"limits.velocity_mm_min: the plan commands {v / MM_PER_MIN:.0f} mm/min, "
                f"above {self.velocity / MM_PER_MIN:.0f} mm/min"
            )

    def check_excitation(self, force_offset: np.ndarray, velocity_offset: np.ndarray) -> None:
        """Raise `LimitError` if an injected amplitude is above its limit."""
        peak_f = float(np.abs(force_offset).max(initial=0.0))
        if peak_f > self.excitation_force:
            raise LimitError(
                f"limits.excitation_N: the plan injects {peak_f:.1f} N, above "
                f"{self.excitation_force:.1f} N"
            )
        peak_v = float(np.abs(velocity_offset).max(initial=0.0))
        if peak_v > self.excitation_velocity:
            raise LimitError(
                f"limits.excitation_velocity_mm_min: the plan injects "
                f"{peak_v / MM_PER_MIN:.0f} mm/min, above "
                f"{self.excitation_velocity / MM_PER_MIN:.0f} mm/min"
            )

    def violation(self, position: float, velocity: float, force: float) -> str | None:
        """The reason a measured sample trips a limit, or None (checked every cycle)."""
        low, high = self.position
        if not low <= position <= high:
            return f"position {position * 1e3:.2f} mm outside [{low * 1e3:.1f}, {high * 1e3:.1f}] mm"
        if abs(velocity) > self.velocity:
            return f"|velocity| {abs(velocity) / MM_PER_MIN:.0f} mm/min above limit"
        if abs(force) > self.force:
            return f"|force| {abs(force):.0f} N above limit {self.force:.0f} N"
        return None
