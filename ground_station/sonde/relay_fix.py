"""The least-squares fix of one relay epoch (relay_fix): Gauss-Newton on the relayed pseudoranges
for the position and the path offset, then linear least squares on the pseudo-Dopplers for the
velocity and the oscillator term (Moroz et al., seed 004, eqs 22-23). Initialises relay tracks."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .measurements import relay_frame_point

__all__ = ["RelayFix", "relay_fix"]


class RelayFix(NamedTuple):
    pos_ecef_m: np.ndarray  # (3,)
    delta_d_m: float
    vel_ecef_m_s: np.ndarray  # (3,)
    osc_m_s: float
    cov_pos_dd: np.ndarray  # (4, 4) over [P, dd]
    cov_vel_osc: np.ndarray  # (4, 4) over [V, osc]
    iterations: int


def relay_fix(sat_pos, sat_vel, pr, prr, var_pr, var_prr, ground, *, max_iter: int = 30,
              tol_m: float = 1e-4) -> RelayFix | None:
    """Least-squares fix from one relay epoch, or None (< 4 satellites, singular geometry or no
    convergence).

    Gauss-Newton on pr_i = |S_i - P| + |P - G| + dd (4 unknowns: P and dd) weighted by
    1/var_pr, started 1 km above G (never on G itself, where K = (P - G)/|P - G| is
    undefined); then prr_i + K_i.W_i = (K_i + K).V + osc, linear in (V, osc), weighted by
    1/var_prr. Covariances (A' W A)^-1.
    """
    sp, sv = np.asarray(sat_pos, float), np.asarray(sat_vel, float)
    pr, prr = np.asarray(pr, float), np.asarray(prr, float)
    wp, wv = 1.0 / np.asarray(var_pr, float), 1.0 / np.asarray(var_prr, float)
    G = np.asarray(ground, float)
    if pr.size < 4:
        return None
    up = G / np.linalg.norm(G)
    P, dd = G + 1000.0 * up, 0.0
    A = np.empty((pr.size, 4))
    A[:, 3] = 1.0
    it = 0
    for it in range(1, max_iter + 1):
        dS = P - sp
        rho = np.linalg.norm(dS, axis=1)
        Ki = dS / rho[:, None]
        dG = P - G
        rG = max(float(np.linalg.norm(dG)), 1e-3)
        A[:, :3] = Ki + dG / rG
        res = pr - (rho + rG + dd)
        N = A.T @ (A * wp[:, None])
        try:
            step = np.linalg.solve(N, A.T @ (wp * res))
        except np.linalg.LinAlgError:
            return None
        P, dd = P + step[:3], dd + step[3]
        if not np.all(np.isfinite(step)):
            return None
        if np.linalg.norm(step) < tol_m:
            break
    else:
        return None
    dS = P - sp
    rho = np.linalg.norm(dS, axis=1)
    Ki = dS / rho[:, None]
    K = (P - G) / max(float(np.linalg.norm(P - G)), 1e-3)
    A[:, :3] = Ki + K
    try:
        cov_pd = np.linalg.inv(A.T @ (A * wp[:, None]))
        Nv = A.T @ (A * wv[:, None])
        cov_vo = np.linalg.inv(Nv)
    except np.linalg.LinAlgError:
        return None
    sol = cov_vo @ (A.T @ (wv * (prr + np.sum(Ki * sv, axis=1))))
    # back from the relay's frame point to the sonde (relay_frame_point, inverted to first order)
    P = P + (P - relay_frame_point(P, sol[:3], G))
    return RelayFix(P, float(dd), sol[:3], float(sol[3]), 0.5 * (cov_pd + cov_pd.T), 0.5 * (cov_vo + cov_vo.T), it)
