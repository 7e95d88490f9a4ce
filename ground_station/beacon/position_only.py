"""The seed's own beacon filter (eq 11; ``motion="position"``), kept for comparison: B only
(ECEF), predicted by the weighted least-squares Doppler velocity (eq 8), updated with the ranges.
On the seed geometry its Doppler velocity solve is ill-conditioned (nearly parallel lines of
sight amplify 0.1 m/s Doppler noise to tens of m/s across them)."""
from __future__ import annotations

import numpy as np

from .config import LocatorConfig
from .measurements import ObserverEpoch, fill_absent
from .update import gated_update

__all__ = ["position_only_step"]


def _doppler_velocity(B, obs: ObserverEpoch, kappa: float):
    """Weighted least-squares beacon velocity from the Dopplers (seed eq 8, any N >= 3).

    rdot_i = u_i . (V_i - V_B)  ->  u_i' V_B = u_i' V_i - rdot_i,  u_i = (U_i - B)/|U_i - B|;
    weight 1 / (var_v + kappa u_i' P_Vi u_i).  Returns (V (T, 3), Cov (T, 3, 3)); absent
    observers weigh 0 (a tiny ridge keeps fewer than 3 finite)."""
    d = obs.pos - B[..., None, :]
    u = d / np.linalg.norm(d, axis=-1, keepdims=True)
    b = np.sum(u * obs.vel, axis=-1) - obs.range_rate_m_s
    var = obs.var_range_rate_m2_s2 + kappa * np.einsum("tni,tnij,tnj->tn", u, obs.cov[..., 3:6, 3:6], u)
    wgt = np.where(obs.mask, 1.0 / var, 0.0)
    A = np.einsum("tni,tn,tnj->tij", u, wgt, u) + 1e-12 * np.eye(3)
    C = np.linalg.inv(A)
    return np.einsum("tij,tj->ti", C, np.einsum("tni,tn,tn->ti", u, wgt, b)), C


def position_only_step(x, P, obs: ObserverEpoch, config: LocatorConfig, dt_s: float, loglik: bool = False,
                       judge=None):
    """The seed's beacon filter (eq 11) on B only (ECEF), batched (module docstring).

    x (T, 3), P (T, 3, 3).  Returns (x, P, nis, used, gated, m2ll, V_hat (T, 3), Cov_V (T, 3, 3)).
    """
    x = np.asarray(x, float)
    P = np.asarray(P, float)
    obs = fill_absent(obs, x)
    T, N = obs.mask.shape
    kappa = config.kappa(dt_s)
    V, CV = _doppler_velocity(x, obs, kappa)
    if dt_s > 0:
        eps = 10.0  # m: central differences of V_hat(B)
        J = np.empty((T, 3, 3))
        for k in range(3):
            e = np.zeros(3)
            e[k] = eps
            J[..., k] = (_doppler_velocity(x + e, obs, kappa)[0] - _doppler_velocity(x - e, obs, kappa)[0]) / (2 * eps)
        F = np.eye(3) + dt_s * J
        x = x + dt_s * V
        P = F @ P @ np.swapaxes(F, -1, -2) + dt_s * dt_s * CV + config.position_q_m2_s3 * dt_s * np.eye(3)
        P = 0.5 * (P + np.swapaxes(P, -1, -2))
    d = obs.pos - x[..., None, :]
    r = np.linalg.norm(d, axis=-1)
    u = d / r[..., None]
    R = obs.var_range_m2 + kappa * np.einsum("tni,tnij,tnj->tn", u, obs.cov[..., 0:3, 0:3], u)
    # ranges only, as 2x2 blocks with a dummy unit second row so that gated_update applies
    H = np.zeros((T, N, 2, 3))
    H[..., 0, :] = -u
    R2 = np.zeros((T, N, 2, 2))
    R2[..., 0, 0] = R
    R2[..., 1, 1] = 1.0
    nu = np.stack([obs.range_m - r, np.zeros_like(r)], axis=-1)
    # (the dummy rows add nothing: zero innovation, zero Jacobian, unit variance)
    xo, Po, nis, used, gated, m2ll = gated_update(x, P, nu, H, R2, obs.mask, config, loglik, judge=judge)
    return xo, Po, nis, used, gated, m2ll, V, CV
