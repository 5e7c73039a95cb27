"""Simulated recordings whose world carries effects no model config declares.

A world table (engineering units, like ``[bench.world]``) sets the axis, its drive, the
motion, the excitation, the sensor noise, and under ``effects`` any of the closure's
vocabulary at a realistic size. `simulate_recording` runs it through the compiled axis
kernel (`AxisSimulator.simulate`) and returns what a recorder would have written: the
channels of the bench's runner (x_ref, position, velocity, force, force_offset). The truth
stays here: analysis never reads a world table, it sees only the recording.

Where each effect lives in the world:
- coulomb, stribeck, direction_dependent, viscous: the guideway friction (Eq. 5.2);
- offset: a constant force on the tool tip (gravity, counterweight);
- ripple, amplitude_nonlinearity, backlash: `AxisEffects` in the kernel;
- structural_mode: the stiff coupling replaced by a flexure (k, c);
- inertia_mismatch: extra mass on the tip (a workpiece the model does not know);
- delay: the force channel records the command τ before it acts;
- sensor_gain, sensor_offset: the force reading is scaled / shifted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from feedbench.config import ConfigError, Field, interval, non_negative, positive, validate_table
from feedbench.models.axis import CSP, AxisSimulator, CascadeGains, ServoTiming, TwoMassAxis
from feedbench.models.effects import AxisEffects
from feedbench.models.friction import AnderssonFriction, DirectionalFriction
from feedbench.units import MIN_PER_MM, MM_PER_MIN, N_PER_UM

CYCLE_S = 1e-3
"""Bus cycle of the simulated recordings (s): the sample period."""

WORLD_SCHEMA = {
    "m_mot_kg": Field(float, 23.1, "motor (carriage) mass (kg)", positive),
    "m_tip_kg": Field(float, 11.3, "mass behind the coupling (kg)", positive),
    "coupling_k_N_um": Field(float, 1000.0, "stiffness of the motor–tip coupling (N/µm)",
                             positive),
    "coupling_zeta": Field(float, 0.3, "damping ratio of the coupling", positive),
    "viscous_Ns_m": Field(float, 168.0, "viscous friction σ (N·s/m)", non_negative),
    "k_tanh_min_mm": Field(float, 0.25, "tanh constant of Eq. (5.2) (min/mm)", positive),
    "delay_ms": Field(float, 0.75, "drive force delay τ_ol (ms), whole velocity-loop periods",
                      non_negative),
    "f_velocity_Hz": Field(float, 8000.0, "velocity-loop rate (Hz), a multiple of 1 kHz",
                           positive),
    "bandwidth_Hz": Field(float, 40.0, "drive tuning, Eqs. (4.2, 4.8, 4.12) (Hz)", positive),
    "force_limit_N": Field(float, 2000.0, "drive force saturation (N)", positive),
    "duration_s": Field(float, 30.0, "length of the recording (s)", positive),
    "stroke_mm": Field(float, 100.0, "travel of the back-and-forth moves (mm)", positive),
    "feeds_mm_min": Field(list, [3000.0, 6000.0, 12000.0], "feeds of successive moves (mm/min)",
                          positive),
    "acceleration_m_s2": Field(float, 2.0, "acceleration of the moves (m/s²)", positive),
    "dwell_s": Field(float, 0.2, "standstill between moves (s)", non_negative),
    "excitation_N": Field(float, 15.0, "RMS of the random force excitation (N)", non_negative),
    "excitation_band_Hz": Field(list, [5.0, 150.0], "band of the excitation (Hz)", interval),
    "force_noise_N": Field(float, 1.0, "RMS of the force-reading noise (N)", non_negative),
    "position_resolution_nm": Field(float, 1.0, "encoder resolution (nm)", positive),
    "seed": Field(int, 1, "random seed of excitation and noise"),
    "effects": Field(dict, {}, "effects the world carries (see EFFECT_SCHEMAS)"),
}

EFFECT_SCHEMAS = {
    "coulomb": {"F_c_N": Field(float, 40.0, "Coulomb level (N)", non_negative)},
    "stribeck": {"dF_s_N": Field(float, 40.0, "static excess F_s − F_c (N)", non_negative),
                 "v_s_mm_min": Field(float, 400.0, "Stribeck velocity (mm/min)", positive)},
    "direction_dependent": {
        "dF_v_Ns_m": Field(float, 70.0, "σ(v<0) − σ(v>0) (N·s/m)"),
        "dF_c_N": Field(float, 0.0, "F_c(v<0) − F_c(v>0) (N)")},
    "offset": {"offset_N": Field(float, 15.0, "constant force the drive must hold (N)")},
    "ripple": {"amplitude_N": Field(float, 8.0, "ripple amplitude (N)", positive),
               "pitch_mm": Field(float, 10.0, "period in position (mm)", positive),
               "phase_deg": Field(float, 30.0, "phase (deg)")},
    "structural_mode": {"k_N_um": Field(float, 1.68, "flexure stiffness (N/µm)", positive),
                        "c_Ns_m": Field(float, 104.0, "flexure damping (N·s/m)", non_negative)},
    "delay": {"tau_ms": Field(float, 1.0, "lead of the recorded force command (ms)",
                              non_negative)},
    "amplitude_nonlinearity": {"beta_per_kN": Field(float, 1.5, "β of F (1 + β|F|) (1/kN)",
                                                    non_negative)},
    "inertia_mismatch": {"dM_kg": Field(float, 7.0, "mass the model does not know (kg)")},
    "sensor_gain": {"gain": Field(float, 1.1, "force-reading gain", positive)},
    "sensor_offset": {"offset_N": Field(float, 10.0, "force-reading offset (N)")},
    "backlash": {"width_um": Field(float, 40.0, "total play of the coupling (µm)", positive),
                 "load_friction_N": Field(float, 20.0, "Coulomb friction of the load behind "
                                          "the play (N)", non_negative)},
}


@dataclass(frozen=True)
class SimulatedRecording:
    """What a recorder would hold: per-cycle channels (SI, runner names) and the cycle (s).

    force_lag_s: the force sample of a cycle is the drive's force averaged over that cycle
    (`AxisSimulator` mean force, as a drive reports it), centred half a cycle before the
    position sample; truth: the world table it came from, for reports only.
    """

    channels: dict[str, np.ndarray]
    cycle_s: float
    force_lag_s: float
    truth: dict[str, Any]


def parse_world(table: Mapping[str, Any], path: str = "world") -> dict[str, Any]:
    """Validate a world table and its effects; returns it with defaults filled in."""
    world = validate_table(table, WORLD_SCHEMA, path)
    effects = {}
    for name, params in world["effects"].items():
        if name not in EFFECT_SCHEMAS:
            raise ConfigError(f"{path}.effects.{name}: unknown effect "
                              f"(known: {', '.join(EFFECT_SCHEMAS)})")
        if not isinstance(params, dict):
            raise ConfigError(f"{path}.effects.{name}: must be a table of parameters")
        effects[name] = validate_table(params, EFFECT_SCHEMAS[name], f"{path}.effects.{name}")
    if "stribeck" in effects and "coulomb" not in effects:
        raise ConfigError(f"{path}.effects.stribeck: needs effects.coulomb "
                          "(F_s − F_c on top of F_c)")
    return {**world, "effects": effects}


def simulate_recording(table: Mapping[str, Any]) -> SimulatedRecording:
    """Run the world of `table` and record it (raises ConfigError on a bad table)."""
    world = parse_world(table)
    rng = np.random.default_rng(world["seed"])
    x_ref = reference_moves(world)
    excitation = band_limited_noise(x_ref.size, world["excitation_band_Hz"],
                                    world["excitation_N"], rng)
    offset = world["effects"].get("offset", {}).get("offset_N", 0.0)
    simulator = build_simulator(world)
    simulator.reset(position=float(x_ref[0]))
    out = simulator.simulate(CSP, x_ref, 0.0, 0.0, force_offset=excitation, tip_force=-offset)
    channels = {
        "time": out["time"],
        "x_ref": x_ref,
        "position": quantised(out["position"], world["position_resolution_nm"] * 1e-9),
        "velocity": out["velocity"],
        "force": force_reading(world, out["time"], out["mean_force"], rng),
        "force_offset": excitation,
    }
    return SimulatedRecording(channels, CYCLE_S, 0.5 * CYCLE_S, world)


def build_simulator(world: Mapping[str, Any]) -> AxisSimulator:
    """The axis, drive and kernel effects of a parsed world."""
    effects = world["effects"]
    extra_mass = effects.get("inertia_mismatch", {}).get("dM_kg", 0.0)
    m_mot, m_tip = world["m_mot_kg"], world["m_tip_kg"] + extra_mass
    k, c = _coupling(world, m_mot, m_tip)
    axis = TwoMassAxis(m_mot=m_mot, m_tip=m_tip, k=k, c=c, friction=world_friction(world))
    gains = CascadeGains.standard(world["m_mot_kg"] + world["m_tip_kg"], world["bandwidth_Hz"])
    timing = ServoTiming(f_velocity=world["f_velocity_Hz"], delay=world["delay_ms"] * 1e-3,
                         cycle=CYCLE_S)
    ripple = effects.get("ripple", {})
    axis_effects = AxisEffects(
        ripple_amplitude=ripple.get("amplitude_N", 0.0),
        ripple_pitch=ripple.get("pitch_mm", 1e3) * 1e-3,
        ripple_phase=math.radians(ripple.get("phase_deg", 0.0)),
        force_level=effects.get("amplitude_nonlinearity", {}).get("beta_per_kN", 0.0) * 1e-3,
        backlash=effects.get("backlash", {}).get("width_um", 0.0) * 1e-6,
        load_coulomb=effects.get("backlash", {}).get("load_friction_N", 0.0),
    )
    return AxisSimulator(axis, gains, timing, force_limit=world["force_limit_N"],
                         effects=axis_effects,
                         physics_substeps=_substeps(axis, timing, axis_effects))


def _substeps(axis: TwoMassAxis, timing: ServoTiming, effects: AxisEffects) -> int:
    """Physics substeps per velocity period: 1, or enough for the explicit backlash force to
    resolve the coupling's mode (ω h ≤ 0.25) and for the explicit load friction to stay
    stable (h ≤ m_tip / (F k_tanh))."""
    if effects.backlash == 0.0 and effects.load_coulomb == 0.0:
        return 1
    omega = math.sqrt(axis.k * (1.0 / axis.m_mot + 1.0 / axis.m_tip))
    step = min(0.25 / omega,
               axis.m_tip / max(effects.load_coulomb * effects.load_k_tanh, 1e-300))
    return max(1, math.ceil(timing.velocity_period / step))


def _coupling(world: Mapping[str, Any], m_mot: float, m_tip: float) -> tuple[float, float]:
    """(k, c) of the motor–tip coupling: the flexure of a structural mode, else stiff."""
    mode = world["effects"].get("structural_mode")
    if mode:
        return mode["k_N_um"] * N_PER_UM, mode["c_Ns_m"]
    k = world["coupling_k_N_um"] * N_PER_UM
    reduced_mass = m_mot * m_tip / (m_mot + m_tip)
    return k, 2.0 * world["coupling_zeta"] * math.sqrt(k * reduced_mass)


def world_friction(world: Mapping[str, Any]) -> DirectionalFriction:
    """Andersson friction per direction (Eq. 5.2) from the world's friction effects."""
    effects = world["effects"]
    f_c = effects.get("coulomb", {}).get("F_c_N", 0.0)
    stribeck = effects.get("stribeck", {"dF_s_N": 0.0, "v_s_mm_min": math.inf})
    asymmetry = effects.get("direction_dependent", {"dF_v_Ns_m": 0.0, "dF_c_N": 0.0})
    k_tanh = world["k_tanh_min_mm"] * MIN_PER_MM

    def side(f_c_side: float, sigma: float) -> AnderssonFriction:
        return AnderssonFriction(F_c=f_c_side, F_s=f_c_side + stribeck["dF_s_N"],
                                 v_s=stribeck["v_s_mm_min"] * MM_PER_MIN, sigma=sigma,
                                 k_tanh=k_tanh)

    sigma = world["viscous_Ns_m"]
    return DirectionalFriction(side(f_c, sigma),
                               side(f_c + asymmetry["dF_c_N"], sigma + asymmetry["dF_v_Ns_m"]))


def force_reading(world: Mapping[str, Any], time: np.ndarray, acting_command: np.ndarray,
                  rng: np.random.Generator) -> np.ndarray:
    """The force channel: the drive's force (delayed channel, gain, offset) plus noise (N)."""
    effects = world["effects"]
    lead = effects.get("delay", {}).get("tau_ms", 0.0) * 1e-3
    reading = np.interp(time + lead, time, acting_command) if lead else acting_command.copy()
    reading = reading * effects.get("sensor_gain", {}).get("gain", 1.0)
    reading = reading + effects.get("sensor_offset", {}).get("offset_N", 0.0)
    return reading + rng.normal(0.0, world["force_noise_N"], reading.size)


def quantised(position: np.ndarray, resolution: float) -> np.ndarray:
    """Encoder reading: the position rounded to the resolution (m)."""
    return np.round(position / resolution) * resolution


def band_limited_noise(n: int, band: list[float], rms: float,
                       rng: np.random.Generator) -> np.ndarray:
    """Gaussian noise band-passed to `band` (Hz) at the cycle rate, scaled to `rms` (N)."""
    if rms == 0.0:
        return np.zeros(n)
    import scipy.signal  # here: 0.6 s to import, only band-limited noise needs it

    high = min(band[1], 0.45 / CYCLE_S)
    sos = scipy.signal.butter(4, [band[0], high], btype="bandpass", fs=1.0 / CYCLE_S,
                              output="sos")
    noise = scipy.signal.sosfilt(sos, rng.normal(size=n))
    return noise * rms / noise.std()


def reference_moves(world: Mapping[str, Any]) -> np.ndarray:
    """Back-and-forth moves over the stroke at the listed feeds, each with a trapezoidal
    velocity profile (the world's acceleration) and a dwell, repeated to the duration (m)."""
    n = int(round(world["duration_s"] / CYCLE_S))
    half = 0.5 * world["stroke_mm"] * 1e-3
    velocity: list[np.ndarray] = []
    direction, feeds = 1.0, world["feeds_mm_min"]
    while sum(v.size for v in velocity) < n:
        for feed in feeds:
            velocity.append(direction * _trapezoid(2 * half, feed * MM_PER_MIN,
                                                   world["acceleration_m_s2"]))
            velocity.append(np.zeros(int(round(world["dwell_s"] / CYCLE_S))))
            direction = -direction
    profile = np.concatenate(velocity)[:n]
    return np.cumsum(profile) * CYCLE_S - half


def _trapezoid(distance: float, speed: float, acceleration: float) -> np.ndarray:
    """Per-cycle velocities (m/s) covering `distance` with a trapezoid (or triangle)."""
    speed = min(speed, math.sqrt(distance * acceleration))
    ramp = np.arange(1, int(math.ceil(speed / acceleration / CYCLE_S)) + 1) * acceleration * CYCLE_S
    ramp = np.minimum(ramp, speed)
    cruise = max(distance - 2 * ramp.sum() * CYCLE_S, 0.0)
    steady = np.full(int(cruise / speed / CYCLE_S), speed)
    profile = np.concatenate([ramp, steady, ramp[::-1]])
    return profile * distance / (profile.sum() * CYCLE_S)
