"""Structure experiments on the simulated lab bench: speed of the bench with the tool-tip world
and the accuracy figures the issue asks for, each speed against a baseline in the same run.

- bench_cycles_per_s: lockstep bus cycles per wall second of an impact-hammer run (drive,
  CiA 401 exciter I/O, serial DAQ at 10 kHz, tool-tip world, recorder with the DAQ stream);
  baseline: a closed-loop Bode run of the drive alone, same bench, same length.
- world_us_per_cycle: the tool-tip world's work in the SYNC handler (exciters, hammer, 10 DAQ
  samples with noise); baseline: the axis physics of the cycle (`AxisSimulator.step_cycle`).
- hammer_d500, hammer_d0: Fig. 5.12, largest |compliance| difference to 1000 mm/min relative
  to its peak, at 500 and at 0 mm/min (3 hits per feed).
- sine_vs_chirp_max_pct: sine-stream against shaker-chirp H1, largest |a/F| deviation in the
  half-power band at 1000 mm/min, 20 N; sine_min_r2: the smallest step R².
"""

from __future__ import annotations

import tempfile
import time

import numpy as np

from feedbench.bench import parse_run_config, run_config
from feedbench.daq.recording import open_recording
from feedbench.engine.family import families
from feedbench.models.axis import CSP, AxisSimulator
from feedbench.protocols import cia401
from feedbench.sim_backends.structure_world import StructureWorld, parse_structure

WORLD_CYCLES = 20_000


def _run(experiment: dict, channel: str) -> tuple[dict, float, int]:
    """Analysis, wall seconds and bus cycles of one run on the simulated bench."""
    config = parse_run_config({"bench": {"simulated": True, "channel": channel, "timeout_s": 5.0,
                                         "output_dir": tempfile.mkdtemp()},
                               "experiment": experiment})
    t0 = time.perf_counter()
    record = run_config(config, progress=False)
    seconds = time.perf_counter() - t0
    analysis = families()[experiment["type"]].analyze(open_recording(record["file"]))
    return analysis, seconds, config.plan.n_cycles


class _Io:
    """Outputs of a sine-stream cycle: the actuator commanded, the others idle."""

    digital = 0

    def analog_force(self, channel: int) -> float:
        return 10.0 if channel == cia401.ACTUATOR else 0.0


class _Drive:
    def __init__(self) -> None:
        self.simulator = AxisSimulator()
        self.tip_force = 0.0


def world_cost_us() -> tuple[float, float]:
    """µs per cycle of the world's two hooks, and of the axis physics step."""
    drive = _Drive()
    world = StructureWorld(drive, _Io(), None, parse_structure({}), 1e-3)
    t0 = time.perf_counter()
    for _ in range(WORLD_CYCLES):
        world.before_physics()
        world.samples(10)
    t1 = time.perf_counter()
    for _ in range(WORLD_CYCLES):
        drive.simulator.step_cycle(CSP, 0.0, 0.0, 0.0, 0.0, 0.0, drive.tip_force)
    t2 = time.perf_counter()
    return 1e6 * (t1 - t0) / WORLD_CYCLES, 1e6 * (t2 - t1) / WORLD_CYCLES


def sine_vs_chirp() -> tuple[float, float]:
    stream, _, _ = _run({"type": "sine_stream", "feeds_mm_min": [1000.0], "amplitudes_N": [20.0],
                         "f_start_Hz": 40.0, "f_stop_Hz": 60.0, "f_step_Hz": 0.5}, "bench-ss")
    chirp, _, _ = _run({"type": "shaker_chirp", "feeds_mm_min": [1000.0], "amplitude_N": 20.0,
                        "f_start_Hz": 30.0, "f_stop_Hz": 70.0, "duration_s": 4.0,
                        "repetitions": 2}, "bench-chirp")
    frf = stream["streams"][0]["frf"]
    f, sine = np.array(frf["f_hz"]), np.array(frf["accelerance_abs"])
    h1 = np.interp(f, chirp["feeds"][0]["frf"]["f_hz"], chirp["feeds"][0]["frf"]["H1_abs"])
    band = sine >= sine.max() / np.sqrt(2.0)
    return 100.0 * float(np.max(np.abs(sine[band] / h1[band] - 1.0))), min(frf["r_squared"])


def run() -> dict[str, float]:
    hammer, hammer_s, hammer_cycles = _run(
        {"type": "impact_hammer", "feeds_mm_min": [0.0, 500.0, 1000.0], "hits_per_feed": 3,
         "record_s": 1.5}, "bench-hammer")
    _, bode_s, bode_cycles = _run(
        {"type": "closed_loop_bode", "f_start_Hz": 10.0, "f_stop_Hz": 120.0, "f_step_Hz": 1.0},
        "bench-bode")
    world_us, physics_us = world_cost_us()
    deviation, min_r2 = sine_vs_chirp()
    feeds = {f["feed_mm_min"]: f for f in hammer["feeds"]}
    figures = {
        "bench_cycles_per_s": hammer_cycles / hammer_s,
        "drive_only_cycles_per_s": bode_cycles / bode_s,
        "world_us_per_cycle": world_us,
        "physics_us_per_cycle": physics_us,
        "hammer_d500": feeds[500.0]["distance_to_highest_feed"],
        "hammer_d0": feeds[0.0]["distance_to_highest_feed"],
        "sine_vs_chirp_max_pct": deviation,
        "sine_min_r2": min_r2,
    }
    print(f"bench_cycles_per_s      {figures['bench_cycles_per_s']:8.0f}  hammer run: drive + "
          f"exciter I/O + DAQ 10 kHz + tool-tip world ({hammer_cycles} cycles)")
    ratio = figures["bench_cycles_per_s"] / figures["drive_only_cycles_per_s"]
    print(f"drive_only_cycles_per_s {figures['drive_only_cycles_per_s']:8.0f}  baseline: Bode "
          f"run, drive alone; ratio {ratio:.2f}")
    print(f"world_us_per_cycle      {world_us:8.1f}  tool-tip world per SYNC (exciters, hammer, "
          f"10 DAQ samples); physics step {physics_us:.1f} µs, ratio {world_us / physics_us:.2f}")
    print(f"hammer_d500             {figures['hammer_d500']:8.3f}  |Φ(500) − Φ(1000)| / peak "
          f"(Fig. 5.12 'invariant'); idle: hammer_d0 = {figures['hammer_d0']:.2f}")
    print(f"sine_vs_chirp_max_pct   {deviation:8.2f}  sine-stream vs chirp H1, half-power band "
          f"(goal < 2 %); smallest step R² {min_r2:.5f} (goal > 0.99)")
    return figures
