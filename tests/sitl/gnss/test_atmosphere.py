"""Thin-shell ionosphere and 1/sin troposphere (seed 000, eqs. 9 and 11)."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from sitl.constants import F_GPS_L1_HZ, glonass_l1_hz
from sitl.gnss.atmosphere import (
    EARTH_RADIUS_M,
    IONO_SHELL_HEIGHT_M,
    iono_mapping,
    iono_mapping_del,
    iono_slant_delay_m,
    iono_zenith_from_tec,
    tropo_mapping,
    tropo_mapping_del,
    tropo_slant_delay_m,
)

R, H = EARTH_RADIUS_M, IONO_SHELL_HEIGHT_M


def test_mappings_are_one_at_zenith():
    assert iono_mapping(np.pi / 2) == pytest.approx(1.0, abs=1e-15)
    assert tropo_mapping(np.pi / 2) == pytest.approx(1.0, abs=1e-15)
    assert iono_slant_delay_m(15.0, np.pi / 2, F_GPS_L1_HZ) == pytest.approx(15.0, rel=1e-14)
    assert tropo_slant_delay_m(2.5, np.pi / 2) == pytest.approx(2.5, rel=1e-14)


def test_iono_mapping_at_horizon_and_via_pierce_point_zenith_angle():
    # at el = 0 the ray grazes the Earth: m = (R+h) / sqrt(h (2R+h))
    assert iono_mapping(0.0) == pytest.approx((R + H) / np.sqrt(H * (2 * R + H)), rel=1e-13)
    assert iono_mapping(0.0) == pytest.approx(2.8502, abs=1e-4)
    # independent geometry: zenith angle z' at the pierce point, sin z' = R cos el / (R+h)
    el = np.deg2rad(np.array([5.0, 10.0, 30.0, 60.0]))
    z_ipp = np.arcsin(R * np.cos(el) / (R + H))
    np.testing.assert_allclose(iono_mapping(el), 1.0 / np.cos(z_ipp), rtol=1e-13)
    # monotonically decreasing with elevation
    grid = np.linspace(0.0, np.pi / 2, 200)
    assert np.all(np.diff(iono_mapping(grid)) < 0)


def test_tropo_mapping_analytic_values():
    np.testing.assert_allclose(tropo_mapping(np.deg2rad([30.0, 90.0])), [2.0, 1.0], rtol=1e-13)
    assert tropo_slant_delay_m(2.5, np.deg2rad(5.0)) == pytest.approx(2.5 / np.sin(np.deg2rad(5.0)))


@settings(derandomize=True, max_examples=200, deadline=None)
@given(st.floats(min_value=np.deg2rad(2.0), max_value=np.deg2rad(89.0)))
def test_mapping_derivatives_match_central_differences(el):
    h = 1e-6
    fd_i = (iono_mapping(el + h) - iono_mapping(el - h)) / (2 * h)
    fd_t = (tropo_mapping(el + h) - tropo_mapping(el - h)) / (2 * h)
    assert iono_mapping_del(el) == pytest.approx(fd_i, rel=1e-6, abs=1e-9)
    assert tropo_mapping_del(el) == pytest.approx(fd_t, rel=1e-6, abs=1e-9)


def test_derivatives_vectorised_and_signs():
    el = np.deg2rad(np.linspace(5, 85, 17))
    assert iono_mapping_del(el).shape == el.shape
    assert np.all(iono_mapping_del(el) < 0) and np.all(tropo_mapping_del(el) < 0)
    assert iono_mapping_del(np.pi / 2) == pytest.approx(0.0, abs=1e-15)


def test_frequency_scaling_glonass_extreme_channels():
    el = np.deg2rad(40.0)
    f_lo, f_hi = glonass_l1_hz(-7), glonass_l1_hz(+6)
    i_lo = iono_slant_delay_m(15.0, el, f_lo)
    i_hi = iono_slant_delay_m(15.0, el, f_hi)
    # lower frequency, larger delay: I ∝ 1/f²
    assert i_lo / i_hi == pytest.approx((f_hi / f_lo) ** 2, rel=1e-14)
    assert i_lo > i_hi
    # zenith delay given at GPS L1 scales to a GLONASS carrier by (f_L1/f)²
    assert iono_slant_delay_m(15.0, np.pi / 2, f_lo) == pytest.approx(15.0 * (F_GPS_L1_HZ / f_lo) ** 2)
    # broadcasting over a (trials, sats) elevation array and an (S,) carrier axis
    k = np.arange(-7, 7)
    out = iono_slant_delay_m(15.0, np.full((3, k.size), el), glonass_l1_hz(k))
    assert out.shape == (3, k.size) and np.all(np.diff(out[0]) < 0)


def test_iono_zenith_from_tec():
    # 1 TECU = 1e16 el/m² is about 0.162 m of group delay at GPS L1
    assert iono_zenith_from_tec(1e16, F_GPS_L1_HZ) == pytest.approx(40.3e16 / F_GPS_L1_HZ**2, rel=1e-14)
    assert iono_zenith_from_tec(1e16, F_GPS_L1_HZ) == pytest.approx(0.1624, abs=1e-4)
    # consistency: the zenith delay at f, referred to f, maps back to itself
    tec = 9.24e17  # ~15 m at L1
    ig = iono_zenith_from_tec(tec)
    f = glonass_l1_hz(2)
    assert iono_slant_delay_m(ig, np.pi / 2, f) == pytest.approx(iono_zenith_from_tec(tec, f), rel=1e-13)
