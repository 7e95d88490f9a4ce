"""UAV kinematics (seed 002): truth trajectories integrated by RK4, batched over vehicles.

State and ODE
-------------
Each vehicle's kinematic state is ``y = [lat_rad, lon_rad, h_m, heading_rad]`` (geodetic
WGS-84 latitude, longitude, ellipsoidal height; heading clockwise from north).  A guidance
law gives, at time t, the 3-D speed v, the climb rate v_u and the heading rate; then

    v_h   = sqrt(v^2 - v_u^2),   v_e = v_h sin(psi),   v_n = v_h cos(psi)
    lat'  = v_n / (M(lat) + h),  lon' = v_e / ((N(lat) + h) cos lat),  h' = v_u,
    psi'  = heading rate,

M, N the meridian and prime-vertical radii of curvature.  The ECEF velocity is the exact
time derivative of geodetic_to_ecef(lat, lon, h): v_ecef = R_enu' [v_e, v_n, v_u]
(dX/dlat = (M + h) north, dX/dlon = (N + h) cos(lat) east, dX/dh = up).  Integrating in
geodetic coordinates keeps the law in the local frame (speed, heading, climb) without an
ECEF -> geodetic iteration at every RK4 stage.  Singular at the poles (cos lat = 0).

The state arrays carry leading batch axes (vehicles, or anything the law's parameters
broadcast to); every vehicle of a swarm is advanced by one vectorised RK4 step.

Guidance laws
-------------
* :class:`SinusoidalLaw` -- the seed 002 example's character: speed
  ``v0 + a sin(w_v t + phi_v)``, climb ``c cos(w_c t + phi_c)``, heading
  ``psi0 + A sin(w_psi t + phi_psi)`` (slow sinusoidal variation, periods ~300-600 s).
* :class:`WaypointMission` -- fly a list of geodetic waypoints at a commanded speed with a
  bounded turn rate and climb rate (the mode a MAVLink mission upload drives).
* :class:`LegsAndTurns` -- straight legs and constant-rate turns on a time schedule.
* :class:`Racetrack` -- a clockwise holding pattern about a fixed centre held by guidance (an
  autopilot's loiter mode): a racetrack, or a circle (:meth:`Racetrack.orbit_through`: each
  vehicle's circle through its start point).
* :class:`Hold` -- a static vehicle (speed 0).
* :class:`PrintedLaw` -- the seed's velocity laws as printed, an ODE of the ECEF position
  itself (state [x, y, z], no geodetic state), integrated by :func:`propagate_printed`
  (RK4) and stepped by :class:`PrintedSwarm`.

How the seed's laws are read (seed 002, the example section "Пример", OCR lines ~426-498)
------------------------------------------------------------------------------------------
The paper prints, for UAV-1..3 and the beacon, the velocity in its Earth-fixed frame
(xi, eta, zeta) as a function of eta and t (r(t) = 6.374e6 + 1500 sin(w_r t),
c = sqrt(1 - eta^2 / r^2)):

    V_xi   = -(a + 0.5 sin 0.02t) eta / r + b cos(w' t) c
    V_eta  = (v0 + 10 sin 0.02t) c + 15 cos(0.01t) eta / r
    V_zeta = (sqrt 3 / 2) [ -(d + sin 0.02t) eta / r + e cos(w' t) c ]

with (a, b, v0, d, e, w', w_r) = UAV-1 (5, 7.5, 100, 10, 15, 0.01, 0.01), UAV-2 (10, 5.5,
110, 10, 15, 0.01, 0.01), UAV-3 (15, 6.5, 110, 20, 19, 0.01, 0.01), beacon (12, 8.5, 115,
25, 17, 0.02, 0.02) (:data:`PRINTED_COEFFS`; the OCR's 5.5, 6.5 and 19 are damaged
digits).  The printed start point (xi0, eta0, zeta0) = (2253549, 4507098, 3903261) m is the
SAME for the three UAVs and the beacon; it is r (cos45 sin30, sin45, cos45 cos30) with
r = 6371 km + 3000 m, i.e. latitude 45, longitude 30 on a sphere, so that

    xi = ECEF y,  eta = ECEF z (the polar axis),  zeta = ECEF x     (:func:`paper_to_ecef`).

Two readings are provided:

* "printed" (:class:`PrintedLaw`, :class:`PrintedSwarm`): the laws exactly as printed,
  integrated by RK4 at 0.01 s in ECEF (the law evaluated in the paper's axes) from the
  printed common start point.  Doubts, stated: the vehicles then climb ~60 m/s (45-51 km
  of height at 1000 s) -- the eta component carries the speed v0 while the xi / zeta
  components carry a tenth of it (a, d ~ v0 / 10), so the velocity is not horizontal;
  all four vehicles (beacon included) leave the same point; some digits are damaged.
  It is what is printed, and the only reading under which the paper's metre-level errors
  are possible (every reading with separate start points leaves the beacon ~250 km away).
* "geodetic" (:func:`example_uav_law`, :data:`EXAMPLE_UAV_START`): the prose's geodetic
  start points (the OCR says longitude 30 / 30.1 / 30.3, latitude 45 / 45.1 / 45.3,
  heights 3000 / 3100 / 3500 m) and the laws' physical content: the V_eta law is exactly
  the polar component of a northward flight at speed v0 + 10 sin(0.02 t) with climb
  15 cos(0.01 t) (north = (.., .., cos lat), up = (.., .., sin lat)), and the printed r(t)
  is the matching altitude h0 + 1500 sin(0.01 t).  So each vehicle flies north at its own
  v0 (100 / 110 / 110 m/s; beacon 115): the formation is not rigid.

SI units, radians inside; no randomness, no clocks: time is the simulation time t_s.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np

from filters.params import Check, ParamError, array, number, param, require, validate

try:  # compiled integration loop; the numpy path below is the reference
    import numba as nb
except ImportError:  # pragma: no cover
    nb = None

from sitl import geodesy
from sitl.constants import Ellipsoid, ellipsoid

__all__ = [
    "SinusoidalLaw",
    "WaypointMission",
    "LegsAndTurns",
    "Racetrack",
    "Hold",
    "KinematicState",
    "VehicleTruth",
    "KinematicSwarm",
    "UavSwarm",
    "geodetic_rates",
    "rk4_step",
    "propagate",
    "initial_state",
    "truth",
    "eta_axis_heading_rad",
    "example_uav_law",
    "example_uav_swarm",
    "EXAMPLE_UAV_START",
    "EXAMPLE_UAV_SPEED_M_S",
    "PRINTED_START_PAPER_M",
    "PRINTED_COEFFS",
    "PrintedLaw",
    "PrintedSwarm",
    "paper_to_ecef",
    "ecef_to_paper",
    "printed_velocity_ecef",
    "propagate_printed",
    "printed_uav_law",
    "printed_uav_swarm",
    "wrap_pi",
]

#: Seed 002 start points of UAV-1..3: (lat deg, lon deg, h m) -- the paper's geodetic values
#: (the OCR: longitude 30 / 30.1 / 30.3, latitude 45 / 45.1 / 45.3).
EXAMPLE_UAV_START = ((45.0, 30.0, 3000.0), (45.1, 30.1, 3100.0), (45.3, 30.3, 3500.0))
#: Mean speeds v0 of UAV-1..3 in the printed V_eta laws, m/s.
EXAMPLE_UAV_SPEED_M_S = (100.0, 110.0, 110.0)
#: The printed start point (xi0, eta0, zeta0), m: the same for UAV-1..3 and the beacon.
PRINTED_START_PAPER_M = (2253549.0, 4507098.0, 3903261.0)
#: Printed law coefficients (a, b, v0, d, e, w', w_r) (module docstring).
PRINTED_COEFFS = {
    "uav1": (5.0, 7.5, 100.0, 10.0, 15.0, 0.01, 0.01),
    "uav2": (10.0, 5.5, 110.0, 10.0, 15.0, 0.01, 0.01),
    "uav3": (15.0, 6.5, 110.0, 20.0, 19.0, 0.01, 0.01),
    "beacon": (12.0, 8.5, 115.0, 25.0, 17.0, 0.02, 0.02),
}


# --------------------------------------------------------------------------- helpers


def wrap_pi(a):
    """Angle(s) wrapped to [-pi, pi)."""
    return np.mod(np.asarray(a, dtype=float) + np.pi, 2.0 * np.pi) - np.pi


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.flags.writeable = False
    return a


def _shown(v) -> str:
    """A value as one short line of text (an array by its first numbers and its shape)."""
    if isinstance(v, np.ndarray):
        if v.size <= 8:
            return repr(v.tolist())
        return f"[{', '.join(f'{x:g}' for x in v.ravel()[:8])}, ...] (shape {v.shape})"
    return repr(v)


def _values(lo: float | None = None, *, lo_open: bool = False, what: str = "finite values") -> Check:
    """Finite numbers as a read-only float array (a scalar, or an array the law broadcasts to
    its batch shape), each >= lo (> lo if lo_open) when lo is given."""
    base = array()

    def test(v):
        try:
            a = base("", v)
        except ParamError:
            a = None
        if a is None or (lo is not None and np.any(a <= lo if lo_open else a < lo)):
            raise ParamError("", f"expected {what}, got {_shown(v)}")
        return a

    return Check(test)


_FINITE = _values()
_NONNEG = _values(0.0, what="finite values >= 0")
_POSITIVE = _values(0.0, lo_open=True, what="finite values > 0")
_GAIN = number(0.0, lo_open=True)  # a positive finite scalar
_STEP = number(0.0, lo_open=True)  # an integration step, s


def _real(key: str, value) -> float:
    """A finite scalar argument (a time, s) as a float."""
    return float(_FINITE(key, value))


def _latitudes(key: str, value) -> np.ndarray:
    """Geodetic latitudes strictly inside (-pi/2, pi/2) rad, as a read-only float array."""
    a = _FINITE(key, value)
    if np.any(np.abs(a) >= np.pi / 2):
        raise ParamError(key, f"expected latitudes in (-pi/2, pi/2) rad (degrees passed?), got {_shown(value)}")
    return a


def _common_shape(named_shapes) -> tuple:
    """The broadcast shape of (field name, shape) pairs; ParamError names the first field whose
    shape does not broadcast with those before it."""
    shape = ()
    for n, s in named_shapes:
        try:
            shape = np.broadcast_shapes(shape, s)
        except ValueError:
            raise ParamError(n, f"expected a shape that broadcasts to {shape} (the fields before it), "
                                f"got shape {s}") from None
    return shape


def _broadcast(obj, names: Sequence[str]) -> tuple:
    """Broadcast the named (checked) array fields to one batch shape, stored read-only."""
    arrays = [getattr(obj, n) for n in names]
    shape = _common_shape((n, a.shape) for n, a in zip(names, arrays))
    for n, a in zip(names, arrays):
        object.__setattr__(obj, n, _readonly(np.broadcast_to(a, shape)))
    return shape


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


# --------------------------------------------------------------------------- guidance laws

# Law codes and the per-vehicle parameter row of the compiled integrator (_integrate_nb).
_LAW_SINUSOID, _LAW_LEGS, _LAW_HOLD, _LAW_WAYPOINTS, _LAW_RACETRACK = 0, 1, 2, 3, 4
_N_PARAMS = 11


@dataclass(frozen=True, eq=False)
class SinusoidalLaw:
    """Speed, climb and heading as sinusoids of time (seed 002 character).

        v(t)   = speed_mean + speed_amp sin(speed_omega t + speed_phase)      (3-D speed)
        v_u(t) = climb_amp cos(climb_omega t + climb_phase)                   (climb rate)
        psi(t) = heading0 + heading_amp sin(heading_omega t + heading_phase)  (heading)

    so the heading rate is heading_amp heading_omega cos(heading_omega t + heading_phase),
    the altitude h0 + (climb_amp / climb_omega) sin(climb_omega t + climb_phase) (when
    climb_phase = 0) and the speed stays in [speed_mean - speed_amp, speed_mean + speed_amp].
    Every field broadcasts to the batch shape (vehicles).  t is the simulation time, s.
    """

    speed_mean_m_s: Any = param(check=_POSITIVE, doc="mean 3-D speed, m/s (> 0)")
    speed_amp_m_s: Any = param(0.0, check=_NONNEG, doc="amplitude of the speed's sinusoid, m/s (< speed_mean_m_s)")
    speed_omega_rad_s: Any = param(0.0, check=_NONNEG, doc="angular frequency of the speed's sinusoid, rad/s")
    speed_phase_rad: Any = param(0.0, check=_FINITE, doc="phase of the speed's sinusoid at t = 0, rad")
    heading0_rad: Any = param(0.0, check=_FINITE, doc="mean heading, clockwise from north, rad")
    heading_amp_rad: Any = param(0.0, check=_NONNEG, doc="amplitude of the heading's sinusoid, rad")
    heading_omega_rad_s: Any = param(0.0, check=_NONNEG, doc="angular frequency of the heading's sinusoid, rad/s")
    heading_phase_rad: Any = param(0.0, check=_FINITE, doc="phase of the heading's sinusoid at t = 0, rad")
    climb_amp_m_s: Any = param(0.0, check=_NONNEG,
                               doc="amplitude of the climb rate's cosine, m/s (< speed_mean_m_s - speed_amp_m_s: the "
                                   "horizontal speed stays > 0)")
    climb_omega_rad_s: Any = param(0.0, check=_NONNEG, doc="angular frequency of the climb rate's cosine, rad/s")
    climb_phase_rad: Any = param(0.0, check=_FINITE, doc="phase of the climb rate's cosine at t = 0, rad")
    batch_shape: tuple = field(init=False)

    _FIELDS = ("speed_mean_m_s", "speed_amp_m_s", "speed_omega_rad_s", "speed_phase_rad", "heading0_rad",
               "heading_amp_rad", "heading_omega_rad_s", "heading_phase_rad", "climb_amp_m_s",
               "climb_omega_rad_s", "climb_phase_rad")

    def __post_init__(self):
        validate(self)
        object.__setattr__(self, "batch_shape", _broadcast(self, self._FIELDS))
        require(not np.any(self.speed_amp_m_s >= self.speed_mean_m_s), "speed_amp_m_s",
                f"expected values < speed_mean_m_s, got {_shown(self.speed_amp_m_s)}")
        require(not np.any(self.climb_amp_m_s >= self.speed_mean_m_s - self.speed_amp_m_s), "climb_amp_m_s",
                "expected values < speed_mean_m_s - speed_amp_m_s (the horizontal speed must stay > 0), "
                f"got {_shown(self.climb_amp_m_s)}")

    def heading_at(self, t_s):
        return self.heading0_rad + self.heading_amp_rad * np.sin(self.heading_omega_rad_s * t_s
                                                                 + self.heading_phase_rad)

    def initial_heading(self, t_s, y):
        return self.heading_at(t_s)

    def target(self, state, t_next_s=None):
        return None

    def commands(self, t_s, y, aux=None):
        """(speed m/s, climb m/s, heading rate rad/s), each of the batch shape."""
        speed = self.speed_mean_m_s + self.speed_amp_m_s * np.sin(self.speed_omega_rad_s * t_s + self.speed_phase_rad)
        climb = self.climb_amp_m_s * np.cos(self.climb_omega_rad_s * t_s + self.climb_phase_rad)
        w = self.heading_omega_rad_s
        rate = self.heading_amp_rad * w * np.cos(w * t_s + self.heading_phase_rad)
        return speed, climb, rate

    def advance(self, state, ell):
        return state.wp_index

    def _kernel_args(self):
        p = np.stack([np.ravel(getattr(self, f)) for f in self._FIELDS], axis=-1)
        return _LAW_SINUSOID, p, {}


def _switch_times(key: str, value) -> np.ndarray:
    """A strictly increasing 1-D array of finite times (read-only)."""
    a = _FINITE(key, value)
    if a.ndim != 1 or (a.size > 1 and np.any(np.diff(a) <= 0)):
        raise ParamError(key, f"expected a strictly increasing 1-D array of times, got {_shown(value)}")
    return a


@dataclass(frozen=True, eq=False)
class LegsAndTurns:
    """Straight legs and constant-rate turns on a time schedule, constant speed, level.

    The heading rate is turn_rates_rad_s[..., j] on the j-th interval of the schedule
    (-inf, switch_times_s[0]), [switch_times_s[0], switch_times_s[1]), ..., [switch_times_s[-1], inf):
    0 on a leg, the turn rate (rad/s, > 0 to the right) in a turn.
    speed_m_s, heading0_rad (heading at the start) broadcast to the batch shape;
    switch_times_s (K,) strictly increasing, turn_rates_rad_s (..., K + 1).
    The integrator cuts its steps at the switch times (``breakpoints_s``) and takes each
    step's interval from its midpoint, so a switch never falls inside an RK4 step.
    """

    speed_m_s: Any = param(check=_NONNEG, doc="speed, m/s (>= 0)")
    heading0_rad: Any = param(check=_FINITE, doc="heading at the start, clockwise from north, rad")
    switch_times_s: Any = param(check=_switch_times, doc="the schedule's switch times (K,), strictly increasing, s")
    turn_rates_rad_s: Any = param(check=_FINITE,
                                  doc="heading rate on each of the K + 1 intervals of the schedule (..., K + 1), "
                                      "rad/s (> 0 to the right; 0 on a leg)")
    batch_shape: tuple = field(init=False)

    def __post_init__(self):
        validate(self)
        sw, tr = self.switch_times_s, self.turn_rates_rad_s
        require(tr.ndim >= 1 and tr.shape[-1] == sw.size + 1, "turn_rates_rad_s",
                f"expected shape (..., {sw.size + 1}) (one rate per interval), got {tr.shape}")
        shape = _common_shape((("speed_m_s", self.speed_m_s.shape), ("heading0_rad", self.heading0_rad.shape),
                               ("turn_rates_rad_s[..., 0]", tr.shape[:-1])))
        object.__setattr__(self, "speed_m_s", _readonly(np.broadcast_to(self.speed_m_s, shape)))
        object.__setattr__(self, "heading0_rad", _readonly(np.broadcast_to(self.heading0_rad, shape)))
        object.__setattr__(self, "turn_rates_rad_s", _readonly(np.broadcast_to(tr, shape + tr.shape[-1:])))
        object.__setattr__(self, "batch_shape", shape)

    breakpoints_s = property(lambda self: self.switch_times_s)

    def initial_heading(self, t_s, y):
        return self.heading0_rad

    def target(self, state, t_next_s=None):
        """The schedule interval of the step [state.t_s, t_next_s] (from its midpoint: the
        integrator cuts its steps at the switch times, so a step lies in one interval)."""
        t = state.t_s if t_next_s is None else 0.5 * (state.t_s + t_next_s)
        return int(np.searchsorted(self.switch_times_s, t, side="right"))

    def commands(self, t_s, y, aux=None):
        j = int(np.searchsorted(self.switch_times_s, t_s, side="right")) if aux is None else aux
        zero = np.zeros(self.batch_shape)
        return self.speed_m_s, zero, self.turn_rates_rad_s[..., j]

    def advance(self, state, ell):
        return state.wp_index

    def _kernel_args(self):
        p = np.zeros((int(np.prod(self.batch_shape, dtype=np.int64)), _N_PARAMS))
        p[:, 0] = np.ravel(self.speed_m_s)
        return _LAW_LEGS, p, {"switch_times_s": self.switch_times_s,
                              "turn_rates_rad_s": self.turn_rates_rad_s.reshape(-1, self.switch_times_s.size + 1)}


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


def _center_offset(lat, lon, h, lat_c, lon_c, ell):
    """(d_e, d_n): a point's offset from (lat, lon, h), local flat east / north metres (as
    WaypointMission._offset and the compiled _offset_nb)."""
    m, nn = _radii(lat, ell)
    return wrap_pi(lon_c - lon) * (nn + h) * np.cos(lat), (lat_c - lat) * (m + h)


def _batch_shape(key: str, value) -> tuple:
    """A batch shape: a tuple of integers >= 0 (one integer n: (n,)), as a tuple of ints."""
    shape = (value,) if isinstance(value, (int, np.integer)) else value
    try:
        dims = tuple(shape)
        ok = not any(isinstance(n, bool) or int(n) != n or n < 0 for n in dims)
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise ParamError(key, f"expected a tuple of integers >= 0, got {value!r}")
    return tuple(int(n) for n in dims)


@dataclass(frozen=True, eq=False)
class Hold:
    """A static vehicle: speed, climb and heading rate 0 (batch_shape vehicles)."""

    batch_shape: tuple = param((), check=_batch_shape,
                               doc="the batch shape (vehicles): a tuple of integers >= 0, or one integer")

    def __post_init__(self):
        validate(self)

    def initial_heading(self, t_s, y):
        return np.zeros(self.batch_shape)

    def target(self, state, t_next_s=None):
        return None

    def commands(self, t_s, y, aux=None):
        z = np.zeros(self.batch_shape)
        return z, z, z

    def advance(self, state, ell):
        return state.wp_index

    def _kernel_args(self):
        return _LAW_HOLD, np.zeros((int(np.prod(self.batch_shape, dtype=np.int64)), _N_PARAMS)), {}


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


# --------------------------------------------------------------------------- state, ODE, RK4


class KinematicState(NamedTuple):
    """t_s simulation time; y (..., 4) [lat_rad, lon_rad, h_m, heading_rad];
    wp_index (...,) current waypoint (== count once a mission is complete); zeros otherwise."""

    t_s: float
    y: np.ndarray
    wp_index: np.ndarray


class VehicleTruth(NamedTuple):
    """Truth of a batch of vehicles at t_s (published for scoring only)."""

    t_s: float
    pos_ecef_m: np.ndarray  # (..., 3)
    vel_ecef_m_s: np.ndarray  # (..., 3)
    lat_rad: np.ndarray
    lon_rad: np.ndarray
    h_m: np.ndarray
    heading_rad: np.ndarray
    speed_m_s: np.ndarray


def _commands(guidance, t_s, y, aux, ell):
    if isinstance(guidance, (WaypointMission, Racetrack)):
        return guidance.commands(t_s, y, aux, ell)
    return guidance.commands(t_s, y, aux)


def _enu_velocity(speed, climb, heading):
    v_h = np.sqrt(np.maximum(speed * speed - climb * climb, 0.0))
    return v_h * np.sin(heading), v_h * np.cos(heading), climb


def geodetic_rates(t_s, y, guidance, aux=None, ell: Ellipsoid | str | None = None) -> np.ndarray:
    """dy/dt (..., 4) of y = [lat, lon, h, psi] under a guidance law (see the module docstring)."""
    e = ellipsoid(ell)
    speed, climb, rate = _commands(guidance, t_s, y, aux, e)
    lat, h = y[..., 0], y[..., 2]
    v_e, v_n, v_u = _enu_velocity(speed, climb, y[..., 3])
    m, n = _radii(lat, e)
    out = np.empty(np.broadcast_shapes(y.shape, np.shape(v_e) + (4,)))
    out[..., 0] = v_n / (m + h)
    out[..., 1] = v_e / ((n + h) * np.cos(lat))
    out[..., 2] = v_u
    out[..., 3] = rate
    return out


def rk4_step(f: Callable, t: float, y: np.ndarray, h: float) -> np.ndarray:
    """One classical 4th-order Runge-Kutta step of y' = f(t, y) from t to t + h."""
    k1 = f(t, y)
    k2 = f(t + 0.5 * h, y + 0.5 * h * k1)
    k3 = f(t + 0.5 * h, y + 0.5 * h * k2)
    k4 = f(t + h, y + h * k3)
    return y + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def initial_state(guidance, lat0_rad, lon0_rad, h0_m, t0_s: float = 0.0, heading0_rad=None) -> KinematicState:
    """The state at t0_s from geodetic start points (broadcast to the guidance's batch shape).

    heading0_rad defaults to the guidance's own (the law's heading at t0, or the bearing to
    the first waypoint)."""
    shape = guidance.batch_shape
    y = np.empty(shape + (4,))
    for k, (name, v) in enumerate((("lat0_rad", lat0_rad), ("lon0_rad", lon0_rad), ("h0_m", h0_m))):
        a = _FINITE(name, v)
        try:
            y[..., k] = np.broadcast_to(a, shape)
        except ValueError:
            raise ValueError(f"{name} must broadcast to the guidance batch shape {shape}, got {a.shape}") from None
    if np.any(np.abs(y[..., 0]) >= np.pi / 2):
        raise ValueError(f"lat0_rad must lie in (-pi/2, pi/2) rad (degrees passed?), got {lat0_rad!r}")
    t0 = _real("t0_s", t0_s)
    y[..., 3] = guidance.initial_heading(t0, y) if heading0_rad is None else _FINITE("heading0_rad", heading0_rad)
    return KinematicState(t0, y, np.zeros(shape, dtype=int))


def propagate(state: KinematicState, t1_s: float, guidance, dt_s: float = 0.01,
              ell: Ellipsoid | str | None = None, backend: str | None = None) -> KinematicState:
    """Integrate from state.t_s to t1_s by RK4 with step dt_s (the last step shortened to land
    on t1_s).  Steps are taken on the grid t0 + k dt_s plus the law's switch times (so a step
    never straddles one); waypoint indices advance between steps.

    backend: 'numba' (default when numba is installed: one compiled loop per vehicle) or
    'numpy' (the reference: :func:`rk4_step` on :func:`geodetic_rates`, vectorised over the
    vehicles).  Both evaluate the same formulas in the same order.
    """
    dt = _STEP("dt_s", dt_s)
    t1 = _real("t1_s", t1_s)
    if t1 < state.t_s:
        raise ValueError(f"t1_s must be >= the state's time {state.t_s}, got {t1_s!r}")
    if backend is None:
        backend = "numba" if nb is not None else "numpy"
    if backend not in ("numba", "numpy") or (backend == "numba" and nb is None):
        raise ValueError(f"backend must be 'numba' (needs numba) or 'numpy', got {backend!r}")
    e = ellipsoid(ell)
    ts = _step_times(state.t_s, t1, dt, getattr(guidance, "breakpoints_s", ()))
    if backend == "numba" and hasattr(guidance, "_kernel_args"):
        law, params, extra = guidance._kernel_args()
        shape = state.y.shape[:-1]
        y = np.ascontiguousarray(state.y, dtype=float).reshape(-1, 4).copy()
        idx = np.ascontiguousarray(state.wp_index, dtype=np.int64).reshape(-1).copy()
        sw = np.ascontiguousarray(extra.get("switch_times_s", np.zeros(0)), dtype=float)
        tr = np.ascontiguousarray(extra.get("turn_rates_rad_s", np.zeros((y.shape[0], 1))), dtype=float)
        wp = np.ascontiguousarray(extra.get("waypoints", np.zeros((y.shape[0], 1, 3))), dtype=float)
        cnt = np.ascontiguousarray(extra.get("count", np.ones(y.shape[0])), dtype=np.int64)
        ready(_integrate_nb)(law, y, idx, np.ascontiguousarray(params, dtype=float), sw, tr, wp, cnt, ts, e.a_m,
                             e.e2)
        return KinematicState(t1, y.reshape(shape + (4,)), idx.reshape(shape))
    y, idx = state.y, state.wp_index
    for ta, tb in zip(ts[:-1], ts[1:]):
        ta, tb = float(ta), float(tb)
        aux = guidance.target(KinematicState(ta, y, idx), tb)
        y = rk4_step(lambda t, yy: geodetic_rates(t, yy, guidance, aux, e), ta, y, tb - ta)
        y[..., 1] = wrap_pi(y[..., 1])
        y[..., 3] = np.mod(y[..., 3], 2.0 * np.pi)
        idx = guidance.advance(KinematicState(tb, y, idx), e)
    return KinematicState(t1, y, idx)


def _step_times(t0: float, t1: float, dt: float, breakpoints) -> np.ndarray:
    """Step boundaries from t0 to t1: the grid t0 + k dt (the last step shortened), plus the
    law's breakpoints inside (t0, t1), so that no step straddles a switch of the law."""
    if t1 <= t0:
        return np.array([t0])
    n = max(int(math.ceil((t1 - t0) / dt - 1e-9)), 1)
    ts = t0 + dt * np.arange(n + 1)
    ts[-1] = t1
    bp = np.asarray(breakpoints, dtype=float)
    bp = bp[(bp > t0) & (bp < t1)]
    if bp.size:
        ts = np.union1d(ts, bp)
        keep = np.concatenate([[True], np.diff(ts) > 1e-9 * np.maximum(1.0, np.abs(ts[1:]))])
        keep[-1] = True
        ts = ts[keep]
        if ts.size > 2 and ts[-1] - ts[-2] <= 1e-9 * max(1.0, abs(t1)):
            ts = np.delete(ts, -2)
    return ts


if nb is not None:
    from filters.nbdispatch import declare, ready, ro, rw

    _TWO_PI = 2.0 * math.pi

    @nb.njit(cache=True, nogil=True)
    def _wrap_nb(a):
        return a - _TWO_PI * math.floor((a + math.pi) / _TWO_PI)

    @nb.njit(cache=True, nogil=True)
    def _offset_nb(lat, lon, h, glat, glon, a, e2):
        w2 = 1.0 - e2 * math.sin(lat) ** 2
        n = a / math.sqrt(w2)
        m = n * (1.0 - e2) / w2
        return _wrap_nb(glon - lon) * (n + h) * math.cos(lat), (glat - lat) * (m + h)

    @nb.njit(cache=True, nogil=True)
    def _rates_nb(law, p, seg, tr, g, t, lat, lon, h, psi, a, e2):
        """The same law and geodetic rates as SinusoidalLaw/LegsAndTurns/Hold/WaypointMission/Racetrack
        .commands + geodetic_rates, for one vehicle (p its parameter row, seg the schedule
        interval of the step, g its waypoint)."""
        if law == 0:
            speed = p[0] + p[1] * math.sin(p[2] * t + p[3])
            climb = p[8] * math.cos(p[9] * t + p[10])
            rate = p[5] * p[6] * math.cos(p[6] * t + p[7])
        elif law == 1:
            speed = p[0]
            climb = 0.0
            rate = tr[seg]
        elif law == 2:
            speed = 0.0
            climb = 0.0
            rate = 0.0
        elif law == 4:  # Racetrack: p = speed, max rate, radius, turn gain, radial gain, centre lat, lon, axis, L
            d_e, d_n = _offset_nb(lat, lon, h, p[5], p[6], a, e2)
            sa, ca = math.sin(p[7]), math.cos(p[7])
            s = -(d_e * sa + d_n * ca)
            c = -(d_e * ca - d_n * sa)
            r = p[2]
            if s > p[8] or s < -p[8]:
                end = p[8] if s > 0 else -p[8]
                g_e, g_n = d_e + end * sa, d_n + end * ca
                ref = math.atan2(g_e, g_n) - 0.5 * math.pi + math.atan(p[4] * (math.hypot(g_e, g_n) - r) / r)
                ff = p[0] / r
            elif c < 0:
                ref = p[7] - math.atan(p[4] * (c + r) / r)
                ff = 0.0
            else:
                ref = p[7] + math.pi - math.atan(p[4] * (r - c) / r)
                ff = 0.0
            rate = min(max(ff + p[3] * _wrap_nb(ref - psi), -p[1]), p[1])
            climb = 0.0
            speed = p[0]
        else:
            d_e, d_n = _offset_nb(lat, lon, h, g[0], g[1], a, e2)
            rate = min(max(p[4] * _wrap_nb(math.atan2(d_e, d_n) - psi), -p[1]), p[1])
            climb = min(max(p[5] * (g[2] - h), -p[2]), p[2])
            speed = p[0]
        v_h = math.sqrt(max(speed * speed - climb * climb, 0.0))
        w2 = 1.0 - e2 * math.sin(lat) ** 2
        n = a / math.sqrt(w2)
        m = n * (1.0 - e2) / w2
        return (v_h * math.cos(psi) / (m + h), v_h * math.sin(psi) / ((n + h) * math.cos(lat)), climb, rate)

    @nb.njit(cache=True, nogil=True)
    def _rk4_steps_nb(law, p, tri, wpi, cnti, sw, ts, j0, j1, lat, lon, h, psi, k_wp, a, e2):
        """RK4 of one vehicle over the step boundaries ts[j0..j1]; returns the new state."""
        for k in range(j0, j1):
            ta = ts[k]
            tb = ts[k + 1]
            hh = tb - ta
            seg = np.searchsorted(sw, 0.5 * (ta + tb), side="right")
            g = wpi[min(k_wp, cnti - 1)]
            a1, b1, c1, d1 = _rates_nb(law, p, seg, tri, g, ta, lat, lon, h, psi, a, e2)
            a2, b2, c2, d2 = _rates_nb(law, p, seg, tri, g, ta + 0.5 * hh, lat + 0.5 * hh * a1,
                                       lon + 0.5 * hh * b1, h + 0.5 * hh * c1, psi + 0.5 * hh * d1, a, e2)
            a3, b3, c3, d3 = _rates_nb(law, p, seg, tri, g, ta + 0.5 * hh, lat + 0.5 * hh * a2,
                                       lon + 0.5 * hh * b2, h + 0.5 * hh * c2, psi + 0.5 * hh * d2, a, e2)
            a4, b4, c4, d4 = _rates_nb(law, p, seg, tri, g, tb, lat + hh * a3, lon + hh * b3, h + hh * c3,
                                       psi + hh * d3, a, e2)
            lat = lat + (hh / 6.0) * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
            lon = _wrap_nb(lon + (hh / 6.0) * (b1 + 2.0 * b2 + 2.0 * b3 + b4))
            h = h + (hh / 6.0) * (c1 + 2.0 * c2 + 2.0 * c3 + c4)
            psi = psi + (hh / 6.0) * (d1 + 2.0 * d2 + 2.0 * d3 + d4)
            psi = psi - _TWO_PI * math.floor(psi / _TWO_PI)
            if law == 3:
                g = wpi[min(k_wp, cnti - 1)]
                d_e, d_n = _offset_nb(lat, lon, h, g[0], g[1], a, e2)
                if math.hypot(d_e, d_n) < p[3]:
                    k_wp = min(k_wp + 1, cnti)
        return lat, lon, h, psi, k_wp

    # one compiled version each (filters/nbdispatch.py): the guidance's arrays may be read-only
    @declare(nb.int64, rw(2), rw(1, nb.int64), ro(2), ro(1), ro(2), ro(3), ro(1, dtype=nb.int64), ro(1), nb.float64,
             nb.float64)
    @nb.njit(cache=True, nogil=True)
    def _integrate_nb(law, y, idx, params, sw, tr, wp, cnt, ts, a, e2):
        """RK4 over the step boundaries ts in place on y (N, 4) and idx (N,), one vehicle at a time."""
        for i in range(y.shape[0]):
            tri = tr[i] if law == 1 else tr[0]
            lat, lon, h, psi, k_wp = _rk4_steps_nb(law, params[i], tri, wp[i], cnt[i], sw, ts, np.int64(0), ts.size - 1,
                                                   y[i, 0], y[i, 1], y[i, 2], y[i, 3], idx[i], a, e2)
            y[i, 0], y[i, 1], y[i, 2], y[i, 3] = lat, lon, h, psi
            idx[i] = k_wp

    @declare(nb.int64, rw(2), rw(1, nb.int64), ro(2), ro(1), ro(2), ro(3), ro(1, dtype=nb.int64), ro(1),
             ro(1, dtype=nb.int64), rw(3), rw(2, nb.int64), nb.float64, nb.float64)
    @nb.njit(cache=True, nogil=True)
    def _integrate_track_nb(law, y, idx, params, sw, tr, wp, cnt, ts, ends, ys, idxs, a, e2):
        """As _integrate_nb over ts, recording the state at the boundaries ts[ends[k]] in
        ys (K, N, 4) and idxs (K, N); y and idx end at the last one."""
        for i in range(y.shape[0]):
            tri = tr[i] if law == 1 else tr[0]
            lat, lon, h, psi, k_wp = y[i, 0], y[i, 1], y[i, 2], y[i, 3], idx[i]
            j = np.int64(0)  # not a literal 0: _rk4_steps_nb would compile again for Literal[int](0)
            for k in range(ends.size):
                lat, lon, h, psi, k_wp = _rk4_steps_nb(law, params[i], tri, wp[i], cnt[i], sw, ts, j, ends[k],
                                                       lat, lon, h, psi, k_wp, a, e2)
                j = ends[k]
                ys[k, i, 0], ys[k, i, 1], ys[k, i, 2], ys[k, i, 3] = lat, lon, h, psi
                idxs[k, i] = k_wp
            y[i, 0], y[i, 1], y[i, 2], y[i, 3] = lat, lon, h, psi
            idx[i] = k_wp


def truth(state: KinematicState, guidance, ell: Ellipsoid | str | None = None) -> VehicleTruth:
    """ECEF position and velocity (and the geodetic state) of every vehicle at state.t_s."""
    e = ellipsoid(ell)
    y = state.y
    speed, climb, _ = _commands(guidance, state.t_s, y, guidance.target(state, state.t_s), e)
    v_enu = np.stack(np.broadcast_arrays(*_enu_velocity(speed, climb, y[..., 3])), axis=-1)
    R = geodesy.enu_rotation(y[..., 0], y[..., 1])  # enu = R @ ecef
    vel = np.matmul(np.swapaxes(R, -1, -2), v_enu[..., None])[..., 0]
    pos = geodesy.geodetic_to_ecef(y[..., 0], y[..., 1], y[..., 2], e)
    return VehicleTruth(state.t_s, pos, vel, y[..., 0].copy(), y[..., 1].copy(), y[..., 2].copy(),
                        y[..., 3].copy(), np.broadcast_to(speed, y.shape[:-1]).copy())


def _stack_truths(truths) -> VehicleTruth:
    return VehicleTruth(np.array([v.t_s for v in truths], dtype=float),
                        *(np.stack([v[i] for v in truths]) for i in range(1, len(VehicleTruth._fields))))


# --------------------------------------------------------------------------- the stepped swarm


class KinematicSwarm:
    """Vehicles of one kind under one guidance law, stepped together in simulation time.

    ``step(t_s)`` integrates (RK4, dt_s) from the current time to t_s and returns the
    :class:`VehicleTruth`; ``state`` is the functional :class:`KinematicState` (the same
    numbers as :func:`propagate`).  ``upload_mission(i, waypoints)`` replaces vehicle i's
    waypoints in waypoint mode and restarts its mission.
    """

    def __init__(self, guidance, lat0_rad, lon0_rad, h0_m, *, t0_s: float = 0.0, dt_s: float = 0.01,
                 heading0_rad=None, ell: Ellipsoid | str | None = None):
        for attr in ("batch_shape", "commands", "initial_heading", "target", "advance"):
            if not hasattr(guidance, attr):
                raise ValueError(f"guidance must be a guidance law (no {attr}), got {guidance!r}")
        self.dt_s = _STEP("dt_s", dt_s)
        self.ell = ellipsoid(ell)
        self.guidance = guidance
        self.state = initial_state(guidance, lat0_rad, lon0_rad, h0_m, t0_s, heading0_rad)

    @property
    def n(self) -> int:
        return int(np.prod(self.guidance.batch_shape, dtype=np.int64))

    @property
    def t_s(self) -> float:
        return self.state.t_s

    def step(self, t_s: float) -> VehicleTruth:
        self.state = propagate(self.state, t_s, self.guidance, self.dt_s, self.ell)
        return self.truth()

    def truth(self) -> VehicleTruth:
        return truth(self.state, self.guidance, self.ell)

    def track(self, times_s) -> VehicleTruth:
        """``step(t)`` for each t of the increasing times_s (K,) in turn, the truths stacked
        on a leading axis (t_s (K,), pos_ecef_m (K, ..., 3), ...): the same numbers.

        With numba and a law the compiled integrator knows, every step runs in one compiled
        call (the per-epoch step boundaries are those ``step`` would take), and for the laws
        whose commands are plain functions of time (SinusoidalLaw, Hold) the truth is
        evaluated for all epochs at once: the same element-wise formulas."""
        ts_req = np.asarray(times_s, dtype=float).reshape(-1)
        if ts_req.size == 0:
            raise ValueError("times_s must hold at least one time")
        if nb is None or not hasattr(self.guidance, "_kernel_args") or np.any(np.diff(ts_req) < 0) \
                or ts_req[0] < self.state.t_s or not np.all(np.isfinite(ts_req)):
            return _stack_truths([self.step(float(t)) for t in ts_req])
        bp = getattr(self.guidance, "breakpoints_s", ())
        parts, ends, t0, n = [np.array([self.state.t_s])], [], self.state.t_s, 0
        for t in ts_req:
            seg = _step_times(t0, float(t), self.dt_s, bp)
            parts.append(seg[1:])
            n += seg.size - 1
            ends.append(n)
            t0 = float(t)
        law, params, extra = self.guidance._kernel_args()
        shape = self.state.y.shape[:-1]
        y = np.ascontiguousarray(self.state.y, dtype=float).reshape(-1, 4).copy()
        idx = np.ascontiguousarray(self.state.wp_index, dtype=np.int64).reshape(-1).copy()
        sw = np.ascontiguousarray(extra.get("switch_times_s", np.zeros(0)), dtype=float)
        tr = np.ascontiguousarray(extra.get("turn_rates_rad_s", np.zeros((y.shape[0], 1))), dtype=float)
        wp = np.ascontiguousarray(extra.get("waypoints", np.zeros((y.shape[0], 1, 3))), dtype=float)
        cnt = np.ascontiguousarray(extra.get("count", np.ones(y.shape[0])), dtype=np.int64)
        K = ts_req.size
        ys = np.empty((K,) + y.shape)
        idxs = np.empty((K, y.shape[0]), dtype=np.int64)
        ready(_integrate_track_nb)(law, y, idx, np.ascontiguousarray(params, dtype=float), sw, tr, wp, cnt,
                                   np.concatenate(parts), np.array(ends, dtype=np.int64), ys, idxs, self.ell.a_m,
                                   self.ell.e2)
        ys = ys.reshape((K,) + shape + (4,))
        idxs = idxs.reshape((K,) + shape)
        self.state = KinematicState(float(ts_req[-1]), y.reshape(shape + (4,)), idx.reshape(shape))
        if isinstance(self.guidance, (SinusoidalLaw, Hold)):
            tk = ts_req.reshape((K,) + (1,) * len(shape))
            out = truth(KinematicState(tk, ys, idxs), self.guidance, self.ell)
            return out._replace(t_s=ts_req.copy())
        return _stack_truths([truth(KinematicState(float(ts_req[k]), ys[k], idxs[k]), self.guidance, self.ell)
                              for k in range(K)])

    def upload_mission(self, i: int, waypoints_rad_m) -> None:
        if not isinstance(self.guidance, WaypointMission):
            raise ValueError(f"guidance must be a WaypointMission to upload a mission, got "
                             f"{type(self.guidance).__name__}")
        self.guidance = self.guidance.replace_vehicle(i, waypoints_rad_m)
        idx = self.state.wp_index.copy()
        idx[int(i)] = 0
        self.state = self.state._replace(wp_index=idx)


class UavSwarm(KinematicSwarm):
    """A swarm of UAVs (a :class:`KinematicSwarm`); see :func:`example_uav_swarm`."""


def example_uav_law() -> SinusoidalLaw:
    """The three UAVs of the seed 002 example, geodetic reading (module docstring).

    Heading north (0), 3-D speed v0_i + 10 sin(0.02 t) with v0 = 100 / 110 / 110 m/s (the
    printed V_eta laws), climb 15 cos(0.01 t) (altitude h0 + 1500 sin(0.01 t), the printed
    r(t)).  Each UAV keeps its own speed law: the formation is not a rigid line."""
    return SinusoidalLaw(speed_mean_m_s=np.array(EXAMPLE_UAV_SPEED_M_S), speed_amp_m_s=10.0,
                         speed_omega_rad_s=0.02, heading0_rad=0.0, climb_amp_m_s=15.0, climb_omega_rad_s=0.01)


def example_uav_swarm(dt_s: float = 0.01, t0_s: float = 0.0) -> UavSwarm:
    """The seed 002 UAV-1..3 at their geodetic start points, RK4 step dt_s (seed: 0.01 s)."""
    s = np.array(EXAMPLE_UAV_START)
    return UavSwarm(example_uav_law(), np.radians(s[:, 0]), np.radians(s[:, 1]), s[:, 2], t0_s=t0_s, dt_s=dt_s)


# --------------------------------------------------------------------------- the printed laws

_R0_M, _R_AMP_M = 6.374e6, 1500.0
_SQRT3_2 = math.sqrt(3.0) / 2.0


def paper_to_ecef(v):
    """The paper's (xi, eta, zeta) (..., 3) -> ECEF (x, y, z) = (zeta, xi, eta) (module docstring)."""
    v = np.asarray(v, dtype=float)
    return v[..., [2, 0, 1]]


def ecef_to_paper(v):
    """ECEF (x, y, z) (..., 3) -> the paper's (xi, eta, zeta) = (y, z, x)."""
    v = np.asarray(v, dtype=float)
    return v[..., [1, 2, 0]]


@dataclass(frozen=True, eq=False)
class PrintedLaw:
    """The seed's velocity laws as printed (module docstring): a velocity field of time and
    the ECEF z (= the paper's eta) coordinate.  Fields a, b, v0, d, e (m/s), cross_omega (w')
    and radius_omega (w_r) (rad/s) broadcast to the batch shape (vehicles)."""

    a_m_s: Any = param(check=_FINITE, doc="a: the eta / r coefficient of V_xi, m/s")
    b_m_s: Any = param(check=_FINITE, doc="b: the cos(w' t) c coefficient of V_xi, m/s")
    v0_m_s: Any = param(check=_FINITE, doc="v0: the mean speed of V_eta, m/s")
    d_m_s: Any = param(check=_FINITE, doc="d: the eta / r coefficient of V_zeta, m/s")
    e_m_s: Any = param(check=_FINITE, doc="e: the cos(w' t) c coefficient of V_zeta, m/s")
    cross_omega_rad_s: Any = param(0.01, check=_FINITE, doc="w': the angular frequency of the cross terms, rad/s")
    radius_omega_rad_s: Any = param(0.01, check=_FINITE,
                                    doc="w_r: the angular frequency of r(t) = 6.374e6 + 1500 sin(w_r t) m, rad/s")
    batch_shape: tuple = field(init=False)

    _FIELDS = ("a_m_s", "b_m_s", "v0_m_s", "d_m_s", "e_m_s", "cross_omega_rad_s", "radius_omega_rad_s")

    def __post_init__(self):
        validate(self)
        object.__setattr__(self, "batch_shape", _broadcast(self, self._FIELDS))

    @classmethod
    def from_coeffs(cls, rows) -> "PrintedLaw":
        """From rows (a, b, v0, d, e, w', w_r) (:data:`PRINTED_COEFFS`' values)."""
        c = _FINITE("rows", rows)
        if c.ndim != 2 or c.shape[1] != 7:
            raise ValueError(f"rows must have shape (n, 7) (a, b, v0, d, e, w', w_r), got {c.shape}")
        return cls(*c.T)

    def params(self) -> np.ndarray:
        """(n, 7) parameter rows of the compiled integrator."""
        return np.stack([np.ravel(getattr(self, f)) for f in self._FIELDS], axis=-1)

    def repeat(self, n: int) -> "PrintedLaw":
        """A batch of n copies of a one-vehicle law (e.g. one beacon per Monte Carlo trial)."""
        if int(np.prod(self.batch_shape, dtype=np.int64)) != 1:
            raise ValueError(f"repeat needs a one-vehicle law, got batch shape {self.batch_shape}")
        return PrintedLaw(*(np.full(int(n), float(np.ravel(getattr(self, f))[0])) for f in self._FIELDS))


def printed_velocity_ecef(t_s, pos_ecef_m, law: PrintedLaw) -> np.ndarray:
    """ECEF velocity (..., 3) of the printed law at time t_s and ECEF positions (..., 3)."""
    pos = np.asarray(pos_ecef_m, dtype=float)
    t = float(t_s)
    r = _R0_M + _R_AMP_M * np.sin(law.radius_omega_rad_s * t)
    s = pos[..., 2] / r  # eta / r
    c = np.sqrt(np.maximum(1.0 - s * s, 0.0))
    s2 = math.sin(0.02 * t)
    cw = np.cos(law.cross_omega_rad_s * t)
    v_xi = -(law.a_m_s + 0.5 * s2) * s + law.b_m_s * cw * c
    v_eta = (law.v0_m_s + 10.0 * s2) * c + 15.0 * math.cos(0.01 * t) * s
    v_zeta = _SQRT3_2 * (-(law.d_m_s + s2) * s + law.e_m_s * cw * c)
    out = np.empty(np.broadcast_shapes(pos.shape, np.shape(v_xi) + (3,)))
    out[..., 0], out[..., 1], out[..., 2] = v_zeta, v_xi, v_eta
    return out


def propagate_printed(pos_ecef_m, t0_s: float, t1_s: float, law: PrintedLaw, dt_s: float = 0.01,
                      backend: str | None = None) -> np.ndarray:
    """ECEF positions (..., 3) at t1_s from pos_ecef_m at t0_s: RK4 with step dt_s on the grid
    t0 + k dt_s (the last step shortened to land on t1_s).

    backend 'numba' (default when installed: one compiled loop per vehicle) or 'numpy' (the
    reference: :func:`rk4_step` on :func:`printed_velocity_ecef`, vectorised); both evaluate
    the same formulas in the same order."""
    dt = _STEP("dt_s", dt_s)
    t0, t1 = _real("t0_s", t0_s), _real("t1_s", t1_s)
    if t1 < t0:
        raise ValueError(f"t1_s must be >= t0_s {t0}, got {t1_s!r}")
    x = _FINITE("pos_ecef_m", pos_ecef_m)
    shape = law.batch_shape
    try:
        x = np.broadcast_to(x, shape + (3,)).astype(float)
    except ValueError:
        raise ValueError(f"pos_ecef_m must broadcast to the law's batch shape {shape} + (3,), got {x.shape}") from None
    if backend is None:
        backend = "numba" if nb is not None else "numpy"
    if backend not in ("numba", "numpy") or (backend == "numba" and nb is None):
        raise ValueError(f"backend must be 'numba' (needs numba) or 'numpy', got {backend!r}")
    ts = _step_times(t0, t1, dt, ())
    if backend == "numba":
        y = np.ascontiguousarray(x.reshape(-1, 3)).copy()
        ys = np.empty((1,) + y.shape)
        _printed_track_nb(law.params(), y, ts, np.array([ts.size - 1], dtype=np.int64), ys)
        return y.reshape(shape + (3,))
    for ta, tb in zip(ts[:-1], ts[1:]):
        x = rk4_step(lambda t, xx: printed_velocity_ecef(t, xx, law), float(ta), x, float(tb - ta))
    return x


def _printed_truth(t_s, pos, law: PrintedLaw, ell) -> "VehicleTruth":
    vel = printed_velocity_ecef(t_s, pos, law)
    lat, lon, h = geodesy.ecef_to_geodetic(pos, ell)
    v_enu = np.matmul(geodesy.enu_rotation(lat, lon), vel[..., None])[..., 0]
    heading = np.mod(np.arctan2(v_enu[..., 0], v_enu[..., 1]), 2.0 * np.pi)
    return VehicleTruth(t_s, pos.copy(), vel, np.asarray(lat, float), np.asarray(lon, float), np.asarray(h, float),
                        heading, np.linalg.norm(vel, axis=-1))


class PrintedSwarm:
    """Vehicles under :class:`PrintedLaw`, stepped in simulation time like a
    :class:`KinematicSwarm` (``step``, ``truth``, ``track``; state: ECEF positions)."""

    def __init__(self, law: PrintedLaw, pos0_ecef_m, *, t0_s: float = 0.0, dt_s: float = 0.01,
                 ell: Ellipsoid | str | None = None):
        if not isinstance(law, PrintedLaw):
            raise ValueError(f"law must be a PrintedLaw, got {law!r}")
        self.law = law
        self.dt_s = _STEP("dt_s", dt_s)
        self.ell = ellipsoid(ell)
        x = _FINITE("pos0_ecef_m", pos0_ecef_m)
        try:
            self.pos = np.broadcast_to(x, law.batch_shape + (3,)).astype(float)
        except ValueError:
            raise ValueError(f"pos0_ecef_m must broadcast to {law.batch_shape} + (3,), got {x.shape}") from None
        self._t = _real("t0_s", t0_s)

    @property
    def n(self) -> int:
        return int(np.prod(self.law.batch_shape, dtype=np.int64))

    @property
    def t_s(self) -> float:
        return self._t

    def step(self, t_s: float) -> VehicleTruth:
        self.pos = propagate_printed(self.pos, self._t, t_s, self.law, self.dt_s)
        self._t = float(t_s)
        return self.truth()

    def truth(self) -> VehicleTruth:
        return _printed_truth(self._t, self.pos, self.law, self.ell)

    def track(self, times_s) -> VehicleTruth:
        """``step(t)`` for each of the increasing times_s (K,), stacked on a leading axis: the
        same numbers (the same step boundaries), in one compiled call with numba."""
        ts_req = np.asarray(times_s, dtype=float).reshape(-1)
        if ts_req.size == 0:
            raise ValueError("times_s must hold at least one time")
        if nb is None or np.any(np.diff(ts_req) < 0) or ts_req[0] < self._t or not np.all(np.isfinite(ts_req)):
            return _stack_truths([self.step(float(t)) for t in ts_req])
        parts, ends, t0, n = [np.array([self._t])], [], self._t, 0
        for t in ts_req:
            seg = _step_times(t0, float(t), self.dt_s, ())
            parts.append(seg[1:])
            n += seg.size - 1
            ends.append(n)
            t0 = float(t)
        shape = self.law.batch_shape
        y = np.ascontiguousarray(self.pos.reshape(-1, 3)).copy()
        K = ts_req.size
        ys = np.empty((K,) + y.shape)
        _printed_track_nb(self.law.params(), y, np.concatenate(parts), np.array(ends, dtype=np.int64), ys)
        self.pos = y.reshape(shape + (3,))
        self._t = float(ts_req[-1])
        pos = ys.reshape((K,) + shape + (3,))
        vel = np.stack([printed_velocity_ecef(float(ts_req[k]), pos[k], self.law) for k in range(K)])
        lat, lon, h = geodesy.ecef_to_geodetic(pos, self.ell)
        v_enu = np.matmul(geodesy.enu_rotation(lat, lon), vel[..., None])[..., 0]
        heading = np.mod(np.arctan2(v_enu[..., 0], v_enu[..., 1]), 2.0 * np.pi)
        return VehicleTruth(ts_req.copy(), pos, vel, np.asarray(lat, float), np.asarray(lon, float),
                            np.asarray(h, float), heading, np.linalg.norm(vel, axis=-1))


if nb is not None:
    @nb.njit(cache=True, nogil=True)
    def _printed_vel_nb(p, t, z):
        r = 6.374e6 + 1500.0 * math.sin(p[6] * t)
        s = z / r
        c = math.sqrt(max(1.0 - s * s, 0.0))
        s2 = math.sin(0.02 * t)
        cw = math.cos(p[5] * t)
        v_xi = -(p[0] + 0.5 * s2) * s + p[1] * cw * c
        v_eta = (p[2] + 10.0 * s2) * c + 15.0 * math.cos(0.01 * t) * s
        v_zeta = (math.sqrt(3.0) / 2.0) * (-(p[3] + s2) * s + p[4] * cw * c)
        return v_zeta, v_xi, v_eta

    @nb.njit(cache=True, nogil=True)
    def _printed_track_nb(params, y, ts, ends, ys):
        """RK4 of every vehicle over the step boundaries ts, recording ys[k] at ts[ends[k]];
        y (N, 3) ends at the last boundary."""
        for i in range(y.shape[0]):
            p = params[i]
            x0, x1, x2 = y[i, 0], y[i, 1], y[i, 2]
            j = 0
            for k in range(ends.size):
                for m in range(j, ends[k]):
                    ta = ts[m]
                    hh = ts[m + 1] - ta
                    a0, a1, a2 = _printed_vel_nb(p, ta, x2)
                    b0, b1, b2 = _printed_vel_nb(p, ta + 0.5 * hh, x2 + 0.5 * hh * a2)
                    c0, c1, c2 = _printed_vel_nb(p, ta + 0.5 * hh, x2 + 0.5 * hh * b2)
                    d0, d1, d2 = _printed_vel_nb(p, ts[m + 1], x2 + hh * c2)
                    x0 = x0 + (hh / 6.0) * (a0 + 2.0 * b0 + 2.0 * c0 + d0)
                    x1 = x1 + (hh / 6.0) * (a1 + 2.0 * b1 + 2.0 * c1 + d1)
                    x2 = x2 + (hh / 6.0) * (a2 + 2.0 * b2 + 2.0 * c2 + d2)
                j = ends[k]
                ys[k, i, 0], ys[k, i, 1], ys[k, i, 2] = x0, x1, x2
            y[i, 0], y[i, 1], y[i, 2] = x0, x1, x2


def printed_uav_law(n: int = 3) -> PrintedLaw:
    """UAV-1..3's printed laws; for n > 3 further UAVs whose coefficients are spread over the
    printed ranges by a low-discrepancy (golden-ratio) sequence: a in [5, 15], b in [5.5, 7.5],
    v0 in [100, 110], d in [10, 20], e in [15, 19], w' = w_r = 0.01 (an extension, not the paper)."""
    if isinstance(n, bool) or int(n) != n or n < 1:
        raise ValueError(f"n must be an integer >= 1, got {n!r}")
    rows = [PRINTED_COEFFS[f"uav{i + 1}"] for i in range(min(int(n), 3))]
    g = (math.sqrt(5.0) - 1.0) / 2.0
    for j in range(int(n) - 3):
        f1, f2, f3 = ((j + 1) * g) % 1.0, ((j + 1) * g * g * 1.7) % 1.0, ((j + 1) * 0.7548776662) % 1.0
        rows.append((5.0 + 10.0 * f1, 5.5 + 2.0 * f2, 100.0 + 10.0 * f3, 10.0 + 10.0 * f2, 15.0 + 4.0 * f1, 0.01, 0.01))
    return PrintedLaw.from_coeffs(rows)


def printed_uav_swarm(n: int = 3, dt_s: float = 0.01, t0_s: float = 0.0) -> PrintedSwarm:
    """n UAVs under the printed laws, all from the printed start point (ECEF)."""
    return PrintedSwarm(printed_uav_law(n), paper_to_ecef(PRINTED_START_PAPER_M), t0_s=t0_s,
                        dt_s=dt_s)
