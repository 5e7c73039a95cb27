"""CAN bus access for both sides: open a canopen Network, fast PDO codecs, the frozen heap
of a real-time cycle (`frozen_heap`).

The interface names are python-can's: ``virtual`` (tests, simulation: any channel name),
``socketcan`` (channel ``can0`` on Linux), ``socketcand`` (a TCP bridge), …
"""

from __future__ import annotations

import collections
import functools
import gc
import hashlib
import logging
import os
import pickle
import queue
import select
import socket
import struct
import threading
import time
from contextlib import AbstractContextManager, contextmanager, nullcontext
from typing import Any, Callable, Iterable, Iterator, NamedTuple

import can
import canopen
from can.interfaces import virtual
from can.interfaces.socketcand import SocketCanDaemonBus
from can.interfaces.socketcand.socketcand import convert_ascii_message_to_can_message
from canopen.nmt import NMT_STATES
from canopen.objectdictionary import NUMBER_TYPES, ODVariable
from canopen.pdo import PdoMap

from feedbench.config import ConfigError
from feedbench.protocols import cia301

SDO_TIMEOUT_S = 2.0
"""How long an SDO request waits for its answer (canopen's default 0.3 s is short for a peer
busy for a moment, e.g. a simulated world compiling its physics on first use)."""

NOTIFIER_POLL_S = 0.05
"""Receive-thread poll period: bounds how long `Network.disconnect` waits (canopen: 1 s)."""

CONNECT_TIMEOUT_S = 2.0
"""How long a socketcand server may take to accept the connection (s); python-can itself
retries for 10 s, then raises `TimeoutError`."""

HANDSHAKE_TIMEOUT_S = 1.0
"""How long a socketcand server may take to say each line of its handshake (s): ``< hi >``
on connecting, ``< ok >`` to ``< open channel >`` and to ``< rawmode >``
(`SocketcandBus`)."""

SOCKETCAND_RECEIVE_BYTES = 65536
"""Most bytes one receive takes from a socketcand server (python-can's: 1024)."""
SOCKETCAND_PENDING_BYTES = 200
"""Bytes without the end of a message (``>``) after which they are dropped as garbage
(python-can's limit)."""
SOCKETCAND_LOGGER = logging.getLogger("can.interfaces.socketcand")
"""python-can's socketcand logger (silenced by `open_bus`: a warning per frame)."""
DIRECT_LOGGER = logging.getLogger("can.interfaces.virtual")
"""Where a listener's error is logged when a frame is handed on in its sender's or the
cycle's thread (`DirectVirtualBus`, `cycle_reads`), not by a receive thread."""
SOCKETCAND_HEX = [b"%x" % value for value in range(256)]
"""A data byte as python-can writes it in ``< send … >``: lower-case hex, no leading zero."""
READS_LEASE_S = 0.01
"""After a lockstep cycle read its socketcand connection itself (`cycle_reads`), the
receive thread stays off the socket this long (s) after the cycle let go: a run's next cycle
claims it again well within it, and a frame that comes while no cycle runs (an SDO answer
to a stop between cycles) is read by the receive thread at most this late."""
ANSWER_POLL_S = 300e-6
"""How long a lockstep cycle that reads its own answers (`cycle_reads`) polls the socket for
them before it sleeps on it (s), giving the CPU to any other thread that wants it between
polls (`os.sched_yield`): `feedbench sim` answers in ≈ 0.1 ms, and a thread asleep when it
does is woken through the other CPU (≈ 50 µs a cycle on this 2-core VM). Measured with
`feedbench sim` (all devices; A/B in one process, 4 × 3000 cycles each): 6165 → 8050
cycles/s quiet; 4287 either way with another process burning one CPU (a poll without the
yield: 2839)."""

SDO_BYTES, EMCY_BYTES, NMT_BYTES, HEARTBEAT_BYTES = 8, 8, 2, 1
"""Data bytes of an SDO, EMCY, NMT command and heartbeat frame (CiA 301)."""

HEARTBEAT_STATE_MASK = 0x7F  # bit 7: the toggle bit
SDO_COMMAND_MASK = 0xE0
SDO_DOWNLOAD_SEGMENT, SDO_INITIATE_DOWNLOAD, SDO_INITIATE_UPLOAD, SDO_UPLOAD_SEGMENT = (
    0x00, 0x20, 0x40, 0x60)
SDO_SEGMENT_REQUESTS = (SDO_DOWNLOAD_SEGMENT, SDO_UPLOAD_SEGMENT)
SDO_REFUSED_REQUESTS = (0xA0, 0xC0, 0xE0)
"""Client command specifiers (CiA 301, bits 5–7 of the first byte): segments, initiates;
block upload, block download and the undefined 7, which the simulated nodes refuse."""
SDO_LAST_SEGMENT = 0x01
"""Download segment request: no more segments."""
SDO_INDEX = struct.Struct("<HB")

Handler = Callable[[int, bytearray, float], None]
"""A frame handler of a canopen Network: (COB-ID, data, timestamp)."""


class ReceiveErrors(can.Listener):
    """Keeps a network's receive thread alive through a receive error (a socketcand peer
    that reset the connection, an error on the adapter): the error is kept in `last`, the
    thread waits one poll period and receives again. A dead peer is then seen as what it
    is, a missing answer (`BusTimeout`, an SDO timeout) or a failed send, not as a receive
    thread's traceback and every later send raising the old error."""

    def __init__(self, notifier: can.Notifier) -> None:
        self.notifier = notifier
        self.last: Exception | None = None

    def on_message_received(self, msg: can.Message) -> None:
        """Frames are the network's own listener's."""

    def on_error(self, exc: Exception) -> None:
        """Keep `exc`, clear it from the notifier (canopen raises it on every send), wait."""
        self.last = exc
        self.notifier.exception = None
        time.sleep(NOTIFIER_POLL_S)


STACK_LOGGERS = ("can", "canopen")
"""The loggers of python-can and canopen (their modules log below these)."""
STACK_LOG_LINES = 1000
"""Lines a `StackLog` keeps until they are taken (older ones are counted, not kept)."""


class StackLog(logging.Handler):
    """python-can's and canopen's own log lines (WARNING and above), kept for the run's
    file instead of going bare to stderr (`capture`); any thread may log, the cycle loop
    takes them (`take`)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.lines: collections.deque[str] = collections.deque(maxlen=STACK_LOG_LINES)
        self.dropped = 0

    def emit(self, record: logging.LogRecord) -> None:
        if len(self.lines) == STACK_LOG_LINES:
            self.dropped += 1
        self.lines.append(f"{record.name}: {record.levelname.lower()}: {record.getMessage()}")

    def take(self) -> list[str]:
        """The lines logged since the last call, oldest first."""
        out = []
        while self.lines:
            out.append(self.lines.popleft())
        return out

    @contextmanager
    def capture(self) -> Iterator[StackLog]:
        """While inside, the stack's loggers log here only (not to stderr)."""
        loggers = [logging.getLogger(name) for name in STACK_LOGGERS]
        for logger in loggers:
            logger.addHandler(self)
            logger.propagate = False
        try:
            yield self
        finally:
            for logger in loggers:
                logger.removeHandler(self)
                logger.propagate = True


def connect(network: canopen.Network) -> canopen.Network:
    """Start the network's receive thread with a short poll period, so it closes quickly,
    and `ReceiveErrors` handling its receive errors. A bus that hands its frames to
    listeners itself (a `listen(listeners)` method: the simulated bench's hub port) gets the
    network's listeners instead, and no receive thread."""
    if callable(getattr(network.bus, "listen", None)):
        network.bus.listen(network.listeners)
        return network
    network.NOTIFIER_CYCLE = NOTIFIER_POLL_S
    network.connect()
    network.notifier.add_listener(ReceiveErrors(network.notifier))
    return network


_frozen = 0
"""How many `frozen_heap` blocks are open (any thread)."""
_frozen_lock = threading.Lock()


@contextmanager
def frozen_heap() -> Iterator[None]:
    """While inside, Python's garbage collector leaves every object that exists on entry
    alone (`gc.freeze`); once the last open block (of any thread) exits, they are its again
    (`gc.unfreeze`). A full collection walks every object of the process: ≈ 0.1 s with
    numpy, scipy and numba loaded, during which no thread of the process runs, so no SYNC
    is sent, no TPDO received, no setpoint sent (measured: one such pause per ≈ 15 s of
    1 kHz cycles, long enough for the drive's SYNC-loss watchdog to stop the axis). Objects
    made inside are collected as before; the young ones cost microseconds."""
    global _frozen
    with _frozen_lock:
        gc.freeze()
        _frozen += 1
    try:
        yield
    finally:
        with _frozen_lock:
            _frozen -= 1
            if not _frozen:
                gc.unfreeze()


def socketcand_messages(pending: bytes, data: bytes) -> tuple[list[bytes], bytes]:
    """The complete socketcand messages in `pending` + `data` (received bytes), each from its
    last ``<`` with its ``>`` cut off (bytes outside ``< … >`` dropped), and the rest, to be
    completed by the next receive: at most `SOCKETCAND_PENDING_BYTES`, more without a ``>``
    is garbage and dropped (python-can's limit). The client (`SocketcandBus`) and the server
    (`sim_backends.socketcand_hub`) split what they receive with it."""
    *parts, rest = (pending + data).split(b">")
    messages = [part[start:] for part in parts if (start := part.rfind(b"<")) >= 0]
    return messages, rest if len(rest) <= SOCKETCAND_PENDING_BYTES else b""


def send_frames(network: canopen.Network, frames: Iterable[can.Message]) -> None:
    """Send `frames` in order on `network`'s bus under its send lock, as canopen's
    `Network.send_message` sends one frame (which makes a new `can.Message` per frame: ≈ 1.3
    µs of the ≈ 4 µs a frame costs, measured), together where the bus can
    (`batched_sends`); `RuntimeError` when not connected, and the network's receive errors
    raised afterwards (`Network.check`), as there."""
    bus = network.bus
    if bus is None:
        raise RuntimeError("Not connected to CAN bus")
    with network.send_lock, batched_sends(network):
        for frame in frames:
            bus.send(frame)
    network.check()


class SendBatch:
    """What one bus sends, held per thread: inside `held()` a thread's items wait and go to
    `flush` together, in the order sent, as its outermost block ends (an exception too:
    what was sent counts as sent); other threads' items are not held (`hold` says so), and
    two threads batch apart (thread-local). `SocketcandBus` and the hub's
    `HubPort` batch with it."""

    def __init__(self, flush: Callable[[list[Any]], None]) -> None:
        self._flush = flush
        self._local = threading.local()

    def hold(self, item: Any) -> bool:
        """Keep `item` in the calling thread's open batch; False when it has none (send it
        now)."""
        items = getattr(self._local, "items", None)
        if items is None:
            return False
        items.append(item)
        return True

    def held(self) -> AbstractContextManager[None]:
        """The calling thread's batch: what it sends inside goes to `flush` at the end."""
        return _HeldBatch(self)


class _HeldBatch:
    """One `SendBatch.held()` block (a class, not a generator: ≈ 0.9 µs less per block,
    measured, and a lockstep cycle opens one on each side): it opens the calling thread's
    batch, or, nested in an open one, leaves the flush to the outer block."""

    __slots__ = ("_batch", "_outer")

    def __init__(self, batch: SendBatch) -> None:
        self._batch = batch
        self._outer = False

    def __enter__(self) -> None:
        local = self._batch._local
        if getattr(local, "items", None) is None:
            local.items = []
            self._outer = True

    def __exit__(self, *exc: object) -> None:
        if self._outer:
            local = self._batch._local
            items, local.items = local.items, None
            if items:
                self._batch._flush(items)


Receive = Callable[[float], bool]
"""Reads a bus in the calling thread for up to its argument (s), handing each frame to the
network's listeners there; False once it cannot read (the receive thread's again)."""


@contextmanager
def cycle_reads(network: canopen.Network) -> Iterator[Receive | None]:
    """One lockstep cycle reads its answers in the calling thread, where the bus lets it
    (`SocketcandBus.claim_reads`: a socketcand connection whose receive thread is not reading
    right now), polling for them first (`ANSWER_POLL_S`): no hand-over from the receive
    thread, no sleep through the answer. With `feedbench sim` on this 2-core VM (29 Nov):
    5300 → 5700 cycles/s by the claim, 6165 → 8050 by the poll. Yields the `Receive` of the
    cycle, or None where the bus cannot (the receive thread's, as always)."""
    bus = network.bus
    claim = getattr(bus, "claim_reads", None)
    if claim is None or network.notifier is None or not claim():
        yield None
        return
    deliver = _Deliver(network.notifier.listeners).put
    try:
        yield lambda timeout_s: bus.read_to(deliver, timeout_s)
    finally:
        bus.release_reads()


def batched_sends(network: canopen.Network) -> AbstractContextManager[None]:
    """While inside, the frames the calling thread sends on `network` go out together at
    the end, in order, where its bus can write several in one go (`SocketcandBus.batch`,
    `sim_backends.socketcand_hub.HubPort.batch`); elsewhere each goes out as sent (nothing
    changes)."""
    batch = getattr(network.bus, "batch", None)
    return batch() if callable(batch) else nullcontext()


class LocalVirtualBus(virtual.VirtualBus):
    """python-can's `virtual` bus (same channels: its frames reach plain `VirtualBus`es on
    the channel and theirs reach it) at a fraction of the cost per frame: a frame is copied
    for each receiver by value, not by `copy.deepcopy` (≈ 13 µs against 2 µs per frame and
    receiver, measured), and it receives through a `queue.SimpleQueue` (C; `queue.Queue`
    takes and notifies a Python-level Condition per frame). A lockstep cycle of one drive
    moves 6 frames. Delivery, order and timestamps are python-can's: a copy per receiver,
    never the sender's own frame unless `receive_own_messages`."""

    def __init__(self, channel: Any = "channel-0", rx_queue_size: int = 0,
                 **options: Any) -> None:
        super().__init__(channel=channel, rx_queue_size=rx_queue_size, **options)
        if rx_queue_size:  # a bounded queue drops frames as python-can's does
            return
        with virtual.channels_lock:
            fast: queue.SimpleQueue[can.Message] = queue.SimpleQueue()
            self.channel[self.channel.index(self.queue)] = fast
            self.queue = fast  # type: ignore[assignment]

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._check_if_open()
        timestamp = msg.timestamp if self.preserve_timestamps else time.time()
        arbitration_id, extended, data = msg.arbitration_id, msg.is_extended_id, msg.data
        all_sent = True
        for bus_queue in self.channel:
            if bus_queue is self.queue and not self.receive_own_messages:
                continue
            copy = can.Message(
                timestamp=timestamp, arbitration_id=arbitration_id, is_extended_id=extended,
                is_remote_frame=msg.is_remote_frame, is_error_frame=msg.is_error_frame,
                channel=self.channel_id, dlc=msg.dlc, data=bytearray(data), is_fd=msg.is_fd,
                is_rx=bus_queue is not self.queue, bitrate_switch=msg.bitrate_switch,
                error_state_indicator=msg.error_state_indicator, check=False)
            try:
                bus_queue.put(copy, block=True, timeout=timeout)
            except queue.Full:
                all_sent = False
        if not all_sent:
            raise can.CanOperationError("Could not send message to one or more recipients")


class DirectVirtualBus(LocalVirtualBus):
    """A `LocalVirtualBus` whose frames, once a canopen network listens on it (`listen`,
    called by `connect`), go to the network's listeners in the sending thread instead of a
    queue and a receive thread. A simulated lockstep `Bench` in one process opens both its
    host and its simulated nodes on such buses when its run needs no device besides the
    drives (``direct`` in `open_bus`, ``one_thread`` in `feedbench.bench`): a cycle's RPDOs
    and SYNC run the drive and its world in the host's thread, and the TPDOs they send
    complete the host's set before the SYNC's send returns; two thread hand-overs a cycle
    fewer. The demo's runs took 10–25 % less CPU each with every recorded sample the same
    (SHA-1 of every dataset, 29 Nov 2026; all ten direct then, 38.6 → 33.0 s).

    Buses on the channel that do not listen (a faulty bus, python-can's `VirtualBus`) queue
    their frames as before; so do the buses of a bench with ``one_thread = false`` (the live
    window's: a run that never waits for its bus leaves the window's thread few chances to
    draw). A handler of a listening network runs while its sender holds its own network's
    send lock: it must not send on the network it listens on, nor wait for a frame (none
    does: they record what came, and the simulated nodes answer on their own network)."""

    def listen(self, listeners: list[can.Listener]) -> None:
        """From now on hand every frame to `listeners` as it is sent; frames queued before
        go to them first."""
        deliver = _Deliver(listeners)
        with virtual.channels_lock:
            inbox = self.queue
            self.channel[self.channel.index(inbox)] = deliver
            self.queue = deliver  # type: ignore[assignment]
        while not inbox.empty():
            deliver.put(inbox.get())


class _Deliver:
    """A listening `DirectVirtualBus`'s place in its channel: what a sender puts there goes
    to the listeners at once, in the sender's thread; a listener's error is logged, one
    line (canopen's `MessageListener` logs its handlers' own), and the next one gets the
    frame."""

    __slots__ = ("listeners",)

    def __init__(self, listeners: list[can.Listener]) -> None:
        self.listeners = list(listeners)

    def put(self, msg: can.Message, block: bool = True, timeout: float | None = None) -> None:
        for listener in self.listeners:
            try:
                listener.on_message_received(msg)
            except Exception as error:  # a listener's bug must not reach the sender
                DIRECT_LOGGER.error("listener %s failed on frame 0x%03X: %s: %s",
                                    type(listener).__name__, msg.arbitration_id,
                                    type(error).__name__, error)


def polled(look: Callable[[], Any], until_s: float) -> Any:
    """`look()` until it returns something true or `time.perf_counter()` passes `until_s`,
    giving the CPU to any other thread between looks (`os.sched_yield`) instead of
    sleeping; its last result. A thread asleep when its data arrives is woken through the
    other CPU on this 2-core VM (`ANSWER_POLL_S`, `socketcand_hub.NEXT_CYCLE_POLL_S`)."""
    while not (found := look()) and time.perf_counter() < until_s:
        os.sched_yield()
    return found


class SocketcandBus(SocketCanDaemonBus):
    """python-can's socketcand bus (its connection and handshake, the same text on the
    wire), with two changes:

    - its handshake waits at most `HANDSHAKE_TIMEOUT_S` for each line of the server:
      python-can 4.6.1's `_expect_msg` calls a blocking ``recv`` without a timeout, so a peer
      that accepts the connection and never speaks holds the host for as long as one waits
      (no upstream python-can issue found for it on 28 Nov 2026; searched hardbyte/python-can
      issues for socketcand handshake timeouts);
    - frames take fewer steps: `send` formats python-can's ``< send … >`` as bytes and
      writes it in one call; a receive takes up to `SOCKETCAND_RECEIVE_BYTES` and parses
      ``< frame … >`` messages as bytes (other messages: python-can's parser). python-can
      takes 1 KiB per receive, re-slices a str buffer per message, formats a debug line per
      receive and sets TCP_QUICKACK after every send and receive (a system call each; with
      TCP_NODELAY on both ends nothing waits for an acknowledgement). A connection the
      server closed raises `can.CanOperationError` (python-can returns nothing, and a
      receive thread then spins on the closed socket);
    - `batch()`: the frames one thread sends inside it go out in one write as it ends, in
      the order sent (a lockstep cycle's RPDOs and SYNC: one system call, and the server
      reads the cycle's frames in one wake-up instead of racing them frame by frame);
    - `claim_reads()`: a lockstep cycle reads the socket in its own thread (`read_to`,
      `cycle_reads`) while the receive thread stays off it (`READS_LEASE_S` after the
      last claim; one reader at a time).
    """

    def __init__(self, channel: str, host: str, port: int, **options: Any) -> None:
        self._frames: collections.deque[can.Message] = collections.deque()
        self._pending = b""
        """What came after the last complete message (``… >``)."""
        self._write_lock = threading.Lock()
        """One write at a time: two threads' texts never interleave on the stream."""
        self._batches = SendBatch(lambda texts: self._write(b"".join(texts)))
        self._reading = threading.Lock()
        """Held by whoever reads the socket: the receive thread, or a cycle (`claim_reads`)."""
        self._leased_until = 0.0
        """Until then (monotonic s) the receive thread leaves the socket to the cycles."""
        self._claimed = False
        """A cycle holds `_reading` (`claim_reads`)."""
        super().__init__(channel, host, port, **options)
        self._sock: socket.socket = self._SocketCanDaemonBus__socket  # python-can's (mangled)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Write `msg` as python-can does (`timeout` ignored, as by python-can); inside
        `batch()`, from its thread, at its end."""
        if msg.is_extended_id:
            can_id = b"%08X" % (msg.arbitration_id & 0x1FFFFFFF)
        else:
            can_id = b"%03X" % (msg.arbitration_id & 0x7FF)
        data = b" ".join([SOCKETCAND_HEX[value] for value in msg.data[:msg.dlc]])
        text = b"< send %s %X %s >" % (can_id, msg.dlc, data)
        if not self._batches.hold(text):
            self._write(text)

    def batch(self) -> AbstractContextManager[None]:
        """While inside, the frames this thread sends wait; on exit they go out in one
        write, in order (`SendBatch`). Other threads' frames go out at once, as always."""
        return self._batches.held()

    def _write(self, data: bytes) -> None:
        with self._write_lock:
            self._sock.sendall(data)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        """The next frame received, waiting up to `timeout` s for the server (None: no
        limit) if none is waiting. While a cycle's lease runs, only what already came (the
        rest of an answer the cycle left to this thread): nothing there, or a cycle holding
        the reads, and it returns nothing after waiting up to `timeout` s
        (`_wait_for_reads`)."""
        if self._reading.acquire(blocking=False):
            try:
                leased = self._leased_until > time.monotonic()
                if not self._frames:
                    self._receive(0.0 if leased else timeout)
                if self._frames or not leased:
                    return (self._frames.popleft() if self._frames else None), False
            finally:
                self._reading.release()
        self._wait_for_reads(timeout)
        return None, False

    def _wait_for_reads(self, timeout: float | None) -> None:
        """Sleep until the lease ends, or one lease while a cycle holds the reads past its
        lease (a slow cycle), at most `timeout` s."""
        wait_s = max(self._leased_until - time.monotonic(), 0.0) or READS_LEASE_S
        time.sleep(wait_s if timeout is None else min(wait_s, timeout))

    def claim_reads(self) -> bool:
        """Take the socket's reads, and the frames received but not handed on yet, for the
        calling thread (`read_to`) until `release_reads`; the receive thread stays off them
        until `READS_LEASE_S` after the release. False if the receive thread is reading
        now: it lets go after this read (the lease is set)."""
        self._leased_until = time.monotonic() + READS_LEASE_S
        if not self._reading.acquire(blocking=False):
            return False
        self._claimed = True
        return True

    def release_reads(self) -> None:
        """End `claim_reads`, unless a receive error ended it; the receive thread stays off
        the socket `READS_LEASE_S` more (the next cycle claims it well within that)."""
        if self._claimed:
            self._claimed = False
            self._leased_until = time.monotonic() + READS_LEASE_S
            self._reading.release()

    def read_to(self, deliver: Callable[[can.Message], None], timeout_s: float) -> bool:
        """Under `claim_reads`: the frames received but not handed on yet, else whatever
        the server sends within `timeout_s` (s), each to `deliver` in this thread. False
        without the claim: a receive error ends it (and its lease), and the receive thread
        meets the error again and keeps it (`ReceiveErrors`), as without a claim."""
        if not self._claimed:
            return False
        frames = self._frames
        if not frames:
            try:
                self._poll(min(timeout_s, ANSWER_POLL_S))
                self._receive(max(timeout_s, 0.0))
            except can.CanOperationError:
                self.release_reads()
                self._leased_until = 0.0
                return False
        while frames:
            deliver(frames.popleft())
        return True

    def _poll(self, poll_s: float) -> None:
        """Return once the server has sent something or after `poll_s` (s), yielding the
        CPU between looks instead of sleeping (`ANSWER_POLL_S`)."""
        sock = [self._sock]
        try:
            polled(lambda: select.select(sock, [], [], 0)[0], time.perf_counter() + poll_s)
        except (OSError, ValueError) as exc:  # closed: a ValueError for its fd -1
            raise can.CanOperationError(f"Failed to receive: {exc}") from exc

    def _receive(self, timeout: float | None) -> None:
        """Whatever the server sent within `timeout` s; its complete messages parsed."""
        try:
            if not select.select([self._sock], [], [], timeout)[0]:
                return
            data = self._sock.recv(SOCKETCAND_RECEIVE_BYTES)
        except (OSError, ValueError) as exc:  # closed meanwhile: a ValueError for its fd -1
            raise can.CanOperationError(f"Failed to receive: {exc}") from exc
        if not data:
            raise can.CanOperationError(f"{self.channel_info}: the server closed the connection")
        self._take(data)

    def _take(self, data: bytes) -> None:
        """Received bytes: their complete messages parsed into frames, the rest kept."""
        messages, self._pending = socketcand_messages(self._pending, data)
        for message in messages:
            if (msg := self._parse(message)) is not None:
                self._frames.append(msg)

    def _parse(self, message: bytes) -> can.Message | None:
        """One server message ``< …`` (its ``>`` cut off) → its frame (None, logged: not a
        frame, or malformed)."""
        fields = message[1:].split()
        try:
            if len(fields) < 3 or fields[0] != b"frame":  # python-can's parser: not a frame
                msg = convert_ascii_message_to_can_message(
                    message.decode("ascii", "replace") + ">")
            else:
                msg = can.Message(timestamp=float(fields[2]), arbitration_id=int(fields[1], 16),
                                  data=bytearray.fromhex(b"".join(fields[3:]).decode("ascii")),
                                  is_extended_id=len(fields[1]) != 3, is_rx=True, check=False)
        except (ValueError, IndexError, UnicodeDecodeError):  # python-can's raises on < error … >
            SOCKETCAND_LOGGER.warning("Invalid message: %r", message)
            return None
        if msg is not None:
            msg.channel = self.channel
        return msg

    def _expect_msg(self, msg: str) -> None:
        """python-can's check of the server's line `msg` (its error if another line came),
        bounded in time: a silent server raises `can.CanInitializationError` and the socket
        is closed. What came after the line in the same receive is kept for `_receive`:
        frames a busy bus relayed right after raw mode's ``< ok >`` (python-can fails on
        them; seen once in a suite with one CPU burnt: the hub's `JOIN_S` had passed)."""
        sock = self._SocketCanDaemonBus__socket  # python-can's own socket (name-mangled)
        sock.settimeout(HANDSHAKE_TIMEOUT_S)
        try:
            received = sock.recv(256)
        except TimeoutError:
            sock.close()
            raise can.CanInitializationError(
                f"the server did not say {msg!r} within {HANDSHAKE_TIMEOUT_S:g} s") from None
        sock.settimeout(None)
        line = msg.encode("ascii")
        if not received.startswith(line):
            raise can.CanError(f"Expected '{msg}' got: '{received.decode('ascii', 'replace')}'")
        self._take(received[len(line):])


def open_bus(interface: str, channel: str, bitrate: int = 1_000_000, **options: Any) -> can.BusABC:
    """A python-can bus; for ``socketcand`` the TCP tuning is on, its handshake bounded in
    time and its frame path lean (`SocketcandBus`) and its log off (a warning per frame; a
    receive error per poll once the peer is gone: `ReceiveErrors`); ``virtual`` is
    `LocalVirtualBus`, or `DirectVirtualBus` with ``direct=True``.

    An unknown interface, or a channel or server that cannot be opened, raises `ConfigError`
    naming the [bench] key.
    """
    try:
        if interface == "socketcand":
            SOCKETCAND_LOGGER.setLevel(logging.CRITICAL)
            options.setdefault("tcp_tune", True)
            reach(options["host"], options["port"])
            return SocketcandBus(channel=channel, bitrate=bitrate, **options)
        if interface == "virtual":
            bus_class = DirectVirtualBus if options.pop("direct", False) else LocalVirtualBus
            return bus_class(channel=channel, bitrate=bitrate, **options)
        return can.Bus(interface=interface, channel=channel, bitrate=bitrate, **options)
    except can.CanInterfaceNotImplementedError as exc:
        raise ConfigError(f"bench.interface: {exc}") from None
    except (can.CanError, OSError) as exc:  # no such channel, no server, no permission
        where = (f"bench.socketcand: {options.get('host')}:{options.get('port')}"
                 if interface == "socketcand" else f"bench.channel: {interface} {channel!r}")
        raise ConfigError(f"{where}: cannot open ({exc})") from None


def reach(host: str, port: int, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
    """Connect to a TCP server once and close again, retrying a refused connection (a server
    still starting) until `timeout_s`; raises `OSError` if it cannot be reached by then."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection((host, port), timeout=timeout_s):
                return
        except ConnectionRefusedError:
            if time.monotonic() >= deadline:
                raise
            time.sleep(0.1)


def disconnect(network: canopen.Network) -> None:
    """Stop the network's receive thread and close its bus. A bus whose peer has gone (a
    socketcand server killed: connection reset) is closed all the same, without an error:
    closing is all that is left to do."""
    try:
        network.disconnect()  # raises the receive thread's last error after closing the bus
    except (can.CanError, OSError):
        if network.bus is not None:
            try:
                network.bus.shutdown()
            except (can.CanError, OSError):  # already gone
                pass
            network.bus = None


def open_network(interface: str, channel: str, bitrate: int = 1_000_000,
                 **options: Any) -> canopen.Network:
    """A connected canopen Network on a new python-can bus (`options` go to python-can)."""
    return connect(canopen.Network(open_bus(interface, channel, bitrate, **options)))


class PdoCodec(NamedTuple):
    """Packs / unpacks one PDO's payload in one `struct` call; `indices` in mapping order."""

    layout: struct.Struct
    indices: tuple[int, ...]
    offsets: tuple[int, ...]
    formats: tuple[str, ...]


def pdo_codec(pdo_map: PdoMap) -> PdoCodec:
    """The codec of a byte-aligned PDO mapping (canopen decodes bit by bit: too slow per cycle)."""
    formats, offsets = [], []
    for var in pdo_map.map:
        fmt = ODVariable.STRUCT_TYPES[var.od.data_type].format.lstrip("<")
        if var.offset % 8 or var.length != 8 * struct.calcsize("<" + fmt):
            raise ValueError(f"{pdo_map.name}: 0x{var.index:04X} must be byte-aligned, "
                             "at its full length")
        formats.append(fmt)
        offsets.append(var.offset // 8)
    return PdoCodec(struct.Struct("<" + "".join(formats)),
                    tuple(var.index for var in pdo_map.map), tuple(offsets), tuple(formats))


def length_checked(handler: Handler, length: int,
                   rejected: collections.Counter[str]) -> Handler:
    """`handler` for frames of at least `length` data bytes; a shorter frame is dropped and
    counted in `rejected` under its reason (canopen's decoders would raise struct.error)."""
    def checked(can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) >= length:
            handler(can_id, data, timestamp)
        else:
            rejected[f"COB-ID 0x{can_id:03X}: {len(data)} data bytes, "
                     f"the service needs {length}"] += 1
    return checked


def check_lengths(handlers: Iterable[tuple[object, str, int]],
                  rejected: collections.Counter[str]) -> None:
    """Each (canopen object, handler name, data bytes): the handler becomes its
    `length_checked`. Call before the node joins its network, which then subscribes (and on
    leaving unsubscribes) the checked handlers."""
    for owner, name, length in handlers:
        setattr(owner, name, length_checked(getattr(owner, name), length, rejected))


def state_checked(on_heartbeat: Handler, rejected: collections.Counter[str]) -> Handler:
    """canopen's heartbeat consumer for states CiA 301 defines; a heartbeat with another
    state is dropped and counted in `rejected` (canopen would keep it as the node's state and
    raise KeyError naming it at the next NMT command)."""
    def checked(can_id: int, data: bytearray, timestamp: float) -> None:
        if data[0] & HEARTBEAT_STATE_MASK in NMT_STATES:
            on_heartbeat(can_id, data, timestamp)
        else:
            rejected[f"COB-ID 0x{can_id:03X}: heartbeat state "
                     f"{data[0] & HEARTBEAT_STATE_MASK} unknown"] += 1
    return checked


class GuardedSdoServer:
    """canopen's SDO server as CiA 301 §7.2.4.3 requires it to answer (its node's simulated
    side): a segment request that does not continue the open transfer (none open, an upload
    segment during a download or the reverse) and a block transfer (none offered) are
    aborted with 0x05040001 (canopen's server answers a stale segment from its old buffer
    and a block upload as an ordinary upload), as is an undefined command specifier, each
    abort naming the request's own index and sub-index; a download of more or fewer bytes than the
    object's data type is aborted with 0x06070012 / 0x06070013 (canopen: 0x06070010 for
    both). A request shorter than 8 bytes is dropped and counted in `rejected`."""

    def __init__(self, server: canopen.sdo.SdoServer, rejected: collections.Counter[str]) -> None:
        self.server = server
        self.rejected = rejected
        self.expected: int | None = None
        """The segment request the open transfer expects next (None: no transfer open)."""
        self._serve = server.on_request
        self._abort = server.abort
        server.abort = self._aborted
        self._set_data = server._node.set_data
        server._node.set_data = self._length_checked_set_data
        server.on_request = length_checked(self.on_request, SDO_BYTES, rejected)

    def on_request(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """Serve one request, or abort it with 0x05040001."""
        ccs = data[0] & SDO_COMMAND_MASK
        if ccs in SDO_REFUSED_REQUESTS or (ccs in SDO_SEGMENT_REQUESTS and ccs != self.expected):
            self._refuse(can_id, ccs, data)
            return
        if ccs not in SDO_SEGMENT_REQUESTS:  # a new request ends any open transfer
            self.server._buffer = None
        self._serve(can_id, data, timestamp)
        self.expected = self._next_segment(ccs, data[0])

    def _refuse(self, can_id: int, ccs: int, data: bytearray) -> None:
        server = self.server
        if ccs in SDO_REFUSED_REQUESTS:
            server._index, server._subindex = SDO_INDEX.unpack_from(data, 1)
        else:
            self.rejected[f"COB-ID 0x{can_id:03X}: SDO segment without a transfer"] += 1
            server._index, server._subindex = 0, 0
        self._aborted(cia301.SDO_ABORT_COMMAND_SPECIFIER)

    def _aborted(self, code: int = cia301.SDO_ABORT_GENERAL) -> None:
        """canopen's abort, and the transfer is closed."""
        self.server._buffer = None
        self.expected = None
        self._abort(code)

    def _next_segment(self, ccs: int, command: int) -> int | None:
        """The segment request expected after serving `ccs` (None: the transfer is over)."""
        buffer = self.server._buffer
        if buffer is None:
            return None
        if ccs in (SDO_INITIATE_UPLOAD, SDO_UPLOAD_SEGMENT):
            return SDO_UPLOAD_SEGMENT if buffer else None
        if ccs == SDO_INITIATE_DOWNLOAD or (ccs == SDO_DOWNLOAD_SEGMENT
                                            and not command & SDO_LAST_SEGMENT):
            return SDO_DOWNLOAD_SEGMENT
        return None

    def _length_checked_set_data(self, index: int, subindex: int, data: bytes,
                                 check_writable: bool = False) -> None:
        obj = self.server._node._find_object(index, subindex)
        writable = obj.writable or not check_writable
        if writable and obj.data_type in NUMBER_TYPES and 8 * len(data) != len(obj):
            raise canopen.SdoAbortedError(cia301.SDO_ABORT_LENGTH_TOO_HIGH
                                          if 8 * len(data) > len(obj)
                                          else cia301.SDO_ABORT_LENGTH_TOO_LOW)
        self._set_data(index, subindex, data, check_writable)


def import_eds(path: str | os.PathLike, node_id: int) -> canopen.ObjectDictionary:
    """`canopen.import_od` of the EDS (or DCF) file at `path` for `node_id`: parsed once per
    file content in a process, then each call unpickles a copy of that parse, its own
    objects as from `import_od` (0.6 ms, reading and hashing the file included, against
    10 ms a drive; the suite opened thousands of drives, ≈ 25 s of its CPU in
    configparser). Keyed on the content, not the modification time: a DCF edited in place
    to a value of the same length within the file system's time resolution is read anew."""
    path = os.path.abspath(path)
    with open(path, "rb") as stream:
        digest = hashlib.blake2b(stream.read()).digest()
    return pickle.loads(_parsed_eds(path, node_id, digest))


@functools.lru_cache(maxsize=32)
def _parsed_eds(path: str, node_id: int, digest: bytes) -> bytes:
    """The pickled object dictionary of one content (`digest`) of an EDS file
    (`import_eds`)."""
    return pickle.dumps(canopen.import_od(path, node_id))


def remote_node(network: canopen.Network, node_id: int,
                object_dictionary: str | os.PathLike | canopen.ObjectDictionary,
                rejected: collections.Counter[str] | None = None) -> canopen.RemoteNode:
    """A RemoteNode added to `network` (`object_dictionary`: the path of its EDS file, read
    by `import_eds`, or the dictionary), its SDO client waiting `SDO_TIMEOUT_S` per answer;
    its SDO, heartbeat, EMCY and NMT frames shorter than CiA 301's and heartbeats of an
    unknown state are dropped and counted in `rejected`."""
    if isinstance(object_dictionary, (str, os.PathLike)):
        object_dictionary = import_eds(object_dictionary, node_id)
    node = canopen.RemoteNode(node_id, object_dictionary)
    node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
    rejected = collections.Counter() if rejected is None else rejected
    node.nmt.on_heartbeat = state_checked(node.nmt.on_heartbeat, rejected)
    check_lengths([(node.sdo, "on_response", SDO_BYTES),
                   (node.nmt, "on_heartbeat", HEARTBEAT_BYTES), (node.emcy, "on_emcy", EMCY_BYTES),
                   (node.nmt, "on_command", NMT_BYTES)], rejected)
    network.add_node(node)
    return node
