"""Simulated streaming DAQ: a USB-CDC instrument behind a pseudo-terminal.

The instrument owns the pty master; `port` is the slave path the host opens like
`/dev/ttyACM0`. It answers ASCII command lines (`*IDN?`, `RATE`, `CHAN`, `START`, `STOP`)
with reply frames and, while started, writes one data frame per sample instant
(docs/serial_daq_protocol.md).

Sample clock. Bench-locked (default): the simulated world calls `push` once per bus cycle
with that cycle's `samples_per_cycle` samples of all 12 inputs, so the sample counter is
`cycle × samples_per_cycle + i` and `counter / rate` is the bench time of the sample (the
instrument's sample clock is derived from the bench clock, as with an external sync input).
Free-running (tests): `free_run(waveform)` generates samples on the wall clock at `rate`.

Link. A pty carries any rate and never loses data (the kernel blocks the writer), so the
instrument emulates the real link: a stream is accepted only if it fits the USB full-speed
budget (`LINK_BYTES_PER_S`), frames leave at the sample rate of their clock, and a bounded
transmit FIFO drops whole frames (counted in `overruns`, visible to the host as counter
gaps) when the host stops reading. `corrupt_next_frame` damages the wire on purpose.

Host behind. A simulated bench can outrun a host that is reading, which the real-time
instrument never does: on a busy machine the host's read of the pty stalls in the kernel for
seconds (measured 2 s, waiting for the tty flip-buffer work) while the bench goes on.
Bench-locked, while more than a quarter of the FIFO waits and the host took bytes within
`host_stall_s`, each `push` waits up to `HOST_WAIT_S` for it; a host that stopped reading
overruns the FIFO as before.
"""

from __future__ import annotations

import binascii
import logging
import os
import select
import threading
import time
import tty
from contextlib import AbstractContextManager, nullcontext
from typing import Any, Callable, Literal

import numpy as np
from numba import njit

from feedbench.protocols.serial_frames import (
    CHANNELS, CRC_BYTES, CRC_INIT, FULL_SCALE_COUNTS, HEADER_BYTES, MAX_RATE_HZ,
    MAX_REPLY_BYTES, MIN_RATE_HZ, SAMPLE_BYTES, SEQ_BYTES, SYNC, TYPE_DATA, TYPE_REPLY,
    data_frame_bytes, link_load,
)

LOGGER = logging.getLogger(__name__)
IDENTITY = "FEEDBENCH,SIM-DAQ12,0,1.0"
DEFAULT_FIFO_BYTES = 1 << 20
"""Transmit FIFO of the instrument (≈ 2.3 s of all 12 inputs at 10 kHz)."""
HOST_WAIT_S = 0.02
"""Longest wait of one bench cycle for a host that is behind (well below a cycle's timeout)."""
HOST_STALL_S = 10.0
"""A host that took nothing for this long has stopped reading: not waited for."""
GARBAGE_BYTES = 64
Corruption = Literal["flip", "truncate", "garbage"]
Waveform = Callable[[np.ndarray], np.ndarray]
"""Sample times (n,) in s → (n, 12) input values in SI."""
ALL_INPUTS = (1 << len(CHANNELS)) - 1
LSB = np.array([c.lsb for c in CHANNELS])


def encode_frame(kind: int, payload: bytes) -> bytes:
    """One frame: sync, type, length, payload, CRC-16/CCITT-FALSE (little-endian)."""
    body = bytes((kind, len(payload))) + payload
    return SYNC + body + binascii.crc_hqx(body, CRC_INIT).to_bytes(2, "little")


def reply_payload(text: str) -> bytes:
    """A reply frame's payload: ASCII (others as ``?``), at most `MAX_REPLY_BYTES` bytes."""
    return text.encode("ascii", "replace")[:MAX_REPLY_BYTES]


def encode_data_frames(sequence: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(n,) sample counters and (n, k) int32 counts → (n, frame length) uint8 wire bytes."""
    n, k = counts.shape
    length = data_frame_bytes(k)
    frames = np.empty((n, length), np.uint8)
    frames[:, :2] = np.frombuffer(SYNC, np.uint8)
    frames[:, 2] = TYPE_DATA
    frames[:, 3] = length - HEADER_BYTES - CRC_BYTES
    samples_at = HEADER_BYTES + SEQ_BYTES
    frames[:, HEADER_BYTES:samples_at] = sequence.astype("<u4").view(np.uint8).reshape(n, 4)
    little_endian = np.ascontiguousarray(counts, "<i4").view(np.uint8).reshape(n, k, 4)
    frames[:, samples_at:-2] = little_endian[:, :, :SAMPLE_BYTES].reshape(n, SAMPLE_BYTES * k)
    flat = memoryview(frames.reshape(-1))
    crc = [binascii.crc_hqx(flat[i * length + 2:(i + 1) * length - 2], CRC_INIT) for i in range(n)]
    frames[:, -2:] = np.array(crc, "<u2").view(np.uint8).reshape(n, 2)
    return frames


def _crc_table() -> np.ndarray:
    """CRC-16/CCITT (poly 0x1021, not reflected) of each byte value, as `binascii.crc_hqx`."""
    table = np.zeros(256, np.uint16)
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = (crc << 1 ^ 0x1021 if crc & 0x8000 else crc << 1) & 0xFFFF
        table[byte] = crc
    return table


_CRC_TABLE = _crc_table()
_LAYOUT = np.array([SYNC[0], SYNC[1], TYPE_DATA, HEADER_BYTES, SEQ_BYTES, SAMPLE_BYTES,
                    CRC_BYTES, CRC_INIT, FULL_SCALE_COUNTS], np.int64)
"""The frame constants of `protocols.serial_frames` that `_data_frames` uses, passed to it:
a compiled kernel's globals are frozen in numba's cache, which a change of that other file
does not invalidate."""


@njit(cache=True)
def _data_frames(samples, inputs, lsb, first, crc_table, layout):
    """`encode_data_frames` of `quantize` of the `inputs` columns of `samples` (n, 12), the
    counters from `first` on, in one pass: the same bytes (rounding half to even as np.round,
    saturation as np.clip; a NaN as numpy casts it, the lowest int32); `layout`: `_LAYOUT`."""
    sync0, sync1, data_type, header, seq_bytes, sample_bytes, crc_bytes, crc_init, full = layout
    n, k = samples.shape[0], inputs.size
    length = header + seq_bytes + sample_bytes * k + crc_bytes
    frames = np.empty((n, length), np.uint8)
    for i in range(n):
        frame = frames[i]
        frame[0], frame[1] = sync0, sync1
        frame[2] = data_type
        frame[3] = length - header - crc_bytes
        sequence = (first + i) % 4294967296
        for b in range(seq_bytes):
            frame[header + b] = (sequence >> (8 * b)) & 0xFF
        at = header + seq_bytes
        for j in range(k):
            count = np.rint(samples[i, inputs[j]] / lsb[j])
            if count != count:
                word = -2147483648
            else:
                word = int(min(max(count, -full), full - 1))
            for b in range(sample_bytes):
                frame[at + b] = (word >> (8 * b)) & 0xFF
            at += sample_bytes
        crc = crc_init
        for b in range(2, length - crc_bytes):
            crc = ((crc << 8) & 0xFFFF) ^ crc_table[((crc >> 8) ^ frame[b]) & 0xFF]
        frame[length - 2] = crc & 0xFF
        frame[length - 1] = crc >> 8
    return frames


def data_frames(first: int, samples: np.ndarray, inputs: np.ndarray) -> np.ndarray:
    """The wire bytes (n, frame length) of `samples` (n, 12, SI) of the `inputs`, counters
    from `first`: `encode_data_frames(counters, quantize(samples[:, inputs], inputs))` in one
    compiled pass (≈ 40 µs less per bench cycle of 10 samples, measured)."""
    return _data_frames(np.ascontiguousarray(samples, dtype=float), inputs, LSB[inputs],
                        first, _CRC_TABLE, _LAYOUT)


def quantize(values: np.ndarray, inputs: np.ndarray) -> np.ndarray:
    """SI values of the given inputs → 24-bit ADC counts, saturated at full scale."""
    counts = np.round(values / LSB[inputs])
    return np.clip(counts, -FULL_SCALE_COUNTS, FULL_SCALE_COUNTS - 1).astype(np.int32)


def corrupt(wire: bytes, frame_bytes: int, kind: Corruption) -> bytes:
    """Damage the first frame of `wire`: flip a sample byte, cut it short, or prefix garbage.

    Garbage bytes are drawn below 0xA5 so they never hold the sync word.
    """
    if kind == "flip":
        damaged = bytearray(wire)
        damaged[frame_bytes // 2] ^= 0xFF
        return bytes(damaged)
    if kind == "truncate":
        return wire[:frame_bytes // 2] + wire[frame_bytes:]
    garbage = np.random.default_rng(len(wire)).integers(0, SYNC[0], GARBAGE_BYTES, np.uint8)
    return garbage.tobytes() + wire


class SimulatedSerialDaq:
    """The instrument on a fresh pty (`port` is the slave path), stopped, all inputs on.

    `cycle_s` is the bench bus cycle its sample clock locks to (s), `rate_hz` the power-on
    sample rate, `fifo_bytes` the transmit FIFO that overruns when the host stops reading
    (took nothing for `host_stall_s`).
    """

    def __init__(self, cycle_s: float = 1e-3, rate_hz: int = 10_000,
                 fifo_bytes: int = DEFAULT_FIFO_BYTES, host_stall_s: float = HOST_STALL_S) -> None:
        self.cycle_s = cycle_s
        self.fifo_bytes = fifo_bytes
        self.host_stall_s = host_stall_s
        self.rate_hz = rate_hz
        self.mask = ALL_INPUTS
        self._inputs_mask = -1
        self._inputs = np.zeros(0, np.int64)
        data_frames(0, np.zeros((1, len(CHANNELS))), np.arange(len(CHANNELS)))  # compiled now,
        # not in the first SYNC that streams
        self._check_stream(rate_hz, ALL_INPUTS)
        self.streaming = False
        self.frames_sent = 0
        self.overruns = 0
        self._cycles = 0
        self._waveform: Waveform | None = None
        self._clock_origin = 0.0
        self._clock_samples = 0
        self._corruption: Corruption | None = None
        self._fifo = bytearray()
        self._host_took_at = time.monotonic()
        self._commands = bytearray()
        self._lock = threading.Lock()
        self._cycle_lock: AbstractContextManager[Any] = nullcontext()
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.port = os.ttyname(self._slave)
        self._wake_read, self._wake_write = os.pipe()
        os.set_blocking(self._wake_write, False)
        self._closing = False
        self._thread = threading.Thread(target=self._serve, name="sim-daq", daemon=True)
        self._thread.start()

    def answer_between_cycles(self, cycle_lock: AbstractContextManager[Any]) -> None:
        """Execute the host's commands under the bus cycle's lock (the simulated drive's,
        whose hooks push the cycle's samples after its TPDOs): a STOP sent after the last
        cycle's TPDOs still sees that cycle's samples pushed."""
        self._cycle_lock = cycle_lock

    @property
    def samples_per_cycle(self) -> int:
        """Samples per bench cycle at the configured rate (what `push` expects)."""
        return round(self.rate_hz * self.cycle_s)

    @property
    def inputs(self) -> np.ndarray:
        """Indices of the enabled inputs, in frame order."""
        return np.flatnonzero([self.mask >> i & 1 for i in range(len(CHANNELS))])

    def _inputs_of(self, mask: int) -> np.ndarray:
        """`inputs` for `mask`, kept while the mask stays."""
        if self._inputs_mask != mask:
            self._inputs_mask, self._inputs = mask, self.inputs
        return self._inputs

    def push(self, samples: np.ndarray) -> None:
        """One bench cycle's samples: (samples_per_cycle, 12) in SI; streamed if started."""
        samples = np.asarray(samples, dtype=float)
        if self._closing:  # unplugged: nothing reaches the host any more
            return
        with self._lock:
            if self._waveform is not None:
                raise RuntimeError("the instrument is free-running; push is for the bench clock")
            n = self.samples_per_cycle
            if samples.shape != (n, len(CHANNELS)):
                raise ValueError(f"push expects ({n}, {len(CHANNELS)}) samples, "
                                 f"got {samples.shape}")
            first = self._cycles * n
            self._cycles += 1
            if self.streaming:
                self._queue(first, samples)
        self._flush_or_wake()
        self._wait_for_host()

    def free_run(self, waveform: Waveform) -> None:
        """Clock the instrument from the wall clock at `rate_hz`, sampling `waveform(t)`."""
        with self._lock:
            self._waveform = waveform
            self._restart_clock()
        self._wake()

    def corrupt_next_frame(self, kind: Corruption = "flip") -> None:
        """Damage the next data frame on the wire: 'flip' (one payload byte inverted),
        'truncate' (only its first half is sent) or 'garbage' (64 junk bytes before it)."""
        if kind not in ("flip", "truncate", "garbage"):
            raise ValueError(f"unknown corruption {kind!r}")
        with self._lock:
            self._corruption = kind

    def unplug(self) -> None:
        """The cable pulled: the pty closes (the host's reads fail); later pushes are
        dropped."""
        self.close()

    def close(self) -> None:
        """Stop the service thread and close the pty (the host then sees the device vanish);
        a second call does nothing."""
        if self._closing:
            return
        self._closing = True
        self._wake()
        self._thread.join(timeout=2.0)
        for fd in (self._master, self._slave, self._wake_read, self._wake_write):
            os.close(fd)

    def __enter__(self) -> SimulatedSerialDaq:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _queue(self, first: int, samples: np.ndarray) -> None:
        """Frame samples of the enabled inputs into the FIFO; frames that do not fit are lost."""
        inputs = self._inputs_of(self.mask)
        frames = data_frames(first, samples, inputs)
        length = frames.shape[1]
        fits = min(len(frames), max(0, self.fifo_bytes - len(self._fifo)) // length)
        self.overruns += len(frames) - fits
        self.frames_sent += fits
        wire = frames[:fits].tobytes()
        if self._corruption is not None and fits:
            wire, self._corruption = corrupt(wire, length, self._corruption), None
        self._fifo += wire

    def _serve(self) -> None:
        """Service loop: commands in, FIFO out, free-running sample generation."""
        while not self._closing:
            writers = [self._master] if self._fifo else []
            timeout = 1e-3 if self._waveform is not None else None
            readable, _, _ = select.select([self._master, self._wake_read], writers, [], timeout)
            if self._wake_read in readable:
                os.read(self._wake_read, 4096)
            if self._master in readable:
                self._receive()
            with self._lock:
                self._catch_up()
            self._flush()

    def _receive(self) -> None:
        """Read command bytes; execute each complete line and queue its reply frame."""
        try:
            self._commands += os.read(self._master, 4096)
        except BlockingIOError:
            return
        *lines, self._commands = self._commands.split(b"\n")
        for line in lines:
            with self._cycle_lock, self._lock:
                self._catch_up()  # a command takes effect at the sample clock's present
                reply = self._execute(line.decode("ascii", "replace").strip())
                self._fifo += encode_frame(TYPE_REPLY, reply_payload(reply))

    def _execute(self, line: str) -> str:
        word, _, argument = line.partition(" ")
        handlers = {"*IDN?": lambda _: IDENTITY, "RATE": self._set_rate,
                    "CHAN": self._set_channels, "START": self._start, "STOP": self._stop}
        handler = handlers.get(word.upper())
        if handler is None:
            LOGGER.warning("serial DAQ: unknown command %r: answered ERR", word)
            return f"ERR unknown command {word!r}"
        try:
            return f"OK {handler(argument.strip())}".rstrip()
        except ValueError as error:
            LOGGER.warning("serial DAQ: %r refused: %s", line, error)
            return f"ERR {error}"
        except Exception as error:  # a fault inside the instrument: answered, never a traceback
            LOGGER.error("serial DAQ: %r failed: %s: %s", line, type(error).__name__, error)
            return f"ERR internal {type(error).__name__}"

    def _set_rate(self, argument: str) -> str:
        rate = int(argument)
        self._check_idle()
        self._check_stream(rate, self.mask)
        self.rate_hz = rate
        self._restart_clock()
        return ""

    def _set_channels(self, argument: str) -> str:
        mask = int(argument, 16)
        self._check_idle()
        if not 0 < mask <= ALL_INPUTS:
            raise ValueError(f"channel mask must be within 0001..{ALL_INPUTS:04X}")
        self._check_stream(self.rate_hz, mask)
        self.mask = mask
        return ""

    def _start(self, _: str) -> str:
        self.streaming = True
        return ""

    def _stop(self, _: str) -> str:
        self.streaming = False
        return ""

    def _check_idle(self) -> None:
        if self.streaming:
            raise ValueError("busy: STOP first")

    def _check_stream(self, rate: int, mask: int) -> None:
        """A rate must be in range, fit the link with these inputs and divide the bench cycle."""
        if not MIN_RATE_HZ <= rate <= MAX_RATE_HZ:
            raise ValueError(f"rate {rate} Hz outside {MIN_RATE_HZ}..{MAX_RATE_HZ} Hz")
        load = link_load(bin(mask).count("1"), rate)
        if load > 1.0:
            raise ValueError(f"{rate} Hz with these channels needs {load:.0%} of the link")
        per_cycle = rate * self.cycle_s
        if abs(per_cycle - round(per_cycle)) > 1e-9 or round(per_cycle) < 1:
            raise ValueError(f"{rate} Hz is not a whole number of samples per bench cycle")

    def _restart_clock(self) -> None:
        self._clock_origin = time.monotonic()
        self._clock_samples = 0

    def _catch_up(self) -> None:
        """Free-running: produce the samples that fell due on the wall clock since last time."""
        if self._waveform is None:
            return
        due = int((time.monotonic() - self._clock_origin) * self.rate_hz)
        first, self._clock_samples = self._clock_samples, due
        if self.streaming and due > first:
            self._queue(first, self._waveform(np.arange(first, due) / self.rate_hz))

    def _flush(self) -> None:
        """Write as much of the FIFO as the pty takes now (never blocks)."""
        with self._lock:
            if not self._fifo:
                return
            try:
                written = os.write(self._master, self._fifo)
            except BlockingIOError:
                return
            del self._fifo[:written]
            if written:
                self._host_took_at = time.monotonic()

    def _wait_for_host(self) -> None:
        """Hold this bench cycle (≤ `HOST_WAIT_S`) while a host that is reading is behind."""
        deadline = time.monotonic() + HOST_WAIT_S
        while (len(self._fifo) > self.fifo_bytes // 4
               and time.monotonic() - self._host_took_at < self.host_stall_s
               and time.monotonic() < deadline):
            time.sleep(1e-3)
            self._flush()

    def _flush_or_wake(self) -> None:
        self._flush()
        if self._fifo:
            self._wake()

    def _wake(self) -> None:
        try:
            os.write(self._wake_write, b"\0")
        except BlockingIOError:
            pass  # a wake-up is already pending
