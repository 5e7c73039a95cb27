"""The `feedbench` command and its sub-commands (`build_parser`; ``feedbench --help`` names
every one).

Errors the user can fix (a config key, a limit, an unknown run, a file that is not what it
should be) print one line ``feedbench: error: <file or field>: <reason>`` and exit with
status 2, before anything moves; any other failure prints one line naming its type (status 2),
Ctrl-C outside a run one line (status 130). ``--debug`` shows the traceback instead. Output
piped into a reader that stops early (``feedbench runs | head``) ends quietly, as Unix tools
do (status 141).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import math
import os
import select
import signal
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

from feedbench.config import ConfigError
from feedbench.engine.limits import LimitError
from feedbench.gui import DisplayError, require_display
from feedbench.protocols.address import split_address

USER_ERRORS = (ConfigError, LimitError, FileNotFoundError, DisplayError)
INTERRUPTED = 130
"""Exit status after Ctrl-C outside a run (128 + SIGINT, as a shell reports it)."""
STDOUT_CLOSED = 128 + signal.SIGPIPE
"""Exit status when the reader of the output went away (141, as a shell reports a tool that
SIGPIPE ended)."""


class Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line (status 2)."""

    def error(self, message: str) -> None:
        """Print ``<prog>: error: <message>`` and exit with status 2."""
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _print_json(data: dict) -> None:
    from feedbench.daq.recording import printable_json

    print(printable_json(data))


def cmd_run(args: argparse.Namespace) -> int:
    """Validate a config, run it, print the run's id, file and status."""
    from feedbench.bench import load_run_config, run_config

    config = load_run_config(args.config)
    if args.live:
        from feedbench.gui.live_window import bench_session

        row = bench_session(config, progress=not args.json, catalog=args.catalog,
                            store=args.store).exec()
    else:
        row = run_config(config, progress=not args.json, catalog=args.catalog, store=args.store)
    if args.json:
        _print_json(row)
    else:
        print(f"{row['id']}  {row['status']}  {row['file']}"
              + (f"  ({row['reason']})" if row["reason"] else ""))
    return 0 if row["status"] == "complete" else 1


def cmd_runs(args: argparse.Namespace) -> int:
    """List the run catalog (the runs the filters select), the runs left unfinished by a
    process that has ended settled first (`Catalog.reconcile`: crashed, samples counted from
    the file)."""
    from feedbench.daq.run_filter import Condition, RunFilter, day_bound

    catalog = open_catalog(args.dir, args.catalog)
    catalog.reconcile()
    where = RunFilter(
        bench=args.bench, experiment=args.family, status=args.status,
        since=args.since and day_bound(args.since, "--since"),
        until=args.until and day_bound(args.until, "--until", end=True),
        where=tuple(map(Condition.parse, args.where)))
    if args.json:
        _print_json({"runs": [vars(r) for r in catalog.list(where=where)]})
        return 0
    listed = 0
    for listed, r in enumerate(catalog.lines(where=where), 1):  # one line at a time
        print(f"{r.id:<42s} {r.status:<9s} {r.n_samples or 0:>8d}  {r.file}"
              + (f"  ({r.reason})" if r.reason else ""))
    if not listed:
        print(f"no runs in {catalog.name}")
    return 0


def cmd_catalog_rebuild(args: argparse.Namespace) -> int:
    """Recreate the run catalog from the recordings in the output directory."""
    catalog = open_catalog(args.dir, args.catalog)
    added, skipped = catalog.rebuild()
    for reason in skipped:
        print(f"skipped {reason}")
    print(f"{catalog.name}: rebuilt from {added} recording(s)")
    return 0


def cmd_catalog_sync(args: argparse.Namespace) -> int:
    """Register in the catalog the runs recorded in the output directory while it was
    unreachable (`Catalog.sync`), then retry the store copies still pending (with --store:
    copy there the recordings without one; `daq.store.sync_copies`)."""
    from feedbench.daq.store import sync_copies

    catalog = open_catalog(args.dir, args.catalog)
    added, settled = catalog.sync()
    print(f"{catalog.name}: {len(added)} run(s) registered, {len(settled)} settled from "
          "their recordings")
    copied, failed = sync_copies(catalog, args.store)
    for line in failed:
        print(line)
    if copied or failed:
        print(f"{len(copied)} recording(s) copied to the store, {len(failed)} still pending")
    return 1 if failed else 0


def resolve_run(run: str, directory: str, catalog: str = "") -> str:
    """A recording path from a file path or a run id (or unique id prefix) in the catalog
    (`open_catalog`): its local file, else its copy in the lab's store
    (`daq.store.recording_file`)."""
    from feedbench.daq.store import recording_file

    if Path(run).is_file() or Path(run).suffix.lower() in (".h5", ".hdf5"):
        return run
    return recording_file(open_catalog(directory, catalog).get(run))


def output_directory(directory: str | Path) -> Path:
    """`--dir` as a path; an existing file there raises `ConfigError`."""
    path = Path(directory)
    if path.exists() and not path.is_dir():
        raise ConfigError(f"--dir: {path} is not a directory")
    return path


def open_catalog(directory: str | Path, url: str = ""):
    """The run catalog of an output directory: `url` (``--catalog``), else
    ``$FEEDBENCH_CATALOG``, else its ``catalog.sqlite`` (`daq.catalog.open_catalog`; a corrupt
    file is moved aside and rebuilt); one that cannot be read or written raises
    `ConfigError`."""
    from feedbench.daq import catalog

    try:
        return catalog.open_catalog(output_directory(directory), url)
    except OSError as exc:
        raise ConfigError(f"{exc.filename}: cannot open the run catalog ({exc.strerror})"
                          ) from None


def cmd_analyze(args: argparse.Namespace) -> int:
    """Analyse one recorded run, or the FRFs of a UFF58 file."""
    from feedbench.commands.exchange import UFF_SUFFIXES, analyze_uff58, describe_uff58

    if Path(args.run).suffix.lower() in UFF_SUFFIXES:
        result, describe = analyze_uff58(args.run), describe_uff58
    else:
        from feedbench.bench import analyze_file
        from feedbench.daq.importers import is_foreign
        from feedbench.daq.importers.mapping import imported_copy
        from feedbench.commands.demo import describe_analysis

        if args.mapping and not is_foreign(args.run):
            raise ConfigError("--mapping: for the recordings of other DAQ systems (.mf4, .tdms)")
        if is_foreign(args.run):  # another DAQ system's file: analysed as imported
            with imported_copy(args.run, args.mapping) as path:
                result = analyze_file(path)
            result["run"]["file"] = args.run
        else:
            result = analyze_file(resolve_run(args.run, args.dir, args.catalog))
        describe = describe_analysis
    if args.json:
        _print_json(result)
    else:
        print(describe(result))
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    """Export a run: its FRFs as UFF58, its drive channels as CSV + closure sidecar."""
    from feedbench.commands import exchange
    from feedbench.bench import analyze_file

    if not (args.uff58 or args.csv):
        raise ConfigError("export: give --uff58 FILE and/or --csv FILE")
    path = resolve_run(args.run, args.dir, args.catalog)
    if args.uff58:
        print(exchange.export_uff58(path, args.uff58, analyze_file))
    if args.csv:
        print(exchange.export_csv(path, args.csv))
    return 0


def cmd_live(args: argparse.Namespace) -> int:
    """Replay a recorded run in the live window (no display: one line, before Qt loads)."""
    path = resolve_run(args.run, args.dir, args.catalog)
    require_display()
    from feedbench.gui.live_window import replay_session

    replay_session(path, speed=args.speed, span_s=args.span).exec()
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    """Write the HTML report of recorded runs and print its path."""
    from feedbench.daq.importers import is_foreign
    from feedbench.daq.importers.mapping import imported_copy
    from feedbench.report import write_report

    output = Path(args.output or Path(args.dir) / "report.html")
    if output.is_dir():
        raise ConfigError(f"-o: {output} is a directory (give the report's file name)")
    if args.mapping and not any(map(is_foreign, args.runs)):
        raise ConfigError("--mapping: for the recordings of other DAQ systems (.mf4, .tdms)")
    with contextlib.ExitStack() as stack:  # another DAQ system's file: reported as imported
        files = [str(stack.enter_context(imported_copy(run, args.mapping))) if is_foreign(run)
                 else resolve_run(run, args.dir, args.catalog) for run in args.runs]
        print(write_report(files, output))
    return 0


def cmd_import(args: argparse.Namespace) -> int:
    """Import another DAQ system's recording (MDF4, TDMS) as a feedbench recording in the
    output directory, catalogued like a measured run; print its id, file and status."""
    from feedbench.daq.importers.mapping import import_recording, load_run

    run = load_run(args.file, args.mapping)
    params = checked_experiment(run.config["experiment"])
    row = import_recording(run, output_directory(args.dir),
                           open_catalog(args.dir, args.catalog), params)
    if args.json:
        _print_json(row)
    else:
        print(f"{row['id']}  {row['status']}  {row['file']}  ({row['n_samples']} samples at "
              f"{row['rate_Hz']:g} Hz from {Path(args.file).name})")
    return 0


def checked_experiment(table: Mapping[str, Any]) -> dict[str, Any]:
    """A mapping's [experiment] table checked against its family's schema (each key named in
    the error as ``mapping.experiment.<key>``); ``imported`` (no family) as it is."""
    from feedbench.config import validate_table
    from feedbench.engine.family import families

    kind = table.get("type", "imported")
    if kind == "imported":
        return dict(table)
    known = families()
    if kind not in known:
        raise ConfigError(f"mapping.experiment.type: unknown experiment family {kind!r} "
                          f"(known: {', '.join(sorted(known))})")
    return validate_table(dict(table), known[kind].schema, "mapping.experiment")


def cmd_demo(args: argparse.Namespace) -> int:
    """The campaign on the simulated bench (every experiment family), identified vs true."""
    t0 = time.monotonic()
    from feedbench.commands.demo import describe_demo, run_demo, runs_not_complete

    imported = time.monotonic()
    result = run_demo(output_directory(args.dir), quiet=args.json, quick=args.quick,
                      distribution=args.distribution, workers=args.workers)
    result["elapsed_s"] = time.monotonic() - t0
    result["timing"]["setup_s"] += imported - t0  # the imports
    failed = runs_not_complete(result)
    if args.json:
        _print_json(result)
        for line in failed:
            print(f"feedbench: demo: {line}", file=sys.stderr)
    else:
        print(describe_demo(result))
    return 1 if failed else 0


def cmd_campaign(args: argparse.Namespace) -> int:
    """Run a campaign config's runs as Dask tasks (progress on stderr), or take recorded
    runs (``--runs``: measured, imported, or MDF4/TDMS files imported as `report` does),
    write its summary table (JSON + CSV) and print it."""
    from feedbench.commands.campaign import (describe_campaign, load_campaign, progress_line,
                                             recorded_summary, run_campaign, write_summary)
    from feedbench.daq.importers import is_foreign
    from feedbench.daq.importers.mapping import imported_copy

    if bool(args.config) == bool(args.runs):
        raise ConfigError("campaign: give a campaign config or --runs RUN… (recorded runs)")
    if args.runs:
        with contextlib.ExitStack() as stack:
            recordings = {run: str(stack.enter_context(imported_copy(run, args.mapping)))
                          if is_foreign(run) else resolve_run(run, args.dir, args.catalog)
                          for run in args.runs}
            summary = recorded_summary(recordings)
        for row, run in zip(summary["runs"], args.runs):
            row["file"] = run if is_foreign(run) else row["file"]  # not the copy, now gone
        directory = Path(args.dir)
    else:
        campaign = load_campaign(args.config)
        summary = run_campaign(campaign, args.scheduler, args.workers, progress=None
                               if args.json else lambda *done: print(progress_line(*done),
                                                                      file=sys.stderr))
        directory = campaign.output_dir
    files = write_summary(summary, directory)
    if args.json:
        _print_json({**summary, "files": [str(f) for f in files]})
    else:
        print(describe_campaign(summary))
        print("Summary: " + ", ".join(map(str, files)))
    return 0 if summary["complete"] == len(summary["runs"]) else 1


def cmd_tune(args: argparse.Namespace) -> int:
    """`feedbench tune CONFIG [--apply NAME | --rollback]` (`feedbench.commands.tune`): progress and
    results on stdout (on stderr with --json, which prints the outcome)."""
    from feedbench.daq.recording import printable_json
    from feedbench.commands.tune import (apply_candidate, damping_text, load_tune_config,
                                recommendation_text, rollback, run_tune)

    def say(text: str) -> None:
        print(text, file=sys.stderr if args.json else sys.stdout, flush=True)

    config = load_tune_config(args.config)
    if args.apply and args.rollback:
        raise ConfigError("--apply, --rollback: give one of them")
    if args.rollback:
        out: dict = {"gains": rollback(config, say)}
    elif args.apply:
        out = apply_candidate(config, args.apply, say)
    else:
        result = run_tune(config, say)
        say(recommendation_text(result))
        say(f"Price of damping (Table 4.3): {damping_text(result)}")
        say(f"report: {config.report_path}\nresult: {config.result_path}")
        out = {"result": str(config.result_path), "report": str(config.report_path),
               "recommendation": result["recommendation"]}
    if args.json:
        print(printable_json(out))
    return 0


def cmd_sim(args: argparse.Namespace) -> int:
    """Serve the simulated bench of a config as its own process until Ctrl-C / SIGTERM."""
    from feedbench.bench import sim_config, start_served
    from feedbench.sim_backends.faults import with_fault_options
    from feedbench.sim_backends.process import serve
    from feedbench.sim_backends.socketcand_hub import HubError

    bench, plan = sim_config(args.config)
    if args.fault:
        bench = with_fault_options(bench, args.fault)
    for field, address in sim_listens(bench).items():
        check_can_listen(field, address)
    try:  # not pinned (`one_core`): the hub's thread runs the cycle alone
        serve(bench, functools.partial(start_served, plan=plan))
    except HubError as exc:
        raise ConfigError(f"bench.socketcand: {exc}") from exc
    return 0


def sim_listens(bench: Mapping[str, Any]) -> dict[str, str]:
    """The addresses `feedbench sim` listens on by field: the socketcand hub's and the
    Modbus devices' it serves (those with a ``unit_id``) that give one."""
    devices = {f"bench.devices.{name}.address": table["address"]
               for name, table in bench["devices"].items()
               if "unit_id" in table and table["address"]}
    return {"bench.socketcand": bench["socketcand"], **devices}


def check_can_listen(field: str, address: str) -> None:
    """A ``host:port`` to listen on must be free (port 0 or none: any free one); raises
    `ConfigError` naming the field and the address, before anything starts."""
    host, port = split_address(address, field, listen=True)
    if not port:
        return
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the servers do
        try:
            probe.bind((host, port))
        except OSError as exc:
            raise ConfigError(f"{field}: cannot listen on {address} ({exc.strerror})") from None


def finite(text: str) -> float:
    """An argument that must be a finite number."""
    value = float(text)
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number (got {text})")
    return value


def positive(text: str) -> float:
    """An argument that must be a finite number > 0."""
    value = finite(text)
    if not value > 0.0:
        raise argparse.ArgumentTypeError(f"must be > 0 (got {text})")
    return value


def count(text: str) -> int:
    """An argument that must be an integer ≥ 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be ≥ 1 (got {text})")
    return value


def store_location(text: str) -> str:
    """An argument that must be a recording store (`daq.store.store_problem`)."""
    from feedbench.daq.store import store_problem

    if problem := store_problem(text):
        raise argparse.ArgumentTypeError(problem.lstrip(": "))
    return text


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every sub-command."""
    parser = Parser(prog="feedbench")
    parser.add_argument("--debug", action="store_true",
                        help="show the traceback of an error instead of its one line")
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="run an experiment config (TOML)")
    run.add_argument("config")
    run.add_argument("--json", action="store_true", help="print the run record as JSON")
    run.add_argument("--live", action="store_true", help="watch the run in the live window")
    run.add_argument("--store", default="", metavar="STORE", type=store_location,
                     help="copy the recording there after the run: a directory (NAS) or an "
                     "fsspec URL (default: bench.store; docs/catalog.md)")
    run.set_defaults(func=cmd_run)

    runs = sub.add_parser("runs", help="list the run catalog")
    runs.add_argument("--dir", default="runs", help="output directory holding catalog.sqlite")
    runs.add_argument("--json", action="store_true")
    runs.add_argument("--bench", help="only the runs of this bench (FEEDBENCH_BENCH, else "
                      "its host's name)")
    runs.add_argument("--family", help="only the runs of this experiment family")
    runs.add_argument("--status", help="only the runs with this status (complete, aborted, "
                      "crashed, running, damaged…)")
    runs.add_argument("--since", metavar="DATE", help="only the runs started on or after DATE "
                      "(YYYY-MM-DD, or an ISO time; UTC)")
    runs.add_argument("--until", metavar="DATE", help="only the runs started on or before DATE")
    runs.add_argument("--where", action="append", default=[], metavar="CONDITION",
                      help="a key parameter's condition, e.g. 'chirp.f_stop_Hz>150' (family "
                      "first, or any family's: 'f_stop_Hz>150'); repeat for more")
    runs.set_defaults(func=cmd_runs)

    catalog = sub.add_parser("catalog", help="maintain the run catalog")
    catalog_sub = catalog.add_subparsers(dest="action", required=True)
    rebuild = catalog_sub.add_parser("rebuild", help="recreate the catalog from the "
                                     "recordings (*.h5) in the output directory")
    rebuild.add_argument("--dir", default="runs", help="output directory holding the recordings")
    rebuild.set_defaults(func=cmd_catalog_rebuild)
    sync = catalog_sub.add_parser("sync", help="register the runs recorded in the output "
                                  "directory while the catalog was unreachable")
    sync.add_argument("--dir", default="runs", help="output directory holding the recordings")
    sync.add_argument("--store", default="", metavar="STORE", type=store_location,
                      help="also copy there the recordings that have no store copy (the "
                      "pending copies are retried without it)")
    sync.set_defaults(func=cmd_catalog_sync)

    analyze = sub.add_parser("analyze", help="analyse a recorded run (id, id prefix or .h5) "
                             "or the FRFs of a UFF58 file (.uff, .unv)")
    analyze.add_argument("run")
    analyze.add_argument("--dir", default="runs")
    analyze.add_argument("--json", action="store_true")
    analyze.add_argument("--mapping", metavar="M.toml", help="which channel of an MDF4 or "
                         "TDMS file is which (default: the file's .toml; docs/import.md)")
    analyze.set_defaults(func=cmd_analyze)

    live = sub.add_parser("live", help="replay a recorded run in the live window")
    live.add_argument("run")
    live.add_argument("--dir", default="runs")
    live.add_argument("--speed", type=finite, default=1.0,
                      help="replay speed × real time (0: as fast as possible)")
    live.add_argument("--span", type=positive, default=10.0, help="window length (s)")
    live.set_defaults(func=cmd_live)

    report = sub.add_parser("report", help="HTML report of recorded runs (ids or .h5 files)")
    report.add_argument("runs", nargs="+")
    report.add_argument("--dir", default="runs")
    report.add_argument("-o", "--output", help="report file (default: DIR/report.html)")
    report.add_argument("--mapping", metavar="M.toml", help="which channel of the MDF4 or "
                        "TDMS files is which (default: each file's .toml; docs/import.md)")
    report.set_defaults(func=cmd_report)

    importer = sub.add_parser("import", help="import another DAQ system's recording (ASAM "
                              "MDF4 .mf4, NI TDMS .tdms) as a catalogued feedbench run")
    importer.add_argument("file", help="the recording (.mf4, .mdf, .tdms)")
    importer.add_argument("--mapping", metavar="M.toml", help="which channel is which, in "
                          "what unit, the experiment (default: FILE's .toml; docs/import.md)")
    importer.add_argument("--dir", default="runs", help="output directory of the recording "
                          "and its catalog")
    importer.add_argument("--json", action="store_true", help="print the run record as JSON")
    importer.set_defaults(func=cmd_import)

    demo = sub.add_parser("demo", help="the campaign on the simulated bench: every "
                          "experiment family, identified vs true values, and its report")
    demo.add_argument("--dir", default="runs/demo")
    demo.add_argument("--json", action="store_true")
    demo.add_argument("--quick", action="store_true",
                      help="shortened runs (each example's Example.quick): a few minutes")
    demo.add_argument("--distribution", metavar="NAME",
                      help="only the families this installed distribution registers "
                      "(feedbench: feedbench's own; default: every installed family)")
    demo.add_argument("--workers", type=count, help="worker processes running the examples "
                      "(default: one per CPU; 1: one after the other in this process)")
    demo.set_defaults(func=cmd_demo)

    campaign = sub.add_parser("campaign", help="a grid or Monte-Carlo set of simulated runs "
                              "as Dask tasks ([campaign] table + a run config)")
    campaign.add_argument("config", nargs="?", help="the campaign config (or --runs)")
    campaign.add_argument("--runs", nargs="+", metavar="RUN", help="instead of a config: "
                          "the summary of recorded runs, measured or imported (run ids, "
                          "recordings, or MDF4/TDMS files with their mapping)")
    campaign.add_argument("--dir", default="runs", help="--runs: output directory holding "
                          "the catalog; the summary goes there")
    campaign.add_argument("--mapping", help="--runs: the mapping of the MDF4/TDMS files "
                          "(default: FILE.toml beside each)")
    campaign.add_argument("--workers", type=int, help="worker processes of the local Dask "
                          "cluster (default: campaign.workers)")
    campaign.add_argument("--scheduler", metavar="ADDRESS", help="use the Dask cluster at "
                          "ADDRESS (e.g. tcp://host:8786) instead of a local one")
    campaign.add_argument("--json", action="store_true", help="print the summary as JSON")
    campaign.set_defaults(func=cmd_campaign)

    tune = sub.add_parser("tune", help="measure the servo loop and the tool tip, predict "
                          "candidate gain sets, report; --apply NAME, --rollback")
    tune.add_argument("config", help="TOML with [bench], [limits] (+ [limits.gains]), [tune]")
    tune.add_argument("--apply", metavar="NAME", help="write candidate NAME's gains (within "
                      "[limits.gains]), measure again, print predicted beside measured")
    tune.add_argument("--rollback", action="store_true",
                      help="write the gains the tune measured at back")
    tune.add_argument("--json", action="store_true", help="print the outcome as JSON")
    tune.set_defaults(func=cmd_tune)

    sim = sub.add_parser("sim", help="serve the simulated bench as its own process (CAN via "
                         "socketcand, Modbus TCP, DAQ pty on loopback)")
    sim.add_argument("config", help="TOML with [bench] (and [experiment] to prepare the "
                     "workpiece of an SMFE plan)")
    sim.add_argument("--fault", action="append", default=[], metavar="KEY=VALUE",
                     help="inject a fault (docs/faults.md), e.g. --fault at_cycle=300 "
                     "--fault emcy_code=0x2310; at_cycle counts the SYNCs since the start")
    sim.set_defaults(func=cmd_sim)

    export = sub.add_parser("export", help="export a run (id, id prefix or .h5): FRFs as "
                            "UFF58, drive channels as CSV with the closure's TOML sidecar")
    export.add_argument("run")
    export.add_argument("--dir", default="runs", help="output directory holding catalog.sqlite")
    export.add_argument("--uff58", metavar="FILE", help="UFF dataset 58 file of the run's "
                        "FRFs (with their coherence)")
    export.add_argument("--csv", metavar="FILE", help="CSV file (FILE.toml: its sidecar)")
    export.set_defaults(func=cmd_export)

    for command in (run, runs, rebuild, sync, analyze, live, report, export, importer,
                    campaign):
        command.add_argument("--catalog", metavar="URL", default="", help="the run catalog: "
                             "postgresql://user@host/database or an SQLite file (default: "
                             "$FEEDBENCH_CATALOG, else bench.catalog, else DIR/catalog.sqlite)")
    from feedbench.commands.closure import add_closure_parser

    add_closure_parser(sub)
    for command in [*sub.choices.values(), *catalog_sub.choices.values()]:  # and after it
        command.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                             help=argparse.SUPPRESS)
    parser.description = f"The feedbench command: {', '.join(sub.choices)}."
    return parser


WITHOUT_MF4 = frozenset({"run", "sim", "tune", "demo"})
"""Commands that never read or write MDF4 files: they start without asammdf
(`without_python_can_mf4`)."""


def without_python_can_mf4() -> None:
    """Mark asammdf absent before python-can is first imported. Every ``import can`` imports
    asammdf for python-can's MF4 log format when it is installed (0.66 of the 0.82 s
    ``import can`` takes, measured), which a command that reads no MDF4 recording
    (`WITHOUT_MF4`: the sim, a run) never uses; python-can then leaves MF4 out, as it does
    where asammdf is not installed. Not for a process that imports MDF4 recordings
    (`daq.importers.mdf4`)."""
    if "can" not in sys.modules:
        sys.modules.setdefault("asammdf", None)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `feedbench` console script."""
    args = build_parser().parse_args(argv)
    if args.command in WITHOUT_MF4:
        without_python_can_mf4()
    try:
        with _noting_interrupts():
            status = args.func(args)
            sys.stdout.flush()  # a reader gone is found here, not in Python's flush at exit
        if _SIGINT_SEEN.is_set():  # dropped where it landed: the command still is interrupted
            raise KeyboardInterrupt
        return status
    except Exception as exc:
        if isinstance(exc, BrokenPipeError) and _stdout_closed():
            return STDOUT_CLOSED
        if args.debug:
            raise
        if _SIGINT_SEEN.is_set():
            _error_line("interrupted")
            return INTERRUPTED
        user = isinstance(exc, USER_ERRORS) or isinstance(exc, OSError) and exc.filename
        _error_line(_user_message(exc) if user else
                    f"{type(exc).__name__}: {exc} (run with --debug for the traceback)")
        return 2
    except KeyboardInterrupt:
        if args.debug:
            raise
        _error_line("interrupted")
        return INTERRUPTED


_SIGINT_SEEN = threading.Event()
"""Set by a Ctrl-C during the command, even one Python could not raise where it landed (a
KeyboardInterrupt inside a ctypes callback of numba's compiler is printed and dropped, and
the command then fails with some other error): the command still ends as interrupted."""


def _raise_interrupt(signum: int, frame: object) -> None:
    _SIGINT_SEEN.set()
    raise KeyboardInterrupt


@contextlib.contextmanager
def _noting_interrupts():
    """SIGINT raises KeyboardInterrupt as by default and is remembered in `_SIGINT_SEEN`; one
    Python cannot raise (in a weakref callback or a __del__, e.g. matplotlib's) is not
    printed as 'Exception ignored'."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _SIGINT_SEEN.clear()
    previous, previous_hook = signal.signal(signal.SIGINT, _raise_interrupt), sys.unraisablehook

    def unraisable(info: Any) -> None:
        if not isinstance(info.exc_value, KeyboardInterrupt):
            previous_hook(info)

    sys.unraisablehook = unraisable
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        sys.unraisablehook = previous_hook


def _stdout_closed() -> bool:
    """Whether the reader of stdout has gone (a pipe closed early): then stdout is pointed at
    /dev/null, so that Python's last flush at exit does not fail again."""
    poller = select.poll()
    try:
        poller.register(sys.stdout.fileno(), select.POLLOUT)
    except (OSError, ValueError):  # no real file behind stdout (a test's capture)
        return False
    if not any(events & select.POLLERR for _, events in poller.poll(0)):
        return False
    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return True


def _user_message(exc: Exception) -> str:
    """A user error's text (a file's error names the file)."""
    if isinstance(exc, OSError) and exc.filename:
        return f"{exc.filename}: {exc.strerror}"
    return str(exc)


def _error_line(message: str) -> None:
    """``feedbench: error: <message>`` as one line on stderr."""
    print(f"feedbench: error: {' '.join(message.split())}", file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())
