"""Building-up results of the experiments whose signals come through the serial DAQ.

- ``sine_stream``: the FRF point by point (Ch. 5.5.3, Figs. 5.21–5.22), each completed step
  fitted as `experiments.sine_stream` fits it, with its R²;
- ``impact_hammer``: the quasi-FRF of the hits so far at each feed, Eq. (5.3), with coherence;
- ``shaker_chirp``: the tool-tip FRF (H1) of the sweeps so far at each feed, with coherence;
- ``smfe``: the spindle speed and the spectrogram of the dynamometer force (Ch. 6.4.1).

The cycle loop only copies the DAQ samples each result needs (`ExciteRecords`,
`SmfeSpectrogram.collect_stream`) and queues them, bounded (`RecordQueue`); fits, FRFs and
spectra are computed by the reader in `build`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np
import scipy.fft
import scipy.signal

from feedbench.analysis.frf import accelerance_to_receptance, estimate_frf, quasi_frf
from feedbench.experiments import impact_hammer, shaker_chirp, sine_stream, smfe
from feedbench.experiments.plan import Plan, Segment
from feedbench.experiments.tool_tip import (
    DAQ_STREAM, FORCE_CHANNELS, RESPONSE_CHANNEL, full_scale, overloaded,
)
from feedbench.gui.live_results import (
    Curve, Image, LiveResult, Panel, RecordQueue, ResultView, live_result, point_frf_panels,
    sine_point,
)
from feedbench.units import RPM

HAMMER_FORCE_WINDOW_S = 0.01
HAMMER_EXP_DECAY_S = 0.5
"""Force window and exponential decay of the hammer records, as
`impact_hammer.analyze_recording` uses them by default."""

COMPLIANCE_LABEL = "|x/F| (m/N)"

SPECTROGRAM_SEGMENT_S = 0.5
SPECTROGRAM_HOP_S = 0.25
"""Hann segments of the live spectrogram (2 Hz resolution) and their spacing (s)."""

SPECTROGRAM_COLUMNS = 2400
"""Columns kept (10 min at the hop); older ones scroll out."""

SPECTROGRAM_RANGE_DB = 60.0
"""Colour range below the loudest bin."""

SMFE_FORCES = ("dyn_fx", "dyn_fy", "dyn_fz")
SMFE_HARMONICS = (1, 2)
"""Tooth-passing harmonics drawn over the spectrogram (the analysis band is the second's)."""


@dataclass
class _OpenWindow:
    """An excite step whose DAQ samples are still arriving: bus cycles [start, stop)."""

    segment: Segment
    start: int
    stop: int
    parts: list[np.ndarray] = field(default_factory=list)


class ExciteRecords(LiveResult):
    """Base of the tool-tip results: the DAQ samples (exciter force, tool-tip acceleration)
    of each excite step, one record (2 × n) per step once a sample of a later cycle (or of
    the next block) arrived; queued with the step's info for the reader (`take`).

    A record holds the stream samples whose bus cycle lies in the step, as
    `experiments.tool_tip.window_samples` selects them from the recording.
    """

    EXCITER = "shaker"

    def __init__(self) -> None:
        super().__init__()
        self.queue = RecordQueue()
        self.fs = float("nan")
        self.record_channels: tuple[str, str] = (FORCE_CHANNELS[self.EXCITER], RESPONSE_CHANNEL)
        self._columns: list[int] = []
        self._open: dict[int, _OpenWindow] = {}

    def on_start(self, plan: Plan, channels: Sequence[str]) -> None:
        super().on_start(plan, channels)
        exciter = plan.exciter or self.param("exciter") or self.EXCITER
        self.record_channels = (FORCE_CHANNELS[exciter], RESPONSE_CHANNEL)
        self._open = {}

    def on_layout(self, units: Mapping[str, str], streams: Mapping[str, Any]) -> None:
        super().on_layout(units, streams)
        spec = streams.get(DAQ_STREAM)
        if spec is not None and all(c in spec.channels for c in self.record_channels):
            self.fs = float(spec.rate_hz)
            self._columns = [spec.channels.index(c) for c in self.record_channels]

    def on_segment(self, index: int, segment: Segment, cycle: int) -> None:
        super().on_segment(index, segment, cycle)
        if segment.kind == "excite":
            self._open[index] = _OpenWindow(segment, cycle, cycle + segment.n_cycles)

    def collect(self, index: int, segment: Segment, rows: np.ndarray) -> None:
        """The rows are not used: the signals are the DAQ's."""

    def collect_stream(self, name: str, cycles: np.ndarray, samples: np.ndarray) -> None:
        if name != DAQ_STREAM or not self._columns or not len(cycles):
            return
        for index, window in list(self._open.items()):
            lo, hi = np.searchsorted(cycles, (window.start, window.stop))
            if hi > lo:
                window.parts.append(samples[lo:hi, self._columns].T.copy())
            if cycles[-1] >= window.stop:
                del self._open[index]
                self._complete(window)

    def _complete(self, window: _OpenWindow) -> None:
        if window.parts:
            self.queue.put(window.segment.info, np.concatenate(window.parts, axis=1))
            self.version += 1

    def on_stop(self, status: str, reason: str) -> None:
        """Steps still open were cut short: left out."""
        self._open = {}

    @property
    def n_excite(self) -> int:
        """Excite steps in the plan."""
        return sum(s.kind == "excite" for s in self.segments)


def feed_label(feed_mm_min: float) -> str:
    """``500 mm/min`` (|feed|: both directions of a feed are one series)."""
    return f"{abs(float(feed_mm_min)):g} mm/min"


@live_result("sine_stream")
class SineStreamPoints(ExciteRecords):
    """Sine-stream FRF point by point (Ch. 5.5.3): per completed step a sine at the step's
    frequency is fitted to the exciter force and the tool-tip acceleration after the settle
    periods (`analysis.sinefit.stepped_sine_frf`, as `sine_stream.fit_step`); the point is
    the compliance x/F = (a/F)/(jω)² with the smaller R² of the two fits. One series per
    feed and force amplitude; points below the quality gate are marked."""

    title = "sine-stream FRF point by point"
    SCHEMA = sine_stream.SCHEMA
    EXCITER = "actuator"

    def __init__(self) -> None:
        super().__init__()
        self.series: dict[str, list[tuple[float, complex, float]]] = {}
        self.failed: list[str] = []

    def build(self) -> ResultView:
        for info, record in self.queue.take():
            f = float(info["frequency_hz"])
            try:
                H, r2 = sine_point(record[0], record[1], self.fs, f, self.param("settle_cycles"))
            except ValueError as error:  # a step too short for its settle periods
                self.failed.append(f"{f:g} Hz: {error}")
                continue
            compliance = complex(accelerance_to_receptance(np.array([f]), np.array([H]))[0])
            label = f"{feed_label(info['feed_mm_min'])}, {float(info['amplitude_N']):g} N"
            self.series.setdefault(label, []).append((f, compliance, r2))
        gate = self.param("r_squared_min")
        panels = point_frf_panels(self.series, COMPLIANCE_LABEL, gate)
        return ResultView(self.title, panels, self._summary(gate))

    def _summary(self, gate: float) -> str:
        if not self.series:
            return "waiting for the first frequency step"
        label, points = list(self.series.items())[-1]
        f, H, _ = (np.array(v) for v in zip(*points))
        every = [p[2] for points in self.series.values() for p in points]
        done = len(every) + len(self.failed) + self.queue.dropped
        return (f"step {done} of {self.n_excite}; {label}: {len(f)} points, peak "
                f"{np.abs(H).max():.3g} m/N at {f[np.argmax(np.abs(H))]:g} Hz; min R² "
                f"{min(every):.4f}, {sum(v < gate for v in every)} below {gate:g}"
                + (f"; {self.queue.dropped} skipped (window behind)" if self.queue.dropped
                   else ""))


class FeedFrf(ExciteRecords):
    """Tool-tip FRF per feed from the records so far (each record one average): compliance
    and coherence in `band`, recomputed for a feed when it gets a record."""

    def __init__(self) -> None:
        super().__init__()
        self.records: dict[float, list[np.ndarray]] = {}
        self.frfs: dict[float, tuple[np.ndarray, np.ndarray, np.ndarray, int]] = {}
        self.notes: list[str] = []

    def band(self) -> tuple[float, float]:
        """Frequency band shown (Hz)."""
        raise NotImplementedError

    def usable(self, record: np.ndarray) -> bool:
        """Whether a record may be averaged (the analysis's overload rule)."""
        raise NotImplementedError

    def feed_frf(self, records: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """(f, accelerance H1, coherence, records used) of one feed's records."""
        raise NotImplementedError

    def build(self) -> ResultView:
        changed = set()
        for info, record in self.queue.take():
            feed = abs(float(info["feed_mm_min"]))
            if not self.usable(record):
                self.notes.append(f"{feed:g} mm/min: record left out (overload)")
                continue
            self.records.setdefault(feed, []).append(record)
            changed.add(feed)
        for feed in changed:
            try:
                self.frfs[feed] = self._in_band(*self.feed_frf(self.records[feed]))
            except ValueError as error:  # every hit of the feed flagged
                self.notes.append(f"{feed:g} mm/min: {error}")
        return ResultView(self.title, self._panels(), self._summary())

    def _in_band(self, f: np.ndarray, H: np.ndarray, coherence: np.ndarray,
                 used: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        inside = (f >= self.band()[0]) & (f <= self.band()[1])
        return (f[inside], accelerance_to_receptance(f[inside], H[inside]), coherence[inside],
                used)

    def _panels(self) -> tuple[Panel, Panel]:
        feeds = sorted(self.frfs)
        return (Panel("tool-tip compliance", "frequency (Hz)", COMPLIANCE_LABEL,
                      tuple(Curve(feed_label(v), self.frfs[v][0], np.abs(self.frfs[v][1]))
                            for v in feeds), log_y=True),
                Panel("coherence", "frequency (Hz)", "γ²",
                      tuple(Curve(feed_label(v), self.frfs[v][0], self.frfs[v][2])
                            for v in feeds), y_range=(0.0, 1.05)))

    def _summary(self) -> str:
        if not self.frfs:
            return "waiting for the first record" + (f" ({self.notes[-1]})" if self.notes else "")
        parts = []
        for feed in sorted(self.frfs):
            f, compliance, coherence, used = self.frfs[feed]
            k = int(np.argmax(np.abs(compliance)))
            parts.append(f"{feed_label(feed)}: {used} of {len(self.records[feed])} "
                         f"{self.unit_name}, peak {f[k]:.2f} Hz, min γ² {coherence.min():.3f}")
        return "; ".join(parts) + (f"; {self.notes[-1]}" if self.notes else "")


@live_result("impact_hammer")
class HammerQuasiFrf(FeedFrf):
    """Quasi-FRF Φ = S_aF / S_FF of the hits so far at each feed, Eq. (5.3)
    (`analysis.frf.quasi_frf`, double hits and overloads left out, as the analysis)."""

    title = "impact hammer: quasi-FRF of the hits so far"
    SCHEMA = impact_hammer.SCHEMA
    EXCITER = "hammer"
    unit_name = "hits"

    def band(self) -> tuple[float, float]:
        return impact_hammer.DEFAULT_BAND_HZ

    def usable(self, record: np.ndarray) -> bool:
        return not overloaded(record[1:], (RESPONSE_CHANNEL,))

    def feed_frf(self, records: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        n = min(r.shape[1] for r in records)
        stacked = np.stack([r[:, :n] for r in records])
        frf = quasi_frf(stacked[:, 0], stacked[:, 1], self.fs, HAMMER_FORCE_WINDOW_S,
                        HAMMER_EXP_DECAY_S, force_range=full_scale(self.record_channels[0]))
        est = frf.estimate
        return est.f, est.H1, est.coherence, len(frf.used_hits)


@live_result("shaker_chirp")
class ShakerChirpFrf(FeedFrf):
    """Tool-tip FRF of the sweeps so far at each feed: each sweep with its ring-down one
    rectangular-window record, H1 and coherence over them (as `shaker_chirp`)."""

    title = "shaker chirp: tool-tip FRF of the sweeps so far"
    SCHEMA = shaker_chirp.SCHEMA
    unit_name = "sweeps"

    def band(self) -> tuple[float, float]:
        return self.param("f_start_Hz"), self.param("f_stop_Hz")

    def usable(self, record: np.ndarray) -> bool:
        return not overloaded(record, self.record_channels)

    def feed_frf(self, records: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        n = min(r.shape[1] for r in records)
        sweeps = [r[:, :n] - r[:, :n].mean(axis=1, keepdims=True) for r in records]
        force, response = np.concatenate(sweeps, axis=1)
        est = estimate_frf(force, response, self.fs, nperseg=n, overlap=0.0, window="boxcar")
        return est.f, est.H1, est.coherence, len(records)


@live_result("smfe")
class SmfeSpectrogram(LiveResult):
    """SMFE (Ch. 6.4.1): the spindle speed read back from the inverter, and the spectrogram
    of the dynamometer force (sum of the PSDs of F_x, F_y, F_z, Hann segments of
    `SPECTROGRAM_SEGMENT_S`) with the tooth-passing harmonics Z·N/60 over it: the sweep the
    cuts excite the structure with."""

    title = "SMFE: spindle speed and force spectrogram"
    SCHEMA = smfe.SCHEMA

    def __init__(self) -> None:
        super().__init__()
        self.queue = RecordQueue()
        self.fs = float("nan")
        self.speed: list[tuple[float, float]] = []
        self.columns_db: dict[int, np.ndarray] = {}
        self._columns: list[int] = []
        self._tail = np.zeros((0, 0))
        self._tail_cycles = np.zeros(0, dtype=np.int64)
        self._since_column = 0
        self.n_segment = self.hop = 0
        self.f_max = 0.0
        self.f = np.zeros(0)

    def on_layout(self, units: Mapping[str, str], streams: Mapping[str, Any]) -> None:
        super().on_layout(units, streams)
        spec = streams.get(DAQ_STREAM)
        if spec is not None:
            self.fs = float(spec.rate_hz)
            self._columns = [spec.channels.index(c) for c in SMFE_FORCES if c in spec.channels]
            self._tail = np.zeros((len(self._columns), 0))
        self.n_segment = int(round(SPECTROGRAM_SEGMENT_S * self.fs)) if self._columns else 0
        self.hop = int(round(SPECTROGRAM_HOP_S * self.fs)) if self._columns else 0
        self.f_max = (max(SMFE_HARMONICS) + 0.5) * self.param("teeth") * \
            self.param("spindle_rpm_stop") / 60.0

    def on_block(self, cycles: np.ndarray, block: np.ndarray) -> None:
        """The block's mean spindle speed (rpm) at its middle cycle."""
        super().on_block(cycles, block)
        if "spindle_speed" in self.columns and len(cycles):
            speed = self.column(block, "spindle_speed")
            if np.isfinite(speed).any():
                self.speed.append((float(self.time_of(cycles[len(cycles) // 2])),
                                   float(np.nanmean(speed)) / RPM))
                self.version += 1

    def collect(self, index: int, segment: Segment, rows: np.ndarray) -> None:
        """Rows are handled per block (`on_block`)."""

    def collect_stream(self, name: str, cycles: np.ndarray, samples: np.ndarray) -> None:
        if name != DAQ_STREAM or not self._columns or not len(cycles):
            return
        self.queue.put(cycles.copy(), samples[:, self._columns].T.copy())
        self._since_column += len(cycles)
        if self._since_column >= self.hop:
            self._since_column = 0
            self.version += 1

    def build(self) -> ResultView:
        self._extend_tail(self.queue.take())
        self._transform_tail()
        speed = np.array(list(self.speed)).reshape(-1, 2)
        panels = (Panel("spindle speed", "time (s)", "N (rpm)",
                        (Curve("spindle speed", speed[:, 0], speed[:, 1]),)),
                  self._spectrogram_panel(speed))
        return ResultView(self.title, panels, self._summary(speed))

    def _extend_tail(self, blocks: list[tuple[np.ndarray, np.ndarray]]) -> None:
        """Append the blocks taken from the queue; after skipped blocks a new tail starts."""
        forces, cycles = [self._tail], [self._tail_cycles]
        last = self._tail_cycles[-1] if len(self._tail_cycles) else None
        for block_cycles, block in blocks:
            if last is not None and block_cycles[0] > last + 1:
                forces, cycles = [], []
            forces.append(block)
            cycles.append(block_cycles)
            last = block_cycles[-1]
        if cycles:
            self._tail, self._tail_cycles = np.hstack(forces), np.concatenate(cycles)

    def _transform_tail(self) -> None:
        """Spectra of every complete segment in the tail, one column per hop."""
        if not self.n_segment:
            return
        window = scipy.signal.get_window("hann", self.n_segment)
        scale = 2.0 / (self.fs * np.sum(window**2))
        f = scipy.fft.rfftfreq(self.n_segment, 1.0 / self.fs)
        self.f = f[(f > 0) & (f <= self.f_max)]  # DC: the dynamometer's offset, no sweep
        while self._tail.shape[1] >= self.n_segment:
            segment = self._tail[:, :self.n_segment]
            spectra = scipy.fft.rfft(segment * window, axis=1)[:, 1:self.f.size + 1]
            psd = scale * np.sum(np.abs(spectra) ** 2, axis=0)
            middle = self.time_of(self._tail_cycles[self.n_segment // 2])
            self.columns_db[int(round(middle / SPECTROGRAM_HOP_S))] = 10.0 * np.log10(
                np.maximum(psd, 1e-30))
            self._tail = self._tail[:, self.hop:]
            self._tail_cycles = self._tail_cycles[self.hop:]
        for slot in sorted(self.columns_db)[:-SPECTROGRAM_COLUMNS]:
            del self.columns_db[slot]

    def _spectrogram_panel(self, speed: np.ndarray) -> Panel:
        harmonics = tuple(Curve(f"{k}·Z·N/60", speed[:, 0], k * self.param("teeth") *
                                speed[:, 1] / 60.0) for k in SMFE_HARMONICS)
        panel = dict(title="force spectrogram, Σ PSD (dB re 1 N²/Hz)",
                     x_label="time (s)", y_label="frequency (Hz)", curves=harmonics)
        if not self.columns_db:
            return Panel(**panel)
        slots = sorted(self.columns_db)
        z = np.full((slots[-1] - slots[0] + 1, self.f.size), np.nan)
        for slot in slots:
            z[slot - slots[0]] = self.columns_db[slot]
        top = float(np.nanmax(z))
        df = self.fs / self.n_segment
        image = Image(z, (slots[0] - 0.5) * SPECTROGRAM_HOP_S, SPECTROGRAM_HOP_S, 0.5 * df, df,
                      (top - SPECTROGRAM_RANGE_DB, top))
        return Panel(**panel, image=image, y_range=(0.0, float(self.f_max)))

    def _summary(self, speed: np.ndarray) -> str:
        if not len(speed):
            return "waiting for the spindle"
        rpm = speed[-1, 1]
        return (f"spindle {rpm:.0f} rpm, tooth passing {self.param('teeth') * rpm / 60.0:.1f} Hz;"
                f" {len(self.columns_db)} spectra of {SPECTROGRAM_SEGMENT_S:g} s"
                + (f"; {self.queue.dropped} blocks skipped (window behind)"
                   if self.queue.dropped else ""))
