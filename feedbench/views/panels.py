"""What the live window draws of a result, as plain data (no Qt here): panels of named
curves and colour maps with their axis labels and units, and a one-line summary. Each
experiment family builds its `ResultView` from the same analysis result the report draws
(`Experiment.live_view`); `feedbench.gui.live_window` lays any of them out the same way.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

OKABE_ITO = {"sky blue": "#56B4E9", "orange": "#E69F00", "bluish green": "#009E73",
             "reddish purple": "#CC79A7", "white": "#FFFFFF", "yellow": "#F0E442",
             "blue": "#0072B2", "vermillion": "#D55E00"}
"""The colour-blind-safe palette of Okabe and Ito (2008), as hex RGB, white in place of its
black (the live window's background is black); the most distinct hues first."""

FLAGGED = OKABE_ITO["vermillion"]
"""Points below a quality gate (and the watched limits)."""

PALETTE = tuple(c for c in OKABE_ITO.values() if c != FLAGGED)
"""Series colours in order, one hue per trace of a plot; the flagged colour is not among them."""


def series_color(index: int) -> str:
    """The colour of a plot's `index`-th series (0-based; repeats after `PALETTE`)."""
    return PALETTE[index % len(PALETTE)]


@dataclass(frozen=True)
class Curve:
    """One named x/y series of a panel; `points` draws markers instead of a line; `color`
    (a Qt colour name or hex RGB) overrides the panel's colour sequence (`series_color`)."""

    name: str
    x: np.ndarray
    y: np.ndarray
    points: bool = False
    color: str | None = None


@dataclass(frozen=True)
class Image:
    """A colour map over a panel: `z` (n_x × n_y) on a regular grid from (x0, y0) with
    steps (dx, dy), NaN where nothing is known; drawn between `levels` (low, high)."""

    z: np.ndarray
    x0: float
    dx: float
    y0: float
    dy: float
    levels: tuple[float, float]


@dataclass(frozen=True)
class Panel:
    """One plot of a result: axis labels (with units), log axes, its curves (drawn over
    its `image`, if any)."""

    title: str
    x_label: str
    y_label: str
    curves: tuple[Curve, ...]
    log_x: bool = False
    log_y: bool = False
    y_range: tuple[float, float] | None = None
    image: Image | None = None


def has_data(panel: Panel) -> bool:
    """True when the panel has a colour map or a curve with a finite point to draw."""
    return panel.image is not None or any(
        np.isfinite(np.asarray(c.y, dtype=float)).any() for c in panel.curves)


@dataclass(frozen=True)
class ResultView:
    """What the window draws for a result: panels plus a one-line summary."""

    title: str
    panels: tuple[Panel, ...]
    summary: str


def unwrapped_degrees(phase_rad: Sequence[float]) -> np.ndarray:
    """A phase (rad, in frequency order) in degrees, unwrapped over its finite values (NaN
    stays NaN and does not cut the unwrapping): how the report and the live window draw
    every phase."""
    phase = np.asarray(phase_rad, dtype=float)
    out = np.full(phase.shape, np.nan)
    finite = np.isfinite(phase)
    out[finite] = np.degrees(np.unwrap(phase[finite]))
    return out


def phase_panel(series: Mapping[str, tuple[Sequence[float], Sequence[float]]]) -> Panel:
    """The phase (°, `unwrapped_degrees`) of named FRFs, name → (f Hz, phase rad): the panel
    under a magnitude panel, so every live FRF is a Bode plot."""
    return Panel("phase", "frequency (Hz)", "phase (°)", tuple(
        Curve(name, np.asarray(f, dtype=float), unwrapped_degrees(phase))
        for name, (f, phase) in series.items()))


def point_frf_panels(series: Mapping[str, Sequence[tuple[float, complex, float]]],
                     magnitude_label: str, r_squared_min: float) -> tuple[Panel, ...]:
    """|H|, phase (unwrapped along each series' frequencies, `unwrapped_degrees`) and R² of
    FRF points (f Hz, H, R²) per named series; points below the R² gate, if any, are drawn
    again in the `FLAGGED` colour as their own series, at their series' phase."""
    magnitude, phase, quality = [], [], []
    rows = {name: _point_rows(points) for name, points in series.items()}
    below = [row for f, H, r2, deg in rows.values() for row in zip(f, H, r2, deg)
             if row[2] < r_squared_min]
    named = [(name, rows[name], None) for name in series]
    flagged = [(f"R² below {r_squared_min:g}", tuple(np.array(v) for v in zip(*below)),
                FLAGGED)] if below else []
    for name, (f, H, r2, degrees), color in [*named, *flagged]:
        magnitude.append(Curve(name, f, np.abs(H), True, color))
        phase.append(Curve(name, f, degrees, True, color))
        quality.append(Curve(name, f, r2, True, color))
    return (Panel("magnitude", "frequency (Hz)", magnitude_label, tuple(magnitude), log_y=True),
            Panel("phase", "frequency (Hz)", "phase (°)", tuple(phase)),
            Panel("R² of the sine fits", "frequency (Hz)", "R²", tuple(quality),
                  y_range=(0.0, 1.05)))


def _point_rows(points: Sequence[tuple[float, complex, float]]
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """FRF points (f Hz, H, R²) in frequency order as f, H, R² and the unwrapped phase (°)."""
    ordered = sorted(points, key=lambda point: point[0])
    f, H, r2 = (np.array(v) for v in zip(*ordered)) if ordered else (np.zeros(0),) * 3
    H = H.astype(complex)
    return f.astype(float), H, r2.astype(float), unwrapped_degrees(np.angle(H))
