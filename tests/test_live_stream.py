"""The live stream and the building-up results: values against ground truth, no Qt."""

from __future__ import annotations

import json
import sys
import threading

import numpy as np
import pytest
import scipy.signal

from feedbench.daq.live import (
    Decimator, LiveStream, RingBuffer, bucket_size, minmax_decimate, recorded_plan, replay,
)
from feedbench.daq.recorder import Recorder
from feedbench.daq.recording import open_recording
from feedbench.experiments.plan import Plan, Segment
from feedbench.experiments.runner import BLOCK_CYCLES, StopRequest
from feedbench.gui.live_results import (
    ChirpMobility, FrictionCurve, SineStreamFrf, live_result_for,
)
from feedbench.models.friction import AnderssonFriction
from feedbench.units import MM_PER_MIN

CHANNELS = ("x_ref", "position", "velocity", "force")
CYCLE_S = 1e-3


def segment(label: str, kind: str, n: int, **info: float) -> Segment:
    return Segment(label, kind, np.zeros(n), info=info)


def feed_like_runner(observers, plan: Plan, rows: np.ndarray, first_cycle: int = 7,
                     lead_in: int = 13) -> None:
    """Call observers as `Runner.run` does: `lead_in` enable cycles, then each segment's
    rows, blocks of BLOCK_CYCLES flushed regardless of segment boundaries."""
    for obs in observers:
        obs.on_start(plan, CHANNELS)
    cycles = np.arange(first_cycle, first_cycle + len(rows))
    starts = lead_in + np.cumsum([0] + [s.n_cycles for s in plan.segments[:-1]])
    next_segment = 0
    for begin in range(0, len(rows), BLOCK_CYCLES):
        end = min(begin + BLOCK_CYCLES, len(rows))
        while next_segment < len(starts) and starts[next_segment] < end:
            for obs in observers:
                obs.on_segment(next_segment, plan.segments[next_segment],
                               int(cycles[starts[next_segment]]))
            next_segment += 1
        for obs in observers:
            obs.on_block(cycles[begin:end], rows[begin:end])
    for obs in observers:
        obs.on_stop("complete", "")


# ring buffer and decimation

def test_ring_buffer_keeps_the_latest_rows_across_wraparound():
    ring = RingBuffer(1000, ("a", "b"))
    values = np.column_stack([np.arange(3500.0), -np.arange(3500.0)])
    for begin in range(0, 3500, 450):
        chunk = values[begin:begin + 450]
        ring.write(np.arange(begin, begin + len(chunk)), chunk)
    cycles, copied, first = ring.copy_rows(2600, 3500, [1, 0])
    assert ring.written == 3500 and first == 2600
    np.testing.assert_array_equal(cycles, np.arange(2600, 3500))
    np.testing.assert_array_equal(copied, values[2600:3500, [1, 0]].T)


def test_ring_buffer_cuts_rows_already_overwritten():
    ring = RingBuffer(100, ("a",))
    ring.write(np.arange(250), np.arange(250.0)[:, None])
    _, copied, first = ring.copy_rows(100, 250, [0])
    assert first == 150
    np.testing.assert_array_equal(copied[0], np.arange(150.0, 250.0))


def test_minmax_decimation_keeps_a_one_sample_spike_and_dip():
    values = np.zeros((1, 100_000))
    values[0, 12_345], values[0, 77_001] = 7.5, -3.25
    t = np.arange(100_000) * CYCLE_S
    k = bucket_size(100_000, 800)
    t_out, out = minmax_decimate(t, values, k)
    assert k == 125 and out.shape == (1, 1600)
    assert out.max() == 7.5 and out.min() == -3.25
    assert t_out[np.argmax(out[0])] == pytest.approx(12_250 * CYCLE_S)
    assert t_out[np.argmin(out[0])] == pytest.approx(77_000 * CYCLE_S)


def test_minmax_decimation_with_a_short_last_bucket():
    values = np.arange(10.0)[None]
    t_out, out = minmax_decimate(np.arange(10.0), values, 4)
    np.testing.assert_array_equal(out[0], [0, 3, 4, 7, 8, 9])
    np.testing.assert_array_equal(t_out, [0, 0, 4, 4, 8, 8])


def plan_of(*segments: Segment, cycle_s: float = CYCLE_S) -> Plan:
    return Plan("test", 8, list(segments), {}, cycle_s)


def test_incremental_decimator_equals_decimating_the_whole_window_at_once():
    rng = np.random.default_rng(1)
    n = 23_456
    rows = rng.normal(size=(n, len(CHANNELS)))
    stream = LiveStream(span_max_s=10.0)
    decimator = Decimator(stream, span_s=5.0, n_buckets=700)
    plan = plan_of(segment("all", "measure", n - 13))
    stream.on_start(plan, CHANNELS)
    for begin in range(0, n, 50):
        stream.on_block(np.arange(begin, begin + 50)[: n - begin], rows[begin:begin + 50])
        if rng.random() < 0.2:
            decimator.frame()
    frame = decimator.frame()
    k = frame.samples_per_point
    start = (n - 5000) // k * k
    expected_t, expected = minmax_decimate(np.arange(start, n) * CYCLE_S, rows.T[:, start:], k)
    assert k == bucket_size(5000, 700) == 8
    np.testing.assert_allclose(frame.t, expected_t)
    for i, name in enumerate(CHANNELS):
        np.testing.assert_array_equal(frame.channels[name], expected[i])
    assert frame.t_end == pytest.approx((n - 1) * CYCLE_S)
    assert frame.t[0] == pytest.approx(start * CYCLE_S)


def test_reader_never_sees_torn_rows_while_the_producer_overwrites_the_ring():
    """Every channel carries its sample number: any torn or misplaced read shows. The GIL
    is handed over every microsecond so the writer runs in the middle of the reader's copies."""
    previous = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        _torn_read_check()
    finally:
        sys.setswitchinterval(previous)


def _torn_read_check() -> None:
    stream = LiveStream(span_max_s=0.2)
    n_total, frames = 200_000, []
    plan = plan_of(segment("all", "measure", n_total))
    stream.on_start(plan, CHANNELS)
    done = threading.Event()

    def produce() -> None:
        for begin in range(0, n_total, 50):
            cycles = np.arange(begin, begin + 50)
            stream.on_block(cycles, np.repeat(cycles[:, None].astype(float), 4, axis=1))
        done.set()

    producer = threading.Thread(target=produce)
    producer.start()
    raw, coarse = Decimator(stream, 0.2, 10_000), Decimator(stream, 0.2, 20)
    while not done.is_set():
        frames += [raw.frame(), coarse.frame()]
    producer.join()
    frames += [raw.frame(), coarse.frame()]
    assert stream.n_received == n_total and len(frames) > 10
    for frame in frames:
        index = np.round(frame.t / CYCLE_S)
        for values in frame.channels.values():
            if frame.samples_per_point == 1:
                np.testing.assert_array_equal(values, index)
            else:
                np.testing.assert_array_equal(values[0::2], index[0::2])
                assert np.all(values[1::2] - values[0::2] <= frame.samples_per_point - 1)
    assert frames[-1].t_end == pytest.approx((n_total - 1) * CYCLE_S)


def test_state_reports_step_progress_and_time_left():
    plan = plan_of(segment("accelerate", "move", 100, feed_mm_min=500.0),
                   segment("measure positive 500 mm/min", "measure", 200, feed_mm_min=500.0),
                   segment("stop", "move", 300))
    stream = LiveStream()
    stream.on_start(plan, CHANNELS)
    stream.on_segment(0, plan.segments[0], 20)
    stream.on_block(np.arange(0, 50), np.zeros((50, 4)))       # 20 enable cycles + 30
    assert stream.state().cycles_done == 30
    stream.on_segment(1, plan.segments[1], 120)
    stream.on_block(np.arange(50, 220), np.zeros((170, 4)))
    state = stream.state()
    assert state.cycles_done == 200 and state.cycles_total == 600
    assert state.fraction == pytest.approx(1 / 3)
    assert state.bench_time_left_s == pytest.approx(0.4)
    assert state.step_text == "step 2/3: measure positive 500 mm/min (feed 500 mm/min)"
    stream.on_stop("aborted", "stop button")
    assert (stream.state().status, stream.state().reason) == ("aborted", "stop button")


# replay

class Collect:
    """Observer keeping everything it is handed."""

    def on_start(self, plan, channels):
        self.plan, self.channels, self.blocks, self.segments = plan, channels, [], []

    def on_segment(self, index, segment, cycle):
        self.segments.append((index, segment.label, cycle))

    def on_block(self, cycles, block):
        self.blocks.append((cycles.copy(), block.copy()))

    def on_stop(self, status, reason):
        self.stop = (status, reason)


def write_recording(path, kinds=(("enable", 30), ("move", 120), ("measure", 275), ("move", 80),
                                 ("disable", 20))):
    rng = np.random.default_rng(3)
    n = sum(length for _, length in kinds)
    rows = rng.normal(size=(n, len(CHANNELS)))
    with Recorder(path, CHANNELS, {c: "m" for c in CHANNELS},
                  {"experiment": "friction_sweep", "cycle_s": CYCLE_S,
                   "config": {"limits": {"force_N": 900.0}}}) as recorder:
        cycle = 100
        for i, (kind, length) in enumerate(kinds):
            recorder.event(cycle, "segment", json.dumps({"label": f"{kind} {i}", "kind": kind,
                                                         "feed_mm_min": 10.0 * i}))
            recorder.append_block(np.arange(cycle, cycle + length),
                                  rows[cycle - 100:cycle - 100 + length])
            cycle += length
    return rows


def test_replay_hands_over_every_recorded_sample_and_step(tmp_path):
    rows = write_recording(tmp_path / "run.h5")
    recording = open_recording(tmp_path / "run.h5")
    collect = Collect()
    status = replay(recording, [collect], speed=0)
    plan, starts = recorded_plan(recording)
    assert status == "complete" and collect.stop == ("complete", "")
    assert [s.kind for s in plan.segments] == ["move", "measure", "move"]
    assert [s.n_cycles for s in plan.segments] == [120, 275, 80] and starts == [130, 250, 525]
    assert collect.segments == [(0, "move 1", 130), (1, "measure 2", 250), (2, "move 3", 525)]
    assert plan.segments[1].info == {"feed_mm_min": 20.0}
    np.testing.assert_array_equal(np.concatenate([b for _, b in collect.blocks]), rows)
    np.testing.assert_array_equal(np.concatenate([c for c, _ in collect.blocks]),
                                  np.arange(100, 100 + len(rows)))
    assert max(len(c) for c, _ in collect.blocks) == BLOCK_CYCLES


def test_replay_stops_when_asked(tmp_path):
    write_recording(tmp_path / "run.h5")
    stop, collect = StopRequest(), Collect()
    stop.request("enough")
    assert replay(open_recording(tmp_path / "run.h5"), [collect], speed=0, stop=stop) == "stopped"
    assert collect.stop == ("stopped", "enough") and len(collect.blocks) == 1


# building-up results

LAW = {"positive": AnderssonFriction(44.2, 84.0, 387.4 * MM_PER_MIN, 0.0028 * 60e3),
       "negative": AnderssonFriction(38.7, 88.0, 421.0 * MM_PER_MIN, 0.0025 * 60e3)}


def friction_run(feeds_mm_min, measure: int = 173):
    """Segments and rows of a friction sweep whose measured force follows LAW exactly
    during each measure window (noise elsewhere)."""
    rng = np.random.default_rng(5)
    segments, parts = [], []
    for feed in feeds_mm_min:
        for sign, name in ((1, "positive"), (-1, "negative")):
            v = sign * feed * MM_PER_MIN
            force = sign * LAW[name].force(abs(v))
            for kind, n in (("move", 61), ("measure", measure), ("move", 47)):
                segments.append(segment(f"{kind} {sign * feed}", kind, n, feed_mm_min=sign * feed))
                rows = rng.normal(size=(n, 4)) * 50
                if kind == "measure":
                    rows[:, 2] = v + 1e-6 * np.sin(np.arange(n))
                    rows[:, 3] = force + 0.5 * np.cos(np.arange(n))
                parts.append(rows)
    return plan_of(*segments), np.concatenate([np.zeros((13, 4)), *parts])


def test_friction_curve_points_are_the_window_means_and_the_fit_finds_the_law():
    feeds = [25, 50, 100, 200, 400, 800, 1500]
    plan, rows = friction_run(feeds)
    curve = FrictionCurve()
    feed_like_runner([curve], plan, rows)
    assert curve.version == 14 and len(curve.points) == 14
    v, force = np.array(curve.points).T
    mean_cos = np.cos(np.arange(173)).mean()
    for i, feed in enumerate(feeds):
        for j, (sign, name) in enumerate(((1, "positive"), (-1, "negative"))):
            speed = feed * MM_PER_MIN
            assert v[2 * i + j] == pytest.approx(sign * speed, rel=1e-4)
            assert force[2 * i + j] == pytest.approx(
                sign * LAW[name].force(speed) + 0.5 * mean_cos, abs=1e-9)
    view = curve.view()
    assert [c.name for c in view.panels[0].curves] == ["measured", "fit positive", "fit negative"]
    assert "F_c 44.2 N" in view.summary and "F_c 38.7 N" in view.summary
    assert curve.view() is view


def test_friction_curve_fits_a_direction_only_with_enough_points():
    plan, rows = friction_run([100, 200, 400])
    curve = FrictionCurve()
    feed_like_runner([curve], plan, rows)
    assert [c.name for c in curve.view().panels[0].curves] == ["measured"]


def mobility_filter(fs: float):
    """A discrete single-DOF mobility (velocity/force, 60 Hz, ζ = 0.15, 8 kg)."""
    m, f_n, zeta = 8.0, 60.0, 0.15
    k, c = m * (2 * np.pi * f_n) ** 2, 2 * zeta * np.sqrt(m * m * (2 * np.pi * f_n) ** 2)
    return scipy.signal.bilinear([1.0, 0.0], [m, c, k], fs)


def test_chirp_mobility_builds_up_sweep_by_sweep_and_matches_the_true_frf():
    fs = 1.0 / CYCLE_S
    b, a = mobility_filter(fs)
    rng = np.random.default_rng(11)
    segments, parts = [], []
    for rep in range(3):
        force = 20 * rng.normal(size=4000)
        velocity = scipy.signal.lfilter(b, a, np.concatenate([np.zeros(500), force]))[500:]
        segments += [segment(f"settle {rep}", "settle", 333), segment(f"sweep {rep}", "excite", 4000)]
        parts += [rng.normal(size=(333, 4)), np.column_stack([0 * force, 0 * force, velocity, force])]
    plan = plan_of(*segments)
    mobility = ChirpMobility()
    versions = []

    class Watch(Collect):
        def on_block(self, cycles, block):
            versions.append(mobility.version)

    feed_like_runner([mobility, Watch()], plan, np.concatenate([np.zeros((13, 4)), *parts]))
    assert mobility.version == 3 and sorted(set(versions)) == [0, 1, 2, 3]
    view = mobility.view()
    magnitude, coherence = view.panels
    f, H = magnitude.curves[0].x, magnitude.curves[0].y
    _, truth = scipy.signal.freqz(b, a, worN=f, fs=fs)
    assert f[0] >= 20.0 and f[-1] <= 150.0
    assert np.max(np.abs(H / np.abs(truth) - 1)) < 0.05
    assert coherence.curves[0].y.min() > 0.95
    assert view.summary.startswith("3 sweeps (10 Welch averages)")  # (12000 − 2048) // 1024 + 1


def test_sine_stream_points_carry_the_true_gain_phase_and_r_squared():
    fs = 1.0 / CYCLE_S
    frequencies = [20.0, 20.25, 35.0, 80.0]
    gain = {f: 1e-3 * (1 + f / 100) for f in frequencies}
    phase = {f: -0.01 * f for f in frequencies}
    segments, parts = [], []
    for f in frequencies:
        n = int(round(5 * fs / f))
        t = np.arange(n) / fs
        force = 30 * np.cos(2 * np.pi * f * t + 0.3)
        response = 30 * gain[f] * np.cos(2 * np.pi * f * t + 0.3 + phase[f])
        segments.append(segment(f"{f} Hz", "excite", n, frequency_Hz=f))
        parts.append(np.column_stack([0 * t, 0 * t, response, force]))
    result = live_result_for("sine_stream")
    assert isinstance(result, SineStreamFrf)
    feed_like_runner([result], plan_of(*segments), np.concatenate([np.zeros((13, 4)), *parts]))
    magnitude, phase_panel, r2 = result.view().panels
    np.testing.assert_allclose(magnitude.curves[0].x, frequencies)
    np.testing.assert_allclose(magnitude.curves[0].y, [gain[f] for f in frequencies], rtol=1e-9)
    np.testing.assert_allclose(phase_panel.curves[0].y, [np.degrees(phase[f]) for f in frequencies],
                               atol=1e-7)
    assert r2.curves[0].y.min() > 1 - 1e-12


def test_unknown_experiment_has_no_live_result():
    assert live_result_for("no_such_experiment") is None
