"""The `skyfuse` command line.

Usage errors (bad flags, bad values, an output directory that cannot be written) end
with one line on stderr and exit status 2, never a traceback. Subcommands import their
heavy modules lazily so that `skyfuse --help` stays instant.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sitl.app.args import (  # noqa: F401  (the vocabulary of every subcommand's flags)
    EXIT_USAGE,
    Parser,
    UsageError,
    int_at_least,
    nonnegative_float,
    nonnegative_int,
    output_dir,
    output_file,
    positive_float,
    positive_int,
)

# --- subcommands -------------------------------------------------------------------------

# the subcommands' modules, imported when a subcommand is built or run (static imports: the
# import contract sees them; `skyfuse --help` stays light)
def _ekf_vs_ukf_experiments():
    from sitl.app.experiments import ekf_vs_ukf

    return ekf_vs_ukf


def _iono_tropo_experiments():
    from sitl.app.experiments import iono_tropo

    return iono_tropo


def _sonde_experiments():
    from sitl.app.experiments import sonde

    return sonde


def _beacon_experiments():
    from sitl.app.experiments import beacon

    return beacon


def _integrity_experiments():
    from sitl.app.experiments import integrity

    return integrity


def _faults_experiments():
    from sitl.app.experiments import network_faults

    return network_faults


def _long_run_experiments():
    from sitl.app.experiments import long_run

    return long_run


def _filters_bench():
    from sitl.app.bench import filters

    return filters


def _iono_tropo_bench():
    from sitl.app.bench import iono_tropo

    return iono_tropo


def _sonde_bench():
    from sitl.app.bench import sonde

    return sonde


def _beacon_bench():
    from sitl.app.bench import beacon

    return beacon


def _integrity_bench():
    from sitl.app.bench import integrity

    return integrity


def _live_bench():
    from sitl.app.bench import live

    return live



EXPERIMENTS = {
    # name -> (its module's loader, one-line description)
    "ekf-vs-ukf": (_ekf_vs_ukf_experiments, "seed 001: EKF vs UKF on a 4-satellite receiver, Monte Carlo with the PCRB"),
    "iono-tropo": (_iono_tropo_experiments, "seed 000: zenith iono/tropo delays by an EKF from a single-frequency "
                                                  "GPS+GLONASS receiver: code+Doppler vs phase increments vs carrier phase"),
    "sonde": (_sonde_experiments, "seed 004: radiosonde tracking, relayed GNSS fused with an aerological radar "
                                        "vs each alone, over the in-memory bus, RMSE by ground range to 250 km"),
    "beacon": (_beacon_experiments, "seed 002: a moving radio beacon located from >= 3 UAVs' range and Doppler "
                                          "over the in-memory bus; decomposed vs centralised, against the PCRB"),
    "integrity": (_integrity_experiments, "seed 003: fault detection/isolation on faulty GNSS data, plain vs "
                                                "adaptive-robust EKF (+ bias estimation), Pd/Pfa, ROC"),
    "faults": (_faults_experiments, "network faults on the measurement links (loss, burst loss, delay, "
                                          "partitions) of the beacon and sonde scenarios: RMSE against the baseline, "
                                          "recovery after partitions"),
    "long-run": (_long_run_experiments, "the default scenario as `demo --batch` runs it for hours: beacon RMSE "
                                              "per window against its PCRB, ANEES against its chi-square band, "
                                              "sonde errors"),
}

BENCHES = {
    "filters": (_filters_bench, "batched EKF/UKF time per trial-step against FilterPy"),
    "iono-tropo": (_iono_tropo_bench, "a 1200 s seed 000 variant-3 run (12 satellites) against real time"),
    "sonde": (_sonde_bench, "a 2 h seed 004 sonde flight at 1 Hz (fused tracker) against real time"),
    "beacon": (_beacon_bench, "one 1000 s seed 002 beacon trial (3 UAVs, bus and locator) against real time"),
    "integrity": (_integrity_bench, "the seed 003 integrity monitor's cost on a 10,000-trial EKF step"),
    "live": (_live_bench, "the largest swarm the live SITL keeps at real time (10 Hz), bus latency, CPU per UAV"),
}


def _add_ekf_vs_ukf_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--trials", type=positive_int, default=1000, help="Monte Carlo trials (default 1000)")
    p.add_argument("--steps", type=positive_int, default=600, help="update steps per trial (default 600, as in the seed)")
    p.add_argument("--seed", type=nonnegative_int, default=1, help="seed of the numpy Generator (default 1)")
    p.add_argument("--out", type=output_dir, default=Path("out/ekf-vs-ukf"), help="output directory for result.json and PNG figures")
    p.add_argument("--noise-reading", choices=("sigma", "variance"), default="sigma",
                   help="read the seed table's 'mean square' noise figures (100 m, 15 m/s) as standard "
                        "deviations (default) or as variances (sigma 10 m, sqrt(15) m/s)")
    p.add_argument("--sigma-prr", type=positive_float, default=None, metavar="M_S",
                   help="override the pseudo-velocity noise sigma, m/s")
    p.add_argument("--sigma-a", type=positive_float, default=None, metavar="M_S2",
                   help="Singer manoeuvre sigma, m/s^2 (default 1; the seed gives none)")
    p.add_argument("--backend", choices=("auto", "numba", "numpy"), default="auto",
                   help="covariance kernels: compiled (numba) or plain numpy (default auto)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")


IONO_TROPO_VARIANTS = ("code_doppler", "phase_increments", "carrier_phase")  # seed 000 variants 1, 2, 3


def finite_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text}")
    return value


def _add_iono_tropo_args(p: argparse.ArgumentParser) -> None:
    # defaults are the seed's (sitl.app.experiments.iono_tropo_filters.IonoTropoScenario); range checks
    # beyond "positive" are the scenario's, reported as usage errors before any run
    p.add_argument("--variant", choices=("all",) + IONO_TROPO_VARIANTS, default="all",
                   help="code_doppler = variant 1 (pseudorange + rate), phase_increments = variant 2 (plus "
                        "code-minus-carrier increments), carrier_phase = variant 3 (plus ambiguous carrier "
                        "phase); all three on the same simulated data (default all)")
    p.add_argument("--trials", type=positive_int, default=20, help="Monte Carlo trials (default 20)")
    p.add_argument("--seed", type=nonnegative_int, default=0, help="seed of the numpy Generator (default 0)")
    p.add_argument("--duration", type=positive_float, default=1200.0, metavar="S",
                   help="observation time, s (default 1200; 10 epochs/s)")
    p.add_argument("--out", type=output_dir, default=Path("out/iono-tropo"), metavar="DIR",
                   help="output directory for result.json, series.npz and PNG figures (default out/iono-tropo)")
    p.add_argument("--sigma-pr", type=positive_float, default=6.0, metavar="M",
                   help="pseudorange noise sigma, m (default 6)")
    p.add_argument("--sigma-prr", type=positive_float, default=0.064, metavar="M_S",
                   help="pseudorange-rate noise sigma, m/s (default 0.064)")
    p.add_argument("--sigma-phase", type=positive_float, default=0.003, metavar="M",
                   help="carrier-phase noise sigma, m (default 0.003)")
    p.add_argument("--el-mask-deg", type=finite_float, default=10.0, metavar="DEG",
                   help="elevation mask, deg, in [5, 90); >= 4 satellites must stay in view (default 10)")
    p.add_argument("--adaptive-q", choices=("off", "all", "dynamic"), default="dynamic",
                   help="adaptive process noise of the seed's eq 7: off; all (every state, as in the seed: "
                        "the paper's filter); dynamic (position, velocity and clock only: Delta_A, I_g, U_g "
                        "and the ambiguities are constants) (default dynamic)")
    p.add_argument("--adaptive-q-decay", type=finite_float, default=None, metavar="X",
                   help="adaptive Q decay, in [0, 1) (default 0.1)")
    p.add_argument("--adaptive-q-gain", type=finite_float, default=None, metavar="X",
                   help="adaptive Q gain, >= 0 (default 0.7)")
    p.add_argument("--slip-rate", type=nonnegative_float, default=0.0, metavar="HZ",
                   help="random cycle slips per tracked satellite per second in the simulated receiver "
                        "(default 0: the seed's 40 dB-Hz case, slips unlikely)")
    p.add_argument("--cmc-noise", choices=("states", "whitened"), default="states",
                   help="variant 2, the code noise in the increments E_j = B_j(t) - B_j(t - 90 s): states = "
                        "exact (the code noise at the window start is a filter state, so E_j carries the "
                        "carrier-phase change); whitened = decorrelated from the same epoch's pseudorange only, "
                        "close to the seed's treatment (default states)")
    p.add_argument("--phase-sats", type=nonnegative_int, default=0, metavar="N",
                   help="variant 3: use the carrier phase of at most N satellites, the highest by the "
                        "filter's elevation (the seed: 'even with a single phase measurement') (default 0: all)")
    p.add_argument("--truth-clock-psd-scale", type=positive_float, default=1.0, metavar="X",
                   help="simulated clock PSD / the filter's (default 1: correctly modelled)")
    p.add_argument("--study", choices=("none", "adaptive-q", "ordering"), default="none",
                   help="instead of one run: adaptive-q = variants 1 and 2 with eq 7 off / on all states / on "
                        "the dynamic states, each with a right and a mismodelled clock (--clock-scale); "
                        "ordering = the three variants over --seeds seeds (default none)")
    p.add_argument("--seeds", type=positive_int, default=20,
                   help="ordering study: seeds --seed, --seed + 1, ... (default 20)")
    p.add_argument("--clock-scale", type=positive_float, default=1e3, metavar="X",
                   help="adaptive-q study: the mismodelled clock's PSD / the filter's (default 1e3)")
    p.add_argument("--backend", choices=("auto", "numba", "numpy"), default="auto",
                   help="covariance kernels: compiled (numba) or plain numpy (default auto)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")


def _add_sonde_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seed", type=nonnegative_int, default=None,
                   help="seed of the numpy SeedSequence (default 4; with --seeds the first seed, default 1)")
    p.add_argument("--seeds", type=positive_int, default=None, metavar="N",
                   help="seed study: trial 0 of N seeds (--seed .. --seed + N - 1), each a '--trials 1' flight; "
                        "fused vs relay-only vs radar-only per seed, overall and per outage, against the targets")
    p.add_argument("--kinematics", choices=("relaxed", "singer"), default=None,
                   help="the trackers' sonde motion model: relaxed (default: the velocity relaxes to a wind the "
                        "tracker estimates, as in the sonde model) or singer (eq 20 as printed)")
    p.add_argument("--out", type=output_dir, default=Path("out/sonde"), metavar="DIR",
                   help="output directory for result.json and PNG figures (default out/sonde)")
    p.add_argument("--trials", type=positive_int, default=20, help="Monte Carlo trials (default 20)")
    p.add_argument("--duration", type=positive_float, default=7200.0, metavar="S",
                   help="flight time simulated, s at 1 Hz (default 7200: the 2 h flight to 250 km)")
    p.add_argument("--filter", choices=("auto", "ekf", "ukf"), default="auto",
                   help="the trackers' filter: auto = the EKF, and the UKF for a sonde while its position "
                        "uncertainty is large against its distance to the radar (a range-only coast near the radar "
                        "defeats the EKF's linearisation); or one of them throughout (default auto)")
    p.add_argument("--no-white-baseline", action="store_true",
                   help="skip the two extra trackers with the naive white radar-noise model (NEES comparison)")
    p.add_argument("--backend", choices=("auto", "numba", "numpy"), default="auto",
                   help="filter kernels and flight loop: compiled (numba) or plain numpy (default auto)")
    p.add_argument("--integrity", choices=("off", "on", "compare"), default=None,
                   help="integrity monitor on the trackers: on, or compare (the three main trackers plain and again "
                        "monitored, <mode>_monitored, on the same messages) (default off)")
    p.add_argument("--relay-step", type=finite_float, default=None, metavar="M",
                   help="inject a satellite clock step of M metres on one relayed satellite's pseudorange")
    p.add_argument("--relay-step-sat", default=None, metavar="ID",
                   help="that satellite (default: the first delivered to trial 0 at the onset)")
    p.add_argument("--relay-step-at", type=nonnegative_float, nargs=2, default=None, metavar=("A", "B"),
                   help="its start and end, s since launch (default 1200 1800)")
    p.add_argument("--az-outliers", type=finite_float, default=None, metavar="P",
                   help="radar azimuth outlier burst: probability per epoch (10-sigma Student-t, 2 dof)")
    p.add_argument("--az-outlier-at", type=nonnegative_float, nargs=2, default=None, metavar=("A", "B"),
                   help="the burst's start and end, s since launch (default 900 1000)")
    p.add_argument("--az-step-deg", type=finite_float, default=None, metavar="D", help="radar azimuth step, degrees")
    p.add_argument("--az-step-at", type=nonnegative_float, nargs=2, default=None, metavar=("A", "B"),
                   help="the step's start and end, s since launch (default 2400 2700)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")


def _uav_counts(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if not values or any(v < 3 for v in values):
        raise argparse.ArgumentTypeError(f"expected comma-separated integers >= 3, got {text!r}")
    return values


def _add_beacon_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--uavs", type=int_at_least(3, "an integer >= 3 (three UAVs at least)"), default=3,
                   help="UAVs of the two main cases (default 3, as in the seed)")
    p.add_argument("--duration", type=positive_float, default=1000.0, metavar="S",
                   help="simulated time, s at 1 Hz; > 105 (errors are scored after the first 100 s) (default 1000)")
    p.add_argument("--seed", type=nonnegative_int, default=1, help="seed of the numpy Generators (default 1)")
    p.add_argument("--out", type=output_dir, default=Path("out/beacon"), metavar="DIR",
                   help="output directory for result.json and PNG figures (default out/beacon)")
    p.add_argument("--trials", type=positive_int, default=20, help="Monte Carlo trials of the main cases (default 20)")
    p.add_argument("--sweep-trials", type=positive_int, default=5,
                   help="Monte Carlo trials of each by_uav_count run (default 5)")
    p.add_argument("--uav-counts", type=_uav_counts, default=[3, 5, 10, 30], metavar="N,N,...",
                   help="UAV counts of by_uav_count, GPS constellation (default 3,5,10,30)")
    p.add_argument("--geometry", choices=("printed", "geodetic"), default="printed",
                   help="printed (default): the paper's laws and common start point as printed, the beacon's "
                        "start drawn about it and the locator started from that prior; geodetic: the prose's "
                        "lat/lon start points, northward flight, blind start")
    p.add_argument("--integrity", choices=("off", "on", "compare"), default="off",
                   help="integrity monitors: on = the production locator per UAV link and the UAVs' "
                        "onboard filters per satellite; compare = each main case again, monitored, on the same "
                        "data (default off)")
    p.add_argument("--range-step", dest="range_step_m", type=finite_float, default=0.0, metavar="M",
                   help="fault: a range step of M m on one UAV's beacon link from --fault-at (default 0: none)")
    p.add_argument("--range-step-uav", type=positive_int, default=2, metavar="I",
                   help="UAV number (1..--uavs) of the range step (default 2)")
    p.add_argument("--pr-step", dest="pr_step_m", type=finite_float, default=0.0, metavar="M",
                   help="fault: a pseudorange step of M m on the first satellite UAV --pr-step-uav tracks at "
                        "--fault-at (default 0: none)")
    p.add_argument("--pr-step-uav", type=positive_int, default=1, metavar="I",
                   help="UAV number of the pseudorange step (default 1)")
    p.add_argument("--fault-at", dest="fault_at_s", type=nonnegative_float, default=150.0, metavar="S",
                   help="start of the injected faults, s since the run's start (default 150)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")


def _add_integrity_args(p: argparse.ArgumentParser) -> None:
    # defaults: sitl.app.experiments.integrity.IntegrityScenario; its checks are usage errors before any run
    p.add_argument("--trials", type=positive_int, default=200, help="Monte Carlo trials (default 200)")
    p.add_argument("--seed", type=nonnegative_int, default=3, help="seed of the numpy SeedSequence (default 3)")
    p.add_argument("--out", type=output_dir, default=Path("out/integrity"), metavar="DIR",
                   help="output directory for result.json and PNG figures (default out/integrity)")
    p.add_argument("--duration", type=positive_float, default=300.0, metavar="S",
                   help="simulated time, s at 10 Hz; faults start between 60 s and 0.7 x this (default 300)")
    p.add_argument("--sigma-pr", type=positive_float, default=None, metavar="M", help="pseudorange white noise (default 6)")
    p.add_argument("--sigma-prr", type=positive_float, default=None, metavar="M_S", help="rate noise (default 0.064)")
    p.add_argument("--el-mask-deg", type=finite_float, default=None, metavar="DEG",
                   help="elevation mask in [5, 90); >= 7 satellites must stay in view (default 10)")
    p.add_argument("--gm-sigma", type=nonnegative_float, default=None, metavar="M",
                   help="Gauss-Markov pseudorange error sigma per satellite (default 2)")
    p.add_argument("--gm-tau", type=positive_float, default=None, metavar="S", help="its correlation time (default 100)")
    p.add_argument("--jump-sigma", type=positive_float, default=None, metavar="X", help="jump test threshold on |beta|")
    p.add_argument("--window", type=positive_int, default=None, help="window of the drift tests, epochs")
    p.add_argument("--window-alpha", type=positive_float, default=None, metavar="A", help="mean-square test alpha")
    p.add_argument("--bias-alpha", type=positive_float, default=None, metavar="A", help="bias test alpha")
    p.add_argument("--huber-c", type=positive_float, default=None, metavar="X", help="Huber threshold on |beta|")
    p.add_argument("--outlier-prob", type=nonnegative_float, default=None, metavar="P",
                   help="outlier probability per pseudorange-epoch (default 0.002)")
    p.add_argument("--ramp-kind", choices=("code", "clock"), default=None,
                   help="code: the pseudorange alone drifts (no Doppler trace; default); clock: a satellite clock "
                        "frequency fault, the pseudorange rate carries the ramp's rate too")
    p.add_argument("--no-faults", action="store_true", help="the same world with no faults injected")
    p.add_argument("--backend", choices=("auto", "numba", "numpy"), default="auto", help="filter kernels")
    p.add_argument("--quiet", action="store_true", help="no progress lines")


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="skyfuse", description="GNSS-aided tracking software-in-the-loop: experiments, benchmarks and the live SITL.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    sub.required = True

    from sitl.app import launcher as _live  # light at import: the live machinery loads in run/demo

    _live.add_demo_args(sub.add_parser(
        "demo", help="the live SITL on the built-in default scenario (3 UAVs, a moving beacon, a radiosonde)",
        description="Run the built-in default scenario live: vehicle processes speaking MAVLink over UDP, "
                    "the Zenoh bus (an embedded router), the ground-station process; a status line; "
                    "everything stops after --duration simulated seconds or on Ctrl-C."))
    _live.add_run_args(sub.add_parser("run", help="run a scenario file (TOML) live",
                                      description="Run a scenario file (TOML) live, as `demo` does the default."))
    _live.add_replay_args(sub.add_parser("replay", help="a recorded bus log through the batch ground station",
                                         description="Run a recorded bus log (OUT/bus.log) through the batch "
                                                     "ground station and compare its estimates with the recorded ones."))

    from sitl.app import live_faults as _fault  # light: the fault models load only when the command runs

    _fault.add_fault_args(sub.add_parser(
        "fault", help="change or list a running live run's network faults (set LINK SPEC..., list)",
        description="Change or list the network faults of a running live run through its control key."))

    sc = sub.add_parser("scenario", help="print the built-in default scenario: every key, its default and what it means",
                        description="Print the built-in default scenario as TOML, every section and key with its default "
                                    "and its doc (a starting point for `skyfuse run FILE`).")
    sc.add_argument("--out", type=output_file, default=None, metavar="FILE", help="write it to FILE instead of stdout")

    exp = sub.add_parser("experiment", help="run a reproducible experiment of a seed paper",
                         description="Run an experiment; each writes DIR/result.json and PNG figures.")
    exp_sub = exp.add_subparsers(dest="experiment", metavar="EXPERIMENT", parser_class=Parser)
    exp_sub.required = True
    for name, (_, doc) in EXPERIMENTS.items():
        p = exp_sub.add_parser(name, help=doc, description=doc)
        if name == "ekf-vs-ukf":
            _add_ekf_vs_ukf_args(p)
        elif name == "iono-tropo":
            _add_iono_tropo_args(p)
        elif name == "sonde":
            _add_sonde_args(p)
        elif name == "beacon":
            _add_beacon_args(p)
        elif name == "integrity":
            _add_integrity_args(p)
        else:  # newer experiments declare their own flags: add_args(parser) in their module
            EXPERIMENTS[name][0]().add_args(p)

    bench = sub.add_parser("bench", help="speed benchmarks, each against a peer measured in the same run",
                           description="Benchmarks report ratios against a peer measured in the same run.")
    bench_sub = bench.add_subparsers(dest="bench", metavar="BENCH", parser_class=Parser)
    bench_sub.required = True
    for name, (_, doc) in BENCHES.items():
        p = bench_sub.add_parser(name, help=doc, description=doc)
        if name == "filters":
            p.add_argument("--trials", type=positive_int, nargs="+", default=[1, 100, 10_000],
                           help="batch sizes to time (default 1 100 10000)")
            p.add_argument("--steps", type=positive_int, default=None,
                           help="steps per timing (default: enough for ~1 s per case)")
            p.add_argument("--json", type=output_file, default=None, metavar="FILE", help="also write the table as JSON")
            p.add_argument("--backend", choices=("numba", "numpy"), default="numba", help="skyfuse kernels to time")
        elif name == "iono-tropo":
            p.add_argument("--duration", type=positive_float, default=1200.0, metavar="S",
                           help="simulated seconds at 10 Hz (default 1200)")
            p.add_argument("--trials", type=positive_int, default=1, help="trials stepped together (default 1)")
            p.add_argument("--rounds", type=positive_int, default=2,
                           help="interleaved rounds; each figure is the minimum (default 2)")
            p.add_argument("--el-mask-deg", type=positive_float, default=17.0, metavar="DEG",
                           help="elevation mask (default 17: 12 satellites on the default trajectory)")
            p.add_argument("--seed", type=nonnegative_int, default=0, help="random seed (default 0)")
            p.add_argument("--backend", choices=("numba", "numpy"), default="numba",
                           help="main kernels (numba: also times numpy as the peer)")
            p.add_argument("--adaptive-q", choices=("off", "all", "dynamic"), default="dynamic",
                           help="eq 7 scope, as in experiment iono-tropo (default dynamic)")
            p.add_argument("--json", type=output_file, default=None, metavar="FILE", help="also write the result as JSON")
            p.add_argument("--quiet", action="store_true", help="no progress lines")
        else:  # newer benches declare their own flags: add_args(parser) in their module
            BENCHES[name][0]().add_args(p)
    return parser


def _dispatch(args: argparse.Namespace) -> int:
    from sitl.runtime import batch_mode

    with batch_mode():  # BLAS on one thread (see sitl/runtime.py)
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    if args.command in ("demo", "run", "replay"):
        from sitl.app import launcher as live

        return {"demo": live.demo_main, "run": live.run_main, "replay": live.replay_main}[args.command](args)
    if args.command == "scenario":
        from sitl.scenario import DEFAULT_SCENARIO_TOML

        if args.out is None:
            sys.stdout.write(DEFAULT_SCENARIO_TOML)
        else:
            Path(args.out).write_text(DEFAULT_SCENARIO_TOML, encoding="utf-8")
            print(f"wrote {args.out}")
        return 0
    if args.command == "fault":
        from sitl.app.fault_cli import fault_main

        return fault_main(args)
    if args.command == "experiment":
        mod = EXPERIMENTS[args.experiment][0]()
        return mod.main(args)
    if args.command == "bench":
        mod = BENCHES[args.bench][0]()
        return mod.main(args)
    raise UsageError(f"skyfuse: unknown command {args.command!r}")


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        return int(_dispatch(args) or 0)
    except UsageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    # `python -m sitl.app.cli` runs this file as __main__, a second copy of the module: the
    # experiments raise sitl.app.cli.UsageError, which __main__.UsageError would not catch.
    # Run the imported module's main, as the `skyfuse` console script does.
    from sitl.app.cli import main as _main

    sys.exit(_main())
