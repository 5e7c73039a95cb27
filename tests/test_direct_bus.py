"""A simulated lockstep bench in one process delivers each CAN frame in its sender's thread
(`protocols.canbus.DirectVirtualBus`): the same frames and recordings as with receive
threads, without their hand-overs."""

from __future__ import annotations

import logging
import threading

import can
import h5py
import numpy as np
import pytest

from feedbench.protocols.canbus import DirectVirtualBus, LocalVirtualBus, open_bus
from feedbench.commands.demo import example_config
from feedbench.testing import virtual_channel


class Heard(can.Listener):
    """Keeps (thread ident, COB-ID) of every frame it gets; fails on `fail_on`."""

    def __init__(self, fail_on: int | None = None) -> None:
        self.frames: list[tuple[int, int]] = []
        self.fail_on = fail_on

    def on_message_received(self, msg: can.Message) -> None:
        self.frames.append((threading.get_ident(), msg.arbitration_id))
        if msg.arbitration_id == self.fail_on:
            raise ValueError("listener bug")


def test_a_direct_bus_hands_each_frame_to_its_listeners_as_it_is_sent(caplog):
    """Frames sent before `listen` reach the listeners first, in order; after it every frame
    reaches every listener in the sending thread before `send` returns, a failing listener is
    logged in one line and the next one still gets the frame; python-can's own `VirtualBus`
    on the channel still queues its copy, and its frames reach the listeners too."""
    channel = virtual_channel()
    direct = open_bus("virtual", channel, direct=True)
    sender = open_bus("virtual", channel)
    plain = can.Bus(interface="virtual", channel=channel)
    try:
        assert type(direct) is DirectVirtualBus and type(sender) is LocalVirtualBus
        sender.send(can.Message(arbitration_id=0x701, data=b"\x05", is_extended_id=False))
        first, second = Heard(fail_on=0x181), Heard()
        direct.listen([first, second])
        me = threading.get_ident()
        assert first.frames == second.frames == [(me, 0x701)]
        with caplog.at_level(logging.ERROR, logger="can.interfaces.virtual"):
            sender.send(can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False))
        assert second.frames[-1] == (me, 0x181)
        assert [r.getMessage() for r in caplog.records] == [
            "listener Heard failed on frame 0x181: ValueError: listener bug"]
        assert plain.recv(1.0).arbitration_id == 0x701 and plain.recv(1.0).arbitration_id == 0x181
        worker = threading.Thread(target=plain.send, args=(can.Message(
            arbitration_id=0x80, data=b"", is_extended_id=False),))
        worker.start()
        worker.join()
        assert second.frames[-1] == (worker.ident, 0x80)
    finally:
        for bus in (direct, sender, plain):
            bus.shutdown()


def _short_chirp() -> dict:
    raw = example_config("chirp")
    raw["experiment"].update(repetitions=1, duration_s=0.6, tail_s=0.2, settle_s=0.1,
                             f_start_Hz=20.0, f_stop_Hz=150.0)
    return raw


def _datasets(path: str) -> dict[str, np.ndarray]:
    found: dict[str, np.ndarray] = {}
    with h5py.File(path) as file:
        file.visititems(lambda name, item: found.__setitem__(name, item[()])
                        if isinstance(item, h5py.Dataset) and item.dtype.kind in "fiu"
                        else None)
    return found


def test_a_simulated_lockstep_bench_runs_its_cycle_in_the_ticking_thread(simulated_bench):
    """The host's SYNC runs the simulated drive's cycle, and the TPDOs it sends complete the
    host's set, all in the thread that ticks: no receive thread in between."""
    with simulated_bench.open(_short_chirp()) as bench:
        assert type(bench.network.bus) is DirectVirtualBus and bench.network.notifier is None
        assert type(bench.simulated.drive.network.bus) is DirectVirtualBus
        host, drive = Heard(), Heard()
        bench.network.subscribe(0x180 + bench.drive.node.id,
                                lambda *_: host.on_message_received(can.Message(
                                    arbitration_id=0x181)))
        bench.simulated.drive.network.subscribe(0x80, lambda *_: drive.on_message_received(
            can.Message(arbitration_id=0x80)))
        for _ in range(20):
            bench.clock.tick()
    me = threading.get_ident()
    assert host.frames == [(me, 0x181)] * 20 and drive.frames == [(me, 0x80)] * 20


def test_a_run_records_the_same_samples_in_one_thread_or_with_receive_threads(
        simulated_bench, tmp_path):
    """A chirp run on the simulated bench, once as `Bench` opens it (``one_thread``, the
    default) and once with ``one_thread = false`` (queues and receive threads on both sides,
    as the live window runs it): every numeric dataset of the two files equal, bit for bit
    (lockstep is deterministic; only the threads differ)."""
    direct = simulated_bench.run(_short_chirp())
    raw = _short_chirp()
    raw["bench"]["one_thread"] = False
    simulated_bench.directory = tmp_path / "queued"
    simulated_bench.directory.mkdir()
    queued = simulated_bench.run(raw)
    assert direct["status"] == queued["status"] == "complete"
    ours, theirs = _datasets(direct["file"]), _datasets(queued["file"])
    assert ours.keys() == theirs.keys() and len(ours) > 5
    for name in ours:
        np.testing.assert_array_equal(ours[name], theirs[name], err_msg=name)


def test_a_run_with_a_device_of_its_own_keeps_the_receive_threads(simulated_bench):
    """A run that needs a device besides the drive (the impact hammer's DAQ, on a serial
    line with its own reader thread) opens queued buses with receive threads: that thread
    would get the interpreter only when the cycle's thread is made to give it up."""
    with simulated_bench.open(example_config("impact_hammer")) as bench:
        assert type(bench.network.bus) is LocalVirtualBus and bench.network.notifier is not None
