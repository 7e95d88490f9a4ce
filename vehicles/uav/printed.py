"""The seed's velocity laws as printed (vehicles.uav's docstring): an ODE of the ECEF position
itself, integrated by RK4 (numpy reference or a compiled loop), and the vehicles stepped under
them."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from filters.params import param, validate
from sitl import geodesy
from sitl.constants import Ellipsoid, ellipsoid

from .kernels import nb
from .kinematics import VehicleTruth, _stack_truths, _step_times, rk4_step
from .values import _FINITE, _STEP, _broadcast, _real

#: The printed start point (xi0, eta0, zeta0), m: the same for UAV-1..3 and the beacon.
PRINTED_START_PAPER_M = (2253549.0, 4507098.0, 3903261.0)
#: Printed law coefficients (a, b, v0, d, e, w', w_r) (vehicles.uav's docstring).
PRINTED_COEFFS = {
    "uav1": (5.0, 7.5, 100.0, 10.0, 15.0, 0.01, 0.01),
    "uav2": (10.0, 5.5, 110.0, 10.0, 15.0, 0.01, 0.01),
    "uav3": (15.0, 6.5, 110.0, 20.0, 19.0, 0.01, 0.01),
    "beacon": (12.0, 8.5, 115.0, 25.0, 17.0, 0.02, 0.02),
}


_R0_M, _R_AMP_M = 6.374e6, 1500.0
_SQRT3_2 = math.sqrt(3.0) / 2.0


def paper_to_ecef(v):
    """The paper's (xi, eta, zeta) (..., 3) -> ECEF (x, y, z) = (zeta, xi, eta) (vehicles.uav's docstring)."""
    v = np.asarray(v, dtype=float)
    return v[..., [2, 0, 1]]


def ecef_to_paper(v):
    """ECEF (x, y, z) (..., 3) -> the paper's (xi, eta, zeta) = (y, z, x)."""
    v = np.asarray(v, dtype=float)
    return v[..., [1, 2, 0]]


@dataclass(frozen=True, eq=False)
class PrintedLaw:
    """The seed's velocity laws as printed (vehicles.uav's docstring): a velocity field of time and
    the ECEF z (= the paper's eta) coordinate.  Fields a, b, v0, d, e (m/s), cross_omega (w')
    and radius_omega (w_r) (rad/s) broadcast to the batch shape (vehicles)."""

    a_m_s: Any = param(check=_FINITE, doc="a: the eta / r coefficient of V_xi, m/s")
    b_m_s: Any = param(check=_FINITE, doc="b: the cos(w' t) c coefficient of V_xi, m/s")
    v0_m_s: Any = param(check=_FINITE, doc="v0: the mean speed of V_eta, m/s")
    d_m_s: Any = param(check=_FINITE, doc="d: the eta / r coefficient of V_zeta, m/s")
    e_m_s: Any = param(check=_FINITE, doc="e: the cos(w' t) c coefficient of V_zeta, m/s")
    cross_omega_rad_s: Any = param(0.01, check=_FINITE, doc="w': the angular frequency of the cross terms, rad/s")
    radius_omega_rad_s: Any = param(0.01, check=_FINITE,
                                    doc="w_r: the angular frequency of r(t) = 6.374e6 + 1500 sin(w_r t) m, rad/s")
    batch_shape: tuple = field(init=False)

    _FIELDS = ("a_m_s", "b_m_s", "v0_m_s", "d_m_s", "e_m_s", "cross_omega_rad_s", "radius_omega_rad_s")

    def __post_init__(self):
        validate(self)
        object.__setattr__(self, "batch_shape", _broadcast(self, self._FIELDS))

    @classmethod
    def from_coeffs(cls, rows) -> "PrintedLaw":
        """From rows (a, b, v0, d, e, w', w_r) (:data:`PRINTED_COEFFS`' values)."""
        c = _FINITE("rows", rows)
        if c.ndim != 2 or c.shape[1] != 7:
            raise ValueError(f"rows must have shape (n, 7) (a, b, v0, d, e, w', w_r), got {c.shape}")
        return cls(*c.T)

    def params(self) -> np.ndarray:
        """(n, 7) parameter rows of the compiled integrator."""
        return np.stack([np.ravel(getattr(self, f)) for f in self._FIELDS], axis=-1)

    def repeat(self, n: int) -> "PrintedLaw":
        """A batch of n copies of a one-vehicle law (e.g. one beacon per Monte Carlo trial)."""
        if int(np.prod(self.batch_shape, dtype=np.int64)) != 1:
            raise ValueError(f"repeat needs a one-vehicle law, got batch shape {self.batch_shape}")
        return PrintedLaw(*(np.full(int(n), float(np.ravel(getattr(self, f))[0])) for f in self._FIELDS))


def printed_velocity_ecef(t_s, pos_ecef_m, law: PrintedLaw) -> np.ndarray:
    """ECEF velocity (..., 3) of the printed law at time t_s and ECEF positions (..., 3)."""
    pos = np.asarray(pos_ecef_m, dtype=float)
    t = float(t_s)
    r = _R0_M + _R_AMP_M * np.sin(law.radius_omega_rad_s * t)
    s = pos[..., 2] / r  # eta / r
    c = np.sqrt(np.maximum(1.0 - s * s, 0.0))
    s2 = math.sin(0.02 * t)
    cw = np.cos(law.cross_omega_rad_s * t)
    v_xi = -(law.a_m_s + 0.5 * s2) * s + law.b_m_s * cw * c
    v_eta = (law.v0_m_s + 10.0 * s2) * c + 15.0 * math.cos(0.01 * t) * s
    v_zeta = _SQRT3_2 * (-(law.d_m_s + s2) * s + law.e_m_s * cw * c)
    out = np.empty(np.broadcast_shapes(pos.shape, np.shape(v_xi) + (3,)))
    out[..., 0], out[..., 1], out[..., 2] = v_zeta, v_xi, v_eta
    return out


def propagate_printed(pos_ecef_m, t0_s: float, t1_s: float, law: PrintedLaw, dt_s: float = 0.01,
                      backend: str | None = None) -> np.ndarray:
    """ECEF positions (..., 3) at t1_s from pos_ecef_m at t0_s: RK4 with step dt_s on the grid
    t0 + k dt_s (the last step shortened to land on t1_s).

    backend 'numba' (default when installed: one compiled loop per vehicle) or 'numpy' (the
    reference: :func:`rk4_step` on :func:`printed_velocity_ecef`, vectorised); both evaluate
    the same formulas in the same order."""
    dt = _STEP("dt_s", dt_s)
    t0, t1 = _real("t0_s", t0_s), _real("t1_s", t1_s)
    if t1 < t0:
        raise ValueError(f"t1_s must be >= t0_s {t0}, got {t1_s!r}")
    x = _FINITE("pos_ecef_m", pos_ecef_m)
    shape = law.batch_shape
    try:
        x = np.broadcast_to(x, shape + (3,)).astype(float)
    except ValueError:
        raise ValueError(f"pos_ecef_m must broadcast to the law's batch shape {shape} + (3,), got {x.shape}") from None
    if backend is None:
        backend = "numba" if nb is not None else "numpy"
    if backend not in ("numba", "numpy") or (backend == "numba" and nb is None):
        raise ValueError(f"backend must be 'numba' (needs numba) or 'numpy', got {backend!r}")
    ts = _step_times(t0, t1, dt, ())
    if backend == "numba":
        y = np.ascontiguousarray(x.reshape(-1, 3)).copy()
        ys = np.empty((1,) + y.shape)
        _printed_track_nb(law.params(), y, ts, np.array([ts.size - 1], dtype=np.int64), ys)
        return y.reshape(shape + (3,))
    for ta, tb in zip(ts[:-1], ts[1:]):
        x = rk4_step(lambda t, xx: printed_velocity_ecef(t, xx, law), float(ta), x, float(tb - ta))
    return x


def _printed_truth(t_s, pos, law: PrintedLaw, ell) -> "VehicleTruth":
    vel = printed_velocity_ecef(t_s, pos, law)
    lat, lon, h = geodesy.ecef_to_geodetic(pos, ell)
    v_enu = np.matmul(geodesy.enu_rotation(lat, lon), vel[..., None])[..., 0]
    heading = np.mod(np.arctan2(v_enu[..., 0], v_enu[..., 1]), 2.0 * np.pi)
    return VehicleTruth(t_s, pos.copy(), vel, np.asarray(lat, float), np.asarray(lon, float), np.asarray(h, float),
                        heading, np.linalg.norm(vel, axis=-1))


class PrintedSwarm:
    """Vehicles under :class:`PrintedLaw`, stepped in simulation time like a
    :class:`KinematicSwarm` (``step``, ``truth``, ``track``; state: ECEF positions)."""

    def __init__(self, law: PrintedLaw, pos0_ecef_m, *, t0_s: float = 0.0, dt_s: float = 0.01,
                 ell: Ellipsoid | str | None = None):
        if not isinstance(law, PrintedLaw):
            raise ValueError(f"law must be a PrintedLaw, got {law!r}")
        self.law = law
        self.dt_s = _STEP("dt_s", dt_s)
        self.ell = ellipsoid(ell)
        x = _FINITE("pos0_ecef_m", pos0_ecef_m)
        try:
            self.pos = np.broadcast_to(x, law.batch_shape + (3,)).astype(float)
        except ValueError:
            raise ValueError(f"pos0_ecef_m must broadcast to {law.batch_shape} + (3,), got {x.shape}") from None
        self._t = _real("t0_s", t0_s)

    @property
    def n(self) -> int:
        return int(np.prod(self.law.batch_shape, dtype=np.int64))

    @property
    def t_s(self) -> float:
        return self._t

    def step(self, t_s: float) -> VehicleTruth:
        self.pos = propagate_printed(self.pos, self._t, t_s, self.law, self.dt_s)
        self._t = float(t_s)
        return self.truth()

    def truth(self) -> VehicleTruth:
        return _printed_truth(self._t, self.pos, self.law, self.ell)

    def track(self, times_s) -> VehicleTruth:
        """``step(t)`` for each of the increasing times_s (K,), stacked on a leading axis: the
        same numbers (the same step boundaries), in one compiled call with numba."""
        ts_req = np.asarray(times_s, dtype=float).reshape(-1)
        if ts_req.size == 0:
            raise ValueError("times_s must hold at least one time")
        if nb is None or np.any(np.diff(ts_req) < 0) or ts_req[0] < self._t or not np.all(np.isfinite(ts_req)):
            return _stack_truths([self.step(float(t)) for t in ts_req])
        parts, ends, t0, n = [np.array([self._t])], [], self._t, 0
        for t in ts_req:
            seg = _step_times(t0, float(t), self.dt_s, ())
            parts.append(seg[1:])
            n += seg.size - 1
            ends.append(n)
            t0 = float(t)
        shape = self.law.batch_shape
        y = np.ascontiguousarray(self.pos.reshape(-1, 3)).copy()
        K = ts_req.size
        ys = np.empty((K,) + y.shape)
        _printed_track_nb(self.law.params(), y, np.concatenate(parts), np.array(ends, dtype=np.int64), ys)
        self.pos = y.reshape(shape + (3,))
        self._t = float(ts_req[-1])
        pos = ys.reshape((K,) + shape + (3,))
        vel = np.stack([printed_velocity_ecef(float(ts_req[k]), pos[k], self.law) for k in range(K)])
        lat, lon, h = geodesy.ecef_to_geodetic(pos, self.ell)
        v_enu = np.matmul(geodesy.enu_rotation(lat, lon), vel[..., None])[..., 0]
        heading = np.mod(np.arctan2(v_enu[..., 0], v_enu[..., 1]), 2.0 * np.pi)
        return VehicleTruth(ts_req.copy(), pos, vel, np.asarray(lat, float), np.asarray(lon, float),
                            np.asarray(h, float), heading, np.linalg.norm(vel, axis=-1))


if nb is not None:
    @nb.njit(cache=True, nogil=True)
    def _printed_vel_nb(p, t, z):
        r = 6.374e6 + 1500.0 * math.sin(p[6] * t)
        s = z / r
        c = math.sqrt(max(1.0 - s * s, 0.0))
        s2 = math.sin(0.02 * t)
        cw = math.cos(p[5] * t)
        v_xi = -(p[0] + 0.5 * s2) * s + p[1] * cw * c
        v_eta = (p[2] + 10.0 * s2) * c + 15.0 * math.cos(0.01 * t) * s
        v_zeta = (math.sqrt(3.0) / 2.0) * (-(p[3] + s2) * s + p[4] * cw * c)
        return v_zeta, v_xi, v_eta

    @nb.njit(cache=True, nogil=True)
    def _printed_track_nb(params, y, ts, ends, ys):
        """RK4 of every vehicle over the step boundaries ts, recording ys[k] at ts[ends[k]];
        y (N, 3) ends at the last boundary."""
        for i in range(y.shape[0]):
            p = params[i]
            x0, x1, x2 = y[i, 0], y[i, 1], y[i, 2]
            j = 0
            for k in range(ends.size):
                for m in range(j, ends[k]):
                    ta = ts[m]
                    hh = ts[m + 1] - ta
                    a0, a1, a2 = _printed_vel_nb(p, ta, x2)
                    b0, b1, b2 = _printed_vel_nb(p, ta + 0.5 * hh, x2 + 0.5 * hh * a2)
                    c0, c1, c2 = _printed_vel_nb(p, ta + 0.5 * hh, x2 + 0.5 * hh * b2)
                    d0, d1, d2 = _printed_vel_nb(p, ts[m + 1], x2 + hh * c2)
                    x0 = x0 + (hh / 6.0) * (a0 + 2.0 * b0 + 2.0 * c0 + d0)
                    x1 = x1 + (hh / 6.0) * (a1 + 2.0 * b1 + 2.0 * c1 + d1)
                    x2 = x2 + (hh / 6.0) * (a2 + 2.0 * b2 + 2.0 * c2 + d2)
                j = ends[k]
                ys[k, i, 0], ys[k, i, 1], ys[k, i, 2] = x0, x1, x2
            y[i, 0], y[i, 1], y[i, 2] = x0, x1, x2


def printed_uav_law(n: int = 3) -> PrintedLaw:
    """UAV-1..3's printed laws; for n > 3 further UAVs whose coefficients are spread over the
    printed ranges by a low-discrepancy (golden-ratio) sequence: a in [5, 15], b in [5.5, 7.5],
    v0 in [100, 110], d in [10, 20], e in [15, 19], w' = w_r = 0.01 (an extension, not the paper)."""
    if isinstance(n, bool) or int(n) != n or n < 1:
        raise ValueError(f"n must be an integer >= 1, got {n!r}")
    rows = [PRINTED_COEFFS[f"uav{i + 1}"] for i in range(min(int(n), 3))]
    g = (math.sqrt(5.0) - 1.0) / 2.0
    for j in range(int(n) - 3):
        f1, f2, f3 = ((j + 1) * g) % 1.0, ((j + 1) * g * g * 1.7) % 1.0, ((j + 1) * 0.7548776662) % 1.0
        rows.append((5.0 + 10.0 * f1, 5.5 + 2.0 * f2, 100.0 + 10.0 * f3, 10.0 + 10.0 * f2, 15.0 + 4.0 * f1, 0.01, 0.01))
    return PrintedLaw.from_coeffs(rows)


def printed_uav_swarm(n: int = 3, dt_s: float = 0.01, t0_s: float = 0.0) -> PrintedSwarm:
    """n UAVs under the printed laws, all from the printed start point (ECEF)."""
    return PrintedSwarm(printed_uav_law(n), paper_to_ecef(PRINTED_START_PAPER_M), t0_s=t0_s,
                        dt_s=dt_s)
