"""The testing kit (`feedbench.testing`), the per-cycle device base
(`devices.PerCycleDevice`) and the registry by distribution (issue 27 items 3, 4):
a lab's package installed beside feedbench joins the demo and stays out of feedbench's own
lists."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest

from feedbench.config import OWN_DISTRIBUTION, distribution_name, registered
from feedbench.daq.recording import open_recording
from feedbench.commands.demo import campaign_config, example_config
from feedbench.devices.cycle_io import DaqStream, SpindleCommands
from feedbench.devices import PerCycleDevice
from feedbench.engine.family import LAB_RANK, examples, families
from feedbench.axes.rack_pinion import AxisEncoders, AxisSettings, LoadCellForce
from feedbench.testing import GAP_CYCLES, LIMITS, Step, cycle_rows, same, synthetic_recording

FEEDBENCH_FAMILIES = {"friction_sweep", "chirp", "closed_loop_bode", "impact_hammer",
                      "shaker_chirp", "sine_stream", "smfe", "stepped_loading",
                      "backlash_reversal"}
"""The families feedbench's pyproject.toml registers."""

# -- a lab's distribution, installed at runtime -----------------------------------------------

LAB_MODULE = '''
from feedbench.engine.family import Example, Experiment


class Reversals(Experiment):
    name = "lab_reversals"
    schema = {}
    examples = (Example("lab_reversals", {"experiment": {"amplitudes_mm": [0.1]}}),)
'''
LAB_EXAMPLE = '[bench]\nsimulated = true\n\n[experiment]\ntype = "lab_reversals"\n'


@pytest.fixture
def lab_installed(tmp_path, monkeypatch):
    """The distribution ``my-lab`` (package ``my_lab``: family ``lab_reversals`` with its
    example config) on sys.path, as `pip install` leaves it; removed afterwards."""
    package = tmp_path / "my_lab"
    (package / "examples").mkdir(parents=True)
    (package / "__init__.py").write_text(LAB_MODULE)
    (package / "examples" / "lab_reversals.toml").write_text(LAB_EXAMPLE)
    info = tmp_path / "my_lab-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: my-lab\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        "[feedbench.experiments]\nlab_reversals = my_lab:Reversals\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    registered.cache_clear()
    yield
    monkeypatch.undo()
    sys.modules.pop("my_lab", None)
    registered.cache_clear()


def test_a_lab_family_is_registered_but_not_among_feedbenchs_own(lab_installed):
    assert set(families()) >= FEEDBENCH_FAMILIES | {"lab_reversals"}  # other labs' beside
    assert set(families(OWN_DISTRIBUTION)) == FEEDBENCH_FAMILIES
    assert list(families("my-lab")) == list(families("My_Lab")) == ["lab_reversals"]


def test_a_lab_example_joins_the_demo_after_feedbenchs_own(lab_installed, tmp_path):
    everything, own = examples(), examples(OWN_DISTRIBUTION)
    assert list(everything)[:len(own)] == [*own]  # then the labs' (another lab's beside)
    assert "lab_reversals" in list(everything)[len(own):]
    lab = everything["lab_reversals"]
    assert (lab.package, lab.rank, lab.required) == ("my_lab", LAB_RANK, False)
    raw = campaign_config("lab_reversals", tmp_path / "runs", quick=True)
    assert raw["experiment"] == {"type": "lab_reversals", "amplitudes_mm": [0.1]}
    assert raw["bench"] == {"simulated": True, "output_dir": str(tmp_path / "runs")}


def test_feedbenchs_own_examples_in_the_demos_order_with_the_bench_core_required():
    own = examples(OWN_DISTRIBUTION)
    assert list(own) == ["friction_sweep", "chirp", "closed_loop_bode", "impact_hammer",
                         "shaker_chirp", "sine_stream", "smfe", "stepped_loading",
                         "backlash_reversal", "friction_sweep_rack_pinion"]
    assert [name for name, e in own.items() if e.required] == ["friction_sweep", "chirp"]
    assert {e.package for e in own.values()} == {"feedbench"}
    assert own["chirp"].config() == example_config("chirp")
    assert own["closed_loop_bode"].quick_config()["experiment"]["f_step_Hz"] == 2.0


def test_distribution_names_compare_as_pep_503_says():
    assert distribution_name("My_Lab.Tools") == distribution_name("my-lab-tools") == \
        "my-lab-tools"


# -- live = offline ---------------------------------------------------------------------------


def test_same_is_equality_of_json_like_values_with_nan_equal_to_nan():
    assert same({"a": [1.0, math.nan], "b": np.array([2.0, np.nan])},
                {"a": (1.0, math.nan), "b": np.array([2.0, np.nan])})
    assert not same({"a": 1.0}, {"a": 1.0, "b": 2.0})
    assert not same([1.0, 2.0], [1.0, 2.5])
    assert not same(np.array([1.0]), np.array([1.0, 1.0]))
    assert not same(math.nan, 0.0)


# -- synthetic recordings ---------------------------------------------------------------------


def test_a_synthetic_recording_holds_the_steps_as_the_runner_writes_them(tmp_path):
    steps = [Step("settle", "settle", {}, cycle_rows(10)),
             ("measure +1", "measure", {"feed_mm_min": 60.0},
              cycle_rows(20, velocity=1e-3, force=np.linspace(0.0, 19.0, 20)))]
    path = synthetic_recording(tmp_path / "run.h5", {"type": "friction_sweep"}, steps)
    recording = open_recording(path)
    assert (recording.experiment, recording.status, recording.n_gaps) == \
        ("friction_sweep", "complete", 0)
    assert recording.config == {"limits": LIMITS, "experiment": {"type": "friction_sweep"}}
    assert recording.metadata["cycle_s"] == 1e-3
    settle, measure = recording.segments()
    assert (settle.start, settle.stop, measure.start, measure.stop) == (1, 11, 11, 31)
    assert '"feed_mm_min": 60.0' in measure.label
    np.testing.assert_array_equal(recording.channels["force"][recording.mask(measure)],
                                  np.linspace(0.0, 19.0, 20))
    assert np.all(recording.channels["velocity"][recording.mask(settle)] == 0.0)


def test_a_synthetic_recording_with_a_daq_stream_a_gap_and_an_abort(tmp_path):
    daq = np.column_stack([np.arange(300.0), np.full(300, 2.0)])
    path = synthetic_recording(tmp_path / "run.h5", {"type": "impact_hammer"},
                               [("hit", "excite", {}, cycle_rows(30), daq)],
                               daq_channels=("hammer_force", "acc_tool_x"),
                               status="aborted", reason="limit trip", gap_after=10)
    recording = open_recording(path)
    assert (recording.status, recording.reason) == ("aborted", "limit trip")
    assert recording.n_gaps == GAP_CYCLES
    assert recording.cycle[-1] == 30 + GAP_CYCLES
    stream = recording.streams["daq"]
    assert (stream.rate_hz, stream.n_samples, stream.n_dropped) == (10_000.0, 300, 0)
    assert stream.units == {"hammer_force": "N", "acc_tool_x": "m/s^2"}
    np.testing.assert_array_equal(stream.channels["hammer_force"], np.arange(300.0))
    np.testing.assert_array_equal(np.unique(stream.cycle), recording.cycle)


# -- the simulated bench ----------------------------------------------------------------------


def test_the_simulated_bench_opens_a_config_on_its_own_channel(simulated_bench):
    raw = example_config("chirp")
    config = simulated_bench.config(raw)
    assert config.bench["channel"] == simulated_bench.channel != raw["bench"]["channel"]
    assert config.bench["output_dir"] == str(simulated_bench.directory)
    assert config.bench["simulated"] is True
    with simulated_bench.open(raw) as bench:
        assert bench.simulated is not None
        assert bench.drive.node.id == raw["bench"].get("node_id", 1)


# -- the per-cycle device base ----------------------------------------------------------------


class Link(PerCycleDevice):
    """A device whose `read` counts its calls and fails at call `fail_at`."""

    def __init__(self, every_cycles: int, fail_at: int = 0) -> None:
        super().__init__(every_cycles)
        self.calls, self.fail_at = 0, fail_at

    def read(self) -> float:
        self.calls += 1
        if self.calls == self.fail_at:
            raise OSError("link down")
        return float(self.calls)


def test_poll_reads_every_n_cycles_from_the_first_and_none_between():
    link = Link(every_cycles=3)
    assert [link.poll(link.read) for _ in range(7)] == [1.0, None, None, 2.0, None, None, 3.0]
    link.start(None, None)
    assert link.poll(link.read) == 4.0


def test_the_first_failure_is_raised_then_nothing_runs():
    link = Link(every_cycles=2, fail_at=2)
    assert link.poll(link.read) == 1.0
    assert link.poll(link.read) is None
    with pytest.raises(OSError, match="link down"):
        link.poll(link.read)
    assert link.failed
    assert [link.poll(link.read) for _ in range(4)] == [None] * 4
    assert link.guarded(link.read) is None and link.calls == 2


class Amplifier:
    """A load-cell amplifier whose second reading fails."""

    def __init__(self) -> None:
        self.calls = 0

    def reading(self):
        self.calls += 1
        if self.calls == 2:
            raise ConnectionError("Modbus: no answer")
        return type("Reading", (), {"force_N": 100.0 * self.calls, "overloaded": False})


def test_the_load_cell_answers_nan_between_readings_and_after_its_failure():
    cell = LoadCellForce(Amplifier(), every_cycles=2)
    cell.start(None, None)
    assert same([cell.after_sync(c) for c in range(2)], [(100.0,), (math.nan,)])
    with pytest.raises(ConnectionError):
        cell.after_sync(2)
    assert same([cell.after_sync(c) for c in range(3, 6)], [(math.nan,)] * 3)
    assert cell.amplifier.calls == 2


def test_the_built_in_per_cycle_devices_share_the_base():
    assert all(issubclass(kind, PerCycleDevice) for kind in
               (SpindleCommands, DaqStream, LoadCellForce, AxisSettings, AxisEncoders))
