"""The seam where an experiment family plugs in: one `Experiment` subclass per family, and
the one registry of them.

A family is everything feedbench knows about one kind of test, in one class: its parameters
(a schema of `config.Field`s whose names carry their units, checked on construction into a
frozen dataclass), the devices it needs besides the drive, `plan()` (the segments the
runner executes), `analyze` (the recording → a JSON-able result; the same function runs on
a finished recording and, in the live window, on the windows completed so far:
`engine.incremental.LiveAnalysis`), and how a person sees the result: `report`
(its report section), `live_view` (its live panels), `headline` (what it measured, in one
line), `summary` (the demo's line against the simulated world's truth) and `details`
(`feedbench analyze`'s lines beyond the headline).

A result judges itself: a family's `analyze` puts its checks of the physics it relies on
into the result (``checks``, `analysis.checks`); `judged_analysis`, the one way every
command and the live view run an analysis, adds the run's own checks (status) and the
verdict (``valid``, ``not_valid_because``). The report's quality rows, `describe` (the
terminal), ``--json`` and the live summary all read them from there.

The registry is Python's entry points, group ``feedbench.experiments``, as python-can finds
its bus interfaces: feedbench declares its own families in its pyproject.toml, and a lab
adds one from its own package with one line in its own::

    [project.entry-points."feedbench.experiments"]
    my_test = "my_lab.my_test:MyTest"

`bench`, `report`, `gui`, `demo` and the CLI look families up here and know none by name:
the demo runs the example configs the families declare (`Experiment.examples`, `examples`),
so a lab's family joins it. `families(distribution)` lists one installed distribution's
families (feedbench's own tests ask for `config.OWN_DISTRIBUTION`'s).
docs/ARCHITECTURE.md walks through adding one (the backlash reversal test).

Loading the families loads every family's module and its analysis modules, so those import
scipy lazily (``import scipy``, then ``scipy.signal.find_peaks`` at the call: SciPy imports a
submodule on first use): `feedbench run` and `sim` start without scipy.signal, .stats and
.optimize unless their plan or world uses them (a chirp's plan does). Measured: their imports
plus `families()` 1.9 → 0.8 s CPU, `feedbench sim` of the friction sweep to its ready line
2.3 → 1.2 s.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import cache
from importlib import resources
from typing import Any, ClassVar, Iterator, Mapping, Union

from feedbench.analysis.checks import check, check_line, verdict, verdict_line
from feedbench.config import ConfigError, Field, read_toml, registered, validate_table
from feedbench.engine.plan import Plan
from feedbench.views.frfs import ExchangeFrf
from feedbench.views.panels import ResultView
from feedbench.views.sections import RunSection, Table

ENTRY_POINT_GROUP = "feedbench.experiments"

LAB_RANK = 1000
"""`Example.rank` by default: a lab's examples run after feedbench's own (ranks 10–100)."""


@dataclass(frozen=True)
class Example:
    """An example config a family ships, ``<package>/examples/<name>.toml``, which
    `feedbench demo` runs (by `rank`, lowest first) and `feedbench campaign` can start from.

    `quick`: what ``demo --quick`` changes, table → keys (``{"experiment": {"settle_s":
    0.4}}``); `package`: whose ``examples/`` holds it ("" as declared: the family's own
    top-level package, `examples` fills it in); `required`: a refusal of its config or plan
    stops the demo (else the demo records it as refused and goes on)."""

    name: str
    quick: Mapping[str, Mapping[str, Any]] = dataclasses.field(default_factory=dict)
    package: str = ""
    rank: int = LAB_RANK
    required: bool = False

    def config(self) -> dict[str, Any]:
        """The example config as a dict (a fresh copy each call)."""
        return read_toml(resources.files(self.package) / "examples" / f"{self.name}.toml")

    def quick_config(self) -> dict[str, Any]:
        """The example config with `quick` applied."""
        raw = self.config()
        for table, keys in self.quick.items():
            raw.setdefault(table, {}).update(keys)
        return raw


class Experiment:
    """One experiment family; subclasses set the class attributes and override the steps.

    `name`: the config's ``experiment.type``; `schema`: its parameters (`config.Field`,
    units in the names); `axes`: the bench axes it runs on (empty: any); `live_kinds`: the
    segment kinds whose completion brings something new to analyse (the live result is
    recomputed then); `title`: what the live panel and the report call it; `has_frfs`: its
    result holds FRFs that `frfs` lists for export; `examples`: the example configs it
    ships (`Example`), which `feedbench demo` runs; `demo_key`: the key of the demo's result
    under which its example's summary (`demo_part`) also goes, its part of the bench's core
    ("": none), printed by `demo_lines`; `demo_compare`: what the campaign's other runs
    show beside its own.
    """

    name: ClassVar[str]
    schema: ClassVar[Mapping[str, Field]]
    title: ClassVar[str] = ""
    axes: ClassVar[tuple[str, ...]] = ()
    live_kinds: ClassVar[tuple[str, ...]] = ("measure", "excite")
    has_frfs: ClassVar[bool] = False
    examples: ClassVar[tuple[Example, ...]] = ()
    demo_key: ClassVar[str] = ""

    def __init__(self, params: Mapping[str, Any], cycle_s: float) -> None:
        """Check `params` (the config's [experiment] table) for a bus cycle of `cycle_s` s;
        raises `ConfigError` naming the field. The checked parameters are `self.params`,
        typed (`typed`): what `plan` and `devices` read (``self.params.f_stop_Hz``), and
        `self.settings`, the same as a dict: what the plan records (`Plan.params`, the
        catalog's row) and a script re-runs (`api`)."""
        self.cycle_s = cycle_s
        self.settings: dict[str, Any] = self.check(params, cycle_s)
        self.params = self.typed(self.settings)

    @classmethod
    def check(cls, params: Mapping[str, Any], cycle_s: float) -> dict[str, Any]:
        """The validated parameters with defaults filled in; a family adds its cross-field
        checks (a frequency below Nyquist, a start below a stop)."""
        return validate_table(params, cls.schema, "experiment")

    @classmethod
    def typed(cls, checked: Mapping[str, Any]) -> Any:
        """Checked parameters (a dict as `check` returns it) as the family's frozen dataclass
        (`params_type`)."""
        return params_type(cls)(**checked)

    @classmethod
    def stored_params(cls, recording) -> Any:
        """The typed parameters a recording ran with, what `analyze` reads: its stored
        [experiment] table validated once against the schema (defaults filled in; a
        `ConfigError` names ``experiment.<key>``). Not `check`'s cross-field checks: those
        decide whether a run may start; a recorded run is analysed as it ran and judged by
        its own checks (a friction sweep of 3 feeds: "3 feeds measured", not a refused
        config)."""
        return cls.typed(validate_table(recording.config["experiment"], cls.schema,
                                        "experiment"))

    def plan(self) -> Plan:
        """The segments the runner executes, every setpoint computed before anything moves."""
        raise NotImplementedError

    def devices(self) -> dict[str, dict[str, Any]]:
        """The devices besides the drive (name → its settings): none by default."""
        return {}

    @classmethod
    def analyze(cls, recording, final: bool = True) -> dict[str, Any]:
        """The result of a `daq.recording.Recording` (SI, JSON-able, ``experiment`` = name).

        `final` False: the recording holds only the windows completed so far (live); a
        family then returns what they allow, or raises `ConfigError` saying what it waits for.
        """
        raise NotImplementedError

    @classmethod
    def report(cls, recording, result: Mapping[str, Any], section: RunSection) -> None:
        """Add the result's plots, tables and quality indicators to `section` (its headline
        and checks are added by `report.run_section`)."""

    @classmethod
    def headline(cls, result: Mapping[str, Any]) -> str:
        """What the run measured, in one line: the report's "what it measured" and the first
        line of `describe`."""
        return scalar_text(result)

    @classmethod
    def live_view(cls, result: Mapping[str, Any]) -> ResultView:
        """The live window's panels and one-line summary of a (partial) result."""
        return ResultView(cls.title or cls.name, (), scalar_text(result))

    @classmethod
    def frfs(cls, result: Mapping[str, Any], recording) -> Iterator[ExchangeFrf]:
        """The result's FRFs with their ends, for UFF58 export (families with `has_frfs`)."""
        return iter(())

    @classmethod
    def summary(cls, result: Mapping[str, Any], truth: Mapping[str, Any]) -> dict[str, Any]:
        """The demo's summary against the simulated world's `truth`: key values in SI and a
        ``headline``."""
        return {"headline": scalar_text(result)}

    @classmethod
    def demo_part(cls, summary: Mapping[str, Any]) -> Any:
        """Its part of the demo's result (under `demo_key`) from its example's `summary`
        (without the headline): the whole summary by default."""
        return dict(summary)

    @classmethod
    def demo_lines(cls, part: Any) -> list[str]:
        """`feedbench demo`'s lines of its `demo_part`, before the experiments (none by
        default)."""
        return []

    @classmethod
    def demo_compare(cls, entries: dict[str, dict], configs: Mapping[str, Mapping]) -> None:
        """Add to its example's entry of the demo (`entries`: example name → its
        ``experiments.<name>`` entry; `configs`: example name → run config; `demo_examples`
        finds a family's) what the campaign's other runs show beside it; nothing by
        default."""

    @classmethod
    def truth_table(cls, result: Mapping[str, Any], truth: Mapping[str, Any]) -> Table:
        """The report's identified-vs-true table of a simulated run: by default the parts of
        the demo summary's headline (`summary`), a row each."""
        parts = cls.summary(result, truth)["headline"].split(HEADLINE_SEPARATOR)
        return Table(TRUTH_TITLE, ("identified against the simulated world",),
                     tuple((part,) for part in parts))

    @classmethod
    def details(cls, result: Mapping[str, Any]) -> list[str]:
        """`feedbench analyze`'s lines between the headline and the checks (none by default)."""
        return []

    @classmethod
    def describe(cls, result: Mapping[str, Any]) -> list[str]:
        """`feedbench analyze`'s lines for the result (after the run line): the `headline`,
        the family's `details`, every check with its reason, and the verdict."""
        return [f"  {cls.headline(result)}", *cls.details(result),
                *(f"  {check_line(c)}" for c in result.get("checks", ())),
                f"  {verdict_line(result)}"]


def run_checks(recording, final: bool) -> list[dict[str, Any]]:
    """The run's own checks for a `final` result: it completed its plan, no sample lost."""
    if not final:
        return []
    status = recording.status + (f" ({recording.reason})" if recording.reason else "")
    return [check("status", status, recording.status == "complete",
                  "the run stopped before its plan ended: the result is of partial data"),
            check("missing samples (gaps)", str(recording.n_gaps), recording.n_gaps == 0,
                  "samples were lost: the spectra and fits mix records across the gaps")]


def judged_analysis(family: type[Experiment], recording, final: bool = True) -> dict[str, Any]:
    """`family`'s analysis of `recording` with its checks, the run's (`run_checks`) and the
    verdict (``valid``, ``not_valid_because``): what every command and the live view show."""
    result = family.analyze(recording, final=final)
    checks = [*result.get("checks", ()), *run_checks(recording, final)]
    return {**result, "checks": checks, **verdict(checks)}


TRUTH_TITLE = "identified vs true (simulated world)"
"""Title of every family's `Experiment.truth_table`."""

HEADLINE_SEPARATOR = "; "
"""Between the parts of a summary's headline (`feedbench demo` prints each on its own line)."""


def headline(*parts: str) -> str:
    """One line of an experiment's key numbers from its parts."""
    return HEADLINE_SEPARATOR.join(parts)


def percent_error(value: float, truth: float) -> float:
    """100 (value − truth) / truth: an identified value against the simulated world's."""
    return 100.0 * (value - truth) / truth


def scalar_text(result: Mapping[str, Any]) -> str:
    """The result's top-level numbers and words as one line (a family's fallback headline)."""
    return ", ".join(f"{key} {value:.4g}" if isinstance(value, float) else f"{key} {value}"
                     for key, value in result.items()
                     if key not in ("experiment", "run", "valid")
                     and isinstance(value, (int, float, str)))


@cache
def params_type(family: type[Experiment]) -> type:
    """The frozen dataclass of a family's parameters, one field per schema entry, typed as
    the entry's `Field.kind` (a tuple of kinds: their union)."""
    return dataclasses.make_dataclass(
        f"{family.__name__}Params",
        [(key, field.kind if isinstance(field.kind, type) else Union[field.kind])
         for key, field in family.schema.items()], frozen=True)


def families(distribution: str | None = None) -> dict[str, type[Experiment]]:
    """Every registered family by name (entry points of `ENTRY_POINT_GROUP`); `distribution`:
    only that installed distribution's (feedbench's own: `config.OWN_DISTRIBUTION`)."""
    return registered(ENTRY_POINT_GROUP, Experiment, distribution)


def examples(distribution: str | None = None) -> dict[str, Example]:
    """The example configs the families declare (`Experiment.examples`), by name, in the
    order `feedbench demo` runs them (`Example.rank`, then name); `distribution` as for
    `families`."""
    found = [dataclasses.replace(example, package=example.package
                                 or cls.__module__.partition(".")[0])
             for cls in families(distribution).values() for example in cls.examples]
    return {e.name: e for e in sorted(found, key=lambda e: (e.rank, e.name))}


def demo_examples(configs: Mapping[str, Mapping], family_name: str) -> list[str]:
    """The names of the examples of `configs` (example name → run config) that run the
    family `family_name`, in their order."""
    return [name for name, raw in configs.items()
            if raw.get("experiment", {}).get("type") == family_name]


def family(name: Any, where: str = "experiment.type") -> type[Experiment]:
    """The family called `name`; an unknown one is a `ConfigError` at `where`."""
    known = families()
    if name not in known:
        raise ConfigError(f"{where}: must be one of {', '.join(sorted(known))} (got {name!r})")
    return known[name]
