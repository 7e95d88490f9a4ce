"""U.S. Standard Atmosphere 1976 (NOAA-S/T 76-1562), lower 86 km: temperature, pressure, density.

The standard defines seven layers of linear molecular-scale temperature T_M in
*geopotential* altitude H (km'):

    H_b = 0, 11, 20, 32, 47, 51, 71, 84.8520 km'
    L_b = -6.5, 0, +1.0, +2.8, 0, -2.8, -2.0 K/km'
    T_M0 = 288.15 K, P0 = 101 325 Pa

with the geometric altitude Z converted by H = r0 Z / (r0 + Z), r0 = 6 356 766 m, and
the hydrostatic equation integrated exactly layer by layer:

    L != 0:  P = P_b [T_M,b / (T_M,b + L (H - H_b))]^(g0' M0 / (R* L))
    L == 0:  P = P_b exp(-g0' M0 (H - H_b) / (R* T_M,b))
    rho = P M0 / (R* T_M)

g0' = 9.80665 m^2/(s^2 m'), M0 = 28.9644 kg/kmol, R* = 8.31432 N m/(mol K) (the 1976
value, not CODATA: the published tables use it).  ``rho = P M0 / (R* T_M)`` is exact
in the standard at every altitude below 86 km (T_M absorbs the change of molecular
weight); the kinetic temperature T = T_M (M / M0) differs from T_M only above 80 km
(M/M0 >= 0.999579), a detail this module does not need: it returns T_M, which is the
kinetic temperature below 80 km.

Altitudes are geometric (metres above mean sea level; the sonde model passes its
ellipsoidal height, the ~tens-of-metres geoid separation is immaterial here).  Valid
from -5 km to 86 km geometric (the standard's tabulated range); outside it a
ValueError is raised.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["P0_PA", "R0_M", "RHO0_KG_M3", "T0_K", "US76", "Z_MAX_M", "Z_MIN_M", "us76", "us76_density"]

R_STAR = 8.31432  # J/(mol K), the 1976 standard's gas constant
M0_KG_MOL = 28.9644e-3
G0_M_S2 = 9.80665
R0_M = 6_356_766.0  # effective Earth radius for the geopotential conversion
T0_K = 288.15
P0_PA = 101_325.0
RHO0_KG_M3 = P0_PA * M0_KG_MOL / (R_STAR * T0_K)  # 1.2250 kg/m^3
Z_MIN_M = -5_000.0
Z_MAX_M = 86_000.0

_GMR = G0_M_S2 * M0_KG_MOL / R_STAR  # K/m
_H_B = np.array([0.0, 11_000.0, 20_000.0, 32_000.0, 47_000.0, 51_000.0, 71_000.0])
_L_B = np.array([-6.5, 0.0, 1.0, 2.8, 0.0, -2.8, -2.0]) * 1e-3  # K/m'


def _layer_bases():
    t_b, p_b = [T0_K], [P0_PA]
    for i in range(len(_H_B) - 1):
        dh, lb, tb, pb = _H_B[i + 1] - _H_B[i], _L_B[i], t_b[-1], p_b[-1]
        t_next = tb + lb * dh
        p_next = pb * np.exp(-_GMR * dh / tb) if lb == 0.0 else pb * (tb / t_next) ** (_GMR / lb)
        t_b.append(t_next)
        p_b.append(p_next)
    return np.array(t_b), np.array(p_b)


_T_B, _P_B = _layer_bases()


class US76(NamedTuple):
    """Standard-atmosphere state at geometric altitudes z (arrays of z's shape)."""

    temperature_k: np.ndarray  # molecular-scale temperature T_M (= kinetic below 80 km)
    pressure_pa: np.ndarray
    density_kg_m3: np.ndarray


def _geometric(z_m) -> np.ndarray:
    try:
        z = np.asarray(z_m, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"z_m: cannot convert {z_m!r} to a float array") from None
    if not np.all(np.isfinite(z)) or np.any(z < Z_MIN_M) or np.any(z > Z_MAX_M):
        raise ValueError(f"z_m must be finite and within [{Z_MIN_M:.0f}, {Z_MAX_M:.0f}] m (US 1976 lower atmosphere)")
    return z


def us76(z_m) -> US76:
    """Temperature (K), pressure (Pa) and density (kg/m^3) at geometric altitude z_m (m)."""
    z = _geometric(z_m)
    h = R0_M * z / (R0_M + z)
    i = np.clip(np.searchsorted(_H_B, h, side="right") - 1, 0, len(_H_B) - 1)
    hb, lb, tb, pb = _H_B[i], _L_B[i], _T_B[i], _P_B[i]
    t = tb + lb * (h - hb)
    iso = lb == 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        p_grad = pb * (tb / t) ** (_GMR / np.where(iso, 1.0, lb))
    p = np.where(iso, pb * np.exp(-_GMR * (h - hb) / tb), p_grad)
    rho = p * M0_KG_MOL / (R_STAR * t)
    return US76(t[()], p[()], rho[()])


def us76_density(z_m) -> np.ndarray:
    """Density (kg/m^3) at geometric altitude z_m (m), US Standard Atmosphere 1976."""
    return us76(z_m).density_kg_m3
