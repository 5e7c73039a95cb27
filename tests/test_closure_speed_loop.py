"""A force channel that falls as the speed rises is not a passive axis's (issue 24: "a result
judges itself"): the verdict says so, on synthetic data with a known slope and on the
gallery's ODrive pull test, and nowhere else in the gallery; a Stribeck decay is friction
where the axis turns both ways, and said to look alike where it turns one way only. Behind
a speed loop, a cogging force is still found: the viscous coefficient the loop's slope holds
on 0 does not hide it."""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest

from feedbench.analysis.closure import (
    ClosureOptions, Kinematics, Trace, close_the_loop, fit_model, new_term,
)
from feedbench.analysis.closure.diagnosis import falls_with_speed
from feedbench.analysis.closure.model import Model, predict
from test_closure import (
    BANDWIDTH, BASE, FS, K_TANH, base_model, exact_kinematics, kin_of, synthetic_trace,
)
from test_closure_gallery import DATASETS, _closed

SPEED_GAIN = 400.0
"""N·s/m: how much a synthetic speed loop's effort drops per m/s of speed."""
NOT_DESCRIBED = 1.0
"""A held-out NRMSE above `describes_below`: the verdict's reasons are wanted."""
CONTROLLER = "looks like a speed controller's effort"
STRIBECK = new_term("stribeck", {"dF_s_N": 20.0, "v_s_mm_min": 0.01, "k_tanh_min_mm": K_TANH})
"""A Stribeck excess of 20 N decaying at 10 mm/s (SI values)."""
SLOW_STRIBECK = new_term("stribeck", {"dF_s_N": 20.0, "v_s_mm_min": 0.05,
                                      "k_tanh_min_mm": K_TANH})
"""20 N decaying at 50 mm/s: on the two-way motion the residual's slope then carries 27 % of
it (above `min_explained`), the decay 54 %."""


def _truth(*extra) -> Model:
    return Model((new_term("inertia", {"M_kg": BASE["M_kg"]}),
                  new_term("coulomb", {"F_c_N": BASE["F_c_N"], "k_tanh_min_mm": K_TANH}))
                 + extra)


def _controller_effort() -> Trace:
    """The force of a speed loop holding an axis against an unseen load: inertia, plus an
    effort that rises as the speed drops (−SPEED_GAIN v), plus noise."""
    kin = exact_kinematics()
    inertia = Model((new_term("inertia", {"M_kg": BASE["M_kg"]}),))
    force = (predict(inertia, kin).reading - SPEED_GAIN * kin.v
             + np.random.default_rng(3).normal(0, 0.3, kin.n))
    return Trace(np.arange(kin.n) / FS, kin.x, force)


def _one_way_kinematics() -> Kinematics:
    """12 s at 1 kHz moving forward only: 1–49 mm/s in a 0.4 Hz swing plus 7 Hz content."""
    t = np.arange(int(12 * FS)) / FS
    parts = ((0.022, 0.4), (0.002, 7.0))
    v = 0.025 + sum(amp * np.sin(2 * np.pi * f * t) for amp, f in parts)
    a = sum(amp * 2 * np.pi * f * np.cos(2 * np.pi * f * t) for amp, f in parts)
    x = 0.025 * t - sum(amp / (2 * np.pi * f) * np.cos(2 * np.pi * f * t) for amp, f in parts)
    return Kinematics(x, v, a, np.zeros_like(t), np.ones(t.size, bool), 1 / FS, BANDWIDTH)


def _with_force(kin: Kinematics, truth: Model) -> Kinematics:
    noise = np.random.default_rng(4).normal(0, 0.3, kin.n)
    return replace(kin, force=predict(truth, kin).reading + noise)


def _speed_loop_against_cogging(seed: int) -> Kinematics:
    """14 s at 1 kHz (the first 2 s dropped): a 0.5 kg carriage held at 50 mm/s by a PI
    speed loop (63 N·s/m, 2000 N/m: about 20 Hz) against a 40 N pull and a cogging force
    COG_N·sin(2πx/COG_PITCH_M), integrated at 20 kHz; the force reading is the loop's
    effort plus 0.05 N of noise. Its physics is exact: effort = M a + pull + cogging."""
    mass, kp, ki, v_ref, pull, dt, sub = 0.5, 63.0, 2000.0, 0.05, 40.0, 1 / FS, 20
    warm, n = int(2 * FS), int(14 * FS)
    x, v, integral = 0.0, v_ref, pull
    out = np.empty((3, n))
    for k in range(n):
        integral += ki * (v_ref - v) * dt
        effort = kp * (v_ref - v) + integral
        out[:, k] = x, v, effort
        for _ in range(sub):
            v += (effort - COG_N * np.sin(2 * np.pi * x / COG_PITCH_M) - pull) / mass * dt / sub
            x += v * dt / sub
    x, v, effort = out[:, warm:]
    force = effort + np.random.default_rng(seed).normal(0, 0.05, x.size)
    return Kinematics(x, v, np.gradient(v, dt), force, np.ones(x.size, bool), dt, BANDWIDTH)


COG_N, COG_PITCH_M = 3.0, 0.004


@pytest.mark.parametrize("seed", [2, 3])
def test_a_cogging_force_behind_a_speed_loop_is_found_with_its_pitch(seed):
    """The loop's slope holds the viscous coefficient on 0; candidates are screened against
    what the model can still move, so the cogging is the finding after the pull (before,
    the screening let the held coefficient take the speed's cogging content: offset, delay,
    a ripple at half the pitch, a structural mode). Tolerances: the pull ± 1 N, the
    cogging ± 5 % in amplitude and ± 0.1 % in pitch, the mass ± 10 % (0.48 kg: the
    band-limited acceleration)."""
    kin = _speed_loop_against_cogging(seed)
    cut = int(0.7 * kin.n)
    base = Model((new_term("inertia"), new_term("viscous")))
    result = close_the_loop(base, kin.window(0, cut - 50), kin.window(cut + 50, kin.n),
                            ClosureOptions())
    assert result.effects == ("offset", "ripple")
    final = {t.name: t.values for t in result.final.model.terms}
    assert final["offset"]["offset_N"] == pytest.approx(40.0, abs=1.0)
    ripple = final["ripple"]
    assert np.hypot(ripple["A_sin_N"], ripple["A_cos_N"]) == pytest.approx(COG_N, rel=0.05)
    assert ripple["pitch_mm"] == pytest.approx(COG_PITCH_M, rel=1e-3)
    assert final["inertia"]["M_kg"] == pytest.approx(0.5, rel=0.1)
    assert result.error_after < 0.01


def _slope(reason: str) -> float:
    return float(re.search(r"slope over the speed is (-?[\d.]+) N·s/m", reason).group(1))


def test_a_speed_loops_effort_is_named_with_its_slope():
    kin = kin_of(_controller_effort())
    model = fit_model(base_model(), kin).model
    reasons = falls_with_speed(model, kin, NOT_DESCRIBED, ClosureOptions())
    assert len(reasons) == 1 and CONTROLLER in reasons[0], reasons
    viscous = model.term("viscous").values["F_v_Ns_m"]
    assert viscous == pytest.approx(0.0, abs=1e-6), "the fit held at its physical bound"
    assert _slope(reasons[0]) == pytest.approx(-SPEED_GAIN, rel=0.05)


def test_nothing_is_said_where_the_model_describes_the_data():
    kin = kin_of(_controller_effort())
    model = fit_model(base_model(), kin).model
    assert falls_with_speed(model, kin, ClosureOptions().describes_below, ClosureOptions()) == []


def test_a_passive_axis_is_not_named():
    kin = kin_of(synthetic_trace())
    model = fit_model(base_model(), kin).model
    assert falls_with_speed(model, kin, NOT_DESCRIBED, ClosureOptions()) == []


def test_a_stribeck_decay_both_ways_is_friction_not_a_controller():
    kin = _with_force(exact_kinematics(), _truth(SLOW_STRIBECK))
    model = fit_model(base_model(), kin).model
    assert falls_with_speed(model, kin, NOT_DESCRIBED, ClosureOptions()) == []


def test_a_stribeck_decay_one_way_only_is_said_to_look_alike():
    """The reviewer's case: one direction, 1–49 mm/s, Stribeck 20 N at 10 mm/s: the base fit
    holds viscous at 0 and the residual falls with the speed; that is friction or a speed
    loop, and one way only the verdict cannot tell which."""
    kin = _with_force(_one_way_kinematics(), _truth(STRIBECK))
    model = fit_model(base_model(), kin).model
    [reason] = falls_with_speed(model, kin, NOT_DESCRIBED, ClosureOptions())
    assert "the axis moved one way only" in reason and "look alike" in reason
    assert CONTROLLER not in reason


@pytest.mark.parametrize("dataset", DATASETS, ids=lambda d: d.name)
def test_in_the_gallery_only_the_speed_loop_record_is_named(dataset):
    """gchenfc/ODrive's pull test is the current of a speed loop at 1 rev/s pulling a
    cogging motor through a string (its README), one way only; every other slice is a
    passive reading."""
    report = _closed(dataset.name)
    named = [any("the force falls as the speed rises" in reason
                 for reason in report[verdict]["reasons"])
             for verdict in ("base_verdict", "final_verdict")]
    assert named == [dataset.name == "odrive-pull"] * 2
