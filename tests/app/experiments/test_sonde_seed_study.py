"""The sonde tracker's motion model (relaxed kinematics) and the seed study of
`skyfuse experiment sonde --seeds N` (issue 19, item 5: the fused track could be worse than
relayed GNSS alone).

The cause of seed 1 (fused 10.1 m against relay-only 4.1 m): the tracker's Singer model
(eq 20 as printed: the velocity a random walk) predicts a coast's position variance growing
as T^3 while the world's sonde velocity relaxes to the wind it meets (vehicles.sonde): over
the 120 s GNSS outage the predicted sigma reached ~470 m against actual coast errors of
~100-250 m, so the fused filter leaned on the radar's angles (280 m per axis at 160 km).
References here are analytic (exact discretisations, integrals, chi-square bands) or the
world's own independent code (vehicles.sonde.axis_discretisation).
"""
from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from scipy import integrate
from scipy.stats import chi2

from filters.metrics import nees
from ground_station.sonde import SondeTracker, SondeTrackerParams, layout_for, relaxed_axis_discretisation
from sitl.bus import SondeRelay
from sitl.app.cli import main
from sitl.app.experiments import sonde as E
from sitl.gnss.orbits import DEFAULT_TOA_GPS_S, default_constellation
from sitl.radio.relay import Relay, RelayParams
from vehicles.sonde import SondeFlight, SondeParams, axis_discretisation, descent_speed_m_s

T0 = DEFAULT_TOA_GPS_S


# ---------------------------------------------------------------- the model


def _relaxed_axis_reference(k, beta, sigma_g, sigma_s, L, w, dt):
    """(F, Q) of the continuous relaxed axis [p, v, g, u, s] over dt by a fine-step numerical
    integration of the moment equations Phi' = A Phi, P' = A P + P A' + Qc (RK, tight tolerances):
    independent of the matrix exponentials (expm, Van Loan) of relaxed_axis_discretisation."""
    lam = abs(w) / L
    A = np.zeros((5, 5))
    A[0, 1] = 1.0  # p' = v
    A[1, 1], A[1, 2], A[1, 3] = -k, 1.0, k  # v' = k (u - v) + g
    A[2, 2] = -beta  # g' = -beta g + noise
    A[3, 4] = w  # u' = (du/dh) (dh/dt) = s w
    A[4, 4] = -lam  # the shear, Gauss-Markov in height: ds/dh = -s / L + noise
    Qc = np.diag([0.0, 0.0, 2.0 * beta * sigma_g**2, 0.0, 2.0 * lam * sigma_s**2])

    def rhs(_, y):
        Phi, P = y[:25].reshape(5, 5), y[25:].reshape(5, 5)
        return np.concatenate([(A @ Phi).ravel(), (A @ P + P @ A.T + Qc).ravel()])

    sol = integrate.solve_ivp(rhs, (0.0, dt), np.concatenate([np.eye(5).ravel(), np.zeros(25)]), method="DOP853",
                              rtol=1e-12, atol=1e-16, max_step=dt / 50.0)
    y = sol.y[:, -1]
    return y[:25].reshape(5, 5), y[25:].reshape(5, 5)


@pytest.mark.parametrize("k, sigma_g, sigma_s, L, w, dt", [(0.1, 0.15, 2.9e-3, 4430.0, 5.0, 1.0),
                                                           (0.1, 0.15, 2.9e-3, 4430.0, -40.0, 1.0),
                                                           (0.2, 0.1, 0.0, 900.0, -15.0, 2.5),
                                                           (0.2, 0.1, 1e-3, 900.0, 0.0, 2.5)])
def test_relaxed_axis_is_the_sonde_models_axis_with_a_gauss_markov_shear_in_height(k, sigma_g, sigma_s, L, w, dt):
    beta = 0.12
    F, Q = relaxed_axis_discretisation(k, beta, sigma_g, sigma_s, L, w, dt)
    # an independent reference: the continuous system integrated numerically
    F_ref, Q_ref = _relaxed_axis_reference(k, beta, sigma_g, sigma_s, L, w, dt)
    np.testing.assert_allclose(F, F_ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(Q, Q_ref, rtol=1e-7, atol=1e-12 * max(np.max(np.abs(Q_ref)), 1e-12))
    # [p, v, g] with the wind u held over the step: the world's own discretisation (its input column is u)
    phi, gam, q, _ = axis_discretisation(k, beta, sigma_g, dt)
    np.testing.assert_allclose(F[:3, :3], phi, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(F[:3, 3], gam, rtol=1e-12, atol=1e-15)
    # the shear is Gauss-Markov in height: u' = w s, s' = -(|w| / L) s + noise (closed forms)
    e = math.exp(-abs(w) * dt / L)
    assert F[4, 4] == pytest.approx(e, rel=1e-12)
    assert F[3, 4] == pytest.approx(math.copysign(L, w) * (1.0 - e) if w else 0.0, rel=1e-9, abs=1e-15)
    assert Q[4, 4] == pytest.approx(sigma_s**2 * (1.0 - e * e), rel=1e-9, abs=1e-30)
    if sigma_s == 0.0 or w == 0.0:
        np.testing.assert_allclose(Q[:3, :3], q, rtol=1e-10, atol=1e-18)  # no shear noise: the world's Q
        # and none on the wind and shear (exactly at w = 0; rounding of the expm otherwise)
        assert np.all(Q[3:, :] == 0.0) if w == 0.0 else np.max(np.abs(Q[3:, :])) <= 1e-14 * np.max(np.abs(q))
    else:
        assert np.all(np.linalg.eigvalsh(Q) > -1e-15)
    if w == 0.0:  # at rest vertically the wind does not change: u and s are held exactly
        np.testing.assert_array_equal(F[3:, :], np.eye(5)[3:])
    else:  # what the wind does depends on the height crossed, w dt, not on w and dt apart
        F2, Q2 = relaxed_axis_discretisation(k, beta, sigma_g, sigma_s, L, 2.0 * w, 0.5 * dt)
        np.testing.assert_allclose(F2[3:, 3:], F[3:, 3:], rtol=1e-10, atol=1e-15)
        np.testing.assert_allclose(Q2[3:, 3:], Q[3:, 3:], rtol=1e-8, atol=1e-30)
        # and not on the direction: the sign of the wind's change flips with w, its spread does not
        F3, Q3 = relaxed_axis_discretisation(k, beta, sigma_g, sigma_s, L, -w, dt)
        assert F3[3, 4] == pytest.approx(-F[3, 4], rel=1e-12)
        np.testing.assert_allclose(np.diag(Q3), np.diag(Q), rtol=1e-9, atol=1e-30)
    L_ = layout_for("fused")
    assert (L_.n_kin, L_.wind, L_.dd, L_.osc, L_.err) == (15, 9, 15, 16, 17)
    assert layout_for("fused", kinematics="singer")[:4] == (9 + 2 + 3, 9, 10, 11)  # the model before the fix


def test_relaxed_axis_moments_match_an_euler_maruyama_simulation():
    """A seeded Euler-Maruyama simulation of the continuous axis (0.01 s steps) from a known start:
    its sample mean and covariance after dt agree with (F x0, Q) inside their sampling error."""
    k, beta, sigma_g, sigma_s, L, w, dt = 0.1, 0.12, 0.15, 3e-3, 4430.0, -40.0, 2.0
    F, Q = relaxed_axis_discretisation(k, beta, sigma_g, sigma_s, L, w, dt)
    rng = np.random.default_rng(20260)
    n, h = 20_000, 0.01
    x0 = np.array([0.0, 10.0, 0.05, 12.0, 2e-3])
    X = np.tile(x0, (n, 1))
    lam = abs(w) / L
    for _ in range(round(dt / h)):
        dW = rng.standard_normal((n, 2)) * math.sqrt(h)
        p, v, g, u, s = X.T
        X = np.column_stack([p + v * h, v + (k * (u - v) + g) * h, g - beta * g * h + math.sqrt(2 * beta) * sigma_g * dW[:, 0],
                             u + w * s * h, s - lam * s * h + math.sqrt(2 * lam) * sigma_s * dW[:, 1]])
    m, C = X.mean(axis=0), np.cov(X.T)
    sd = np.sqrt(np.diag(Q))
    np.testing.assert_allclose(m, F @ x0, atol=5.0 * float(np.max(sd)) / math.sqrt(n) + 1e-9)
    for i in range(5):  # each variance within 5 of its standard errors (sqrt(2 / n) relative)
        if Q[i, i] > 0.0:
            assert C[i, i] == pytest.approx(Q[i, i], rel=5.0 * math.sqrt(2.0 / n) + 2e-3), (i, C[i, i], Q[i, i])


def test_wind_shear_statistics_of_profiles_match_the_integrals():
    a = 2e-3  # wind speed grows 2 m/s per km, from the west, at every height
    alt = (0.0, 50_000.0)
    sp = SondeParams(wind_alt_m=alt, wind_speed_m_s=(0.0, a * alt[1]), wind_from_rad=math.radians(270.0))
    h_rms, corr_h, v_rms = E.wind_shear_statistics(sp)
    # a constant shear a on the east axis, 0 on the north: the rms over both axes is a / sqrt(2)
    assert h_rms == pytest.approx(a / math.sqrt(2.0), rel=1e-6)
    top = 0.5 * sum(sp.burst_alt_range_m)
    assert 1.0 <= corr_h <= top
    # the target vertical speed has no residual shear: the descent law is the tracker's input, the
    # world's own (vehicles.sonde.descent_speed_m_s; ground_station has its own copy of it)
    assert v_rms == 0.0
    from ground_station.sonde import descent_speed as tracker_descent_speed
    hh = np.linspace(0.0, top, 2001)
    np.testing.assert_allclose(tracker_descent_speed(hh, sp.descent_rate_sl_m_s), descent_speed_m_s(hh, sp.descent_rate_sl_m_s),
                               rtol=1e-6)
    const = SondeParams(wind_alt_m=alt, wind_speed_m_s=(10.0, 10.0), wind_from_rad=math.radians(270.0))
    assert E.wind_shear_statistics(const)[0] == 0.0
    # the default jet profile (x 1.15, the experiment's): piecewise linear, so its shear is constant
    # between knots; the rms from the knots, weighted by each layer's depth between the launch height
    # and the middle of the burst range
    jet = E._sonde_params(E.SondeScenario())
    knots = np.asarray(jet.wind_alt_m, float)
    uv = jet.wind_enu_m_s(knots)
    lo, hi = 190.0, 0.5 * sum(jet.burst_alt_range_m)
    acc = 0.0
    for i in range(knots.size - 1):
        depth = max(0.0, min(hi, knots[i + 1]) - max(lo, knots[i]))
        acc += depth * float(np.sum(((uv[i + 1] - uv[i]) / (knots[i + 1] - knots[i])) ** 2))
    assert E.wind_shear_statistics(jet)[0] == pytest.approx(math.sqrt(acc / (2.0 * (hi - lo))), rel=2e-3)
    assert E.wind_shear_statistics(jet)[0] == pytest.approx(SondeTrackerParams().wind_shear_sigma_horizontal_1_s, rel=2e-3)
    assert E.wind_shear_statistics(jet)[1] == pytest.approx(SondeTrackerParams().wind_shear_corr_height_m, rel=2e-3)


# ---------------------------------------------------------------- the cause: a coast's covariance


def _coast_nees(kinematics: str, n: int = 20, outage=(150.0, 270.0)):
    """Relay-only tracker on n sondes in a constant wind (the sonde model's case without shear:
    the relaxed model is then the world's model exactly), relay lost over ``outage`` (s since
    launch); the 3-dof position NEES of every sonde at each outage epoch, (n, epochs)."""
    sp = SondeParams(wind_alt_m=(0.0, 50_000.0), wind_speed_m_s=(15.0, 15.0), wind_from_rad=math.radians(250.0))
    streams = E._streams(0, [0] * n, range(100, 100 + n))
    lat, lon, h = E.gcpp_site(E.SondeScenario())
    T = int(outage[1]) + 1
    tr = SondeFlight([s[0] for s in streams], params=sp, t0_gps_s=T0).simulate(T)
    rt = Relay([s[2] for s in streams], default_constellation("GR"), ground_lat_rad=lat, ground_lon_rad=lon,
               ground_h_m=h, params=RelayParams(outage_schedule=((T0 + outage[0], T0 + outage[1]),)),
               batch_shape=(n,)).track(tr.t_gps_s, tr.pos_ecef_m, tr.vel_ecef_m_s)
    beta = sp.p1_1_s + sp.p2_1_s
    if kinematics == "relaxed":  # the world's parameters; in the ascent of a constant wind nothing changes the wind
        params = SondeTrackerParams(mode="relay_only", kinematics="relaxed", velocity_relax_rate_horizontal_1_s=sp.p1_1_s,
                                    velocity_relax_rate_vertical_1_s=sp.vertical_relax_rate_1_s, accel_rate_1_s=beta,
                                    sigma_acc_horizontal_m_s2=sp.sigma_a_m_s2,
                                    sigma_acc_vertical_m_s2=sp.sigma_a_vertical_m_s2,
                                    wind_shear_sigma_horizontal_1_s=0.0, wind_shear_sigma_vertical_1_s=0.0)
    else:  # the tracker before the fix: Singer with the stationary acceleration variance of the sonde model
        params = SondeTrackerParams(mode="relay_only", kinematics="singer", accel_rate_1_s=beta,
                                    sigma_acc_horizontal_m_s2=sp.sigma_a_m_s2 * math.sqrt(beta / (beta + sp.p1_1_s)),
                                    sigma_acc_vertical_m_s2=sp.sigma_a_vertical_m_s2
                                    * math.sqrt(beta / (beta + sp.vertical_relax_rate_1_s)))
    trk = SondeTracker("t19", params)
    out = np.full((n, int(outage[1] - outage[0])), np.nan)
    for k in range(T):
        t = float(rt.t_gps_s[k])
        for b in range(n):
            d = rt.delivered[k, b]
            trk.on_message(f"t19/sonde/s{b}/relay", SondeRelay(
                t_gps_s=t, source_id="g", seq=k, sat_ids=rt.sat_id[d], pseudorange_m=rt.pseudorange_m[k, b][d],
                pseudo_doppler_m_s=rt.pseudo_doppler_m_s[k, b][d], var_pseudorange_m2=rt.var_pr_m2[k, b][d],
                var_pseudo_doppler_m2_s2=rt.var_prr_m2_s2[k, b][d], sat_pos_ecef_m=rt.sat_pos_ecef_m[k, b][d],
                sat_vel_ecef_m_s=rt.sat_vel_ecef_m_s[k, b][d], ground_pos_ecef_m=rt.ground_pos_ecef_m))
        trk.step(t)
        j = int(round(t - T0 - outage[0]))
        if 0 <= j < out.shape[1]:
            for b in range(n):
                _, x, P = trk.state(f"s{b}")
                out[b, j] = nees(x[:3] - tr.pos_ecef_m[k, b], P[:3, :3])
    return out


@pytest.mark.slow
def test_a_relay_only_coast_through_an_outage_is_consistent_with_the_relaxed_model_and_not_with_singer():
    n = 20
    lo, hi = chi2.ppf([0.005, 0.995], 3 * n) / n  # the mean NEES of n independent sondes at one epoch
    relaxed, singer = _coast_nees("relaxed", n), _coast_nees("singer", n)
    for j in (29, 59, 119):  # 30, 60 and 120 s into the outage
        assert lo <= relaxed[:, j].mean() <= hi, (j, relaxed[:, j].mean(), (lo, hi))
    # the model before the fix: its coast covariance is far too large (the position variance grows
    # as T^3 with a random-walk velocity), so the NEES falls out of the band below
    assert singer[:, 119].mean() < lo, singer[:, 119].mean()
    assert singer[:, 119].mean() < 0.5 * relaxed[:, 119].mean()


# ---------------------------------------------------------------- the seed study, short variant

#: the trackers pick the sonde up 300 s before the default GNSS outage (3600-3720 s, at ~160 km, where
#: the radar's angles are worth ~280 m a axis), the radar angles are lost 3400-3500 s
SHORT_STUDY = E.SondeScenario(duration_s=3800.0, acquire_s=3300.0, radar_loss_s=(3400.0, 3500.0))


@pytest.fixture(scope="module")
def short_study():
    return E.seed_study(SHORT_STUDY, range(1, 13), batch=12)


@pytest.mark.slow
@pytest.mark.slow
def test_seed_study_short_variant_fused_is_no_worse_than_the_source_left_in_each_outage(short_study):
    d = short_study
    assert d["seeds"] == list(range(1, 13)) and len(d["per_seed"]) == 12
    g, loss = d["during_gnss_outage"], d["during_radar_loss"]
    # the issue's outage targets: no worse on average than the source still available
    assert g["source_left"] == "radar_only" and g["fused_no_worse_on_average"]
    assert g["mean_rmse_m"]["fused"] < g["mean_rmse_m"]["radar_only"]
    assert loss["source_left"] == "relay_only" and loss["fused_no_worse_on_average"]
    # and not worse than the relay's coast on average (the radar's range fixes the radial error)
    assert g["pooled_rmse_m"]["fused"] < g["pooled_rmse_m"]["relay_only"]
    assert d["checks"]["gnss_outage_no_worse_than_radar_only"] and d["checks"]["radar_loss_no_worse_than_relay_only"]


@pytest.mark.slow
@pytest.mark.slow
def test_seed_study_short_variant_the_issue_seed_is_fixed(short_study):
    """Seed 1, the issue's reproduction: fused below relay-only now; with the tracker's model before
    the fix (kinematics "singer") the fused track is well above it, as reported."""
    s1 = short_study["per_seed"][0]
    assert s1["seed"] == 1 and s1["fused_below_relay_only"], s1
    old = E.seed_study(dataclasses.replace(SHORT_STUDY, kinematics="singer"), [1])
    assert old["per_seed"][0]["fused_to_relay_only"] > 1.5, old["per_seed"][0]


def test_cli_seed_study_writes_result_json_and_png(tmp_path, capsys):
    out = tmp_path / "study"
    rc = main(["experiment", "sonde", "--seeds", "2", "--seed", "5", "--duration", "60", "--out", str(out), "--quiet"])
    assert rc == 0
    doc = json.loads((out / "result.json").read_text(), parse_constant=lambda c: pytest.fail(f"non-strict JSON {c}"))
    assert doc["study"] == "seeds" and doc["seeds"] == [5, 6] and doc["scenario"]["kinematics"] == "relaxed"
    for r in doc["per_seed"]:
        assert set(r["overall_rmse_m"]) == {"fused", "relay_only", "radar_only"}
        assert r["fused_to_relay_only"] == pytest.approx(r["overall_rmse_m"]["fused"] / r["overall_rmse_m"]["relay_only"])
        assert r["gnss_outage_rmse_m"]["fused"] is None  # the outage is after this 60 s flight
    assert doc["during_gnss_outage"]["mean_rmse_m"] is None and "gnss_outage_no_worse_than_radar_only" not in doc["checks"]
    assert doc["pass"] == all(doc["checks"].values())
    assert (out / E.STUDY_FIGURE).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "study" in capsys.readouterr().out
    # the batched seeds are each seed's own trial 0: seed 6 alone gives the same flight
    one = E.run_trials(E.SondeScenario(duration_s=20.0, white_baseline=False), 6, [0], modes=("relay_only",))
    two = E.run_trials(E.SondeScenario(duration_s=20.0, white_baseline=False), 5, [0, 0], modes=("relay_only",),
                       seeds=[5, 6])
    np.testing.assert_array_equal(one["truth_pos"][0], two["truth_pos"][1])


# ---------------------------------------------------------------- the 6 h demo: landing


def _landing_run(landing: bool):
    """One sonde bursting at 2 km (lands ~800 s after launch), relayed GNSS until 600 s (descending),
    nothing after: relay-only tracker to 1500 s. (truth track, tracker, position errors (T,))."""
    sp = SondeParams(burst_alt_range_m=(2000.0, 2000.0))
    streams = E._streams(0, [0], [7])
    lat, lon, h = E.gcpp_site(E.SondeScenario())
    tr = SondeFlight([streams[0][0]], params=sp, t0_gps_s=T0).simulate(1500)
    rt = Relay([streams[0][2]], default_constellation("GR"), ground_lat_rad=lat, ground_lon_rad=lon, ground_h_m=h,
               batch_shape=(1,)).track(tr.t_gps_s[:601], tr.pos_ecef_m[:601], tr.vel_ecef_m_s[:601])
    trk = SondeTracker("t19", dataclasses.replace(E.tracker_params(E.SondeScenario(), "relay_only"), landing=landing,
                                                  max_coast_s=None))  # (the landing itself: never lost here)
    err = np.full(tr.t_gps_s.size, np.nan)
    for k in range(tr.t_gps_s.size):
        t = float(tr.t_gps_s[k])
        if k <= 600:
            d = rt.delivered[k, 0]
            trk.on_message("t19/sonde/s1/relay", SondeRelay(
                t_gps_s=t, source_id="g", seq=k, sat_ids=rt.sat_id[d], pseudorange_m=rt.pseudorange_m[k, 0][d],
                pseudo_doppler_m_s=rt.pseudo_doppler_m_s[k, 0][d], var_pseudorange_m2=rt.var_pr_m2[k, 0][d],
                var_pseudo_doppler_m2_s2=rt.var_prr_m2_s2[k, 0][d], sat_pos_ecef_m=rt.sat_pos_ecef_m[k, 0][d],
                sat_vel_ecef_m_s=rt.sat_vel_ecef_m_s[k, 0][d], ground_pos_ecef_m=rt.ground_pos_ecef_m))
        est = trk.step(t)
        if est:
            err[k] = np.linalg.norm(est[0].pos_ecef_m - tr.pos_ecef_m[k, 0])
    return tr, trk, err


@pytest.mark.slow
def test_a_coasting_descending_sonde_lands_and_its_error_stays_bounded():
    from sitl.geodesy import ecef_to_geodetic

    tr, trk, err = _landing_run(True)
    land_k = int(np.argmax(tr.phase[:, 0] == 2))
    assert 700 < land_k < 1000  # the world's sonde lands (and stays) ~800 s after launch
    assert trk.counters.landings == 1
    _, x, P = trk.state("s1")
    lat, lon, h_est = ecef_to_geodetic(x[:3])
    assert h_est == pytest.approx(E.gcpp_site(E.SondeScenario())[2], abs=1e-3)  # on the ground (flat, the site's height)
    np.testing.assert_array_equal(x[3:15], 0.0)  # at rest
    # landed, the error stops growing: the same 200 s after the later landing and at the end, and
    # inside the filter's own 3-sigma
    assert err[-1] == pytest.approx(err[land_k + 200], rel=1e-6)
    assert err[-1] < 3.0 * math.sqrt(np.trace(P[:3, :3]))
    # the tracker without the landing (its behaviour before) coasts on through the ground, at the wind
    tr2, trk2, err2 = _landing_run(False)
    assert trk2.counters.landings == 0
    assert err2[-1] > 3.0 * err[-1] and err2[-1] > err2[land_k + 200] + 1000.0
