"""`feedbench demo`: the campaign on the simulated lab bench, every experiment family.

Each packaged example config (`feedbench/examples/`) runs exactly as `feedbench run` runs it:
through the real drivers over a virtual CAN bus (and Modbus TCP, the serial DAQ) against the
simulated devices. Each recording is analysed and summarised beside the simulated world's
truth or the thesis's figures; the runs go into one HTML report (`REPORT_AXES`).
`quick=True` shortens the runs (`QUICK_OVERRIDES`) so the campaign takes a few minutes.
"""

from __future__ import annotations

import time
from dataclasses import asdict
from importlib import resources
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from feedbench.bench import analyze_file, parse_run_config, run_config
from feedbench.config import ConfigError, read_toml
from feedbench.experiments.chirp import band_text, extrema_text
from feedbench.experiments.family import HEADLINE_SEPARATOR, family, headline, percent_error
from feedbench.experiments import stepped_loading
from feedbench.experiments.limits import LimitError
from feedbench.models.structure import POINT_DOF, ModalStructure
from feedbench.report import write_report
from feedbench.sim_backends import rack_pinion
from feedbench.sim_backends.smfe_world import build_process
from feedbench.sim_backends.world import world_truth
from feedbench.units import MM_PER_MIN, N_MIN_PER_MM, N_PER_UM

BENCH_CORE = ("friction_sweep", "chirp")
CAMPAIGN = (*BENCH_CORE, "closed_loop_bode", "impact_hammer", "shaker_chirp", "sine_stream",
            "smfe", "stepped_loading", "friction_sweep_rack_pinion")
"""The example configs the demo runs, in this order."""
FRICTION_KEYS = ("F_c", "F_s", "v_s", "sigma")

QUICK_OVERRIDES: dict[str, dict[str, dict[str, Any]]] = {
    # 13 feeds per direction with shorter plateaus (the drive settles in ≈ 50 ms): the
    # Eq. (5.2) fit still within 0.3 % of the truth. The chirp runs as configured.
    "friction_sweep": {"experiment": {"settle_s": 0.4, "measure_s": 0.3}},
    # 20–120 Hz in 2 Hz steps still brackets f_t and f_r: Eq. (4.20) gives both within 1.5 %.
    "closed_loop_bode": {"experiment": {"f_start_Hz": 20.0, "f_stop_Hz": 120.0,
                                        "f_step_Hz": 2.0, "cycles_per_frequency": 8,
                                        "settle_cycles": 4}},
    # idle, slow, at and above Fig. 5.12's 500 mm/min, 3 hits each: the FRF still changes
    # with feed and is invariant from 500 mm/min.
    "impact_hammer": {"experiment": {"feeds_mm_min": [0.0, 100.0, 500.0, 1000.0],
                                     "hits_per_feed": 3, "record_s": 1.5}},
    # 2 sweeps of 4 s over 30–70 Hz cover the resonance's half-power band (≈ 43–60 Hz)
    # with coherence > 0.99.
    "shaker_chirp": {"experiment": {"f_start_Hz": 30.0, "f_stop_Hz": 70.0, "duration_s": 4.0,
                                    "repetitions": 2}},
    # one feed and amplitude (the shaker chirp's), 40–60 Hz in 0.5 Hz steps: the resonance
    # for the comparison with the chirp's H1.
    "sine_stream": {"experiment": {"feeds_mm_min": [1000.0], "amplitudes_N": [20.0],
                                   "f_start_Hz": 40.0, "f_stop_Hz": 60.0, "f_step_Hz": 0.5}},
    # 8 s ramps (300 → 1500 rpm) give 6 Welch averages of 4 s: peaks within 5 % of the truth.
    "smfe": {"experiment": {"ramp_s": 8.0, "spindle_accel_rpm_s": 3000.0, "approach_mm": 0.3,
                            "return_feed_mm_min": 2500.0}},
    # the test's short version (the thesis's low and high preload, loading only, coarser
    # single-motor steps) with 0.1 s measure windows and 1 s set-ups, the load cell read
    # every 5th cycle (a Modbus read per cycle costs ⅓ of the wall time): k_m, k_s within
    # 1 %, backlash within 2 µm, both loss forces within 5 % of the thesis's.
    "stepped_loading": {"bench": {"load_cell_every": 5},
                        "experiment": {**stepped_loading.QUICK, "setup_s": 1.0,
                                       "measure_s": 0.1}},
    # 7 feeds instead of 13, shorter plateaus: the Eq. (5.2) fit within 1–3 %.
    "friction_sweep_rack_pinion": {"experiment": {
        "feeds_mm_min": [25, 50, 100, 200, 400, 800, 1500], "settle_s": 0.4, "measure_s": 0.3}},
}
"""`--quick`: per example, the keys of its tables that shorten it (and what it still shows)."""

REPORT_AXES = ("lab", "rack_pinion")
"""Axes whose recordings go into the report: `report.headroom` reads the single drive's
`force` channel, which a rack-and-pinion recording (`master.*`, `slave.*`) lacks (KeyError)."""

THESIS_INVARIANT_FEED_MM_MIN = 500.0
"""Fig. 5.12: the in-motion FRF becomes invariant above ≈ 500 mm/min (DIGEST §3)."""
THESIS_PRELOAD_LOSS_N = {4.0: 1100.0, 20.0: 5300.0, 25.0: 6600.0}
"""Ch. 3.4.3: preload lost at ≈ 1100 N (4 %), ≈ 5300 N (20 %), ≈ 6600 N (25 %)."""


def example_config(name: str) -> dict:
    """A packaged example config (`feedbench/examples/<name>.toml`) as a dict."""
    return read_toml(resources.files("feedbench") / "examples" / f"{name}.toml")


def campaign_config(name: str, directory: Path, quick: bool) -> dict:
    """The example `name` writing to `directory`, shortened by `QUICK_OVERRIDES` if `quick`."""
    raw = example_config(name)
    raw["bench"]["output_dir"] = str(directory)
    for table, keys in (QUICK_OVERRIDES.get(name, {}) if quick else {}).items():
        raw[table].update(keys)
    return raw


# -- truth of each example's simulated world (SI) ------------------------------------------


def rack_pinion_truth(world: Mapping[str, Any]) -> dict:
    """The rack-and-pinion world's truth, with the friction the summed motor forces show:
    the guideway's Eq. (5.2) plus both motors' viscous drag in σ."""
    axis = rack_pinion.build_simulator(world, 1e-3).axis
    friction = {d: asdict(getattr(axis.friction, d)) for d in ("positive", "negative")}
    for side in friction.values():
        side["sigma"] += 2.0 * axis.motor_damping
    return {**rack_pinion.world_truth(world), "friction": friction}


def example_truth(raw: Mapping[str, Any]) -> dict:
    """The truth behind an example config's simulated world (read by the demo only); with
    a milling world also its modal structure (tool rows 0–2, workpiece 3–5)."""
    world = raw["bench"].get("world", {})
    if raw["bench"].get("axis") == "rack_pinion":
        return rack_pinion_truth(world)
    truth = world_truth(world)
    if "milling" in world:
        truth["milling_structure"] = build_process(world["milling"])[0].structure
    return truth


# -- per-experiment summaries: JSON-able values in SI and a headline -----------------------


def _friction_comparison(analysis: dict, truth: dict) -> dict:
    out = {}
    for direction in ("positive", "negative"):
        identified = analysis[direction]["identified"]
        true = {k: truth["friction"][direction][k] for k in FRICTION_KEYS}
        out[direction] = {
            "identified": identified,
            "truth": true,
            "error_pct": {k: percent_error(identified[k], true[k]) for k in FRICTION_KEYS},
            "std": analysis[direction]["std"],
        }
    return out


def summarize_friction(analysis: dict, truth: dict) -> dict:
    """Eq. (5.2) per direction against the world's friction."""
    comparison = _friction_comparison(analysis, truth)
    worst = max(((abs(c["error_pct"][k]), k, d) for d, c in comparison.items()
                 for k in FRICTION_KEYS))
    pos, neg = comparison["positive"]["identified"], comparison["negative"]["identified"]
    return {**comparison, "max_abs_error_pct": worst[0],
            "headline": headline(f"Eq. 5.2: F_c {pos['F_c']:.1f} / {neg['F_c']:.1f} N, F_s "
                                 f"{pos['F_s']:.1f} / {neg['F_s']:.1f} N (+/−)",
                                 f"largest error vs truth {worst[0]:.2f} % ({worst[1]}, "
                                 f"{worst[2]})")}


def summarize_bode(analysis: dict, truth: dict) -> dict:
    """The open-loop mobility from the closed velocity loop by Eq. (4.20): f_t, f_r."""
    m = analysis["mobility"]
    return {"antiresonance_hz": m["antiresonance_hz"], "resonance_hz": m["resonance_hz"],
            "truth_f_t_hz": truth["f_t_hz"], "truth_f_r_hz": truth["f_r_hz"],
            "min_r_squared": analysis["min_r_squared"], "flagged": len(analysis["flagged"]),
            "headline": headline(extrema_text(m, truth, "Eq. 4.20: "),
                                 f"min R² {analysis['min_r_squared']:.4f}, "
                                 f"{len(analysis['flagged'])} points flagged")}


def _feed_text(feed: float | None) -> str:
    return "only the highest feed" if feed is None else f"{feed:g} mm/min"


def summarize_hammer(analysis: dict, truth: dict) -> dict:
    """The feed from which the quasi-FRF (Eq. 5.3) is invariant, against Fig. 5.12."""
    feeds = [{k: feed[k] for k in ("feed_mm_min", "peak_hz", "peak_compliance_m_N",
                                   "distance_to_highest_feed", "min_coherence", "hits_used")}
             for feed in analysis["feeds"]]
    idle, top = feeds[0], feeds[-1]
    invariant = analysis["invariant_from_mm_min"]
    return {"invariant_from_mm_min": invariant,
            "thesis_invariant_mm_min": THESIS_INVARIANT_FEED_MM_MIN,
            "truth_f_t_hz": truth["f_t_hz"], "feeds": feeds,
            "headline": headline(
                f"invariant from {_feed_text(invariant)} "
                f"(Fig. 5.12: ≈ {_feed_text(THESIS_INVARIANT_FEED_MM_MIN)})",
                f"peak {idle['peak_hz']:.1f} Hz at {_feed_text(idle['feed_mm_min'])} "
                f"(f_t {truth['f_t_hz']:.1f}), {top['peak_hz']:.1f} Hz at "
                f"{_feed_text(top['feed_mm_min'])}",
                "distance to the highest feed "
                + ", ".join(f"{f['distance_to_highest_feed']:.2f}" for f in feeds))}


def summarize_shaker_chirp(analysis: dict, _truth: dict) -> dict:
    """Tool-tip FRF per feed: compliance peak and coherence."""
    feeds = [{k: feed[k] for k in ("feed_mm_min", "peak_hz", "min_coherence", "n_averages")}
             for feed in analysis["feeds"]]
    return {"feeds": feeds, "headline": headline(*(
        f"{_feed_text(f['feed_mm_min'])}: compliance peak {f['peak_hz']:.2f} Hz, "
        f"min coherence {f['min_coherence']:.4f}" for f in feeds))}


def summarize_sine_stream(analysis: dict, _truth: dict) -> dict:
    """Quality gate and linearity of the streams (the chirp comparison is added later)."""
    streams = analysis["streams"]
    min_r2 = min(s["min_r_squared"] for s in streams)
    spread = analysis["amplitude_spread"]
    return {"streams": len(streams), "steps": sum(s["steps"] for s in streams),
            "steps_flagged": analysis["steps_flagged"], "min_r_squared": min_r2,
            "amplitude_spread": spread,
            "headline": headline(
                f"{sum(s['steps_used'] for s in streams)} steps used, "
                f"{analysis['steps_flagged']} flagged, min R² {min_r2:.4f}",
                "amplitude spread (Fig. 5.22) "
                + ", ".join(f"{v:.3f} at {k} mm/min" for k, v in spread.items()))}


def _truth_peak(structure: ModalStructure, row: int, f: np.ndarray) -> tuple[float, float]:
    """Largest analytic |Φ_ii| (m/N) over f's span on a 0.01 Hz grid, and its frequency."""
    fine = np.arange(f[0], f[-1], 0.01)
    magnitude = np.abs(structure.receptance(fine)[:, row, row])
    return float(magnitude.max()), float(fine[np.argmax(magnitude)])


def _smfe_peaks(analysis: dict, side: str, structure: ModalStructure, first_row: int) -> dict:
    """Each direct peak of one side beside the truth's largest |Φ_ii| in the band."""
    f = np.asarray(analysis["f_hz"])
    out = {}
    for row, (axis, peak) in enumerate(analysis[side]["peaks"].items(), start=first_row):
        truth_abs, truth_f = _truth_peak(structure, row, f)
        out[axis] = {**peak, "truth_abs_m_N": truth_abs, "truth_f_hz": truth_f,
                     "error_pct": percent_error(peak["abs_m_N"], truth_abs)}
    return out


def summarize_smfe(analysis: dict, truth: dict) -> dict:
    """Direct receptance peaks of Φ_tt and Φ_ww (Eq. 6.13) against the world's modal
    structure, condition number (6.14) against the planned C_th."""
    structure = truth["milling_structure"]
    sides = {"tool": _smfe_peaks(analysis, "tool", structure, 0)}
    if structure.n_dof > POINT_DOF:
        sides["workpiece"] = _smfe_peaks(analysis, "workpiece", structure, POINT_DOF)
    cond = analysis["condition_number"]
    return {**sides, "condition_number": cond, "warnings": analysis["warnings"],
            "headline": headline(
                *(_smfe_side_text(side, peaks) for side, peaks in sides.items()),
                f"condition number (Eq. 6.14) median {cond['median']:.1f}, max "
                f"{cond['max']:.1f} (planned C_th {cond['planned_C_th']:.2f})")}


def _smfe_side_text(side: str, peaks: Mapping[str, dict]) -> str:
    worst = max(abs(p["error_pct"]) for p in peaks.values())
    return (f"Φ_{side[0] * 2} peaks "
            + ", ".join(f"{axis * 2} {p['f_hz']:.2f} Hz" for axis, p in peaks.items())
            + f": |Φ| within {worst:.1f} % of the truth")


def _preload_level(test: dict, truth: dict) -> dict:
    """One coupled test's loss force beside the thesis's and 2 τ_p K_tr (Eq. 3.1)."""
    level = test["preload_pct"]
    keys = ("loss_force_N", "loss_force_from_torques_N", "jump_m", "error")
    return {"preload_pct": level, **{k: test.get(k) for k in keys},
            "thesis_loss_force_N": THESIS_PRELOAD_LOSS_N.get(level),
            "eq_3_1_loss_force_N": 2.0 * level / 100.0 * truth["rated_force"]}


def _loss_text(level: dict) -> str:
    if level["error"]:
        return f"{level['preload_pct']:g} %: {level['error']}"
    thesis = level["thesis_loss_force_N"]
    return (f"loss {level['loss_force_N']:.0f} N at {level['preload_pct']:g} % "
            + (f"(thesis ≈ {thesis:.0f})" if thesis else "(thesis: –)"))


def summarize_stepped_loading(analysis: dict, truth: dict) -> dict:
    """k_m, k_s (Eq. 3.26) and backlash against the world; preload-loss forces against the
    thesis (Ch. 3.4.3) and 2 τ_p K_tr (Eq. 3.1)."""
    k = {m: s["k_N_m"] for m, s in analysis["stiffness"].items()}
    backlash = {m: b["value_m"] for m, b in analysis["backlash"].items()}
    levels = [_preload_level(test, truth) for test in analysis["preload"]]
    return {"k_N_m": k, "truth_k_N_m": {m: truth[f"k_{m}"] for m in k},
            "backlash_m": backlash, "truth_backlash_m": {m: truth[f"backlash_{m}"]
                                                         for m in backlash},
            "preload": levels,
            "headline": headline(
                ", ".join(f"k_{m[0]} {v / N_PER_UM:.2f} N/µm ({truth[f'k_{m}'] / N_PER_UM:g})"
                          for m, v in k.items()),
                "backlash " + ", ".join(f"{m} {v * 1e6:.1f} µm ({truth[f'backlash_{m}'] * 1e6:g})"
                                        for m, v in backlash.items()),
                ", ".join(_loss_text(level) for level in levels))}


SUMMARIES: dict[str, Callable[[dict, dict], dict]] = {
    "friction_sweep": summarize_friction,
    "friction_sweep_rack_pinion": summarize_friction,
    "closed_loop_bode": summarize_bode,
    "impact_hammer": summarize_hammer,
    "shaker_chirp": summarize_shaker_chirp,
    "sine_stream": summarize_sine_stream,
    "smfe": summarize_smfe,
    "stepped_loading": summarize_stepped_loading,
}
"""Per example: summary(analysis, truth of its world) → key values in SI and a 'headline'."""


def sine_stream_vs_chirp(stream: dict, chirp: dict, feed: float, amplitude: float) -> dict:
    """Largest |a/F| deviation of the sine-stream from the shaker chirp's H1 in the
    half-power band of the resonance (|H| ≥ max/√2), at the chirp's feed and amplitude."""
    steps = next(s for s in stream["streams"]
                 if s["feed_mm_min"] == feed and s["amplitude_N"] == amplitude)
    h1 = next(f for f in chirp["feeds"] if f["feed_mm_min"] == feed)["frf"]
    f = np.asarray(steps["frf"]["f_hz"])
    sine = np.asarray(steps["frf"]["accelerance_abs"])
    band = sine >= sine.max() / np.sqrt(2.0)
    deviation = np.abs(sine[band] / np.interp(f[band], h1["f_hz"], h1["H1_abs"]) - 1.0)
    return {"feed_mm_min": feed, "amplitude_N": amplitude,
            "band_hz": [float(f[band].min()), float(f[band].max())],
            "n_points": int(band.sum()), "max_deviation": float(deviation.max())}


def _add_chirp_comparison(experiments: dict, configs: dict) -> None:
    """The sine-stream against the shaker chirp (Ch. 5.5.3), when both completed and share
    a feed."""
    pair = ("sine_stream", "shaker_chirp")
    if any(experiments.get(n, {}).get("run", {}).get("status") != "complete" for n in pair):
        return
    chirp = configs["shaker_chirp"]["experiment"]
    feeds = set(chirp["feeds_mm_min"]) & set(configs["sine_stream"]["experiment"]["feeds_mm_min"])
    if not feeds:
        return
    stream = experiments["sine_stream"]
    comparison = sine_stream_vs_chirp(stream["analysis"], experiments["shaker_chirp"]["analysis"],
                                      max(feeds), chirp["amplitude_N"])
    stream["summary"]["vs_shaker_chirp"] = comparison
    stream["headline"] = headline(
        stream["headline"],
        f"vs shaker-chirp H1 at {_feed_text(comparison['feed_mm_min'])}, "
        f"{comparison['amplitude_N']:g} N: {100 * comparison['max_deviation']:.2f} % in "
        f"{comparison['band_hz'][0]:g}–{comparison['band_hz'][1]:g} Hz (half-power band)")


# -- the campaign ------------------------------------------------------------------------


def _run_one(name: str, raw: dict, quiet: bool) -> tuple[dict, dict]:
    """Run one config and analyse it; the run record (with wall times) and the analysis.

    A further experiment whose config or plan is refused before anything moves is recorded
    as ``refused`` (no file) and the campaign goes on; the bench core's must run."""
    t0 = time.monotonic()
    try:
        row = run_config(parse_run_config(raw), progress=not quiet)
    except (ConfigError, LimitError) as exc:
        if name in BENCH_CORE:
            raise
        return {"id": "", "file": "", "status": "refused", "reason": str(exc),
                "elapsed_s": time.monotonic() - t0, "analysis_s": 0.0}, {}
    t1 = time.monotonic()
    analysis = analyze_file(row["file"])
    run = {"id": row["id"], "file": row["file"], "status": row["status"],
           "reason": row["reason"], "elapsed_s": t1 - t0, "analysis_s": time.monotonic() - t1}
    return run, analysis


def _entry(name: str, run: dict, analysis: dict, raw: dict) -> dict:
    """`experiments.<name>`: the run record, the headline, the summary against the truth of
    the example's world (a complete run only) and the whole analysis."""
    summary = ({"headline": f"{run['status']}: {run['reason']}"} if run["status"] != "complete"
               else family(analysis["experiment"]).summary(analysis, example_truth(raw)))
    return {"run": run, "headline": summary.pop("headline"), "summary": summary,
            "analysis": analysis}


def run_demo(directory: Path, quiet: bool = False, quick: bool = False) -> dict:
    """Run and analyse the campaign (`CAMPAIGN`; `quick`: `QUICK_OVERRIDES`); returns the
    JSON-able summary: the bench-core keys, then `experiments.<name>` per example."""
    configs = {name: campaign_config(name, directory, quick) for name in CAMPAIGN}
    experiments = {name: _entry(name, *_run_one(name, raw, quiet), raw)
                   for name, raw in configs.items()}
    _add_chirp_comparison(experiments, configs)
    truth = example_truth(configs["friction_sweep"])
    reported = [name for name, raw in configs.items() if experiments[name]["run"]["file"]
                and raw["bench"].get("axis", "lab") in REPORT_AXES]
    t0 = time.monotonic()
    report = write_report([experiments[name]["run"]["file"] for name in reported],
                          directory / "report.html", title="feedbench demo campaign")
    return {
        "friction": _friction_comparison(experiments["friction_sweep"]["analysis"], truth),
        "servo_mobility": experiments["chirp"]["summary"],
        "runs": [experiments[name]["run"] for name in BENCH_CORE],
        "report": str(report),
        "report_s": time.monotonic() - t0,
        "report_left_out": [name for name in configs if name not in reported],
        "quick": quick,
        "experiments": experiments,
    }


# -- text ----------------------------------------------------------------------------------


def _si_to_display(key: str, value: float) -> str:
    """Friction parameters in the units of Fig. 5.11."""
    if key == "v_s":
        return f"{value / MM_PER_MIN:8.1f} mm/min"
    if key == "sigma":
        return f"{value / N_MIN_PER_MM:8.5f} N·min/mm"
    return f"{value:8.2f} N"


def _bench_core_lines(result: dict) -> list[str]:
    lines = ["Friction (Andersson, Eq. 5.2): identified vs simulator truth"]
    for direction, comp in result["friction"].items():
        lines.append(f"  {direction}:")
        for k in FRICTION_KEYS:
            lines.append(
                f"    {k:<6s} {_si_to_display(k, comp['identified'][k])}   truth "
                f"{_si_to_display(k, comp['truth'][k])}   error {comp['error_pct'][k]:+6.2f} %"
            )
    m = result["servo_mobility"]
    return lines + [
        "Servo mobility (motor force -> motor velocity, H1):",
        f"  anti-resonance {m['antiresonance_hz']:6.2f} Hz   "
        f"(f_t, Eq. 4.13: {m['truth_f_t_hz']:.2f} Hz)",
        f"  resonance      {m['resonance_hz']:6.2f} Hz   "
        f"(f_r, Eq. 4.14: {m['truth_f_r_hz']:.2f} Hz)",
        f"  min coherence {band_text(m)}: {m['min_coherence']:.4f}",
    ]


def _experiment_lines(name: str, entry: dict) -> list[str]:
    """A header line per experiment, then each '; '-separated part of its headline."""
    run = entry["run"]
    return ([f"  {name} ({run['status']}, run {run['elapsed_s']:.1f} s + analysis "
             f"{run['analysis_s']:.1f} s)"]
            + [f"    {part}" for part in entry["headline"].split(HEADLINE_SEPARATOR)])


def describe_demo(result: dict) -> str:
    """Human-readable summary of `run_demo`'s result."""
    lines = _bench_core_lines(result)
    experiments = result.get("experiments", {})
    lines.append("Experiments" + (" (--quick)" if result.get("quick") else "") + ":")
    for name, entry in experiments.items():
        lines += _experiment_lines(name, entry)
    lines.append("Runs:")
    lines += [f"  {e['run']['id'] or name}  {e['run']['status']}  "
              f"{e['run']['file'] or e['run']['reason']}" for name, e in experiments.items()]
    left_out = result.get("report_left_out")
    lines.append(f"Report: {result['report']}"
                 + (f" (left out: {', '.join(left_out)})" if left_out else ""))
    if "elapsed_s" in result:
        lines.append(f"Finished in {result['elapsed_s']:.1f} s")
    return "\n".join(lines)


def describe_analysis(result: dict) -> str:
    """Human-readable summary of one run's analysis (its family's `describe`)."""
    return "\n".join([f"{result['experiment']}: {result['run']['file']} "
                      f"({result['run']['status']})", *family(result["experiment"]).describe(result)])
