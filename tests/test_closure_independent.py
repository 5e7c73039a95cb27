"""The closure on data its own models did not make (issue 13).

The independent simulator (`tests/independent_sim`, no feedbench code) is first checked
against closed-form physics; then a fast subset of its cases asserts, per case, what
`benchmarks/bench_closure_independent.py` counts over all of them: the injected effect (or the
wrongly declared parameter) is the first and only finding and the held-out error is fixed
(at least halved, or within 1.5× the noise floor); a clean case is left untouched; nothing
crashes. A case the closure fails would be marked xfail(strict) naming what goes wrong (none
today).
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import scipy.optimize

from feedbench.analysis.closure import report_dict
from feedbench.analysis.closure.effects import follower_force
from feedbench.analysis.closure.trace import kinematics, lowpass
from feedbench.commands.closure import closure_report
from feedbench.report import closure_section
from feedbench.closure_io import read_csv_trace
from independent_sim import CASES, write_case
from independent_sim.cases import FIT_PROGRAM, STRUCTURES, record, world
from independent_sim.judge import AT_THE_FLOOR, judge
from independent_sim.plant import (
    FRICTION_SMOOTHING, PHYSICS_HZ, RECORD_STEPS, natural_modes, tip_acceleration,
)


def _transmissibility(f: np.ndarray, f_n: float, zeta: float) -> np.ndarray:
    """Closed form x_tip / x_motor of a mass on a spring-damper: (2ζω_n s + ω_n²) /
    (s² + 2ζω_n s + ω_n²), s = j2πf (Eq. 4.25)."""
    s, w = 2j * math.pi * f, 2 * math.pi * f_n
    return (2 * zeta * w * s + w ** 2) / (s ** 2 + 2 * zeta * w * s + w ** 2)


_SECOND = CASES["second_mode"].truth
MODES = [pytest.param(f"clean_{s}", 1, STRUCTURES[s].f_n_Hz, STRUCTURES[s].zeta, id=s)
         for s in ("2mass", "2mass_stiff", "2mass_soft")]
MODES.append(pytest.param("second_mode", 2, _SECOND["f2_Hz"], _SECOND["zeta2"],
                          id="second_mode"))


@pytest.mark.parametrize("name, mass, f_n, zeta", MODES)
def test_simulated_mode_matches_closed_form(name, mass, f_n, zeta):
    """The FRF mass/motor of a simulated closed-loop chirp recording, fitted by the closed
    form, gives the mode's f_n (Hz) within 0.5 % and ζ within 5 % (the tip's mode; a second
    mode's mass on its own spring from the motor, whatever else the motor carries). The
    recording starts and ends at rest, so the ratio of its whole DFTs is the FRF: no window,
    no leakage (Welch's Hann segments put a 130 Hz ζ of 0.02 at 0.023)."""
    run = record(CASES[name], FIT_PROGRAM, seed=3)
    n = run.states.shape[1] // 2
    v_motor, v_mass = np.fft.rfft(run.states[:, n]), np.fft.rfft(run.states[:, n + mass])
    f = np.fft.rfftfreq(run.time.size, 1e-3)
    near = (f > 0.5 * f_n) & (f < 1.5 * f_n)
    band = near & (np.abs(v_motor) > 0.1 * np.abs(v_motor[near]).max())
    measured = v_mass[band] / v_motor[band]

    def residual(p: np.ndarray) -> np.ndarray:
        error = measured - _transmissibility(f[band], p[0], p[1])
        return np.concatenate([error.real, error.imag])

    fitted_f_n, fitted_zeta = scipy.optimize.least_squares(residual, [f_n * 1.1, 0.03]).x
    assert fitted_f_n == pytest.approx(f_n, rel=0.005)
    assert fitted_zeta == pytest.approx(zeta, rel=0.05)


def test_second_mode_adds_a_pole_pair_and_keeps_the_total_mass():
    """second_mode: the world's masses sum to the declared 40 kg (the second mode's 3 kg
    carved out of the motor) and the free plant has two oscillating pole pairs."""
    plant, _ = world(CASES["second_mode"])
    assert sum(plant.masses) == pytest.approx(STRUCTURES["2mass"].total_kg)
    assert len(natural_modes(plant)) == 2


@pytest.mark.parametrize("name", ["backlash_drivetrain_small", "backlash_drivetrain_large"])
def test_simulated_drivetrain_play_is_a_dead_zone(name):
    """Well inside the play (|x_motor − x_tip| < 0.9 L/2 at both ends of a cycle) nothing
    acts on the tip: its velocity does not change (to 1e-9 m/s); the gap spans more than
    the play."""
    case = CASES[name]
    run = record(case, FIT_PROGRAM, seed=6)
    n = run.states.shape[1] // 2
    gap = run.states[:, 0] - run.states[:, 1]
    half = 0.5e-6 * case.truth["play_um"]
    inside = (np.abs(gap[1:]) < 0.9 * half) & (np.abs(gap[:-1]) < 0.9 * half)
    assert inside.sum() > 1000
    assert np.abs(np.diff(run.states[:, n + 1])[inside]).max() < 1e-9
    assert np.ptp(gap) > 2 * half


def test_simulated_table_friction_holds_the_tip_against_the_play():
    """backlash_guided_large: the table's guideways carry F_table of the Coulomb level. At
    the 16 m/min cruise the motor pushes the table through the play: the gap is the half
    play plus the spring's deflection F_table / k (k = m (2π f_n)²) within 0.5 µm, and the
    motor's own Coulomb level is the rest (30 − 10 N)."""
    case = CASES["backlash_guided_large"]
    plant, _ = world(case)
    run = record(case, FIT_PROGRAM, seed=8)
    speed = np.gradient(run.reference, run.time)
    V = FIT_PROGRAM.feeds[-1] / 60.0
    cruise = np.flatnonzero(np.abs(speed - V) < 1e-6 * V)
    settled = cruise[cruise.size // 2:]
    gap = (run.states[:, 0] - run.states[:, 1])[settled]
    s = STRUCTURES["2mass"]
    k = s.modal_kg * (2 * math.pi * s.f_n_Hz) ** 2
    expected = 0.5e-6 * case.truth["play_um"] + case.truth["F_table_N"] / k
    assert np.abs(gap - expected).max() < 0.5e-6
    assert plant.friction.F_c == pytest.approx(s.F_c - case.truth["F_table_N"])
    assert plant.coulomb()[1] == case.truth["F_table_N"]


def test_simulated_channel_skew_latches_the_position_early():
    """channel_skew: at the 16 m/min cruise the recorded position trails the motor's
    position at the time stamp by V × skew (V 0.267 m/s, skew 3/8 of a 1 ms cycle: 100 µm)
    within 0.5 %."""
    case = CASES["channel_skew"]
    run = record(case, FIT_PROGRAM, seed=7)
    speed = np.gradient(run.reference, run.time)
    V = FIT_PROGRAM.feeds[-1] / 60.0
    cruise = np.flatnonzero(np.abs(speed - V) < 1e-6 * V)
    skew_s = case.truth["skew_cycles"] * RECORD_STEPS / PHYSICS_HZ
    trail = run.states[cruise, 0] - run.position[cruise]
    assert trail.mean() == pytest.approx(V * skew_s, rel=0.005)


def test_simulated_cruise_force_is_viscous_plus_coulomb():
    """At every cruise of the fit recording the mean force read equals ±(σ V + F_c tanh(V/v_ε))
    within 0.5 % (σ 150 N·s/m, F_c 30 N at 1–16 m/min)."""
    run = record(CASES["clean_2mass"], FIT_PROGRAM, seed=4)
    speed = np.gradient(run.reference, run.time)
    declared = STRUCTURES["2mass"]
    checked = 0
    for feed in FIT_PROGRAM.feeds:
        V = feed / 60.0
        for sign in (1.0, -1.0):
            cruise = np.flatnonzero(np.abs(speed - sign * V) < 1e-6 * V)
            settled = cruise[cruise > cruise[0] + 0.4 * cruise.size]   # the loop has settled
            expected = sign * (declared.sigma * V
                               + declared.F_c * math.tanh(V / FRICTION_SMOOTHING))
            assert run.force[settled].mean() == pytest.approx(expected, rel=0.005)
            checked += 1
    assert checked == 2 * len(FIT_PROGRAM.feeds)


@pytest.mark.parametrize("name", ["clean_2mass", "cubic_stiffening_large",
                                  "backlash_drivetrain_large", "second_mode"])
def test_simulated_tip_acceleration_integrates_to_tip_velocity(name):
    """The tip channel's noiseless acceleration, integrated by the trapezoid over each 1 ms
    cycle, gives the simulated tip velocity change within 3 % RMS (the trapezoid's own error
    near the 61 Hz mode is (ωh)²/12 ≈ 1.2 %)."""
    case = CASES[name]
    run = record(case, FIT_PROGRAM, seed=5)
    acceleration = tip_acceleration(world(case)[0], run.states)
    n = run.states.shape[1] // 2
    change = np.diff(run.states[:, n + 1])
    trapezoid = 0.5 * (acceleration[1:] + acceleration[:-1]) * np.diff(run.time)
    assert np.linalg.norm(change - trapezoid) < 0.03 * np.linalg.norm(change)


@pytest.fixture(scope="module")
def case_directory(tmp_path_factory):
    return tmp_path_factory.mktemp("independent_cases")


SUBSET = [
    pytest.param("clean_2mass", False, id="clean_2mass"),
    pytest.param("clean_3mass", False, id="clean_3mass"),
    pytest.param("clean_mode_120Hz_zeta0.01", False, id="clean_mode_120Hz_zeta0.01"),
    pytest.param("coulomb_small", False, id="coulomb_small"),
    pytest.param("delay_small", False, id="delay_small"),
    pytest.param("structural_mode_small", False, id="structural_mode_small"),
    pytest.param("backlash_large", True, id="backlash_large-free"),
    pytest.param("recal_fn", False, id="recal_fn"),
    pytest.param("recal_mass", False, id="recal_mass"),
    pytest.param("coulomb_small", True, id="coulomb_small-free"),
    pytest.param("offset_small", True, id="offset_small-free"),
    pytest.param("ripple_long_pitch", False, id="ripple_long_pitch"),
    pytest.param("channel_skew", False, id="channel_skew"),
    pytest.param("backlash_drivetrain_large", False, id="backlash_drivetrain_large"),
    pytest.param("backlash_guided_small", False, id="backlash_guided_small"),
    pytest.param("second_mode", False, id="second_mode"),
]


@pytest.mark.parametrize("name, low, high", [("backlash_guided_small", 0.25, 0.6),
                                             ("backlash_guided_large", 0.45, 0.8)])
def test_a_rattle_in_the_play_is_not_predictable_open_loop(case_directory, name, low, high):
    """What docs/closure.md says of a play in the mode's spring: the closure's follower
    (`effects.follower_force`) driven by the recorded motor motion with the *true* mass,
    play, friction and the mode's own ζ leaves `low`–`high` of the held-out force (measured
    0.41 and 0.62: the mass rattles across the play under the excitation, a motion no
    open-loop simulation follows), the linear mode more than all of it."""
    truth = CASES[name].truth
    trace, _ = read_csv_trace(write_case(name, case_directory).validation_csv)
    kin = kinematics(trace, 200.0, 5.33e-3)
    m, omega, k_tanh = truth["m_kg"], 2 * math.pi * truth["f_n_Hz"], 1e3
    motor = ((truth["M_kg"] - m) * kin.a + truth["F_v_Ns_m"] * kin.v
             + (truth["F_c_N"] - truth["F_table_N"]) * np.tanh(k_tanh * kin.v))
    played = follower_force(kin.x, kin.v, kin.dt, omega, truth["zeta"], 0.0,
                            0.5e-6 * truth["play_um"], truth["F_table_N"] / m, k_tanh)
    linear = m * follower_force(kin.x, kin.v, kin.dt, omega, truth["zeta"])
    rows = kin.rows

    def left(prediction: np.ndarray) -> float:
        return float(np.linalg.norm((kin.force - prediction)[rows])
                     / np.linalg.norm(kin.force[rows]))

    assert low < left(motor + m * lowpass(played, kin.bandwidth, kin.dt)) < high
    assert left(motor + linear + truth["F_table_N"] * np.tanh(k_tanh * kin.v)) > 1.0


SHARED = {("recal_mass", False), ("channel_skew", False)}
"""Cases whose closure report a second test of this file reads too (the report's section of a
recalibration, the timing finding of an undeclared skew): run once, kept in `_REPORTS`."""
_REPORTS: dict[tuple[str, bool], tuple] = {}


def _closure(directory, name: str, free: bool):
    """(the case's files, the closure's report on them); a `SHARED` case's run once."""
    if (name, free) in _REPORTS:
        return _REPORTS[name, free]
    files = write_case(name, directory, free)
    closed = files, closure_report(files.data_csv, files.model_toml, files.validation_csv)
    if (name, free) in SHARED:
        _REPORTS[name, free] = closed
    return closed


def _closed(directory, name: str, free: bool) -> dict:
    """The closure's JSON report on a case, after asserting what the benchmark counts:
    named first, the only finding, and fixed (halved or within 1.5× the noise floor) for
    effects and recalibrations; untouched and within 1.5× the simulator's noise floor for
    clean cases; no crash."""
    files, closed = _closure(directory, name, free)
    injected, kind = CASES[name].expected(free)
    report = report_dict(closed)
    verdict = judge(report, kind, injected, files.noise_floor)
    if kind == "clean":
        assert verdict.found == ()
        assert verdict.error_after <= AT_THE_FLOOR * files.noise_floor
    else:
        assert verdict.named_first, verdict.found
        assert verdict.one_finding, verdict.found
        assert verdict.fixed, (verdict.error_before, verdict.error_after)
    return report


@pytest.mark.parametrize("name, free", SUBSET)
def test_closure_on_independent_case(case_directory, name, free):
    _closed(case_directory, name, free)


def test_a_recalibration_that_appears_only_after_the_play_is_not_a_finding(case_directory):
    """backlash_large, exact model (declared M = 40 kg, the truth): the play is the one
    finding. Freed on the declared model M moves to 39.55 kg; after the play's load form it
    would move to 41.29 kg (held-out 3.63 → 3.03 %): the load behind the play is part of M,
    and the move is the play's effective parameters re-split, refused
    (`diagnosis.moved_only_with_effects`; before it, M was a second finding)."""
    report = _closed(case_directory, "backlash_large", False)
    assert report["effects"] == ["backlash"] and report["recalibrations"] == []
    reasons = {r["effect"]: r["reason"] for r in report["rejected"]}
    assert reasons["inertia.M_kg"].startswith("moves only with the effects added")


def test_replay_after_a_delay_recalibration_runs_the_drive_with_it(case_directory):
    """recal_delay (declared 0.5 ms, true 1.5 ms): recalibrated, and the final model's
    closed-loop replay runs the drive with the recalibrated delay: its force error falls and
    its FRF phase error goes below 10° (it rose with the declared delay kept)."""
    replay = _closed(case_directory, "recal_delay", False)["replay"]
    assert replay["after"]["force"] < 0.8 * replay["before"]["force"]
    assert replay["after"]["frf_phase_deg"] < 10.0 < replay["before"]["frf_phase_deg"]


def test_an_undeclared_sub_cycle_skew_is_a_timing_finding_not_a_gain(case_directory):
    """Position latched 3/8 of a cycle before its time stamp, not declared: one finding, the
    timing (the declared delay moved by ≈ 0.375 ms), never a sensor gain. (The report of
    `test_closure_on_independent_case[channel_skew]`; the declared skew's test is in
    `test_closure_measurement`.)"""
    data = _closed(case_directory, "channel_skew", False)
    steps = [s["effect"] for s in data["steps"]]
    assert steps == ["delay.tau_ms"]
    moved = data["recalibrations"][0]["value"] - data["recalibrations"][0]["declared"]
    assert moved == pytest.approx(0.375, abs=0.05)
    assert "sensor_gain" not in steps


def test_closure_section_shows_a_recalibration(case_directory):
    """The report's section of the independent simulator's axis declared 10 % heavy (44 kg,
    true 40 kg): the one finding is the declared mass recalibrated, declared → fitted ± σ in
    the table. (The report of `test_closure_on_independent_case[recal_mass]`; the report's
    other closure sections are tested in `test_report`.)"""
    section = closure_section(_closure(case_directory, "recal_mass", False)[1])
    rows = next(t.rows for t in section.tables if t.title == "findings")
    findings = {row[0]: row[1:] for row in rows}
    assert list(findings) == ["inertia.M_kg"]
    kind, parameters = findings["inertia.M_kg"][0], findings["inertia.M_kg"][-1]
    assert kind == "declared value recalibrated"
    pattern = r"declared (\S+) → (\S+) ± \S+ kg, moved \S+ σ"
    declared, fitted = re.match(pattern, parameters).groups()
    assert float(declared) == 44.0 and float(fitted) == pytest.approx(40.0, rel=0.01)
    assert section.headline.startswith("inertia.M_kg recalibrated: ")
