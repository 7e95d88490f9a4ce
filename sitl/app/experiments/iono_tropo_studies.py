"""Seed 000 studies on top of the three-variant runner (sitl/app/experiments/iono_tropo_filters.py).

* :func:`adaptive_q_study` -- what the adaptive process noise of eq 7 does. The same
  simulated data (same seed) run with eq 7 off, with eq 7 on every state as in the seed
  ("all", the paper's filter), and with eq 7 on the dynamic states only ("dynamic":
  position, velocity, clock bias and drift; Delta_A, I_g, U_g, K_j are constants), each
  with the clock modelled right and with a mismodelled clock (the simulated clock's N_eps
  ``clock_scale`` times the filter's). Scores: time to 1 m, final errors, ANEES of the
  (I_g, U_g) block and of the clock (bias, drift) block.
* :func:`ordering_study` -- time to 1 m of the three variants over many seeds; the
  ordering variant 3 < variant 2 < variant 1 is checked seed by seed.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from sitl.app.experiments.iono_tropo_filters import IonoTropoScenario, run_streamed

VARIANT_NAMES = {1: "code_doppler", 2: "phase_increments", 3: "carrier_phase"}
ADAPTIVE_CONFIGS = {
    "off": {"adaptive_q": False},
    "eq7_all_states": {"adaptive_q": True, "adaptive_q_scope": "all"},
    "eq7_dynamic_states": {"adaptive_q": True, "adaptive_q_scope": "dynamic"},
}


def _finite_or_none(v):
    v = float(v)
    return v if math.isfinite(v) else None


def _row(res) -> dict:
    ttm = np.asarray(res["time_to_1m_s_per_trial"], dtype=float)
    return {
        "time_to_1m_s": _finite_or_none(res["time_to_1m_s"]),
        "never_within_1m": int(np.sum(~np.isfinite(ttm))),
        "final_error_m": {k: float(v) for k, v in res["final_error_m"].items()},
        "anees": float(res["anees"]),
        "anees_clock": float(res["anees_clock"]),
        "anees_bounds_99_one_epoch": [float(b) for b in res["anees_bounds_99_one_epoch"]],
        "wall_s": float(res["wall_s"]),
    }


def adaptive_q_study(base: IonoTropoScenario, trials: int, seed: int, variants=(1, 2), clock_scale=1e3,
                     progress=None, backend=None) -> dict:
    """Rows {variant, config, clock, ...scores} over configs x {nominal, mismodelled} clocks."""
    if not clock_scale > 1.0:
        raise ValueError(f"clock_scale must be > 1 (a clock noisier than modelled), got {clock_scale!r}")
    rows = []
    for v in variants:
        for clock, scale in (("nominal", 1.0), ("mismodelled", float(clock_scale))):
            for name, kw in ADAPTIVE_CONFIGS.items():
                scn = dataclasses.replace(base, truth_clock_psd_scale=scale, **kw)
                res = run_streamed(scn, trials, seed, variant=v, backend=backend)
                row = {"variant": VARIANT_NAMES[v], "config": name, "clock": clock, "truth_clock_psd_scale": scale,
                       **_row(res)}
                rows.append(row)
                if progress:
                    t = row["time_to_1m_s"]
                    progress(f"adaptive-q study: {VARIANT_NAMES[v]:<16} {clock:<11} {name:<19} time to 1 m "
                             f"{'never' if t is None else f'{t:7.1f} s'}  ANEES atmo {row['anees']:.2f} "
                             f"clock {row['anees_clock']:.3g}  ({row['wall_s']:.0f} s)", done=len(rows),
                             total=len(variants) * 2 * len(ADAPTIVE_CONFIGS))
    return {"trials": trials, "seed": seed, "clock_scale": float(clock_scale), "rows": rows}


def ordering_study(base: IonoTropoScenario, seeds, trials: int, progress=None, backend=None) -> dict:
    """Median time to 1 m per variant for each seed, and whether 3 < 2 < 1 holds for it."""
    per_seed = []
    pooled = {name: [] for name in VARIANT_NAMES.values()}
    for s in seeds:
        ttm = {}
        for v in (1, 2, 3):
            res = run_streamed(base, trials, int(s), variant=v, backend=backend)
            ttm[VARIANT_NAMES[v]] = float(res["time_to_1m_s"])
            pooled[VARIANT_NAMES[v]].append(np.asarray(res["time_to_1m_s_per_trial"], dtype=float))
        a, b, c = ttm["carrier_phase"], ttm["phase_increments"], ttm["code_doppler"]
        holds = bool(a < b < c) or bool(a < b and math.isinf(c))
        per_seed.append({"seed": int(s), "time_to_1m_s": {k: _finite_or_none(v) for k, v in ttm.items()},
                         "ordering_holds": holds})
        if progress:
            progress(f"ordering study: seed {s:3d}  variant 1 {c:7.1f} s  variant 2 {b:7.1f} s  variant 3 "
                     f"{a:6.1f} s  {'3 < 2 < 1' if holds else 'ORDER BROKEN'}", done=len(per_seed), total=len(seeds))
    # pooled over seeds and trials; the variants see the same data trial by trial, so the
    # paired comparison (fraction of trials where one settles strictly first) is the sharp test
    t1, t2, t3 = (np.concatenate(pooled[n]) for n in ("code_doppler", "phase_increments", "carrier_phase"))
    pooled_median = {n: _finite_or_none(np.median(np.concatenate(pooled[n]))) for n in pooled}
    m1, m2, m3 = (np.median(q) for q in (t1, t2, t3))
    return {"trials_per_seed": trials, "seeds": [int(s) for s in seeds], "per_seed": per_seed,
            "holds_for": int(sum(r["ordering_holds"] for r in per_seed)), "of": len(per_seed),
            "pooled_median_time_to_1m_s": pooled_median,
            "pooled_ordering_holds": bool(m3 < m2 < m1 or (m3 < m2 and math.isinf(m1))),
            "paired_fraction": {"variant2_before_variant1": float(np.mean(t2 < t1)),
                                "variant3_before_variant2": float(np.mean(t3 < t2)),
                                "variant3_before_variant1": float(np.mean(t3 < t1))},
            "trials_total": int(t1.size)}


def adaptive_q_table(study: dict) -> str:
    head = (f"{'variant':<17} {'clock':<12} {'eq 7':<19} {'time to 1 m':>11} {'never':>5} {'final I_g':>9} "
            f"{'U_g':>6} {'ANEES atmo':>10} {'ANEES clock':>11}")
    lines = [head, "-" * len(head)]
    for r in study["rows"]:
        t = r["time_to_1m_s"]
        lines.append(f"{r['variant']:<17} {r['clock']:<12} {r['config']:<19} "
                     f"{'never' if t is None else f'{t:9.1f} s':>11} {r['never_within_1m']:>5d} "
                     f"{r['final_error_m']['iono_zenith']:9.3f} {r['final_error_m']['tropo_zenith']:6.3f} "
                     f"{r['anees']:10.3f} {r['anees_clock']:11.4g}")
    lo, hi = study["rows"][0]["anees_bounds_99_one_epoch"]
    lines.append(f"mismodelled clock: simulated N_eps = {study['clock_scale']:g} x the filter's; ANEES 99 % "
                 f"one-epoch band {lo:.3f}..{hi:.3f} (1 = consistent)")
    return "\n".join(lines)


def plot_adaptive_q(study: dict, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = study["rows"]
    variants = list(dict.fromkeys(r["variant"] for r in rows))
    configs = list(ADAPTIVE_CONFIGS)
    fig, axes = plt.subplots(2, len(variants), figsize=(5.5 * len(variants), 7), squeeze=False)
    width = 0.38
    for j, v in enumerate(variants):
        for i, (key, label, log) in enumerate((("time_to_1m_s", "median time to 1 m, s", False),
                                               ("anees_clock", "ANEES of the clock block (1 = consistent)", True))):
            ax = axes[i, j]
            for c_i, clock in enumerate(("nominal", "mismodelled")):
                vals = []
                for cfg in configs:
                    r = next(r for r in rows if r["variant"] == v and r["config"] == cfg and r["clock"] == clock)
                    val = r[key]
                    vals.append(np.nan if val is None else val)
                xs = np.arange(len(configs)) + (c_i - 0.5) * width
                bars = ax.bar(xs, [0 if np.isnan(q) else q for q in vals], width,
                              label=f"clock {clock}" + (f" (N_eps x{study['clock_scale']:.0e})" if c_i else ""))
                ax.bar_label(bars, labels=["" if np.isnan(q) else (f"{q:.0f}" if not log else f"{q:.3g}")
                                           for q in vals], fontsize=7, padding=1)
                for b, q in zip(bars, vals):
                    if np.isnan(q):
                        ax.annotate("never", (b.get_x() + b.get_width() / 2, 0), ha="center", va="bottom",
                                    fontsize=8)
            ax.set_xticks(np.arange(len(configs)), ["eq 7 off", "eq 7, all states\n(the seed)",
                                                     "eq 7, dynamic\nstates only"])
            ax.set_ylabel(label)
            if log:
                ax.set_yscale("log")
                ax.axhline(1.0, color="k", lw=0.8, ls="--")
            if i == 0:
                ax.set_title(f"{v}")
                paper = {"code_doppler": 500.0, "phase_increments": 350.0}.get(v)
                if paper:
                    ax.axhline(paper, color="k", lw=0.8, ls=":", label=f"paper ~{paper:.0f} s")
            lo_, hi_ = ax.get_ylim()
            ax.set_ylim(lo_, hi_ * (8.0 if log else 1.35))  # room for the legend above the bars
            ax.legend(fontsize=8, loc="upper left")
    from sitl.app.experiments.common import run_label

    fig.suptitle(run_label("iono-tropo adaptive-Q study", paper="000", seed=study["seed"], trials=study["trials"])
                 + "\nadaptive process noise (the paper's eq 7)")
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight", pad_inches=0.1)
    plt.close(fig)


def plot_ordering(study: dict, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seeds = [r["seed"] for r in study["per_seed"]]
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for name, label in (("code_doppler", "variant 1: code + Doppler"), ("phase_increments", "variant 2: + CMC increments"),
                        ("carrier_phase", "variant 3: + carrier phase")):
        vals = [r["time_to_1m_s"][name] for r in study["per_seed"]]
        ax.plot(seeds, [np.nan if q is None else q for q in vals], "o-", label=label)
    ax.set_yscale("log")
    ax.set_xlabel("RNG seed")
    ax.set_xticks(seeds if len(seeds) <= 30 else ax.get_xticks())
    ax.set_ylabel(f"median time to 1 m over {study['trials_per_seed']} trials, s (log scale)")
    pm = study["pooled_median_time_to_1m_s"]
    from sitl.app.experiments.common import run_label

    ax.set_title(run_label("iono-tropo ordering study", paper="000", seed=f"{seeds[0]}-{seeds[-1]}",
                           trials=study["trials_per_seed"], extra="per seed") + "\n"
                 f"median of each seed; 3 < 2 < 1 holds for {study['holds_for']} of {study['of']} seeds\n"
                 f"pooled medians over {study['trials_total']} trials: v1 {pm['code_doppler']} s, "
                 f"v2 {pm['phase_increments']} s, v3 {pm['carrier_phase']} s", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight", pad_inches=0.1)
    plt.close(fig)
