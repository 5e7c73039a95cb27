"""Exchange formats: FRFs of every FRF family to UFF58 and back (read with pyuff itself),
`feedbench analyze FILE.uff`, and a recording's CSV export read by the closure."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import pyuff

from feedbench.bench import analyze_file
from feedbench.commands.cli import main
from feedbench.closure_io import read_csv_trace, read_recording
from feedbench.commands.exchange import HEADER_BYTES_FIELD, read_uff58, write_uff58
from feedbench.views.frfs import Dof, ExchangeFrf
from test_report import (
    K_P, SDOF, T_I, bode_steps, chirp_steps, friction_steps, hammer_steps, record,
    record_with_daq, shaker_chirp_steps, sine_stream_steps,
)

TIP_DAQ = {"impact_hammer": ("hammer_force", "acc_tool_x"),
           "sine_stream": ("actuator_force", "acc_tool_x"),
           "shaker_chirp": ("shaker_force", "acc_tool_x")}

EXPECTED = {  # family → per FRF: (numerator, denominator) specific data types and unit labels
    "chirp": [((11, "m/s"), (13, "N"))],
    "shaker_chirp": [((12, "m/s^2"), (13, "N"))],
    "sine_stream": [((12, "m/s^2"), (13, "N"))],
    "impact_hammer": [((8, "m"), (13, "N"))] * 2,
    "closed_loop_bode": [((11, "m/s"), (11, "m/s")), ((11, "m/s"), (13, "N"))],
}
EXPONENTS = {8: (1, 0), 11: (1, 0), 12: (1, 0), 13: (0, 1)}
"""UFF58 Addendum A: length and force unit exponents of each specific data type."""
RECORD_7 = 1e-5
"""Record 7 holds the abscissa minimum and increment (and ASCII 58 an uneven abscissa) in
E13.5: 6 significant digits."""


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    directory = tmp_path_factory.mktemp("exchange")
    paths = {name: directory / f"{name}.h5" for name in EXPECTED}
    record(paths["chirp"], "chirp", chirp_steps())
    record_with_daq(paths["impact_hammer"], {"type": "impact_hammer"}, hammer_steps(),
                    TIP_DAQ["impact_hammer"])
    record_with_daq(paths["sine_stream"], {"type": "sine_stream", "amplitudes_N": [20.0]},
                    sine_stream_steps(), TIP_DAQ["sine_stream"])
    record_with_daq(paths["shaker_chirp"], {"type": "shaker_chirp", "f_start_Hz": 20.0,
                                            "f_stop_Hz": 100.0}, shaker_chirp_steps(),
                    TIP_DAQ["shaker_chirp"])
    record(paths["closed_loop_bode"], "closed_loop_bode", bode_steps(),
           config={"type": "closed_loop_bode", "f_start_Hz": 20.0, "f_stop_Hz": 120.0},
           metadata={"drive_gains": {"K_p": K_P, "T_i": T_I}})
    return paths


def polar(block: dict, magnitude: str, phase: str) -> np.ndarray:
    return np.asarray(block[magnitude]) * np.exp(1j * np.asarray(block[phase]))


def analysed_frfs(result: dict) -> list[tuple[np.ndarray, np.ndarray, np.ndarray | None]]:
    """(f, complex H, coherence) of every FRF in an analysis result, as it prints them."""
    family = result["experiment"]
    if family == "chirp":
        frf = result["frf"]
        return [(frf["f_hz"], polar(frf, "H1_abs", "H1_phase_rad"), frf["coherence"])]
    if family == "shaker_chirp":
        return [(x["frf"]["f_hz"], polar(x["frf"], "H1_abs", "H1_phase_rad"),
                 x["frf"]["coherence"]) for x in result["feeds"]]
    if family == "impact_hammer":
        return [(x["frf"]["f_hz"], polar(x["frf"], "compliance_abs", "compliance_phase_rad"),
                 x["frf"]["coherence"]) for x in result["feeds"]]
    if family == "sine_stream":
        return [(x["frf"]["f_hz"], polar(x["frf"], "accelerance_abs", "accelerance_phase_rad"),
                 None) for x in result["streams"]]
    frf = result["frf"]
    return [(frf["f_hz"], polar(frf, "abs", "phase_rad"), None),
            (frf["f_hz"], polar(result["mobility"], "abs", "phase_rad"), None)]


@pytest.mark.parametrize("family", list(EXPECTED))
def test_export_writes_every_frf_as_uff58_that_pyuff_reads_back(runs, family, tmp_path, capsys):
    out = tmp_path / f"{family}.uff"
    assert main(["export", str(runs[family]), "--uff58", str(out)]) == 0
    assert capsys.readouterr().out.strip() == str(out)
    sets = pyuff.UFF(str(out)).read_sets()
    sets = sets if isinstance(sets, list) else [sets]
    expected = analysed_frfs(analyze_file(runs[family]))
    frf_sets = [s for s in sets if s["func_type"] == 4]
    assert len(frf_sets) == len(expected) == len(EXPECTED[family])
    assert [s["func_type"] for s in sets] == [t for _, _, c in expected
                                              for t in ((4, 6) if c is not None else (4,))]
    coherence_sets = iter(s for s in sets if s["func_type"] == 6)
    for dataset, (f, H, coherence), ends in zip(frf_sets, expected, EXPECTED[family]):
        assert dataset["binary"] == 1 and dataset["ord_data_type"] == 6
        assert dataset["abscissa_spec_data_type"] == 18
        assert dataset["abscissa_axis_units_lab"] == "Hz"
        for record_name, (spec, unit) in zip(("ordinate", "orddenom"), ends):
            assert dataset[f"{record_name}_spec_data_type"] == spec
            assert dataset[f"{record_name}_axis_units_lab"] == unit
            assert (dataset[f"{record_name}_len_unit_exp"],
                    dataset[f"{record_name}_force_unit_exp"]) == EXPONENTS[spec]
        assert dataset["rsp_dir"] == dataset["ref_dir"] == 1
        node = 2 if family in TIP_DAQ else 1  # the tool tip, or the motor
        assert dataset["rsp_node"] == dataset["ref_node"] == node
        assert dataset["id2"] == family and dataset["load_case_id"] == 0
        np.testing.assert_allclose(dataset["x"], f, rtol=RECORD_7, atol=0)
        assert np.array_equal(dataset["data"], H)  # bit-exact: 58b stores the doubles
        if coherence is not None:
            assert np.array_equal(next(coherence_sets)["data"], coherence)
    if family in TIP_DAQ:
        response, reference = TIP_DAQ[family][1], TIP_DAQ[family][0]
        assert all(s["id4"] == f"{response} / {reference}" for s in sets)


def frfs_on(f: np.ndarray) -> list[ExchangeFrf]:
    rng = np.random.default_rng(5)
    H = rng.normal(size=f.size) + 1j * rng.normal(size=f.size)
    tip = Dof("acc_tool_x", "tool_tip", 2, 1, "acceleration")
    force = Dof("shaker_force", "tool_tip", 2, 1, "force")
    return [ExchangeFrf("accelerance", "feed 0 mm/min", f, H, tip, force,
                        rng.uniform(size=f.size)),
            ExchangeFrf("receptance", "feed 500 mm/min", f, H / 3, tip, force)]


@pytest.mark.parametrize("f", [np.arange(164, 1229) * (1000 / 8192),  # the chirp's FFT bins
                               20.0 + 0.25 * np.arange(300)],           # a stepped sine
                         ids=["fft-bins", "steps"])
def test_uff58_round_trip_is_exact_on_an_even_grid(f, tmp_path):
    written = frfs_on(f)
    path = write_uff58(tmp_path / "frf.uff", written, "run-1", "25-Nov-26 12:00:00")
    assert [s["binary"] for s in pyuff.UFF(str(path)).read_sets()] == [1, 1, 1]  # 58b
    read = read_uff58(path)
    assert len(read) == 2
    for a, b in zip(written, read):
        assert np.array_equal(a.H, b.H)
        np.testing.assert_allclose(b.f, a.f, rtol=RECORD_7, atol=0)
        assert (b.response.channel, b.response.node, b.response.quantity) == \
            ("acc_tool_x", 2, "acceleration")
        assert (b.reference.channel, b.reference.quantity) == ("shaker_force", "force")
        assert (b.description, b.condition) == (a.description, a.condition)
    assert np.array_equal(read[0].coherence, written[0].coherence)
    assert read[1].coherence is None


def test_an_uneven_grid_is_ascii_to_12_digits(tmp_path):
    """A stepped sine with flagged steps: ASCII 58 (the binary uneven case wants a single-
    precision abscissa, which pyuff writes as doubles)."""
    f = np.delete(20.0 + 0.25 * np.arange(100), [7, 30, 31])
    written = frfs_on(f)
    path = write_uff58(tmp_path / "frf.uff", written)
    sets = pyuff.UFF(str(path)).read_sets()
    assert [(s["binary"], s["abscissa_spacing"], s["ord_data_type"]) for s in sets] == \
        [(0, 0, 6), (0, 0, 4), (0, 0, 6)]
    for a, b in zip(written, read_uff58(path)):
        np.testing.assert_allclose(b.H, a.H, rtol=5e-12)
        np.testing.assert_allclose(b.f, a.f, rtol=RECORD_7, atol=0)


def test_an_frf_of_one_line_is_left_out(tmp_path):
    one_line = replace(frfs_on(np.array([40.0]))[0], description="all steps flagged but one")
    read = read_uff58(write_uff58(tmp_path / "frf.uff", [one_line] + frfs_on(np.arange(1.0, 9.0))))
    assert [frf.description for frf in read] == ["accelerance", "receptance"]


def test_binary_header_counts_the_bytes_that_follow(tmp_path):
    """pyuff writes one value's bytes per point; readers that trust the count need all."""
    f = np.arange(1, 101) * 0.3
    data = write_uff58(tmp_path / "frf.uff", frfs_on(f)).read_bytes()
    offset, width = HEADER_BYTES_FIELD
    counts, start = [], 0
    for expected in (16 * f.size, 8 * f.size, 16 * f.size):  # H, coherence, H (even grid)
        counts.append(int(data[start + offset:start + offset + width]))
        header_end = start
        for _ in range(13):
            header_end = data.index(b"\n", header_end) + 1
        assert data[header_end + counts[-1]:header_end + counts[-1] + 7] == b"    -1\n"
        start = header_end + counts[-1] + 7
        assert counts[-1] == expected
    assert start == len(data)


def test_analyze_reads_a_uff58_frf_and_identifies_its_mode(runs, tmp_path, capsys):
    out = tmp_path / "hammer.uff"
    main(["export", str(runs["impact_hammer"]), "--uff58", str(out)])
    capsys.readouterr()
    assert main(["analyze", str(out), "--json"]) == 0
    frfs = json.loads(capsys.readouterr().out)["frfs"]
    for frf, structure in zip(frfs, (SDOF["idle"], SDOF["moving"])):
        assert (frf["form"], frf["units"]) == ("receptance", "m/N")
        mode, = frf["modes"]
        assert mode["f_n_hz"] == pytest.approx(structure.f_n[0], rel=0.01)
        assert mode["zeta"] == pytest.approx(structure.zeta[0], rel=0.12)
        assert mode["k_N_m"] == pytest.approx(structure.k[0], rel=0.02)
    assert main(["analyze", str(out)]) == 0
    text = capsys.readouterr().out
    assert "acc_tool_x (node 2, dir 1) / hammer_force (node 2, dir 1): receptance in m/N" in text
    assert "mode 60.0" in text and "mode 47.1" in text


def test_analyze_reads_another_tool_s_ascii_uff58_in_g_per_newton(tmp_path, capsys):
    """ASCII 58, accelerance in g/N, a mobility-style header as other tools write it."""
    f = np.arange(1, 801) * 0.25
    accelerance = -(2 * np.pi * f) ** 2 * SDOF["idle"].receptance(f)[:, 0, 0]
    dataset = pyuff.prepare_58(
        binary=0, func_type=4, rsp_node=7, rsp_dir=3, ref_node=7, ref_dir=3,
        data=accelerance / 9.80665, x=f, id1="Point 7 +Z / 7 +Z", rsp_ent_name="pt7",
        ref_ent_name="pt7", abscissa_spacing=1, abscissa_spec_data_type=18,
        ordinate_spec_data_type=12, orddenom_spec_data_type=13,
        ordinate_axis_units_lab="g", orddenom_axis_units_lab="N")
    path = tmp_path / "other.unv"
    pyuff.UFF(str(path)).write_sets(dataset, mode="overwrite")
    frf, = read_uff58(path)
    np.testing.assert_allclose(frf.H, accelerance, rtol=1e-10)
    assert main(["analyze", str(path), "--json"]) == 0
    mode, = json.loads(capsys.readouterr().out)["frfs"][0]["modes"]
    assert mode["f_n_hz"] == pytest.approx(60.0, rel=1e-4)
    assert mode["zeta"] == pytest.approx(0.05, rel=1e-3)
    assert mode["k_N_m"] == pytest.approx(2.0e6, rel=1e-3)


def test_csv_export_goes_straight_into_the_closure_reader(runs, tmp_path, capsys):
    out = tmp_path / "chirp.csv"
    assert main(["export", str(runs["chirp"]), "--csv", str(out)]) == 0
    assert (tmp_path / "chirp.toml").is_file()
    recorded = read_recording(runs["chirp"])
    exported, controller = read_csv_trace(out)
    assert controller == {}
    assert exported.force_lag == pytest.approx(recorded.force_lag, rel=1e-12)
    for channel in ("time", "position", "force", "reference", "excitation"):
        np.testing.assert_allclose(getattr(exported, channel), getattr(recorded, channel),
                                   rtol=1e-8, atol=1e-12, err_msg=channel)
    assert np.abs(recorded.force).max() > 10.0 and np.abs(recorded.excitation).max() > 10.0


def test_export_errors_are_one_line(runs, tmp_path, capsys):
    friction = tmp_path / "friction.h5"
    record(friction, "friction_sweep", friction_steps()[:3])
    furlongs = tmp_path / "furlongs.uff"
    pyuff.UFF(str(furlongs)).write_sets(pyuff.prepare_58(
        binary=0, func_type=4, rsp_node=1, rsp_dir=1, ref_node=1, ref_dir=1,
        data=np.ones(20, complex), x=np.arange(1.0, 21.0), abscissa_spacing=1,
        ordinate_spec_data_type=8, orddenom_spec_data_type=13,
        ordinate_axis_units_lab="furlong"), mode="overwrite")
    cases = [
        (["export", str(runs["chirp"])], "export: give --uff58 FILE and/or --csv FILE"),
        (["export", str(friction), "--uff58", str(tmp_path / "f.uff")],
         f"{friction}: a friction_sweep run has no FRF to export (FRFs come from chirp, "
         "closed_loop_bode, impact_hammer, shaker_chirp, sine_stream)"),
        (["export", str(runs["chirp"]), "--csv", str(tmp_path / "c.txt")],
         f"{tmp_path / 'c.txt'}: a CSV export must end in .csv (its sidecar is c.toml)"),
        (["analyze", str(tmp_path / "missing.uff")], f"{tmp_path / 'missing.uff'}: no such file"),
        (["analyze", str(furlongs)], "furlongs.uff dataset 1: ordinate units 'furlong' unknown "
         "(known: m, mm, um, µm, m/s, mm/s, m/s^2, m/s2, m/s², g, N, kN)"),
    ]
    for argv, line in cases:
        assert main(argv) == 2
        assert capsys.readouterr().err == f"feedbench: error: {line}\n"
    assert not (tmp_path / "f.uff").exists()
