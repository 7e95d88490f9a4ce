"""`skyfuse gnss orbits --nav NAV --sp3 SP3 [--clk CLK] --out DIR`: broadcast ephemerides
checked against IGS precise orbits and clocks (sitl.gnss.orbit_check).

Writes DIR/result.json (orbit_3d_rms_m, radial/along/cross_rms_m, clock_rms_ns, sisre_m,
by_block, by_satellite, the exclusions by health flag, the reference points of each product
and the figures at each of them) and DIR/orbit_errors.png (3D error per satellite over the day,
and the per-satellite RMS by component). Prints the figures by satellite block at the three
reference points. A file that cannot be read is a usage error: one line naming the file and
line, exit 2.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from sitl.app.args import OUTPUT_DIR, UsageError, options_of
from sitl.app.provenance import options_scenario, write_json
from sitl.params import add_flags, choice, from_text, optional, param, switch, validate

DOC = "broadcast GPS/GLONASS orbits and clocks against IGS precise orbits (SP3) and clocks"


def _input_file(text: str) -> Path:
    import argparse

    p = Path(text)
    if not p.is_file():
        raise argparse.ArgumentTypeError(f"no such file: {text}")
    return p


INPUT_FILE = optional(from_text(_input_file))


@dataclass(frozen=True)
class GnssOrbitsOptions:
    """`skyfuse gnss orbits`' options, declared once (sitl.params)."""

    nav: Path | None = param(None, check=INPUT_FILE, metavar="NAV",
                             doc="RINEX 2.x/3.x navigation file (GPS 'N', GLONASS 'G' or mixed); required")
    sp3: Path | None = param(None, check=INPUT_FILE, metavar="SP3", doc="SP3-c/d precise orbit file; required")
    clk: Path | None = param(None, check=INPUT_FILE, metavar="CLK",
                             doc="RINEX clock file for the clock figure (else the SP3 clocks)")
    apc: str = param("control-segment", check=choice("control-segment", "igs05", "none"),
                     doc=("GPS reference point of the figures: the control segment's antenna phase centre (the one "
                          "the broadcast orbits refer to), igs05.atx's, or none (IGS centre of mass)"))
    gps_record: str = param("transmitted", check=choice("transmitted", "nearest"),
                            doc=("GPS record in force at t: the latest transmitted (ttm <= t, what a receiver holds) "
                                 "or the one nearest in Toe"))
    by_satellite: bool = param(False, check=switch(), doc="also print the figures of each satellite")
    out: Path = param(Path("out/gnss-orbits"), check=OUTPUT_DIR, metavar="DIR", doc="output directory")

    __post_init__ = validate


def add_args(p) -> None:
    add_flags(p, GnssOrbitsOptions)


def run(opts: GnssOrbitsOptions):
    """Read the files and compare; GnssFileError (a ValueError) on a bad file."""
    from sitl.gnss.orbit_check import check_orbits
    from sitl.gnss.rinex_clk import read_clk
    from sitl.gnss.rinex_nav import read_nav
    from sitl.gnss.sp3 import read_sp3

    nav = read_nav(opts.nav)
    sp3 = read_sp3(opts.sp3)
    clk = read_clk(opts.clk) if opts.clk is not None else None
    return check_orbits(nav, sp3, clk, apc=opts.apc, gps_select=opts.gps_record)


def plot(res, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    ep = res.epochs
    t0 = float(np.min(ep["t_gps_s"]))
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(11, 8))
    sats = sorted(set(ep["sat"].tolist()))
    cmap = plt.get_cmap("tab20")
    for k, s in enumerate(sats):
        m = ep["sat"] == s
        ax1.plot((ep["t_gps_s"][m] - t0) / 3600.0, ep["err_3d_m"][m], ".-", ms=2, lw=0.7, color=cmap(k % 20), label=s)
    ax1.set_xlabel("hours since the first epoch")
    ax1.set_ylabel("3-D orbit error (broadcast - precise), m")
    rp = res.summary["reference_point"]
    ax1.set_title(f"skyfuse gnss orbits (real data, no RNG): broadcast vs precise: 3D RMS {res.summary['orbit_3d_rms_m']:.2f} m "
                  f"({', '.join(res.summary['systems'])}; GPS reference point: {rp['apc']}, "
                  f"record: {res.summary['record_selection']['gps']})", fontsize=9)
    ax1.legend(ncol=8, fontsize=6)
    ax1.grid(alpha=0.3)
    bs = res.summary["by_satellite"]
    names = [s for s in sats if bs[s]["orbit_3d_rms_m"] is not None]
    x = np.arange(len(names))
    for off, key, lab in ((-0.3, "radial_rms_m", "radial"), (-0.1, "along_rms_m", "along"),
                          (0.1, "cross_rms_m", "cross"), (0.3, "orbit_3d_rms_m", "3D")):
        ax2.bar(x + off, [bs[s][key] for s in names], width=0.2, label=lab)
    ax2.set_xticks(x, names, rotation=90, fontsize=7)
    ax2.set_ylabel("RMS orbit error over the data span, m")
    ax2.set_xlabel("satellite")
    ax2.legend(fontsize=8)
    ax2.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight", pad_inches=0.1)
    plt.close(fig)


def main(args) -> int:
    opts = options_of(GnssOrbitsOptions, args)
    if opts.nav is None or opts.sp3 is None:
        raise UsageError("skyfuse gnss orbits: --nav and --sp3 are required")
    t = time.perf_counter()
    try:
        res = run(opts)
    except ValueError as exc:  # GnssFileError: '<file>, line <n>: <reason>'
        raise UsageError(str(exc)) from None
    elapsed = time.perf_counter() - t
    out = Path(opts.out)
    summary = dict(res.summary, elapsed_s=round(elapsed, 3))
    write_json(out / "result.json", summary, scenario=options_scenario(opts), indent=2)
    plot(res, out / "orbit_errors.png")
    s = res.summary
    clk = "n/a" if s["clock_rms_ns"] is None else f"{s['clock_rms_ns']:.2f} ns"
    print(f"{s['satellites_compared']} satellites, {s['satellite_epochs']} satellite-epochs: orbit 3D RMS "
          f"{s['orbit_3d_rms_m']:.2f} m (R/A/C {s['radial_rms_m']:.2f}/{s['along_rms_m']:.2f}/"
          f"{s['cross_rms_m']:.2f} m, radial mean {s['radial_mean_m']:+.2f} m), clock {clk}, SISRE "
          f"{s['sisre_m']:.2f} m; {s['unhealthy_excluded']} unhealthy satellite-epochs excluded "
          f"({elapsed:.2f} s)")
    blocks = s.get("by_block") or {}
    if blocks:
        print(f"{'block':12s} {'sats':>4s} {'3D':>6s} {'R':>6s} {'A':>6s} {'C':>6s} {'R mean':>7s}   "
              f"{'3D/R mean at CoM':>17s}   {'3D/R mean at igs05 APC':>22s}   clock mean/RMS")
        for b, e in blocks.items():
            clk_b = ("n/a" if e["clock_rms_ns"] is None else
                     f"{e['clock_mean_ns']:+.2f}/{e['clock_rms_ns']:.2f} ns")
            print(f"{b:12s} {len(e['satellites']):4d} {e['orbit_3d_rms_m']:6.2f} {e['radial_rms_m']:6.2f} "
                  f"{e['along_rms_m']:6.2f} {e['cross_rms_m']:6.2f} {e['radial_mean_m']:+7.2f}   "
                  f"{e['orbit_3d_rms_com_m']:8.2f}/{e['radial_mean_com_m']:+6.2f} m   "
                  f"{e['orbit_3d_rms_igs05_apc_m']:13.2f}/{e['radial_mean_igs05_apc_m']:+6.2f} m   {clk_b}")
        rp = s["reference_point"]
        print(f"reference point {rp['apc']}: {rp['correction']}; 3D RMS at the CoM "
              f"{rp['com']['orbit_3d_rms_m']:.2f} m, at the igs05 APC {rp['igs05_apc']['orbit_3d_rms_m']:.2f} m, "
              f"at the control segment's APC {rp['control_segment_apc']['orbit_3d_rms_m']:.2f} m")
    if opts.by_satellite:
        print(f"{'sat':4s} {'svn':5s} {'block':12s} {'epochs':>6s} {'3D':>6s} {'R':>6s} {'A':>6s} {'C':>6s} "
              f"{'R mean':>7s} {'at CoM':>7s} {'at igs05':>8s} {'excluded':>8s}")
        for name, e in s["by_satellite"].items():
            if e["orbit_3d_rms_m"] is None:
                print(f"{name:4s} {e['svn'] or '-':5s} {e['block'] or '-':12s} {0:6d}   (unhealthy "
                      f"{e['unhealthy_excluded']}, no record {e['no_record_in_force']})")
                continue
            print(f"{name:4s} {e['svn'] or '-':5s} {e['block'] or '-':12s} {e['epochs']:6d} {e['orbit_3d_rms_m']:6.2f} "
                  f"{e['radial_rms_m']:6.2f} {e['along_rms_m']:6.2f} {e['cross_rms_m']:6.2f} {e['radial_mean_m']:+7.2f} "
                  f"{e['radial_mean_com_m']:+7.2f} {e['radial_mean_igs05_apc_m']:+8.2f} "
                  f"{e['unhealthy_excluded'] + e['no_record_in_force']:8d}")
    print(f"wrote {out / 'result.json'}, {out / 'orbit_errors.png'}")
    return 0
