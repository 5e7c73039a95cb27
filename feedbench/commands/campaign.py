"""`feedbench campaign`: a grid or a Monte-Carlo set of simulated runs as Dask tasks.

A campaign config is a run config (``[bench]``, ``[limits]``, ``[experiment]``) plus
``[campaign]`` (`CAMPAIGN_SCHEMA`): ``[campaign.grid]`` gives axes of values under dotted
keys into the run config (``"bench.gains.K_p_Ns_m" = [...]``; every combination runs once per
noise seed), ``[campaign.spread]`` relative spreads (1 σ, normal) of values of the run config
for a Monte-Carlo set (``"bench.world.friction.positive.F_c_N" = 0.1``; ``n`` draws per seed,
each with its own measurement-noise seed). Each task is one simulated run in a Dask worker
process (`run_task`: its own virtual CAN channel, `bench.run_config`), its family's analysis
and summary against the simulated world's truth (`demo.example_truth`); the rows go into the
run catalog with the campaign's parameters (``params.campaign``) and into one summary table
(JSON + CSV). A failed task is reported and the others kept.
"""

from __future__ import annotations

import csv
import itertools
import json
import logging
import signal
import threading
import time
import uuid
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

import numpy as np

from feedbench.bench import analyze_file, parse_run_config, run_axis, run_config
from feedbench.config import ConfigError, Field, one_of, positive, read_toml, validate_table
from feedbench.daq.recording import printable_json
from feedbench.commands.demo import example_truth
from feedbench.engine.family import families


def _seeds(value: list) -> str | None:
    if not value or not all(isinstance(v, int) and v >= 0 for v in value):
        return f": must be a non-empty list of integers ≥ 0 (got {value!r})"
    return None


CAMPAIGN_SCHEMA = {
    "kind": Field(str, "grid", "grid (every combination of [campaign.grid]) or montecarlo "
                  "(n draws of [campaign.spread] per seed)", one_of("grid", "montecarlo")),
    "seeds": Field(list, [0], "grid: the measurement-noise seeds each point runs with; "
                   "montecarlo: the seeds of the draws", _seeds),
    "n": Field(int, 10, "montecarlo: draws per seed", positive),
    "workers": Field(int, 2, "worker processes of the local Dask cluster (--workers)", positive),
    "grid": Field(dict, {}, "dotted run-config key → list of values"),
    "spread": Field(dict, {}, "montecarlo: dotted run-config key → relative spread (1 σ)"),
}


@dataclass(frozen=True)
class Task:
    """One run of a campaign: its index, the parameters it varies (dotted key → value) and
    its whole run config."""

    index: int
    params: dict[str, Any]
    raw: dict[str, Any]


@dataclass(frozen=True)
class Campaign:
    """A validated campaign: its id, [campaign] settings, family and tasks."""

    id: str
    settings: dict[str, Any]
    experiment: str
    tasks: list[Task]

    @property
    def output_dir(self) -> Path:
        """Where the runs, their catalog and the summary table go (the base ``bench.output_dir``)."""
        return Path(self.tasks[0].raw["bench"].get("output_dir", "runs"))


# -- the config ----------------------------------------------------------------------------


def dotted(table: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """A nested table as dotted key → value (``{"a": {"b": 1}}`` → ``{"a.b": 1}``); a quoted
    TOML key with dots stays as it is."""
    out = {}
    for key, value in table.items():
        if isinstance(value, dict):
            out.update(dotted(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def with_values(raw: Mapping[str, Any], values: Mapping[str, Any]) -> dict[str, Any]:
    """A copy of the run config `raw` with each dotted key set to its value."""
    out = json.loads(json.dumps(raw))
    for key, value in values.items():
        *tables, last = key.split(".")
        table = out
        for name in tables:
            table = table.setdefault(name, {})
            if not isinstance(table, dict):
                raise ConfigError(f"campaign: {key}: {name} is not a table in the run config")
        table[last] = value
    return out


def _base_value(raw: Mapping[str, Any], key: str) -> float:
    """The run config's number under a dotted key (what a spread varies)."""
    value = dotted(raw).get(key)
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        raise ConfigError(f"campaign.spread.{key}: the run config gives no number to spread "
                          f"(set it in the base config; got {value!r})")
    return float(value)


def _grid_points(grid: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Every combination of the grid's axes (one empty point without axes)."""
    for key, values in grid.items():
        if not isinstance(values, list) or not values:
            raise ConfigError(f"campaign.grid.{key}: must be a non-empty list of values "
                              f"(got {values!r})")
    return [dict(zip(grid, combination)) for combination in itertools.product(*grid.values())]


def _draws(settings: Mapping[str, Any], base: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Per seed and draw the spread values and the noise seed; grid: per seed its noise seed.

    A draw's random numbers come from ``numpy.random.default_rng([seed, k])``, so a run's
    parameters do not depend on which worker runs it or when."""
    noise = run_axis(base).noise_seed  # the key of the simulated axis's noise seed, if any
    if settings["kind"] == "grid":
        return [{noise: seed} if noise else {} for seed in settings["seeds"]]
    spread = dotted(settings["spread"])
    centre = {key: _base_value(base, key) for key in spread}
    draws = []
    for seed, k in itertools.product(settings["seeds"], range(settings["n"])):
        rng = np.random.default_rng([seed, k])
        draw = {key: centre[key] * (1.0 + float(spread[key]) * float(rng.standard_normal()))
                for key in sorted(spread)}
        draws.append({**draw, **({noise: int(rng.integers(2**31))} if noise else {})})
    return draws


def parse_campaign(raw: Mapping[str, Any]) -> Campaign:
    """Validate a campaign config (parsed TOML) and every run config it makes, before
    anything moves; raises `ConfigError` naming the field (and the run)."""
    if "campaign" not in raw:
        raise ConfigError("config.campaign: required table [campaign] is missing")
    settings = validate_table(raw["campaign"], CAMPAIGN_SCHEMA, "campaign")
    if settings["kind"] == "grid" and settings["spread"]:
        raise ConfigError("campaign.spread: only with kind = \"montecarlo\"")
    base = {key: value for key, value in raw.items() if key != "campaign"}
    points = _grid_points(dotted(settings["grid"]))
    values = [{**point, **draw} for point in points for draw in _draws(settings, base)]
    tasks = [Task(index, params, with_values(base, params)) for index, params in enumerate(values)]
    for task in tasks:
        try:
            parse_run_config(task.raw)
        except ConfigError as exc:
            raise ConfigError(f"campaign run {task.index} ({params_text(task.params)}): "
                              f"{exc}") from exc
    stamp = datetime.now(timezone.utc).strftime("%Y%m%d-%H%M%S")
    return Campaign(f"{stamp}-{uuid.uuid4().hex[:6]}", settings,
                    base["experiment"]["type"], tasks)


def load_campaign(path: str | Path) -> Campaign:
    """Read and validate a campaign config file."""
    return parse_campaign(read_toml(path))


def params_text(params: Mapping[str, Any]) -> str:
    """``K_p_Ns_m=9000, noise_seed=1``: the last part of each dotted key and its value."""
    return ", ".join(f"{key.rsplit('.', 1)[-1]}={value:.6g}" if isinstance(value, float)
                     else f"{key.rsplit('.', 1)[-1]}={value}" for key, value in params.items())


# -- one task, in a worker process ---------------------------------------------------------


def numbers(data: Mapping[str, Any], prefix: str = "") -> dict[str, float]:
    """The numbers (not lists, not text) of a nested result as dotted key → value."""
    return {key: float(value) for key, value in dotted(data, prefix).items()
            if isinstance(value, (int, float)) and not isinstance(value, bool)}


def run_task(task: Task, campaign_id: str) -> dict[str, Any]:
    """Run one task's simulated run on its own virtual CAN channel, analyse it with its
    family's analysis and summarise it against its world's truth (`demo.example_truth`);
    the catalog row carries the campaign's parameters. Returns the summary row (SI)."""
    raw = with_values(task.raw, {"bench.channel": f"campaign-{uuid.uuid4().hex}"})
    config = parse_run_config(raw)
    tag = {"campaign": {"id": campaign_id, "index": task.index, "params": task.params}}
    config = replace(config, plan=replace(config.plan, params={**config.plan.params, **tag}))
    t0 = time.monotonic()
    record = run_config(config, progress=False)
    row = summary_row(task.index, task.params, {**record, "experiment": config.plan.experiment},
                      example_truth(raw))
    return {**row, "elapsed_s": time.monotonic() - t0}


def summary_row(index: int, params: Mapping[str, Any], record: Mapping[str, Any],
                truth: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The summary row of a recorded run (`record`: id, file, status, reason, experiment):
    a complete one analysed by its family, its headline and results (numbers, SI) against
    the simulated world's `truth` (the family's `summary`) or, for a run on a real bench or
    one imported from another DAQ system (no truth), as the report's "what it measured"
    (the family's `headline`); a family without analysis says so."""
    row = {"index": index, "params": dict(params), "run_id": record["id"],
           "file": record["file"], "status": record["status"], "reason": record["reason"],
           "headline": "", "results": {}}
    family = families().get(record["experiment"])
    if record["status"] != "complete":
        return row
    if family is None:
        return {**row, "headline": f"no analysis for experiment {record['experiment']!r}"}
    analysis = analyze_file(record["file"])
    analysis.pop("run")
    if truth is None:
        return {**row, "headline": family.headline(analysis), "results": numbers(analysis)}
    summary = family.summary(analysis, truth)
    return {**row, "headline": summary.pop("headline"),
            "results": {**numbers(analysis), **numbers(summary)}}


def recorded_summary(files: Mapping[str, str]) -> dict[str, Any]:
    """The campaign summary (as `run_campaign`'s) of recorded runs, measured on a bench or
    imported from another DAQ system (`files`: as given → the recording), in that order:
    each analysed by its family (`summary_row`, no truth); its parameters its recorded
    ``[experiment]`` table (dotted, without ``type``); a run whose analysis fails is
    ``failed`` with why, the others kept."""
    from feedbench.daq.recording import open_recording

    t0 = time.monotonic()
    rows, kinds = [], []
    for index, file in enumerate(files.values()):
        recording = open_recording(file)
        kinds.append(recording.experiment)
        params = {key: value for key, value in
                  dotted(recording.config.get("experiment", {})).items() if key != "type"}
        record = {"id": recording.metadata.get("run_id", recording.path.stem), "file": file,
                  "status": recording.status, "reason": recording.reason,
                  "experiment": recording.experiment}
        try:
            rows.append(summary_row(index, params, record))
        except Exception as exc:  # one run's failing analysis fails its row, not the table
            why = str(exc) if isinstance(exc, ConfigError) else f"{type(exc).__name__}: {exc}"
            rows.append(summary_row(index, params, {**record, "status": "failed",
                                                    "reason": why}))
        rows[-1]["elapsed_s"] = None
        if "source_file" in recording.metadata:
            rows[-1]["imported_from"] = Path(recording.metadata["source_file"]).name
    stamp = datetime.now(timezone.utc).strftime("%Y%m%d-%H%M%S")
    return {"campaign": f"{stamp}-{uuid.uuid4().hex[:6]}-recorded",
            "experiment": ", ".join(dict.fromkeys(kinds)),
            "settings": {"runs": list(files)}, "scheduler": "recorded runs", "runs": rows,
            "complete": sum(row["status"] == "complete" for row in rows),
            "elapsed_s": time.monotonic() - t0}


def failed_row(task: Task, exc: BaseException) -> dict[str, Any]:
    """The summary row of a task that raised `exc`."""
    return {"index": task.index, "params": task.params, "run_id": "", "file": "",
            "status": "failed", "reason": f"{type(exc).__name__}: {exc}", "headline": "",
            "results": {}, "elapsed_s": None}


# -- the campaign on a Dask cluster --------------------------------------------------------


@contextmanager
def dask_client(scheduler: str | None, workers: int) -> Iterator[Any]:
    """A Dask client: of the cluster at `scheduler`, else of a local cluster of `workers`
    processes (one thread each: the simulated bench has its own threads), no dashboard, its
    scheduler's HTTP server on a free port (not 8787, which another cluster may hold: a
    warning). The local cluster's own log lines are kept off the terminal (a failed task is
    reported by its row)."""
    from dask.distributed import Client, LocalCluster

    with ExitStack() as stack:
        if scheduler is None:
            with _sigint_ignored():
                cluster = stack.enter_context(LocalCluster(
                    n_workers=workers, threads_per_worker=1, processes=True,
                    dashboard_address=None, silence_logs=logging.CRITICAL,
                    scheduler_kwargs={"dashboard_address": ":0"}))  # HTTP: a free port
            scheduler = cluster
        yield stack.enter_context(Client(scheduler))


@contextmanager
def _sigint_ignored() -> Iterator[None]:
    """SIGINT ignored while the local workers start: their processes inherit it, so a Ctrl-C
    at the terminal reaches this process only, which cancels the futures and stops them
    (else each worker prints its own KeyboardInterrupt traceback)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


Progress = Callable[[int, int, dict], None]


def run_campaign(campaign: Campaign, scheduler: str | None = None,
                 workers: int | None = None, progress: Progress | None = None) -> dict:
    """Run every task as a Dask future and collect the rows as they finish (`progress`
    after each: done, total, row). A task that raises is a ``failed`` row; Ctrl-C cancels
    the futures not finished and raises KeyboardInterrupt. Returns the summary (JSON-able)."""
    from dask.distributed import as_completed

    t0 = time.monotonic()
    rows = []
    with dask_client(scheduler, workers or campaign.settings["workers"]) as client:
        futures = {client.submit(run_task, task, campaign.id, pure=False,
                                 key=f"feedbench-campaign-{campaign.id}-{task.index}"): task
                   for task in campaign.tasks}
        try:
            for future in as_completed(futures):
                rows.append(failed_row(futures[future], future.exception())
                            if future.status == "error" else future.result())
                if progress:
                    progress(len(rows), len(futures), rows[-1])
        except KeyboardInterrupt:
            client.cancel(list(futures))
            raise
        where = client.scheduler.address
    return {"campaign": campaign.id, "experiment": campaign.experiment,
            "settings": campaign.settings, "scheduler": where,
            "runs": sorted(rows, key=lambda row: row["index"]),
            "complete": sum(row["status"] == "complete" for row in rows),
            "elapsed_s": time.monotonic() - t0}


def progress_line(done: int, total: int, row: dict) -> str:
    """One line per finished task: ``[3/6] run 2 (K_p_Ns_m=9000): complete 3.1 s``."""
    took = f" {row['elapsed_s']:.1f} s" if row["elapsed_s"] is not None else ""
    why = f" ({row['reason']})" if row["reason"] else ""
    return (f"[{done}/{total}] run {row['index']} ({params_text(row['params'])}): "
            f"{row['status']}{took}{why}")


# -- the summary table ---------------------------------------------------------------------


def table_columns(summary: Mapping[str, Any]) -> tuple[list[str], list[str]]:
    """The parameter and result columns of the summary table, in first-seen order."""
    params = list(dict.fromkeys(k for row in summary["runs"] for k in row["params"]))
    results = list(dict.fromkeys(k for row in summary["runs"] for k in row["results"]))
    return params, results


def write_summary(summary: Mapping[str, Any], directory: Path) -> tuple[Path, Path]:
    """``campaign-<id>.json`` (the whole summary) and ``.csv`` (a row per run: index,
    status, run id, parameters, results, reason) in `directory`; returns both paths."""
    directory.mkdir(parents=True, exist_ok=True)
    stem = directory / f"campaign-{summary['campaign']}"
    json_path, csv_path = stem.with_suffix(".json"), stem.with_suffix(".csv")
    json_path.write_text(printable_json(dict(summary)) + "\n", encoding="utf-8")
    params, results = table_columns(summary)
    with csv_path.open("w", newline="", encoding="utf-8") as file:
        writer = csv.writer(file)
        writer.writerow(["index", "status", "run_id", *params, *results, "reason"])
        for row in summary["runs"]:
            writer.writerow([row["index"], row["status"], row["run_id"],
                             *(row["params"].get(k, "") for k in params),
                             *(row["results"].get(k, "") for k in results), row["reason"]])
    return json_path, csv_path


def describe_campaign(summary: Mapping[str, Any]) -> str:
    """The compact table: one line per run (index, parameters, status, headline or reason)
    and a last line with the counts and the wall time."""
    params, _ = table_columns(summary)
    header = ["#", *(key.rsplit(".", 1)[-1] for key in params), "status", "result"]
    cells = [[str(row["index"]),
              *(f"{row['params'][k]:.6g}" if isinstance(row["params"].get(k), float)
                else str(row["params"].get(k, "")) for k in params),
              row["status"], row["headline"] or row["reason"]] for row in summary["runs"]]
    widths = [max(len(line[i]) for line in [header, *cells]) for i in range(len(header) - 1)]
    lines = ["  ".join(cell.ljust(width) for cell, width in zip(line, widths)) + "  " + line[-1]
             for line in [header, *cells]]
    n = len(summary["runs"])
    return "\n".join([*lines, f"{summary['experiment']} campaign {summary['campaign']}: "
                      f"{summary['complete']} of {n} runs complete in "
                      f"{summary['elapsed_s']:.1f} s on {summary['scheduler']}"])
