"""Tests of sitl.geodesy: round trips, independent references, hand cases, bad input."""
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import brentq

from sitl import geodesy as g
from sitl.constants import PZ90_11, WGS84, ellipsoid

HALF_PI = math.pi / 2
TOL_M = 1e-6  # all round trips are checked well below the 1 mm requirement

det = settings(derandomize=True, deadline=None, database=None, max_examples=300)
ELLS = st.sampled_from(["wgs84", "pz90.11"])
LAT = st.one_of(st.floats(-HALF_PI, HALF_PI), st.sampled_from([HALF_PI, -HALF_PI, 0.0, 1e-12, HALF_PI - 1e-12]))
LON = st.one_of(st.floats(-math.pi, math.pi), st.sampled_from([0.0, math.pi, -math.pi, HALF_PI]))
H = st.one_of(st.floats(-1000.0, 4.0e7), st.sampled_from([-1000.0, 0.0, 4.0e7]))


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _check_geodetic(lat, lon, h, lat2, lon2, h2, ell):
    """Compare geodetic triples as distances in metres (lon is meaningless at the poles)."""
    e = ellipsoid(ell)
    n = e.a_m / np.sqrt(1 - e.e2 * np.sin(lat) ** 2)
    assert np.all(np.abs(h2 - h) < TOL_M)
    assert np.all(np.abs(lat2 - lat) * (e.b_m * (1 - e.e2) + h) < TOL_M)  # M >= b (1 - e2)
    assert np.all(np.abs(_wrap(lon2 - lon)) * (n + h) * np.cos(lat) < TOL_M)
    assert np.all(np.abs(lat2) <= HALF_PI)


# ---------------------------------------------------------------- geodetic <-> ECEF
@det
@given(LAT, LON, H, ELLS)
def test_geodetic_ecef_round_trip(lat, lon, h, ell):
    pos = g.geodetic_to_ecef(lat, lon, h, ell)
    lat2, lon2, h2 = g.ecef_to_geodetic(pos, ell)
    assert np.linalg.norm(g.geodetic_to_ecef(lat2, lon2, h2, ell) - pos) < TOL_M
    _check_geodetic(lat, lon, h, lat2, lon2, h2, ell)


@pytest.mark.parametrize("ell", ["wgs84", "pz90.11"])
def test_geodetic_ecef_round_trip_dense_vectorised(ell):
    rng = np.random.default_rng(7)
    n = 200_000
    lat = np.arcsin(rng.uniform(-1, 1, n))
    lat[:3000] = np.repeat([HALF_PI, -HALF_PI, 0.0], 1000)
    lon = rng.uniform(-np.pi, np.pi, n)
    h = np.where(rng.random(n) < 0.5, rng.uniform(-1000, 4e7, n), 10 ** rng.uniform(-3, 4, n) - 1000)
    pos = g.geodetic_to_ecef(lat, lon, h, ell)
    lat2, lon2, h2 = g.ecef_to_geodetic(pos, ell)
    assert np.linalg.norm(g.geodetic_to_ecef(lat2, lon2, h2, ell) - pos, axis=-1).max() < TOL_M
    _check_geodetic(lat, lon, h, lat2, lon2, h2, ell)


def test_poles_and_equator_exact():
    for e in (WGS84, PZ90_11):
        for h in (-1000.0, 0.0, 20_200e3, 4e7):
            lat, _, h2 = g.ecef_to_geodetic([0.0, 0.0, e.b_m + h], e)
            assert lat == HALF_PI and abs(h2 - h) < TOL_M
            lat, _, h2 = g.ecef_to_geodetic([0.0, 0.0, -(e.b_m + h)], e)
            assert lat == -HALF_PI and abs(h2 - h) < TOL_M
            lat, lon, h2 = g.ecef_to_geodetic([0.0, -(e.a_m + h), 0.0], e)
            assert lat == 0.0 and lon == -HALF_PI and abs(h2 - h) < TOL_M


def test_near_centre_is_finite():
    rng = np.random.default_rng(3)
    pos = rng.normal(size=(20_000, 3)) * rng.uniform(0, 1e5, (20_000, 1))
    pos[:4] = [[0, 0, 0], [1, 0, 0], [0, 0, 1], [0, 0, -1]]
    lat, lon, h = g.ecef_to_geodetic(pos)
    assert np.isfinite(lat).all() and np.isfinite(lon).all() and np.isfinite(h).all()
    assert np.abs(lat).max() <= HALF_PI


def test_published_point_epsg_guidance_note_7_2():
    # EPSG Guidance Note 7-2, method 9602 example (WGS 84):
    # 53 deg 48' 33.820" N, 2 deg 07' 46.380" E, h = 73.0 m
    # <-> X = 3771793.968 m, Y = 140253.342 m, Z = 5124304.349 m.
    lat = math.radians(53 + 48 / 60 + 33.820 / 3600)
    lon = math.radians(2 + 7 / 60 + 46.380 / 3600)
    xyz = np.array([3771793.968, 140253.342, 5124304.349])
    np.testing.assert_allclose(g.geodetic_to_ecef(lat, lon, 73.0), xyz, atol=1e-3)
    lat2, lon2, h2 = g.ecef_to_geodetic(xyz)
    assert abs(lat2 - lat) * 6.4e6 < 1e-3 and abs(lon2 - lon) * 3.8e6 < 1e-3 and abs(h2 - 73.0) < 1e-3


def test_ellipsoid_axes():
    for e in (WGS84, PZ90_11):
        np.testing.assert_allclose(g.geodetic_to_ecef(0, 0, 0, e), [e.a_m, 0, 0], atol=1e-9)
        np.testing.assert_allclose(g.geodetic_to_ecef(HALF_PI, 0.7, 10, e), [0, 0, e.b_m + 10], atol=1e-6)
        np.testing.assert_allclose(g.geodetic_to_ecef(0, HALF_PI, 1e3, e), [0, e.a_m + 1e3, 0], atol=1e-6)


def _normal_foot(p, z, e):
    """Independent geodetic latitude and height: root of the normal condition by Brent.

    The foot F(phi) = (N cos phi, N (1 - e2) sin phi) of a point (p, z) in its meridian
    plane satisfies (P - F) x n(phi) = 0, i.e. p sin phi - z cos phi - N e2 sin phi cos phi = 0.
    The root lies between the geocentric latitude psi and psi + 0.01 rad (north).
    """
    s = 1.0 if z >= 0 else -1.0
    z = abs(z)
    psi = math.atan2(z, p)

    def cond(phi):
        n = e.a_m / math.sqrt(1 - e.e2 * math.sin(phi) ** 2)
        return p * math.sin(phi) - z * math.cos(phi) - n * e.e2 * math.sin(phi) * math.cos(phi)

    phi = psi if cond(psi) == 0.0 else brentq(cond, psi, min(psi + 0.01, HALF_PI), xtol=1e-16, rtol=1e-15)
    n = e.a_m / math.sqrt(1 - e.e2 * math.sin(phi) ** 2)
    dp, dz = p - n * math.cos(phi), z - n * (1 - e.e2) * math.sin(phi)
    h = math.copysign(math.hypot(dp, dz), dp * math.cos(phi) + dz * math.sin(phi))
    return s * phi, h


@pytest.mark.parametrize("e", [WGS84, PZ90_11])
def test_ecef_to_geodetic_against_brent_normal_foot(e):
    rng = np.random.default_rng(11)
    pos = rng.normal(size=(300, 3))
    pos *= rng.uniform(e.a_m - 30e3, e.a_m + 4e7, (300, 1)) / np.linalg.norm(pos, axis=1, keepdims=True)
    lat, _, h = g.ecef_to_geodetic(pos, e)
    for k, (x, y, z) in enumerate(pos):
        phi, hh = _normal_foot(math.hypot(x, y), z, e)
        assert abs(phi - lat[k]) < 1e-12 and abs(hh - h[k]) < TOL_M


def test_broadcasting_shapes():
    pos = g.geodetic_to_ecef(np.zeros((4, 1)), np.zeros(5), 0.0)
    assert pos.shape == (4, 5, 3)
    assert all(v.shape == (4, 5) for v in g.ecef_to_geodetic(pos))
    assert g.ecef_to_enu(pos, 0.1, 0.2, 3.0).shape == (4, 5, 3)
    assert g.enu_to_ecef(np.zeros(3), np.zeros(6), 0.0, 0.0).shape == (6, 3)
    assert g.enu_rotation(np.zeros((2, 4)), 0.0).shape == (2, 4, 3, 3)
    az, el, r = g.ecef_to_aer(pos[0, 0], pos)
    assert az.shape == el.shape == r.shape == (4, 5)
    assert g.aer_to_ecef(az, el, r, pos[0, 0]).shape == (4, 5, 3)
    assert g.geocentric_elevation_rad(pos[:, 0] + 1.0, pos[0, 0] * 4).shape == (4,)
    assert np.ndim(g.ecef_to_geodetic([7e6, 0, 0])[0]) == 0


# ---------------------------------------------------------------- ENU and AER
def test_enu_rotation_orthonormal_and_axes():
    r = g.enu_rotation(np.array([0.3, -HALF_PI, HALF_PI]), np.array([-2.0, 0.5, 3.0]))
    np.testing.assert_allclose(r @ np.swapaxes(r, -1, -2), np.broadcast_to(np.eye(3), r.shape), atol=1e-15)
    np.testing.assert_allclose(np.linalg.det(r), 1.0)
    # At (0, 0): east = +y, north = +z, up = +x.
    np.testing.assert_allclose(g.enu_rotation(0.0, 0.0), [[0, 1, 0], [0, 0, 1], [1, 0, 0]], atol=1e-16)


@det
@given(LAT, LON, st.floats(-1000, 1e5), st.lists(st.floats(-5e7, 5e7), min_size=3, max_size=3), ELLS)
def test_enu_round_trip(lat, lon, h, enu, ell):
    pos = g.enu_to_ecef(enu, lat, lon, h, ell)
    np.testing.assert_allclose(g.ecef_to_enu(pos, lat, lon, h, ell), enu, rtol=0, atol=TOL_M)
    # The reference itself maps to the origin, and "up" is along the ellipsoid normal.
    up = g.ecef_to_enu(g.geodetic_to_ecef(lat, lon, h + 100.0, ell), lat, lon, h, ell)
    np.testing.assert_allclose(up, [0, 0, 100.0], atol=TOL_M)


@det
@given(LAT, LON, st.floats(-1000, 1e5), st.floats(0, 2 * math.pi, exclude_max=True),
       st.floats(-HALF_PI, HALF_PI), st.floats(1.0, 5e7), ELLS)
def test_aer_round_trip(lat, lon, h, az, el, rng, ell):
    rx = g.geodetic_to_ecef(lat, lon, h, ell)
    tgt = g.aer_to_ecef(az, el, rng, rx, ell)
    az2, el2, rng2 = g.ecef_to_aer(rx, tgt, ell)
    assert 0.0 <= az2 < 2 * math.pi and -HALF_PI <= el2 <= HALF_PI
    assert abs(rng2 - rng) < TOL_M and abs(el2 - el) * rng < TOL_M
    assert abs(_wrap(az2 - az)) * rng * math.cos(el) < TOL_M
    assert np.linalg.norm(g.aer_to_ecef(az2, el2, rng2, rx, ell) - tgt) < TOL_M


def test_aer_hand_cases():
    rx = np.array([WGS84.a_m, 0.0, 0.0])  # equator, lon 0: east = +y, north = +z, up = +x
    for d, az_want, el_want in [([0, 1e3, 0], HALF_PI, 0.0), ([0, 0, 1e3], 0.0, 0.0),
                                ([0, -1e3, 0], 3 * HALF_PI, 0.0), ([0, 0, -1e3], math.pi, 0.0),
                                ([-1e3, 0, 0], 0.0, -HALF_PI)]:
        az, el, r = g.ecef_to_aer(rx, rx + d)
        assert abs(az - az_want) < 1e-15 and abs(el - el_want) < 1e-15 and abs(r - 1e3) < 1e-9
    # Straight overhead anywhere, incl. the pole: geodetic up.
    for lat, lon in [(0.7, -1.2), (HALF_PI, 0.0), (-0.3, 3.0)]:
        rx = g.geodetic_to_ecef(lat, lon, 100.0)
        _, el, r = g.ecef_to_aer(rx, g.geodetic_to_ecef(lat, lon, 20_200e3))
        assert abs(el - HALF_PI) < 1e-12 and abs(r - (20_200e3 - 100.0)) < TOL_M
    # A hair west of north stays below 2 pi.
    az, _, _ = g.ecef_to_aer([WGS84.a_m, 0, 0], [WGS84.a_m, -1e-300, 1e3])
    assert 0.0 <= az < 2 * math.pi


def test_geocentric_elevation():
    x = np.array([0.0, 0.0, 6.4e6])
    assert abs(g.geocentric_elevation_rad(x, x * 4) - HALF_PI) < 1e-15
    assert abs(g.geocentric_elevation_rad(x, x + [1e7, 0, 0])) < 1e-15
    assert abs(g.geocentric_elevation_rad(x, [0, 0, 0]) + HALF_PI) < 1e-15
    # 45 deg: target up 1 km and across 1 km.
    assert abs(g.geocentric_elevation_rad(x, x + [0, 1e3, 1e3]) - math.pi / 4) < 1e-12
    # Equals geodetic elevation where the normal passes through the centre (equator).
    rx = g.geodetic_to_ecef(0.0, 1.0, 0.0)
    sat = rx + [1e6, 2e6, 3e6]
    assert abs(g.geocentric_elevation_rad(rx, sat) - g.ecef_to_aer(rx, sat)[1]) < 1e-12
    with pytest.raises(ValueError, match="rx_pos_ecef_m"):
        g.geocentric_elevation_rad([0, 0, 0], x)
    with pytest.raises(ValueError, match="sat_pos_ecef_m"):
        g.geocentric_elevation_rad(x, x)


# ---------------------------------------------------------------- PZ-90.11 <-> WGS-84
@det
@given(st.lists(st.floats(-5e7, 5e7), min_size=3, max_size=3))
def test_helmert_round_trip(pos):
    np.testing.assert_allclose(g.wgs84_to_pz90_11(g.pz90_11_to_wgs84(pos)), pos, rtol=0, atol=1e-8)
    np.testing.assert_allclose(g.pz90_11_to_wgs84(g.wgs84_to_pz90_11(pos)), pos, rtol=0, atol=1e-8)


def test_helmert_values():
    # Origin maps to the translation; the rotation convention (coordinate frame) is pinned by
    # a point on the z axis: x' = tx - ry z, y' = ty + rx z (rx = 0.019, ry = -0.042 mas).
    np.testing.assert_allclose(g.pz90_11_to_wgs84([0, 0, 0]), [-0.003, -0.001, 0.0], atol=1e-15)
    mas = math.radians(1e-3 / 3600)
    want = [-0.003 + 0.042 * mas * 6.4e6, -0.001 + 0.019 * mas * 6.4e6, 6.4e6]
    np.testing.assert_allclose(g.pz90_11_to_wgs84([0, 0, 6.4e6]), want, rtol=0, atol=1e-9)
    pts = g.geodetic_to_ecef(np.linspace(-1.5, 1.5, 50), np.linspace(-3, 3, 50), 20e6)
    shift = np.linalg.norm(g.pz90_11_to_wgs84(pts) - pts, axis=-1)
    assert shift.max() < 0.01 and shift.min() > 0.0
    assert g.pz90_11_to_wgs84(np.zeros((2, 7, 3))).shape == (2, 7, 3)


# ---------------------------------------------------------------- bad input
@pytest.mark.parametrize("call, name", [
    (lambda: g.ecef_to_geodetic(np.zeros((4, 2))), "pos_ecef_m"),
    (lambda: g.ecef_to_geodetic(5.0), "pos_ecef_m"),
    (lambda: g.ecef_to_enu(np.zeros(4), 0, 0, 0), "pos_ecef_m"),
    (lambda: g.enu_to_ecef(np.zeros((3, 2)), 0, 0, 0), "enu_m"),
    (lambda: g.ecef_to_aer(np.zeros(3) + 7e6, np.zeros((5, 4))), "tgt_pos_ecef_m"),
    (lambda: g.ecef_to_aer(np.zeros(2), np.zeros(3)), "rx_pos_ecef_m"),
    (lambda: g.aer_to_ecef(0, 0, 1, np.zeros(6)), "rx_pos_ecef_m"),
    (lambda: g.geocentric_elevation_rad(np.ones(3), np.ones(2)), "sat_pos_ecef_m"),
    (lambda: g.pz90_11_to_wgs84(np.zeros((3, 4))), "pos_ecef_m"),
    (lambda: g.wgs84_to_pz90_11([1.0, 2.0]), "pos_ecef_m"),
    (lambda: g.geodetic_to_ecef(45.0, 0.0, 0.0), "lat_rad"),
    (lambda: g.enu_rotation(-2.0, 0.0), "lat_rad"),
    (lambda: g.ecef_to_enu(np.zeros(3), 30.0, 0, 0), "ref_lat_rad"),
    (lambda: g.enu_to_ecef(np.zeros(3), -30.0, 0, 0), "ref_lat_rad"),
    (lambda: g.geodetic_to_ecef(0.0, 0.0, 0.0, "clarke1866"), "clarke1866"),
])
def test_bad_input_raises_value_error(call, name):
    with pytest.raises(ValueError, match=name):
        call()
