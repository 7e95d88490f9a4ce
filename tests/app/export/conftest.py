"""A small bus log whose every exported value is known in closed form (geodetic positions
turned into ECEF by pymap3d, an independent implementation; errors and covariances laid out in
east-north-up), and the run directory holding it."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pymap3d
import pytest

from sitl.bus import Estimate, RadarMeasurement, Truth, UavNav, encode, key_for
from sitl.bus.buslog import BusLogWriter

RUN = "r1"
T0 = 1419728400.0  # GPS s: 2025-01-01T00:59:42Z
RECV_LAG_S = 0.25  # every record is received this long after its message's time
BEACON_LLH = (55.9, 37.5, 200.0)  # deg, deg, m (h grows 10 m per epoch)
ERR_ENU_M = np.array([3.0, 4.0, 0.0])  # estimate - truth, east/north/up
SIGMA_ENU_M = np.array([4.0, 2.0, 9.0])  # the estimate's position sigmas, east/north/up
VEL_ERR_M_S = np.array([0.5, 0.0, 0.0])  # ECEF
NIS = 1.5
RADAR_LLH = (55.8, 37.4, 150.0)
UAV_LON0 = 179.9999  # UAV 7 flies east across the antimeridian: 4e-5 deg per epoch
EPOCHS = 5


def enu_rotation(lat_deg: float, lon_deg: float) -> np.ndarray:
    """enu = R @ d_ecef (the textbook rows: east, north, up)."""
    la, lo = math.radians(lat_deg), math.radians(lon_deg)
    return np.array([[-math.sin(lo), math.cos(lo), 0.0],
                     [-math.sin(la) * math.cos(lo), -math.sin(la) * math.sin(lo), math.cos(la)],
                     [math.cos(la) * math.cos(lo), math.cos(la) * math.sin(lo), math.sin(la)]])


def ecef(lat: float, lon: float, h: float) -> np.ndarray:
    return np.array(pymap3d.geodetic2ecef(lat, lon, h))


def beacon_llh(k: int) -> tuple:
    return BEACON_LLH[0], BEACON_LLH[1], BEACON_LLH[2] + 10.0 * k


def uav_lon(k: int) -> float:
    lon = UAV_LON0 + 4e-5 * k
    return lon - 360.0 if lon > 180.0 else lon


@dataclass
class SyntheticLog:
    path: object
    records: int
    per_key: dict  # key -> records of it that decode
    undecodable: int
    no_receive_time: int


def write_log(path) -> SyntheticLog:
    per_key: dict = {}
    n = 0
    with BusLogWriter(path, append=False, fsync=False) as w:
        def put(key, msg, t_recv=None):
            nonlocal n
            w.append(key, encode(msg), msg.t_gps_s + RECV_LAG_S if t_recv is None else t_recv)
            per_key[key] = per_key.get(key, 0) + 1
            n += 1
        zero = np.zeros(3)
        for k in range(EPOCHS):
            t = T0 + k
            lat, lon, h = beacon_llh(k)
            p = ecef(lat, lon, h)
            tr = Truth(t_gps_s=t, source_id="truth", seq=k, kind="beacon", pos_ecef_m=p, vel_ecef_m_s=zero)
            put(key_for(RUN, tr, id="b1"), tr)
            if k >= 1:  # the first epoch has a truth and no estimate
                r = enu_rotation(lat, lon)
                cov = np.zeros((6, 6))
                cov[:3, :3] = r.T @ np.diag(SIGMA_ENU_M ** 2) @ r
                cov[3:, 3:] = np.eye(3)
                est_p = np.array(pymap3d.enu2ecef(*ERR_ENU_M, lat, lon, h))
                est = Estimate(t_gps_s=t, source_id="gs", seq=k, kind="beacon", pos_ecef_m=est_p,
                               vel_ecef_m_s=VEL_ERR_M_S.copy(), cov=(cov + cov.T) / 2, nis=NIS, mode="fused")
                put(key_for(RUN, est, id="b1"), est)
            up = ecef(10.0, uav_lon(k), 1000.0)
            tu = Truth(t_gps_s=t, source_id="truth", seq=k, kind="uav", pos_ecef_m=up, vel_ecef_m_s=zero)
            put(key_for(RUN, tu, id="7"), tu)
            nav = UavNav(t_gps_s=t, source_id="uav7", seq=k, pos_ecef_m=up + np.array([1.0, 0.0, 0.0]),
                         vel_ecef_m_s=zero, cov=np.eye(6), n_sats=8, fix_type=3)
            put(key_for(RUN, nav, uav=7), nav)
        ts = Truth(t_gps_s=T0 + 2, source_id="truth", seq=0, kind="sonde", pos_ecef_m=ecef(56.0, 37.6, 5000.0),
                   vel_ecef_m_s=zero)
        put(key_for(RUN, ts, id="s0001"), ts)
        rm = RadarMeasurement(t_gps_s=T0 + 2, source_id="arls1", seq=0, slant_range_m=1e4, az_rad=1.0, el_rad=0.3,
                              var_range_m2=25.0, var_az_rad2=1e-6, var_el_rad2=1e-6, angles_valid=True,
                              radar_pos_ecef_m=ecef(*RADAR_LLH))
        put(key_for(RUN, rm, radar="arls1", sonde="s0001"), rm, t_recv=-math.inf)  # before the clock started
        w.append(f"{RUN}/uav/7/nav", b"\x81\xa3not a bus payload", T0 + 4.5)  # a payload that does not decode
        n += 1
    return SyntheticLog(path, n, per_key, undecodable=1, no_receive_time=1)


@pytest.fixture
def synthetic_run(tmp_path) -> SyntheticLog:
    out = tmp_path / "run"
    out.mkdir()
    return write_log(out / "bus.log")
