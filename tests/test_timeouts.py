"""No wait without a bound (issue 26, item 3): a peer that accepts the connection and never
speaks is one line within 2 s, against a real listening socket on 127.0.0.1.

The bounds are the named timeouts of docs/faults.md ("Every wait has a bound"):
`protocols.canbus.HANDSHAKE_TIMEOUT_S` (socketcand hello, open, rawmode),
`drivers.modbus_devices.MODBUS_TIMEOUT_S` (Modbus connect and each request).
"""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
from typing import Iterator

import pytest

from feedbench.commands.cli import main
from feedbench.daq.catalog import Catalog
from feedbench.daq.recording import open_recording
from feedbench.drivers.modbus_devices import DeviceError, SpindleInverter, connect_tcp
from feedbench.engine.family import families
from sim_peer import start_sim
from test_fault_paths import SWEEP, _end, _host_config, _run_with_fault


@contextmanager
def silent_peer() -> Iterator[int]:
    """A TCP listener on 127.0.0.1 whose backlog accepts connections (the kernel completes
    the handshake) and that never reads or writes; its port."""
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(8)
        yield server.getsockname()[1]


def test_a_silent_socketcand_peer_is_one_line_within_2_s(tmp_path, capsys):
    with silent_peer() as port:
        config = tmp_path / "run.toml"
        config.write_text(f'[bench]\nsimulated = false\ninterface = "socketcand"\n'
                          f'socketcand = "127.0.0.1:{port}"\noutput_dir = "{tmp_path}"\n' + SWEEP)
        families()  # the experiment families imported (scipy: seconds), not part of the wait
        t0 = time.monotonic()
        status = main(["run", str(config)])
        elapsed = time.monotonic() - t0
    assert status == 2 and elapsed < 2.0
    out, err = capsys.readouterr()
    assert out == ""
    assert err == (f"feedbench: error: bench.socketcand: 127.0.0.1:{port}: cannot open (the "
                   "server did not say '< hi >' within 1 s)\n")
    assert not list(tmp_path.glob("*.h5"))


def test_a_silent_modbus_peer_is_an_error_within_2_s():
    with silent_peer() as port:
        t0 = time.monotonic()
        client = connect_tcp("127.0.0.1", port)
        with pytest.raises(DeviceError) as info:
            SpindleInverter(client).check_fault()
        elapsed = time.monotonic() - t0
        client.close()
    assert elapsed < 2.0
    assert "\n" not in str(info.value)


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> Iterator[tuple[subprocess.Popen, dict]]:
    """One `feedbench sim` for both tests (one start-up fewer, as test_fault_paths' hung and
    killed peers): the hung one leaves it running again, the killed one (the module's last)
    ends it. The host records into each test's `tmp_path`."""
    process, info = start_sim(tmp_path_factory.mktemp("timeouts-sim"))
    yield process, info
    if process.returncode is None:
        _end(process)


def test_a_hung_peers_stack_log_lines_go_to_the_runs_file(sim, tmp_path, capsys):
    """The bench process stopped (SIGSTOP) for 3 s mid-sweep: canopen's own lines about the
    SDO transfers that timed out are ``log`` events in the recording, not bare on stderr."""
    process, info = sim

    def hang() -> None:
        process.send_signal(signal.SIGSTOP)
        time.sleep(3.0)
        process.send_signal(signal.SIGCONT)

    assert _run_with_fault(_host_config(info, tmp_path, SWEEP), hang) == 1
    err = capsys.readouterr().err
    assert "canopen" not in err and "Transfer aborted" not in err
    recording = open_recording(Catalog(tmp_path / "catalog.sqlite").list()[0].file)
    logs = [e.text for e in recording.events if e.kind == "log"]
    assert "canopen.sdo.client: error: Transfer aborted by client with code 0x05040000" in logs


def test_the_host_exits_within_2_s_of_its_final_line_after_a_killed_sim(sim, tmp_path):
    process, info = sim
    config = _host_config(info, tmp_path, SWEEP)
    host = subprocess.Popen([sys.executable, "-m", "feedbench.commands.cli", "run", str(config)],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        deadline = time.monotonic() + 60.0
        while not list(tmp_path.glob("*.h5")) and time.monotonic() < deadline:
            time.sleep(0.02)
        time.sleep(0.3)
        process.kill()
        line = host.stdout.readline()
        final = time.monotonic()
        host.wait(timeout=30)
        exited = time.monotonic()
    finally:
        _end(process)
        if host.poll() is None:
            host.kill()
    assert "aborted" in line and "drive state unknown" in line
    assert exited - final < 2.0
