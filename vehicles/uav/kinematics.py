"""The geodetic state [lat, lon, h, heading] of a batch of vehicles, its ODE under a guidance law,
RK4 (numpy reference, or the compiled loop of kernels.py) and the truth (ECEF position and
velocity) at a state."""
from __future__ import annotations

import math
from typing import Callable, NamedTuple

import numpy as np

from sitl import geodesy
from sitl.constants import Ellipsoid, ellipsoid

from .geometry import _radii, wrap_pi
from .guidance import Racetrack, WaypointMission
from .kernels import _integrate_nb, nb, ready
from .values import _FINITE, _STEP, _real


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
    """dy/dt (..., 4) of y = [lat, lon, h, psi] under a guidance law (see vehicles.uav's docstring)."""
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
