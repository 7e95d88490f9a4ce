"""Extended Kalman filter, batched over leading axes (trials and/or vehicles).

Predict:  x- = f(x);                 P- = F P F' + Q,   F = df/dx at x
Update:   y = z - h(x-);  S = H P- H' + R;  K = P- H' S^-1
          x+ = x- + K y;  P+ = (I - K H) P- (I - K H)' + K R K'     (Joseph form)

x: (..., n)   P: (..., n, n)   z: (..., m)
The models supply f, F, Q, linear (filters.protocols.TransitionModel) and h_and_H, R_diag
(filters.protocols.MeasurementModel); see filters/models.py. The covariance algebra runs in
filters/kernels.py (numpy or compiled).
Functions are pure: they return new arrays and never modify their inputs.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from . import kernels
from .protocols import MeasurementModel, TransitionModel, full_R, require


class UpdateResult(NamedTuple):
    x: np.ndarray  # (..., n) posterior mean
    P: np.ndarray  # (..., n, n) posterior covariance
    y: np.ndarray  # (..., m) innovation z - h(x-)
    nis: np.ndarray  # (...,) normalised innovation squared y' S^-1 y


def measure(model: MeasurementModel, x):
    """(h(x), H(x)) from the model's h_and_H."""
    return require(model, MeasurementModel, "measurement model").h_and_H(x)


def _flatten(x, P):
    batch = x.shape[:-1]
    n = x.shape[-1]
    if P.shape != batch + (n, n):
        raise ValueError(f"P must have shape {batch + (n, n)} to match x {x.shape}, got {P.shape}")
    return batch, x.reshape(-1, n), P.reshape(-1, n, n)


def ekf_predict(x, P, model: TransitionModel, dt, backend=None):
    """x- = f(x),  P- = F P F' + Q.  Returns (x-, P-)."""
    x = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    batch, xf, Pf = _flatten(x, P)
    n = xf.shape[-1]
    require(model, TransitionModel, "transition model")
    F = np.asarray(model.F(x, dt), dtype=float)
    if F.ndim > 2:
        F = kernels.batched(F, batch + (n, n)).reshape(-1, n, n)
    x_pred = model.f(x, dt)
    P_pred = kernels.cov_predict(F, Pf, model.Q(dt), backend=backend)
    return x_pred, P_pred.reshape(batch + (n, n))


def ekf_update(x, P, z, model: MeasurementModel, backend=None) -> UpdateResult:
    """Joseph-form update with the measurement model linearised at the prior x-."""
    x = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    batch, xf, Pf = _flatten(x, P)
    n = xf.shape[-1]
    z = np.asarray(z, dtype=float)
    hx, H = measure(model, x)
    y = z - hx
    m = y.shape[-1]
    H = kernels.batched(H, batch + (m, n)).reshape(-1, m, n)
    yf = kernels.batched(y, batch + (m,)).reshape(-1, m)
    r_diag = model.R_diag()
    if r_diag is not None:
        r = kernels.batched(r_diag, batch + (m,)).reshape(-1, m)
        xo, Po, nis = kernels.joseph_update(xf, Pf, yf, H, r_diag=r, backend=backend)
    else:
        R = kernels.batched(full_R(model), batch + (m, m)).reshape(-1, m, m)
        xo, Po, nis = kernels.joseph_update(xf, Pf, yf, H, R=R, backend=backend)
    return UpdateResult(xo.reshape(batch + (n,)), Po.reshape(batch + (n, n)), y, nis.reshape(batch))


def ekf_step(x, P, z, transition: TransitionModel, measurement: MeasurementModel, dt, backend=None) -> UpdateResult:
    """One predict + update cycle; the same numbers as ekf_predict then ekf_update.

    For a linear transition with a shared F and a diagonal R, the covariance
    prediction and the sequential Joseph update run as one fused kernel (one pass
    over P instead of two), which is what batched Monte Carlo spends its time on.
    """
    x = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    require(transition, TransitionModel, "transition model")
    r_diag = require(measurement, MeasurementModel, "measurement model").R_diag()
    F = transition.F(x, dt) if transition.linear else None
    if F is None or np.ndim(F) != 2 or r_diag is None:
        x_pred, P_pred = ekf_predict(x, P, transition, dt, backend=backend)
        return ekf_update(x_pred, P_pred, z, measurement, backend=backend)
    batch, xf, Pf = _flatten(x, P)
    x_pred = xf @ F.T  # = transition.f(x) for a linear model, without its overhead
    return _fused_step(batch, x_pred, Pf, z, F, transition.Q(dt), measurement, r_diag, backend)


def ekf_predicted_step(x_pred, P, z, F, Q, measurement: MeasurementModel, backend=None) -> UpdateResult:
    """ekf_step with the predicted mean x- computed by the caller (a transition with a known
    input, x- = F x + B u, or one held in place): P- = F P F' + Q, then the Joseph update at x-.

    x_pred (..., n); P (..., n, n) the covariance BEFORE the prediction; F (n, n) or (..., n, n);
    Q (n, n) or (..., n, n). With a shared F and Q and a diagonal R the covariance prediction and
    the update run as ekf_step's fused kernel; otherwise as kernels.cov_predict then ekf_update
    (the same numbers either way, to rounding).
    """
    x_pred = np.asarray(x_pred, dtype=float)
    P = np.asarray(P, dtype=float)
    batch, xf, Pf = _flatten(x_pred, P)
    n = xf.shape[-1]
    F = np.asarray(F, dtype=float)
    Q = np.asarray(Q, dtype=float)
    r_diag = require(measurement, MeasurementModel, "measurement model").R_diag()
    if F.ndim == 2 and Q.ndim == 2 and r_diag is not None:
        return _fused_step(batch, xf, Pf, z, F, Q, measurement, r_diag, backend)
    if F.ndim > 2:
        F = kernels.batched(F, batch + (n, n)).reshape(-1, n, n)
    if Q.ndim > 2:
        Q = kernels.batched(Q, batch + (n, n)).reshape(-1, n, n)
    P_pred = kernels.cov_predict(F, Pf, Q, backend=backend).reshape(batch + (n, n))
    return ekf_update(x_pred, P_pred, z, measurement, backend=backend)


def _fused_step(batch, x_pred, Pf, z, F, Q, measurement, r_diag, backend) -> UpdateResult:
    """P- = F P F' + Q and the Joseph update at x_pred (N, n), one compiled pass over P."""
    n = x_pred.shape[-1]
    hx, H = measure(measurement, x_pred.reshape(batch + (n,)))
    m = hx.shape[-1]
    y = (np.asarray(z, dtype=float) - hx).reshape(-1, m)
    H = kernels.batched(H, batch + (m, n)).reshape(-1, m, n)
    r = kernels.batched(r_diag, batch + (m,)).reshape(-1, m)
    xo, Po, nis = kernels.predict_joseph_update(F, Q, x_pred, Pf, y, H, r, backend=backend)
    return UpdateResult(xo.reshape(batch + (n,)), Po.reshape(batch + (n, n)), y.reshape(batch + (m,)),
                        nis.reshape(batch))
