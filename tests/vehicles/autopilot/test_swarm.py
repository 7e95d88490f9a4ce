"""The autopilot in the loop changes nothing until a GCS commands: the seed scenarios' flight
(both [uavs] patterns, built as vehicles/process.py builds them) is bit-for-bit the plain
swarm's, and a command to one UAV leaves the others' bit-for-bit."""
from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.scenario import default_scenario
from vehicles import uav
from vehicles.autopilot import Autopilot, AutopilotSwarm
from vehicles.autopilot import convention as cv


pytestmark = pytest.mark.slow


def seed_swarm(pattern: str):
    """The vehicle process's swarm for the default scenario (VehicleGroup.__init__'s law)."""
    u = default_scenario().uavs
    pts = np.array(u.start_points())
    n = len(pts)
    if pattern == "orbit":
        lat_c, lon_c = (math.radians(v) for v in u.center)
        law = uav.Racetrack.orbit_through(np.radians(pts[:, 0]), np.radians(pts[:, 1]), lat_c, lon_c, u.speed_m_s)
    else:
        law = uav.SinusoidalLaw(speed_mean_m_s=np.full(n, u.speed_m_s), speed_amp_m_s=10.0, speed_omega_rad_s=0.02,
                                heading0_rad=0.0, climb_amp_m_s=15.0, climb_omega_rad_s=0.01)
    return uav.UavSwarm(law, np.radians(pts[:, 0]), np.radians(pts[:, 1]), pts[:, 2])


def with_autopilot(sw):
    y = sw.state.y
    return AutopilotSwarm(sw, Autopilot(y[:, 0], y[:, 1], y[:, 2], y[:, 3], in_flight=True, t0_s=sw.state.t_s))


@pytest.mark.parametrize("pattern", ["orbit", "north"])
@pytest.mark.parametrize("epoch_s, duration_s", [(1.0, 300.0), (0.1, 20.0)])
def test_no_command_is_bit_for_bit_the_current_flight(pattern, epoch_s, duration_s):
    plain, fl = seed_swarm(pattern), with_autopilot(seed_swarm(pattern))
    k = int(round(duration_s / epoch_s))
    for j in range(1, k + 1):
        t = j * epoch_s
        a, b = plain.step(t), fl.step(t)
        assert not fl.events
        for f in a._fields:
            assert np.array_equal(np.asarray(getattr(a, f)), np.asarray(getattr(b, f))), (f, t)
    ap = fl.ap
    assert np.all(ap.mode == cv.AUTO) and np.all(ap.armed) and np.all(ap.phase == cv.FLYING)
    assert all(ap.heartbeat(i)[2] == 217 for i in range(ap.n)) and not fl.own.any()


def test_a_command_to_one_uav_leaves_the_others_bit_for_bit():
    plain, fl = seed_swarm("orbit"), with_autopilot(seed_swarm("orbit"))
    for t in range(1, 31):
        plain.step(float(t)), fl.step(float(t))
    assert fl.ap.command(1, mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH).ok
    for t in range(31, 300):
        a, b = plain.step(float(t)), fl.step(float(t))
    others = np.arange(fl.n) != 1
    assert np.array_equal(a.pos_ecef_m[others], b.pos_ecef_m[others])
    assert np.array_equal(a.vel_ecef_m_s[others], b.vel_ecef_m_s[others])
    assert not np.allclose(a.pos_ecef_m[1], b.pos_ecef_m[1])  # UAV 1 flies home
    assert fl.own.tolist() == [False, True, False]


def test_clearing_the_mission_rejoins_the_scenario_pattern():
    fl = with_autopilot(seed_swarm("orbit"))
    from .sim import item
    from vehicles.autopilot.core import NAV_WAYPOINT
    assert fl.ap.set_mission(0, [item(0, NAV_WAYPOINT), item(1, NAV_WAYPOINT, 45.3, 30.3, 100.0)]).ok
    for t in range(1, 20):
        fl.step(float(t))
    assert fl.own[0] and fl.ap.kind[0] != 1
    assert fl.ap.set_mission(0, []).ok
    tu = fl.step(20.0)
    assert fl.last_guidance.kind[0] == 1 and np.all(np.isfinite(tu.pos_ecef_m))  # SCENARIO again
    assert abs(float(tu.speed_m_s[0]) - 100.0) < 1e-9  # the orbit law's speed


def test_checkpoint_pickle_resumes_identically():
    # the vehicle worker checkpoints its group by pickle (vehicles/process.py): the fleet must survive it
    import pickle
    fl = with_autopilot(seed_swarm("orbit"))
    assert fl.ap.command(0, mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH).ok
    for t in range(1, 11):
        fl.step(float(t))
    copy = pickle.loads(pickle.dumps(fl))
    for t in range(11, 40):
        a, b = fl.step(float(t)), copy.step(float(t))
    assert np.array_equal(a.pos_ecef_m, b.pos_ecef_m) and fl.ap.counters == copy.ap.counters
