"""One epoch of beacon measurements (ObserverEpoch) and their model: ranges and Dopplers at the
UAVs' own estimates, with the UAVs' navigation covariance as a consider term, and the 2x2
whitening of each observer's block."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["ObserverEpoch", "epoch_from_messages", "formation_spread", "fill_absent", "range_doppler_blocks", "second_order_var", "cholesky_2x2",
           "solve_lower_2x2"]

_sum = np.add.reduce  # what np.sum calls, without its per-call overhead (same numbers)


class ObserverEpoch(NamedTuple):
    """One epoch of beacon measurements for a batch of trials, padded to N observers.

    pos (T, N, 3), vel (T, N, 3): the UAVs' own estimates; cov (T, N, 6, 6) their covariance
    over [U, V]; range_m, range_rate_m_s, var_range_m2, var_range_rate_m2_s2 (T, N);
    mask (T, N) True where an observer is present.  Absent slots hold finite fillers.
    """

    pos: np.ndarray
    vel: np.ndarray
    cov: np.ndarray
    range_m: np.ndarray
    range_rate_m_s: np.ndarray
    var_range_m2: np.ndarray
    var_range_rate_m2_s2: np.ndarray
    mask: np.ndarray

    @property
    def n_trials(self) -> int:
        return self.pos.shape[0]

    def take(self, idx) -> "ObserverEpoch":
        return ObserverEpoch(*(a[idx] for a in self))

    @staticmethod
    def empty(n_trials: int, n_obs: int) -> "ObserverEpoch":
        cov = np.broadcast_to(np.eye(6), (n_trials, n_obs, 6, 6)).copy()
        z = np.zeros((n_trials, n_obs))
        return ObserverEpoch(np.zeros((n_trials, n_obs, 3)), np.zeros((n_trials, n_obs, 3)), cov, z + 1.0, z.copy(),
                             z + 1.0, z + 1.0, np.zeros((n_trials, n_obs), bool))


def epoch_from_messages(inputs: list[dict], n_trials: int, slots: dict | None = None) -> ObserverEpoch:
    """Per trial {uav id: BeaconMeasurement} -> padded arrays, UAVs in id order.  slots: {uav id:
    observer slot}, a fixed slot per UAV id, grown here with the ids first seen (None: each
    trial's UAVs packed in id order)."""
    per = [sorted(d.items(), key=lambda a: a[0]) for d in inputs]
    consider = slots is not None
    if consider:
        for now in per:
            for uid, _ in now:
                slots.setdefault(uid, len(slots))
    N = max(1, len(slots) if consider else max(len(p) for p in per))
    obs = ObserverEpoch.empty(n_trials, N)
    for k, now in enumerate(per):
        for j, (uid, m) in enumerate(now):
            i = slots[uid] if consider else j
            obs.pos[k, i] = m.uav_pos_ecef_m
            obs.vel[k, i] = m.uav_vel_ecef_m_s
            obs.cov[k, i] = m.uav_cov
            obs.range_m[k, i] = m.range_m
            obs.range_rate_m_s[k, i] = m.range_rate_m_s
            obs.var_range_m2[k, i] = m.var_range_m2
            obs.var_range_rate_m2_s2[k, i] = m.var_range_rate_m2_s2
            obs.mask[k, i] = True
    return obs


def formation_spread(obs: ObserverEpoch):
    """(sv2, sigma) (T,): the second singular value of the present UAVs' estimated positions about
    their centroid, and their RMS per-axis position sigma (is the formation wider than its own
    errors?)."""
    m = obs.mask
    n = m.sum(axis=-1)
    c = _sum(obs.pos * m[..., None], axis=-2) / np.maximum(n, 1)[:, None]
    d = (obs.pos - c[:, None]) * m[..., None]
    sv2 = np.sqrt(np.maximum(np.linalg.eigvalsh(np.swapaxes(d, -1, -2) @ d)[:, 1], 0.0))
    var = np.trace(obs.cov[..., 0:3, 0:3], axis1=-2, axis2=-1) / 3.0
    sig = np.sqrt(_sum(var * m, axis=-1) / np.maximum(n, 1))
    return sv2, sig


def fill_absent(obs: ObserverEpoch, anchor) -> ObserverEpoch:
    """Absent observers moved to a harmless finite place (1000 km from ``anchor`` along x,
    unit covariance) so that the geometry stays finite; their rows are zeroed anyway."""
    m = obs.mask
    if m.all():
        return obs
    filler = np.asarray(anchor, float)[..., None, 0:3] + np.array([1.0e6, 0.0, 0.0])
    one = np.ones_like(obs.range_m)
    return ObserverEpoch(np.where(m[..., None], obs.pos, filler), np.where(m[..., None], obs.vel, 0.0),
                         np.where(m[..., None, None], obs.cov, np.eye(6)), np.where(m, obs.range_m, one),
                         np.where(m, obs.range_rate_m_s, 0.0), np.where(m, obs.var_range_m2, one),
                         np.where(m, obs.var_range_rate_m2_s2, one), m)


def cholesky_2x2(S):
    """Cholesky factors of 2x2 blocks (..., 2, 2): (l11, l21, l22)."""
    l11 = np.sqrt(S[..., 0, 0])
    l21 = S[..., 1, 0] / l11
    l22 = np.sqrt(np.maximum(S[..., 1, 1] - l21 * l21, 1e-300))
    return l11, l21, l22


def solve_lower_2x2(l11, l21, l22, v):
    """L^-1 v for lower-triangular 2x2 factors; v (..., 2, k)."""
    a = v[..., 0, :] / l11[..., None]
    b = (v[..., 1, :] - l21[..., None] * a) / l22[..., None]
    shape = np.broadcast_shapes(a.shape, b.shape)
    out = np.empty(shape[:-1] + (2,) + shape[-1:])
    out[..., 0, :] = a
    out[..., 1, :] = b
    return out


def range_doppler_blocks(x, obs: ObserverEpoch, kappa: float):
    """(zhat (T, N, 2), H (T, N, 2, 6) wrt ECEF [B, V_B], R (T, N, 2, 2)) at x (T, 6).

    R = diag(var_r, var_v) + kappa J_i P_i J_i' (kappa 0: the UAVs taken as exact), J_i the
    Jacobian wrt UAV i's [U_i, V_i] -- which is minus the Jacobian wrt [B, V_B] (d r/dU = u =
    -d r/dB, d rdot/dU = -d rdot/dB, d rdot/dV_i = u = -d rdot/dV_B): the same numbers as
    ``ObserverRangeDoppler.R`` with "inflate", without forming the full 2N x 2N matrix."""
    T, N = obs.mask.shape
    # ObserverRangeDoppler's checks and formulas (_geometry, _jac, h_and_H), written out
    # here to spare building the model object every epoch: the same numbers
    if not (np.isfinite(obs.pos).all() and np.isfinite(obs.vel).all()):
        raise ValueError("observer_pos_ecef_m and observer_vel_ecef_m_s must be finite")
    for name in ("var_range_m2", "var_range_rate_m2_s2"):
        v = getattr(obs, name)
        if not ((v > 0).all() and np.isfinite(v).all()):
            raise ValueError(f"{name} must be finite and > 0")
    x = np.asarray(x, dtype=float)
    d_pos = obs.pos - x[..., None, 0:3]
    r = np.sqrt(_sum(d_pos * d_pos, axis=-1))
    u = d_pos / r[..., None]
    dv = obs.vel - x[..., None, 3:6]
    rdot = _sum(u * dv, axis=-1)
    g = (dv - rdot[..., None] * u) / r[..., None]
    zhat = np.empty(r.shape + (2,))
    zhat[..., 0] = r
    zhat[..., 1] = rdot
    H = np.zeros(r.shape + (2, 6))
    H[..., 0, 0:3] = -u
    H[..., 1, 0:3] = -g
    H[..., 1, 3:6] = -u
    R = np.zeros((T, N, 2, 2))
    if kappa > 0:
        R += kappa * np.einsum("tnai,tnij,tnbj->tnab", H, obs.cov, H)
    R[..., 0, 0] += obs.var_range_m2
    R[..., 1, 1] += obs.var_range_rate_m2_s2
    return zhat, H, R


def second_order_var(x, upos, uvel, P_rel):
    """Variance of the second-order terms of each range and range rate, 0.5 tr((Hess P)^2),
    with Hess the Hessian wrt the beacon's position and P_rel (T, N, 3, 3) the covariance of
    the beacon-UAV relative position: (var_r, var_v) (T, N).  Added to R it keeps an EKF
    honest where the ranges are comparable with that uncertainty (one linearisation is then
    poor, the Doppler's most: its position Jacobian scales as 1 / r).

        Hess r    = (I - u u') / r
        Hess rdot = -(rdot (I - u u') / r^2 + (u g' + g u') / r),  g = (I - u u') dv / r
    (u = (U - B) / r, dv = V - V_B, rdot = u . dv)."""
    d = upos - x[..., None, 0:3]
    r = np.sqrt(_sum(d * d, axis=-1))
    u = d / r[..., None]
    dv = uvel - x[..., None, 3:6]
    rdot = _sum(u * dv, axis=-1)
    g = (dv - rdot[..., None] * u) / r[..., None]
    M = np.eye(3) - u[..., :, None] * u[..., None, :]
    Hr = M / r[..., None, None]
    Hv = -(rdot[..., None, None] * M / (r * r)[..., None, None]
           + (u[..., :, None] * g[..., None, :] + g[..., :, None] * u[..., None, :]) / r[..., None, None])
    A, B = Hr @ P_rel, Hv @ P_rel
    return 0.5 * np.einsum("...ij,...ji->...", A, A), 0.5 * np.einsum("...ij,...ji->...", B, B)
