"""U-D factorised (Bierman-Thornton) Kalman filter, batched over leading axes.

The covariance is never formed: it is carried as P = U diag(d) U' with U unit upper
triangular and d > 0 (Bierman 1977, "Factorization Methods for Discrete Sequential
Estimation"; Thornton & Bierman 1980; seed 003: the U-D form of the robust filter).

Predict (Thornton, modified weighted Gram-Schmidt):
    x- = f(x);   W = [F U | G],  Dw = diag(d, dq)  with Q = G diag(dq) G'
    so that P- = W Dw W' = F P F' + Q.  W is orthogonalised row by row, last row first,
    in the Dw-weighted inner product: d-_j = <w_j, w_j>, U-_ij = <w_i, w_j> / d-_j, then
    w_i -= U-_ij w_j for every i < j before the next row (the "modified" order).
    Q is factored once per call (cached per value): a diagonal Q by its nonzero entries,
    any other symmetric PSD Q by its eigendecomposition (G = eigenvectors with a positive
    eigenvalue), so a singular or non-diagonal Q is fine.
Update (Bierman, one scalar measurement at a time):
    f = U' h,  v = d * f,  alpha_0 = r,  alpha_j = alpha_{j-1} + f_j v_j
    d+_j = d_j alpha_{j-1} / alpha_j,   U+_ij = U_ij - (f_j / alpha_{j-1}) b_i^(j)  (i < j)
    b^(j) = sum_{k<j} U[:, k] v_k,   K = U v / alpha_n,   x+ = x + K y
    Every d+_j is a positive number times a ratio of positive numbers: d stays > 0 however
    ill-conditioned P is, which the conventional P - K H P does not guarantee.
The measurement model is linearised once at the prior x- (as in ekf_update): y = z - h(x-)
and H = H(x-); the k-th scalar update uses y_k - H_k (x - x-), the k-th innovation given
the k - 1 updates before it, so the sequence equals the vector EKF update exactly in
exact arithmetic, and nis = sum_k y_k'^2 / alpha_n(k) = y' S^-1 y.

Scalar updates need independent measurement errors. A model with ``R_diag()`` (not None)
is processed as it is; a model with only a full R is first decorrelated by the Cholesky
factor L of R (R = L L'): y <- L^-1 y, H <- L^-1 H, r = 1. The returned y is always the
innovation z - h(x-) in the model's own coordinates, as in ekf_update.

Shapes: x (..., n), U (..., n, n), d (..., n), z (..., m). Pure functions: inputs are
never modified. The numpy code here is the reference; see ``backend`` for the compiled one.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

from . import kernels
from .ekf import measure
from .protocols import MeasurementModel, TransitionModel, full_R, require

__all__ = ["UDUpdateResult", "ud_factor", "ud_to_cov", "ud_predict", "ud_update", "ud_step", "factor_q"]


class UDUpdateResult(NamedTuple):
    x: np.ndarray  # (..., n) posterior mean
    U: np.ndarray  # (..., n, n) unit upper triangular factor
    d: np.ndarray  # (..., n) diagonal factor, > 0
    y: np.ndarray  # (..., m) innovation z - h(x-)
    nis: np.ndarray  # (...,) normalised innovation squared y' S^-1 y

    @property
    def P(self) -> np.ndarray:
        """The covariance U diag(d) U' (formed on demand)."""
        return ud_to_cov(self.U, self.d)


# ============================================================================ validation


def _as_float(name, a):
    a = np.asarray(a, dtype=float)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite, got non-finite entries")
    return a


@functools.lru_cache(maxsize=32)
def _lower_mask(n):
    """(mask of the lower triangle with the diagonal, its values in a unit upper U)."""
    mask = np.tril(np.ones((n, n), dtype=bool))
    return mask, np.eye(n)[mask]


def _check_ud(U, d, x=None):
    """Validate a U-D pair (and x): shapes, finite unit upper triangular U, finite d >= 0.

    Returns (batch, n, U, d) with U, d as float arrays. Written as few whole-array
    operations as possible: it runs at every step, also on single trials."""
    U = np.asarray(U, dtype=float)
    d = np.asarray(d, dtype=float)
    if U.ndim < 2 or U.shape[-1] != U.shape[-2]:
        raise ValueError(f"U must have shape (..., n, n), got shape {U.shape}")
    n = U.shape[-1]
    batch = U.shape[:-2]
    if d.shape != batch + (n,):
        raise ValueError(f"d must have shape {batch + (n,)} to match U {U.shape}, got {d.shape}")
    if x is not None and x.shape != batch + (n,):
        raise ValueError(f"x must have shape {batch + (n,)} to match U {U.shape}, got {x.shape}")
    if not (d >= 0).all() or not np.isfinite(d).all():  # the first is False for NaN too
        if not np.isfinite(d).all():
            raise ValueError("d must be finite")
        raise ValueError(f"d must be >= 0 (a covariance), got min(d) = {d.min():g}")
    mask, unit = _lower_mask(n)
    if not (U[..., mask] == unit).all():
        raise ValueError("U must be unit upper triangular (ones on the diagonal, zeros below)")
    if not np.isfinite(U).all():
        raise ValueError("U must be finite")
    return batch, n, U, d


# ============================================================================ factor / compose


def ud_factor(P):
    """(U, d) with P = U diag(d) U', U unit upper triangular, d > 0; batched over (..., n, n).

    Computed from the Cholesky factor of the reversed matrix: with J the exchange matrix,
    J P J = L L' (L lower) gives P = (J L J)(J L J)', and J L J is upper triangular; its
    columns scaled to a unit diagonal give U, the squared diagonal gives d.
    Raises ValueError unless P is finite, symmetric (to 1e-10 of sqrt(P_ii P_jj)) and
    positive definite.
    """
    P = _as_float("P", P)
    if P.ndim < 2 or P.shape[-1] != P.shape[-2] or P.shape[-1] < 1:
        raise ValueError(f"P must have shape (..., n, n), got shape {P.shape}")
    diag = np.diagonal(P, axis1=-2, axis2=-1)
    if np.any(diag <= 0):
        raise ValueError(f"P must be positive definite, got a diagonal entry {diag.min():g} <= 0")
    scale = np.sqrt(diag[..., :, None] * diag[..., None, :])
    asym = np.abs(P - np.swapaxes(P, -1, -2)) / scale
    if np.any(asym > 1e-10):
        raise ValueError(f"P must be symmetric, got |P - P'| up to {asym.max():.3g} x sqrt(P_ii P_jj)")
    Pr = P[..., ::-1, ::-1]
    try:
        L = np.linalg.cholesky(Pr)
    except np.linalg.LinAlgError:
        bad = [i for i, p in np.ndenumerate(np.zeros(P.shape[:-2]))
               if not np.all(np.linalg.eigvalsh(Pr[i]) > 0)] if P.ndim > 2 else []
        where = f" (batch index {bad[0]})" if bad else ""
        raise ValueError(f"P must be positive definite{where}: its Cholesky factorisation failed") from None
    l = np.diagonal(L, axis1=-2, axis2=-1)
    if not np.all(l > 0):
        raise ValueError("P must be positive definite: a zero pivot in its factorisation")
    U = (L / l[..., None, :])[..., ::-1, ::-1]
    U = np.triu(U, 1) + np.eye(P.shape[-1])  # exact zeros below and ones on the diagonal
    return U, np.square(l)[..., ::-1].copy()


def ud_to_cov(U, d):
    """P = U diag(d) U' (..., n, n) from a U-D pair; ValueError on bad shapes or d < 0."""
    _, _, U, d = _check_ud(U, d)
    P = (U * d[..., None, :]) @ np.swapaxes(U, -1, -2)
    return 0.5 * (P + np.swapaxes(P, -1, -2))


@functools.lru_cache(maxsize=64)
def _factor_q_cached(shape, data):
    Q = np.frombuffer(data, dtype=float).reshape(shape)
    G, dq = _factor_q(Q)
    G.flags.writeable = False
    dq.flags.writeable = False
    return G, dq


def _factor_q(Q):
    n = Q.shape[-1]
    scale = max(float(np.max(np.abs(Q), initial=0.0)), np.finfo(float).tiny)
    if np.any(np.abs(Q - Q.T) > 1e-12 * scale):
        raise ValueError("Q must be symmetric")
    qd = np.diag(Q)
    if np.any(qd < 0):
        raise ValueError(f"Q must be positive semidefinite, got a diagonal entry {qd.min():g} < 0")
    if not np.any(Q - np.diag(qd)):
        keep = qd > 0
        return np.eye(n)[:, keep], qd[keep].copy()
    lam, V = np.linalg.eigh(Q)
    if lam[0] < -1e-10 * lam[-1]:
        raise ValueError(f"Q must be positive semidefinite, got an eigenvalue {lam[0]:g}")
    keep = lam > 0
    return np.ascontiguousarray(V[:, keep]), lam[keep].copy()


def factor_q(Q):
    """(G, dq) with Q = G diag(dq) G', dq > 0 (columns for zero directions are dropped).

    Q (n, n) symmetric positive semidefinite. A diagonal Q gives unit columns (exact);
    otherwise G holds the eigenvectors of Q with a positive eigenvalue. Cached per value.
    """
    Q = _as_float("Q", Q)
    if Q.ndim != 2 or Q.shape[0] != Q.shape[1]:
        raise ValueError(f"Q must have shape (n, n), got shape {Q.shape}")
    return _factor_q_cached(Q.shape, np.ascontiguousarray(Q).tobytes())


# ============================================================================ numpy kernels (one batch axis)


def mwgs(W, Dw):
    """Modified weighted Gram-Schmidt: (U, d) with U diag(d) U' = W diag(Dw) W'.

    W (N, n, M), Dw (N, M) >= 0 -> U (N, n, n) unit upper triangular, d (N, n) >= 0.
    W is not modified. A zero weighted norm (a direction with no variance) gives d_j = 0
    and a zero column j of U above the diagonal.
    """
    W = np.array(W, dtype=float)  # a copy: orthogonalised in place
    N, n, M = W.shape
    U = np.zeros((N, n, n))
    U[:, np.arange(n), np.arange(n)] = 1.0
    d = np.empty((N, n))
    for j in range(n - 1, -1, -1):
        wj = W[:, j, :]
        c = wj * Dw
        dj = np.einsum("nk,nk->n", wj, c)
        d[:, j] = dj
        if j == 0:
            break
        num = np.einsum("nik,nk->ni", W[:, :j, :], c)
        pos = dj > 0
        u = np.divide(num, dj[:, None], out=np.zeros_like(num), where=pos[:, None])
        U[:, :j, j] = u
        W[:, :j, :] -= u[:, :, None] * wj[:, None, :]
    return U, d


def bierman_update(x, U, d, y, H, r):
    """Sequential scalar (Bierman) updates, numpy, one batch axis.

    x (N, n), U (N, n, n), d (N, n), y (N, m) innovations z - h(x0) at the linearisation
    point x0 = x, H (N, m, n), r (N, m) > 0 independent measurement variances.
    Returns (x+, U+, d+, nis).
    """
    N, n = x.shape
    m = y.shape[-1]
    x0 = x
    x = x.copy()
    U = U.copy()
    d = d.copy()
    nis = np.zeros(N)
    upper = np.triu(np.ones((n, n), dtype=bool), 1)
    for k in range(m):
        h = H[:, k, :]
        yk = y[:, k] - np.einsum("ni,ni->n", h, x - x0)
        f = np.einsum("nij,ni->nj", U, h)  # U' h
        v = d * f
        alpha = r[:, k, None] + np.cumsum(f * v, axis=1)  # alpha_j, j = 0..n-1
        alpha_prev = np.empty_like(alpha)
        alpha_prev[:, 0] = r[:, k]
        alpha_prev[:, 1:] = alpha[:, :-1]
        d = d * (alpha_prev / alpha)
        C = np.cumsum(U * v[:, None, :], axis=2)  # C[:, i, j] = sum_{k<=j} U_ik v_k
        B = np.zeros_like(C)
        B[:, :, 1:] = C[:, :, :-1]  # b^(j)_i = sum_{k<j} U_ik v_k
        U = U - np.where(upper, (f / alpha_prev)[:, None, :] * B, 0.0)
        s = alpha[:, -1]  # innovation variance h P h' + r
        x = x + C[:, :, -1] * (yk / s)[:, None]  # K y,  K = U v / s
        nis = nis + yk * yk / s
    return x, U, d, nis


# ============================================================================ filter API


def _flat(batch, n, *arrays):
    return [a.reshape((-1,) + a.shape[len(batch):]) for a in arrays]


def ud_predict(x, U, d, model: TransitionModel, dt, backend=None):
    """Thornton MWGS prediction: x- = f(x), U- diag(d-) U-' = F U diag(d) U' F' + Q.

    Returns (x-, U-, d-). F may be shared (n, n) or per batch member (..., n, n); Q is
    (n, n) (factored once, cached) or (..., n, n). backend: "numpy", "numba"
    (filters/_nbud.py) or None/"auto" = the filters' default (kernels.default_backend).
    """
    x = _as_float("x", x)
    batch, n, U, d = _check_ud(U, d, x)
    require(model, TransitionModel, "transition model")
    F = np.asarray(model.F(x, dt), dtype=float)
    if F.shape[-2:] != (n, n):
        raise ValueError(f"model.F must have shape (..., {n}, {n}), got {F.shape}")
    Q = np.asarray(model.Q(dt), dtype=float)
    if Q.ndim == 2:
        G, dq = factor_q(Q)
        G = G[None]
        dq = dq[None]
    else:
        Qf = kernels.batched(Q, batch + (n, n)).reshape(-1, n, n)
        parts = [_factor_q(q) for q in Qf]
        r = max(len(p[1]) for p in parts)
        G = np.zeros((len(parts), n, r))
        dq = np.zeros((len(parts), r))  # zero-weight padding columns change nothing
        for i, (g, q) in enumerate(parts):
            G[i, :, : len(q)] = g
            dq[i, : len(q)] = q
    x_pred = model.f(x, dt)
    Uf, df = _flat(batch, n, U, d)
    N = Uf.shape[0]
    if F.ndim > 2:
        F = kernels.batched(F, batch + (n, n)).reshape(-1, n, n)
    if _use_numba(backend):
        from . import _nbud

        Up, dp = _nbud.mwgs_predict(F, Uf, df, G, dq)
    else:
        FU = F @ Uf  # (N, n, n)
        W = np.concatenate([FU, np.broadcast_to(G, (N,) + G.shape[1:])], axis=-1)
        Dw = np.concatenate([df, np.broadcast_to(dq, (N, dq.shape[-1]))], axis=-1)
        Up, dp = mwgs(W, Dw)
    return x_pred, Up.reshape(batch + (n, n)), dp.reshape(batch + (n,))


def _decorrelated(model, y, H, batch, m, n):
    """(y, H, r) with independent errors: R_diag as is, a full R whitened by chol(R)."""
    r_diag = model.R_diag()
    if r_diag is not None:
        r = kernels.batched(np.asarray(r_diag, dtype=float), batch + (m,)).reshape(-1, m)
        if not np.all(r > 0):
            raise ValueError("the measurement variances R_diag must be > 0 for scalar updates")
        return y, H, r
    R = kernels.batched(np.asarray(full_R(model), dtype=float), batch + (m, m)).reshape(-1, m, m)
    try:
        L = np.linalg.cholesky(R)
    except np.linalg.LinAlgError:
        raise ValueError("the measurement covariance R must be positive definite") from None
    y = np.linalg.solve(L, y[..., None])[..., 0]
    H = np.linalg.solve(L, H)
    return y, H, np.ones((y.shape[0], m))


def ud_update(x, U, d, z, model: MeasurementModel, backend=None) -> UDUpdateResult:
    """Bierman scalar sequential update, the measurement model linearised at the prior x.

    Returns UDUpdateResult(x+, U+, d+, y, nis) with y = z - h(x) and nis = y' S^-1 y.
    A full (non-diagonal) R is decorrelated by its Cholesky factor first (module doc).
    """
    x = _as_float("x", x)
    batch, n, U, d = _check_ud(U, d, x)
    z = np.asarray(z, dtype=float)
    hx, H = measure(model, x)
    y = z - hx
    m = y.shape[-1]
    if y.shape != batch + (m,):
        raise ValueError(f"z must have shape {batch + (m,)}, got {z.shape}")
    H = np.asarray(H, dtype=float)
    if H.shape[-2:] != (m, n):
        raise ValueError(f"model H must have shape (..., {m}, {n}), got {H.shape}")
    Hf = kernels.batched(H, batch + (m, n)).reshape(-1, m, n)
    xf, Uf, df, yf = _flat(batch, n, x, U, d, y)
    yw, Hw, r = _decorrelated(model, yf, Hf, batch, m, n)
    if _use_numba(backend):
        from . import _nbud

        xo, Uo, do, nis = _nbud.bierman_update(xf, Uf, df, yw, Hw, r)
    else:
        xo, Uo, do, nis = bierman_update(xf, Uf, df, yw, Hw, r)
    return UDUpdateResult(xo.reshape(batch + (n,)), Uo.reshape(batch + (n, n)), do.reshape(batch + (n,)),
                          y, nis.reshape(batch))


def ud_step(x, U, d, z, transition: TransitionModel, measurement: MeasurementModel, dt,
            backend=None) -> UDUpdateResult:
    """ud_predict then ud_update (the same numbers as calling both)."""
    xp, Up, dp = ud_predict(x, U, d, transition, dt, backend=backend)
    return ud_update(xp, Up, dp, z, measurement, backend=backend)


def _use_numba(backend):
    """True for the compiled kernels: backend "numba", or None/"auto" when the filters'
    default backend (kernels.default_backend, numba when installed) is numba."""
    return kernels.resolve_backend(backend) == "numba"
