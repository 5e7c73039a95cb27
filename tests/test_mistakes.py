"""Plausible user mistakes of a test engineer's first week (issue 25): each is refused before
anything moves with one line naming the field, or its result is marked not valid with the
reason, in the terminal (`feedbench analyze`'s text), in ``--json`` and in the report. None
reports "all checks passed".

The mistakes in the data are recorded arrays (the report tests' recordings of known
structures, with the mistake put in) analysed as `feedbench analyze` does; one runs on the
simulated bench (a chirp too weak to move the axis out of its stiction band).
"""

from __future__ import annotations

import json
from typing import Callable

import numpy as np
import pytest

from feedbench.bench import analyze_file, parse_run_config, run_config
from feedbench.commands.cli import main
from feedbench.config import ConfigError
from feedbench.daq.recording import open_recording, printable_json
from feedbench.commands.demo import describe_analysis, example_config
from feedbench.experiments.smfe import DAQ_CHANNELS as SMFE_CHANNELS
from feedbench.report import run_section, verdict
from feedbench.units import MM_PER_MIN
from feedbench.testing import live_replay, synthetic_recording
from test_report import (
    COLUMN, DAQ_RATE, K_P, PER_CYCLE, T_I, bode_steps, chirp_steps, friction_steps,
    hammer_steps, record, record_with_daq, shaker_chirp_steps, sine_stream_steps, smfe_steps,
)

pytestmark = [pytest.mark.filterwarnings("ignore:Data has no positive values:UserWarning"),
              pytest.mark.filterwarnings("ignore:All-NaN axis encountered:RuntimeWarning")]
"""An unplugged accelerometer's compliance is all zero: its report plot has nothing to draw
on a log axis (matplotlib says so)."""

FRICTION_FEEDS_M_MIN = [0.025, 0.05, 0.075, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.7, 0.9, 1.2, 1.5]
"""The friction sweep's default feeds typed in m/min (issue 25)."""

# -- refused before anything moves --------------------------------------------------------

REFUSED = {
    "chirp feed typed in m/min": (
        "chirp", {"experiment": {"feed_mm_min": 0.5}},
        "experiment.feed_mm_min = 0.5 is below the measurable 2.4 mm/min",
        "typed in m/min? 0.5 m/min = 500 mm/min; in mm/s? 0.5 mm/s = 30 mm/min"),
    "friction feeds typed in mm/s": (
        "friction_sweep", {"experiment": {"feeds_mm_min": [0.5, 1.0, 2.0, 5.0, 10.0, 25.0]}},
        "experiment.feeds_mm_min[0] = 0.5 is below the measurable",
        "in mm/s? 0.5 mm/s = 30 mm/min"),
    "friction feeds typed in m/min": (
        "friction_sweep", {"experiment": {"feeds_mm_min": FRICTION_FEEDS_M_MIN}},
        "experiment.feeds_mm_min[0] = 0.025 is below the measurable 2.4 mm/min",
        "typed in m/min? 0.025 m/min = 25 mm/min"),
    "hammer feeds typed in m/min": (
        "impact_hammer", {"experiment": {"feeds_mm_min": [0.0, 0.025, 0.5, 1.0]}},
        "experiment.feeds_mm_min[1] = 0.025 is below the measurable", "= 25 mm/min"),
    "sine-stream feeds typed in m/min": (
        "sine_stream", {"experiment": {"feeds_mm_min": [0.0, 0.1, 1.0]}},
        "experiment.feeds_mm_min[1] = 0.1 is below the measurable", "= 100 mm/min"),
    "shaker chirp feeds typed in m/min": (
        "shaker_chirp", {"experiment": {"feeds_mm_min": [0.0, 0.5, 1.0]}},
        "experiment.feeds_mm_min[1] = 0.5 is below the measurable", "= 500 mm/min"),
    "closed-loop Bode feed typed in m/min": (
        "closed_loop_bode", {"experiment": {"feed_mm_min": 0.5}},
        "experiment.feed_mm_min = 0.5 is below the measurable", "= 500 mm/min"),
    "bus cycle typed in s": (
        "chirp", {"bench": {"cycle_ms": 0.001}},
        "bench.cycle_ms = 0.001 is outside the 0.125–10 ms", "typed in s? 0.001 s = 1 ms"),
    "bus cycle typed in µs": (
        "friction_sweep", {"bench": {"cycle_ms": 1000.0}},
        "bench.cycle_ms = 1000 is outside the 0.125–10 ms", "typed in µs? 1000 µs = 1 ms"),
    "velocity chirp amplitude reaches the feed (sticks every period)": (
        "chirp", {"experiment": {"inject": "velocity", "amplitude_mm_min": 600.0}},
        "experiment.amplitude_mm_min = 600 reaches the feed 500 mm/min", "reverse and stick"),
    "Bode excitation reaches the feed (sticks every period)": (
        "closed_loop_bode", {"experiment": {"amplitude_mm_min": 500.0}},
        "experiment.amplitude_mm_min = 500 reaches the feed 500 mm/min", "keep it below"),
    "chirp record too short for its lowest frequency": (
        "chirp", {"experiment": {"duration_s": 0.2, "tail_s": 0.1}},
        "experiment.duration_s = 0.2: a 0.3 s record holds 3 periods of f_start_Hz = 10 Hz",
        "it needs 5"),
    "hammer record too short for the band": (
        "impact_hammer", {"experiment": {"record_s": 0.01, "pretrigger_s": 0.001}},
        "experiment.record_s: 0.01 s gives 1 frequency lines", "needs at least 3"),
    "chirp stop frequency above Nyquist": (
        "chirp", {"experiment": {"f_stop_Hz": 600.0}},
        "experiment.f_stop_Hz: must be below the bus Nyquist frequency 500 Hz", "(got 600)"),
    "mobility band edges swapped": (
        "chirp", {"experiment": {"band_low_Hz": 150.0, "band_high_Hz": 20.0}},
        "experiment.band_low_Hz: must be below band_high_Hz", "(20 Hz)"),
    "chirp amplitude typed in mN": (
        "chirp", {"experiment": {"amplitude_N": 20_000.0}},
        "experiment.amplitude_N: 20000 N exceeds the force limit", "limits.force_N"),
}


def mistaken(example: str, updates: dict[str, dict]) -> dict:
    """The packaged example config `example` with the mistaken values of `updates`."""
    raw = example_config(example)
    for table, values in updates.items():
        raw[table].update(values)
    return raw


@pytest.mark.parametrize("mistake", sorted(REFUSED))
def test_refused_before_anything_moves_with_one_line_naming_the_field(mistake):
    example, updates, start, fragment = REFUSED[mistake]
    with pytest.raises(ConfigError) as error:
        parse_run_config(mistaken(example, updates))
    line = str(error.value)
    assert line.startswith(start) and fragment in line and "\n" not in line, line


def test_the_friction_sweep_in_m_min_is_refused_by_feedbench_run(tmp_path, capsys):
    """`feedbench run` on the issue's sweep (feeds 0.025–1.5 typed in m/min): one error line
    naming the field and the unit, exit status 2, no recording, no catalog."""
    raw = mistaken("friction_sweep", {"experiment": {"feeds_mm_min": FRICTION_FEEDS_M_MIN},
                                      "bench": {"output_dir": str(tmp_path / "runs")}})
    path = tmp_path / "sweep.toml"
    path.write_text(toml_text(raw), encoding="utf-8")
    assert main(["run", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "experiment.feeds_mm_min[0] = 0.025" in err
    assert "typed in m/min? 0.025 m/min = 25 mm/min" in err
    assert not (tmp_path / "runs").exists()


def test_a_bus_cycle_the_simulated_drive_cannot_run_is_refused_before_anything_moves(
        tmp_path, can_channel):
    """0.5 ms is a cycle a drive may run, not the simulated one (a 1 ms position loop): the
    bench refuses it while it starts, naming the field, before a recording exists."""
    raw = mistaken("chirp", {"bench": {"cycle_ms": 0.5, "output_dir": str(tmp_path),
                                       "channel": can_channel}})
    with pytest.raises(ConfigError, match=r"^bench\.cycle_ms = 0\.5 is not a whole number of "
                                          r"the simulated position loop's 1 ms periods"):
        run_config(parse_run_config(raw), progress=False)
    assert not list(tmp_path.glob("*.h5"))


def toml_text(raw: dict) -> str:
    """A config dict of tables of numbers, strings, booleans and lists as TOML."""
    def value(v) -> str:
        return json.dumps(v) if not isinstance(v, bool) else str(v).lower()

    return "".join(f"[{table}]\n" + "".join(f"{k} = {value(v)}\n" for k, v in keys.items())
                   for table, keys in raw.items() if isinstance(keys, dict)
                   and not any(isinstance(v, dict) for v in keys.values()))


# -- not valid, with the reason -----------------------------------------------------------

def with_column(steps, column: str, change: Callable[[np.ndarray], np.ndarray],
                kinds=("excite",), which=None):
    """Rows `steps` with `change` applied to `column` in the steps of `kinds` (`which`: only
    those step indices)."""
    out = []
    for i, (label, kind, info, rows) in enumerate(steps):
        if kind in kinds and (which is None or i in which):
            rows = rows.copy()
            rows[:, COLUMN[column]] = change(rows[:, COLUMN[column]])
        out.append((label, kind, info, rows))
    return out


def with_daq(steps, channel: int, change: Callable[[np.ndarray], np.ndarray], which=None):
    """DAQ steps with `change` applied to DAQ `channel` (0 force, 1 acceleration) of the
    excite steps (`which`: only those step indices)."""
    out = []
    for i, (label, kind, info, rows, daq) in enumerate(steps):
        if kind == "excite" and (which is None or i in which):
            daq = daq.copy()
            daq[:, channel] = change(daq[:, channel])
        out.append((label, kind, info, rows, daq))
    return out


def noise(scale: float, seed: int = 7) -> Callable[[np.ndarray], np.ndarray]:
    rng = np.random.default_rng(seed)
    return lambda x: scale * rng.normal(size=x.size)


def double_hit(force: np.ndarray) -> np.ndarray:
    """The hammer bounces: a second 10 N pulse 20 ms after the first."""
    out = force.copy()
    out[700:711] += 10.0 * np.sin(np.pi * np.arange(11) / 10)
    return out


def chirp_run(steps, **config) -> Callable:
    return lambda path: record(path, "chirp", steps, config={"type": "chirp", **config})


def daq_run(experiment: dict, steps, channels: tuple[str, ...]) -> Callable:
    return lambda path: record_with_daq(path, experiment, steps, channels)


HAMMER = ({"type": "impact_hammer"}, ("hammer_force", "acc_tool_x"))
SINES = ({"type": "sine_stream", "amplitudes_N": [20.0]}, ("actuator_force", "acc_tool_x"))
SHAKER = ({"type": "shaker_chirp", "f_start_Hz": 20.0, "f_stop_Hz": 100.0},
          ("shaker_force", "acc_tool_x"))
BODE = {"type": "closed_loop_bode", "f_start_Hz": 20.0, "f_stop_Hz": 120.0}


def bode_run(steps) -> Callable:
    return lambda path: record(path, "closed_loop_bode", steps, config=BODE,
                               metadata={"drive_gains": {"K_p": K_P, "T_i": T_I}})


STOPPED = "stopped by the operator (Ctrl-C)"
SMFE = ({"type": "smfe", "segment_s": 2.0, "ramp_s": 12.0}, SMFE_CHANNELS)
SMFE_STEPS = smfe_steps()


def aborted_daq_run(family: tuple[dict, tuple[str, ...]], steps) -> Callable:
    """A DAQ recording of `steps` whose run was stopped (Ctrl-C) after the last of them."""
    experiment, channels = family
    return lambda path: synthetic_recording(path, experiment, steps, daq_channels=channels,
                                            daq_rate_hz=DAQ_RATE, status="aborted",
                                            reason=STOPPED)


def cut_short(step, share: float):
    """A DAQ step stopped after `share` of its cycles (the stop came inside it)."""
    label, kind, info, rows, daq = step
    n = max(1, int(len(rows) * share))
    return label, kind, info, rows[:n], daq[:n * PER_CYCLE]


def feed_moves(x: np.ndarray) -> np.ndarray:
    """The chirp's velocity with its 500 mm/min feed taken out: the axis stood still."""
    return x - 500 * MM_PER_MIN


NOT_VALID = {
    "chirp: velocity channel unplugged": (
        chirp_run(with_column(chirp_steps(), "velocity", np.zeros_like)),
        "motor velocity reached", "constant: channel unplugged"),
    "chirp: force channel unplugged": (
        chirp_run(with_column(chirp_steps(), "force", np.zeros_like)),
        "motor force reached", "constant: channel unplugged"),
    "chirp: feed too low, the axis stays in its stiction band": (
        chirp_run(with_column(chirp_steps(), "velocity", noise(1e-6))),
        "motor velocity reached", "stuck in its stiction band"),
    "chirp: amplitude so large the axis reverses at the feed": (
        chirp_run(with_column(chirp_steps(), "velocity", lambda v: 10 * feed_moves(v)
                              + 500 * MM_PER_MIN)),
        "the axis slid", "the axis stuck or reversed in"),
    "chirp: direction sign flipped (feed negative, sweeps positive)": (
        chirp_run(chirp_steps(), direction="negative"),
        "the axis slid", "the axis stuck or reversed in 100.0 %"),
    "chirp: band starts above the anti-resonance": (
        chirp_run(chirp_steps(), band_low_Hz=65.0),
        "peaks inside the band", "f_t 65.06 Hz is the edge of 65.06–149.9 Hz"),
    "chirp: run aborted half-way": (
        lambda path: record(path, "chirp", chirp_steps()[:4], status="aborted",
                            reason="stopped by the operator (Ctrl-C)"),
        "status", "the run stopped before its plan ended"),
    "chirp: one sweep (its coherence is 1 whatever the response)": (
        chirp_run(chirp_steps()[:2]),
        "sweeps averaged", "the coherence of one record is 1 by construction"),
    "chirp: samples lost": (
        lambda path: record(path, "chirp", chirp_steps(), skip_after=2000),
        "missing samples (gaps)", "samples were lost"),
    "friction: force sign flipped": (
        lambda path: record(path, "friction_sweep", with_column(
            friction_steps(), "force", np.negative, ("measure",))),
        "motor force along the motion", "the force's sign is flipped"),
    "friction: force saturated at 60 N": (
        lambda path: record(path, "friction_sweep", with_column(
            friction_steps(), "force", lambda f: np.clip(f, -60.0, 60.0), ("measure",))),
        "R² of the positive fit", "Eq. (5.2) does not describe the positive points"),
    "friction: settle too short (windows still drifting)": (
        lambda path: record(path, "friction_sweep", with_column(
            friction_steps(), "force", lambda f: f * np.linspace(0.7, 1.0, f.size),
            ("measure",), {1})),
        "windows not at steady state (left out of the fit)", "raise settle_s"),
    "hammer: double hit": (
        daq_run(HAMMER[0], with_daq(hammer_steps(), 0, double_hit, {2}), HAMMER[1]),
        "hits left out", "0 mm/min: hit 1 at 0.050 s: double hit"),
    "hammer: force overload (hammer too hard)": (
        daq_run(HAMMER[0], with_daq(hammer_steps(), 0, lambda f: 250.0 * f, {6}), HAMMER[1]),
        "hits left out", "500 mm/min: hit 1 at 0.050 s: force overload"),
    "hammer: accelerometer unplugged": (
        daq_run(HAMMER[0], with_daq(hammer_steps(), 1, np.zeros_like), HAMMER[1]),
        "min coherence in the band", "a channel is constant (unplugged?)"),
    "sine-stream: accelerometer unplugged": (
        daq_run(SINES[0], with_daq(sine_stream_steps(), 1, np.zeros_like), SINES[1]),
        "steps flagged (quality gate)", "40 Hz (1000 mm/min, 20 N): R²"),
    "sine-stream: response saturated": (
        daq_run(SINES[0], with_daq(sine_stream_steps(), 1,
                                   lambda a: np.clip(a, -0.3 * abs(a).max(), 0.3 * abs(a).max()),
                                   {5, 6}), SINES[1]),
        "steps flagged (quality gate)", "45 Hz (1000 mm/min, 20 N): R²"),
    "sine-stream: force too small, response in the noise": (
        daq_run(SINES[0], with_daq(sine_stream_steps(), 1, noise(5.0), {3}), SINES[1]),
        "steps flagged (quality gate)", "43 Hz (1000 mm/min, 20 N): R²"),
    "shaker chirp: accelerometer unplugged": (
        daq_run(SHAKER[0], with_daq(shaker_chirp_steps(), 1, np.zeros_like), SHAKER[1]),
        "min coherence in the band", "a channel is constant (unplugged?)"),
    "shaker chirp: one sweep (its coherence is 1 whatever the response)": (
        daq_run(SHAKER[0], shaker_chirp_steps()[:1], SHAKER[1]),
        "sweeps averaged", "the coherence of one record is 1 by construction"),
    "hammer: one hit per feed (its coherence is 1 whatever the response)": (
        daq_run(HAMMER[0], hammer_steps()[:2] + hammer_steps()[4:6], HAMMER[1]),
        "hits averaged", "the coherence of one record is 1 by construction"),
    "shaker chirp: force channel swapped for noise": (
        daq_run(SHAKER[0], with_daq(shaker_chirp_steps(), 0, noise(20.0)), SHAKER[1]),
        "min coherence in the band", "below 0.9"),
    "hammer: run aborted inside a hit (mid-feed)": (
        aborted_daq_run(HAMMER, hammer_steps()[:6] + [cut_short(hammer_steps()[6], 0.5)]),
        "status", "the run stopped before its plan ended"),
    "hammer: run aborted inside a feed's first hit (none of it whole)": (
        aborted_daq_run(HAMMER, hammer_steps()[:5] + [cut_short(hammer_steps()[5], 0.5)]),
        "notes", "records were left out"),
    "hammer: run aborted before its first hit": (
        aborted_daq_run(HAMMER, hammer_steps()[:1]),
        "hits analysed", "no usable hits recorded (no excite segment)"),
    "shaker chirp: run aborted inside the second sweep": (
        aborted_daq_run(SHAKER, shaker_chirp_steps()[:1]
                        + [cut_short(shaker_chirp_steps()[1], 0.5)]),
        "notes", "records were left out"),
    "shaker chirp: run aborted early in its first sweep": (
        aborted_daq_run(SHAKER, [cut_short(shaker_chirp_steps()[0], 0.002)]),
        "sweeps analysed", "records of 0.005 s hold no frequency line in 20–100 Hz"),
    "sine stream: run aborted at the start of a step": (
        aborted_daq_run(SINES, sine_stream_steps()[:4] + [cut_short(sine_stream_steps()[4],
                                                                    0.002)]),
        "notes", "a step was left out: the FRF lacks its frequency"),
    "smfe: run aborted inside the last cut": (
        aborted_daq_run(SMFE, SMFE_STEPS[:5] + [cut_short(SMFE_STEPS[5], 0.5)]),
        "status", "the run stopped before its plan ended"),
    "smfe: run aborted inside the second cut": (
        aborted_daq_run(SMFE, SMFE_STEPS[:3] + [cut_short(SMFE_STEPS[3], 0.5)]),
        "cuts recorded", "the receptances (Eq. 6.13) need all 3 cuts"),
    "smfe: run aborted before its first cut": (
        aborted_daq_run(SMFE, SMFE_STEPS[:1]),
        "cuts recorded", "the receptances (Eq. 6.13) need all 3 cuts"),
    "closed-loop Bode: response in the noise at high frequencies": (
        bode_run(bode_steps()[:90] + with_column(bode_steps()[90:], "velocity", noise(1e-3))),
        "frequencies flagged", "110 Hz: R²"),
}


@pytest.fixture(scope="module")
def analysed(tmp_path_factory):
    """Each mistake's recording, written once: mistake → its path."""
    directory = tmp_path_factory.mktemp("mistakes")
    paths = {}
    for i, (mistake, (write, _, _)) in enumerate(sorted(NOT_VALID.items())):
        paths[mistake] = directory / f"mistake_{i}.h5"
        write(paths[mistake])
    return paths


def assert_not_valid_everywhere(path, name: str, fragment: str) -> None:
    """The result of `path` not valid because of check `name`, whose reason holds
    `fragment`: in the terminal text, the JSON and the report's quality rows and verdict."""
    result = analyze_file(path)
    failed = {c["name"]: c for c in result["checks"] if not c["ok"]}
    assert name in failed and fragment in failed[name]["reason"], result["checks"]
    text = describe_analysis(result)
    assert f"✘ {name}: " in text and fragment in text and "NOT VALID: " in text
    assert "checks passed" not in text and "np.float" not in text
    data = json.loads(printable_json(result))
    assert data["valid"] is False
    assert any(line.startswith(f"{name}: ") and fragment in line
               for line in data["not_valid_because"])
    section = run_section(open_recording(path))
    ok, summary = verdict(section)
    assert not ok and "all" not in summary and name in summary
    row = next(q for q in section.quality if q.name == name)
    assert row.ok is False and fragment in row.value


@pytest.mark.parametrize("mistake", sorted(NOT_VALID))
def test_result_marked_not_valid_with_its_reason_in_terminal_json_and_report(mistake, analysed):
    _, name, fragment = NOT_VALID[mistake]
    assert_not_valid_everywhere(analysed[mistake], name, fragment)


@pytest.mark.parametrize("mistake, cut", [
    ("hammer: run aborted inside a feed's first hit (none of it whole)",
     "hit 1: cut short by the stop (500 of 1000 cycles), left out"),
    ("shaker chirp: run aborted inside the second sweep",
     "sweep 2: cut short by the stop (1250 of 2500 cycles), left out"),
    ("sine stream: run aborted at the start of a step",
     "44 Hz: cut short by the stop after 1 cycle(s), left out")])
def test_a_record_cut_short_by_the_stop_is_left_out_and_named(mistake, cut, analysed):
    """The stop cuts the run's last record: it is not averaged with the whole ones (its
    frequency lines are not theirs), and the notes say which and why."""
    result = analyze_file(analysed[mistake])
    notes = next(c for c in result["checks"] if c["name"] == "notes")
    assert notes["value"] == cut and result["notes"] == [cut]


@pytest.mark.parametrize("mistake", ["hammer: double hit", "chirp: velocity channel unplugged"])
def test_the_live_view_says_not_valid_and_why(mistake, analysed):
    """Replayed as a run feeds the live window: the summary starts with the verdict and the
    failed check's reason, before the family's own summary."""
    _, name, fragment = NOT_VALID[mistake]
    summary = live_replay(analysed[mistake]).view().summary
    assert summary.startswith(f"NOT VALID: {name}: ") and fragment in summary.split(" | ")[0]
    assert len(summary.split(" | ")) == 2


def test_chirp_too_weak_to_break_stiction_on_the_simulated_bench(tmp_path, can_channel):
    """A 2 N chirp with the axis holding position: the motor velocity stays below the
    measurable 2.4 mm/min (the axis sits in its stiction band), so the servo mobility it
    prints is stiction's, not the structure's: not valid, said in every view."""
    raw = mistaken("chirp", {"experiment": {
        "repetitions": 1, "duration_s": 1.0, "tail_s": 0.3, "settle_s": 0.2, "f_start_Hz": 20.0,
        "f_stop_Hz": 150.0, "feed_mm_min": 0.0, "amplitude_N": 2.0}})
    raw["bench"].update(output_dir=str(tmp_path), channel=can_channel)
    row = run_config(parse_run_config(raw), progress=False)
    assert row["status"] == "complete", row["reason"]
    assert_not_valid_everywhere(row["file"], "motor velocity reached",
                                "the axis did not move under the excitation")
