"""`feedbench runs --where` evaluated in SQL (issue 28, benchmark of the "Done when"): the
same runs as `Condition.matches` (the definition) selects, on SQLite and on PostgreSQL, for
numbers, text, booleans, null, arrays, nested tables, a family's prefix, missing keys and
damaged rows; and the SQL itself selects exactly the matching rows wherever the value is no
array or table (nor a number tested against text), so listing does not read the rest."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy import text

from feedbench.daq.catalog import Catalog
from feedbench.daq.run_filter import Condition, RunFilter
from pg_server import BINARIES, new_database, postgres_url, server  # noqa: F401  (fixtures)
from prerequisites import requires

PARAMS = [
    ("chirp", {"f_stop_Hz": 120.0, "mode": "open", "window": True, "seed": 7}),
    ("chirp", {"f_stop_Hz": 200, "mode": "closed", "window": False, "seed": None}),
    ("chirp", {"f_stop_Hz": 150.0, "mode": "150", "label": "Ünïcode", "seed": 12}),
    ("chirp", {"f_stop_Hz": "high", "mode": "b"}),
    ("friction_sweep", {"feeds_mm_min": [100, 200], "f_stop_Hz": 900,
                        "chirp": {"f_stop_Hz": 160.0}, "mode": "open"}),
    ("friction_sweep", {"feeds_mm_min": [100.0, 200.0], "settle_s": 1e-5}),
    ("stepped_loading", {"steps": {"force_N": [10, 20]}, "f_stop_Hz": 1.5e3, "window": "true"}),
    ("stepped_loading", {}),
]
CONDITIONS = [
    "chirp.f_stop_Hz>150", "f_stop_Hz>150", "f_stop_Hz>=150", "f_stop_Hz=200",
    "f_stop_Hz!=200", "f_stop_Hz<1500", "f_stop_Hz<=1500.0", "chirp.f_stop_Hz = high",
    "f_stop_Hz>h", "f_stop_Hz=200.0", "mode=open", "mode>c", "mode=150", "mode<150",
    "mode!=open", "window=true", "window!=false", "window=True", "seed=None", "seed>5",
    "seed!=None", "feeds_mm_min=[100, 200]", "friction_sweep.feeds_mm_min=[100.0, 200.0]",
    "feeds_mm_min>[", "steps.force_N=[10, 20]", "stepped_loading.steps.force_N=[10, 20]",
    "label>Z", "label=Ünïcode", "settle_s=1e-05", "settle_s<0.001", "f_stop_Hz>nan",
    "f_stop_Hz<inf", "f_stop_Hz!=nan", "missing=1", "chirp.missing.deeper>0",
]
DAMAGED = ["not json {", "[1, 2]", '"f_stop_Hz"', '{"f_stop_Hz": 300']


BACKENDS = ["sqlite", pytest.param("postgresql", marks=requires(
    BINARIES is not None, "PostgreSQL's server programs (Debian package postgresql)"))]


def filled(location: str, directory: Path) -> Catalog:
    """A catalog at `location` holding `PARAMS`' runs, oldest first."""
    catalog = Catalog(location, directory=directory)
    for family, params in PARAMS:
        run_id = catalog.new_run_id(family)
        catalog.add(run_id, family, f"{run_id}.h5", params)
        catalog.finish(run_id, "complete", "", 1)
    return catalog


@pytest.fixture(params=BACKENDS)
def catalog(request: pytest.FixtureRequest, tmp_path: Path) -> Catalog:
    """A catalog holding `PARAMS`' runs, oldest first (the test's own: it may damage rows)."""
    location = (str(tmp_path / "catalog.sqlite") if request.param == "sqlite"
                else request.getfixturevalue("postgres_url"))
    return filled(location, tmp_path)


@pytest.fixture(scope="module", params=BACKENDS)
def shared_catalog(request: pytest.FixtureRequest,
                   tmp_path_factory: pytest.TempPathFactory) -> Iterator[Catalog]:
    """`catalog`, made once per backend for the tests that only read it (made for each of
    the 35 conditions it took 36 of the file's 40 s)."""
    directory = tmp_path_factory.mktemp("shared_catalog")
    if request.param == "sqlite":
        yield filled(str(directory / "catalog.sqlite"), directory)
        return
    server = request.getfixturevalue("server")
    with pytest.MonkeyPatch.context() as monkeypatch:
        yield filled(new_database(server, monkeypatch), directory)


def by_definition(catalog: Catalog, conditions: tuple[Condition, ...]) -> list[str]:
    """The ids `Condition.matches` selects from every row read."""
    return [row.id for row in catalog.list() if row.status != "damaged" and all(
        condition.matches(row.experiment, row.params) for condition in conditions)]


def selected_in_sql(catalog: Catalog, where: RunFilter) -> list[str]:
    return [row[0] for row in catalog._select(where, None)]


@pytest.mark.parametrize("condition", CONDITIONS)
def test_a_condition_selects_in_sql_what_its_definition_selects(shared_catalog, condition):
    catalog = shared_catalog
    conditions = (Condition.parse(condition),)
    expected = by_definition(catalog, conditions)
    assert [row.id for row in catalog.list(where=RunFilter(where=conditions))] == expected
    in_sql = selected_in_sql(catalog, RunFilter(where=conditions))
    assert set(expected) <= set(in_sql)
    [condition] = conditions
    let_through = {row.id for row in catalog.list() if lets_through(condition, row)}
    assert set(in_sql) - set(expected) <= let_through, "SQL exact but for arrays and tables"


def lets_through(condition: Condition, row) -> bool:
    """Whether SQL leaves the row to `Condition.matches`: its value is an array or a table,
    or a number and the condition's value no finite number (a real's text differs between
    Python and SQL)."""
    path = (condition.path[1:] if len(condition.path) > 1
            and condition.path[0] == row.experiment else condition.path)
    found = row.params
    for key in path:
        if not isinstance(found, dict) or key not in found:
            return False
        found = found[key]
    if isinstance(found, (list, dict)):
        return True
    try:
        number = math.isfinite(float(condition.value))
    except ValueError:
        number = False
    return not number and isinstance(found, (int, float)) and not isinstance(found, bool)


def test_conditions_together_and_with_the_other_filters(catalog):
    conditions = (Condition.parse("f_stop_Hz>100"), Condition.parse("mode!=closed"))
    where = RunFilter(experiment="chirp", where=conditions)
    expected = [row_id for row_id in by_definition(catalog, conditions)
                if "-chirp-" in row_id]
    assert len(expected) == 3, "120 open, 150 (mode 150), high (text: 'high' > '100')"
    assert [row.id for row in catalog.list(where=where)] == expected
    assert selected_in_sql(catalog, where) == expected
    assert [row.id for row in catalog.list(limit=1, where=where)] == expected[:1]


def test_damaged_rows_never_match_and_the_others_still_do(catalog):
    rows = catalog.list()
    for row, damage in zip(rows, DAMAGED):
        with catalog._engine.begin() as connection:
            connection.execute(text("UPDATE runs SET params = :p WHERE id = :id"),
                               {"p": damage, "id": row.id})
    for condition in ("f_stop_Hz>100", "chirp.f_stop_Hz>100", "mode=open", "seed=None"):
        conditions = (Condition.parse(condition),)
        listed = [row.id for row in catalog.list(where=RunFilter(where=conditions))]
        assert listed == by_definition(catalog, conditions)
        assert not set(listed) & {row.id for row in rows[:len(DAMAGED)]}
    assert [row.status for row in catalog.list()][:len(DAMAGED)] == ["damaged"] * len(DAMAGED)


def test_a_listed_row_has_every_field_of_a_run_row(catalog):
    from dataclasses import fields

    from feedbench.daq.catalog import COLUMN_NAMES, RunRow

    assert tuple(field.name for field in fields(RunRow)) == COLUMN_NAMES
    row = catalog.list()[0]
    assert row == RunRow(**{name: getattr(row, name) for name in COLUMN_NAMES})


LINE_FILTERS = [RunFilter(), RunFilter(status="complete"), RunFilter(status="damaged"),
                RunFilter(experiment="chirp")] + [
    RunFilter(where=tuple(map(Condition.parse, conditions))) for conditions in (
        ("f_stop_Hz>150",), ("chirp.f_stop_Hz>150",), ("mode=open",), ("seed=None",),
        ("feeds_mm_min=[100, 200]",), ("window=true",), ("f_stop_Hz>100", "mode!=closed"),
        ("settle_s<0.001",))] + [
    RunFilter(status="complete", where=(Condition.parse("f_stop_Hz>100"),))]


def test_the_lines_of_runs_are_those_of_the_rows_listed(catalog):
    """`Catalog.lines` (what `feedbench runs` prints, decoding only what it must) gives what
    `Catalog.list` gives of each row, damaged rows (parameters naming a condition's key among
    them, a damaged timing) and limits included."""
    rows = catalog.list()
    damage = DAMAGED + ['["f_stop_Hz", 300]', '{"f_stop_Hz": 300, "x": NaN']
    with catalog._engine.begin() as connection:
        for row, params in zip(rows, damage):
            connection.execute(text("UPDATE runs SET params = :p WHERE id = :id"),
                               {"p": params, "id": row.id})
        connection.execute(text("UPDATE runs SET timing = :t WHERE id = :id"),
                           {"t": "{not json", "id": rows[-1].id})
    for where in LINE_FILTERS:
        expected = [(row.id, row.status, row.n_samples, row.file, row.reason)
                    for row in catalog.list(where=where)]
        assert [tuple(line) for line in catalog.lines(where=where)] == expected, where
        assert [tuple(line) for line in catalog.lines(limit=1, where=where)] == expected[:1]
    [line] = [line for line in catalog.lines(where=RunFilter(where=(
        Condition.parse("chirp.f_stop_Hz>100"),))) if line.id == rows[-1].id]
    assert line.status == "damaged" and "timing is not JSON" in line.reason


def test_a_postgresql_catalog_of_version_2_gets_its_parsed_parameters(postgres_url, tmp_path):
    """Schema version 3 (PostgreSQL's parameters parsed when a row is written): a version-2
    catalog upgrades in place and lists with --where as before."""
    catalog = Catalog(postgres_url, directory=tmp_path)
    for family, params in PARAMS:
        run_id = catalog.new_run_id(family)
        catalog.add(run_id, family, f"{run_id}.h5", params)
    with catalog._engine.begin() as connection:
        connection.execute(text("ALTER TABLE runs DROP COLUMN document"))
        connection.execute(text("DROP FUNCTION feedbench_parameters"))
        connection.execute(text("UPDATE catalog_schema SET version = 2"))
    where = RunFilter(where=(Condition.parse("f_stop_Hz>150"),))
    catalog = Catalog(postgres_url, directory=tmp_path)
    assert [row.id for row in catalog.list(where=where)] == by_definition(catalog, where.where)
    with catalog._engine.begin() as connection:
        assert connection.execute(text("SELECT version FROM catalog_schema")).scalar_one() == 3
