"""Traces from elsewhere (CSV + sidecar, EMPS .mat) and the `feedbench closure` command."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from feedbench.analysis.closure import Trace
from feedbench.commands.cli import main
from feedbench.closure_io import read_csv_trace, read_emps, write_csv_trace
from feedbench.config import ConfigError
from feedbench.daq.recording import printable_json
from prerequisites import SHARED_DATA, requires

EXAMPLES = Path(__file__).resolve().parents[1] / "feedbench" / "examples" / "closure"
EMPS = SHARED_DATA / "emps"


def small_trace() -> Trace:
    t = np.arange(200) * 1e-3
    return Trace(t, 0.01 * np.sin(t), 5.0 * np.cos(t), 0.01 * np.sin(t + 0.01), 0.1 * t,
                 "small", 0.5e-3)


def test_csv_and_sidecar_round_trip_in_si(tmp_path):
    trace = small_trace()
    write_csv_trace(tmp_path / "a.csv", trace, {"controller": {"K_p_Ns_m": 100.0,
                                                               "K_v_1_s": 10.0}})
    back, controller = read_csv_trace(tmp_path / "a.csv")
    for channel in ("time", "position", "force", "reference", "excitation"):
        np.testing.assert_allclose(getattr(back, channel), getattr(trace, channel), rtol=1e-8,
                                   atol=1e-12)
    assert back.force_lag == pytest.approx(0.5e-3)
    assert controller == {"K_p_Ns_m": 100.0, "K_v_1_s": 10.0}


def test_csv_with_semicolons_decimal_commas_units_and_no_time_column(tmp_path):
    (tmp_path / "scope.csv").write_text("X [mm];F [kN]\n" + "\n".join(
        f"{0.5 * i:.1f};{0.001 * i:.3f}".replace(".", ",") for i in range(40)))
    trace, _ = read_csv_trace(tmp_path / "scope.csv", {
        "sample_rate_Hz": 500.0, "delimiter": ";", "decimal": ",",
        "columns": {"position": "X [mm]", "force": "F [kN]"},
        "units": {"position": "mm", "force": "kN"}})
    assert trace.sample_rate == pytest.approx(500.0)
    assert trace.position[10] == pytest.approx(5e-3)
    assert trace.force[10] == pytest.approx(10.0)
    assert trace.reference is None


@pytest.mark.parametrize("sidecar, message", [
    ({"columns": {"position": "x_mm"}}, "sidecar.columns.force: required"),
    ({"columns": {"position": "x_mm", "force": "nope"}}, "sidecar.columns.force: no column 'nope'"),
    ({"columns": {"position": "x_mm", "force": "F_N"}, "units": {"force": "lbf"}},
     "sidecar.units.force: unknown unit 'lbf'"),
    ({"columns": {"position": "x_mm", "force": "F_N"}, "colour": 1}, "sidecar.colour: unknown key"),
])
def test_sidecar_errors_name_the_field(tmp_path, sidecar, message):
    write_csv_trace(tmp_path / "a.csv", small_trace(), {})
    with pytest.raises(ConfigError, match=message):
        read_csv_trace(tmp_path / "a.csv", sidecar)


@requires((EMPS / "DATA_EMPS_PULSES.mat").exists(), f"EMPS data not in {EMPS}")
def test_emps_reader_scales_voltage_by_the_drive_gain():
    import scipy.io

    raw = scipy.io.loadmat(EMPS / "DATA_EMPS_PULSES.mat")
    trace = read_emps(EMPS / "DATA_EMPS_PULSES.mat")
    gain = float(raw["gtau"][0, 0])
    assert gain == pytest.approx(35.15, abs=0.01)
    np.testing.assert_allclose(trace.force, gain * raw["vir"].ravel())
    np.testing.assert_allclose(trace.excitation, gain * raw["pulses_N"].ravel())
    assert trace.sample_rate == pytest.approx(1000.0, rel=1e-4)


def _not_json(constant: str) -> None:
    raise AssertionError(f"{constant} is not JSON")


def test_printed_json_is_strict_json():
    """`--json` output: an unknown σ (NaN) or an infinite value is null, numpy values plain."""
    text = printable_json({"std": float("nan"), "peak": np.float64(np.inf),
                           "values": [1.0, np.array([np.nan, 2.0])], "n": np.int64(3)})
    assert json.loads(text, parse_constant=_not_json) == {
        "std": None, "peak": None, "values": [1.0, [None, 2.0]], "n": 3}


def test_command_finds_the_effect_hidden_in_the_sample_csv(tmp_path, capsys):
    status = main(["closure", str(EXAMPLES / "sample_axis.csv"), "--model",
                   str(EXAMPLES / "bench_coulomb_viscous.toml"), "--json",
                   "--plots", str(tmp_path)])
    assert status == 0
    data = json.loads(capsys.readouterr().out, parse_constant=_not_json)
    assert data["effects"] == ["ripple"]  # 6 N at a 5 mm pitch (sample_axis.toml's world)
    assert data["params"]["ripple"]["pitch_mm"]["value"] == pytest.approx(5.0, rel=0.01)
    assert data["error_after"] < 0.5 * data["error_before"]
    assert data["replay"]["after"]["force"] < data["replay"]["before"]["force"]
    assert {Path(p).name for p in data["plots"]} == {"closure_residual.png", "closure_frf.png"}
    assert all(Path(p).stat().st_size > 10_000 for p in data["plots"])


def test_the_frf_plot_shows_the_band_the_excitation_drives():
    """A 10–100 Hz chirp: the plotted band is the swept one (±2 bins of 1 Hz), capped at the
    closure's bandwidth; the DC bin and the unexcited 1–8 Hz are left out (issue 16)."""
    import scipy.signal

    from feedbench.closure_io import excited_band

    fs, n = 1000.0, 20_000
    t = np.arange(n) / fs
    excitation = scipy.signal.chirp(t, 10.0, t[-1], 100.0)
    f = np.fft.rfftfreq(1000, 1 / fs)
    shown = f[excited_band(excitation, fs, 1000, bandwidth=400.0)]
    assert 8.0 <= shown.min() <= 12.0 and 98.0 <= shown.max() <= 102.0
    assert f[excited_band(excitation, fs, 1000, bandwidth=50.0)].max() == 50.0


def test_command_reports_user_errors_in_one_line(tmp_path, capsys):
    (tmp_path / "m.toml").write_text('[terms.inertia]\nM_kg = "heavy"\n')
    status = main(["closure", str(EXAMPLES / "sample_axis.csv"), "--model",
                   str(tmp_path / "m.toml")])
    assert status == 2
    assert "terms.inertia.M_kg: must be a number" in capsys.readouterr().err


def test_command_rejects_a_trace_too_short_for_the_filter(tmp_path, capsys):
    t = np.arange(100) * 1e-3
    write_csv_trace(tmp_path / "short.csv", Trace(t, 0.01 * t, np.ones_like(t)), {})
    status = main(["closure", str(tmp_path / "short.csv"), "--model",
                   str(EXAMPLES / "bench_viscous.toml")])
    assert status == 2
    assert "too short to hold out 30% at a 150 Hz bandwidth" in capsys.readouterr().err
