"""The safe stop depends on nothing else (issue 18, item 3): one test per defect seen.

The host (`feedbench run` in its own process) runs against the simulated bench in another
process (`feedbench sim`, reached over socketcand on loopback), as on a real machine; the
drive's state afterwards is read by SDO from a third connection. Faults: a disk that fills
mid-run (the run's file-size limit, RLIMIT_FSIZE, below what the run records), a peer that
hangs for 3 s (SIGSTOP, SIGCONT), a peer that dies (SIGKILL), an address nobody listens on.
"""

from __future__ import annotations

import os
import resource
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from feedbench.bench import Bench, bench_schema
from feedbench.commands.cli import main
from feedbench.config import validate_table
from feedbench.daq.catalog import Catalog
from feedbench.daq.recording import open_recording
from feedbench.drivers.cia402 import SAFE_STATES
from prerequisites import requires
from sim_peer import start_sim
from test_sim_process import _host_bench

OPERATION_ENABLED_MASK, OPERATION_ENABLED = 0x6F, 0x27
SWEEP = ('[experiment]\ntype = "friction_sweep"\nfeeds_mm_min = [100, 200, 300, 400, 500]\n'
         "settle_s = 0.5\nmeasure_s = 0.5\n")
CHIRP = ('[limits]\nexcitation_N = 300.0\n[experiment]\ntype = "chirp"\namplitude_N = 20.0\n'
         "f_start_Hz = 10.0\nf_stop_Hz = 200.0\nduration_s = 3.0\nrepetitions = 1\n"
         "feed_mm_min = 500.0\nsettle_s = 0.2\ntail_s = 0.2\n")
FILE_LIMIT_BYTES = 1_250_000
"""The host's file-size limit in the disk-full test: the recorder's 1 MiB reserve and about
100 kB of samples (the chirp records about 4 MB)."""


def _mount_tmpfs(directory: Path, size: str) -> bool:
    """Mount a tmpfs of `size` (e.g. "1m") on `directory`; False where that is not allowed."""
    return subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(directory)],
                          capture_output=True).returncode == 0


def _can_mount_tmpfs() -> bool:
    with tempfile.TemporaryDirectory() as directory:
        if os.geteuid() != 0 or not _mount_tmpfs(Path(directory), "64k"):
            return False
        subprocess.run(["umount", directory], check=True)
        return True


def _end(process: subprocess.Popen) -> None:
    if process.poll() is None:
        process.send_signal(signal.SIGCONT)
        process.terminate()
    process.communicate(timeout=20)


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """One simulated bench process for the tests that leave it running."""
    process, info = start_sim(tmp_path_factory.mktemp("fault-sim"))
    yield process, info
    _end(process)


def _host_config(info: dict, directory: Path, experiment: str) -> Path:
    """The host's run config of `experiment` against the bench process, output to `directory`."""
    config = directory / "host.toml"
    config.write_text(_host_bench({**info, "directory": directory}) + "\n" + experiment)
    return config


def _run_with_fault(config: Path, fault: Callable[[], None]) -> int:
    """`feedbench run config` in this process, `fault()` in a thread 0.3 s after the
    recording appeared (the run is moving); the command's exit status."""
    def inject() -> None:
        deadline = time.monotonic() + 60.0
        while not list(config.parent.glob("*.h5")) and time.monotonic() < deadline:
            time.sleep(0.02)
        time.sleep(0.3)
        fault()

    thread = threading.Thread(target=inject, daemon=True)
    thread.start()
    status = main(["run", str(config)])
    thread.join()
    return status


def _drive_state(info: dict) -> str:
    """The drive's CiA 402 state, from the statusword read by SDO on a new connection."""
    cfg = validate_table({"simulated": False, "interface": "socketcand",
                          "socketcand": info["socketcand"], "channel": info["channel"]},
                         bench_schema(), "bench")
    with Bench(cfg) as bench:
        return bench.drive.state


def _file_limit() -> None:
    """In the host process: files up to FILE_LIMIT_BYTES; a longer write fails (EFBIG)."""
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (FILE_LIMIT_BYTES, FILE_LIMIT_BYTES))


def test_disk_full_mid_run_stops_the_drive_and_keeps_the_samples(sim, tmp_path):
    """The recording fails mid-chirp: the drive is stopped all the same, the samples
    flushed before stay readable, the file and the catalog say aborted and why, and the
    failure is one line on stderr (no traceback, no HDF5 noise, no SIGBUS)."""
    process, info = sim
    host = subprocess.Popen(
        [sys.executable, "-m", "feedbench.commands.cli", "run", str(_host_config(info, tmp_path, CHIRP))],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_file_limit)
    out, err = host.communicate(timeout=120)
    assert host.returncode == 1, err
    assert "Traceback" not in err and "Exception ignored" not in err
    assert [line for line in err.splitlines() if "File too large" in line] == [
        err.splitlines()[-1]]
    [row] = Catalog(tmp_path / "catalog.sqlite").list()
    assert out.split()[:3] == [row.id, "aborted", row.file]
    recording = open_recording(row.file)
    assert recording.status == row.status == "aborted"
    assert "recording failed: [Errno 27] File too large" in recording.reason
    assert row.n_samples == recording.n_samples >= 1000
    assert np.array_equal(recording.cycle, recording.cycle[0] + np.arange(recording.n_samples))
    statusword = recording.channels["statusword"].astype(int)
    assert any((statusword & OPERATION_ENABLED_MASK) == OPERATION_ENABLED), "it did run"
    assert _drive_state(info) in SAFE_STATES


def test_hung_peer_for_3_s_ends_in_a_safe_state(sim, tmp_path, capsys):
    """The bench process stopped (SIGSTOP) for 3 s mid-sweep: the host's cycle times out
    (1 s), it keeps trying to stop the drive (quick stop by SDO, a SYNC) and, once the peer
    is back, confirms a safe state; the run is aborted with the bus timeout as reason."""
    process, info = sim

    def hang() -> None:
        process.send_signal(signal.SIGSTOP)
        time.sleep(3.0)
        process.send_signal(signal.SIGCONT)

    assert _run_with_fault(_host_config(info, tmp_path, SWEEP), hang) == 1
    [line] = capsys.readouterr().out.splitlines()
    assert "aborted" in line and "BusTimeout" in line and "drive state unknown" not in line
    assert _drive_state(info) in SAFE_STATES
    recording = open_recording(Catalog(tmp_path / "catalog.sqlite").list()[0].file)
    assert recording.status == "aborted" and "BusTimeout" in recording.reason
    assert any(e.kind == "fault" and "safe state by SDO quick stop" in e.text
               for e in recording.events)


def test_killed_peer_says_drive_state_unknown_in_one_line(sim, tmp_path, capsys):
    """The bench process killed mid-sweep (the module's last test: it ends the process): the
    host tries to stop the drive for the bounded time, then says "drive state unknown" in
    its run-record line, which reaches stdout (no CanError from closing the bus of a dead
    peer, no receive thread's traceback); the file says aborted."""
    process, info = sim
    t0 = time.monotonic()
    assert _run_with_fault(_host_config(info, tmp_path, SWEEP), process.kill) == 1
    out, err = capsys.readouterr()
    assert "Traceback" not in err and "Exception in thread" not in err
    [line] = out.splitlines()
    assert "aborted" in line and "drive state unknown" in line
    assert time.monotonic() - t0 < 20.0
    recording = open_recording(Catalog(tmp_path / "catalog.sqlite").list()[0].file)
    assert recording.status == "aborted" and "drive state unknown" in recording.reason


def test_unreachable_address_is_one_line_within_5_s(tmp_path, capsys):
    with socket.socket() as probe:  # a port nobody listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    config = tmp_path / "run.toml"
    config.write_text(f'[bench]\nsimulated = false\ninterface = "socketcand"\n'
                      f'socketcand = "127.0.0.1:{port}"\noutput_dir = "{tmp_path}"\n' + SWEEP)
    t0 = time.monotonic()
    assert main(["run", str(config)]) == 2
    assert time.monotonic() - t0 < 5.0
    err = capsys.readouterr().err
    assert err.startswith(f"feedbench: error: bench.socketcand: 127.0.0.1:{port}: cannot open")
    assert len(err.splitlines()) == 1
    assert not list(tmp_path.glob("*.h5"))


@requires(_can_mount_tmpfs(), "mounting a 1 MiB tmpfs (root with the mount capability)")
def test_run_without_room_for_its_recording_is_refused_before_anything_moves(tmp_path, capsys,
                                                                                 can_channel):
    """A friction sweep (≈ 1.3 MB of recording, 2 MiB of recorder reserve, × 1.5) on a 1 MiB
    disk: one line naming bench.output_dir, status 2, no recording."""
    disk = tmp_path / "disk"
    disk.mkdir()
    assert _mount_tmpfs(disk, "1m")
    try:
        config = tmp_path / "run.toml"
        config.write_text(f'[bench]\nchannel = "{can_channel}"\noutput_dir = "{disk}"\n' + SWEEP)
        assert main(["run", str(config)]) == 2
        [line] = capsys.readouterr().err.splitlines()
        assert line.startswith(f"feedbench: error: bench.output_dir: {disk}: the run needs ")
        assert line.endswith("the disk has 1.0 MB")
        assert not list(disk.glob("*.h5"))
    finally:
        subprocess.run(["umount", str(disk)], check=True)
