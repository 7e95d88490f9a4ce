"""The telemetry a GCS needs, fed from the simulation's own state (issue 21), with pymavlink as the
GCS on loopback: the vehicle worker's VehicleGroup + build_endpoints stepped in simulated time.

References: analytic DOPs of a symmetric constellation, pymap3d's rotations and look angles (an
independent implementation), the truth of the run (the estimate's accuracy against its real
error), the battery's analytic charge, the autopilot's flight phase, and the statistics a
consistent filter must show (E[test ratio] = 1 / gate^2)."""
from __future__ import annotations

import math
import select

import numpy as np
import pymap3d
import pytest
from pymap3d.vincenty import vdist
from pymavlink.dialects.v20 import ardupilotmega as mav
from tests.mavlink_peer import Peer, of_type

from sitl.bus import InMemoryTransport
from sitl.scenario import default_scenario
from vehicles import uav_nav
from vehicles.autopilot import convention as cv
from tests.procs import udp_base
from vehicles.process import VehicleGroup, _mav_telemetry, build_endpoints


# ---------------------------------------------------------------------- pure: DOP, NED covariance


def _sat_at(rx_lat, rx_lon, rx_h, az, el, rng_m=2.0e7):
    x, y, z = pymap3d.aer2ecef(math.degrees(az), math.degrees(el), rng_m, math.degrees(rx_lat), math.degrees(rx_lon),
                               rx_h)
    return np.array([x, y, z])


@pytest.mark.parametrize("el_deg", [20.0, 45.0, 70.0])
def test_clock_free_dops_of_a_symmetric_constellation_match_the_analytic_values(el_deg):
    """Three satellites at azimuths 0 / 120 / 240 deg and one elevation e: G'G = diag(1.5 cos^2 e,
    1.5 cos^2 e, 3 sin^2 e), so HDOP = sqrt(4 / (3 cos^2 e)) and VDOP = 1 / (sqrt(3) sin e)."""
    lat, lon, h = math.radians(45.0), math.radians(30.0), 2000.0
    rx = np.array(pymap3d.geodetic2ecef(45.0, 30.0, h))
    e = math.radians(el_deg)
    sats = np.stack([_sat_at(lat, lon, h, math.radians(a), e) for a in (0.0, 120.0, 240.0)]
                    + [_sat_at(lat, lon, h, 0.3, -0.5)])  # a fourth one, below the horizon: not tracked
    hdop, vdop = uav_nav.dops_clock_free(rx, sats, np.array([True, True, True, False]))
    assert float(hdop) == pytest.approx(math.sqrt(4.0 / (3.0 * math.cos(e) ** 2)), rel=1e-9)
    assert float(vdop) == pytest.approx(1.0 / (math.sqrt(3.0) * math.sin(e)), rel=1e-9)
    # fewer than three tracked: no fix, no DOP
    hdop, vdop = uav_nav.dops_clock_free(rx, sats, np.array([True, True, False, False]))
    assert np.isnan(hdop) and np.isnan(vdop)


def test_ned_covariance_is_the_ecef_covariance_rotated_as_pymap3d_rotates():
    rng = np.random.default_rng(5)
    A = rng.standard_normal((6, 6))
    P = A @ A.T
    lat, lon = 47.3, -122.1
    x = np.zeros(6)
    x[0:3] = pymap3d.geodetic2ecef(lat, lon, 500.0)
    est = uav_nav.NavEstimate(0.0, x[None], P[None], np.zeros(1), np.array([8]))
    Pp, Pv = uav_nav.ned_covariances(est)
    # pymap3d's ECEF -> ENU of the unit vectors: the columns of R_enu; NED = (N, E, -U)
    cols = np.array([pymap3d.ecef2enuv(*u, lat, lon) for u in np.eye(3)]).T  # rows E, N, U
    R = np.stack([cols[1], cols[0], -cols[2]])
    assert Pp[0] == pytest.approx(R @ P[0:3, 0:3] @ R.T, rel=1e-9, abs=1e-9)
    assert Pv[0] == pytest.approx(R @ P[3:6, 3:6] @ R.T, rel=1e-9, abs=1e-9)


# ---------------------------------------------------------------------- the worker's group on loopback


class Group:
    """count UAVs (no sonde) of the worker's VehicleGroup with their endpoints; a pymavlink GCS."""

    def __init__(self, tmp_path, start="in-flight", count=2, **uavs):
        self.peer = Peer()
        self.base = udp_base(count)
        self.scn = default_scenario().replace(
            sonde={"enabled": False}, uavs={"count": count, "start": start, **uavs},
            mavlink={"gcs": f"127.0.0.1:{self.peer.addr[1]}", "base_port": self.base, "tlog": False})
        self.g = VehicleGroup(self.scn, list(range(count)), InMemoryTransport(), np.random.SeedSequence(7),
                              with_sonde=False)
        self.eg = build_endpoints(self.g, self.scn, tmp_path)
        self.dt = 1.0 / self.scn.run.rate_hz
        self.k = 0

    @property
    def t(self) -> float:
        return self.scn.run.t0_gps_s + self.k * self.dt

    def step(self, n: int = 1, each=None) -> list:
        out = []
        for _ in range(n):
            t = self.t
            self.g.step(t)
            self.eg.step(t, _mav_telemetry(self.g.telemetry(), len(self.eg)))
            self.k += 1
            got = self.peer.drain(0.0)
            if each is not None:
                each(got)
            out += got
        return out

    def addr(self, sysid: int):
        return ("127.0.0.1", self.base + 10 * (sysid - 1))

    def send(self, sysid, msg, steps: int = 3) -> list:
        self.peer.send(msg, self.addr(sysid))
        select.select([self.g.endpoints[sysid - 1].sock], [], [], 0.05)
        return self.step(steps)

    def cmd(self, sysid, command, *params):
        p = list(params) + [0.0] * (7 - len(params))
        return self.send(sysid, self.peer.mav.command_long_encode(sysid, 1, command, 0, *p))

    def all_streams(self, hz: int = 1) -> None:
        for s in range(1, len(self.eg) + 1):
            self.send(s, self.peer.mav.request_data_stream_encode(s, 1, mav.MAV_DATA_STREAM_ALL, hz, 1), steps=1)

    def close(self):
        self.eg.close()
        self.peer.close()


def _of(got, name, sysid=1):
    return [m for m in of_type(got, name) if m.get_srcSystem() == sysid]


@pytest.fixture
def grp(tmp_path):
    g = Group(tmp_path)
    yield g
    g.close()


@pytest.fixture
def seed_grp(tmp_path):
    """Three UAVs on the seed 002 trajectories (pattern "north"), the ones the onboard filter's q
    was tuned on by its NEES (vehicles/uav_nav.py): the statistics of a consistent filter hold."""
    g = Group(tmp_path, count=3, pattern="north")
    yield g
    g.close()


@pytest.mark.live  # loopback sockets
def test_gps_raw_int_dop_and_accuracy_from_the_receiver_and_the_ekf_against_the_truth(seed_grp):
    """GPS_RAW_INT over 300 s: fix_type 3 and satellites_visible = the satellites above the
    receiver's 10 deg mask at the true position (pymap3d's look angles); eph / epv = 100 x the
    clock-free HDOP / VDOP of those satellites (computed here from pymap3d's azimuth and
    elevation, another implementation); h_acc / v_acc (the EKF's sqrt(P_nn + P_ee), sqrt(P_dd))
    agree with the real error of the reported position against the truth: RMS ratio in 0.7..1.4
    over the 3 UAVs after the first 30 s (measured: 1.15 horizontal, 0.86 vertical)."""
    from sitl.gnss.orbits import sat_state_ecef

    grp = seed_grp
    grp.all_streams(1)
    herr, verr, hacc, vacc = [], [], [], []
    checked = [0]

    def each(got):
        for j in range(3):
            gps = _of(got, "GPS_RAW_INT", j + 1)
            if not gps:
                continue
            m = gps[-1]
            tu = grp.g.last_uav_truth
            la, lo, hh = math.degrees(tu.lat_rad[j]), math.degrees(tu.lon_rad[j]), float(tu.h_m[j])
            n, e, d = pymap3d.geodetic2ned(m.lat * 1e-7, m.lon * 1e-7, m.alt * 1e-3, la, lo, hh)
            if grp.k > 30:  # after the filter's start from a least-squares fix
                herr.append(n * n + e * e)
                verr.append(d * d)
                hacc.append((m.h_acc * 1e-3) ** 2)
                vacc.append((m.v_acc * 1e-3) ** 2)
            if grp.k % 50 == 0:  # the DOP check every 50 s
                sp, _ = sat_state_ecef(grp.g.const, grp.t - grp.dt)
                az, el, _ = pymap3d.ecef2aer(sp[:, 0], sp[:, 1], sp[:, 2], la, lo, hh)
                up = el >= 10.0
                a, z = np.radians(az[up]), np.radians(el[up])
                G = np.stack([np.cos(z) * np.sin(a), np.cos(z) * np.cos(a), np.sin(z)], axis=-1)
                Q = np.linalg.inv(G.T @ G)
                assert m.fix_type == mav.GPS_FIX_TYPE_3D_FIX and m.satellites_visible == int(up.sum())
                # the receiver's DOP is at its estimated position (metres from the truth): 1 % agrees
                assert m.eph == pytest.approx(100 * math.sqrt(Q[0, 0] + Q[1, 1]), rel=0.01, abs=1)
                assert m.epv == pytest.approx(100 * math.sqrt(Q[2, 2]), rel=0.01, abs=1)
                checked[0] += 1

    grp.step(300, each)
    assert checked[0] >= 15 and len(herr) >= 3 * 260
    rh = math.sqrt(np.mean(herr) / np.mean(hacc))
    rv = math.sqrt(np.mean(verr) / np.mean(vacc))
    assert 0.7 < rh < 1.4 and 0.7 < rv < 1.4, (rh, rv)


@pytest.mark.live  # loopback sockets
def test_ekf_status_report_flags_and_test_ratios_from_the_onboard_filter(seed_grp):
    """EKF_STATUS_REPORT: the flags of an aided filter (attitude, velocities, positions, the
    predicted ones; no constant-position mode, no compass); its "variances" are sqrt(test ratio)
    of ArduPilot's 5-sigma gate, so for a consistent filter E[variance^2] = 1 / 25: the mean over
    300 s x 3 UAVs is within a factor 2 of that (measured: 0.69, 0.87, 0.86 x 1/25 for velocity,
    horizontal, vertical).  (On the default "orbit" pattern the constant-velocity filter lags the
    turns: 4.6 and 3.2 x 1/25 for velocity and horizontal position -- what the report is for.)
    SYS_STATUS: GPS and AHRS present, enabled, healthy."""
    grp = seed_grp
    grp.all_streams(1)
    got = grp.step(300)
    rep = [r for s in (1, 2, 3) for r in _of(got, "EKF_STATUS_REPORT", s)[30:]]
    assert len(rep) >= 3 * 260
    want = (mav.EKF_ATTITUDE | mav.EKF_VELOCITY_HORIZ | mav.EKF_VELOCITY_VERT | mav.EKF_POS_HORIZ_REL
            | mav.EKF_POS_HORIZ_ABS | mav.EKF_POS_VERT_ABS | mav.EKF_PRED_POS_HORIZ_REL | mav.EKF_PRED_POS_HORIZ_ABS)
    late = rep
    assert all(r.flags & want == want for r in late)
    assert not any(r.flags & (mav.EKF_CONST_POS_MODE | mav.EKF_UNINITIALIZED) for r in late)
    assert all(r.compass_variance == 0 and r.terrain_alt_variance == 0 for r in late)
    for f in ("velocity_variance", "pos_horiz_variance", "pos_vert_variance"):
        m = float(np.mean([getattr(r, f) ** 2 for r in late]))
        assert 0.5 / 25 < m < 2.0 / 25, (f, m)
    s = _of(got, "SYS_STATUS")[-1]
    for bit in (mav.MAV_SYS_STATUS_SENSOR_GPS, mav.MAV_SYS_STATUS_AHRS, mav.MAV_SYS_STATUS_SENSOR_BATTERY):
        assert s.onboard_control_sensors_present & s.onboard_control_sensors_enabled \
            & s.onboard_control_sensors_health & bit, bit


@pytest.mark.live  # loopback sockets
def test_losing_the_satellites_clears_fix_ekf_flags_and_health_consistently(grp):
    """GNSS_EL_MASK raised to 1.5 rad, 86 deg (PARAM_SET, its maximum): nothing tracked -> GPS_RAW_INT NO_FIX with 0
    satellites and no DOP (65535); EKF_STATUS_REPORT keeps only ATTITUDE (the filter predicts);
    SYS_STATUS clears the GPS and AHRS health bits; EXTENDED_SYS_STATE still IN_AIR."""
    grp.all_streams(1)
    grp.step(5)
    grp.send(1, grp.peer.mav.param_set_encode(1, 1, b"GNSS_EL_MASK", 1.5, mav.MAV_PARAM_TYPE_REAL32))
    got = grp.step(5)
    g = _of(got, "GPS_RAW_INT")[-1]
    assert g.fix_type == mav.GPS_FIX_TYPE_NO_FIX and g.satellites_visible == 0 and g.eph == g.epv == 65535
    assert _of(got, "EKF_STATUS_REPORT")[-1].flags == mav.EKF_ATTITUDE
    s = _of(got, "SYS_STATUS")[-1]
    assert not s.onboard_control_sensors_health & (mav.MAV_SYS_STATUS_SENSOR_GPS | mav.MAV_SYS_STATUS_AHRS)
    assert s.onboard_control_sensors_present & mav.MAV_SYS_STATUS_SENSOR_GPS
    assert _of(got, "EXTENDED_SYS_STATE")[-1].landed_state == mav.MAV_LANDED_STATE_IN_AIR


@pytest.mark.live  # loopback sockets
def test_battery_drawn_in_simulated_time_as_the_model_says(grp):
    """BATTERY_STATUS / SYS_STATUS over 120 s of cruise (100 m/s, the battery's cruise airspeed):
    10 A + 0.5 A idle = 1050 cA; consumed 10.5 A x 119 s (from the first epoch to the last
    report's) = 347 mAh; remaining 100 x (1 - 347 / 3300) %."""
    grp.all_streams(1)
    got = grp.step(120)
    b = _of(got, "BATTERY_STATUS")[-1]
    t_last = grp.g.batteries._t - grp.scn.run.t0_gps_s
    assert b.current_battery == 1050
    assert b.current_consumed == pytest.approx(10.5 * t_last / 3.6, abs=1.0)
    assert b.battery_remaining == round(100 * (1 - 10.5 * t_last / 3.6 / 3300))
    s = _of(got, "SYS_STATUS")[-1]
    assert s.current_battery == b.current_battery and s.battery_remaining == b.battery_remaining


@pytest.mark.live  # loopback sockets
def test_ground_start_landed_state_battery_idle_then_take_off(tmp_path):
    """A ground start: EXTENDED_SYS_STATE ON_GROUND and the battery at its idle draw (disarmed,
    50 cA), no NAV_CONTROLLER_OUTPUT in MANUAL (ArduPlane sends none there); armed and TAKEOFF:
    TAKEOFF, then IN_AIR once the climb-out is done (the autopilot's phases), the current rising
    with the airspeed; NAV_CONTROLLER_OUTPUT's altitude error is TKOFF_ALT above home - altitude."""
    grp = Group(tmp_path, start="ground", count=1)
    try:
        grp.all_streams(1)
        got = grp.step(5)
        assert {m.landed_state for m in _of(got, "EXTENDED_SYS_STATE")} == {mav.MAV_LANDED_STATE_ON_GROUND}
        assert _of(got, "BATTERY_STATUS")[-1].current_battery == 50
        assert not _of(got, "NAV_CONTROLLER_OUTPUT")
        grp.cmd(1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        grp.send(1, grp.peer.mav.set_mode_encode(1, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, cv.TAKEOFF))
        states, nav_alt_err = [], []

        def each(got):
            for m in _of(got, "EXTENDED_SYS_STATE"):
                if not states or states[-1] != m.landed_state:
                    states.append(m.landed_state)
            for m in _of(got, "NAV_CONTROLLER_OUTPUT"):
                ap = grp.g.autopilot
                nav_alt_err.append((m.alt_error, float(ap.home[0, 2] + ap.cfgs[0].tkoff_alt_m - ap.pos[0, 2])))
        grp.step(120, each)
        assert states[:3] == [mav.MAV_LANDED_STATE_ON_GROUND, mav.MAV_LANDED_STATE_TAKEOFF,
                              mav.MAV_LANDED_STATE_IN_AIR] or states[:2] == [mav.MAV_LANDED_STATE_TAKEOFF,
                                                                            mav.MAV_LANDED_STATE_IN_AIR], states
        assert grp.g.autopilot.phase[0] == cv.FLYING
        assert nav_alt_err
        b = grp.step(2)
        assert _of(b, "BATTERY_STATUS")[-1].current_battery > 50
    finally:
        grp.close()


@pytest.mark.live  # loopback sockets
def test_nav_controller_output_in_guided_against_pymap3d(tmp_path):
    """GUIDED to a point 8 km away, 150 m up (COMMAND_INT DO_REPOSITION, MAV_FRAME_GLOBAL): target_bearing and wp_dist are the point's
    azimuth and horizontal distance from the UAV (pymap3d's look angle and Vincenty distance from
    the UAV's position now: 1 deg, 0.5 %); alt_error = target altitude - altitude; nav_bearing = target_bearing
    (the guidance flies straight at it); aspd_error = commanded - flown airspeed ~ 0 in cruise."""
    grp = Group(tmp_path, count=1)
    try:
        grp.all_streams(1)
        grp.step(3)
        ap = grp.g.autopilot
        la, lo, h = (float(v) for v in ap.pos[0])
        tla, tlo, _ = pymap3d.aer2geodetic(60.0, 0.0, 8000.0, math.degrees(la), math.degrees(lo), h)
        talt = h + 150.0
        grp.send(1, grp.peer.mav.command_int_encode(1, 1, mav.MAV_FRAME_GLOBAL_INT, mav.MAV_CMD_DO_REPOSITION, 0, 0,
                                                     -1, mav.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE, 0, 0,
                                                     int(round(tla * 1e7)), int(round(tlo * 1e7)), talt))
        assert ap.mode[0] == cv.GUIDED
        seen = 0
        for _ in range(20):
            got = grp.step(1)
            nav = _of(got, "NAV_CONTROLLER_OUTPUT")
            if not nav:
                continue
            m = nav[-1]
            pla, plo, ph = (float(v) for v in grp.g.fleet.state_y[0, :3])  # where the UAV is now
            az, _el, _r = pymap3d.geodetic2aer(tla, tlo, ph, math.degrees(pla), math.degrees(plo), ph)
            dist = vdist(math.degrees(pla), math.degrees(plo), tla, tlo)[0]
            if dist < 1500:
                break
            assert abs(((m.target_bearing - az) + 180) % 360 - 180) <= 1.0
            assert m.nav_bearing == m.target_bearing
            assert m.wp_dist == pytest.approx(dist, rel=0.005)
            assert m.alt_error == pytest.approx(talt - ph, abs=0.5)
            assert abs(m.aspd_error) < 1.0
            seen += 1
        assert seen >= 10
    finally:
        grp.close()
