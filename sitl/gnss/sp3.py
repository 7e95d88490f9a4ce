"""SP3-c / SP3-d precise orbit files (NGS/IGS format, Hilla 2010 and 2016).

    orb = read_sp3("igs15904.sp3")
    orb.sats        # ('G01', ...), as in the header
    orb.t_gps_s     # (T,) epochs, GPS seconds since 1980-01-06
    orb.pos_m       # (T, S, 3) ECEF position of the centre of mass, m; NaN where the file has none
    orb.clock_s     # (T, S) satellite clock offset, s; NaN for the 999999.999999 'no value'
    orb.coord_sys, orb.agency, orb.time_system

Positions of exactly 0.000000 km and clocks >= 999999 us are the format's 'no value' and
become NaN. Velocity records ('V', dm/s and 1e-4 us/s) fill ``vel_m_s`` / ``clock_rate``
when present (pos/vel flag 'V'). Epochs in UTC or TAI are converted to GPS time
(the IERS leap seconds; TAI - 19 s); GLONASS time (UTC + 3 h) likewise.

Why an own reader and not georinex's load_sp3 (which reads both files here in 0.03 s): the
errors must name the file and line, a truncated file must be refused (the header's epoch
count is checked), and the file's time system is honoured. The tests check it against
georinex on the same files.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .rinex_common import calendar_seconds, fail, fortran_float, gps_utc_leap_seconds, read_lines

__all__ = ["Sp3", "read_sp3"]


@dataclass(frozen=True, eq=False)
class Sp3:
    """A precise orbit file's content; see the module docstring."""

    path: str
    version: str
    sats: tuple
    t_gps_s: np.ndarray
    pos_m: np.ndarray
    clock_s: np.ndarray
    vel_m_s: np.ndarray | None
    clock_rate: np.ndarray | None
    interval_s: float
    coord_sys: str
    orbit_type: str
    agency: str
    time_system: str

    def __post_init__(self):
        for a in (self.t_gps_s, self.pos_m, self.clock_s, self.vel_m_s, self.clock_rate):
            if a is not None:
                a.setflags(write=False)

    def index(self, sat: str) -> int:
        return self.sats.index(sat)


def _sat_id(text: str) -> str:
    text = text.replace(" ", "0") if text[:1] != " " else "G" + text[1:].replace(" ", "0")
    return text


def read_sp3(path) -> Sp3:
    """Read an SP3-c or SP3-d file; :class:`~sitl.gnss.rinex_common.GnssFileError` naming the
    file and line if it is malformed, truncated, of another version, or has no satellite."""
    lines = read_lines(path)
    if not lines:
        fail(path, None, "empty file")
    h = lines[0]
    if not h.startswith("#"):
        fail(path, 1, "not an SP3 file (the first line does not start with '#')")
    version = h[1:2]
    if version not in ("c", "d"):
        fail(path, 1, f"unsupported SP3 version {version!r} (SP3-c and SP3-d are read)")
    flag = h[2:3]
    if flag not in ("P", "V"):
        fail(path, 1, f"position/velocity flag must be 'P' or 'V', got {flag!r}")
    try:
        n_epochs = int(h[32:39])
    except ValueError:
        fail(path, 1, f"cannot read the number of epochs from {h[32:39]!r}")
    coord_sys, orbit_type, agency = h[46:51].strip(), h[52:55].strip(), h[56:60].strip()
    if len(lines) < 2 or not lines[1].startswith("##"):
        fail(path, 2, "second header line must start with '##'")
    interval = fortran_float(lines[1][24:38], path, 2)
    # satellite list: '+' lines (5 in SP3-c, at least 5 in SP3-d), 17 ids each from column 9
    j = 2
    plus = []
    while j < len(lines) and lines[j].startswith("+ "):
        plus.append(lines[j])
        j += 1
    if not plus:
        fail(path, 3, "no '+' satellite list line")
    try:
        n_sat = int(plus[0][3:6])
    except ValueError:
        fail(path, 3, f"cannot read the number of satellites from {plus[0][3:6]!r}")
    ids = []
    for ln in plus:
        for q in range(17):
            s = ln[9 + 3 * q:12 + 3 * q]
            if len(ids) < n_sat and s.strip() and s.strip() != "0":
                ids.append(_sat_id(s))
    if n_sat <= 0 or len(ids) != n_sat:
        fail(path, 3, f"header announces {n_sat} satellites, lists {len(ids)}")
    first_c = next((ln for ln in lines[j:] if ln.startswith(("%c", "*"))), "")
    ts = first_c[9:12].strip() if first_c.startswith("%c") else ""
    time_system = "GPS" if ts in ("", "ccc") else ts
    if time_system not in ("GPS", "UTC", "TAI", "GLO"):
        fail(path, None, f"unsupported time system {time_system!r}")
    col = {s: q for q, s in enumerate(ids)}
    t_list, pos, clk, vel, rate = [], [], [], [], []
    seen_eof = False
    last = None
    for k in range(j, len(lines)):
        ln = lines[k]
        lineno = k + 1
        if ln.startswith("*"):
            try:
                y, mo, d, hh, mi = (int(v) for v in ln[3:31].split()[:5])
                sec = float(ln[3:31].split()[5])
            except (ValueError, IndexError):
                fail(path, lineno, f"cannot read the epoch from {ln[:31]!r}")
            t = calendar_seconds(y, mo, d, hh, mi, sec)
            if time_system == "UTC":
                t += gps_utc_leap_seconds(y, mo, d)
            elif time_system == "GLO":
                t += gps_utc_leap_seconds(y, mo, d) - 3 * 3600.0
            elif time_system == "TAI":
                t -= 19.0
            if t_list and t <= t_list[-1]:
                fail(path, lineno, "epochs must increase")
            t_list.append(t)
            pos.append(np.full((n_sat, 3), np.nan))
            clk.append(np.full(n_sat, np.nan))
            vel.append(np.full((n_sat, 3), np.nan))
            rate.append(np.full(n_sat, np.nan))
            last = lineno
        elif ln.startswith("P") or (ln.startswith("V") and flag == "V"):
            if not t_list:
                fail(path, lineno, "a record before the first epoch line")
            sid = _sat_id(ln[1:4])
            if sid not in col:
                fail(path, lineno, f"satellite {sid} is not in the header's list")
            x, y_, z = (fortran_float(ln[4 + 14 * q:18 + 14 * q], path, lineno, blank=np.nan) for q in range(3))
            c = fortran_float(ln[46:60], path, lineno, blank=np.nan)
            q = col[sid]
            if ln[0] == "P":
                if not np.isnan(pos[-1][q, 0]):
                    fail(path, lineno, f"satellite {sid} twice in one epoch")
                if not (x == 0.0 and y_ == 0.0 and z == 0.0):
                    pos[-1][q] = (x * 1e3, y_ * 1e3, z * 1e3)
                if np.isfinite(c) and abs(c) < 999999.0:
                    clk[-1][q] = c * 1e-6
            else:
                if not (x == 0.0 and y_ == 0.0 and z == 0.0):
                    vel[-1][q] = (x * 0.1, y_ * 0.1, z * 0.1)
                if np.isfinite(c) and abs(c) < 999999.0:
                    rate[-1][q] = c * 1e-10
            last = lineno
        elif ln.startswith("EOF"):
            seen_eof = True
            break
        elif ln.startswith(("EP", "EV", "/*", "%", "#", "+")) or not ln.strip():
            continue
        else:
            fail(path, lineno, f"unexpected line {ln[:20]!r}")
    if len(t_list) != n_epochs:
        fail(path, last or len(lines), f"header announces {n_epochs} epochs, the file has {len(t_list)} (truncated?)")
    if not seen_eof:
        fail(path, len(lines), "no 'EOF' line (truncated?)")
    pos_a = np.array(pos)
    if not np.isfinite(pos_a).any():
        fail(path, None, "no satellite position in the file")
    has_vel = flag == "V"
    return Sp3(str(path), version, tuple(ids), np.array(t_list), pos_a, np.array(clk),
               np.array(vel) if has_vel else None, np.array(rate) if has_vel else None,
               interval, coord_sys, orbit_type, agency, time_system)
