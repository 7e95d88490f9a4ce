"""UAV kinematics (vehicles/uav/): RK4 truth of the seed 002 law and the waypoint mode.

* RK4 against scipy's solve_ivp (DOP853, tight tolerances) on the same ODE, and its 4th order;
* the compiled integrator against the numpy reference, for every guidance law;
* the seed law, geodetic reading: start points lat 45 / 45.1 / 45.3, lon 30 / 30.1 / 30.3
  (the OCR's order), speed v0_i + 10 sin(0.02 t) with v0 = 100 / 110 / 110, heading north,
  altitude h0 + 1500 sin(0.01 t), ECEF velocity = derivative of the ECEF position;
* the printed laws: RK4 (compiled and numpy) against solve_ivp, 4th order, the printed
  formulas by hand, the printed start point and the paper-axes mapping (xi, eta, zeta) =
  (ECEF y, z, x), track == step, the ~60 m/s climb the printed laws imply;
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
    s = np.array(uav.EXAMPLE_UAV_START)
    return np.radians(s[:, 0]), np.radians(s[:, 1]), s[:, 2]


# ============================================================================ RK4 and the ODE


@pytest.mark.slow
def test_rk4_matches_solve_ivp_on_the_seed_law():
    law = uav.example_uav_law()
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
        law = uav.example_uav_law()
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
    law = uav.example_uav_law()
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
        law = uav.example_uav_law()
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
    sw = uav.example_uav_swarm(dt_s=0.01)
    return [sw.step(float(t)) for t in range(0, 1001)]


def test_seed_start_points_are_the_geodetic_values(seed_run):
    tr = seed_run[0]
    lat, lon, h = seed_start()
    expected = geodesy.geodetic_to_ecef(lat, lon, h)
    assert np.allclose(tr.pos_ecef_m, expected, atol=1e-6)
    # not the paper's copy error (one ECEF start value for every vehicle)
    assert np.min(np.linalg.norm(tr.pos_ecef_m[:, None] - tr.pos_ecef_m[None], axis=-1) + np.eye(3) * 1e9) > 10e3
    assert np.allclose(np.degrees(tr.lat_rad), [45.0, 45.1, 45.3]) and np.allclose(tr.h_m, [3000, 3100, 3500])
    assert np.allclose(np.degrees(tr.lon_rad), [30.0, 30.1, 30.3])


def test_seed_speed_range_and_sinusoidal_variation(seed_run):
    t = np.array([tr.t_s for tr in seed_run])
    v = np.array([np.linalg.norm(tr.vel_ecef_m_s, axis=-1) for tr in seed_run])  # (T, 3)
    v0 = np.array(uav.EXAMPLE_UAV_SPEED_M_S)
    assert np.all(v.min(axis=0) >= v0 - 10.0 - 1e-9) and np.all(v.max(axis=0) <= v0 + 10.0 + 1e-9)
    assert np.all(v.min(axis=0) < v0 - 9.99) and np.all(v.max(axis=0) > v0 + 9.99)  # the whole band
    # least-squares fit a + b sin(0.02 t) + c cos(0.02 t): b = 10, c = 0, a = v0, no residual
    A = np.stack([np.ones_like(t), np.sin(0.02 * t), np.cos(0.02 * t)], axis=1)
    coef, *_ = np.linalg.lstsq(A, v, rcond=None)
    assert np.allclose(coef, [v0, [10.0] * 3, [0.0] * 3], atol=1e-9)
    assert np.max(np.abs(A @ coef - v)) < 1e-9
    period = 2 * math.pi / 0.02
    assert 300.0 < period < 600.0


def test_seed_altitude_and_heading_laws(seed_run):
    t = np.array([tr.t_s for tr in seed_run])
    h = np.array([tr.h_m for tr in seed_run])
    h0 = np.array(uav.EXAMPLE_UAV_START)[:, 2]
    assert np.max(np.abs(h - (h0 + 1500.0 * np.sin(0.01 * t)[:, None]))) < 1e-6
    psi = np.array([tr.heading_rad for tr in seed_run])
    assert np.max(np.abs(uav.wrap_pi(psi))) < 1e-9  # north all along


def test_ecef_velocity_is_the_derivative_of_ecef_position():
    sw = uav.example_uav_swarm(dt_s=0.01)
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


@pytest.mark.slow
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
    (lambda: uav.UavSwarm(uav.example_uav_law(), *seed_start(), dt_s=0.0), "dt_s"),
    (lambda: uav.UavSwarm(uav.example_uav_law(), 45.0, 30.0, 3000.0), "lat0_rad"),
    (lambda: uav.PrintedLaw.from_coeffs([[1.0, 2.0, 3.0]]), "rows"),
    (lambda: uav.PrintedSwarm(uav.printed_uav_law(), np.zeros((2, 3))), "pos0_ecef_m"),
    (lambda: uav.propagate_printed(np.zeros(3), 10.0, 5.0, uav.printed_uav_law(1)), "t1_s"),
    (lambda: uav.printed_uav_law(0), "n"),
    (lambda: uav.example_uav_swarm().step(-1.0), "t1_s"),
    (lambda: uav.propagate(uav.initial_state(uav.Hold(1), 0.1, 0.1, 0.0), 1.0, uav.Hold(1), backend="gpu"),
     "backend"),
    (lambda: uav.example_uav_swarm().upload_mission(0, np.array([[0.5, 0.8, 100.0]])), "guidance"),
])
def test_bad_parameters_raise_value_error_naming_them(make, name):
    with pytest.raises(ValueError, match=name.replace("[", r"\[").replace("]", r"\]")):
        make()


# ============================================================================ the printed laws


PRINTED_M_ECEF = uav.paper_to_ecef(uav.PRINTED_START_PAPER_M)


def test_paper_axes_mapping_against_a_hand_computation():
    """The printed start point is r (cos45 sin30, sin45, cos45 cos30), r = 6371 km + 3000 m:
    xi = ECEF y, eta = ECEF z, zeta = ECEF x (lat 45, lon 30 on a sphere)."""
    r = 6371e3 + 3000.0
    xi, eta, zeta = r * math.cos(math.radians(45)) * math.sin(math.radians(30)), r * math.sin(math.radians(45)), \
        r * math.cos(math.radians(45)) * math.cos(math.radians(30))
    assert np.allclose(uav.PRINTED_START_PAPER_M, [xi, eta, zeta], atol=1.0)  # printed to the metre
    x_sphere = r * np.array([math.cos(math.radians(45)) * math.cos(math.radians(30)),
                             math.cos(math.radians(45)) * math.sin(math.radians(30)), math.sin(math.radians(45))])
    assert np.allclose(PRINTED_M_ECEF, x_sphere, atol=1.0)
    assert np.array_equal(PRINTED_M_ECEF, [3903261.0, 2253549.0, 4507098.0])
    v = np.array([1.0, 2.0, 3.0])  # (xi, eta, zeta)
    assert np.array_equal(uav.paper_to_ecef(v), [3.0, 1.0, 2.0])
    assert np.array_equal(uav.ecef_to_paper(uav.paper_to_ecef(v)), v)


def test_printed_velocity_is_the_printed_formula():
    """UAV-1's law evaluated by hand from the printed formulas, in the paper's axes."""
    law = uav.printed_uav_law(1)
    t = 123.4
    xi, eta, zeta = 2.25e6, 4.52e6, 3.9e6
    r = 6.374e6 + 1500.0 * math.sin(0.01 * t)
    c = math.sqrt(1.0 - eta ** 2 / r ** 2)
    v_xi = -(5.0 + 0.5 * math.sin(0.02 * t)) / r * eta + 7.5 * math.cos(0.01 * t) * c
    v_eta = (100.0 + 10.0 * math.sin(0.02 * t)) * c + 15.0 * math.cos(0.01 * t) * eta / r
    v_zeta = math.sqrt(3.0) / 2.0 * (-(10.0 + math.sin(0.02 * t)) / r * eta + 15.0 * math.cos(0.01 * t) * c)
    got = uav.printed_velocity_ecef(t, uav.paper_to_ecef([xi, eta, zeta])[None], law)[0]
    assert np.allclose(uav.ecef_to_paper(got), [v_xi, v_eta, v_zeta], rtol=1e-13, atol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["numba", "numpy"])
def test_printed_rk4_matches_solve_ivp(backend):
    law = uav.PrintedLaw.from_coeffs(list(uav.PRINTED_COEFFS.values()))  # the 3 UAVs and the beacon
    x0 = np.broadcast_to(PRINTED_M_ECEF, (4, 3))
    t1 = 300.0 if backend == "numba" else 60.0
    out = uav.propagate_printed(x0, 0.0, t1, law, dt_s=0.01, backend=backend)
    f = lambda t, y: uav.printed_velocity_ecef(t, y.reshape(4, 3), law).ravel()
    ref = solve_ivp(f, (0.0, t1), x0.ravel(), method="DOP853", rtol=1e-13, atol=1e-9)
    assert ref.success
    assert np.max(np.abs(out - ref.y[:, -1].reshape(4, 3))) < 1e-6  # m, after up to ~35 km


def test_printed_rk4_is_fourth_order_and_compiled_equals_numpy():
    law = uav.PrintedLaw(50.0, 40.0, 100.0, 60.0, 50.0, 0.2, 0.3)  # fast, to see the error
    f = lambda t, y: uav.printed_velocity_ecef(t, y.reshape(1, 3), law).ravel()
    ref = solve_ivp(f, (0.0, 60.0), PRINTED_M_ECEF, method="DOP853", rtol=1e-13, atol=1e-9).y[:, -1]
    errs = [np.linalg.norm(uav.propagate_printed(PRINTED_M_ECEF, 0.0, 60.0, law, dt_s=dt, backend="numpy") - ref)
            for dt in (4.0, 2.0, 1.0)]
    ratios = errs[0] / errs[1], errs[1] / errs[2]
    assert all(12.0 < r < 20.0 for r in ratios), (errs, ratios)
    law3 = uav.printed_uav_law(5)
    a = uav.propagate_printed(PRINTED_M_ECEF, 0.0, 25.0, law3, backend="numba")
    b = uav.propagate_printed(PRINTED_M_ECEF, 0.0, 25.0, law3, backend="numpy")
    assert np.max(np.abs(a - b)) < 1e-6


def test_printed_swarm_track_equals_step_and_reads_as_printed():
    a, b = uav.printed_uav_swarm(3), uav.printed_uav_swarm(3)
    times = [0.0, 1.0, 2.5, 10.0, 10.005, 31.0]
    tr = a.track(times)
    for k, t in enumerate(times):
        s = b.step(t)
        assert np.allclose(tr.pos_ecef_m[k], s.pos_ecef_m, rtol=0, atol=1e-8)
        assert np.allclose(tr.vel_ecef_m_s[k], s.vel_ecef_m_s, rtol=0, atol=1e-10)
    assert np.array_equal(tr.pos_ecef_m[0], np.broadcast_to(PRINTED_M_ECEF, (3, 3)))  # one start for all
    # velocity = derivative of position (central difference along the RK4 track)
    c = uav.printed_uav_swarm(3)
    p1 = c.step(499.99).pos_ecef_m
    mid = c.step(500.0)
    p2 = c.step(500.01).pos_ecef_m
    assert np.max(np.abs((p2 - p1) / 0.02 - mid.vel_ecef_m_s)) < 1e-4
    # as printed, the vehicles climb ~60 m/s (the doubt the module docstring states)
    climb = (c.step(1000.0).h_m - mid.h_m) / 500.0
    assert np.all((40.0 < climb) & (climb < 70.0))
