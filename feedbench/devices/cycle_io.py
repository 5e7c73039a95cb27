"""Host devices the runner serves every bus cycle besides the drive (`runner.CycleDevice`).

- `SpindleCommands`: the spindle inverter over Modbus. A plan segment whose commands hold
  ``spindle_rpm`` (and optionally ``spindle_ramp_rpm_s``) sets the inverter's ramp limit and
  speed setpoint in the cycle the segment starts (0 rpm: stop), so a linear speed ramp is the
  inverter's own ramp, as on the thesis's SMFE bench (Ch. 6.4.1); the actual speed is read
  back every `readback_cycles` and recorded as ``spindle_speed`` (rad/s).
- `DaqStream`: the streaming DAQ over its serial port. Started with the run, read every
  cycle into the recording's high-rate stream; each sample is given the bus cycle it belongs
  to from its counter (the first sample after START is the first cycle after it: exact in
  lockstep, where the instrument's sample clock is the bench clock).

Either raises on its first failure (the runner aborts the run) and goes silent afterwards,
so the drive's safe stop never waits on a broken link (`devices.PerCycleDevice`).

Their device kinds (`devices.Device`, entry points ``feedbench.devices``):
`SpindleDevice` (``spindle``), `DaqDevice` (``daq``) and `ExciterDevice` (``exciter``, the
tool-tip exciters' I/O module driving `ExciterOutputs`).
"""

from __future__ import annotations

import math
import time
from typing import Any, Mapping

import numpy as np

from feedbench.config import Field, positive
from feedbench.daq.recorder import StreamSpec
from feedbench.devices import Device, DeviceLinks, PerCycleDevice
from feedbench.engine.plan import Plan
from feedbench.engine.runner import CycleDevice
from feedbench.protocols import cia401
from feedbench.protocols.serial_frames import CHANNEL_INDEX, CHANNELS
from feedbench.units import RPM

DAQ_SILENCE_CYCLES = 1000
DAQ_SILENCE_S = 5.0
"""The stream counts as lost after this many bus cycles AND wall seconds without one sample
(lockstep cycles run faster than real time: the reader thread may lag many cycles). A device
that went away, a CRC error or a gap in the sample counter end the run at once; this limit
only catches an instrument that stays connected and stops streaming. Not 2 s: the tty layer
was measured holding a pty's bytes for 2 s on a busy machine (`sim_backends.serial_daq`),
which aborted live-window runs of the test suite."""


LOCKSTEP_LAG_CYCLES = 200
LOCKSTEP_WAIT_S = 0.005
"""In lockstep (virtual time: a simulated bench, in the host's process or `feedbench sim`), a
stream silent for `LOCKSTEP_LAG_CYCLES` bus cycles (and one sample period, at a rate below
one sample a cycle) waits up to `LOCKSTEP_WAIT_S` per cycle for the reader thread. The
cycle's threads hand the GIL among themselves, and the serial reader's thread, which wakes
every 10 ms, was measured starved for hundreds of cycles (beside two busy processes: 1001 cycles and 5.6 s, and the quick
demo's SMFE run aborted as if the DAQ had stopped). The wait gives it the GIL; virtual time
and the samples' cycles (from their counter) are unchanged, and a DAQ that did stop still
ends the run after `DAQ_SILENCE_CYCLES` and `DAQ_SILENCE_S`. In real time nothing waits."""


class DeviceLinkError(RuntimeError):
    """A per-cycle device stopped answering."""


SPINDLE_COMMANDS = ("spindle_rpm", "spindle_ramp_rpm_s")
"""Segment commands of the spindle inverter: speed setpoint (rpm), ramp limit (rpm/s)."""


def spindle_commands(plan: Plan) -> dict[int, tuple[float, float | None]]:
    """Plan cycle index → (speed setpoint rpm, ramp limit rpm/s or None) from the segments'
    commands."""
    return {index: (float(found["spindle_rpm"]), found.get("spindle_ramp_rpm_s"))
            for index, found in plan.commands_at(SPINDLE_COMMANDS).items()
            if "spindle_rpm" in found}


class SpindleCommands(PerCycleDevice):
    """The spindle inverter (`drivers.modbus_devices.SpindleInverter`) commanded from the
    plan; its speed read back every `readback_cycles` and held between readings."""

    channels = ("spindle_speed",)
    units = {"spindle_speed": "rad/s"}

    def __init__(self, inverter, readback_cycles: int = 10) -> None:
        super().__init__(readback_cycles)
        self.inverter = inverter
        self._commands: dict[int, tuple[float, float | None]] = {}
        self._speed = math.nan

    def start(self, plan: Plan, recorder) -> None:
        super().start(plan, recorder)
        self._commands = spindle_commands(plan)
        self.guarded(self.inverter.reset_fault)

    def before_sync(self, index: int | None) -> None:
        command = self._commands.get(index) if index is not None else None
        if command is not None:
            self.guarded(lambda: self._apply(*command))

    def after_sync(self, cycle: int) -> tuple[float]:
        speed_rpm = self.poll(lambda: self.inverter.actual_speed_rpm)
        if speed_rpm is not None:
            self._speed = speed_rpm * RPM
        return (math.nan if self.failed else self._speed,)

    def stop(self, recorder) -> None:
        """Ramp the spindle down (the inverter's ramp limit)."""
        self.guarded(self.inverter.stop)

    def _apply(self, speed_rpm: float, ramp_rpm_s: float | None) -> None:
        if ramp_rpm_s is not None:
            self.inverter.set_ramp_rpm_s(ramp_rpm_s)
        if speed_rpm > 0.0:
            self.inverter.set_speed_rpm(speed_rpm)
            self.inverter.run()
        else:
            self.inverter.stop()



class DaqStream(PerCycleDevice):
    """The streaming DAQ (`drivers.serial_daq.SerialDaq`) recorded as stream `name` (its
    device's); in `lockstep` a lagging reader is waited for (`LOCKSTEP_LAG_CYCLES`)."""

    def __init__(self, daq, name: str, lockstep: bool = False) -> None:
        super().__init__()
        self.daq = daq
        self.name = name
        self.lockstep = lockstep
        units = {c: CHANNELS[CHANNEL_INDEX[c]].unit for c in daq.channels}
        self.streams = {name: StreamSpec(tuple(daq.channels), units, daq.rate)}
        self._recorder = None
        self._samples_per_cycle = 1
        self._first_cycle: int | None = None
        self._first_sequence: int | None = None
        self._last_cycle = 0
        self._silent = 0
        self._lag_cycles = LOCKSTEP_LAG_CYCLES
        self._last_sample = time.monotonic()

    def start(self, plan: Plan, recorder) -> None:
        super().start(plan, recorder)
        self._recorder = recorder
        self._samples_per_cycle = max(1, round(self.daq.rate * plan.cycle_s))
        self._lag_cycles = LOCKSTEP_LAG_CYCLES + math.ceil(1.0 / (self.daq.rate * plan.cycle_s))
        self.daq.start()

    def before_sync(self, index: int | None) -> None:
        """Nothing to send: the instrument streams on its own."""

    def after_sync(self, cycle: int) -> tuple[()]:
        if self._first_cycle is None:
            self._first_cycle = cycle
        self._last_cycle = cycle
        self.guarded(lambda: self._watch(cycle))
        return ()

    def _watch(self, cycle: int) -> None:
        """Record what arrived; a lost frame or a stream silent too long is an error."""
        arrived = self._drain()
        if (not arrived and self.lockstep and self._silent >= self._lag_cycles
                and self.daq.wait_for_samples(LOCKSTEP_WAIT_S)):
            arrived = self._drain()
        self._silent = 0 if arrived else self._silent + 1
        self._check_lost(cycle)
        now = time.monotonic()
        if not self._silent:
            self._last_sample = now
        elif self._silent > DAQ_SILENCE_CYCLES and now - self._last_sample > DAQ_SILENCE_S:
            raise DeviceLinkError(f"DAQ: no sample for {self._silent} bus cycles "
                                  f"({now - self._last_sample:.1f} s)")

    def _check_lost(self, cycle: int) -> None:
        """A frame lost on the link (CRC error, a gap in the sample counter) ends the run:
        the stream it leaves has a hole no analysis of it may bridge."""
        crc, dropped = self.daq.crc_errors, self.daq.dropped_frames
        if crc or dropped:
            raise DeviceLinkError(f"DAQ: samples lost on the serial link by bus cycle {cycle} "
                                  f"({crc} CRC errors, {dropped} frames dropped)")

    def stop(self, recorder) -> None:
        """STOP the stream, record what was still in flight and the link's loss counters."""
        self.guarded(lambda: self._finish(recorder))

    def _finish(self, recorder) -> None:
        self.daq.stop()
        self._drain()
        lost = {"crc_errors": self.daq.crc_errors, "dropped_frames": self.daq.dropped_frames,
                "overflowed_frames": self.daq.overflowed_frames}
        if any(lost.values()):
            recorder.event(self._last_cycle + 1, "gap", f"{self.name}: {lost}")

    def _drain(self) -> int:
        """Everything received so far into the recording; returns the number of samples."""
        try:
            block = self.daq.read_available()
        except Exception as exc:  # the device went away: the run stops, the link is silent
            raise DeviceLinkError(f"DAQ: {exc}") from None
        n = len(block.sequence)
        if n:
            if self._first_sequence is None:
                self._first_sequence = int(block.sequence[0])
            cycles = self._first_cycle + (block.sequence - self._first_sequence) \
                // self._samples_per_cycle
            self._recorder.append_stream(self.name, cycles, block.sequence, block.samples)
        return n


class SpindleDevice(Device):
    """The spindle inverter over Modbus TCP (``address``, unit ``unit_id``); its speed read
    back every ``readback_cycles`` (`SpindleCommands`)."""

    name = "spindle"
    address_doc = "host:port of the inverter's Modbus TCP server"
    unit_id = 1
    schema = {"readback_cycles": Field(int, 10, "read the speed back every n bus cycles",
                                       positive)}
    old_keys = {"modbus": "address"}

    @classmethod
    def open(cls, settings: Mapping[str, Any], links: DeviceLinks) -> SpindleCommands:
        from feedbench.drivers.modbus_devices import SpindleInverter

        inverter = SpindleInverter(cls.modbus_client(settings, links), settings["unit_id"])
        return SpindleCommands(inverter, settings["readback_cycles"])


class DaqDevice(Device):
    """The streaming DAQ on its serial port (``address``); settings: ``channels`` (names of
    `protocols.serial_frames.CHANNELS`) and ``rate_hz`` (samples/s)."""

    name = "daq"
    address_doc = "serial port of the streaming DAQ, e.g. /dev/ttyACM0"
    schema = {"channels": Field((list, tuple), [c.name for c in CHANNELS],
                                "channels streamed (protocols.serial_frames.CHANNELS)"),
              "rate_hz": Field(float, 10_000.0, "sample rate (samples/s)", positive)}
    old_keys = {"daq_port": "address"}

    @classmethod
    def open(cls, settings: Mapping[str, Any], links: DeviceLinks) -> DaqStream:
        from feedbench.drivers.serial_daq import SerialDaq

        daq = links.stack.enter_context(SerialDaq(cls.address(settings), settings["channels"],
                                                  settings["rate_hz"]))
        return DaqStream(daq, settings["name"], lockstep=links.cfg["clock"] == "lockstep")


class ExciterDevice(Device):
    """The tool-tip exciters' CiA 401 I/O module, node ``node_id`` on the drives' CAN
    network, checked and started; the runner's `ExciterOutputs`."""

    name = "exciter"
    schema = {"node_id": Field(int, 10, "CANopen node id of the CiA 401 I/O module (a "
                               "tool-tip [experiment] gives its io_node_id)", positive)}
    old_keys = {"io_node_id": "node_id"}

    @classmethod
    def open(cls, settings: Mapping[str, Any], links: DeviceLinks) -> CycleDevice:
        from feedbench.drivers.io_module import IoModule

        io = IoModule(links.network, settings["node_id"])
        io.configure()
        return ExciterOutputs(io)


class ExciterOutputs:
    """The plan's exciter commands, sent every cycle through the CiA 401 I/O module
    (`drivers.io_module.IoModule`); a runner `CycleDevice`. Records the command sent as
    ``excitation`` (N). Outside the plan (enable, disable, safe stop) the outputs are zero.
    """

    channels = ("excitation",)
    units = {"excitation": "N"}
    streams: dict[str, StreamSpec] = {}

    def __init__(self, io) -> None:
        self.io = io
        self._commands = np.zeros(0)
        self._exciter: str | None = None
        self._value = 0.0

    def start(self, plan: Plan, recorder) -> None:
        self._commands = plan.concatenated("excitation")
        self._exciter = plan.exciter
        self.io.zero()

    def before_sync(self, index: int | None) -> None:
        value = float(self._commands[index]) if index is not None and self._exciter else 0.0
        if self._exciter == "hammer":
            self.io.set_force(cia401.HAMMER_LEVEL, value)
            self.io.set_digital(cia401.HAMMER_FIRE if value > 0.0 else 0)
        elif self._exciter is not None:
            self.io.set_force(cia401.EXCITER_CHANNELS[self._exciter], value)
        self.io.transmit()
        self._value = value

    def after_sync(self, cycle: int) -> tuple[float]:
        return (self._value,)

    def stop(self, recorder) -> None:
        """All outputs off."""
        self.io.zero()

    def safe_torque_off(self) -> str:
        """The drives' safe torque off through the module (`IoModule.safe_torque_off`)."""
        return self.io.safe_torque_off()
