"""Seed 004 sonde tracker (ground_station.sonde) and `skyfuse experiment sonde`.

Consistency (NEES in chi-square bounds, and the naive white radar noise failing them),
fused against each single source, rejection of bad bus payloads, range-only updates,
azimuth wrap, relay-only initialisation, batch against loop, the measurement model
against the world's truth, and the command line.
"""
from __future__ import annotations

import dataclasses
import json
import math

import msgpack
import numpy as np
import pytest

from filters.metrics import chi2_bounds, nees
from ground_station.sonde import (
    SondeMeasurement,
    SondeTracker,
    SondeTrackerParams,
    layout_for,
    relay_fix,
    relay_frame_point,
    wrap_pi,
)
from sitl.bus import (
    InMemoryTransport,
    RadarMeasurement,
    SondeRelay,
    encode,
    pack_sealed,
)
from sitl.app.cli import main
from sitl.app.experiments import sonde as E
from sitl.geodesy import enu_rotation, geodetic_to_ecef
from sitl.gnss.orbits import DEFAULT_TOA_GPS_S, default_constellation
from sitl.radio.radar import Radar
from sitl.radio.relay import Relay
from vehicles.sonde import (
    SondeFlight,
)

RUN = "t004"
T0 = DEFAULT_TOA_GPS_S
SHORT = E.SondeScenario(duration_s=700.0, radar_loss_s=(30.0, 130.0), gnss_outage_s=(450.0, 570.0))


@pytest.fixture(scope="module")
def short_run():
    """6 trials of a 700 s flight: angle tracking lost 30-130 s, GNSS outage 450-570 s."""
    raw = E.run_trials(SHORT, 11, range(6))
    return raw, E.score(raw, SHORT)


def _site():
    lat, lon, h = E.gcpp_site(SHORT)
    return lat, lon, h, geodetic_to_ecef(lat, lon, h)


# ---------------------------------------------------------------- consistency and accuracy


@pytest.mark.slow
def test_each_mode_is_consistent_and_the_naive_radar_noise_is_not(short_run):
    raw, sc = short_run
    B = len(raw["trials"])
    lo, hi = chi2_bounds(6, B, 0.99)
    for mode in ("fused", "radar_only", "relay_only"):
        a = sc["anees"][mode]
        assert a["bounds_99_one_epoch"] == [lo, hi]
        assert lo <= a["mean"] <= hi, (mode, a["mean"])
        assert a["fraction_of_epochs_inside"] > 0.85, (mode, a["fraction_of_epochs_inside"])
    # the test can fail: radar errors taken as white (10 s correlation ignored) -> over-confident
    assert sc["anees"]["radar_only_white"]["mean"] > hi
    assert sc["anees"]["radar_only_white"]["mean"] > 3 * sc["anees"]["radar_only"]["mean"]


@pytest.mark.slow
def test_fused_beats_each_single_source_and_stays_continuous(short_run):
    raw, sc = short_run
    r = sc["overall_rmse_m"]
    assert r["fused"] < r["relay_only"] and r["fused"] < r["radar_only"]
    loss, out = sc["during_radar_loss"]["rmse_m"], sc["during_gnss_outage"]["rmse_m"]
    assert loss["fused"] < 0.1 * loss["radar_only"]  # the relay carries it through the angle loss
    assert out["fused"] < out["relay_only"]  # the radar carries it through the GNSS outage
    assert sc["continuity"]["fused_estimate_every_epoch"] and sc["continuity"]["max_gap_s"] == 1.0
    c = raw["counters"]["fused"]
    assert c["range_only_updates"] == 6 * 100 and c["relay_empty"] >= 6 * 120
    assert raw["bus"]["rejected"] == {} and raw["bus"]["callback_errors"] == 0 and raw["scorer_unexpected"] == 0


# ---------------------------------------------------------------- a small hand-driven world


def _world(duration_s: int):
    """One sonde, duration_s seconds: truth, radar and relay epochs (no loss, no outage)."""
    streams = E._trial_streams(21, [0])[0]
    lat, lon, h, _ = _site()
    tr = SondeFlight([streams[0]], params=E._sonde_params(SHORT), t0_gps_s=T0).simulate(duration_s)
    radar = Radar([streams[1]], site_lat_rad=lat, site_lon_rad=lon, site_h_m=h, batch_shape=(1,))
    rad = [radar.step(tr.t_gps_s[k], tr.pos_ecef_m[k], tr.vel_ecef_m_s[k]) for k in range(len(tr))]
    relay = Relay([streams[2]], default_constellation("GR"), ground_lat_rad=lat, ground_lon_rad=lon, ground_h_m=h,
                  batch_shape=(1,))
    rt = relay.track(tr.t_gps_s, tr.pos_ecef_m, tr.vel_ecef_m_s)
    return tr, rad, rt


@pytest.fixture(scope="module")
def world():
    """One sonde, 200 s: truth, radar and relay epochs (no loss, no outage)."""
    return _world(200)


def radar_msg(m, k, seq, **over) -> RadarMeasurement:
    kw = {"t_gps_s": float(m.t_gps_s), "source_id": "radar", "seq": seq, "slant_range_m": float(m.slant_range_m[0]),
          "az_rad": float(m.az_rad[0]), "el_rad": float(m.el_rad[0]), "var_range_m2": float(m.var_range_m2[0]),
          "var_az_rad2": float(m.var_az_rad2[0]), "var_el_rad2": float(m.var_el_rad2[0]),
          "angles_valid": bool(m.angles_valid[0]), "radar_pos_ecef_m": m.site_pos_ecef_m}
    kw.update(over)
    return RadarMeasurement(**kw)


def relay_msg(rt, k, seq) -> SondeRelay:
    d = rt.delivered[k, 0]
    return SondeRelay(t_gps_s=float(rt.t_gps_s[k]), source_id="gcpp", seq=seq, sat_ids=rt.sat_id[d],
                      pseudorange_m=rt.pseudorange_m[k, 0][d], pseudo_doppler_m_s=rt.pseudo_doppler_m_s[k, 0][d],
                      var_pseudorange_m2=rt.var_pr_m2[k, 0][d], var_pseudo_doppler_m2_s2=rt.var_prr_m2_s2[k, 0][d],
                      sat_pos_ecef_m=rt.sat_pos_ecef_m[k, 0][d], sat_vel_ecef_m_s=rt.sat_vel_ecef_m_s[k, 0][d],
                      ground_pos_ecef_m=rt.ground_pos_ecef_m)


RADAR_KEY = f"{RUN}/radar/r1/sonde/s1"
RELAY_KEY = f"{RUN}/sonde/s1/relay"


def test_bad_radar_payloads_are_rejected_by_the_bus_and_leave_the_estimate_alone(world):
    _, rad, rt = world
    buses, trackers = [], []
    for _ in range(2):
        bus = InMemoryTransport()
        t = SondeTracker(RUN, SondeTrackerParams(mode="fused"))
        t.attach(bus)
        buses.append(bus)
        trackers.append(t)
    bad_at = (60, 61, 62)
    for k in range(1, 80):
        for bus in buses:
            bus.publish(RELAY_KEY, relay_msg(rt, k, k))
        good = radar_msg(rad[k], k, k)
        if k in bad_at:  # only on bus 0: a NaN range, an azimuth of 7 rad, truncated bytes
            obj = msgpack.unpackb(encode(good), raw=False)
            obj.update({60: {"slant_range_m": float("nan")}, 61: {"az_rad": 7.0}, 62: {}}[k])
            payload = pack_sealed(obj)  # a valid checksum: the field checks reject it
            buses[0].publish_raw(RADAR_KEY, payload[:-3] if k == 62 else payload, good.t_gps_s)
        else:
            for bus in buses:
                bus.publish(RADAR_KEY, good)
        for bus, t in zip(buses, trackers):
            bus.drain(good.t_gps_s)
            t.step(good.t_gps_s)
    rej = buses[0].stats.total.rejected
    assert sum(rej.values()) == 3 and buses[1].stats.total.rejected == {}
    assert any("slant_range_m" in r for r in rej) and any("az_rad" in r for r in rej)
    # the tracker never saw them: its estimate equals the one fed nothing at those epochs
    s0, s1 = trackers[0].state("s1"), trackers[1].state("s1")
    np.testing.assert_array_equal(s0[1], s1[1])
    np.testing.assert_array_equal(s0[2], s1[2])
    assert trackers[0].counters.radar_updates == trackers[1].counters.radar_updates


def test_lost_angles_give_a_range_only_update(world):
    tr, rad, _ = world
    k0, k1 = 10, 11
    out = {}
    for name, over in (("nan", {"az_rad": float("nan"), "el_rad": float("nan"), "angles_valid": False}),
                       ("junk", {"az_rad": 1.0, "el_rad": 0.5, "angles_valid": False}),
                       ("valid", {})):
        t = SondeTracker(RUN, SondeTrackerParams(mode="radar_only"))
        t.on_message(RADAR_KEY, radar_msg(rad[k0], k0, 0))
        t.step(float(tr.t_gps_s[k0]))
        t.on_message(RADAR_KEY, radar_msg(rad[k1], k1, 1, **over))
        est = t.step(float(tr.t_gps_s[k1]))
        out[name] = (t.state("s1"), t.counters, est[0])
    (_, x_nan, P_nan), c_nan, e_nan = out["nan"]
    (_, x_junk, P_junk), _, _ = out["junk"]
    np.testing.assert_array_equal(x_nan, x_junk)  # the angles are not looked at
    np.testing.assert_array_equal(P_nan, P_junk)
    assert c_nan.range_only_updates == 1 and c_nan.radar_updates == 1
    assert out["valid"][1].range_only_updates == 0
    assert not np.allclose(out["valid"][0][1], x_nan)
    assert math.isfinite(e_nan.nis) and e_nan.mode == "radar_only"


def test_a_sonde_crossing_north_of_the_radar_gives_no_azimuth_jump():
    lat, lon, h, site = _site()
    R = enu_rotation(lat, lon)
    t = T0 + np.arange(0.0, 301.0)
    enu = np.stack([-3000.0 + 20.0 * (t - T0), np.full(t.size, 1500.0), 800.0 + 2.0 * (t - T0)], -1)
    pos = site + enu @ R
    vel = np.broadcast_to(np.array([20.0, 0.0, 2.0]) @ R, pos.shape)
    radar = Radar(np.random.default_rng(3), site_lat_rad=lat, site_lon_rad=lon, site_h_m=h)
    trk = SondeTracker(RUN, SondeTrackerParams(mode="radar_only", accel_rate_1_s=0.12))
    az, err = [], []
    for k in range(t.size):
        m = radar.step(t[k], pos[k], vel[k])
        msg = RadarMeasurement(t_gps_s=float(t[k]), source_id="radar", seq=k, slant_range_m=float(m.slant_range_m),
                               az_rad=float(m.az_rad), el_rad=float(m.el_rad), var_range_m2=float(m.var_range_m2),
                               var_az_rad2=float(m.var_az_rad2), var_el_rad2=float(m.var_el_rad2),
                               angles_valid=bool(m.angles_valid), radar_pos_ecef_m=m.site_pos_ecef_m)
        trk.on_message(RADAR_KEY, msg)
        est = trk.step(float(t[k]))[0]
        az.append(float(m.az_rad))
        err.append(np.linalg.norm(est.pos_ecef_m - pos[k]))
        if k > 5:
            assert est.nis < 30.0, (k, est.nis)
    az, err = np.array(az), np.array(err)
    cross = int(np.flatnonzero(np.diff(az) < -np.pi)[0])  # 2 pi -> 0 between cross and cross + 1
    assert az[cross] > 6.2 and az[cross + 1] < 0.1
    # errors are the radar's (15 m range errors correlated over 10 s), with no jump at the crossing
    assert err[20:].max() < 60.0
    assert np.abs(np.diff(err[cross - 10:cross + 10])).max() < 20.0  # a 2 pi slip would throw it km away
    c = trk.counters
    assert c.radar_gated == 0 and c.radar_manoeuvre == 0 and c.reacquired == 0


def test_relay_only_initialises_from_a_least_squares_fix(world):
    tr, _, rt = world
    k = 50
    m = relay_msg(rt, k, 0)
    assert m.n >= 4
    fix = relay_fix(m.sat_pos_ecef_m, m.sat_vel_ecef_m_s, m.pseudorange_m, m.pseudo_doppler_m_s,
                    m.var_pseudorange_m2, m.var_pseudo_doppler_m2_s2, m.ground_pos_ecef_m)
    p_err = fix.pos_ecef_m - tr.pos_ecef_m[k, 0]
    assert nees(p_err, fix.cov_pos_dd[:3, :3]) < 20.0 and np.linalg.norm(p_err) < 40.0
    assert abs(fix.delta_d_m - rt.delta_d_m[k, 0]) < 40.0
    assert np.linalg.norm(fix.vel_ecef_m_s - tr.vel_ecef_m_s[k, 0]) < 1.0
    assert abs(fix.osc_m_s - rt.osc_doppler_m_s[k, 0]) < 1.0
    # fewer than four satellites: no fix (4 unknowns: P and dd)
    few = slice(0, 3)
    assert relay_fix(m.sat_pos_ecef_m[few], m.sat_vel_ecef_m_s[few], m.pseudorange_m[few], m.pseudo_doppler_m_s[few],
                     m.var_pseudorange_m2[few], m.var_pseudo_doppler_m2_s2[few], m.ground_pos_ecef_m) is None
    # the tracker: the first usable relay epoch initialises it, later ones update it
    trk = SondeTracker(RUN, SondeTrackerParams(mode="relay_only"))
    for j in range(k, k + 30):
        trk.on_message(RELAY_KEY, relay_msg(rt, j, j))
        est = trk.step(float(rt.t_gps_s[j]))
    assert trk.counters.init_relay == 1 and trk.counters.relay_updates == 29
    assert np.linalg.norm(est[0].pos_ecef_m - tr.pos_ecef_m[k + 29, 0]) < 5.0
    # 15 kinematic states (position, velocity, gust acceleration, wind, wind shear), dd, osc, one error state per satellite slot
    assert trk.layout.n == 17 + 24 and trk.state("s1")[1].size == 41


def test_measurement_model_matches_the_world_and_the_compiled_rows_match_numpy(world):
    tr, rad, rt = world
    k = 150
    d = rt.delivered[k, 0]
    U = int(d.sum())
    L = layout_for("fused")
    x = np.zeros((1, L.n))
    x[0, :3], x[0, 3:6] = tr.pos_ecef_m[k, 0], tr.vel_ecef_m_s[k, 0]
    x[0, L.dd], x[0, L.osc] = rt.delta_d_m[k, 0], rt.osc_doppler_m_s[k, 0]
    x[0, L.err:L.err + 3] = rad[k].error[0]
    z = np.concatenate([np.zeros(2 * U), [rad[k].slant_range_m[0], rad[k].az_rad[0], rad[k].el_rad[0]]])[None]
    site = rad[k].site_pos_ecef_m
    lat, lon, _ = _site()[:3]
    model = SondeMeasurement(L, z, np.ones_like(z), sat_pos=rt.sat_pos_ecef_m[k, 0][d][None],
                             sat_vel=rt.sat_vel_ecef_m_s[k, 0][d][None], relay_mask=np.ones((1, U), bool),
                             ground=rt.ground_pos_ecef_m, site=site, rot=enu_rotation(lat, lon),
                             radar_mask=np.ones((1, 3), bool))
    h, H = model.h_and_H(x)
    h2, H2 = model.h_and_H_numpy(x)
    np.testing.assert_allclose(h, h2, rtol=0, atol=1e-6)
    np.testing.assert_allclose(H, H2, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(model.h(x[None])[0], h2, rtol=0, atol=1e-6)  # sigma-point broadcasting
    # noise-free world: the model reproduces the relayed path and its rate, and the radar
    np.testing.assert_allclose(h[0, :U], rt.true_path_m[k, 0][d] + rt.delta_d_m[k, 0], atol=0.01)
    np.testing.assert_allclose(h[0, U:2 * U], rt.true_path_rate_m_s[k, 0][d] + rt.osc_doppler_m_s[k, 0], atol=1e-3)
    np.testing.assert_allclose(h[0, 2 * U:], z[0, 2 * U:], atol=1e-9)
    # the frame point is the relay's P: 0.1 - 0.4 m from the sonde at these ranges
    assert 0.0 < np.linalg.norm(relay_frame_point(x[0, :3], x[0, 3:6], rt.ground_pos_ecef_m) - x[0, :3]) < 0.5
    # the Jacobian against central differences
    eps = np.array([1.0, 1.0, 1.0, 0.01, 0.01, 0.01])
    for i in range(6):
        xp, xm = x.copy(), x.copy()
        xp[0, i] += eps[i]
        xm[0, i] -= eps[i]
        num = (model.h_and_H_numpy(xp)[0] - model.h_and_H_numpy(xm)[0]) / (2 * eps[i])
        num[0, 2 * U + 1] = wrap_pi(num[0, 2 * U + 1] * 2 * eps[i]) / (2 * eps[i])
        # (h also moves with V through the relay's light time, ~|P - G|/c: not in H)
        np.testing.assert_allclose(H[0, :, i], num[0], rtol=1e-4, atol=1e-7 if i < 3 else 5e-5)


@pytest.mark.slow
def test_trials_batched_equal_trials_one_by_one():
    scn = dataclasses.replace(SHORT, duration_s=120.0, radar_loss_s=(20.0, 60.0), gnss_outage_s=(80.0, 100.0),
                              white_baseline=False)
    batch = E.run_trials(scn, 5, [0, 1, 2])
    for j in range(3):
        one = E.run_trials(scn, 5, [j])
        # the world is bitwise the same; the trackers agree to rounding (the satellite rows of a
        # batch are ordered over all its sondes, and the compiled kernels run lanes of trials)
        np.testing.assert_array_equal(one["truth_pos"][0], batch["truth_pos"][j])
        np.testing.assert_array_equal(np.isnan(one["pos"][:, 0]), np.isnan(batch["pos"][:, j]))
        np.testing.assert_allclose(one["pos"][:, 0], batch["pos"][:, j], rtol=0, atol=1e-4)
        np.testing.assert_allclose(one["vel"][:, 0], batch["vel"][:, j], rtol=0, atol=1e-5)
        np.testing.assert_allclose(one["cov"][:, 0], batch["cov"][:, j], rtol=1e-5, atol=1e-8)


# ---------------------------------------------------------------- command line


@pytest.mark.slow
def test_cli_tiny_run_writes_result_json(tmp_path, capsys):
    out = tmp_path / "sonde"
    rc = main(["experiment", "sonde", "--trials", "1", "--duration", "40", "--seed", "3", "--out", str(out),
               "--quiet", "--no-white-baseline"])
    assert rc == 0
    res = json.loads((out / "result.json").read_text(),
                     parse_constant=lambda c: pytest.fail(f"non-strict JSON {c}"))
    for key in ("by_range_km", "during_radar_loss", "during_gnss_outage", "anees", "wall_s", "continuity"):
        assert key in res
    assert [b["range_km"] for b in res["by_range_km"]] == [25.0 * i for i in range(10)]
    assert set(res["by_range_km"][0]["rmse_m"]) == {"fused", "radar_only", "relay_only"}
    assert res["by_range_km"][0]["n"] > 0
    assert set(res["anees"]) == {"fused", "radar_only", "relay_only"}
    assert res["continuity"]["fused_estimate_every_epoch"] is True
    for f in E.FIGURES:
        assert (out / f).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("argv", [["--trials", "0"], ["--duration", "-5"], ["--backend", "gpu"],
                                  ["--filter", "kalman"], ["--seed", "x"], ["--bogus"]])
def test_cli_bad_flags_exit_2_with_one_line(argv, capsys, tmp_path):
    rc = main(["experiment", "sonde", "--out", str(tmp_path)] + argv)
    err = capsys.readouterr().err
    assert rc == 2
    assert len(err.strip().splitlines()) == 1 and err.startswith("error:")


def test_tracker_rejects_bad_parameters():
    with pytest.raises(ValueError, match="mode"):
        SondeTrackerParams(mode="both")
    with pytest.raises(ValueError, match="radar_sigma"):
        SondeTrackerParams(radar_sigma=(15.0, 0.0, 1e-3))
    with pytest.raises(ValueError, match="gate_prob"):
        SondeTrackerParams(gate_prob=1.0)
    with pytest.raises(ValueError, match="run_id"):
        SondeTracker("bad run id")


# ---------------------------------------------------------------- relay error states


def test_satellite_error_states_persist_through_an_outage_and_new_satellites_get_a_fresh_one():
    trk = SondeTracker(RUN, SondeTrackerParams(mode="relay_only", bias_slots=3))
    L = trk.layout
    assert L.nb == 3 and L.n == 17 + 3 and L.bias == 17
    s = trk._slot("s1")
    trk._x[s] = 1.0
    trk._P[s] = np.full((L.n, L.n), 0.5) + np.eye(L.n)
    c1 = trk._bias_cols(s, ("G01", "G02"), 0.0)
    assert sorted(c1.tolist()) == [17, 18]
    # a fresh state: zero, unit variance, uncorrelated
    for k in c1:
        assert trk._x[s, k] == 0.0 and trk._P[s, k, k] == 1.0
        assert np.count_nonzero(trk._P[s, k]) == 1 and np.count_nonzero(trk._P[s, :, k]) == 1
    trk._x[s, c1] = [0.3, -0.2]
    trk._bias_cols(s, (), 5.0)  # a GNSS outage: nothing delivered
    c2 = trk._bias_cols(s, ("G02", "G01"), 10.0)  # back, in another order: the same states, untouched
    np.testing.assert_array_equal(c2, c1[::-1])
    np.testing.assert_array_equal(trk._x[s, c1], [0.3, -0.2])
    c3 = trk._bias_cols(s, ("G01", "R05", "R06"), 11.0)  # G02 set, two new ones: G02's state is reused
    assert c3[0] == c1[0] and sorted(c3.tolist()) == [17, 18, 19]
    assert trk._x[s, c3[1]] == 0.0 and trk._x[s, c3[2]] == 0.0 and trk.counters.bias_assigned == 4
    c4 = trk._bias_cols(s, ("G01", "R05", "R06", "G07"), 12.0)  # more satellites than states
    assert c4[-1] == -1 and trk.counters.bias_overflow == 1
    np.testing.assert_array_equal(c4[:3], c3)


def test_relay_error_model_compiled_matches_numpy_and_the_world_budget():
    from sitl.geodesy import enu_to_ecef
    from sitl.radio.relay import RelayErrorBudget

    lat, lon, h, _ = _site()
    trk = SondeTracker(RUN, SondeTrackerParams(mode="fused"))
    ref = SondeTracker(RUN, SondeTrackerParams(mode="fused", backend="numpy"))
    el = np.radians([5.0, 12.0, 30.0, 60.0, 89.0])
    az = np.radians([10.0, 100.0, 200.0, 300.0, 45.0])
    hs = np.array([100.0, 8_000.0, 31_000.0])
    pos = np.stack([geodetic_to_ecef(lat, lon, hh) for hh in hs])
    los = np.stack([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), np.sin(el)], -1)
    sat = np.stack([np.stack([enu_to_ecef(2.2e7 * u, lat, lon, hh) for u in los]) for hh in hs])
    glo = np.array([False, True, False, True, False])
    a, b = trk._relay_error_model(pos, sat, glo, 1.0), ref._relay_error_model(pos, sat, glo, 1.0)
    np.testing.assert_allclose(a[0], b[0], rtol=1e-12)
    np.testing.assert_allclose(a[1], b[1], rtol=1e-12)
    e = RelayErrorBudget()
    want = np.sqrt(np.sum(e.slow_sigmas_m(glo, el, hs[:, None]) ** 2, axis=-1))
    np.testing.assert_allclose(a[0], want, rtol=2e-3)  # the tracker's vertical and height are approximate
    mu = math.exp(-1.0 / e.multipath_tau_s)
    np.testing.assert_allclose(a[1], np.broadcast_to(e.multipath_sigma_m(el) ** 2 * (1 + mu) / (1 - mu), (3, 5)), rtol=2e-3)
    assert SondeTrackerParams().slow_tau_s == pytest.approx(1800.0, rel=0.1)  # the ionosphere dominates


@pytest.mark.slow
def test_relay_only_with_the_error_budget_beats_a_tracker_that_ignores_it():
    """On budget data, the same relay-only filter without the error states (white-noise model)
    is over-confident: its NEES is far above that of the modelled one."""
    raw = E.run_trials(E.SondeScenario(duration_s=900.0, white_baseline=False), 21, range(3), modes=("relay_only",))
    ok = raw["count"][0] > 0
    err = (raw["pos"][0] - raw["truth_pos"])[ok]
    n_model = float(np.mean(nees(err, raw["cov"][0][ok][:, :3, :3])))
    # the same data, a tracker that takes the relay errors as absent
    t0, _, _, _, track, radar, relay = E.world(E.SondeScenario(duration_s=900.0), 21, [0])
    assert 1.0 < n_model < 6.0
    naive = SondeTracker(RUN, dataclasses.replace(E.tracker_params(E.SondeScenario(), "relay_only"), relay_errors=None))
    assert naive.layout.nb == 0
    rt = relay.track(track.t_gps_s, track.pos_ecef_m, track.vel_ecef_m_s)
    e2 = []
    for k in range(0, track.t_gps_s.size):
        d = rt.delivered[k, 0]
        naive.on_message(f"{RUN}/sonde/s0/relay", SondeRelay(
            t_gps_s=float(rt.t_gps_s[k]), source_id="g", seq=k, sat_ids=rt.sat_id[d], pseudorange_m=rt.pseudorange_m[k, 0][d],
            pseudo_doppler_m_s=rt.pseudo_doppler_m_s[k, 0][d], var_pseudorange_m2=rt.var_pr_m2[k, 0][d],
            var_pseudo_doppler_m2_s2=rt.var_prr_m2_s2[k, 0][d], sat_pos_ecef_m=rt.sat_pos_ecef_m[k, 0][d],
            sat_vel_ecef_m_s=rt.sat_vel_ecef_m_s[k, 0][d], ground_pos_ecef_m=rt.ground_pos_ecef_m))
        est = naive.step(float(rt.t_gps_s[k]))
        if est and k > 100:
            pe = est[0].pos_ecef_m - track.pos_ecef_m[k, 0]
            e2.append(float(nees(pe, est[0].cov[:3, :3])))
    assert np.mean(e2) > 3 * n_model
