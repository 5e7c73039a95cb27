"""Contour and tracking error of two axes with matching dynamics under the P-PI cascade of
Fig. 4.15 (thesis Ch. 4.6, Table 4.3).

Each axis: the open-loop mobility ẋ_mot/F_mot (m/(N·s), a rational model such as
`polezero.PoleZeroModel.transfer_function` or `servo.with_delay(servo.chain_mobility(...))`)
closed by the PI velocity loop F = K_p (1 + 1/(T_i s)) (v_cmd − ẋ_mot) and the P position
loop v_cmd = P(s) (K_v (x_f − x_mot) + K_ffv v_ref). The position reference passes the
first-order balancing filter x_f = x_ref/(τ_BF s + 1); the velocity feed-forward takes the
unfiltered reference velocity; P(s) is the Padé approximation (Eq. 4.16) of an optional
position-loop delay (1 without): the whole velocity command of a sampled position loop is
late (≈ half its period for the hold), feed-forward included. The closed loop is one state-space model, simulated by
`scipy.signal.lsim` (exact for the piecewise-linear reference); its denominator is
`rootlocus.cascade_characteristic`. Errors are those of the motor-side (encoder) position,
as in the thesis's simulation.

Test contours: a circle and a 90° corner at one feed. Every move starts and ends at rest
with a sin² velocity ramp (jerk finite, acceleration continuous) whose peak tangential
acceleration is the caller's limit; the corner is two straight moves with an exact stop at
the corner. After the reference stops the run continues for `SETTLE_S`.
"""

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import linalg, signal
from scipy.spatial import cKDTree

from feedbench.analysis.servo import StateSpace, pade_delay
from feedbench.models.axis import CascadeGains
from feedbench.units import mm_per_min_to_m_per_s

RealArray = NDArray[np.float64]

SETTLE_S = 0.2
"""Time (s) the simulation runs on after the reference has stopped."""


@dataclass(frozen=True)
class ContourSpec:
    """Test contour: circle radius (mm), feed (mm/min), peak path acceleration (m/s²),
    corner leg length (mm) and simulation step (s)."""

    radius_mm: float = 10.0
    feed_mm_min: float = 5000.0
    acceleration_m_s2: float = 2.0
    corner_leg_mm: float = 20.0
    step_s: float = 0.5e-3


@dataclass(frozen=True)
class Feedforward:
    """Velocity feed-forward gain K_ffv (–) and balancing-filter time constant τ_BF (s)
    on the position reference (Fig. 4.15: K_ffv = 1, τ_BF = 1 ms); τ_BF = 0: no filter."""

    K_ffv: float = 1.0
    tau_BF: float = 1e-3


@dataclass(frozen=True)
class Path:
    """A reference trajectory in the x–y plane: time (s, n), position and velocity (n × 2;
    m, m/s), `moving` (n, bool): before the reference has stopped; `cruise` (n, bool): at
    the constant feed."""

    time: RealArray
    position: RealArray
    velocity: RealArray
    moving: NDArray[np.bool_]
    cruise: NDArray[np.bool_]


@dataclass(frozen=True)
class MotionErrors:
    """Table 4.3's four numbers (µm): contour error max/RMS (distance of the actual point
    to the reference path), tracking error max/RMS (|reference(t) − actual(t)|). RMS over
    the reference's motion, max over the motion and the settling after it."""

    contour_max_um: float
    contour_rms_um: float
    tracking_max_um: float
    tracking_rms_um: float


@dataclass(frozen=True)
class ContourRun:
    """A simulated contour: the reference path, the actual (motor) positions (n × 2, m),
    contour and tracking error per sample (n, m) and their summary."""

    path: Path
    actual: RealArray
    contour_error: RealArray
    tracking_error: RealArray
    errors: MotionErrors


def ramp_profile(distance: float, speed: float, acceleration: float, step: float
                 ) -> tuple[RealArray, RealArray, NDArray[np.bool_]]:
    """Arc length s (m) and speed (m/s) every `step` s of a rest-to-rest move over
    `distance` (m): sin² ramps of peak acceleration `acceleration` (m/s²) to `speed`, cruise,
    sin² ramp down; plus the cruise mask. A move too short to reach `speed` cruises at the
    speed its ramps reach."""
    if min(distance, speed, acceleration, step) <= 0:
        raise ValueError("distance, speed, acceleration and step must be positive")
    speed = min(speed, np.sqrt(2.0 * distance * acceleration / np.pi))
    ramp = np.pi * speed / (2.0 * acceleration)
    cruise = (distance - speed * ramp) / speed
    t = np.arange(0.0, 2.0 * ramp + cruise + step / 2, step)
    up, down = np.clip(t / ramp, 0, 1), np.clip((t - ramp - cruise) / ramp, 0, 1)
    velocity = speed * (np.sin(np.pi * up / 2) ** 2 - np.sin(np.pi * down / 2) ** 2)
    arc = speed * ramp * (_ramp_integral(up) - _ramp_integral(down)) + speed * (
        np.maximum(t - ramp, 0) - np.maximum(t - 2.0 * ramp - cruise, 0))
    return np.minimum(arc, distance), velocity, (t >= ramp) & (t <= ramp + cruise)


def _ramp_integral(u: RealArray) -> RealArray:
    """∫₀ᵘ sin²(π w/2) dw = u/2 − sin(π u)/(2π): a sin² ramp's distance per speed·ramp time."""
    return u / 2 - np.sin(np.pi * u) / (2 * np.pi)


def _settled(path: Path, step: float) -> Path:
    """`path` followed by SETTLE_S at rest at its last point."""
    extra = int(round(SETTLE_S / step))
    time = np.concatenate([path.time, path.time[-1] + step * np.arange(1, extra + 1)])
    hold = np.repeat(path.position[-1:], extra, axis=0)
    still = np.zeros(extra, dtype=bool)
    return Path(time, np.concatenate([path.position, hold]),
                np.concatenate([path.velocity, np.zeros((extra, 2))]),
                np.concatenate([path.moving, still]), np.concatenate([path.cruise, still]))


def straight_path(start_mm: tuple[float, float], end_mm: tuple[float, float], feed_mm_min: float,
                  acceleration_m_s2: float, step_s: float) -> Path:
    """Rest-to-rest straight move from `start_mm` to `end_mm` (mm) at the feed (mm/min)."""
    start, end = np.asarray(start_mm, float) * 1e-3, np.asarray(end_mm, float) * 1e-3
    length = float(np.hypot(*(end - start)))
    direction = (end - start) / length
    arc, speed, cruise = ramp_profile(length, mm_per_min_to_m_per_s(feed_mm_min),
                                      acceleration_m_s2, step_s)
    return Path(np.arange(arc.size) * step_s, start + arc[:, None] * direction,
                speed[:, None] * direction, np.ones(arc.size, dtype=bool), cruise)


def circle_path(spec: ContourSpec) -> Path:
    """One full revolution at the feed (counter-clockwise, centre at the origin, starting at
    (R, 0)), entered and left along the circle by the sin² ramps; then SETTLE_S at rest.

    The centripetal acceleration v²/R must not exceed the acceleration limit."""
    radius, speed = spec.radius_mm * 1e-3, mm_per_min_to_m_per_s(spec.feed_mm_min)
    if speed**2 / radius > spec.acceleration_m_s2:
        raise ValueError(f"feed {spec.feed_mm_min} mm/min on a {spec.radius_mm} mm circle needs "
                         f"{speed**2 / radius:.3g} m/s² centripetal, above the "
                         f"{spec.acceleration_m_s2} m/s² limit")
    ramp_distance = np.pi * speed**2 / (2.0 * spec.acceleration_m_s2)
    arc, velocity, cruise = ramp_profile(2 * np.pi * radius + ramp_distance, speed,
                                         spec.acceleration_m_s2, spec.step_s)
    angle = arc / radius
    unit = np.column_stack([np.cos(angle), np.sin(angle)])
    tangent = np.column_stack([-np.sin(angle), np.cos(angle)])
    path = Path(np.arange(arc.size) * spec.step_s, radius * unit, velocity[:, None] * tangent,
                np.ones(arc.size, dtype=bool), cruise)
    return _settled(path, spec.step_s)


def corner_path(spec: ContourSpec) -> Path:
    """A 90° corner: along +x for `corner_leg_mm`, exact stop, along +y as far; then
    SETTLE_S at rest."""
    leg = spec.corner_leg_mm
    first = straight_path((0.0, 0.0), (leg, 0.0), spec.feed_mm_min, spec.acceleration_m_s2,
                          spec.step_s)
    second = straight_path((leg, 0.0), (leg, leg), spec.feed_mm_min, spec.acceleration_m_s2,
                           spec.step_s)
    offset = first.time[-1] + spec.step_s
    path = Path(np.concatenate([first.time, second.time + offset]),
                *(np.concatenate([getattr(first, name), getattr(second, name)])
                  for name in ("position", "velocity", "moving", "cruise")))
    return _settled(path, spec.step_s)


def _balanced(a: RealArray, b: RealArray, c: RealArray) -> tuple[RealArray, RealArray, RealArray]:
    """(A, B, C) under the diagonal similarity that balances A (LAPACK gebal): the companion
    forms of tf2ss span many decades, which the balanced form keeps off the state scaling."""
    a_balanced, (scale, _) = linalg.matrix_balance(a, permute=False, separate=True)
    return a_balanced, b / scale[:, None], c * scale[None, :]


def _plant(mobility: signal.TransferFunction) -> tuple[RealArray, RealArray, RealArray]:
    """Balanced (A, B, C) of the mobility F_mot → ẋ_mot; it must be strictly proper."""
    a, b, c, d = signal.tf2ss(mobility.num, mobility.den)
    if np.any(np.abs(d) > 0):
        raise ValueError("the mobility must be strictly proper (no direct force → velocity term)")
    return _balanced(a, b, c)


def _delay(position_delay: float, pade_order: int) -> StateSpace:
    """State space of the position loop's delay by Padé (Eq. 4.16); a unit gain without."""
    if position_delay <= 0:
        return np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)), np.ones((1, 1))
    pade = pade_delay(position_delay, pade_order)
    a, b, c, d = signal.tf2ss(pade.num, pade.den)
    return (*_balanced(a, b, c), d)


def cascade_state_space(mobility: signal.TransferFunction, gains: CascadeGains,
                        feedforward: Feedforward = Feedforward(), position_delay: float = 0.0,
                        pade_order: int = 2) -> StateSpace:
    """One axis of Fig. 4.15 closed: inputs (x_ref m, v_ref m/s), output x_mot (m).

    States: plant, x_mot, PI integral ∫(v_cmd − ẋ_mot) dt, Padé delay, balancing filter.
    Each signal is written as a row over [states, inputs] and the state derivatives are
    stacked from them; at rest at 0 every state is 0.
    """
    a_g, b_g, c_g = _plant(mobility)
    a_p, b_p, c_p, d_p = _delay(position_delay, pade_order)
    filtered = feedforward.tau_BF > 0
    sizes = [a_g.shape[0], 1, 1, a_p.shape[0], int(filtered), 1, 1]
    edges = np.cumsum([0, *sizes])
    width = int(edges[-1])
    plant, x_mot, integral, delay, bf, x_ref, v_ref = (
        np.eye(width)[edges[i]:edges[i + 1]] for i in range(len(sizes)))
    x_f = bf if filtered else x_ref
    position_loop = gains.K_v * (x_f - x_mot) + feedforward.K_ffv * v_ref
    v_cmd = c_p @ delay + d_p @ position_loop
    v_mot = c_g @ plant
    velocity_error = v_cmd - v_mot
    force = gains.K_p * (velocity_error + integral / gains.T_i)
    derivatives = [a_g @ plant + b_g @ force, v_mot, velocity_error,
                   a_p @ delay + b_p @ position_loop]
    if filtered:
        derivatives.append((x_ref - bf) / feedforward.tau_BF)
    ab = np.vstack(derivatives)
    n = width - 2
    return ab[:, :n], ab[:, n:], x_mot[:, :n], np.zeros((1, 2))


def distance_to_path(vertices: RealArray, points: RealArray) -> RealArray:
    """Distance (m) of each point to the polyline through `vertices` (both n × 2, m).

    The nearest vertex (k-d tree) and the segments on either side of it: exact where the
    polyline is sampled finer than the distances and its curvature radius."""
    finite = np.all(np.isfinite(points), axis=1)
    if not finite.all():  # a diverging (unstable) loop's points: infinitely far
        distance = np.full(points.shape[0], np.inf)
        distance[finite] = distance_to_path(vertices, points[finite])
        return distance
    keep = np.r_[True, np.any(np.diff(vertices, axis=0) != 0, axis=1)]
    v = vertices[keep]
    if v.shape[0] == 1:
        return np.hypot(*(points - v[0]).T)
    _, nearest = cKDTree(v).query(points)
    best = np.full(points.shape[0], np.inf)
    for first in (nearest - 1, nearest):
        i = np.clip(first, 0, v.shape[0] - 2)
        a, edge = v[i], v[i + 1] - v[i]
        t = np.clip(np.einsum("ij,ij->i", points - a, edge) / np.einsum("ij,ij->i", edge, edge),
                    0, 1)
        best = np.minimum(best, np.hypot(*(points - a - t[:, None] * edge).T))
    return best


def motion_errors(path: Path, actual: RealArray) -> tuple[RealArray, RealArray, MotionErrors]:
    """Contour error (distance to the reference path) and tracking error (|x_ref(t) − x(t)|)
    per sample (m), and their maxima and RMS in µm (`MotionErrors`)."""
    contour = distance_to_path(path.position, actual)
    tracking = np.hypot(*(path.position - actual).T)

    def rms(e: RealArray) -> float:
        return float(np.sqrt(np.mean(e[path.moving] ** 2)) * 1e6)

    summary = MotionErrors(contour_max_um=float(contour.max() * 1e6), contour_rms_um=rms(contour),
                           tracking_max_um=float(tracking.max() * 1e6),
                           tracking_rms_um=rms(tracking))
    return contour, tracking, summary


def follow(mobility: signal.TransferFunction, gains: CascadeGains, path: Path,
           feedforward: Feedforward = Feedforward(), position_delay: float = 0.0,
           pade_order: int = 2) -> ContourRun:
    """Both axes (matching dynamics) following `path` from rest: actual positions and errors.

    The loop is linear, so each axis is simulated from its start point as the origin. An
    unstable loop (a pole in the right half-plane) diverges: positions and errors infinite."""
    system = cascade_state_space(mobility, gains, feedforward, position_delay, pade_order)
    start = path.position[0]
    if np.any(np.linalg.eigvals(system[0]).real > 0):
        actual = np.full(path.position.shape, np.inf)
    else:
        actual = np.column_stack([
            signal.lsim(system, np.column_stack([path.position[:, axis] - start[axis],
                                                 path.velocity[:, axis]]), path.time)[1]
            for axis in (0, 1)
        ]) + start
    contour, tracking, summary = motion_errors(path, actual)
    return ContourRun(path, actual, contour, tracking, summary)


def contour_paths(spec: ContourSpec) -> dict[str, Path]:
    """The circle and the corner of `spec` by name ("circle", "corner")."""
    return {"circle": circle_path(spec), "corner": corner_path(spec)}
