"""Atmospheric delays of a single-frequency GNSS signal: thin-shell ionosphere, troposphere.

Seed 000 ("Atmosphere"):

    ionosphere (eq. 9)   I_j = I_g * (f_ref / f_j)^2 * m_I(el_j)
                         m_I(el) = 1 / sqrt(1 - (R_E cos el / (R_E + h))^2),  h = 432.5 km
                         I_g = 40.3 * N_S / f_ref^2          (zenith group delay, metres)
    troposphere (eq. 11) U_j = U_g * m_U(el_j),   m_U(el) = 1 / sin el,   U_g ~ 2.5 m

Sign convention (seed 000, eqs. 18/19 and 29/35): the ionosphere is dispersive, so the
code (group) delay is ``+I_j`` on the pseudorange and the carrier phase is *advanced* by
the same amount, ``-I_j``. The troposphere is non-dispersive: ``+U_j`` on both.

All functions are pure, take scalars or arrays (broadcasting), angles in radians, SI units.
The mapping functions are singular at or below the horizon (``m_U`` at el = 0); callers
apply an elevation mask first.
"""
from __future__ import annotations

import numpy as np

from sitl.constants import F_GPS_L1_HZ

IONO_SHELL_HEIGHT_M = 432.5e3  # shell height holding 50 % of the vertical electron column
EARTH_RADIUS_M = 6371e3  # mean Earth radius of the thin-shell geometry
IONO_K_M3_S2 = 40.3  # I = 40.3 * TEC / f^2 (first-order group delay), m^3/s^2
TROPO_ZENITH_M = 2.5  # typical zenith tropospheric delay U_g, seed 000


def iono_mapping(el_rad, h_shell_m: float = IONO_SHELL_HEIGHT_M, r_earth_m: float = EARTH_RADIUS_M):
    """Thin-shell ionospheric obliquity factor (seed 000, eq. 9).

    m_I(el) = 1 / sqrt(1 - (R cos el / (R + h))^2)

    Equals 1 at the zenith and (R + h) / sqrt(h (2R + h)) (about 2.85 for h = 432.5 km)
    at the horizon. It is the secant of the zenith angle at the ionospheric pierce point.
    """
    el_rad = np.asarray(el_rad, dtype=float)
    s = r_earth_m * np.cos(el_rad) / (r_earth_m + h_shell_m)
    return 1.0 / np.sqrt(1.0 - s * s)


def iono_mapping_del(el_rad, h_shell_m: float = IONO_SHELL_HEIGHT_M, r_earth_m: float = EARTH_RADIUS_M):
    """Derivative of the thin-shell mapping with respect to elevation, 1/rad.

    With a = R / (R + h):  d m_I / d el = -a^2 cos(el) sin(el) * m_I(el)^3

    Negative above the horizon: the slant delay shrinks as the satellite rises. Needed by
    the filters' H, whose rows depend on the receiver position through the elevation.
    """
    el_rad = np.asarray(el_rad, dtype=float)
    a = r_earth_m / (r_earth_m + h_shell_m)
    m = iono_mapping(el_rad, h_shell_m, r_earth_m)
    return -a * a * np.cos(el_rad) * np.sin(el_rad) * m**3


def iono_frequency_factor(f_hz, f_ref_hz: float = F_GPS_L1_HZ):
    """(f_ref / f)^2: converts a group delay at f_ref to one at f (first-order ionosphere)."""
    f_hz = np.asarray(f_hz, dtype=float)
    return (f_ref_hz / f_hz) ** 2


def iono_slant_delay_m(
    i_zenith_m,
    el_rad,
    f_hz,
    f_ref_hz: float = F_GPS_L1_HZ,
    h_shell_m: float = IONO_SHELL_HEIGHT_M,
    r_earth_m: float = EARTH_RADIUS_M,
):
    """Slant ionospheric group delay of a satellite, metres (seed 000, eq. 9).

    I_j = I_g * (f_ref / f_j)^2 * m_I(el_j)

    i_zenith_m: zenith delay I_g at the reference frequency f_ref_hz (GPS L1 by default).
    f_hz: carrier of the satellite (GLONASS FDMA: each channel has its own).
    Added to code (+I_j), subtracted from carrier phase (-I_j).
    """
    return (
        np.asarray(i_zenith_m, dtype=float)
        * iono_frequency_factor(f_hz, f_ref_hz)
        * iono_mapping(el_rad, h_shell_m, r_earth_m)
    )


def iono_zenith_from_tec(tec_el_m2, f_hz=F_GPS_L1_HZ):
    """Zenith group delay from vertical total electron content, metres.

    I_g = 40.3 * N_S / f^2,   N_S in electrons/m^2 (1 TECU = 1e16 el/m^2 gives
    about 0.162 m at GPS L1).
    """
    tec_el_m2 = np.asarray(tec_el_m2, dtype=float)
    f_hz = np.asarray(f_hz, dtype=float)
    return IONO_K_M3_S2 * tec_el_m2 / (f_hz * f_hz)


def tropo_mapping(el_rad):
    """Tropospheric mapping function m_U(el) = 1 / sin(el) (seed 000, eq. 11)."""
    return 1.0 / np.sin(np.asarray(el_rad, dtype=float))


def tropo_mapping_del(el_rad):
    """d m_U / d el = -cos(el) / sin(el)^2, 1/rad."""
    el_rad = np.asarray(el_rad, dtype=float)
    s = np.sin(el_rad)
    return -np.cos(el_rad) / (s * s)


def tropo_slant_delay_m(u_zenith_m, el_rad):
    """Slant tropospheric delay U_j = U_g / sin(el_j), metres (seed 000, eq. 11).

    Non-dispersive: the same on code and carrier. Typical U_g is TROPO_ZENITH_M = 2.5 m.
    """
    return np.asarray(u_zenith_m, dtype=float) * tropo_mapping(el_rad)
