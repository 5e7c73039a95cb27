"""Several simulated CiA 402 drives on one CAN bus that share one simulated world.

A machine axis driven by two motors (the rack-and-pinion master and slave) is one world
behind two nodes. One canopen `Network` carries both `LocalNode`s and ONE SYNC consumer:
on each SYNC every drive first latches its RPDOs and advances its state machine
(`SimulatedCia402Drive.begin_cycle`, which hands its setpoints to its port of the world),
then the world steps once, then every drive publishes its actual values and sends its
TPDOs (`end_cycle`). So the world advances exactly one cycle per SYNC, with the setpoints
of the same cycle from all nodes, whatever order the frames came in. The drives share one
lock, so each drive's watchdog (`sim_backends.watchdog`) runs the whole bus's cycle when it
must ramp down without SYNC (once per cycle period, whichever drive asks).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Callable

import can
import canopen

from feedbench.protocols.canbus import connect
from feedbench.protocols.cia301 import SYNC_COB_ID
from feedbench.sim_backends.cia402_drive import DriveObjects, SimulatedCia402Drive
from feedbench.sim_backends.faults import NO_FAULTS, Faults


class SimulatedDriveBus:
    """Simulated drives on one network over `bus` (owned: `close()` shuts it down).

    `step_world()` advances the shared world by one bus cycle; it runs on the network's
    receive thread between the drives' latch and publish phases. `faults`: the drives'
    (`sim_backends.faults`).
    """

    def __init__(self, bus: can.BusABC, step_world: Callable[[], None],
                 faults: Faults = NO_FAULTS) -> None:
        self.network = canopen.Network(bus)
        self.faults = faults
        self.drives: list[SimulatedCia402Drive] = []
        self._step_world = step_world
        self.lock = threading.RLock()
        self._last_cycle = 0.0
        self.network.subscribe(SYNC_COB_ID, self._on_sync)
        connect(self.network)

    def add_drive(self, node_id: int, simulator, eds_path: Path | str | None = None,
                  objects: DriveObjects | None = None) -> SimulatedCia402Drive:
        """A drive node on this bus; `simulator` is its port of the shared world."""
        drive = SimulatedCia402Drive(self.network.bus, node_id, simulator, eds_path,
                                     network=self.network, objects=objects, lock=self.lock,
                                     free_run=self._free_run, faults=self.faults)
        self.drives.append(drive)
        return drive

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self.lock:
            for drive in self.drives:
                drive.sync_received()
            self._cycle()

    def _free_run(self) -> None:
        """A cycle without SYNC, at most one per cycle period of the wall clock."""
        now = time.monotonic()
        if now - self._last_cycle >= self.drives[0].watchdog.cycle_s:
            self._cycle()

    def _cycle(self) -> None:
        self._last_cycle = time.monotonic()
        try:
            for drive in self.drives:
                drive.begin_cycle()
            self._step_world()
            for drive in self.drives:
                drive.end_cycle()
        except Exception as error:  # every drive faults (EMCY), never a traceback
            for drive in self.drives:
                drive.world_fault(error)

    def close(self) -> None:
        """Stop every drive's heartbeat, the receive thread and the bus."""
        for drive in self.drives:
            drive.close()
        self.network.disconnect()
