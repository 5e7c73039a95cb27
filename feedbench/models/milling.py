"""Milling force model (Ch. 6.2.1, Eqs. 6.1–6.5) and the SMFE cutting simulation (Ch. 6.3.2).

Angles follow the thesis (Fig. 6.2): the immersion angle φ of a tooth is measured from the
+y axis in the direction of rotation, the feed is along +x, and the chip thickness of a tooth
at φ is h = f_z sin φ sin κ + uᵀ Δr with u = [sin φ sin κ, cos φ sin κ, −cos κ] (Eq. 6.1).
Up-milling enters at φ = 0, down-milling leaves at φ = π.

Chip width and edge length are both a_p / sin κ (straight insert edge with lead angle κ), as
in the author's simulation; with them Eq. (6.3) reads F_tra = (K_c a_p h + K_e a_p) / sin κ.

`simulate_smfe_cut` integrates the structure (feedbench.models.structure) under the cutting
force with the regenerative chip thickness (Eq. 6.2): Δr is the relative tool–workpiece
displacement now minus its value when the previous tooth passed the same angle, found on the
recorded spindle angle, so the delay follows a varying spindle speed exactly.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

from feedbench.models.structure import POINT_DOF, ModalStructure, modal_step
from feedbench.units import RPM

MILLING_MODES = ("down", "up", "central")
"""Cutting operations of the SMFE set (DM, UM, CM), Eq. (6.13)."""

SMFE_FEED_PER_TOOTH = 0.1e-3
"""f_z of the SMFE tests and simulation (m), Ch. 6.4.1 and DIGEST §3b."""

MAX_STEP_ROTATION = math.radians(2.0)
"""Largest spindle rotation per simulation step (rad): twice the author's 1°, so that the tooth
entry/exit and the regenerative delay stay resolved."""

SMFE_SENSOR_NOISE = (0.016, 0.012, 0.0014)
"""Accelerometer noise standard deviations x, y, z (m/s²) of the author's simulation, Eq. (6.18)."""

_JIT = {"cache": True, "error_model": "numpy"}


@dataclass(frozen=True)
class CuttingCoefficients:
    """Linear edge-force model of Eq. (6.3): shear K_tc, K_rc, K_ac (N/m²), edge K_te, K_re, K_ae (N/m)."""

    K_tc: float
    K_rc: float
    K_ac: float
    K_te: float
    K_re: float
    K_ae: float

    @property
    def K_r(self) -> float:
        """Cutting force ratio K_r = K_rc / K_tc (Sec. 6.3.1)."""
        return self.K_rc / self.K_tc

    @classmethod
    def shear_only(cls, K_r: float, K_a: float = 0.0, K_tc: float = 1.0) -> CuttingCoefficients:
        """Shear forces only, K_rc = K_r K_tc, K_ac = K_a K_tc (the simplification of Eqs. 6.16–6.17)."""
        return cls(K_tc, K_r * K_tc, K_a * K_tc, 0.0, 0.0, 0.0)

    def as_array(self) -> np.ndarray:
        """[K_tc, K_rc, K_ac, K_te, K_re, K_ae] for the compiled kernels."""
        return np.array([self.K_tc, self.K_rc, self.K_ac, self.K_te, self.K_re, self.K_ae])


TABLE_6_1 = CuttingCoefficients(
    K_tc=1889e6, K_rc=806e6, K_ac=291e6, K_te=63e3, K_re=114e3, K_ae=-3e3,
)
"""Cutting coefficients of the SMFE simulation, Table 6.1 (N/mm² and N/mm in the thesis)."""


@dataclass(frozen=True)
class Tool:
    """Milling tool: diameter D (m), number of teeth Z, lead angle κ (rad)."""

    D: float
    Z: int
    kappa: float

    def __post_init__(self) -> None:
        if self.D <= 0:
            raise ValueError(f"D: tool diameter must be > 0 m, got {self.D}")
        if int(self.Z) != self.Z or self.Z < 1:
            raise ValueError(f"Z: number of teeth must be a positive integer, got {self.Z}")
        if not 0 < self.kappa <= math.pi / 2:
            raise ValueError(f"kappa: lead angle must be in (0, π/2] rad, got {self.kappa}")


SMFE_TOOL = Tool(D=0.080, Z=2, kappa=math.radians(45.0))
"""Sandvik R245-080Q27-12M with two inserts, Table 6.2 and Ch. 6.4.1."""


def engagement_angles(a_e: float, D: float, mode: str) -> tuple[float, float]:
    """Entry and exit angles φ_en, φ_ex (rad) of the screen function, Eq. (6.4).

    a_e: radial engagement (m), D: tool diameter (m); mode "down" ends at π, "up" starts at 0,
    "central" is symmetric about π/2. a_e = 12 mm on D = 80 mm: 134.4–180°, 0–45.6°, 81.4–98.6°.
    """
    if not 0 < a_e <= D:
        raise ValueError(f"a_e: radial engagement must be in (0, D = {D}] m, got {a_e}")
    if mode == "up":
        return 0.0, math.acos(1.0 - 2.0 * a_e / D)
    if mode == "down":
        return math.pi - math.acos(1.0 - 2.0 * a_e / D), math.pi
    if mode == "central":
        half = math.asin(a_e / D)
        return math.pi / 2 - half, math.pi / 2 + half
    raise ValueError(f"mode: expected one of {MILLING_MODES}, got {mode!r}")


def tooth_angles(spindle_angle: ArrayLike, Z: int) -> np.ndarray:
    """Immersion angles φ_j = θ + (j − 1) 2π/Z of the Z teeth (rad), shape (..., Z), Eq. (6.1)."""
    return np.asarray(spindle_angle, dtype=float)[..., None] + 2.0 * np.pi * np.arange(Z) / Z


def static_chip_thickness(phi: ArrayLike, f_z: float, kappa: float) -> np.ndarray:
    """Static chip thickness h_s = f_z sin φ sin κ (m), Eq. (6.1)."""
    return chip_thickness(np.asarray(phi, dtype=float), f_z, kappa, 0.0, 0.0, 0.0)


@njit(**_JIT)
def chip_thickness(phi, f_z: float, kappa: float, dr_x: float, dr_y: float, dr_z: float):
    """Chip thickness h = f_z sin φ sin κ + uᵀΔr (m), Eq. (6.1), scalar or array φ.

    u = [sin φ sin κ, cos φ sin κ, −cos κ]; Δr (m) is the regenerative term of Eq. (6.2).
    """
    s_k = math.sin(kappa)
    return (f_z + dr_x) * np.sin(phi) * s_k + dr_y * np.cos(phi) * s_k - dr_z * math.cos(kappa)


@njit(**_JIT)
def screen(phi, phi_en: float, phi_ex: float):
    """Screen function g(φ), Eq. (6.4): true where φ_en < φ mod 2π < φ_ex (scalar or array)."""
    wrapped = phi % (2.0 * np.pi)
    return (wrapped > phi_en) & (wrapped < phi_ex)


@njit(**_JIT)
def tooth_force(phi, h, width: float, kappa: float, K: np.ndarray):
    """Force of one engaged tooth on the tool in x, y, z (N), Eqs. (6.3) and (6.5).

    phi: immersion angle (rad), h: chip thickness (m), width = a_p / sin κ (m) is both the
    chip width and the edge length S_e; K = CuttingCoefficients.as_array(). Scalar or array.
    """
    f_t = (K[0] * h + K[3]) * width
    f_r = (K[1] * h + K[4]) * width
    f_a = (K[2] * h + K[5]) * width
    s, c = np.sin(phi), np.cos(phi)
    s_k, c_k = math.sin(kappa), math.cos(kappa)
    f_x = -c * f_t - s * s_k * f_r - s * c_k * f_a
    f_y = s * f_t - c * s_k * f_r - c * c_k * f_a
    f_z = c_k * f_r - s_k * f_a
    return f_x, f_y, f_z


def cutting_forces(
    phi: ArrayLike,
    h: ArrayLike,
    a_p: float,
    tool: Tool,
    coeffs: CuttingCoefficients,
    phi_en: float,
    phi_ex: float,
) -> np.ndarray:
    """Total force on the tool (N), shape (..., 3), Eqs. (6.3–6.5).

    phi, h: immersion angle (rad) and chip thickness (m) of each tooth, shape (..., Z); teeth
    outside φ_en < φ mod 2π < φ_ex (Eq. 6.4) carry no force.
    """
    phi, h = np.broadcast_arrays(np.asarray(phi, dtype=float), np.asarray(h, dtype=float))
    width = a_p / math.sin(tool.kappa)
    per_tooth = np.stack(tooth_force(phi, h, width, tool.kappa, coeffs.as_array()), axis=-1)
    engaged = screen(phi, phi_en, phi_ex)
    return np.sum(per_tooth * engaged[..., None], axis=-2)


def stationary_forces(
    spindle_angle: ArrayLike,
    a_p: float,
    a_e: float,
    mode: str,
    tool: Tool,
    coeffs: CuttingCoefficients,
    f_z: float = SMFE_FEED_PER_TOOTH,
) -> np.ndarray:
    """Force on the tool (N), shape (..., 3), for a rigid machine (h = h_s), Eqs. (6.1–6.5)."""
    phi = tooth_angles(spindle_angle, tool.Z)
    phi_en, phi_ex = engagement_angles(a_e, tool.D, mode)
    return cutting_forces(phi, static_chip_thickness(phi, f_z, tool.kappa), a_p, tool, coeffs, phi_en, phi_ex)


def spindle_ramp(rpm_start: float, acceleration: float, duration: float, fs: float) -> np.ndarray:
    """Spindle speed (rpm) at each sample of a linear ramp: N(t) = N_0 + α t · 60/2π.

    acceleration α in rad/s²; DIGEST §3b: 600 rpm, +1.5 rad/s², 65 s (≈ 600 → 1531 rpm).
    """
    t = np.arange(int(round(duration * fs))) / fs
    return rpm_start + acceleration * t / RPM


def simulate_smfe_cut(
    structure: ModalStructure,
    tool: Tool,
    coeffs: CuttingCoefficients,
    a_p: float,
    a_e: float,
    mode: str,
    rpm_profile: ArrayLike,
    fs: float,
    noise_std: Sequence[float] = (0.0, 0.0, 0.0),
    seed: int | None = None,
    f_z: float = SMFE_FEED_PER_TOOTH,
) -> dict[str, np.ndarray]:
    """Time-domain simulation of one cut with regenerative chip thickness (Ch. 6.3.2).

    structure: 3 directions (tool; rigid workpiece) or 6 (tool rows 0–2, workpiece rows 3–5,
    e.g. `ModalStructure.tool_and_workpiece`); the tool takes F, the workpiece −F.
    rpm_profile: spindle speed (rpm) at each sample; the feed is kept at f_z (m) per tooth, as
    the CNC's feed override does in the SMFE test. Semi-implicit Euler at the sample period
    1/fs: at fs = 10 kHz and ≤ 1531 rpm that is ≤ 0.92° of rotation per step (the author used
    1°). Gaussian sensor noise of std noise_std (m/s², per x, y, z) is added to every
    accelerometer, Eq. (6.18) with zero mean.

    Returns t (s), F (3 × n, force on the tool, N), acc (3 × n, tool acceleration, m/s²),
    rpm (n), theta (n, spindle angle, rad), and acc_workpiece (3 × n) for a 6-direction structure.
    """
    rpm = np.asarray(rpm_profile, dtype=float)
    _check_cut_inputs(structure, a_p, rpm, fs, noise_std)
    from scipy.integrate import cumulative_trapezoid  # here: 0.3 s to import, a cut needs it

    theta = cumulative_trapezoid(rpm * RPM, dx=1.0 / fs, initial=0.0)
    phi_en, phi_ex = engagement_angles(a_e, tool.D, mode)
    relative = structure.shapes[:POINT_DOF]
    if structure.n_dof == 2 * POINT_DOF:
        relative = relative - structure.shapes[POINT_DOF:]
    # writable copies of the read-only structure arrays: numba compiles one signature only
    force, acceleration = _cut_kernel(
        theta, 1.0 / fs, tool.Z, tool.kappa, a_p / math.sin(tool.kappa), f_z, coeffs.as_array(),
        phi_en, phi_ex, np.array(relative), np.array(structure.shapes),
        structure.mass, structure.damping, np.array(structure.k),
    )
    noise = np.tile(np.asarray(noise_std, dtype=float), structure.n_dof // POINT_DOF)
    acceleration += np.random.default_rng(seed).normal(size=acceleration.shape) * noise[:, None]
    result = {"t": np.arange(rpm.size) / fs, "F": force, "acc": acceleration[:POINT_DOF], "rpm": rpm,
              "theta": theta}
    if structure.n_dof == 2 * POINT_DOF:
        result["acc_workpiece"] = acceleration[POINT_DOF:]
    return result


def _check_cut_inputs(structure: ModalStructure, a_p: float, rpm: np.ndarray, fs: float,
                      noise_std: Sequence[float]) -> None:
    if structure.n_dof not in (POINT_DOF, 2 * POINT_DOF):
        raise ValueError(
            f"structure: expected 3 (tool) or 6 (tool + workpiece) directions, got {structure.n_dof}")
    if a_p <= 0:
        raise ValueError(f"a_p: axial depth of cut must be > 0 m, got {a_p}")
    if fs <= 0:
        raise ValueError(f"fs: sample rate must be > 0 Hz, got {fs}")
    if rpm.ndim != 1 or rpm.size < 2 or not np.all(rpm > 0):
        raise ValueError("rpm_profile: expected a 1-D array of ≥ 2 spindle speeds > 0 rpm")
    if rpm.max() * RPM / fs > MAX_STEP_ROTATION:
        raise ValueError(
            f"fs: {fs} Hz gives {math.degrees(rpm.max() * RPM / fs):.1f}° of rotation per step "
            f"at {rpm.max():.0f} rpm; at most {math.degrees(MAX_STEP_ROTATION):.0f}° is allowed")
    if len(noise_std) != POINT_DOF or min(noise_std) < 0:
        raise ValueError(f"noise_std: expected 3 standard deviations ≥ 0 m/s², got {noise_std}")


@njit(**_JIT)
def _previous_pass(theta: np.ndarray, k: int, target: float, start: int) -> tuple[int, float]:
    """Index p and weight w with θ_p ≤ target < θ_(p+1), w = (target − θ_p)/(θ_(p+1) − θ_p).

    Searches forward from `start` (the angle only grows); p = −1 before the first sample,
    where the surface is the undisturbed one.
    """
    if target < theta[0]:
        return -1, 0.0
    p = start
    while p + 1 < k and theta[p + 1] <= target:
        p += 1
    return p, (target - theta[p]) / (theta[p + 1] - theta[p])


@njit(**_JIT)
def _project(matrix: np.ndarray, vector: np.ndarray, out: np.ndarray) -> None:
    """out = matrix @ vector, written out because the sizes (3 × 3) are too small for BLAS."""
    for i in range(matrix.shape[0]):
        total = 0.0
        for j in range(matrix.shape[1]):
            total += matrix[i, j] * vector[j]
        out[i] = total


@njit(**_JIT)
def _cut_kernel(theta, dt, Z, kappa, width, f_z, K, phi_en, phi_ex, relative, shapes,
                mass, damping, stiffness):
    """Force (3 × n) and accelerations (n_dof × n) of a cut; see `simulate_smfe_cut`."""
    n, n_modes = theta.size, mass.size
    q, qd, qdd = np.zeros(n_modes), np.zeros(n_modes), np.zeros(n_modes)
    modal_force, dr = np.zeros(n_modes), np.zeros(POINT_DOF)
    history = np.zeros((POINT_DOF, n))
    force = np.zeros((POINT_DOF, n))
    acceleration = np.zeros((shapes.shape[0], n))
    pitch = 2.0 * np.pi / Z
    p = 0
    for k in range(n):
        _project(relative, q, history[:, k])
        p, w = _previous_pass(theta, k, theta[k] - pitch, max(p, 0))
        for i in range(POINT_DOF):
            previous = 0.0 if p < 0 else (1.0 - w) * history[i, p] + w * history[i, p + 1]
            dr[i] = history[i, k] - previous
        for j in range(Z):
            phi = theta[k] + j * pitch
            if screen(phi, phi_en, phi_ex):
                h = chip_thickness(phi, f_z, kappa, dr[0], dr[1], dr[2])
                f = tooth_force(phi, max(h, 0.0), width, kappa, K)
                for i in range(POINT_DOF):
                    force[i, k] += f[i]
        _project(relative.T, force[:, k], modal_force)
        modal_step(q, qd, modal_force, mass, damping, stiffness, dt, qdd)
        _project(shapes, qdd, acceleration[:, k])
    return force, acceleration
