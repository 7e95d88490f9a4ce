"""Accuracy and consistency metrics, and the posterior Cramér-Rao bound.

    RMSE    sqrt(mean e^2)
    NEES    e' P^-1 e            (state error e, filter covariance P)
    NIS     nu' S^-1 nu          (innovation nu, innovation covariance S)
    ANEES   mean of NEES over Monte Carlo runs; for a consistent filter N_runs * ANEES is
            chi2 with n * N_runs degrees of freedom (Bar-Shalom, Li & Kirubarajan, 5.4)
    PCRB    Tichavsky, Muravchik & Nehorai (1998), additive Gaussian noise

Batched over leading axes: e (..., n), P (..., n, n). Pure numpy/scipy.
"""
from __future__ import annotations

import numpy as np

try:  # optional compiled helpers (numba); numpy is the reference path
    from . import _nbkernels as _nbk
except ImportError:  # pragma: no cover
    _nbk = None
import scipy.linalg
import scipy.stats

__all__ = ["rmse", "nees", "nis", "anees", "anis", "chi2_bounds", "pcrb"]


def rmse(err, axis=0, norm_axis=None):
    """Root mean square error, sqrt(mean(e^2, axis)).

    norm_axis: if given, e^2 is first summed over it, so that e.g. err (runs, steps, 3) with
    axis=0, norm_axis=-1 gives the RMS of the spherical error |e| per step.
    """
    e2 = np.square(np.asarray(err, dtype=float))
    if norm_axis is None:
        return np.sqrt(np.mean(e2, axis=axis))
    e2 = e2.sum(axis=norm_axis, keepdims=True)
    out = np.sqrt(np.mean(e2, axis=axis, keepdims=True))
    axes = set(range(e2.ndim)) if axis is None else {int(a) % e2.ndim for a in np.atleast_1d(axis)}
    return np.squeeze(out, axis=tuple(sorted(axes | {norm_axis % e2.ndim})))


def _mahalanobis_sq(v, C, v_name, C_name):
    """v' C^-1 v = |L^-1 v|^2, C = L L' (Cholesky), batched."""
    v = np.asarray(v, dtype=float)
    C = np.asarray(C, dtype=float)
    n = v.shape[-1]
    if C.shape[-2:] != (n, n):
        raise ValueError(f"{C_name} must have shape (..., {n}, {n}), got shape {C.shape}")
    batch = np.broadcast_shapes(v.shape[:-1], C.shape[:-2])
    N = int(np.prod(batch, dtype=np.int64))
    if _nbk is not None and N >= 256 and C.shape[:-2] == batch and v.shape[:-1] == batch:
        # compiled per-trial Cholesky solve: the same numbers, without numpy's batched
        # solve machinery (which costs more than a filter step on 10,000 trials)
        out = _nbk.mahalanobis_sq(np.ascontiguousarray(v).reshape(N, n),
                                  np.ascontiguousarray(C).reshape(N, n, n)).reshape(batch)
        if np.isnan(out).any() and np.isfinite(C).all() and np.isfinite(v).all():
            raise ValueError(f"{C_name} is not positive definite")
        return out
    try:
        L = np.linalg.cholesky(C)
    except np.linalg.LinAlgError as exc:
        raise ValueError(f"{C_name} is not positive definite") from exc
    L = np.broadcast_to(L, batch + (n, n))
    # np.linalg.solve is batched and much faster than a looped triangular solve.
    z = np.linalg.solve(L, np.broadcast_to(v, batch + (n,))[..., None])[..., 0]
    return np.einsum("...i,...i->...", z, z)


def nees(err, P):
    """Normalised estimation error squared e' P^-1 e.  err (..., n), P (..., n, n) -> (...)."""
    return _mahalanobis_sq(err, P, "err", "P")


def nis(nu, S):
    """Normalised innovation squared nu' S^-1 nu.  nu (..., m), S (..., m, m) -> (...)."""
    return _mahalanobis_sq(nu, S, "nu", "S")


def anees(err, P, axis=0):
    """Average NEES over the Monte Carlo axis (not divided by n): ~ n for a consistent filter."""
    return np.mean(nees(err, P), axis=axis)


def anis(nu, S, axis=0):
    """Average NIS over the Monte Carlo axis: ~ m for a consistent filter."""
    return np.mean(nis(nu, S), axis=axis)


def chi2_bounds(dof, n_runs, p=0.99):
    """Two-sided probability-p interval for the average of n_runs independent chi2(dof) values.

    n_runs * average ~ chi2(dof * n_runs), so the bounds are chi2.ppf((1 -+ p)/2, dof n_runs)
    divided by n_runs. Returns (lo, hi).
    """
    dof = int(dof)
    n_runs = int(n_runs)
    if dof < 1:
        raise ValueError(f"dof must be an integer >= 1, got {dof!r}")
    if n_runs < 1:
        raise ValueError(f"n_runs must be an integer >= 1, got {n_runs!r}")
    if not 0.0 < float(p) < 1.0:
        raise ValueError(f"p must be in (0, 1), got {p!r}")
    k = dof * n_runs
    lo = scipy.stats.chi2.ppf(0.5 * (1.0 - p), k) / n_runs
    hi = scipy.stats.chi2.ppf(0.5 * (1.0 + p), k) / n_runs
    return float(lo), float(hi)


# --------------------------------------------------------------------------------------
# posterior Cramér-Rao bound


def _sym(A):
    return 0.5 * (A + np.swapaxes(A, -1, -2))


def _factor(P, name):
    """A square factor L with L L' = P: Cholesky, or an eigen-factor if P is only PSD."""
    try:
        return np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(P)
        if w.min() < -1e-9 * max(w.max(), 0.0) - 1e-300:
            raise ValueError(f"{name} is not positive semidefinite (min eigenvalue {w.min():.3g})")
        return V * np.sqrt(np.clip(w, 0.0, None))


def _add_information(P, I, name="P"):
    """(P^-1 + I)^-1 without inverting P:  L (Id + L' I L)^-1 L',  P = L L'.

    Stable when P is ill-conditioned or singular, since Id + L' I L has eigenvalues >= 1.
    """
    L = _factor(P, name)
    n = P.shape[-1]
    M = _sym(np.eye(n) + L.T @ I @ L)
    Lm = np.linalg.cholesky(M)
    X = scipy.linalg.solve_triangular(Lm, L.T, lower=True)  # Lm^-1 L'
    return _sym(X.T @ X)


def _mean_quadratic(A, C, C_name):
    """E[A' C^-1 A] over samples: A (k, n) or (N, k, n);  C (k, k) or (N, k, k)."""
    A = np.asarray(A, dtype=float)
    C = np.asarray(C, dtype=float)
    k, n = A.shape[-2:]
    if C.shape[-2:] != (k, k):
        raise ValueError(f"{C_name} must have shape (..., {k}, {k}), got shape {C.shape}")
    try:
        Lc = np.linalg.cholesky(C)
    except np.linalg.LinAlgError as exc:
        raise ValueError(f"{C_name} is not positive definite") from exc
    Li = np.linalg.solve(Lc, np.broadcast_to(np.eye(k), Lc.shape))  # Lc^-1, (..., k, k)
    W = (Li @ A).reshape(-1, n)
    N = W.shape[0] // k
    # sum over samples of A' C^-1 A = sum over all rows w of (Lc^-1 A) of w w'
    return (W.T @ W) / N


def _at(arr_or_fn, j):
    if callable(arr_or_fn):
        return np.asarray(arr_or_fn(j), dtype=float)
    return arr_or_fn[j]


def pcrb(
    J0,
    transition,
    dt: float,
    steps: int,
    H,
    R,
    *,
    F_samples=None,
    first_meas_at_0: bool = False,
):
    """Posterior Cramér-Rao bound, Tichavsky, Muravchik & Nehorai (1998), additive Gaussian noise.

    x(k+1) = f(x(k)) + w, w ~ N(0, Q);  z(k) = h(x(k)) + v, v ~ N(0, R). The Fisher
    information J follows the TMN recursion with, for additive Gaussian noise,

        D11 = E[F' Q^-1 F],  D12 = -E[F'] Q^-1,  D22 = Q^-1 + E[H' R^-1 H]
        J(k+1) = D22 - D12' (J(k) + D11)^-1 D12

    the expectations over the TRUE state trajectory (Monte Carlo averages of the Jacobians
    F = df/dx, H = dh/dx at true states). With D11 = Fb'Q^-1 Fb + Sigma, Fb = E[F],
    Sigma = E[(F - Fb)' Q^-1 (F - Fb)], the matrix inversion lemma gives the same recursion as

        J(k+1) = (Q + Fb (J(k) + Sigma)^-1 Fb')^-1 + E[H' R^-1 H]

    which for linear dynamics (Sigma = 0) is the familiar information-form Riccati recursion,
    and for linear-Gaussian measurements the Kalman filter covariance. It is evaluated in
    covariance form, B = J^-1, with (P^-1 + I)^-1 = L (Id + L' I L)^-1 L' (P = L L'), so
    no large, ill-conditioned J or Q^-1 is formed or subtracted; Q^-1 enters only through
    Sigma, i.e. only when F varies across samples (then Q must be positive definite).
    A singular Q (e.g. the seed 001 clock) is fine with a deterministic F.

    J0:         (n, n) prior information P0^-1 (positive definite).
    transition: a transition model; Q(dt) is used, and F(None, dt) when F_samples is None
                (then the model must be linear).
    steps:      number of measurement epochs j = 0 .. steps-1.
    H:          (steps, N_mc, m, n) Jacobians at true states, or (steps, m, n) for a
                deterministic H, or a callable j -> (N_mc, m, n) | (m, n).
    R:          (m, m), (steps, m, m), (steps, N_mc, m, m), or a callable
                j -> (m, m) | (N_mc, m, m).
    F_samples:  optional (steps, N_mc, n, n) or callable j -> (N_mc, n, n): Jacobians of f
                at the true states, for the transition INTO epoch j (F_samples[0] is unused
                when first_meas_at_0).
    first_meas_at_0: if True the first measurement is at the prior's epoch,
                J(0) = J0 + E[H0' R^-1 H0]; otherwise every epoch, the first included,
                follows one prediction over dt.

    Returns B (steps, n, n), B[j] = J(j)^-1, the bound after the j-th measurement update.
    """
    J0 = np.asarray(J0, dtype=float)
    if J0.ndim != 2 or J0.shape[0] != J0.shape[1]:
        raise ValueError(f"J0 must be a square (n, n) matrix, got shape {J0.shape}")
    n = J0.shape[0]
    steps = int(steps)
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps!r}")
    if not callable(H):
        H = np.asarray(H, dtype=float)
        if H.ndim not in (3, 4) or H.shape[0] < steps or H.shape[-1] != n:
            raise ValueError(
                f"H must have shape (steps>={steps}, [N_mc,] m, {n}), got shape {H.shape}"
            )
    if not callable(R):
        R = np.asarray(R, dtype=float)
        if R.ndim not in (2, 3, 4) or (R.ndim > 2 and R.shape[0] < steps):
            raise ValueError(
                "R must have shape (m, m), (steps, m, m) or (steps, N_mc, m, m), "
                f"got shape {R.shape}"
            )
    if F_samples is None:
        if not transition.linear:
            raise ValueError("F_samples must be given for a nonlinear transition model")
        F_const = np.asarray(transition.F(None, dt), dtype=float)
    elif not callable(F_samples):
        F_samples = np.asarray(F_samples, dtype=float)
        shape = F_samples.shape
        if F_samples.ndim not in (3, 4) or shape[0] < steps or shape[-2:] != (n, n):
            raise ValueError(
                f"F_samples must have shape (steps>={steps}, [N_mc,] {n}, {n}), got shape {shape}"
            )
    Q = _sym(np.asarray(transition.Q(dt), dtype=float))
    if Q.shape != (n, n):
        raise ValueError(f"transition.Q(dt) has shape {Q.shape}, J0 is {n}x{n}")

    try:
        LJ = np.linalg.cholesky(_sym(J0))
    except np.linalg.LinAlgError as exc:
        raise ValueError("J0 must be positive definite") from exc
    Linv = scipy.linalg.solve_triangular(LJ, np.eye(n), lower=True)
    B = _sym(Linv.T @ Linv)

    def info(j):
        Hj = _at(H, j)
        Rj = _at(R, j) if callable(R) or R.ndim > 2 else R
        return _sym(_mean_quadratic(Hj, Rj, "R"))

    out = np.empty((steps, n, n))
    start = 0
    if first_meas_at_0:
        B = _add_information(B, info(0), "J0^-1")
        out[0] = B
        start = 1
    for j in range(start, steps):
        if F_samples is None:
            Fb = F_const
        else:
            Fs = _at(F_samples, j)
            Fb = Fs.mean(axis=0) if Fs.ndim == 3 else Fs
            if Fs.ndim == 3 and np.any(Fs != Fb):
                try:
                    np.linalg.cholesky(Q)
                except np.linalg.LinAlgError as exc:
                    raise ValueError(
                        "transition.Q(dt) is singular but F_samples vary across samples; "
                        "the Tichavsky recursion needs Q^-1"
                    ) from exc
                B = _add_information(B, _sym(_mean_quadratic(Fs - Fb, Q, "Q")), "B")
        P_pred = _sym(Fb @ B @ Fb.T + Q)
        B = _add_information(P_pred, info(j), "P_pred")
        out[j] = B
    return out
