"""Shared fixtures: every test gets its own virtual CAN channel and output directory;
`simulated_bench` is the testing kit's (`feedbench.testing`).

`make test` runs two pytest-xdist workers, whole files each (`--dist loadfile`), the slowest
files first (`SLOW_FIRST`). Each worker compiles numba kernels into its own cache directory.
"""

from __future__ import annotations

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
    "test_demo.py", "test_report.py", "test_structure_experiments.py", "test_smfe_bench.py",
    "test_notebook.py", "test_stepped_loading.py", "test_scripts.py", "test_live_window.py",
    "test_config_cli.py", "test_closure_cases.py", "test_api.py", "test_fault_paths.py",
    "test_campaign.py", "test_rack_pinion_bench.py", "test_sim_process.py",
    "test_fault_matrix.py", "test_fault_matrix_devices.py", "test_fault_matrix_host.py",
)
"""Test files, longest first (measured under `make test`: the demo ≈ 170 s, the scripts
≈ 85 s, the others 15–60 s each); they start first so the other worker spreads the short
ones around them. The scripts (four simulated benches at once) start once the demo is
done: together the two overload the 2 cores and a 1 s bus timeout trips."""

def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """`SLOW_FIRST` files first, the rest in collection order; each file's tests stay together."""
    rank = {name: i for i, name in enumerate(SLOW_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(SLOW_FIRST)))


def pytest_runtest_setup(item: pytest.Item) -> None:
    """Tests marked `requires(available, reason)` skip, or fail in CI (`prerequisites.py`)."""
    check_requirements(item)


@pytest.fixture
def can_channel() -> str:
    """A python-can `virtual` channel name no other test uses."""
    return virtual_channel()
