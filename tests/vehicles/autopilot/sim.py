"""The test harness of the autopilot: UAVs on the scenario's orbit (vehicles.uav.Racetrack, as
vehicles/process.py flies [uavs] pattern = "orbit") with the autopilot in the loop, stepped in
simulation time; distances by sitl.geodesy (ECEF -> ENU), independent of the autopilot's own
flat-earth offsets."""
from __future__ import annotations

import math

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl import geodesy
from vehicles import uav
from vehicles.autopilot import Autopilot, AutopilotSwarm
from vehicles.mavlink.mission import MissionItem

CENTER = (45.15, 30.15)
REL = mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT


def ring(n: int, radius_m: float = 15000.0, alt_m: float = 2000.0):
    """(n, 3) starts (lat deg, lon deg, h m) on a ring about CENTER (sitl.scenario's layout)."""
    out = []
    for i in range(n):
        a = 2.0 * math.pi * i / n + 0.3
        lat = CENTER[0] + math.degrees(radius_m * math.cos(a) / 6_371_000.0)
        lon = CENTER[1] + math.degrees(radius_m * math.sin(a) / (6_371_000.0 * math.cos(math.radians(CENTER[0]))))
        out.append((lat, lon, alt_m + 500.0 * (i % 3)))
    return np.array(out)


def orbit_swarm(starts, speed=100.0, dt_s=0.1):
    lat, lon = np.radians(starts[:, 0]), np.radians(starts[:, 1])
    law = uav.Racetrack.orbit_through(lat, lon, math.radians(CENTER[0]), math.radians(CENTER[1]), speed)
    return uav.UavSwarm(law, lat, lon, starts[:, 2], dt_s=dt_s)


def fleet(n=1, *, in_flight=True, starts=None, dt_s=0.5, config=None):
    """n UAVs: in flight on the orbit (armed, AUTO), or on the ground (disarmed, MANUAL; held)."""
    starts = ring(n) if starts is None else np.asarray(starts, float)
    if in_flight:
        sw = orbit_swarm(starts)
    else:
        sw = uav.UavSwarm(uav.Hold((len(starts),)), np.radians(starts[:, 0]), np.radians(starts[:, 1]),
                          starts[:, 2], dt_s=0.1)
    y = sw.state.y
    ap = Autopilot(y[:, 0], y[:, 1], y[:, 2], y[:, 3], in_flight=in_flight, config=config)
    return AutopilotSwarm(sw, ap, dt_s=dt_s)


class Run:
    """Steps a fleet at 1 s epochs, recording every event with its time and the track."""

    def __init__(self, fl, epoch_s=1.0):
        self.fl = fl
        self.epoch_s = epoch_s
        self.events = []  # (t, Event)
        self.track = []  # (t, (N, 4) y)

    def run(self, duration_s, until=None):
        t_end = self.fl.t_s + duration_s
        while self.fl.t_s < t_end - 1e-9:
            self.fl.step(self.fl.t_s + self.epoch_s)
            self.events += [(self.fl.t_s, e) for e in self.fl.events]
            self.track.append((self.fl.t_s, self.fl.state_y.copy()))
            if until is not None and until(self):
                return True
        return False

    def kinds(self, vehicle=0, kind=None):
        return [(t, e) for t, e in self.events if e.vehicle == vehicle and (kind is None or e.kind == kind)]

    def values(self, kind, vehicle=0):
        return [e.value for _, e in self.kinds(vehicle, kind)]


def item(seq, cmd, lat_deg=0.0, lon_deg=0.0, alt=0.0, p=(0.0, 0.0, 0.0, 0.0), frame=REL):
    return MissionItem(seq, frame, cmd, 0, 1, *[float(x) for x in p], int(round(lat_deg * 1e7)),
                       int(round(lon_deg * 1e7)), float(alt))


def ref_distance(y, lat_deg, lon_deg):
    """Horizontal distance (m) of states y (..., 4) from a point, by sitl.geodesy's ENU."""
    y = np.asarray(y, float)
    pos = geodesy.geodetic_to_ecef(y[..., 0], y[..., 1], y[..., 2])
    enu = geodesy.ecef_to_enu(pos, math.radians(lat_deg), math.radians(lon_deg), 0.0)
    return np.hypot(enu[..., 0], enu[..., 1])


def ref_distance_rad(y, lat_rad, lon_rad):
    return ref_distance(y, math.degrees(lat_rad), math.degrees(lon_rad))
