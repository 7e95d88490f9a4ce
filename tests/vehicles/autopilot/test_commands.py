"""Operations: arming rules, modes, and bad input -- a clear code and a counter, never an exception."""
from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from vehicles.autopilot import Autopilot, Result
from vehicles.autopilot import convention as cv
from vehicles.autopilot.core import DO_JUMP, FLYABLE_ITEMS, NAV_WAYPOINT

from .sim import item

R = mavlink
LAT, LON = math.radians(45.15), math.radians(30.15)


def ground(n=1):
    return Autopilot(np.full(n, LAT), np.full(n, LON), np.full(n, 150.0), 0.0, in_flight=False)


def flying(n=1):
    return Autopilot(np.full(n, LAT), np.full(n, LON), np.full(n, 2000.0), 0.0, in_flight=True)


def test_cannot_take_off_disarmed_then_can():
    ap = ground()
    r = ap.takeoff(0, 100.0)
    assert r.code == R.MAV_RESULT_FAILED and "disarmed" in r.reason and ap.counters["disarmed"] == 1
    assert ap.phase[0] == cv.ON_GROUND and ap.mode[0] == cv.MANUAL
    assert ap.command(0, R.MAV_CMD_COMPONENT_ARM_DISARM, (1, 0, 0, 0, 0, 0, 0)).ok
    assert ap.armed[0] and ap.heartbeat(0)[2] & R.MAV_MODE_FLAG_SAFETY_ARMED
    assert ap.takeoff(0, 100.0).ok and ap.mode[0] == cv.TAKEOFF
    g, ev = ap.step(0.0, 1.0, LAT, LON, 150.0, 0.0)
    assert ap.phase[0] == cv.TAKING_OFF and [e.kind for e in ev][:2] == ["armed", "mode"]


def test_disarm_in_flight_refused_unless_forced():
    ap = flying()
    r = ap.arm(0, False)
    assert r.code == R.MAV_RESULT_FAILED and ap.armed[0] and ap.counters["in_flight"] == 1
    assert ap.command(0, R.MAV_CMD_COMPONENT_ARM_DISARM, (0, cv.FORCE_MAGIC, 0, 0, 0, 0, 0)).ok
    assert not ap.armed[0] and ap.phase[0] == cv.LANDING  # motor off: it glides down
    assert ap.heartbeat(0)[4] == R.MAV_STATE_ACTIVE  # still in the air
    gr = ground()
    assert gr.arm(0, True).ok and gr.arm(0, False).ok and not gr.armed[0]  # on the ground: fine
    assert gr.arm(0, False).ok  # already disarmed: accepted, as ArduPilot


def test_modes_set_by_number_and_heartbeat_follows():
    ap = flying()
    for m in sorted(cv.SUPPORTED_MODES):
        r = ap.command(0, R.MAV_CMD_DO_SET_MODE, (R.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, m, 0, 0, 0, 0, 0))
        assert r.ok, (m, r)
        assert ap.heartbeat(0)[3] == m
    assert ap.set_mode(0, cv.RTL).ok and ap.mode[0] == cv.RTL


@pytest.mark.parametrize("mode, base, code, counter", [
    (99, 1, R.MAV_RESULT_DENIED, "bad_mode"),
    (math.nan, 1, R.MAV_RESULT_DENIED, "nonfinite"),
    (math.inf, 1, R.MAV_RESULT_DENIED, "nonfinite"),
    (10.5, 1, R.MAV_RESULT_DENIED, "nonfinite"),
    (cv.MODES["QHOVER"], 1, R.MAV_RESULT_FAILED, "mode_unsupported"),
    (cv.AUTO, 0, R.MAV_RESULT_DENIED, "bad_mode"),  # base_mode without CUSTOM_MODE_ENABLED
])
def test_bad_modes(mode, base, code, counter):
    ap = flying()
    r = ap.set_mode(0, mode, base)
    assert isinstance(r, Result) and r.code == code and r.reason and "\n" not in r.reason
    assert ap.counters[counter] == 1 and ap.mode[0] == cv.AUTO


def test_unknown_mode_99_says_so():
    ap = flying()
    assert ap.command(0, R.MAV_CMD_DO_SET_MODE, (1, 99, 0, 0, 0, 0, 0)).code == R.MAV_RESULT_DENIED
    _, ev = ap.step(0.0, 1.0, LAT, LON, 2000.0, 0.0)
    assert [(e.kind, e.text) for e in ev] == [("text", "No such mode 99")]


def test_commands_with_nan_and_unknown_commands():
    ap = flying()
    r = ap.command(0, R.MAV_CMD_DO_REPOSITION, (-1, 1, 0, 0, math.nan, 30.0, 100.0))
    assert r.code == R.MAV_RESULT_DENIED and ap.counters["nonfinite"] == 1 and ap.mode[0] == cv.AUTO
    r = ap.command(0, R.MAV_CMD_DO_REPOSITION, (-1, 1, 0, 0, 95.0, 30.0, 100.0))
    assert r.code == R.MAV_RESULT_DENIED and ap.counters["bad_param"] == 1
    r = ap.command(0, R.MAV_CMD_DO_DIGICAM_CONTROL, (0,) * 7)
    assert r.code == R.MAV_RESULT_UNSUPPORTED and ap.counters["unsupported_command"] == 1
    assert "DIGICAM" in r.reason
    r = ap.command(0, R.MAV_CMD_COMPONENT_ARM_DISARM, (math.nan, 0, 0, 0, 0, 0, 0))
    assert r.code == R.MAV_RESULT_DENIED and ap.armed[0]
    r = ap.guided_item(0, item(0, NAV_WAYPOINT, 45.2, 30.2, math.nan)._replace(current=2))
    assert r.code == R.MAV_MISSION_INVALID_PARAM7
    r = ap.command(7, R.MAV_CMD_NAV_RETURN_TO_LAUNCH)
    assert r.code == R.MAV_RESULT_DENIED and ap.counters["bad_vehicle"] == 1
    # repositioning without CHANGE_MODE outside GUIDED: FAILED (ArduPlane)
    assert ap.command(0, R.MAV_CMD_DO_REPOSITION, (-1, 0, 0, 0, 45.2, 30.2, 100.0)).code == R.MAV_RESULT_FAILED


def test_unsupported_mission_item_names_its_index_and_keeps_the_old_mission():
    ap = flying()
    good = [item(0, NAV_WAYPOINT)] + [item(k, NAV_WAYPOINT, 45.2 + 0.1 * k, 30.2, 100.0) for k in (1, 2)]
    assert ap.set_mission(0, good).ok and ap.m_count[0] == 3
    bad = good[:3] + [item(3, R.MAV_CMD_DO_DIGICAM_CONTROL)]
    r = ap.set_mission(0, bad)
    assert (r.code, r.index) == (R.MAV_MISSION_UNSUPPORTED, 3) and "DO_DIGICAM_CONTROL" in r.reason
    assert ap.counters["unsupported_item"] == 1 and ap.m_count[0] == 3
    assert R.MAV_CMD_DO_DIGICAM_CONTROL not in FLYABLE_ITEMS


@pytest.mark.parametrize("it, code", [
    (item(1, NAV_WAYPOINT, 91.0, 30.0, 100.0), R.MAV_MISSION_INVALID_PARAM5_X),
    (item(1, NAV_WAYPOINT, 45.0, 181.0, 100.0), R.MAV_MISSION_INVALID_PARAM6_Y),
    (item(1, NAV_WAYPOINT, 45.0, 30.0, math.nan), R.MAV_MISSION_INVALID_PARAM7),
    (item(1, NAV_WAYPOINT, 45.0, 30.0, 100.0, frame=R.MAV_FRAME_LOCAL_NED), R.MAV_MISSION_UNSUPPORTED_FRAME),
    (item(1, DO_JUMP, p=(7, 1, 0, 0)), R.MAV_MISSION_INVALID_PARAM1),
    (item(1, DO_JUMP, p=(1, 1, 0, 0)), R.MAV_MISSION_INVALID_PARAM1),  # onto itself
    (item(1, R.MAV_CMD_NAV_LOITER_TURNS, 45.0, 30.0, 100.0, p=(math.nan, 0, 0, 0)), R.MAV_MISSION_INVALID_PARAM1),
    (item(2, NAV_WAYPOINT, 45.0, 30.0, 100.0), R.MAV_MISSION_INVALID_SEQUENCE),
])
def test_bad_items(it, code):
    ap = flying()
    r = ap.set_mission(0, [item(0, NAV_WAYPOINT), it])
    assert r.code == code and r.index == 1 and r.reason and ap.m_count[0] == 0
    assert ap.counters["bad_item"] == 1


def test_set_current_checks_the_sequence():
    ap = flying()
    assert ap.set_current(0, 1).code == R.MAV_RESULT_DENIED and ap.counters["no_mission"] == 1
    ap.set_mission(0, [item(0, NAV_WAYPOINT)] + [item(k, NAV_WAYPOINT, 45.2 + 0.1 * k, 30.2, 100.0) for k in (1, 2)])
    assert ap.set_current(0, 5).code == R.MAV_RESULT_DENIED and ap.counters["bad_sequence"] == 1
    assert ap.set_current(0, 2).ok and ap.cur[0] == 2
    assert ap.command(0, R.MAV_CMD_DO_SET_MISSION_CURRENT, (0, 0, 0, 0, 0, 0, 0)).ok and ap.cur[0] == 1  # 0 = home
    st = ap.mission_status()
    assert (st.seq[0], st.total[0], st.state[0]) == (1, 2, R.MISSION_STATE_ACTIVE)


GARBAGE = [None, "x", math.nan, math.inf, -math.inf, -1, 1e300, True, [1, 2], object()]


def test_garbage_never_raises():
    ap = flying(2)
    ops = [lambda v: ap.arm(v), lambda v: ap.arm(0, True, v), lambda v: ap.set_mode(0, v), lambda v: ap.set_mode(v, 10),
           lambda v: ap.takeoff(0, v), lambda v: ap.goto(0, v, v, v), lambda v: ap.goto(0, LAT, LON, 100, radius_m=v,
                                                                                          speed_m_s=v),
           lambda v: ap.land(0, v, v, v), lambda v: ap.set_current(0, v), lambda v: ap.change_speed(0, v, v),
           lambda v: ap.set_home(0, v, v, v), lambda v: ap.set_mission(0, v), lambda v: ap.set_mission(0, [v]),
           lambda v: ap.command(0, 400, (v,) * 7), lambda v: ap.command(0, v), lambda v: ap.command(0, 176, v),
           lambda v: ap.guided_item(0, v), lambda v: ap.mission_start(0, v, v)]
    for op in ops:
        for v in GARBAGE:
            r = op(v)
            assert isinstance(r, tuple) and isinstance(r.code, int) and isinstance(r.reason, str), (op, v, r)
    g, ev = ap.step(0.0, 1.0, [LAT, math.nan], [LON, LON], [2000.0, 2000.0], [0.0, 0.0])
    assert np.all(np.isfinite(g.speed_m_s)) and ap.counters["nonfinite"] > 0
    assert sum(ap.counters.values()) > 50 and ap.counters["internal_error"] == 0, ap.last_reason
