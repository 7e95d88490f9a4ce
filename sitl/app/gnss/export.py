"""`skyfuse gnss export`: the simulated GNSS world as RINEX 3.04, for an independent engine.

    skyfuse gnss export [--scenario FILE] [--receiver static|uav] [--duration S] [--no-iono]
                        [--no-tropo] --out DIR

One receiver of the scenario's world (``[run]`` seed, t0_gps_s, rate_hz, duration_s):

* ``static``: the ground receiver at the sonde's launch pad (``[sonde].launch``), at rest;
* ``uav``: UAV 1 of ``[uavs]`` (its start, pattern and speed, as the vehicle workers fly it:
  vehicles.uav), its ECEF truth sampled at the reception instants.

Its observations are what the world generates (sitl.gnss: ``world.geometry_track`` -- light time,
Sagnac -- then ``Receiver.step``: the seed 000 receiver, sigma 6 m code, 3 mm phase, 0.064 m/s
rate, 5 deg mask; the ``ClockModel`` TCXO clock), the whole GPS + GLONASS constellation of
``orbits.default_constellation("GR")``. A receiver tags its epochs with its own clock, so the
RINEX epochs are the receiver's grid t0 + k / rate_hz and the true reception instants are
tag - clock_bias / c (the clock simulated on the receiver's epochs; the bias moves by < 1e-7 m
between the two instants).

DIR gets
  sim.obs     RINEX 3.04 observations: C1C, L1C (cycles), D1C (Hz, positive approaching),
              S1C (a constant 45 dB-Hz: the simulated noise does not depend on the signal level);
              LLI bit 0 on the phase at (re)acquisition and slips;
  sim.nav     RINEX 3.04 mixed navigation: GPS LNAV and GLONASS records every 15 min (the finest
              grid RTKLIB takes for GLONASS; sitl.gnss.rinex_write: the encoding and its errors),
              with ION ALPHA/BETA of a flat Klobuchar at the simulated zenith delay when the
              ionosphere is on;
  truth.csv   per epoch: true reception GPS time, the RINEX tag, ECEF position and velocity,
              receiver clock bias (m, against GLONASS time = GPS time here) and drift, and the
              numbers of GPS and GLONASS satellites tracked;
  truth_geometry.npz  the truth of the light-time solution per epoch and satellite (line of
              sight, elevations, slant iono and tropo delays, tracked): the geometry for DOP
              and for the atmosphere's expected effect;
  export.json the settings, the models and the encoding errors.
"""
from __future__ import annotations

import csv
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sitl.app.args import OUTPUT_DIR, Parser, UsageError, options_of
from sitl.app.provenance import write_json
from sitl.params import choice, from_text, number, optional, param, switch, validate, add_flags

#: spacing of the navigation records, s (RTKLIB rounds GLONASS record epochs to 15 min)
NAV_SPACING_S = 900.0
#: the constant C/N0 written as S1C, dB-Hz
SNR_DBHZ = 45.0


def _scenario_file(text: str) -> Path:
    return Path(text)


@dataclass(frozen=True)
class ExportOptions:
    """`skyfuse gnss export`'s options, declared once (sitl.params)."""

    scenario: Path | None = param(None, check=optional(from_text(_scenario_file)), metavar="FILE",
                                  doc="scenario TOML", default_help="default: the built-in scenario")
    receiver: str = param("static", check=choice("static", "uav"),
                          doc="the receiver: static (at [sonde].launch) or uav (UAV 1 of [uavs])")
    duration: float | None = param(None, check=optional(number(0, lo_open=True)), metavar="S",
                                   doc="seconds of observations", default_help="default: the scenario's run.duration_s")
    no_iono: bool = param(False, check=switch(), doc="no ionospheric delay in the observations")
    no_tropo: bool = param(False, check=switch(), doc="no tropospheric delay in the observations")
    clock_bias0: float = param(3000.0, check=number(), metavar="M",
                               doc="receiver clock bias at the first epoch, m (10 us: the tags differ from true time)")
    clock_drift0: float = param(0.5, check=number(), metavar="M/S", doc="receiver clock drift at the first epoch, m/s")
    out: Path = param(Path("out/gnss_export"), check=OUTPUT_DIR, metavar="DIR", doc="output directory")
    rtklib: bool = param(False, check=switch(),
                         doc="also solve the files with RTKLIB's rnx2rtkp (single point: GPS+GLONASS and GPS only, its "
                             "iono/tropo corrections off and, with the atmosphere on, Klobuchar + Saastamoinen) and "
                             "score it against truth.csv: DIR/rtklib.json")

    __post_init__ = validate


def add_args(p) -> None:
    add_flags(p, ExportOptions)


# ---------------------------------------------------------------------------------------------

def _trajectory(scn, kind: str, t_true: np.ndarray):
    """ECEF position and velocity (T, 3) of the receiver at the true reception instants."""
    from sitl import geodesy

    if kind == "static":
        lat, lon, h = scn.sonde.launch
        p = geodesy.geodetic_to_ecef(math.radians(lat), math.radians(lon), h)
        return np.broadcast_to(p, (t_true.size, 3)).copy(), np.zeros((t_true.size, 3))
    from vehicles import uav as uav_mod

    if scn.uavs.count < 1:
        raise UsageError("gnss export: --receiver uav needs a scenario with [uavs].count >= 1")
    pts = np.array(scn.uavs.start_points()[:1])
    if scn.uavs.pattern == "orbit":
        lat_c, lon_c = (math.radians(v) for v in scn.uavs.center)
        law = uav_mod.Racetrack.orbit_through(np.radians(pts[:, 0]), np.radians(pts[:, 1]), lat_c, lon_c,
                                              scn.uavs.speed_m_s)
    else:  # "north": the vehicle workers' sinusoidal law (vehicles/process.py)
        law = uav_mod.SinusoidalLaw(speed_mean_m_s=np.full(1, scn.uavs.speed_m_s), speed_amp_m_s=10.0,
                                    speed_omega_rad_s=0.02, heading0_rad=0.0, climb_amp_m_s=15.0,
                                    climb_omega_rad_s=0.01)
    t_rel = t_true - scn.run.t0_gps_s
    swarm = uav_mod.UavSwarm(law, np.radians(pts[:, 0]), np.radians(pts[:, 1]), pts[:, 2], t0_s=float(t_rel[0]))
    tr = swarm.track(t_rel)
    return np.asarray(tr.pos_ecef_m)[:, 0, :], np.asarray(tr.vel_ecef_m_s)[:, 0, :]


def _nav_epochs(t_first: float, t_last: float, offset: float) -> np.ndarray:
    """Record epochs offset + 900 m covering [t_first, t_last] so that the nearest is <= 450 s away."""
    lo = math.floor((t_first - offset) / NAV_SPACING_S + 0.5)
    hi = math.floor((t_last - offset) / NAV_SPACING_S + 0.5)
    return offset + NAV_SPACING_S * np.arange(lo, hi + 1)


def export(opts: ExportOptions) -> dict:
    """Simulate and write DIR (module docstring); returns export.json's content."""
    from sitl.constants import C_M_S, GPS_UTC_LEAP_S
    from sitl.gnss import rinex_write as rw
    from sitl.gnss.clock import ClockModel
    from sitl.gnss.orbits import default_constellation
    from sitl.gnss.receiver import Receiver, ReceiverConfig
    from sitl.gnss.world import geometry_track
    from sitl.scenario import default_scenario, load_scenario

    try:
        scn = default_scenario() if opts.scenario is None else load_scenario(opts.scenario)
    except ValueError as exc:
        raise UsageError(" ".join(str(exc).split())) from None
    out = Path(opts.out)
    rate = scn.run.rate_hz
    duration = scn.run.duration_s if opts.duration is None else opts.duration
    n = int(math.floor(duration * rate + 1e-9)) + 1
    tag = scn.run.t0_gps_s + np.arange(n) / rate
    rng = np.random.default_rng(scn.run.seed)
    const = default_constellation("GR")
    base = ReceiverConfig()
    cfg = ReceiverConfig(iono_zenith_m=0.0 if opts.no_iono else base.iono_zenith_m,
                         tropo_zenith_m=0.0 if opts.no_tropo else base.tropo_zenith_m)
    clock = ClockModel()
    bias, drift = np.empty(n), np.empty(n)
    bias[0], drift[0] = opts.clock_bias0, opts.clock_drift0
    for k in range(1, n):  # the receiver's clock on its own epochs
        bias[k], drift[k] = clock.step(rng, bias[k - 1], drift[k - 1], tag[k] - tag[k - 1])
    t_true = tag - bias / C_M_S
    pos, vel = _trajectory(scn, opts.receiver, t_true)

    S = len(const)
    receiver = Receiver(S, cfg)
    carrier = const.carrier_l1_hz
    is_gps = const.system == "G"
    names = ("pr", "phase", "prr", "lock", "iono", "tropo", "el", "el_atmo", "vis")
    acc = {k: np.empty((n, S)) for k in names}
    los = np.empty((n, S, 3))
    for k, eg in enumerate(geometry_track(t_true, pos, vel, const)):
        g = eg.geometry
        obs = receiver.step(rng, eg.t_gps_s, g.range_m, g.range_rate_m_s, eg.el_rad, carrier, is_gps,
                            bias[k], drift[k], el_atmo_rad=eg.el_atmo_rad)
        for key, v in (("pr", obs.pseudorange_m), ("phase", obs.carrier_phase_cycles),
                       ("prr", obs.pseudorange_rate_m_s), ("lock", obs.lock_count), ("iono", obs.iono_slant_m),
                       ("tropo", obs.tropo_slant_m), ("el", eg.el_rad), ("el_atmo", eg.el_atmo_rad),
                       ("vis", obs.visible)):
            acc[key][k] = v
        los[k] = g.los_unit
    vis = acc["vis"].astype(bool)
    lam = C_M_S / carrier
    doppler = -acc["prr"] / lam
    lli = ((acc["lock"] == 0) & (np.arange(n)[:, None] > 0)).astype(int)
    snr = np.where(vis, SNR_DBHZ, np.nan)
    t_span = (float(t_true[0]), float(t_true[-1]))

    gps_toes = _nav_epochs(*t_span, 0.0)
    glo_toes = _nav_epochs(*t_span, GPS_UTC_LEAP_S)  # UTC on the 15-min grid
    gps_recs, gps_clock_res_s = rw.gps_lnav_records(const, gps_toes, NAV_SPACING_S / 2)
    glo_recs, glo_fit_max_m, glo_errs = rw.glonass_records(const, glo_toes, NAV_SPACING_S / 2)
    klob = None if opts.no_iono else rw.klobuchar_constant(cfg.iono_zenith_m)
    comment = [f"skyfuse simulated world, receiver {opts.receiver}, seed {scn.run.seed}",
               f"iono {'off' if opts.no_iono else f'{cfg.iono_zenith_m:g} m zenith, thin shell 432.5 km'}, "
               f"tropo {'off' if opts.no_tropo else f'{cfg.tropo_zenith_m:g} m / sin el'}"]
    rw.write_nav(out / "sim.nav", gps_recs, glo_recs, iono_alpha=None if klob is None else klob[0],
                 iono_beta=None if klob is None else klob[1], comment=comment)
    rw.write_obs(out / "sim.obs", tag, const.sat_id, const.glonass_k, acc["pr"], acc["phase"], doppler, snr, lli,
                 approx_pos_ecef_m=np.round(pos[0], 0), interval_s=1.0 / rate, comment=comment)

    with open(out / "truth.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t_gps_s", "rinex_tag_gps_s", "x_m", "y_m", "z_m", "vx_m_s", "vy_m_s", "vz_m_s",
                    "clock_bias_m", "clock_drift_m_s", "n_gps", "n_glonass"])
        n_g = (vis & is_gps).sum(axis=1)
        n_r = (vis & ~is_gps).sum(axis=1)
        for k in range(n):
            w.writerow([f"{t_true[k]:.9f}", f"{tag[k]:.7f}", *(f"{v:.4f}" for v in pos[k]),
                        *(f"{v:.5f}" for v in vel[k]), f"{bias[k]:.5f}", f"{drift[k]:.6f}", int(n_g[k]), int(n_r[k])])
    np.savez_compressed(out / "truth_geometry.npz", t_gps_s=t_true, sat_id=np.array(const.sat_id), visible=vis,
                        los_unit=los, el_rad=acc["el"], el_atmo_rad=acc["el_atmo"], iono_slant_m=acc["iono"],
                        tropo_slant_m=acc["tropo"], carrier_hz=carrier)
    meta = {
        "scenario": scn.source, "seed": scn.run.seed, "receiver": opts.receiver, "t0_gps_s": float(tag[0]),
        "epochs": n, "rate_hz": rate, "duration_s": duration,
        "clock": {"bias0_m": opts.clock_bias0, "drift0_m_s": opts.clock_drift0, "psd_1_s": clock.psd_1_s},
        "receiver_config": {"sigma_pr_m": cfg.sigma_pr_m, "sigma_prr_m_s": cfg.sigma_prr_m_s,
                            "sigma_phase_m": cfg.sigma_phase_m, "el_mask_deg": math.degrees(cfg.el_mask_rad),
                            "gps_glonass_offset_m": cfg.gps_glonass_offset_m},
        "atmosphere": {
            "iono": None if opts.no_iono else {"zenith_m_at_gps_l1": cfg.iono_zenith_m, "model": (
                "constant zenith group delay, thin-shell mapping 1/sqrt(1-(R cos el/(R+h))^2), R 6371 km, h 432.5 km, "
                "geocentric elevation, scaled (f_L1/f)^2; +code, -phase")},
            "tropo": None if opts.no_tropo else {"zenith_m": cfg.tropo_zenith_m,
                                                 "model": "U_g / sin(geocentric elevation), code and phase"},
            "klobuchar_in_nav_header": None if klob is None else {"alpha": klob[0], "beta": klob[1]},
        },
        "nav": {"spacing_s": NAV_SPACING_S, "gps_records": len(gps_recs), "glonass_records": len(glo_recs),
                "gps_orbit": "exact (the simulated IS-GPS-200 elements re-referenced to each t_oe)",
                "gps_clock_fit_max_m": gps_clock_res_s * C_M_S,
                "glonass_fit_max_m": glo_fit_max_m,
                "glonass_fit_rms_of_record_max_m": float(np.sqrt(np.mean(glo_errs ** 2))) if glo_errs.size else 0.0},
        "snr_dbhz": SNR_DBHZ,
        "files": ["sim.obs", "sim.nav", "truth.csv", "truth_geometry.npz"],
    }
    return write_json(out / "export.json", meta, seed=scn.run.seed, scenario=scn)


# --------------------------------------------------------------------------------------------- RTKLIB

#: rnx2rtkp settings of every run (2.4.3 option names); navsys / ionoopt / tropopt vary
RTKLIB_CONF = {"pos1-posmode": "single", "pos1-frequency": "l1", "pos1-soltype": "forward", "pos1-elmask": "0",
               "pos1-sateph": "brdc", "out-solformat": "xyz", "out-outhead": "on", "out-timesys": "gpst",
               "out-timeform": "tow", "out-timendec": "3"}
#: RTKLIB 2.4.3 pntpos.c error model of a single-point code residual (variance terms, m^2)
_RTK_ERR = {"eratio": 100.0, "a": 0.003, "b": 0.003, "efact": {"G": 1.0, "R": 1.5}, "ura_gps": 2.4,
            "eph_glo": 5.0, "cbias": 0.3, "ion_off": 5.0, "trop_off": 3.0, "saas": 0.3, "brdci": 0.5}


def run_rnx2rtkp(out: Path, systems: str = "GR", corrections: bool = False, exe: str = "rnx2rtkp") -> Path:
    """rnx2rtkp single point on DIR/sim.obs + sim.nav; returns the .pos file."""
    import subprocess

    conf = dict(RTKLIB_CONF, **{"pos1-navsys": "5" if systems == "GR" else "1",
                                "pos1-ionoopt": "brdc" if corrections else "off",
                                "pos1-tropopt": "saas" if corrections else "off"})
    name = f"rtklib_{systems}_{'brdc_saas' if corrections else 'off'}"
    (out / f"{name}.conf").write_text("".join(f"{k:<18} ={v}\n" for k, v in conf.items()))
    pos = out / f"{name}.pos"
    subprocess.run([exe, "-k", str(out / f"{name}.conf"), "-o", str(pos), str(out / "sim.obs"), str(out / "sim.nav")],
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=600)
    return pos


def read_pos(path) -> tuple[np.ndarray, np.ndarray]:
    """(GPS seconds (K,), ECEF (K, 3)) of an rnx2rtkp xyz/tow .pos file."""
    rows = [ln.split() for ln in Path(path).read_text().splitlines() if ln.strip() and not ln.startswith("%")]
    if not rows:
        return np.zeros(0), np.zeros((0, 3))
    a = np.array([[float(v) for v in r[:5]] for r in rows])
    return a[:, 0] * 604800.0 + a[:, 1], a[:, 2:5]


def score(out: Path, pos_file, systems: str = "GR", corrections: bool = False) -> dict:
    """RTKLIB's solution against truth.csv (ENU about the first true position): mean and std per axis,
    and what the simulated world predicts for it from the truth geometry (truth_geometry.npz):
    the scatter sigma_pr * DOP (equal weights) and with RTKLIB's own weights (its pntpos error
    model), and the bias the simulated atmosphere puts into a solution that does not correct it
    (the weighted least-squares image of the slant delays)."""
    from sitl import geodesy

    t_sol, x_sol = read_pos(pos_file)
    truth = np.genfromtxt(out / "truth.csv", delimiter=",", names=True)
    with np.load(out / "truth_geometry.npz") as z:  # read each array once (an NpzFile decompresses per access)
        geo = {name: z[name] for name in z.files}
    meta = json.loads((out / "export.json").read_text())
    sigma = meta["receiver_config"]["sigma_pr_m"]
    t_true = truth["t_gps_s"]
    k = np.searchsorted(t_true, t_sol - 0.5)
    ok = (k < t_true.size) & (np.abs(t_true[np.minimum(k, t_true.size - 1)] - t_sol) < 1e-3)
    k, t_sol, x_sol = k[ok], t_sol[ok], x_sol[ok]
    pos_true = np.stack([truth["x_m"], truth["y_m"], truth["z_m"]], axis=1)
    lat, lon, h = geodesy.ecef_to_geodetic(pos_true[0])
    R = geodesy.enu_rotation(lat, lon)
    err = (x_sol - pos_true[k]) @ R.T
    sys_ = np.array([s[0] for s in geo["sat_id"]])
    use = geo["visible"] & (np.isin(sys_, list(systems))[None, :])
    cov_eq, cov_rtk, bias = np.zeros((3, 3)), np.zeros((3, 3)), np.zeros(3)
    n_ok = 0
    for kk in k:
        j = np.flatnonzero(use[kk])
        if j.size < 4 + (systems == "GR"):
            continue
        lat_k, lon_k, _ = geodesy.ecef_to_geodetic(pos_true[kk])
        Rk = geodesy.enu_rotation(lat_k, lon_k)
        H = np.zeros((j.size, 4 + (systems == "GR")))
        H[:, :3] = -(geo["los_unit"][kk, j] @ Rk.T)
        H[:, 3] = 1.0
        if systems == "GR":
            H[:, 4] = sys_[j] == "R"
            if not (H[:, 4].any() and (~H[:, 4].astype(bool)).any()):
                continue
        el = geo["el_rad"][kk, j]
        e = _RTK_ERR
        var = (np.where(sys_[j] == "R", e["efact"]["R"], e["efact"]["G"]) ** 2
               * e["eratio"] ** 2 * (e["a"] ** 2 + e["b"] ** 2 / np.sin(el))
               + np.where(sys_[j] == "R", e["eph_glo"] ** 2, e["ura_gps"] ** 2) + e["cbias"] ** 2)
        d = np.nan_to_num(geo["iono_slant_m"][kk, j]) + np.nan_to_num(geo["tropo_slant_m"][kk, j])
        if corrections:
            var = var + (e["brdci"] * geo["iono_slant_m"][kk, j]) ** 2 + (e["saas"] / (np.sin(el) + 0.1)) ** 2
        else:
            var = var + e["ion_off"] ** 2 + e["trop_off"] ** 2
        N = np.linalg.inv(H.T @ H)
        cov_eq += sigma ** 2 * N[:3, :3]
        W = 1.0 / var
        A = np.linalg.inv((H.T * W) @ H) @ (H.T * W)
        cov_rtk += sigma ** 2 * (A @ A.T)[:3, :3]
        bias += (A @ d)[:3]
        n_ok += 1
    n_ok = max(n_ok, 1)
    return {
        "systems": systems, "corrections": "klobuchar+saastamoinen" if corrections else "off", "epochs": int(len(k)),
        "epochs_truth": int(t_true.size),
        "mean_enu_m": err.mean(axis=0).round(4).tolist(), "std_enu_m": err.std(axis=0, ddof=1).round(4).tolist(),
        "rms_3d_m": round(float(np.sqrt(np.mean(np.sum(err ** 2, axis=1)))), 4),
        "predicted_std_enu_m_sigma_dop": np.sqrt(np.diag(cov_eq) / n_ok).round(4).tolist(),
        "predicted_std_enu_m_rtklib_weights": np.sqrt(np.diag(cov_rtk) / n_ok).round(4).tolist(),
        "predicted_bias_enu_m_uncorrected_atmosphere": (bias / n_ok).round(4).tolist(),
        "mean_dop_enu": np.sqrt(np.diag(cov_eq) / n_ok / sigma ** 2).round(3).tolist(),
    }


def rtklib_report(out: Path, atmosphere: bool) -> dict:
    runs = []
    for systems in ("GR", "G"):
        for corr in ((False, True) if atmosphere else (False,)):
            runs.append(score(out, run_rnx2rtkp(out, systems, corr), systems, corr))
    doc = {"rnx2rtkp": "RTKLIB 2.4.3 single point", "runs": runs}
    return write_json(out / "rtklib.json", doc, scenario={"conf": RTKLIB_CONF, "atmosphere": atmosphere})


def _fmt3(v) -> str:
    return "/".join(f"{x:+.3f}" for x in v)


def main(args=None) -> int:
    """``main(namespace)`` for the `skyfuse gnss export` subcommand (UsageError propagates to the
    command line), or ``main(argv list)`` standing alone (one line on stderr, exit 2)."""
    if args is None or isinstance(args, (list, tuple)):
        parser = Parser(prog="skyfuse gnss export", flags=add_args)
        try:
            return main(parser.parse_args(list(args or [])))
        except UsageError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    opts = options_of(ExportOptions, args)
    meta = export(opts)
    print(f"gnss export: {meta['epochs']} epochs of {opts.receiver} receiver -> {opts.out} "
          f"(GLONASS record fit max {meta['nav']['glonass_fit_max_m']:.3f} m, GPS clock fit max "
          f"{meta['nav']['gps_clock_fit_max_m'] * 1e3:.2f} mm)")
    if opts.rtklib:
        import shutil

        if shutil.which("rnx2rtkp") is None:
            raise UsageError("gnss export: --rtklib needs RTKLIB's rnx2rtkp on PATH (Debian package rtklib)")
        doc = rtklib_report(Path(opts.out), not (opts.no_iono and opts.no_tropo))
        for r in doc["runs"]:
            print(f"  rnx2rtkp {r['systems']:2s} corrections {r['corrections']:23s}: mean ENU "
                  f"{_fmt3(r['mean_enu_m'])} m, std {_fmt3(r['std_enu_m'])} m (sigma*DOP {_fmt3(r['predicted_std_enu_m_sigma_dop'])},"
                  f" RTKLIB weights {_fmt3(r['predicted_std_enu_m_rtklib_weights'])}); predicted uncorrected-atmosphere bias "
                  f"{_fmt3(r['predicted_bias_enu_m_uncorrected_atmosphere'])} m; {r['epochs']}/{r['epochs_truth']} epochs")
    return 0
