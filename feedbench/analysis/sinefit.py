"""Sine fits at a known frequency and the stepped-sine (sine-stream) FRF of Ch. 5.5.3.

Each frequency step holds a sine for a few cycles; a sine a·cos ωt + b·sin ωt + c is fitted by
linear least squares to the force and to the response after the settle cycles, and the FRF
point is the ratio of the two complex amplitudes. R² of each fit is the quality indicator the
thesis uses in place of coherence (Figs. 5.21, 5.22). R² says how much of the signal is not a
sine (noise, harmonics); it hardly sees a response still building up near a lightly damped
resonance, so each step also reports `drift`, the change of H between the first and the
second half of its fitted cycles.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np


@dataclass(frozen=True)
class SineFit:
    """signal ≈ amplitude·cos(2πf t + phase) + offset, t from the segment's first sample (s).

    `phasor` = amplitude·e^{j·phase}; `r_squared` = 1 − SS_residual / SS_total.
    """

    frequency: float
    amplitude: float
    phase: float
    offset: float
    r_squared: float

    @property
    def phasor(self) -> complex:
        return self.amplitude * np.exp(1j * self.phase)


@dataclass(frozen=True)
class SteppedSineFrf:
    """One FRF point per step: H = response phasor / force phasor (response unit per N).

    `r_squared` is the smaller R² of the force and response fits of each step; `drift` is
    |H_second_half − H_first_half| / |H| (0 in steady state).
    """

    f: np.ndarray
    H: np.ndarray
    force_amplitude: np.ndarray
    response_amplitude: np.ndarray
    r_squared_force: np.ndarray
    r_squared_response: np.ndarray
    drift: np.ndarray

    @property
    def r_squared(self) -> np.ndarray:
        return np.minimum(self.r_squared_force, self.r_squared_response)


def fit_sine(signal: np.ndarray, fs: float, f: float, settle_cycles: float = 0.0) -> SineFit:
    """Least-squares sine at the known frequency f (Hz) on samples at fs (Hz).

    The first `settle_cycles` periods are left out of the fit; the phase still refers to the
    first sample of `signal`, so fits of two signals over the same samples compare directly.
    """
    signal = np.asarray(signal, dtype=float)
    if f <= 0 or fs <= 0 or settle_cycles < 0:
        raise ValueError(
            f"f, fs, settle_cycles: need f > 0, fs > 0, settle_cycles >= 0, got {f}, {fs}, "
            f"{settle_cycles}"
        )
    first = int(np.ceil(settle_cycles * fs / f))
    if signal.size - first < 4:
        raise ValueError(
            f"signal: {signal.size} samples leave {signal.size - first} after "
            f"{settle_cycles} settle cycles"
        )
    t = np.arange(first, signal.size) / fs
    kept = signal[first:]
    basis = np.column_stack([np.cos(2 * np.pi * f * t), np.sin(2 * np.pi * f * t), np.ones_like(t)])
    (a, b, c), *_ = np.linalg.lstsq(basis, kept, rcond=None)
    residual = kept - basis @ (a, b, c)
    total = np.sum((kept - kept.mean()) ** 2)
    r_squared = 1.0 - np.sum(residual**2) / total if total > 0 else 0.0
    amplitude, phase = float(np.hypot(a, b)), float(np.arctan2(-b, a))
    return SineFit(float(f), amplitude, phase, float(c), float(r_squared))


def stepped_sine_frf(
    force: np.ndarray,
    response: np.ndarray,
    fs: float,
    steps: Iterable[tuple[float, int, int]],
    settle_cycles: float = 1.0,
) -> SteppedSineFrf:
    """FRF of a sine-stream test (Ch. 5.5.3): a sine fitted to force (N) and response per step.

    steps: (frequency Hz, start sample, stop sample) per step, stop exclusive; the first
    `settle_cycles` periods of each step are left out.
    """
    force, response = np.asarray(force, dtype=float), np.asarray(response, dtype=float)
    if force.shape != response.shape or force.ndim != 1:
        raise ValueError(
            f"force, response: need equal 1-D shapes, got {force.shape}, {response.shape}"
        )
    fits = [_fit_step(force, response, fs, f, start, stop, settle_cycles)
            for f, start, stop in steps]
    if not fits:
        raise ValueError("steps: empty")
    force_fits, response_fits, drifts = zip(*fits)
    return SteppedSineFrf(
        f=np.array([fit.frequency for fit in force_fits]),
        H=np.array([r.phasor / F.phasor for F, r in zip(force_fits, response_fits)]),
        force_amplitude=np.array([fit.amplitude for fit in force_fits]),
        response_amplitude=np.array([fit.amplitude for fit in response_fits]),
        r_squared_force=np.array([fit.r_squared for fit in force_fits]),
        r_squared_response=np.array([fit.r_squared for fit in response_fits]),
        drift=np.array(drifts),
    )


def sine_stream_steps(
    frequencies: np.ndarray, cycles: float, fs: float, start: int = 0
) -> list[tuple[float, int, int]]:
    """Step table of a sine stream holding each frequency (Hz) for `cycles` periods, back to back.

    Each step lasts round(cycles·fs/f) samples (the thesis: 20→80 Hz, 0.25 Hz steps, 5 cycles).
    """
    lengths = np.rint(cycles * fs / np.asarray(frequencies, dtype=float)).astype(int)
    stops = start + np.cumsum(lengths)
    return [(float(f), int(stop - n), int(stop)) for f, n, stop in zip(frequencies, lengths, stops)]


def _fit_step(force, response, fs, f, start, stop, settle_cycles) -> tuple[SineFit, SineFit, float]:
    """Force and response fits of one step, and the drift of H between the two halves."""
    first = start + int(np.ceil(settle_cycles * fs / f))
    if not 0 <= start < stop <= force.size or stop - first < 8:
        raise ValueError(
            f"steps: ({f}, {start}, {stop}) is outside the record or too short after settling"
        )
    middle = (first + stop) // 2
    halves = [
        fit_sine(response[a:b], fs, f).phasor / fit_sine(force[a:b], fs, f).phasor
        for a, b in ((first, middle), (middle, stop))
    ]
    mean = abs(0.5 * (halves[0] + halves[1]))
    drift = abs(halves[1] - halves[0]) / mean if mean > 0.0 else float("nan")
    return fit_sine(force[first:stop], fs, f), fit_sine(response[first:stop], fs, f), float(drift)
