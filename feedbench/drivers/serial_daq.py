"""Host driver of the streaming DAQ: binary frames over a serial port (USB-CDC), on pyserial.

The port is opened by path exactly as a real instrument's `/dev/ttyUSB0` / `/dev/ttyACM0`;
the simulated instrument is a pseudo-terminal slave path. Protocol (docs/serial_daq_protocol.md):
frames `A5 5A | type | length | payload | CRC-16/CCITT-FALSE`, one data frame per sample
instant carrying a 32-bit sample counter and the enabled channels as signed 24-bit counts;
ASCII command lines to the instrument, answered by reply frames in the same byte stream.

The parser resynchronises on the sync word after a bad frame (every header candidate is
checked against its CRC), counts CRC errors, bytes skipped, and frames missing from the
sample counter. A lost sample is counted, never hidden.
"""

from __future__ import annotations

import binascii
import collections
import queue
import threading
from typing import NamedTuple, Sequence

import numpy as np
import serial

from feedbench.protocols.serial_frames import (  # noqa: F401  (re-exported API)
    CHANNELS,
    CHANNEL_INDEX,
    CRC_BYTES,
    CRC_INIT,
    DaqChannel,
    FULL_SCALE_COUNTS,
    HEADER_BYTES,
    LINK_BYTES_PER_S,
    MAX_RATE_HZ,
    MAX_REPLY_BYTES,
    MIN_RATE_HZ,
    SAMPLE_BYTES,
    SEQ_BYTES,
    SYNC,
    TYPE_DATA,
    TYPE_REPLY,
    data_frame_bytes,
    link_load,
)


class SerialDaqError(RuntimeError):
    """The instrument refused a command, did not answer, or the configuration is invalid."""


class DaqBlock(NamedTuple):
    """Samples read from the stream: unwrapped sample counter and n × channels values."""

    sequence: np.ndarray
    samples: np.ndarray


def channel_mask(names: Sequence[str]) -> int:
    """Bit mask of the named inputs (bit i = CHANNELS[i])."""
    unknown = [n for n in names if n not in CHANNEL_INDEX]
    if unknown or not names or len(set(names)) != len(names):
        raise SerialDaqError(f"channels must be distinct names from {list(CHANNEL_INDEX)}, "
                             f"got {list(names)}")
    return sum(1 << CHANNEL_INDEX[n] for n in names)


def decode_int24(raw: np.ndarray) -> np.ndarray:
    """(..., 3k) little-endian signed 24-bit bytes → (..., k) int32 counts."""
    b = raw.reshape(*raw.shape[:-1], raw.shape[-1] // SAMPLE_BYTES, SAMPLE_BYTES).astype(np.int32)
    unsigned = b[..., 0] | (b[..., 1] << 8) | (b[..., 2] << 16)
    return (unsigned ^ 0x800000) - 0x800000


class FrameParser:
    """Splits a byte stream into data frames and replies; resynchronises after corruption.

    `feed` returns the data frames completed so far as (unwrapped counters, ADC counts) and
    the replies. Counters: `crc_errors` (frames whose header looked valid but whose CRC
    failed), `skipped_bytes` (bytes discarded while hunting for the next frame),
    `dropped_frames` (gaps in the sample counter between consecutive good data frames).
    """

    def __init__(self, n_channels: int) -> None:
        self.n_channels = n_channels
        self.data_payload = SEQ_BYTES + SAMPLE_BYTES * n_channels
        self.crc_errors = 0
        self.skipped_bytes = 0
        self.dropped_frames = 0
        self._buffer = bytearray()
        self._last_sequence: int | None = None

    def restart_sequence(self) -> None:
        """Forget the last counter (a new stream starts: its first frame sets the origin)."""
        self._last_sequence = None

    def feed(self, data: bytes) -> tuple[DaqBlock, list[str]]:
        """Parse `data` after what was left over: (sequence int64, counts int32), replies."""
        self._buffer += data
        offsets, replies, consumed = self._scan()
        frames = np.frombuffer(bytes(self._buffer[:consumed]), np.uint8)
        del self._buffer[:consumed]
        return self._decode(frames, np.asarray(offsets, dtype=np.int64)), replies

    def _scan(self) -> tuple[list[int], list[str], int]:
        """Walk the buffer frame by frame: offsets of good data frames, replies, bytes used."""
        buf, offsets, replies, pos = self._buffer, [], [], 0
        while True:
            start = buf.find(SYNC, pos)
            if start < 0:
                keep = 1 if pos < len(buf) and buf[-1] == SYNC[0] else 0
                self.skipped_bytes += len(buf) - pos - keep
                return offsets, replies, len(buf) - keep
            self.skipped_bytes += start - pos
            pos = start
            if len(buf) - pos < HEADER_BYTES:
                return offsets, replies, pos
            kind, length = buf[pos + 2], buf[pos + 3]
            end = pos + HEADER_BYTES + length + CRC_BYTES
            plausible = self._plausible_header(kind, length)
            if plausible and end > len(buf):
                return offsets, replies, pos
            if not (plausible and self._crc_ok(pos, end)):
                pos, self.skipped_bytes = pos + 1, self.skipped_bytes + 1
                continue
            if kind == TYPE_DATA:
                offsets.append(pos)
            else:
                replies.append(buf[pos + HEADER_BYTES:end - CRC_BYTES].decode("ascii", "replace"))
            pos = end

    def _plausible_header(self, kind: int, length: int) -> bool:
        if kind == TYPE_DATA:
            return length == self.data_payload
        return kind == TYPE_REPLY and 0 < length <= MAX_REPLY_BYTES

    def _crc_ok(self, start: int, end: int) -> bool:
        """CRC over type, length and payload; a mismatch counts one CRC error."""
        buf = self._buffer
        ok = binascii.crc_hqx(buf[start + 2:end - CRC_BYTES], CRC_INIT) == int.from_bytes(
            buf[end - CRC_BYTES:end], "little")
        self.crc_errors += not ok
        return ok

    def _decode(self, frames: np.ndarray, offsets: np.ndarray) -> DaqBlock:
        """Vectorised payload decoding of the good data frames found by `_scan`."""
        index = offsets[:, None] + np.arange(HEADER_BYTES, HEADER_BYTES + self.data_payload)
        payload = frames[index].reshape(len(offsets), self.data_payload)
        seq32 = np.ascontiguousarray(payload[:, :SEQ_BYTES]).view("<u4").ravel()
        return DaqBlock(self._unwrap(seq32), decode_int24(payload[:, SEQ_BYTES:]))

    def _unwrap(self, seq32: np.ndarray) -> np.ndarray:
        """32-bit sample counters → int64 (modulo 2³² steps), counting every gap as dropped."""
        if len(seq32) == 0:
            return np.empty(0, np.int64)
        previous = int(seq32[0]) - 1 if self._last_sequence is None else self._last_sequence
        steps = np.diff(seq32.astype(np.int64), prepend=previous) % 2 ** 32
        sequence = previous + np.cumsum(steps)
        self.dropped_frames += int(sequence[-1] - previous) - len(seq32)
        self._last_sequence = int(sequence[-1])
        return sequence


COMMAND_TIMEOUT_S = 3.0
"""How long a command waits for its reply (s): the instrument answers within a millisecond,
but on a loaded 2-core machine the fault matrix saw a reply later than 1 s."""


class SerialDaq:
    """The streaming DAQ behind a serial port path, with a reader thread and a bounded queue.

    `channels` are names from `CHANNELS` in the column order wanted back; `rate` in Hz (a
    whole number). The reader thread parses continuously; `read_available` hands over what
    arrived (the thread collects up to 10 ms of bytes per read). If the caller does not read
    for longer than `buffer_s`, the oldest samples are discarded and counted in
    `overflowed_frames`.
    """

    def __init__(self, port: str, channels: Sequence[str], rate: float, *,
                 timeout: float = COMMAND_TIMEOUT_S, buffer_s: float = 10.0) -> None:
        if rate != int(rate):
            raise SerialDaqError(f"rate must be a whole number of Hz, got {rate}")
        self.channels = tuple(channels)
        self.mask = channel_mask(self.channels)
        self.rate = float(rate)
        self.timeout = timeout
        enabled = [i for i in range(len(CHANNELS)) if self.mask >> i & 1]
        self._columns = np.array([enabled.index(CHANNEL_INDEX[n]) for n in self.channels])
        self._lsb = np.array([CHANNELS[CHANNEL_INDEX[n]].lsb for n in self.channels])
        self._parser = FrameParser(len(enabled))
        self._capacity = max(1, int(buffer_s * self.rate))
        self._blocks: collections.deque[DaqBlock] = collections.deque()
        self._queued = 0
        self.overflowed_frames = 0
        self.gone = ""
        """Why the port stopped reading (the device went away), "" while it reads."""
        self._lock = threading.Lock()
        self._arrived = threading.Condition(self._lock)
        """Notified when samples are queued (`wait_for_samples`)."""
        self._command_lock = threading.Lock()
        self._replies: queue.Queue[str] = queue.Queue()
        self._closing = threading.Event()
        self._serial = serial.Serial(port, baudrate=12_000_000, timeout=0.01)
        self._reader = threading.Thread(target=self._read_loop, name=f"daq-{port}", daemon=True)
        self._reader.start()
        try:
            self.identity = self.command("*IDN?")
            self.command("STOP")  # a stream a host that died left running (fault matrix)
            self.command(f"CHAN {self.mask:04X}")
            self.command(f"RATE {int(rate)}")
        except SerialDaqError:
            self.close()
            raise
        with self._lock:  # what that stream sent is not this host's: its losses neither
            self._blocks.clear()
            self._queued = 0
            self._parser = FrameParser(len(enabled))

    @property
    def crc_errors(self) -> int:
        """Frames rejected because their CRC did not match."""
        return self._parser.crc_errors

    @property
    def dropped_frames(self) -> int:
        """Sample instants missing from the counter sequence (corrupted or overrun frames)."""
        return self._parser.dropped_frames

    @property
    def skipped_bytes(self) -> int:
        """Bytes discarded while resynchronising."""
        return self._parser.skipped_bytes

    def start(self) -> None:
        """Start the stream; the first frame received sets the counter origin."""
        with self._lock:
            self._parser.restart_sequence()
        self.command("START")

    def stop(self) -> None:
        """Stop the stream; every frame sent before the stop is parsed when this returns."""
        self.command("STOP")

    def read_available(self) -> DaqBlock:
        """Everything received since the last call: sequence (n,) int64, samples (n, ch) SI;
        once all of it is read, `SerialDaqError` if the device went away (`gone`)."""
        with self._lock:
            blocks, self._blocks, self._queued = list(self._blocks), collections.deque(), 0
        if not blocks and self.gone:
            raise SerialDaqError(f"{self._serial.port}: the device went away ({self.gone})")
        if not blocks:
            return DaqBlock(np.empty(0, np.int64), np.empty((0, len(self.channels))))
        return DaqBlock(np.concatenate([b.sequence for b in blocks]),
                        np.concatenate([b.samples for b in blocks]))

    def wait_for_samples(self, timeout_s: float) -> bool:
        """Wait at most `timeout_s` (s) until samples are queued for `read_available`, the
        calling thread idle meanwhile (the reader thread gets the GIL); whether some are."""
        with self._arrived:
            return self._arrived.wait_for(lambda: self._queued > 0, timeout_s)

    def close(self) -> None:
        """Stop the reader thread and close the port."""
        self._closing.set()
        self._reader.join(timeout=2.0)
        self._serial.close()

    def __enter__(self) -> SerialDaq:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def command(self, line: str) -> str:
        """Send one command line (docs/serial_daq_protocol.md) and return the text after
        `OK`; an `ERR` reply or no reply within `timeout` raises `SerialDaqError`."""
        with self._command_lock:
            self._serial.write(line.encode("ascii") + b"\n")
            try:
                reply = self._replies.get(timeout=self.timeout)
            except queue.Empty:
                raise SerialDaqError(f"no reply to {line!r} within {self.timeout} s") from None
        if not reply.startswith("OK"):
            raise SerialDaqError(f"{line!r} refused: {reply}")
        return reply[2:].strip()

    def _read_loop(self) -> None:
        while not self._closing.is_set():
            try:
                data = self._serial.read(65536)
            except (serial.SerialException, OSError) as exc:  # the device went away
                self.gone = " ".join(f"{type(exc).__name__}: {exc}".split())
                return
            if data:
                self._handle(data)

    def _handle(self, data: bytes) -> None:
        """Parse a chunk; queue its samples before its replies (stream order)."""
        with self._lock:
            block, replies = self._parser.feed(data)
            if len(block.sequence):
                samples = block.samples[:, self._columns] * self._lsb
                self._enqueue(DaqBlock(block.sequence, samples))
        for reply in replies:
            self._replies.put(reply)

    def _enqueue(self, block: DaqBlock) -> None:
        """Queue `block` for `read_available` (the caller holds `_lock`, which the
        notification of `wait_for_samples` needs); the oldest go when the buffer is full."""
        self._blocks.append(block)
        self._queued += len(block.sequence)
        self._arrived.notify_all()
        while self._queued > self._capacity:
            oldest = self._blocks.popleft()
            self._queued -= len(oldest.sequence)
            self.overflowed_frames += len(oldest.sequence)
