"""The CNC-style closed-loop Bode of the drive (Ch. 4.3.1): discrete frequencies into the
velocity or the position reference, at a feed that keeps friction sliding.

- ``loop = "velocity"``: CSV, target velocity = the feed, a sine of `amplitude_mm_min` in the
  velocity offset 0x60B1 at each frequency; response ẋ_mot (0x606C). The closed velocity
  loop ẋ_mot/ẋ_ref feeds Eq. (4.20): the open-loop mobility G = H / (PI (1 − H)) with the
  drive's K_p and T_i (read by SDO before the run, `metadata.drive_gains`), and its
  anti-resonance f_t and resonance f_r (Eqs. 4.13, 4.14).
- ``loop = "position"``: CSP, the target position carries a sine whose velocity amplitude is
  `amplitude_mm_min`; response x_mot. The ratio is taken on the per-cycle increments of both
  (the same difference operator cancels); reported with its −3 dB bandwidth.

Each frequency is held `settle_cycles` + `cycles_per_frequency` periods, phase-continuous; a
sine fitted after the settle cycles gives the FRF point and R² (`analysis.sinefit`); a point
below `r_squared_min` is flagged and left out of the FRF (kept with its point, shown red
live). The mobility's extrema are searched in `band_low_Hz` … `band_high_Hz`, the chirp's
band parameters (Ch. 3.5.1).
"""

from __future__ import annotations

from typing import Any, Iterator, Mapping

import numpy as np

from feedbench.analysis.checks import check, peak_checks
from feedbench.analysis.servo import open_loop_mobility
from feedbench.analysis.sinefit import stepped_sine_frf
from feedbench.config import ConfigError, Field, one_of, positive
from feedbench.experiments.chirp import SCHEMA as CHIRP_SCHEMA
from feedbench.experiments.chirp import extrema_text, mobility_band, mobility_extrema
from feedbench.engine.family import Example, Experiment, headline
from feedbench.engine.preflight import check_amplitude_below_feed, check_feed
from feedbench.engine.plan import Plan, Segment, recorded_windows
from feedbench.experiments.signals import integrate_velocity, ramp_to_feed
from feedbench.protocols.cia402 import CSP, CSV
from feedbench.units import MM_PER_MIN
from feedbench.views.frfs import MOTOR_FORCE, MOTOR_VELOCITY, Dof, ExchangeFrf, polar
from feedbench.views.panels import ResultView, point_frf_panels
from feedbench.views.sections import (
    FrfSeries, Plot, RunSection, Table, frf_figure, png_of,
)

NAME = "closed_loop_bode"

SCHEMA = {
    "type": Field(str, NAME, "experiment family"),
    "loop": Field(str, "velocity", "the loop whose reference is excited",
                  one_of("velocity", "position")),
    "feed_mm_min": Field(float, 500.0, "axis feed during the measurement (mm/min)", positive),
    "amplitude_mm_min": Field(float, 60.0, "velocity amplitude of the excitation (mm/min)",
                              positive),
    "f_start_Hz": Field(float, 10.0, "first frequency (Hz)", positive),
    "f_stop_Hz": Field(float, 150.0, "last frequency (Hz)", positive),
    "f_step_Hz": Field(float, 1.0, "frequency step (Hz)", positive),
    "cycles_per_frequency": Field(int, 10, "periods fitted per frequency", positive),
    "settle_cycles": Field(int, 5, "periods before the fit at each frequency", positive),
    "r_squared_min": Field(float, 0.99, "quality gate on both fits", positive),
    "stroke_mm": Field(float, 200.0, "longest travel of one pass (mm)", positive),
    "settle_s": Field(float, 0.5, "time at feed before the first frequency of a pass (s)",
                      positive),
    "accel_m_s2": Field(float, 1.0, "acceleration of the ramps (m/s²)", positive),
    "band_low_Hz": CHIRP_SCHEMA["band_low_Hz"],
    "band_high_Hz": CHIRP_SCHEMA["band_high_Hz"],
}

MIN_BAND_POINTS = 3
"""Frequencies the mobility's extrema need in the band: a resonance with a point below it."""


def frequencies(p: Any) -> np.ndarray:
    """The discrete frequencies (Hz), start to stop inclusive."""
    count = int(np.floor((p.f_stop_Hz - p.f_start_Hz) / p.f_step_Hz + 1e-9)) + 1
    return p.f_start_Hz + p.f_step_Hz * np.arange(count)


def _sine_steps(p: Any, cycle_s: float) -> list[tuple[float, np.ndarray]]:
    """Per frequency the velocity excitation (m/s) per cycle, phase-continuous."""
    amplitude = p.amplitude_mm_min * MM_PER_MIN
    periods = p.settle_cycles + p.cycles_per_frequency
    steps, phase = [], 0.0
    for f in frequencies(p):
        n = int(round(periods / (f * cycle_s)))
        t = np.arange(1, n + 1) * cycle_s
        steps.append((float(f), amplitude * np.sin(phase + 2.0 * np.pi * f * t)))
        phase += 2.0 * np.pi * f * n * cycle_s
    return steps


def _pass_groups(steps: list[tuple[float, np.ndarray]], travel_per_cycle: float,
                 stroke: float) -> list[list[tuple[float, np.ndarray]]]:
    groups: list[list[tuple[float, np.ndarray]]] = [[]]
    used = 0.0
    for step in steps:
        travel = len(step[1]) * travel_per_cycle
        if groups[-1] and used + travel > stroke:
            groups.append([])
            used = 0.0
        groups[-1].append(step)
        used += travel
    return groups


def _pass(group: list[tuple[float, np.ndarray]], velocity: float, x0: float, n_settle: int,
          p: Any, cycle_s: float) -> tuple[list[Segment], float]:
    """One pass at `velocity` (m/s) from x0 (m); returns its segments and end position."""
    up = ramp_to_feed(0.0, velocity, p.accel_m_s2, cycle_s)
    down = ramp_to_feed(velocity, 0.0, p.accel_m_s2, cycle_s)
    feed = np.concatenate([up, np.full(n_settle + sum(len(s) for _, s in group), velocity), down])
    path = integrate_velocity(feed, x0, cycle_s)
    cuts = np.cumsum([0, len(up), n_settle] + [len(s) for _, s in group])
    info = {"feed_mm_min": velocity / MM_PER_MIN}
    segments = [Segment("accelerate", "move", path[:cuts[1]], info=info,
                        target_velocity=feed[:cuts[1]]),
                Segment("settle", "settle", path[cuts[1]:cuts[2]], info=info,
                        target_velocity=feed[cuts[1]:cuts[2]])]
    for (f, sine), a, b in zip(group, cuts[2:-1], cuts[3:]):
        target = path[a:b]
        offset = None
        if p.loop == "velocity":
            offset = sine
        else:
            target = target + integrate_velocity(sine, 0.0, cycle_s)
        segments.append(Segment(f"{f:g} Hz", "excite", target, velocity_offset=offset,
                                target_velocity=feed[a:b],
                                info={**info, "frequency_hz": f}))
    segments.append(Segment("stop", "move", path[cuts[-1]:], info=info,
                            target_velocity=feed[cuts[-1]:]))
    return segments, float(path[-1])


def loop_signals(recording, window, loop: str) -> tuple[np.ndarray, np.ndarray]:
    """Reference and response of one window: velocity offset and velocity (velocity loop),
    per-cycle increments of target and position (position loop)."""
    channels = recording.channels
    if loop == "velocity":
        rows = slice(window.start, window.stop)
        return channels["velocity_offset"][rows], channels["velocity"][rows]
    rows = slice(window.start - 1, window.stop)
    return np.diff(channels["x_ref"][rows]), np.diff(channels["position"][rows])


def measured_loop(recording, p: Any) -> dict:
    """FRF points of every frequency with R² (Ch. 5.5.3, `analysis.sinefit`); points below
    the quality gate are flagged: listed with their |H|, phase (rad) and R², not used."""
    fs = 1.0 / float(recording.metadata["cycle_s"])
    f, H, r2, flagged = [], [], [], []
    for window in recorded_windows(recording, "excite"):
        reference, response = loop_signals(recording, window, p.loop)
        frequency = float(window.info["frequency_hz"])
        fit = stepped_sine_frf(reference, response, fs, [(frequency, 0, len(reference))],
                               p.settle_cycles)
        if fit.r_squared[0] < p.r_squared_min:
            flagged.append({"frequency_hz": frequency, "r_squared": float(fit.r_squared[0]),
                            "abs": float(np.abs(fit.H[0])),
                            "phase_rad": float(np.angle(fit.H[0]))})
            continue
        f.append(frequency)
        H.append(complex(fit.H[0]))
        r2.append(float(fit.r_squared[0]))
    return {"f": np.array(f), "H": np.array(H), "r_squared": r2, "flagged": flagged}


HALF_POWER = 1.0 / np.sqrt(2.0)
"""|H| at −3 dB."""


def bandwidth_and_reason(f: np.ndarray, H: np.ndarray) -> tuple[float, str]:
    """The −3 dB bandwidth (Hz) of a closed loop, and why it is not defined where it is not.

    The first crossing of |H| = 1/√2 after which |H| stays below it up to the last measured
    frequency, linearly interpolated; a dip below that |H| climbs out of again (an
    anti-resonance notch) is not the bandwidth. NaN with the reason when |H| ends above
    −3 dB or starts below it.
    """
    magnitude = np.abs(np.asarray(H))
    if not magnitude.size:
        return float("nan"), "no frequency measured"
    above = np.flatnonzero(magnitude >= HALF_POWER)
    if not above.size:
        return float("nan"), f"|H| is below −3 dB from the first frequency {f[0]:g} Hz on"
    k = int(above[-1]) + 1
    if k == len(magnitude):
        dips = np.flatnonzero(magnitude < HALF_POWER)
        dip = f" (it dips below at {f[dips[0]]:g} Hz and climbs back)" if dips.size else ""
        return float("nan"), (f"|H| is {magnitude[-1]:.2f} at the last frequency {f[-1]:g} Hz, "
                              f"above −3 dB{dip}: measure higher frequencies")
    a, b = magnitude[k - 1], magnitude[k]
    return float(f[k - 1] + (a - HALF_POWER) / (a - b) * (f[k] - f[k - 1])), ""


def bandwidth(f: np.ndarray, H: np.ndarray) -> float:
    """The −3 dB bandwidth (Hz) of `bandwidth_and_reason`, NaN where it is not defined."""
    return bandwidth_and_reason(f, H)[0]


def bandwidth_text(result: Mapping[str, Any]) -> str:
    """``bandwidth 50.1 Hz`` or ``bandwidth not defined: <why>``."""
    if result["bandwidth_note"]:
        return f"bandwidth not defined: {result['bandwidth_note']}"
    return f"bandwidth {result['bandwidth_hz']:.1f} Hz"


def loop_checks(result: Mapping[str, Any], p: Any) -> list[dict]:
    """The points' sine fits at least the gate (R², Ch. 5.5.3), none flagged, and the
    mobility's f_t and f_r inside the band with a good fit at each."""
    gate, low = p.r_squared_min, result["min_r_squared"]
    flagged = result["flagged"]
    checks = [
        check("min R² of the points used", "none" if low is None else f"{low:.5f}",
              low is not None and low >= gate, f"no point passed R² {gate:g}"),
        check("frequencies flagged", ", ".join(f"{x['frequency_hz']:g} Hz" for x in flagged)
              or "none", not flagged,
              "; ".join(f"{x['frequency_hz']:g} Hz: R² {x['r_squared']:.3f} < {gate:g}"
                        for x in flagged) + " (response in the noise, or the axis stuck)"),
    ]
    mobility = result.get("mobility")
    if mobility:
        frf, band = result["frf"], mobility["band_hz"]
        f = np.asarray(frf["f_hz"])
        inside = (f >= band[0]) & (f <= band[1])
        r2 = np.asarray(frf["r_squared"])[inside]
        checks += peak_checks([(name, mobility[key], f[inside], r2) for name, key in
                               (("f_t", "antiresonance_hz"), ("f_r", "resonance_hz"))],
                              gate, "R²")
    return checks


def open_loop(f: np.ndarray, H: np.ndarray, gains: Mapping[str, float],
              band: tuple[float, float]) -> dict:
    """The open-loop mobility G (m/(N·s)) of the closed velocity loop H by Eq. (4.20) with the
    drive's K_p (N·s/m) and T_i (s), and its extrema f_t, f_r (Hz) in `band` (Eqs. 4.13,
    4.14); `ValueError` while the band holds no resonance with a point below it."""
    mobility = open_loop_mobility(f, H, gains["K_p"], gains["T_i"])
    inside = (f >= band[0]) & (f <= band[1])
    f_t, f_r = mobility_extrema(f[inside], mobility[inside], band)
    return {"antiresonance_hz": f_t, "resonance_hz": f_r, "band_hz": list(band),
            "abs": np.abs(mobility).tolist(), "phase_rad": np.angle(mobility).tolist()}


def _points(result: Mapping[str, Any]) -> list[tuple[float, complex, float]]:
    """Every measured point (f Hz, H, R²), the flagged ones included, by frequency."""
    frf = result["frf"]
    used = [(f, a * np.exp(1j * phase), r2) for f, a, phase, r2
            in zip(frf["f_hz"], frf["abs"], frf["phase_rad"], frf["r_squared"])]
    flagged = [(x["frequency_hz"], x["abs"] * np.exp(1j * x["phase_rad"]), x["r_squared"])
               for x in result["flagged"]]
    return sorted(used + flagged, key=lambda point: point[0])


class ClosedLoopBode(Experiment):
    """The closed-loop Bode of the drive (Ch. 4.3.1): the closed velocity or position loop
    point by point, for the velocity loop the open-loop mobility by Eq. (4.20) and its f_t,
    f_r (Eqs. 4.13, 4.14)."""

    name = NAME
    schema = SCHEMA
    has_frfs = True
    title = "closed-loop FRF point by point"
    examples = (
        # --quick: 20–120 Hz in 2 Hz steps still brackets f_t and f_r: Eq. (4.20) gives both
        # within 1.5 %.
        Example(NAME, {"experiment": {"f_start_Hz": 20.0, "f_stop_Hz": 120.0,
                                      "f_step_Hz": 2.0, "cycles_per_frequency": 8,
                                      "settle_cycles": 4}}, rank=30),
    )
    live_kinds = ("excite",)

    @classmethod
    def check(cls, params: Mapping[str, Any], cycle_s: float) -> dict:
        """A measurable feed the excitation stays below (`preflight`), frequencies below a
        quarter of the bus rate; the velocity loop needs `MIN_BAND_POINTS` of them in the
        mobility band."""
        settings = super().check(params, cycle_s)
        p = cls.typed(settings)
        check_feed("experiment.feed_mm_min", p.feed_mm_min, cycle_s)
        check_amplitude_below_feed("experiment.amplitude_mm_min", p.amplitude_mm_min,
                                   p.feed_mm_min)
        if not p.f_start_Hz <= p.f_stop_Hz < 0.25 / cycle_s:
            raise ConfigError(f"experiment.f_stop_Hz: must lie at or above f_start_Hz and below "
                              f"{0.25 / cycle_s:g} Hz (4 samples per period at the bus cycle)")
        low, high = mobility_band(p)
        f = frequencies(p)
        in_band = int(np.sum((f >= low) & (f <= high)))
        if p.loop == "velocity" and in_band < MIN_BAND_POINTS:
            raise ConfigError(f"experiment.f_start_Hz: the open-loop mobility (Eq. 4.20) is read "
                              f"in {low:g}–{high:g} Hz and needs at least {MIN_BAND_POINTS} "
                              f"frequencies there (f_start_Hz … f_stop_Hz by f_step_Hz give "
                              f"{in_band})")
        return settings

    def plan(self) -> Plan:
        """Passes at the feed, each: accelerate, settle, frequencies back to back, stop."""
        p, cycle_s = self.params, self.cycle_s
        speed = p.feed_mm_min * MM_PER_MIN
        n_settle = int(round(p.settle_s / cycle_s))
        stroke = p.stroke_mm * 1e-3 - n_settle * speed * cycle_s
        segments: list[Segment] = []
        x, direction = 0.0, 1.0
        for group in _pass_groups(_sine_steps(p, cycle_s), speed * cycle_s, stroke):
            more, x = _pass(group, direction * speed, x, n_settle, p, cycle_s)
            segments += more
            direction = -direction
        return Plan(NAME, CSV if p.loop == "velocity" else CSP, segments, self.settings,
                    cycle_s)

    @classmethod
    def analyze(cls, recording, final: bool = True) -> dict:
        """The measured loop; for the velocity loop also Eq. (4.20) and the mobility's extrema
        (while the run goes on, `final` False, only once the band allows them).

        SI: frequencies Hz, mobility m/(N·s); gains from `metadata.drive_gains` (K_p N·s/m,
        T_i s).
        """
        p = cls.stored_params(recording)
        loop = measured_loop(recording, p)
        f, H = loop["f"], loop["H"]
        band_hz, why = bandwidth_and_reason(f, H)
        result = {"experiment": NAME, "loop": p.loop, "feed_mm_min": p.feed_mm_min,
                  "frequencies_planned": len(frequencies(p)),
                  "r_squared_min": p.r_squared_min, "flagged": loop["flagged"],
                  "min_r_squared": min(loop["r_squared"], default=None),
                  "bandwidth_hz": band_hz, "bandwidth_note": why,
                  "frf": {"f_hz": f.tolist(), "abs": np.abs(H).tolist(),
                          "phase_rad": np.angle(H).tolist(), "r_squared": loop["r_squared"]}}
        gains = recording.metadata.get("drive_gains")
        if p.loop == "velocity" and gains:
            try:
                result["mobility"] = open_loop(f, H, gains, mobility_band(p))
            except ValueError:
                if final:
                    raise
        return {**result, "checks": loop_checks(result, p)}

    @classmethod
    def report(cls, recording, result: Mapping[str, Any], section: RunSection) -> None:
        """Closed-loop FRF points with R² and −3 dB bandwidth; for the velocity loop the
        open-loop mobility of Eq. (4.20) with f_t and f_r (Eqs. 4.13, 4.14)."""
        frf = result["frf"]
        f = np.array(frf["f_hz"])
        gate = result["r_squared_min"]
        label = f"{result['loop']} loop at {result['feed_mm_min']:g} mm/min"
        series = [FrfSeries(label, f, np.array(frf["abs"]), np.array(frf["phase_rad"]),
                            np.array(frf["r_squared"]))]
        section.plots.append(Plot(f"closed {result['loop']} loop: magnitude, phase, R²", png_of(
            frf_figure(series, "|H| closed loop (–)", "R² of the sine fits", gate,
                       points=True))))
        rows = [("−3 dB bandwidth", bandwidth_text(result).removeprefix("bandwidth ")),
                ("frequencies flagged (R²)", str(len(result["flagged"])))]
        mobility = result.get("mobility")
        if mobility:
            marks = [(f"{name} {mobility[key]:.1f} Hz", mobility[key])
                     for key, name in (("antiresonance_hz", "f_t"), ("resonance_hz", "f_r"))]
            open_loop = [FrfSeries(f"open-loop mobility G, {label}", f, np.array(mobility["abs"]),
                                   np.array(mobility["phase_rad"]), np.array(frf["r_squared"]))]
            section.plots.append(Plot("open-loop mobility by Eq. (4.20): magnitude, phase, R²",
                                      png_of(frf_figure(open_loop, "|G| ((m/s)/N)",
                                                        "R² of the sine fits", gate, points=True,
                                                        marks=marks))))
            rows += [("anti-resonance f_t (Eq. 4.13)", f"{mobility['antiresonance_hz']:.2f} Hz"),
                     ("resonance f_r (Eq. 4.14)", f"{mobility['resonance_hz']:.2f} Hz")]
        section.tables.append(Table(f"closed {result['loop']} loop", ("quantity", "value"),
                                    tuple(rows)))

    @classmethod
    def headline(cls, result: Mapping[str, Any]) -> str:
        """f_t and f_r of the open-loop mobility (velocity loop), else the bandwidth."""
        mobility = result.get("mobility")
        if mobility:
            return (f"f_t {mobility['antiresonance_hz']:.1f} Hz, "
                    f"f_r {mobility['resonance_hz']:.1f} Hz")
        return bandwidth_text(result)

    @classmethod
    def details(cls, result: Mapping[str, Any]) -> list[str]:
        """The closed loop's bandwidth, frequencies measured and the lowest R² measured."""
        low = result["min_r_squared"]
        return [f"  closed {result['loop']} loop at {result['feed_mm_min']:g} mm/min: "
                f"{bandwidth_text(result)}",
                f"  {len(result['frf']['f_hz'])} of {result['frequencies_planned']} frequencies "
                f"used, min R² {'none' if low is None else f'{low:.5f}'}"]

    @classmethod
    def live_view(cls, result: Mapping[str, Any]) -> ResultView:
        """|H| (–), phase (°) and R² of the frequencies so far, those below the gate red;
        f_t and f_r (Eq. 4.20) in the summary once the band allows them."""
        gate = result["r_squared_min"]
        points = _points(result)
        r2 = [point[2] for point in points]
        panels = point_frf_panels({f"{result['loop']} loop": points}, "|H| (–)", gate)
        summary = (f"{len(points)} of {result['frequencies_planned']} frequencies, min R² "
                   f"{min(r2):.4f}, {sum(v < gate for v in r2)} below {gate:g}")
        mobility = result.get("mobility")
        if mobility:
            summary += (f"; Eq. 4.20: f_t {mobility['antiresonance_hz']:.1f} Hz, "
                        f"f_r {mobility['resonance_hz']:.1f} Hz")
        return ResultView(cls.title, panels, summary)

    @classmethod
    def frfs(cls, result: Mapping[str, Any], recording) -> Iterator[ExchangeFrf]:
        """The closed loop's FRF, and the open-loop mobility by Eq. (4.20) where derived."""
        frf, condition = result["frf"], f"feed {result['feed_mm_min']:g} mm/min"
        f = np.asarray(frf["f_hz"])
        if result["loop"] == "velocity":
            reference = Dof("velocity_offset", "motor", 1, 1, "velocity")
            response = MOTOR_VELOCITY
        else:
            reference = Dof("x_ref", "motor", 1, 1, "displacement")
            response = Dof("position", "motor", 1, 1, "displacement")
        yield ExchangeFrf(f"closed_loop_bode: closed {result['loop']} loop", condition, f,
                          polar(frf, "abs", "phase_rad"), response, reference)
        if "mobility" in result:
            yield ExchangeFrf("closed_loop_bode: open-loop mobility (Eq. 4.20)", condition, f,
                              polar(result["mobility"], "abs", "phase_rad"), MOTOR_VELOCITY,
                              MOTOR_FORCE)

    @classmethod
    def summary(cls, result: Mapping[str, Any], truth: Mapping[str, Any]) -> dict:
        """The open-loop mobility from the closed velocity loop by Eq. (4.20): f_t, f_r
        against the model's (Eqs. 4.13, 4.14)."""
        m = result["mobility"]
        return {"antiresonance_hz": m["antiresonance_hz"], "resonance_hz": m["resonance_hz"],
                "truth_f_t_hz": truth["f_t_hz"], "truth_f_r_hz": truth["f_r_hz"],
                "min_r_squared": result["min_r_squared"], "flagged": len(result["flagged"]),
                "headline": headline(extrema_text(m, truth, "Eq. 4.20: "),
                                     f"min R² {result['min_r_squared']:.4f}, "
                                     f"{len(result['flagged'])} points flagged")}
