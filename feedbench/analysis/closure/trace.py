"""A closed-loop axis recording in SI units, and the band-limited kinematics the inverse
model is fitted on.

Derivatives follow the IDIM practice (Gautier 1997; the EMPS benchmark): the position is
low-pass filtered with the zero-phase Butterworth response (order 4 forward and backward,
so no lag), then differentiated; the force goes through the same filter ("parallel
filtering"), so the measured and the predicted force share one band. Filter and
derivatives are applied together in the frequency domain (jω times |H|², on the signal
extended by its mirror image so that it is periodic without a jump): central differences lose
26 % of the acceleration at 0.15 fs, which biases the mass when the band reaches that
high; jω is exact in the band. The ends, where the mirror leaves a kink, are dropped.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import numpy as np
import scipy.fft

from feedbench.analysis.closure.units import axis_unit

FILTER_ORDER = 4
"""Order of the zero-phase Butterworth filter (applied twice by filtfilt: order 8 in gain)."""

EDGE_PERIODS = 3.0
"""Samples within this many filter periods (1 / bandwidth) of an end are dropped."""

UNIFORM_TOLERANCE = 0.01
"""Largest allowed deviation of a time step from the median step, as a fraction of it."""

SIGNALS = ("time", "position", "force", "reference", "excitation", "external_force",
           "tip_acceleration")
"""The sampled channels of a trace (the optional ones may be None)."""


@dataclass(frozen=True)
class Trace:
    """One closed-loop axis recording, uniformly sampled, SI units.

    time (s); position: motor position (m; rad for a rotary axis); force: motor force
    (N; N·m); reference: commanded position (m) or None; excitation: force added to the
    controller's output (N) or None, e.g. a chirp into the force offset or the EMPS pulses;
    force_lag: how far the force samples lag the position samples (s), e.g. half a cycle
    when each force sample is the force held over the cycle that ends at its time stamp;
    external_force: a known force the motor works against besides the model's terms (N;
    N·m), e.g. a robot joint's gravity and coupling torques, or None: the model explains
    force − external_force; tip_acceleration: acceleration of the load side (m/s²) or None;
    rotary: whether the axis turns (position in rad, force in N·m or the dataset's own force
    unit): the numbers are the same, the units the report names are the rotary ones
    (`units.axis_unit`).
    """

    time: np.ndarray
    position: np.ndarray
    force: np.ndarray
    reference: np.ndarray | None = None
    excitation: np.ndarray | None = None
    name: str = ""
    force_lag: float = 0.0
    external_force: np.ndarray | None = None
    tip_acceleration: np.ndarray | None = None
    rotary: bool = False

    def __post_init__(self) -> None:
        n = np.shape(self.time)[0] if np.ndim(self.time) == 1 else -1
        for field in SIGNALS:
            value = getattr(self, field)
            if value is None:
                continue
            array = np.asarray(value, dtype=float)
            if array.shape != (n,):
                raise ValueError(f"{field}: must be 1-D with {max(n, 0)} samples like time, "
                                 f"got shape {array.shape}")
            if not np.all(np.isfinite(array)):
                raise ValueError(f"{field}: contains NaN or inf")
            object.__setattr__(self, field, array)
        if n < 16:
            raise ValueError(f"time: need at least 16 samples, got {max(n, 0)}")
        steps = np.diff(self.time)
        step = float(np.median(steps))
        if not step > 0.0 or np.max(np.abs(steps - step)) > UNIFORM_TOLERANCE * step:
            raise ValueError("time: samples must be uniformly spaced and increasing")

    @property
    def sample_rate(self) -> float:
        """Sample rate (Hz)."""
        return float((self.time.size - 1) / (self.time[-1] - self.time[0]))

    @property
    def n_samples(self) -> int:
        """Number of samples."""
        return int(self.time.size)

    def window(self, start: int, stop: int) -> Trace:
        """Samples [start, stop) as a trace of their own."""
        def cut(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[start:stop]

        return replace(self, **{field: cut(getattr(self, field)) for field in SIGNALS})


@dataclass(frozen=True)
class Kinematics:
    """Band-limited signals of one trace, edges trimmed.

    x (m), v (m/s), a (m/s²): filtered motor position and its derivatives; force: the
    filtered measured force less the trace's known external force (N); used: samples that
    fits and errors count (the axis moving faster than the standstill speed: in stiction
    the friction force is a constraint force no friction law predicts); dt: sample period
    (s); bandwidth: cut-off (Hz); tip: the filtered load-side acceleration (m/s²) or None;
    rotary: the trace's (rad and N·m for m and N).
    """

    x: np.ndarray
    v: np.ndarray
    a: np.ndarray
    force: np.ndarray
    used: np.ndarray
    dt: float
    bandwidth: float
    tip: np.ndarray | None = None
    rotary: bool = False

    @property
    def rows(self) -> np.ndarray:
        """Indices of the samples used."""
        return np.flatnonzero(self.used)

    @property
    def n(self) -> int:
        """Number of samples (all, used or not)."""
        return int(self.x.size)

    @property
    def n_used(self) -> int:
        """Number of samples used."""
        return int(np.count_nonzero(self.used))

    @property
    def effective_n(self) -> float:
        """Independent samples among those used, for a signal limited to `bandwidth`:
        n_used · 2B/fs (≤ n_used)."""
        return self.n_used * min(1.0, 2.0 * self.bandwidth * self.dt)

    def window(self, start: int, stop: int) -> Kinematics:
        """Samples [start, stop)."""
        return replace(self, x=self.x[start:stop], v=self.v[start:stop], a=self.a[start:stop],
                       force=self.force[start:stop], used=self.used[start:stop],
                       tip=None if self.tip is None else self.tip[start:stop])


def lowpass(signal: np.ndarray, bandwidth: float, dt: float, derivative: int = 0,
            lead: float = 0.0) -> np.ndarray:
    """Zero-phase Butterworth low-pass (|H|² of order FILTER_ORDER, as forward-backward
    filtering), differentiated `derivative` times and advanced by `lead` seconds."""
    return lowpass_derivatives(signal, bandwidth, dt, (derivative,), lead)[0]


def lowpass_derivatives(signal: np.ndarray, bandwidth: float, dt: float,
                        orders: tuple[int, ...], lead: float = 0.0) -> list[np.ndarray]:
    """`lowpass` for several derivative orders from one forward transform.

    Applied in the frequency domain to the signal followed by its last value held and its
    mirror image (periodic without a jump; the hold pads to a fast FFT length).
    """
    n = signal.size
    length = scipy.fft.next_fast_len(2 * n, real=True)
    extended = np.concatenate([signal, np.full(length - 2 * n, signal[-1]), signal[::-1]])
    shift, gain, derivatives = _filter_factors(length, dt, bandwidth, float(lead).hex(), orders)
    spectrum = scipy.fft.rfft(extended) * shift
    spectrum /= gain
    return [scipy.fft.irfft(spectrum * d, length)[:n] for d in derivatives]


@functools.lru_cache(maxsize=16)
def _filter_factors(length: int, dt: float, bandwidth: float, lead: str, orders: tuple[int, ...]
                    ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, ...]]:
    """The factors `lowpass_derivatives` applies to a spectrum of `length` samples taken
    every dt (s), computed once per closure's filter: the lead's e^{jωτ} (`lead`: τ in s as
    `float.hex`, so that -0.0 and 0.0 stay apart), the filter's 1 + (f/B)^(2·FILTER_ORDER)
    (B in Hz) it divides by, and (jω)^order per derivative order. Read-only."""
    f = frequencies(length, dt)
    jw = 2j * np.pi * f
    return (read_only(np.exp(2j * np.pi * f * float.fromhex(lead))),
            read_only(1.0 + (f / bandwidth) ** (2 * FILTER_ORDER)),
            tuple(read_only(jw**order) for order in orders))


@functools.lru_cache(maxsize=16)
def frequencies(length: int, dt: float) -> np.ndarray:
    """`scipy.fft.rfftfreq(length, dt)` (Hz, dt in s), read-only, computed once per length."""
    return read_only(scipy.fft.rfftfreq(length, dt))


def read_only(array: np.ndarray) -> np.ndarray:
    """`array`, made read-only (a cached value that no caller may change), returned."""
    array.flags.writeable = False
    return array


def edge_samples(bandwidth: float, dt: float) -> int:
    """Samples dropped at each end, where the filter's start-up transient lives."""
    return int(np.ceil(EDGE_PERIODS / (bandwidth * dt)))


def kinematics(trace: Trace, bandwidth: float, standstill: float = 0.0) -> Kinematics:
    """Filtered position, velocity, acceleration and force of `trace`, edges trimmed.

    bandwidth: cut-off (Hz) of the zero-phase filter, below the Nyquist frequency;
    standstill: speed (m/s) below which a sample is not used.
    """
    dt = 1.0 / trace.sample_rate
    if not 0.0 < bandwidth < 0.5 / dt:
        raise ValueError(f"bandwidth must lie in (0, {0.5 / dt:g}) Hz, got {bandwidth}")
    x, v, a = lowpass_derivatives(trace.position, bandwidth, dt, (0, 1, 2))
    force = lowpass(trace.force, bandwidth, dt, lead=trace.force_lag)
    if trace.external_force is not None:
        force = force - lowpass(trace.external_force, bandwidth, dt)
    edge = edge_samples(bandwidth, dt)
    if trace.n_samples <= 4 * edge:
        raise ValueError(f"{trace.name or 'trace'}: {trace.n_samples} samples are too few for "
                         f"a {bandwidth:g} Hz filter (need > {4 * edge})")
    tip = (None if trace.tip_acceleration is None
           else lowpass(trace.tip_acceleration, bandwidth, dt))
    kin = Kinematics(x, v, a, force, np.abs(v) >= standstill, dt, bandwidth, tip,
                     trace.rotary)
    kin = kin.window(edge, trace.n_samples - edge)
    if kin.n_used < 16:
        raise ValueError(f"{trace.name or 'trace'}: only {kin.n_used} samples move faster "
                         f"than the standstill speed {standstill:g} "
                         f"{axis_unit('m/s', trace.rotary)}")
    return kin


def standstill_speed(kin: Kinematics, fraction: float) -> float:
    """`fraction` of the 95th-percentile speed (m/s): the default standstill threshold."""
    return fraction * float(np.quantile(np.abs(kin.v), 0.95))


def nrmse(measured: np.ndarray, predicted: np.ndarray) -> float:
    """Normalised RMS error ‖y − ŷ‖ / ‖y‖ (the EMPS benchmark's relative error), as a fraction."""
    return float(np.linalg.norm(measured - predicted) / np.linalg.norm(measured))
