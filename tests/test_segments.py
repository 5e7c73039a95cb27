"""Segments carry labels for analysis (`info`) apart from what devices act on (`commands`);
both reach the recording in one segment event, and recordings from before the split still
read."""

from __future__ import annotations

import json

import numpy as np

from feedbench.devices.cycle_io import spindle_commands
from feedbench.engine.plan import Plan, Segment, segment_event
from feedbench.axes.rack_pinion import SETTING_KEYS
from feedbench.engine.runner import segment_text
from feedbench.protocols.cia402 import CSP


def _plan() -> Plan:
    return Plan("smfe", CSP, [
        Segment("spindle start", "settle", np.zeros(5),
                commands={"spindle_rpm": 300.0, "spindle_ramp_rpm_s": 600.0}),
        Segment("approach", "move", np.zeros(7), info={"cut": 0}),
        Segment("ramp", "measure", np.zeros(11), info={"cut": 0},
                commands={"spindle_rpm": 1500.0}),
        Segment("setup", "settle", np.zeros(3), commands={"coupling": "master"}),
    ], {}, 1e-3)


def test_the_event_keeps_commands_apart_and_reads_back_as_written():
    ramp = _plan().segments[2]
    text = segment_text(ramp)
    assert json.loads(text) == {"label": "ramp", "kind": "measure", "cut": 0,
                                "commands": {"spindle_rpm": 1500.0}}
    assert segment_event(text) == ("ramp", "measure", {"cut": 0}, {"spindle_rpm": 1500.0})
    assert "commands" not in segment_text(_plan().segments[1])


def test_a_recording_from_before_the_split_reads_its_commands_as_info():
    old = json.dumps({"label": "ramp", "kind": "measure", "cut": 0, "spindle_rpm": 1500.0})
    assert segment_event(old) == ("ramp", "measure", {"cut": 0, "spindle_rpm": 1500.0}, {})


def test_each_device_finds_its_commands_at_the_cycle_its_segment_starts():
    plan = _plan()
    assert spindle_commands(plan) == {0: (300.0, 600.0), 12: (1500.0, None)}
    assert plan.commands_at(SETTING_KEYS) == {23: {"coupling": "master"}}
