"""The units the closure's texts name, for a linear or a rotary axis.

The closure computes in SI whatever the axis moves: position in m, or in rad on a rotary
axis; force in N, or in N·m (or the dataset's own force unit, e.g. a current). The
parameter keys (`M_kg`, `pitch_mm`, `offset_N`) are the config and JSON vocabulary and stay,
and so do the numbers: a key's scale (1e3 for mm) is the same scale of a radian (mrad) on a
rotary axis. Only the unit a text names changes, here, in one table.
"""

from __future__ import annotations

ROTARY_UNITS = {
    "m": "rad", "mm": "mrad", "µm": "µrad",
    "m/s": "rad/s", "mm/s": "mrad/s", "mm/min": "mrad/min", "min/mm": "min/mrad",
    "m/s²": "rad/s²",
    "N": "N·m", "1/kN": "1/(kN·m)", "kg": "kg·m²",
    "N·s/m": "N·m·s/rad", "N/µm": "N·m/µrad", "1/µm²": "1/µrad²",
    "N/kg": "N·m/(kg·m²)",
    "m/(N·s)": "rad/(N·m·s)",
}
"""Each unit of a linear axis that names its position or force, and the rotary axis's unit
of the same quantity at the same scale (a unit not listed, s, ms, Hz, -, has no axis)."""


def axis_unit(unit: str, rotary: bool) -> str:
    """`unit` (a linear axis's) as the axis reads it: itself on a linear axis, its
    `ROTARY_UNITS` counterpart on a rotary one (a unit without the axis in it unchanged)."""
    return ROTARY_UNITS.get(unit, unit) if rotary else unit


def unit_after_key(unit: str, rotary: bool) -> str:
    """What follows a value printed after its key ("M_kg = 0.2"): nothing on a linear axis,
    whose key names the unit; " kg·m²" on a rotary one, whose key names the linear unit
    (nothing for a quantity without a unit, "-")."""
    return f" {axis_unit(unit, rotary)}" if rotary and unit not in ("", "-") else ""


def axis_units(rotary: bool, *units: str) -> tuple[str, ...]:
    """`axis_unit` of each of `units`, in order (the units of one sentence)."""
    return tuple(axis_unit(unit, rotary) for unit in units)
