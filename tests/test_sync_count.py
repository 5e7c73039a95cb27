"""Setpoints for counted SYNCs (issue 26 item 2, docs/realtime.md): `daq.clock.SyncSender`
puts each SYNC on the bus and counts it under one lock, so a frame sent under that lock
lands before SYNC `sent + 1` whatever the receiver's backlog; `engine.runner.SentTargets`
models the target the drive runs at each SYNC (sent, extrapolated, held)."""

from __future__ import annotations

import time

import can
import pytest

from feedbench.daq.clock import SyncSender, counts_syncs
from feedbench.engine.runner import SentTargets
from feedbench.protocols.canbus import LocalVirtualBus
from feedbench.protocols.cia301 import SYNC_COB_ID
from feedbench.protocols.cia402 import EXTRAPOLATED_CYCLES

MARK_ID = 0x201


def test_a_frame_sent_under_the_lock_lands_before_the_sync_it_was_counted_for(can_channel):
    """Sixty frames, each carrying `sent + 1` read under the lock, between SYNCs sent every
    millisecond by python-can's thread: the receiver, reading all of them late at once (a
    peer working through a backlog), finds each right after SYNC `sent` of its count."""
    sender_bus = LocalVirtualBus(channel=can_channel)
    peer = LocalVirtualBus(channel=can_channel)
    assert counts_syncs(sender_bus)
    sync = SyncSender(sender_bus, 1e-3)
    sync.start()
    try:
        for _ in range(60):
            with sync.lock:
                due = sync.sent + 1
                sender_bus.send(can.Message(arbitration_id=MARK_ID,
                                            data=due.to_bytes(4, "little"),
                                            is_extended_id=False))
            time.sleep(0.7e-3)
    finally:
        sync.stop()
        time.sleep(5e-3)
    syncs, checked = 0, 0
    while (msg := peer.recv(timeout=0.05)) is not None:
        if msg.arbitration_id == SYNC_COB_ID:
            syncs += 1
        elif msg.arbitration_id == MARK_ID:
            assert int.from_bytes(msg.data, "little") == syncs + 1
            checked += 1
    assert checked == 60 and syncs == sync.sent
    sender_bus.shutdown()
    peer.shutdown()


def test_the_count_goes_on_across_a_restart(can_channel):
    """After a stop and start (the stall watchdog's) the count goes on from where it was."""
    bus = LocalVirtualBus(channel=can_channel)
    sync = SyncSender(bus, 1e-3)
    sync.start()
    time.sleep(0.02)
    sync.stop()
    time.sleep(5e-3)
    before = sync.sent
    sync.start()
    time.sleep(0.02)
    sync.stop()
    assert before > 0 and sync.sent > before
    bus.shutdown()


def test_sent_targets_model_the_drive_at_each_sync():
    """Consecutive SYNCs: the step is the distance; after SYNCs without a setpoint the drive's
    step stays (0 once it held after `EXTRAPOLATED_CYCLES`); `at` gives the sent target,
    the extrapolation between, the hold at the start before the first."""
    sent = SentTargets(1.0)
    assert sent.unsent(7) == 0 and sent.at(3) == 1.0
    sent.sent(1.1, 10)
    sent.sent(1.3, 11)
    assert sent.step == pytest.approx(0.2)
    assert sent.unsent(12) == 0 and sent.unsent(11) == -1 and sent.unsent(15) == 3
    assert sent.behind(15) and not sent.behind(12)
    sent.due = 15
    assert not sent.behind(15)
    sent.sent(sent.extrapolated(4), 15)  # 3 SYNCs extrapolated at 0.2, then this one
    assert sent.step == pytest.approx(0.2) and sent.last == pytest.approx(2.1)
    assert sent.at(9) == 1.0 and sent.at(10) == 1.1 and sent.at(11) == 1.3
    assert sent.at(13) == pytest.approx(1.7) and sent.at(15) == pytest.approx(2.1)
    assert sent.at(15 + EXTRAPOLATED_CYCLES + 9) == pytest.approx(2.1 + EXTRAPOLATED_CYCLES * 0.2)
    sent.sent(9.0, 15 + EXTRAPOLATED_CYCLES + 2)  # it held before this one: step 0
    assert sent.step == 0.0
