"""Broadcast ionosphere model of GPS (Klobuchar, IS-GPS-200 20.3.3.5.2.5) from the nav
header's alpha/beta: the L1 group delay in metres of one line of sight.

Pure numpy; angles in radians at the interface (the ICD works in semicircles inside).
"""
from __future__ import annotations

import numpy as np

from sitl.constants import C_M_S

__all__ = ["klobuchar_delay_m"]


def klobuchar_delay_m(alpha, beta, lat_rad, lon_rad, az_rad, el_rad, t_gps_s):
    """Slant L1 ionospheric group delay (m) of the ICD's broadcast model; broadcasting arrays."""
    a = np.asarray(alpha, dtype=float)
    b = np.asarray(beta, dtype=float)
    phi_u = np.asarray(lat_rad, dtype=float) / np.pi
    lam_u = np.asarray(lon_rad, dtype=float) / np.pi
    E = np.asarray(el_rad, dtype=float) / np.pi
    A = np.asarray(az_rad, dtype=float)
    psi = 0.0137 / (E + 0.11) - 0.022
    phi_i = np.clip(phi_u + psi * np.cos(A), -0.416, 0.416)
    lam_i = lam_u + psi * np.sin(A) / np.cos(phi_i * np.pi)
    phi_m = phi_i + 0.064 * np.cos((lam_i - 1.617) * np.pi)
    t = np.mod(43200.0 * lam_i + np.asarray(t_gps_s, dtype=float), 86400.0)
    F = 1.0 + 16.0 * (0.53 - E) ** 3
    amp = np.maximum(a[0] + phi_m * (a[1] + phi_m * (a[2] + phi_m * a[3])), 0.0)
    per = np.maximum(b[0] + phi_m * (b[1] + phi_m * (b[2] + phi_m * b[3])), 72000.0)
    x = 2.0 * np.pi * (t - 50400.0) / per
    delay_s = np.where(np.abs(x) < 1.57, F * (5e-9 + amp * (1.0 - x * x / 2.0 + x**4 / 24.0)), F * 5e-9)
    return C_M_S * delay_s
