"""Standard P-PI cascade tuning from a velocity bandwidth (thesis Ch. 4.2).

The laws live in `feedbench.models.axis` (`CascadeGains.standard`: Eqs. 4.2, 4.8, 4.12;
`TwoMassAxis.f_t` / `f_r`: Eqs. 4.13, 4.14); this module applies them to the tunings the
thesis compares and reports gains in the units the CNC shows.
"""

from dataclasses import dataclass

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
