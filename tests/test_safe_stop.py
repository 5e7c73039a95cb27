"""Safe means stopped, measured (issue 26, item 1): what a drive's stop depends on is read and
checked at configure, and a stop is confirmed by the measured velocity, escalated when the
drive's own quick stop does not stop the axis.

The probe of the issue: quick-stop deceleration 0x6085 = 0 on the simulated drive is refused
at configure, naming the object; a drive whose quick stop does not stop (0x6085 set to 0
after the check) is stopped by disable voltage, and the run's reason says so.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from feedbench.bench import Bench, parse_run_config
from feedbench.config import ConfigError
from feedbench.daq.catalog import Catalog
from feedbench.daq.recording import open_recording
from feedbench.commands.demo import example_config
from feedbench.drivers.cia402 import StopSettings, decode_state
from feedbench.engine.runner import StopRequest
from feedbench.units import MM_PER_MIN
from test_cia402_sim import loopback

QUICK_STOP_DECELERATION, QUICK_STOP_OPTION, FAULT_REACTION, FOLLOWING_ERROR_WINDOW = (
    0x6085, 0x605A, 0x605E, 0x6065)
STOP_AFTER_BLOCKS = 20
"""The stop is requested after this many 50-cycle blocks (1 s: the axis runs at its feed)."""


def test_quick_stop_deceleration_zero_is_refused_at_configure(can_channel):
    with loopback(can_channel, configure=False) as bench:
        bench.drive.node.sdo[QUICK_STOP_DECELERATION].raw = 0
        with pytest.raises(ConfigError) as info:
            bench.drive.configure()
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("bench.stop: drive node 3 cannot stop the axis: 0x6085 = 0 nm/s²")


def test_every_refused_object_is_named_in_one_line(can_channel):
    with loopback(can_channel, configure=False) as bench:
        sdo = bench.drive.node.sdo
        sdo[QUICK_STOP_OPTION].raw = 5  # slow-down ramp 0x6084, then stay in quick stop
        sdo[0x6084].raw = 100_000_000  # 0.1 m/s²
        sdo[FAULT_REACTION].raw = 0  # the axis coasts
        sdo[FOLLOWING_ERROR_WINDOW].raw = 0xFFFFFFFF  # off
        with pytest.raises(ConfigError) as info:
            bench.drive.configure()
    assert str(info.value).split(": ", 2)[2] == (
        "0x6084 = 100000000 nm/s² is below the 0.5 m/s² a stop needs; "
        "0x605E = 0: the fault reaction lets the axis coast; "
        "0x6065 = 4294967295 nm is above the 10 mm allowed (0xFFFFFFFF: off)")


def test_safe_values_are_written_where_the_config_says_so(can_channel):
    with loopback(can_channel, configure=False) as bench:
        sdo = bench.drive.node.sdo
        sdo[QUICK_STOP_DECELERATION].raw = 0
        sdo[QUICK_STOP_OPTION].raw = 0
        bench.drive.configure(stop=StopSettings(deceleration=1.5, write=True))
        assert bench.device.values[QUICK_STOP_DECELERATION] == 1_500_000_000
        assert bench.device.values[QUICK_STOP_OPTION] == 2
        assert bench.drive.stop_parameters.as_metadata() == {
            "0x6085": 1_500_000_000, "0x6084": 1_000_000_000, "0x605A": 2, "0x605E": 2,
            "0x6065": 10_000_000, "0x1016": 3000}
        assert bench.drive.stop_deceleration == 1.5


class StopAfter:
    """An observer that asks for a safe stop after `blocks` blocks of cycles."""

    def __init__(self, stop: StopRequest, blocks: int) -> None:
        self.stop = stop
        self.blocks = blocks

    def on_start(self, plan, channels) -> None: ...

    def on_segment(self, index, segment, cycle) -> None: ...

    def on_block(self, cycles: np.ndarray, block: np.ndarray) -> None:
        self.blocks -= 1
        if self.blocks == 0:
            self.stop.request("stop requested by the test")

    def on_stop(self, status: str, reason: str) -> None: ...


def _chirp_stopped(tmp_path: Path, channel: str, quick_stop_deceleration: int | None,
                   example: str = "chirp") -> tuple[dict, object]:
    """The `example` (a chirp at 500 mm/min) stopped after 1 s; with `quick_stop_deceleration`
    (nm/s²) written to the drive after the configure check (a drive whose parameter changed
    since). The run's record and the simulated bench (closed)."""
    raw = example_config(example)
    raw["bench"].update(output_dir=str(tmp_path), channel=channel)
    config = parse_run_config(raw)
    stop = StopRequest()
    with Bench(config.bench, config.plan, config.experiment.devices()) as bench:
        if quick_stop_deceleration is not None:
            bench.drive.node.sdo[QUICK_STOP_DECELERATION].raw = quick_stop_deceleration
        row = bench.run(config, Catalog(tmp_path / "catalog.sqlite"), tmp_path,
                        observers=[StopAfter(stop, STOP_AFTER_BLOCKS)], progress=False,
                        stop=stop)
    return row, bench.simulated


def _stopped_at_the_end(recording) -> None:
    velocity = recording.channels["velocity"]
    assert np.all(np.abs(velocity[-10:]) < 5.0 * MM_PER_MIN)
    assert decode_state(int(recording.channels["statusword"][-1])) == "SWITCH ON DISABLED"


def test_a_stop_is_confirmed_by_standstill_and_the_statusword(tmp_path, can_channel):
    row, _ = _chirp_stopped(tmp_path, can_channel, None)
    assert row["status"] == "aborted" and row["reason"] == "stop requested by the test"
    recording = open_recording(row["file"])
    _stopped_at_the_end(recording)
    [stop] = [e for e in recording.events if e.kind == "stop"]
    assert stop.text.startswith("axis stopped, power stage off after ")
    assert stop.text.endswith("(|v| < 5 mm/min for 10 cycles; 0x6041 = 0x0240 SWITCH ON DISABLED)")
    assert recording.metadata["drive_stop"]["0x6085"] == 2_000_000_000


def test_a_quick_stop_that_does_not_stop_is_escalated(tmp_path, can_channel):
    row, _ = _chirp_stopped(tmp_path, can_channel, 0)
    reason = row["reason"]
    assert row["status"] == "aborted" and reason.startswith("stop requested by the test; ")
    steps = reason.split("; ")[1:]
    recording = open_recording(row["file"])
    _stopped_at_the_end(recording)
    faults = [e for e in recording.events if e.kind == "fault"]
    assert [e.text for e in faults] == [f"safe stop: {step}" for step in steps]
    [abort] = [e for e in recording.events if e.kind == "abort"]
    velocity = recording.channels["velocity"]
    held = velocity[(recording.cycle >= faults[0].cycle - 50) & (recording.cycle < faults[0].cycle)]
    assert np.ptp(held) < 0.01 * abs(held[-1]) and abs(held[-1]) > 300 * MM_PER_MIN, \
        "the quick stop held the speed it had"
    # bound: 3000 mm/min / 2 m/s² (0x6085 read at configure) + 0.25 s + 10 cycles = 0.285 s
    assert faults[0].cycle - abort.cycle == 285
    assert steps[0] == (f"not stopped within 0.285 s (QUICK STOP ACTIVE at "
                        f"{abs(held[-1]) / MM_PER_MIN:.3g} mm/min): disable voltage")
    assert steps[1].startswith("axis stopped after ")
    assert steps[1].endswith(" more cycles (0x6041 = 0x0240 SWITCH ON DISABLED)")


def test_the_escalation_ends_with_safe_torque_off_where_an_io_module_has_it(tmp_path,
                                                                           can_channel):
    """A shaker chirp (the bench has the exciters' I/O module): after disable voltage the
    module's safe-torque-off output, wired to the simulated drive, is set."""
    row, simulated = _chirp_stopped(tmp_path, can_channel, 0, "shaker_chirp")
    steps = row["reason"].split("; ")
    assert steps[1].startswith("not stopped within ") and steps[1].endswith(": disable voltage")
    assert steps[2] == "safe torque off by I/O module node 10 (digital output 0x80)"
    assert steps[3].startswith("axis stopped after ")
    assert simulated.peers["exciter"].structure.io.digital & 0x80
    _stopped_at_the_end(open_recording(row["file"]))


def test_a_standstill_once_reached_stays_reached_for_the_stop_commands():
    """A stop sends disable operation once the axis stood `cycles` cycles; one noisy sample
    above the threshold afterwards resets the count (the stop is confirmed on a fresh run of
    still cycles) but not `reached`, so enable operation is not sent again behind the
    disable operation on its way (a flicker seen behind a 200-cycle bus backlog)."""
    from feedbench.engine.runner import Standstill

    standstill = Standstill(velocity=1e-5, cycles=3)
    for v in (2e-5, 0.0, 0.0):
        standstill.update([v])
    assert not standstill.reached and not standstill.stopped
    standstill.update([0.0])
    assert standstill.reached and standstill.stopped
    standstill.update([3e-5])
    assert standstill.reached and not standstill.stopped and standstill.count == 0
