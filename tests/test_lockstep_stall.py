"""A simulated (lockstep) run survives the machine not running its process for a while: a
loaded machine or a paused process is not a silent peer (`clock.wait_awake`). The pause is
real: a child process stops this one (SIGSTOP) mid-run and continues it (SIGCONT) later,
so the host, its simulated drive and every thread stand still alike."""

from __future__ import annotations

import multiprocessing
import os
import subprocess
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from feedbench.daq.clock import LockstepClock, wait_awake
from feedbench.drivers.cia402 import Cia402Drive
from feedbench.models.axis import AxisSimulator
from feedbench.protocols.canbus import open_network
from feedbench.sim_backends.bench import start_simulated_axis
from feedbench.sim_backends.eds import packaged_eds_path
from test_cia402_sim import NODE_ID

PAUSE_S = 1.5
"""How long the process is stopped: longer than the bench's 1 s TPDO timeout."""
AFTER_S = 0.2
"""How long the paused cycle still takes once the process runs again (s)."""


class PausedMidCycle(AxisSimulator):
    """A simulated axis that, at its `at`-th cycle, has a child process stop this whole
    process for `PAUSE_S` while it computes (the host then waits for this cycle's TPDOs),
    then continue it; the cycle ends `AFTER_S` after that, so the host's wait has expired
    by the wall clock when the process runs again."""

    def __init__(self, at: int) -> None:
        super().__init__()
        self.at = at
        self.calls = 0
        self.child: subprocess.Popen | None = None

    def step_cycle(self, *args, **kwargs):
        self.calls += 1
        if self.calls == self.at:
            pid = os.getpid()
            self.child = subprocess.Popen(
                ["sh", "-c", f"kill -STOP {pid}; sleep {PAUSE_S}; kill -CONT {pid}"])
            self.child.wait()  # the stop lands here, inside the cycle
            time.sleep(AFTER_S)
        return super().step_cycle(*args, **kwargs)


def paused_ticks(channel: str) -> tuple[float, list[int], int, int]:
    """Five lockstep ticks on `channel` with the process stopped inside the third cycle:
    (their wall time s, the counters, the gaps, the stopping child's exit code). Run in a
    process of its own: stopping the test's process would stop pytest (and, from a shell,
    take it out of the foreground)."""
    simulator = PausedMidCycle(at=3)
    device = start_simulated_axis("virtual", channel, NODE_ID, simulator)
    network = open_network("virtual", channel)
    try:
        drive = Cia402Drive(network, NODE_ID, packaged_eds_path())
        drive.configure()
        lockstep = LockstepClock(network, [drive], timeout_s=1.0)
        start = time.perf_counter()
        counters = [lockstep.tick() for _ in range(5)]
        took = time.perf_counter() - start
    finally:
        network.disconnect()
        device.close()
    return took, counters, lockstep.gaps, simulator.child.wait(10)


def test_a_cycle_paused_longer_than_the_bus_timeout_is_waited_for(can_channel):
    """The process stopped for 1.5 s inside a cycle: the tick after it returns (the old wait
    raised "no TPDOs 1.0 s after SYNC"); a peer slow while the process runs still times out
    at 1 s (test_clock.py::test_the_first_lockstep_cycle_may_be_slow_the_others_not)."""
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        took, counters, gaps, stopped = pool.submit(paused_ticks, can_channel).result(120)
    assert stopped == 0
    assert took > PAUSE_S, "the pause happened during the ticks"
    assert np.all(np.diff(counters) == 1) and gaps == 0


def test_waiting_counts_only_the_time_the_process_was_awake():
    """Slices that return late (here: each takes 0.2 s for 0.05 s asked) count as asked;
    one that returns on time counts as itself; the wall time is bounded by the limit."""
    calls = []

    def late(asked: float) -> bool:
        calls.append(asked)
        time.sleep(0.2)
        return False

    start = time.perf_counter()
    assert not wait_awake(late, 0.2, limit_s=10.0)
    assert len(calls) == 4 and time.perf_counter() - start >= 0.8
    calls.clear()
    start = time.perf_counter()
    assert not wait_awake(late, 1.0, limit_s=0.5)
    assert 2 <= len(calls) <= 3 and time.perf_counter() - start >= 0.5, \
        "stopped at the wall-time limit"
    assert wait_awake(lambda asked: True, 1.0, limit_s=1.0)
