"""Parsers that never fall over (issue 18.5): every parser that reads bytes from outside, fed
≥ 10⁵ malformed inputs each (the targets of `tests/test_fuzz_parsers.py`: CANopen frames to
the host driver and to the simulated drive, serial DAQ frames, raw Modbus TCP frames to the
simulated devices, CSV + sidecar, EMPS and KUKA .mat, HDF5 recordings, UFF58 FRFs read,
analysed and described as `feedbench analyze FILE.uff` does).

An input is a valid seed after 1–8 random mutations (xor, truncate, insert, delete a byte),
one in ten raw random bytes; seeded, so every run feeds the same inputs. Prints per parser:
inputs, crashes (an exception other than the documented rejection, or a traceback logged by a
library: must be 0), accepted, the most frequent rejection reasons (numbers blanked), and
inputs/s against the valid seeds' parse rate measured in the same run (the baseline).
Each parser runs in its own process: a crash that kills it (a segfault in a C reader) or
a hang (no result within `PARSER_TIMEOUT_S`) is printed with the input it was at, and counted.

Figures per parser: fuzz_<parser>_inputs, fuzz_<parser>_crashes, fuzz_<parser>_per_s,
fuzz_<parser>_vs_valid (fuzz rate / valid rate). `FEEDBENCH_FUZZ_INPUTS` overrides the
count (default 100 000), `FEEDBENCH_FUZZ_TIMEOUT_S` the time limit per parser (900 s).
Run alone: `python benchmarks/bench_fuzz.py [PARSER ...]`.
"""

from __future__ import annotations

import collections
import json
import os
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_fuzz_parsers import (  # noqa: E402  (tests/test_fuzz_parsers.py)
    EXAMPLES, OK, Target, mutate, random_operations, reason_key, targets)

INPUTS = int(os.environ.get("FEEDBENCH_FUZZ_INPUTS", 100_000))
VALID_INPUTS = 500
RAW_SHARE = 10
"""One input in RAW_SHARE is raw random bytes (up to 80)."""
SHOWN_REASONS = 4
PARSER_TIMEOUT_S = float(os.environ.get("FEEDBENCH_FUZZ_TIMEOUT_S", 900))
LAST_INPUT = "input"


def fuzz_input(rng: random.Random, target: Target, number: int) -> bytes:
    """The `number`-th input: raw bytes, or a seed after random mutations."""
    if number % RAW_SHARE == 0:
        return rng.randbytes(rng.randrange(81))
    seed = rng.choice(target.seeds)
    return mutate(seed, random_operations(rng, len(seed)))


def fuzz(target: Target, count: int) -> tuple[collections.Counter[str], int, float]:
    """Outcomes by reason key, crashes, wall time (s) of `count` inputs."""
    rng = random.Random(f"fuzz-{target.name}")
    outcomes: collections.Counter[str] = collections.Counter()
    crashes = 0
    start = time.perf_counter()
    for number in range(count):
        if number % 1000 == 0:
            print(f"   {LAST_INPUT}: {number}", file=sys.stderr, flush=True)
        try:
            outcomes[reason_key(target.outcome(fuzz_input(rng, target, number)))] += 1
        except AssertionError as crash:
            crashes += 1
            if crashes <= 3:
                print(f"   CRASH {str(crash)[:300]}", flush=True)
    return outcomes, crashes, time.perf_counter() - start


def valid_rate(target: Target) -> float:
    """Valid seeds parsed per second (the baseline)."""
    start = time.perf_counter()
    for number in range(VALID_INPUTS):
        target.outcome(target.seeds[number % len(target.seeds)])
    return VALID_INPUTS / (time.perf_counter() - start)


def run(names: list[str] | None = None) -> dict[str, float]:
    """Every parser (or those in `names`), each in a child process; their figures."""
    figures: dict[str, float] = {}
    for name in [n for n in EXAMPLES if not names or n in names]:
        try:
            child = subprocess.run([sys.executable, __file__, "--child", name], text=True,
                                   capture_output=True, timeout=PARSER_TIMEOUT_S)
            output, progress, died = child.stdout, child.stderr, child.returncode
        except subprocess.TimeoutExpired as hung:
            output, progress, died = _text(hung.stdout), _text(hung.stderr), "hang"
        lines = output.splitlines()
        print("\n".join(lines[:-1] if not died else lines), flush=True)
        if died:
            at = [line for line in progress.splitlines() if LAST_INPUT in line][-1:]
            how = (f"no result within {PARSER_TIMEOUT_S:g} s" if died == "hang"
                   else f"exit status {died}")
            print(f"{name:<15s} CRASHED ({how}) at or after "
                  f"{at[0].strip() if at else 'the start'}",
                  flush=True)
            figures[f"fuzz_{name}_crashes"] = 1
        else:
            figures.update(json.loads(lines[-1]))
    return figures


def _text(output: bytes | str | None) -> str:
    return output.decode(errors="replace") if isinstance(output, bytes) else output or ""


def run_here(names: list[str]) -> dict[str, float]:
    """The parsers in `names` in this process (a child of `run`)."""
    figures: dict[str, float] = {}
    scratch = "/dev/shm" if os.path.isdir("/dev/shm") else None
    with tempfile.TemporaryDirectory(dir=scratch) as directory, \
            targets(Path(directory)) as found:
        for name, target in found.items():
            if name not in names:
                continue
            baseline = valid_rate(target)
            outcomes, crashes, seconds = fuzz(target, INPUTS)
            rate = INPUTS / seconds
            print(f"{name:<15s} inputs {INPUTS}  crashes {crashes}  accepted {outcomes[OK]}  "
                  f"{rate:8.0f} inputs/s  (valid input {baseline:.0f}/s: "
                  f"{rate / baseline:.2f}x)", flush=True)
            rejections = [(key, n) for key, n in outcomes.most_common() if key != OK]
            for key, n in rejections[:SHOWN_REASONS]:
                print(f"    {n:7d}  {key}")
            print(f"    {sum(n for _, n in rejections[SHOWN_REASONS:]):7d}  "
                  f"({max(len(rejections) - SHOWN_REASONS, 0)} other reasons)")
            figures.update({f"fuzz_{name}_inputs": INPUTS, f"fuzz_{name}_crashes": crashes,
                            f"fuzz_{name}_per_s": rate,
                            f"fuzz_{name}_vs_valid": rate / baseline})
    return figures


if __name__ == "__main__":
    if sys.argv[1:2] == ["--child"]:
        print(json.dumps(run_here(sys.argv[2:])))
    else:
        run(sys.argv[1:])
