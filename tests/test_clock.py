"""Bench clocks over the real stack: lockstep cycle counting, gaps, timeouts (real time:
tests/test_realtime.py)."""

from __future__ import annotations

import gc
import os
import threading
import time

import can
import numpy as np
import pytest

from feedbench.bench import parse_run_config, run_config
from feedbench.daq import clock
from feedbench.daq.clock import BusTimeout, LockstepClock, one_core
from feedbench.protocols.canbus import frozen_heap
from feedbench.daq.recording import open_recording
from feedbench.commands.demo import example_config
from feedbench.protocols.canbus import open_network
from feedbench.drivers.cia402 import Cia402Drive
from feedbench.models.axis import CSV, AxisSimulator
from feedbench.sim_backends.bench import start_simulated_axis
from feedbench.sim_backends.eds import packaged_eds_path
from prerequisites import requires
from test_cia402_sim import NODE_ID, enable, loopback


def wait_for_tpdo_sets(drive: Cia402Drive, count: int, timeout_s: float = 2.0) -> None:
    deadline = time.monotonic() + timeout_s
    while drive.sets_received < count:
        assert time.monotonic() < deadline, f"TPDO sets {drive.sets_received} < {count}"
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
        before, sets = bench.clock.cycle, bench.drive.sets_received
        bench.listener.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
        wait_for_tpdo_sets(bench.drive, sets + 1)  # its TPDOs reached the host
        after_gap = bench.clock.tick()
        later = [bench.clock.tick() for _ in range(5)]
    assert after_gap == before + 2
    assert bench.clock.gaps == 1 and bench.clock.gap_cycles == [before + 2]
    assert later == list(range(before + 3, before + 8))


def test_bus_timeout_when_the_device_is_gone(can_channel):
    with loopback(can_channel) as bench:
        bench.clock.tick()  # at the default timeout: the first SYNC of a process is slower
        bench.clock.timeout_s = 0.1
        bench.device.close()
        with pytest.raises(BusTimeout, match=f"node {NODE_ID}"):
            bench.clock.tick()


class SlowCycles(AxisSimulator):
    """A simulated axis whose physics takes `delays` seconds at its first cycles."""

    def __init__(self, delays: list[float]) -> None:
        super().__init__()
        self.delays = delays

    def step_cycle(self, *args, **kwargs):
        if self.delays:
            time.sleep(self.delays.pop(0))
        return super().step_cycle(*args, **kwargs)


def test_the_first_lockstep_cycle_may_be_slow_the_others_not(can_channel):
    """A peer 0.6 s late at its first cycle (loading what it needs) is waited for, up to
    `clock.FIRST_CYCLE_TIMEOUT_S`; 0.6 s late at a later cycle is a BusTimeout at the
    clock's 0.4 s. (1.5 s late against 1 s until 30 Nov: 2 s of the suite's wall time
    waited.)"""
    device = start_simulated_axis("virtual", can_channel, NODE_ID, SlowCycles([]))
    network = open_network("virtual", can_channel)
    try:
        drive = Cia402Drive(network, NODE_ID, packaged_eds_path())
        drive.configure()
        lockstep = LockstepClock(network, [drive], timeout_s=0.4)
        device.simulator.delays.extend([0.6, 0.0, 0.6])
        lockstep.tick()
        lockstep.tick()
        with pytest.raises(BusTimeout, match=r"no TPDOs 0.4 s after SYNC"):
            lockstep.tick()
    finally:
        network.disconnect()
        device.close()


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


TWO_CPUS = hasattr(os, "sched_getaffinity") and len(os.sched_getaffinity(0)) >= 2
needs_two_cpus = requires(TWO_CPUS, "needs Linux and two allowed CPUs")


@needs_two_cpus
def test_one_core_pins_the_thread_and_the_threads_it_starts_then_restores():
    before = os.sched_getaffinity(0)
    started = {}
    with one_core() as cpu:
        inside = os.sched_getaffinity(0)
        thread = threading.Thread(target=lambda: started.update(cpus=os.sched_getaffinity(0)))
        thread.start()
        thread.join()
    assert cpu in before and inside == started["cpus"] == {cpu}
    assert os.sched_getaffinity(0) == before



@needs_two_cpus
def test_two_benches_at_once_get_a_cpu_each(tmp_path, monkeypatch):
    """Two pinned threads (two simulated benches of a campaign or of two test workers) never
    share a CPU while the other one idles: the second takes the CPU the first does not hold,
    whichever CPU it ran on. (Lock files of its own: the other test worker's benches hold
    the machine's.)"""
    monkeypatch.setattr(clock, "CPU_LOCKS", tmp_path)
    results: dict[str, int | None] = {}
    first_in, release = threading.Event(), threading.Event()

    def hold() -> None:
        with one_core() as cpu:
            results["first"] = cpu
            first_in.set()
            release.wait(10)

    holder = threading.Thread(target=hold)
    holder.start()
    first_in.wait(10)
    with one_core() as second:
        results["second"] = second
    release.set()
    holder.join()
    assert results["first"] != results["second"]
    assert {results["first"], results["second"]} <= os.sched_getaffinity(0)

class _ThreadCpus:
    """Observer: the CPUs allowed to each thread started since `before`, seen mid-run."""

    def __init__(self) -> None:
        self.before = {t.native_id for t in threading.enumerate()}
        self.cpus: list[set[int]] = []

    def on_start(self, plan, channels) -> None: ...

    def on_segment(self, index, segment, cycle) -> None:
        self.cpus += [os.sched_getaffinity(t.native_id) for t in threading.enumerate()
                      if t.native_id not in self.before]

    def on_block(self, cycles, block) -> None: ...

    def on_stop(self, status, reason) -> None: ...


@needs_two_cpus
def test_simulated_run_on_one_core_records_exactly_the_same_samples(tmp_path, can_channel):
    """`bench.one_core` (the default for a simulated lockstep bench): the run's threads
    (bus receive threads, heartbeat, simulated drive) share one CPU during the run, the
    caller gets its CPUs back after it, and the recording equals the one on all CPUs."""
    recordings, observers, cpus_before = {}, {}, os.sched_getaffinity(0)
    for pinned in (True, False):
        raw = example_config("chirp")
        raw["bench"].update(output_dir=str(tmp_path / str(pinned)), channel=can_channel,
                            one_core=pinned)
        raw["experiment"].update(repetitions=1, duration_s=0.5, settle_s=0.2)
        observers[pinned] = _ThreadCpus()
        row = run_config(parse_run_config(raw), [observers[pinned]], progress=False)
        recordings[pinned] = open_recording(row["file"])
    assert os.sched_getaffinity(0) == cpus_before
    pinned_cpus = {frozenset(c) for c in observers[True].cpus}
    assert len(observers[True].cpus) >= 3 and len(pinned_cpus) == 1
    assert len(next(iter(pinned_cpus))) == 1
    assert all(len(c) >= 2 for c in observers[False].cpus)
    pinned, free = recordings[True], recordings[False]
    assert pinned.status == free.status == "complete" and pinned.n_samples == free.n_samples
    for name, values in free.channels.items():
        np.testing.assert_array_equal(pinned.channels[name], values, err_msg=name)


def test_a_frozen_heap_keeps_what_exists_out_of_the_collector_until_the_last_block_exits():
    """A real-time run's cycles (`guarded`) and `feedbench sim` run in `frozen_heap`: a full
    collection walks only what was made inside, not the ≈ 200 000 objects of the imports.
    Blocks of two threads overlap: the first to exit leaves the other's freeze alone. (The
    suite's workers freeze their heap after collecting, `conftest.py`: this test starts
    from a heap that is not frozen, as the worker's tests after a real-time run do.)"""
    gc.unfreeze()
    entered, leave = threading.Event(), threading.Event()

    def other_thread() -> None:
        with frozen_heap():
            entered.set()
            leave.wait(5)

    thread = threading.Thread(target=other_thread)
    thread.start()
    assert entered.wait(5)
    assert gc.get_freeze_count() > 1000  # this process's modules, functions, test objects
    with frozen_heap():
        pass
    assert gc.get_freeze_count() > 1000, "the other thread's block is still open"
    leave.set()
    thread.join(5)
    assert gc.get_freeze_count() == 0
