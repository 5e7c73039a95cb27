"""Per-experiment results that build up while a run acquires (no Qt here).

Each result is a runner observer: from the cycle loop it only sorts incoming rows into the
plan's steps and accumulates (sums, copies of excited stretches) — O(block), nothing to
fit. The live window calls `view()` on its own timer; the fit or FRF is computed there, once
per completed step, and handed over as plain arrays (`ResultView`), so the window draws any
experiment the same way.

The registry `LIVE_RESULTS` maps an experiment name to its result class; a new experiment
family adds one class with ``@live_result("name")``. Present: ``friction_sweep`` (friction
point per measure step and the Andersson fit, Eq. 5.2), ``chirp`` (servo mobility FRF of the
sweeps so far, H1 with coherence), ``sine_stream`` (FRF point per frequency step with the R²
of its sine fits; its channel names wait for the sine-stream plan of issue 4). Slots still
open: ``hammer`` (FRF of the hits so far), ``smfe`` (spindle speed and force spectrogram).
"""

from __future__ import annotations

from bisect import bisect_right
from dataclasses import dataclass
from typing import Callable, Iterator, Sequence

import numpy as np

from feedbench.analysis.frf import estimate_frf
from feedbench.analysis.friction import FrictionFit, fit_andersson
from feedbench.analysis.sinefit import SineFit, fit_sine
from feedbench.experiments.chirp import mobility_extrema
from feedbench.experiments.plan import Plan, Segment
from feedbench.units import MM_PER_MIN

FRF_NPERSEG = 2048
"""Welch segment length of the live FRF, as `experiments.chirp.analyze_recording` uses."""

MOBILITY_BAND_HZ = (20.0, 150.0)
"""Band searched for the servo mobility's anti-resonance and resonance (as the analysis)."""

MIN_POINTS_PER_FIT = 5
"""Andersson has 4 parameters: fit a direction once it has one point more."""


@dataclass(frozen=True)
class Curve:
    """One named x/y series of a panel; `points` draws markers instead of a line."""

    name: str
    x: np.ndarray
    y: np.ndarray
    points: bool = False


@dataclass(frozen=True)
class Panel:
    """One plot of a result: axis labels (with units), log axes, its curves."""

    title: str
    x_label: str
    y_label: str
    curves: tuple[Curve, ...]
    log_x: bool = False
    log_y: bool = False
    y_range: tuple[float, float] | None = None


@dataclass(frozen=True)
class ResultView:
    """What the window draws for a result: panels plus a one-line summary."""

    title: str
    panels: tuple[Panel, ...]
    summary: str


class StepTracker:
    """Which plan step each bus cycle belongs to.

    Blocks reach observers every 50 cycles and may straddle a step boundary; the runner
    announces each step with the cycle it starts at, so rows are sorted by cycle.
    """

    def __init__(self) -> None:
        self.starts: list[int] = []
        self.steps: list[tuple[int, Segment]] = []

    def begin(self, index: int, segment: Segment, cycle: int) -> None:
        """A step starts at `cycle`."""
        self.starts.append(cycle)
        self.steps.append((index, segment))

    def split(self, cycles: np.ndarray) -> Iterator[tuple[int, Segment, slice]]:
        """(step index, step, row slice) of every step present in `cycles` (ascending)."""
        if not len(cycles) or not self.starts:
            return
        first = bisect_right(self.starts, int(cycles[0])) - 1
        for k in range(max(first, 0), len(self.starts)):
            lo = int(np.searchsorted(cycles, self.starts[k]))
            hi = (int(np.searchsorted(cycles, self.starts[k + 1]))
                  if k + 1 < len(self.starts) else len(cycles))
            if hi > lo:
                index, segment = self.steps[k]
                yield index, segment, slice(lo, hi)
            if hi >= len(cycles):
                return


class LiveResult:
    """Base of every building-up result: observer plumbing, per-step rows, cached view.

    Subclasses implement `collect` (cycle loop thread: cheap accumulation, bump `version`
    when something new is complete) and `build` (reader thread: fits, FRFs).
    """

    title = ""

    def __init__(self) -> None:
        self.version = 0
        self.cycle_s = 1e-3
        self.columns: dict[str, int] = {}
        self.steps = StepTracker()
        self._parts: dict[int, list[np.ndarray]] = {}
        self._cached: tuple[int, ResultView] | None = None

    def on_start(self, plan: Plan, channels: Sequence[str]) -> None:
        """Learn the cycle time and the column of each channel."""
        self.cycle_s = plan.cycle_s
        self.columns = {name: i for i, name in enumerate(channels)}

    def on_segment(self, index: int, segment: Segment, cycle: int) -> None:
        """Remember where the step starts."""
        self.steps.begin(index, segment, cycle)

    def on_block(self, cycles: np.ndarray, block: np.ndarray) -> None:
        """Hand each step's rows of the block to `collect`."""
        for index, segment, rows in self.steps.split(cycles):
            self.collect(index, segment, block[rows])

    def on_stop(self, status: str, reason: str) -> None:
        """Nothing to finish: only completed steps count."""

    def column(self, rows: np.ndarray, name: str) -> np.ndarray:
        """One channel of a block of rows."""
        return rows[:, self.columns[name]]

    def gather(self, index: int, segment: Segment, rows: np.ndarray,
               names: Sequence[str]) -> np.ndarray | None:
        """Collect channels `names` of a step's rows; the whole step (n × len(names)) once
        its last row arrived, else None."""
        parts = self._parts.setdefault(index, [])
        parts.append(rows[:, [self.columns[name] for name in names]].copy())
        if sum(len(p) for p in parts) < segment.n_cycles:
            return None
        del self._parts[index]
        return np.concatenate(parts)

    def collect(self, index: int, segment: Segment, rows: np.ndarray) -> None:
        """Accumulate the rows of one step (called from the cycle loop)."""
        raise NotImplementedError

    def build(self) -> ResultView:
        """The result from what is complete so far (called from the reader)."""
        raise NotImplementedError

    def view(self) -> ResultView:
        """The current result; rebuilt only when `version` changed."""
        version = self.version
        if self._cached is None or self._cached[0] != version:
            self._cached = (version, self.build())
        return self._cached[1]


LIVE_RESULTS: dict[str, type[LiveResult]] = {}


def live_result(name: str) -> Callable[[type[LiveResult]], type[LiveResult]]:
    """Class decorator: register the building-up result of experiment `name`."""

    def register(cls: type[LiveResult]) -> type[LiveResult]:
        LIVE_RESULTS[name] = cls
        return cls

    return register


def live_result_for(experiment: str) -> LiveResult | None:
    """A fresh result for `experiment`, or None if the family has none registered."""
    cls = LIVE_RESULTS.get(experiment)
    return cls() if cls else None


@live_result("friction_sweep")
class FrictionCurve(LiveResult):
    """Friction point (mean velocity, mean motor force) per completed measure step, and
    the Andersson fit, Eq. (5.2), of each direction once it has enough points."""

    title = "friction curve, Eq. (5.2)"

    def __init__(self) -> None:
        super().__init__()
        self._sums: dict[int, list[float]] = {}
        self.points: list[tuple[float, float]] = []

    def collect(self, index: int, segment: Segment, rows: np.ndarray) -> None:
        if segment.kind != "measure":
            return
        acc = self._sums.setdefault(index, [0, 0.0, 0.0])
        acc[0] += len(rows)
        acc[1] += float(self.column(rows, "velocity").sum())
        acc[2] += float(self.column(rows, "force").sum())
        if acc[0] == segment.n_cycles:
            self.points.append((acc[1] / acc[0], acc[2] / acc[0]))
            self.version += 1

    def build(self) -> ResultView:
        points = np.array(list(self.points)).reshape(-1, 2)
        v, force = points[:, 0], points[:, 1]
        curves = [Curve("measured", v / MM_PER_MIN, force, points=True)]
        notes = [f"{len(v)} points"]
        for name, side in (("positive", v > 0), ("negative", v < 0)):
            if side.sum() >= MIN_POINTS_PER_FIT:
                fit = fit_andersson(v[side], force[side])
                curves.append(_fitted_curve(name, fit, v[side]))
                notes.append(f"{name}: F_c {fit.params.F_c:.1f} N, F_s {fit.params.F_s:.1f} N, "
                             f"R² {fit.r_squared:.4f}")
        panel = Panel("friction force vs feed", "feed (mm/min)", "motor force (N)", tuple(curves))
        return ResultView(self.title, (panel,), "; ".join(notes))


def _fitted_curve(name: str, fit: FrictionFit, v: np.ndarray) -> Curve:
    """The fitted law of one direction over the range of its points (feed in mm/min)."""
    sign = np.sign(v[0])
    speed = np.linspace(np.abs(v).min(), np.abs(v).max(), 200)
    return Curve(f"fit {name}", sign * speed / MM_PER_MIN, sign * fit.params.force(speed))


@live_result("chirp")
class ChirpMobility(LiveResult):
    """Servo mobility motor force → motor velocity (H1, Welch) of the sweeps completed so
    far, with its coherence; anti-resonance f_t and resonance f_r (Eqs. 4.13, 4.14)."""

    title = "servo mobility of the sweeps so far"

    def __init__(self) -> None:
        super().__init__()
        self.sweeps: list[np.ndarray] = []

    def collect(self, index: int, segment: Segment, rows: np.ndarray) -> None:
        if segment.kind != "excite":
            return
        sweep = self.gather(index, segment, rows, ("force", "velocity"))
        if sweep is not None:
            self.sweeps.append(sweep - sweep.mean(axis=0))
            self.version += 1

    def build(self) -> ResultView:
        sweeps = list(self.sweeps)
        if not sweeps:
            return ResultView(self.title, _empty_frf_panels(), "waiting for the first sweep")
        force, velocity = np.concatenate(sweeps).T
        est = estimate_frf(force, velocity, 1.0 / self.cycle_s, nperseg=welch_length(len(force)))
        inside = (est.f >= MOBILITY_BAND_HZ[0]) & (est.f <= MOBILITY_BAND_HZ[1])
        panels = _frf_panels(est.f[inside], est.H1[inside], est.coherence[inside])
        summary = (f"{len(sweeps)} sweep{'s' if len(sweeps) > 1 else ''} "
                   f"({est.n_averages} Welch averages); {_extrema_text(est.f, est.H1)}"
                   f"min coherence {est.coherence[inside].min():.3f}")
        return ResultView(self.title, panels, summary)


def welch_length(n_samples: int) -> int:
    """Welch segment length: the analysis's, or a power of two short enough for at least
    three averages while little is recorded (one segment would make coherence 1 trivially)."""
    return int(min(FRF_NPERSEG, 2 ** np.floor(np.log2(max(n_samples // 2, 8)))))


def _extrema_text(f: np.ndarray, H: np.ndarray) -> str:
    """``f_t … Hz, f_r … Hz, `` or nothing while the resolution cannot separate them yet."""
    try:
        f_t, f_r = mobility_extrema(f, H, MOBILITY_BAND_HZ)
    except ValueError:
        return ""
    return f"f_t {f_t:.1f} Hz, f_r {f_r:.1f} Hz, "


def _frf_panels(f: np.ndarray, H: np.ndarray, coherence: np.ndarray) -> tuple[Panel, Panel]:
    """|H| in (m/s)/N and the coherence over frequency (Hz)."""
    return (
        Panel("|H1| motor velocity / motor force", "frequency (Hz)", "|H| ((m/s)/N)",
              (Curve("H1", f, np.abs(H)),), log_y=True),
        Panel("coherence", "frequency (Hz)", "γ²", (Curve("coherence", f, coherence),),
              y_range=(0.0, 1.05)),
    )


def _empty_frf_panels() -> tuple[Panel, Panel]:
    empty = np.zeros(0)
    return _frf_panels(empty, empty.astype(complex), empty)


@live_result("sine_stream")
class SineStreamFrf(LiveResult):
    """Stepped-sine FRF (Ch. 5.5.3) point by point: at each completed excite step a sine at
    the step's frequency is fitted to input and response; H = response / input phasor,
    with the smaller R² of the two fits as quality (Figs. 5.21, 5.22).

    The channel names, the info key of the step frequency and the settle periods left out
    of each fit are class attributes, for the sine-stream plan to match.
    """

    title = "sine-stream FRF point by point"
    INPUT = "force"
    RESPONSE = "velocity"
    FREQUENCY_KEY = "frequency_Hz"
    SETTLE_CYCLES = 1.0

    def __init__(self) -> None:
        super().__init__()
        self.steps_done: list[tuple[float, np.ndarray]] = []
        self.fits: list[tuple[SineFit, SineFit]] = []

    def collect(self, index: int, segment: Segment, rows: np.ndarray) -> None:
        if segment.kind != "excite" or self.FREQUENCY_KEY not in segment.info:
            return
        step = self.gather(index, segment, rows, (self.INPUT, self.RESPONSE))
        if step is not None:
            self.steps_done.append((float(segment.info[self.FREQUENCY_KEY]), step))
            self.version += 1

    def build(self) -> ResultView:
        fs = 1.0 / self.cycle_s
        for f, step in list(self.steps_done)[len(self.fits):]:
            self.fits.append((fit_sine(step[:, 0], fs, f, self.SETTLE_CYCLES),
                              fit_sine(step[:, 1], fs, f, self.SETTLE_CYCLES)))
        f = np.array([fin.frequency for fin, _ in self.fits])
        H = np.array([out.phasor / fin.phasor for fin, out in self.fits], dtype=complex)
        r2 = np.array([min(fin.r_squared, out.r_squared) for fin, out in self.fits])
        panels = (
            Panel("|H|", "frequency (Hz)", f"|H| ({self.RESPONSE} / {self.INPUT})",
                  (Curve("H", f, np.abs(H), points=True),), log_y=True),
            Panel("phase", "frequency (Hz)", "phase (°)",
                  (Curve("phase", f, np.degrees(np.angle(H)), points=True),)),
            Panel("R² of the sine fits", "frequency (Hz)", "R²",
                  (Curve("R²", f, r2, points=True),), y_range=(0.0, 1.05)),
        )
        summary = (f"{len(f)} points, min R² {r2.min():.4f}" if len(f)
                   else "waiting for the first frequency step")
        return ResultView(self.title, panels, summary)
