"""Guideway friction of the feed drive: the Andersson law, Eq. (5.2), per motion direction.

F = [F_c + (F_s − F_c) exp(−(|v|/v_s)^δ)] tanh(k_tanh v) + σ v   (Ch. 5.3, Eq. (5.2))

The law is evaluated by the compiled kernel (`_kernel.friction_force`), the same code the
axis simulation runs, so it has exactly one definition.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from feedbench.models import _kernel
from feedbench.units import MIN_PER_MM, MM_PER_MIN, N_MIN_PER_MM


def _evaluate(table: np.ndarray, v: np.ndarray | float, column: int) -> np.ndarray | float:
    """Force (column 0) or slope (column 1) of the law in `table` at v, shaped like v."""
    velocities = np.asarray(v, dtype=float)
    result = _kernel.friction_forces(velocities.ravel(), table)[column].reshape(velocities.shape)
    return float(result) if result.ndim == 0 else result


@dataclass(frozen=True)
class AnderssonFriction:
    """Andersson friction for one motion direction, Eq. (5.2), SI units.

    F_c: Coulomb (sliding) level (N); F_s: static level (N); v_s: Stribeck velocity (m/s,
    ``inf`` for no Stribeck effect); sigma: viscous coefficient (N·s/m); k_tanh: tanh
    constant (s/m); delta: Stribeck shape exponent (–).
    """

    F_c: float
    F_s: float
    v_s: float
    sigma: float
    k_tanh: float = 15000.0
    delta: float = 1.0

    def __post_init__(self) -> None:
        for name in ("F_c", "F_s", "sigma"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("v_s", "k_tanh", "delta"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")

    @classmethod
    def from_engineering(
        cls,
        F_c: float,
        F_s: float,
        v_s_mm_min: float,
        sigma_N_min_mm: float,
        k_tanh_min_mm: float = 0.25,
        delta: float = 1.0,
    ) -> AnderssonFriction:
        """From the units of Fig. 5.11: N, N, mm/min, N·min/mm, min/mm, –."""
        return cls(F_c=F_c, F_s=F_s, v_s=v_s_mm_min * MM_PER_MIN,
                   sigma=sigma_N_min_mm * N_MIN_PER_MM, k_tanh=k_tanh_min_mm * MIN_PER_MM,
                   delta=delta)

    def row(self) -> np.ndarray:
        """The parameters as one row of a kernel friction table (F_c, F_s, 1/v_s, σ, k_tanh, δ)."""
        return np.array([self.F_c, self.F_s, 1.0 / self.v_s, self.sigma, self.k_tanh, self.delta])

    def table(self) -> np.ndarray:
        """Kernel friction table (2 × 6): this law for both directions."""
        return np.vstack([self.row(), self.row()])

    def force(self, v: np.ndarray | float) -> np.ndarray | float:
        """Friction force (N) at velocity v (m/s), Eq. (5.2)."""
        return _evaluate(self.table(), v, 0)

    def slope(self, v: np.ndarray | float) -> np.ndarray | float:
        """Local slope dF/dv (N·s/m) of Eq. (5.2) at velocity v (m/s), analytic."""
        return _evaluate(self.table(), v, 1)


@dataclass(frozen=True)
class DirectionalFriction:
    """Direction-dependent friction: `positive` for v >= 0, `negative` for v < 0 (Fig. 5.11).

    Each side keeps its own sign convention through tanh, so F(v) < 0 for v < 0.
    """

    positive: AnderssonFriction
    negative: AnderssonFriction

    def table(self) -> np.ndarray:
        """Kernel friction table (2 × 6): row 0 positive, row 1 negative direction."""
        return np.vstack([self.positive.row(), self.negative.row()])

    def force(self, v: np.ndarray | float) -> np.ndarray | float:
        """Friction force (N) at velocity v (m/s), Eq. (5.2) with the side's parameters."""
        return _evaluate(self.table(), v, 0)

    def slope(self, v: np.ndarray | float) -> np.ndarray | float:
        """Local slope dF/dv (N·s/m) at velocity v (m/s), analytic."""
        return _evaluate(self.table(), v, 1)


LAB_BENCH_FRICTION = DirectionalFriction(
    positive=AnderssonFriction.from_engineering(44.2, 84.0, 387.4, 0.0028, 0.25, 1.0),
    negative=AnderssonFriction.from_engineering(38.7, 88.0, 421.0, 0.0025, 0.25, 1.0),
)
"""Friction of the laboratory bench, Fig. 5.11 (Ch. 5.3.2), "+" / "−" direction."""

NO_FRICTION = DirectionalFriction(
    positive=AnderssonFriction(F_c=0.0, F_s=0.0, v_s=np.inf, sigma=0.0),
    negative=AnderssonFriction(F_c=0.0, F_s=0.0, v_s=np.inf, sigma=0.0),
)
"""A frictionless guideway (for open-loop checks of the linear axis)."""
