"""Unscented Kalman filter, batched over leading axes (trials and/or vehicles).

Scaled sigma points (Julier 2002; Wan & van der Merwe 2000):
  lambda = alpha^2 (n + kappa) - n,   c = sqrt(n + lambda)
  X_0 = x,  X_i = x + c L_i,  X_{n+i} = x - c L_i,   L L' = P (Cholesky)
  Wm_0 = lambda/(n+lambda),  Wc_0 = Wm_0 + 1 - alpha^2 + beta,  W_i = 1/(2(n+lambda))
The seed 001 choice is alpha = 1, beta = 0, kappa = 3 - n ("kappa + n = 3"), which gives
the seed's weights W_0 = kappa/(n+kappa), W_i = 1/(2(n+kappa)): ``SigmaPoints.julier(n)``.

Predict:  X = sigma(x, P);  x- = sum Wm f(X);  P- = sum Wc (f(X) - x-)(f(X) - x-)' + Q
Update:   X = sigma(x-, P-) (redrawn, so that Q reaches the measurement statistics)
          Z = h(X);  z^ = sum Wm Z;  S = sum Wc (Z - z^)(Z - z^)' + R
          Pxz = sum Wc (X - x-)(Z - z^)';  K = Pxz S^-1
          x+ = x- + K (z - z^);  P+ = P- - K S K'
For a linear h this covariance update equals the Joseph form exactly (it is tested
against the linear Kalman filter); with a nonlinear h, P- - K S K' is the form that keeps
the linearisation-error covariance inside S, so it is the one used here.

The sigma-point axis is the FIRST axis of X (2n+1, ..., n) so that models broadcast their
per-step context (e.g. satellite positions (..., S, 3)) against it without knowing it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import kernels
from .ekf import UpdateResult, _flatten
from .params import integer, number, param, require, reworded, validate
from .protocols import SigmaPointMeasurementModel, TransitionModel, full_R
from .protocols import require as require_model


_FINITE = reworded(number(numpy=True), "must be finite")


@dataclass(frozen=True)
class SigmaPoints:
    """Scaled symmetric sigma-point set for an n-dimensional state."""

    n: int = param(check=reworded(integer(1, numpy=True), "must be a positive integer"),
                   doc="dimension of the state the points are for")
    alpha: float = param(1e-3, check=_FINITE, doc="spread of the points around the mean (> 0)")
    beta: float = param(2.0, check=_FINITE,
                        doc="prior-distribution weight in Wc_0 (2: optimal for a Gaussian)")
    kappa: float = param(0.0, check=_FINITE, doc="secondary scaling: lambda = alpha^2 (n + kappa) - n")

    def __post_init__(self):
        validate(self)
        require(self.alpha > 0, "alpha", f"alpha must be > 0, got {self.alpha!r}")
        require(self.n + self.lam > 0, "kappa",
                f"n + lambda must be > 0 (n={self.n}, alpha={self.alpha}, kappa={self.kappa})")

    @classmethod
    def julier(cls, n: int) -> "SigmaPoints":
        """The seed 001 rule kappa + n = 3 (alpha = 1, beta = 0)."""
        return cls(n=n, alpha=1.0, beta=0.0, kappa=3.0 - n)

    @property
    def lam(self) -> float:
        return self.alpha**2 * (self.n + self.kappa) - self.n

    @property
    def c(self) -> float:
        return float(np.sqrt(self.n + self.lam))

    @property
    def Wm(self) -> np.ndarray:
        w = np.full(2 * self.n + 1, 0.5 / (self.n + self.lam))
        w[0] = self.lam / (self.n + self.lam)
        return w

    @property
    def Wc(self) -> np.ndarray:
        w = self.Wm.copy()
        w[0] += 1.0 - self.alpha**2 + self.beta
        return w


def _points_for(points, n):
    if points is None:
        return SigmaPoints(n)
    if points.n != n:
        raise ValueError(f"sigma points are for n={points.n}, the state has n={n}")
    return points


def ukf_predict(x, P, model: TransitionModel, dt, points: SigmaPoints | None = None, backend=None,
                exploit_linear=True):
    """Unscented prediction through model.f. Returns (x-, P-).

    The unscented transform of a linear map is exact: for a transition model with
    ``linear = True`` (and exploit_linear) the sigma points would return exactly
    x- = F x and P- = F P F' + Q, so those are computed directly (the same numbers to
    rounding, tested), which halves the cost of a UKF step on such models.
    """
    x = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    batch, xf, Pf = _flatten(x, P)
    n = xf.shape[-1]
    sp = _points_for(points, n)
    require_model(model, TransitionModel, "transition model")
    if exploit_linear and model.linear:
        F = np.asarray(model.F(x, dt), dtype=float)
        if F.ndim == 2:
            Pp = kernels.cov_predict(F, Pf, model.Q(dt), backend=backend)
            return model.f(x, dt), Pp.reshape(batch + (n, n))
    X = kernels.sigma_points(xf, Pf, sp.c, backend=backend)  # (K, N, n)
    Xf = model.f(X.reshape((2 * n + 1,) + batch + (n,)), dt).reshape(X.shape)
    mean, Pp = kernels.ut_moments(Xf, sp.Wm, sp.Wc, model.Q(dt), backend=backend)
    return mean.reshape(batch + (n,)), Pp.reshape(batch + (n, n))


def ukf_update(x, P, z, model: SigmaPointMeasurementModel, points: SigmaPoints | None = None,
               backend=None) -> UpdateResult:
    """Unscented update with sigma points redrawn from (x-, P-)."""
    x = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    batch, xf, Pf = _flatten(x, P)
    n = xf.shape[-1]
    sp = _points_for(points, n)
    K = 2 * n + 1
    require_model(model, SigmaPointMeasurementModel, "measurement model")
    X = kernels.sigma_points(xf, Pf, sp.c, backend=backend)
    Z = np.asarray(model.h(X.reshape((K,) + batch + (n,))), dtype=float)
    m = Z.shape[-1]
    Z = kernels.batched(Z, (K,) + batch + (m,)).reshape(K, -1, m)
    z = kernels.batched(np.asarray(z, dtype=float), batch + (m,)).reshape(-1, m)
    r_diag = model.R_diag()
    if r_diag is not None and np.ndim(r_diag) == 1:
        R = np.diag(r_diag)  # shared by all trials: broadcast, not copied, by the kernel
    elif r_diag is not None:
        R = kernels.batched(r_diag, batch + (m,)).reshape(-1, m)[..., None, :] * np.eye(m)
    else:
        R = kernels.batched(full_R(model), batch + (m, m)).reshape(-1, m, m)
    xo, Po, y, nis = kernels.ukf_update(xf, Pf, X, Z, z, R, sp.Wm, sp.Wc, backend=backend)
    return UpdateResult(xo.reshape(batch + (n,)), Po.reshape(batch + (n, n)), y.reshape(batch + (m,)), nis.reshape(batch))
