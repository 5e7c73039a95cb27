"""The host CiA 402 driver against the simulated drive over the real stack.

Asserted on the frames a third bus records (controlword order, payload units, PDO
lengths) and on the drive's own objects read back by SDO.
"""

from __future__ import annotations

import struct
import subprocess
import sys

import numpy as np
import pytest

from feedbench.bench import Bench, bench_schema, sync_loss_cycles
from feedbench.config import ConfigError, validate_table
from feedbench.drivers.cia402 import DriveError, PdoConfig, decode_state
from feedbench.models.axis import CSP, CST, CSV
from test_cia402_sim import NODE_ID, enable, loopback

RPDO1, TPDO1, TPDO2 = 0x200 + NODE_ID, 0x180 + NODE_ID, 0x280 + NODE_ID


def test_enable_reaches_operation_enabled_only_through_the_controlwords(can_channel):
    with loopback(can_channel) as bench:
        bench.drive.set_mode(CSP)
        bench.drive.set_targets(position=0.0)
        bench.frames()
        bench.drive.enable(bench.clock.tick)
        frames = bench.frames()
    controlwords = [(i, struct.unpack_from("<H", d)[0]) for i, (c, d) in enumerate(frames)
                    if c == RPDO1]
    states = [(i, decode_state(struct.unpack_from("<H", d)[0])) for i, (c, d) in enumerate(frames)
              if c == TPDO1]
    assert [cw for _, cw in controlwords] == [0x06, 0x07, 0x0F]
    assert [s for _, s in states] == ["READY TO SWITCH ON", "SWITCHED ON", "OPERATION ENABLED"]
    assert bench.drive.is_enabled
    first_enabled = states[-1][0]
    assert controlwords[-1][0] < first_enabled  # 0x0F was on the bus before the statusword


def test_disable_quick_stops_then_de_energises(can_channel):
    with loopback(can_channel) as bench:
        enable(bench, CSV, velocity=0.0)
        bench.run(200, velocity=0.01)
        bench.drive.set_targets(velocity=0.01)
        bench.frames()
        bench.drive.disable(bench.clock.tick)
        controlwords = [struct.unpack_from("<H", d)[0] for c, d in bench.frames() if c == RPDO1]
        assert bench.drive.state == "SWITCH ON DISABLED"
        # quick stop until the stop is complete (bit 10), then disable voltage, never back
        assert controlwords[0] == 0x02 and set(controlwords) <= {0x02, 0x00}
        assert controlwords == sorted(controlwords, reverse=True)
        assert abs(bench.drive.actual.velocity) < 10e-6
        assert bench.drive.disable_step() is True
        bench.clock.tick()
        assert bench.drive.actual.force == 0.0


def test_setpoints_go_out_in_bus_units(can_channel):
    with loopback(can_channel) as bench:
        bench.drive.set_mode(CSP)
        bench.drive.set_targets(position=0.0123456789, velocity=-0.001, velocity_offset=2.5e-6,
                                force=12.4, force_offset=1.2345)
        bench.drive.transmit()
        bench.clock.tick()
        frames = dict(bench.frames())
        assert struct.unpack("<Hib", frames[RPDO1]) == (0x00, 12_345_679, CSP)
        assert struct.unpack("<ii", frames[0x300 + NODE_ID]) == (-1_000_000, 2_500)
        assert struct.unpack("<ihh", frames[0x400 + NODE_ID]) == (1_234, 0, 12)  # mN, ‰, ‰
        sdo = bench.drive.node.sdo
        assert (sdo[0x607A].raw, sdo[0x6061].raw, sdo[0x2011].raw) == (12_345_679, CSP, 1_234)


def test_set_mode_refuses_modes_the_drive_does_not_support(can_channel):
    with loopback(can_channel) as bench:
        with pytest.raises(ValueError, match="0x6502 = 0x0384"):
            bench.drive.set_mode(1)  # profile position
        bench.drive.set_mode(CST)
        bench.clock.tick()
        assert bench.drive.node.sdo[0x6061].raw == CST


def test_tpdo_remapped_to_torque_actual(can_channel):
    config = PdoConfig(tpdo={1: (0x6041, 0x6064, 0x2020), 2: (0x606C, 0x6077)})
    with loopback(can_channel, pdo_config=config, configure=False) as bench:
        bench.drive.node.sdo[0x6076].raw = 500_000  # rated force 500 N: 1 ‰ = 0.5 N
        bench.drive.configure()
        assert bench.device.node.sdo[0x1A01][2].raw == 0x60770010
        enable(bench, CSV, velocity=0.0)
        forces = [a.force for a in bench.run(300, velocity=0.01)]
        fine_mN = bench.drive.node.sdo[0x2010].raw  # force of the last cycle, by SDO
        lengths = {len(d) for c, d in bench.frames() if c == TPDO2}
    assert lengths == {6}  # INTEGER32 + INTEGER16
    assert forces[-1] == pytest.approx(fine_mN * 1e-3, abs=0.25)  # ½ ‰ of 500 N
    assert forces[-1] / 0.5 == pytest.approx(round(forces[-1] / 0.5), abs=1e-9)  # ‰ steps
    assert 30.0 < forces[-1] < 90.0  # sliding friction at 10 mm/s (Fig. 5.11 levels)


def test_force_offset_falls_back_to_torque_offset_without_0x2011(can_channel):
    config = PdoConfig(rpdo={1: (0x6040, 0x607A, 0x6060), 2: (0x60FF, 0x60B1),
                             3: (0x60B2, 0x6071)})
    with loopback(can_channel, pdo_config=config) as bench:
        enable(bench, CST, force=0.0, force_offset=0.0)
        actual = bench.run(3, force_offset=42.4)[-1]
        payload = dict(bench.frames())[0x400 + NODE_ID]
    assert struct.unpack("<hh", payload) == (42, 0)  # 1 ‰ of 1000 N = 1 N steps
    assert actual.force == 42.0


def test_configure_fails_without_heartbeat(can_channel):
    with loopback(can_channel, configure=False) as bench:
        with pytest.raises(DriveError, match="no heartbeat"):
            bench.drive.configure(heartbeat_ms=0, timeout_s=0.2)


def test_unmapped_objects_are_errors_or_nan(can_channel):
    config = PdoConfig(rpdo={1: (0x6040, 0x607A, 0x6060)}, tpdo={1: (0x6041, 0x6064, 0x2020)})
    with loopback(can_channel, pdo_config=config) as bench:
        with pytest.raises(DriveError, match="0x60FF"):
            bench.drive.set_targets(velocity=0.01)
        with pytest.raises(DriveError, match="0x607A: 3000000000 is out of"):
            bench.drive.set_targets(position=3.0)  # beyond INTEGER32 nm (±2.147 m)
        enable(bench, CSP, position=0.0)
        actual = bench.run(2, position=1e-6)[-1]
    assert actual.cycle == 5 and actual.position > 0.0
    assert np.isnan(actual.velocity) and np.isnan(actual.force)


def test_drivers_do_not_import_the_simulation():
    code = ("import sys, feedbench.drivers.cia402, feedbench.protocols.canbus, feedbench.daq.clock;"
            "print(sorted(m for m in sys.modules if m.startswith(('feedbench.sim_backends',"
            "'feedbench.models'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_the_driver_tells_the_drive_its_bus_cycle_and_a_drive_on_another_cycle_refuses(
        can_channel):
    """0x1006 (µs): the period the drive counts missed SYNCs in. The simulated axis runs
    1 ms; a host on 2 ms is stopped before anything moves, naming bench.cycle_ms."""
    with loopback(can_channel, configure=False) as bench:
        bench.drive.configure(cycle_s=1e-3)
        assert bench.drive.node.sdo[0x1006].raw == 1000
        with pytest.raises(ConfigError, match=rf"bench.cycle_ms: drive node {NODE_ID} refuses a bus "
                                              r"cycle of 2 ms: it runs 1 ms"):
            bench.drive.configure(cycle_s=2e-3)
        assert bench.device.values[0x1006] == 1000


@pytest.mark.parametrize("sync_loss_ms, cycle_ms, clock, cycles", [
    (10.0, 1.0, "realtime", 10), (2.5, 1.0, "realtime", 3), (50.0, 2.0, "realtime", 25),
    (10.0, 1.0, "lockstep", 0)])
def test_the_sync_loss_limit_is_bench_sync_loss_ms_in_whole_cycles(sync_loss_ms, cycle_ms,
                                                                    clock, cycles):
    cfg = validate_table({"sync_loss_ms": sync_loss_ms, "cycle_ms": cycle_ms, "clock": clock},
                         bench_schema(), "bench")
    assert sync_loss_cycles(cfg) == cycles


def test_a_sync_loss_limit_no_drive_can_hold_is_an_error_naming_the_field():
    cfg = validate_table({"sync_loss_ms": 300.0, "clock": "realtime"}, bench_schema(), "bench")
    with pytest.raises(ConfigError, match=r"^bench.sync_loss_ms: 300 ms is 300 bus cycles of "
                                          r"1 ms; a drive counts at most 255 \(0x2021\)$"):
        Bench(cfg).__enter__()
