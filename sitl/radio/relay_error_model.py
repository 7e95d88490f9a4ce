"""The relayed pseudoranges' error formulas, written once: the ionosphere's thin-shell obliquity,
the troposphere's mapping and pressure scaling, the airborne multipath std (RTCA DO-229 app. J;
Misra and Enge ch. 5; the values and sources: sitl.radio.relay.RelayErrorBudget).

Each function is plain arithmetic on numpy ufuncs (no calls between them), so the same source serves the world's relay
(arrays, sitl.radio.relay) and, compiled by numba, the sonde tracker's per-satellite loop (scalars,
ground_station.sonde.relay_errors)."""
from __future__ import annotations

import numpy as np

from sitl.atmosphere_std import P0_PA, us76

__all__ = ["LN_P_TABLE", "P_TABLE_H_M", "iono_obliquity", "iono_sigma_m", "multipath_sigma_m", "pressure_ratio",
           "tropo_mapping", "tropo_sigma_m"]

P_TABLE_H_M = np.arange(-500.0, 86_000.0 + 1.0, 50.0)
LN_P_TABLE = np.log(us76(P_TABLE_H_M).pressure_pa / P0_PA)


def pressure_ratio(h_m):
    """p(h) / p0 of the US-76 atmosphere, tabulated every 50 m and interpolated in ln p (relative
    error < 1e-5; ~100x faster than sitl.atmosphere_std.us76 on a few values)."""
    return np.exp(np.interp(h_m, P_TABLE_H_M, LN_P_TABLE))


def iono_sigma_m(iono_zenith_m, shell_ratio, el_rad):
    """The ionosphere's residual std at elevation el: the zenith value times the thin-shell
    obliquity F(el) = 1/sqrt(1 - (R cos el / (R + h_I))^2), shell_ratio = R / (R + h_I);
    elevations below 0 count as 0."""
    c = shell_ratio * np.cos(np.maximum(el_rad, 0.0))
    return iono_zenith_m * (1.0 / np.sqrt(1.0 - c * c))


def tropo_sigma_m(tropo_zenith_m, p_ratio, el_rad):
    """The troposphere's residual std: the zenith value times p(h)/p0 (the air above the sonde)
    times the mapping m(el) = 1.001 / sqrt(0.002001 + sin^2 el) (RTCA DO-229); elevations below 0
    count as 0."""
    s = np.sin(np.maximum(el_rad, 0.0))
    return tropo_zenith_m * p_ratio * (1.001 / np.sqrt(0.002001 + s * s))


def iono_obliquity(shell_ratio, el_rad):
    """The obliquity factor F(el) alone (iono_sigma_m of a unit zenith value: the same numbers)."""
    return iono_sigma_m(1.0, shell_ratio, el_rad)


def tropo_mapping(el_rad):
    """The mapping m(el) alone (tropo_sigma_m of a unit zenith value at p0: the same numbers)."""
    return tropo_sigma_m(1.0, 1.0, el_rad)


def multipath_sigma_m(a_m, b_m, el0_deg, el_rad):
    """Airborne multipath std: a + b e^{-el / el0} (el in degrees; below 0 counts as 0)."""
    return a_m + b_m * np.exp(-np.degrees(np.maximum(el_rad, 0.0)) / el0_deg)
