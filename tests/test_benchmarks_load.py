"""Every benchmark loads the way `make bench` loads it (`benchmarks/run_all.py`): a module
that fails there ends `make bench` at that point, after every benchmark before it has run
(bench_closure_real's dataclasses did, 29 Nov: `make bench` had not completed since)."""

from __future__ import annotations

import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import run_all  # noqa: E402  (benchmarks/run_all.py)

BENCH_EXTRA = {requirement.split(">")[0].split("=")[0].strip()
               for requirement in tomllib.loads((ROOT / "pyproject.toml").read_text())
               ["project"]["optional-dependencies"]["bench"]}
"""The libraries only `make bench` installs (pyproject's `bench` extra): python-control,
pyFRF, pyEMA, the baselines some benchmarks compare against."""


def test_every_benchmark_is_found():
    assert len(run_all.BENCHMARKS) >= 20


@pytest.mark.parametrize("path", run_all.BENCHMARKS, ids=lambda path: path.stem)
def test_every_benchmark_loads_with_a_run_function(path):
    """Loaded as run_all loads it, it has `run()`; where it needs a library of the bench
    extra that this environment lacks, that is the only thing missing."""
    try:
        module = run_all.load(path)
    except ModuleNotFoundError as missing:
        assert missing.name in BENCH_EXTRA, missing
        return
    assert callable(module.run)
