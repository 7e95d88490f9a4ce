"""The seed 000 filter on real GPS L1 observations (`skyfuse gnss solve`), one receiver.

The same models and the same EKF as the simulated experiment
(sitl.app.experiments.iono_tropo_filters): IonoTropoTransition / IonoTropoGnss
(filters.iono_tropo), filters.ekf's predict and Joseph update, the variant-2 code-noise-state
increment model and the state edits of sitl.app.experiments.iono_tropo_models, and
filters.cycleslip. What differs is the data, so only the bookkeeping around them is here.

Variants (the experiment's three):
* code_doppler: pseudoranges and pseudorange rates. With a Doppler in the file (D1, D1C) the rate is
  -lambda_1 D + c d(dt_sv)/dt (sigma_doppler_m_s). The station file has none, so the rate row is the
  L1 phase's rate over the epoch, moved from the interval's middle to its end with the broadcast
  geometry and rid of the atmosphere's change that the seed's rate model leaves out (the filter's
  own predicted U_g, I_g on the two epochs' mappings): prr_j(k) = (phase_j(k) - phase_j(k-1) -
  a_j) / T + [u_j . v_j - (rho_j(k) - rho_j(k-1)) / T], a_j = U_g dm_U - I_g dm_I (1 cm/s of
  tropo at 10 deg); the bracket is the satellite's range curvature over T (m/s at T = 30 s), rho
  from the filter's predicted position. Only on a slip-free epoch pair (LLI and the detector);
  elsewhere the row is inert (z = h, sigma 1e3 m/s).
* phase_increments: plus the code-minus-carrier increments E_j over cmc_window_s, the code noise at
  each window start a state (the experiment's cmc_noise = "states"), on arcs the detector calls
  slip-free over the window.
* carrier_phase: pseudoranges plus the ambiguous L1 phase with one constant K_j per satellite
  (eq 38), appended at rise, dropped at set, reset at a flagged slip (mean from the phase minus
  the predicted phase, variance sigma0_amb_m^2). The phase-rate rows are inert here: the phase
  rows hold the same information and would count it twice.

Tuning for 30 s epochs (the seed's 0.1 s values would not do); defaults in
sitl.app.gnss.solve.GnssSolveOptions:
* the process noise is a continuous-time PSD, discretised exactly over T by IonoTropoTransition,
  so the rate itself needs no rescaling; what T changes is which terms matter:
* clock: a free-running receiver oscillator (this Trimble: ~418 m/s drift, no steps). N_eps is
  fitted to the file (`clock_psd_from_phase`: the clock change per epoch from the
  epoch-differenced phase, var(second difference) ~ c^2 N_eps (2/3) T^3 for a drift random walk),
  with the seed's TCXO value as a floor. On 0759 the fit gives 2.5e-22, below the floor: the
  seed's 0.8e-20 is used (the results do not move between 1e-21 and 1e-19);
* receiver motion: --static sets velocity 0 with no process noise (a geodetic station); otherwise
  q_accel_m2_s3 (default 1e-4: 0.05 m/s of velocity wander per 30 s);
* atmosphere: random walks. I_g moves by ~1 m an hour in the morning (q_iono 3e-4 m^2/s: 1 m in
  1 h); U_g by centimetres (q_tropo 1e-7 m^2/s: 2 cm in 1 h). Priors: I_g from broadcast
  Klobuchar's vertical delay at the first fix and epoch, sigma half of it (the ICD's model takes
  out about half the delay); U_g 2.3 +- 0.5 m (a standard atmosphere at sea level);
* the ionosphere's shape (iono_shape): the seed's one zenith value on a thin shell (eq 9) cannot
  hold the horizontal gradient of the real ionosphere, which then goes into the horizontal
  position (east -1.0 m, north -1.1 m on 0759 with carrier phase); by default (auto) the filter
  keeps its one zenith state I_g but maps it with Klobuchar's slant / vertical per line of sight
  (IonoTropoGnss.iono_obliquity), which carries the broadcast model's gradient;
* noise: elevation-weighted code, sigma_pr_m / sin(el) (code_weighting "sin"; "rtklib" adds
  RTKLIB's elevation-independent floor, see code_sigma_m), 0.6 m: four times the white code noise
  measured on the file (epoch-differenced code minus carrier: 0.12-0.15 m sin(el)^-1), for the
  broadcast orbit and clock errors and the multipath that is correlated over minutes; a phase row
  sigma_phase_m = 5 cm: the phase noise is 3 mm, the rest is what a one-zenith atmosphere leaves.
Delta_A (GPS - GLONASS offset) is not observable with GPS only: held at 0 (prior variance 0).

Cycle slips: the L1 LLI bit and filters.cycleslip on the geometry-removed phase. With no Doppler
the test is fed phase - rho (broadcast orbit, the filter's predicted position), a zero rate, and as
the expected change the common mode (median over satellites: the receiver clock) plus the filter's
own slant tropo/iono change; sigma_model_m_s bounds what is left (orbit, position error times the
line-of-sight turn, atmosphere error) per second.
"""
from __future__ import annotations

import math
import time

import numpy as np

from filters.cycleslip import CycleSlipConfig, CycleSlipDetector
from filters.ekf import ekf_predict, ekf_update
from filters.iono_tropo import (
    F_REF_HZ, IDX_CLOCK, IDX_DRIFT, IDX_GPS_GLO, IDX_IONO, IDX_TROPO, N_BASE, IonoTropoGnss, IonoTropoTransition,
    iono_mapping, tropo_mapping, elevation_rad,
)
from sitl.app.experiments.iono_tropo_models import _append_states, _CodeNoiseStateModel, _drop_states
from sitl.constants import C_M_S
from sitl.geodesy import ecef_to_aer, ecef_to_geodetic
from sitl.gnss.klobuchar import klobuchar_delay_m

VARIANTS = ("code_doppler", "phase_increments", "carrier_phase")
MIN_SATS = 4
INERT_SIGMA_PRR_M_S = 1e3
CLOCK_PSD_FLOOR_1_S = 0.8e-20  # the seed's TCXO (filters.iono_tropo.CLOCK_PSD_1_S)
SEED_SIGMA0_IONO_M = 20.0  # the seed's prior sigma of I_g (IonoTropoScenario.sigma0_iono_m)

__all__ = ["VARIANTS", "run_filter", "clock_psd_from_phase", "code_sigma_m"]


def clock_psd_from_phase(ep, el_mask_deg: float) -> float:
    """N_eps (1/s) of a drift random walk from the file: the receiver clock change per epoch
    from the epoch-differenced phase (common mode of phase - rho over the satellites, median),
    then var(second difference) = c^2 N_eps (2/3) T^3 (white frequency noise neglected)."""
    T = float(np.median(np.diff(ep.t_gps_s)))
    rx = np.nanmedian(ep.ls_pos_m, axis=0)
    rho = np.linalg.norm(ep.sat_pos_m - rx, axis=-1)
    el = ecef_to_aer(rx, ep.sat_pos_m)[1]
    g = np.where(el >= math.radians(el_mask_deg), ep.phase_m - rho, np.nan)
    d = np.diff(g, axis=0)
    d = np.where(np.abs(d - np.nanmedian(d, axis=1, keepdims=True)) < 1.0, d, np.nan)  # slips out
    with np.errstate(all="ignore"):
        dc = np.nanmedian(d, axis=1)
    dd = np.diff(dc)
    dd = dd[np.isfinite(dd)]
    if dd.size < 3:
        return CLOCK_PSD_FLOOR_1_S
    return max(float(np.var(dd)) / (C_M_S**2 * (2.0 / 3.0) * T**3), CLOCK_PSD_FLOOR_1_S)


def _transition(opts, n_amb, clock_psd, still):
    return IonoTropoTransition(n_amb=n_amb, q_accel_m2_s3=0.0 if still else opts.q_accel_m2_s3,
                               clock_psd_1_s=clock_psd, q_gps_glo_m2_s=0.0, q_iono_m2_s=opts.q_iono_m2_s,
                               q_tropo_m2_s=opts.q_tropo_m2_s)


def run_filter(ep, opts, progress=None, fixed_position_m=None) -> dict:
    """One pass of the chosen variant over the file's epochs; per-epoch series and counts.
    fixed_position_m (3,): RTKLIB's "fixed" mode -- the receiver held at known coordinates (no
    position or velocity uncertainty, no motion); clock, atmosphere and ambiguities estimated."""
    variant = opts.variant
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    t_wall = time.perf_counter()
    t = ep.t_gps_s
    T, S = ep.pr_m.shape
    dts = np.diff(t)
    dt_nom = float(np.median(dts)) if T > 1 else 30.0
    mask = math.radians(opts.el_mask_deg)
    clock_psd = opts.clock_psd_1_s if opts.clock_psd_1_s is not None else clock_psd_from_phase(ep, opts.el_mask_deg)
    still = opts.static or fixed_position_m is not None  # no motion: velocity 0, no process noise
    trans_cache = {}

    def trans(n):
        if n not in trans_cache:
            trans_cache[n] = _transition(opts, n, clock_psd, still)
        return trans_cache[n]

    have_klob = ep.ion_alpha is not None and ep.ion_beta is not None
    shape = opts.iono_shape if opts.iono_shape != "auto" else ("klobuchar" if have_klob else "thin_shell")
    use_klob = shape == "klobuchar"
    if use_klob and not have_klob:
        raise ValueError(f"{ep.path}: --iono-shape klobuchar needs ION ALPHA/BETA in the navigation header")

    def obliquity(pos, az, el_, t_s):
        """(n,) slant-to-zenith iono ratio: the thin shell m_I (eq 9) or Klobuchar's slant / vertical."""
        if not use_klob:
            return None
        lat, lon, _ = ecef_to_geodetic(pos)
        sl = klobuchar_delay_m(ep.ion_alpha, ep.ion_beta, lat, lon, az, el_, t_s)
        return sl / klobuchar_delay_m(ep.ion_alpha, ep.ion_beta, lat, lon, 0.0, math.pi / 2, t_s)

    carrier = np.full(S, F_REF_HZ)
    is_gps = np.ones(S, dtype=bool)
    k0 = int(np.flatnonzero(np.isfinite(ep.ls_clock_m))[0])
    x = np.zeros((1, N_BASE))
    x[0, 0:3] = ep.ls_pos_m[k0] if fixed_position_m is None else fixed_position_m
    x[0, IDX_CLOCK] = ep.ls_clock_m[k0]
    iono0, sd_iono0 = opts.iono_prior_m, opts.sigma0_iono_m
    if iono0 is None:
        iono0 = 0.0
        if have_klob:
            lat0, lon0, _ = ecef_to_geodetic(ep.ls_pos_m[k0])
            iono0 = float(klobuchar_delay_m(ep.ion_alpha, ep.ion_beta, lat0, lon0, 0.0, math.pi / 2, t[k0]))
            sd_iono0 = max(0.5 * iono0, 0.5) if sd_iono0 is None else sd_iono0
    if sd_iono0 is None:
        sd_iono0 = SEED_SIGMA0_IONO_M
    x[0, IDX_IONO] = iono0
    x[0, IDX_TROPO] = opts.tropo_prior_m
    sd = np.zeros(N_BASE)
    sd[0:3] = opts.sigma0_pos_m if fixed_position_m is None else 0.0
    sd[IDX_CLOCK] = opts.sigma0_clock_bias_m
    sd[4:7] = 0.0 if still else opts.sigma0_vel_m_s
    sd[IDX_DRIFT] = opts.sigma0_clock_drift_m_s
    sd[IDX_GPS_GLO] = 0.0
    sd[IDX_IONO] = sd_iono0
    sd[IDX_TROPO] = opts.sigma0_tropo_m
    P = np.diag(sd**2)[None]

    det = CycleSlipDetector((S,), CycleSlipConfig(sigma_prr_m_s=0.0, sigma_phase_m=opts.sigma_phase_noise_m,
                                                  sigma_model_m_s=opts.slip_model_m_s,
                                                  max_dt_s=1.5 * dt_nom))
    W = max(1, round(opts.cmc_window_s / dt_nom))
    amb_sats: list[int] = []  # variant 3: satellite of K state N_BASE + i
    e_sats: list[int] = []  # variant 2: satellite whose window-start code noise is state N_BASE + i
    e_m = np.full(S, np.nan)
    e_B = np.full(S, np.nan)
    counts = {"epochs_updated": 0, "epochs_skipped": 0, "lli_resets": 0, "detector_slips": 0, "k_resets": 0,
              "increments_used": 0, "increments_rejected_slip": 0, "rate_rows": 0}
    keys = ("pos_x", "pos_y", "pos_z", "clock_m", "drift_m_s", "iono_m", "tropo_m", "iono_sd_m", "tropo_sd_m",
            "nis", "n_sats", "n_state")
    ser = {k: np.full(T, np.nan) for k in keys}
    prev = {"phase": np.full(S, np.nan), "sat": np.full((S, 3), np.nan), "pos": None, "el": np.full(S, np.nan),
            "mI": np.full(S, np.nan)}
    report_every = max(1, T // 10)

    for k in range(T):
        dt = float(t[k] - t[k - 1]) if k > 0 else 0.0
        x_pred, P_pred = (ekf_predict(x, P, trans(x.shape[-1] - N_BASE), dt) if k > 0 else (x, P))
        pos_f = x_pred[0, 0:3]
        sp_all, sv_all = ep.sat_pos_m[k], ep.sat_vel_m_s[k]
        fin = np.isfinite(ep.pr_m[k])
        el = np.full(S, np.nan)
        az = np.full(S, np.nan)
        az[fin], el[fin], _ = ecef_to_aer(pos_f, sp_all[fin])
        mI_all = np.full(S, np.nan)
        if use_klob:
            mI_all[fin] = obliquity(pos_f, az[fin], el[fin], t[k])
        else:
            mI_all[fin] = iono_mapping(elevation_rad(pos_f, sp_all[fin]))
        rho = np.full(S, np.nan)
        rho[fin] = np.linalg.norm(sp_all[fin] - pos_f, axis=-1)

        # ---- cycle slips on the real phase (all variants: the rate rows need slip-free pairs too)
        ph = np.where(fin & np.isfinite(ep.phase_m[k]), ep.phase_m[k], np.nan)
        lli = (ep.lli_l1[k] & 1).astype(bool)
        counts["lli_resets"] += int(np.sum(lli & np.isfinite(ph)))
        geo = ph - rho
        if prev["pos"] is not None:
            rho_prev_new = np.linalg.norm(prev["sat"] - pos_f, axis=-1)  # last epoch's satellites, this position
            rho_prev_old = np.linalg.norm(prev["sat"] - prev["pos"], axis=-1)
            both = np.isfinite(geo) & np.isfinite(prev["phase"])
            atmo = np.zeros(S)
            ok_el = both & np.isfinite(el) & np.isfinite(prev["el"]) & (el > 0) & (prev["el"] > 0)
            el_c = np.where(ok_el, el, 1.0)
            el_p = np.where(ok_el, prev["el"], 1.0)
            atmo[ok_el] = (x_pred[0, IDX_TROPO] * (tropo_mapping(el_c) - tropo_mapping(el_p))
                           - x_pred[0, IDX_IONO] * (mI_all - prev["mI"]))[ok_el]
            d = (geo - (prev["phase"] - rho_prev_new)) - atmo
            common = float(np.nanmedian(d[both])) if both.sum() >= 3 else 0.0
            expected = np.where(np.isfinite(geo), common + atmo + (rho_prev_old - rho_prev_new), 0.0)
            expected = np.nan_to_num(expected)
        else:
            expected = np.zeros(S)
        lock = np.where(lli, 0, 1)
        res_slip = det.update(t[k], geo, np.where(np.isfinite(geo), 0.0, np.nan), lock_count=lock, expected_m=expected)
        slip = res_slip.slip
        counts["detector_slips"] += int(slip.sum())
        pair_ok = res_slip.tested & ~slip  # slip-free from k-1 to k

        tracked = fin & (np.nan_to_num(el, nan=-1.0) >= mask)
        idx = np.flatnonzero(tracked)
        ser["n_sats"][k] = idx.size
        if idx.size < MIN_SATS:
            counts["epochs_skipped"] += 1
            x, P = x_pred, P_pred
            prev.update(phase=ph, sat=sp_all.copy(), pos=pos_f.copy(), el=el, mI=mI_all)
            _record(ser, k, x, P, np.nan)
            continue
        sp_v, sv_v = sp_all[idx][None], sv_all[idx][None]
        sin_el = np.sin(el[idx])
        sig_pr = code_sigma_m(opts.sigma_pr_m, sin_el, opts.code_weighting)

        # ---- the rate rows (variants 1, 2): the file's Doppler, else the phase rate moved to the
        # epoch and rid of the filter's own atmosphere change; carrier_phase: inert
        prr = np.zeros(idx.size)
        sig_prr = np.full(idx.size, INERT_SIGMA_PRR_M_S)
        have_rate = np.zeros(idx.size, dtype=bool)
        j = idx
        if variant != "carrier_phase" and ep.doppler_prr_m_s is not None:
            dop = ep.doppler_prr_m_s[k, j]
            have_rate = np.isfinite(dop)
            prr[have_rate] = dop[have_rate]
            sig_prr[have_rate] = opts.sigma_doppler_m_s
        elif variant != "carrier_phase" and k > 0:
            ok = pair_ok[j] & np.isfinite(prev["phase"][j]) & np.isfinite(atmo[j])
            if ok.any():
                u = (sp_all[j] - pos_f) / rho[j, None]
                rho_prev = np.linalg.norm(prev["sat"][j] - pos_f, axis=-1)
                curv = np.sum(u * sv_all[j], axis=-1) - (rho[j] - rho_prev) / dt
                prr[ok] = ((ph[j] - prev["phase"][j] - atmo[j]) / dt + curv)[ok]
                sig_prr[ok] = opts.sigma_prr_m_s
                have_rate = ok
        counts["rate_rows"] += int(have_rate.sum())
        obl = mI_all[idx][None] if use_klob else None
        tob = _tropo_obliquity(opts.tropo_mapping, sin_el)
        base = IonoTropoGnss(sp_v, sv_v, carrier[idx], is_gps[idx], sig_pr[None], sig_prr[None],
                             n_state=x_pred.shape[-1], iono_obliquity=obl, tropo_obliquity=tob)
        h0 = base.h(x_pred)[0]
        prr_z = np.where(have_rate, prr, h0[idx.size:2 * idx.size])
        z = np.concatenate([ep.pr_m[k, idx], prr_z])[None]

        if variant == "code_doppler":
            res = ekf_update(x_pred, P_pred, z, base)
        elif variant == "phase_increments":
            res, x_pred, P_pred = _increment_update(ep, k, idx, x_pred, P_pred, z, sp_v, sv_v, carrier, is_gps,
                                                    sig_pr, sig_prr, det, W, dt_nom, e_sats, e_m, e_B, counts,
                                                    2.0 * opts.sigma_phase_noise_m**2, mI_all, obl, tob)
        else:
            res, amb_sats = _phase_update(ep, ph, idx, slip, lli, x_pred, P_pred, z, sp_v, sv_v, carrier, is_gps,
                                          sig_pr, sig_prr, opts, amb_sats, counts, obl, tob)
        x, P = res.x, res.P
        counts["epochs_updated"] += 1
        _record(ser, k, x, P, float(res.nis[0]))
        prev.update(phase=ph, sat=sp_all.copy(), pos=pos_f.copy(), el=el, mI=mI_all)
        if progress and (k % report_every == 0 or k == T - 1):
            progress(f"sats {idx.size:2d}  I_g {x[0, IDX_IONO]:6.2f} m  U_g "
                     f"{x[0, IDX_TROPO]:5.2f} m  ({time.perf_counter() - t_wall:.2f} s)", done=k + 1, total=T)

    return {"series": ser, "counts": counts, "clock_psd_1_s": clock_psd, "iono_shape": shape, "iono_prior_m": iono0,
            "sigma0_iono_m": sd_iono0, "cmc_window_epochs": W,
            "epoch_interval_s": dt_nom, "wall_s": time.perf_counter() - t_wall}


def code_sigma_m(sigma_zenith_m, sin_el, law: str = "sin"):
    """Code sigma per line of sight: sigma / sin el (the seed's), or RTKLIB's variance
    a^2 + b^2 / sin^2 el with a = b = sigma / sqrt 2 (RTKLIB 2.4.2 rtkpos.c and ppp.c varerr; the
    same sigma at the zenith; its pntpos.c divides b^2 by sin el only once)."""
    if law == "sin":
        return sigma_zenith_m / sin_el
    if law == "rtklib":
        return sigma_zenith_m * np.sqrt(0.5 * (1.0 + 1.0 / sin_el**2))
    raise ValueError(f"code weighting must be 'sin' or 'rtklib', got {law!r}")


def _tropo_obliquity(name, sin_el):
    """None (the seed's 1/sin of the geocentric elevation, inside IonoTropoGnss) or (1, n) fixed values:
    1/sin of the elevation above the ellipsoid's normal, or the RTCA MOPS (DO-229) mapping
    1.001 / sqrt(0.002001 + sin^2 el), which stays finite at the horizon and is ~3.5% below 1/sin at 10 deg."""
    if name == "seed":
        return None
    if name == "geodetic":
        return (1.0 / sin_el)[None]
    return (1.001 / np.sqrt(0.002001 + sin_el**2))[None]


def _record(ser, k, x, P, nis):
    ser["pos_x"][k], ser["pos_y"][k], ser["pos_z"][k] = x[0, 0:3]
    ser["clock_m"][k] = x[0, IDX_CLOCK]
    ser["drift_m_s"][k] = x[0, IDX_DRIFT]
    ser["iono_m"][k] = x[0, IDX_IONO]
    ser["tropo_m"][k] = x[0, IDX_TROPO]
    ser["iono_sd_m"][k] = math.sqrt(P[0, IDX_IONO, IDX_IONO])
    ser["tropo_sd_m"][k] = math.sqrt(P[0, IDX_TROPO, IDX_TROPO])
    ser["nis"][k] = nis
    ser["n_state"][k] = x.shape[-1]


def _increment_update(ep, k, idx, x_pred, P_pred, z, sp_v, sv_v, carrier, is_gps, sig_pr, sig_prr, det, W,
                      dt_nom, e_sats, e_m, e_B, counts, var_e, m_now, obl, tob):
    """Variant 2 (the experiment's cmc_noise="states"): on the W-epoch grid, the code noise of every
    tracked satellite becomes a state; at the next grid epoch E_j = B_j(t) - B_j(t - W) ties it to
    the one at the window start (2 k dm I_g + e_new - e_old, variance 2 sigma_phase^2)."""
    tracked = set(idx.tolist())
    gone = [i for i, s in enumerate(e_sats) if s not in tracked]
    if gone:  # set inside its window: its start noise is marginalised, no increment
        x_pred, P_pred = _drop_states(x_pred, P_pred, [N_BASE + i for i in gone])
        e_sats[:] = [s for i, s in enumerate(e_sats) if i not in set(gone)]
    pr_cols = np.full(idx.size, -1)
    inc_rows = np.zeros(0, dtype=int)
    old = np.zeros(0, dtype=int)
    inc_new, coef, ok, E = old, np.zeros((1, 0)), np.zeros((1, 0), bool), np.zeros((1, 0))
    B_now = ep.pr_m[k] - ep.phase_m[k]
    if k % W == 0:
        n_old = len(e_sats)
        x_pred, P_pred = _append_states(x_pred, P_pred, idx.size)
        cols = N_BASE + n_old + np.arange(idx.size)
        P_pred[:, cols, cols] = sig_pr**2
        pr_cols = cols
        loc = {s: j for j, s in enumerate(idx.tolist())}
        inc_rows = np.array([loc[s] for s in e_sats], dtype=int)
        old = N_BASE + np.arange(n_old)
        inc_new = pr_cols[inc_rows]
        sats = idx[inc_rows]
        ok = det.slip_free(W * dt_nom - 0.5 * dt_nom)[sats][None] & np.isfinite(B_now[sats] - e_B[sats])[None]
        counts["increments_used"] += int(ok.sum())
        counts["increments_rejected_slip"] += int((~ok).sum())
        coef = (2.0 * (m_now[sats] - e_m[sats]))[None]
        E = np.nan_to_num(B_now[sats] - e_B[sats])[None]
        coef = np.nan_to_num(coef)
        e_sats[:] = e_sats + idx.tolist()
        e_m[idx] = m_now[idx]
        e_B[idx] = B_now[idx]
    base = IonoTropoGnss(sp_v, sv_v, carrier[idx], is_gps[idx], sig_pr[None], sig_prr[None],
                         n_state=x_pred.shape[-1], iono_obliquity=obl, tropo_obliquity=tob)
    m2 = _CodeNoiseStateModel(base, pr_cols, inc_rows, inc_new, old, coef, ok, var_e)
    z2 = np.concatenate([z, np.where(ok, E, 0.0)], axis=1)
    res = ekf_update(x_pred, P_pred, z2, m2)
    if old.size:  # the ended windows' start noises: used, marginalised
        rx, rP = _drop_states(res.x, res.P, old)
        e_sats[:] = e_sats[old.size:]
        res = res._replace(x=rx, P=rP)
    return res, x_pred, P_pred


def _phase_update(ep, ph, idx, slip, lli, x_pred, P_pred, z, sp_v, sv_v, carrier, is_gps, sig_pr, sig_prr, opts,
                  amb_sats, counts, obl, tob):
    """Variant 3: the ambiguous phase rows with one K_j each (appended at rise, dropped at set,
    reset at a slip or an LLI flag), as the experiment's run_streamed(variant=3)."""
    x, P = x_pred, P_pred
    has_ph = np.isfinite(ph[idx])
    tracked = set(idx[has_ph].tolist())
    gone = [i for i, s in enumerate(amb_sats) if s not in tracked]
    if gone:
        x, P = _drop_states(x, P, [N_BASE + i for i in gone])
        amb_sats = [s for i, s in enumerate(amb_sats) if i not in set(gone)]
    new = [s for s in idx[has_ph].tolist() if s not in set(amb_sats)]
    if new:
        x, P = _append_states(x, P, len(new))
        amb_sats = amb_sats + new
    reset_sats = [s for s in amb_sats if s not in set(new) and (slip[s] or lli[s])]
    counts["k_resets"] += len(reset_sats)
    init = [N_BASE + amb_sats.index(s) for s in new + reset_sats]
    kidx = np.array([N_BASE + amb_sats.index(s) if s in amb_sats else -1 for s in idx.tolist()])
    has = kidx >= 0
    m3 = IonoTropoGnss(sp_v, sv_v, carrier[idx], is_gps[idx], sig_pr[None], sig_prr[None],
                       sigma_phase_m=opts.sigma_phase_m, phase_state_index=kidx, use_phase=True, n_state=x.shape[-1],
                       iono_obliquity=obl, tropo_obliquity=tob)
    if init:
        x = x.copy()
        P = P.copy()
        hph = m3.h(x)[0, 2 * idx.size:]
        kinit = ph[idx[has]] - hph + x[0, kidx[has]]
        for c in init:
            jj = int(np.flatnonzero(kidx[has] == c)[0])
            x[0, c] = kinit[jj]
            P[0, c, :] = 0.0
            P[0, :, c] = 0.0
            P[0, c, c] = opts.sigma0_amb_m**2
    z3 = np.concatenate([z, ph[idx[has]][None]], axis=1)
    return ekf_update(x, P, z3, m3), amb_sats
