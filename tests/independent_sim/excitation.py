"""Excitation as a bench would apply it, at the physics rate: back-and-forth moves at several
feeds (jerk-limited: the acceleration rises and falls as a half cosine), force pulses during
moves, and a force chirp through the structural modes on top of slow moves."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

M_PER_S_PER_M_MIN = 1.0 / 60.0


@dataclass(frozen=True)
class Program:
    """What a recording does: feeds (m/min) of one back-and-forth each, the peak
    acceleration (m/s²), the cruise time of a move (s), the dwell between moves (s); pulses
    (N, s) on moves at `pulse_feed`; a chirp (N, Hz → Hz) swept once over back-and-forths
    at `chirp_feed` lasting at least `chirp_time` (s)."""

    feeds: tuple[float, ...]
    acceleration: float = 3.0
    cruise: float = 0.5
    dwell: float = 0.15
    pulse_feed: float = 4.0
    pulse_force: float = 120.0
    pulse_width: float = 0.02
    chirp_feed: float = 3.0
    chirp_force: float = 40.0
    chirp_band: tuple[float, float] = (10.0, 200.0)
    chirp_time: float = 3.0


def _move(speed: float, acceleration: float, cruise: float, dt: float) -> np.ndarray:
    """Velocity samples (m/s) of one move: half-cosine ramps to `speed`, cruise, down."""
    ramp_time = math.pi * abs(speed) / (2.0 * acceleration)
    ramp = np.arange(0.0, ramp_time, dt)
    up = speed * 0.5 * (1.0 - np.cos(math.pi * ramp / ramp_time))
    return np.concatenate([up, np.full(int(round(cruise / dt)), speed), up[::-1]])


def _back_and_forth(speed: float, program: Program, cruise: float, dt: float) -> np.ndarray:
    """Velocity of a move out, a dwell, a move back, a dwell (m/s)."""
    move = _move(speed, program.acceleration, cruise, dt)
    rest = np.zeros(int(round(program.dwell / dt)))
    return np.concatenate([move, rest, -move, rest])


def _pulses(n: int, force: float, width: float, dt: float) -> np.ndarray:
    """Six force pulses (N) of alternating sign spread over n samples, `width` (s) long."""
    out = np.zeros(n)
    length = int(round(width / dt))
    for k, centre in enumerate(np.linspace(0.1, 0.9, 6)):
        start = int(centre * n)
        out[start:start + length] = force * (-1) ** k
    return out


def _chirp(n: int, force: float, band: tuple[float, float], dt: float) -> np.ndarray:
    """A linear sine sweep (N) over n samples, faded in and out over 5 % each."""
    t = np.arange(n) * dt
    span = n * dt
    phase = 2 * math.pi * (band[0] * t + 0.5 * (band[1] - band[0]) / span * t ** 2)
    fade = np.clip(np.minimum(t, span - t) / (0.05 * span), 0.0, 1.0)
    return force * fade * np.sin(phase)


def program_signals(program: Program, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reference position (m, from 0), its velocity (m/s) and the excitation force (N)."""
    velocity, excitation = [], []
    for feed in program.feeds:
        v = _back_and_forth(feed * M_PER_S_PER_M_MIN, program, program.cruise, dt)
        velocity.append(v)
        excitation.append(np.zeros(v.size))
    pulse_moves = _back_and_forth(program.pulse_feed * M_PER_S_PER_M_MIN, program,
                                  2 * program.cruise, dt)
    velocity.append(pulse_moves)
    excitation.append(_pulses(pulse_moves.size, program.pulse_force, program.pulse_width, dt))
    chirp_moves = []
    while sum(m.size for m in chirp_moves) * dt < program.chirp_time:
        chirp_moves.append(_back_and_forth(program.chirp_feed * M_PER_S_PER_M_MIN, program,
                                           2 * program.cruise, dt))
    chirp_velocity = np.concatenate(chirp_moves)
    velocity.append(chirp_velocity)
    excitation.append(_chirp(chirp_velocity.size, program.chirp_force, program.chirp_band, dt))
    lead = np.zeros(int(round(0.2 / dt)))
    v = np.concatenate([lead, *velocity, lead])
    exc = np.concatenate([lead, *excitation, lead])
    x = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1])) * dt])
    return x, v, exc
