"""The hard real-time cycle (issue 18.1): SYNC from python-can's periodic sender, the host
paced by the TPDO sets, per-cycle times recorded, missed / repeated / late cycles counted.

Against `feedbench sim` in its own process. Timing values depend on the machine's load:
they are asserted only for consistency here; the targets are `benchmarks/bench_realtime.py`'s.
"""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

import feedbench
from feedbench.api import RunError
from feedbench.bench import Bench, bench_schema
from feedbench.commands.cli import main
from feedbench.config import validate_table
from feedbench.daq.clock import BusTimeout, RealtimeClock
from feedbench.daq.recording import open_recording
from feedbench.daq.timing import TIMING_CHANNELS, cycle_timing, recorded_timing
from feedbench.report import write_report
from sim_peer import start_sim

CYCLE_MS = 1.0
"""The simulated drive's cycle (its 0x1006 and physics step)."""


def test_cycle_timing_counts_missed_repeated_late_and_lateness():
    """Cycles 10…19 with 12 and 13 missing; cycle 15's setpoints left after its TPDOs
    (repeated); cycle 17's TPDOs 0.7 ms behind the grid of the fastest answer (late)."""
    cycle = np.array([10, 11, 14, 15, 16, 17, 18, 19])
    tpdo = 100.0 + cycle * 1e-3 + 3e-4
    tpdo[cycle == 17] += 7e-4
    tpdo[cycle == 11] -= 1e-4  # the fastest answer: lateness 0
    rpdo = tpdo - 8e-4
    rpdo[cycle == 15] = tpdo[cycle == 15] + 1e-5
    timing = cycle_timing(cycle, tpdo, rpdo, 1e-3)
    assert (timing.expected, timing.received, timing.missed) == (10, 8, 2)
    assert (timing.repeated, timing.late) == (1, 1)
    assert timing.lateness_max_us == pytest.approx(800.0, abs=0.01)
    assert timing.lateness_p50_us == pytest.approx(100.0, abs=0.01)
    assert sum(timing.histogram_counts) == 8
    assert timing.histogram_edges_us[:3] == pytest.approx([0.0, 25.0, 50.0])
    assert timing.histogram_edges_us[-1] == pytest.approx(800.0)  # 32 bins of 25 µs
    assert timing.missed_share == 0.2


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """`feedbench sim` in its own process, its world warmed up by a few lockstep cycles (its
    physics compiles on the first SYNC)."""
    process, info = start_sim(tmp_path_factory.mktemp("sim"), "realtime")
    try:
        with Bench(host_bench(info, "lockstep")) as bench:
            for _ in range(20):
                bench.clock.tick()
        yield info
    finally:
        process.terminate()
        process.communicate(timeout=20)


def host_bench(info: dict, clock: str) -> dict:
    return validate_table({"simulated": False, "interface": "socketcand",
                           "socketcand": info["socketcand"], "channel": info["channel"],
                           "clock": clock, "cycle_ms": CYCLE_MS,
                           "output_dir": str(info["directory"])}, bench_schema(), "bench")


def test_realtime_run_records_its_cycle_timing(sim, capsys):
    """1 s recorded through the runner: the per-cycle times are rows, the counts are in the
    file's metadata, equal to those the rows give, missed + received = expected, missed =
    the recording's gaps; `feedbench runs --json` and the report show them. (On a loaded
    machine the sim process may miss SYNCs for longer than `bench.sync_loss_ms` and stop
    the run: an aborted run's counts are written the same way.)"""
    with feedbench.open_bench({"bench": host_bench(sim, "realtime")}) as bench:
        bench.drive.enable()
        try:
            run = bench.record(1.0)
        except RunError as error:
            assert "EMCY 0x8100" in error.run.reason  # SYNC loss, nothing else
            run = error.run
    recording = open_recording(run.path)
    timing = recording.metadata["timing"]
    assert timing == recorded_timing(recording).as_dict()
    assert timing["missed"] + timing["received"] == timing["expected"]
    assert timing["received"] == recording.n_samples > 0
    assert timing["missed"] == recording.n_gaps
    assert timing["expected"] == recording.cycle[-1] - recording.cycle[0] + 1
    assert sum(timing["histogram_counts"]) == timing["received"]
    assert 0 <= timing["repeated"] <= timing["received"] and 0 <= timing["late"]
    assert timing["cycle_s"] == CYCLE_MS * 1e-3
    for channel in TIMING_CHANNELS:
        assert recording.units[channel] == "s"
    assert np.all(np.isfinite(recording.channels["tpdo_time"]))
    unsent = np.isnan(recording.channels["rpdo_time"])  # taken while behind: nothing sent
    assert unsent.sum() <= timing["repeated"]

    capsys.readouterr()
    assert main(["runs", "--dir", str(sim["directory"]), "--json"]) == 0
    rows = {row["id"]: row for row in json.loads(capsys.readouterr().out)["runs"]}
    assert rows[run.id]["timing"] == timing

    html = write_report([run.path], sim["directory"] / "report.html").read_text()
    assert "cycle timing: lateness histogram" in html
    assert f"{timing['received']} of {timing['expected']} received" in html


def test_lockstep_recording_has_no_cycle_timing(sim):
    """Virtual time has no wall-clock timing: no timing channels, no metadata, none listed."""
    with feedbench.open_bench({"bench": host_bench(sim, "lockstep")}) as bench:
        bench.drive.enable()
        run = bench.record(0.05)
    recording = open_recording(run.path)
    assert "timing" not in recording.metadata and recorded_timing(recording) is None
    assert not set(TIMING_CHANNELS) & set(recording.channels)


def test_realtime_clock_times_out_when_the_drive_stops_answering(sim):
    """SYNC keeps coming from the periodic sender; a drive that sends no new TPDO set (NMT
    pre-operational: no PDOs) is a BusTimeout after `timeout_s`."""
    with Bench(host_bench(sim, "realtime")) as bench:
        clock = bench.clock
        assert isinstance(clock, RealtimeClock)
        first = clock.tick()
        later = [clock.tick() for _ in range(20)]
        assert all(b > a for a, b in zip([first, *later], later))
        clock.timeout_s = 0.2
        bench.drive.node.nmt.state = "PRE-OPERATIONAL"
        with pytest.raises(BusTimeout, match="no new TPDO set for 0.2 s"):
            for _ in range(500):
                clock.tick()
        bench.drive.node.nmt.state = "OPERATIONAL"


def test_a_host_loop_that_stalls_mid_run_leaves_the_drive_to_stop_itself(sim):
    """SYNC and the heartbeat come from periodic senders, which would keep a hung host's
    drive enabled: the run's stall guard stops both once no tick came for `timeout_s`, the
    drive's SYNC-loss watchdog (0x2021) stops the axis, and the host, back, aborts the run
    with one reason and keeps its samples. Here the hang is a progress callback that blocks
    the cycle loop for 2 s (the bench's bus timeout is 1 s) at a third of a 1 s record."""
    stalled = []

    def hang_once(fraction: float, step: str) -> None:
        if fraction > 0.3 and not stalled:
            stalled.append(fraction)
            time.sleep(2.0)

    with feedbench.open_bench({"bench": host_bench(sim, "realtime")}) as bench:
        bench.drive.enable()
        with pytest.raises(RunError) as error:
            bench.record(1.0, progress=hang_once)
        state = bench.drive.state
    run = error.value.run
    assert run.reason.startswith("host cycle loop stalled for more than 1 s: SYNC and "
                                 "heartbeat stopped")
    assert state != "operation enabled"
    recording = open_recording(run.path)
    assert recording.status == "aborted"
    assert recording.n_samples >= 250  # the cycles before the stall are kept
