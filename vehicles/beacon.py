"""Radio beacon (seed 002): moving or static, batched, RK4 truth like the UAVs.

The beacon is a :class:`vehicles.uav.KinematicSwarm` with its own guidance law:

* ``mode="seed"`` -- :func:`seed002_beacon_law`, the character of the seed's beacon law
  (seed 002, "Пример", the V_xi_p, V_eta_p, V_zeta_p formulas): the dominant ECEF-eta term
  ``(115 + 10 sin 0.02t)`` and terms varying with 0.02t where the UAV laws have 0.01t.  As for
  the UAVs (see vehicles/uav.py) the printed ECEF formulas are damaged and cannot be used
  literally; the law of the same character is speed 115 + 5 sin(0.02 t) m/s, climb
  10 cos(0.02 t) m/s (altitude h0 +- 500 m), heading psi0 + 0.1 sin(0.02 t), psi0 the
  horizontal direction of the ECEF eta axis at the start point (119.2 deg at 31 N 47.3 E).
* ``mode="legs"`` -- straight legs and constant-rate turns at 115 m/s
  (:func:`legs_and_turns`), level flight.
* ``mode="static"`` -- a beacon that does not move (:class:`vehicles.uav.Hold`).

Start point (the seed's geodetic values): lat 31 deg, lon 47.3 deg, h 3200 m; the paper's
ECEF start values are a copy of the UAVs' (a copy error) and are not used.
"""
from __future__ import annotations

import math

import numpy as np

from vehicles.uav import Hold, KinematicSwarm, LegsAndTurns, SinusoidalLaw, eta_axis_heading_rad

__all__ = ["SEED002_BEACON_START", "BeaconSwarm", "seed002_beacon_law", "legs_and_turns", "seed002_beacon"]

#: Seed 002 beacon start: (lat deg, lon deg, h m).
SEED002_BEACON_START = (31.0, 47.3, 3200.0)

_MODES = ("seed", "legs", "static")


class BeaconSwarm(KinematicSwarm):
    """One or more beacons stepped together (a :class:`KinematicSwarm`)."""


def seed002_beacon_law(lat0_rad=math.radians(SEED002_BEACON_START[0]), lon0_rad=math.radians(SEED002_BEACON_START[1]),
                       heading_amp_rad: float = 0.1) -> SinusoidalLaw:
    """Speed 115 + 5 sin(0.02 t), climb 10 cos(0.02 t), heading psi0 + heading_amp sin(0.02 t)."""
    return SinusoidalLaw(speed_mean_m_s=115.0, speed_amp_m_s=5.0, speed_omega_rad_s=0.02,
                         heading0_rad=eta_axis_heading_rad(lat0_rad, lon0_rad), heading_amp_rad=heading_amp_rad,
                         heading_omega_rad_s=0.02, climb_amp_m_s=10.0, climb_omega_rad_s=0.02)


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


def seed002_beacon(mode: str = "seed", dt_s: float = 0.01, t0_s: float = 0.0, start=SEED002_BEACON_START) -> BeaconSwarm:
    """The seed 002 beacon (batch shape ()) in the given mode, RK4 step dt_s."""
    if mode not in _MODES:
        raise ValueError(f"mode must be one of {_MODES}, got {mode!r}")
    lat, lon, h = math.radians(start[0]), math.radians(start[1]), float(start[2])
    if mode == "seed":
        law = seed002_beacon_law(lat, lon)
    elif mode == "legs":
        law = legs_and_turns(eta_axis_heading_rad(lat, lon))
    else:
        law = Hold(())
    return BeaconSwarm(law, lat, lon, h, t0_s=t0_s, dt_s=dt_s)
