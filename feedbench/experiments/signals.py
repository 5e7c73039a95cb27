"""Trajectories and excitation signals, sampled once per bus cycle (SI units)."""

from __future__ import annotations

import numpy as np
import scipy


def ramp_to_feed(v_from: float, v_to: float, accel: float, dt: float) -> np.ndarray:
    """Velocity samples (m/s) ramping from `v_from` to `v_to` at `accel` (m/s²), ends at v_to."""
    n = max(1, int(np.ceil(abs(v_to - v_from) / (accel * dt))))
    return np.linspace(v_from, v_to, n + 1)[1:]


def integrate_velocity(velocity: np.ndarray, x0: float, dt: float) -> np.ndarray:
    """Positions (m) reached at the end of each cycle when moving at `velocity` (m/s)."""
    return x0 + np.cumsum(velocity) * dt


def constant_feed_move(
    x0: float, feed: float, accel: float, cruise_s: float, dt: float
) -> tuple[np.ndarray, int, int]:
    """A trapezoidal move: accelerate to `feed` (m/s, signed), cruise, stop.

    Returns the per-cycle target positions (m) and the index range of the cruise part.
    """
    up = ramp_to_feed(0.0, feed, accel, dt)
    cruise = np.full(int(round(cruise_s / dt)), feed)
    down = ramp_to_feed(feed, 0.0, accel, dt)
    velocity = np.concatenate([up, cruise, down])
    return integrate_velocity(velocity, x0, dt), len(up), len(up) + len(cruise)


def chirp(
    amplitude: float, f_start: float, f_stop: float, duration_s: float, dt: float,
    method: str = "linear",
) -> np.ndarray:
    """Swept sine of `amplitude` from `f_start` to `f_stop` Hz (scipy.signal.chirp).

    `method` is ``linear`` or ``logarithmic``. Short cosine tapers (2 % of the duration)
    at both ends keep the drive from seeing a force step.
    """
    t = np.arange(int(round(duration_s / dt))) * dt
    sweep = scipy.signal.chirp(t, f_start, duration_s, f_stop, method=method, phi=-90.0)
    taper = scipy.signal.windows.tukey(len(t), alpha=0.04)
    return amplitude * sweep * taper


def move_to(x_from: float, x_to: float, feed: float, accel: float, dt: float) -> np.ndarray:
    """Per-cycle targets (m) of a trapezoidal move from `x_from` to exactly `x_to`.

    `feed` (m/s, > 0) is the cruise speed, reduced to a triangle for short moves; the
    profile is scaled by at most one cycle's travel so it ends on the target.
    """
    distance = x_to - x_from
    if distance == 0.0:
        return np.zeros(0)
    speed = min(feed, np.sqrt(abs(distance) * accel))
    signed = np.copysign(speed, distance)
    up = ramp_to_feed(0.0, signed, accel, dt)
    cruise_s = max(abs(distance) / speed - speed / accel, 0.0)
    cruise = np.full(int(round(cruise_s / dt)), signed)
    velocity = np.concatenate([up, cruise, up[::-1][1:], [0.0]])
    velocity *= distance / (velocity.sum() * dt)
    return integrate_velocity(velocity, x_from, dt)
