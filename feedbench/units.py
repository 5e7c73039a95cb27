"""Conversions between the engineering units users read and the SI units used inside.

Config files, the CLI and reports speak mm/min, N/µm, (m/min)/mm, rpm, N·min/mm;
everything between them is SI (m, s, N, kg, rad).
"""

import math

MM_PER_MIN = 1e-3 / 60.0
"""1 mm/min in m/s."""

N_PER_UM = 1e6
"""1 N/µm in N/m."""

M_PER_MIN_PER_MM = 1000.0 / 60.0
"""1 (m/min)/mm position-loop gain in 1/s (DIGEST: ≈ 16.67 1/s)."""

N_MIN_PER_MM = 60.0 / 1e-3
"""1 N·min/mm viscous coefficient in N·s/m."""

MIN_PER_MM = 60.0 / 1e-3
"""1 min/mm (friction model constant k_tanh) in s/m."""

RPM = 2.0 * math.pi / 60.0
"""1 rpm in rad/s."""


def mm_per_min_to_m_per_s(feed_mm_min: float) -> float:
    """Feed in mm/min → velocity in m/s."""
    return feed_mm_min * MM_PER_MIN


def m_per_s_to_mm_per_min(velocity_m_s: float) -> float:
    """Velocity in m/s → feed in mm/min."""
    return velocity_m_s / MM_PER_MIN


def kv_to_per_second(kv_m_min_per_mm: float) -> float:
    """Position-loop gain (m/min)/mm → 1/s."""
    return kv_m_min_per_mm * M_PER_MIN_PER_MM


def kv_to_m_min_per_mm(kv_per_s: float) -> float:
    """Position-loop gain 1/s → (m/min)/mm."""
    return kv_per_s / M_PER_MIN_PER_MM


FEED_TYPOS = (("m/min", 1000.0), ("mm/s", 60.0))
"""Units a feed typed into a ``_mm_min`` field was probably meant in, with their size in
mm/min: m/min (×1000), mm/s (×60)."""

MS_TYPOS = (("s", 1000.0), ("µs", 1e-3))
"""Units a time typed into a ``_ms`` field was probably meant in, with their size in ms."""


def typed_in(value: float, unit: str, low: float, high: float,
             typos: tuple[tuple[str, float], ...]) -> str:
    """``; typed in m/min? 0.5 m/min = 500 mm/min; in mm/s? 0.5 mm/s = 30 mm/min``: each of
    `typos` (unit, its size in `unit`) that brings `value` into [`low`, `high`] (in `unit`),
    or "" when none does."""
    guesses = [f"{name}? {value:g} {name} = {value * size:g} {unit}" for name, size in typos
               if low <= value * size <= high]
    return "; typed in " + "; in ".join(guesses) if guesses else ""


SI_UNITS: dict[str, tuple[float, str]] = {
    "s": (1.0, "time"), "ms": (1e-3, "time"), "us": (1e-6, "time"), "µs": (1e-6, "time"),
    "m": (1.0, "length"), "mm": (1e-3, "length"), "um": (1e-6, "length"),
    "µm": (1e-6, "length"), "nm": (1e-9, "length"),
    "rad": (1.0, "angle"), "deg": (math.pi / 180.0, "angle"),
    "rev": (2.0 * math.pi, "angle"),
    "N": (1.0, "force"), "kN": (1e3, "force"),
    "Nm": (1.0, "torque"), "N·m": (1.0, "torque"), "kNm": (1e3, "torque"),
    "m/s": (1.0, "velocity"), "mm/s": (1e-3, "velocity"), "mm/min": (MM_PER_MIN, "velocity"),
    "m/min": (1.0 / 60.0, "velocity"), "rad/s": (1.0, "angular velocity"),
    "deg/s": (math.pi / 180.0, "angular velocity"), "rpm": (RPM, "angular velocity"),
    "rev/s": (2.0 * math.pi, "angular velocity"),
    "m/s2": (1.0, "acceleration"), "mm/s2": (1e-3, "acceleration"),
    "g": (9.80665, "acceleration"), "rad/s2": (1.0, "angular acceleration"),
}
"""Units a recording's sidecar or import mapping may name: their SI factor (m, rad, N, N·m,
s, m/s, rad/s, m/s², rad/s²) and the quantity they measure."""

UNITS_TO_SI = {unit: factor for unit, (factor, _) in SI_UNITS.items()}
"""Each known unit's SI factor (`SI_UNITS` without the quantity)."""
