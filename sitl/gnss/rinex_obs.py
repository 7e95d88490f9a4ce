"""RINEX 2.x / 3.x observation files (GPS, GLONASS and the other systems' records kept as read).

    obs = read_obs("07590920.05o")
    obs.t_gps_s            # (T,) epochs (GPS seconds since 1980-01-06; receiver time tags)
    obs.sats               # ('G01', 'G03', ...) sorted
    obs.codes["G"]         # the file's observation codes for GPS, in file order: RINEX 2
                           # ('L1', 'C1', 'L2', 'P2') or RINEX 3 ('C1C', 'L1C', 'D1C', 'S1C')
    obs.data["C1"]         # (T, S) values (m, cycles, Hz, dB-Hz), NaN where not observed
    obs.lli["L1"], obs.ssi["L1"]   # (T, S) loss-of-lock / signal-strength digits, 0 if blank
    obs.epoch_flag         # (T,) 0 OK, 1 power failure before the epoch, 6 cycle-slip records
    obs.approx_position_m, obs.antenna_delta_hen_m, obs.interval_s, obs.receiver, obs.antenna
    obs.glonass_slots      # RINEX 3 'GLONASS SLOT / FRQ #': {'R01': 1, ...} (k), else {}
    obs.column('G05'), obs.get('C1', 'G05')    # helpers

RINEX 2 files hold one code list for every system ('# / TYPES OF OBSERV'); ``codes`` then has
that list for each system seen. Event epochs (flags 2-5: their header/comment lines are
skipped) are not epochs of data. Epoch times are in the file's time system: GPS (the default
and the only one used here; a 'GLO' TIME OF FIRST OBS is refused).

Why an own reader: georinex 1.16.2 reads the 1 h station file in 0.06 s and agrees with this
one value for value (tests/sitl/gnss/test_gnss_readers.py), but it names no line on a bad
file and silently stops at a truncated epoch; this reader refuses both with the line.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from .rinex_common import calendar_seconds, fail, fortran_float, read_lines, two_digit_year, version_line

__all__ = ["ObsFile", "read_obs"]

_V2_EPOCH = re.compile(r"^ [ \d]\d [ \d]\d [ \d]\d [ \d]\d [ \d]\d [ \d]\d\.\d{7}  [0-6][ \d]{2}\d")


@dataclass(frozen=True, eq=False)
class ObsFile:
    path: str
    version: float
    marker: str
    receiver: str
    antenna: str
    approx_position_m: np.ndarray | None
    antenna_delta_hen_m: np.ndarray | None
    interval_s: float | None
    codes: dict
    t_gps_s: np.ndarray
    sats: tuple
    data: dict
    lli: dict
    ssi: dict
    epoch_flag: np.ndarray
    clock_offset_s: np.ndarray
    glonass_slots: dict = field(default_factory=dict)

    def column(self, sat: str) -> int:
        return self.sats.index(sat)

    def get(self, code: str, sat: str) -> np.ndarray:
        """(T,) values of ``code`` for ``sat`` (NaN where not observed)."""
        return self.data[code][:, self.column(sat)]


def _sat_v2(text: str, default: str) -> str:
    s = text[0] if text[0] != " " else default
    return f"{s}{int(text[1:3]):02d}"


def read_obs(path) -> ObsFile:
    """Read a RINEX 2.x or 3.x observation file; :class:`~sitl.gnss.rinex_common.GnssFileError`
    naming the file and line if it is malformed, truncated, of another version or has no
    observation."""
    lines = read_lines(path)
    version, _ = version_line(path, lines)
    h = lines[0]
    if h[20:21] != "O":
        fail(path, 1, f"not an observation file: type {h[20:21]!r}")
    major = int(version)
    if major not in (2, 3):
        fail(path, 1, f"unsupported RINEX version {version:g} (2.x and 3.x are read)")
    default_sys = h[40:41].strip() or "G"
    if default_sys == "M":
        default_sys = "G"
    marker = receiver = antenna = ""
    pos = delta = None
    interval = None
    codes: dict = {}
    v2_codes: list = []
    v2_n = 0
    glo_slots = {}
    end = None
    pending_sys = None
    for j in range(1, len(lines)):
        ln = lines[j]
        lineno = j + 1
        label = ln[60:].strip()
        if label == "END OF HEADER":
            end = j + 1
            break
        if label == "MARKER NAME":
            marker = ln[:60].strip()
        elif label == "REC # / TYPE / VERS":
            receiver = ln[20:40].strip()
        elif label == "ANT # / TYPE":
            antenna = ln[20:40].strip()
        elif label == "APPROX POSITION XYZ":
            pos = np.array([fortran_float(ln[14 * q:14 * q + 14], path, lineno) for q in range(3)])
        elif label == "ANTENNA: DELTA H/E/N":
            delta = np.array([fortran_float(ln[14 * q:14 * q + 14], path, lineno) for q in range(3)])
        elif label == "INTERVAL":
            interval = fortran_float(ln[:10], path, lineno) or None
        elif label == "TIME OF FIRST OBS":
            ts = ln[48:51].strip()
            if ts not in ("", "GPS"):
                fail(path, lineno, f"unsupported time system {ts!r} (GPS time tags are read)")
        elif label == "# / TYPES OF OBSERV":
            if ln[:6].strip():
                try:
                    v2_n = int(ln[:6])
                except ValueError:
                    fail(path, lineno, f"cannot read the number of observation types from {ln[:6]!r}")
            v2_codes += ln[6:60].split()
        elif label == "SYS / # / OBS TYPES":
            if ln[0] != " ":
                pending_sys = ln[0]
                try:
                    n = int(ln[3:6])
                except ValueError:
                    fail(path, lineno, f"cannot read the number of observation types from {ln[3:6]!r}")
                codes[pending_sys] = (n, ln[7:60].split())
            elif pending_sys is not None:
                codes[pending_sys][1].extend(ln[7:60].split())
        elif label == "GLONASS SLOT / FRQ #":
            items = ln[4:60].split()
            for a, b in zip(items[::2], items[1::2]):
                try:
                    glo_slots[a] = int(b)
                except ValueError:
                    fail(path, lineno, f"cannot read a GLONASS channel from {b!r}")
    if end is None:
        fail(path, len(lines), "no 'END OF HEADER' line")
    if major == 2:
        if v2_n <= 0 or len(v2_codes) != v2_n:
            fail(path, end, f"'# / TYPES OF OBSERV' announces {v2_n} types, lists {len(v2_codes)}")
        code_lists = None
    else:
        for sysc, (n, lst) in codes.items():
            if n != len(lst):
                fail(path, end, f"'SYS / # / OBS TYPES' for {sysc} announces {n} types, lists {len(lst)}")
        code_lists = {k: v[1] for k, v in codes.items()}
        if not code_lists:
            fail(path, end, "no 'SYS / # / OBS TYPES' header line")

    epochs = []  # (t, flag, clock, {sat: [(value, lli, ssi), ...]})
    j = end
    n = len(lines)
    while j < n:
        ln = lines[j]
        lineno = j + 1
        if not ln.strip():
            j += 1
            continue
        if major == 2:
            try:
                flag = int(ln[28:29] or 0)
                nsat = int(ln[29:32])
            except ValueError:
                fail(path, lineno, f"cannot read an epoch line from {ln[:32]!r}")
            if flag > 1 and flag != 6:  # event (its date may be blank): nsat header/comment lines follow
                j += 1 + nsat
                continue
            try:
                yy, mo, dd, hh, mi = (int(ln[1 + 3 * q:3 + 3 * q]) for q in range(5))
                sec = float(ln[15:26])
            except ValueError:
                fail(path, lineno, f"cannot read an epoch line from {ln[:32]!r}")
            sat_txt = ln[32:68]
            k = j + 1
            while len(sat_txt) < 3 * nsat:
                if k >= n:
                    fail(path, lineno, "epoch truncated in its satellite list")
                sat_txt += lines[k][32:68]
                k += 1
            try:
                sats = [_sat_v2(sat_txt[3 * q:3 * q + 3], default_sys) for q in range(nsat)]
            except ValueError:
                fail(path, lineno, f"cannot read the satellite list {sat_txt.strip()!r}")
            clock = fortran_float(ln[68:80], path, lineno, blank=np.nan)
            per_line = 5
            nlines = -(-v2_n // per_line)
            rows = {}
            for s in sats:
                vals = []
                for q in range(nlines):
                    if k >= n:
                        fail(path, lineno, f"epoch truncated: {s} has no observation line")
                    dl = lines[k]
                    if _V2_EPOCH.match(dl):
                        fail(path, k + 1, f"epoch of line {lineno} truncated: an epoch line where {s}'s "
                                          "observations were expected")
                    for f in range(per_line):
                        if len(vals) == v2_n:
                            break
                        fld = dl[16 * f:16 * f + 16]
                        vals.append(_obs_field(fld, path, k + 1))
                    k += 1
                rows[s] = vals
            epochs.append((calendar_seconds(two_digit_year(yy), mo, dd, hh, mi, sec), flag, clock, rows))
            j = k
        else:
            if ln[0] != ">":
                fail(path, lineno, f"expected an epoch line ('>'), got {ln[:20]!r}")
            try:
                flag = int(ln[31:32] or 0)
                nsat = int(ln[32:35])
            except ValueError:
                fail(path, lineno, f"cannot read an epoch line from {ln[:35]!r}")
            if flag > 1 and flag != 6:  # event: nsat header/comment lines follow
                j += 1 + nsat
                continue
            try:
                y, mo, dd, hh, mi = (int(v) for v in ln[2:29].split()[:5])
                sec = float(ln[2:29].split()[5])
            except (ValueError, IndexError):
                fail(path, lineno, f"cannot read an epoch line from {ln[:35]!r}")
            clock = fortran_float(ln[41:56], path, lineno, blank=np.nan)
            rows = {}
            for q in range(nsat):
                k = j + 1 + q
                if k >= n or lines[k][:1] == ">":
                    fail(path, lineno, f"epoch truncated: {q} of its {nsat} satellite lines")
                dl = lines[k]
                try:
                    s = f"{dl[0]}{int(dl[1:3]):02d}"
                except ValueError:
                    fail(path, k + 1, f"cannot read the satellite from {dl[:3]!r}")
                lst = code_lists.get(dl[0])
                if lst is None:
                    fail(path, k + 1, f"no observation types declared for system {dl[0]!r}")
                rows[s] = [_obs_field(dl[3 + 16 * f:19 + 16 * f], path, k + 1) for f in range(len(lst))]
            epochs.append((calendar_seconds(y, mo, dd, hh, mi, sec), flag, clock, rows))
            j += 1 + nsat
    if not epochs:
        fail(path, None, "no observation epoch")
    all_sats = sorted({s for e in epochs for s in e[3]})
    if major == 2:
        code_lists = {s[0]: list(v2_codes) for s in all_sats}
    col = {s: q for q, s in enumerate(all_sats)}
    T, S = len(epochs), len(all_sats)
    all_codes = sorted({c for lst in code_lists.values() for c in lst})
    data = {c: np.full((T, S), np.nan) for c in all_codes}
    lli = {c: np.zeros((T, S), np.int8) for c in all_codes}
    ssi = {c: np.zeros((T, S), np.int8) for c in all_codes}
    for i, (_, _, _, rows) in enumerate(epochs):
        for s, vals in rows.items():
            q = col[s]
            for c, (v, a, b) in zip(code_lists[s[0]], vals):
                data[c][i, q] = v
                lli[c][i, q] = a
                ssi[c][i, q] = b
    t = np.array([e[0] for e in epochs])
    if np.any(np.diff(t) <= 0):
        k = int(np.flatnonzero(np.diff(t) <= 0)[0])
        fail(path, None, f"epochs do not increase (epoch {k + 2})")
    for d in (data, lli, ssi):
        for a in d.values():
            a.setflags(write=False)
    return ObsFile(str(path), version, marker, receiver, antenna, pos, delta, interval,
                   {k: tuple(v) for k, v in code_lists.items()}, t, tuple(all_sats), data, lli, ssi,
                   np.array([e[1] for e in epochs]), np.array([e[2] for e in epochs]), glo_slots)


def _obs_field(fld: str, path, lineno: int):
    """One F14.3 + LLI (I1) + SSI (I1) field: (value or NaN, lli, ssi)."""
    v = fld[:14]
    value = fortran_float(v, path, lineno, blank=np.nan) if v.strip() else np.nan
    a = fld[14:15].strip()
    b = fld[15:16].strip()
    if (a and not a.isdigit()) or (b and not b.isdigit()):
        fail(path, lineno, f"bad loss-of-lock / signal-strength digits {fld[14:16]!r}")
    return value, int(a or 0), int(b or 0)
