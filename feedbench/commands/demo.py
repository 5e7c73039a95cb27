"""`feedbench demo`: the campaign on the simulated lab bench, every experiment family.

Each family's example config (feedbench's own in `feedbench/examples/`) runs exactly as
`feedbench run` runs it: through the real drivers over a virtual CAN bus (and Modbus TCP, the
serial DAQ) against the simulated devices. Each recording is analysed and summarised beside
the simulated world's truth (`example_truth`: its axis kind's, `axes.Axis.truth`) or the
thesis's figures; the runs go into one HTML report (those of axis kinds it draws,
`axes.Axis.reported`).
The campaign is what the registered families declare (`engine.family.Example`), so an
installed lab family joins it; `quick=True` shortens each run as its `Example.quick` says, so
the campaign takes a few minutes.

The runs are independent (each its own virtual bus, CPU and recording), so they go to a pool of
worker processes (`demo_workers`: one per CPU), each of which runs, analyses, summarises and
draws its example's report section while the other measures; the numbers are the same as one
after the other in this process (``workers=1``): lockstep virtual time.
"""

from __future__ import annotations

import gc
import multiprocessing
import os
import sys
import time
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Mapping

from feedbench.bench import analyze_file, parse_run_config, run_axis, run_config
from feedbench.config import ConfigError, read_toml
from feedbench.engine.family import HEADLINE_SEPARATOR, Example, examples, families, family
from feedbench.engine.limits import LimitError
from feedbench.daq.recording import open_recording
from feedbench.report import run_section, write_sections
from feedbench.views.sections import RunSection


def example_config(name: str) -> dict:
    """A packaged example config (`feedbench/examples/<name>.toml`) as a dict."""
    return read_toml(resources.files("feedbench") / "examples" / f"{name}.toml")


def campaign_config(example: str | Example, directory: Path, quick: bool) -> dict:
    """A family's `example` (or the one of that name) writing to `directory`, shortened as
    its `Example.quick` says if `quick`."""
    if isinstance(example, str):
        example = examples()[example]
    raw = example.quick_config() if quick else example.config()
    raw["bench"]["output_dir"] = str(directory)
    return raw


# -- truth of each example's simulated world (SI) ------------------------------------------


def example_truth(raw: Mapping[str, Any]) -> dict:
    """The truth behind a run config's simulated world (read by the demo and a campaign
    only): its axis kind's (`axes.Axis.truth`)."""
    return run_axis(raw).truth(raw["bench"].get("world", {}))


def core_parts(configs: Mapping[str, Mapping], experiments: Mapping[str, dict]) -> dict:
    """The bench core's parts of the demo's result: for each family that declares a
    `Experiment.demo_key`, its `demo_part` of its first example that completed."""
    parts: dict[str, Any] = {}
    for name, raw in configs.items():
        cls = family(raw["experiment"]["type"])
        if (cls.demo_key and cls.demo_key not in parts
                and experiments[name]["run"]["status"] == "complete"):
            parts[cls.demo_key] = cls.demo_part(experiments[name]["summary"])
    return parts


# -- the campaign ------------------------------------------------------------------------


def _run_one(example: Example, raw: dict, quiet: bool) -> tuple[dict, dict]:
    """Run one config and analyse it; the run record (with wall times) and the analysis.

    An example whose config or plan is refused before anything moves is recorded as
    ``refused`` (no file) and the campaign goes on, unless it is `Example.required`."""
    t0 = time.monotonic()
    try:
        row = run_config(parse_run_config(raw), progress=not quiet)
    except (ConfigError, LimitError) as exc:
        if example.required:
            raise
        return {"id": "", "file": "", "status": "refused", "reason": str(exc),
                "elapsed_s": time.monotonic() - t0, "analysis_s": 0.0}, {}
    t1 = time.monotonic()
    analysis = analyze_file(row["file"])
    run = {"id": row["id"], "file": row["file"], "status": row["status"],
           "reason": row["reason"], "elapsed_s": t1 - t0, "analysis_s": time.monotonic() - t1}
    return run, analysis


def _entry(run: dict, analysis: dict, truth: Mapping[str, Any] | None) -> dict:
    """`experiments.<name>`: the run record, the headline, the summary against the `truth`
    of the example's world (a complete run only) and the whole analysis."""
    summary = ({"headline": f"{run['status']}: {run['reason']}"} if run["status"] != "complete"
               else family(analysis["experiment"]).summary(analysis, truth))
    return {"run": run, "headline": summary.pop("headline"), "summary": summary,
            "analysis": analysis}


@dataclass(frozen=True)
class Measured:
    """One example done: its `experiments.<name>` entry and its report section (None: not
    in the report, `axes.Axis.reported`, or no recording)."""

    entry: dict
    section: RunSection | None


def measure(example: Example, raw: dict, quiet: bool = True) -> Measured:
    """Run one example's config, analyse it, summarise it against its world's truth and draw
    its report section (in a worker process or this one); the run record gains
    ``report_s``, the section's drawing time (s)."""
    run, analysis = _run_one(example, raw, quiet)
    truth = example_truth(raw) if run["status"] == "complete" else None
    t0 = time.monotonic()
    section = (run_section(open_recording(run["file"]), truth, analysis)
               if run["file"] and run_axis(raw).reported else None)
    run["report_s"] = time.monotonic() - t0
    return Measured(_entry(run, analysis, truth), section)


RUN_NAMES_AND_TIMES = ("id", "file", "report", "elapsed_s", "analysis_s", "report_s", "timing")
"""The keys of a demo summary that name a run (id, file, report file) or time it."""


def numbers_of(summary: Any) -> Any:
    """A demo summary or a part of it (as JSON) without `RUN_NAMES_AND_TIMES`: what two
    demos of the same configs share to the last digit (lockstep virtual time), however many
    workers ran them."""
    if isinstance(summary, dict):
        return {key: numbers_of(value) for key, value in summary.items()
                if key not in RUN_NAMES_AND_TIMES}
    return [numbers_of(value) for value in summary] if isinstance(summary, list) else summary


def demo_workers(n_examples: int) -> int:
    """Worker processes for `n_examples` runs: one per CPU this process may use (each
    simulated bench runs on one, `daq.clock.one_core`), at most one per run."""
    return max(1, min(len(os.sched_getaffinity(0)), n_examples))


def measure_all(chosen: Mapping[str, tuple[Example, dict]], workers: int,
                quiet: bool = False) -> dict[str, Measured]:
    """`measure` each example (name → (example, config)), by name in the given order; on
    `workers` > 1 forked worker processes (they inherit the imports, frozen: `gc.freeze`
    as each starts, so that their full collections leave the imports alone: 1.5 → 0.6 s
    of CPU in full collections over the campaign), the longest plans first
    (`plan_cycles`: the last to start is a short one), one line per finished run on
    stderr unless `quiet`."""
    if workers <= 1:
        return {name: measure(example, raw, quiet) for name, (example, raw) in chosen.items()}
    done: dict[str, Measured] = {}
    longest_first = sorted(chosen, key=lambda name: -plan_cycles(chosen[name][1]))
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork"),
                             initializer=gc.freeze) as pool:
        futures = {pool.submit(measure, *chosen[name]): name for name in longest_first}
        try:
            for future in as_completed(futures):
                done[futures[future]] = future.result()
                if not quiet:
                    print(_finished_line(futures, future, done), file=sys.stderr, flush=True)
        except BaseException:
            pool.shutdown(cancel_futures=True)
            raise
    return {name: done[name] for name in chosen}


def imports_for_workers() -> None:
    """What each run and its report section import on first use (the catalog's SQLAlchemy,
    matplotlib's Agg canvas: about 1 s), imported here once before the workers fork, which
    inherit it, rather than in each worker."""
    import matplotlib.backends.backend_agg  # noqa: F401
    import matplotlib.figure  # noqa: F401

    import feedbench.daq.catalog  # noqa: F401


def plan_cycles(raw: dict) -> int:
    """A run config's plan length in bench cycles (0: a config refused before it runs)."""
    try:
        return parse_run_config(raw).plan.n_cycles
    except (ConfigError, LimitError):
        return 0


def _finished_line(futures: Mapping[Future, str], future: Future,
                   done: Mapping[str, Measured]) -> str:
    """``[3/10] smfe: complete (run 6.1 s, analysis 0.2 s, report 0.9 s)``."""
    run = done[futures[future]].entry["run"]
    return (f"[{len(done)}/{len(futures)}] {futures[future]}: {run['status']} (run "
            f"{run['elapsed_s']:.1f} s, analysis {run['analysis_s']:.1f} s, report "
            f"{run['report_s']:.1f} s)")


def run_demo(directory: Path, quiet: bool = False, quick: bool = False,
             distribution: str | None = None, workers: int | None = None) -> dict:
    """Run and analyse the campaign: every example the families declare (`family.examples`;
    `distribution`: only that distribution's families; `quick`: each `Example.quick`) on
    `workers` processes (default `demo_workers`; 1: one after the other in this process).
    Returns the JSON-able summary: the bench core's keys (friction law, servo mobility;
    ``runs``: the required examples'), then `experiments.<name>` per example, and
    ``timing``: where the wall time went (`timing`)."""
    t0 = time.monotonic()
    declared = examples(distribution)
    configs = {name: campaign_config(example, directory, quick)
               for name, example in declared.items()}
    workers = workers or demo_workers(len(configs))
    if workers > 1:
        imports_for_workers()
    t1 = time.monotonic()
    measured = measure_all({name: (declared[name], configs[name]) for name in configs},
                           workers, quiet)
    t2 = time.monotonic()
    experiments = {name: m.entry for name, m in measured.items()}
    for cls in dict.fromkeys(family(raw["experiment"]["type"]) for raw in configs.values()):
        cls.demo_compare(experiments, configs)  # what the other runs show beside its own
    report = write_sections([m.section for m in measured.values() if m.section],
                            directory / "report.html", "feedbench demo campaign")
    return {
        **core_parts(configs, experiments),
        "runs": [experiments[name]["run"] for name, example in declared.items()
                 if example.required],
        "report": str(report),
        "report_left_out": [name for name, m in measured.items() if m.section is None],
        "quick": quick,
        "experiments": experiments,
        "timing": timing(experiments, workers, t1 - t0, t2 - t1, time.monotonic() - t2),
    }


def timing(experiments: Mapping[str, dict], workers: int, setup_s: float, runs_s: float,
           report_s: float) -> dict:
    """Where the demo's wall time went (s): `setup_s` (configs, before the first run),
    `runs_s` (the runs, their analyses and report sections, on `workers` processes),
    `report_s` (the chirp comparison and the report file); and the worker time (s) the
    runs' measuring, analyses and report sections took, summed over the runs."""
    runs = [e["run"] for e in experiments.values()]
    return {"workers": workers, "setup_s": setup_s, "runs_s": runs_s, "report_s": report_s,
            **{f"{part}_worker_s": sum(run[f"{part}_s"] for run in runs)
               for part in ("elapsed", "analysis", "report")}}


# -- text ----------------------------------------------------------------------------------


def _bench_core_lines(result: dict) -> list[str]:
    """Each family's lines of its part of the bench's core (`Experiment.demo_lines`)."""
    return [line for cls in families().values() if cls.demo_key in result
            for line in cls.demo_lines(result[cls.demo_key])]


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
              + "  ".join(filter(None, (e["run"]["file"], e["run"]["reason"])))
              for name, e in experiments.items()]
    left_out = result.get("report_left_out")
    lines.append(f"Report: {result['report']}"
                 + (f" (left out: {', '.join(left_out)})" if left_out else ""))
    if "elapsed_s" in result:
        lines += timing_lines(result["timing"], result["elapsed_s"])
    return "\n".join(lines)


def runs_not_complete(result: dict) -> list[str]:
    """``smfe: aborted: DeviceLinkError: …``: a line per run of `run_demo`'s result that did
    not complete, with its reason (what `--json` says on stderr beside its exit status 1)."""
    return [f"{name}: {e['run']['status']}: {e['run']['reason']}"
            for name, e in result["experiments"].items() if e["run"]["status"] != "complete"]


def timing_lines(timing: Mapping[str, float], elapsed_s: float) -> list[str]:
    """Where the wall time went (`timing`), and the worker time of the runs' parts."""
    return [f"Finished in {elapsed_s:.1f} s: set-up {timing['setup_s']:.1f} s, runs "
            f"{timing['runs_s']:.1f} s on {timing['workers']} worker(s), report "
            f"{timing['report_s']:.1f} s",
            f"  worker time: measuring {timing['elapsed_worker_s']:.1f} s, analysis "
            f"{timing['analysis_worker_s']:.1f} s, report sections "
            f"{timing['report_worker_s']:.1f} s"]


def describe_analysis(result: dict) -> str:
    """Human-readable summary of one run's analysis (its family's `describe`)."""
    return "\n".join([f"{result['experiment']}: {result['run']['file']} "
                      f"({result['run']['status']})", *family(result["experiment"]).describe(result)])
