"""Recorder speed and memory: row-by-row HDF5 appends vs one np.save of the whole array."""

from __future__ import annotations

import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

from feedbench.daq.recorder import Recorder

from _timing import print_figures  # benchmarks/_timing.py

N_CHANNELS = 8
N_ROWS = 200_000
CHUNK_ROWS = 1000
BLOCK_ROWS = 100
CHANNELS = [f"ch{index}" for index in range(N_CHANNELS)]
UNITS = {name: "m" for name in CHANNELS}


def sample_rows() -> list[list[float]]:
    """One chunk of distinct rows, reused cyclically (the loop must not hold a whole run)."""
    return np.random.default_rng(0).normal(size=(CHUNK_ROWS, N_CHANNELS)).tolist()


def record(path: Path, rows: list[list[float]]) -> float:
    """Append N_ROWS rows one call at a time; returns the wall time in s (close included)."""
    start = time.perf_counter()
    with Recorder(path, CHANNELS, UNITS, {"experiment": "bench"}, CHUNK_ROWS) as recorder:
        for cycle in range(N_ROWS):
            recorder.append(cycle, rows[cycle % CHUNK_ROWS])
    return time.perf_counter() - start


def append_latencies(path: Path, rows: list[list[float]]) -> np.ndarray:
    """Wall time in s of each single append call (the chunk-completing ones write + flush)."""
    latencies = np.empty(N_ROWS)
    clock = time.perf_counter
    with Recorder(path, CHANNELS, UNITS, {"experiment": "bench"}, CHUNK_ROWS) as recorder:
        for cycle in range(N_ROWS):
            start = clock()
            recorder.append(cycle, rows[cycle % CHUNK_ROWS])
            latencies[cycle] = clock() - start
    return latencies


def record_blocks(path: Path, rows: list[list[float]], block_rows: int) -> float:
    """Append the same N_ROWS rows with append_block in blocks; returns the wall time in s."""
    block = np.asarray(rows[:block_rows])
    start = time.perf_counter()
    with Recorder(path, CHANNELS, UNITS, {"experiment": "bench"}, CHUNK_ROWS) as recorder:
        for first in range(0, N_ROWS, block_rows):
            recorder.append_block(np.arange(first, first + block_rows), block)
    return time.perf_counter() - start


def full_array(rows: list[list[float]]) -> np.ndarray:
    """The same N_ROWS rows (cycle column first) held in memory at once."""
    values = np.tile(np.asarray(rows), (N_ROWS // CHUNK_ROWS, 1))
    return np.column_stack([np.arange(N_ROWS, dtype=np.float64), values])


def save_at_once(path: Path, array: np.ndarray) -> float:
    """Baseline: write the whole run with np.save; returns the wall time in s."""
    start = time.perf_counter()
    np.save(path, array)
    return time.perf_counter() - start


def recorder_peak_bytes(path: Path, rows: list[list[float]]) -> int:
    """Peak Python/numpy heap allocated while recording (tracemalloc; HDF5's C heap unseen)."""
    tracemalloc.start()
    try:
        record(path, rows)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def run() -> dict[str, float]:
    rows = sample_rows()
    with tempfile.TemporaryDirectory() as directory:
        folder = Path(directory)
        recorder_s = min(record(folder / f"run{index}.h5", rows) for index in range(3))
        block_s = min(record_blocks(folder / f"b{index}.h5", rows, BLOCK_ROWS) for index in range(3))
        latencies = append_latencies(folder / "latencies.h5", rows)
        flush_calls = latencies[CHUNK_ROWS - 1 :: CHUNK_ROWS]
        array = full_array(rows)
        npsave_s = min(save_at_once(folder / f"run{index}.npy", array) for index in range(3))
        peak_bytes = recorder_peak_bytes(folder / "traced.h5", rows)
    mib = 2.0**20
    figures = {
        "recorder_append_us": recorder_s / N_ROWS * 1e6,
        "recorder_rows_per_s": N_ROWS / recorder_s,
        "recorder_flush_append_ms": float(np.median(flush_calls)) * 1e3,
        "recorder_max_append_ms": float(latencies.max()) * 1e3,
        "recorder_block_rows_per_s": N_ROWS / block_s,
        "npsave_rows_per_s": N_ROWS / npsave_s,
        "recorder_over_npsave": recorder_s / npsave_s,
        "recorder_peak_mib": peak_bytes / mib,
        "full_array_mib": array.nbytes / mib,
        "recorder_peak_over_full_array": peak_bytes / array.nbytes,
    }
    explanations = {
        "recorder_append_us": f"mean µs per Recorder.append, {N_CHANNELS} channels, "
        f"{N_ROWS} rows, chunk {CHUNK_ROWS} (target < 5 µs; budget 1000 µs per bus cycle)",
        "recorder_rows_per_s": "rows/s through Recorder.append incl. HDF5 writes and flushes",
        "recorder_flush_append_ms": "median ms of an append that completes a chunk (write + "
        "flush): the stall the bus loop sees once per chunk",
        "recorder_max_append_ms": "worst single append call (ms), includes OS scheduling noise",
        "recorder_block_rows_per_s": f"rows/s through append_block, {BLOCK_ROWS} rows per call",
        "npsave_rows_per_s": "baseline: rows/s of one np.save of the full array (no row loop)",
        "recorder_over_npsave": "recorder time / np.save time for the same rows",
        "recorder_peak_mib": "peak traced heap while recording (MiB)",
        "full_array_mib": "size of the full run as one array, what np.save needs in memory (MiB)",
        "recorder_peak_over_full_array": "recorder peak memory / full array size",
    }
    print_figures(figures, explanations, 32, "14.3f")
    return figures


if __name__ == "__main__":
    run()
