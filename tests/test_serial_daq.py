"""Serial streaming DAQ: the pyserial driver against the simulated instrument over a real pty."""

from __future__ import annotations

import binascii
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
import serial

from feedbench.devices.cycle_io import DaqStream
from feedbench.drivers.serial_daq import (
    CHANNELS, FrameParser, SerialDaq, SerialDaqError, data_frame_bytes,
)
from feedbench.sim_backends.serial_daq import (
    GARBAGE_BYTES, SimulatedSerialDaq, encode_data_frames, encode_frame,
)

RATE = 10_000
NAMES = [c.name for c in CHANNELS]
FULL_SCALE = np.array([c.full_scale for c in CHANNELS])
LSB = FULL_SCALE / 2 ** 23
FRAME_12 = data_frame_bytes(12)


def waveform(t: np.ndarray) -> np.ndarray:
    """Known test signal: a distinct sine per input at 0.6 of its full scale (n, 12) SI."""
    frequencies = 37.0 * np.arange(1, len(CHANNELS) + 1)
    return 0.6 * FULL_SCALE * np.sin(2 * np.pi * frequencies * t[:, None] + 0.3)


def expected(sequence: np.ndarray, columns: list[int] | None = None) -> np.ndarray:
    """What an ideal 24-bit ADC delivers for `waveform` at the given sample counters."""
    columns = list(range(len(CHANNELS))) if columns is None else columns
    return np.round(waveform(sequence / RATE) / LSB)[:, columns] * LSB[columns]


@pytest.fixture
def instrument():
    with SimulatedSerialDaq(cycle_s=1e-3, rate_hz=RATE) as sim:
        yield sim


@pytest.fixture
def free_running(instrument):
    instrument.free_run(waveform)
    return instrument


def stream(daq: SerialDaq, seconds: float, during=None):
    """Start, wait (optionally act half-way), stop, and return everything received.

    The instrument streams for at least `seconds` (from its START reply to the STOP send)."""
    daq.start()
    time.sleep(seconds / 2)
    if during is not None:
        during()
    time.sleep(seconds / 2)
    daq.stop()
    return daq.read_available()


def test_crc_is_ccitt_false():
    assert binascii.crc_hqx(b"123456789", 0xFFFF) == 0x29B1
    assert encode_frame(0x52, b"OK")[-2:] == binascii.crc_hqx(b"\x52\x02OK", 0xFFFF).to_bytes(
        2, "little")


def test_known_waveform_at_10khz_for_1s_arrives_bit_exact(free_running):
    with SerialDaq(free_running.port, NAMES, RATE) as daq:
        assert daq.identity == "FEEDBENCH,SIM-DAQ12,0,1.0"
        sequence, samples = stream(daq, 1.1)
        assert len(sequence) >= RATE  # ≥ 1 s of samples
        np.testing.assert_array_equal(np.diff(sequence), 1)
        np.testing.assert_array_equal(samples, expected(sequence))
        assert (daq.crc_errors, daq.dropped_frames, daq.skipped_bytes) == (0, 0, 0)
        assert len(sequence) == free_running.frames_sent


@pytest.mark.parametrize("kind, crc_errors, skipped", [
    ("flip", 1, FRAME_12),  # the damaged frame's bytes are passed over
    ("truncate", 1, FRAME_12 // 2),  # its first half, then the next sync is found
])
def test_corrupted_frame_is_counted_and_the_stream_resynchronises(
        free_running, kind, crc_errors, skipped):
    with SerialDaq(free_running.port, NAMES, RATE) as daq:
        sequence, samples = stream(daq, 0.3, lambda: free_running.corrupt_next_frame(kind))
        gaps = np.flatnonzero(np.diff(sequence) != 1)
        assert daq.crc_errors == crc_errors
        assert daq.dropped_frames == 1
        assert daq.skipped_bytes == skipped
        assert len(gaps) == 1 and sequence[gaps[0] + 1] - sequence[gaps[0]] == 2
        assert len(sequence) == free_running.frames_sent - 1
        assert gaps[0] > 500 and len(sequence) - gaps[0] > 500  # good frames on both sides
        np.testing.assert_array_equal(samples, expected(sequence))


def test_garbage_burst_is_skipped_without_losing_a_frame(free_running):
    with SerialDaq(free_running.port, NAMES, RATE) as daq:
        sequence, samples = stream(daq, 0.3, lambda: free_running.corrupt_next_frame("garbage"))
        np.testing.assert_array_equal(np.diff(sequence), 1)
        assert (daq.crc_errors, daq.dropped_frames) == (0, 0)
        assert daq.skipped_bytes == GARBAGE_BYTES
        np.testing.assert_array_equal(samples, expected(sequence))


def test_parser_handles_frames_split_at_every_byte_boundary():
    sequence = np.arange(2 ** 32 - 3, 2 ** 32 + 3) % 2 ** 32  # wraps through zero
    counts = np.array([[-2 ** 23, -1, 0, 1, 2 ** 23 - 1]] * len(sequence), np.int32)
    wire = encode_data_frames(sequence, counts).tobytes() + encode_frame(0x52, b"OK")
    parser = FrameParser(5)
    blocks, replies = zip(*(parser.feed(wire[i:i + 1]) for i in range(len(wire))))
    received = np.concatenate([b.sequence for b in blocks])
    np.testing.assert_array_equal(received, np.arange(2 ** 32 - 3, 2 ** 32 + 3))
    np.testing.assert_array_equal(np.concatenate([b.samples for b in blocks]), counts)
    assert sum(replies, []) == ["OK"]
    assert (parser.crc_errors, parser.dropped_frames, parser.skipped_bytes) == (0, 0, 0)


def test_start_and_stop_gate_the_stream(free_running):
    with SerialDaq(free_running.port, NAMES, RATE) as daq:
        time.sleep(0.1)
        assert len(daq.read_available().sequence) == 0  # power-on: stopped
        first, _ = stream(daq, 0.2)
        sent = free_running.frames_sent
        time.sleep(0.2)
        assert len(daq.read_available().sequence) == 0 and free_running.frames_sent == sent
        second, _ = stream(daq, 0.2)
        # each run lasted ≥ 0.2 s; the sample clock ran on through the ≥ 0.2 s pause
        assert len(first) >= 0.2 * RATE - 10 and len(second) >= 0.2 * RATE - 10
        assert second[0] - first[-1] >= 0.2 * RATE - 10
        assert daq.dropped_frames == 0  # a restart is not a loss


def test_channel_selection_and_order_are_respected(free_running):
    wanted = ["dyn_fz", "acc_tool_x", "actuator_force"]
    with SerialDaq(free_running.port, wanted, RATE) as daq:
        sequence, samples = stream(daq, 0.2)
        assert samples.shape == (len(sequence), 3) and len(sequence) > 1000
        np.testing.assert_array_equal(samples, expected(sequence, [8, 0, 11]))
        assert free_running.mask == 0b1001_0000_0001


def test_rate_is_configurable_and_the_link_budget_enforced(free_running):
    with SerialDaq(free_running.port, NAMES[:4], 20_000) as daq:
        sequence, samples = stream(daq, 0.3)
        assert len(sequence) >= 0.3 * 20_000 - 10
        np.testing.assert_array_equal(samples, np.round(
            waveform(sequence / 20_000) / LSB)[:, :4] * LSB[:4])
    with pytest.raises(SerialDaqError, match="link"):
        SerialDaq(free_running.port, NAMES, 25_000)  # 46 B × 25 kHz = 1.15 MB/s


def test_configuration_refused_while_streaming(free_running):
    with SerialDaq(free_running.port, NAMES, RATE) as daq:
        daq.start()
        with pytest.raises(SerialDaqError, match="busy"):
            daq.command("RATE 20000")
        daq.stop()
        assert free_running.rate_hz == RATE


def test_bench_locked_samples_carry_the_bench_time(instrument):
    """The world pushes one bus cycle at a time; counter / rate is the bench time."""
    per_cycle = instrument.samples_per_cycle
    assert per_cycle == 10

    def push_cycles(first: int, count: int) -> None:
        for cycle in range(first, first + count):
            counter = cycle * per_cycle + np.arange(per_cycle)
            instrument.push(waveform(counter / RATE))

    with SerialDaq(instrument.port, NAMES, RATE) as daq:
        push_cycles(0, 5)  # before START: sampled, not sent
        daq.start()
        push_cycles(5, 200)
        daq.stop()
        push_cycles(205, 5)
        sequence, samples = daq.read_available()
        np.testing.assert_array_equal(sequence, np.arange(50, 2050))
        np.testing.assert_array_equal(samples, expected(sequence))
    with pytest.raises(ValueError, match="expects"):
        instrument.push(np.zeros((7, len(CHANNELS))))


def test_overrun_when_the_host_stops_reading_shows_as_a_counted_gap():
    """A small FIFO and a host that does not read: new frames are lost, and the host sees
    exactly that many missing counter values once it reads again."""
    with SimulatedSerialDaq(fifo_bytes=100 * FRAME_12, host_stall_s=0.2) as sim, \
            serial.Serial(sim.port, timeout=0.2) as port:
        parser = FrameParser(len(CHANNELS))
        port.write(b"START\n")
        assert parser.feed(port.read(8))[1] == ["OK"]
        for cycle in range(1000):  # 10 000 frames, 460 kB, never read meanwhile
            sim.push(np.zeros((10, len(CHANNELS))))
        received = drain(port, parser)
        sim.push(np.zeros((10, len(CHANNELS))))
        received += drain(port, parser)
        assert sim.overruns > 9000
        assert received == sim.frames_sent == 10_010 - sim.overruns
        assert parser.dropped_frames == sim.overruns
        assert parser.crc_errors == 0


def test_bench_locked_instrument_waits_for_a_host_that_is_behind_but_reading():
    """The bench pushes 276 kB at once, a host reading 4 kB every 5 ms is behind (the FIFO
    and the pty hold a quarter of it): the instrument waits for it, no frame overruns."""
    with SimulatedSerialDaq(fifo_bytes=1000 * FRAME_12) as sim, \
            serial.Serial(sim.port, timeout=0.2) as port:
        parser = FrameParser(len(CHANNELS))
        port.write(b"START\n")
        assert parser.feed(port.read(8))[1] == ["OK"]
        received, done = [0], threading.Event()

        def slow_host() -> None:
            while not done.is_set() or port.in_waiting:
                received[0] += len(parser.feed(port.read(min(4096, port.in_waiting or 1)))[0]
                                   .sequence)
                time.sleep(5e-3)

        host = threading.Thread(target=slow_host)
        host.start()
        for _ in range(600):  # 6000 frames, 276 kB
            sim.push(np.zeros((10, len(CHANNELS))))
        deadline = time.monotonic() + 10.0
        while received[0] < 6000 and time.monotonic() < deadline:
            time.sleep(0.01)
        done.set()
        host.join()
    assert sim.overruns == 0 and sim.frames_sent == 6000
    assert received[0] == 6000 and parser.dropped_frames == 0


def drain(port: serial.Serial, parser: FrameParser) -> int:
    """Read until the line is quiet; number of data frames parsed."""
    frames = 0
    while chunk := port.read(65536):
        frames += len(parser.feed(chunk)[0].sequence)
    return frames


def test_host_buffer_overflow_is_counted(free_running):
    with SerialDaq(free_running.port, NAMES, RATE, buffer_s=0.01) as daq:
        sequence, _ = stream(daq, 0.3)
        assert daq.overflowed_frames > 2000
        assert daq.overflowed_frames + len(sequence) == free_running.frames_sent
        assert daq.dropped_frames == 0


def test_compiled_data_frames_are_the_bytes_of_quantize_and_encode():
    """`data_frames` (what a streaming cycle sends) is `encode_data_frames` of `quantize`, bit
    for bit: any channel mask, rounding ties, saturation both ways, counters that wrap."""
    from feedbench.sim_backends.serial_daq import LSB, data_frames, encode_data_frames, quantize

    rng = np.random.default_rng(7)
    for trial in range(200):
        n = int(rng.integers(1, 25))
        samples = rng.normal(size=(n, 12)) * 10.0 ** rng.uniform(-6, 3)
        inputs = np.flatnonzero([int(rng.integers(1, 4096)) >> i & 1 for i in range(12)])
        if trial % 4 == 0:
            samples[0, inputs[0]], samples[-1, inputs[-1]] = 1e9, -1e9
        if trial % 5 == 0:
            samples[:, inputs] = (np.floor(samples[:, inputs] / LSB[inputs]) + 0.5) * LSB[inputs]
        first = int(rng.integers(0, 2 ** 33))
        expected = encode_data_frames((first + np.arange(n)) % 2 ** 32,
                                      quantize(samples[:, inputs], inputs))
        assert np.array_equal(data_frames(first, samples, inputs), expected)


class _StreamCount:
    """The stream side of a run's recorder: how many samples were recorded so far."""

    def __init__(self) -> None:
        self.samples = 0

    def append_stream(self, name: str, cycles: np.ndarray, sequence: np.ndarray,
                      samples: np.ndarray) -> None:
        self.samples += len(sequence)


@pytest.mark.parametrize("lockstep", [True, False], ids=["lockstep", "real time"])
def test_a_lockstep_stream_waits_for_a_reader_behind_and_real_time_never_does(
        instrument, lockstep):
    """The instrument's samples of 1000 bus cycles reach the port only 1 s after the host's
    first cycle (a reader thread starved of the GIL by the cycle's threads). In lockstep
    the stream, silent for `LOCKSTEP_LAG_CYCLES`, waits for them (`LOCKSTEP_WAIT_S` per
    cycle: up to 4 s in all) and records them before its last cycle; in real time its
    1000 cycles go by without waiting and record nothing yet (about 3 ms, measured)."""
    n, delay_s = 1000, 1.0
    with SerialDaq(instrument.port, NAMES, RATE) as daq:
        stream = DaqStream(daq, "daq", lockstep=lockstep)
        recorder = _StreamCount()
        stream.start(SimpleNamespace(cycle_s=instrument.cycle_s), recorder)
        cycle = np.zeros((instrument.samples_per_cycle, len(CHANNELS)))
        late = threading.Timer(delay_s, lambda: [instrument.push(cycle) for _ in range(n)])
        late.start()
        try:
            t0 = time.monotonic()
            for k in range(n):
                stream.after_sync(k)
            elapsed, recorded = time.monotonic() - t0, recorder.samples
        finally:
            late.join()
            stream.stop(recorder)
    if lockstep:
        assert recorded > 0 and elapsed >= delay_s - 0.01
    else:
        assert recorded == 0 and elapsed < delay_s / 2
    assert recorder.samples == n * instrument.samples_per_cycle
