"""The model config a user writes (TOML, already parsed): terms, controller, search.

    [model]
    name = "rigid body with viscous friction"
    bandwidth_Hz = 50.0          # cut-off of the zero-phase derivative filter
    standstill = 0.02            # samples slower than this × the 95th-percentile speed
                                 # are not used (stiction)
    [terms.inertia]
    M_kg = "free"                # "free", a number (declared, fixed) or
    [terms.viscous]              # { value = 200.0, free = true } (a start value)
    F_v_Ns_m = { value = 200.0, free = true }

    [controller]                 # for the forward replay (optional)
    K_p_Ns_m = 8557.0            # velocity-loop gain
    K_v_1_s = 160.18             # position-loop gain
    T_i_ms = 0.0                 # integral time; 0: P velocity loop (e.g. the EMPS PD)
    ...

    [closure]                    # search settings (optional)
    holdout_fraction = 0.3       # later part held out when no validation recording is given

Every key names its unit; values are converted to SI here. Errors are `ConfigError`s that
name the field. Missing parameters of a declared term are free (settings take their
default).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

from feedbench.analysis.closure.diagnosis import ClosureOptions
from feedbench.analysis.closure.effects import CANDIDATES, EFFECTS, RETIRED, Effect, Parameter
from feedbench.analysis.closure.model import Model, Term
from feedbench.config import ConfigError, Field, REQUIRED, non_negative, positive, validate_table

MODEL_SCHEMA = {
    "name": Field(str, "", "what the model is"),
    "bandwidth_Hz": Field(float, 0.0, "derivative filter cut-off (Hz); 0: a tenth of the "
                          "sample rate", non_negative),
    "standstill": Field(float, 0.02, "standstill threshold as a fraction of the "
                        "95th-percentile speed", non_negative),
}

CONTROLLER_SCHEMA = {
    "K_p_Ns_m": Field(float, REQUIRED, "velocity-loop gain (N·s/m)", positive),
    "K_v_1_s": Field(float, REQUIRED, "position-loop gain (1/s)", non_negative),
    "T_i_ms": Field(float, 0.0, "velocity-loop integral time (ms); 0: none", non_negative),
    "f_velocity_Hz": Field(float, 1000.0, "velocity-loop rate (Hz)", positive),
    "f_position_Hz": Field(float, 1000.0, "position-loop rate (Hz)", positive),
    "delay_ms": Field(float, 0.0, "force delay inside the drive (ms)", non_negative),
    "force_limit_N": Field(float, 1e6, "force saturation (N)", positive),
    "velocity_feedforward": Field(bool, False, "feed the reference's speed forward"),
}

def _fraction(value: float) -> str | None:
    return None if 0.0 < value < 1.0 else f": must lie in (0, 1) (got {value})"


CLOSURE_SCHEMA = {
    "holdout_fraction": Field(float, 0.3, "share of a single recording held out (its end)",
                              _fraction),
    "bic_threshold": Field(float, 10.0, "ΔBIC an effect must beat", non_negative),
    "min_explained": Field(float, 0.15, "share of the residual an effect must explain",
                           non_negative),
    "max_effects": Field(int, 6, "most effects added", non_negative),
    "candidates": Field(list, list(CANDIDATES), "effects the search may add"),
}

TOP_SCHEMA = {
    "model": Field(dict, {}, "name, derivative bandwidth, standstill threshold"),
    "terms": Field(dict, REQUIRED, "declared terms and their parameters"),
    "controller": Field(dict, {}, "the drive's controller (for the replay)"),
    "closure": Field(dict, {}, "search settings"),
}


@dataclass(frozen=True)
class ControllerSpec:
    """P position loop and P(I) velocity loop, Eq. (5.4), SI: N·s/m, 1/s, s (inf: no
    integral action), Hz, Hz, s, N."""

    K_p: float
    K_v: float
    T_i: float
    f_velocity: float
    f_position: float
    delay: float
    force_limit: float
    velocity_feedforward: bool


@dataclass(frozen=True)
class ModelSpec:
    """A parsed model config: the declared model, its filter settings, controller, search."""

    model: Model
    bandwidth: float
    standstill: float
    controller: ControllerSpec | None
    options: ClosureOptions
    holdout_fraction: float


def parse_model_config(raw: Mapping[str, Any]) -> ModelSpec:
    """Validate a parsed model config; raises `ConfigError` naming the field."""
    top = validate_table(raw, TOP_SCHEMA, "config")
    head = validate_table(top["model"], MODEL_SCHEMA, "model")
    terms = tuple(_term(name, table) for name, table in top["terms"].items())
    names = {t.name for t in terms}
    if "inertia" not in names:
        raise ConfigError("terms.inertia: required (the rigid-body mass M_kg)")
    for term in terms:
        missing = [r for r in term.effect.requires if r not in names]
        if missing:
            raise ConfigError(f"terms.{term.name}: needs terms.{missing[0]} as well")
    closure = validate_table(top["closure"], CLOSURE_SCHEMA, "closure")
    try:
        options = ClosureOptions(closure["bic_threshold"], closure["min_explained"],
                                 closure["max_effects"], tuple(closure["candidates"]))
    except ValueError as exc:
        raise ConfigError(f"closure.{exc}") from None
    controller = _controller(top["controller"]) if top["controller"] else None
    return ModelSpec(Model(terms, head["name"]), head["bandwidth_Hz"], head["standstill"],
                     controller, options, closure["holdout_fraction"])


def _term(name: str, table: Any) -> Term:
    """One declared term: each parameter fixed (number), free ("free") or both (table)."""
    if name in RETIRED:
        raise ConfigError(f"terms.{name}: retired: {RETIRED[name]}")
    if name not in EFFECTS:
        raise ConfigError(f"terms.{name}: unknown term (known: {', '.join(EFFECTS)})")
    if not isinstance(table, dict):
        raise ConfigError(f"terms.{name}: must be a table of parameters")
    effect = EFFECTS[name]
    schema = {p.key: Field((float, str, dict), None, p.doc) for p in effect.parameters}
    given = validate_table(table, schema, f"terms.{name}")
    values, free = effect.defaults(), set()
    for p in effect.parameters:
        value, is_free = _parameter(effect, p.key, given[p.key], f"terms.{name}.{p.key}")
        values[p.key] = value
        if is_free:
            free.add(p.key)
    return Term(effect, values, frozenset(free))


def _parameter(effect: Effect, key: str, given: Any, path: str) -> tuple[float, bool]:
    """(SI value, free) of one parameter from a number, "free", {value, free} or nothing."""
    p = effect.parameter(key)
    if given is None:
        return p.default, not p.setting
    if isinstance(given, str):
        if given != "free":
            raise ConfigError(f'{path}: must be a number, "free" or {{ value, free }} '
                              f"(got {given!r})")
        if p.setting:
            raise ConfigError(f"{path}: a setting, declared but never fitted")
        return p.default, True
    if isinstance(given, dict):
        entry = validate_table(given, {"value": Field(float, None, "value"),
                                       "free": Field(bool, False, "fit it")}, path)
        if entry["free"] and p.setting:
            raise ConfigError(f"{path}.free: a setting, declared but never fitted")
        value = p.default if entry["value"] is None else entry["value"] * p.to_si
        return _checked(p, value, path), entry["free"]
    return _checked(p, float(given) * p.to_si, path), False


def _checked(p: Parameter, value: float, path: str) -> float:
    """`value` (SI) if finite and within the parameter's bounds."""
    if not (math.isfinite(value) and p.lower <= value <= p.upper):
        raise ConfigError(f"{path}: must lie in [{p.lower / p.to_si:g}, {p.upper / p.to_si:g}] "
                          f"{p.unit} (got {value / p.to_si:g})")
    return value


def _controller(table: Mapping[str, Any]) -> ControllerSpec:
    c = validate_table(table, CONTROLLER_SCHEMA, "controller")
    return ControllerSpec(
        K_p=c["K_p_Ns_m"], K_v=c["K_v_1_s"],
        T_i=c["T_i_ms"] * 1e-3 if c["T_i_ms"] > 0.0 else math.inf,
        f_velocity=c["f_velocity_Hz"], f_position=c["f_position_Hz"],
        delay=c["delay_ms"] * 1e-3, force_limit=c["force_limit_N"],
        velocity_feedforward=c["velocity_feedforward"],
    )
