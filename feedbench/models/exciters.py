"""Force exciters at the tool tip: shaker, inertial actuator, impact hammer (Ch. 3.5.1, 5.3,
5.5.3). One definition of each law; the simulated world steps them with the truth, the host
plans its excitation with the same laws and the exciter's datasheet values.

- Shaker on a stinger, voltage amplifier: the force per command falls above a corner frequency
  (back-EMF, coil inductance); at 160 Hz the force of a constant command falls from 70 N at
  25 Hz to 61 N at 100 Hz, the drop of Ch. 3.5.1 ("~70 N falling to ~60 N").
- Inertial actuator (Fig. 5.20): a reaction mass m_a on a suspension (f_a, ζ_a) driven by a coil
  force u; the force on the structure is m_a ÿ_a = u s²/(s² + 2ζ_a ω_a s + ω_a²) (base motion
  neglected: the tip moves tens of µm where the mass moves millimetres). Below f_a it cannot
  push; its stroke bounds the force at low frequency, F ≤ m_a ω² · stroke.
- Impact hammer: a half-sine contact pulse (soft rubber tip: a few ms), Eq. (5.3)'s input.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike


@dataclass(frozen=True)
class ExciterDynamics:
    """Force on the tip per command, F/u = N(s)/D(s) (coefficients, highest power first), and
    the largest command the amplifier delivers, `command_limit` (N)."""

    numerator: tuple[float, ...]
    denominator: tuple[float, ...]
    command_limit: float

    def response(self, f: ArrayLike) -> np.ndarray:
        """F/u at frequencies f (Hz), complex."""
        s = 2j * np.pi * np.asarray(f, dtype=float)
        return np.polyval(self.numerator, s) / np.polyval(self.denominator, s)

    def discrete(self, cycle_s: float) -> tuple[np.ndarray, ...]:
        """(A_d, B_d, C_d, D_d) over one bus cycle (s), Tustin: a sine command sequence gives
        a force sequence of amplitude |F/u| at (2/T) tan(ωT/2) (0.8 % above ω at 50 Hz,
        1 kHz). A zero-order hold would alias the steps' images (1 kHz ± f) onto f: the
        amplifier is fed through the output's reconstruction filter, not a staircase.

        scipy.signal's `tf2ss` + `cont2discrete` to the last bit, with scipy.linalg (a
        simulated bench starts its exciters before it is ready, and scipy.signal takes 0.6 s
        to import); a transfer function they would trim or refuse goes to scipy.signal."""
        num = np.asarray(self.numerator, dtype=float)
        den = np.asarray(self.denominator, dtype=float)
        if not (num.ndim == den.ndim == 1 and 1 <= num.size <= den.size and den.size >= 2
                and den[0] != 0.0 and abs(num[0] / den[0]) > 1e-14):
            import scipy.signal

            a, b, c, d = scipy.signal.tf2ss(self.numerator, self.denominator)
            return scipy.signal.cont2discrete((a, b, c, d), cycle_s, method="bilinear")[:4]
        return _tustin(num / den[0], den / den[0], cycle_s)


def _tustin(num: np.ndarray, den: np.ndarray, cycle_s: float) -> tuple[np.ndarray, ...]:
    """(A_d, B_d, C_d, D_d) of N(s)/D(s) (`den[0]` = 1, len(num) <= len(den)) as
    scipy.signal computes them: controller canonical form (`tf2ss`), then the generalised
    bilinear transform at alpha = 1/2 (`cont2discrete`, ``method="bilinear"``)."""
    from scipy import linalg

    n = den.size - 1
    num = np.hstack((np.zeros(den.size - num.size), num))[None, :]
    a = np.r_[-np.array([den[1:]]), np.eye(n - 1, n)]
    b = np.eye(n, 1)
    c = num[:, 1:] - np.outer(num[:, 0], den[1:])
    d = np.atleast_2d(num[:, 0]).reshape((c.shape[0], b.shape[1]))
    ima = np.eye(n) - 0.5 * cycle_s * a
    bd = linalg.solve(ima, cycle_s * b)
    return (linalg.solve(ima, np.eye(n) + 0.5 * cycle_s * a), bd,
            linalg.solve(ima.transpose(), c.transpose()).transpose(), d + 0.5 * np.dot(c, bd))


def shaker(corner_hz: float = 160.0, command_limit: float = 500.0) -> ExciterDynamics:
    """A shaker on a stinger: first-order fall-off above `corner_hz` (Hz)."""
    omega = 2.0 * math.pi * corner_hz
    return ExciterDynamics((omega,), (1.0, omega), command_limit)


@dataclass(frozen=True)
class InertialActuator:
    """Reaction mass (kg) on a suspension f_n (Hz), ζ; coil force limit (N); stroke ± (m)."""

    mass: float = 2.0
    f_n: float = 15.0
    zeta: float = 0.3
    command_limit: float = 300.0
    stroke: float = 5e-3

    def dynamics(self) -> ExciterDynamics:
        """F/u = s² / (s² + 2ζω_a s + ω_a²)."""
        omega = 2.0 * math.pi * self.f_n
        return ExciterDynamics((1.0, 0.0, 0.0), (1.0, 2.0 * self.zeta * omega, omega**2),
                               self.command_limit)

    def stroke_amplitude(self, f: ArrayLike, force: ArrayLike) -> np.ndarray:
        """Travel amplitude (m) of the mass for a force amplitude (N) at f (Hz): F / (m ω²)."""
        omega = 2.0 * np.pi * np.asarray(f, dtype=float)
        return np.asarray(force, dtype=float) / (self.mass * omega**2)

    def max_force(self, f: ArrayLike) -> np.ndarray:
        """Largest force amplitude (N) at f (Hz): coil limit × |F/u|, and m ω² × stroke."""
        omega = 2.0 * np.pi * np.asarray(f, dtype=float)
        coil = self.command_limit * np.abs(self.dynamics().response(f))
        return np.minimum(coil, self.mass * omega**2 * self.stroke)


def half_sine_pulse(peak: float, contact_s: float, cycle_s: float) -> np.ndarray:
    """A hammer's contact pulse peak·sin(π t / τ), 0 ≤ t ≤ τ, at the ends of the bus cycles
    from its start: the tip-force values of those cycles (N); the last one is 0.

    The tip force ramps between cycle values, so the pulse acts as the piecewise-linear
    interpolation of the half-sine (τ = 4 ms at 1 ms: 0, 0.71, 1, 0.71, 0 × peak).
    """
    t = np.arange(1, int(math.ceil(contact_s / cycle_s - 1e-9)) + 1) * cycle_s
    return np.where(t < contact_s, peak * np.sin(math.pi * t / contact_s), 0.0)
