"""The ground station as a MAVLink component (issue 21): its HEARTBEAT, signed output a GCS with
the key accepts and one with another key refuses, ADSB_VEHICLE + UTM_GLOBAL_POSITION whose
uncertainty matches the estimate's covariance computed independently, STATUSTEXT for integrity
events (severity, rate limit, chunks), bad input counted and never raised, and MAVSDK seeing the
component connected."""
from __future__ import annotations

import math
import select
import socket
import time
from types import SimpleNamespace

import numpy as np
import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as m

from ground_station.mavlink_link import (GS_COMPID, GS_SYSID, INTEGRITY_SEVERITY, GcsLink, uncertainty_1sigma,
                                         unix_us_from_gps)
from sitl.bus.schema import Estimate, IntegrityEvent, LinkStats
from sitl.geodesy import ecef_to_geodetic, enu_to_ecef, geodetic_to_ecef

pytestmark = pytest.mark.live  # UDP on loopback

KEY = bytes(range(1, 33))
WALL0 = 1_780_000_000.0
T0 = 1_400_000_000.0  # GPS seconds (2024)
LAT, LON, H = math.radians(45.2), math.radians(30.1), 1500.0


class Clock:
    def __init__(self, now: float = WALL0):
        self.now = now

    def __call__(self) -> float:
        return self.now


class Rx:
    """A pymavlink GCS on loopback (key None: no signature check; else required)."""

    def __init__(self, key: bytes | None = None):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.mav = m.MAVLink(None)
        if key is not None:
            self.mav.signing.secret_key = key
            self.mav.signing.allow_unsigned_callback = lambda mav, msgid: False
        self.raw: list[bytes] = []
        self.refused = 0

    @property
    def addr(self) -> str:
        return "127.0.0.1:%d" % self.sock.getsockname()[1]

    def drain(self, wait_s: float = 0.3) -> list:
        out = []
        while True:
            r, _, _ = select.select([self.sock], [], [], wait_s)
            if not r:
                return out
            d = self.sock.recv(65535)
            self.raw.append(d)
            try:
                out += [x for x in (self.mav.parse_buffer(d) or []) if x.get_type() != "BAD_DATA"]
            except m.MAVError:
                self.refused += 1

    def close(self):
        self.sock.close()


def _ecef_cov(C_enu_pos, C_enu_vel, lat=LAT, lon=LON, h=H):
    """A 6 x 6 ECEF covariance from ENU blocks, the ENU axes taken from sitl.geodesy's
    enu_to_ecef (tested against pymap3d), not from the rotation the link uses."""
    o = enu_to_ecef(np.zeros(3), lat, lon, h)
    B = np.stack([enu_to_ecef(e, lat, lon, h) - o for e in np.eye(3)], axis=1)  # columns: E, N, U in ECEF
    P = np.zeros((6, 6))
    P[:3, :3] = B @ C_enu_pos @ B.T
    P[3:, 3:] = B @ C_enu_vel @ B.T
    return P


def _estimate(cov, pos=None, vel=(12.0, -3.0, 1.5), t=T0 + 10.0, kind="sonde"):
    pos = geodetic_to_ecef(LAT, LON, H) if pos is None else np.asarray(pos, float)
    return Estimate(t_gps_s=t, source_id="gs", seq=0, kind=kind, pos_ecef_m=np.asarray(pos, float),
                    vel_ecef_m_s=np.asarray(vel, float), cov=cov, nis=1.0, mode="fused")


# ---------------------------------------------------------------------------- heartbeat
def test_heartbeat_once_per_simulated_second_as_a_gcs_type_non_autopilot():
    rx = Rx()
    g = GcsLink(rx.addr, clock=Clock())
    try:
        for k in range(101):  # 10 s of 0.1 s ticks (the worker's paced loop)
            g.tick(T0 + 0.1 * k)
        g.tick(T0 + 10.05)
        hb = [x for x in rx.drain() if x.get_type() == "HEARTBEAT"]
        assert len(hb) == 11  # t0, t0 + 1, ..., t0 + 10
        x = hb[0]
        assert (x.get_srcSystem(), x.get_srcComponent()) == (GS_SYSID, m.MAV_COMP_ID_ONBOARD_COMPUTER) == (250, GS_COMPID)
        assert (x.type, x.autopilot, x.base_mode, x.custom_mode) == (m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0)
        assert x.system_status == m.MAV_STATE_ACTIVE and x.mavlink_version == 3
        # pymavlink's own test: not a vehicle heartbeat (so mavutil never targets system 250)
        conn = mavutil.mavlink_connection("udpin:127.0.0.1:0")
        try:
            assert not conn.probably_vehicle_heartbeat(x)
        finally:
            conn.close()
    finally:
        g.close()
        rx.close()


def test_heartbeat_after_a_stall_resumes_without_a_burst_and_ignores_bad_times():
    rx = Rx()
    g = GcsLink(rx.addr, clock=Clock())
    try:
        g.tick(T0)
        g.tick(T0 + 30.0)  # the worker stalled 30 s: one heartbeat, not 30
        g.tick(T0 + 30.5)
        g.tick(math.nan)
        g.tick("later")
        g.tick(T0 + 31.0)
        assert [x.get_type() for x in rx.drain()] == ["HEARTBEAT"] * 3
        assert g.text_skipped["bad_time"] == 2 and "\n" not in g.last_reason
    finally:
        g.close()
        rx.close()


# ---------------------------------------------------------------------------- signing
def _one_of_each(g: GcsLink):
    g.tick(T0)
    cov = _ecef_cov(np.diag([25.0, 4.0, 9.0]), np.diag([0.04, 0.04, 0.01]))
    g.adsb("sonde", "s0000", _estimate(cov))
    g.integrity_event(IntegrityEvent(t_gps_s=T0, source_id="gs", seq=0, channel="s0000.relay.G07",
                                     event="step", statistic=7.25))


def test_signed_output_accepted_with_the_key_refused_with_another():
    good, wrong, nokey = Rx(KEY), Rx(bytes(32)), Rx()
    clock = Clock()
    links = [GcsLink(r.addr, signing_key=KEY, clock=clock) for r in (good, wrong, nokey)]
    try:
        for g in links:
            _one_of_each(g)
        got = good.drain()
        assert [x.get_type() for x in got] == ["HEARTBEAT", "ADSB_VEHICLE", "UTM_GLOBAL_POSITION", "STATUSTEXT"]
        assert all(x._signed and x._link_id == 0 for x in got)
        assert good.mav.signing.goodsig_count == 4 and good.mav.signing.badsig_count == 0
        assert wrong.drain() == [] and len(wrong.raw) == 4 and wrong.refused == 4
        assert wrong.mav.signing.badsig_count == 4 and wrong.mav.signing.goodsig_count == 0
        # the frames carry the signature (a GCS without signing still reads them: MAVSDK, MAVProxy)
        assert len(nokey.drain()) == 4 and all(b[2] & 0x01 for b in nokey.raw)
        ts = [int.from_bytes(b[-12:-6], "little") for b in good.raw]
        assert ts == sorted(set(ts)) and ts[0] == int((WALL0 - 1_420_070_400.0) * 100_000)
    finally:
        for x in (*links, good, wrong, nokey):
            x.close()


def test_signing_state_keeps_timestamps_rising_when_the_clock_steps_back_across_a_restart(tmp_path):
    rx = Rx(KEY)
    state = tmp_path / "mav_signing_250.json"
    clock = Clock()
    try:
        g = GcsLink(rx.addr, signing_key=KEY, clock=clock, signing_state=state)
        for k in range(5):
            g.tick(T0 + k)
            clock.now += 1.0
        g.close()
        assert state.exists() and g.signing.saves >= 1
        clock.now -= 3600.0  # the wall clock went back an hour before the restart
        g = GcsLink(rx.addr, signing_key=KEY, clock=clock, signing_state=state)
        g.tick(T0 + 100)
        g.close()
        got = rx.drain()
        assert len(got) == 6 and rx.mav.signing.badsig_count == 0
        ts = [int.from_bytes(b[-12:-6], "little") for b in rx.raw]
        assert all(b > a for a, b in zip(ts, ts[1:]))
        import json
        d = json.loads(state.read_text())
        assert d["sysid"] == 250 and d["reserved"] > ts[4] and ts[5] > d["reserved"] - 500_000 * 2
    finally:
        rx.close()


# ---------------------------------------------------------------------------- ADSB + uncertainty
def test_adsb_and_utm_uncertainty_match_the_covariance_computed_independently():
    # a 1-sigma ellipse of 40 m x 6 m with its long axis 30 deg east of north, 15 m vertical;
    # velocity sigmas 0.3 / 0.5 / 2.0 m/s on rotated axes
    th = math.radians(30.0)
    Rh = np.array([[math.sin(th), math.cos(th)], [math.cos(th), -math.sin(th)]])  # columns: long, short (E, N)
    C = np.zeros((3, 3))
    C[:2, :2] = Rh @ np.diag([40.0**2, 6.0**2]) @ Rh.T
    C[2, 2] = 15.0**2
    Q = np.linalg.qr(np.array([[1.0, 0.2, 0.1], [0.3, 1.0, 0.4], [0.2, 0.5, 1.0]]))[0]
    Cv = Q @ np.diag([0.3**2, 0.5**2, 2.0**2]) @ Q.T
    P = _ecef_cov(C, Cv)
    vel_enu = np.array([12.0, -3.0, 1.5])
    vel_ecef = enu_to_ecef(vel_enu, LAT, LON, H) - enu_to_ecef(np.zeros(3), LAT, LON, H)
    est = _estimate(P, vel=vel_ecef)
    rx = Rx()
    g = GcsLink(rx.addr, clock=Clock())
    try:
        g.adsb("sonde", "s0000", est)
        adsb, utm = rx.drain()
        assert (adsb.get_type(), utm.get_type()) == ("ADSB_VEHICLE", "UTM_GLOBAL_POSITION")
        # independent figures: numpy eig of the ENU blocks we built
        h_sigma_m = math.sqrt(max(np.linalg.eig(C[:2, :2])[0].real))
        v_sigma_m = math.sqrt(C[2, 2])
        speed_sigma_m_s = math.sqrt(max(np.linalg.eig(Cv)[0].real))
        assert h_sigma_m == pytest.approx(40.0) and speed_sigma_m_s == pytest.approx(2.0)
        assert utm.h_acc == round(h_sigma_m * 1e3) == 40_000
        assert utm.v_acc == round(v_sigma_m * 1e3) == 15_000
        assert utm.vel_acc == round(speed_sigma_m_s * 1e2) == 200
        assert bytes(utm.uas_id).rstrip(b"\0") == adsb.callsign.encode() == b"SONs0000"
        lat, lon, h = ecef_to_geodetic(est.pos_ecef_m)
        for x in (adsb, utm):
            assert x.lat == round(math.degrees(lat) * 1e7) and x.lon == round(math.degrees(lon) * 1e7)
        assert adsb.altitude == utm.alt == round(H * 1e3)
        assert utm.time == unix_us_from_gps(T0 + 10.0) == round((T0 + 10.0 - 18 + 315_964_800) * 1e6)
        assert (utm.vx, utm.vy, utm.vz) == (-300, 1200, -150)  # north, east, down cm/s
        assert adsb.hor_velocity == round(math.hypot(12.0, 3.0) * 100) and adsb.ver_velocity == 150
        assert adsb.emitter_type == m.ADSB_EMITTER_TYPE_LIGHTER_AIR and adsb.altitude_type == m.ADSB_ALTITUDE_TYPE_GEOMETRIC
        want = (m.UTM_DATA_AVAIL_FLAGS_TIME_VALID | m.UTM_DATA_AVAIL_FLAGS_UAS_ID_AVAILABLE
                | m.UTM_DATA_AVAIL_FLAGS_POSITION_AVAILABLE | m.UTM_DATA_AVAIL_FLAGS_ALTITUDE_AVAILABLE
                | m.UTM_DATA_AVAIL_FLAGS_HORIZONTAL_VELO_AVAILABLE | m.UTM_DATA_AVAIL_FLAGS_VERTICAL_VELO_AVAILABLE)
        assert utm.flags == want
        assert not g.skipped and not g.uncertainty_skipped and not g.uncertainty_clamped
    finally:
        g.close()
        rx.close()


def test_every_estimated_object_gets_its_own_adsb_and_uncertainty():
    rx = Rx()
    g = GcsLink(rx.addr, clock=Clock())
    cov = _ecef_cov(np.diag([100.0, 100.0, 400.0]), np.eye(3))
    try:
        for kind, tid in (("beacon", "b1"), ("sonde", "s0000"), ("sonde", "s0001")):
            g.adsb(kind, tid, _estimate(cov, kind=kind))
        got = rx.drain()
        adsb = [x for x in got if x.get_type() == "ADSB_VEHICLE"]
        utm = [x for x in got if x.get_type() == "UTM_GLOBAL_POSITION"]
        assert [x.callsign for x in adsb] == ["BEAb1", "SONs0000", "SONs0001"]
        assert len({x.ICAO_address for x in adsb}) == 3
        # outside MAVProxy's synthetic-obstacle ICAO bands (it then draws the emitter type sent)
        assert all(0x004000 <= x.ICAO_address < 0xA00000 for x in adsb)
        assert [bytes(x.uas_id).rstrip(b"\0").decode() for x in utm] == [x.callsign for x in adsb]
        assert {x.h_acc for x in utm} == {10_000} and {x.v_acc for x in utm} == {20_000}
        assert adsb[0].emitter_type == m.ADSB_EMITTER_TYPE_UAV
    finally:
        g.close()
        rx.close()


def test_uncertainty_1sigma_is_the_semi_major_axis_not_drms_or_cep():
    P = _ecef_cov(np.diag([9.0, 16.0, 1.0]), np.diag([1.0, 4.0, 0.25]))
    h, v, s = uncertainty_1sigma(LAT, LON, P)
    assert (h, v, s) == pytest.approx((4.0, 1.0, 2.0))


BAD_COV = [
    ("NaN", np.full((6, 6), np.nan), "invalid_covariance", {}),
    ("inf", np.diag([np.inf, 1, 1, 1, 1, 1.0]), "invalid_covariance", {}),
    ("5 x 5", np.eye(5), "invalid_covariance", {}),
    ("negative variance", np.diag([-4.0, 1, 1, 1, 1, 1]), "invalid_covariance", {}),
    ("asymmetric", np.eye(6) + np.triu(np.ones((6, 6)), 1), "invalid_covariance", {}),
    ("text", "abc", "invalid_covariance", {}),
    ("huge", np.eye(6) * 1e12, None, {"h_acc": 1, "v_acc": 1, "vel_acc": 1}),
]


@pytest.mark.parametrize("name, cov, skipped, clamped", BAD_COV, ids=[b[0] for b in BAD_COV])
def test_a_bad_covariance_never_raises_the_adsb_still_goes(name, cov, skipped, clamped):
    rx = Rx()
    g = GcsLink(rx.addr, clock=Clock())
    est = SimpleNamespace(pos_ecef_m=geodetic_to_ecef(LAT, LON, H), vel_ecef_m_s=np.zeros(3), cov=cov, t_gps_s=T0)
    try:
        g.adsb("beacon", "b1", est)
        got = rx.drain()
        assert got[0].get_type() == "ADSB_VEHICLE" and g.sent["ADSB_VEHICLE"] == 1
        if skipped:
            assert len(got) == 1 and dict(g.uncertainty_skipped) == {skipped: 1}
            assert g.last_reason.startswith("UTM_GLOBAL_POSITION BEAb1 not sent: covariance") and "\n" not in g.last_reason
        else:
            (utm,) = got[1:]
            assert (utm.h_acc, utm.v_acc, utm.vel_acc) == (65535, 65535, 65535)
            assert dict(g.uncertainty_clamped) == clamped
    finally:
        g.close()
        rx.close()


def test_unknown_kinds_and_nan_estimates_are_counted_with_a_one_line_reason():
    g = GcsLink("127.0.0.1:9", clock=Clock())
    frames = []
    g.write = frames.append
    try:
        g.adsb("uav", "3", _estimate(np.eye(6), kind="uav"))
        assert g.skipped == {"unknown_kind": 1} and "unknown kind 'uav'" in g.last_reason
        g.adsb("beacon", "b1", SimpleNamespace(pos_ecef_m=[math.nan] * 3, vel_ecef_m_s=[0, 0, 0], cov=np.eye(6)))
        g.adsb("beacon", "b1", object())
        g.adsb("sonde", "s0", SimpleNamespace(pos_ecef_m=geodetic_to_ecef(LAT, LON, H), vel_ecef_m_s=[0, 0, 0]))
        assert g.skipped == {"unknown_kind": 1, "non_finite_position": 1, "invalid:AttributeError": 1}
        assert g.uncertainty_skipped == {"no_covariance": 1}
        assert [m.MAVLink(None).parse_char(f).get_type() for f in frames] == ["ADSB_VEHICLE"]
        assert set(g.status()) >= {"sent", "skipped", "uncertainty_skipped", "text_skipped", "last_reason"}
    finally:
        g.close()


# ---------------------------------------------------------------------------- STATUSTEXT
def _ev(event="step", channel="uav3.G12", stat=5.213, seq=0):
    return IntegrityEvent(t_gps_s=T0, source_id="gs", seq=seq, channel=channel, event=event, statistic=stat)


def test_integrity_events_as_statustext_with_severity_by_kind():
    rx = Rx()
    g = GcsLink(rx.addr, clock=Clock(), text_burst=10)
    try:
        g.tick(T0)
        rx.drain()
        for kind in ("step", "ramp", "outlier", "readmit"):
            g.integrity_event(_ev(kind, stat=math.nan if kind == "readmit" else 5.213))
        g.link_change(LinkStats(t_gps_s=T0, source_id="gs", seq=0, link="uav2", received=10, missing=0,
                                duplicates=0, out_of_order=0, gaps=0, stale=True, latency_mean_s=0.1,
                                latency_max_s=0.2, last_t_gps_s=T0))
        got = rx.drain()
        assert [(x.severity, x.text) for x in got] == [
            (m.MAV_SEVERITY_WARNING, "integrity step uav3.G12 5.21"),
            (m.MAV_SEVERITY_WARNING, "integrity ramp uav3.G12 5.21"),
            (m.MAV_SEVERITY_NOTICE, "integrity outlier uav3.G12 5.21"),
            (m.MAV_SEVERITY_INFO, "integrity readmit uav3.G12"),
            (m.MAV_SEVERITY_WARNING, "link uav2: stale")]
        assert INTEGRITY_SEVERITY.keys() == {"step", "ramp", "outlier", "readmit"}
        assert all(len(x.text) <= 50 and x.id == 0 for x in got)
        g.integrity_event(SimpleNamespace(event="wobble", channel="uav1.G01", statistic=1.0))
        g.integrity_event(None)
        (x,) = rx.drain()
        assert x.severity == m.MAV_SEVERITY_NOTICE and x.text == "integrity wobble uav1.G01 1"
        assert g.text_skipped == {"unknown_event_kind": 1, "invalid:AttributeError": 1}
    finally:
        g.close()
        rx.close()


def test_statustext_is_rate_limited_in_simulated_time_and_the_held_back_are_summed_up():
    rx = Rx()
    g = GcsLink(rx.addr, clock=Clock())  # 5 at once, then 1 per simulated second, per bucket
    try:
        g.tick(T0)
        rx.drain()
        for k in range(20):
            g.integrity_event(_ev("outlier", seq=k))
        g.integrity_event(_ev("step"))  # the WARNING bucket is not drained by the outliers
        got = rx.drain()
        assert [x.text.split()[1] for x in got] == ["outlier"] * 5 + ["step"]
        assert g.text_skipped["rate"] == 15
        g.tick(T0 + 0.5)
        assert [x.get_type() for x in rx.drain()] == []  # no token yet (all 5 spent, 0.5 back)
        g.tick(T0 + 1.0)
        got = [x for x in rx.drain() if x.get_type() == "STATUSTEXT"]
        assert [(x.severity, x.text) for x in got] == [(m.MAV_SEVERITY_NOTICE, "gs: 15 held back (outlier:15)")]
    finally:
        g.close()
        rx.close()


def test_a_long_text_goes_in_chunks_with_an_id_and_chunk_seq():
    rx = Rx()
    g = GcsLink(rx.addr, clock=Clock())
    channel = "s0001.relay." + "G" * 52  # the longest bus token: 64 chars
    try:
        g.integrity_event(_ev("step", channel=channel, stat=12.5))
        g.statustext("x" * 100, m.MAV_SEVERITY_INFO)  # exactly 2 x 50: an empty chunk ends it
        got = rx.drain()
        a, b = got[:2], got[2:]
        assert {x.id for x in a} == {1} and [x.chunk_seq for x in a] == [0, 1]
        assert len(a[0].text) == 50 and len(a[1].text) < 50
        assert "".join(x.text for x in a) == f"integrity step {channel} 12.5"
        assert {x.id for x in b} == {2} and [x.chunk_seq for x in b] == [0, 1, 2] and b[2].text == ""
    finally:
        g.close()
        rx.close()


# ---------------------------------------------------------------------------- MAVSDK
def _mavsdk():
    try:
        import mavsdk
        from mavsdk import ComponentType, Configuration, Mavsdk
        return Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION)), mavsdk
    except Exception as e:  # no wheel, or its libcmavsdk cannot load here
        pytest.skip(f"MAVSDK's core (mavsdk wheel, libcmavsdk.so) cannot start: {type(e).__name__}: {e}")


@pytest.mark.slow
@pytest.mark.parametrize("signed", [False, True], ids=["unsigned", "signed"])
def test_mavsdk_sees_the_ground_station_connected_once_it_heartbeats(signed):
    """MAVSDK 4.1 (its C++ core in-process): ADSB_VEHICLE alone makes system 250 known but not
    connected (what issue 21 saw); the HEARTBEAT connects it, as a standalone component (no
    autopilot). Bounded: 20 s."""
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    d, mavsdk = _mavsdk()
    g = None
    try:
        res = d.add_any_connection(f"udpin://127.0.0.1:{port}")
        assert res == mavsdk.ConnectionResult.SUCCESS, res
        g = GcsLink(f"127.0.0.1:{port}", signing_key=KEY if signed else None)
        cov = _ecef_cov(np.eye(3) * 25.0, np.eye(3))
        deadline = time.monotonic() + 20.0
        systems = []
        while time.monotonic() < deadline and not systems:
            g.adsb("sonde", "s0000", _estimate(cov))
            time.sleep(0.1)
            systems = [s for s in d.get_systems() if s.get_system_id() == GS_SYSID]
        assert systems, "MAVSDK never saw system 250"
        assert not systems[0].is_connected()
        t = T0
        while time.monotonic() < deadline and not systems[0].is_connected():
            g.tick(t)
            t += 0.5
            time.sleep(0.1)
        s = systems[0]
        assert s.is_connected(), "no connection within 20 s"
        assert not s.has_autopilot() and s.is_standalone() and s.component_ids() == [GS_COMPID]
    finally:
        if g is not None:
            g.close()
        d.destroy()


def test_standby_heartbeats_while_the_worker_waits_then_the_thread_is_gone():
    from ground_station.process import _standby_heartbeats
    rx = Rx()
    g = GcsLink(rx.addr, clock=Clock())
    try:
        stop = _standby_heartbeats(g, period_wall_s=0.1)
        time.sleep(0.35)
        stop()
        n = len(rx.drain())
        g.tick(T0)  # the main loop's, ACTIVE
        got = rx.drain()
        assert n >= 2 and [x.system_status for x in got] == [m.MAV_STATE_ACTIVE]
        import threading
        assert not [t for t in threading.enumerate() if t.name == "gs-standby-heartbeat"]
    finally:
        g.close()
        rx.close()


# ---------------------------------------------------------------------------- MAVProxy
def _tlog_heartbeats(path, sysid) -> int:
    """HEARTBEATs from ``sysid`` in a tlog (one still being written: a cut last record ends it)."""
    if not path.exists():
        return 0
    tl = mavutil.mavlink_connection(str(path))
    hb = 0
    try:
        while (x := tl.recv_match(type="HEARTBEAT")) is not None:
            hb += x.get_srcSystem() == sysid
    finally:
        tl.close()
    return hb


def _mavproxy(tmp_path, mav_type, monkeypatch, seconds=6.0, give_up_s=60.0):
    """MAVProxy 1.8.75 headless on udpin, the GS heartbeating (and sending a track) to it: its
    output and the HEARTBEATs from system 250 in its own tlog (proof it heard them).

    Runs ``seconds`` at least, then until MAVProxy's tlog holds 3 of the GS's HEARTBEATs (on a
    loaded machine MAVProxy's start-up alone can take longer than ``seconds``), ``give_up_s``
    at most."""
    import subprocess
    import sys

    import ground_station.mavlink_link as ml
    pytest.importorskip("MAVProxy")
    monkeypatch.setattr(ml, "GS_MAV_TYPE", mav_type)
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    p = subprocess.Popen([sys.executable, "-m", "MAVProxy.mavproxy", f"--master=udpin:127.0.0.1:{port}",
                          "--non-interactive", "--default-modules=link,adsb,console", f"--state-basedir={tmp_path}",
                          "--cmd=set heartbeat 0"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                         cwd=tmp_path)
    g = GcsLink(f"127.0.0.1:{port}", clock=Clock())
    cov = _ecef_cov(np.eye(3) * 25.0, np.eye(3))
    tlog = tmp_path / "mav.tlog"
    try:
        t, t0 = T0, time.monotonic()
        while time.monotonic() < t0 + give_up_s:
            g.tick(t)
            g.adsb("sonde", "s0000", _estimate(cov))
            t += 0.5
            time.sleep(0.25)
            if time.monotonic() > t0 + seconds and _tlog_heartbeats(tlog, GS_SYSID) >= 3:
                break
    finally:
        g.close()
        p.terminate()
        out = p.communicate(timeout=20)[0]
    return out, _tlog_heartbeats(tlog, GS_SYSID)


@pytest.mark.slow
def test_mavproxy_hears_the_ground_station_and_does_not_list_it_as_a_vehicle(tmp_path, monkeypatch):
    out, hb = _mavproxy(tmp_path, m.MAV_TYPE_GCS, monkeypatch)
    assert hb >= 3, out[-2000:]
    assert "Detected vehicle 250" not in out and "online system 250" not in out, out[-2000:]


@pytest.mark.slow
def test_mavproxy_would_list_an_onboard_controller_type_as_a_vehicle(tmp_path, monkeypatch):
    """The control for the test above: the one other candidate type is listed."""
    out, hb = _mavproxy(tmp_path, m.MAV_TYPE_ONBOARD_CONTROLLER, monkeypatch)
    assert hb >= 3 and "Detected vehicle 250:191" in out and "online system 250" not in out, out[-2000:]
