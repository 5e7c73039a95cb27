"""The generalized Maxwell-slip (GMS) friction model (Al-Bender, Lampaert, Swevers 2005)
against a second implementation (scipy's solve_ivp on the paper's hybrid ODEs, each block's
stick → slip switch found as an event) and against its known properties: Masing's rule and
non-local memory in the rate-independent case, steady sliding on the Stribeck curve, and one
block reducing to Dahl's law at α → 0 and to the elasto-plastic law at z_ba → z_ss."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from feedbench.models.dynamic_friction import (
    GMS, ElastoPlastic, dahl_force, maxwell_slip_limits, maxwell_slip_normalised,
)

FS = 2000.0
F_C = 30.0

LAW = GMS(stiffness=(8e6, 4e6, 2e6, 1e6), weights=(0.1, 0.2, 0.3, 0.4), F_c=F_C, F_s=45.0,
          v_s=2e-4, C=1.5e4, delta=2.0, sigma1=300.0, sigma2=100.0)
"""Slip displacements α_i F_c/k_i of 0.375 to 12 µm, a Stribeck peak of 1.5 F_c at speeds
below 0.2 mm/s, a frictional lag |s|/C of 2–3 ms."""


def sine_velocity(amplitude: float, frequency: float, seconds: float, fs: float = FS
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Time (s) and velocity (m/s) of x = amplitude sin(2π f t) sampled at fs."""
    t = np.arange(int(seconds * fs)) / fs
    return t, amplitude * 2 * np.pi * frequency * np.cos(2 * np.pi * frequency * t)


def path(v: np.ndarray, fs: float = FS) -> np.ndarray:
    """Position (m) from 0 of v linear between samples (the input the law assumes)."""
    return np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) / fs)])


def reference_blocks(law: GMS, t: np.ndarray, v: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Block forces (N, samples × blocks) and states (0 sticking, ±1 slipping that way)
    of Eqs. (3)–(4) by DOP853 on v linear between
    the samples: each sample interval split where v crosses zero (every block sticks
    again), each piece integrated until a sticking block's d F_i reaches α_i |s(v)| (a
    terminal event), which then slips: no code shared with the law's exact substeps."""
    k, alpha = np.array(law.stiffness), np.array(law.weights)
    level = lambda speed: (law.F_c + (law.F_s - law.F_c)            # noqa: E731
                           * np.exp(-abs(speed / law.v_s) ** law.delta))
    velocity = lambda time: float(np.interp(time, t, v))            # noqa: E731
    force, direction = np.zeros(k.size), np.zeros(k.size)     # 0 sticking, ±1 slipping
    out, states = np.zeros((t.size, k.size)), np.zeros((t.size, k.size))
    for i in range(t.size - 1):
        cuts = [t[i], t[i + 1]]
        if v[i] * v[i + 1] < 0.0:
            cuts.insert(1, t[i] + (t[i + 1] - t[i]) * v[i] / (v[i] - v[i + 1]))
        for start, end in zip(cuts[:-1], cuts[1:]):
            d = np.sign(velocity(0.5 * (start + end)))
            if d == 0.0:
                continue
            direction[direction != d] = 0.0                      # reversed: sticks
            now = start
            while now < end:
                direction[d * force >= alpha * level(velocity(now))] = d
                slipping = direction != 0.0

                def rhs(time, f, d=d):
                    speed = velocity(time)
                    s = d * level(speed)
                    return np.where(slipping, d * law.C * (alpha - f / s), k * speed)

                events = []
                for j in np.flatnonzero(~slipping):
                    def hit(time, f, j=j, d=d):
                        return d * f[j] - alpha[j] * level(velocity(time))
                    hit.terminal, hit.direction = True, 1.0
                    events.append((j, hit))
                solution = solve_ivp(rhs, (now, end), force, method="DOP853",
                                     events=[e for _, e in events] or None, rtol=1e-11,
                                     atol=1e-11 * law.F_c)
                assert solution.success
                force = solution.y[:, -1]
                if solution.status == 1:
                    first = min((te[0], j) for (j, _), te in zip(events, solution.t_events)
                                if te.size)
                    now = first[0]
                    direction[first[1]] = d
                else:
                    now = end
        out[i + 1], states[i + 1] = force, direction
    return out, states


def reference_force(law: GMS, t: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Eq. (6) on the reference blocks: Σ F_i + σ1/Σk Σ dF_i/dt + σ2 v, the rates from the
    block states at each sample (Eq. (4) for a block slipping the way v goes, else (3))."""
    k, alpha = np.array(law.stiffness), np.array(law.weights)
    blocks, states = reference_blocks(law, t, v)
    s = np.sign(v) * (law.F_c + (law.F_s - law.F_c) * np.exp(-np.abs(v / law.v_s) ** law.delta))
    slipping = (states != 0.0) & (states == np.sign(v)[:, None])
    with np.errstate(divide="ignore", invalid="ignore"):
        slip_rate = np.sign(v)[:, None] * law.C * (alpha - blocks / s[:, None])
    rate = np.where(slipping, slip_rate, k * v[:, None]).sum(axis=1)
    return blocks.sum(axis=1) + law.sigma1 / k.sum() * rate + law.sigma2 * v


def virgin(law: GMS, x: np.ndarray | float) -> np.ndarray:
    """The virgin curve of the rate-independent law from rest, written out from the model:
    Σ_i min(k_i x, α_i F_c) for x ≥ 0 (every block elastic until its limit)."""
    x = np.asarray(x, dtype=float)[..., None]
    return np.minimum(np.array(law.stiffness) * x, np.array(law.weights) * law.F_c).sum(-1)


# --- against the second implementation ------------------------------------------------------

def test_gms_matches_solve_ivp_on_a_reversal_record():
    """Four blocks, Stribeck, finite attraction C, block damping and viscous term, a 20 µm
    sine at 5 Hz (reversals, every block slipping on each stroke) at 2 kHz: the force and
    every block's force within 5e-5 F_c of DOP853 with events (measured: 1.2e-5 F_c on the
    blocks; the law holds v and s(v) at the substep midpoint, the reference follows v
    linear: 2e-4 F_c with substeps of 0.05 v_s, 9e-5 at 0.02, 1.2e-5 at 0.005, the
    default)."""
    t, v = sine_velocity(20e-6, 5.0, 0.5)
    blocks, _ = LAW.block_forces(v, 1 / FS)
    reference, _ = reference_blocks(LAW, t, v)
    assert np.max(np.abs(reference)) > 0.35 * F_C            # the blocks saturated
    np.testing.assert_allclose(blocks, reference, rtol=0, atol=5e-5 * F_C)
    np.testing.assert_allclose(LAW.force(v, 1 / FS), reference_force(LAW, t, v), rtol=0,
                               atol=5e-5 * F_C)


def test_gms_loop_is_hysteretic_with_frictional_lag():
    """The same record: the force–displacement loop encloses a positive area (energy
    dissipated per cycle) and the force is not a function of the velocity alone (the two
    branches at the same speed differ by more than F_c)."""
    t, v = sine_velocity(20e-6, 5.0, 1.0)
    x, force = path(v), LAW.force(v, 1 / FS) - LAW.sigma2 * v
    cycle = slice(t.size // 2, t.size // 2 + int(FS / 5.0) + 1)
    assert float(np.sum(0.5 * (force[cycle][1:] + force[cycle][:-1]) * np.diff(x[cycle]))) > 0
    near_zero = np.abs(v[cycle]) < 0.05 * np.max(np.abs(v))
    assert np.ptp(force[cycle][near_zero]) > F_C


# --- its properties -----------------------------------------------------------------------

RATE_FREE = GMS(stiffness=(9e6, 5e6, 3e6, 2e6, 1e6, 0.5e6), weights=(0.05, 0.1, 0.15, 0.2,
                                                                      0.2, 0.3),
                F_c=F_C, F_s=F_C, v_s=1.0, C=1e6)
"""F_s = F_c: s(v) is constant, a slipping block stays at its limit, C does not matter."""


def test_gms_virgin_curve_and_masing_rule():
    """A 40 µm sine from rest: the first quarter is the virgin curve Σ min(k_i x, α_i F_c);
    after the reversal at x = A the branch is F(A) − 2 F_v((A − x)/2), after the one at −A
    it is F(−A) + 2 F_v((x + A)/2) (Masing: the virgin curve scaled by 2 in x and F);
    within 1e-9 F_c (measured: 1e-14 F_c, the law is exact here)."""
    t, v = sine_velocity(40e-6, 5.0, 0.45)
    x, force = path(v), RATE_FREE.force(v, 1 / FS)
    top, bottom = 100, 300                                     # v = 0 there (samples)
    np.testing.assert_allclose(force[:top + 1], virgin(RATE_FREE, x[:top + 1]), rtol=0,
                               atol=1e-9 * F_C)
    down = slice(top, bottom + 1)
    np.testing.assert_allclose(force[down], force[top] - 2 * virgin(RATE_FREE,
                                                                    (x[top] - x[down]) / 2),
                               rtol=0, atol=1e-9 * F_C)
    up = slice(bottom, 2 * bottom - top + 1)
    np.testing.assert_allclose(force[up], force[bottom] + 2 * virgin(RATE_FREE,
                                                                     (x[up] - x[bottom]) / 2),
                               rtol=0, atol=1e-9 * F_C)
    assert force[top] == pytest.approx(F_C, rel=1e-12)         # 40 µm > every slip length


def test_gms_non_local_memory_wipes_out_a_closed_minor_loop():
    """From rest up 6 µm, back 3 µm, up again past 6 µm to 10 µm: once the minor loop
    closes at 6 µm the force continues on the virgin curve as if it had never been made
    (measured 1e-15 F_c; bound 1e-9 F_c), and the branch down from 6 µm is Masing's
    about that reversal point."""
    speed, dt = 1e-4, 1 / FS
    legs = [(+1, 6e-6), (-1, 3e-6), (+1, 7e-6)]
    v = np.concatenate([[0.0]] + [np.full(int(round(length / speed / dt)), sign * speed)
                                  for sign, length in legs])
    x, force = path(v), RATE_FREE.force(v, dt)
    beyond = x >= 6e-6 - 1e-15
    second = np.arange(x.size) > 2 * int(round(6e-6 / speed / dt))
    np.testing.assert_allclose(force[beyond & second], virgin(RATE_FREE, x[beyond & second]),
                               rtol=0, atol=1e-9 * F_C)
    turn, low = np.flatnonzero(np.diff(np.sign(v[1:]))) + 1   # v reverses after these
    top = x[turn] + 0.25 * speed * dt                          # v linear through zero
    branch = slice(turn + 1, low + 1)
    np.testing.assert_allclose(force[branch], virgin(RATE_FREE, top)
                               - 2 * virgin(RATE_FREE, (top - x[branch]) / 2),
                               rtol=0, atol=1e-9 * F_C)
    assert top - (x[low] - 0.25 * speed * dt) == pytest.approx(3e-6, rel=0.01)


def test_gms_steady_state_is_the_stribeck_curve():
    """At constant speeds from 0.02 to 20 mm/s after 200 µm of travel (every block long
    past its limit, e^{−C t/|s|} below 1e-100): s(v) + σ2 v within 1e-9 relative."""
    for speed in (-2e-2, -1e-3, -1e-4, 2e-5, 3e-4, 2e-2):
        v = np.full(int(max(200e-6 / abs(speed) * FS, 10)), speed)
        assert LAW.force(v, 1 / FS)[-1] == pytest.approx(float(LAW.steady(speed)), rel=1e-9)
        expected = (F_C + 15.0 * np.exp(-(speed / 2e-4) ** 2)) * np.sign(speed) + 100 * speed
        assert float(LAW.steady(speed)) == pytest.approx(expected, rel=1e-12)


def test_one_block_is_dahl_at_alpha_to_zero():
    """One block (k = σ0, α_1 = 1): the Maxwell-slip element, F = σ0 z with |z| ≤ F_c/σ0,
    is Dahl's law at α → 0 (du/dξ = −1: linear until saturation). On a 20 µm sine with
    reversals on samples: within 1e-6 F_c of Dahl at α = 1e-7 (measured 8e-8 F_c)."""
    sigma0 = 1e7
    t, v = sine_velocity(20e-6, 5.0, 0.5)
    block = GMS(stiffness=(sigma0,), weights=(1.0,), F_c=F_C, F_s=F_C, v_s=1.0, C=1e12)
    np.testing.assert_allclose(block.force(v, 1 / FS), dahl_force(path(v), F_C, sigma0, 1e-7),
                               rtol=0, atol=1e-6 * F_C)


def test_one_block_is_the_elastoplastic_law_at_z_ba_to_z_ss():
    """One block, F_s = F_c, against Dupont et al.'s law with the elastic range up to
    99.9 % of z_ss (the sine blend over the last 0.1 %) on a 20 µm sine at 2 kHz: within
    1e-4 F_c (measured 1.4e-5 F_c; 3e-4 at 99.5 %, 1e-3 at 99 %: the blend's width). With
    a Stribeck peak the two differ by design: a slipping GMS block follows s(v) in time
    (rate C), the elasto-plastic z follows z_ss(v) only as the contact travels."""
    sigma0 = 1e7
    t, v = sine_velocity(20e-6, 5.0, 0.5)
    block = GMS(stiffness=(sigma0,), weights=(1.0,), F_c=F_C, F_s=F_C, v_s=1.0, C=1e9)
    ep = ElastoPlastic(sigma0=sigma0, F_c=F_C, F_s=F_C, v_s=1.0, z_ba=0.999 * F_C / sigma0)
    np.testing.assert_allclose(block.force(v, 1 / FS), ep.force(v, 1 / FS), rtol=0,
                               atol=1e-4 * F_C)


def test_uniform_distribution_is_the_normalised_path_law():
    """`GMS.uniform` (one stiffness, slip lengths uniform on (0, 2 x_p]) on a reversal
    record equals F_c × `maxwell_slip_normalised` (the closure's rate-independent column)
    within 1e-12 F_c; its virgin curve is Iwan's parabola F_c (ξ − ξ²/4), ξ = x/x_p ≤ 2,
    within F_c/(4N²) (the N blocks' piecewise-linear curve is that far above it at the slip
    lengths, on it midway between); the initial stiffness is F_c/x_p."""
    x_p = 3e-6
    t, v = sine_velocity(10e-6, 5.0, 0.5)
    law = GMS.uniform(F_C, x_p, blocks=8)
    w, _ = maxwell_slip_normalised(path(v), x_p, blocks=8)
    np.testing.assert_allclose(law.force(v, 1 / FS), F_C * w, rtol=0, atol=1e-12 * F_C)
    limits, _ = maxwell_slip_limits(x_p, 8)
    xi = limits / x_p
    np.testing.assert_allclose(virgin(law, limits), F_C * (xi - xi**2 / 4 + 1 / 256),
                               rtol=1e-12)
    grid = np.linspace(0.0, 2 * x_p, 1601)
    parabola = F_C * (grid / x_p - (grid / x_p) ** 2 / 4)
    assert np.max(np.abs(virgin(law, grid) - parabola)) <= F_C / 256 * (1 + 1e-9)
    assert sum(law.stiffness) == pytest.approx(F_C / x_p, rel=1e-12)


def test_gms_rejects_unphysical_parameters():
    with pytest.raises(ValueError, match="weights"):
        GMS(stiffness=(1e6, 1e6), weights=(0.5, 0.4), F_c=F_C, F_s=F_C, v_s=1.0, C=1.0)
    with pytest.raises(ValueError, match="as many"):
        GMS(stiffness=(1e6,), weights=(0.5, 0.5), F_c=F_C, F_s=F_C, v_s=1.0, C=1.0)
    with pytest.raises(ValueError, match="C"):
        GMS(stiffness=(1e6,), weights=(1.0,), F_c=F_C, F_s=F_C, v_s=1.0, C=0.0)


# --- the closure's `gms` candidate -------------------------------------------------------

X_P_RECORDED = 10e-6
"""The recorded contact's pre-sliding displacement F_c/σ0 (m): σ0 = 3 N/µm at F_c = 30 N."""


def iwan_friction(motion, t: np.ndarray, blocks: int = 64, oversample: int = 10
                  ) -> np.ndarray:
    """F_c Σ α_i z_i/Δ_i of `blocks` elastic-perfectly-plastic blocks of one stiffness, slip
    lengths uniform on (0, 2 x_p], on the analytic motion sampled `oversample` times finer
    than t and read at t: written here from the model's definition, with 4 times the
    candidate's blocks (its column is an approximation of this contact, not a copy)."""
    limits = 2 * X_P_RECORDED * (np.arange(blocks) + 0.5) / blocks
    fine = np.arange(t.size * oversample) * (t[1] - t[0]) / oversample
    x, z = motion.derivative(fine, 0), np.zeros(blocks)
    force = np.empty(t.size)
    for i in range(fine.size):
        if i:
            z = np.clip(z + (x[i] - x[i - 1]), -limits, limits)
        if i % oversample == 0:
            force[i // oversample] = F_C * float(np.sum(z)) / float(np.sum(limits))
    return force


def gms_closure():
    """The closure on a fit and a validation recording (test_dynamic_friction's motions,
    mass, viscous and noise) of Iwan's contact, the declared model inertia + viscous +
    Coulomb, all free."""
    from test_dynamic_friction import (
        AXIS, BANDWIDTH, NOISE_N, RECORD_FS, VALIDATION_MOTION, Motion,
    )

    from feedbench.analysis.closure import Model, Trace, close_the_loop, kinematics, new_term
    from feedbench.analysis.closure.trace import standstill_speed
    from feedbench.commands.closure import single_blas_thread

    traces = []
    for motion, seed, seconds in ((Motion(), 1, 12.0), (VALIDATION_MOTION, 2, 8.0)):
        t = np.arange(int(seconds * RECORD_FS)) / RECORD_FS
        force = (iwan_friction(motion, t) + AXIS["M_kg"] * motion.derivative(t, 2)
                 + AXIS["F_v_Ns_m"] * motion.derivative(t, 1)
                 + np.random.default_rng(seed).normal(0.0, NOISE_N, t.size))
        traces.append(Trace(t, motion.derivative(t, 0), force))
    fit, validation = (kinematics(trace, BANDWIDTH,
                                  standstill_speed(kinematics(trace, BANDWIDTH), 0.02))
                       for trace in traces)
    model = Model((new_term("inertia"), new_term("viscous"), new_term("coulomb")))
    with single_blas_thread():
        return close_the_loop(model, fit, validation)


def test_closure_names_gms_on_a_maxwell_slip_contact():
    """Iwan's contact (x_p = 10 µm, F_c = 30 N) undeclared: `gms` is the one finding, not
    Dahl's `presliding`. Measured: x_p 9.9998 µm, F_p 30.02 N, σ1 0 (on its bound), the
    Coulomb level 30.00 N; held-out NRMSE 33.1 → 0.43 % (the noise leaves 0.4 %); ΔBIC
    −20 633 against Dahl's −14 791 (α 0.33, σ1 1953 N·s/m mimicking the Masing branches,
    99.82 % of the residual against 99.99 %). On the LuGre and elasto-plastic recordings of
    test_dynamic_friction `presliding` stays the finding (ΔBIC −20 093 / −14 904 against
    `gms`'s −9 554 / −12 573)."""
    result = gms_closure()
    assert result.effects == ("gms",) and result.recalibrated == ()
    term = result.final.model.term("gms").values
    assert term["x_p_um"] == pytest.approx(X_P_RECORDED, rel=0.01)
    assert term["F_p_N"] == pytest.approx(F_C, rel=0.01)
    assert result.final.model.term("coulomb").values["F_c_N"] == pytest.approx(F_C, rel=0.01)
    assert result.error_before > 0.2
    assert result.error_after < 0.006
    ranked = {c.name: c for c in result.steps[0].ranking}
    assert ranked["gms"].delta_bic < ranked["presliding"].delta_bic - 1000.0


def test_closure_does_not_add_gms_to_a_clean_coulomb_recording():
    """test_dynamic_friction's clean recording, F_c tanh(k v) and no hysteresis: no
    finding (measured: `gms` not significant, ΔBIC +12.9, 0.44 % of the residual)."""
    from test_dynamic_friction import closure_on

    result = closure_on("coulomb")
    assert "gms" not in result.effects
    gms = [c for c in result.final_ranking if c.name == "gms"]
    assert len(gms) == 1 and not gms[0].significant(result.options)
