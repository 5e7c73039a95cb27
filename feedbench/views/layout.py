"""The layout of a column of panels sharing x (the report's key time traces, a Bode plot): what
constrained layout makes of it, measured once instead of twice. Imports matplotlib: imported
by `sections.new_figure` when a figure is drawn.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from matplotlib import rcParams
from matplotlib.figure import Figure
from matplotlib.layout_engine import LayoutEngine

LAYOUT_PAD_IN = 3 / 72
"""Space (in) around each panel's labels, tick labels and legend: constrained layout's."""

Reach = np.ndarray
"""How far each panel's labels, tick labels, legend and tags reach out of it (px; n × 4:
left, right, above, below)."""


class ColumnLayout(LayoutEngine):
    """The figure's axes, top to bottom, as a column sharing x (x tick labels and label under
    the last), with the figure's legends above it: `fit_column`."""

    _adjust_compatible = False
    _colorbar_gridspec = False

    def execute(self, fig: Figure) -> None:
        """Place the axes of `fig` (`fit_column`)."""
        fit_column(fig, fig.axes)


def fit_column(figure: Figure, axes: Sequence) -> None:
    """Lay out a column of panels sharing x (top to bottom; heights in their grid's ratios) as
    constrained layout does, in one measuring pass instead of its two: the panels placed as
    the fonts suggest (`guessed_reach`), measured (`column_reach`), placed by what they
    need; measured again only if the ticks the panels then get are not the ones measured
    (`tick_locations`)."""
    renderer = figure.canvas.get_renderer()
    for ax in axes[:-1]:
        ax.xaxis.set_in_layout(False)  # its tick labels are hidden (shared x)
    above = legends_reach(figure, renderer)
    reach, seen = guessed_reach(figure, len(axes)), None
    for _ in range(3):
        place_column(figure, axes, reach, above)
        ticks = tick_locations(axes)
        if ticks == seen:
            return
        reach, seen = column_reach(axes, renderer), ticks
    place_column(figure, axes, reach, above)


def guessed_reach(figure: Figure, n_panels: int) -> Reach:
    """What a column's panels reach out before measuring (px): the last one's x tick labels
    and label below it (three lines of the font, for the ticks and pads), nothing else."""
    reach = np.zeros((n_panels, 4))
    reach[-1, 3] = 3.0 * rcParams["font.size"] * figure.dpi / 72
    return reach


def legends_reach(figure: Figure, renderer) -> float:
    """How far down from the figure's top its own legends (above the column) reach (px)."""
    return max((figure.bbox.y1 - legend.get_window_extent(renderer).y0
                for legend in figure.legends), default=0.0)


def column_reach(axes: Sequence, renderer) -> Reach:
    """What each panel's labels, tick labels, tick marks, legend and tags reach out of it as
    placed (px). Its spines are left out of the measurement (each measures its axis' ticks
    again, for the tick marks: `tick_marks_reach`)."""
    reach = []
    for ax in axes:
        spines = set(ax.spines.values())
        box, panel = ax.get_tightbbox(renderer, for_layout_only=True, bbox_extra_artists=[
            a for a in ax.get_default_bbox_extra_artists() if a not in spines]), ax.bbox
        reach.append((panel.x0 - box.x0, box.x1 - panel.x1, box.y1 - panel.y1,
                      panel.y0 - box.y0))
    return np.maximum(np.array(reach), tick_marks_reach(axes))


def tick_marks_reach(axes: Sequence) -> Reach:
    """How far each panel's tick marks reach out of it (px): the y axis' left, the x axis'
    below."""
    return np.array([(ax.yaxis.get_tick_padding(), 0.0, 0.0, ax.xaxis.get_tick_padding())
                     for ax in axes]) * axes[0].figure.dpi / 72


def place_column(figure: Figure, axes: Sequence, reach: Reach, above: float = 0.0) -> None:
    """Place a column's panels, their heights in their grid's ratios, so what each reaches
    out (`Reach`, px) fits beside, between and around them with `LAYOUT_PAD_IN` around it,
    under `above` (px: the figure's legends)."""
    pad = LAYOUT_PAD_IN * figure.dpi
    width, height = figure.bbox.width, figure.bbox.height
    left, right = reach[:, 0].max() + pad, reach[:, 1].max() + pad
    gaps = np.concatenate([[above + (pad if above else 0.0) + reach[0, 2] + pad],
                           reach[:-1, 3] + reach[1:, 2] + 2 * pad])
    ratios = np.asarray(axes[0].get_subplotspec().get_gridspec().get_height_ratios())
    panels = (height - gaps.sum() - reach[-1, 3] - pad) * ratios / ratios.sum()
    tops = height - np.cumsum(gaps) - np.concatenate([[0.0], np.cumsum(panels[:-1])])
    for ax, y1, panel in zip(axes, tops, panels):
        ax.set_position([left / width, (y1 - panel) / height, (width - left - right) / width,
                         panel / height])


def tick_locations(axes: Sequence) -> tuple:
    """The major tick locations of a column's y axes and of its last x axis, as placed: the
    same ones, the same tick labels."""
    return (*(tuple(ax.yaxis.get_majorticklocs()) for ax in axes),
            tuple(axes[-1].xaxis.get_majorticklocs()))
