"""``host:port`` addresses of the TCP links (socketcand, Modbus TCP), parsed once for both
ends: the host that connects to one and `feedbench sim` that listens on one."""

from __future__ import annotations

from feedbench.config import ConfigError

LOOPBACK = "127.0.0.1"
"""Where the simulated bench listens unless told otherwise."""

MAX_PORT = 65535


def split_address(address: str, field: str, listen: bool = False) -> tuple[str, int]:
    """``host:port`` → (host, port); a `ConfigError` naming `field` (the config key) if it
    is not one. To `listen`, the host may be left out (loopback) and so may the port (0:
    any free one)."""
    host, colon, port = address.rpartition(":")
    if not colon:
        host, port = address, ""
    if listen:
        host, port = host or LOOPBACK, port or "0"
    if not host or not port.isdigit():
        raise ConfigError(f"{field}: expected host:port, got {address!r}")
    if int(port) > MAX_PORT:
        raise ConfigError(f"{field}: port {port} of {address!r} is above {MAX_PORT}")
    return host, int(port)
