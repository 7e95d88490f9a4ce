"""Satellite position, velocity and clock from broadcast ephemerides (GPS and GLONASS).

    nav = read_nav(path)                                   # sitl.gnss.rinex_nav
    st = broadcast_states(nav, sats, t_gps_s)              # the record in force per (sat, t)
    st.pos_m, st.vel_m_s, st.clock_s, st.ok, st.healthy, st.record

Which GPS record is "in force" (``select``): ``"nearest"`` (the default) takes the record whose
Toe is nearest t within its fit interval (``GpsEphemerides.select``), which may be one the
satellite had not yet transmitted at t; ``"transmitted"`` takes the one a receiver holds at t:
among the records whose fit interval covers t, the latest transmitted (transmission time of
message ttm <= t; ties: the latest Toe). The control segment transmits each 2-hourly set from
about 2 h before its Toe, and a mid-period upload (a new IODE) from its ttm on.

GPS (IS-GPS-200, sec. 20.3.3.3.3 and Table 20-IV): the Keplerian set with Delta_n, IDOT,
OMEGA DOT, the six harmonic corrections C_uc, C_us, C_rc, C_rs, C_ic, C_is and the Earth's
rotation (Omega_k = OMEGA0 + (OMEGA DOT - w_e) t_k - w_e t_oe), evaluated by the same
propagator as the simulated constellations (:func:`sitl.gnss.orbits.kepler_state_ecef`;
t_k in continuous GPS seconds, so the week crossover needs no +- 604800 rule), GM =
3.986005e14, w_e = 7.2921151467e-5. Clock: dt_sv = af0 + af1 (t - toc) + af2 (t - toc)^2 +
dt_r with the relativistic term dt_r = F e sqrt(A) sin E, F = -4.442807633e-10 s/m^0.5
(20.3.3.3.3.1); ``clock_s`` is dt_sv, for the L1-L2 ionosphere-free combination the
broadcast clock refers to; an L1-only (C/A or P1) user takes dt_sv - TGD (20.3.3.3.3.2):
``clock_l1_s``. ``relativistic_s`` is dt_r alone (IGS clock products exclude it).

GLONASS (ICD ed. 5.1, 2008, Appendix A.3.1.2): the broadcast state vector at t_b is
integrated to t by 4th-order Runge-Kutta in the rotating PZ-90 frame, with the central
term, J2 (C20), the centrifugal and Coriolis terms and the broadcast lunisolar accelerations
held constant; steps of at most 60 s (equal steps over t - t_b). mu = 398600.4418e9,
a_e = 6378136 m, J2 = 1082625.75e-9, w_e = 7.292115e-5 (PZ-90). Clock: -tau_n + gamma_n
(t - t_b). The positions are in the PZ-90 realisation of the epoch; :func:`pz90_to_itrf`
moves them to ITRF (see there for what is applied when).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .orbits import kepler_state_ecef
from .rinex_common import calendar_seconds
from .rinex_nav import GlonassEphemerides, GpsEphemerides, NavFile

__all__ = ["BroadcastStates", "broadcast_states", "gps_states", "glonass_states", "pz90_to_itrf",
           "select_transmitted", "F_RELATIVISTIC_S_SQRT_M", "GLONASS_STEP_S", "GPS_RECORD_SELECTIONS"]

GM_GPS = 3.986005e14
OMEGA_E_GPS = 7.2921151467e-5
F_RELATIVISTIC_S_SQRT_M = -4.442807633e-10

GLO_MU = 398600.4418e9
GLO_AE = 6378136.0
GLO_J2 = 1082625.75e-9
GLO_OMEGA = 7.292115e-5
GLONASS_STEP_S = 60.0
GPS_RECORD_SELECTIONS = ("nearest", "transmitted")
WEEK_S = 604_800.0


@dataclass(frozen=True, eq=False)
class BroadcastStates:
    """Per query (N,): ``record`` index into the system's ephemerides (-1: none in force),
    ``ok`` (a record is in force), ``healthy`` (it is, and its health flag is 0), pos_m and
    vel_m_s (N, 3) Earth-fixed (NaN where not ok), clock_s (see the module docstring),
    clock_l1_s (GPS: clock_s - TGD; GLONASS: clock_s), relativistic_s (GPS dt_r; GLONASS 0)."""

    record: np.ndarray
    ok: np.ndarray
    healthy: np.ndarray
    pos_m: np.ndarray
    vel_m_s: np.ndarray
    clock_s: np.ndarray
    clock_l1_s: np.ndarray
    relativistic_s: np.ndarray


def _empty(n):
    nan3 = np.full((n, 3), np.nan)
    nan = np.full(n, np.nan)
    return nan3, nan3.copy(), nan, nan.copy(), np.zeros(n)


def select_transmitted(eph: GpsEphemerides, sat, t_gps_s, usable=None) -> np.ndarray:
    """Index of the record a receiver holds at t for each (satellite, time) pair, -1 where
    none: among the records whose fit interval covers t (|t - toe| <= fit_h * 1800 s), the one
    with the latest transmission time ttm <= t (ties: the latest Toe, then the last in the
    file). ttm is seconds of the record's week, put on the continuous scale next to its Toe.
    ``usable`` (bool (N,)) leaves records out, as in ``GpsEphemerides.select``."""
    sat = np.asarray(sat, dtype=str).reshape(-1)
    t = np.asarray(t_gps_s, dtype=float).reshape(-1)
    ttm = eph.week * WEEK_S + eph.ttm_s
    ttm = ttm + WEEK_S * np.round((eph.toe_gps_s - ttm) / WEEK_S)  # the week of its Toe
    half = eph.fit_h * 1800.0
    keep = np.ones(len(eph), bool) if usable is None else np.asarray(usable, bool)
    out = np.full(t.shape, -1, dtype=np.int64)
    for s in np.unique(sat):
        q = np.flatnonzero(sat == s)
        r = np.flatnonzero((eph.sat == s) & keep)
        if r.size == 0:
            continue
        r = r[np.lexsort((r, eph.toe_gps_s[r], ttm[r]))]  # by ttm, then Toe, then file order
        ok = (ttm[r][None, :] <= t[q, None]) & (np.abs(t[q, None] - eph.toe_gps_s[r][None, :]) <= half[r][None, :])
        last = r.size - 1 - np.argmax(ok[:, ::-1], axis=1)
        has = ok.any(axis=1)
        out[q[has]] = r[last[has]]
    return out


def gps_states(eph: GpsEphemerides, sat, t_gps_s, drop_mislabelled: bool = True,
               select: str = "nearest") -> BroadcastStates:
    """IS-GPS-200 states of GPS satellites ``sat`` (N,) at GPS times ``t_gps_s`` (N,), from the
    record in force: ``select="nearest"`` (default, ``GpsEphemerides.select``) or
    ``"transmitted"`` (:func:`select_transmitted`; see the module docstring);
    ``drop_mislabelled`` (default) leaves out records that are copies of another PRN's
    (``GpsEphemerides.mislabelled``)."""
    if select not in GPS_RECORD_SELECTIONS:
        raise ValueError(f"select: {select!r} is not one of {', '.join(GPS_RECORD_SELECTIONS)}")
    sat, t = np.broadcast_arrays(np.asarray(sat, dtype=str).reshape(-1), np.asarray(t_gps_s, float).reshape(-1))
    usable = ~eph.mislabelled() if drop_mislabelled else None
    rec = eph.select(sat, t, usable=usable) if select == "nearest" else select_transmitted(eph, sat, t, usable)
    ok = rec >= 0
    pos, vel, clk, clk_l1, rel = _empty(t.size)
    if ok.any():
        r, tq = rec[ok], t[ok]
        p, v, E = kepler_state_ecef(
            GM_GPS, OMEGA_E_GPS, eph.toe_gps_s[r], eph.sqrt_a[r] ** 2, eph.e[r], eph.i0_rad[r],
            eph.omega0_rad[r], eph.omega_dot_rad_s[r], eph.omega_rad[r], eph.m0_rad[r], eph.delta_n_rad_s[r],
            eph.idot_rad_s[r], eph.cuc_rad[r], eph.cus_rad[r], eph.crc_m[r], eph.crs_m[r], eph.cic_rad[r],
            eph.cis_rad[r], tq)
        dtc = tq - eph.toc_gps_s[r]
        dtr = F_RELATIVISTIC_S_SQRT_M * eph.e[r] * eph.sqrt_a[r] * np.sin(E)
        pos[ok], vel[ok] = p, v
        rel[ok] = dtr
        clk[ok] = eph.af0_s[r] + eph.af1[r] * dtc + eph.af2[r] * dtc**2 + dtr
        clk_l1[ok] = clk[ok] - eph.tgd_s[r]
    healthy = ok & np.where(ok, eph.health[np.maximum(rec, 0)] == 0, False)
    return BroadcastStates(rec, ok, healthy, pos, vel, clk, clk_l1, rel)


def _glo_deriv(state, acc_ls):
    r = state[:, :3]
    v = state[:, 3:]
    x, y, z = r[:, 0], r[:, 1], r[:, 2]
    r2 = np.einsum("ij,ij->i", r, r)
    rn = np.sqrt(r2)
    mu_r3 = GLO_MU / (r2 * rn)
    j2 = 1.5 * GLO_J2 * GLO_MU * GLO_AE**2 / (r2 * r2 * rn)
    zz = 5.0 * z * z / r2
    w2 = GLO_OMEGA**2
    ax = -mu_r3 * x - j2 * x * (1.0 - zz) + w2 * x + 2.0 * GLO_OMEGA * v[:, 1] + acc_ls[:, 0]
    ay = -mu_r3 * y - j2 * y * (1.0 - zz) + w2 * y - 2.0 * GLO_OMEGA * v[:, 0] + acc_ls[:, 1]
    az = -mu_r3 * z - j2 * z * (3.0 - zz) + acc_ls[:, 2]
    return np.concatenate([v, np.stack((ax, ay, az), axis=1)], axis=1)


def glonass_integrate(pos0_m, vel0_m_s, acc_ls_m_s2, dt_s, step_s: float = GLONASS_STEP_S):
    """The ICD's RK4 integration of N state vectors over dt_s (N,) (either sign), with
    ceil(|dt| / step_s) equal steps each. Returns (pos_m, vel_m_s), (N, 3) each."""
    dt = np.asarray(dt_s, dtype=float)
    state = np.concatenate([np.asarray(pos0_m, float), np.asarray(vel0_m_s, float)], axis=1)
    acc = np.asarray(acc_ls_m_s2, float)
    nsteps = np.maximum(np.ceil(np.abs(dt) / step_s), 1).astype(int)
    h = (dt / nsteps)[:, None]
    for k in range(int(nsteps.max()) if dt.size else 0):
        active = (k < nsteps)[:, None]
        k1 = _glo_deriv(state, acc)
        k2 = _glo_deriv(state + 0.5 * h * k1, acc)
        k3 = _glo_deriv(state + 0.5 * h * k2, acc)
        k4 = _glo_deriv(state + h * k3, acc)
        state = np.where(active, state + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4), state)
    return state[:, :3], state[:, 3:]


def glonass_states(eph: GlonassEphemerides, sat, t_gps_s, itrf: bool = True) -> BroadcastStates:
    """GLONASS states at GPS times (N,) from the record nearest in t_b (within 30 min);
    ``itrf`` (default) moves them from PZ-90 to ITRF with :func:`pz90_to_itrf`."""
    sat, t = np.broadcast_arrays(np.asarray(sat, dtype=str).reshape(-1), np.asarray(t_gps_s, float).reshape(-1))
    rec = eph.select(sat, t)
    ok = rec >= 0
    pos, vel, clk, _, rel = _empty(t.size)
    if ok.any():
        r, tq = rec[ok], t[ok]
        dt = tq - eph.toc_gps_s[r]
        p, v = glonass_integrate(eph.pos_m[r], eph.vel_m_s[r], eph.acc_m_s2[r], dt)
        if itrf:
            p = pz90_to_itrf(p, tq)
        pos[ok], vel[ok] = p, v
        clk[ok] = -eph.tau_n_s[r] + eph.gamma_n[r] * dt
    healthy = ok & np.where(ok, eph.health[np.maximum(rec, 0)] == 0, False)
    return BroadcastStates(rec, ok, healthy, pos, vel, clk, clk.copy(), rel)


# PZ-90.02 was the GLONASS broadcast frame from 2007-09-20 12:00 UTC to 2013-12-31 15:00 UTC
# (then PZ-90.11). PZ-90.02 -> ITRF2000: a shift of (-0.36, +0.08, +0.18) m, no rotation, no
# scale (GLONASS ICD ed. 5.1, 2008, sec. 3.3.2). PZ-90.11 -> ITRF2008: sitl.geodesy (EPSG:7960,
# a few mm). ITRF2000/2005/2008 agree at the cm level, below the broadcast errors.
_PZ90_02_START = calendar_seconds(2007, 9, 20, 12, 0, 0.0) + 14
_PZ90_11_START = calendar_seconds(2013, 12, 31, 15, 0, 0.0) + 16
PZ90_02_TO_ITRF2000_M = np.array([-0.36, 0.08, 0.18])


def pz90_to_itrf(pos_m, t_gps_s) -> np.ndarray:
    """PZ-90 positions (N, 3) at GPS times (N,) -> ITRF: PZ-90.02 + (-0.36, +0.08, +0.18) m
    between 2007-09-20 and 2013-12-31; PZ-90.11 -> ITRF2008 (sitl.geodesy) after. Earlier
    epochs (the original PZ-90, metre-level parameters that differ between sources) are
    refused with a ValueError."""
    from sitl.geodesy import pz90_11_to_wgs84

    p = np.asarray(pos_m, dtype=float)
    t = np.broadcast_to(np.asarray(t_gps_s, dtype=float), p.shape[:-1])
    if np.any(t < _PZ90_02_START):
        raise ValueError("GLONASS before 2007-09-20 (PZ-90, not PZ-90.02): no PZ-90 -> ITRF transformation here")
    out = p + PZ90_02_TO_ITRF2000_M
    late = t >= _PZ90_11_START
    if late.any():
        out[late] = pz90_11_to_wgs84(p[late])
    return out


def broadcast_states(nav: NavFile, sat, t_gps_s, gps_select: str = "nearest") -> BroadcastStates:
    """GPS ('G..') and GLONASS ('R..') satellites mixed: each by its system's algorithm
    (``gps_select``: which GPS record is in force, see :func:`gps_states`)."""
    sat, t = np.broadcast_arrays(np.asarray(sat, dtype=str).reshape(-1), np.asarray(t_gps_s, float).reshape(-1))
    n = t.size
    rec = np.full(n, -1, dtype=np.int64)
    ok = np.zeros(n, bool)
    healthy = np.zeros(n, bool)
    pos, vel, clk, clk_l1, rel = _empty(n)
    for letter, eph, fn in (("G", nav.gps, gps_states), ("R", nav.glonass, glonass_states)):
        m = np.char.startswith(sat, letter)
        if not m.any() or eph is None:
            continue
        s = fn(eph, sat[m], t[m], select=gps_select) if letter == "G" else fn(eph, sat[m], t[m])
        rec[m], ok[m], healthy[m] = s.record, s.ok, s.healthy
        pos[m], vel[m], clk[m], clk_l1[m], rel[m] = s.pos_m, s.vel_m_s, s.clock_s, s.clock_l1_s, s.relativistic_s
    return BroadcastStates(rec, ok, healthy, pos, vel, clk, clk_l1, rel)
