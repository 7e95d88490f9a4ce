"""Guidance laws that close the loop on the vehicle's position: a holding pattern about a fixed
centre (racetrack or circle) and a waypoint mission."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from filters.params import ParamError, number, param, require, validate
from sitl.constants import Ellipsoid, ellipsoid

from .geometry import _center_offset, _radii, wrap_pi
from .kernels import _LAW_RACETRACK, _LAW_WAYPOINTS, _N_PARAMS
from .values import _FINITE, _GAIN, _NONNEG, _POSITIVE, _broadcast, _latitudes, _readonly, _shown


@dataclass(frozen=True, eq=False)
class Racetrack:
    """A holding pattern flown clockwise at constant speed, level: a racetrack (stadium) about a
    fixed centre -- two straight legs of length 2 half_length_m parallel to the axis (heading
    axis_rad), radius_m either side of it, joined by half circles of radius_m about the axis'
    ends -- or with half_length_m = 0 a circle of radius_m about the centre (an orbit).  Held by
    guidance (what an autopilot's loiter / racetrack mode does), evaluated at every RK4 stage:

        (d_e, d_n): the centre's offset from the vehicle, local flat metres (as WaypointMission's)
        s = -(d_e sin a + d_n cos a), c = -(d_e cos a - d_n sin a)   (vehicle along / right of the axis a)
        |s| > L: about the near end's centre g = (d_e, d_n) + sign(s) L (sin a, cos a), d = |g|:
            psi_ref = atan2(g_e, g_n) - pi/2 + atan(radial_gain (d - r) / r),   feed-forward v / r
        |s| <= L, c < 0 (the leg along a):   psi_ref = a - atan(radial_gain (c + r) / r),   feed-forward 0
        |s| <= L, c >= 0 (the leg back):     psi_ref = a + pi - atan(radial_gain (r - c) / r)
        psi' = clip(feed-forward + turn_gain wrap(psi_ref - psi), -max_turn_rate, +max_turn_rate),
        v_u = 0, v = speed_m_s.

    On the pattern (heading along it) that is the feed-forward alone: straight legs, turns at
    v / r.  Off it the heading is tilted towards it; linearised on a circle the radial error e
    obeys e'' + turn_gain e' + (v^2 / r^2 + turn_gain radial_gain v / r) e = 0 (stable; at the
    defaults and v / r = 100 m/s / 15 km, time constants ~11 s and ~130 s).  Why guidance and not
    constant turns on a schedule (LegsAndTurns): the heading is relative to local north, and
    along an east-west displacement north itself turns by sin(lat) dlon, so a constant heading
    rate is not a constant geodesic curvature, and the error comes back every loop: a constant
    turn's circle walks ~pi r^2 tan(lat) / R_E per loop (measured: ~110 m per loop at r = 15 km,
    lat 45 deg, ~2.5 km in 6 h), the scheduled racetrack of the same size as the default
    beacon's ~41 m per loop (~1.4 km in 6 h).  Here both stay on the pattern (measured: within
    ~20 m of the nominal circle over 6 h).

    center_lat_rad, center_lon_rad, radius_m, speed_m_s, axis_rad, half_length_m broadcast to
    the batch shape.
    """

    center_lat_rad: Any = param(check=_latitudes, doc="geodetic latitude of the pattern's centre, rad")
    center_lon_rad: Any = param(check=_FINITE, doc="longitude of the pattern's centre, rad")
    radius_m: Any = param(check=_POSITIVE,
                          doc="turn radius (a circle's radius), m (> 0, >= speed_m_s / max_turn_rate_rad_s)")
    speed_m_s: Any = param(check=_POSITIVE, doc="speed, m/s (> 0)")
    axis_rad: Any = param(0.0, check=_FINITE, doc="heading of the first straight leg, clockwise from north, rad")
    half_length_m: Any = param(0.0, check=_NONNEG, doc="half the straight legs' length, m (0: a circle)")
    max_turn_rate_rad_s: Any = param(math.radians(3.0), check=_POSITIVE, doc="turn-rate bound, rad/s (> 0)")
    turn_gain_1_s: float = param(0.1, check=_GAIN, doc="heading-error gain of the turn rate, 1/s (> 0)")
    radial_gain: float = param(1.0, check=number(0.0),
                               doc="gain of the reference heading's tilt towards the pattern per unit of radial "
                                   "error (relative to radius_m), dimensionless (>= 0)")
    batch_shape: tuple = field(init=False)

    _FIELDS = ("center_lat_rad", "center_lon_rad", "radius_m", "speed_m_s", "axis_rad", "half_length_m",
               "max_turn_rate_rad_s")

    def __post_init__(self):
        validate(self)
        object.__setattr__(self, "batch_shape", _broadcast(self, self._FIELDS))
        require(not np.any(self.speed_m_s / self.radius_m > self.max_turn_rate_rad_s), "radius_m",
                "expected values >= speed_m_s / max_turn_rate_rad_s (the tightest turn the turn rate allows), "
                f"got {_shown(self.radius_m)}")

    @classmethod
    def orbit_through(cls, lat_rad, lon_rad, center_lat_rad, center_lon_rad, speed_m_s, **kw) -> "Racetrack":
        """Circles (half_length 0) about one centre through the start points (lat_rad, lon_rad)
        (arrays of the batch shape): each radius is its start's distance from the centre (the
        guidance's own measure, at h = 0), so every vehicle starts on its circle (and, with
        :meth:`initial_heading`, along it)."""
        lat, lon = np.broadcast_arrays(_FINITE("lat_rad", lat_rad), _FINITE("lon_rad", lon_rad))
        d_e, d_n = _center_offset(lat, lon, np.zeros(lat.shape), float(center_lat_rad), float(center_lon_rad),
                                  ellipsoid(None))
        r = np.hypot(d_e, d_n)
        if np.any(r < 1.0):
            raise ValueError(f"a start point lies at the centre (radius {float(np.min(r)):.3g} m): no circle")
        return cls(np.full(lat.shape, float(center_lat_rad)), np.full(lat.shape, float(center_lon_rad)), r,
                   speed_m_s, **kw)

    def _reference(self, y, ell):
        """(psi_ref, feed-forward rate) at the states y (..., 4) (class docstring)."""
        d_e, d_n = _center_offset(y[..., 0], y[..., 1], y[..., 2], self.center_lat_rad, self.center_lon_rad, ell)
        sa, ca = np.sin(self.axis_rad), np.cos(self.axis_rad)
        s = -(d_e * sa + d_n * ca)
        c = -(d_e * ca - d_n * sa)
        r, L, k = self.radius_m, self.half_length_m, self.radial_gain
        end = np.where(s > 0, L, -L)
        g_e, g_n = d_e + end * sa, d_n + end * ca
        turn = (s > L) | (s < -L)
        ref = np.where(turn, np.arctan2(g_e, g_n) - 0.5 * np.pi + np.arctan(k * (np.hypot(g_e, g_n) - r) / r),
                       np.where(c < 0, self.axis_rad - np.arctan(k * (c + r) / r),
                                self.axis_rad + np.pi - np.arctan(k * (r - c) / r)))
        return ref, np.where(turn, self.speed_m_s / r, 0.0)

    def initial_heading(self, t_s, y):
        """Along the pattern (the reference heading at the start)."""
        return np.mod(self._reference(y, ellipsoid(None))[0], 2.0 * np.pi)

    def target(self, state, t_next_s=None):
        return None

    def commands(self, t_s, y, aux=None, ell: Ellipsoid | None = None):
        ref, ff = self._reference(y, ellipsoid(ell))
        rate = np.clip(ff + self.turn_gain_1_s * wrap_pi(ref - y[..., 3]), -self.max_turn_rate_rad_s,
                       self.max_turn_rate_rad_s)
        return self.speed_m_s, np.zeros(self.batch_shape), rate

    def advance(self, state, ell):
        return state.wp_index

    def _kernel_args(self):
        n = int(np.prod(self.batch_shape, dtype=np.int64))
        p = np.zeros((n, _N_PARAMS))
        p[:, :9] = np.stack([np.ravel(self.speed_m_s), np.ravel(self.max_turn_rate_rad_s), np.ravel(self.radius_m),
                             np.full(n, self.turn_gain_1_s), np.full(n, self.radial_gain),
                             np.ravel(self.center_lat_rad), np.ravel(self.center_lon_rad), np.ravel(self.axis_rad),
                             np.ravel(self.half_length_m)], axis=-1)
        return _LAW_RACETRACK, p, {}


def _waypoint_lists(key: str, value) -> tuple:
    """One (K_i >= 1, 3) array [lat_rad, lon_rad, h_m] per vehicle (a single (K, 3) array: one
    vehicle), latitudes in [-pi/2, pi/2]: a tuple of read-only float arrays."""
    try:
        wps = list(value) if not isinstance(value, np.ndarray) else ([value] if value.ndim == 2 else list(value))
    except TypeError:
        raise ParamError(key, f"expected one waypoint list per vehicle, got {_shown(value)}") from None
    if not wps:
        raise ParamError(key, "expected one waypoint list per vehicle, got none")
    out = []
    for i, w in enumerate(wps):
        k = f"{key}[{i}]"
        a = _FINITE(k, w)
        if a.ndim != 2 or a.shape[-1] != 3 or a.shape[0] < 1:
            raise ParamError(k, f"expected shape (K >= 1, 3) [lat_rad, lon_rad, h_m], got {a.shape}")
        if np.any(np.abs(a[:, 0]) > np.pi / 2):
            raise ParamError(k, f"expected latitudes in [-pi/2, pi/2] rad (degrees passed?), got {_shown(a[:, 0])}")
        out.append(a)
    return tuple(out)


@dataclass(frozen=True, eq=False)
class WaypointMission:
    """Fly geodetic waypoints in order at a commanded speed with bounded turn and climb rates.

    waypoints_rad_m: one (K_i, 3) array [lat_rad, lon_rad, h_m] per vehicle (batch shape (n,)).
    Guidance towards the current waypoint (lat_w, lon_w, h_w), evaluated at every RK4 stage:

        d_n = (lat_w - lat)(M + h),  d_e = wrap(lon_w - lon)(N + h) cos(lat)   (local flat bearing)
        psi' = clip(turn_gain * wrap(atan2(d_e, d_n) - psi), -max_turn_rate, +max_turn_rate)
        v_u  = clip(climb_gain * (h_w - h), -max_climb, +max_climb),   v = speed_m_s.

    After each integration step a vehicle whose horizontal distance to its waypoint is below
    accept_radius_m moves on to the next one; after the last it keeps pursuing the last
    waypoint (passes and turns back over it: a loiter).  Pure pursuit with a bounded turn
    rate cannot hit a point inside its turning circle (radius speed / max_turn_rate): keep
    consecutive waypoints further apart than about twice that radius, or widen
    accept_radius_m.
    """

    waypoints_rad_m: Sequence = param(check=_waypoint_lists,
                                      doc="one waypoint list per vehicle, each a (K_i >= 1, 3) array [lat_rad, lon_rad, "
                                          "h_m] (geodetic latitude and longitude in rad, ellipsoidal height in m; one "
                                          "(K, 3) array: one vehicle); stored as a tuple of read-only arrays")
    speed_m_s: Any = param(check=_POSITIVE, doc="commanded 3-D speed, m/s (> 0; a scalar or one per vehicle)")
    max_turn_rate_rad_s: Any = param(math.radians(3.0), check=_POSITIVE, doc="turn-rate bound, rad/s (> 0)")
    max_climb_m_s: Any = param(5.0, check=_POSITIVE, doc="climb and sink rate bound, m/s (> 0, < speed_m_s)")
    accept_radius_m: Any = param(150.0, check=_POSITIVE,
                                 doc="a waypoint is reached within this horizontal distance of it, m (> 0)")
    turn_gain_1_s: float = param(0.5, check=_GAIN, doc="heading-error gain of the turn rate, 1/s (> 0)")
    climb_gain_1_s: float = param(0.05, check=_GAIN, doc="height-error gain of the climb rate, 1/s (> 0)")
    batch_shape: tuple = field(init=False)
    _wp: np.ndarray = field(init=False, repr=False)
    _count: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        validate(self)
        arrs = self.waypoints_rad_m
        n, kmax = len(arrs), max(a.shape[0] for a in arrs)
        wp = np.zeros((n, kmax, 3))
        for i, a in enumerate(arrs):
            wp[i, :a.shape[0]] = a
            wp[i, a.shape[0]:] = a[-1]
        object.__setattr__(self, "_wp", _readonly(wp))
        object.__setattr__(self, "_count", np.array([a.shape[0] for a in arrs]))
        object.__setattr__(self, "batch_shape", (n,))
        for name in ("speed_m_s", "max_turn_rate_rad_s", "max_climb_m_s", "accept_radius_m"):
            a = getattr(self, name)
            try:
                a = np.broadcast_to(a, (n,))
            except ValueError:
                raise ParamError(name, f"expected a scalar or shape ({n},), got shape {a.shape}") from None
            object.__setattr__(self, name, _readonly(a))
        require(not np.any(self.max_climb_m_s >= self.speed_m_s), "max_climb_m_s",
                f"expected values < speed_m_s, got {_shown(self.max_climb_m_s)}")

    @property
    def n_waypoints(self) -> np.ndarray:
        return self._count.copy()

    def replace_vehicle(self, i: int, waypoints_rad_m) -> "WaypointMission":
        """The same mission with vehicle i's waypoint list replaced (a mission upload)."""
        if not 0 <= int(i) < self.batch_shape[0]:
            raise ValueError(f"i must be a vehicle index in [0, {self.batch_shape[0]}), got {i!r}")
        wps = list(self.waypoints_rad_m)
        wps[int(i)] = waypoints_rad_m
        return WaypointMission(wps, self.speed_m_s, self.max_turn_rate_rad_s, self.max_climb_m_s,
                               self.accept_radius_m, self.turn_gain_1_s, self.climb_gain_1_s)

    def _goal(self, wp_index):
        idx = np.minimum(np.asarray(wp_index), self._count - 1)
        return self._wp[np.arange(self.batch_shape[0]), idx]  # (n, 3)

    def _offset(self, y, goal, ell):
        m, nn = _radii(y[..., 0], ell)
        d_n = (goal[..., 0] - y[..., 0]) * (m + y[..., 2])
        d_e = wrap_pi(goal[..., 1] - y[..., 1]) * (nn + y[..., 2]) * np.cos(y[..., 0])
        return d_e, d_n

    def initial_heading(self, t_s, y):
        d_e, d_n = self._offset(y, self._goal(np.zeros(self.batch_shape, int)), ellipsoid(None))
        return np.arctan2(d_e, d_n)

    def target(self, state, t_next_s=None):
        return self._goal(state.wp_index)

    def commands(self, t_s, y, aux, ell: Ellipsoid | None = None):
        ell = ellipsoid(ell)
        d_e, d_n = self._offset(y, aux, ell)
        err = wrap_pi(np.arctan2(d_e, d_n) - y[..., 3])
        rate = np.clip(self.turn_gain_1_s * err, -self.max_turn_rate_rad_s, self.max_turn_rate_rad_s)
        climb = np.clip(self.climb_gain_1_s * (aux[..., 2] - y[..., 2]), -self.max_climb_m_s, self.max_climb_m_s)
        return self.speed_m_s, climb, rate

    def advance(self, state, ell):
        """Next waypoint index for vehicles within accept_radius_m of their current one."""
        idx = np.asarray(state.wp_index)
        d_e, d_n = self._offset(state.y, self._goal(idx), ell)
        reached = np.hypot(d_e, d_n) < self.accept_radius_m
        return np.where(reached, np.minimum(idx + 1, self._count), idx)

    def _kernel_args(self):
        p = np.zeros((self.batch_shape[0], _N_PARAMS))
        p[:, :6] = np.stack([self.speed_m_s, self.max_turn_rate_rad_s, self.max_climb_m_s, self.accept_radius_m,
                             np.full(self.batch_shape, self.turn_gain_1_s),
                             np.full(self.batch_shape, self.climb_gain_1_s)], axis=-1)
        return _LAW_WAYPOINTS, p, {"waypoints": self._wp, "count": self._count}
