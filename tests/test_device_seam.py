"""The device seam (issue 14): a device kind is one registered class (`devices`)
with its simulated peer registered under the same name (`sim_backends.process`);
`open_cycle_devices` and `SimulatedBench` iterate over a run's needs and know no kind by
name. The proof: the bumper's load-cell kind of the rack-and-pinion axis, asked for by a
tool-tip run on the lab axis, is started, served and recorded there with no wiring added.
"""

from __future__ import annotations

import uuid
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import pytest

import feedbench
from feedbench.bench import Bench, parse_run_config
from feedbench.config import OWN_DISTRIBUTION, ConfigError, read_toml, registered
from feedbench.daq.catalog import Catalog
from feedbench.daq.recording import open_recording
from feedbench.devices import (
    Device, DeviceLinks, device_tables, devices, open_cycle_devices,
)
from feedbench.engine.plan import segment_event
from feedbench.sim_backends.process import simulated_peers

EXAMPLES = Path(feedbench.__file__).parent / "examples"


def test_every_kind_is_registered_by_its_name_with_its_simulated_peer():
    kinds = devices(OWN_DISTRIBUTION)  # feedbench's own: a lab's installed kinds beside them
    assert set(kinds) == {"spindle", "daq", "exciter", "axis_settings", "encoders",
                          "load_cell"}
    assert all(kind.name == name for name, kind in kinds.items())
    # the rack-and-pinion axis's simulator serves its settings and encoders (its drives)
    assert set(simulated_peers(OWN_DISTRIBUTION)) == {"spindle", "daq", "exciter", "load_cell"}
    assert all(peer.name == name for name, peer in simulated_peers().items())


class Thermometer(Device):
    """A lab's own device kind, registered by its own package's metadata below."""

    name = "thermometer"


class Misnamed(Device):
    name = "not_its_entry_point"


def _lab_package(directory: Path, line: str) -> None:
    """An installed package of a lab whose pyproject.toml has `line` under
    ``[project.entry-points."feedbench.devices"]``: its metadata, as pip leaves it."""
    metadata = directory / "lab_devices-1.0.dist-info"
    metadata.mkdir()
    (metadata / "METADATA").write_text("Metadata-Version: 2.1\nName: lab-devices\n"
                                       "Version: 1.0\n")
    (metadata / "entry_points.txt").write_text(f"[feedbench.devices]\n{line}\n")


@pytest.fixture
def lab_package(tmp_path, monkeypatch):
    """Install a lab's package (on sys.path) for one test; the registry reads it afresh."""
    monkeypatch.syspath_prepend(str(tmp_path))
    registered.cache_clear()
    yield lambda line: _lab_package(tmp_path, line)
    registered.cache_clear()


def test_a_lab_package_adds_a_kind_with_one_entry_point_line(lab_package):
    lab_package("thermometer = test_device_seam:Thermometer")
    assert devices()["thermometer"] is Thermometer
    assert {"spindle", "daq", "exciter"} <= set(devices())


def test_a_kind_not_named_as_its_entry_point_is_refused(lab_package):
    lab_package("thermometer = test_device_seam:Misnamed")
    with pytest.raises(TypeError, match="^entry point thermometer = test_device_seam:Misnamed: "
                                        "not a Device subclass of that name$"):
        devices()


def test_an_unregistered_device_is_a_config_error():
    with pytest.raises(ConfigError, match=r"^experiment.type: needs the device thermometer, "
                                          r"which is not registered \(known: axis_settings, "
                                          r"daq, "):
        device_tables({}, {"thermometer": {}})


@pytest.mark.parametrize("kind", ["daq", "spindle", "load_cell"])
def test_a_device_without_an_address_names_its_table(kind):
    with ExitStack() as stack, pytest.raises(
            ConfigError, match=rf"^bench.devices.{kind}.address: the experiment uses the {kind} "
                               "device; give its address$"):
        open_cycle_devices(device_tables({}, {kind: {}}), DeviceLinks({}, None, {}, stack))


def test_a_lab_run_records_the_load_cell_it_asks_for(tmp_path):
    """A shaker chirp (1 sweep of 1 s, 20 N) on the lab axis with the load-cell kind added
    to its needs: the simulated bench starts the load cell's peer on its Modbus server (it
    samples the exciters' force on the tool tip once per bus cycle), the host opens it at
    the address the bench reports and records ``load_cell.force`` beside the DAQ's
    ``shaker_force``: read every 5th cycle (a Modbus round trip per cycle slows the cycle
enough, on a loaded machine, to trip the DAQ's 2 s stall check), the force at the cycle's
end, within the load cell's noise
    (2 N; measured: residual 2.03 N std, −0.07 N mean over 1500 cycles)."""
    raw = read_toml(EXAMPLES / "shaker_chirp.toml")
    raw["bench"].update(channel=f"seam-{uuid.uuid4().hex[:8]}", output_dir=str(tmp_path))
    raw["experiment"].update(duration_s=1.0, repetitions=1)
    config = parse_run_config(raw)
    needs = {**config.experiment.devices(), "load_cell": {"every_cycles": 5}}
    with Bench(config.bench, config.plan, needs) as bench:
        assert set(bench.simulated.peers) == {"daq", "exciter", "load_cell"}
        assert bench.simulated.addresses["load_cell"].startswith("127.0.0.1:")
        record = bench.run(config, Catalog(tmp_path / "catalog.sqlite"), tmp_path,
                           progress=False)
    assert record["status"] == "complete", record["reason"]
    recording = open_recording(record["file"])
    sweep, = [s for s in recording.segments() if segment_event(s.label)[1] == "excite"]
    window = recording.mask(sweep)
    read = window & np.isfinite(recording.channels["load_cell.force"])  # every 5th cycle
    cycles, load_cell = recording.cycle[read], recording.channels["load_cell.force"][read]
    stream = recording.streams["daq"]
    at_cycle_end = dict(zip(stream.cycle, stream.channels["shaker_force"]))  # last sample wins
    shaker = np.array([at_cycle_end[cycle] for cycle in cycles])
    residual = load_cell - shaker
    assert np.sqrt(np.mean(shaker ** 2)) > 10.0  # N: the 20 N chirp through the shaker
    assert abs(residual.mean()) < 0.3  # N
    assert residual.std() == pytest.approx(2.0, abs=0.3)  # N: the load cell's noise
