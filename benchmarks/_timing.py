"""Helpers the benchmarks share: best-of-n wall time, the one-line-per-figure printout,
another process burning one CPU (a machine with one core busy), the CPU time of child
processes."""

from __future__ import annotations

import resource
import subprocess
import sys
import time
from contextlib import contextmanager
from typing import Callable, Iterator, TypeVar

Result = TypeVar("Result")


def best_of(action: Callable[[], Result], repeats: int) -> tuple[float, Result]:
    """Shortest wall time (s) of `repeats` calls, the least disturbed by other processes,
    and the last call's result."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        result = action()
        best = min(best, time.perf_counter() - start)
    return best, result


def best_seconds(action: Callable[[], object], repeats: int) -> float:
    """Shortest wall time (s) of `repeats` calls of `action`."""
    return best_of(action, repeats)[0]


def print_figures(figures: dict[str, float], notes: dict[str, str], name_width: int,
                  value_format: str) -> None:
    """One line per figure: name, value (`value_format`, e.g. "10.3f") and its note."""
    for name, value in figures.items():
        print(f"{name:<{name_width}s} {value:{value_format}}  {notes[name]}")


@contextmanager
def burning_one_cpu() -> Iterator[None]:
    """While inside, another process spins on one CPU; killed on exit."""
    burner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        yield
    finally:
        burner.kill()
        burner.wait()


def children_cpu_s() -> float:
    """CPU time (s) of this process's ended child processes (and theirs, when waited for)."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime
