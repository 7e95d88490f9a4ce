"""Vehicles of one kind under one guidance law, stepped together in simulation time, and the
seed 002 example's three UAVs."""
from __future__ import annotations

import numpy as np

from sitl.constants import Ellipsoid, ellipsoid

from .guidance import WaypointMission
from .kernels import _integrate_track_nb, nb, ready
from .kinematics import KinematicState, VehicleTruth, _stack_truths, _step_times, initial_state, propagate, truth
from .laws import Hold, SinusoidalLaw
from .values import _STEP

#: Seed 002 start points of UAV-1..3: (lat deg, lon deg, h m) -- the paper's geodetic values
#: (the OCR: longitude 30 / 30.1 / 30.3, latitude 45 / 45.1 / 45.3).
EXAMPLE_UAV_START = ((45.0, 30.0, 3000.0), (45.1, 30.1, 3100.0), (45.3, 30.3, 3500.0))
#: Mean speeds v0 of UAV-1..3 in the printed V_eta laws, m/s.
EXAMPLE_UAV_SPEED_M_S = (100.0, 110.0, 110.0)


class KinematicSwarm:
    """Vehicles of one kind under one guidance law, stepped together in simulation time.

    ``step(t_s)`` integrates (RK4, dt_s) from the current time to t_s and returns the
    :class:`VehicleTruth`; ``state`` is the functional :class:`KinematicState` (the same
    numbers as :func:`propagate`).  ``upload_mission(i, waypoints)`` replaces vehicle i's
    waypoints in waypoint mode and restarts its mission.
    """

    def __init__(self, guidance, lat0_rad, lon0_rad, h0_m, *, t0_s: float = 0.0, dt_s: float = 0.01,
                 heading0_rad=None, ell: Ellipsoid | str | None = None):
        for attr in ("batch_shape", "commands", "initial_heading", "target", "advance"):
            if not hasattr(guidance, attr):
                raise ValueError(f"guidance must be a guidance law (no {attr}), got {guidance!r}")
        self.dt_s = _STEP("dt_s", dt_s)
        self.ell = ellipsoid(ell)
        self.guidance = guidance
        self.state = initial_state(guidance, lat0_rad, lon0_rad, h0_m, t0_s, heading0_rad)

    @property
    def n(self) -> int:
        return int(np.prod(self.guidance.batch_shape, dtype=np.int64))

    @property
    def t_s(self) -> float:
        return self.state.t_s

    def step(self, t_s: float) -> VehicleTruth:
        self.state = propagate(self.state, t_s, self.guidance, self.dt_s, self.ell)
        return self.truth()

    def truth(self) -> VehicleTruth:
        return truth(self.state, self.guidance, self.ell)

    def track(self, times_s) -> VehicleTruth:
        """``step(t)`` for each t of the increasing times_s (K,) in turn, the truths stacked
        on a leading axis (t_s (K,), pos_ecef_m (K, ..., 3), ...): the same numbers.

        With numba and a law the compiled integrator knows, every step runs in one compiled
        call (the per-epoch step boundaries are those ``step`` would take), and for the laws
        whose commands are plain functions of time (SinusoidalLaw, Hold) the truth is
        evaluated for all epochs at once: the same element-wise formulas."""
        ts_req = np.asarray(times_s, dtype=float).reshape(-1)
        if ts_req.size == 0:
            raise ValueError("times_s must hold at least one time")
        if nb is None or not hasattr(self.guidance, "_kernel_args") or np.any(np.diff(ts_req) < 0) \
                or ts_req[0] < self.state.t_s or not np.all(np.isfinite(ts_req)):
            return _stack_truths([self.step(float(t)) for t in ts_req])
        bp = getattr(self.guidance, "breakpoints_s", ())
        parts, ends, t0, n = [np.array([self.state.t_s])], [], self.state.t_s, 0
        for t in ts_req:
            seg = _step_times(t0, float(t), self.dt_s, bp)
            parts.append(seg[1:])
            n += seg.size - 1
            ends.append(n)
            t0 = float(t)
        law, params, extra = self.guidance._kernel_args()
        shape = self.state.y.shape[:-1]
        y = np.ascontiguousarray(self.state.y, dtype=float).reshape(-1, 4).copy()
        idx = np.ascontiguousarray(self.state.wp_index, dtype=np.int64).reshape(-1).copy()
        sw = np.ascontiguousarray(extra.get("switch_times_s", np.zeros(0)), dtype=float)
        tr = np.ascontiguousarray(extra.get("turn_rates_rad_s", np.zeros((y.shape[0], 1))), dtype=float)
        wp = np.ascontiguousarray(extra.get("waypoints", np.zeros((y.shape[0], 1, 3))), dtype=float)
        cnt = np.ascontiguousarray(extra.get("count", np.ones(y.shape[0])), dtype=np.int64)
        K = ts_req.size
        ys = np.empty((K,) + y.shape)
        idxs = np.empty((K, y.shape[0]), dtype=np.int64)
        ready(_integrate_track_nb)(law, y, idx, np.ascontiguousarray(params, dtype=float), sw, tr, wp, cnt,
                                   np.concatenate(parts), np.array(ends, dtype=np.int64), ys, idxs, self.ell.a_m,
                                   self.ell.e2)
        ys = ys.reshape((K,) + shape + (4,))
        idxs = idxs.reshape((K,) + shape)
        self.state = KinematicState(float(ts_req[-1]), y.reshape(shape + (4,)), idx.reshape(shape))
        if isinstance(self.guidance, (SinusoidalLaw, Hold)):
            tk = ts_req.reshape((K,) + (1,) * len(shape))
            out = truth(KinematicState(tk, ys, idxs), self.guidance, self.ell)
            return out._replace(t_s=ts_req.copy())
        return _stack_truths([truth(KinematicState(float(ts_req[k]), ys[k], idxs[k]), self.guidance, self.ell)
                              for k in range(K)])

    def upload_mission(self, i: int, waypoints_rad_m) -> None:
        if not isinstance(self.guidance, WaypointMission):
            raise ValueError(f"guidance must be a WaypointMission to upload a mission, got "
                             f"{type(self.guidance).__name__}")
        self.guidance = self.guidance.replace_vehicle(i, waypoints_rad_m)
        idx = self.state.wp_index.copy()
        idx[int(i)] = 0
        self.state = self.state._replace(wp_index=idx)


class UavSwarm(KinematicSwarm):
    """A swarm of UAVs (a :class:`KinematicSwarm`); see :func:`example_uav_swarm`."""


def example_uav_law() -> SinusoidalLaw:
    """The three UAVs of the seed 002 example, geodetic reading (vehicles.uav's docstring).

    Heading north (0), 3-D speed v0_i + 10 sin(0.02 t) with v0 = 100 / 110 / 110 m/s (the
    printed V_eta laws), climb 15 cos(0.01 t) (altitude h0 + 1500 sin(0.01 t), the printed
    r(t)).  Each UAV keeps its own speed law: the formation is not a rigid line."""
    return SinusoidalLaw(speed_mean_m_s=np.array(EXAMPLE_UAV_SPEED_M_S), speed_amp_m_s=10.0,
                         speed_omega_rad_s=0.02, heading0_rad=0.0, climb_amp_m_s=15.0, climb_omega_rad_s=0.01)


def example_uav_swarm(dt_s: float = 0.01, t0_s: float = 0.0) -> UavSwarm:
    """The seed 002 UAV-1..3 at their geodetic start points, RK4 step dt_s (seed: 0.01 s)."""
    s = np.array(EXAMPLE_UAV_START)
    return UavSwarm(example_uav_law(), np.radians(s[:, 0]), np.radians(s[:, 1]), s[:, 2], t0_s=t0_s, dt_s=dt_s)
