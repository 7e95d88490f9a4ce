"""RINEX 2.x / 3.x navigation files: every GPS and GLONASS broadcast record, as columns.

    nav = read_nav("brdc1820.10n")          # RINEX 2 'N' (GPS), 'G' (GLONASS) or 3.x 'N'
    nav.gps        # GpsEphemerides or None: one row per record, file order, none dropped
    nav.glonass    # GlonassEphemerides or None
    i = nav.gps.select(["G05", "G05"], [t0, t1])   # the record in force at each time (-1: none)

Why an own reader and not georinex (1.16.2, measured on the shared files): georinex reads
them fast (0.08 s for the day's GPS file, 0.09 s GLONASS) and covers GPS and GLONASS
navigation, but (1) it keys records on a (time, sv) grid, so two records of a satellite with
the same epoch (IGS brdc files carry such duplicates) cannot both be kept; (2) it accepted a
file truncated inside a record without a word; (3) its errors name neither file nor line
("could not convert string to float"), which the command line must give; and (4) it has no
RINEX clock reader at all. These readers are line-based and strict; the tests check them
against georinex on the same files as an independent peer, and against values typed from
the files' text.

Times are GPS seconds since 1980-01-06 (``t_gps_s``, continuous: no week wrap). GPS epochs
(toc) are GPS time; GLONASS epochs are UTC in RINEX (2.x and 3.x) and are converted with
the header's LEAP SECONDS, else the IERS leap-second history
(:func:`sitl.gnss.rinex_common.gps_utc_leap_seconds`).

Units are SI: metres, m/s, m/s^2, seconds, radians (RINEX GLONASS km are converted).
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from .rinex_common import (version_line, 
    GnssFileError,
    calendar_seconds,
    fail,
    fortran_float,
    gps_utc_leap_seconds,
    read_lines,
    two_digit_year,
)

__all__ = ["NavFile", "GpsEphemerides", "GlonassEphemerides", "read_nav", "GnssFileError",
           "GPS_DEFAULT_FIT_H", "GLONASS_MAX_AGE_S"]

#: Fit interval used when the record's fit field is 0 or blank: IS-GPS-200 sec. 20.3.3.4.3.1
#: (fit interval flag 0 = 4 hours); RINEX 2.11 gives the interval in hours in that field.
GPS_DEFAULT_FIT_H = 4.0

#: A GLONASS record is used up to this far from its epoch t_b. The ICD's records are
#: refreshed every 30 min and meant for t_b +- 15 min; 30 min (RTKLIB's MAXDTOE_GLO) keeps a
#: satellite in use when one record is missing.
GLONASS_MAX_AGE_S = 1800.0

_SECONDS_PER_WEEK = 604_800.0

# Lines per record in RINEX 3 (systems whose records are skipped need their length).
_V3_RECORD_LINES = {"G": 8, "R": 4, "E": 8, "C": 8, "J": 8, "I": 8, "S": 4}


class _Records:
    """What both systems' record tables share: read-only columns, a length, the satellites."""

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, np.ndarray):
                v.setflags(write=False)

    def __len__(self) -> int:
        return int(self.sat.shape[0])

    @property
    def sats(self) -> list[str]:
        """The satellites with at least one record, sorted."""
        return sorted(set(self.sat.tolist()))


@dataclass(frozen=True, eq=False)
class GpsEphemerides(_Records):
    """Every GPS broadcast record of a file (N rows, file order; IS-GPS-200 Table 20-III names).

    sat 'Gnn'; toc_gps_s (clock epoch); toe_gps_s = week * 604800 + Toe; af0_s, af1, af2
    (clock polynomial, s, s/s, s/s^2); iode, iodc; sqrt_a (m^0.5), e, i0_rad, omega0_rad
    (OMEGA0: node longitude at the weekly epoch), omega_rad, m0_rad, delta_n_rad_s,
    omega_dot_rad_s, idot_rad_s, cuc_rad, cus_rad, crc_m, crs_m, cic_rad, cis_rad; week;
    sv_accuracy_m; health (0 = all signals OK); tgd_s; ttm_s (transmission time of message,
    seconds of week); fit_h (fit interval, hours; 0/blank read as 4 h); line (the record's first
    line in the file).
    """

    sat: np.ndarray
    toc_gps_s: np.ndarray
    toe_gps_s: np.ndarray
    af0_s: np.ndarray
    af1: np.ndarray
    af2: np.ndarray
    iode: np.ndarray
    iodc: np.ndarray
    sqrt_a: np.ndarray
    e: np.ndarray
    i0_rad: np.ndarray
    omega0_rad: np.ndarray
    omega_rad: np.ndarray
    m0_rad: np.ndarray
    delta_n_rad_s: np.ndarray
    omega_dot_rad_s: np.ndarray
    idot_rad_s: np.ndarray
    cuc_rad: np.ndarray
    cus_rad: np.ndarray
    crc_m: np.ndarray
    crs_m: np.ndarray
    cic_rad: np.ndarray
    cis_rad: np.ndarray
    week: np.ndarray
    sv_accuracy_m: np.ndarray
    health: np.ndarray
    tgd_s: np.ndarray
    ttm_s: np.ndarray
    fit_h: np.ndarray
    line: np.ndarray

    def select(self, sat, t_gps_s, usable=None) -> np.ndarray:
        """Index of the record in force for each (satellite, time) pair, -1 where none is.

        The record whose Toe is nearest t among those whose fit interval covers t
        (|t - toe| <= fit_h * 1800 s, IS-GPS-200 20.3.4.4), the earliest in the file on a
        tie. Health is not looked at: the caller decides what an unhealthy record in force
        means (``health[i] != 0``). ``usable`` (bool (N,)) leaves records out (e.g.
        ``~mislabelled()``)."""
        half = self.fit_h * 1800.0
        if usable is not None:
            half = np.where(np.asarray(usable, bool), half, -1.0)
        return _select(self.sat, self.toe_gps_s, half, sat, t_gps_s)

    def mislabelled(self) -> np.ndarray:
        """Records that are copies of another satellite's record (bool (N,)).

        Two satellites cannot broadcast the same orbit: records of different PRNs with the same
        Toe, sqrt(A), e, M0, OMEGA0, i0 and af0 are one satellite's message filed under two
        PRNs (a merging artefact of daily brdc files: brdc1820.10n has PRN 23's 06:00 record
        also as PRN 1, health 0). The copy is the one whose eccentricity differs from the median
        of its own PRN's other records (e changes by ~1e-7 a day); file-internal, no reference
        orbit is looked at."""
        key = np.stack([self.toe_gps_s, self.sqrt_a, self.e, self.m0_rad, self.omega0_rad, self.i0_rad,
                        self.af0_s], axis=1)
        bad = np.zeros(len(self), bool)
        _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        for g in np.flatnonzero(counts > 1):
            members = np.flatnonzero(inv.reshape(-1) == g)
            if len(set(self.sat[members].tolist())) < 2:
                continue
            for m in members:
                others = (self.sat == self.sat[m]) & (inv.reshape(-1) != g)
                if others.any() and abs(np.median(self.e[others]) - self.e[m]) > 1e-5:
                    bad[m] = True
        return bad


@dataclass(frozen=True, eq=False)
class GlonassEphemerides(_Records):
    """Every GLONASS broadcast record of a file (N rows, file order; GLONASS ICD 5.1 names).

    sat 'Rnn' (slot); toc_gps_s (t_b, converted from UTC); tau_n_s (the ICD's tau_n: RINEX
    stores -tau_n as 'SV clock bias', so the satellite clock offset is
    -tau_n + gamma_n (t - t_b)); gamma_n; tk_s (message frame time, as in the file); pos_m,
    vel_m_s, acc_m_s2 ((N, 3), PZ-90 of the epoch, rotating frame; acc = the lunisolar
    acceleration); health (RINEX: 0 = OK); freq_num (FDMA channel k); age_days (E_n);
    line (the record's first line).
    """

    sat: np.ndarray
    toc_gps_s: np.ndarray
    tau_n_s: np.ndarray
    gamma_n: np.ndarray
    tk_s: np.ndarray
    pos_m: np.ndarray
    vel_m_s: np.ndarray
    acc_m_s2: np.ndarray
    health: np.ndarray
    freq_num: np.ndarray
    age_days: np.ndarray
    line: np.ndarray

    def select(self, sat, t_gps_s, max_age_s: float = GLONASS_MAX_AGE_S) -> np.ndarray:
        """Index of the record nearest in t_b for each (satellite, time), within ``max_age_s``
        (default 30 min), -1 where none is; health not looked at (see GpsEphemerides.select)."""
        return _select(self.sat, self.toc_gps_s, np.full(len(self), float(max_age_s)), sat, t_gps_s)


@dataclass(frozen=True, eq=False)
class NavFile:
    """A navigation file: its version, header values and records by system.

    ion_alpha / ion_beta: the Klobuchar coefficients (4 each) or None; leap_seconds: the
    header's LEAP SECONDS or None; gps / glonass: the records, or None if the file has none.
    """

    path: str
    version: float
    leap_seconds: int | None
    ion_alpha: tuple | None
    ion_beta: tuple | None
    gps: GpsEphemerides | None
    glonass: GlonassEphemerides | None
    skipped: dict = field(default_factory=dict)  # records of other systems, by letter: count


def _select(rec_sat, rec_t, rec_half, sat, t_gps_s) -> np.ndarray:
    sat = np.asarray(sat, dtype=str).reshape(-1)
    t = np.asarray(t_gps_s, dtype=float).reshape(-1)
    if sat.shape != t.shape:
        sat, t = np.broadcast_arrays(sat, t)
    out = np.full(t.shape, -1, dtype=np.int64)
    for s in np.unique(sat):
        q = np.flatnonzero(sat == s)
        r = np.flatnonzero(rec_sat == s)
        if r.size == 0:
            continue
        dt = np.abs(t[q, None] - rec_t[None, r])
        dt = np.where(dt <= rec_half[None, r], dt, np.inf)
        best = np.argmin(dt, axis=1)  # first minimum = earliest record in the file
        ok = np.isfinite(dt[np.arange(q.size), best])
        out[q[ok]] = r[best[ok]]
    return out


# ---------------------------------------------------------------------------------------------

def _header(path, lines):
    version, _ = version_line(path, lines)
    head = lines[0]
    if int(version) not in (2, 3):
        fail(path, 1, f"unsupported RINEX version {version:g} (2.x and 3.x are read)")
    ftype = head[20:21]
    if int(version) == 2:
        if ftype not in ("N", "G"):
            fail(path, 1, f"not a GPS ('N') or GLONASS ('G') navigation file: type {ftype!r}")
        system = "G" if ftype == "N" else "R"
    else:
        if ftype != "N":
            fail(path, 1, f"not a navigation file: type {ftype!r}")
        system = head[40:41] or "M"
    end = None
    leap = None
    alpha = beta = None
    for j, ln in enumerate(lines[1:], start=2):
        label = ln[60:].strip()
        if label == "END OF HEADER":
            end = j
            break
        try:
            if label == "LEAP SECONDS":
                leap = int(ln[:6])
            elif label == "ION ALPHA":
                alpha = tuple(fortran_float(ln[2 + 12 * q:14 + 12 * q], path, j) for q in range(4))
            elif label == "ION BETA":
                beta = tuple(fortran_float(ln[2 + 12 * q:14 + 12 * q], path, j) for q in range(4))
            elif label == "IONOSPHERIC CORR" and ln[:4] in ("GPSA", "GPSB"):
                vals = tuple(fortran_float(ln[5 + 12 * q:17 + 12 * q], path, j) for q in range(4))
                if ln[:4] == "GPSA":
                    alpha = vals
                else:
                    beta = vals
        except ValueError as exc:
            if isinstance(exc, GnssFileError):
                raise
            fail(path, j, f"cannot read the {label} header line")
    if end is None:
        fail(path, len(lines), "no 'END OF HEADER' line")
    return version, system, end, leap, alpha, beta


def _epoch_v2(ln, path, lineno):
    try:
        yy, mo, dd, hh, mi = (int(ln[2 + 3 * q:5 + 3 * q]) for q in range(5))
        sec = float(ln[17:22])
        return calendar_seconds(two_digit_year(yy), mo, dd, hh, mi, sec), (two_digit_year(yy), mo, dd)
    except ValueError:
        fail(path, lineno, f"cannot read the record's epoch from {ln[3:22]!r}")


def _epoch_v3(ln, path, lineno):
    try:
        y, mo, dd, hh, mi, ss = int(ln[4:8]), *(int(ln[8 + 3 * q:11 + 3 * q]) for q in range(5))
        return calendar_seconds(y, mo, dd, hh, mi, float(ss)), (y, mo, dd)
    except ValueError:
        fail(path, lineno, f"cannot read the record's epoch from {ln[4:23]!r}")


def read_nav(path) -> NavFile:
    """Read every GPS and GLONASS record of a RINEX 2.x ('N' GPS, 'G' GLONASS) or 3.x ('N',
    any system; Galileo, BeiDou, QZSS, SBAS, IRNSS records are counted in ``skipped``)
    navigation file. Raises :class:`GnssFileError` naming the file and line on a malformed,
    truncated or unknown-version file, or one without a GPS/GLONASS record."""
    lines = read_lines(path)
    version, system, end, leap, alpha, beta = _header(path, lines)
    major = int(version)
    gps_rows, glo_rows, skipped = [], [], {}
    j = end  # index of the first body line (0-based)
    n = len(lines)
    while j < n:
        ln = lines[j]
        if not ln.strip():
            j += 1
            continue
        lineno = j + 1
        if major == 3:
            sysc = ln[0]
            if sysc not in _V3_RECORD_LINES:
                fail(path, lineno, f"expected a record's first line (system letter), got {ln[:20]!r}")
            nlines = _V3_RECORD_LINES[sysc]
            if sysc == "R" and version >= 3.05:
                nlines = 5
            first_col, cont_col = 23, 4
        else:
            if not ln[:2].strip():
                fail(path, lineno, f"expected a record's first line (satellite number), got {ln[:20]!r}")
            sysc = system
            nlines = 8 if sysc == "G" else 4
            first_col, cont_col = 22, 3
        rec = lines[j:j + nlines]
        if len(rec) < nlines or any(not r.strip() for r in rec):
            fail(path, lineno, f"record truncated: {len(rec)} of its {nlines} lines")
        for k in range(1, nlines):
            if rec[k][:cont_col].strip():
                fail(path, lineno + k, f"record has {k} of its {nlines} lines (a broadcast orbit line "
                                       "starts with blanks)")
        j += nlines
        if sysc not in ("G", "R"):
            skipped[sysc] = skipped.get(sysc, 0) + 1
            continue
        try:
            prn = int(ln[1:3] if major == 3 else ln[0:2])
        except ValueError:
            fail(path, lineno, f"cannot read the satellite number from {ln[:3]!r}")
        if not 1 <= prn <= 99:
            fail(path, lineno, f"satellite number {prn} out of 1..99")
        toc, ymd = (_epoch_v3 if major == 3 else _epoch_v2)(ln, path, lineno)
        vals = [fortran_float(ln[first_col + 19 * q:first_col + 19 * (q + 1)], path, lineno) for q in range(3)]
        for k in range(1, nlines):
            r = rec[k]
            vals += [fortran_float(r[cont_col + 19 * q:cont_col + 19 * (q + 1)], path, lineno + k) for q in range(4)]
        if sysc == "G":
            gps_rows.append(_gps_row(prn, toc, vals, path, lineno))
        else:
            lp = leap if leap is not None else gps_utc_leap_seconds(*ymd)
            glo_rows.append(_glo_row(prn, toc + lp, vals, lineno))
    if not gps_rows and not glo_rows:
        fail(path, None, "no GPS or GLONASS navigation record")
    gps = _columns(GpsEphemerides, gps_rows) if gps_rows else None
    glo = _columns(GlonassEphemerides, glo_rows) if glo_rows else None
    return NavFile(str(path), version, leap, alpha, beta, gps, glo, skipped)


def _gps_row(prn, toc, v, path, lineno):
    (af0, af1, af2, iode, crs, dn, m0, cuc, e, cus, sqrt_a, toe, cic, om0, cis, i0, crc, w, omd,
     idot, _codes, week, _l2p, acc, health, tgd, iodc, ttm, fit) = v[:29]
    if not 0.0 <= e < 1.0:
        fail(path, lineno + 2, f"eccentricity {e} out of [0, 1)")
    if sqrt_a <= 0.0:
        fail(path, lineno + 2, f"sqrt(A) {sqrt_a} must be positive")
    if not 0.0 <= toe < _SECONDS_PER_WEEK:
        fail(path, lineno + 3, f"Toe {toe} outside the week")
    if week != int(week) or week <= 0:
        fail(path, lineno + 5, f"bad GPS week {week}")
    return dict(
        sat=f"G{prn:02d}", toc_gps_s=toc, toe_gps_s=week * _SECONDS_PER_WEEK + toe, af0_s=af0, af1=af1,
        af2=af2, iode=iode, iodc=iodc, sqrt_a=sqrt_a, e=e, i0_rad=i0, omega0_rad=om0, omega_rad=w,
        m0_rad=m0, delta_n_rad_s=dn, omega_dot_rad_s=omd, idot_rad_s=idot, cuc_rad=cuc, cus_rad=cus,
        crc_m=crc, crs_m=crs, cic_rad=cic, cis_rad=cis, week=int(week), sv_accuracy_m=acc,
        health=int(health), tgd_s=tgd, ttm_s=ttm, fit_h=fit if fit > 0 else GPS_DEFAULT_FIT_H, line=lineno,
    )


def _glo_row(prn, toc, v, lineno):
    (mtau, gamma, tk, x, vx, ax, health, y, vy, ay, k, z, vz, az, age) = v[:15]
    return dict(
        sat=f"R{prn:02d}", toc_gps_s=toc, tau_n_s=-mtau, gamma_n=gamma, tk_s=tk,
        pos_m=(x * 1e3, y * 1e3, z * 1e3), vel_m_s=(vx * 1e3, vy * 1e3, vz * 1e3),
        acc_m_s2=(ax * 1e3, ay * 1e3, az * 1e3), health=int(health), freq_num=int(k), age_days=age,
        line=lineno,
    )


def _columns(cls, rows):
    cols = {}
    for f in fields(cls):
        vals = [r[f.name] for r in rows]
        cols[f.name] = np.array(vals, dtype=str if f.name == "sat" else None)
    return cls(**cols)
