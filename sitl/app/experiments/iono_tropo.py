"""`skyfuse experiment iono-tropo`: seed 000, zenith ionospheric (I_g) and tropospheric (U_g)
delays estimated by an EKF from a single-frequency GPS+GLONASS receiver.

The three variants of the seed (sitl.app.experiments.iono_tropo_filters.run_streamed) run on one scenario
and one seed, hence on the same simulated data:

* ``code_doppler``      variant 1: pseudoranges + pseudorange rates (paper: ~500 s to 1 m);
* ``phase_increments``  variant 2: plus code-minus-carrier increments (paper: ~350 s);
* ``carrier_phase``     variant 3: plus the ambiguous carrier phase with one ambiguity state
                        per satellite (paper: 1 m "practically at once").

Writes DIR/result.json (strict JSON: inf and nan are written as null), DIR/series.npz (the
per-epoch series of every variant, keys "<variant>/<series>") and three PNG figures in the
spirit of the paper's figures 2 (I_g) and 3 (U_g), where "series 1" is variant 2 and
"series 2" is variant 1.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from sitl.app.experiments.common import prepare_out, progress_printer, save_figure, strict, write_result
from sitl.app.report import write_report

from sitl.app.experiments import iono_tropo_filters
from sitl.app.args import OUTPUT_DIR
from sitl.params import (
    add_flags, backend_option, choice, default_of, flag_of, integer, number, optional, param, quiet_option, validate,
)

VARIANTS = {"code_doppler": 1, "phase_increments": 2, "carrier_phase": 3}  # name -> seed000 variant
LABELS = {
    "code_doppler": "v1 code + Doppler (paper series 2)",
    "phase_increments": "v2 + phase increments (paper series 1)",
    "carrier_phase": "v3 + carrier phase",
}
COLORS = {"code_doppler": "C0", "phase_increments": "C1", "carrier_phase": "C2"}
# decreasing widths: where two variants coincide (variant 2 before its first increment is
# variant 1) the one drawn first still shows around the other
WIDTHS = {"code_doppler": 2.6, "phase_increments": 1.6, "carrier_phase": 1.2}
PAPER = {"code_doppler": {"time_to_1m_s": 500}, "phase_increments": {"time_to_1m_s": 350},
         "carrier_phase": {"time_to_1m_s": "practically at once"}}
PAPER_TEXT = {"code_doppler": "~500 s", "phase_increments": "~350 s", "carrier_phase": "practically at once"}
SCALAR_KEYS = ("time_to_1m_s", "final_error_m", "final_bias_m", "anees", "anees_bounds_99_one_epoch", "wall_s")
EXTRA_KEYS = ("increments", "ambiguity", "anees_clock")  # when the run returns them
INFO_KEYS = ("variant", "epochs", "n_visible_min", "n_visible_max", "prior_error")
FIGURES = ("iono_tropo_estimates.png", "iono_tropo_errors.png", "iono_tropo_time_to_1m.png")


# ------------------------------------------------------------------ scenario and runs
# ------------------------------------------------------------------ the command's options
_SCN = iono_tropo_filters.IonoTropoScenario


@dataclasses.dataclass(frozen=True)
class IonoTropoOptions:
    """`skyfuse experiment iono-tropo`'s options, declared once (sitl.params). The defaults are the
    seed's, read from IonoTropoScenario; range checks beyond these are the scenario's, reported as
    usage errors before any run."""

    variant: str = param("all", check=choice("all", *VARIANTS),
                         doc="code_doppler = variant 1 (pseudorange + rate), phase_increments = variant 2 (plus "
                             "code-minus-carrier increments), carrier_phase = variant 3 (plus ambiguous carrier "
                             "phase); all three on the same simulated data")
    trials: int = param(20, check=integer(lo=1), doc="Monte Carlo trials")
    seed: int = param(0, check=integer(lo=0), doc="seed of the numpy Generator")
    duration: float = param(default_of(_SCN, "duration_s"), check=number(0, lo_open=True), metavar="S",
                            doc="observation time, s", note="; 10 epochs/s")
    out: Path = param(Path("out/iono-tropo"), check=OUTPUT_DIR, metavar="DIR",
                      doc="output directory for result.json, series.npz and PNG figures")
    sigma_pr: float = param(default_of(_SCN, "sigma_pr_m"), check=number(0, lo_open=True), metavar="M",
                            doc="pseudorange noise sigma, m")
    sigma_prr: float = param(default_of(_SCN, "sigma_prr_m_s"), check=number(0, lo_open=True), metavar="M_S",
                             doc="pseudorange-rate noise sigma, m/s")
    sigma_phase: float = param(default_of(_SCN, "sigma_phase_m"), check=number(0, lo_open=True), metavar="M",
                               doc="carrier-phase noise sigma, m")
    el_mask_deg: float = param(default_of(_SCN, "el_mask_deg"), check=number(), metavar="DEG",
                               doc="elevation mask, deg, in [5, 90); >= 4 satellites must stay in view")
    adaptive_q: str = param("dynamic", check=choice("off", "all", "dynamic"),
                            doc="adaptive process noise of the seed's eq 7: off; all (every state, as in the seed: "
                                "the paper's filter); dynamic (position, velocity and clock only: Delta_A, I_g, U_g "
                                "and the ambiguities are constants)")
    adaptive_q_decay: float | None = param(None, check=optional(number()), metavar="X", doc="adaptive Q decay, in [0, 1)",
                                           shown=lambda: default_of(_SCN, "adaptive_q_decay"))
    adaptive_q_gain: float | None = param(None, check=optional(number()), metavar="X", doc="adaptive Q gain, >= 0",
                                          shown=lambda: default_of(_SCN, "adaptive_q_gain"))
    slip_rate: float = param(default_of(_SCN, "cycle_slip_rate_hz"), check=number(0), metavar="HZ",
                             doc="random cycle slips per tracked satellite per second in the simulated receiver",
                             note=": the seed's 40 dB-Hz case, slips unlikely")
    cmc_noise: str = param(default_of(_SCN, "cmc_noise"), check=choice("states", "whitened"),
                           doc="variant 2, the code noise in the increments E_j = B_j(t) - B_j(t - 90 s): states = "
                               "exact (the code noise at the window start is a filter state, so E_j carries the "
                               "carrier-phase change); whitened = decorrelated from the same epoch's pseudorange only, "
                               "close to the seed's treatment")
    phase_sats: int = param(default_of(_SCN, "phase_max_sats"), check=integer(lo=0), metavar="N",
                            doc="variant 3: use the carrier phase of at most N satellites, the highest by the "
                                "filter's elevation (the seed: 'even with a single phase measurement')", note=": all")
    truth_clock_psd_scale: float = param(default_of(_SCN, "truth_clock_psd_scale"), check=number(0, lo_open=True),
                                         metavar="X", doc="simulated clock PSD / the filter's",
                                         note=": correctly modelled")
    study: str = param("none", check=choice("none", "adaptive-q", "ordering"),
                       doc="instead of one run: adaptive-q = variants 1 and 2 with eq 7 off / on all states / on "
                           "the dynamic states, each with a right and a mismodelled clock (--clock-scale); "
                           "ordering = the three variants over --seeds seeds")
    seeds: int = param(20, check=integer(lo=1), doc="ordering study: seeds --seed, --seed + 1, ...")
    clock_scale: float = param(1e3, check=number(0, lo_open=True), metavar="X",
                               doc="adaptive-q study: the mismodelled clock's PSD / the filter's")
    backend: str = backend_option()
    quiet: bool = quiet_option()

    __post_init__ = validate


# scenario field -> the option that sets it, to name the flag in a usage error (dt_s must fit in
# --duration; --adaptive-q sets adaptive_q and its scope)
OPTION_OF = {"duration_s": "duration", "dt_s": "duration", "sigma_pr_m": "sigma_pr", "sigma_prr_m_s": "sigma_prr",
             "sigma_phase_m": "sigma_phase", "el_mask_deg": "el_mask_deg", "adaptive_q": "adaptive_q",
             "adaptive_q_scope": "adaptive_q", "adaptive_q_decay": "adaptive_q_decay",
             "adaptive_q_gain": "adaptive_q_gain", "truth_clock_psd_scale": "truth_clock_psd_scale",
             "cycle_slip_rate_hz": "slip_rate", "cmc_noise": "cmc_noise", "phase_max_sats": "phase_sats"}
FLAGS = {field: flag_of(IonoTropoOptions, opt) for field, opt in OPTION_OF.items()}


def add_args(p) -> None:
    add_flags(p, IonoTropoOptions)


def scenario_from_args(args) -> iono_tropo_filters.IonoTropoScenario:
    """The scenario of the command line; ValueError (naming the flag) on a bad value."""
    kw = {"duration_s": args.duration, "sigma_pr_m": args.sigma_pr, "sigma_prr_m_s": args.sigma_prr,
          "sigma_phase_m": args.sigma_phase, "el_mask_deg": args.el_mask_deg,
          "adaptive_q": args.adaptive_q != "off", "truth_clock_psd_scale": args.truth_clock_psd_scale,
          "cycle_slip_rate_hz": getattr(args, "slip_rate", default_of(IonoTropoOptions, "slip_rate")), "cmc_noise": getattr(args, "cmc_noise", default_of(IonoTropoOptions, "cmc_noise")),
          "phase_max_sats": getattr(args, "phase_sats", default_of(IonoTropoOptions, "phase_sats"))}
    if args.adaptive_q != "off":
        kw["adaptive_q_scope"] = args.adaptive_q
    if args.adaptive_q_decay is not None:
        kw["adaptive_q_decay"] = args.adaptive_q_decay
    if args.adaptive_q_gain is not None:
        kw["adaptive_q_gain"] = args.adaptive_q_gain
    try:
        return iono_tropo_filters.IonoTropoScenario(**kw)
    except ValueError as exc:
        msg = " ".join(str(exc).split())  # one line
        flag = next((f for name, f in FLAGS.items() if msg.startswith((name + " ", name + ":"))), None)
        raise ValueError(f"{flag}: {msg}" if flag else msg) from None


def selected_variants(choice: str) -> list[str]:
    return list(VARIANTS) if choice == "all" else [choice]


def run_all(scn, names, trials: int, seed: int, backend=None, progress=None) -> dict:
    """{name: iono_tropo_filters.run_streamed(...)} for the named variants, same scenario and seed."""
    out = {}
    for name in names:
        v = VARIANTS[name]
        if progress:
            progress(f"[{name}] variant {v}: {trials} trials x {scn.n_epochs} epochs")
        prog = (lambda msg, _n=name, **kw: progress(f"[{_n}] {msg}", **kw)) if progress else None
        out[name] = iono_tropo_filters.run_streamed(scn, trials, seed, variant=v, progress=prog, backend=backend)
    return out


# ------------------------------------------------------------------ result.json


def ordering_3_lt_2_lt_1(results: dict):
    """Paper's ordering of the median times to 1 m (variant 3 < 2 < 1); None unless all three ran."""
    if not all(n in results for n in VARIANTS):
        return None
    t = [results[n]["time_to_1m_s"] for n in ("carrier_phase", "phase_increments", "code_doppler")]
    return bool(t[0] < t[1] < t[2])


def result_document(scn, trials: int, seed: int, results: dict, figures) -> dict:
    variants = {}
    for name, res in results.items():
        d = {k: res[k] for k in INFO_KEYS if k in res}
        d.update({k: res[k] for k in SCALAR_KEYS})
        d["time_to_1m_s_per_trial"] = np.asarray(res["time_to_1m_s_per_trial"]).tolist()
        d.update({k: res[k] for k in EXTRA_KEYS if k in res})
        variants[name] = d
    doc = {"experiment": "iono-tropo", "schema": None, "seed": seed, "trials": trials,
           "scenario": dataclasses.asdict(scn), "variants": variants, "paper": PAPER,
           "ordering_3_lt_2_lt_1": ordering_3_lt_2_lt_1(results), "figures": [Path(f).name for f in figures]}
    return strict(doc)


def series_arrays(results: dict) -> dict:
    """Every per-epoch (and per-trial) array of every variant, keyed "<variant>/<name>"."""
    out = {}
    for name, res in results.items():
        for k, v in res.items():
            if isinstance(v, np.ndarray) and v.ndim >= 1:
                out[f"{name}/{k}"] = v
    return out


def write(out: Path, scn, trials: int, seed: int, results: dict) -> list[Path]:
    figures = plot(results, scn, trials, seed, out)
    write_result(out / "result.json", result_document(scn, trials, seed, results, figures), seed=seed, scenario=scn)
    write_report(out)  # OUT/report.html from result.json (sitl.app.report)
    np.savez(out / "series.npz", **series_arrays(results))
    return [out / "result.json", out / "series.npz", *figures, out / "report.html"]


# ------------------------------------------------------------------ the table
def _fmt_s(t: float) -> str:
    return f"{t:.1f} s" if math.isfinite(t) else "never"


def comparison_table(results: dict) -> str:
    head = (f"{'variant':<17} | {'time to 1 m':>11} | {'paper':<19} | {'final RMS I_g':>13} {'U_g':>7} "
            f"{'position':>9} | {'ANEES':>8} | {'wall':>7}")
    rows = [head, "-" * len(head)]
    for name, res in results.items():
        fe = res["final_error_m"]
        rows.append(f"{name:<17} | {_fmt_s(res['time_to_1m_s']):>11} | {PAPER_TEXT[name]:<19} | "
                    f"{fe['iono_zenith']:>11.3f} m {fe['tropo_zenith']:>5.3f} m {fe['position']:>7.2f} m | "
                    f"{res['anees']:>8.3f} | {res['wall_s']:>5.1f} s")
    order = ordering_3_lt_2_lt_1(results)
    if order is not None:
        rows.append(f"paper's ordering (carrier_phase < phase_increments < code_doppler, median time to 1 m): "
                    f"{'holds' if order else 'does not hold'}")
    first = next(iter(results.values()))
    lo, hi = first["anees_bounds_99_one_epoch"]
    rows.append(f"time to 1 m: median over trials of the first time after which |I_g err| < 1 m and "
                f"|U_g err| < 1 m to the end; final RMS and ANEES over the last "
                f"{first['scenario']['final_window_s']:g} s (ANEES 99% one-epoch band {lo:.3f}..{hi:.3f})")
    return "\n".join(rows)


# ------------------------------------------------------------------ figures


def _title(results: dict, scn) -> str:
    trials = next(iter(results.values()))["trials"]
    seed = next(iter(results.values()))["seed"]
    from sitl.app.experiments.common import run_label

    return run_label("iono-tropo", paper="000", seed=seed, trials=trials,
                     extra=f"{scn.duration_s:g} s, elevation mask {scn.el_mask_deg:g} deg")


def plot(results: dict, scn, trials: int, seed: int, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sub = _title(results, scn)
    files = []

    # a) the estimates against time (paper figures 2 and 3)
    fig, axes = plt.subplots(2, 1, figsize=(10, 8), sharex=True, constrained_layout=True)
    panels = (("iono", "I_g", scn.iono_zenith_m, 10.0), ("tropo", "U_g", scn.tropo_zenith_m, 4.0))
    for ax, (key, sym, truth, half) in zip(axes, panels):
        ax.axhspan(truth - 1.0, truth + 1.0, color="0.88", zorder=0, label="truth ± 1 m")
        ax.axhline(truth, color="k", ls="--", lw=1.2, label=f"truth {truth:g} m")
        for name, res in results.items():
            t = res["t_s"]
            est = truth + res[f"{key}_err_mean_m"]
            rms = res[f"{key}_err_rms_m"]
            c = COLORS[name]
            ax.fill_between(t, est - rms, est + rms, color=c, alpha=0.18, lw=0)
            ax.plot(t, est, color=c, lw=WIDTHS[name], label=LABELS[name] + f" (band: ± RMS error over {res['trials']} trials)")
            one = res.get(f"{key}_est_trial0_m")
            if one is not None:
                ax.plot(t, one, color=c, lw=0.7, alpha=0.8, ls="-.",
                        label=f"v{VARIANTS[name]}: trial 0 alone (one realisation, as in the paper)")
            t1 = res["time_to_1m_s"]
            if math.isfinite(t1):
                ax.axvline(t1, color=c, ls=":", lw=WIDTHS[name],
                           label=f"v{VARIANTS[name]}: median time to 1 m {t1:.1f} s")
        ax.set_ylim(truth - half, truth + half)
        ax.set_ylabel(f"zenith {sym} estimate, m")
        ax.grid(alpha=0.3)
    axes[0].set_title("mean estimate over trials, band ± RMS error; dash-dot: trial 0 alone; dotted: median time "
                      "to 1 m", fontsize=10)
    axes[-1].set_xlabel("time since the first epoch, s")
    axes[-1].set_xlim(0, scn.duration_s)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", fontsize=8, ncol=2)
    fig.suptitle(f"{sub}\nzenith ionospheric (I_g) and tropospheric (U_g) delay estimates")
    files.append(save_figure(fig, out / FIGURES[0]))

    # b) RMS error against the filter's own sigma, log scale
    fig, axes = plt.subplots(3, 1, figsize=(10, 10), sharex=True, constrained_layout=True)
    panels = (("iono_err_rms_m", "iono_sd_m", "I_g"), ("tropo_err_rms_m", "tropo_sd_m", "U_g"),
              ("pos_err_rms_m", None, "position"))
    for ax, (ek, sk, sym) in zip(axes, panels):
        for name, res in results.items():
            c = COLORS[name]
            ax.plot(res["t_s"], res[ek], color=c, lw=WIDTHS[name] * 0.8)
            if sk:
                ax.plot(res["t_s"], res[sk], color=c, lw=WIDTHS[name] * 0.6, ls="--")
        if sk:
            ax.axhline(1.0, color="k", lw=0.8, ls=":")
        ax.set_yscale("log")
        ax.set_ylabel(f"{sym} error, m (log scale)" if sk else "position error (3-D RMS), m (log scale)")
        ax.grid(alpha=0.3, which="both")
    axes[0].set_title("RMS error over trials (solid) and the filter's own sigma (dashed); dotted: 1 m",
                      fontsize=10)
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], color=COLORS[n], lw=2, label=LABELS[n]) for n in results]
    handles += [Line2D([], [], color="0.3", lw=1.4, label="RMS error over trials"),
                Line2D([], [], color="0.3", lw=1.0, ls="--", label="filter sigma (RMS over trials)")]
    fig.legend(handles=handles, loc="outside lower center", fontsize=8, ncol=min(len(handles), 3))
    axes[-1].set_xlabel("time since the first epoch, s")
    axes[-1].set_xlim(0, scn.duration_s)
    fig.suptitle(f"{sub}\nestimation errors and consistency")
    files.append(save_figure(fig, out / FIGURES[1]))

    # c) per-trial time to 1 m
    fig, ax = plt.subplots(figsize=(3.0 + 2.2 * len(results), 5.5), constrained_layout=True)
    jitter = np.random.default_rng(0)
    marks = [PAPER[n]["time_to_1m_s"] for n in results]
    top = max([scn.duration_s] + [m for m in marks if isinstance(m, (int, float))])  # paper marks in view
    never_y = scn.duration_s + 0.05 * top  # just above the end of the run
    for i, (name, res) in enumerate(results.items()):
        c = COLORS[name]
        tt = np.asarray(res["time_to_1m_s_per_trial"], dtype=float)
        fin = tt[np.isfinite(tt)]
        if fin.size:
            ax.boxplot([fin], positions=[i], widths=0.5, showfliers=False, manage_ticks=False,
                       medianprops={"color": c, "lw": 2})
            ax.scatter(i + jitter.uniform(-0.18, 0.18, fin.size), fin, s=14, color=c, alpha=0.7, zorder=3)
        n_never = tt.size - fin.size
        if n_never:
            ax.scatter(i + jitter.uniform(-0.18, 0.18, n_never), np.full(n_never, never_y), marker="x", s=22,
                       color=c, zorder=3)
            ax.annotate(f"never: {n_never}", (i, never_y), xytext=(0, 8), textcoords="offset points",
                        ha="center", fontsize=8, color=c)
        med = res["time_to_1m_s"]  # over all trials, the never-settled ones included
        ax.scatter([i + 0.3], [med if math.isfinite(med) else never_y], marker="D", s=30, color=c,
                   edgecolors="k", zorder=5, label="median over all trials" if i == 0 else None)
        paper = PAPER[name]["time_to_1m_s"]
        y = paper if isinstance(paper, (int, float)) else 0.0
        ax.hlines(y, i - 0.4, i + 0.4, colors="k", linestyles="--", lw=1.3, zorder=4)
        ax.annotate(f"paper: {PAPER_TEXT[name]}", (i + 0.4, y), xytext=(0, 3), textcoords="offset points",
                    ha="right", va="bottom", fontsize=8)
    ax.axhline(scn.duration_s, color="0.5", lw=0.8, ls=":")
    ax.annotate(f"end of run ({scn.duration_s:g} s)", (-0.55, scn.duration_s), xytext=(0, 3),
                textcoords="offset points", fontsize=7, color="0.4")
    ax.set_xticks(range(len(results)), [LABELS[n].replace(" (", "\n(", 1) for n in results], fontsize=8)
    ax.set_xlim(-0.6, len(results) - 0.4)
    ax.set_ylim(-0.04 * top, max(1.12 * top, never_y + 0.08 * top))
    ax.legend(loc="upper right", fontsize=8)
    ax.set_ylabel("time to 1 m on I_g and U_g, s")
    ax.grid(alpha=0.3, axis="y")
    ax.set_title(f"{sub}\nper-trial time to 1 m (box: settled trials; x: never)", fontsize=10)
    files.append(save_figure(fig, out / FIGURES[2]))
    return files


# ------------------------------------------------------------------ the command




def main(args) -> int:
    from sitl.app.args import UsageError

    # every check before any run: the scenario (incl. satellites in view) and the output
    try:
        scn = scenario_from_args(args)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    out = prepare_out(Path(args.out))
    names = selected_variants(args.variant)
    backend = None if args.backend == "auto" else args.backend
    if getattr(args, "study", default_of(IonoTropoOptions, "study")) != "none":
        return _study(args, scn, out, backend)
    try:
        results = run_all(scn, names, args.trials, args.seed, backend=backend, progress=progress_printer(args.quiet, "iono-tropo"))
    except ValueError as exc:
        # the per-epoch visibility check is finer than the scenario's 10 s pre-check
        if "satellites in view" in str(exc):
            raise UsageError(f"--el-mask-deg: {exc}") from None
        raise
    files = write(out, scn, args.trials, args.seed, results)
    for res in results.values():
        print(iono_tropo_filters.summary(res))
        print()
    print(comparison_table(results))
    print("wrote " + ", ".join(str(f) for f in files))
    return 0


def _study(args, scn, out: Path, backend) -> int:
    """`--study adaptive-q|ordering`: writes DIR/<study>.json and a PNG."""
    from sitl.app.experiments import iono_tropo_studies as studies

    prog = progress_printer(args.quiet, f"iono-tropo {args.study} study")
    if args.study == "adaptive-q":
        res = studies.adaptive_q_study(scn, args.trials, args.seed, clock_scale=args.clock_scale, progress=prog,
                                       backend=backend)
        fig = out / "adaptive_q_study.png"
        studies.plot_adaptive_q(res, fig)
        name = "adaptive_q_study.json"
        print(studies.adaptive_q_table(res))
    else:
        seeds = list(range(args.seed, args.seed + args.seeds))
        res = studies.ordering_study(scn, seeds, args.trials, progress=prog, backend=backend)
        fig = out / "ordering_study.png"
        studies.plot_ordering(res, fig)
        name = "ordering_study.json"
        pm, pf = res["pooled_median_time_to_1m_s"], res["paired_fraction"]
        print(f"ordering variant 3 < variant 2 < variant 1 (median time to 1 m over {args.trials} trials): "
              f"holds for {res['holds_for']} of {res['of']} seeds")
        print(f"pooled over {res['trials_total']} trials: median time to 1 m variant 1 {pm['code_doppler']} s, "
              f"variant 2 {pm['phase_increments']} s, variant 3 {pm['carrier_phase']} s "
              f"({'holds' if res['pooled_ordering_holds'] else 'does not hold'}); same-data pairs: variant 2 "
              f"first in {pf['variant2_before_variant1']:.0%}, variant 3 before 2 in "
              f"{pf['variant3_before_variant2']:.0%} of trials")
    doc = {"experiment": "iono-tropo", "study": args.study, "schema": None, "scenario": dataclasses.asdict(scn), **res}
    doc["figures"] = [fig.name]
    write_result(out / name, doc, seed=seeds if args.study == "ordering" else args.seed, scenario=scn)
    print(f"wrote {out / name}, {fig}")
    return 0
