"""The campaign report on recordings whose truth is known: values, quality flags, and a
headless-browser rendering (skipped when Chromium is not installed).

Set FEEDBENCH_SCREENSHOT_DIR to keep the rendered page for the README (docs/img/report.png).
"""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import struct
import subprocess
import tempfile

import numpy as np
import pytest
import scipy.signal

from feedbench.analysis.stability import directional_matrix
from feedbench.bench import analyze_file
from feedbench.daq.recording import open_recording
from feedbench.experiments import chirp, smfe
from feedbench.experiments.impact_hammer import ImpactHammer
from feedbench.experiments.friction_sweep import FrictionSweep
from feedbench.engine.runner import CHANNELS
from feedbench.models.friction import AnderssonFriction
from feedbench.models.milling import engagement_angles
from feedbench.models.structure import SMFE_TOOL_STRUCTURE, ModalStructure
from feedbench.experiments.tool_tip import TABLE_5_1, tool_tip_lobes
from feedbench.report import closure_section, render_html, run_section, verdict, write_report
from feedbench.testing import CYCLE_S, synthetic_recording
from feedbench.testing import cycle_rows as rows_of
from feedbench.units import MM_PER_MIN
from prerequisites import CHROMIUM, requires

LAW = {1: AnderssonFriction(44.2, 84.0, 387.4 * MM_PER_MIN, 0.0028 * 60e3),
       -1: AnderssonFriction(38.7, 88.0, 421.0 * MM_PER_MIN, 0.0025 * 60e3)}
COLUMN = {name: i for i, name in enumerate(CHANNELS)}


def record(path, experiment: str, steps, status: str = "complete", reason: str = "",
           skip_after: int | None = None, config: dict | None = None,
           metadata: dict | None = None) -> None:
    """A recording of `steps` = [(label, kind, info, rows n × CHANNELS)], as the runner
    writes it (`feedbench.testing.synthetic_recording`); `skip_after` drops 5 cycles there."""
    synthetic_recording(path, config or {"type": experiment}, steps, status=status,
                        reason=reason, gap_after=skip_after, metadata=metadata)


def friction_steps():
    rng = np.random.default_rng(2)
    steps = []
    for feed in (25, 50, 75, 100, 150, 200, 300, 400, 500, 700, 900, 1200, 1500):
        for sign in (1, -1):
            v = sign * feed * MM_PER_MIN
            info = {"feed_mm_min": sign * feed}
            steps += [
                ("accelerate", "move", info, rows_of(40, velocity=rng.normal(size=40) * v)),
                ("measure", "measure", info,
                 rows_of(120, velocity=v, force=sign * LAW[sign].force(abs(v)),
                         position=np.cumsum(np.full(120, v * CYCLE_S)))),
                ("stop", "move", info, rows_of(30)),
            ]
    return steps


def two_mass_mobility(fs: float):
    """Motor velocity / motor force of the lab bench's two masses (Ch. 4), with the servo
    acting as 2000 N·s/m of damping to ground; bilinear discretisation."""
    m1, m2, k, c, c0 = 23.1, 11.3, 1.68e6, 104.0, 2000.0
    tip = np.array([m2, c, k])
    motor = np.array([m1, c + c0, k])
    coupling = np.array([c, k])
    numerator = np.polymul([1.0, 0.0], tip)
    denominator = np.polysub(np.polymul(motor, tip), np.polymul(coupling, coupling))
    return scipy.signal.bilinear(numerator, denominator, fs)


def chirp_steps():
    """Three sweeps as the chirp experiment records them at its default feed (500 mm/min):
    a 10–200 Hz chirp, then a tail with no excitation in which the response rings down
    (each sweep starts at rest)."""
    fs = 1.0 / CYCLE_S
    b, a = two_mass_mobility(fs)
    t = np.arange(6000) / fs
    force = np.r_[20.0 * scipy.signal.chirp(t, 10.0, t[-1], 200.0), np.zeros(2192)]
    velocity = scipy.signal.lfilter(b, a, force)
    rng = np.random.default_rng(4)
    steps = []
    for rep in range(3):
        noise = 1e-3 * rng.normal(size=force.size)
        steps += [(f"settle {rep}", "settle", {}, rows_of(300)),
                  (f"sweep {rep}", "excite", {"repetition": rep},
                   rows_of(force.size, force=force + noise,
                           velocity=500 * MM_PER_MIN + velocity, force_offset=force))]
    return steps


def true_extrema(band=(20.0, 150.0)) -> tuple[float, float]:
    """Anti-resonance and resonance (Hz) of the discrete filter, on a 0.01 Hz grid."""
    f = np.arange(*band, 0.01)
    _, H = scipy.signal.freqz(*two_mass_mobility(1.0 / CYCLE_S), worN=f, fs=1.0 / CYCLE_S)
    k_r = int(np.argmax(np.abs(H)))
    return float(f[np.argmin(np.abs(H[:k_r]))]), float(f[k_r])


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    directory = tmp_path_factory.mktemp("report")
    paths = [directory / name for name in ("friction.h5", "chirp.h5", "aborted.h5")]
    record(paths[0], "friction_sweep", friction_steps())
    record(paths[1], "chirp", chirp_steps())
    record(paths[2], "friction_sweep", friction_steps()[:9], status="aborted",
           reason="stop button in the live window", skip_after=200)
    return paths


DRAWN: dict[str, list] = {}
"""(experiment, matplotlib figure) of every plot `sectioned` drew, per recording path: the
legend test (`drawn_figures`) checks the module fixtures' figures instead of drawing every
section a second time (≈ 20 s)."""


def sectioned(path):
    """`run_section` of the recording at `path`, the figures it draws kept in `DRAWN`."""
    from matplotlib.figure import Figure

    drawn, savefig = [], Figure.savefig

    def recorded(figure, *args, **kwargs):
        drawn.append(figure)
        return savefig(figure, *args, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Figure, "savefig", recorded)
        recording = open_recording(path)
        section = run_section(recording)
    DRAWN[str(path)] = [(recording.experiment, figure) for figure in drawn]
    return section


@pytest.fixture(scope="module")
def sections(runs):
    return [sectioned(path) for path in runs]


@pytest.fixture(scope="module")
def report(runs):
    return write_report(runs, runs[0].parent / "report.html")


def png_size(png: bytes) -> tuple[int, int]:
    """Width and height from a PNG's IHDR chunk (after checking the signature)."""
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and png[12:16] == b"IHDR"
    return struct.unpack(">II", png[16:24])


def test_report_is_one_html_file_with_its_plots_inside(report):
    text = report.read_text(encoding="utf-8")
    images = re.findall(r"<img alt='([^']*)' src='data:image/png;base64,([^']+)'>", text)
    assert [alt for alt, _ in images] == [
        "key time traces", "friction curve and fitted model, Eq. (5.2)",
        "key time traces", "servo mobility (H1, Welch): magnitude, phase, coherence",
        "key time traces"]
    sizes = [png_size(base64.b64decode(data)) for _, data in images]
    assert sizes == [(1000, 700), (800, 450), (1000, 700), (800, 700), (1000, 700)]
    assert text.count("<img") == 5
    assert "http:" not in text and "https:" not in text and "<link" not in text


def table(section, title: str) -> dict[str, tuple[str, ...]]:
    rows = next(t.rows for t in section.tables if t.title == title)
    return {row[0]: row[1:] for row in rows}


def value(cell: str) -> float:
    return float(cell.split()[0])


def test_friction_section_shows_the_identified_law(sections):
    section = sections[0]
    params = table(section, "identified friction parameters")
    for name, unit_scale, key in (("F_c (N)", 1.0, "F_c"), ("F_s (N)", 1.0, "F_s"),
                                  ("v_s (mm/min)", 1 / MM_PER_MIN, "v_s")):
        for column, sign in ((0, 1), (1, -1)):
            truth = getattr(LAW[sign], key) * unit_scale
            assert value(params[name][column]) == pytest.approx(truth, rel=1e-3)
    assert value(params["sigma (N·min/mm)"][0]) == pytest.approx(0.0028, rel=1e-3)
    quality = {q.name: q for q in section.quality}
    assert quality["R² of the positive fit"].ok and quality["status"].ok
    assert quality["missing samples (gaps)"].value == "0"
    assert section.headline == "F_c 44.2 N, F_s 84.0 N (positive)"


def test_friction_window_not_at_steady_state_is_left_out_drawn_and_counted(tmp_path):
    """A measure window whose force still rises 30 % (a transient: the axis had not
    settled) is flagged, left out of the fit (the law is found from the 12 others), drawn
    apart and counted; R² is over the points used. With the identified-vs-true table."""
    steps = friction_steps()
    label, kind, info, rows = steps[1]  # positive, 25 mm/min
    rows = rows.copy()
    rows[:, COLUMN["force"]] *= np.linspace(0.7, 1.0, len(rows))
    steps[1] = (label, kind, info, rows)
    record(tmp_path / "transient.h5", "friction_sweep", steps)
    truth = {"friction": {d: {"F_c": LAW[s].F_c, "F_s": LAW[s].F_s, "v_s": LAW[s].v_s,
                              "sigma": LAW[s].sigma} for d, s in (("positive", 1), ("negative", -1))}}
    section = run_section(open_recording(tmp_path / "transient.h5"), truth)
    quality = {q.name: q for q in section.quality}
    left_out = quality["windows not at steady state (left out of the fit)"]
    assert (left_out.value, left_out.ok) == ("1: at 25 mm/min — the velocity was off the feed "
                                             "or the force still drifting: raise settle_s or "
                                             "settle_mm", False)
    assert quality["R² of the positive fit"].value == "1.00000 (rms 0.00 N) over its 12 points"
    assert quality["R² of the negative fit"].value.endswith("over its 13 points")
    rows = next(t.rows for t in section.tables if t.title == "identified vs true (simulated world)")
    assert len(rows) == 8 and all(abs(value(row[4])) < 0.1 for row in rows)  # error in %
    assert plot_sizes(section)["friction curve and fitted model, Eq. (5.2)"] == (800, 450)


def test_friction_text_and_summary_give_the_law_in_the_units_of_fig_5_11(runs):
    """`feedbench analyze`'s lines and the demo's summary against the recorded law."""
    result = analyze_file(runs[0])
    lines = FrictionSweep.describe(result)
    assert lines[:2] == ["  F_c 44.2 N, F_s 84.0 N (positive)",
                         "  positive: R² 1.00000, rms 0.000 N"]
    assert lines[2:6] == ["    F_c       44.20 N", "    F_s       84.00 N",
                          "    v_s       387.4 mm/min", "    sigma   0.00280 N·min/mm"]
    assert lines[7:11] == ["    F_c       38.70 N", "    F_s       88.00 N",
                           "    v_s       421.0 mm/min", "    sigma   0.00250 N·min/mm"]
    assert lines[11] == "  ✔ R² of the positive fit: 1.00000 (rms 0.00 N) over its 13 points"
    assert lines[-1] == "  all 8 checks passed"
    truth = {"friction": {d: vars(LAW[sign]) for d, sign in (("positive", 1), ("negative", -1))}}
    summary = FrictionSweep.summary(result, truth)
    assert summary["max_abs_error_pct"] < 1e-6
    assert summary["headline"].startswith("Eq. 5.2: F_c 44.2 / 38.7 N, F_s 84.0 / 88.0 N (+/−); "
                                          "largest error vs truth 0.00 % (")


def test_chirp_section_finds_anti_resonance_and_resonance(runs, sections):
    section = sections[1]
    mobility = table(section, "servo mobility")
    f_t, f_r = true_extrema()
    assert value(mobility["anti-resonance f_t (Eq. 4.13)"][0]) == pytest.approx(f_t, abs=0.5)
    assert value(mobility["resonance f_r (Eq. 4.14)"][0]) == pytest.approx(f_r, abs=0.5)
    assert mobility["sweeps averaged"] == ("3",)
    coherence = next(q for q in section.quality if q.name == "min coherence in 20-150 Hz")
    frf = chirp.analyze_recording(open_recording(runs[1]))["frf"]
    lowest = int(np.argmin(frf["coherence"]))
    assert coherence.value == f"{frf['coherence'][lowest]:.4f}"
    assert coherence.ok is (frf["coherence"][lowest] >= 0.9)
    assert frf["f_hz"][lowest] == pytest.approx(f_t, abs=1.0)  # leakage where |H| vanishes


def test_quality_flags_an_aborted_run_with_missing_samples(sections):
    section = sections[2]
    quality = {q.name: q for q in section.quality}
    assert quality["status"].value == "aborted (stop button in the live window)"
    assert quality["status"].ok is False
    assert quality["missing samples (gaps)"].value == "5"
    assert quality["missing samples (gaps)"].ok is False
    assert quality["analysis"].ok is False and quality["analysis"].value.startswith("failed")
    peak = max(LAW[1].force(25 * MM_PER_MIN), LAW[-1].force(25 * MM_PER_MIN),
               LAW[1].force(50 * MM_PER_MIN))  # the three measured windows before the abort
    assert quality["peak |force|"].value == f"{peak:.1f} N = 6 % of the limit"


def chromium(*args: str) -> subprocess.CompletedProcess:
    """Headless Chromium with a throw-away profile and no background traffic."""
    with tempfile.TemporaryDirectory() as profile:
        return subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu",
                               "--hide-scrollbars", f"--user-data-dir={profile}",
                               "--no-first-run", "--disable-background-networking",
                               "--disable-component-update", "--disable-sync", *args],
                              capture_output=True, text=True, timeout=120)


def decoded_images(report, directory) -> list[str]:
    """Width × height of every image Chromium decoded once the page loaded."""
    probe = directory / "probe.html"
    probe.write_text(report.read_text(encoding="utf-8").replace(
        "</body>", "<script>window.addEventListener('load', () => {document.body.dataset"
        ".decoded = [...document.images].filter(i => i.complete && i.naturalWidth > 0)"
        ".map(i => i.naturalWidth + 'x' + i.naturalHeight).join(' ');});</script></body>"),
        encoding="utf-8")
    dom = chromium("--virtual-time-budget=5000", "--dump-dom", probe.as_uri()).stdout
    return re.search(r'data-decoded="([^"]*)"', dom).group(1).split()


@requires(CHROMIUM is not None, "headless Chromium is not installed")
def test_report_renders_in_headless_chromium_with_every_image_decoded(report, tmp_path):
    assert decoded_images(report, tmp_path) == [
        "1000x700", "800x450", "1000x700", "800x700", "1000x700"]
    shot = tmp_path / "report.png"
    chromium("--window-size=1200,1600", f"--screenshot={shot}", report.as_uri())
    width, height = png_size(shot.read_bytes())
    assert (width, height) == (1200, 1600)
    if os.environ.get("FEEDBENCH_SCREENSHOT_DIR"):
        shutil.copy(shot, os.path.join(os.environ["FEEDBENCH_SCREENSHOT_DIR"], "report.png"))


# -- the other experiment families ---------------------------------------------------------
# Recordings as the runner and the serial DAQ write them (rows per bus cycle, the DAQ's
# samples with their cycle and counter), from structures whose FRF is known; the stepped
# loading is a short run on the simulated rack-and-pinion axis.

DAQ_RATE = 10_000.0
PER_CYCLE = 10


def record_with_daq(path, experiment: dict, steps, daq_channels: tuple[str, ...],
                    metadata: dict | None = None) -> None:
    """Steps [(label, kind, info, rows n × CHANNELS, daq n·PER_CYCLE × channels)]."""
    synthetic_recording(path, experiment, steps, metadata=metadata, daq_channels=daq_channels,
                        daq_rate_hz=DAQ_RATE)


def daq_step(label: str, kind: str, info: dict, daq: np.ndarray):
    return (label, kind, info, rows_of(len(daq) // PER_CYCLE), daq)


SDOF = {"idle": ModalStructure(60.0, 0.05, 2.0e6, [[1.0]]),
        "moving": ModalStructure(47.0, 0.15, 1.0e6, [[1.0]])}
"""Tool tips along the feed: idle (motor locked by stiction) and moving (the servo damps the
mode), as on the lab bench (Fig. 5.12)."""


def compliance(structure: ModalStructure, f) -> np.ndarray:
    return structure.receptance(f)[:, 0, 0]


def compliance_peak_hz(structure: ModalStructure) -> float:
    """Where |x/F| of a single mode peaks: f_n √(1 − 2ζ²)."""
    return float(structure.f_n[0] * np.sqrt(1 - 2 * structure.zeta[0] ** 2))


def hammer_steps():
    """Three 1 s hits at each of two feeds: a 1 ms half-sine of 25 N, the structure's
    acceleration from rest (`ModalStructure.simulate`) with 1e-3 m/s² noise."""
    rng = np.random.default_rng(12)
    force = np.zeros(int(DAQ_RATE))
    force[500:511] = 25.0 * np.sin(np.pi * np.arange(11) / 10)
    steps = []
    for feed, structure in ((0.0, SDOF["idle"]), (500.0, SDOF["moving"])):
        acc = structure.simulate(force[None], DAQ_RATE).acceleration[0]
        steps.append(daq_step("settle", "settle", {"feed_mm_min": feed}, np.zeros((500, 2))))
        for hit in range(3):
            noisy = acc + 1e-3 * rng.normal(size=acc.size)
            steps.append(daq_step(f"hit {hit + 1}", "excite", {"feed_mm_min": feed, "hit": hit},
                                  np.column_stack([force, noisy])))
    return steps


def sine_stream_steps():
    """Steady-state sines at 40…60 Hz (1 Hz steps, 5 + 5 periods) on the moving tip, 20 N."""
    steps = []
    for i, f in enumerate(np.arange(40.0, 61.0)):
        n = int(round(10 / (f * CYCLE_S))) * PER_CYCLE
        t = np.arange(n) / DAQ_RATE
        a_over_f = -(2 * np.pi * f) ** 2 * compliance(SDOF["moving"], [f])[0]
        force = 20.0 * np.sin(2 * np.pi * f * t)
        acc = 20.0 * abs(a_over_f) * np.sin(2 * np.pi * f * t + np.angle(a_over_f))
        steps.append(daq_step(f"{f:g} Hz", "excite", {
            "feed_mm_min": 1000.0, "amplitude_N": 20.0, "step": i, "repeat": 0,
            "frequency_hz": f, "held_N": 20.0, "limited": False}, np.column_stack([force, acc])))
    return steps


def shaker_chirp_steps():
    """Two 20–100 Hz sweeps of 2 s with 0.5 s ring-down on the moving tip."""
    t = np.arange(int(2.0 * DAQ_RATE)) / DAQ_RATE
    force = np.r_[20.0 * scipy.signal.chirp(t, 20.0, t[-1], 100.0), np.zeros(int(0.5 * DAQ_RATE))]
    acc = SDOF["moving"].simulate(force[None], DAQ_RATE).acceleration[0]
    return [daq_step(f"sweep {i + 1}", "excite", {"feed_mm_min": 1000.0, "repetition": i},
                     np.column_stack([force, acc])) for i in range(2)]


K_P, T_I = 12_968.0, 0.01


def lab_bench_mobility(f) -> np.ndarray:
    """Motor velocity / motor force of the lab bench's two masses (DIGEST §3: M_mot 23.1 kg,
    M_tip 11.3 kg, k 1.68 N/µm, c 104 N·s/m): f_t 61.4 Hz, f_r 74.9 Hz (Eqs. 4.13, 4.14)."""
    s = 2j * np.pi * np.asarray(f)
    m1, m2, k, c = 23.1, 11.3, 1.68e6, 104.0
    tip = m2 * s**2 + c * s + k
    return tip / (s * (m1 * tip + m2 * (c * s + k)))


def bode_steps():
    """Closed velocity loop (Eq. 4.21 with K_P, T_I) as steady sines at 20…120 Hz, 1 Hz
    steps, 5 + 10 periods of a 60 mm/min reference at a 500 mm/min feed."""
    from feedbench.analysis.servo import closed_velocity_loop

    steps = []
    for f in np.arange(20.0, 121.0):
        n = int(round(15 / (f * CYCLE_S)))
        t = np.arange(n) * CYCLE_S
        H = closed_velocity_loop([f], lab_bench_mobility([f]), K_P, T_I)[0]
        reference = 60 * MM_PER_MIN * np.sin(2 * np.pi * f * t)
        velocity = 500 * MM_PER_MIN + 60 * MM_PER_MIN * abs(H) * np.sin(2 * np.pi * f * t
                                                                         + np.angle(H))
        steps.append((f"{f:g} Hz", "excite", {"feed_mm_min": 500.0, "frequency_hz": f},
                      rows_of(n, velocity_offset=reference, velocity=velocity)))
    return steps


SMFE_DIRECTIONS = {"down": (1.0, 0.4, 0.2), "up": (0.3, 1.0, -0.3), "central": (0.2, -0.4, 1.0)}
"""Force direction of each cut: as in milling, every force component of a cut is coherent
with its F_x (the analysis's reference), the cuts point different ways."""


def smfe_steps():
    """Three 12 s 'cuts', each a broadband force along its own direction, on Table 6.2's
    tool structure (DAQ: the dynamometer reads −F); the workpiece side moves as −½ the tool."""
    rng = np.random.default_rng(21)
    steps = []
    for k, (mode, direction) in enumerate(SMFE_DIRECTIONS.items()):
        signal = scipy.signal.lfilter(*scipy.signal.butter(4, 300.0, fs=DAQ_RATE),
                                      100.0 * rng.normal(size=int(12 * DAQ_RATE)))
        force = np.outer(direction, signal)
        acc = SMFE_TOOL_STRUCTURE.simulate(force, DAQ_RATE).acceleration
        daq = np.vstack([-force, acc, -0.5 * acc]).T
        steps += [daq_step(f"approach {mode}", "move", {"cut": k}, np.zeros((100, 9))),
                  daq_step(f"{mode} milling ramp", "measure", {"cut": k, "mode": mode}, daq)]
    return steps


@pytest.fixture(scope="module")
def family_runs(tmp_path_factory):
    directory = tmp_path_factory.mktemp("families")
    paths = {name: directory / f"{name}.h5" for name in (
        "impact_hammer", "sine_stream", "shaker_chirp", "closed_loop_bode", "smfe")}
    record_with_daq(paths["impact_hammer"], {"type": "impact_hammer"}, hammer_steps(),
                    ("hammer_force", "acc_tool_x"))
    record_with_daq(paths["sine_stream"], {"type": "sine_stream", "amplitudes_N": [20.0]},
                    sine_stream_steps(), ("actuator_force", "acc_tool_x"))
    record_with_daq(paths["shaker_chirp"], {"type": "shaker_chirp", "f_start_Hz": 20.0,
                                            "f_stop_Hz": 100.0}, shaker_chirp_steps(),
                    ("shaker_force", "acc_tool_x"))
    record(paths["closed_loop_bode"], "closed_loop_bode", bode_steps(),
           config={"type": "closed_loop_bode", "f_start_Hz": 20.0, "f_stop_Hz": 120.0},
           metadata={"drive_gains": {"K_p": K_P, "T_i": T_I}})
    record_with_daq(paths["smfe"], {"type": "smfe", "segment_s": 2.0, "ramp_s": 12.0},
                    smfe_steps(), smfe.DAQ_CHANNELS)
    return paths


@pytest.fixture(scope="module")
def family_sections(family_runs):
    return {name: sectioned(path) for name, path in family_runs.items()}


def plot_sizes(section) -> dict[str, tuple[int, int]]:
    return {plot.title: png_size(plot.png) for plot in section.plots}


def test_every_family_section_has_its_plots_and_no_failed_analysis(family_sections):
    expected = {
        "impact_hammer": {"key time traces": (1000, 950),
                          "tool-tip compliance per feed (quasi-FRF, Eq. 5.3): magnitude, phase, "
                          "coherence": (800, 700),
                          "stability lobes from the measured tool-tip FRF": (800, 450)},
        "sine_stream": {"key time traces": (1000, 950),
                        "sine-stream compliance points: magnitude, phase, R² of each step":
                            (800, 700)},
        "shaker_chirp": {"key time traces": (1000, 950),
                         "tool-tip compliance per feed (H1 over the sweeps): magnitude, phase, "
                         "coherence": (800, 700),
                         "stability lobes from the measured tool-tip FRF": (800, 450)},
        "closed_loop_bode": {"key time traces": (1000, 700),
                             "closed velocity loop: magnitude, phase, R²": (800, 700),
                             "open-loop mobility by Eq. (4.20): magnitude, phase, R²":
                                 (800, 700)},
        "smfe": {"key time traces": (1000, 1400),  # 6 accelerations: a panel each
                 "SMFE direct receptances Φ_tt at the tool (Eq. 6.13): magnitude, phase, "
                 "coherence (Eq. 6.15, lowest over the cuts)": (800, 700),
                 "SMFE direct receptances Φ_ww at the workpiece (Eq. 6.13): magnitude, phase, "
                 "coherence (Eq. 6.15, lowest over the cuts)": (800, 700),
                 "condition number (Eq. 6.14) against the planned C_th": (800, 300),
                 "spindle speed and force spectrogram with the tooth-passing harmonics":
                     (1000, 450)},
    }
    for name, section in family_sections.items():
        assert plot_sizes(section) == expected[name], name
        assert not [q for q in section.quality if q.name in ("analysis", "results")], name


def test_hammer_section_shows_each_feeds_compliance_and_the_lobes_it_predicts(family_runs,
                                                                              family_sections):
    section = family_sections["impact_hammer"]
    feeds = table(section, "impact hammer per feed")
    assert value(feeds["0"][0]) == pytest.approx(compliance_peak_hz(SDOF["idle"]), abs=1.0)
    assert value(feeds["500"][0]) == pytest.approx(compliance_peak_hz(SDOF["moving"]), abs=1.0)
    assert feeds["0"][2] == "3 of 3"
    # peak |x/F| = 1/(2ζ√(1−ζ²) k); the exponential window (τ 0.5 s) adds 1/(ωτ) to ζ
    for feed, structure in (("0", SDOF["idle"]), ("500", SDOF["moving"])):
        zeta = structure.zeta[0] + 1 / (2 * np.pi * structure.f_n[0] * 0.5)
        peak = 1e6 / (2 * zeta * np.sqrt(1 - zeta**2) * structure.k[0])
        assert value(feeds[feed][1]) == pytest.approx(peak, rel=0.03)
    lobes = table(section, "stability lobes (Table 5.1 cut, y taken rigid)")
    result = ImpactHammer.analyze(open_recording(family_runs["impact_hammer"]))
    for label, feed in (("0 mm/min", result["feeds"][0]), ("500 mm/min", result["feeds"][1])):
        frf = feed["frf"]
        measured = (np.array(frf["compliance_abs"])
                    * np.exp(1j * np.array(frf["compliance_phase_rad"])))
        expected = tool_tip_lobes(np.array(frf["f_hz"]), measured)
        assert value(lobes[label][0]) == pytest.approx(expected.min_depth * 1e3, abs=5e-4)
    assert value(lobes["500 mm/min"][0]) > 1.3 * value(lobes["0 mm/min"][0])  # Fig. 5.25
    assert section.headline == "invariant from 500 mm/min"


def test_hammer_analysis_uses_the_configured_exponential_window(tmp_path):
    """`exp_decay_s` 0.25 s instead of 0.5 s: the window adds 1/(ωτ) to ζ, twice as much,
    and the peak |x/F| = 1/(2ζ√(1−ζ²) k) falls with it."""
    path = tmp_path / "hammer.h5"
    record_with_daq(path, {"type": "impact_hammer", "exp_decay_s": 0.25}, hammer_steps(),
                    ("hammer_force", "acc_tool_x"))
    feeds = ImpactHammer.analyze(open_recording(path))["feeds"]
    for feed, structure in zip(feeds, (SDOF["idle"], SDOF["moving"])):
        zeta = structure.zeta[0] + 1 / (2 * np.pi * structure.f_n[0] * 0.25)
        peak = 1 / (2 * zeta * np.sqrt(1 - zeta**2) * structure.k[0])
        assert feed["peak_compliance_m_N"] == pytest.approx(peak, rel=0.03)


def test_tool_tip_lobes_reach_the_single_direction_limit_of_the_zoa():
    """With y rigid the ZOA's one eigenvalue is α_xx Φ_xx: the lowest lobe minimum is
    a = 2π / (Z K_tc α_xx min Re Φ_xx) (Altintas & Budak); Table 5.1's cut."""
    f = np.linspace(20.0, 150.0, 2601)
    phi = compliance(SDOF["moving"], f)
    lobes = tool_tip_lobes(f, phi)
    start, stop = engagement_angles(TABLE_5_1.a_e, TABLE_5_1.D, TABLE_5_1.mode)
    alpha = directional_matrix(TABLE_5_1.K_rc / TABLE_5_1.K_tc, start, stop)[0, 0]
    real_part = phi.real.max() if alpha > 0 else phi.real.min()
    limit = 2 * np.pi / (TABLE_5_1.Z * TABLE_5_1.K_tc * alpha * real_part)
    assert lobes.min_depth == pytest.approx(limit, rel=0.01)
    assert 0.2e-3 < limit < 2e-3


def test_sine_stream_section_has_the_true_points_and_their_r_squared(family_sections):
    section = family_sections["sine_stream"]
    rows = table(section, "sine-stream per feed and amplitude")["1000"]
    assert rows[:2] == ("20", "21 of 21")
    f = np.arange(40.0, 61.0)
    assert value(rows[2]) == f[np.argmax(np.abs(compliance(SDOF["moving"], f)))]
    quality = {q.name: q for q in section.quality}
    assert quality["steps flagged (quality gate)"].value == "0"
    assert float(quality["min R² of the steps used"].value) > 0.99999
    n = sum(int(round(10 / (f * CYCLE_S))) * PER_CYCLE for f in np.arange(40.0, 61.0))
    assert quality["daq stream"].value == f"{n} samples at 10000 Hz, 0 lost"


def test_shaker_chirp_section_finds_the_resonance(family_sections):
    section = family_sections["shaker_chirp"]
    row = table(section, "shaker chirp per feed")["1000"]
    assert row[0] == "2"  # 2.5 s records: 0.4 Hz resolution
    assert value(row[1]) == pytest.approx(compliance_peak_hz(SDOF["moving"]), abs=0.4)
    assert value(row[2]) > 0.99
    lobes = table(section, "stability lobes (Table 5.1 cut, y taken rigid)")
    assert list(lobes) == ["1000 mm/min"]


def test_closed_loop_bode_section_gives_the_flexure_frequencies(family_sections):
    section = family_sections["closed_loop_bode"]
    rows = table(section, "closed velocity loop")
    assert value(rows["anti-resonance f_t (Eq. 4.13)"][0]) == pytest.approx(61.4, abs=1.0)
    assert value(rows["resonance f_r (Eq. 4.14)"][0]) == pytest.approx(74.9, abs=1.0)
    assert rows["frequencies flagged (R²)"] == ("0",)
    assert section.headline.startswith("f_t 61")


def test_smfe_section_recovers_the_tool_receptance_peaks(family_sections):
    """Table 6.2's tool: |Φ_tt| peaks within 10 % of the truth at ±1 Hz (1 s segments)."""
    section = family_sections["smfe"]
    peaks = {(row[0], row[1]): row[2:] for row in
             next(t for t in section.tables if t.title == "SMFE peaks").rows}
    f = np.arange(20.0, 100.0, 0.01)
    truth = np.abs(SMFE_TOOL_STRUCTURE.receptance(f))
    for i, axis in enumerate("xyz"):
        f_peak, magnitude, coherence = peaks[("tool", f"{axis}{axis}")]
        k = np.argmax(truth[:, i, i])
        assert float(f_peak) == pytest.approx(f[k], abs=1.0)
        assert float(magnitude) == pytest.approx(truth[k, i, i], rel=0.1)
        assert float(coherence) > 0.9
        assert float(peaks[("workpiece", f"{axis}{axis}")][1]) == pytest.approx(
            0.5 * float(magnitude), rel=5e-3)  # three digits in the table
    quality = {q.name: q for q in section.quality}
    median, worst, planned = (float(v) for v in quality[
        "condition number (median / max / planned C_th)"].value.split(" — ")[0].split(" / "))
    assert 1.0 <= median < worst and planned == pytest.approx(9.1, abs=0.1)


@pytest.fixture(scope="module")
def stepped_loading_run(tmp_path_factory):
    """A short stepped loading on the simulated rack-and-pinion axis (≈ 8 s): master only,
    one backlash stroke, single-motor loading, coupled loading at 20 % preload."""
    from feedbench.bench import parse_run_config, run_config
    from feedbench.commands.demo import example_config

    raw = example_config("stepped_loading")
    raw["bench"].update(output_dir=str(tmp_path_factory.mktemp("stepped")),
                        channel=f"report-stepped-{os.getpid()}")
    raw["bench"]["devices"]["load_cell"]["every_cycles"] = 5
    raw["experiment"].update(backlash=["master"], single_motor=["master"], preload_pct=[20.0],
                             unload=False, settle_s=0.03, measure_s=0.06, ramp_s=0.01,
                             depth_um=250.0, step_um=10.0, single_depth_um=350.0,
                             single_step_um=20.0, strokes=1, setup_s=0.5, dwell_s=0.1)
    row = run_config(parse_run_config(raw), progress=False)
    assert row["status"] == "complete", row["reason"]
    return row["file"], sectioned(row["file"])


def test_stepped_loading_section_shows_stiffness_backlash_and_preload_loss(stepped_loading_run):
    """Truth of the simulated axis (DIGEST §3): k_m 81 N/µm, backlash 314 µm; preload loss
    at 20 %: 2 τ_p K_tr = 5320 N, the jump equals the backlash."""
    _, section = stepped_loading_run
    assert plot_sizes(section) == {
        "key time traces": (1000, 700), "single-motor loading and backlash": (1000, 450),
        "coupled loading per preload level: master displacement against load": (1000, 400)}
    stiffness = table(section, "drive-train stiffness (Eq. 3.26) and backlash")["master"]
    assert value(stiffness[0]) == pytest.approx(81.0, rel=0.02)
    assert value(stiffness[2]) == pytest.approx(314.0, abs=3.0)
    loss = table(section, "preload loss per level (Ch. 3.4.3)")["20"]
    assert value(loss[0]) == pytest.approx(5320.0, rel=0.05)
    assert value(loss[3]) == pytest.approx(314.0, rel=0.05)
    quality = {q.name: q for q in section.quality}
    assert quality["peak |force|"].ok and quality["preload levels analysed"].value == "1 of 1"
    assert section.headline.startswith("k_m 8")


@pytest.fixture(scope="module")
def closure_result():
    from feedbench.commands.closure import EXAMPLES, closure_report

    return closure_report(EXAMPLES / "sample_axis.csv", EXAMPLES / "bench_coulomb_viscous.toml")


def test_closure_section_shows_the_residual_before_and_after(closure_result):
    from feedbench.analysis.closure import report_dict

    section = closure_section(closure_result)
    data = report_dict(closure_result)
    assert plot_sizes(section) == {"held-out force residual before and after": (1000, 450)}
    effects = table(section, "findings")
    assert list(effects) == data["effects"] == ["ripple"]
    assert effects["ripple"][0] == "effect added"
    assert effects["ripple"][4] == (f"{100 * data['error_before']:.2f} → "
                                    f"{100 * data['error_after']:.2f} %")
    assert data["error_after"] < 0.5 * data["error_before"]
    quality = {q.name: q for q in section.quality}
    assert quality["held-out force NRMSE before → after"].ok
    replay = table(section, "closed-loop replay on the held-out data")
    assert value(replay["force NRMSE"][1]) < value(replay["force NRMSE"][0])


@pytest.fixture(scope="module")
def campaign(family_sections, stepped_loading_run, closure_result, tmp_path_factory):
    """Every family's section and the closure's in one report."""
    sections = [*family_sections.values(), stepped_loading_run[1],
                closure_section(closure_result)]
    path = tmp_path_factory.mktemp("campaign") / "campaign.html"
    path.write_text(render_html(sections, "every family"), encoding="utf-8")
    return path, sections


def test_campaign_report_holds_every_family_and_the_closure_offline(campaign):
    path, sections = campaign
    text = path.read_text(encoding="utf-8")
    images = re.findall(r"<img alt='[^']*' src='data:image/png;base64,([^']+)'>", text)
    # smfe: 5 plots, the sweep (spindle speed, force spectrogram) added to its section
    assert len(images) == sum(len(s.plots) for s in sections) == 3 + 2 + 3 + 3 + 5 + 3 + 1
    assert [png_size(base64.b64decode(data)) for data in images] == [
        png_size(plot.png) for s in sections for plot in s.plots]
    assert "http:" not in text and "https:" not in text and "<link" not in text
    assert text.count("<h2 ") == len(sections) and "closure: bench" in text


def test_write_report_takes_closure_results(closure_result, tmp_path):
    path = write_report([], tmp_path / "closure.html", "closure", closures=[closure_result])
    text = path.read_text(encoding="utf-8")
    assert text.count("<img") == 1 and "held-out force residual before and after" in text


@requires(CHROMIUM is not None, "headless Chromium is not installed")
def test_every_family_renders_in_headless_chromium(campaign, tmp_path):
    path, sections = campaign
    assert decoded_images(path, tmp_path) == [
        "x".join(map(str, png_size(plot.png))) for s in sections for plot in s.plots]


def drawn_figures(paths) -> list[tuple[str, object]]:
    """(experiment, matplotlib figure) of every plot the report draws for the recordings, as
    their module fixtures' `sectioned` drew them."""
    return [pair for path in paths for pair in DRAWN[str(path)]]


def points_in(box, ax) -> int:
    """How many finite points of the axes' lines and scatter markers lie in the display box."""
    count = 0
    for artist in [*ax.get_lines(), *ax.collections]:
        if hasattr(artist, "get_xydata"):
            xy, transform = np.asarray(artist.get_xydata(), float), artist.get_transform()
        else:
            xy, transform = (np.asarray(artist.get_offsets(), float).reshape(-1, 2),
                             artist.get_offset_transform())
        xy = transform.transform(xy[np.isfinite(xy).all(axis=1)])
        count += int(np.sum((xy[:, 0] >= box.x0) & (xy[:, 0] <= box.x1)
                            & (xy[:, 1] >= box.y0) & (xy[:, 1] <= box.y1)))
    return count


def test_every_familys_report_plots_keep_legends_off_the_data_and_axes_aligned(
        runs, sections, family_runs, family_sections, stepped_loading_run):
    """Every plot of every family's report section (issue 25): no data point under an axes
    legend or a frequency tag and no figure legend over an axes (display coordinates), and
    the axes of one column start and end at the same x (magnitude, phase and coherence line
    up)."""
    figures = drawn_figures([*runs[:2], *family_runs.values(),
                                          stepped_loading_run[0]])
    assert {name for name, _ in figures} == {
        "friction_sweep", "chirp", "impact_hammer", "sine_stream", "shaker_chirp",
        "closed_loop_bode", "smfe", "stepped_loading"}
    legends = tags = 0
    for name, figure in figures:
        renderer = figure.canvas.get_renderer()
        for legend in figure.legends:
            box = legend.get_window_extent(renderer)
            assert not any(box.overlaps(ax.get_window_extent(renderer)) for ax in figure.axes)
            legends += 1
        columns: dict[tuple[int, int], list] = {}
        for ax in figure.axes:
            if ax.get_legend() is not None:
                assert points_in(ax.get_legend().get_window_extent(renderer), ax) == 0, name
                legends += 1
            for tag in ax.texts:  # f_t, f_r, peak marks: above the axes, as the legends
                assert points_in(tag.get_window_extent(renderer), ax) == 0, (name, tag)
                tags += 1
            spec = ax.get_subplotspec()  # None: a colour bar
            if spec is not None:
                columns.setdefault((spec.colspan.start, spec.colspan.stop), []).append(ax)
        for axes in columns.values():
            edges = {(round(ax.get_position().x0, 4), round(ax.get_position().x1, 4))
                     for ax in axes}
            assert len(edges) == 1, (name, edges)
    assert legends >= 10 and tags >= 8


def test_a_legend_over_the_data_moves_out_of_the_axes():
    """`png_of` moves an axes legend that lies over a data point right of the axes (one that
    covers nothing stays); the plot beside it in its column keeps the same x extent."""
    from feedbench.views.sections import new_figure, png_of

    figure = new_figure(6.0, 4.0)
    top, bottom = figure.subplots(2, 1)
    x = np.linspace(0.0, 1.0, 200)
    top.plot(x, 0.5 + 0.0 * x, label="through the middle")
    top.legend(loc="center")
    bottom.plot(x, x, label="rising")
    bottom.legend(loc="upper left")
    renderer = figure.canvas.get_renderer()
    figure.draw_without_rendering()
    assert points_in(top.get_legend().get_window_extent(renderer), top) > 0
    png_of(figure)
    moved = top.get_legend().get_window_extent(renderer)
    assert points_in(moved, top) == 0 and moved.x0 >= top.get_window_extent(renderer).x1
    assert bottom.get_legend().get_window_extent(renderer).x1 < bottom.get_window_extent(
        renderer).x1  # covered nothing: stays inside
    assert top.get_position().x1 == pytest.approx(bottom.get_position().x1)


@pytest.mark.parametrize("x_scale", ["log", "linear"])
def test_frequency_tags_of_close_marks_do_not_overlap_and_stay_inside_the_figure(x_scale):
    """Five marks, four of them close (and one at the x axis' right end) on a column of
    panels laid out as the Bode plots are: drawn, no two tags (text or box) overlap, no box
    overlaps the figure's legend and every tag lies inside the figure."""
    from feedbench.views.sections import mark_frequencies, new_figure

    figure = new_figure(8.0, 5.0, layout="column")
    magnitude, phase = figure.subplots(2, 1, sharex=True)
    f = np.geomspace(1.0, 1000.0, 400)
    magnitude.loglog(f, 1.0 / np.abs(1.0 - (f / 120.0) ** 2 + 0.05j * f / 120.0), label="X")
    phase.plot(f, -np.degrees(np.arctan2(0.05 * f / 120.0, 1.0 - (f / 120.0) ** 2)))
    phase.set_xscale(x_scale)
    figure.legend(loc="outside upper center", fontsize=8)
    mark_frequencies((magnitude, phase), [(f"f_r {m:.1f} Hz", m)
                                          for m in (100.0, 104.0, 109.0, 115.0, 1000.0)])
    figure.canvas.draw()
    tags = magnitude.texts
    texts = [tag.get_window_extent() for tag in tags]
    boxes = [tag.get_bbox_patch().get_window_extent() for tag in tags]
    assert len(tags) == 5
    for extents in (texts, boxes):
        assert not [(i, j) for i, a in enumerate(extents) for j, b in enumerate(extents[:i])
                    if a.overlaps(b)]
    legend = figure.legends[0].get_window_extent()
    assert not any(box.overlaps(legend) for box in boxes)
    assert all(figure.bbox.x0 <= box.x0 and box.x1 <= figure.bbox.x1
               and figure.bbox.y0 <= box.y0 and box.y1 <= figure.bbox.y1 for box in texts)


def test_an_empty_shaded_area_covers_no_legend_and_a_kept_legend_draws_once():
    """An empty filled area (no windows to shade: its extent is infinite and inverted) does
    not count as data under a legend: the legend in a free corner stays, and the figure is
    laid out once and drawn once (a moved legend needs a second layout)."""
    from matplotlib.figure import Figure

    from feedbench.views import sections
    from feedbench.views.sections import new_figure, png_of

    figure = new_figure(6.0, 3.0)
    ax = figure.subplots()
    x = np.linspace(0.0, 1.0, 200)
    ax.plot(x, x**2, label="rising late")
    ax.fill_between([], [], [])
    ax.legend(loc="upper left")
    layouts, drawings = [], []
    with pytest.MonkeyPatch.context() as patch:
        lay_out, draw = sections.lay_out, Figure.draw
        patch.setattr(sections, "lay_out", lambda fig: layouts.append(lay_out(fig)))
        patch.setattr(Figure, "draw", lambda self, renderer: drawings.append(draw(self, renderer)))
        png_of(figure)
    assert ax.get_legend()._loc == 2 and ax.get_legend().get_bbox_to_anchor().x0 < ax.bbox.x1
    assert len(layouts) == 1 and len(drawings) == 1


FRF_PLOT = re.compile(r"compliance|mobility|receptance|loop:")
"""Titles of the plots that draw an FRF (each must have a phase panel)."""


def page_text(dom: str) -> str:
    """The text a reader sees in a dumped DOM: no tags, no style, no image data."""
    dom = re.sub(r"<style>.*?</style>|<img[^>]*>", " ", dom, flags=re.S)
    return re.sub(r"\s+", " ", re.sub(r"<[^>]+>", " ", dom))


def leakage_outside_band(text: str) -> list[str]:
    """Leakage findings ("leakage at n resonances in a–b Hz (f1, f2 Hz)") naming a frequency
    outside their band."""
    out = []
    for low, high, listed in re.findall(r"resonances? in ([\d.]+)–([\d.]+) Hz \(([^)]*) Hz\)",
                                        text):
        out += [f for f in listed.split(", ") if not float(low) <= float(f) <= float(high)]
    return out


@requires(CHROMIUM is not None, "headless Chromium is not installed")
def test_report_as_read_in_chromium_has_no_nan_warnings_in_band_and_bode_phases(
        sections, campaign, tmp_path):
    """The whole report (the bench core's runs, every family, a closure) as Chromium shows
    it: contents with a verdict per run linked to its section, no "nan" anywhere, leakage
    warnings only inside the swept band, a phase in every FRF plot; its first screen and
    the chirp's section saved as PNGs (FEEDBENCH_SCREENSHOT_DIR: kept for docs/img)."""
    every = [*sections, *campaign[1]]
    path = tmp_path / "report.html"
    path.write_text(render_html(every, "feedbench report"), encoding="utf-8")
    text = page_text(chromium("--virtual-time-budget=5000", "--dump-dom", path.as_uri()).stdout)
    assert not re.search(r"\bnan\b", text, re.IGNORECASE)
    assert all(verdict(s)[1] in text for s in every)
    assert verdict(every[2]) == (False, "3 of 6 checks failed: status, missing samples (gaps), "
                                        "analysis")  # the aborted run, too short to fit
    for s in every:
        for q in s.quality:
            lines = q.value.split("\n")
            assert len(set(lines)) == len(lines), (s.run_id, q.name)  # one line per finding
    assert not leakage_outside_band(text)
    frf_plots = [p.title for s in every for p in s.plots if FRF_PLOT.search(p.title)]
    assert len(frf_plots) == 8 and all("phase" in title for title in frf_plots)
    html_text = path.read_text(encoding="utf-8")
    assert all(f"href='#{'-'.join(s.run_id.split())}'" in html_text for s in every)
    chirp_page = tmp_path / "chirp.html"  # headless Chromium does not scroll to a #fragment
    chirp_page.write_text(render_html([every[1]], "chirp"), encoding="utf-8")
    for name, page in (("report.png", path), ("report_chirp.png", chirp_page)):
        chromium("--window-size=1200,1600", f"--screenshot={tmp_path / name}", page.as_uri())
        png = (tmp_path / name).read_bytes()
        assert png_size(png) == (1200, 1600) and len(png) > 50_000  # not a blank page
        if os.environ.get("FEEDBENCH_SCREENSHOT_DIR"):
            shutil.copy(tmp_path / name, os.path.join(os.environ["FEEDBENCH_SCREENSHOT_DIR"], name))


def test_closure_command_writes_its_report(tmp_path, capsys):
    """``feedbench closure DATA --model M --report FILE --json``: the JSON names the report,
    which holds the closure's section and its residual plot."""
    from feedbench.commands.cli import main
    from feedbench.commands.closure import EXAMPLES

    path = tmp_path / "closure.html"
    assert main(["closure", str(EXAMPLES / "sample_axis.csv"), "--model",
                 str(EXAMPLES / "bench_coulomb_viscous.toml"), "--report", str(path),
                 "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["report"] == str(path) and data["effects"] == ["ripple"]
    text = path.read_text(encoding="utf-8")
    assert ("<h2 id='closure:-bench:-rigid-body-+-Coulomb-+-viscous-friction'>closure: "
            "bench: rigid body + Coulomb + viscous friction — closure<a class='top' "
            "href='#contents'>contents</a></h2>") in text
    assert text.count("<img") == 1
