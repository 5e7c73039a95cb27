"""A socketcand server in raw mode: processes on one machine share CAN buses over loopback TCP.

Hand-written: socketcand itself is a C daemon over kernel SocketCAN (not available here, see
STACKS.md) and no Python library provides a socketcand server; python-can only has the
client (`interface="socketcand"`). The hub speaks the subset that client uses:

    server: < hi >                 client: < open <bus> >     server: < ok >
    client: < rawmode >            server: < ok >
    client: < send <id> <dlc> <byte> … >      (hex; an 8-digit id is an extended id)
    server: < frame <id> <seconds.micros> <hex data> >   to every other client on <bus>

A frame goes to every other client that opened the same bus name, never back to its sender
(as on SocketCAN without `recv_own_msgs`). A new client receives frames only once it has sent
its first frame or `JOIN_S` after its raw-mode `< ok >`: python-can reads that `< ok >` with
a single `recv` and would fail if a frame arrived in the same TCP segment.

Nodes in the hub's own process (`feedbench sim`'s simulated drives) join a bus through a
`HubPort` (python-can interface ``feedbench_hub``) instead of a TCP connection to themselves:
a frame a TCP client sends reaches them without a second trip through the text protocol and
the kernel (a canopen network's listener straight as its `Network.notify` call, others as a
`can.Message`), and a frame they send is written to the TCP clients at once by the sending
thread. Within one process, that halves the loopback hops of a cycle. Frames the
ports send in the hub's thread while it delivers a client's frame to them (a drive's answer
to SYNC: its TPDOs) wait until `flush()` or the end of that delivery, then go out in one
write per client: one wake-up of the host's receive thread per cycle, not one per frame
(`process.SimulatedBench` flushes right after the drive's TPDOs, before its world steps).
The frames of one receive from a client (a lockstep cycle's RPDOs and SYNC, which the
host writes at once: `protocols.canbus.batched_sends`) are relayed together: one stamp,
one write to each other client, then to the ports in order.
"""

from __future__ import annotations

import binascii
import logging
import os
import queue
import selectors
import socket
import threading
import time
from collections.abc import Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass, field

import can
from canopen.network import MessageListener

from feedbench.protocols.address import LOOPBACK
from feedbench.protocols.canbus import SendBatch, polled, socketcand_messages

LOGGER = logging.getLogger(__name__)
CANOPEN_LOGGER = logging.getLogger("canopen.network")
"""Where canopen's `MessageListener` logs an error of its network's handlers (`HubPort`
logs one there as it would)."""
JOIN_S = 0.05
RECEIVE_BYTES = 65536
NEXT_CYCLE_POLL_S = 300e-6
"""How long the hub polls for a client's next frames after relaying some that its ports
answered, giving the CPU to any other thread between looks (`protocols.canbus.polled`),
before it sleeps in `select` (s); only while the frames came within this time of the relay
before them: a lockstep host's next cycle (its RPDOs and SYNC ≈ 0.1 ms after the drive's
answers), not a real-time host (its RPDOs come soon after the TPDOs but are not answered;
its next SYNC comes ≈ 0.7 ms later). The host's side polls the same way
(`protocols.canbus.ANSWER_POLL_S`). With every device served, quiet: 5201 / 5403 → 7329 /
7091 cycles/s (median of 5, two A/B runs, 30 Nov); with another process burning one CPU
3513 → 3239. Only for ports that answer in the hub's thread: a port wrapped for fault
injection (`faults.FaultyBus`) is answered from canopen's receive thread, and the hub then
sleeps between cycles as before."""
THREAD_TIMEOUT_S = 5.0


class HubError(RuntimeError):
    """The hub could not start."""


@dataclass
class _Client:
    sock: socket.socket
    bus: str | None = None
    raw: bool = False
    joined_at: float = float("inf")
    inbox: bytes = b""
    """What came after the last complete message (``… >``)."""
    outbox: bytearray = field(default_factory=bytearray)
    writing: bool = False
    """Registered for EVENT_WRITE: the outbox holds what the socket did not take."""

    def receives(self, now: float) -> bool:
        """Frames are delivered to it (raw mode, and it has sent or waited `JOIN_S`)."""
        return self.raw and now >= self.joined_at


HEX_BYTE = {form.format(value).encode("ascii"): value
            for value in range(256) for form in ("{:x}", "{:02x}", "{:X}", "{:02X}")}
"""A data byte's token in `< send … >` (1 or 2 hex digits, either case) → its value."""
_hex_byte = HEX_BYTE.__getitem__

Frame = tuple[int, bool, bytearray]
"""A data frame: (id, extended: a 29-bit id, written as 8 hex digits, payload)."""


def frames_text(frames: Sequence[Frame], stamp: float) -> bytes:
    """The server's `< frame <id> <seconds.micros> <HEX DATA> >` messages for `frames`
    received at `stamp` (s since the epoch), in order, in one piece; the id as socketcand
    writes it: 3 hex digits, or 8 for an extended id."""
    at = b" %.6f " % stamp
    return b"".join([b"< frame %s%s%s >" % (b"%08X" % can_id if extended else b"%03X" % can_id,
                                            at, binascii.hexlify(data).upper())
                     for can_id, extended, data in frames])


def parse_send(fields: list[bytes]) -> Frame:
    """`send <id> <dlc> <bytes…>` tokens → its frame (`Frame`); ValueError if malformed."""
    can_id, dlc = fields[1], int(fields[2], 16)
    try:
        data = bytearray(map(_hex_byte, fields[3:3 + dlc]))
    except KeyError:
        raise ValueError(f"malformed send: {fields!r}") from None
    if len(can_id) not in (3, 8) or len(data) != dlc or dlc > 8:
        raise ValueError(f"malformed send: {fields!r}")
    return int(can_id, 16), len(can_id) == 8, data


class SocketcandHub:
    """The hub on `host:port` (port 0: a free one); `start()` returns the address it listens on."""

    def __init__(self, host: str = LOOPBACK, port: int = 0) -> None:
        self.host = host
        self.port = port
        self.frames = 0
        """Frames relayed: from TCP clients and from ports (each delivered to every other
        client and port of its bus)."""
        self._selector = selectors.DefaultSelector()
        self._clients: dict[socket.socket, _Client] = {}
        self._ports: list[HubPort] = []
        self._lock = threading.RLock()
        """Guards the clients and their outboxes: the hub's thread and its ports' threads
        relay frames (in one order to every client)."""
        self._holding = False
        """The hub's thread is delivering a client's frame to the ports: what they send from
        it waits in the outboxes for `flush()`."""
        self._held: list[_Client] = []
        """Clients with frames waiting for `flush()`."""
        self._answered = False
        """Set by `_send` when the hub's thread, while `_holding`, queues a port's answer for a
        TCP client (an early `flush()` leaves it set); reset as each `_relay` delivers (after
        the sender's frames went to the other clients)."""
        self._listener: socket.socket | None = None
        self._wake_read, self._wake_write = os.pipe()
        self._closing = False
        self._relayed_at = -float("inf")
        """When the hub's thread last relayed a client's frames (`time.perf_counter`, s)."""
        self._poll_after_relay = False
        """The last relay's frames were answered by the ports (`_answered`) and came within
        `NEXT_CYCLE_POLL_S` of the relay before them."""
        self._thread = threading.Thread(target=self._serve, name="socketcand-hub", daemon=True)

    def start(self) -> tuple[str, int]:
        """Listen and serve in a background thread; returns (host, port)."""
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            listener.bind((self.host, self.port))
        except OSError as error:
            listener.close()
            self.stop()
            raise HubError(f"socketcand hub cannot listen on {self.host}:{self.port}: "
                           f"{error}") from error
        listener.listen()
        listener.setblocking(False)
        self._listener = listener
        self.port = listener.getsockname()[1]
        self._selector.register(listener, selectors.EVENT_READ)
        self._selector.register(self._wake_read, selectors.EVENT_READ)
        self._thread.start()
        return self.host, self.port

    def stop(self) -> None:
        """Close every connection and the listener; the thread ends."""
        if self._wake_write < 0:
            return
        self._closing = True
        os.write(self._wake_write, b"\0")
        if self._thread.is_alive():
            self._thread.join(THREAD_TIMEOUT_S)
        for fd in (self._wake_read, self._wake_write):
            os.close(fd)
        self._wake_read = self._wake_write = -1

    def __enter__(self) -> SocketcandHub:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _serve(self) -> None:
        try:
            while not self._closing:
                for key, events in self._ready():
                    self._dispatch(key.fileobj, events)
        finally:
            for sock in list(self._clients):
                self._drop(sock)
            self._selector.close()
            self._listener.close()

    @property
    def polls_for_next_cycle(self) -> bool:
        """The hub polls for a client's next frames now (`NEXT_CYCLE_POLL_S`): the last ones
        were answered by its ports and came within that time of the relay before them."""
        return self._poll_after_relay

    def _ready(self) -> list[tuple[selectors.SelectorKey, int]]:
        """The selector's next events: polled for first while a client's frames are expected
        soon (`NEXT_CYCLE_POLL_S`), then waited for (at most `JOIN_S`)."""
        if self._poll_after_relay and (ready := polled(
                lambda: self._selector.select(timeout=0), self._relayed_at + NEXT_CYCLE_POLL_S)):
            return ready
        return self._selector.select(timeout=JOIN_S)

    def _dispatch(self, source, events: int) -> None:
        if source is self._listener:
            self._accept()
        elif source == self._wake_read:
            os.read(self._wake_read, 64)
        elif (client := self._clients.get(source)) is not None:  # a port may drop it meanwhile
            if events & selectors.EVENT_READ:
                self._receive(client)
            if events & selectors.EVENT_WRITE:
                self._flush(client)

    def _accept(self) -> None:
        try:
            sock, _ = self._listener.accept()
        except OSError:  # the connection went away before it was accepted
            return
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setblocking(False)
        client = _Client(sock)
        with self._lock:
            self._clients[sock] = client
            self._selector.register(sock, selectors.EVENT_READ)
            self._send(client, b"< hi >")

    def attach(self, port: HubPort) -> None:
        """Deliver the frames of `port.channel` to `port` from now on."""
        with self._lock:
            self._ports.append(port)

    def detach(self, port: HubPort) -> None:
        """No more frames to `port`."""
        with self._lock:
            if port in self._ports:
                self._ports.remove(port)

    def relay_from_port(self, sender: HubPort, msgs: Sequence[can.Message]) -> None:
        """Frames a port sends, in order: to every TCP client (stamped now) and every other
        port of its bus."""
        frames = [(msg.arbitration_id, msg.is_extended_id, msg.data) for msg in msgs]
        for port in self._fan_out(sender, sender.channel, frames, time.time()):
            for msg in msgs:
                port.deliver(msg)

    def _fan_out(self, sender: object, bus: str | None, frames: Sequence[Frame],
                 stamp: float) -> list[HubPort]:
        """Frames from `sender` on `bus`, in order: their text (`frames_text` at `stamp`,
        made only if a client takes it) to every TCP client of the bus that receives frames,
        in one piece; returns the ports of the bus to deliver them to, outside the lock (a
        port's listeners send frames themselves). Never back to `sender`."""
        with self._lock:
            self.frames += len(frames)
            now = time.monotonic()
            clients = [client for client in self._clients.values() if client is not sender
                       and client.bus == bus and client.receives(now)]
            if clients:
                text = frames_text(frames, stamp)
                for client in clients:
                    self._send(client, text)
            return [port for port in self._ports if port is not sender and port.channel == bus]

    def _receive(self, client: _Client) -> None:
        try:
            data = client.sock.recv(RECEIVE_BYTES)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            self._drop(client.sock)
            return
        messages, client.inbox = socketcand_messages(client.inbox, data)
        frames: list[Frame] = []
        for message in messages:
            if not (tokens := message[1:].split()):
                continue
            if tokens[0] == b"send" and client.raw:
                try:
                    frames.append(parse_send(tokens))
                    continue
                except (ValueError, IndexError):  # malformed: answered by `_handle`, in place
                    pass
            if frames:
                self._relay(client, frames)
                frames = []
            self._handle(client, tokens)
        if frames:
            self._relay(client, frames)

    def _handle(self, client: _Client, message: list[bytes]) -> None:
        command = message[0]
        if command == b"send" and client.raw:  # a frame `_receive` could not parse
            LOGGER.warning("socketcand hub: malformed frame %r: answered < error >",
                           _text(message))
            self._send(client, b"< error malformed frame >")
        elif command == b"open" and len(message) == 2 and client.bus is None:
            client.bus = message[1].decode("ascii", "replace")
            self._send(client, b"< ok >")
        elif command == b"rawmode" and client.bus is not None:
            client.raw = True
            client.joined_at = time.monotonic() + JOIN_S
            self._send(client, b"< ok >")
        elif command == b"echo":
            self._send(client, b"< echo >")
        else:
            LOGGER.warning("socketcand hub: unsupported command %r: answered < error >",
                           _text(message))
            self._send(client, b"< error unsupported command >")

    def _relay(self, sender: _Client, frames: list[Frame]) -> None:
        """The frames (`parse_send`) one receive from `sender` brought, in order: stamped
        alike (they arrived together), to the TCP clients in one write each, then to the
        ports (`HubPort.deliver_frame`); what the ports send meanwhile waits for the end
        (`_holding`)."""
        sender.joined_at = min(sender.joined_at, time.monotonic())
        soon = time.perf_counter() - self._relayed_at < NEXT_CYCLE_POLL_S
        stamp = time.time()
        ports = self._fan_out(sender, sender.bus, frames, stamp)
        self._holding, self._answered = True, False
        try:
            for can_id, extended, data in frames:
                for port in ports:
                    port.deliver_frame(can_id, extended, data, stamp)
        finally:
            self._holding = False
            self._poll_after_relay = soon and self._answered
            if self._held:
                self.flush()
            self._relayed_at = time.perf_counter()

    def flush(self) -> None:
        """Write the frames the ports' answers left waiting (`_holding`) now."""
        with self._lock:
            held, self._held = self._held, []
            for client in held:
                self._flush(client)

    def _send(self, client: _Client, text: bytes) -> None:
        """Queue `text` and write what the socket takes now (never blocks the hub); from the
        hub's thread while `_holding`, only queue it for `flush()`."""
        with self._lock:
            client.outbox += text
            if not (self._holding and threading.get_ident() == self._thread.ident):
                self._flush(client)
            else:
                self._answered = True
                if client not in self._held:
                    self._held.append(client)

    def _flush(self, client: _Client) -> None:
        """Write what the socket takes of the outbox; watch for writability while some is
        left."""
        with self._lock:
            if client.sock not in self._clients:
                return
            try:
                sent = client.sock.send(client.outbox)
            except (BlockingIOError, InterruptedError):
                sent = 0
            except OSError:
                self._drop(client.sock)
                return
            del client.outbox[:sent]
            self._want_write(client, bool(client.outbox))

    def _want_write(self, client: _Client, writing: bool) -> None:
        """Watch `client` for writability (`writing`) or only for reading."""
        if client.writing != writing:
            client.writing = writing
            self._selector.modify(client.sock, selectors.EVENT_READ
                                  | (selectors.EVENT_WRITE if writing else 0))

    def _drop(self, sock: socket.socket) -> None:
        with self._lock:
            self._clients.pop(sock, None)
            try:
                self._selector.unregister(sock)
            except (KeyError, ValueError):
                pass
            sock.close()


def _text(message: list[bytes]) -> str:
    """A received message's tokens as one line of text (for the log)."""
    return b" ".join(message).decode("ascii", "replace")


class HubPort(can.BusABC):
    """A python-can bus on the hub's bus `channel` for nodes in the hub's own process
    (interface ``feedbench_hub``, option ``hub``: the running `SocketcandHub`).

    `send` relays the frame to the bus's TCP clients and other ports in the calling thread.
    Frames from them queue for `recv`, or, once `listen` was called, go straight to the
    listeners in the thread that relayed them (the hub's): no receive thread, no hand-over
    between threads in a cycle (`protocols.canbus.connect` does this for a canopen network;
    a port wrapped for fault injection, `faults.FaultyBus`, is read by canopen's receive
    thread as before). `feedbench sim` has one port per hub: a frame from one port to
    another would run the receiver's listeners in the sender's thread, under its locks.
    """

    def __init__(self, channel: str, hub: SocketcandHub, **_: object) -> None:
        self.channel = str(channel)
        self.channel_info = f"feedbench hub port on {self.channel}"
        self._hub = hub
        self._inbox: queue.SimpleQueue[can.Message] = queue.SimpleQueue()
        self._listeners: list[can.Listener] = []
        self._batches = SendBatch(lambda msgs: hub.relay_from_port(self, msgs))
        super().__init__(channel=self.channel)
        hub.attach(self)

    def listen(self, listeners: list[can.Listener]) -> None:
        """From now on give every frame to `listeners` (python-can `Listener`s) at once;
        frames queued before go to them first."""
        self._listeners = list(listeners)
        while not self._inbox.empty():
            self.deliver(self._inbox.get())

    def deliver(self, msg: can.Message) -> None:
        """A frame of the bus for this port (called by the hub, any thread). A listener's
        error is logged, one line, and the frame goes on to the next listener."""
        listeners = self._listeners
        if not listeners:
            self._inbox.put(msg)
        for listener in listeners:
            self._give(listener, msg)

    def deliver_frame(self, can_id: int, extended: bool, data: bytearray, stamp: float) -> None:
        """A data frame of a TCP client received at `stamp` (s since the epoch) for this port
        (called by the hub's thread), as `deliver` gives it, except that a canopen
        `MessageListener` gets it as its `on_message_received` would pass a data frame on,
        `network.notify(can_id, data, stamp)`, without a `can.Message` (its handler's error
        is logged as canopen logs it, `CANOPEN_LOGGER`); the others get one `can.Message`,
        made for the first of them."""
        msg = None
        listeners = self._listeners
        for listener in listeners:
            if type(listener) is MessageListener:
                try:
                    listener.network.notify(can_id, data, stamp)
                except Exception as error:  # canopen's listener logs it and goes on
                    CANOPEN_LOGGER.error(str(error))
                continue
            if msg is None:
                msg = self._message(can_id, extended, data, stamp)
            self._give(listener, msg)
        if not listeners:
            self._inbox.put(self._message(can_id, extended, data, stamp))

    def _message(self, can_id: int, extended: bool, data: bytearray, stamp: float) -> can.Message:
        """The frame as python-can's message on this port's channel, stamped `stamp` (s)."""
        return can.Message(timestamp=stamp, arbitration_id=can_id, data=data,
                           is_extended_id=extended, channel=self.channel, check=False)

    def _give(self, listener: can.Listener, msg: can.Message) -> None:
        """`msg` to `listener`; its error is logged, one line, and not raised."""
        try:
            listener.on_message_received(msg)
        except Exception as error:  # a listener's bug must not stop the hub
            LOGGER.error("hub port %s: listener %s failed on frame 0x%03X: %s: %s",
                         self.channel, type(listener).__name__, msg.arbitration_id,
                         type(error).__name__, error)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self._is_shutdown:
            raise can.CanOperationError(f"{self.channel_info}: shut down")
        if not self._batches.hold(msg):
            self._hub.relay_from_port(self, (msg,))

    def batch(self) -> AbstractContextManager[None]:
        """While inside, the frames this thread sends are relayed together as it ends, in
        order (`protocols.canbus.SendBatch`): one stamp, one piece to each TCP client (a
        drive's TPDOs, `protocols.canbus.send_frames`). Other threads' frames go at once."""
        return self._batches.held()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        try:
            return self._inbox.get(timeout=timeout), False
        except queue.Empty:
            return None, False

    def shutdown(self) -> None:
        self._listeners = []
        self._hub.detach(self)
        super().shutdown()
