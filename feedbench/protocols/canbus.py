"""CAN bus access for both sides: open a canopen Network, fast PDO codecs.

The interface names are python-can's: ``virtual`` (tests, simulation: any channel name),
``socketcan`` (channel ``can0`` on Linux), ``socketcand`` (a TCP bridge), …
"""

from __future__ import annotations

import logging
import struct
from typing import Any, NamedTuple

import can
import canopen
from canopen.objectdictionary import ODVariable
from canopen.pdo import PdoMap

from feedbench.config import ConfigError

SDO_TIMEOUT_S = 2.0
"""How long an SDO request waits for its answer (canopen's default 0.3 s is short for a peer
busy for a moment, e.g. a simulated world compiling its physics on first use)."""

NOTIFIER_POLL_S = 0.05
"""Receive-thread poll period: bounds how long `Network.disconnect` waits (canopen: 1 s)."""


def connect(network: canopen.Network) -> canopen.Network:
    """Start the network's receive thread with a short poll period, so it closes quickly."""
    network.NOTIFIER_CYCLE = NOTIFIER_POLL_S
    return network.connect()


def open_bus(interface: str, channel: str, bitrate: int = 1_000_000, **options: Any) -> can.BusABC:
    """A python-can bus; for ``socketcand`` the TCP tuning is on and its per-frame warnings off.

    An unknown interface, or a channel or server that cannot be opened, raises `ConfigError`
    naming the [bench] key.
    """
    if interface == "socketcand":
        logging.getLogger("can.interfaces.socketcand").setLevel(logging.ERROR)
        options.setdefault("tcp_tune", True)
    try:
        return can.Bus(interface=interface, channel=channel, bitrate=bitrate, **options)
    except can.CanInterfaceNotImplementedError as exc:
        raise ConfigError(f"bench.interface: {exc}") from None
    except (can.CanError, OSError) as exc:  # no such channel, no server, no permission
        where = (f"bench.socketcand: {options.get('host')}:{options.get('port')}"
                 if interface == "socketcand" else f"bench.channel: {interface} {channel!r}")
        raise ConfigError(f"{where}: cannot open ({exc})") from None


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


def remote_node(network: canopen.Network, node_id: int,
                object_dictionary: str | canopen.ObjectDictionary) -> canopen.RemoteNode:
    """A RemoteNode added to `network`, its SDO client waiting `SDO_TIMEOUT_S` per answer."""
    node = canopen.RemoteNode(node_id, object_dictionary)
    node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
    network.add_node(node)
    return node
