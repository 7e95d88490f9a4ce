"""GPS and GLONASS time scales, and Greenwich mean sidereal time.

The simulation clock is ``t_gps_s``: seconds of GPS time since the GPS epoch,
1980-01-06T00:00:00 UTC.  UTC is taken as GPS - ``GPS_UTC_LEAP_S`` (18 s, in force
since 2017-01-01) for every instant; dates before 2017 are therefore off by the
leap seconds inserted since (one-to-one and invertible, but not historical UTC).

GLONASS time (GLONASS ICD ed. 5.1, sec. 3.3.3) is UTC(SU) + 3 h, counted as
N4 (four-year interval, 1 for 1996-1999), NT (day within it, 1 = January 1 of the
leap year) and the time of day tod_s.
"""
from __future__ import annotations

from datetime import datetime, timedelta, timezone

import numpy as np

from .constants import GLONASS_UTC_OFFSET_S, GPS_UTC_LEAP_S

SECONDS_PER_DAY = 86_400.0
SECONDS_PER_WEEK = 604_800.0
DAYS_PER_FOUR_YEARS = 1461
GPS_EPOCH = datetime(1980, 1, 6, tzinfo=timezone.utc)
# Days from the GPS epoch (1980-01-06) to the first GLONASS four-year interval, 1996-01-01.
_GLO_N4_DAY0 = (datetime(1996, 1, 1, tzinfo=timezone.utc) - GPS_EPOCH).days  # 5839
# t_gps_s of J2000.0 as a UT instant: 2000-01-01T12:00:00 (JD 2451545.0).
_J2000_UTC_FROM_GPS_EPOCH_S = (datetime(2000, 1, 1, 12, tzinfo=timezone.utc) - GPS_EPOCH).total_seconds()


def gps_seconds_from_utc(dt: datetime) -> float:
    """GPS seconds since the GPS epoch for a UTC ``datetime``.

    t_gps_s = (dt - 1980-01-06T00:00Z) + GPS_UTC_LEAP_S.  A naive ``dt`` is taken as
    UTC; an aware one is converted to UTC first.  Resolution is 1 us.
    """
    if not isinstance(dt, datetime):
        raise ValueError(f"dt must be a datetime.datetime, got {type(dt).__name__}")
    dt = dt.replace(tzinfo=timezone.utc) if dt.tzinfo is None else dt.astimezone(timezone.utc)
    return (dt - GPS_EPOCH).total_seconds() + GPS_UTC_LEAP_S


def utc_from_gps_seconds(t_gps_s: float) -> datetime:
    """Aware UTC ``datetime`` for scalar GPS seconds (inverse of gps_seconds_from_utc).

    Rounded to the microsecond.
    """
    t = np.asarray(t_gps_s, dtype=float)
    if t.ndim != 0 or not np.isfinite(t):
        raise ValueError(f"t_gps_s must be a finite scalar, got {t_gps_s!r}")
    return GPS_EPOCH + timedelta(seconds=float(t) - GPS_UTC_LEAP_S)


def gps_week_tow(t_gps_s):
    """Full (not mod-1024) GPS week number and time of week.

    week = floor(t / 604800) (int64), tow_s = t - 604800 week in [0, 604800) s.
    """
    t = np.asarray(t_gps_s, dtype=float)
    week = np.floor(t / SECONDS_PER_WEEK)
    tow_s = t - week * SECONDS_PER_WEEK
    return week.astype(np.int64)[()], tow_s[()]


def gps_seconds_from_week_tow(week, tow_s):
    """GPS seconds from a full week number and time of week: t = 604800 week + tow_s."""
    return (np.asarray(week, dtype=float) * SECONDS_PER_WEEK + np.asarray(tow_s, dtype=float))[()]


def glonass_from_gps(t_gps_s):
    """GLONASS time (N4, NT, tod_s) for GPS seconds.

    t_glo = t_gps_s - GPS_UTC_LEAP_S + 3 h is GLONASS time counted from 1980-01-06T00:00.
    With d = floor(t_glo / 86400) - 5839 the day since 1996-01-01 (GLONASS):
    N4 = floor(d / 1461) + 1, NT = d mod 1461 + 1, tod_s = t_glo - 86400 floor(t_glo / 86400).
    (Every fourth year is taken as leap, as the ICD does; fine until 2100.)
    Raises ValueError before 1996-01-01T00:00 GLONASS (N4 would be < 1).
    """
    t = np.asarray(t_gps_s, dtype=float)
    if not np.all(np.isfinite(t)):
        raise ValueError("t_gps_s must be finite")
    t_glo = t - GPS_UTC_LEAP_S + GLONASS_UTC_OFFSET_S
    day = np.floor(t_glo / SECONDS_PER_DAY)
    tod_s = t_glo - day * SECONDS_PER_DAY
    d = day.astype(np.int64) - _GLO_N4_DAY0
    if np.any(d < 0):
        raise ValueError("t_gps_s precedes the GLONASS N4 count (1996-01-01 GLONASS time)")
    n4, nt0 = np.divmod(d, DAYS_PER_FOUR_YEARS)
    return (n4 + 1)[()], (nt0 + 1)[()], tod_s[()]


def gps_from_glonass(n4, nt, tod_s):
    """GPS seconds from GLONASS (N4, NT, tod_s); inverse of glonass_from_gps.

    t_gps_s = 86400 (1461 (N4 - 1) + NT - 1 + 5839) + tod_s - 3 h + GPS_UTC_LEAP_S.
    Requires N4 >= 1 and 1 <= NT <= 1461.
    """
    n4, nt = np.asarray(n4), np.asarray(nt)
    if np.any(n4 < 1):
        raise ValueError(f"n4 must be >= 1, got {n4}")
    if np.any((nt < 1) | (nt > DAYS_PER_FOUR_YEARS)):
        raise ValueError(f"nt must be in 1..{DAYS_PER_FOUR_YEARS}, got {nt}")
    days = DAYS_PER_FOUR_YEARS * (n4 - 1) + (nt - 1) + _GLO_N4_DAY0
    return (days * SECONDS_PER_DAY + np.asarray(tod_s, dtype=float)
            - GLONASS_UTC_OFFSET_S + GPS_UTC_LEAP_S)[()]


def gmst_rad(t_gps_s, dut1_s=0.0):
    """Greenwich mean sidereal angle, IAU 1982 (Aoki et al. 1982), rad in [0, 2 pi).

    With D = JD(UT1) - 2451545.0 and T = D / 36525 (UT1 = t_gps_s - GPS_UTC_LEAP_S + dut1_s):
    GMST_deg = 280.46061837 + 360.98564736629 D + 0.000387933 T^2 - T^3 / 38710000.
    ``dut1_s`` = UT1 - UTC (|.| < 0.9 s); leaving it 0 costs up to 6.6e-5 rad.
    The day count is split into whole days and a fraction to keep ~1e-12 rad rounding.
    """
    s = np.asarray(t_gps_s, dtype=float) - GPS_UTC_LEAP_S + np.asarray(dut1_s, dtype=float) \
        - _J2000_UTC_FROM_GPS_EPOCH_S
    d_int = np.floor(s / SECONDS_PER_DAY)
    d_frac = (s - d_int * SECONDS_PER_DAY) / SECONDS_PER_DAY
    t = (d_int + d_frac) / 36525.0
    # 360.98564736629 D = 360 D + 0.98564736629 D; 360 * d_int is a whole number of turns.
    deg = 280.46061837 + 360.0 * d_frac + 0.98564736629 * (d_int + d_frac) \
        + 0.000387933 * t**2 - t**3 / 38_710_000.0
    return np.radians(np.mod(deg, 360.0))[()]
