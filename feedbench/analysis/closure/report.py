"""The closure's report: a dict for `--json` and the text a user reads.

JSON values are in the units their keys name (the model config's), errors are fractions
(NRMSE = ‖measured − predicted‖ / ‖measured‖ of the band-limited motor force, the EMPS
benchmark's relative error). On a rotary axis (`"rotary": true`) a key's length is an angle
and its force a torque at the same scale (pitch_mm in mrad, M_kg in kg·m², offset_N in
N·m): the keys stay, the units the texts and the "unit" strings name are the rotary ones
(`units.axis_unit`).
"""

from __future__ import annotations

import math
from typing import Any

from feedbench.analysis.closure.diagnosis import Candidate, ClosureResult, Step, Verdict
from feedbench.analysis.closure.model import Fit, Term, tip_error
from feedbench.analysis.closure.replay import ReplayErrors
from feedbench.analysis.closure.run import ClosureReport
from feedbench.analysis.closure.units import axis_unit, unit_after_key

RUNNERS_UP = 3


def term_params(term: Term, fit: Fit) -> dict[str, dict[str, float | bool]]:
    """{key: {value, std, free}} of a term, in its config units (std NaN when declared)."""
    out = {}
    for p in term.effect.parameters:
        if p.setting:
            continue
        std = fit.std.get((term.name, p.key), math.nan)
        out[p.key] = {"value": term.values[p.key] / p.to_si, "std": std / p.to_si,
                      "free": p.key in term.free}
    return out


def model_params(fit: Fit) -> dict[str, dict[str, dict[str, float | bool]]]:
    """Parameters of every term of a fitted model."""
    return {t.name: term_params(t, fit) for t in fit.model.terms}


POSITIVE = frozenset({"M_kg", "m_kg", "m_load_kg"})
"""Masses and inertias (kg, kg·m², or the dataset's force unit · s²/m): must be > 0."""
NON_NEGATIVE = frozenset({"F_v_Ns_m", "F_c_N", "dF_s_N", "friction_N_kg", "zeta_contact"})
"""Friction levels (viscous, Coulomb, Stribeck excess, a load's friction) and a contact's
damping ratio (a contact may be overdamped): must be ≥ 0."""
DAMPING = frozenset({"zeta"})
"""Damping ratios of structural modes (lightly damped by what a mode is): must lie in (0, 1)."""


def unphysical(params: dict[str, dict[str, dict[str, Any]]]) -> tuple[str, ...]:
    """"term.key = value" of every mass ≤ 0, friction level < 0 or ζ outside (0, 1) in a
    report's `model_params` (`base_params`, `final_params`)."""
    flags = []
    for term, values in params.items():
        for key, entry in values.items():
            value = entry["value"]
            if ((key in POSITIVE and not value > 0.0)
                    or (key in NON_NEGATIVE and not value >= 0.0)
                    or (key in DAMPING and not 0.0 < value < 1.0)):
                flags.append(f"{term}.{key} = {value:.4g}")
    return tuple(flags)


def candidate_dict(candidate: Candidate) -> dict[str, Any]:
    """One ranked candidate: its evidence and score."""
    return {"effect": candidate.name, "kind": candidate.kind, "evidence": candidate.evidence,
            "signature_share": candidate.screened, "explained": candidate.explained,
            "delta_bic": candidate.delta_bic, "rejected": candidate.rejected}


def replay_dict(errors: ReplayErrors | None) -> dict[str, Any] | None:
    """Replay errors as a dict (None without a replay)."""
    if errors is None:
        return None
    return {"force": errors.force, "position": errors.position, "tracking": errors.tracking,
            "frf_magnitude_db": errors.frf_magnitude_db, "frf_phase_deg": errors.frf_phase_deg,
            "frf_band_Hz": list(errors.frf_band_hz), "left_out": list(errors.left_out)}


def stop_reason(result: ClosureResult) -> str:
    """Why the search stopped, in one sentence."""
    options = result.options
    if result.steps and len(result.steps) >= options.max_effects:
        return f"reached max_effects = {options.max_effects}"
    valid = [c for c in result.final_ranking if c.rejected is None]
    if not valid:
        return "no candidate left to try"
    best = valid[0]
    checks = ((f"ΔBIC {best.delta_bic:.0f}", f"< −{options.bic_threshold:g}",
               best.delta_bic < -options.bic_threshold),
              (f"explains {100 * best.explained:.1f} % of the residual",
               f"≥ {100 * options.min_explained:.0f} %", best.explained >= options.min_explained))
    failed = " and ".join(f"{value} (needs {need})" for value, need, ok in checks if not ok)
    passed = "".join(f"; its {value} would pass ({need})" for value, need, ok in checks if ok)
    return f"no candidate significant: the best, {best.name}, fails on {failed}{passed}"


def recalibration_dict(step: Step, rotary: bool = False) -> dict[str, Any]:
    """A recalibrated declared parameter in its config unit (named as a `rotary` axis reads
    it): declared → fitted ± std, and by how many standard deviations it moved (NaN when the
    std is not finite and positive)."""
    i, key = step.chosen.freed
    p = step.fit.model.terms[i].effect.parameter(key)
    declared, value, std = (v / p.to_si for v in step.recalibration)
    known = math.isfinite(std) and std > 0.0
    return {"parameter": step.chosen.name, "unit": axis_unit(p.unit, rotary),
            "declared": declared,
            "value": value, "std": std,
            "sigmas": abs(value - declared) / std if known else math.nan}


def _step_dict(step: Step, rotary: bool = False) -> dict[str, Any]:
    """One step of the search: an effect added or a declared parameter recalibrated (its
    texts in the units a `rotary` axis or a linear one reads)."""
    out = {"kind": step.chosen.kind, "effect": step.chosen.name,
           "evidence": step.chosen.evidence, "delta_bic": step.chosen.delta_bic,
           "holdout_delta_bic": step.holdout_delta_bic, "explained": step.chosen.explained,
           "error_before": step.error_before, "error_after": step.error_after,
           "runners_up": [candidate_dict(c) for c in step.ranking[1:1 + RUNNERS_UP]],
           "model_params": model_params(step.fit)}
    if step.chosen.freed is not None:
        recalibration = recalibration_dict(step, rotary)
        return {**out, "description": _recalibration_text(recalibration),
                "recalibration": recalibration}
    term = step.fit.model.term(step.chosen.name)
    return {**out, "description": term.effect.describe(term.values, rotary),
            "params": term_params(term, step.fit)}


def _recalibration_text(r: dict[str, Any]) -> str:
    moved = f"{r['declared']:.4g} → {r['value']:.4g}"
    if math.isfinite(r["sigmas"]):
        return f"declared {moved} ± {r['std']:.2g} {r['unit']}, moved {r['sigmas']:.3g} σ"
    why = ("its information is not finite: a derivative step left the stable range"
           if math.isnan(r["std"]) else "its information is singular")
    return f"declared {moved} {r['unit']}, σ unknown ({why})"


def verdict_dict(verdict: Verdict) -> dict[str, Any]:
    """Whether a model describes the data, why not, what sits on a bound, the diagnosis."""
    return {"describes": verdict.describes, "reasons": list(verdict.reasons),
            "on_bounds": list(verdict.bounds), "diagnosis": verdict.diagnosis}


def verdict_text(which: str, verdict: Verdict) -> list[str]:
    """One line saying whether the `which` model describes the data, one for its bounds."""
    if verdict.describes:
        lines = [f"{which} model describes the data"]
    else:
        lines = [f"{which} model does not describe this data: {'; '.join(verdict.reasons)}; "
                 f"the residual is {verdict.diagnosis}"]
    if verdict.bounds:
        lines.append(f"    on a bound of its range: {', '.join(verdict.bounds)}")
    return lines


def report_dict(report: ClosureReport) -> dict[str, Any]:
    """The machine-readable report (`feedbench closure --json`)."""
    result = report.result
    steps = [_step_dict(step, report.rotary) for step in result.steps]
    final = result.final
    return {
        "model": report.name,
        "fit_data": report.fit_source,
        "holdout_data": report.holdout_source,
        "rotary": report.rotary,
        "bandwidth_Hz": report.bandwidth,
        "standstill_mm_s": report.standstill * 1e3,
        "effects": list(result.effects),
        "recalibrations": [{**s["recalibration"], "error_before": s["error_before"],
                            "error_after": s["error_after"]}
                           for s in steps if s["kind"] == "recalibration"],
        "error_before": result.error_before,
        "error_after": result.error_after,
        "fit_error_before": result.base.error,
        "fit_error_after": final.error,
        **_tip_errors(report),
        "base_params": model_params(result.base),
        "steps": steps,
        "params": {name: term_params(final.model.term(name), final) for name in result.effects},
        "final_params": model_params(final),
        "stopped": stop_reason(result),
        "base_verdict": verdict_dict(result.base_verdict),
        "final_verdict": verdict_dict(result.final_verdict),
        "final_ranking": [candidate_dict(c) for c in result.final_ranking],
        "rejected": [{"effect": c.name, "reason": c.rejected} for c in result.rejected],
        "replay": None if report.replay_before is None else {
            "before": replay_dict(report.replay_before),
            "after": replay_dict(report.replay_after)},
    }


def _tip_errors(report: ClosureReport) -> dict[str, float | None]:
    """Held-out NRMSE of the load-side acceleration before and after (None without a tip
    channel)."""
    kin = report.holdout.kin
    fits = {"tip_error_before": report.result.base, "tip_error_after": report.result.final}
    return {key: None if kin.tip is None else tip_error(fit.model, kin)
            for key, fit in fits.items()}


def _params_text(params: dict[str, dict[str, float | bool]], term: Term, rotary: bool,
                 indent: str = "    ") -> str:
    """"key = value ± std" of a term's `params`; on a `rotary` axis followed by the unit, the
    key's own naming the linear one."""
    parts = []
    for key, p in params.items():
        std = "" if not p["free"] or math.isnan(p["std"]) else f" ± {p['std']:.3g}"
        parts.append(f"{key} = {p['value']:.5g}{std}"
                     + unit_after_key(term.effect.parameter(key).unit, rotary)
                     + ("" if p["free"] else " (declared)"))
    return indent + ", ".join(parts)


def _replay_text(before: ReplayErrors, after: ReplayErrors) -> list[str]:
    lines = [f"replay in closed loop, held out: force {before.force:.2%} → {after.force:.2%}, "
             f"tracking error {before.tracking:.2%} → {after.tracking:.2%}, "
             f"position {before.position:.3%} → {after.position:.3%}"]
    if not math.isnan(after.frf_magnitude_db):
        low, high = after.frf_band_hz
        lines.append(f"FRF velocity/excitation, {low:.3g}–{high:.3g} Hz: |H| error "
                     f"{before.frf_magnitude_db:.2f} → {after.frf_magnitude_db:.2f} dB RMS, "
                     f"phase {before.frf_phase_deg:.1f}° → {after.frf_phase_deg:.1f}° RMS")
    if after.left_out:
        lines.append(f"not replayed: {', '.join(after.left_out)}")
    return lines


def report_text(report: ClosureReport) -> str:
    """The human-readable report."""
    data = report_dict(report)
    result = report.result
    lines = [
        f"closure: {report.name or 'model'}",
        f"fit on {report.fit_source}, judged on {report.holdout_source}; bandwidth "
        f"{report.bandwidth:.4g} Hz; samples slower than {report.standstill * 1e3:.3g} "
        f"{axis_unit('mm/s', report.rotary)} "
        f"not used (stiction)",
        f"base model ({', '.join(t.name for t in result.base.model.terms)}): held-out force "
        f"NRMSE {result.error_before:.2%} (fit {result.base.error:.2%})",
    ]
    for name, params in data["base_params"].items():
        lines.append(f"  {name}:" + _params_text(params, result.base.model.term(name),
                                                 report.rotary, " "))
    lines += verdict_text("the declared", result.base_verdict)
    for i, (step, found) in enumerate(zip(data["steps"], result.steps), 1):
        runners = "; ".join(f"{c['effect']} ΔBIC {c['delta_bic']:.0f}, {c['explained']:.1%}"
                            + (f" [{c['rejected']}]" if c["rejected"] else "")
                            for c in step["runners_up"]) or "none"
        action = "recalibrate" if step["kind"] == "recalibration" else "+"
        lines += [
            f"step {i}: {action} {step['effect']} ({step['description']}) — held-out "
            f"{step['error_before']:.2%} → {step['error_after']:.2%}",
            f"    signature: {step['evidence']}",
            f"    why: ΔBIC {step['delta_bic']:.0f} (held-out {step['holdout_delta_bic']:.0f}), "
            f"removes {step['explained']:.1%} of the fit residual; runners-up: {runners}",
        ]
        if "params" in step:
            lines.append(_params_text(step["params"], found.fit.model.term(step["effect"]),
                                      report.rotary))
    for r in data["rejected"]:
        lines.append(f"rejected: {r['effect']}: {r['reason']}")
    if not result.steps:
        lines.append("no missing effect found: nothing added")
    lines.append(f"stop: {data['stopped']}")
    if result.steps:
        lines += verdict_text("the final", result.final_verdict)
    lines.append(f"held-out force NRMSE before → after: {result.error_before:.2%} → "
                 f"{result.error_after:.2%}")
    if data["tip_error_before"] is not None:
        lines.append(f"held-out tip acceleration NRMSE before → after: "
                     f"{data['tip_error_before']:.2%} → {data['tip_error_after']:.2%}")
    if report.replay_before is not None:
        lines += _replay_text(report.replay_before, report.replay_after)
    return "\n".join(lines)
