"""Settling time at the tool tip after point-to-point moves, read by a linear scale.

The axis makes `moves` point-to-point moves of `stroke_mm` (trapezoidal, `feed_mm_min`,
`accel_m_s2`), alternating in direction, and holds each target for `dwell_s`. A linear scale
at the tool tip (the ``linear_scale`` device kind of this package) is read every bus cycle.
When the deceleration ends, the structure between the carriage and the tool tip rings out:
after each move the analysis takes the scale's error from its final value e(t) and gives

- the settling time: from the end of the move until |e| stays within ±`band_um`;
- the overshoot: the largest excursion past the final value in the direction of motion;
- the residual vibration: its frequency from the zero crossings of e and its damping ratio
  from the logarithmic decrement of the successive peaks (a linear fit of ln|peak| over
  time: slope −ζω_n). With the carriage held by the position loop the tool tip rings near
  the structure's anti-resonance f_t = √(k/m_tip)/2π (thesis Eq. 4.13), which the demo
  compares it with.

A result judges itself: its checks say whether the scale saw each stroke (a slipping or
unplugged scale fails) and whether every move settled within its dwell (else the dwell was
too short to say).
"""

from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

from feedbench.analysis.checks import check
from feedbench.config import ConfigError, Field, positive
from feedbench.engine.family import Example, Experiment, headline, percent_error
from feedbench.engine.plan import Plan, Segment, recorded_windows
from feedbench.experiments.signals import move_to
from feedbench.protocols.cia402 import CSP
from feedbench.units import MM_PER_MIN
from feedbench.views.panels import Curve, Panel, ResultView
from feedbench.views.sections import Plot, RunSection, Table, new_figure, png_of

NAME = "settling_time"
SCALE = "linear_scale"
"""The device it needs (this package's kind), and its channel's prefix."""
CHANNEL = f"{SCALE}.position"

SCHEMA = {
    "type": Field(str, NAME, "experiment family"),
    "stroke_mm": Field(float, 10.0, "length of each move (mm)", positive),
    "feed_mm_min": Field(float, 2000.0, "feed of the moves (mm/min)", positive),
    "accel_m_s2": Field(float, 2.0, "acceleration of the moves (m/s²)", positive),
    "moves": Field(int, 4, "moves, alternating in direction", positive),
    "dwell_s": Field(float, 0.8, "standstill after each move, measured (s)", positive),
    "rest_s": Field(float, 0.2, "standstill before the first move (s)", positive),
    "band_um": Field(float, 2.0, "settling band: ± around the final value (µm)", positive),
    "every_cycles": Field(int, 1, "read the scale every n bus cycles", positive),
}

FINAL_SHARE = 0.2
"""The final value of a move: the mean of the scale over the last share of its dwell."""
STROKE_TOLERANCE = 0.05
"""The scale saw a stroke when its travel is within this share of the commanded stroke."""
NOISE_FACTOR = 5.0
"""Peaks of the residual vibration count above this many times the final part's noise."""
MIN_PEAKS = 3


def _cycles(duration_s: float, cycle_s: float) -> int:
    return max(1, int(round(duration_s / cycle_s)))


def _valid(t: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The samples the scale gave (NaN between its readings left out)."""
    keep = np.isfinite(x)
    return t[keep], x[keep]


def residual_vibration(t: np.ndarray, e: np.ndarray, floor: float) -> dict[str, float]:
    """Frequency (Hz, zero crossings) and damping ratio (logarithmic decrement of the
    peaks between crossings) of the decaying oscillation e(t) while its peaks are above
    `floor`; NaN with fewer than `MIN_PEAKS` such peaks."""
    crossings = np.flatnonzero(np.signbit(e[1:]) != np.signbit(e[:-1]))
    peaks_t, peaks = [], []
    for a, b in zip(crossings[:-1], crossings[1:]):
        i = a + 1 + int(np.argmax(np.abs(e[a + 1:b + 1])))
        if abs(e[i]) <= floor:
            break
        peaks_t.append(t[i])
        peaks.append(abs(e[i]))
    if len(peaks) < MIN_PEAKS:
        return {"frequency_hz": math.nan, "damping_ratio": math.nan, "n_peaks": len(peaks)}
    # crossing times (linear interpolation) over the stretch the peaks span
    used = crossings[:len(peaks) + 1]
    tc = t[used] - e[used] * (t[used + 1] - t[used]) / (e[used + 1] - e[used])
    frequency = (len(tc) - 1) / (2.0 * (tc[-1] - tc[0]))
    sigma = -np.polyfit(peaks_t, np.log(peaks), 1)[0]
    omega_d = 2.0 * math.pi * frequency
    return {"frequency_hz": float(frequency),
            "damping_ratio": float(sigma / math.hypot(sigma, omega_d)),
            "n_peaks": len(peaks)}


def settling_of_move(t: np.ndarray, x: np.ndarray, before: float, stroke: float,
                     band: float) -> dict[str, Any]:
    """One move's settling from the scale's samples `x` (m) at times `t` (s) after the move
    ended, `before` the scale's reading before it, `stroke` the commanded travel (m)."""
    t, x = _valid(t, x)
    tail = x[-max(2, int(FINAL_SHARE * len(x))):]
    final = float(tail.mean())
    e = x - final
    outside = np.flatnonzero(np.abs(e) > band)
    settled = not outside.size or outside[-1] < len(x) - len(tail)
    settling = 0.0 if not outside.size else float(t[min(outside[-1] + 1, len(t) - 1)])
    floor = max(NOISE_FACTOR * float(tail.std()), band / 4.0)
    return {"stroke_m": stroke, "travel_m": final - before, "final_m": final,
            "settling_s": settling, "settled": bool(settled),
            "overshoot_m": float(max(0.0, np.max(np.sign(stroke) * e))),
            **residual_vibration(t, e, floor),
            "t_s": t.tolist(), "error_m": e.tolist()}


def _median(values: list[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return float(np.median(finite)) if finite else math.nan


def settling_checks(moves: list[Mapping[str, Any]]) -> list[dict]:
    """The scale saw each stroke (within `STROKE_TOLERANCE`), each move settled in its
    dwell."""
    if not moves:
        return []
    missed = [f"move {i + 1}: {m['travel_m'] * 1e3:.3f} of {m['stroke_m'] * 1e3:.3f} mm"
              for i, m in enumerate(moves)
              if not abs(m["travel_m"] - m["stroke_m"]) <= STROKE_TOLERANCE * abs(m["stroke_m"])]
    late = [f"move {i + 1}" for i, m in enumerate(moves) if not m["settled"]]
    return [check("the scale saw every stroke", f"{len(moves) - len(missed)}/{len(moves)}",
                  not missed, "; ".join(missed) + ": the scale's travel differs from the "
                  "commanded stroke (a slipping or unplugged scale, or the axis did not move)"),
            check("settled within the dwell", f"{len(moves) - len(late)}/{len(moves)}",
                  not late, ", ".join(late) + " still outside the band in the last "
                  f"{100 * FINAL_SHARE:g} % of the dwell: lengthen dwell_s or widen band_um")]


class SettlingTime(Experiment):
    """Settling time, overshoot and residual vibration of the tool tip after point-to-point
    moves, read by a linear scale (this package's ``linear_scale`` device)."""

    name = NAME
    schema = SCHEMA
    title = "settling at the tool tip (linear scale)"
    axes = ("lab",)
    live_kinds = ("measure",)
    # --quick: two moves instead of four; each still rings out and settles in its dwell.
    examples = (Example(NAME, {"experiment": {"moves": 2}}),)

    @classmethod
    def check(cls, params: Mapping[str, Any], cycle_s: float) -> dict:
        """The schema's checks, and a dwell long enough to tell a final value."""
        p = super().check(params, cycle_s)
        if p["dwell_s"] * FINAL_SHARE < 10 * p["every_cycles"] * cycle_s:
            raise ConfigError(f"experiment.dwell_s: {p['dwell_s']:g} s leaves fewer than 10 "
                              f"scale readings for the final value (its last "
                              f"{100 * FINAL_SHARE:g} %)")
        return p

    def devices(self) -> dict[str, dict[str, Any]]:
        """The linear scale, read every ``every_cycles``."""
        return {SCALE: {"every_cycles": self.params.every_cycles}}

    def plan(self) -> Plan:
        """A rest, then per move: the move, then its dwell (measured), alternating."""
        p, dt = self.params, self.cycle_s
        segments = [Segment("rest", "settle", np.zeros(_cycles(p.rest_s, dt)))]
        x, stroke = 0.0, p.stroke_mm * 1e-3
        for i in range(p.moves):
            target = x + stroke if i % 2 == 0 else x - stroke
            info = {"move": i + 1, "stroke_m": target - x}
            segments += [Segment(f"move {i + 1}", "move",
                                 move_to(x, target, p.feed_mm_min * MM_PER_MIN,
                                         p.accel_m_s2, dt), info=info),
                         Segment(f"dwell {i + 1}", "measure",
                                 np.full(_cycles(p.dwell_s, dt), target), info=info)]
            x = target
        return Plan(NAME, CSP, segments, self.settings, dt)

    @classmethod
    def analyze(cls, recording, final: bool = True) -> dict:
        """Per move: settling time (s), overshoot (m), residual vibration; the worst and
        the median over the moves. Live: the moves completed so far."""
        p = cls.stored_params(recording)
        cycle_s = float(recording.metadata["cycle_s"])
        x = recording.channels[CHANNEL]
        moves = {w.info["move"]: w for w in recorded_windows(recording, "move")}
        found = []
        for w in recorded_windows(recording, "measure", at_least=1 if final else 0):
            start = moves[w.info["move"]].start
            before = x[max(0, start - 20):start]
            before = before[np.isfinite(before)]
            t = np.arange(w.stop - w.start) * cycle_s
            found.append(settling_of_move(t, x[w.start:w.stop],
                                          float(before.mean()) if before.size else math.nan,
                                          w.info["stroke_m"], p.band_um * 1e-6))
        if not found and not final:
            raise ConfigError(f"{recording.path}: waiting for the first move to settle")
        return {"experiment": NAME, "band_m": p.band_um * 1e-6, "moves": found,
                "settling_s_max": max(m["settling_s"] for m in found),
                "settling_s_median": _median([m["settling_s"] for m in found]),
                "overshoot_m_max": max(m["overshoot_m"] for m in found),
                "frequency_hz": _median([m["frequency_hz"] for m in found]),
                "damping_ratio": _median([m["damping_ratio"] for m in found]),
                "checks": settling_checks(found)}

    @classmethod
    def headline(cls, result: Mapping[str, Any]) -> str:
        """Worst and median settling time, overshoot, residual vibration."""
        band = result["band_m"] * 1e6
        vibration = ("no residual vibration above the noise"
                     if not math.isfinite(result["frequency_hz"]) else
                     f"residual vibration {result['frequency_hz']:.1f} Hz, "
                     f"ζ {result['damping_ratio']:.4f}")
        return headline(f"settling to ±{band:g} µm in {result['settling_s_max']:.3f} s "
                        f"(median {result['settling_s_median']:.3f} s, "
                        f"{len(result['moves'])} moves)",
                        f"overshoot {result['overshoot_m_max'] * 1e6:.1f} µm", vibration)

    @classmethod
    def report(cls, recording, result: Mapping[str, Any], section: RunSection) -> None:
        """The error from the final value after each move (µm) with the band, and a row per
        move."""
        figure = new_figure(8.0, 4.0)
        axes = figure.subplots()
        for i, m in enumerate(result["moves"]):
            axes.plot(np.array(m["t_s"]) * 1e3, np.array(m["error_m"]) * 1e6, lw=0.8,
                      label=f"move {i + 1}")
        band = result["band_m"] * 1e6
        for level in (band, -band):
            axes.axhline(level, color="k", lw=0.6, ls="--")
        axes.set_xlabel("time after the move (ms)")
        axes.set_ylabel("tool tip from its final value (µm)")
        axes.grid(alpha=0.3)
        axes.legend(fontsize=8)
        section.plots.append(Plot("settling after each move (linear scale)", png_of(figure)))
        section.tables.append(Table("settling per move", (
            "move", "stroke (mm)", "settling (s)", "overshoot (µm)", "vibration (Hz)", "ζ"),
            tuple((str(i + 1), f"{m['stroke_m'] * 1e3:+.3f}", f"{m['settling_s']:.3f}",
                   f"{m['overshoot_m'] * 1e6:.1f}", f"{m['frequency_hz']:.1f}",
                   f"{m['damping_ratio']:.4f}") for i, m in enumerate(result["moves"]))))

    @classmethod
    def live_view(cls, result: Mapping[str, Any]) -> ResultView:
        """The error after each move completed so far (µm) and the headline."""
        curves = tuple(Curve(f"move {i + 1}", np.array(m["t_s"]) * 1e3,
                             np.array(m["error_m"]) * 1e6)
                       for i, m in enumerate(result["moves"]))
        panel = Panel("tool tip from its final value", "time after the move (ms)",
                      "error (µm)", curves)
        return ResultView(cls.title, (panel,), cls.headline(result))

    @classmethod
    def summary(cls, result: Mapping[str, Any], truth: Mapping[str, Any]) -> dict:
        """The settling time and, beside the world's anti-resonance f_t (Eq. 4.13), the
        residual vibration's frequency."""
        out = {"settling_s_max": result["settling_s_max"],
               "overshoot_m_max": result["overshoot_m_max"],
               "frequency_hz": result["frequency_hz"], "damping_ratio": result["damping_ratio"]}
        parts = [cls.headline(result)]
        if truth and "f_t_hz" in truth and math.isfinite(result["frequency_hz"]):
            out["truth_f_t_hz"] = truth["f_t_hz"]
            out["error_pct"] = percent_error(result["frequency_hz"], truth["f_t_hz"])
            parts.append(f"vibration vs f_t (Eq. 4.13) {truth['f_t_hz']:.2f} Hz: "
                         f"{out['error_pct']:+.1f} %")
        return {**out, "headline": headline(*parts)}
