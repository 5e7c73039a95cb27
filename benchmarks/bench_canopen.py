"""Lockstep bus cycles per second: the full stack against the bare python-can + canopen loop.

Both loops move the same frames per cycle in one process: host → 3 RPDOs + SYNC, device →
2 TPDOs, host waits for the last TPDO. The bare loop has only canopen Networks with raw
subscriptions on both sides, on python-can's own `virtual` bus (`can_bus`); the full loop is
`Cia402Drive` + `LockstepClock` on the host and `SimulatedCia402Drive` (state machine,
AxisSimulator physics) on the device, on the bus feedbench opens for `virtual`
(`protocols.canbus.LocalVirtualBus`: python-can's, without its deep copy per frame and
receiver). Both wait for the last TPDO on the same primitive (`CycleSignal`). The bare loop
on feedbench's bus is measured too and printed beside it: over that one the ratio is the cost
of driver, simulated drive and physics alone.
Rounds alternate between the loops so that load from other processes hits them alike;
cycles/s are medians over the rounds; each ratio is printed for 5 repeats (each the median
of 6 consecutive rounds' own ratios: a round's loops run back to back, so a slow phase of
the machine cancels out) as min / median / max. CPU time per cycle (all threads of the
process, `time.process_time`) is reported beside the rates, and the load average.

Why the wall-clock ratio can exceed 1 although the full loop does more work: the three
threads of a cycle (host, device receive thread, host receive thread) hand over the GIL
three times per cycle, and the bare loop is little more than those hand-overs; on this VM
their latency depends on how long the other core sat idle. Pinned to one core
(`taskset -c 1`) both loops run faster (bare ≈ 2×) and the ratio is the CPU ratio.
"""

from __future__ import annotations

import itertools
import os
import tempfile
import statistics
import struct
import time
from pathlib import Path
from contextlib import contextmanager
from functools import partial
from typing import Callable, Iterator, NamedTuple

import can
import canopen
import numpy as np

from feedbench.daq.clock import LockstepClock, one_core
from feedbench.protocols.canbus import connect, open_bus, open_network
from feedbench.drivers.cia402 import Cia402Drive, CycleSignal
from feedbench.daq.recorder import Recorder
from feedbench.engine.limits import Limits
from feedbench.engine.plan import Plan, Segment
from feedbench.engine.runner import CHANNELS, UNITS, Runner
from feedbench.models.axis import CSP, CSV
from feedbench.sim_backends.bench import start_simulated_axis
from feedbench.sim_backends.eds import packaged_eds_path

NODE_ID = 1
N_CYCLES = 500
REPEATS = 5
ROUNDS_PER_REPEAT = 6
RPDO_PAYLOADS = ((0x200 + NODE_ID, bytes(7)), (0x300 + NODE_ID, bytes(8)),
                 (0x400 + NODE_ID, bytes(8)))
TPDO_COB_IDS = (0x180 + NODE_ID, 0x280 + NODE_ID)
_channels = itertools.count()


def _channel(kind: str) -> str:
    return f"bench-canopen-{kind}-{next(_channels)}"


class Timing(NamedTuple):
    cycles_per_s: float
    cpu_us_per_cycle: float


def _timed(n_cycles: int, cycle) -> Timing:
    wall, cpu = time.perf_counter(), time.process_time()
    for _ in range(n_cycles):
        cycle()
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    return Timing(n_cycles / wall, cpu / n_cycles * 1e6)


def bare_lockstep_cycles_per_s(n_cycles: int = N_CYCLES) -> float:
    """Cycles/s of the bare loop: canopen Networks, raw frames, no drive logic, no physics."""
    return _bare_loop(n_cycles).cycles_per_s


def driver_sim_physics_cycles_per_s(n_cycles: int = N_CYCLES) -> float:
    """Cycles/s of the full loop in CSV: set_targets, tick, actual, with the physics stepping."""
    return _full_loop(n_cycles).cycles_per_s


def can_bus(channel: str) -> can.BusABC:
    """python-can's own `virtual` bus (`can.interfaces.virtual.VirtualBus`)."""
    return can.Bus(interface="virtual", channel=channel)


def _bare_loop(n_cycles: int, bus: Callable[[str], can.BusABC] = partial(open_bus, "virtual"),
               ) -> Timing:
    """The bare loop on `bus(channel)` buses: feedbench's (`open_bus`, a `LocalVirtualBus`)
    or python-can's own (`can_bus`)."""
    channel = _channel("bare")
    host = connect(canopen.Network(bus(channel)))
    device = connect(canopen.Network(bus(channel)))
    answered = CycleSignal()
    received: dict[int, bytearray] = {}
    count = [0]

    def on_rpdo(can_id: int, data: bytearray, timestamp: float) -> None:
        received[can_id] = data

    def on_sync(can_id: int, data: bytearray, timestamp: float) -> None:
        count[0] += 1
        counter = count[0] & 0xFFFF
        device.send_message(TPDO_COB_IDS[0], struct.pack("<HiH", 0x1237, count[0], counter))
        device.send_message(TPDO_COB_IDS[1], struct.pack("<ii", count[0], count[0]))

    def on_last_tpdo(can_id: int, data: bytearray, timestamp: float) -> None:
        answered.set()

    for cob_id, _ in RPDO_PAYLOADS:
        device.subscribe(cob_id, on_rpdo)
    device.subscribe(0x80, on_sync)
    host.subscribe(TPDO_COB_IDS[-1], on_last_tpdo)
    def cycle() -> None:
        for cob_id, payload in RPDO_PAYLOADS:
            host.send_message(cob_id, payload)
        host.send_message(0x80, b"")
        if not answered.wait(1.0):
            raise RuntimeError("bare loop: TPDO missing")

    try:
        return _timed(n_cycles, cycle)
    finally:
        host.disconnect()
        device.disconnect()


@contextmanager
def _drive_on_simulated_axis(kind: str) -> Iterator[tuple[Cia402Drive, LockstepClock]]:
    """A configured host driver and its lockstep clock, against a simulated axis."""
    channel = _channel(kind)
    simulated = start_simulated_axis("virtual", channel, NODE_ID)
    network = open_network("virtual", channel)
    try:
        drive = Cia402Drive(network, NODE_ID, packaged_eds_path())
        drive.configure()
        yield drive, LockstepClock(network, [drive])
    finally:
        network.disconnect()
        simulated.close()


def _full_loop(n_cycles: int) -> Timing:
    with _drive_on_simulated_axis("full") as (drive, clock):
        drive.set_mode(CSV)
        drive.enable(clock.tick)

        def cycle() -> None:
            drive.set_targets(velocity=0.01, velocity_offset=0.0, force_offset=0.0)
            clock.tick()
            drive.actual

        return _timed(n_cycles, cycle)


def _runner_loop(n_cycles: int) -> Timing:
    """The whole run path: `Runner` (limits, observers' blocks) + `Recorder` (HDF5) on top
    of the full loop, holding position in CSP; counts every bus cycle of the run."""
    with _drive_on_simulated_axis("runner") as (drive, clock), \
            tempfile.TemporaryDirectory() as directory:
        runner = Runner(drive, clock, Limits.from_config({}))
        plan = Plan("benchmark", CSP, [Segment("hold", "settle", np.zeros(n_cycles))], {},
                    1e-3)
        start = runner.read_position()
        recorder = Recorder(Path(directory) / "run.h5", CHANNELS, UNITS, {})
        first, wall, cpu = clock.cycle, time.perf_counter(), time.process_time()
        runner.run(plan, recorder, start)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        cycles = clock.cycle - first
        return Timing(cycles / wall, cpu / cycles * 1e6)


def _runner_loop_on_one_core(n_cycles: int) -> Timing:
    """`_runner_loop` with its threads on one CPU, as a simulated `Bench` runs it
    (`bench.one_core`)."""
    with one_core():
        return _runner_loop(n_cycles)


def run() -> dict[str, float]:
    _full_loop(10)  # compile the physics, import everything: not part of any round
    _bare_loop(10, can_bus)
    load = os.getloadavg()[0]
    rounds = [(_bare_loop(N_CYCLES, can_bus), _full_loop(N_CYCLES), _runner_loop(N_CYCLES),
               _runner_loop_on_one_core(N_CYCLES), _bare_loop(N_CYCLES))
              for _ in range(REPEATS * ROUNDS_PER_REPEAT)]
    load = max(load, os.getloadavg()[0])
    bare, full, stack, stack_one_core, bare_local = (
        Timing(*(statistics.median(column) for column in zip(*(r[i] for r in rounds))))
        for i in range(5))
    full_ratios, stack_ratios = _repeats(rounds, 1), _repeats(rounds, 2)
    one_core_ratios = _repeats(rounds, 3, over=2)
    local_ratios = _repeats(rounds, 2, over=4)
    figures = {
        "bare_canopen_cycles_per_s": bare.cycles_per_s,
        "driver_sim_physics_cycles_per_s": full.cycles_per_s,
        "driver_sim_physics_over_bare": statistics.median(full_ratios),
        "bare_canopen_cpu_us_per_cycle": bare.cpu_us_per_cycle,
        "driver_sim_physics_cpu_us_per_cycle": full.cpu_us_per_cycle,
        "driver_sim_physics_cpu_over_bare": bare.cpu_us_per_cycle / full.cpu_us_per_cycle,
        "full_stack_cycles_per_s": stack.cycles_per_s,
        "full_stack_over_bare": statistics.median(stack_ratios),
        "full_stack_over_bare_min_of_5": min(stack_ratios),
        "full_stack_over_bare_max_of_5": max(stack_ratios),
        "full_stack_cpu_us_per_cycle": stack.cpu_us_per_cycle,
        "full_stack_cpu_over_bare": bare.cpu_us_per_cycle / stack.cpu_us_per_cycle,
        "bare_local_bus_cycles_per_s": bare_local.cycles_per_s,
        "full_stack_over_bare_local_bus": statistics.median(local_ratios),
        "full_stack_one_core_cycles_per_s": stack_one_core.cycles_per_s,
        "full_stack_one_core_over_all_cpus": statistics.median(one_core_ratios),
        "canopen_load_average": load,
    }
    print(f"bare python-can + canopen lockstep loop (SYNC, 3 RPDO, 2 TPDO; python-can's "
          f"VirtualBus): {bare.cycles_per_s:7.0f} cycles/s, {bare.cpu_us_per_cycle:5.0f} us "
          f"CPU/cycle (baseline)")
    print(f"Cia402Drive + LockstepClock + SimulatedCia402Drive + physics:   "
          f"{full.cycles_per_s:7.0f} cycles/s, {full.cpu_us_per_cycle:5.0f} us CPU/cycle")
    print(f"full stack (Runner + Recorder + the above):                    "
          f"{stack.cycles_per_s:7.0f} cycles/s, {stack.cpu_us_per_cycle:5.0f} us CPU/cycle")
    print(f"over bare, {REPEATS} repeats (each the median of {ROUNDS_PER_REPEAT} interleaved "
          f"rounds' own ratios), min / median / max: driver + sim + physics "
          f"{_spread(full_ratios)}, full stack {_spread(stack_ratios)} (target: min >= 0.9); "
          f"in CPU per cycle {figures['driver_sim_physics_cpu_over_bare']:.2f} and "
          f"{figures['full_stack_cpu_over_bare']:.2f}; rounds of {N_CYCLES} cycles, load "
          f"average {load:.1f} on {os.cpu_count()} CPUs")
    print(f"the bare loop on feedbench's own virtual bus (`LocalVirtualBus`, which the stack "
          f"uses): {bare_local.cycles_per_s:7.0f} cycles/s, {bare_local.cpu_us_per_cycle:5.0f} "
          f"us CPU/cycle; the full stack over it {_spread(local_ratios)}")
    print(f"full stack on one CPU (bench.one_core, the simulated bench's default):   "
          f"{stack_one_core.cycles_per_s:7.0f} cycles/s, {stack_one_core.cpu_us_per_cycle:5.0f} "
          f"us CPU/cycle; over the full stack on all CPUs {_spread(one_core_ratios)}")
    return figures


def _repeats(rounds: list[tuple[Timing, ...]], column: int, over: int = 0) -> list[float]:
    """`REPEATS` ratios of loop `column` over loop `over` (the bare loop): each the median
    of `ROUNDS_PER_REPEAT` consecutive rounds' own ratios of cycles/s."""
    ratios = [r[column].cycles_per_s / r[over].cycles_per_s for r in rounds]
    return [statistics.median(ratios[i:i + ROUNDS_PER_REPEAT])
            for i in range(0, len(ratios), ROUNDS_PER_REPEAT)]


def _spread(values: list[float]) -> str:
    """min / median / max."""
    return f"{min(values):.2f} / {statistics.median(values):.2f} / {max(values):.2f}"


if __name__ == "__main__":
    run()
