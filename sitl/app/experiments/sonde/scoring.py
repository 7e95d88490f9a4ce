"""Scoring of a sonde run (scoring-side truth only): RMSE by ground range and in the episodes,
the same-data comparisons, the NEES against its chi-square band, the fused track's continuity,
and the integrity monitor's summary."""
from __future__ import annotations

import itertools
import math

import numpy as np

from sitl.app.experiments.sonde.scenario import MODES, MONITORED, SONDE_INTEGRITY, SondeScenario


def _rmse(e2: np.ndarray):
    return float(np.sqrt(np.mean(e2))) if e2.size else None


def _paired(e2_a: np.ndarray, e2_b: np.ndarray, sel: np.ndarray):
    """Same-data comparison of two modes over the samples sel (B, T): the relative RMSE gain
    of a over b, 100 (1 - rmse_a / rmse_b) %, and the difference of the per-trial mean squared
    errors, mean and standard error over the trials (the trials are independent, the epochs
    of one trial are not)."""
    if not sel.any():
        return None
    per = [float(np.mean(e2_a[b][sel[b]] - e2_b[b][sel[b]])) for b in range(sel.shape[0]) if sel[b].any()]
    d = np.array(per)
    se = float(d.std(ddof=1) / math.sqrt(d.size)) if d.size > 1 else None
    ra, rb = math.sqrt(np.mean(e2_a[sel])), math.sqrt(np.mean(e2_b[sel]))
    return {"gain_percent": 100.0 * (1.0 - ra / rb), "mse_difference_m2": float(d.mean()),
            "mse_difference_stderr_m2": se, "trials": int(d.size)}


def score(raw: dict, scn: SondeScenario) -> dict:
    """The result document's numbers from run_trials' arrays."""
    from filters.metrics import chi2_bounds, nees

    modes = list(raw["modes"])
    t_rel = raw["t_gps_s"] - raw["t0_gps_s"]
    gr_km = raw["ground_range_m"] / 1e3  # (B, T)
    B = gr_km.shape[0]
    err = raw["pos"] - raw["truth_pos"][None]  # (M, B, T, 3)
    e2 = np.sum(err * err, axis=-1)  # (M, B, T)
    have = np.isfinite(e2)
    main = [modes.index(m) for m in MODES]
    common = np.all(have[main], axis=0)  # every main mode has an estimate
    # inside the operating radius: ground range below 250 km and slant range from the GCPP
    # within it too (beyond, neither radar nor relay measures: every mode coasts alike)
    inside = (gr_km < scn.max_range_km) & (raw["slant_range_m"] <= scn.max_range_km * 1e3)

    # RMSE by ground range
    edges = np.arange(0.0, scn.max_range_km + 1e-9, scn.bin_km)
    bins = []
    for lo, hi in itertools.pairwise(edges):
        sel = common & inside & (gr_km >= lo) & (gr_km < hi)
        row = {"range_km": float(lo), "rmse_m": {m: _rmse(e2[i][sel]) for i, m in enumerate(modes)},
               "n": int(sel.sum())}
        r = row["rmse_m"]
        row["fused_below_both"] = (None if r["fused"] is None else bool(r["fused"] < r["radar_only"]
                                                                        and r["fused"] < r["relay_only"]))
        row["fused_vs_relay_only"] = _paired(e2[modes.index("fused")], e2[modes.index("relay_only")], sel)
        bins.append(row)
    filled = [b for b in bins if b["n"] > 0]

    def episode(a, b):
        sel = common & (t_rel >= a)[None] & (t_rel < b)[None] & inside
        fi, ri, di = modes.index("fused"), modes.index("relay_only"), modes.index("radar_only")
        return {"window_s": [a, b], "n": int(sel.sum()),
                "rmse_m": {m: _rmse(e2[i][sel]) for i, m in enumerate(modes)},
                "fused_vs_relay_only": _paired(e2[fi], e2[ri], sel),
                "fused_vs_radar_only": _paired(e2[fi], e2[di], sel),
                "max_error_m": {m: (float(np.sqrt(e2[i][sel].max())) if sel.any() else None)
                                for i, m in enumerate(modes)}}

    # consistency: NEES of the published [pos, vel] estimate (6 dof), epochs with every trial inside
    x_err = np.concatenate([err, raw["vel"] - raw["truth_vel"][None]], axis=-1)  # (M, B, T, 6)
    ep = np.all(inside, axis=0) & np.all(common, axis=0)  # epochs (T,)
    lo, hi = chi2_bounds(6, B, 0.99)
    lo3, hi3 = chi2_bounds(3, B, 0.99)
    anees = {}
    for i, m in enumerate(modes):
        e_ok = ep & np.all(have[i], axis=0)
        if not e_ok.any():
            anees[m] = None
            continue
        nv = nees(x_err[i][:, e_ok], raw["cov"][i][:, e_ok])  # (B, Te)
        np3 = nees(err[i][:, e_ok], raw["cov"][i][:, e_ok, :3, :3])
        a, a3 = nv.mean(axis=0), np3.mean(axis=0)
        anees[m] = {"dof": 6, "mean": float(a.mean()), "median": float(np.median(a)),
                    "bounds_99_one_epoch": [lo, hi], "fraction_of_epochs_inside": float(np.mean((a >= lo) & (a <= hi))),
                    "consistent": bool(lo <= a.mean() <= hi),
                    "position_only": {"dof": 3, "mean": float(a3.mean()), "bounds_99_one_epoch": [lo3, hi3],
                                      "fraction_of_epochs_inside": float(np.mean((a3 >= lo3) & (a3 <= hi3)))},
                    "epochs": int(e_ok.sum()), "trials": B, "per_epoch": a, "per_epoch_t_s": t_rel[e_ok]}

    # continuity of the fused track: an estimate at every epoch from its first one
    fi = modes.index("fused")
    got = raw["count"][fi] > 0  # (B, T)
    first = np.argmax(got, axis=1)
    missing, max_gap = 0, 0.0
    for b in range(B):
        g = got[b, first[b]:]
        missing += int((~g).sum())
        idx = np.flatnonzero(got[b])
        if idx.size > 1:
            max_gap = max(max_gap, float(np.max(np.diff(idx)) * scn.dt_s))
    dup = int((raw["count"][fi] > 1).sum())
    first_s = (first * scn.dt_s).tolist()
    reached = np.any(gr_km >= scn.max_range_km, axis=1)
    t_reach = [float(t_rel[np.argmax(g >= scn.max_range_km)]) if r else None for g, r in zip(gr_km, reached)]
    out = {
        "by_range_km": bins,
        "fused_below_both_in_every_bin": bool(filled and all(b["fused_below_both"] for b in filled)),
        "during_radar_loss": episode(*scn.radar_loss_s),
        "during_gnss_outage": episode(*scn.gnss_outage_s),
        "anees": anees,
        "continuity": {"fused_estimate_every_epoch": bool(missing == 0 and dup == 0), "missing_epochs": missing,
                       "duplicate_epochs": dup, "max_gap_s": max_gap, "first_estimate_s": first_s},
        "flight": {"reached_max_range": [bool(r) for r in reached], "time_to_max_range_s": t_reach,
                   "all_reach_max_range": bool(reached.all()), "max_ground_range_km": gr_km.max(axis=1).tolist(),
                   "burst_alt_m": raw["burst_alt_m"].tolist(),
                   "burst_time_s": [float(t_rel[np.argmax(p == 1)]) if (p == 1).any() else None for p in raw["phase"]]},
    }
    out["overall_rmse_m"] = {m: _rmse(e2[i][common & inside]) for i, m in enumerate(modes)}
    with np.errstate(invalid="ignore"):
        w = (common & inside).sum(axis=0)
        out["series"] = {"t_s": t_rel, "rms_error_m": {m: np.where(w > 0, np.sqrt(
            np.where(common & inside, e2[i], 0.0).sum(axis=0) / np.maximum(w, 1)), np.nan) for i, m in enumerate(modes)}}
    return out


def integrity_summary(raw: dict, sc: dict, scn: SondeScenario) -> dict | None:
    """The integrity monitor's part of the result: events on the bus by tracker and kind, by
    channel kind (relayed satellite / radar axis), the first ones, and with ``integrity="compare"``
    each main mode's RMSE without and with the monitor on the same messages."""
    if scn.integrity == "off":
        return None
    ev = raw.get("integrity_events", [])
    by_tracker: dict = {}
    by_channel: dict = {}
    for t, src, ch, kind, stat in ev:
        tr = src.removeprefix("sonde_tracker.").removesuffix(".integrity")
        d = by_tracker.setdefault(tr, {})
        d[kind] = d.get(kind, 0) + 1
        part = ch.split(".", 1)[1] if "." in ch else ch  # drop the sonde id
        key = f"{tr}:{part}:{kind}"
        by_channel[key] = by_channel.get(key, 0) + 1
    out = {"mode": scn.integrity, "config": dict(SONDE_INTEGRITY), "events": len(ev), "by_tracker": by_tracker,
           "by_channel": dict(sorted(by_channel.items(), key=lambda kv: -kv[1])[:40]),
           "first_events": [{"t_s": t, "source": src, "channel": ch, "event": kind,
                             "statistic": None if not math.isfinite(stat) else stat}
                            for t, src, ch, kind, stat in ev[:20]],
           "fault_relay_step_sat": raw.get("fault_relay_step_sat")}
    if scn.integrity == "compare":
        r = sc["overall_rmse_m"]
        out["overall_rmse_m"] = {m: {"without_monitor": r[m], "with_monitor": r.get(m + MONITORED)} for m in MODES}
    return out
