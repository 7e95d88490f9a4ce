"""The beacon experiment's figures."""
from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np

from sitl.app.experiments.beacon.constants import AXES, AXIS_ECEF, FIGURES, PAPER_ERRORS_M, PRODUCTION, SETTLE_S
from sitl.app.experiments.beacon.scoring import _truth3
from sitl.app.experiments.common import run_label, save_figure


def plot(out: Path, cases: dict, sweep: list, meta: str, geometry: str = "printed", *, seed=None,
         trials=None) -> list[Path]:
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    head = run_label("beacon", paper="002", seed=seed, trials=trials)
    files = []
    # a) error per ECEF axis over time, trial 0 and the RMS over trials, the paper's band of each axis;
    # linear axes scaled to the scored epochs (after SETTLE_S); the blind start's larger errors are
    # clipped and their size printed on the panel
    fig, axes = plt.subplots(3, len(cases), figsize=(6.5 * len(cases), 9), sharex=True, squeeze=False,
                             constrained_layout=True)
    for c, (case, d) in enumerate(cases.items()):
        t, x, truth = d["t"], d["x"], d["truth"]
        e = x[..., 0:3] - _truth3(truth)[..., 0:3]
        n_trials = e.shape[1]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            rms = np.sqrt(np.nanmean(e ** 2, axis=1))
        scored = t >= SETTLE_S
        for row, ax_name in enumerate(AXES):
            a = AXIS_ECEF[ax_name]  # the paper's axis -> its ECEF component
            ax = axes[row, c]
            lim = PAPER_ERRORS_M[ax_name]
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                peak = float(np.nanmax(np.abs(np.concatenate([rms[scored, a], e[scored, 0, a]])))) if scored.any() else lim
                early = float(np.nanmax(np.abs(np.concatenate([rms[~scored, a], e[~scored, 0, a]])))) if (~scored).any() else 0.0
            ylim = max(2.0 * lim, 1.15 * (peak if math.isfinite(peak) else lim))
            ax.axhspan(-lim, lim, color="C2", alpha=0.25, lw=0,
                       label="paper's bound on this axis (xi +-25 m, eta +-9 m, zeta +-15 m)")
            ax.fill_between(t, -rms[:, a], rms[:, a], color="C0", alpha=0.15, lw=0,
                            label=f"+- RMS error over the {n_trials} trials")
            ax.plot(t, e[:, 0, a], color="C0", lw=0.9, label="error of trial 0")
            ax.axvline(SETTLE_S, color="0.5", ls=":", lw=0.8, label=f"scored from {SETTLE_S:g} s (blind start before)")
            ax.set_ylim(-ylim, ylim)
            ax.text(0.995, 0.97, f"band +-{lim:g} m", transform=ax.transAxes, ha="right", va="top", fontsize=8,
                    color="C2")
            if math.isfinite(early) and early > ylim:
                ax.text(0.005, 0.97, f"before {SETTLE_S:g} s: up to {early:,.0f} m (clipped)", transform=ax.transAxes,
                        ha="left", va="top", fontsize=7, color="0.3")
            ax.set_ylabel(f"{ax_name} (= ECEF {'xyz'[a]}) error, m")
            ax.grid(alpha=0.3)
        axes[0, c].set_title(case.replace("_", " "), fontsize=10)
        axes[-1, c].set_xlabel("time since the run's start, s")
    h, lab = axes[0, 0].get_legend_handles_labels()
    fig.legend(h, lab, loc="outside lower center", ncol=2, fontsize=8)
    fig.suptitle(f"{head}\nbeacon position error per paper axis (xi, eta, zeta = ECEF y, z, x), linear scale\n{meta}")
    files.append(save_figure(fig, out / FIGURES[0]))

    # b) RMSE vs PCRB over time
    fig, axes = plt.subplots(1, len(cases), figsize=(6.5 * len(cases), 4.8), squeeze=False, constrained_layout=True)
    for c, (case, d) in enumerate(cases.items()):
        ax = axes[0, c]
        t = d["t"]
        ax.plot(t, d["rmse_series"], color="C0", lw=1.4, label=f"decomposed locator ({PRODUCTION}): RMSE over trials")
        if d.get("central_series") is not None:
            ax.plot(t, d["central_series"], color="C1", lw=1.1, label="centralised filter: RMSE over trials")
        if d.get("ignore_series") is not None:
            ax.plot(t, d["ignore_series"], color="C3", lw=0.9, ls="--", label="locator ignoring the UAVs' nav error: RMSE")
        ax.plot(t, d["sigma_series"], color="C0", lw=0.8, ls=":", label="locator's own 1-sigma (sqrt trace P_pos, RMS over trials)")
        ax.plot(t, d["pcrb_series"], color="k", lw=1.4, label="sqrt PCRB (centralised, true states)")
        ax.axhline(math.sqrt(sum(v * v for v in PAPER_ERRORS_M.values())), color="C2", lw=1.0, ls="-.",
                   label="paper's bands as a 3-D figure (30 m)")
        ax.set_yscale("log")
        ax.set_xlabel("time since the run's start, s")
        ax.set_ylabel("3-D position error, m (log scale)")
        ax.set_title(case.replace("_", " "), fontsize=10)
        ax.grid(alpha=0.3, which="both")
    h, lab = axes[0, 0].get_legend_handles_labels()
    fig.legend(h, lab, loc="outside lower center", ncol=3, fontsize=8)
    fig.suptitle(f"{head}\nbeacon 3-D position RMSE over trials against the posterior Cramer-Rao bound (sqrt PCRB)\n{meta}")
    files.append(save_figure(fig, out / FIGURES[1]))

    # c) RMSE and PCRB vs number of UAVs
    fig, ax = plt.subplots(figsize=(6.5, 4.8), constrained_layout=True)
    if sweep:
        n = [s["uavs"] for s in sweep]
        ax.plot(n, [s["rmse_m"] for s in sweep], "o-", color="C0", label=f"locator RMSE (after {SETTLE_S:g} s, RMS over trials)")
        ax.plot(n, [s["pcrb_m"] for s in sweep], "s--", color="k", label="sqrt PCRB (centralised)")
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
    ax.set_xlabel("number of UAVs (log scale)")
    ax.set_ylabel("3-D beacon position error, m (log scale)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    sweep_trials = sweep[0]["trials"] if sweep else 0
    ax.set_title(f"{run_label('beacon', paper='002', seed=None if seed is None else f'{seed} + 1000 + N', trials=sweep_trials)}\n"
                 "GPS constellation: accuracy against the number of UAVs (RMSE and sqrt PCRB after "
                 f"{SETTLE_S:g} s)\n"
                 + ("printed geometry: every UAV from the printed point,\nfurther UAVs' laws spread over the printed "
                    "coefficients" if geometry == "printed" else
                    "geodetic geometry: 3 UAVs on the seed's line;\nmore: spread in two dimensions"), fontsize=9)
    files.append(save_figure(fig, out / FIGURES[2]))
    return files
