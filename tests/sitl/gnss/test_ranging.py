"""Tests of sitl.gnss.ranging: light-time fixed point, exact range rate, Sagnac term."""
from __future__ import annotations


import numpy as np
import pytest

from sitl.constants import C_M_S, WGS84, Ellipsoid
from sitl.gnss.orbits import DEFAULT_TOA_GPS_S, default_constellation, gps_constellation, sat_state_ecef
from sitl.gnss.ranging import Geometry, light_time_geometry, sat_state_at_reception_frame
from tests.helpers import rot_z as _rot_z

W_E = WGS84.omega_rad_s


def _geodetic_to_ecef(lat_deg, lon_deg, h_m):
    la, lo = np.radians(lat_deg), np.radians(lon_deg)
    n = WGS84.a_m / np.sqrt(1 - WGS84.e2 * np.sin(la) ** 2)
    return np.stack([(n + h_m) * np.cos(la) * np.cos(lo), (n + h_m) * np.cos(la) * np.sin(lo),
                     (n * (1 - WGS84.e2) + h_m) * np.sin(la)], axis=-1)


def _receivers(n, seed=1):
    rng = np.random.default_rng(seed)
    pos = _geodetic_to_ecef(rng.uniform(-80, 80, n), rng.uniform(-180, 180, n), rng.uniform(0, 12_000, n))
    vel = rng.normal(0.0, 150.0, (n, 3))
    return pos, vel


def _sat_at(c, t_emit):
    """ECEF state of satellite j at t_emit[..., j] (own per-satellite evaluation)."""
    p, v = sat_state_ecef(c, t_emit)  # (..., S, S, 3): time index x satellite index
    idx = np.arange(len(c))
    return p[..., idx, idx, :], v[..., idx, idx, :]


def test_shapes_and_broadcasting():
    c = default_constellation()
    S = len(c)
    pos, vel = _receivers(6)
    g = light_time_geometry(DEFAULT_TOA_GPS_S, pos.reshape(2, 3, 3), vel.reshape(2, 3, 3), c)
    assert isinstance(g, Geometry)
    assert g.range_m.shape == g.range_rate_m_s.shape == g.tau_s.shape == (2, 3, S)
    assert g.sat_pos_ecef_m.shape == g.sat_vel_ecef_m_s.shape == g.los_unit.shape == (2, 3, S, 3)
    flat = light_time_geometry(DEFAULT_TOA_GPS_S, pos, vel, c)
    assert np.allclose(flat.range_m, g.range_m.reshape(6, S), rtol=0, atol=1e-9)
    # Per-receiver times, and one receiver at many times.
    t = DEFAULT_TOA_GPS_S + np.arange(6.0) * 0.3
    g2 = light_time_geometry(t, pos, vel, c)
    assert g2.range_m.shape == (6, S)
    g3 = light_time_geometry(t, pos[0], vel[0], c)
    assert g3.range_m.shape == (6, S)
    single = light_time_geometry(t[4], pos[0], vel[0], c)
    assert single.range_m.shape == (S,)
    assert np.allclose(g3.range_m[4], single.range_m, rtol=0, atol=1e-7)
    assert np.allclose(np.linalg.norm(g.los_unit, axis=-1), 1.0)


def test_tau_is_range_over_c_and_fixed_point_holds_independently():
    """Small epochs (full float64 time resolution) and a realistic 2025 epoch."""
    pos, vel = _receivers(5)
    for toa, tol in ((1000.0, 1e-6), (DEFAULT_TOA_GPS_S, 2e-3)):
        c = default_constellation(toa_gps_s=toa)
        t_rx = toa + 4321.0
        g = light_time_geometry(t_rx, pos, vel, c)
        assert np.abs(g.range_m / C_M_S - g.tau_s).max() < 1e-12
        assert np.all((g.tau_s > 0.060) & (g.tau_s < 0.112))  # incl. satellites below the horizon
        # Independent: ephemeris at t_rx - tau, rotated by w_e tau, is c tau away.
        p_emit, _ = _sat_at(c, t_rx - g.tau_s)
        s = _rot_z(W_E * g.tau_s, p_emit)
        assert np.abs(s - g.sat_pos_ecef_m).max() < tol
        dist = np.linalg.norm(s - pos[:, None, :], axis=-1)
        assert np.abs(dist - C_M_S * g.tau_s).max() < tol


@pytest.mark.parametrize("times", ["shared", "per_receiver", "spread"])
def test_range_rate_is_derivative_of_range(times):
    """Receivers moving linearly in ECEF; central difference of range_m in t_rx."""
    c = default_constellation()
    pos0, vel = _receivers(8, seed=7)
    vel[0] = [250.0, -120.0, 40.0]  # an aircraft
    t0 = DEFAULT_TOA_GPS_S + 5000.0
    if times == "per_receiver":
        t0 = t0 + np.arange(8.0) * 0.25  # distinct, exactly representable
    elif times == "spread":
        t0 = t0 + np.arange(8.0) * 1500.0  # uses the 1 s node grid
    h = 2.0**-5  # exact in float64 next to these epochs
    t0b = np.broadcast_to(t0, (8,))

    def geom(dt):
        return light_time_geometry(t0b + dt, pos0 + vel * dt, vel, c)

    gm, g0, gp = geom(-h), geom(0.0), geom(h)
    fd = (gp.range_m - gm.range_m) / (2 * h)
    assert np.abs(fd - g0.range_rate_m_s).max() < 1e-3  # typically ~1e-6 m/s
    fd_sat = (gp.sat_pos_ecef_m - gm.sat_pos_ecef_m) / (2 * h)
    assert np.abs(fd_sat - g0.sat_vel_ecef_m_s).max() < 1e-3
    # The documented identity: rho' = u . (ds/dt - r')
    proj = np.einsum("...k,...k->...", g0.los_unit, g0.sat_vel_ecef_m_s - vel[:, None, :])
    assert np.abs(proj - g0.range_rate_m_s).max() < 1e-8
    assert np.abs(g0.range_rate_m_s).max() < 1500.0


def test_state_at_reception_frame_matches_geometry():
    c = default_constellation()
    pos, vel = _receivers(7)
    t = DEFAULT_TOA_GPS_S + 777.0
    g = light_time_geometry(t, pos, vel, c)
    p, v = sat_state_at_reception_frame(t, g.tau_s, c, g.range_rate_m_s / C_M_S)
    assert p.shape == v.shape == g.sat_pos_ecef_m.shape
    assert np.abs(p - g.sat_pos_ecef_m).max() < 1e-6
    assert np.abs(v - g.sat_vel_ecef_m_s).max() < 1e-6
    # tau_rate = 0: the rotated emission velocity R3 v; differs by ~1e-2 m/s only.
    p0, v0 = sat_state_at_reception_frame(t, g.tau_s, c)
    assert np.array_equal(p0, p)
    diff = np.abs(v0 - g.sat_vel_ecef_m_s).max()
    assert 1e-4 < diff < 0.1
    # Independent: rotated ephemeris velocity at emission.
    _, v_emit = _sat_at(c, t - g.tau_s)
    assert np.abs(_rot_z(W_E * g.tau_s, v_emit) - v0).max() < 1e-6
    # Shared tau for all receivers broadcasts against t.
    p1, _ = sat_state_at_reception_frame(t + np.arange(3.0), g.tau_s[0], c)
    assert p1.shape == (3, len(c), 3)
    with pytest.raises(ValueError, match="tau_s"):
        sat_state_at_reception_frame(t, np.zeros(3), c)
    with pytest.raises(ValueError, match="t_rx_gps_s"):
        sat_state_at_reception_frame(np.zeros(4), g.tau_s, c)


def _range_without_rotation(c, t_rx, pos):
    """Light time ignoring Earth rotation during the flight (own iteration)."""
    tau = np.full(pos.shape[:-1] + (len(c),), 0.07)
    for _ in range(6):
        p, _ = _sat_at(c, t_rx - tau)
        rho = np.linalg.norm(p - pos[..., None, :], axis=-1)
        tau = rho / C_M_S
    return rho, p


def test_sagnac_term():
    c = default_constellation(toa_gps_s=5000.0)
    t_rx = 5000.0 + 3600.0
    sites = _geodetic_to_ecef(np.array([45.0, 45.0, 0.0, 90.0]), np.array([7.0, -120.0, 30.0, 0.0]), 0.0)
    g = light_time_geometry(t_rx, sites, np.zeros_like(sites), c)
    rho0, p_norot = _range_without_rotation(c, t_rx, sites)
    sagnac = g.range_m - rho0
    # First-order expression (w_e / c) z.(s x r) (e.g. Ashby 2003, Living Rev. Relativ.).
    s = g.sat_pos_ecef_m
    expected = W_E / C_M_S * (s[..., 0] * sites[:, None, 1] - s[..., 1] * sites[:, None, 0])
    assert np.abs(sagnac - expected).max() < 2e-3
    # Mid-latitude static receiver, satellites above the horizon: tens of metres.
    up = sites[0] / np.linalg.norm(sites[0])
    visible = ((s[0] - sites[0]) @ up) > 0
    assert 10.0 < np.abs(sagnac[0, visible]).max() < 45.0
    # Sign: satellites east of the receiver's meridian come closer (negative).
    east = (s[0, :, 1] * sites[0, 0] - s[0, :, 0] * sites[0, 1]) > 0
    assert np.all(sagnac[0, east & visible] < 0) and np.all(sagnac[0, ~east & visible] > 0)
    # Receiver on the rotation axis: the term vanishes for every satellite.
    assert np.abs(sagnac[3]).max() < 1e-3
    # Omega = 0 frame reproduces the non-rotating light time.
    still = Ellipsoid("still", WGS84.a_m, WGS84.f, WGS84.gm_m3_s2, 0.0)
    g_still = light_time_geometry(t_rx, sites, np.zeros_like(sites), c, ell=still)
    assert np.abs(g_still.range_m - rho0).max() < 1e-6


def test_grid_path_matches_direct_ephemeris():
    """Many distinct reception times (1 s node grid) and repeated times (gather)."""
    c = default_constellation().subset(["G05", "R11", "G30"])
    pos, vel = _receivers(400, seed=3)
    t = DEFAULT_TOA_GPS_S + np.linspace(0.0, 200.0, 400)
    for tt in (t, np.repeat(t[:20], 20)):
        g = light_time_geometry(tt, pos, vel, c)
        p, v = sat_state_at_reception_frame(tt, g.tau_s, c, g.range_rate_m_s / C_M_S)
        assert np.abs(p - g.sat_pos_ecef_m).max() < 1e-6
        assert np.abs(v - g.sat_vel_ecef_m_s).max() < 1e-6


def test_input_validation():
    c = gps_constellation()
    pos, vel = _receivers(3)
    with pytest.raises(ValueError, match="rx_pos_ecef_m"):
        light_time_geometry(0.0, pos[:, :2], vel, c)
    with pytest.raises(ValueError, match="rx_vel_ecef_m_s"):
        light_time_geometry(0.0, pos, vel[:2], c)
    with pytest.raises(ValueError, match="t_rx_gps_s"):
        light_time_geometry(np.zeros(4), pos, vel, c)
    with pytest.raises(ValueError, match="t_rx_gps_s"):
        light_time_geometry(np.inf, pos, vel, c)
    with pytest.raises(ValueError, match="rx_pos_ecef_m"):
        light_time_geometry(0.0, np.full(3, np.nan), vel[0], c)
    with pytest.raises(ValueError, match="constellation"):
        light_time_geometry(0.0, pos, vel, None)
    with pytest.raises(ValueError, match="ell"):
        light_time_geometry(0.0, pos, vel, c, ell="mars")
