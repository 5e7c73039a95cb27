"""The `feedbench closure` command: run the closure on a trace, or the table of simulated
cases with undeclared effects.

    feedbench closure DATA [--model M.toml] [--validation DATA2] [--axis N] [--json]
                           [--plots DIR] [--report FILE]
    feedbench closure --cases [CASES.toml] [--json]

DATA: a CSV file with its TOML sidecar, an EMPS or KUKA robot .mat file (--axis: the
joint), or a feedbench .h5 recording.
This module composes the room that simulates (`sim_backends.effects`) with the one that
analyses (`analysis.closure`); the analysis never sees a world table. The numerical
packages are imported where used, so that registering the command costs nothing.
"""

from __future__ import annotations

import argparse
import time
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, Mapping, Sequence

from feedbench.config import ConfigError, Field, read_toml, validate_table

if TYPE_CHECKING:
    from feedbench.analysis.closure import ClosureReport, ModelSpec, Trace

EXAMPLES = Path(__file__).parents[1] / "examples" / "closure"
CASES_PATH = EXAMPLES / "cases.toml"
EMPS_MODEL = EXAMPLES / "emps_rigid_viscous.toml"
KUKA_MODEL = EXAMPLES / "kuka_joint.toml"

WORLD_TO_VOCABULARY = {"sensor_offset": "offset", "inertia_mismatch": "inertia.M_kg"}
"""World effects the closure names differently: a force-reading offset is an offset, a mass
the declared model does not know is the recalibration of its declared mass."""


@contextmanager
def single_blas_thread() -> Iterator[None]:
    """Run the block with one BLAS thread (threadpoolctl), then restore the previous count.

    The closure's least squares are thin (n × p, p ≤ 15): threads only spin and contend on
    a loaded 2-core machine (measured 3× the CPU time).
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1, user_api="blas"):
        yield


def load_model_spec(path: str | Path) -> ModelSpec:
    """Read and validate a model config file."""
    from feedbench.analysis.closure import parse_model_config

    return parse_model_config(read_toml(path))


def default_model(data: str | Path, axis: int | None = None) -> Path | None:
    """The packaged model config of a .mat trace: EMPS, or a KUKA joint (given an axis)."""
    if Path(data).suffix.lower() != ".mat":
        return None
    return EMPS_MODEL if axis is None else KUKA_MODEL


def closure_report(data: str | Path, model: str | Path | None = None,
                   validation: str | Path | None = None,
                   holdout: float | None = None, axis: int | None = None,
                   mapping: str | Path | None = None) -> ClosureReport:
    """Read the traces (joint `axis` of a KUKA file; `mapping`: which channel of an MDF4 or
    TDMS file is which) and the model config, run the closure; returns the report."""
    from feedbench.analysis.closure import parse_model_config, run_closure

    if holdout is not None and not 0.0 < holdout < 1.0:
        raise ConfigError(f"--holdout: must lie between 0 and 1 (got {holdout:g})")
    trace, controller = read_checked(data, axis, mapping)
    model_path = model or default_model(data, axis)
    if model_path is None:
        raise ConfigError("--model: required (a model config TOML, see docs/closure.md)")
    raw = read_toml(model_path)
    if controller and "controller" not in raw:
        raw = {**raw, "controller": controller}
    spec = parse_model_config(raw)
    if holdout is not None:
        spec = replace(spec, holdout_fraction=holdout)
    second = read_checked(validation, axis)[0] if validation else None
    try:
        with single_blas_thread():
            return run_closure(spec, trace, second)
    except ValueError as exc:  # data the closure cannot use: too short, too slow, no reference
        raise ConfigError(f"{data}: {exc}") from None


def read_checked(path: str | Path, axis: int | None = None,
                 mapping: str | Path | None = None) -> tuple[Trace, dict[str, Any]]:
    """`closure_io.read_trace`; a file its reader or `Trace` refuses (NaN or inf samples, time
    not increasing, not a MATLAB file) raises `ConfigError` naming the file."""
    from scipy.io.matlab import MatReadError

    from feedbench.closure_io import read_trace

    try:
        return read_trace(path, axis, mapping)
    except ConfigError:
        raise
    except (ValueError, MatReadError) as exc:
        raise ConfigError(f"{path}: {exc}") from None
    except KeyError as exc:  # a recording without the channel
        raise ConfigError(f"{path}: no {exc.args[0]!r} channel") from None


# -- simulated cases -----------------------------------------------------------------------

CASE_SCHEMA = {
    "name": Field(str, None, "case name"),
    "model": Field(str, None, "model config, relative to the cases file"),
    "effects": Field(dict, {}, "effects the world carries (sim_backends.effects)"),
    "world": Field(dict, {}, "overrides of [defaults] for this case"),
    "acceptance": Field(bool, True, "counts in the acceptance figures (false: exploratory)"),
}


@dataclass(frozen=True)
class CaseOutcome:
    """One simulated case: the undeclared effect(s) injected, what the closure found (effects
    and "term.key" of recalibrated declared parameters, in order), the fitted parameters of
    the effects and of the recalibrated terms."""

    name: str
    injected: tuple[str, ...]
    found: tuple[str, ...]
    error_before: float
    error_after: float
    seconds: float
    params: dict[str, Any]
    acceptance: bool = True

    @property
    def right_first(self) -> bool:
        """The first effect found is the one injected (or nothing found on a clean case)."""
        return self.found[:1] == self.injected[:1]

    @property
    def reduction(self) -> float:
        """Share of the held-out error removed."""
        return 1.0 - self.error_after / self.error_before


def read_cases(path: str | Path = CASES_PATH) -> list[dict[str, Any]]:
    """The case entries of a cases file, each with its world table and model path."""
    raw = read_toml(path)
    defaults = raw.get("defaults", {})
    cases = []
    for i, entry in enumerate(raw.get("case", [])):
        case = validate_table(entry, CASE_SCHEMA, f"case[{i}]")
        if not case["name"] or not case["model"]:
            raise ConfigError(f"case[{i}]: needs a name and a model")
        world = {**defaults, **case["world"], "effects": case["effects"]}
        cases.append({"name": case["name"], "world": world, "acceptance": case["acceptance"],
                      "model": Path(path).parent / case["model"]})
    return cases


def simulated_trace(world: Mapping[str, Any], name: str) -> Trace:
    """Record a simulated world as a trace (the analysis's view of it)."""
    from feedbench.analysis.closure import Trace
    from feedbench.sim_backends.effects import simulate_recording

    recording = simulate_recording(world)
    c = recording.channels
    return Trace(c["time"], c["position"], c["force"], c["x_ref"], c["force_offset"], name,
                 recording.force_lag_s)


def undeclared(world: Mapping[str, Any], spec: ModelSpec) -> tuple[str, ...]:
    """The world's effects the model does not declare, in the closure's vocabulary."""
    names = (WORLD_TO_VOCABULARY.get(n, n) for n in world.get("effects", {}))
    return tuple(n for n in names if n not in spec.model.names)


def run_case(case: Mapping[str, Any]) -> CaseOutcome:
    """Generate one case's recording and close the loop on it."""
    from feedbench.analysis.closure import report_dict, run_closure

    start = time.perf_counter()
    spec = load_model_spec(case["model"])
    trace = simulated_trace(case["world"], case["name"])
    with single_blas_thread():
        report = run_closure(spec, trace)
    data = report_dict(report)
    found = tuple(step.chosen.name for step in report.result.steps)
    recalibrated = {name.split(".")[0] for name in report.result.recalibrated}
    params = {**data["params"], **{term: data["final_params"][term] for term in recalibrated}}
    return CaseOutcome(case["name"], undeclared(case["world"], spec), found,
                       report.result.error_before, report.result.error_after,
                       time.perf_counter() - start, params, case.get("acceptance", True))


def run_cases(path: str | Path = CASES_PATH) -> list[CaseOutcome]:
    """Every case of a cases file."""
    return [run_case(case) for case in read_cases(path)]


def cases_table(outcomes: Sequence[CaseOutcome]) -> str:
    """The acceptance table: case, effect injected, effect found, error before → after.
    Exploratory cases are listed but left out of the closing counts."""
    lines = [f"{'case':<24s} {'injected':<24s} {'found (in order)':<40s} "
             f"{'held-out error before → after':>30s}  ok"]
    for o in outcomes:
        ok = "yes" if o.right_first and (not o.found or o.reduction >= 0.5) else "NO"
        lines.append(f"{o.name:<24s} {', '.join(o.injected) or '—':<24s} "
                     f"{', '.join(o.found) or '—':<40s} "
                     f"{o.error_before:>13.2%} → {o.error_after:>6.2%} ({-o.reduction:+.0%})  {ok}"
                     + ("" if o.acceptance else "  (exploratory)"))
    counted = [o for o in outcomes if o.acceptance]
    with_effect = [o for o in counted if o.injected]
    clean = [o for o in counted if not o.injected]
    found = [o for o in counted if o.found]
    lines.append(f"right effect first: {sum(o.right_first for o in with_effect)}/"
                 f"{len(with_effect)}; clean cases with nothing added: "
                 f"{sum(not o.found for o in clean)}/{len(clean)}; held-out error reduced "
                 f"≥ 50 % where an effect was found: {sum(o.reduction >= 0.5 for o in found)}/"
                 f"{len(found)}")
    return "\n".join(lines)


def cases_dict(outcomes: Sequence[CaseOutcome]) -> dict[str, Any]:
    """The case table as JSON."""
    return {"cases": [{"name": o.name, "injected": list(o.injected), "found": list(o.found),
                       "right_first": o.right_first, "error_before": o.error_before,
                       "error_after": o.error_after, "acceptance": o.acceptance,
                       "seconds": o.seconds, "params": o.params} for o in outcomes]}


# -- the command ---------------------------------------------------------------------------

def cmd_closure(args: argparse.Namespace) -> int:
    """Run the closure on a trace, or the simulated case table."""
    from feedbench.analysis.closure import report_dict, report_text
    from feedbench.closure_io import save_plots
    from feedbench.daq.recording import printable_json

    if args.cases:
        outcomes = run_cases(args.cases)
        print(printable_json(cases_dict(outcomes)) if args.json
              else cases_table(outcomes))
        return 0
    if not args.data:
        raise ConfigError("closure: give a trace (CSV + sidecar, .mat or .h5) or --cases")
    data, validation = (run_file(given, args.dir, args.catalog) if given else None
                        for given in (args.data, args.validation))
    report = closure_report(data, args.model, validation, args.holdout, args.axis,
                            args.mapping)
    plots = save_plots(report, args.plots) if args.plots else []
    html = None
    if args.report:
        from feedbench.report import write_report

        html = write_report([], args.report, f"closure of {Path(args.data).name}",
                            closures=[report])
    if args.json:
        data = report_dict(report)
        data["plots"] = [str(p) for p in plots]
        data["report"] = str(html) if html else None
        print(printable_json(data))
    else:
        print(report_text(report))
        for path in plots:
            print(f"plot: {path}")
        if html:
            print(f"report: {html}")
    return 0


TRACE_SUFFIXES = (".csv", ".mat", ".h5", ".hdf5", ".mf4", ".mdf", ".tdms")


def run_file(data: str, directory: str, catalog: str = "") -> str:
    """A trace file as given, or the recording of a run id (or unique id prefix) in the
    catalog: its local file, else its copy in the lab's store (`daq.store.run_recording`)."""
    if Path(data).exists() or Path(data).suffix.lower() in TRACE_SUFFIXES:
        return data
    from feedbench.daq.store import run_recording

    return run_recording(data, directory, catalog)


def add_closure_parser(sub: Any) -> None:
    """Register `feedbench closure` on the sub-command parsers."""
    closure = sub.add_parser("closure", help="residual → missing effect → augmented model → "
                             "error before/after, on a trace or on simulated cases")
    closure.add_argument("data", nargs="?", help="trace: .csv (+ .toml sidecar), .mat, .h5, "
                         ".mf4 or .tdms (+ .toml mapping), "
                         "or a run id in the catalog (its recording, else its store copy)")
    closure.add_argument("--dir", default="runs", help="output directory holding the "
                         "catalog (a run id's)")
    closure.add_argument("--catalog", metavar="URL", default="", help="the run catalog of a "
                         "run id (default: $FEEDBENCH_CATALOG, else DIR/catalog.sqlite)")
    closure.add_argument("--model", help="model config TOML (default for .mat: EMPS rigid "
                         "body + viscous; KUKA: motor inertia + viscous, link side)")
    closure.add_argument("--axis", type=int, help="joint of a KUKA robot .mat file (1–6)")
    closure.add_argument("--mapping", metavar="M.toml", help="which channel of an MDF4 or "
                         "TDMS file (DATA) is which (default: its .toml; docs/import.md)")
    closure.add_argument("--validation", help="second trace to judge on (else the end of DATA)")
    closure.add_argument("--holdout", type=float, help="share of DATA held out (0–1)")
    closure.add_argument("--plots", help="directory for PNG plots")
    closure.add_argument("--report", help="also write the result as an HTML report (the "
                         "campaign report's closure section)")
    closure.add_argument("--cases", nargs="?", const=str(CASES_PATH),
                         help="run the simulated cases table (default: the packaged one)")
    closure.add_argument("--json", action="store_true", help="print the report as JSON")
    closure.set_defaults(func=cmd_closure)
