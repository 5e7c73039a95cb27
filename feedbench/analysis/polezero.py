"""Multiplicative pole–zero model of the open-loop servo mobility with rigid body and delay,
Eq. (4.27), and its fit to a measured mobility ẋ_mot/F_mot.

The fit follows the thesis's order: rigid body from the low-frequency end, then resonances and
anti-resonances, then the delay from the phase; a joint least-squares refinement on the complex
logarithm (log-magnitude and phase error) finishes it.
"""

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy import optimize, signal

from feedbench.analysis.servo import ComplexArray, RealArray, laplace, with_delay

INITIAL_DAMPING = 0.05
"""Starting damping ratio for every picked resonance and anti-resonance."""


@dataclass(frozen=True)
class VibratoryMode:
    """One pole pair over one zero pair of Eq. (4.27); frequencies in Hz, damping ratios."""

    pole_frequency: float
    pole_damping: float
    zero_frequency: float
    zero_damping: float

    def factor(self, s: ComplexArray) -> ComplexArray:
        """(ω_p²/ω_z²)(s² + 2ζ_z ω_z s + ω_z²)/(s² + 2ζ_p ω_p s + ω_p²); 1 at s = 0."""
        w_p, w_z = 2 * np.pi * self.pole_frequency, 2 * np.pi * self.zero_frequency
        zeros = s**2 + 2 * self.zero_damping * w_z * s + w_z**2
        poles = s**2 + 2 * self.pole_damping * w_p * s + w_p**2
        return (w_p / w_z) ** 2 * zeros / poles

    def polynomials(self) -> tuple[RealArray, RealArray]:
        """Numerator and denominator coefficients of `factor` (highest power first)."""
        w_p, w_z = 2 * np.pi * self.pole_frequency, 2 * np.pi * self.zero_frequency
        scale = (w_p / w_z) ** 2
        return (
            scale * np.array([1.0, 2 * self.zero_damping * w_z, w_z**2]),
            np.array([1.0, 2 * self.pole_damping * w_p, w_p**2]),
        )


@dataclass(frozen=True)
class PoleZeroModel:
    """Eq. (4.27): e^{-τ_ol s}/(m_total s + σ) · Π modes. SI: kg, N·s/m, s."""

    m_total: float
    sigma: float
    delay: float
    modes: tuple[VibratoryMode, ...]

    def mobility(self, frequency: ArrayLike) -> ComplexArray:
        """Open-loop mobility ẋ_mot/F_mot in m/(N·s) at the given frequencies (Hz)."""
        s = laplace(frequency)
        response = np.exp(-self.delay * s) / (self.m_total * s + self.sigma)
        for mode in self.modes:
            response = response * mode.factor(s)
        return response

    def transfer_function(self, pade_order: int) -> signal.TransferFunction:
        """Rational mobility with the delay replaced by its Padé approximation, Eq. (4.16)."""
        numerator, denominator = np.array([1.0]), np.array([self.m_total, self.sigma])
        for mode in self.modes:
            mode_num, mode_den = mode.polynomials()
            numerator = np.polymul(numerator, mode_num)
            denominator = np.polymul(denominator, mode_den)
        return with_delay(signal.TransferFunction(numerator, denominator), self.delay, pade_order)


@dataclass(frozen=True)
class PoleZeroFit:
    """Fitted model and its RMS complex-log error (≈ relative magnitude and phase error)."""

    model: PoleZeroModel
    rms_log_error: float


def _pack(model: PoleZeroModel) -> RealArray:
    modes = [
        np.log([m.pole_frequency, m.pole_damping, m.zero_frequency, m.zero_damping])
        for m in model.modes
    ]
    return np.concatenate([[np.log(model.m_total), model.sigma, model.delay], *modes])


def _unpack(x: RealArray) -> PoleZeroModel:
    mode_values = np.exp(x[3:]).reshape(-1, 4)
    modes = tuple(VibratoryMode(*map(float, row)) for row in mode_values)
    return PoleZeroModel(
        m_total=float(np.exp(x[0])), sigma=float(x[1]), delay=float(x[2]), modes=modes
    )


def _rigid_body_guess(frequency: RealArray, mobility: ComplexArray) -> tuple[float, float]:
    """m_total and σ from 1/H ≈ σ + jω m over the lowest tenth of the band (at least 5 points)."""
    low = slice(0, max(5, frequency.size // 10))
    impedance = 1.0 / mobility[low]
    omega = 2 * np.pi * frequency[low]
    mass = float(np.sum(omega * impedance.imag) / np.sum(omega**2))
    return mass, max(float(np.mean(impedance.real)), 0.0)


def _pick(log_magnitude: RealArray, frequency: RealArray, count: int) -> RealArray:
    """Frequencies of the `count` most prominent peaks of a curve, ascending."""
    peaks, properties = signal.find_peaks(log_magnitude, prominence=0.0)
    if peaks.size < count:
        raise ValueError(f"found {peaks.size} peaks/dips in the mobility, {count} modes requested")
    strongest = peaks[np.argsort(properties["prominences"])[::-1][:count]]
    return np.sort(frequency[strongest])


def initial_model(frequency: ArrayLike, mobility: ArrayLike, n_modes: int) -> PoleZeroModel:
    """Starting point: rigid body from the low end, resonances as peaks and anti-resonances as
    dips of the mobility normalised by the rigid body, no delay."""
    f = np.asarray(frequency, dtype=float)
    h = np.asarray(mobility, dtype=complex)
    mass, sigma = _rigid_body_guess(f, h)
    log_vibratory = np.log(np.abs(h * (mass * laplace(f) + sigma)))
    poles, zeros = _pick(log_vibratory, f, n_modes), _pick(-log_vibratory, f, n_modes)
    modes = tuple(
        VibratoryMode(float(p), INITIAL_DAMPING, float(z), INITIAL_DAMPING)
        for p, z in zip(poles, zeros)
    )
    return PoleZeroModel(m_total=mass, sigma=sigma, delay=0.0, modes=modes)


def _bounds(n_modes: int) -> tuple[RealArray, RealArray]:
    per_mode_low, per_mode_high = [-np.inf, np.log(1e-4)] * 2, [np.inf, 0.0] * 2
    low = np.array([-np.inf, 0.0, 0.0, *per_mode_low * n_modes])
    high = np.array([np.inf, np.inf, np.inf, *per_mode_high * n_modes])
    return low, high


def _delay_from_phase(frequency: RealArray, ratio: ComplexArray) -> float:
    """Pure delay τ fitting the unwrapped phase of `ratio` as −ωτ (least squares through 0)."""
    omega = 2 * np.pi * frequency
    phase = np.unwrap(np.angle(ratio))
    return max(float(-np.sum(omega * phase) / np.sum(omega**2)), 0.0)


def _stack(error: ComplexArray) -> RealArray:
    return np.concatenate([error.real, error.imag])


def fit_pole_zero(
    frequency: ArrayLike, mobility: ArrayLike, n_modes: int, initial: PoleZeroModel | None = None
) -> PoleZeroFit:
    """Fit Eq. (4.27) with `n_modes` pole/zero pairs to a measured mobility ẋ_mot/F_mot.

    frequency in Hz (ascending, > 0), mobility in m/(N·s). `initial` overrides the automatic
    starting point (`initial_model`).
    """
    f = np.asarray(frequency, dtype=float)
    h = np.asarray(mobility, dtype=complex)
    start = initial if initial is not None else initial_model(f, h, n_modes)
    bounds = _bounds(len(start.modes))

    def log_error(x: RealArray) -> ComplexArray:
        return np.log(_unpack(x).mobility(f) / h)

    magnitude = optimize.least_squares(
        lambda x: log_error(x).real, _pack(start), bounds=bounds, x_scale="jac"
    )
    shaped = _unpack(magnitude.x)
    delay = _delay_from_phase(f, h / shaped.mobility(f) * np.exp(-shaped.delay * laplace(f)))
    x0 = np.concatenate([magnitude.x[:2], [delay], magnitude.x[3:]])
    joint = optimize.least_squares(
        lambda x: _stack(log_error(x)), x0, bounds=bounds, x_scale="jac"
    )
    rms = float(np.sqrt(np.mean(np.abs(log_error(joint.x)) ** 2)))
    return PoleZeroFit(model=_unpack(joint.x), rms_log_error=rms)
