"""Scoring of the beacon experiment: errors per paper axis, RMSE, ANEES, the PCRB series, the
UAVs' navigation errors and the integrity monitors' summary."""
from __future__ import annotations

import math
import warnings

import numpy as np

from sitl.app.experiments.beacon.constants import AXIS_ECEF, BEACON_ID, PAPER_ERRORS_M, PRODUCTION, SETTLE_S
from sitl.app.experiments.beacon.world import gnss_information


def _truth3(truth):
    """Truth (K, 6) or (K, T, 6) as (K, T or 1, 6)."""
    return truth[:, None] if truth.ndim == 2 else truth


def _scores(t, x, P, truth):
    """errors_m, rmse_m, anees of one estimator's series (K, T, 6) against truth (K, [T,] 6).
    errors_m / rmse_axes_m per paper axis (AXIS_ECEF)."""
    from filters import metrics

    sel = t >= SETTLE_S
    tr = _truth3(truth)[sel]
    e = x[sel, :, 0:3] - tr[..., 0:3]
    ok = np.all(np.isfinite(e), axis=(0, 2))
    if not ok.any():
        return None
    e = e[:, ok]
    Pp = P[sel][:, ok, 0:3, 0:3]
    T = e.shape[1]
    per_trial_max = np.max(np.abs(e), axis=0)  # (T, 3)
    errors = {ax: {"ecef_axis": "xyz"[a], "median_of_trial_max": float(np.median(per_trial_max[:, a])),
                   "max_over_trials": float(np.max(per_trial_max[:, a])),
                   "paper": PAPER_ERRORS_M[ax],
                   "within_paper_fraction": float(np.mean(per_trial_max[:, a] <= PAPER_ERRORS_M[ax]))}
              for ax, a in AXIS_ECEF.items()}
    nees = metrics.nees(e, Pp)  # (Ks, T)
    per_epoch = nees.mean(axis=1)
    lo, hi = metrics.chi2_bounds(3, T, 0.99)
    ev = x[sel][:, ok, 3:6] - tr[:, ok if tr.shape[1] > 1 else slice(None), 3:6]
    return {
        "errors_m": errors,
        "rmse_m": float(np.sqrt(np.mean(np.sum(e * e, axis=-1)))),
        "rmse_per_trial_m": np.sqrt(np.mean(np.sum(e * e, axis=-1), axis=0)).tolist(),
        "rmse_axes_m": {ax: float(np.sqrt(np.mean(e[..., a] ** 2))) for ax, a in AXIS_ECEF.items()},
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
    e = x[..., 0:3] - _truth3(truth)[..., 0:3]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN epochs before the start
        return np.sqrt(np.nanmean(np.sum(e * e, axis=-1), axis=1))


def pcrb_series(tracks, const, nav_cfg, cfg, prior=None):
    """sqrt(trace) of the PCRB beacon position block per epoch (K,) (centralised model), at
    trial 0's truth when each trial has its own beacon; the beacon's prior information at
    epoch 0 is the scenario's prior's (inverse covariance) when there is one, else the blind
    start's weak height and velocity priors."""
    from ground_station.beacon import local_up, pcrb_central
    from sitl.radio.beacon_link import BeaconLinkConfig
    from vehicles import uav_nav

    t, U, V, B, VB = tracks
    if B.ndim == 3:
        B, VB = B[:, 0], VB[:, 0]
    t_gps = uav_nav.EXAMPLE_T0_GPS_S + t
    info = gnss_information(t_gps, U, V, const, nav_cfg)
    if prior is not None:
        J0 = np.linalg.inv(np.asarray(prior[1], float))
    else:
        up, _ = local_up(B[0])
        J0 = np.zeros((6, 6))
        J0[0:3, 0:3] = np.outer(up, up) / cfg.init_height_sigma_m ** 2 + np.eye(3) / 1e5 ** 2
        J0[3:6, 3:6] = np.eye(3) / cfg.init_vel_sigma_m_s ** 2
    link = BeaconLinkConfig()
    Bd = pcrb_central(t, B, VB, U, V, info, link.var_range_m2, link.var_range_rate_m2_s2, J0,
                      q_beacon_m2_s3=cfg.q_m2_s3, q_uav_m2_s3=nav_cfg.q_m2_s3)
    return np.sqrt(np.trace(Bd, axis1=-2, axis2=-1)), Bd


def summarise_case(res, pcrb_tr, name=PRODUCTION) -> dict:
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


def integrity_summary(res_plain, res_mon, trials: int) -> dict:
    """The integrity part of a case (``--integrity compare``: the same faulty data, plain
    locator and UAV filters against monitored ones; ``on``: res_plain None): events by source and
    kind, the isolation of each injected fault (delay from the fault's start to the first step
    or ramp event on its channel, per trial; rate = trials isolated), exclusions of other
    channels after the fault and before it (fault-free epochs: per channel-epoch), and the
    production locator's RMSE and ANEES, over the whole scored span and after the fault."""
    fl = res_mon["faults"]
    ev = res_mon["integrity_events"]
    t = res_mon["t"]
    t_f = float(fl["fault_at_s"])
    by_src = {}
    for _, _, src, _, kind, _ in ev:
        grp = "locator" if src.startswith("gs") else "uav_nav"
        by_src.setdefault(grp, {}).setdefault(kind, 0)
        by_src[grp][kind] += 1

    def isolation(source, channel):
        first = {}
        for j, te, src, ch, kind, _ in ev:
            if src == source and ch == channel and kind in ("step", "ramp") and te >= t_f - 1e-9:
                first[j] = min(first.get(j, math.inf), te - t_f)
        d = np.array([first.get(j, math.inf) for j in range(trials)])
        ok = np.isfinite(d)
        return {"channel": channel, "rate": float(ok.mean()), "trials": trials,
                "delay_s_median": float(np.median(d[ok])) if ok.any() else None,
                "delay_s_max": float(d[ok].max()) if ok.any() else None}

    out = {"faults": fl, "events": len(ev), "by_source_and_kind": by_src}
    N = res_mon["nav_x"].shape[2]
    n_pre = int(np.sum((t >= 0) & (t < t_f)))
    gs_excl_pre = sum(1 for _, te, s, _, k, _ in ev if s.startswith("gs") and k in ("step", "ramp") and te < t_f)
    out["locator_exclusions_before_fault_per_link_epoch"] = gs_excl_pre / max(1, n_pre * trials * N)
    if fl["range_step_m"]:
        ch = f"{BEACON_ID}.uav{int(fl['range_step_uav'])}"
        out["range_step_isolation"] = isolation("gs.integrity", ch)
        out["range_step_isolation"]["other_links_excluded_after_fault"] = sum(
            1 for _, te, s, c, k, _ in ev if s.startswith("gs") and c != ch and k in ("step", "ramp") and te >= t_f)
    if fl["pr_step_m"] and fl.get("pr_step_sat"):
        u = int(fl["pr_step_uav"])
        out["pr_step_isolation"] = isolation(f"uav{u}.integrity", f"uav{u}.{fl['pr_step_sat']}")
    after = t >= max(SETTLE_S, t_f)

    def score(res):
        sc = _scores(t, res["x"][PRODUCTION], res["P"][PRODUCTION], res["truth"])
        if sc is None:
            return None
        e = res["x"][PRODUCTION][after, :, 0:3] - _truth3(res["truth"])[after][..., 0:3]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            ra = float(np.sqrt(np.nanmean(np.sum(e * e, axis=-1)))) if after.any() else None
        return {"rmse_m": sc["rmse_m"], "rmse_after_fault_m": ra, "anees": sc["anees"]["value"],
                "rmse_per_trial_m": sc["rmse_per_trial_m"]}

    out["monitored"] = score(res_mon)
    if res_plain is not None:
        out["plain"] = score(res_plain)
        if out["plain"] and out["monitored"]:
            d = np.array(out["monitored"]["rmse_per_trial_m"]) - np.array(out["plain"]["rmse_per_trial_m"])
            out["paired_rmse_difference_m"] = {"mean": float(d.mean()), "standard_error":
                                               float(d.std(ddof=1) / math.sqrt(d.size)) if d.size > 1 else None,
                                               "monitored_better_in": int(np.sum(d < 0)), "of": int(d.size)}
    return out
