"""The closure's search on data that does not fit it (issue 13): a candidate whose fit fails
is rejected with its reason, a base fit that cannot run says why in one line, a wrong
declared value is recalibrated rather than explained by an effect, and a step must pass on
the held-out data too. Data from the inverse model itself: these test the search mechanics
(the independent simulator's cases are in benchmarks/bench_closure_independent.py)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from feedbench.analysis.closure import (
    ClosureOptions, Kinematics, Model, Trace, close_the_loop, fit_model, kinematics, new_term, report_dict,
)
from feedbench.analysis.closure.diagnosis import try_effect, _free_basis
from feedbench.analysis.closure.effects import EFFECTS, Context, Offset
from feedbench.analysis.closure.report import _step_dict
from feedbench.closure_command import single_blas_thread
from feedbench.config import ConfigError
from test_closure import BASE, K_TANH, base_model, kin_of, synthetic_trace


@pytest.fixture(autouse=True)
def _one_blas_thread():
    with single_blas_thread():
        yield


@dataclass(frozen=True)
class BrokenOffset(Offset):
    """An effect whose signature looks fine but whose columns are not finite: its fit
    cannot run."""

    def columns(self, kin, values):
        return np.full((kin.n, 1), np.nan)

    def probe(self, kin, context, start):
        return np.ones((kin.n, 1))


def test_a_candidate_whose_fit_fails_is_rejected_with_its_reason():
    kin = kin_of(synthetic_trace())
    current = fit_model(base_model(), kin)
    broken = BrokenOffset("broken", "no columns", "none", EFFECTS["offset"].parameters)
    candidate = try_effect(broken, current, kin, Context(current.residual, current.acting),
                           _free_basis(current, kin), 1)
    assert candidate.fit is None
    assert candidate.rejected == "fit failed: non-finite regressors or force at the start values"
    assert not candidate.significant(ClosureOptions())


def test_amplitude_nonlinearity_is_finite_for_every_beta_and_starts_invertible():
    """The issue's "Residuals are not finite in the initial point": a reading beyond the
    law's largest, 1/(4|β|), had no acting force behind it."""
    kin = kin_of(synthetic_trace())
    current = fit_model(base_model(), kin)
    peak = float(np.max(np.abs(kin.force)))
    effect = EFFECTS["amplitude_nonlinearity"]
    acting = effect.inverse(kin.force, {"beta_per_kN": -1.0 / peak})
    assert np.all(np.isfinite(acting))
    assert np.max(np.abs(acting)) == pytest.approx(0.5 * peak)   # the law's peak, 1/(2|β|)
    beta = effect.starts(kin, Context(current.residual, current.acting))[0]["beta_per_kN"]
    assert 1.0 + 4.0 * beta * peak >= 0.5


def test_a_base_fit_that_cannot_run_is_one_config_error_line():
    t = np.arange(6000) / 1000.0
    x = t + 1e-4 * np.sin(2 * np.pi * 3.0 * t)        # one direction only, 1 m/s
    trace = Trace(t, x, 30.0 * np.ones_like(t))
    model = Model((new_term("inertia"), new_term("coulomb"), new_term("offset")), "one-way")
    kin = kinematics(trace, 50.0)
    with pytest.raises(ConfigError) as error:
        close_the_loop(model, kin, kin)
    message = str(error.value)
    assert "\n" not in message
    assert "offset.offset_N cannot be told apart from inertia.M_kg, coulomb.F_c_N" in message


def wrong_delay_case() -> tuple[Kinematics, Kinematics, Model]:
    """Data with a 1.5 ms force lead; a declared model that says 0.5 ms and is otherwise
    exact (all declared)."""
    truth = {"tau_ms": 1.5e-3}
    trace = synthetic_trace((new_term("delay", truth),))
    kin = kin_of(trace)
    declared = Model((new_term("inertia", {"M_kg": BASE["M_kg"]}, ()),
                      new_term("viscous", {"F_v_Ns_m": BASE["F_v_Ns_m"]}, ()),
                      new_term("coulomb", {"F_c_N": BASE["F_c_N"], "k_tanh_min_mm": K_TANH}, ()),
                      new_term("delay", {"tau_ms": 0.5e-3}, ())), "declared")
    return kin.window(0, 7000), kin.window(7300, kin.n), declared


def test_a_wrong_declared_delay_is_recalibrated_not_explained_by_an_effect():
    fit_kin, holdout, declared = wrong_delay_case()
    result = close_the_loop(declared, fit_kin, holdout)
    assert result.recalibrated == ("delay.tau_ms",)
    assert result.effects == ()
    step = result.steps[0]
    before, after, std = step.recalibration
    assert before == pytest.approx(0.5e-3)
    assert after == pytest.approx(1.5e-3, abs=0.02e-3)
    assert 0.0 < std < 0.02e-3
    assert result.error_after < 0.2 * result.error_before
    entry = _step_dict(step)
    assert entry["kind"] == "recalibration"
    r = entry["recalibration"]
    assert (r["parameter"], r["unit"]) == ("delay.tau_ms", "ms")
    assert r["declared"] == pytest.approx(0.5)
    assert r["value"] == pytest.approx(1.5, abs=0.02)
    assert r["sigmas"] == pytest.approx(abs(r["value"] - 0.5) / r["std"])
    assert math.isfinite(entry["holdout_delta_bic"]) and entry["holdout_delta_bic"] < -10.0


def test_recalibration_can_be_switched_off():
    fit_kin, holdout, declared = wrong_delay_case()
    result = close_the_loop(declared, fit_kin, holdout,
                            ClosureOptions(recalibrate=False, candidates=("offset", "ripple")))
    assert result.recalibrated == ()


def test_a_step_that_does_not_hold_on_the_held_out_data_is_rejected():
    """Ripple in the fit part only: significant there, worse on the held-out data."""
    ripple = new_term("ripple", {"A_sin_N": 4.0, "A_cos_N": 0.0, "pitch_mm": 0.012})
    offset = new_term("offset", {"offset_N": 8.0})
    fit_kin = kin_of(synthetic_trace((offset, ripple))).window(0, 7000)
    holdout = kin_of(synthetic_trace((offset,), seed=6)).window(7300, 11000)
    result = close_the_loop(base_model(), fit_kin, holdout)
    assert result.effects == ("offset",)
    rejected = {c.name: c.rejected for c in result.rejected}
    assert rejected["ripple"].startswith("not confirmed on the held-out data")


def test_report_lists_rejected_candidates_with_reasons():
    from feedbench.analysis.closure.run import run_closure
    from feedbench.analysis.closure import parse_model_config

    spec = parse_model_config({"terms": {"inertia": {"M_kg": "free"},
                                         "viscous": {"F_v_Ns_m": "free"},
                                         "coulomb": {"k_tanh_min_mm": K_TANH}},
                               "model": {"bandwidth_Hz": 100.0}})
    trace = synthetic_trace((new_term("offset", {"offset_N": 8.0}),))
    data = report_dict(run_closure(spec, trace))
    assert data["effects"][:1] == ["offset"]
    assert data["rejected"] and all(set(r) == {"effect", "reason"} and r["reason"]
                                    for r in data["rejected"])
    assert data["recalibrations"] == []


def test_a_ripple_longer_than_half_the_stroke_is_not_a_ripple():
    kin = kin_of(synthetic_trace())
    ripple = EFFECTS["ripple"]
    half_stroke = float(np.ptp(kin.x)) / 2.0
    values = {"A_sin_N": 1.0, "A_cos_N": 0.0}
    assert ripple.implausible({**values, "pitch_mm": 0.5 * half_stroke}, 30.0, kin) is None
    reason = ripple.implausible({**values, "pitch_mm": 10.0}, 30.0, kin)
    assert reason.startswith("pitch 1e+04 mm longer than half the stroke")


def test_cubic_stiffening_is_identified_on_its_mode():
    mode = {"m_kg": 8.0, "f_n_Hz": 25.0, "zeta": 0.05}
    kappa = 2e-4 * 1e12                                     # 2e-4 /µm²
    truth = (new_term("structural_mode", mode, ()),
             new_term("cubic_stiffening", {"m_kg": 8.0, "kappa_per_um2": kappa,
                                           "f_n_Hz": 25.0, "zeta": 0.05}))
    kin = kin_of(synthetic_trace(truth))
    start = {"f_n_Hz": 25.0, "zeta": 0.05, "kappa_per_um2": 0.5 * kappa}
    model = base_model().with_term(truth[0]).with_term(new_term("cubic_stiffening", start))
    fitted = fit_model(model, kin).model.term("cubic_stiffening").values
    assert fitted["kappa_per_um2"] == pytest.approx(kappa, rel=0.03)
    assert fitted["m_kg"] == pytest.approx(8.0, rel=0.03)
