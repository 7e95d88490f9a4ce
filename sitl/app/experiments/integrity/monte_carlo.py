"""The seed 003 Monte Carlo: the faulty world (GM errors, injected faults) and every filter on
the same data, trials stepped together; the scoring runs alongside (sitl.app.experiments.integrity.scoring)."""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from filters.adaptive import AdaptiveQ
from filters.ekf import ekf_predict
from filters.integrity import IntegrityMonitor
from filters.models import PseudorangeDoppler
from sitl.app.experiments.integrity.models import BiasedPseudorangeDoppler
from sitl.app.experiments.integrity.scenario import N_BASE, IntegrityScenario
from sitl.app.experiments.integrity.scoring import TARGETS, _pfa_only, _ramp_oracle, _Score
from sitl.gnss.clock import ClockModel
from sitl.gnss.receiver import Receiver
from sitl.gnss.world import ephemeris_for_filter, geometry_track
from sitl.measfault import FAULT_KINDS, Fault, FaultInjector, GaussMarkov
from sitl.params import integer

__all__ = ["run", "FILTERS", "DETECTION_FILTER"]

FILTERS = ("plain", "adaptive_robust", "adaptive_robust_with_bias_estimation")
# fault-free pairs (the same world before injection): each EKF without and with the monitor
CLEAN = ("plain_fault_free", "monitored_fault_free", "bias_states_fault_free", "bias_states_monitored_fault_free")
MONITORED = ("adaptive_robust", "adaptive_robust_with_bias_estimation", "monitored_fault_free",
             "bias_states_monitored_fault_free")
BIASED = ("adaptive_robust_with_bias_estimation", "bias_states_fault_free", "bias_states_monitored_fault_free")
DYNAMIC = tuple(range(N_BASE))
# the filter whose monitor `detection` reports: the one whose model matches the world (the GM errors are
# states), so its healthy innovations are white N(0, 1) as the seed's tests assume; the plain-model
# adaptive-robust filter's monitor is reported beside it (detection_by_filter)
DETECTION_FILTER = "adaptive_robust_with_bias_estimation"
K_STEP, K_RAMP, K_OUT, K_DROP = (FAULT_KINDS.index(k) + 1 for k in ("step", "ramp", "outlier", "dropout"))


def _faults(scn: IntegrityScenario, rng, trials: int, S: int):
    """The per-trial fault draws: (list of Fault on the (2S,) measurement columns, dict of truth)."""
    T_end = scn.duration_s
    lo, hi = scn.onset_min_s, scn.onset_max_frac * T_end
    dt = scn.dt_s

    def onset(n):  # on the epoch grid, so that onset epochs are exact
        return np.round(rng.uniform(lo, hi, n) / dt) * dt

    step_ch = rng.integers(0, S, trials)
    ramp_ch = (step_ch + rng.integers(1, S, trials)) % S  # another satellite
    drop_ch = rng.integers(0, S, trials)
    step_t0, ramp_t0, drop_t0 = onset(trials), onset(trials), onset(trials)
    step_mag = rng.uniform(*scn.step_sigma, trials) * scn.sigma_ref_m * rng.choice([-1.0, 1.0], trials)
    step_len = rng.uniform(*scn.step_duration_s, trials)
    ramp_rate = rng.uniform(*scn.ramp_rate_m_s, trials) * rng.choice([-1.0, 1.0], trials)
    drop_len = rng.uniform(*scn.dropout_s, trials)
    faults = []
    for i in range(trials):
        faults.append(Fault("step", int(step_ch[i]), float(step_t0[i]), float(step_t0[i] + step_len[i]),
                            magnitude=float(step_mag[i]), trial=i))
        faults.append(Fault("ramp", int(ramp_ch[i]), float(ramp_t0[i]), rate=float(ramp_rate[i]), trial=i))
        if scn.ramp_kind == "clock":  # the clock's frequency error shows in the pseudorange rate
            faults.append(Fault("step", S + int(ramp_ch[i]), float(ramp_t0[i]), magnitude=float(ramp_rate[i]),
                                trial=i))
    for c in range(S):
        if scn.outlier_prob > 0:
            faults.append(Fault("outlier", c, 0.0, prob=scn.outlier_prob, scale=scn.sigma_pr_m,
                                dof=scn.outlier_dof))
    for i in range(trials):  # last: a dropout overrides everything on its rows
        for col in (int(drop_ch[i]), S + int(drop_ch[i])):
            faults.append(Fault("dropout", col, float(drop_t0[i]), float(drop_t0[i] + drop_len[i]), trial=i))
    truth = {"step_ch": step_ch, "step_k0": np.round(step_t0 / dt).astype(int),
             "step_k1": np.round((step_t0 + step_len) / dt).astype(int), "step_mag": step_mag,
             "ramp_ch": ramp_ch, "ramp_k0": np.round(ramp_t0 / dt).astype(int), "ramp_rate": ramp_rate}
    return faults, truth


def run(scn: IntegrityScenario, trials: int, seed: int, progress=None, backend=None, clean=True) -> dict:
    """All filters on the same simulated data; returns a dict (numpy arrays for the series)."""
    trials = integer(lo=1)("trials", trials)
    t_wall = time.perf_counter()
    ss = np.random.SeedSequence(seed)
    rng_w, rng_f, rng_p = (np.random.default_rng(s) for s in ss.spawn(3))
    const = scn.constellation()
    sats = scn.channel_sats()
    S = sats.size
    sub = const.subset(sats)
    carrier = sub.carrier_l1_hz
    is_gps = sub.system == "G"
    receiver = Receiver(S, scn.receiver_config(), (trials,))
    clock = ClockModel()
    dt = scn.dt_s
    T = scn.n_epochs
    t_rel = scn.times()
    pos_true, vel_true = scn.trajectory(t_rel)
    k_warm = int(np.searchsorted(t_rel, scn.warmup_s - 1e-9))

    # truth clock, GM errors, faults
    bias = scn.sigma0_clock_bias_m * rng_w.standard_normal(trials)
    drift = scn.sigma0_clock_drift_m_s * rng_w.standard_normal(trials)
    gm = GaussMarkov(scn.gm_sigma_m, scn.gm_tau_s, (trials, S), rng_w)
    if scn.faults:
        fault_list, ftruth = _faults(scn, rng_f, trials, S)
    else:
        fault_list, ftruth = [], None
    injector = FaultInjector(fault_list, (trials,), 2 * S)

    # filters
    channels = np.concatenate([np.arange(S), np.arange(S)])
    sd0 = np.array([scn.sigma0_pos_m] * 3 + [scn.sigma0_clock_bias_m] + [scn.sigma0_vel_m_s] * 3
                   + [scn.sigma0_clock_drift_m_s])
    x0 = np.zeros((trials, N_BASE))
    x0[:, 0:3] = pos_true[0] + scn.sigma0_pos_m * rng_p.standard_normal((trials, 3))
    x0[:, 4:7] = vel_true[0] + scn.sigma0_vel_m_s * rng_p.standard_normal((trials, 3))
    P0 = np.broadcast_to(np.diag(sd0**2), (trials, N_BASE, N_BASE)).copy()
    nb = N_BASE + S
    xb0 = np.zeros((trials, nb))
    xb0[:, :N_BASE] = x0
    Pb0 = np.zeros((trials, nb, nb))
    Pb0[:, :N_BASE, :N_BASE] = P0
    Pb0[:, np.arange(N_BASE, nb), np.arange(N_BASE, nb)] = scn.gm_sigma_m**2
    tr_base, tr_bias = scn.transition(), scn.transition(S)
    cfg = scn.monitor_config()
    detect_only = IntegrityMonitor(dataclasses.replace(cfg, isolate=False, huber_c=None, adapt_r=False))
    mon = IntegrityMonitor(cfg)
    aq = AdaptiveQ(scn.adaptive_q_decay, scn.adaptive_q_gain, DYNAMIC)
    var_white_gm = scn.sigma_pr_m**2 + scn.gm_sigma_m**2

    names = FILTERS + (CLEAN if clean else ())
    st = {}
    for name in names:
        biased = name in BIASED
        m = mon if name in MONITORED else detect_only
        st[name] = {"x": (xb0 if biased else x0).copy(), "P": (Pb0 if biased else P0).copy(),
                    "mon": m, "ms": m.init((trials,), 2 * S, S), "biased": biased,
                    "aq": name in FILTERS[1:], "aqs": aq.init((trials,), nb if biased else N_BASE),
                    "tr": tr_bias if biased else tr_base, "se": np.zeros(trials), "err0": np.empty(T),
                    "excl": 0}
    scores = {n: _Score(scn, trials, S, ftruth) for n in FILTERS[1:]} if scn.faults else {}
    clean_fa = {n: {"n": 0, "fa": 0} for n in ("monitored_fault_free", "bias_states_monitored_fault_free")}
    last_fault = np.full((trials, S), -10**9)
    n_missing_mask = 0
    report_every = max(1, T // 10)
    geom = geometry_track(scn.t0_gps_s + t_rel, pos_true, vel_true, sub)
    for k in range(T):
        t = scn.t0_gps_s + t_rel[k]
        # ---------------- world (truth)
        if k > 0:
            bias, drift = clock.step(rng_w, bias, drift, dt)
            e_gm = gm.step(rng_w, dt)
        else:
            e_gm = gm.x
        eg = next(geom)
        geo = eg.geometry
        obs = receiver.step(rng_w, t, geo.range_m, geo.range_rate_m_s, eg.el_rad, carrier, is_gps, bias, drift,
                            el_atmo_rad=eg.el_atmo_rad)
        z_clean = np.concatenate([obs.pseudorange_m + e_gm, obs.pseudorange_rate_m_s], axis=1)
        n_missing_mask += int(np.isnan(z_clean).sum())
        z, inj = injector.step(rng_f, t_rel[k], z_clean)

        # ---------------- filters (measurements + ephemeris only)
        data = {}
        for which, zz in (("faulty", z), ("clean", z_clean)):
            if which == "clean" and not clean:
                continue
            pr, prr = zz[:, :S], zz[:, S:]
            sp, sv = ephemeris_for_filter(t, pr, sub, pseudorange_rate_m_s=np.where(np.isfinite(pr), prr, np.nan))
            data[which] = (zz, sp, sv)
        for name, s in st.items():
            zz, sp, sv = data["clean" if name in CLEAN else "faulty"]
            if s["biased"]:
                meas = BiasedPseudorangeDoppler(PseudorangeDoppler(sp, sv, scn.sigma_pr_m, scn.sigma_prr_m_s, n=nb),
                                                N_BASE)
            else:
                meas = PseudorangeDoppler(sp, sv, math.sqrt(var_white_gm), scn.sigma_prr_m_s, n=N_BASE)
            x, P = s["x"], s["P"]
            if k > 0:
                if s["aq"]:
                    x_pred, P_pred = ekf_predict(x, P, aq.transition(s["tr"], s["aqs"]), dt, backend=backend)
                    P_pred = aq.add_diag(P_pred, s["aqs"])
                else:
                    x_pred, P_pred = ekf_predict(x, P, s["tr"], dt, backend=backend)
            else:
                x_pred, P_pred = x, P
            res, s["ms"], rep = s["mon"].step(s["ms"], x_pred, P_pred, zz, meas, channels, backend=backend)
            if s["aq"]:
                s["aqs"] = aq.next(s["aqs"], res.x - x_pred)
            s["x"], s["P"] = res.x, res.P
            e2 = np.sum((res.x[:, 0:3] - pos_true[k]) ** 2, axis=1)
            s["err0"][k] = math.sqrt(e2[0])
            if k >= k_warm:
                s["se"] += e2
            s["excl"] += int(rep.newly_excluded.sum())
            s["rep"] = rep

        # ---------------- scoring (truth side)
        if scn.faults:
            kind, missing = inj.kind, inj.missing
            fault_now = (kind[:, :S] > 0) | (kind[:, S:] > 0)
            tr = ftruth
            r = np.arange(trials)
            step_on = (k >= tr["step_k0"]) & (k < tr["step_k1"])
            ramp_on = k >= tr["ramp_k0"]
            fault_now[r[step_on], tr["step_ch"][step_on]] = True
            fault_now[r[ramp_on], tr["ramp_ch"][ramp_on]] = True
            last_fault[fault_now] = k
            missing_ch = missing[:, :S] | missing[:, S:] | np.isnan(z[:, :S]) | np.isnan(z[:, S:])
            healthy = (k - last_fault > scn.window) & ~missing_ch & (k >= k_warm)
            big = (kind[:, :S] == K_OUT) & (np.abs(inj.bias[:, :S]) >= 5.0 * scn.sigma_ref_m) & ~missing_ch
            big[r[step_on], tr["step_ch"][step_on]] = False
            big[r[ramp_on], tr["ramp_ch"][ramp_on]] = False
            count = min(k + 1, scn.window)
            for name, sc in scores.items():
                sc.epoch(k, st[name]["rep"], count, healthy, big, missing_ch)
        if clean and k >= k_warm + scn.window:
            ok = np.isfinite(z_clean[:, :S]) & np.isfinite(z_clean[:, S:])
            for name in ("monitored_fault_free", "bias_states_monitored_fault_free"):
                rep = st[name]["rep"]
                alarm_rows = rep.jump | rep.drift
                clean_fa[name]["n"] += int(ok.sum())
                clean_fa[name]["fa"] += int(((alarm_rows[:, :S] | alarm_rows[:, S:]) & ok).sum())
        if progress and (k % report_every == 0 or k == T - 1):
            rms = {n: math.sqrt(np.mean(np.sum((st[n]["x"][:, :3] - pos_true[k]) ** 2, axis=1))) for n in FILTERS}
            progress(f"t {t_rel[k]:6.1f} s  position error rms: " + "  ".join(f"{n} {v:7.2f} m" for n, v in rms.items())
                     + f"  ({time.perf_counter() - t_wall:.1f} s)", done=k + 1, total=T)

    n_scored = T - k_warm
    rmse = {n: float(math.sqrt(st[n]["se"].sum() / (trials * n_scored))) for n in st}
    per_trial = {n: np.sqrt(st[n]["se"] / n_scored) for n in st}
    out = {
        "trials": trials, "seed": seed, "epochs": T, "channels": int(S), "sat_ids": np.array(sub.sat_id).tolist(),
        "t_s": t_rel, "position_rmse_m": {n: rmse[n] for n in FILTERS},
        "rmse_ratio": {"plain_over_adaptive_robust": rmse["plain"] / rmse["adaptive_robust"],
                       "plain_over_adaptive_robust_with_bias_estimation":
                           rmse["plain"] / rmse["adaptive_robust_with_bias_estimation"],
                       "adaptive_robust_over_with_bias_estimation":
                           rmse["adaptive_robust"] / rmse["adaptive_robust_with_bias_estimation"]},
        "position_rmse_per_trial_m": per_trial,
        "position_error_trial0_m": {n: st[n]["err0"] for n in st},
        "exclusions": {n: st[n]["excl"] for n in FILTERS[1:]},
        "missing_by_mask": n_missing_mask,
    }
    if scn.faults:
        det, roc = {}, {}
        for n, sc in scores.items():
            det[n], roc[n] = sc.result()
        # the best any detector could do on these ramps at the false-alarm target (code-only ramps; a clock ramp
        # also moves the pseudorange rate, sigma_prr: its bound is 1 to many digits)
        oracle = (_ramp_oracle(scn, seed, ftruth["ramp_rate"], scores[DETECTION_FILTER].ramp_valid, TARGETS["pfa_max"])
                  if scn.ramp_kind == "code" else None)
        for n in det:
            det[n]["ramp"]["oracle"] = oracle
        out["detection"] = det[DETECTION_FILTER]
        out["detection_by_filter"] = det
        out["roc"] = roc
        out["fault_onsets_trial0_s"] = {"step": float(ftruth["step_k0"][0] * dt),
                                        "step_end": float(ftruth["step_k1"][0] * dt),
                                        "ramp": float(ftruth["ramp_k0"][0] * dt),
                                        "step_channel": int(ftruth["step_ch"][0]),
                                        "ramp_channel": int(ftruth["ramp_ch"][0]),
                                        "step_sigma": float(ftruth["step_mag"][0] / scn.sigma_ref_m),
                                        "ramp_rate_m_s": float(ftruth["ramp_rate"][0])}
    if clean:
        out["fault_free"] = {}
        for key, a_name, b_name in (("plain_model", "plain_fault_free", "monitored_fault_free"),
                                    ("bias_state_model", "bias_states_fault_free", "bias_states_monitored_fault_free")):
            a, b = per_trial[a_name], per_trial[b_name]
            d = b - a
            se = float(d.std(ddof=1) / math.sqrt(trials)) if trials > 1 else math.nan
            out["fault_free"][key] = {
                "position_rmse_m": {"without_monitor": rmse[a_name], "with_monitor": rmse[b_name]},
                "paired_difference_m": {"mean": float(d.mean()), "standard_error": se,
                                        "upper_95": float(d.mean() + 1.645 * se) if trials > 1 else None},
                "pfa": _pfa_only(clean_fa[b_name]["fa"], clean_fa[b_name]["n"]),
            }
    out["wall_s"] = time.perf_counter() - t_wall
    return out
