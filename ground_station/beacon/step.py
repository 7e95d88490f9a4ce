"""One filter step of the locator's stacked rows (its tracks and their mirror hypotheses): by motion
model ("cv": the cylindrical / ECEF filter, "position": the seed's position-only one) and, with
"consider", by acquisition (a track's first ``acquire_s`` run as "inflate")."""
from __future__ import annotations

import numpy as np

from .config import LocatorConfig
from .frame import Frame
from .position_only import position_only_step
from .update import cyl_step

__all__ = ["filter_rows"]


def filter_rows(config: LocatorConfig, acquire_config: LocatorConfig | None, y, P, fr, obs, dt, loglik, C=None,
                Pu=None, acq=None, judge=None):
    """One filter step on stacked rows (tracks and mirror hypotheses); returns (y, P, frame,
    nis, used, gated, m2ll, V, C): V the position-only filter's Doppler velocity (V, Cov_V) or
    None, C the consider cross-covariances ("consider" only, else None).  acq (rows,) bool:
    "consider" rows still in their acquisition (``acquire_s``), stepped by ``acquire_config``
    ("inflate") with their cross-covariances kept at 0.  judge: the integrity verdict (cyl_step), as
    judge(nu, s_diag, mask, rows=None) with rows the stacked rows of a subset."""
    c = config
    if c.motion == "cv":
        if c.observer_uncertainty == "consider":
            if acq is None or not acq.any():
                y, P, nis, used, gated, m2ll, fr, C_out = cyl_step(y, P, fr, obs, c, dt, loglik, C, Pu, judge)
                return y, P, fr, nis, used, gated, m2ll, None, C_out
            ca = acquire_config
            if acq.all():
                C_out = np.zeros_like(C)
                y, P, nis, used, gated, m2ll, fr = cyl_step(y, P, fr, obs, ca, dt, loglik, judge=judge)
                return y, P, fr, nis, used, gated, m2ll, None, C_out
            a, b = np.flatnonzero(acq), np.flatnonzero(~acq)
            ja = jb = None
            if judge is not None:
                def ja(nu, s, m):
                    return judge(nu, s, m, a)

                def jb(nu, s, m):
                    return judge(nu, s, m, b)
            ra = cyl_step(y[a], P[a], fr.take(a), obs.take(a), ca, dt, loglik, judge=ja)
            rb = cyl_step(y[b], P[b], fr.take(b), obs.take(b), c, dt, loglik, C[b], Pu[b], jb)
            C_out = np.zeros_like(C)
            C_out[b] = rb[7]
            out = []
            for i in range(6):  # y, P, nis, used, gated, m2ll
                if ra[i] is None:
                    out.append(None)
                    continue
                v = np.empty((y.shape[0],) + ra[i].shape[1:], ra[i].dtype)
                v[a], v[b] = ra[i], rb[i]
                out.append(v)
            frame = Frame(*(np.empty((y.shape[0],) + u.shape[1:], u.dtype) for u in ra[6]))
            for full, pa, pb in zip(frame, ra[6], rb[6]):
                full[a], full[b] = pa, pb
            y, P, nis, used, gated, m2ll = out
            return y, P, frame, nis, used, gated, m2ll, None, C_out
        else:
            y, P, nis, used, gated, m2ll, fr = cyl_step(y, P, fr, obs, c, dt, loglik, judge=judge)
        return y, P, fr, nis, used, gated, m2ll, None, None
    y, P, nis, used, gated, m2ll, V, CV = position_only_step(y, P, obs, c, dt, loglik, judge)
    return y, P, fr, nis, used, gated, m2ll, (V, CV), None
