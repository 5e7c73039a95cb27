"""The CiA 402 servo drive's object table, shared by both ends: the host driver
(`drivers.cia402`), the simulated drive and its EDS (`sim_backends.cia402_drive`, `eds`)
and the physics kernel behind it (`models._kernel`, which takes the mode codes).

Plain ints (numba compiles the kernel against the mode codes). Every object here is a VAR
at sub-index 0; the communication objects and PDO records are `protocols.cia301`'s.
Units on the bus (docs/ARCHITECTURE.md): position 1 nm, velocity 1 nm/s, the
torque objects in per mille of the rated force `RATED_TORQUE` (mN), the manufacturer
force objects in mN, the gains in SI (REAL32).
"""

from __future__ import annotations

# -- modes of operation (0x6060 / 0x6061) --------------------------------------------------

CSP, CSV, CST = 8, 9, 10
"""Cyclic synchronous position, velocity, torque."""
MODES = (CSP, CSV, CST)
"""The modes the physics kernel runs."""
PV = 3
"""Profile velocity: the drive ramps its own velocity command to 0x60FF at 0x6083 / 0x6084
and runs it as CSV (for third-party hosts such as canopen's BaseNode402)."""
DRIVE_MODES = (PV, *MODES)
"""The modes the simulated drive accepts in 0x6060."""


def mode_bit(mode: int) -> int:
    """The bit of 0x6502 (supported drive modes) that announces the profile mode code
    `mode` (1–10); 0 for any other code."""
    return 1 << (mode - 1) if 1 <= mode <= 10 else 0


SUPPORTED_MODES = 0x0384
"""0x6502 bits 2, 7, 8, 9: profile velocity and the three cyclic synchronous modes."""

DEVICE_TYPE = 0x00020192
"""Value of the device type object (`cia301.DEVICE_TYPE`): profile 402 (0x0192), servo drive."""

# -- profile objects (CiA 402) -------------------------------------------------------------

ABORT_CONNECTION_OPTION_CODE = 0x6007
"""What a lost heartbeat or SYNC does (`protocols.cia301` watchdogs); the simulated drive
has 1: fault, reached through the fault reaction (quick-stop ramp, then FAULT)."""
ERROR_CODE = 0x603F
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
QUICK_STOP_OPTION_CODE = 0x605A
"""How the drive stops on the quick-stop command (`QUICK_STOP_OPTIONS`)."""
FAULT_REACTION_OPTION_CODE = 0x605E
"""How the drive stops on a fault (`FAULT_REACTIONS`)."""
MODES_OF_OPERATION = 0x6060
MODES_OF_OPERATION_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064
FOLLOWING_ERROR_WINDOW = 0x6065
VELOCITY_ACTUAL = 0x606C
VELOCITY_WINDOW = 0x606D
TARGET_TORQUE = 0x6071
RATED_TORQUE = 0x6076
"""mN: a linear motor's rated force, the 1000 ‰ of the torque objects."""
TORQUE_ACTUAL = 0x6077
TARGET_POSITION = 0x607A
PROFILE_ACCELERATION = 0x6083
PROFILE_DECELERATION = 0x6084
"""nm/s²: the profile velocity ramps."""
QUICK_STOP_DECELERATION = 0x6085
VELOCITY_OFFSET = 0x60B1
TORQUE_OFFSET = 0x60B2
FOLLOWING_ERROR_ACTUAL = 0x60F4
TARGET_VELOCITY = 0x60FF
SUPPORTED_DRIVE_MODES = 0x6502

# -- manufacturer objects of the simulated drive (differ per vendor) ------------------------

GAIN_OBJECTS = {"K_p": 0x2001, "T_i": 0x2002, "K_v": 0x2003}
"""Cascade gains (Eq. 5.4: N·s/m, s, 1/s) by `CascadeGains` field name."""
FORCE_LIMIT = 0x2004
"""N."""
FORCE_ACTUAL = 0x2010
"""mN: the force the motor applies to the carriage."""
FORCE_OFFSET_FINE = 0x2011
"""mN, added to `TORQUE_OFFSET`."""
CYCLE_COUNTER = 0x2020
"""The SYNCs processed, 16 bit (wraps)."""
FAULT_INJECTION = 0x2030
"""An EMCY code written here faults the drive with it at the next SYNC."""

DEFAULT_RPDO_MAPS: dict[int, tuple[int, ...]] = {
    1: (CONTROLWORD, TARGET_POSITION, MODES_OF_OPERATION),  # 7 bytes
    2: (TARGET_VELOCITY, VELOCITY_OFFSET),  # 8 bytes
    3: (FORCE_OFFSET_FINE, TORQUE_OFFSET, TARGET_TORQUE),  # 8 bytes
}
DEFAULT_TPDO_MAPS: dict[int, tuple[int, ...]] = {
    1: (STATUSWORD, POSITION_ACTUAL, CYCLE_COUNTER),  # 8 bytes
    2: (VELOCITY_ACTUAL, FORCE_ACTUAL),  # 8 bytes
}
"""PDO maps of the simulated drive's EDS, which the host writes by SDO unless told others."""

# -- state machine -------------------------------------------------------------------------

NOT_READY = "NOT READY TO SWITCH ON"
SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
READY = "READY TO SWITCH ON"
SWITCHED_ON = "SWITCHED ON"
OPERATION_ENABLED = "OPERATION ENABLED"
QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
FAULT_REACTION = "FAULT REACTION ACTIVE"
FAULT = "FAULT"
"""State names (canopen's p402 spelling, which decodes the statusword on the host)."""
STATE_BITS = {
    SWITCH_ON_DISABLED: 0x0040,
    READY: 0x0031,
    SWITCHED_ON: 0x0033,
    OPERATION_ENABLED: 0x0037,
    QUICK_STOP_ACTIVE: 0x0017,
    FAULT_REACTION: 0x000F,
    FAULT: 0x0008,
}
"""Statusword of each state the drive reports: state bits incl. bit 4 voltage enabled and
bit 5 quick stop (1 = not active)."""
SW_FAULT = 0x0008
SW_REMOTE = 0x0200
SW_TARGET_REACHED = 0x0400
"""In quick stop active: the stop is complete."""
SW_FOLLOWS_COMMAND = 0x1000
SW_FOLLOWING_ERROR = 0x2000

TRANSITIONS = {
    (READY, "DISABLE VOLTAGE"): SWITCH_ON_DISABLED,  # 7
    (SWITCHED_ON, "DISABLE VOLTAGE"): SWITCH_ON_DISABLED,  # 10
    (OPERATION_ENABLED, "DISABLE VOLTAGE"): SWITCH_ON_DISABLED,  # 9
    (QUICK_STOP_ACTIVE, "DISABLE VOLTAGE"): SWITCH_ON_DISABLED,  # 12
    (READY, "QUICK STOP"): SWITCH_ON_DISABLED,  # 7
    (SWITCHED_ON, "QUICK STOP"): SWITCH_ON_DISABLED,  # 10
    (OPERATION_ENABLED, "QUICK STOP"): QUICK_STOP_ACTIVE,  # 11
    (SWITCH_ON_DISABLED, "SHUTDOWN"): READY,  # 2
    (SWITCHED_ON, "SHUTDOWN"): READY,  # 6
    (OPERATION_ENABLED, "SHUTDOWN"): READY,  # 8
    (READY, "SWITCH ON"): SWITCHED_ON,  # 3
    (OPERATION_ENABLED, "SWITCH ON"): SWITCHED_ON,  # 5 (disable operation)
    (READY, "ENABLE OPERATION"): OPERATION_ENABLED,  # 3 + 4
    (SWITCHED_ON, "ENABLE OPERATION"): OPERATION_ENABLED,  # 4
}
"""The device's state machine: (state, `command_of` the controlword) → next state (CiA 402
transition numbers); absent pairs leave the state unchanged. Quick-stop option code 2: no
transition 16 back to operation enabled."""
POWERED = (OPERATION_ENABLED, QUICK_STOP_ACTIVE, FAULT_REACTION)
"""States in which the drive's power stage is on."""

# -- how the drive stops (0x605A, 0x605E) --------------------------------------------------

STOP_COAST, STOP_SLOW_DOWN_RAMP, STOP_QUICK_RAMP, STOP_CURRENT_LIMIT, STOP_VOLTAGE_LIMIT = range(5)
"""Ramps a stop slows the axis on: none (the power stage off at once, the axis coasts), the
slow-down ramp (profile deceleration 0x6084), the quick-stop ramp (0x6085), at the current
(force) limit, at the voltage limit (CiA 402 option codes 0–4)."""
QUICK_STOP_OPTIONS = range(9)
"""0x605A codes: 0–4 stop on `STOP_*` and switch on disabled (0 at once); 5–8 stop on the
ramp of code − 4 and stay in quick stop active until the host disables the drive."""
FAULT_REACTIONS = range(5)
"""0x605E codes: stop on `STOP_*`, then FAULT."""


def quick_stop_ramp(option: int) -> int:
    """The `STOP_*` ramp of quick-stop option code `option` (0–8)."""
    return option - 4 if option > STOP_VOLTAGE_LIMIT else option


def quick_stop_holds(option: int) -> bool:
    """True if quick-stop option code `option` stays in quick stop active once stopped."""
    return option > STOP_VOLTAGE_LIMIT


# -- controlword (0x6040) ------------------------------------------------------------------

CW_SWITCH_ON_BIT, CW_ENABLE_VOLTAGE_BIT, CW_QUICK_STOP_BIT, CW_ENABLE_OPERATION_BIT = 1, 2, 4, 8
"""Controlword bits 0–3 (bit 2 low: quick stop)."""
CW_FAULT_RESET = 0x0080
"""Controlword bit 7: resets a fault on its rising edge."""
COMMANDS = {"DISABLE VOLTAGE": 0x00, "QUICK STOP": 0x02, "SHUTDOWN": 0x06, "SWITCH ON": 0x07,
            "ENABLE OPERATION": 0x0F}
"""Controlword of each command (canopen's p402 values); "SWITCH ON" from operation enabled
is disable operation (transition 5)."""


def command_of(controlword: int) -> str:
    """The command coded in controlword bits 0–3 (a `COMMANDS` name; bit 7 is an edge)."""
    if not controlword & CW_ENABLE_VOLTAGE_BIT:
        return "DISABLE VOLTAGE"
    if not controlword & CW_QUICK_STOP_BIT:
        return "QUICK STOP"
    if not controlword & CW_SWITCH_ON_BIT:
        return "SHUTDOWN"
    return "ENABLE OPERATION" if controlword & CW_ENABLE_OPERATION_BIT else "SWITCH ON"


EXTRAPOLATED_CYCLES = 50
"""Cyclic synchronous position: a cycle whose setpoint (0x607A in a synchronous RPDO) did not
come before its SYNC runs on the target extrapolated from the last two (the cyclic modes'
rule for a missing setpoint), for at most this many cycles in a row; then the drive holds
it. A host further behind than this stops the run ("host stalled")."""
FOLLOWING_ERROR_OFF = 0xFFFFFFFF
"""0x6065 value that switches the following-error check off."""

# -- emergency codes the simulated drive sends ---------------------------------------------

EMCY_FOLLOWING_ERROR = 0x8611
EMCY_INTERNAL_SOFTWARE = 0x6100
EMCY_PDO_LENGTH = 0x8210
