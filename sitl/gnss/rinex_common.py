"""What the GNSS file readers share: the error that names the file and line, Fortran-style
numbers, calendar epochs as GPS seconds, and the GPS - UTC leap seconds of the past.

Every reader in ``sitl.gnss`` (rinex_nav, rinex_obs, sp3, rinex_clk) raises
:class:`GnssFileError` (a ``ValueError``) for a file it cannot read: the message is one line,
``"<path>, line <n>: <what is wrong>"`` (``"<path>: ..."`` when no single line is to blame), so
the command line prints it as it is and exits 2.
"""
from __future__ import annotations

import re
from datetime import datetime
from pathlib import Path

__all__ = [
    "GnssFileError",
    "fail",
    "read_lines",
    "fortran_float",
    "calendar_seconds",
    "gps_utc_leap_seconds",
]

_GPS_EPOCH_ORDINAL = datetime(1980, 1, 6).toordinal()


class GnssFileError(ValueError):
    """A GNSS file that cannot be read: ``path`` and ``line`` (1-based, or None) and the reason."""

    def __init__(self, path, line: int | None, reason: str):
        self.path, self.line, self.reason = str(path), line, reason
        where = self.path if line is None else f"{self.path}, line {line}"
        super().__init__(f"{where}: {reason}")


def fail(path, line: int | None, reason: str):
    raise GnssFileError(path, line, reason)


def read_lines(path) -> list[str]:
    """The file's lines (ASCII; undecodable bytes become U+FFFD and fail where parsed)."""
    try:
        text = Path(path).read_bytes().decode("ascii", errors="replace")
    except OSError as exc:
        fail(path, None, f"cannot read the file ({exc.strerror})")
    return text.splitlines()


_NUMBER = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([EeDd][+-]?\d+)?$")


def version_line(path, lines: list[str]) -> tuple[float, str]:
    """(version, file-type letter) of a RINEX file's first line, 'RINEX VERSION / TYPE';
    GnssFileError naming line 1 if the file is empty or that line is not such a header."""
    if not lines:
        fail(path, None, "empty file")
    head = lines[0]
    if "RINEX VERSION / TYPE" not in head:
        fail(path, 1, "first line is not a 'RINEX VERSION / TYPE' header")
    try:
        version = float(head[:9])
    except ValueError:
        fail(path, 1, f"cannot read the RINEX version from {head[:9].strip()!r}")
    return version, head[20:21]


def fortran_float(text: str, path, line: int, blank: float = 0.0) -> float:
    """A RINEX/SP3 number ('D' exponents allowed); a blank field is ``blank`` (RINEX leaves
    unknown fields empty)."""
    s = text.strip()
    if not s:
        return blank
    if not _NUMBER.match(s):
        fail(path, line, f"cannot read a number from {text.strip()!r}")
    return float(s.replace("D", "E").replace("d", "e"))


def calendar_seconds(year: int, month: int, day: int, hour: int, minute: int, second: float) -> float:
    """Seconds from 1980-01-06 00:00:00 to the given calendar epoch *of the same time scale*
    (no leap seconds counted): for a GPS-time epoch this is t_gps_s itself; for a UTC epoch
    add :func:`gps_utc_leap_seconds`."""
    days = datetime(year, month, day).toordinal() - _GPS_EPOCH_ORDINAL
    return days * 86400.0 + hour * 3600.0 + minute * 60.0 + second


def two_digit_year(yy: int) -> int:
    """RINEX 2's two-digit years: 80-99 -> 1980-1999, 00-79 -> 2000-2079."""
    return yy + (1900 if yy >= 80 else 2000)


# GPS - UTC after each leap second (IERS Bulletin C; the date is the first UTC day it holds).
_LEAPS = (
    ((1981, 7, 1), 1), ((1982, 7, 1), 2), ((1983, 7, 1), 3), ((1985, 7, 1), 4), ((1988, 1, 1), 5),
    ((1990, 1, 1), 6), ((1991, 1, 1), 7), ((1992, 7, 1), 8), ((1993, 7, 1), 9), ((1994, 7, 1), 10),
    ((1996, 1, 1), 11), ((1997, 7, 1), 12), ((1999, 1, 1), 13), ((2006, 1, 1), 14), ((2009, 1, 1), 15),
    ((2012, 7, 1), 16), ((2015, 7, 1), 17), ((2017, 1, 1), 18),
)


def gps_utc_leap_seconds(year: int, month: int, day: int) -> int:
    """GPS - UTC in whole seconds on a UTC date (IERS Bulletin C history, to 2017-01-01: 18 s)."""
    leap = 0
    for date, value in _LEAPS:
        if (year, month, day) >= date:
            leap = value
    return leap
