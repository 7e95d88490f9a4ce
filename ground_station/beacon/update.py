"""The locator's per-epoch filter step: predict, then the measurement update of the epoch's ranges
and Dopplers -- EKF (a gated, whitened sequential Joseph update), iterated EKF
(filters.iekf.iterated_update) or, with observer_uncertainty="consider", the Schmidt update
(filters.schmidt) with the UAVs' navigation errors as consider states.  Batched over trials;
absent or rejected observers have zero rows (gain exactly 0), so every trial may have its own N.
"""
from __future__ import annotations

import math

import numpy as np

from filters import kernels
from filters.iekf import iterated_update, relinearized_innovation
from filters.schmidt import schmidt_innovation, schmidt_update

from .config import LocatorConfig
from .frame import Frame, cyl_to_ecef, ecef_to_cyl, formation_frame
from .measurements import (
    ObserverEpoch,
    cholesky_2x2,
    fill_absent,
    range_doppler_blocks,
    second_order_var,
    solve_lower_2x2,
)
from .motion import cv_matrices, uav_error_transition

__all__ = ["cyl_step", "consider_step", "gated_update", "consider_update"]


def _m2ll(yw, Hw, P, logdet_r):
    """-2 log-likelihood (without 2 pi) of whitened innovations yw (T, M) with whitened
    Jacobians Hw (T, M, n) (zero rows for absent observers): nu' S^-1 nu + log det S,
    S = Hw P Hw' + I, plus log det R (logdet_r (T,))."""
    S = np.einsum("tai,tij,tbj->tab", Hw, P, Hw) + np.eye(yw.shape[-1])
    L = np.linalg.cholesky(S)
    w = np.linalg.solve(L, yw[..., None])[..., 0]
    return np.sum(w * w, axis=-1) + 2.0 * np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1) + logdet_r


# the iterated update's stopping rules (filters.iekf.iterated_update; LocatorConfig.update_iterations)
_STEP_TOL = 1e-3  # m, m/s: stop once no row's ECEF iterate moved by this much or more (a further
#                   update would relinearise at the same point)
_INNOVATION_TOL = 1e-3  # stop once relinearising changed no used innovation by this fraction of its
#                         noise sigma or more (the next update would repeat the last one)


def _iterate(y, y1, fr, xp, nu_prior, R, used, obs: ObserverEpoch, kappa: float, update, iterations: int):
    """The iterations of an iterated EKF update after the first one (filters.iekf.iterated_update):
    the epoch's ranges and Dopplers relinearised at each iterate's ECEF state (R kept at the
    prediction's, the used set the first update's), the prior (y, P) updated again by
    ``update(nu, (H wrt y, H wrt ECEF))``; stopped by the step (in ECEF, from the prediction xp)
    or by the innovation of the used rows (from nu_prior, in units of sqrt(diag R))."""
    z = np.stack([obs.range_m, obs.range_rate_m_s], axis=-1)
    at = {}

    def point(yi):  # the iterate in ECEF, with the Jacobian linearize needs at the same point
        at["y"] = yi
        at["x"], at["G"] = cyl_to_ecef(yi, fr, jacobian=True)
        return at["x"]

    def linearize(yi):
        if at.get("y") is not yi:
            point(yi)
        zh, He, _ = range_doppler_blocks(at["x"], obs, kappa)
        Hy = He @ at["G"][:, None]
        return relinearized_innovation(z, zh, Hy, y[:, None], yi[:, None]), (Hy, He)

    return iterated_update(y, y1, linearize, update, iterations, step_tol=_STEP_TOL, point=point, point_prior=xp,
                           innovation_tol=_INNOVATION_TOL, nu_prior=nu_prior,
                           sigma=np.sqrt(np.diagonal(R, axis1=-2, axis2=-1)), innovation_rows=used[..., None])


def cyl_step(y, P, fr: Frame, obs: ObserverEpoch, config: LocatorConfig, dt_s: float, loglik: bool = False,
             C=None, Pu_prev=None, judge=None):
    """One predict (over dt_s, skipped when 0) + update of the cylindrical filter, batched.

    y (T, 6), P (T, 6, 6) in the frames ``fr``; obs with T rows.  Returns (y, P, frame,
    nis (T,), used (T, N), gated (T, N), m2ll (T,) or None); the new frame is the epoch's;
    nis is NaN where no observer was used; m2ll (``loglik``) is -2 log p(z | past) of every
    present observer, gated or not (it scores hypotheses).  judge: None, or a callable
    (nu (T, N, 2), diag S (T, N, 2), mask (T, N)) -> mask (T, N) called once at the prior (the
    integrity monitor's verdict: the links it returns False for are neither used nor scored).
    """
    y = np.asarray(y, float)
    P = np.asarray(P, float)
    x, G = cyl_to_ecef(y, fr, jacobian=True)
    F6, Q = cv_matrices(float(config.q_m2_s3), float(dt_s))
    xp = x @ F6.T
    fr = formation_frame(obs.pos, obs.mask, xp[:, 0:3], fr, config.axis_ratio)
    y, Gi, G2 = ecef_to_cyl(xp, fr, jacobian=True)
    if dt_s > 0:
        F = Gi @ F6 @ G
        P = F @ P @ np.swapaxes(F, -1, -2) + Gi @ Q @ np.swapaxes(Gi, -1, -2)
        P = 0.5 * (P + np.swapaxes(P, -1, -2))
    if config.observer_uncertainty == "consider":
        return consider_step(y, P, C, fr, xp, Gi @ F6 @ G if dt_s > 0 else None, obs, config, dt_s, loglik,
                              Pu_prev, judge)
    obs = fill_absent(obs, xp)
    T, N = obs.mask.shape
    kappa = config.kappa(dt_s)
    zhat, H, R = range_doppler_blocks(xp, obs, kappa)
    if config.second_order_r:
        Pb = (G2 @ P @ np.swapaxes(G2, -1, -2))[:, None, 0:3, 0:3]
        var_r2, var_v2 = second_order_var(xp, obs.pos, obs.vel, Pb + obs.cov[..., 0:3, 0:3])
        R[..., 0, 0] += var_r2
        R[..., 1, 1] += var_v2
    H = H @ G2[:, None]  # wrt the cylindrical state
    nu = np.stack([obs.range_m, obs.range_rate_m_s], axis=-1) - zhat  # (T, N, 2)
    R_score = None
    if loglik and kappa > 1.0:
        # hypotheses are scored with the UAVs' per-epoch error variance (kappa = 1): kappa > 1
        # discounts their information for the update, and as a noise model its log det term
        # would favour whichever hypothesis projects less of the UAVs' covariance (measured:
        # it picked the mirror in 10 of 10 constellation trials)
        R0 = np.zeros_like(R)
        R0[..., 0, 0], R0[..., 1, 1] = obs.var_range_m2, obs.var_range_rate_m2_s2
        R_score = R0 + (R - R0) / kappa
    out = gated_update(y, P, nu, H, R, obs.mask, config, loglik, R_score, judge)
    if config.update_iterations > 1:  # iterated EKF: relinearise at the updated state
        used0 = out[3]
        it = _iterate(y, out[0], fr, xp, nu, R, used0, obs, kappa,
                      lambda nui, Hi: gated_update(y, P, nui, Hi[0], R, used0, config, False),
                      config.update_iterations).result
        if it is not None:
            out = (it[0], it[1], it[2], it[3], (out[3] | out[4]) & ~it[3], out[5])  # (judged mask: used | gated)
    return out + (fr,)


def consider_step(y, P, C, fr, xp, F, obs, config, dt_s, loglik, Pu_prev=None, judge=None):
    """observer_uncertainty="consider": the UAVs' navigation errors eps_i = U_i - U^_i as
    Schmidt (consider) states, first-order Gauss-Markov with correlation times
    uav_error_corr_s (position) and uav_vel_error_corr_s (velocity), covariance P_i (the
    UAV's own, sent with each message).  The filter carries C_i = Cov(state error, eps_i)
    (T, N, n, 6) per observer slot: predicted C_i <- F C_i A_i' with the transition
    eps_i(k) = A_i eps_i(k-1) + w, A_i = L_k diag(rho_p, rho_v) L_{k-1}^-1 (L the Cholesky
    factors of the UAV's covariance sent at the two epochs, Pu_prev (T, N, 6, 6) the previous
    ones): Gauss-Markov in the UAV's whitened error, so that Cov(eps_i(k)) is exactly the P_i
    sent now whatever the UAV's filter did meanwhile (a plain eps(k) = diag(rho) eps(k-1) + w
    needs Var(w) = P_k - rho^2 P_{k-1}, negative while the UAV's filter converges -- its
    covariance shrinks by half in the first second of the seed run -- and the joint covariance
    is then over-confident); the
    update is one batched update of the epoch's 2N rows with S = H P H' + H X + X' H' +
    blockdiag(J_i P_i J_i' + R_i), X_i = C_i J_i' (J_i = d z_i / d U_i = -H_i in ECEF),
    gain K = (P H' + X) S^-1, P -= K S K', C_i -= K (H C_i + E_i J_i P_i): the memory of
    the UAVs' errors in each direction of the state is the filter's own (no kappa).
    Returns (y, P, nis, used, gated, m2ll, frame, C)."""
    T = y.shape[0]
    n = y.shape[-1]
    obs = fill_absent(obs, xp)
    N = obs.mask.shape[1]
    if C is None or C.shape[1] != N:
        C0 = np.zeros((T, N, n, 6))
        if C is not None:
            C0[:, :C.shape[1]] = C[:, :N]
        C = C0
    if F is not None:
        tp, tv = float(config.uav_error_corr_s), float(config.uav_vel_error_corr_s)
        rp = math.exp(-dt_s / tp) if tp > 0 else 0.0
        rv = math.exp(-dt_s / tv) if tv > 0 else 0.0
        A = np.array([rp] * 3 + [rv] * 3)
        C = np.einsum("tij,tnjb->tnib", F, C)
        if Pu_prev is None:
            C = C * A
        else:
            # absent slots and new ones: the covariance kept
            seen = (Pu_prev[..., 0, 0] > 0)[..., None, None]
            Pn = np.where(obs.mask[..., None, None], obs.cov, np.where(seen, Pu_prev, np.eye(6)))
            C = C @ np.swapaxes(uav_error_transition(np.where(seen, Pu_prev, Pn), Pn, A), -1, -2)
    zhat, He, R0 = range_doppler_blocks(xp, obs, 0.0)
    _, G2 = cyl_to_ecef(y, fr, jacobian=True)
    if config.second_order_r:
        var_r2, var_v2 = second_order_var(xp, obs.pos, obs.vel, (G2 @ P @ np.swapaxes(G2, -1, -2))[:, None, 0:3, 0:3]
                                          + obs.cov[..., 0:3, 0:3])
        R0[..., 0, 0] += var_r2
        R0[..., 1, 1] += var_v2
    z = np.stack([obs.range_m, obs.range_rate_m_s], axis=-1)
    Hy = He @ G2[:, None]
    J = -He  # d z / d U_i (wrt UAV i's [U, V])
    out = consider_update(y, P, C, z - zhat, Hy, J, obs.cov, R0, obs.mask, config, False, None, judge)
    present = out[3] | out[4]  # obs.mask less the links the integrity monitor left out (judge)
    if config.update_iterations > 1:
        used0 = out[3]
        it = _iterate(y, out[0], fr, xp, z - zhat, R0, used0, obs, 0.0,
                      lambda nui, Hi: consider_update(y, P, C, nui, Hi[0], -Hi[1], obs.cov, R0, obs.mask, config,
                                                      False, used0),
                      config.update_iterations).result
        if it is not None:
            out = (it[0], it[1], it[2], it[3], present & ~it[3], out[5], it[6])
    y1, P1, nis, used, gated, _, C1 = out
    m2ll = None
    if loglik:
        # hypotheses are scored as by "inflate": the UAVs' errors white with their per-epoch
        # variance (R0 + J P_i J', no cross-covariances).  With the Schmidt S the log det term
        # favours whichever side projects less of the UAVs' covariance -- measured on the
        # printed run with the prior split in two halves by the side of the UAVs' plane: the
        # mirror was chosen in 18 of 20 three-satellite trials
        R1 = R0 + np.einsum("tnai,tnij,tnbj->tnab", He, obs.cov, He)
        l11, l21, l22 = cholesky_2x2(R1)
        pm = present[..., None]
        T, N = obs.mask.shape
        yw = solve_lower_2x2(l11, l21, l22, (z - zhat)[..., None])[..., 0]
        Hw = solve_lower_2x2(l11, l21, l22, Hy)
        m2ll = _m2ll((yw * pm).reshape(T, 2 * N), (Hw * pm[..., None]).reshape(T, 2 * N, n), P,
                     2.0 * np.sum(np.log(l11 * l22) * present, axis=-1))
    return y1, P1, nis, used, gated, m2ll, fr, C1


def consider_update(y, P, C, nu, Hy, J, Pe, R0, mask, config, loglik, used_fixed=None, judge=None):
    """The batched Schmidt update of consider_step (filters.schmidt, per observer 2 rows and its
    UAV's 6 consider states), gated per observer on its own block of S (the used set
    ``used_fixed`` when given: the iterations keep the first update's); -2 log-likelihood
    (``loglik``) of every present observer under the Schmidt S.  Returns (y, P, nis, used,
    gated, m2ll, C)."""
    T, N = mask.shape
    m = 2 * N
    inn = schmidt_innovation(P, C, Hy, J, Pe, R0)
    S, Sjj = inn.S, inn.S_blocks
    if judge is not None and used_fixed is None:
        mask = judge(nu, np.stack([Sjj[..., 0, 0], Sjj[..., 1, 1]], axis=-1), mask)
    # absent slots (a lost message) keep their cross-covariances with the state, and their
    # filler geometry can make their block indefinite: they are not used, so not factored
    s11, s21, s22 = cholesky_2x2(np.where(mask[..., None, None], Sjj, np.eye(2)))
    w = solve_lower_2x2(s11, s21, s22, nu[..., None])[..., 0]
    d = np.sum(w * w, axis=-1)
    if used_fixed is None:
        gated = mask & ~(d <= config.gate_chi2)
        used = mask & ~gated
    else:
        used = used_fixed
        gated = mask & ~used
    m2ll = None
    if loglik:
        um = np.repeat(mask, 2, axis=1).astype(float)
        Sm = S * um[:, :, None] * um[:, None, :] + np.eye(m) * (1.0 - um)[:, None, :]
        num = nu.reshape(T, m) * um
        L = np.linalg.cholesky(Sm)
        wv = np.linalg.solve(L, num[..., None])[..., 0]
        m2ll = np.sum(wv * wv, axis=-1) + 2.0 * np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1)
    up = schmidt_update(y, P, C, nu, Hy, J, Pe, inn, used)
    return up.x, up.P, up.nis, used, gated, m2ll, up.C


def gated_update(y, P, nu, H, R, mask, config, loglik, R_score=None, judge=None):
    """Gate per observer, whiten the 2x2 blocks, Joseph update.  Returns (y, P, nis, used,
    gated, m2ll); m2ll (``loglik``) with R_score in place of R when given."""
    T, N = mask.shape
    n = y.shape[-1]
    S = np.einsum("tnai,tij,tnbj->tnab", H, P, H) + R
    if judge is not None:
        mask = judge(nu, np.diagonal(S, axis1=-2, axis2=-1), mask)
    s11, s21, s22 = cholesky_2x2(S)
    w = solve_lower_2x2(s11, s21, s22, nu[..., None])[..., 0]
    d = np.sum(w * w, axis=-1)
    gated = mask & ~(d <= config.gate_chi2)
    used = mask & ~gated
    l11, l21, l22 = cholesky_2x2(R)
    yw_all = solve_lower_2x2(l11, l21, l22, nu[..., None])[..., 0]
    Hw_all = solve_lower_2x2(l11, l21, l22, H)
    m2ll = None
    if loglik:
        pm = mask[..., None]
        f11, f21, f22 = (l11, l21, l22) if R_score is None else cholesky_2x2(R_score)
        yw_s = yw_all if R_score is None else solve_lower_2x2(f11, f21, f22, nu[..., None])[..., 0]
        Hw_s = Hw_all if R_score is None else solve_lower_2x2(f11, f21, f22, H)
        m2ll = _m2ll((yw_s * pm).reshape(T, 2 * N), (Hw_s * pm[..., None]).reshape(T, 2 * N, n), P,
                     2.0 * np.sum(np.log(f11 * f22) * mask, axis=-1))
    yo, Po, nis = kernels.joseph_update(np.ascontiguousarray(y), np.ascontiguousarray(P),
                                        (yw_all * used[..., None]).reshape(T, 2 * N),
                                        (Hw_all * used[..., None, None]).reshape(T, 2 * N, n),
                                        r_diag=np.ones((T, 2 * N)), backend=config.backend)
    nis = np.where(used.any(axis=-1), nis, np.nan)
    return yo, Po, nis, used, gated, m2ll
