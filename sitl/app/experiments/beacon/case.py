"""One case of the beacon experiment through the in-memory bus: the UAVs' onboard filters, the
locators on the same messages (the production one publishing its Estimates), the scorer on the
truth and the estimates, and the centralised filter replayed on the same data."""
from __future__ import annotations

import time

import numpy as np

from sitl.app.experiments.beacon.constants import (BEACON_ID, CASES, CENTRAL_START_PRIOR_S, FAULT_DEFAULTS,
                                                   LOCATORS, MEASUREMENT_KEYS, PRIOR_UPDATE_ITERATIONS, PRODUCTION)
from sitl.app.experiments.beacon.world import constellation_for, world_epochs
from sitl.app.experiments.common import measurement_faults


def locator_config(name: str = PRODUCTION, prior=None, integrity: bool = False):
    """The LocatorConfig of a locator of LOCATORS, started from ``prior`` (mean, cov) if given;
    ``integrity``: with the integrity monitor per UAV link (ground_station.beacon.INTEGRITY)."""
    from ground_station import beacon as bl
    LocatorConfig = bl.LocatorConfig
    kw = dict(LOCATORS[name])
    if integrity:
        kw["integrity"] = bl.INTEGRITY
    if prior is not None:
        # the beacon starts among the UAVs: ranges comparable with the prior's sigma for the
        # first ~20 s, where one linearisation is poor -> iterated EKF updates
        kw.update(init="prior", prior_mean=tuple(prior[0]), prior_cov=tuple(map(tuple, prior[1])),
                  update_iterations=PRIOR_UPDATE_ITERATIONS, second_order_r=True)
    return LocatorConfig(**kw)


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
        self.truth = np.full((K, T, 6), np.nan)  # per trial (a shared beacon's truth fills every row)
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
            k = self.row.get(key.split("/", 1)[0])
            x = np.concatenate([msg.pos_ecef_m, msg.vel_ecef_m_s])
            if k is None:
                self.truth[self.t_index] = x
            else:
                self.truth[self.t_index, k] = x
        else:
            self.uav_truth_msgs += 1


def run_case(case, tracks, trials, seed, locators=(PRODUCTION,), progress=None, central=True,
             timing=None, prior=None, integrity: str = "off", faults: dict | None = None,
             bus_faults=None, fault_seed: int | None = None) -> dict:
    """One case through the bus (module docstring).  Returns the raw series and counters.

    bus_faults: network faults on the MEASUREMENT links only, the UAVs' beacon
    measurements (keys MEASUREMENT_KEYS), never the truth or the estimates the ground station
    publishes: a list of FaultFilters (``sitl.netfault.KeyFaults``, ``LinkFault``) and/or
    KeyFaults rules ``(key_expr, spec)`` seeded with ``fault_seed`` (default: from ``seed``);
    times in the specs are seconds since the first epoch (``partition=150-180``).  Default none:
    no fault layer, the run it always was.  The estimates are scored as published at each epoch
    (real time); ``out["bus_faults"]`` holds the injected truth (summed over the links).

    integrity "on": the production locator runs the integrity monitor per UAV link and the UAVs'
    onboard filters theirs per satellite (vehicles.uav_nav.RECOMMENDED_INTEGRITY), their events
    on the bus (``integrity_events``: (t since start, source, channel, event, statistic)).
    faults (world side, sitl.measfault, the same in every trial; see FAULT_DEFAULTS): a range
    step on one UAV's beacon link and a pseudorange step on one satellite of one UAV."""
    from ground_station.beacon import BeaconLocator
    from sitl.bus import BeaconMeasurement, InMemoryTransport, Truth, UavNav, key_for
    from sitl.radio import beacon_link
    from vehicles import uav_nav

    t, U, V, B, VB = tracks
    K, N = U.shape[:2]
    T = int(trials)
    per_trial = B.ndim == 3  # one beacon per trial (its own start)
    if per_trial and B.shape[1] != T:
        raise ValueError(f"tracks hold {B.shape[1]} beacons, trials = {T}")
    tm = timing if timing is not None else {}

    def clock(name, t0):
        tm[name] = tm.get(name, 0.0) + time.perf_counter() - t0

    if integrity not in ("off", "on"):
        raise ValueError(f"integrity must be off or on, got {integrity!r}")
    fl = {**FAULT_DEFAULTS, **(faults or {})}
    t0 = time.perf_counter()
    const = constellation_for(case, U[0, 0], t[-1])
    nav_cfg = uav_nav.NavConfig()
    mon = integrity == "on"
    nav_cfg_run = nav_cfg
    if mon:
        # RECOMMENDED_INTEGRITY's min_channels (3): with three satellites in view the UAVs' monitors only
        # detect (an excluded satellite would be a lost fix: isolating on the printed run took the locator's
        # RMSE from 24 to 172 m fault-free, 6 trials, 300 s), per UAV and epoch
        nav_cfg_run = uav_nav.NavConfig(integrity=uav_nav.RECOMMENDED_INTEGRITY)
    link_cfg = beacon_link.BeaconLinkConfig()
    t_gps = uav_nav.EXAMPLE_T0_GPS_S + t
    clock("setup", t0)
    rng = np.random.default_rng([seed, CASES.index(case) if case in CASES else 7, N])
    base = f"beacon-{case[:5]}-n{N}-s{seed}"
    run_ids = [f"{base}-t{k:03d}" for k in range(T)]
    fault_list, mfaults = measurement_faults(
        bus_faults, MEASUREMENT_KEYS, seed=(seed * 1009 + 8) if fault_seed is None else fault_seed,
        t0_gps_s=float(t_gps[0]))
    bus = InMemoryTransport(start_t_gps_s=float(t_gps[0]), faults=fault_list)
    locs = {}
    pub = locators[0]  # publishes on the bus, scored from there; the others from their states
    for name in locators:
        cfg = locator_config(name, prior, integrity=mon and name == locators[0])
        locs[name] = BeaconLocator(bus, run_ids=run_ids, beacon_id=BEACON_ID, config=cfg,
                                   source_id="gs" if name == pub else f"gs-{name.replace('_', '-')}",
                                   publish_estimates=name == pub)
    scorer = _Scorer(bus, run_ids, K)
    src = [f"uav{i + 1}" for i in range(N)]
    events = []
    if mon:
        from sitl.integrity_events import IntegrityEventPublisher

        trial_of = {r: j for j, r in enumerate(run_ids)}
        bus.subscribe("*/gs/integrity/*", lambda key, m: events.append(
            (trial_of.get(key.split("/", 1)[0], -1), m.t_gps_s - float(t_gps[0]), m.source_id, m.channel, m.event,
             m.statistic)))
        nav = uav_nav.OnboardNav(const, nav_cfg_run, events=IntegrityEventPublisher(
            lambda b: run_ids[b[0]], lambda b: f"{src[b[-1]]}.integrity", bus))
    else:
        nav = uav_nav.OnboardNav(const, nav_cfg)
    from sitl.measfault import Fault, FaultInjector

    ru = int(fl["range_step_uav"]) - 1
    pu = int(fl["pr_step_uav"]) - 1
    if not (0 <= ru < N and 0 <= pu < N):
        raise ValueError(f"range_step_uav / pr_step_uav must lie in 1..{N}")
    range_inj = FaultInjector([Fault("step", ru, float(fl["fault_at_s"]), magnitude=float(fl["range_step_m"]))],
                              (T,), N) if fl["range_step_m"] else None
    pr_inj, pr_sat = None, None  # built at the fault's start: a satellite the UAV tracks then
    side = {name: np.full((K, T, 6), np.nan) for name in locators if name != pub}
    side_P = {name: np.full((K, T, 6, 6), np.nan) for name in locators if name != pub}
    nav_x = np.empty((K, T, N, 6))
    nav_P = np.empty((K, T, N, 6, 6))
    epochs, links = [], []
    uav_keys = [[key_for(r, UavNav, uav=i + 1) for i in range(N)] for r in run_ids]
    bm_keys = [[key_for(r, BeaconMeasurement, uav=i + 1, beacon=BEACON_ID) for i in range(N)] for r in run_ids]
    truth_base = base
    truth_b_key = key_for(truth_base, Truth, kind="beacon", id=BEACON_ID)
    truth_b_keys = [key_for(r, Truth, kind="beacon", id=BEACON_ID) for r in run_ids]
    truth_u_keys = [key_for(truth_base, Truth, kind="uav", id=i + 1) for i in range(N)]
    world = world_epochs(tracks, const, T, rng, nav_cfg, link_cfg, clock=clock)
    nonpositive = 0
    for k in range(K):
        tk = float(t_gps[k])
        ep, meas, sat = next(world)
        # measurement faults (world side; step faults draw nothing: the world's draws are unchanged)
        if fl["pr_step_m"] and t[k] >= fl["fault_at_s"] - 1e-9:
            if pr_inj is None:
                tracked = np.flatnonzero(ep.tracked[0, pu])
                pr_sat = int(tracked[0]) if tracked.size else 0
                pr_inj = FaultInjector([Fault("step", pr_sat, float(fl["fault_at_s"]),
                                              magnitude=float(fl["pr_step_m"]))], (T,), ep.pseudorange_m.shape[-1])
            pr = ep.pseudorange_m.copy()
            pr[:, pu], _ = pr_inj.step(None, float(t[k]), pr[:, pu])
            ep = ep._replace(pseudorange_m=pr)
        if range_inj is not None:
            meas = meas._replace(range_m=range_inj.step(None, float(t[k]), meas.range_m)[0])
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
        # a beacon among the UAVs (printed geometry): range + noise may come out <= 0, which no
        # receiver reports -- that UAV sends no beacon measurement this epoch (counted)
        valid = (meas.range_m > 0).tolist()
        vr_l, vv_l = meas.var_range_m2.tolist(), meas.var_range_rate_m2_s2.tolist()
        for j in range(T):
            for i in range(N):
                x, C = est.x[j, i], sym[j, i]
                bus.publish(uav_keys[j][i], UavNav(t_gps_s=tk, source_id=src[i], seq=k, pos_ecef_m=x[0:3],
                                                   vel_ecef_m_s=x[3:6], cov=C, n_sats=ntr[j][i], fix_type=3))
                if not valid[j][i]:
                    nonpositive += 1
                    continue
                bus.publish(bm_keys[j][i], BeaconMeasurement(
                    t_gps_s=tk, source_id=src[i], seq=k, range_m=r_l[j][i], range_rate_m_s=rr_l[j][i],
                    var_range_m2=vr_l[j][i], var_range_rate_m2_s2=vv_l[j][i], uav_pos_ecef_m=x[0:3],
                    uav_vel_ecef_m_s=x[3:6], uav_cov=C))
        if per_trial:
            for j in range(T):
                bus.publish(truth_b_keys[j], Truth(t_gps_s=tk, source_id="truth", seq=k, kind="beacon",
                                                   pos_ecef_m=B[k, j], vel_ecef_m_s=VB[k, j]))
        else:
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
            if name != pub:
                side[name][k], side_P[name][k] = loc.state_ecef()
                side[name][k][~loc.initialised] = np.nan
        t0 = time.perf_counter()
        bus.drain(tk)
        clock("bus_drain", t0)
        if progress and (k % 200 == 0 or k == K - 1):
            progress(f"[{case} N={N}]", done=t[k] - t[0], total=t[-1] - t[0])
    est_x, est_P = scorer.x, scorer.P
    out = {"t": t, "truth": scorer.truth, "nav_x": nav_x, "nav_P": nav_P, "x": {pub: est_x},
           "P": {pub: est_P}, "mode": scorer.mode, "counters": {}, "bus": _bus_stats(bus),
           "integrity_events": events, "bus_faults": None if mfaults is None else mfaults.totals(),
           "faults": {**fl, "pr_step_sat": None if pr_sat is None else
                                                   str(np.asarray(const.sat_id)[pr_sat])}}
    for name in side:
        out["x"][name], out["P"][name] = side[name], side_P[name]
    for name, loc in locs.items():
        out["counters"][name] = {**dict(loc.counters), **{f"rejected_{r}": c for r, c in loc.rejected.items()},
                                 "links_nonpositive_not_sent": nonpositive}
    loc = locs.get(pub)
    if central and loc is not None:
        t0 = time.perf_counter()
        start = None
        if loc.config.init == "prior":  # from the locator's estimate at CENTRAL_START_PRIOR_S (module doc)
            kc = int(np.searchsorted(t, CENTRAL_START_PRIOR_S))
            if kc < K and np.all(np.isfinite(est_x[kc])):
                start = (kc, est_x[kc], est_P[kc])
        out["central"] = _central(loc, const, nav_cfg, t_gps, epochs, links, nav_x, nav_P, start)
        clock("central_filter", t0)
    out["constellation"] = const
    return out


def _bus_stats(bus) -> dict:
    s = bus.stats
    return {"published": s.published, "published_bytes": s.published_bytes, "delivered": s.total.delivered,
            "rejected": dict(s.total.rejected), "callback_errors": s.total.callback_errors}


def _central(loc, const, nav_cfg, t_gps, epochs, links, nav_x, nav_P, start=None):
    """Replay the centralised filter on the same data from the locator's start (module doc),
    or from ``start`` = (epoch index, ECEF x (T, 6), P (T, 6, 6)): the locator's estimate then."""
    from ground_station.beacon import CentralFilter, LinkEpoch
    from vehicles import uav_nav

    K, T, N = nav_x.shape[:3]
    if not loc.initialised.all() or len(set(loc.init_t_gps_s.tolist())) != 1:
        return None
    # every trial initialised at the same epoch (no losses); with a prior that is epoch 0 and
    # the central filter, started from the prior there, takes its links from epoch 1 on
    k0 = int(np.flatnonzero(np.isclose(t_gps, loc.init_t_gps_s[0]))[0])
    y0, P0, fr0 = [], [], []
    chosen = loc.start_side
    if start is not None:
        k0 = int(start[0])
    for j, fix in enumerate(loc.init_info):
        x, P = (fix.mirror_x, fix.mirror_P) if chosen[j] else (fix.x, fix.P)
        if start is not None:
            x, P = start[1][j], start[2][j]
        ob = loc.init_window_last[j]
        y, Py, fr = loc.to_state(x, P, ob)
        y0.append(y)
        P0.append(Py)
        fr0.append(fr)
    from ground_station.beacon import Frame

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
        cf.step(t_gps[k], gnss, LinkEpoch(m.range_m, m.range_rate_m_s, m.var_range_m2, m.var_range_rate_m2_s2,
                                          m.range_m > 0))
        xs[k], Ps[k] = cf.beacon_ecef()
    return {"x": xs, "P": Ps}
