"""Beacon (vehicles/beacon.py), beacon link and multilateration (sitl/radio/beacon_link.py).

* the beacon's start point (geodetic: lat 47.3, lon 31), speed band and modes (seed law,
  legs and turns, static, printed: the printed law from the printed point, one per trial);
* link range and range rate against finite differences along RK4 trajectories (sign: > 0
  when the range grows), ranges below 300 km over the seed run (the light-time premise);
* the noise: per-sample variance N / dt returned with the measurements, sample variances
  within chi-square bounds, and the 1/dt scaling;
* multilateration: exact on noise-free data (3 and 5 anchors, the seed's own geometry),
  errors within 3 sigma of its own covariance on noisy data, the mirror choice;
* bad parameters.

Every random draw comes from np.random.default_rng(seed).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.stats

from filters import metrics
from sitl import geodesy
from sitl.radio import beacon_link as bl
from vehicles import beacon, uav
from tests.helpers import chi2_var_bounds


@pytest.fixture(scope="module")
def seed_truth():
    """UAVs and the beacon of the seed example every second over 1000 s (RK4, 0.01 s)."""
    u, b = uav.example_uav_swarm(), beacon.example_beacon("seed")
    out = []
    for t in range(0, 1001):
        out.append((u.step(float(t)), b.step(float(t))))
    return out


# ============================================================================ the beacon


def test_beacon_start_speed_and_modes(seed_truth):
    b0 = seed_truth[0][1]
    assert np.allclose(b0.pos_ecef_m, geodesy.geodetic_to_ecef(math.radians(47.3), math.radians(31.0), 3200.0))
    speed = np.array([np.linalg.norm(bt.vel_ecef_m_s) for _, bt in seed_truth])
    assert 105.0 - 1e-9 <= speed.min() < 105.01 and 124.99 < speed.max() <= 125.0 + 1e-9  # 115 +- 10
    assert max(abs(uav.wrap_pi(bt.heading_rad)) for _, bt in seed_truth) < 1e-9  # north
    legs = beacon.example_beacon("legs", dt_s=0.05)
    psi0 = legs.truth().heading_rad
    tr = legs.step(200.0)
    assert abs(uav.wrap_pi(tr.heading_rad - psi0)) < 1e-9 and abs(tr.speed_m_s - 115.0) < 1e-12
    tr = legs.step(200.0 + 60.0)  # a 90 deg turn at 1.5 deg/s takes 60 s
    assert abs(uav.wrap_pi(tr.heading_rad - psi0 - math.pi / 2)) < 1e-9
    static = beacon.example_beacon("static")
    p0 = static.truth().pos_ecef_m
    assert np.array_equal(static.step(500.0).pos_ecef_m, p0)


def test_beacon_batched_equals_single():
    law = beacon.example_beacon_law()
    lat, lon = math.radians(47.3), math.radians(31.0)
    law2 = uav.SinusoidalLaw(**{f: np.full(2, float(getattr(law, f))) for f in law._FIELDS})
    both = uav.KinematicSwarm(law2, [lat, lat + 0.01], [lon, lon], [3200.0, 3300.0])
    one = beacon.BeaconSwarm(law, lat + 0.01, lon, 3300.0)
    assert np.allclose(both.step(123.0).pos_ecef_m[1], one.step(123.0).pos_ecef_m, rtol=0, atol=1e-9)


def test_printed_beacon_law_start_and_one_per_trial():
    m = uav.paper_to_ecef(uav.PRINTED_START_PAPER_M)
    one = beacon.example_beacon("printed")
    assert np.array_equal(one.truth().pos_ecef_m[0], m)  # the UAVs' printed start point
    law = beacon.printed_beacon_law(1)
    assert np.allclose(law.params()[0], uav.PRINTED_COEFFS["beacon"])
    starts = m + np.array([[0.0, 0.0, 0.0], [30.0, -20.0, 50.0]])
    two = beacon.printed_beacon(starts)
    a = two.track([0.0, 100.0, 400.0])
    b = one.track([0.0, 100.0, 400.0])
    assert np.allclose(a.pos_ecef_m[:, 0], b.pos_ecef_m[:, 0], rtol=0, atol=1e-9)
    # the law depends on eta only weakly: the offset is carried along within a metre in 400 s
    d = a.pos_ecef_m[:, 1] - a.pos_ecef_m[:, 0]
    assert np.max(np.abs(d - (starts[1] - starts[0]))) < 1.0
    assert 80.0 < np.linalg.norm(b.vel_ecef_m_s[1, 0]) < 130.0  # ~ (115 + 10 sin) cos 45 along eta, + the climb


# ============================================================================ the link


def test_range_rate_sign_and_values_against_finite_differences(seed_truth):
    u, b = uav.example_uav_swarm(), beacon.example_beacon("seed")
    h = 0.05
    for t in (10.0, 333.0, 777.0):
        ua, ba = u.step(t - h), b.step(t - h)
        um, bm = u.step(t), b.step(t)
        ub, bb = u.step(t + h), b.step(t + h)
        ra, _ = bl.range_and_rate(ua.pos_ecef_m, ua.vel_ecef_m_s, ba.pos_ecef_m, ba.vel_ecef_m_s)
        rm, rate = bl.range_and_rate(um.pos_ecef_m, um.vel_ecef_m_s, bm.pos_ecef_m, bm.vel_ecef_m_s)
        rb, _ = bl.range_and_rate(ub.pos_ecef_m, ub.vel_ecef_m_s, bb.pos_ecef_m, bb.vel_ecef_m_s)
        fd = (rb - ra) / (2 * h)
        assert np.max(np.abs(fd - rate)) < 1e-4, (t, fd, rate)
        assert np.all(np.sign(fd) == np.sign(rate))
        assert np.allclose(rm, np.linalg.norm(um.pos_ecef_m - bm.pos_ecef_m, axis=-1))
    # explicit sign: a UAV flying straight away from a static beacon sees a positive rate
    r, rr = bl.range_and_rate([1000.0, 0, 0], [50.0, 0, 0], [0.0, 0, 0], [0.0, 0, 0])
    assert r == 1000.0 and rr == 50.0
    # ranges of the seed run stay below 300 km: the premise of neglecting light time
    ranges = np.array([np.linalg.norm(ut.pos_ecef_m - bt.pos_ecef_m, axis=-1) for ut, bt in seed_truth])
    assert ranges.max() < 300e3


@pytest.mark.parametrize("dt_s", [1.0, 0.25])
def test_link_noise_variance_and_chi2(dt_s):
    rng = np.random.default_rng(202)
    cfg = bl.BeaconLinkConfig(dt_s=dt_s)
    U = np.array([[4.0e6, 4.0e6, 3.2e6], [4.01e6, 3.99e6, 3.21e6], [3.98e6, 4.02e6, 3.19e6]])
    V = np.array([[50.0, -60.0, 10.0], [0.0, 100.0, 0.0], [-80.0, 20.0, 5.0]])
    B, VB = np.array([4.1e6, 4.05e6, 3.25e6]), np.array([30.0, 110.0, -3.0])
    n = 20000
    m = bl.measure(rng, U, V, B, VB, cfg, trials_shape=(n,))
    assert m.range_m.shape == (n, 3) and m.var_range_m2.shape == (n, 3)
    assert np.allclose(m.var_range_m2, 25.0 / dt_s, rtol=1e-14, atol=0)
    assert np.allclose(m.var_range_rate_m2_s2, 0.01 / dt_s, rtol=1e-14, atol=0)
    r, rr = bl.range_and_rate(U, V, B, VB)
    lo, hi = chi2_var_bounds(n)
    for err, var in ((m.range_m - r, 25.0 / dt_s), (m.range_rate_m_s - rr, 0.01 / dt_s)):
        ratio = err.var(axis=0, ddof=1) / var
        assert np.all((lo < ratio) & (ratio < hi)), ratio
        assert np.all(np.abs(err.mean(axis=0)) < 4 * math.sqrt(var / n))


def test_psd_to_variance_scales_as_one_over_dt():
    dts = np.array([0.01, 0.1, 0.5, 1.0, 2.0, 10.0])
    v = np.array([bl.psd_to_variance(25.0, dt) for dt in dts])
    assert np.allclose(v * dts, 25.0, rtol=0, atol=1e-12)
    assert bl.psd_to_variance(0.1**2, 1.0) == pytest.approx(0.01)
    assert np.allclose(bl.psd_to_variance(np.array([25.0, 900.0]), 4.0), [6.25, 225.0])


# ============================================================================ multilateration


def _enu_points(pts, lat0=math.radians(30.5), lon0=math.radians(46.0)):
    return np.array([geodesy.enu_to_ecef(np.array(p, float), lat0, lon0, 0.0) for p in pts])


ANCHORS3 = [(-20e3, 0, 3000), (15e3, -10e3, 3500), (5e3, 25e3, 4200)]
ANCHORS5 = ANCHORS3 + [(0, 0, 5000), (-10e3, -20e3, 2500)]
BEACON = (30e3, 40e3, 3200.0)


@pytest.mark.parametrize("anchors", [ANCHORS3, ANCHORS5])
def test_multilateration_exact_on_noise_free_data(anchors):
    U = _enu_points(anchors)
    B = _enu_points([BEACON])[0]
    fix = bl.multilaterate(np.linalg.norm(U - B, axis=-1), U)
    assert np.max(np.abs(fix.pos_ecef_m - B)) < 1e-6
    assert np.max(np.abs(fix.residual_m)) < 1e-6
    assert np.linalg.norm(fix.mirror_pos_ecef_m - B) > 1e3  # the rejected mirror is elsewhere


def test_multilateration_exact_on_the_seed_geometry(seed_truth):
    for k in (0, 500, 1000):
        ut, bt = seed_truth[k]
        r = np.linalg.norm(ut.pos_ecef_m - bt.pos_ecef_m, axis=-1)
        fix = bl.multilaterate(r, ut.pos_ecef_m)
        assert np.max(np.abs(fix.pos_ecef_m - bt.pos_ecef_m)) < 1e-3, k
    # batched over epochs: the same numbers
    U = np.array([seed_truth[k][0].pos_ecef_m for k in (0, 500, 1000)])
    B = np.array([seed_truth[k][1].pos_ecef_m for k in (0, 500, 1000)])
    fix = bl.multilaterate(np.linalg.norm(U - B[:, None], axis=-1), U)
    assert np.max(np.abs(fix.pos_ecef_m - B)) < 1e-3


def test_mirror_choice_follows_the_prior_altitude():
    U = _enu_points(ANCHORS3)
    B = _enu_points([BEACON])[0]
    r = np.linalg.norm(U - B, axis=-1)
    default = bl.multilaterate(r, U)
    h_mirror = geodesy.ecef_to_geodetic(default.mirror_pos_ecef_m)[2]
    flipped = bl.multilaterate(r, U, prior_h_m=h_mirror)
    assert np.allclose(flipped.pos_ecef_m, default.mirror_pos_ecef_m, atol=1e-6)
    assert np.allclose(flipped.mirror_pos_ecef_m, B, atol=1e-6)


@pytest.mark.parametrize("anchors", [ANCHORS3, ANCHORS5])
def test_multilateration_noisy_within_three_sigma_of_its_covariance(anchors):
    rng = np.random.default_rng(77)
    U = _enu_points(anchors)
    B = _enu_points([BEACON])[0]
    n = 3000
    z = np.linalg.norm(U - B, axis=-1) + 5.0 * rng.standard_normal((n, len(anchors)))
    fix = bl.multilaterate(z, U, 25.0)
    e = fix.pos_ecef_m - B
    nees = metrics.nees(e, fix.cov_m2)
    inside = np.mean(nees < scipy.stats.chi2.ppf(0.9973, 3))  # the 3-sigma ellipsoid
    assert inside > 0.99, inside
    sd = np.sqrt(np.diagonal(fix.cov_m2, axis1=-2, axis2=-1))
    assert np.mean(np.all(np.abs(e) < 3 * sd, axis=-1)) > 0.99
    assert 2.8 < nees.mean() < 3.3  # ~ chi2(3): the covariance is neither too small nor too large


# ============================================================================ bad parameters


@pytest.mark.parametrize("make, name", [
    (lambda: bl.psd_to_variance(-1.0, 1.0), "psd_two_sided"),
    (lambda: bl.psd_to_variance(1.0, 0.0), "dt_s"),
    (lambda: bl.BeaconLinkConfig(dt_s=-1.0), "dt_s"),
    (lambda: bl.BeaconLinkConfig(psd_range_m2_s=float("nan")), "psd_range_m2_s"),
    (lambda: bl.measure(np.random, [0, 0, 1e6], [0, 0, 0], [0, 0, 0], [0, 0, 0]), "rng"),
    (lambda: bl.range_and_rate([1.0, 2.0], [0, 0, 0], [0, 0, 0], [0, 0, 0]), "uav_pos_ecef_m"),
    (lambda: bl.range_and_rate([1.0, 2.0, 3.0], [0, 0, 0], [1.0, 2.0, 3.0], [0, 0, 0]), "uav_pos_ecef_m"),
    (lambda: bl.multilaterate([1e4, 1e4], _enu_points(ANCHORS3[:2])), "anchors_pos_ecef_m"),
    (lambda: bl.multilaterate([1e4, 1e4], _enu_points(ANCHORS3)), "range_m"),
    (lambda: bl.multilaterate([1e4, 1e4, 1e4], _enu_points([(0, 0, 0), (1e3, 0, 0), (2e3, 0, 0)])),
     "anchors_pos_ecef_m"),
    (lambda: bl.multilaterate([1e4, 1e4, 1e4], _enu_points(ANCHORS3), 0.0), "var_range_m2"),
    (lambda: bl.multilaterate([1e4, 1e4, 1e4], _enu_points(ANCHORS3), gauss_newton_iterations=-1),
     "gauss_newton_iterations"),
    (lambda: beacon.example_beacon("orbit"), "mode"),
    (lambda: beacon.printed_beacon(np.zeros(3)), "pos0_ecef_m"),
    (lambda: beacon.legs_and_turns(0.0, leg_s=0.0), "leg_s"),
])
def test_bad_parameters_raise_value_error_naming_them(make, name):
    with pytest.raises(ValueError, match=name):
        make()
