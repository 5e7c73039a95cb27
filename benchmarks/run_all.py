"""Run every benchmark (`benchmarks/bench_*.py`), print each figure, end with one JSON line.

Each module exposes ``run() -> dict[str, float]``; it prints its own figures with the
baseline measured in the same run. The last line of output maps every figure to its value.
"""

from __future__ import annotations

import importlib.util
import json
import sys
import time
from pathlib import Path
from types import ModuleType


BENCHMARKS = sorted(Path(__file__).parent.glob("bench_*.py"))


def load(path: Path) -> ModuleType:
    """The benchmark module at `path`, imported under its file name (registered in
    `sys.modules` first: a dataclass looks its module up there while it is defined)."""
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[path.stem] = module
    spec.loader.exec_module(module)
    return module


def main(names: list[str]) -> int:
    figures: dict[str, float] = {}
    for path in BENCHMARKS:
        if names and path.stem.removeprefix("bench_") not in names:
            continue
        print(f"== {path.stem}", flush=True)
        module = load(path)
        t0 = time.perf_counter()
        figures.update(module.run())
        print(f"   ({time.perf_counter() - t0:.1f} s)", flush=True)
    print(json.dumps(figures))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
