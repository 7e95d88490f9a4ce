"""The locator's published estimate: the ECEF moments of each track, and the two-track mixture
while a track's mirror hypothesis is alive."""
from __future__ import annotations

import numpy as np

from .frame import ut_to_ecef

__all__ = ["ecef_moments", "mixture_moments"]


def ecef_moments(motion: str, y, P, fr, vel_doppler, vel_cov, on):
    """ECEF moments (x (T, 6), P (T, 6, 6)) of states (rows where ``on``; the others 0 and I):
    motion "cv", the unscented transform of the cylindrical Gaussian (ut_to_ecef: the banana's
    moments); "position", the position with the Doppler velocity (cross-covariance 0)."""
    T = y.shape[0]
    if motion == "cv":
        if on.all():  # every row (the steady state): no gather / scatter copies
            return ut_to_ecef(y, P, fr)
        x = np.zeros((T, 6))
        Px = np.broadcast_to(np.eye(6), (T, 6, 6)).copy()
        rows = np.flatnonzero(on)
        if rows.size:
            x[rows], Px[rows] = ut_to_ecef(y[rows], P[rows], fr.take(rows))
        return x, Px
    x = np.concatenate([y, vel_doppler], axis=-1)
    Px = np.zeros((T, 6, 6))
    Px[:, 0:3, 0:3] = P
    Px[:, 3:6, 3:6] = vel_cov
    return x, Px


def mixture_moments(x0, P0, x1, P1, score0, score1):
    """The two-component Gaussian mixture's mean and covariance (moments matched: the MMSE
    estimate), weights from the components' summed -2 log-likelihoods score0, score1 (k,)."""
    w = 1.0 / (1.0 + np.exp(np.clip(0.5 * (score1 - score0), -700, 700)))
    w0 = 1.0 - w
    xm = w0[:, None] * x0 + w[:, None] * x1
    d0, d1 = x0 - xm, x1 - xm
    Pm = (w0[:, None, None] * (P0 + d0[:, :, None] * d0[:, None, :])
          + w[:, None, None] * (P1 + d1[:, :, None] * d1[:, None, :]))
    return xm, Pm
