"""`skyfuse gnss solve OBS --nav NAV --variant code_doppler|phase_increments|carrier_phase
[--frequency L1] [--static] [--reference-ecef X,Y,Z] [--fixed-position] [--el-mask DEG] --out DIR`: real GPS L1
observations through the seed 000 filter (sitl.app.gnss.solve_filter; the data path is
sitl.app.gnss.solve_data), scored against a reference position, the file's own dual-frequency
ionosphere, broadcast Klobuchar and RTKLIB's L1 single-point solution (sitl.app.gnss.solve_reference).

DIR/result.json:
  position_error_m {mean_enu, std_enu, rms_3d} of the filter's position against the reference
    (default the file's APPROX POSITION), over every updated epoch;
  series {t_gps_s, iono_zenith_m, iono_sd_m, tropo_zenith_m, tropo_sd_m, enu_error_m, n_sats}: per epoch;
  iono_reference {dual_frequency_zenith_m (per epoch), rms_estimate_m (the filter's I_g against it),
    klobuchar_zenith_m, rms_klobuchar_m, receiver_code_bias (how it is treated, its value), arcs};
  rtklib {l1_spp_rms_3d_m, mean_enu, std_enu, epochs, iono_free {mean_enu, std_enu, rms_3d_m}} where
    rnx2rtkp is installed (else a reason);
  iono_free_static {enu_error_m, by_satellite, ...}: the file's own dual-frequency iono-free code,
    one static least-squares position with the same broadcast orbits and clocks (solve_reference.
    iono_free_static_fix): the position error that remains with the ionosphere taken out;
  settings, counts (slips, resets, increments), timing.
DIR/solve.png: ENU error and the zenith ionosphere against the references over time.
A bad file or flag: one line naming it, exit 2.
"""
from __future__ import annotations

import argparse
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from sitl.app.args import OUTPUT_DIR, UsageError, add_positional, options_of
from sitl.app.progress import progress_printer
from sitl.app.provenance import options_scenario, write_json
from sitl.params import add_flags, choice, from_text, number, optional, param, quiet_option, switch, validate

DOC = "real GPS L1 observations through the seed 000 filter, scored against RTKLIB and dual-frequency iono"


def _input_file(text: str) -> Path:
    p = Path(text)
    if not p.is_file():
        raise argparse.ArgumentTypeError(f"no such file: {text}")
    return p


def _ecef(text: str):
    parts = text.split(",")
    try:
        v = [float(p) for p in parts]
    except ValueError:
        v = []
    if len(v) != 3 or not all(math.isfinite(c) for c in v) or not 6.0e6 < math.hypot(*v) < 6.5e6:
        raise argparse.ArgumentTypeError(f"expected X,Y,Z in metres near the Earth's surface, got {text!r}")
    return tuple(v)


INPUT_FILE = optional(from_text(_input_file))
_POS = number(0, lo_open=True)
_NONNEG = number(0)


@dataclass(frozen=True)
class GnssSolveOptions:
    """`skyfuse gnss solve`'s options and the filter's tuning for 30 s real data, declared once."""

    obs: Path | None = param(None, check=INPUT_FILE, metavar="OBS", cli=False,
                             doc="RINEX 2.x/3.x observation file (GPS L1 C/A code and phase)")
    nav: Path | None = param(None, check=INPUT_FILE, metavar="NAV", doc="RINEX navigation file of the same day; required")
    variant: str = param("carrier_phase", check=choice("code_doppler", "phase_increments", "carrier_phase"),
                         doc="the seed 000 variant: code + rate, + code-minus-carrier increments, + carrier phase")
    frequency: str = param("L1", check=choice("L1"), doc="the single frequency solved")
    static: bool = param(False, check=switch(), doc="the receiver does not move (velocity 0, no process noise)")
    fixed_position: bool = param(False, check=switch(),
                                 doc="RTKLIB's fixed mode, a diagnostic: the receiver held at the reference position "
                                     "(--reference-ecef, else APPROX POSITION); only the clock, atmosphere and "
                                     "ambiguities are estimated, so the iono estimate shows what the atmosphere "
                                     "states do when the geometry is known (position_error_m is then 0)")
    reference_ecef: tuple | None = param(None, check=optional(from_text(_ecef)), metavar="X,Y,Z",
                                         doc="reference position, ECEF m (default the file's APPROX POSITION)")
    el_mask_deg: float = param(10.0, check=number(0, hi=60), flag="--el-mask", metavar="DEG",
                               doc="elevation mask of the filter, the references and RTKLIB, deg")
    iono_shape: str = param("auto", check=choice("auto", "thin_shell", "klobuchar"),
                            doc="the slant-to-zenith ionosphere of the filter: the seed's thin shell (eq 9), or "
                                "broadcast Klobuchar's slant over its vertical (its horizontal gradient; the filter "
                                "still estimates the zenith I_g); auto: klobuchar when the navigation header has "
                                "ION ALPHA/BETA, else thin_shell")
    tropo_mapping: str = param("seed", check=choice("seed", "geodetic", "mops"),
                               doc="the filter's tropo mapping: seed (1/sin of the geocentric elevation, eq 10-11), "
                                   "geodetic (1/sin above the ellipsoid's normal) or mops (RTCA DO-229: "
                                   "1.001/sqrt(0.002001 + sin^2 el), geodetic)")
    sigma_pr_m: float = param(0.6, check=_POS, doc="code sigma at the zenith, m (see --code-weighting)")
    code_weighting: str = param("sin", check=choice("sin", "rtklib"),
                                doc="the code sigma's elevation law: sin (sigma / sin el) or rtklib (RTKLIB's "
                                    "a^2 + b^2 / sin^2 el with a = b, the same sigma at the zenith: a floor for the "
                                    "elevation-independent broadcast orbit and clock errors)")
    sigma_prr_m_s: float = param(0.02, check=_POS,
                                 doc="sigma of the phase-rate range-rate row (atmosphere and clock changes over "
                                     "the epoch), m/s")
    sigma_doppler_m_s: float = param(0.1, check=_POS,
                                     doc="sigma of a Doppler range-rate row, where the file has D1/D1C, m/s")
    sigma_phase_m: float = param(0.05, check=_POS,
                                 doc="sigma of a carrier-phase row (noise plus what the one-zenith atmosphere does "
                                     "not model), m")
    sigma_phase_noise_m: float = param(0.003, check=_POS,
                                       doc="carrier-phase noise (the slip test and the increments' variance), m")
    slip_model_m_s: float = param(0.002, check=_POS,
                                  doc="the slip test's bound on the unmodelled rate of phase minus geometry, m/s")
    q_accel_m2_s3: float = param(1e-4, check=_NONNEG, doc="white-acceleration PSD (not --static), m^2/s^3")
    clock_psd_1_s: float | None = param(None, check=optional(_POS),
                                        doc="clock N_eps, 1/s (default: fitted to the file's phase, floor the seed's "
                                            "TCXO 0.8e-20)")
    q_iono_m2_s: float = param(3e-4, check=_NONNEG, doc="random-walk PSD of the zenith iono I_g, m^2/s")
    q_tropo_m2_s: float = param(1e-7, check=_NONNEG, doc="random-walk PSD of the zenith tropo U_g, m^2/s")
    iono_prior_m: float | None = param(None, check=optional(number()),
                                       doc="prior mean of I_g, m (default: broadcast Klobuchar's vertical delay at "
                                           "the first fix and epoch, else 0)")
    sigma0_iono_m: float | None = param(None, check=optional(_POS),
                                        doc="prior sigma of I_g, m (default: half the Klobuchar prior, at least "
                                            "0.5 m -- the ICD's model removes about half the delay --, else the "
                                            "seed's 20 m)")
    tropo_prior_m: float = param(2.3, check=number(), doc="prior mean of U_g (a standard atmosphere at sea level), m")
    sigma0_tropo_m: float = param(0.5, check=_POS, doc="prior sigma of U_g, m")
    sigma0_pos_m: float = param(100.0, check=_POS, doc="prior sigma per axis about the first code-only fix, m")
    sigma0_vel_m_s: float = param(1.0, check=_POS, doc="prior velocity sigma per axis (not --static), m/s")
    sigma0_clock_bias_m: float = param(300.0, check=_POS, doc="prior clock sigma about the first fix's clock, m")
    sigma0_clock_drift_m_s: float = param(1000.0, check=_POS,
                                          doc="prior drift sigma about 0 (a free-running oscillator: ppm), m/s")
    sigma0_amb_m: float = param(1000.0, check=_POS, doc="carrier_phase: prior / reset sigma of K_j, m")
    cmc_window_s: float = param(300.0, check=_POS, doc="phase_increments: the increment window W, s")
    no_rtklib: bool = param(False, check=switch(), doc="skip RTKLIB's run (else it runs where rnx2rtkp is installed)")
    out: Path = param(Path("out/gnss-solve"), check=OUTPUT_DIR, metavar="DIR", doc="output directory")
    quiet: bool = quiet_option()

    __post_init__ = validate


def add_args(p) -> None:
    add_positional(p, GnssSolveOptions, "obs")
    add_flags(p, GnssSolveOptions)


def _enu(pos_ecef, ref):
    from sitl.geodesy import ecef_to_enu, ecef_to_geodetic

    lat, lon, h = ecef_to_geodetic(ref)
    return ecef_to_enu(pos_ecef, lat, lon, h)


def _stats(enu):
    e = enu[np.all(np.isfinite(enu), axis=1)]
    return {"mean_enu": e.mean(axis=0).tolist(), "std_enu": e.std(axis=0).tolist(),
            "rms_3d": float(np.sqrt(np.mean(np.sum(e * e, axis=1)))), "epochs": int(e.shape[0])}


def iono_references(ep, nav, ref, el_mask_deg):
    """The dual-frequency zenith reference per epoch (receiver bias by least squares) and the
    broadcast Klobuchar's zenith by the same fit, from the reference position's geometry."""
    from filters.iono_tropo import elevation_rad, iono_mapping
    from sitl.app.gnss.solve_reference import GAMMA, dual_frequency_slant, zenith_and_bias
    from sitl.geodesy import ecef_to_aer, ecef_to_geodetic
    from sitl.gnss.klobuchar import klobuchar_delay_m

    az, el, _ = ecef_to_aer(ref, ep.sat_pos_m)
    use = np.isfinite(el) & (el >= math.radians(el_mask_deg))
    slant, arc = dual_frequency_slant(ep.c1_m, ep.p2_m, ep.l1_cyc, ep.l2_cyc, ep.lli, np.nan_to_num(ep.tgd_s), use)
    m = iono_mapping(elevation_rad(ref, ep.sat_pos_m))
    iz, b, resid = zenith_and_bias(slant, m)
    out = {"dual_frequency_zenith_m": iz, "receiver_code_bias_m": b, "fit_residual_rms_m": resid,
           "arcs": int(arc.max() + 1) if arc.size else 0}
    if nav.ion_alpha is None or nav.ion_beta is None:
        out["klobuchar_zenith_m"] = None
        return out
    lat, lon, _ = ecef_to_geodetic(ref)
    t = np.broadcast_to(ep.t_gps_s[:, None], el.shape)
    kl = klobuchar_delay_m(nav.ion_alpha, nav.ion_beta, lat, lon, np.nan_to_num(az), np.nan_to_num(el), t)
    fit = np.isfinite(slant)
    num = np.sum(np.where(fit, m * kl, 0.0), axis=1)
    den = np.sum(np.where(fit, m * m, 0.0), axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        out["klobuchar_zenith_m"] = np.where(den > 0, num / den, np.nan)
    out["klobuchar_vertical_m"] = klobuchar_delay_m(nav.ion_alpha, nav.ion_beta, lat, lon, 0.0, math.pi / 2,
                                                    ep.t_gps_s)
    out["gamma"] = GAMMA
    return out


def _rms(a, b):
    m = np.isfinite(a) & np.isfinite(b)
    return float(np.sqrt(np.mean((a[m] - b[m]) ** 2))) if m.any() else None


def run(opts: GnssSolveOptions, progress=None) -> dict:
    """Read, prepare, filter and score; GnssFileError (a ValueError) on a bad file."""
    from sitl.app.gnss.solve_data import prepare
    from sitl.app.gnss.solve_filter import run_filter
    from sitl.gnss.rinex_common import GnssFileError
    from sitl.gnss.rinex_nav import read_nav
    from sitl.gnss.rinex_obs import read_obs

    t0 = time.perf_counter()
    obs = read_obs(opts.obs)
    nav = read_nav(opts.nav)
    t_read = time.perf_counter() - t0
    ep = prepare(obs, nav, opts.frequency)
    if opts.reference_ecef is not None:
        ref, ref_src = np.array(opts.reference_ecef, float), "--reference-ecef"
    elif ep.approx_position_m is not None and np.linalg.norm(ep.approx_position_m) > 6e6:
        ref, ref_src = ep.approx_position_m, "APPROX POSITION XYZ of the observation file"
    else:
        raise GnssFileError(obs.path, None, "no APPROX POSITION XYZ in the header: give --reference-ecef X,Y,Z")
    fr = run_filter(ep, opts, progress=progress, fixed_position_m=ref if opts.fixed_position else None)
    t_proc = time.perf_counter() - t0
    ser = fr["series"]
    pos = np.stack([ser["pos_x"], ser["pos_y"], ser["pos_z"]], axis=1)
    enu = _enu(pos, ref)
    iref = iono_references(ep, nav, ref, opts.el_mask_deg)
    iz = iref["dual_frequency_zenith_m"]
    kz = iref.get("klobuchar_zenith_m")
    result = {
        "command": "gnss solve",
        "obs": str(opts.obs), "nav": str(opts.nav), "variant": opts.variant, "frequency": opts.frequency,
        "static": opts.static, "fixed_position": opts.fixed_position, "el_mask_deg": opts.el_mask_deg,
        "reference": {"ecef_m": ref.tolist(), "source": ref_src},
        "position_error_m": _stats(enu),
        "position_error_after_10min_m": _stats(np.where((ep.t_gps_s - ep.t_gps_s[0] >= 600.0)[:, None], enu, np.nan)),
        "series": {"t_gps_s": ep.t_gps_s, "iono_zenith_m": ser["iono_m"], "iono_sd_m": ser["iono_sd_m"],
                   "tropo_zenith_m": ser["tropo_m"], "tropo_sd_m": ser["tropo_sd_m"], "enu_error_m": enu,
                   "n_sats": ser["n_sats"], "nis": ser["nis"]},
        "iono_reference": {
            "dual_frequency_zenith_m": iz,
            "rms_estimate_m": _rms(ser["iono_m"], iz),
            "klobuchar_zenith_m": kz,
            "rms_klobuchar_m": None if kz is None else _rms(kz, iz),
            "klobuchar_vertical_m": iref.get("klobuchar_vertical_m"),
            "receiver_code_bias": {
                "treatment": "one constant per file, estimated with the per-epoch zenith values by least squares "
                             "(levelled slant = m_I(el) I_z + b; separable because m_I differs across the "
                             "satellites of an epoch); C1 taken for P1 (P1-C1 ignored); broadcast TGD applied",
                "value_m_of_l1_delay": iref["receiver_code_bias_m"],
                "fit_residual_rms_m": iref["fit_residual_rms_m"]},
            "arcs": iref["arcs"],
            "mapping": "the seed's thin shell m_I at 432.5 km on the geocentric elevation (eq 9-10), from the "
                       "reference position",
        },
        "counts": {**ep.counts, **fr["counts"]},
        "tuning": {"iono_shape": fr["iono_shape"], "iono_prior_m": fr["iono_prior_m"],
                   "sigma0_iono_m": fr["sigma0_iono_m"], "clock_psd_1_s": fr["clock_psd_1_s"], "epoch_interval_s": fr["epoch_interval_s"],
                   "cmc_window_epochs": fr["cmc_window_epochs"]},
        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(opts).items()},
        "timing_s": {"read": t_read, "read_and_process": t_proc, "filter": fr["wall_s"]},
    }
    result["iono_free_static"] = iono_free_block(ep, ref, opts.el_mask_deg)
    result["rtklib"] = rtklib_block(opts, ref) if not opts.no_rtklib else {"skipped": "--no-rtklib"}
    return result


def iono_free_block(ep, ref, el_mask_deg) -> dict:
    from sitl.app.gnss.solve_reference import iono_free_static_fix

    fx = iono_free_static_fix(ep, ref, el_mask_deg)
    if fx is None:
        return {"skipped": "no second-frequency code (P2) in the file"}
    return {"enu_error_m": fx["enu_error_m"], "error_3d_m": float(np.linalg.norm(fx["enu_error_m"])),
            "pos_ecef_m": fx["pos_ecef_m"], "rms_residual_m": fx["rms_residual_m"], "by_satellite": fx["by_satellite"],
            "epochs": fx["epochs"], "samples": fx["samples"],
            "what": "(gamma C1 - P2)/(gamma - 1) with the broadcast orbits and clocks (no TGD), Saastamoinen, one "
                    "static position and a clock per epoch, weights 1/(a^2 + b^2/sin^2 el): the error left with "
                    "the ionosphere removed -- broadcast orbit/clock, satellite P1-C1 biases (x2.55), multipath"}


def rtklib_block(opts, ref) -> dict:
    from sitl.app.gnss.solve_reference import rnx2rtkp_path, run_rtklib

    if rnx2rtkp_path() is None:
        return {"skipped": "rnx2rtkp not installed (Debian package rtklib)"}
    out = run_rtklib(opts.obs, opts.nav, el_mask_deg=opts.el_mask_deg)
    if out is None or out[1].size == 0:
        return {"skipped": "RTKLIB gave no solution"}
    t, xyz = out
    s = _stats(_enu(xyz, ref))
    block = {"l1_spp_rms_3d_m": s["rms_3d"], "mean_enu": s["mean_enu"], "std_enu": s["std_enu"], "epochs": s["epochs"],
             "t_gps_s": t, "enu_error_m": _enu(xyz, ref),
             "settings": "pos1-posmode single, frequency l1, ionoopt brdc (Klobuchar), tropopt saas, navsys GPS, "
                         f"elmask {opts.el_mask_deg:g}"}
    out_if = run_rtklib(opts.obs, opts.nav, el_mask_deg=opts.el_mask_deg, ionoopt="dual-freq")
    if out_if is not None and out_if[1].size:
        si = _stats(_enu(out_if[1], ref))
        block["iono_free"] = {"mean_enu": si["mean_enu"], "std_enu": si["std_enu"], "rms_3d_m": si["rms_3d"],
                              "epochs": si["epochs"], "settings": "as above with frequency l1+l2, ionoopt dual-freq"}
    return block


def _m(v) -> str:
    return "n/a" if v is None else f"{v:.2f} m"


def plot(res, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = res["series"]
    t0 = s["t_gps_s"][0]
    tm = (s["t_gps_s"] - t0) / 60.0
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(10, 8), sharex=True)
    for i, lab in enumerate("ENU"):
        a1.plot(tm, s["enu_error_m"][:, i], color=f"C{i}", label=f"{lab} (filter)")
    rt = res.get("rtklib", {})
    if "enu_error_m" in rt:
        tr = (np.asarray(rt["t_gps_s"]) - t0) / 60.0
        for i, lab in enumerate("ENU"):
            a1.plot(tr, np.asarray(rt["enu_error_m"])[:, i], ":", color=f"C{i}", lw=0.9, label=f"{lab} (RTKLIB L1 SPP)")
    pe = res["position_error_m"]
    a1.set_title("skyfuse gnss solve (real data, no RNG): "
                 f"{res['variant']}{' static' if res['static'] else ''}: 3D RMS {pe['rms_3d']:.2f} m"
                 + (f" (RTKLIB {rt['l1_spp_rms_3d_m']:.2f} m)" if "l1_spp_rms_3d_m" in rt else ""))
    a1.set_ylabel("position error (east, north, up), m")
    a1.set_ylim(-5, 5)
    a1.legend(ncol=3, fontsize=7)
    a1.grid(alpha=0.3)
    ir = res["iono_reference"]
    a2.plot(tm, s["iono_zenith_m"], label=f"filter I_g (RMS {_m(ir['rms_estimate_m'])})")
    a2.fill_between(tm, s["iono_zenith_m"] - s["iono_sd_m"], s["iono_zenith_m"] + s["iono_sd_m"], alpha=0.2,
                    label="filter I_g +- its own 1-sigma (68 %)")
    a2.plot(tm, ir["dual_frequency_zenith_m"], "k", label="dual-frequency reference")
    if ir["klobuchar_zenith_m"] is not None:
        a2.plot(tm, ir["klobuchar_zenith_m"], "--", label=f"Klobuchar (RMS {_m(ir['rms_klobuchar_m'])})")
    a2.plot(tm, s["tropo_zenith_m"], label="filter U_g")
    a2.set_ylim(-2, 15)
    a2.set_xlabel("minutes since the first epoch")
    a2.set_ylabel("zenith delay at L1, m")
    a2.legend(fontsize=8)
    a2.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight", pad_inches=0.1)
    plt.close(fig)


def _jsonable(v):
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist())
    if isinstance(v, (np.floating, float)):
        return None if not math.isfinite(float(v)) else float(v)
    if isinstance(v, np.integer):
        return int(v)
    return v


def main(args) -> int:
    opts = options_of(GnssSolveOptions, args)
    if opts.obs is None or opts.nav is None:
        raise UsageError("skyfuse gnss solve: OBS and --nav are required")
    progress = progress_printer(opts.quiet, "gnss solve")
    try:
        res = run(opts, progress=progress)
    except ValueError as exc:  # GnssFileError: '<file>, line <n>: <reason>'
        raise UsageError(str(exc)) from None
    out = Path(opts.out)
    write_json(out / "result.json", _jsonable(res), scenario=options_scenario(opts))
    plot(res, out / "solve.png")
    pe, ir, rt = res["position_error_m"], res["iono_reference"], res["rtklib"]
    rtk = f"{rt['l1_spp_rms_3d_m']:.2f} m" if "l1_spp_rms_3d_m" in rt else rt.get("skipped", "n/a")
    print(f"{res['variant']}: 3D RMS {pe['rms_3d']:.2f} m (ENU mean {', '.join(f'{v:+.2f}' for v in pe['mean_enu'])}; "
          f"std {', '.join(f'{v:.2f}' for v in pe['std_enu'])}) over {pe['epochs']} epochs; RTKLIB L1 SPP {rtk}")
    print(f"zenith iono RMS against the dual-frequency reference: filter {_m(ir['rms_estimate_m'])}, "
          f"Klobuchar {_m(ir['rms_klobuchar_m'])}; read + process {res['timing_s']['read_and_process']:.2f} s")
    fx = res["iono_free_static"]
    if "enu_error_m" in fx:
        rif = rt.get("iono_free", {}).get("mean_enu")
        print("with the ionosphere removed by the second frequency (iono-free static fix): ENU error "
              + ", ".join(f"{v:+.2f}" for v in fx["enu_error_m"]) + " m"
              + (" (RTKLIB iono-free mean " + ", ".join(f"{v:+.2f}" for v in rif) + " m)" if rif else ""))
    print(f"wrote {out / 'result.json'}, {out / 'solve.png'}")
    return 0
