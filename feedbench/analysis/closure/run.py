"""The whole closure on traces: split or pair them, diagnose, replay before and after."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from feedbench.analysis.closure.diagnosis import ClosureResult, close_the_loop
from feedbench.analysis.closure.model import predict
from feedbench.analysis.closure.replay import Replay, ReplayErrors, replay, replay_errors
from feedbench.analysis.closure.spec import ControllerSpec, ModelSpec
from feedbench.analysis.closure.trace import (
    Kinematics, Trace, edge_samples, kinematics, standstill_speed,
)

DEFAULT_BANDWIDTH_FRACTION = 0.1
"""Derivative filter cut-off as a fraction of the sample rate when the config gives none."""


@dataclass(frozen=True)
class Judged:
    """The held-out data: its trace, the trace samples judged, its kinematics."""

    trace: Trace
    start: int
    stop: int
    kin: Kinematics


@dataclass(frozen=True)
class ClosureReport:
    """Everything the text, JSON and plots show.

    bandwidth (Hz) and standstill (m/s): the filter and the speed below which samples are
    not used; fit_source / holdout_source: where the fit and the judgement came from;
    replay_before / replay_after: the closed-loop replay errors on the held-out data (None
    without a controller or a reference); replays: the replayed channels.
    """

    name: str
    fit_source: str
    holdout_source: str
    bandwidth: float
    standstill: float
    result: ClosureResult
    holdout: Judged
    replay_before: ReplayErrors | None
    replay_after: ReplayErrors | None
    replays: tuple[Replay, Replay] | None

    @property
    def rotary(self) -> bool:
        """Whether the axis turns: the units the report names are the rotary ones."""
        return self.holdout.trace.rotary

    def held_out_residuals(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sample times (s, from the held-out start) and force residuals (N) of the base and
        the final model on the used held-out samples."""
        kin = self.holdout.kin
        rows = kin.rows
        before = kin.force - predict(self.result.base.model, kin).reading
        after = kin.force - predict(self.result.final.model, kin).reading
        return rows * kin.dt, before[rows], after[rows]


def run_closure(spec: ModelSpec, trace: Trace, validation: Trace | None = None) -> ClosureReport:
    """Fit `spec`'s model on `trace`, judge on `validation` (or on the trace's last
    `holdout_fraction`), add effects while significant, replay before and after."""
    if validation is not None and validation.rotary != trace.rotary:
        raise ValueError(f"{validation.name or 'the validation trace'}: "
                         f"{_axis(validation)}, but {trace.name or 'the trace'} is "
                         f"{_axis(trace)}: both must be of one axis (the position unit "
                         "of each recording's sidecar or import mapping decides: an angle, "
                         "rad or deg, is a rotary axis; a KUKA joint is rotary)")
    bandwidth = spec.bandwidth or DEFAULT_BANDWIDTH_FRACTION * trace.sample_rate
    standstill = standstill_speed(kinematics(trace, bandwidth), spec.standstill)
    fit_kin, judged = _fit_and_judged(trace, validation, bandwidth, standstill,
                                      spec.holdout_fraction)
    result = close_the_loop(spec.model, fit_kin, judged.kin, spec.options)
    replays = _replays(spec, judged.trace, result)
    errors = (None, None) if replays is None else tuple(
        replay_errors(judged.trace, r, bandwidth, judged.start, judged.stop) for r in replays)
    holdout_source = (validation.name if validation is not None
                      else f"{trace.name} (last {spec.holdout_fraction:.0%})")
    return ClosureReport(spec.model.name, trace.name, holdout_source, bandwidth, standstill,
                         result, judged, errors[0], errors[1], replays)


def _axis(trace: Trace) -> str:
    """What kind of axis a trace records (for a message)."""
    return "rotary (rad)" if trace.rotary else "linear (m)"


def _fit_and_judged(trace: Trace, validation: Trace | None, bandwidth: float,
                    standstill: float, holdout_fraction: float) -> tuple[Kinematics, Judged]:
    """Fit kinematics and the judged part: a second recording, or the trace's end."""
    if validation is not None:
        held = kinematics(validation, bandwidth, standstill)
        return kinematics(trace, bandwidth, standstill), Judged(validation, 0,
                                                                validation.n_samples, held)
    kin = kinematics(trace, bandwidth, standstill)
    edge = edge_samples(bandwidth, 1.0 / trace.sample_rate)
    cut = int(round(kin.n * (1.0 - holdout_fraction)))
    if not 4 * edge < cut < kin.n - 4 * edge:
        raise ValueError(f"{trace.name or 'trace'}: too short to hold out "
                         f"{holdout_fraction:.0%} at a {bandwidth:g} Hz bandwidth")
    held = kin.window(cut + edge, kin.n)
    return kin.window(0, cut - edge), Judged(trace, edge + cut + edge, trace.n_samples, held)


def _replays(spec: ModelSpec, trace: Trace, result: ClosureResult) -> tuple[Replay, Replay] | None:
    """Replays of the base and the final model on the judged trace, when possible."""
    if spec.controller is None or trace.reference is None:
        return None
    return (replay(trace, result.base.model, spec.controller),
            replay(trace, result.final.model, recalibrated_controller(spec.controller, result)))


def recalibrated_controller(controller: ControllerSpec, result: ClosureResult) -> ControllerSpec:
    """The controller the final model is replayed with: the drive's force delay moved by as
    much as a recalibration moved the declared `delay` term (the two declare the same drive
    delay, s). A delay the search added as an effect is a lead of the force channel only,
    and leaves the drive's delay as declared."""
    if "delay.tau_ms" not in result.recalibrated:
        return controller
    moved = (result.final.model.term("delay").values["tau_ms"]
             - result.base.model.term("delay").values["tau_ms"])
    periods = max(round((controller.delay + moved) * controller.f_velocity), 0)
    return replace(controller, delay=periods / controller.f_velocity)
