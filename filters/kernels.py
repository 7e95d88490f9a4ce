"""Batched covariance kernels shared by the EKF and the UKF.

Every function here takes arrays with ONE leading batch axis (N trials or vehicles) and
has two interchangeable implementations:

* ``numpy``: plain stacked linear algebra; the readable reference;
* ``numba``: compiled loops (filters/_nbkernels.py) that take 32 trials side by side
  so that every scalar step of the algorithm is a SIMD operation across trials, skip the
  zeros of sparse transition and measurement Jacobians, and spread blocks of trials over
  the cores. ``skyfuse bench filters`` shows what this buys against the numpy path and
  against FilterPy in the same run (10-16x over numpy at 10,000 trials).

Both are tested to agree to rounding. numba is optional: without it the numpy path runs.
The filter modules (ekf.py, ukf.py) flatten any leading batch shape to one axis before
calling in here.
"""
from __future__ import annotations

import numpy as np

try:  # the compiled path is optional; the numpy path is always there
    from . import nbdispatch, _nbkernels

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only where numba is missing
    nbdispatch = _nbkernels = None
    HAVE_NUMBA = False

BACKENDS = ("numpy", "numba")
_default_backend = "numba" if HAVE_NUMBA else "numpy"


def default_backend() -> str:
    return _default_backend


def numba_threads():
    """numba's thread count, or False without numba."""
    if not HAVE_NUMBA:
        return False
    import numba

    return numba.get_num_threads()


def set_default_backend(name: str) -> None:
    """Select the kernels used when a filter call does not name a backend."""
    global _default_backend
    _default_backend = resolve_backend(name)


def resolve_backend(name: str | None) -> str:
    if name is None or name == "auto":
        return _default_backend
    if name not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS} or 'auto', got {name!r}")
    if name == "numba" and not HAVE_NUMBA:
        raise ValueError("backend 'numba' requested but numba is not installed")
    return name


def _sym(P):
    return 0.5 * (P + np.swapaxes(P, -1, -2))


# ============================================================================ numpy path

def _np_cov_predict(F, P, Q):
    """P- = F P F' + Q for a shared F (n, n) or a batched F (N, n, n)."""
    N, n, _ = P.shape
    if F.ndim == 2:
        # Two large GEMMs instead of N small ones: B = P F' as (N n, n) @ (n, n), then
        # F B as (n, n) @ (n, N n) via tensordot.
        B = (P.reshape(N * n, n) @ F.T).reshape(N, n, n)
        FPF = np.tensordot(F, B, axes=(1, 1)).transpose(1, 0, 2)
    else:
        FPF = F @ P @ np.swapaxes(F, -1, -2)
    return _sym(FPF + Q)


def _np_joseph_update(x, P, y, H, R):
    """Vector Kalman update in Joseph form; R is (N, m, m). Returns x+, P+, nis."""
    N, n = x.shape
    PHt = P @ np.swapaxes(H, -1, -2)
    S = H @ PHt + R
    L = np.linalg.cholesky(S)
    # K = P H' S^-1 computed as solve(S, H P)' with the Cholesky factor
    Kt = _chol_solve(L, np.swapaxes(PHt, -1, -2))
    K = np.swapaxes(Kt, -1, -2)
    w = np.linalg.solve(L, y[..., None])[..., 0]
    nis = np.einsum("...i,...i->...", w, w)
    x_new = x + np.einsum("...ij,...j->...i", K, y)
    IKH = np.eye(n) - K @ H
    P_new = IKH @ P @ np.swapaxes(IKH, -1, -2) + K @ R @ Kt
    return x_new, _sym(P_new), nis


def _chol_solve(L, B):
    """Solve (L L') X = B for batched lower-triangular L."""
    Y = np.linalg.solve(L, B)
    return np.linalg.solve(np.swapaxes(L, -1, -2), Y)


def _np_sigma_points(x, P, c):
    """Sigma points (2n+1, N, n): x, x + c L_i, x - c L_i with L L' = P."""
    L = np.linalg.cholesky(P)  # (N, n, n); columns are the square-root directions
    cols = c * np.swapaxes(L, -1, -2)  # (N, n, n): row i = c * column i of L
    X = np.concatenate([x[None], x[None] + np.moveaxis(cols, 1, 0), x[None] - np.moveaxis(cols, 1, 0)], axis=0)
    return X


def _np_ut_moments(X, Wm, Wc, Q):
    """Weighted mean (N, n) and covariance (N, n, n) of sigma points X (K, N, n), + Q."""
    mean = np.tensordot(Wm, X, axes=(0, 0))
    D = X - mean[None]
    P = np.einsum("k,kni,knj->nij", Wc, D, D, optimize=True)
    return mean, _sym(P + Q)


def _np_ukf_update(xbar, Pbar, X, Z, z, R, Wm, Wc):
    """Unscented update from sigma points X (K,N,n) and their images Z (K,N,m)."""
    # relative to the centre point's measurement (see _nbkernels._ukf_update_block)
    Z0 = Z[0]
    zrel = np.tensordot(Wm, Z - Z0[None], axes=(0, 0))
    DX = X - xbar[None]
    DZ = (Z - Z0[None]) - zrel[None]
    S = np.einsum("k,kni,knj->nij", Wc, DZ, DZ, optimize=True) + R
    Pxz = np.einsum("k,kni,knj->nij", Wc, DX, DZ, optimize=True)
    L = np.linalg.cholesky(S)
    Kt = _chol_solve(L, np.swapaxes(Pxz, -1, -2))
    K = np.swapaxes(Kt, -1, -2)
    y = (z - Z0) - zrel
    w = np.linalg.solve(L, y[..., None])[..., 0]
    nis = np.einsum("...i,...i->...", w, w)
    x_new = xbar + np.einsum("...ij,...j->...i", K, y)
    P_new = Pbar - K @ S @ Kt
    return x_new, _sym(P_new), y, nis


# ============================================================================ dispatch

# Below this many trials the compiled kernels run on one thread: waking the thread pool
# costs more than it saves on small batches.
PARALLEL_MIN_TRIALS = 256


_DRIVERS: dict = {}


def _nbk(name, N):
    """The compiled serial or parallel driver of a kernel, with its one signature (read-only
    inputs: filters/nbdispatch.py) compiled or loaded on first use."""
    key = (name, N >= PARALLEL_MIN_TRIALS)
    d = _DRIVERS.get(key)
    if d is None:
        d = _DRIVERS[key] = nbdispatch.ready(getattr(_nbkernels, f"{name}_{'par' if key[1] else 'ser'}"))
    return d


def _c(a):
    return np.ascontiguousarray(a, dtype=float)


def batched(a, shape):
    """a broadcast to shape: a itself when it already has it (np.broadcast_to costs
    several microseconds, which matters on single-trial steps)."""
    a = np.asarray(a, dtype=float)
    return a if a.shape == shape else np.broadcast_to(a, shape)


def cov_predict(F, P, Q, backend=None):
    """P- = F P F' + Q.  F: (n, n) shared or (N, n, n); P: (N, n, n); Q: (n, n)."""
    backend = resolve_backend(backend)
    Q = np.asarray(Q, dtype=float)
    if backend == "numba" and Q.ndim == 2:
        if np.ndim(F) == 2:
            return _nbk("predict", P.shape[0])(_c(F), _c(P), _c(Q))
        return nbdispatch.ready(_nbkernels._batched_predict_par)(_c(F), _c(P), _c(Q))
    return _np_cov_predict(F, P, Q)


_NO_F = np.zeros((0, 0))


def joseph_update(x, P, y, H, R=None, r_diag=None, backend=None):
    """Kalman update in Joseph form, batched over the first axis.

    y: innovation z - h(x-) (N, m); H (N, m, n); either R (m, m) / (N, m, m) or its
    diagonal r_diag (m,) / (N, m). Returns (x+, P+, nis).
    With a full R the compiled path first whitens the measurement with the Cholesky
    factor of R, so that the scalar sequential form applies to any R.
    """
    backend = resolve_backend(backend)
    N, n = x.shape
    m = y.shape[-1]
    if backend == "numpy":
        if R is None:
            R = np.broadcast_to(np.asarray(r_diag, float)[..., None, :] * np.eye(m), (N, m, m))
        return _np_joseph_update(x, P, y, H, np.broadcast_to(R, (N, m, m)))
    y, H, r = _whitened(y, H, R, r_diag, N, m, n)
    return _nbk("joseph", N)(_c(x), _c(P), y, H, r, _NO_F, _NO_F, False, min(N, _nbkernels.LANES))


def _whitened(y, H, R, r_diag, N, m, n):
    """(y, H, r) for the scalar sequential update: a full R is whitened by its Cholesky factor."""
    if r_diag is None:
        # L^-1 z = L^-1 H x + L^-1 v with cov(L^-1 v) = I
        L = np.linalg.cholesky(np.broadcast_to(R, (N, m, m)))
        y = np.linalg.solve(L, y[..., None])[..., 0]
        H = np.linalg.solve(L, H)
        r_diag = np.ones((N, m))
    return _c(y), _c(batched(H, (N, m, n))), _c(batched(r_diag, (N, m)))


def predict_joseph_update(F, Q, x_pred, P, y, H, r_diag, backend=None):
    """Fused EKF step for a linear (shared F) transition and a diagonal R.

    P- = F P F' + Q, then the Joseph update with innovation y = z - h(x-) and H at x-,
    in one pass over P. x_pred (N, n) is f(x) computed by the caller.
    Returns (x+, P+, nis).
    """
    backend = resolve_backend(backend)
    N, n = x_pred.shape
    m = y.shape[-1]
    if backend == "numba" and np.ndim(F) == 2 and np.ndim(Q) == 2:
        y, H, r = _whitened(y, H, None, r_diag, N, m, n)
        return _nbk("joseph", N)(_c(x_pred), _c(P), y, H, r, _c(F), _c(Q), True, min(N, _nbkernels.LANES))
    Pp = cov_predict(F, P, Q, backend=backend)
    return joseph_update(x_pred, Pp, y, H, r_diag=r_diag, backend=backend)


def sigma_points(x, P, c, backend=None):
    """Symmetric sigma points (2n+1, N, n) at spread c = sqrt(n + lambda)."""
    backend = resolve_backend(backend)
    if backend == "numba":
        return _nbk("sigma", x.shape[0])(_c(x), _c(P), float(c), min(x.shape[0], _nbkernels.LANES))
    return _np_sigma_points(x, P, c)


def ut_moments(X, Wm, Wc, Q, backend=None):
    """Weighted mean (N, n) and covariance (N, n, n) of sigma points X (K, N, n), plus Q."""
    backend = resolve_backend(backend)
    Q = np.asarray(Q, float)
    if backend == "numba" and Q.ndim == 2:
        return _nbk("moments", X.shape[1])(_c(X), _c(Wm), _c(Wc), _c(Q))
    return _np_ut_moments(X, Wm, Wc, Q)


def ukf_update(xbar, Pbar, X, Z, z, R, Wm, Wc, backend=None):
    """Unscented update from sigma points X (K, N, n) and images Z (K, N, m).

    Returns (x+, P+, y, nis) with y = z - zbar."""
    backend = resolve_backend(backend)
    N = xbar.shape[0]
    m = Z.shape[-1]
    R = batched(R, (N, m, m))  # a shared R stays a stride-0 view
    if backend == "numba":
        return _nbk("ukf_update", N)(_c(xbar), _c(Pbar), _c(X), _c(Z), _c(z), R, _c(Wm), _c(Wc),
                                       min(N, _nbkernels.LANES))
    return _np_ukf_update(xbar, Pbar, X, Z, z, R, Wm, Wc)
