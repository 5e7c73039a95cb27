"""CANopen (CiA 301) objects and COB-IDs every node of the bench shares: the drives (CiA 402,
`protocols.cia402`) and the exciters' I/O module (CiA 401, `protocols.cia401`), host side
and simulated side alike."""

from __future__ import annotations

NMT_COB_ID = 0x000
SYNC_COB_ID = 0x080
NMT_RESET_NODE = 0x81
"""NMT command: reset node (application and communication); 0x82 resets communication."""
HEARTBEAT_COB_BASE = 0x700
"""COB-ID of a node's heartbeat (and boot-up) without the node id."""
HEARTBEAT_OPERATIONAL = 0x05
"""Heartbeat payload: the producer's NMT state, operational."""
HOST_NODE_ID = 0x7F
"""Node id of the host's heartbeat (the bench's NMT master; no drive may take it)."""

DEVICE_TYPE = 0x1000
"""Object: profile number in the low 16 bits, additional information above."""
ERROR_REGISTER = 0x1001
ERROR_REGISTER_GENERIC = 0x01
"""Error register bit 0: generic error (set with every EMCY the drive sends)."""
CYCLE_PERIOD = 0x1006
"""µs: one SYNC advances the simulated axis by this time."""
CONSUMER_HEARTBEAT_TIME = 0x1016
"""Array: sub n (1…`CONSUMER_ENTRIES`) = producer node id << 16 | consumer time in ms
(`consumer_entry`); 0 or a time of 0: the entry is unused."""
CONSUMER_ENTRIES = 4
"""Consumer entries each simulated node offers."""
HEARTBEAT_TIME = 0x1017
"""ms; 0: no heartbeat."""
IDENTITY = 0x1018
MANUFACTURER_FIRST = 0x2000
"""First index of the manufacturer-specific objects."""
SYNC_LOSS_LIMIT = 0x2021
"""Manufacturer object of every simulated node: SYNCs missed in a row (each `CYCLE_PERIOD`
long on the wall clock) after which the node reacts as to a lost heartbeat; 0: off."""
PROFILE_FIRST = 0x6000
"""First index of the device-profile objects."""

RPDO_COMMUNICATION, RPDO_MAPPING = 0x1400, 0x1600
TPDO_COMMUNICATION, TPDO_MAPPING = 0x1800, 0x1A00
"""First PDO parameter record of each kind (PDO n at + n − 1)."""
PDO_RECORDS_END = 0x1C00
"""First index past the TPDO mapping records."""
PDO_COB_ID, PDO_TRANSMISSION_TYPE, PDO_INHIBIT_TIME, PDO_EVENT_TIMER = 1, 2, 3, 5
"""Sub-indices of a PDO communication record; a mapping record's sub 0 counts its
entries, subs 1–8 are the entries."""
RPDO_COB_BASE, TPDO_COB_BASE = 0x200, 0x180
"""COB-ID of PDO 1 without the node id (predefined connection set; PDO n: + 0x100 (n − 1))."""
TRANSMISSION_SYNC = 1
"""PDO transmission type: every SYNC."""

SDO_ABORT_GENERAL = 0x08000000
"""SDO abort code: general error."""
SDO_ABORT_COMMAND_SPECIFIER = 0x05040001
"""SDO abort code: the command specifier is not valid or unknown (a block transfer, which
the simulated nodes do not offer; a segment outside a transfer)."""
SDO_ABORT_UNSUPPORTED_ACCESS = 0x06010000
"""SDO abort code: unsupported access (a PDO mapping written while the PDO is valid or its
sub-index 0 is not 0)."""
SDO_ABORT_NO_OBJECT = 0x06020000
"""SDO abort code: the object does not exist in the object dictionary."""
SDO_ABORT_NOT_MAPPABLE = 0x06040041
"""SDO abort code: the object cannot be mapped to the PDO."""
SDO_ABORT_PDO_LENGTH = 0x06040042
"""SDO abort code: the mapped objects exceed the PDO length (64 bits)."""
SDO_ABORT_NO_SUBINDEX = 0x06090011
"""SDO abort code: the sub-index does not exist (e.g. any sub-index ≠ 0 of a plain VAR)."""
SDO_ABORT_VALUE_RANGE = 0x06090030
"""SDO abort code: the value is out of the parameter's range (not one it accepts)."""
SDO_ABORT_VALUE_TOO_HIGH, SDO_ABORT_VALUE_TOO_LOW = 0x06090031, 0x06090032
"""SDO abort codes: the value is above the object's HighLimit / below its LowLimit."""
SDO_ABORT_LENGTH_TOO_HIGH, SDO_ABORT_LENGTH_TOO_LOW = 0x06070012, 0x06070013
"""SDO abort codes: more / fewer data bytes than the object's data type has."""

EMCY_COMMUNICATION = 0x8100
"""EMCY code: communication error, here the loss of SYNC (`SYNC_LOSS_LIMIT`)."""
EMCY_HEARTBEAT = 0x8130
"""EMCY code: life guard or heartbeat error (a consumed heartbeat lost)."""


def consumer_entry(node_id: int, time_ms: int) -> int:
    """A 0x1016 entry: watch `node_id`'s heartbeat, lost after `time_ms` ms without one."""
    return (node_id & 0x7F) << 16 | (time_ms & 0xFFFF)


def consumer_of(entry: int) -> tuple[int, int]:
    """(producer node id, consumer time in ms) of a 0x1016 entry."""
    return entry >> 16 & 0x7F, entry & 0xFFFF
