"""Speed of the rack-and-pinion axis: its physics, and its two drives on the bus.

Figures:
- rack_pinion_realtime_factor: simulated seconds per wall second of
  `RackPinionSimulator.simulate` over 60 s of coupled stepped loading into the bumper
  (three bodies, two dead zones, two velocity PIs and the preload PI at 8 kHz).
- lab_axis_realtime_factor: the lab bench's `AxisSimulator` on the same 60 s of targets,
  the baseline; rack_pinion_vs_lab_physics: the ratio.
- rack_pinion_bus_cycles_per_s: lockstep bus cycles per wall second with both drives (11
  CAN frames per cycle, the shared world stepped once per SYNC), no load cell.
- lab_bus_cycles_per_s: the same loop with the lab bench's single drive (the baseline);
  rack_pinion_vs_lab_bus: the ratio.
- load_cell_read_us: one Modbus TCP request to the simulated load cell on 127.0.0.1 (µs).
"""

from __future__ import annotations

import numpy as np

from feedbench.axes import axis_kind
from feedbench.bench import bench_table
from feedbench.daq.clock import LockstepClock
from feedbench.devices import device_tables
from feedbench.drivers.cia402 import Cia402Drive
from feedbench.drivers.modbus_devices import LoadCellAmplifier, connect_tcp
from feedbench.axes.rack_pinion import AXIS_PDOS
from feedbench.models.axis import CSP, AxisSimulator
from feedbench.models.rack_pinion import RackPinionSimulator
from feedbench.protocols.canbus import open_network
from feedbench.sim_backends.bench import start_simulated_axis
from feedbench.sim_backends.eds import packaged_eds_path
from feedbench.sim_backends.rack_pinion import packaged_eds_path as rack_pinion_eds

from _timing import best_seconds  # benchmarks/_timing.py

SIMULATED_SECONDS = 60.0
BUS_CYCLES = 3000
MODBUS_READS = 1000
REPEATS = 5


def staircase(seconds: float, cycle: float = 1e-3) -> np.ndarray:
    """10 µm steps into a bumper 50 µm away, every 0.3 s, to 300 µm and back (m)."""
    steps = np.r_[np.arange(0, 31), np.arange(29, -1, -1)] * -10e-6
    per_step = np.repeat(steps, int(0.3 / cycle))
    return np.resize(per_step, int(round(seconds / cycle)))


def physics_factors() -> tuple[float, float]:
    """Real-time factors of the rack-and-pinion and the lab-bench physics on 60 s."""
    targets = staircase(SIMULATED_SECONDS)
    rack, lab = RackPinionSimulator(), AxisSimulator()
    rack.simulate(CSP, targets[:10])
    lab.simulate(CSP, targets[:10], 0.0, 0.0)

    def run_rack() -> None:
        rack.reset()
        rack.simulate(CSP, targets)

    def run_lab() -> None:
        lab.reset()
        lab.simulate(CSP, targets, 0.0, 0.0)

    return (SIMULATED_SECONDS / best_seconds(run_rack, REPEATS),
            SIMULATED_SECONDS / best_seconds(run_lab, REPEATS))


def cycles_per_second(clock: LockstepClock) -> float:
    """Lockstep ticks per wall second (best of REPEATS blocks)."""
    return BUS_CYCLES / best_seconds(lambda: [clock.tick() for _ in range(BUS_CYCLES)], REPEATS)


def rack_pinion_bus(channel: str) -> tuple[float, float]:
    """Cycles per second with both drives, and µs per load-cell request."""
    bench = bench_table({"axis": "rack_pinion", "channel": channel})
    axis = axis_kind("rack_pinion")(bench, None, {})
    tables = device_tables(bench, axis.needs)
    simulated = axis.start_simulated(1e-3, {}, tables)
    network = open_network("virtual", channel)
    try:
        drives = [Cia402Drive(network, node_id, rack_pinion_eds(), AXIS_PDOS)
                  for node_id in (1, 2)]
        for drive in drives:
            drive.configure()
        rate = cycles_per_second(LockstepClock(network, drives))
        host, port = simulated.addresses["load_cell"].split(":")
        client = connect_tcp(host, int(port))
        amplifier = LoadCellAmplifier(client, tables["load_cell"]["unit_id"])
        read = best_seconds(lambda: [amplifier.reading() for _ in range(MODBUS_READS)], REPEATS)
        client.close()
        return rate, read / MODBUS_READS * 1e6
    finally:
        network.disconnect()
        simulated.close()


def lab_bus(channel: str) -> float:
    """Cycles per second with the lab bench's one drive."""
    simulated = start_simulated_axis("virtual", channel)
    network = open_network("virtual", channel)
    try:
        drive = Cia402Drive(network, 1, packaged_eds_path())
        drive.configure()
        return cycles_per_second(LockstepClock(network, [drive]))
    finally:
        network.disconnect()
        simulated.close()


def run() -> dict[str, float]:
    rack, lab = physics_factors()
    rack_rate, read_us = rack_pinion_bus("bench-rack-pinion")
    lab_rate = lab_bus("bench-rack-pinion-lab")
    figures = {
        "rack_pinion_realtime_factor": rack,
        "lab_axis_realtime_factor": lab,
        "rack_pinion_vs_lab_physics": rack / lab,
        "rack_pinion_bus_cycles_per_s": rack_rate,
        "lab_bus_cycles_per_s": lab_rate,
        "rack_pinion_vs_lab_bus": rack_rate / lab_rate,
        "load_cell_read_us": read_us,
    }
    print(f"rack-and-pinion physics: {rack:8.0f} × real time (60 s of stepped loading, 8 kHz)")
    print(f"lab-bench physics:       {lab:8.0f} × real time (same targets; baseline), "
          f"ratio {rack / lab:.2f}")
    print(f"bus, two drives:         {rack_rate:8.0f} cycles/s (lockstep, 11 frames per cycle)")
    print(f"bus, lab drive:          {lab_rate:8.0f} cycles/s (baseline), "
          f"ratio {rack_rate / lab_rate:.2f}")
    print(f"load-cell Modbus read:   {read_us:8.0f} µs per request (TCP on 127.0.0.1)")
    return figures


if __name__ == "__main__":
    run()
