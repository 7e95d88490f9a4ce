"""`skyfuse experiment beacon`: its options (declared once, sitl.params) and their range checks,
the whole experiment (the main cases, the sweep over the number of UAVs, result.json) and its
summary table."""
from __future__ import annotations

import dataclasses
import math
import time
import warnings
from pathlib import Path

import numpy as np

from sitl.app.args import OUTPUT_DIR
from sitl.app.experiments.beacon.case import locator_config, run_case
from sitl.app.experiments.beacon.constants import (AXES, AXIS_ECEF, CASES, CENTRAL_START_PRIOR_S, DT_S,
                                                   FAULT_DEFAULTS, GEOMETRIES, INTEGRITY_MODES, LOCATORS,
                                                   PAPER_ERRORS_M, PRIOR_POS_SIGMA_M, PRIOR_VEL_SIGMA_M_S,
                                                   PRODUCTION, SETTLE_S)
from sitl.app.experiments.beacon.figures import plot
from sitl.app.experiments.beacon.scoring import (_scores, _series, integrity_summary, pcrb_series, summarise_case,
                                                 uav_nav_rmse)
from sitl.app.experiments.beacon.world import beacon_prior, scenario
from sitl.app.experiments.common import options_scenario, prepare_out, progress_printer, write_result
from sitl.app.report import write_report
from sitl.params import add_flags, choice, default_of, from_text, integer, number, param, quiet_option, validate


def _uav_counts(text: str) -> list[int]:
    import argparse

    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if not values or any(v < 3 for v in values):
        raise argparse.ArgumentTypeError(f"expected comma-separated integers >= 3, got {text!r}")
    return values


@dataclasses.dataclass(frozen=True)
class BeaconOptions:
    """`skyfuse experiment beacon`'s options, declared once (sitl.params); the fault options
    default to run_case's (FAULT_DEFAULTS)."""

    uavs: int = param(3, check=integer(lo=3, what="an integer >= 3 (three UAVs at least)"),
                      doc="UAVs of the two main cases", note=", as in the seed")
    duration: float = param(1000.0, check=number(0, lo_open=True), metavar="S",
                            doc="simulated time, s at 1 Hz; > 105 (errors are scored after the first 100 s)")
    seed: int = param(1, check=integer(lo=0), doc="seed of the numpy Generators")
    out: Path = param(Path("out/beacon"), check=OUTPUT_DIR, metavar="DIR", doc="output directory for result.json and PNG figures")
    trials: int = param(20, check=integer(lo=1), doc="Monte Carlo trials of the main cases")
    sweep_trials: int = param(5, check=integer(lo=1), doc="Monte Carlo trials of each by_uav_count run")
    uav_counts: list = param(default_factory=lambda: [3, 5, 10, 30], check=from_text(_uav_counts, show=lambda v: ",".join(map(str, v))),
                              metavar="N,N,...", doc="UAV counts of by_uav_count, GPS constellation")
    geometry: str = param("printed", check=choice(*GEOMETRIES),
                          doc="printed: the paper's laws and common start point as printed, the beacon's start drawn "
                              "about it and the locator started from that prior; geodetic: the prose's lat/lon start "
                              "points, northward flight, blind start")
    integrity: str = param("off", check=choice(*INTEGRITY_MODES),
                           doc="integrity monitors: on = the production locator per UAV link and the UAVs' onboard "
                               "filters per satellite; compare = each main case again, monitored, on the same data")
    range_step_m: float = param(FAULT_DEFAULTS["range_step_m"], check=number(), flag="--range-step", metavar="M",
                                doc="fault: a range step of M m on one UAV's beacon link from --fault-at",
                                note=": none")
    range_step_uav: int = param(FAULT_DEFAULTS["range_step_uav"], check=integer(lo=1), metavar="I",
                                doc="UAV number (1..--uavs) of the range step")
    pr_step_m: float = param(FAULT_DEFAULTS["pr_step_m"], check=number(), flag="--pr-step", metavar="M",
                             doc="fault: a pseudorange step of M m on the first satellite UAV --pr-step-uav tracks at "
                                 "--fault-at", note=": none")
    pr_step_uav: int = param(FAULT_DEFAULTS["pr_step_uav"], check=integer(lo=1), metavar="I",
                             doc="UAV number of the pseudorange step")
    fault_at_s: float = param(FAULT_DEFAULTS["fault_at_s"], check=number(0), flag="--fault-at", metavar="S",
                              doc="start of the injected faults, s since the run's start")
    quiet: bool = quiet_option()

    __post_init__ = validate


def add_args(p) -> None:
    add_flags(p, BeaconOptions)


def check_args(args):
    """Range checks beyond argparse's types; UsageError (one line) on a bad value."""
    from sitl.app.args import UsageError

    if args.uavs < 3:
        raise UsageError(f"--uavs: at least 3 UAVs are needed, got {args.uavs}")
    if args.uavs > 100:
        raise UsageError(f"--uavs: at most 100, got {args.uavs}")
    if not (math.isfinite(args.duration) and args.duration > SETTLE_S + 5.0):
        raise UsageError(f"--duration: must exceed {SETTLE_S + 5.0:g} s (the errors are scored after the first "
                         f"{SETTLE_S:g} s), got {args.duration:g}")
    if args.duration > 36000.0:
        raise UsageError(f"--duration: at most 36000 s, got {args.duration:g}")
    if getattr(args, "integrity", default_of(BeaconOptions, "integrity")) not in INTEGRITY_MODES:
        raise UsageError(f"--integrity: one of {', '.join(INTEGRITY_MODES)}, got {args.integrity!r}")
    for name in ("range_step_m", "pr_step_m", "fault_at_s"):
        v = getattr(args, name, default_of(BeaconOptions, name))
        if not math.isfinite(v) or abs(v) > 1e7 or (name == "fault_at_s" and v < 0):
            raise UsageError(f"--{name.replace('_', '-')}: a finite number{' >= 0' if name == 'fault_at_s' else ''}, "
                             f"got {v:g}")
    for name in ("range_step_uav", "pr_step_uav"):
        v = getattr(args, name, default_of(BeaconOptions, name))
        if not 1 <= v <= args.uavs:
            raise UsageError(f"--{name.replace('_', '-')}: a UAV number in 1..{args.uavs}, got {v}")
    counts = sorted(set(args.uav_counts))
    if any(n < 3 or n > 100 for n in counts):
        raise UsageError(f"--uav-counts: each must lie in 3..100, got {args.uav_counts}")
    return counts


def run(args) -> dict:
    """The whole experiment; returns the result document (also written to DIR)."""
    from ground_station.beacon import LocatorConfig
    from vehicles import uav_nav

    counts = check_args(args)
    geometry = getattr(args, "geometry", default_of(BeaconOptions, "geometry"))
    out = prepare_out(Path(args.out))
    prog = progress_printer(args.quiet, "beacon")
    wall0 = time.perf_counter()
    timing = {}
    cfg = LocatorConfig()
    nav_cfg = uav_nav.NavConfig()
    track_cache = {}

    def tracks_for(n, trials):
        """(tracks, prior) of n UAVs and ``trials`` beacons (printed: starts drawn per trial,
        the same for both cases)."""
        if (n, trials) not in track_cache:
            t0 = time.perf_counter()
            rng = np.random.default_rng([args.seed, 77, n, trials])
            track_cache[(n, trials)] = scenario(geometry, n, args.duration, trials, rng)
            timing[f"truth_rk4_n{n}_t{trials}"] = time.perf_counter() - t0
        return track_cache[(n, trials)]

    integrity = getattr(args, "integrity", default_of(BeaconOptions, "integrity"))
    faults = {k: getattr(args, k, v) for k, v in FAULT_DEFAULTS.items()}
    integ = {}
    plots, doc_cases = {}, {}
    inflate_vs_ignore, central_vs = {}, {}
    for case in CASES:
        if prog:
            prog(f"[{case}] {args.trials} trials x {args.uavs} UAVs, {args.duration:g} s, {geometry} geometry")
        tr, prior = tracks_for(args.uavs, args.trials)
        tm = {}
        t0 = time.perf_counter()
        res = run_case(case, tr, args.trials, args.seed, locators=tuple(LOCATORS), progress=prog, timing=tm,
                       prior=prior, integrity="on" if integrity == "on" else "off", faults=faults)
        tm["case_wall_s"] = time.perf_counter() - t0
        if integrity == "on":
            integ[case] = integrity_summary(None, res, args.trials)
        elif integrity == "compare":  # the same data again, monitored (the production locator alone)
            t0 = time.perf_counter()
            res_m = run_case(case, tr, args.trials, args.seed, locators=(PRODUCTION,), progress=prog, central=False,
                             prior=prior, integrity="on", faults=faults)
            tm["case_monitored_wall_s"] = time.perf_counter() - t0
            integ[case] = integrity_summary(res, res_m, args.trials)
        t0 = time.perf_counter()
        pc, Bd = pcrb_series(tr, res["constellation"], nav_cfg, cfg, prior)
        tm["pcrb"] = time.perf_counter() - t0
        timing[case] = tm
        t = res["t"]
        d = summarise_case(res, pc)
        # per paper axis: RMS over the scored epochs of the PCRB's standard deviation (the
        # bound on each axis's RMSE; a run's largest error is some 2.5-3 times its RMSE)
        sel = res["t"] >= SETTLE_S
        d["pcrb_axes_m"] = {ax: float(np.sqrt(np.mean(Bd[sel, a, a]))) for ax, a in AXIS_ECEF.items()}
        d["uav_nav_rmse"] = uav_nav_rmse(res, tr)
        d["satellites"] = len(res["constellation"])
        d["counters"] = res["counters"][PRODUCTION]
        d["bus"] = res["bus"]
        d["modes"] = {m: int(np.sum(res["mode"] == m)) for m in ("fused", "degraded", "coast", "lost")}
        doc_cases[case] = d
        comp = {}
        for name in LOCATORS:
            sc = _scores(t, res["x"][name], res["P"][name], res["truth"])
            comp[name] = None if sc is None else {"rmse_m": sc["rmse_m"], "anees": sc["anees"],
                                                   "sigma_m": sc["sigma_m"], "errors_m": sc["errors_m"]}
        inflate_vs_ignore[case] = comp
        cen = res.get("central")
        if cen is not None:
            sc = _scores(t, cen["x"], cen["P"], res["truth"])
            dd = np.array(d["rmse_per_trial_m"]) - np.array(sc["rmse_per_trial_m"])
            central_vs[case] = {"decomposed_rmse_m": d.get("rmse_m"), "centralised_rmse_m": sc["rmse_m"],
                                "paired_per_trial_rmse_difference_m": {
                                    "mean": float(dd.mean()),
                                    "standard_error": (float(dd.std(ddof=1) / math.sqrt(dd.size))
                                                       if dd.size > 1 else None),
                                    "decomposed_better_in": int(np.sum(dd < 0)), "of": int(dd.size)},
                                "difference_m": d.get("rmse_m") - sc["rmse_m"],
                                "ratio": d.get("rmse_m") / sc["rmse_m"], "centralised_anees": sc["anees"],
                                "centralised_errors_m": sc["errors_m"], "pcrb_m": d["pcrb_m"]}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            sig = np.sqrt(np.nanmean(np.trace(res["P"][PRODUCTION][..., 0:3, 0:3], axis1=-2, axis2=-1), axis=1))
        plots[case] = {"t": t, "x": res["x"][PRODUCTION], "truth": res["truth"],
                       "rmse_series": _series(t, res["x"][PRODUCTION], res["truth"]),
                       "ignore_series": _series(t, res["x"]["ignore"], res["truth"]),
                       "central_series": None if cen is None else _series(t, cen["x"], res["truth"]),
                       "sigma_series": sig, "pcrb_series": pc}
    # by number of UAVs (constellation)
    sweep = []
    for n in counts:
        if prog:
            prog(f"[by_uav_count] {n} UAVs, {args.sweep_trials} trials")
        tr, prior = tracks_for(n, args.sweep_trials)
        tm = {}
        t0 = time.perf_counter()
        res = run_case("constellation", tr, args.sweep_trials, args.seed + 1000 + n, locators=(PRODUCTION,),
                       progress=prog, central=False, timing=tm, prior=prior)
        pc, _ = pcrb_series(tr, res["constellation"], nav_cfg, cfg, prior)
        tm["wall_s"] = time.perf_counter() - t0
        timing[f"sweep_n{n}"] = tm
        sc = _scores(res["t"], res["x"][PRODUCTION], res["P"][PRODUCTION], res["truth"])
        sel = res["t"] >= SETTLE_S
        sweep.append({"uavs": n, "rmse_m": sc["rmse_m"], "pcrb_m": float(np.mean(pc[sel])),
                      "anees": sc["anees"]["value"], "errors_m": sc["errors_m"], "trials": args.sweep_trials,
                      "uav_nav_rmse": uav_nav_rmse(res, tr)})
    lc = locator_config(PRODUCTION, beacon_prior() if geometry == "printed" else None)
    wall = time.perf_counter() - wall0
    three = doc_cases["three_satellites"]["errors_m"]
    reproduces = all(three[ax]["median_of_trial_max"] <= PAPER_ERRORS_M[ax] for ax in AXES)
    meta = f"{geometry} geometry, {args.uavs} UAVs, {args.duration:g} s at 1 Hz"
    figs = plot(out, plots, sweep, meta, geometry, seed=args.seed, trials=args.trials)
    prior = beacon_prior() if geometry == "printed" else None
    doc = {
        "experiment": "beacon", "schema": None, "seed": args.seed, "trials": args.trials, "uavs": args.uavs,
        "duration_s": args.duration, "epoch_s": DT_S, "settle_s": SETTLE_S, "geometry": geometry,
        "axes": {"xi": "ECEF y", "eta": "ECEF z (polar axis)", "zeta": "ECEF x",
                 "note": "the paper's frame: its printed start point is r (cos45 sin30, sin45, cos45 cos30)"},
        "prior": None if prior is None else {
            "mean_ecef": prior[0].tolist(), "pos_sigma_m": PRIOR_POS_SIGMA_M, "vel_sigma_m_s": PRIOR_VEL_SIGMA_M_S,
            "note": "each trial's true beacon start drawn from N(printed point, pos_sigma^2 I); the locators start at "
                    "the mean with this covariance; the centralised filter starts from the locator's estimate at "
                    f"{CENTRAL_START_PRIOR_S:g} s"},
        "paper": {"errors_m": PAPER_ERRORS_M, "note": "seed 002: errors settle within 25 / 9 / 15 m (xi / eta / zeta)"},
        "reproduces_paper": reproduces,
        "cases": doc_cases,
        "centralised_vs_decomposed": central_vs,
        "inflate_vs_ignore": inflate_vs_ignore,
        "production_locator": PRODUCTION,
        "by_uav_count": sweep,
        "integrity": {"mode": integrity, "faults": faults, "cases": integ} if integrity != "off" else None,
        "locator": {k: getattr(lc, k) for k in lc.__dataclass_fields__ if k not in ("prior_mean", "prior_cov")},
        "wall_s": wall,
        "timing_s": timing,
        "figures": [f.name for f in figs],
    }
    doc = write_result(out / "result.json", doc, seed=args.seed, scenario=options_scenario(args, BeaconOptions))
    write_report(out)  # OUT/report.html from result.json (sitl.app.report)
    return doc


def table(doc) -> str:
    rows = []
    for case, d in doc["cases"].items():
        e = d["errors_m"]
        a = d["anees"]
        rows.append(f"{case:<17} max|err| after 100 s (median / max over {a['trials']} trials): "
                    + ", ".join(f"{ax} {e[ax]['median_of_trial_max']:.0f} / {e[ax]['max_over_trials']:.0f} m "
                                f"(paper {e[ax]['paper']:g})" for ax in AXES))
        rows.append(f"{'':<17} RMSE {d['rmse_m']:.1f} m, PCRB {d['pcrb_m']:.1f} m, ANEES {a['value']:.2f} "
                    f"(99% band {a['bounds_99_one_epoch'][0]:.2f}..{a['bounds_99_one_epoch'][1]:.2f}), "
                    f"UAV nav RMSE {d['uav_nav_rmse']['pos_m']:.1f} m / {d['uav_nav_rmse']['vel_m_s']:.3f} m/s")
        if d.get("pcrb_axes_m") and d.get("rmse_axes_m"):
            rows.append(f"{'':<17} per axis RMSE / PCRB: " + ", ".join(
                f"{ax} {d['rmse_axes_m'][ax]:.1f} / {d['pcrb_axes_m'][ax]:.1f} m" for ax in AXES))
        c = doc["centralised_vs_decomposed"].get(case)
        if c:
            rows.append(f"{'':<17} centralised RMSE {c['centralised_rmse_m']:.1f} m vs decomposed "
                        f"{c['decomposed_rmse_m']:.1f} m (ratio {c['ratio']:.2f})")
        iv = doc["inflate_vs_ignore"][case]
        rows.append(f"{'':<17} " + "; ".join(f"{k}: RMSE {v['rmse_m']:.0f} m ANEES {v['anees']['value']:.3g}"
                                             for k, v in iv.items() if v))
    for case, ig in ((doc.get("integrity") or {}).get("cases") or {}).items():
        m, p = ig.get("monitored") or {}, ig.get("plain") or {}
        line = f"integrity {case}: {ig['events']} events {ig['by_source_and_kind']}"
        for key in ("range_step_isolation", "pr_step_isolation"):
            if key in ig:
                iso = ig[key]
                line += f"; {key} {iso['channel']} rate {iso['rate']:.2f} delay median {iso['delay_s_median']} s"
        rows.append(line)
        if m:
            rows.append(f"{'':<17} RMSE monitored {m['rmse_m']:.1f} m (after fault {m['rmse_after_fault_m']:.1f}), "
                        f"ANEES {m['anees']:.2f}" + (f"; plain {p['rmse_m']:.1f} m (after fault "
                                                     f"{p['rmse_after_fault_m']:.1f}), ANEES {p['anees']:.2f}"
                                                     if p else ""))
    for s in doc["by_uav_count"]:
        rows.append(f"by_uav_count {s['uavs']:>3} UAVs: RMSE {s['rmse_m']:.1f} m, PCRB {s['pcrb_m']:.1f} m, "
                    f"ANEES {s['anees']:.2f} ({s['trials']} trials)")
    rows.append(f"geometry: {doc.get('geometry')}; errors per paper axis (xi, eta, zeta = ECEF y, z, x)")
    rows.append(f"paper's 25/9/15 m reproduced (three satellites, median of trial max): {doc['reproduces_paper']}; "
                f"wall {doc['wall_s']:.1f} s")
    return "\n".join(rows)


def main(args) -> int:
    doc = run(args)
    print(table(doc))
    print(f"wrote {Path(args.out) / 'result.json'} and {', '.join(doc['figures'] + ['report.html'])}")
    return 0
