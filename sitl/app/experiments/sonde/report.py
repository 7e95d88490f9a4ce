"""The sonde experiment's result document (result.json), its figures and its summary table, and
the bus path's per-message cost the document reports."""
from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import numpy as np

from sitl.app.experiments.common import run_label, save_figure, strict
from sitl.app.experiments.sonde.scenario import COLORS, FIGURES, LABELS, MODES, WHITE_MODES, SondeScenario
from sitl.app.experiments.sonde.scoring import integrity_summary


def bus_costs(examples: dict, rounds: int = 200) -> dict:
    """Per-message cost (us, best of 3 x ``rounds``) of the bus path for one example of each
    kind: building the message (the schema's validation), encoding, and decoding (which
    validates again) -- what every message of the run pays."""
    from sitl.bus import decode, encode

    out = {}
    for kind, msg in examples.items():
        if msg is None:
            continue
        cls = type(msg)
        kw = {f: getattr(msg, f) for f in ("t_gps_s", "source_id", "seq")}
        kw.update({s.name: getattr(msg, s.name) for s in cls.FIELDS})
        wire = encode(msg)
        best = {"build": math.inf, "encode": math.inf, "decode": math.inf}
        calls = (("build", lambda c=cls, k=kw: c(**k)), ("encode", lambda m=msg: encode(m)),
                 ("decode", lambda w=wire: decode(w)))
        for _ in range(3):
            for name, fn in calls:
                t0 = time.perf_counter()
                for _ in range(rounds):
                    fn()
                best[name] = min(best[name], (time.perf_counter() - t0) / rounds * 1e6)
        out[kind] = {**{k: round(v, 1) for k, v in best.items()}, "total_us": round(sum(best.values()), 1),
                     "bytes": len(wire)}
    return out


def result_document(scn, seed: int, raw: dict, sc: dict, figures, wall_s: float, one_trial_wall_s) -> dict:
    anees = {m: ({k: v for k, v in a.items() if not k.startswith("per_epoch")} if a else None)
             for m, a in sc["anees"].items()}
    main = {m: anees[m] for m in MODES}
    comparison = None
    if scn.white_baseline:
        comparison = {
            "note": "naive: radar AR(1) errors taken as white (R = sigma^2); colored: the errors are states",
            "anees": {"colored": {m: anees[m] for m in ("fused", "radar_only")},
                      "white": {m.removesuffix("_white"): anees[m] for m in WHITE_MODES}},
            "overall_rmse_m": {"colored": {m: sc["overall_rmse_m"][m] for m in ("fused", "radar_only")},
                               "white": {m.removesuffix("_white"): sc["overall_rmse_m"][m] for m in WHITE_MODES}},
        }
    timing = dict(raw["timing_s"])
    nmsg = raw["bus"]["delivered"]
    costs = bus_costs(raw.get("examples", {}))
    kinds = raw["bus"]["messages_by_kind"]
    implied = sum(kinds.get(k, 0) * c["total_us"] for k, c in costs.items()) * 1e-6
    bus_s = timing["publish"] + timing["deliver"] + timing["estimates_delivery"]
    doc = {
        "experiment": "sonde", "schema": None, "seed": seed, "trials": len(raw["trials"]),
        "scenario": dataclasses.asdict(scn), "epochs": scn.n_epochs,
        "by_range_km": sc["by_range_km"],
        "fused_below_both_in_every_bin": sc["fused_below_both_in_every_bin"],
        "during_radar_loss": sc["during_radar_loss"], "during_gnss_outage": sc["during_gnss_outage"],
        "anees": main, "radar_noise_comparison": comparison,
        "continuity": sc["continuity"], "flight": sc["flight"], "overall_rmse_m": sc["overall_rmse_m"],
        "tracker_counters": raw["counters"], "bus": raw["bus"],
        "integrity": integrity_summary(raw, sc, scn),
        "wall_s": wall_s, "wall_s_per_trial": wall_s / max(1, len(raw["trials"])),
        "one_trial_wall_s": one_trial_wall_s,
        "timing_s": {**timing, "bus_total": bus_s, "messages_delivered": nmsg,
                     "bus_s_per_message": bus_s / nmsg if nmsg else None},
        "bus_cost_per_message_us": costs,
        "bus_cost_implied_s": implied,
        "bus_cost_note": "build + encode + decode of every message of the run at the measured per-kind cost "
                         "(the Estimates are built and published inside the trackers' time)",
        "figures": [Path(f).name for f in figures],
    }
    return strict(doc)


def _shade(ax, scn):
    a, b = scn.radar_loss_s
    ax.axvspan(a, b, color="C0", alpha=0.12, lw=0, label=f"radar angle tracking lost ({a:g}-{b:g} s)")
    a, b = scn.gnss_outage_s
    ax.axvspan(a, b, color="C2", alpha=0.15, lw=0, label=f"GNSS outage ({a:g}-{b:g} s)")


def plot(raw: dict, sc: dict, scn: SondeScenario, seed: int, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    B = len(raw["trials"])
    filt = "EKF (UKF where needed)" if scn.filter == "auto" else scn.filter.upper()
    sub = run_label("sonde", paper="004", seed=seed, trials=B,
                    extra=f"{scn.duration_s:g} s at {1 / scn.dt_s:g} Hz, {filt}")
    files = []
    t = sc["series"]["t_s"]
    # a) error against time
    fig, ax = plt.subplots(figsize=(11, 6), constrained_layout=True)
    _shade(ax, scn)
    for m in ("radar_only", "relay_only", "fused"):  # fused last: on top of relay-only, which it hugs
        ax.plot(t, sc["series"]["rms_error_m"][m], color=COLORS[m], lw=1.0 if m != "fused" else 0.9,
                ls="-" if m != "fused" else (0, (4, 2)), label=LABELS[m])
    ax.set_yscale("log")
    ax.set_xlabel("time since launch, s")
    ax.set_ylabel("3-D position error, m (RMS over trials, log scale)")
    ax.set_xlim(0, scn.duration_s)
    ax.grid(alpha=0.3, which="both")
    ax2 = ax.twinx()
    gr = np.nanmean(raw["ground_range_m"], axis=0) / 1e3
    ax2.plot(t, gr, color="0.5", lw=0.8, ls="--", label="mean ground range (right axis)")
    ax2.set_ylabel("ground range, km")
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, loc="upper left", fontsize=8)
    ax.set_title(f"{sub}\nradiosonde position error against time (epochs inside {scn.max_range_km:g} km)")
    files.append(save_figure(fig, out / FIGURES[0]))

    # b) RMSE against ground range, and the same-data gain of fused over relay-only
    fig, (ax, axg) = plt.subplots(2, 1, figsize=(10, 8), sharex=True, constrained_layout=True,
                                  gridspec_kw={"height_ratios": [2.2, 1]})
    bins = [b for b in sc["by_range_km"] if b["n"] > 0]
    centres = np.array([b["range_km"] + scn.bin_km / 2 for b in bins])
    order = [m for m in raw["modes"] if m in WHITE_MODES] + ["radar_only", "relay_only", "fused"]
    for m in order:
        y = np.array([np.nan if b["rmse_m"][m] is None else b["rmse_m"][m] for b in bins])
        white = m in WHITE_MODES
        ax.plot(centres, y, marker="s" if m == "fused" else "o", ms=4 if m == "fused" else 6,
                ls=":" if white else ("--" if m == "fused" else "-"), color=COLORS[m], label=LABELS[m],
                lw=1.0 if white else 1.6, zorder=5 if m == "fused" else 3)
        if m == "fused":
            for c, v in zip(centres, y):
                ax.annotate(f"{v:.2f}", (c, v), xytext=(5, -12), textcoords="offset points", ha="left",
                            fontsize=7, color=COLORS[m])
    ax.set_yscale("log")
    ax.set_ylabel("3-D position RMSE, m (log scale)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="center left")
    ax.set_title(f"{sub}\nposition RMSE against ground range ({scn.bin_km:g} km bins, all trials pooled)")
    import scipy.stats

    t95 = float(scipy.stats.t.ppf(0.975, B - 1)) if B >= 2 else math.nan
    gains, errs = [], []
    for b in bins:
        p = b.get("fused_vs_relay_only")
        r = b["rmse_m"]["relay_only"]
        if not p or not r:
            gains.append(np.nan)
            errs.append(np.nan)
            continue
        gains.append(p["gain_percent"])
        se = p["mse_difference_stderr_m2"]
        # the 95 % confidence half-width of the mean per-trial MSE difference (Student t, B - 1 dof),
        # in RMSE %: d(RMSE)/RMSE = d(MSE) / (2 MSE)
        errs.append(np.nan if se is None else t95 * 100.0 * se / (2.0 * r * r))
    gains, errs = np.array(gains), np.array(errs)
    # an error bar is a spread over independent trials: with one trial there is none to draw
    with_bars = B >= 2 and np.isfinite(errs).any()
    label = ("fused vs relay-only, same data: bar = RMSE gain; error bar = 95 % confidence interval of the mean "
             f"per-trial MSE difference over the {B} trials (Student t, {B - 1} dof)" if with_bars else
             f"fused vs relay-only, same data: bar = RMSE gain ({B} trial: no error bar, it needs >= 2 trials)")
    axg.bar(centres, gains, width=0.6 * scn.bin_km, color=np.where(gains > 0, "C3", "0.6"), alpha=0.8,
            yerr=np.nan_to_num(errs) if with_bars else None, capsize=3 if with_bars else 0)
    axg.axhline(0.0, color="k", lw=0.8)
    axg.set_ylabel("RMSE gain over\nrelay-only, %")
    axg.set_xlabel("ground range from the launch site, km (bin centres)")
    axg.set_xlim(0, scn.max_range_km)
    axg.grid(alpha=0.3)
    axg.set_title(label, fontsize=8)
    files.append(save_figure(fig, out / FIGURES[1]))

    # c) ANEES against time with the chi-square band
    fig, ax = plt.subplots(figsize=(11, 5.5), constrained_layout=True)
    _shade(ax, scn)
    band = None
    order = [m for m in raw["modes"] if m in WHITE_MODES] + ["radar_only", "relay_only", "fused"]
    for m in order:
        a = sc["anees"].get(m)
        if not a:
            continue
        ax.plot(a["per_epoch_t_s"], a["per_epoch"], color=COLORS[m], lw=0.7, ls=":" if m in WHITE_MODES else "-",
                label=f"{LABELS[m]} (mean {a['mean']:.2f}, {100 * a['fraction_of_epochs_inside']:.0f} % inside)")
        band = a["bounds_99_one_epoch"]
    if band:
        ax.axhspan(band[0], band[1], color="k", alpha=0.08, label=f"99 % chi-square band of the mean NEES over {B} trials at one epoch ({band[0]:.2f}-{band[1]:.2f})")
        ax.axhline(6.0, color="k", lw=0.8, label="expected value (6 dof)")
    ax.set_yscale("log")
    ax.set_xlabel("time since launch, s")
    ax.set_ylabel("mean NEES over trials, [pos, vel] (6 dof; 1, log scale)")
    ax.set_xlim(0, scn.duration_s)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="upper right")
    ax.set_title(f"{sub}\nconsistency: mean NEES over trials per epoch (while every trial is inside "
                 f"{scn.max_range_km:g} km)")
    files.append(save_figure(fig, out / FIGURES[2]))
    return files




def _paired_text(p) -> str:
    if not p:
        return "-"
    se = p["mse_difference_stderr_m2"]
    return (f"{p['gain_percent']:+.2f} %, {p['mse_difference_m2']:+.4g}"
            + (f" +- {se:.2g}" if se is not None else ""))


def summary_table(doc: dict) -> str:
    modes = list(MODES) + ([m for m in WHITE_MODES] if doc["radar_noise_comparison"] else [])
    head = (f"{'range km':>9} | " + " | ".join(f"{m:>16}" for m in modes)
            + f" | {'n':>7} | fused best | fused vs relay-only: RMSE gain, MSE diff +- s.e. (m^2)")
    rows = [f"position RMSE (m) by ground range, {doc['trials']} trials, seed {doc['seed']}", head, "-" * len(head)]
    for b in doc["by_range_km"]:
        if not b["n"]:
            continue
        vals = [("" if b["rmse_m"][m] is None else f"{b['rmse_m'][m]:.2f}") for m in MODES]
        extra = [f"{b['rmse_m'][m]:.2f}" for m in WHITE_MODES] if doc["radar_noise_comparison"] else []
        rows.append(f"{b['range_km']:>5.0f}-{b['range_km'] + doc['scenario']['bin_km']:<3.0f} | "
                    + " | ".join(f"{v:>16}" for v in vals + extra) + f" | {b['n']:>7d} | {b['fused_below_both']!s:>10} | "
                    + _paired_text(b["fused_vs_relay_only"]))
    for name in ("during_radar_loss", "during_gnss_outage"):
        e = doc[name]
        vals = ", ".join(f"{m} {e['rmse_m'][m]:.2f}" for m in MODES if e["rmse_m"][m] is not None)
        rows.append(f"{name} {e['window_s']} s: RMSE {vals} m (n={e['n']}); fused vs relay-only "
                    f"{_paired_text(e['fused_vs_relay_only'])}; vs radar-only {_paired_text(e['fused_vs_radar_only'])}")
    for m in modes:
        a = (doc["anees"] if m in MODES else
             doc["radar_noise_comparison"]["anees"]["white"]).get(m.removesuffix("_white") if m in WHITE_MODES else m)
        if a:
            rows.append(f"ANEES {m:<17} {a['mean']:8.3f}  (99 % one-epoch band {a['bounds_99_one_epoch'][0]:.3f}-"
                        f"{a['bounds_99_one_epoch'][1]:.3f}, {100 * a['fraction_of_epochs_inside']:.1f} % of "
                        f"{a['epochs']} epochs inside; position only {a['position_only']['mean']:.3f})")
    c = doc["continuity"]
    rows.append(f"fused continuity: estimate every epoch {c['fused_estimate_every_epoch']} (missing {c['missing_epochs']}, "
                f"max gap {c['max_gap_s']:g} s); fused below both in every bin: {doc['fused_below_both_in_every_bin']}")
    f = doc["flight"]
    rows.append(f"every flight reaches {doc['scenario']['max_range_km']:g} km: {f['all_reach_max_range']} "
                f"(at {', '.join('-' if x is None else f'{x:.0f}' for x in f['time_to_max_range_s'])} s)")
    tm = doc["timing_s"]
    rows.append(f"wall {doc['wall_s']:.1f} s ({doc['wall_s_per_trial']:.2f} s per trial): world {tm['world']:.1f}, "
                f"publish {tm['publish']:.1f}, bus delivery {tm['deliver']:.1f} + {tm['estimates_delivery']:.1f}, "
                f"trackers {tm['trackers']:.1f} s; bus {1e6 * (tm['bus_s_per_message'] or 0):.0f} us per message")
    ig = doc.get("integrity")
    if ig:
        rows.append(f"integrity monitor ({ig['mode']}): {ig['events']} events on the bus; by tracker "
                    + "; ".join(f"{t}: " + ", ".join(f"{k} {v}" for k, v in d.items()) for t, d in ig["by_tracker"].items()))
        if "overall_rmse_m" in ig:
            rows.append("RMSE without / with the monitor, same messages (m): "
                        + ", ".join(f"{m} {v['without_monitor']:.2f} / {v['with_monitor']:.2f}"
                                    for m, v in ig["overall_rmse_m"].items() if v["with_monitor"] is not None))
    bc = doc["bus_cost_per_message_us"]
    rows.append("bus path per message (build + encode + decode, us): "
                + ", ".join(f"{k} {v['total_us']:.0f}" for k, v in bc.items())
                + f"; for the {sum(doc['bus']['messages_by_kind'].values())} messages of this run: "
                  f"{doc['bus_cost_implied_s']:.1f} s of the {doc['wall_s']:.1f} s")
    return "\n".join(rows)
