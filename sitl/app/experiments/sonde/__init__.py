"""`skyfuse experiment sonde`: seed 004, radiosonde position from relayed GNSS fused with an
aerological radar, against each source alone, in batch mode over the in-memory bus.

The world (vehicles.sonde.SondeFlight, sitl.radio.radar.Radar, sitl.radio.relay.Relay)
publishes, per sonde and epoch, a `Truth`, a `SondeRelay` (empty during a GNSS outage or
out of range) and a `RadarMeasurement` (when the radar has a valid range) through an
`InMemoryTransport`; three `ground_station.sonde.SondeTracker`s (fused,
radar_only, relay_only) subscribe, and by default two more with the naive white radar-noise
treatment (fused_white, radar_only_white) for the consistency comparison. Each epoch:
publish, ``drain(t)``, ``tracker.step(t)`` (which publishes the Estimates), ``drain(t)``.
A scorer subscribed to truth/** and gs/estimate/** gathers the errors; nothing else reads
the truth.

Scenario (`SondeScenario`): a 2 h flight at 1 Hz from the default aerological station; the
GCPP (radar and relay ground receiver G) 300 m from the launch pad at a bearing of 140 deg,
i.e. across the surface wind (from 230 deg), so the launch happens in a strong side wind
for the radar's antenna; the default winter jet-stream profile scaled by 1.15 (67 m/s at
11 km) so that every sonde reaches 250 km ground range inside the 2 h (checked and
reported); angular auto-tracking lost from 30 s to 330 s after launch (a 5 min loss in
the side wind at launch: range only meanwhile); a 120 s GNSS outage (the relay delivers
nothing) from 3600 s. Monte Carlo trials draw everything independently (one SeedSequence
child per trial, split into flight, radar and relay streams), so a trial's numbers do not
depend on which other trials run beside it.

Trackers: the tracker's model is the world models' parameters (not their states): the sonde
model's kinematics (``kinematics="relaxed"``: the velocity relaxes with p1, k_v vertically, to a
wind the tracker estimates, driven by the gust a_g of eq 20 with rate p1 + p2 and std sigma_a; the
wind changing at the shear x the vertical speed, the shear Gauss-Markov in height with the std and
correlation height of ``wind_shear_statistics``, the wind profile between launch and burst), or ``kinematics="singer"`` (eq 20 as printed, the model
before the relaxed model: Singer with the rate p1 + p2 and the stationary acceleration std of the sonde
model, sigma_a sqrt((p1 + p2) / (2 p1 + p2))), the relay's oscillator, the radar's AR(1) errors. ``filter="auto"``: the EKF, and the UKF for a sonde-epoch whose position
uncertainty is large against its distance to the radar (the radar-only track's range-only
coast after launch).

Scoring (scoring-side truth: the Truth messages, the flight's ground range and the slant
range from the GCPP), over the epochs inside the operating radius (ground range < 250 km and
slant range <= 250 km: beyond, neither source measures and every mode coasts alike):
  * ``by_range_km``: 3-D position RMSE per mode in 25 km ground-range bins up to 250 km,
    pooled over trials, over the epochs where every mode has an estimate; with the same-data
    comparison of fused and relay-only (RMSE gain, per-trial MSE difference and its standard
    error over the trials);
  * ``during_radar_loss``, ``during_gnss_outage``: RMSE per mode inside the episodes;
  * ``anees``: NEES of the published [pos, vel] estimate and covariance (6 dof) averaged over
    the trials at each epoch while every trial is inside, against the two-sided 99 %
    chi-square band of one epoch's average (chi2(6 N)/N); reported as the time mean, the
    fraction of epochs inside the band and the per-epoch band; ``consistent`` = the time
    mean inside the band;
  * ``continuity``: the fused track has an estimate at every epoch of every trial (from its
    first one), and its largest gap;
  * ``seed_study`` (``--seeds N``): trial 0 of N seeds (each the flight of ``--seed S --trials 1``),
    fused / relay-only / radar-only RMSE per seed overall and in each episode, against the live-robustness
    targets (fused below relay-only in >= 95 % of the seeds and never above 1.5x it; in each outage
    no worse on average than the source left); ``acquire_s`` starts the trackers in flight (the
    suite's short variant picks the sonde up 300 s before the GNSS outage);
  * ``wall_s`` and where it went (world, publishing, bus delivery, trackers -- which include
    building and publishing their Estimates).

The package: ``scenario`` (SondeScenario, the trackers' names), ``simulation`` (the world of a
batch of trials), ``scoring``, ``report`` (result.json, figures, table), ``study`` (the seed
study), ``cli`` (the options and the command); here, the batch run over the bus (the trackers'
model and ``run_trials``) and every public name of the experiment.
"""
from __future__ import annotations

import math
import time

import numpy as np

from sitl.app.experiments.common import measurement_faults
from sitl.app.experiments.sonde.cli import (FIRST_SEED, SEED, SondeOptions, _scn, add_args, main,  # noqa: F401
                                            scenario_from_args)
from sitl.app.experiments.sonde.report import (_paired_text, _shade, bus_costs, plot, result_document,  # noqa: F401
                                               summary_table)
from sitl.app.experiments.sonde.scenario import (COLORS, FIGURES, INTEGRITY, LABELS, MEASUREMENT_KEYS,  # noqa: F401
                                                 MODES, MONITORED, RADAR_ID, RUN_ID, SONDE_INTEGRITY, WHITE_MODES,
                                                 SondeScenario, _POSITIVE, _relayed_satellite, _window,
                                                 integrity_config)
from sitl.app.experiments.sonde.scoring import _paired, _rmse, integrity_summary, score  # noqa: F401
from sitl.app.experiments.sonde.simulation import (_sonde_params, _streams, _trial_streams, gcpp_site,  # noqa: F401
                                                   wind_shear_statistics, world)
from sitl.app.experiments.sonde.study import (STUDY_FIGURE, STUDY_MAX_RATIO_TO_RELAY,  # noqa: F401
                                              STUDY_MIN_FRACTION_BELOW_RELAY, plot_seed_study, seed_study,
                                              seed_study_table)


# ------------------------------------------------------------------ the batch run over the bus
# (here, in the package's own namespace: run_trials builds its trackers with this module's
# tracker_params, which a caller may replace, e.g. a test's monkeypatch of sonde.tracker_params)


def tracker_params(scn: SondeScenario, label: str, backend=None):
    """The trackers' model: the world models' parameters (not their states)."""
    from ground_station.sonde import SondeTrackerParams
    from sitl.radio.radar import RadarParams
    from sitl.radio.relay import RelayParams

    sp, rp, gp = _sonde_params(scn), RadarParams(), RelayParams()
    monitored = label.endswith(MONITORED) or scn.integrity == "on"
    white = label.removesuffix(MONITORED).endswith("_white")
    beta = sp.p1_1_s + sp.p2_1_s
    g_h, g_len, g_v = wind_shear_statistics(sp)
    if scn.kinematics == "relaxed":  # the sonde model's own structure: its gust a_g, relaxation rates p1 and k_v
        s_h, s_v = sp.sigma_a_m_s2, sp.sigma_a_vertical_m_s2
    else:
        # the acceleration of the sonde model, a = (s / (s + p1)) a_g (the gust a_g seen through the
        # sonde's response p1; k_v vertically), has the stationary variance sigma_a^2 beta / (beta + p1):
        # the Singer model's sigma_a (eq 20 with the rate p1 + p2)
        s_h = sp.sigma_a_m_s2 * math.sqrt(beta / (beta + sp.p1_1_s))
        s_v = sp.sigma_a_vertical_m_s2 * math.sqrt(beta / (beta + sp.vertical_relax_rate_1_s))
    return SondeTrackerParams(
        mode=label.removesuffix(MONITORED).removesuffix("_white"), radar_noise="white" if white else "colored", filter=scn.filter_for(label),
        kinematics=scn.kinematics, velocity_relax_rate_horizontal_1_s=sp.p1_1_s,
        velocity_relax_rate_vertical_1_s=sp.vertical_relax_rate_1_s, wind_shear_sigma_horizontal_1_s=g_h,
        wind_shear_sigma_vertical_1_s=g_v, wind_shear_corr_height_m=g_len, descent_rate_sl_m_s=sp.descent_rate_sl_m_s,
        burst_alt_range_m=tuple(sp.burst_alt_range_m),
        accel_rate_1_s=beta, sigma_acc_horizontal_m_s2=s_h, sigma_acc_vertical_m_s2=s_v, osc_gamma_1_s=gp.osc_gamma_1_s,
        osc_sigma_m_s=2.0 * math.pi * gp.osc_sigma_hz * gp.osc_doppler_scale_m_s_per_rad_s,
        radar_sigma=tuple(rp.sigma), radar_gamma_1_s=tuple(rp.gamma_1_s), label=label,
        backend=None if backend in (None, "auto") else backend, integrity=integrity_config() if monitored else None)


class _Scorer:
    """Collects Truth and Estimate messages from the bus into arrays (trial, epoch)."""

    def __init__(self, modes, n_trials: int, n_epochs: int, t0: float, dt: float, sonde_index: dict):
        self.modes = {m: i for i, m in enumerate(modes)}
        self.t0, self.dt, self.index = t0, dt, sonde_index
        M, B, T = len(modes), n_trials, n_epochs
        self.truth_pos = np.full((B, T, 3), np.nan)
        self.truth_vel = np.full((B, T, 3), np.nan)
        self.pos = np.full((M, B, T, 3), np.nan)
        self.vel = np.full((M, B, T, 3), np.nan)
        self.cov = np.full((M, B, T, 6, 6), np.nan)
        self.count = np.zeros((M, B, T), dtype=np.int32)
        self.unexpected = 0
        self.k_now = None  # the epoch being stepped: an Estimate is scored there, as published (real time)

    def _k(self, t):
        return round((t - self.t0) / self.dt)

    def on_truth(self, key, msg):
        b = self.index.get(key.rsplit("/", 1)[-1])
        if b is None:
            self.unexpected += 1
            return
        k = self._k(msg.t_gps_s)
        self.truth_pos[b, k], self.truth_vel[b, k] = msg.pos_ecef_m, msg.vel_ecef_m_s

    def on_estimate(self, key, msg):
        b = self.index.get(key.rsplit("/", 1)[-1])
        m = self.modes.get(msg.mode)
        if b is None or m is None:
            self.unexpected += 1
            return
        k = self._k(msg.t_gps_s) if self.k_now is None else self.k_now
        self.pos[m, b, k], self.vel[m, b, k], self.cov[m, b, k] = msg.pos_ecef_m, msg.vel_ecef_m_s, msg.cov
        self.count[m, b, k] += 1


def run_trials(scn: SondeScenario, seed: int, trials, *, backend=None, progress=None, chunk: int = 300,
               modes=None, bus_faults=None, fault_seed: int | None = None, seeds=None) -> dict:
    """Simulate and track the given trial indices as one batch over the in-memory bus.

    modes: the trackers to run (default ``scn.modes``; a subset for timing -- ``score`` needs
    the three main ones). Returns the raw arrays (truth, estimates per mode, ground range,
    times) and timings.

    bus_faults: network faults on the MEASUREMENT links only (MEASUREMENT_KEYS: the
    relayed GNSS and the radar measurements), never the truth or the trackers' estimates: a
    list of FaultFilters (``sitl.netfault.KeyFaults``, ``LinkFault``) and/or KeyFaults rules
    ``(key_expr, spec)`` seeded with ``fault_seed`` (default: from ``seed``); times in the specs
    are seconds since launch.  Default none: no fault layer, the run it always was.  Estimates
    are scored at the epoch they are published (real time); ``out["bus_faults"]`` holds the
    injected truth summed over the links.

    seeds: one seed per trial (trial ``trials[b]`` of seed ``seeds[b]``, e.g. trial 0 of many seeds
    in one batch: the seed study); the sondes are then named by their place in the batch.
    """
    # the world and the ground station are imported here, not at module import: sitl must
    # not import vehicles or ground_station when it is itself imported
    from ground_station.sonde import SondeTracker
    from sitl.bus import InMemoryTransport, RadarMeasurement, SondeRelay, Truth
    from sitl.geodesy import geodetic_to_ecef

    trials = list(trials)
    B, T = len(trials), scn.n_epochs
    timing = dict.fromkeys(("world", "publish", "deliver", "trackers", "estimates_delivery"), 0.0)
    wall0 = time.perf_counter()
    w0 = time.perf_counter()
    t0, lat, lon, h, track, radar, relay = world(scn, seed, trials, backend=backend, seeds=seeds)
    timing["world"] += time.perf_counter() - w0

    fault_list, mfaults = measurement_faults(
        bus_faults, MEASUREMENT_KEYS, seed=(seed * 1009 + 8) if fault_seed is None else fault_seed, t0_gps_s=t0)
    bus = InMemoryTransport(start_t_gps_s=t0, faults=fault_list)
    ids = [f"s{i:04d}" for i in (trials if seeds is None else range(B))]
    index = {s: b for b, s in enumerate(ids)}
    modes = scn.modes if modes is None else tuple(modes)
    scorer = _Scorer(modes, B, T, t0, scn.dt_s, index)
    bus.subscribe(f"{RUN_ID}/truth/sonde/*", scorer.on_truth)
    bus.subscribe(f"{RUN_ID}/gs/estimate/sonde/*", scorer.on_estimate)
    events = []  # the integrity events on the bus: (t since launch, source, channel, event, statistic)
    bus.subscribe(f"{RUN_ID}/gs/integrity/*", lambda key, m: events.append(
        (m.t_gps_s - t0, m.source_id, m.channel, m.event, m.statistic)))
    # measurement faults (world side), one seeded stream for the batch
    from sitl.measfault import Fault, FaultInjector
    from sitl.radio.radar import RadarParams

    frng = np.random.default_rng(np.random.SeedSequence([seed, 3003]))
    az_faults = []
    if scn.az_outlier_prob:
        az_faults.append(Fault("outlier", 0, *scn.az_outlier_s, prob=scn.az_outlier_prob,
                               scale=scn.az_outlier_sigmas * RadarParams().sigma_az_rad, dof=2.0))
    if scn.az_step_rad:
        az_faults.append(Fault("step", 0, *scn.az_step_s, magnitude=scn.az_step_rad))
    az_inj = FaultInjector(az_faults, (B,), 1) if az_faults else None
    relay_inj, step_sat = None, None
    trackers = []
    for m in modes:
        tr = SondeTracker(RUN_ID, tracker_params(scn, m, backend), radar_id=RADAR_ID)
        tr.attach(bus)
        trackers.append(tr)
    k_relay = [f"{RUN_ID}/sonde/{s}/relay" for s in ids]
    k_radar = [f"{RUN_ID}/radar/{RADAR_ID}/sonde/{s}" for s in ids]
    k_truth = [f"{RUN_ID}/truth/sonde/{s}" for s in ids]
    seq = {"world": 0, "gcpp": 0, RADAR_ID: 0}
    examples = {"truth": None, "relay": None, "radar": None, "estimate": None}
    n_msgs = {"truth": 0, "relay": 0, "radar": 0}
    last_report = 0
    for c0 in range(0, T, chunk):
        c1 = min(T, c0 + chunk)
        w0 = time.perf_counter()
        rt = relay.track(track.t_gps_s[c0:c1], track.pos_ecef_m[c0:c1], track.vel_ecef_m_s[c0:c1])
        rmt = radar.track(track.t_gps_s[c0:c1], track.pos_ecef_m[c0:c1], track.vel_ecef_m_s[c0:c1])
        timing["world"] += time.perf_counter() - w0
        sat_id = rt.sat_id
        for j, k in enumerate(range(c0, c1)):
            t = float(track.t_gps_s[k])
            w0 = time.perf_counter()
            rv, rd, raz, rel, ra = (rmt.range_valid[j], rmt.slant_range_m[j], rmt.az_rad[j], rmt.el_rad[j],
                                    rmt.angles_valid[j])
            pr_all = rt.pseudorange_m[j]
            if scn.relay_step_m and relay_inj is None and t - t0 >= scn.relay_step_s[0]:
                ids = [str(v) for v in sat_id]
                if scn.relay_step_sat:
                    if scn.relay_step_sat not in ids:
                        raise ValueError(f"relay_step_sat: no satellite {scn.relay_step_sat!r} in the constellation")
                    step_sat = scn.relay_step_sat
                else:
                    seen = np.flatnonzero(rt.delivered[j, 0])
                    step_sat = ids[int(seen[0])] if seen.size else ids[0]
                relay_inj = FaultInjector([Fault("step", ids.index(step_sat), *scn.relay_step_s,
                                                 magnitude=scn.relay_step_m)], (B,), len(ids))
            if relay_inj is not None:
                pr_all, _ = relay_inj.step(frng, t - t0, pr_all)
            if az_inj is not None:
                az_f = az_inj.step(frng, t - t0, raz[:, None])[0][:, 0]
                raz = np.where(np.isfinite(az_f), np.mod(az_f, 2.0 * math.pi), az_f)
            vr, va, ve = rmt.var_range_m2[j], rmt.var_az_rad2[j], rmt.var_el_rad2[j]
            for b in range(B):
                msg = Truth(t_gps_s=t, source_id="world", seq=seq["world"], kind="sonde",
                            pos_ecef_m=track.pos_ecef_m[k, b], vel_ecef_m_s=track.vel_ecef_m_s[k, b])
                seq["world"] += 1
                bus.publish(k_truth[b], msg)
                examples["truth"] = msg
                n_msgs["truth"] += 1
                if t - t0 < scn.acquire_s:  # the measurement links are not up yet
                    continue
                d = rt.delivered[j, b]
                msg = SondeRelay(t_gps_s=t, source_id="gcpp", seq=seq["gcpp"], sat_ids=sat_id[d],
                                 pseudorange_m=pr_all[b][d], pseudo_doppler_m_s=rt.pseudo_doppler_m_s[j, b][d],
                                 var_pseudorange_m2=rt.var_pr_m2[j, b][d], var_pseudo_doppler_m2_s2=rt.var_prr_m2_s2[j, b][d],
                                 sat_pos_ecef_m=rt.sat_pos_ecef_m[j, b][d], sat_vel_ecef_m_s=rt.sat_vel_ecef_m_s[j, b][d],
                                 ground_pos_ecef_m=rt.ground_pos_ecef_m)
                seq["gcpp"] += 1
                bus.publish(k_relay[b], msg)
                if msg.n:
                    examples["relay"] = msg
                n_msgs["relay"] += 1
                if rv[b]:
                    msg = RadarMeasurement(t_gps_s=t, source_id=RADAR_ID, seq=seq[RADAR_ID],
                                           slant_range_m=float(rd[b]), az_rad=float(raz[b]), el_rad=float(rel[b]),
                                           var_range_m2=float(vr[b]), var_az_rad2=float(va[b]), var_el_rad2=float(ve[b]),
                                           angles_valid=bool(ra[b]), radar_pos_ecef_m=rmt.site_pos_ecef_m)
                    seq[RADAR_ID] += 1
                    bus.publish(k_radar[b], msg)
                    examples["radar"] = msg
                    n_msgs["radar"] += 1
            w1 = time.perf_counter()
            scorer.k_now = k
            bus.drain(t)
            w2 = time.perf_counter()
            for tr in trackers:
                est = tr.step(t)
            if est:
                examples["estimate"] = est[-1]
            w3 = time.perf_counter()
            bus.drain(t)
            w4 = time.perf_counter()
            timing["publish"] += w1 - w0
            timing["deliver"] += w2 - w1
            timing["trackers"] += w3 - w2
            timing["estimates_delivery"] += w4 - w3
        if progress and (c1 == T or c1 - last_report >= T // 10):
            last_report = c1
            progress(f"[sonde] {B} trial(s), {time.perf_counter() - wall0:6.1f} s wall", done=c1 - 1, total=T - 1)
    bus.close()
    return {
        "trials": trials, "t_gps_s": track.t_gps_s.copy(), "t0_gps_s": t0, "modes": modes,
        "ground_range_m": track.ground_range_m.T.copy(),  # (B, T), scoring-side truth
        "slant_range_m": np.linalg.norm(track.pos_ecef_m - geodetic_to_ecef(lat, lon, h), axis=-1).T.copy(),
        "alt_m": track.alt_m.T.copy(), "phase": track.phase.T.copy(), "burst_alt_m": track.burst_alt_m.copy(),
        "truth_pos": scorer.truth_pos, "truth_vel": scorer.truth_vel,
        "pos": scorer.pos, "vel": scorer.vel, "cov": scorer.cov, "count": scorer.count,
        "counters": {tr.label: tr.counters.as_dict() for tr in trackers},
        "bus": {"published": bus.stats.published, "delivered": bus.stats.total.delivered,
                "rejected": dict(bus.stats.total.rejected), "callback_errors": bus.stats.total.callback_errors,
                "messages_by_kind": {**n_msgs, "estimate": int(scorer.count.sum()), "integrity": len(events)}},
        "scorer_unexpected": scorer.unexpected,
        "integrity_events": events, "fault_relay_step_sat": step_sat,
        "bus_faults": None if mfaults is None else mfaults.totals(),
        "timing_s": timing, "wall_s": time.perf_counter() - wall0, "examples": examples,
    }


def _merge(parts: list[dict]) -> dict:
    """Concatenate run_trials outputs along the trial axis (same scenario)."""
    if len(parts) == 1:
        return parts[0]
    out = dict(parts[0])
    for k in ("ground_range_m", "slant_range_m", "alt_m", "phase", "burst_alt_m", "truth_pos", "truth_vel"):
        out[k] = np.concatenate([p[k] for p in parts], axis=0)
    for k in ("pos", "vel", "cov", "count"):
        out[k] = np.concatenate([p[k] for p in parts], axis=1)
    out["trials"] = [i for p in parts for i in p["trials"]]
    out["counters"] = {m: {c: sum(p["counters"][m][c] for p in parts) for c in parts[0]["counters"][m]}
                       for m in parts[0]["counters"]}
    bus = {"published": 0, "delivered": 0, "rejected": {}, "callback_errors": 0, "messages_by_kind": {}}
    for p in parts:
        for k in ("published", "delivered", "callback_errors"):
            bus[k] += p["bus"][k]
        for k, v in p["bus"]["rejected"].items():
            bus["rejected"][k] = bus["rejected"].get(k, 0) + v
        for k, v in p["bus"]["messages_by_kind"].items():
            bus["messages_by_kind"][k] = bus["messages_by_kind"].get(k, 0) + v
    out["bus"] = bus
    out["scorer_unexpected"] = sum(p["scorer_unexpected"] for p in parts)
    out["integrity_events"] = [e for p in parts for e in p["integrity_events"]]
    out["timing_s"] = {k: sum(p["timing_s"][k] for p in parts) for k in parts[0]["timing_s"]}
    out["wall_s"] = sum(p["wall_s"] for p in parts)
    if any(p.get("bus_faults") for p in parts):
        bf: dict = {}
        for p in parts:
            for k, v in (p.get("bus_faults") or {}).items():
                bf[k] = max(bf.get(k, 0), v) if k.endswith("_max") else bf.get(k, 0) + v
        out["bus_faults"] = bf
    return out


def run(scn: SondeScenario, trials: int, seed: int, *, backend=None, progress=None, batch: int = 10,
        pool=None) -> dict:
    """All trials, in batches of ``batch`` trials (the bus and the trackers carry a batch).
    ``pool``: a sitl.app.cluster.TrialPool -- the same batches as Dask tasks, merged in order
    (each batch computed as here: the same result)."""
    batches = [list(range(s, min(trials, s + batch))) for s in range(0, trials, batch)]
    if pool is not None:
        return _merge(pool.map(run_trials, [(scn, seed, idx) for idx in batches], kwargs={"backend": backend},
                               labels=[f"trials {i[0]}-{i[-1]}" for i in batches]))
    parts = []
    for idx in batches:
        prog = (lambda m, _i=idx, **kw: progress(f"trials {_i[0]}-{_i[-1]}: {m}", **kw)) if progress else None
        parts.append(run_trials(scn, seed, idx, backend=backend, progress=prog))
    return _merge(parts)
