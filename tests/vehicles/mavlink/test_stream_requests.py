"""StreamOutput.set_interval / request_message (the functions the COMMAND_LONG router calls for
MAV_CMD_SET_MESSAGE_INTERVAL and MAV_CMD_REQUEST_MESSAGE) and AUTOPILOT_VERSION's encoding,
with pymavlink as the GCS peer on loopback, stepped in simulated time."""
from __future__ import annotations

import math
import subprocess
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav
from tests.mavlink_peer import Link, of_type

from vehicles.mavlink.battery import Battery, BatteryParams
from vehicles.mavlink.endpoint.streams import flight_custom_version

pytestmark = pytest.mark.live

ATT = mav.MAVLINK_MSG_ID_ATTITUDE


def test_set_interval_rates_measured_in_simulated_time():
    with Link() as L:
        assert L.ep.set_interval(ATT, 250_000) == mav.MAV_RESULT_ACCEPTED  # MAVProxy's 4 Hz
        got = L.step(100)  # 10 s at 10 Hz steps
        assert abs(len(of_type(got, "ATTITUDE")) - 40) <= 1
        assert L.ep.set_interval(ATT, 100_000) == mav.MAV_RESULT_ACCEPTED
        assert abs(len(of_type(L.step(100), "ATTITUDE")) - 100) <= 1


def test_set_interval_clamped_to_the_epoch():
    with Link() as L:
        # 50 Hz asked: one per vehicle epoch (0.1 s here), never more than one a step
        assert L.ep.set_interval(ATT, 20_000) == mav.MAV_RESULT_ACCEPTED
        assert L.ep._interval[ATT] == pytest.approx(0.1)
        assert abs(len(of_type(L.step(50), "ATTITUDE")) - 50) <= 1
        L.ep.epoch_s = 0.05  # a scenario at 20 Hz
        assert L.ep.set_interval(ATT, 20_000) == mav.MAV_RESULT_ACCEPTED
        assert L.ep._interval[ATT] == pytest.approx(0.05)


@pytest.mark.parametrize("msgid, iv, result", [
    (ATT, math.nan, mav.MAV_RESULT_DENIED), (ATT, -5, mav.MAV_RESULT_DENIED), (ATT, math.inf, mav.MAV_RESULT_DENIED),
    (ATT, "x", mav.MAV_RESULT_DENIED), (397, 100_000, mav.MAV_RESULT_UNSUPPORTED),
    (math.nan, 100_000, mav.MAV_RESULT_UNSUPPORTED), (None, 1, mav.MAV_RESULT_DENIED)])
def test_set_interval_bad_input_clear_result_counted_never_raises(msgid, iv, result):
    with Link() as L:
        L.step(1)
        before = dict(L.ep._interval)
        assert L.ep.set_interval(msgid, iv) == result
        assert L.ep._interval == before  # nothing changed
        key = "cmd_unsupported" if result == mav.MAV_RESULT_UNSUPPORTED else "interval_bad"
        assert L.ep.counters.get(key) == 1


def test_set_interval_stop_and_default():
    with Link() as L:
        assert L.ep.set_interval(ATT, -1) == mav.MAV_RESULT_ACCEPTED
        assert not of_type(L.step(30), "ATTITUDE")
        assert L.ep.set_interval(ATT, 0) == mav.MAV_RESULT_ACCEPTED  # default 4 Hz
        assert abs(len(of_type(L.step(50), "ATTITUDE")) - 20) <= 1


def test_request_message_sends_at_once_or_says_why_not():
    with Link() as L:
        L.step(1)
        assert L.ep.request_message(mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION, L.peer.addr) == mav.MAV_RESULT_ACCEPTED
        assert of_type(L.peer.drain(0.5), "AUTOPILOT_VERSION")
        assert L.ep.request_message(397) == mav.MAV_RESULT_UNSUPPORTED
        assert L.ep.request_message(math.nan) == mav.MAV_RESULT_UNSUPPORTED
        assert L.ep.counters["cmd_unsupported"] == 2
    with Link(tel=None) as L:
        L.tel = None
        L.step(1)
        assert L.ep.request_message(ATT) == mav.MAV_RESULT_TEMPORARILY_REJECTED


def test_autopilot_version_custom_version_is_the_git_hash():
    with Link() as L:
        L.step(1)
        L.ep.request_message(mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION, L.peer.addr)
        v = of_type(L.peer.drain(0.5), "AUTOPILOT_VERSION")[0]
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent, capture_output=True,
                          text=True).stdout.strip()
    assert bytes(v.flight_custom_version).hex() == head[:16] == bytes(flight_custom_version()).hex()
    # flight_sw_version: major << 24 | minor << 16 | patch << 8 | FIRMWARE_VERSION_TYPE (ArduPilot's packing)
    assert v.flight_sw_version & 0xFF in (mav.FIRMWARE_VERSION_TYPE_DEV, mav.FIRMWARE_VERSION_TYPE_OFFICIAL)


def test_mavproxy_4hz_request_data_stream_rates_measured_and_new_streams():
    with Link() as L:
        L.ep.battery = Battery(BatteryParams(capacity_mah=3300.0, cruise_current_a=10.0, cruise_airspeed_m_s=100.0))
        L.exchange(L.peer.mav.request_data_stream_encode(1, 1, mav.MAV_DATA_STREAM_ALL, 4, 1), lambda g: False,
                   max_steps=1)
        got = L.step(100)  # 10 s simulated
        for name in ("ATTITUDE", "GLOBAL_POSITION_INT", "GPS_RAW_INT", "SYS_STATUS", "SYSTEM_TIME", "VFR_HUD",
                     "EXTENDED_SYS_STATE", "BATTERY_STATUS", "HOME_POSITION"):
            assert abs(len(of_type(got, name)) - 40) <= 1, name
        tel = L.tel
        h = of_type(got, "VFR_HUD")[-1]
        gs = math.hypot(*tel.vel_ned_m_s[:2])
        assert h.groundspeed == pytest.approx(gs, rel=1e-6) and h.climb == pytest.approx(-tel.vel_ned_m_s[2])
        assert h.heading == 357 and h.alt == pytest.approx(tel.alt_msl_m, abs=1e-3)
        assert of_type(got, "EXTENDED_SYS_STATE")[-1].landed_state == mav.MAV_LANDED_STATE_IN_AIR
        b = of_type(got, "BATTERY_STATUS")[-1]
        # ~101 m/s: 10 A x (101.33/100)^3 + 0.5 A idle ~ 10.9 A; over ~10 s ~ 30 mAh of 3300
        i_a = 0.5 + 10.0 * (gs / 100.0) ** 3
        assert b.current_battery == pytest.approx(i_a * 100, abs=1)  # cA
        assert b.current_consumed == pytest.approx(i_a * 9.9 / 3.6, abs=2)  # mAh
        assert b.battery_remaining == 99 and 10_500 < b.voltages[0] < 12_600 and b.voltages[1] == 65535
        s = of_type(got, "SYS_STATUS")[-1]
        for bit in ("SENSOR_GPS", "AHRS", "SENSOR_BATTERY"):
            v = getattr(mav, "MAV_SYS_STATUS_" + bit)
            assert s.onboard_control_sensors_present & s.onboard_control_sensors_enabled & \
                s.onboard_control_sensors_health & v, bit
        g = mav.MAV_SYS_STATUS_GEOFENCE  # no fence, and not "breached" (MAVProxy's fence module)
        assert not s.onboard_control_sensors_present & g and s.onboard_control_sensors_health & g
        assert s.battery_remaining == 99 and s.current_battery == b.current_battery
        # stop all: only the heartbeat stays
        L.exchange(L.peer.mav.request_data_stream_encode(1, 1, mav.MAV_DATA_STREAM_ALL, 0, 0), lambda g: False,
                   max_steps=1)
        assert {m.get_type() for m in L.step(30)} == {"HEARTBEAT"}


def test_request_data_stream_bad_input_counted():
    with Link() as L:
        L.step(1)
        before = dict(L.ep._interval)
        L.ep.request_data_stream(mav.MAV_DATA_STREAM_ALL, math.nan, 1)
        L.ep.request_data_stream(77, 4, 1)
        assert L.ep._interval == before and L.ep.counters["interval_bad"] == 2


def test_landed_state_hook():
    with Link() as L:
        L.ep.landed_state_fn = lambda: mav.MAV_LANDED_STATE_ON_GROUND
        got = L.step(20)
        assert {m.landed_state for m in of_type(got, "EXTENDED_SYS_STATE")} == {mav.MAV_LANDED_STATE_ON_GROUND}


def test_battery_model():
    b = Battery(BatteryParams(capacity_mah=1000.0, cruise_current_a=10.0, exponent=0.0, idle_current_a=0.0))
    for k in range(361):
        b.step(k * 1.0, 50.0)  # constant draw: 10 A for 360 s = 1000 mAh
    assert b.consumed_mah == pytest.approx(1000.0) and b.remaining_pct == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(ValueError):
        BatteryParams(voltage_empty_v=13.0)


# ---------------------------------------------------------------------- the commands reach the streams


def _cmd(L, command, *params):
    p = list(params) + [0.0] * (7 - len(params))
    return L.peer.mav.command_long_encode(1, 1, command, 0, *p)


def _ack_of(got, command):
    acks = [m for m in of_type(got, "COMMAND_ACK") if m.command == command]
    return acks[-1].result if acks else None


def test_command_long_set_message_interval_reaches_every_stream_rates_measured():
    """MAV_CMD_SET_MESSAGE_INTERVAL over the wire (MAVSDK's and QGC's way): ACCEPTED, and the
    rate received over 20 simulated seconds is the one asked for, for a base stream (ATTITUDE),
    for streams beside it (VFR_HUD, EXTENDED_SYS_STATE), up to one per vehicle epoch."""
    with Link() as L:
        vfr = mav.MAVLINK_MSG_ID_VFR_HUD
        ess = mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE
        for msgid, us in ((ATT, 100_000), (vfr, 250_000), (ess, 500_000)):
            got = L.exchange(_cmd(L, mav.MAV_CMD_SET_MESSAGE_INTERVAL, msgid, us),
                             lambda g: _ack_of(g, mav.MAV_CMD_SET_MESSAGE_INTERVAL) is not None, max_steps=5)
            assert _ack_of(got, mav.MAV_CMD_SET_MESSAGE_INTERVAL) == mav.MAV_RESULT_ACCEPTED
        got = L.step(200)  # 20 s simulated at 10 Hz steps
        assert abs(len(of_type(got, "ATTITUDE")) - 200) <= 1  # 10 Hz
        assert abs(len(of_type(got, "VFR_HUD")) - 80) <= 1  # 4 Hz
        assert abs(len(of_type(got, "EXTENDED_SYS_STATE")) - 40) <= 1  # 2 Hz
        # GET_MESSAGE_INTERVAL says what was set
        got = L.exchange(_cmd(L, mav.MAV_CMD_GET_MESSAGE_INTERVAL, vfr),
                         lambda g: bool(of_type(g, "MESSAGE_INTERVAL")), max_steps=5)
        mi = of_type(got, "MESSAGE_INTERVAL")[-1]
        assert mi.message_id == vfr and mi.interval_us == 250_000


def test_command_long_set_message_interval_bad_input_acked_and_counted():
    with Link() as L:
        L.step(1)
        before = dict(L.ep._interval)
        for msgid, us, want in ((ATT, math.nan, mav.MAV_RESULT_DENIED), (ATT, -7, mav.MAV_RESULT_DENIED),
                                (397, 100_000, mav.MAV_RESULT_UNSUPPORTED)):
            got = L.exchange(_cmd(L, mav.MAV_CMD_SET_MESSAGE_INTERVAL, msgid, us),
                             lambda g: _ack_of(g, mav.MAV_CMD_SET_MESSAGE_INTERVAL) is not None, max_steps=5)
            assert _ack_of(got, mav.MAV_CMD_SET_MESSAGE_INTERVAL) == want
        assert L.ep._interval == before
        assert L.ep.counters["interval_bad"] == 2 and L.ep.counters["cmd_unsupported"] == 1


def test_command_long_request_message_reaches_the_extra_streams():
    """MAV_CMD_REQUEST_MESSAGE for a message beside the base streams (EXTENDED_SYS_STATE,
    BATTERY_STATUS): the message, then COMMAND_ACK ACCEPTED; no battery: TEMPORARILY_REJECTED;
    an id that is no stream: UNSUPPORTED, counted."""
    with Link() as L:
        L.step(1)
        ess = mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE
        got = L.exchange(_cmd(L, mav.MAV_CMD_REQUEST_MESSAGE, ess),
                         lambda g: _ack_of(g, mav.MAV_CMD_REQUEST_MESSAGE) is not None, max_steps=5)
        assert _ack_of(got, mav.MAV_CMD_REQUEST_MESSAGE) == mav.MAV_RESULT_ACCEPTED
        assert of_type(got, "EXTENDED_SYS_STATE")
        got = L.exchange(_cmd(L, mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_BATTERY_STATUS),
                         lambda g: _ack_of(g, mav.MAV_CMD_REQUEST_MESSAGE) is not None, max_steps=5)
        assert _ack_of(got, mav.MAV_CMD_REQUEST_MESSAGE) == mav.MAV_RESULT_TEMPORARILY_REJECTED
        L.ep.battery = Battery()
        got = L.exchange(_cmd(L, mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_BATTERY_STATUS),
                         lambda g: _ack_of(g, mav.MAV_CMD_REQUEST_MESSAGE) is not None, max_steps=5)
        assert _ack_of(got, mav.MAV_CMD_REQUEST_MESSAGE) == mav.MAV_RESULT_ACCEPTED
        assert of_type(got, "BATTERY_STATUS")
        n = L.ep.counters["cmd_unsupported"]
        got = L.exchange(_cmd(L, mav.MAV_CMD_REQUEST_MESSAGE, 12345),
                         lambda g: _ack_of(g, mav.MAV_CMD_REQUEST_MESSAGE) is not None, max_steps=5)
        assert _ack_of(got, mav.MAV_CMD_REQUEST_MESSAGE) == mav.MAV_RESULT_UNSUPPORTED
        assert L.ep.counters["cmd_unsupported"] == n + 1
