"""Shared fixtures: every test gets its own virtual CAN channel and output directory;
`simulated_bench` is the testing kit's (`feedbench.testing`).

`make test` runs two pytest-xdist workers, whole files each (`--dist loadfile`), the slowest
files first (`SLOW_FIRST`). Each worker compiles numba kernels into its own cache directory.
"""

from __future__ import annotations

import gc
import os
from pathlib import Path

import pytest

from prerequisites import check_requirements

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

_WORKER = os.environ.get("PYTEST_XDIST_WORKER")
if _WORKER:
    # numba's cache is not safe for two processes compiling two signatures of one function
    # at once (the index of one may name the other's data file), so one directory per
    # worker, kept between runs; set before anything imports numba. Subprocesses inherit it.
    _base = os.environ.get("NUMBA_CACHE_DIR") or Path(__file__).parents[1] / ".pytest_cache"
    os.environ["NUMBA_CACHE_DIR"] = str(Path(_base) / "numba" / _WORKER)

# the testing kit's fixtures (after NUMBA_CACHE_DIR is set: the kit imports the bench)
from feedbench.testing import simulated_bench, virtual_channel  # noqa: E402, F401

SLOW_FIRST = (
    "test_demo.py", "test_closure_independent.py", "test_report.py", "test_fault_matrix_host.py",
    "test_fault_matrix.py", "test_watchdogs.py", "test_live_window.py",
    "test_smfe_bench.py", "test_tune.py", "test_closure_cases.py", "test_scripts.py",
    "test_timeouts.py", "test_fault_paths.py", "test_closure_measurement.py",
    "test_catalog_postgres_benches.py", "test_campaign.py", "test_mistakes.py",
    "test_notebook.py", "test_fault_matrix_devices.py", "test_structure_experiments.py",
    "test_stepped_loading.py", "test_config_cli.py", "test_catalog_truth.py", "test_import.py",
    "test_sim_process.py", "test_dynamic_friction.py", "test_closure_emps.py",
    "test_closure_gallery.py", "test_realtime.py", "test_closure_robust.py",
    "test_late_host.py", "test_bad_inputs.py", "test_catalog_postgres.py", "test_store.py",
    "test_catalog_paths.py", "test_fuzz_parsers.py", "test_rack_pinion_bench.py",
    "test_closure_io.py", "test_catalog_concurrency.py", "test_serial_daq.py",
    "test_sim_serves_all.py",
    "test_run_safety.py", "test_cia402_conformance.py", "test_api.py", "test_smfe.py",
    "test_closure_kuka.py", "test_clock.py", "test_live_offline.py", "test_bench_tables.py",
    "test_backlash_reversal.py",
)
"""Test files of 5 s or more alone (`pytest -n 0 FILE`, pytest's ≈ 2 s start included),
longest first: measured one file at a time on 28 Nov beside other jobs, the demo ≈ 45 s
(its runs on two processes), the closure on the independent simulator 78 s, the report
52 s, the SIGKILL rows ≈ 37 s (56 s until each row's drive stop overlapped the next row's
run: 99 → 66 s back to back at load 5 on 29 Nov), the others 5–31 s. They start first so
the other worker spreads the short ones around them; the demo first, so that the scripts
(four simulated benches at once) start after it: together they overload the 2 cores and a
1 s bus timeout trips.
test_import (15 s), test_store (9 s), test_closure_io (6 s) alone on 29 Nov: they had been
left out and ran last, among the short files (test_import ended one worker's share).
Marked ``slow``: `make test-fast` runs the other files."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """`SLOW_FIRST` files first, their tests marked ``slow`` (`make test-fast` leaves them
    out), the rest in collection order; each file's tests stay together."""
    rank = {name: i for i, name in enumerate(SLOW_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(SLOW_FIRST)))
    for item in items:
        if item.path.name in rank:
            item.add_marker(pytest.mark.slow)


def pytest_collection_finish(session: pytest.Session) -> None:
    """Freeze the heap once collected (`gc.freeze`): every test module and the libraries
    they import, ≈ 250 000 objects a worker, are then left out of Python's full
    collections, which walked them about 50 times a worker in a fifth of the suite (8.5 of
    a worker's 38 s of CPU went to full collections; 1.8 s frozen, measured 29 Nov). A
    real-time run's `frozen_heap` unfreezes it as it ends: that worker's later tests
    collect as before (kept frozen, the next real-time run there faulted on SYNC loss right
    after its enable, cause not found)."""
    gc.freeze()


def pytest_runtest_setup(item: pytest.Item) -> None:
    """Tests marked `requires(available, reason)` skip, or fail in CI (`prerequisites.py`)."""
    check_requirements(item)


@pytest.fixture
def can_channel() -> str:
    """A python-can `virtual` channel name no other test uses."""
    return virtual_channel()
