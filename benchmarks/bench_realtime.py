"""The hard real-time cycle at 1 kHz against `feedbench sim` in its own process (issue 18.1).

Three runs of `FEEDBENCH_REALTIME_S` seconds each (60 s by default) against one
`feedbench sim` process over its socketcand hub on loopback, the drive enabled in CSV and a
new setpoint every cycle:

- ``realtime``: `daq.clock.RealtimeClock`: SYNC from python-can's periodic sender, the host's
  loop paced by the TPDO sets;
- ``sleep_spin`` (baseline, the loop of before issue 18): the host sleeps to each SYNC slot,
  spins its last 0.5 ms, sends the RPDOs and the SYNC itself and waits for the TPDOs until
  0.9 of the cycle (`SleepSpinLoop`; kept here only);
- ``realtime_run``: the product's whole path, `feedbench.open_bench(...).record(seconds)`:
  runner, limits and the HDF5 recorder on the real-time clock; its timing read back from the
  recording.

Each: % missed, repeated and late cycles and p50/p99/max lateness (`daq.timing`: missed +
received = expected; the same definitions for both loops, the baseline's "cycle" being its
SYNC slot). The load average beside them: other processes share the 2 CPUs.

``python benchmarks/bench_realtime.py --loaded [N]`` (not part of `make bench`): N real-time
chirps (20 by default; the example chirp, shortened as `tests/test_late_host.py` runs it)
through the runner against one `feedbench sim` process while one CPU-burning process per CPU
runs beside them (started and stopped here; issue 26 item 2): per chirp its status, the
largest setpoint (x_ref) and position step in one cycle, the largest following error
|x_ref - position| while the plan ran, the host's catch-ups (``timing`` events: cycles and
ms), the cycles it took without sending, how many cycles after it was sent the stop
reached the drive (the bus backlog, measured from the SYNC count) and the stop's ``fault``
events (escalation, stop by SDO); then the limit trips, completed and aborted.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import numpy as np

from bench_sim_process import cycles_per_s, start_bench_process

import feedbench
from feedbench.api import RunError
from feedbench.bench import Bench, bench_schema
from feedbench.config import ConfigError, validate_table
from feedbench.daq.clock import HOST_HEARTBEAT
from feedbench.daq.timing import MISSED_TARGET, CycleTiming, cycle_timing
from feedbench.models.axis import CSV
from feedbench.protocols.cia301 import SYNC_COB_ID

SECONDS = float(os.environ.get("FEEDBENCH_REALTIME_S", "60"))
CYCLE_S = 1e-3
VELOCITY = 1e-3
"""m/s: the commanded feed (60 mm/min), one setpoint per cycle."""
SETTLE_S = 2.0
WARMUP_CYCLES = 1000
"""Cycles run before the measurement (a backlog the enable left drains)."""
SPIN_S = 0.5e-3
RESPONSE_SHARE = 0.9


class SleepSpinLoop:
    """The baseline: the host's own SYNC in a sleep-then-spin loop (before issue 18).

    `tick()` sleeps to the next slot (the last `SPIN_S` spun), sends RPDOs and SYNC and
    waits for the TPDO set until `RESPONSE_SHARE` of the cycle; a set that does not come, or
    whose counter did not advance, is the old loop's repeated row (it recorded the cycle
    again); slots that passed while the host was busy got no SYNC at all."""

    def __init__(self, bench: Bench) -> None:
        self.network, self.drive = bench.network, bench.drive
        self.heartbeat = self.network.send_periodic(*HOST_HEARTBEAT, 0.1)
        self.repeated = 0
        self.slots, self.rpdo_times, self.tpdo_times = [], [], []
        self._start = self._next = time.perf_counter()
        self._last = None

    def tick(self) -> int:
        now = time.perf_counter()
        if now > self._next + CYCLE_S:
            self._next += (now - self._next) // CYCLE_S * CYCLE_S
        slot = self._next
        remaining = slot - time.perf_counter()
        if remaining > SPIN_S:
            time.sleep(remaining - SPIN_S)
        while time.perf_counter() < slot:
            time.sleep(0)
        self.drive.arm_cycle()
        rpdo_time = time.time()
        self.drive.transmit()
        self.network.send_message(SYNC_COB_ID, b"")
        self._next = slot + CYCLE_S
        fresh = self.drive.wait_cycle(max(0.0, slot + RESPONSE_SHARE * CYCLE_S
                                           - time.perf_counter()))
        if fresh and self.drive.device_cycle != self._last:
            self._last = self.drive.device_cycle
            self.slots.append(round((slot - self._start) / CYCLE_S))
            self.rpdo_times.append(rpdo_time)
            self.tpdo_times.append(self.drive.set_time)
        else:
            self.repeated += 1
        return self.drive.device_cycle

    def reset_timing(self) -> None:
        self.repeated = 0
        self.slots, self.rpdo_times, self.tpdo_times = [], [], []

    def timing(self) -> dict:
        timing = cycle_timing(self.slots, self.tpdo_times, self.rpdo_times, CYCLE_S).as_dict()
        return {**timing, "repeated": self.repeated}

    def close(self) -> None:
        self.heartbeat.stop()


def host_bench(info: dict, clock: str) -> dict:
    """The [bench] table that reaches the sim process, with `clock`."""
    return {"simulated": False, "interface": "socketcand", "socketcand": info["socketcand"],
            "channel": info["channel"], "clock": clock, "cycle_ms": CYCLE_S * 1e3}


def moving_loop(bench: Bench, tick, timing_of) -> CycleTiming:
    """Enable in CSV, then `SECONDS` of cycles at a new setpoint each; disable."""
    drive = bench.drive
    drive.set_mode(CSV)
    drive.set_targets(velocity=0.0)
    drive.enable(tick, max_cycles=2000)
    for _ in range(WARMUP_CYCLES):
        tick()
    timing_of.reset_timing()
    for k in range(round(SECONDS / CYCLE_S)):
        drive.set_targets(velocity=VELOCITY if k % 2000 < 1000 else -VELOCITY)
        tick()
    timing = timing_of.timing()
    if drive.fault:
        print(f"  the drive stopped during the loop: EMCY 0x{drive.emcy_code or 0:04X}")
    drive.set_targets(velocity=0.0)
    drive.disable(tick)
    return CycleTiming(**timing)


def realtime_loop(info: dict) -> CycleTiming:
    """The moving loop on the real-time clock, inside `guarded()` as the runner runs its
    cycles (the stall guard, and no full garbage collection meanwhile)."""
    with Bench(validate_table(host_bench(info, "realtime"), bench_schema(), "bench")) as bench, \
            bench.clock.guarded():
        return moving_loop(bench, bench.clock.tick, bench.clock)


def sleep_spin_loop(info: dict) -> CycleTiming:
    with Bench(validate_table(host_bench(info, "lockstep"), bench_schema(), "bench")) as bench:
        loop = SleepSpinLoop(bench)
        try:
            return moving_loop(bench, loop.tick, loop)
        finally:
            loop.close()


def realtime_run(info: dict, directory: Path) -> CycleTiming:
    """`SECONDS` recorded at standstill through the runner and recorder (a run the drive
    stopped, e.g. on a lost SYNC, counts up to its stop; its reason is printed)."""
    config = {"bench": {**host_bench(info, "realtime"), "output_dir": str(directory)}}
    with feedbench.open_bench(config) as bench:
        bench.drive.enable()
        try:
            run = bench.record(SECONDS)
        except RunError as error:
            run = error.run
            print(f"  realtime_run aborted: {run.reason}")
    return CycleTiming(**run.recording.metadata["timing"])


def sim_capacity(info: dict) -> float:
    """Lockstep cycles/s against the same sim process: how many cycles it answers per second
    when nothing waits for the wall clock (a 1 kHz real-time cycle needs more than 1000)."""
    with Bench(validate_table(host_bench(info, "lockstep"), bench_schema(), "bench")) as bench:
        cycles_per_s(bench, WARMUP_CYCLES)  # the first cycles of a fresh sim run slower
        return cycles_per_s(bench, 2000)


def line(name: str, t: CycleTiming) -> str:
    share = 100.0 / max(t.expected, 1)
    return (f"{name:<13s} {t.expected:7d} cycles: missed {share * t.missed:7.3f} %, "
            f"repeated {share * t.repeated:7.3f} %, late {share * t.late:7.3f} %; lateness "
            f"p50 {t.lateness_p50_us:7.0f} µs, p99 {t.lateness_p99_us:7.0f} µs, "
            f"max {t.lateness_max_us:7.0f} µs")


def run() -> dict[str, float]:
    with tempfile.TemporaryDirectory() as directory:
        process, info = start_bench_process(Path(directory))
        print(f"{SECONDS:g} s at {1 / CYCLE_S:g} Hz against `feedbench sim` in its own "
              f"process (load average over 1 min before each):", flush=True)
        try:
            results = {}
            capacity = sim_capacity(info)
            print(f"  the sim process answers {capacity:.0f} lockstep cycles/s "
                  f"(load {os.getloadavg()[0]:.1f})", flush=True)
            for name, measure in (("realtime", realtime_loop), ("sleep_spin", sleep_spin_loop),
                                  ("realtime_run", lambda i: realtime_run(i, Path(directory)))):
                time.sleep(SETTLE_S)  # the sim works off what the loop before left queued
                load = os.getloadavg()[0]
                results[name] = measure(info)
                print(f"  {line(name, results[name])}  (load {load:.1f})", flush=True)
        finally:
            process.terminate()
            process.wait(timeout=20)
    new, old = results["realtime"], results["sleep_spin"]
    ratio = (f"{old.missed_share / new.missed_share:.1f}× fewer" if new.missed
             else "none missed")
    print(f"  missed: realtime {100 * new.missed_share:.3f} % vs sleep-then-spin "
          f"{100 * old.missed_share:.3f} % ({ratio}; target ≤ "
          f"{100 * MISSED_TARGET:g} %: {'met' if new.missed_share <= MISSED_TARGET else 'NOT met'})")
    figures = {}
    for name, timing in results.items():
        figures.update({f"{name}_missed_pct": 100 * timing.missed_share,
                        f"{name}_repeated_pct": 100 * timing.repeated / max(timing.expected, 1),
                        f"{name}_late_pct": 100 * timing.late / max(timing.expected, 1),
                        f"{name}_lateness_p99_us": timing.lateness_p99_us})
    figures["realtime_load_average"] = os.getloadavg()[0]
    figures["realtime_sim_lockstep_cycles_per_s"] = capacity
    return figures


CHIRP_FASTEST_M_PER_CYCLE = 1500 / 60e3 * CYCLE_S
"""The example chirp's fastest planned step (its 1500 mm/min return move), m per cycle."""


def burners() -> list[subprocess.Popen]:
    """One busy-looping Python process per CPU this process may use."""
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"])
            for _ in os.sched_getaffinity(0)]


def loaded_chirp(info: dict, directory: Path) -> dict:
    """One real-time example chirp against the sim process; its figures (µm, ms)."""
    from feedbench.bench import parse_run_config
    from feedbench.daq.catalog import Catalog
    from feedbench.daq.recording import open_recording
    from feedbench.commands.demo import example_config

    raw = example_config("chirp")
    raw["bench"].update(host_bench(info, "realtime"), output_dir=str(directory))
    raw["experiment"].update(duration_s=1.0, repetitions=1, settle_s=0.3, tail_s=0.3)
    config = parse_run_config(raw)
    with Bench(config.bench, config.plan, config.experiment.devices()) as bench:
        row = bench.run(config, Catalog(directory / "catalog.sqlite"), directory,
                        progress=False)
    recording = open_recording(row["file"])
    stop = min((e.cycle for e in recording.events
                if e.kind == "segment" and '"disable"' in e.text), default=np.inf)
    moving = recording.cycle < stop
    cycles = np.diff(recording.cycle[moving])
    x_ref, position = (np.asarray(recording.channels[c])[moving] for c in ("x_ref", "position"))
    catch_ups = [e.text.split("(")[1].split(")")[0] for e in recording.events
                 if e.kind == "timing"]
    unsent = ~(np.asarray(recording.channels["rpdo_time"]) <= np.asarray(
        recording.channels["tpdo_time"]))
    reached = [e.text.split("stop reached the drive ")[1].split(" cycles")[0]
               for e in recording.events if "stop reached the drive " in e.text]
    faults = [e.text for e in recording.events if e.kind == "fault"]
    return {"status": row["status"], "reason": row["reason"], "reached": reached,
            "faults": faults,
            "trip": "limit tripped" in row["reason"],
            "x_ref_step_um": 1e6 * float(np.max(np.abs(np.diff(x_ref)) / cycles)),
            "position_step_um": 1e6 * float(np.max(np.abs(np.diff(position)) / cycles)),
            "following_error_um": 1e6 * float(np.max(np.abs(x_ref - position))),
            "catch_ups": catch_ups, "unsent_cycles": int(unsent.sum()),
            "longest_unsent": _longest_run(unsent),
            "missed": recording.metadata["timing"]["missed"]}


def _longest_run(flags: np.ndarray) -> int:
    """The longest run of True in `flags`."""
    longest = current = 0
    for flag in flags:
        current = current + 1 if flag else 0
        longest = max(longest, current)
    return longest


def loaded(n: int) -> dict:
    """`n` real-time chirps against `feedbench sim` with every CPU busy (see the module)."""
    results = []
    with tempfile.TemporaryDirectory() as directory:
        process, info = start_bench_process(Path(directory))
        hogs = burners()
        try:
            time.sleep(SETTLE_S)
            print(f"{n} real-time chirps against `feedbench sim`, {len(hogs)} CPU burners "
                  f"(load {os.getloadavg()[0]:.1f}):", flush=True)
            for k in range(n):
                try:
                    chirp = loaded_chirp(info, Path(directory))
                except ConfigError as error:  # the loaded machine kept the sim from answering
                    print(f"  {k + 1:2d} not started: {error} (load {os.getloadavg()[0]:.1f})",
                          flush=True)
                    continue
                results.append(chirp)
                reached = (f"; stop reached the drive {'/'.join(chirp['reached'])} cycles after "
                           "it was sent" if chirp["reached"] else "")
                reached += "".join(f"; {fault}" for fault in chirp["faults"])
                print(f"  {k + 1:2d} {chirp['status']:<8s} steps x_ref "
                      f"{chirp['x_ref_step_um']:5.1f} / position {chirp['position_step_um']:5.1f}"
                      f" µm, following error {chirp['following_error_um']:6.1f} µm, "
                      f"{chirp['unsent_cycles']:4d} cycles without a setpoint (longest "
                      f"{chirp['longest_unsent']:3d}), missed {chirp['missed']:3d}, "
                      f"catch-ups noted {len(chirp['catch_ups'])} (longest away "
                      f"{max([int(c.split()[0]) for c in chirp['catch_ups']], default=0)} ms)"
                      f"{'; ' + chirp['reason'] if chirp['reason'] else ''}"
                      f"{reached}"
                      f" (load {os.getloadavg()[0]:.1f})", flush=True)
        finally:
            for hog in hogs:
                hog.kill()
                hog.wait()
            process.terminate()
            process.wait(timeout=20)
    figures = {
        "chirps": len(results), "limit_trips": sum(c["trip"] for c in results),
        "complete": sum(c["status"] == "complete" for c in results),
        "aborted": sum(c["status"] != "complete" for c in results),
        "max_x_ref_step_um": max((c["x_ref_step_um"] for c in results), default=math.nan),
        "max_position_step_um": max((c["position_step_um"] for c in results), default=math.nan),
        "max_following_error_um": max((c["following_error_um"] for c in results), default=math.nan),
        "longest_unsent_cycles": max((c["longest_unsent"] for c in results), default=0),
        "planned_fastest_step_um": 1e6 * CHIRP_FASTEST_M_PER_CYCLE,
    }
    print("  " + ", ".join(f"{k} {v:.1f}" if isinstance(v, float) else f"{k} {v}"
                           for k, v in figures.items()))
    reasons = sorted({c["reason"] for c in results if c["reason"]})
    for reason in reasons:
        print(f"  aborted: {reason}")
    return figures


if __name__ == "__main__":
    if "--loaded" in sys.argv[1:]:
        rest = [a for a in sys.argv[1:] if a != "--loaded"]
        loaded(int(rest[0]) if rest else 20)
    else:
        run()
