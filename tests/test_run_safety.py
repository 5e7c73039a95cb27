"""Safe stops: Ctrl-C mid-run, a limit trip, a plan outside the travel."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from feedbench.bench import parse_run_config, run_config
from feedbench.daq.catalog import Catalog
from feedbench.daq.recording import open_recording
from feedbench.commands.demo import example_config
from feedbench.drivers.cia402 import decode_state
from feedbench.engine.limits import LimitError

OPERATION_ENABLED_MASK, OPERATION_ENABLED = 0x6F, 0x27


def _config(tmp_path: Path, channel: str, name: str = "friction_sweep") -> dict:
    raw = example_config(name)
    raw["bench"].update(output_dir=str(tmp_path), channel=channel)
    return raw


def _write_toml(raw: dict, path: Path) -> None:
    lines = []
    for table, values in (("bench", raw["bench"]), ("limits", raw["limits"]),
                          ("experiment", raw["experiment"])):
        lines.append(f"[{table}]")
        lines += [f"{k} = {v!r}".replace("'", '"').replace("True", "true").replace("False", "false")
                  for k, v in values.items() if not isinstance(v, dict)]
    path.write_text("\n".join(lines) + "\n")


def _assert_stopped_safely(recording) -> None:
    assert recording.status == "aborted"
    assert recording.n_gaps == 0
    assert np.array_equal(np.diff(recording.cycle), np.ones(recording.n_samples - 1))
    statusword = recording.channels["statusword"].astype(int)
    assert decode_state(int(statusword[-1])) == "SWITCH ON DISABLED"
    assert any((statusword & OPERATION_ENABLED_MASK) == OPERATION_ENABLED), "it did run"


def test_sigint_mid_run_ramps_down_disables_and_keeps_every_sample(tmp_path, can_channel):
    config = tmp_path / "sweep.toml"
    _write_toml(_config(tmp_path, can_channel), config)
    proc = subprocess.Popen([sys.executable, "-m", "feedbench.commands.cli", "run", str(config)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for line in proc.stderr:
        if "%" in line:  # the first progress line: about a wall second into the run
            break
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 1, err
    assert "aborted" in out and "SIGINT" in out
    [row] = Catalog(tmp_path / "catalog.sqlite").list()
    assert row.status == "aborted" and "SIGINT" in row.reason
    recording = open_recording(row.file)
    _assert_stopped_safely(recording)
    assert "SIGINT" in recording.reason
    assert row.n_samples == recording.n_samples > 500
    abort = [e for e in recording.events if e.kind == "abort"]
    assert len(abort) == 1
    after = recording.cycle >= abort[0].cycle
    commanded_speed = np.abs(np.diff(recording.channels["x_ref"][after])) / 1e-3
    assert commanded_speed.max(initial=0.0) <= 0.03, "the stop ramp never speeds up"


def test_force_limit_trip_aborts_with_reason(tmp_path, can_channel):
    raw = _config(tmp_path, can_channel, "chirp")
    raw["limits"].update(force_N=120.0, excitation_N=100.0)
    raw["experiment"].update(amplitude_N=100.0, repetitions=1)
    row = run_config(parse_run_config(raw), progress=False)
    assert row["status"] == "aborted"
    assert "limit tripped: |force|" in row["reason"]
    recording = open_recording(row["file"])
    _assert_stopped_safely(recording)
    assert recording.channels["force_offset"][-1] == 0.0


def test_plan_outside_travel_is_refused_before_anything_moves(tmp_path, can_channel):
    raw = _config(tmp_path, can_channel)
    raw["limits"]["position_mm"] = [-5.0, 5.0]
    with pytest.raises(LimitError, match="limits.position_mm: the plan reaches"):
        run_config(parse_run_config(raw), progress=False)
    assert not list(tmp_path.glob("*.h5"))
