"""The ArduPlane identity: numbers from pymavlink (never typed), ArduPlane's base_mode, and what
pymavlink's own decoders (the ones MAVProxy uses) read back from our HEARTBEAT."""
from __future__ import annotations

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from vehicles.autopilot import convention as cv


def test_mode_numbers_are_pymavlinks():
    assert cv.MODES == mavutil.mode_mapping_byname(mavlink.MAV_TYPE_FIXED_WING)
    apm = {v: k for k, v in mavutil.mode_mapping_apm.items()}
    for name in ("MANUAL", "CIRCLE", "STABILIZE", "FBWA", "AUTO", "RTL", "LOITER", "TAKEOFF", "GUIDED"):
        assert cv.MODES[name] == apm[name]
    # and the dialect's PLANE_MODE enum agrees (a second, independent table in pymavlink)
    assert (cv.MANUAL, cv.CIRCLE, cv.STABILIZE, cv.FBWA, cv.AUTO, cv.RTL, cv.LOITER, cv.TAKEOFF, cv.GUIDED) == (
        mavlink.PLANE_MODE_MANUAL, mavlink.PLANE_MODE_CIRCLE, mavlink.PLANE_MODE_STABILIZE,
        mavlink.PLANE_MODE_FLY_BY_WIRE_A, mavlink.PLANE_MODE_AUTO, mavlink.PLANE_MODE_RTL, mavlink.PLANE_MODE_LOITER,
        mavlink.PLANE_MODE_TAKEOFF, mavlink.PLANE_MODE_GUIDED)
    assert cv.SUPPORTED_MODES <= set(cv.MODE_NAMES)


def _hb(mode, armed, phase):
    t, ap, base, custom, status = cv.heartbeat_fields(mode, armed, phase)
    return mavlink.MAVLink_heartbeat_message(t, ap, base, custom, status, 3)


def test_heartbeat_decodes_as_arduplane():
    for m in sorted(cv.SUPPORTED_MODES):
        for armed in (False, True):
            hb = _hb(m, armed, cv.FLYING if armed else cv.ON_GROUND)
            assert mavutil.mode_string_v10(hb) == cv.MODE_NAMES[m]  # what MAVProxy prints
            assert bool(hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED) == armed
            assert hb.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            assert not hb.base_mode & mavlink.MAV_MODE_FLAG_AUTO_ENABLED  # ArduPlane never sets it
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA and hb.type == mavlink.MAV_TYPE_FIXED_WING


def test_base_mode_as_arduplane_sitl_reports_it():
    # ArduPlane SITL's HEARTBEAT: AUTO armed 217, AUTO disarmed 89, MANUAL disarmed 65
    F = mavlink
    assert cv.base_mode(cv.AUTO, True) == (F.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | F.MAV_MODE_FLAG_GUIDED_ENABLED
                                           | F.MAV_MODE_FLAG_STABILIZE_ENABLED | F.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
                                           | F.MAV_MODE_FLAG_SAFETY_ARMED) == 217
    assert cv.base_mode(cv.AUTO, False) == 89
    assert cv.base_mode(cv.MANUAL, False) == 65
    assert cv.base_mode(cv.FBWA, False) == 81  # stabilize + manual input (stick mixing) + custom
    for m in (cv.RTL, cv.LOITER, cv.GUIDED, cv.TAKEOFF, cv.CIRCLE):
        assert cv.base_mode(m, True) & F.MAV_MODE_FLAG_GUIDED_ENABLED


def test_status_phase_and_mission_rules():
    assert cv.system_status(cv.ON_GROUND) == mavlink.MAV_STATE_STANDBY
    assert cv.system_status(cv.LANDED) == mavlink.MAV_STATE_STANDBY
    for p in (cv.TAKING_OFF, cv.FLYING, cv.LANDING):
        assert cv.system_status(p) == mavlink.MAV_STATE_ACTIVE
    assert [cv.landed_state(p) for p in (cv.ON_GROUND, cv.TAKING_OFF, cv.FLYING, cv.LANDING, cv.LANDED)] == [
        mavlink.MAV_LANDED_STATE_ON_GROUND, mavlink.MAV_LANDED_STATE_TAKEOFF, mavlink.MAV_LANDED_STATE_IN_AIR,
        mavlink.MAV_LANDED_STATE_LANDING, mavlink.MAV_LANDED_STATE_ON_GROUND]
    assert cv.FIRST_ITEM == 1 and cv.mission_total(5) == 4 and cv.mission_total(0) == 0
    assert cv.mode_name(99) == "MODE(99)" and cv.mode_name(cv.AUTO) == "AUTO"
