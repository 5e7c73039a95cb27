"""What a report section is made of: plots, tables, quality indicators, and the figure
helpers every experiment family draws its results with (matplotlib's Agg canvas: no pyplot
state, no display). `feedbench.report` assembles the sections; each family's
`Experiment.report` fills its own (`feedbench.experiments.family`).
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure as MplFigure

MIN_COHERENCE = 0.9
"""Coherence below this in the analysed band is flagged (Ch. 3.5.1)."""

MIN_R_SQUARED = 0.99
"""A friction fit with a lower R² is flagged."""

@dataclass(frozen=True)
class Plot:
    """A titled PNG image."""

    title: str
    png: bytes


@dataclass(frozen=True)
class Table:
    """A titled table: header and rows of text."""

    title: str
    header: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]


@dataclass(frozen=True)
class Indicator:
    """One quality indicator; `ok` None means informative only."""

    name: str
    value: str
    ok: bool | None = None


@dataclass
class RunSection:
    """Everything the report shows about one run."""

    run_id: str
    experiment: str
    status: str
    plots: list[Plot] = field(default_factory=list)
    tables: list[Table] = field(default_factory=list)
    quality: list[Indicator] = field(default_factory=list)
    headline: str = ""



# figures

def new_figure(width_in: float = 10.0, height_in: float = 4.0) -> MplFigure:
    """A matplotlib figure on an Agg canvas (no pyplot global state)."""
    figure = MplFigure(figsize=(width_in, height_in), dpi=100, layout="constrained")
    FigureCanvasAgg(figure)
    return figure


def png_of(figure: MplFigure) -> bytes:
    """The figure rendered as PNG bytes."""
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    return buffer.getvalue()


@dataclass(frozen=True)
class FrfSeries:
    """One FRF of a figure: label, frequencies (Hz), |H| and its quality (coherence or R²)."""

    label: str
    f: np.ndarray
    magnitude: np.ndarray
    quality: np.ndarray


def frf_figure(series: Sequence[FrfSeries], y_label: str, quality_label: str = "coherence γ²",
               gate: float = MIN_COHERENCE, points: bool = False) -> MplFigure:
    """|H| (log) above its quality per frequency, one colour per series, the gate dotted."""
    figure = new_figure(8.0, 5.5)
    magnitude, quality = figure.subplots(2, 1, sharex=True, height_ratios=(2, 1))
    style = dict(marker="o", ms=3, lw=0.6) if points else dict(lw=1.2)
    for s in series:
        magnitude.semilogy(s.f, s.magnitude, label=s.label, **style)
        quality.plot(s.f, s.quality, **style)
    quality.axhline(gate, color="r", ls=":", lw=0.8)
    magnitude.set_ylabel(y_label)
    magnitude.grid(alpha=0.3, which="both")
    magnitude.legend(fontsize=8)
    quality.set_ylim(min(0.0, float(np.nanmin([s.quality.min(initial=1.0) for s in series]))),
                     1.05)
    quality.set_ylabel(quality_label)
    quality.set_xlabel("frequency (Hz)")
    quality.grid(alpha=0.3)
    return figure
