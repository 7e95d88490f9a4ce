"""`skyfuse experiment beacon`: seed 002, a (moving) radio beacon located from >= 3 UAVs.

Batch mode of the SITL (docs: ARCHITECTURE.md "Two ways to run"): the same components a
live run has, stepped in simulation time over one ``sitl.bus.InMemoryTransport``, drained
every epoch (1 s):

    UAV swarm (RK4, 0.01 s) -> GNSS receivers -> onboard EKFs    -> bus uav/<i>/nav (UavNav)
    beacon (RK4) -> range / Doppler at each UAV + the UAV's nav  -> bus uav/<i>/beacon/b1
    truth                                                        -> bus truth/{beacon,uav}/...
    ground station: ground_station.beacon_locator.BeaconLocator  -> bus gs/estimate/beacon/b1
    scoring: subscribes to truth and gs/estimate only

Each Monte Carlo trial is one run id (``<base>-t<k>``) on the shared bus; the UAVs' filters
and the locator run all trials as one batch.  The production locator ("inflate") publishes
its Estimates on the bus and is scored from there; the comparison locators on the same
messages ("ignore", "inflate" with white UAV errors, the seed's position-only filter) are
scored from their states.  The centralised filter (ground_station.beacon_central) is then
replayed on the same receiver outputs and links, and the PCRB computed at the truth.

Cases: ``three_satellites`` (the paper's: three satellites on unperturbed Keplerian orbits,
vehicles.uav_nav.seed002_three_satellites) and ``constellation`` (the GPS almanac, every
satellite above 10 deg), both with --uavs UAVs; ``by_uav_count``: the constellation case
with 3, 5, 10 and 30 UAVs -- the first three at the seed's start points, the others on a
sunflower pattern (golden-angle spiral) of radius 0.35 deg about (30.15 N, 45.15 E) at
3000-3500 m, flying the seed's law (105 +- 5 m/s, climb 15 cos(0.01 t), heading along the
ECEF eta axis +- 0.1 rad): "placed like the seed's with further offsets", but spread in
two dimensions rather than along the seed's line.

Scoring (after the first 100 s, as in the paper): ``errors_m`` per ECEF axis (xi, eta,
zeta = x, y, z): the largest |error| of each trial, their median over trials and their max;
``rmse_m`` the 3-D position RMSE over trials and epochs; ``pcrb_m`` the mean over the same
epochs of sqrt(trace) of the PCRB's beacon position block; ``anees`` the position NEES (3
dof) averaged over trials at each epoch, then over the epochs, with the 99 % chi-square
band of one epoch's average.

Writes DIR/result.json (strict JSON) and PNG figures.  Progress on stderr.
"""
from __future__ import annotations

import json
import math
import time
import warnings
from pathlib import Path

import numpy as np

from sitl.experiments._common import component, prepare_out, progress_printer, save_figure, strict

PAPER_ERRORS_M = {"xi": 25.0, "eta": 9.0, "zeta": 15.0}
AXES = ("xi", "eta", "zeta")
CASES = ("three_satellites", "constellation")
SETTLE_S = 100.0
DT_S = 1.0
BEACON_ID = "b1"
FIGURES = ("beacon_errors.png", "beacon_rmse_vs_pcrb.png", "beacon_uav_count.png")
# locators on the same messages: name -> LocatorConfig overrides
_BLOCK = 64  # epochs whose world side (receiver geometry, filter ephemeris) is computed in one call
_BLOCK_ROWS = 4096  # at most this many epochs x trials x UAVs in one block
LOCATORS = {
    "inflate": {},
    "inflate_white": {"uav_error_corr_s": 0.0},
    "ignore": {"observer_uncertainty": "ignore"},
    "position_only": {"motion": "position"},
}


# ------------------------------------------------------------------ the world
def uav_starts(n: int):
    """(lat deg, lon deg, h m) of n UAVs: the seed's three, then a sunflower pattern."""
    SEED002_UAV_START = component("vehicles.uav").SEED002_UAV_START

    out = [tuple(s) for s in SEED002_UAV_START[:n]]
    golden = math.pi * (3.0 - math.sqrt(5.0))
    m = n - 3
    for j in range(m):
        r = 0.35 * math.sqrt((j + 0.5) / m)
        th = j * golden
        out.append((30.15 + r * math.cos(th), 45.15 + r * math.sin(th), 3000.0 + 100.0 * (j % 6)))
    return out[:n]


def truth_tracks(n_uavs: int, duration_s: float):
    """Truth at the epochs 0, 1, ... duration (RK4, 0.01 s): t (K,), U, V (K, N, 3), B, VB (K, 3)."""
    beacon = component("vehicles.beacon")
    uav = component("vehicles.uav")

    if n_uavs == 3:
        sw = uav.seed002_uav_swarm()
    else:
        s = np.array(uav_starts(n_uavs))
        lat, lon = np.radians(s[:, 0]), np.radians(s[:, 1])
        law = uav.SinusoidalLaw(speed_mean_m_s=105.0, speed_amp_m_s=5.0, speed_omega_rad_s=0.02,
                                heading0_rad=uav.eta_axis_heading_rad(lat, lon), heading_amp_rad=0.1,
                                heading_omega_rad_s=0.01, climb_amp_m_s=15.0, climb_omega_rad_s=0.01)
        sw = uav.UavSwarm(law, lat, lon, s[:, 2])
    bc = beacon.seed002_beacon("seed")
    t = np.arange(0.0, float(duration_s) + 1e-9, DT_S)
    tu, tb = sw.track(t), bc.track(t)  # = step(t) epoch by epoch, in one compiled call each
    return t, tu.pos_ecef_m, tu.vel_ecef_m_s, tb.pos_ecef_m, tb.vel_ecef_m_s


def constellation_for(case: str, U0, duration_s: float):
    from sitl.gnss import orbits
    uav_nav = component("vehicles.uav_nav")

    if case == "three_satellites":
        return uav_nav.seed002_three_satellites(U0, uav_nav.SEED002_T0_GPS_S, duration_s=duration_s)
    return orbits.gps_constellation()


def gnss_information(t_gps, U, V, constellation, config):
    """Each UAV's GNSS Fisher information H' R^-1 H at its true state (K, N, 6, 6), with the
    satellites' instantaneous states and the elevation mask at the true position."""
    from sitl import geodesy
    from sitl.gnss import orbits
    ClockFreePseudorangeDoppler = component("vehicles.uav_nav").ClockFreePseudorangeDoppler

    K, N = U.shape[:2]
    out = np.empty((K, N, 6, 6))
    for k in range(K):
        sp, sv = orbits.sat_state_ecef(constellation, float(t_gps[k]))
        _, el, _ = geodesy.ecef_to_aer(U[k][:, None, :], sp[None])
        model = ClockFreePseudorangeDoppler(np.broadcast_to(sp, (N,) + sp.shape), np.broadcast_to(sv, (N,) + sv.shape),
                                            config.noise.var_pr_m2, config.noise.var_prr_m2_s2,
                                            el >= config.el_mask_rad)
        _, H = model.h_and_H(np.concatenate([U[k], V[k]], axis=-1))
        w = 1.0 / model.R_diag()
        out[k] = np.einsum("nki,nk,nkj->nij", H, w, H)
    return out


# ------------------------------------------------------------------ one case over the bus
class _Scorer:
    """Subscribes to the truth and the ground station's estimates (scoring only)."""

    def __init__(self, bus, run_ids, K, source_id="gs"):
        self.row = {r: k for k, r in enumerate(run_ids)}
        self.source_id = source_id
        self.t_index = None
        T = len(run_ids)
        self.x = np.full((K, T, 6), np.nan)
        self.P = np.full((K, T, 6, 6), np.nan)
        self.mode = np.full((K, T), "", dtype=object)
        self.truth = np.full((K, 6), np.nan)
        self.uav_truth_msgs = 0
        bus.subscribe(f"*/gs/estimate/beacon/{BEACON_ID}", self.on_estimate)
        bus.subscribe("*/truth/**", self.on_truth)

    def on_estimate(self, key, msg):
        k = self.row.get(key.split("/", 1)[0])
        if k is None or msg.source_id != self.source_id:
            return
        self.x[self.t_index, k] = np.concatenate([msg.pos_ecef_m, msg.vel_ecef_m_s])
        self.P[self.t_index, k] = msg.cov
        self.mode[self.t_index, k] = msg.mode

    def on_truth(self, key, msg):
        if msg.kind == "beacon":
            self.truth[self.t_index] = np.concatenate([msg.pos_ecef_m, msg.vel_ecef_m_s])
        else:
            self.uav_truth_msgs += 1


def run_case(case, tracks, trials, seed, locators=("inflate",), progress=None, central=True,
             timing=None) -> dict:
    """One case through the bus (module docstring).  Returns the raw series and counters."""
    BeaconLocator = component("ground_station.beacon_locator").BeaconLocator
    LocatorConfig = component("ground_station.beacon_locator").LocatorConfig
    from sitl.bus import BeaconMeasurement, InMemoryTransport, Truth, UavNav, key_for
    from sitl.radio import beacon_link
    uav_nav = component("vehicles.uav_nav")

    t, U, V, B, VB = tracks
    K, N = U.shape[:2]
    T = int(trials)
    tm = timing if timing is not None else {}

    def clock(name, t0):
        tm[name] = tm.get(name, 0.0) + time.perf_counter() - t0

    t0 = time.perf_counter()
    const = constellation_for(case, U[0, 0], t[-1])
    nav_cfg = uav_nav.NavConfig()
    link_cfg = beacon_link.BeaconLinkConfig()
    t_gps = uav_nav.SEED002_T0_GPS_S + t
    clock("setup", t0)
    rng = np.random.default_rng([seed, CASES.index(case) if case in CASES else 7, N])
    base = f"beacon-{case[:5]}-n{N}-s{seed}"
    run_ids = [f"{base}-t{k:03d}" for k in range(T)]
    bus = InMemoryTransport(start_t_gps_s=float(t_gps[0]))
    locs = {}
    for name in locators:
        cfg = LocatorConfig(**LOCATORS[name])
        locs[name] = BeaconLocator(bus, run_ids=run_ids, beacon_id=BEACON_ID, config=cfg,
                                   source_id="gs" if name == "inflate" else f"gs-{name.replace('_', '-')}",
                                   publish_estimates=name == "inflate")
    scorer = _Scorer(bus, run_ids, K)
    nav = uav_nav.OnboardNav(const, nav_cfg)
    side = {name: np.full((K, T, 6), np.nan) for name in locators if name != "inflate"}
    side_P = {name: np.full((K, T, 6, 6), np.nan) for name in locators if name != "inflate"}
    nav_x = np.empty((K, T, N, 6))
    nav_P = np.empty((K, T, N, 6, 6))
    epochs, links = [], []
    uav_keys = [[key_for(r, UavNav, uav=i + 1) for i in range(N)] for r in run_ids]
    bm_keys = [[key_for(r, BeaconMeasurement, uav=i + 1, beacon=BEACON_ID) for i in range(N)] for r in run_ids]
    truth_base = base
    truth_b_key = key_for(truth_base, Truth, kind="beacon", id=BEACON_ID)
    truth_u_keys = [key_for(truth_base, Truth, kind="uav", id=i + 1) for i in range(N)]
    src = [f"uav{i + 1}" for i in range(N)]
    world = world_epochs(tracks, const, T, rng, nav_cfg, link_cfg, clock=clock)
    for k in range(K):
        tk = float(t_gps[k])
        ep, meas, sat = next(world)
        # UAVs: onboard filters (all trials x UAVs as one batch)
        t0 = time.perf_counter()
        est = nav.update(ep, sat)
        nav_x[k], nav_P[k] = est.x, est.P
        clock("uav_gnss_and_nav", t0)
        if central:
            epochs.append(ep)
            links.append(meas)
        # publish: UavNav, BeaconMeasurement (with the nav snapshot), truth
        t0 = time.perf_counter()
        # per-epoch conversions done once for the batch (the same numbers: C + C' element-wise,
        # Python ints and floats from tolist)
        ntr = est.n_tracked.tolist()
        sym = 0.5 * (est.P + np.swapaxes(est.P, -1, -2))
        r_l, rr_l = meas.range_m.tolist(), meas.range_rate_m_s.tolist()
        vr_l, vv_l = meas.var_range_m2.tolist(), meas.var_range_rate_m2_s2.tolist()
        for j in range(T):
            for i in range(N):
                x, C = est.x[j, i], sym[j, i]
                bus.publish(uav_keys[j][i], UavNav(t_gps_s=tk, source_id=src[i], seq=k, pos_ecef_m=x[0:3],
                                                   vel_ecef_m_s=x[3:6], cov=C, n_sats=ntr[j][i], fix_type=3))
                bus.publish(bm_keys[j][i], BeaconMeasurement(
                    t_gps_s=tk, source_id=src[i], seq=k, range_m=r_l[j][i], range_rate_m_s=rr_l[j][i],
                    var_range_m2=vr_l[j][i], var_range_rate_m2_s2=vv_l[j][i], uav_pos_ecef_m=x[0:3],
                    uav_vel_ecef_m_s=x[3:6], uav_cov=C))
        bus.publish(truth_b_key,
                    Truth(t_gps_s=tk, source_id="truth", seq=k, kind="beacon", pos_ecef_m=B[k], vel_ecef_m_s=VB[k]))
        for i in range(N):
            bus.publish(truth_u_keys[i],
                        Truth(t_gps_s=tk, source_id="truth", seq=k, kind="uav", pos_ecef_m=U[k, i],
                              vel_ecef_m_s=V[k, i]))
        clock("bus_publish", t0)
        t0 = time.perf_counter()
        scorer.t_index = k
        bus.drain(tk)
        clock("bus_drain", t0)
        # the ground station: every locator steps the epoch (the production one publishes)
        for name, loc in locs.items():
            t0 = time.perf_counter()
            loc.step(tk)  # the production locator also publishes its Estimates here
            clock(f"locator_{name}", t0)
            if name != "inflate":
                side[name][k], side_P[name][k] = loc.state_ecef()
                side[name][k][~loc.initialised] = np.nan
        t0 = time.perf_counter()
        bus.drain(tk)
        clock("bus_drain", t0)
        if progress and (k % 200 == 0 or k == K - 1):
            progress(f"[{case} N={N}] t = {t[k]:6.0f} s of {t[-1]:.0f}")
    est_x, est_P = scorer.x, scorer.P
    out = {"t": t, "truth": scorer.truth, "nav_x": nav_x, "nav_P": nav_P, "x": {"inflate": est_x},
           "P": {"inflate": est_P}, "mode": scorer.mode, "counters": {}, "bus": _bus_stats(bus)}
    for name in side:
        out["x"][name], out["P"][name] = side[name], side_P[name]
    for name, loc in locs.items():
        out["counters"][name] = {**dict(loc.counters), **{f"rejected_{r}": c for r, c in loc.rejected.items()}}
    loc = locs.get("inflate")
    if central and loc is not None:
        t0 = time.perf_counter()
        out["central"] = _central(loc, const, nav_cfg, t_gps, epochs, links, nav_x, nav_P)
        clock("central_filter", t0)
    out["constellation"] = const
    return out


def world_epochs(tracks, const, trials, rng, nav_cfg, link_cfg, filter_states=True, clock=None):
    """The world side of run_case, epoch by epoch: yields (GnssEpoch, BeaconLinkMeasurement,
    the onboard filters' satellite states or None) for trials x UAVs.

    Computed in blocks of up to _BLOCK epochs: the receivers' geometry of a block's epochs in one
    call, then the receivers' and links' noise epoch by epoch (the random draws in the same
    order as stepping one epoch at a time), then the ephemeris the onboard filters compute
    from those receiver outputs (``filter_states``), again in one call: the same numbers as
    one epoch at a time (vehicles.uav_nav.truth_geometry, filter_sat_states).  clock(name,
    t0) is told the time spent ("uav_gnss_and_nav", "beacon_link")."""
    uav_nav = component("vehicles.uav_nav")
    from sitl.radio import beacon_link

    t, U, V, B, VB = tracks
    K, N = U.shape[:2]
    t_gps = uav_nav.SEED002_T0_GPS_S + t
    tick = clock or (lambda name, t0: None)
    # epochs per block: up to _BLOCK, fewer for large trials x UAVs batches so that a block's
    # arrays stay small (<= _BLOCK_ROWS receivers x satellites x 3 doubles each)
    block = max(1, min(_BLOCK, _BLOCK_ROWS // max(1, int(trials) * N)))
    for k0 in range(0, K, block):
        blk = range(k0, min(k0 + block, K))
        t0 = time.perf_counter()
        geo = uav_nav.truth_geometry(t_gps[blk.start:blk.stop, None], U[blk.start:blk.stop], V[blk.start:blk.stop],
                                     const, nav_cfg)
        eps, links = [], []
        for j, k in enumerate(blk):
            eps.append(uav_nav.gnss_measure(rng, float(t_gps[k]), U[k], V[k], const, nav_cfg, trials_shape=(trials,),
                                            geometry=geo.at(j)))
            t2 = time.perf_counter()
            links.append(beacon_link.measure(rng, U[k], V[k], B[k], VB[k], link_cfg, trials_shape=(trials,)))
            tick("beacon_link", t2)
            t0 += time.perf_counter() - t2
        sat = uav_nav.filter_sat_states(eps, const, nav_cfg) if filter_states else None
        tick("uav_gnss_and_nav", t0)
        for j in range(len(blk)):
            yield eps[j], links[j], None if sat is None else (sat[0][j], sat[1][j])


def _bus_stats(bus) -> dict:
    s = bus.stats
    return {"published": s.published, "published_bytes": s.published_bytes, "delivered": s.total.delivered,
            "rejected": dict(s.total.rejected), "callback_errors": s.total.callback_errors}


def _central(loc, const, nav_cfg, t_gps, epochs, links, nav_x, nav_P):
    """Replay the centralised filter on the same data from the locator's start (module doc)."""
    CentralFilter = component("ground_station.beacon_central").CentralFilter
    LinkEpoch = component("ground_station.beacon_central").LinkEpoch
    uav_nav = component("vehicles.uav_nav")

    K, T, N = nav_x.shape[:3]
    if not loc.initialised.all() or len({f.n_epochs for f in loc.init_info}) != 1:
        return None
    k0 = loc.config.init_epochs - 1  # every trial initialised at the same epoch (no losses)
    y0, P0, fr0 = [], [], []
    chosen = loc.start_side
    for j, fix in enumerate(loc.init_info):
        x, P = (fix.mirror_x, fix.mirror_P) if chosen[j] else (fix.x, fix.P)
        ob = loc.init_window_last[j]
        y, Py, fr = loc._to_state(x, P, ob)
        y0.append(y)
        P0.append(Py)
        fr0.append(fr)
    Frame = component("ground_station.beacon_locator").Frame

    frame = Frame(*(np.concatenate([f[i] for f in fr0]) for i in range(len(Frame._fields))))
    cf = CentralFilter(N, loc.config, q_uav_m2_s3=nav_cfg.q_m2_s3).start(
        t_gps[k0], np.array(y0), np.array(P0), frame, nav_x[k0], nav_P[k0])
    xs = np.full((K, T, 6), np.nan)
    Ps = np.full((K, T, 6, 6), np.nan)
    xs[k0], Ps[k0] = cf.beacon_ecef()
    for k in range(k0 + 1, K):
        model, z = uav_nav.nav_measurement_model(epochs[k], const, nav_cfg)
        gnss = []
        for i in range(N):
            mi = uav_nav.ClockFreePseudorangeDoppler(model.sat_pos_ecef_m[:, i], model.sat_vel_ecef_m_s[:, i],
                                                     nav_cfg.noise.var_pr_m2, nav_cfg.noise.var_prr_m2_s2,
                                                     model.tracked[:, i])
            gnss.append((mi, z[:, i]))
        m = links[k]
        cf.step(t_gps[k], gnss, LinkEpoch(m.range_m, m.range_rate_m_s, m.var_range_m2, m.var_range_rate_m2_s2))
        xs[k], Ps[k] = cf.beacon_ecef()
    return {"x": xs, "P": Ps}


# ------------------------------------------------------------------ metrics
def _scores(t, x, P, truth):
    """errors_m, rmse_m, anees of one estimator's series (K, T, 6) against truth (K, 6)."""
    from filters import metrics

    sel = t >= SETTLE_S
    e = x[sel, :, 0:3] - truth[sel, None, 0:3]
    ok = np.all(np.isfinite(e), axis=(0, 2))
    if not ok.any():
        return None
    e = e[:, ok]
    Pp = P[sel][:, ok, 0:3, 0:3]
    T = e.shape[1]
    per_trial_max = np.max(np.abs(e), axis=0)  # (T, 3)
    errors = {ax: {"median_of_trial_max": float(np.median(per_trial_max[:, a])),
                   "max_over_trials": float(np.max(per_trial_max[:, a])),
                   "paper": PAPER_ERRORS_M[ax],
                   "within_paper_fraction": float(np.mean(per_trial_max[:, a] <= PAPER_ERRORS_M[ax]))}
              for a, ax in enumerate(AXES)}
    nees = metrics.nees(e, Pp)  # (Ks, T)
    per_epoch = nees.mean(axis=1)
    lo, hi = metrics.chi2_bounds(3, T, 0.99)
    ev = x[sel][:, ok, 3:6] - truth[sel, None, 3:6]
    return {
        "errors_m": errors,
        "rmse_m": float(np.sqrt(np.mean(np.sum(e * e, axis=-1)))),
        "rmse_per_trial_m": np.sqrt(np.mean(np.sum(e * e, axis=-1), axis=0)).tolist(),
        "rmse_axes_m": {ax: float(np.sqrt(np.mean(e[..., a] ** 2))) for a, ax in enumerate(AXES)},
        "vel_rmse_m_s": float(np.sqrt(np.mean(np.sum(ev * ev, axis=-1)))),
        "sigma_m": float(np.sqrt(np.mean(np.trace(Pp, axis1=-2, axis2=-1)))),
        "anees": {"value": float(per_epoch.mean()), "dof": 3, "trials": int(T),
                  "bounds_99_one_epoch": [lo, hi],
                  "fraction_of_epochs_inside": float(np.mean((per_epoch >= lo) & (per_epoch <= hi))),
                  "median_over_epochs": float(np.median(per_epoch))},
        "trials_scored": int(T),
    }


def _series(t, x, truth):
    """RMS over trials per epoch of the 3-D position error (K,), NaN before initialisation."""
    e = x[..., 0:3] - truth[:, None, 0:3]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN epochs before the start
        return np.sqrt(np.nanmean(np.sum(e * e, axis=-1), axis=1))


def pcrb_series(tracks, const, nav_cfg, cfg):
    """sqrt(trace) of the PCRB beacon position block per epoch (K,) (centralised model)."""
    pcrb_central = component("ground_station.beacon_central").pcrb_central
    _up = component("ground_station.beacon_locator")._up
    from sitl.radio.beacon_link import BeaconLinkConfig
    uav_nav = component("vehicles.uav_nav")

    t, U, V, B, VB = tracks
    t_gps = uav_nav.SEED002_T0_GPS_S + t
    info = gnss_information(t_gps, U, V, const, nav_cfg)
    up, _ = _up(B[0])
    J0 = np.zeros((6, 6))
    J0[0:3, 0:3] = np.outer(up, up) / cfg.init_height_sigma_m ** 2 + np.eye(3) / 1e5 ** 2
    J0[3:6, 3:6] = np.eye(3) / cfg.init_vel_sigma_m_s ** 2
    link = BeaconLinkConfig()
    Bd = pcrb_central(t, B, VB, U, V, info, link.var_range_m2, link.var_range_rate_m2_s2, J0,
                      q_beacon_m2_s3=cfg.q_m2_s3, q_uav_m2_s3=nav_cfg.q_m2_s3)
    return np.sqrt(np.trace(Bd, axis1=-2, axis2=-1)), Bd


def summarise_case(res, pcrb_tr, name="inflate") -> dict:
    t, truth = res["t"], res["truth"]
    sc = _scores(t, res["x"][name], res["P"][name], truth)
    sel = t >= SETTLE_S
    d = dict(sc) if sc else {}
    d["pcrb_m"] = float(np.mean(pcrb_tr[sel]))
    return d


def uav_nav_rmse(res, tracks):
    t, U, V, _, _ = tracks
    sel = t >= SETTLE_S
    e = res["nav_x"][sel] - np.concatenate([U, V], axis=-1)[sel][:, None]
    return {"pos_m": float(np.sqrt(np.mean(np.sum(e[..., 0:3] ** 2, axis=-1)))),
            "vel_m_s": float(np.sqrt(np.mean(np.sum(e[..., 3:6] ** 2, axis=-1))))}


# ------------------------------------------------------------------ result.json and figures




def plot(out: Path, cases: dict, sweep: list, meta: str) -> list[Path]:
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    # a) error per ECEF axis over time, trial 0 and the RMS over trials, paper bands
    fig, axes = plt.subplots(3, len(cases), figsize=(6.5 * len(cases), 9), sharex=True, squeeze=False,
                             constrained_layout=True)
    for c, (case, d) in enumerate(cases.items()):
        t, x, truth = d["t"], d["x"], d["truth"]
        e = x[..., 0:3] - truth[:, None, 0:3]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            rms = np.sqrt(np.nanmean(e ** 2, axis=1))
        for a, ax_name in enumerate(AXES):
            ax = axes[a, c]
            lim = PAPER_ERRORS_M[ax_name]
            ax.axhspan(-lim, lim, color="C2", alpha=0.25, lw=0, label=f"paper: within +-{lim:g} m")
            ax.fill_between(t, -rms[:, a], rms[:, a], color="C0", alpha=0.15, lw=0, label="+- RMS over trials")
            ax.plot(t, e[:, 0, a], color="C0", lw=0.9, label="trial 0")
            ax.axvline(SETTLE_S, color="0.5", ls=":", lw=0.8)
            ax.set_yscale("symlog", linthresh=30.0)
            ax.set_ylabel(f"{ax_name} (ECEF {'xyz'[a]}) error, m")
            ax.grid(alpha=0.3, which="both")
        axes[0, c].set_title(case.replace("_", " "), fontsize=10)
        axes[-1, c].set_xlabel("time, s")
    h, lab = axes[0, 0].get_legend_handles_labels()
    fig.legend(h, lab, loc="outside lower center", ncol=3, fontsize=8)
    fig.suptitle(f"Seed 002: beacon position error per ECEF axis (symlog; linear within +-30 m)\n{meta}")
    files.append(save_figure(fig, out / FIGURES[0]))

    # b) RMSE vs PCRB over time
    fig, axes = plt.subplots(1, len(cases), figsize=(6.5 * len(cases), 4.8), squeeze=False, constrained_layout=True)
    for c, (case, d) in enumerate(cases.items()):
        ax = axes[0, c]
        t = d["t"]
        ax.plot(t, d["rmse_series"], color="C0", lw=1.4, label="decomposed locator (inflate): RMSE")
        if d.get("central_series") is not None:
            ax.plot(t, d["central_series"], color="C1", lw=1.1, label="centralised filter: RMSE")
        if d.get("ignore_series") is not None:
            ax.plot(t, d["ignore_series"], color="C3", lw=0.9, ls="--", label="locator, UAVs ignored: RMSE")
        ax.plot(t, d["sigma_series"], color="C0", lw=0.8, ls=":", label="locator's own sigma (RMS)")
        ax.plot(t, d["pcrb_series"], color="k", lw=1.4, label="PCRB (centralised, true states)")
        ax.axhline(math.sqrt(sum(v * v for v in PAPER_ERRORS_M.values())), color="C2", lw=1.0, ls="-.",
                   label="paper's bands as a 3-D figure (30 m)")
        ax.set_yscale("log")
        ax.set_xlabel("time, s")
        ax.set_ylabel("3-D position, m")
        ax.set_title(case.replace("_", " "), fontsize=10)
        ax.grid(alpha=0.3, which="both")
    h, lab = axes[0, 0].get_legend_handles_labels()
    fig.legend(h, lab, loc="outside lower center", ncol=3, fontsize=8)
    fig.suptitle(f"Seed 002: beacon RMSE against the posterior Cramer-Rao bound\n{meta}")
    files.append(save_figure(fig, out / FIGURES[1]))

    # c) RMSE and PCRB vs number of UAVs
    fig, ax = plt.subplots(figsize=(6.5, 4.8), constrained_layout=True)
    if sweep:
        n = [s["uavs"] for s in sweep]
        ax.plot(n, [s["rmse_m"] for s in sweep], "o-", color="C0", label="locator RMSE (after 100 s)")
        ax.plot(n, [s["pcrb_m"] for s in sweep], "s--", color="k", label="PCRB (centralised)")
        for s in sweep:
            ax.annotate(f"{s['rmse_m']:.0f}", (s["uavs"], s["rmse_m"]), xytext=(4, 4), textcoords="offset points",
                        fontsize=8, color="C0")
            ax.annotate(f"{s['pcrb_m']:.0f}", (s["uavs"], s["pcrb_m"]), xytext=(4, -11), textcoords="offset points",
                        fontsize=8)
        ax.axhline(30.0, color="C2", lw=1.0, ls="-.", label="paper's bands as a 3-D figure (30 m)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xticks(n, [str(v) for v in n])
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel("number of UAVs")
    ax.set_ylabel("3-D beacon position, m")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    trials = sweep[0]["trials"] if sweep else 0
    ax.set_title(f"Seed 002, GPS constellation: accuracy against the number of UAVs ({trials} trials each)\n"
                 "3 UAVs: the seed's near-collinear line; more: spread in two dimensions", fontsize=10)
    files.append(save_figure(fig, out / FIGURES[2]))
    return files


# ------------------------------------------------------------------ the command




def check_args(args):
    """Range checks beyond argparse's types; UsageError (one line) on a bad value."""
    from sitl.cli import UsageError

    if args.uavs < 3:
        raise UsageError(f"--uavs: at least 3 UAVs are needed, got {args.uavs}")
    if args.uavs > 100:
        raise UsageError(f"--uavs: at most 100, got {args.uavs}")
    if not (math.isfinite(args.duration) and args.duration > SETTLE_S + 5.0):
        raise UsageError(f"--duration: must exceed {SETTLE_S + 5.0:g} s (the errors are scored after the first "
                         f"{SETTLE_S:g} s), got {args.duration:g}")
    if args.duration > 36000.0:
        raise UsageError(f"--duration: at most 36000 s, got {args.duration:g}")
    counts = sorted(set(args.uav_counts))
    if any(n < 3 or n > 100 for n in counts):
        raise UsageError(f"--uav-counts: each must lie in 3..100, got {args.uav_counts}")
    return counts


def run(args) -> dict:
    """The whole experiment; returns the result document (also written to DIR)."""
    LocatorConfig = component("ground_station.beacon_locator").LocatorConfig
    uav_nav = component("vehicles.uav_nav")

    counts = check_args(args)
    out = prepare_out(Path(args.out))
    prog = progress_printer(args.quiet)
    wall0 = time.perf_counter()
    timing = {}
    cfg = LocatorConfig()
    nav_cfg = uav_nav.NavConfig()
    track_cache = {}

    def tracks_for(n):
        if n not in track_cache:
            t0 = time.perf_counter()
            track_cache[n] = truth_tracks(n, args.duration)
            timing[f"truth_rk4_n{n}"] = time.perf_counter() - t0
        return track_cache[n]

    plots, doc_cases = {}, {}
    inflate_vs_ignore, central_vs = {}, {}
    for case in CASES:
        if prog:
            prog(f"[{case}] {args.trials} trials x {args.uavs} UAVs, {args.duration:g} s")
        tr = tracks_for(args.uavs)
        tm = {}
        t0 = time.perf_counter()
        res = run_case(case, tr, args.trials, args.seed, locators=tuple(LOCATORS), progress=prog, timing=tm)
        tm["case_wall_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        pc, _ = pcrb_series(tr, res["constellation"], nav_cfg, cfg)
        tm["pcrb"] = time.perf_counter() - t0
        timing[case] = tm
        t = res["t"]
        d = summarise_case(res, pc)
        d["uav_nav_rmse"] = uav_nav_rmse(res, tr)
        d["satellites"] = len(res["constellation"])
        d["counters"] = res["counters"]["inflate"]
        d["bus"] = res["bus"]
        d["modes"] = {m: int(np.sum(res["mode"] == m)) for m in ("fused", "degraded", "coast", "lost")}
        doc_cases[case] = d
        comp = {}
        for name in LOCATORS:
            sc = _scores(t, res["x"][name], res["P"][name], res["truth"])
            comp[name] = None if sc is None else {"rmse_m": sc["rmse_m"], "anees": sc["anees"],
                                                   "sigma_m": sc["sigma_m"], "errors_m": sc["errors_m"]}
        inflate_vs_ignore[case] = comp
        cen = res.get("central")
        if cen is not None:
            sc = _scores(t, cen["x"], cen["P"], res["truth"])
            dd = np.array(d["rmse_per_trial_m"]) - np.array(sc["rmse_per_trial_m"])
            central_vs[case] = {"decomposed_rmse_m": d.get("rmse_m"), "centralised_rmse_m": sc["rmse_m"],
                                "paired_per_trial_rmse_difference_m": {
                                    "mean": float(dd.mean()),
                                    "standard_error": (float(dd.std(ddof=1) / math.sqrt(dd.size))
                                                       if dd.size > 1 else None),
                                    "decomposed_better_in": int(np.sum(dd < 0)), "of": int(dd.size)},
                                "difference_m": d.get("rmse_m") - sc["rmse_m"],
                                "ratio": d.get("rmse_m") / sc["rmse_m"], "centralised_anees": sc["anees"],
                                "centralised_errors_m": sc["errors_m"], "pcrb_m": d["pcrb_m"]}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            sig = np.sqrt(np.nanmean(np.trace(res["P"]["inflate"][..., 0:3, 0:3], axis1=-2, axis2=-1), axis=1))
        plots[case] = {"t": t, "x": res["x"]["inflate"], "truth": res["truth"],
                       "rmse_series": _series(t, res["x"]["inflate"], res["truth"]),
                       "ignore_series": _series(t, res["x"]["ignore"], res["truth"]),
                       "central_series": None if cen is None else _series(t, cen["x"], res["truth"]),
                       "sigma_series": sig, "pcrb_series": pc}
    # by number of UAVs (constellation)
    sweep = []
    for n in counts:
        if prog:
            prog(f"[by_uav_count] {n} UAVs, {args.sweep_trials} trials")
        tr = tracks_for(n)
        tm = {}
        t0 = time.perf_counter()
        res = run_case("constellation", tr, args.sweep_trials, args.seed + 1000 + n, locators=("inflate",),
                       progress=prog, central=False, timing=tm)
        pc, _ = pcrb_series(tr, res["constellation"], nav_cfg, cfg)
        tm["wall_s"] = time.perf_counter() - t0
        timing[f"sweep_n{n}"] = tm
        sc = _scores(res["t"], res["x"]["inflate"], res["P"]["inflate"], res["truth"])
        sel = res["t"] >= SETTLE_S
        sweep.append({"uavs": n, "rmse_m": sc["rmse_m"], "pcrb_m": float(np.mean(pc[sel])),
                      "anees": sc["anees"]["value"], "errors_m": sc["errors_m"], "trials": args.sweep_trials,
                      "uav_nav_rmse": uav_nav_rmse(res, tr)})
    wall = time.perf_counter() - wall0
    three = doc_cases["three_satellites"]["errors_m"]
    reproduces = all(three[ax]["median_of_trial_max"] <= PAPER_ERRORS_M[ax] for ax in AXES)
    meta = f"{args.trials} trials, seed {args.seed}, {args.uavs} UAVs, {args.duration:g} s"
    figs = plot(out, plots, sweep, meta)
    doc = {
        "experiment": "beacon", "schema": 1, "seed": args.seed, "trials": args.trials, "uavs": args.uavs,
        "duration_s": args.duration, "epoch_s": DT_S, "settle_s": SETTLE_S,
        "paper": {"errors_m": PAPER_ERRORS_M, "note": "seed 002: errors settle within 25 / 9 / 15 m (xi / eta / zeta)"},
        "reproduces_paper": reproduces,
        "cases": doc_cases,
        "centralised_vs_decomposed": central_vs,
        "inflate_vs_ignore": inflate_vs_ignore,
        "by_uav_count": sweep,
        "locator": {k: getattr(cfg, k) for k in cfg.__dataclass_fields__},
        "wall_s": wall,
        "timing_s": timing,
        "figures": [f.name for f in figs],
    }
    doc = strict(doc)
    (out / "result.json").write_text(json.dumps(doc, indent=1, allow_nan=False))
    return doc


def table(doc) -> str:
    rows = []
    for case, d in doc["cases"].items():
        e = d["errors_m"]
        a = d["anees"]
        rows.append(f"{case:<17} max|err| after 100 s (median / max over {a['trials']} trials): "
                    + ", ".join(f"{ax} {e[ax]['median_of_trial_max']:.0f} / {e[ax]['max_over_trials']:.0f} m "
                                f"(paper {e[ax]['paper']:g})" for ax in AXES))
        rows.append(f"{'':<17} RMSE {d['rmse_m']:.1f} m, PCRB {d['pcrb_m']:.1f} m, ANEES {a['value']:.2f} "
                    f"(99% band {a['bounds_99_one_epoch'][0]:.2f}..{a['bounds_99_one_epoch'][1]:.2f}), "
                    f"UAV nav RMSE {d['uav_nav_rmse']['pos_m']:.1f} m / {d['uav_nav_rmse']['vel_m_s']:.3f} m/s")
        c = doc["centralised_vs_decomposed"].get(case)
        if c:
            rows.append(f"{'':<17} centralised RMSE {c['centralised_rmse_m']:.1f} m vs decomposed "
                        f"{c['decomposed_rmse_m']:.1f} m (ratio {c['ratio']:.2f})")
        iv = doc["inflate_vs_ignore"][case]
        rows.append(f"{'':<17} " + "; ".join(f"{k}: RMSE {v['rmse_m']:.0f} m ANEES {v['anees']['value']:.3g}"
                                             for k, v in iv.items() if v))
    for s in doc["by_uav_count"]:
        rows.append(f"by_uav_count {s['uavs']:>3} UAVs: RMSE {s['rmse_m']:.1f} m, PCRB {s['pcrb_m']:.1f} m, "
                    f"ANEES {s['anees']:.2f} ({s['trials']} trials)")
    rows.append(f"paper's 25/9/15 m reproduced (three satellites, median of trial max): {doc['reproduces_paper']}; "
                f"wall {doc['wall_s']:.1f} s")
    return "\n".join(rows)


def main(args) -> int:
    doc = run(args)
    print(table(doc))
    print(f"wrote {Path(args.out) / 'result.json'} and {', '.join(doc['figures'])}")
    return 0
