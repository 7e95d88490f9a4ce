"""The `skyfuse` command line.

Usage errors (bad flags, bad values, an output directory that cannot be written) end
with one line on stderr and exit status 2, never a traceback. Subcommands import their
heavy modules lazily so that `skyfuse --help` stays instant.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

EXIT_USAGE = 2


class UsageError(Exception):
    """A bad input from the user: reported as one line, exit status 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # argparse's default prints the whole usage block
        raise UsageError(f"{self.prog}: {message}")


# --- argument types: each rejects bad values with a one-line reason ----------------------

def _int_at_least(lowest: int, what: str):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
        if value < lowest:
            raise argparse.ArgumentTypeError(f"expected {what}, got {value}")
        return value

    return parse


positive_int = _int_at_least(1, "a positive integer")
nonnegative_int = _int_at_least(0, "an integer >= 0")


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not value > 0 or value != value or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a positive finite number, got {text}")
    return value


def output_dir(text: str) -> Path:
    """An output directory: created if missing, and it must be writable."""
    path = Path(text)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise argparse.ArgumentTypeError(f"cannot create output directory {text!r}: {exc.strerror}") from None
    if not path.is_dir():
        raise argparse.ArgumentTypeError(f"output path {text!r} is not a directory")
    if not os.access(path, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"output directory {text!r} is not writable")
    return path


def output_file(text: str) -> Path:
    path = Path(text)
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise argparse.ArgumentTypeError(f"directory of {text!r} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"directory of {text!r} is not writable")
    return path


# --- subcommands -------------------------------------------------------------------------

EXPERIMENTS = {
    # name -> (module, one-line description); modules are imported only when run
    "ekf-vs-ukf": ("sitl.experiments.seed001", "seed 001: EKF vs UKF on a 4-satellite receiver, Monte Carlo with the PCRB"),
}

BENCHES = {
    "filters": ("sitl.bench.filters", "batched EKF/UKF time per trial-step against FilterPy"),
}


def _add_seed001_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--trials", type=positive_int, default=1000, help="Monte Carlo trials (default 1000)")
    p.add_argument("--steps", type=positive_int, default=600, help="update steps per trial (default 600, as in the seed)")
    p.add_argument("--seed", type=nonnegative_int, default=1, help="seed of the numpy Generator (default 1)")
    p.add_argument("--out", type=output_dir, default=Path("out/ekf-vs-ukf"), help="output directory for result.json and PNG figures")
    p.add_argument("--noise-reading", choices=("sigma", "variance"), default="sigma",
                   help="read the seed table's 'mean square' noise figures (100 m, 15 m/s) as standard "
                        "deviations (default) or as variances (MODELS.md: sigma 10 m, sqrt(15) m/s)")
    p.add_argument("--sigma-prr", type=positive_float, default=None, metavar="M_S",
                   help="override the pseudo-velocity noise sigma, m/s")
    p.add_argument("--sigma-a", type=positive_float, default=None, metavar="M_S2",
                   help="Singer manoeuvre sigma, m/s^2 (default 1; the seed gives none)")
    p.add_argument("--backend", choices=("auto", "numba", "numpy"), default="auto",
                   help="covariance kernels: compiled (numba) or plain numpy (default auto)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="skyfuse", description="GNSS-aided tracking software-in-the-loop: experiments, benchmarks and the live SITL.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True

    demo = sub.add_parser("demo", help="the main job on the built-in default scenario",
                          description="Run the built-in default. Until the live SITL lands this is a short seed 001 "
                                      "experiment (EKF vs UKF with the PCRB) whose table is printed.")
    demo.add_argument("--trials", type=positive_int, default=500, help="Monte Carlo trials (default 500)")
    demo.add_argument("--seed", type=nonnegative_int, default=1, help="random seed (default 1)")
    demo.add_argument("--out", type=output_dir, default=Path("out/demo"), help="output directory (default out/demo)")

    exp = sub.add_parser("experiment", help="run a reproducible experiment of a seed paper",
                         description="Run an experiment; each writes DIR/result.json and PNG figures.")
    exp_sub = exp.add_subparsers(dest="experiment", metavar="EXPERIMENT", parser_class=_Parser)
    exp_sub.required = True
    for name, (_, doc) in EXPERIMENTS.items():
        p = exp_sub.add_parser(name, help=doc, description=doc)
        if name == "ekf-vs-ukf":
            _add_seed001_args(p)

    bench = sub.add_parser("bench", help="speed benchmarks, each against a peer measured in the same run",
                           description="Benchmarks report ratios against a peer measured in the same run.")
    bench_sub = bench.add_subparsers(dest="bench", metavar="BENCH", parser_class=_Parser)
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
    return parser


def _dispatch(args: argparse.Namespace) -> int:
    import importlib

    from sitl.runtime import batch_mode

    with batch_mode():  # BLAS on one thread (see sitl/runtime.py)
        return _run(args, importlib)


def _run(args: argparse.Namespace, importlib) -> int:
    if args.command == "demo":
        mod = importlib.import_module("sitl.experiments.seed001")
        return mod.demo(args)
    if args.command == "experiment":
        mod = importlib.import_module(EXPERIMENTS[args.experiment][0])
        return mod.main(args)
    if args.command == "bench":
        mod = importlib.import_module(BENCHES[args.bench][0])
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
    sys.exit(main())
