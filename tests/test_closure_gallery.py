"""The gallery of real measurements from other labs (tests/data, issue 24.5): every slice
reads through the CSV + sidecar route with the units, shape and sample rate its README
states, and the closure runs on every dataset. What the closure finds there is measured by
`benchmarks/bench_closure_real.py`; only what holds whatever the closure's search does is
asserted here."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from feedbench.cli import main
from feedbench.closure_command import closure_report
from feedbench.closure_io import read_csv_trace
from gallery import Dataset, datasets

DATASETS = datasets()
RECORDINGS = [(d, path) for d in DATASETS for path in d.files]
RANGE_TOLERANCE = 1e-3
"""Largest difference of a recorded [min, max] from gallery.toml, as a fraction of its span
(the table rounds to four or five digits)."""


def _id(item: Dataset | tuple[Dataset, object]) -> str:
    dataset, path = item if isinstance(item, tuple) else (item, item.fit)
    return f"{dataset.name}/{path.name}"


def test_the_gallery_has_four_datasets_and_holds_one_out():
    assert len(DATASETS) >= 4
    assert any(d.held_out for d in DATASETS)
    assert {d.key for d in DATASETS} <= {"ripple", "coulomb", "stribeck", "offset",
                                         "backlash", "structural_mode", "delay"}


@pytest.mark.parametrize("dataset", DATASETS, ids=_id)
def test_every_dataset_states_source_licence_and_key(dataset):
    readme = (dataset.fit.parent / "README.md").read_text()
    for needed in ("Source", "commit", "Licence", "Sampling", f"`{dataset.key}`"):
        assert needed in readme, f"{dataset.name}/README.md lacks {needed!r}"
    assert ("HELD OUT" in readme) == dataset.held_out


@pytest.mark.parametrize(("dataset", "path"), RECORDINGS, ids=map(_id, RECORDINGS))
def test_every_slice_reads_with_its_units_shape_and_rate(dataset, path):
    expected = dataset.recordings[path.name]
    trace, controller = read_csv_trace(path)
    assert path.stat().st_size < 1_000_000
    assert controller == {}
    assert trace.n_samples == expected["samples"]
    assert trace.sample_rate == pytest.approx(expected["sample_rate_Hz"], rel=1e-6)
    for channel in ("position", "force", "external_force"):
        values = getattr(trace, channel)
        if channel not in expected:
            assert values is None, f"{channel} read but not declared in gallery.toml"
            continue
        low, high = expected[channel]
        span = high - low
        np.testing.assert_allclose([values.min(), values.max()], [low, high],
                                   atol=RANGE_TOLERANCE * span, err_msg=channel)


@pytest.mark.parametrize("dataset", DATASETS, ids=_id)
def test_the_closure_runs_on_every_dataset(dataset):
    report = closure_report(dataset.fit, dataset.model, dataset.validation)
    result = report.result
    assert math.isfinite(result.error_before) and result.error_before > 0.0
    assert math.isfinite(result.error_after) and result.error_after > 0.0


def test_feedbench_closure_takes_a_gallery_slice_from_the_command_line(capsys):
    dataset = next(d for d in DATASETS if d.validation is not None)
    code = main(["closure", str(dataset.fit), "--model", str(dataset.model),
                 "--validation", str(dataset.validation), "--json"])
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    assert math.isfinite(out["error_before"]) and math.isfinite(out["error_after"])
