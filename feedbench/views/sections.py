"""What a report section is made of: plots, tables, quality indicators, and the figure
helpers every experiment family draws its results with (matplotlib's Agg canvas: no pyplot
state, no display). `feedbench.report` assembles the sections; each family's
`Experiment.report` fills its own (`feedbench.engine.family`).
"""

from __future__ import annotations

import io
import textwrap
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Sequence

import numpy as np

from feedbench.views.panels import unwrapped_degrees

if TYPE_CHECKING:
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
    """A titled table: header and rows of text; `folded` ones open on a click (HTML
    ``<details>``)."""

    title: str
    header: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]
    folded: bool = False


@dataclass(frozen=True)
class Indicator:
    """One quality indicator; `ok` None means informative only; `details` are lines folded
    under the value (HTML ``<details>``)."""

    name: str
    value: str
    ok: bool | None = None
    details: tuple[str, ...] = ()


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



def frf_warnings(lines: Sequence[str], details: Sequence[str] = ()) -> Indicator:
    """The "FRF warnings" indicator: one line per distinct finding in the excited band
    (`analysis.frf.findings_in_band`), the per-resonance details folded under them."""
    return Indicator("FRF warnings", "\n".join(lines) or "none", not lines, tuple(details))


# figures

def new_figure(width_in: float = 10.0, height_in: float = 4.0,
               layout: str = "constrained") -> MplFigure:
    """A matplotlib figure (width and height in inches, 100 dpi) on an Agg canvas (no pyplot
    global state), laid out by constrained layout; `layout` "column": a column of panels
    sharing x, with the figure's legends above it (`layout.ColumnLayout`, as constrained
    layout but faster)."""
    # matplotlib here: about 0.5 s to import, and a run, a sim or the CLI draw nothing
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure as MplFigure

    from feedbench.views.layout import ColumnLayout

    figure = MplFigure(figsize=(width_in, height_in), dpi=100,
                       layout=ColumnLayout() if layout == "column" else layout)
    FigureCanvasAgg(figure)
    return figure


LEGEND_BESIDE = (1.01, 1.0)
"""Where an axes legend beside its data is anchored by its upper left corner (axes
fraction): right of the axes, clear of a point on the axes' right edge."""


def png_of(figure: MplFigure) -> bytes:
    """The figure rendered as PNG bytes, no legend over its data: laid out (`lay_out`), laid
    out again only when `legends_off_the_data` moved a legend of the figure as laid out,
    then drawn once with that layout fixed (savefig with a layout engine draws twice: a
    hidden drawing to lay out, then the image)."""
    from matplotlib import rc_context

    lay_out(figure)
    if legends_off_the_data(figure):
        lay_out(figure)
    # no engine at all (a "none" placeholder engine still draws twice), whatever a
    # matplotlibrc's autolayout or constrained_layout.use would put in its place
    with rc_context({"figure.autolayout": False, "figure.constrained_layout.use": False}):
        figure.set_layout_engine(None)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png")
    return buffer.getvalue()


def lay_out(figure: MplFigure) -> None:
    """Place the figure's axes, legends and labels by its layout engine, if any
    (constrained layout: every label and tick label inside the figure), without drawing."""
    engine = figure.get_layout_engine()
    if engine is not None and figure.axes:
        engine.execute(figure)


def data_points(ax) -> np.ndarray:
    """Display coordinates (px, n × 2) of the finite points of an axes' lines and markers."""
    points = [np.zeros((0, 2))]
    for line in ax.get_lines():
        xy = np.column_stack([np.asarray(line.get_xdata(), dtype=float),
                              np.asarray(line.get_ydata(), dtype=float)])
        points.append(line.get_transform().transform(xy[np.isfinite(xy).all(axis=1)]))
    for collection in ax.collections:
        offsets = np.asarray(collection.get_offsets(), dtype=float).reshape(-1, 2)
        if len(offsets) > 1:  # a scatter's markers (a filled area has one offset)
            points.append(collection.get_offset_transform().transform(offsets))
    return np.concatenate(points)


def covers_data(ax, box) -> bool:
    """True when the display box (a legend's) lies over a data point, a colour map or a
    filled area of the axes."""
    areas = [*ax.images, *(c for c in ax.collections
                           if len(np.asarray(c.get_offsets()).reshape(-1, 2)) <= 1)]
    extents = [area.get_window_extent() for area in areas]
    if any(np.isfinite(e.extents).all() and e.overlaps(box) for e in extents):
        return True  # an empty area's extent is infinite, inverted: it "overlaps" everything
    x, y = data_points(ax).T
    return bool(np.any((x >= box.x0) & (x <= box.x1) & (y >= box.y0) & (y <= box.y1)))


def legends_off_the_data(figure: MplFigure) -> bool:
    """Every axes legend that lies over the axes' data in the figure as last laid out moves
    out, right of the axes (top aligned); the figure's layout makes room at the next layout
    and keeps the axes of a column aligned. Whether any legend moved."""
    renderer = figure.canvas.get_renderer()
    moved = False
    for ax in figure.axes:
        legend = ax.get_legend()
        if legend is not None and covers_data(ax, legend.get_window_extent(renderer)):
            legend.set_loc("upper left")
            legend.set_bbox_to_anchor(LEGEND_BESIDE, transform=ax.transAxes)
            moved = True
    return moved


@dataclass(frozen=True)
class FrfSeries:
    """One FRF of a figure: label, frequencies (Hz), |H|, its phase (rad) and its quality
    (coherence or R²)."""

    label: str
    f: np.ndarray
    magnitude: np.ndarray
    phase: np.ndarray
    quality: np.ndarray


QUALITY_LABEL_CHARS = 18
"""Characters per line of the quality panel's y label: a longer one, on the short panel,
ran over the phase panel's tick labels."""


def frf_figure(series: Sequence[FrfSeries], y_label: str, quality_label: str = "coherence γ²",
               gate: float = MIN_COHERENCE, points: bool = False,
               marks: Sequence[tuple[str, float]] = ()) -> MplFigure:
    """Bode plot: |H| (log), phase (°, unwrapped) and the quality per frequency, one colour
    per series, the gate dotted; `marks` (label, Hz) dashed through all three panels."""
    figure = new_figure(8.0, 7.0, layout="column")
    magnitude, phase, quality = figure.subplots(3, 1, sharex=True, height_ratios=(2, 1.2, 1))
    style = dict(marker="o", ms=3, lw=0.6) if points else dict(lw=1.2)
    for s in series:
        magnitude.semilogy(s.f, s.magnitude, label=s.label, **style)
        phase.plot(s.f, unwrapped_degrees(s.phase), **style)
        quality.plot(s.f, s.quality, **style)
    quality.axhline(gate, color="r", ls=":", lw=0.8)
    magnitude.set_ylabel(y_label)
    magnitude.grid(alpha=0.3, which="both")
    figure.legend(loc="outside upper center", ncols=min(len(series), 3), fontsize=8)
    phase.set_ylabel("phase (°)")
    phase.grid(alpha=0.3)
    quality.set_ylim(min(0.0, float(np.nanmin([s.quality.min(initial=1.0) for s in series]))),
                     1.05)
    quality.set_ylabel("\n".join(textwrap.wrap(quality_label, QUALITY_LABEL_CHARS)))
    quality.set_xlabel("frequency (Hz)")
    quality.grid(alpha=0.3)
    mark_frequencies((magnitude, phase, quality), marks)
    return figure


def mark_frequencies(axes: Sequence, marks: Sequence[tuple[str, float]]) -> None:
    """Dashed lines at `marks` (label, Hz) through `axes`, labelled above the first one in a
    boxed tag (outside the data, as the legends); each tag, in ascending frequency, on the
    lowest level (13 pt apart) where its box overlaps no box already there, as the axes
    stand before layout (which widens them: tags only move apart)."""
    tags = []
    for label, f_hz in sorted(marks, key=lambda m: m[1]):
        for ax in axes:
            ax.axvline(f_hz, color="k", ls="--", lw=0.8)
        tags.append(axes[0].annotate(
            label, (f_hz, 1.0), xycoords=("data", "axes fraction"), xytext=(0, 3),
            textcoords="offset points", ha="center", va="bottom", fontsize=8,
            bbox=dict(boxstyle="round,pad=0.2", fc="white", ec="0.6", alpha=0.9)))
    axes[0].get_xlim()  # autoscaled to the lines first, as drawn (marks beyond the data)
    figure = axes[0].figure
    gap = 5 * figure.dpi / 72  # two box pads (1.6 pt), their edges and some air (px)
    rights: list[float] = []  # per level, the right end of its last tag's text (px)
    for tag in tags:
        text = tag.get_window_extent(figure.canvas.get_renderer())
        level = next((n for n, right in enumerate(rights) if right + gap <= text.x0),
                     len(rights))
        rights[level:level + 1] = [text.x1]
        tag.xyann = (0, 3 + 13 * level)
