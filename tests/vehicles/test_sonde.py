"""Radiosonde flight (seed 004): standard atmosphere, ascent/burst/descent, wind drift, gusts."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest
import scipy.linalg
from scipy import stats

from filters.models import Singer
from sitl.atmosphere_std import RHO0_KG_M3, us76, us76_density
from vehicles.sonde import (
    ASCENT,
    DESCENT,
    LANDED,
    SondeFlight,
    SondeParams,
    axis_discretisation,
    descent_speed_m_s,
    spawn_rngs,
)
from tests.helpers import fisher_z_ok, variance_ok

# U.S. Standard Atmosphere 1976 (NOAA-S/T 76-1562), Table I, geometric altitude:
# z (m), temperature (K), pressure (Pa), density (kg/m^3).  At 86 km the tabulated
# temperature is the kinetic one (186.87 K); T_M = 186.946 K.
US76_TABLE = [
    (-5_000.0, 320.676, 1.77762e5, 1.9311),
    (0.0, 288.150, 1.01325e5, 1.2250),
    (1_000.0, 281.651, 8.9876e4, 1.1117),
    (5_000.0, 255.676, 5.4048e4, 7.3643e-1),
    (11_000.0, 216.774, 2.2700e4, 3.6480e-1),
    (20_000.0, 216.650, 5.5293e3, 8.8910e-2),
    (32_000.0, 228.490, 8.8906e2, 1.3555e-2),
    (50_000.0, 270.650, 7.9779e1, 1.0269e-3),
    (70_000.0, 219.585, 5.2209, 8.2829e-5),
    (86_000.0, 186.946, 3.7338e-1, 6.958e-6),
]


# ---------------------------------------------------------------------------
# standard atmosphere


@pytest.mark.parametrize("z, t_k, p_pa, rho", US76_TABLE)
def test_us76_matches_the_table(z, t_k, p_pa, rho):
    a = us76(z)
    assert a.temperature_k == pytest.approx(t_k, rel=2e-5)
    assert a.pressure_pa == pytest.approx(p_pa, rel=1e-4)
    assert a.density_kg_m3 == pytest.approx(rho, rel=1e-4)


def test_us76_vectorised_and_range_checked():
    z = np.array([[0.0, 11_000.0], [20_000.0, 32_000.0]])
    np.testing.assert_allclose(us76_density(z), [[1.2250, 0.36480], [0.088910, 0.013555]], rtol=1e-4)
    assert RHO0_KG_M3 == pytest.approx(1.2250, rel=1e-5)
    # continuity at the layer boundaries (geopotential 11, 20, 32, 47 km')
    for h_gp in (11_000.0, 20_000.0, 32_000.0, 47_000.0, 51_000.0, 71_000.0):
        z_b = 6_356_766.0 * h_gp / (6_356_766.0 - h_gp)
        lo, hi = us76_density(z_b - 1e-6), us76_density(z_b + 1e-6)
        assert hi == pytest.approx(lo, rel=1e-9)
    for bad in (-6_000.0, 90_000.0, np.nan):
        with pytest.raises(ValueError, match="z_m"):
            us76(bad)


def test_descent_speed_scales_with_density():
    h = np.array([0.0, 1_000.0, 5_000.0, 12_345.0, 25_000.0, 34_999.0])
    expect = 5.0 * np.sqrt(RHO0_KG_M3 / us76_density(h))
    np.testing.assert_allclose(descent_speed_m_s(h, 5.0), expect, rtol=1e-6)
    hh = np.linspace(0.0, 40_000.0, 401)
    assert np.all(np.diff(descent_speed_m_s(hh)) > 0.0)  # faster where the air is thinner
    assert 35.0 < descent_speed_m_s(30_000.0) < 45.0  # about 8x the sea-level speed at 30 km


# ---------------------------------------------------------------------------
# discretisation


def test_axis_discretisation_is_singer_without_relaxation_and_van_loan_otherwise():
    beta, sig, T = 0.12, 0.15, 1.0
    phi, gam, q, lo = axis_discretisation(0.0, beta, sig, T)
    s = Singer(alpha_1_s=beta, sigma_a_m_s2=sig, ndim_pos=1)
    np.testing.assert_allclose(phi, s.F(None, T), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(q, s.Q(T), rtol=1e-9, atol=1e-18)
    np.testing.assert_allclose(lo @ lo.T, q, rtol=1e-9, atol=1e-18)
    np.testing.assert_array_equal(gam, 0.0)
    # with relaxation k: Phi = expm(A T), Q = int_0^T Phi(s) g g' Phi(s)' ds (trapezoid),
    # Gamma = int_0^T Phi(s) b ds; the a_g marginal is the seed's Gauss-Markov step
    k = 0.1
    a = np.array([[0.0, 1.0, 0.0], [0.0, -k, 1.0], [0.0, 0.0, -beta]])
    phi, gam, q, lo = axis_discretisation(k, beta, sig, T)
    np.testing.assert_allclose(phi, scipy.linalg.expm(a * T), rtol=1e-12)
    ss = np.linspace(0.0, T, 4001)
    lam, vec = np.linalg.eig(a)  # distinct eigenvalues 0, -k, -beta: Phi(s) = V e^{lam s} V^-1
    ph = np.real(np.einsum("ij,sj,jk->sik", vec, np.exp(np.outer(ss, lam)), np.linalg.inv(vec)))
    np.testing.assert_allclose(ph[-1], scipy.linalg.expm(a * T), rtol=1e-10, atol=1e-14)
    g = ph[:, :, 2] * math.sqrt(2 * beta) * sig
    qn = np.trapezoid(g[:, :, None] * g[:, None, :], ss, axis=0)
    np.testing.assert_allclose(q, qn, rtol=1e-6, atol=1e-14)
    np.testing.assert_allclose(gam, np.trapezoid(ph[:, :, 1] * k, ss, axis=0), rtol=1e-6, atol=1e-14)
    assert phi[2, 2] == pytest.approx(math.exp(-beta * T), rel=1e-13)
    assert q[2, 2] == pytest.approx(sig**2 * (1 - math.exp(-2 * beta * T)), rel=1e-12)
    np.testing.assert_allclose(lo @ lo.T, q, rtol=1e-9, atol=1e-16)


# ---------------------------------------------------------------------------
# flight phases


@pytest.fixture(scope="module")
def batch_flight():
    f = SondeFlight(np.random.default_rng(404), batch_shape=(24,))
    return f, f.simulate(until_landed=True)


def test_burst_altitudes_are_uniform_in_the_range():
    f = SondeFlight(np.random.default_rng(1), batch_shape=(400,))
    b = f.burst_alt_m
    assert b.min() >= 25_000.0 and b.max() <= 35_000.0
    assert stats.kstest((b - 25_000.0) / 10_000.0, "uniform").pvalue > 1e-3
    f2 = SondeFlight(np.random.default_rng(1), batch_shape=(400,), params=SondeParams(burst_alt_range_m=(28e3, 30e3)))
    assert f2.burst_alt_m.min() >= 28e3 and f2.burst_alt_m.max() <= 30e3


@pytest.mark.slow
def test_ascent_burst_descent_landing(batch_flight):
    f, tr = batch_flight
    ph = tr.phase
    assert np.all(np.diff(ph, axis=0) >= 0)  # ascent -> descent -> landed, never back
    assert np.all(ph[-1] == LANDED)
    t = tr.t_gps_s - tr.t_gps_s[0]
    k_burst = np.argmax(ph == DESCENT, axis=0)
    h0 = tr.alt_m[0]
    # mean ascent rate 5 m/s (gusts average out over ~1.5 h)
    rate = (tr.alt_m[k_burst, np.arange(24)] - h0) / t[k_burst]
    np.testing.assert_allclose(rate, 5.0, rtol=0.01)
    # the sonde bursts at its drawn altitude (within one step of climb)
    np.testing.assert_allclose(tr.alt_m.max(axis=0), f.burst_alt_m, atol=20.0)
    assert np.all(np.where(ph == ASCENT, tr.alt_m, 0.0) < f.burst_alt_m)
    # after landing: on the ground at the launch height, at rest, not moving
    landed = ph == LANDED
    np.testing.assert_array_equal(tr.alt_m[landed], np.broadcast_to(h0, ph.shape)[landed])
    assert np.all(tr.vel_ecef_m_s[landed] == 0.0) and np.all(tr.acc_ecef_m_s2[landed] == 0.0)
    np.testing.assert_array_equal(tr.pos_ecef_m[-1], tr.pos_ecef_m[-2])
    # descent lasts ~40-50 min from 25-35 km with 5 m/s at sea level
    k_land = np.argmax(landed, axis=0)
    assert np.all((t[k_land] - t[k_burst] > 2000.0) & (t[k_land] - t[k_burst] < 3300.0))


@pytest.mark.slow
def test_descent_speed_follows_the_density(batch_flight):
    _, tr = batch_flight
    d = (tr.phase == DESCENT) & (tr.alt_m < 24_000.0)  # past the burst transient
    h, vu = tr.alt_m[d], tr.vel_enu_m_s[..., 2][d]
    target = descent_speed_m_s(h, 5.0)
    # binned: the mean sink rate matches sqrt(rho0/rho) within 3 % and grows with altitude
    bins = np.arange(0.0, 24_001.0, 3_000.0)
    idx = np.digitize(h, bins)
    means = np.array([np.mean(-vu[idx == i]) for i in range(1, bins.size)])
    expect = np.array([np.mean(target[idx == i]) for i in range(1, bins.size)])
    np.testing.assert_allclose(means, expect, rtol=0.03)
    assert np.all(np.diff(means) > 0.0)
    assert means[-1] > 2.5 * means[0]


def test_default_flight_reaches_250_km_and_is_fast():
    # the lowest burst of the range (25 km) is the shortest flight: it must still get there
    for burst in (25_000.0, None):
        f = SondeFlight(spawn_rngs(2024, 1), burst_alt_m=burst)
        tr = f.simulate(until_landed=True)
        assert tr.ground_range_m.max() >= 250_000.0, (burst, tr.ground_range_m.max())
        assert tr.phase[-1, 0] == LANDED
    f = SondeFlight(np.random.default_rng(3))
    f.simulate(10)  # compile/warm up
    t0 = time.perf_counter()
    tr = f.simulate(7200)  # 2 h at 1 Hz
    elapsed = time.perf_counter() - t0
    assert len(tr) == 7201 and tr.pos_ecef_m.shape == (7201, 3)
    assert elapsed < 0.5, elapsed


@pytest.mark.slow
def test_ground_range_is_the_great_circle_distance(batch_flight):
    _, tr = batch_flight
    # chord between the sub-sonde point and the launch point on the sphere vs ECEF chord at h0
    from sitl.geodesy import geodetic_to_ecef

    k = len(tr) // 2
    sub = geodetic_to_ecef(tr.lat_rad[k], tr.lon_rad[k], tr.alt_m[0])
    chord = np.linalg.norm(sub - tr.launch_pos_ecef_m, axis=-1)
    arc = tr.ground_range_m[k]
    assert np.all(arc > 50_000.0)
    np.testing.assert_allclose(arc, chord, rtol=4e-3)  # arc - chord ~ d^3/(24 R^2) and the sphere
    np.testing.assert_array_equal(tr.ground_range_m[0], 0.0)


# ---------------------------------------------------------------------------
# wind response and gusts


def test_velocity_relaxes_to_the_wind_with_time_constant_1_over_p1():
    # constant wind, no gusts: v(t) = w (1 - exp(-p1 t)) exactly (exact discretisation)
    p = SondeParams(p1_1_s=0.07, sigma_a_m_s2=0.0, sigma_a_vertical_m_s2=0.0, wind_alt_m=(0.0,),
                    wind_speed_m_s=(20.0,), wind_from_rad=math.radians(300.0))
    tr = SondeFlight(np.random.default_rng(0), params=p, dt_s=2.0).simulate(100)
    t = tr.t_gps_s - tr.t_gps_s[0]
    w = 20.0 * np.array([math.sin(math.radians(120.0)), math.cos(math.radians(120.0))])
    expect = w * (1.0 - np.exp(-0.07 * t))[:, None]
    np.testing.assert_allclose(tr.vel_enu_m_s[:, :2], expect, atol=1e-9)
    np.testing.assert_allclose(tr.vel_enu_m_s[:, 2], 5.0, atol=1e-12)


@pytest.mark.slow
def test_gust_acceleration_is_the_seed_gauss_markov_process():
    p = SondeParams()
    beta = p.p1_1_s + p.p2_1_s
    f = SondeFlight(np.random.default_rng(77), batch_shape=(300,))
    tr = f.simulate(1500)
    a = tr.gust_acc_enu_m_s2  # (T, B, 3)
    sig = np.array([p.sigma_a_m_s2, p.sigma_a_m_s2, p.sigma_a_vertical_m_s2])
    ks = np.arange(0, 1500 - 10, 60)  # 60 s apart: corr exp(-7.2) ~ 7e-4, effectively independent
    for ax in range(3):
        x = a[ks, :, ax].ravel()
        assert variance_ok(x, sig[ax] ** 2), ax
        assert not variance_ok(x, (1.15 * sig[ax]) ** 2)  # a 15 % wrong sigma is rejected
        for lag in (1, 4, 10):
            y = a[ks + lag, :, ax].ravel()
            assert fisher_z_ok(x, y, math.exp(-beta * lag)), (ax, lag)
        y = a[ks + 4, :, ax].ravel()
        assert not fisher_z_ok(x, y, math.exp(-p.p1_1_s * 4))  # width p1 alone is rejected


def test_gust_velocity_variance_with_constant_wind():
    # dv/dt = -p1 v + a_g, a_g Gauss-Markov(beta, sigma): var v = sigma^2 / (p1 (p1 + beta))
    p = SondeParams(wind_alt_m=(0.0,), wind_speed_m_s=(15.0,), wind_from_rad=0.0)
    beta = p.p1_1_s + p.p2_1_s
    tr = SondeFlight(np.random.default_rng(5), params=p, batch_shape=(300,)).simulate(1400)
    w_north = -15.0
    ks = np.arange(200, 1401, 100)  # 100 s apart, past the release transient
    dv = (tr.vel_enu_m_s[ks, :, 1] - w_north).ravel()
    var = p.sigma_a_m_s2**2 / (p.p1_1_s * (p.p1_1_s + beta))
    assert variance_ok(dv, var)
    assert abs(np.mean(dv)) < 4.0 * math.sqrt(var / dv.size)


def test_kinematics_are_consistent_in_ecef():
    # noise-free flight at 0.1 s: central differences of position/velocity give velocity/acceleration
    p = SondeParams(sigma_a_m_s2=0.0, sigma_a_vertical_m_s2=0.0)
    dt = 0.1
    tr = SondeFlight(np.random.default_rng(0), params=p, dt_s=dt, burst_alt_m=3_000.0).simulate(until_landed=True)
    same = (tr.phase[2:] == tr.phase[:-2])
    fd_v = (tr.pos_ecef_m[2:] - tr.pos_ecef_m[:-2]) / (2 * dt)
    fd_a = (tr.vel_ecef_m_s[2:] - tr.vel_ecef_m_s[:-2]) / (2 * dt)
    assert np.abs(fd_v - tr.vel_ecef_m_s[1:-1])[same].max() < 2e-3
    assert np.abs(fd_a - tr.acc_ecef_m_s2[1:-1])[same].max() < 1e-3
    # speed in ECEF equals speed in ENU; the ENU acceleration is the model's
    np.testing.assert_allclose(np.linalg.norm(tr.vel_ecef_m_s, axis=-1), np.linalg.norm(tr.vel_enu_m_s, axis=-1),
                               rtol=1e-12, atol=1e-12)


# ---------------------------------------------------------------------------
# batching, determinism, backends


def _fields_equal(a, b, exact=True):
    for name in ("pos_ecef_m", "vel_ecef_m_s", "acc_ecef_m_s2", "alt_m", "phase", "gust_acc_enu_m_s2",
                 "ground_range_m"):
        x, y = getattr(a, name), getattr(b, name)
        if exact:
            np.testing.assert_array_equal(x, y, err_msg=name)
        else:
            np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-6, err_msg=name)


@pytest.mark.parametrize("backend", ["numba", "numpy"])
def test_batch_of_four_equals_four_single_runs(backend):
    lat = np.radians([55.9, 56.1, 50.0, 60.0])
    lon = np.radians([37.5, 37.6, 30.0, 40.0])
    n_steps = 2400 if backend == "numba" else 400
    batch = SondeFlight(spawn_rngs(99, 4), launch_lat_rad=lat, launch_lon_rad=lon, launch_h_m=150.0,
                        backend=backend).simulate(n_steps)
    for i, g in enumerate(spawn_rngs(99, 4)):
        one = SondeFlight([g], launch_lat_rad=lat[i], launch_lon_rad=lon[i], launch_h_m=150.0,
                          backend=backend).simulate(n_steps)
        _fields_equal(batch.sonde(i), one.sonde(0))


def test_step_equals_simulate_and_seeds_repeat():
    a = SondeFlight(spawn_rngs(7, 3))
    states = [a.state()] + [a.step() for _ in range(1500)]  # crosses a noise block boundary
    b = SondeFlight(spawn_rngs(7, 3)).simulate(1500)
    np.testing.assert_array_equal(np.stack([s.pos_ecef_m for s in states]), b.pos_ecef_m)
    np.testing.assert_array_equal(np.stack([s.acc_ecef_m_s2 for s in states]), b.acc_ecef_m_s2)
    np.testing.assert_array_equal([s.t_gps_s for s in states], b.t_gps_s)
    c = SondeFlight(spawn_rngs(8, 3)).simulate(1500)
    assert not np.allclose(c.pos_ecef_m[-1], b.pos_ecef_m[-1])
    # until_landed then more steps = the same flight as one long simulate
    d = SondeFlight(spawn_rngs(7, 3))
    d.simulate(700)
    e = d.simulate(800)
    np.testing.assert_array_equal(e.pos_ecef_m, b.pos_ecef_m[700:])


def test_numba_and_numpy_backends_agree():
    a = SondeFlight(spawn_rngs(11, 2), backend="numba", burst_alt_m=6_000.0).simulate(until_landed=True)
    b = SondeFlight(spawn_rngs(11, 2), backend="numpy", burst_alt_m=6_000.0).simulate(until_landed=True)
    assert len(a) == len(b)
    _fields_equal(a, b, exact=False)


# ---------------------------------------------------------------------------
# parameters


@pytest.mark.parametrize("kwargs, name", [
    (dict(ascent_rate_m_s=-5.0), "ascent_rate_m_s"),
    (dict(descent_rate_sl_m_s=0.0), "descent_rate_sl_m_s"),
    (dict(p1_1_s=0.0), "p1_1_s"),
    (dict(p2_1_s=float("nan")), "p2_1_s"),
    (dict(sigma_a_m_s2=-0.1), "sigma_a_m_s2"),
    (dict(sigma_a_vertical_m_s2="x"), "sigma_a_vertical_m_s2"),
    (dict(vertical_relax_rate_1_s=-1.0), "vertical_relax_rate_1_s"),
    (dict(burst_alt_range_m=(35e3, 25e3)), "burst_alt_range_m"),
    (dict(burst_alt_range_m=5.0), "burst_alt_range_m"),
    (dict(wind_alt_m=(0.0, 0.0), wind_speed_m_s=(1.0, 2.0), wind_from_rad=0.0), "wind_alt_m"),
    (dict(wind_alt_m=(0.0, 1.0), wind_speed_m_s=(1.0,), wind_from_rad=0.0), "wind_speed_m_s"),
    (dict(wind_alt_m=(0.0, 1.0), wind_speed_m_s=(1.0, 2.0), wind_from_rad=(0.0, 1.0, 2.0)), "wind_from_rad"),
])
def test_bad_parameters_raise_naming_them(kwargs, name):
    with pytest.raises(ValueError, match=name):
        SondeParams(**kwargs)


@pytest.mark.parametrize("kwargs, name", [
    (dict(rng="seed"), "rng"),
    (dict(rng=[np.random.default_rng(1)] * 2, batch_shape=(3,)), "rng"),
    (dict(dt_s=0.0), "dt_s"),
    (dict(launch_lat_rad=56.0), "launch_lat_rad"),
    (dict(launch_h_m=np.nan), "launch_h_m"),
    (dict(t0_gps_s=float("inf")), "t0_gps_s"),
    (dict(burst_alt_m=-3.0), "burst_alt_m"),
    (dict(backend="cuda"), "backend"),
    (dict(params="default"), "params"),
])
def test_bad_flight_arguments_raise_naming_them(kwargs, name):
    kw = dict(rng=np.random.default_rng(0))
    kw.update(kwargs)
    rng = kw.pop("rng")
    with pytest.raises(ValueError, match=name):
        SondeFlight(rng, **kw)
    f = SondeFlight(np.random.default_rng(0))
    with pytest.raises(ValueError, match="n_steps"):
        f.simulate(-1)
