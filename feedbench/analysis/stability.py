"""Chatter stability lobes by the zeroth-order approximation (ZOA, Altintas & Budak 1995,
thesis ref. [11]; used in Chs. 4.5, 5.5.6 and 6.4.3 with the measured Φ of Eq. 6.11).

Angles as in `feedbench.models.milling`: the immersion angle φ is measured from +y in the
direction of rotation, the feed is along +x, up-milling enters at φ = 0 and down-milling
leaves at φ = π (`models.milling.engagement_angles` gives φ_st, φ_ex). With the
time-averaged directional matrix A0 = (N K_t / 4π) α the regenerative loop
F = a (1 − e^{−iωT}) A0 Φ(iω) F has a non-trivial solution when det(I + Λ α Φ) = 0,
Λ = −(N a K_t / 4π)(1 − e^{−iωT}). For each eigenvalue λ of αΦ at a chatter frequency ω,
Λ = −1/λ gives the depth a = −(2π / (N K_t)) Λ_R (1 + κ²), κ = Λ_I/Λ_R (only Λ_R < 0 is
physical), and the tooth period T = (π − 2 arctan κ + 2πk)/ω of lobe k.
"""

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Lobes:
    """Stability limit per spindle speed.

    spindle_rpm: the speeds asked for (rpm); depth: critical axial depth a_lim (m), ∞ where
    no lobe reaches that speed from inside the frequency grid; chatter_frequency (Hz, NaN
    there); lobe: lobe number k (−1 there).
    """

    spindle_rpm: np.ndarray
    depth: np.ndarray
    chatter_frequency: np.ndarray
    lobe: np.ndarray

    @property
    def min_depth(self) -> float:
        """Smallest critical depth over the speeds (m): the absolute stability limit there."""
        return float(np.min(self.depth))


def directional_matrix(K_r: float, phi_st: float, phi_ex: float) -> np.ndarray:
    """Integrated directional coefficients α (2 × 2, –) of Altintas & Budak (1995).

    α_ij = ∫_{φ_st}^{φ_ex} a_ij(φ) dφ with F = ½ a K_t [a_ij(φ)] Δ for one tooth, so that
    A0 = (N K_t / 4π) α. K_r = K_rc/K_tc (–), angles in rad.
    """

    def primitive(phi: float) -> np.ndarray:
        s2, c2 = np.sin(2.0 * phi), np.cos(2.0 * phi)
        return 0.5 * np.array([
            [c2 - 2.0 * K_r * phi + K_r * s2, -s2 - 2.0 * phi + K_r * c2],
            [-s2 + 2.0 * phi + K_r * c2, -c2 - 2.0 * K_r * phi - K_r * s2],
        ])

    return primitive(phi_ex) - primitive(phi_st)


def _eigenvalues_2x2(B: np.ndarray) -> np.ndarray:
    """Both eigenvalues of a stack of 2 × 2 matrices (…, 2), closed form.

    The larger root from the quadratic formula, the other as det/λ₁, so neither cancels.
    """
    half_trace = 0.5 * (B[..., 0, 0] + B[..., 1, 1])
    det = B[..., 0, 0] * B[..., 1, 1] - B[..., 0, 1] * B[..., 1, 0]
    root = np.sqrt(half_trace**2 - det)
    root = np.where((half_trace.conj() * root).real >= 0.0, root, -root)
    first = half_trace + root
    with np.errstate(divide="ignore", invalid="ignore"):
        second = np.where(first != 0.0, det / first, 0.0)
    return np.stack([first, second], axis=-1)


def _paired_segments(lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues at both ends of each frequency step, paired by proximity (n_f − 1, 2)."""
    start, end = lam[:-1], lam[1:]
    straight = np.abs(start - end).sum(axis=-1)
    crossed = np.abs(start - end[:, ::-1]).sum(axis=-1)
    end = np.where((crossed < straight)[:, None], end[:, ::-1], end)
    return start, end


def _depth_and_phase(lam: np.ndarray, n_teeth: int, K_t: float) -> tuple[np.ndarray, np.ndarray]:
    """Critical depth a (m) and phase ε = ωT − 2πk (rad) for each eigenvalue λ of αΦ.

    Depth is NaN where Λ_R ≥ 0 (no positive depth) or λ = 0.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        Lam = -1.0 / lam
        real, imag = Lam.real, Lam.imag
        depth = np.where(real < 0.0, -2.0 * np.pi / (n_teeth * K_t) * (real**2 + imag**2) / real, np.nan)
        return depth, np.pi - 2.0 * np.arctan(imag / real)


def _spindle_rpm(f: np.ndarray, epsilon: np.ndarray, n_teeth: int, lobe: np.ndarray) -> np.ndarray:
    """Spindle speed (rpm) at which chatter at f (Hz) with phase ε lies on lobe k:
    tooth period T = (ε + 2πk)/ω, speed 60/(N T)."""
    return 60.0 * 2.0 * np.pi * f / (n_teeth * (epsilon + 2.0 * np.pi * lobe))


def _lowest_per_speed(speeds, rpm0, rpm1, a0, a1, f0, f1, lobe) -> tuple[np.ndarray, ...]:
    """Lowest depth over all lobe segments crossing each speed, with its frequency and lobe.

    Each segment (straight between two frequency samples) covers a contiguous run of the
    sorted speeds; the runs are expanded into (segment, speed) pairs, interpolated, and
    reduced per speed by a lexicographic sort (no Python loop over speeds or lobes).
    """
    lo = np.searchsorted(speeds, np.minimum(rpm0, rpm1), side="left")
    hi = np.searchsorted(speeds, np.maximum(rpm0, rpm1), side="right")
    count = hi - lo
    segment = np.repeat(np.arange(count.size), count)
    speed_index = lo[segment] + np.arange(segment.size) - np.repeat(np.cumsum(count) - count, count)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.nan_to_num((speeds[speed_index] - rpm0[segment]) / (rpm1[segment] - rpm0[segment]))
    depth = a0[segment] + t * (a1[segment] - a0[segment])
    frequency = f0[segment] + t * (f1[segment] - f0[segment])
    order = np.lexsort((depth, speed_index))
    first = order[np.unique(speed_index[order], return_index=True)[1]]
    result_depth = np.full(speeds.size, np.inf)
    result_frequency = np.full(speeds.size, np.nan)
    result_lobe = np.full(speeds.size, -1)
    result_depth[speed_index[first]] = depth[first]
    result_frequency[speed_index[first]] = frequency[first]
    result_lobe[speed_index[first]] = lobe[segment[first]]
    return result_depth, result_frequency, result_lobe


def zoa_lobes(
    f: np.ndarray,
    Phi: np.ndarray,
    spindle_rpm: np.ndarray,
    n_teeth: int,
    K_t: float,
    K_r: float,
    phi_st: float,
    phi_ex: float,
    n_lobes: int = 20,
) -> Lobes:
    """ZOA stability lobes of a 2-D (x, y) milling system from a measured receptance.

    f: frequency grid (Hz, > 0, increasing); Phi: receptance Φ (n_f × 2 × 2, m/N) with
    cross terms, e.g. Φ_tt + Φ_ww − 2Φ_tw of Eq. (6.11); spindle_rpm: increasing speeds
    (rpm); n_teeth: N; K_t: tangential cutting coefficient K_tc (N/m²); K_r: K_rc/K_tc (–);
    phi_st, phi_ex: engagement (rad); n_lobes: lobes k = 0 … n_lobes − 1.
    The lobes are straight between frequency samples, so the grid must resolve the modes.
    """
    f = np.asarray(f, dtype=float)
    Phi = np.asarray(Phi, dtype=complex)
    speeds = np.asarray(spindle_rpm, dtype=float)
    if Phi.shape != (f.size, 2, 2):
        raise ValueError(f"Phi: expected ({f.size}, 2, 2) for {f.size} frequencies, got {Phi.shape}")
    if np.any(f <= 0.0) or np.any(np.diff(f) <= 0.0):
        raise ValueError("f: frequencies must be positive and increasing")
    if np.any(np.diff(speeds) <= 0.0):
        raise ValueError("spindle_rpm: speeds must be increasing")
    lam = _eigenvalues_2x2(directional_matrix(K_r, phi_st, phi_ex) @ Phi)
    start, end = _paired_segments(lam)
    a0, eps0 = _depth_and_phase(start, n_teeth, K_t)
    a1, eps1 = _depth_and_phase(end, n_teeth, K_t)
    valid = np.isfinite(a0) & np.isfinite(a1)
    step = np.nonzero(valid)[0]
    lobes = np.arange(n_lobes)[:, None]
    segments = [
        np.broadcast_to(values, (n_lobes, step.size)).ravel()
        for values in (
            _spindle_rpm(f[step], eps0[valid], n_teeth, lobes),
            _spindle_rpm(f[step + 1], eps1[valid], n_teeth, lobes),
            a0[valid], a1[valid], f[step], f[step + 1], lobes,
        )
    ]
    depth, frequency, lobe = _lowest_per_speed(speeds, *segments)
    return Lobes(spindle_rpm=speeds, depth=depth, chatter_frequency=frequency, lobe=lobe)
