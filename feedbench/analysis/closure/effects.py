"""The vocabulary of model terms and candidate effects of the closure.

The inverse model predicts the measured motor force from the measured motion:

    F̂ = S( A( Σ_terms Φ_term(x, v, a; η)(t + τ) · θ_term ) )

θ: linear parameters (masses, friction levels, offsets, ripple components); η: nonlinear
ones (Stribeck velocity, ripple pitch, mode frequency and damping, backlash width);
τ: the `delay` between the force channel and the motion; A: the `amplitude_nonlinearity`
of the force reading; S: its `sensor_gain`. A model config declares some terms; the closure
adds the others from this library. Names below are the JSON/TOML vocabulary.

Each effect says which columns it adds, where its nonlinear parameters may start (from the
residual: its signature test), and when it applies. Friction columns come from the Andersson
law, Eq. (5.2), in `feedbench.models.friction` (linear in F_c, F_s − F_c and σ); ripple,
backlash, transmissibility and force-level laws from `feedbench.models.effects`.
"""

from __future__ import annotations

import functools
import math
from collections import OrderedDict
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field
from typing import Callable, Iterator, Mapping, Protocol

import numpy as np
import scipy.fft
import scipy.signal
from numba import njit

from feedbench.analysis.closure.trace import (
    Kinematics, frequencies, lowpass, lowpass_derivatives, read_only,
)
from feedbench.analysis.closure.units import axis_unit, axis_units, unit_after_key
from feedbench.models import effects as laws
from feedbench.models.dynamic_friction import dahl_normalised, maxwell_slip_normalised
from feedbench.models._kernel import TANH_SATURATION
from feedbench.models.friction import AnderssonFriction, DirectionalFriction
from feedbench.units import MIN_PER_MM, MM_PER_MIN, N_PER_UM

K_TANH_DEFAULT_MIN_MM = 0.25
"""tanh constant of Eq. (5.2) (min/mm), the thesis's value (Fig. 5.11)."""

DIFFERENCE_STEP = float(np.sqrt(np.finfo(float).eps))
"""Relative finite-difference step of a smooth term (scipy's default for 2-point)."""

RUGGED_STEP = 0.02
"""Relative finite-difference step of a term whose SSR is rugged at fine scale (backlash: the
load rattling in the play); on the model's own data it recovers play, contact and load
friction within 10 % where differences of √ε stop at 57 % of the residual explained."""

_NO_FRICTION = AnderssonFriction(F_c=0.0, F_s=0.0, v_s=math.inf, sigma=0.0)


@dataclass(frozen=True)
class Parameter:
    """One parameter of a term. `key` names it in TOML and JSON, in `unit`; SI = value · to_si.

    linear: enters the prediction linearly (solved by least squares, needs no start);
    setting: a shape constant that is declared, never fitted; default: SI start or setting;
    lower, upper: SI bounds: of a nonlinear parameter, its search range; of a linear one, its
    physical range (a mass, a stiffness, a damping or a friction level cannot be negative:
    the least squares are bounded there, and a value that ends on the bound is reported).
    tolerance: relative difference (beside the two fits' uncertainty) within which the
    values fitted on two recordings count as the same physical effect.
    """

    key: str
    unit: str
    to_si: float
    doc: str
    linear: bool = True
    setting: bool = False
    default: float = 0.0
    lower: float = -math.inf
    upper: float = math.inf
    tolerance: float = 0.25


@dataclass(frozen=True)
class Context:
    """What a signature test may look at besides the kinematics.

    residual: measured − predicted force on the used samples (`Kinematics.rows`) (N);
    acting: the model's force before the output transforms, every sample (N).
    """

    residual: np.ndarray
    acting: np.ndarray
    terms: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    """SI values of the current model's terms, by name."""


class TermLike(Protocol):
    """A term's values (SI) and which parameters are free (`closure.model.Term`)."""

    values: Mapping[str, float]
    free: frozenset[str]


@dataclass(frozen=True)
class Effect:
    """A model term / candidate effect. Subclasses give its columns and its signature.

    Parameter values travel as SI floats keyed by the parameter's `key` (whose suffix names
    the unit of the TOML and JSON value, not of the SI float).
    """

    name: str
    doc: str
    signature: str
    parameters: tuple[Parameter, ...]
    kind: str = "additive"
    """additive (adds columns), shift (delays them), output (maps the summed force)."""

    requires: tuple[str, ...] = ()
    """Terms that must already be in the model for this one to make sense."""

    rivals: tuple[str, ...] = ()
    """Terms that explain the same signature another way (a play with friction behind it and
    pre-sliding both shape the force after each reversal): once one is in the model, the
    other is not offered on top of it (one finding per signature, not two that share it)."""

    difference_step: float = DIFFERENCE_STEP
    """Relative step of the finite differences of the nonlinear refinement's Jacobian in this
    term's parameters: √ε (scipy's own) for a smooth SSR; larger where the SSR is rugged at
    fine scale, so the step is a secant across the ruggedness."""

    @property
    def linear_keys(self) -> tuple[str, ...]:
        """Keys of the linear parameters, in column order."""
        return tuple(p.key for p in self.parameters if p.linear and not p.setting)

    @property
    def nonlinear_keys(self) -> tuple[str, ...]:
        """Keys of the fitted nonlinear parameters."""
        return tuple(p.key for p in self.parameters if not p.linear and not p.setting)

    def parameter(self, key: str) -> Parameter:
        """The parameter named `key`."""
        for p in self.parameters:
            if p.key == key:
                return p
        raise KeyError(f"{self.name}: no parameter {key!r}")

    def defaults(self) -> dict[str, float]:
        """SI start values of every parameter (linear ones 0, settings their value)."""
        return {p.key: p.default for p in self.parameters}

    def fitted_keys(self, start: Mapping[str, float]) -> tuple[str, ...]:
        """Parameters a candidate started at `start` fits (all but the settings)."""
        return self.linear_keys + self.nonlinear_keys

    def applicable(self, present: frozenset[str], fixed: frozenset[str]) -> bool:
        """Whether the effect can be added to a model holding the terms `present`."""
        return (self.name not in present and all(r in present for r in self.requires)
                and not present.intersection(self.rivals))

    def columns(self, kin: Kinematics, values: Mapping[str, float]) -> np.ndarray:
        """Regressors (n × len(linear_keys)) of an additive effect at the SI `values`."""
        return np.empty((kin.n, 0))

    def starts(self, kin: Kinematics, context: Context) -> list[dict[str, float]]:
        """Candidate start values of the nonlinear parameters (SI), to be screened."""
        return [{}]

    def probe(self, kin: Kinematics, context: Context, start: Mapping[str, float]) -> np.ndarray:
        """Columns (every sample) whose span is the effect's first-order signature."""
        return self.columns(kin, {**self.defaults(), **start})

    def follower_inputs(self, kin: Kinematics, values: Mapping[str, float]
                        ) -> list[tuple[float, ...]]:
        """The `follower_force` parameters (ω, ζ, κ, half play, friction, k_tanh) `columns`
        simulates at `values` (none by default): the screening computes a candidate's starts
        together (`prefetch_followers`)."""
        return []

    def shift(self, values: Mapping[str, float]) -> float:
        """Lead (s) of the force channel over the motion this term introduces."""
        return 0.0

    def forward(self, force: np.ndarray, values: Mapping[str, float]) -> np.ndarray:
        """Reading (N) of the acting force `force` (N) (identity but for output effects)."""
        return force

    def inverse(self, reading: np.ndarray, values: Mapping[str, float]) -> np.ndarray:
        """Acting force (N) behind a reading (N): the inverse of `forward`."""
        return reading

    def slope(self, force: np.ndarray, values: Mapping[str, float]) -> np.ndarray | float:
        """d forward / d force at `force`."""
        return 1.0

    def implausible(self, values: Mapping[str, float], total_mass: float,
                    kin: Kinematics) -> str | None:
        """Why fitted values cannot be physical, or cannot be told on the data `kin` (None if
        they can)."""
        return None

    def invariants(self, term: TermLike, std: Mapping[tuple[str, str], float]
                   ) -> dict[str, tuple[str, float, float, float]]:
        """What must come out the same on every recording if the effect is physical:
        {name: (unit, value, σ, relative tolerance)} in config units; by default every
        fitted parameter with its `Parameter.tolerance` (inf for an effective value, which is
        then not compared)."""
        out = {}
        for p in self.parameters:
            if p.setting or p.key not in term.free:
                continue
            out[p.key] = (p.unit, term.values[p.key] / p.to_si,
                          std.get((self.name, p.key), math.nan) / p.to_si, p.tolerance)
        return out

    def describe(self, values: Mapping[str, float], rotary: bool = False) -> str:
        """What the fitted effect looks like, in engineering units (a `rotary` axis's: rad
        for m, N·m for N, `units.axis_unit`)."""
        return ", ".join(f"{p.key} = {values[p.key] / p.to_si:.4g}{unit_after_key(p.unit, rotary)}"
                         for p in self.parameters if not p.setting)


def _andersson(kin: Kinematics, values: Mapping[str, float], v: np.ndarray | None = None,
               **law: float) -> np.ndarray:
    """Eq. (5.2) at velocity v (default: the filtered motor velocity) with the given levels
    and the term's tanh constant, band-limited as the force reading is: the measured force
    is the filtered tanh of the true speed, and near each reversal the tanh of the filtered
    speed has content above the band that the reading has not (filter both sides alike)."""
    friction = AnderssonFriction(k_tanh=values["k_tanh_min_mm"], **law)
    return lowpass(np.asarray(friction.force(kin.v if v is None else v)), kin.bandwidth, kin.dt)


def _k_tanh_setting() -> Parameter:
    return Parameter("k_tanh_min_mm", "min/mm", MIN_PER_MM, "tanh constant of Eq. (5.2)",
                     linear=False, setting=True, default=K_TANH_DEFAULT_MIN_MM * MIN_PER_MM)


@dataclass(frozen=True)
class Inertia(Effect):
    """Rigid-body inertia M·a."""

    def columns(self, kin, values):
        return kin.a[:, None]


@dataclass(frozen=True)
class Viscous(Effect):
    """Viscous friction σ v (Eq. 5.2, σ term)."""

    def columns(self, kin, values):
        return kin.v[:, None]


@dataclass(frozen=True)
class Coulomb(Effect):
    """Coulomb friction F_c tanh(k_tanh v) (Eq. 5.2 with F_s = F_c)."""

    def columns(self, kin, values):
        return _andersson(kin, values, F_c=1.0, F_s=1.0, v_s=math.inf, sigma=0.0)[:, None]


@dataclass(frozen=True)
class Stribeck(Effect):
    """Stribeck excess (F_s − F_c) exp(−(|v|/v_s)^δ) tanh(k_tanh v) (Eq. 5.2)."""

    def columns(self, kin, values):
        return _andersson(kin, values, F_c=0.0, F_s=1.0, v_s=values["v_s_mm_min"],
                          sigma=0.0, delta=values["delta"])[:, None]

    def implausible(self, values, total_mass, kin):
        if not values["dF_s_N"] > 0.0:
            return "static level below the Coulomb level"
        fastest = float(np.max(np.abs(kin.v[kin.rows])))
        if values["v_s_mm_min"] > fastest:
            speed = axis_unit("mm/min", kin.rotary)
            return (f"Stribeck velocity {values['v_s_mm_min'] / MM_PER_MIN:.4g} {speed} beyond "
                    f"the fastest speed used, {fastest / MM_PER_MIN:.4g} {speed}: a slope over "
                    f"the data, not a decay it shows")
        return None

    def starts(self, kin, context):
        top = max(float(np.quantile(np.abs(kin.v), 0.9)), 1e-4)
        return [{"v_s_mm_min": v_s} for v_s in np.geomspace(top * 1e-3, top, 16)]


@dataclass(frozen=True)
class DirectionDependent(Effect):
    """Viscous friction that differs by direction: Δσ·v for v < 0 only
    (`DirectionalFriction`, Fig. 5.11). A Coulomb level that differs by direction is, while
    the axis moves, a Coulomb level plus a constant force: the `offset` effect."""

    def columns(self, kin, values):
        negative_only = DirectionalFriction(_NO_FRICTION,
                                            AnderssonFriction(0.0, 0.0, math.inf, 1.0))
        return np.asarray(negative_only.force(kin.v))[:, None]


@dataclass(frozen=True)
class Offset(Effect):
    """A constant force: gravity on an inclined axis, an unbalanced counterweight, or a
    force-reading offset (the two are the same in the force balance)."""

    def columns(self, kin, values):
        return np.ones((kin.n, 1))


@dataclass(frozen=True)
class Ripple(Effect):
    """Force ripple periodic in position: A_s sin(2π x/p) + A_c cos(2π x/p) (cogging,
    screw lead, pinion pitch); amplitude √(A_s² + A_c²), `models.effects.ripple_force`."""

    def columns(self, kin, values):
        pitch = values["pitch_mm"]
        return np.column_stack([laws.ripple_forces(kin.x, 1.0, pitch, 0.0),
                                laws.ripple_forces(kin.x, 1.0, pitch, 0.5 * math.pi)])

    def starts(self, kin, context):
        """Peaks of the Lomb–Scargle periodogram of the residual against position.

        On every `stride`-th sample (≥ 3 per period of the band's edge: the residual is
        band-limited) and at two wavenumbers per 2π/stroke (the periodogram's resolution),
        by `lomb_scargle` (work ∝ samples + wavenumbers, not their product).
        """
        low, high = _pitch_range(kin)
        stroke = float(np.ptp(kin.x))
        wavenumbers = np.arange(2 * np.pi / high, 2 * np.pi / low, np.pi / stroke)
        if wavenumbers.size < 3:
            return []
        stride = max(1, int(1.0 / (3.0 * kin.bandwidth * kin.dt)))
        residual = context.residual[::stride]
        power = lomb_scargle(kin.x[kin.rows[::stride]], residual - residual.mean(),
                             wavenumbers[0], np.pi / stroke, wavenumbers.size)
        peaks = scipy.signal.find_peaks(power)[0]
        best = peaks[np.argsort(power[peaks])[::-1][:3]]
        return [{"pitch_mm": 2 * np.pi / wavenumbers[i]} for i in best]

    def implausible(self, values, total_mass, kin):
        longest = _pitch_range(kin)[1]
        if values["pitch_mm"] > longest:
            mm = axis_unit("mm", kin.rotary)
            return (f"pitch {values['pitch_mm'] * 1e3:.3g} {mm} longer than half the stroke "
                    f"({longest * 1e3:.3g} {mm}): not a periodic force on this data")
        return None

    def invariants(self, term, std):
        """Amplitude and pitch (the phase depends on where each recording's encoder zero is)."""
        values, pitch = term.values, self.parameter("pitch_mm")
        sigma = float(np.fmax(std.get((self.name, "A_sin_N"), math.nan),
                              std.get((self.name, "A_cos_N"), math.nan)))
        return {"amplitude_N": ("N", math.hypot(values["A_sin_N"], values["A_cos_N"]), sigma,
                                self.parameter("A_sin_N").tolerance),
                "pitch_mm": ("mm", values["pitch_mm"] / pitch.to_si,
                             std.get((self.name, "pitch_mm"), math.nan) / pitch.to_si,
                             pitch.tolerance)}

    def describe(self, values, rotary=False):
        amplitude = math.hypot(values["A_sin_N"], values["A_cos_N"])
        n, mm = axis_units(rotary, "N", "mm")
        return f"amplitude {amplitude:.3g} {n} at pitch {values['pitch_mm'] * 1e3:.4g} {mm}"


def _pitch_range(kin: Kinematics) -> tuple[float, float]:
    """Shortest pitch the filter passes at the top speed, longest half the stroke (m)."""
    fastest = float(np.quantile(np.abs(kin.v), 0.95))
    return max(fastest / kin.bandwidth, 1e-6), max(float(np.ptp(kin.x)) / 2.0, 2e-6)


EXTIRPOLATION_NODES = 8
"""Mesh nodes each sample is spread onto by `lomb_scargle` (Lagrange weights of degree 7)."""

MESH_PER_WAVENUMBER = 32
"""Mesh points per wavenumber of `lomb_scargle`'s grid: the highest wavenumber turns by at
most 2π/32 rad per mesh step, so a sample's extirpolation error is below (2π/32)⁸ · 43 / 8!
≈ 2·10⁻⁹ of its weight (the Lagrange remainder, 43 the node product's bound)."""


def lomb_scargle(x: np.ndarray, y: np.ndarray, first: float, step: float,
                 count: int) -> np.ndarray:
    """`scipy.signal.lombscargle(x, y, first + step · arange(count))`, its default power
    ((y's unit)², A² n/4 for a sine of amplitude A on the n samples), from sums made by
    extirpolation onto a uniform position mesh and FFTs (Press & Rybicki 1989): work ∝
    n + count log count instead of n · count.

    x: positions (m, any order, repeats), y: the centred signal at them, first and step:
    the wavenumber grid (rad/m). The periodogram is shift-invariant, so x counts from its
    least value. Equal to lombscargle's within ≈ 10⁻⁸ of the largest power (see
    `MESH_PER_WAVENUMBER`). Hand-written: scipy has only the direct sums, and astropy's
    `LombScargle(method="fast")`, the same algorithm, would add astropy for this function.
    """
    x = x - x.min()
    n = x.size
    z = _trig_sums(x, y * np.exp(1j * first * x), step, count)
    w = _trig_sums(x, np.exp(2j * first * x), 2.0 * step, count)
    rotated = z * np.exp(-0.5j * np.angle(w))
    smallest = np.finfo(float).epsneg
    in_phase = np.maximum(0.5 + np.abs(w) / (2.0 * n), smallest)
    quadrature = np.maximum(0.5 - np.abs(w) / (2.0 * n), smallest)
    return (rotated.real**2 / in_phase + rotated.imag**2 / quadrature) / (2.0 * n)


def _trig_sums(x: np.ndarray, weights: np.ndarray, step: float, count: int) -> np.ndarray:
    """Σ_i weights_i exp(i j step x_i) for j = 0 … count − 1 (x ≥ 0 in m, step in rad/m):
    the weights extirpolated onto `MESH_PER_WAVENUMBER` · count nodes over 2π/step (a
    period of every term, so the mesh wraps around exactly), then one inverse FFT."""
    size = scipy.fft.next_fast_len(max(MESH_PER_WAVENUMBER * count, EXTIRPOLATION_NODES))
    u = x * (step * size / (2.0 * math.pi))
    first_node = np.floor(u).astype(np.int64) - (EXTIRPOLATION_NODES // 2 - 1)
    mesh = np.zeros(size, dtype=complex)
    for node, lagrange in enumerate(_lagrange_weights(u - first_node)):
        index = (first_node + node) % size
        spread = weights * lagrange
        mesh += np.bincount(index, spread.real, size) + 1j * np.bincount(index, spread.imag, size)
    return scipy.fft.ifft(mesh)[:count] * size


def _lagrange_weights(t: np.ndarray) -> np.ndarray:
    """Lagrange weights (`EXTIRPOLATION_NODES` × len(t)) of nodes 0, 1, … at t (in nodes)."""
    nodes = range(EXTIRPOLATION_NODES)
    weights = np.ones((EXTIRPOLATION_NODES, t.size))
    for m in nodes:
        for other in nodes:
            if other != m:
                weights[m] *= (t - other) / (m - other)
    return weights


@dataclass(frozen=True)
class StructuralMode(Effect):
    """A mass m on a spring-damper behind the motor: m (T(s) − 1) a, T = x_tip/x_mot of
    `models.effects.tip_transmissibility` (Eq. 4.25), f_n = √(k/m)/2π (Eq. 4.13)."""

    def columns(self, kin, values):
        return _mode_column(kin, values["f_n_Hz"], values["zeta"])[:, None]

    def implausible(self, values, total_mass, kin):
        if not 0.0 < values["m_kg"] < total_mass:
            kg = axis_unit("kg", kin.rotary)
            return f"modal mass {values['m_kg']:.3g} {kg} outside (0, {total_mass:.3g}) {kg}"
        return None

    def starts(self, kin, context):
        top = 0.9 * kin.bandwidth
        return [{"f_n_Hz": f, "zeta": z} for f in np.geomspace(2.0, top, 32) for z in (0.02, 0.1)]

    def describe(self, values, rotary=False):
        return (f"mass {values['m_kg']:.3g} {axis_unit('kg', rotary)} at "
                f"{values['f_n_Hz']:.4g} Hz, "
                f"ζ = {values['zeta']:.3g}")


def _mode_column(kin: Kinematics, f_n: float, zeta: float) -> np.ndarray:
    """(T(jω) − 1) a, T of Eq. (4.25) evaluated exactly at each frequency of the band.

    Not a discretisation of T: Tustin moves a resonance at f_n by (tan(π f_n dt)/(π f_n dt)
    − 1) f_n (1.2 % at 61 Hz at 1 kHz, a whole half-power bandwidth when ζ ≈ 0.01), and the
    model's force is dominated by that narrow peak. The acceleration is band-limited (the
    zero-phase filter), so T applied in the frequency domain is exact within the band.
    """
    return spectral(kin.a, kin.dt, functools.partial(_mode_response, f_n, zeta))


@functools.lru_cache(maxsize=64)
def _mode_response(f_n: float, zeta: float, length: int, dt: float) -> np.ndarray:
    """T(jω) − 1 of Eq. (4.25) (f_n in Hz) at the `frequencies(length, dt)` (dt in s),
    read-only: a held mode's column is computed again at every fit of a model holding it."""
    num, den = laws.tip_transmissibility(f_n, zeta)
    s = 2j * np.pi * frequencies(length, dt)
    return read_only(np.polyval(num, s) / np.polyval(den, s) - 1.0)


MODE_SEPARATION = 0.2
"""Relative distance in frequency a second mode keeps from the declared one: closer, the
two are one mode at a moved f_n (a recalibration), not a mode the model lacks."""


@dataclass(frozen=True)
class SecondMode(StructuralMode):
    """A second mass on a spring-damper, beside the declared structural mode: the motor's
    reaction to a structure with several modes is a sum of modal terms m_i (T_i − 1) a
    (Eq. 4.25 per mode), so a missing mode is a term of its own, not a moved first mode."""

    def starts(self, kin, context):
        declared = context.terms["structural_mode"]["f_n_Hz"]
        return [{**s, "declared_f_n_Hz": declared} for s in super().starts(kin, context)
                if abs(s["f_n_Hz"] / declared - 1.0) > MODE_SEPARATION]

    def implausible(self, values, total_mass, kin):
        return (super().implausible(values, total_mass, kin) or _out_of_band(values, kin)
                or _too_close(values))

    def describe(self, values, rotary=False):
        return "second mode: " + super().describe(values, rotary)


def _too_close(values: Mapping[str, float]) -> str | None:
    """Why a second mode is the declared one moved (within `MODE_SEPARATION`), or None."""
    declared = values["declared_f_n_Hz"]
    if declared > 0.0 and abs(values["f_n_Hz"] / declared - 1.0) <= MODE_SEPARATION:
        return (f"f_n {values['f_n_Hz']:.4g} Hz within {MODE_SEPARATION:.0%} of the declared "
                f"mode's {declared:.4g} Hz: the declared mode moved, not a second one")
    return None


def _out_of_band(values: Mapping[str, float], kin: Kinematics) -> str | None:
    """Why a mode's f_n cannot be told on this data (above the filter band), or None."""
    if values["f_n_Hz"] > kin.bandwidth:
        return (f"f_n {values['f_n_Hz']:.4g} Hz above the {kin.bandwidth:.4g} Hz band: "
                f"not resolved on this data")
    return None


def spectral(columns: np.ndarray, dt: float,
             response: Callable[[int, float], np.ndarray]) -> np.ndarray:
    """`columns` (n or n × p samples, along axis 0, every dt s) through the frequency
    response `response(length, dt)` (complex, at the `trace.frequencies(length, dt)` of the
    spectrum), on the columns followed by their mirror image (periodic without a jump, as
    the derivative filter of `trace.lowpass_derivatives`)."""
    n = columns.shape[0]
    length = scipy.fft.next_fast_len(2 * n, real=True)
    pad = np.repeat(columns[-1:], length - 2 * n, axis=0)
    extended = np.concatenate([columns, pad, columns[::-1]], axis=0)
    gain = response(length, dt)
    spectrum = scipy.fft.rfft(extended, axis=0) * (gain if columns.ndim == 1 else gain[:, None])
    return scipy.fft.irfft(spectrum, length, axis=0)[:n]


@dataclass(frozen=True)
class CubicStiffening(Effect):
    """The structural spring stiffens with deflection: k d (1 + κ d²), d = x_mot − x_tip.
    The tip follows the measured motor motion through the nonlinear spring (Eq. 4.25's
    mass-spring-damper with a cubic spring, `follower_force`); the motor force changes by
    m (a_tip(κ) − a_tip(0)). f_n and ζ are the model's structural mode's (settings taken
    from it); m is fitted (≈ the mode's mass), κ refined."""

    def columns(self, kin, values):
        omega, zeta = 2.0 * math.pi * values["f_n_Hz"], values["zeta"]
        stiff = follower_force(kin.x, kin.v, kin.dt, omega, zeta, values["kappa_per_um2"])
        linear = follower_force(kin.x, kin.v, kin.dt, omega, zeta, 0.0)
        return (stiff - linear)[:, None]

    def starts(self, kin, context):
        mode = context.terms.get("structural_mode")
        if mode is None:
            return []
        reach = max(float(np.max(np.abs(kin.a))) / (2.0 * math.pi * mode["f_n_Hz"]) ** 2,
                    1e-9)
        return [{"f_n_Hz": mode["f_n_Hz"], "zeta": mode["zeta"], "kappa_per_um2": k / reach**2}
                for k in (0.03, 0.1, 0.3, 1.0)]

    def implausible(self, values, total_mass, kin):
        if not 0.0 < values["m_kg"] < total_mass:
            kg = axis_unit("kg", kin.rotary)
            return f"spring mass {values['m_kg']:.3g} {kg} outside (0, {total_mass:.3g}) {kg}"
        return None

    def describe(self, values, rotary=False):
        per_um2, kg = axis_units(rotary, "1/µm²", "kg")
        return (f"κ = {values['kappa_per_um2'] * 1e-12:.3g} {per_um2} on the "
                f"{values['f_n_Hz']:.4g} Hz mode, mass {values['m_kg']:.3g} {kg}")


TIP_SUBSTEPS = 8
"""Least RK4 steps per sample of a follower body (ω h ≤ 0.05 at 61 Hz at 1 kHz)."""

FOLLOWER_STEP = 0.3
"""Largest ω h of a follower body's RK4 step (a stiff backlash contact takes more steps)."""


def follower_force(x: np.ndarray, v: np.ndarray, dt: float, omega: float, zeta: float,
                   kappa: float = 0.0, half_play: float = 0.0, friction: float = 0.0,
                   k_tanh: float = 0.0) -> np.ndarray:
    """Spring-damper force per kg of the follower (m/s², N/kg) on a body driven by the
    measured motor motion x (m), v (m/s) sampled every dt (s): a dead zone of ± half_play
    (m) (backlash: the dead-zone spring of Ch. 3.4, Moradi), then a spring ω² s (1 + κ s²)
    on the deflection s beyond it and a damper 2ζω ḋ while in contact; the body's own
    Coulomb friction `friction` tanh(k_tanh v_body) (N/kg, k_tanh s/m). With no play and no
    friction the force per kg is the body's acceleration (Eq. 4.25 with a cubic spring)."""
    steps = _follower_steps(dt, omega)
    x, v = np.ascontiguousarray(x, dtype=float), np.ascontiguousarray(v, dtype=float)
    memo = _FOLLOWER_MEMO.get()
    if memo is None:
        return _follower(x, v, dt, omega, zeta, kappa, half_play, friction, k_tanh, steps)
    return memo.force(x, v, (dt, omega, zeta, kappa, half_play, friction, k_tanh), steps)


def _follower_steps(dt: float, omega: float) -> int:
    return max(TIP_SUBSTEPS, int(math.ceil(omega * dt / FOLLOWER_STEP)))


def prefetch_followers(x: np.ndarray, v: np.ndarray, dt: float,
                       inputs: list[tuple[float, ...]]) -> None:
    """Within a `follower_memo`, simulate the follower bodies of `inputs` (each the
    parameters ω, ζ, κ, half play, friction, k_tanh of `follower_force`) that it does not
    hold yet, side by side (`_followers`: twice the throughput of one at a time), and put
    them in the memo; `follower_force` then returns them. Nothing without a memo."""
    memo = _FOLLOWER_MEMO.get()
    if memo is None or not inputs:
        return
    x, v = np.ascontiguousarray(x, dtype=float), np.ascontiguousarray(v, dtype=float)
    memo.prefetch(x, v, dt, inputs)


FOLLOWER_MEMO_BYTES = 512 * 2**20
"""Most bytes of follower forces one `follower_memo` keeps (the least recently used go
first): about 4 600 forces of a 14 000-sample recording."""

FOLLOWER_MEMO_MOTIONS = 8
"""Most motions (x, v pairs) one `follower_memo` keeps forces of (a closure has two: the
fit and the held-out kinematics)."""


class _FollowerMemo:
    """The follower forces computed within one `follower_memo`, keyed on the exact inputs:
    the motion arrays (by identity, held, and checked bit for bit against a copy on every
    use, so an array changed in place is recomputed) and the bit patterns of the parameters
    (-0.0 and 0.0 apart). A hit returns the very array computed before, made read-only."""

    def __init__(self) -> None:
        self.motions: OrderedDict[tuple[int, int], tuple[np.ndarray, ...]] = OrderedDict()
        self.forces: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self.bytes = 0

    def force(self, x: np.ndarray, v: np.ndarray, params: tuple[float, ...],
              steps: int) -> np.ndarray:
        self.force_motion(x, v)
        key = ((id(x), id(v)), np.array(params, dtype=float).tobytes(), steps)
        out = self.forces.get(key)
        if out is not None:
            self.forces.move_to_end(key)
            return out
        return self._keep(key, _follower(x, v, *params, steps))

    def prefetch(self, x: np.ndarray, v: np.ndarray, dt: float,
                 inputs: list[tuple[float, ...]]) -> None:
        """The forces of `inputs` (ω, ζ, κ, half play, friction, k_tanh) on x, v not held
        yet, simulated together per substep count."""
        self.force_motion(x, v)
        motion, groups = (id(x), id(v)), {}
        for one in inputs:
            params = (dt, *one)
            key = (motion, np.array(params, dtype=float).tobytes(), _follower_steps(dt, one[0]))
            if key not in self.forces:
                groups.setdefault(key[2], {})[key] = params
        for steps, batch in groups.items():
            table = np.array([params[1:] for params in batch.values()], dtype=float)
            simulate = _followers_staged if len(batch) >= STAGED_BODIES else _followers
            for key, out in zip(batch, simulate(x, v, dt, table, steps)):
                self._keep(key, out.copy())

    def force_motion(self, x: np.ndarray, v: np.ndarray) -> None:
        """Hold the motion x, v (recorded anew, its forces dropped, if it changed)."""
        motion = (id(x), id(v))
        held = self.motions.get(motion)
        if held is None or not (_same_bits(held[2], x) and _same_bits(held[3], v)):
            self._forget(motion)
            self.motions[motion] = (x, v, x.copy(), v.copy())
            while len(self.motions) > FOLLOWER_MEMO_MOTIONS:
                self._forget(next(iter(self.motions)))
        self.motions.move_to_end(motion)

    def _keep(self, key: tuple, out: np.ndarray) -> np.ndarray:
        out.flags.writeable = False
        self.forces[key] = out
        self.bytes += out.nbytes
        while self.bytes > FOLLOWER_MEMO_BYTES and len(self.forces) > 1:
            self.bytes -= self.forces.popitem(last=False)[1].nbytes
        return out

    def _forget(self, motion: tuple[int, int]) -> None:
        """Drop a motion and every force computed on it."""
        self.motions.pop(motion, None)
        for key in [key for key in self.forces if key[0] == motion]:
            self.bytes -= self.forces.pop(key).nbytes


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and np.array_equal(a.view(np.int64), b.view(np.int64))


COLUMN_MEMO_BLOCKS = 64
"""Most column blocks one `follower_memo` keeps (the least recently used go first): a block
is asked for again within one candidate's fit (refinement, solve, prediction) and by the
next candidates' fits of the same model."""


class _ColumnMemo:
    """The `Effect.columns` blocks computed within one `follower_memo`, keyed on the effect
    and the kinematics (by identity, both held: a `Kinematics` is never changed) and the
    bit patterns of the values. A hit returns the very array computed before, read-only."""

    def __init__(self) -> None:
        self.blocks: OrderedDict[tuple, tuple[Effect, Kinematics, np.ndarray]] = OrderedDict()

    def columns(self, effect: Effect, kin: Kinematics, values: Mapping[str, float]
                ) -> np.ndarray:
        key = (id(effect), id(kin), tuple(values),
               np.array(list(values.values()), dtype=float).tobytes())
        held = self.blocks.get(key)
        if held is not None:
            self.blocks.move_to_end(key)
            return held[2]
        block = read_only(effect.columns(kin, values))
        self.blocks[key] = (effect, kin, block)
        if len(self.blocks) > COLUMN_MEMO_BLOCKS:
            self.blocks.popitem(last=False)
        return block


def term_columns(effect: Effect, kin: Kinematics, values: Mapping[str, float]) -> np.ndarray:
    """`effect.columns(kin, values)`; within a `follower_memo`, computed once per exact
    input (read-only: the same array each time)."""
    memo = _COLUMN_MEMO.get()
    return effect.columns(kin, values) if memo is None else memo.columns(effect, kin, values)


_FOLLOWER_MEMO: ContextVar[_FollowerMemo | None] = ContextVar("follower_memo", default=None)
_COLUMN_MEMO: ContextVar[_ColumnMemo | None] = ContextVar("column_memo", default=None)


@contextmanager
def follower_memo() -> Iterator[None]:
    """Within the block, `follower_force` computes each exact input once (one closure run:
    `diagnosis.close_the_loop`), and so does `term_columns`. The screening of a candidate
    probes many starts, each with the same linear mode beside it
    (`Backlash._in_the_mode_spring`, `CubicStiffening`), and a start is simulated again when
    it is fitted: on the independent simulator's recal_mass case, 964 follower simulations
    held 301 distinct inputs; a model's held terms give the same columns at every fit.
    Results are the same arrays, so the closure's results are bit for bit those without
    the memo. Nested blocks share the outer memo; it is dropped when the outermost block
    ends (no cache outlives a run)."""
    if _FOLLOWER_MEMO.get() is not None:
        yield
        return
    token = _FOLLOWER_MEMO.set(_FollowerMemo())
    columns = _COLUMN_MEMO.set(_ColumnMemo())
    try:
        yield
    finally:
        _COLUMN_MEMO.reset(columns)
        _FOLLOWER_MEMO.reset(token)


@njit(cache=True, inline="always")
def _tanh(x: float) -> float:
    """`math.tanh`, bit for bit, without its library call where it is ±1 exactly
    (|x| > `TANH_SATURATION`): a braked follower moving at the axis's speed is there nearly
    always, and the call is on the step's critical path (one braked body: 9 % faster)."""
    if x > TANH_SATURATION:
        return 1.0
    if x < -TANH_SATURATION:
        return -1.0
    return math.tanh(x)


@njit(cache=True)
def _spring_force(d: float, dv: float, w2: float, c: float, kappa: float,
                  half_play: float) -> float:
    """Force per kg of the dead-zone spring-damper at deflection d (m), rate dv (m/s): the
    spring on the deflection beyond the play (`models.effects.dead_zone`), the damper while
    in contact (|d| ≥ half_play)."""
    if abs(d) < half_play:
        return 0.0
    s = laws.dead_zone(d, 2.0 * half_play)
    return w2 * (s + kappa * s * s * s) + c * dv


def _follower(x: np.ndarray, v: np.ndarray, dt: float, omega: float, zeta: float,
              kappa: float, half_play: float, friction: float, k_tanh: float,
              steps: int) -> np.ndarray:
    """RK4 of the follower body of `follower_force` (`_followers` with one body), the
    motor position and speed linearly interpolated within each sample; starts at rest in
    the middle of the play on x[0]."""
    table = np.array([[omega, zeta, kappa, half_play, friction, k_tanh]], dtype=float)
    return _followers(x, v, dt, table, steps)[0]


@njit(cache=True)
def _substep_motion(x: np.ndarray, v: np.ndarray, i: int, j: int,
                    steps: int) -> tuple[float, float, float, float, float, float]:
    """The motor's position (m) and speed (m/s) at the start, the middle and the end of
    substep `j` of `steps` after sample `i`, linearly interpolated: RK4's three points."""
    dx, dv = x[i + 1] - x[i], v[i + 1] - v[i]
    f0, f1, f2 = j / steps, (j + 0.5) / steps, (j + 1.0) / steps
    return (x[i] + f0 * dx, v[i] + f0 * dv, x[i] + f1 * dx, v[i] + f1 * dv,
            x[i] + f2 * dx, v[i] + f2 * dv)


@njit(cache=True)
def _followers(x: np.ndarray, v: np.ndarray, dt: float, table: np.ndarray,
               steps: int) -> np.ndarray:
    """The follower body of `follower_force` for each row (ω, ζ, κ, half play, friction,
    k_tanh) of `table` on the same motion: RK4, the motor position and speed linearly
    interpolated within each sample, each body starting at rest in the middle of its play
    on x[0].

    Hand-written loop (numba): each step depends on the last, nothing to vectorise along
    time; the bodies are stepped side by side, so that independent bodies' steps overlap
    in the processor where one body's steps wait on each other (about twice the
    throughput on 24 bodies; one body alone costs 0.2 ms more per call than a loop for one
    body, measured). A body's friction is only evaluated when it can be non-zero
    (`braked`): tanh is on the step's critical path (a third of a frictionless call), and
    0 · tanh(k v) changes no bit of the output (at most the sign of a zero state, which no
    force sees)."""
    n, k_bodies = x.size, table.shape[0]
    out = np.empty((k_bodies, n))
    xt, vt = np.full(k_bodies, x[0]), np.full(k_bodies, v[0])
    h = dt / steps
    w2, c = np.empty(k_bodies), np.empty(k_bodies)
    braked = np.empty(k_bodies, dtype=np.bool_)
    for k in range(k_bodies):
        w2[k], c[k] = table[k, 0] * table[k, 0], 2.0 * table[k, 1] * table[k, 0]
        braked[k] = table[k, 4] != 0.0 or not math.isfinite(table[k, 5])
    for i in range(n):
        for k in range(k_bodies):
            out[k, i] = _spring_force(x[i] - xt[k], v[i] - vt[k], w2[k], c[k], table[k, 2],
                                      table[k, 3])
        if i + 1 == n:
            break
        for j in range(steps):
            x0, v0, x1, v1, x2, v2_ = _substep_motion(x, v, i, j, steps)
            for k in range(k_bodies):
                kappa, half_play = table[k, 2], table[k, 3]
                friction, k_tanh = table[k, 4], table[k, 5]
                xk, vk = xt[k], vt[k]
                a1 = _spring_force(x0 - xk, v0 - vk, w2[k], c[k], kappa, half_play)
                if braked[k]:
                    a1 = a1 - friction * _tanh(k_tanh * vk)
                v2 = vk + 0.5 * h * a1
                a2 = _spring_force(x1 - (xk + 0.5 * h * vk), v1 - v2, w2[k], c[k], kappa,
                                   half_play)
                if braked[k]:
                    a2 = a2 - friction * _tanh(k_tanh * v2)
                v3 = vk + 0.5 * h * a2
                a3 = _spring_force(x1 - (xk + 0.5 * h * v2), v1 - v3, w2[k], c[k], kappa,
                                   half_play)
                if braked[k]:
                    a3 = a3 - friction * _tanh(k_tanh * v3)
                v4 = vk + h * a3
                a4 = _spring_force(x2 - (xk + h * v3), v2_ - v4, w2[k], c[k], kappa,
                                   half_play)
                if braked[k]:
                    a4 = a4 - friction * _tanh(k_tanh * v4)
                xt[k] = xk + h * (vk + 2.0 * v2 + 2.0 * v3 + v4) / 6.0
                vt[k] = vk + h * (a1 + 2.0 * a2 + 2.0 * a3 + a4) / 6.0
    return out


STAGED_BODIES = 8
"""Bodies from which `prefetch_followers` steps them with `_followers_staged` (measured on
a 14 000-sample motion: 8 bodies 1.4×, 24 and more 2× the throughput of `_followers`; below
8, its stores between stages cost more than the vector lanes gain)."""


@njit(cache=True)
def _followers_staged(x: np.ndarray, v: np.ndarray, dt: float, table: np.ndarray,
                      steps: int) -> np.ndarray:
    """`_followers`, bit for bit (the same operations on each body in the same order), one
    RK4 stage at a time over all the bodies: each stage's loop over the bodies holds no
    call and no state carried from one body to the next, so the compiler can run it on
    the processor's vector lanes; the friction of the braked bodies is added in a loop of
    its own (`_tanh` is a call)."""
    n, k_bodies = x.size, table.shape[0]
    out = np.empty((k_bodies, n))
    xt, vt = np.full(k_bodies, x[0]), np.full(k_bodies, v[0])
    h = dt / steps
    w2, c = table[:, 0] * table[:, 0], 2.0 * table[:, 1] * table[:, 0]
    kappa, half_play = table[:, 2].copy(), table[:, 3].copy()
    friction, k_tanh = table[:, 4].copy(), table[:, 5].copy()
    braked = (friction != 0.0) | ~np.isfinite(k_tanh)
    a1, a2, a3, a4 = np.empty(k_bodies), np.empty(k_bodies), np.empty(k_bodies), np.empty(k_bodies)
    v2, v3, v4 = np.empty(k_bodies), np.empty(k_bodies), np.empty(k_bodies)
    for i in range(n):
        for k in range(k_bodies):
            out[k, i] = _spring_force(x[i] - xt[k], v[i] - vt[k], w2[k], c[k], kappa[k],
                                      half_play[k])
        if i + 1 == n:
            break
        for j in range(steps):
            x0, v0, x1, v1, x2, v2_ = _substep_motion(x, v, i, j, steps)
            for k in range(k_bodies):
                a1[k] = _spring_force(x0 - xt[k], v0 - vt[k], w2[k], c[k], kappa[k],
                                      half_play[k])
            _brake(a1, vt, braked, friction, k_tanh)
            for k in range(k_bodies):
                v2[k] = vt[k] + 0.5 * h * a1[k]
                a2[k] = _spring_force(x1 - (xt[k] + 0.5 * h * vt[k]), v1 - v2[k], w2[k],
                                      c[k], kappa[k], half_play[k])
            _brake(a2, v2, braked, friction, k_tanh)
            for k in range(k_bodies):
                v3[k] = vt[k] + 0.5 * h * a2[k]
                a3[k] = _spring_force(x1 - (xt[k] + 0.5 * h * v2[k]), v1 - v3[k], w2[k],
                                      c[k], kappa[k], half_play[k])
            _brake(a3, v3, braked, friction, k_tanh)
            for k in range(k_bodies):
                v4[k] = vt[k] + h * a3[k]
                a4[k] = _spring_force(x2 - (xt[k] + h * v3[k]), v2_ - v4[k], w2[k], c[k],
                                      kappa[k], half_play[k])
            _brake(a4, v4, braked, friction, k_tanh)
            for k in range(k_bodies):
                xk, vk = xt[k], vt[k]
                xt[k] = xk + h * (vk + 2.0 * v2[k] + 2.0 * v3[k] + v4[k]) / 6.0
                vt[k] = vk + h * (a1[k] + 2.0 * a2[k] + 2.0 * a3[k] + a4[k]) / 6.0
    return out


@njit(cache=True, inline="always")
def _brake(a: np.ndarray, v: np.ndarray, braked: np.ndarray, friction: np.ndarray,
           k_tanh: np.ndarray) -> None:
    """a −= friction · tanh(k_tanh v) (m/s², v in m/s) in place, on the braked bodies."""
    for k in range(a.size):
        if braked[k]:
            a[k] = a[k] - friction[k] * _tanh(k_tanh[k] * v[k])


@dataclass(frozen=True)
class Delay(Effect):
    """The force channel leads the motion by τ: F_meas(t) = F(t + τ) (a current-loop delay
    behind a recorded force command, or channels not aligned in time)."""

    def shift(self, values):
        return values["tau_ms"]

    def probe(self, kin, context, start):
        return np.gradient(context.acting, kin.dt)[:, None]

    def starts(self, kin, context):
        slope = np.gradient(context.acting, kin.dt)[kin.rows]
        tau = float(slope @ context.residual / max(slope @ slope, 1e-300))
        bound = self.parameter("tau_ms").upper
        return [{"tau_ms": float(np.clip(tau, -bound, bound))}]

    def describe(self, values, rotary=False):
        return f"force leads motion by {values['tau_ms'] * 1e3:.3g} ms"


@dataclass(frozen=True)
class AmplitudeNonlinearity(Effect):
    """Force-level nonlinearity of the reading: F_meas = F (1 + β|F|)
    (`models.effects.reported_force`)."""

    def forward(self, force, values):
        return laws.reported_forces(force, values["beta_per_kN"])

    def inverse(self, reading, values):
        """The acting force; for β < 0 a reading beyond the law's largest, 1/(4|β|), is
        taken at that largest (the force at the peak, 1/(2|β|)): finite for every β the
        search may try."""
        beta = values["beta_per_kN"]
        if beta < 0.0:
            reading = np.clip(reading, 0.25 / beta, -0.25 / beta)
        return laws.acting_forces(reading, beta)

    def slope(self, force, values):
        return 1.0 + 2.0 * values["beta_per_kN"] * np.abs(force)

    def probe(self, kin, context, start):
        return (context.acting * np.abs(context.acting))[:, None]

    def starts(self, kin, context):
        """β by regression on F|F|, kept where the reading stays invertible: a reading r
        comes from an acting force only while 1 + 4β|r| > 0 (half of that margin kept)."""
        acting = context.acting[kin.rows]
        q = acting * np.abs(acting)
        beta = float(q @ context.residual / max(q @ q, 1e-300))
        lower, upper = _bounds(self, "beta_per_kN")
        lower = max(lower, -0.5 / (4.0 * max(float(np.max(np.abs(kin.force))), 1e-300)))
        return [{"beta_per_kN": float(np.clip(beta, lower, upper))}]

    def describe(self, values, rotary=False):
        return f"β = {values['beta_per_kN'] * 1e3:.3g} {axis_unit('1/kN', rotary)}"


@dataclass(frozen=True)
class SensorGain(Effect):
    """The force reading is scaled: F_meas = g F (a wrong motor force constant or drive gain).
    Identifiable only against declared (fixed) terms: with every level free it is absorbed."""

    def applicable(self, present, fixed):
        return super().applicable(present, fixed) and bool(fixed)

    def forward(self, force, values):
        return values["gain"] * force

    def inverse(self, reading, values):
        return reading / values["gain"]

    def slope(self, force, values):
        return values["gain"]

    def probe(self, kin, context, start):
        return context.acting[:, None]

    def starts(self, kin, context):
        q = context.acting[kin.rows]
        gain = 1.0 + float(q @ context.residual / max(q @ q, 1e-300))
        return [{"gain": float(np.clip(gain, *_bounds(self, "gain")))}]

    def invariants(self, term, std):
        """The gain's departure from 1 (what the effect is)."""
        p = self.parameter("gain")
        return {"gain − 1": (p.unit, term.values["gain"] - 1.0,
                             std.get((self.name, "gain"), math.nan), p.tolerance)}

    def describe(self, values, rotary=False):
        return f"gain {values['gain']:.4g}"


@dataclass(frozen=True)
class Backlash(Effect):
    """Backlash. With a structural mode declared, a dead zone of width b inside the mode's
    spring (motor ↔ play ↔ drive-train spring ↔ mode mass, the thesis's picture, Ch. 3.4):
    the mode's mass followed through the spring with the play, less the linear mode.
    Without one: a load behind a play of width b, pushed through a contact spring-damper
    (the dead zone with stiffness of Ch. 3.4, Moradi) and braked by its own Coulomb
    friction. The load is simulated from the measured motor motion (`follower_force`: contact
    at f_c = √(k_c/m_L)/2π with ζ_c, friction μ = F_L/m_L per kg); the declared model carries
    the load as rigid mass and friction of the motor (m_L a + F_L tanh(k v)), so the motor
    force changes by m_L (g − a − μ tanh(k v)), g the contact force per kg, band-limited as
    the force reading is."""

    def columns(self, kin, values):
        if values["mode_f_n_Hz"] > 0.0:
            return self._in_the_mode_spring(kin, values)
        k_tanh, mu = values["k_tanh_min_mm"], values["friction_N_kg"]
        contact = follower_force(kin.x, kin.v, kin.dt, *self.follower_inputs(kin, values)[0])
        return (lowpass(contact - mu * np.tanh(k_tanh * kin.v), kin.bandwidth, kin.dt)
                - kin.a)[:, None]

    def follower_inputs(self, kin, values):
        """The load on its contact; in the mode's spring, the mass behind the play and the
        linear mode."""
        k_tanh, mu = values["k_tanh_min_mm"], values["friction_N_kg"]
        if values["mode_f_n_Hz"] <= 0.0:
            return [(2.0 * math.pi * values["f_contact_Hz"], values["zeta_contact"], 0.0,
                     0.5 * values["width_um"], mu, k_tanh)]
        omega = 2.0 * math.pi * values["mode_f_n_Hz"]
        return [(omega, values["zeta_contact"], 0.0, 0.5 * values["width_um"], mu, k_tanh),
                (omega, values["mode_zeta"], 0.0, 0.0, 0.0, 0.0)]

    def _in_the_mode_spring(self, kin: Kinematics, values: Mapping[str, float]) -> np.ndarray:
        """m (g(play, μ, ζ_c) − a_tip − μ tanh(k v)): the declared mode's mass followed
        through its spring with a dead zone of the play (motor ↔ play ↔ drive-train spring ↔
        mass, Ch. 3.4) and braked by its own share μ of the friction (guides behind the
        play), g the spring force per kg on the motor; less the linear mode a_tip and the
        friction the model already puts at the motor. Band-limited as the reading is.

        The spring in contact is damped by ζ_c, screened and refined, not the mode's ζ: a
        mass that bounces in a play is sensitive to its state (a rattle no open-loop
        simulation follows over seconds), and a follower with the mode's light damping rings
        where the real one does not. ζ_c comes out at an effective 0.1–0.3 on the
        independent simulator (whose contact has the mode's 0.012): the follower predicts
        the rattle's average force, and the play, mass and friction come out within 8 %
        (docs/closure.md)."""
        k_tanh, mu = values["k_tanh_min_mm"], values["friction_N_kg"]
        played, linear = (follower_force(kin.x, kin.v, kin.dt, *inputs)
                          for inputs in self.follower_inputs(kin, values))
        return (lowpass(played - mu * np.tanh(k_tanh * kin.v), kin.bandwidth, kin.dt)
                - linear)[:, None]

    def fitted_keys(self, start):
        """In the mode's spring: the mass, the play, its friction and the contact's
        damping (the spring is the mode's)."""
        if start.get("mode_f_n_Hz", 0.0) > 0.0:
            return ("m_load_kg", "width_um", "friction_N_kg", "zeta_contact")
        return super().fitted_keys(start)

    def implausible(self, values, total_mass, kin):
        kg, um = axis_units(kin.rotary, "kg", "µm")
        if not 0.0 < values["m_load_kg"] < total_mass:
            return f"load mass {values['m_load_kg']:.3g} {kg} outside (0, {total_mass:.3g}) {kg}"
        if values["width_um"] < 0.5 * SMALLEST_PLAY:
            return (f"play {values['width_um'] * 1e6:.3g} {um} below the "
                    f"{SMALLEST_PLAY * 1e6:.3g} {um} the screening resolves: friction behind a "
                    f"spring, not a play")
        return None

    def starts(self, kin, context):
        """A load on a contact behind the play (below); with a structural mode declared,
        also a play in its spring (the thesis's picture, the mode's f_n and ζ as settings)
        at widths from 1 µm to a twentieth of the stroke, four per decade, with no, 30 %
        or all of the declared friction behind it, and a contact damping ζ_c on a log grid
        (`CONTACT_DAMPINGS`, the mode's ζ at least). The screening picks the form and the
        start."""
        mode = context.terms.get("structural_mode")
        in_the_mode = [] if mode is None else [
            {"width_um": w, "mode_f_n_Hz": mode["f_n_Hz"], "mode_zeta": mode["zeta"],
             "friction_N_kg": min(share * _declared_friction(context) / max(mode["m_kg"], 1e-3),
                                  self.parameter("friction_N_kg").upper),
             "zeta_contact": zeta}
            for w in _play_widths(kin)[::2] for share in (0.0, 0.3, 1.0)
            for zeta in sorted({max(mode["zeta"], z) for z in CONTACT_DAMPINGS})]
        return in_the_mode + self._load_starts(kin, context)

    def _load_starts(self, kin: Kinematics, context: Context) -> list[dict[str, float]]:
        """Around the rigid play that explains the residual best: the fit's SSR is rugged
        in every parameter at fine scale (the load rattling in the play), smooth at coarse
        scale, and the screening of a start is already its exact fit in m_L. The rigid
        play (`models.effects.play`, the contact infinitely stiff) is screened over widths
        from 1 µm to a twentieth of the stroke, eight per decade (each reversal's transient
        moves with the width); its load mass and friction give μ = F_L/m_L. Around that
        width and μ (× ½, 1, 2): the contact from half the band's edge to twice it (beyond,
        the band cannot tell it from rigid), ζ_c 0.3 and 1."""
        k_tanh, rows = self.defaults()["k_tanh_min_mm"], kin.rows
        widths = _play_widths(kin)
        best = (-math.inf, widths[0], 0.0)
        for width in widths:
            columns = _rigid_play(kin, width, k_tanh)[rows]
            with np.errstate(all="ignore"):
                theta = np.linalg.lstsq(columns, context.residual, rcond=None)[0]
            explained = float(np.sum((columns @ theta) ** 2))
            if explained > best[0]:
                best = (explained, width, theta[1] / theta[0] if theta[0] > 0.0 else 0.0)
        braking = max(float(np.quantile(np.abs(kin.a), 0.95)), 1e-6)
        mu = float(np.clip(best[2], 0.1 * braking, 10.0 * braking))
        return [{"width_um": best[1], "f_contact_Hz": f * kin.bandwidth, "zeta_contact": z,
                 "friction_N_kg": mu * r}
                for f in (0.5, 1.0, 2.0) for z in (0.3, 1.0) for r in (0.5, 1.0, 2.0)]

    def describe(self, values, rotary=False):
        um, kg, n = axis_units(rotary, "µm", "kg", "N")
        if values["mode_f_n_Hz"] > 0.0:
            return (f"play {values['width_um'] * 1e6:.3g} {um} in the spring of the "
                    f"{values['mode_f_n_Hz']:.4g} Hz mode, mass {values['m_load_kg']:.3g} {kg}, "
                    f"friction behind it {values['m_load_kg'] * values['friction_N_kg']:.3g} {n}, "
                    f"contact damping ζ {values['zeta_contact']:.2g} (effective)")
        return (f"play {values['width_um'] * 1e6:.3g} {um}, load {values['m_load_kg']:.3g} {kg} "
                f"on a {values['f_contact_Hz']:.3g} Hz contact (ζ {values['zeta_contact']:.2g}), "
                f"load friction {values['m_load_kg'] * values['friction_N_kg']:.3g} {n}")


def _declared_friction(context: Context) -> float:
    """The model's Coulomb level (N), the most friction a part of the axis can carry."""
    return context.terms.get("coulomb", {}).get("F_c_N", 0.0)


CONTACT_DAMPINGS = (0.03, 0.1, 0.3, 1.0)
"""Contact damping ratios ζ_c screened for a play in the mode's spring: two per decade, not
tuned to a case (the SSR is rugged in ζ_c: the refinement leaves it near the screened one)."""

SMALLEST_PLAY = 1e-6
"""Smallest play (m) the backlash starts screen; a fitted play below half of it is none."""


def _play_widths(kin: Kinematics) -> np.ndarray:
    """Plays (m) to screen: `SMALLEST_PLAY` to a twentieth of the stroke, eight per decade."""
    low, high = SMALLEST_PLAY, max(float(np.ptp(kin.x)) / 20.0, 2 * SMALLEST_PLAY)
    return np.geomspace(low, high, max(2, int(np.ceil(8 * np.log10(high / low))) + 1))


def _rigid_play(kin: Kinematics, width: float, k_tanh: float) -> np.ndarray:
    """Columns of a load behind a rigid play of `width` (m): m_L (a_L − a) and
    F_L (tanh(k v_L) − tanh(k v)), x_L = `models.effects.play`(x, width)."""
    lag = laws.play(kin.x, width) - kin.x
    v_lag, a_lag = lowpass_derivatives(lag, kin.bandwidth, kin.dt, (1, 2))
    slip = np.tanh(k_tanh * (kin.v + v_lag)) - np.tanh(k_tanh * kin.v)
    return np.column_stack([a_lag, slip])


def _bounds(effect: Effect, key: str) -> tuple[float, float]:
    p = effect.parameter(key)
    return p.lower, p.upper


def _nonlinear(key: str, unit: str, to_si: float, doc: str, default: float, lower: float,
               upper: float, tolerance: float = 0.25) -> Parameter:
    return Parameter(key, unit, to_si, doc, linear=False, default=default, lower=lower,
                     upper=upper, tolerance=tolerance)


PRESLIDING_RESOLVED_PERIODS = 1.0
"""A pre-sliding shows on the data when the travel of 2 x_p after a reversal takes at least
this many periods of the filter's cut-off (median over the reversals)."""

PRESLIDING_DECADE_STARTS = 8
"""Pre-sliding displacements screened per decade (the Dahl column changes smoothly with x_p;
eight per decade put a start within 15 % of any x_p)."""


@dataclass(frozen=True)
class Presliding(Effect):
    """Pre-sliding hysteresis (Ch. 2.3, Fig. 2.9; §5.2's dynamic friction): after a reversal
    the contact first deforms elastically, and the friction force follows the displacement
    since the reversal, not the velocity. Dahl's law with exponent α (Dahl 1968/1976; LuGre,
    Canudas de Wit et al. 1995, with F_s = F_c and σ1 = 0 is its α = 1), normalised:
    dw/dx = (1/x_p) |1 − w sgn ẋ|^α sgn(1 − w sgn ẋ), x_p = F_p/σ0
    (`models.dynamic_friction.dahl_normalised`, exact over each sample interval). The term
    adds F_p (w(x) − tanh(k_tanh v)), band-limited as the force reading is: the
    bristle force less the declared Coulomb tanh that it replaces at the same level, so the
    Coulomb level stays the sliding friction (marginality: offered on top of `coulomb`,
    whose k_tanh it takes); and LuGre's bristle damping σ1 dz/dt, dz/dt = x_p dw/dt =
    v |1 − w sgn v|^α (v − |v| w for α = 1), zero while sliding. Linear: F_p (N), σ1
    (N·s/m); nonlinear: x_p and α (α < 1 saturates sooner, as the elasto-plastic law of
    Dupont et al. 2002 does); σ0 = F_p/x_p (N/µm) the bristle stiffness (the initial slope
    of the force–displacement loop from w = 0)."""

    def columns(self, kin, values):
        k_tanh = values["k_tanh_min_mm"]
        w = dahl_normalised(kin.x, values["x_p_um"], values["alpha"],
                            math.tanh(k_tanh * kin.v[0]) if kin.n else 0.0)
        bristle_rate = kin.v * np.abs(1.0 - w * np.sign(kin.v)) ** values["alpha"]
        return lowpass_columns(np.column_stack([w - np.tanh(k_tanh * kin.v), bristle_rate]),
                               kin)

    def starts(self, kin, context):
        """The declared Coulomb's k_tanh; x_p on a grid from 0.1 µm to the smaller of a
        twentieth of the stroke and the bound, `PRESLIDING_DECADE_STARTS` per decade (the
        screening picks the start whose column explains the residual best)."""
        k_tanh = context.terms.get("coulomb", {}).get("k_tanh_min_mm",
                                                       self.defaults()["k_tanh_min_mm"])
        low, top = 1e-7, self.parameter("x_p_um").upper
        high = max(min(float(np.ptp(kin.x)) / 20.0, top), 2.0 * low)
        count = max(2, int(np.ceil(PRESLIDING_DECADE_STARTS * np.log10(high / low))) + 1)
        return [{"x_p_um": float(x_p), "k_tanh_min_mm": k_tanh}
                for x_p in np.geomspace(low, high, count)]

    def invariants(self, term, std):
        """The bristle stiffness σ0 = F_p/x_p (N/µm) and the level F_p (N): what the contact
        is, on every recording (σ from the two fits' deviations, correlation left out); σ1,
        often at the noise, is an effective value, not compared."""
        values, level, x_p = term.values, self.parameter("F_p_N"), self.parameter("x_p_um")
        sigma0 = values["F_p_N"] / values["x_p_um"]
        relative = (math.hypot(std.get((self.name, "F_p_N"), math.nan) / values["F_p_N"],
                               std.get((self.name, "x_p_um"), math.nan) / values["x_p_um"])
                    if values["F_p_N"] > 0.0 else math.nan)
        return {"F_p_N": ("N", values["F_p_N"], std.get((self.name, "F_p_N"), math.nan),
                          level.tolerance),
                "sigma0_N_um": ("N/µm", sigma0 / N_PER_UM, abs(sigma0) * relative / N_PER_UM,
                                x_p.tolerance)}

    def implausible(self, values, total_mass, kin):
        """A level that is not positive, or a pre-sliding the band cannot resolve: when the
        axis crosses 2 x_p after a reversal (w from −1 to 0.73) within less than one filter
        period 1/B, the term is a Coulomb transition read through the filter, not
        hysteresis this data can show."""
        n, um = axis_units(kin.rotary, "N", "µm")
        if not values["F_p_N"] > 0.0:
            return f"pre-sliding level {values['F_p_N']:.3g} {n} not positive"
        crossing = presliding_time(kin, 2.0 * values["x_p_um"])
        if crossing < PRESLIDING_RESOLVED_PERIODS / kin.bandwidth:
            return (f"pre-sliding over {values['x_p_um'] * 1e6:.3g} {um} lasts "
                    f"{crossing * 1e3:.3g} ms after a reversal (median), shorter than the "
                    f"filter period {1e3 / kin.bandwidth:.3g} ms: not resolved on this data")
        return None

    def describe(self, values, rotary=False):
        n_um, n, um, ns_m = axis_units(rotary, "N/µm", "N", "µm", "N·s/m")
        return (f"pre-sliding hysteresis: bristle stiffness "
                f"{values['F_p_N'] / values['x_p_um'] / N_PER_UM:.3g} {n_um}, level "
                f"{values['F_p_N']:.3g} {n}, pre-sliding displacement "
                f"{values['x_p_um'] * 1e6:.3g} {um}, bristle damping "
                f"{values['sigma1_Ns_m']:.3g} {ns_m}")


GMS_BLOCKS = 16
"""Blocks of the `gms` candidate's Iwan distribution (its virgin curve within 1/(4·16²) =
0.1 % of F_p of the parabola)."""


@dataclass(frozen=True)
class MaxwellSlip(Presliding):
    """Pre-sliding by the generalized Maxwell-slip model (Al-Bender, Lampaert, Swevers 2005,
    the thesis's [107]; `models.dynamic_friction.GMS`), rate independent (F_s = F_c: a
    slipping block stays at its limit whatever the attraction C): `GMS_BLOCKS` blocks of one
    stiffness with slip displacements uniform on (0, 2 x_p] (Iwan's distribution,
    `models.dynamic_friction.maxwell_slip_normalised`, exact over each sample interval).
    Its signature beside Dahl's (`presliding`): non-local memory, a branch after a reversal
    is the virgin curve w = ξ − ξ²/4 (ξ = x/x_p ≤ 2) scaled by 2 (Masing), and a closed
    minor loop leaves no trace. The term adds F_p (w(x) − tanh(k_tanh v)) and the blocks'
    damping σ1 v × (share of the blocks still elastic), band-limited as the reading is;
    linear F_p (N), σ1 (N·s/m), nonlinear x_p = F_p/σ0 (σ0 the initial stiffness of the
    loop); starts, invariants and resolution test as `presliding`'s."""

    def columns(self, kin, values):
        k_tanh = values["k_tanh_min_mm"]
        w, u = maxwell_slip_normalised(kin.x, values["x_p_um"], GMS_BLOCKS,
                                       math.tanh(k_tanh * kin.v[0]) if kin.n else 0.0)
        elastic = np.mean((np.abs(u) < 1.0) | (np.sign(u) != np.sign(kin.v)[:, None]), axis=1)
        return lowpass_columns(np.column_stack([w - np.tanh(k_tanh * kin.v),
                                                kin.v * elastic]), kin)

    def describe(self, values, rotary=False):
        n_um, n, um, ns_m = axis_units(rotary, "N/µm", "N", "µm", "N·s/m")
        return (f"pre-sliding hysteresis (generalized Maxwell-slip, {GMS_BLOCKS} blocks): "
                f"initial stiffness {values['F_p_N'] / values['x_p_um'] / N_PER_UM:.3g} {n_um}, "
                f"level {values['F_p_N']:.3g} {n}, full sliding after "
                f"{2e6 * values['x_p_um']:.3g} {um}, damping {values['sigma1_Ns_m']:.3g} {ns_m}")


def lowpass_columns(columns: np.ndarray, kin: Kinematics) -> np.ndarray:
    """Each column (n × p) through the kinematics' zero-phase filter, as the force is."""
    return np.column_stack([lowpass(column, kin.bandwidth, kin.dt) for column in columns.T])


def presliding_time(kin: Kinematics, travel: float) -> float:
    """Median time (s) the axis takes after a reversal (a sign change of the filtered
    velocity) to move `travel` (m) from the reversal point, over the reversals that get that
    far before the next one; inf when none does (every reversal stays within `travel`)."""
    reversals = np.flatnonzero(np.signbit(kin.v[1:]) != np.signbit(kin.v[:-1])) + 1
    ends = np.append(reversals[1:], kin.n)
    times = []
    for start, end in zip(reversals, ends):
        moved = np.abs(kin.x[start:end] - kin.x[start]) >= travel
        if moved.any():
            times.append(int(np.argmax(moved)) * kin.dt)
    return float(np.median(times)) if times else math.inf


LIBRARY: tuple[Effect, ...] = (
    Inertia("inertia", "rigid-body inertia M a", "declared (base term)",
            (Parameter("M_kg", "kg", 1.0, "moving mass (kg; kg·m² for a rotary axis)",
                       lower=0.0),)),
    Viscous("viscous", "viscous friction σ v, Eq. (5.2)", "residual ∝ v",
            (Parameter("F_v_Ns_m", "N·s/m", 1.0, "viscous coefficient σ", lower=0.0),)),
    Coulomb("coulomb", "Coulomb friction F_c tanh(k_tanh v), Eq. (5.2)",
            "residual ∝ sign(v)",
            (Parameter("F_c_N", "N", 1.0, "Coulomb level F_c", lower=0.0), _k_tanh_setting())),
    Stribeck("stribeck", "Stribeck excess (F_s − F_c) exp(−(|v|/v_s)^δ) tanh(k_tanh v), Eq. (5.2)",
             "residual ∝ sign(v), decaying with |v|",
             (Parameter("dF_s_N", "N", 1.0, "static excess F_s − F_c", lower=0.0),
              _nonlinear("v_s_mm_min", "mm/min", MM_PER_MIN, "Stribeck velocity v_s",
                         100 * MM_PER_MIN, 1e-6, 10.0),
              Parameter("delta", "-", 1.0, "Stribeck shape exponent δ", linear=False,
                        setting=True, default=1.0),
              _k_tanh_setting()),
             requires=("coulomb",)),
    DirectionDependent("direction_dependent",
                       "viscous friction per direction: σ differs for v < 0 (Fig. 5.11)",
                       "residual ∝ v on one side only",
                       (Parameter("dF_v_Ns_m", "N·s/m", 1.0, "σ(v<0) − σ(v>0)"),),
                       requires=("viscous", "coulomb", "offset")),
    Offset("offset", "constant force offset (gravity, counterweight, force-reading offset)",
           "residual has a non-zero mean",
           (Parameter("offset_N", "N", 1.0, "constant force"),)),
    Backlash("backlash", "a play in the declared mode's spring, or a load behind a play on a "
             "contact spring (dead zone, Ch. 3.4)",
             "residual after each reversal, while the motor crosses the play",
             (Parameter("m_load_kg", "kg", 1.0, "mass behind the play", lower=0.0),
              _nonlinear("width_um", "µm", 1e-6, "total play L_z", 20e-6, 0.0, 0.05),
              _nonlinear("f_contact_Hz", "Hz", 1.0, "contact frequency √(k_c/m_L)/2π",
                         200.0, 1.0, 5e3, tolerance=math.inf),
              _nonlinear("zeta_contact", "-", 1.0, "contact damping ratio", 0.2, 0.0, 2.0,
                         tolerance=math.inf),
              _nonlinear("friction_N_kg", "N/kg", 1.0, "load's Coulomb friction per kg F_L/m_L",
                         1.0, 0.0, 100.0),
              _k_tanh_setting(),
              Parameter("mode_f_n_Hz", "Hz", 1.0, "the structural mode whose spring holds "
                        "the play (0: a load on a contact)", linear=False, setting=True),
              Parameter("mode_zeta", "-", 1.0, "that mode's ζ", linear=False, setting=True)),
             difference_step=RUGGED_STEP, rivals=("presliding", "gms")),
    Ripple("ripple", "force ripple periodic in position (cogging, screw, pinion)",
           "residual periodic in position (Lomb–Scargle peak)",
           (Parameter("A_sin_N", "N", 1.0, "sine component"),
            Parameter("A_cos_N", "N", 1.0, "cosine component"),
            _nonlinear("pitch_mm", "mm", 1e-3, "period in position", 10e-3, 1e-6, 10.0))),
    StructuralMode("structural_mode",
                   "a mass on a spring-damper behind the motor (Eqs. 4.13, 4.25)",
                   "residual ∝ (T(s) − 1)·a: resonant near f_n",
                   (Parameter("m_kg", "kg", 1.0, "mass on the spring", lower=0.0),
                    _nonlinear("f_n_Hz", "Hz", 1.0, "motor-locked frequency √(k/m)/2π",
                               50.0, 0.5, 1e4),
                    _nonlinear("zeta", "-", 1.0, "damping ratio", 0.05, 1e-3, 1.0))),
    SecondMode("second_mode", "a second mass on a spring-damper behind the motor (Eq. 4.25)",
               "residual ∝ (T₂(s) − 1)·a: resonant away from the declared mode",
               (Parameter("m_kg", "kg", 1.0, "mass on the spring", lower=0.0),
                _nonlinear("f_n_Hz", "Hz", 1.0, "motor-locked frequency √(k/m)/2π",
                           50.0, 0.5, 1e4),
                _nonlinear("zeta", "-", 1.0, "damping ratio", 0.05, 1e-3, 1.0),
                Parameter("declared_f_n_Hz", "Hz", 1.0, "the declared mode's f_n (0: none)",
                          linear=False, setting=True)),
               requires=("structural_mode",)),
    CubicStiffening("cubic_stiffening",
                    "the structural spring stiffens with deflection k d (1 + κ d²)",
                    "residual at the mode, growing with the deflection's cube",
                    (Parameter("m_kg", "kg", 1.0, "mass on the spring", lower=0.0),
                     _nonlinear("kappa_per_um2", "1/µm²", 1e12, "stiffening κ", 1e8, 0.0,
                                1e13),
                     Parameter("f_n_Hz", "Hz", 1.0, "the structural mode's f_n", linear=False,
                               setting=True, default=50.0),
                     Parameter("zeta", "-", 1.0, "the structural mode's ζ", linear=False,
                               setting=True, default=0.05)),
                    requires=("structural_mode",)),
    Delay("delay", "force channel leads the motion by τ", "residual ∝ dF/dt",
          (_nonlinear("tau_ms", "ms", 1e-3, "lead of the force channel", 0.0, -0.02, 0.02),),
          kind="shift"),
    AmplitudeNonlinearity("amplitude_nonlinearity",
                          "force-level nonlinearity of the reading F (1 + β|F|)",
                          "residual ∝ F|F|",
                          (_nonlinear("beta_per_kN", "1/kN", 1e-3, "β", 0.0, -5e-3, 5e-3),),
                          kind="output"),
    SensorGain("sensor_gain", "force reading scaled by g", "residual ∝ F",
               (_nonlinear("gain", "-", 1.0, "force-reading gain g", 1.0, 0.2, 5.0),),
               kind="output"),
    Presliding("presliding",
               "pre-sliding hysteresis: Dahl / LuGre bristle friction F_p w(x) in place of "
               "F_p tanh(k_tanh v)",
               "residual after each reversal, following the displacement since it "
               "(hysteresis in force vs displacement)",
               (Parameter("F_p_N", "N", 1.0, "level of the bristle friction F_p", lower=0.0),
                Parameter("sigma1_Ns_m", "N·s/m", 1.0, "bristle damping σ1 (LuGre)", lower=0.0),
                _nonlinear("x_p_um", "µm", 1e-6, "pre-sliding displacement x_p = F_p/σ0",
                           5e-6, 1e-8, 1e-3),
                _nonlinear("alpha", "-", 1.0, "Dahl's exponent α", 1.0, 0.2, 5.0),
                _k_tanh_setting()),
               requires=("coulomb",), rivals=("backlash", "gms")),
    MaxwellSlip("gms",
                "pre-sliding hysteresis: generalized Maxwell-slip friction F_p w(x), Iwan's "
                "uniform blocks, in place of F_p tanh(k_tanh v)",
                "residual after each reversal, following the displacement since it, "
                "with non-local memory (Masing branches)",
                (Parameter("F_p_N", "N", 1.0, "level of the Maxwell-slip friction F_p",
                           lower=0.0),
                 Parameter("sigma1_Ns_m", "N·s/m", 1.0, "blocks' damping σ1", lower=0.0),
                 _nonlinear("x_p_um", "µm", 1e-6, "pre-sliding displacement x_p = F_p/σ0 "
                            "(full sliding at 2 x_p)", 5e-6, 1e-8, 1e-3),
                 _k_tanh_setting()),
                requires=("coulomb",), rivals=("backlash", "presliding")),
)
"""Every term, base terms first; the order breaks ties between equally good candidates."""

EFFECTS: dict[str, Effect] = {effect.name: effect for effect in LIBRARY}

CANDIDATES: tuple[str, ...] = tuple(e.name for e in LIBRARY if e.name != "inertia")
"""Effects the closure may add (everything but the rigid-body inertia)."""

RETIRED: dict[str, str] = {
    "inertia_mismatch": "a declared mass that is off is the recalibration of inertia.M_kg "
                        "(found whenever M_kg is declared)",
}
"""Effect names of earlier versions, with what took their place."""
