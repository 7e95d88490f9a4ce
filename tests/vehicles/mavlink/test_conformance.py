"""Conformance of the vehicles' MAVLink endpoints, with pymavlink as the GCS peer on loopback.

Every message and protocol of issue 7 for a UAV and a sonde endpoint: streams with their
fields in MAVLink units, AUTOPILOT_VERSION, commands and ACKs, parameters, missions,
TIMESYNC, signing, bad input, the .tlog, and a group of endpoints.
"""
from __future__ import annotations

import math
import os
import subprocess
import sys

import numpy as np
import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mav
from tests.mavlink_peer import T0_GPS_S, Link, Peer, of_type, telemetry

from sitl.timescales import utc_from_gps_seconds
from vehicles.mavlink import (CAPABILITIES, REJECT_REASONS, EndpointGroup, ParamSpec, ParamStore, VehicleEndpoint,
                              sonde_param_specs, uav_param_specs)

pytestmark = pytest.mark.live

KEY = bytes(range(32))


def _unix_us(t_gps_s: float) -> int:
    # independent path: sitl.timescales' datetime (the endpoint uses the closed form)
    return int(round(utc_from_gps_seconds(t_gps_s).timestamp() * 1e6))


# ---------------------------------------------------------------------------- streams
@pytest.mark.parametrize("kind, mav_type", [("uav", mav.MAV_TYPE_FIXED_WING), ("sonde", mav.MAV_TYPE_FREE_BALLOON)])
def test_streams_rates_and_fields(kind, mav_type):
    with Link(kind) as L:
        got = L.step(100, dt=0.1)  # 10 s of simulated time at 10 Hz
        hb = of_type(got, "HEARTBEAT")
        # rates: default 1, 1, 1, 2, 4, 4 Hz over 10 s (phase kept: at most one more or less)
        for name, hz in [("HEARTBEAT", 1), ("SYS_STATUS", 1), ("SYSTEM_TIME", 1), ("GPS_RAW_INT", 2),
                         ("ATTITUDE", 4), ("GLOBAL_POSITION_INT", 4)]:
            assert abs(len(of_type(got, name)) - 10 * hz) <= 1, name
        h = hb[0]
        assert (h.type, h.autopilot, h.mavlink_version) == (mav_type, mav.MAV_AUTOPILOT_GENERIC, 3)
        assert h.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED and h.system_status == mav.MAV_STATE_ACTIVE
        assert all(m.get_srcSystem() == 1 and m.get_srcComponent() == mav.MAV_COMP_ID_AUTOPILOT1 for m in got)
        assert all(m.get_header().incompat_flags == 0 for m in got)  # MAVLink 2 frames (parsed as v2), unsigned
        tel = L.tel
        deg7 = lambda a: int(np.rint(np.degrees(a) * 1e7))  # noqa: E731
        g = of_type(got, "GLOBAL_POSITION_INT")[-1]
        assert (g.lat, g.lon, g.alt) == (deg7(tel.lat_rad), deg7(tel.lon_rad), int(np.rint(tel.alt_msl_m * 1e3)))
        assert g.relative_alt == 0  # home = the first position
        assert (g.vx, g.vy, g.vz) == tuple(int(np.rint(v * 100)) for v in tel.vel_ned_m_s)
        assert g.hdg == int(np.rint(np.degrees(tel.yaw_rad) * 100)) % 36000
        r = of_type(got, "GPS_RAW_INT")[-1]
        assert (r.fix_type, r.satellites_visible, r.lat, r.lon) == (3, 9, deg7(tel.lat_rad), deg7(tel.lon_rad))
        assert (r.eph, r.epv) == (87, 131)  # DOP x 100
        assert (r.h_acc, r.v_acc) == (2345, 4560)  # mm
        assert r.alt == int(np.rint(tel.alt_msl_m * 1e3))
        assert r.vel == int(np.rint(np.hypot(*tel.vel_ned_m_s[:2]) * 100))
        assert r.cog == int(np.rint(np.degrees(np.arctan2(tel.vel_ned_m_s[1], tel.vel_ned_m_s[0])) % 360 * 100))
        a = of_type(got, "ATTITUDE")[-1]
        assert a.roll == pytest.approx(tel.roll_rad, abs=1e-7) and a.pitch == pytest.approx(tel.pitch_rad, abs=1e-7)
        assert a.yaw == pytest.approx(math.radians(357.3) - 2 * math.pi, abs=1e-6)  # -pi..pi
        st = of_type(got, "SYSTEM_TIME")
        assert st[0].time_unix_usec == _unix_us(T0_GPS_S) and st[0].time_boot_ms == 0
        assert st[1].time_unix_usec - st[0].time_unix_usec == 1_000_000 and st[1].time_boot_ms == 1000
        s = of_type(got, "SYS_STATUS")[-1]
        assert s.onboard_control_sensors_health & mav.MAV_SYS_STATUS_SENSOR_GPS
        assert s.voltage_battery == 65535 and s.battery_remaining == -1


def test_heartbeat_standby_without_telemetry_and_disarmed():
    with Link("sonde", tel=telemetry(armed=False, fix_type=1)) as L:
        got = L.step(3)
        h = of_type(got, "HEARTBEAT")[0]
        assert h.system_status == mav.MAV_STATE_STANDBY and not h.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
        assert not of_type(got, "SYS_STATUS")[0].onboard_control_sensors_health & mav.MAV_SYS_STATUS_SENSOR_GPS
        L.tel = None  # no telemetry yet: heartbeat and status only, never a made-up position
        got = L.step(30)
        assert of_type(got, "HEARTBEAT") and not of_type(got, "GLOBAL_POSITION_INT")


# ---------------------------------------------------------------------------- commands
def _cmd(L, command, *params, use_int=False):
    p = list(params) + [0.0] * (7 - len(params))
    if use_int:
        msg = L.peer.mav.command_int_encode(1, 1, 0, command, 0, 0, p[0], p[1], p[2], p[3], int(p[4]), int(p[5]),
                                            p[6])
    else:
        msg = L.peer.mav.command_long_encode(1, 1, command, 0, *p)
    return msg


@pytest.mark.parametrize("use_int", [False, True])
def test_autopilot_version_on_request(use_int):
    with Link() as L:
        for req in (_cmd(L, mav.MAV_CMD_REQUEST_MESSAGE, 148, use_int=use_int),
                    _cmd(L, mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1, use_int=use_int)):
            got = L.exchange(req, lambda g: of_type(g, "AUTOPILOT_VERSION") and of_type(g, "COMMAND_ACK"))
            ack = of_type(got, "COMMAND_ACK")[0]
            assert (ack.command, ack.result) == (req.command, mav.MAV_RESULT_ACCEPTED)
            assert (ack.target_system, ack.target_component) == (255, 190)
            v = of_type(got, "AUTOPILOT_VERSION")[0]
            assert v.capabilities == CAPABILITIES
            for bit in ("MAVLINK2", "PARAM_FLOAT", "MISSION_INT", "COMMAND_INT", "FTP", "SET_POSITION_TARGET_GLOBAL_INT"):
                assert v.capabilities & getattr(mav, "MAV_PROTOCOL_CAPABILITY_" + bit), bit
            for bit in ("MISSION_FENCE", "MISSION_RALLY", "PARAM_ENCODE_BYTEWISE", "TERRAIN"):
                assert not v.capabilities & getattr(mav, "MAV_PROTOCOL_CAPABILITY_" + bit), bit
            assert v.uid != 0 and (v.flight_sw_version >> 16) & 0xFF == 1


def test_qgc_connect_requests_answered_at_once():
    """What QGroundControl asks at connection: each answered in the same step (no stall)."""
    with Link() as L:
        for msgid in (397, 395, 435, 300):  # COMPONENT_METADATA, COMPONENT_INFORMATION, AVAILABLE_MODES, PROTOCOL_VERSION
            got = L.exchange(_cmd(L, mav.MAV_CMD_REQUEST_MESSAGE, msgid), lambda g: of_type(g, "COMMAND_ACK"),
                             max_steps=1)
            assert [(a.command, a.result) for a in of_type(got, "COMMAND_ACK")] == \
                [(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAV_RESULT_UNSUPPORTED)], msgid
        for cmd in (mav.MAV_CMD_NAV_TAKEOFF, mav.MAV_CMD_REQUEST_PROTOCOL_VERSION, 42424):
            got = L.exchange(_cmd(L, cmd, 1), lambda g: of_type(g, "COMMAND_ACK"), max_steps=1)
            assert [(a.command, a.result) for a in of_type(got, "COMMAND_ACK")] == [(cmd, mav.MAV_RESULT_UNSUPPORTED)]
        # a streamed message on request: ACK then the message, to the requester
        got = L.exchange(_cmd(L, mav.MAV_CMD_REQUEST_MESSAGE, 24), lambda g: of_type(g, "GPS_RAW_INT"), max_steps=1)
        assert of_type(got, "COMMAND_ACK")[0].result == mav.MAV_RESULT_ACCEPTED and of_type(got, "GPS_RAW_INT")


def test_commands_for_another_system_are_ignored():
    with Link() as L:
        got = L.exchange(L.peer.mav.command_long_encode(7, 1, mav.MAV_CMD_REQUEST_MESSAGE, 0, 148, 0, 0, 0, 0, 0, 0),
                         lambda g: False, max_steps=3)
        assert not of_type(got, "COMMAND_ACK") and L.ep.counters["not_for_us"] == 1


def test_set_and_get_message_interval():
    with Link() as L:
        got = L.exchange(_cmd(L, mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ATTITUDE, 100_000),
                         lambda g: of_type(g, "COMMAND_ACK"))
        assert of_type(got, "COMMAND_ACK")[0].result == mav.MAV_RESULT_ACCEPTED
        got = L.step(50)  # 5 s at 10 Hz steps: ATTITUDE now 10 Hz
        assert abs(len(of_type(got, "ATTITUDE")) - 50) <= 1
        got = L.exchange(_cmd(L, mav.MAV_CMD_GET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ATTITUDE),
                         lambda g: of_type(g, "MESSAGE_INTERVAL"))
        mi = of_type(got, "MESSAGE_INTERVAL")[0]
        assert (mi.message_id, mi.interval_us) == (mav.MAVLINK_MSG_ID_ATTITUDE, 100_000)
        L.exchange(_cmd(L, mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ATTITUDE, -1),
                   lambda g: of_type(g, "COMMAND_ACK"))
        assert not of_type(L.step(30), "ATTITUDE")
        L.exchange(_cmd(L, mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ATTITUDE, 0),  # back to default 4 Hz
                   lambda g: of_type(g, "COMMAND_ACK"))
        assert abs(len(of_type(L.step(50), "ATTITUDE")) - 20) <= 1
        got = L.exchange(_cmd(L, mav.MAV_CMD_SET_MESSAGE_INTERVAL, 397, 100_000), lambda g: of_type(g, "COMMAND_ACK"))
        assert of_type(got, "COMMAND_ACK")[0].result == mav.MAV_RESULT_UNSUPPORTED
        got = L.exchange(_cmd(L, mav.MAV_CMD_SET_MESSAGE_INTERVAL, 30, -5), lambda g: of_type(g, "COMMAND_ACK"))
        assert of_type(got, "COMMAND_ACK")[0].result == mav.MAV_RESULT_DENIED


def test_request_data_stream_as_mavproxy_sends_it():
    with Link() as L:
        L.exchange(L.peer.mav.request_data_stream_encode(1, 1, mav.MAV_DATA_STREAM_ALL, 10, 1), lambda g: False,
                   max_steps=1)
        got = L.step(50)
        for name in ("ATTITUDE", "GLOBAL_POSITION_INT", "GPS_RAW_INT", "SYS_STATUS", "SYSTEM_TIME"):
            assert abs(len(of_type(got, name)) - 50) <= 1, name
        assert abs(len(of_type(got, "HEARTBEAT")) - 5) <= 1  # heartbeat stays 1 Hz
        L.exchange(L.peer.mav.request_data_stream_encode(1, 1, mav.MAV_DATA_STREAM_ALL, 0, 0), lambda g: False,
                   max_steps=1)
        got = L.step(30)
        assert {m.get_type() for m in got} == {"HEARTBEAT"}


def test_timesync():
    with Link() as L:
        got = L.exchange(L.peer.mav.timesync_encode(0, 123_456_789), lambda g: of_type(g, "TIMESYNC"))
        ts = of_type(got, "TIMESYNC")[0]
        assert ts.ts1 == 123_456_789
        t_reply = T0_GPS_S + 0.1 * (L.ep.time_boot_ms / 100)  # the step that answered
        assert abs(ts.tc1 - _unix_us(t_reply) * 1000) <= 1000  # ns, float rounding of ~1.7e18
        got = L.exchange(L.peer.mav.timesync_encode(5, 6), lambda g: False, max_steps=2)  # an answer: no reply
        assert not of_type(got, "TIMESYNC")


# ---------------------------------------------------------------------------- params
def _uav_store():
    from vehicles.uav import WaypointMission
    wm = WaypointMission([np.array([[0.8, 0.5, 3000.0]])], speed_m_s=100.0)
    return ParamStore(uav_param_specs(wm)), wm


def test_param_list_read_set():
    store, wm = _uav_store()
    seen = []
    store.on_change(lambda n, v: seen.append((n, v)))
    with Link(params=store) as L:
        got = L.exchange(L.peer.mav.param_request_list_encode(1, 1),
                         lambda g: len(of_type(g, "PARAM_VALUE")) >= len(store))
        pv = of_type(got, "PARAM_VALUE")
        assert sorted(p.param_index for p in pv) == list(range(len(store)))
        assert {p.param_count for p in pv} == {len(store)}
        assert {p.param_type for p in pv} == {mav.MAV_PARAM_TYPE_REAL32}
        assert {p.param_id: p.param_value for p in pv} == {k: float(np.float32(v)) for k, v in store.items()}
        assert dict(store)["WP_SPEED"] == 100.0 and dict(store)["NAV_Q"] == 0.035
        # read by name and by index
        got = L.exchange(L.peer.mav.param_request_read_encode(1, 1, b"WP_RADIUS", -1), lambda g: of_type(g, "PARAM_VALUE"))
        p = of_type(got, "PARAM_VALUE")[0]
        assert (p.param_id, p.param_value, p.param_index) == ("WP_RADIUS", 150.0, store.index("WP_RADIUS"))
        got = L.exchange(L.peer.mav.param_request_read_encode(1, 1, b"", 0), lambda g: of_type(g, "PARAM_VALUE"))
        assert of_type(got, "PARAM_VALUE")[0].param_id == store.name_at(0)
        # set: accepted, the simulation's callback sees it
        got = L.exchange(L.peer.mav.param_set_encode(1, 1, b"WP_SPEED", 120.5, mav.MAV_PARAM_TYPE_REAL32),
                         lambda g: of_type(g, "PARAM_VALUE"))
        assert (of_type(got, "PARAM_VALUE")[0].param_id, of_type(got, "PARAM_VALUE")[0].param_value) == ("WP_SPEED", 120.5)
        assert store["WP_SPEED"] == 120.5 and seen == [("WP_SPEED", 120.5)]
        assert float(store.replace_into(wm).speed_m_s[0]) == 120.5
        # rejected: out of range, NaN -> the unchanged value comes back, counted
        for bad in (-3.0, float("nan"), float("inf")):
            got = L.exchange(L.peer.mav.param_set_encode(1, 1, b"WP_SPEED", bad, mav.MAV_PARAM_TYPE_REAL32),
                             lambda g: of_type(g, "PARAM_VALUE"))
            assert of_type(got, "PARAM_VALUE")[0].param_value == 120.5
        assert L.ep.counters["param_rejected"] == 3 and store["WP_SPEED"] == 120.5 and len(seen) == 1
        # unknown name / index: no answer, counted
        for req in (L.peer.mav.param_set_encode(1, 1, b"NO_SUCH_PARAM", 1.0, 9),
                    L.peer.mav.param_request_read_encode(1, 1, b"NO_SUCH_PARAM", -1),
                    L.peer.mav.param_request_read_encode(1, 1, b"", 999)):
            assert not of_type(L.exchange(req, lambda g: False, max_steps=2), "PARAM_VALUE")
        assert L.ep.counters["param_unknown"] == 3


def test_param_veto_by_the_simulation_keeps_the_old_value():
    store = ParamStore(sonde_param_specs())

    def veto(name, value):
        if name == "SND_ASCENT" and value > 10:
            raise ValueError("too fast for this balloon")

    store.on_change(veto)
    with Link("sonde", params=store) as L:
        old = store["SND_ASCENT"]
        got = L.exchange(L.peer.mav.param_set_encode(1, 1, b"SND_ASCENT", 12.0, 9), lambda g: of_type(g, "PARAM_VALUE"))
        assert of_type(got, "PARAM_VALUE")[0].param_value == old == store["SND_ASCENT"]
        assert L.ep.counters["param_rejected"] == 1


# ---------------------------------------------------------------------------- missions
def _items(peer_mav, wps, frame=mav.MAV_FRAME_GLOBAL_INT, mission_type=0):
    return [peer_mav.mission_item_int_encode(1, 1, i, frame, mav.MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0, 0,
                                             int(round(la * 1e7)), int(round(lo * 1e7)), alt, mission_type)
            for i, (la, lo, alt) in enumerate(wps)]


def _upload(L, items, mission_type=0, max_steps=40):
    """Run the GCS side of an upload; returns the MISSION_ACK (or None) and all received."""
    got = L.exchange(L.peer.mav.mission_count_encode(1, 1, len(items), mission_type),
                     lambda g: of_type(g, "MISSION_REQUEST_INT") or of_type(g, "MISSION_ACK"))
    all_got = list(got)
    for _ in range(max_steps):
        acks = of_type(got, "MISSION_ACK")
        if acks:
            return acks[0], all_got
        req = of_type(got, "MISSION_REQUEST_INT")[-1]
        got = L.exchange(items[req.seq], lambda g: of_type(g, "MISSION_REQUEST_INT") or of_type(g, "MISSION_ACK"))
        all_got += got
    return None, all_got


def _download(L, mission_type=0):
    got = L.exchange(L.peer.mav.mission_request_list_encode(1, 1, mission_type), lambda g: of_type(g, "MISSION_COUNT"))
    n = of_type(got, "MISSION_COUNT")[0].count
    items = []
    for seq in range(n):
        got = L.exchange(L.peer.mav.mission_request_int_encode(1, 1, seq, mission_type),
                         lambda g: of_type(g, "MISSION_ITEM_INT"))
        items.append(of_type(got, "MISSION_ITEM_INT")[0])
    L.exchange(L.peer.mav.mission_ack_encode(1, 1, 0, mission_type), lambda g: False, max_steps=1)
    return items


def test_uav_mission_upload_download_clear():
    flown = []
    wps = [(45.2, 30.1, 3000.0), (45.3, 30.2, 3100.5), (45.25, 30.35, 2900.0)]
    with Link("uav", on_mission=flown.append) as L:
        L.step(1)  # home = first telemetry
        ack, got = _upload(L, _items(L.peer.mav, wps))
        assert ack is not None and ack.type == mav.MAV_MISSION_ACCEPTED
        assert [r.seq for r in of_type(got, "MISSION_REQUEST_INT")] == [0, 1, 2]
        assert len(flown) == 1 and len(flown[0]) == 3
        for (la, lo, alt), (lat_rad, lon_rad, alt_m) in zip(wps, flown[0]):
            assert lat_rad == pytest.approx(math.radians(la), abs=2e-9)  # degE7 quantisation
            assert lon_rad == pytest.approx(math.radians(lo), abs=2e-9) and alt_m == pytest.approx(alt, abs=1e-3)
        items = _download(L)
        assert [(i.seq, i.x, i.y, i.command) for i in items] == \
            [(k, int(round(la * 1e7)), int(round(lo * 1e7)), mav.MAV_CMD_NAV_WAYPOINT) for k, (la, lo, _) in enumerate(wps)]
        # relative altitude frame: converted with the home height
        ack, _ = _upload(L, _items(L.peer.mav, [(45.0, 30.0, 100.0)], frame=mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT))
        assert ack.type == mav.MAV_MISSION_ACCEPTED
        assert flown[-1][0][2] == pytest.approx(L.tel.alt_msl_m + 100.0, abs=1e-3)
        # clear
        got = L.exchange(L.peer.mav.mission_clear_all_encode(1, 1, 0), lambda g: of_type(g, "MISSION_ACK"))
        assert of_type(got, "MISSION_ACK")[0].type == mav.MAV_MISSION_ACCEPTED and flown[-1] == []
        assert _download(L) == []
        # fence and rally: zero items, upload refused at once (no stall)
        assert _download(L, mav.MAV_MISSION_TYPE_FENCE) == [] and _download(L, mav.MAV_MISSION_TYPE_RALLY) == []
        ack, _ = _upload(L, _items(L.peer.mav, wps, mission_type=mav.MAV_MISSION_TYPE_FENCE),
                         mission_type=mav.MAV_MISSION_TYPE_FENCE)
        assert ack.type == mav.MAV_MISSION_UNSUPPORTED


def test_uav_mission_bad_items_refused_and_old_plan_kept():
    flown = []
    with Link("uav", on_mission=flown.append) as L:
        ack, _ = _upload(L, _items(L.peer.mav, [(45.0, 30.0, 10.0)]))
        assert ack.type == mav.MAV_MISSION_ACCEPTED
        ack, _ = _upload(L, _items(L.peer.mav, [(45.0, 30.0, 10.0), (95.0, 30.0, 10.0)]))
        assert ack.type == mav.MAV_MISSION_INVALID_PARAM5_X
        ack, _ = _upload(L, _items(L.peer.mav, [(45.0, 30.0, 10.0)], frame=mav.MAV_FRAME_LOCAL_NED))
        assert ack.type == mav.MAV_MISSION_UNSUPPORTED_FRAME
        assert len(flown) == 1 and len(_download(L)) == 1
        assert L.ep.counters["mission_rejected"] == 2


def test_uav_mission_on_mission_error_is_refused():
    def refuse(wps):
        raise ValueError("waypoints too close")

    with Link("uav", on_mission=refuse) as L:
        ack, _ = _upload(L, _items(L.peer.mav, [(45.0, 30.0, 10.0)]))
        assert ack.type == mav.MAV_MISSION_ERROR and _download(L) == []


def test_uav_mission_upload_timeout_retries_then_cancels():
    with Link("uav", on_mission=lambda w: None, mission_timeout_s=1.0, mission_retries=3) as L:
        got = L.exchange(L.peer.mav.mission_count_encode(1, 1, 2, 0), lambda g: of_type(g, "MISSION_REQUEST_INT"))
        got += L.step(60, dt=0.1)  # 6 s of silence from the GCS
        reqs = of_type(got, "MISSION_REQUEST_INT")
        assert [r.seq for r in reqs] == [0] * 4  # first request + 3 retries, 1 s apart
        assert of_type(got, "MISSION_ACK")[0].type == mav.MAV_MISSION_OPERATION_CANCELLED
        assert L.ep.counters["mission_timeout"] == 1 and not L.ep.mission.uploading


def test_sonde_has_zero_mission_items():
    with Link("sonde") as L:
        assert _download(L) == []
        ack, _ = _upload(L, _items(L.peer.mav, [(45.0, 30.0, 10.0)]))
        assert ack.type == mav.MAV_MISSION_UNSUPPORTED


# ---------------------------------------------------------------------------- signing
def test_signing_accepts_signed_rejects_unsigned_bad_and_replayed():
    quiet = {k: 0 for k in (0, 1, 2, 24, 30, 33)}  # replies only
    store = ParamStore(sonde_param_specs())
    with Link("sonde", signing_key=KEY, params=store, stream_rates_hz=quiet) as L:
        req = L.peer.mav.param_request_read_encode(1, 1, b"SND_P1", -1)
        buf = L.peer.pack(req)
        got = L.exchange(buf, lambda g: of_type(g, "PARAM_VALUE"))
        pv = of_type(got, "PARAM_VALUE")
        assert pv and pv[0]._signed and pv[0].get_header().incompat_flags & mav.MAVLINK_IFLAG_SIGNED
        assert L.peer.mav.signing.goodsig_count >= 1 and L.peer.mav.signing.badsig_count == 0
        # the same bytes again: replayed
        assert not of_type(L.exchange(buf, lambda g: False, max_steps=2), "PARAM_VALUE")
        # unsigned and wrongly signed
        unsigned = Peer()
        wrong = Peer(signing_key=bytes(32))
        try:
            unsigned.send(unsigned.mav.param_request_read_encode(1, 1, b"SND_P1", -1), L.to)
            wrong.send(wrong.mav.param_request_read_encode(1, 1, b"SND_P1", -1), L.to)
            got = L.exchange(None, lambda g: False, max_steps=3)
            assert not unsigned.drain(0.01) and not wrong.drain(0.0)
        finally:
            unsigned.close()
            wrong.close()
        c = L.ep.counters
        assert (c["replayed"], c["unsigned"], c["bad_signature"], c["received"]) == (1, 1, 1, 1)
        # a signed frame with one payload byte changed (CRC recomputed): bad signature, not bad CRC
        tampered = bytearray(L.peer.pack(L.peer.mav.param_request_read_encode(1, 1, b"SND_P2", -1)))
        hdr = L.peer.mav.decode(bytearray(tampered)).get_header()
        tampered[12] ^= 0x01
        from pymavlink.generator.mavcrc import x25crc
        crc = x25crc(bytes(tampered[1:10 + hdr.mlen]))
        crc.accumulate([mav.MAVLink_param_request_read_message.crc_extra])
        tampered[10 + hdr.mlen:12 + hdr.mlen] = crc.crc.to_bytes(2, "little")
        L.exchange(bytes(tampered), lambda g: False, max_steps=2)
        assert L.ep.counters["bad_signature"] == 2 and L.ep.counters["bad_crc"] == 0


# ---------------------------------------------------------------------------- bad input
def test_bad_input_is_rejected_counted_and_survived():
    store = ParamStore([ParamSpec("A", 1.0), ParamSpec("B", 2.0)])
    with Link(params=store) as L:
        good = L.peer.pack(L.peer.mav.param_request_read_encode(1, 1, b"A", -1))
        bad_crc = bytearray(good)
        bad_crc[-1] ^= 0xFF
        unknown = bytearray(good)
        unknown[7:10] = (0xFFFF00).to_bytes(3, "little")  # msgid 16776960: in no dialect
        flags = bytearray(good)
        flags[2] = 0x02  # an incompat flag we do not know
        cases = [(b"hello, not mavlink", "garbage"), (bytes(bad_crc), "bad_crc"), (bytes(unknown), "unknown_msgid"),
                 (good[:-3], "truncated"), (bytes(flags), "unsupported_flags"), (b"", None)]
        for data, reason in cases:
            before = dict(L.ep.counters)
            L.exchange(data, lambda g: False, max_steps=2)
            if reason is not None:
                assert L.ep.counters[reason] == before[reason] + 1, reason
        # several packets in one datagram, with garbage between them: both answered
        two = good + b"\x00junk" + L.peer.pack(L.peer.mav.param_request_read_encode(1, 1, b"B", -1))
        got = L.exchange(two, lambda g: len(of_type(g, "PARAM_VALUE")) >= 2)
        assert sorted(p.param_id for p in of_type(got, "PARAM_VALUE")) == ["A", "B"]
        assert L.ep.counters["garbage"] == 2
        # and it still streams
        assert of_type(L.step(10), "HEARTBEAT")


def test_bad_input_hypothesis_never_raises():
    from hypothesis import given, settings
    from hypothesis import strategies as st

    with Link(params=ParamStore([ParamSpec("A", 1.0)])) as L:
        ep = L.ep
        good = L.peer.pack(L.peer.mav.param_request_read_encode(1, 1, b"A", -1))

        @settings(max_examples=200, deadline=None, derandomize=True)
        @given(st.binary(max_size=600), st.integers(0, 600), st.booleans())
        def feed(data, cut, with_good):
            blob = (data[:cut] + good + data[cut:]) if with_good else data
            keys = ("received",) + REJECT_REASONS
            n0, d0 = sum(ep.counters[k] for k in keys), ep.counters["rx_datagrams"]
            ep.handle_datagram(blob, L.peer.addr)
            # every datagram is seen, and anything in it is either accepted or rejected with a reason
            assert ep.counters["rx_datagrams"] == d0 + 1
            assert sum(ep.counters[k] for k in keys) > n0 or not blob
            if with_good and not data:
                assert ep.counters["received"] > 0

        feed()


# ---------------------------------------------------------------------------- tlog
def test_tlog_reads_with_pymavlink_and_mavlogdump(tmp_path):
    path = tmp_path / "uav1.tlog"
    with Link(tlog=str(path), params=ParamStore([ParamSpec("A", 1.0)])) as L:
        got = L.step(20)
        got += L.exchange(L.peer.mav.param_request_read_encode(1, 1, b"A", -1), lambda g: of_type(g, "PARAM_VALUE"))
        sent, received = L.ep.counters["sent"], L.ep.counters["received"]
    log = mavutil.mavlink_connection(str(path))
    msgs = []
    while True:
        m = log.recv_match()
        if m is None:
            break
        msgs.append(m)
    log.close()
    assert len(msgs) == sent + received
    assert [m.get_type() for m in msgs if m.get_srcSystem() == 255] == ["PARAM_REQUEST_READ"]
    first = msgs[0]
    assert first._timestamp == pytest.approx(_unix_us(T0_GPS_S) / 1e6, abs=1e-6)  # simulated unix time
    st = [m for m in msgs if m.get_type() == "SYSTEM_TIME"]
    assert all(abs(m._timestamp * 1e6 - m.time_unix_usec) < 2 for m in st)
    import pymavlink
    tool = os.path.join(os.path.dirname(pymavlink.__file__), "tools", "mavlogdump.py")
    out = subprocess.run([sys.executable, tool, "--types", "HEARTBEAT", str(path)], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0
    assert out.stdout.count("HEARTBEAT") == len([m for m in msgs if m.get_type() == "HEARTBEAT"]) \
        == len(of_type(got, "HEARTBEAT")) >= 2


# ---------------------------------------------------------------------------- group
def test_group_of_uavs_and_a_sonde():
    peer = Peer()
    eps = [VehicleEndpoint(i + 1, kind, gcs=peer.addr, listen=("127.0.0.1", 0),
                           params=ParamStore(uav_param_specs() if kind == "uav" else sonde_param_specs()))
           for i, kind in enumerate(["uav", "uav", "sonde"])]
    try:
        with pytest.raises(ValueError, match="distinct"):
            EndpointGroup([eps[0], eps[0]])
        with EndpointGroup(eps) as g:
            got = []
            for k in range(20):
                g.step(T0_GPS_S + 0.1 * k, [telemetry(), telemetry(), telemetry(armed=False)])
                got += peer.drain(0.0)
            hb = {m.get_srcSystem(): m.type for m in of_type(got, "HEARTBEAT")}
            assert hb == {1: mav.MAV_TYPE_FIXED_WING, 2: mav.MAV_TYPE_FIXED_WING, 3: mav.MAV_TYPE_FREE_BALLOON}
            # a request to system 2 answered by 2 only, through the group's poll
            peer.send(peer.mav.param_request_list_encode(2, 1), eps[1].listen_addr)
            for k in range(20, 40):
                g.step(T0_GPS_S + 0.1 * k, [None, telemetry(), None])
                got += peer.drain(0.005)
                if len(of_type(got, "PARAM_VALUE")) >= len(eps[1].params):
                    break
            pv = of_type(got, "PARAM_VALUE")
            assert {m.get_srcSystem() for m in pv} == {2} and len(pv) == len(eps[1].params)
            assert g.counters["sent"] == sum(e.counters["sent"] for e in eps) > 0
            with pytest.raises(ValueError, match="one entry per endpoint"):
                g.step(T0_GPS_S + 5, [None])
    finally:
        peer.close()


# ---------------------------------------------------------------------------- what GCSs do at connect
def test_qgc_initial_connect_sequence_completes_without_waiting():
    """QGroundControl's InitialConnectStateMachine, request by request, each answered within
    one step of 0.1 s (QGC waits seconds for an unanswered one)."""
    store, _ = _uav_store()
    with Link("uav", params=store, on_mission=lambda w: None) as L:
        L.step(2)
        seq = [
            (_cmd(L, mav.MAV_CMD_REQUEST_MESSAGE, 148), lambda g: of_type(g, "AUTOPILOT_VERSION")),
            (_cmd(L, mav.MAV_CMD_REQUEST_MESSAGE, 397), lambda g: of_type(g, "COMMAND_ACK")),
            (_cmd(L, mav.MAV_CMD_REQUEST_MESSAGE, 395), lambda g: of_type(g, "COMMAND_ACK")),
            (_cmd(L, mav.MAV_CMD_REQUEST_MESSAGE, 435), lambda g: of_type(g, "COMMAND_ACK")),
            (L.peer.mav.param_request_list_encode(1, 1), lambda g: len(of_type(g, "PARAM_VALUE")) == len(store)),
            (L.peer.mav.mission_request_list_encode(1, 1, 0), lambda g: of_type(g, "MISSION_COUNT")),
            (_cmd(L, mav.MAV_CMD_REQUEST_MESSAGE, 242), lambda g: of_type(g, "HOME_POSITION")),
        ]
        for req, done in seq:
            got = L.exchange(req, done, max_steps=1)
            assert done(got), req.get_type()
        home = of_type(got, "HOME_POSITION")[0]
        assert (home.latitude, home.longitude, home.altitude) == (
            int(np.rint(np.degrees(L.tel.lat_rad) * 1e7)), int(np.rint(np.degrees(L.tel.lon_rad) * 1e7)),
            int(np.rint(L.tel.alt_msl_m * 1e3)))


def test_ftp_parameter_download_of_param_pck():
    """MAVProxy's first parameter request, OpenFileRO @PARAM/param.pck, then a burst read: the
    file decodes (MAVProxy's own param.pck decoder) to the vehicle's parameters; a path that
    does not exist is a Nak FileNotFound; every request is counted ("ftp")."""
    param_ftp = pytest.importorskip("MAVProxy.modules.lib.param_ftp")
    store = ParamStore([ParamSpec("WP_RADIUS", 200.0, 1.0, 1e5, "m"), ParamSpec("NAV_Q", 0.5, 0.0, 10.0, "q")])
    with Link(params=store) as L:
        def ftp(seq, session, opcode, data=b"", offset=0, size=None):
            size = len(data) if size is None else size
            payload = seq.to_bytes(2, "little") + bytes([session, opcode, size, 0, 0, 0]) + \
                offset.to_bytes(4, "little") + data
            req = L.peer.mav.file_transfer_protocol_encode(0, L.ep.sysid, 1, list(payload.ljust(251, b"\x00")))
            got = L.exchange(req, lambda g: of_type(g, "FILE_TRANSFER_PROTOCOL"), max_steps=1)
            return [bytes(m.payload) for m in of_type(got, "FILE_TRANSFER_PROTOCOL")]

        p = ftp(7, 3, 4, b"@PARAM/param.pck")[0]  # OpenFileRO
        assert (int.from_bytes(p[:2], "little"), p[2], p[3], p[5]) == (8, 3, 128, 4)  # Ack of the open
        size = int.from_bytes(p[12:16], "little")
        data = b""
        for r in ftp(9, 3, 15, size=239):  # BurstReadFile from 0
            if r[3] == 128:
                off, n = int.from_bytes(r[8:12], "little"), r[4]
                data = data[:off] + r[12:12 + n]
        assert len(data) == size
        pdata = param_ftp.ftp_param_decode(data)
        got = {name.decode(): value for name, value, _ptype in pdata.params}
        assert got == pytest.approx({"WP_RADIUS": 200.0, "NAV_Q": 0.5})
        assert ftp(20, 3, 1)[0][3] == 128  # TerminateSession: Ack
        p = ftp(22, 4, 4, b"@PARAM/nothing.pck")[0]
        assert (p[3], p[12]) == (129, 10)  # Nak FileNotFound
        assert L.ep.counters["ftp"] == 4


def test_a_gcs_connecting_to_the_vehicle_port_gets_the_streams_until_it_goes_quiet():
    with Link() as L:
        direct = Peer(sysid=254)
        try:
            direct.send(direct.mav.heartbeat_encode(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0), L.to)
            L.exchange(None, lambda g: False, max_steps=1)
            L.step(20)
            assert len(of_type(direct.drain(0.01), "HEARTBEAT")) >= 2  # streams to it as well as to the GCS
            L.step(700, dt=0.1)  # 70 s without a word from it
            direct.drain(0.0)
            L.step(20)
            assert not direct.drain(0.01)
        finally:
            direct.close()


def test_legacy_mission_item_float_messages():
    flown = []
    with Link("uav", on_mission=flown.append) as L:
        items = [L.peer.mav.mission_item_encode(1, 1, 0, mav.MAV_FRAME_GLOBAL, mav.MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0, 0,
                                                45.5, 30.25, 1234.5, 0)]
        got = L.exchange(L.peer.mav.mission_count_encode(1, 1, 1, 0), lambda g: of_type(g, "MISSION_REQUEST_INT"))
        got = L.exchange(items[0], lambda g: of_type(g, "MISSION_ACK"))
        assert of_type(got, "MISSION_ACK")[0].type == mav.MAV_MISSION_ACCEPTED
        assert flown[0][0] == pytest.approx((math.radians(45.5), math.radians(30.25), 1234.5), abs=2e-9)
        got = L.exchange(L.peer.mav.mission_request_encode(1, 1, 0, 0), lambda g: of_type(g, "MISSION_ITEM"))
        it = of_type(got, "MISSION_ITEM")[0]
        assert (it.x, it.y, it.z) == pytest.approx((45.5, 30.25, 1234.5), abs=1e-6)
        got = L.exchange(L.peer.mav.mission_request_int_encode(1, 1, 5, 0), lambda g: of_type(g, "MISSION_ACK"))
        assert of_type(got, "MISSION_ACK")[0].type == mav.MAV_MISSION_INVALID_SEQUENCE


def test_a_handler_bug_is_counted_not_raised():
    with Link() as L:
        def boom(msg, addr):
            raise RuntimeError("simulated bug")
        L.ep._handlers["TIMESYNC"] = boom
        L.exchange(L.peer.mav.timesync_encode(0, 1), lambda g: False, max_steps=2)
        assert L.ep.counters["handler_errors"] == 1 and "RuntimeError: simulated bug" in L.ep.last_error
        assert of_type(L.step(10), "HEARTBEAT")


def test_a_group_can_share_one_tlog(tmp_path):
    from vehicles.mavlink import TlogWriter
    path = tmp_path / "group.tlog"
    peer = Peer()
    try:
        with TlogWriter(path) as w:
            eps = [VehicleEndpoint(i + 1, "uav", gcs=peer.addr, listen=("127.0.0.1", 0), tlog=w) for i in range(2)]
            with EndpointGroup(eps) as g:
                for k in range(15):
                    g.step(T0_GPS_S + 0.1 * k, [telemetry(), telemetry()])
                sent = g.counters["sent"]
                sent_by_sys = {ep.sysid: ep.counters["sent"] for ep in eps}
        log = mavutil.mavlink_connection(str(path))
        by_sys = {}
        while (m := log.recv_match()) is not None:
            by_sys[m.get_srcSystem()] = by_sys.get(m.get_srcSystem(), 0) + 1
        log.close()
        # every packet each endpoint sent is in the one file, under its own system id (the
        # endpoints' streams are phase-spread, so their counts need not be equal)
        assert sum(by_sys.values()) == sent and by_sys == sent_by_sys
    finally:
        peer.close()
