"""Bench clocks over the real stack: lockstep cycle counting, gaps, timeouts, real-time pacing."""

from __future__ import annotations

import time

import can
import pytest

from feedbench.daq.clock import BusTimeout, LockstepClock, RealtimeClock
from feedbench.protocols.canbus import open_network
from feedbench.drivers.cia402 import Cia402Drive
from feedbench.models.axis import CSV
from feedbench.sim_backends.bench import start_simulated_axis
from feedbench.sim_backends.eds import packaged_eds_path
from test_cia402_sim import NODE_ID, enable, loopback


def wait_for_device_cycle(drive: Cia402Drive, value: int, timeout_s: float = 2.0) -> None:
    deadline = time.monotonic() + timeout_s
    while drive.device_cycle != value:
        assert time.monotonic() < deadline, f"device cycle {drive.device_cycle} != {value}"
        time.sleep(1e-3)


def test_tick_returns_the_device_counter_unwrapped_across_16_bits(can_channel):
    with loopback(can_channel) as bench:
        bench.device._count = 0xFFFF - 4  # as if the drive had processed 65531 SYNCs
        counters = [bench.clock.tick() for _ in range(10)]
        raw = bench.drive.device_cycle
    assert counters == list(range(0xFFFF - 3, 0xFFFF + 7))
    assert raw == 5  # 65541 mod 65536
    assert bench.clock.gaps == 0 and bench.clock.cycle == counters[-1]


def test_gap_counts_a_sync_the_host_did_not_clock(can_channel):
    with loopback(can_channel) as bench:
        enable(bench, CSV, velocity=0.0)
        before = bench.clock.cycle
        bench.listener.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
        wait_for_device_cycle(bench.drive, before + 1)  # its TPDOs reached the host
        after_gap = bench.clock.tick()
        later = [bench.clock.tick() for _ in range(5)]
    assert after_gap == before + 2
    assert bench.clock.gaps == 1 and bench.clock.gap_cycles == [before + 2]
    assert later == list(range(before + 3, before + 8))


def test_bus_timeout_when_the_device_is_gone(can_channel):
    with loopback(can_channel) as bench:
        bench.clock.timeout_s = 0.1
        bench.clock.tick()
        bench.device.close()
        with pytest.raises(BusTimeout, match=f"node {NODE_ID}"):
            bench.clock.tick()


def test_lockstep_clock_drives_two_axes(can_channel):
    devices = [start_simulated_axis("virtual", can_channel, node) for node in (1, 2)]
    network = open_network("virtual", can_channel)
    try:
        drives = [Cia402Drive(network, node, packaged_eds_path()) for node in (1, 2)]
        for drive in drives:
            drive.configure()
            drive.set_mode(CSV)
            drive.set_targets(velocity=0.0)
        clock = LockstepClock(network, drives, timeout_s=2.0)
        for _ in range(4):
            for drive in drives:
                drive.enable_step()
            clock.tick()
        drives[1].set_targets(velocity=0.005)
        for _ in range(200):
            clock.tick()
    finally:
        network.disconnect()
        for device in devices:
            device.close()
    assert clock.cycles == [204, 204] and clock.gaps == 0
    assert drives[0].actual.velocity == 0.0
    assert drives[1].actual.velocity == pytest.approx(0.005, rel=0.01)


def test_realtime_clock_paces_sync_and_records_lateness(can_channel):
    period = 2e-3
    with loopback(can_channel) as bench:
        clock = RealtimeClock(bench.drive.network, [bench.drive], period_s=period)
        start = time.perf_counter()
        for _ in range(50):
            clock.tick()
        elapsed = time.perf_counter() - start
        deadline = time.monotonic() + 2.0
        while bench.device.values[0x2020] < 50 and time.monotonic() < deadline:
            time.sleep(1e-3)  # a late last cycle may still be in the device's queue
        device_cycles = bench.device.values[0x2020]
    stats = clock.jitter_stats()
    assert elapsed >= 49 * period  # SYNC slots are never early
    assert device_cycles == 50  # one SYNC per tick
    assert stats["n"] == 50 and 0.0 <= stats["mean_us"] <= stats["max_us"]
    assert stats["std_us"] >= 0.0
    assert 0 < clock.cycle <= 50


def test_realtime_clock_times_out_without_answers(can_channel):
    with loopback(can_channel) as bench:
        clock = RealtimeClock(bench.drive.network, [bench.drive], period_s=2e-3, timeout_s=0.05)
        clock.tick()
        bench.device.close()
        with pytest.raises(BusTimeout, match="no complete TPDO set"):
            for _ in range(200):
                clock.tick()
    assert clock.missed >= 1
