"""What both ends of the linear-scale link agree on: the reader's Modbus register map.

The reader (a counter interface behind an incremental linear scale, e.g. mounted at the tool
tip) holds the position as a signed 32-bit count of nanometres in holding registers 0–1,
high word first, and a status word in register 2. The host device (`linear_scale`) and the
simulated reader (`linear_scale_peer`) both import it, as feedbench's own devices share
`feedbench.protocols`.
"""

from __future__ import annotations

from feedbench.protocols.modbus_registers import Register, RegisterMap

STATUS_SIGNAL_OK = 0x0001
"""Status bit 0: the scale's signal is within its amplitude limits (the count is valid)."""

SCALE_MAP = RegisterMap("linear scale reader", (
    Register("POSITION", 0, "INT32", 1e-9, "m"),
    Register("STATUS", 2, "UINT16"),
))
