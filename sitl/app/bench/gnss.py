"""`skyfuse bench gnss`: the real-file readers and the day's orbit check against the clock, with
georinex (the peer reader) timed on the same files in the same run.

Targets (issue 24): reading the 1 h station file <= 5 s, and reading and processing it
(`skyfuse gnss solve`, each variant) <= 5 s; the orbit comparison over a day <= 10 s. Best of
``--rounds`` wall-clock timings (time.perf_counter), each a fresh read.

The files are the real ones of a skyfuse checkout's tests/data/gnss (``DATA_FILES``), which an
installed package does not carry: ``--data DIR`` names the folder; without it the checkout's
folder is used when skyfuse runs from a clone (found next to the sitl package), else the run
stops with a one-line usage error naming --data (exit 2).
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from pathlib import Path

from sitl.app.provenance import options_scenario, write_json
from sitl.app.args import OUTPUT_FILE, UsageError
from sitl.params import add_flags, integer, optional, param, validate, from_text

#: The files the bench reads (tests/data/gnss of a checkout; see its README).
DATA_FILES = ("07590920.05o", "07590920.05n", "brdc1820.10n", "brdc0910.09g", "igs15904.sp3", "igs15904.clk", "igl15253.sp3")


def _missing(folder: Path) -> list[str]:
    return [f for f in DATA_FILES if not (folder / f).is_file()]


def checkout_data_dir(package_file: str | Path = __file__) -> Path | None:
    """tests/data/gnss of the checkout this module runs from (a clone, or an editable install),
    else of the clone the command runs in (the current directory: a clone with the package
    installed from it), or None when there is neither (site-packages has no tests/)."""
    for root in (Path(package_file).resolve().parents[3], Path.cwd()):
        folder = root / "tests" / "data" / "gnss"
        if not _missing(folder):
            return folder
    return None


def _data_dir(text: str) -> Path:
    p = Path(text)
    missing = _missing(p)
    if missing:
        import argparse

        raise argparse.ArgumentTypeError(f"{text} does not hold {', '.join(missing)} (the files of tests/data/gnss)")
    return p


def resolve_data_dir(data: Path | None, package_file: str | Path = __file__) -> Path:
    """``data`` if given, else the checkout's folder; UsageError (one line, naming --data) if
    neither exists."""
    if data is not None:
        return Path(data)
    found = checkout_data_dir(package_file)
    if found is None:
        raise UsageError("skyfuse bench gnss: no GNSS data folder found (an installed skyfuse carries none): "
                         "pass --data DIR, a folder holding " + ", ".join(DATA_FILES)
                         + " (a skyfuse checkout's tests/data/gnss)")
    return found


@dataclass(frozen=True)
class GnssBenchOptions:
    """`skyfuse bench gnss`' options, declared once (sitl.params)."""

    data: Path | None = param(None, check=optional(from_text(_data_dir)), metavar="DIR",
                              doc="folder of the real GNSS files (a checkout's tests/data/gnss)",
                              default_help="default: the checkout's tests/data/gnss when run from a clone")
    rounds: int = param(3, check=integer(lo=1), doc="timings per item (the best is reported)")
    json: Path | None = param(None, check=optional(OUTPUT_FILE), metavar="FILE", doc="also write the result as JSON")

    __post_init__ = validate


def add_args(p) -> None:
    add_flags(p, GnssBenchOptions)


def _best(fn, rounds):
    best = float("inf")
    for _ in range(rounds):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def run(data: Path, rounds: int) -> dict:
    from sitl.gnss.orbit_check import check_orbits
    from sitl.gnss.rinex_clk import read_clk
    from sitl.gnss.rinex_nav import read_nav
    from sitl.gnss.rinex_obs import read_obs
    from sitl.gnss.sp3 import read_sp3

    res = {
        "read_obs_1h_s": _best(lambda: read_obs(data / "07590920.05o"), rounds),
        "read_nav_gps_day_s": _best(lambda: read_nav(data / "brdc1820.10n"), rounds),
        "read_nav_glonass_day_s": _best(lambda: read_nav(data / "brdc0910.09g"), rounds),
        "read_sp3_s": _best(lambda: read_sp3(data / "igs15904.sp3"), rounds),
        "read_clk_s": _best(lambda: read_clk(data / "igs15904.clk"), rounds),
        "orbit_check_gps_day_s": _best(lambda: check_orbits(read_nav(data / "brdc1820.10n"), read_sp3(
            data / "igs15904.sp3"), read_clk(data / "igs15904.clk")), rounds),
        "orbit_check_glonass_day_s": _best(lambda: check_orbits(read_nav(data / "brdc0910.09g"),
                                                                read_sp3(data / "igl15253.sp3")), rounds),
    }
    try:
        import georinex as gr
    except ImportError:
        res["georinex"] = None
    else:
        warnings.simplefilter("ignore")
        res["georinex"] = {
            "version": getattr(gr, "__version__", None),
            "read_obs_1h_s": _best(lambda: gr.load(data / "07590920.05o"), rounds),
            "read_nav_gps_day_s": _best(lambda: gr.load(data / "brdc1820.10n"), rounds),
            "read_nav_glonass_day_s": _best(lambda: gr.load(data / "brdc0910.09g"), rounds),
            "read_sp3_s": _best(lambda: gr.load_sp3(data / "igs15904.sp3", None), rounds),
        }
    res.update(solve_timings(data, rounds))
    res["targets"] = {"read_obs_1h_s": 5.0, "orbit_check_day_s": 10.0, "solve_station_1h_s": 5.0}
    return res


def solve_timings(data: Path, rounds: int) -> dict:
    """`skyfuse gnss solve` on the 1 h station file, reading included, per variant (static, no RTKLIB
    run, no plot): the issue's "reading and processing the 1 h station file <= 5 s"."""
    from sitl.app.gnss.solve import GnssSolveOptions
    from sitl.app.gnss.solve import run as solve

    out = {}
    for variant in ("code_doppler", "phase_increments", "carrier_phase"):
        opts = GnssSolveOptions(obs=data / "07590920.05o", nav=data / "07590920.05n", variant=variant, static=True,
                                no_rtklib=True)
        out[f"solve_station_1h_{variant}_s"] = _best(lambda: solve(opts), rounds)
    return out


def main(args) -> int:
    from sitl.app.args import options_of

    opts = options_of(GnssBenchOptions, args)
    res = run(resolve_data_dir(opts.data), opts.rounds)
    peer = res.get("georinex") or {}
    for k, v in res.items():
        if isinstance(v, float):
            p = peer.get(k)
            print(f"{k:28s} {v:8.3f} s" + (f"   georinex {p:8.3f} s" if p is not None else ""))
    if opts.json is not None:
        write_json(opts.json, res, scenario=options_scenario(opts))
    return 0
