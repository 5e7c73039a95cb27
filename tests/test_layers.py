"""One-way layers and no import circles between feedbench's modules (issue 14).

Every import of every module is read from the source with `ast`: at module level, inside
functions and under ``if TYPE_CHECKING`` alike, so a lazy import cannot hide a circle.

The layers, lowest first; a module may import its own room and the rooms of lower layers,
never a room beside it or above it. This is the issue's path of the data (models →
sim_backends / drivers → daq → experiments → analysis → report / gui → cli) as imports
see it, with two placements it implies: `protocols` below drivers and sim_backends (both
ends of a link import its format), and `analysis` right above models, since it is pure
(arrays in, results out) and imports only models, protocols, units and itself; each
family's analyze step in `experiments` calls it. `config` sits with `units` at the bottom:
it imports nothing from feedbench, and every room raises its `ConfigError` (the one
bad-input error) or validates a table with it.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import feedbench

PACKAGE = Path(feedbench.__file__).parent

LAYERS = (
    ("units", "config"),
    ("protocols",),
    ("models",),
    ("analysis", "views"),
    ("drivers", "sim_backends"),
    ("daq",),
    ("engine",),  # the run engine: the family seam, plans, limits, runner, replay
    ("devices",),  # the host device kinds' seam and the built-in per-cycle devices
    ("experiments",),  # the families, over the engine
    ("axes",),  # the axis kinds' seam (`feedbench.axes`) and the lab and rack-and-pinion axes
    ("closure_io",),  # readers of recordings (CSV + sidecar, .mat, HDF5) for the closure
    ("bench",),  # the composition root
    ("report", "gui", "testing"),  # testing: the kit over the bench (`feedbench.testing`)
    ("api",),  # the scripting face (issue 17)
    # the commands (`feedbench.commands`), one room each, over the library
    ("commands.exchange", "commands.closure", "commands.demo"),
    ("commands.campaign", "commands.tune"),  # Dask runs against the demo's truth; tuning
    ("commands.cli",),
    ("commands.console", "commands"),  # the console script: cli.main, Ctrl-C one line
)
LAYER = {room: level for level, rooms in enumerate(LAYERS) for room in rooms}

NEVER = {
    "drivers": {"models", "sim_backends"},  # the host side does not know the peer is simulated
    "daq": {"sim_backends"},
    "engine": {"sim_backends"},
    "devices": {"sim_backends"},
    "experiments": {"sim_backends", "devices"},  # a family asks for devices by name
}
"""Rooms a room may not import although they lie below it (docs/ARCHITECTURE.md)."""

EXCEPTIONS: set[tuple[str, str]] = set()
"""(importing module, imported module) pairs allowed against the layers: none remain."""


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(path): path for path in sorted(PACKAGE.rglob("*.py"))}


def known(name: str) -> str | None:
    """The feedbench module `name` refers to (a package's attribute → the package)."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def imports(name: str) -> set[str]:
    """The feedbench modules `name` imports, anywhere in its source."""
    path = MODULES[name]
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parent + ([base] if base else []))
            found.update(f"{base}.{alias.name}" if f"{base}.{alias.name}" in MODULES else base
                         for alias in node.names)
    return {target for target in map(known, found) if target and target != name}


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    """Each feedbench module → the feedbench modules it imports (parsed when a test asks,
    not at collection: 2 s of every collecting process)."""
    return {name: imports(name) for name in MODULES}


def room(name: str) -> str:
    """``feedbench.models.axis`` → ``models``; a command is a room of its own:
    ``feedbench.commands.cli`` → ``commands.cli``."""
    parts = name.split(".")
    return ".".join(parts[1:3]) if parts[1] == "commands" else parts[1]


def test_the_graph_is_read(graph):
    assert len(graph) > 80
    assert "feedbench.drivers.cia402" in graph["feedbench.bench"]
    assert "feedbench.models.axis" in graph["feedbench.analysis.tuning"]
    assert "feedbench.bench" in graph["feedbench.commands.cli"]  # a function-level import counts
    rooms = {room(name) for name in graph if name != "feedbench"}
    assert rooms == set(LAYER), "every room has its place in LAYERS"


def test_imports_go_one_way_down_the_layers(graph):
    wrong = sorted(
        f"{name} imports {target} ({room(name)} → {room(target)})"
        for name, targets in graph.items() if name != "feedbench"
        for target in targets
        if (name, target) not in EXCEPTIONS
        and room(target) != room(name)
        and (LAYER[room(target)] >= LAYER[room(name)]
             or room(target) in NEVER.get(room(name), ()))
    )
    assert wrong == []


def test_analysis_imports_only_models_protocols_units_and_itself(graph):
    allowed = {"analysis", "models", "protocols", "units", "config"}
    assert sorted((name, target) for name, targets in graph.items() for target in targets
                  if room(name) == "analysis" and room(target) not in allowed) == []


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for target in sorted(graph[node]):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while not component or component[-1] != node:
                component.append(stack.pop())
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_the_cycle_finder_finds_a_circle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_circles(graph):
    assert cycles(graph) == []
