"""Recordings other DAQ systems wrote (issue 28 item 4): MDF4 and TDMS files written by asammdf
and npTDMS from a simulated run read back bit-exact, imported as catalogued runs that analyse
as the original does; rates met on one time base; gaps and bad mappings refused in one line;
two public files from real measurements (tests/data/asap2-canape, tests/data/nptdms-daqmx-raw)
analysed and judged; the closure on an imported MDF4 recording."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from feedbench.bench import analyze_file
from feedbench.commands.cli import main
from feedbench.closure_io import read_csv_trace, read_recording
from feedbench.config import ConfigError
from feedbench.daq.importers import formats, read_foreign
from feedbench.daq.importers.mapping import load_run
from feedbench.daq.recording import open_recording
from feedbench.engine.plan import segment_event
from feedbench.report import trace_panels
from test_report import DAQ_RATE, chirp_steps, hammer_steps, record, record_with_daq

DATA = Path(__file__).parent / "data"
PUBLIC_MDF4 = DATA / "asap2-canape" / "ASAP2_Demo_V171_slice.mf4"
PUBLIC_TDMS = DATA / "nptdms-daqmx-raw" / "raw1.tdms"
EXAMPLES = Path(__file__).parents[1] / "feedbench" / "examples" / "closure"
MAPPED = {"position": "position", "velocity": "velocity", "force": "force",
          "reference": "x_ref", "excitation": "force_offset"}
"""Mapping channel → the recording's channel, for the simulated chirp's export."""
UNITS = {"position": "m", "velocity": "m/s", "force": "N", "x_ref": "m", "force_offset": "N"}


@pytest.fixture(scope="module")
def chirp_run(tmp_path_factory) -> Path:
    """A simulated chirp run (the two-mass servo mobility, three sweeps) as the runner
    records it."""
    path = tmp_path_factory.mktemp("import") / "chirp.h5"
    record(path, "chirp", chirp_steps())
    return path


def segment_tables(recording) -> list[str]:
    """The run's segments as a mapping's [[segments]] TOML (start and stop in s from the
    first sample)."""
    cycle_s, first = recording.metadata["cycle_s"], int(recording.cycle[0])
    lines = []
    for seg in recording.segments():
        label, kind, info, _ = segment_event(seg.label)
        lines += ["[[segments]]", f'label = "{label}"', f'kind = "{kind}"',
                  f"start_s = {(seg.start - first) * cycle_s!r}",
                  f"stop_s = {(seg.stop - first) * cycle_s!r}"]
        if info:
            lines += ["[segments.info]"] + [f"{k} = {json.dumps(v)}" for k, v in info.items()]
    return lines


def mapping_text(recording, channels: dict[str, str]) -> str:
    """A mapping naming `channels` (mapping channel → the file's channel), the chirp
    family and the run's segments."""
    lines = ['name = "simulated chirp"', "[channels]"]
    lines += [f'{key} = "{name}"' for key, name in channels.items()]
    lines += ["[experiment]", 'type = "chirp"', *segment_tables(recording)]
    return "\n".join(lines) + "\n"


def write_mdf4(recording, path: Path, names: dict[str, str]) -> None:
    """The run's channels as an MDF 4.10 file written by asammdf (one channel group at the
    drive's cycle, SI units)."""
    from asammdf import MDF, Signal

    time = recording.cycle * recording.metadata["cycle_s"]
    mdf = MDF(version="4.10")
    mdf.append([Signal(recording.channels[channel], time, name=names[key],
                       unit=UNITS[channel]) for key, channel in MAPPED.items()],
               comment="feedbench simulated chirp")
    mdf.save(path, overwrite=True)
    mdf.close()


def write_tdms(recording, path: Path, names: dict[str, str]) -> None:
    """The run's channels as a TDMS file written by npTDMS (waveform channels: start 0,
    increment the drive's cycle, SI units)."""
    from nptdms import ChannelObject, TdmsWriter

    with TdmsWriter(path) as writer:
        writer.write_segment([ChannelObject("drive", names[key].split("/")[-1],
                                            recording.channels[channel], properties={
                                                "wf_increment": recording.metadata["cycle_s"],
                                                "wf_start_offset": 0.0,
                                                "unit_string": UNITS[channel]})
                              for key, channel in MAPPED.items()])


WRITERS = {"mdf4": (write_mdf4, ".mf4", "X_{}"), "tdms": (write_tdms, ".tdms", "drive/X_{}")}


@pytest.mark.parametrize("fmt", list(WRITERS))
def test_a_file_written_by_the_library_imports_bit_exact_and_analyses_as_the_run(
        fmt, chirp_run, tmp_path, capsys):
    write, suffix, pattern = WRITERS[fmt]
    original = open_recording(chirp_run)
    names = {key: pattern.format(key) for key in MAPPED}
    source = tmp_path / f"chirp{suffix}"
    write(original, source, names)
    source.with_suffix(".toml").write_text(mapping_text(original, names))

    assert main(["import", str(source), "--dir", str(tmp_path / "runs"), "--json"]) == 0
    row = json.loads(capsys.readouterr().out)
    imported = open_recording(row["file"])
    for key, channel in MAPPED.items():  # bit-exact: the samples themselves, SI in and out
        assert np.array_equal(imported.channels[channel], original.channels[channel]), channel
    assert imported.metadata["cycle_s"] == original.metadata["cycle_s"]
    first = int(original.cycle[0])  # the import numbers its cycles from 0
    assert [(s.start, s.stop, s.label) for s in imported.segments()] == \
        [(s.start - first, s.stop - first, s.label) for s in original.segments()]
    assert imported.status == "complete" and imported.experiment == "chirp"
    assert row["n_samples"] == original.n_samples == imported.n_samples

    ours, theirs = analyze_file(chirp_run), analyze_file(row["file"])
    for key in ("antiresonance_hz", "resonance_hz", "min_coherence", "valid"):
        assert theirs[key] == ours[key], key
    assert theirs["valid"] is True

    assert main(["runs", "--dir", str(tmp_path / "runs"), "--family", "chirp", "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)["runs"]
    assert [r["id"] for r in listed] == [row["id"]] and listed[0]["status"] == "complete"
    assert main(["analyze", row["id"], "--dir", str(tmp_path / "runs"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["resonance_hz"] == ours["resonance_hz"]
    assert main(["analyze", str(source), "--json"]) == 0  # the file itself, not catalogued
    assert json.loads(capsys.readouterr().out)["resonance_hz"] == ours["resonance_hz"]


def test_an_imported_run_is_reported_like_a_measured_one(chirp_run, tmp_path, capsys):
    original = open_recording(chirp_run)
    names = {key: f"X_{key}" for key in MAPPED}
    source = tmp_path / "chirp.mf4"
    write_mdf4(original, source, names)
    (tmp_path / "m.toml").write_text(mapping_text(original, names))
    runs = tmp_path / "runs"
    assert main(["import", str(source), "--mapping", str(tmp_path / "m.toml"),
                 "--dir", str(runs)]) == 0
    run_id = capsys.readouterr().out.split()[0]
    assert main(["report", run_id, "--dir", str(runs), "-o", str(tmp_path / "r.html")]) == 0
    html = (tmp_path / "r.html").read_text()
    assert run_id in html and "servo mobility" in html


def test_a_campaign_summary_takes_imported_runs_as_measured_ones(chirp_run, tmp_path, capsys):
    """`feedbench campaign --runs`: the summary table of recorded runs — a run as the runner
    records it, the same run written as MDF4 and imported, and a public TDMS file imported
    on the fly — each analysed by its family: the imported chirp's row equals the measured
    one's (headline and every result), its source named."""
    original = open_recording(chirp_run)
    names = {key: f"X_{key}" for key in MAPPED}
    source = tmp_path / "chirp.mf4"
    write_mdf4(original, source, names)
    source.with_suffix(".toml").write_text(mapping_text(original, names))
    runs = tmp_path / "runs"
    assert main(["import", str(source), "--dir", str(runs), "--json"]) == 0
    run_id = json.loads(capsys.readouterr().out)["id"]
    assert main(["campaign", "--runs", str(chirp_run), run_id, str(PUBLIC_TDMS),
                 "--dir", str(runs), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    measured, imported, public = summary["runs"]
    assert [row["index"] for row in summary["runs"]] == [0, 1, 2]
    assert [row["status"] for row in summary["runs"]] == ["complete"] * 3
    assert imported["run_id"] == run_id and imported["imported_from"] == "chirp.mf4"
    assert public["file"] == str(PUBLIC_TDMS) and public["imported_from"] == "raw1.tdms"
    assert imported["headline"] == measured["headline"] and "f_r" in measured["headline"]
    assert imported["results"] == measured["results"]
    assert measured["results"]["resonance_hz"] == analyze_file(chirp_run)["resonance_hz"]
    assert public["headline"].startswith("f_t ") and summary["complete"] == 3
    for path in summary["files"]:
        assert Path(path).parent == runs and Path(path).exists()
    csv_text = Path(summary["files"][1]).read_text()
    assert run_id in csv_text and "resonance_hz" in csv_text


def test_rates_meet_on_one_time_base(tmp_path):
    """Position at 1 kHz (the base), a reference at 100 Hz (interpolated), a force at 4 kHz
    (low-passed, then taken at the base's times), an accelerometer at 10 kHz kept as a
    stream with the cycle of each sample."""
    from asammdf import MDF, Signal

    t1, t4, t10 = (np.arange(int(2.0 * f)) / f for f in (1000.0, 4000.0, 10000.0))
    t01 = np.arange(200) / 100.0
    mdf = MDF(version="4.10")
    mdf.append([Signal(np.sin(2 * np.pi * 3 * t1), t1, name="x", unit="mm")])
    mdf.append([Signal(5.0 * t01, t01, name="xref", unit="mm")])
    mdf.append([Signal(np.sin(2 * np.pi * 50 * t4) + 0.5 * np.sin(2 * np.pi * 1700 * t4), t4,
                       name="F", unit="kN")])
    mdf.append([Signal(np.cos(2 * np.pi * 800 * t10), t10, name="acc", unit="g")])
    source = tmp_path / "rates.mf4"
    mdf.save(source, overwrite=True)
    run = load_run(source, {"channels": {"position": "x", "reference": "xref", "force": "F"},
                            "streams": {"daq": {"acc_tool_x": "acc"}}})
    base = np.arange(run.n_samples) * run.cycle_s
    assert run.cycle_s == pytest.approx(1e-3, rel=1e-12)
    assert run.n_samples == 1991  # the span every channel covers: 0 … 1.99 s (the 100 Hz one)
    assert np.array_equal(run.channels["position"], 1e-3 * np.sin(2 * np.pi * 3 * t1[:1991]))
    np.testing.assert_allclose(run.channels["x_ref"], 5e-3 * base, rtol=0, atol=1e-15)
    inner = slice(100, -100)  # away from the filter's ends: the 50 Hz sine, phase kept
    np.testing.assert_allclose(run.channels["force"][inner],
                               1e3 * np.sin(2 * np.pi * 50 * base[inner]), rtol=0, atol=2.0)
    notes = run.metadata["import_channels"]
    assert notes["reference"]["resampled"].startswith("linear interpolation from 100 Hz")
    assert notes["force"]["resampled"].startswith("polyphase FIR resampling by 1/4")
    assert notes["position"]["resampled"] == "none (on the time base)"
    spec, cycle, sequence, values = run.streams["daq"]
    assert spec.rate_hz == pytest.approx(10000.0) and spec.units["acc_tool_x"] == "m/s2"
    assert np.array_equal(cycle[:12], [0] * 10 + [1] * 2)
    assert np.array_equal(values["acc_tool_x"], 9.80665 * np.cos(2 * np.pi * 800 * t10)[:19910])
    path = tmp_path / "rates.h5"
    from feedbench.daq.importers.mapping import write_recording

    recording = open_recording(write_recording(run, path))
    assert np.array_equal(recording.streams["daq"].channels["acc_tool_x"], values["acc_tool_x"])
    assert recording.streams["daq"].n_dropped == 0


def gap_file(tmp_path: Path, gap: bool = True) -> Path:
    """An MDF4 file whose force channel lost 50 samples (0.05 s) at t = 1 s (or none)."""
    from asammdf import MDF, Signal

    t = np.arange(2000) / 1000.0
    kept = np.r_[0:1000, 1050:2000] if gap else np.arange(2000)
    mdf = MDF(version="4.10")
    mdf.append([Signal(t, t, name="x", unit="mm")])
    mdf.append([Signal(t[kept], t[kept], name="F", unit="N")])
    path = tmp_path / "gap.mf4"
    mdf.save(path, overwrite=True)
    return path


BAD = {
    "gap": ({"position": "x", "force": "F"}, {},
            r"^mapping\.channels\.force: channel 'F' has 1 gap\(s\): the first 0\.051 s long "
            r"at t = 0\.999 s \(sample period 0\.001 s\); gaps are refused"),
    "no channel": ({"position": "x", "force": "Fx"}, {},
                   r"^mapping\.channels\.force: no channel 'Fx' in gap\.mf4 \(channels: F, x\)$"),
    "wrong quantity": ({"position": "x", "force": "F"}, {"force": "mm"},
                       r"^mapping\.units\.force: 'mm' is a unit of length, the run's force is "
                       r"a force or torque"),
    "no position": ({"force": "F"}, {},
                    r"^mapping\.channels\.position: required"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_input_is_one_line_naming_the_field(case, tmp_path, capsys):
    channels, units, message = BAD[case]
    source = gap_file(tmp_path, gap=case == "gap")
    lines = ["[channels]"] + [f'{k} = "{v}"' for k, v in channels.items()]
    lines += ["[units]"] + [f'{k} = "{v}"' for k, v in units.items()]
    source.with_suffix(".toml").write_text("\n".join(lines) + "\n")
    assert main(["import", str(source), "--dir", str(tmp_path / "runs")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert re.search(message, err.removeprefix("feedbench: error: ")), err
    assert not list((tmp_path / "runs").glob("*.h5"))  # nothing written, nothing catalogued


@pytest.mark.parametrize("channel, message", [
    ("ASAM.M.SCALAR.UBYTE.HYPERBOLIC", r"has \d+ NaN or infinite sample\(s\), the first at t ="),
    ("ASAM.M.SCALAR.UBYTE.VTAB_RANGE_NO_DEFAULT_VALUE", r"is not numeric \(\|S21 samples"),
])
def test_a_real_file_s_unusable_channel_is_named(channel, message, tmp_path, capsys):
    mapping = tmp_path / "m.toml"
    mapping.write_text(f'[channels]\nposition = "ASAM.M.SCALAR.FLOAT64.IDENTICAL"\n'
                       f'force = "{channel}"\n[units]\nposition = "um"\nforce = "N"\n')
    assert main(["analyze", str(PUBLIC_MDF4), "--mapping", str(mapping)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "mapping.channels.force" in err, err
    assert re.search(message, err), err


@pytest.mark.parametrize("path, source_rates", [
    (PUBLIC_MDF4, {"position": 1000.0, "force": 1000.0, "reference": 100.0, "excitation": 10.0}),
    (PUBLIC_TDMS, {"position": 50000.0, "force": 50000.0}),
])
def test_public_recordings_analyse_and_judge_themselves(path, source_rates, capsys):
    """Real files from real DAQ systems (CANape on an ETK, NI DAQmx raw), small, cited; their
    signals are no feed drive, so the chirp analysis the mapping asks for must run and say
    that its FRF is not one (the coherence across the four records)."""
    assert path.stat().st_size < 300_000
    readme = (path.parent / "README.md").read_text()
    assert "LGPL-3.0" in readme and "commit" in readme
    run = load_run(path)
    for key, rate in source_rates.items():
        assert run.metadata["import_channels"][key]["rate_Hz"] == pytest.approx(rate, rel=1e-4)
    assert main(["analyze", str(path), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["experiment"] == "chirp" and result["n_sweeps"] == 4
    assert result["valid"] is False
    assert any("coherence at the peaks" in why for why in result["not_valid_because"])
    assert all(check["ok"] for check in result["checks"]
               if check["name"] in ("status", "missing samples (gaps)"))


@pytest.mark.parametrize("path, started, said", [
    (PUBLIC_MDF4, "2018-11-22T14:26:35.439737+00:00", "MDF header start time"),
    (PUBLIC_TDMS, "2016-12-15T22:35:21+00:00", "wf_start_time of First  Channel"),
])
def test_an_imported_run_starts_when_its_recording_did(path, started, said, tmp_path, capsys):
    """The catalog's and the recording's start are the file's own (an MDF4 header's start
    time, a TDMS waveform's wf_start_time; each moved on by the first sample of the time
    base), its stop that plus its samples; the import's time is kept apart (`imported_at`);
    `runs --since/--until` find the run on the day it was recorded."""
    from datetime import datetime, timedelta, timezone

    from feedbench.daq.catalog import Catalog

    runs = tmp_path / "runs"
    before = datetime.now(timezone.utc)
    assert main(["import", str(path), "--dir", str(runs), "--json"]) == 0
    row = json.loads(capsys.readouterr().out)
    run = load_run(path)
    first = datetime.fromisoformat(started) + timedelta(seconds=run.t0_s)
    assert run.metadata["source_started_from"].startswith(said)
    [listed] = Catalog(runs / "catalog.sqlite").list()
    recording = open_recording(row["file"])
    for start, stop in ((listed.started_at, listed.stopped_at),
                        (row["started_at"], row["stopped_at"]),
                        (recording.started_at, recording.stopped_at)):
        assert datetime.fromisoformat(start) == first
        assert datetime.fromisoformat(stop) - first == pytest.approx(
            timedelta(seconds=run.n_samples * run.cycle_s), abs=timedelta(microseconds=1))
    imported_at = datetime.fromisoformat(recording.metadata["imported_at"])
    assert before <= imported_at <= datetime.now(timezone.utc)
    day = started[:10]
    assert main(["runs", "--dir", str(runs), "--since", day, "--until", day]) == 0
    assert row["id"] in capsys.readouterr().out
    assert main(["runs", "--dir", str(runs), "--since", before.date().isoformat()]) == 0
    assert row["id"] not in capsys.readouterr().out


def test_the_formats_are_one_seam():
    assert set(formats()) >= {"mdf4", "tdms"}
    tdms = read_foreign(PUBLIC_TDMS)
    assert tdms.channels["First  Channel"].unit == "Volts"
    assert np.array_equal(tdms.channels["First  Channel"].values,
                          tdms.channels["Layer Data/First  Channel"].values)
    mdf = read_foreign(PUBLIC_MDF4)
    assert "ASAM.M.SCALAR.UBYTE.VTAB_RANGE_NO_DEFAULT_VALUE" in mdf.skipped


@pytest.mark.slow
def test_the_closure_runs_on_an_imported_mdf4_recording(tmp_path, capsys):
    """The closure's sample axis (a simulated bench axis with an effect hidden in it) written
    as MDF4 by asammdf, imported, and closed: the same finding as on its CSV."""
    from asammdf import MDF, Signal

    trace, controller = read_csv_trace(EXAMPLES / "sample_axis.csv")
    mdf = MDF(version="4.10")
    mdf.append([Signal(trace.position * 1e3, trace.time, name="X_pos", unit="mm"),
                Signal(trace.force, trace.time, name="F_motor", unit="N"),
                Signal(trace.reference * 1e3, trace.time, name="X_ref", unit="mm"),
                Signal(trace.excitation, trace.time, name="F_exc", unit="N")])
    source = tmp_path / "axis.mf4"
    mdf.save(source, overwrite=True)
    source.with_suffix(".toml").write_text(
        'force_lag_ms = 0.5\n[channels]\nposition = "X_pos"\nforce = "F_motor"\n'
        'reference = "X_ref"\nexcitation = "F_exc"\n[controller]\n'
        + "".join(f"{k} = {json.dumps(v)}\n" for k, v in controller.items()))
    assert main(["import", str(source), "--dir", str(tmp_path / "runs"), "--json"]) == 0
    imported = json.loads(capsys.readouterr().out)["file"]
    again = read_recording(imported)
    np.testing.assert_allclose(again.position, trace.position, rtol=1e-15, atol=0)
    assert again.force_lag == pytest.approx(trace.force_lag, rel=1e-12)
    model = str(EXAMPLES / "bench_coulomb_viscous.toml")
    assert main(["closure", imported, "--model", model, "--json"]) == 0
    on_import = json.loads(capsys.readouterr().out)
    assert main(["closure", str(EXAMPLES / "sample_axis.csv"), "--model", model, "--json"]) == 0
    on_csv = json.loads(capsys.readouterr().out)
    assert on_import["effects"] == on_csv["effects"] == ["ripple"]
    for key in ("error_before", "error_after"):
        assert on_import[key] == pytest.approx(on_csv[key], rel=1e-6), key


def test_a_joint_recorded_in_degrees_imports_and_closes_as_a_rotary_axis(tmp_path, capsys):
    """A mapping whose position is an angle (deg, rev) and force a torque (N·m): the imported
    run stores them in rad and N·m, and the closure reads the file and the imported run
    as a rotary axis (its report in mrad, N·m); a position in mm stays linear."""
    from asammdf import MDF, Signal

    from feedbench.closure_io import read_trace

    t = np.arange(2000) * 1e-3
    angle_deg = 30.0 * np.sin(2 * np.pi * 0.5 * t)
    torque = 2.0 * np.cos(2 * np.pi * 0.5 * t)
    for unit, rotary, to_si in (("deg", True, np.pi / 180.0), ("rev", True, 2.0 * np.pi),
                                ("mm", False, 1e-3)):
        mdf = MDF(version="4.10")
        mdf.append([Signal(angle_deg, t, name="q", unit=unit),
                    Signal(torque, t, name="tau", unit="N·m" if rotary else "N")])
        source = tmp_path / f"joint_{unit}.mf4"
        mdf.save(source, overwrite=True)
        source.with_suffix(".toml").write_text('[channels]\nposition = "q"\nforce = "tau"\n')
        foreign, _ = read_trace(source)
        assert foreign.rotary is rotary
        np.testing.assert_allclose(foreign.position, angle_deg * to_si, rtol=1e-12)
        assert main(["import", str(source), "--dir", str(tmp_path / unit), "--json"]) == 0
        imported = json.loads(capsys.readouterr().out)["file"]
        assert read_recording(imported).rotary is rotary
        recording = open_recording(imported)
        assert recording.rotary is rotary
        units = recording.units
        assert (units["position"], units["velocity"], units["force"]) == (
            ("rad", "rad/s", "N·m") if rotary else ("m", "m/s", "N"))
        assert [label for label, _ in trace_panels(recording)] == (
            ["angle (mrad)", "angular velocity (mrad/min)", "torque (N·m)"] if rotary
            else ["position (mm)", "velocity (mm/min)", "force (N)"])


@pytest.mark.parametrize("name, content, message", [
    ("cut.mf4", PUBLIC_MDF4.read_bytes()[:5000], r"cut\.mf4: not a readable MDF file \("),
    ("cut.tdms", PUBLIC_TDMS.read_bytes()[:3000],
     r"cut\.tdms: no channel in the file \(npTDMS: Last segment metadata is incomplete"),
    ("noise.mf4", bytes(range(256)) * 16, r"noise\.mf4: not a readable MDF file \(MdfException"),
    ("noise.tdms", bytes(range(256)) * 16, r"noise\.tdms: not a readable TDMS file \("),
    ("empty.mf4", b"", r"empty\.mf4: not a readable MDF file"),
])
def test_a_damaged_file_is_one_line_naming_it(name, content, message, tmp_path, capsys):
    source = tmp_path / name
    source.write_bytes(content)
    source.with_suffix(".toml").write_text('[channels]\nposition = "x"\nforce = "F"\n')
    assert main(["import", str(source), "--dir", str(tmp_path / "runs")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err  # the libraries' log lines and __del__ kept quiet
    assert re.search(message, err), err


@pytest.mark.parametrize("experiment, message", [
    ('type = "chirp"\nf_stop_hz = 150.0', r"^mapping\.experiment\.f_stop_hz: unknown key"),
    ('type = "chrip"', r"^mapping\.experiment\.type: unknown experiment family 'chrip' "
                       r"\(known: .*chirp"),
])
def test_the_experiment_is_checked_before_anything_is_written(experiment, message, tmp_path,
                                                              capsys):
    source = gap_file(tmp_path, gap=False)
    source.with_suffix(".toml").write_text(
        f'[channels]\nposition = "x"\nforce = "F"\n[experiment]\n{experiment}\n')
    assert main(["import", str(source), "--dir", str(tmp_path / "runs")]) == 2
    err = capsys.readouterr().err.strip().removeprefix("feedbench: error: ")
    assert re.search(message, err), err
    assert not (tmp_path / "runs").exists() or not list((tmp_path / "runs").glob("*.h5"))


def test_an_imported_run_closes_with_its_mapping_s_controller(tmp_path, capsys):
    source = gap_file(tmp_path, gap=False)
    source.with_suffix(".toml").write_text(
        '[channels]\nposition = "x"\nforce = "F"\n[controller]\nK_p_Ns_m = 8645.7\n'
        'delay_ms = 0.75\n')
    assert main(["import", str(source), "--dir", str(tmp_path / "runs"), "--json"]) == 0
    from feedbench.closure_io import read_trace

    trace, controller = read_trace(json.loads(capsys.readouterr().out)["file"])
    assert controller == {"K_p_Ns_m": 8645.7, "delay_ms": 0.75}
    assert trace.force_lag == 0.0  # as the mapping declares (no lag), not half a cycle


def test_a_tdms_group_s_time_channel_times_the_channels_without_waveform_timing(tmp_path):
    """A logger writing its own time stamps (1 kHz with 20 µs jitter, no wf_increment): the
    group's `Time` channel times the others, which are interpolated onto the even base."""
    from nptdms import ChannelObject, TdmsWriter

    rng = np.random.default_rng(1)
    time = np.arange(3000) * 1e-3 + rng.uniform(-2e-5, 2e-5, 3000)
    with TdmsWriter(tmp_path / "log.tdms") as writer:
        writer.write_segment([ChannelObject("log", "Time", time),
                              ChannelObject("log", "x", 2.0 * time, {"unit_string": "mm"}),
                              ChannelObject("log", "F", 7.0 + 0 * time, {"unit_string": "N"})])
    run = load_run(tmp_path / "log.tdms", {"channels": {"position": "x", "force": "F"}})
    assert run.cycle_s == pytest.approx(1e-3, rel=1e-4)
    base = run.t0_s + np.arange(run.n_samples) * run.cycle_s
    np.testing.assert_allclose(run.channels["position"], 2e-3 * base, rtol=0, atol=1e-15)
    assert np.all(run.channels["force"] == 7.0)
    assert run.metadata["import_channels"]["position"]["resampled"].startswith("linear")


def test_a_hammer_test_s_daq_channels_stay_a_stream_and_analyse_as_the_run(tmp_path, capsys):
    """The tool-tip analyses read the DAQ at its own rate: a simulated impact-hammer run (1 kHz
    drive, hammer force and tip acceleration at 10 kHz) written as TDMS by npTDMS, the DAQ
    channels mapped as the `daq` stream, imported: the stream equal bit for bit, each sample
    in its bus cycle, and the hammer analysis the same as the original's."""
    from nptdms import ChannelObject, TdmsWriter

    original_path = tmp_path / "hammer.h5"
    record_with_daq(original_path, {"type": "impact_hammer"}, hammer_steps(),
                    ("hammer_force", "acc_tool_x"))
    original = open_recording(original_path)
    stream = original.streams["daq"]
    cycle_s = original.metadata["cycle_s"]
    with TdmsWriter(tmp_path / "hammer.tdms") as writer:
        writer.write_segment(
            [ChannelObject("drive", channel, original.channels[channel],
                           {"wf_increment": cycle_s, "wf_start_offset": 0.0,
                            "unit_string": UNITS[channel]})
             for channel in ("position", "force")]
            + [ChannelObject("daq", channel, stream.channels[channel],
                             {"wf_increment": 1.0 / DAQ_RATE, "wf_start_offset": 0.0,
                              "unit_string": {"hammer_force": "N", "acc_tool_x": "m/s2"}[channel]})
               for channel in ("hammer_force", "acc_tool_x")])
    lines = ["[channels]", 'position = "drive/position"', 'force = "drive/force"',
             "[streams.daq]", 'hammer_force = "daq/hammer_force"', 'acc_tool_x = "daq/acc_tool_x"',
             "[experiment]", 'type = "impact_hammer"', *segment_tables(original)]
    (tmp_path / "hammer.toml").write_text("\n".join(lines) + "\n")
    assert main(["import", str(tmp_path / "hammer.tdms"), "--dir", str(tmp_path / "runs"),
                 "--json"]) == 0
    imported = open_recording(json.loads(capsys.readouterr().out)["file"])
    got = imported.streams["daq"]
    for channel in ("hammer_force", "acc_tool_x"):
        assert np.array_equal(got.channels[channel], stream.channels[channel]), channel
    assert np.array_equal(got.cycle, stream.cycle - int(original.cycle[0]))
    assert np.array_equal(got.sequence, stream.sequence) and got.n_dropped == 0
    ours, theirs = analyze_file(original_path), analyze_file(imported.path)
    assert theirs["valid"] == ours["valid"]
    for mine, other in zip(ours["feeds"], theirs["feeds"]):
        assert other["frf"] == mine["frf"]


@pytest.mark.parametrize("segments, message", [
    ([{"start_s": 0.0}], r"^mapping\.segments\[0\]\.kind: required key is missing"),
    ([{"kind": "excite", "start_s": 0.02, "stop_s": 0.01}],
     r"^mapping\.segments\[0\]\.stop_s: 0\.01 s is not after its start_s 0\.02 s$"),
    ([{"kind": "excite", "start_s": 1.0}],
     r"^mapping\.segments\[0\]\.start_s: 1 s lies after the run's 0\.03998 s$"),
    ([{"kind": "excite", "start_s": 0.0, "stop_s": 0.02}, {"kind": "excite", "start_s": 0.01}],
     r"^mapping\.segments\[1\]\.start_s: overlaps the segment before$"),
])
def test_bad_segments_are_named(segments, message):
    mapping = {"channels": {"position": "First  Channel", "force": "Second Chan"},
               "units": {"position": "mm", "force": "N"}, "segments": segments}
    with pytest.raises(ConfigError, match=message):
        load_run(PUBLIC_TDMS, mapping)
