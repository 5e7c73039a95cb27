"""Host side of the rack-and-pinion axis: the two drives' PDO maps and the axis controller.

The axis controller's objects (`protocols.rack_pinion`) answer on the master node; they
are written by SDO between bus cycles. Each node's TPDO 3 carries its motor encoder and
the linear scale, so the host records x_m, x_s and x_load synchronously with the
statusword, position, velocity and force of both drives.
"""

from __future__ import annotations

from feedbench.drivers.cia402 import Cia402Drive, DriveError, PdoConfig
from feedbench.protocols import rack_pinion as objects
from feedbench.protocols.cia402 import (
    CONTROLWORD, CYCLE_COUNTER, FORCE_ACTUAL, POSITION_ACTUAL, STATUSWORD, TARGET_POSITION,
    TARGET_VELOCITY, TORQUE_OFFSET, VELOCITY_ACTUAL, VELOCITY_OFFSET,
)

AXIS_PDOS = PdoConfig(
    rpdo={
        1: (CONTROLWORD, TARGET_POSITION, TORQUE_OFFSET),  # torque offset in ‰
        2: (TARGET_VELOCITY, VELOCITY_OFFSET),
    },
    tpdo={
        1: (STATUSWORD, POSITION_ACTUAL, CYCLE_COUNTER),  # position actual: the axis
        2: (VELOCITY_ACTUAL, FORCE_ACTUAL),  # motor velocity, motor force at the rack (mN)
        3: objects.AXIS_TPDO,  # motor encoder at the rack, linear scale (nm)
    },
)
"""PDO maps of both nodes: two full RPDOs per cycle (the mode of operation goes by SDO),
three TPDOs; 11 frames per bus cycle with the SYNC."""


class AxisController:
    """The master–slave coupling of the axis, set through the master node (SDO)."""

    def __init__(self, master: Cia402Drive) -> None:
        self.sdo = master.node.sdo

    def set_coupling(self, coupling: str) -> None:
        """``coupled`` (master–slave with preload), ``master`` or ``slave`` (alone)."""
        if coupling not in objects.COUPLINGS:
            raise DriveError(f"coupling must be one of {', '.join(objects.COUPLINGS)}, "
                             f"got {coupling!r}")
        self.sdo[objects.COUPLING].raw = objects.COUPLINGS[coupling]

    def set_preload(self, fraction: float) -> None:
        """Preload τ_p as a fraction of the motors' rated torque (0x2040 in ‰)."""
        self.sdo[objects.PRELOAD_LEVEL].raw = round(fraction * 1000)

    def set_weights(self, K_Tm: float, K_Ts: float) -> None:
        """Torque weighting factors of master and slave (Fig. 3.2)."""
        self.sdo[objects.WEIGHT_MASTER].raw = K_Tm
        self.sdo[objects.WEIGHT_SLAVE].raw = K_Ts

    def read(self) -> dict[str, float | str]:
        """Coupling, preload fraction and weighting factors as the drive holds them."""
        names = {code: name for name, code in objects.COUPLINGS.items()}
        return {"coupling": names[self.sdo[objects.COUPLING].raw],
                "preload": self.sdo[objects.PRELOAD_LEVEL].raw / 1000,
                "K_Tm": self.sdo[objects.WEIGHT_MASTER].raw,
                "K_Ts": self.sdo[objects.WEIGHT_SLAVE].raw}


def motor_position(drive: Cia402Drive) -> float:
    """The drive's motor encoder at the rack from its latest TPDO (m)."""
    return drive.latest(objects.MOTOR_POSITION) * 1e-9


def load_position(drive: Cia402Drive) -> float:
    """The linear scale from the drive's latest TPDO (m)."""
    return drive.latest(objects.LOAD_POSITION) * 1e-9
