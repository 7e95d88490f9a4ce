"""The autopilot identity the vehicles follow: ArduPlane's, declared once.

Why ArduPlane: the UAVs are fixed-wing; MAVProxy (already used against the vehicles) and
ArduPilot SITL's ports are the anchor of issue 21; MAVSDK and QGroundControl know ArduPilot's
custom modes.  Every consumer (the autopilot core, the MAVLink endpoint's HEARTBEAT,
EXTENDED_SYS_STATE and MISSION_CURRENT, the tests) reads the numbers from here:

* HEARTBEAT.autopilot = MAV_AUTOPILOT_ARDUPILOTMEGA, type = MAV_TYPE_FIXED_WING;
* custom_mode = the ArduPlane mode number, taken from pymavlink's own table
  (``mavutil.mode_mapping_bynumber(MAV_TYPE_FIXED_WING)`` = ``mavutil.mode_mapping_apm``,
  the table MAVProxy's ``mode X`` and MAVSDK's ArduPilot mode decoding use), never typed here;
* base_mode as ArduPlane computes it (ArduPlane/GCS_MAVLink_Plane.cpp ``base_mode()``):
  CUSTOM_MODE_ENABLED always; STABILIZE_ENABLED in every mode but MANUAL; GUIDED_ENABLED in
  the navigation modes (AUTO, RTL, LOITER, GUIDED, CIRCLE, TAKEOFF, AUTOLAND, AVOID_ADSB,
  THERMAL); MANUAL_INPUT_ENABLED in MANUAL/TRAINING/ACRO and, with stick mixing on (ArduPlane's
  default STICK_MIXING = 1), in every mode; SAFETY_ARMED when armed.  (AUTO_ENABLED is never
  set: ArduPlane does not.)  So AUTO armed = 217, AUTO disarmed = 89, MANUAL disarmed = 65.
* system_status (``vehicle_system_status()``): ACTIVE when flying, else STANDBY;
* EXTENDED_SYS_STATE.landed_state from the flight phase (:func:`landed_state`);
* missions: item 0 is home (its uploaded content is ignored, home stays the vehicle's; a
  download returns home), flying starts at item 1; MISSION_CURRENT.total excludes home
  (:func:`mission_total`); the end of a mission in AUTO switches to RTL (ArduPlane/
  commands_logic.cpp ``exit_mission_callback``: "Mission complete, changing mode to RTL").
"""
from __future__ import annotations

import math

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

AUTOPILOT = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
MAV_TYPE = mavlink.MAV_TYPE_FIXED_WING

#: ArduPlane mode number -> name, pymavlink's table (MAVProxy and MAVSDK decode with it)
MODE_NAMES: dict[int, str] = dict(mavutil.mode_mapping_bynumber(MAV_TYPE))
#: name -> number
MODES: dict[str, int] = {v: k for k, v in MODE_NAMES.items()}

MANUAL, CIRCLE, STABILIZE, TRAINING, ACRO = (MODES[n] for n in ("MANUAL", "CIRCLE", "STABILIZE", "TRAINING", "ACRO"))
FBWA, FBWB, CRUISE, AUTO, RTL = (MODES[n] for n in ("FBWA", "FBWB", "CRUISE", "AUTO", "RTL"))
LOITER, TAKEOFF, GUIDED, AUTOLAND = (MODES[n] for n in ("LOITER", "TAKEOFF", "GUIDED", "AUTOLAND"))

#: modes flown by the pilot's sticks: with no RC input they fly straight and level (centred sticks)
PILOT_MODES = frozenset({MANUAL, STABILIZE, TRAINING, ACRO, FBWA, FBWB, CRUISE})
#: modes the autopilot flies itself
NAV_MODES = frozenset({AUTO, RTL, LOITER, CIRCLE, GUIDED, TAKEOFF, AUTOLAND})
#: every mode a GCS may set on these vehicles
SUPPORTED_MODES = PILOT_MODES | NAV_MODES
#: ArduPlane's modes that get GUIDED_ENABLED in base_mode
_GUIDED_FLAG_MODES = frozenset(MODES[n] for n in ("AUTO", "RTL", "LOITER", "THERMAL", "AVOID_ADSB", "GUIDED",
                                                  "CIRCLE", "TAKEOFF", "AUTOLAND", "QRTL", "LOITERALTQLAND"))
_MANUAL_FLAG_MODES = frozenset({MANUAL, TRAINING, ACRO, MODES["QACRO"]})

#: ArduPlane's STICK_MIXING default (1, FBW): MANUAL_INPUT_ENABLED in every mode
STICK_MIXING = True

# flight phases (the autopilot's); values chosen freely, mapped to MAV_LANDED_STATE below
ON_GROUND, TAKING_OFF, FLYING, LANDING, LANDED = 0, 1, 2, 3, 4
PHASE_NAMES = {ON_GROUND: "on ground", TAKING_OFF: "taking off", FLYING: "flying", LANDING: "landing",
               LANDED: "landed"}
_LANDED_STATE = {ON_GROUND: mavlink.MAV_LANDED_STATE_ON_GROUND, TAKING_OFF: mavlink.MAV_LANDED_STATE_TAKEOFF,
                 FLYING: mavlink.MAV_LANDED_STATE_IN_AIR, LANDING: mavlink.MAV_LANDED_STATE_LANDING,
                 LANDED: mavlink.MAV_LANDED_STATE_ON_GROUND}
AIRBORNE = frozenset({TAKING_OFF, FLYING, LANDING})

#: MAV_CMD_COMPONENT_ARM_DISARM param2 that forces (ArduPilot, MAVLink spec)
FORCE_MAGIC = 21196

#: the item index flying starts at (item 0 is home)
FIRST_ITEM = 1


def mode_name(custom_mode: int) -> str:
    """ArduPlane's name of a mode number ("MODE(99)" for a number it does not have)."""
    return MODE_NAMES.get(int(custom_mode), f"MODE({int(custom_mode)})")


def base_mode(custom_mode: int, armed: bool) -> int:
    """HEARTBEAT.base_mode as ArduPlane computes it (module docstring)."""
    m = int(custom_mode)
    flags = 0
    if m in _MANUAL_FLAG_MODES:
        flags = mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
    elif m in _GUIDED_FLAG_MODES:
        flags = mavlink.MAV_MODE_FLAG_GUIDED_ENABLED | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
    elif m in MODE_NAMES and m != MODES["INITIALISING"]:
        flags = mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
    if m != MANUAL and m != MODES["INITIALISING"]:
        flags |= mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
    if STICK_MIXING and m != MODES["INITIALISING"]:
        flags |= mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
    if armed and m != MODES["INITIALISING"]:
        flags |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    return flags | mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED


def system_status(phase: int) -> int:
    """HEARTBEAT.system_status: ACTIVE while airborne (ArduPlane: is_flying()), else STANDBY."""
    return mavlink.MAV_STATE_ACTIVE if int(phase) in AIRBORNE else mavlink.MAV_STATE_STANDBY


def landed_state(phase: int) -> int:
    """EXTENDED_SYS_STATE.landed_state of a flight phase."""
    return _LANDED_STATE.get(int(phase), mavlink.MAV_LANDED_STATE_UNDEFINED)


def mission_total(count: int) -> int:
    """MISSION_CURRENT.total: the items without home (MAVLink: "If the autopilot stores its home
    location as part of the mission this will be excluded from the total")."""
    return max(int(count) - 1, 0)


def heartbeat_fields(custom_mode: int, armed: bool, phase: int) -> tuple:
    """(type, autopilot, base_mode, custom_mode, system_status) for heartbeat_send."""
    return MAV_TYPE, AUTOPILOT, base_mode(custom_mode, armed), int(custom_mode), system_status(phase)


def deg_e7_to_rad(v) -> float:
    """A MISSION_ITEM_INT / COMMAND_INT x or y (degE7) in radians (NaN if not finite)."""
    v = float(v)
    return math.radians(v * 1e-7) if math.isfinite(v) else math.nan


def result_name(code: int) -> str:
    """MAV_RESULT_* or MAV_MISSION_* name of a code (for reasons and logs)."""
    e = mavlink.enums["MAV_RESULT"]
    return e[code].name if code in e else str(code)


def mission_result_name(code: int) -> str:
    e = mavlink.enums["MAV_MISSION_RESULT"]
    return e[code].name if code in e else str(code)


def command_name(cmd: int) -> str:
    e = mavlink.enums["MAV_CMD"]
    return e[cmd].name if cmd in e else f"MAV_CMD({cmd})"
