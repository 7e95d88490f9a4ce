"""Seed 002: a beacon's range and range rate measured at N observers (UAVs).

State of the beacon x = [B (3), V_B (3)] (ECEF, m and m/s), batched (..., 6). Observer i at
U_i with velocity V_i (its own navigation estimate, with covariance P_i over [U_i, V_i]):

    r_i    = |U_i - B| + w_r,                 u_i = (U_i - B) / r_i
    rdot_i = u_i . (V_i - V_B) + w_v          (positive when the range grows)

Jacobians (d = V_i - V_B):
    dr_i/dB = -u_i',          dr_i/dV_B = 0
    drdot_i/dB = -(d - rdot_i u_i)' / r_i,    drdot_i/dV_B = -u_i'
and with respect to the observer's own state (for its uncertainty):
    dr_i/dU_i = u_i',         drdot_i/dU_i = (d - rdot_i u_i)' / r_i,   drdot_i/dV_i = u_i'.

The observers' positions are estimates, not truth. ``observer_uncertainty``:
* "inflate" (default): R_i = diag(var_r, var_rdot) + J_i P_i J_i' (2x2 per observer, so R is
  block diagonal): the first-order effect of the observer's error on the measurement,
  treated as white -- the consider (Schmidt) update with the observer states as consider
  parameters whose errors do not persist from step to step;
* "ignore": R_i = diag(var_r, var_rdot), the observers taken as exact.
The measurement vector is ordered per observer: z = [r_1, rdot_1, r_2, rdot_2, ...].
Pure numpy; no I/O.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .params import array, choice, optional, param, require, validate

__all__ = ["ObserverRangeDoppler", "OBSERVER_UNCERTAINTY"]

OBSERVER_UNCERTAINTY = ("inflate", "ignore")


_STATES = array((..., -1, 3), copy=False, what="a finite numeric array of shape (..., N, 3)")
_VARIANCES = array(lo=0, lo_open=True, copy=False, what="finite numbers > 0")


@dataclass(frozen=True, eq=False)
class ObserverRangeDoppler:
    """Range and range rate of a beacon at N observers (module docstring).

    observer_pos_ecef_m, observer_vel_ecef_m_s: (..., N, 3); observer_cov: (..., N, 6, 6) over
    [U, V] (only used with "inflate"); var_range_m2, var_range_rate_m2_s2: scalar, (N,) or
    (..., N).
    """

    observer_pos_ecef_m: np.ndarray = param(check=_STATES, doc="the observers' estimated positions (ECEF), "
                                                              "(..., N, 3), m")
    observer_vel_ecef_m_s: np.ndarray = param(check=_STATES, doc="the observers' estimated velocities (ECEF), "
                                                                "(..., N, 3), m/s")
    var_range_m2: object = param(check=_VARIANCES, doc="range noise variance: a scalar, (N,) or (..., N), m^2")
    var_range_rate_m2_s2: object = param(check=_VARIANCES,
                                         doc="range-rate noise variance: a scalar, (N,) or (..., N), m^2/s^2")
    observer_cov: np.ndarray | None = param(
        None, check=optional(array((..., -1, 6, 6), copy=False, what="a finite numeric array of shape (..., N, 6, 6)")),
        doc="covariance of each observer's own [U, V] estimate, (..., N, 6, 6), m^2, m^2/s, m^2/s^2 (used with "
            "'inflate')")
    observer_uncertainty: str = param("inflate", check=choice(*OBSERVER_UNCERTAINTY),
                                      doc="'inflate': the observers' covariance added to R to first order; "
                                          "'ignore': the observers taken as exact")

    def __post_init__(self):
        validate(self)
        U, V = self.observer_pos_ecef_m, self.observer_vel_ecef_m_s
        N = U.shape[-2]
        require(N >= 1, "observer_pos_ecef_m", f"expected (..., N, 3) with N >= 1, got shape {U.shape}")
        require(V.shape[-2:] == (N, 3), "observer_vel_ecef_m_s", f"expected shape (..., {N}, 3), got shape {V.shape}")
        for name in ("var_range_m2", "var_range_rate_m2_s2"):
            v = getattr(self, name)
            require(v.ndim == 0 or v.shape[-1] in (1, N), name, f"expected a scalar or (..., {N}), got shape {v.shape}")
        if self.observer_uncertainty == "inflate":
            C = self.observer_cov
            require(C is not None, "observer_cov", "observer_cov must be given when observer_uncertainty='inflate'")
            require(C.shape[-3:] == (N, 6, 6), "observer_cov", f"expected shape (..., {N}, 6, 6), got shape {C.shape}")

    @property
    def n_observers(self) -> int:
        return self.observer_pos_ecef_m.shape[-2]

    @property
    def ndim_meas(self) -> int:
        return 2 * self.n_observers

    ndim_state = 6

    def _geometry(self, x):
        x = np.asarray(x, dtype=float)
        if x.ndim < 1 or x.shape[-1] != 6:
            raise ValueError(f"x must have shape (..., 6), got shape {x.shape}")
        d_pos = self.observer_pos_ecef_m - x[..., None, 0:3]
        r = np.sqrt(np.sum(d_pos * d_pos, axis=-1))
        u = d_pos / r[..., None]
        dv = self.observer_vel_ecef_m_s - x[..., None, 3:6]
        rdot = np.sum(u * dv, axis=-1)
        return r, u, dv, rdot

    def h(self, x):
        r, _, _, rdot = self._geometry(x)
        z = np.empty(r.shape[:-1] + (2 * r.shape[-1],))
        z[..., 0::2] = r
        z[..., 1::2] = rdot
        return z

    def _jac(self, x):
        r, u, dv, rdot = self._geometry(x)
        g = (dv - rdot[..., None] * u) / r[..., None]  # drdot/dU = -drdot/dB
        return r, u, rdot, g

    def h_and_H(self, x):
        r, u, rdot, g = self._jac(x)
        N = r.shape[-1]
        batch = r.shape[:-1]
        z = np.empty(batch + (2 * N,))
        z[..., 0::2] = r
        z[..., 1::2] = rdot
        H = np.zeros(batch + (2 * N, 6))
        H[..., 0::2, 0:3] = -u
        H[..., 1::2, 0:3] = -g
        H[..., 1::2, 3:6] = -u
        object.__setattr__(self, "_last_x", x)  # R depends on the linearisation point ("inflate")
        return z, H

    def H(self, x):
        return self.h_and_H(x)[1]

    def R_diag(self):
        if self.observer_uncertainty == "inflate":
            return None  # full (block-diagonal) R, see R()
        N = self.n_observers
        vr = np.broadcast_to(self.var_range_m2, np.shape(self.var_range_m2)[:-1] + (N,)) \
            if np.ndim(self.var_range_m2) else np.full(N, float(self.var_range_m2))
        vv = np.broadcast_to(self.var_range_rate_m2_s2, np.shape(self.var_range_rate_m2_s2)[:-1] + (N,)) \
            if np.ndim(self.var_range_rate_m2_s2) else np.full(N, float(self.var_range_rate_m2_s2))
        batch = np.broadcast_shapes(vr.shape[:-1], vv.shape[:-1])
        out = np.empty(batch + (2 * N,))
        out[..., 0::2] = vr
        out[..., 1::2] = vv
        return out

    def R(self, x=None):
        """Full R (..., 2N, 2N). With "inflate" it needs the linearisation point: the x of the
        last h_and_H call (what ekf_update does) unless given."""
        N = self.n_observers
        if self.observer_uncertainty == "ignore":
            d = self.R_diag()
            return d[..., None] * np.eye(2 * N)
        if x is None:
            x = getattr(self, "_last_x", None)
            if x is None:
                raise ValueError("R with observer_uncertainty='inflate' needs x (call h_and_H first)")
        r, u, rdot, g = self._jac(x)
        J = np.zeros(r.shape + (2, 6))  # (..., N, 2, 6) over [U_i, V_i]
        J[..., 0, 0:3] = u
        J[..., 1, 0:3] = g
        J[..., 1, 3:6] = u
        blk = J @ self.observer_cov @ np.swapaxes(J, -1, -2)  # (..., N, 2, 2)
        vr = np.broadcast_to(self.var_range_m2, r.shape)
        vv = np.broadcast_to(self.var_range_rate_m2_s2, r.shape)
        blk[..., 0, 0] += vr
        blk[..., 1, 1] += vv
        R = np.zeros(r.shape[:-1] + (2 * N, 2 * N))
        for i in range(N):
            R[..., 2 * i:2 * i + 2, 2 * i:2 * i + 2] = blk[..., i, :, :]
        return R
