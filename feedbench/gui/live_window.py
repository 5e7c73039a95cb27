"""The live window: scrolling traces, progress, limits, a building-up result, a Stop button.

The bench (or a replay) runs in a worker thread and feeds a `LiveStream` plus the
experiment family's `LiveAnalysis`; the window reads them on a Qt timer in the GUI thread. The cycle
loop never waits for the window: a slow window draws fewer frames, the recording keeps
every sample. Closing the window leaves the run going; only the Stop button (or Ctrl-C)
asks the runner for its safe stop (ramp down, disable, file marked aborted).

``feedbench run CONFIG --live`` → `bench_session`; ``feedbench live RUN`` → `replay_session`.
"""

from __future__ import annotations

import html
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtWidgets

from feedbench.daq.live import ROWS, Decimator, LiveFrame, LiveState, LiveStream
from feedbench.experiments.limits import Limits
from feedbench.experiments.replay import replay
from feedbench.experiments.runner import StopRequest
from feedbench.experiments.family import families
from feedbench.experiments.incremental import LiveAnalysis
from feedbench.views.panels import Curve, Image, Panel, ResultView
from feedbench.units import MM_PER_MIN, RPM


SPANS_S = (1.0, 2.0, 5.0, 10.0, 20.0, 60.0)
"""Window lengths offered (s of bench time); the stream holds the longest."""

STOP_REASON = "stop button in the live window"


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
    ChannelGroup("forces / torques", ("N", "N·m", "Nm"), "N, N·m", 1.0, "force", "rows"),
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
    """Peak |value| of the group in the frame and its share of the limit (min/max keeps it)."""
    values = [channels[n] for n in names if n in channels and len(channels[n])]
    if not values:
        return ""
    peak = float(np.max(np.abs(np.concatenate(values)))) * group.scale
    text = f"peak {peak:.4g} {group.display_unit}"
    if lines:
        text += f", {100.0 * peak / max(abs(x) for x in lines):.0f} % of limit"
    return text


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

    def join(self, timeout: float | None = None) -> None:
        """Wait for the thread (at most `timeout` s)."""
        self._thread.join(timeout)

    def wait(self, stop: StopRequest) -> Any:
        """Join; Ctrl-C asks `stop` for the safe stop; re-raise the run's error."""
        while self.alive:
            try:
                self.join(0.2)
            except KeyboardInterrupt:
                stop.request("interrupted by SIGINT")
        if self.error is not None:
            raise self.error
        return self.result


def sticky_range(shown: tuple[float, float] | None, low: float, high: float) -> tuple[float, float]:
    """A y range that holds still while the data stay inside and fill at least a third of it.

    Redrawing an axis costs more than redrawing the curves, so the range changes only when
    the data leave it or shrink well inside it; then it is reset with 10 % margins.
    """
    if not np.isfinite(low) or not np.isfinite(high):
        return shown or (-1.0, 1.0)
    if shown is not None:
        lo, hi = shown
        if lo <= low and high <= hi and (high - low) >= (hi - lo) / 3:
            return shown
    margin = 0.1 * (high - low) or 0.1 * max(abs(high), 1e-9)
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
            plot = self.layout.addPlot(row=row, col=0)
            plot.setLabel("left", group.title)
            plot.showGrid(x=True, y=True, alpha=0.3)
            plot.addLegend(offset=(5, 5))
            plot.setMouseEnabled(x=False, y=True)
            if row < len(self.groups) - 1:
                plot.hideAxis("bottom")
            for side in ("left", "bottom"):
                # a cached pixmap: the axis text is drawn again only when its ticks change
                plot.getAxis(side).setCacheMode(QtWidgets.QGraphicsItem.DeviceCoordinateCache)
            if self.plots:
                plot.setXLink(self.plots[0])
            for name in names:
                pen = pg.mkPen(pg.intColor(len(self.curves), hues=8), width=1)
                self.curves[name] = plot.plot([], [], pen=pen, name=name, skipFiniteCheck=True)
            lines = limit_lines(group, limits)
            for y in lines:
                plot.addItem(pg.InfiniteLine(y, angle=0, pen=pg.mkPen(
                    "r", width=1, style=QtCore.Qt.DashLine)))
            self.plots.append(plot)
            self.lines.append(lines)
        self.ranges = [None] * len(self.plots)
        if self.plots:
            self.plots[-1].setLabel("bottom", "time before now", units="s")
            self.set_span(span_s)

    def set_span(self, span_s: float) -> None:
        """Show the last `span_s` seconds."""
        if self.plots:
            self.plots[0].setXRange(-span_s, 0.0, padding=0)

    def draw(self, frames: Sequence[LiveFrame], fit_limits: bool, now: float) -> None:
        """Put frames (the rows', each stream's) on the plots, newest sample at x = 0."""
        t_end = max((f.t_end for f in frames if f.n_received), default=0.0)
        xs = {name: frame.t - t_end for frame in frames for name in frame.channels}
        channels = {name: y for frame in frames for name, y in frame.channels.items()}
        retitle = now - self._title_time >= self.TITLE_PERIOD_S
        for i, ((group, names), plot, lines) in enumerate(zip(self.groups, self.plots, self.lines)):
            ys = [channels[name] * group.scale for name in names if name in channels]
            for name, y in zip((n for n in names if n in channels), ys):
                self.curves[name].setData(xs[name], y)
            self._set_y_range(i, ys, lines if fit_limits else ())
            if retitle:
                plot.setTitle(f"{group.title} ({group.display_unit}) — "
                              f"{headroom_text(channels, names, group, lines)}", size="9pt")
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
    """The experiment's building-up result: one plot per panel and a summary line."""

    def __init__(self, layout: pg.GraphicsLayoutWidget, summary: QtWidgets.QLabel) -> None:
        self.layout = layout
        self.summary = summary
        self.plots: list[pg.PlotItem] = []
        self.curves: list[dict[str, pg.PlotDataItem]] = []
        self.images: list[pg.ImageItem | None] = []

    def draw(self, view: ResultView) -> None:
        """Update (or first create) the plots of a result view."""
        if len(self.plots) != len(view.panels):
            self._create(view.panels)
        for i, (plot, curves, panel) in enumerate(zip(self.plots, self.curves, view.panels)):
            if panel.image is not None:
                self._draw_image(i, plot, panel.image)
            for curve in panel.curves:
                if curve.name not in curves:
                    curves[curve.name] = self._new_curve(plot, curve, len(curves))
                curves[curve.name].setData(curve.x, curve.y)
        self.summary.setText(f"<b>{view.title}</b>: {view.summary}")

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

    def _create(self, panels: Sequence[Panel]) -> None:
        self.layout.clear()
        self.plots, self.curves, self.images = [], [], [None] * len(panels)
        for row, panel in enumerate(panels):
            plot = self.layout.addPlot(row=row, col=0, title=panel.title)
            plot.setLabel("bottom", panel.x_label)
            plot.setLabel("left", panel.y_label)
            plot.setLogMode(x=panel.log_x, y=panel.log_y)
            plot.getAxis("left").enableAutoSIPrefix(False)
            if panel.y_range is not None:
                plot.setYRange(*panel.y_range, padding=0)
            plot.showGrid(x=True, y=True, alpha=0.3)
            plot.addLegend(offset=(5, 5))
            self.plots.append(plot)
            self.curves.append({})

    @staticmethod
    def _new_curve(plot: pg.PlotItem, curve: Curve, index: int) -> pg.PlotDataItem:
        # the palette starts after red, which marks points below a quality gate
        color = pg.mkColor(curve.color) if curve.color else pg.intColor(index + 1, hues=6)
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
        self.stop_button.setStyleSheet("background:#c0392b;color:white;font-weight:bold;")
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
        if state.status not in ("idle", "running"):
            self.stop_button.setEnabled(False)

    def eventFilter(self, watched: QtCore.QObject, event: QtCore.QEvent) -> bool:
        """Count the trace view's repaints (what the frame rate is measured on)."""
        if event.type() == QtCore.QEvent.Paint:
            self.paints += 1
        return False


class LiveSession:
    """A run (or replay) in a worker thread with its live window."""

    def __init__(self, window: LiveWindow, worker: Worker, stop: StopRequest) -> None:
        self.window, self.worker, self.stop = window, worker, stop

    def start(self) -> None:
        """Show the window and start the worker (the caller runs the Qt event loop)."""
        self.window.show()
        self.worker.start()

    def exec(self) -> Any:
        """Start, run Qt until the window closes, then wait for the run to end.

        Closing the window does not stop the run; Ctrl-C asks for the safe stop.
        """
        app = qt_app()
        self.start()
        previous = signal.signal(signal.SIGINT, lambda *_: self.stop.request("interrupted by SIGINT"))
        try:
            app.exec()
        finally:
            signal.signal(signal.SIGINT, previous)
        if self.worker.alive:
            print("feedbench: live window closed, the run goes on (Ctrl-C stops it safely)",
                  file=sys.stderr)
        return self.worker.wait(self.stop)


def live_result_for(experiment: str) -> LiveAnalysis | None:
    """The live analysis of `experiment`'s family (None for an unknown experiment)."""
    family = families().get(experiment)
    return LiveAnalysis(family) if family else None


def qt_app() -> QtWidgets.QApplication:
    """The process's QApplication (created on first use)."""
    return QtWidgets.QApplication.instance() or QtWidgets.QApplication(sys.argv[:1])


def bench_session(config, span_s: float = 10.0, progress: bool = True) -> LiveSession:
    """A live window on a bench run of `config` (a `feedbench.bench.RunConfig`)."""
    from feedbench.bench import run_config

    qt_app()
    stream, stop = LiveStream(), StopRequest()
    result = live_result_for(config.plan.experiment)
    observers = [stream, *([result] if result else [])]
    worker = Worker(lambda: run_config(config, observers=observers, progress=progress,
                                       stop=stop))
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
