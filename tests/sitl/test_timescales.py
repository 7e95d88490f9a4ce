"""Tests of sitl.timescales: GPS week/TOW, UTC, GLONASS N4/NT/tod, GMST."""
import math
from datetime import date, datetime, timedelta, timezone

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sitl import timescales as ts
from sitl.constants import OMEGA_E_GPS_RAD_S

UTC = timezone.utc
det = settings(derandomize=True, deadline=None, database=None, max_examples=300)
# The module's UTC = GPS - 18 s convention is historical UTC from 2017-01-01 on.
DATES = st.datetimes(min_value=datetime(2017, 1, 1), max_value=datetime(2099, 12, 31))


# ---------------------------------------------------------------- GPS / UTC
def test_gps_week_tow_known_dates():
    # GPS week 1930 began 2017-01-01 00:00:00 GPS = 2016-12-31 23:59:42 UTC (13510 days =
    # 1930 weeks after 1980-01-06), so 2017-01-01 00:00:00 UTC is TOW 18 s.
    t = ts.gps_seconds_from_utc(datetime(2017, 1, 1))
    assert t == 1930 * 604800 + 18.0
    week, tow = ts.gps_week_tow(t)
    assert week == 1930 and tow == 18.0
    # Second 10-bit week rollover: week 2048 began 2019-04-06 23:59:42 UTC (published).
    assert ts.utc_from_gps_seconds(2048 * 604800.0) == datetime(2019, 4, 6, 23, 59, 42, tzinfo=UTC)


def test_aware_and_naive_datetimes():
    moscow = timezone(timedelta(hours=3))
    t = ts.gps_seconds_from_utc(datetime(2024, 5, 1, 12, 0, 0, 250_000))
    assert ts.gps_seconds_from_utc(datetime(2024, 5, 1, 15, 0, 0, 250_000, tzinfo=moscow)) == t
    assert ts.utc_from_gps_seconds(t) == datetime(2024, 5, 1, 12, 0, 0, 250_000, tzinfo=UTC)


@det
@given(DATES)
def test_utc_round_trip(dt):
    back = ts.utc_from_gps_seconds(ts.gps_seconds_from_utc(dt))
    assert abs((back - dt.replace(tzinfo=UTC)).total_seconds()) <= 1e-6


@det
@given(st.floats(0.0, 4.0e9))
def test_week_tow_round_trip(t):
    week, tow = ts.gps_week_tow(t)
    assert 0.0 <= tow < 604800.0
    assert abs(ts.gps_seconds_from_week_tow(week, tow) - t) <= 1e-6


def test_week_tow_vectorised():
    t = np.array([[0.0, 604799.5], [604800.0, 1.5e9]])
    week, tow = ts.gps_week_tow(t)
    np.testing.assert_array_equal(week, [[0, 0], [1, 2480]])
    np.testing.assert_allclose(tow, [[0.0, 604799.5], [0.0, 1.5e9 - 2480 * 604800]])
    assert week.dtype == np.int64
    np.testing.assert_allclose(ts.gps_seconds_from_week_tow(week, tow), t)


@pytest.mark.parametrize("bad", ["2017-01-01", date(2017, 1, 1), 1.0e9])
def test_gps_seconds_from_utc_rejects_non_datetime(bad):
    with pytest.raises(ValueError, match="dt"):
        ts.gps_seconds_from_utc(bad)


def test_utc_from_gps_seconds_rejects_arrays():
    with pytest.raises(ValueError, match="t_gps_s"):
        ts.utc_from_gps_seconds(np.array([1.0, 2.0]))


# ---------------------------------------------------------------- GLONASS
@pytest.mark.parametrize("utc, want", [
    # 2017-01-01 03:00 Moscow: 4-year interval 2016-2019 is N4 = 6; day 366 + 1 = 367.
    (datetime(2017, 1, 1, 0, 0, 0), (6, 367, 10800.0)),
    # 2020-03-01 21:00 UTC = 2020-03-02 00:00 GLONASS: N4 = 7, NT = 31 + 29 + 2 = 62.
    (datetime(2020, 3, 1, 21, 0, 0), (7, 62, 0.0)),
    # The N4 boundary: 2020-01-01 00:00 GLONASS and one second before it.
    (datetime(2019, 12, 31, 21, 0, 0), (7, 1, 0.0)),
    (datetime(2019, 12, 31, 20, 59, 59), (6, 1461, 86399.0)),
])
def test_glonass_known_dates(utc, want):
    t = ts.gps_seconds_from_utc(utc)
    n4, nt, tod = ts.glonass_from_gps(t)
    assert (int(n4), int(nt), float(tod)) == want
    assert ts.gps_from_glonass(*want) == t


@det
@given(st.floats(ts.gps_seconds_from_utc(datetime(1996, 1, 1)), 4.0e9))
def test_glonass_round_trip(t):
    n4, nt, tod = ts.glonass_from_gps(t)
    assert n4 >= 1 and 1 <= nt <= 1461 and 0.0 <= tod < 86400.0
    assert abs(ts.gps_from_glonass(n4, nt, tod) - t) <= 1e-6


def test_glonass_vectorised():
    t = ts.gps_seconds_from_utc(datetime(2017, 1, 1)) + np.arange(6).reshape(2, 3) * 43200.0
    n4, nt, tod = ts.glonass_from_gps(t)
    assert n4.shape == nt.shape == tod.shape == (2, 3)
    np.testing.assert_array_equal(nt, [[367, 367, 368], [368, 369, 369]])
    np.testing.assert_allclose(ts.gps_from_glonass(n4, nt, tod), t)


@pytest.mark.parametrize("args, name", [((0, 1, 0.0), "n4"), ((1, 0, 0.0), "nt"), ((1, 1462, 0.0), "nt")])
def test_glonass_bad_input(args, name):
    with pytest.raises(ValueError, match=name):
        ts.gps_from_glonass(*args)


def test_glonass_before_1996_rejected():
    with pytest.raises(ValueError, match="t_gps_s"):
        ts.glonass_from_gps(ts.gps_seconds_from_utc(datetime(1995, 12, 31, 20, 0)))


# ---------------------------------------------------------------- GMST
def test_gmst_at_j2000():
    # IAU 1982: GMST = 280.46061837 deg at JD 2451545.0 = 2000-01-01 12:00 UT1.
    t = ts.gps_seconds_from_utc(datetime(2000, 1, 1, 12))
    assert abs(ts.gmst_rad(t) - math.radians(280.46061837)) < 1e-12


def test_gmst_vallado_example():
    # Vallado, Fundamentals of Astrodynamics, Example 3-5: 1992-08-20 12:14 UT1 -> ~152.578788 deg.
    t = ts.gps_seconds_from_utc(datetime(1992, 8, 20, 12, 14))
    assert abs(ts.gmst_rad(t) - math.radians(152.578788)) < 1e-6


def _gmst_almanac_rad(dt_ut1):
    """Independent form of IAU 1982 (Astronomical Almanac): GMST at 0h UT1 plus sidereal day fraction.

    GMST(0h) = 24110.54841 + 8640184.812866 Tu + 0.093104 Tu^2 - 6.2e-6 Tu^3 s, Tu in Julian
    centuries of UT1 from J2000 to that 0h; then + 1.00273790935 * UT1 seconds of day.
    """
    midnight = datetime(dt_ut1.year, dt_ut1.month, dt_ut1.day, tzinfo=UTC)
    tu = (midnight - datetime(2000, 1, 1, 12, tzinfo=UTC)).total_seconds() / 86400.0 / 36525.0
    s = 24110.54841 + 8640184.812866 * tu + 0.093104 * tu**2 - 6.2e-6 * tu**3
    s += 1.00273790935 * (dt_ut1 - midnight).total_seconds()
    return (s % 86400.0) / 86400.0 * 2 * math.pi


@det
@given(st.datetimes(min_value=datetime(1990, 1, 1), max_value=datetime(2060, 1, 1)))
def test_gmst_matches_almanac_form(dt):
    dt = dt.replace(tzinfo=UTC)
    got = ts.gmst_rad(ts.gps_seconds_from_utc(dt))
    diff = (got - _gmst_almanac_rad(dt) + math.pi) % (2 * math.pi) - math.pi
    assert 0.0 <= got < 2 * math.pi and abs(diff) < 1e-8


def test_gmst_rate_and_dut1():
    t = ts.gps_seconds_from_utc(datetime(2024, 3, 1)) + np.array([0.0, 1000.0])
    g0, g1 = ts.gmst_rad(t)
    assert abs((g1 - g0) / 1000.0 - OMEGA_E_GPS_RAD_S) < 1e-11  # sidereal rate
    assert abs(ts.gmst_rad(t[0], dut1_s=0.5) - g0 - 0.5 * OMEGA_E_GPS_RAD_S) < 1e-10
    assert ts.gmst_rad(np.zeros((3, 4))).shape == (3, 4)
