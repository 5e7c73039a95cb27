"""What both ends of a link share (`feedbench.protocols`): one address parser, one CiA 402
object table."""

import io
import os
import shutil
import threading

import can
import canopen
import pytest
from canopen.objectdictionary import ODVariable
from canopen.objectdictionary.eds import export_eds
from canopen.profiles.p402 import State402

from feedbench.config import ConfigError
from feedbench.drivers.cia402 import PdoConfig, controlword_towards, decode_state
from feedbench.protocols import cia301, cia402
from feedbench.protocols.address import split_address
from feedbench.protocols.canbus import LocalVirtualBus, SendBatch, import_eds, open_bus
from feedbench.sim_backends import eds, rack_pinion


@pytest.mark.parametrize("address, expected", [
    ("10.0.0.2:5020", ("10.0.0.2", 5020)), ("localhost:0", ("localhost", 0)),
])
def test_a_host_reaches_host_and_port(address, expected):
    assert split_address(address, "bench.modbus") == expected


@pytest.mark.parametrize("address", ["", "10.0.0.2", ":5020", "10.0.0.2:x", "10.0.0.2:"])
def test_a_host_needs_both_and_the_error_names_the_field(address):
    with pytest.raises(ConfigError, match=rf"^bench\.modbus: expected host:port, got '{address}'$"):
        split_address(address, "bench.modbus")


@pytest.mark.parametrize("address, expected", [
    ("", ("127.0.0.1", 0)), ("0.0.0.0", ("0.0.0.0", 0)), (":29536", ("127.0.0.1", 29536)),
    ("127.0.0.1:5021", ("127.0.0.1", 5021)),
])
def test_a_listener_defaults_to_loopback_and_any_free_port(address, expected):
    assert split_address(address, "bench.socketcand", listen=True) == expected


def test_a_listener_refuses_a_port_that_is_no_number():
    with pytest.raises(ConfigError, match=r"^bench\.socketcand: expected host:port"):
        split_address("127.0.0.1:http", "bench.socketcand", listen=True)


def test_every_state_the_simulated_drive_reports_decodes_to_itself_on_the_host():
    """The device's statusword table against canopen's p402 masks the host decodes with."""
    assert len(cia402.STATE_BITS) == 7
    for state, bits in cia402.STATE_BITS.items():
        assert decode_state(bits | cia402.SW_REMOTE | cia402.SW_FOLLOWS_COMMAND) == state


def test_the_supported_modes_are_the_bits_of_the_mode_codes():
    assert cia402.MODES == (8, 9, 10)
    assert sum(cia402.mode_bit(mode) for mode in cia402.DRIVE_MODES) == cia402.SUPPORTED_MODES == 0x0384
    assert cia402.mode_bit(1) == 0x01 and cia402.mode_bit(0) == cia402.mode_bit(11) == 0


def test_the_command_words_are_canopens_and_the_device_decodes_each_to_itself():
    assert cia402.COMMANDS == {"DISABLE VOLTAGE": State402.CW_DISABLE_VOLTAGE,
                               "QUICK STOP": State402.CW_QUICK_STOP,
                               "SHUTDOWN": State402.CW_SHUTDOWN, "SWITCH ON": State402.CW_SWITCH_ON,
                               "ENABLE OPERATION": State402.CW_OPERATION_ENABLED}
    reset = State402.TRANSITIONTABLE[(cia402.FAULT, cia402.SWITCH_ON_DISABLED)]
    assert cia402.CW_FAULT_RESET == reset
    for command, word in cia402.COMMANDS.items():
        assert cia402.command_of(word) == cia402.command_of(word | cia402.CW_FAULT_RESET) == command


def test_each_step_the_host_takes_to_enable_leads_the_device_there():
    """The host's path to operation enabled (canopen's p402 table, one controlword a cycle)
    walks the device's state machine from switch on disabled, one transition a step."""
    state, path = cia402.SWITCH_ON_DISABLED, []
    while state != cia402.OPERATION_ENABLED:
        state = cia402.TRANSITIONS[(state, cia402.command_of(
            controlword_towards(state, cia402.OPERATION_ENABLED)))]
        path.append(state)
    assert path == [cia402.READY, cia402.SWITCHED_ON, cia402.OPERATION_ENABLED]


COMMUNICATION_NAMES = {
    "DEVICE_TYPE": "Device type", "ERROR_REGISTER": "Error register",
    "CYCLE_PERIOD": "Communication cycle period", "HEARTBEAT_TIME": "Producer heartbeat time",
    "IDENTITY": "Identity object",
}
EDS_NAMES = {
    "ERROR_CODE": "Error code", "CONTROLWORD": "Controlword",
    "STATUSWORD": "Statusword", "QUICK_STOP_OPTION_CODE": "Quick stop option code",
    "MODES_OF_OPERATION": "Modes of operation",
    "MODES_OF_OPERATION_DISPLAY": "Modes of operation display",
    "POSITION_ACTUAL": "Position actual value", "FOLLOWING_ERROR_WINDOW": "Following error window",
    "VELOCITY_ACTUAL": "Velocity actual value", "VELOCITY_WINDOW": "Velocity window",
    "TARGET_TORQUE": "Target torque", "RATED_TORQUE": "Motor rated torque",
    "TORQUE_ACTUAL": "Torque actual value", "TARGET_POSITION": "Target position",
    "QUICK_STOP_DECELERATION": "Quick stop deceleration", "VELOCITY_OFFSET": "Velocity offset",
    "TORQUE_OFFSET": "Torque offset", "FOLLOWING_ERROR_ACTUAL": "Following error actual value",
    "TARGET_VELOCITY": "Target velocity", "SUPPORTED_DRIVE_MODES": "Supported drive modes",
    "FORCE_LIMIT": "Force limit", "FORCE_ACTUAL": "Force actual value",
    "FORCE_OFFSET_FINE": "Force offset fine", "CYCLE_COUNTER": "Cycle counter",
    "FAULT_INJECTION": "Fault injection",
}


def test_the_packaged_eds_holds_each_object_of_the_table_under_its_name():
    od = eds.load(3)
    assert {name: od[getattr(cia301, name)].name for name in COMMUNICATION_NAMES} \
        == COMMUNICATION_NAMES
    assert {name: od[getattr(cia402, name)].name for name in EDS_NAMES} == EDS_NAMES
    assert [od[index].name for index in cia402.GAIN_OBJECTS.values()] == [
        "Velocity loop gain K_p", "Velocity loop integral time T_i", "Position loop gain K_v"]
    assert od[cia301.DEVICE_TYPE].default == cia402.DEVICE_TYPE
    assert od[cia402.SUPPORTED_DRIVE_MODES].default == cia402.SUPPORTED_MODES
    assert od[cia402.MODES_OF_OPERATION].default == cia402.CSV
    assert od[cia301.TPDO_COMMUNICATION][cia301.PDO_TRANSMISSION_TYPE].default \
        == cia301.TRANSMISSION_SYNC
    assert od[cia301.RPDO_COMMUNICATION][cia301.PDO_COB_ID].default == cia301.RPDO_COB_BASE + 3


def test_the_host_maps_by_default_what_the_eds_maps():
    od = eds.load(3)
    for first_map, default in ((cia301.RPDO_MAPPING, PdoConfig().rpdo),
                               (cia301.TPDO_MAPPING, PdoConfig().tpdo)):
        for number, objects in default.items():
            record = od[first_map + number - 1]
            mapped = [record[sub].default >> 16 for sub in range(1, record[0].default + 1)]
            assert mapped == list(objects), number


@pytest.mark.parametrize("listen", [False, True])
def test_a_port_above_65535_names_the_field(listen):
    with pytest.raises(ConfigError, match=r"^bench\.modbus: port 70000 of '127.0.0.1:70000' is "
                                          r"above 65535$"):
        split_address("127.0.0.1:70000", "bench.modbus", listen=listen)


def test_the_local_virtual_bus_shares_python_cans_channels_and_copies_each_frame():
    """`open_bus("virtual")` (`LocalVirtualBus`) and python-can's own `VirtualBus` on one
    channel: each receives the other's frames, in order, as a copy of its own (a sender
    that reuses its buffer does not change a frame already sent), never its own frame."""
    local = open_bus("virtual", "test-local-virtual-bus")
    plain = can.Bus(interface="virtual", channel="test-local-virtual-bus")
    try:
        assert isinstance(local, LocalVirtualBus)
        data = bytearray(b"\x01\x02\x03")
        for n in range(3):
            data[0] = n
            local.send(can.Message(arbitration_id=0x181, data=data, is_extended_id=False))
        plain.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
        received = [plain.recv(1.0) for _ in range(3)]
        assert [bytes(m.data) for m in received] == [bytes([n, 2, 3]) for n in range(3)]
        assert all(m.is_rx and m.arbitration_id == 0x181 for m in received)
        assert plain.recv(0.01) is None
        sync = local.recv(1.0)
        assert sync.arbitration_id == 0x80 and local.recv(0.01) is None
    finally:
        local.shutdown()
        plain.shutdown()


def test_two_threads_batch_apart_and_flush_their_own_frames_in_order():
    """`SendBatch` is per thread: two threads inside their batches at once, their items
    interleaved in time, each flush gets exactly its own thread's items in the order sent;
    a thread outside a batch is not held, and a nested block leaves the flush to the outer."""
    flushed: list[tuple[str, list[int]]] = []
    batches = SendBatch(lambda items: flushed.append((threading.current_thread().name, items)))
    turn = threading.Barrier(2)

    def sender(offset: int) -> None:
        with batches.held():
            for k in range(5):
                turn.wait()
                assert batches.hold(offset + k)
                with batches.held():
                    assert batches.hold(offset + 100 + k)
            turn.wait()
        assert not batches.hold(offset)

    threads = [threading.Thread(target=sender, args=(o,), name=f"t{o}") for o in (0, 1000)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(flushed) == [(f"t{o}", [o + d + k for k in range(5) for d in (0, 100)])
                               for o in (0, 1000)]
    assert not batches.hold(7)


def test_a_batch_left_by_an_exception_flushes_what_was_sent_and_raises_it():
    """What a thread sent inside its batch counts as sent: an exception leaving the block
    flushes it, then goes on; the thread's next item is not held."""
    flushed: list[list[int]] = []
    batches = SendBatch(flushed.append)
    with pytest.raises(KeyError, match="boom"):
        with batches.held():
            assert batches.hold(1) and batches.hold(2)
            raise KeyError("boom")
    assert flushed == [[1, 2]]
    assert not batches.hold(3)


def _eds_text(od) -> str:
    """An object dictionary written as EDS text (canopen's exporter, fixed file info)."""
    stream = io.StringIO()
    export_eds(od, stream, file_info={"CreationDate": "01-01-2025", "CreationTime": "12:00PM",
                                      "ModificationDate": "01-01-2025",
                                      "ModificationTime": "12:00PM"})
    return stream.getvalue()


@pytest.mark.parametrize("path", [eds.packaged_eds_path(), rack_pinion.packaged_eds_path()],
                         ids=["lab", "rack_pinion"])
def test_an_eds_read_again_is_canopens_parse_in_objects_of_its_own(path):
    """`import_eds` gives what `canopen.import_od` gives (every entry, COB-IDs resolved for
    the node), each call its own objects: a change to one drive's dictionary is nobody
    else's."""
    first, again = import_eds(path, 5), import_eds(path, 5)
    assert _eds_text(first) == _eds_text(again) == _eds_text(canopen.import_od(str(path), 5))
    assert first.node_id == canopen.import_od(str(path), 5).node_id
    assert all(sub.parent is entry for entry in first.values()
               if not isinstance(entry, ODVariable) for sub in entry.values())
    assert all(first.names[entry.name] is first.indices[entry.index] for entry in first.values())
    assert first is not again and first[cia402.CONTROLWORD] is not again[cia402.CONTROLWORD]
    first[cia402.CONTROLWORD].default = 0x1234
    assert import_eds(path, 5)[cia402.CONTROLWORD].default != 0x1234
    assert _eds_text(import_eds(path, 6)) == _eds_text(canopen.import_od(str(path), 6))


def test_an_eds_file_changed_on_disk_is_read_anew(tmp_path, monkeypatch):
    """A file edited in place is parsed again, even to the same size with its modification
    time put back (a DCF value changed within the file system's time resolution); a
    relative path is the file it names from where it was given; a missing file is the
    error `canopen.import_od` raises."""
    path = tmp_path / "drive.eds"
    shutil.copy(eds.packaged_eds_path(), path)
    monkeypatch.chdir(tmp_path)
    assert import_eds("drive.eds", 1)["Statusword"].name == "Statusword"
    stat = path.stat()
    path.write_text(path.read_text().replace("ParameterName=Statusword",
                                             "ParameterName=StatusWord"))
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert path.stat().st_size == stat.st_size
    assert "StatusWord" in import_eds("drive.eds", 1).names
    other = tmp_path / "elsewhere"
    other.mkdir()
    shutil.copy(eds.packaged_eds_path(), other / "drive.eds")
    monkeypatch.chdir(other)
    assert "Statusword" in import_eds("drive.eds", 1).names
    path.unlink()
    with pytest.raises(FileNotFoundError, match="drive.eds"):
        import_eds(path, 1)
