"""Start a simulated axis (CiA 402 drive + physics) on a bus channel; `close()` stops it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from feedbench.protocols.canbus import open_bus
from feedbench.models.axis import AxisSimulator
from feedbench.sim_backends.cia402_drive import SensorNoise, SimulatedCia402Drive
from feedbench.sim_backends.faults import NO_FAULTS, Faults


def start_simulated_axis(interface: str = "virtual", channel: str = "feedbench",
                         node_id: int = 1, simulator: AxisSimulator | None = None,
                         eds_path: Path | str | None = None,
                         noise: SensorNoise = SensorNoise(), faults: Faults = NO_FAULTS,
                         **bus_options: Any) -> SimulatedCia402Drive:
    """A simulated drive on its own python-can bus (`interface`, `channel`).

    `simulator` defaults to the laboratory bench (`AxisSimulator()`); the drive owns the
    bus and boots to NMT pre-operational with its heartbeat running. `faults`: what goes
    wrong, and when (`sim_backends.faults`).
    """
    bus = faults.bus(open_bus(interface, channel, **bus_options))
    try:
        return SimulatedCia402Drive(bus, node_id, simulator or AxisSimulator(), eds_path,
                                    noise=noise, faults=faults)
    except BaseException:
        bus.shutdown()
        raise
