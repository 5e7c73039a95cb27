"""The FRFs of a result as other tools exchange them: each with its two ends (the recorded
channel, its node and direction, its quantity) and SI values. A family lists its own
(`Experiment.frfs`); `feedbench.commands.exchange` writes them as UFF58.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np


@dataclass(frozen=True)
class Dof:
    """One end of an FRF: the recorded channel, the UFF node and direction, the quantity."""

    channel: str
    entity: str
    node: int
    direction: int
    quantity: str


@dataclass(frozen=True)
class ExchangeFrf:
    """One FRF H = response / reference over f (Hz), SI units, with its coherence if any."""

    description: str
    condition: str
    f: np.ndarray
    H: np.ndarray
    response: Dof
    reference: Dof
    coherence: np.ndarray | None = None


MOTOR_FORCE = Dof("force", "motor", 1, 1, "force")
MOTOR_VELOCITY = Dof("velocity", "motor", 1, 1, "velocity")


def polar(block: Mapping[str, list], magnitude: str, phase: str) -> np.ndarray:
    """Complex values from an analysis result's magnitude and phase (rad) lists."""
    return np.asarray(block[magnitude]) * np.exp(1j * np.asarray(block[phase]))
