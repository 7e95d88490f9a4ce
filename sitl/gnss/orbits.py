"""GNSS satellite orbits: almanac-like Keplerian constellations and their propagation.

A :class:`Constellation` holds one row of orbital elements per satellite, in the
convention of the GPS broadcast ephemeris / almanac (IS-GPS-200, Table 20-III/IV):

* ``Omega0_rad`` is the ICD's Omega_0: the longitude of the ascending node at the
  *weekly epoch* (the start of the GPS week containing ``toa_gps_s``), i.e. YUMA's
  "Right Ascen at Week" and RINEX's OMEGA0 -- not an inertial right ascension.
  The Earth-fixed longitude of the node at time t is (IS-GPS-200 Table 20-IV)

      Omega_k(t) = Omega0 + (OmegaDot - omega_e) * t_k - omega_e * t_oa,

  with t_k = t - toa_gps_s (continuous seconds, no week wrap) and
  t_oa = toa_gps_s mod 604800 the time of applicability in its week.

The propagator is the ICD user algorithm (Table 20-IV): mean motion
n = sqrt(GM/a^3) + Delta_n, Kepler's equation M = E - e sin E solved by Newton,
true anomaly, argument of latitude, then the rotation into ECEF by Omega_k and
the inclination.  Almanacs and the built-in constellations carry no harmonic
corrections (Delta_n, IDOT, C_uc ... C_is are zero, the pure Keplerian orbit plus
the secular node drift OmegaDot); :func:`load_rinex_nav` fills them in from a
broadcast ephemeris.  Velocity is the analytic derivative of that position in the
rotating Earth-fixed frame (the ICD's Table 20-IV position differentiated term by
term, e.g. Remondi 2004, "Computing satellite velocity using the broadcast
ephemeris", GPS Solutions 8:181).

GM and the Earth rotation rate are per system: the GPS ICD values
(``GM_GPS_M3_S2``, ``OMEGA_E_GPS_RAD_S``) for GPS satellites and the PZ-90.11
values for GLONASS satellites (which are treated with the same Keplerian model;
real GLONASS broadcasts a numerically integrated state vector instead).

Times are GPS seconds since the GPS epoch (1980-01-06 00:00:00 GPS time).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

import numpy as np

from sitl.constants import (
    F_GPS_L1_HZ,
    GM_GPS_M3_S2,
    OMEGA_E_GPS_RAD_S,
    PZ90_11,
    glonass_l1_hz,
)

__all__ = [
    "Constellation",
    "sat_state_ecef",
    "gps_constellation",
    "glonass_constellation",
    "default_constellation",
    "load_yuma_almanac",
    "load_rinex_nav",
    "kepler_state_ecef",
    "DEFAULT_TOA_GPS_S",
    "SECONDS_PER_WEEK",
    "GPS_A_M",
    "GPS_I_RAD",
    "GLONASS_A_M",
    "GLONASS_I_RAD",
    "GLONASS_SLOT_K",
    "KEPLER_TOL_RAD",
]

SECONDS_PER_WEEK = 604_800.0

#: Default reference epoch of the built-in constellations: 2025-01-01 00:00:00 GPS
#: time = GPS week 2347, second of week 259200 (16432 days after 1980-01-06).
DEFAULT_TOA_GPS_S = 16_432 * 86_400.0

#: Newton iterations on Kepler's equation stop once the eccentric anomaly is known
#: to this accuracy.
KEPLER_TOL_RAD = 1e-13

GPS_A_M = 26_559_700.0
GPS_I_RAD = math.radians(55.0)
GLONASS_A_M = 25_510_000.0
GLONASS_I_RAD = math.radians(64.8)

# J2 of the Earth (WGS-84 EGM, C20 = -4.84165371736e-4 * sqrt(5)), used only to
# give the built-in constellations a realistic secular node regression.
_J2 = 1.08262982131e-3
_R_EARTH_M = 6_378_137.0

_GPS_PARAMS = (GM_GPS_M3_S2, OMEGA_E_GPS_RAD_S)
_GLO_PARAMS = (PZ90_11.gm_m3_s2, PZ90_11.omega_rad_s)
_SYSTEM_PARAMS = {"G": _GPS_PARAMS, "R": _GLO_PARAMS}

# Elements that are per-satellite float arrays, in field order.
_FLOAT_FIELDS = (
    "toa_gps_s", "a_m", "e", "i_rad", "Omega0_rad", "OmegaDot_rad_s", "omega_rad", "M0_rad",
)
_HARMONIC_FIELDS = (
    "delta_n_rad_s", "idot_rad_s", "cuc_rad", "cus_rad", "crc_m", "crs_m", "cic_rad", "cis_rad",
)


def _as_1d(name: str, value, dtype) -> np.ndarray:
    try:
        arr = np.array(value, dtype=dtype, ndmin=1)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: cannot convert to a 1-D {np.dtype(dtype).name} array ({exc})") from None
    if arr.ndim != 1:
        raise ValueError(f"{name}: expected a 1-D array, got shape {arr.shape}")
    return arr


@dataclass(frozen=True, eq=False)
class Constellation:
    """Per-satellite almanac-like Keplerian elements (S satellites, arrays of shape (S,)).

    Fields
    ------
    sat_id : str array, e.g. 'G01', 'R07'; the first letter must equal ``system``.
    system : 'G' (GPS) or 'R' (GLONASS) per satellite.
    toa_gps_s : reference epoch of the elements (time of applicability / t_oe), GPS s.
    a_m : semi-major axis.  e : eccentricity (0 <= e < 1).  i_rad : inclination.
    Omega0_rad : longitude of the ascending node at the weekly epoch (ICD Omega_0,
        see the module docstring); *not* the inertial RAAN.
    OmegaDot_rad_s : rate of right ascension (secular node drift, J2 regression).
    omega_rad : argument of perigee.  M0_rad : mean anomaly at ``toa_gps_s``.
    glonass_k : GLONASS FDMA channel number (-7..+6); 0 for GPS.
    delta_n_rad_s, idot_rad_s, cuc_rad, cus_rad, crc_m, crs_m, cic_rad, cis_rad :
        optional broadcast-ephemeris corrections (IS-GPS-200 Table 20-III), zero
        (the default) for almanacs and the built-in constellations.

    Arrays are copied and made read-only.  Equality is identity (arrays inside).
    """

    sat_id: np.ndarray
    system: np.ndarray
    toa_gps_s: np.ndarray
    a_m: np.ndarray
    e: np.ndarray
    i_rad: np.ndarray
    Omega0_rad: np.ndarray
    OmegaDot_rad_s: np.ndarray
    omega_rad: np.ndarray
    M0_rad: np.ndarray
    glonass_k: np.ndarray
    delta_n_rad_s: np.ndarray | None = None
    idot_rad_s: np.ndarray | None = None
    cuc_rad: np.ndarray | None = None
    cus_rad: np.ndarray | None = None
    crc_m: np.ndarray | None = None
    crs_m: np.ndarray | None = None
    cic_rad: np.ndarray | None = None
    cis_rad: np.ndarray | None = None
    _prop: dict = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        ids = _as_1d("sat_id", self.sat_id, str)
        n = ids.shape[0]
        if n == 0:
            raise ValueError("sat_id: a constellation needs at least one satellite")

        def setf(name, arr):
            if arr.shape != (n,):
                arr = np.broadcast_to(arr, (n,)).copy() if arr.shape == (1,) else arr
            if arr.shape != (n,):
                raise ValueError(f"{name}: expected {n} values (one per sat_id), got shape {arr.shape}")
            arr = np.array(arr)  # own copy
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
            return arr

        setf("sat_id", ids)
        system = setf("system", _as_1d("system", self.system, str))
        bad = ~np.isin(system, ("G", "R"))
        if bad.any():
            raise ValueError(f"system: expected 'G' or 'R', got {sorted(set(system[bad]))}")
        first = np.array([s[:1] for s in ids])
        if (first != system).any():
            raise ValueError(f"sat_id: first letter must equal system, bad ids {list(ids[first != system])}")
        if len(set(ids.tolist())) != n:
            dup = sorted({s for s in ids.tolist() if ids.tolist().count(s) > 1})
            raise ValueError(f"sat_id: duplicate satellite ids {dup}")
        for name in _FLOAT_FIELDS:
            arr = setf(name, _as_1d(name, getattr(self, name), float))
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name}: values must be finite")
        for name in _HARMONIC_FIELDS:
            value = getattr(self, name)
            arr = np.zeros(n) if value is None else _as_1d(name, value, float)
            arr = setf(name, arr)
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name}: values must be finite")
        k_in = _as_1d("glonass_k", self.glonass_k, float)
        if not np.all(k_in == np.round(k_in)):
            raise ValueError("glonass_k: channel numbers must be integers")
        k = setf("glonass_k", k_in.astype(np.int64))
        if (self.a_m <= 0).any():
            raise ValueError("a_m: semi-major axes must be positive")
        if ((self.e < 0) | (self.e >= 1)).any():
            raise ValueError("e: eccentricities must be in [0, 1)")
        is_glo = system == "R"
        if (k[~is_glo] != 0).any():
            raise ValueError("glonass_k: must be 0 for GPS satellites")
        if ((k[is_glo] < -7) | (k[is_glo] > 6)).any():
            raise ValueError("glonass_k: GLONASS channels must be in -7..+6")
        object.__setattr__(self, "_prop", _precompute(self))

    # -- container protocol -------------------------------------------------
    def __len__(self) -> int:
        return int(self.sat_id.shape[0])

    def __repr__(self) -> str:
        ids = self.sat_id.tolist()
        shown = ", ".join(ids[:6]) + (", ..." if len(ids) > 6 else "")
        return f"Constellation({len(self)} satellites: {shown})"

    @property
    def carrier_l1_hz(self) -> np.ndarray:
        """L1 carrier per satellite: GPS 1575.42 MHz; GLONASS 1602 MHz + k * 0.5625 MHz."""
        return np.where(self.system == "G", F_GPS_L1_HZ, glonass_l1_hz(self.glonass_k.astype(float)))

    @property
    def gm_m3_s2(self) -> np.ndarray:
        """Gravitational constant used for each satellite (GPS ICD or PZ-90.11)."""
        return self._prop["gm"].copy()

    @property
    def omega_e_rad_s(self) -> np.ndarray:
        """Earth rotation rate used for each satellite (GPS ICD or PZ-90.11)."""
        return self._prop["we"].copy()

    def _field_arrays(self) -> dict:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.init}

    def index(self, ids: "str | Iterable[str]") -> np.ndarray:
        """Integer positions of the given satellite ids (ValueError for unknown ids)."""
        ids = [ids] if isinstance(ids, str) else list(ids)
        lookup = {s: j for j, s in enumerate(self.sat_id.tolist())}
        missing = [s for s in ids if s not in lookup]
        if missing:
            raise ValueError(f"mask_or_ids: unknown satellite ids {missing}")
        return np.array([lookup[s] for s in ids], dtype=np.int64)

    def subset(self, mask_or_ids) -> "Constellation":
        """The satellites selected by a boolean mask of length S, integer indices,
        or satellite ids (a string or an iterable of strings; order is kept)."""
        if isinstance(mask_or_ids, str):
            idx = self.index(mask_or_ids)
        else:
            arr = np.asarray(mask_or_ids)
            if arr.dtype == bool:
                if arr.shape != (len(self),):
                    raise ValueError(f"mask_or_ids: boolean mask must have shape ({len(self)},), got {arr.shape}")
                idx = np.flatnonzero(arr)
            elif arr.dtype.kind in "US":
                idx = self.index(arr.reshape(-1).tolist())
            elif arr.dtype.kind in "iu":
                idx = arr.reshape(-1)
                if ((idx < -len(self)) | (idx >= len(self))).any():
                    raise ValueError("mask_or_ids: index out of range")
            elif arr.size == 0:
                idx = np.zeros(0, dtype=np.int64)
            else:
                raise ValueError(f"mask_or_ids: expected a bool mask, indices or ids, got dtype {arr.dtype}")
        if idx.size == 0:
            raise ValueError("mask_or_ids: selects no satellite")
        return Constellation(**{k: v[idx] for k, v in self._field_arrays().items()})

    def concat(self, other: "Constellation") -> "Constellation":
        """This constellation followed by ``other`` (ValueError on duplicate ids)."""
        if not isinstance(other, Constellation):
            raise ValueError(f"other: expected a Constellation, got {type(other).__name__}")
        a, b = self._field_arrays(), other._field_arrays()
        return Constellation(**{k: np.concatenate([a[k], b[k]]) for k in a})

    def __reduce__(self):
        # Pickle through the constructor: arrays come back validated and read-only.
        return (_constellation_from_fields, (self._field_arrays(),))

    def replace(self, **changes) -> "Constellation":
        """A copy with some element arrays replaced (validated again)."""
        return dataclasses.replace(self, **changes)


def _constellation_from_fields(fields: dict) -> Constellation:
    return Constellation(**fields)


def _precompute(c: Constellation) -> dict:
    """Per-satellite constants of the propagator, as (S,) arrays ('row') and as
    (S, 1) columns ('col', for satellite-major (S, T) evaluation)."""
    gm = np.where(c.system == "G", _GPS_PARAMS[0], _GLO_PARAMS[0])
    we = np.where(c.system == "G", _GPS_PARAMS[1], _GLO_PARAMS[1])
    row = _kepler_constants(gm, we, c.toa_gps_s, c.a_m, c.e, c.i_rad, c.Omega0_rad, c.OmegaDot_rad_s,
                            c.omega_rad, c.M0_rad, **{name: getattr(c, name) for name in _HARMONIC_FIELDS})
    harmonic = any(np.any(getattr(c, name) != 0.0) for name in _HARMONIC_FIELDS[1:])
    return {
        "gm": gm,
        "we": we,
        "harmonic": bool(harmonic),
        "row": row,
        "col": {k: v[:, None] for k, v in row.items()},
    }


def _kepler_constants(gm, we, toa_gps_s, a_m, e, i_rad, Omega0_rad, OmegaDot_rad_s, omega_rad, M0_rad,
                      delta_n_rad_s, idot_rad_s, cuc_rad, cus_rad, crc_m, crs_m, cic_rad, cis_rad) -> dict:
    """The propagator's constants of N element sets (arrays of shape (N,))."""
    toa_sow = np.mod(toa_gps_s, SECONDS_PER_WEEK)
    return {
        "e": e,
        "a": a_m,
        "M0": M0_rad,
        "n": np.sqrt(gm / a_m**3) + delta_n_rad_s,
        "sqrt1me2": np.sqrt(1.0 - e**2),
        "cos_w": np.cos(omega_rad),
        "sin_w": np.sin(omega_rad),
        # Node longitude at t_k = 0, reduced to [0, 2 pi) for precision.
        "node0": np.mod(Omega0_rad - we * toa_sow, 2.0 * np.pi),
        "node_rate": OmegaDot_rad_s - we,
        "i": i_rad,
        "cos_i": np.cos(i_rad),
        "sin_i": np.sin(i_rad),
        "idot_rad_s": idot_rad_s, "cuc_rad": cuc_rad, "cus_rad": cus_rad, "crc_m": crc_m,
        "crs_m": crs_m, "cic_rad": cic_rad, "cis_rad": cis_rad,
    }


def kepler_state_ecef(gm, we, toa_gps_s, a_m, e, i_rad, Omega0_rad, OmegaDot_rad_s, omega_rad, M0_rad,
                      delta_n_rad_s, idot_rad_s, cuc_rad, cus_rad, crc_m, crs_m, cic_rad, cis_rad, t_gps_s):
    """IS-GPS-200 Table 20-IV for N element sets at N times (all arguments (N,) arrays or
    scalars): the same propagator as :func:`sat_state_ecef`, for element sets that are not a
    :class:`Constellation` (several broadcast records of one satellite).

    t_k = t_gps_s - toa_gps_s in continuous GPS seconds, so the ICD's week crossover rule
    (t_k +- 604800 when |t_k| > 302400) is never needed.

    Returns (pos_m (N, 3), vel_m_s (N, 3) in the rotating Earth-fixed frame, E_rad (N,) the
    eccentric anomaly, for the relativistic clock term F e sqrt(A) sin E).
    """
    args = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (
        gm, we, toa_gps_s, a_m, e, i_rad, Omega0_rad, OmegaDot_rad_s, omega_rad, M0_rad, delta_n_rad_s,
        idot_rad_s, cuc_rad, cus_rad, crc_m, crs_m, cic_rad, cis_rad, t_gps_s)))
    args = [np.atleast_1d(a) for a in args]
    p = _kepler_constants(*args[:18])
    tk = args[18] - args[2]
    x, y, z, vx, vy, vz, E = _propagate_rows(p, True, tk, want_vel=True)
    return np.stack((x, y, z), axis=-1), np.stack((vx, vy, vz), axis=-1), E


# ---------------------------------------------------------------------------
# Propagation
# ---------------------------------------------------------------------------

def _solve_kepler(M: np.ndarray, e: np.ndarray) -> np.ndarray:
    """Eccentric anomaly E with E - e sin E = M, by Newton's method.

    E_{j+1} = E_j - d_j,  d_j = (E_j - e sin E_j - M) / (1 - e cos E_j),  from
    E_0 = M + e sin M.  For f(E) = E - e sin E - M, |f''| <= e and f' >= 1 - e, so the
    error left after a step d is at most e d^2 / (2 (1 - e)) (Newton's error bound);
    iteration stops once twice that bound, or the step itself, is below
    ``KEPLER_TOL_RAD`` (1e-13 rad), i.e. E is known to better than 1e-13 rad.
    M is reduced to (-pi, pi] first so that E carries full precision.
    """
    M = np.remainder(M + np.pi, 2.0 * np.pi) - np.pi
    E = M + e * np.sin(M)
    bound = e / (1.0 - e)
    for _ in range(60):
        d = (E - e * np.sin(E) - M) / (1.0 - e * np.cos(E))
        E -= d
        if np.all((bound * (d * d) < KEPLER_TOL_RAD) | (np.abs(d) < KEPLER_TOL_RAD)):
            return E
    raise RuntimeError("Kepler's equation did not converge")  # pragma: no cover


def _propagate(c: Constellation, tk_s: np.ndarray, want_vel: bool = True, sat_major: bool = False):
    """ECEF position (and velocity) components at t_k = t - toa.

    ``tk_s`` broadcasts against the per-satellite constants as (..., S), or as
    (S, ...) with ``sat_major`` (numpy is much faster with the long axis last).

    Returns (x, y, z, vx, vy, vz) as arrays of the broadcast shape; vx.. are None
    when ``want_vel`` is False.  IS-GPS-200 Table 20-IV:

        M = M0 + n t_k,  E - e sin E = M,  nu = atan2(sqrt(1-e^2) sin E, cos E - e),
        Phi = nu + omega,  u = Phi + du,  r = a (1 - e cos E) + dr,  i = i0 + di + IDOT t_k,
        (du, dr, di) = (C_us, C_rs, C_is) sin 2Phi + (C_uc, C_rc, C_ic) cos 2Phi,
        x' = r cos u,  y' = r sin u,  Omega = Omega0 + (OmegaDot - w_e) t_k - w_e t_oa,
        x = x' cos Omega - y' cos i sin Omega,  y = x' sin Omega + y' cos i cos Omega,
        z = y' sin i.

    (cos nu = (cos E - e)/(1 - e cos E), sin nu = sqrt(1-e^2) sin E/(1 - e cos E), and
    cos/sin of Phi by the angle-addition formulas: no arctan needed.)

    Velocity: dE/dt = n / (1 - e cos E), dnu/dt = sqrt(1-e^2) n / (1 - e cos E)^2,
    dr/dt = a e sin E dE/dt + 2 dnu/dt (C_rs cos 2Phi - C_rc sin 2Phi), and so on;
    dx/dt = x'' cos Omega - y'' cos i sin Omega + y' sin i sin Omega di/dt - dOmega/dt y,
    dy/dt = x'' sin Omega + y'' cos i cos Omega - y' sin i cos Omega di/dt + dOmega/dt x,
    dz/dt = y'' sin i + y' cos i di/dt, with x'' = dx'/dt etc.
    """
    x, y, z, vx, vy, vz, _ = _propagate_rows(c._prop["col" if sat_major else "row"], c._prop["harmonic"],
                                             tk_s, want_vel)
    return x, y, z, vx, vy, vz


def _propagate_rows(p: dict, harmonic: bool, tk_s, want_vel: bool = True):
    """:func:`_propagate` on the constants ``p`` of :func:`_kepler_constants`; also returns E."""
    e = p["e"]
    E = _solve_kepler(p["M0"] + p["n"] * tk_s, e)
    sinE, cosE = np.sin(E), np.cos(E)
    den = 1.0 - e * cosE
    inv_den = 1.0 / den
    cnu = (cosE - e) * inv_den
    snu = p["sqrt1me2"] * sinE * inv_den
    cphi = cnu * p["cos_w"] - snu * p["sin_w"]
    sphi = snu * p["cos_w"] + cnu * p["sin_w"]
    r = p["a"] * den
    node = p["node0"] + p["node_rate"] * tk_s
    cO, sO = np.cos(node), np.sin(node)
    if harmonic:
        s2, c2 = 2.0 * sphi * cphi, cphi * cphi - sphi * sphi
        du = p["cus_rad"] * s2 + p["cuc_rad"] * c2
        cdu, sdu = np.cos(du), np.sin(du)
        cu, su = cphi * cdu - sphi * sdu, sphi * cdu + cphi * sdu
        r = r + p["crs_m"] * s2 + p["crc_m"] * c2
        inc = p["i"] + p["cis_rad"] * s2 + p["cic_rad"] * c2 + p["idot_rad_s"] * tk_s
        ci, si = np.cos(inc), np.sin(inc)
    else:
        cu, su = cphi, sphi
        ci, si = p["cos_i"], p["sin_i"]
    xp, yp = r * cu, r * su
    yp_ci = yp * ci
    x = xp * cO - yp_ci * sO
    y = xp * sO + yp_ci * cO
    z = yp * si
    if not want_vel:
        return x, y, z, None, None, None, E
    Edot = p["n"] * inv_den
    nudot = p["sqrt1me2"] * Edot * inv_den
    rdot = p["a"] * e * sinE * Edot
    if harmonic:
        udot = nudot * (1.0 + 2.0 * (p["cus_rad"] * c2 - p["cuc_rad"] * s2))
        rdot = rdot + 2.0 * nudot * (p["crs_m"] * c2 - p["crc_m"] * s2)
        idot = p["idot_rad_s"] + 2.0 * nudot * (p["cis_rad"] * c2 - p["cic_rad"] * s2)
    else:
        udot = nudot
        idot = None
    r_udot = r * udot
    xpd = rdot * cu - r_udot * su
    ypd = rdot * su + r_udot * cu
    ypd_ci = ypd * ci
    Od = p["node_rate"]
    vx = xpd * cO - ypd_ci * sO - Od * y
    vy = xpd * sO + ypd_ci * cO + Od * x
    vz = ypd * si
    if idot is not None:
        yp_si_idot = yp * si * idot
        vx = vx + yp_si_idot * sO
        vy = vy - yp_si_idot * cO
        vz = vz + yp_ci * idot
    return x, y, z, vx, vy, vz, E


def _check_constellation(constellation) -> Constellation:
    if not isinstance(constellation, Constellation):
        raise ValueError(f"constellation: expected a Constellation, got {type(constellation).__name__}")
    return constellation


def sat_state_ecef(constellation: Constellation, t_gps_s) -> tuple[np.ndarray, np.ndarray]:
    """Satellite ECEF position and velocity at GPS time(s) ``t_gps_s``.

    Unperturbed Keplerian orbit plus the secular node drift OmegaDot (and the
    broadcast harmonic corrections if the constellation carries any), rotated into
    the Earth-fixed frame: the IS-GPS-200 Table 20-IV user algorithm (see
    :func:`_propagate` for the equations).  Kepler's equation is solved by Newton's
    method to ``KEPLER_TOL_RAD`` (1e-13 rad).  GM and omega_e are the GPS ICD values
    for GPS satellites and PZ-90.11 values for GLONASS ones.

    Parameters
    ----------
    constellation : Constellation with S satellites.
    t_gps_s : array_like of any shape (...), GPS seconds.

    Returns
    -------
    pos_ecef_m : (..., S, 3) position in the Earth-fixed frame at t.
    vel_ecef_m_s : (..., S, 3) its exact time derivative in the *rotating* Earth-fixed
        frame (analytic; inertial velocity = vel + omega_e z x pos).
    """
    c = _check_constellation(constellation)
    t = np.asarray(t_gps_s, dtype=float)
    if not np.all(np.isfinite(t)):
        raise ValueError("t_gps_s: times must be finite")
    # t - toa first (exact for nearby float64 values), so no precision is lost.
    # Satellite-major (S, T) evaluation, then one (3, S, T) -> (..., S, 3) copy.
    tk = t.reshape(1, -1) - c.toa_gps_s[:, None]
    x, y, z, vx, vy, vz = _propagate(c, tk, want_vel=True, sat_major=True)
    shape = t.shape + (len(c), 3)
    pos = np.ascontiguousarray(np.stack((x, y, z)).transpose(2, 1, 0)).reshape(shape)
    vel = np.ascontiguousarray(np.stack((vx, vy, vz)).transpose(2, 1, 0)).reshape(shape)
    return pos, vel


# ---------------------------------------------------------------------------
# Built-in constellations
# ---------------------------------------------------------------------------

def _j2_node_rate(gm, a_m, e, i_rad):
    """Secular J2 nodal regression dOmega/dt = -3/2 n J2 (R/p)^2 cos i
    (Vallado, Fundamentals of Astrodynamics, eq. 9-41), rad/s."""
    n = np.sqrt(gm / np.asarray(a_m) ** 3)
    p = np.asarray(a_m) * (1.0 - np.asarray(e) ** 2)
    return -1.5 * n * _J2 * (_R_EARTH_M / p) ** 2 * np.cos(i_rad)


def _mean_from_true(nu, e):
    """Mean anomaly from true anomaly: E = 2 atan(sqrt((1-e)/(1+e)) tan(nu/2)), M = E - e sin E."""
    E = 2.0 * np.arctan2(np.sqrt(1.0 - e) * np.sin(nu / 2.0), np.sqrt(1.0 + e) * np.cos(nu / 2.0))
    return E - e * np.sin(E)


def _omega0_from_node_longitude(node_lon_at_toa_rad, toa_gps_s, we):
    """ICD Omega_0 for a given Earth-fixed node longitude at toa: Omega0 = lon + w_e t_oa."""
    return np.mod(node_lon_at_toa_rad + we * np.mod(toa_gps_s, SECONDS_PER_WEEK), 2.0 * np.pi)


# GPS slot layout: (PRN, plane, argument of latitude u at toa [deg], e, argument of
# perigee [deg]).  Derived (rounded) from a real 31-satellite YUMA almanac of
# February 2018 (GPS week 1987): planes assigned by node longitude, u computed from
# omega + true anomaly at its toa.  Plane A has Earth-fixed node longitude
# _GPS_NODE_A_DEG at toa (as in that almanac at its toa), planes B..F follow every
# 60 deg east.  So the Earth-fixed pattern at DEFAULT_TOA resembles that almanac at
# its own toa; it is not an ephemeris of the real 2025 constellation.
_GPS_NODE_A_DEG = 194.0
_GPS_LAYOUT = (
    (31, "A", 122.4, 0.0088, 351.0), (24, "A", 225.5, 0.0068, 29.9),
    (30, "A", 333.6, 0.0031, 181.5), (7, "A", 357.3, 0.0112, 214.2),
    (16, "B", 26.1, 0.0099, 26.7), (26, "B", 55.6, 0.0027, 0.6),
    (25, "B", 130.5, 0.0072, 46.4), (12, "B", 162.4, 0.0069, 52.7),
    (28, "B", 269.5, 0.0198, 272.5),
    (29, "C", 70.2, 0.0005, 42.9), (19, "C", 179.6, 0.0097, 64.3),
    (17, "C", 197.2, 0.0124, 257.3), (8, "C", 297.4, 0.0033, 328.0),
    (27, "C", 330.2, 0.0055, 20.3),
    (2, "D", 94.2, 0.0178, 251.3), (6, "D", 125.0, 0.0011, 288.5),
    (1, "D", 216.7, 0.0073, 35.2), (11, "D", 241.6, 0.0167, 99.7),
    (21, "D", 353.4, 0.0244, 268.5),
    (5, "E", 27.4, 0.0053, 35.8), (3, "E", 156.8, 0.0012, 28.7),
    (22, "E", 175.4, 0.0073, 267.4), (10, "E", 262.7, 0.0033, 197.7),
    (18, "E", 293.8, 0.0185, 259.6), (20, "E", 341.7, 0.0045, 102.4),
    (9, "F", 60.4, 0.0012, 100.3), (23, "F", 91.0, 0.0120, 222.6),
    (14, "F", 174.2, 0.0093, 247.9), (32, "F", 198.5, 0.0017, 205.7),
    (15, "F", 294.5, 0.0102, 38.2), (13, "F", 316.2, 0.0037, 93.1),
)

#: GLONASS slot -> FDMA channel k (slots 1..24), the assignment in force since the
#: late 2010s (GLONASS IAC constellation status; e.g. commaai/laika constants).
#: Antipodal slots j and j+4 of the same plane share a channel.
GLONASS_SLOT_K = (
    1, -4, 5, 6, 1, -4, 5, 6,
    -2, -7, 0, -1, -2, -7, 0, -1,
    4, -3, 3, 2, 4, -3, 3, 2,
)
# Earth-fixed node longitude of GLONASS plane 1 at toa and argument of latitude of
# slot 1 at toa: arbitrary choices (no real epoch is reproduced).
_GLO_NODE_1_DEG = 30.0
_GLO_U_SLOT1_DEG = 0.0


def gps_constellation(toa_gps_s: float = DEFAULT_TOA_GPS_S) -> Constellation:
    """A 31-satellite GPS constellation in six planes A-F (sorted by PRN).

    Nominal a = 26,559.7 km, i = 55 deg, planes every 60 deg of node longitude,
    real-like non-uniform slot phasing (4-6 per plane) and small eccentricities
    taken from a 2018 almanac (see ``_GPS_LAYOUT``), OmegaDot from the J2 nodal
    regression.  ``toa_gps_s`` sets the reference epoch of the elements.
    """
    toa = _scalar_time("toa_gps_s", toa_gps_s)
    rows = sorted(_GPS_LAYOUT)
    prn = np.array([r[0] for r in rows])
    plane = np.array(["ABCDEF".index(r[1]) for r in rows])
    u = np.radians([r[2] for r in rows])
    e = np.array([r[3] for r in rows])
    w = np.radians([r[4] for r in rows])
    n_sat = len(rows)
    gm, we = _GPS_PARAMS
    node_lon = np.radians(_GPS_NODE_A_DEG + 60.0 * plane)
    return Constellation(
        sat_id=np.array([f"G{p:02d}" for p in prn]),
        system=np.full(n_sat, "G"),
        toa_gps_s=np.full(n_sat, toa),
        a_m=np.full(n_sat, GPS_A_M),
        e=e,
        i_rad=np.full(n_sat, GPS_I_RAD),
        Omega0_rad=_omega0_from_node_longitude(node_lon, toa, we),
        OmegaDot_rad_s=_j2_node_rate(gm, GPS_A_M, e, GPS_I_RAD),
        omega_rad=w,
        M0_rad=np.mod(_mean_from_true(u - w, e), 2.0 * np.pi),
        glonass_k=np.zeros(n_sat, dtype=int),
    )


def glonass_constellation(toa_gps_s: float = DEFAULT_TOA_GPS_S) -> Constellation:
    """The nominal 24-slot GLONASS constellation R01..R24 (Walker 24/3/1).

    Three planes (slots 1-8, 9-16, 17-24) with node longitudes 120 deg apart,
    i = 64.8 deg, a = 25,510 km, circular orbits; within a plane the slots are 45 deg
    apart in argument of latitude and plane p+1 is shifted by +15 deg (the nominal
    GLONASS slot plan described in the GLONASS ICD).  That slot j+1 trails slot j,
    and the absolute node longitudes and phases, are this module's choices, not a
    real epoch.  FDMA channels from ``GLONASS_SLOT_K`` (antipodal slots j, j+4 share
    a channel); OmegaDot from the J2 nodal regression.
    """
    toa = _scalar_time("toa_gps_s", toa_gps_s)
    slot = np.arange(1, 25)
    plane = (slot - 1) // 8
    pos_in_plane = (slot - 1) % 8
    u = np.radians(_GLO_U_SLOT1_DEG - 45.0 * pos_in_plane + 15.0 * plane)
    gm, we = _GLO_PARAMS
    node_lon = np.radians(_GLO_NODE_1_DEG + 120.0 * plane)
    n_sat = slot.size
    return Constellation(
        sat_id=np.array([f"R{s:02d}" for s in slot]),
        system=np.full(n_sat, "R"),
        toa_gps_s=np.full(n_sat, toa),
        a_m=np.full(n_sat, GLONASS_A_M),
        e=np.zeros(n_sat),
        i_rad=np.full(n_sat, GLONASS_I_RAD),
        Omega0_rad=_omega0_from_node_longitude(node_lon, toa, we),
        OmegaDot_rad_s=np.full(n_sat, _j2_node_rate(gm, GLONASS_A_M, 0.0, GLONASS_I_RAD)),
        omega_rad=np.zeros(n_sat),
        M0_rad=np.mod(u, 2.0 * np.pi),
        glonass_k=np.array(GLONASS_SLOT_K),
    )


def default_constellation(systems: str = "GR", toa_gps_s: float = DEFAULT_TOA_GPS_S) -> Constellation:
    """The built-in GPS ('G') and/or GLONASS ('R') constellations, concatenated in
    the order given by ``systems`` (e.g. 'GR', 'G', 'R')."""
    if not isinstance(systems, str) or not systems or set(systems) - {"G", "R"} or len(set(systems)) != len(systems):
        raise ValueError(f"systems: expected a string of distinct 'G'/'R' letters, got {systems!r}")
    makers = {"G": gps_constellation, "R": glonass_constellation}
    out = makers[systems[0]](toa_gps_s)
    for s in systems[1:]:
        out = out.concat(makers[s](toa_gps_s))
    return out


def _scalar_time(name: str, value) -> float:
    try:
        t = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a number of GPS seconds, got {value!r}") from None
    if not math.isfinite(t):
        raise ValueError(f"{name}: must be finite")
    return t


# ---------------------------------------------------------------------------
# File loaders
# ---------------------------------------------------------------------------

def _fail(path, lineno: int | None, msg: str):
    where = f"{path}" if lineno is None else f"{path}, line {lineno}"
    raise ValueError(f"{where}: {msg}")


def _read_lines(path) -> list[str]:
    try:
        text = Path(path).read_text(encoding="ascii", errors="replace")
    except OSError as exc:
        raise ValueError(f"path: cannot read {path}: {exc}") from None
    return text.splitlines()


# YUMA key (lower-cased prefix) -> our field name.
_YUMA_KEYS = (
    ("id", "id"),
    ("health", "health"),
    ("eccentricity", "e"),
    ("time of applicability", "toa"),
    ("orbital inclination", "i"),
    ("rate of right ascen", "OmegaDot"),
    ("sqrt(a)", "sqrtA"),
    ("right ascen at", "Omega0"),  # "Right Ascen at Week(rad)" (some files: "at TOA")
    ("argument of perigee", "omega"),
    ("mean anom", "M0"),
    ("af0", "af0"),
    ("af1", "af1"),
    ("week", "week"),
)
_YUMA_REQUIRED = ("id", "e", "toa", "i", "OmegaDot", "sqrtA", "Omega0", "omega", "M0", "week")


def _full_gps_week(week: int, reference_t_gps_s: float) -> int:
    """Resolve a 10-bit (mod 1024) GPS week to the full week nearest the reference."""
    if week >= 1024:
        return week
    ref_week = reference_t_gps_s / SECONDS_PER_WEEK
    rollovers = round((ref_week - week) / 1024.0)
    return week + 1024 * max(rollovers, 0)


def load_yuma_almanac(path, reference_t_gps_s: float = DEFAULT_TOA_GPS_S,
                      healthy_only: bool = False) -> Constellation:
    """Read a GPS YUMA almanac (text; the USCG NAVCEN / CelesTrak format).

    Each satellite block starts with a '****' header line followed by 'Key: value'
    lines (ID, Health, Eccentricity, Time of Applicability(s), Orbital Inclination
    (rad), Rate of Right Ascen(r/s), SQRT(A) (m 1/2), Right Ascen at Week(rad),
    Argument of Perigee(rad), Mean Anom(rad), Af0(s), Af1(s/s), week).  The week is
    usually given modulo 1024; a week below 1024 is resolved to the rollover epoch
    nearest ``reference_t_gps_s``.  The clock terms Af0/Af1 are read but not kept.
    ``healthy_only`` drops satellites with a non-zero health word.

    Returns a GPS-only :class:`Constellation` (sat ids 'Gnn', in file order).
    Raises ValueError naming the file and line for a malformed file.
    """
    lines = _read_lines(path)
    blocks: list[tuple[int, dict]] = []
    current: dict | None = None
    for lineno, raw in enumerate(lines, start=1):
        line = raw.strip()
        if not line:
            continue
        if line.startswith("*"):
            current = {}
            blocks.append((lineno, current))
            continue
        if current is None:
            _fail(path, lineno, f"text before the first '****' almanac header: {line[:40]!r}")
        if ":" not in line:
            _fail(path, lineno, f"expected 'Key: value', got {line[:40]!r}")
        key, value = line.split(":", 1)
        key_l = key.strip().lower()
        for prefix, name in _YUMA_KEYS:
            if key_l.startswith(prefix):
                try:
                    current[name] = (float(value.strip()), lineno)
                except ValueError:
                    _fail(path, lineno, f"cannot parse a number for {key.strip()!r}: {value.strip()!r}")
                break
        else:
            _fail(path, lineno, f"unknown YUMA key {key.strip()!r}")
    if not blocks:
        _fail(path, None, "no YUMA almanac records found")
    rows = []
    for start, blk in blocks:
        missing = [k for k in _YUMA_REQUIRED if k not in blk]
        if missing:
            _fail(path, start, f"almanac record lacks {missing}")
        val = {k: v for k, (v, _) in blk.items()}
        prn = val["id"]
        if prn != int(prn) or not 1 <= prn <= 99:
            _fail(path, blk["id"][1], f"bad satellite ID {prn}")
        if not 0.0 <= val["e"] < 1.0:
            _fail(path, blk["e"][1], f"eccentricity {val['e']} out of [0, 1)")
        if val["sqrtA"] <= 0.0:
            _fail(path, blk["sqrtA"][1], f"SQRT(A) {val['sqrtA']} must be positive")
        if not 0.0 <= val["toa"] < SECONDS_PER_WEEK:
            _fail(path, blk["toa"][1], f"time of applicability {val['toa']} outside the week")
        week = val["week"]
        if week != int(week) or week < 0:
            _fail(path, blk["week"][1], f"bad week number {week}")
        if healthy_only and val.get("health", 0.0) != 0.0:
            continue
        full_week = _full_gps_week(int(week), reference_t_gps_s)
        rows.append((f"G{int(prn):02d}", full_week * SECONDS_PER_WEEK + val["toa"], val, start))
    if not rows:
        _fail(path, None, "no (healthy) satellites in the almanac")
    ids = [r[0] for r in rows]
    dup = sorted({s for s in ids if ids.count(s) > 1})
    if dup:
        _fail(path, rows[ids.index(dup[0])][3], f"duplicate almanac records for {dup}")
    v = [r[2] for r in rows]
    return Constellation(
        sat_id=np.array(ids),
        system=np.full(len(rows), "G"),
        toa_gps_s=np.array([r[1] for r in rows]),
        a_m=np.array([x["sqrtA"] ** 2 for x in v]),
        e=np.array([x["e"] for x in v]),
        i_rad=np.array([x["i"] for x in v]),
        Omega0_rad=np.array([x["Omega0"] for x in v]),
        OmegaDot_rad_s=np.array([x["OmegaDot"] for x in v]),
        omega_rad=np.array([x["omega"] for x in v]),
        M0_rad=np.array([x["M0"] for x in v]),
        glonass_k=np.zeros(len(rows), dtype=int),
    )


def load_rinex_nav(path, harmonics: bool = True, healthy_only: bool = False,
                   t_gps_s: float | None = None) -> Constellation:
    """The GPS broadcast ephemerides in force at ``t_gps_s``, from a RINEX 2.x (GPS 'N') or
    3.x ('N') navigation file, as a :class:`Constellation` (one element set per satellite).

    Every record of the file is read (:func:`sitl.gnss.rinex_nav.read_nav`, which keeps them
    all); per satellite the record in force at ``t_gps_s`` is taken: the one whose Toe is
    nearest among those whose fit interval covers it (IS-GPS-200; ``GpsEphemerides.select``).
    ``t_gps_s`` None means the earliest Toe in the file. Satellites with no record in force
    are left out. sqrt(A), e, i0, OMEGA0, OMEGA DOT, omega, M0 at t_oe, so
    ``toa_gps_s = week * 604800 + t_oe`` (the RINEX week is continuous, not modulo 1024). With
    ``harmonics`` (default) Delta_n, IDOT and C_uc .. C_is are kept (the full IS-GPS-200 Table
    20-IV algorithm); ``harmonics=False`` drops them (the almanac-like Keplerian orbit). A
    Constellation carries no clock terms: for clocks, TGD and a record per epoch, use
    ``read_nav`` and :mod:`sitl.gnss.broadcast`. ``healthy_only`` drops satellites whose
    record in force has a non-zero SV health word. GLONASS and other systems are skipped.

    Raises ValueError naming the file and line for a malformed file.
    """
    from sitl.gnss.rinex_common import GnssFileError
    from sitl.gnss.rinex_nav import read_nav

    try:
        nav = read_nav(path)
    except GnssFileError as exc:
        if exc.line is None and exc.reason.startswith("cannot read the file"):
            raise ValueError(f"path: cannot read {path}: {exc.reason}") from None
        raise
    g = nav.gps
    if g is None:
        _fail(path, None, "no (healthy) GPS navigation records found")
    t = float(np.min(g.toe_gps_s)) if t_gps_s is None else _scalar_time("t_gps_s", t_gps_s)
    ids = g.sats
    idx = g.select(ids, np.full(len(ids), t))
    keep = idx >= 0
    if healthy_only:
        keep &= np.where(idx >= 0, g.health[idx] == 0, False)
    if not keep.any():
        _fail(path, None, "no (healthy) GPS navigation records found")
    sel = idx[keep]
    cols = dict(
        toa_gps_s=g.toe_gps_s[sel], a_m=g.sqrt_a[sel] ** 2, e=g.e[sel], i_rad=g.i0_rad[sel],
        Omega0_rad=g.omega0_rad[sel], OmegaDot_rad_s=g.omega_dot_rad_s[sel], omega_rad=g.omega_rad[sel],
        M0_rad=g.m0_rad[sel],
    )
    if harmonics:
        cols.update(delta_n_rad_s=g.delta_n_rad_s[sel], idot_rad_s=g.idot_rad_s[sel], cuc_rad=g.cuc_rad[sel],
                    cus_rad=g.cus_rad[sel], crc_m=g.crc_m[sel], crs_m=g.crs_m[sel], cic_rad=g.cic_rad[sel],
                    cis_rad=g.cis_rad[sel])
    n = int(sel.size)
    return Constellation(sat_id=g.sat[sel], system=np.full(n, "G"), glonass_k=np.zeros(n, dtype=int), **cols)
