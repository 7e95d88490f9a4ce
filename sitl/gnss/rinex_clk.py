"""RINEX clock files (2.00 - 3.04): satellite ('AS') and receiver ('AR') clock offsets.

    clk = read_clk("igs15904.clk")
    clk.sats, clk.t_gps_s, clk.bias_s      # (S,), (T,), (T, S) satellite clocks, NaN = no value
    clk.stations, clk.station_bias_s       # the same for 'AR' records
    clk.bias_at(["G05"], t)                # linear interpolation between the file's epochs

The epochs are GPS time (the format's default 'TIME SYSTEM ID' for GPS files); a file that
declares another time system is refused. The satellite clocks of IGS products hold no
periodic relativistic term (the user applies -2 r.v/c^2, as for the broadcast clock's
F e sqrt(A) sin E) and refer to the ionosphere-free P1/P2 combination.

georinex 1.16.2 has no clock reader ("unknown file type"), hence this one.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .rinex_common import calendar_seconds, fail, fortran_float, read_lines, version_line

__all__ = ["ClockFile", "read_clk"]


@dataclass(frozen=True, eq=False)
class ClockFile:
    path: str
    version: float
    t_gps_s: np.ndarray
    sats: tuple
    bias_s: np.ndarray
    sigma_s: np.ndarray
    stations: tuple
    station_bias_s: np.ndarray

    def bias_at(self, sats, t_gps_s, max_gap_s: float = 900.0) -> np.ndarray:
        """Satellite clock offsets at ``t_gps_s`` (any shape (...)) for ``sats`` -> (..., len(sats)),
        linear between the two neighbouring epochs when both have a value and are at most
        ``max_gap_s`` apart, NaN otherwise."""
        t = np.asarray(t_gps_s, dtype=float)
        tt = self.t_gps_s
        k = np.clip(np.searchsorted(tt, t, side="right") - 1, 0, len(tt) - 1)
        k1 = np.clip(k + 1, 0, len(tt) - 1)
        cols = [self.sats.index(s) if s in self.sats else -1 for s in sats]
        out = np.full(t.shape + (len(cols),), np.nan)
        for q, c in enumerate(cols):
            if c < 0:
                continue
            b0, b1 = self.bias_s[k, c], self.bias_s[k1, c]
            span = tt[k1] - tt[k]
            w = np.where(span > 0, (t - tt[k]) / np.where(span > 0, span, 1.0), 0.0)
            exact = np.isclose(t, tt[k], atol=1e-6, rtol=0)
            v = np.where(exact, b0, b0 + w * (b1 - b0))
            ok = (t >= tt[0] - 1e-6) & (t <= tt[-1] + 1e-6) & (exact | (span <= max_gap_s))
            out[..., q] = np.where(ok, v, np.nan)
        return out


def read_clk(path) -> ClockFile:
    """Read a RINEX clock file; :class:`~sitl.gnss.rinex_common.GnssFileError` naming the file
    and line if it is malformed, of another version or has no satellite clock."""
    lines = read_lines(path)
    version, _ = version_line(path, lines)
    h = lines[0]
    if h[20:21] != "C":
        fail(path, 1, f"not a clock file: type {h[20:21]!r}")
    if not 2.0 <= version < 4.0:
        fail(path, 1, f"unsupported clock file version {version:g}")
    end = None
    for k, ln in enumerate(lines[1:], start=2):
        label = ln[60:].strip() if version < 3.04 else ln[65:].strip() or ln[60:].strip()
        if label == "TIME SYSTEM ID" and ln[3:6].strip() not in ("GPS", ""):
            fail(path, k, f"unsupported time system {ln[3:6].strip()!r}")
        if "END OF HEADER" in ln[60:]:
            end = k
            break
    if end is None:
        fail(path, len(lines), "no 'END OF HEADER' line")
    name_w = 9 if version >= 3.04 else 4
    recs = {"AS": {}, "AR": {}}
    times = set()
    for k in range(end, len(lines)):
        ln = lines[k]
        lineno = k + 1
        typ = ln[:2]
        if typ not in ("AS", "AR"):
            if typ in ("CR", "DR", "MS") or not ln.strip():
                continue
            if ln[:1] == " " and ln.strip():  # continuation of a record with > 2 values
                continue
            fail(path, lineno, f"unexpected record type {typ!r}")
        name = ln[3:3 + name_w].strip()
        rest = ln[3 + name_w:].split()
        try:
            y, mo, d, hh, mi = (int(v) for v in rest[:5])
            sec = float(rest[5])
            nval = int(rest[6])
        except (ValueError, IndexError):
            fail(path, lineno, f"cannot read the epoch of {ln[:40]!r}")
        if nval < 1:
            fail(path, lineno, f"record has {nval} values")
        if len(rest) < 8:
            fail(path, lineno, "record truncated: no clock value")
        bias = fortran_float(rest[7], path, lineno)
        sig = fortran_float(rest[8], path, lineno) if nval >= 2 and len(rest) > 8 else np.nan
        t = calendar_seconds(y, mo, d, hh, mi, sec)
        times.add(t)
        recs[typ].setdefault(name, {})[t] = (bias, sig)
    if not recs["AS"]:
        fail(path, None, "no satellite clock ('AS') record")
    tt = np.array(sorted(times))
    ti = {t: q for q, t in enumerate(tt)}
    sats = tuple(sorted(recs["AS"]))
    bias = np.full((tt.size, len(sats)), np.nan)
    sigma = np.full((tt.size, len(sats)), np.nan)
    for c, s in enumerate(sats):
        for t, (b, sg) in recs["AS"][s].items():
            bias[ti[t], c], sigma[ti[t], c] = b, sg
    stations = tuple(sorted(recs["AR"]))
    sb = np.full((tt.size, len(stations)), np.nan)
    for c, s in enumerate(stations):
        for t, (b, _) in recs["AR"][s].items():
            sb[ti[t], c] = b
    for a in (tt, bias, sigma, sb):
        a.setflags(write=False)
    return ClockFile(str(path), version, tt, sats, bias, sigma, stations, sb)
