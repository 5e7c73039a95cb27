"""The milling process at the tool of the simulated bench (Ch. 6.2–6.3), one bus cycle a step.

`SmfeWorld.step` runs in the simulated drive's SYNC handler, right after the axis physics:
  1. the spindle inverter advances one bus cycle (`SimulatedSpindleInverter.advance`); its
     actual speed, interpolated linearly over the cycle, integrates to the spindle angle θ;
  2. the feed travel is the axis's load (tip) position, interpolated linearly over the cycle;
  3. `MillingProcess.advance` cuts the cycle's DAQ samples (10 at 10 kHz, 1 ms): chip thickness
     Eq. (6.1) with the regenerative term Eq. (6.2), tooth forces Eqs. (6.3–6.5) on the modal
     structure at the tool (Eqs. 6.6–6.8);
  4. the samples go to the serial DAQ (`SimulatedSerialDaq.push`): tool- and workpiece-side
     accelerations with Gaussian sensor noise, Eq. (6.18), and the dynamometer under the
     workpiece, which measures the force on the workpiece, −F.

The static chip is the feed travel since the previous tooth passed the same angle (looked up
on the recorded spindle angle, as in `models.milling.simulate_smfe_cut`), so a feed held at
f_z·Z·N gives exactly f_z per tooth while the spindle accelerates, and the axis's own
tracking error shows up in the chip. The cut does not load the feed axis: the lab-bench
flexure (1.68 N/µm) models a tool tip, not a machine table. The tool engages while the feed
travel lies inside a lane of the workpiece (`CutLane`); lanes switch on and off at their
edges (no entry arc).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from numba import njit

from feedbench.config import ConfigError, Field, non_negative, one_of, positive, validate_table
from feedbench.models.milling import (
    MILLING_MODES,
    SMFE_SENSOR_NOISE,
    TABLE_6_1,
    CuttingCoefficients,
    Tool,
    chip_thickness,
    engagement_angles,
    screen,
    tooth_force,
)
from feedbench.models.structure import POINT_DOF, SMFE_TOOL_STRUCTURE, ModalStructure, modal_step
from feedbench.protocols.serial_frames import CHANNEL_INDEX, CHANNELS
from feedbench.units import N_PER_UM

_JIT = {"cache": True, "error_model": "numpy"}
NOISE_BLOCK_CYCLES = 50
"""Cycles of accelerometer noise drawn at once (`SmfeWorld._noise_rows`): 1000 took 2–7 ms
at 10 samples a cycle, 43–66 ms at 50–100, inside one SYNC (late TPDOs in real time)."""

ACCELEROMETERS = ("acc_tool_x", "acc_tool_y", "acc_tool_z", "acc_work_x", "acc_work_y",
                  "acc_work_z")
DYNAMOMETER = ("dyn_fx", "dyn_fy", "dyn_fz")
_ACC_COLUMNS = np.array([CHANNEL_INDEX[name] for name in ACCELEROMETERS])
_DYN_COLUMNS = np.array([CHANNEL_INDEX[name] for name in DYNAMOMETER])

STRUCTURE_SCHEMA = {
    "f_n_Hz": Field(list, None, "natural frequency of each mode (Hz)", positive),
    "zeta": Field(list, None, "damping ratio of each mode", positive),
    "k_N_um": Field(list, None, "modal stiffness of each mode (N/µm)", positive),
    "shapes": Field(list, None, "mode shape (x, y, z) of each mode, one mode after another"),
}

MILLING_SCHEMA = {
    "tool_diameter_mm": Field(float, 80.0, "milling tool diameter D (mm)", positive),
    "teeth": Field(int, 2, "number of teeth Z", positive),
    "lead_angle_deg": Field(float, 45.0, "lead angle κ (deg)", positive),
    "K_tc_N_mm2": Field(float, TABLE_6_1.K_tc * 1e-6, "tangential shear coefficient (N/mm²)"),
    "K_rc_N_mm2": Field(float, TABLE_6_1.K_rc * 1e-6, "radial shear coefficient (N/mm²)"),
    "K_ac_N_mm2": Field(float, TABLE_6_1.K_ac * 1e-6, "axial shear coefficient (N/mm²)"),
    "K_te_N_mm": Field(float, TABLE_6_1.K_te * 1e-3, "tangential edge coefficient (N/mm)"),
    "K_re_N_mm": Field(float, TABLE_6_1.K_re * 1e-3, "radial edge coefficient (N/mm)"),
    "K_ae_N_mm": Field(float, TABLE_6_1.K_ae * 1e-3, "axial edge coefficient (N/mm)"),
    "noise_m_s2": Field(list, list(SMFE_SENSOR_NOISE),
                        "accelerometer noise std x, y, z (m/s²), Eq. (6.18)", non_negative),
    "seed": Field(int, 0, "seed of the sensor noise"),
    "min_rpm": Field(float, 30.0, "slowest spindle speed whose tooth period the regeneration "
                     "history covers (rpm)", positive),
    "tool": Field(dict, {}, "modal structure at the tool (default: Table 6.2)"),
    "workpiece": Field(dict, {}, "modal structure of the workpiece (default: rigid)"),
}

LANE_SCHEMA = {
    "mode": Field(str, None, "down, up or central milling", one_of(*MILLING_MODES)),
    "a_e_mm": Field(float, None, "radial engagement (mm)", positive),
    "a_p_mm": Field(float, None, "axial depth of cut (mm)", positive),
    "start_mm": Field(float, None, "feed travel where the lane begins (mm)"),
    "stop_mm": Field(float, None, "feed travel where the lane ends (mm)"),
}


@dataclass(frozen=True)
class CutLane:
    """A prepared stretch of workpiece along the feed: travel [start, stop) (m), one cut."""

    start: float
    stop: float
    mode: str
    a_e: float
    a_p: float


class MillingProcess:
    """The cut at the tool, advanced block by block with its state (modes, surface history).

    structure: 3 directions (tool; rigid workpiece) or 6 (tool rows 0–2, workpiece 3–5); the
    tool takes the cutting force F, the workpiece −F. `min_rpm` sizes the history: a tooth
    period longer than 60/(Z·min_rpm) s looks up the oldest sample kept.
    """

    def __init__(self, structure: ModalStructure, tool: Tool, coeffs: CuttingCoefficients,
                 min_rpm: float = 30.0) -> None:
        if structure.n_dof not in (POINT_DOF, 2 * POINT_DOF):
            raise ValueError(f"structure: expected 3 or 6 directions, got {structure.n_dof}")
        self.structure = structure
        self.tool = tool
        self.coeffs = coeffs
        self.min_rpm = min_rpm
        relative = np.array(structure.shapes[:POINT_DOF])
        if structure.n_dof == 2 * POINT_DOF:
            relative -= structure.shapes[POINT_DOF:]
        self._relative = relative
        self._shapes = np.array(structure.shapes)
        self._mass, self._damping = structure.mass, structure.damping
        self._stiffness = np.array(structure.k)
        self._K = coeffs.as_array()
        n_modes = structure.f_n.size
        self._q, self._qd, self._qdd = np.zeros(n_modes), np.zeros(n_modes), np.zeros(n_modes)
        self._dt = 0.0
        self._ring_theta = np.zeros(0)
        self._ring_state = np.zeros((1 + POINT_DOF, 0))
        self._counters = np.zeros(2, dtype=np.int64)
        # compile here, not in the first SYNC (numba takes seconds the first time)
        copy.deepcopy(self).advance(np.zeros(1), np.zeros(1), None, 1e-4)

    def advance(self, theta: np.ndarray, travel: np.ndarray, lane: CutLane | None,
                dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Cut n samples dt (s) apart: spindle angle θ (rad) and feed travel (m) at each.

        lane: the engagement of this block, None when out of the material. Returns the force
        on the tool (3 × n, N) and the accelerations (n_dof × n, m/s², noise-free).
        """
        if dt != self._dt:
            self._restart_history(dt)
        n = len(theta)
        force = np.zeros((POINT_DOF, n))
        acceleration = np.zeros((self.structure.n_dof, n))
        engaged, phi_en, phi_ex, width = False, 0.0, 0.0, 0.0
        if lane is not None:
            engaged = True
            phi_en, phi_ex = engagement_angles(lane.a_e, self.tool.D, lane.mode)
            width = lane.a_p / math.sin(self.tool.kappa)
        _cut_block(np.ascontiguousarray(theta, dtype=float),
                   np.ascontiguousarray(travel, dtype=float), engaged, phi_en, phi_ex, width,
                   self.tool.Z, self.tool.kappa, self._K, self._relative, self._shapes,
                   self._mass, self._damping, self._stiffness, dt, self._q, self._qd, self._qdd,
                   self._ring_theta, self._ring_state, self._counters, force, acceleration)
        return force, acceleration

    def _restart_history(self, dt: float) -> None:
        """A new sample period: a fresh surface history long enough for `min_rpm`."""
        capacity = int(math.ceil(60.0 / (self.tool.Z * self.min_rpm) / dt)) + 2
        self._dt = dt
        self._ring_theta = np.zeros(capacity)
        self._ring_state = np.zeros((1 + POINT_DOF, capacity))
        self._counters[:] = 0


@njit(**_JIT)
def _previous_pass(ring_theta, counters, target):
    """Absolute sample index p and weight w with θ_p ≤ target < θ_(p+1) in the history.

    Searches forward from the last answer (the angle never decreases); clamps to the oldest
    sample kept when the target is older (spindle slower than `min_rpm`, or just started).
    """
    capacity = ring_theta.size
    newest = counters[0] - 1
    oldest = max(0, newest + 1 - capacity)
    p = max(counters[1], oldest)
    if target < ring_theta[p % capacity]:
        counters[1] = p
        return p, 0.0
    while p + 1 <= newest and ring_theta[(p + 1) % capacity] <= target:
        p += 1
    counters[1] = p
    if p == newest:
        return p, 0.0
    low, high = ring_theta[p % capacity], ring_theta[(p + 1) % capacity]
    return p, (target - low) / (high - low) if high > low else 0.0


@njit(**_JIT)
def _cut_block(theta, travel, engaged, phi_en, phi_ex, width, Z, kappa, K, relative, shapes,
               mass, damping, stiffness, dt, q, qd, qdd, ring_theta, ring_state, counters,
               force, acceleration):
    """Fill force (3 × n) and acceleration (n_dof × n); see `MillingProcess.advance`.

    ring_state rows: feed travel, then the relative tool–workpiece displacement x, y, z.
    """
    capacity = ring_theta.size
    n_modes = q.size
    pitch = 2.0 * np.pi / Z
    modal_force = np.zeros(n_modes)
    lagged = np.empty(1 + POINT_DOF)
    for k in range(theta.size):
        slot = counters[0] % capacity
        ring_theta[slot] = theta[k]
        ring_state[0, slot] = travel[k]
        for i in range(POINT_DOF):
            total = 0.0
            for m in range(n_modes):
                total += relative[i, m] * q[m]
            ring_state[1 + i, slot] = total
        counters[0] += 1
        if engaged:
            p, w = _previous_pass(ring_theta, counters, theta[k] - pitch)
            a, b = p % capacity, (p + 1) % capacity
            for i in range(1 + POINT_DOF):
                lagged[i] = (1.0 - w) * ring_state[i, a] + w * ring_state[i, b]
            f_z = travel[k] - lagged[0]
            for j in range(Z):
                phi = theta[k] + j * pitch
                if screen(phi, phi_en, phi_ex):
                    h = chip_thickness(phi, f_z, kappa, ring_state[1, slot] - lagged[1],
                                       ring_state[2, slot] - lagged[2],
                                       ring_state[3, slot] - lagged[3])
                    f = tooth_force(phi, max(h, 0.0), width, kappa, K)
                    for i in range(POINT_DOF):
                        force[i, k] += f[i]
        for m in range(n_modes):
            total = 0.0
            for i in range(POINT_DOF):
                total += relative[i, m] * force[i, k]
            modal_force[m] = total
        modal_step(q, qd, modal_force, mass, damping, stiffness, dt, qdd)
        for i in range(shapes.shape[0]):
            total = 0.0
            for m in range(n_modes):
                total += shapes[i, m] * qdd[m]
            acceleration[i, k] = total


class Workpiece:
    """Lanes of workpiece along the feed travel; `lane_at(travel)` is the one the tool is in."""

    def __init__(self, lanes: Sequence[CutLane] = ()) -> None:
        self.lanes = tuple(lanes)

    def lane_at(self, travel: float) -> CutLane | None:
        for lane in self.lanes:
            if lane.start <= travel < lane.stop:
                return lane
        return None


class SmfeWorld:
    """The milling process wired to the bench's simulated devices; `step()` once per SYNC.

    feed_position: the axis's load position (m) after the cycle's physics (the drive's
    `simulator.tip_position`); inverter: `SimulatedSpindleInverter`; daq:
    `SimulatedSerialDaq` (its rate sets the process's sample period).
    """

    def __init__(self, process: MillingProcess, workpiece: Workpiece,
                 feed_position: Callable[[], float], inverter, daq, cycle_s: float,
                 noise_std: Sequence[float] = SMFE_SENSOR_NOISE, seed: int = 0) -> None:
        self.process = process
        self.workpiece = workpiece
        self.feed_position = feed_position
        self.inverter = inverter
        self.daq = daq
        self.cycle_s = cycle_s
        self._noise = np.tile(np.asarray(noise_std, dtype=float), 2)
        self._rng = np.random.default_rng(seed)
        self._noise_block = np.zeros((0, 2 * POINT_DOF))
        self._noise_used = 0
        self._fraction = np.zeros(0)
        self._theta = 0.0
        self._omega = inverter.speed_rad_s
        self._travel = feed_position()
        self._force = np.zeros((POINT_DOF, 1))
        _interpolated(0.0, 0.0, 0.0, 0.0, 0.0, np.ones(1), 0.0)  # compiled here, not at a SYNC

    @property
    def force(self) -> np.ndarray:
        """Mean force on the tool over the last cycle (N); computed when asked."""
        return self._force.mean(axis=1)

    def step(self) -> None:
        """One bus cycle: spindle, feed, cut, and the cycle's samples to the DAQ."""
        self.inverter.advance(self.cycle_s)
        n = self.daq.samples_per_cycle
        if self._fraction.size != n:
            self._fraction = np.arange(1, n + 1) / n
        dt = self.cycle_s / n
        travel_now = self.feed_position()
        theta, travel, omega_end = _interpolated(
            self._omega, self.inverter.speed_rad_s, self._theta, self._travel, travel_now,
            self._fraction, 0.5 * dt)
        force, acceleration = self.process.advance(
            theta, travel, self.workpiece.lane_at(travel_now), dt)
        self._theta, self._omega, self._travel = float(theta[-1]), omega_end, travel_now
        self._force = force
        self.daq.push(self._samples(force, acceleration))

    def _samples(self, force: np.ndarray, acceleration: np.ndarray) -> np.ndarray:
        """The DAQ's 12 inputs for the cycle: accelerometers with noise, dynamometer −F."""
        n = force.shape[1]
        samples = np.zeros((n, len(CHANNELS)))
        accelerometers = self._noise_rows(n)
        accelerometers[:, :acceleration.shape[0]] += acceleration.T
        samples[:, _ACC_COLUMNS] = accelerometers
        samples[:, _DYN_COLUMNS] = -force.T
        return samples

    def _noise_rows(self, n: int) -> np.ndarray:
        """The accelerometers' noise of the next n samples, drawn `NOISE_BLOCK_CYCLES` cycles
        at a time (the same numbers as a draw per cycle: the generator fills in order)."""
        if self._noise_used + n > len(self._noise_block):
            self._noise_block = self._rng.standard_normal(
                (NOISE_BLOCK_CYCLES * n, 2 * POINT_DOF)) * self._noise
            self._noise_used = 0
        rows = self._noise_block[self._noise_used:self._noise_used + n].copy()
        self._noise_used += n
        return rows


@njit(**_JIT)
def _interpolated(omega_start, omega_end, theta_start, travel_start, travel_end, fraction,
                  half_dt):
    """A cycle's spindle angle θ and feed travel at its samples, the speed and the travel
    linear over the cycle from their values at its start to those at its end (`fraction`:
    k/n, k = 1..n); θ by the trapezoidal rule (`half_dt`: half the sample period). The
    arithmetic of the numpy expressions it replaces, in their order (bit for bit); returns
    (θ, travel, the speed at the last sample)."""
    n = fraction.size
    theta = np.empty(n)
    travel = np.empty(n)
    previous = omega_start
    total = 0.0
    omega = omega_start
    for k in range(n):
        omega = omega_start + (omega_end - omega_start) * fraction[k]
        total += half_dt * (omega + previous)
        theta[k] = theta_start + total
        travel[k] = travel_start + (travel_end - travel_start) * fraction[k]
        previous = omega
    return theta, travel, omega


def structure_from_table(table: Mapping[str, Any], path: str) -> ModalStructure | None:
    """A `ModalStructure` from a ``f_n_Hz, zeta, k_N_um, shapes`` table (None if empty)."""
    t = validate_table(table, STRUCTURE_SCHEMA, path)
    if not table:
        return None
    missing = [key for key, value in t.items() if value is None]
    if missing:
        raise ConfigError(f"{path}.{missing[0]}: required when {path} is given")
    n_modes = len(t["f_n_Hz"])
    if len(t["shapes"]) != POINT_DOF * n_modes:
        raise ConfigError(f"{path}.shapes: expected {POINT_DOF * n_modes} numbers "
                          f"(x, y, z per mode), got {len(t['shapes'])}")
    try:
        return ModalStructure(f_n=t["f_n_Hz"], zeta=t["zeta"],
                              k=np.asarray(t["k_N_um"], dtype=float) * N_PER_UM,
                              shapes=np.reshape(t["shapes"], (n_modes, POINT_DOF)).T)
    except ValueError as error:
        raise ConfigError(f"{path}: {error}") from None


def lanes_from_list(items: Sequence[Mapping[str, Any]], path: str) -> list[CutLane]:
    """Workpiece lanes from tables of ``mode, a_e_mm, a_p_mm, start_mm, stop_mm``."""
    lanes = []
    for i, item in enumerate(items):
        t = validate_table(item, LANE_SCHEMA, f"{path}[{i}]")
        if not t["start_mm"] < t["stop_mm"]:
            raise ConfigError(f"{path}[{i}].stop_mm: must be above start_mm")
        lanes.append(CutLane(t["start_mm"] * 1e-3, t["stop_mm"] * 1e-3, t["mode"],
                             t["a_e_mm"] * 1e-3, t["a_p_mm"] * 1e-3))
    return lanes


def build_process(table: Mapping[str, Any]) -> tuple[MillingProcess, dict[str, Any]]:
    """The milling process of a ``[bench.world.milling]`` table and its validated values."""
    t = validate_table(table, MILLING_SCHEMA, "bench.world.milling")
    tool_structure = structure_from_table(t["tool"], "bench.world.milling.tool") \
        or SMFE_TOOL_STRUCTURE
    workpiece = structure_from_table(t["workpiece"], "bench.world.milling.workpiece")
    structure = tool_structure if workpiece is None else \
        ModalStructure.tool_and_workpiece(tool_structure, workpiece)
    if len(t["noise_m_s2"]) != POINT_DOF:
        raise ConfigError("bench.world.milling.noise_m_s2: expected 3 standard deviations "
                          "(x, y, z)")
    try:
        tool = Tool(D=t["tool_diameter_mm"] * 1e-3, Z=t["teeth"],
                    kappa=math.radians(t["lead_angle_deg"]))
    except ValueError as error:
        raise ConfigError(f"bench.world.milling: {error}") from None
    coeffs = CuttingCoefficients(
        K_tc=t["K_tc_N_mm2"] * 1e6, K_rc=t["K_rc_N_mm2"] * 1e6, K_ac=t["K_ac_N_mm2"] * 1e6,
        K_te=t["K_te_N_mm"] * 1e3, K_re=t["K_re_N_mm"] * 1e3, K_ae=t["K_ae_N_mm"] * 1e3)
    return MillingProcess(structure, tool, coeffs, t["min_rpm"]), t
