"""Transition models: the beacon's constant velocity (ECEF, white acceleration) and the UAVs'
navigation errors as Gauss-Markov consider states ("consider")."""
from __future__ import annotations

import functools

import numpy as np

from filters.models import ConstantVelocity

__all__ = ["cv_matrices", "uav_error_transition"]


@functools.lru_cache(maxsize=64)
def cv_matrices(q: float, dt: float):
    """(F, Q) of the constant-velocity model (memoised: built every step otherwise)."""
    m = ConstantVelocity(3, q=q)
    F, Q = np.asarray(m.F(None, dt), float), np.asarray(m.Q(dt), float)
    F.flags.writeable = False
    Q.flags.writeable = False
    return F, Q


def uav_error_transition(P_prev, P_now, rho):
    """Transition A (..., 6, 6) of a UAV's navigation error between two epochs at which it
    sent covariances P_prev and P_now (..., 6, 6): first-order Gauss-Markov with
    correlations rho (6,) in its whitened error, A = L_now diag(rho) L_prev^-1 (L the Cholesky
    factors).  Then eps_now = A eps_prev + w with Cov(w) = L_now (I - diag(rho)^2) L_now' >= 0,
    so Cov(eps_now) = P_now exactly, however fast the UAV's filter shrank its covariance."""
    Ln, Lp = np.linalg.cholesky(P_now), np.linalg.cholesky(P_prev)
    # A' = L_prev^-T diag(rho) L_now'
    At = np.linalg.solve(np.swapaxes(Lp, -1, -2), np.asarray(rho, float)[:, None] * np.swapaxes(Ln, -1, -2))
    return np.swapaxes(At, -1, -2)
