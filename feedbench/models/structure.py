"""Modal structure of the machining system (Ch. 6.2.2, Eqs. 6.6–6.11).

A `ModalStructure` is N uncoupled modes seen at n_dof measurement directions: natural
frequencies f_n (Hz), damping ratios ζ, modal stiffnesses k (N/m) and a mode-shape matrix
(n_dof × N, one column per mode). Modal mass m = k/ω_n², modal damping c = 2ζ√(k m), as in
the author's SMFE simulation. n_dof = 3 is one point (x, y, z); n_dof = 6 is the tool point
(rows 0–2) and the workpiece point (rows 3–5) of one structure, which is how tool/workpiece
coupling (Eqs. 6.9–6.11) is described.

The same parameters give the receptance matrix on a frequency grid (Eqs. 6.6–6.8) and the
time stepping used by the milling simulation (semi-implicit Euler, `modal_step`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

POINT_DOF = 3
"""Directions per measurement point: x, y, z."""

_JIT = {"cache": True, "error_model": "numpy"}


@dataclass(frozen=True)
class ModalStructure:
    """N modes seen at n_dof directions; SI: Hz, –, N/m, – (shapes n_dof × N)."""

    f_n: np.ndarray
    zeta: np.ndarray
    k: np.ndarray
    shapes: np.ndarray

    def __post_init__(self) -> None:
        fields = {name: np.atleast_1d(np.asarray(getattr(self, name), dtype=float))
                  for name in ("f_n", "zeta", "k")}
        shapes = np.atleast_2d(np.asarray(self.shapes, dtype=float))
        n_modes = fields["f_n"].size
        for name, values in fields.items():
            if values.ndim != 1 or values.size != n_modes:
                raise ValueError(f"{name}: expected {n_modes} values (one per mode), got {values.shape}")
            if not np.all(values > 0):
                raise ValueError(f"{name}: every value must be > 0, got {values}")
        if shapes.ndim != 2 or shapes.shape[1] != n_modes:
            raise ValueError(f"shapes: expected n_dof × {n_modes} (one column per mode), got {shapes.shape}")
        for name, values in {**fields, "shapes": shapes}.items():
            values.setflags(write=False)
            object.__setattr__(self, name, values)

    @property
    def n_dof(self) -> int:
        """Number of measured directions (rows of `shapes`)."""
        return self.shapes.shape[0]

    @property
    def omega_n(self) -> np.ndarray:
        """Natural angular frequencies ω_n = 2π f_n (rad/s)."""
        return 2.0 * np.pi * self.f_n

    @property
    def mass(self) -> np.ndarray:
        """Modal masses m = k/ω_n² (kg)."""
        return self.k / self.omega_n**2

    @property
    def damping(self) -> np.ndarray:
        """Modal viscous damping c = 2ζ m ω_n (N·s/m)."""
        return 2.0 * self.zeta * self.mass * self.omega_n

    def receptance(self, f: ArrayLike) -> np.ndarray:
        """Receptance matrix Φ(f) (m/N), shape (n_f, n_dof, n_dof), Eqs. (6.6–6.8).

        Φ(ω) = Σ_i ψ_i ψ_iᵀ / (m_i (ω_i² − ω² + 2jζ_i ω_i ω)).
        """
        omega = 2.0 * np.pi * np.atleast_1d(np.asarray(f, dtype=float))[:, None]
        modal = 1.0 / (self.mass * (self.omega_n**2 - omega**2 + 2j * self.zeta * self.omega_n * omega))
        return np.einsum("im,jm,fm->fij", self.shapes, self.shapes, modal)

    def simulate(self, force: ArrayLike, fs: float) -> ModalResponse:
        """Response to forces (n_dof × n samples, N) sampled at fs (Hz), starting at rest.

        Semi-implicit Euler (`modal_step`) at the sample period; the discrete modes have f_n
        and ζ high by ≈ ζ ω_n/(2 fs) + (ω_n/fs)²/24 (0.06 % for the 58.6 Hz mode at 10 kHz).
        """
        force = np.asarray(force, dtype=float)
        if force.ndim != 2 or force.shape[0] != self.n_dof:
            raise ValueError(f"force: expected {self.n_dof} × n samples, got {force.shape}")
        modal_force = self.shapes.T @ force
        q, qdd = _simulate_modes(modal_force, self.mass, self.damping, np.array(self.k), 1.0 / fs)
        return ModalResponse(displacement=self.shapes @ q, acceleration=self.shapes @ qdd)

    @classmethod
    def tool_and_workpiece(cls, tool: ModalStructure, workpiece: ModalStructure) -> ModalStructure:
        """Uncoupled tool (rows 0–2) and workpiece (rows 3–5) as one 6-direction structure."""
        for name, side in (("tool", tool), ("workpiece", workpiece)):
            if side.n_dof != POINT_DOF:
                raise ValueError(f"{name}: expected a {POINT_DOF}-direction structure, got {side.n_dof}")
        shapes = np.block([
            [tool.shapes, np.zeros((POINT_DOF, workpiece.f_n.size))],
            [np.zeros((POINT_DOF, tool.f_n.size)), workpiece.shapes],
        ])
        return cls(
            f_n=np.concatenate([tool.f_n, workpiece.f_n]),
            zeta=np.concatenate([tool.zeta, workpiece.zeta]),
            k=np.concatenate([tool.k, workpiece.k]),
            shapes=shapes,
        )


@dataclass(frozen=True)
class ModalResponse:
    """Displacement (m) and acceleration (m/s²), each n_dof × n samples."""

    displacement: np.ndarray
    acceleration: np.ndarray


def tool_workpiece_blocks(phi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Split a 6-direction receptance (n_f × 6 × 6) into Φ_tt, Φ_tw, Φ_wt, Φ_ww (Eq. 6.9)."""
    if phi.shape[-2:] != (2 * POINT_DOF, 2 * POINT_DOF):
        raise ValueError(f"phi: expected (..., 6, 6) tool + workpiece receptance, got {phi.shape}")
    t, w = slice(0, POINT_DOF), slice(POINT_DOF, 2 * POINT_DOF)
    return phi[..., t, t], phi[..., t, w], phi[..., w, t], phi[..., w, w]


def relative_receptance(
    phi_tt: np.ndarray,
    phi_ww: np.ndarray,
    phi_tw: np.ndarray | None = None,
    phi_wt: np.ndarray | None = None,
) -> np.ndarray:
    """Machining-system receptance Φ = Φ_tt + Φ_ww − Φ_tw − Φ_wt (Eqs. 6.10, 6.11), m/N.

    r = r_t − r_w with F_t = −F_w. Without cross terms the sides are uncoupled; with Φ_tw only,
    the thesis's reciprocity assumption Φ_wt = Φ_tw gives Eq. (6.11), Φ_tt + Φ_ww − 2Φ_tw.
    Pass Φ_wt as well for the exact form (reciprocity of a structure gives Φ_wt = Φ_twᵀ).
    """
    if phi_tw is None:
        if phi_wt is not None:
            raise ValueError("phi_wt: given without phi_tw")
        return phi_tt + phi_ww
    cross = phi_tw if phi_wt is None else phi_wt
    return phi_tt + phi_ww - phi_tw - cross


@njit(**_JIT)
def modal_step(q: np.ndarray, qd: np.ndarray, modal_force: np.ndarray, mass: np.ndarray,
               damping: np.ndarray, stiffness: np.ndarray, dt: float, qdd: np.ndarray) -> None:
    """One semi-implicit Euler step of m q̈ + c q̇ + k q = Q for every mode, in place.

    q̈ = (Q − c q̇ − k q)/m at the current state; q̇ += dt q̈; q += dt q̇ (the new q̇), as in
    the author's SMFE simulation. `qdd` receives the acceleration belonging to `modal_force`.
    """
    for i in range(q.size):
        qdd[i] = (modal_force[i] - damping[i] * qd[i] - stiffness[i] * q[i]) / mass[i]
        qd[i] += dt * qdd[i]
        q[i] += dt * qd[i]


@njit(**_JIT)
def _simulate_modes(modal_force: np.ndarray, mass: np.ndarray, damping: np.ndarray,
                    stiffness: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Modal displacement (at each sample, before the step) and acceleration, modes × samples."""
    n_modes, n = modal_force.shape
    q, qd, qdd = np.zeros(n_modes), np.zeros(n_modes), np.zeros(n_modes)
    displacement, acceleration = np.empty((n_modes, n)), np.empty((n_modes, n))
    for k in range(n):
        displacement[:, k] = q
        modal_step(q, qd, modal_force[:, k], mass, damping, stiffness, dt, qdd)
        acceleration[:, k] = qdd
    return displacement, acceleration


SMFE_TOOL_STRUCTURE = ModalStructure(
    f_n=(33.37, 57.44, 58.61),
    zeta=(0.061, 0.0822, 0.0287),
    k=(45.5e6, 32.1e6, 36.7e6),
    shapes=((-0.055, 0.0199, 0.999),
            (0.6245, 0.9968, 0.0004),
            (0.7724, -0.0161, 0.0096)),
)
"""Tool side of the SMFE simulation, Table 6.2 (f_n 33.4 / 57.4 / 58.6 Hz, ζ 6.1 / 8.2 /
2.9 %, k 45.5 / 32.1 / 36.7 N/µm) at the unrounded values and mode-shape matrix of the
author's published simulation (DIGEST §3b); its receptance peaks are |Φ_xx| = 4.74e-7 m/N
at 58.6 Hz, |Φ_yy| = 1.89e-7 at 57.2 Hz, |Φ_zz| = 1.08e-7 at 33.3 Hz."""
