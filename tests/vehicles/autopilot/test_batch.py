"""Batched: UAVs in different modes stepped together give what each gives stepped alone; the
step's cost at N = 1000 (printed; run with -s to see it)."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from vehicles import uav
from vehicles.autopilot import Autopilot, AutopilotSwarm
from vehicles.autopilot import convention as cv
from vehicles.autopilot.core import DO_JUMP, NAV_WAYPOINT

from .sim import item, orbit_swarm, ring

R = mavlink
N_KINDS = 9


def command(ap, i, j, start):
    """UAV i (position j in the list) gets the j-th kind of treatment (j % N_KINDS)."""
    la, lo = start[0], start[1]
    k = j % N_KINDS
    if k == 1:
        items = [item(0, NAV_WAYPOINT, la, lo)] + [item(1, NAV_WAYPOINT, la + 0.1, lo, 300.0),
                                                   item(2, NAV_WAYPOINT, la + 0.1, lo + 0.15, 200.0),
                                                   item(3, DO_JUMP, p=(1, 1, 0, 0))]
        assert ap.set_mission(i, items).ok
    elif k == 2:
        assert ap.command(i, R.MAV_CMD_DO_REPOSITION, (-1, 1, 0, 0, la - 0.1, lo + 0.1, 400.0)).ok
    elif k == 3:
        assert ap.set_mode(i, cv.LOITER).ok
    elif k == 4:
        assert ap.set_mode(i, cv.RTL).ok
    elif k == 5:
        assert ap.set_mode(i, cv.FBWA).ok
    elif k == 6:
        assert ap.command(i, R.MAV_CMD_NAV_LAND, (0, 0, 0, 0, math.nan, math.nan, math.nan)).ok
    elif k == 7:  # on the ground, then a take-off
        assert ap.arm(i).ok and ap.takeoff(i, 150.0).ok
    elif k == 8:  # on the ground, disarmed, held
        pass


def build(starts, ground):
    sw = orbit_swarm(starts)
    y = sw.state.y
    ap = Autopilot(y[:, 0], y[:, 1], y[:, 2], y[:, 3], in_flight=~ground)
    return AutopilotSwarm(sw, ap, dt_s=0.5)


@pytest.mark.slow
def test_fifty_uavs_together_equal_each_alone():
    n = 50
    starts = ring(n)
    ground = np.array([j % N_KINDS in (7, 8) for j in range(n)])
    fl = build(starts, ground)
    for i in range(n):
        command(fl.ap, i, i, starts[i])
    alone = []
    for i in range(n):
        f1 = build(starts[i:i + 1], ground[i:i + 1])
        command(f1.ap, 0, i, starts[i])
        alone.append(f1)
    ev_all = {i: [] for i in range(n)}
    ev_one = {i: [] for i in range(n)}
    for t in range(2, 401, 2):  # 2 s epochs: every kind of UAV changes task in 400 s
        fl.step(float(t))
        for e in fl.events:
            ev_all[e.vehicle].append((t, e._replace(vehicle=0)))
        for i, f1 in enumerate(alone):
            f1.step(float(t))
            ev_one[i] += [(t, e) for e in f1.events]
    y_all = fl.state_y
    y_one = np.concatenate([f.state_y for f in alone])
    assert np.array_equal(y_all, y_one), np.abs(y_all - y_one).max(axis=0)
    assert ev_all == ev_one
    for field in ("mode", "phase", "armed", "cur", "kind", "task"):
        assert np.array_equal(getattr(fl.ap, field), np.concatenate([getattr(f.ap, field) for f in alone])), field
    kinds = set(fl.ap.mode.tolist())
    assert {cv.AUTO, cv.GUIDED, cv.LOITER, cv.RTL, cv.FBWA, cv.TAKEOFF, cv.MANUAL} <= kinds


def test_step_time_at_1000_uavs():
    n = 1000
    rng = np.random.default_rng(1)
    lat = np.radians(45.0 + rng.uniform(-0.5, 0.5, n))
    lon = np.radians(30.0 + rng.uniform(-0.5, 0.5, n))
    h = np.full(n, 2000.0)
    psi = rng.uniform(0, 2 * np.pi, n)
    ground = np.arange(n) % N_KINDS >= 7
    ap = Autopilot(lat, lon, h, psi, in_flight=~ground)
    starts = np.stack([np.degrees(lat), np.degrees(lon), h], -1)
    for i in range(n):
        command(ap, i, i, starts[i])
    ap.step(0.0, 0.1, lat, lon, h, psi)
    times = []
    for k in range(1, 51):
        w = time.perf_counter()
        g, ev = ap.step(0.1 * k, 0.1, lat, lon, h, psi)
        times.append(time.perf_counter() - w)
    law = __import__("vehicles.autopilot.guidance", fromlist=["AutopilotLaw"]).AutopilotLaw(g)
    st = uav.KinematicState(5.0, np.stack([lat, lon, h, psi], -1), np.zeros(n, dtype=int))
    w = time.perf_counter()
    uav.propagate(st, 5.1, law, 0.01, backend="numpy")
    t_prop = time.perf_counter() - w
    med = float(np.median(times))
    print(f"\nAutopilot.step N={n}: median {med * 1e3:.2f} ms, max {max(times) * 1e3:.2f} ms; "
          f"AutopilotLaw RK4 over one 0.1 s epoch (10 steps of 0.01 s): {t_prop * 1e3:.1f} ms")
    assert med < 0.1  # generous: the shared 2-core CI machine
    assert np.all(np.isfinite(g.speed_m_s))
