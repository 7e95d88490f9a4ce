"""Relayed GNSS at the ground point G (seed 004): pseudorange, pseudo-Doppler, oscillator, outages."""
from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
from scipy import stats

from sitl.constants import C_M_S, WGS84
from sitl.geodesy import ecef_to_aer, enu_to_ecef
from sitl.gnss.orbits import DEFAULT_TOA_GPS_S, default_constellation
from sitl.gnss.ranging import light_time_geometry
from sitl.radio.relay import (
    Relay,
    RelayErrorBudget,
    RelayParams,
    compact,
    gauss_markov_step,
    oscillator_discretisation,
    pressure_ratio,
)
from vehicles.sonde import (
    DEFAULT_LAUNCH_H_M as H,
)
from vehicles.sonde import (
    DEFAULT_LAUNCH_LAT_RAD as LAT,
)
from vehicles.sonde import (
    DEFAULT_LAUNCH_LON_RAD as LON,
)
from vehicles.sonde import (
    SondeFlight,
    SondeParams,
    spawn_rngs,
)
from tests.helpers import chi2_ok

CONST = default_constellation("GR")
S = len(CONST)
G = enu_to_ecef(np.zeros(3), LAT, LON, H)


def make(rng, params=None, batch_shape=None):
    return Relay(rng, CONST, ground_lat_rad=LAT, ground_lon_rad=LON, ground_h_m=H, params=params,
                 batch_shape=batch_shape)


@pytest.fixture(scope="module")
def flight():
    """Two default sondes, a whole flight, relayed every 10 s."""
    tr = SondeFlight(spawn_rngs(404, 2)).simulate(until_landed=True)
    k = np.arange(0, len(tr), 10)
    relay = make(spawn_rngs(405, 2))
    return tr, k, relay.track(tr.t_gps_s[k], tr.pos_ecef_m[k], tr.vel_ecef_m_s[k])


def test_pseudorange_is_the_two_leg_path_plus_delta_d(flight):
    # the default world has the error budget: dd varies about c (tau_ret + clock) by the path
    # variation, and the per-satellite errors are reported; what is left is the white noise
    tr, k, rt = flight
    p = RelayParams()
    d = rt.delivered
    dd0 = C_M_S * (1.5e-6 + 100e-9)
    assert d.sum() > 10_000 and np.std(rt.delta_d_m) > 0.5 and np.all(np.abs(rt.delta_d_m - dd0) < 6 * 1.5)
    assert 1.0 < np.sqrt(np.mean(rt.pr_error_m[d] ** 2)) < 6.0  # metres, a single-frequency error budget
    resid = rt.pseudorange_m - (rt.true_path_m + rt.delta_d_m[..., None] + rt.pr_error_m)
    assert np.all(np.isnan(resid[~d])) and np.all(np.isfinite(resid[d]))
    assert chi2_ok(resid[d], p.sigma_pr_m)
    assert abs(resid[d].mean()) < 4 * p.sigma_pr_m / math.sqrt(d.sum())
    assert not chi2_ok(resid[d] + 2.0, p.sigma_pr_m)  # a 2 m error in dd would be seen
    # the noise-free path, computed here independently: satellite leg by light time to the
    # sonde at t - |P - G|/c - tau_ret, downlink |P - G| plus the Sagnac term
    j = np.arange(0, k.size, 25)
    pos, vel = tr.pos_ecef_m[k[j]], tr.vel_ecef_m_s[k[j]]
    tau_down = np.linalg.norm(pos - G, axis=-1) / C_M_S
    p_out = pos - vel * tau_down[..., None]  # the sonde when it re-radiated (a few cm back)
    p_in = pos - vel * (tau_down + 1.5e-6)[..., None]  # ... and when the satellite signal arrived
    t_in = tr.t_gps_s[k[j]][:, None] - tau_down - 1.5e-6
    geo = light_time_geometry(t_in, p_in, vel, CONST)
    sagnac = WGS84.omega_rad_s / C_M_S * (p_out[..., 0] * G[1] - p_out[..., 1] * G[0])
    expect = geo.range_m + (np.linalg.norm(p_out - G, axis=-1) + sagnac)[..., None]
    dj = d[j]
    np.testing.assert_allclose(rt.true_path_m[j][dj], expect[dj], rtol=0, atol=2e-3)
    resid2 = rt.pseudorange_m[j] - expect - rt.delta_d_m[j][..., None] - rt.pr_error_m[j]
    assert chi2_ok(resid2[dj], p.sigma_pr_m)
    assert np.abs(sagnac).max() < 0.5 and np.abs(sagnac).max() > 0.05


def test_delivery_masks_and_radio_range(flight):
    tr, k, rt = flight
    p = RelayParams()
    d = rt.delivered
    assert np.all(rt.sat_el_at_sonde_rad[d] >= p.sat_el_mask_rad)
    pos = tr.pos_ecef_m[k]
    _, el_g, rng_g = ecef_to_aer(G, pos)
    vis = (el_g >= 0.0) & (rng_g <= 250_000.0)
    np.testing.assert_array_equal(rt.sonde_visible, vis)
    assert np.all(~d[~vis])  # out of radio range or below G's horizon: nothing
    assert np.any(~vis) and np.any(vis)  # the default flights leave the 250 km radius
    n = d.sum(-1)
    assert n[vis].min() >= 8  # GPS + GLONASS from a sonde above 5 deg
    c = compact(rt.epoch(50), 1)
    assert c["sat_id"].size == n[50, 1] and c["pseudorange_m"].shape == (n[50, 1],)
    assert c["sat_pos_ecef_m"].shape == (n[50, 1], 3) and np.all(np.isfinite(c["sat_vel_ecef_m_s"]))
    np.testing.assert_array_equal(c["ground_pos_ecef_m"], G)
    np.testing.assert_array_equal(rt.var_pr_m2[d], p.sigma_pr_m**2)
    np.testing.assert_array_equal(rt.var_prr_m2_s2[d], p.sigma_prr_m_s**2)


def test_reported_satellite_states_fit_the_model_within_a_metre(flight):
    # the ground receiver's ephemeris (transit time from its own pseudorange) against the sonde's
    # downlink-emission point rotated into the frame of t: the path model holds to a few cm
    tr, k, rt = flight
    d = rt.delivered
    pos, vel = tr.pos_ecef_m[k], tr.vel_ecef_m_s[k]
    tau = np.linalg.norm(pos - G, axis=-1) / C_M_S
    pe = pos - vel * tau[..., None]
    th = WGS84.omega_rad_s * tau
    prot = np.stack([np.cos(th) * pe[..., 0] + np.sin(th) * pe[..., 1],
                     np.cos(th) * pe[..., 1] - np.sin(th) * pe[..., 0], pe[..., 2]], -1)
    model = (np.linalg.norm(rt.sat_pos_ecef_m - prot[..., None, :], axis=-1)
             + np.linalg.norm(prot - G, axis=-1)[..., None])
    assert np.nanmax(np.abs(model - rt.true_path_m)[d]) < 0.05
    # and the textbook model with the plain ECEF sonde position is within half a metre
    plain = (np.linalg.norm(rt.sat_pos_ecef_m - pos[..., None, :], axis=-1)
             + np.linalg.norm(pos - G, axis=-1)[..., None])
    assert np.nanmax(np.abs(plain - rt.true_path_m)[d]) < 0.6


def test_pseudo_doppler_is_the_path_rate_with_the_stated_sign():
    # noise-free sonde at 0.5 s; central differences of the noise-free path along the trajectory
    p = SondeParams(sigma_a_m_s2=0.0, sigma_a_vertical_m_s2=0.0)
    f = SondeFlight(np.random.default_rng(1), params=p, dt_s=0.5)
    f.simulate(6000)  # 50 min into the ascent, ~100 km downwind
    tr = f.simulate(240)
    rp = RelayParams(sigma_pr_m=0.0, errors=None)
    rt = make(np.random.default_rng(2), rp).track(tr.t_gps_s, tr.pos_ecef_m, tr.vel_ecef_m_s)
    fd = (rt.true_path_m[2:] - rt.true_path_m[:-2]) / 1.0
    d = rt.delivered[1:-1]
    assert d.sum() > 1000
    np.testing.assert_allclose(rt.true_path_rate_m_s[1:-1][d], fd[d], rtol=0, atol=2e-3)
    # the seed's formula (K_i + K).V - K_i.W_i with the satellite at emission and its velocity
    P, V = rt.true_sonde_pos_ecef_m[..., None, :], tr.vel_ecef_m_s[:, None, :]
    Ki = (P - rt.true_sat_pos_ecef_m) / np.linalg.norm(P - rt.true_sat_pos_ecef_m, axis=-1, keepdims=True)
    K = (tr.pos_ecef_m - G) / np.linalg.norm(tr.pos_ecef_m - G, axis=-1, keepdims=True)
    formula = np.sum((Ki + K[:, None, :]) * V, -1) - np.sum(Ki * rt.true_sat_vel_ecef_m_s, -1)
    np.testing.assert_allclose(formula[rt.delivered], rt.true_path_rate_m_s[rt.delivered], atol=1e-3)
    # sign: the sonde drifts away from G, so the downlink part K.V is positive (path grows)
    assert np.all(np.sum(K * tr.vel_ecef_m_s, -1) > 10.0)
    # measured = path rate + (c/omega) Dw + white noise sigma_prr
    resid = rt.pseudo_doppler_m_s - rt.true_path_rate_m_s - rt.osc_doppler_m_s[:, None]
    assert chi2_ok(resid[rt.delivered], rp.sigma_prr_m_s)
    np.testing.assert_allclose(rt.pseudorange_m[rt.delivered],
                               (rt.true_path_m + rt.delta_d_m[:, None])[rt.delivered], atol=1e-6)


def test_outage_schedule_yields_empty_epochs(flight):
    tr, k, _ = flight
    t = tr.t_gps_s[k[:60]]
    sched = [(t[10], t[20]), (t[40], t[40] + 0.5)]
    rt = make(spawn_rngs(405, 2), RelayParams(outage_schedule=sched)).track(t, tr.pos_ecef_m[k[:60]],
                                                                          tr.vel_ecef_m_s[k[:60]])
    out = np.zeros(60, bool)
    out[10:20] = True
    out[40] = True
    np.testing.assert_array_equal(rt.outage, out)
    assert rt.delivered[out].sum() == 0 and np.all(np.isnan(rt.pseudorange_m[out]))
    assert np.all(rt.delivered[~out].sum(-1) >= 8)
    e = rt.epoch(15)
    assert e.outage and compact(e, 0)["sat_id"].size == 0 and compact(e, 0)["pseudorange_m"].shape == (0,)


def test_oscillator_discretisation_is_exact():
    for gamma, sig, npsd, T in ((1e-3, 2 * math.pi * 10.0, 0.0, 1.0), (0.3, 1.5, 0.2, 2.5),
                                (1e-4, 7.0, 0.01, 0.1), (0.05, 1.0, 0.0, 0.999)):
        F, Q = oscillator_discretisation(gamma, sig, npsd, T)
        a = np.array([[0.0, 1.0], [0.0, -gamma]])
        gq = np.diag([npsd, 2 * gamma * sig**2])
        vl = scipy.linalg.expm(np.block([[-a, gq], [np.zeros((2, 2)), a.T]]) * T)
        np.testing.assert_allclose(F, vl[2:, 2:].T, rtol=1e-12)
        np.testing.assert_allclose(Q, vl[2:, 2:].T @ vl[:2, 2:], rtol=1e-7)


def test_oscillator_statistics_and_common_doppler_term():
    # 500 static sondes, Gauss-Markov LO offset with a 10 s correlation time
    rp = RelayParams(osc_sigma_hz=5.0, osc_gamma_1_s=0.1)
    B = 500
    pos = np.broadcast_to(enu_to_ecef(np.array([20e3, 30e3, 10e3]), LAT, LON, H), (B, 3))
    t = DEFAULT_TOA_GPS_S + np.concatenate([np.arange(0.0, 121.0, 40.0), [121.0, 123.0]])
    rt = make(np.random.default_rng(9), rp, (B,)).track(t, np.broadcast_to(pos, (t.size, B, 3)), np.zeros((t.size, B, 3)))
    sw = 2 * math.pi * 5.0
    w = rt.osc_freq_rad_s  # (T, B)
    lo, hi = stats.chi2.ppf([5e-4, 1 - 5e-4], df=B)
    for kk in range(5):
        assert lo < np.sum(w[kk] ** 2) / sw**2 < hi
    r = np.corrcoef(w[3], w[4])[0, 1]  # lag 1 s: exp(-0.1)
    assert abs(np.arctanh(r) - np.arctanh(math.exp(-0.1))) * math.sqrt(B - 3) < 3.3
    r = np.corrcoef(w[4], w[5])[0, 1]  # lag 2 s
    assert abs(np.arctanh(r) - np.arctanh(math.exp(-0.2))) * math.sqrt(B - 3) < 3.3
    # the common term: (c/omega) Dw in every satellite's pseudo-Doppler of the sonde
    np.testing.assert_allclose(rt.osc_doppler_m_s, C_M_S / (2 * math.pi * rp.carrier_hz) * w, rtol=1e-14)
    mean_resid = np.nanmean(rt.pseudo_doppler_m_s - rt.true_path_rate_m_s, axis=-1)
    n = rt.delivered.sum(-1)
    assert np.all(np.abs(mean_resid - rt.osc_doppler_m_s) < 5 * rp.sigma_prr_m_s / np.sqrt(n))
    # the phase integrates the frequency: innovations of [phi, Dw] over the 2 s step have the
    # covariance Q of the exact discretisation (and the phase one is rejected without it)
    F, Q = oscillator_discretisation(0.1, sw, 0.0, 2.0)
    x0 = np.stack([rt.osc_phase_rad[4], w[4]], -1)
    x1 = np.stack([rt.osc_phase_rad[5], w[5]], -1)

    def lr(e):  # likelihood-ratio statistic of cov(e) = Q, ~ chi2(3)
        a = np.linalg.solve(Q, e.T @ e / B)
        return B * (np.trace(a) - np.log(np.linalg.det(a)) - 2)

    assert lr(x1 - x0 @ F.T) < stats.chi2.ppf(0.999, df=3)
    assert lr(x1 - x0) > stats.chi2.ppf(0.999, df=3)  # a phase that did not integrate Dw is rejected


def test_step_equals_track_and_batch_equals_loop(flight):
    tr, k, _ = flight
    kk = k[:30]
    t, pos, vel = tr.t_gps_s[kk], tr.pos_ecef_m[kk], tr.vel_ecef_m_s[kk]
    rt = make(spawn_rngs(405, 2)).track(t, pos, vel, block=7)
    relay = make(spawn_rngs(405, 2))
    eps = [relay.step(t[i], pos[i], vel[i]) for i in range(t.size)]
    for f in ("pseudorange_m", "pseudo_doppler_m_s", "sat_pos_ecef_m", "osc_freq_rad_s", "true_path_m"):
        a, b = np.stack([getattr(e, f) for e in eps]), getattr(rt, f)
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-5, err_msg=f)
    for i, g in enumerate(spawn_rngs(405, 2)):
        one = make([g]).track(t, pos[:, i:i + 1], vel[:, i:i + 1])
        np.testing.assert_array_equal(one.delivered[:, 0], rt.delivered[:, i])
        np.testing.assert_allclose(one.pseudorange_m[:, 0], rt.pseudorange_m[:, i], rtol=0, atol=1e-5)
        np.testing.assert_array_equal(one.osc_freq_rad_s[:, 0], rt.osc_freq_rad_s[:, i])


@pytest.mark.parametrize("kwargs, name", [
    (dict(sigma_pr_m=-5.0), "sigma_pr_m"),
    (dict(sigma_prr_m_s=float("nan")), "sigma_prr_m_s"),
    (dict(sat_el_mask_rad=5.0), "sat_el_mask_rad"),
    (dict(ground_el_mask_rad=-2.0), "ground_el_mask_rad"),
    (dict(max_range_m=0.0), "max_range_m"),
    (dict(relay_delay_s=-1e-6), "relay_delay_s"),
    (dict(gcpp_clock_offset_s=1.0), "gcpp_clock_offset_s"),
    (dict(osc_sigma_hz=-1.0), "osc_sigma_hz"),
    (dict(osc_gamma_1_s=0.0), "osc_gamma_1_s"),
    (dict(carrier_hz=0.0), "carrier_hz"),
    (dict(outage_schedule=[(5.0, 5.0)]), "outage_schedule"),
    (dict(downlink_sagnac="yes"), "downlink_sagnac"),
])
def test_bad_parameters_raise_naming_them(kwargs, name):
    with pytest.raises(ValueError, match=name):
        RelayParams(**kwargs)


def test_bad_arguments_raise_naming_them():
    with pytest.raises(ValueError, match="constellation"):
        Relay(np.random.default_rng(0), "GPS", ground_lat_rad=LAT, ground_lon_rad=LON, ground_h_m=H)
    with pytest.raises(ValueError, match="ground_lat_rad"):
        Relay(np.random.default_rng(0), CONST, ground_lat_rad=55.9, ground_lon_rad=LON, ground_h_m=H)
    with pytest.raises(ValueError, match="rng"):
        make(None)
    r = make(np.random.default_rng(0))
    with pytest.raises(ValueError, match="sonde_pos_ecef_m"):
        r.step(DEFAULT_TOA_GPS_S, np.zeros((2, 3)), np.zeros((2, 3)))
    r.step(DEFAULT_TOA_GPS_S, G + 1000.0, np.zeros(3))
    with pytest.raises(ValueError, match="t_gps_s"):
        r.step(DEFAULT_TOA_GPS_S, G + 1000.0, np.zeros(3))
    with pytest.raises(ValueError, match="t_gps_s"):
        r.track([DEFAULT_TOA_GPS_S + 2, DEFAULT_TOA_GPS_S + 1], np.zeros((2, 3)) + G, np.zeros((2, 3)))


# ---------------------------------------------------------------- the error budget


def test_white_world_is_reachable_and_its_errors_are_zero(flight):
    tr, k, _ = flight
    rt = make(spawn_rngs(405, 2), RelayParams(errors=None)).track(tr.t_gps_s[k[:200]], tr.pos_ecef_m[k[:200]],
                                                                 tr.vel_ecef_m_s[k[:200]])
    d = rt.delivered
    assert np.all(rt.delta_d_m == pytest.approx(C_M_S * (1.5e-6 + 100e-9))) and np.all(rt.pr_error_m == 0.0)
    assert chi2_ok((rt.pseudorange_m - rt.true_path_m - rt.delta_d_m[..., None])[d], RelayParams().sigma_pr_m)


def test_gauss_markov_step_has_unit_variance_and_its_correlation_time():
    rng = np.random.default_rng(7)
    tau, dt, n, K = 20.0, 2.0, 4000, 60
    u = rng.standard_normal(n)
    u0 = u.copy()
    for _ in range(K):
        u = gauss_markov_step(u, rng.standard_normal(n), dt, tau)
    assert abs(u.var() - 1.0) < 0.08  # stationary: unit variance after K steps
    rho = np.corrcoef(u0, u)[0, 1]
    assert abs(rho - math.exp(-K * dt / tau)) < 0.05  # e^-6 = 0.0025
    v = gauss_markov_step(u0, rng.standard_normal(n), dt, tau)
    assert abs(np.corrcoef(u0, v)[0, 1] - math.exp(-dt / tau)) < 0.02
    assert not abs(np.corrcoef(u0, v)[0, 1] - math.exp(-dt / (2 * tau))) < 0.02  # a wrong tau is seen


def _static_relay(budget, epochs=1500, n=6, seed=11):
    """n sondes held still 20 km above G (zero velocity), 1 Hz."""
    t = DEFAULT_TOA_GPS_S + np.arange(epochs, dtype=float)
    p = enu_to_ecef(np.array([0.0, 0.0, 20_000.0]), LAT, LON, H)
    pos = np.broadcast_to(p, (epochs, n, 3)).copy()
    relay = make(spawn_rngs(seed, n), RelayParams(errors=budget))
    return relay.track(t, pos, np.zeros_like(pos))


def _lag_corr(x, lag):
    """Pooled correlation of x (T, ...) with itself lag epochs later (finite entries)."""
    a, b = x[:-lag].ravel(), x[lag:].ravel()
    ok = np.isfinite(a) & np.isfinite(b)
    return np.corrcoef(a[ok], b[ok])[0, 1]


def test_relay_path_variation_is_gauss_markov_with_its_parameters():
    zero = dict(sisre_gps_m=0.0, sisre_glonass_m=0.0, iono_zenith_m=0.0, tropo_zenith_m=0.0, multipath_a_m=0.0,
                multipath_b_m=0.0)
    rt = _static_relay(RelayErrorBudget(path_sigma_m=2.0, path_tau_s=40.0, **zero))
    v = rt.delta_d_m - C_M_S * (1.5e-6 + 100e-9)
    assert np.all(rt.pr_error_m == 0.0)
    assert abs(v.std() / 2.0 - 1.0) < 0.12  # 6 sondes x 1500 s / 40 s: ~200 independent values
    assert abs(_lag_corr(v, 1) - math.exp(-1 / 40)) < 0.01
    assert abs(_lag_corr(v, 40) - math.exp(-1.0)) < 0.12


def test_sisre_is_per_satellite_gauss_markov_with_the_system_std():
    zero = dict(iono_zenith_m=0.0, tropo_zenith_m=0.0, multipath_a_m=0.0, multipath_b_m=0.0, path_sigma_m=0.0)
    rt = _static_relay(RelayErrorBudget(sisre_gps_m=1.0, sisre_glonass_m=2.0, sisre_tau_s=30.0, **zero))
    glo = np.char.startswith(CONST.sat_id.astype(str), "R")
    e = rt.pr_error_m  # every satellite, delivered or not: the process runs regardless
    assert abs(e[..., ~glo].std() - 1.0) < 0.05 and abs(e[..., glo].std() - 2.0) < 0.1
    assert abs(_lag_corr(e, 1) - math.exp(-1 / 30)) < 0.01
    assert abs(_lag_corr(e, 30) - math.exp(-1.0)) < 0.05
    # independent between satellites
    assert abs(np.corrcoef(e[:, :, 0].ravel(), e[:, :, 1].ravel())[0, 1]) < 0.1
    np.testing.assert_array_equal(rt.delta_d_m, C_M_S * (1.5e-6 + 100e-9))


def test_multipath_is_short_correlated_and_follows_elevation():
    zero = dict(sisre_gps_m=0.0, sisre_glonass_m=0.0, iono_zenith_m=0.0, tropo_zenith_m=0.0, path_sigma_m=0.0)
    b = RelayErrorBudget(multipath_tau_s=5.0, **zero)
    rt = _static_relay(b, epochs=600)
    sig = b.multipath_sigma_m(rt.sat_el_at_sonde_rad)
    z = rt.pr_error_m / sig  # unit variance whatever the elevation
    assert abs(z.std() - 1.0) < 0.05
    assert abs(_lag_corr(z, 1) - math.exp(-1 / 5)) < 0.02 and abs(_lag_corr(z, 10) - math.exp(-2)) < 0.05
    assert b.multipath_sigma_m(0.0) == pytest.approx(0.66) and b.multipath_sigma_m(math.pi / 2) == pytest.approx(
        0.13, abs=1e-4)


def test_scale_functions():
    b = RelayErrorBudget()
    assert b.iono_obliquity(math.pi / 2) == pytest.approx(1.0)
    r = WGS84.a_m / (WGS84.a_m + 350e3)
    assert b.iono_obliquity(0.0) == pytest.approx(1.0 / math.sqrt(1 - r * r)) and 3.0 < b.iono_obliquity(0.0) < 3.2
    assert b.tropo_mapping(math.pi / 2) == pytest.approx(1.0, abs=1e-3) and 9.0 < b.tropo_mapping(math.radians(5)) < 12
    s0 = b.slow_sigmas_m(np.array([False, True]), math.radians(30.0), 0.0)
    s30 = b.slow_sigmas_m(np.array([False, True]), math.radians(30.0), 30_000.0)
    np.testing.assert_allclose(s0[:, 0], [0.6, 1.5])
    np.testing.assert_allclose(s0[:, 1], s30[:, 1])  # the ionosphere is above the sonde
    assert s30[0, 2] / s0[0, 2] == pytest.approx(pressure_ratio(30_000.0)) and pressure_ratio(30_000.0) < 0.015
    from sitl.atmosphere_std import P0_PA, us76
    h = np.linspace(-400.0, 40_000.0, 301)
    np.testing.assert_allclose(pressure_ratio(h), us76(h).pressure_pa / P0_PA, rtol=1e-5)


def test_error_budget_draws_are_seeded_and_per_sonde():
    a = _static_relay(RelayErrorBudget(), epochs=50, n=3, seed=5)
    b = _static_relay(RelayErrorBudget(), epochs=50, n=3, seed=5)
    c = _static_relay(RelayErrorBudget(), epochs=50, n=3, seed=6)
    np.testing.assert_array_equal(a.pr_error_m, b.pr_error_m)
    assert not np.allclose(a.pr_error_m, c.pr_error_m)


@pytest.mark.parametrize("kwargs", [dict(sisre_tau_s=0.0), dict(iono_zenith_m=-1.0), dict(path_tau_s=float("nan"))])
def test_bad_budget_raises(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        RelayErrorBudget(**kwargs)
    with pytest.raises(ValueError, match="errors"):
        RelayParams(errors="white")
