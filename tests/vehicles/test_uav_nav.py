"""Onboard GNSS navigation of the UAVs (vehicles/uav_nav.py).

* the PSD -> variance rule: a finely sampled white noise of two-sided PSD N averaged over dt
  has variance N / dt (chi-square bounds), and the configured variances scale as 1/dt;
* the three satellites: the analytic Kepler propagation equals an RK4 and a solve_ivp
  integration of the two-body ODE; they stay above the mask for the whole run;
* the clock-free measurement model: Jacobian against finite differences, masked channels;
* the receiver: noise sample variances within chi-square bounds, Doppler sign;
* the least-squares fix: exact on noise-free data (three satellites and the GPS constellation);
* the EKF: NEES within chi-square bounds over Monte Carlo (trials x UAVs batched) on the
  seed's trajectories with three satellites and with the GPS constellation, and far outside
  them for a filter whose noise model is wrong; the batched filter over 5 UAVs equals 5
  single-UAV runs on the same data;
* bad parameters.

Every random draw comes from np.random.default_rng(seed).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from filters import metrics
from sitl.gnss import orbits, ranging
from vehicles import uav, uav_nav
from vehicles.uav_nav import GnssEpoch, GnssNoise, NavConfig
from tests.helpers import chi2_var_bounds

T0 = uav_nav.EXAMPLE_T0_GPS_S


@pytest.fixture(scope="module")
def seed_truth():
    """The seed's three UAVs (RK4, 0.01 s) at 1 s epochs for 200 s, and the three satellites."""
    sw = uav.example_uav_swarm()
    trs = [sw.step(float(k)) for k in range(200)]
    pos = np.array([tr.pos_ecef_m for tr in trs])
    vel = np.array([tr.vel_ecef_m_s for tr in trs])
    const3 = uav_nav.example_three_satellites(pos[0, 0], T0, duration_s=1000.0)
    return T0 + np.arange(200.0), pos, vel, const3


# ============================================================================ PSD -> variance


@pytest.mark.parametrize("dt_s", [0.1, 0.5, 1.0])
def test_white_noise_averaged_over_dt_has_variance_psd_over_dt(dt_s):
    """Fine-grid white noise (step d, variance N/d) averaged over dt: variance N/dt."""
    rng = np.random.default_rng(11)
    N, d, blocks = 900.0, 1e-3, 4000
    per = int(round(dt_s / d))
    w = rng.standard_normal((blocks, per)) * math.sqrt(N / d)
    avg = w.mean(axis=1)
    lo, hi = chi2_var_bounds(blocks)
    ratio = avg.var(ddof=1) / (N / dt_s)
    assert lo < ratio < hi, ratio
    assert GnssNoise(dt_s=dt_s).var_pr_m2 == pytest.approx(N / dt_s, rel=1e-14)


def test_configured_variances_scale_as_one_over_dt():
    dts = np.array([0.05, 0.2, 1.0, 5.0])
    pr = np.array([GnssNoise(dt_s=dt).var_pr_m2 for dt in dts])
    prr = np.array([GnssNoise(dt_s=dt).var_prr_m2_s2 for dt in dts])
    assert np.allclose(pr * dts, 900.0, rtol=1e-14) and np.allclose(prr * dts, 0.04, rtol=1e-14)
    assert math.sqrt(GnssNoise().var_pr_m2) == pytest.approx(30.0)
    assert math.sqrt(GnssNoise().var_prr_m2_s2) == pytest.approx(0.2)


# ============================================================================ satellites


def _two_body(gm):
    def f(t, s):
        r = s[:3]
        return np.concatenate([s[3:], -gm * r / np.linalg.norm(r) ** 3])
    return f


def _eci_to_ecef(r_i, v_i, theta, we):
    """ECEF state of an inertial state, the frames aligned at theta = 0 (R3 rotates the axes)."""
    c, s = math.cos(theta), math.sin(theta)
    R = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    p = R @ r_i
    return p, R @ v_i - we * np.array([-p[1], p[0], 0.0])


@pytest.mark.parametrize("duration_s", [1000.0, 21600.0])
def test_kepler_propagation_equals_two_body_ode(seed_truth, duration_s):
    const = seed_truth[3]
    p0, v0 = orbits.sat_state_ecef(const, T0)
    p1, v1 = orbits.sat_state_ecef(const, T0 + duration_s)
    for j in range(len(const)):
        gm, we = const.gm_m3_s2[j], const.omega_e_rad_s[j]
        s0 = np.concatenate([p0[j], v0[j] + we * np.array([-p0[j, 1], p0[j, 0], 0.0])])  # inertial velocity
        ref = solve_ivp(_two_body(gm), (0.0, duration_s), s0, method="DOP853", rtol=1e-13, atol=1e-9)
        s_rk4 = s0.copy()
        h = 10.0
        for k in range(int(duration_s / h)):
            s_rk4 = uav.rk4_step(_two_body(gm), k * h, s_rk4, h)
        for s in (ref.y[:, -1], s_rk4):
            p, v = _eci_to_ecef(s[:3], s[3:], we * duration_s, we)
            assert np.linalg.norm(p - p1[j]) < 1e-4, (j, np.linalg.norm(p - p1[j]))  # m, of ~26,600 km
            assert np.linalg.norm(v - v1[j]) < 1e-8
    # the unperturbed orbit is what is tested: the almanac's node drift alone moves a
    # satellite by kilometres in 6 h, so the same comparison fails for the drifting orbit
    if duration_s > 10000:
        drifting = orbits.gps_constellation().subset(const.sat_id)
        assert np.min(np.linalg.norm(orbits.sat_state_ecef(drifting, T0 + duration_s)[0] - p1, axis=-1)) > 100.0


def test_three_satellites_stay_tracked_for_the_whole_run():
    sw = uav.example_uav_swarm(dt_s=0.05)
    start = sw.truth().pos_ecef_m
    const = uav_nav.example_three_satellites(start[0], T0, 1000.0)
    assert len(const) == 3 and np.all(const.OmegaDot_rad_s == 0.0)
    cfg = NavConfig(el_mask_rad=math.radians(10.0))
    for t in (0.0, 500.0, 1000.0):
        tr = sw.step(t)
        ep = uav_nav.gnss_measure(np.random.default_rng(0), T0 + t, tr.pos_ecef_m, tr.vel_ecef_m_s, const, cfg)
        assert ep.tracked.all(), t
        pos, _ = orbits.sat_state_ecef(const, T0 + t)
        assert np.all(uav_nav.pdop_clock_free(tr.pos_ecef_m, np.broadcast_to(pos, (3, 3, 3))) < 10.0)


# ============================================================================ measurement model


def test_clock_free_model_jacobian_and_masking(seed_truth):
    t, pos, vel, const = seed_truth
    sp, sv = orbits.sat_state_ecef(orbits.gps_constellation(), t[0])
    rng = np.random.default_rng(3)
    x = np.concatenate([pos[0, 1] + rng.normal(0, 50, 3), vel[0, 1] + rng.normal(0, 2, 3)])
    tracked = rng.random(len(sp)) < 0.5
    model = uav_nav.ClockFreePseudorangeDoppler(np.where(tracked[:, None], sp, np.nan), sv, 900.0, 0.04, tracked)
    hx, H = model.h_and_H(x)
    S = len(sp)
    fd = np.empty_like(H)
    for i, step in enumerate([1.0] * 3 + [0.01] * 3):
        dx = np.zeros(6)
        dx[i] = step
        fd[:, i] = (model.h(x + dx) - model.h(x - dx)) / (2 * step)
    assert np.allclose(H, fd, rtol=1e-6, atol=1e-9)
    # tracked rows: the seed's eqs 1-2 evaluated directly
    d = sp - x[:3]
    rho = np.linalg.norm(d, axis=-1)
    assert np.allclose(hx[:S][tracked], rho[tracked], rtol=1e-15, atol=1e-6)
    assert np.allclose(hx[S:][tracked], (np.sum(d * (sv - x[3:]), axis=-1) / rho)[tracked], atol=1e-9)
    masked = np.concatenate([~tracked, ~tracked])
    assert not np.any(hx[masked]) and not np.any(H[masked])
    r = model.R_diag()
    assert np.all(r[masked] == 1.0) and np.all(r[:S][tracked] == 900.0) and np.all(r[S:][tracked] == 0.04)


@pytest.mark.parametrize("dt_s", [1.0, 0.5])
def test_receiver_noise_variance_and_doppler_sign(seed_truth, dt_s):
    t, pos, vel, const = seed_truth
    cfg = NavConfig(noise=GnssNoise(dt_s=dt_s))
    n = 20000
    ep = uav_nav.gnss_measure(np.random.default_rng(21), t[5], pos[5], vel[5], const, cfg, trials_shape=(n,))
    geo = ranging.light_time_geometry(t[5], pos[5], vel[5], const)
    lo, hi = chi2_var_bounds(n)
    for err, var in ((ep.pseudorange_m - geo.range_m, 900.0 / dt_s),
                     (ep.pseudorange_rate_m_s - geo.range_rate_m_s, 0.04 / dt_s)):
        ratio = err.reshape(n, -1).var(axis=0, ddof=1) / var
        assert np.all((lo < ratio) & (ratio < hi)), ratio
    # the Doppler is the range rate: positive when the range grows (finite difference)
    h = 0.5
    ra = ranging.light_time_geometry(t[5] - h, pos[5] - h * vel[5], vel[5], const).range_m
    rb = ranging.light_time_geometry(t[5] + h, pos[5] + h * vel[5], vel[5], const).range_m
    assert np.allclose((rb - ra) / (2 * h), geo.range_rate_m_s, atol=2e-3)


# ============================================================================ least-squares fix


@pytest.mark.parametrize("case", ["three", "gps", "three-instantaneous"])
def test_ls_fix_exact_on_noise_free_data(seed_truth, case):
    t, pos, vel, const3 = seed_truth
    const = orbits.gps_constellation() if case == "gps" else const3
    cfg = NavConfig(noise=GnssNoise(1e-12, 1e-16), el_mask_rad=math.radians(5.0), light_time=case != "three-instantaneous")
    ep = uav_nav.gnss_measure(np.random.default_rng(1), t[7], pos[7], vel[7], const, cfg)
    x, P = uav_nav.ls_fix(ep, const, cfg)
    assert np.max(np.abs(x[:, :3] - pos[7])) < 1e-4
    assert np.max(np.abs(x[:, 3:] - vel[7])) < 1e-6
    assert np.all(np.linalg.eigvalsh(P) > 0)


# ============================================================================ EKF consistency


def _nees_stats(track, pos, vel, first=10):
    xt = np.concatenate([pos, vel], axis=-1)[:, None]  # (T, 1, n_uav, 6)
    nees = metrics.nees(track.x - xt, track.P)  # (T, trials, n_uav)
    per_epoch = nees.mean(axis=(1, 2))
    return per_epoch, float(per_epoch[first:].mean())


@pytest.mark.slow
def test_nees_within_chi2_bounds_three_satellites(seed_truth):
    t, pos, vel, const = seed_truth
    trials = 100
    cfg = NavConfig(el_mask_rad=math.radians(5.0))
    track = uav_nav.nav_track(np.random.default_rng(2024), t, pos, vel, const, cfg, trials_shape=(trials,))
    assert track.x.shape == (200, trials, 3, 6) and track.P.shape == (200, trials, 3, 6, 6)
    assert np.all(track.n_tracked == 3)
    per_epoch, anees = _nees_stats(track, pos, vel)
    lo, hi = metrics.chi2_bounds(6, trials * 3, p=0.99)
    assert lo < anees < hi, (anees, lo, hi)
    # a constant-velocity filter on sinusoidal accelerations: the per-epoch NEES swings
    # around its mean (module docstring), but never far above the band
    assert np.mean((per_epoch[1:] > lo) & (per_epoch[1:] < hi)) > 0.6
    assert per_epoch[10:].max() < 1.2 * hi
    nis_ratio = np.mean(track.nis[1:]) / np.mean(2 * track.n_tracked[1:])
    assert 0.95 < nis_ratio < 1.05, nis_ratio
    err = np.linalg.norm(track.x[-1, ..., :3] - pos[-1], axis=-1)
    assert np.sqrt(np.mean(err**2)) < 10.0  # from ~55 m (the single-epoch fix) to a few metres


def test_nees_within_chi2_bounds_gps_constellation(seed_truth):
    t, pos, vel, _ = seed_truth
    trials = 30
    const = orbits.gps_constellation()
    track = uav_nav.nav_track(np.random.default_rng(99), t[:120], pos[:120], vel[:120], const, NavConfig(),
                              trials_shape=(trials,))
    assert np.all(track.n_tracked >= 5)
    _, anees = _nees_stats(track, pos[:120], vel[:120])
    lo, hi = metrics.chi2_bounds(6, trials * 3, p=0.99)
    assert lo < anees < hi, (anees, lo, hi)


def test_nees_fails_for_a_mismatched_noise_model(seed_truth):
    """The filter believes the receiver averages over 10 s (variances 10x too small)."""
    t, pos, vel, const = seed_truth
    cfg = NavConfig(el_mask_rad=math.radians(5.0))
    wrong = NavConfig(noise=GnssNoise(dt_s=10.0), el_mask_rad=math.radians(5.0))
    track = uav_nav.nav_track(np.random.default_rng(5), t[:60], pos[:60], vel[:60], const, cfg, trials_shape=(30,),
                              filter_config=wrong)
    _, anees = _nees_stats(track, pos[:60], vel[:60])
    assert anees > 2 * metrics.chi2_bounds(6, 90, p=0.99)[1], anees


def test_batched_filter_over_five_uavs_equals_five_single_runs():
    lat = np.radians([30.0, 30.1, 30.3, 29.9, 30.2])
    lon = np.radians([45.0, 45.1, 45.3, 45.2, 44.9])
    h = np.array([3000.0, 3100.0, 3500.0, 2800.0, 3300.0])
    law = uav.SinusoidalLaw(105.0, 5.0, 0.02, [0.0, 0.5, 1.0, 1.5, 2.0], uav.eta_axis_heading_rad(lat, lon),
                            [0.1, 0.2, 0.05, 0.15, 0.1], 0.01, 0.0, 15.0, 0.01)
    sw = uav.UavSwarm(law, lat, lon, h)
    const = orbits.gps_constellation()
    rng = np.random.default_rng(8)
    epochs = []
    for k in range(30):
        tr = sw.step(float(k))
        epochs.append(uav_nav.gnss_measure(rng, T0 + k, tr.pos_ecef_m, tr.vel_ecef_m_s, const))
    batched = uav_nav.OnboardNav(const)
    singles = [uav_nav.OnboardNav(const) for _ in range(5)]
    for ep in epochs:
        est = batched.update(ep)
        for i, nav in enumerate(singles):
            one = nav.update(GnssEpoch(ep.t_gps_s, ep.pseudorange_m[i], ep.pseudorange_rate_m_s[i], ep.var_pr_m2,
                                       ep.var_prr_m2_s2, ep.tracked[i]))
            sd = np.sqrt(np.diag(one.P))
            assert np.max(np.abs(est.x[i] - one.x) / sd) < 1e-9
            assert np.max(np.abs(est.P[i] - one.P) / np.outer(sd, sd)) < 1e-9
    assert len(np.unique(est.n_tracked)) >= 1 and est.x.shape == (5, 6)


@pytest.mark.parametrize("case", ["three", "gps", "gps_instantaneous"])
def test_many_epochs_at_once_equal_one_epoch_at_a_time(seed_truth, case):
    """truth_geometry / filter_sat_states over many epochs in one call (what batch runs use)
    give gnss_measure's and the filters' numbers bitwise, with the same random draws."""
    t, pos, vel, const3 = seed_truth
    const = const3 if case == "three" else orbits.gps_constellation()
    cfg = NavConfig(light_time=case != "gps_instantaneous")
    K = 40
    geo = uav_nav.truth_geometry(t[:K, None], pos[:K], vel[:K], const, cfg)
    assert geo.range_m.shape == (K, 3, len(const))
    ra, rb = np.random.default_rng(5), np.random.default_rng(5)
    nav_a, nav_b = uav_nav.OnboardNav(const, cfg), uav_nav.OnboardNav(const, cfg)
    eps_a, eps_b = [], []
    for k in range(K):
        eps_a.append(uav_nav.gnss_measure(ra, t[k], pos[k], vel[k], const, cfg, trials_shape=(2,)))
        eps_b.append(uav_nav.gnss_measure(rb, t[k], pos[k], vel[k], const, cfg, trials_shape=(2,),
                                          geometry=geo.at(k)))
        for f in ("pseudorange_m", "pseudorange_rate_m_s", "tracked"):
            assert np.array_equal(getattr(eps_a[k], f), getattr(eps_b[k], f), equal_nan=True), (k, f)
    sp, sv = uav_nav.filter_sat_states(eps_b, const, cfg)
    assert sp.shape == (K, 2, 3, len(const), 3)
    for k in range(K):
        model, _ = uav_nav.nav_measurement_model(eps_a[k], const, cfg)
        mb, _ = uav_nav.nav_measurement_model(eps_b[k], const, cfg, (sp[k], sv[k]))
        assert np.array_equal(model.sat_pos_ecef_m, mb.sat_pos_ecef_m)
        assert np.array_equal(model.sat_vel_ecef_m_s, mb.sat_vel_ecef_m_s)
        a, b = nav_a.update(eps_a[k]), nav_b.update(eps_b[k], (sp[k], sv[k]))
        assert np.array_equal(a.x, b.x) and np.array_equal(a.P, b.P)
    with pytest.raises(ValueError, match="geometry"):
        uav_nav.gnss_measure(ra, t[0], pos[0], vel[0], const, cfg, geometry=(1.0, 2.0, 3.0))


# ============================================================================ bad parameters


@pytest.mark.parametrize("make, name", [
    (lambda: GnssNoise(dt_s=0.0), "dt_s"),
    (lambda: GnssNoise(psd_pr_m2_s=-900.0), "psd_pr_m2_s"),
    (lambda: NavConfig(q_m2_s3=-1.0), "q_m2_s3"),
    (lambda: NavConfig(el_mask_rad=2.0), "el_mask_rad"),
    (lambda: NavConfig(ls_iterations=0), "ls_iterations"),
    (lambda: NavConfig(noise=900.0), "noise"),
    (lambda: uav_nav.example_three_satellites(np.array([3.9e6, 3.9e6, 3.2e6]), el_min_rad=math.radians(80.0)),
     "el_min_rad"),
    (lambda: uav_nav.example_three_satellites(np.zeros(2)), "rx_pos_ecef_m"),
    (lambda: uav_nav.unperturbed("GPS"), "constellation"),
    (lambda: uav_nav.gnss_measure(np.random, T0, np.zeros(3), np.zeros(3), orbits.gps_constellation()), "rng"),
    (lambda: uav_nav.ClockFreePseudorangeDoppler(np.ones((3, 3)) * 2e7, np.zeros((3, 3)), 0.0, 1.0), "var_pr_m2"),
    (lambda: uav_nav.ls_fix(GnssEpoch(T0, np.array([2e7, 2e7, np.nan]), np.array([0.0, 0.0, np.nan]), 900.0, 0.04,
                                      np.array([True, True, False])),
                            orbits.gps_constellation().subset([0, 1, 2])), "epoch"),
])
def test_bad_parameters_raise_value_error_naming_them(make, name):
    with pytest.raises(ValueError, match=name):
        make()


def test_memoised_transition_is_the_constant_velocity_model_bit_for_bit():
    """The onboard filters' transition (F, Q and f memoised per step length) gives the numbers of
    filters.models.ConstantVelocity itself, for batched states and several step lengths."""
    from filters.models import ConstantVelocity

    rng = np.random.default_rng(4)
    x = rng.normal(size=(7, 3, 6)) * 1e6
    memo = uav_nav._transition(0.035)
    ref = ConstantVelocity(3, q=0.035)
    for dt in (0.1, 1.0, 2.5):
        np.testing.assert_array_equal(memo.f(x, dt), ref.f(x, dt))
        np.testing.assert_array_equal(memo.F(None, dt), ref.F(None, dt))
        np.testing.assert_array_equal(memo.Q(dt), ref.Q(dt))
    with pytest.raises(ValueError, match="shape"):
        memo.f(np.zeros(4), 1.0)
