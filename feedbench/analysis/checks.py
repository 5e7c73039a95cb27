"""A result judges itself: checks that the physics an analysis relies on was there.

Each check is a JSON-able dict ``{"name", "value", "ok", "reason"}``: what was checked,
the measured value as text, the verdict (True passed, False failed) and, for a failed
check, why in one line a person can act on ("hit 2 at 0.050 s: double hit"). A result
holding a failed check is not valid (`verdict`). These are pure functions of arrays and
numbers; `engine.family.judged_analysis` puts them into every family's result, and
the terminal, ``--json``, the report and the live view read them from there.

Display convention (docs/results.md): SI with engineering prefixes (Hz, N, µm/N, kg),
feeds in mm/min, as the thesis writes them.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from feedbench.units import MM_PER_MIN

EDGE_BINS = 2
"""A peak within this many frequency lines of its band's edge is taken to be the edge
(the maximum of a falling or rising slope), not a mode."""

SLID_SHARE = 0.99
"""An in-motion measurement needs the axis sliding (no sticking, no reversal) in at least
this share of its samples: only then does friction act only by its viscous part (Ch. 5.3.2)."""


def check(name: str, value: str, ok: bool, reason: str = "") -> dict[str, Any]:
    """One check; `reason` is kept only for a failed one."""
    return {"name": name, "value": value, "ok": bool(ok), "reason": "" if ok else reason}


def verdict(checks: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """``valid``: no check failed; ``not_valid_because``: ``"name: reason"`` of each failed."""
    failed = [f"{c['name']}: {c['reason'] or c['value']}" for c in checks if c["ok"] is False]
    return {"valid": not failed, "not_valid_because": failed}


def check_line(c: Mapping[str, Any]) -> str:
    """``✔ name: value`` or ``✘ name: value — reason``: a check as one line of text."""
    mark = "✔" if c["ok"] else "✘"
    reason = f" — {c['reason']}" if c.get("reason") else ""
    return f"{mark} {c['name']}: {c['value']}{reason}"


def verdict_line(result: Mapping[str, Any]) -> str:
    """``NOT VALID: …`` with every failed check's reason, or ``all n checks passed``."""
    if not result.get("valid", True):
        return "NOT VALID: " + "; ".join(result["not_valid_because"])
    return f"all {len(result.get('checks', ()))} checks passed"


def peak_checks(peaks: Sequence[tuple[str, float, np.ndarray, np.ndarray]],
                gate: float, quality: str = "coherence") -> list[dict[str, Any]]:
    """Identified peaks (or anti-resonances) ``(label, f_peak Hz, f Hz, γ²)`` of FRFs on
    lines `f` with coherence γ² (or another `quality` per line, e.g. R²): none on an edge
    of the band its `f` spans (`EDGE_BINS`), and the quality at each at least `gate`."""
    edge, low, places, gammas = [], [], [], []
    for label, f_peak, f, coherence in peaks:
        f = np.asarray(f, dtype=float)
        k = int(np.argmin(np.abs(f - f_peak)))
        gamma = float(np.asarray(coherence, dtype=float)[k])
        places.append(f"{label} {f_peak:.2f} Hz")
        gammas.append(f"{label} {gamma:.3f}")
        if k < EDGE_BINS or k > len(f) - 1 - EDGE_BINS:
            edge.append(f"{label} {f_peak:.2f} Hz is the edge of {f[0]:.4g}–{f[-1]:.4g} Hz")
        if not gamma >= gate:
            low.append(f"{label} {quality} {gamma:.3f} at {f_peak:.2f} Hz")
    return [
        check("peaks inside the band", ", ".join(places), not edge,
              "; ".join(edge) + ": a slope's end, not a mode (did the excitation reach the "
              "structure? is the band wide enough?)"),
        check(f"{quality} at the peaks", ", ".join(gammas), not low,
              "; ".join(low) + f" below {gate:g}: the response there is noise or another "
              "input, not this excitation"),
    ]


def averaged(records: int, what: str = "sweeps") -> dict[str, Any]:
    """At least two records (`what`: "sweeps", "hits") averaged: over one record the
    coherence γ² = |S_xy|²/(S_xx S_yy) is 1 at every line by construction, so a coherence
    gate passes whatever the response is (noise, another input, another signal)."""
    return check(f"{what} averaged", str(records), records >= 2,
                 f"{records} of them: the coherence of one record is 1 by construction and "
                 f"says nothing about noise or other inputs; repeat the excitation (at least "
                 f"2 {what})")


def above_floor(name: str, signal: np.ndarray, floor: float, unit: str,
                why: str) -> dict[str, Any]:
    """`signal`'s RMS about its mean above `floor` (same unit): a channel unplugged (all
    zeros or constant) or an excitation too small fails, `why` saying what the floor is."""
    signal = np.asarray(signal, dtype=float)
    rms = float(np.sqrt(np.mean((signal - signal.mean()) ** 2))) if signal.size else 0.0
    reason = ("constant: channel unplugged or sensor not powered?" if rms == 0.0 else
              f"{rms:.3g} {unit} RMS is not above {floor:.3g} {unit}: {why}")
    return check(f"{name} reached", f"{rms:.3g} {unit} RMS", rms > floor, reason)


def slid(velocity: np.ndarray, feed: float, band: float) -> dict[str, Any]:
    """The axis slid at feed `feed` (m/s, signed) during an in-motion record: the share of
    `velocity` samples (m/s) on the feed's side of the stiction band ±`band` (m/s) against
    `SLID_SHARE` (Ch. 5.3.2: friction then acts only by its viscous part)."""
    velocity = np.asarray(velocity, dtype=float)
    share = float(np.mean(np.sign(feed) * velocity > band)) if velocity.size else 0.0
    return check("the axis slid", f"{100 * share:.1f} % of the samples above the stiction band "
                 f"{band / MM_PER_MIN:.3g} mm/min", share >= SLID_SHARE,
                 f"the axis stuck or reversed in {100 * (1 - share):.1f} % of the samples: "
                 "raise the feed or lower the excitation amplitude")


def positive_parameters(label: str, values: Mapping[str, tuple[float, str]]
                        ) -> dict[str, Any]:
    """Identified masses, stiffnesses, dampings, friction forces of `label`, name → (value,
    its display unit: docs/results.md), all > 0 and finite."""
    bad = [k for k, (v, _) in values.items() if not (np.isfinite(v) and v > 0.0)]
    text = ", ".join(f"{k} {v:.4g} {unit}" for k, (v, unit) in values.items())
    return check(f"{label} parameters > 0", text, not bad,
                 f"{', '.join(bad)} not > 0: the model does not describe the data")


POSITION_RESOLUTION_M = 1e-9
"""The finest position the host reads: the bus's position unit, 1 nm (protocols.cia402)."""

MEASURABLE_INCREMENTS = 40
"""Position increments per bus cycle below which a velocity is not measurable: the ±1
increment quantisation of a one-cycle difference is then more than 2.5 % of it."""


def measurable_velocity(cycle_s: float) -> float:
    """The slowest velocity (m/s) resolved at a bus cycle of `cycle_s` s:
    `MEASURABLE_INCREMENTS` × `POSITION_RESOLUTION_M` / cycle (2.4 mm/min at 1 ms); the
    stiction band of the in-motion checks (`slid`)."""
    return MEASURABLE_INCREMENTS * POSITION_RESOLUTION_M / cycle_s
