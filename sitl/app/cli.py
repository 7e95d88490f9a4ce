"""The `skyfuse` command line.

Usage errors (bad flags, bad values, an output directory that cannot be written) end
with one line on stderr and exit status 2, never a traceback. Subcommands import their
heavy modules lazily so that `skyfuse --help` stays instant.
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

from sitl.app.args import (  # noqa: F401  (the vocabulary of every subcommand's flags)
    EXIT_USAGE,
    OUTPUT_FILE,
    Parser,
    UsageError,
    int_at_least,
    nonnegative_float,
    nonnegative_int,
    options_of,
    output_dir,
    output_file,
    positive_float,
    positive_int,
)
from sitl.app.cluster import ClusterError
from sitl.params import add_flags, optional, param, validate


@dataclass(frozen=True)
class ScenarioOptions:
    """`skyfuse scenario`'s options, declared once (sitl.params)."""

    out: Path | None = param(None, check=optional(OUTPUT_FILE), metavar="FILE", doc="write it to FILE instead of stdout")

    __post_init__ = validate

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
    from sitl.app.experiments.sonde import cli as sonde

    return sonde


def _beacon_experiments():
    from sitl.app.experiments.beacon import cli as beacon

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


def _gnss_bench():
    from sitl.app.bench import gnss

    return gnss


def _live_bench():
    from sitl.app.bench import live

    return live


def _mavlink_bench():
    from sitl.app.bench import mavlink

    return mavlink



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
    "gnss": (_gnss_bench, "the real-file GNSS readers and the day's broadcast-vs-IGS orbit check, against georinex"),
    "live": (_live_bench, "the largest swarm the live SITL keeps at real time (10 Hz), bus latency, CPU per UAV"),
    "mavlink": (_mavlink_bench, "the vehicles' MAVLink streams: batched framing against pymavlink's frame per datagram"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="skyfuse", description="GNSS-aided tracking software-in-the-loop: experiments, benchmarks and the live SITL.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    sub.required = True

    from sitl.app import launcher as _live  # light at import: the live machinery loads in run/demo

    # the live commands' options (launcher.DemoOptions, RunOptions, ReplayOptions): their flags
    # are added when the subcommand is parsed or its --help printed (--help reads defaults from
    # the scenario's declarations: `skyfuse --help` does not import it)
    sub.add_parser(
        "demo", help="the live SITL on the built-in default scenario (3 UAVs, a moving beacon, a radiosonde)",
        description="Run the built-in default scenario live: vehicle processes speaking MAVLink over UDP, "
                    "the Zenoh bus (an embedded router), the ground-station process; a status line; "
                    "everything stops after --duration simulated seconds or on Ctrl-C.", flags=_live.add_demo_args)
    sub.add_parser("run", help="run a scenario file (TOML) live",
                   description="Run a scenario file (TOML) live, as `demo` does the default.", flags=_live.add_run_args)
    sub.add_parser("replay", help="a recorded bus log through the batch ground station",
                   description="Run a recorded bus log (OUT/bus.log) through the batch "
                               "ground station and compare its estimates with the recorded ones.",
                   flags=_live.add_replay_args)

    from sitl.app import live_faults as _fault  # light: the fault models load only when the command runs

    _fault.add_fault_args(sub.add_parser(
        "fault", help="change or list a running live run's network faults (set LINK SPEC..., list)",
        description="Change or list the network faults of a running live run through its control key."))

    sc = sub.add_parser("scenario", help="print the built-in default scenario: every key, its default and what it means",
                        description="Print the built-in default scenario as TOML, every section and key with its default "
                                    "and its doc (a starting point for `skyfuse run FILE`).")
    add_flags(sc, ScenarioOptions)

    exp = sub.add_parser("experiment", help="run a reproducible experiment of a seed paper",
                         description="Run an experiment; each writes DIR/result.json and PNG figures.")
    exp_sub = exp.add_subparsers(dest="experiment", metavar="EXPERIMENT", parser_class=Parser)
    exp_sub.required = True
    for name, (load, doc) in EXPERIMENTS.items():
        # each experiment declares its options once (an Options dataclass of sitl.params.param
        # fields; add_args = sitl.params.add_flags): added when the subcommand is parsed or its
        # --help printed, so that `skyfuse --help` does not import every experiment
        exp_sub.add_parser(name, help=doc, description=doc, flags=lambda p, _load=load: _load().add_args(p))

    from sitl.app.gnss.command import add_parser as add_gnss_parser  # `gnss`: sitl/app/gnss/ (light)
    add_gnss_parser(sub)

    # `export`: sitl/app/export/ (light; pyarrow and mcap load when a subcommand runs)
    from sitl.app.export.command import add_parser as add_export_parser
    add_export_parser(sub)

    bench = sub.add_parser("bench", help="speed benchmarks, each against a peer measured in the same run",
                           description="Benchmarks report ratios against a peer measured in the same run.")
    bench_sub = bench.add_subparsers(dest="bench", metavar="BENCH", parser_class=Parser)
    bench_sub.required = True
    for name, (load, doc) in BENCHES.items():
        bench_sub.add_parser(name, help=doc, description=doc, flags=lambda p, _load=load: _load().add_args(p))
    return parser


#: the commands that compile numba kernels in their own process on a first run (the live runs
#: warm them up in a subprocess first and say so: sitl.app.launcher)
IN_PROCESS_KERNELS = ("experiment", "bench", "gnss")


def _dispatch(args: argparse.Namespace) -> int:
    from sitl.app.progress import KernelCompileNotice
    from sitl.runtime import batch_mode

    compiles_here = args.command in IN_PROCESS_KERNELS or (args.command in ("demo", "run") and getattr(args, "batch", False))
    with batch_mode(), KernelCompileNotice(compiles_here and not getattr(args, "quiet", False)):
        return _run(args)  # BLAS on one thread (see sitl/runtime.py); says so if kernels compile


def _run(args: argparse.Namespace) -> int:
    if args.command in ("demo", "run", "replay"):
        from sitl.app import launcher as live

        return {"demo": live.demo_main, "run": live.run_main, "replay": live.replay_main}[args.command](args)
    if args.command == "scenario":
        from sitl.scenario import DEFAULT_SCENARIO_TOML

        opts = options_of(ScenarioOptions, args)
        if opts.out is None:
            sys.stdout.write(DEFAULT_SCENARIO_TOML)
        else:
            Path(opts.out).write_text(DEFAULT_SCENARIO_TOML, encoding="utf-8")
            print(f"wrote {opts.out}")
        return 0
    if args.command == "fault":
        from sitl.app.fault_cli import fault_main

        return fault_main(args)
    if args.command == "experiment":
        mod = EXPERIMENTS[args.experiment][0]()
        return mod.main(args)
    if args.command == "gnss":  # registered by sitl.app.gnss.command.add_parser, which set gnss_main
        return args.gnss_main(args)
    if args.command == "export":  # registered by sitl.app.export.command.add_parser
        return args.export_main(args)
    if args.command == "bench":
        mod = BENCHES[args.bench][0]()
        return mod.main(args)
    raise UsageError(f"skyfuse: unknown command {args.command!r}")


def main(argv: list[str] | None = None) -> int:
    from sitl.app.provenance import mark_started

    # every output of this command records its start and command line (sitl/app/provenance.py)
    mark_started(["skyfuse", *(sys.argv[1:] if argv is None else argv)])
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        return int(_dispatch(args) or 0)
    except UsageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except ClusterError as exc:  # a chunk failed on Dask, a worker died, no scheduler (sitl.app.cluster)
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # the reader went away (`skyfuse gnss ... | head`): stop quietly, as cat and grep do;
        # stdout is pointed at devnull so that the interpreter's final flush does not fail too
        import os
        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (OSError, ValueError):
            pass
        return 141  # 128 + SIGPIPE, the shell's status for a writer cut off by its reader


if __name__ == "__main__":  # pragma: no cover
    # `python -m sitl.app.cli` runs this file as __main__, a second copy of the module: the
    # experiments raise sitl.app.cli.UsageError, which __main__.UsageError would not catch.
    # Run the imported module's main, as the `skyfuse` console script does.
    from sitl.app.cli import main as _main

    sys.exit(_main())
