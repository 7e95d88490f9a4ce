"""What the seed 003 integrity run writes and prints: the targets met, result.json, the ROC and
position-error figures, the summary lines."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from sitl.app.experiments.common import run_label, save_figure, strict
from sitl.app.experiments.integrity.monte_carlo import FILTERS
from sitl.app.experiments.integrity.scoring import TARGETS

__all__ = ["FIGURES", "targets_check", "result_document", "plot", "summary"]

FIGURES = ("integrity_roc.png", "integrity_position_error.png")


def targets_check(res: dict) -> dict:
    det = res.get("detection")
    out = {}
    if det:
        st, rp = det["step"], det["ramp"]
        out["step_pd_ge_0.99"] = st["pd"]["value"] >= TARGETS["pd_min"]
        out["ramp_pd_ge_0.99_within_10s"] = rp["pd"]["value"] >= TARGETS["pd_min"]
        if rp.get("oracle"):  # can any detector meet it on these ramps?
            out["ramp_pd_ge_0.99_possible_at_all"] = rp["oracle"]["pd"] >= TARGETS["pd_min"]
        out["pfa_le_0.003"] = st["pfa"]["value"] <= TARGETS["pfa_max"]
    r = res["rmse_ratio"]
    out["adaptive_robust_cuts_rmse_more_than_2x"] = r["plain_over_adaptive_robust"] > 2.0
    out["with_bias_estimation_ratio"] = r["plain_over_adaptive_robust_with_bias_estimation"]
    for key, ff in res.get("fault_free", {}).items():
        d = ff["paired_difference_m"]
        if d["upper_95"] is None:
            continue
        # not significantly worse (one-sided 95 %) and non-inferior within 2 % of the RMSE
        out[f"fault_free_{key}_monitor_not_significantly_worse"] = d["mean"] - 1.645 * d["standard_error"] <= 0.0
        out[f"fault_free_{key}_monitor_noninferior_2pct"] = \
            d["upper_95"] <= 0.02 * ff["position_rmse_m"]["without_monitor"]
    return out


def result_document(scn, trials, seed, res, figures) -> dict:
    keep = ("trials", "seed", "epochs", "channels", "sat_ids", "position_rmse_m", "rmse_ratio", "exclusions",
            "detection", "detection_by_filter", "fault_free", "fault_onsets_trial0_s", "missing_by_mask", "wall_s")
    doc = {"experiment": "integrity", "schema": None, "scenario": dataclasses.asdict(scn),
           "monitor_config": dataclasses.asdict(scn.monitor_config()), "sigma_ref_m": scn.sigma_ref_m}
    doc.update({k: res[k] for k in keep if k in res})
    if "roc" in res:  # thinned to keep the file small
        doc["roc"] = {f: {kind: {kk: (np.asarray(v)[::10] if isinstance(v, np.ndarray) else v) for kk, v in c.items()}
                          for kind, c in r.items()} for f, r in res["roc"].items()}
    doc["targets"] = TARGETS
    doc["targets_met"] = targets_check(res)
    doc["paper"] = {"adaptive_robust_rmse_cut": "more than 2x", "with_bias_estimation": "about 10x (an order of magnitude)"}
    doc["figures"] = [Path(f).name for f in figures]
    return strict(doc)


def plot(res: dict, scn, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    sub = run_label("integrity", paper="003", seed=res["seed"], trials=res["trials"],
                    extra=f"{scn.duration_s:g} s at {1 / scn.dt_s:g} Hz, {res['channels']} satellites")
    # ROC
    fig, axes = plt.subplots(1, 3, figsize=(15, 5), constrained_layout=True)
    if "roc" in res:
        for ax, kind in zip(axes, ("step", "ramp", "outlier")):
            for name, ls in (("adaptive_robust", "-"), ("adaptive_robust_with_bias_estimation", "--")):
                c = res["roc"][name][kind]
                if c["pd"] is None:
                    continue
                pfa = np.maximum(np.asarray(c["pfa"], dtype=float), 1e-8)
                ax.plot(pfa, c["pd"], ls, label=name.replace("_", " "))
                i = int(np.argmin(np.abs(np.asarray(c["threshold"]) - c["operating_threshold"])))
                ax.plot(pfa[i], c["pd"][i], "o", ms=8, mfc="none", mew=2, color=ax.lines[-1].get_color(),
                        label=f"operating point (threshold {c['operating_threshold']:g})")
            orc = res.get("detection", {}).get("ramp", {}).get("oracle") if kind == "ramp" else None
            if orc:
                ax.plot(orc["pfa_per_epoch"], orc["pd"], "*", ms=12, color="k",
                        label=f"bound: oracle knowing the onset ({orc['pd']:.3f})")
            ax.axvline(TARGETS["pfa_max"], color="k", ls=":", lw=1, label=f"Pfa target {TARGETS['pfa_max']:g}")
            ax.axhline(TARGETS["pd_min"], color="0.5", ls=":", lw=1, label=f"Pd target {TARGETS['pd_min']:g}")
            ax.set_xscale("log")
            ax.set_xlim(1e-7, 1)
            ax.set_ylim(0, 1.02)
            ax.set_xlabel("false-alarm probability per channel-epoch\n(this statistic alone; log scale)")
            ax.set_ylabel("probability of detection, 1")
            ax.set_title({"step": "steps (|beta|, onset or next epoch)", "ramp": f"ramps (window statistic, within "
                          f"{scn.ramp_detect_s:g} s)", "outlier": "outliers >= 5 sigma (|beta|, at the epoch)"}[kind],
                         fontsize=10)
            ax.grid(alpha=0.3, which="both")
            ax.legend(fontsize=7, loc="lower right")
    fig.suptitle(f"{sub}\nintegrity monitor: ROC per fault kind (Pd over the faults of all trials)")
    files.append(save_figure(fig, out / FIGURES[0]))
    # position error vs time, trial 0
    fig, ax = plt.subplots(figsize=(11, 5), constrained_layout=True)
    t = res["t_s"]
    for name in FILTERS:
        ax.plot(t, res["position_error_trial0_m"][name], lw=1.0,
                label=f"{name.replace('_', ' ')} (RMSE all trials {res['position_rmse_m'][name]:.2f} m)")
    fo = res.get("fault_onsets_trial0_s")
    if fo:
        ax.axvline(fo["step"], color="r", ls="--", lw=1, label=f"step onset (sat ch {fo['step_channel']}, "
                   f"{fo['step_sigma']:+.1f} sigma)")
        ax.axvline(fo["step_end"], color="r", ls=":", lw=1, label="step end")
        ax.axvline(fo["ramp"], color="m", ls="--", lw=1, label=f"ramp onset (ch {fo['ramp_channel']}, "
                   f"{fo['ramp_rate_m_s']:+.2f} m/s)")
    ax.axvline(scn.warmup_s, color="0.5", ls=":", lw=1, label="end of warm-up (scoring starts)")
    ax.set_yscale("log")
    ax.set_xlabel("time since the run's start, s")
    ax.set_ylabel("3-D position error of trial 0, m (log scale)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    ax.set_title(f"{sub}\nposition error of the three filters on the same faulty data, trial 0", fontsize=10)
    files.append(save_figure(fig, out / FIGURES[1]))
    return files


def summary(res: dict) -> str:
    lines = []
    r = res["position_rmse_m"]
    lines.append("position RMSE: " + ", ".join(f"{n} {v:.2f} m" for n, v in r.items()))
    q = res["rmse_ratio"]
    lines.append(f"ratios: plain / adaptive-robust {q['plain_over_adaptive_robust']:.2f}x, plain / with bias "
                 f"estimation {q['plain_over_adaptive_robust_with_bias_estimation']:.2f}x (paper: > 2x, ~10x)")
    for name, det in res.get("detection_by_filter", {}).items():
        parts = []
        for kind in ("step", "ramp", "outlier"):
            d = det[kind]
            lo, hi = d["pd"]["ci95"]
            md = d["mean_delay_s"]
            parts.append(f"{kind} Pd {d['pd']['value']:.4f} [{lo:.4f}, {hi:.4f}] delay "
                         f"{'-' if md is None else f'{md:.2f} s'}")
        p = det["step"]["pfa"]
        lines.append(f"{name}: " + "; ".join(parts) + f"; Pfa {p['value']:.2e} [{p['ci95'][0]:.2e}, {p['ci95'][1]:.2e}]")
    orc = res.get("detection", {}).get("ramp", {}).get("oracle")
    if orc:
        lines.append(f"ramp bound (oracle that knows the onset, Pfa {orc['pfa_per_epoch']:g} per epoch): Pd "
                     f"{orc['pd']:.4f} on these ramps; " + ", ".join(f"{k} m/s {v:.4f}" for k, v in
                                                                      orc["by_rate_m_s"].items() if v is not None)
                     + "; at " + ", ".join(f"{k} m/s {v:.3f}" for k, v in orc["pd_at_rate_m_s"].items()))
    for key, ff in res.get("fault_free", {}).items():
        d = ff["paired_difference_m"]
        lines.append(f"fault-free ({key}): without monitor {ff['position_rmse_m']['without_monitor']:.3f} m, with "
                     f"{ff['position_rmse_m']['with_monitor']:.3f} m; paired difference {d['mean']:+.4f} +- "
                     f"{d['standard_error']:.4f} m; monitor Pfa {ff['pfa']['value']:.2e}")
    lines.append(f"wall {res['wall_s']:.1f} s")
    return "\n".join(lines)
