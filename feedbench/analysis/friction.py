"""Friction identification from a friction sweep (Ch. 5.3.2, Fig. 5.11; Ch. 5.5.2, Fig. 5.19).

Input: the steady-state mean motor force F (N) at each commanded feed v (m/s) of a
constant-velocity sweep. Output: the Andersson law of Eq. (5.2) per direction (or the
reduced Coulomb + viscous law), fitted by bounded least squares, with the parameter
standard deviations from the Jacobian, the RMS residual and R².

The law itself lives in `feedbench.models.friction` (one definition shared with the
simulator); this module only fits it and reads derived quantities off it.
"""

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy

from feedbench.models.friction import AnderssonFriction, DirectionalFriction

_TOL = 1e-12
"""ftol/xtol/gtol of least_squares: noise-free data must come back to machine precision."""


@dataclass(frozen=True)
class AnderssonStd:
    """One-sigma standard deviations of the fitted parameters (N, N, m/s, N·s/m, –).

    NaN for a parameter that was held fixed (or does not exist in the reduced model).
    """

    F_c: float
    F_s: float
    v_s: float
    sigma: float
    delta: float


@dataclass(frozen=True)
class FrictionFit:
    """A friction law fitted to one direction of a friction sweep.

    params: the fitted law, SI; std: parameter standard deviations; rms: RMS residual (N);
    r_squared: coefficient of determination; n_points: number of feeds used.
    """

    params: AnderssonFriction
    std: AnderssonStd
    rms: float
    r_squared: float
    n_points: int


@dataclass(frozen=True)
class DirectionalFrictionFit:
    """Fits of both directions; `negative` was fitted on |v|, |F|."""

    positive: FrictionFit
    negative: FrictionFit

    @property
    def model(self) -> DirectionalFriction:
        """The fitted direction-dependent law, ready for the simulator."""
        return DirectionalFriction(positive=self.positive.params, negative=self.negative.params)


@dataclass(frozen=True)
class _Parametrisation:
    """How a free-parameter vector x maps to a law and to the physical parameters.

    jacobian: d(F_c, F_s, v_s, sigma, delta)/dx, used to carry the covariance of x over.
    """

    to_law: Callable[[np.ndarray], AnderssonFriction]
    jacobian: np.ndarray


def _one_direction(v: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Speeds |v| and force magnitudes |F| of a sweep that must not change direction."""
    v = np.asarray(v, dtype=float).ravel()
    F = np.asarray(F, dtype=float).ravel()
    if v.shape != F.shape:
        raise ValueError(f"v and F must have the same length, got {v.size} and {F.size}")
    if np.any(v == 0.0) or not (np.all(v > 0.0) or np.all(v < 0.0)):
        raise ValueError("v must be non-zero and of one sign; use fit_andersson_directional")
    return np.abs(v), np.abs(F)


def _fit(
    speed: np.ndarray,
    force: np.ndarray,
    x0: np.ndarray,
    lower: np.ndarray,
    x_scale: np.ndarray,
    param: _Parametrisation,
) -> FrictionFit:
    """Bounded least squares of the law against the data, then covariance from the Jacobian."""
    n_free = x0.size
    if speed.size <= n_free:
        raise ValueError(f"need more than {n_free} feeds to fit {n_free} parameters, got {speed.size}")

    def residual(x: np.ndarray) -> np.ndarray:
        return param.to_law(x).force(speed) - force

    sol = scipy.optimize.least_squares(
        residual, x0, bounds=(lower, np.inf), x_scale=x_scale, jac="3-point",
        ftol=_TOL, xtol=_TOL, gtol=_TOL,
    )
    ssr = float(sol.fun @ sol.fun)
    dof_variance = ssr / (speed.size - n_free)
    cov_x = np.linalg.pinv(sol.jac.T @ sol.jac) * dof_variance
    cov = param.jacobian @ cov_x @ param.jacobian.T
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    std[~np.any(param.jacobian != 0.0, axis=1)] = np.nan
    sst = float(np.sum((force - force.mean()) ** 2))
    return FrictionFit(
        params=param.to_law(sol.x),
        std=AnderssonStd(*std),
        rms=float(np.sqrt(ssr / speed.size)),
        r_squared=1.0 - ssr / sst if sst > 0.0 else float("nan"),
        n_points=speed.size,
    )


def _sliding_line(speed: np.ndarray, force: np.ndarray) -> tuple[float, float]:
    """Coulomb level and viscous slope (N, N·s/m) of a line through the fastest third."""
    fast = speed >= np.quantile(speed, 2.0 / 3.0)
    sigma, coulomb = np.polyfit(speed[fast], force[fast], 1)
    sigma = max(sigma, 0.0)
    coulomb = max(float(np.mean(force[fast] - sigma * speed[fast])), 1e-3 * force.max())
    return coulomb, sigma


def _stribeck_guess(speed: np.ndarray, force: np.ndarray, coulomb: float, sigma: float) -> tuple[float, float]:
    """Static level F_s (N) and Stribeck speed v_s (m/s) read off the excess over the line.

    v_s: the speed where the excess has fallen to 1/e of its value at the slowest feed.
    """
    order = np.argsort(speed)
    v, excess = speed[order], force[order] - coulomb - sigma * speed[order]
    peak = max(excess[0], 0.0)
    below = np.nonzero(excess < peak / np.e)[0]
    v_s = v[below[0]] if below.size and peak > 0.0 else float(np.median(v))
    return coulomb + peak * np.exp(v[0] / v_s), float(v_s)


def fit_andersson(
    v: np.ndarray,
    F: np.ndarray,
    k_tanh: float = 15000.0,
    delta: float = 1.0,
    fit_delta: bool = False,
) -> FrictionFit:
    """Fit the Andersson law, Eq. (5.2), to ONE direction of a friction sweep.

    v: feeds of one sign (m/s); F: steady-state mean motor force per feed (N).
    A negative sweep is fitted on |v|, |F|. k_tanh (s/m) is held fixed; δ is held at
    `delta` unless `fit_delta`. Bounds: 0 < F_c ≤ F_s, v_s ≥ 1e-9 max|v|, σ ≥ 0 (F_s
    is parametrised as F_c + ΔF with ΔF ≥ 0; least_squares' 'trf' keeps iterates strictly
    inside the bounds). Initial guesses: a line through the fastest third of the points
    (F_c, σ) and the excess over that line at the slow end (F_s, v_s).
    """
    speed, force = _one_direction(v, F)
    coulomb, sigma = _sliding_line(speed, force)
    static, v_s = _stribeck_guess(speed, force, coulomb, sigma)
    f_scale, v_scale = float(force.max()), float(speed.max())

    def to_law(x: np.ndarray) -> AnderssonFriction:
        shape = x[4] if fit_delta else delta
        return AnderssonFriction(
            F_c=x[0], F_s=x[0] + x[1], v_s=x[2], sigma=x[3], k_tanh=k_tanh, delta=shape
        )

    # rows: F_c, F_s, v_s, sigma, delta; columns: F_c, ΔF, v_s, sigma(, delta)
    jacobian = np.zeros((5, 5 if fit_delta else 4))
    jacobian[[0, 1, 1, 2, 3], [0, 0, 1, 2, 3]] = 1.0
    x0 = [coulomb, static - coulomb, v_s, sigma]
    lower = [0.0, 0.0, 1e-9 * v_scale, 0.0]
    x_scale = [f_scale, f_scale, v_scale, f_scale / v_scale]
    if fit_delta:
        jacobian[4, 4] = 1.0
        x0, lower, x_scale = x0 + [delta], lower + [0.05], x_scale + [1.0]
    return _fit(speed, force, np.array(x0), np.array(lower), np.array(x_scale),
                _Parametrisation(to_law, jacobian))


def fit_coulomb_viscous(v: np.ndarray, F: np.ndarray, k_tanh: float = 15000.0) -> FrictionFit:
    """Fit the reduced Coulomb + viscous law, Eq. (5.2) with F_s = F_c (Ch. 5.4, Fig. 5.15).

    F = F_c tanh(k_tanh v) + σ v for ONE direction; v_s is meaningless there and set to ∞
    (its std is NaN). Bounds: F_c > 0, σ ≥ 0.
    """
    speed, force = _one_direction(v, F)
    coulomb, sigma = _sliding_line(speed, force)
    f_scale, v_scale = float(force.max()), float(speed.max())

    def to_law(x: np.ndarray) -> AnderssonFriction:
        return AnderssonFriction(F_c=x[0], F_s=x[0], v_s=np.inf, sigma=x[1], k_tanh=k_tanh)

    jacobian = np.zeros((5, 2))
    jacobian[[0, 1, 3], [0, 0, 1]] = 1.0
    return _fit(speed, force, np.array([coulomb, sigma]), np.zeros(2),
                np.array([f_scale, f_scale / v_scale]), _Parametrisation(to_law, jacobian))


def fit_andersson_directional(
    v: np.ndarray,
    F: np.ndarray,
    k_tanh: float = 15000.0,
    delta: float = 1.0,
    fit_delta: bool = False,
) -> DirectionalFrictionFit:
    """Fit Eq. (5.2) separately for v > 0 and v < 0 (points at v = 0 are ignored).

    The thesis finds direction-dependent parameters (Fig. 5.11: F_c 44.2⁺ / 38.7⁻ N).
    """
    v = np.asarray(v, dtype=float).ravel()
    F = np.asarray(F, dtype=float).ravel()
    return DirectionalFrictionFit(
        positive=fit_andersson(v[v > 0], F[v > 0], k_tanh, delta, fit_delta),
        negative=fit_andersson(v[v < 0], F[v < 0], k_tanh, delta, fit_delta),
    )


def invariant_feed(law: AnderssonFriction, K_p: float, fraction: float = 0.05) -> float:
    """Feed (m/s) above which the in-motion FRF is 'invariant' (Ch. 5.3.2, Fig. 5.12).

    Definition used here: the lowest speed above which the friction slope |dF/dv| stays
    below `fraction` × K_p, K_p (N·s/m) being the velocity-loop gain, i.e. the damping
    c_1 = K_p of the controller's mechanical equivalent, Eqs. (5.6–5.8). Above it the
    friction law acts on small vibrations as a damper much weaker than the controller.
    Lab bench (Fig. 5.11) with K_p = 2π · 34.4 kg · 30 Hz: fraction 0.05 gives 979 (+) /
    1135 (−) mm/min; the thesis's ≈ 500 mm/min corresponds to a fraction of ≈ 0.25–0.3.
    Searched on a log grid from 0.1 µm/s to 10 m/s, refined by brentq. Raises ValueError if the viscous slope σ alone is not below the threshold.
    """
    threshold = fraction * K_p
    if law.sigma >= threshold:
        raise ValueError(f"viscous slope σ = {law.sigma:.4g} N·s/m is not below {threshold:.4g} N·s/m")

    def excess(speed: float) -> float:
        return abs(float(law.slope(speed))) - threshold

    grid = np.geomspace(1e-7, 10.0, 4000)
    above = np.nonzero(np.abs(law.slope(grid)) >= threshold)[0]
    if above.size == 0:
        return 0.0
    last = above[-1]
    return float(scipy.optimize.brentq(excess, grid[last], grid[last + 1], xtol=1e-12))
