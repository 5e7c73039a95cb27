"""`feedbench demo`: the bench-core campaign on the simulated lab bench.

A friction sweep and a chirp run through the real drivers over a virtual CAN bus
against the simulated CiA 402 drive; each recording is analysed and the identified
values are printed beside the simulated world's true ones.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from feedbench.bench import EXPERIMENTS, parse_run_config, run_config
from feedbench.config import read_toml
from feedbench.report import write_report
from feedbench.sim_backends.world import world_truth

DEMO_EXPERIMENTS = ("friction_sweep", "chirp")
FRICTION_KEYS = ("F_c", "F_s", "v_s", "sigma")


def example_config(name: str) -> dict:
    """A packaged example config (`feedbench/examples/<name>.toml`) as a dict."""
    return read_toml(resources.files("feedbench") / "examples" / f"{name}.toml")


def _friction_comparison(analysis: dict, truth: dict) -> dict:
    out = {}
    for direction in ("positive", "negative"):
        identified = analysis[direction]["identified"]
        true = {k: truth["friction"][direction][k] for k in FRICTION_KEYS}
        out[direction] = {
            "identified": identified,
            "truth": true,
            "error_pct": {k: 100.0 * (identified[k] - true[k]) / true[k] for k in FRICTION_KEYS},
            "std": analysis[direction]["std"],
        }
    return out


def run_demo(directory: Path, quiet: bool = False) -> dict:
    """Run and analyse the demo campaign; returns the JSON-able summary."""
    from feedbench.cli import analyze_file

    runs, analyses, world = [], {}, {}
    for name in DEMO_EXPERIMENTS:
        raw = example_config(name)
        raw["bench"]["output_dir"] = str(directory)
        world = raw["bench"].get("world", world)
        row = run_config(parse_run_config(raw), progress=not quiet)
        runs.append({"id": row["id"], "file": row["file"], "status": row["status"],
                     "reason": row["reason"]})
        analyses[name] = analyze_file(row["file"])
    truth = world_truth(world)
    mobility = analyses["chirp"]
    report = write_report([r["file"] for r in runs], directory / "report.html",
                          title="feedbench demo campaign")
    return {
        "friction": _friction_comparison(analyses["friction_sweep"], truth),
        "servo_mobility": {
            "antiresonance_hz": mobility["antiresonance_hz"],
            "resonance_hz": mobility["resonance_hz"],
            "min_coherence_20_150hz": mobility["min_coherence_20_150hz"],
            "truth_f_t_hz": truth["f_t_hz"],
            "truth_f_r_hz": truth["f_r_hz"],
            "warnings": mobility["warnings"],
        },
        "runs": runs,
        "report": str(report),
    }


def _si_to_display(key: str, value: float) -> str:
    """Friction parameters in the units of Fig. 5.11."""
    if key == "v_s":
        return f"{value * 60e3:8.1f} mm/min"
    if key == "sigma":
        return f"{value / 60e3:8.5f} N·min/mm"
    return f"{value:8.2f} N"


def describe_demo(result: dict) -> str:
    """Human-readable summary of `run_demo`'s result."""
    lines = ["Friction (Andersson, Eq. 5.2): identified vs simulator truth"]
    for direction, comp in result["friction"].items():
        lines.append(f"  {direction}:")
        for k in FRICTION_KEYS:
            lines.append(
                f"    {k:<6s} {_si_to_display(k, comp['identified'][k])}   truth "
                f"{_si_to_display(k, comp['truth'][k])}   error {comp['error_pct'][k]:+6.2f} %"
            )
    m = result["servo_mobility"]
    lines += [
        "Servo mobility (motor force -> motor velocity, H1):",
        f"  anti-resonance {m['antiresonance_hz']:6.2f} Hz   (f_t, Eq. 4.13: {m['truth_f_t_hz']:.2f} Hz)",
        f"  resonance      {m['resonance_hz']:6.2f} Hz   (f_r, Eq. 4.14: {m['truth_f_r_hz']:.2f} Hz)",
        f"  min coherence 20-150 Hz: {m['min_coherence_20_150hz']:.4f}",
        "Runs:",
    ]
    lines += [f"  {r['id']}  {r['status']}  {r['file']}" for r in result["runs"]]
    lines.append(f"Report: {result['report']}")
    if "elapsed_s" in result:
        lines.append(f"Finished in {result['elapsed_s']:.1f} s")
    return "\n".join(lines)


def describe_analysis(result: dict) -> str:
    """Human-readable summary of one run's analysis."""
    lines = [f"{result['experiment']}: {result['run']['file']} ({result['run']['status']})"]
    module = EXPERIMENTS.get(result["experiment"])
    if hasattr(module, "describe"):
        lines += module.describe(result)
    elif result["experiment"] == "friction_sweep":
        for direction in ("positive", "negative"):
            fit = result[direction]
            lines.append(f"  {direction}: R² {fit['r_squared']:.5f}, rms {fit['rms_N']:.3f} N")
            for k in FRICTION_KEYS:
                lines.append(f"    {k:<6s} {_si_to_display(k, fit['identified'][k])}")
    else:
        lines += [f"  anti-resonance {result['antiresonance_hz']:.2f} Hz, "
                  f"resonance {result['resonance_hz']:.2f} Hz",
                  f"  min coherence 20-150 Hz {result['min_coherence_20_150hz']:.4f}"]
        lines += [f"  warning: {w}" for w in result["warnings"]]
    return "\n".join(lines)

