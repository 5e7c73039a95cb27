"""A force channel that falls as the speed rises is not a passive axis's (issue 24: "a result
judges itself"): the verdict says so, on synthetic data with a known slope and on the
gallery's ODrive pull test, and nowhere else in the gallery."""

from __future__ import annotations

import re

import numpy as np
import pytest

from feedbench.analysis.closure import ClosureOptions, Trace, fit_model, new_term
from feedbench.analysis.closure.diagnosis import falls_with_speed
from feedbench.analysis.closure.model import Model, predict
from test_closure import BASE, FS, base_model, exact_kinematics, kin_of, synthetic_trace
from test_closure_gallery import DATASETS, _closed

SPEED_GAIN = 400.0
"""N·s/m: how much a synthetic speed loop's effort drops per m/s of speed."""


def _controller_effort() -> Trace:
    """The force of a speed loop holding an axis against an unseen load: inertia, plus an
    effort that rises as the speed drops (−SPEED_GAIN v), plus noise."""
    kin = exact_kinematics()
    inertia = Model((new_term("inertia", {"M_kg": BASE["M_kg"]}),))
    force = (predict(inertia, kin).reading - SPEED_GAIN * kin.v
             + np.random.default_rng(3).normal(0, 0.3, kin.n))
    return Trace(np.arange(kin.n) / FS, kin.x, force)


def _slope(reason: str) -> float:
    return float(re.search(r"slope over the speed is (-?[\d.]+) N·s/m", reason).group(1))


def test_a_speed_loops_effort_is_named_with_its_slope():
    kin = kin_of(_controller_effort())
    model = fit_model(base_model(), kin).model
    reasons = falls_with_speed(model, kin, ClosureOptions())
    assert len(reasons) == 1 and reasons[0].startswith("the force falls as the speed rises")
    viscous = model.term("viscous").values["F_v_Ns_m"]
    assert viscous == pytest.approx(0.0, abs=1e-6), "the fit held at its physical bound"
    assert _slope(reasons[0]) == pytest.approx(-SPEED_GAIN, rel=0.05)


def test_a_passive_axis_is_not_named():
    kin = kin_of(synthetic_trace())
    model = fit_model(base_model(), kin).model
    assert falls_with_speed(model, kin, ClosureOptions()) == []


@pytest.mark.parametrize("dataset", DATASETS, ids=lambda d: d.name)
def test_in_the_gallery_only_the_speed_loop_record_is_named(dataset):
    """gchenfc/ODrive's pull test is the current of a speed loop at 1 rev/s pulling a
    cogging motor through a string (its README); every other slice is a passive reading."""
    report = _closed(dataset.name)
    named = [any("the force falls as the speed rises" in reason
                 for reason in report[verdict]["reasons"])
             for verdict in ("base_verdict", "final_verdict")]
    assert named == [dataset.name == "odrive-pull"] * 2
