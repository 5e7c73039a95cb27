"""The fault matrix, in lockstep in this process (issue 18.4, `tests/fault_matrix.py`):
bus-off, the devices' faults (Modbus timeout and exception, serial CRC errors, desync,
unplug), a full disk (the recording's file-size limit) and Ctrl-C (a real SIGINT to this
process at SYNC 300), against every experiment family; the other bus faults are
tests/test_fault_matrix.py's.
"""

from __future__ import annotations

import pytest

from fault_matrix import FAMILIES, FAULT, row_test

FAULTS = [FAULT[name] for name in ("bus_off", "modbus_timeout", "modbus_exception", "serial_crc",
                                   "serial_desync", "serial_unplug", "disk_full", "sigint")]


@pytest.mark.parametrize("fault", FAULTS, ids=lambda fault: fault.name)
@pytest.mark.parametrize("family", FAMILIES)
def test_fault_row(fault, family, tmp_path, can_channel):
    row_test(fault, family, tmp_path, can_channel)
