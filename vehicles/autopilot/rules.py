"""The autopilot's vocabulary: task codes, the mission item kinds it flies, the refusal
counters, the result and event types and the per-item mission check (vehicles.autopilot.core
and .operations share them)."""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from . import convention as cv

# tasks: what ends the current behaviour
T_NONE, T_APPROACH, T_WP, T_TURNS, T_TIME, T_ALT, T_CLIMB, T_ROLL, T_TKOFF, T_LAND, T_ROLLOUT, T_GLIDE = range(12)

MAV_CMD = mavlink
NAV_WAYPOINT = mavlink.MAV_CMD_NAV_WAYPOINT
LOITER_UNLIM = mavlink.MAV_CMD_NAV_LOITER_UNLIM
LOITER_TURNS = mavlink.MAV_CMD_NAV_LOITER_TURNS
LOITER_TIME = mavlink.MAV_CMD_NAV_LOITER_TIME
LOITER_TO_ALT = mavlink.MAV_CMD_NAV_LOITER_TO_ALT
NAV_RTL = mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH
NAV_TAKEOFF = mavlink.MAV_CMD_NAV_TAKEOFF
NAV_LAND = mavlink.MAV_CMD_NAV_LAND
DO_JUMP = mavlink.MAV_CMD_DO_JUMP
DO_CHANGE_SPEED = mavlink.MAV_CMD_DO_CHANGE_SPEED

#: mission items the vehicles fly (any other: MAV_MISSION_UNSUPPORTED with its index)
FLYABLE_ITEMS = frozenset({NAV_WAYPOINT, LOITER_UNLIM, LOITER_TURNS, LOITER_TIME, LOITER_TO_ALT, NAV_RTL,
                           NAV_TAKEOFF, NAV_LAND, DO_JUMP, DO_CHANGE_SPEED})
NAV_ITEMS = frozenset({NAV_WAYPOINT, LOITER_UNLIM, LOITER_TURNS, LOITER_TIME, LOITER_TO_ALT, NAV_RTL, NAV_TAKEOFF,
                       NAV_LAND})
POSITION_ITEMS = frozenset({NAV_WAYPOINT, LOITER_UNLIM, LOITER_TURNS, LOITER_TIME, LOITER_TO_ALT, NAV_TAKEOFF,
                            NAV_LAND})
_NAV_ARR = np.array(sorted(NAV_ITEMS))
ABS_FRAMES = frozenset({mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_GLOBAL_INT})
#: relative to home; the terrain frames too (the simulated world is flat at home's height)
REL_FRAMES = frozenset({mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                        mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT, mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT})

#: what a refusal is counted as (``Autopilot.counters``)
REFUSALS = ("bad_vehicle", "nonfinite", "bad_mode", "mode_unsupported", "unsupported_command", "bad_param",
            "disarmed", "in_flight", "not_in_mode", "unsupported_item", "bad_item", "bad_sequence", "no_mission",
            "bad_state", "internal_error")

_TAKEOFF_ALT_TOL_M = 2.0  # ArduPlane: take-off complete 2 m below the target altitude
_LOITER_ALT_TOL_M = 5.0
_TOUCHDOWN_M = 0.5
_FLARE_M = 2.0  # a landing aims this far below the ground, so that it crosses the touchdown height
_EPS = 1e-9


def _guarded(mission: bool = False):
    """An operation never raises: an exception is a refusal (counted 'internal_error', reason
    kept), so that a bug shows up in the counters and the ACK, not as a dead endpoint."""
    def wrap(fn):
        import functools

        @functools.wraps(fn)
        def op(self, *a, **kw):
            try:
                return fn(self, *a, **kw)
            except Exception as e:  # noqa: BLE001 - the contract: a code, never an exception
                reason = f"{fn.__name__}: {type(e).__name__}: {' '.join(str(e).split())}"
                if mission:
                    return self._refuse("internal_error", mavlink.MAV_MISSION_ERROR, reason, MissionResult)
                return self._refuse("internal_error", mavlink.MAV_RESULT_FAILED, reason)
        return op
    return wrap


class Result(NamedTuple):
    """A command's MAV_RESULT and a one-line reason ('' when accepted)."""

    code: int
    reason: str = ""

    @property
    def ok(self) -> bool:
        return self.code == mavlink.MAV_RESULT_ACCEPTED


class MissionResult(NamedTuple):
    """An upload's MAV_MISSION_RESULT, a one-line reason and the offending item's index (-1: none)."""

    code: int
    reason: str = ""
    index: int = -1

    @property
    def ok(self) -> bool:
        return self.code == mavlink.MAV_MISSION_ACCEPTED


class Event(NamedTuple):
    """Something the endpoint reports.  kind: 'mode' (value: the new custom mode), 'armed',
    'disarmed', 'item_reached' (value: seq -> MISSION_ITEM_REACHED), 'mission_current' (value:
    seq -> MISSION_CURRENT now), 'takeoff_complete', 'landed', 'mission_complete', 'text';
    severity: MAV_SEVERITY; text: the STATUSTEXT ArduPlane would send ('' for none)."""

    vehicle: int
    kind: str
    value: int
    severity: int
    text: str


class MissionStatus(NamedTuple):
    """MISSION_CURRENT's fields per UAV: seq (current item), total (items without home),
    state (MISSION_STATE_*)."""

    seq: np.ndarray
    total: np.ndarray
    state: np.ndarray


_INFO, _NOTICE, _WARNING = mavlink.MAV_SEVERITY_INFO, mavlink.MAV_SEVERITY_NOTICE, mavlink.MAV_SEVERITY_WARNING


def _wrap(a):
    return np.mod(a + np.pi, 2.0 * np.pi) - np.pi


def _finite(*v) -> bool:
    try:
        return all(math.isfinite(float(x)) for x in v)
    except (TypeError, ValueError):
        return False


def check_item(k: int, it, n: int) -> MissionResult:
    """Item k of an n-item upload: MAV_MISSION_ACCEPTED, or the code of what is wrong with it
    (pure; the MissionServer may call it item by item as they arrive)."""
    try:
        seq, frame, cmd = int(it.seq), int(it.frame), int(it.command)
        p = [float(it.param1), float(it.param2), float(it.param3), float(it.param4)]
        x, y, z = float(it.x), float(it.y), float(it.z)
    except (AttributeError, TypeError, ValueError, OverflowError):
        return MissionResult(mavlink.MAV_MISSION_ERROR, f"item {k}: not a mission item", k)
    if seq != k:
        return MissionResult(mavlink.MAV_MISSION_INVALID_SEQUENCE, f"item {k}: seq {seq}", k)
    if k == 0:
        return MissionResult(mavlink.MAV_MISSION_ACCEPTED)  # home: the vehicle's own
    if cmd not in FLYABLE_ITEMS:
        return MissionResult(mavlink.MAV_MISSION_UNSUPPORTED,
                             f"item {k}: {cv.command_name(cmd)} ({cmd}) cannot be flown", k)
    if cmd in POSITION_ITEMS:
        if frame not in ABS_FRAMES and frame not in REL_FRAMES:
            return MissionResult(mavlink.MAV_MISSION_UNSUPPORTED_FRAME, f"item {k}: frame {frame}", k)
        if not (math.isfinite(x) and -900_000_000 <= x <= 900_000_000):
            return MissionResult(mavlink.MAV_MISSION_INVALID_PARAM5_X, f"item {k}: latitude {x!r} degE7", k)
        if not (math.isfinite(y) and -1_800_000_000 <= y <= 1_800_000_000):
            return MissionResult(mavlink.MAV_MISSION_INVALID_PARAM6_Y, f"item {k}: longitude {y!r} degE7", k)
        if not math.isfinite(z):
            return MissionResult(mavlink.MAV_MISSION_INVALID_PARAM7, f"item {k}: altitude {z!r}", k)
    if cmd == LOITER_TURNS and not (math.isfinite(p[0]) and p[0] > 0):
        return MissionResult(mavlink.MAV_MISSION_INVALID_PARAM1, f"item {k}: turns {p[0]!r}", k)
    if cmd == LOITER_TIME and not (math.isfinite(p[0]) and p[0] >= 0):
        return MissionResult(mavlink.MAV_MISSION_INVALID_PARAM1, f"item {k}: time {p[0]!r} s", k)
    if cmd == DO_JUMP:
        if not (math.isfinite(p[0]) and p[0] == int(p[0]) and 1 <= p[0] < n and int(p[0]) != k):
            return MissionResult(mavlink.MAV_MISSION_INVALID_PARAM1, f"item {k}: DO_JUMP target {p[0]!r}", k)
        if not (math.isfinite(p[1]) and p[1] == int(p[1]) and p[1] >= -1):
            return MissionResult(mavlink.MAV_MISSION_INVALID_PARAM2, f"item {k}: DO_JUMP repeats {p[1]!r}", k)
    if cmd == DO_CHANGE_SPEED and not (math.isfinite(p[0]) and math.isfinite(p[1])):
        return MissionResult(mavlink.MAV_MISSION_INVALID_PARAM2, f"item {k}: speed {p[1]!r}", k)
    return MissionResult(mavlink.MAV_MISSION_ACCEPTED)
