"""Standard P-PI tuning (Eqs. 4.2, 4.8, 4.12) and f_t, f_r (4.13, 4.14) against thesis numbers;
the candidates of `feedbench tune` and their predictions on the simulated lab bench."""

import dataclasses
import json

import numpy as np
import pytest

from feedbench.analysis import contour, lft, servo, tuning
from feedbench.analysis.tuning import (
    bandwidth_tunings,
    engineering_gains,
    optimum_bandwidth,
    standard_gains,
    total_mass,
)
from feedbench.models.axis import CascadeGains, TwoMassAxis
from feedbench.models.milling import engagement_angles

CHAPTER4_BENCH = TwoMassAxis(m_mot=24.9, m_tip=9.5, k=1.98e6, c=104.0)
"""Ch. 4.2.3 bench (DIGEST §3)."""


def test_table_4_1_controller_c1_from_45_hz():
    """M_total = 80 + 130 + 10.8 kg at 45 Hz: K_p 62.4 kN·s/m, T_i 7.07 ms, K_v 4.24 (m/min)/mm."""
    gains = engineering_gains(standard_gains(80.0 + 130.0 + 10.8, 45.0))
    assert gains.K_p == pytest.approx(62.4e3, rel=5e-3)
    assert gains.T_i_ms == pytest.approx(7.07, abs=0.005)
    assert gains.K_v_m_min_per_mm == pytest.approx(4.24, abs=0.005)


def test_k_v_unit_conversion():
    """K_v = π·45/2 = 70.69 1/s; 1 (m/min)/mm = 16.67 1/s."""
    gains = standard_gains(220.8, 45.0)
    assert gains.K_v == pytest.approx(70.69, abs=0.01)
    assert gains.K_v / engineering_gains(gains).K_v_m_min_per_mm == pytest.approx(16.667, abs=1e-3)


def test_lab_bench_characteristic_frequencies():
    """Ch. 5.3.2 bench: f_t = 61.4 Hz, f_r = 74.9 Hz (DIGEST §3 check values)."""
    axis = TwoMassAxis()
    assert axis.f_t == pytest.approx(61.4, abs=0.05)
    assert axis.f_r == pytest.approx(74.9, abs=0.05)


def test_chapter4_tunings():
    """Low 15 Hz, high 87 Hz, optimum 58 Hz = 80 % of f_t on M_total = 34.4 kg."""
    assert total_mass(CHAPTER4_BENCH) == pytest.approx(34.4)
    assert optimum_bandwidth(CHAPTER4_BENCH) == pytest.approx(58.0, abs=0.5)
    tunings = bandwidth_tunings(CHAPTER4_BENCH)
    assert tunings["high"].K_p == pytest.approx(2 * 3.141592653589793 * 34.4 * 87.0)
    assert tunings["low"].T_i == pytest.approx(1.0 / (3.141592653589793 * 15.0))
    assert tunings["optimum"].K_v == pytest.approx(3.141592653589793 * 58.13 / 2, rel=1e-3)


# -- candidates for `feedbench tune` (issue 15) --------------------------------------------

SIM_AXIS = TwoMassAxis()
"""The simulated lab bench (feedbench.sim_backends.world defaults: 23.1 kg, 11.3 kg,
1.68 N/µm, 104 N·s/m; friction's viscous term 0.0028 N·min/mm = 168 N·s/m; τ_ol 0.75 ms)."""

SIM_M_TOTAL = total_mass(SIM_AXIS)
SIM_SIGMA, SIM_DELAY = 168.0, 0.75e-3
SIM_MOBILITY = servo.with_delay(
    servo.chain_mobility([SIM_AXIS.m_mot, SIM_AXIS.m_tip], [SIM_AXIS.k], [SIM_AXIS.c], SIM_SIGMA),
    SIM_DELAY, 4)
SIM_BANDWIDTH_HZ = 60.0
"""The simulated drive's factory tuning (bench.world bandwidth_Hz)."""

FREQUENCY = np.linspace(20.0, 200.0, 721)
SIM_MATRICES = servo.chain_matrices([SIM_AXIS.m_mot, SIM_AXIS.m_tip], [SIM_AXIS.k], [SIM_AXIS.c],
                                    SIM_SIGMA)
TABLE_4_2 = tuning.CuttingParameters(
    spindle_rpm=np.linspace(500.0, 6000.0, 1100), n_teeth=4, K_t=1885e6, K_r=749.0 / 1885.0,
    phi_st=engagement_angles(32e-3, 40e-3, "down")[0], phi_ex=np.pi)
"""Table 4.2's cut (Z 4, K_tc 1885 N/mm², K_rc 749 N/mm², a_e 32 of D 40 mm, down-milling)."""

TABLE_4_3 = {"max_damping": (110.5, 23.8, 212.9, 75.5), "standard": (9.4, 2.42, 31.7, 12.1)}
"""Contour max/RMS, tracking max/RMS (µm): optimum damping vs high bandwidth, ram machine."""


def _closed_tip_truth(gains: CascadeGains) -> np.ndarray:
    """x_tip/F_tip (m/N) by solving the two-mass equations with F_mot = K x_mot, K of
    Eq. (4.24) behind the drive delay: no LFT involved."""
    s = servo.laplace(FREQUENCY)[:, None, None]
    mass, damping, stiffness = SIM_MATRICES
    controller = -lft.pppi_feedback(FREQUENCY, gains)[:, None, None] * np.exp(-SIM_DELAY * s)
    dynamic = mass * s**2 + damping * s + stiffness + controller * np.diag([1.0, 0.0])
    return np.linalg.inv(dynamic)[:, 1, 1]


def _tip_measurements() -> tuning.TipMeasurements:
    """What the bench would measure: open-loop x_mot/F_mot; approach #1 under a 2 Hz tuning
    (K_0) with the transmissibility; approach #2 under the 30 and 90 Hz tunings."""
    system = servo.lumped_state_space(*SIM_MATRICES, force_dofs=[1, 0], outputs=[(1, 0), (0, 0)])
    h = servo.state_space_frf(system, FREQUENCY)
    delay = np.exp(-SIM_DELAY * servo.laplace(FREQUENCY))
    mot_mot, tip_mot = h[:, 1, 1] * delay, h[:, 0, 1] * delay
    k0 = lft.pppi_feedback(FREQUENCY, standard_gains(SIM_M_TOTAL, 2.0))
    tip_k0 = _closed_tip_truth(standard_gains(SIM_M_TOTAL, 2.0))
    mot_tip_k0 = h[:, 1, 0] / (1.0 - mot_mot * k0)
    measured = (standard_gains(SIM_M_TOTAL, 30.0), standard_gains(SIM_M_TOTAL, 90.0))
    return tuning.TipMeasurements(
        frequency=FREQUENCY, mot_mot=mot_mot, tip_closed_k0=tip_k0, mot_tip_k0=mot_tip_k0,
        transmissibility=tip_mot / mot_mot,
        tip_closed=tuple(_closed_tip_truth(g) for g in measured), measured_gains=measured)


SETUP = tuning.TuningSetup(band=(0.5 * SIM_AXIS.f_t, 2.0 * SIM_AXIS.f_r), tip=_tip_measurements(),
                           cutting=TABLE_4_2)


@pytest.fixture(scope="module")
def sim_rows() -> dict[str, tuning.CandidatePrediction]:
    listed = {"high": standard_gains(SIM_M_TOTAL, 87.0)}
    candidates = tuning.candidate_gains(SIM_MOBILITY, SETUP, SIM_M_TOTAL, SIM_BANDWIDTH_HZ,
                                        tuning.bandwidth_bounds(SIM_M_TOTAL, 15.0, 87.0), listed)
    return {row.name: row for row in tuning.predict_candidates(candidates, SIM_MOBILITY, SETUP)}


def _print_beside_table_4_3(rows: dict[str, tuning.CandidatePrediction], path: str) -> None:
    for name, thesis in TABLE_4_3.items():
        e = rows[name].motion[path]
        print(f"{path} {name:12s} ζ {rows[name].critical.damping:.3f}  contour max/RMS "
              f"{e.contour_max_um:7.2f} {e.contour_rms_um:6.2f}  tracking max/RMS "
              f"{e.tracking_max_um:7.1f} {e.tracking_rms_um:6.1f} µm   Table 4.3: {thesis}")


def test_max_damping_on_the_sim_bench_raises_damping_without_costing_bandwidth(sim_rows, capsys):
    """The sim axis: max-damping ζ 0.50 vs the factory 60 Hz tuning's 0.18 (+174 %; thesis
    +44 % on the ram machine). Its contour error is NOT an order of magnitude higher here,
    and that is the physics of this axis, not a flaw of the search: on a two-mass axis the
    damping optimum lies at ≈ 0.8 f_t = 49 Hz of velocity bandwidth (Ch. 4.2.3; the search's
    K_p is 95 % of the 60 Hz tuning's), so it gives up almost no bandwidth, while on the ram
    machine it cut the velocity bandwidth from 25 to 9 Hz (Ch. 4.6), which is what costs the
    10× (see the next test). Measured (R 10 mm, 5000 mm/min, 2 m/s²): circle contour max
    7.9 vs 8.1 µm, corner 15.5 vs 9.9 µm."""
    standard, best = sim_rows["standard"], sim_rows["max_damping"]
    assert best.critical.damping >= 1.4 * standard.critical.damping
    assert best.critical.stable and standard.critical.stable
    assert best.gains.K_p == pytest.approx(standard.gains.K_p, rel=0.1)
    for path in ("circle", "corner"):
        ratio = best.motion[path].contour_max_um / standard.motion[path].contour_max_um
        assert ratio < 5.0
    with capsys.disabled():
        _print_beside_table_4_3(sim_rows, "circle")
        _print_beside_table_4_3(sim_rows, "corner")


def test_the_thesis_bandwidth_cut_costs_an_order_of_magnitude_in_contour_error():
    """Ch. 4.6's cut of the velocity bandwidth from 25 to 9 Hz (standard tunings) on the sim
    axis: the circle's contour error grows ≥ 5× (measured 11.2× max, 20× RMS; tracking 6.6×,
    4.3×; Table 4.3: 11.7, 9.8, 6.7, 6.2)."""
    setup = tuning.TuningSetup(band=SETUP.band)
    high, low = (tuning.predict_candidate(name, standard_gains(SIM_M_TOTAL, f), SIM_MOBILITY, setup)
                 for name, f in (("high", 25.0), ("low", 9.0)))
    ratio = {key: getattr(low.motion["circle"], key) / getattr(high.motion["circle"], key)
             for key in ("contour_max_um", "contour_rms_um", "tracking_max_um", "tracking_rms_um")}
    print("25 → 9 Hz circle error ratios", {k: round(v, 1) for k, v in ratio.items()})
    assert ratio["contour_max_um"] >= 5.0 and ratio["contour_rms_um"] >= 5.0
    assert ratio["tracking_max_um"] >= 3.0


@pytest.mark.parametrize("name", ["standard", "max_damping", "high"])
def test_tip_predictions_agree_with_the_closed_loop_truth(sim_rows, name):
    """Approach #2 (from the 30 and 90 Hz settings) is exact on linear data: peak and its
    frequency as the two-mass equations give them; approach #1 (K_0 = a 2 Hz tuning taken as
    open loop) within 3 % of the peak."""
    row = sim_rows[name]
    truth = np.abs(_closed_tip_truth(row.gains))
    peak = int(np.argmax(truth))
    assert row.tip["settings"].peak_um_per_N == pytest.approx(truth[peak] * 1e6, rel=1e-6)
    assert row.tip["settings"].peak_frequency_hz == FREQUENCY[peak]
    assert row.tip["transmissibility"].peak_um_per_N == pytest.approx(truth[peak] * 1e6, rel=0.03)


def test_rows_are_json_and_the_recommendation_is_plain(sim_rows):
    """Each row → dataclasses.asdict → JSON; roughing goes to the deepest stable cut,
    finishing to the smallest contour error."""
    rows = list(sim_rows.values())
    decoded = json.loads(json.dumps([dataclasses.asdict(row) for row in rows]))
    assert decoded[1]["name"] == "max_damping"
    assert decoded[1]["motion"]["circle"]["contour_max_um"] == rows[1].motion["circle"].contour_max_um
    assert set(decoded[1]["tip"]) == {"settings", "transmissibility"}
    advice = tuning.recommend(rows)
    depth = {row.name: row.tip["settings"].min_stable_depth_mm for row in rows}
    error = {row.name: max(e.contour_max_um for e in row.motion.values()) for row in rows}
    assert advice.roughing == max(depth, key=depth.get)
    assert advice.finishing == min(error, key=error.get)
    assert advice.roughing_by == "min stable depth (settings)"
    print("min stable depth (mm)", depth, "contour max (µm)", error, advice)


def test_candidate_names_do_not_clash():
    with pytest.raises(ValueError, match="standard"):
        tuning.candidate_gains(SIM_MOBILITY, SETUP, SIM_M_TOTAL, 60.0,
                               tuning.bandwidth_bounds(SIM_M_TOTAL, 15.0, 87.0),
                               {"standard": standard_gains(SIM_M_TOTAL, 30.0)})


@pytest.mark.parametrize("position_delay", [0.0, 1e-3])
def test_critical_mode_is_an_eigenvalue_of_the_contour_loop(position_delay):
    """The root-locus polynomial (rootlocus.cascade_characteristic) and the contour's closed
    loop (state space assembled block by block) are two formulations of one cascade: the
    critical root's f_n and ζ are an eigenvalue of the latter's A (to 1e-6), whose other
    eigenvalues are the characteristic's roots plus the balancing filter's −1/τ_BF."""
    gains = standard_gains(SIM_M_TOTAL, 60.0)
    setup = tuning.TuningSetup(band=SETUP.band, position_delay=position_delay)
    mode = tuning.critical_mode(SIM_MOBILITY, gains, setup)
    a = contour.cascade_state_space(SIM_MOBILITY, gains, setup.feedforward, position_delay)[0]
    eigenvalues = np.linalg.eigvals(a)
    natural, zeta = np.abs(eigenvalues) / (2 * np.pi), -eigenvalues.real / np.abs(eigenvalues)
    nearest = np.argmin(np.abs(natural - mode.frequency_hz) + np.abs(zeta - mode.damping))
    assert natural[nearest] == pytest.approx(mode.frequency_hz, rel=1e-6)
    assert zeta[nearest] == pytest.approx(mode.damping, rel=1e-6)
    assert np.min(np.abs(eigenvalues + 1e3)) < 1e-6 * 1e3
    assert mode.stable and np.all(eigenvalues.real < 0)


def test_tip_measurements_refuse_half_an_approach():
    f, h = FREQUENCY, np.ones(FREQUENCY.size, dtype=complex)
    with pytest.raises(ValueError, match="approach #1"):
        tuning.TipMeasurements(frequency=f, mot_mot=h, tip_closed_k0=h)
    with pytest.raises(ValueError, match="approach #2"):
        tuning.TipMeasurements(frequency=f, mot_mot=h, tip_closed=(h,),
                               measured_gains=(standard_gains(SIM_M_TOTAL, 30.0),))


def test_a_band_the_search_can_empty_is_refused():
    """Band f_t…f_r (61–75 Hz) on the sim axis: the controller pulls the structural root out
    of it (std 60 Hz: 49 Hz), so "no root in band" would win the search; refused, and the
    critical mode of such gains is NaN, not ζ = 0."""
    setup = tuning.TuningSetup(band=(SIM_AXIS.f_t, SIM_AXIS.f_r))
    with pytest.raises(ValueError, match="widen"):
        tuning.max_damping_gains(SIM_MOBILITY, setup,
                                 tuning.bandwidth_bounds(SIM_M_TOTAL, 15.0, 87.0))
    mode = tuning.critical_mode(SIM_MOBILITY, standard_gains(SIM_M_TOTAL, 60.0), setup)
    assert np.isnan(mode.frequency_hz) and np.isnan(mode.damping)
