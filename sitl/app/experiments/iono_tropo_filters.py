"""Seed 000, variants 1-3: zenith iono/tropo delays from a single-frequency receiver (EKF).

A single-frequency GPS+GLONASS receiver on a moving object; an EKF on the seed-000 model
(filters.iono_tropo: x = [x, y, z, Delta, vx, vy, vz, dDelta, Delta_A, I_g, U_g]) estimates,
among the rest, the zenith ionospheric delay I_g and the zenith tropospheric delay U_g.
The seed reports ~500 s of observation to reach 1 m on both (the seed 000 paper, README "The papers",
variant 1).

World (sitl, truth): one trajectory shared by all trials -- a great circle at constant
speed (default 50 m/s, heading 90 deg) on the geocentric sphere through the start point
(55 N 37 E, 1 km), so its ECEF acceleration is only v^2/r ~ 4e-4 m/s^2. Per trial,
independently: the receiver clock (ClockModel, the seed's TCXO, initial bias/drift drawn
from the prior below) and all measurement noise (Receiver). The light-time geometry
(ranging.light_time_geometry, Earth rotation during the flight) and the look angles are
computed for the shared trajectory by `world.geometry_track` (a block of epochs per call)
and fed, broadcast, to the batched Receiver -- what `world.observe` does, without
repeating the identical geometry for every trial or paying its call overhead every epoch.

Filter (no truth): each epoch it gets the tracked satellites' pseudoranges and rates and
the satellite states from `world.ephemeris_for_filter` evaluated at the *measured*
transit time with the filter's own predicted clock bias. The visible set is common to
all trials (shared trajectory), so one IonoTropoGnss is built per epoch on the tracked
satellites (equivalent to `.subset(tracked)` of the full-constellation model).

Prior (documented choice):
* position: the truth plus a draw of N(0, sigma0_pos_m^2 I) (an external coarse fix with
  that error); velocity likewise with sigma0_vel_m_s;
* clock bias / drift: the truth is drawn from N(0, sigma0_clock_*^2); the filter's prior
  mean is 0 with those sigmas (no truth needed);
* Delta_A: prior 0 +- sigma0_gps_glo_m (truth gps_glonass_offset_m = 5 m);
* I_g: prior 0 +- 20 m (truth 15 m); U_g: prior 0 +- 5 m (truth 2.5 m).
Process noise: white acceleration q_accel_m2_s3 = 0.01 m^2/s^3 (the truth barely
accelerates), the seed's clock PSD, and near-zero random walks (1e-10 m^2/s) for
Delta_A, I_g, U_g (constant in the truth).

Only per-epoch statistics over the trials are kept (streamed); memory is flat in the
run length.

Adaptive process noise (eq 7, filters/adaptive.py; off by default here, `adaptive_q`):
Q(i+1) = Q_min + decay Q(i) + gain diag((W nu)^2), W nu = x(i|i) - x(i|i-1), on every state
(`adaptive_q_scope="all"`, the seed) or on position, velocity and clock only ("dynamic").
The K_j entries follow their states (dropped on a set, zero on a rise or a reset). The
truth clock can be made noisier than the filter's model (`truth_clock_psd_scale`) to show
what eq 7 is for; the clock block's NEES is scored beside the (I_g, U_g) block's.

Variant 2 (run_cmc_increments = run_streamed(variant=2); same world, same draws, so the
same seed gives the same data as variant 1): additionally, per satellite j and window,
E_j = B_j(t) - B_j(t - W), B_j = pr_j - phase_j (= 2 I_j - lambda N_j + noise), W =
cmc_window_s (90 s), modelled (eq 33) as 2 I_g k_j [m_I(eta_j(t)) - m_I(eta_j(t - W))],
k_j = (f_ref/f_j)^2, H only in the I_g column. The m_I values are the filter's: geocentric
elevation (eq 10) from its predicted position and the ephemeris_for_filter satellites,
kept per satellite in a ring buffer of W epochs with B_j. Used only where the cycle-slip
detector (filters.cycleslip, fed the receiver's phase and Doppler only -- not its
lock_count, which the simulator resets at the slips it generates) reports the carrier arc
slip-free over the whole window.
The code noise of E_j is the same noise as that of pr_j(t) and pr_j(t - W); its two treatments
(`cmc_noise`: "states", exact, the default; "whitened", close to the seed) are
sitl.app.experiments.iono_tropo_models' (its docstring: the noise bookkeeping).

Variant 3 (run_carrier_phase = run_streamed(variant=3); same world and draws again): the
ambiguous carrier phase in metres (eqs 35-37, sigma_phase_m) of every tracked satellite is
a third measurement row, and one constant K_j per tracked satellite is appended to the
state (eq 38), x = [11 base states, K_j for the satellites in `amb_sats` order]. The
tracked set is common to the trials, so the state dimension is too; it changes with time:
* a satellite that rises gets a new K_j appended (after the prediction), one that sets has
  its row/column removed (marginalised); the transition IonoTropoTransition(n_amb=N) is
  cached by N;
* K_j prior (documented choice): mean = phase_j - h_phase,j(x_pred) with K_j = 0, i.e. the
  phase minus the filter's predicted phase without ambiguity (its error is -H dx + e,
  a few hundred metres at most at epoch 0 with the 300 m clock prior, metres later), and a
  flat variance sigma0_amb_m^2 = (1 km)^2 with zero cross-covariances. K enters linearly,
  so the mean only matters through its weight ~sigma_phase^2/sigma0_amb^2 ~ 1e-11: the
  same-epoch phase row effectively initialises K_j, and the prior stays conservative;
* a slip flagged by the cycle-slip detector (fed time, phase and Doppler only, never the
  receiver's lock_count) resets K_j in that trial the same way (mean re-initialised, variance
  sigma0_amb_m^2, cross-covariances zeroed) before that epoch's update. A slip the detector
  misses would bias K_j (counted on the scoring side as `missed_true_slips`).
* `phase_max_sats` = N > 0 (the seed's "even with a single phase measurement"): only N
  satellites carry a K state and a phase row; free slots go to the highest satellites by the
  filter's own elevation (mean over trials), a set satellite's slot to the next one.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict

import numpy as np

from filters import metrics
from filters.adaptive import AdaptiveQ
from filters.cycleslip import CycleSlipConfig, CycleSlipDetector
from filters.ekf import ekf_predict, ekf_step, ekf_update
from filters.iono_tropo import (
    F_REF_HZ, IDX_CLOCK, IDX_DRIFT, IDX_IONO, IDX_TROPO, N_BASE, IonoTropoGnss, elevation_rad, iono_mapping,
)
from sitl.app.experiments.iono_tropo_models import (
    _append_states, _CmcIncrementModel, _CodeNoiseStateModel, _drop_states,
)
from sitl.app.experiments.iono_tropo_scenario import (  # noqa: F401  (CB, CMC_NOISE, IB: re-exported)
    ADAPTIVE_Q_SCOPES, CB, CMC_NOISE, IB, MIN_SATS, IonoTropoScenario,
)
from sitl.gnss.clock import ClockModel
from sitl.gnss.receiver import Receiver
from sitl.gnss.world import ephemeris_for_filter, geometry_track
from sitl.params import integer

__all__ = ["MIN_SATS", "IonoTropoScenario", "run_carrier_phase", "run_cmc_increments", "run_code_doppler",
           "run_streamed"]


def run_code_doppler(scn: IonoTropoScenario, trials: int, seed: int, progress=None, backend=None) -> dict:
    """Variant 1 (pseudorange + pseudorange rate): ``run_streamed(..., variant=1)``."""
    return run_streamed(scn, trials, seed, variant=1, progress=progress, backend=backend)


def run_cmc_increments(scn: IonoTropoScenario, trials: int, seed: int, progress=None, backend=None) -> dict:
    """Variant 2 (plus code-minus-carrier increments): ``run_streamed(..., variant=2)``."""
    return run_streamed(scn, trials, seed, variant=2, progress=progress, backend=backend)


def run_carrier_phase(scn: IonoTropoScenario, trials: int, seed: int, progress=None, backend=None) -> dict:
    """Variant 3 (plus ambiguous carrier phase, K_j states): ``run_streamed(..., variant=3)``."""
    return run_streamed(scn, trials, seed, variant=3, progress=progress, backend=backend)


def _nees2(e0, e1, P, i, j):
    """NEES of a 2-state block (i, j) in closed form, (N,): the scoring runs every epoch."""
    a, b, c = P[:, i, i], P[:, i, j], P[:, j, j]
    return (c * e0 * e0 - 2.0 * b * e0 * e1 + a * e1 * e1) / (a * c - b * b)


def run_streamed(scn: IonoTropoScenario, trials: int, seed: int, variant: int = 1, progress=None,
                 backend=None) -> dict:
    """Seed-000 Monte Carlo, trials stepped together; variant 1 (pseudorange + pseudorange
    rate), 2 (plus code-minus-carrier increments over scn.cmc_window_s, eqs 29-33) or 3
    (plus ambiguous carrier phase with one K_j state per tracked satellite, eqs 35-38).
    The world (receiver draws) does not depend on the variant: the same seed gives the same
    simulated data for both.

    Returns a dict (JSON-able apart from numpy arrays for the per-epoch series):
      t_s (T,), n_visible (T,), iono_err_mean_m / iono_err_rms_m / tropo_err_mean_m /
      tropo_err_rms_m / pos_err_rms_m (T,), nees_atmo_mean (T,) (mean over trials of the
      NEES of the (I_g, U_g) block), nis_mean (T,), iono_sd_m / tropo_sd_m (T,) (the
      filter's own sigma, RMS over trials);
      time_to_1m_s (median over trials; inf if the median trial never settles),
      time_to_1m_s_per_trial (trials,): first time after which |I_g err| < 1 and
      |U_g err| < 1 hold to the end of the run (inf if the last epoch is not below);
      final_error_m {iono_zenith, tropo_zenith, position}: RMS over trials and the epochs
      of the last final_window_s (the whole run if shorter); final_bias_m {iono_zenith, tropo_zenith}: mean error
      over the same window; anees: mean (I_g, U_g) NEES / 2 over that window;
      anees_bounds_99_one_epoch; wall_s.
    Variant 2 also: increments {candidates, used, rejected_slip, spanning_true_slip,
      used_spanning_true_slip, detector_slips} (counts over trials, satellites, epochs;
      see sitl.app.experiments.iono_tropo_models for the pairing rule) and n_increments_used (T,) per epoch.
    Variant 3 also: n_state (T,) (state dimension after the epoch's update = 11 + number of
      K states = 11 + n_visible), ambiguity {rises, sets, k_resets (detector slips on
      satellites with a K state, summed over trials), true_slips, missed_true_slips (true
      slips at epochs where the detector did not flag that satellite/trial; scoring side)}.
    """
    if variant not in (1, 2, 3):
        raise ValueError(f"variant must be 1, 2 or 3, got {variant!r}")
    if not isinstance(scn, IonoTropoScenario):
        raise ValueError(f"scn must be an IonoTropoScenario, got {type(scn).__name__}")  # noqa: TRY004
    trials = integer(lo=1)("trials", trials)
    t_wall = time.perf_counter()
    rng = np.random.default_rng(seed)
    const = scn.constellation()
    S = len(const)
    carrier = const.carrier_l1_hz
    is_gps = const.system == "G"
    cfg = scn.receiver_config()
    receiver = Receiver(S, cfg, (trials,))
    trans = scn.transition()
    clock = ClockModel(psd_1_s=trans.clock_psd_1_s * scn.truth_clock_psd_scale)
    dt = scn.dt_s
    T = scn.n_epochs
    t_rel = scn.times()
    pos_true, vel_true = scn.trajectory(t_rel)  # (T, 3): shared by all trials
    I_true, U_true = scn.iono_zenith_m, scn.tropo_zenith_m

    # truth clocks and the filter prior
    sd0 = scn.prior_sigmas()
    bias = sd0[IDX_CLOCK] * rng.standard_normal(trials)
    drift = sd0[IDX_DRIFT] * rng.standard_normal(trials)
    x = np.zeros((trials, N_BASE))
    x[:, 0:3] = pos_true[0] + sd0[0] * rng.standard_normal((trials, 3))
    x[:, 4:7] = vel_true[0] + sd0[4] * rng.standard_normal((trials, 3))
    x[:, IDX_IONO] = scn.iono_prior_m
    x[:, IDX_TROPO] = scn.tropo_prior_m
    P = np.broadcast_to(np.diag(sd0**2), (trials, N_BASE, N_BASE)).copy()

    keys = ("iono_err_mean_m", "iono_err_rms_m", "tropo_err_mean_m", "tropo_err_rms_m", "pos_err_rms_m",
            "nees_atmo_mean", "nis_mean", "iono_sd_m", "tropo_sd_m", "clock_err_rms_m", "drift_err_rms_m",
            "nees_clock_mean", "iono_est_trial0_m", "tropo_est_trial0_m")
    ser = {k: np.empty(T) for k in keys}
    n_vis = np.empty(T, dtype=int)
    prior_err = {"iono_rms_m": float(np.sqrt(np.mean((x[:, IDX_IONO] - I_true) ** 2))),
                 "tropo_rms_m": float(np.sqrt(np.mean((x[:, IDX_TROPO] - U_true) ** 2)))}
    last_bad = np.full(trials, -1, dtype=int)  # last epoch with |err| >= 1 m on I_g or U_g
    k_final = int(np.searchsorted(t_rel, scn.duration_s - min(scn.final_window_s, scn.duration_s) - 1e-9))
    acc = {"iono": 0.0, "tropo": 0.0, "pos": 0.0, "nees": 0.0, "nees_c": 0.0, "iono_b": 0.0, "tropo_b": 0.0, "n": 0}
    report_every = max(1, T // 10)

    # adaptive process noise (eq 7): Q(i) = s_i Q_min + diag(q_i), see filters/adaptive.py
    # variant 2's code-noise states are samples of measurement noise, not part of the seed's
    # state vector: they never adapt (a random walk on them would forget what pr_j(t - W) said)
    scope = ADAPTIVE_Q_SCOPES[scn.adaptive_q_scope]
    if scope is None and variant == 2 and scn.cmc_noise == "states":
        scope = tuple(range(N_BASE))
    aq = AdaptiveQ(scn.adaptive_q_decay, scn.adaptive_q_gain, scope) if scn.adaptive_q else None
    aqs = aq.init((trials,), N_BASE) if aq else None

    def predict(x, P, tr):
        if aq is None:
            return ekf_predict(x, P, tr, dt, backend=backend)
        xp, Pp = ekf_predict(x, P, aq.transition(tr, aqs), dt, backend=backend)
        return xp, aq.add_diag(Pp, aqs)

    if variant in (2, 3):
        # the detector sees only the receiver's phase and Doppler (no lock_count: the
        # simulated receiver resets it at the slips it generates, which is truth)
        detector = CycleSlipDetector((trials, S), CycleSlipConfig(sigma_prr_m_s=scn.sigma_prr_m_s,
                                                                  sigma_phase_m=scn.sigma_phase_m))
    cmc_states = False
    if variant == 3:
        amb_sats = []  # satellite (constellation index) of K state N_BASE + i
        trans_cache = {0: trans}
        n_state = np.empty(T, dtype=int)
        amb = {"rises": 0, "sets": 0, "k_resets": 0, "true_slips": 0, "missed_true_slips": 0}
        slips_prev = receiver.slip_count.copy()
        var_amb = scn.sigma0_amb_m**2
    if variant == 2:
        W = scn.cmc_window_epochs
        cmc_states = scn.cmc_noise == "states"
        if not cmc_states:
            B_buf = np.full((W, trials, S), np.nan)  # ring buffers over the window (filter side)
            m_buf = np.full((W, trials, S), np.nan)
            slips_buf = np.zeros((W, trials, S), dtype=np.int64)  # scoring side only (truth)
        k_iono = (F_REF_HZ / carrier) ** 2
        # disjoint pairing: satellite j's epochs alternate between W-epoch "start" and "end"
        # blocks (staggered by satellite); at an end epoch k, E_j pairs B(k) with B(k - W),
        # which lies in a start block, so every B sample enters at most one increment
        offset = (np.arange(S) * 2 * W) // S
        var_e = scn.sigma_pr_m**2 + 2.0 * scn.sigma_phase_m**2  # after whitening against pr_j(t)
        inc = {"candidates": 0, "used": 0, "rejected_slip": 0, "spanning_true_slip": 0,
               "used_spanning_true_slip": 0, "detector_slips": 0}
        n_inc = np.zeros(T, dtype=int)
        if cmc_states:
            # x = [11 base, e states]; e_sats[i] = satellite whose window-start code noise is
            # column N_BASE + i; one window per satellite at a time, all on the same W grid
            e_sats = []
            trans_cache = {0: trans}
            e_m = np.full((trials, S), np.nan)  # filter's m_I at each window start
            e_B = np.full((trials, S), np.nan)  # B_j at each window start
            e_slips = np.zeros((trials, S), dtype=np.int64)  # scoring side only (truth)
            var_e = 2.0 * scn.sigma_phase_m**2
            inc["lost_to_set"] = 0
            n_state = np.empty(T, dtype=int)

    # the truth geometry of the shared trajectory, a block of epochs per call
    geom = geometry_track(scn.t0_gps_s + t_rel, pos_true, vel_true, const)
    sub_const = {}
    for k in range(T):
        t = scn.t0_gps_s + t_rel[k]
        # ---------------- world (truth)
        if k > 0:
            bias, drift = clock.step(rng, bias, drift, dt)
        eg = next(geom)
        geo = eg.geometry
        # mask on the geodetic horizon; atmosphere on the geocentric vertical (eq. 10)
        obs = receiver.step(rng, t, geo.range_m, geo.range_rate_m_s, eg.el_rad, carrier, is_gps, bias, drift,
                            el_atmo_rad=eg.el_atmo_rad)
        vis = obs.visible[0]
        if np.any(obs.visible != vis):  # pragma: no cover - the shared trajectory makes it common
            raise RuntimeError("visible set differs between trials")
        idx = np.flatnonzero(vis)
        n_vis[k] = idx.size
        if idx.size < MIN_SATS:
            raise ValueError(f"el_mask_deg = {scn.el_mask_deg!r}: only {idx.size} satellites in view at "
                             f"t = {t_rel[k]:.1f} s (>= {MIN_SATS} needed)")
        pr = obs.pseudorange_m
        prr = obs.pseudorange_rate_m_s
        if variant in (2, 3):
            det = detector.update(t_rel[k], obs.carrier_phase_m, prr)
        if variant == 2:
            inc["detector_slips"] += int(np.sum(det.slip))

        # ---------------- filter (measurements + ephemeris + its own clock estimate only)
        clock_est = x[:, IDX_CLOCK] + (dt * x[:, IDX_DRIFT] if k > 0 else 0.0)
        # the tracked satellites' ephemeris only (the sub-constellation is cached per tracked set)
        key = idx.tobytes()
        sub = sub_const.get(key)
        if sub is None:
            sub = sub_const[key] = const.subset(idx)
        sp_v, sv_v = ephemeris_for_filter(t, pr[:, idx], sub, pseudorange_rate_m_s=prr[:, idx],
                                          clock_bias_est_m=clock_est)
        if variant != 3:
            meas = IonoTropoGnss(sp_v, sv_v, carrier[idx], is_gps[idx], scn.sigma_pr_m,
                                 scn.sigma_prr_m_s)
        z = np.concatenate([pr[:, idx], prr[:, idx]], axis=1)
        if variant == 2:
            # filter's own mapping at this epoch: predicted position, filter-side satellites
            pos_f = x[:, 0:3] + (dt * x[:, 4:7] if k > 0 else 0.0)
            m_now = np.full((trials, S), np.nan)
            m_now[:, idx] = iono_mapping(elevation_rad(pos_f[:, None, :], sp_v))
            B_now = pr - obs.carrier_phase_m  # pr - phase = 2I - lambda N + noise
            slips_now = receiver.slip_count.copy()
        if variant == 2 and not cmc_states:
            slot = k % W
            rows = np.zeros(0, dtype=int)
            if k >= W:
                end = ((k + offset[idx]) // W) % 2 == 1
                cand = end & np.all(np.isfinite(B_buf[slot][:, idx]), axis=0)
                rows = np.flatnonzero(cand)
            if rows.size:
                sats = idx[rows]
                ok = detector.slip_free(scn.cmc_window_s)[:, sats]
                true_slip = (slips_now[:, sats] - slips_buf[slot][:, sats]) > 0
                inc["candidates"] += ok.size
                inc["used"] += int(ok.sum())
                inc["rejected_slip"] += int((~ok).sum())
                inc["spanning_true_slip"] += int(true_slip.sum())
                inc["used_spanning_true_slip"] += int((ok & true_slip).sum())
                n_inc[k] = int(ok.sum())
                E = B_now[:, sats] - B_buf[slot][:, sats]
                coef = 2.0 * k_iono[sats] * (m_now[:, sats] - m_buf[slot][:, sats])
                meas = _CmcIncrementModel(meas, rows, coef, ok, var_e)
                z = np.concatenate([z, np.where(ok, E - pr[:, sats], 0.0)], axis=1)
            B_buf[slot] = B_now
            m_buf[slot] = m_now
            slips_buf[slot] = slips_now
        tr_now = trans
        if variant == 2 and cmc_states:
            tracked = set(idx.tolist())
            gone = [i for i, s_ in enumerate(e_sats) if s_ not in tracked]
            boundary = k % W == 0
            n_e = len(e_sats)
            if gone or boundary:
                x_pred, P_pred = predict(x, P, trans_cache[n_e]) if k > 0 else (x, P)
                if gone:  # set inside its window: the start noise is marginalised, no increment
                    cols_g = [N_BASE + i for i in gone]
                    x_pred, P_pred = _drop_states(x_pred, P_pred, cols_g)
                    if aq is not None:
                        aqs = aqs._replace(q_diag=np.delete(aqs.q_diag, cols_g, axis=-1))
                    inc["lost_to_set"] += len(gone) * trials
                    e_sats = [s_ for i, s_ in enumerate(e_sats) if i not in set(gone)]
                pr_cols = np.full(idx.size, -1)
                inc_rows = np.zeros(0, dtype=int)
                old = np.zeros(0, dtype=int)
                if boundary:
                    n_old = len(e_sats)
                    x_pred, P_pred = _append_states(x_pred, P_pred, idx.size)
                    P_pred[:, n_old + N_BASE + np.arange(idx.size), n_old + N_BASE + np.arange(idx.size)] = \
                        scn.sigma_pr_m**2
                    if aq is not None:
                        aqs = aqs._replace(q_diag=np.concatenate([aqs.q_diag, np.zeros((trials, idx.size))], axis=-1))
                    pr_cols = N_BASE + n_old + np.arange(idx.size)
                    loc = {s_: j for j, s_ in enumerate(idx.tolist())}
                    inc_rows = np.array([loc[s_] for s_ in e_sats], dtype=int)
                    old = N_BASE + np.arange(n_old)
                    inc_new = pr_cols[inc_rows]
                    sats = idx[inc_rows]
                    ok = detector.slip_free(scn.cmc_window_s)[:, sats]
                    true_slip = (slips_now[:, sats] - e_slips[:, sats]) > 0
                    inc["candidates"] += ok.size
                    inc["used"] += int(ok.sum())
                    inc["rejected_slip"] += int((~ok).sum())
                    inc["spanning_true_slip"] += int(true_slip.sum())
                    inc["used_spanning_true_slip"] += int((ok & true_slip).sum())
                    n_inc[k] = int(ok.sum())
                    coef = 2.0 * k_iono[sats] * (m_now[:, sats] - e_m[:, sats])
                    E = B_now[:, sats] - e_B[:, sats]
                    e_sats = e_sats + idx.tolist()
                    e_m[:, idx] = m_now[:, idx]
                    e_B[:, idx] = B_now[:, idx]
                    e_slips[:, idx] = slips_now[:, idx]
                else:
                    inc_new, coef, ok, E = old, np.zeros((trials, 0)), np.zeros((trials, 0), bool), np.zeros((trials, 0))
                base = IonoTropoGnss(sp_v, sv_v, carrier[idx], is_gps[idx], scn.sigma_pr_m, scn.sigma_prr_m_s,
                                     n_state=x_pred.shape[-1])
                m2 = _CodeNoiseStateModel(base, pr_cols, inc_rows, inc_new, old, coef, ok, var_e)
                z2 = np.concatenate([z, np.where(ok, E, 0.0)], axis=1)
                res = ekf_update(x_pred, P_pred, z2, m2, backend=backend)
                aq_dx = res.x - x_pred
                if boundary and old.size:  # the ended windows' start noises: used, marginalised
                    rx, rP = _drop_states(res.x, res.P, old)
                    if aq is not None:
                        aqs = aqs._replace(q_diag=np.delete(aqs.q_diag, old, axis=-1))
                        aq_dx = np.delete(aq_dx, old, axis=-1)
                    e_sats = e_sats[old.size:]
                    res = res._replace(x=rx, P=rP)
                cmc_done = True
            else:
                cmc_done = False
            if len(e_sats) not in trans_cache:
                trans_cache[len(e_sats)] = scn.transition(n_amb=len(e_sats))
            tr_now = trans_cache[len(e_sats)]
            if not cmc_done:
                meas = IonoTropoGnss(sp_v, sv_v, carrier[idx], is_gps[idx], scn.sigma_pr_m, scn.sigma_prr_m_s,
                                     n_state=N_BASE + len(e_sats))
        if variant == 3:
            phase = obs.carrier_phase_m
            tracked = set(idx.tolist())
            gone = [i for i, s in enumerate(amb_sats) if s not in tracked]
            new = [s for s in idx.tolist() if s not in set(amb_sats)]
            if scn.phase_max_sats and new:
                # only phase_max_sats satellites carry a K state and a phase row: free slots go
                # to the highest satellites by the filter's own elevation (mean over trials)
                free = scn.phase_max_sats - (len(amb_sats) - len(gone))
                pos_f = x[:, 0:3] + (dt * x[:, 4:7] if k > 0 else 0.0)
                el_f = elevation_rad(pos_f[:, None, :], sp_v).mean(axis=0)
                loc = {s_: j for j, s_ in enumerate(idx.tolist())}
                new = sorted(new, key=lambda s_: -el_f[loc[s_]])[:max(free, 0)]
            # resets: detector slips on satellites that keep their K state (per trial)
            old_cols = np.array([N_BASE + i for i, s in enumerate(amb_sats) if s in tracked], dtype=int)
            old_sats = np.array([s for s in amb_sats if s in tracked], dtype=int)
            reset = det.slip[:, old_sats] if old_sats.size else np.zeros((trials, 0), dtype=bool)
            amb["k_resets"] += int(reset.sum())
            slips_now = receiver.slip_count.copy()
            true_slip = (slips_now - slips_prev)[:, idx] > 0
            amb["true_slips"] += int(true_slip.sum())
            amb["missed_true_slips"] += int((true_slip & ~det.slip[:, idx]).sum())
            slips_prev = slips_now
            if gone or new or reset.any() or k == 0 or aq is not None:
                if k > 0:
                    x, P = predict(x, P, trans_cache[len(amb_sats)])
                if gone:
                    x, P = _drop_states(x, P, [N_BASE + i for i in gone])
                    if aq is not None:
                        aqs = aqs._replace(q_diag=np.delete(aqs.q_diag, [N_BASE + i for i in gone], axis=-1))
                    amb_sats = [s for i, s in enumerate(amb_sats) if i not in set(gone)]
                    amb["sets"] += len(gone)
                    old_cols = np.array([N_BASE + amb_sats.index(s) for s in old_sats], dtype=int)
                if new:
                    x, P = _append_states(x, P, len(new))
                    if aq is not None:
                        aqs = aqs._replace(q_diag=np.concatenate([aqs.q_diag, np.zeros((trials, len(new)))], axis=-1))
                    amb_sats = amb_sats + new
                    amb["rises"] += len(new)
                init = np.zeros((trials, x.shape[-1]), dtype=bool)  # state columns to (re)initialise
                init[:, N_BASE + len(amb_sats) - len(new):] = True
                if old_cols.size:
                    init[:, old_cols] = reset
                kidx = np.array([N_BASE + amb_sats.index(s) if s in amb_sats else -1 for s in idx.tolist()])
                has = kidx >= 0
                m3 = IonoTropoGnss(sp_v, sv_v, carrier[idx], is_gps[idx], scn.sigma_pr_m,
                                   scn.sigma_prr_m_s, sigma_phase_m=scn.sigma_phase_m, phase_state_index=kidx,
                                   use_phase=True, n_state=x.shape[-1])
                cols = np.flatnonzero(init.any(axis=0))
                if cols.size:
                    hph = m3.h(x)[:, 2 * idx.size:]  # predicted phase incl. the current K
                    kinit = phase[:, idx[has]] - hph + x[:, kidx[has]]  # phase - predicted phase without K
                for c in cols:
                    tr = init[:, c]
                    j = int(np.flatnonzero(kidx[has] == c)[0])
                    x[tr, c] = kinit[tr, j]
                    P[tr, c, :] = 0.0
                    P[tr, :, c] = 0.0
                    P[tr, c, c] = var_amb
                    if aq is not None:
                        aqs.q_diag[tr, c] = 0.0
                if len(amb_sats) not in trans_cache:
                    trans_cache[len(amb_sats)] = scn.transition(n_amb=len(amb_sats))
                z = np.concatenate([z, phase[:, idx[has]]], axis=1)
                x_pred = x
                res = ekf_update(x, P, z, m3, backend=backend)
            else:
                kidx = np.array([N_BASE + amb_sats.index(s) if s in amb_sats else -1 for s in idx.tolist()])
                has = kidx >= 0
                m3 = IonoTropoGnss(sp_v, sv_v, carrier[idx], is_gps[idx], scn.sigma_pr_m,
                                   scn.sigma_prr_m_s, sigma_phase_m=scn.sigma_phase_m, phase_state_index=kidx,
                                   use_phase=True, n_state=x.shape[-1])
                z = np.concatenate([z, phase[:, idx[has]]], axis=1)
                res = ekf_step(x, P, z, trans_cache[len(amb_sats)], m3, dt, backend=backend)
            n_state[k] = res.x.shape[-1]
        elif variant == 2 and cmc_states and cmc_done:
            pass  # updated above (window boundary or a satellite set)
        elif k == 0:
            x_pred = x
            res = ekf_update(x, P, z, meas, backend=backend)  # the prior is at the first epoch
        elif aq is not None:
            x_pred, P_pred = predict(x, P, tr_now)
            res = ekf_update(x_pred, P_pred, z, meas, backend=backend)
        else:
            res = ekf_step(x, P, z, tr_now, meas, dt, backend=backend)
        if aq is not None:
            aqs = aq.next(aqs, aq_dx if (variant == 2 and cmc_states and cmc_done) else res.x - x_pred)
        if variant == 2 and cmc_states:
            n_state[k] = res.x.shape[-1]
        x, P = res.x, res.P

        # ---------------- statistics (scoring side)
        eI = x[:, IDX_IONO] - I_true
        eU = x[:, IDX_TROPO] - U_true
        ep2 = np.sum((x[:, 0:3] - pos_true[k]) ** 2, axis=1)
        nees = _nees2(eI, eU, P, IDX_IONO, IDX_TROPO)
        ec = np.stack([x[:, IDX_CLOCK] - bias, x[:, IDX_DRIFT] - drift], axis=1)
        nees_c = _nees2(ec[:, 0], ec[:, 1], P, IDX_CLOCK, IDX_DRIFT)
        ser["clock_err_rms_m"][k] = math.sqrt(np.mean(ec[:, 0] ** 2))
        ser["drift_err_rms_m"][k] = math.sqrt(np.mean(ec[:, 1] ** 2))
        ser["nees_clock_mean"][k] = nees_c.mean()
        ser["iono_est_trial0_m"][k] = x[0, IDX_IONO]  # one realisation, as the paper's figures show
        ser["tropo_est_trial0_m"][k] = x[0, IDX_TROPO]
        ser["iono_err_mean_m"][k] = eI.mean()
        ser["iono_err_rms_m"][k] = math.sqrt(np.mean(eI * eI))
        ser["tropo_err_mean_m"][k] = eU.mean()
        ser["tropo_err_rms_m"][k] = math.sqrt(np.mean(eU * eU))
        ser["pos_err_rms_m"][k] = math.sqrt(np.mean(ep2))
        ser["nees_atmo_mean"][k] = nees.mean()
        ser["nis_mean"][k] = float(np.mean(res.nis))
        ser["iono_sd_m"][k] = math.sqrt(np.mean(P[:, IDX_IONO, IDX_IONO]))
        ser["tropo_sd_m"][k] = math.sqrt(np.mean(P[:, IDX_TROPO, IDX_TROPO]))
        bad = (np.abs(eI) >= 1.0) | (np.abs(eU) >= 1.0) | ~np.isfinite(eI) | ~np.isfinite(eU)
        last_bad[bad] = k
        if k >= k_final:
            acc["iono"] += float(np.sum(eI * eI))
            acc["tropo"] += float(np.sum(eU * eU))
            acc["pos"] += float(np.sum(ep2))
            acc["nees"] += float(np.sum(nees))
            acc["nees_c"] += float(np.sum(nees_c))
            acc["iono_b"] += float(np.sum(eI))
            acc["tropo_b"] += float(np.sum(eU))
            acc["n"] += trials
        if progress and (k % report_every == 0 or k == T - 1):
            progress(f"t {t_rel[k]:7.1f} s  sats {idx.size:2d}  rms I_g err {ser['iono_err_rms_m'][k]:6.3f} m  "
                     f"U_g err {ser['tropo_err_rms_m'][k]:6.3f} m  pos {ser['pos_err_rms_m'][k]:7.2f} m  "
                     f"({time.perf_counter() - t_wall:.1f} s)", done=k + 1, total=T)

    settled = last_bad < T - 1
    ttm = np.where(settled, t_rel[np.minimum(last_bad + 1, T - 1)], np.inf)
    ttm = np.where(last_bad < 0, 0.0, ttm)
    n = acc["n"]
    lo, hi = metrics.chi2_bounds(2, trials, p=0.99)
    extra = {}
    if variant == 2:
        extra = {"increments": inc, "n_increments_used": n_inc}
        if cmc_states:
            extra["n_state"] = n_state
    if variant == 3:
        extra = {"ambiguity": amb, "n_state": n_state}
    names = {1: "seed000-variant1-code-doppler", 2: "seed000-variant2-cmc-increments",
             3: "seed000-variant3-carrier-phase"}
    return {
        "experiment": names[variant],
        "variant": variant,
        "trials": trials,
        "seed": seed,
        "scenario": asdict(scn),
        "epochs": T,
        "t_s": t_rel,
        "n_visible": n_vis,
        "n_visible_min": int(n_vis.min()),
        "n_visible_max": int(n_vis.max()),
        **ser,
        "prior_error": prior_err,
        "time_to_1m_s": float(np.median(ttm)),
        "time_to_1m_s_per_trial": ttm,
        "final_error_m": {"iono_zenith": math.sqrt(acc["iono"] / n), "tropo_zenith": math.sqrt(acc["tropo"] / n),
                          "position": math.sqrt(acc["pos"] / n)},
        "final_bias_m": {"iono_zenith": acc["iono_b"] / n, "tropo_zenith": acc["tropo_b"] / n},
        "anees": acc["nees"] / n / 2.0,
        "anees_clock": acc["nees_c"] / n / 2.0,
        "anees_bounds_99_one_epoch": [lo / 2.0, hi / 2.0],
        **extra,
        "wall_s": time.perf_counter() - t_wall,
    }


def summary(res: dict) -> str:
    fe = res["final_error_m"]
    fb = res["final_bias_m"]
    ttm = np.asarray(res["time_to_1m_s_per_trial"])
    label = {1: "code + Doppler", 2: "code + Doppler + CMC increments",
             3: "code + Doppler + ambiguous carrier phase"}[res.get("variant", 1)]
    lines = [
        (f"seed 000 variant {res.get('variant', 1)} ({label}): "
         f"{res['trials']} trials x {res['epochs']} epochs, "
         f"{res['n_visible_min']}..{res['n_visible_max']} satellites in view"),
        (f"time to 1 m (I_g and U_g): median {res['time_to_1m_s']:.1f} s; per trial min {ttm.min():.1f} "
         f"max {ttm.max():.1f} s ({int(np.sum(~np.isfinite(ttm)))} never)"),
        (f"final RMS (last {min(res['scenario']['final_window_s'], res['scenario']['duration_s']):g} s): I_g {fe['iono_zenith']:.3f} m  "
         f"U_g {fe['tropo_zenith']:.3f} m  position {fe['position']:.2f} m;  mean error I_g "
         f"{fb['iono_zenith']:+.3f} m  U_g {fb['tropo_zenith']:+.3f} m"),
        (f"ANEES (I_g, U_g) last window {res['anees']:.3f}  (99% one-epoch band "
         f"{res['anees_bounds_99_one_epoch'][0]:.3f}..{res['anees_bounds_99_one_epoch'][1]:.3f});  "
         f"clock (bias, drift) {res['anees_clock']:.3f}"),
        f"wall {res['wall_s']:.1f} s",
    ]
    if "increments" in res:
        lines.insert(-1, "increments: " + ", ".join(f"{k} {v}" for k, v in res["increments"].items()))
    if "ambiguity" in res:
        ns = np.asarray(res["n_state"])
        lines.insert(-1, f"state dim {ns.min()}..{ns.max()}; ambiguity: "
                     + ", ".join(f"{k} {v}" for k, v in res["ambiguity"].items()))
    return "\n".join(lines)
