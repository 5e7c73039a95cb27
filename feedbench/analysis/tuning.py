"""P-PI cascade tunings and what each would do (thesis Ch. 4.2–4.6).

The laws live in `feedbench.models.axis` (`CascadeGains.standard`: Eqs. 4.2, 4.8, 4.12;
`TwoMassAxis.f_t` / `f_r`: Eqs. 4.13, 4.14); this module applies them to the tunings the
thesis compares and reports gains in the units the CNC shows.

Candidate gain sets for `feedbench tune` (issue 15): the standard tuning at a bandwidth,
the maximum-damping tuning of the critical structural mode (root locus, Ch. 4.3.3) and any
the user lists (`candidate_gains`); for each, `predict_candidate` gives the critical mode
(f_n, ζ), the tool-tip compliance by LFT (approach #1, Eq. 4.25; approach #2, Eqs. 4.26,
4.23) with its peak and the minimum stable depth of its ZOA lobes, and the contour and
tracking errors of the test contours (`contour`, Table 4.3); `recommend` picks roughing
(stability) and finishing (accuracy). Everything is pure: arrays and dataclasses in, frozen
dataclasses out, each row JSON-able through `dataclasses.asdict`.
"""

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from feedbench.analysis import lft, rootlocus, stability
from feedbench.analysis.contour import (
    ContourRun, ContourSpec, Feedforward, MotionErrors, contour_paths, follow,
)
from feedbench.analysis.servo import ComplexArray
from feedbench.models.axis import CascadeGains, TwoMassAxis
from feedbench.units import kv_to_m_min_per_mm

OPTIMUM_FRACTION_OF_F_T = 0.8
"""Optimum-damping bandwidth as a fraction of the motor-locked frequency f_t (Ch. 4.2.3)."""


def standard_gains(M_total: float, f_bw: float) -> CascadeGains:
    """K_p = 2π M f_bw, T_i = 1/(π f_bw), K_v = π f_bw/2, Eqs. (4.2, 4.8, 4.12); kg, Hz → SI."""
    return CascadeGains.standard(M_total, f_bw)


def total_mass(axis: TwoMassAxis) -> float:
    """M_total = M_mot + M_tip (kg), the mass the velocity loop accelerates as a rigid body."""
    return axis.m_mot + axis.m_tip


def optimum_bandwidth(axis: TwoMassAxis) -> float:
    """Velocity bandwidth (Hz) for optimum structural damping: 80 % of f_t, Eq. (4.13)."""
    return OPTIMUM_FRACTION_OF_F_T * axis.f_t


def bandwidth_tunings(
    axis: TwoMassAxis, low: float = 15.0, high: float = 87.0
) -> dict[str, CascadeGains]:
    """The three tunings of Ch. 4.2.3: "low", "high" (bandwidths in Hz) and "optimum" (0.8 f_t)."""
    mass = total_mass(axis)
    bandwidths = {"low": low, "high": high, "optimum": optimum_bandwidth(axis)}
    return {name: standard_gains(mass, f_bw) for name, f_bw in bandwidths.items()}


@dataclass(frozen=True)
class EngineeringGains:
    """Gains as a CNC shows them: K_p in N·s/m, T_i in ms, K_v in (m/min)/mm."""

    K_p: float
    T_i_ms: float
    K_v_m_min_per_mm: float


def engineering_gains(gains: CascadeGains) -> EngineeringGains:
    """SI gains → CNC units (1 (m/min)/mm = 16.67 1/s)."""
    return EngineeringGains(
        K_p=gains.K_p, T_i_ms=gains.T_i * 1e3, K_v_m_min_per_mm=kv_to_m_min_per_mm(gains.K_v)
    )


def bandwidth_bounds(M_total: float, low_hz: float, high_hz: float) -> rootlocus.GainBounds:
    """Search box spanned by the standard tunings at two bandwidths (Hz) on M_total (kg):
    K_p and K_v from the low to the high tuning, T_i from the high to the low one."""
    low, high = standard_gains(M_total, low_hz), standard_gains(M_total, high_hz)
    return rootlocus.GainBounds(K_p=(low.K_p, high.K_p), T_i=(high.T_i, low.T_i),
                                K_v=(low.K_v, high.K_v))


@dataclass(frozen=True)
class TipMeasurements:
    """Measured FRFs on one frequency grid for the LFT predictions (compliances in m/N).

    frequency (Hz); mot_mot: open-loop x_mot/F_mot (the mobility over jω,
    `servo.mobility_to_compliance`). Approach #1 (Eq. 4.25): tip_closed_k0 = x_tip/F_tip and
    mot_tip_k0 = x_mot/F_tip under a very low controller, transmissibility = x_tip/x_mot
    under motor excitation. Approach #2 (Eq. 4.26): tip_closed = x_tip/F_tip under each of
    ≥ 2 measured gain sets `measured_gains`. Leave an approach's fields empty to skip it.
    """

    frequency: NDArray[np.float64]
    mot_mot: ComplexArray
    tip_closed_k0: ComplexArray | None = None
    mot_tip_k0: ComplexArray | None = None
    transmissibility: ComplexArray | None = None
    tip_closed: tuple[ComplexArray, ...] = ()
    measured_gains: tuple[CascadeGains, ...] = ()

    def __post_init__(self) -> None:
        approach_1 = (self.tip_closed_k0, self.mot_tip_k0, self.transmissibility)
        if any(x is None for x in approach_1) and not all(x is None for x in approach_1):
            raise ValueError("approach #1 needs tip_closed_k0, mot_tip_k0 and transmissibility")
        if len(self.tip_closed) != len(self.measured_gains) or len(self.tip_closed) == 1:
            raise ValueError("approach #2 needs one gain set per tip compliance, at least two")


@dataclass(frozen=True)
class CuttingParameters:
    """Milling for the ZOA lobes (`stability.zoa_lobes`): spindle speeds (rpm, increasing),
    teeth, K_t = K_tc (N/m²), K_r = K_rc/K_tc (–), engagement φ_st, φ_ex (rad).

    y_compliance: x_tip/F_tip of the y direction (m/N, on `TipMeasurements.frequency`);
    None: the y axis has the matching dynamics of the x axis (as in the contour simulation),
    so the predicted compliance is used for both."""

    spindle_rpm: NDArray[np.float64]
    n_teeth: int
    K_t: float
    K_r: float
    phi_st: float
    phi_ex: float
    y_compliance: ComplexArray | None = None
    n_lobes: int = 20


@dataclass(frozen=True)
class TuningSetup:
    """What every candidate is judged by: the band (Hz) of the critical structural mode (wide
    enough to hold its closed-loop root at every gain: it wanders below f_t as the
    controller's poles meet it; 0.5 f_t to 2 f_r on the lab bench), the test contour and
    its feed-forward settings, the position-loop delay (s) with its Padé order (root locus,
    contour, LFT controller), the tool-tip measurements and the cutting parameters (None:
    no compliance prediction / no lobes)."""

    band: tuple[float, float]
    contour: ContourSpec = field(default_factory=ContourSpec)
    feedforward: Feedforward = field(default_factory=Feedforward)
    position_delay: float = 0.0
    pade_order: int = 2
    tip: TipMeasurements | None = None
    cutting: CuttingParameters | None = None


def max_damping_gains(mobility: signal.TransferFunction, setup: TuningSetup,
                      bounds: rootlocus.GainBounds, seed: int = 0) -> CascadeGains:
    """Gains within `bounds` maximising the critical mode's damping in `setup.band`
    (`rootlocus.maximise_critical_damping`, Ch. 4.3.3; deterministic for a seed).

    A band some gains empty of roots would make "no root in band" the optimum: refused,
    first on a 6 × 6 × 6 log grid of the box (one batched call), then at the optimum."""
    grid = np.meshgrid(*(np.geomspace(*bound, 6) for bound in (bounds.K_p, bounds.T_i,
                                                               bounds.K_v)))
    if np.all(np.isfinite(rootlocus.critical_damping_of_gains(
            mobility, *(g.ravel() for g in grid), setup.band, setup.position_delay,
            setup.pade_order))):
        optimum = rootlocus.maximise_critical_damping(mobility, setup.band, bounds,
                                                      setup.position_delay, setup.pade_order, seed)
        if np.isfinite(optimum.damping):
            return optimum.gains
    raise ValueError(f"band {setup.band} Hz: some gains leave no closed-loop root in it; widen "
                     "it to hold the structural mode at every gain (e.g. 0.5 f_t to 2 f_r)")


def candidate_gains(mobility: signal.TransferFunction, setup: TuningSetup, M_total: float,
                    f_bw: float, bounds: rootlocus.GainBounds,
                    listed: Mapping[str, CascadeGains] | None = None,
                    seed: int = 0) -> dict[str, CascadeGains]:
    """The candidates by name: "standard" (Eqs. 4.2, 4.8, 4.12 at f_bw Hz on M_total kg),
    "max_damping" (`max_damping_gains`) and the user's `listed` gain sets."""
    clash = sorted({"standard", "max_damping"} & set(listed or {}))
    if clash:
        raise ValueError(f"listed gain set {clash[0]!r}: the name of a computed candidate")
    return {"standard": standard_gains(M_total, f_bw),
            "max_damping": max_damping_gains(mobility, setup, bounds, seed), **(listed or {})}


@dataclass(frozen=True)
class CriticalMode:
    """The least-damped closed-loop root in the band: natural frequency f_n (Hz), damping
    ratio ζ (–; both NaN when no root lies in the band), and whether every root of the
    cascade is in the left half-plane."""

    frequency_hz: float
    damping: float
    stable: bool


def critical_mode(mobility: signal.TransferFunction, gains: CascadeGains,
                  setup: TuningSetup) -> CriticalMode:
    """Critical structural mode of the closed cascade (roots of 1 − H_x,F K, Eq. 4.24)."""
    roots = rootlocus.polynomial_roots(rootlocus.cascade_characteristic(
        mobility, gains.K_p, gains.T_i, gains.K_v, setup.position_delay, setup.pade_order))
    root = complex(rootlocus.critical_root(roots, setup.band))
    damping = float(rootlocus.damping_ratios(root)) if np.isfinite(root) else float("nan")
    return CriticalMode(frequency_hz=abs(root) / (2 * np.pi), damping=damping,
                        stable=bool(np.all(roots.real < 0)))


def predict_tip(tip: TipMeasurements, gains: CascadeGains,
                position_delay: float = 0.0) -> dict[str, ComplexArray]:
    """x_tip/F_tip (m/N) under `gains` by each approach the measurements allow:
    "transmissibility" (#1, Eq. 4.25) and "settings" (#2, Eqs. 4.26 then 4.23)."""
    def controller(g: CascadeGains) -> ComplexArray:
        return lft.pppi_feedback(tip.frequency, g, position_delay)

    predicted = {}
    if tip.tip_closed_k0 is not None:
        predicted["transmissibility"] = lft.predict_tip_by_transmissibility(
            tip.tip_closed_k0, tip.mot_tip_k0, tip.mot_mot, tip.transmissibility,
            controller(gains))
    if len(tip.tip_closed) >= 2:
        terms = lft.estimate_tip_terms(np.stack(tip.tip_closed),
                                       np.stack([controller(g) for g in tip.measured_gains]),
                                       tip.mot_mot)
        predicted["settings"] = lft.predict_tip_compliance(terms, tip.mot_mot, controller(gains))
    return predicted


def min_stable_depth(frequency: NDArray[np.float64], compliance: ComplexArray,
                     cutting: CuttingParameters) -> float:
    """Smallest critical axial depth (m) of the ZOA lobes over the spindle speeds, with
    Φ = diag(x compliance, y compliance) (`stability.zoa_lobes`)."""
    phi = np.zeros((len(frequency), 2, 2), dtype=complex)
    phi[:, 0, 0] = compliance
    phi[:, 1, 1] = compliance if cutting.y_compliance is None else cutting.y_compliance
    lobes = stability.zoa_lobes(frequency, phi, cutting.spindle_rpm, cutting.n_teeth,
                                cutting.K_t, cutting.K_r, cutting.phi_st, cutting.phi_ex,
                                cutting.n_lobes)
    return lobes.min_depth


@dataclass(frozen=True)
class TipPrediction:
    """Predicted tool-tip compliance: peak |x_tip/F_tip| (µm/N) and its frequency (Hz);
    minimum stable depth of its lobes (mm; None without cutting parameters, inf when no
    lobe reaches the speeds)."""

    peak_um_per_N: float
    peak_frequency_hz: float
    min_stable_depth_mm: float | None


def tip_prediction(frequency: NDArray[np.float64], compliance: ComplexArray,
                   cutting: CuttingParameters | None) -> TipPrediction:
    """Peak of a compliance (m/N → µm/N) and, given cutting parameters, its lobes' limit."""
    peak = int(np.argmax(np.abs(compliance)))
    depth = None if cutting is None else min_stable_depth(frequency, compliance, cutting) * 1e3
    return TipPrediction(peak_um_per_N=float(np.abs(compliance[peak]) * 1e6),
                         peak_frequency_hz=float(frequency[peak]), min_stable_depth_mm=depth)


@dataclass(frozen=True)
class CandidatePrediction:
    """One candidate row: name, gains (SI), critical mode, tool-tip predictions by approach
    ("transmissibility", "settings") and motion errors by contour ("circle", "corner")."""

    name: str
    gains: CascadeGains
    critical: CriticalMode
    tip: dict[str, TipPrediction]
    motion: dict[str, MotionErrors]


def contour_runs(mobility: signal.TransferFunction, gains: CascadeGains,
                 setup: TuningSetup) -> dict[str, ContourRun]:
    """The test contours of `setup` under `gains` by name ("circle", "corner"): reference,
    actual path and errors per sample (`contour.follow`), e.g. for plots."""
    return {contour: follow(mobility, gains, path, setup.feedforward, setup.position_delay,
                            setup.pade_order)
            for contour, path in contour_paths(setup.contour).items()}


def predict_candidate(name: str, gains: CascadeGains, mobility: signal.TransferFunction,
                      setup: TuningSetup) -> CandidatePrediction:
    """Everything `setup` asks about one gain set (mobility: rational ẋ_mot/F_mot, m/(N·s))."""
    tip = {}
    if setup.tip is not None:
        tip = {approach: tip_prediction(setup.tip.frequency, compliance, setup.cutting)
               for approach, compliance in predict_tip(setup.tip, gains,
                                                       setup.position_delay).items()}
    motion = {contour: run.errors for contour, run in contour_runs(mobility, gains, setup).items()}
    return CandidatePrediction(name=name, gains=gains,
                               critical=critical_mode(mobility, gains, setup),
                               tip=tip, motion=motion)


def predict_candidates(candidates: Mapping[str, CascadeGains], mobility: signal.TransferFunction,
                       setup: TuningSetup) -> list[CandidatePrediction]:
    """`predict_candidate` for each named gain set, in the mapping's order."""
    return [predict_candidate(name, gains, mobility, setup) for name, gains in candidates.items()]


PREFERRED_APPROACH = ("settings", "transmissibility")
"""Tool-tip prediction whose lobes decide roughing: approach #2 where measured (more
accurate, Fig. 4.11), else #1."""


@dataclass(frozen=True)
class Recommendation:
    """Candidate names for roughing (stability) and finishing (accuracy), and what decided
    each ("min stable depth (settings)", "critical damping", "contour error")."""

    roughing: str
    roughing_by: str
    finishing: str
    finishing_by: str


def _depth(row: CandidatePrediction, approach: str) -> float:
    """A row's minimum stable depth (mm) by `approach`; −inf where it has none."""
    prediction = row.tip.get(approach)
    return -np.inf if prediction is None or prediction.min_stable_depth_mm is None else (
        prediction.min_stable_depth_mm)


def recommend(rows: Sequence[CandidatePrediction]) -> Recommendation:
    """Roughing: the stable candidate with the highest minimum stable depth (by the preferred
    approach), or, without lobes, the highest critical-mode damping; finishing: the stable
    candidate with the lowest contour error (max over the contours)."""
    stable = [row for row in rows if row.critical.stable]
    if not stable:
        raise ValueError("no candidate leaves the closed loop stable")
    approach = next((a for a in PREFERRED_APPROACH
                     if any(np.isfinite(_depth(row, a)) for row in stable)), None)
    if approach is None:
        roughing, roughing_by = max(stable, key=lambda r: r.critical.damping), "critical damping"
    else:
        roughing = max(stable, key=lambda r: _depth(r, approach))
        roughing_by = f"min stable depth ({approach})"
    finishing = min(stable, key=lambda r: max(e.contour_max_um for e in r.motion.values()))
    return Recommendation(roughing=roughing.name, roughing_by=roughing_by,
                          finishing=finishing.name, finishing_by="contour error")
