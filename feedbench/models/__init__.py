"""Physics shared by simulation and analysis: friction (Eq. 5.2), the two-mass axis and its
P-PI cascade (Ch. 4.2, 5.3). One definition of each law."""

from feedbench.models.axis import (
    CSP,
    CST,
    CSV,
    LAB_BENCH_GAINS,
    AxisSimulator,
    CascadeGains,
    ServoTiming,
    TwoMassAxis,
)
from feedbench.models.friction import (
    LAB_BENCH_FRICTION,
    NO_FRICTION,
    AnderssonFriction,
    DirectionalFriction,
)

__all__ = [
    "CSP", "CSV", "CST", "AxisSimulator", "CascadeGains", "LAB_BENCH_GAINS", "ServoTiming",
    "TwoMassAxis", "AnderssonFriction", "DirectionalFriction", "LAB_BENCH_FRICTION",
    "NO_FRICTION",
]
