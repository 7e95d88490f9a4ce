"""The real observations of `skyfuse gnss solve`, made ready for the seed 000 filter.

    obs, nav = read_obs(path), read_nav(path)
    ep = prepare(obs, nav)            # GPS L1 only: C1 code, L1 phase (and P2/L2 for the reference)
    ep.pr_m, ep.phase_m               # (T, S) corrected for the satellite clock, m
    ep.sat_pos_m, ep.sat_vel_m_s      # (T, S, 3) in the ECEF frame of the reception instant
    ep.ls_pos_m, ep.ls_clock_m        # (T, 3), (T,) the code-only least-squares fix per epoch

Satellite states (broadcast ephemerides, sitl.gnss.broadcast, IS-GPS-200):
* emission time from the measured code: t_tx = t_rx - C1 / c - dt_sv(t_tx) (receiver tag minus
  the code's transit, which holds the receiver clock; the satellite clock by one fixed-point step);
* the satellite clock for an L1 C/A user: dt_sv - TGD (``clock_l1_s``: af0..af2, the
  relativistic e sqrt(A) sin E term, minus the broadcast TGD), added to code and phase:
  pr = C1 + c (dt_sv - TGD), phase = lambda_1 L1 + c (dt_sv - TGD);
* Sagnac / light time: the emission-time ECEF state rotated about z by w_e tau into the frame of
  the reception instant, tau = |s - X| / c from a receiver position X (the epoch's code-only fix;
  6 mm of satellite position per km of error in X), velocity rotated alike.
The filter's model (filters.iono_tropo) then sees |s - X| as the range, as in the simulation
(sitl.gnss.world.ephemeris_for_filter), whose truth applies the same two effects.

The code-only least-squares fix (position, clock; no atmosphere; all healthy satellites above 5
degrees once a first pass has an elevation) gives the light-time origin, the filter's prior at
the first epoch and the receiver-clock series that the process noise is tuned on (solve_filter).
Unhealthy satellites (health flag != 0) and satellites without a record in force are dropped and
counted; only GPS is used (the file's other systems are counted).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sitl.constants import C_M_S, OMEGA_E_GPS_RAD_S
from sitl.gnss.broadcast import gps_states
from sitl.gnss.rinex_common import GnssFileError

F_L1_HZ = 1575.42e6
F_L2_HZ = 1227.60e6
LAMBDA_L1_M = C_M_S / F_L1_HZ
LAMBDA_L2_M = C_M_S / F_L2_HZ
LS_ITERATIONS = 8
LS_MASK_DEG = 5.0
#: the observables used, by RINEX 2 / RINEX 3 code (the first one the file has)
OBS_CODES = {"C1": ("C1", "C1C"), "L1": ("L1", "L1C"), "P2": ("P2", "C2W", "C2P"), "L2": ("L2", "L2W", "L2P"),
             "D1": ("D1", "D1C")}

__all__ = ["Epochs", "prepare", "rotate_to_reception", "least_squares_fix", "F_L1_HZ", "F_L2_HZ",
           "LAMBDA_L1_M", "LAMBDA_L2_M"]


@dataclass(frozen=True, eq=False)
class Epochs:
    """GPS L1 observations of a file, per epoch (T) and satellite (S); NaN where not usable."""

    path: str
    t_gps_s: np.ndarray
    sats: tuple
    pr_m: np.ndarray  # C1 + c (dt_sv - TGD)
    phase_m: np.ndarray  # lambda_1 L1 + c (dt_sv - TGD)
    lli_l1: np.ndarray  # the L1 phase's loss-of-lock digits
    c1_m: np.ndarray  # raw code and phases, for the dual-frequency reference
    p2_m: np.ndarray
    l1_cyc: np.ndarray
    l2_cyc: np.ndarray
    lli: np.ndarray  # LLI of L1 | LLI of L2
    tgd_s: np.ndarray  # (T, S) broadcast TGD of the record in force
    sat_pos_m: np.ndarray
    sat_vel_m_s: np.ndarray
    ls_pos_m: np.ndarray
    ls_clock_m: np.ndarray
    approx_position_m: np.ndarray | None
    counts: dict
    ion_alpha: tuple | None = None  # the nav header's Klobuchar coefficients
    ion_beta: tuple | None = None
    doppler_prr_m_s: np.ndarray | None = None  # -lambda_1 D1 + c d(dt_sv)/dt, None without Doppler


def rotate_to_reception(pos_m, vel_m_s, tau_s):
    """R3(w_e tau) applied to emission-time ECEF states (..., 3): the frame of the reception instant."""
    th = OMEGA_E_GPS_RAD_S * np.asarray(tau_s, float)
    c, s = np.cos(th), np.sin(th)

    def rot(v):
        return np.stack([c * v[..., 0] + s * v[..., 1], c * v[..., 1] - s * v[..., 0], v[..., 2]], axis=-1)

    return rot(pos_m), rot(vel_m_s)


def least_squares_fix(pr_m, sat_pos_m, use, x0=None):
    """Code-only Gauss-Newton fix per epoch: (pos (T, 3), clock (T,) m, n used (T,)); no atmosphere.
    From the Earth's centre (x0 None); an epoch with fewer than 4 satellites gets NaN."""
    T = pr_m.shape[0]
    x = np.zeros((T, 4)) if x0 is None else np.array(x0, float)
    for _ in range(LS_ITERATIONS):
        with np.errstate(invalid="ignore", divide="ignore"):
            d = sat_pos_m - x[:, None, :3]
            rho = np.linalg.norm(d, axis=-1)
            y = np.where(use, pr_m - rho - x[:, 3:4], 0.0)
            H = np.concatenate([-d / rho[..., None], np.ones(rho.shape + (1,))], axis=-1)
            H = np.where(use[..., None], H, 0.0)
            N = np.einsum("tsi,tsj->tij", H, H)
            ok = use.sum(axis=1) >= 4
            N[~ok] = np.eye(4)
            dx = np.linalg.solve(N, np.einsum("tsi,ts->ti", H, y)[..., None])[..., 0]
            x = x + np.where(ok[:, None], dx, 0.0)
    x[use.sum(axis=1) < 4] = np.nan
    return x[:, :3], x[:, 3], use.sum(axis=1)


def _elevation(rx_m, sat_m):
    """Geodetic-normal elevation of sat (T, S, 3) from rx (T, 3) (ellipsoidal normal, WGS-84)."""
    from sitl.geodesy import ecef_to_aer

    return ecef_to_aer(rx_m[:, None, :], sat_m)[1]


def prepare(obs, nav, frequency: str = "L1") -> Epochs:
    """The file's GPS L1 observations with broadcast satellite states (module docstring).
    GnssFileError (one line naming the file) when nothing usable is left."""
    if frequency != "L1":
        raise GnssFileError(obs.path, None, f"frequency {frequency!r}: only L1 is solved")
    if nav.gps is None or len(nav.gps) == 0:
        raise GnssFileError(nav.path, None, "no GPS ephemerides in the navigation file")
    gcols = [j for j, s in enumerate(obs.sats) if s.startswith("G")]
    counts = {"epochs": int(obs.t_gps_s.size), "non_gps_satellites": len(obs.sats) - len(gcols)}
    if not gcols:
        raise GnssFileError(obs.path, None, "no GPS satellites in the observation file")
    names = {k: next((c for c in alts if c in obs.data), None) for k, alts in OBS_CODES.items()}
    for code in ("C1", "L1"):
        if names[code] is None:
            raise GnssFileError(obs.path, None, f"no {code} observations (GPS L1 C/A code and phase are needed: "
                                                f"{' or '.join(OBS_CODES[code])})")
    sats = tuple(obs.sats[j] for j in gcols)
    T, S = obs.t_gps_s.size, len(sats)

    def col(code):
        c = names[code]
        return obs.data[c][:, gcols] if c is not None else np.full((T, S), np.nan)

    def lli(code):
        c = names[code]
        return obs.lli[c][:, gcols] if c is not None and c in obs.lli else np.zeros((T, S), dtype=int)

    c1 = col("C1")
    t_rx = np.broadcast_to(obs.t_gps_s[:, None], (T, S))
    sat = np.broadcast_to(np.array(sats)[None, :], (T, S))
    have = np.isfinite(c1)
    t_tx = np.where(have, t_rx - np.nan_to_num(c1) / C_M_S, t_rx)
    st = gps_states(nav.gps, sat.ravel(), t_tx.ravel())
    t_tx2 = t_tx - np.nan_to_num(st.clock_s.reshape(T, S))
    st = gps_states(nav.gps, sat.ravel(), t_tx2.ravel())
    ok = st.ok.reshape(T, S)
    healthy = st.healthy.reshape(T, S)
    counts["no_ephemeris"] = int((have & ~ok).sum())
    counts["unhealthy"] = int((have & ok & ~healthy).sum())
    use = have & healthy
    if not use.any():
        raise GnssFileError(obs.path, None, "no satellite with a healthy broadcast record in force (is the "
                                            "navigation file of the same day?)")
    clk_l1 = st.clock_l1_s.reshape(T, S)
    pos_tx = st.pos_m.reshape(T, S, 3)
    vel_tx = st.vel_m_s.reshape(T, S, 3)
    tgd = np.full((T, S), np.nan)
    rec = st.record.reshape(T, S)
    tgd[ok] = nav.gps.tgd_s[rec[ok]]
    pr = np.where(use, c1 + C_M_S * clk_l1, np.nan)
    doppler = None
    if names["D1"] is not None:  # D1 positive approaching; the satellite clock's rate added like its offset
        drift = np.zeros((T, S))
        dtc = t_tx2 - np.where(ok, nav.gps.toc_gps_s[np.maximum(rec, 0)], 0.0)
        drift[ok] = (nav.gps.af1[rec[ok]] + 2.0 * nav.gps.af2[rec[ok]] * dtc[ok])
        doppler = np.where(use, -LAMBDA_L1_M * col("D1") + C_M_S * drift, np.nan)

    # light time / Sagnac from the code-only fix, twice (the fix with the rotated states)
    pos, vel = np.where(use[..., None], pos_tx, 0.0), np.where(use[..., None], vel_tx, 0.0)
    rx, clk, _ = least_squares_fix(pr, pos, use)
    for _ in range(2):
        rx0 = np.nan_to_num(rx)
        tau = np.linalg.norm(pos_tx - rx0[:, None, :], axis=-1) / C_M_S
        pos, vel = rotate_to_reception(np.nan_to_num(pos_tx), np.nan_to_num(vel_tx), np.nan_to_num(tau))
        el = _elevation(rx0, pos)
        use_ls = use & (el >= np.radians(LS_MASK_DEG))
        x0 = np.concatenate([rx0, np.nan_to_num(clk)[:, None]], axis=1)
        rx, clk, n_ls = least_squares_fix(pr, pos, use_ls, x0=x0)
    counts["epochs_without_fix"] = int(np.sum(~np.isfinite(clk)))
    nan3 = np.full((T, S, 3), np.nan)
    return Epochs(
        path=str(obs.path), t_gps_s=np.asarray(obs.t_gps_s, float), sats=sats, pr_m=pr,
        phase_m=np.where(use, col("L1") * LAMBDA_L1_M + C_M_S * clk_l1, np.nan), lli_l1=lli("L1"),
        c1_m=np.where(use, c1, np.nan), p2_m=np.where(use, col("P2"), np.nan),
        l1_cyc=np.where(use, col("L1"), np.nan), l2_cyc=np.where(use, col("L2"), np.nan),
        lli=lli("L1") | lli("L2"), tgd_s=tgd,
        sat_pos_m=np.where(use[..., None], pos, nan3), sat_vel_m_s=np.where(use[..., None], vel, nan3),
        ls_pos_m=rx, ls_clock_m=clk,
        approx_position_m=None if obs.approx_position_m is None else np.asarray(obs.approx_position_m, float),
        counts=counts, ion_alpha=nav.ion_alpha, ion_beta=nav.ion_beta, doppler_prr_m_s=doppler,
    )
