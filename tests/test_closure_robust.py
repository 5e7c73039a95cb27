"""The closure's search on data that does not fit it (issue 13): a candidate whose fit fails
is rejected with its reason, a base fit that cannot run says why in one line, a wrong
declared value is recalibrated rather than explained by an effect, and a step must pass on
the held-out data too. Data from the inverse model itself: these test the search mechanics
(the independent simulator's cases are in benchmarks/bench_closure_independent.py)."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np
import pytest

from feedbench.analysis.closure import (
    ClosureOptions, Kinematics, Model, Trace, close_the_loop, fit_model, kinematics, new_term, report_dict,
)
from feedbench.analysis.closure.diagnosis import try_effect, _free_basis
from feedbench.analysis.closure.effects import EFFECTS, Context, Offset, Ripple
from feedbench.analysis.closure.model import predict
from feedbench.analysis.closure.report import _step_dict
from feedbench.commands.closure import single_blas_thread
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


@dataclass(frozen=True)
class FarFailingRipple(Ripple):
    """A ripple whose law raises beyond 10 % off a 12 mm pitch: a refinement with 30 %
    difference steps fails, one with √ε steps does not."""

    def columns(self, kin, values):
        if abs(values["pitch_mm"] / 0.012 - 1.0) > 0.1:
            raise ValueError("pitch out of the law's range")
        return super().columns(kin, values)


def test_a_failing_coarse_step_refinement_keeps_the_fine_step_fit():
    """A term refined with both difference steps: the coarse one raises, the √ε one's fit
    is kept (it was thrown away with it, the candidate rejected)."""
    truth = new_term("ripple", {"A_sin_N": 4.0, "A_cos_N": 0.0, "pitch_mm": 0.012})
    kin = kin_of(synthetic_trace((truth,)))
    ripple = new_term("ripple", {"A_sin_N": 0.0, "A_cos_N": 0.0, "pitch_mm": 0.0121})
    effect = FarFailingRipple(**{f.name: getattr(EFFECTS["ripple"], f.name)
                                 for f in fields(Ripple)} | {"difference_step": 0.3})
    fit = fit_model(base_model().with_term(replace(ripple, effect=effect)), kin)
    assert fit.model.term("ripple").values["pitch_mm"] == pytest.approx(0.012, rel=1e-3)
    assert fit.model.term("ripple").values["A_sin_N"] == pytest.approx(4.0, rel=0.01)


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


def test_a_recalibration_without_a_finite_std_says_sigma_unknown():
    """A recalibrated parameter whose std could not be computed (NaN: the information matrix
    was not finite) or is zero: σ moved is NaN (null in JSON), and the text says why instead
    of "± nan, moved inf σ"."""
    fit_kin, holdout, declared = wrong_delay_case()
    step = close_the_loop(declared, fit_kin, holdout).steps[0]
    for std, why in (({}, "not finite"), ({("delay", "tau_ms"): 0.0}, "singular")):
        entry = _step_dict(replace(step, fit=replace(step.fit, std=std)))
        assert math.isnan(entry["recalibration"]["sigmas"])
        assert entry["description"] == (f"declared 0.5 → {entry['recalibration']['value']:.4g} "
                                        f"ms, σ unknown (its information is {why}"
                                        + (": a derivative step left the stable range)"
                                           if why == "not finite" else ")"))


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


def test_recalibrated_delay_moves_the_drive_delay_of_the_replay():
    """A recalibrated declared delay is the drive's delay too: the final model is replayed
    with the controller's delay moved as far, in whole velocity-loop periods (0.5 → 1.5 ms
    at 4 kHz); the base model keeps the declared one."""
    from feedbench.analysis.closure.run import recalibrated_controller
    from feedbench.analysis.closure.spec import ControllerSpec

    fit_kin, holdout, declared = wrong_delay_case()
    result = close_the_loop(declared, fit_kin, holdout)
    controller = ControllerSpec(K_p=8000.0, K_v=160.0, T_i=math.inf, f_velocity=4000.0,
                                f_position=1000.0, delay=0.5e-3, force_limit=500.0,
                                velocity_feedforward=False)
    assert recalibrated_controller(controller, result).delay == pytest.approx(1.5e-3)
    unchanged = close_the_loop(declared, fit_kin, holdout,
                               ClosureOptions(recalibrate=False, candidates=("offset",)))
    assert recalibrated_controller(controller, unchanged) is controller


def test_a_declared_mass_that_is_off_is_one_recalibration():
    """M declared 10 % high: one finding, the recalibration inertia.M_kg back to the truth
    (no effect ΔM a beside it); the retired effect name says what took its place."""
    kin = kin_of(synthetic_trace())
    declared = Model((new_term("inertia", {"M_kg": 1.1 * BASE["M_kg"]}, ()),
                      new_term("viscous", {"F_v_Ns_m": BASE["F_v_Ns_m"]}, ()),
                      new_term("coulomb", {"F_c_N": BASE["F_c_N"], "k_tanh_min_mm": K_TANH}, ())),
                     "declared")
    result = close_the_loop(declared, kin.window(0, 7000), kin.window(7300, kin.n))
    assert result.recalibrated == ("inertia.M_kg",) and result.effects == ()
    before, after, std = result.steps[0].recalibration
    assert (before, after) == (pytest.approx(33.0), pytest.approx(BASE["M_kg"], rel=0.005))
    assert 0.0 < std < 0.05
    with pytest.raises(ValueError, match="'inertia_mismatch' is retired: a declared mass"):
        ClosureOptions(candidates=("inertia_mismatch",))
    from feedbench.analysis.closure import parse_model_config
    with pytest.raises(ConfigError, match="terms.inertia_mismatch: retired"):
        parse_model_config({"terms": {"inertia": {"M_kg": 30.0}, "inertia_mismatch": {}}})


def test_backlash_load_on_a_contact_spring_is_identified_from_reversals():
    """A load behind a 200 µm play on a 30 Hz contact (ζ 0.3), braked by 0.5 N/kg, on
    reversal moves (the model's own term, its force band-limited at 400 Hz, above the fit's
    100 Hz; 0.3 N noise): the candidate, from its screened
    grid, gets play, contact and friction within 10 % and the error to the noise."""
    truth = {"m_load_kg": 6.0, "width_um": 200e-6, "f_contact_Hz": 30.0, "zeta_contact": 0.3,
             "friction_N_kg": 0.5}
    t = np.arange(12000) / 1000.0
    x = 0.02 * np.sin(2 * np.pi * 0.5 * t) + 0.004 * np.sin(2 * np.pi * 1.7 * t + 1.0)
    v = np.gradient(x, t)
    motion = Kinematics(x, v, np.gradient(v, t), np.zeros_like(t), np.ones(t.size, bool),
                        1e-3, 400.0)
    world = Model((new_term("inertia", {"M_kg": BASE["M_kg"]}),
                   new_term("viscous", {"F_v_Ns_m": BASE["F_v_Ns_m"]}),
                   new_term("coulomb", {"F_c_N": BASE["F_c_N"], "k_tanh_min_mm": K_TANH}),
                   new_term("backlash", truth)))
    force = predict(world, motion).reading + np.random.default_rng(5).normal(0, 0.3, t.size)
    kin = kin_of(Trace(t, x, force))
    current = fit_model(base_model(), kin)
    context = Context(current.residual, current.acting,
                      {term.name: term.values for term in current.model.terms})
    candidate = try_effect(EFFECTS["backlash"], current, kin, context, _free_basis(current, kin), 1)
    fitted = candidate.fit.model.term("backlash").values
    for key in ("width_um", "f_contact_Hz", "zeta_contact", "friction_N_kg", "m_load_kg"):
        assert fitted[key] == pytest.approx(truth[key], rel=0.1), key
    assert candidate.fit.error < 0.2 * current.error
