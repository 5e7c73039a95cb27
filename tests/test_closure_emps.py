"""The closure on real measured data: the EMPS benchmark (Janot, Gautier, Brunot 2019).

Starting from a rigid body with viscous friction only, fitted on DATA_EMPS.mat and judged on
DATA_EMPS_PULSES.mat, the closure must add Coulomb friction and the offset (in either order)
and land within 10 % of the published IDIM-LS estimate: M = 95.1089 kg,
F_v = 203.5034 N·s/m, F_c = 20.3935 N, offset = −3.1648 N.
"""

from __future__ import annotations

import pytest

from feedbench.analysis.closure import report_text
from feedbench.commands.closure import closure_report
from prerequisites import SHARED_DATA, requires

EMPS = SHARED_DATA / "emps"
PUBLISHED = {("inertia", "M_kg"): 95.1089, ("viscous", "F_v_Ns_m"): 203.5034,
             ("coulomb", "F_c_N"): 20.3935, ("offset", "offset_N"): -3.1648}

pytestmark = requires((EMPS / "DATA_EMPS.mat").exists(), f"EMPS data not in {EMPS}")


@pytest.fixture(scope="module")
def report():
    return closure_report(EMPS / "DATA_EMPS.mat", validation=EMPS / "DATA_EMPS_PULSES.mat")


def test_closure_adds_coulomb_and_offset_first(report):
    print("\n" + report_text(report))
    assert set(report.result.effects[:2]) == {"coulomb", "offset"}


def test_parameters_land_within_10_percent_of_the_published_idim_estimate(report):
    step = next(s for s in report.result.steps if {"coulomb", "offset"} <= s.fit.model.names)
    for (term, key), published in PUBLISHED.items():
        value = step.fit.model.term(term).values[key]
        assert value == pytest.approx(published, rel=0.10), (term, key, value)
    # the Jacobian deviations match the published ones (0.1085, 1.1460, 0.1012, 0.0444)
    # to within a factor 2: the n/n_eff scaling for a band-limited residual is honest
    assert 0.05 < step.fit.std[("inertia", "M_kg")] < 0.25
    assert 0.02 < step.fit.std[("offset", "offset_N")] < 0.1


def test_held_out_error_falls_at_each_step_and_overall(report):
    result = report.result
    assert result.error_before == pytest.approx(0.18, abs=0.02)  # viscous only: ≈ 18 %
    for step in result.steps[:2]:
        assert step.error_after < step.error_before
    after_two = result.steps[1].error_after
    assert after_two < 0.07  # published IDIM-LS cross validation: 5.98 %
    assert result.error_after <= after_two


def test_closed_loop_replay_improves_like_the_published_simulation(report):
    # published full simulation with the IDIM-LS estimate on PULSES: force error 8.94 %
    assert report.replay_after.force < 0.10
    assert report.replay_after.force < 0.5 * report.replay_before.force
