"""UAV kinematics (vehicles/uav.py): RK4 truth of the seed 002 law and the waypoint mode.

* RK4 against scipy's solve_ivp (DOP853, tight tolerances) on the same ODE, and its 4th order;
* the compiled integrator against the numpy reference, for every guidance law;
* the seed law: geodetic start points, speed 100..110 m/s varying as 105 + 5 sin(0.02 t),
  altitude h0 + 1500 sin(0.01 t), ECEF velocity = derivative of the ECEF position;
* waypoint mode: reaches every waypoint in order with bounded turn and climb rates, and a
  mission upload restarts one vehicle's mission;
* legs and turns, hold; bad parameters.

Deterministic: no randomness.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from sitl import geodesy
from vehicles import uav


def seed_start():
    s = np.array(uav.SEED002_UAV_START)
    return np.radians(s[:, 0]), np.radians(s[:, 1]), s[:, 2]


# ============================================================================ RK4 and the ODE


def test_rk4_matches_solve_ivp_on_the_seed_law():
    law = uav.seed002_uav_law()
    st = uav.initial_state(law, *seed_start())
    t1 = 300.0
    out = uav.propagate(st, t1, law, dt_s=0.01)
    f = lambda t, yf: uav.geodetic_rates(t, yf.reshape(-1, 4), law).ravel()
    ref = solve_ivp(f, (0.0, t1), st.y.ravel(), method="DOP853", rtol=1e-13, atol=1e-15)
    assert ref.success
    y_ref = ref.y[:, -1].reshape(-1, 4)
    p = geodesy.geodetic_to_ecef(out.y[:, 0], out.y[:, 1], out.y[:, 2])
    p_ref = geodesy.geodetic_to_ecef(y_ref[:, 0], y_ref[:, 1], y_ref[:, 2])
    assert np.max(np.linalg.norm(p - p_ref, axis=-1)) < 1e-5  # m, after ~31 km of flight
    dpsi = np.abs(uav.wrap_pi(out.y[:, 3] - y_ref[:, 3]))
    assert np.max(dpsi) < 1e-12


def test_rk4_is_fourth_order():
    """Halving the step divides the global error by ~16 (a wrong RK4 tableau gives ~4 or ~2)."""
    law = uav.SinusoidalLaw(100.0, 10.0, 0.2, 0.0, 0.3, 0.5, 0.1, 0.0, 10.0, 0.1)  # fast, to see the error
    st = uav.initial_state(law, *(np.radians(40.0), np.radians(10.0), 1000.0))
    f = lambda t, y: uav.geodetic_rates(t, y, law)
    ref = solve_ivp(f, (0.0, 60.0), st.y, method="DOP853", rtol=1e-13, atol=1e-15).y[:, -1]
    errs = []
    for dt in (2.0, 1.0, 0.5):
        y = uav.propagate(st, 60.0, law, dt_s=dt).y
        errs.append(np.linalg.norm(geodesy.geodetic_to_ecef(*y[:3]) - geodesy.geodetic_to_ecef(*ref[:3])))
    ratios = errs[0] / errs[1], errs[1] / errs[2]
    assert all(12.0 < r < 20.0 for r in ratios), (errs, ratios)


@pytest.mark.parametrize("kind", ["sinusoid", "waypoints", "legs", "hold"])
def test_compiled_integrator_equals_numpy_reference(kind):
    lat, lon, h = seed_start()
    if kind == "sinusoid":
        law = uav.seed002_uav_law()
    elif kind == "waypoints":
        wps = [np.array([[lat[i] + 0.05, lon[i] + 0.02, 3500.0], [lat[i] + 0.05, lon[i] + 0.12, 3000.0]])
               for i in range(3)]
        law = uav.WaypointMission(wps, speed_m_s=100.0)
    elif kind == "legs":
        law = uav.LegsAndTurns(110.0, [0.3, 1.0, 2.0], [10.0, 20.005], [[0.0, 0.05, 0.0]] * 3)  # off-grid switch
    else:
        law = uav.Hold(3)
    st = uav.initial_state(law, lat, lon, h)
    a = uav.propagate(st, 25.0, law, dt_s=0.01, backend="numba")
    b = uav.propagate(st, 25.0, law, dt_s=0.01, backend="numpy")
    assert np.max(np.abs(uav.wrap_pi(a.y - b.y))) < 1e-9
    assert np.array_equal(a.wp_index, b.wp_index)


def test_propagate_in_pieces_equals_one_call():
    law = uav.seed002_uav_law()
    st = uav.initial_state(law, *seed_start())
    one = uav.propagate(st, 10.0, law, 0.01)
    piece = st
    for t in (0.005, 3.0, 3.0, 7.37, 10.0):
        piece = uav.propagate(piece, t, law, 0.01)
    assert piece.t_s == 10.0
    assert np.max(np.abs(piece.y - one.y)) < 1e-9


@pytest.mark.parametrize("kind", ["sinusoid", "waypoints", "legs", "hold"])
def test_track_equals_stepping_epoch_by_epoch(kind):
    """KinematicSwarm.track (one compiled call, batched truth) gives step()'s numbers bitwise."""
    lat, lon, h = seed_start()
    if kind == "sinusoid":
        law = uav.seed002_uav_law()
    elif kind == "waypoints":
        wps = [np.array([[lat[i] + 0.0002, lon[i] + 0.0002, 3200.0], [lat[i] + 0.02, lon[i] + 0.03, 3000.0]])
               for i in range(3)]
        law = uav.WaypointMission(wps, speed_m_s=100.0)
    elif kind == "legs":
        law = uav.LegsAndTurns(110.0, [0.3, 1.0, 2.0], [10.0, 20.005], [[0.0, 0.05, 0.0]] * 3)
    else:
        law = uav.Hold(3)
    times = np.array([0.0, 0.5, 3.0, 3.0, 7.37, 12.0, 20.0, 21.0, 30.0])
    a = uav.UavSwarm(law, lat, lon, h)
    steps = [a.step(float(t)) for t in times]
    b = uav.UavSwarm(law, lat, lon, h)
    tr = b.track(times)
    assert np.array_equal(tr.t_s, times)
    for f in uav.VehicleTruth._fields[1:]:
        assert np.array_equal(getattr(tr, f), np.stack([getattr(v, f) for v in steps])), f
    assert b.state.t_s == a.state.t_s and np.array_equal(b.state.y, a.state.y)
    assert np.array_equal(b.state.wp_index, a.state.wp_index)
    if kind == "waypoints":
        assert a.state.wp_index.max() > 0  # the waypoint switching was exercised
    # and it goes on from there like step()
    assert np.array_equal(b.step(31.0).pos_ecef_m, a.step(31.0).pos_ecef_m)


# ============================================================================ the seed law


@pytest.fixture(scope="module")
def seed_run():
    """The seed's three UAVs over 1000 s at the seed's RK4 step (0.01 s), sampled every 1 s."""
    sw = uav.seed002_uav_swarm(dt_s=0.01)
    return [sw.step(float(t)) for t in range(0, 1001)]


def test_seed_start_points_are_the_geodetic_values(seed_run):
    tr = seed_run[0]
    lat, lon, h = seed_start()
    expected = geodesy.geodetic_to_ecef(lat, lon, h)
    assert np.allclose(tr.pos_ecef_m, expected, atol=1e-6)
    # not the paper's copy error (one ECEF start value for every vehicle)
    assert np.min(np.linalg.norm(tr.pos_ecef_m[:, None] - tr.pos_ecef_m[None], axis=-1) + np.eye(3) * 1e9) > 10e3
    assert np.allclose(np.degrees(tr.lat_rad), [30.0, 30.1, 30.3]) and np.allclose(tr.h_m, [3000, 3100, 3500])


def test_seed_speed_range_and_sinusoidal_variation(seed_run):
    t = np.array([tr.t_s for tr in seed_run])
    v = np.array([np.linalg.norm(tr.vel_ecef_m_s, axis=-1) for tr in seed_run])  # (T, 3)
    assert v.min() >= 100.0 - 1e-9 and v.max() <= 110.0 + 1e-9
    assert v.min() < 100.01 and v.max() > 109.99  # it really varies over the whole band
    # least-squares fit a + b sin(0.02 t) + c cos(0.02 t): b = 5, c = 0, a = 105, no residual
    A = np.stack([np.ones_like(t), np.sin(0.02 * t), np.cos(0.02 * t)], axis=1)
    coef, *_ = np.linalg.lstsq(A, v, rcond=None)
    assert np.allclose(coef, [[105.0] * 3, [5.0] * 3, [0.0] * 3], atol=1e-9)
    assert np.max(np.abs(A @ coef - v)) < 1e-9
    period = 2 * math.pi / 0.02
    assert 300.0 < period < 600.0


def test_seed_altitude_and_heading_laws(seed_run):
    t = np.array([tr.t_s for tr in seed_run])
    h = np.array([tr.h_m for tr in seed_run])
    h0 = np.array(uav.SEED002_UAV_START)[:, 2]
    assert np.max(np.abs(h - (h0 + 1500.0 * np.sin(0.01 * t)[:, None]))) < 1e-6
    psi = np.array([tr.heading_rad for tr in seed_run])
    law = uav.seed002_uav_law()
    assert np.max(np.abs(uav.wrap_pi(psi - law.heading_at(t[:, None])))) < 1e-9


def test_ecef_velocity_is_the_derivative_of_ecef_position():
    sw = uav.seed002_uav_swarm(dt_s=0.01)
    a = sw.step(499.99).pos_ecef_m
    mid = sw.step(500.0)
    b = sw.step(500.01).pos_ecef_m
    fd = (b - a) / 0.02
    assert np.max(np.abs(fd - mid.vel_ecef_m_s)) < 1e-4  # central difference error ~ |a| dt^2 / 6


# ============================================================================ waypoint mode


def _mission(speed=100.0, turn=math.radians(3.0)):
    lat, lon, h = seed_start()
    wps = []
    for i in range(3):
        base = np.array([lat[i], lon[i]])
        legs = [(0.15, 0.0, 3500.0), (0.15, 0.2, 3000.0), (0.0, 0.25, 4000.0), (-0.05, 0.05, 3200.0)]
        wps.append(np.array([[base[0] + math.radians(a), base[1] + math.radians(b), c] for a, b, c in legs]))
    return uav.WaypointMission(wps, speed_m_s=speed, max_turn_rate_rad_s=turn, max_climb_m_s=5.0,
                               accept_radius_m=150.0)


def test_waypoint_mode_reaches_waypoints_in_order_with_bounded_rates():
    law = _mission()
    lat, lon, h = seed_start()
    sw = uav.UavSwarm(law, lat, lon, h, dt_s=0.01, heading0_rad=[math.pi / 2, math.pi, 0.0])  # off course
    dt = 0.25
    trs = [sw.truth()]
    reached_at = np.full((3, 4), np.nan)
    while sw.t_s < 3000.0 and np.any(sw.state.wp_index < law.n_waypoints):
        before = sw.state.wp_index.copy()
        trs.append(sw.step(round(sw.t_s + dt, 6)))
        for i in np.flatnonzero(sw.state.wp_index > before):
            reached_at[i, before[i]] = sw.t_s
    assert np.all(sw.state.wp_index == law.n_waypoints), sw.state.wp_index
    assert np.all(np.diff(reached_at, axis=1) > 0)  # in order
    psi = np.array([tr.heading_rad for tr in trs])
    h_ = np.array([tr.h_m for tr in trs])
    rate = np.abs(uav.wrap_pi(np.diff(psi, axis=0))) / dt
    assert rate.max() <= math.radians(3.0) * (1 + 1e-9)
    assert rate.max() > 0.99 * math.radians(3.0)  # the bound is actually used (initial turn)
    assert np.max(np.abs(np.diff(h_, axis=0))) / dt <= 5.0 * (1 + 1e-9)
    speed = np.array([np.linalg.norm(tr.vel_ecef_m_s, axis=-1) for tr in trs])
    assert np.allclose(speed, 100.0, atol=1e-9)
    # at each reach event the vehicle was within the acceptance radius of that waypoint
    for i in range(3):
        for k in range(4):
            tr = trs[int(round(reached_at[i, k] / dt))]
            wp = law.waypoints_rad_m[i][k]
            d = np.linalg.norm(geodesy.ecef_to_enu(tr.pos_ecef_m[i], *wp)[:2])
            assert d < 150.0 + 100.0 * dt, (i, k, d)


def test_mission_upload_restarts_one_vehicle():
    law = _mission()
    lat, lon, h = seed_start()
    sw = uav.UavSwarm(law, lat, lon, h, dt_s=0.05)
    sw.step(200.0)
    idx_before = sw.state.wp_index.copy()
    target = np.array([[lat[1] - math.radians(0.1), lon[1] - math.radians(0.05), 3100.0]])
    sw.upload_mission(1, target)
    assert sw.state.wp_index[1] == 0 and sw.state.wp_index[0] == idx_before[0]
    while sw.state.wp_index[1] == 0 and sw.t_s < 2000.0:
        sw.step(sw.t_s + 1.0)
    assert sw.state.wp_index[1] == 1
    d = np.linalg.norm(geodesy.ecef_to_enu(sw.truth().pos_ecef_m[1], *target[0])[:2])
    assert d < 150.0 + 100.0


def test_legs_and_turns_and_hold():
    law = uav.LegsAndTurns(115.0, 0.0, [100.0, 160.0], [0.0, math.radians(1.5), 0.0])
    sw = uav.KinematicSwarm(law, math.radians(31.0), math.radians(47.3), 3200.0, dt_s=0.01)
    assert abs(sw.step(100.0).heading_rad - 0.0) < 1e-12
    assert abs(sw.step(160.0).heading_rad - math.radians(90.0)) < 1e-9
    assert abs(sw.step(300.0).heading_rad - math.radians(90.0)) < 1e-9
    hold = uav.KinematicSwarm(uav.Hold(2), [0.5, 0.6], [0.1, 0.2], [100.0, 0.0])
    p0 = hold.truth().pos_ecef_m
    tr = hold.step(50.0)
    assert np.array_equal(tr.pos_ecef_m, p0) and not np.any(tr.vel_ecef_m_s)


# ============================================================================ bad parameters


@pytest.mark.parametrize("make, name", [
    (lambda: uav.SinusoidalLaw(-1.0), "speed_mean_m_s"),
    (lambda: uav.SinusoidalLaw(100.0, speed_amp_m_s=100.0), "speed_amp_m_s"),
    (lambda: uav.SinusoidalLaw(100.0, speed_amp_m_s=5.0, climb_amp_m_s=96.0), "climb_amp_m_s"),
    (lambda: uav.SinusoidalLaw(100.0, heading_omega_rad_s=float("nan")), "heading_omega_rad_s"),
    (lambda: uav.WaypointMission([np.array([[0.5, 0.5, 100.0]])], 100.0, max_turn_rate_rad_s=0.0),
     "max_turn_rate_rad_s"),
    (lambda: uav.WaypointMission([np.array([[30.0, 45.0, 100.0]])], 100.0), "waypoints_rad_m[0]"),
    (lambda: uav.WaypointMission([np.array([[0.5, 0.5, 100.0]])], 10.0, max_climb_m_s=20.0), "max_climb_m_s"),
    (lambda: uav.LegsAndTurns(100.0, 0.0, [10.0, 5.0], [0.0, 0.1, 0.0]), "switch_times_s"),
    (lambda: uav.UavSwarm(uav.seed002_uav_law(), *seed_start(), dt_s=0.0), "dt_s"),
    (lambda: uav.UavSwarm(uav.seed002_uav_law(), 30.0, 45.0, 3000.0), "lat0_rad"),
    (lambda: uav.seed002_uav_swarm().step(-1.0), "t1_s"),
    (lambda: uav.propagate(uav.initial_state(uav.Hold(1), 0.1, 0.1, 0.0), 1.0, uav.Hold(1), backend="gpu"),
     "backend"),
    (lambda: uav.seed002_uav_swarm().upload_mission(0, np.array([[0.5, 0.8, 100.0]])), "guidance"),
])
def test_bad_parameters_raise_value_error_naming_them(make, name):
    with pytest.raises(ValueError, match=name.replace("[", r"\[").replace("]", r"\]")):
        make()
