"""Inverse-model evaluation and fitting: declared and added terms, variable projection.

For given nonlinear parameters η the linear ones θ follow by least squares on the acting
force behind the reading (output transforms inverted); η is then refined by bounded
nonlinear least squares on the reading (variable projection, Golub & Pereyra). Parameter
standard deviations come from the Jacobian of the reading at the optimum, scaled for the
band-limited residual (n / n_eff, see `Kinematics.effective_n`).
"""

from __future__ import annotations

import functools
import inspect
import math
from dataclasses import dataclass, replace
from typing import Callable, Iterable, Iterator, Mapping

import numpy as np
from scipy.optimize import least_squares, lsq_linear

from feedbench.analysis.closure.effects import (
    DIFFERENCE_STEP, EFFECTS, Effect, prefetch_followers, spectral, term_columns,
)
from feedbench.analysis.closure.trace import Kinematics, frequencies, nrmse, read_only

MAX_NONLINEAR_EVALUATIONS = 40
"""Budget of residual evaluations of one nonlinear refinement (per free η)."""

NONLINEAR_TOLERANCE = 1e-6
"""Relative change of cost and η that ends a refinement (the ranking needs no more)."""

SINGULAR_TOLERANCE = 1e-8
"""Free columns whose unit-norm QR pivot falls below this cannot be told apart (the
relative precision of a least-squares solve in double precision, √ε)."""


class FitError(ValueError):
    """A fit that cannot run: non-finite residuals at its start, columns the data cannot
    tell apart, or an optimiser failure. The message says which, in one line."""


@dataclass(frozen=True)
class Term:
    """One term of a model: its effect, SI values of every parameter, the free ones."""

    effect: Effect
    values: Mapping[str, float]
    free: frozenset[str] = frozenset()

    @property
    def name(self) -> str:
        """The effect's name."""
        return self.effect.name

    @property
    def free_linear(self) -> tuple[str, ...]:
        """Free linear parameters, in column order."""
        return tuple(k for k in self.effect.linear_keys if k in self.free)

    @property
    def free_nonlinear(self) -> tuple[str, ...]:
        """Free nonlinear parameters."""
        return tuple(k for k in self.effect.nonlinear_keys if k in self.free)

    def with_values(self, values: Mapping[str, float]) -> Term:
        """The same term with some values replaced."""
        return replace(self, values={**self.values, **values})


def new_term(name: str, values: Mapping[str, float] | None = None,
             free: tuple[str, ...] | None = None) -> Term:
    """A term of the library effect `name` with SI `values` over its defaults; all of its
    fittable parameters free unless `free` says otherwise."""
    effect = EFFECTS[name]
    keys = effect.linear_keys + effect.nonlinear_keys if free is None else free
    return Term(effect, {**effect.defaults(), **(values or {})}, frozenset(keys))


@dataclass(frozen=True)
class Model:
    """An inverse model: an ordered tuple of terms (base terms first, then effects added)."""

    terms: tuple[Term, ...]
    name: str = ""

    @property
    def names(self) -> frozenset[str]:
        """Names of the terms present."""
        return frozenset(t.name for t in self.terms)

    @property
    def fixed(self) -> frozenset[str]:
        """Additive terms whose linear parameters are all declared (none free)."""
        return frozenset(t.name for t in self.terms
                         if t.effect.linear_keys and not t.free_linear)

    @property
    def total_mass(self) -> float:
        """Rigid-body mass (kg): the inertia term's."""
        return sum(t.values.get("M_kg", 0.0) for t in self.terms)

    def term(self, name: str) -> Term:
        """The term named `name`."""
        for t in self.terms:
            if t.name == name:
                return t
        raise KeyError(f"model has no term {name!r}")

    def with_term(self, term: Term) -> Model:
        """This model with `term` appended."""
        return replace(self, terms=self.terms + (term,))

    def nonlinear_vector(self) -> tuple[np.ndarray, list[tuple[int, str]]]:
        """Free nonlinear values (SI) and their (term index, key)."""
        slots = [(i, k) for i, t in enumerate(self.terms) for k in t.free_nonlinear]
        return np.array([self.terms[i].values[k] for i, k in slots]), slots

    def with_nonlinear(self, vector: np.ndarray, slots: list[tuple[int, str]]) -> Model:
        """This model with the free nonlinear values replaced by `vector`."""
        terms = list(self.terms)
        for value, (i, key) in zip(vector, slots):
            terms[i] = terms[i].with_values({key: float(value)})
        return replace(self, terms=tuple(terms))


@dataclass(frozen=True)
class Design:
    """Regressors of a model on one kinematics: every linear column, which are free, and
    which (term index, key) owns each."""

    columns: np.ndarray
    owners: list[tuple[int, str]]
    free: np.ndarray
    theta: np.ndarray


ColumnCache = dict[int, tuple[float, np.ndarray]]
"""Shifted columns of terms whose values do not change, by term index, with their lead (s)."""


def design(model: Model, kin: Kinematics, cache: ColumnCache | None = None,
           rows: np.ndarray | None = None) -> Design:
    """Columns of every linear parameter (shifted by the model's delay) and current values.

    rows: keep only these samples (after the shift); cache: columns of the terms it holds,
    already cut to the same rows, are reused while the lead is the same.
    """
    lead = sum(t.effect.shift(t.values) for t in model.terms)
    blocks, owners, free, theta = [], [], [], []
    for i, term in enumerate(model.terms):
        if not term.effect.linear_keys:
            continue
        if cache is not None and i in cache and cache[i][0] == lead:
            blocks.append(cache[i][1])
        else:
            block = _advance(term_columns(term.effect, kin, term.values), lead / kin.dt)
            blocks.append(block if rows is None else block[rows])
        for key in term.effect.linear_keys:
            owners.append((i, key))
            free.append(key in term.free)
            theta.append(term.values[key])
    columns = np.hstack(blocks) if blocks else np.zeros((kin.n if rows is None else rows.size, 0))
    return Design(columns, owners, np.array(free, dtype=bool), np.array(theta, dtype=float))


def _advance(columns: np.ndarray, samples: float) -> np.ndarray:
    """Columns evaluated `samples` later: e^{jωτ} in the frequency domain, exact for the
    band-limited columns (linear interpolation would lose 1 − cos(πf dt) at half a sample:
    2 % at 61 Hz at 1 kHz, where a lightly damped mode makes the force)."""
    if samples == 0.0:
        return columns
    return spectral(columns, 1.0, functools.partial(_lead_response, samples))


@functools.lru_cache(maxsize=64)
def _lead_response(samples: float, length: int, dt: float) -> np.ndarray:
    """e^{jω·samples} (a lead of `samples` sample periods dt, f in cycles per sample at
    dt = 1) at the `frequencies(length, dt)`, read-only: a model's lead is the same at
    every evaluation that does not refine it."""
    return read_only(np.exp(2j * np.pi * frequencies(length, dt) * samples))


def _outputs(model: Model) -> list[Term]:
    return [t for t in model.terms if t.effect.kind == "output"]


def forward(model: Model, acting: np.ndarray) -> np.ndarray:
    """The reading of the acting force through the model's output effects."""
    for term in _outputs(model):
        acting = term.effect.forward(acting, term.values)
    return acting


def inverse(model: Model, reading: np.ndarray) -> np.ndarray:
    """The acting force behind a reading (output effects inverted, last first)."""
    for term in reversed(_outputs(model)):
        reading = term.effect.inverse(reading, term.values)
    return reading


def output_slope(model: Model, acting: np.ndarray) -> np.ndarray:
    """d reading / d acting force, per sample."""
    slope = np.ones_like(acting)
    for term in _outputs(model):
        slope = slope * term.effect.slope(acting, term.values)
        acting = term.effect.forward(acting, term.values)
    return slope


@dataclass(frozen=True)
class Prediction:
    """acting: the model's force (N); reading: what the force channel shows (N)."""

    acting: np.ndarray
    reading: np.ndarray


def predict(model: Model, kin: Kinematics) -> Prediction:
    """The model's force prediction on `kin` with its current values."""
    d = design(model, kin)
    acting = d.columns @ d.theta
    return Prediction(acting, forward(model, acting))


def held_out_error(model: Model, kin: Kinematics) -> float:
    """NRMSE of the predicted force reading against the measured one on the used samples."""
    rows = kin.rows
    return nrmse(kin.force[rows], predict(model, kin).reading[rows])


TIP_TERMS = frozenset({"structural_mode"})
"""Terms whose column is (T − 1) a, T = x_tip/x_mot (Eq. 4.25): the load's acceleration is
the motor's plus that column."""


def predict_tip(model: Model, kin: Kinematics) -> np.ndarray:
    """The load-side acceleration the model predicts (m/s²): the motor's plus (T − 1) a of
    each structural mode (Eq. 4.25); the load of a rigid model moves with the motor."""
    tip = kin.a
    for term in model.terms:
        if term.name in TIP_TERMS:
            tip = tip + term_columns(term.effect, kin, term.values)[:, 0]
    return tip


def tip_error(model: Model, kin: Kinematics) -> float:
    """NRMSE of the predicted load-side acceleration on the used samples (NaN without a
    tip channel)."""
    if kin.tip is None:
        return math.nan
    rows = kin.rows
    return nrmse(kin.tip[rows], predict_tip(model, kin)[rows])


def least_squares_solution(columns: np.ndarray, target: np.ndarray) -> np.ndarray:
    """argmin ‖columns θ − target‖ by the normal equations of unit-norm columns (p ≪ n);
    `FitError` if columns or target are not finite."""
    if not (np.all(np.isfinite(columns)) and np.all(np.isfinite(target))):
        raise FitError("non-finite regressors or force at the start values")
    norms = np.linalg.norm(columns, axis=0)
    norms[norms == 0.0] = 1.0
    scaled = columns / norms
    gram = scaled.T @ scaled
    try:
        solution = np.linalg.solve(gram, scaled.T @ target)
    except np.linalg.LinAlgError:
        solution = np.linalg.lstsq(scaled, target, rcond=None)[0]
    return solution / norms


def bounded_least_squares(columns: np.ndarray, target: np.ndarray, lower: np.ndarray,
                          upper: np.ndarray) -> np.ndarray:
    """argmin ‖columns θ − target‖ with lower ≤ θ ≤ upper (SI physical ranges): the
    unconstrained solution where it is physical, else scipy's bounded linear least squares
    (a negative mass that absorbs an effect the model lacks is held at zero instead)."""
    theta = least_squares_solution(columns, target)
    if np.all((theta >= lower) & (theta <= upper)):
        return theta
    norms = np.linalg.norm(columns, axis=0)
    norms[norms == 0.0] = 1.0
    result = lsq_linear(columns / norms, target, bounds=(lower * norms, upper * norms),
                        method="bvls")
    return result.x / norms


def linear_bounds(model: Model, owners: list[tuple[int, str]]) -> tuple[np.ndarray, np.ndarray]:
    """SI physical ranges of the linear parameters `owners` (term index, key)."""
    params = [model.terms[i].effect.parameter(key) for i, key in owners]
    return np.array([p.lower for p in params]), np.array([p.upper for p in params])


def solve_linear(model: Model, kin: Kinematics) -> Model:
    """Least-squares values of the free linear parameters for the model's current η, on
    the used samples."""
    return _solve(model, kin, kin.rows)[0]


def _solve(model: Model, kin: Kinematics, rows: np.ndarray,
           cache: ColumnCache | None = None) -> tuple[Model, np.ndarray]:
    """The model with its free θ solved on `rows`, and its force reading there."""
    d = design(model, kin, cache, rows)
    theta = d.theta.copy()
    if d.free.any():
        target = inverse(model, kin.force[rows]) - d.columns[:, ~d.free] @ theta[~d.free]
        owners = [o for o, f in zip(d.owners, d.free) if f]
        theta[d.free] = bounded_least_squares(d.columns[:, d.free], target,
                                              *linear_bounds(model, owners))
        terms = list(model.terms)
        for value, (i, key) in zip(theta[d.free], owners):
            terms[i] = terms[i].with_values({key: float(value)})
        model = replace(model, terms=tuple(terms))
    return model, forward(model, d.columns @ theta)


@dataclass(frozen=True)
class Fit:
    """A model fitted on one kinematics.

    residual: measured − predicted reading on the used samples (N); acting: the model's
    force on every sample (N); ssr: sum of squared residuals (N²); n, n_eff: used and
    independent samples; k: free parameters; std: one-sigma SI standard deviation per
    (term name, key); measured_norm: ‖measured force‖ over the used samples (N); tip_ssr,
    tip_norm: the same for the load-side acceleration (m²/s⁴, m/s²), None without a tip
    channel.
    """

    model: Model
    residual: np.ndarray
    acting: np.ndarray
    ssr: float
    n: int
    n_eff: float
    k: int
    std: dict[tuple[str, str], float]
    measured_norm: float
    tip_ssr: float | None = None
    tip_norm: float | None = None

    @property
    def bic(self) -> float:
        """Bayesian information criterion n_eff ln(SSR/n) + k ln(n_eff) (Schwarz 1978); a
        tip channel adds n_eff ln(SSR_tip/n): two outputs, each with its own variance."""
        tip = 0.0 if self.tip_ssr is None else self.n_eff * np.log(self.tip_ssr / self.n)
        return self.n_eff * np.log(self.ssr / self.n) + tip + self.k * np.log(self.n_eff)

    @property
    def cost(self) -> float:
        """Relative SSR, (‖r‖/‖F‖)², plus that of the tip acceleration when there is one:
        the share of it a candidate removes is what it explains."""
        tip = 0.0 if self.tip_ssr is None else self.tip_ssr / self.tip_norm**2
        return self.ssr / self.measured_norm**2 + tip

    @property
    def error(self) -> float:
        """NRMSE of the force reading on the fit data."""
        return float(np.sqrt(self.ssr) / self.measured_norm)


def fit_model(model: Model, kin: Kinematics, with_std: bool = True) -> Fit:
    """Fit every free parameter of `model` on `kin`; start η at the model's values.

    with_std: also compute the parameter standard deviations (else `std` is empty).
    """
    x0, slots = model.nonlinear_vector()
    if slots:
        model = _refine_nonlinear(model, kin, x0, slots)
    model = solve_linear(model, kin)
    prediction = predict(model, kin)
    rows = kin.rows
    residual = kin.force[rows] - prediction.reading[rows]
    if not np.all(np.isfinite(residual)):
        raise FitError("the fitted prediction is not finite")
    k = sum(len(t.free_linear) + len(t.free_nonlinear) for t in model.terms)
    std = _standard_deviations(model, kin, prediction, residual, k) if with_std else {}
    tip = {} if kin.tip is None else {
        "tip_ssr": float(np.sum((kin.tip - predict_tip(model, kin))[rows] ** 2)),
        "tip_norm": float(np.linalg.norm(kin.tip[rows]))}
    return Fit(model, residual, prediction.acting, float(residual @ residual), kin.n_used,
               kin.effective_n, k, std, float(np.linalg.norm(kin.force[rows])), **tip)


def standard_deviations(fit: Fit, kin: Kinematics) -> dict[tuple[str, str], float]:
    """One-sigma SI standard deviation per (term name, key) of `fit`, a fit on `kin`: its
    own `std`, or, for one made `with_std=False`, what `fit_model` would have computed."""
    if fit.std or fit.k == 0:
        return fit.std
    return _standard_deviations(fit.model, kin, predict(fit.model, kin), fit.residual, fit.k)


def _refine_nonlinear(model: Model, kin: Kinematics, x0: np.ndarray,
                      slots: list[tuple[int, str]]) -> Model:
    """Bounded least squares over the free η, θ solved inside (variable projection).

    Runs on every `stride`-th sample: the band is oversampled, the optimum barely moves.
    With a tip channel and a moving term that shapes it, the tip acceleration's residual is
    a second output, weighted by the ratio of the two residuals' norms at the start (each
    output's noise level, as maximum likelihood weighs them). The Jacobian is by differences
    of √ε; a term whose SSR is rugged (`Effect.difference_step`) is refined once more with
    differences of its own step (a secant across the ruggedness), the lower cost kept; a
    refinement that fails is dropped, the fit fails only when every one does.
    """
    lower = np.array([model.terms[i].effect.parameter(k).lower for i, k in slots])
    upper = np.array([model.terms[i].effect.parameter(k).upper for i, k in slots])
    x0 = np.clip(x0, lower, upper)
    moving = {i for i, _ in slots}
    rows = kin.rows[::_stride(kin)]
    lead = sum(t.effect.shift(t.values) for t in model.terms)
    cache = {i: (lead, _advance(term_columns(t.effect, kin, t.values), lead / kin.dt)[rows])
             for i, t in enumerate(model.terms) if i not in moving and t.effect.linear_keys}
    measured = kin.force[rows]

    def force_residual(x: np.ndarray) -> np.ndarray:
        """The reading's residual; NaN where the columns are not finite (a trial step the
        optimiser then shortens)."""
        try:
            return measured - _solve(model.with_nonlinear(x, slots), kin, rows, cache)[1]
        except FitError:
            return np.full(measured.size, np.nan)

    def tip_residual(x: np.ndarray) -> np.ndarray:
        return kin.tip[rows] - predict_tip(model.with_nonlinear(x, slots), kin)[rows]

    weight = 0.0
    if kin.tip is not None and any(model.terms[i].name in TIP_TERMS for i in moving):
        weight = np.linalg.norm(force_residual(x0)) / np.linalg.norm(tip_residual(x0))

    def residual(x: np.ndarray) -> np.ndarray:
        force = force_residual(x)
        return force if weight == 0.0 else np.concatenate([force, weight * tip_residual(x)])

    if not np.all(np.isfinite(residual(x0))):
        start = ", ".join(f"{model.terms[i].name}.{k} = {v:.3g}" for (i, k), v in zip(slots, x0))
        raise FitError(f"residuals not finite at the start ({start}, SI)")
    unit = _magnitudes(x0, lower, upper)

    def differences(fun: Callable[[np.ndarray], np.ndarray],
                    points: Iterable[np.ndarray]) -> Iterator[np.ndarray]:
        """`least_squares`' map over a Jacobian's difference points (its `workers`): their
        follower bodies simulated together first (`_prefetch`), then each point in turn."""
        points = list(points)
        _prefetch([model.with_nonlinear(u * unit, slots) for u in points], moving, kin)
        return map(fun, points)

    steps = np.array([model.terms[i].effect.difference_step for i, _ in slots])
    tangent = np.full(len(slots), DIFFERENCE_STEP)
    results, failures = [], []
    with np.errstate(all="ignore"):
        for step in (tangent, steps) if np.any(steps != tangent) else (tangent,):
            try:  # each step on its own: a failure of one keeps the other's fit
                results.append(least_squares(
                    lambda u: residual(u * unit), x0 / unit,
                    bounds=(lower / unit, upper / unit), x_scale="jac", diff_step=step,
                    ftol=NONLINEAR_TOLERANCE, xtol=NONLINEAR_TOLERANCE,
                    max_nfev=MAX_NONLINEAR_EVALUATIONS * len(slots),
                    **({"workers": differences} if BATCHED_DIFFERENCES else {})))
            except (ValueError, np.linalg.LinAlgError) as exc:
                failures.append(str(exc))
    if not results:
        raise FitError(f"nonlinear refinement failed: {'; '.join(failures)}")
    best = min(results, key=lambda result: result.cost)
    return model.with_nonlinear(best.x * unit, slots)


BATCHED_DIFFERENCES = "workers" in inspect.signature(least_squares).parameters
"""Whether `least_squares` takes a map for its finite differences (scipy ≥ 1.16): the
refinement then simulates a Jacobian's follower bodies side by side (results the same)."""


def _prefetch(models: list[Model], moving: set[int], kin: Kinematics) -> None:
    """Simulate together the follower bodies (`effects.prefetch_followers`) of the terms
    `moving` (indices) of each of `models` on `kin`, within a `follower_memo`."""
    prefetch_followers(kin.x, kin.v, kin.dt, [
        inputs for m in models for i in sorted(moving)
        for inputs in m.terms[i].effect.follower_inputs(kin, m.terms[i].values)])


def _magnitudes(x0: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Each η's own scale (SI): its start, else a thousandth of its range (else 1). The
    refinement runs on η / scale, so its step tolerance is relative to every parameter
    alike: a play of 1e-4 m beside a contact of 300 Hz would stop at the first step."""
    span = np.where(np.isfinite(upper - lower), upper - lower, 1e3)
    return np.where(x0 != 0.0, np.abs(x0), 1e-3 * span)


def check_identifiable(model: Model, kin: Kinematics) -> None:
    """Raise `FitError` naming the free linear parameters the data cannot determine: a
    column that is zero on the used samples, or one that the others already span."""
    d = design(model, kin, rows=kin.rows)
    names = [f"{model.terms[i].name}.{key}" for (i, key), f in zip(d.owners, d.free) if f]
    columns = d.columns[:, d.free]
    if not np.all(np.isfinite(columns)):
        raise FitError("the data give non-finite regressors (check for jumps in position)")
    norms = np.linalg.norm(columns, axis=0)
    for name, norm in zip(names, norms):
        if norm == 0.0:
            raise FitError(f"{name} cannot be determined: its regressor is zero on every "
                           f"used sample (the axis never shows it)")
    for j in range(1, len(names)):
        r = np.linalg.qr(columns[:, :j + 1] / norms[:j + 1], mode="r")
        if abs(r[j, j]) < SINGULAR_TOLERANCE:
            raise FitError(f"{names[j]} cannot be told apart from "
                           f"{', '.join(names[:j])} on this data (collinear regressors)")


def _stride(kin: Kinematics) -> int:
    """Sample stride that keeps ≥ 4 samples per period of the filter's cut-off."""
    return max(1, int(1.0 / (4.0 * kin.bandwidth * kin.dt)))


def _standard_deviations(model: Model, kin: Kinematics, prediction: Prediction,
                         residual: np.ndarray, k: int) -> dict[tuple[str, str], float]:
    """One-sigma SI deviations from (Σ JᵀJ / s²)⁻¹ over the outputs: the force reading, and
    the tip acceleration when there is one (only a tip-shaping term's η moves it)."""
    rows = kin.rows
    d = design(model, kin)
    slope = output_slope(model, prediction.acting)
    blocks = [(d.columns[:, d.free] * slope[:, None])[rows]]
    names = [(model.terms[i].name, key) for (i, key), f in zip(d.owners, d.free) if f]
    x, slots = model.nonlinear_vector()
    for j, (i, key) in enumerate(slots):
        blocks.append(_nonlinear_derivative(model, kin, x, slots, j)[rows, None])
        names.append((model.terms[i].name, key))
    if not names:
        return {}
    information = _information(np.column_stack(blocks), residual, k, kin)
    if kin.tip is not None:
        tip = np.zeros((rows.size, len(names)))
        for j, (i, _) in enumerate(slots):
            if model.terms[i].name in TIP_TERMS:
                tip[:, len(names) - len(slots) + j] = _nonlinear_derivative(
                    model, kin, x, slots, j, tip=True)[rows]
        information += _information(tip, (kin.tip - predict_tip(model, kin))[rows], k, kin)
    if not np.all(np.isfinite(information)):  # a derivative step left the stable range
        return dict.fromkeys(names, math.nan)
    std = np.sqrt(np.clip(np.diag(np.linalg.pinv(information)), 0.0, None))
    return dict(zip(names, map(float, std)))


def _information(jacobian: np.ndarray, residual: np.ndarray, k: int,
                 kin: Kinematics) -> np.ndarray:
    """JᵀJ / s² of one output, s² its residual variance scaled by n/n_eff for the
    band-limited residual."""
    dof = max(kin.n_used - k, 1)
    variance = float(residual @ residual) / dof * kin.n_used / kin.effective_n
    return jacobian.T @ jacobian / variance


def _nonlinear_derivative(model: Model, kin: Kinematics, x: np.ndarray,
                          slots: list[tuple[int, str]], j: int, tip: bool = False) -> np.ndarray:
    """Central difference of the reading (or the tip acceleration) in η_j with θ held (the
    joint model's Jacobian)."""
    i, key = slots[j]
    p = model.terms[i].effect.parameter(key)
    span = p.upper - p.lower if np.isfinite(p.upper - p.lower) else 1.0
    h = 1e-4 * max(abs(x[j]), 1e-3 * span)
    plus, minus = x.copy(), x.copy()
    plus[j] += h
    minus[j] -= h
    def output(values: np.ndarray) -> np.ndarray:
        varied = model.with_nonlinear(values, slots)
        return predict_tip(varied, kin) if tip else predict(varied, kin).reading

    return (output(plus) - output(minus)) / (2.0 * h)
