"""The fault matrix, in lockstep in forked processes (issue 18.4): the bus faults the simulated
peers inject (`feedbench.sim_backends.faults`: CAN frame loss and bursts, SYNC and PDO
timeouts, EMCY) against every experiment family, each row a test (`tests/fault_matrix.py`;
bus-off, the devices' faults, a full disk and SIGINT: tests/test_fault_matrix_devices.py;
SIGKILL: tests/test_fault_matrix_host.py), the table of docs/faults.md and the fault
tables' checks.

Each row asserts: the drive leaves operation enabled within 2 cycles of the host's
detection (the simulated drive's own state log, by SYNC count), every cycle before the
fault is in the file, the file opens and says aborted and why, and its line in
docs/faults.md is what was measured. A family without the fault's device is a row "n/a".
"""

from __future__ import annotations

import pytest

from feedbench.config import ConfigError
from feedbench.sim_backends.faults import Faults, parse_fault_options, with_fault_options
from fault_matrix import (DOC, FAMILIES, FAULT, FAULTS, HEADER, applies, measured_rows,
                          row_line, row_test)

BUS = [FAULT[name] for name in ("can_loss", "can_burst", "sync_timeout", "pdo_timeout", "emcy")]
"""This file's faults; bus-off, the devices', a full disk and SIGINT:
test_fault_matrix_devices.py (two files, so that two test workers share the matrix)."""


measured = measured_rows(BUS)
"""Every row of this file's faults, `fault_matrix.ROW_PROCESSES` at a time."""


@pytest.mark.parametrize("fault", BUS, ids=lambda fault: fault.name)
@pytest.mark.parametrize("family", FAMILIES)
def test_fault_row(fault, family, measured):
    row_test(fault, family, measured)


def test_the_table_has_every_row_in_order():
    """docs/faults.md: the header and one row per fault x family, in matrix order, each a
    measured row or "n/a" (the rows' tests check their values)."""
    text = DOC.read_text()
    assert HEADER in text
    table = text.split(HEADER + "\n")[1].splitlines()
    keys = [tuple(cell.strip() for cell in line.split("|")[1:3]) for line in table]
    assert keys == [(fault.name, family) for fault in FAULTS for family in FAMILIES]
    for line in table:
        fault = FAULT[line.split("|")[1].strip()]
        family = line.split("|")[2].strip()
        if not applies(fault, family):
            assert line == row_line(fault, family, None)
        else:
            assert "n/a" not in line and "unknown" not in line


def test_fault_tables_are_checked_and_name_the_field():
    """A bad ``[bench.world.faults]`` key or value, or a fault without its cycle, is one
    ConfigError naming the field; `feedbench sim --fault KEY=VALUE` reads TOML values."""
    for table, field in (({"at_cycle": 5, "can_loss": 0.1}, "bench.world.faults.can_loss"),
                         ({"at_cycle": 5, "can_loss_share": 1.5},
                          "bench.world.faults.can_loss_share"),
                         ({"at_cycle": 5, "modbus": "late"}, "bench.world.faults.modbus"),
                         ({"emcy_code": 0x2310}, "bench.world.faults.at_cycle"),
                         ({"at_cycle": 5, "modbus": "exception", "modbus_exception_code": 9},
                          "bench.world.faults.modbus_exception_code")):
        with pytest.raises(ConfigError, match=f"^{field}: "):
            Faults(table)
    assert parse_fault_options(["at_cycle=300", "serial=crc", "can_loss_share=0.05"]) == {
        "at_cycle": 300, "serial": "crc", "can_loss_share": 0.05}
    with pytest.raises(ConfigError, match="^--fault at_cycle: give KEY=VALUE"):
        parse_fault_options(["at_cycle"])
    bench = {"world": {"faults": {"at_cycle": 300}}}
    assert with_fault_options(bench, ["emcy_code=0x2310"])["world"]["faults"] == {
        "at_cycle": 300, "emcy_code": 0x2310}
    with pytest.raises(ConfigError, match="^--fault.serial: must be one of"):
        with_fault_options(bench, ["serial=cut"])
