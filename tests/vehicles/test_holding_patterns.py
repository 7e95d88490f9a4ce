"""The default scenario's geometry (issue 19): UAVs orbiting [uavs].center, a beacon on its
racetrack, both held by guidance (vehicles.uav.Racetrack), and their scenario keys.

* an orbit stays on its circle over several loops, while a constant heading rate from the same
  start walks off (the meridian-convergence resonance the Racetrack docstring describes);
* the beacon's racetrack repeats itself and has the pattern's dimensions (legs, turn radius);
* the compiled integrator equals the numpy reference for the new law, through a leg-to-turn switch;
* VehicleGroup flies [uavs].pattern: "orbit" half a loop later puts each UAV across its circle,
  "north" keeps the seed law's northward flight;
* [uavs].pattern / [beacon].mode: bad values and an orbit too tight end in one line naming the key.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from sitl import geodesy
from sitl.scenario import ScenarioError, default_scenario, parse_scenario
from vehicles import beacon, uav


def _horizontal_from(pos_ecef_m, lat_rad, lon_rad):
    """(east, north) of ECEF points about a geodetic point at h = 0 (an independent measure: the
    tangent plane, not the guidance's flat lat/lon offsets)."""
    enu = geodesy.ecef_to_enu(pos_ecef_m, lat_rad, lon_rad, 0.0)
    return enu[..., 0], enu[..., 1]


def _ring():
    u = default_scenario().uavs
    pts = np.array(u.start_points())
    return np.radians(pts[:, 0]), np.radians(pts[:, 1]), pts[:, 2], math.radians(u.center[0]), math.radians(u.center[1])


@pytest.mark.slow
def test_orbit_stays_on_its_circle_while_a_constant_turn_walks_off():
    lat, lon, h, lat_c, lon_c = _ring()
    law = uav.Racetrack.orbit_through(lat, lon, lat_c, lon_c, 100.0)
    period = 2 * math.pi * float(np.mean(law.radius_m)) / 100.0
    times = np.arange(0.0, 3 * period, 30.0)
    orbit = uav.UavSwarm(law, lat, lon, h).track(times)
    # the same start, heading and nominal rate, but a constant heading rate (no guidance)
    heading = uav.initial_state(law, lat, lon, h).y[:, 3]
    turn = uav.LegsAndTurns(100.0, heading, np.zeros(0), (100.0 / law.radius_m)[:, None])
    const = uav.UavSwarm(turn, lat, lon, h).track(times)
    r_orbit = np.hypot(*_horizontal_from(orbit.pos_ecef_m, lat_c, lon_c))
    r_const = np.hypot(*_horizontal_from(const.pos_ecef_m, lat_c, lon_c))
    assert np.max(np.abs(r_orbit - r_orbit[0])) < 40.0  # metres, 3 loops of ~94 km
    assert np.max(np.abs(r_const[-1] - r_const[0])) > 150.0  # ~110 m per loop (Racetrack docstring)
    assert np.allclose(orbit.speed_m_s, 100.0) and np.allclose(np.linalg.norm(orbit.vel_ecef_m_s, axis=-1), 100.0)
    # clockwise: the bearing from the centre increases
    e, n = _horizontal_from(orbit.pos_ecef_m[:2], lat_c, lon_c)
    assert np.all(np.mod(np.arctan2(e[1], n[1]) - np.arctan2(e[0], n[0]), 2 * math.pi) < math.pi)


def test_beacon_racetrack_repeats_with_the_pattern_dimensions():
    scn = default_scenario()
    b = beacon.example_beacon("racetrack", start=scn.beacon.start)
    law = b.guidance
    r, L = 115.0 / math.radians(1.5), 0.5 * 200.0 * 115.0
    assert law.radius_m == pytest.approx(r) and law.half_length_m == pytest.approx(L)
    period = 2 * (200.0 + math.pi / math.radians(1.5))  # 640 s
    times = np.arange(0.0, 3 * period + 1.0, 1.0)
    tr = b.track(times)
    lat_c, lon_c = float(law.center_lat_rad), float(law.center_lon_rad)
    e, n = _horizontal_from(tr.pos_ecef_m, lat_c, lon_c)
    k1, k3 = int(period), int(3 * period)
    assert math.hypot(e[k3] - e[k1], n[k3] - n[k1]) < 5.0  # the second and third loops are the first's
    last = times >= period  # after the first loop (the start's tiny transient)
    assert np.ptp(n[last]) == pytest.approx(2 * (L + r), abs=60.0)
    assert np.ptp(e[last]) == pytest.approx(2 * r, abs=30.0)
    legs = np.abs(n) < L - 100.0  # on a leg: heading north (west leg) or south (east leg), r to the side
    assert np.all(np.abs(np.abs(e[legs & last]) - r) < 20.0)
    hd = np.degrees(tr.heading_rad[legs & last])
    assert np.all(np.minimum(np.abs(uav.wrap_pi(np.radians(hd))), np.abs(uav.wrap_pi(np.radians(hd) - math.pi)))
                  < math.radians(1.0))
    # the scenario's start centres the racetrack on the UAVs' orbit centre
    assert math.degrees(lat_c) == pytest.approx(scn.uavs.center[0], abs=0.002)
    assert math.degrees(lon_c) == pytest.approx(scn.uavs.center[1], abs=0.002)


@pytest.mark.slow
def test_compiled_racetrack_equals_numpy_reference():
    lat, lon, h, lat_c, lon_c = _ring()
    orbit = uav.Racetrack.orbit_through(lat, lon, lat_c, lon_c, 100.0)
    track = beacon.racetrack((45.0, 30.0, 300.0), leg_s=20.0)  # its first turn starts at 20 s
    for law, la, lo, hh in ((orbit, lat, lon, h), (track, math.radians(45.0), math.radians(30.0), 300.0)):
        st = uav.initial_state(law, la, lo, hh)
        a = uav.propagate(st, 25.0, law, dt_s=0.01, backend="numba")
        b = uav.propagate(st, 25.0, law, dt_s=0.01, backend="numpy")
        assert np.max(np.abs(uav.wrap_pi(a.y - b.y))) < 1e-9
    assert abs(uav.wrap_pi(a.y[3] - st.y[3])) > 0.1  # the racetrack's turn was entered (7.5 deg by 25 s)


def test_vehicle_group_flies_the_scenario_pattern():
    from sitl.bus import InMemoryTransport
    from vehicles.process import VehicleGroup

    for pattern in ("orbit", "north"):
        scn = default_scenario().replace(uavs={"pattern": pattern}, sonde={"enabled": False})
        g = VehicleGroup(scn, [0, 1, 2], InMemoryTransport(start_t_gps_s=scn.run.t0_gps_s), np.random.SeedSequence(0),
                         with_sonde=False)
        t0 = scn.run.t0_gps_s
        g.step(t0)
        p0 = np.array(g.last_uav_truth.pos_ecef_m)
        lat_c, lon_c = (math.radians(v) for v in scn.uavs.center)
        half = math.pi * scn.uavs.radius_m / scn.uavs.speed_m_s  # half a loop
        g.step(t0 + half)
        p1 = np.array(g.last_uav_truth.pos_ecef_m)
        e0, n0 = _horizontal_from(p0, lat_c, lon_c)
        e1, n1 = _horizontal_from(p1, lat_c, lon_c)
        if pattern == "orbit":  # across the circle: the opposite point
            np.testing.assert_allclose(e1, -e0, atol=200.0)
            np.testing.assert_allclose(n1, -n0, atol=200.0)
        else:  # north at ~100 m/s
            assert np.all(n1 - n0 > 0.9 * scn.uavs.speed_m_s * half)


@pytest.mark.parametrize("text, key, expected", [
    ('[uavs]\npattern = "circle"', "uavs.pattern", "orbit, north"),
    ("[uavs]\nradius_m = 1000.0", "uavs.radius_m", "at least 2005 m"),
    ("[uavs]\nstarts = [[45.15, 30.15, 100.0], [45.2, 30.1, 100.0], [45.1, 30.2, 100.0]]", "uavs.starts[0]",
     "from uavs.center"),
    ('[uavs]\nspeed_m_s = 0.0', "uavs.speed_m_s", "> 0"),
    ('[beacon]\nmode = "loop"', "beacon.mode", "racetrack"),
])
def test_pattern_keys_bad_values_one_line(text, key, expected):
    with pytest.raises(ScenarioError) as exc:
        parse_scenario(text)
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith("scenario: ") and key in msg and expected in msg, msg


def test_northbound_pattern_takes_any_ring():
    scn = parse_scenario('[uavs]\npattern = "north"\nradius_m = 0.0\n[beacon]\nmode = "legs"')
    assert scn.uavs.pattern == "north" and scn.beacon.mode == "legs"
