"""The simulated CiA 402 drive over the real stack (python-can `virtual`, canopen both sides).

Ground truth: the drive's physics must be exactly the `AxisSimulator` driven directly with
the same (1 nm / 1 mN quantised) setpoints, so bus positions are compared with a direct
`simulate` run to one increment (1 nm, 1 nm/s, 1 mN). A third bus on the channel records
every frame; protocol facts are asserted on those frames.
"""

from __future__ import annotations

import struct
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator

import can
import numpy as np
import pytest
from canopen.profiles.p402 import BaseNode402
from canopen.sdo import SdoAbortedError

from feedbench.daq.clock import LockstepClock
from feedbench.protocols.canbus import open_network
from feedbench.protocols.cia301 import HOST_NODE_ID
from feedbench.drivers.cia402 import Cia402Drive, PdoConfig
from feedbench.models.axis import CSP, CST, CSV, AxisSimulator, ServoTiming
from feedbench.sim_backends import eds
from feedbench.sim_backends.bench import start_simulated_axis
from feedbench.sim_backends.cia402_drive import SimulatedCia402Drive

NODE_ID = 3
TIMEOUT_S = 2.0


@dataclass
class Loopback:
    """Simulated drive, host driver and clock on one virtual channel, plus a listener bus."""

    device: SimulatedCia402Drive
    drive: Cia402Drive
    clock: LockstepClock
    listener: can.BusABC

    def frames(self) -> list[tuple[int, bytes]]:
        """Every frame on the bus since the last call: (COB-ID, payload)."""
        out = []
        while (msg := self.listener.recv(0)) is not None:
            out.append((msg.arbitration_id, bytes(msg.data)))
        return out

    def run(self, cycles: int, **targets: float) -> list:
        """`cycles` ticks with these setpoints (SI); the `actual` after each."""
        out = []
        for _ in range(cycles):
            self.drive.set_targets(**targets)
            self.clock.tick()
            out.append(self.drive.actual)
        return out


@contextmanager
def loopback(channel: str, simulator: AxisSimulator | None = None,
             pdo_config: PdoConfig | None = None, configure: bool = True) -> Iterator[Loopback]:
    """Listener first (it sees the boot-up), then the simulated drive, then the host."""
    listener = can.Bus(interface="virtual", channel=channel)
    device = start_simulated_axis("virtual", channel, NODE_ID, simulator or AxisSimulator())
    network = open_network("virtual", channel)
    try:
        drive = Cia402Drive(network, NODE_ID, eds.packaged_eds_path(), pdo_config)
        if configure:
            drive.configure()
        yield Loopback(device, drive, LockstepClock(network, [drive], TIMEOUT_S), listener)
    finally:
        network.disconnect()
        device.close()
        listener.shutdown()


def enable(bench: Loopback, mode: int, **hold: float) -> None:
    """Mode and holding setpoints, then the controlword sequence to operation enabled."""
    bench.drive.set_mode(mode)
    bench.drive.set_targets(**hold)
    bench.drive.enable(bench.clock.tick)


def reference(mode: int, simulator: AxisSimulator, **columns: np.ndarray) -> dict:
    """The same physics driven directly, with the setpoints quantised as on the bus."""
    quantum = {"target_position": 1e-9, "target_velocity": 1e-9, "velocity_offset": 1e-9,
               "force_offset": 1e-3, "target_force": 1.0}
    quantised = {k: np.round(np.asarray(v) / quantum[k]) * quantum[k] for k, v in columns.items()}
    n = max(np.size(v) for v in quantised.values())
    args = {k: np.broadcast_to(quantised.get(k, 0.0), n) for k in quantum}
    return simulator.simulate(mode, **args)


# -- object dictionary ------------------------------------------------------------------


def test_packaged_eds_is_the_exported_dictionary(tmp_path):
    fresh = tmp_path / "cia402.eds"
    eds.export(fresh)
    assert fresh.read_bytes() == eds.packaged_eds_path().read_bytes()
    od = eds.load(5)
    assert od[0x1800][1].default == 0x185  # $NODEID+0x180 resolved for node 5
    assert od[0x1403][1].default == 0x80000505  # RPDO4 off by default
    tpdo1 = [od[0x1A00][sub].default for sub in range(1, od[0x1A00][0].default + 1)]
    assert tpdo1 == [0x60410010, 0x60640020, 0x20200010]
    assert od[0x6502].default == 0x0384  # PV, CSP, CSV, CST
    assert (od[0x2001].data_type, od[0x2001].unit) == (eds.F32, "N*s/m")


# -- NMT, SDO, heartbeat, PDO traffic ---------------------------------------------------


def test_boot_configure_and_cycle_traffic(can_channel):
    with loopback(can_channel, configure=False) as bench:
        boot = bench.frames()
        assert (0x700 + NODE_ID, b"\x00") in boot  # boot-up message
        bench.drive.configure()
        configure = bench.frames()
        ids = [cob for cob, _ in configure]
        assert ids[0] == 0x000 and configure[0][1] == bytes([0x80, NODE_ID])  # NMT pre-op
        assert (0x700 + NODE_ID, b"\x7f") in configure  # heartbeat, pre-operational
        assert ids.count(0x600 + NODE_ID) == ids.count(0x580 + NODE_ID) > 20  # SDO
        assert configure[-1] == (0x000, bytes([0x01, NODE_ID]))  # NMT start
        enable(bench, CSV, velocity=0.0)
        bench.run(20, velocity=0.005)
        frames = bench.frames()
        assert frames[0] == (0x700 + HOST_NODE_ID, b"\x05")  # the host's heartbeat, tick 0
        cycle = [cob for cob, _ in frames if cob not in (0x700 + NODE_ID, 0x700 + HOST_NODE_ID)]
        assert cycle.count(0x080) == 23  # 3 enable ticks + 20
        for cob in (0x200, 0x300, 0x400, 0x180, 0x280):
            assert cycle.count(cob + NODE_ID) == 23
        assert cycle[:6] == [0x200 + NODE_ID, 0x300 + NODE_ID, 0x400 + NODE_ID, 0x080,
                             0x180 + NODE_ID, 0x280 + NODE_ID]


def test_tpdo_payload_carries_cycle_counter_and_units(can_channel):
    with loopback(can_channel) as bench:
        enable(bench, CSV, velocity=0.0)
        actual = bench.run(100, velocity=0.004)[-1]
        tpdo1 = [data for cob, data in bench.frames() if cob == 0x180 + NODE_ID]
        statusword, position_nm, counter = struct.unpack("<HiH", tpdo1[-1])
        assert counter == 103 == actual.cycle
        assert position_nm == round(bench.device.simulator.position * 1e9)
        assert actual.position == pytest.approx(position_nm * 1e-9, abs=1e-15)
        assert statusword & 0x6F == 0x27 and statusword & 0x0200  # enabled, remote


# -- CiA 402 state machine --------------------------------------------------------------


def test_switched_on_drive_ignores_targets(can_channel):
    with loopback(can_channel) as bench:
        bench.drive.set_mode(CSV)
        for _ in range(2):  # 0x06 then 0x07: switched on, not enabled
            bench.drive.enable_step()
            bench.clock.tick()
        assert bench.drive.state == "SWITCHED ON"
        actuals = bench.run(50, velocity=0.01, force_offset=200.0)
        assert bench.drive.state == "SWITCHED ON"
        assert all(a.force == 0.0 and a.velocity == 0.0 and a.position == 0.0 for a in actuals)
        assert bench.device.simulator.enabled is False


def test_quick_stop_ramps_down_then_switches_off(can_channel):
    with loopback(can_channel) as bench:
        enable(bench, CSV, velocity=0.0)
        bench.run(300, velocity=0.01)
        bench.drive.quick_stop()
        states, speeds = [], []
        while bench.drive.state != "SWITCH ON DISABLED" and len(states) < 100:
            bench.clock.tick()
            states.append(bench.drive.state)
            speeds.append(bench.drive.actual.velocity)
        ramp_cycles = 0.01 / 2.0 / 1e-3  # v / 0x6085 (2 m/s²) / cycle
        assert states[0] == "QUICK STOP ACTIVE"
        assert ramp_cycles <= states.count("QUICK STOP ACTIVE") <= ramp_cycles + 15
        assert abs(speeds[-1]) < 10e-6  # below the velocity window 0x606D when switched off
        assert bench.run(5, velocity=0.01)[-1].force == 0.0  # de-energised


def test_following_error_fault_emcy_and_reset(can_channel):
    with loopback(can_channel) as bench:
        codes = []
        bench.drive.on_emcy(lambda error: codes.append(error.code))
        bench.drive.node.sdo[0x6065].raw = 100_000  # following error window 100 µm
        enable(bench, CSP, position=0.0)
        bench.run(5, position=0.0)
        bench.frames()
        bench.run(1, position=1e-3)  # a 1 mm jump: error ≫ window
        emcy = [data for cob, data in bench.frames() if cob == 0x080 + NODE_ID]
        assert emcy == [struct.pack("<HB5s", 0x8611, 0x01, b"")]
        assert codes == [0x8611] and bench.drive.emcy_code == 0x8611
        assert bench.drive.fault and bench.drive.state == "FAULT"
        assert bench.drive.statusword & 0x2000  # following error bit
        assert bench.drive.node.sdo[0x603F].raw == 0x8611
        assert bench.drive.node.sdo[0x1001].raw == 0x01
        assert bench.run(3, position=1e-3)[-1].force == 0.0
        bench.drive.set_targets(position=bench.drive.actual.position)
        bench.frames()
        bench.drive.enable(bench.clock.tick)
        controlwords = [data[0] for cob, data in bench.frames() if cob == 0x200 + NODE_ID]
        assert controlwords[:4] == [0x80, 0x06, 0x07, 0x0F]  # rising edge of bit 7 first
        assert codes == [0x8611, 0x0000] and bench.drive.emcy_code == 0  # EMCY error reset
        assert not bench.drive.fault and bench.drive.node.sdo[0x603F].raw == 0


def test_injected_fault_via_0x2030(can_channel):
    with loopback(can_channel) as bench:
        enable(bench, CSV, velocity=0.0)
        bench.drive.node.sdo[0x2030].raw = 0x5530
        bench.run(1, velocity=0.0)
        assert bench.drive.emcy_code == 0x5530 and bench.drive.state == "FAULT"
        enable(bench, CSV, velocity=0.0)  # fault reset, enabled again
        bench.run(2, velocity=0.0)
        assert bench.drive.state == "OPERATION ENABLED"  # one-shot
        with pytest.raises(SdoAbortedError) as info:
            bench.drive.node.sdo[0x2030].raw  # a command: write-only
        assert info.value.code == 0x06010001


# -- physics through the bus equals the physics driven directly ----------------------------


def test_csv_velocity_converges_and_matches_direct_simulation(can_channel):
    with loopback(can_channel) as bench:
        enable(bench, CSV, velocity=0.0)
        velocity = np.full(500, 0.01)
        actuals = bench.run(500, velocity=0.01)
    truth = reference(CSV, AxisSimulator(), target_velocity=np.r_[0.0, velocity])
    bus_velocity = np.array([a.velocity for a in actuals])
    np.testing.assert_allclose(bus_velocity, np.round(truth["mean_velocity"][1:] * 1e9) * 1e-9,
                               rtol=0, atol=1.01e-9)
    assert abs(bus_velocity[-1] - 0.01) < 0.005 * 0.01


def test_csp_ramp_followed_as_direct_simulation(can_channel):
    ramp = 0.02 * 1e-3 * np.arange(1, 501)  # 20 mm/s
    with loopback(can_channel) as bench:
        enable(bench, CSP, position=0.0)
        positions = np.array([bench.run(1, position=x)[0].position for x in ramp])
    truth = reference(CSP, AxisSimulator(), target_position=np.r_[0.0, ramp])
    np.testing.assert_allclose(positions, np.round(truth["position"][1:] * 1e9) * 1e-9,
                               rtol=0, atol=1.01e-9)
    assert abs(ramp[-1] - positions[-1]) < 0.01 * ramp[-1]  # followed: within 1 % of travel


def test_cst_force_offset_appears_after_the_drive_delay(can_channel):
    timing = ServoTiming(delay=2.5e-3)  # 2.5 bus cycles
    with loopback(can_channel, AxisSimulator(timing=timing)) as bench:
        enable(bench, CST, force=0.0, force_offset=0.0)
        before = bench.run(3, force_offset=0.0)
        after = bench.run(6, force_offset=100.0)
    forces = [a.force for a in before + after]
    # the step starts with cycle 3; 2.5 ms later is half-way through cycle 5, whose
    # reported force (the cycle mean) is therefore half the step
    assert forces[:5] == [0.0] * 5
    assert forces[5:] == [50.0] + [100.0] * 3
    truth = reference(CST, AxisSimulator(timing=timing),
                      force_offset=np.r_[np.zeros(4), np.full(6, 100.0)])
    np.testing.assert_allclose(forces, truth["mean_force"][1:], rtol=0, atol=1e-3)


def test_sdo_gains_change_the_closed_loop(can_channel):
    slow = AxisSimulator().gains
    with loopback(can_channel) as bench:
        assert bench.drive.read_gains() == pytest.approx((slow.K_p, slow.T_i, slow.K_v), rel=1e-7)
        bench.drive.write_gains(K_p=3.0 * slow.K_p)
        read = bench.drive.read_gains()
        assert read.K_p == pytest.approx(3.0 * slow.K_p, rel=1e-7)
        assert (read.T_i, read.K_v) == pytest.approx((slow.T_i, slow.K_v), rel=1e-7)
        with pytest.raises(SdoAbortedError):
            bench.drive.write_gains(T_i=0.0)
        enable(bench, CSV, velocity=0.0)
        bus = np.array([a.velocity for a in bench.run(40, velocity=0.01)])
    stiff = AxisSimulator()
    stiff.set_gains(type(slow)(float(np.float32(3.0 * slow.K_p)), slow.T_i, slow.K_v))
    command = np.r_[0.0, np.full(40, 0.01)]
    with_new = reference(CSV, stiff, target_velocity=command)["mean_velocity"][1:]
    with_old = reference(CSV, AxisSimulator(), target_velocity=command)["mean_velocity"][1:]
    np.testing.assert_allclose(bus, np.round(with_new * 1e9) * 1e-9, rtol=0, atol=1.01e-9)
    assert np.max(np.abs(bus - with_old)) > 1e-3  # 3 × K_p: visibly faster response


# -- PDO mapping checks on the device ----------------------------------------------------


def test_device_refuses_unmappable_and_oversized_pdo_maps(can_channel):
    with loopback(can_channel) as bench:
        sdo = bench.drive.node.sdo
        for pdo in (0x1801, 0x1401):  # CiA 301: PDO not valid, then no entries, then map
            sdo[pdo][1].raw |= 0x80000000
            sdo[pdo + 0x200][0].raw = 0
        with pytest.raises(SdoAbortedError) as info:
            sdo[0x1A01][1].raw = 0x60650020  # following error window: not PDO-mappable
        assert info.value.code == 0x06040041
        with pytest.raises(SdoAbortedError) as info:
            sdo[0x1601][1].raw = 0x60410010  # statusword is read-only: not in an RPDO
        assert info.value.code == 0x06040041
        for sub, entry in enumerate((0x607A0020, 0x60FF0020, 0x60B10020), start=1):
            sdo[0x1603][sub].raw = entry
        with pytest.raises(SdoAbortedError) as info:
            sdo[0x1603][0].raw = 3  # 96 bits > 64
        assert info.value.code == 0x06040042


# -- interoperability: canopen's own CiA 402 master ---------------------------------------


def test_canopen_basenode402_enables_the_simulated_drive(can_channel):
    """canopen's p402 master (wall clock, periodic SYNC and RPDO threads) reaches operation
    enabled on the simulated drive and reads its statusword and mode through the TPDOs."""
    with loopback(can_channel, configure=False) as bench:
        network = bench.drive.network
        del network[NODE_ID]  # canopen's master instead of ours
        node = BaseNode402(NODE_ID, str(eds.packaged_eds_path()))
        # canopen's defaults (0.2-0.8 s) assume a dedicated host; CI shares two cores
        node.TIMEOUT_SWITCH_STATE_FINAL = node.TIMEOUT_SWITCH_STATE_SINGLE = 5.0
        node.TIMEOUT_CHECK_TPDO = 5.0
        network.add_node(node)
        node.nmt.state = "PRE-OPERATIONAL"
        node.tpdo.read()
        node.rpdo.read()
        node.tpdo[1].clear()
        for index in (0x6041, 0x6061):
            node.tpdo[1].add_variable(index)
        node.tpdo[1].save()
        node.setup_402_state_machine(read_pdos=False)
        node.nmt.state = "OPERATIONAL"
        node.rpdo[1]["Modes of operation"].raw = CSV
        network.sync.start(2e-3)
        node.rpdo[1].start(2e-3)
        try:
            node.state = "OPERATION ENABLED"
            node.check_statusword()
            enabled = node.statusword
            node.state = "SWITCH ON DISABLED"
            node.check_statusword()
            disabled = node.statusword
        finally:
            node.rpdo[1].stop()
            network.sync.stop()
    assert enabled & 0x6F == 0x27 and node.tpdo_values[0x6061] == CSV
    assert disabled & 0x4F == 0x40
