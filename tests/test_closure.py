"""The closure's analysis core against synthetic data with known answers.

Synthetic force = the inverse model itself at known parameters, plus noise; each effect of
the library must be identifiable from it, and the search must add it (and nothing on clean
data). The model config parser must name the field of every error.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from feedbench.analysis.closure import (
    ClosureOptions, Kinematics, Model, Trace, close_the_loop, fit_model, kinematics, new_term,
    parse_model_config,
)
from feedbench.analysis.closure.model import predict
from feedbench.analysis.closure.trace import lowpass, standstill_speed
from feedbench.commands.closure import single_blas_thread
from feedbench.config import ConfigError

FS = 1000.0
BANDWIDTH = 100.0


@pytest.fixture(autouse=True)
def _one_blas_thread():
    with single_blas_thread():
        yield


MOTION = ((0.04, 0.4, 0.0), (0.01, 1.3, 1.0), (4e-4, 7.0, 2.0), (6e-5, 17.0, 0.5),
          (1.5e-5, 31.0, 1.5))
"""(amplitude m, frequency Hz, phase rad) of the synthetic motion: reversals, many speeds,
and enough acceleration content up to 31 Hz for mass, mode and delay."""

K_TANH = 600.0
"""A soft Coulomb transition (s/m), so that the synthetic force stays in the filter's band."""


def exact_kinematics(seconds: float = 12.0) -> Kinematics:
    """Analytic position, velocity and acceleration of MOTION plus a random motion
    band-limited to 60 Hz (0.3 m/s² RMS, its derivatives exact in the frequency domain)."""
    t = np.arange(int(seconds * FS)) / FS
    x, v, a = (sum(amp * (2 * np.pi * f) ** k * np.sin(2 * np.pi * f * t + phase + k * np.pi / 2)
                   for amp, f, phase in MOTION) for k in range(3))
    noise = np.random.default_rng(1).normal(size=t.size)
    random = [lowpass(noise, 60.0, 1 / FS, k) for k in range(3)]
    scale = 0.3 / random[2].std()
    x, v, a = (x + scale * random[0], v + scale * random[1], a + scale * random[2])
    return Kinematics(x, v, a, np.zeros_like(t), np.ones(t.size, bool), 1 / FS, BANDWIDTH)


BASE = {"M_kg": 30.0, "F_v_Ns_m": 150.0, "F_c_N": 35.0}


def base_model() -> Model:
    return Model((new_term("inertia"), new_term("viscous"),
                  new_term("coulomb", {"k_tanh_min_mm": K_TANH})))


def synthetic_trace(extra: tuple = (), noise: float = 0.3, seed: int = 5) -> Trace:
    """A trace whose force is the model (base + `extra` terms at their values) plus noise."""
    kin = exact_kinematics()
    truth = Model((new_term("inertia", {"M_kg": BASE["M_kg"]}),
                   new_term("viscous", {"F_v_Ns_m": BASE["F_v_Ns_m"]}),
                   new_term("coulomb", {"F_c_N": BASE["F_c_N"], "k_tanh_min_mm": K_TANH}))
                  + extra)
    force = predict(truth, kin).reading + np.random.default_rng(seed).normal(0, noise, kin.n)
    return Trace(np.arange(kin.n) / FS, kin.x, force)


def kin_of(trace: Trace):
    """Kinematics at BANDWIDTH, samples below 2 % of the 95th-percentile speed not used."""
    return kinematics(trace, BANDWIDTH, standstill_speed(kinematics(trace, BANDWIDTH), 0.02))


def test_kinematics_differentiates_exactly_in_band():
    t = np.arange(4000) / FS
    f = 60.0  # 0.06 fs: central differences would lose 14 % of the acceleration here
    x = 1e-3 * np.sin(2 * np.pi * f * t)
    kin = kinematics(Trace(t, x, np.zeros_like(x)), 150.0)
    w = 2 * np.pi * f
    edge = (t.size - kin.n) // 2
    a_true = -w**2 * 1e-3 * np.sin(w * t[edge:edge + kin.n])
    gain = 1.0 / (1.0 + (f / 150.0) ** 8)
    assert np.max(np.abs(kin.a - gain * a_true)) < 2e-3 * np.max(np.abs(a_true))


def test_base_fit_recovers_mass_and_friction_with_honest_std():
    kin = kin_of(synthetic_trace())
    fit = fit_model(base_model(), kin)
    values = {k: v for t in fit.model.terms for k, v in t.values.items()}
    for key, truth in BASE.items():
        assert values[key] == pytest.approx(truth, rel=0.01)
        std = fit.std[(next(t.name for t in fit.model.terms if key in t.values), key)]
        assert abs(values[key] - truth) < 5 * std, key
    assert fit.error < 0.02


EFFECT_CASES = [
    # name, true values (SI), start values, relative tolerance
    ("offset", {"offset_N": 6.0}, {}, 0.03),
    ("stribeck", {"dF_s_N": 25.0, "v_s_mm_min": 0.01, "k_tanh_min_mm": K_TANH},
     {"v_s_mm_min": 0.005, "k_tanh_min_mm": K_TANH}, 0.1),
    ("ripple", {"A_sin_N": 3.0, "A_cos_N": -2.0, "pitch_mm": 0.008}, {"pitch_mm": 0.0079}, 0.03),
    ("structural_mode", {"m_kg": 8.0, "f_n_Hz": 45.0, "zeta": 0.05},
     {"f_n_Hz": 40.0, "zeta": 0.1}, 0.03),
    ("delay", {"tau_ms": 0.0012}, {"tau_ms": 0.0}, 0.03),
    ("amplitude_nonlinearity", {"beta_per_kN": 2e-3}, {"beta_per_kN": 0.0}, 0.03),
]
"""(backlash, whose SSR is rugged, is identified from its screened grid in
test_closure_robust.py)"""


@pytest.mark.parametrize("name, truth, start, tolerance", EFFECT_CASES,
                         ids=[c[0] for c in EFFECT_CASES])
def test_each_effect_is_identified_from_its_own_signature(name, truth, start, tolerance):
    kin = kin_of(synthetic_trace((new_term(name, truth),)))
    fit = fit_model(base_model().with_term(new_term(name, start)), kin)
    fitted = fit.model.term(name).values
    for key, value in truth.items():
        assert fitted[key] == pytest.approx(value, rel=tolerance, abs=1e-9), key
    assert fit.error < 0.02


def test_search_adds_the_missing_effect_then_stops():
    trace = synthetic_trace((new_term("ripple", {"A_sin_N": 4.0, "A_cos_N": 0.0,
                                                  "pitch_mm": 0.012}),))
    kin = kin_of(trace)
    fit_kin, holdout = kin.window(0, 7000), kin.window(7300, kin.n)
    result = close_the_loop(base_model(), fit_kin, holdout)
    assert result.effects == ("ripple",)
    assert result.final.model.term("ripple").values["pitch_mm"] == pytest.approx(0.012, rel=1e-3)
    assert result.error_after < 0.5 * result.error_before


def test_search_adds_nothing_to_a_complete_model():
    kin = kin_of(synthetic_trace())
    result = close_the_loop(base_model(), kin.window(0, 7000), kin.window(7300, kin.n))
    assert result.effects == ()
    assert result.error_after == result.error_before


def test_sensor_gain_and_mass_recalibration_apply_only_to_declared_terms():
    declared = Model((new_term("inertia", {"M_kg": 30.0}, ()), new_term("viscous"),
                      new_term("coulomb", {"k_tanh_min_mm": K_TANH})))
    options = ClosureOptions(candidates=("sensor_gain",))
    from feedbench.analysis.closure.diagnosis import rank_candidates, rank_recalibrations

    kin = kin_of(synthetic_trace())
    for model, expected in ((declared, {"sensor_gain", "inertia.M_kg"}), (base_model(), set())):
        fit = fit_model(model, kin)
        names = {c.name for c in rank_candidates(fit, kin, options)
                 + rank_recalibrations(fit, kin, options)}
        assert names == expected


GOOD = {"model": {"name": "m", "bandwidth_Hz": 50.0},
        "terms": {"inertia": {"M_kg": "free"}, "viscous": {"F_v_Ns_m": 200.0},
                  "stribeck": {"v_s_mm_min": {"value": 300.0, "free": True}},
                  "coulomb": {}},
        "controller": {"K_p_Ns_m": 8000.0, "K_v_1_s": 160.0}}


def test_model_config_converts_units_and_free_flags():
    spec = parse_model_config(GOOD)
    stribeck = spec.model.term("stribeck")
    assert stribeck.values["v_s_mm_min"] == pytest.approx(300.0 / 60000.0)
    assert stribeck.free == {"dF_s_N", "v_s_mm_min"}
    assert spec.model.term("viscous").free == frozenset()
    assert spec.model.term("coulomb").free == {"F_c_N"}
    assert spec.controller.T_i == math.inf
    assert spec.bandwidth == 50.0


@pytest.mark.parametrize("patch, message", [
    ({"terms": {"viscous": {}}}, "terms.inertia: required"),
    ({"terms": {"inertia": {}, "friction": {}}}, "terms.friction: unknown term"),
    ({"terms": {"inertia": {"M_kg": "loose"}}}, "terms.inertia.M_kg: must be a number"),
    ({"terms": {"inertia": {}, "delay": {"tau_ms": 50.0}}}, "terms.delay.tau_ms: must lie in"),
    ({"terms": {"inertia": {}, "stribeck": {}}}, "terms.stribeck: needs terms.coulomb"),
    ({"terms": {"inertia": {}, "coulomb": {"k_tanh_min_mm": "free"}}},
     "terms.coulomb.k_tanh_min_mm: a setting"),
    ({"terms": {"inertia": {}}, "closure": {"candidates": ["magic"]}},
     "closure.candidates: unknown effect 'magic'"),
    ({"terms": {"inertia": {}}, "controller": {"K_v_1_s": 1.0}},
     "controller.K_p_Ns_m: required"),
])
def test_model_config_errors_name_the_field(patch, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        parse_model_config(patch)


def test_follower_memo_returns_the_plain_simulation():
    """`effects.follower_memo` (one closure run) hands back, for each exact input, the very
    simulation computed without it: bit for bit, once per input, read-only; recomputed
    when the motion changed in place or a parameter differs only in the sign of zero; gone
    after the block."""
    from feedbench.analysis.closure import effects

    t = np.arange(2000) * 1e-3
    x, v = 1e-3 * np.sin(2 * np.pi * t), 2e-3 * np.pi * np.cos(2 * np.pi * t)
    inputs = [(300.0, 0.05), (300.0, 0.05, 0.0, 2e-6, 1.5, 1e4), (300.0, 0.05, 0.0, -0.0)]
    plain = [effects.follower_force(x, v, 1e-3, *p) for p in inputs]
    with effects.follower_memo():
        memo = effects._FOLLOWER_MEMO.get()
        first = [effects.follower_force(x, v, 1e-3, *p) for p in inputs]
        again = [effects.follower_force(x, v, 1e-3, *p) for p in inputs]
        with effects.follower_memo():  # nested: the same memo
            assert effects.follower_force(x, v, 1e-3, *inputs[0]) is first[0]
        assert len(memo.forces) == 3  # -0.0 and 0.0 kept apart
        for a, b, c in zip(plain, first, again):
            assert a.tobytes() == b.tobytes() and b is c and not b.flags.writeable
        x[1000:] += 1e-4  # changed in place: simulated anew
        moved = effects.follower_force(x, v, 1e-3, *inputs[1])
        assert moved is not first[1] and len(memo.forces) == 1
    assert effects._FOLLOWER_MEMO.get() is None
    assert moved.tobytes() == effects.follower_force(x, v, 1e-3, *inputs[1]).tobytes()


def _plain_follower(x, v, dt, omega, zeta, kappa, half_play, friction, k_tanh, steps):
    """The follower's RK4 as first written: the friction term evaluated at every stage."""
    from feedbench.analysis.closure.effects import _spring_force

    spring = _spring_force.py_func
    out = np.empty(x.size)
    xt, vt = x[0], v[0]
    h, w2, c = dt / steps, omega * omega, 2.0 * zeta * omega
    for i in range(x.size):
        out[i] = spring(x[i] - xt, v[i] - vt, w2, c, kappa, half_play)
        if i + 1 == x.size:
            break
        dx, dv = x[i + 1] - x[i], v[i + 1] - v[i]
        for j in range(steps):
            f0, f1, f2 = j / steps, (j + 0.5) / steps, (j + 1.0) / steps
            a1 = (spring(x[i] + f0 * dx - xt, v[i] + f0 * dv - vt, w2, c, kappa, half_play)
                  - friction * math.tanh(k_tanh * vt))
            v2 = vt + 0.5 * h * a1
            a2 = (spring(x[i] + f1 * dx - (xt + 0.5 * h * vt), v[i] + f1 * dv - v2, w2, c,
                         kappa, half_play) - friction * math.tanh(k_tanh * v2))
            v3 = vt + 0.5 * h * a2
            a3 = (spring(x[i] + f1 * dx - (xt + 0.5 * h * v2), v[i] + f1 * dv - v3, w2, c,
                         kappa, half_play) - friction * math.tanh(k_tanh * v3))
            v4 = vt + h * a3
            a4 = (spring(x[i] + f2 * dx - (xt + h * v3), v[i] + f2 * dv - v4, w2, c, kappa,
                         half_play) - friction * math.tanh(k_tanh * v4))
            xt += h * (vt + 2.0 * v2 + 2.0 * v3 + v4) / 6.0
            vt += h * (a1 + 2.0 * a2 + 2.0 * a3 + a4) / 6.0
    return out


def test_follower_kernel_is_the_plain_rk4():
    """The numba follower (which skips the friction term when it is zero) gives, bit for
    bit, the plain RK4 with the term at every stage: with and without play, friction,
    cubic stiffening, on motions through signed zeros."""
    from feedbench.analysis.closure.effects import _follower

    rng = np.random.default_rng(7)
    for trial in range(24):
        n, dt = 150, 1e-3
        x = np.cumsum(rng.normal(size=n)) * 10.0 ** rng.uniform(-7, -4)
        x[rng.random(n) < 0.2] = 0.0 if trial % 2 else -0.0
        v = np.gradient(x, dt)
        v[rng.random(n) < 0.1] = -0.0
        p = (1e-3, 10.0 ** rng.uniform(1.5, 3.5), (0.0, 0.012, 0.3)[trial % 3],
             (0.0, -0.0, 1e9)[trial % 4 % 3], (0.0, 1e-6)[trial % 2],
             (0.0, -0.0, 2.0)[trial % 3 - 1], (0.0, 1.5e4, math.inf)[trial % 5 % 3],
             int(rng.integers(1, 10)))
        plain = _plain_follower(x, v, *p)
        assert _follower(x, v, *p).tobytes() == plain.tobytes(), p


def test_followers_side_by_side_are_the_single_follower():
    """`effects._followers` (bodies stepped side by side, for the screening's prefetch) and
    `_followers_staged` (a stage at a time over all bodies, for 8 or more) give each body
    what it gives the body alone, bit for bit (no body sees another's state); a
    prefetched input is what `follower_force` then returns, and its linear mode is
    simulated once."""
    from feedbench.analysis.closure import effects

    rng = np.random.default_rng(11)
    n, dt = 400, 1e-3
    x = np.cumsum(rng.normal(size=n)) * 1e-5
    x[rng.random(n) < 0.1] = -0.0
    v = np.gradient(x, dt)
    table = np.array([(10.0 ** rng.uniform(1.5, 3.5), zeta, kappa, half, friction, k_tanh)
                      for zeta in (0.012, 0.3) for kappa in (0.0, 1e9)
                      for half in (0.0, 2e-6) for friction in (0.0, -0.0, 2.0)
                      for k_tanh in (0.0, 1.5e4, math.inf)])
    side_by_side = effects._followers(x, v, dt, table, 9)
    for row, out in zip(table, side_by_side):
        assert out.tobytes() == effects._follower(x, v, dt, *row, 9).tobytes(), row
    assert len(table) >= effects.STAGED_BODIES  # the staged kernel of a large batch: the same
    assert effects._followers_staged(x, v, dt, table, 9).tobytes() == side_by_side.tobytes()
    inputs = [(300.0, 0.3, 0.0, 1e-6, 2.0, 1.5e4), (300.0, 0.012, 0.0, 0.0, 0.0, 0.0),
              (300.0, 0.012, 0.0, 0.0, 0.0, 0.0), (3000.0, 0.3, 0.0, 1e-6, 1.0, 1.5e4)]
    with effects.follower_memo():
        effects.prefetch_followers(x, v, dt, inputs)
        memo = effects._FOLLOWER_MEMO.get()
        assert len(memo.forces) == 3
        held = list(memo.forces.values())
        got = [effects.follower_force(x, v, dt, *one) for one in inputs]
        assert len(memo.forces) == 3 and got[1] is got[2]
        assert all(any(g is h for h in held) for g in got)
    for one, g in zip(inputs, got):
        assert g.tobytes() == effects.follower_force(x, v, dt, *one).tobytes()
