"""The sonde tracker over a long coast (issue 19, "estimates stay right over long runs"): a
descending sonde that no source measures any more, its landing, and the coast limit.

On the 6 h demo the sonde track, once the relay and the radar had lost the sonde, descended and
landed with a constant ~35 km error and an ANEES of ~9000: the old relaxed model's wind changed at
a Gauss-Markov rate in time (the ascent's statistics), while in the descent the sonde crosses the
wind profile ~3x faster; the landing dropped the height's uncertainty instead of carrying it on
as horizontal uncertainty. References here are the world's own code (vehicles.sonde.SondeFlight,
sitl.radio.relay.Relay) and chi-square bands: the sondes are independent (each its own wind
profile, drawn with the shear statistics the tracker assumes, and its own gusts).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.stats import chi2

from ground_station.sonde import SondeTracker, SondeTrackerParams
from sitl.bus import SondeRelay
from sitl.app.experiments import sonde as E
from sitl.geodesy import ecef_to_geodetic, enu_rotation
from sitl.gnss.orbits import DEFAULT_TOA_GPS_S, default_constellation
from sitl.radio.relay import Relay
from vehicles.sonde import DESCENT, LANDED, SondeFlight, SondeParams

T0 = DEFAULT_TOA_GPS_S
BURST_M = 12_000.0
KNOT_M = 250.0


def _profile(rng, sigma_s: float, corr_h: float, top: float = 15_000.0) -> SondeParams:
    """A sonde model with its own mean wind profile: a random wind at the ground plus a shear
    that is Gauss-Markov in height (std sigma_s per axis, correlation height corr_h), held over
    250 m layers (piecewise-linear components, on the world's 10 m grid)."""
    h = np.arange(0.0, top + KNOT_M, KNOT_M)
    rho = math.exp(-KNOT_M / corr_h)
    s = np.empty((h.size - 1, 2))
    s[0] = sigma_s * rng.standard_normal(2)
    for i in range(1, s.shape[0]):
        s[i] = rho * s[i - 1] + sigma_s * math.sqrt(1.0 - rho * rho) * rng.standard_normal(2)
    uv = np.vstack([rng.normal(0.0, 10.0, 2), np.zeros((h.size - 1, 2))])
    uv[1:] = uv[0] + np.cumsum(s * KNOT_M, axis=0)
    spd = np.hypot(uv[:, 0], uv[:, 1])
    frm = np.arctan2(-uv[:, 0], -uv[:, 1])  # the direction the wind blows from
    sp = SondeParams(wind_alt_m=tuple(h), wind_speed_m_s=tuple(spd), wind_from_rad=tuple(frm))
    np.testing.assert_allclose(sp.wind_enu_m_s(h), uv, atol=1e-9)
    return sp


def _relay_msg(rt, k, b, t, seq):
    d = rt.delivered[k, b]
    return SondeRelay(t_gps_s=t, source_id="g", seq=seq, sat_ids=rt.sat_id[d], pseudorange_m=rt.pseudorange_m[k, b][d],
                      pseudo_doppler_m_s=rt.pseudo_doppler_m_s[k, b][d], var_pseudorange_m2=rt.var_pr_m2[k, b][d],
                      var_pseudo_doppler_m2_s2=rt.var_prr_m2_s2[k, b][d], sat_pos_ecef_m=rt.sat_pos_ecef_m[k, b][d],
                      sat_vel_ecef_m_s=rt.sat_vel_ecef_m_s[k, b][d], ground_pos_ecef_m=rt.ground_pos_ecef_m)


def _descent_coast(n: int, seed: int, track_s=(90.0, 330.0), end_after_landing_s: float = 300.0, **overrides):
    """n independent sondes (each its own wind profile and gusts) bursting at 12 km; relayed GNSS
    from ``track_s`` (s after the burst) only, in the descent; nothing after. A relay-only tracker
    (the experiment's parameters, the shear statistics the profiles are drawn with) steps at 1 Hz
    until ``end_after_landing_s`` after the last sonde's landing. Returns (t since the burst (T,),
    phase (T, n), truth positions (T, n, 3), the published position errors (T, n, 3) and covariances
    (T, n, 3, 3), NaN without an Estimate, the tracker)."""
    base = E.tracker_params(E.SondeScenario(), "relay_only")
    params = dataclasses.replace(base, wind_shear_sigma_horizontal_1_s=SondeTrackerParams().wind_shear_sigma_horizontal_1_s,
                                 wind_shear_corr_height_m=SondeTrackerParams().wind_shear_corr_height_m, **overrides)
    root = np.random.SeedSequence(seed)
    kids = [np.random.default_rng(s) for s in root.spawn(2 * n)]
    tracks = []
    for b in range(n):
        sp = _profile(kids[b], params.wind_shear_sigma_horizontal_1_s, params.wind_shear_corr_height_m)
        tracks.append(SondeFlight([kids[n + b]], params=sp, t0_gps_s=T0, burst_alt_m=BURST_M)
                      .simulate(until_landed=True, max_duration_s=3 * 3600.0))
    k_burst = min(int(np.argmax(tr.phase[:, 0] == DESCENT)) for tr in tracks)
    k_end = max(len(tr) for tr in tracks) - 1 + int(end_after_landing_s)
    T = k_end - k_burst + 1
    pos = np.empty((T, n, 3))
    phase = np.empty((T, n), dtype=np.int8)
    for b, tr in enumerate(tracks):  # landed sondes stay where they are
        m = min(len(tr) - k_burst, T)
        pos[:m, b], phase[:m, b] = tr.pos_ecef_m[k_burst:k_burst + m, 0], tr.phase[k_burst:k_burst + m, 0]
        pos[m:, b], phase[m:, b] = tr.pos_ecef_m[-1, 0], LANDED
    t = T0 + np.arange(k_burst, k_end + 1, dtype=float)
    k0, k1 = int(track_s[0]), int(track_s[1])
    vel = np.stack([tr.vel_ecef_m_s[k_burst + k0:k_burst + k1, 0] for tr in tracks], axis=1)
    lat, lon, h = E.gcpp_site(E.SondeScenario())
    rt = Relay([np.random.default_rng(s) for s in np.random.SeedSequence(seed + 1).spawn(n)],
               default_constellation("GR"), ground_lat_rad=lat, ground_lon_rad=lon, ground_h_m=h,
               batch_shape=(n,)).track(t[k0:k1], pos[k0:k1], vel)
    trk = SondeTracker("t19", params)
    d_out, cov_out = np.full((T, n, 3), np.nan), np.full((T, n, 3, 3), np.nan)
    for k in range(k0, T):
        if k < k1:
            for b in range(n):
                trk.on_message(f"t19/sonde/s{b}/relay", _relay_msg(rt, k - k0, b, float(t[k]), k))
        ests = trk.step(float(t[k]))
        live = [int(s[1:]) for s in trk.sondes if trk.state(s) is not None]  # step's order: the slots'
        assert len(live) == len(ests)
        for b, est in zip(live, ests):
            d_out[k, b], cov_out[k, b] = est.pos_ecef_m - pos[k, b], est.cov[:3, :3]
    return t - t[0], phase, pos, d_out, cov_out, trk


def _nees(d, cov):
    """Position NEES of errors d (..., 3) under cov (..., 3, 3) (NaN where there is none)."""
    ok = np.isfinite(d[..., 0])
    out = np.full(d.shape[:-1], np.nan)
    out[ok] = np.einsum("ni,ni->n", d[ok], np.linalg.solve(cov[ok], d[ok][..., None])[..., 0])
    return out


def _enu(p_ecef):
    """ENU rotations (n, 3, 3) at positions (n, 3)."""
    lat, lon, _ = ecef_to_geodetic(p_ecef)
    return np.stack([enu_rotation(float(a), float(o)) for a, o in zip(np.atleast_1d(lat), np.atleast_1d(lon))])


def _landed_nees_band(cov, p_ecef, rng, draws: int = 20_000, q=(0.005, 0.995)):
    """The 99 % band of the mean position NEES of landed sondes when each one's horizontal error is
    N(0, its published horizontal covariance) and it lies on the ground: curved, so |d|^2 / 2R
    below the estimate's tangent plane (not Gaussian: a chi-square band does not apply to that
    part). cov (n, 3, 3), p_ecef (n, 3): the published covariances and positions. Seeded Monte Carlo."""
    n = cov.shape[0]
    tot = np.zeros(draws)
    r_all = np.linalg.norm(p_ecef, axis=1)
    for b in range(n):
        R = _enu(p_ecef[b:b + 1])[0]
        up, Rh = R[2], R[:2]  # the tangent plane at the estimate
        Ch = Rh @ cov[b] @ Rh.T
        z = rng.multivariate_normal(np.zeros(2), Ch, draws)
        d = z @ Rh - (np.sum(z * z, axis=1) / (2.0 * r_all[b]))[:, None] * up
        tot += np.einsum("ni,ni->n", d, np.linalg.solve(cov[b], d.T).T)
    return tuple(np.quantile(tot / n, q))


N_MC = 16


@pytest.fixture(scope="module")
def coast():
    return _descent_coast(N_MC, seed=19, max_coast_s=None)


def test_a_descent_coast_and_the_landing_are_consistent(coast):
    tau, phase, pos, d, cov, trk = coast
    n = d.shape[1]
    assert trk.counters.landings == n and trk.counters.lost == 0
    nz = _nees(d, cov)
    lo, hi = chi2.ppf([0.005, 0.995], 3 * n) / n  # the mean position NEES of n independent sondes at one epoch
    land = [int(np.argmax(phase[:, b] == LANDED)) for b in range(n)]
    k1 = 330
    coast_k = np.arange(k1 + 60, min(land) - 10, 120)  # every 2 min of the coast, from 1 min in
    assert coast_k.size >= 10
    # the errors grow large (the wind the sondes meet is unknown: tens of km by the ground) ...
    rms = np.sqrt(np.mean(np.sum(d ** 2, axis=2), axis=1))
    assert rms[coast_k[-1]] > 10_000.0
    # ... and the published covariance follows them: the mean NEES inside the band all the way down
    for k in coast_k:
        assert lo <= np.mean(nz[k]) <= hi, (k, float(np.mean(nz[k])), (lo, hi))
    # landed: at rest, the error constant; the height's uncertainty carried on as horizontal
    # uncertainty along the trajectory, the ground's curvature below the tangent plane
    k_end = len(tau) - 1
    np.testing.assert_allclose(d[k_end], d[k_end - 100], atol=1e-6)
    rng = np.random.default_rng(7)
    for k in (k_end - 100, k_end):  # (every track landed by then)
        p_est = d[k] + pos[k]
        band = _landed_nees_band(cov[k], p_est, rng)
        assert band[0] <= np.mean(nz[k]) <= band[1], (k, float(np.mean(nz[k])), band)
        # the horizontal part (the tangent plane at the estimate) is Gaussian: its chi-square band
        R = _enu(p_est)
        up, Rh = R[:, 2], R[:, :2]
        dh = np.einsum("nij,nj->ni", Rh, d[k])
        Ch = Rh @ cov[k] @ np.swapaxes(Rh, 1, 2)
        nh = np.einsum("ni,ni->n", dh, np.linalg.solve(Ch, dh[..., None])[..., 0])
        lo2, hi2 = chi2.ppf([0.005, 0.995], 2 * n) / n
        assert lo2 <= np.mean(nh) <= hi2, (k, float(np.mean(nh)), (lo2, hi2))
        # on the ground, as the sonde: only the curvature apart
        r = np.linalg.norm(p_est, axis=1)
        np.testing.assert_allclose(np.einsum("ni,ni->n", d[k], up), np.sum(dh ** 2, axis=1) / (2.0 * r),
                                   rtol=0.02, atol=1.0)


# ---------------------------------------------------------------- the coast limit (max_coast_s)

RUN = "t19c"
KEY = f"{RUN}/sonde/s1/relay"


@pytest.fixture(scope="module")
def relay_world():
    """One sonde of the experiment's scenario, 200 s of truth and relayed GNSS."""
    streams = E._trial_streams(23, [0])[0]
    lat, lon, h = E.gcpp_site(E.SondeScenario())
    tr = SondeFlight([streams[0]], params=E._sonde_params(E.SondeScenario()), t0_gps_s=T0).simulate(200)
    rt = Relay([streams[2]], default_constellation("GR"), ground_lat_rad=lat, ground_lon_rad=lon, ground_h_m=h,
               batch_shape=(1,)).track(tr.t_gps_s, tr.pos_ecef_m, tr.vel_ecef_m_s)
    return tr, rt


def _run(rt, params, feed, steps, late=None):
    """A tracker fed the relay epochs ``feed`` (in time), stepped at ``steps``; ``late``: {step k:
    [epochs delivered just before step k]} (late messages). Returns (tracker, {k: Estimates})."""
    trk = SondeTracker(RUN, params)
    out = {}
    for k in steps:
        for j in (late or {}).get(k, []):
            trk.on_message(KEY, _relay_msg(rt, j, 0, float(rt.t_gps_s[j]), j))
        if k in feed:
            trk.on_message(KEY, _relay_msg(rt, k, 0, float(rt.t_gps_s[k]), k))
        out[k] = trk.step(float(rt.t_gps_s[k]))
    return trk, out


def test_a_track_without_measurements_for_max_coast_s_is_lost_and_reinitialised(relay_world):
    tr, rt = relay_world
    params = dataclasses.replace(E.tracker_params(E.SondeScenario(), "relay_only"), max_coast_s=20.0)
    assert SondeTrackerParams().max_coast_s == 300.0  # the default
    feed = set(range(10, 61)) | set(range(120, 151))
    trk, out = _run(rt, params, feed, range(10, 151))
    # coasting up to max_coast_s after the last accepted measurement (60): published
    assert all(len(out[k]) == 1 for k in range(10, 81))
    assert trk.counters.lost == 1
    # beyond it: lost, nothing published, no state
    assert all(out[k] == [] for k in range(81, 120))
    # the next measurement initialises it again, as at its acquisition, and it tracks
    assert trk.counters.init_relay == 2 and len(out[120]) == 1
    assert all(len(out[k]) == 1 for k in range(120, 151))
    assert np.linalg.norm(out[150][0].pos_ecef_m - tr.pos_ecef_m[150, 0]) < 5.0
    assert trk.counters.lost == 1
    # None: never lost (the behaviour before), it coasts on
    trk2, out2 = _run(rt, dataclasses.replace(params, max_coast_s=None), feed, range(10, 151))
    assert trk2.counters.lost == 0 and trk2.counters.init_relay == 1 and all(len(out2[k]) == 1 for k in range(10, 151))


def test_the_lag_window_reprocessing_keeps_the_coast_bookkeeping(relay_world):
    """A relay epoch arriving late (inside the lag window) after the track was declared lost: the
    steps since are re-run from the snapshot before it (_t_meas, the landing's arrays in
    _SNAP_ARRAYS), the loss is undone (counter too), and the result is the on-time tracker's."""
    _, rt = relay_world
    assert {"_t_meas", "_land_t", "_land_a", "_land_b", "_land_var", "_land_v"} <= set(SondeTracker._SNAP_ARRAYS)
    params = dataclasses.replace(E.tracker_params(E.SondeScenario(), "relay_only"), max_coast_s=20.0, lag_window_s=6.0)
    feed = set(range(10, 61))
    late, _ = _run(rt, params, feed, range(10, 90), late={84: [79]})
    ontime, _ = _run(rt, params, feed | {79}, range(10, 90))
    lost_only, _ = _run(rt, params, feed, range(10, 90))
    assert lost_only.counters.lost == 1 and lost_only.state("s1") is None  # lost at 81 without the epoch at 79
    assert late.counters.late_accepted == 1 and late.counters.reprocess_runs == 1
    assert late.counters.lost == ontime.counters.lost == 0
    s_late, s_on = late.state("s1"), ontime.state("s1")
    assert s_late is not None and s_late[0] == s_on[0]
    np.testing.assert_allclose(s_late[1], s_on[1], rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(s_late[2], s_on[2], rtol=1e-9, atol=1e-12)
    assert late._t_meas[0] == ontime._t_meas[0] == float(rt.t_gps_s[79])
    # and a loss inside the lag window, undone: lost again later at the same time as on time
    late2, o2 = _run(rt, params, feed, range(10, 110), late={84: [79]})
    assert late2.counters.lost == 1 and o2[100] == [] and len(o2[99]) == 1  # 79 + 20 s


@pytest.mark.parametrize("bad", [0.0, -5.0, float("nan"), float("inf"), True, "soon"])
def test_a_bad_max_coast_s_is_refused(bad):
    with pytest.raises(ValueError, match="max_coast_s"):
        SondeTrackerParams(max_coast_s=bad)
