"""FRF estimation: H1/H2/coherence against scipy and ground truth, leakage, hammer quasi-FRF
(Eq. 5.3), FRF forms."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import scipy.signal

from feedbench.analysis.frf import (
    accelerance_to_receptance,
    convert_frf,
    estimate_frf,
    mobility_to_receptance,
    quasi_frf,
    receptance_to_accelerance,
    receptance_to_mobility,
    welch_lag_window,
    welch_spectra,
)
from feedbench.models.axis import TwoMassAxis
from feedbench.experiments.chirp import mobility_extrema

# The lab-bench flexure with the motor held (DIGEST §3): 11.3 kg on 1.68 N/µm, c = 104 N·s/m.
BENCH = TwoMassAxis()
M_TIP, K_FLEX, C_FLEX = BENCH.m_tip, BENCH.k, BENCH.c


def sdof_filter(m: float, k: float, c: float, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """Discrete (bilinear) receptance 1/(m s² + c s + k) in m/N; its freqz is the truth."""
    return scipy.signal.bilinear([1.0], [m, c, k], fs)


def discrete_response(b, a, f, fs, decay_rate=0.0):
    """H(z) at z = exp(j2πf/fs + decay_rate/fs): the filter seen through exp(−decay_rate·t)."""
    z = np.exp(2j * np.pi * np.asarray(f) / fs + decay_rate / fs)
    return np.polyval(b[::-1], 1 / z) / np.polyval(a[::-1], 1 / z)


@pytest.fixture(scope="module")
def random_test():
    """White force (N) into the flexure, displacement (m) with 1 % output noise, fs = 1 kHz."""
    rng = np.random.default_rng(7)
    fs = 1000.0
    force = 20.0 * rng.standard_normal(2**17)
    b, a = sdof_filter(M_TIP, K_FLEX, C_FLEX, fs)
    displacement = scipy.signal.lfilter(b, a, force)
    noisy = displacement + 0.01 * displacement.std() * rng.standard_normal(force.size)
    return fs, force, noisy, (b, a)


def test_h1_h2_coherence_match_scipy_welch_and_csd(random_test):
    fs, x, y, _ = random_test
    for nperseg, overlap, window in ((1024, 0.5, "hann"), (1001, 0.75, "hamming")):
        noverlap = int(round(overlap * nperseg))
        est = estimate_frf(x, np.stack([y, 3.0 * y + x]), fs, nperseg, overlap, window)
        _, Pxx = scipy.signal.welch(x, fs, window, nperseg, noverlap)
        for channel, out in enumerate((y, 3.0 * y + x)):
            _, Pyy = scipy.signal.welch(out, fs, window, nperseg, noverlap)
            _, Pxy = scipy.signal.csd(x, out, fs, window, nperseg, noverlap)
            np.testing.assert_allclose(est.H1[channel], Pxy / Pxx, rtol=1e-9)
            np.testing.assert_allclose(est.H2[channel], Pyy / Pxy.conj(), rtol=1e-9)
            coherence = np.abs(Pxy) ** 2 / (Pxx * Pyy)
            np.testing.assert_allclose(est.coherence[channel], coherence, rtol=1e-9)
        assert est.n_averages == (x.size - noverlap) // (nperseg - noverlap)


def test_spectra_are_scaled_as_scipy(random_test):
    fs, x, y, _ = random_test
    spectra = welch_spectra(x, y, fs, 512)
    f, Pxx = scipy.signal.welch(x, fs, nperseg=512)
    _, Pxy = scipy.signal.csd(x, y, fs, nperseg=512)
    np.testing.assert_allclose(spectra.f, f)
    np.testing.assert_allclose(spectra.Sxx, Pxx, rtol=1e-10)
    np.testing.assert_allclose(spectra.Sxy, Pxy, rtol=1e-9)
    # white force of σ = 20 N: one-sided density 2σ²/fs = 0.8 N²/Hz
    assert np.median(spectra.Sxx[10:-10]) == pytest.approx(2 * 20.0**2 / fs, rel=0.03)


def test_h1_matches_truth_with_output_noise_and_is_low_with_input_noise(random_test):
    fs, x, y, (b, a) = random_test
    est = estimate_frf(x, y, fs, 2048)
    truth = discrete_response(b, a, est.f, fs)
    # away from the 61 Hz resonance, where leakage (3 bins half-power) would bias H1 too
    band = (est.f > 20) & (est.f < 150) & (np.abs(est.f - 61.3) > 5.0)
    ratio = est.H1[band] / truth[band]
    assert np.median(np.abs(ratio)) == pytest.approx(1.0, abs=0.005)
    assert np.max(np.abs(ratio - 1)) < 0.05
    # input noise of variance 1/4 of the force: H1 → H/(1 + 1/4) = 0.8 H, H2 unbiased
    noisy_force = x + 0.5 * x.std() * np.random.default_rng(3).standard_normal(x.size)
    est = estimate_frf(noisy_force, y, fs, 2048)
    assert np.median(np.abs(est.H1[band] / truth[band])) == pytest.approx(0.8, abs=0.01)
    assert np.median(np.abs(est.H2[band] / truth[band])) == pytest.approx(1.0, abs=0.02)


def test_leakage_at_lightly_damped_mode_is_flagged_and_h2_offered():
    """2 % mode at 100 Hz, 2 Hz resolution: H1 ≈ 0.8 of the truth at the peak (STACKS.md: 0.83)."""
    fs, rng = 1024.0, np.random.default_rng(1)
    m, k = 1.0, (2 * np.pi * 100.0) ** 2
    b, a = sdof_filter(m, k, 2 * 0.02 * np.sqrt(k * m), fs)
    x = rng.standard_normal(2**18)
    y = scipy.signal.lfilter(b, a, x)
    leaky = estimate_frf(x, y, fs, nperseg=512)
    truth = discrete_response(b, a, leaky.f, fs)
    peak = np.argmax(np.abs(truth))
    assert 0.7 < abs(leaky.H1[peak] / truth[peak]) < 0.9
    h1_error, h2_error = (abs(abs(H[peak] / truth[peak]) - 1) for H in (leaky.H1, leaky.H2))
    assert h2_error < 0.1 and h2_error < h1_error / 2
    assert leaky.leakage_suspected and leaky.leaky_peaks[0] == pytest.approx(leaky.f[peak], abs=2.0)
    assert "leakage" in leaky.warnings[0] and "H2" in leaky.warnings[0]
    assert leaky.preferred is leaky.H2
    fine = estimate_frf(x, y, fs, nperseg=8192)
    assert not fine.warnings and fine.preferred is fine.H1


def test_welch_lag_window_is_the_normalised_window_autocorrelation():
    n = 64
    v = welch_lag_window("hann", n)
    w = scipy.signal.get_window("hann", n)
    expected = [np.dot(w[: n - lag], w[lag:]) / np.dot(w, w) for lag in range(n)]
    np.testing.assert_allclose(v, expected, atol=1e-12)
    assert v[0] == pytest.approx(1.0) and np.all(np.diff(v) <= 1e-12)


def hammer_record(fs, n, t_hit, peak, width=1e-3):
    """Half-sine hammer pulse (N) of `width` s starting at t_hit."""
    t = np.arange(n) / fs
    inside = (t >= t_hit) & (t < t_hit + width)
    pulse = np.zeros(n)
    pulse[inside] = peak * np.sin(np.pi * (t[inside] - t_hit) / width)
    return pulse


def test_quasi_frf_of_four_hits_matches_exponentially_windowed_truth():
    """Eq. (5.3) on 4 impacts (Ch. 5.5.1) of 25 N on the flexure; τ = 0.5 s exponential window."""
    fs, n, tau = 5000.0, 10000, 0.5
    b, a = sdof_filter(M_TIP, K_FLEX, C_FLEX, fs)
    rng = np.random.default_rng(5)
    forces = np.stack([hammer_record(fs, n, 0.1 + 0.01 * i, 25.0 + i) for i in range(4)])
    responses = scipy.signal.lfilter(b, a, forces, axis=-1)
    responses += 2e-3 * np.abs(responses).max() * rng.standard_normal(responses.shape)
    forces += 0.05 * rng.standard_normal(forces.shape)
    result = quasi_frf(forces, responses, fs, force_window_s=0.005, exp_decay=tau)
    est = result.estimate
    assert result.used_hits == (0, 1, 2, 3) and est.n_averages == 4 and not est.warnings
    assert result.window_decay_rate == pytest.approx(1 / tau)
    windowed_truth = discrete_response(b, a, est.f, fs, decay_rate=1 / tau)
    band = (est.f > 30) & (est.f < 120)
    assert np.max(np.abs(est.H1[band] / windowed_truth[band] - 1)) < 0.03
    peak = np.argmax(np.abs(windowed_truth))
    assert est.coherence[peak] > 0.99
    assert est.f[np.argmax(np.abs(est.H1))] == pytest.approx(BENCH.f_t, abs=0.5)  # Eq. (4.13)


def test_double_hit_and_overload_are_flagged_and_left_out():
    fs, n = 5000.0, 5000
    b, a = sdof_filter(M_TIP, K_FLEX, C_FLEX, fs)
    clean = hammer_record(fs, n, 0.1, 30.0)
    double = clean + hammer_record(fs, n, 0.13, 12.0)
    clipped = np.minimum(hammer_record(fs, n, 0.1, 100.0, width=2e-3), 50.0)
    forces = np.stack([clean, double, clipped, 0.9 * clean])
    responses = scipy.signal.lfilter(b, a, forces, axis=-1)
    result = quasi_frf(forces, responses, fs, force_window_s=0.005, exp_decay=0.5)
    flags = [(h.double_hit, h.overload) for h in result.hits]
    assert flags == [(False, False), (True, False), (False, True), (False, False)]
    assert result.used_hits == (0, 3)
    assert result.hits[0].trigger_time == pytest.approx(0.1, abs=2 / fs)
    assert result.hits[0].peak_force == pytest.approx(clean.max())
    assert any("double hit" in w for w in result.estimate.warnings)
    assert any("force overload" in w for w in result.estimate.warnings)
    at_range = quasi_frf(clean, responses[0], fs, 0.005, 0.5, force_range=1.01 * clean.max(),
                         reject_flagged=False)
    assert at_range.hits[0].overload and at_range.used_hits == (0,)
    assert "kept" in at_range.estimate.warnings[0]
    with pytest.raises(ValueError, match="all 2 hits are flagged"):
        quasi_frf(forces[1:3], responses[1:3], fs, 0.005, 0.5)


def test_frf_forms_of_a_single_mode():
    """Mobility is 1/c at resonance; accelerance tends to 1/m (a = F/m) far above it."""
    f_n = np.sqrt(K_FLEX / M_TIP) / (2 * np.pi)
    f = np.array([0.0, 10.0, f_n, 50 * f_n])
    w = 2 * np.pi * f
    receptance = 1.0 / (K_FLEX - M_TIP * w**2 + 1j * C_FLEX * w)
    mobility = receptance_to_mobility(f, receptance)
    accelerance = receptance_to_accelerance(f, receptance)
    assert mobility[2] == pytest.approx(1.0 / C_FLEX)
    assert accelerance[3] == pytest.approx(1.0 / M_TIP, rel=1e-3)
    np.testing.assert_allclose(mobility_to_receptance(f[1:], mobility[1:]), receptance[1:])
    np.testing.assert_allclose(accelerance_to_receptance(f[1:], accelerance[1:]), receptance[1:])
    np.testing.assert_allclose(convert_frf(f, mobility, "mobility", "accelerance"), accelerance)
    with pytest.raises(ValueError, match="form"):
        convert_frf(f, receptance, "receptance", "compliance")


def test_bad_input_names_the_field():
    x = np.zeros(100)
    with pytest.raises(ValueError, match="nperseg"):
        estimate_frf(x, x, 100.0, nperseg=200)
    with pytest.raises(ValueError, match="y"):
        estimate_frf(x, np.zeros(99), 100.0, nperseg=50)
    with pytest.raises(ValueError, match="overlap"):
        estimate_frf(x, x, 100.0, nperseg=50, overlap=1.0)


def test_mobility_extrema_take_a_silent_bin_as_the_smallest_magnitude_without_a_warning():
    """A live estimate's first windows can hold |H| = 0 bins: the anti-resonance search
    takes them as the smallest magnitude (as -inf dB would), and numpy warns nothing."""
    f = np.arange(0.0, 101.0)
    H = 1.0 / np.abs(1.0 - (f / 60.0) ** 2 + 0.05j * f / 60.0)  # resonance at 60 Hz
    H[30] = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        f_t, f_r = mobility_extrema(f, H, (20.0, 90.0))
    assert abs(f_t - 30.0) < 0.01
    assert abs(f_r - 60.0) < 0.5
