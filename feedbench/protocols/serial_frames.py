"""Frame format of the streaming DAQ (docs/serial_daq_protocol.md), shared by both ends.

`A5 5A | type | length | payload | CRC-16/CCITT-FALSE`; a data frame carries a 32-bit
sample counter and the enabled channels as signed 24-bit counts.
"""

from __future__ import annotations

from typing import NamedTuple

SYNC = b"\xa5\x5a"
TYPE_DATA = 0x44  # "D"
TYPE_REPLY = 0x52  # "R"
HEADER_BYTES = 4  # sync (2), type (1), payload length (1)
CRC_BYTES = 2
SEQ_BYTES = 4
SAMPLE_BYTES = 3  # signed 24-bit, little-endian
MAX_REPLY_BYTES = 64
CRC_INIT = 0xFFFF  # CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no xor-out
FULL_SCALE_COUNTS = 2 ** 23
LINK_BYTES_PER_S = 1_000_000
"""Sustained payload budget of the USB 2.0 full-speed CDC link (12 Mbit/s signalling,
bulk ≤ 19 × 64 B per 1 ms frame = 1.216 MB/s); 1.0 MB/s leaves margin for a shared hub."""
MIN_RATE_HZ = 1000
MAX_RATE_HZ = 100_000


class DaqChannel(NamedTuple):
    """One physical input of the instrument: name, SI unit and symmetric full scale."""

    name: str
    unit: str
    full_scale: float

    @property
    def lsb(self) -> float:
        """One count of the 24-bit ADC in SI units."""
        return self.full_scale / FULL_SCALE_COUNTS


CHANNELS: tuple[DaqChannel, ...] = (
    DaqChannel("acc_tool_x", "m/s^2", 500.0),
    DaqChannel("acc_tool_y", "m/s^2", 500.0),
    DaqChannel("acc_tool_z", "m/s^2", 500.0),
    DaqChannel("acc_work_x", "m/s^2", 500.0),
    DaqChannel("acc_work_y", "m/s^2", 500.0),
    DaqChannel("acc_work_z", "m/s^2", 500.0),
    DaqChannel("dyn_fx", "N", 20_000.0),
    DaqChannel("dyn_fy", "N", 20_000.0),
    DaqChannel("dyn_fz", "N", 40_000.0),
    DaqChannel("hammer_force", "N", 5000.0),
    DaqChannel("shaker_force", "N", 1000.0),
    DaqChannel("actuator_force", "N", 1000.0),
)
"""Input i is bit i of the channel mask; frames carry the enabled inputs in ascending i."""
CHANNEL_INDEX = {c.name: i for i, c in enumerate(CHANNELS)}


def data_frame_bytes(n_channels: int) -> int:
    """Length of one data frame on the wire for n enabled channels (bytes)."""
    return HEADER_BYTES + SEQ_BYTES + SAMPLE_BYTES * n_channels + CRC_BYTES


def link_load(n_channels: int, rate_hz: float) -> float:
    """Fraction of the link budget a stream of n channels at rate_hz uses."""
    return data_frame_bytes(n_channels) * rate_hz / LINK_BYTES_PER_S
