"""The UAVs' autopilot over MAVLink (issue 21), with pymavlink as the GCS: the vehicle worker's own
VehicleGroup + build_endpoints on loopback, stepped in simulated time (no clock, no sleeps).
Every new message and command for every vehicle kind, including bad input (modes that do not
exist, NaN parameters, a mission with an item the vehicles cannot fly): a clear ACK, counted,
never a crash."""
from __future__ import annotations

import math
import select

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav
from tests.mavlink_peer import Peer, of_type

from sitl.bus import InMemoryTransport
from sitl.scenario import default_scenario
from vehicles.autopilot import convention as cv
from tests.procs import udp_base
from vehicles.process import VehicleGroup, _mav_telemetry, build_endpoints


class Group:
    """A vehicle group (3 UAVs + the sonde) and its endpoints, with a pymavlink GCS peer."""

    def __init__(self, tmp_path, start="in-flight", count=3, sonde=True):
        self.peer = Peer()
        self.base = udp_base(count + 1)
        scn = default_scenario().replace(sonde={"enabled": sonde}, uavs={"count": count, "start": start},
                                         mavlink={"gcs": f"127.0.0.1:{self.peer.addr[1]}", "base_port": self.base,
                                                  "tlog": False})
        self.scn = scn
        self.g = VehicleGroup(scn, list(range(count)), InMemoryTransport(), np.random.SeedSequence(3),
                              with_sonde=sonde)
        self.eg = build_endpoints(self.g, scn, tmp_path)
        self.dt = 1.0 / scn.run.rate_hz
        self.k = 0

    @property
    def t(self) -> float:
        return self.scn.run.t0_gps_s + self.k * self.dt

    def step(self, n: int = 1) -> list:
        out = []
        for _ in range(n):
            t = self.t
            self.g.step(t)
            self.eg.step(t, _mav_telemetry(self.g.telemetry(), len(self.eg)))
            self.k += 1
            out += self.peer.drain(0.0)
        return out

    def addr(self, sysid: int):
        return ("127.0.0.1", self.base + 10 * (sysid - 1))

    def ep(self, sysid: int):
        return self.g.endpoints[sysid - 1]

    def exchange(self, sysid: int, msg, until, max_steps: int = 5) -> list:
        self.peer.send(msg, self.addr(sysid))
        got = []
        for _ in range(max_steps):
            select.select([self.ep(sysid).sock], [], [], 0.02)
            got += self.step(1)
            got += self.peer.drain(0.005)
            if until(got):
                return got
        return got

    def cmd(self, sysid, command, *params, use_int=False):
        p = list(params) + [0.0] * (7 - len(params))
        if use_int:
            return self.peer.mav.command_int_encode(sysid, 1, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command, 0, 0,
                                                    *p[:4], int(p[4]), int(p[5]), p[6])
        return self.peer.mav.command_long_encode(sysid, 1, command, 0, *p)

    def ack(self, sysid, msg) -> tuple:
        got = self.exchange(sysid, msg, lambda g: of_type(g, "COMMAND_ACK"))
        acks = [a for a in of_type(got, "COMMAND_ACK") if a.get_srcSystem() == sysid]
        assert acks, f"no COMMAND_ACK from {sysid} for {msg}"
        return acks[0].command, acks[0].result

    def heartbeat(self, sysid, steps: int = 12):
        got = [m for m in self.step(steps) if m.get_type() == "HEARTBEAT" and m.get_srcSystem() == sysid]
        assert got, f"no HEARTBEAT from {sysid}"
        return got[-1]

    def close(self):
        self.eg.close()
        self.peer.close()


@pytest.fixture
def grp(tmp_path):
    g = Group(tmp_path)
    yield g
    g.close()


def _item(peer, seq, lat, lon, alt, cmd=mav.MAV_CMD_NAV_WAYPOINT, frame=mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
          current=0, sysid=1, p=(0, 0, 0, 0)):
    return peer.mav.mission_item_int_encode(sysid, 1, seq, frame, cmd, current, 1, *p, int(round(lat * 1e7)),
                                            int(round(lon * 1e7)), alt, 0)


def upload(grp, sysid, items) -> int:
    """MISSION_COUNT then each requested item; the MISSION_ACK type."""
    got = grp.exchange(sysid, grp.peer.mav.mission_count_encode(sysid, 1, len(items), 0),
                       lambda g: of_type(g, "MISSION_REQUEST_INT") or of_type(g, "MISSION_ACK"))
    for _ in range(len(items) + 1):
        acks = [a for a in of_type(got, "MISSION_ACK") if a.get_srcSystem() == sysid]
        if acks:
            return acks[0].type
        req = [r for r in of_type(got, "MISSION_REQUEST_INT") if r.get_srcSystem() == sysid][-1]
        got = grp.exchange(sysid, items[req.seq],
                           lambda g: of_type(g, "MISSION_REQUEST_INT") or of_type(g, "MISSION_ACK"))
    raise AssertionError("upload did not finish")


def _pos(grp, sysid):
    ap = grp.g.autopilot
    la, lo, h = ap.pos[sysid - 1]
    return math.degrees(la), math.degrees(lo), h


def test_heartbeat_is_arduplane_in_auto_and_armed_in_flight(grp):
    hb = grp.heartbeat(1)
    assert (hb.type, hb.autopilot) == (mav.MAV_TYPE_FIXED_WING, mav.MAV_AUTOPILOT_ARDUPILOTMEGA)
    assert hb.custom_mode == cv.AUTO and hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
    assert hb.base_mode & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED and hb.system_status == mav.MAV_STATE_ACTIVE
    sonde = grp.heartbeat(4)
    assert sonde.type == mav.MAV_TYPE_FREE_BALLOON


@pytest.mark.parametrize("use_int", [False, True])
def test_modes_by_command_and_set_mode_with_bad_input(grp, use_int):
    ep = grp.ep(1)
    assert grp.ack(1, grp.cmd(1, mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, cv.LOITER,
                              use_int=use_int)) == (mav.MAV_CMD_DO_SET_MODE, mav.MAV_RESULT_ACCEPTED)
    assert grp.heartbeat(1, 3).custom_mode == cv.LOITER
    before = ep.counters["cmd_refused"]
    assert grp.ack(1, grp.cmd(1, mav.MAV_CMD_DO_SET_MODE, 1, 99, use_int=use_int))[1] == mav.MAV_RESULT_DENIED
    assert grp.ack(1, grp.cmd(1, mav.MAV_CMD_DO_SET_MODE, 1, math.nan, use_int=use_int))[1] != mav.MAV_RESULT_ACCEPTED
    assert ep.counters["cmd_refused"] == before + 2
    # SET_MODE: answered with COMMAND_ACK(DO_SET_MODE) as ArduPilot does
    assert grp.ack(1, grp.peer.mav.set_mode_encode(1, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, cv.RTL)) == \
        (mav.MAV_CMD_DO_SET_MODE, mav.MAV_RESULT_ACCEPTED)
    assert grp.heartbeat(1, 3).custom_mode == cv.RTL
    assert grp.ack(1, grp.peer.mav.set_mode_encode(1, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 99))[1] == \
        mav.MAV_RESULT_DENIED
    # an unknown command; NaN in a command the autopilot knows
    assert grp.ack(1, grp.cmd(1, 42424, 1, use_int=use_int))[1] == mav.MAV_RESULT_UNSUPPORTED
    assert grp.ack(1, grp.cmd(1, mav.MAV_CMD_DO_REPOSITION, -1, 1, 0, 0, math.nan, math.nan, 100))[1] != \
        mav.MAV_RESULT_ACCEPTED
    # the other UAVs were not touched
    assert grp.g.autopilot.mode.tolist()[1:] == [cv.AUTO, cv.AUTO]


def test_sonde_refuses_flight_commands_clearly(grp):
    ep = grp.ep(4)
    for cmd in (mav.MAV_CMD_COMPONENT_ARM_DISARM, mav.MAV_CMD_DO_SET_MODE, mav.MAV_CMD_NAV_RETURN_TO_LAUNCH):
        assert grp.ack(4, grp.cmd(4, cmd, 1, 1)) == (cmd, mav.MAV_RESULT_UNSUPPORTED)
    assert grp.ack(4, grp.peer.mav.set_mode_encode(4, 1, cv.GUIDED)) == (mav.MAV_CMD_DO_SET_MODE,
                                                                           mav.MAV_RESULT_UNSUPPORTED)
    assert ep.counters["cmd_unsupported"] >= 4
    grp.peer.send(grp.peer.mav.set_position_target_global_int_encode(0, 4, 1, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                                                       0b110111111000, 0, 0, 100, 0, 0, 0, 0, 0, 0, 0,
                                                                       0), grp.addr(4))
    grp.step(2)
    assert ep.counters["handler_errors"] == 0


def test_mission_with_home_at_item_0_progress_and_download(grp):
    lat, lon, h = _pos(grp, 1)
    home = _item(grp.peer, 0, lat, lon, 0.0, frame=mav.MAV_FRAME_GLOBAL_INT)
    wps = [_item(grp.peer, k, lat + 0.01 * k, lon, 2000.0 + 100 * k) for k in (1, 2, 3)]
    assert upload(grp, 1, [home] + wps) == mav.MAV_MISSION_ACCEPTED
    got = grp.step(15)
    cur = [m for m in of_type(got, "MISSION_CURRENT") if m.get_srcSystem() == 1]
    assert cur and cur[-1].seq == 1 and cur[-1].total == 3
    # download: item 0 is home (the autopilot's), then the uploaded items
    got = grp.exchange(1, grp.peer.mav.mission_request_list_encode(1, 1, 0), lambda g: of_type(g, "MISSION_COUNT"))
    assert of_type(got, "MISSION_COUNT")[0].count == 4
    got = grp.exchange(1, grp.peer.mav.mission_request_int_encode(1, 1, 0, 0), lambda g: of_type(g, "MISSION_ITEM_INT"))
    it0 = of_type(got, "MISSION_ITEM_INT")[0]
    hl = grp.g.autopilot.home[0]
    assert (it0.x, it0.y) == (round(math.degrees(hl[0]) * 1e7), round(math.degrees(hl[1]) * 1e7))
    # MISSION_SET_CURRENT: MISSION_CURRENT says so at once
    got = grp.exchange(1, grp.peer.mav.mission_set_current_encode(1, 1, 3),
                       lambda g: [m for m in of_type(g, "MISSION_CURRENT") if m.seq == 3])
    assert [m for m in of_type(got, "MISSION_CURRENT") if m.get_srcSystem() == 1 and m.seq == 3]
    before = grp.ep(1).counters["mission_rejected"]
    grp.exchange(1, grp.peer.mav.mission_set_current_encode(1, 1, 77), lambda g: False, max_steps=2)
    assert grp.ep(1).counters["mission_rejected"] == before + 1
    # MAV_CMD_DO_SET_MISSION_CURRENT too
    assert grp.ack(1, grp.cmd(1, mav.MAV_CMD_DO_SET_MISSION_CURRENT, 2))[1] == mav.MAV_RESULT_ACCEPTED


def test_mission_items_reached_in_order(grp):
    lat, lon, h = _pos(grp, 2)
    home = _item(grp.peer, 0, lat, lon, 0.0, frame=mav.MAV_FRAME_GLOBAL_INT, sysid=2)
    # two waypoints 3 km and 6 km ahead-ish (the UAV turns to them at 100 m/s)
    wps = [_item(grp.peer, k, lat + 0.027 * k, lon, h, frame=mav.MAV_FRAME_GLOBAL_INT, sysid=2) for k in (1, 2)]
    assert upload(grp, 2, [home] + wps) == mav.MAV_MISSION_ACCEPTED
    reached = []
    for _ in range(400):
        reached += [m.seq for m in of_type(grp.step(10), "MISSION_ITEM_REACHED") if m.get_srcSystem() == 2]
        if 2 in reached:
            break
    assert reached[:2] == [1, 2]
    assert grp.heartbeat(2, 5).custom_mode == cv.RTL  # ArduPlane: the end of a mission is RTL


def test_mission_with_an_unsupported_item_is_refused_with_its_code(grp):
    lat, lon, h = _pos(grp, 1)
    items = [_item(grp.peer, 0, lat, lon, 0.0, frame=mav.MAV_FRAME_GLOBAL_INT),
             _item(grp.peer, 1, lat + 0.01, lon, 100.0),
             _item(grp.peer, 2, 0, 0, 0, cmd=mav.MAV_CMD_DO_DIGICAM_CONTROL, frame=mav.MAV_FRAME_MISSION)]
    before = grp.ep(1).counters["mission_rejected"]
    assert upload(grp, 1, items) == mav.MAV_MISSION_UNSUPPORTED
    assert grp.ep(1).counters["mission_rejected"] == before + 1
    assert "item 2" in grp.ep(1).last_error
    got = grp.exchange(1, grp.peer.mav.mission_request_list_encode(1, 1, 0), lambda g: of_type(g, "MISSION_COUNT"))
    assert of_type(got, "MISSION_COUNT")[0].count == 1  # home only: nothing was stored


def test_guided_by_mission_item_current_2_and_set_position_target(grp):
    lat, lon, h = _pos(grp, 3)
    got = grp.exchange(3, _item(grp.peer, 0, lat + 0.02, lon, 500.0, current=2, sysid=3),
                       lambda g: of_type(g, "MISSION_ACK"))
    assert of_type(got, "MISSION_ACK")[0].type == mav.MAV_MISSION_ACCEPTED
    assert grp.heartbeat(3, 3).custom_mode == cv.GUIDED
    ap = grp.g.autopilot
    assert math.degrees(ap.guided[2, 0]) == pytest.approx(lat + 0.02, abs=1e-6)
    # SET_POSITION_TARGET_GLOBAL_INT (GUIDED: the new target; no ACK in the protocol)
    grp.peer.send(grp.peer.mav.set_position_target_global_int_encode(
        0, 3, 1, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 0b110111111000, int((lat - 0.02) * 1e7), int(lon * 1e7),
        700.0, 0, 0, 0, 0, 0, 0, 0, 0), grp.addr(3))
    select.select([grp.ep(3).sock], [], [], 0.05)
    grp.step(2)
    assert math.degrees(ap.guided[2, 0]) == pytest.approx(lat - 0.02, abs=1e-6)
    # a guided request with NaN altitude: a MISSION_ACK error, counted
    before = grp.ep(3).counters["mission_rejected"]
    got = grp.exchange(3, _item(grp.peer, 0, lat, lon, math.nan, current=2, sysid=3),
                       lambda g: of_type(g, "MISSION_ACK"))
    assert of_type(got, "MISSION_ACK")[0].type != mav.MAV_MISSION_ACCEPTED
    assert grp.ep(3).counters["mission_rejected"] == before + 1


def test_parameters_are_per_vehicle_and_change_its_autopilot(grp):
    ep1, ep2 = grp.ep(1), grp.ep(2)
    for name in ("WP_RADIUS", "WP_LOITER_RAD", "RTL_ALTITUDE", "AIRSPEED_CRUISE", "TKOFF_ALT", "BATT_CAPACITY",
                 "SYSID_THISMAV", "GNSS_PSD_PR"):
        assert name in ep1.params, name
    assert ep2.params["SYSID_THISMAV"] == 2.0
    got = grp.exchange(1, grp.peer.mav.param_set_encode(1, 1, b"WP_RADIUS", 321.0, mav.MAV_PARAM_TYPE_REAL32),
                       lambda g: of_type(g, "PARAM_VALUE"))
    pv = [p for p in of_type(got, "PARAM_VALUE") if p.get_srcSystem() == 1][0]
    assert (pv.param_id, pv.param_value) == ("WP_RADIUS", 321.0)
    ap = grp.g.autopilot
    assert ap.cfgs[0].wp_radius_m == 321.0 and ap.cfgs[1].wp_radius_m == 200.0 and ep2.params["WP_RADIUS"] == 200.0
    # read-only, and a combination the autopilot refuses: the unchanged value comes back, counted
    for name, v in ((b"SYSID_THISMAV", 9.0), (b"AIRSPEED_CRUISE", 10.0)):
        before = ep1.counters["param_rejected"]
        got = grp.exchange(1, grp.peer.mav.param_set_encode(1, 1, name, v, mav.MAV_PARAM_TYPE_REAL32),
                           lambda g: of_type(g, "PARAM_VALUE"))
        pv = [p for p in of_type(got, "PARAM_VALUE") if p.get_srcSystem() == 1][0]
        assert pv.param_value != v and ep1.counters["param_rejected"] == before + 1
    # a navigation parameter is the group's (one batch of filters): every UAV re-announces it
    got = grp.exchange(2, grp.peer.mav.param_set_encode(2, 1, b"NAV_Q", 0.25, mav.MAV_PARAM_TYPE_REAL32),
                       lambda g: len({p.get_srcSystem() for p in of_type(g, "PARAM_VALUE")}) >= 3)
    srcs = {p.get_srcSystem() for p in of_type(got, "PARAM_VALUE") if p.param_id == "NAV_Q"}
    assert srcs == {1, 2, 3} and ep1.params["NAV_Q"] == 0.25 and grp.g.nav_cfg.q_m2_s3 == 0.25


def test_a_ground_start_is_disarmed_until_armed_and_taken_off(tmp_path):
    grp = Group(tmp_path, start="ground", sonde=False)
    try:
        hb = grp.heartbeat(1)
        assert hb.custom_mode == cv.MANUAL and not hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
        assert hb.system_status == mav.MAV_STATE_STANDBY
        h0 = grp.g.autopilot.pos[0, 2]
        grp.step(20)
        assert grp.g.autopilot.pos[0, 2] == h0  # it stays on the ground
        assert grp.ack(1, grp.cmd(1, mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 100))[1] != mav.MAV_RESULT_ACCEPTED
        assert grp.ack(1, grp.cmd(1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)) == (mav.MAV_CMD_COMPONENT_ARM_DISARM,
                                                                              mav.MAV_RESULT_ACCEPTED)
        assert grp.heartbeat(1, 3).base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
        assert grp.ack(1, grp.cmd(1, mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 100))[1] == mav.MAV_RESULT_ACCEPTED
        texts = []
        for _ in range(120):
            texts += [m.text for m in of_type(grp.step(10), "STATUSTEXT") if m.get_srcSystem() == 1]
            if grp.g.autopilot.pos[0, 2] > h0 + 90:
                break
        assert grp.g.autopilot.pos[0, 2] > h0 + 90
        assert any("Takeoff" in t for t in texts)
        assert grp.g.autopilot.pos[1, 2] == h0  # the others did not move
    finally:
        grp.close()


def test_ten_uavs_from_the_ground_armed_taken_off_and_flown_through_a_5_item_mission(tmp_path):
    """Issue 21: 10 UAVs started on the ground, all armed, taken off and flown through a 5-item
    mission (home + 4 waypoints) by the GCS, concurrently (pymavlink, the worker's group)."""
    n = 10
    grp = Group(tmp_path, start="ground", count=n, sonde=False)
    try:
        ap = grp.g.autopilot
        grp.step(2)
        for s in range(1, n + 1):
            lat, lon, _h = _pos(grp, s)
            items = [_item(grp.peer, 0, lat, lon, 0.0, frame=mav.MAV_FRAME_GLOBAL_INT, sysid=s),
                     _item(grp.peer, 1, lat + 0.005, lon, 300.0, cmd=mav.MAV_CMD_NAV_TAKEOFF, sysid=s,
                           p=(10, 0, 0, 0))]
            items += [_item(grp.peer, k, lat + 0.01 * k, lon + 0.01 * (k % 2), 300.0, sysid=s) for k in (2, 3, 4)]
            assert upload(grp, s, items) == mav.MAV_MISSION_ACCEPTED, s
        for s in range(1, n + 1):
            assert grp.ack(s, grp.cmd(s, mav.MAV_CMD_COMPONENT_ARM_DISARM, 1))[1] == mav.MAV_RESULT_ACCEPTED, s
        for s in range(1, n + 1):
            assert grp.ack(s, grp.peer.mav.set_mode_encode(s, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, cv.AUTO))[1] == \
                mav.MAV_RESULT_ACCEPTED, s
        assert ap.armed.all() and (ap.mode == cv.AUTO).all()
        reached = {s: [] for s in range(1, n + 1)}
        airborne_seen = np.zeros(n, bool)
        for _ in range(300):  # <= 300 s simulated
            for m in of_type(grp.step(10), "MISSION_ITEM_REACHED"):
                reached[m.get_srcSystem()].append(m.seq)
            airborne_seen |= ap.pos[:, 2] > 100.0
            if all(r[-1:] == [4] for r in reached.values()):
                break
        assert airborne_seen.all()
        assert all(r == [1, 2, 3, 4] for r in reached.values()), reached
    finally:
        grp.close()


NAN = math.nan
#: the commands the autopilot flies by, all parameters NaN (COMMAND_INT: x, y = 0, z NaN): the
#: results a NaN in a field the command needs must give (None: NaN means "default / here" in
#: MAVLink for every field it uses, or it uses none -- any clear result)
NAN_COMMANDS = {
    mav.MAV_CMD_COMPONENT_ARM_DISARM: {mav.MAV_RESULT_DENIED},
    mav.MAV_CMD_DO_SET_MODE: {mav.MAV_RESULT_DENIED},
    mav.MAV_CMD_DO_CHANGE_SPEED: {mav.MAV_RESULT_DENIED},
    mav.MAV_CMD_DO_SET_MISSION_CURRENT: {mav.MAV_RESULT_DENIED},
    mav.MAV_CMD_MISSION_START: {mav.MAV_RESULT_DENIED},
    mav.MAV_CMD_DO_SET_HOME: {mav.MAV_RESULT_DENIED},
    mav.MAV_CMD_DO_REPOSITION: {mav.MAV_RESULT_DENIED, mav.MAV_RESULT_FAILED},
    mav.MAV_CMD_NAV_TAKEOFF: None,  # NaN altitude: TKOFF_ALT
    mav.MAV_CMD_NAV_LAND: None,  # NaN position: straight ahead
    mav.MAV_CMD_NAV_RETURN_TO_LAUNCH: None,
    mav.MAV_CMD_NAV_LOITER_UNLIM: None,
    # the endpoint's own: NaN message id
    mav.MAV_CMD_REQUEST_MESSAGE: {mav.MAV_RESULT_UNSUPPORTED},
    mav.MAV_CMD_SET_MESSAGE_INTERVAL: {mav.MAV_RESULT_UNSUPPORTED},
    mav.MAV_CMD_GET_MESSAGE_INTERVAL: {mav.MAV_RESULT_UNSUPPORTED},
    64999: {mav.MAV_RESULT_UNSUPPORTED},  # no such command (not in the ardupilotmega dialect)
    mav.MAV_CMD_DO_DIGICAM_CONTROL: {mav.MAV_RESULT_UNSUPPORTED},  # one the vehicles have not
}
_RESULTS = set(mav.enums["MAV_RESULT"]) - {mav.MAV_RESULT_ENUM_END}
assert 64999 not in mav.enums["MAV_CMD"]


def _nan_cmd(grp, sysid, command, use_int):
    if use_int:
        return grp.peer.mav.command_int_encode(sysid, 1, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command, 0, 0,
                                               NAN, NAN, NAN, NAN, 0, 0, NAN)
    return grp.peer.mav.command_long_encode(sysid, 1, command, 0, *([NAN] * 7))


@pytest.mark.parametrize("use_int", [False, True])
def test_every_command_with_nan_parameters_gets_one_clear_ack_counted_uav_and_sonde(grp, use_int):
    """Each command with NaN parameters, to a UAV (sysid 1) and to the sonde (sysid 4): exactly one
    COMMAND_ACK of that command with a MAV_RESULT; a refusal counted once (cmd_refused or
    cmd_unsupported); the sonde flies nothing (UNSUPPORTED for every flight command); no handler
    error, no autopilot internal error."""
    ap = grp.g.autopilot
    for sysid in (1, 4):
        ep = grp.ep(sysid)
        for command, want in NAN_COMMANDS.items():
            before = ep.counters["cmd_refused"] + ep.counters["cmd_unsupported"]
            got = grp.exchange(sysid, _nan_cmd(grp, sysid, command, use_int), lambda g: of_type(g, "COMMAND_ACK"))
            grp.step(1)  # nothing more comes
            got += grp.peer.drain(0.005)
            acks = [a for a in of_type(got, "COMMAND_ACK") if a.get_srcSystem() == sysid]
            assert [a.command for a in acks] == [command], (sysid, command, acks)
            res = acks[0].result
            assert res in _RESULTS, (sysid, command, res)
            if sysid == 4 and command not in (mav.MAV_CMD_REQUEST_MESSAGE, mav.MAV_CMD_SET_MESSAGE_INTERVAL,
                                              mav.MAV_CMD_GET_MESSAGE_INTERVAL):
                assert res == mav.MAV_RESULT_UNSUPPORTED, (command, res)
            elif want is not None:
                assert res in want, (sysid, command, res)
            after = ep.counters["cmd_refused"] + ep.counters["cmd_unsupported"]
            assert after == before + (res != mav.MAV_RESULT_ACCEPTED), (sysid, command, res)
            if res not in (mav.MAV_RESULT_ACCEPTED, mav.MAV_RESULT_UNSUPPORTED):
                assert ep.last_error and "\n" not in ep.last_error
        assert ep.counters["handler_errors"] == 0, ep.last_error
    assert ap.counters["internal_error"] == 0, ap.last_reason
    assert grp.heartbeat(1, 3).type == mav.MAV_TYPE_FIXED_WING  # alive and answering


@pytest.mark.parametrize("how", ["set_mode", "do_set_mode"])
def test_modes_that_do_not_exist_or_cannot_be_flown(grp, how):
    """ArduPlane's numbers (pymavlink's table): one it has not -> DENIED with 'No such mode';
    one it has but these fixed-wing UAVs cannot fly (QHOVER) -> FAILED; base_mode without
    CUSTOM_MODE_ENABLED -> DENIED; each counted, the mode unchanged; the sonde has no modes."""
    ep = grp.ep(1)
    custom = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    cases = [(custom, 99, mav.MAV_RESULT_DENIED), (custom, cv.MODES["QHOVER"], mav.MAV_RESULT_FAILED),
             (0, cv.LOITER, mav.MAV_RESULT_DENIED)]
    texts = []
    for sysid in (1, 4):
        for base, mode, code in cases:
            before = grp.ep(sysid).counters["cmd_refused"] + grp.ep(sysid).counters["cmd_unsupported"]
            msg = (grp.peer.mav.set_mode_encode(sysid, base, mode) if how == "set_mode"
                   else grp.cmd(sysid, mav.MAV_CMD_DO_SET_MODE, base, mode))
            got = grp.exchange(sysid, msg, lambda g: of_type(g, "COMMAND_ACK"))
            got += grp.step(2)
            texts += [m.text for m in of_type(got, "STATUSTEXT") if m.get_srcSystem() == sysid]
            acks = [a for a in of_type(got, "COMMAND_ACK") if a.get_srcSystem() == sysid]
            assert [(a.command, a.result) for a in acks] == [
                (mav.MAV_CMD_DO_SET_MODE, code if sysid == 1 else mav.MAV_RESULT_UNSUPPORTED)], (sysid, mode, acks)
            after = grp.ep(sysid).counters["cmd_refused"] + grp.ep(sysid).counters["cmd_unsupported"]
            assert after == before + 1
    assert grp.heartbeat(1, 3).custom_mode == cv.AUTO and grp.g.autopilot.mode[0] == cv.AUTO
    assert "No such mode 99" in texts, texts  # ArduPlane's words
    assert any("QHOVER" in t for t in texts), texts
    assert ep.counters["handler_errors"] == 0


def _upload_until_ack(grp, sysid, items):
    """MISSION_COUNT, then each requested item: (the MISSION_ACK, the seqs requested)."""
    asked = []
    got = grp.exchange(sysid, grp.peer.mav.mission_count_encode(sysid, 1, len(items), 0),
                       lambda g: of_type(g, "MISSION_REQUEST_INT") or of_type(g, "MISSION_ACK"))
    for _ in range(len(items) + 1):
        acks = [a for a in of_type(got, "MISSION_ACK") if a.get_srcSystem() == sysid]
        if acks:
            return acks[0], asked
        req = [r for r in of_type(got, "MISSION_REQUEST_INT") if r.get_srcSystem() == sysid][-1]
        asked.append(req.seq)
        got = grp.exchange(sysid, items[req.seq],
                           lambda g: of_type(g, "MISSION_REQUEST_INT") or of_type(g, "MISSION_ACK"))
    raise AssertionError("upload did not finish")


def _bad_items(peer, lat, lon):
    """(item, its MAV_MISSION_RESULT, the autopilot's counter) -- each as item 2 of a 4-item upload."""
    it = lambda **kw: _item(peer, 2, kw.pop("la", lat + 0.02), kw.pop("lo", lon), kw.pop("alt", 300.0), **kw)
    return [
        (it(cmd=mav.MAV_CMD_DO_DIGICAM_CONTROL, frame=mav.MAV_FRAME_MISSION), mav.MAV_MISSION_UNSUPPORTED,
         "unsupported_item"),
        (it(cmd=mav.MAV_CMD_NAV_SPLINE_WAYPOINT), mav.MAV_MISSION_UNSUPPORTED, "unsupported_item"),
        (it(cmd=mav.MAV_CMD_CONDITION_DELAY, frame=mav.MAV_FRAME_MISSION, p=(5, 0, 0, 0)),
         mav.MAV_MISSION_UNSUPPORTED, "unsupported_item"),
        (it(cmd=mav.MAV_CMD_NAV_VTOL_TAKEOFF), mav.MAV_MISSION_UNSUPPORTED, "unsupported_item"),
        (it(alt=NAN), mav.MAV_MISSION_INVALID_PARAM7, "bad_item"),
        (it(la=95.0), mav.MAV_MISSION_INVALID_PARAM5_X, "bad_item"),
        (it(frame=mav.MAV_FRAME_LOCAL_NED), mav.MAV_MISSION_UNSUPPORTED_FRAME, "bad_item"),
        (it(cmd=mav.MAV_CMD_NAV_LOITER_TURNS, p=(NAN, 0, 0, 0)), mav.MAV_MISSION_INVALID_PARAM1, "bad_item"),
        (it(cmd=mav.MAV_CMD_DO_JUMP, p=(9, 1, 0, 0), frame=mav.MAV_FRAME_MISSION), mav.MAV_MISSION_INVALID_PARAM1,
         "bad_item"),
    ]


def test_mission_items_refused_at_the_item_with_their_code_counted_old_plan_kept(grp):
    """Any item the UAVs cannot fly (not NAV_WAYPOINT, NAV_LOITER_*, NAV_RETURN_TO_LAUNCH,
    NAV_TAKEOFF, NAV_LAND, DO_JUMP, DO_CHANGE_SPEED): MISSION_ACK MAV_MISSION_UNSUPPORTED as it
    arrives (item 3 is never asked for); a bad field: its MAV_MISSION_INVALID_* / frame code; each
    counted (the endpoint's mission_rejected, the autopilot's counter), said in a STATUSTEXT that
    names the item, and the plan before it stays; the sonde takes no mission at all."""
    lat, lon, h = _pos(grp, 1)
    ep, ap = grp.ep(1), grp.g.autopilot
    home = _item(grp.peer, 0, lat, lon, 0.0, frame=mav.MAV_FRAME_GLOBAL_INT)
    good = [home, _item(grp.peer, 1, lat + 0.01, lon, 300.0), _item(grp.peer, 2, lat + 0.02, lon, 300.0)]
    assert upload(grp, 1, good) == mav.MAV_MISSION_ACCEPTED
    for bad, code, counter in _bad_items(grp.peer, lat, lon):
        before, before_ap = ep.counters["mission_rejected"], ap.counters[counter]
        items = [home, good[1], bad, _item(grp.peer, 3, lat + 0.03, lon, 300.0)]
        ack, asked = _upload_until_ack(grp, 1, items)
        assert (ack.type, asked) == (code, [0, 1, 2]), (bad, ack, asked)
        assert ep.counters["mission_rejected"] == before + 1 and ap.counters[counter] == before_ap + 1, bad
        assert ep.last_error.startswith("mission: item 2"), ep.last_error
        texts = [m.text for m in of_type(grp.step(1), "STATUSTEXT") if m.get_srcSystem() == 1]
        texts += [m.text for m in of_type(grp.peer.drain(0.005), "STATUSTEXT") if m.get_srcSystem() == 1]
        got = grp.exchange(1, grp.peer.mav.mission_request_list_encode(1, 1, 0), lambda g: of_type(g, "MISSION_COUNT"))
        assert of_type(got, "MISSION_COUNT")[0].count == 3  # the good plan
        assert ap.m_count[0] == 3
    assert ep.counters["handler_errors"] == 0 and ap.counters["internal_error"] == 0
    # the sonde: MAV_MISSION_UNSUPPORTED at the count, counted; it downloads zero items
    before = grp.ep(4).counters["mission_rejected"]
    ack, asked = _upload_until_ack(grp, 4, [_item(grp.peer, k, lat, lon, 300.0, sysid=4) for k in range(2)])
    assert (ack.type, asked) == (mav.MAV_MISSION_UNSUPPORTED, [])
    assert grp.ep(4).counters["mission_rejected"] == before + 1
    got = grp.exchange(4, grp.peer.mav.mission_request_list_encode(4, 1, 0), lambda g: of_type(g, "MISSION_COUNT"))
    assert of_type(got, "MISSION_COUNT")[0].count == 0


def _dedup(seq):
    return [v for k, v in enumerate(seq) if k == 0 or v != seq[k - 1]]


@pytest.mark.slow
def test_every_flyable_item_kind_flown_over_mavlink(tmp_path):
    """Uploaded by pymavlink with home at item 0: WP, LOITER_TURNS, DO_CHANGE_SPEED, LOITER_TIME,
    DO_JUMP (-> 1, once), LOITER_TO_ALT, NAV_RETURN_TO_LAUNCH; MISSION_ITEM_REACHED per ArduPlane's
    rules (every navigation item when complete, the DO item when run, not DO_JUMP; items 1..4 twice),
    MISSION_CURRENT following it, then RTL (HEARTBEAT) at the RTL item."""
    grp = Group(tmp_path, count=1, sonde=False)
    try:
        la, lo, _h = _pos(grp, 1)
        pts = [(la + 0.03, lo), (la + 0.06, lo + 0.03), (la + 0.03, lo + 0.06), (la, lo + 0.03)]
        P, NOF = _item, mav.MAV_FRAME_MISSION
        items = [P(grp.peer, 0, la, lo, 0.0, frame=mav.MAV_FRAME_GLOBAL_INT),
                 P(grp.peer, 1, *pts[0], 300.0),
                 P(grp.peer, 2, *pts[1], 300.0, cmd=mav.MAV_CMD_NAV_LOITER_TURNS, p=(1, 0, 1000, 0)),
                 P(grp.peer, 3, 0, 0, 0, cmd=mav.MAV_CMD_DO_CHANGE_SPEED, frame=NOF, p=(0, 80, -1, 0)),
                 P(grp.peer, 4, *pts[2], 300.0, cmd=mav.MAV_CMD_NAV_LOITER_TIME, p=(60, 0, 800, 0)),
                 P(grp.peer, 5, 0, 0, 0, cmd=mav.MAV_CMD_DO_JUMP, frame=NOF, p=(1, 1, 0, 0)),
                 P(grp.peer, 6, *pts[3], 500.0, cmd=mav.MAV_CMD_NAV_LOITER_TO_ALT, p=(0, 900, 0, 0)),
                 P(grp.peer, 7, 0, 0, 0, cmd=mav.MAV_CMD_NAV_RETURN_TO_LAUNCH, frame=NOF)]
        assert upload(grp, 1, items) == mav.MAV_MISSION_ACCEPTED
        reached, current, modes, texts = [], [], [], []
        for _ in range(1200):  # <= 12000 epochs (the default scenario's 1 Hz)
            got = [m for m in grp.step(10) if m.get_srcSystem() == 1]
            reached += [m.seq for m in of_type(got, "MISSION_ITEM_REACHED")]
            current += [m.seq for m in of_type(got, "MISSION_CURRENT")]
            modes += [m.custom_mode for m in of_type(got, "HEARTBEAT")]
            texts += [m.text for m in of_type(got, "STATUSTEXT")]
            if modes and modes[-1] == cv.RTL:
                break
        assert reached == [1, 2, 3, 4, 1, 2, 3, 4, 6], reached
        assert _dedup(current) == [1, 2, 4, 1, 2, 4, 6, 7], _dedup(current)
        assert modes[-1] == cv.RTL and "Mission: RTL" in texts and "Set airspeed 80 m/s" in texts
        assert grp.ep(1).counters["handler_errors"] == 0
    finally:
        grp.close()


@pytest.mark.slow
def test_takeoff_and_land_items_flown_over_mavlink_from_the_ground(tmp_path):
    """A ground start: home, NAV_TAKEOFF (100 m), a waypoint, NAV_LAND at a point; armed and AUTO
    by pymavlink: it rolls, climbs, flies, lands there (MISSION_ITEM_REACHED 1, 2, 3), then disarms
    after LAND_DISARMDELAY (HEARTBEAT: not armed, STANDBY)."""
    grp = Group(tmp_path, start="ground", count=1, sonde=False)
    try:
        ap = grp.g.autopilot
        la, lo, h0 = _pos(grp, 1)
        land = (la + 0.03, lo + 0.03)
        items = [_item(grp.peer, 0, la, lo, 0.0, frame=mav.MAV_FRAME_GLOBAL_INT),
                 _item(grp.peer, 1, 0, 0, 100.0, cmd=mav.MAV_CMD_NAV_TAKEOFF, p=(10, 0, 0, 0)),
                 _item(grp.peer, 2, la + 0.05, lo, 100.0),
                 _item(grp.peer, 3, *land, 0.0, cmd=mav.MAV_CMD_NAV_LAND)]
        assert upload(grp, 1, items) == mav.MAV_MISSION_ACCEPTED
        assert grp.ack(1, grp.cmd(1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 1))[1] == mav.MAV_RESULT_ACCEPTED
        assert grp.ack(1, grp.peer.mav.set_mode_encode(1, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, cv.AUTO))[1] == \
            mav.MAV_RESULT_ACCEPTED
        reached, texts, hbs, top = [], [], [], h0
        for _ in range(1500):  # <= 15000 epochs (the default scenario's 1 Hz)
            got = [m for m in grp.step(10) if m.get_srcSystem() == 1]
            reached += [m.seq for m in of_type(got, "MISSION_ITEM_REACHED")]
            texts += [m.text for m in of_type(got, "STATUSTEXT")]
            hbs += of_type(got, "HEARTBEAT")
            top = max(top, ap.pos[0, 2])
            if hbs and not hbs[-1].base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED and "Landed" in texts:
                break
        assert reached == [1, 2, 3], reached
        assert top >= h0 + 100.0 - 2.0  # TAKEOFF to 100 m (ArduPlane: complete 2 m below)
        assert "Touchdown" in texts and "Landed" in texts and "Disarming motors" in texts
        hb = hbs[-1]
        assert not hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED and hb.system_status == mav.MAV_STATE_STANDBY
        assert abs(ap.pos[0, 2] - h0) < 1.0
        from sitl import geodesy
        enu = geodesy.ecef_to_enu(geodesy.geodetic_to_ecef(*ap.pos[0]), math.radians(land[0]), math.radians(land[1]),
                                  0.0)
        # on the ground past the landing point: the flare and roll-out (a few hundred metres)
        assert math.hypot(enu[0], enu[1]) < 2000.0, enu
    finally:
        grp.close()
