"""Aerological radar (seed 004): AR(1) errors, coverage, tracking loss, AER <-> ECEF and Jacobians."""
from __future__ import annotations

import math

import numpy as np
import pytest

from sitl.geodesy import ecef_to_aer, enu_to_ecef, geodetic_to_ecef
from sitl.radio.radar import (
    Radar,
    RadarParams,
    aer_cov_to_ecef,
    aer_to_ecef_jacobian,
    ar1_coefficients,
    ecef_to_aer_jacobian,
    radar_aer_to_ecef,
)
from tests.helpers import fisher_z_ok, variance_ok

LAT, LON, H = math.radians(55.93), math.radians(37.52), 190.0
SITE = geodetic_to_ecef(LAT, LON, H)
T0 = 1_419_724_800.0


def enu_point(e, n, u):
    return enu_to_ecef(np.stack(np.broadcast_arrays(e, n, u), -1), LAT, LON, H)


def make(rng, params=None, batch_shape=None):
    return Radar(rng, site_lat_rad=LAT, site_lon_rad=LON, site_h_m=H, params=params, batch_shape=batch_shape)


def wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


def run(radar, times, pos, vel=None):
    return [radar.step(t, pos, vel) for t in times]


@pytest.fixture(scope="module")
def error_series():
    """Errors of 400 targets over 301 epochs 1 s apart, then 40 epochs 3 s apart."""
    p = RadarParams(gamma_range_1_s=0.05, gamma_az_1_s=0.1, gamma_el_1_s=0.2)
    B = 400
    radar = make(np.random.default_rng(31), p, (B,))
    pos = np.broadcast_to(enu_point(30_000.0, 40_000.0, 12_000.0), (B, 3))
    times = np.concatenate([T0 + np.arange(301.0), T0 + 300.0 + 3.0 * np.arange(1, 41)])
    ms = run(radar, times, pos)
    err = np.stack([np.stack([m.slant_range_m - m.true_range_m, wrap(m.az_rad - m.true_az_rad),
                              m.el_rad - m.true_el_rad], -1) for m in ms])  # (T, B, 3)
    return p, ms, err


def test_measurement_is_truth_plus_error(error_series):
    p, ms, _ = error_series
    for m in ms[:3]:
        np.testing.assert_allclose(m.slant_range_m, m.true_range_m + m.error[:, 0], rtol=0, atol=1e-8)
        np.testing.assert_allclose(wrap(m.az_rad - m.true_az_rad - m.error[:, 1]), 0.0, atol=1e-12)
        assert np.all((m.az_rad >= 0) & (m.az_rad < 2 * math.pi))
        np.testing.assert_array_equal(m.var_range_m2, p.sigma_range_m**2)
        np.testing.assert_array_equal(m.var_az_rad2, p.sigma_az_rad**2)
        np.testing.assert_array_equal(m.var_el_rad2, p.sigma_el_rad**2)
        assert np.all(m.range_valid & m.angles_valid & m.in_range & ~m.tracking_lost)
    # the truth is ecef_to_aer of the target from the site
    az, el, d = ecef_to_aer(SITE, enu_point(30_000.0, 40_000.0, 12_000.0))
    assert ms[0].true_range_m[0] == pytest.approx(d) and ms[0].true_az_rad[0] == pytest.approx(az)
    assert ms[0].true_el_rad[0] == pytest.approx(el)


def test_ar1_errors_have_the_stationary_variance_and_lag_correlation(error_series):
    p, _, err = error_series
    sig, gam = p.sigma, p.gamma_1_s
    ks = np.arange(0, 291, 40)  # 40 s apart (corr <= e^-2 between samples, pooled over 400 targets)
    for ax in range(3):
        x0 = err[0, :, ax]  # stationary start
        assert variance_ok(x0, sig[ax] ** 2)
        x = err[ks, :, ax].ravel()
        assert variance_ok(err[ks[-1], :, ax], sig[ax] ** 2)
        assert variance_ok(x, sig[ax] ** 2, alpha=1e-4)
        assert not variance_ok(x, (1.2 * sig[ax]) ** 2)
        y = err[ks + 1, :, ax].ravel()
        assert fisher_z_ok(x, y, math.exp(-gam[ax] * 1.0)), ax  # lag 1 at T = 1 s
        assert not fisher_z_ok(x, y, math.exp(-2.0 * gam[ax]))
        y = err[ks + 10, :, ax].ravel()
        assert fisher_z_ok(x, y, math.exp(-gam[ax] * 10.0)), ax
        # after the step change to T = 3 s: lag-1 correlation exp(-3 gamma)
        k3 = np.arange(301, 340, 13)
        assert fisher_z_ok(err[k3, :, ax].ravel(), err[k3 + 1, :, ax].ravel(), math.exp(-3.0 * gam[ax])), ax
    mu, v = ar1_coefficients(sig, gam, 2.0)
    np.testing.assert_allclose(mu, np.exp(-2.0 * gam))
    np.testing.assert_allclose(v**2, sig**2 * (1 - mu**2))


def test_range_limit_and_elevation_mask():
    radar = make(np.random.default_rng(2), batch_shape=(4,))
    # 249 km and 251 km slant at 20 km height (north), and one below the horizon
    far = [enu_point(0.0, n, 20_000.0) for n in (248_000.0, 252_000.0)]
    pos = np.stack([far[0], far[1], enu_point(1_000.0, 50_000.0, -500.0), enu_point(0.0, 10.0, 100.0)])
    m = radar.step(T0, pos)
    assert m.true_range_m[0] < 250_000.0 < m.true_range_m[1]
    np.testing.assert_array_equal(m.in_range, [True, False, True, True])
    np.testing.assert_array_equal(m.range_valid, [True, False, False, True])
    np.testing.assert_array_equal(m.angles_valid, [True, False, False, True])
    assert np.isnan(m.slant_range_m[1]) and np.isnan(m.az_rad[1]) and np.isnan(m.el_rad[2])
    assert np.all(np.isfinite([m.slant_range_m[0], m.az_rad[0], m.el_rad[0], m.slant_range_m[3]]))
    m2 = make(np.random.default_rng(2), RadarParams(max_range_m=300_000.0), (4,)).step(T0, pos)
    np.testing.assert_array_equal(m2.range_valid, [True, True, False, True])


def test_tracking_loss_schedule_blanks_angles_keeps_range():
    p = RadarParams(loss_schedule=[(T0 + 10.0, T0 + 20.0), (T0 + 50.0, T0 + 51.0)])
    radar = make(np.random.default_rng(4), p)
    times = T0 + np.arange(60.0)
    ms = run(radar, times, enu_point(2_000.0, 3_000.0, 1_000.0), np.array([10.0, 0.0, 5.0]))
    lost = np.array([m.tracking_lost for m in ms])
    expect = ((times >= T0 + 10) & (times < T0 + 20)) | (times == T0 + 50)
    np.testing.assert_array_equal(lost, expect)
    np.testing.assert_array_equal([m.angles_valid for m in ms], ~expect)
    assert all(np.isnan(m.az_rad) and np.isnan(m.el_rad) for m, e in zip(ms, expect) if e)
    assert all(np.isfinite(m.slant_range_m) and m.range_valid for m in ms)


def test_random_tracking_loss_rate_and_angular_rate_dependence():
    lam, dur = 0.02, 20.0
    p = RadarParams(loss_rate_1_s=lam, loss_mean_duration_s=dur, loss_ang_rate_ref_rad_s=math.radians(1.0))
    B, K = 300, 800
    pos = np.broadcast_to(enu_point(20_000.0, 0.0, 5_000.0), (B, 3))
    radar = make(np.random.default_rng(8), p, (B,))
    lost = np.array([m.tracking_lost for m in run(radar, T0 + np.arange(K), pos, np.zeros((B, 3)))])
    ps, pe = -math.expm1(-lam), -math.expm1(-1.0 / dur)
    frac = lost[200:].mean()  # stationary fraction of a two-state chain: ps / (ps + pe)
    assert frac == pytest.approx(ps / (ps + pe), abs=0.02)
    # mean loss duration: runs of lost epochs ~ geometric with mean 1/pe
    runs = []
    for b in range(B):
        x = np.diff(np.concatenate([[0], lost[:, b].astype(int), [0]]))
        s, e = np.flatnonzero(x == 1), np.flatnonzero(x == -1)
        runs += list((e - s)[(s > 0) & (e < K)])
    assert np.mean(runs) == pytest.approx(1.0 / pe, rel=0.1)
    # a sonde just after launch, 500 m away, crossing at 15 m/s: omega = 0.03 rad/s > 1 deg/s
    near = np.broadcast_to(enu_point(0.0, 500.0, 100.0), (B, 3))
    v_side = np.broadcast_to(np.array(enu_point(15.0, 500.0, 100.0) - enu_point(0.0, 500.0, 100.0)), (B, 3))
    radar2 = make(np.random.default_rng(8), p, (B,))
    lost2 = np.array([m.tracking_lost for m in run(radar2, T0 + np.arange(K), near, v_side)])
    assert lost2[200:].mean() > frac + 0.2
    # no random process by default
    radar3 = make(np.random.default_rng(8), batch_shape=(B,))
    assert not any(m.tracking_lost.any() for m in run(radar3, T0 + np.arange(50), near, v_side))


def test_aer_to_ecef_round_trip():
    rng = np.random.default_rng(5)
    pts = enu_point(rng.uniform(-2e5, 2e5, 200), rng.uniform(-2e5, 2e5, 200), rng.uniform(0, 35e3, 200))
    az, el, d = ecef_to_aer(SITE, pts)
    np.testing.assert_allclose(radar_aer_to_ecef(az, el, d, SITE), pts, rtol=0, atol=1e-6)


def test_jacobians_match_finite_differences():
    rng = np.random.default_rng(6)
    az, el, d = rng.uniform(0, 2 * math.pi, 50), rng.uniform(0.02, 1.4, 50), rng.uniform(1e3, 2.5e5, 50)
    J = aer_to_ecef_jacobian(az, el, d, SITE)
    assert J.shape == (50, 3, 3)
    hs = (1e-7, 1e-7, 1e-2)
    x = np.stack([az, el, d], -1)
    for i, h in enumerate(hs):
        xp, xm = x.copy(), x.copy()
        xp[:, i] += h
        xm[:, i] -= h
        fd = (radar_aer_to_ecef(*xp.T, SITE) - radar_aer_to_ecef(*xm.T, SITE)) / (2 * h)
        np.testing.assert_allclose(J[:, :, i], fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())
    pos = radar_aer_to_ecef(az, el, d, SITE)
    Ji = ecef_to_aer_jacobian(pos, SITE)
    for i in range(3):
        dp = np.zeros(3)
        dp[i] = 1e-2
        a1, e1, d1 = ecef_to_aer(SITE, pos + dp)
        a0, e0, d0 = ecef_to_aer(SITE, pos - dp)
        fd = np.stack([wrap(a1 - a0), e1 - e0, d1 - d0], -1) / 2e-2
        np.testing.assert_allclose(Ji[:, :, i], fd, rtol=1e-5, atol=1e-12)
    np.testing.assert_allclose(Ji @ J, np.broadcast_to(np.eye(3), J.shape), atol=1e-9)
    # covariance of a radar fix: J diag(var) J'; at long range the angles dominate
    var = np.array([math.radians(0.1) ** 2, math.radians(0.1) ** 2, 15.0**2])
    P = aer_cov_to_ecef(az, el, d, SITE, var)
    np.testing.assert_allclose(P, J @ np.diag(var) @ np.swapaxes(J, -1, -2), rtol=1e-12)
    assert np.all(np.linalg.eigvalsh(P) > 0)


def test_batch_equals_loop_with_per_target_streams():
    from vehicles.sonde import spawn_rngs

    p = RadarParams(loss_rate_1_s=0.05)
    pos = np.stack([enu_point(1e3 * i, 2e4, 5e3) for i in range(4)])
    vel = np.tile([3.0, 4.0, 5.0], (4, 1))
    batch = run(make(spawn_rngs(12, 4), p), T0 + np.arange(100.0), pos, vel)
    for i, g in enumerate(spawn_rngs(12, 4)):
        one = run(make([g], p), T0 + np.arange(100.0), pos[i:i + 1], vel[i:i + 1])
        for mb, m1 in zip(batch, one):
            np.testing.assert_array_equal(mb.error[i], m1.error[0])
            np.testing.assert_array_equal(mb.az_rad[i], m1.az_rad[0])
            np.testing.assert_array_equal(mb.tracking_lost[i], m1.tracking_lost[0])


@pytest.mark.parametrize("kwargs, name", [
    (dict(sigma_range_m=-1.0), "sigma_range_m"),
    (dict(sigma_az_rad=float("nan")), "sigma_az_rad"),
    (dict(gamma_el_1_s=0.0), "gamma_el_1_s"),
    (dict(max_range_m=-250e3), "max_range_m"),
    (dict(el_mask_rad=2.0), "el_mask_rad"),
    (dict(loss_schedule=[(10.0, 5.0)]), "loss_schedule"),
    (dict(loss_schedule=[1.0, 2.0]), "loss_schedule"),
    (dict(loss_rate_1_s=-0.1), "loss_rate_1_s"),
    (dict(loss_mean_duration_s=0.0), "loss_mean_duration_s"),
])
def test_bad_parameters_raise_naming_them(kwargs, name):
    with pytest.raises(ValueError, match=name):
        RadarParams(**kwargs)


def test_bad_arguments_raise_naming_them():
    with pytest.raises(ValueError, match="site_lat_rad"):
        Radar(np.random.default_rng(0), site_lat_rad=55.9, site_lon_rad=LON, site_h_m=H)
    with pytest.raises(ValueError, match="rng"):
        Radar(42, site_lat_rad=LAT, site_lon_rad=LON, site_h_m=H)
    with pytest.raises(ValueError, match="rng"):
        make([np.random.default_rng(0)], batch_shape=(3,))
    r = make(np.random.default_rng(0))
    with pytest.raises(ValueError, match="pos_ecef_m"):
        r.step(T0, np.zeros((2, 3)))
    r.step(T0, enu_point(0.0, 1e4, 1e3))
    with pytest.raises(ValueError, match="t_gps_s"):
        r.step(T0, enu_point(0.0, 1e4, 1e3))


def test_track_equals_step_bitwise_with_schedule_and_random_losses():
    from sitl.radio.radar import Radar, RadarParams
    from vehicles.sonde import DEFAULT_LAUNCH_H_M, DEFAULT_LAUNCH_LAT_RAD, DEFAULT_LAUNCH_LON_RAD, SondeFlight, spawn_rngs

    tr = SondeFlight(spawn_rngs(4, 3)).simulate(400)
    prm = RadarParams(loss_rate_1_s=0.01, loss_schedule=((tr.t_gps_s[30], tr.t_gps_s[90]),))
    kw = dict(site_lat_rad=DEFAULT_LAUNCH_LAT_RAD, site_lon_rad=DEFAULT_LAUNCH_LON_RAD + 0.001,
              site_h_m=DEFAULT_LAUNCH_H_M, params=prm)
    a, b = Radar(spawn_rngs(9, 3), **kw), Radar(spawn_rngs(9, 3), **kw)
    steps = [a.step(tr.t_gps_s[k], tr.pos_ecef_m[k], tr.vel_ecef_m_s[k]) for k in range(len(tr))]
    parts = [b.track(tr.t_gps_s[s], tr.pos_ecef_m[s], tr.vel_ecef_m_s[s]) for s in (slice(0, 150), slice(150, None))]
    for f in parts[0]._fields:
        if f == "site_pos_ecef_m":
            continue
        got = np.concatenate([getattr(p, f) for p in parts])
        want = np.stack([np.asarray(getattr(s, f)) for s in steps])
        assert np.array_equal(got, want, equal_nan=True), f
    assert parts[0].tracking_lost.any() and not parts[0].tracking_lost.all()
    with pytest.raises(ValueError, match="increase"):
        b.track(tr.t_gps_s[:5], tr.pos_ecef_m[:5], tr.vel_ecef_m_s[:5])  # not after the previous step
