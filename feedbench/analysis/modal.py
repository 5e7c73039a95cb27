"""Modal parameters of the modes in a band: natural frequency, damping ratio, modal stiffness
and modal mass (as in Table 3.1), from receptance FRFs.

Method (holds for closely spaced modes, unlike peak picking):
1. poles by the least-squares complex-frequency method (LSCF, common denominator over all
   outputs, z-domain basis with complex coefficients on the zoomed band) at a range of model
   orders; poles that repeat from one order to the next are stable (stabilisation diagram);
   the `n_modes` most persistent stable poles are kept;
2. residues, a lower residual (modes below the band) and an upper residual (modes above it)
   by linear least squares with the poles fixed (LSFD);
3. optionally the poles are polished by nonlinear least squares on the whole model, the
   residues re-solved linearly at every step (variable projection).

Model, receptance (m/N), ω = 2πf, for output o:

    H_o(ω) = Σ_k [ r_ok / (jω − λ_k) + r_ok* / (jω − λ_k*) ] + U_o + L_o / (jω)²

λ_k = −ζ_k ω_k + j ω_k √(1 − ζ_k²). A single-degree-of-freedom receptance
1 / (k − mω² + jωc) has r = 1 / (2j m ω_d), ω_d = ω_k √(1 − ζ_k²), so the modal mass and
stiffness referred to the driving point d are

    m_k = 1 / (2 ω_d |r_dk|),   k_k = m_k ω_k².

Referred to any other output they are the "apparent" values m_k / (φ_d φ_o).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft
import scipy.linalg
import scipy.optimize

from feedbench.analysis.frf import LEAKAGE_BANDWIDTH_BINS, leakage_suspected

ZOOM = 0.9
"""Fraction of the unit circle onto which the band is mapped (conditioning of LSCF)."""

STABLE_FREQUENCY_TOLERANCE = 0.005
"""Relative change of a pole's frequency between consecutive orders that still counts as stable."""

STABLE_DAMPING_TOLERANCE = 0.10
"""Relative change of a pole's damping ratio between consecutive orders that counts as stable."""

MAX_DAMPING_RATIO = 0.3
"""Poles with more damping than this are taken as computational, not structural."""


@dataclass(frozen=True)
class Mode:
    """One mode: f_n (Hz, undamped), zeta (–), modal stiffness (N/m) and mass (kg) at the
    driving point, complex residue per output (m/(N·s) for a receptance)."""

    f_n: float
    zeta: float
    modal_stiffness: float
    modal_mass: float
    residue: np.ndarray

    @property
    def pole(self) -> complex:
        """λ = −ζω_n + jω_n√(1 − ζ²) in rad/s."""
        omega_n = 2.0 * np.pi * self.f_n
        return complex(-self.zeta * omega_n, omega_n * np.sqrt(1.0 - self.zeta**2))


@dataclass(frozen=True)
class StabilizationDiagram:
    """Every physical pole found (rad/s) with its model order and stable flag."""

    order: np.ndarray
    poles: np.ndarray
    stable: np.ndarray

    @property
    def f(self) -> np.ndarray:
        """Damped natural frequencies (Hz)."""
        return self.poles.imag / (2.0 * np.pi)

    @property
    def zeta(self) -> np.ndarray:
        return -self.poles.real / np.abs(self.poles)


@dataclass(frozen=True)
class ModalFit:
    """Identified modes (ascending f_n) and the fitted model over the band.

    `H_model` (shape of the band-limited H) is the synthesised receptance, `relative_error` =
    ‖H − H_model‖ / ‖H‖ over the band, `lower_residual` L_o (N⁻¹·m·s⁻²) and `upper_residual` U_o
    (m/N) per output.
    """

    modes: tuple[Mode, ...]
    f: np.ndarray
    H_model: np.ndarray
    lower_residual: np.ndarray
    upper_residual: np.ndarray
    relative_error: float
    stabilization: StabilizationDiagram
    warnings: tuple[str, ...] = ()


def fit_modes(
    f: np.ndarray,
    H: np.ndarray,
    band: tuple[float, float],
    n_modes: int,
    *,
    max_order: int | None = None,
    driving_point: int = 0,
    coherence: np.ndarray | None = None,
    lag_window: np.ndarray | None = None,
    refine: bool = True,
) -> ModalFit:
    """Identify `n_modes` modes of the receptance(s) H (m/N) in `band` (Hz).

    f: frequencies (Hz), evenly spaced; H: shape (n_f,) or (n_outputs, n_f), one reference.
    max_order: highest LSCF model order (default 2·n_modes + 24, at most n_lines/2 − 1).
    driving_point: output whose residue gives modal mass and stiffness.
    coherence (shape of H): a mode narrower than LEAKAGE_BANDWIDTH_BINS bins with a coherence
    dip at its peak gets a leakage warning.
    lag_window: `frf.welch_lag_window(window, nperseg)` when H is a Welch H1 on its rfft bins;
    the model is then passed through the lag window, so leakage does not bias ζ or k.
    """
    f_band, H_band, omega = _band_data(f, H, band)
    max_order = _checked_max_order(max_order, n_modes, f_band.size)
    response = (_ContinuousPoles(omega) if lag_window is None
                else _LagWindowedPoles(f_band, lag_window))
    scale = np.sqrt(np.mean(np.abs(H_band) ** 2, axis=1, keepdims=True))
    H_scaled = H_band / scale
    diagram = _stabilization(omega, H_scaled, n_modes, max_order, band)
    poles = _select_poles(diagram, n_modes)
    if refine and poles.size:
        poles = _refine_poles(omega, H_scaled, poles, response)
    coefficients, H_model = _residues(omega, H_scaled, poles, response)
    coefficients, H_model = coefficients * scale.T, H_model * scale
    modes = tuple(
        _mode(pole, coefficients[2 * i] + 1j * coefficients[2 * i + 1], driving_point)
        for i, pole in enumerate(poles)
    )
    squeeze = (lambda a: a[0]) if np.ndim(H) == 1 else (lambda a: a)
    return ModalFit(
        modes=modes,
        f=f_band,
        H_model=squeeze(H_model),
        lower_residual=squeeze(coefficients[-1]),
        upper_residual=squeeze(coefficients[-2]),
        relative_error=float(np.linalg.norm(H_band - H_model) / np.linalg.norm(H_band)),
        stabilization=diagram,
        warnings=_fit_warnings(modes, n_modes, band, f, coherence, driving_point,
                               lag_corrected=lag_window is not None),
    )


def synthesize_receptance(
    f: np.ndarray, modes: tuple[Mode, ...], lower_residual=0.0, upper_residual=0.0
) -> np.ndarray:
    """Receptance (m/N) of `modes` plus residual terms at frequencies f (Hz), per the model above.

    Shape (n_f,) for scalar residues, (n_outputs, n_f) for residue arrays.
    """
    jw = 2j * np.pi * np.asarray(f, dtype=float)
    H = sum(
        (np.asarray(m.residue)[..., None] / (jw - m.pole)
         + np.conj(m.residue)[..., None] / (jw - np.conj(m.pole)) for m in modes),
        np.zeros_like(jw),
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        lower = np.asarray(lower_residual)[..., None] / jw**2
        return H + np.asarray(upper_residual)[..., None] + lower


def remove_window_decay(modes: tuple[Mode, ...], decay_rate: float) -> tuple[Mode, ...]:
    """Undo an exponential response window exp(−t·decay_rate) (1/s): λ_true = λ_fit + decay_rate.

    The window leaves residues unchanged when it starts at the impact (quasi_frf does).
    """
    return tuple(
        _mode_from_pole(m.pole + decay_rate, m.residue, _driving_residue(m)) for m in modes
    )


def _band_data(f, H, band) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    f = np.asarray(f, dtype=float)
    H2d = np.atleast_2d(np.asarray(H))
    lo, hi = band
    if not (0.0 <= lo < hi) or H2d.ndim != 2 or H2d.shape[-1] != f.size:
        raise ValueError(
            f"band, H: need 0 <= lo < hi and H with {f.size} lines, got {band}, {np.shape(H)}"
        )
    inside = (f >= lo) & (f <= hi) & np.all(np.isfinite(H2d), axis=0)
    if inside.sum() < 8:
        raise ValueError(f"band: only {inside.sum()} finite frequency lines in {band} Hz")
    return f[inside], H2d[:, inside], 2.0 * np.pi * f[inside]


def _checked_max_order(max_order: int | None, n_modes: int, n_lines: int) -> int:
    highest = n_lines // 2 - 1
    if max_order is None:
        max_order = min(2 * n_modes + 24, highest)
    if not 1 <= n_modes <= max_order <= highest:
        raise ValueError(
            f"n_modes, max_order: need 1 <= n_modes <= max_order <= {highest} (half the lines in "
            f"the band), got {n_modes}, {max_order}"
        )
    return max_order


def _normal_matrices(omega: np.ndarray, H: np.ndarray, order: int):
    """R, S, T of the LSCF normal equations on the zoomed band, per output.

    Basis Ω_k^r, Ω_k = exp(−j(ω_k − ω_c)Δt), maps the band onto ±ZOOM·π. Each matrix is
    Toeplitz, entry (r, s) = Σ_k w_k exp(jθ_k(r − s)) with w = 1, −H, |H|².
    """
    omega_c = 0.5 * (omega[0] + omega[-1])
    dt = ZOOM * np.pi / (0.5 * (omega[-1] - omega[0]))
    lags = np.exp(1j * np.outer(np.arange(order + 1), (omega - omega_c) * dt))
    weights = np.vstack([np.ones_like(omega), -H, np.abs(H) ** 2])
    matrices = np.stack([
        scipy.linalg.toeplitz(column, row)
        for column, row in zip(weights @ lags.T, weights @ lags.conj().T)
    ])
    n_out = H.shape[0]
    return matrices[0], matrices[1:1 + n_out], matrices[1 + n_out:], omega_c, dt


def _stabilization(omega, H, n_modes, max_order, band) -> StabilizationDiagram:
    """LSCF poles at orders n_modes..max_order, each flagged stable or not."""
    R, S, T, omega_c, dt = _normal_matrices(omega, H, max_order)
    orders, poles, stable = [], [], []
    previous = np.array([], dtype=complex)
    for n in range(n_modes, max_order + 1):
        current = _lscf_poles(R, S, T, n, omega_c, dt)
        current = current[_physical(current, band)]
        orders.append(np.full(current.size, n))
        poles.append(current)
        stable.append(np.array([_is_stable(p, previous) for p in current], dtype=bool))
        previous = current
    return StabilizationDiagram(*(np.concatenate(a) for a in (orders, poles, stable)))


def _lscf_poles(R, S, T, n, omega_c, dt) -> np.ndarray:
    """Poles of the order-n common denominator from the reduced normal equations (α_n = 1)."""
    k = n + 1
    Rinv_S = np.linalg.solve(R[:k, :k], S[:, :k, :k])
    M = np.sum(T[:, :k, :k] - S[:, :k, :k].conj().transpose(0, 2, 1) @ Rinv_S, axis=0)
    alpha = np.linalg.solve(M[:n, :n], -M[:n, n])
    roots = np.roots(np.r_[1.0, alpha[::-1]])
    return 1j * omega_c - np.log(roots) / dt


def _physical(poles: np.ndarray, band) -> np.ndarray:
    f_d = poles.imag / (2.0 * np.pi)
    zeta = -poles.real / np.abs(poles)
    return (f_d >= band[0]) & (f_d <= band[1]) & (zeta > 0.0) & (zeta < MAX_DAMPING_RATIO)


def _is_stable(pole: complex, previous: np.ndarray) -> bool:
    """A pole is stable when the previous order has one with nearly the same f and ζ."""
    if previous.size == 0:
        return False
    zeta, zeta_prev = -pole.real / abs(pole), -previous.real / np.abs(previous)
    close_f = np.abs(previous.imag - pole.imag) < STABLE_FREQUENCY_TOLERANCE * abs(pole.imag)
    close_zeta = np.abs(zeta_prev - zeta) < STABLE_DAMPING_TOLERANCE * zeta
    return bool(np.any(close_f & close_zeta))


def _select_poles(diagram: StabilizationDiagram, n_modes: int) -> np.ndarray:
    """Cluster the stable poles; keep the n_modes clusters seen at the most orders (means)."""
    sums: list[complex] = []
    counts: list[int] = []
    for pole in diagram.poles[diagram.stable]:
        centres = np.array(sums) / np.array(counts) if sums else np.array([], dtype=complex)
        distance = np.abs(centres - pole) / abs(pole)
        if distance.size and distance.min() < STABLE_FREQUENCY_TOLERANCE:
            best = int(np.argmin(distance))
            sums[best] += pole
            counts[best] += 1
        else:
            sums.append(pole)
            counts.append(1)
    ranked = np.argsort(counts, kind="stable")[::-1][:n_modes]
    return _by_frequency(np.array([sums[i] / counts[i] for i in ranked], dtype=complex))


def _by_frequency(poles: np.ndarray) -> np.ndarray:
    return poles[np.argsort(poles.imag)]


class _ContinuousPoles:
    """Pole responses 1/(jω − λ) (one column per pole) and their derivatives d/dλ."""

    def __init__(self, omega: np.ndarray):
        self.jw = 1j * omega[:, None]

    def values(self, poles: np.ndarray) -> np.ndarray:
        return 1.0 / (self.jw - poles)

    def derivatives(self, poles: np.ndarray) -> np.ndarray:
        return 1.0 / (self.jw - poles) ** 2


class _LagWindowedPoles:
    """Pole responses as a Welch H1 sees them: DFT of v(τ)·e^{λτ}/fs at the bins of f.

    E[H1] = Σ_τ v(τ) h(τ) e^{−jωτ} when the input spectrum is smooth over the window's main
    lobe, v = frf.welch_lag_window; the bins are f/Δf with fs = nperseg·Δf.
    """

    def __init__(self, f: np.ndarray, lag_window: np.ndarray):
        df = f[1] - f[0]
        self.bins = np.rint(f / df).astype(int)
        if not np.allclose(self.bins * df, f, rtol=0.0, atol=1e-6 * df):
            raise ValueError("lag_window: f must be the rfft bins k·fs/nperseg of the Welch H1")
        fs = lag_window.size * df
        self.tau = np.arange(lag_window.size) / fs
        self.weights = lag_window / fs

    def values(self, poles: np.ndarray) -> np.ndarray:
        return self._dft(self.weights, poles)

    def derivatives(self, poles: np.ndarray) -> np.ndarray:
        return self._dft(self.weights * self.tau, poles)

    def _dft(self, weights: np.ndarray, poles: np.ndarray) -> np.ndarray:
        impulse_responses = weights[:, None] * np.exp(np.outer(self.tau, poles))
        return scipy.fft.fft(impulse_responses, axis=0)[self.bins]


def _design_matrix(omega: np.ndarray, poles: np.ndarray, response) -> np.ndarray:
    """Real-stacked basis: per mode Re r and Im r columns, then upper and lower residuals."""
    p, p_conj = response.values(poles), response.values(poles.conj())
    modal = np.stack([p + p_conj, 1j * (p - p_conj)], axis=-1).reshape(omega.size, -1)
    complex_basis = np.column_stack([modal, np.ones_like(omega), 1.0 / (1j * omega) ** 2])
    return _real_stacked(complex_basis)


def _real_stacked(Z: np.ndarray) -> np.ndarray:
    return np.vstack([Z.real, Z.imag])


def _residues(omega, H, poles, response) -> tuple[np.ndarray, np.ndarray]:
    """LSFD: residues and residual terms by linear least squares with the poles fixed.

    Returns coefficients (2·n_modes + 2 rows: Re r, Im r per mode, U, L; one column per output)
    and the model H.
    """
    A = _design_matrix(omega, poles, response)
    solution = _least_squares(A, _real_stacked(H.T))
    fitted = A @ solution
    return solution, (fitted[:omega.size] + 1j * fitted[omega.size:]).T


def _least_squares(A: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """min ‖A x − rhs‖ by the normal equations of A with unit-norm columns (cond stays small)."""
    norms = np.linalg.norm(A, axis=0)
    scaled = A / norms
    try:
        return np.linalg.solve(scaled.T @ scaled, scaled.T @ rhs) / norms[:, None]
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(scaled, rhs, rcond=None)[0] / norms[:, None]


class _VariableProjection:
    """Misfit model − H over the poles alone, residues re-solved linearly for every trial, and
    Kaufman's Jacobian P⊥ (∂A/∂θ) c (Golub & Pereyra's variable projection)."""

    def __init__(self, omega: np.ndarray, H: np.ndarray, response):
        self.omega, self.H, self.response = omega, H, response

    def misfit(self, poles: np.ndarray) -> np.ndarray:
        difference = _residues(self.omega, self.H, poles, self.response)[1] - self.H
        return np.concatenate([difference.real.ravel(), difference.imag.ravel()])

    def jacobian(self, poles: np.ndarray) -> np.ndarray:
        """∂ misfit / ∂(Re λ_k, Im λ_k), columns in that order per pole."""
        A = _design_matrix(self.omega, poles, self.response)
        c = _least_squares(A, _real_stacked(self.H.T))
        dp, dp_conj = self.response.derivatives(poles), self.response.derivatives(poles.conj())
        columns = []
        for k in range(poles.size):
            c_re, c_im = c[2 * k], c[2 * k + 1]
            even, odd = dp[:, k] + dp_conj[:, k], 1j * (dp[:, k] - dp_conj[:, k])
            d_sigma = np.outer(even, c_re) + np.outer(odd, c_im)
            d_omega = np.outer(odd, c_re) - np.outer(even, c_im)
            columns += [self._projected(A, d_sigma), self._projected(A, d_omega)]
        return np.column_stack(columns)

    def _projected(self, A: np.ndarray, derivative: np.ndarray) -> np.ndarray:
        """P⊥ applied to (∂A/∂θ) c (n_f × outputs), flattened in the misfit's order."""
        stacked = _real_stacked(derivative)
        stacked = stacked - A @ _least_squares(A, stacked)
        n = self.omega.size
        return np.concatenate([stacked[:n].T.ravel(), stacked[n:].T.ravel()])


def _refine_poles(omega, H, poles, response) -> np.ndarray:
    """Nonlinear least squares (Levenberg–Marquardt) on the poles by variable projection."""
    omega_ref = float(np.mean(omega))
    problem = _VariableProjection(omega, H, response)

    def to_poles(x: np.ndarray) -> np.ndarray:
        return (x[0::2] + 1j * x[1::2]) * omega_ref

    x0 = np.column_stack([poles.real, poles.imag]).ravel() / omega_ref
    solution = scipy.optimize.least_squares(
        lambda x: problem.misfit(to_poles(x)), x0,
        jac=lambda x: problem.jacobian(to_poles(x)) * omega_ref, method="lm", x_scale="jac",
    )
    refined = to_poles(solution.x)
    return _by_frequency(refined) if np.all(refined.real < 0) else poles


def _mode(pole: complex, residue: np.ndarray, driving_point: int) -> Mode:
    driving_residue = complex(np.atleast_1d(residue)[driving_point])
    return _mode_from_pole(pole, np.asarray(residue), driving_residue)


def _mode_from_pole(pole: complex, residue: np.ndarray, driving_residue: complex) -> Mode:
    omega_n = abs(pole)
    modal_mass = 1.0 / (2.0 * pole.imag * abs(driving_residue))
    return Mode(
        f_n=omega_n / (2.0 * np.pi),
        zeta=-pole.real / omega_n,
        modal_stiffness=modal_mass * omega_n**2,
        modal_mass=modal_mass,
        residue=residue if residue.size > 1 else residue.reshape(()),
    )


def _driving_residue(mode: Mode) -> complex:
    """The residue that gives the mode's modal mass: |r_d| = 1 / (2 ω_d m)."""
    return 1.0 / (2.0 * mode.pole.imag * mode.modal_mass)


def _fit_warnings(modes, n_modes, band, f, coherence, driving_point, lag_corrected):
    warnings = []
    if len(modes) < n_modes:
        warnings.append(
            f"only {len(modes)} of {n_modes} modes have stable poles in {band} Hz; "
            "raise max_order or check the band"
        )
    if coherence is None:
        return tuple(warnings)
    f = np.asarray(f, dtype=float)
    coh = np.atleast_2d(coherence)[driving_point]
    remedy = (
        "corrected: the model was passed through the lag window" if lag_corrected
        else "H1 is biased low there: refit with lag_window=FrfEstimate.lag_window "
        "or use a longer segment"
    )
    for mode in modes:
        bandwidth = 2.0 * mode.zeta * mode.f_n
        if leakage_suspected(f, coh, mode.f_n, bandwidth):
            warnings.append(
                f"leakage: mode at {mode.f_n:.2f} Hz has a half-power bandwidth of "
                f"{bandwidth / (f[1] - f[0]):.1f} frequency bins (< {LEAKAGE_BANDWIDTH_BINS:g}) "
                f"and the coherence dips there; {remedy}"
            )
    return tuple(warnings)
