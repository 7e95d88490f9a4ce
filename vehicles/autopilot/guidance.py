"""The autopilot's output: per-UAV guidance in the form the kinematics take.

:class:`Guidance` holds, for every UAV, a guidance *kind* and its targets for the interval
[t, t + dt] the autopilot was stepped for.  :class:`AutopilotLaw` is a guidance law in the
sense of vehicles.uav (``batch_shape``, ``commands(t, y, aux)`` -> (speed m/s, climb m/s,
heading rate rad/s), ``initial_heading``, ``target``, ``advance``), so
``vehicles.uav.propagate(state, t1, AutopilotLaw(g), dt_s)`` integrates it with the same RK4
and the same ODE (vehicles.uav.geodetic_rates) as every other law; the commands are
evaluated at every RK4 stage from the stage's state, as the existing laws are.  The formulas
are the existing laws' own (vehicles/uav/):

  GOTO    WaypointMission's pursuit:  psi' = clip(k_goto wrap(bearing - psi), +-w_max),
          v_u = clip(k_climb (alt - h), -sink_max, +climb_max)
  ORBIT   Racetrack's circle (half_length 0), clockwise about the target with radius r:
          psi_ref = bearing - pi/2 + atan(k_r (d - r) / r), psi' = clip(v / r + k_orbit
          wrap(psi_ref - psi), +-w_max); v_u as GOTO (a loiter also changes altitude)
  LEG     heading hold: psi' = clip(k_goto wrap(heading - psi), +-w_max); v_u as GOTO
  LAND    the approach: GOTO's turn towards the landing point, v_u = clip(k_climb (alt + slope d
          - h), -sink_max, 0): down the glide slope from above, level below it, never a climb
  FINAL   past the landing point: LEG's heading hold, v_u = -clip(max(slope v, k_climb (h - alt)),
          0, sink_max) above the ground (alt), 0 on it: straight ahead down to the ground, at least at
          the glide slope's sink rate
  HOLD    v = v_u = psi' = 0 (on the ground)
  SCENARIO  the scenario's own law flies this UAV (the caller's; :class:`AutopilotLaw` evaluates
          it for these UAVs only when given one, see vehicles.autopilot.swarm)

(d_e, d_n) are the target's local flat offsets (east, north; the same as WaypointMission's and
Racetrack's: wrap(dlon)(N + h) cos(lat), dlat (M + h)), d = hypot(d_e, d_n), bearing =
atan2(d_e, d_n).  The climb is further bounded by half the speed (a 30 deg flight path).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from sitl.constants import Ellipsoid, ellipsoid

HOLD, SCENARIO, GOTO, ORBIT, LEG, LAND, FINAL = 0, 1, 2, 3, 4, 5, 6
KIND_NAMES = {HOLD: "hold", SCENARIO: "scenario", GOTO: "goto", ORBIT: "orbit", LEG: "leg", LAND: "land",
              FINAL: "final"}

#: gains: WaypointMission's turn and climb gains, Racetrack's turn and radial gains (vehicles/uav/ defaults)
K_GOTO_1_S, K_CLIMB_1_S, K_ORBIT_1_S, K_RADIAL = 0.5, 0.05, 0.1, 1.0


class Guidance(NamedTuple):
    """Per-UAV guidance for one interval; every field has shape (N,).

    kind: HOLD / SCENARIO / GOTO / ORBIT / LEG / LAND; speed_m_s: commanded 3-D speed;
    lat_rad, lon_rad, alt_m: the target (GOTO, LAND: the point; ORBIT: the centre; alt_m is the
    altitude to climb or descend to, for LAND the ground's); radius_m: ORBIT's radius;
    heading_rad: LEG's heading; max_turn_rate_rad_s, climb_max_m_s, sink_max_m_s: limits;
    slope: LAND's glide slope."""

    kind: np.ndarray
    speed_m_s: np.ndarray
    lat_rad: np.ndarray
    lon_rad: np.ndarray
    alt_m: np.ndarray
    radius_m: np.ndarray
    heading_rad: np.ndarray
    max_turn_rate_rad_s: np.ndarray
    climb_max_m_s: np.ndarray
    sink_max_m_s: np.ndarray
    slope: np.ndarray

    def subset(self, idx) -> "Guidance":
        return Guidance(*(np.asarray(a)[idx] for a in self))


def _wrap(a):
    return np.mod(a + np.pi, 2.0 * np.pi) - np.pi


def offsets(lat, lon, h, lat_t, lon_t, ell: Ellipsoid | None = None):
    """(d_e, d_n): the target's local flat east / north offset from (lat, lon, h), m (the
    offset vehicles.uav's WaypointMission and Racetrack steer by)."""
    e = ellipsoid(ell)
    w2 = 1.0 - e.e2 * np.sin(lat) ** 2
    n = e.a_m / np.sqrt(w2)
    m = n * (1.0 - e.e2) / w2
    return _wrap(lon_t - lon) * (n + h) * np.cos(lat), (lat_t - lat) * (m + h)


def commands(g: Guidance, y, ell: Ellipsoid | None = None, scenario=None):
    """(speed, climb, heading rate) of every UAV at states y (N, 4) [lat, lon, h, heading].

    scenario: (speed, climb, rate) arrays (N,) of the scenario's law at y, used for the
    SCENARIO UAVs (zeros if None).  When every UAV has the same kind only that kind's formulas
    are evaluated (the same numbers: each kind's formula is element-wise)."""
    lat, lon, h, psi = y[..., 0], y[..., 1], y[..., 2], y[..., 3]
    kind = g.kind
    k0 = int(kind[0]) if kind.size else HOLD
    uniform = bool(np.all(kind == k0))
    kinds = (k0,) if uniform else tuple(int(k) for k in np.unique(kind))
    v = g.speed_m_s
    zero = np.zeros(kind.shape)
    if uniform and k0 == HOLD:
        return zero, zero.copy(), zero.copy()
    if uniform and k0 == SCENARIO:
        return scenario if scenario is not None else (zero, zero.copy(), zero.copy())
    need_target = any(k in (GOTO, ORBIT, LAND) for k in kinds)
    if need_target:
        d_e, d_n = offsets(lat, lon, h, g.lat_rad, g.lon_rad, ell)
        bearing = np.arctan2(d_e, d_n)
    rate = zero
    if GOTO in kinds or LAND in kinds:
        r_goto = K_GOTO_1_S * _wrap(bearing - psi)
        rate = r_goto if uniform else np.where((kind == GOTO) | (kind == LAND), r_goto, rate)
    if ORBIT in kinds:
        d = np.hypot(d_e, d_n)
        r = np.maximum(g.radius_m, 1.0)
        ref = bearing - 0.5 * np.pi + np.arctan(K_RADIAL * (d - r) / r)
        r_orbit = v / r + K_ORBIT_1_S * _wrap(ref - psi)
        rate = r_orbit if uniform else np.where(kind == ORBIT, r_orbit, rate)
    if LEG in kinds or FINAL in kinds:
        r_leg = K_GOTO_1_S * _wrap(g.heading_rad - psi)
        rate = r_leg if uniform else np.where((kind == LEG) | (kind == FINAL), r_leg, rate)
    w = g.max_turn_rate_rad_s
    rate = np.minimum(np.maximum(rate, -w), w)
    vmax = 0.5 * v
    up = np.minimum(g.climb_max_m_s, vmax)
    down = np.minimum(g.sink_max_m_s, vmax)
    climb = np.minimum(np.maximum(K_CLIMB_1_S * (g.alt_m - h), -down), up)
    if LAND in kinds:
        land = np.minimum(np.maximum(K_CLIMB_1_S * (g.alt_m + g.slope * np.hypot(d_e, d_n) - h), -down), 0.0)
        climb = land if uniform else np.where(kind == LAND, land, climb)
    if FINAL in kinds:
        fin = np.where(h > g.alt_m, -np.minimum(np.maximum(g.slope * v, K_CLIMB_1_S * (h - g.alt_m)), down), 0.0)
        climb = fin if uniform else np.where(kind == FINAL, fin, climb)
    speed = v
    if not uniform:
        still = kind == HOLD
        speed = np.where(still, 0.0, v)
        climb = np.where(still, 0.0, climb)
        rate = np.where(still, 0.0, rate)
        if scenario is not None:
            sc = kind == SCENARIO
            speed = np.where(sc, scenario[0], speed)
            climb = np.where(sc, scenario[1], climb)
            rate = np.where(sc, scenario[2], rate)
    return speed, climb, rate


class AutopilotLaw:
    """A vehicles.uav guidance law flying :class:`Guidance` g (module docstring).

    scenario_law: the scenario's law for the same N UAVs (a vehicles.uav law whose
    ``commands(t, y, aux)`` takes the full batch), evaluated for the SCENARIO UAVs; None: those
    UAVs hold (the caller flies them with the scenario's own swarm instead)."""

    def __init__(self, g: Guidance, scenario_law=None, ell: Ellipsoid | None = None):
        self.g = g
        self.batch_shape = (int(np.shape(g.kind)[0]),)
        self.scenario_law = scenario_law
        self.ell = ellipsoid(ell)

    def initial_heading(self, t_s, y):
        d_e, d_n = offsets(y[..., 0], y[..., 1], y[..., 2], self.g.lat_rad, self.g.lon_rad, self.ell)
        return np.arctan2(d_e, d_n)

    def target(self, state, t_next_s=None):
        return None

    def commands(self, t_s, y, aux=None):
        sc = None
        if self.scenario_law is not None and np.any(self.g.kind == SCENARIO):
            sc = _scenario_commands(self.scenario_law, t_s, y, self.ell)
        return commands(self.g, y, self.ell, sc)

    def advance(self, state, ell):
        return state.wp_index


def _scenario_commands(law, t_s, y, ell):
    from vehicles import uav
    if isinstance(law, (uav.WaypointMission, uav.Racetrack)):
        out = law.commands(t_s, y, None, ell)
    else:
        out = law.commands(t_s, y, None)
    n = y.shape[0]
    return tuple(np.broadcast_to(np.asarray(a, float), (n,)) for a in out)


def empty(n: int) -> Guidance:
    z = np.zeros(int(n))
    return Guidance(np.full(int(n), HOLD, dtype=np.int64), z.copy(), z.copy(), z.copy(), z.copy(), np.ones(int(n)),
                    z.copy(), np.full(int(n), math.radians(3.0)), np.full(int(n), 5.0), np.full(int(n), 5.0),
                    np.full(int(n), 0.05))
