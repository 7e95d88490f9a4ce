"""The guidance laws' local geometry: angles wrapped to [-pi, pi), the ellipsoid's radii of
curvature, a point's flat east / north offset, the heading of the ECEF eta axis."""
from __future__ import annotations

import numpy as np

from sitl.constants import Ellipsoid


def wrap_pi(a):
    """Angle(s) wrapped to [-pi, pi)."""
    return np.mod(np.asarray(a, dtype=float) + np.pi, 2.0 * np.pi) - np.pi


def _radii(lat, ell: Ellipsoid):
    """Meridian M and prime-vertical N radii of curvature at geodetic latitude lat."""
    w2 = 1.0 - ell.e2 * np.sin(lat) ** 2
    n = ell.a_m / np.sqrt(w2)
    return n * (1.0 - ell.e2) / w2, n


def eta_axis_heading_rad(lat_rad, lon_rad):
    """Heading (clockwise from north) of the horizontal projection of the ECEF eta (y) axis.

    east . y = cos(lon),  north . y = -sin(lat) sin(lon)  ->  atan2(cos lon, -sin lat sin lon).
    The seed's velocity laws are dominated by the eta component; this is its direction.
    """
    lat, lon = np.asarray(lat_rad, float), np.asarray(lon_rad, float)
    return np.mod(np.arctan2(np.cos(lon), -np.sin(lat) * np.sin(lon)), 2.0 * np.pi)


def _center_offset(lat, lon, h, lat_c, lon_c, ell):
    """(d_e, d_n): a point's offset from (lat, lon, h), local flat east / north metres (as
    WaypointMission._offset and the compiled _offset_nb)."""
    m, nn = _radii(lat, ell)
    return wrap_pi(lon_c - lon) * (nn + h) * np.cos(lat), (lat_c - lat) * (m + h)
