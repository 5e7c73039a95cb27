"""Dynamic friction: pre-sliding hysteresis laws integrated over a measured motion record.

The static law of the thesis, Eq. (5.2), makes friction a function of velocity. At a
motion reversal the contact first deforms elastically over a few µm ("pre-sliding", Ch. 2.3,
Fig. 2.9) before it slips, so the force follows the displacement since the reversal, not
the velocity: a hysteresis loop in the force–displacement plane. The thesis names the
dynamic models that capture it (§2.3.1: "LuGre [105] or GMS [106]"; §5.3.1, beside
Eq. (5.2), names them again without numbers) and leaves them out of its own model. Its
in-text numbers there run one behind its reference list (its "Hagman [107]" is list entry
[108]): list [107] is the GMS paper; list [106] is Canudas de Wit's 1998 "Comments on 'A
new model for control of systems with friction'", not the 1995 LuGre paper cited below.
Four laws, each from its paper, SI units (m, s, N):

- Dahl (P. R. Dahl, "A solid friction model", Aerospace Corp. TOR-0158(3107-18)-1, 1968;
  "Solid friction damping of mechanical vibrations", AIAA J. 14 (1976) 1675–1682):
      dF/dx = σ0 |1 − (F/F_c) sgn ẋ|^α sgn(1 − (F/F_c) sgn ẋ)
  rate independent: F depends on the path of x only (`dahl_force`, exact per sample).
- LuGre (C. Canudas de Wit, H. Olsson, K. J. Åström, P. Lischinsky, "A new model for
  control of systems with friction", IEEE Trans. Autom. Control 40 (1995) 419–425):
      dz/dt = v − σ0 |v| z / g(v),   g(v) = F_c + (F_s − F_c) e^{−(v/v_s)²},
      F = σ0 z + σ1 dz/dt + σ2 v
  (`LuGre.force`, the z-equation solved exactly over each substep at constant v).
- Elasto-plastic (P. Dupont, V. Hayward, B. Armstrong, F. Altpeter, "Single state
  elastoplastic friction models", IEEE Trans. Autom. Control 47 (2002) 787–792):
      dz/dt = v (1 − α(z, v) z / z_ss(v)),  z_ss(v) = g(v) sgn(v) / σ0,
      F = σ0 z + σ1 dz/dt + σ2 v,
  α = 0 for |z| ≤ z_ba or sgn z ≠ sgn v (purely elastic: no drift under a force below
  breakaway, which LuGre and Dahl show), α = 1 for |z| ≥ |z_ss|, between them
  ½ sin(π (|z| − (|z_ss| + z_ba)/2) / (|z_ss| − z_ba)) + ½ (`ElastoPlastic.force`, RK4).
- Generalized Maxwell-slip, GMS (F. Al-Bender, V. Lampaert, J. Swevers, "The generalized
  Maxwell-slip model: a novel model for friction simulation and compensation", IEEE Trans.
  Autom. Control 50 (2005) 1883–1887, the thesis's [107]; V. Lampaert, F. Al-Bender,
  J. Swevers, "A generalized Maxwell-slip friction model appropriate for control purposes",
  PhysCon 2003): N blocks in parallel, block i a spring k_i whose force F_i = k_i z_i
  cannot exceed W_i = α_i s(v), Σ α_i = 1. Sliding obeys the single-state law
      dF/dt = sgn(v) C (1 − F/s(v)),
  with the Stribeck curve
      s(v) = sgn(v) (F_c + (F_s − F_c) e^{−|v/v_s|^δ}),
  C (N/s) the attraction parameter. Block i sticks (the sticking-block state equation)
      dF_i/dt = k_i v
  until |F_i| reaches W_i, then slips (the slipping-block state equation)
      dF_i/dt = sgn(v) C (α_i − F_i/s(v))
  until the velocity reverses (or stops); the friction force is
      F = Σ F_i + σ2 v
  or, with the blocks' damping, Σ (k_i z_i + σ_i dz_i/dt) + σ2 v (`GMS.force`;
  stick exact, slip exact over each substep at constant v: F_i → α_i s + (F_i − α_i s)
  e^{−C t/|s|}). The α_i inside the slip law makes the sum of slipping blocks obey the
  single-state law. The laws are cited by content, not by the paper's equation numbers:
  its text was not at hand, so the numbers could not be confirmed. The forms were checked
  against open reproductions (github.com/jchristopherson/friction README, which cites
  it; jchristopherson/FrictionModels.jl, src/GeneralizedMaxwellSlipModels.jl): dz_i/dt = v
  sticking, sgn(v) ν_i C (1 − z_i/(ν_i s(v))) slipping, F = Σ (k_i z_i + b_i dz_i/dt) +
  b_v v, Σ ν_i = 1, which agree with the above. With F_s = F_c a slipping block stays at
  W_i whatever C: the model is rate independent, Iwan's parallel elastic-perfectly-plastic
  blocks (`maxwell_slip_normalised`): Masing's rule and non-local memory hold exactly.

With F_s = F_c and σ1 = σ2 = 0, LuGre is Dahl with α = 1: F_c w(x) where w follows
dw/dx = (1 − w sgn ẋ)/x_p, x_p = F_c/σ0 the pre-sliding displacement; its steady state is
the static Stribeck curve g(v) sgn v + σ2 v.

Hand-written (numba) because the laws are sequential in time and no maintained library
integrates them over a sampled record.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

_JIT = {"cache": True, "error_model": "numpy"}

MAX_DECAY_PER_SUBSTEP = 0.2
"""Largest σ0 |v| h / g(v) of one substep (the bristle's relaxation over the substep); the
exact exponential is stable at any size, the substeps resolve v changing within a sample."""

MAX_SUBSTEPS = 512
"""Cap on the substeps of one sample interval."""


@njit(**_JIT)
def _dahl_path(x: np.ndarray, x_p: float, alpha: float, w0: float) -> np.ndarray:
    """Normalised Dahl force w = F/F_c along the positions x (m): exact per interval.

    With u = 1 − w s (s = sgn Δx, constant over a linear interval) the law reads
    du/dξ = −u^α along the path ξ = |Δx|/x_p, so u^{1−α} = u0^{1−α} − (1 − α) ξ (α ≠ 1)
    and u = u0 e^{−ξ} (α = 1); u stays in [0, 2] because w does in [−1, 1].
    """
    out = np.empty(x.size)
    w = w0
    if x.size:
        out[0] = w
    for i in range(1, x.size):
        dx = x[i] - x[i - 1]
        if dx != 0.0:
            s = 1.0 if dx > 0.0 else -1.0
            u = 1.0 - w * s
            xi = abs(dx) / x_p
            if alpha == 1.0:
                u = u * math.exp(-xi)
            elif u > 0.0:
                base = u ** (1.0 - alpha) - (1.0 - alpha) * xi
                u = base ** (1.0 / (1.0 - alpha)) if base > 0.0 else 0.0
            w = s * (1.0 - u)
        out[i] = w
    return out


def dahl_normalised(x: np.ndarray, presliding: float, alpha: float = 1.0,
                    w0: float = 0.0) -> np.ndarray:
    """Dahl's force over its level, w = F/F_c ∈ [−1, 1], along positions x (m).

    presliding: x_p = F_c/σ0 (m), the pre-sliding displacement (the Dahl force reaches
    1 − 1/e of F_c after x_p of travel from w = 0 when α = 1); alpha: Dahl's exponent
    (> 0); w0: w at x[0]. Exact for x linear between samples (the law is rate
    independent, so only the path counts).
    """
    if not (presliding > 0.0 and alpha > 0.0 and -1.0 <= w0 <= 1.0):
        raise ValueError(f"need presliding > 0, alpha > 0, |w0| <= 1; got {presliding}, "
                         f"{alpha}, {w0}")
    return _dahl_path(np.ascontiguousarray(x, dtype=float), float(presliding), float(alpha),
                      float(w0))


def dahl_force(x: np.ndarray, F_c: float, sigma0: float, alpha: float = 1.0,
               F0: float = 0.0) -> np.ndarray:
    """Dahl friction force (N) along positions x (m): F_c (N), σ0 (N/m) the rest stiffness,
    α (–) the exponent, F0 (N) the force at x[0]. See the module docstring."""
    if not (F_c > 0.0 and sigma0 > 0.0):
        raise ValueError(f"need F_c > 0 and sigma0 > 0, got {F_c}, {sigma0}")
    return F_c * dahl_normalised(x, F_c / sigma0, alpha, F0 / F_c)


@njit(**_JIT)
def _stribeck(v: float, F_c: float, F_s: float, v_s: float) -> float:
    """g(v) = F_c + (F_s − F_c) e^{−(v/v_s)²} (N), LuGre's steady-state level."""
    return F_c + (F_s - F_c) * math.exp(-(v / v_s) ** 2)


@njit(**_JIT)
def _substeps(v0: float, v1: float, dt: float, rate: float) -> int:
    """Substeps of one interval so that rate · max|v| · h ≤ MAX_DECAY_PER_SUBSTEP."""
    decay = rate * max(abs(v0), abs(v1)) * dt
    return min(MAX_SUBSTEPS, max(1, int(math.ceil(decay / MAX_DECAY_PER_SUBSTEP))))


@njit(**_JIT)
def _lugre(v: np.ndarray, dt: float, p: np.ndarray, z0: float) -> tuple:
    """Bristle deflection z (m) and its rate (m/s) at the samples of v (m/s): v linear
    between samples; on each substep v is held at its midpoint value and the z-equation
    solved exactly, z → z_ss + (z − z_ss) e^{−σ0|v|h/g(v)}, z_ss = v g(v) / (σ0 |v|)."""
    sigma0, F_c, F_s, v_s = p[0], p[1], p[2], p[3]
    z = np.empty(v.size)
    rate = np.empty(v.size)
    zi = z0
    for i in range(v.size):
        if i > 0:
            m = _substeps(v[i - 1], v[i], dt, sigma0 / min(F_c, F_s))
            h = dt / m
            for j in range(m):
                vm = v[i - 1] + (v[i] - v[i - 1]) * (j + 0.5) / m
                if vm != 0.0:
                    g = _stribeck(vm, F_c, F_s, v_s)
                    z_ss = math.copysign(g / sigma0, vm)
                    zi = z_ss + (zi - z_ss) * math.exp(-sigma0 * abs(vm) * h / g)
        z[i] = zi
        rate[i] = v[i] - sigma0 * abs(v[i]) * zi / _stribeck(v[i], F_c, F_s, v_s)
    return z, rate


@dataclass(frozen=True)
class BristleLaw:
    """What LuGre and the elasto-plastic law share, SI: sigma0 (N/m) bristle stiffness,
    F_c, F_s (N) Coulomb and static levels, v_s (m/s) Stribeck velocity, sigma1 (N·s/m)
    bristle damping, sigma2 (N·s/m) viscous coefficient; F = σ0 z + σ1 dz/dt + σ2 v."""

    sigma0: float
    F_c: float
    F_s: float
    v_s: float
    sigma1: float = 0.0
    sigma2: float = 0.0

    def __post_init__(self) -> None:
        for name in ("sigma0", "F_c", "F_s", "v_s"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("sigma1", "sigma2"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")

    def steady(self, v: np.ndarray | float) -> np.ndarray:
        """Steady-state force (N) at constant v (m/s): g(v) sgn v + σ2 v, the static
        Stribeck curve."""
        v = np.asarray(v, dtype=float)
        g = self.F_c + (self.F_s - self.F_c) * np.exp(-(v / self.v_s) ** 2)
        return g * np.sign(v) + self.sigma2 * v

    def deflection(self, v: np.ndarray, dt: float, z0: float = 0.0
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Bristle deflection z (m) and dz/dt (m/s) at each sample of v (m/s, every dt s)."""
        raise NotImplementedError

    def force(self, v: np.ndarray, dt: float, z0: float = 0.0) -> np.ndarray:
        """Friction force (N) σ0 z + σ1 dz/dt + σ2 v at each sample of v (m/s, every dt s),
        starting from deflection z0 (m)."""
        z, rate = self.deflection(v, dt, z0)
        return self.sigma0 * z + self.sigma1 * rate + self.sigma2 * np.asarray(v, dtype=float)


@dataclass(frozen=True)
class LuGre(BristleLaw):
    """The LuGre law (Canudas de Wit et al. 1995), `BristleLaw`'s parameters."""

    def deflection(self, v, dt, z0=0.0):
        params = np.array([self.sigma0, self.F_c, self.F_s, self.v_s])
        return _lugre(np.ascontiguousarray(v, dtype=float), float(dt), params, float(z0))


@njit(**_JIT)
def _attachment(z: float, v: float, z_ss: float, z_ba: float) -> float:
    """Dupont's α(z, v): 0 in the elastic range or against the motion, 1 at steady
    sliding, the sine blend between (z_ss the steady deflection magnitude, z_ba < z_ss)."""
    if v == 0.0 or (z > 0.0) != (v > 0.0):
        return 0.0
    a = abs(z)
    if a <= z_ba:
        return 0.0
    if a >= z_ss:
        return 1.0
    return 0.5 * math.sin(math.pi * (a - 0.5 * (z_ss + z_ba)) / (z_ss - z_ba)) + 0.5


@njit(**_JIT)
def _ep_rate(z: float, v: float, p: np.ndarray) -> float:
    """dz/dt (m/s) of the elasto-plastic law at deflection z (m), velocity v (m/s)."""
    sigma0, F_c, F_s, v_s, z_ba = p[0], p[1], p[2], p[3], p[4]
    z_ss = _stribeck(v, F_c, F_s, v_s) / sigma0
    return v * (1.0 - _attachment(z, v, z_ss, z_ba) * abs(z) / z_ss)


@njit(**_JIT)
def _elastoplastic(v: np.ndarray, dt: float, p: np.ndarray, z0: float) -> tuple:
    """z (m) and dz/dt (m/s) at the samples of v (m/s), RK4 on v linear between samples;
    substeps keep |v| h (1/z_ss + π / (2 (z_ss − z_ba))) ≤ MAX_DECAY_PER_SUBSTEP (the
    law's largest slope in z)."""
    sigma0, F_c, F_s, z_ba = p[0], p[1], p[2], p[4]
    z_min = min(F_c, F_s) / sigma0
    stiffness = 1.0 / z_min + 0.5 * math.pi / (z_min - z_ba)
    z = np.empty(v.size)
    rate = np.empty(v.size)
    zi = z0
    for i in range(v.size):
        if i > 0:
            m = _substeps(v[i - 1], v[i], dt, stiffness)
            h = dt / m
            dv = (v[i] - v[i - 1]) / m
            for j in range(m):
                va = v[i - 1] + j * dv
                k1 = _ep_rate(zi, va, p)
                k2 = _ep_rate(zi + 0.5 * h * k1, va + 0.5 * dv, p)
                k3 = _ep_rate(zi + 0.5 * h * k2, va + 0.5 * dv, p)
                k4 = _ep_rate(zi + h * k3, va + dv, p)
                zi += h * (k1 + 2.0 * k2 + 2.0 * k3 + k4) / 6.0
        z[i] = zi
        rate[i] = _ep_rate(zi, v[i], p)
    return z, rate


@dataclass(frozen=True)
class ElastoPlastic(BristleLaw):
    """The elasto-plastic law (Dupont et al. 2002): `BristleLaw`'s parameters and `z_ba`
    (m, keyword), the breakaway deflection below which the contact is purely elastic,
    0 ≤ z_ba < min(F_c, F_s)/σ0."""

    z_ba: float = field(kw_only=True)

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 0.0 <= self.z_ba < min(self.F_c, self.F_s) / self.sigma0:
            raise ValueError(f"z_ba must lie in [0, min(F_c, F_s)/sigma0), got {self.z_ba}")

    def deflection(self, v, dt, z0=0.0):
        params = np.array([self.sigma0, self.F_c, self.F_s, self.v_s, self.z_ba])
        return _elastoplastic(np.ascontiguousarray(v, dtype=float), float(dt), params,
                              float(z0))


# --- the generalized Maxwell-slip model -----------------------------------------------------

GMS_STRIBECK_STEP = 0.005
"""Largest change of v on one GMS substep, in Stribeck velocities (s(v) is held at the
substep's midpoint: this bounds its change there to about 0.4 % of F_s − F_c)."""


@njit(**_JIT)
def _stribeck_delta(v: float, F_c: float, F_s: float, v_s: float, delta: float) -> float:
    """|s(v)| = F_c + (F_s − F_c) e^{−|v/v_s|^δ} (N), the GMS paper's Stribeck curve."""
    return F_c + (F_s - F_c) * math.exp(-abs(v / v_s) ** delta)


@njit(**_JIT)
def _gms_block(F: float, slip: float, k: float, alpha: float, vm: float, h: float,
               S: float, C: float) -> tuple:
    """One block over h (s) at constant velocity vm ≠ 0 (m/s), |s(vm)| = S (N): its force
    F (N) and state slip (0 sticking, ±1 slipping in that direction) after h.

    Sticking, dF/dt = k v, is exact; the instant it reaches W = α S in the direction of
    motion the block slips for the rest of h, where dF/dt = sgn(v) C (α − F/s(v)) has the
    exact solution F → d α S + (F − d α S) e^{−C t/S} (d = sgn v)."""
    d = 1.0 if vm > 0.0 else -1.0
    if slip != 0.0 and slip != d:
        slip = 0.0                                   # the velocity reversed: it sticks
    target = d * alpha * S
    remaining = h
    if slip == 0.0:
        if d * F >= alpha * S:
            remaining = h                            # at or beyond its limit: slips now
        else:
            reach = (target - F) / (k * vm)
            if reach >= h:
                return F + k * vm * h, 0.0
            F = target
            remaining = h - reach
        slip = d
    return target + (F - target) * math.exp(-C * remaining / S), slip


@njit(**_JIT)
def _gms(v: np.ndarray, dt: float, k: np.ndarray, alpha: np.ndarray, p: np.ndarray,
         F0: np.ndarray) -> tuple:
    """Block forces F_i (N, samples × blocks) and Σ dF_i/dt (N/s) at the samples of v
    (m/s), v linear between samples and held at its midpoint on each substep (sticking is
    then exact: the midpoint rule integrates a linear v exactly). Substeps keep a block's
    elastic travel k_i |v| h / (α_i min(F_c, F_s)) ≤ MAX_DECAY_PER_SUBSTEP and, with a
    Stribeck peak, the change of v within GMS_STRIBECK_STEP v_s, so a block's stick–slip
    transition and s(v) are resolved within a sample."""
    F_c, F_s, v_s, delta, C = p[0], p[1], p[2], p[3], p[4]
    stribeck_step = GMS_STRIBECK_STEP * v_s if F_s != F_c else math.inf
    n_blocks = k.size
    rate = 0.0
    for b in range(n_blocks):
        rate = max(rate, k[b] / (alpha[b] * min(F_c, F_s)))
    forces = np.empty((v.size, n_blocks))
    total_rate = np.empty(v.size)
    F = F0.copy()
    slip = np.zeros(n_blocks)
    for i in range(v.size):
        if i > 0:
            m = _substeps(v[i - 1], v[i], dt, rate)
            m = min(MAX_SUBSTEPS, max(m, int(math.ceil(abs(v[i] - v[i - 1]) / stribeck_step))))
            h = dt / m
            for j in range(m):
                vm = v[i - 1] + (v[i] - v[i - 1]) * (j + 0.5) / m
                if vm == 0.0:
                    for b in range(n_blocks):
                        slip[b] = 0.0
                    continue
                S = _stribeck_delta(vm, F_c, F_s, v_s, delta)
                for b in range(n_blocks):
                    F[b], slip[b] = _gms_block(F[b], slip[b], k[b], alpha[b], vm, h, S, C)
        forces[i] = F
        S = _stribeck_delta(v[i], F_c, F_s, v_s, delta)
        d = 0.0 if v[i] == 0.0 else (1.0 if v[i] > 0.0 else -1.0)
        r = 0.0
        for b in range(n_blocks):
            if slip[b] != 0.0 and slip[b] == d:
                r += d * C * (alpha[b] - F[b] / (d * S))
            else:
                r += k[b] * v[i]
        total_rate[i] = r
    return forces, total_rate


@dataclass(frozen=True)
class GMS:
    """The generalized Maxwell-slip model (Al-Bender, Lampaert, Swevers 2005; its laws
    are written out in the module docstring), SI: stiffness k_i (N/m) and weights α_i
    (–, Σ α_i = 1) of the N blocks, F_c, F_s (N) Coulomb and static levels and v_s (m/s),
    δ (–) of the Stribeck curve s(v), C (N/s) the attraction parameter (how fast a
    slipping block's force follows α_i s(v): the frictional lag), sigma1 (N·s/m) the
    blocks' damping (block i gets σ1 k_i / Σk, so σ1 v while every block sticks, as
    LuGre's σ1), sigma2 (N·s/m) the viscous coefficient."""

    stiffness: tuple[float, ...]
    weights: tuple[float, ...]
    F_c: float
    F_s: float
    v_s: float
    C: float
    delta: float = 2.0
    sigma1: float = 0.0
    sigma2: float = 0.0

    def __post_init__(self) -> None:
        k, a = np.asarray(self.stiffness, float), np.asarray(self.weights, float)
        if not (k.ndim == 1 and k.size >= 1 and k.shape == a.shape):
            raise ValueError(f"need as many stiffnesses as weights (≥ 1), got {k.size}, "
                             f"{a.size}")
        if not (np.all(k > 0.0) and np.all(a > 0.0) and abs(a.sum() - 1.0) <= 1e-9):
            raise ValueError("stiffnesses and weights must be > 0, the weights sum to 1")
        for name in ("F_c", "F_s", "v_s", "C", "delta"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("sigma1", "sigma2"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")

    @classmethod
    def uniform(cls, F_c: float, presliding: float, blocks: int = 8, **law) -> "GMS":
        """`blocks` blocks of one stiffness whose slip displacements Δ_i = α_i F_c / k_i
        are the midpoints of N equal parts of (0, 2 x_p] (`maxwell_slip_limits`): Iwan's
        uniform distribution, a virgin curve within F_c/(4N²) of F_c (ξ − ξ²/4), ξ = x/x_p
        ≤ 2, initial stiffness σ0 = F_c/x_p. `law`: F_s (default
        F_c), v_s (1 m/s), C (1e9 N/s), delta, sigma1, sigma2."""
        limits, weights = maxwell_slip_limits(presliding, blocks)
        law = {"F_s": F_c, "v_s": 1.0, "C": 1e9} | law
        return cls(stiffness=tuple(float(k) for k in weights * F_c / limits),
                   weights=tuple(float(a) for a in weights), F_c=F_c, **law)

    def stribeck(self, v: np.ndarray | float) -> np.ndarray:
        """|s(v)| = F_c + (F_s − F_c) e^{−|v/v_s|^δ} (N)."""
        v = np.asarray(v, dtype=float)
        return self.F_c + (self.F_s - self.F_c) * np.exp(-np.abs(v / self.v_s) ** self.delta)

    def steady(self, v: np.ndarray | float) -> np.ndarray:
        """Steady sliding force (N) at constant v (m/s): s(v) + σ2 v (every block at
        α_i s(v), the Stribeck curve)."""
        v = np.asarray(v, dtype=float)
        return self.stribeck(v) * np.sign(v) + self.sigma2 * v

    def block_forces(self, v: np.ndarray, dt: float, F0: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
        """Each block's force F_i (N, samples × blocks) and Σ_i dF_i/dt (N/s) at the
        samples of v (m/s, every dt s), from block forces F0 (N; default 0, every block
        sticking at the start)."""
        k, a = np.asarray(self.stiffness, float), np.asarray(self.weights, float)
        F0 = np.zeros(k.size) if F0 is None else np.asarray(F0, dtype=float)
        params = np.array([self.F_c, self.F_s, self.v_s, self.delta, self.C])
        return _gms(np.ascontiguousarray(v, dtype=float), float(dt), k, a, params,
                    np.ascontiguousarray(F0))

    def force(self, v: np.ndarray, dt: float, F0: np.ndarray | None = None) -> np.ndarray:
        """Friction force (N) Σ_i (F_i + σ_i dz_i/dt) + σ2 v, the GMS output with the
        blocks' damping (module docstring), F_i = k_i z_i and σ_i = σ1 k_i/Σk, at each
        sample of v (m/s, every dt s)."""
        forces, rate = self.block_forces(v, dt, F0)
        return (forces.sum(axis=1) + self.sigma1 / float(np.sum(self.stiffness)) * rate
                + self.sigma2 * np.asarray(v, dtype=float))


def maxwell_slip_limits(presliding: float, blocks: int) -> tuple[np.ndarray, np.ndarray]:
    """Slip displacements Δ_i (m) and weights α_i of Iwan's uniform distribution: blocks of
    one stiffness, Δ_i = 2 x_p (i − ½)/N, α_i = Δ_i / Σ Δ (so k_i = α_i F_c/Δ_i is the
    same for all, and the initial stiffness Σ k_i is F_c/x_p)."""
    if not (presliding > 0.0 and blocks >= 1):
        raise ValueError(f"need presliding > 0 and blocks >= 1, got {presliding}, {blocks}")
    limits = 2.0 * presliding * (np.arange(blocks) + 0.5) / blocks
    return limits, limits / limits.sum()


@njit(**_JIT)
def _maxwell_slip_path(x: np.ndarray, limits: np.ndarray, u0: float) -> np.ndarray:
    """Normalised block deflections u_i = z_i/Δ_i ∈ [−1, 1] (samples × blocks) along x:
    each block follows x until |z_i| = Δ_i and slips there (exact for x linear between
    samples: an elastic-perfectly-plastic block depends on the path only)."""
    out = np.empty((x.size, limits.size))
    z = u0 * limits
    for i in range(x.size):
        if i > 0:
            dx = x[i] - x[i - 1]
            for b in range(limits.size):
                z[b] = min(max(z[b] + dx, -limits[b]), limits[b])
        for b in range(limits.size):
            out[i, b] = z[b] / limits[b]
    return out


def maxwell_slip_normalised(x: np.ndarray, presliding: float, blocks: int = 8,
                            u0: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The rate-independent GMS (F_s = F_c, or C → ∞ at a constant s) over its level:
    w = F/F_c = Σ α_i u_i ∈ [−1, 1] along positions x (m), Iwan's uniform distribution of
    `blocks` blocks (`maxwell_slip_limits`), and the block states u_i = z_i/Δ_i (samples ×
    blocks); u0: every block's u at x[0]. Virgin curve within 1/(4N²) of w = ξ − ξ²/4,
    ξ = x/x_p ≤ 2 (piecewise linear, breaking at the Δ_i); after a reversal the branch is
    the virgin curve scaled by 2 in x and w (Masing), and a closed minor loop leaves no
    trace (non-local memory)."""
    if not -1.0 <= u0 <= 1.0:
        raise ValueError(f"need |u0| <= 1, got {u0}")
    limits, weights = maxwell_slip_limits(presliding, blocks)
    u = _maxwell_slip_path(np.ascontiguousarray(x, dtype=float), limits, float(u0))
    return u @ weights, u
