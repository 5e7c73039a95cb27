"""Recorder + reader: bit-exact round trip, bounded memory, live (SWMR) reading, crash
safety, gap detection, abort status."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest

from feedbench.config import ConfigError
from feedbench.daq import recorder as recorder_module
from feedbench.daq.recorder import Recorder, RecordingError, software_versions
from feedbench.daq.recording import Segment, open_recording

CHANNELS = [f"ch{index}" for index in range(10)]
UNITS = {name: "m" for name in CHANNELS}
METADATA = {
    "experiment": "friction_sweep",
    "config": {"experiment": {"feeds_mm_min": [10.0, 100.0]}, "bench": {"node_id": 1}},
    "operator": "test",
}


def reference_values(cycles: np.ndarray) -> np.ndarray:
    """Deterministic, non-trivial float64 rows (n × 10) for bit-exact comparison."""
    return np.sin(np.outer(cycles, np.arange(1, 11)) * 1e-3) * 1e3 + cycles[:, None] * 1e-7


def test_round_trip_is_bit_exact_with_attrs_and_events(tmp_path: Path) -> None:
    path = tmp_path / "run.h5"
    cycles = np.arange(25_003, dtype=np.int64)
    values = reference_values(cycles)
    with Recorder(path, CHANNELS, UNITS, METADATA, chunk_rows=1000) as recorder:
        recorder.event(0, "segment", "feed 10 mm/min")
        for cycle, row in zip(cycles[:12_000], values[:12_000]):
            recorder.append(int(cycle), row.tolist())
        recorder.event(12_000, "segment", "feed 100 mm/min")
        recorder.append_block(cycles[12_000:], values[12_000:])
        assert recorder.n_samples == 25_003

    recording = open_recording(path)
    np.testing.assert_array_equal(recording.cycle, cycles)
    for column, name in enumerate(CHANNELS):
        np.testing.assert_array_equal(recording.channels[name], values[:, column])
    assert recording.units == UNITS
    assert recording.status == "complete"
    assert recording.reason == ""
    assert recording.experiment == "friction_sweep"
    assert recording.config == METADATA["config"]
    assert recording.metadata == {"operator": "test"}
    assert recording.versions["numpy"] == np.__version__
    assert recording.versions["h5py"] == h5py.__version__
    assert recording.started_at.endswith("+00:00") and recording.stopped_at > recording.started_at
    assert recording.n_gaps == 0
    assert [(event.cycle, event.kind, event.text) for event in recording.events] == [
        (0, "segment", "feed 10 mm/min"),
        (12_000, "segment", "feed 100 mm/min"),
    ]
    assert recording.segments() == [
        Segment("feed 10 mm/min", 0, 12_000),
        Segment("feed 100 mm/min", 12_000, 25_003),
    ]
    assert int(recording.mask(recording.segments()[1]).sum()) == 13_003
    with h5py.File(path, "r") as file:
        assert file.attrs["n_samples"] == 25_003
        assert file["data/ch0"].chunks == (1000,)
        assert json.loads(file.attrs["channels"]) == CHANNELS


def test_software_versions_are_read_once_and_each_caller_gets_its_own_copy():
    """The installed packages' metadata is read once per process (9 ms a recording before);
    a caller that changes its dict changes nobody else's."""
    first = software_versions()
    assert first["numpy"] == np.__version__ and first["python-can"] is not None
    first["numpy"] = "changed"
    assert software_versions()["numpy"] == np.__version__


def test_buffer_is_bounded_and_each_chunk_is_on_disk_for_a_live_reader(tmp_path: Path) -> None:
    path = tmp_path / "live.h5"
    chunk_rows = 500
    cycles = np.arange(5 * chunk_rows + 123, dtype=np.int64)
    values = reference_values(cycles)
    with Recorder(path, CHANNELS, UNITS, METADATA, chunk_rows=chunk_rows) as recorder:
        assert recorder.buffer_rows == chunk_rows
        for cycle, row in zip(cycles, values):
            recorder.append(int(cycle), row.tolist())
            if recorder.n_samples % chunk_rows == 0:
                live = open_recording(path)
                assert live.status == "running"
                assert live.n_samples == recorder.n_samples
                np.testing.assert_array_equal(live.channels["ch9"], values[: live.n_samples, 9])
        assert recorder.buffer_rows == chunk_rows
        assert open_recording(path).n_samples == 5 * chunk_rows
    assert open_recording(path).n_samples == len(cycles)


CRASHING_WRITER = """
import sys, time
import numpy as np
from feedbench.daq.recorder import Recorder

path, chunk_rows = sys.argv[1], int(sys.argv[2])
recorder = Recorder(path, ["a", "b"], {"a": "m", "b": "N"}, {"experiment": "crash"},
                    chunk_rows=chunk_rows)
recorder.event(0, "segment", "first")
for cycle in range(5 * chunk_rows + chunk_rows // 2):
    recorder.append(cycle, [cycle * 0.5, -cycle * 0.25])
print("ready", recorder.n_samples, flush=True)
time.sleep(60)
"""


def test_other_process_reads_live_file_and_file_of_killed_writer(tmp_path: Path) -> None:
    path = tmp_path / "crash.h5"
    chunk_rows = 1000
    writer = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(CRASHING_WRITER), str(path), str(chunk_rows)],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert writer.stdout.readline().split() == ["ready", str(5 * chunk_rows + chunk_rows // 2)]
        live = open_recording(path)
        assert (live.status, live.n_samples) == ("running", 5 * chunk_rows)
    finally:
        writer.send_signal(signal.SIGKILL)
        writer.wait(timeout=10)
    assert writer.returncode == -signal.SIGKILL

    recording = open_recording(path)
    assert recording.status == "running"
    assert recording.stopped_at == ""
    flushed = np.arange(5 * chunk_rows)
    np.testing.assert_array_equal(recording.cycle, flushed)
    np.testing.assert_array_equal(recording.channels["a"], flushed * 0.5)
    np.testing.assert_array_equal(recording.channels["b"], -flushed * 0.25)
    assert [(event.cycle, event.kind, event.text) for event in recording.events] == [
        (0, "segment", "first")
    ]


def test_gap_is_reported_with_missing_range_and_count(tmp_path: Path) -> None:
    path = tmp_path / "gap.h5"
    cycles = np.r_[0:100, 105:200]
    with Recorder(path, ["x"], {"x": "m"}, {"experiment": "gap"}, chunk_rows=64) as recorder:
        for cycle in cycles:
            recorder.append(int(cycle), [float(cycle)])
        assert recorder.gaps == 5

    recording = open_recording(path)
    assert recording.n_gaps == 5
    assert [(event.cycle, event.kind) for event in recording.events] == [(105, "gap")]
    assert "100-104" in recording.events[0].text
    np.testing.assert_array_equal(recording.cycle, cycles)
    with h5py.File(path, "r") as file:
        assert file.attrs["n_gaps"] == 5


def test_block_gaps_match_row_by_row_gaps(tmp_path: Path) -> None:
    cycles = np.r_[0:10, 12:20, 30:40]
    with Recorder(tmp_path / "b.h5", ["x"], {"x": "m"}, {}, chunk_rows=7) as recorder:
        recorder.append_block(cycles[:15], np.zeros((15, 1)))
        recorder.append_block(cycles[15:], np.zeros((len(cycles) - 15, 1)))
        recorder.append(45, [0.0])
    recording = open_recording(tmp_path / "b.h5")
    assert recording.n_gaps == 2 + 10 + 5
    assert [event.text for event in recording.events] == [
        "missing cycles 10-11 (2)",
        "missing cycles 20-29 (10)",
        "missing cycles 40-44 (5)",
    ]


def test_exception_inside_with_marks_the_run_aborted(tmp_path: Path) -> None:
    path = tmp_path / "abort.h5"
    with pytest.raises(RuntimeError, match="following error too large"):
        with Recorder(path, ["x"], {"x": "m"}, {"experiment": "abort"}, chunk_rows=10) as recorder:
            for cycle in range(25):
                recorder.append(cycle, [cycle * 1.0])
            raise RuntimeError("following error too large")
    assert recorder.closed
    recording = open_recording(path)
    assert (recording.status, recording.reason) == ("aborted", "following error too large")
    np.testing.assert_array_equal(recording.channels["x"], np.arange(25.0))


def test_close_is_idempotent_and_closed_recorder_refuses_rows(tmp_path: Path) -> None:
    path = tmp_path / "twice.h5"
    recorder = Recorder(path, ["x"], {"x": "m"}, {}, chunk_rows=10)
    recorder.append(0, [1.0])
    recorder.close("aborted", "limit: position")
    stopped_at = open_recording(path).stopped_at
    recorder.close()
    recording = open_recording(path)
    assert (recording.status, recording.reason, recording.stopped_at) == (
        "aborted", "limit: position", stopped_at,
    )
    with pytest.raises(RuntimeError, match="closed"):
        recorder.append(1, [2.0])


def test_a_header_declaring_more_rows_than_the_file_holds_is_refused_before_reading(
        tmp_path: Path) -> None:
    """Found by fuzzing: a damaged extent made the reader allocate gigabytes of fill values.
    Every row dataset's rows must fit the file's bytes (but for one unwritten chunk)."""
    path = tmp_path / "run.h5"
    with Recorder(path, ["x"], {"x": "m"}, {}, chunk_rows=100) as recorder:
        recorder.append_block(np.arange(250), np.zeros((250, 1)))
    with h5py.File(path, "r+") as file:
        for name in ("cycle", "data/x"):
            file[name].resize((10**9,))  # nothing allocated: reading it would make 8 GB
    size = path.stat().st_size
    assert size < 10**6
    with pytest.raises(ConfigError, match=rf"^{path}: not a feedbench recording \(/cycle: "
                                          rf"1000000000 rows of 8 bytes do not fit in the "
                                          rf"file's \d+ bytes\)$"):
        open_recording(path)
    with h5py.File(path, "r+") as file:
        file["cycle"].resize((250,))
        file["data/x"].resize((350,))  # a writer died between this resize and the next
    assert open_recording(path).n_samples == 250


LOCKING_READER = textwrap.dedent("""
    import sys, time
    import h5py
    with h5py.File(sys.argv[1], "r", swmr=True):  # h5py's default: a shared file lock
        print("open", flush=True)
        time.sleep(float(sys.argv[2]))
""")


def closed_while_locked(path: Path, hold_s: float) -> Recorder:
    """A recorder of 10 rows and another process that holds a lock on its file for
    `hold_s` (s) while the recorder closes it: the recorder, closed or having raised."""
    recorder = Recorder(path, CHANNELS, UNITS, METADATA, chunk_rows=4)
    recorder.append_block(np.arange(10), reference_values(np.arange(10)))
    holder = subprocess.Popen([sys.executable, "-c", LOCKING_READER, str(path), str(hold_s)],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline() == "open\n"
        recorder.close()
    finally:
        holder.wait(30)
    return recorder


def test_a_lock_held_by_another_process_delays_the_status_and_the_file_says_so(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    closed_while_locked(tmp_path / "run.h5", hold_s=0.5)
    recording = open_recording(tmp_path / "run.h5")
    assert (recording.status, recording.n_samples) == ("complete", 10)
    wait = recording.metadata["status_wait"]
    assert wait["attempts"] > 1 and 0.2 < wait["waited_s"] < recorder_module.STATUS_LOCK_WAIT_S
    [line] = [r.getMessage() for r in caplog.records if r.name == recorder_module.__name__]
    assert line.startswith(f"{tmp_path / 'run.h5'}: status complete written after "
                           f"{wait['attempts']} attempts in ")


def test_a_lock_held_past_the_bound_is_one_error_naming_the_wait(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(recorder_module, "STATUS_LOCK_WAIT_S", 0.3)
    with pytest.raises(RecordingError, match=r"status complete not written \(.*unable to lock "
                       r"file.*; locked by another process through \d+ attempts in 0\.\d s\)"):
        closed_while_locked(tmp_path / "run.h5", hold_s=1.5)
    assert open_recording(tmp_path / "run.h5").status == "running"
