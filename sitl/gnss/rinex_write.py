"""RINEX 3.04 writers for the simulated GNSS world: observations (GPS + GLONASS, L1 C/A:
C1C, L1C, D1C, S1C) and mixed navigation records whose ephemerides reproduce the simulated
orbits and clocks for an independent engine (RTKLIB's rnx2rtkp, georinex).

Pure functions of arrays: no command line, no scenario (``sitl.app.gnss.export`` drives them).

Encoding of the simulated world (see ``sitl.gnss.orbits``, ``ranging``, ``receiver``):

* GPS.  The simulated orbit *is* the IS-GPS-200 Table 20-IV algorithm with the ICD's GM and
  Earth rate, so an LNAV record carries it exactly: the elements are re-referenced to the
  record's t_oe (M0 + n dt, the node longitude carried along its rate, i0 + IDOT dt; the
  harmonic terms depend on the argument of latitude only and are copied), no fit.
  The simulated satellite clocks are perfect: a pseudorange is range + receiver clock (+ the
  GPS-GLONASS offset), with no relativistic periodic term. A user engine adds that term,
  dt_r = -2 sqrt(GM A) e sin E / c^2 (IS-GPS-200 20.3.3.3.3.1; RTKLIB's eph2pos), to the
  broadcast polynomial, so the polynomial af0 + af1 dt + af2 dt^2 written here is the
  least-squares fit of +2 sqrt(GM A) e sin E / c^2 over the record's span: the sum the user
  forms is the simulated zero (to ~1e-3 m over +/-15 min; ``gps_lnav_records`` returns the
  worst residual). TGD = 0 (the simulated receiver has no L1 group delay).
* GLONASS.  The simulation flies GLONASS on the same Keplerian model (PZ-90.11 GM and Earth
  rate, secular J2 node drift only), while a GLONASS record is a PZ-90 state vector that the
  user integrates with a J2 force model plus a constant luni-solar acceleration (GLONASS ICD
  A.3.1.2; RTKLIB's geph2pos: RK4, 60 s steps). ``glonass_records`` fits, per record, the
  state at t_b and the three accelerations so that this integration (``glonass_orbit``, a
  line-for-line replica of RTKLIB 2.4.3's) follows the simulated orbit over t_b +/- half the
  record spacing, and returns the worst position error of the fit. -TauN = GammaN = 0.
* Times.  Observation epochs are receiver time tags (GPS time + receiver clock bias / c, what
  a receiver writes); GLONASS record epochs are UTC (GPS - leap seconds) on the 15-minute
  grid RTKLIB rounds them to.

Values written are rounded to the format's precision: F14.3 observations (1 mm, 1e-3 cycle,
1e-3 Hz), D19.12 navigation fields (12 significant digits: < 0.1 mm of orbit).
"""
from __future__ import annotations

from datetime import timedelta
from pathlib import Path

import numpy as np

from sitl.constants import C_M_S, GM_GPS_M3_S2, GPS_UTC_LEAP_S, OMEGA_E_GPS_RAD_S
from sitl.gnss.orbits import SECONDS_PER_WEEK, Constellation, _propagate, _solve_kepler
from sitl.timescales import GPS_EPOCH

__all__ = [
    "gps_lnav_records", "glonass_records", "glonass_orbit", "klobuchar_constant",
    "write_nav", "write_obs", "RTKLIB_GLO",
]

#: RTKLIB 2.4.3's GLONASS force-model constants (rtklib.h: MU_GLO, J2_GLO, OMGE_GLO, RE_GLO) and
#: its integration step (ephemeris.c: TSTEP)
RTKLIB_GLO = {"mu": 3.9860044e14, "j2": 1.0826257e-3, "omega": 7.292115e-5, "re": 6378136.0, "step_s": 60.0}

_HEADER_W = 60


def _hline(text: str, label: str) -> str:
    return f"{text:<{_HEADER_W}.{_HEADER_W}}{label}\n"


def _d19(v: float) -> str:
    """RINEX D19.12 (written with E, as RINEX 3 allows)."""
    s = f"{float(v):19.12E}"
    if len(s) != 19:
        raise ValueError(f"value {v!r} does not fit D19.12")
    return s


def _calendar(t_gps_s: float, leap_s: float = 0.0):
    """(y, m, d, h, mi, sec float) of GPS seconds t (minus leap_s: UTC), to the 0.1 us."""
    whole = float(np.floor(t_gps_s))
    ticks = int(round((t_gps_s - whole) * 1e7))  # 0.1 us, the epoch's F11.7
    if ticks >= 10_000_000:
        whole, ticks = whole + 1.0, ticks - 10_000_000
    dt = GPS_EPOCH.replace(tzinfo=None) + timedelta(seconds=whole - float(leap_s))
    return dt.year, dt.month, dt.day, dt.hour, dt.minute, dt.second + ticks * 1e-7


# ---------------------------------------------------------------------------
# GPS LNAV records
# ---------------------------------------------------------------------------

def _gps_clock_fit(c: Constellation, j: int, toe: float, half_s: float):
    """(af0, af1, af2) fitting +2 sqrt(GM A) e sin E / c^2 over toe +/- half_s, and the worst
    residual of the fit, s."""
    t = np.linspace(-half_s, half_s, 121)
    sub = c.subset([j])
    p = sub._prop["row"]
    M = p["M0"] + p["n"] * ((toe - sub.toa_gps_s[0]) + t)
    E = _solve_kepler(M, np.full(t.shape, p["e"][0]))
    rel = 2.0 * np.sqrt(GM_GPS_M3_S2 * p["a"][0]) * p["e"][0] * np.sin(E) / C_M_S**2
    A = np.stack([np.ones_like(t), t, t * t], axis=1)
    coef, *_ = np.linalg.lstsq(A, rel, rcond=None)
    return coef, float(np.max(np.abs(A @ coef - rel)))


def gps_lnav_records(constellation: Constellation, toes_gps_s, half_span_s: float = 900.0):
    """LNAV records of the GPS satellites of ``constellation`` at each t_oe of ``toes_gps_s``.

    Returns (records, max_clock_residual_s): records a list of dicts (sat_id, toe_gps_s, the
    broadcast fields), one per satellite and t_oe. The orbit is exact (module docstring); the
    clock polynomial folds in the relativistic term over toe +/- half_span_s (the span a user
    picking the nearest t_oe uses: half the record spacing).
    """
    c = constellation
    p = c._prop["row"]
    out, worst = [], 0.0
    for toe in np.atleast_1d(np.asarray(toes_gps_s, dtype=float)):
        week = int(np.floor(toe / SECONDS_PER_WEEK))
        toe_sow = toe - week * SECONDS_PER_WEEK
        for j in np.flatnonzero(c.system == "G"):
            dt = toe - c.toa_gps_s[j]
            m0 = np.mod(p["M0"][j] + p["n"][j] * dt + np.pi, 2 * np.pi) - np.pi
            node0 = p["node0"][j] + p["node_rate"][j] * dt  # Earth-fixed node longitude at toe
            om0 = np.mod(node0 + OMEGA_E_GPS_RAD_S * toe_sow + np.pi, 2 * np.pi) - np.pi
            (af0, af1, af2), res = _gps_clock_fit(c, int(j), toe, half_span_s)
            worst = max(worst, res)
            out.append(dict(
                sat_id=str(c.sat_id[j]), toe_gps_s=float(toe), week=week, toe_sow=float(toe_sow),
                af0=af0, af1=af1, af2=af2, iode=0, crs=c.crs_m[j], delta_n=c.delta_n_rad_s[j], m0=m0,
                cuc=c.cuc_rad[j], e=c.e[j], cus=c.cus_rad[j], sqrt_a=np.sqrt(c.a_m[j]),
                cic=c.cic_rad[j], omega0=om0, cis=c.cis_rad[j],
                i0=c.i_rad[j] + c.idot_rad_s[j] * dt, crc=c.crc_m[j], omega=c.omega_rad[j],
                omega_dot=c.OmegaDot_rad_s[j], idot=c.idot_rad_s[j], ura_m=2.0, health=0, tgd=0.0,
            ))
    for k, r in enumerate(out):  # IODE/IODC: distinct per satellite's successive records
        r["iode"] = (k // max(1, int(np.sum(c.system == "G")))) % 256
    return out, worst


# ---------------------------------------------------------------------------
# GLONASS records
# ---------------------------------------------------------------------------

def _deq(x, acc):
    """RTKLIB 2.4.3 ephemeris.c deq(): GLONASS ICD A.3.1.2 force model, ECEF, x (..., 6)."""
    mu, j2, we, re = RTKLIB_GLO["mu"], RTKLIB_GLO["j2"], RTKLIB_GLO["omega"], RTKLIB_GLO["re"]
    r2 = np.sum(x[..., :3] ** 2, axis=-1)
    r3 = r2 * np.sqrt(r2)
    omg2 = we * we
    a = 1.5 * j2 * mu * re * re / r2 / r3
    b = 5.0 * x[..., 2] ** 2 / r2
    c = -mu / r3 - a * (1.0 - b)
    out = np.empty_like(x)
    out[..., :3] = x[..., 3:]
    out[..., 3] = (c + omg2) * x[..., 0] + 2.0 * we * x[..., 4] + acc[..., 0]
    out[..., 4] = (c + omg2) * x[..., 1] - 2.0 * we * x[..., 3] + acc[..., 1]
    out[..., 5] = (c - 2.0 * a) * x[..., 2] + acc[..., 2]
    return out


def _rk4(x, acc, h):
    k1 = _deq(x, acc)
    k2 = _deq(x + k1 * (h / 2.0), acc)
    k3 = _deq(x + k2 * (h / 2.0), acc)
    k4 = _deq(x + k3 * h, acc)
    return x + (k1 + 2.0 * k2 + 2.0 * k3 + k4) * (h / 6.0)


def glonass_orbit(state0, acc, dt_s):
    """Position (..., 3) at toe + dt_s (scalar) of RTKLIB's geph2pos from the record's state
    (..., 6) [m, m/s] and accelerations (..., 3) [m/s^2]: RK4 steps of 60 s towards dt_s, the
    last one shortened (the same sequence of steps, so the same numbers up to rounding)."""
    x = np.array(state0, dtype=float)
    acc = np.asarray(acc, dtype=float)
    t = float(dt_s)
    step = RTKLIB_GLO["step_s"]
    tt = -step if t < 0.0 else step
    while abs(t) > 1e-9:
        if abs(t) < step:
            tt = t
        x = _rk4(x, acc, tt)
        t -= tt
    return x[..., :3]


def _glonass_track(state0, acc, offsets):
    """Positions (..., K, 3) at the offsets (K,), multiples of the 60 s step from toe, sorted
    and spanning both signs: one integration each way."""
    offsets = np.asarray(offsets, dtype=float)
    out = np.empty(np.shape(state0)[:-1] + (offsets.size, 3))
    step = RTKLIB_GLO["step_s"]
    for sign in (1.0, -1.0):
        x = np.array(state0, dtype=float)
        t = 0.0
        for k in (np.argsort(offsets) if sign > 0 else np.argsort(offsets)[::-1]):
            target = offsets[k]
            if sign * target < 0 or (sign < 0 and target == 0):
                continue
            while abs(target - t) > 1e-9:
                h = sign * min(step, abs(target - t))
                x = _rk4(x, acc, h)
                t += h
            out[..., k, :] = x[..., :3]
    return out


def glonass_records(constellation: Constellation, toes_gps_s, half_span_s: float = 900.0,
                    iterations: int = 3):
    """GLONASS records (state vector + luni-solar accelerations) at each t_b of ``toes_gps_s``.

    Per satellite and t_b, a Gauss-Newton least-squares fit of (position, velocity, acceleration)
    at t_b so that ``glonass_orbit`` (RTKLIB's integration) follows the simulated orbit on a
    60 s grid over t_b +/- half_span_s (rounded up to the grid). Returns (records, max_fit_error_m, errors):
    the worst position error over the grid, and per record the worst error (m).
    """
    c = constellation
    glo = np.flatnonzero(c.system == "R")
    if glo.size == 0:
        return [], 0.0, np.zeros(0)
    sub = c.subset(glo)
    step = RTKLIB_GLO["step_s"]
    n_half = int(np.ceil((half_span_s + 1.0) / step))  # the span a nearest-t_b user needs, + transit time
    offs = step * np.arange(-n_half, n_half + 1)
    recs, errs = [], []
    for toe in np.atleast_1d(np.asarray(toes_gps_s, dtype=float)):
        tk = (toe - sub.toa_gps_s)[:, None] + offs[None, :]
        x, y, z, *_ = _propagate(sub, tk, want_vel=False, sat_major=True)
        truth = np.stack([x, y, z], axis=-1)  # (S, K, 3)
        x0, y0, z0, vx, vy, vz = _propagate(sub, (toe - sub.toa_gps_s)[:, None], want_vel=True, sat_major=True)
        p = np.concatenate([np.stack([x0, y0, z0, vx, vy, vz], axis=-1)[:, 0, :], np.zeros((len(sub), 3))], axis=1)
        scale = np.array([1.0] * 3 + [1e-3] * 3 + [1e-7] * 3)
        for _ in range(iterations):
            base = _glonass_track(p[:, :6], p[:, 6:], offs)
            r = (truth - base).reshape(len(sub), -1)
            J = np.empty((len(sub), r.shape[1], 9))
            for q in range(9):
                pq = p.copy()
                pq[:, q] += scale[q]
                J[:, :, q] = ((_glonass_track(pq[:, :6], pq[:, 6:], offs) - base).reshape(len(sub), -1)) / scale[q]
            for s in range(len(sub)):
                dp, *_ = np.linalg.lstsq(J[s], r[s], rcond=None)
                p[s] += dp
        # what a record really holds: the fields rounded as written (D19.12 of km, km/s, km/s^2)
        p = np.array([[float(_d19(v / 1e3)) * 1e3 for v in row] for row in p])
        err = np.linalg.norm(truth - _glonass_track(p[:, :6], p[:, 6:], offs), axis=-1).max(axis=1)
        for s, j in enumerate(glo):
            recs.append(dict(sat_id=str(c.sat_id[j]), toe_gps_s=float(toe), pos_m=p[s, :3], vel_m_s=p[s, 3:6],
                             acc_m_s2=p[s, 6:], k=int(c.glonass_k[j]), health=0, tau_n=0.0, gamma_n=0.0,
                             fit_error_m=float(err[s])))
            errs.append(float(err[s]))
    errs = np.array(errs)
    return recs, float(errs.max()), errs


# ---------------------------------------------------------------------------
# the ionosphere in the header
# ---------------------------------------------------------------------------

#: the Klobuchar period written to make its cosine flat: x = 2 pi (t - 50400) / PER stays below
#: 2 pi 50400 / 1e7 = 0.032 rad, so the day term is AMP (1 - x^2/2 + x^4/24) >= 0.9995 AMP
KLOBUCHAR_FLAT_PER_S = 1.0e7


def klobuchar_constant(zenith_delay_m: float):
    """(alpha, beta) of a Klobuchar model whose vertical L1 delay is constant at zenith_delay_m
    (to 0.05 %): the simulated ionosphere's zenith delay. AMP = alpha0 = I_g / c - 5 ns (the
    model's night floor), PER = beta0 = 1e7 s. Klobuchar's slant factor F = 1 + 16 (0.53 - E)^3
    is not the simulated thin-shell mapping (h = 432.5 km); None if I_g < 5 ns c (1.5 m):
    Klobuchar cannot go below its floor."""
    amp = zenith_delay_m / C_M_S - 5e-9
    if amp < 0:
        return None
    return (amp, 0.0, 0.0, 0.0), (KLOBUCHAR_FLAT_PER_S, 0.0, 0.0, 0.0)


# ---------------------------------------------------------------------------
# writers
# ---------------------------------------------------------------------------

def _pgm_line(program: str, when_gps_s: float) -> str:
    y, mo, d, h, mi, s = _calendar(when_gps_s, GPS_UTC_LEAP_S)
    return _hline(f"{program:<20.20}{'skyfuse':<20.20}{y:04d}{mo:02d}{d:02d} {h:02d}{mi:02d}{int(s):02d} UTC",
                  "PGM / RUN BY / DATE")


def write_nav(path, gps_records, glonass_records_, *, iono_alpha=None, iono_beta=None,
              leap_s: float = GPS_UTC_LEAP_S, program: str = "skyfuse gnss export", comment=()) -> Path:
    """A RINEX 3.04 mixed navigation file of GPS LNAV and GLONASS records (dicts of
    ``gps_lnav_records`` / ``glonass_records``); ION ALPHA/BETA (GPSA/GPSB) when given."""
    path = Path(path)
    when = min([r["toe_gps_s"] for r in gps_records] + [r["toe_gps_s"] for r in glonass_records_] or [0.0])
    lines = [_hline(f"{'3.04':>9}{'':11}{'N: GNSS NAV DATA':<20}{'M: MIXED':<20}", "RINEX VERSION / TYPE"),
             _pgm_line(program, when)]
    for text in comment:
        lines.append(_hline(text, "COMMENT"))
    if iono_alpha is not None:
        lines.append(_hline("GPSA " + "".join(f"{v:12.4E}" for v in iono_alpha), "IONOSPHERIC CORR"))
        lines.append(_hline("GPSB " + "".join(f"{v:12.4E}" for v in iono_beta), "IONOSPHERIC CORR"))
    week = int(np.floor(when / SECONDS_PER_WEEK))
    lines.append(_hline(f"GPUT {0.0:17.10E}{0.0:16.9E}{0:7d}{week:5d}", "TIME SYSTEM CORR"))
    lines.append(_hline(f"GLUT {0.0:17.10E}{0.0:16.9E}{0:7d}{week:5d}", "TIME SYSTEM CORR"))
    lines.append(_hline(f"{int(leap_s):6d}", "LEAP SECONDS"))
    lines.append(_hline("", "END OF HEADER"))
    recs = [("G", r) for r in gps_records] + [("R", r) for r in glonass_records_]
    recs.sort(key=lambda sr: (sr[1]["toe_gps_s"], sr[1]["sat_id"]))
    for sys_, r in recs:
        if sys_ == "G":
            y, mo, d, h, mi, s = _calendar(r["toe_gps_s"])
            rows = [(r["af0"], r["af1"], r["af2"]),
                    (r["iode"], r["crs"], r["delta_n"], r["m0"]),
                    (r["cuc"], r["e"], r["cus"], r["sqrt_a"]),
                    (r["toe_sow"], r["cic"], r["omega0"], r["cis"]),
                    (r["i0"], r["crc"], r["omega"], r["omega_dot"]),
                    (r["idot"], 0.0, r["week"], 0.0),
                    (r["ura_m"], r["health"], r["tgd"], r["iode"]),
                    (r["toe_sow"], 4.0)]
        else:
            y, mo, d, h, mi, s = _calendar(r["toe_gps_s"], leap_s)  # GLONASS records: UTC
            t_utc = r["toe_gps_s"] - leap_s
            tof = t_utc - np.floor(t_utc / SECONDS_PER_WEEK) * SECONDS_PER_WEEK
            p, v, a = (np.asarray(r[k]) / 1e3 for k in ("pos_m", "vel_m_s", "acc_m_s2"))
            rows = [(-r["tau_n"], r["gamma_n"], tof),
                    (p[0], v[0], a[0], r["health"]),
                    (p[1], v[1], a[1], r["k"]),
                    (p[2], v[2], a[2], 0.0)]
        if abs(s - round(s)) > 1e-6:
            raise ValueError(f"{r['sat_id']}: record epoch must fall on a whole second, got {s}")
        lines.append(f"{r['sat_id']} {y:04d} {mo:02d} {d:02d} {h:02d} {mi:02d} {int(round(s)):02d}"
                     + "".join(_d19(v) for v in rows[0]) + "\n")
        for row in rows[1:]:
            lines.append("    " + "".join(_d19(v) for v in row) + "\n")
    path.write_text("".join(lines), encoding="ascii")
    return path


OBS_TYPES = ("C1C", "L1C", "D1C", "S1C")


def write_obs(path, t_tag_gps_s, sat_id, glonass_k, pseudorange_m, phase_cycles, doppler_hz, snr_dbhz,
              lli=None, *, approx_pos_ecef_m=(0.0, 0.0, 0.0), interval_s=None, marker="SKYFUSE",
              program: str = "skyfuse gnss export", comment=()) -> Path:
    """A RINEX 3.04 mixed observation file (GPS + GLONASS, C1C L1C D1C S1C).

    t_tag_gps_s (T,): receiver time tags (GPS time scale); sat_id (S,) 'Gnn'/'Rnn'; glonass_k
    (S,) FDMA channels (GLONASS SLOT / FRQ # for the R satellites); pseudorange_m, phase_cycles,
    doppler_hz, snr_dbhz (T, S), NaN where not tracked (a satellite is written when its
    pseudorange is finite); lli (T, S) loss-of-lock indicators (0/1) on the phase.
    """
    path = Path(path)
    t = np.asarray(t_tag_gps_s, dtype=float)
    ids = [str(s) for s in sat_id]
    pr, ph, dop, snr = (np.asarray(a, dtype=float) for a in (pseudorange_m, phase_cycles, doppler_hz, snr_dbhz))
    T, S = pr.shape
    if t.shape != (T,) or len(ids) != S or any(a.shape != (T, S) for a in (ph, dop, snr)):
        raise ValueError("write_obs: arrays must be (T, S) with t (T,) and sat_id (S,)")
    lli = np.zeros((T, S), dtype=int) if lli is None else np.asarray(lli, dtype=int)
    x, y_, z = (float(v) for v in approx_pos_ecef_m)
    lines = [_hline(f"{'3.04':>9}{'':11}{'OBSERVATION DATA':<20}{'M: MIXED':<20}", "RINEX VERSION / TYPE"),
             _pgm_line(program, float(t[0]))]
    for text in comment:
        lines.append(_hline(text, "COMMENT"))
    lines += [_hline(marker, "MARKER NAME"), _hline("SIMULATED", "MARKER TYPE"),
              _hline(f"{'skyfuse':<20}{'skyfuse':<40}", "OBSERVER / AGENCY"),
              _hline(f"{'0':<20}{'SKYFUSE SITL L1':<20}{'1':<20}", "REC # / TYPE / VERS"),
              _hline(f"{'0':<20}{'SKYFUSE POINT':<20}", "ANT # / TYPE"),
              _hline(f"{x:14.4f}{y_:14.4f}{z:14.4f}", "APPROX POSITION XYZ"),
              _hline(f"{0.0:14.4f}{0.0:14.4f}{0.0:14.4f}", "ANTENNA: DELTA H/E/N")]
    for sysc in "GR":
        lines.append(_hline(f"{sysc}  {len(OBS_TYPES):3d} " + " ".join(OBS_TYPES), "SYS / # / OBS TYPES"))
        lines.append(_hline(f"{sysc} L1C", "SYS / PHASE SHIFT"))
    lines.append(_hline(" DBHZ", "SIGNAL STRENGTH UNIT"))
    if interval_s is not None:
        lines.append(_hline(f"{interval_s:10.3f}", "INTERVAL"))
    y, mo, d, h, mi, s = _calendar(float(t[0]))
    lines.append(_hline(f"{y:6d}{mo:6d}{d:6d}{h:6d}{mi:6d}{s:13.7f}     GPS", "TIME OF FIRST OBS"))
    y, mo, d, h, mi, s = _calendar(float(t[-1]))
    lines.append(_hline(f"{y:6d}{mo:6d}{d:6d}{h:6d}{mi:6d}{s:13.7f}     GPS", "TIME OF LAST OBS"))
    glo = [(sid, int(k)) for sid, k in zip(ids, glonass_k) if sid.startswith("R")]
    for q in range(0, max(len(glo), 1), 8):
        chunk = glo[q:q + 8]
        head = f"{len(glo):3d} " if q == 0 else "    "
        lines.append(_hline(head + "".join(f"{sid} {k:2d} " for sid, k in chunk), "GLONASS SLOT / FRQ #"))
    lines.append(_hline(" C1C    0.000 C1P    0.000 C2C    0.000 C2P    0.000", "GLONASS COD/PHS/BIS"))
    lines.append(_hline(f"{int(GPS_UTC_LEAP_S):6d}", "LEAP SECONDS"))
    lines.append(_hline("", "END OF HEADER"))

    def field(v, flag=0):
        if not np.isfinite(v):
            return " " * 16
        s = f"{v:14.3f}"
        if len(s) > 14:
            raise ValueError(f"observation {v!r} does not fit F14.3")
        return s + (str(flag) if flag else " ") + " "

    order = sorted(range(S), key=lambda j: ("GR".index(ids[j][0]), ids[j]))
    for k in range(T):
        sats = [j for j in order if np.isfinite(pr[k, j])]
        y, mo, d, h, mi, s = _calendar(float(t[k]))
        lines.append(f"> {y:04d} {mo:02d} {d:02d} {h:02d} {mi:02d}{s:11.7f}  0{len(sats):3d}\n")
        for j in sats:
            row = (field(pr[k, j]) + field(ph[k, j], lli[k, j]) + field(dop[k, j]) + field(snr[k, j])).rstrip()
            lines.append(ids[j] + row + "\n")
    path.write_text("".join(lines), encoding="ascii")
    return path
