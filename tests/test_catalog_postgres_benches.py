"""Several benches, one PostgreSQL catalog (issue 28, item 2): four bench processes record 50
short runs each at once into their own directories and one catalog, while `feedbench runs`
lists it: 200 rows, none lost or duplicated, ids unique, every run findable with its bench;
and a catalog whose server stops mid-run never stops the recording: the run is kept, says so
in one line, and `feedbench catalog sync` registers it once the server is back.

The writers record as `test_catalog_concurrency`'s do (the catalog and recorder calls
`Bench.run` makes, 300 cycles in three chunks): 200 whole simulated runs cost more CPU than
this test's budget on two cores. The catalog-down test runs a whole simulated bench."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from importlib import resources
from pathlib import Path

from feedbench.commands.cli import main
from feedbench.daq.catalog import Catalog
from feedbench.daq.recording import open_recording
from feedbench.daq.run_filter import RunFilter
from pg_server import BINARIES, own_server, postgres_url, server  # noqa: F401  (fixtures)
from prerequisites import requires
from test_catalog_concurrency import LISTER, WRITER, python
from test_catalog_truth import _flushed

pytestmark = requires(BINARIES is not None, "PostgreSQL's server programs (Debian package "
                      "postgresql; .ci/run installs it)")

BENCHES = 4
RUNS_PER_BENCH = 50
CYCLES_PER_RUN = 300


def test_four_benches_at_once_lose_and_duplicate_no_run(postgres_url, tmp_path, monkeypatch):
    Catalog(postgres_url)  # the schema, made once before the benches start
    stop = tmp_path / "stop"
    monkeypatch.setenv("FEEDBENCH_CATALOG", postgres_url)  # the lister's `feedbench runs`
    lister = python(LISTER, tmp_path, stop)
    started = time.monotonic()
    for k in range(BENCHES):
        (tmp_path / f"bench-{k}").mkdir()
    writers = [python(WRITER, postgres_url, tmp_path / f"bench-{k}", f"bench-{k}",
                      RUNS_PER_BENCH, CYCLES_PER_RUN) for k in range(BENCHES)]
    written = [writer.communicate(timeout=300) for writer in writers]
    elapsed = time.monotonic() - started
    stop.touch()
    listed, lister_err = lister.communicate(timeout=60)

    assert [(writer.returncode, err) for writer, (_, err) in zip(writers, written)] == [
        (0, "")] * BENCHES
    assert (lister.returncode, lister_err) == (0, "") and int(listed) > 0
    recorded = {line.split()[0]: (f"bench-{k}", line.split()[1])
                for k, (out, _) in enumerate(written) for line in out.splitlines()}
    assert len(recorded) == BENCHES * RUNS_PER_BENCH, "ids unique across the benches"
    catalog = Catalog(postgres_url)
    rows = catalog.list()
    assert len(rows) == len({row.id for row in rows}) == BENCHES * RUNS_PER_BENCH
    assert {row.id: (row.bench, row.file) for row in rows} == recorded
    assert {(row.status, row.n_samples) for row in rows} == {("complete", CYCLES_PER_RUN)}
    for run_id, (bench, file) in recorded.items():
        assert (catalog.get(run_id).file, catalog.get(run_id).bench) == (file, bench)
    assert [len(catalog.list(where=RunFilter(bench=f"bench-{k}"))) for k in range(BENCHES)
            ] == [RUNS_PER_BENCH] * BENCHES
    print(f"{len(rows)} runs by {BENCHES} benches in {elapsed:.1f} s "
          f"({len(rows) / elapsed:.0f} runs/s), listed {listed.strip()} times meanwhile")


def sweep_config(path: Path, directory: Path, channel: str, catalog: str) -> Path:
    """A friction sweep of five feeds (≈ 8 s of bench time) into `directory`, catalogued in
    `catalog`, written to `path`."""
    text = (resources.files("feedbench") / "examples" / "friction_sweep.toml").read_text()
    replaced = (text.replace('output_dir = "runs"', f'output_dir = "{directory}"\n'
                             f'catalog = "{catalog}"')
                .replace('channel = "feedbench-demo"', f'channel = "{channel}"')
                .replace("[25, 50, 75, 100, 150, 200, 300, 400, 500, 700, 900, 1200, 1500]",
                         "[100, 200, 300, 400, 500]"))
    assert replaced.count(catalog) == 1 and "[100, 200, 300, 400, 500]" in replaced
    path.write_text(replaced)
    return path


def test_a_catalog_that_goes_away_mid_run_never_stops_the_recording(
        own_server, tmp_path, can_channel, capsys, monkeypatch):
    monkeypatch.setenv("PGPASSWORD", own_server.password)
    directory = tmp_path / "runs"
    config = sweep_config(tmp_path / "sweep.toml", directory, can_channel, own_server.url)
    run = subprocess.Popen([sys.executable, "-m", "feedbench.commands.cli", "run", str(config)],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not _flushed(directory, at_least=2000) and time.monotonic() < deadline:
        time.sleep(0.05)
    own_server.stop()
    out, err = run.communicate(timeout=300)

    assert run.returncode == 0, err
    [path] = directory.glob("*.h5")
    recording = open_recording(path)
    assert (recording.status, recording.reason) == ("complete", "")
    assert recording.n_samples > 5000, "the run went on to its end"
    [line] = out.splitlines()
    run_id = path.stem
    assert line.startswith(f"{run_id}  complete  {path}  (run {run_id} complete, kept in its "
                           f"recording but not in the catalog ({own_server.url}: cannot use "
                           "the run catalog (connection failed: ")
    assert line.endswith("); feedbench catalog sync registers it once the catalog is back)")

    own_server.start()
    assert main(["catalog", "sync", "--dir", str(directory), "--catalog", own_server.url]) == 0
    assert capsys.readouterr().out == (f"{own_server.url}: 0 run(s) registered, 1 settled from "
                                       "their recordings\n")
    assert main(["runs", "--catalog", own_server.url, "--json"]) == 0
    [row] = json.loads(capsys.readouterr().out)["runs"]
    assert (row["id"], row["status"], row["n_samples"], row["file"]) == (
        run_id, "complete", recording.n_samples, str(path))
