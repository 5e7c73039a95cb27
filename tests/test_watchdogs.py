"""Watchdogs on both ends (issue 18.2) and CANopen conformance (18.6).

The simulated drive consumes the host's heartbeat (0x1016) in virtual time at each SYNC and,
while powered, on the wall clock (a dead host sends nothing); a loss is the CiA 402 fault
reaction (quick-stop ramp, then FAULT) with EMCY 0x8130 (SYNC loss: 0x8100). The host
consumes the drives' heartbeats. The SDO server aborts a sub-index a plain variable lacks;
the state machine answers SDO, NMT and asynchronous PDOs without SYNC (canopen's
BaseNode402 drives it); motion and synchronous TPDOs need SYNC.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from typing import Iterator

import can
import canopen
import pytest
from canopen.profiles.p402 import BaseNode402
from canopen.sdo import SdoAbortedError

from feedbench.daq.clock import LockstepClock, NodeLost
from feedbench.daq.recording import open_recording, read_summary
from feedbench.drivers.cia402 import Cia402Drive, decode_state
from feedbench.drivers.io_module import IoModule
from feedbench.protocols import cia301
from feedbench.protocols.canbus import open_bus, open_network
from feedbench.protocols.cia402 import (
    CONTROLWORD, CSV, FAULT, FAULT_REACTION, MODES_OF_OPERATION, MODES_OF_OPERATION_DISPLAY,
    OPERATION_ENABLED, PV, QUICK_STOP_DECELERATION, READY, STATUSWORD, SWITCH_ON_DISABLED,
)
from feedbench.sim_backends import eds
from feedbench.sim_backends.bench import start_simulated_axis
from feedbench.sim_backends.io_module import SimulatedIoModule
from sim_peer import start_sim
from test_cia402_conformance import map_event_driven, velocity_on_sync

NODE = 1
IO_NODE = 10
LATE_S = 0.5
"""Allowed lateness of a wall-clock detection behind its limit (the 20 ms poll, and threads
delayed on a loaded 2-core machine; ≤ 0.1 s in the runs of docs/canopen.md)."""
EARLY_S = 0.01
"""How much earlier than `dead` the host's last heartbeat may have left (s)."""


@contextmanager
def bench(channel: str, **configure) -> Iterator[tuple]:
    """Simulated drive, host driver configured (`configure` to `Cia402Drive.configure`),
    lockstep clock, and a listener for the EMCYs."""
    listener = can.Bus(interface="virtual", channel=channel)
    device = start_simulated_axis("virtual", channel, NODE)
    network = open_network("virtual", channel)
    try:
        drive = Cia402Drive(network, NODE, eds.packaged_eds_path())
        drive.configure(**configure)
        yield device, drive, network, listener
    finally:
        network.disconnect()
        device.close()
        listener.shutdown()


def emcy_codes(listener: can.BusABC, timeout_s: float) -> list[tuple[int, float]]:
    """(EMCY code, receive time.monotonic()) of node NODE's EMCYs within `timeout_s`."""
    found, deadline = [], time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        message = listener.recv(0.01)
        if message is not None and message.arbitration_id == 0x80 + NODE and message.data:
            found.append((int.from_bytes(message.data[:2], "little"), time.monotonic()))
    return found


def enabled_at(drive: Cia402Drive, clock: LockstepClock, velocity: float) -> None:
    drive.set_mode(CSV)
    drive.set_targets(velocity=velocity)
    drive.enable(clock.tick)
    for _ in range(50):
        clock.tick()


def test_a_host_heartbeat_older_than_the_consumer_time_in_virtual_time_faults_the_drive(
        can_channel):
    """SYNCs keep coming but the host's heartbeat stops (sent once, at tick 0): at the 1001st
    SYNC its age, 1001 × 1 ms, passes the 1000 ms consumer time: fault reaction with EMCY
    0x8130, the quick-stop ramp at 0x6085, then FAULT; the host's commands are ignored."""
    with bench(can_channel, consumer_ms=1000) as (device, drive, network, _):
        clock = LockstepClock(network, [drive], timeout_s=2.0, heartbeat_s=60.0)
        enabled_at(drive, clock, velocity=0.05)  # m/s
        while clock.cycle < 1000:
            clock.tick()
            assert drive.state == OPERATION_ENABLED
        clock.tick()
        assert (clock.cycle, drive.state) == (1001, FAULT_REACTION)
        ramp = [device.simulator.velocity]
        while drive.state == FAULT_REACTION:
            drive.enable_step()  # the host asks for operation: refused during the reaction
            clock.tick()
            ramp.append(device.simulator.velocity)
        assert drive.state == FAULT and drive.emcy_code == cia301.EMCY_HEARTBEAT
        assert device.values[0x603F] == cia301.EMCY_HEARTBEAT
    deceleration = device.values[QUICK_STOP_DECELERATION] * 1e-9  # m/s²: 2
    assert ramp[0] > 0.02 and abs(ramp[-1]) < 1e-4
    assert len(ramp) - 1 == pytest.approx(ramp[0] / deceleration / 1e-3, abs=3)



def test_a_dead_host_is_noticed_on_the_wall_clock_and_the_drive_ramps_down_alone(
        can_channel):
    """The host stops mid-motion (no SYNC, no heartbeat): after the 500 ms consumer time
    (+ the watchdog's poll and the machine's load) the drive sends EMCY 0x8130 and runs its own cycles down
    the quick-stop ramp to FAULT, the power stage off."""
    with bench(can_channel, consumer_ms=500) as (device, drive, network, listener):
        clock = LockstepClock(network, [drive], timeout_s=2.0)
        enabled_at(drive, clock, velocity=0.02)
        while listener.recv(0) is not None:
            pass
        dead = time.monotonic()
        [(code, when)] = emcy_codes(listener, 0.5 + LATE_S)
        assert code == cia301.EMCY_HEARTBEAT
        # the consumer counts from the host's last heartbeat, sent at one of the last
        # lockstep ticks, a few ms before `dead` (measured 0.9 ms early once)
        assert 0.5 - EARLY_S <= when - dead < 0.5 + LATE_S
        deadline = time.monotonic() + 1.0
        while device.state != FAULT and time.monotonic() < deadline:
            time.sleep(0.01)
        assert device.state == FAULT and not device.simulator.enabled
        assert abs(device.simulator.velocity) < 1e-5  # 0x606D: 10 µm/s
        assert decode_state(drive.node.sdo[STATUSWORD].raw) == FAULT


def test_sync_loss_after_the_configured_missed_syncs(can_channel):
    """0x2021 = 10 missed SYNCs of 1 ms (0x1006): EMCY 0x8100 10 ms (+ a poll) later."""
    with bench(can_channel, consumer_ms=60_000, sync_loss_cycles=10) as (
            device, drive, network, listener):
        clock = LockstepClock(network, [drive], timeout_s=2.0)
        enabled_at(drive, clock, velocity=0.0)
        while listener.recv(0) is not None:
            pass
        stopped = time.monotonic()
        [(code, when)] = emcy_codes(listener, 0.3)
    assert code == cia301.EMCY_COMMUNICATION and when - stopped < 0.01 + LATE_S


def test_the_host_stops_on_a_drive_heartbeat_lost(can_channel):
    """The drive's heartbeat (20 ms) stops while its TPDOs still come: the clock raises
    NodeLost "node 1 heartbeat lost" after 30 heartbeat times, once."""
    with bench(can_channel, heartbeat_ms=20) as (device, drive, network, _):
        clock = LockstepClock(network, [drive], timeout_s=2.0)
        for _ in range(64):
            clock.tick()
        device.node.nmt.stop_heartbeat()
        silent = time.monotonic()
        with pytest.raises(NodeLost, match="^node 1 heartbeat lost$"):
            while time.monotonic() - silent < 3.0:
                clock.tick()
        assert 0.58 <= time.monotonic() - silent < 0.6 + LATE_S  # 0.6 s after the last beat
        for _ in range(64):
            clock.tick()  # reported once: the safe stop can still tick


def test_the_io_module_zeroes_its_outputs_when_the_host_heartbeat_stops(can_channel):
    """The host's I/O module driver writes the module's consumer entry (3 s) at configure;
    outputs set and the host silent: after the consumer time every output is 0, EMCY."""
    device = start_simulated_axis("virtual", can_channel, NODE)
    network = open_network("virtual", can_channel)
    try:
        module = SimulatedIoModule(device.network, IO_NODE)
        host = IoModule(network, IO_NODE)
        host.configure()
        assert host.node.sdo.upload(cia301.CONSUMER_HEARTBEAT_TIME, 1) == (
            cia301.consumer_entry(cia301.HOST_NODE_ID, 3000).to_bytes(4, "little"))
        network.send_message(0x700 + cia301.HOST_NODE_ID, b"\x05")
        host.set_force(0, 100.0)
        host.transmit()
        silent = time.monotonic()
        time.sleep(0.05)
        assert module.analog[0] == 6553  # 100 N of 500 N full scale
        while module.analog[0] and time.monotonic() - silent < 3.0 + LATE_S:
            time.sleep(0.02)
        assert module.analog == [0, 0, 0, 0] and time.monotonic() - silent >= 2.9
    finally:
        network.disconnect()
        device.close()


def test_both_rack_and_pinion_drives_stop_one_world_when_the_host_dies(can_channel):
    """Master and slave on one bus (`drive_bus`), host gone mid-move: both fault with EMCY
    0x8130, and the shared world runs one cycle per 1 ms period while they ramp down (not one
    per drive), both power stages off and the world still afterwards."""
    from feedbench.axes.rack_pinion import AXIS_PDOS
    from feedbench.sim_backends.rack_pinion import (
        SimulatedRackPinionAxis, build_simulator, packaged_eds_path,
    )

    simulated = SimulatedRackPinionAxis(build_simulator({"bumper_mm": 0.0}, 1e-3), "virtual",
                                        can_channel)
    network = open_network("virtual", can_channel)
    try:
        drives = [Cia402Drive(network, node_id, packaged_eds_path(), AXIS_PDOS)
                  for node_id in (1, 2)]
        for drive in drives:
            drive.configure(consumer_ms=500)
        clock = LockstepClock(network, drives, timeout_s=2.0)
        for drive in drives:
            drive.set_mode(CSV)
            drive.enable(clock.tick)
        for _ in range(100):
            for drive in drives:
                drive.set_targets(velocity=0.01)
            clock.tick()
        world = simulated.world.simulator
        dead, cycles = time.monotonic(), world.cycle_count
        deadline = dead + 2.0
        while (any(d.state != FAULT for d in simulated.bus.drives)
               and time.monotonic() < deadline):
            time.sleep(0.01)
        elapsed = time.monotonic() - dead
        assert [d.state for d in simulated.bus.drives] == [FAULT, FAULT]
        assert [d.values[0x603F] for d in simulated.bus.drives] == [cia301.EMCY_HEARTBEAT] * 2
        assert world.cycle_count - cycles <= (elapsed - 0.5) / 1e-3 + 5
        assert not any(d.simulator.enabled for d in simulated.bus.drives)
        at_rest = world.cycle_count
        time.sleep(0.1)
        assert world.cycle_count == at_rest, "no cycles once both are in FAULT"
    finally:
        network.disconnect()
        simulated.close()


# -- conformance (18.6) ---------------------------------------------------------------------


def test_a_sub_index_a_plain_variable_lacks_is_aborted(can_channel):
    """0x06090011 for sub 1 of the statusword (read) and of the controlword (write), on the
    drive and on the I/O module; sub 0 and a record's sub-indices answer."""
    with bench(can_channel) as (device, drive, network, _):
        module = SimulatedIoModule(device.network, IO_NODE)
        io = network.add_node(IO_NODE, canopen.ObjectDictionary())
        for sdo, index in ((drive.node.sdo, STATUSWORD), (io.sdo, cia301.DEVICE_TYPE)):
            with pytest.raises(SdoAbortedError) as aborted:
                sdo.upload(index, 1)
            assert aborted.value.code == cia301.SDO_ABORT_NO_SUBINDEX
        with pytest.raises(SdoAbortedError) as aborted:
            drive.node.sdo.download(CONTROLWORD, 3, b"\x06\x00")
        assert aborted.value.code == cia301.SDO_ABORT_NO_SUBINDEX
        assert drive.node.sdo.upload(STATUSWORD, 0) == b"\x40\x02"
        assert drive.node.sdo[cia301.IDENTITY][2].raw == 0x402
        assert module.node.id == IO_NODE


def test_the_state_machine_answers_sdo_and_nmt_without_sync(can_channel):
    """No SYNC at all: controlword writes by SDO move the state machine at once (statusword
    read back by SDO), the mode display follows 0x6060, NMT commands are answered."""
    with bench(can_channel) as (device, drive, network, _):
        sdo = drive.node.sdo
        drive.node.nmt.state = "PRE-OPERATIONAL"
        drive.node.nmt.wait_for_heartbeat(1.0)
        assert drive.node.nmt.state == "PRE-OPERATIONAL"
        states = []
        for command in (0x06, 0x07, 0x0F, 0x02):
            sdo[CONTROLWORD].raw = command
            states.append(decode_state(sdo[STATUSWORD].raw))
        sdo[MODES_OF_OPERATION].raw = PV
        assert sdo[MODES_OF_OPERATION_DISPLAY].raw == PV
        assert device.values[0x2020] == 0, "no SYNC was processed"
    assert states == [READY, "SWITCHED ON", OPERATION_ENABLED, "QUICK STOP ACTIVE"]


def test_canopens_basenode402_drives_the_simulated_drive(can_channel):
    """canopen's BaseNode402 through its documented calls: state changes and the operation
    mode without any SYNC (controlword and mode by an event-driven RPDO, statusword by an
    event-driven TPDO), then profile velocity: 0x60FF by SDO, SYNCs from canopen's producer
    move the axis, the velocity actual value read from a synchronous TPDO reaches it."""
    device = start_simulated_axis("virtual", can_channel, NODE)
    network = open_network("virtual", can_channel)
    try:
        node = BaseNode402(NODE, str(eds.packaged_eds_path()))
        network.add_node(node)
        node.nmt.state = "PRE-OPERATIONAL"
        map_event_driven(node)
        node.setup_402_state_machine(read_pdos=False)
        node.nmt.state = "OPERATIONAL"
        node.state = "SWITCHED ON"
        node.op_mode = "PROFILED VELOCITY"
        node.state = "OPERATION ENABLED"
        assert device.values[0x2020] == 0, "no SYNC so far"
        assert node.sdo[MODES_OF_OPERATION_DISPLAY].raw == PV and node.state == OPERATION_ENABLED
        velocity = velocity_on_sync(node, device, network, 10_000_000)  # nm/s: 10 mm/s
        node.state = "SWITCH ON DISABLED"
        assert node.state == SWITCH_ON_DISABLED
    finally:
        network.disconnect()
        device.close()
    assert velocity == pytest.approx(10_000_000, rel=1e-3)  # 1 m/s² ramp: there in 10 ms, settled by 300


# -- the host killed mid-chirp, the simulated bench in its own process ---------------------


@pytest.fixture
def sim_process(tmp_path):
    process, info = start_sim(tmp_path)
    try:
        yield info
    finally:
        process.terminate()
        process.communicate(timeout=20)


def test_a_host_killed_mid_chirp_leaves_the_drive_stopped_and_the_run_readable(
        tmp_path, sim_process, capsys):
    """SIGKILL of `feedbench run` (chirp) against `feedbench sim`: the drive sends EMCY
    0x8130 within the consumer time (3 s, + `LATE_S`) of the kill and ends in FAULT with its
    power stage off; the recording reads back to its last flushed cycle and `feedbench runs`
    lists it crashed with that many samples, and marks the file crashed too."""
    from feedbench.commands.cli import main

    host, port = sim_process["socketcand"].split(":")
    config = tmp_path / "chirp.toml"
    config.write_text(
        f'[bench]\nsimulated = false\ninterface = "socketcand"\n'
        f'socketcand = "{sim_process["socketcand"]}"\nchannel = "{sim_process["channel"]}"\n'
        f'output_dir = "{tmp_path}"\n[experiment]\ntype = "chirp"\nrepetitions = 20\n')
    listener = open_bus("socketcand", sim_process["channel"], host=host, port=int(port))
    run = subprocess.Popen([sys.executable, "-m", "feedbench.commands.cli", "run", str(config)],
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while not _flushed(tmp_path, 3000) and time.monotonic() < deadline:
            assert run.poll() is None, run.stderr.read()
            time.sleep(0.05)
        while listener.recv(0) is not None:
            pass
        run.send_signal(signal.SIGKILL)
        killed = time.monotonic()
        run.wait(10)
        found = emcy_codes(listener, 3.0 + LATE_S)
    finally:
        listener.shutdown()
    assert [code for code, _ in found] == [cia301.EMCY_HEARTBEAT]
    assert found[0][1] - killed < 3.0 + LATE_S
    network = open_network("socketcand", sim_process["channel"], host=host, port=int(port))
    try:
        drive = Cia402Drive(network, NODE, eds.packaged_eds_path())
        assert decode_state(drive.node.sdo[STATUSWORD].raw) == FAULT
        assert drive.node.sdo[0x603F].raw == cia301.EMCY_HEARTBEAT
    finally:
        network.disconnect()
    assert main(["runs", "--dir", str(tmp_path), "--json"]) == 0
    [row] = json.loads(capsys.readouterr().out)["runs"]
    recording = open_recording(row["file"])
    assert recording.n_samples >= 3000 and recording.status == "crashed"
    assert (row["status"], row["n_samples"]) == ("crashed", recording.n_samples)


def _flushed(directory, at_least: int) -> bool:
    try:
        [path] = directory.glob("*.h5")
        return read_summary(path).n_samples >= at_least
    except Exception:  # no file yet, or between flushes
        return False
