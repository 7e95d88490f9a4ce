"""Saastamoinen's tropospheric delay with a standard atmosphere (J. Saastamoinen 1972, "Atmospheric
correction for the troposphere and stratosphere in radio ranging of satellites"; the form and the
standard atmosphere RTKLIB's tropmodel uses): the slant delay in metres of one line of sight.

Standard atmosphere: 1013.25 hPa at sea level scaled with height (exponent 5.2568), 15 C with a
lapse rate of 6.5 K/km, relative humidity 0.7 unless given. Zenith hydrostatic part
0.0022768 p / (1 - 0.00266 cos 2 lat - 0.00028 h_km), mapped by 1 / cos z (no separate mapping
function: RTKLIB's choice, a few cm too small below 15 deg).

Pure numpy; latitude and elevation in radians, height in metres above the ellipsoid (heights
below 0 are taken as 0).
"""
from __future__ import annotations

import numpy as np

__all__ = ["saastamoinen_delay_m", "STANDARD_HUMIDITY"]

STANDARD_HUMIDITY = 0.7


def saastamoinen_delay_m(lat_rad, h_m, el_rad, humidity: float = STANDARD_HUMIDITY):
    """Slant tropospheric delay (m) at elevation el_rad from a receiver at lat_rad, h_m."""
    h = np.maximum(np.asarray(h_m, float), 0.0)
    p_hpa = 1013.25 * (1.0 - 2.2557e-5 * h) ** 5.2568
    t_k = 15.0 - 6.5e-3 * h + 273.16
    e_hpa = 6.108 * humidity * np.exp((17.15 * t_k - 4684.0) / (t_k - 38.45))
    cos_z = np.sin(np.asarray(el_rad, float))
    dry = 0.0022768 * p_hpa / (1.0 - 0.00266 * np.cos(2.0 * np.asarray(lat_rad, float)) - 0.00028 * h / 1e3)
    wet = 0.002277 * (1255.0 / t_k + 0.05) * e_hpa
    return (dry + wet) / cos_z
