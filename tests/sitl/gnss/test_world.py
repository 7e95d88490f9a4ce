"""The GNSS world glue: trajectory -> light-time geometry -> elevation -> receiver (seed 000)."""
from __future__ import annotations

import inspect

import numpy as np
import pytest

from sitl.constants import C_M_S, F_GPS_L1_HZ, WGS84, glonass_l1_hz
from sitl.geodesy import ecef_to_aer, geocentric_elevation_rad, geodetic_to_ecef
from sitl.gnss.atmosphere import iono_slant_delay_m, tropo_slant_delay_m
from sitl.gnss.clock import ClockModel
from sitl.gnss.orbits import DEFAULT_TOA_GPS_S, GLONASS_SLOT_K, default_constellation
from sitl.gnss.ranging import light_time_geometry, sat_state_at_reception_frame
from sitl.gnss.receiver import Observation, Receiver, ReceiverConfig
from sitl.gnss.world import (
    ObservationTrack,
    ephemeris_for_filter,
    geometry_track,
    look_angles,
    observe,
    simulate_receiver,
    visible_count,
)
from tests.helpers import chi2_ok

CONST = default_constellation("GR")
S = len(CONST)
IS_GPS = CONST.system == "G"
RX_STATIC = geodetic_to_ecef(np.radians(45.0), np.radians(30.0), 200.0)
W_E = WGS84.omega_rad_s
# Inertial speed of any built-in satellite: circular speed sqrt(GM/a) (GPS 3874 m/s,
# GLONASS 3953 m/s) times at most sqrt((1+e)/(1-e)) = 1.025 for e <= 0.0244.
V_SAT_MAX_M_S = 4_000.0


@pytest.fixture(scope="module")
def static_2h():
    t = DEFAULT_TOA_GPS_S + np.arange(0.0, 7200.0 + 1.0, 30.0)
    pos = np.broadcast_to(RX_STATIC, (t.size, 3))
    return t, pos, simulate_receiver(np.random.default_rng(2024), t, pos, np.zeros(3), CONST,
                                     clock_bias0_m=100.0, clock_drift0_m_s=0.1)


def aircraft(n_epochs, dt_s, batch=3, seed=7):
    """(T,) times and (T, batch, 3) ECEF positions/velocities of aircraft at 10 km flying
    straight (constant ECEF velocity, 150-250 m/s) from points near 45 N 30 E."""
    rng = np.random.default_rng(seed)
    t = DEFAULT_TOA_GPS_S + 1800.0 + dt_s * np.arange(n_epochs)
    p0 = geodetic_to_ecef(np.radians(45.0 + rng.uniform(-3, 3, batch)),
                          np.radians(30.0 + rng.uniform(-3, 3, batch)), 10_000.0)
    v = rng.normal(0.0, 1.0, (batch, 3))
    v *= rng.uniform(150.0, 250.0, (batch, 1)) / np.linalg.norm(v, axis=1, keepdims=True)
    pos = p0 + (t - t[0])[:, None, None] * v
    return t, pos, np.broadcast_to(v, pos.shape)


# ---------------------------------------------------------------------------
# visibility and tracking over a static receiver's sky
# ---------------------------------------------------------------------------

def test_static_receiver_sky_changes_and_mask_is_respected(static_2h):
    t, pos, tr = static_2h
    cfg = ReceiverConfig()
    assert isinstance(tr, ObservationTrack) and len(tr) == t.size and tr.batch_shape == ()
    vis = tr.visible
    assert vis.shape == (t.size, S)

    # a realistic number in view for GPS + GLONASS above 5 deg
    n = visible_count(tr)
    assert n.min() >= 12 and n.max() <= 24
    assert visible_count(tr, CONST, "G").min() >= 6 and visible_count(tr, CONST, "R").min() >= 4
    np.testing.assert_array_equal(n, visible_count(tr, CONST, "G") + visible_count(tr, CONST, "R"))

    # the sky changes: satellites rise and set
    rise = vis[1:] & ~vis[:-1]
    set_ = vis[:-1] & ~vis[1:]
    assert rise.sum() >= 1 and set_.sum() >= 1

    # elevation is the geodetic one of the satellite at emission (reception frame)
    geo = light_time_geometry(t, pos, np.zeros(3), CONST)
    _, el_ref, _ = ecef_to_aer(pos[:, None, :], geo.sat_pos_ecef_m)
    np.testing.assert_allclose(tr.el_rad, el_ref, rtol=0, atol=1e-9)
    # ... which differs from the spherical-Earth elevation by less than the 0.19 deg
    # geodetic-geocentric latitude difference at 45 N
    el_sph = geocentric_elevation_rad(pos[:, None, :], geo.sat_pos_ecef_m)
    assert np.abs(tr.el_rad - el_sph).max() < np.radians(0.2)

    # tracked exactly when el >= mask; nothing is measured below it
    np.testing.assert_array_equal(vis, tr.el_rad >= cfg.el_mask_rad)
    for name in ("pseudorange_m", "pseudorange_rate_m_s", "carrier_phase_m", "carrier_phase_cycles",
                 "ambiguity_cycles", "iono_slant_m", "tropo_slant_m"):
        a = getattr(tr, name)
        assert np.all(np.isnan(a[~vis])), name
        assert np.all(np.isfinite(a[vis])), name
    assert np.all(tr.lock_count[~vis] == -1)

    # acquisition (first epoch or a rise) restarts the lock count at 0 with no slip flag;
    # while tracked the count goes up by one and the ambiguity stays (no slips configured)
    lc = tr.lock_count
    assert np.all(lc[0][vis[0]] == 0)
    assert np.all(lc[1:][rise] == 0) and not tr.slip.any()
    kept = vis[1:] & vis[:-1]
    np.testing.assert_array_equal(lc[1:][kept], lc[:-1][kept] + 1)
    np.testing.assert_array_equal(tr.ambiguity_cycles[1:][kept], tr.ambiguity_cycles[:-1][kept])
    # a rising satellite's ambiguity is a fresh draw, not one held by anyone before
    held = set(tr.ambiguity_cycles[0][vis[0]].tolist())
    fresh = tr.ambiguity_cycles[1:][rise]
    assert not held & set(fresh.tolist())

    # the epoch view is the receiver's Observation
    o = tr.epoch(-1)
    assert isinstance(o, Observation) and o.t_gps_s == t[-1]
    np.testing.assert_array_equal(o.pseudorange_m, tr.pseudorange_m[-1])


def test_satellite_that_sets_and_rises_again_gets_a_new_ambiguity():
    # 12 h at 10 min: most GPS satellites set and come back within half a sidereal day
    t = DEFAULT_TOA_GPS_S + np.arange(0.0, 12 * 3600.0 + 1.0, 600.0)
    pos = np.broadcast_to(RX_STATIC, (t.size, 3))
    tr = simulate_receiver(np.random.default_rng(5), t, pos, np.zeros(3), CONST)
    returns = 0
    for j in range(S):
        v = tr.visible[:, j]
        for k_set in np.flatnonzero(v[:-1] & ~v[1:]):
            later = np.flatnonzero(v[k_set + 1:])
            if later.size == 0:
                continue
            k_rise = k_set + 1 + later[0]
            returns += 1
            assert tr.lock_count[k_rise, j] == 0
            assert tr.ambiguity_cycles[k_rise, j] != tr.ambiguity_cycles[k_set, j]
            assert np.all(np.isnan(tr.pseudorange_m[k_set + 1:k_rise, j]))
    assert returns >= 3


# ---------------------------------------------------------------------------
# measurement content against an independent truth
# ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def flight():
    cfg = ReceiverConfig(gps_glonass_offset_m=25.0)
    t, pos, vel = aircraft(121, 10.0, batch=3)
    tr = simulate_receiver(np.random.default_rng(99), t, pos, vel, CONST, cfg,
                           clock_bias0_m=np.array([100.0, -3.0e4, 0.0]), clock_drift0_m_s=0.2)
    return cfg, t, pos, vel, tr


def truth_terms(cfg, t, pos, vel, tr):
    """Independent truth: one vectorised light-time solution over all epochs, geodetic
    elevations (the mask), the seed's atmosphere mapped on the geocentric elevation of
    seed 000 eq. 10 (written out here), with the FDMA carriers from constants.py."""
    geo = light_time_geometry(t[:, None], pos, vel, CONST)
    _, el, _ = ecef_to_aer(pos[..., None, :], geo.sat_pos_ecef_m)
    X = pos[..., None, :]
    d = geo.sat_pos_ecef_m - X
    el_geoc = np.arcsin(np.sum(d * X, axis=-1) / (np.linalg.norm(X, axis=-1) * np.linalg.norm(d, axis=-1)))
    k = np.array([0 if s[0] == "G" else GLONASS_SLOT_K[int(s[1:]) - 1] for s in CONST.sat_id])
    f = np.where(IS_GPS, F_GPS_L1_HZ, glonass_l1_hz(k))
    with np.errstate(invalid="ignore", divide="ignore"):
        iono = iono_slant_delay_m(cfg.iono_zenith_m, el_geoc, f)
        tropo = tropo_slant_delay_m(cfg.tropo_zenith_m, el_geoc)
    offset = np.where(IS_GPS, cfg.gps_glonass_offset_m, 0.0)
    return geo, el, iono, tropo, offset, C_M_S / f


def test_measurements_have_the_configured_noise_about_the_truth(flight):
    cfg, t, pos, vel, tr = flight
    geo, el, iono, tropo, offset, lam = truth_terms(cfg, t, pos, vel, tr)
    vis = tr.visible
    assert vis.sum() > 3 * 121 * 12
    np.testing.assert_allclose(tr.range_m, geo.range_m, rtol=0, atol=1e-5)
    np.testing.assert_allclose(tr.range_rate_m_s, geo.range_rate_m_s, rtol=0, atol=1e-6)
    np.testing.assert_allclose(tr.el_rad, el, rtol=0, atol=1e-12)
    np.testing.assert_allclose(tr.iono_slant_m[vis], iono[vis], rtol=1e-12)
    np.testing.assert_allclose(tr.tropo_slant_m[vis], tropo[vis], rtol=1e-12)
    bias, drift = tr.clock_bias_m[..., None], tr.clock_drift_m_s[..., None]
    n_amb = tr.ambiguity_cycles

    e_pr = tr.pseudorange_m - (geo.range_m + bias + offset + tropo + iono)
    e_prr = tr.pseudorange_rate_m_s - (geo.range_rate_m_s + drift)
    e_ph = tr.carrier_phase_m - (geo.range_m + bias + offset + tropo - iono + lam * n_amb)
    # code minus carrier = 2 I - lambda N + (eps_D - eps_G): the ionosphere delays code and
    # advances phase; the ambiguity sits on the phase
    e_cmc = (tr.pseudorange_m - tr.carrier_phase_m) - (2.0 * iono - lam * n_amb)
    for e, sigma in ((e_pr, cfg.sigma_pr_m), (e_prr, cfg.sigma_prr_m_s), (e_ph, cfg.sigma_phase_m),
                     (e_cmc, np.hypot(cfg.sigma_pr_m, cfg.sigma_phase_m))):
        e = e[vis]
        assert np.all(np.isfinite(e))
        assert chi2_ok(e, sigma)
        assert not chi2_ok(e, 1.1 * sigma) and not chi2_ok(e, sigma / 1.1)  # the test has power
        assert abs(e.mean()) < 4.0 * sigma / np.sqrt(e.size)
    # the GPS-GLONASS offset is on GPS only: a GPS-only / GLONASS-only mean split
    assert abs(e_pr[vis & IS_GPS].mean()) < 4.0 * cfg.sigma_pr_m / np.sqrt((vis & IS_GPS).sum())
    # clock follows the seed's model from the given start (per trial)
    np.testing.assert_array_equal(tr.clock_bias_m[0], [100.0, -3.0e4, 0.0])
    np.testing.assert_array_equal(tr.clock_drift_m_s[0], [0.2, 0.2, 0.2])


def test_clock_increments_follow_the_two_state_model():
    # 400 trials, 3 epochs 30 s apart: increments minus F x must have covariance Q(30 s)
    clk = ClockModel(psd_1_s=1e-19)
    t = DEFAULT_TOA_GPS_S + np.array([0.0, 30.0, 60.0])
    pos = np.broadcast_to(RX_STATIC, (3, 400, 3))
    tr = simulate_receiver(np.random.default_rng(3), t, pos, np.zeros(3), CONST.subset("G01"),
                           clock=clk, clock_bias0_m=50.0, clock_drift0_m_s=-0.5)
    b, d = tr.clock_bias_m, tr.clock_drift_m_s
    xi = np.stack([b[1:] - b[:-1] - 30.0 * d[:-1], d[1:] - d[:-1]], axis=-1).reshape(-1, 2)
    L_inv = np.linalg.inv(np.linalg.cholesky(clk.Q(30.0)))
    w = xi @ L_inv.T  # whitened: N(0, I)
    assert chi2_ok(w.ravel(), 1.0)
    assert abs(np.corrcoef(w.T)[0, 1]) < 4.0 / np.sqrt(w.shape[0])


def test_glonass_fdma_wavelengths_and_phase_in_cycles(flight):
    cfg, t, pos, vel, tr = flight
    for j, sid in enumerate(tr.sat_id):
        if sid.startswith("R"):
            k = GLONASS_SLOT_K[int(sid[1:]) - 1]
            assert tr.wavelength_m[j] == pytest.approx(C_M_S / (1602.0e6 + k * 0.5625e6), rel=1e-15)
        else:
            assert tr.wavelength_m[j] == pytest.approx(C_M_S / 1575.42e6, rel=1e-15)
    glo = ~IS_GPS
    assert len(set(np.round(tr.wavelength_m[glo], 12).tolist())) == 12  # 12 channels for 24 slots
    vis = tr.visible
    np.testing.assert_allclose((tr.carrier_phase_cycles * tr.wavelength_m)[vis], tr.carrier_phase_m[vis],
                               rtol=1e-15)
    # dispersive delay scales with 1/f^2 per channel: GLONASS below GPS at equal elevation
    # (the atmosphere is mapped on the geocentric elevation, seed 000 eq. 10)
    geo = light_time_geometry(t[:, None], pos, vel, CONST)
    el_geoc = geocentric_elevation_rad(pos[..., None, :], geo.sat_pos_ecef_m)
    ratio = tr.iono_slant_m / iono_slant_delay_m(cfg.iono_zenith_m, el_geoc, F_GPS_L1_HZ)
    np.testing.assert_allclose(ratio[vis & glo], ((tr.wavelength_m / (C_M_S / F_GPS_L1_HZ)) ** 2
                                                  * np.ones_like(ratio))[vis & glo], rtol=1e-12)


# ---------------------------------------------------------------------------
# what the estimator sees
# ---------------------------------------------------------------------------

def test_ephemeris_for_filter_uses_no_truth_and_matches_the_emission_states():
    params = list(inspect.signature(ephemeris_for_filter).parameters)
    assert params == ["t_rx_gps_s", "pseudorange_m", "constellation", "pseudorange_rate_m_s",
                      "clock_bias_est_m", "ell"]

    cfg = ReceiverConfig()
    t, pos, vel = aircraft(1, 1.0, batch=8, seed=3)
    t, pos, vel = t[0], pos[0], vel[0]
    rx = Receiver(S, cfg, (8,))
    obs = observe(np.random.default_rng(1), t, pos, vel, 100.0, 0.3, CONST, rx)
    geo = light_time_geometry(t, pos, vel, CONST)
    vis = obs.visible

    sat_pos, sat_vel = ephemeris_for_filter(t, obs.pseudorange_m, CONST)
    assert sat_pos.shape == (8, S, 3) and sat_vel.shape == (8, S, 3)
    assert np.all(np.isnan(sat_pos[~vis])) and np.all(np.isfinite(sat_pos[vis]))
    err = np.linalg.norm(sat_pos - geo.sat_pos_ecef_m, axis=-1)[vis]

    # The measured transit time pr/c exceeds the true one by (clock 100 m + tropo + iono
    # + noise)/c; moving the emission time by dtau moves s = R3(w tau) p(t - tau) by
    # ds/dtau = -(R3 v + w z x s), the inertial velocity: |ds| <= 4 km/s * |dtau|.
    dtau = (obs.pseudorange_m - geo.range_m) / C_M_S
    bound = V_SAT_MAX_M_S * np.abs(dtau)[vis] + 1e-6
    assert np.all(err <= bound)
    # 100 m + at most 28.7 m tropo + 43 m iono (5 deg) + 5 sigma noise ~ 200 m -> < 2.7 mm
    assert err.max() < 3e-3 and err.max() < 1e-2
    assert err.min() > 5e-4  # not the truth: 100 m of clock alone moves a satellite ~1.3 mm

    # and it is exactly that first-order motion (second order: |a| dtau^2 / 2 < 1e-12 m)
    s0, rv = sat_state_at_reception_frame(t, geo.tau_s, CONST)
    w_in = rv + W_E * np.stack([-s0[..., 1], s0[..., 0], np.zeros_like(s0[..., 0])], axis=-1)
    pred = geo.sat_pos_ecef_m - w_in * dtau[..., None]
    np.testing.assert_allclose(sat_pos[vis], pred[vis], rtol=0, atol=1e-6)

    # velocities: with the measured rate as tau' they match the exact ds/dt_rx to << mm/s;
    # without it they miss the tau' w_in term (< |range rate|/c * 4 km/s ~ 1e-2 m/s)
    _, vel_f = ephemeris_for_filter(t, obs.pseudorange_m, CONST, pseudorange_rate_m_s=obs.pseudorange_rate_m_s)
    dv = np.linalg.norm(vel_f - geo.sat_vel_ecef_m_s, axis=-1)[vis]
    assert dv.max() < 1e-4
    dv0 = np.linalg.norm(sat_vel - geo.sat_vel_ecef_m_s, axis=-1)[vis]
    assert dv0.max() < V_SAT_MAX_M_S * np.abs(geo.range_rate_m_s[vis]).max() / C_M_S + 1e-4
    assert dv0.max() > 1e-3

    # the estimator's own clock estimate is subtracted before forming tau
    pos_b, _ = ephemeris_for_filter(t, obs.pseudorange_m, CONST, clock_bias_est_m=np.full(8, 100.0))
    err_b = np.linalg.norm(pos_b - geo.sat_pos_ecef_m, axis=-1)[vis]
    assert err_b.max() < err.max()


def test_ephemeris_for_filter_along_a_track_with_a_drifting_clock(static_2h):
    # The free-running TCXO of seed 000 walks ~10 km in 2 h: the raw transit time then
    # misplaces satellites by up to |bias|/c * 4 km/s ~ 0.15 m, always within the bound;
    # an estimator that removes its clock estimate gets back below the cm.
    t, pos, tr = static_2h
    geo = light_time_geometry(t, pos, np.zeros(3), CONST)
    sat_pos, _ = ephemeris_for_filter(t, tr.pseudorange_m, CONST)
    vis = tr.visible
    err = np.linalg.norm(sat_pos - geo.sat_pos_ecef_m, axis=-1)[vis]
    dtau = ((tr.pseudorange_m - geo.range_m) / C_M_S)[vis]
    assert np.all(err <= V_SAT_MAX_M_S * np.abs(dtau) + 1e-6)
    assert np.abs(tr.clock_bias_m).max() > 1e3  # exercised: ~7 km with this seed (random-walk std ~9 km at 2 h)
    # an estimator within 100 m of the true clock
    est = tr.clock_bias_m + np.random.default_rng(0).uniform(-100.0, 100.0, tr.clock_bias_m.shape)
    sat_pos_c, _ = ephemeris_for_filter(t, tr.pseudorange_m, CONST, clock_bias_est_m=est)
    assert np.linalg.norm(sat_pos_c - geo.sat_pos_ecef_m, axis=-1)[vis].max() < 1e-2


# ---------------------------------------------------------------------------
# determinism, batching and bad input
# ---------------------------------------------------------------------------

def test_same_seed_same_track_and_batch_axes():
    t, pos, vel = aircraft(4, 1.0, batch=2)
    a = simulate_receiver(np.random.default_rng(11), t, pos, vel, CONST)
    b = simulate_receiver(np.random.default_rng(11), t, pos, vel, CONST)
    np.testing.assert_array_equal(a.pseudorange_m, b.pseudorange_m)
    np.testing.assert_array_equal(a.carrier_phase_m, b.carrier_phase_m)
    assert a.pseudorange_m.shape == (4, 2, S) and a.clock_bias_m.shape == (4, 2)
    # a 2-D trial batch works too
    pos2 = np.broadcast_to(pos[:, :, None, :], (4, 2, 3, 3))
    c = simulate_receiver(np.random.default_rng(11), t, pos2, np.zeros(3), CONST)
    assert c.pseudorange_m.shape == (4, 2, 3, S) and c.batch_shape == (2, 3)


def test_bad_input_raises_value_error_naming_the_parameter():
    t, pos, vel = aircraft(3, 1.0, batch=2)
    rng = np.random.default_rng(0)

    def sim(**kw):
        args = dict(rng=rng, t_gps_s=t, rx_pos_ecef_m=pos, rx_vel_ecef_m_s=vel, constellation=CONST)
        args.update(kw)
        return simulate_receiver(**args)

    cases = [
        (dict(rng=0), "rng"),
        (dict(t_gps_s=t[::-1]), "t_gps_s"),
        (dict(t_gps_s=np.r_[t[:2], np.nan]), "t_gps_s"),
        (dict(t_gps_s=t[:, None]), "t_gps_s"),
        (dict(rx_pos_ecef_m=pos[:2]), "rx_pos_ecef_m"),
        (dict(rx_pos_ecef_m=pos[..., :2]), "rx_pos_ecef_m"),
        (dict(rx_vel_ecef_m_s=vel[:, :1, :2]), "rx_vel_ecef_m_s"),
        (dict(rx_vel_ecef_m_s=np.zeros((3, 5, 3))), "rx_vel_ecef_m_s"),
        (dict(constellation="GR"), "constellation"),
        (dict(receiver_config={"sigma_pr_m": 1.0}), "receiver_config"),
        (dict(clock=1e-20), "clock"),
        (dict(clock_bias0_m=np.zeros(5)), "clock_bias0_m"),
        (dict(clock_drift0_m_s=np.inf), "clock_drift0_m_s"),
    ]
    for kw, name in cases:
        with pytest.raises(ValueError, match=name):
            sim(**kw)

    rx = Receiver(S, None, (2,))
    p, v = pos[0], vel[0]
    obs_cases = [
        (lambda: observe(rng, t[:2], p, v, 0.0, 0.0, CONST, rx), "t_gps_s"),
        (lambda: observe(rng, t[0], p, v, 0.0, 0.0, CONST, Receiver(S - 1, None, (2,))), "receiver"),
        (lambda: observe(rng, t[0], p, v, 0.0, 0.0, CONST, "rx"), "receiver"),
        (lambda: observe(rng, t[0], np.zeros((5, 3)), v, 0.0, 0.0, CONST, rx), "rx_pos_ecef_m"),
        (lambda: observe(rng, t[0], p, np.zeros((5, 3)), 0.0, 0.0, CONST, rx), "rx_vel_ecef_m_s"),
        (lambda: observe(rng, t[0], p, v, np.zeros(5), 0.0, CONST, rx), "clock_bias_m"),
        (lambda: observe(rng, t[0], p, v, 0.0, np.nan, CONST, rx), "clock_drift_m_s"),
        (lambda: observe(None, t[0], p, v, 0.0, 0.0, CONST, rx), "rng"),
    ]
    for fn, name in obs_cases:
        with pytest.raises(ValueError, match=name):
            fn()
    observe(rng, t[1], p, v, 0.0, 0.0, CONST, rx)
    with pytest.raises(ValueError, match="t_gps_s"):  # epochs must increase
        observe(rng, t[0], p, v, 0.0, 0.0, CONST, rx)

    pr = np.full((2, S), 2.2e7)
    eph_cases = [
        (lambda: ephemeris_for_filter(t[0], pr[:, :-1], CONST), "pseudorange_m"),
        (lambda: ephemeris_for_filter(t[0], np.where(pr > 0, np.inf, 0), CONST), "pseudorange_m"),
        (lambda: ephemeris_for_filter(t, pr, CONST), "t_rx_gps_s"),
        (lambda: ephemeris_for_filter(t[0], pr, CONST.subset("G01")), "pseudorange_m"),
        (lambda: ephemeris_for_filter(t[0], pr, None), "constellation"),
        (lambda: ephemeris_for_filter(t[0], pr, CONST, pseudorange_rate_m_s=pr[:1]), "pseudorange_rate_m_s"),
        (lambda: ephemeris_for_filter(t[0], pr, CONST, clock_bias_est_m=np.zeros(3)), "clock_bias_est_m"),
    ]
    for fn, name in eph_cases:
        with pytest.raises(ValueError, match=name):
            fn()
    with pytest.raises(ValueError, match="system"):
        visible_count(np.ones((2, S), bool), CONST, "E")


def test_geometry_track_equals_per_epoch_geometry():
    """Blocks of epochs in one call give what one call per epoch gives (to the ephemeris
    interpolation: 1e-7 m, 1e-6 m/s), across block boundaries and a ragged last block."""
    t = DEFAULT_TOA_GPS_S + 900.0 + 0.1 * np.arange(23)
    pos = RX_STATIC + np.outer(np.arange(23), [30.0, -20.0, 5.0])
    vel = np.broadcast_to([300.0, -200.0, 50.0], (23, 3))
    track = list(geometry_track(t, pos, vel, CONST, block=10))
    assert len(track) == 23
    for k in (0, 9, 10, 22):
        g = light_time_geometry(t[k], pos[k], vel[k], CONST)
        _, el = look_angles(pos[k], g)
        e = track[k]
        assert e.t_gps_s == t[k]
        np.testing.assert_allclose(e.geometry.range_m, g.range_m, rtol=0, atol=1e-7)
        np.testing.assert_allclose(e.geometry.range_rate_m_s, g.range_rate_m_s, rtol=0, atol=1e-6)
        np.testing.assert_allclose(e.el_rad, el, rtol=0, atol=1e-12)
        np.testing.assert_allclose(e.el_atmo_rad, geocentric_elevation_rad(pos[k][None, :], g.sat_pos_ecef_m),
                                   rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="block"):
        next(geometry_track(t, pos, vel, CONST, block=0))
    with pytest.raises(ValueError, match="shape"):
        next(geometry_track(t, pos[:5], vel, CONST))
