"""Static stiffness, backlash and preload of a rack-and-pinion master–slave axis (Ch. 3.4).

Inputs are the synchronous records of a stepped-loading test against a rigid bumper
(load-cell force, motor encoders expressed at the rack, linear scale) or of back-and-forth
moves without load. Relative displacement δ = x_motor − x_load (m) is the deflection of
everything in the motor's force path (Eq. 3.4) plus its dead zone (backlash).
"""

from dataclasses import dataclass

import numpy as np
import scipy


@dataclass(frozen=True)
class StiffnessFit:
    """Equivalent linear stiffness from load vs relative displacement, Eq. (3.26).

    k: stiffness (N/m) and its standard error; offset: relative displacement at zero load
    extrapolated from the loaded branch (m); force_range: (min, max) load used (N).
    """

    k: float
    k_std: float
    offset: float
    r_squared: float
    force_range: tuple[float, float]
    n_points: int


@dataclass(frozen=True)
class BacklashEstimate:
    """Lost motion between motor and load at direction reversals (m), Ch. 3.4.2.

    per_reversal: one value per reversal; value: their mean; std: their spread.
    """

    value: float
    std: float
    per_reversal: np.ndarray


@dataclass(frozen=True)
class PreloadLoss:
    """Where the electronically preloaded motor loses contact (Ch. 3.4.3, Fig. 3.11-a).

    force: load at the loss (N), where the master's contact force reaches zero; recovery:
    load at which it carries again on the other flank (N; equal to `force` if the crossing
    left no sample); jump: relative-displacement jump between the two contacts (m), which
    the thesis finds equal to the backlash; k_before / k_after: Eq. (3.26) stiffness of the
    two contact segments (N/m).
    """

    force: float
    recovery: float
    jump: float
    k_before: float
    k_after: float


@dataclass(frozen=True)
class LossStiffness:
    """Eq. (3.26) stiffness of the other (slave) motor around a preload loss (N/m), Fig. 3.12-b.

    contact: while both motors carry; lost: while the master has lost contact and the
    slave carries the whole load (half the contact value); n_lost: samples in that phase.
    """

    contact: float
    lost: float
    n_lost: int


@dataclass(frozen=True)
class TorqueSharing:
    """Fit of τ_master = share · (τ_master + τ_slave) + τ_preload, Eq. (3.1).

    share: fraction of the net torque the master carries (0.5 for K_Tm = K_Ts = 0.5);
    preload: the preload torque τ_p (N·m, or N if forces are given); r_squared of the fit.
    """

    share: float
    preload: float
    r_squared: float


def _loading_branch(force: np.ndarray, *signals: np.ndarray) -> tuple[np.ndarray, ...]:
    """Samples from the start up to the peak |load|, signs flipped so the load is positive."""
    force = np.asarray(force, dtype=float).ravel()
    peak = int(np.argmax(np.abs(force)))
    sign = np.sign(force[peak]) or 1.0
    return tuple(sign * np.asarray(s, dtype=float).ravel()[: peak + 1] for s in (force, *signals))


def equivalent_stiffness(
    force: np.ndarray,
    x_motor: np.ndarray,
    x_load: np.ndarray,
    min_fraction: float = 0.2,
    share: float = 1.0,
) -> StiffnessFit:
    """Equivalent stiffness k = share · ΔF_load / Δδ, Eq. (3.26), by a line fit.

    Uses the loading branch (start to peak load) above `min_fraction` of the peak, which
    leaves out the backlash take-up and the contact settling at low load. share = 1 for one
    motor alone (Ch. 3.4.1), 0.5 for master and slave in full contact (Eq. 3.26).
    """
    load, motor, scale = _loading_branch(force, x_motor, x_load)
    used = load >= min_fraction * load[-1]
    if np.count_nonzero(used) < 3:
        raise ValueError("fewer than 3 samples on the loaded branch above min_fraction")
    line = scipy.stats.linregress(motor[used] - scale[used], load[used])
    return StiffnessFit(
        k=share * line.slope,
        k_std=share * line.stderr,
        offset=-line.intercept / line.slope,
        r_squared=line.rvalue**2,
        force_range=(float(load[used].min()), float(load[used].max())),
        n_points=int(np.count_nonzero(used)),
    )


def incremental_stiffness(force: np.ndarray, delta: np.ndarray, share: float = 0.5) -> np.ndarray:
    """Sample-to-sample stiffness share · ΔF/Δδ (N/m), Eq. (3.26); length n − 1 (Fig. 3.12).

    Near zero where a motor crosses its backlash, about twice the pair value where one motor
    carries the whole load.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        return share * np.diff(np.asarray(force, dtype=float)) / np.diff(np.asarray(delta, dtype=float))


def backlash_from_reversals(
    x_motor: np.ndarray,
    x_load: np.ndarray,
    min_travel: float | None = None,
    settle_fraction: float = 0.5,
) -> BacklashEstimate:
    """Equivalent backlash L_z from back-and-forth moves without load (Ch. 3.4.2, Fig. 3.9).

    The motor's turning points are peaks of x_motor with prominence ≥ `min_travel`
    (default: half the stroke). In each stroke the plateau of δ = x_motor − x_load is taken
    as the median over the part after `settle_fraction` of the stroke's travel (the load has
    caught up once the motor has crossed the dead zone, so the stroke must exceed twice the
    backlash); the lost motion is the difference of consecutive plateaus. It includes the
    friction wind-up 2 F_friction / k of the drive train, as the measured value does.
    """
    x_motor = np.asarray(x_motor, dtype=float).ravel()
    delta = x_motor - np.asarray(x_load, dtype=float).ravel()
    travel = min_travel if min_travel is not None else 0.5 * np.ptp(x_motor)
    turns = np.sort(np.concatenate([
        scipy.signal.find_peaks(x_motor, prominence=travel)[0],
        scipy.signal.find_peaks(-x_motor, prominence=travel)[0],
    ]))
    if turns.size == 0:
        raise ValueError("no direction reversal with the required travel in x_motor")
    bounds = np.concatenate([[0], turns, [x_motor.size - 1]])
    plateaus = []
    for start, stop in zip(bounds[:-1], bounds[1:]):
        moved = np.abs(x_motor[start : stop + 1] - x_motor[start])
        if moved[-1] >= travel:
            plateaus.append(np.median(delta[start : stop + 1][moved >= settle_fraction * moved[-1]]))
    lost = np.abs(np.diff(plateaus))
    if lost.size == 0:
        raise ValueError("need two strokes of at least min_travel around a reversal")
    return BacklashEstimate(value=float(lost.mean()), std=float(lost.std()), per_reversal=lost)


def _line_sse_prefix(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """SSE of the least-squares line through the first m points, for every m (0 for m < 3).

    Running sums make every split of the two-segment fit O(1).
    """
    m = np.arange(1, x.size + 1)
    sx, sy = np.cumsum(x), np.cumsum(y)
    sxx, sxy, syy = np.cumsum(x * x), np.cumsum(x * y), np.cumsum(y * y)
    var_x = sxx - sx * sx / m
    cov = sxy - sx * sy / m
    var_y = syy - sy * sy / m
    with np.errstate(divide="ignore", invalid="ignore"):
        sse = var_y - np.where(var_x > 0.0, cov * cov / var_x, 0.0)
    sse[:2] = 0.0
    return sse


def _two_segment_split(f: np.ndarray, d: np.ndarray, min_points: int) -> int:
    """Index splitting sorted data into two lines with the least total squared error."""
    sse_left = _line_sse_prefix(f, d)
    sse_right = _line_sse_prefix(f[::-1], d[::-1])[::-1]
    splits = np.arange(min_points, f.size - min_points + 1)
    return int(splits[np.argmin(sse_left[splits - 1] + sse_right[splits])])


def _robust_line(f: np.ndarray, d: np.ndarray, max_points: int = 400) -> tuple[float, float]:
    """Siegel repeated-medians line (slope, intercept), 50 % breakdown, on ≤ max_points
    evenly spaced samples (its cost grows with the square of the count)."""
    pick = np.unique(np.linspace(0, f.size - 1, min(f.size, max_points)).astype(int))
    line = scipy.stats.siegelslopes(d[pick], f[pick])
    return line.slope, line.intercept


def _assign_to_lines(f: np.ndarray, d: np.ndarray, split: int, n_sigma: float) -> tuple[np.ndarray, ...]:
    """Masks of the samples on the first line, on the second, and on neither (crossing).

    Two robust lines fitted either side of `split`; each sample goes to the nearer one
    unless its distance exceeds n_sigma robust (MAD) standard deviations: then it was taken
    while the pinion crossed its dead zone.
    """
    distances = np.array([
        np.abs(d - intercept - slope * f)
        for slope, intercept in (_robust_line(f[:split], d[:split]), _robust_line(f[split:], d[split:]))
    ])
    nearest = np.min(distances, axis=0)
    crossing = nearest > n_sigma * 1.4826 * np.median(nearest)
    first = (distances[0] <= distances[1]) & ~crossing
    return first, ~first & ~crossing, crossing


def _master_contact_lines(load: np.ndarray, delta_master: np.ndarray, min_points: int,
                          n_sigma: float) -> tuple[np.ndarray, ...]:
    """The master's contact states on the loading branch, samples sorted by load.

    Returns the sort order, f (load, N) and δ_m (m) sorted, and the masks of the samples on
    the first contact line, on the second and on neither (crossing), split where a
    two-segment line fit of δ_m(F) has the least squared error.
    """
    order = np.argsort(load, kind="stable")
    f, d = load[order], delta_master[order]
    if f.size < 2 * min_points:
        raise ValueError(f"need at least {2 * min_points} samples on the loading branch")
    return order, f, d, *_assign_to_lines(f, d, _two_segment_split(f, d, min_points), n_sigma)


def preload_loss_force(
    force: np.ndarray,
    x_master: np.ndarray,
    x_load: np.ndarray,
    min_points: int = 5,
    share: float = 0.5,
    n_sigma: float = 6.0,
) -> PreloadLoss:
    """Load at which the preloaded master loses contact, from a coupled loading test.

    On the loading branch, δ_m = x_master − x_load against the load F follows one line
    while both motors carry (slope 1/(2 k_m)); at the loss the master's stiffness drops
    to zero and its pinion crosses the backlash at constant load, after which it carries
    on the other flank along a second line (Fig. 3.11-a). A two-segment piecewise-linear
    fit of δ_m(F) (the split with the least squared error, exhaustive via running sums)
    locates the kink; robust lines either side sort the samples into first line, second
    line and crossing (on neither), and the two lines are refitted on their own samples.
    The loss is the midpoint between the last load on the first line and the next load
    (crossing or second line); the recovery, between the last crossing load and the first
    on the second line. The flank change takes time (Ch. 3.4.3), so under a rising load the
    crossing spans loads. jump: the distance between the lines at the loss (≈ the
    backlash, Ch. 3.4.3).
    """
    load, master, scale = _loading_branch(force, x_master, x_load)
    _, f, d, first, second, crossing = _master_contact_lines(load, master - scale, min_points,
                                                             n_sigma)
    if np.count_nonzero(first) < 3 or np.count_nonzero(second) < 3:
        raise ValueError("fewer than 3 samples on one of the contact lines: the loading "
                         "must go on well beyond the loss (and start below it)")
    before = scipy.stats.linregress(f[first], d[first])
    after = scipy.stats.linregress(f[second], d[second])
    last_contact = f[first].max()
    loss = 0.5 * (last_contact + f[f > last_contact].min())
    recovery = 0.5 * (f[crossing].max() + f[second].min()) if crossing.any() else loss
    return PreloadLoss(
        force=float(loss),
        recovery=float(recovery),
        jump=float(after.intercept - before.intercept + (after.slope - before.slope) * loss),
        k_before=share / before.slope,
        k_after=share / after.slope,
    )


def stiffness_while_lost(
    force: np.ndarray,
    x_master: np.ndarray,
    x_other: np.ndarray,
    x_load: np.ndarray,
    force_master: np.ndarray,
    share: float = 0.5,
    idle_fraction: float = 0.02,
    min_points: int = 5,
    n_sigma: float = 6.0,
) -> LossStiffness:
    """The other motor's stiffness k = share · ΔF_load / Δδ, Eq. (3.26), before and during
    the master's preload loss, from a coupled loading test (Ch. 3.4.3, Fig. 3.12-b).

    The master's contact states come from δ_m(F) as in `preload_loss_force`: samples on
    its first line (both carry, taken above 20 % of that line's load range to leave out
    the take-up) and samples on neither line while the master's own force is below
    `idle_fraction` of its peak (its pinion crosses the backlash and carries nothing; the
    re-contact transient, where it carries again, is left out). Line fits of F against the
    other motor's δ = x_other − x_load on each set.
    """
    load, master, other, scale, own = _loading_branch(force, x_master, x_other, x_load,
                                                      force_master)
    order, f, _, first, _, crossing = _master_contact_lines(load, master - scale, min_points,
                                                            n_sigma)
    delta, own = (other - scale)[order], np.abs(own[order])
    both = first & (f >= 0.2 * f[first].max())
    lost = crossing & (own < idle_fraction * own.max())
    if np.count_nonzero(both) < 3 or np.count_nonzero(lost) < 3:
        raise ValueError("fewer than 3 samples with both motors in contact or with the "
                         "master out of contact")
    return LossStiffness(contact=share * scipy.stats.linregress(delta[both], f[both]).slope,
                         lost=share * scipy.stats.linregress(delta[lost], f[lost]).slope,
                         n_lost=int(np.count_nonzero(lost)))


def torque_sharing(tau_master: np.ndarray, tau_slave: np.ndarray) -> TorqueSharing:
    """Share of the net torque carried by the master and the preload torque, Eq. (3.1).

    τ_m = τ_ref/2 + τ_p with τ_ref = τ_m + τ_s: a line of τ_m against the net torque.
    """
    tau_master = np.asarray(tau_master, dtype=float).ravel()
    net = tau_master + np.asarray(tau_slave, dtype=float).ravel()
    line = scipy.stats.linregress(net, tau_master)
    return TorqueSharing(share=line.slope, preload=line.intercept, r_squared=line.rvalue**2)


def mesh_stiffness(c_prime: float, contact_ratio: float, width: float) -> float:
    """Pinion–rack mesh stiffness K = b c_γα = b c' (0.75 ε_α + 0.25), Eq. (3.27) (N/m).

    c_prime: single-tooth-pair stiffness c' of Eq. (3.28) per unit face width (N/m²;
    1 (N/mm)/µm = 1e9 N/m²); width: face width b (m).
    """
    return width * c_prime * (0.75 * contact_ratio + 0.25)


def mesh_stiffness_bounds(c_prime: float, width: float) -> tuple[float, float]:
    """Mesh stiffness with one and with two tooth pairs in mesh (ε_α = 1, 2), Ch. 3.4.3 (N/m)."""
    return mesh_stiffness(c_prime, 1.0, width), mesh_stiffness(c_prime, 2.0, width)


def series_stiffness(*stiffnesses: float) -> float:
    """Equivalent stiffness of elements in series, 1/k = Σ 1/k_i, Eq. (3.4) (N/m)."""
    return 1.0 / sum(1.0 / k for k in stiffnesses)
