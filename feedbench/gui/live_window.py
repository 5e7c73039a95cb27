"""The live window: scrolling traces, progress, limits, a building-up result, a Stop button.

The bench (or a replay) runs in a worker thread and feeds a `LiveStream` plus the
experiment family's `LiveAnalysis`; the window reads them on a Qt timer in the GUI thread. The cycle
loop never waits for the window: a slow window draws fewer frames, the recording keeps
every sample. The Stop button, Ctrl-C and closing the window ask the runner for its safe
stop (ramp down, disable, file marked aborted); after Ctrl-C or closing, the command ends
once the run has stopped, with the record line `feedbench run` prints.

``feedbench run CONFIG --live`` → `bench_session`; ``feedbench live RUN`` → `replay_session`.
"""

from __future__ import annotations

import html
import signal
import sys
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtWidgets

from feedbench.gui import require_display
from feedbench.daq.live import ROWS, Decimator, LiveFrame, LiveState, LiveStream
from feedbench.engine.limits import Limits
from feedbench.engine.replay import replay
from feedbench.engine.runner import StopRequest
from feedbench.engine.family import families
from feedbench.engine.incremental import LiveAnalysis
from feedbench.views.panels import FLAGGED, Curve, Image, Panel, ResultView, has_data, series_color
from feedbench.units import MM_PER_MIN, RPM


SPANS_S = (1.0, 2.0, 5.0, 10.0, 20.0, 60.0)
"""Window lengths offered (s of bench time); the stream holds the longest."""

STOP_REASON = "stop button in the live window"
CLOSED_REASON = "live window closed"
SIGINT_REASON = "interrupted by SIGINT"

LEFT_AXIS_PX = 80
"""Width of every plot's left axis (tick labels and the label), so that the view boxes of
a pane start at the same x and panels over the same frequency line up."""

STOP_STYLE = ("QPushButton{background:#c0392b;color:white;font-weight:bold;}"
              "QPushButton:disabled{background:#9a9a9a;color:#e0e0e0;}")
"""The Stop button: red while it can stop a run, grey once the run (or replay) is over."""


@dataclass(frozen=True)
class ChannelGroup:
    """Channels of one SI unit drawn in one plot, shown in `display_unit` (× `scale`).

    `limit`: the watched limit drawn as lines; `source`: ``rows`` (per-cycle channels),
    ``streams`` (the devices' high-rate streams, e.g. the DAQ) or ``any``.
    """

    title: str
    si_units: tuple[str, ...]
    display_unit: str
    scale: float
    limit: str = ""
    source: str = "any"


CHANNEL_GROUPS = (
    ChannelGroup("positions", ("m",), "mm", 1e3, "position"),
    ChannelGroup("velocities", ("m/s",), "mm/min", 1.0 / MM_PER_MIN, "velocity"),
    ChannelGroup("forces", ("N",), "N", 1.0, "force", "rows"),
    ChannelGroup("spindle speed", ("rad/s",), "rpm", 1.0 / RPM),
    ChannelGroup("DAQ forces", ("N",), "N", 1.0, source="streams"),
    ChannelGroup("accelerations", ("m/s²", "m/s^2"), "m/s²", 1.0),
)


def group_channels(units: Mapping[str, str],
                   streamed: Sequence[str] = ()) -> list[tuple[ChannelGroup, list[str]]]:
    """The groups that have channels, each with its channels in stream order; `streamed`
    names the channels that come from a high-rate stream."""
    out = []
    for group in CHANNEL_GROUPS:
        names = [name for name, unit in units.items() if unit in group.si_units
                 and group.source in ("any", "streams" if name in streamed else "rows")]
        if names:
            out.append((group, names))
    return out


def limit_lines(group: ChannelGroup, limits: Limits | None) -> tuple[float, ...]:
    """The watched limits of a group in its display unit (none for an unwatched group)."""
    if limits is None or not group.limit:
        return ()
    if group.limit == "position":
        return tuple(x * group.scale for x in limits.position)
    bound = getattr(limits, group.limit) * group.scale
    return (-bound, bound)


def headroom_text(channels: Mapping[str, np.ndarray], names: Sequence[str],
                  group: ChannelGroup, lines: tuple[float, ...]) -> str:
    """Peak |value| of the group in the frame (display unit; min/max keeps it), the channel
    holding it and the share of the limit of the channels the limit watches (the drives'
    own ``force``, ``master.force``, …; not a load cell or a command); channels without a
    reading in the frame (NaN: not read) are named, not averaged in."""
    peaks = {n: float(np.max(np.abs(y[np.isfinite(y)]))) for n in names
             if n in channels and np.isfinite(y := channels[n]).any()}
    if not peaks:
        return "no data yet"
    channel = max(peaks, key=peaks.__getitem__)
    peak = peaks[channel] * group.scale
    shown = f"{peak:.0f}" if peak >= 1e4 else f"{peak:.4g}"
    text = f"peak {shown} {group.display_unit}" + (f" ({channel})" if len(names) > 1 else "")
    watched = [n for n in peaks if n == group.limit or n.endswith("." + group.limit)]
    if lines and watched:
        share = 100.0 * max(peaks[n] for n in watched) * group.scale / max(map(abs, lines))
        text += (", " if channel in watched else "; drives at ") + f"{share:.0f} % of limit"
    silent = [n for n in names if n not in peaks]
    return text + (f"; no data: {', '.join(silent)}" if silent else "")


def add_legend(layout: pg.GraphicsLayoutWidget, plot: pg.PlotItem, row: int, col: int,
               columns: int = 1) -> pg.LegendItem:
    """The plot's legend in a layout cell of its own (`row`, `col`: beside or above the
    plot), never over the data; its entries in `columns` columns. Dark background, grey
    frame; the plot's named items are listed in it."""
    legend = pg.LegendItem(brush=pg.mkBrush(0, 0, 0, 200), pen=pg.mkPen("#808080"))
    legend.setSizePolicy(QtWidgets.QSizePolicy.Fixed, QtWidgets.QSizePolicy.Fixed)
    legend.setColumnCount(columns)
    layout.addItem(legend, row=row, col=col)
    layout.ci.layout.setAlignment(legend, QtCore.Qt.AlignTop | QtCore.Qt.AlignLeft)
    plot.legend = legend
    for item in plot.listDataItems():
        if item.name():
            legend.addItem(item, item.name())
    return legend


class LogAxis(pg.AxisItem):
    """pyqtgraph's axis with log labels that do not overlap (pyqtgraph labels 2× … 9× of
    every decade, one over another): the mantissas of `LABELLED` for the span shown, the
    other ticks drawn without a label."""

    LABELLED = ((0.5, tuple(range(1, 10))), (2.0, (1, 2, 5)), (np.inf, (1,)))
    """(shown span below this many decades, mantissas labelled), the first that applies."""

    def tickStrings(self, values: list[float], scale: float, spacing: float) -> list[str]:
        """Labels of one tick level; in log mode the minor level (`spacing` None) keeps
        only the labels of the `LABELLED` mantissas."""
        strings = super().tickStrings(values, scale, spacing)
        if not self.logMode or spacing is not None:
            return strings
        span = abs(self.range[1] - self.range[0])
        labelled = next(mantissas for below, mantissas in self.LABELLED if span < below)
        return [text if round(10 ** (v % 1.0)) in labelled else ""
                for v, text in zip(values, strings)]


def new_plot(layout: pg.GraphicsLayoutWidget, row: int, title: str | None = None) -> pg.PlotItem:
    """A plot in column 0 of `row` with `LogAxis` axes and a left axis `LEFT_AXIS_PX` wide."""
    plot = layout.addPlot(row=row, col=0, title=title, axisItems={
        side: LogAxis(side) for side in ("left", "bottom")})
    plot.getAxis("left").setWidth(LEFT_AXIS_PX)
    return plot


def label_axes(plot: pg.PlotItem, x_label: str, y_label: str) -> None:
    """Axis labels that carry their unit, e.g. ``frequency (Hz)``; pyqtgraph's SI-prefix
    rescaling (a ``(x0.001)`` against the unit) is off."""
    for side, text in (("bottom", x_label), ("left", y_label)):
        plot.setLabel(side, text)
        plot.getAxis(side).enableAutoSIPrefix(False)


def state_text(state: LiveState) -> str:
    """Run state for the window's header: experiment, status, step, time left."""
    if state.status == "idle":
        return "waiting for the run to start…"
    left = f"{state.bench_time_left_s:.1f} s bench time left"
    if np.isfinite(state.wall_time_left_s) and state.status == "running":
        left += f" (≈ {state.wall_time_left_s:.0f} s wall)"
    status = state.status + (f": {state.reason}" if state.reason else "")
    return (f"<b>{html.escape(state.experiment)}</b> — {html.escape(status)}<br>"
            f"{html.escape(state.step_text)}<br>{left}")


class Worker:
    """Runs `target` in a thread and keeps what it returned or raised."""

    def __init__(self, target: Callable[[], Any]) -> None:
        self.result: Any = None
        self.error: BaseException | None = None
        self._target = target
        self._thread = threading.Thread(target=self._run, name="feedbench-run", daemon=True)

    def _run(self) -> None:
        try:
            self.result = self._target()
        except BaseException as exc:  # handed to the GUI thread, re-raised by `wait`
            self.error = exc

    def start(self) -> None:
        """Start the thread."""
        self._thread.start()

    @property
    def alive(self) -> bool:
        """True while `target` runs."""
        return self._thread.is_alive()

    @property
    def done(self) -> bool:
        """True once `target` has returned or raised."""
        return self._thread.ident is not None and not self._thread.is_alive()

    def join(self, timeout: float | None = None) -> None:
        """Wait for the thread (at most `timeout` s)."""
        self._thread.join(timeout)

    def wait(self, stop: StopRequest) -> Any:
        """Join; Ctrl-C asks `stop` for the safe stop; re-raise the run's error."""
        while self.alive:
            try:
                self.join(0.2)
            except KeyboardInterrupt:
                stop.request(SIGINT_REASON)
        if self.error is not None:
            raise self.error
        return self.result


def sticky_range(shown: tuple[float, float] | None, low: float, high: float) -> tuple[float, float]:
    """A y range that holds still while the data stay inside and fill at least a third of it.

    Redrawing an axis costs more than redrawing the curves, so the range changes only when
    the data leave it or shrink well inside it; then it is reset with 10 % margins (a
    trace that is exactly zero gets ±1 of its unit, not ±1e-10 ticks).
    """
    if not np.isfinite(low) or not np.isfinite(high):
        return shown or (-1.0, 1.0)
    if shown is not None:
        lo, hi = shown
        if lo <= low and high <= hi and (high - low) >= (hi - lo) / 3:
            return shown
    margin = 0.1 * (high - low) or 0.1 * abs(high) or 1.0  # a flat zero trace: ±1 unit
    return low - margin, high + margin


class TracePlots:
    """One scrolling plot per channel group with limit lines and headroom.

    The x axis shows seconds before now (−span … 0), so it never has to be redrawn while
    the traces scroll; y ranges are sticky (see `sticky_range`).
    """

    TITLE_PERIOD_S = 0.25
    """Headroom titles change at most this often (a new title re-lays the plot out)."""

    def __init__(self, layout: pg.GraphicsLayoutWidget) -> None:
        self.layout = layout
        self.groups: list[tuple[ChannelGroup, list[str]]] = []
        self.plots: list[pg.PlotItem] = []
        self.curves: dict[str, pg.PlotDataItem] = {}
        self.lines: list[tuple[float, ...]] = []
        self.ranges: list[tuple[float, float] | None] = []
        self._title_time = 0.0

    def build(self, units: Mapping[str, str], limits: Limits | None, span_s: float,
              streamed: Sequence[str] = ()) -> None:
        """(Re)create the plots for the channels (`streamed`: those of high-rate streams)."""
        self.layout.clear()
        self.groups = group_channels(units, streamed)
        self.plots, self.curves, self.lines = [], {}, []
        for row, (group, names) in enumerate(self.groups):
            plot = new_plot(self.layout, row)
            label_axes(plot, "time before now (s)", f"{group.title} ({group.display_unit})")
            plot.showGrid(x=True, y=True, alpha=0.3)
            add_legend(self.layout, plot, row, col=1)
            plot.setMouseEnabled(x=False, y=True)
            if row < len(self.groups) - 1:
                plot.hideAxis("bottom")
            for side in ("left", "bottom"):
                # a cached pixmap: the axis text is drawn again only when its ticks change
                plot.getAxis(side).setCacheMode(QtWidgets.QGraphicsItem.DeviceCoordinateCache)
            if self.plots:
                plot.setXLink(self.plots[0])
            for i, name in enumerate(names):
                pen = pg.mkPen(series_color(i), width=1)
                self.curves[name] = plot.plot([], [], pen=pen, name=name, skipFiniteCheck=True)
            lines = limit_lines(group, limits)
            for y in lines:
                plot.addItem(pg.InfiniteLine(y, angle=0, pen=pg.mkPen(
                    FLAGGED, width=1, style=QtCore.Qt.DashLine)))
            self.plots.append(plot)
            self.lines.append(lines)
        self.ranges = [None] * len(self.plots)
        if self.plots:
            self.set_span(span_s)

    def set_span(self, span_s: float) -> None:
        """Show the last `span_s` seconds."""
        if self.plots:
            self.plots[0].setXRange(-span_s, 0.0, padding=0)

    def draw(self, frames: Sequence[LiveFrame], fit_limits: bool, now: float) -> None:
        """Put frames (the rows', each stream's) on the plots, newest sample at x = 0; a
        channel read only every few cycles (NaN between) is drawn connected over its readings."""
        t_end = max((f.t_end for f in frames if f.n_received), default=0.0)
        xs = {name: frame.t - t_end for frame in frames for name in frame.channels}
        channels = {name: y for frame in frames for name, y in frame.channels.items()}
        retitle = now - self._title_time >= self.TITLE_PERIOD_S
        for i, ((group, names), plot, lines) in enumerate(zip(self.groups, self.plots, self.lines)):
            ys = []
            for name in (n for n in names if n in channels):
                x, y = xs[name], channels[name] * group.scale
                read = np.isfinite(y)
                if not read.all():
                    x, y = x[read], y[read]
                self.curves[name].setData(x, y)
                ys.append(y)
            self._set_y_range(i, ys, lines if fit_limits else ())
            if retitle:
                plot.setTitle(f"{group.title} — {headroom_text(channels, names, group, lines)}",
                              size="9pt")
        if retitle:
            self._title_time = now

    def _set_y_range(self, i: int, ys: list[np.ndarray], lines: tuple[float, ...]) -> None:
        data = [y for y in ys if len(y)]
        low = min([float(y.min()) for y in data] + list(lines), default=np.nan)
        high = max([float(y.max()) for y in data] + list(lines), default=np.nan)
        shown = sticky_range(self.ranges[i], low, high)
        if shown != self.ranges[i]:
            self.ranges[i] = shown
            self.plots[i].setYRange(*shown, padding=0)


class ResultPlots:
    """The experiment's building-up result: one plot per panel and a summary line; a
    placeholder line instead of a panel without data yet (no empty 0–1 axes); a legend in
    the row above a panel once it has two series, unless one above names them all."""

    NO_RESULT = "the result is drawn here once a step has completed"
    LEGEND_COLUMNS = 3
    """Entries per row of a panel's legend (over the panel: the pane is narrow)."""

    def __init__(self, layout: pg.GraphicsLayoutWidget, summary: QtWidgets.QLabel) -> None:
        self.layout = layout
        self.summary = summary
        self.plots: list[pg.PlotItem | None] = []
        self.rows: list[int] = []
        self.placeholders: list[str] = []
        self.curves: list[dict[str, pg.PlotDataItem]] = []
        self.images: list[pg.ImageItem | None] = []
        self._shown: tuple[bool, ...] | None = None

    def draw(self, view: ResultView) -> None:
        """Update the plots of a result view (re-laid out when a panel gets its first data)."""
        shown = tuple(has_data(panel) for panel in view.panels)
        if shown != self._shown:
            self._create(view.panels, shown)
        for i, (plot, curves, panel) in enumerate(zip(self.plots, self.curves, view.panels)):
            if plot is None:
                continue
            if panel.image is not None:
                self._draw_image(i, plot, panel.image)
            if plot.legend is None and len(panel.curves) > 1 and not self.named_above(i, panel):
                # one series is named in the summary; more: a legend in the row above
                add_legend(self.layout, plot, self.rows[i] - 1, 0, self.LEGEND_COLUMNS)
            for curve in panel.curves:
                if curve.name not in curves:
                    curves[curve.name] = self._new_curve(plot, curve, len(curves))
                curves[curve.name].setData(curve.x, curve.y)
        self.summary.setText(f"<b>{view.title}</b>: {view.summary}")

    def named_above(self, i: int, panel: Panel) -> bool:
        """True when a legend over an earlier panel lists every curve of panel `i` (the
        magnitude's legend names the phase's and the coherence's curves too)."""
        names = {curve.name for curve in panel.curves}
        return any(names <= {label.text for _, label in plot.legend.items}
                   for plot in self.plots[:i] if plot is not None and plot.legend is not None)

    def _draw_image(self, i: int, plot: pg.PlotItem, image: Image) -> None:
        """The colour map behind the panel's curves; unknown cells at the lowest level."""
        item = self.images[i]
        if item is None:
            item = self.images[i] = pg.ImageItem(colorMap=pg.colormap.get("viridis"))
            item.setZValue(-10)
            plot.addItem(item)
        z = np.nan_to_num(image.z, nan=image.levels[0])
        item.setImage(z, levels=image.levels, autoLevels=False)
        item.setRect(QtCore.QRectF(image.x0, image.y0, image.dx * z.shape[0],
                                   image.dy * z.shape[1]))

    def _create(self, panels: Sequence[Panel], shown: Sequence[bool]) -> None:
        """Lay out a plot per panel with data and a placeholder line per panel without."""
        self.layout.clear()
        self._shown = tuple(shown)
        self.plots, self.curves, self.images = [], [], [None] * len(panels)
        self.rows = [2 * i + 1 for i in range(len(panels))]  # 2 i: the panel's legend
        self.placeholders = [] if panels else [self.NO_RESULT]
        if not panels:
            self.layout.addLabel(self.NO_RESULT, row=0, col=0, color="#A0A0A0")
        for row, panel, data in zip(self.rows, panels, shown):
            self.curves.append({})
            if not data:
                text = f"{panel.title}: no data yet"
                self.layout.addLabel(text, row=row, col=0, color="#A0A0A0")
                self.placeholders.append(text)
                self.plots.append(None)
                continue
            plot = new_plot(self.layout, row, panel.title)
            label_axes(plot, panel.x_label, panel.y_label)
            plot.setLogMode(x=panel.log_x, y=panel.log_y)
            if panel.y_range is not None:
                plot.setYRange(*panel.y_range, padding=0)
            plot.showGrid(x=True, y=True, alpha=0.3)
            self._link_x(plot, panel, panels)
            self.plots.append(plot)

    def _link_x(self, plot: pg.PlotItem, panel: Panel, panels: Sequence[Panel]) -> None:
        """Share the x axis with the first plot drawn over the same x (label and log mode):
        magnitude, phase and coherence zoom and pan together."""
        same = next((other for other, p in zip(self.plots, panels) if other is not None
                     and (p.x_label, p.log_x) == (panel.x_label, panel.log_x)), None)
        if same is not None:
            plot.setXLink(same)

    @staticmethod
    def _new_curve(plot: pg.PlotItem, curve: Curve, index: int) -> pg.PlotDataItem:
        color = pg.mkColor(curve.color or series_color(index))
        if curve.points:
            return plot.plot([], [], pen=None, symbol="o", symbolSize=6, symbolBrush=color,
                             name=curve.name)
        return plot.plot([], [], pen=pg.mkPen(color, width=2), name=curve.name)


class LiveWindow(QtWidgets.QMainWindow):
    """Reads a `LiveStream` (and a `LiveAnalysis`) on a timer and draws them.

    `units` maps channel → SI unit (groups the traces), over what the stream learned from
    the runner (`LiveStream.units`: rows and DAQ streams); `limits` draws the watched limits;
    `stop` is the runner's `StopRequest` the Stop button uses; `worker` (optional) lets the
    window show a run that ended with an error. `fps` is the redraw timer's target rate.
    `frames` counts trace redraws (each with new data), `paints` the repaints Qt did.
    """

    def __init__(self, stream: LiveStream, units: Mapping[str, str], limits: Limits | None = None,
                 result: LiveAnalysis | None = None, stop: StopRequest | None = None,
                 worker: Worker | None = None, span_s: float = 10.0, fps: float = 60.0,
                 title: str = "feedbench live") -> None:
        super().__init__()
        self.stream, self.units, self.limits = stream, dict(units), limits
        self.result, self.stop, self.worker = result, stop, worker
        self.span_s = span_s
        self.frames = 0
        self.paints = 0
        self._seen: tuple = ((), ())
        self._decimators: dict[str, Decimator] = {}
        self._result_version = -1
        self.setWindowTitle(title)
        self.resize(1280, 800)
        self._build_widgets()
        self.timer = QtCore.QTimer(self)
        self.timer.setInterval(max(1, int(1000.0 / fps)))
        self.timer.timeout.connect(self.refresh)
        self.timer.start()

    # widgets
    def _build_widgets(self) -> None:
        central = QtWidgets.QWidget()
        outer = QtWidgets.QVBoxLayout(central)
        outer.addLayout(self._header())
        splitter = QtWidgets.QSplitter(QtCore.Qt.Horizontal)
        self.trace_view = pg.GraphicsLayoutWidget()
        self.trace_view.viewport().installEventFilter(self)
        self.traces = TracePlots(self.trace_view)
        splitter.addWidget(self.trace_view)
        splitter.addWidget(self._result_pane())
        splitter.setSizes([800, 480])
        outer.addWidget(splitter, 1)
        self.setCentralWidget(central)

    def _header(self) -> QtWidgets.QHBoxLayout:
        header = QtWidgets.QHBoxLayout()
        self.state_label = QtWidgets.QLabel(state_text(LiveState()))
        self.progress = QtWidgets.QProgressBar()
        self.progress.setRange(0, 1000)
        self.progress.setFormat("%p %")
        self.span_box = QtWidgets.QComboBox()
        for span in SPANS_S:
            if span <= self.stream.span_max_s:
                self.span_box.addItem(f"{span:g} s", span)
        self.span_box.setCurrentIndex(max(self.span_box.findData(self.span_s), 0))
        self.span_box.currentIndexChanged.connect(self._span_changed)
        self.fit_limits = QtWidgets.QCheckBox("scale to limits")
        self.stop_button = QtWidgets.QPushButton("Stop (safe)")
        self.stop_button.setStyleSheet(STOP_STYLE)
        self.stop_button.setEnabled(self.stop is not None)
        self.stop_button.clicked.connect(self.request_stop)
        header.addWidget(self.state_label, 3)
        header.addWidget(self.progress, 2)
        header.addWidget(QtWidgets.QLabel("window"))
        header.addWidget(self.span_box)
        header.addWidget(self.fit_limits)
        header.addWidget(self.stop_button)
        return header

    def _result_pane(self) -> QtWidgets.QWidget:
        pane = QtWidgets.QWidget()
        column = QtWidgets.QVBoxLayout(pane)
        summary = QtWidgets.QLabel("no building-up result for this experiment"
                                   if self.result is None else "")
        summary.setWordWrap(True)
        self.result_view = pg.GraphicsLayoutWidget()
        self.result_plots = ResultPlots(self.result_view, summary)
        column.addWidget(summary)
        column.addWidget(self.result_view, 1)
        return pane

    # behaviour
    def request_stop(self) -> None:
        """Ask the runner for its safe stop (ramp down, disable, file marked aborted)."""
        if self.stop is not None:
            self.stop.request(STOP_REASON)
            self.stop_button.setEnabled(False)
            self.stop_button.setText("stopping…")

    def _span_changed(self) -> None:
        self.span_s = float(self.span_box.currentData())
        self.traces.set_span(self.span_s)
        self._decimators = {}

    def refresh(self) -> None:
        """One timer tick: header, traces if new samples arrived, result if it grew."""
        state = self.stream.state()
        self._show_state(state)
        sources = self.stream.sources
        seen = (tuple(r.written for r in sources.values()),
                tuple((name, r.channels) for name, r in sources.items()))
        if seen != self._seen and self.stream.n_received > 0:
            if seen[1] != self._seen[1]:
                self._build_traces(sources)
            self._seen = seen
            self.traces.draw(self._decimated(), self.fit_limits.isChecked(), time.monotonic())
            self.frames += 1
        if self.result is not None and self.result.version != self._result_version:
            self._result_version = self.result.version
            self.result_plots.draw(self.result.view())

    def _build_traces(self, sources: Mapping[str, Any]) -> None:
        """Plots for every channel of the rows and the streams, grouped by unit."""
        units = {**self.stream.units, **self.units}
        names = [c for ring in sources.values() for c in ring.channels]
        streamed = [c for name, ring in sources.items() if name != ROWS for c in ring.channels]
        self.traces.build({n: units.get(n, "") for n in names}, self.limits, self.span_s,
                          streamed)
        self._decimators = {}

    def _decimated(self) -> list[LiveFrame]:
        """The newest frame of every source; about two points per horizontal pixel."""
        width = max(int(self.trace_view.width()), 200)
        frames = []
        for source in self.stream.sources:
            decimator = self._decimators.get(source)
            if decimator is None or decimator.n_buckets != width:
                decimator = self._decimators[source] = Decimator(self.stream, self.span_s,
                                                                 width, source=source)
            frames.append(decimator.frame())
        return frames

    def _show_state(self, state: LiveState) -> None:
        text = state_text(state)
        if self.worker is not None and self.worker.error is not None:
            text += f"<br><font color='red'>error: {html.escape(str(self.worker.error))}</font>"
        self.state_label.setText(text)
        self.progress.setValue(int(round(1000 * state.fraction)))
        over = self.worker is not None and self.worker.done
        if over or state.status not in ("idle", "running"):
            self.stop_button.setEnabled(False)

    def closeEvent(self, event: QtCore.QEvent) -> None:
        """Closing the window asks a run still going for its safe stop."""
        if self.stop is not None and self.worker is not None and self.worker.alive:
            self.stop.request(CLOSED_REASON)
        super().closeEvent(event)

    def eventFilter(self, watched: QtCore.QObject, event: QtCore.QEvent) -> bool:
        """Count the trace view's repaints (what the frame rate is measured on)."""
        if event.type() == QtCore.QEvent.Paint:
            self.paints += 1
        return False


class LiveSession:
    """A run (or replay) in a worker thread with its live window."""

    WATCH_MS = 100
    """How often Qt hands control back to Python: a Ctrl-C is seen within this time, and the
    window closes this long at most after the run it interrupted has stopped."""

    def __init__(self, window: LiveWindow, worker: Worker, stop: StopRequest) -> None:
        self.window, self.worker, self.stop = window, worker, stop

    def start(self) -> None:
        """Show the window and start the worker (the caller runs the Qt event loop)."""
        self.window.show()
        self.worker.start()

    def exec(self) -> Any:
        """Start, run Qt until the window closes, then wait for the run to end; what the
        run returned (a `feedbench run` record).

        Ctrl-C asks for the safe stop and closes the window once the run has stopped;
        closing the window asks for the safe stop (`LiveWindow.closeEvent`).
        """
        app = qt_app()
        self.start()
        interrupted = threading.Event()

        def on_sigint(*_: Any) -> None:
            self.stop.request(SIGINT_REASON)
            interrupted.set()

        def close_once_stopped() -> None:
            if interrupted.is_set() and self.worker.done:
                self.window.close()
                app.quit()

        watch = QtCore.QTimer()
        watch.timeout.connect(close_once_stopped)
        watch.start(self.WATCH_MS)
        previous = signal.signal(signal.SIGINT, on_sigint)
        try:
            app.exec()
        finally:
            watch.stop()
            signal.signal(signal.SIGINT, previous)
        if self.worker.alive:
            print("feedbench: live window closed, the run stops safely", file=sys.stderr)
        return self.worker.wait(self.stop)


def live_result_for(experiment: str) -> LiveAnalysis | None:
    """The live analysis of `experiment`'s family (None for an unknown experiment)."""
    family = families().get(experiment)
    return LiveAnalysis(family) if family else None


def qt_app() -> QtWidgets.QApplication:
    """The process's QApplication (created on first use); `DisplayError` in one line where
    Qt would abort the process (no display, a system library of its xcb plugin missing)."""
    app = QtWidgets.QApplication.instance()
    if app is None:
        require_display()
        app = QtWidgets.QApplication(sys.argv[:1])
    return app


def bench_session(config, span_s: float = 10.0, progress: bool = True,
                  catalog: str = "", store: str = "") -> LiveSession:
    """A live window on a bench run of `config` (a `feedbench.bench.RunConfig`), catalogued
    in `catalog` (``--catalog``), copied to `store` (``--store``; `feedbench.bench.run_config`)."""
    from feedbench.bench import run_config

    qt_app()
    config = replace(config, bench={**config.bench, "one_thread": False},  # see `one_thread`
                     raw={**config.raw, "bench": {**config.raw["bench"], "one_thread": False}})
    stream, stop = LiveStream(), StopRequest()
    result = live_result_for(config.plan.experiment)
    observers = [stream, *([result] if result else [])]
    worker = Worker(lambda: run_config(config, observers=observers, progress=progress,
                                       stop=stop, catalog=catalog, store=store))
    window = LiveWindow(stream, {}, config.limits, result, stop, worker, span_s,
                        title=f"feedbench live — {config.plan.experiment}")
    return LiveSession(window, worker, stop)


def replay_session(path: str | Path, speed: float = 1.0, span_s: float = 10.0) -> LiveSession:
    """A live window replaying a recording at `speed` × real time (≤ 0: as fast as possible)."""
    from feedbench.daq.recording import open_recording

    qt_app()
    recording = open_recording(path)
    stream, stop = LiveStream(), StopRequest()
    result = live_result_for(recording.experiment)
    observers = [stream, *([result] if result else [])]
    worker = Worker(lambda: replay(recording, observers, speed, stop))
    window = LiveWindow(stream, recording.units, recorded_limits(recording), result, stop,
                        worker, span_s, title=f"feedbench replay — {Path(path).name}")
    return LiveSession(window, worker, stop)


def recorded_limits(recording) -> Limits | None:
    """The limits a recording was made with (None if its config has no valid table)."""
    try:
        return Limits.from_config(recording.config.get("limits", {}))
    except ValueError:
        return None
