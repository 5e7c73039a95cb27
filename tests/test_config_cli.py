"""Bad input: one clear line naming the field and the reason, exit status 2, no traceback."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from feedbench.bench import parse_run_config
from feedbench.config import ConfigError
from feedbench.commands.demo import example_config

BAD_CASES = {
    "unknown key": ("[experiment]\ntype = 'friction_sweep'\nfeeds = [100]\n",
                    "experiment.feeds: unknown key"),
    "wrong type": ("[experiment]\ntype = 'friction_sweep'\nsettle_s = 'long'\n",
                   "experiment.settle_s: must be a number"),
    "negative feed": ("[experiment]\ntype = 'friction_sweep'\nfeeds_mm_min = [100, -50]\n",
                      "experiment.feeds_mm_min[1]: must be > 0 (got -50)"),
    "excitation above force limit": (
        "[limits]\nforce_N = 500.0\nexcitation_N = 5000.0\n"
        "[experiment]\ntype = 'chirp'\namplitude_N = 800.0\n",
        "experiment.amplitude_N: 800 N exceeds the force limit limits.force_N (500 N)"),
    "bad bench type": ("[bench]\nnode_id = 'one'\n[experiment]\ntype = 'chirp'\n",
                       "bench.node_id: must be a integer"),
    "unknown experiment": ("[experiment]\ntype = 'dance'\n", "experiment.type: must be one of"),
}


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_config_prints_one_line_and_exits_2(tmp_path: Path, case: str) -> None:
    text, expected = BAD_CASES[case]
    config = tmp_path / "bad.toml"
    config.write_text(text + f"[bench]\noutput_dir = '{tmp_path}'\n" if "[bench]" not in text
                      else text)
    proc = subprocess.run([sys.executable, "-m", "feedbench.commands.cli", "run", str(config)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("feedbench: error: ")
    assert expected in lines[0]
    assert "Traceback" not in proc.stderr
    assert not list(tmp_path.glob("*.h5")), "nothing may be recorded (nothing moved)"


def test_examples_validate() -> None:
    for name in ("friction_sweep", "chirp"):
        config = parse_run_config(example_config(name))
        assert config.plan.n_cycles > 1000


def test_chirp_above_nyquist_rejected() -> None:
    raw = {"experiment": {"type": "chirp", "f_stop_Hz": 600.0}}
    with pytest.raises(ConfigError, match="experiment.f_stop_Hz: must be below the bus Nyquist"):
        parse_run_config(raw)


def test_commands_that_read_no_mdf4_start_without_asammdf_and_the_others_keep_it():
    """`feedbench sim`, `run`… mark asammdf absent before python-can imports it for its MF4
    log format (0.66 s of every start); python-can then works without MF4, as where asammdf
    is not installed. The commands that read recordings of other DAQ systems are not among
    them, and asammdf still loads there."""
    from feedbench.commands.cli import WITHOUT_MF4, build_parser

    commands = set(build_parser()._subparsers._group_actions[0].choices)
    assert WITHOUT_MF4 < commands
    assert not WITHOUT_MF4 & {"import", "analyze", "report", "closure", "live", "export"}
    probe = ("import sys\n"
             "from feedbench.commands.cli import without_python_can_mf4\n"
             "without_python_can_mf4() if sys.argv[1] == 'without' else None\n"
             "import can\n"
             "bus = can.Bus(interface='virtual', channel='mf4-probe')\n"
             "bus.shutdown()\n"
             "print(sys.modules.get('asammdf') is not None)\n")
    loaded = {how: subprocess.run([sys.executable, "-c", probe, how], capture_output=True,
                                  text=True, check=True).stdout.strip()
              for how in ("without", "with")}
    assert loaded == {"without": "False", "with": "True"}


def test_a_campaign_over_recorded_runs_reads_an_mdf4_file_in_a_fresh_process(tmp_path):
    """`feedbench campaign --runs FILE.mf4` imports the file with asammdf (so `campaign` is
    not among `WITHOUT_MF4`): in its own process, where nothing imported asammdf before,
    the CANape recording's chirp is analysed."""
    data = Path(__file__).parent / "data" / "asap2-canape" / "ASAP2_Demo_V171_slice.mf4"
    proc = subprocess.run([sys.executable, "-m", "feedbench.commands.cli", "campaign", "--runs",
                           str(data), "--dir", str(tmp_path)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "1 of 1 runs complete" in proc.stdout and "f_t " in proc.stdout
