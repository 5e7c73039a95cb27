"""Residual diagnosis: rank the candidate effects, add the best, refit, repeat.

Each round, every applicable effect of the library is
1. screened by its signature test: the share of the current residual that its first-order
   columns explain once made orthogonal to the model's free columns, over its start values;
2. fitted from its best starts together with the model's linear parameters (the model's
   own nonlinear parameters held), and scored by ΔBIC on the fit part.
The best candidate is added when its ΔBIC is below −`bic_threshold` (very strong evidence on
the Kass–Raftery scale) and it explains at least `min_explained` of the residual; the
augmented model is refitted jointly. The loop stops when no candidate is significant. Every
error that judges a step is measured on the held-out kinematics.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from feedbench.analysis.closure.effects import CANDIDATES, EFFECTS, Context, Effect
from feedbench.analysis.closure.model import (
    Fit, Model, Term, design, fit_model, held_out_error, least_squares_solution, output_slope,
)
from feedbench.analysis.closure.trace import Kinematics


@dataclass(frozen=True)
class ClosureOptions:
    """Search settings. bic_threshold: ΔBIC an effect must beat (−10: very strong evidence);
    min_explained: share of the fit-part residual it must explain; max_effects: stop after
    this many; candidates: effect names the search may add; starts: fits per candidate."""

    bic_threshold: float = 10.0
    min_explained: float = 0.15
    max_effects: int = 6
    candidates: tuple[str, ...] = CANDIDATES
    starts: int = 1

    def __post_init__(self) -> None:
        unknown = sorted(set(self.candidates) - set(CANDIDATES))
        if unknown:
            raise ValueError(f"candidates: unknown effect {unknown[0]!r} "
                             f"(known: {', '.join(CANDIDATES)})")


@dataclass(frozen=True)
class Candidate:
    """One effect tried against the current model.

    screened: share of the residual its signature explains; explained: share of the fit-part
    SSR removed after fitting it; delta_bic: BIC change; rejected: why it cannot be added.
    """

    name: str
    screened: float
    evidence: str
    fit: Fit | None
    explained: float
    delta_bic: float
    rejected: str | None = None

    def significant(self, options: ClosureOptions) -> bool:
        """Whether this candidate pays for its parameters."""
        return (self.rejected is None and self.delta_bic < -options.bic_threshold
                and self.explained >= options.min_explained)


@dataclass(frozen=True)
class Step:
    """One effect added: why (the ranking), the refitted model, held-out error before/after."""

    chosen: Candidate
    ranking: tuple[Candidate, ...]
    fit: Fit
    error_before: float
    error_after: float


@dataclass(frozen=True)
class ClosureResult:
    """The whole search: the base fit, the steps, the final ranking that stopped it."""

    base: Fit
    steps: tuple[Step, ...]
    final_ranking: tuple[Candidate, ...]
    error_before: float
    error_after: float
    options: ClosureOptions

    @property
    def final(self) -> Fit:
        """The augmented model's fit (the base fit if nothing was added)."""
        return self.steps[-1].fit if self.steps else self.base

    @property
    def effects(self) -> tuple[str, ...]:
        """Names of the added effects, in the order added."""
        return tuple(step.chosen.name for step in self.steps)


def close_the_loop(model: Model, fit_kin: Kinematics, holdout_kin: Kinematics,
                   options: ClosureOptions = ClosureOptions()) -> ClosureResult:
    """Fit `model` on `fit_kin`, then add effects while one is significant.

    Errors before/after are NRMSE of the force reading on `holdout_kin`.
    """
    base = fit_model(model, fit_kin)
    current, steps = base, []
    while True:
        ranking = rank_candidates(current, fit_kin, options)
        best = ranking[0] if ranking else None
        if best is None or not best.significant(options) or len(steps) >= options.max_effects:
            break
        refit = fit_model(_free_again(best.fit.model, current.model), fit_kin)
        steps.append(Step(best, tuple(ranking), refit,
                          held_out_error(current.model, holdout_kin),
                          held_out_error(refit.model, holdout_kin)))
        current = refit
    return ClosureResult(base, tuple(steps), tuple(ranking),
                         held_out_error(base.model, holdout_kin),
                         held_out_error(current.model, holdout_kin), options)


def rank_candidates(current: Fit, kin: Kinematics, options: ClosureOptions) -> list[Candidate]:
    """Every applicable candidate tried against `current`, best (lowest ΔBIC) first."""
    present, fixed = current.model.names, current.model.fixed
    context = Context(current.residual, current.acting)
    basis = _free_basis(current, kin)
    tried = [try_effect(EFFECTS[name], current, kin, context, basis, options.starts)
             for name in options.candidates if EFFECTS[name].applicable(present, fixed)]
    return sorted(tried, key=lambda c: (c.rejected is not None, c.delta_bic))


def try_effect(effect: Effect, current: Fit, kin: Kinematics, context: Context,
               basis: np.ndarray, n_starts: int) -> Candidate:
    """Screen `effect` on the residual, fit it from its best starts, score it."""
    starts = effect.starts(kin, context)
    if not starts:
        return Candidate(effect.name, 0.0, "no start in the data's range", None, 0.0, 0.0,
                         "not testable on this data")
    rows = kin.rows
    shares = [_explained_share(effect.probe(kin, context, s)[rows], context.residual, basis)
              for s in starts]
    order = np.argsort(shares)[::-1][:n_starts]
    fits = [_fit_candidate(effect, current, kin, starts[i]) for i in order]
    fit = min(fits, key=lambda f: f.ssr)
    evidence = f"{effect.signature}: explains {shares[order[0]]:.0%} of the residual"
    explained = 1.0 - fit.ssr / current.ssr
    delta_bic = fit.bic - current.bic
    term = fit.model.terms[-1]
    return Candidate(effect.name, float(shares[order[0]]), evidence, fit, float(explained),
                     float(delta_bic), effect.implausible(term.values, fit.model.total_mass))


def _fit_candidate(effect: Effect, current: Fit, kin: Kinematics, start: dict) -> Fit:
    """The current model (its nonlinear parameters held) plus `effect` from `start`."""
    held = _hold_nonlinear(current.model)
    term = Term(effect, {**effect.defaults(), **start},
                frozenset(effect.linear_keys + effect.nonlinear_keys))
    return fit_model(held.with_term(term), kin, with_std=False)


def _hold_nonlinear(model: Model) -> Model:
    terms = tuple(replace(t, free=t.free - set(t.free_nonlinear)) for t in model.terms)
    return replace(model, terms=terms)


def _free_again(augmented: Model, before: Model) -> Model:
    """Restore the free sets the held terms had before the candidate was fitted."""
    terms = tuple(replace(t, free=b.free) for t, b in zip(augmented.terms, before.terms))
    return replace(augmented, terms=terms + augmented.terms[len(before.terms):])


def _free_basis(current: Fit, kin: Kinematics) -> np.ndarray:
    """Orthonormal basis of the columns the current model can still move (free θ)."""
    d = design(current.model, kin)
    columns = d.columns[:, d.free] * output_slope(current.model, current.acting)[:, None]
    columns = columns[kin.rows]
    if columns.shape[1] == 0:
        return np.zeros((kin.n_used, 0))
    q, r = np.linalg.qr(columns)
    keep = np.abs(np.diag(r)) > 1e-10 * max(np.abs(np.diag(r)).max(), 1e-300)
    return q[:, keep]


def _explained_share(probe: np.ndarray, residual: np.ndarray, basis: np.ndarray) -> float:
    """Share of ‖residual‖² in the span of `probe` made orthogonal to `basis`."""
    probe = probe - basis @ (basis.T @ probe)
    if not np.any(np.abs(probe) > 0.0):
        return 0.0
    explained = probe @ least_squares_solution(probe, residual)
    return float(min(1.0, explained @ explained / max(residual @ residual, 1e-300)))

