"""Forward replay: the model in closed loop with the recording's own inputs.

The model's mass, friction, structure and effects become an `AxisSimulator` (the same
compiled kernel and cascade, Eq. (5.4), as the simulated bench), driven by the recorded
reference (CSP) and excitation (force offset); the replayed position and force reading are
compared with the measured ones. A rigid body is replayed as two halves on a coupling whose
mode lies far above the loop rate, critically damped: the exact zero-order-hold
discretisation of the axis integrates it without error. Backlash is not replayed (its load
on a contact spring would be a third body beside the kernel's motor and tip), nor a cubic
stiffening (the kernel's coupling is linear); the report says so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from feedbench.analysis.closure.effects import EFFECTS
from feedbench.analysis.closure.model import Model
from feedbench.analysis.closure.spec import ControllerSpec
from feedbench.analysis.closure.trace import Trace, edge_samples, lowpass, nrmse
from feedbench.analysis.frf import estimate_frf
from feedbench.models.axis import CSP, AxisSimulator, CascadeGains, ServoTiming, TwoMassAxis
from feedbench.models.effects import AxisEffects
from feedbench.models.friction import AnderssonFriction, DirectionalFriction

RIGID_MODE_FACTOR = 20.0
"""The rigid body's internal mode sits this many times above the velocity-loop rate."""

COHERENCE_MIN = 0.8
"""FRF bins with a lower measured coherence are left out of the FRF errors."""

NOT_REPLAYED = ("backlash", "second_mode", "cubic_stiffening", "presliding", "gms")


@dataclass(frozen=True)
class Replay:
    """Replayed channels (every sample of the trace) and what was left out. The force is
    the cycle-mean force, as a drive reports it."""

    position: np.ndarray
    force: np.ndarray
    velocity: np.ndarray
    left_out: tuple[str, ...]


@dataclass(frozen=True)
class ReplayErrors:
    """NRMSE per channel over the judged samples; FRF errors over the excited band.

    force: band-limited force reading; position: motor position; tracking: reference −
    position; frf_magnitude_db / frf_phase_deg: RMS difference of the mobility
    velocity/excitation, model vs measured, where the measured coherence ≥ COHERENCE_MIN
    (NaN without excitation); left_out: model terms the replay could not carry.
    """

    force: float
    position: float
    tracking: float
    frf_magnitude_db: float
    frf_phase_deg: float
    frf_band_hz: tuple[float, float]
    left_out: tuple[str, ...]


def _values(model: Model, name: str) -> dict[str, float]:
    return dict(model.term(name).values) if name in model.names else {}


def replay_friction(model: Model) -> DirectionalFriction:
    """The model's friction terms as the Andersson law per direction (Eq. 5.2); negative
    levels, which a fit may return for an absent effect, are replayed as 0."""
    coulomb, stribeck = _values(model, "coulomb"), _values(model, "stribeck")
    viscous = _values(model, "viscous").get("F_v_Ns_m", 0.0)
    asymmetry = _values(model, "direction_dependent").get("dF_v_Ns_m", 0.0)
    f_c = max(coulomb.get("F_c_N", 0.0), 0.0)
    k_tanh = coulomb.get("k_tanh_min_mm", EFFECTS["coulomb"].defaults()["k_tanh_min_mm"])

    def side(sigma: float) -> AnderssonFriction:
        return AnderssonFriction(F_c=f_c, F_s=f_c + max(stribeck.get("dF_s_N", 0.0), 0.0),
                                 v_s=stribeck.get("v_s_mm_min", math.inf), sigma=max(sigma, 0.0),
                                 k_tanh=k_tanh, delta=stribeck.get("delta", 1.0))

    return DirectionalFriction(side(viscous), side(viscous + asymmetry))


def replay_axis(model: Model, controller: ControllerSpec) -> TwoMassAxis:
    """Motor and tip masses of the model: the structural mode's, or a rigid pair."""
    total = model.total_mass
    if "structural_mode" in model.names:
        mode = model.term("structural_mode").values
        m, omega = mode["m_kg"], 2.0 * math.pi * mode["f_n_Hz"]
        if 0.0 < m < total:
            return TwoMassAxis(m_mot=total - m, m_tip=m, k=m * omega**2,
                               c=2.0 * mode["zeta"] * omega * m, friction=replay_friction(model))
    half = 0.5 * total
    omega = 2.0 * math.pi * RIGID_MODE_FACTOR * controller.f_velocity
    reduced = 0.5 * half
    return TwoMassAxis(m_mot=half, m_tip=half, k=reduced * omega**2, c=2.0 * reduced * omega,
                       friction=replay_friction(model))


def replay_effects(model: Model) -> AxisEffects:
    """Ripple and force-level nonlinearity of the model for the kernel. The ripple term is
    the force the drive must add; the world's ripple acting on the carriage is its opposite."""
    ripple = _values(model, "ripple")
    sine, cosine = -ripple.get("A_sin_N", 0.0), -ripple.get("A_cos_N", 0.0)
    return AxisEffects(
        ripple_amplitude=math.hypot(sine, cosine),
        ripple_pitch=ripple.get("pitch_mm", 1.0),
        ripple_phase=math.atan2(cosine, sine),
        force_level=max(_values(model, "amplitude_nonlinearity").get("beta_per_kN", 0.0), 0.0),
    )


def replay(trace: Trace, model: Model, controller: ControllerSpec) -> Replay:
    """Simulate `model` under `controller` with the trace's reference and excitation; the
    model's offset and the trace's known external force act on the load."""
    if trace.reference is None:
        raise ValueError(f"{trace.name or 'trace'}: no reference channel to replay")
    dt = 1.0 / trace.sample_rate
    simulator = AxisSimulator(
        replay_axis(model, controller),
        CascadeGains(K_p=controller.K_p, T_i=controller.T_i, K_v=controller.K_v),
        ServoTiming(f_velocity=controller.f_velocity, f_position=controller.f_position,
                    delay=controller.delay, cycle=dt),
        force_limit=controller.force_limit,
        velocity_feedforward=controller.velocity_feedforward,
        effects=replay_effects(model),
    )
    simulator.reset(position=float(trace.position[0]))
    excitation = 0.0 if trace.excitation is None else trace.excitation
    load = _values(model, "offset").get("offset_N", 0.0) + (
        0.0 if trace.external_force is None else trace.external_force)
    out = simulator.simulate(CSP, trace.reference, 0.0, 0.0, force_offset=excitation,
                             tip_force=-load)
    return Replay(out["position"], _reading(model, out["mean_force"], dt), out["velocity"],
                  tuple(n for n in NOT_REPLAYED if n in model.names))


def _reading(model: Model, force: np.ndarray, dt: float) -> np.ndarray:
    """The force channel of the replay: advanced by the model's delay, scaled by its gain."""
    lead = _values(model, "delay").get("tau_ms", 0.0)
    index = np.arange(force.size, dtype=float)
    reading = np.interp(index + lead / dt, index, force) if lead else force
    return reading * _values(model, "sensor_gain").get("gain", 1.0)


def replay_errors(trace: Trace, result: Replay, bandwidth: float, start: int = 0,
                  stop: int | None = None) -> ReplayErrors:
    """Errors of a replay against the trace over samples [start, stop) (edges dropped)."""
    dt = 1.0 / trace.sample_rate
    edge = edge_samples(bandwidth, dt)
    window = slice(max(start, edge), (trace.n_samples if stop is None else stop) - edge)
    measured = lowpass(trace.force, bandwidth, dt, lead=trace.force_lag)[window]
    replayed = lowpass(result.force, bandwidth, dt, lead=trace.force_lag)[window]
    tracking = (trace.reference - trace.position)[window]
    tracking_model = (trace.reference - result.position)[window]
    magnitude, phase, band = _frf_errors(trace, result, bandwidth, window)
    return ReplayErrors(nrmse(measured, replayed),
                        nrmse(trace.position[window], result.position[window]),
                        nrmse(tracking, tracking_model), magnitude, phase, band,
                        result.left_out)


def _frf_errors(trace: Trace, result: Replay, bandwidth: float,
                window: slice) -> tuple[float, float, tuple[float, float]]:
    """RMS magnitude (dB) and phase (deg) difference of the mobility velocity/excitation,
    over bins up to the bandwidth where the measured coherence is high."""
    nan = (math.nan, math.nan, (math.nan, math.nan))
    if trace.excitation is None or not np.any(trace.excitation[window]):
        return nan
    dt = 1.0 / trace.sample_rate
    excitation = trace.excitation[window]
    velocities = np.vstack([lowpass(trace.position, bandwidth, dt, 1)[window],
                            lowpass(result.position, bandwidth, dt, 1)[window]])
    nperseg = int(min(excitation.size // 4, 2 ** round(math.log2(2.0 / dt))))
    if nperseg < 64:
        return nan
    frf = estimate_frf(excitation, velocities, 1.0 / dt, nperseg)
    keep = (frf.coherence[0] >= COHERENCE_MIN) & (frf.f > 0.0) & (frf.f <= bandwidth)
    if not keep.any():
        return nan
    ratio = frf.H1[1, keep] / frf.H1[0, keep]
    magnitude = float(np.sqrt(np.mean((20.0 * np.log10(np.abs(ratio))) ** 2)))
    phase = float(np.sqrt(np.mean(np.degrees(np.angle(ratio)) ** 2)))
    return magnitude, phase, (float(frf.f[keep].min()), float(frf.f[keep].max()))
