"""The timing of a real-time run's bus cycles, from what the host records per cycle.

In real time (`daq.clock.RealtimeClock`) SYNC comes from python-can's periodic sender, one
per `cycle_s`, and the drive counts them (0x2020, the recording's `/cycle`). Per received
cycle the host records two wall-clock times (s, the clock of the CAN frames' timestamps):

- ``tpdo_time``: the receive timestamp of the cycle's last TPDO (python-can's
  ``msg.timestamp``: the adapter's or kernel's receive time on hardware);
- ``rpdo_time``: when the host sent the setpoints the drive was to apply at that cycle's SYNC
  (NaN: it sent none, it was behind and took the cycle's set when the SYNC had run).

From these, for the cycles ``first … last`` of a run:

- expected: ``last - first + 1`` SYNCs; received: the rows; missed: the cycles without a row
  (their TPDO set never came whole, or the host fell more than `drivers.cia402.SET_QUEUE`
  sets behind), so missed + received = expected;
- repeated: rows whose setpoints left after the cycle's TPDOs were back, or never (NaN): the
  drive ran that cycle on the previous cycle's setpoints or on its extrapolation of them (a
  lower bound: a setpoint that missed its SYNC by less than the drive's answer time is not
  seen);
- lateness (µs): ``tpdo_time - (t0 + cycle · cycle_s)``, with ``t0`` such that the earliest
  answer of the run is 0: how much later than the run's fastest one a cycle's answer came
  (SYNC jitter + the drive's and the bus's answer jitter + the host's receive path);
  late: lateness above `LATE_SHARE` of the cycle.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from feedbench.daq.recording import Recording

TIMING_CHANNELS = ("rpdo_time", "tpdo_time")
"""Per-cycle channels of a real-time recording (s, wall clock)."""
TIMING_UNITS = dict.fromkeys(TIMING_CHANNELS, "s")
LATE_SHARE = 0.5
"""A cycle whose TPDOs come more than this share of the cycle after the run's fastest
answer is late: the host has less than half a cycle left for the next setpoints."""
MISSED_TARGET = 1e-3
"""Share of missed cycles a real-time run should stay within (issue 18: ≤ 0.1 %)."""
BIN_SHARE = 1 / 40
"""Histogram bin width as a share of the cycle (25 µs at 1 ms)."""
HISTOGRAM_CYCLES = 2
"""The histogram's bins reach this many cycles of lateness; its last bin holds the rest."""


@dataclass(frozen=True)
class CycleTiming:
    """Counts and lateness of a real-time run's cycles (see the module); µs, lists for JSON.

    `histogram_edges_us` has one more entry than `histogram_counts`; its last edge is the
    largest lateness when that is beyond `HISTOGRAM_CYCLES` cycles."""

    cycle_s: float
    expected: int
    received: int
    missed: int
    repeated: int
    late: int
    lateness_p50_us: float
    lateness_p99_us: float
    lateness_max_us: float
    histogram_edges_us: list[float]
    histogram_counts: list[int]

    @property
    def missed_share(self) -> float:
        """Missed cycles as a share of the expected ones (0 for none expected)."""
        return self.missed / self.expected if self.expected else 0.0

    def as_dict(self) -> dict:
        """Plain JSON types, for the recording's metadata and the run catalog."""
        return asdict(self)


def cycle_timing(cycle: np.ndarray, tpdo_time: np.ndarray, rpdo_time: np.ndarray,
                 cycle_s: float) -> CycleTiming:
    """Counts, lateness percentiles and histogram of received cycles (`cycle` increasing
    integers, the times in s; see the module)."""
    cycle = np.asarray(cycle, dtype=np.int64)
    tpdo_time, rpdo_time = np.asarray(tpdo_time, float), np.asarray(rpdo_time, float)
    if cycle.size == 0:
        return CycleTiming(cycle_s, 0, 0, 0, 0, 0, np.nan, np.nan, np.nan, [0.0], [])
    expected = int(cycle[-1] - cycle[0]) + 1
    late_us = lateness_us(cycle, tpdo_time, cycle_s)
    edges, counts = lateness_histogram(late_us, cycle_s)
    p50, p99 = np.percentile(late_us, [50, 99])
    return CycleTiming(
        cycle_s=cycle_s, expected=expected, received=int(cycle.size),
        missed=expected - int(cycle.size), repeated=int(np.sum(~(rpdo_time <= tpdo_time))),
        late=int(np.sum(late_us > LATE_SHARE * cycle_s * 1e6)),
        lateness_p50_us=float(p50), lateness_p99_us=float(p99),
        lateness_max_us=float(late_us.max()), histogram_edges_us=edges,
        histogram_counts=counts)


def lateness_us(cycle: np.ndarray, tpdo_time: np.ndarray, cycle_s: float) -> np.ndarray:
    """Each answer's lateness behind the run's fastest one on the cycle grid (µs, ≥ 0).

    Times are taken relative to the first answer before the grid is subtracted, so the
    µs survive float64 next to epoch seconds."""
    offset = (tpdo_time - tpdo_time[0]) - (cycle - cycle[0]) * cycle_s
    return (offset - offset.min()) * 1e6


def lateness_histogram(late_us: np.ndarray, cycle_s: float) -> tuple[list[float], list[int]]:
    """Bins of `BIN_SHARE` of the cycle up to `HISTOGRAM_CYCLES` cycles (µs), the last bin
    stretched to the largest lateness beyond them; (edges, counts)."""
    width = BIN_SHARE * cycle_s * 1e6
    n_bins = max(1, min(int(np.ceil(late_us.max() / width)), round(HISTOGRAM_CYCLES / BIN_SHARE)))
    edges = np.arange(n_bins + 1) * width
    edges[-1] = max(edges[-1], float(late_us.max()))
    counts, _ = np.histogram(late_us, bins=edges)
    return edges.tolist(), counts.tolist()


def recorded_timing(recording: Recording) -> CycleTiming | None:
    """The cycle timing of a real-time recording, from its rows (also of a crashed run's
    file, which has no ``timing`` metadata); None for a lockstep one."""
    if not set(TIMING_CHANNELS) <= set(recording.channels):
        return None
    return cycle_timing(recording.cycle, recording.channels["tpdo_time"],
                        recording.channels["rpdo_time"],
                        float(recording.metadata.get("cycle_s", 1e-3)))
