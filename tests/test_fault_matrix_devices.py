"""The fault matrix, in lockstep in forked processes (issue 18.4, `tests/fault_matrix.py`):
bus-off, the devices' faults (Modbus timeout and exception, serial CRC errors, desync,
unplug), a full disk (the recording's file-size limit) and Ctrl-C (a real SIGINT to the
row's process at SYNC 300), against every experiment family; the other bus faults are
tests/test_fault_matrix.py's.
"""

from __future__ import annotations

import pytest

from fault_matrix import FAMILIES, FAULT, measured_rows, row_test

FAULTS = [FAULT[name] for name in ("bus_off", "modbus_timeout", "modbus_exception", "serial_crc",
                                   "serial_desync", "serial_unplug", "disk_full", "sigint")]
measured = measured_rows(FAULTS)
"""Every row of this file's faults, `fault_matrix.ROW_PROCESSES` at a time."""


@pytest.mark.parametrize("fault", FAULTS, ids=lambda fault: fault.name)
@pytest.mark.parametrize("family", FAMILIES)
def test_fault_row(fault, family, measured):
    row_test(fault, family, measured)
