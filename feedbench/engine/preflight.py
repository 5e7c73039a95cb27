"""Preflight from physics: what the bench can measure, checked before anything moves.

Limits say what the bench may do; these checks say what it can measure. A feed below the
measurable velocity is refused (the position moves too few encoder increments per bus cycle
for the velocity to be resolved, and the axis sits in its stiction band), and a velocity
chirp whose amplitude reaches the feed is refused (the axis would reverse and stick every
period, Ch. 5.3.2). A value off by a unit factor (×1000, ×60) says which unit it was
probably typed in. Every refusal is a `ConfigError` naming the field.
"""

from __future__ import annotations

from typing import Sequence

from feedbench.analysis.checks import measurable_velocity
from feedbench.config import ConfigError
from feedbench.units import FEED_TYPOS, MM_PER_MIN, typed_in

HIGHEST_FEED_MM_MIN = 60_000.0
"""The fastest feed a unit hint proposes (60 m/min): a rapid traverse of a large machine."""


def measurable_feed_mm_min(cycle_s: float) -> float:
    """The slowest feed (mm/min) the bench resolves at a bus cycle of `cycle_s` s
    (`analysis.checks.measurable_velocity`)."""
    return measurable_velocity(cycle_s) / MM_PER_MIN


def check_feed(field: str, feed_mm_min: float, cycle_s: float) -> None:
    """A feed of 0 (hold position) or at least the measurable one; else a `ConfigError`
    naming `field`, with the unit it was probably typed in."""
    slowest = measurable_feed_mm_min(cycle_s)
    if 0.0 < abs(feed_mm_min) < slowest:
        hint = typed_in(feed_mm_min, "mm/min", slowest, HIGHEST_FEED_MM_MIN, FEED_TYPOS)
        raise ConfigError(
            f"{field} = {feed_mm_min:g} is below the measurable {slowest:.2g} mm/min (the "
            f"velocity is resolved from {cycle_s * 1e3:g} ms bus cycles of a 1 nm encoder, "
            f"and the axis sits in its stiction band){hint}")


def check_feeds(field: str, feeds_mm_min: Sequence[float], cycle_s: float) -> None:
    """`check_feed` on every feed of a list, the field named with the index."""
    for i, feed in enumerate(feeds_mm_min):
        check_feed(f"{field}[{i}]", feed, cycle_s)


def check_amplitude_below_feed(field: str, amplitude_mm_min: float, feed_mm_min: float) -> None:
    """A velocity excitation of `amplitude_mm_min` on a feed of `feed_mm_min` (> 0) must stay
    below the feed, else the axis reverses and sticks every period (Ch. 5.3.2): a
    `ConfigError` naming `field`."""
    if feed_mm_min and amplitude_mm_min >= feed_mm_min:
        raise ConfigError(
            f"{field} = {amplitude_mm_min:g} reaches the feed {feed_mm_min:g} mm/min: the axis "
            "would reverse and stick every period (Ch. 5.3.2); keep it below the feed")
