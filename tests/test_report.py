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

import numpy as np
import pytest
import scipy.signal

from feedbench.daq.recorder import Recorder
from feedbench.daq.recording import open_recording
from feedbench.experiments import chirp
from feedbench.experiments.runner import CHANNELS, UNITS
from feedbench.models.friction import AnderssonFriction
from feedbench.report import run_section, write_report
from feedbench.units import MM_PER_MIN

CYCLE_S = 1e-3
LIMITS = {"position_mm": [-250.0, 250.0], "velocity_mm_min": 3000.0, "force_N": 1500.0}
LAW = {1: AnderssonFriction(44.2, 84.0, 387.4 * MM_PER_MIN, 0.0028 * 60e3),
       -1: AnderssonFriction(38.7, 88.0, 421.0 * MM_PER_MIN, 0.0025 * 60e3)}
COLUMN = {name: i for i, name in enumerate(CHANNELS)}


def record(path, experiment: str, steps, status: str = "complete", reason: str = "",
           skip_after: int | None = None) -> None:
    """A recording of `steps` = [(label, kind, info, rows n × CHANNELS)], as the runner
    writes it (one JSON segment event per step); `skip_after` drops 5 cycles there."""
    metadata = {"experiment": experiment, "cycle_s": CYCLE_S, "run_id": path.stem,
                "config": {"limits": LIMITS, "experiment": {"type": experiment}}}
    with Recorder(path, CHANNELS, UNITS, metadata) as recorder:
        cycle = 1
        for label, kind, info, rows in steps:
            recorder.event(cycle, "segment", json.dumps({"label": label, "kind": kind, **info}))
            cycles = cycle + np.arange(len(rows))
            if skip_after is not None and cycle <= skip_after < cycles[-1]:
                cycles[cycles >= skip_after] += 5
            recorder.append_block(cycles, rows)
            cycle = int(cycles[-1]) + 1
        if status != "complete":
            recorder.close(status, reason)


def rows_of(n: int, **columns) -> np.ndarray:
    rows = np.zeros((n, len(CHANNELS)))
    for name, values in columns.items():
        rows[:, COLUMN[name]] = values
    return rows


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
    """Three sweeps as the chirp experiment records them: a 10–200 Hz chirp, then a tail
    with no excitation in which the response rings down (each sweep starts at rest)."""
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
                   rows_of(force.size, force=force + noise, velocity=velocity,
                           force_offset=force))]
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


@pytest.fixture(scope="module")
def sections(runs):
    return [run_section(open_recording(path)) for path in runs]


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
        "key time traces", "servo mobility (H1, Welch) with coherence",
        "key time traces"]
    sizes = [png_size(base64.b64decode(data)) for _, data in images]
    assert sizes == [(1000, 700), (800, 450), (1000, 700), (800, 550), (1000, 700)]
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


def test_chirp_section_finds_anti_resonance_and_resonance(runs, sections):
    section = sections[1]
    mobility = table(section, "servo mobility")
    f_t, f_r = true_extrema()
    assert value(mobility["anti-resonance f_t (Eq. 4.13)"][0]) == pytest.approx(f_t, abs=0.5)
    assert value(mobility["resonance f_r (Eq. 4.14)"][0]) == pytest.approx(f_r, abs=0.5)
    assert mobility["sweeps averaged"] == ("3",)
    coherence = next(q for q in section.quality if q.name == "min coherence in the band")
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


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def chromium(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu",
                           "--hide-scrollbars", *args], capture_output=True, text=True,
                          timeout=120)


@pytest.mark.skipif(CHROMIUM is None, reason="headless Chromium is not installed")
def test_report_renders_in_headless_chromium_with_every_image_decoded(report, tmp_path):
    probe = tmp_path / "probe.html"
    probe.write_text(report.read_text(encoding="utf-8").replace(
        "</body>", "<script>window.addEventListener('load', () => {document.body.dataset"
        ".decoded = [...document.images].filter(i => i.complete && i.naturalWidth > 0)"
        ".map(i => i.naturalWidth + 'x' + i.naturalHeight).join(' ');});</script></body>"),
        encoding="utf-8")
    dom = chromium("--virtual-time-budget=5000", "--dump-dom", probe.as_uri()).stdout
    decoded = re.search(r'data-decoded="([^"]*)"', dom).group(1).split()
    assert decoded == ["1000x700", "800x450", "1000x700", "800x550", "1000x700"]
    shot = tmp_path / "report.png"
    chromium("--window-size=1200,1600", f"--screenshot={shot}", report.as_uri())
    width, height = png_size(shot.read_bytes())
    assert (width, height) == (1200, 1600)
    if os.environ.get("FEEDBENCH_SCREENSHOT_DIR"):
        shutil.copy(shot, os.path.join(os.environ["FEEDBENCH_SCREENSHOT_DIR"], "report.png"))
