"""Radio beacon (seed 002): moving or static, batched, RK4 truth like the UAVs.

Modes (see the docstring of vehicles/uav/__init__.py for how the seed's laws are read):

* ``mode="printed"`` -- :func:`printed_beacon`: the beacon's velocity law exactly as
  printed (V_xi_p, V_eta_p, V_zeta_p: a = 12, b = 8.5, v0 = 115, d = 25, e = 17,
  w' = w_r = 0.02), a :class:`vehicles.uav.PrintedSwarm` integrated by RK4 at 0.01 s from
  the printed start point (the same as the UAVs') or from given ECEF start points (one
  beacon per Monte Carlo trial: the experiment draws each trial's start about the printed
  point, see sitl/app/experiments/beacon/world.py).
* ``mode="seed"`` -- the geodetic reading: start lat 47.3, lon 31, h 3200 m (the OCR:
  longitude 31, latitude 47.3), heading north at 115 + 10 sin(0.02 t) m/s with climb
  15 cos(0.01 t) (:func:`example_beacon_law`), a :class:`vehicles.uav.KinematicSwarm`.
* ``mode="legs"`` -- straight legs and constant-rate turns at 115 m/s
  (:func:`legs_and_turns`), level flight, first leg north.
* ``mode="racetrack"`` -- a holding pattern at 115 m/s (:func:`racetrack`): straight legs of
  200 s north and south joined by 180 deg right turns at 1.5 deg/s (radius 4.39 km), level,
  first leg north from the start: a 23 km x 8.8 km loop (period 2 x (200 + 120) = 640 s) whose
  centre is 11.5 km north and 4.39 km east of the start, flown for ever (held by guidance,
  vehicles.uav.Racetrack; the live default scenario's beacon: it stays within reach of a
  formation orbiting that area).
* ``mode="static"`` -- a beacon that does not move (:class:`vehicles.uav.Hold`).
"""
from __future__ import annotations

import math

import numpy as np

from sitl.constants import ellipsoid

from vehicles.uav import (
    PRINTED_COEFFS,
    PRINTED_START_PAPER_M,
    Hold,
    KinematicSwarm,
    LegsAndTurns,
    PrintedLaw,
    PrintedSwarm,
    Racetrack,
    SinusoidalLaw,
    paper_to_ecef,
)

__all__ = ["EXAMPLE_BEACON_START", "EXAMPLE_BEACON_SPEED_M_S", "BeaconSwarm", "example_beacon_law",
           "printed_beacon_law", "printed_beacon", "legs_and_turns", "racetrack", "example_beacon"]

#: Seed 002 beacon start, geodetic reading: (lat deg, lon deg, h m) (OCR: longitude 31, latitude 47.3).
EXAMPLE_BEACON_START = (47.3, 31.0, 3200.0)
#: Mean speed v0 of the printed V_eta_p law, m/s.
EXAMPLE_BEACON_SPEED_M_S = 115.0

_MODES = ("printed", "seed", "legs", "racetrack", "static")
_WGS84 = ellipsoid(None)


class BeaconSwarm(KinematicSwarm):
    """One or more beacons stepped together (a :class:`KinematicSwarm`)."""


def example_beacon_law() -> SinusoidalLaw:
    """Geodetic reading: heading north, 3-D speed 115 + 10 sin(0.02 t), climb 15 cos(0.01 t)."""
    return SinusoidalLaw(speed_mean_m_s=EXAMPLE_BEACON_SPEED_M_S, speed_amp_m_s=10.0, speed_omega_rad_s=0.02,
                         heading0_rad=0.0, climb_amp_m_s=15.0, climb_omega_rad_s=0.01)


def printed_beacon_law(n: int = 1) -> PrintedLaw:
    """The beacon's printed law, batch shape (n,) (one per trial)."""
    return PrintedLaw.from_coeffs([PRINTED_COEFFS["beacon"]]).repeat(n)


def printed_beacon(pos0_ecef_m=None, dt_s: float = 0.01, t0_s: float = 0.0) -> PrintedSwarm:
    """Beacons under the printed law from pos0_ecef_m (n, 3) (default: one, at the printed
    start point), RK4 step dt_s."""
    if pos0_ecef_m is None:
        pos0_ecef_m = paper_to_ecef(PRINTED_START_PAPER_M)[None]
    p = np.asarray(pos0_ecef_m, dtype=float)
    if p.ndim != 2 or p.shape[-1] != 3:
        raise ValueError(f"pos0_ecef_m must have shape (n, 3), got {p.shape}")
    return PrintedSwarm(printed_beacon_law(p.shape[0]), p, t0_s=t0_s, dt_s=dt_s)


def legs_and_turns(heading0_rad, speed_m_s: float = 115.0, leg_s: float = 200.0, turn_rad: float = math.pi / 2,
                   turn_rate_rad_s: float = math.radians(1.5), n_legs: int = 8, alternate: bool = True) -> LegsAndTurns:
    """A schedule of n_legs straight legs of leg_s seconds joined by turns of turn_rad at
    turn_rate_rad_s (right turns; alternately right and left with ``alternate``).  After the
    last leg the beacon flies straight on."""
    for name, v in (("speed_m_s", speed_m_s), ("leg_s", leg_s), ("turn_rad", turn_rad),
                    ("turn_rate_rad_s", turn_rate_rad_s)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
    if isinstance(n_legs, bool) or int(n_legs) != n_legs or n_legs < 1:
        raise ValueError(f"n_legs must be an integer >= 1, got {n_legs!r}")
    turn_s = turn_rad / turn_rate_rad_s
    switches, rates, t = [], [0.0], 0.0
    for k in range(int(n_legs) - 1):
        t += leg_s
        switches.append(t)
        rates.append(turn_rate_rad_s * (-1.0 if alternate and k % 2 else 1.0))
        t += turn_s
        switches.append(t)
        rates.append(0.0)
    if not switches:  # one leg: a single straight line
        switches, rates = [leg_s], [0.0, 0.0]
    return LegsAndTurns(speed_m_s, heading0_rad, np.array(switches), np.array(rates))


def racetrack(start, heading0_rad: float = 0.0, speed_m_s: float = EXAMPLE_BEACON_SPEED_M_S, leg_s: float = 200.0,
              turn_rate_rad_s: float = math.radians(1.5)) -> Racetrack:
    """A clockwise holding pattern (:class:`vehicles.uav.Racetrack`) entered at ``start`` (lat
    deg, lon deg, h m) at the beginning of its first leg, heading heading0_rad: legs of leg_s
    seconds, turns of radius speed / turn_rate_rad_s (the legs' axis through the pattern's
    centre, turn radius either side of it), flown again and again, held by guidance (no drift:
    see Racetrack).  The centre is a half leg along heading0 and a turn radius to its right of
    the start (in the guidance's own local flat metres, so the start lies on the pattern)."""
    for name, v in (("speed_m_s", speed_m_s), ("leg_s", leg_s), ("turn_rate_rad_s", turn_rate_rad_s)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
    lat, lon = math.radians(start[0]), math.radians(start[1])
    r, half = speed_m_s / turn_rate_rad_s, 0.5 * leg_s * speed_m_s
    sa, ca = math.sin(heading0_rad), math.cos(heading0_rad)
    d_e, d_n = half * sa + r * ca, half * ca - r * sa  # the centre from the start: L u + r n
    w2 = 1.0 - _WGS84.e2 * math.sin(lat) ** 2
    n_rad = _WGS84.a_m / math.sqrt(w2)
    m_rad = n_rad * (1.0 - _WGS84.e2) / w2
    return Racetrack(lat + d_n / m_rad, lon + d_e / (n_rad * math.cos(lat)), r, speed_m_s, axis_rad=heading0_rad,
                     half_length_m=half, max_turn_rate_rad_s=2.0 * turn_rate_rad_s)


def example_beacon(mode: str = "seed", dt_s: float = 0.01, t0_s: float = 0.0, start=EXAMPLE_BEACON_START):
    """The seed 002 beacon (batch shape ()) in the given mode, RK4 step dt_s.  ``start`` is the
    geodetic start of the geodetic modes; "printed" starts at the printed point (batch (1,))."""
    if mode not in _MODES:
        raise ValueError(f"mode must be one of {_MODES}, got {mode!r}")
    if mode == "printed":
        return printed_beacon(dt_s=dt_s, t0_s=t0_s)
    lat, lon, h = math.radians(start[0]), math.radians(start[1]), float(start[2])
    if mode == "seed":
        law = example_beacon_law()
    elif mode == "legs":
        law = legs_and_turns(0.0)
    elif mode == "racetrack":
        law = racetrack(start)
    else:
        law = Hold(())
    return BeaconSwarm(law, lat, lon, h, t0_s=t0_s, dt_s=dt_s)
