"""Frequency response functions from recorded force and response arrays.

- H1, H2 and ordinary coherence with Welch averaging (Ewins; the thesis's shaker and chirp
  FRFs, Ch. 3.5.1),
- the quasi-FRF of hammer records, Eq. (5.3): Φ = S_xF / S_FF (Ch. 5.3.1),
- conversions between receptance, mobility and accelerance.

Spectra use scipy.signal.csd's conventions (one-sided density, constant detrend per
segment, periodic window) so that results agree with scipy to rounding. Leakage at a lightly
damped resonance biases H1 low (H1/H2 = coherence there); `estimate_frf` says so in
`warnings`, offers H2 for the peak magnitude (`FrfEstimate.preferred`) and the Welch lag window
(`FrfEstimate.lag_window`) with which `modal.fit_modes` fits H1 without the bias.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy
from numpy.lib.stride_tricks import sliding_window_view

FRF_FORMS = ("receptance", "mobility", "accelerance")
"""FRF forms, ordered by the power of jω that converts receptance into them."""

LEAKAGE_BANDWIDTH_BINS = 8.0
"""A resonance whose half-power bandwidth spans fewer bins than this is at risk of leakage."""

LEAKAGE_COHERENCE_DIP = 0.02
"""Coherence drop at a peak, against its neighbourhood, that reveals leakage (or nonlinearity)."""

_NEIGHBOURHOOD_BINS = 12
"""Bins each side of a peak whose median coherence is the reference for a dip."""


@dataclass(frozen=True)
class Spectra:
    """Welch auto- and cross-spectral densities, scaled as scipy.signal.csd.

    `Sxx` (units²/Hz) of the input; `Syy`, `Sxy` = csd(x, y) of each output, shape (n_f,) for
    one output or (n_outputs, n_f).
    """

    f: np.ndarray
    Sxx: np.ndarray
    Syy: np.ndarray
    Sxy: np.ndarray
    n_averages: int
    nperseg: int


@dataclass(frozen=True)
class Leak:
    """A resonance whose H1 leakage biases low: its frequency (Hz), half-power bandwidth
    (frequency bins), the lowest coherence within ±1 bin of it, and the segment length
    (samples) that would resolve it with `LEAKAGE_BANDWIDTH_BINS` bins."""

    f_hz: float
    bandwidth_bins: float
    coherence: float
    nperseg_needed: int

    @property
    def text(self) -> str:
        """The finding in one sentence, with what to do about it."""
        return (
            f"leakage: the resonance near {self.f_hz:.2f} Hz is {self.bandwidth_bins:.1f} "
            f"frequency bins wide (half power) and coherence dips to {self.coherence:.2f} there, "
            f"so H1 is biased low (H1/H2 = coherence): read the peak from H2 "
            f"(FrfEstimate.preferred), fit modes to H1 with lag_window=FrfEstimate.lag_window, "
            f"or use nperseg >= {self.nperseg_needed}"
        )


@dataclass(frozen=True)
class FrfEstimate:
    """FRF estimates y/x at frequencies `f` (Hz), shape (n_f,) or (n_outputs, n_f).

    H1 = S_xy / S_xx (Eq. 5.3), H2 = S_yy / S_yx, coherence = |S_xy|² / (S_xx S_yy).
    `leaks` are the resonances where leakage biases H1 (each also a line of `warnings`);
    `window` is the Welch segment window (None for transient records such as hammer hits).
    """

    f: np.ndarray
    H1: np.ndarray
    H2: np.ndarray
    coherence: np.ndarray
    n_averages: int
    nperseg: int
    warnings: tuple[str, ...] = ()
    leaks: tuple[Leak, ...] = ()
    window: str | None = None

    @property
    def leaky_peaks(self) -> tuple[float, ...]:
        """Frequencies (Hz) of the leakage-biased resonances, ascending."""
        return tuple(sorted({leak.f_hz for leak in self.leaks}))

    @property
    def leakage_suspected(self) -> bool:
        """True when at least one resonance is too narrow for the frequency resolution."""
        return bool(self.leaky_peaks)

    @property
    def preferred(self) -> np.ndarray:
        """H2 where leakage was detected (its peak magnitude is not biased low), else H1."""
        return self.H2 if self.leakage_suspected else self.H1

    @property
    def lag_window(self) -> np.ndarray | None:
        """Lag window of the Welch averaging (for modal.fit_modes on H1), None if not Welch."""
        return None if self.window is None else welch_lag_window(self.window, self.nperseg)


@dataclass(frozen=True)
class HitCheck:
    """Quality flags of one hammer hit: peak force (N), trigger time (s), and why it was dropped."""

    index: int
    trigger_time: float
    peak_force: float
    double_hit: bool
    overload: bool

    @property
    def ok(self) -> bool:
        return not (self.double_hit or self.overload)

    @property
    def reason(self) -> str:
        """Why the hit is flagged: ``double hit``, ``force overload``, both, or ""."""
        flags = (("double hit", self.double_hit), ("force overload", self.overload))
        return " and ".join(name for name, flag in flags if flag)


@dataclass(frozen=True)
class HammerFrf:
    """Quasi-FRF of hammer hits, Eq. (5.3), with the per-hit checks.

    The exponential window adds `window_decay_rate` (1/s) to every mode's decay rate:
    λ_true = λ_fit + window_decay_rate (see `modal.remove_window_decay`).
    """

    estimate: FrfEstimate
    hits: tuple[HitCheck, ...]
    used_hits: tuple[int, ...]
    window_decay_rate: float


def welch_spectra(
    x: np.ndarray,
    y: np.ndarray,
    fs: float,
    nperseg: int,
    overlap: float = 0.5,
    window: str = "hann",
) -> Spectra:
    """Welch spectra of input `x` and output(s) `y` (channels × samples), each FFT once.

    Hand-written because scipy.signal.csd recomputes the input's segment FFTs for every call.
    """
    squeeze = _squeezer(y)
    x, y = _validated_signals(x, y, nperseg, overlap)
    step = nperseg - int(round(overlap * nperseg))
    win = scipy.signal.get_window(window, nperseg)
    X = _segment_spectra(x[None], win, step)[0]
    Y = _segment_spectra(y, win, step)
    Sxx, Syy, Sxy = _averaged_spectra(X, Y)
    scale = _density_scale(fs, win)
    f = scipy.fft.rfftfreq(nperseg, 1.0 / fs)
    return Spectra(
        f=f,
        Sxx=Sxx * scale,
        Syy=squeeze(Syy * scale),
        Sxy=squeeze(Sxy * scale),
        n_averages=X.shape[0],
        nperseg=nperseg,
    )


def estimate_frf(
    x: np.ndarray,
    y: np.ndarray,
    fs: float,
    nperseg: int,
    overlap: float = 0.5,
    window: str = "hann",
) -> FrfEstimate:
    """H1, H2 and coherence of y/x with Welch averaging; flags leakage-biased resonances.

    x: input (force, N), 1-D; y: output(s), 1-D or channels × samples; fs in Hz.
    """
    spectra = welch_spectra(x, y, fs, nperseg, overlap, window)
    H1, H2, coherence = _frf_from_spectra(spectra.Sxx, spectra.Syy, spectra.Sxy)
    estimate = FrfEstimate(spectra.f, H1, H2, coherence, spectra.n_averages, nperseg, window=window)
    return _with_leakage_check(estimate)


def quasi_frf(
    force: np.ndarray,
    response: np.ndarray,
    fs: float,
    force_window_s: float,
    exp_decay: float,
    *,
    pretrigger_s: float = 0.002,
    trigger_level: float = 0.1,
    double_hit_level: float = 0.1,
    force_range: float | None = None,
    reject_flagged: bool = True,
) -> HammerFrf:
    """Quasi-FRF Φ = S_xF / S_FF of hammer records, Eq. (5.3), averaged over hits.

    force, response: one record (1-D) or one row per hit (hits × samples), N and the response
    unit. Each hit is found where force first exceeds `trigger_level` × its peak. Force window:
    force kept from `pretrigger_s` before the trigger to `force_window_s` after it, zero
    elsewhere. Response window: exp(−(t − t_trigger)/`exp_decay`) (τ in s) after the trigger.
    A hit is flagged as double when the force, after falling below `double_hit_level` × peak,
    rises above it again; as overload when its peak reaches 0.98 × `force_range` (N) or the
    signal clips (the peak value held for ≥ 3 samples). Flagged hits are left out of the
    average unless `reject_flagged` is False.
    """
    forces, responses = _hit_records(force, response)
    if force_window_s <= 0 or exp_decay <= 0:
        raise ValueError("force_window_s and exp_decay must be > 0 s")
    checks = tuple(
        _check_hit(i, record, fs, trigger_level, double_hit_level, force_range)
        for i, record in enumerate(forces)
    )
    used = tuple(c for c in checks if c.ok or not reject_flagged)
    if not used:
        raise ValueError(f"force: all {len(checks)} hits are flagged (double hit or overload)")
    force_span = (pretrigger_s, force_window_s)
    X, Y = _windowed_hit_spectra(forces, responses, used, fs, force_span, exp_decay)
    Sxx, Syy, Sxy = _averaged_spectra(X, Y[None])
    H1, H2, coherence = _frf_from_spectra(Sxx, Syy[0], Sxy[0])
    f = scipy.fft.rfftfreq(forces.shape[1], 1.0 / fs)
    warnings = tuple(_hit_warning(c, reject_flagged) for c in checks if not c.ok)
    estimate = FrfEstimate(f, H1, H2, coherence, len(used), forces.shape[1], warnings)
    return HammerFrf(estimate, checks, tuple(c.index for c in used), 1.0 / exp_decay)


def convert_frf(f: np.ndarray, H: np.ndarray, source: str, target: str) -> np.ndarray:
    """Convert an FRF between receptance (m/N), mobility (m/(N·s)) and accelerance (m/(N·s²)).

    Multiplies by (jω)^k, k = index(target) − index(source) in FRF_FORMS; ω = 2πf. Division at
    f = 0 gives inf/nan there.
    """
    power = _form_index(target) - _form_index(source)
    jw = 2j * np.pi * np.asarray(f, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray(H) * jw**power


def receptance_to_mobility(f: np.ndarray, H: np.ndarray) -> np.ndarray:
    """Receptance x/F → mobility v/F = jω · x/F."""
    return convert_frf(f, H, "receptance", "mobility")


def receptance_to_accelerance(f: np.ndarray, H: np.ndarray) -> np.ndarray:
    """Receptance x/F → accelerance a/F = (jω)² · x/F."""
    return convert_frf(f, H, "receptance", "accelerance")


def mobility_to_receptance(f: np.ndarray, H: np.ndarray) -> np.ndarray:
    """Mobility v/F → receptance x/F = v/F / (jω)."""
    return convert_frf(f, H, "mobility", "receptance")


def accelerance_to_receptance(f: np.ndarray, H: np.ndarray) -> np.ndarray:
    """Accelerance a/F → receptance x/F = a/F / (jω)²."""
    return convert_frf(f, H, "accelerance", "receptance")


def welch_lag_window(window: str, nperseg: int) -> np.ndarray:
    """Lag window v(τ) = Σ_n w(n) w(n + τ) / Σ w², τ = 0..nperseg − 1, of Welch averaging.

    With an input spectrum smooth over the window's main lobe, E[H1](f_k) = Σ_τ v(τ) h(τ)
    e^{−j2πkτ/nperseg}: leakage multiplies the impulse response h by v (modal.fit_modes
    uses this to fit H1 without the leakage bias).
    """
    win = scipy.signal.get_window(window, nperseg)
    autocorrelation = scipy.fft.irfft(np.abs(scipy.fft.rfft(win, 2 * nperseg)) ** 2, 2 * nperseg)
    return autocorrelation[:nperseg] / np.sum(win * win)


def leakage_suspected(
    f: np.ndarray, coherence: np.ndarray, f_peak: float, half_power_bandwidth: float
) -> bool:
    """True when a resonance (Hz) is narrower than LEAKAGE_BANDWIDTH_BINS bins and the
    coherence dips at it by more than LEAKAGE_COHERENCE_DIP against its neighbourhood."""
    df = f[1] - f[0]
    if half_power_bandwidth >= LEAKAGE_BANDWIDTH_BINS * df:
        return False
    return _coherence_dip(coherence, int(round((f_peak - f[0]) / df))) > LEAKAGE_COHERENCE_DIP


def _form_index(form: str) -> int:
    if form not in FRF_FORMS:
        raise ValueError(f"form: expected one of {FRF_FORMS}, got {form!r}")
    return FRF_FORMS.index(form)


def _validated_signals(x, y, nperseg, overlap) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(x, dtype=float)
    y2 = np.atleast_2d(np.asarray(y, dtype=float))
    if x.ndim != 1:
        raise ValueError(f"x: expected a 1-D input signal, got shape {x.shape}")
    if y2.ndim != 2 or y2.shape[1] != x.size:
        raise ValueError(f"y: expected {x.size} samples per channel, got shape {np.shape(y)}")
    if not 2 <= nperseg <= x.size:
        raise ValueError(f"nperseg: must be within 2..{x.size} samples, got {nperseg}")
    if not 0.0 <= overlap < 1.0:
        raise ValueError(f"overlap: must be a fraction in [0, 1), got {overlap}")
    return x, (y2 if np.ndim(y) == 2 else y2.reshape(1, -1))


def _hit_records(force, response) -> tuple[np.ndarray, np.ndarray]:
    """Force and response as hits × samples arrays of equal shape."""
    forces = np.atleast_2d(np.asarray(force, dtype=float))
    responses = np.atleast_2d(np.asarray(response, dtype=float))
    if forces.ndim != 2 or forces.shape != responses.shape:
        raise ValueError(
            f"force, response: expected equal shapes (samples or hits × samples), "
            f"got {np.shape(force)} and {np.shape(response)}"
        )
    return forces, responses


def _check_hit(index, force, fs, trigger_level, double_hit_level, force_range) -> HitCheck:
    """Trigger time and double-hit / overload flags of one hammer record."""
    peak_index = int(np.argmax(np.abs(force)))
    peak = float(force[peak_index])
    pulse = force * np.sign(peak)
    trigger = int(np.argmax(pulse >= trigger_level * abs(peak)))
    after_peak = pulse[peak_index:] < double_hit_level * abs(peak)
    pulse_end = peak_index + (int(np.argmax(after_peak)) if after_peak.any() else pulse.size)
    double_hit = bool(np.any(pulse[pulse_end:] >= double_hit_level * abs(peak)))
    overload = _is_overload(pulse, abs(peak), force_range)
    return HitCheck(index, trigger / fs, peak, double_hit, overload)


def _is_overload(pulse: np.ndarray, peak: float, force_range: float | None) -> bool:
    """Peak at the sensor's range, or clipped: the peak value held for 3 samples or more."""
    if force_range is not None and peak >= 0.98 * force_range:
        return True
    at_peak = np.concatenate(([0], (pulse >= peak * (1.0 - 1e-9)).astype(np.int8), [0]))
    edges = np.flatnonzero(np.diff(at_peak))
    return bool(np.max(edges[1::2] - edges[::2]) >= 3)


def _windowed_hit_spectra(forces, responses, hits, fs, force_span, tau):
    """rfft of each hit's force (force window) and response (exponential window)."""
    t = np.arange(forces.shape[1]) / fs
    X = [forces[h.index] * _force_window(t, h.trigger_time, *force_span) for h in hits]
    Y = [responses[h.index] * _exponential_window(t, h.trigger_time, tau) for h in hits]
    return scipy.fft.rfft(np.stack(X)), scipy.fft.rfft(np.stack(Y))


def _force_window(t, trigger_time, pretrigger_s, force_window_s) -> np.ndarray:
    """Rectangular window around the hammer pulse (zeroes the force channel's noise)."""
    return ((t >= trigger_time - pretrigger_s) & (t < trigger_time + force_window_s)).astype(float)


def _exponential_window(t, trigger_time, tau) -> np.ndarray:
    """exp(−(t − t_trigger)/τ) after the trigger, 1 before it."""
    return np.exp(-np.clip(t - trigger_time, 0.0, None) / tau)


def _hit_warning(check: HitCheck, rejected: bool) -> str:
    fate = "left out of the average" if rejected else "kept (reject_flagged=False)"
    return f"hit {check.index} at {check.trigger_time:.3f} s: {check.reason}; {fate}"


def _squeezer(y: np.ndarray):
    """Drop the channel axis again when the caller passed a single 1-D output."""
    return (lambda a: a[0]) if np.ndim(y) == 1 else (lambda a: a)


def _segment_spectra(signals: np.ndarray, win: np.ndarray, step: int) -> np.ndarray:
    """rfft of every windowed, mean-removed segment (channels × segments × bins), as csd."""
    segments = sliding_window_view(signals, win.size, axis=-1)[:, ::step]
    spectra = scipy.fft.rfft(segments * win, axis=-1)
    window_spectrum = scipy.fft.rfft(win)
    # detrend='constant': rfft((s − mean)·w) = rfft(s·w) − mean·rfft(w); rfft(w) is sparse.
    bins = np.flatnonzero(np.abs(window_spectrum) > 1e-12 * np.abs(window_spectrum).max())
    spectra[..., bins] -= segments.mean(axis=-1)[..., None] * window_spectrum[bins]
    return spectra


def _averaged_spectra(X: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean over segments of |X|², |Y|², conj(X)·Y; X is segments × bins, Y has a channel axis.

    Conjugates X in place (it is not used afterwards) to spare a copy.
    """
    n = X.shape[0]
    Sxx = _summed_squares(X[None])[0] / n
    Syy = _summed_squares(Y) / n
    Sxy = np.einsum("sf,csf->cf", np.conjugate(X, out=X), Y) / n
    return Sxx, Syy, Sxy


def _summed_squares(Z: np.ndarray) -> np.ndarray:
    """Σ_s |Z[c, s, f]|², reading re and im as one float array (half the passes of re² + im²)."""
    pairs = np.einsum("csf,csf->cf", Z.view(float), Z.view(float))
    return pairs[:, 0::2] + pairs[:, 1::2]


def _density_scale(fs: float, win: np.ndarray) -> np.ndarray:
    """scipy.signal.csd 'density' scaling, doubled for the one-sided spectrum."""
    n_bins = win.size // 2 + 1
    scale = np.full(n_bins, 2.0 / (fs * np.sum(win * win)))
    scale[0] /= 2.0
    if win.size % 2 == 0:
        scale[-1] /= 2.0
    return scale


def _frf_from_spectra(Sxx, Syy, Sxy) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    with np.errstate(divide="ignore", invalid="ignore"):
        H1 = Sxy / Sxx
        H2 = Syy / Sxy.conj()
        coherence = (Sxy.real**2 + Sxy.imag**2) / (Sxx * Syy)
    return H1, H2, coherence


def _with_leakage_check(estimate: FrfEstimate) -> FrfEstimate:
    """The estimate with a warning for every resonance that leakage biases."""
    f, channels = estimate.f, np.atleast_2d(estimate.H1).shape[0]
    leaks = tuple(
        _leak(f_peak, bw / (f[1] - f[0]), coh, estimate.nperseg)
        for c in range(channels)
        for f_peak, bw, coh in _leaky_peaks(f, np.atleast_2d(estimate.H1)[c],
                                            np.atleast_2d(estimate.H2)[c],
                                            np.atleast_2d(estimate.coherence)[c])
    )
    return replace(estimate, warnings=estimate.warnings + tuple(leak.text for leak in leaks),
                   leaks=leaks)


def findings_in_band(estimate: FrfEstimate,
                     band: tuple[float, float]) -> tuple[list[str], list[str]]:
    """What a person reads about the estimate inside `band` (Hz, the excited range: outside
    it the coherence is noise and its 'peaks' are not modes): one line per distinct finding
    (all leaky resonances in one line, with the lowest coherence and where), and the detail
    lines behind them (one per resonance). Warnings without a frequency (hammer hits) are
    their own findings."""
    leaks = [leak for leak in estimate.leaks if band[0] <= leak.f_hz <= band[1]]
    lines = [w for w in estimate.warnings if not w.startswith("leakage:")]
    if leaks:
        worst = min(leaks, key=lambda leak: leak.coherence)
        lines.append(
            f"leakage at {len(leaks)} resonance{'s' if len(leaks) > 1 else ''} in "
            f"{band[0]:g}–{band[1]:g} Hz ({', '.join(f'{x.f_hz:.1f}' for x in leaks)} Hz): "
            f"narrower than {LEAKAGE_BANDWIDTH_BINS:g} bins, H1 biased low there (coherence "
            f"{worst.coherence:.2f} at {worst.f_hz:.1f} Hz); read peaks from H2 or use "
            f"nperseg ≥ {max(x.nperseg_needed for x in leaks)}")
    return lines, [leak.text for leak in leaks]


def _leaky_peaks(f, H1, H2, coherence) -> list[tuple[float, float, float]]:
    """(frequency, half-power bandwidth, coherence) of resonances that leakage biases."""
    magnitude = np.nan_to_num(np.abs(H1))
    peaks, _ = scipy.signal.find_peaks(magnitude, prominence=0.5 * magnitude)
    peaks = peaks[_in_coherent_region(coherence, peaks)]
    h2_magnitude = np.nan_to_num(np.abs(H2))
    found = []
    for k in peaks:
        bandwidth = _half_power_bandwidth(f, h2_magnitude, k)
        if leakage_suspected(f, coherence, f[k], bandwidth):
            found.append((float(f[k]), bandwidth, float(np.min(coherence[max(k - 1, 0):k + 2]))))
    return found


def _in_coherent_region(coherence: np.ndarray, peaks: np.ndarray) -> np.ndarray:
    """Mask of peaks whose flanks have coherence > 0.5 (peaks in output noise are not modes)."""
    reach = int(LEAKAGE_BANDWIDTH_BINS) + 2
    flanks = np.clip(np.stack([peaks - reach, peaks + reach]), 0, coherence.size - 1)
    return np.all(np.nan_to_num(coherence[flanks]) > 0.5, axis=0)


def _half_power_bandwidth(f: np.ndarray, magnitude: np.ndarray, k: int) -> float:
    """Width (Hz) between the points where |H| falls to peak/√2 around bin k.

    Searches LEAKAGE_BANDWIDTH_BINS bins each side; a wider peak returns inf.
    """
    level = magnitude[k] / np.sqrt(2.0)
    reach = int(LEAKAGE_BANDWIDTH_BINS) + 1
    left = np.flatnonzero(magnitude[max(k - reach, 0):k] < level)
    right = np.flatnonzero(magnitude[k + 1:k + 1 + reach] < level)
    if left.size == 0 or right.size == 0:
        return np.inf
    i_left = max(k - reach, 0) + left[-1]
    i_right = k + right[0]
    return _crossing(f, magnitude, i_right, level) - _crossing(f, magnitude, i_left, level)


def _crossing(f, magnitude, i, level) -> float:
    """Frequency where |H| crosses `level` between bins i and i + 1 (linear interpolation)."""
    fraction = (level - magnitude[i]) / (magnitude[i + 1] - magnitude[i])
    return float(f[i] + fraction * (f[i + 1] - f[i]))


def _coherence_dip(coherence: np.ndarray, k: int) -> float:
    """Neighbourhood median coherence minus the minimum within ±1 bin of bin k."""
    lo, hi = max(k - _NEIGHBOURHOOD_BINS, 0), min(k + _NEIGHBOURHOOD_BINS + 1, coherence.size)
    around = np.r_[coherence[lo:max(k - 3, lo)], coherence[min(k + 4, hi):hi]]
    at_peak = coherence[max(k - 1, 0):k + 2]
    if around.size == 0:
        return 0.0
    return float(np.nanmedian(around) - np.nanmin(at_peak))


def _leak(f_peak: float, bandwidth_bins: float, coherence: float, nperseg: int) -> Leak:
    needed = int(2 ** np.ceil(np.log2(nperseg * LEAKAGE_BANDWIDTH_BINS / max(bandwidth_bins, 0.1))))
    return Leak(f_peak, bandwidth_bins, coherence, needed)
