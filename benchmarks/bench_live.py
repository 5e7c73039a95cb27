"""Live window under load: 8 channels at 10 kHz for 60 s, a 20 s span, offscreen Qt.

A producer thread plays a real-time acquisition (blocks of 50 samples paced by the wall
clock) into the HDF5 recorder and the live stream; the window redraws from the stream on
its own timer. Figures: the window's redraw rate, the recorder's lag behind the
acquisition clock (with and without the window), the samples on disk and their gaps, and
the cost of one frame drawn from raw samples against one drawn from the min/max copy.
"""

from __future__ import annotations

import os
import tempfile
import threading
import time
from pathlib import Path

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import numpy as np  # noqa: E402

from feedbench.daq.live import Decimator, LiveStream  # noqa: E402
from feedbench.daq.recorder import Recorder  # noqa: E402
from feedbench.daq.recording import open_recording  # noqa: E402
from feedbench.experiments.plan import Plan, Segment  # noqa: E402
from feedbench.gui.live_window import LiveWindow, qt_app  # noqa: E402

N_CHANNELS = 8
RATE_HZ = 10_000
DURATION_S = 60.0
BASELINE_S = 10.0
SPAN_S = 20.0
BLOCK = 50
NAMES = tuple(f"ch{i}" for i in range(N_CHANNELS))
UNITS = {name: ("m", "m/s", "N", "m/s²")[i % 4] for i, name in enumerate(NAMES)}


def signals(first: int, n: int) -> np.ndarray:
    """n samples (rows) of 8 channels from sample number `first`: sines, noise, a spike
    every 10 000 samples."""
    index = np.arange(first, first + n)
    t = index / RATE_HZ
    rows = np.sin(2 * np.pi * (1.0 + np.arange(N_CHANNELS)) * t[:, None])
    rows += 0.05 * np.cos(2 * np.pi * 997.0 * t)[:, None]
    rows[index % 10_000 == 0] += 3.0
    return rows


class Acquisition(threading.Thread):
    """The producer: blocks paced to real time into the recorder and the stream.

    `lags` holds, per block, how late (s) its last sample reached the recorder against
    the acquisition clock; `observer_s` the time spent handing blocks to the stream.
    """

    def __init__(self, recorder: Recorder, stream: LiveStream | None, duration_s: float) -> None:
        super().__init__(name="acquisition")
        self.recorder, self.stream = recorder, stream
        self.n_total = int(duration_s * RATE_HZ)
        self.lags = np.zeros(self.n_total // BLOCK)
        self.observer_s = np.zeros(self.n_total // BLOCK)

    def run(self) -> None:
        plan = Plan("bench_live", 0, [Segment("acquire", "measure",
                                              np.broadcast_to(0.0, (self.n_total,)))],
                    {}, 1.0 / RATE_HZ)
        if self.stream is not None:
            self.stream.on_start(plan, NAMES)
            self.stream.on_segment(0, plan.segments[0], 0)
        start = time.perf_counter()
        for b, first in enumerate(range(0, self.n_total, BLOCK)):
            due = start + (first + BLOCK) / RATE_HZ
            pause = due - time.perf_counter()
            if pause > 0:
                time.sleep(pause)
            cycles, rows = np.arange(first, first + BLOCK), signals(first, BLOCK)
            self.recorder.append_block(cycles, rows)
            self.lags[b] = time.perf_counter() - due
            if self.stream is not None:
                t0 = time.perf_counter()
                self.stream.on_block(cycles, rows)
                self.observer_s[b] = time.perf_counter() - t0
        if self.stream is not None:
            self.stream.on_stop("complete", "")


def acquire(path: Path, duration_s: float, with_window: bool) -> dict[str, float]:
    """One paced acquisition, with or without the live window; its figures."""
    app = qt_app()
    stream = LiveStream(span_max_s=SPAN_S) if with_window else None
    recorder = Recorder(path, NAMES, UNITS, {"experiment": "bench_live"}, chunk_rows=1000)
    window = LiveWindow(stream, UNITS, span_s=SPAN_S, fps=60.0) if with_window else None
    if window is not None:
        window.show()
        app.processEvents()
        frames0, paints0 = window.frames, window.paints
    producer = Acquisition(recorder, stream, duration_s)
    t0 = time.perf_counter()
    producer.start()
    while producer.is_alive():
        app.processEvents()
        time.sleep(0.001)
    elapsed = time.perf_counter() - t0
    recorder.close()
    recording = open_recording(path)
    out = {"n_samples": recording.n_samples, "n_gaps": recording.n_gaps,
           "lag_p99_s": float(np.percentile(producer.lags, 99)), "lag_max_s": float(producer.lags.max()),
           "samples_equal": float(np.array_equal(recording.channels["ch3"][-BLOCK:],
                                                 signals(producer.n_total - BLOCK, BLOCK)[:, 3]))}
    if window is not None:
        out.update(fps=(window.frames - frames0) / elapsed, paints_per_s=(window.paints - paints0) / elapsed,
                   observer_max_s=float(producer.observer_s.max()),
                   **frame_costs(window, stream))
        window.close()
    return out


def frame_costs(window: LiveWindow, stream: LiveStream, repeats: int = 5) -> dict[str, float]:
    """Seconds to build and paint one frame from the 20 s of raw samples (200 000 points
    per channel) and from the window's min/max copy (two points per pixel)."""
    costs = {}
    for name, buckets in (("raw", 10**9), ("decimated", max(window.trace_view.width(), 200))):
        start = time.perf_counter()
        for _ in range(repeats):
            window.traces.draw(Decimator(stream, SPAN_S, buckets).frame(), False, time.monotonic())
            window.trace_view.grab()
        costs[f"frame_{name}_s"] = (time.perf_counter() - start) / repeats
    return costs


def run(duration_s: float = DURATION_S) -> dict[str, float]:
    """Measure, print and return the figures."""
    with tempfile.TemporaryDirectory() as tmp:
        live = acquire(Path(tmp) / "live.h5", duration_s, with_window=True)
        baseline = acquire(Path(tmp) / "baseline.h5", min(BASELINE_S, duration_s), with_window=False)
    figures = {
        "live_fps": live["fps"],
        "live_paints_per_s": live["paints_per_s"],
        "live_samples": float(live["n_samples"]),
        "live_gaps": float(live["n_gaps"]),
        "live_recorder_lag_p99_ms": 1e3 * live["lag_p99_s"],
        "live_recorder_lag_max_ms": 1e3 * live["lag_max_s"],
        "baseline_recorder_lag_p99_ms": 1e3 * baseline["lag_p99_s"],
        "live_observer_block_max_us": 1e6 * live["observer_max_s"],
        "live_frame_raw_ms": 1e3 * live["frame_raw_s"],
        "live_frame_decimated_ms": 1e3 * live["frame_decimated_s"],
    }
    print(f"  {N_CHANNELS} channels at {RATE_HZ} Hz for {duration_s:g} s, window span {SPAN_S:g} s "
          "(offscreen Qt)")
    print(f"  window redraws            {figures['live_fps']:7.1f} frames/s (target ≥ 30; "
          f"{figures['live_paints_per_s']:.1f} Qt repaints/s)")
    print(f"  samples on disk           {live['n_samples']:7d} of {int(duration_s * RATE_HZ)}, "
          f"gaps {live['n_gaps']}, last block equal to the source: {bool(live['samples_equal'])}")
    print(f"  recorder lag p99 / max    {figures['live_recorder_lag_p99_ms']:7.2f} / "
          f"{figures['live_recorder_lag_max_ms']:.2f} ms behind the acquisition clock with the "
          f"window; {figures['baseline_recorder_lag_p99_ms']:.2f} ms p99 without it "
          f"(ratio {figures['live_recorder_lag_p99_ms'] / figures['baseline_recorder_lag_p99_ms']:.2f})")
    print(f"  stream.on_block worst     {figures['live_observer_block_max_us']:7.0f} µs per 50-sample "
          "block (the producer's whole cost of the window)")
    print(f"  one frame raw / min-max   {figures['live_frame_raw_ms']:7.1f} / "
          f"{figures['live_frame_decimated_ms']:.1f} ms (raw is "
          f"{figures['live_frame_raw_ms'] / figures['live_frame_decimated_ms']:.1f}× slower)")
    return figures


if __name__ == "__main__":
    run()
