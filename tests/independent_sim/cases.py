"""The independent cases: an axis structure, the effect its world carries that the declared
model lacks (or none, or a declared parameter that is off), two recordings and the model.

Files of `write_case(name, directory)`, all in `directory`:
    <name>_data.csv / .toml          the fit recording and its sidecar
    <name>_validation.csv / .toml    a second recording (other seed, other feeds)
    <name>_model.toml                the declared model (…_free_model.toml: M, F_v free)
(<name>_tip_data.csv … with the optional tip accelerometer channel), in the documented
CSV + sidecar and model-config formats (README "Your own data: CSV + sidecar", "Model
config"). Written with the standard library and numpy only.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .excitation import Program, program_signals
from .plant import (
    PHYSICS_HZ, POSITION_STEPS, RECORD_STEPS, VELOCITY_STEPS, Drive, Friction, Plant, Run,
    Sensors, Spring, simulate,
)

FIT_PROGRAM = Program(feeds=(1.0, 3.0, 8.0, 16.0))
VALIDATION_PROGRAM = Program(feeds=(1.5, 5.0, 12.0), pulse_feed=6.0, pulse_force=-100.0,
                             chirp_feed=2.5, chirp_force=35.0, chirp_time=2.5)
VELOCITY_BANDWIDTH_HZ = 25.0
"""Velocity-loop bandwidth the cascade is tuned for: K_p = 2π f M, T_i = 4/(2π f),
K_v = 2π f / 4 (the symmetric-optimum spacing, a factor 4 between the loops)."""

FORCE_LIMIT_N = 3000.0
BANDWIDTH_HZ = 200.0
"""Derivative filter cut-off declared in every model: above the highest declared mode."""


@dataclass(frozen=True)
class Structure:
    """An axis as declared: motor-side mass, the structural mode (tip mass kg, motor-locked
    f_n Hz, ζ; tip mass 0: rigid), friction (N·s/m, N), force delay (ms); `third` adds a
    (mass kg, f Hz, ζ) behind the tip, beyond the derivative bandwidth."""

    motor_kg: float
    tip_kg: float = 0.0
    f_n_Hz: float = 1.0
    zeta: float = 0.0
    sigma: float = 150.0
    F_c: float = 30.0
    delay_ms: float = 0.5
    third: tuple[float, float, float] | None = None

    @property
    def total_kg(self) -> float:
        """Everything that moves with the motor at low frequency (kg)."""
        return self.motor_kg + self.tip_kg + (self.third[0] if self.third else 0.0)

    @property
    def modal_kg(self) -> float:
        """The mass on the structural spring (kg)."""
        return self.tip_kg + (self.third[0] if self.third else 0.0)


TWO_MASS = Structure(25.0, 15.0, 61.0, 0.012)
STRUCTURES = {
    "2mass": TWO_MASS,
    "2mass_stiff": Structure(60.0, 20.0, 110.0, 0.04, sigma=250.0, F_c=60.0, delay_ms=0.25),
    "2mass_soft": Structure(80.0, 30.0, 32.0, 0.05, sigma=300.0, F_c=80.0),
    "3mass": Structure(30.0, 12.0, 45.0, 0.02, sigma=200.0, F_c=40.0, third=(1.5, 400.0, 0.05)),
    "rigid": Structure(50.0, sigma=200.0, F_c=40.0),
    "2mass_light": Structure(38.0, 2.0, 90.0, 0.03),
}
MODE_GRID = {f"mode_{f_n:g}Hz_zeta{zeta:g}": Structure(25.0, 15.0, f_n, zeta)
             for f_n in (30.0, 120.0) for zeta in (0.01, 0.05)}
"""The corners of issue 13.4's range (f_n 30–120 Hz, ζ 0.01–0.05) on the 2-mass axis: with
the exact model declared the held-out error must stay within 1.5× the noise floor."""
STRUCTURES.update(MODE_GRID)


@dataclass(frozen=True)
class CaseSpec:
    """One case. injected: the closure effect expected first (None: clean;
    "recalibrate:<term>.<param>": a declared parameter is off); truth: the world's
    parameters (SI but for ms, Hz, m/min as named); kind: "effect" | "clean" |
    "recalibration". injected_free / kind_free: the same when mass and viscous friction are
    left free (a mass or viscous error is then no error at all)."""

    name: str
    injected: str | None
    truth: dict[str, float]
    kind: str
    structure: str = "2mass"
    plant: dict = field(default_factory=dict, repr=False)
    drive: dict = field(default_factory=dict, repr=False)
    declared: dict = field(default_factory=dict, repr=False)
    omit: tuple[str, ...] = ()
    injected_free: str | None = None
    kind_free: str = ""

    def expected(self, free_mass_viscous: bool) -> tuple[str | None, str]:
        """(injected, kind) in the exact or the free-mass-and-viscous variant."""
        if not free_mass_viscous:
            return self.injected, self.kind
        return self.injected_free, self.kind_free


@dataclass(frozen=True)
class CaseFiles:
    """The files of a case, and the validation record's noise floor (NRMSE of the
    force reading against the noiseless force, fraction)."""

    data_csv: Path
    validation_csv: Path
    model_toml: Path
    noise_floor: float


def _case(name: str, injected: str | None, kind: str, structure: str = "2mass",
          plant: dict | None = None, drive: dict | None = None, declared: dict | None = None,
          omit: tuple[str, ...] = (), free: tuple[str | None, str] | None = None) -> CaseSpec:
    """A case whose truth is its structure with the world's overrides (config units)."""
    s = STRUCTURES[structure]
    truth = {"M_kg": s.total_kg + (plant or {}).get("dM_kg", 0.0), "m_kg": s.modal_kg,
             "f_n_Hz": s.f_n_Hz, "zeta": s.zeta, "F_v_Ns_m": s.sigma, "F_c_N": s.F_c,
             "tau_ms": s.delay_ms, **(plant or {}), **(drive or {})}
    if not s.modal_kg:
        for key in ("m_kg", "f_n_Hz", "zeta"):
            del truth[key]
    injected_free, kind_free = free or (injected, kind)
    return CaseSpec(name, injected, truth, kind, structure, plant or {}, drive or {},
                    declared or {}, omit, injected_free, kind_free)


def _sized(effect: str, small: dict, large: dict, inside: str = "plant",
           injected: str | None = None, **common) -> list[CaseSpec]:
    """The small and the large case of one effect of the plant (or inside="drive"), named
    `effect`, expected to be found as `injected` (default: `effect`)."""
    return [_case(f"{effect}_{size}", injected or effect, "effect", **{inside: dict(world)},
                  **common)
            for size, world in (("small", small), ("large", large))]


_RIPPLE = {"pitch_mm": 5.0, "phase_deg": 40.0}
_CLEAN_FREE = (None, "clean")
_LIST = [
    *[_case(f"clean_{s}", None, "clean", s)
      for s in ("2mass", "2mass_stiff", "2mass_soft", "3mass", "rigid", *MODE_GRID)],
    *_sized("coulomb", {"F_c_N": 4.0}, {"F_c_N": 60.0}, omit=("coulomb",)),
    *_sized("stribeck", {"dF_s_N": 30.0, "v_s_mm_min": 1000.0},
            {"dF_s_N": 60.0, "v_s_mm_min": 1000.0}),
    *_sized("direction_dependent", {"dF_v_Ns_m": 55.0}, {"dF_v_Ns_m": 100.0},
            declared={"offset_N": 0.0}),
    *_sized("offset", {"offset_N": 3.0}, {"offset_N": 30.0}),
    *_sized("backlash", {"m_load_kg": 5.0, "F_load_N": 25.0, "width_um": 100.0},
            {"m_load_kg": 8.0, "F_load_N": 40.0, "width_um": 150.0}),
    *_sized("ripple", {"amplitude_N": 4.0, **_RIPPLE}, {"amplitude_N": 20.0, **_RIPPLE}),
    _case("structural_mode_small", "structural_mode", "effect", "2mass_light",
          omit=("structural_mode",)),
    _case("structural_mode_large", "structural_mode", "effect", omit=("structural_mode",)),
    *_sized("delay", {"tau_ms": 0.25}, {"tau_ms": 1.5}, "drive", omit=("delay",)),
    *_sized("cubic_stiffening", {"stiffening": 0.2}, {"stiffening": 0.6}),
    *_sized("inertia_mismatch", {"dM_kg": 3.0}, {"dM_kg": 8.0}, free=_CLEAN_FREE),
    *_sized("amplitude_nonlinearity", {"beta_per_kN": 0.5}, {"beta_per_kN": 1.2}, "drive"),
    *_sized("sensor_gain", {"gain": 1.07}, {"gain": 1.2}, "drive"),
    _case("recal_delay", "recalibrate:delay.tau_ms", "recalibration", drive={"tau_ms": 1.5}),
    _case("recal_fn", "recalibrate:structural_mode.f_n_Hz", "recalibration",
          declared={"f_n_Hz": TWO_MASS.f_n_Hz * 1.08}),
    _case("recal_zeta", "recalibrate:structural_mode.zeta", "recalibration",
          declared={"zeta": TWO_MASS.zeta * 2.0}),
    _case("recal_mass", "recalibrate:inertia.M_kg", "recalibration",
          declared={"M_kg": TWO_MASS.total_kg * 1.10}, free=_CLEAN_FREE),
    _case("recal_viscous", "recalibrate:viscous.F_v_Ns_m", "recalibration",
          declared={"F_v_Ns_m": TWO_MASS.sigma * 1.30}, free=_CLEAN_FREE),
    *_sized("backlash_drivetrain", {"play_um": 30.0}, {"play_um": 100.0}, injected="backlash"),
    *_sized("backlash_guided", {"play_um": 30.0, "F_table_N": 10.0},
            {"play_um": 100.0, "F_table_N": 10.0}, injected="backlash"),
    _case("second_mode", "second_mode", "effect",
          plant={"m2_kg": 3.0, "f2_Hz": 130.0, "zeta2": 0.02}),
    _case("ripple_long_pitch", "ripple", "effect",
          plant={"amplitude_N": 3.0, "pitch_mm": 60.0, "phase_deg": 90.0}),
    _case("channel_skew", "delay", "effect", plant={"skew_cycles": 0.375}),
]
CASES: dict[str, CaseSpec] = {case.name: case for case in _LIST}
"""Every case by name."""

STIFFENING_DEFLECTION_M = 40e-6
"""Cubic stiffening: the spring is stiffer by the case's `stiffening` share at this
deflection (m): k d (1 + stiffening (d / d_ref)²)."""


def world(case: CaseSpec) -> tuple[Plant, Drive]:
    """The simulated axis and drive of a case. A backlash load and a second mode's mass are
    carved out of the motor side, the backlash load's friction out of the motor's Coulomb
    level, the table's guideway friction (F_table_N) too: as declared, the axis's mass and
    friction include them, and only the play or the
    second mode is undeclared."""
    s, w = STRUCTURES[case.structure], case.truth
    load_N, table_N = w.get("F_load_N", 0.0), w.get("F_table_N", 0.0)
    masses, springs = _chain(s, w)
    friction = Friction(s.sigma, w["F_c_N"] - load_N - table_N, w.get("dF_s_N", 0.0),
                        w.get("v_s_mm_min", 1.0) * 1e-3 / 60.0, 2.0, w.get("dF_v_Ns_m", 0.0))
    backlash = ((w["m_load_kg"], load_N, w["width_um"] * 1e-6)
                if "m_load_kg" in w else None)
    ripple = (w.get("amplitude_N", 0.0), w.get("pitch_mm", 1.0) * 1e-3,
              math.radians(w.get("phase_deg", 0.0)))
    plant = Plant(masses, springs, friction, w.get("offset_N", 0.0), ripple, backlash, table_N)
    return plant, Drive(*_gains(s.total_kg), FORCE_LIMIT_N, w["tau_ms"] * 1e-3,
                        w.get("beta_per_kN", 0.0) * 1e-3, w.get("gain", 1.0))


def _chain(s: Structure, w: dict[str, float]) -> tuple[tuple[float, ...], tuple[Spring, ...]]:
    """Masses (kg) and springs of a structure with the world's overrides: a mass error, a
    load carved out, cubic stiffening or a play (µm) in the mode's spring, a second mode
    (kg, Hz, ζ) on its own spring from the motor."""
    second_kg = w.get("m2_kg", 0.0)
    masses = [s.motor_kg + w.get("dM_kg", 0.0) - w.get("m_load_kg", 0.0) - second_kg]
    springs = []
    if s.modal_kg:
        masses.append(s.tip_kg)
        springs.append(_spring(0, 1, s.modal_kg, s.f_n_Hz, s.zeta, w.get("stiffening", 0.0),
                               w.get("play_um", 0.0) * 1e-6))
    if s.third:
        masses.append(s.third[0])
        springs.append(_spring(1, 2, *s.third))
    if second_kg:
        masses.append(second_kg)
        springs.append(_spring(0, len(masses) - 1, second_kg, w["f2_Hz"], w["zeta2"]))
    return tuple(masses), tuple(springs)


def _spring(i: int, j: int, mass: float, f: float, zeta: float, stiffening: float = 0.0,
            play: float = 0.0) -> Spring:
    """The spring-damper that makes `mass` (kg) on it ring at f (Hz) with ζ when i is held,
    stiffer by the share `stiffening` at STIFFENING_DEFLECTION_M, with a play (m)."""
    omega = 2 * math.pi * f
    k = mass * omega ** 2
    return Spring(i, j, k, 2 * zeta * omega * mass,
                  k * stiffening / STIFFENING_DEFLECTION_M ** 2, play)


def sensors(case: CaseSpec) -> Sensors:
    """The case's sensors: the default ones, the position latched `skew_cycles` of a
    recording cycle before its time stamp (whole physics steps)."""
    return Sensors(position_skew=case.truth.get("skew_cycles", 0.0) * RECORD_STEPS / PHYSICS_HZ)


def _gains(mass: float) -> tuple[float, float, float]:
    """K_p (N·s/m), T_i (s), K_v (1/s) for a velocity loop of VELOCITY_BANDWIDTH_HZ."""
    omega = 2 * math.pi * VELOCITY_BANDWIDTH_HZ
    return omega * mass, 4.0 / omega, omega / 4.0


def record(case: CaseSpec, program: Program, seed: int) -> Run:
    """One recording of the case's world running `program`."""
    plant, drive = world(case)
    x, v, exc = program_signals(program, 1.0 / PHYSICS_HZ)
    return simulate(plant, drive, sensors(case), x, v, exc, seed)


def recordings(name: str) -> tuple[Run, Run]:
    """The fit and the validation recording of case `name` (in memory, as `write_case`
    writes them: FIT_PROGRAM and VALIDATION_PROGRAM, seeds crc32(name) and crc32(name) + 1);
    a few seconds per case."""
    case, seed = CASES[name], zlib.crc32(name.encode())
    return record(case, FIT_PROGRAM, seed), record(case, VALIDATION_PROGRAM, seed + 1)


_CACHE: dict[tuple[str, Path], float] = {}
"""Noise floors of the cases already written, by (name, directory)."""


def write_case(name: str, directory: Path, free_mass_viscous: bool = False,
               tip_channel: bool = False) -> CaseFiles:
    """Write a case's two recordings (once per directory and process) and its model config;
    `free_mass_viscous` declares M and F_v free instead of their values; `tip_channel` adds
    the tip accelerometer (`tip_acceleration`, m/s2) to recordings of an axis with a tip."""
    case = CASES[name]
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    stem = f"{name}_tip" if tip_channel else name
    data, validation = directory / f"{stem}_data.csv", directory / f"{stem}_validation.csv"
    key = (stem, directory.resolve())
    if key not in _CACHE:
        fit, held = recordings(name)
        _write_recording(data, fit, case, "fit", tip_channel)
        _write_recording(validation, held, case, "validation", tip_channel)
        _CACHE[key] = float(np.linalg.norm(held.force - held.force_clean)
                            / np.linalg.norm(held.force_clean))
    model = directory / f"{name}{'_free' if free_mass_viscous else ''}_model.toml"
    model.write_text(model_config(case, free_mass_viscous))
    return CaseFiles(data, validation, model, _CACHE[key])


COLUMNS = {"time": ("t_s", "s"), "position": ("x_mm", "mm"), "force": ("F_N", "N"),
           "reference": ("x_ref_mm", "mm"), "excitation": ("excitation_N", "N"),
           "tip_acceleration": ("a_tip_m_s2", "m/s2")}


def _write_recording(path: Path, run: Run, case: CaseSpec, part: str, tip_channel: bool
                     ) -> None:
    """The CSV (s, mm, N, m/s²) and its sidecar: the force is the mean command over each
    cycle, so it lags the cycle-end positions by half a cycle."""
    values = {"time": run.time, "position": run.position * 1e3, "force": run.force,
              "reference": run.reference * 1e3, "excitation": run.excitation}
    if tip_channel and run.tip_acceleration is not None:
        values["tip_acceleration"] = run.tip_acceleration
    columns = {channel: COLUMNS[channel] for channel in values}
    np.savetxt(path, np.column_stack(list(values.values())), delimiter=",", fmt="%.10g",
               comments="", header=",".join(column for column, _ in columns.values()))
    cycle_ms = 1e3 * RECORD_STEPS / PHYSICS_HZ
    lines = [f'name = "independent simulator: {case.name} ({part})"',
             f"force_lag_ms = {0.5 * cycle_ms!r}", "", "[columns]"]
    lines += [f'{channel} = "{column}"' for channel, (column, _) in columns.items()]
    lines += ["", "[units]"] + [f'{channel} = "{unit}"' for channel, (_, unit) in columns.items()]
    lines += ["", "[controller]", *_controller_lines(case)]
    path.with_suffix(".toml").write_text("\n".join(lines) + "\n")


def _controller_lines(case: CaseSpec) -> list[str]:
    """The drive's cascade as a model config's [controller] table (declared values)."""
    K_p, T_i, K_v = _gains(STRUCTURES[case.structure].total_kg)
    return [f"K_p_Ns_m = {K_p!r}", f"T_i_ms = {T_i * 1e3!r}", f"K_v_1_s = {K_v!r}",
            f"f_velocity_Hz = {PHYSICS_HZ / VELOCITY_STEPS!r}",
            f"f_position_Hz = {PHYSICS_HZ / POSITION_STEPS!r}",
            f"delay_ms = {_declared(case)['tau_ms']!r}", f"force_limit_N = {FORCE_LIMIT_N!r}",
            "velocity_feedforward = true"]


def _declared(case: CaseSpec) -> dict[str, float]:
    """The declared parameter values (config units): the structure's, or the case's own."""
    s = STRUCTURES[case.structure]
    values = {"M_kg": s.total_kg, "F_v_Ns_m": s.sigma, "F_c_N": s.F_c, "m_kg": s.modal_kg,
              "f_n_Hz": s.f_n_Hz, "zeta": s.zeta, "tau_ms": s.delay_ms, **case.declared}
    if "delay" in case.omit:
        values["tau_ms"] = 0.0
    return values


TERMS = {"inertia": ("M_kg",), "viscous": ("F_v_Ns_m",), "coulomb": ("F_c_N",),
         "offset": ("offset_N",), "structural_mode": ("m_kg", "f_n_Hz", "zeta"),
         "delay": ("tau_ms",)}


def model_config(case: CaseSpec, free_mass_viscous: bool = False) -> str:
    """The declared model of a case as model-config TOML text."""
    s, values = STRUCTURES[case.structure], _declared(case)
    present = [t for t in TERMS if t not in case.omit
               and (t != "structural_mode" or s.modal_kg)
               and (t != "offset" or "offset_N" in case.declared)]
    free = {"M_kg", "F_v_Ns_m"} if free_mass_viscous else set()
    lines = [f"# Declared model of the independent case {case.name!r}"
             f"{' (M and F_v free)' if free_mass_viscous else ''}.", "",
             "[model]", f'name = "independent {case.name}"', f"bandwidth_Hz = {BANDWIDTH_HZ!r}"]
    for term in present:
        lines += ["", f"[terms.{term}]"]
        lines += [f'{key} = "free"' if key in free else f"{key} = {float(values[key])!r}"
                  for key in TERMS[term]]
    lines += ["", "[controller]", *_controller_lines(case)]
    return "\n".join(lines) + "\n"
