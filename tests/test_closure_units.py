"""The units the closure's report names: a rotary axis's (rad, N·m, kg·m²) where the recording
is rotary, a linear axis's (m, N, kg) otherwise; keys and numbers the same either way."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from feedbench.analysis.closure import Trace, report_dict, report_text, run_closure
from feedbench.analysis.closure.effects import EFFECTS
from feedbench.analysis.closure.spec import parse_model_config
from feedbench.analysis.closure.units import ROTARY_UNITS, axis_unit
from feedbench.closure_io import read_csv_trace, write_csv_trace
from gallery import DATA
from test_closure_gallery import closure_of

LINEAR_UNIT = re.compile(r"(?<![\w·/])(mm|µm|mm/s|mm/min|N|kg|N·s/m|N/µm)(?![\w·/²])")
"""A linear unit standing alone (not part of a key such as pitch_mm, nor of N·m or kg·m²)."""

AXIS_FREE = frozenset({"-", "Hz", "ms"})
"""Parameter units that name no length and no force."""


def test_every_parameter_unit_has_its_rotary_counterpart_or_names_no_axis():
    units = {p.unit for effect in EFFECTS.values() for p in effect.parameters}
    assert units - AXIS_FREE <= set(ROTARY_UNITS)
    assert all(axis_unit(unit, False) == unit for unit in units | set(ROTARY_UNITS))
    assert axis_unit("Hz", True) == "Hz" and axis_unit("N·s/m", True) == "N·m·s/rad"


def test_a_rotary_sidecar_makes_a_rotary_trace_and_a_linear_one_a_linear_trace():
    assert read_csv_trace(DATA / "odrive-pull" / "pull.csv")[0].rotary
    assert not read_csv_trace(DATA / "pneumatic-seal" / "oring_3bar.csv")[0].rotary


@pytest.mark.parametrize("rotary", [True, False])
def test_a_written_trace_reads_back_on_its_kind_of_axis(tmp_path, rotary):
    t = np.arange(200) / 100.0
    written = Trace(t, 0.5 * np.sin(t), np.cos(t), rotary=rotary)
    write_csv_trace(tmp_path / "axis.csv", written, {})
    read = read_csv_trace(tmp_path / "axis.csv")[0]
    assert read.rotary is rotary
    np.testing.assert_allclose(read.position, written.position, rtol=1e-8)
    np.testing.assert_allclose(read.force, written.force, rtol=1e-8)
    sidecar = (tmp_path / "axis.toml").read_text()
    assert ('force = "Nm"' in sidecar) is rotary and ('force = "N"' in sidecar) is not rotary


def test_a_validation_trace_of_the_other_kind_of_axis_is_refused():
    t = np.arange(2000) / 1000.0
    x = 0.05 * np.sin(2 * np.pi * t)
    force = 3.0 * np.gradient(np.gradient(x, t), t)
    spec = parse_model_config({"terms": {"inertia": {"M_kg": "free"}}})
    with pytest.raises(ValueError, match=r"slides: linear \(m\), but turns is rotary \(rad\): "
                                         "both must be of one axis"):
        run_closure(spec, Trace(t, x, force, name="turns", rotary=True),
                    Trace(t, x, force, name="slides"))


REPORTED = {
    "odrive-pull": (True, LINEAR_UNIT, (
        "samples slower than 185 mrad/s not used",
        "+ ripple (amplitude 0.821 N·m at pitch 898 mrad)",
        "+ offset (offset_N = 4.119 N·m)",
        "M_kg = 0.00092863 ± 0.000435 kg·m²",
        "slope over the speed is -1.163 N·m·s/rad",
        "modal mass 0 kg·m² outside")),
    "pneumatic-seal": (False, re.compile(r"rad|N·m|kg·m²"), (
        "samples slower than 0.321 mm/s not used",
        "inertia.M_kg = 0 kg is on the lower bound of its range",
        "viscous.F_v_Ns_m = 0 N·s/m",
        "Stribeck velocity 1256 mm/min beyond the fastest speed used",
        "+ coulomb (F_c_N = 5.942)",
        "    F_c_N = 5.9423 ± 0.304\n")),
}
"""Per gallery dataset: rotary, the units its text must not name, lines it holds."""


@pytest.mark.parametrize("name", REPORTED)
def test_the_text_names_the_units_of_the_axis_recorded(name):
    rotary, foreign, lines = REPORTED[name]
    report = closure_of(name)
    text = report_text(report)
    assert [line for line in lines if line not in text] == []
    assert foreign.findall(text) == []
    assert report_dict(report)["rotary"] is rotary


def test_a_rotary_json_keeps_its_keys_and_values_and_names_the_rotary_units():
    data = report_dict(closure_of("odrive-pull"))
    assert "pitch_mm" in data["params"]["ripple"] and "offset_N" in data["params"]["offset"]
    assert math.isclose(data["params"]["ripple"]["pitch_mm"]["value"], 897.99, rel_tol=1e-4)
    assert data["final_verdict"]["on_bounds"] == ["viscous.F_v_Ns_m = 0 N·m·s/rad"]
    described = " ".join(step["description"] for step in data["steps"])
    assert LINEAR_UNIT.findall(described) == []
