"""Compiled (numba) kernels behind filters/kernels.py; imported only when numba is present.

Each kernel is a ``_*_block`` function that processes trials [lo, hi) with scratch arrays
allocated once per block, plus two drivers: ``*_par`` (blocks spread over the cores with
prange) and ``*_ser`` (one block, no thread start-up: small batches). Hot loops index the
batched arrays directly instead of slicing them, since slicing inside prange refcounts
the parent array from every thread.
"""
from __future__ import annotations

import numba as nb
import numpy as np

# fastmath without nnan/ninf: a failed Cholesky is reported as NaN and must stay NaN.
_jit = dict(cache=True, nogil=True, error_model="numpy", fastmath={"contract", "arcp", "nsz", "reassoc"})
N_BLOCKS = 64


@nb.njit(**_jit)
def sparse_rows(F):
    """Row-wise nonzero pattern of F: (count per row, column indices, values)."""
    n, m = F.shape
    cnt = np.zeros(n, np.int64)
    cols = np.zeros((n, m), np.int64)
    vals = np.zeros((n, m))
    for i in range(n):
        c = 0
        for j in range(m):
            if F[i, j] != 0.0:
                cols[i, c] = j
                vals[i, c] = F[i, j]
                c += 1
        cnt[i] = c
    return cnt, cols, vals


@nb.njit(**_jit)
def _predict_into(cnt, cols, vals, P, Q, Pout, A):
    """Pout = F P F' + Q for one trial, F given by its sparse rows; A is (n, n) scratch.

    A = F P row by row (contiguous rows of the symmetric P); then F P F' = A F'.
    All arguments are per-trial local arrays: LLVM vectorises loops over arrays that it
    can see do not alias, which the batched arrays indexed by t do not show it.
    """
    n = P.shape[0]
    for i in range(n):
        for j in range(n):
            A[i, j] = 0.0
        for c in range(cnt[i]):
            l = cols[i, c]
            f = vals[i, c]
            for j in range(n):
                A[i, j] += f * P[l, j]
    for i in range(n):
        for j in range(i, n):
            s = Q[i, j]
            for c in range(cnt[j]):
                s += A[i, cols[j, c]] * vals[j, c]
            Pout[i, j] = s
            Pout[j, i] = s


@nb.njit(**_jit)
def _seq_update_into(P, dx, y, H, r, b, k, idx):
    """Scalar sequential Joseph updates of one trial's P (in place), diagonal R.

    For channel j, with the linearisation point fixed at the prior (so that the result
    equals the vector EKF update exactly):
      nu_j = y_j - h_j dx;  b = P h_j';  s = h_j b + r_j;  k = b / s;  dx += k nu_j
      P <- (I - k h_j) P (I - k h_j)' + r_j k k'  =  P - k b' - b k' + s k k'
    (the Joseph product multiplied out; valid for any gain k). Returns the sum of
    nu_j^2 / s, which equals y' S^-1 y by the chain rule.
    """
    n = P.shape[0]
    m = y.shape[0]
    acc = 0.0
    for i in range(n):
        dx[i] = 0.0
    for j in range(m):
        nz = 0
        for i in range(n):
            if H[j, i] != 0.0:
                idx[nz] = i
                nz += 1
        nu = y[j]
        for c in range(nz):
            nu -= H[j, idx[c]] * dx[idx[c]]
        for i in range(n):
            b[i] = 0.0
        for c in range(nz):  # b = P h' = sum_c h_c P[idx_c, :]  (P symmetric: rows)
            hc = H[j, idx[c]]
            row = idx[c]
            for i in range(n):
                b[i] += hc * P[row, i]
        s = r[j]
        for c in range(nz):
            s += H[j, idx[c]] * b[idx[c]]
        for i in range(n):
            k[i] = b[i] / s
            dx[i] += k[i] * nu
        acc += nu * nu / s
        for i in range(n):
            ki = k[i]
            ci = s * ki - b[i]
            for l in range(n):
                P[i, l] += ci * k[l] - ki * b[l]
    return acc


@nb.njit(**_jit)
def _chol_lower(A, t, L):
    """Lower Cholesky factor of A[t] into L; False when A[t] is not positive definite."""
    n = A.shape[1]
    for j in range(n):
        s = A[t, j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            return False
        d = np.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            s = A[t, i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / d
        for i in range(j):
            L[i, j] = 0.0
    return True


# ----------------------------------------------------------------------------- blocks

@nb.njit(**_jit)
def _predict_block(F, P, Q, out, lo, hi):
    cnt, cols, vals = sparse_rows(F)
    n = P.shape[1]
    A = np.empty((n, n))
    Pin = np.empty((n, n))
    Pt = np.empty((n, n))
    for t in range(lo, hi):
        Pin[:, :] = P[t]
        _predict_into(cnt, cols, vals, Pin, Q, Pt, A)
        out[t] = Pt


@nb.njit(**_jit)
def _joseph_block(x, P, y, H, r, xo, Po, nis, lo, hi, F, Q, predict):
    """Sequential Joseph update of trials [lo, hi); with predict, P- = F P F' + Q first."""
    n = x.shape[1]
    m = y.shape[1]
    cnt, cols, vals = sparse_rows(F)
    A = np.empty((n, n))
    Pin = np.empty((n, n))
    Pt = np.empty((n, n))
    Ht = np.empty((m, n))
    yt = np.empty(m)
    rt = np.empty(m)
    dx = np.empty(n)
    b = np.empty(n)
    k = np.empty(n)
    idx = np.empty(n, np.int64)
    for t in range(lo, hi):
        if predict:
            Pin[:, :] = P[t]
            _predict_into(cnt, cols, vals, Pin, Q, Pt, A)
        else:
            Pt[:, :] = P[t]
        Ht[:, :] = H[t]
        yt[:] = y[t]
        rt[:] = r[t]
        nis[t] = _seq_update_into(Pt, dx, yt, Ht, rt, b, k, idx)
        for i in range(n):
            xo[t, i] = x[t, i] + dx[i]
            for j in range(n):  # exact symmetry against rounding drift
                Po[t, i, j] = 0.5 * (Pt[i, j] + Pt[j, i])


@nb.njit(**_jit)
def _sigma_block(x, P, c, X, lo, hi):
    n = x.shape[1]
    L = np.zeros((n, n))
    for t in range(lo, hi):
        ok = _chol_lower(P, t, L)
        for i in range(n):
            X[0, t, i] = x[t, i]
        for col in range(n):
            for i in range(n):
                d = c * L[i, col] if ok else np.nan
                X[1 + col, t, i] = x[t, i] + d
                X[1 + n + col, t, i] = x[t, i] - d


@nb.njit(**_jit)
def _moments_block(X, Wm, Wc, Q, mean, P, lo, hi):
    K, N, n = X.shape
    mu = np.empty(n)
    d = np.empty(n)
    for t in range(lo, hi):
        for i in range(n):
            mu[i] = 0.0
        for k in range(K):
            for i in range(n):
                mu[i] += Wm[k] * X[k, t, i]
        for i in range(n):
            mean[t, i] = mu[i]
            for j in range(n):
                P[t, i, j] = Q[i, j]
        for k in range(K):
            w = Wc[k]
            for i in range(n):
                d[i] = X[k, t, i] - mu[i]
            for i in range(n):
                wd = w * d[i]
                for j in range(i, n):
                    P[t, i, j] += wd * d[j]
        for i in range(n):
            for j in range(i + 1, n):
                P[t, j, i] = P[t, i, j]


@nb.njit(**_jit)
def _ukf_update_block(xbar, Pbar, X, Z, z, R, Wm, Wc, xo, Po, yo, nis, lo, hi):
    """x+ = xbar + Pxz S^-1 (z - zbar),  P+ = Pbar - Pxz S^-1 Pxz'  via G = L^-1 Pxz'."""
    K_, N, n = X.shape
    m = Z.shape[2]
    zb = np.empty(m)
    S = np.empty((1, m, m))
    Pxz = np.empty((n, m))
    dz = np.empty(m)
    dx = np.empty(n)
    L = np.zeros((m, m))
    wv = np.empty(m)
    G = np.empty((m, n))
    for t in range(lo, hi):
        for a in range(m):
            zb[a] = 0.0
        for k in range(K_):
            for a in range(m):
                zb[a] += Wm[k] * Z[k, t, a]
        for a in range(m):
            for b_ in range(m):
                S[0, a, b_] = R[t, a, b_]
            for i in range(n):
                Pxz[i, a] = 0.0
        for k in range(K_):
            w = Wc[k]
            for a in range(m):
                dz[a] = w * (Z[k, t, a] - zb[a])
            for i in range(n):
                dx[i] = X[k, t, i] - xbar[t, i]
            for a in range(m):
                za = Z[k, t, a] - zb[a]
                for b_ in range(m):
                    S[0, a, b_] += dz[b_] * za
            for i in range(n):
                for a in range(m):
                    Pxz[i, a] += dx[i] * dz[a]
        for a in range(m):
            yo[t, a] = z[t, a] - zb[a]
        if not _chol_lower(S, 0, L):
            for i in range(n):
                xo[t, i] = np.nan
                for j in range(n):
                    Po[t, i, j] = np.nan
            nis[t] = np.nan
            continue
        for a in range(m):  # wv = L^-1 y
            s = yo[t, a]
            for b_ in range(a):
                s -= L[a, b_] * wv[b_]
            wv[a] = s / L[a, a]
        for i in range(n):  # G = L^-1 Pxz'
            for a in range(m):
                s = Pxz[i, a]
                for b_ in range(a):
                    s -= L[a, b_] * G[b_, i]
                G[a, i] = s / L[a, a]
        acc = 0.0
        for a in range(m):
            acc += wv[a] * wv[a]
        nis[t] = acc
        for i in range(n):
            s = xbar[t, i]
            for a in range(m):
                s += G[a, i] * wv[a]
            xo[t, i] = s
            for j in range(i, n):
                v = Pbar[t, i, j]
                for a in range(m):
                    v -= G[a, i] * G[a, j]
                Po[t, i, j] = v
                Po[t, j, i] = v


# ----------------------------------------------------------------------------- drivers

@nb.njit(parallel=True, **_jit)
def predict_par(F, P, Q):
    N = P.shape[0]
    out = np.empty_like(P)
    nb_ = min(N, N_BLOCKS)
    for blk in nb.prange(nb_):
        _predict_block(F, P, Q, out, blk * N // nb_, (blk + 1) * N // nb_)
    return out


@nb.njit(**_jit)
def predict_ser(F, P, Q):
    out = np.empty_like(P)
    _predict_block(F, P, Q, out, 0, P.shape[0])
    return out


@nb.njit(parallel=True, **_jit)
def joseph_par(x, P, y, H, r, F, Q, predict):
    N = x.shape[0]
    xo = np.empty_like(x)
    Po = np.empty_like(P)
    nis = np.empty(N)
    nb_ = min(N, N_BLOCKS)
    for blk in nb.prange(nb_):
        _joseph_block(x, P, y, H, r, xo, Po, nis, blk * N // nb_, (blk + 1) * N // nb_, F, Q, predict)
    return xo, Po, nis


@nb.njit(**_jit)
def joseph_ser(x, P, y, H, r, F, Q, predict):
    xo = np.empty_like(x)
    Po = np.empty_like(P)
    nis = np.empty(x.shape[0])
    _joseph_block(x, P, y, H, r, xo, Po, nis, 0, x.shape[0], F, Q, predict)
    return xo, Po, nis


@nb.njit(parallel=True, **_jit)
def sigma_par(x, P, c):
    N, n = x.shape
    X = np.empty((2 * n + 1, N, n))
    nb_ = min(N, N_BLOCKS)
    for blk in nb.prange(nb_):
        _sigma_block(x, P, c, X, blk * N // nb_, (blk + 1) * N // nb_)
    return X


@nb.njit(**_jit)
def sigma_ser(x, P, c):
    N, n = x.shape
    X = np.empty((2 * n + 1, N, n))
    _sigma_block(x, P, c, X, 0, N)
    return X


@nb.njit(parallel=True, **_jit)
def moments_par(X, Wm, Wc, Q):
    K, N, n = X.shape
    mean = np.empty((N, n))
    P = np.empty((N, n, n))
    nb_ = min(N, N_BLOCKS)
    for blk in nb.prange(nb_):
        _moments_block(X, Wm, Wc, Q, mean, P, blk * N // nb_, (blk + 1) * N // nb_)
    return mean, P


@nb.njit(**_jit)
def moments_ser(X, Wm, Wc, Q):
    K, N, n = X.shape
    mean = np.empty((N, n))
    P = np.empty((N, n, n))
    _moments_block(X, Wm, Wc, Q, mean, P, 0, N)
    return mean, P


@nb.njit(parallel=True, **_jit)
def ukf_update_par(xbar, Pbar, X, Z, z, R, Wm, Wc):
    K_, N, n = X.shape
    m = Z.shape[2]
    xo = np.empty((N, n))
    Po = np.empty((N, n, n))
    yo = np.empty((N, m))
    nis = np.empty(N)
    nb_ = min(N, N_BLOCKS)
    for blk in nb.prange(nb_):
        _ukf_update_block(xbar, Pbar, X, Z, z, R, Wm, Wc, xo, Po, yo, nis, blk * N // nb_, (blk + 1) * N // nb_)
    return xo, Po, yo, nis


@nb.njit(**_jit)
def ukf_update_ser(xbar, Pbar, X, Z, z, R, Wm, Wc):
    K_, N, n = X.shape
    m = Z.shape[2]
    xo = np.empty((N, n))
    Po = np.empty((N, n, n))
    yo = np.empty((N, m))
    nis = np.empty(N)
    _ukf_update_block(xbar, Pbar, X, Z, z, R, Wm, Wc, xo, Po, yo, nis, 0, N)
    return xo, Po, yo, nis


@nb.njit(parallel=True, **_jit)
def _batched_predict_par(F, P, Q):
    N, n, _ = P.shape
    out = np.empty_like(P)
    for t in nb.prange(N):
        B = F[t] @ P[t] @ F[t].T
        for i in range(n):
            for j in range(n):
                out[t, i, j] = 0.5 * (B[i, j] + B[j, i]) + Q[i, j]
    return out


# ----------------------------------------------------------------------------- models

@nb.njit(parallel=True, **_jit)
def pr_prr_h(x, sp, sv, ip, iv, ib, idr):
    """Pseudoranges and rates (seed 001 model) for x (L, M, n) against satellites (M, S, 3).

    out[l, t, :S] = |S - X| + x[ib];  out[l, t, S:] = u.(V_S - V) + x[idr].
    """
    L, M, n = x.shape
    S = sp.shape[1]
    out = np.empty((L, M, 2 * S))
    for lt in nb.prange(L * M):
        l = lt // M
        t = lt % M
        X0 = x[l, t, ip[0]]
        X1 = x[l, t, ip[1]]
        X2 = x[l, t, ip[2]]
        V0 = x[l, t, iv[0]]
        V1 = x[l, t, iv[1]]
        V2 = x[l, t, iv[2]]
        for s in range(S):
            d0 = sp[t, s, 0] - X0
            d1 = sp[t, s, 1] - X1
            d2 = sp[t, s, 2] - X2
            rho = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            out[l, t, s] = rho + x[l, t, ib]
            out[l, t, S + s] = (d0 * (sv[t, s, 0] - V0) + d1 * (sv[t, s, 1] - V1) + d2 * (sv[t, s, 2] - V2)) / rho \
                + x[l, t, idr]
    return out


@nb.njit(parallel=True, **_jit)
def pr_prr_h_H(x, sp, sv, ip, iv, ib, idr):
    """pr_prr_h and its Jacobian for x (M, n) against satellites (M, S, 3).

    d pr/dX = -u',  d pr/dD' = 1;  d prr/dX = (u (u.w) - w)' / rho,  d prr/dV = -u',
    d prr/dV' = 1, with u = (S - X)/rho and w = V_S - V.
    """
    M, n = x.shape
    S = sp.shape[1]
    out = np.empty((M, 2 * S))
    H = np.zeros((M, 2 * S, n))
    for t in nb.prange(M):
        for s in range(S):
            d0 = sp[t, s, 0] - x[t, ip[0]]
            d1 = sp[t, s, 1] - x[t, ip[1]]
            d2 = sp[t, s, 2] - x[t, ip[2]]
            rho = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            u0 = d0 / rho
            u1 = d1 / rho
            u2 = d2 / rho
            w0 = sv[t, s, 0] - x[t, iv[0]]
            w1 = sv[t, s, 1] - x[t, iv[1]]
            w2 = sv[t, s, 2] - x[t, iv[2]]
            uw = u0 * w0 + u1 * w1 + u2 * w2
            out[t, s] = rho + x[t, ib]
            out[t, S + s] = uw + x[t, idr]
            H[t, s, ip[0]] = -u0
            H[t, s, ip[1]] = -u1
            H[t, s, ip[2]] = -u2
            H[t, s, ib] = 1.0
            H[t, S + s, ip[0]] = (u0 * uw - w0) / rho
            H[t, S + s, ip[1]] = (u1 * uw - w1) / rho
            H[t, S + s, ip[2]] = (u2 * uw - w2) / rho
            H[t, S + s, iv[0]] = -u0
            H[t, S + s, iv[1]] = -u1
            H[t, S + s, iv[2]] = -u2
            H[t, S + s, idr] = 1.0
    return out, H
