"""Conformance as a real master sees it (issue 26, item 6): the simulated drive driven by
canopen's own `BaseNode402`, and a plain SDO client (frames written and read by hand on a
python-can bus) over every abort case of CiA 301 §7.2.4.3.17 that applies to the drive.

The cases and the sim's answers are listed in docs/canopen.md ("SDO aborts").
"""

from __future__ import annotations

import struct
import time
from contextlib import contextmanager
from typing import Iterator

import can
import pytest
from canopen.profiles.p402 import BaseNode402

from feedbench.daq.clock import LockstepClock
from feedbench.drivers.cia402 import decode_state
from feedbench.protocols.canbus import open_network
from feedbench.protocols.cia402 import (
    CONTROLWORD, CSP, CST, CSV, FAULT_REACTION_OPTION_CODE, MODES_OF_OPERATION, PV,
    QUICK_STOP_OPTION_CODE, STATUSWORD,
    TARGET_VELOCITY, VELOCITY_ACTUAL, VELOCITY_WINDOW,
)
from feedbench.sim_backends import eds
from feedbench.sim_backends.bench import start_simulated_axis
from feedbench.sim_backends.cia402_drive import SimulatedCia402Drive
from test_cia402_sim import enable, loopback

NODE = 4
SDO_RX, SDO_TX = 0x600 + NODE, 0x580 + NODE
ANSWER_S = 2.0
"""How long the plain client waits for an answer (s; the sim answers within milliseconds)."""


class PlainSdoClient:
    """Writes SDO request frames and reads the answers on its own python-can bus."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus

    def request(self, *data: int) -> bytes:
        """Send one 8-byte request (`data` padded with zeros); the server's answer."""
        self.bus.send(can.Message(arbitration_id=SDO_RX, is_extended_id=False,
                                  data=bytes(data) + bytes(8 - len(data))))
        deadline = time.monotonic() + ANSWER_S
        while time.monotonic() < deadline:
            message = self.bus.recv(0.05)
            if message is not None and message.arbitration_id == SDO_TX:
                return bytes(message.data)
        raise AssertionError(f"no SDO answer to {bytes(data).hex()}")

    def upload(self, index: int, subindex: int = 0) -> bytes:
        """Initiate upload (ccs 2)."""
        return self.request(0x40, index & 0xFF, index >> 8, subindex)

    def download(self, index: int, subindex: int, value: bytes) -> bytes:
        """Expedited download of `value` (1–4 bytes), size indicated."""
        command = 0x23 | (4 - len(value)) << 2
        return self.request(command, index & 0xFF, index >> 8, subindex, *value)


def abort_code(answer: bytes, index: int, subindex: int) -> int:
    """The abort code of `answer`, checked to be an abort for `index`:`subindex`."""
    command, answered_index, answered_sub, code = struct.unpack("<BHBL", answer)
    assert command == 0x80, f"not an abort: {answer.hex()}"
    assert (answered_index, answered_sub) == (index, subindex)
    return code


@contextmanager
def drive(channel: str) -> Iterator[tuple[SimulatedCia402Drive, PlainSdoClient]]:
    device = start_simulated_axis("virtual", channel, NODE)
    bus = can.Bus(interface="virtual", channel=channel)
    try:
        yield device, PlainSdoClient(bus)
    finally:
        bus.shutdown()
        device.close()


# (case, request as (index, sub, data) or raw frame, expected abort code)
ABORTS = [
    ("no object", ("up", 0x1234, 0), 0x06020000),
    ("no sub-index of a VAR", ("up", STATUSWORD, 1), 0x06090011),
    ("no sub-index of a record", ("up", 0x1018, 9), 0x06090011),
    ("write a read-only object", ("down", STATUSWORD, 0, b"\x06\x00"), 0x06010002),
    ("write a const object", ("down", 0x6007, 0, b"\x00\x00"), 0x06010002),
    ("read a write-only object", ("up", 0x2030, 0), 0x06010001),
    ("value above HighLimit", ("down", QUICK_STOP_OPTION_CODE, 0, b"\x09\x00"), 0x06090031),
    ("value below LowLimit", ("down", QUICK_STOP_OPTION_CODE, 0, b"\xff\xff"), 0x06090032),
    ("unsupported mode 1", ("down", MODES_OF_OPERATION, 0, b"\x01"), 0x06090030),
    ("unsupported mode 100", ("down", MODES_OF_OPERATION, 0, b"\x64"), 0x06090030),
    ("another bus cycle", ("down", 0x1006, 0, b"\xd0\x07\x00\x00"), 0x06090030),
    ("length too high", ("down", CONTROLWORD, 0, b"\x06\x00\x00\x00"), 0x06070012),
    ("length too low", ("down", CONTROLWORD, 0, b"\x06"), 0x06070013),
    ("mapping entry while the PDO is valid", ("down", 0x1A00, 1, b"\x20\x00\x41\x60"),
     0x06010000),
    ("mapping count while the PDO is valid", ("down", 0x1A00, 0, b"\x01"), 0x06010000),
]


@pytest.mark.parametrize("case, sdo_request, code", ABORTS, ids=[case for case, *_ in ABORTS])
def test_the_sim_aborts_as_cia301_requires(can_channel, case, sdo_request, code):
    with drive(can_channel) as (device, client):
        kind, index, subindex, *value = sdo_request
        answer = (client.upload(index, subindex) if kind == "up"
                  else client.download(index, subindex, *value))
        assert abort_code(answer, index, subindex) == code
        assert device.values[QUICK_STOP_OPTION_CODE] == 2, "a refused value is not stored"


def test_mapping_follows_the_cia301_procedure(can_channel):
    """PDO not valid, count 0, entries, count, valid again: each step answered; an entry
    while the count is not 0, an unmappable object and 65 bits are aborted."""
    with drive(can_channel) as (device, client):
        cob_id = 0x180 + NODE
        assert client.download(0x1800, 1, struct.pack("<L", cob_id | 0x80000000))[0] == 0x60
        assert abort_code(client.download(0x1A00, 1, struct.pack("<L", 0x60410010)),
                          0x1A00, 1) == 0x06010000  # the count is still 2
        assert client.download(0x1A00, 0, b"\x00")[0] == 0x60
        assert abort_code(client.download(0x1A00, 1, struct.pack("<L", 0x60650020)),
                          0x1A00, 1) == 0x06040041  # following error window: not mappable
        for sub, entry in enumerate((0x60410010, 0x606C0020, 0x607A0020), start=1):
            assert client.download(0x1A00, sub, struct.pack("<L", entry))[0] == 0x60
        assert abort_code(client.download(0x1A00, 0, b"\x03"), 0x1A00, 0) == 0x06040042
        assert client.download(0x1A00, 0, b"\x02")[0] == 0x60
        assert client.download(0x1800, 1, struct.pack("<L", cob_id))[0] == 0x60
        assert client.upload(0x1A00, 0)[4] == 2


def test_segmented_transfers_toggle_and_stray_segments(can_channel):
    """A segmented download of the controlword; a wrong toggle bit is aborted 0x05030000;
    a segment with no transfer open (never opened, after the last one, upload segment
    during a download) 0x05040001; so are block upload and block download."""
    with drive(can_channel) as (device, client):
        lo, hi = CONTROLWORD & 0xFF, CONTROLWORD >> 8
        assert client.request(0x21, lo, hi, 0, 2)[0] == 0x60  # initiate, size 2, segmented
        assert client.request(0x0B, 0x06, 0x00)[0] == 0x20  # toggle 0, 2 bytes, last
        assert device.state == "READY TO SWITCH ON"
        assert abort_code(client.request(0x00, 1, 2), 0, 0) == 0x05040001  # after the last
        assert abort_code(client.request(0x60), 0, 0) == 0x05040001  # none ever opened
        assert client.request(0x21, lo, hi, 0, 2)[0] == 0x60
        assert abort_code(client.request(0x60), 0, 0) == 0x05040001  # upload during download
        assert client.request(0x21, lo, hi, 0, 2)[0] == 0x60
        assert abort_code(client.request(0x1B, 0x07, 0x00), CONTROLWORD, 0) == 0x05030000
        assert device.state == "READY TO SWITCH ON", "the aborted transfer wrote nothing"
        assert abort_code(client.request(0xA4, lo, hi, 0, 16), CONTROLWORD, 0) == 0x05040001
        assert abort_code(client.request(0xC6, lo, hi, 0, 2), CONTROLWORD, 0) == 0x05040001
        assert abort_code(client.request(0xE0, 0x41, 0x60, 0), STATUSWORD, 0) == 0x05040001


def test_basenode402_walks_the_state_machine_and_modes_pdo_driven(can_channel):
    """canopen's master, controlword and mode in an event-driven RPDO, statusword and mode
    display in an event-driven TPDO: every state of the walk, quick stop with option code 6
    (stay in quick stop) and back to operation enabled (transition 16), the supported modes
    switched, an unsupported one refused by canopen's own check of 0x6502; then profile
    velocity moves the axis on canopen's SYNC."""
    device = start_simulated_axis("virtual", can_channel, NODE)
    network = open_network("virtual", can_channel)
    try:
        node = BaseNode402(NODE, str(eds.packaged_eds_path()))
        node.TIMEOUT_SWITCH_STATE_FINAL = node.TIMEOUT_SWITCH_STATE_SINGLE = 5.0
        node.TIMEOUT_SWITCH_OP_MODE = 5.0
        network.add_node(node)
        node.nmt.state = "PRE-OPERATIONAL"
        node.sdo[QUICK_STOP_OPTION_CODE].raw = 6
        map_event_driven(node)
        node.setup_402_state_machine(read_pdos=False)
        node.nmt.state = "OPERATIONAL"
        walked = []
        for state in ("READY TO SWITCH ON", "SWITCHED ON", "OPERATION ENABLED",
                      "QUICK STOP ACTIVE", "OPERATION ENABLED"):
            node.state = state
            walked.append(node.state)
        modes = []
        for mode in ("CYCLIC SYNCHRONOUS POSITION", "CYCLIC SYNCHRONOUS TORQUE",
                     "CYCLIC SYNCHRONOUS VELOCITY", "PROFILED VELOCITY"):
            node.op_mode = mode  # confirmed by the display in the TPDO, or a warning
            modes.append(node.sdo[0x6061].raw)  # canopen's getter takes two event-driven
            # TPDOs for a periodic one and waits for a third: the display read by SDO
        with pytest.raises(TypeError, match="not suppported"):
            node.op_mode = "PROFILED POSITION"
        velocity = velocity_on_sync(node, device, network, 5_000_000)  # nm/s: 5 mm/s
        node.state = "SWITCH ON DISABLED"
        walked.append(node.state)
    finally:
        network.disconnect()
        device.close()
    assert walked == ["READY TO SWITCH ON", "SWITCHED ON", "OPERATION ENABLED",
                      "QUICK STOP ACTIVE", "OPERATION ENABLED", "SWITCH ON DISABLED"]
    assert modes == [CSP, CST, CSV, PV]
    assert velocity == pytest.approx(5_000_000, rel=1e-3)


def velocity_on_sync(node: BaseNode402, device: SimulatedCia402Drive, network,
                     target: int) -> int:
    """Profile velocity 0x60FF = `target` (nm/s) by SDO, then canopen's SYNC producer at
    1 ms until the drive ran 300 cycles; the velocity actual of TPDO 2 (nm/s) then."""
    node.sdo[TARGET_VELOCITY].raw = target
    network.sync.start(1e-3)
    try:
        deadline = time.monotonic() + 10.0
        while device.values[0x2020] < 300 and time.monotonic() < deadline:
            node.tpdo[2].wait_for_reception(1.0)
        return node.tpdo[2]["Velocity actual value"].raw
    finally:
        network.sync.stop()


def map_event_driven(node: BaseNode402) -> None:
    """TPDO 1 statusword + mode display and RPDO 1 controlword + mode, event-driven (255);
    TPDO 2 velocity actual on SYNC; the other RPDOs off."""
    for pdo_map, entries, trans_type in (
            (node.tpdo[1], (STATUSWORD, 0x6061), 255), (node.tpdo[2], (VELOCITY_ACTUAL,), 1),
            (node.rpdo[1], (CONTROLWORD, MODES_OF_OPERATION), 255)):
        pdo_map.read()
        pdo_map.clear()
        for index in entries:
            pdo_map.add_variable(index)
        pdo_map.trans_type = trans_type
        pdo_map.enabled = True
        pdo_map.save()
    for number in (2, 3):
        node.rpdo[number].read()
        node.rpdo[number].enabled = False
        node.rpdo[number].save()


# -- quick-stop option codes (0x605A) as CiA 402 defines them ------------------------------

SLOWED = {0: None, 1: (10, 12), 2: (5, 9), 3: (3, 6), 4: (3, 6)}
"""Ramp of each 0x605A code 0–4 (5–8: as code − 4): cycles from 10 mm/s until |v| < 0.2 mm/s
(1 m/s² on 0x6084: 10 ms; 2 m/s² on 0x6085: 5 ms plus the velocity loop's lag; a zero
command at the force limit: the loop's lag); None: no ramp, the power stage off at once."""


def _slowed_after(velocities: list[float]) -> int:
    return next(n for n, v in enumerate(velocities) if abs(v) < 200e-6)


@pytest.mark.parametrize("option", range(9))
def test_quick_stop_option_codes(can_channel, option):
    """From 10 mm/s in CSV (velocity window 0x606D 60 µm/s): each 0x605A code ramps down as
    CiA 402 defines it; codes 0–4 then switch on disabled (0 at once, the axis coasting),
    5–8 stay in quick stop with the stop complete (bit 10) and go back to operation enabled
    on enable operation (transition 16)."""
    holds = option > 4
    with loopback(can_channel) as bench:
        enable(bench, CSV, velocity=0.0)
        bench.run(200, velocity=0.01)
        bench.drive.node.sdo[QUICK_STOP_OPTION_CODE].raw = option
        bench.drive.node.sdo[VELOCITY_WINDOW].raw = 60_000
        bench.drive.quick_stop()
        actuals = bench.run(60, velocity=0.01)
        states = [decode_state(a.statusword) for a in actuals]
        ramp = SLOWED[option - 4 if holds else option]
        if ramp is None:
            assert states[0] == "SWITCH ON DISABLED" and actuals[0].force == 0.0
        else:
            low, high = ramp
            assert low <= _slowed_after([a.velocity for a in actuals]) <= high
            assert states[0] == "QUICK STOP ACTIVE"
        assert states[-1] == ("QUICK STOP ACTIVE" if holds else "SWITCH ON DISABLED")
        if holds:
            assert bench.drive.statusword & 0x0400, "stop complete: target reached"
            bench.drive.enable_step()
            bench.clock.tick()
            assert bench.drive.state == "OPERATION ENABLED"


@pytest.mark.parametrize("reaction, ramp_s", [(0, None), (1, 0.05 / 1.0), (2, 0.05 / 2.0)])
def test_fault_reaction_option_codes(can_channel, reaction, ramp_s):
    """A lost host heartbeat (SYNCs go on, the heartbeat stops: at SYNC 1001 for 1000 ms)
    from 50 mm/s: 0x605E = 0 faults at once (power stage off), 1 ramps on 0x6084 (1 m/s²),
    2 on 0x6085 (2 m/s²), then FAULT."""
    with loopback(can_channel, configure=False) as bench:
        device, drive = bench.device, bench.drive
        drive.configure(consumer_ms=1000)
        drive.node.sdo[FAULT_REACTION_OPTION_CODE].raw = reaction
        clock = LockstepClock(drive.network, [drive], timeout_s=2.0, heartbeat_s=60.0)
        drive.set_mode(CSV)
        drive.set_targets(velocity=0.05)  # m/s
        drive.enable(clock.tick)
        while clock.cycle < 1001:
            clock.tick()
        ramp = [device.simulator.velocity]
        while drive.state == "FAULT REACTION ACTIVE":
            clock.tick()
            ramp.append(device.simulator.velocity)
        assert drive.state == "FAULT" and drive.emcy_code == 0x8130
    if ramp_s is None:
        assert len(ramp) == 1 and not device.simulator.enabled
    else:
        assert abs(ramp[-1]) < 1e-4
        assert len(ramp) - 1 == pytest.approx(ramp_s / 1e-3, abs=3)
