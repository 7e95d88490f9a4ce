"""`skyfuse experiment sonde`'s options (declared once, sitl.params), its scenario from the parsed
flags, and the command."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

from sitl.app.args import OUTPUT_DIR
from sitl.app.cluster import dask_option, trial_pool
from sitl.app.experiments.common import prepare_out, progress_printer, strict, write_result
from sitl.app.report import write_report
from sitl.app.experiments.sonde.report import plot, result_document, summary_table
from sitl.app.experiments.sonde.scenario import SondeScenario
from sitl.app.experiments.sonde.scoring import score
from sitl.app.experiments.sonde.study import plot_seed_study, seed_study, seed_study_table
from sitl.params import (
    add_flags, backend_option, choice, default_of, integer, number, optional, param, quiet_option, several,
    string, switch, validate,
)


SEED = 4  # the default seed of a run
FIRST_SEED = 1  # ... and the first seed of a seed study


def _scn(name, f=lambda v: v):
    return lambda: f(default_of(SondeScenario, name))  # the default a None option stands for


@dataclass(frozen=True)
class SondeOptions:
    """`skyfuse experiment sonde`'s options, declared once (sitl.params). A None option keeps
    SondeScenario's default (shown in --help)."""

    seed: int | None = param(None, check=optional(integer(lo=0)), doc="seed of the numpy SeedSequence",
                             default_help=f"default {SEED}; with --seeds the first seed, default {FIRST_SEED}")
    seeds: int | None = param(None, check=optional(integer(lo=1)), metavar="N",
                              doc="seed study: trial 0 of N seeds (--seed .. --seed + N - 1), each a '--trials 1' "
                                  "flight; fused vs relay-only vs radar-only per seed, overall and per outage, "
                                  "against the targets")
    kinematics: str | None = param(None, check=optional(choice("relaxed", "singer")),
                                   doc="the trackers' sonde motion model: relaxed (the velocity relaxes to a wind the "
                                       "tracker estimates, as in the sonde model) or singer (eq 20 as printed)",
                                   shown=_scn("kinematics"))
    out: Path = param(Path("out/sonde"), check=OUTPUT_DIR, metavar="DIR",
                      doc="output directory for result.json and PNG figures")
    trials: int = param(20, check=integer(lo=1), doc="Monte Carlo trials")
    duration: float = param(default_of(SondeScenario, "duration_s"), check=number(0, lo_open=True), metavar="S",
                            doc="flight time simulated, s at 1 Hz", note=": the 2 h flight to 250 km")
    filter: str = param(default_of(SondeScenario, "filter"), check=choice("auto", "ekf", "ukf"),
                        doc="the trackers' filter: auto = the EKF, and the UKF for a sonde while its position "
                            "uncertainty is large against its distance to the radar (a range-only coast near the "
                            "radar defeats the EKF's linearisation); or one of them throughout")
    no_white_baseline: bool = param(False, check=switch(),
                                    doc="skip the two extra trackers with the naive white radar-noise model "
                                        "(NEES comparison)")
    backend: str = backend_option("filter kernels and flight loop: compiled (numba) or plain numpy")
    integrity: str | None = param(None, check=optional(choice("off", "on", "compare")),
                                  doc="integrity monitor on the trackers: on, or compare (the three main trackers "
                                      "plain and again monitored, <mode>_monitored, on the same messages)",
                                  shown=_scn("integrity"))
    relay_step: float | None = param(None, check=optional(number()), metavar="M",
                                     doc="inject a satellite clock step of M metres on one relayed satellite's "
                                         "pseudorange")
    relay_step_sat: str | None = param(None, check=optional(string()), metavar="ID",
                                       doc="that satellite", default_help="default: the first delivered to trial 0 "
                                                                          "at the onset")
    relay_step_at: list | None = param(None, check=optional(several(number(0), 2)), metavar=("A", "B"),
                                       doc="its start and end, s since launch", shown=_scn("relay_step_s"))
    az_outliers: float | None = param(None, check=optional(number()), metavar="P",
                                      doc="radar azimuth outlier burst: probability per epoch (10-sigma Student-t, "
                                          "2 dof)")
    az_outlier_at: list | None = param(None, check=optional(several(number(0), 2)), metavar=("A", "B"),
                                       doc="the burst's start and end, s since launch", shown=_scn("az_outlier_s"))
    az_step_deg: float | None = param(None, check=optional(number()), metavar="D", doc="radar azimuth step, degrees")
    az_step_at: list | None = param(None, check=optional(several(number(0), 2)), metavar=("A", "B"),
                                    doc="the step's start and end, s since launch", shown=_scn("az_step_s"))
    dask: str | None = dask_option()
    quiet: bool = quiet_option()

    __post_init__ = validate


def add_args(p) -> None:
    add_flags(p, SondeOptions)


def scenario_from_args(args) -> SondeScenario:
    kw = {"white_baseline": not getattr(args, "no_white_baseline", False), "filter": getattr(args, "filter", default_of(SondeOptions, "filter")),
          "kinematics": getattr(args, "kinematics", None) or default_of(SondeScenario, "kinematics")}
    if getattr(args, "duration", None) is not None:
        kw["duration_s"] = float(args.duration)
    # the integrity options (flags --integrity, --relay-step M, --relay-step-sat ID, --relay-step-at A B,
    # --az-outliers P, --az-outlier-at A B, --az-step-deg D, --az-step-at A B; absent: the defaults)
    if getattr(args, "integrity", None) is not None:
        kw["integrity"] = args.integrity
    for flag, name, conv in (("relay_step", "relay_step_m", float), ("relay_step_sat", "relay_step_sat", str),
                             ("relay_step_at", "relay_step_s", tuple), ("az_outliers", "az_outlier_prob", float),
                             ("az_outlier_at", "az_outlier_s", tuple), ("az_step_at", "az_step_s", tuple)):
        v = getattr(args, flag, None)
        if v is not None:
            kw[name] = conv(v)
    if getattr(args, "az_step_deg", None) is not None:
        kw["az_step_rad"] = math.radians(float(args.az_step_deg))
    return SondeScenario(**kw)


def main(args) -> int:
    from sitl.app.args import UsageError
    from sitl.app.experiments.sonde import run

    try:
        scn = scenario_from_args(args)
    except ValueError as exc:
        raise UsageError(" ".join(str(exc).split())) from None
    out = prepare_out(Path(args.out))
    progress = progress_printer(args.quiet, "sonde")
    backend = None if args.backend == "auto" else args.backend
    n_seeds = getattr(args, "seeds", None)
    dask = getattr(args, "dask", None)
    if n_seeds is not None and dask is not None:
        raise UsageError("--dask: the seed study (--seeds) runs as one batch in this process; drop one of them")
    if n_seeds is not None:  # the seed study: trial 0 of seeds --seed (default 1) .. + n - 1
        first = FIRST_SEED if args.seed is None else args.seed
        doc = strict(seed_study(scn, range(first, first + n_seeds), backend=backend, progress=progress))
        doc["figures"] = [plot_seed_study(doc, out).name]
        doc = write_result(out / "result.json", doc, seed=list(range(first, first + n_seeds)), scenario=scn)
        write_report(out)  # OUT/report.html from result.json (sitl.app.report)
        print(seed_study_table(doc))
        print("wrote " + ", ".join(str(p) for p in [out / "result.json", *(out / f for f in doc["figures"]),
                                                    out / "report.html"]))
        return 0
    if args.seed is None:
        args.seed = SEED
    wall0 = time.perf_counter()
    with trial_pool(dask, progress=progress) as pool:
        raw = run(scn, args.trials, args.seed, backend=backend, progress=progress, pool=pool)
    sc = score(raw, scn)
    wall = time.perf_counter() - wall0
    one = raw["wall_s"] if args.trials == 1 else None
    figures = plot(raw, sc, scn, args.seed, out)
    doc = write_result(out / "result.json", result_document(scn, args.seed, raw, sc, figures, wall, one),
                       seed=args.seed, scenario=scn)
    write_report(out)  # OUT/report.html from result.json (sitl.app.report)
    print(summary_table(doc))
    print("wrote " + ", ".join(str(p) for p in [out / "result.json", *figures, out / "report.html"]))
    return 0
