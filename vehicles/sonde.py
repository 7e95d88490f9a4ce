"""Radiosonde flight (seed 004): ascent, burst, parachute descent, drift with the wind.

The world's truth model of a batch of aerological radiosondes (estimators come later).

Vertical
    Ascent at ``ascent_rate_m_s`` (about 5 m/s) to a burst altitude drawn uniformly in
    ``burst_alt_range_m`` (25-35 km) per sonde, then descent under a parachute at the
    terminal speed
        v_d(h) = descent_rate_sl_m_s * sqrt(rho0 / rho(h)),
    rho the U.S. Standard Atmosphere 1976 density (``sitl.atmosphere_std``), rho0 its
    sea-level value 1.225 kg/m^3: the drag balance rho v^2 = const.  The sonde lands at
    the launch site's height (flat terrain) and stays there (phase LANDED).

Horizontal
    The wind is a mean profile (east/north components linearly interpolated between
    altitude knots; the default is a winter jet stream, 58 m/s near 11 km) plus gusts.
    The sonde's velocity relaxes to the local mean wind with the aerodynamic rate p1
    (time constant 1/p1) and is driven by the gust acceleration a_g of seed 004
    (eq 20), a first-order Gauss-Markov process per axis with spectrum width p1 + p2:

        dv/dt   = p1 (w(h) - v) + a_g,
        da_g/dt = -(p1 + p2) a_g + sqrt(2 (p1 + p2)) sigma_a n,     E[a_g^2] = sigma_a^2.

    The seed writes the drive as (p1 + p2) sigma_a n and calls sigma_a^2 the variance of
    the acceleration fluctuations; the scaling used here makes sigma_a^2 the stationary
    variance exactly (as filters.models.Singer does); with a unit-PSD n the seed's literal
    form would give (p1 + p2) sigma_a^2 / 2.  The gust velocity v - (mean response) then
    has the stationary variance sigma_a^2 / (p1 (2 p1 + p2)) (about 1 m/s rms by
    default); p2 is the width of the wind-fluctuation spectrum.  The sonde starts from
    rest horizontally (held at the launcher) and climbing at the ascent rate, so it
    accelerates into the surface wind during the first ~1/p1 seconds.

    The vertical axis has the same structure: dv_u/dt = k_v (v_target(h) - v_u) + a_g,u,
    with v_target = +ascent rate or -v_d(h), k_v = ``vertical_relax_rate_1_s`` and
    a_g,u Gauss-Markov with the same width p1 + p2 and std ``sigma_a_vertical_m_s2``.

Discretisation
    Per axis the state [displacement, v, a_g] is a linear system driven by the input
    u = w(h) (or v_target(h)), held constant over a step and evaluated at the mid-step
    altitude predicted from the current vertical speed.  The step is the exact
    discretisation for any dt: Phi = expm(A dt), Gamma = int_0^dt expm(A s) B ds (from
    an augmented matrix exponential) and the process noise Q by Van Loan's method
    (scipy.linalg.expm), drawn as L n with L L^T = Q, n ~ N(0, I_3).  With p1 -> 0 this
    is exactly Singer's model (filters.models.Singer); the a_g marginal is
    a_g(k+1) = e^{-(p1+p2)dt} a_g(k) + sigma_a sqrt(1 - e^{-2(p1+p2)dt}) n.

Frames
    The state is geodetic (lat, lon, ellipsoidal height h) plus velocity, gust and
    total acceleration in the local east-north-up frame *at the sonde* (so "wind from
    the west" means the same thing 250 km downstream).  A step's east/north
    displacement (de, dn) moves the position by dlat = dn / (M + h), dlon = de / ((N + h)
    cos lat) with the meridian and prime-vertical radii M, N (at the step's start
    latitude: they change by < 1e-7 relative over a step), h and the cos at mid-step: no
    flat-Earth error (250 km downstream the Earth has dropped 4.9 km below the launch
    tangent plane).  Outputs are converted to ECEF (WGS-84):
        pos = geodetic_to_ecef(lat, lon, h),  vel = R^T v_enu,
        acc = R^T a_enu + (dR^T/dt) v_enu   (the transport-rate term, < 1e-3 m/s^2),
    R the ENU rotation at the sonde.  Earth rotation does not enter the dynamics (the
    sonde moves with the air; the Coriolis force acts on the air, i.e. on the wind).

Ground range: great-circle distance from the launch site to the sub-sonde point on
the Gaussian mean-curvature sphere at the launch latitude, R = sqrt(M N) (within
~0.3 % of the ellipsoidal geodesic for a few hundred km).

Randomness (conventions: every draw from a numpy.random.Generator passed in)
    ``rng`` is either one Generator for the whole batch, or a sequence of Generators,
    one per sonde (e.g. ``[np.random.default_rng(s) for s in SeedSequence(n).spawn(B)]``).
    With per-sonde Generators a sonde's flight depends only on its own stream: a batch of
    B sondes equals B single-sonde runs with the same streams, bitwise.  Per sonde, the
    draws are: the burst altitude (uniform), the initial gust accelerations (3 normals,
    stationary start), then 9 normals per step (3 axes x [displacement, v, a_g]), drawn
    for every step whatever the phase.  Noise is drawn in blocks and buffered, so
    ``simulate`` and repeated ``step`` give identical flights; the Generators belong to
    the flight once passed (drawing from them elsewhere changes it).

Shapes: per-sonde arrays carry the batch shape (...) (from the launch-site arrays or
``batch_shape``); vectors add a last axis of 3.  A track adds a leading time axis T.
Time is GPS seconds; SI units throughout.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np
import scipy.linalg

from filters.params import ParamError, array, as_given, number, param, require, validate
from sitl.atmosphere_std import RHO0_KG_M3, Z_MAX_M, Z_MIN_M, us76_density
from sitl.constants import WGS84
from sitl.geodesy import enu_rotation, geodetic_to_ecef
from sitl.gnss.orbits import DEFAULT_TOA_GPS_S

try:  # compiled flight loop (numba); the numpy path below is the reference
    import numba as _nb
except ImportError:  # pragma: no cover
    _nb = None

__all__ = [
    "ASCENT",
    "DEFAULT_LAUNCH_H_M",
    "DEFAULT_LAUNCH_LAT_RAD",
    "DEFAULT_LAUNCH_LON_RAD",
    "DESCENT",
    "LANDED",
    "SondeFlight",
    "SondeParams",
    "SondeState",
    "SondeTrack",
    "axis_discretisation",
    "descent_speed_m_s",
    "spawn_rngs",
]

ASCENT, DESCENT, LANDED = 0, 1, 2

#: A default launch site: an aerological station near Moscow (55.93 N, 37.52 E, 190 m).
DEFAULT_LAUNCH_LAT_RAD = math.radians(55.93)
DEFAULT_LAUNCH_LON_RAD = math.radians(37.52)
DEFAULT_LAUNCH_H_M = 190.0

# Winter jet-stream profile (altitude knot, speed, direction the wind blows FROM):
# westerlies veering from SW at the ground to W aloft, 58 m/s at 11 km.
_WIND_ALT_M = (0.0, 1_000.0, 3_000.0, 6_000.0, 9_000.0, 11_000.0, 13_000.0, 16_000.0, 20_000.0,
               25_000.0, 30_000.0, 36_000.0)
_WIND_SPEED_M_S = (7.0, 13.0, 22.0, 36.0, 52.0, 58.0, 52.0, 38.0, 26.0, 22.0, 25.0, 30.0)
_WIND_FROM_DEG = (230.0, 240.0, 250.0, 260.0, 265.0, 268.0, 270.0, 270.0, 270.0, 270.0, 270.0, 270.0)

_BLOCK_STEPS = 1024  # noise is drawn this many steps at a time, then buffered
# Targets are tabulated on a uniform altitude grid (linear interpolation between nodes):
# the wind profile exactly where its knots fall on the grid (the defaults do), the
# log of the descent-speed ratio to < 1e-7 relative.
_GRID_DZ_M = 10.0
_GRID_Z0_M = Z_MIN_M
_GRID_M = np.arange(Z_MIN_M, 60_000.0 + 0.5 * _GRID_DZ_M, _GRID_DZ_M)
_LOG_DESCENT_RATIO = 0.5 * np.log(RHO0_KG_M3 / us76_density(np.minimum(_GRID_M, Z_MAX_M)))


def _grid_lookup(table: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Linear interpolation of table (G, C) rows at altitudes h (...) -> (..., C); clamped."""
    x = np.clip((h - _GRID_Z0_M) * (1.0 / _GRID_DZ_M), 0.0, table.shape[0] - 1.0)
    i = np.minimum(x.astype(np.intp), table.shape[0] - 2)
    f = (x - i)[..., None]
    return table[i] * (1.0 - f) + table[i + 1] * f


def descent_speed_m_s(h_m, descent_rate_sl_m_s: float = 5.0) -> np.ndarray:
    """Terminal parachute descent speed (> 0) at altitude h_m: v_sl sqrt(rho0 / rho(h)).

    rho from the US 1976 standard; ln(v/v_sl) is interpolated linearly on a 10 m grid
    (relative error < 1e-7); altitudes outside [-5 km, 60 km] are clamped to that range.
    """
    h = np.asarray(h_m, dtype=float)
    return descent_rate_sl_m_s * np.exp(_grid_lookup(_LOG_DESCENT_RATIO[:, None], h)[..., 0])


def axis_discretisation(relax_rate_1_s: float, gust_rate_1_s: float, sigma_a: float, dt_s: float):
    """Exact discretisation of one axis [x, v, a_g] with input u held over the step.

        dx/dt = v,  dv/dt = k (u - v) + a_g,  da_g/dt = -beta a_g + sqrt(2 beta) sigma_a n
    (k = relax_rate_1_s >= 0, beta = gust_rate_1_s > 0, n unit white noise).

    Returns Phi (3, 3) = expm(A dt), Gamma (3,) = int_0^dt expm(A s) ds B (B = [0, k, 0]),
    Q (3, 3) the process-noise covariance (Van Loan) and L (3, 3) with L L^T = Q.
    """
    k, beta, T = float(relax_rate_1_s), float(gust_rate_1_s), float(dt_s)
    a = np.array([[0.0, 1.0, 0.0], [0.0, -k, 1.0], [0.0, 0.0, -beta]])
    b = np.array([0.0, k, 0.0])
    g = np.array([0.0, 0.0, math.sqrt(2.0 * beta) * sigma_a])
    aug = np.zeros((4, 4))
    aug[:3, :3], aug[:3, 3] = a, b
    e = scipy.linalg.expm(aug * T)
    phi, gam = e[:3, :3], e[:3, 3]
    vl = np.zeros((6, 6))
    vl[:3, :3], vl[:3, 3:], vl[3:, 3:] = -a, np.outer(g, g), a.T
    ev = scipy.linalg.expm(vl * T)
    q = ev[3:, 3:].T @ ev[:3, 3:]
    q = 0.5 * (q + q.T)
    w, v = np.linalg.eigh(q)
    lo = v * np.sqrt(np.clip(w, 0.0, None))  # L L^T = Q also when Q is (near) singular
    return phi, gam, q, lo


def spawn_rngs(seed, n: int) -> list[np.random.Generator]:
    """n independent per-sonde Generators from one seed (SeedSequence.spawn)."""
    return [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(int(n))]


# ---------------------------------------------------------------------------
# parameters

_POSITIVE = number(0.0, lo_open=True)
_NONNEG = number(0.0)


def _burst_range(key, value):
    """A pair (low, high) of heights, 0 < low <= high <= 50 km, stored as given."""
    try:
        lo, hi = (float(x) for x in value)
    except (TypeError, ValueError):
        lo = hi = math.nan
    if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 < lo <= hi <= 50_000.0):
        raise ParamError(key, f"expected a pair (low, high) of metres with 0 < low <= high <= 50 km, got {value!r}")
    return value


def _altitude_knots(key, value):
    """A non-empty, strictly increasing sequence of finite altitudes, stored as given."""
    alt = array()(key, value)
    if alt.ndim != 1 or alt.size < 1 or np.any(np.diff(alt) <= 0.0):
        raise ParamError(key, f"expected a non-empty, strictly increasing sequence of altitudes, got {value!r}")
    return value


@dataclass(frozen=True)
class SondeParams:
    """Radiosonde flight parameters (SI units).

    The seed (004) gives the model structure (eq 20) but no numbers for p1, p2, sigma_a;
    the defaults are chosen for a balloon-borne sonde: response time 1/p1 = 10 s, gust
    correlation time 1/p2 = 50 s, acceleration fluctuations 0.15 m/s^2 rms horizontally.
    """

    ascent_rate_m_s: float = param(5.0, check=_POSITIVE, doc="balloon ascent rate, m/s")
    burst_alt_range_m: tuple = param((25_000.0, 35_000.0), check=_burst_range,
                                     doc="the burst height's range (low, high), m: drawn uniformly, 0 < low <= high "
                                         "<= 50 km")
    descent_rate_sl_m_s: float = param(5.0, check=_POSITIVE, doc="parachute terminal speed at sea level, m/s")
    p1_1_s: float = param(0.1, check=_POSITIVE,
                          doc="aerodynamic response rate p1, 1/s: the velocity relaxes to the wind in 1/p1")
    p2_1_s: float = param(0.02, check=_POSITIVE, doc="width p2 of the wind-fluctuation spectrum, 1/s")
    sigma_a_m_s2: float = param(0.15, check=_NONNEG,
                                doc="stationary std of the horizontal gust acceleration (per axis), m/s^2")
    sigma_a_vertical_m_s2: float = param(0.1, check=_NONNEG,
                                         doc="stationary std of the vertical gust acceleration, m/s^2")
    vertical_relax_rate_1_s: float = param(0.2, check=_POSITIVE,
                                           doc="rate at which the vertical speed relaxes to its target, 1/s (0.2: in 5 s)")
    wind_alt_m: tuple = param(_WIND_ALT_M, check=_altitude_knots,
                              doc="altitude knots of the mean wind profile, strictly increasing, m")
    wind_speed_m_s: tuple = param(_WIND_SPEED_M_S, check=as_given(array(lo=0.0, what="finite wind speeds >= 0")),
                                  doc="mean wind speed at each altitude knot, m/s (>= 0)")
    wind_from_rad: tuple = param(tuple(math.radians(d) for d in _WIND_FROM_DEG),
                                 check=as_given(array(what="finite directions")),
                                 doc="direction the wind blows FROM, clockwise from north (meteorological), rad: a "
                                     "scalar or one per altitude knot")

    def __post_init__(self):
        validate(self)
        n = len(self.wind_alt_m)
        require(np.shape(self.wind_speed_m_s) == (n,), "wind_speed_m_s",
                f"expected one value per altitude knot ({n}), got shape {np.shape(self.wind_speed_m_s)}")
        require(np.ndim(self.wind_from_rad) == 0 or np.shape(self.wind_from_rad) == (n,), "wind_from_rad",
                f"expected a scalar or one value per altitude knot ({n}), got shape {np.shape(self.wind_from_rad)}")

    @classmethod
    def with_wind_scale(cls, scale: float):
        """The default parameters with the wind profile's speeds x scale."""
        return cls(wind_speed_m_s=tuple(scale * v for v in cls().wind_speed_m_s))

    def wind_enu_m_s(self, h_m) -> np.ndarray:
        """Mean wind (..., 2) [east, north] at altitude(s) h_m (linear in components)."""
        alt, spd = np.asarray(self.wind_alt_m, float), np.asarray(self.wind_speed_m_s, float)
        to = np.broadcast_to(np.asarray(self.wind_from_rad, float), alt.shape) + math.pi
        h = np.asarray(h_m, dtype=float)
        return np.stack([np.interp(h, alt, spd * np.sin(to)), np.interp(h, alt, spd * np.cos(to))], axis=-1)


# ---------------------------------------------------------------------------
# outputs


class SondeState(NamedTuple):
    """One epoch of a batch of sondes (batch shape (...))."""

    t_gps_s: float
    pos_ecef_m: np.ndarray  # (..., 3)
    vel_ecef_m_s: np.ndarray  # (..., 3)
    acc_ecef_m_s2: np.ndarray  # (..., 3) total acceleration (mean-wind response + gusts)
    lat_rad: np.ndarray
    lon_rad: np.ndarray
    alt_m: np.ndarray  # ellipsoidal height
    vel_enu_m_s: np.ndarray  # (..., 3) in the local ENU frame at the sonde
    acc_enu_m_s2: np.ndarray  # (..., 3)
    gust_acc_enu_m_s2: np.ndarray  # (..., 3) the Gauss-Markov part a_g of the acceleration
    phase: np.ndarray  # int8: ASCENT 0, DESCENT 1, LANDED 2
    ground_range_m: np.ndarray  # great-circle distance from the launch site


@dataclass(frozen=True, eq=False)
class SondeTrack:
    """A flight: every SondeState field stacked on a leading time axis T, plus constants."""

    t_gps_s: np.ndarray  # (T,)
    pos_ecef_m: np.ndarray  # (T, ..., 3)
    vel_ecef_m_s: np.ndarray
    acc_ecef_m_s2: np.ndarray
    lat_rad: np.ndarray  # (T, ...)
    lon_rad: np.ndarray
    alt_m: np.ndarray
    vel_enu_m_s: np.ndarray
    acc_enu_m_s2: np.ndarray
    gust_acc_enu_m_s2: np.ndarray
    phase: np.ndarray
    ground_range_m: np.ndarray
    burst_alt_m: np.ndarray  # (...)
    launch_pos_ecef_m: np.ndarray  # (..., 3)

    def __len__(self) -> int:
        return self.t_gps_s.size

    def epoch(self, k: int) -> SondeState:
        return SondeState(float(self.t_gps_s[k]), *(getattr(self, f)[k] for f in SondeState._fields[1:]))

    def sonde(self, index) -> SondeTrack:
        """The track of one sonde (or a sub-batch): index into the batch axes."""
        idx = index if isinstance(index, tuple) else (index,)
        out = {}
        for f in fields(self):
            a = getattr(self, f.name)
            if f.name == "t_gps_s":
                out[f.name] = a
            elif f.name in ("burst_alt_m", "launch_pos_ecef_m"):
                out[f.name] = a[idx]
            else:
                out[f.name] = a[(slice(None),) + idx]
        return SondeTrack(**out)


# ---------------------------------------------------------------------------
# the flight


def _check_rng(rng, n: int):
    """-> (single Generator or None, list of per-sonde Generators or None)."""
    if isinstance(rng, np.random.Generator):
        return rng, None
    if isinstance(rng, (str, bytes)) or not isinstance(rng, Sequence):
        raise ValueError(f"rng: expected a numpy.random.Generator or a sequence of them, got {type(rng).__name__}")
    gens = list(rng)
    if not all(isinstance(g, np.random.Generator) for g in gens):
        raise ValueError("rng: every element of the sequence must be a numpy.random.Generator")
    if len(gens) != n:
        raise ValueError(f"rng: expected one Generator per sonde ({n}), got {len(gens)}")
    return None, gens


def _radii(lat):
    s2 = np.sin(lat) ** 2
    w = np.sqrt(1.0 - WGS84.e2 * s2)
    return WGS84.a_m * (1.0 - WGS84.e2) / w**3, WGS84.a_m / w  # M (meridian), N (prime vertical)


# ---------------------------------------------------------------------------
# compiled flight loop: the same arithmetic as SondeFlight._advance, sonde by sonde


def _flight_block_py(M, Z, lat, lon, h, phase, burst, h0, table, z0, dz, ascent, dt, a_m, e2, noise,
                     rec_lat, rec_lon, rec_h, rec_vz, rec_ph):
    m, B, G = noise.shape[0], Z.shape[0], table.shape[0]
    o = np.empty((3, 3))
    for j in range(m):
        for b in range(B):
            if phase[b] != 2:  # LANDED sondes stay put
                x = (h[b] + 0.5 * dt * Z[b, 2, 0] - z0) * (1.0 / dz)
                x = min(max(x, 0.0), G - 1.0)
                i = min(int(x), G - 2)
                f = x - i
                for c in range(3):
                    Z[b, c, 2] = table[i, c] * (1.0 - f) + table[i + 1, c] * f
                if phase[b] == 0:
                    Z[b, 2, 2] = ascent
                for c in range(3):
                    for r in range(3):
                        Z[b, c, 3 + r] = noise[j, b, c, r]
                for c in range(3):
                    for r in range(3):
                        acc = 0.0
                        for q in range(6):
                            acc += M[c, r, q] * Z[b, c, q]
                        o[c, r] = acc
                h_mid = h[b] + 0.5 * o[2, 0]
                w = math.sqrt(1.0 - e2 * math.sin(lat[b]) ** 2)
                dlat = o[1, 0] / (a_m * (1.0 - e2) / (w * w * w) + h_mid)
                lon[b] = lon[b] + o[0, 0] / ((a_m / w + h_mid) * math.cos(lat[b] + 0.5 * dlat))
                lat[b] = lat[b] + dlat
                h_new = h[b] + o[2, 0]
                for c in range(3):
                    Z[b, c, 0] = o[c, 1]
                    Z[b, c, 1] = o[c, 2]
                if phase[b] == 0 and h_new >= burst[b]:
                    phase[b] = 1
                if phase[b] == 1 and h_new <= h0[b]:
                    phase[b] = 2
                    h_new = h0[b]
                    for c in range(3):
                        Z[b, c, 0] = 0.0
                        Z[b, c, 1] = 0.0
                h[b] = h_new
            rec_lat[j, b] = lat[b]
            rec_lon[j, b] = lon[b]
            rec_h[j, b] = h[b]
            rec_ph[j, b] = phase[b]
            for c in range(3):
                rec_vz[j, b, c, 0] = Z[b, c, 0]
                rec_vz[j, b, c, 1] = Z[b, c, 1]


_flight_block = None if _nb is None else _nb.njit(cache=True, nogil=True)(_flight_block_py)


class SondeFlight:
    """A batch of radiosonde flights stepped in simulation time.

    Parameters
    ----------
    rng : numpy.random.Generator, or a sequence of one Generator per sonde (see the
        module docstring: per-sonde streams make a batch equal to separate runs).
    launch_lat_rad, launch_lon_rad, launch_h_m : launch site(s), broadcast to the batch.
    t0_gps_s : launch time (GPS s).
    params : SondeParams.
    dt_s : step (default 1 s); the discretisation is exact for any step.
    batch_shape : batch shape; default: the launch arrays' broadcast shape, or (len(rng),)
        when rng is a sequence and the sites are scalars.
    burst_alt_m : optional fixed burst altitudes (...) instead of drawing them (the draw
        is then skipped).
    backend : 'auto' (numba when installed), 'numba' or 'numpy'.  The numpy step
        (``_advance``) is the reference; the compiled loop does the same arithmetic
        sonde by sonde (agreement to rounding, ~1e-9 m over a flight, is tested).
    """

    def __init__(self, rng, *, launch_lat_rad=DEFAULT_LAUNCH_LAT_RAD, launch_lon_rad=DEFAULT_LAUNCH_LON_RAD,
                 launch_h_m=DEFAULT_LAUNCH_H_M, t0_gps_s: float = DEFAULT_TOA_GPS_S,
                 params: SondeParams | None = None, dt_s: float = 1.0, batch_shape=None, burst_alt_m=None,
                 backend: str = "auto"):
        if backend not in ("auto", "numba", "numpy"):
            raise ValueError(f"backend must be 'auto', 'numba' or 'numpy', got {backend!r}")
        if backend == "numba" and _flight_block is None:
            raise ValueError("backend='numba' needs numba installed")
        self.backend = ("numba" if _flight_block is not None else "numpy") if backend == "auto" else backend
        self.params = p = SondeParams() if params is None else params
        if not isinstance(p, SondeParams):
            raise ValueError(f"params: expected a SondeParams, got {type(p).__name__}")
        self.dt_s = _POSITIVE("dt_s", dt_s)
        try:
            t0 = float(t0_gps_s)
        except (TypeError, ValueError):
            raise ValueError(f"t0_gps_s must be a number of GPS seconds, got {t0_gps_s!r}") from None
        if not math.isfinite(t0):
            raise ValueError(f"t0_gps_s must be finite, got {t0_gps_s!r}")
        site = []
        for name, v in (("launch_lat_rad", launch_lat_rad), ("launch_lon_rad", launch_lon_rad),
                        ("launch_h_m", launch_h_m)):
            try:
                a = np.asarray(v, dtype=float)
            except (TypeError, ValueError):
                raise ValueError(f"{name} must be a number or an array of numbers") from None
            if not np.all(np.isfinite(a)):
                raise ValueError(f"{name} must be finite")
            site.append(a)
        if np.any(np.abs(site[0]) > math.pi / 2):
            raise ValueError("launch_lat_rad must lie in [-pi/2, pi/2] (degrees passed?)")
        if np.any(site[2] < Z_MIN_M) or np.any(site[2] > 10_000.0):
            raise ValueError(f"launch_h_m must lie in [{Z_MIN_M:.0f}, 10000] m")
        site_shape = np.broadcast_shapes(*(a.shape for a in site))
        if batch_shape is None:
            if site_shape == () and not isinstance(rng, np.random.Generator) and isinstance(rng, Sequence):
                batch_shape = (len(rng),)
            else:
                batch_shape = site_shape
        try:
            self.batch_shape = tuple(int(n) for n in batch_shape)
        except (TypeError, ValueError):
            raise ValueError(f"batch_shape must be a tuple of ints, got {batch_shape!r}") from None
        if any(n < 1 for n in self.batch_shape):
            raise ValueError(f"batch_shape must have positive sizes, got {batch_shape!r}")
        try:
            site = [np.broadcast_to(a, self.batch_shape).reshape(-1).copy() for a in site]
        except ValueError:
            raise ValueError(f"launch site arrays of shape {site_shape} do not broadcast to batch_shape "
                             f"{self.batch_shape}") from None
        B = self.n = int(np.prod(self.batch_shape, dtype=int))
        self._rng, self._gens = _check_rng(rng, B)
        self._lat0, self._lon0, self._h0 = site
        self.launch_pos_ecef_m = geodetic_to_ecef(*site).reshape(self.batch_shape + (3,))
        m0, n0 = _radii(self._lat0)
        self._r_gauss = np.sqrt(m0 * n0)

        # per-sonde initial draws: burst altitude, then stationary gust accelerations
        lo, hi = (float(x) for x in p.burst_alt_range_m)
        sig = np.array([p.sigma_a_m_s2, p.sigma_a_m_s2, p.sigma_a_vertical_m_s2])
        if burst_alt_m is not None:
            try:
                burst = np.broadcast_to(np.asarray(burst_alt_m, dtype=float), self.batch_shape).reshape(-1).copy()
            except (TypeError, ValueError):
                raise ValueError(f"burst_alt_m must broadcast to the batch shape {self.batch_shape}") from None
            if not np.all(np.isfinite(burst)) or np.any(burst > 50_000.0) or np.any(burst <= self._h0):
                raise ValueError("burst_alt_m must be finite, above the launch height and <= 50 km")
            n0 = self._normals((3,))
        elif self._rng is not None:
            burst = self._rng.uniform(lo, hi, B)
            n0 = self._rng.standard_normal((B, 3))
        else:
            burst, n0 = np.empty(B), np.empty((B, 3))
            for i, g in enumerate(self._gens):
                burst[i] = g.uniform(lo, hi)
                n0[i] = g.standard_normal(3)
        if np.any(burst <= self._h0):
            raise ValueError("burst_alt_range_m must lie above the launch height")
        self._burst = burst

        # exact per-axis discretisation: east, north (relax p1), up (relax k_v); one step is
        # [dx, v, a_g](k+1) = M_axis @ [v, a_g, u, n0, n1, n2](k), M = [Phi[:, 1:] | Gamma | L]
        beta = p.p1_1_s + p.p2_1_s
        dh = axis_discretisation(p.p1_1_s, beta, p.sigma_a_m_s2, self.dt_s)
        dv = axis_discretisation(p.vertical_relax_rate_1_s, beta, p.sigma_a_vertical_m_s2, self.dt_s)
        self._M = np.stack([np.column_stack([d[0][:, 1:], d[1], d[3]]) for d in (dh, dh, dv)])  # (3, 3, 6)
        self._relax = np.array([p.p1_1_s, p.p1_1_s, p.vertical_relax_rate_1_s])
        # target table: wind east, wind north, -descent speed, on the altitude grid
        wind = p.wind_enu_m_s(_GRID_M)
        self._table = np.column_stack([wind, -p.descent_rate_sl_m_s * np.exp(_LOG_DESCENT_RATIO)])

        # state: position (geodetic), Z = [v, a_g, u, noise x3] per axis, phase
        self._k = 0
        self._t0 = t0
        self._lat, self._lon, self._h = self._lat0.copy(), self._lon0.copy(), self._h0.copy()
        self._Z = np.zeros((B, 3, 6))
        self._Z[:, 2, 0] = p.ascent_rate_m_s  # released from rest horizontally, climbing
        self._Z[:, :, 1] = n0 * sig
        self._phase = np.full(B, ASCENT, dtype=np.int8)
        self._n_landed = 0
        self._noise_buf = np.empty((0, B, 3, 3))

    # -- randomness ---------------------------------------------------------

    def _normals(self, shape) -> np.ndarray:
        if self._rng is not None:
            return self._rng.standard_normal((self.n,) + shape)
        return np.stack([g.standard_normal(shape) for g in self._gens])

    def _noise(self, k: int) -> np.ndarray:
        """The next k steps of unit normals (k, B, 3, 3), from the buffer then fresh blocks."""
        while self._noise_buf.shape[0] < k:
            m = max(_BLOCK_STEPS, k - self._noise_buf.shape[0])
            if self._rng is not None:
                blk = self._rng.standard_normal((m, self.n, 3, 3))
            else:
                blk = np.stack([g.standard_normal((m, 3, 3)) for g in self._gens], axis=1)
            self._noise_buf = np.concatenate([self._noise_buf, blk])
        out, self._noise_buf = self._noise_buf[:k], self._noise_buf[k:]
        return out

    # -- dynamics -----------------------------------------------------------

    @property
    def t_gps_s(self) -> float:
        return self._t0 + self._k * self.dt_s

    @property
    def burst_alt_m(self) -> np.ndarray:
        return self._burst.reshape(self.batch_shape).copy()

    @property
    def all_landed(self) -> bool:
        return self._n_landed == self.n

    def _targets(self, h, phase) -> np.ndarray:
        """Inputs u (..., 3): mean wind east/north and the vertical speed target at h."""
        u = _grid_lookup(self._table, h)
        asc = phase == ASCENT
        u[..., 2] = np.where(asc, self.params.ascent_rate_m_s, u[..., 2])
        return u

    def _acc_enu(self, h, v, ag, phase) -> np.ndarray:
        """Continuous-time acceleration (..., 3) of states (0 once landed)."""
        a = self._relax * (self._targets(h, phase) - v) + ag
        a[phase == LANDED] = 0.0
        return a

    def _advance(self, noise: np.ndarray) -> None:
        """One step of dt with unit normals noise (B, 3, 3)."""
        Z, h, dt = self._Z, self._h, self.dt_s
        Z[:, :, 2] = self._targets(h + (0.5 * dt) * Z[:, 2, 0], self._phase)
        Z[:, :, 3:] = noise
        out = np.matmul(self._M, Z[..., None])[..., 0]  # (B, axis, [dx, v, a_g])
        if self._n_landed:
            out[self._phase == LANDED] = 0.0
        dx = out[..., 0]
        # geodetic update: radii at the current latitude, mid-step height and latitude
        h_mid = h + 0.5 * dx[:, 2]
        s2 = np.sin(self._lat) ** 2
        w = np.sqrt(1.0 - WGS84.e2 * s2)
        dlat = dx[:, 1] / (WGS84.a_m * (1.0 - WGS84.e2) / (w * w * w) + h_mid)
        self._lon = self._lon + dx[:, 0] / ((WGS84.a_m / w + h_mid) * np.cos(self._lat + 0.5 * dlat))
        self._lat = self._lat + dlat
        h_new = h + dx[:, 2]
        Z[:, :, :2] = out[..., 1:]
        asc = self._phase == ASCENT
        burst = asc & (h_new >= self._burst)
        if burst.any():
            self._phase[burst] = DESCENT
        if not asc.all():
            landing = (self._phase == DESCENT) & (h_new <= self._h0)
            if landing.any():
                self._phase[landing] = LANDED
                h_new[landing] = self._h0[landing]
                Z[landing, :, :2] = 0.0
                self._n_landed = int(np.count_nonzero(self._phase == LANDED))
        self._h = h_new
        self._k += 1

    def _run(self, m: int):
        """Advance m steps; returns the per-step records (lat, lon, h, [v, a_g], phase)."""
        B = self.n
        noise = self._noise(m)
        rec = (np.empty((m, B)), np.empty((m, B)), np.empty((m, B)), np.empty((m, B, 3, 2)),
               np.empty((m, B), np.int8))
        if self.backend == "numba":
            _flight_block(self._M, self._Z, self._lat, self._lon, self._h, self._phase, self._burst, self._h0,
                          self._table, _GRID_Z0_M, _GRID_DZ_M, float(self.params.ascent_rate_m_s), self.dt_s,
                          WGS84.a_m, WGS84.e2, noise, *rec)
            self._k += m
            self._n_landed = int(np.count_nonzero(self._phase == LANDED))
        else:
            for j in range(m):
                self._advance(noise[j])
                rec[0][j], rec[1][j], rec[2][j], rec[3][j], rec[4][j] = (
                    self._lat, self._lon, self._h, self._Z[:, :, :2], self._phase)
        return rec

    def _snapshot(self):
        return (self._lat.copy(), self._lon.copy(), self._h.copy(), self._Z[:, :, 0].copy(),
                self._Z[:, :, 1].copy(), self._phase.copy())

    def _outputs(self, t, lat, lon, h, v_enu, ag, phase, lead=()):
        """ECEF outputs from geodetic/ENU arrays of shape lead + (B,) [+ (3,)]."""
        shp = lead + self.batch_shape
        lon = np.where(np.abs(lon) > math.pi, np.mod(lon + math.pi, 2.0 * math.pi) - math.pi, lon)
        a_enu = self._acc_enu(h, v_enu, ag, phase)
        pos = geodetic_to_ecef(lat, lon, h)
        r = enu_rotation(lat, lon)  # (..., 3, 3), rows e, n, u
        vel = np.einsum("...ji,...j->...i", r, v_enu)
        m, n = _radii(lat)
        sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
        lat_dot = v_enu[..., 1] / (m + h)
        lon_dot = v_enu[..., 0] / ((n + h) * cl)
        z = np.zeros_like(lat)
        de = np.stack([-co, -so, z], -1) * lon_dot[..., None]
        dn = (np.stack([-cl * co, -cl * so, -sl], -1) * lat_dot[..., None]
              + np.stack([sl * so, -sl * co, z], -1) * lon_dot[..., None])
        du = (np.stack([-sl * co, -sl * so, cl], -1) * lat_dot[..., None]
              + np.stack([-cl * so, cl * co, z], -1) * lon_dot[..., None])
        acc = (np.einsum("...ji,...j->...i", r, a_enu)
               + v_enu[..., 0:1] * de + v_enu[..., 1:2] * dn + v_enu[..., 2:3] * du)
        # great-circle distance on the launch site's Gaussian sphere (haversine)
        dlat, dlon = lat - self._lat0, np.mod(lon - self._lon0 + math.pi, 2.0 * math.pi) - math.pi
        hav = np.sin(dlat / 2) ** 2 + np.cos(lat) * np.cos(self._lat0) * np.sin(dlon / 2) ** 2
        rng_m = 2.0 * self._r_gauss * np.arcsin(np.sqrt(np.clip(hav, 0.0, 1.0)))
        vec = lambda a: a.reshape(shp + (3,))
        sca = lambda a: a.reshape(shp)
        return (t, vec(pos), vec(vel), vec(acc), sca(lat), sca(lon), sca(h), vec(v_enu), vec(a_enu),
                vec(ag), sca(phase), sca(rng_m))

    def state(self) -> SondeState:
        """The current state (no time advance)."""
        return SondeState(*self._outputs(self.t_gps_s, *self._snapshot()))

    def step(self) -> SondeState:
        """Advance by dt_s and return the new state."""
        self._run(1)
        return self.state()

    def simulate(self, n_steps: int | None = None, *, until_landed: bool = False,
                 max_duration_s: float = 6 * 3600.0) -> SondeTrack:
        """The current state followed by n_steps further ones (T = n_steps + 1).

        until_landed=True: step until every sonde has landed (or max_duration_s has
        elapsed since the current time); n_steps must then be None.  The flight is the
        same as with repeated ``step`` calls (same noise, same order).
        """
        if until_landed:
            if n_steps is not None:
                raise ValueError("n_steps must be None when until_landed=True")
            k_max = math.ceil(_POSITIVE("max_duration_s", max_duration_s) / self.dt_s)
        else:
            if n_steps is None or isinstance(n_steps, bool) or int(n_steps) != n_steps or n_steps < 0:
                raise ValueError(f"n_steps must be an integer >= 0, got {n_steps!r}")
            k_max = int(n_steps)
        cols = [[c] for c in self._snapshot()]
        k_start, k = self._k, 0
        while k < k_max and not (until_landed and self.all_landed):
            m = min(k_max - k, _BLOCK_STEPS if not until_landed else 60)
            lat, lon, h, vz, ph = self._run(m)
            for c, new in zip(cols, (lat, lon, h, vz[..., 0], vz[..., 1], ph)):
                c.append(new)
            k += m
        cols = [np.concatenate([c[0][None]] + c[1:]) for c in cols]
        times = self._t0 + self.dt_s * np.arange(k_start, self._k + 1)
        out = self._outputs(times, *cols, lead=(times.size,))
        return SondeTrack(*out, burst_alt_m=self.burst_alt_m, launch_pos_ecef_m=self.launch_pos_ecef_m.copy())
