"""The example scripts (examples/scripts/, issue 17) run against the simulated bench and print
what the simulated world holds; Ctrl-C inside a script leaves the drive disabled and the
recording aborted.

Each script runs as its own process with short parameters from its command line; the four
start together (most of their wall time is waiting on the bus, not CPU) and each test
reads its own script's output. Tolerances are stated beside each assertion.
"""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from feedbench.config import ConfigError, read_toml
from feedbench.daq.recording import open_recording, read_summary
from feedbench.drivers.cia402 import decode_state
from feedbench.sim_backends import rack_pinion
from feedbench.sim_backends.world import world_truth
from feedbench.units import MM_PER_MIN, N_MIN_PER_MM, N_PER_UM

ROOT = Path(__file__).parents[1]
SCRIPTS = ROOT / "examples" / "scripts"
SHORT = {
    "friction_sweep_fit.py": ["--settle-s", "0.25", "--measure-s", "0.15",
                              "--feeds", "25", "50", "100", "200", "400", "800", "1500"],
    "chirp_three_gains.py": ["--duration-s", "1.5", "--repetitions", "2"],
    "stepped_loading_schedule.py": ["--single", "master", "--preloads", "18", "--step-um", "20",
                                    "--depth-um", "240", "--measure-s", "0.1", "--setup-s", "1",
                                    "--load-cell-every", "10"],
    "closure_fresh_chirp.py": ["--duration-s", "2", "--repetitions", "2"],
}
"""Per script, the command line that keeps it short."""
TIMEOUT_S = 240
LAB = world_truth({})
RACK = rack_pinion.world_truth(read_toml(ROOT / "feedbench" / "examples" /
                                         "stepped_loading.toml")["bench"]["world"])


class Scripts:
    """The scripts, each run once on first use in its own working directory, one at a time
    (four simulated benches at once, beside the other test worker, overload 2 cores)."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.done: dict[str, subprocess.CompletedProcess] = {}

    def cwd(self, name: str) -> Path:
        return self.directory / name.removesuffix(".py")

    def run(self, name: str) -> subprocess.CompletedProcess:
        if name not in self.done:
            self.cwd(name).mkdir()
            self.done[name] = subprocess.run(
                [sys.executable, str(SCRIPTS / name), *SHORT[name]], cwd=self.cwd(name),
                capture_output=True, text=True, timeout=TIMEOUT_S)
        return self.done[name]


@pytest.fixture(scope="module")
def scripts(tmp_path_factory) -> Scripts:
    return Scripts(tmp_path_factory.mktemp("scripts"))


def printed(scripts: Scripts, name: str) -> dict[str, str]:
    """The ``key = value`` lines script `name` printed (it must exit 0)."""
    done = scripts.run(name)
    assert done.returncode == 0, done.stderr[-3000:]
    return dict(re.findall(r"^(.+?) = (\S+)", done.stdout, flags=re.M))


def close(value: str, truth: float, rel: float) -> bool:
    return abs(float(value) - truth) <= rel * abs(truth)


def test_friction_sweep_then_fit(scripts):
    out = printed(scripts, "friction_sweep_fit.py")
    assert out["run"].split("-")[2] == "friction_sweep"
    for direction in ("positive", "negative"):
        true = LAB["friction"][direction]
        assert close(out[f"{direction}.F_c_N"], true["F_c"], 0.01)  # 44.2 / 38.7 N within 1 %
        assert close(out[f"{direction}.F_s_N"], true["F_s"], 0.01)  # 84 / 88 N within 1 %
        assert close(out[f"{direction}.v_s_mm_min"], true["v_s"] / MM_PER_MIN, 0.03)
        assert close(out[f"{direction}.sigma_N_min_mm"], true["sigma"] / N_MIN_PER_MM, 0.05)
        assert float(out[f"{direction}.r_squared"]) > 0.999
        # the δ-free refit finds the world's δ = 1 and the same Coulomb level
        assert close(out[f"{direction}.delta_free.delta"], true["delta"], 0.05)
        assert close(out[f"{direction}.delta_free.F_c_N"], true["F_c"], 0.02)


def test_chirp_at_three_gains(scripts):
    out = printed(scripts, "chirp_three_gains.py")
    for gain in ("6000", "9000", "13000"):
        # the mobility is the mechanics': Eqs. (4.13, 4.14) at every gain
        assert close(out[f"K_p {gain}: f_t_Hz"], LAB["f_t_hz"], 0.02)  # 61.37 Hz within 2 %
        assert close(out[f"K_p {gain}: f_r_Hz"], LAB["f_r_hz"], 0.03)  # 74.89 Hz within 3 %
        assert float(out[f"K_p {gain}: min_coherence"]) > 0.95
    plot = scripts.cwd("chirp_three_gains.py") / out["plot"]
    assert plot.read_bytes()[:4] == b"\x89PNG" and plot.stat().st_size > 20_000


def test_stepped_loading_with_own_schedule(scripts):
    out = printed(scripts, "stepped_loading_schedule.py")
    assert close(out["k_master_N_um"], RACK["k_master"] / N_PER_UM, 0.03)  # 81 N/µm within 3 %
    assert "k_slave_N_um" not in out  # the schedule loads the master alone
    assert "load_cell.force" in out["device_channels"].split(",")  # the bumper's load cell
    # Eq. (3.1): the preload is lost at twice the preload force, 2 × 18 % × 13.3 kN = 4788 N
    assert close(out["preload_18.loss_force_N"], 2 * 0.18 * RACK["rated_force"], 0.08)
    assert close(out["preload_18.torque_share"], 0.5, 0.05)  # master and slave share equally


def test_closure_on_a_fresh_chirp(scripts):
    out = printed(scripts, "closure_fresh_chirp.py")
    assert out["effects"].split(",")[0] == "structural_mode"  # the tip mode the model lacks
    assert close(out["structural_mode.f_n_Hz"], LAB["f_t_hz"], 0.03)  # 61.37 Hz within 3 %
    assert close(out["structural_mode.m_kg"], LAB["m_tip"], 0.10)  # 11.3 kg within 10 %
    assert float(out["error_after"]) < 0.7 * float(out["error_before"])


def samples_on_disk(directory: Path) -> int:
    """Samples flushed to the one recording being written in `directory` (0 while there is
    none, or while the writer's last flush leaves it unreadable for a moment)."""
    try:
        [path] = directory.glob("*.h5")
        return read_summary(path).n_samples
    except (ValueError, ConfigError):
        return 0


def test_ctrl_c_in_a_script_disables_the_drive_and_aborts_the_file(tmp_path):
    args = ["--gains", "9000", "9000", "9000", "--duration-s", "20", "--repetitions", "1"]
    process = subprocess.Popen([sys.executable, str(SCRIPTS / "chirp_three_gains.py"), *args],
                               cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True)
    deadline = time.monotonic() + TIMEOUT_S
    while (samples_on_disk(tmp_path / "runs" / "scripts")) < 500:  # the chirp is running
        assert process.poll() is None and time.monotonic() < deadline, process.stderr.read()
        time.sleep(0.2)
    files = list(tmp_path.glob("runs/scripts/*.h5"))
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=TIMEOUT_S)
    assert process.returncode != 0
    assert "RunStopped" in err and "interrupted by SIGINT" in err
    recording = open_recording(files[0])
    assert (recording.status, recording.reason) == ("aborted", "interrupted by SIGINT")
    assert recording.n_samples < 20_000  # stopped inside the 20 s sweep
    assert decode_state(int(recording.channels["statusword"][-1])) == "SWITCH ON DISABLED"
    assert len(files) == 1  # the script went no further
