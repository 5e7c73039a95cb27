"""The simulated world's parameters: the truth behind the bus, read only by the simulator.

``[bench.world]`` in a bench config sets the physics of the simulated axis in engineering
units; defaults are the thesis's laboratory bench (Ch. 5.3.2, DIGEST §3). The host side
(drivers, experiments, analysis) never reads this table: it sees the world only through
the bus. The demo reads `world_truth` to print the identified values beside the truth.
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any, Mapping

from feedbench.config import ConfigError, Field, positive, non_negative, validate_table
from feedbench.models.axis import AxisSimulator, CascadeGains, ServoTiming, TwoMassAxis
from feedbench.sim_backends.cia402_drive import SensorNoise
from feedbench.models.friction import AnderssonFriction, DirectionalFriction
from feedbench.units import MM_PER_MIN, N_MIN_PER_MM, MIN_PER_MM, N_PER_UM

FRICTION_SCHEMA = {
    "F_c_N": Field(float, None, "Coulomb friction (N)", positive),
    "F_s_N": Field(float, None, "static friction (N)", positive),
    "v_s_mm_min": Field(float, None, "Stribeck velocity (mm/min)", positive),
    "sigma_N_min_mm": Field(float, None, "viscous coefficient (N·min/mm)", non_negative),
    "k_tanh_min_mm": Field(float, 0.25, "tanh constant (min/mm)", positive),
    "delta": Field(float, 1.0, "Stribeck shape exponent", positive),
}

LAB_FRICTION = {
    "positive": {"F_c_N": 44.2, "F_s_N": 84.0, "v_s_mm_min": 387.4, "sigma_N_min_mm": 0.0028},
    "negative": {"F_c_N": 38.7, "F_s_N": 88.0, "v_s_mm_min": 421.0, "sigma_N_min_mm": 0.0025},
}

WORLD_SCHEMA = {
    "m_mot_kg": Field(float, 23.1, "motor (carriage) mass (kg)", positive),
    "m_tip_kg": Field(float, 11.3, "flexure tip mass (kg)", positive),
    "k_N_um": Field(float, 1.68, "flexure stiffness (N/µm)", positive),
    "c_Ns_m": Field(float, 104.0, "flexure damping (N·s/m)", non_negative),
    "delay_ms": Field(float, 0.75, "drive force delay (ms)", non_negative),
    "force_limit_N": Field(float, 2000.0, "drive force saturation (N)", positive),
    "f_velocity_Hz": Field(float, 8000.0, "velocity-loop rate (Hz)", positive),
    "f_position_Hz": Field(float, 1000.0, "position-loop rate (Hz)", positive),
    "bandwidth_Hz": Field(float, 60.0, "drive's factory tuning bandwidth, Eqs. (4.2, 4.8, 4.12)",
                          positive),
    "force_noise_N": Field(float, 0.05, "noise (1 σ) on the drive's reported force (N)",
                           non_negative),
    "velocity_noise_mm_min": Field(float, 0.06, "noise (1 σ) on the drive's reported "
                                   "velocity (mm/min; 0.06 = 1 nm per 1 ms cycle)", non_negative),
    "noise_seed": Field(int, 0, "seed of the measurement noise", non_negative),
    "friction": Field(dict, {}, "Andersson friction per direction, Eq. (5.2)"),
    "milling": Field(dict, {}, "milling process and structure at the tool (SMFE, Ch. 6): "
                     "feedbench.sim_backends.smfe_world.MILLING_SCHEMA"),
    "structure": Field(dict, {}, "exciters and sensors at the tool tip (shaker, inertial "
                       "actuator, hammer): feedbench.sim_backends.structure_world"),
    "faults": Field(dict, {}, "fault injection: feedbench.sim_backends.faults.FAULT_SCHEMA"),
}


def _friction(table: Mapping[str, Any], direction: str) -> AnderssonFriction:
    merged = {**LAB_FRICTION[direction], **table.get(direction, {})}
    f = validate_table(merged, FRICTION_SCHEMA, f"bench.world.friction.{direction}")
    return AnderssonFriction(
        F_c=f["F_c_N"], F_s=f["F_s_N"], v_s=f["v_s_mm_min"] * MM_PER_MIN,
        sigma=f["sigma_N_min_mm"] * N_MIN_PER_MM, k_tanh=f["k_tanh_min_mm"] * MIN_PER_MM,
        delta=f["delta"],
    )


def build_axis(table: Mapping[str, Any], cycle_s: float) -> AxisSimulator:
    """The simulated axis from a ``[bench.world]`` table (engineering units)."""
    w = validate_table(table, WORLD_SCHEMA, "bench.world")
    unknown = sorted(set(w["friction"]) - {"positive", "negative"})
    if unknown:
        raise ConfigError(f"bench.world.friction.{unknown[0]}: unknown key "
                          "(known: negative, positive)")
    friction = DirectionalFriction(_friction(w["friction"], "positive"),
                                   _friction(w["friction"], "negative"))
    axis = TwoMassAxis(m_mot=w["m_mot_kg"], m_tip=w["m_tip_kg"], k=w["k_N_um"] * N_PER_UM,
                       c=w["c_Ns_m"], friction=friction)
    timing = servo_timing(w, cycle_s)
    gains = CascadeGains.standard(axis.m_mot + axis.m_tip, w["bandwidth_Hz"])
    return AxisSimulator(axis, gains, timing, force_limit=w["force_limit_N"])


def servo_timing(w: Mapping[str, Any], cycle_s: float) -> ServoTiming:
    """The servo loops of a validated world table (``f_velocity_Hz``, ``f_position_Hz``,
    ``delay_ms``) at a bus cycle of `cycle_s` s; a cycle that is no whole number of position-
    loop periods is a `ConfigError` naming ``bench.cycle_ms``, other misfits ``bench.world``."""
    if abs(w["f_position_Hz"] * cycle_s - round(w["f_position_Hz"] * cycle_s)) > 1e-9 or \
            round(w["f_position_Hz"] * cycle_s) < 1:
        raise ConfigError(f"bench.cycle_ms = {cycle_s * 1e3:g} is not a whole number of the "
                          f"simulated position loop's {1e3 / w['f_position_Hz']:g} ms periods "
                          "(bench.world.f_position_Hz)")
    try:
        return ServoTiming(w["f_velocity_Hz"], w["f_position_Hz"], w["delay_ms"] * 1e-3, cycle_s)
    except ValueError as exc:
        raise ConfigError(f"bench.world: {exc}") from None


def world_truth(table: Mapping[str, Any]) -> dict:
    """The true parameters in SI, for printing beside what was identified."""
    sim = build_axis(table, 1e-3)
    axis = sim.axis
    friction = {d: asdict(getattr(axis.friction, d)) for d in ("positive", "negative")}
    return {"m_mot": axis.m_mot, "m_tip": axis.m_tip, "k": axis.k, "c": axis.c,
            "f_t_hz": axis.f_t, "f_r_hz": axis.f_r, "friction": friction}


def build_sensor_noise(table: Mapping[str, Any]) -> SensorNoise:
    """The drive's measurement noise from a ``[bench.world]`` table."""
    w = validate_table(table, WORLD_SCHEMA, "bench.world")
    return SensorNoise(force=w["force_noise_N"], velocity=w["velocity_noise_mm_min"] * MM_PER_MIN,
                       seed=w["noise_seed"])
