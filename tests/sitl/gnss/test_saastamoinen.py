"""sitl.gnss.saastamoinen against the closed form of Saastamoinen's zenith hydrostatic delay
(0.0022768 m/hPa x pressure / f(lat, h); Davis et al. 1985's constant) and its 1/cos z mapping."""
from __future__ import annotations

import math

import numpy as np
import pytest

from sitl.gnss.saastamoinen import saastamoinen_delay_m


def test_dry_zenith_at_sea_level_45_degrees_is_the_closed_form():
    # f(45 deg, 0 m) = 1 exactly, p = 1013.25 hPa: 2.3069 m
    got = saastamoinen_delay_m(math.radians(45.0), 0.0, math.pi / 2, humidity=0.0)
    assert got == pytest.approx(0.0022768 * 1013.25, rel=1e-12)
    assert got == pytest.approx(2.3069, abs=1e-4)


def test_mapping_is_one_over_sin_elevation_and_height_lowers_the_delay():
    lat = math.radians(35.0)
    z = saastamoinen_delay_m(lat, 70.0, math.pi / 2)
    np.testing.assert_allclose(saastamoinen_delay_m(lat, 70.0, np.radians([30.0, 10.0])),
                               z / np.sin(np.radians([30.0, 10.0])), rtol=1e-12)
    assert 2.3 < z < 2.5  # standard atmosphere with 70 % humidity: ~0.1 m of wet delay
    assert saastamoinen_delay_m(lat, 2000.0, math.pi / 2) < 0.8 * z
    assert saastamoinen_delay_m(lat, -50.0, math.pi / 2) == saastamoinen_delay_m(lat, 0.0, math.pi / 2)
