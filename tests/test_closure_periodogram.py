"""The ripple's periodogram (`effects.lomb_scargle`, extirpolation and an FFT) against the
direct sums of `scipy.signal.lombscargle`, on a residual the way `Ripple.starts` sees it:
positions of a back-and-forth motion (repeats, any order), a ripple under noise."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal

from feedbench.analysis.closure.effects import lomb_scargle

STROKE_M = 0.03
SHORTEST_PITCH_M = 40e-6
TOLERANCE = 1e-8
"""Largest difference from scipy's power, as a share of the largest power (the helper's
error budget, `effects.MESH_PER_WAVENUMBER`, is ≈ 10⁻⁹ of a sample's weight)."""


def _residual(pitch: float, amplitude: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Positions (m) of 4 s of two superposed strokes at 1 kHz and a centred residual (N):
    a ripple of `amplitude` (N) at `pitch` (m) under white noise of 1 N."""
    rng = np.random.default_rng(seed)
    t = np.arange(4000) * 1e-3
    x = 0.05 + STROKE_M / 3 * (np.sin(2 * np.pi * 0.7 * t) + 0.5 * np.sin(2 * np.pi * 1.9 * t))
    y = amplitude * np.sin(2 * np.pi * x / pitch + 0.4) + rng.normal(0.0, 1.0, t.size)
    return x, y - y.mean()


@pytest.mark.parametrize("pitch, amplitude", [(5e-3, 0.3), (45e-6, 0.3), (1e-3, 0.05)])
def test_lomb_scargle_matches_the_direct_sums(pitch, amplitude):
    x, y = _residual(pitch, amplitude, seed=3)
    stroke = float(np.ptp(x))
    step = np.pi / stroke
    wavenumbers = np.arange(4 * np.pi / stroke + 0.3 * step, 2 * np.pi / SHORTEST_PITCH_M, step)
    direct = scipy.signal.lombscargle(x, y, wavenumbers)
    fast = lomb_scargle(x, y, wavenumbers[0], step, wavenumbers.size)
    assert np.max(np.abs(fast - direct)) <= TOLERANCE * np.max(direct)
    peaks = scipy.signal.find_peaks(direct)[0]
    assert np.array_equal(scipy.signal.find_peaks(fast)[0], peaks)
    best = peaks[np.argsort(direct[peaks])[::-1][:3]]
    assert np.array_equal(best, peaks[np.argsort(fast[peaks])[::-1][:3]])
    if amplitude >= 0.3:
        assert abs(wavenumbers[best[0]] - 2 * np.pi / pitch) <= step
