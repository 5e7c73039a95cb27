"""Run catalog speed (issue 28): listing 100 000 runs with a filter on SQLite and on
PostgreSQL (target < 200 ms each: the lines `feedbench runs` prints, `Catalog.lines`; whole
rows, `Catalog.list`, beside them), the `--where` condition in SQL against the baseline of the
same filter checked in Python on every row that names the key (how `feedbench runs` listed
before, measured in the same run); and the insert rate of 4 bench processes writing at once
(each run: a new id, its start, its end — the catalog's three transactions of a run) against
one writer alone.

PostgreSQL is a throw-away server started as the tests start it (`tests/pg_server.py`:
Debian's `postgresql` package, 127.0.0.1, a free port); without it the PostgreSQL figures are
left out, said in one line. ``FEEDBENCH_BENCH_CATALOG_RUNS`` sets the number of runs listed
(default 100 000), ``FEEDBENCH_BENCH_CATALOG_WRITES`` the runs per writer (default 100).
"""

from __future__ import annotations

import json
import os
import random
import subprocess
import sys
import tempfile
import textwrap
import time
import uuid
from pathlib import Path

from feedbench.daq.catalog import RUNS, Catalog
from feedbench.daq.run_filter import Condition, RunFilter

from _timing import best_of, print_figures  # benchmarks/_timing.py

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import pg_server  # noqa: E402  (tests/pg_server.py)

N_RUNS = int(os.environ.get("FEEDBENCH_BENCH_CATALOG_RUNS", 100_000))
WRITES = int(os.environ.get("FEEDBENCH_BENCH_CATALOG_WRITES", 100))
WRITERS = 4
REPEATS = 7
TARGET_S = 0.200
BENCHES = ("feed-drive", "rack-pinion-rig", "spindle-stand", "test-rig")
F_STOP_HZ = (100.0, 120.0, 150.0, 200.0, 250.0, 300.0, 500.0)
FILTERS = {
    "where": RunFilter(where=(Condition.parse("chirp.f_stop_Hz>150"),)),
    "family_bench_where": RunFilter(bench="rack-pinion-rig", experiment="chirp",
                                    where=(Condition.parse("chirp.f_stop_Hz>150"),)),
    "bench_status_where": RunFilter(bench="feed-drive", status="complete", where=(
        Condition.parse("f_stop_Hz>=250"), Condition.parse("window=hann"))),
}
"""The filters listed: `--where 'chirp.f_stop_Hz>150'` alone (≈ 17 % of the runs), with
`--bench` and `--family` (≈ 4 %), and two conditions with `--bench --status` (≈ 2 %)."""
WRITER = textwrap.dedent("""
    import json, sys, time
    from feedbench.daq.catalog import Catalog
    location, bench, runs, start_at = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
    catalog = Catalog(location, bench=bench)
    time.sleep(max(0.0, start_at - time.time()))
    start = time.time()
    for _ in range(runs):
        run_id = catalog.new_run_id("chirp")
        catalog.add(run_id, "chirp", f"/runs/{run_id}.h5", {"f_stop_Hz": 200.0})
        catalog.finish(run_id, "complete", "", 8000)
    print(json.dumps([start, time.time()]))
""")


def rows(n: int) -> list[dict]:
    """`n` finished runs of four families on four benches over two years, oldest first."""
    rng = random.Random(28)
    out = []
    for index in range(n):
        family = rng.choices(("chirp", "friction_sweep", "stepped_loading", "sine_stream"),
                             (4, 3, 2, 1))[0]
        params: dict = {"type": family}
        if family == "chirp":
            params.update(f_start_Hz=5.0, f_stop_Hz=rng.choice(F_STOP_HZ), amplitude_N=50.0,
                          window=rng.choice(("hann", "none")))
        elif family == "friction_sweep":
            params["feeds_mm_min"] = [100, 200, 400, 800]
        elif family == "stepped_loading":
            params.update(forces_N=[100, 200, 400], hold_s=0.5)
        else:
            params.update(f_Hz=[10.0, 20.0, 40.0], amplitude_N=20.0)
        day = 1 + index * 730 // n
        run_id = f"2025{day:04d}-{index:06d}-{family}-1"
        out.append({"id": run_id, "experiment": family,
                    "started_at": f"2025-01-01T00:00:{index % 60:02d}+00:00",
                    "stopped_at": None,
                    "status": rng.choices(("complete", "aborted", "crashed"), (90, 7, 3))[0],
                    "reason": "", "file": f"{run_id}.h5", "n_samples": 8000,
                    "params": json.dumps(params, sort_keys=True), "pid": 4242,
                    "host": "bench-pc", "timing": None, "bench": rng.choice(BENCHES)})
    return out


def fill(catalog: Catalog, n: int) -> None:
    """Insert `n` runs (`rows`) in batches."""
    data = rows(n)
    with catalog._transaction() as connection:
        for start in range(0, n, 10_000):
            connection.execute(RUNS.insert(), data[start:start + 10_000])


def listing(catalog: Catalog, prefix: str) -> tuple[dict[str, float], dict[str, str]]:
    """Best-of-`REPEATS` wall time of each filter's listing, in SQL and the baseline."""
    figures, notes = {}, {}
    for name, where in FILTERS.items():
        sql_s = base_s = cpu_s = rows_s = float("inf")
        lines = lambda where=where: list(catalog.lines(where=where))  # noqa: E731
        for _ in range(REPEATS):  # in turn: a burst of the machine's other work hits all
            sql_s = min(sql_s, best_of(lines, 1)[0])
            rows_s = min(rows_s, best_of(lambda where=where: catalog.list(where=where), 1)[0])
            base_s = min(base_s, best_of(lambda where=where: baseline(catalog, where), 1)[0])
            cpu_s = min(cpu_s, cpu_seconds(lines))
        listed = catalog.list(where=where)
        assert [row.id for row in baseline(catalog, where)] == [row.id for row in listed]
        assert [tuple(line) for line in lines()] == [
            (row.id, row.status, row.n_samples, row.file, row.reason) for row in listed]
        figures[f"{prefix}_list_{name}_ms"] = sql_s * 1e3
        notes[f"{prefix}_list_{name}_ms"] = (
            f"ms to list {N_RUNS} runs, {name.replace('_', ' + ')} ({len(listed)} listed; "
            "the lines of `feedbench runs`, Catalog.lines; "
            f"target < {TARGET_S * 1e3:.0f} ms: {'met' if sql_s < TARGET_S else 'NOT met'})")
        figures[f"{prefix}_list_{name}_cpu_ms"] = cpu_s * 1e3
        notes[f"{prefix}_list_{name}_cpu_ms"] = (
            "CPU ms of this process for it (what a machine busy with other work does not "
            "inflate as much" + (")" if prefix == "sqlite" else "; the server's not in it)"))
        figures[f"{prefix}_list_{name}_rows_ms"] = rows_s * 1e3
        notes[f"{prefix}_list_{name}_rows_ms"] = ("the same as whole rows (Catalog.list, "
                                                  "every field decoded: `runs --json`)")
        figures[f"{prefix}_list_{name}_python_ms"] = base_s * 1e3
        notes[f"{prefix}_list_{name}_python_ms"] = ("baseline: the same, --where checked in "
                                                    "Python on each row naming the key")
        figures[f"{prefix}_list_{name}_speedup"] = base_s / sql_s
        notes[f"{prefix}_list_{name}_speedup"] = "baseline time / SQL time"
    return figures, notes


def cpu_seconds(action) -> float:
    """CPU time (s) of this process for one call of `action`."""
    start = time.process_time()
    action()
    return time.process_time() - start


def baseline(catalog: Catalog, where: RunFilter) -> list:
    """The baseline listing (see `listing`)."""
    read = [catalog._row(row) for row in catalog._select(where, None, in_sql=False)]
    return [row for row in read if where.matches(row.experiment, row.status, row.params)]


def insert_rate(location: str, writers: int, environment: dict[str, str]) -> float:
    """Runs/s that `writers` processes record at once into the catalog at `location`, each
    `WRITES` runs (new id, add, finish), timed from the first one's start to the last one's
    end (imports and connecting left out)."""
    start_at = time.time() + 3.0
    processes = [subprocess.Popen([sys.executable, "-c", WRITER, location, BENCHES[k],
                                   str(WRITES), str(start_at)], stdout=subprocess.PIPE,
                                  env=environment, text=True)
                 for k in range(writers)]
    spans = [json.loads(process.communicate(timeout=600)[0]) for process in processes]
    if any(process.returncode for process in processes):
        raise RuntimeError(f"a catalog writer failed on {location}")
    return writers * WRITES / (max(end for _, end in spans) - min(start for start, _ in spans))


def writing(location: str, prefix: str,
            environment: dict[str, str]) -> tuple[dict[str, float], dict[str, str]]:
    one = insert_rate(location, 1, environment)
    several = insert_rate(location, WRITERS, environment)
    figures = {f"{prefix}_insert_runs_per_s_1_writer": one,
               f"{prefix}_insert_runs_per_s_{WRITERS}_writers": several,
               f"{prefix}_insert_{WRITERS}_writers_over_1": several / one}
    notes = {f"{prefix}_insert_runs_per_s_1_writer": f"baseline: runs/s of one writer ({WRITES} "
             "runs: new id, add, finish)",
             f"{prefix}_insert_runs_per_s_{WRITERS}_writers": f"runs/s of {WRITERS} bench "
             f"processes at once, {WRITES} runs each",
             f"{prefix}_insert_{WRITERS}_writers_over_1": f"{WRITERS} writers' rate / one's"}
    return figures, notes


def run() -> dict[str, float]:
    print("load average at the start: {:.2f} {:.2f} {:.2f} ({} CPUs)".format(
        *os.getloadavg(), os.cpu_count()))
    figures: dict[str, float] = {}
    notes: dict[str, str] = {}
    environment = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    with tempfile.TemporaryDirectory() as directory:
        sqlite = Catalog(Path(directory) / "catalog.sqlite")
        fill(sqlite, N_RUNS)
        for part in (listing(sqlite, "sqlite"),
                     writing(str(Path(directory) / "writes.sqlite"), "sqlite", environment)):
            figures.update(part[0])
            notes.update(part[1])
    if pg_server.BINARIES is None:
        print("(PostgreSQL figures left out: no PostgreSQL server programs; Debian package "
              "postgresql)")
    else:
        server = pg_server.start_server()
        try:
            os.environ["PGPASSWORD"] = environment["PGPASSWORD"] = server.password
            urls = []
            for _ in range(2):
                name = f"bench_{uuid.uuid4().hex[:12]}"
                with pg_server.psycopg.connect(server.url, autocommit=True) as connection:
                    connection.execute(f"CREATE DATABASE {name}")
                urls.append(server.url.rsplit("/", 1)[0] + "/" + name)
            postgres = Catalog(urls[0])
            fill(postgres, N_RUNS)
            for part in (listing(postgres, "postgresql"),
                         writing(urls[1], "postgresql", environment)):
                figures.update(part[0])
                notes.update(part[1])
        finally:
            os.environ.pop("PGPASSWORD", None)
            pg_server.remove_server(server)
    print("load average at the end: {:.2f} {:.2f} {:.2f}".format(*os.getloadavg()))
    print_figures(figures, notes, 48, "12.1f")
    return figures


if __name__ == "__main__":
    run()
