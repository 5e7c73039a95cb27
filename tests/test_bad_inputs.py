"""Bad input to every command ends in one line on stderr that names the file, field or
channel and what is wrong, exit status 2, never a traceback — and nothing already recorded
or catalogued is touched (issue 12, item 3). `--debug` shows the traceback instead.

Each case builds its bad input in a copy of a small run directory (one good recording and
its catalog row, made once per module) and runs `feedbench.commands.cli.main` in-process.
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import warnings
from pathlib import Path
from typing import Callable

import h5py
import numpy as np
import pytest

from feedbench.commands.cli import main
from feedbench.closure_io import write_csv_trace
from feedbench.analysis.closure import Trace
from feedbench.daq.catalog import Catalog
from feedbench.daq.recorder import Recorder
from feedbench.experiments.impact_hammer import FORCE_CHANNEL, RESPONSE_CHANNEL
from test_report import COLUMN, PER_CYCLE, daq_step, friction_steps, record, record_with_daq

GOOD = "good.h5"
FEEDS = [25, 50, 75, 100, 150, 200, 300, 400, 500, 700, 900, 1200, 1500]
STEPS_PER_FEED = 6
"""`friction_steps`: accelerate, measure and stop, in each direction."""


@pytest.fixture(scope="module")
def template(tmp_path_factory) -> Path:
    """A run directory: a good friction-sweep recording and its catalog row."""
    directory = tmp_path_factory.mktemp("runs")
    record(directory / GOOD, "friction_sweep", friction_steps(),
           config={"type": "friction_sweep", "feeds_mm_min": FEEDS})
    catalog = Catalog(directory / "catalog.sqlite")
    run_id = catalog.new_run_id("friction_sweep")
    catalog.add(run_id, "friction_sweep", str(directory / GOOD), {"feeds": len(FEEDS)})
    catalog.finish(run_id, "complete", "", 1)
    return directory


@pytest.fixture
def runs(template: Path, tmp_path: Path) -> Path:
    """This case's copy of the template run directory."""
    return Path(shutil.copytree(template, tmp_path / "runs"))


# -- the bad inputs: each writes its files into `d` and returns the command line -----------

def config(d: Path, text: str, name: str = "bad.toml") -> str:
    """A run config file: `text` with its [bench] table (made if missing) writing into `d`."""
    path = d / name
    output = f"[bench]\noutput_dir = '{d}'\n"
    if "output_dir" not in text:
        text = text.replace("[bench]\n", output, 1) if "[bench]\n" in text else output + text
    path.write_text(text)
    return str(path)


def run(text: str) -> Callable[[Path], list[str]]:
    return lambda d: ["run", config(d, text)]


def friction(extra: str) -> Callable[[Path], list[str]]:
    return run(f"[experiment]\ntype = 'friction_sweep'\n{extra}\n")


def stepped(extra: str) -> Callable[[Path], list[str]]:
    return run(f"[bench]\naxis = 'rack_pinion'\n[experiment]\ntype = 'stepped_loading'\n{extra}\n")


def recording_file(write: Callable[[Path], None], command: str = "analyze",
                   name: str = "bad.h5") -> Callable[[Path], list[str]]:
    def make(d: Path) -> list[str]:
        write(d / name)
        return [command, str(d / name), "--dir", str(d)]
    return make


def empty(path: Path) -> None:
    path.write_bytes(b"")


def truncated(path: Path) -> None:
    data = (path.parent / GOOD).read_bytes()
    path.write_bytes(data[: len(data) // 3])


def foreign(path: Path) -> None:
    with h5py.File(path, "w") as f:
        f["x"] = np.arange(3.0)


def text_file(path: Path) -> None:
    path.write_text("t,x\n0,1\n")


def family(experiment: str, steps: Callable[[], list], **config) -> Callable[[Path], None]:
    return lambda path: record(path, experiment, steps(), config={"type": experiment, **config})


def hammer_never_fired(path: Path) -> None:
    """An impact-hammer recording with its DAQ stream but no hit (no excite segment)."""
    record_with_daq(path, {"type": "impact_hammer"},
                    [daq_step("settle", "settle", {}, np.zeros((50 * PER_CYCLE, 2)))],
                    (FORCE_CHANNEL, RESPONSE_CHANNEL))


def nan_force() -> list:
    """A friction sweep whose drive force reads NaN for one sample of a measure window."""
    steps = friction_steps()
    steps[1][3][7, COLUMN["force"]] = np.nan
    return steps


def cycle_back(path: Path) -> None:
    """The good recording with its bus cycle counter stepping back at row 100."""
    shutil.copy(path.parent / GOOD, path)
    with h5py.File(path, "r+") as f:
        f["cycle"][100] = 3


def cases_file(d: Path) -> list[str]:
    """A closure cases file whose world names an effect nobody knows."""
    (d / "cases.toml").write_text(f"[[case]]\nname = 'x'\nmodel = '{model(d)}'\n"
                                  "effects = { ripplez = { amplitude_N = 5.0 } }\n")
    return ["closure", "--cases", str(d / "cases.toml")]


def no_drive_channels(path: Path) -> None:
    """A friction-sweep recording with one named drive's velocity and force, but not its
    statusword: neither a single drive's channels nor an axis of several."""
    units = {"master.velocity": "m/s", "master.force": "N"}
    metadata = {"experiment": "friction_sweep", "cycle_s": 1e-3,
                "config": {"experiment": {"type": "friction_sweep"}}}
    with Recorder(path, tuple(units), units, metadata) as recorder:
        recorder.append_block(np.arange(1, 101), np.zeros((100, 2)))


def three_feeds() -> list:
    return friction_steps()[: 3 * STEPS_PER_FEED]


def trace(d: Path, n: int = 400, edit: Callable[[dict], None] | None = None) -> Path:
    """A small closure trace (CSV + sidecar) whose columns `edit` may spoil."""
    t = np.arange(1, n + 1) * 1e-3
    x = 0.01 * np.sin(2 * np.pi * 2 * t)
    path = d / "trace.csv"
    write_csv_trace(path, Trace(t, x, 100 * np.cos(2 * np.pi * 2 * t), x), {})
    if edit:
        columns = dict(zip(["t_s", "x_mm", "F_N", "x_ref_mm"],
                           np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2).T))
        edit(columns)
        np.savetxt(path, np.column_stack(list(columns.values())), delimiter=",",
                   header=",".join(columns), comments="")
    return path


def model(d: Path, text: str = "[model]\nname = 'm'\n[terms.inertia]\nM_kg = 'free'\n") -> str:
    path = d / "model.toml"
    path.write_text(text)
    return str(path)


def closure(edit_csv: Callable[[Path], None] | None = None,
            edit_columns: Callable[[dict], None] | None = None,
            model_text: str | None = None, extra: tuple[str, ...] = ()
            ) -> Callable[[Path], list[str]]:
    def make(d: Path) -> list[str]:
        path = trace(d, edit=edit_columns)
        if edit_csv:
            edit_csv(path)
        m = model(d) if model_text is None else model(d, model_text)
        return ["closure", str(path), "--model", m, *extra]
    return make


def sidecar(old: str, new: str) -> Callable[[Path], None]:
    def edit(path: Path) -> None:
        side = path.with_suffix(".toml")
        side.write_text(side.read_text().replace(old, new))
    return edit


def csv_text(change: Callable[[str], str]) -> Callable[[Path], None]:
    return lambda path: path.write_text(change(path.read_text()))


def set_sample(column: str, index: int, value: float) -> Callable[[dict], None]:
    def edit(columns: dict) -> None:
        columns[column][index] = value
    return edit


def catalog_directory(command: list[str]) -> Callable[[Path], list[str]]:
    """A catalog.sqlite that is a directory (a corrupt file is moved aside and rebuilt:
    `test_catalog_truth.py`)."""
    def make(d: Path) -> list[str]:
        bad = d / "other"
        (bad / "catalog.sqlite").mkdir(parents=True)
        return [*command, "--dir", str(bad)]
    return make


def sim(text: str) -> Callable[[Path], list[str]]:
    return lambda d: ["sim", config(d, text, "sim.toml")]


CASES: dict[str, tuple[Callable[[Path], list[str]], str]] = {
    # recordings given to analyze, report, live, closure
    "analyze empty h5": (recording_file(empty), "bad.h5: not a readable HDF5 file"),
    "analyze truncated h5": (recording_file(truncated), "bad.h5: not a readable HDF5 file"),
    "analyze foreign h5": (recording_file(foreign), "bad.h5: not a feedbench recording"),
    "analyze text as h5": (recording_file(text_file), "bad.h5: not a readable HDF5 file"),
    "analyze missing h5": (lambda d: ["analyze", str(d / "gone.h5")], "gone.h5: no such recording"),
    "analyze unknown family": (recording_file(family("dance", friction_steps)),
                               "bad.h5: no analysis for experiment 'dance'"),
    "analyze another family's data": (recording_file(family("chirp", friction_steps)),
                                      "bad.h5: 0 excite segment(s) recorded"),
    "analyze hammer run of friction data": (recording_file(family("impact_hammer",
                                                                   friction_steps)),
                                            "bad.h5: impact_hammer analysis: no 'daq' recorded"),
    "analyze hammer that never fired": (recording_file(hammer_never_fired),
                                        "bad.h5: no usable hammer hit recorded"),
    "analyze friction with a NaN force": (recording_file(family("friction_sweep", nan_force)),
                                          "bad.h5: force: NaN or inf samples in the measure "
                                          "window 'measure'"),
    "report into a directory": (lambda d: ["report", str(d / GOOD), "-o", str(d)],
                                "runs is a directory"),
    "analyze cycle counter stepping back": (recording_file(cycle_back),
                                            "bad.h5: not a feedbench recording (/cycle not "
                                            "increasing: row 100 has cycle 3 after"),
    "closure case with an unknown effect": (cases_file, "world.effects.ripplez: unknown effect"),
    "analyze friction with 3 feeds": (recording_file(family("friction_sweep", three_feeds,
                                                            feeds_mm_min=FEEDS[:3])),
                                      "bad.h5: 3 feeds measured in the positive direction"),
    "analyze unknown run id": (lambda d: ["analyze", "nosuchrun", "--dir", str(d)],
                               "no run id starts with 'nosuchrun'"),
    "analyze catalog is a directory": (catalog_directory(["analyze", "someid"]),
                                       "catalog.sqlite: cannot use the run catalog (unable to "
                                       "open database file)"),
    "runs catalog is a directory": (catalog_directory(["runs"]),
                                    "catalog.sqlite: cannot use the run catalog (unable to "
                                    "open database file)"),
    "runs dir is a file": (lambda d: ["runs", "--dir", str(d / GOOD)],
                           f"/{GOOD} is not a directory"),
    "report foreign h5": (recording_file(foreign, "report"), "bad.h5: not a feedbench recording"),
    "report empty h5": (recording_file(empty, "report"), "bad.h5: not a readable HDF5 file"),
    "live truncated h5": (recording_file(truncated, "live"), "bad.h5: not a readable HDF5 file"),
    "closure foreign h5": (lambda d: (foreign(d / "x.h5"), ["closure", str(d / "x.h5"),
                                                           "--model", model(d)])[1],
                           "x.h5: not a feedbench recording"),
    "closure recording without position": (lambda d: (no_drive_channels(d / "x.h5"),
                                                      ["closure", str(d / "x.h5"), "--model",
                                                       model(d)])[1],
                                           "x.h5: no 'position' channel"),
    "analyze friction without drive channels": (recording_file(no_drive_channels),
                                                "bad.h5: friction_sweep analysis: no drive "
                                                "channels recorded"),
    "closure text as mat": (lambda d: ((d / "x.mat").write_text("no"),
                                       ["closure", str(d / "x.mat")])[1], "x.mat: "),
    "closure unknown format": (lambda d: ["closure", str(trace(d).with_suffix(".toml"))],
                               "trace.toml: unknown trace format"),
    # run configs: TOML, keys, types, units, ranges, what the analysis needs
    "toml syntax error": (run("[experiment\ntype = 'chirp'\n"), "bad.toml: not valid TOML"),
    "config file missing": (lambda d: ["run", str(d / "none.toml")],
                            "none.toml: no such config file"),
    "experiment table missing": (run("[limits]\n"), "config.experiment: required"),
    "unknown family": (run("[experiment]\ntype = 'dance'\n"), "experiment.type: must be one of"),
    "unknown key": (friction("feeds = [100]"), "experiment.feeds: unknown key"),
    "wrong unit suffix": (friction("settle_ms = 400"), "experiment.settle_ms: unknown key"),
    "unit in the value": (friction("settle_s = '0.4 s'"), "experiment.settle_s: must be a number"),
    "nan in config": (friction("settle_s = nan"), "experiment.settle_s: must be finite"),
    "inf in config": (friction("measure_s = inf"), "experiment.measure_s: must be finite"),
    "friction 3 feeds": (friction("feeds_mm_min = [100, 500, 1000]"),
                         "experiment.feeds_mm_min: the Andersson fit (Eq. 5.2) needs at least 5"),
    "friction repeated feeds": (friction("feeds_mm_min = [100, 100, 100, 100, 200]"),
                                "experiment.feeds_mm_min: the Andersson fit"),
    "friction one direction": (friction("directions = ['positive']"),
                               "experiment.directions: the analysis fits Eq. (5.2) per direction"),
    "unknown direction": (friction("directions = ['up', 'down']"),
                          "experiment.directions: must be one of positive, negative"),
    "chirp above nyquist": (run("[experiment]\ntype = 'chirp'\nf_stop_Hz = 600.0\n"),
                            "experiment.f_stop_Hz: must be below the bus Nyquist"),
    "chirp band reversed": (run("[experiment]\ntype = 'chirp'\nf_start_Hz = 300.0\n"),
                            "experiment.f_start_Hz: must be below f_stop_Hz"),
    "sine stream above quarter rate": (
        run("[experiment]\ntype = 'sine_stream'\nf_stop_Hz = 300.0\n"),
        "experiment.f_stop_Hz: must be below 250 Hz"),
    "stepped loading 2 levels": (stepped("step_um = 150.0"),
                                 "experiment.step_um: depth_um / step_um gives 2 load level(s)"),
    "stepped loading 1 single level": (
        stepped("single_step_um = 500.0"),
        "experiment.single_step_um: single_depth_um / single_step_um gives 1 load level(s)"),
    "stepped loading on the lab axis": (run("[experiment]\ntype = 'stepped_loading'\n"),
                                        "bench.axis: experiment stepped_loading needs axis"),
    "negative gain": (run("[bench.gains]\nK_p_Ns_m = -5.0\n[experiment]\ntype = 'chirp'\n"),
                      "bench.gains.K_p_Ns_m: must be > 0"),
    "unknown gain": (run("[bench.gains]\nKp = 5.0\n[experiment]\ntype = 'chirp'\n"),
                     "bench.gains.Kp: unknown key"),
    "zero cycle": (run("[bench]\ncycle_ms = 0.0\n[experiment]\ntype = 'chirp'\n"),
                   "bench.cycle_ms: must be > 0"),
    "limits reversed": (run("[limits]\nposition_mm = [100.0, -100.0]\n"
                            "[experiment]\ntype = 'chirp'\n"), "limits.position_mm: must be"),
    "excitation above force limit": (
        run("[limits]\nforce_N = 500.0\nexcitation_N = 5000.0\n"
            "[experiment]\ntype = 'chirp'\namplitude_N = 800.0\n"),
        "experiment.amplitude_N: 800 N exceeds the force limit limits.force_N"),
    "unknown CAN interface": (run("[bench]\ninterface = 'nosuchbus'\n[experiment]\n"
                                  "type = 'chirp'\n"), "bench.interface: Unknown interface type"),
    "no drive on the bus": (lambda d: ["run", config(d, f"[bench]\noutput_dir = '{d}'\n"
                                                     "simulated = false\nchannel = "
                                                     f"'fb-nodrive-{d.parent.name}'\n"
                                                     "[experiment]\ntype = 'chirp'\n")],
                            "bench.node_id: no drive answers as node 1"),
    "bode below the mobility band": (
        run("[experiment]\ntype = 'closed_loop_bode'\nf_start_Hz = 5.0\nf_stop_Hz = 19.0\n"),
        "experiment.f_start_Hz: the open-loop mobility (Eq. 4.20) is read in 20–150 Hz"),
    "hammer record too short": (run("[experiment]\ntype = 'impact_hammer'\nrecord_s = 0.01\n"
                                    "pretrigger_s = 0.005\n"),
                                "experiment.record_s: 0.01 s gives 1 frequency lines"),
    "smfe one cut": (run("[experiment]\ntype = 'smfe'\ncuts = ['down']\n"), "experiment.cuts: "),
    # closure traces: CSV, sidecar, units, samples, model config
    "csv missing column": (closure(sidecar('reference = "x_ref_mm"', 'reference = "x_cmd_mm"')),
                           "sidecar.columns.reference: no column 'x_cmd_mm' in trace.csv"),
    "csv misnamed header": (closure(csv_text(lambda s: s.replace("F_N", "force", 1))),
                            "sidecar.columns.force: no column 'F_N' in trace.csv"),
    "sidecar missing": (closure(lambda p: p.with_suffix(".toml").unlink()),
                        "trace.toml: no such config file"),
    "csv missing": (closure(lambda p: p.unlink()), "trace.csv: no such file"),
    "sidecar key misspelled": (closure(sidecar("[columns]", "[colums]")),
                               "sidecar.colums: unknown key"),
    "sidecar column key misspelled": (closure(sidecar("position =", "postion =")),
                                      "sidecar.columns.postion: unknown key"),
    "wrong unit": (closure(sidecar('position = "mm"', 'position = "inch"')),
                   "sidecar.units.position: unknown unit 'inch'"),
    "nan sample": (closure(edit_columns=set_sample("F_N", 7, np.nan)),
                   "trace.csv: force: contains NaN or inf"),
    "inf sample": (closure(edit_columns=set_sample("x_mm", 9, np.inf)),
                   "trace.csv: position: contains NaN or inf"),
    "time not monotonic": (closure(edit_columns=set_sample("t_s", 50, 0.01)),
                           "trace.csv: time: samples must be uniformly spaced and increasing"),
    "empty csv": (closure(csv_text(lambda s: "")), "trace.csv: no data rows"),
    "header only csv": (closure(csv_text(lambda s: s.splitlines()[0] + "\n")),
                        "trace.csv: no data rows"),
    "truncated csv": (closure(csv_text(lambda s: s[: len(s) // 2].rsplit(",", 1)[0])),
                      "trace.csv: row 206 has 3 values, the header 4 names"),
    "text in csv": (closure(csv_text(lambda s: s.replace("\n0.01,", "\nten,", 1))),
                    "trace.csv: row 11: 'ten' is not a number"),
    "unknown effect name": (closure(model_text="[model]\nname = 'm'\n[terms.inertia]\n"
                                    "M_kg = 'free'\n[terms.ripplez]\n"),
                            "terms.ripplez: unknown term"),
    "model toml syntax": (closure(model_text="[model\n"), "model.toml: not valid TOML"),
    "model missing": (lambda d: ["closure", str(trace(d))], "--model: required"),
    "holdout out of range": (closure(extra=("--holdout", "1.5")), "holdout"),
    # sim, demo and the command line itself
    "sim toml syntax": (sim("[bench\n"), "sim.toml: not valid TOML"),
    "sim unknown bench key": (sim("[bench]\nnode = 3\n"), "bench.node: unknown key"),
    "demo dir is a file": (lambda d: ["demo", "--quick", "--dir", str(d / GOOD)], GOOD),
    "export a run without FRF": (lambda d: ["export", str(d / GOOD), "--uff58", str(d / "x.uff")],
                                 "good.h5: a friction_sweep run has no FRF to export"),
    "export into a file's folder": (lambda d: ["export", str(d / GOOD), "--csv",
                                               str(d / GOOD / "x.csv")],
                                   "good.h5 is a file, not a folder"),
    "unknown option": (lambda d: ["analyze", "x", "--jsn"], "unrecognized arguments: --jsn"),
    "live span zero": (lambda d: ["live", str(d / GOOD), "--span", "0"],
                       "feedbench live: error: argument --span: must be > 0 (got 0)"),
    "live speed nan": (lambda d: ["live", str(d / GOOD), "--speed", "nan"],
                       "argument --speed: must be a finite number (got nan)"),
    "live speed text": (lambda d: ["live", str(d / GOOD), "--speed", "fast"],
                        "argument --speed: invalid finite value: 'fast'"),
}


def snapshot(directory: Path) -> tuple[bytes, list]:
    """The good recording's bytes and the catalog's rows (files relative to `directory`:
    the catalog resolves them against itself)."""
    return ((directory / GOOD).read_bytes(),
            [{**vars(r), "file": Path(r.file).relative_to(directory)}
             for r in Catalog(directory / "catalog.sqlite").list()])


def written(directory: Path) -> set[Path]:
    """Every file under `directory` but the catalog's SQLite journal."""
    return {p for p in directory.rglob("*") if "-wal" not in p.name and "-shm" not in p.name}


class LogLines(logging.Handler):
    """The log records the console script would print on stderr (warnings and errors)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(f"log: {record.name}: {record.getMessage()}")


def run_main(argv: list[str], capsys) -> tuple[int, list[str]]:
    """`feedbench ARGV` in-process: exit status and the lines on stderr, each warning and
    log record (which the command line would print) counted as a line."""
    log = LogLines()
    logging.getLogger().addHandler(log)
    try:
        with warnings.catch_warnings(record=True) as warned:
            warnings.simplefilter("always")
            try:
                status = main(argv)
            except SystemExit as exc:  # argparse
                status = exc.code
    finally:
        logging.getLogger().removeHandler(log)
    lines = capsys.readouterr().err.strip().splitlines()
    return status, [f"warning: {w.message}" for w in warned] + log.lines + lines


@pytest.mark.parametrize("case", list(CASES))
def test_bad_input_is_one_line_and_corrupts_nothing(case, runs, template, capsys, tmp_path,
                                                   monkeypatch):
    make, expected = CASES[case]
    argv = make(runs)
    files = written(runs)
    working = tmp_path / "cwd"
    working.mkdir()
    monkeypatch.chdir(working)
    status, lines = run_main(argv, capsys)
    assert list(working.iterdir()) == [], "nothing is written into the working directory"
    assert status == 2, lines
    assert len(lines) == 1, lines
    assert lines[0].startswith("feedbench") and ": error: " in lines[0], lines[0]
    assert expected in lines[0], lines[0]
    assert "Traceback" not in lines[0] and "--debug" not in lines[0], lines[0]
    assert snapshot(runs) == snapshot(template), "the recording and the catalog are untouched"
    assert written(runs) == files, "nothing new is written"


def test_the_command_line_prints_one_line_too(runs):
    """As the user of issue 12 saw it: the console script's whole stderr is the one line."""
    make, expected = CASES["analyze friction with 3 feeds"]
    proc = subprocess.run([sys.executable, "-m", "feedbench.commands.cli", *make(runs)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and expected in proc.stderr, proc.stderr


@pytest.mark.parametrize("key", ["socketcand", "devices.spindle.address"])
def test_port_in_use_names_the_field_and_address(key, runs, capsys):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        address = "127.0.0.1:{}".format(taken.getsockname()[1])
        status, lines = run_main(["sim", config(runs, f"[bench]\n{key} = '{address}'\n",
                                                "sim.toml")], capsys)
    assert (status, lines) == (2, [f"feedbench: error: bench.{key}: cannot listen on "
                                   f"{address} (Address already in use)"])


def test_debug_shows_the_traceback(runs):
    (runs / "bad.h5").write_bytes(b"")
    with pytest.raises(Exception, match="not a readable HDF5 file"):
        main(["--debug", "analyze", str(runs / "bad.h5")])
    with pytest.raises(Exception, match="not a readable HDF5 file"):
        main(["analyze", str(runs / "bad.h5"), "--debug"])


def test_an_unexpected_error_is_one_line_naming_its_type(runs, capsys, monkeypatch):
    """The last resort: any other exception is one line with its type and the hint."""
    import feedbench.commands.cli

    def broken(args):
        raise ZeroDivisionError("float division by zero")

    monkeypatch.setattr(feedbench.commands.cli, "cmd_runs", broken)
    status, lines = run_main(["runs", "--dir", str(runs)], capsys)
    assert (status, lines) == (2, ["feedbench: error: ZeroDivisionError: float division by "
                                   "zero (run with --debug for the traceback)"])


def test_ctrl_c_outside_a_run_is_one_line_and_status_130(capsys, monkeypatch):
    """Ctrl-C (a real SIGINT to this process) as the closure's first simulated case starts:
    deterministic, whatever numba's cache holds."""
    import feedbench.commands.closure as command

    first_case = command.run_case

    def interrupted(case):
        os.kill(os.getpid(), signal.SIGINT)
        return first_case(case)

    monkeypatch.setattr(command, "run_case", interrupted)
    assert run_main(["closure", "--cases"], capsys) == (130, ["feedbench: error: interrupted"])


CTRL_C_WHILE_IMPORTING = """
import builtins, os, signal, sys
signal.signal(signal.SIGINT, signal.default_int_handler)  # Python's own, as in a terminal
from feedbench.commands.console import run

real_import = builtins.__import__


def import_then_ctrl_c(name, *args, **kwargs):
    if name == "feedbench.commands.cli":
        os.kill(os.getpid(), signal.SIGINT)
    return real_import(name, *args, **kwargs)


builtins.__import__ = import_then_ctrl_c if sys.argv[1] == "importing" else real_import
sys.argv[1:] = ["runs", "--dir", sys.argv[2]]
status = run()
os.kill(os.getpid(), signal.SIGINT)  # while the interpreter exits
sys.exit(status)
"""


@pytest.mark.parametrize("moment, status", [("importing", 130), ("exiting", 0)])
def test_ctrl_c_before_and_after_the_command_is_one_line_or_none(tmp_path, moment, status):
    """The console script (`feedbench.commands.console.run`): a real SIGINT while Python imports the
    command's modules ends with one line and status 130; one after the command, while the
    interpreter exits, changes nothing (no 'Exception ignored', no traceback). The child
    starts with Python's SIGINT handler, as from a terminal: a suite started as a background
    job of a shell without job control inherits SIGINT ignored, and so did the child (it
    then ran to the end, status 0; twice on 30 Nov)."""
    done = subprocess.run([sys.executable, "-c", CTRL_C_WHILE_IMPORTING, moment, str(tmp_path)],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == status
    assert done.stderr.splitlines() == (["feedbench: error: interrupted"] if status else [])
