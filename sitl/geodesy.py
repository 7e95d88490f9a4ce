"""Geodetic, ECEF, local ENU and azimuth-elevation-range conversions; WGS-84 <-> PZ-90.11.

Angles in radians, lengths in metres.  Positions are arrays whose last axis has size 3
(x, y, z or e, n, u); every function broadcasts over leading axes.  ``ell`` is an
``Ellipsoid`` or a name ('wgs84', 'pz90.11'); None means WGS-84.
"""
from __future__ import annotations

import math

import numpy as np

from .constants import Ellipsoid, ellipsoid

_BOWRING_ITERATIONS = 3  # 2 already reach rounding level for h in [-1 km, 40 000 km]


def _xyz(v, name: str) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    if v.ndim == 0 or v.shape[-1] != 3:
        raise ValueError(f"{name} must have a last axis of size 3, got shape {v.shape}")
    return v


def _lat(lat_rad, name: str = "lat_rad") -> np.ndarray:
    lat = np.asarray(lat_rad, dtype=float)
    if np.any(np.abs(lat) > np.pi / 2 + 1e-12):
        raise ValueError(f"{name} must lie in [-pi/2, pi/2] rad (degrees passed?)")
    return lat


def geodetic_to_ecef(lat_rad, lon_rad, h_m, ell: Ellipsoid | str | None = None) -> np.ndarray:
    """Geodetic latitude, longitude, ellipsoidal height -> ECEF position (..., 3), m.

    N = a / sqrt(1 - e2 sin^2 lat);  x = (N + h) cos lat cos lon,
    y = (N + h) cos lat sin lon,  z = (N (1 - e2) + h) sin lat.
    """
    e = ellipsoid(ell)
    lat, lon, h = np.broadcast_arrays(_lat(lat_rad), np.asarray(lon_rad, float), np.asarray(h_m, float))
    sl, cl = np.sin(lat), np.cos(lat)
    n = e.a_m / np.sqrt(1.0 - e.e2 * sl**2)
    return np.stack([(n + h) * cl * np.cos(lon), (n + h) * cl * np.sin(lon), (n * (1.0 - e.e2) + h) * sl], axis=-1)


def ecef_to_geodetic(pos_ecef_m, ell: Ellipsoid | str | None = None):
    """ECEF position (..., 3), m -> (lat_rad, lon_rad, h_m); Bowring (1976) iterated.

    With p = hypot(x, y), b = a (1 - f), e'2 = e2 / (1 - e2), start from the reduced
    latitude beta = atan2(a z, b p) and iterate
        lat  = atan2(z + e'2 b sin^3 beta, max(p - e2 a cos^3 beta, 0)),
        beta = atan2((1 - f) sin lat, cos lat).
    Two iterations already reach rounding level (~2e-8 m at GEO distance) for any point
    more than ~300 km from the centre (so for every altitude from the deepest point on
    Earth to far beyond GEO); three are done.  Exact at the poles (p = 0 gives
    lat = +-pi/2) and on the equator.  Height h = p cos lat + z sin lat - a sqrt(1 - e2 sin^2 lat)
    has no pole singularity.  Closer to the centre convergence slows, and inside the
    ellipsoid's evolute (~43 km) the clamp keeps the result finite with lat in
    [-pi/2, pi/2], but it is then not the nearest-surface solution.
    """
    e = ellipsoid(ell)
    pos = _xyz(pos_ecef_m, "pos_ecef_m")
    x, y, z = pos[..., 0], pos[..., 1], pos[..., 2]
    a, b, e2 = e.a_m, e.b_m, e.e2
    ep2 = e2 / (1.0 - e2)
    p = np.hypot(x, y)
    beta = np.arctan2(a * z, b * p)
    for _ in range(_BOWRING_ITERATIONS):
        lat = np.arctan2(z + ep2 * b * np.sin(beta) ** 3, np.maximum(p - e2 * a * np.cos(beta) ** 3, 0.0))
        beta = np.arctan2((1.0 - e.f) * np.sin(lat), np.cos(lat))
    sl, cl = np.sin(lat), np.cos(lat)
    h = p * cl + z * sl - a * np.sqrt(1.0 - e2 * sl**2)
    return lat, np.arctan2(y, x), h


def enu_rotation(lat_rad, lon_rad) -> np.ndarray:
    """Rotation R (..., 3, 3) with enu = R @ d_ecef at geodetic (lat, lon).

    Rows: east = (-sin lon, cos lon, 0); north = (-sin lat cos lon, -sin lat sin lon, cos lat);
    up = (cos lat cos lon, cos lat sin lon, sin lat).  R is orthonormal, R^-1 = R^T.
    """
    lat, lon = np.broadcast_arrays(_lat(lat_rad), np.asarray(lon_rad, float))
    sp, cp, sl, cl = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    return np.stack([
        np.stack([-sl, cl, np.zeros_like(sl)], axis=-1),
        np.stack([-sp * cl, -sp * sl, cp], axis=-1),
        np.stack([cp * cl, cp * sl, sp], axis=-1),
    ], axis=-2)


def _rotate(r: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.matmul(r, v[..., None])[..., 0]


def ecef_to_enu(pos_ecef_m, ref_lat_rad, ref_lon_rad, ref_h_m, ell: Ellipsoid | str | None = None) -> np.ndarray:
    """ECEF position (..., 3) -> local east-north-up (..., 3) about a geodetic reference, m.

    enu = R(ref_lat, ref_lon) @ (pos - geodetic_to_ecef(ref)).
    """
    pos, _ = _xyz(pos_ecef_m, "pos_ecef_m"), _lat(ref_lat_rad, "ref_lat_rad")
    ref = geodetic_to_ecef(ref_lat_rad, ref_lon_rad, ref_h_m, ell)
    return _rotate(enu_rotation(ref_lat_rad, ref_lon_rad), pos - ref)


def enu_to_ecef(enu_m, ref_lat_rad, ref_lon_rad, ref_h_m, ell: Ellipsoid | str | None = None) -> np.ndarray:
    """Local east-north-up (..., 3) about a geodetic reference -> ECEF (..., 3), m.

    pos = geodetic_to_ecef(ref) + R^T @ enu.
    """
    enu, _ = _xyz(enu_m, "enu_m"), _lat(ref_lat_rad, "ref_lat_rad")
    rt = np.swapaxes(enu_rotation(ref_lat_rad, ref_lon_rad), -1, -2)
    return geodetic_to_ecef(ref_lat_rad, ref_lon_rad, ref_h_m, ell) + _rotate(rt, enu)


def _enu_about_receiver(rx: np.ndarray, ell) -> np.ndarray:
    lat, lon, _ = ecef_to_geodetic(rx, ell)
    return enu_rotation(lat, lon)


def ecef_to_aer(rx_pos_ecef_m, tgt_pos_ecef_m, ell: Ellipsoid | str | None = None):
    """Azimuth, elevation (geodetic up) and range of a target seen from a receiver.

    (e, n, u) = R(lat_rx, lon_rx) @ (tgt - rx); az = atan2(e, n) in [0, 2 pi) clockwise
    from north, el = atan2(u, hypot(e, n)) in [-pi/2, pi/2], range_m = |tgt - rx|.
    """
    rx = _xyz(rx_pos_ecef_m, "rx_pos_ecef_m")
    d = _xyz(tgt_pos_ecef_m, "tgt_pos_ecef_m") - rx
    enu = _rotate(_enu_about_receiver(rx, ell), d)
    e, n, u = enu[..., 0], enu[..., 1], enu[..., 2]
    az = np.mod(np.arctan2(e, n), 2.0 * np.pi)
    az = np.where(az >= 2.0 * np.pi, 0.0, az)[()]  # mod of a tiny negative rounds up to 2 pi
    return az, np.arctan2(u, np.hypot(e, n)), np.linalg.norm(d, axis=-1)


def aer_to_ecef(az_rad, el_rad, range_m, rx_pos_ecef_m, ell: Ellipsoid | str | None = None) -> np.ndarray:
    """Target ECEF position (..., 3) from azimuth, elevation, range seen from a receiver.

    enu = range (cos el sin az, cos el cos az, sin el);  tgt = rx + R^T(lat_rx, lon_rx) @ enu.
    """
    rx = _xyz(rx_pos_ecef_m, "rx_pos_ecef_m")
    az, el, rng = (np.asarray(v, dtype=float) for v in (az_rad, el_rad, range_m))
    enu = np.stack(np.broadcast_arrays(rng * np.cos(el) * np.sin(az), rng * np.cos(el) * np.cos(az),
                                       rng * np.sin(el)), axis=-1)
    rt = np.swapaxes(_enu_about_receiver(rx, ell), -1, -2)
    return rx + _rotate(rt, enu)


def great_circle_track(lat_deg: float, lon_deg: float, h_m: float, speed_m_s: float, heading_deg: float,
                       t_rel_s):
    """ECEF position and velocity (..., 3) at t_rel_s of a point moving at constant speed on
    the great circle of the geocentric sphere through the start (lat, lon, h), heading from
    north: acceleration only v^2/r."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    p0 = geodetic_to_ecef(lat, lon, h_m)
    r0 = float(np.linalg.norm(p0))
    u = p0 / r0
    R = enu_rotation(lat, lon)
    hd = math.radians(heading_deg)
    d = math.sin(hd) * R[0] + math.cos(hd) * R[1]
    w = d - (d @ u) * u
    w /= np.linalg.norm(w)
    th = np.asarray(t_rel_s, dtype=float)[..., None] * (speed_m_s / r0)
    return r0 * (np.cos(th) * u + np.sin(th) * w), speed_m_s * (-np.sin(th) * u + np.cos(th) * w)


def geocentric_elevation_rad(rx_pos_ecef_m, sat_pos_ecef_m):
    """Spherical-Earth elevation of a satellite S seen from X (seed 000 eq. 10), rad.

    sin el = (S - X) . X / (|X| |S - X|).  Raises ValueError if X = 0 or S = X.
    """
    x = _xyz(rx_pos_ecef_m, "rx_pos_ecef_m")
    d = _xyz(sat_pos_ecef_m, "sat_pos_ecef_m") - x
    nx, nd = np.linalg.norm(x, axis=-1), np.linalg.norm(d, axis=-1)
    if np.any(nx == 0.0):
        raise ValueError("rx_pos_ecef_m must not be the Earth's centre (elevation undefined)")
    if np.any(nd == 0.0):
        raise ValueError("sat_pos_ecef_m must differ from rx_pos_ecef_m (elevation undefined)")
    return np.arcsin(np.clip(np.sum(d * x, axis=-1) / (nx * nd), -1.0, 1.0))


# PZ-90.11 -> ITRF2008 (epoch 2010.0): EPSG:7960, information source "Parametry Zemli 1990"
# reference document (Military Topographic Dept., General Staff of the Russian Armed Forces);
# PZ-90.11 itself is established by Russian Government decree No. 1240 of 2016-11-24.
# tx, ty, tz = -0.003, -0.001, 0.000 m; rx, ry, rz = +0.019, -0.042, +0.002 mas; ds = 0 ppm,
# coordinate-frame-rotation convention: X_t = T + (1 + ds) [[1, rz, -ry], [-rz, 1, rx], [ry, -rx, 1]] X_s.
# WGS-84 (G1150 and later) agrees with ITRF2008 at the cm level, so ITRF2008 stands for WGS-84.
_MAS_RAD = np.pi / (180.0 * 3600.0 * 1000.0)
_PZ_T_M = np.array([-0.003, -0.001, 0.000])
_PZ_RX, _PZ_RY, _PZ_RZ = 0.019 * _MAS_RAD, -0.042 * _MAS_RAD, 0.002 * _MAS_RAD
_PZ_DS = 0.0
_PZ_TO_WGS_M = (1.0 + _PZ_DS) * np.array([[1.0, _PZ_RZ, -_PZ_RY], [-_PZ_RZ, 1.0, _PZ_RX], [_PZ_RY, -_PZ_RX, 1.0]])
_WGS_TO_PZ_M = np.linalg.inv(_PZ_TO_WGS_M)  # exact inverse, not the sign-flipped parameters
_PZ_TO_WGS_M.flags.writeable = _WGS_TO_PZ_M.flags.writeable = _PZ_T_M.flags.writeable = False


def pz90_11_to_wgs84(pos_ecef_m) -> np.ndarray:
    """PZ-90.11 ECEF (..., 3) -> WGS-84 ECEF, m: 7-parameter Helmert X_w = T + M X_pz (EPSG:7960).

    The shift is a few mm: |X_w - X_pz| < ~1 cm anywhere up to GEO altitude.
    """
    return _xyz(pos_ecef_m, "pos_ecef_m") @ _PZ_TO_WGS_M.T + _PZ_T_M


def wgs84_to_pz90_11(pos_ecef_m) -> np.ndarray:
    """WGS-84 ECEF (..., 3) -> PZ-90.11 ECEF, m: exact inverse X_pz = M^-1 (X_w - T)."""
    return (_xyz(pos_ecef_m, "pos_ecef_m") - _PZ_T_M) @ _WGS_TO_PZ_M.T
