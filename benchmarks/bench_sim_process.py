"""The simulated bench in its own process against the in-process default, and the SMFE world.

- Lockstep bus cycles per second of the same host loop (`Cia402Drive` + `LockstepClock`,
  RPDOs, SYNC, TPDOs) against three simulated benches: `feedbench sim` in a separate
  process over the socketcand hub on loopback TCP (every device served: drive, I/O module,
  spindle, load cell, DAQ and their worlds); the same bench in the host's process on
  python-can's `virtual` bus (the baseline: the process boundary is the only difference);
  and the simulated drive alone in the host's process (the figure the issue quoted: it
  leaves out the other devices' worlds). The same bench in process is also timed on
  `DirectVirtualBus` (as a simulated lockstep `Bench` opens it since 29 Nov: no receive
  threads), with `feedbench sim`'s ratio over it. The in-process benches run on one CPU
  (`one_core`), as a simulated `Bench` does; the bench process's host is not pinned. Five
  repeats interleave the three (process, in process, drive alone), so that load from other
  processes hits them alike; the ratio is printed per repeat (min / median / max) with the
  load average.
- Hub relay: frames per second one way between two python-can socketcand clients.
- SMFE world: wall time of one bus cycle of the milling process (10 samples at 10 kHz) in
  `MillingProcess.advance`, against the offline `simulate_smfe_cut` per 10 samples
  (baseline: the same numba kernel family without per-call overhead), and a whole
  world step after the axis physics (`SmfeWorld.step`: inverter, cut, noise; the load cell;
  the DAQ's inputs to the instrument) with the DAQ not streaming.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Iterator

import can
import numpy as np
from can.interfaces import virtual

import feedbench.bench
from feedbench.bench import Bench, bench_table
from feedbench.devices import device_tables
from feedbench.daq.clock import one_core
from feedbench.models.milling import SMFE_TOOL, TABLE_6_1, simulate_smfe_cut, spindle_ramp
from feedbench.models.structure import SMFE_TOOL_STRUCTURE
from feedbench.protocols import canbus
from feedbench.protocols.canbus import open_bus
from feedbench.protocols.modbus_registers import INVERTER_CONTROL_RUN
from feedbench.sim_backends.process import READY, SimulatedBench, simulated_peers
from feedbench.sim_backends.smfe_world import CutLane, MillingProcess
from feedbench.sim_backends.socketcand_hub import SocketcandHub
from feedbench.units import RPM

N_CYCLES = 4000
"""Lockstep cycles per timed stretch (≈ 0.6 s each): with 1000 (≈ 0.15 s) a pause of the VM
of a few tenths of a second fell on one stretch and not its pair, and the in-process rate
alone ranged 3509–6789 cycles/s within one run (30 Nov); with 4000, 5984–6771."""
LOCKSTEP_REPEATS = 5
WARM_UP_CYCLES = 100
HUB_FRAMES = 5000
REPEATS = 3
FS = 10_000.0


def cycles_per_s(bench: Bench, n: int) -> float:
    t0 = time.perf_counter()
    for _ in range(n):
        bench.clock.tick()
    return n / (time.perf_counter() - t0)


def _bench_table(**values) -> dict:
    return bench_table(values)


def start_bench_process(directory: Path) -> tuple[subprocess.Popen, dict]:
    """`feedbench sim` (every device) on free loopback ports; its process and ready info."""
    config = directory / "bench.toml"
    config.write_text('[bench]\nsimulated = true\ninterface = "socketcand"\n'
                      'socketcand = "127.0.0.1:0"\n'
                      f'channel = "bench-{uuid.uuid4().hex[:8]}"\n')
    process = subprocess.Popen([sys.executable, "-m", "feedbench.commands.cli", "sim", str(config)],
                               stdout=subprocess.PIPE, text=True)
    line = process.stdout.readline()
    if not line.startswith(READY):
        process.kill()
        raise RuntimeError("feedbench sim did not start")
    return process, json.loads(line[len(READY):])


def every_device_in_process(stack: ExitStack, direct: bool = False) -> Bench:
    """The bench `feedbench sim` serves (every simulated device), in this process on a
    virtual bus and on one CPU as a simulated `Bench` runs, and a host `Bench` on it;
    `direct`: both on `DirectVirtualBus`, as a simulated lockstep `Bench` opens them (each
    frame handled in its sender's thread), else on `LocalVirtualBus` with receive threads."""
    channel = f"bench-full-{uuid.uuid4().hex[:8]}"
    stack.enter_context(one_core())
    bench = _bench_table(channel=channel)
    options = {"direct": True} if direct else {}
    stack.enter_context(SimulatedBench(bench, device_tables(bench, dict.fromkeys(
        simulated_peers(), {})), bus_options=options))
    if direct:
        stack.enter_context(host_bus_options(options))
    return stack.enter_context(Bench(_bench_table(simulated=False, channel=channel)))


@contextmanager
def host_bus_options(options: dict) -> Iterator[None]:
    """While inside, a host `Bench` opens its bus with `options` (a simulated one's
    `DirectVirtualBus` for a host that is not simulated itself)."""
    saved = feedbench.bench._bus_options
    feedbench.bench._bus_options = lambda cfg, devices=None: dict(options)
    try:
        yield
    finally:
        feedbench.bench._bus_options = saved


def lockstep_rates() -> tuple[list[float], list[float], list[float], list[float], list[float]]:
    """Cycles/s in `LOCKSTEP_REPEATS` interleaved repeats: the bench process over socketcand
    (the host not pinned, as a host of hardware runs; it stays up over the repeats), then the
    same bench in process and the simulated drive alone (opened anew in each repeat: a
    simulated `Bench` pins the host thread for as long as it is open), and the same bench
    in process on python-can's own virtual bus (`python_can_virtual_bus`)."""
    plain: list[float] = []
    direct: list[float] = []
    remote: list[float] = []
    local: list[float] = []
    drive_only: list[float] = []
    with tempfile.TemporaryDirectory() as directory, ExitStack() as stack:
        process, info = start_bench_process(Path(directory))
        stack.callback(process.wait, timeout=20)
        stack.callback(process.terminate)
        far = stack.enter_context(Bench(_bench_table(
            simulated=False, interface="socketcand", socketcand=info["socketcand"],
            channel=info["channel"])))
        cycles_per_s(far, WARM_UP_CYCLES)
        for _ in range(LOCKSTEP_REPEATS):
            remote.append(cycles_per_s(far, N_CYCLES))
            with ExitStack() as here:
                full = every_device_in_process(here)
                near = here.enter_context(Bench(_bench_table(
                    channel=f"bench-local-{uuid.uuid4().hex[:8]}")))
                cycles_per_s(full, WARM_UP_CYCLES)
                cycles_per_s(near, WARM_UP_CYCLES)
                local.append(cycles_per_s(full, N_CYCLES))
                drive_only.append(cycles_per_s(near, N_CYCLES))
            with ExitStack() as here, python_can_virtual_bus():
                full = every_device_in_process(here)
                cycles_per_s(full, WARM_UP_CYCLES)
                plain.append(cycles_per_s(full, N_CYCLES))
            with ExitStack() as here:
                full = every_device_in_process(here, direct=True)
                cycles_per_s(full, WARM_UP_CYCLES)
                direct.append(cycles_per_s(full, N_CYCLES))
    return remote, local, drive_only, plain, direct


@contextmanager
def python_can_virtual_bus() -> Iterator[None]:
    """While inside, `open_bus("virtual", …)` opens python-can's own `VirtualBus` instead
    of feedbench's `LocalVirtualBus` (the in-process baseline before it: a deep copy per
    frame and receiver)."""
    saved = canbus.LocalVirtualBus
    canbus.LocalVirtualBus = virtual.VirtualBus
    try:
        yield
    finally:
        canbus.LocalVirtualBus = saved


def _spread(values: list[float], digits: int = 2) -> str:
    """min / median / max."""
    return " / ".join(f"{v:.{digits}f}" for v in (min(values), statistics.median(values),
                                                  max(values)))


def hub_frames_per_s() -> float:
    """One-way frames/s from one socketcand client to another through the hub."""
    with SocketcandHub() as hub:
        sender, receiver = (open_bus("socketcand", "relay", host=hub.host, port=hub.port)
                            for _ in range(2))
        try:
            receiver.send(can.Message(arbitration_id=0x700, data=b"", is_extended_id=False))
            time.sleep(0.1)
            message = can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False)
            t0 = time.perf_counter()
            for _ in range(HUB_FRAMES):
                sender.send(message)
            received = sum(receiver.recv(2.0) is not None for _ in range(HUB_FRAMES))
            elapsed = time.perf_counter() - t0
        finally:
            sender.shutdown()
            receiver.shutdown()
    return received / elapsed


def _best_us(job, per: int, repeats: int = REPEATS) -> float:
    """Best wall time of `job()` over `repeats`, in µs per one of its `per` units."""
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        job()
        best = min(best, time.perf_counter() - t0)
    return best / per * 1e6


def milling_cycle_us() -> tuple[float, float, float]:
    """µs per bus cycle (10 samples): stepping process, offline kernel, whole world step."""
    rpm = spindle_ramp(1000.0, 0.0, 2.0, FS)
    theta = np.cumsum(rpm * RPM / FS)
    travel = 1e-4 * SMFE_TOOL.Z * theta / (2 * np.pi)
    lane = CutLane(-1.0, 1.0, "down", 12e-3, 2e-3)
    cycles = rpm.size // 10

    def stepped() -> None:
        process = MillingProcess(SMFE_TOOL_STRUCTURE, SMFE_TOOL, TABLE_6_1)
        for k in range(0, rpm.size, 10):
            process.advance(theta[k:k + 10], travel[k:k + 10], lane, 1 / FS)

    def offline() -> None:
        simulate_smfe_cut(SMFE_TOOL_STRUCTURE, SMFE_TOOL, TABLE_6_1, 2e-3, 12e-3, "down", rpm, FS)

    offline()  # compile (or load the numba cache) outside the timing
    table = _bench_table(channel=f"bench-world-{uuid.uuid4().hex[:8]}")
    with SimulatedBench(table, device_tables(table, {"spindle": {}, "load_cell": {},
                                                     "daq": {}})) as bench:
        inverter = bench.peers["spindle"].inverter  # as the host's register writes set it
        inverter.apply("SPEED_SETPOINT", 1000.0)
        inverter.apply("CONTROL", INVERTER_CONTROL_RUN)
        world = _best_us(lambda: [hook() for _ in range(cycles)
                                  for hook in bench.drive.after_physics], cycles)
    return _best_us(stepped, cycles), _best_us(offline, cycles), world


def run() -> dict[str, float]:
    load = os.getloadavg()[0]
    remotes, locals_, drives_only, plains, directs = lockstep_rates()
    load = max(load, os.getloadavg()[0])
    ratios = [r / l for r, l in zip(remotes, locals_)]
    plain_ratios = [r / p for r, p in zip(remotes, plains)]
    direct_ratios = [r / d for r, d in zip(remotes, directs)]
    remote, local, drive_only = (statistics.median(x) for x in (remotes, locals_, drives_only))
    relay = hub_frames_per_s()
    stepping, offline, world = milling_cycle_us()
    print(f"lockstep cycles/s, every simulated device in the host process (virtual bus): "
          f"{local:.0f} (baseline; min / median / max of {LOCKSTEP_REPEATS}: "
          f"{_spread(locals_, 0)}); "
          f"the simulated drive alone: {drive_only:.0f}")
    print(f"lockstep cycles/s, `feedbench sim` in its own process (socketcand hub, TCP): "
          f"{remote:.0f} ({_spread(remotes, 0)}); over the same bench in process, each of "
          f"{LOCKSTEP_REPEATS} interleaved repeats: {_spread(ratios)} (target: min >= 0.8); "
          f"{remote / drive_only:.2f}× the drive alone (load average {load:.1f} on "
          f"{os.cpu_count()} CPUs)")
    print(f"  the same bench in process on python-can's own VirtualBus (deep copy per frame "
          f"and receiver): {_spread(plains, 0)} cycles/s; `feedbench sim` over it "
          f"{_spread(plain_ratios)}")
    print(f"  the same bench in process on `DirectVirtualBus` (each frame handled in its "
          f"sender's thread, as a simulated lockstep `Bench` runs since 29 Nov): "
          f"{_spread(directs, 0)} cycles/s; `feedbench sim` over it {_spread(direct_ratios)}")
    print(f"hub relay, one way between two socketcand clients: {relay:.0f} frames/s")
    print(f"milling process per bus cycle (10 samples at 10 kHz): {stepping:.1f} µs stepped "
          f"per cycle vs {offline:.1f} µs in one offline call = {stepping / offline:.2f}×; "
          f"whole world step (inverter, cut, noise, load cell, 10 DAQ samples): {world:.1f} µs")
    return {"sim_inprocess_cycles_per_s": local, "sim_process_cycles_per_s": remote,
            "sim_process_ratio": statistics.median(ratios),
            "sim_process_ratio_min_of_5": min(ratios),
            "sim_process_ratio_max_of_5": max(ratios), "sim_process_load_average": load,
            "sim_process_over_python_can_virtual_min_of_5": min(plain_ratios),
            "sim_inprocess_direct_cycles_per_s": statistics.median(directs),
            "sim_process_over_direct_min_of_5": min(direct_ratios),
            "sim_process_over_direct": statistics.median(direct_ratios),
            "sim_inprocess_drive_only_cycles_per_s": drive_only,
            "sim_process_over_drive_only": remote / drive_only, "hub_frames_per_s": relay,
            "smfe_step_us_per_cycle": stepping, "smfe_offline_us_per_cycle": offline,
            "smfe_world_step_us": world}


if __name__ == "__main__":
    run()
