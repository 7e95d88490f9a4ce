"""Compiled (numba) kernels behind filters/kernels.py; imported only when numba is present.

Layout of a kernel: a ``_*_block`` function processes trials [lo, hi) with scratch arrays
allocated once per block, and two drivers call it: ``*_par`` (blocks spread over the
cores with prange) and ``*_ser`` (one block, no thread start-up: small batches).

The EKF/UKF update and sigma-point blocks take LANES trials at a time and transpose them
into "structure of arrays" scratch (P[i, j, lane]), so that the innermost loop of every
step runs over trials and vectorises. The lane count is passed in at run time: with a
compile-time trip count LLVM unrolls those loops into scalar code instead. Batched input
arrays are read in the order that streams through memory (for sigma points: point by
point, a contiguous run of trials each).
"""
from __future__ import annotations

import os

# The parallel drivers run on numba's OpenMP threading layer (libgomp), whose worker threads by
# default keep spinning for milliseconds after every parallel region (GOMP_SPINCOUNT 300000): on
# a 2-core machine that takes a core from the numpy work the main thread does between kernels
# (ekf_predict at 10,000 trials 7.9 -> 3.0 ms without the spin) and from every other process.
# Passive workers sleep at once. libgomp reads its environment when numba loads it, at the
# first parallel kernel call -- after this import, so this takes effect; every parallel kernel
# is defined here or imports this module. A policy set by the user wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numba as nb
import numpy as np

from .nbdispatch import declare, ro

# fastmath without nnan/ninf: a failed Cholesky is reported as NaN and must stay NaN.
_jit = dict(cache=True, nogil=True, error_model="numpy", fastmath={"contract", "arcp", "nsz", "reassoc"})
# The parallel drivers split the trials into one block per thread: numba's OpenMP layer schedules
# a prange statically (equal contiguous shares), so more blocks balance nothing and only repeat
# each block's scratch allocation (measured at 10,000 trials: joseph_par -0.2 ms, 3 %, and the
# integrity kernel, whose block holds ~40 scratch arrays, -0.4 ms, with one block per thread
# instead of 64 blocks). A constant, read when this module is imported (a call to
# get_num_threads() inside a kernel would keep numba from caching it); any count is correct.
N_BLOCKS = nb.config.NUMBA_NUM_THREADS


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


LANES = 32  # trials processed side by side: every inner loop runs over them (SIMD)


# The sequential Joseph update of one lane group, shared by _joseph_block and the integrity
# monitor's fused kernel (filters/_nbintegrity.py), inlined in numba's IR (inline="always"):
# called as a function instead (reference counts on its array arguments per lane group), the
# 10,000-trial steps of `skyfuse bench integrity` were ~4 % slower (minimum over 60 interleaved
# rounds in one process: plain 16.2 vs 15.4 ms, monitored 18.8 vs 18.0 ms); inlined they are
# the copied code's (15.5 and 18.5 ms).

@nb.njit(inline="always", **_jit)
def _joseph_scratch(n, B):
    """The scratch arrays of _joseph_lanes for n states and B lanes: dx, b, k (n, B), nu, sv, acc (B,)."""
    return np.empty((n, B)), np.empty((n, B)), np.empty((n, B)), np.empty(B), np.empty(B), np.empty(B)


@nb.njit(inline="always", **_jit)
def _lane_columns(Hl, nzr, nzc):
    """Per row a of a lane group's H (Hl[a, i, lane]): the columns nonzero in some lane,
    nzr[a, :nzc[a]], in increasing order."""
    m, n, B = Hl.shape
    for a in range(m):
        nz = 0
        for i in range(n):
            any_ = False
            for q in range(B):
                if Hl[a, i, q] != 0.0:
                    any_ = True
            if any_:
                nzr[a, nz] = i
                nz += 1
        nzc[a] = nz


@nb.njit(inline="always", **_jit)
def _joseph_lanes(Pl, Hl, yl, rl, nzr, nzc, dx, b, k, nu, sv, acc):
    """Sequential Joseph update of a lane group, diagonal R, linearised at the prior.

    Pl (n, n, B) the prior P (upper triangle; updated in place), Hl (m, n, B), yl, rl (m, B) the
    innovations z - h(x-) and R's diagonal; nzr, nzc: Hl's columns (_lane_columns; a column that is
    zero in every lane of the row would add exact zeros). Per channel a:
      nu = y_a - h_a dx;  b = P h_a';  s = h_a b + r_a;  k = b / s;  dx += k nu
      P <- (I - k h_a) P (I - k h_a)' + r_a k k'  =  P - k b' - b k' + s k k'
    (the Joseph product multiplied out, valid for any gain; upper triangle). Out: dx (n, B)
    = x+ - x-, acc (B,) = sum nu^2 / s, which equals y' S^-1 y by the chain rule.
    Scratch: b, k (n, B), nu, sv (B,).
    """
    n = Pl.shape[0]
    m = Hl.shape[0]
    B = Pl.shape[2]  # a run-time value: LLVM vectorises the lane loops instead of unrolling them
    for i in range(n):
        for q in range(B):
            dx[i, q] = 0.0
    for q in range(B):
        acc[q] = 0.0
    for a in range(m):
        nz = nzc[a]
        for q in range(B):
            nu[q] = yl[a, q]
        for c in range(nz):
            i = nzr[a, c]
            for q in range(B):
                nu[q] -= Hl[a, i, q] * dx[i, q]
        # b = P h' from the upper triangle: P[i, l] for i <= l, P[l, i] otherwise
        for i in range(n):
            for q in range(B):
                b[i, q] = 0.0
        for c in range(nz):
            l = nzr[a, c]
            for i in range(l + 1):
                for q in range(B):
                    b[i, q] += Pl[i, l, q] * Hl[a, l, q]
            for i in range(l + 1, n):
                for q in range(B):
                    b[i, q] += Pl[l, i, q] * Hl[a, l, q]
        for q in range(B):
            sv[q] = rl[a, q]
        for c in range(nz):
            i = nzr[a, c]
            for q in range(B):
                sv[q] += Hl[a, i, q] * b[i, q]
        for i in range(n):
            for q in range(B):
                k[i, q] = b[i, q] / sv[q]
                dx[i, q] += k[i, q] * nu[q]
        for q in range(B):
            acc[q] += nu[q] * nu[q] / sv[q]
        for i in range(n):
            for l in range(i, n):
                for q in range(B):
                    Pl[i, l, q] += (sv[q] * k[i, q] - b[i, q]) * k[l, q] - k[i, q] * b[l, q]


@nb.njit(inline="always", **_jit)
def _store_lanes(x, dx, Pl, acc, xo, Po, nis, t0, nl):
    """The lane group's posterior, transposed back: trials t0 .. t0 + nl - 1 (Po mirrored)."""
    n = x.shape[1]
    for q in range(nl):
        t = t0 + q
        nis[t] = acc[q]
        for i in range(n):
            xo[t, i] = x[t, i] + dx[i, q]
            for l in range(i, n):
                Po[t, i, l] = Pl[i, l, q]
                Po[t, l, i] = Pl[i, l, q]


@nb.njit(**_jit)
def _joseph_block(x, P, y, H, r, xo, Po, nis, lo, hi, F, Q, predict, lanes):
    """Sequential Joseph update of trials [lo, hi); with predict, P- = F P F' + Q first.

    Trials are taken LANES at a time and transposed into "structure of arrays" scratch
    (P[i, j, lane]) so that every scalar operation of the algorithm becomes a vector
    operation across trials; the update itself is _joseph_lanes. Channels are skipped per
    column where H is zero for every trial of the lane group.
    """
    n = x.shape[1]
    m = y.shape[1]
    # B is a run-time value on purpose: with a compile-time trip count LLVM unrolls the
    # lane loops into scalar code instead of vectorising them.
    B = lanes
    cnt, cols, vals = sparse_rows(F)
    Pin = np.empty((n, n, B))
    A = np.empty((n, n, B))
    Pl = np.empty((n, n, B))
    Hl = np.empty((m, n, B))
    yl = np.empty((m, B))
    rl = np.empty((m, B))
    dx, b, k, nu, sv, acc = _joseph_scratch(n, B)
    nzr = np.empty((m, n), np.int64)
    nzc = np.empty(m, np.int64)
    for t0 in range(lo, hi, B):
        nl = min(B, hi - t0)
        # load, transposed; idle lanes get a harmless problem (P = I, H = 0, r = 1)
        for q in range(B):
            if q < nl:
                t = t0 + q
                for i in range(n):
                    for j in range(n):
                        Pin[i, j, q] = P[t, i, j]
                for a in range(m):
                    yl[a, q] = y[t, a]
                    rl[a, q] = r[t, a]
                    for i in range(n):
                        Hl[a, i, q] = H[t, a, i]
            else:
                for i in range(n):
                    for j in range(n):
                        Pin[i, j, q] = 1.0 if i == j else 0.0
                for a in range(m):
                    yl[a, q] = 0.0
                    rl[a, q] = 1.0
                    for i in range(n):
                        Hl[a, i, q] = 0.0
        if predict:  # A = F P (sparse rows of F), Pl = A F' + Q (upper triangle)
            for i in range(n):
                for j in range(n):
                    for q in range(B):
                        A[i, j, q] = 0.0
                for c in range(cnt[i]):
                    l = cols[i, c]
                    f = vals[i, c]
                    for j in range(n):
                        for q in range(B):
                            A[i, j, q] += f * Pin[l, j, q]
            for i in range(n):
                for j in range(i, n):
                    for q in range(B):
                        Pl[i, j, q] = Q[i, j]
                    for c in range(cnt[j]):
                        l = cols[j, c]
                        f = vals[j, c]
                        for q in range(B):
                            Pl[i, j, q] += A[i, l, q] * f
        else:
            for i in range(n):
                for j in range(i, n):
                    for q in range(B):
                        Pl[i, j, q] = Pin[i, j, q]
        _lane_columns(Hl, nzr, nzc)
        _joseph_lanes(Pl, Hl, yl, rl, nzr, nzc, dx, b, k, nu, sv, acc)
        _store_lanes(x, dx, Pl, acc, xo, Po, nis, t0, nl)


@nb.njit(**_jit)
def _sigma_block(x, P, c, X, lo, hi, lanes):
    """Sigma points of trials [lo, hi): lanes of trials, Cholesky factors side by side,
    written point by point (contiguous runs of trials) into X (2n+1, N, n)."""
    n = x.shape[1]
    B = lanes
    Pl = np.empty((n, n, B))
    L = np.empty((n, n, B))
    ok = np.empty(B, np.bool_)
    d = np.empty(B)
    for t0 in range(lo, hi, B):
        nl = min(B, hi - t0)
        for q in range(B):
            if q < nl:
                for i in range(n):
                    for j in range(i, n):
                        Pl[i, j, q] = P[t0 + q, i, j]
            else:
                for i in range(n):
                    for j in range(i, n):
                        Pl[i, j, q] = 1.0 if i == j else 0.0
        _chol_lanes(Pl, L, ok, d, B)
        for q in range(nl):
            t = t0 + q
            for i in range(n):
                X[0, t, i] = x[t, i]
        for col in range(n):
            for q in range(nl):
                t = t0 + q
                for i in range(n):
                    dd = c * L[i, col, q] if ok[q] else np.nan
                    X[1 + col, t, i] = x[t, i] + dd
            for q in range(nl):
                t = t0 + q
                for i in range(n):
                    dd = c * L[i, col, q] if ok[q] else np.nan
                    X[1 + n + col, t, i] = x[t, i] - dd


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
def _chol_lanes(S, L, ok, d, B):
    """Lower Cholesky factors of S[:, :, q] (upper triangle read) for all lanes at once.

    Lanes whose matrix is not positive definite get ok[q] = False and a unit pivot, so
    that the other lanes proceed; d is (B,) scratch. Lanes are the innermost loops.
    """
    m = S.shape[0]
    for q in range(B):
        ok[q] = True
    for j in range(m):
        for q in range(B):
            d[q] = S[j, j, q]
        for kk in range(j):
            for q in range(B):
                d[q] -= L[j, kk, q] * L[j, kk, q]
        for q in range(B):
            if d[q] > 0.0:
                L[j, j, q] = np.sqrt(d[q])
            else:
                ok[q] = False
                L[j, j, q] = 1.0
            d[q] = 1.0 / L[j, j, q]
        for i in range(j + 1, m):
            for q in range(B):
                L[i, j, q] = S[j, i, q]
            for kk in range(j):
                for q in range(B):
                    L[i, j, q] -= L[i, kk, q] * L[j, kk, q]
            for q in range(B):
                L[i, j, q] *= d[q]
        for i in range(j):
            for q in range(B):
                L[i, j, q] = 0.0


@nb.njit(**_jit)
def _ukf_update_block(xbar, Pbar, X, Z, z, R, Wm, Wc, xo, Po, yo, nis, lo, hi, lanes):
    """x+ = xbar + Pxz S^-1 (z - zbar),  P+ = Pbar - Pxz S^-1 Pxz'  via G = L^-1 Pxz'.

    Lanes of trials side by side as in _joseph_block (B is a run-time value so that
    LLVM vectorises the lane loops rather than unrolling them). Sigma points are read
    point by point, so that each read is one contiguous run of B trials: reading all
    2n+1 points of one trial at a time touches 2n+1 distant cache lines per trial.
    """
    K_, N, n = X.shape
    m = Z.shape[2]
    B = lanes
    Dx = np.empty((K_, n, B))
    Dz = np.empty((K_, m, B))
    zb = np.empty((m, B))
    S = np.empty((m, m, B))
    Pxz = np.empty((n, m, B))
    L = np.empty((m, m, B))
    ok = np.empty(B, np.bool_)
    d = np.empty(B)
    wv = np.empty((m, B))
    G = np.empty((m, n, B))
    GG = np.empty((n, n, B))
    yl = np.empty((m, B))
    for t0 in range(lo, hi, B):
        nl = min(B, hi - t0)
        # load, transposed; idle lanes keep a harmless problem (zeros, R = I).
        # Measurements are taken relative to the centre point's: pseudoranges of ~2e7 m
        # averaged with a weight like -8/3 would otherwise lose ~1e-8 m.
        for k in range(K_):
            for q in range(B):
                if q < nl:
                    t = t0 + q
                    for i in range(n):
                        Dx[k, i, q] = X[k, t, i] - xbar[t, i]
                    for a in range(m):
                        Dz[k, a, q] = Z[k, t, a] - Z[0, t, a]
                else:
                    for i in range(n):
                        Dx[k, i, q] = 0.0
                    for a in range(m):
                        Dz[k, a, q] = 0.0
        for q in range(B):
            if q < nl:
                t = t0 + q
                for a in range(m):
                    yl[a, q] = z[t, a] - Z[0, t, a]
                    for b_ in range(a, m):
                        S[a, b_, q] = R[t, a, b_]
            else:
                for a in range(m):
                    yl[a, q] = 0.0
                    for b_ in range(a, m):
                        S[a, b_, q] = 1.0 if a == b_ else 0.0
        for a in range(m):
            for q in range(B):
                zb[a, q] = 0.0
            for k in range(K_):
                w = Wm[k]
                for q in range(B):
                    zb[a, q] += w * Dz[k, a, q]
            for k in range(K_):
                for q in range(B):
                    Dz[k, a, q] -= zb[a, q]
            for q in range(B):
                yl[a, q] -= zb[a, q]
            for i in range(n):
                for q in range(B):
                    Pxz[i, a, q] = 0.0
        for k in range(K_):
            w = Wc[k]
            for a in range(m):
                for b_ in range(a, m):
                    for q in range(B):
                        S[a, b_, q] += w * Dz[k, a, q] * Dz[k, b_, q]
                for i in range(n):
                    for q in range(B):
                        Pxz[i, a, q] += w * Dx[k, i, q] * Dz[k, a, q]
        _chol_lanes(S, L, ok, d, B)
        for a in range(m):  # wv = L^-1 y,  G = L^-1 Pxz'  (forward substitution)
            for q in range(B):
                wv[a, q] = yl[a, q]
            for b_ in range(a):
                for q in range(B):
                    wv[a, q] -= L[a, b_, q] * wv[b_, q]
            for q in range(B):
                d[q] = 1.0 / L[a, a, q]
                wv[a, q] *= d[q]
            for i in range(n):
                for q in range(B):
                    G[a, i, q] = Pxz[i, a, q]
                for b_ in range(a):
                    for q in range(B):
                        G[a, i, q] -= L[a, b_, q] * G[b_, i, q]
                for q in range(B):
                    G[a, i, q] *= d[q]
        for i in range(n):  # GG = G'G (upper triangle)
            for j in range(i, n):
                for q in range(B):
                    GG[i, j, q] = 0.0
                for a in range(m):
                    for q in range(B):
                        GG[i, j, q] += G[a, i, q] * G[a, j, q]
        for q in range(nl):
            t = t0 + q
            for a in range(m):
                yo[t, a] = yl[a, q]
            if not ok[q]:
                nis[t] = np.nan
                for i in range(n):
                    xo[t, i] = np.nan
                    for j in range(n):
                        Po[t, i, j] = np.nan
                continue
            acc = 0.0
            for a in range(m):
                acc += wv[a, q] * wv[a, q]
            nis[t] = acc
            for i in range(n):
                v = xbar[t, i]
                for a in range(m):
                    v += G[a, i, q] * wv[a, q]
                xo[t, i] = v
                for j in range(i, n):
                    v = Pbar[t, i, j] - GG[i, j, q]
                    Po[t, i, j] = v
                    Po[t, j, i] = v


# ----------------------------------------------------------------------------- drivers

@declare(ro(2), ro(3), ro(2))
@nb.njit(parallel=True, **_jit)
def predict_par(F, P, Q):
    N = P.shape[0]
    out = np.empty_like(P)
    nb_ = min(N, N_BLOCKS)
    for blk in nb.prange(nb_):
        _predict_block(F, P, Q, out, blk * N // nb_, (blk + 1) * N // nb_)
    return out


@declare(ro(2), ro(3), ro(2))
@nb.njit(**_jit)
def predict_ser(F, P, Q):
    out = np.empty_like(P)
    _predict_block(F, P, Q, out, np.int64(0), P.shape[0])
    return out


@declare(ro(2), ro(3), ro(2), ro(3), ro(2), ro(2), ro(2), nb.boolean, nb.int64)
@nb.njit(parallel=True, **_jit)
def joseph_par(x, P, y, H, r, F, Q, predict, lanes):
    N = x.shape[0]
    xo = np.empty_like(x)
    Po = np.empty_like(P)
    nis = np.empty(N)
    nb_ = min(N, N_BLOCKS)
    for blk in nb.prange(nb_):
        _joseph_block(x, P, y, H, r, xo, Po, nis, blk * N // nb_, (blk + 1) * N // nb_, F, Q, predict, lanes)
    return xo, Po, nis


@declare(ro(2), ro(3), ro(2), ro(3), ro(2), ro(2), ro(2), nb.boolean, nb.int64)
@nb.njit(**_jit)
def joseph_ser(x, P, y, H, r, F, Q, predict, lanes):
    xo = np.empty_like(x)
    Po = np.empty_like(P)
    nis = np.empty(x.shape[0])
    _joseph_block(x, P, y, H, r, xo, Po, nis, np.int64(0), x.shape[0], F, Q, predict, lanes)
    return xo, Po, nis


@declare(ro(2), ro(3), nb.float64, nb.int64)
@nb.njit(parallel=True, **_jit)
def sigma_par(x, P, c, lanes):
    N, n = x.shape
    X = np.empty((2 * n + 1, N, n))
    nb_ = min(N, N_BLOCKS)
    for blk in nb.prange(nb_):
        _sigma_block(x, P, c, X, blk * N // nb_, (blk + 1) * N // nb_, lanes)
    return X


@declare(ro(2), ro(3), nb.float64, nb.int64)
@nb.njit(**_jit)
def sigma_ser(x, P, c, lanes):
    N, n = x.shape
    X = np.empty((2 * n + 1, N, n))
    _sigma_block(x, P, c, X, np.int64(0), N, lanes)
    return X


@declare(ro(3), ro(1), ro(1), ro(2))
@nb.njit(parallel=True, **_jit)
def moments_par(X, Wm, Wc, Q):
    K, N, n = X.shape
    mean = np.empty((N, n))
    P = np.empty((N, n, n))
    nb_ = min(N, N_BLOCKS)
    for blk in nb.prange(nb_):
        _moments_block(X, Wm, Wc, Q, mean, P, blk * N // nb_, (blk + 1) * N // nb_)
    return mean, P


@declare(ro(3), ro(1), ro(1), ro(2))
@nb.njit(**_jit)
def moments_ser(X, Wm, Wc, Q):
    K, N, n = X.shape
    mean = np.empty((N, n))
    P = np.empty((N, n, n))
    _moments_block(X, Wm, Wc, Q, mean, P, np.int64(0), N)
    return mean, P


@declare(ro(2), ro(3), ro(3), ro(3), ro(2), ro(3, "A"), ro(1), ro(1), nb.int64)
@nb.njit(parallel=True, **_jit)
def ukf_update_par(xbar, Pbar, X, Z, z, R, Wm, Wc, lanes):
    K_, N, n = X.shape
    m = Z.shape[2]
    xo = np.empty((N, n))
    Po = np.empty((N, n, n))
    yo = np.empty((N, m))
    nis = np.empty(N)
    nb_ = min(N, N_BLOCKS)
    for blk in nb.prange(nb_):
        _ukf_update_block(xbar, Pbar, X, Z, z, R, Wm, Wc, xo, Po, yo, nis, blk * N // nb_, (blk + 1) * N // nb_, lanes)
    return xo, Po, yo, nis


@declare(ro(2), ro(3), ro(3), ro(3), ro(2), ro(3, "A"), ro(1), ro(1), nb.int64)
@nb.njit(**_jit)
def ukf_update_ser(xbar, Pbar, X, Z, z, R, Wm, Wc, lanes):
    K_, N, n = X.shape
    m = Z.shape[2]
    xo = np.empty((N, n))
    Po = np.empty((N, n, n))
    yo = np.empty((N, m))
    nis = np.empty(N)
    _ukf_update_block(xbar, Pbar, X, Z, z, R, Wm, Wc, xo, Po, yo, nis, np.int64(0), N, lanes)
    return xo, Po, yo, nis


@declare(ro(3), ro(3), ro(2))
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

@nb.njit(**_jit)
def _pr_prr_h_into(x, sp, sv, ip, iv, ib, idr, out, lt):
    """Pseudoranges and rates of the flat point lt = l * M + t (see pr_prr_h_par)."""
    L, M, n = x.shape
    S = sp.shape[1]
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


@nb.njit(parallel=True, **_jit)
def pr_prr_h_par(x, sp, sv, ip, iv, ib, idr):
    """Pseudoranges and rates (seed 001 model) for x (L, M, n) against satellites (M, S, 3).

    out[l, t, :S] = |S - X| + x[ib];  out[l, t, S:] = u.(V_S - V) + x[idr].
    """
    L, M, n = x.shape
    out = np.empty((L, M, 2 * sp.shape[1]))
    for lt in nb.prange(L * M):  # the prange index is unsigned: pass int64, as the serial driver does
        _pr_prr_h_into(x, sp, sv, ip, iv, ib, idr, out, np.int64(lt))
    return out


@nb.njit(**_jit)
def pr_prr_h_ser(x, sp, sv, ip, iv, ib, idr):
    L, M, n = x.shape
    out = np.empty((L, M, 2 * sp.shape[1]))
    for lt in range(L * M):
        _pr_prr_h_into(x, sp, sv, ip, iv, ib, idr, out, lt)
    return out


@nb.njit(**_jit)
def _pr_prr_h_H_into(x, sp, sv, ip, iv, ib, idr, out, H, t):
    """pr_prr_h and its Jacobian for x (M, n) against satellites (M, S, 3).

    d pr/dX = -u',  d pr/dD' = 1;  d prr/dX = (u (u.w) - w)' / rho,  d prr/dV = -u',
    d prr/dV' = 1, with u = (S - X)/rho and w = V_S - V.
    """
    S = sp.shape[1]
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


@nb.njit(parallel=True, **_jit)
def pr_prr_h_H_par(x, sp, sv, ip, iv, ib, idr):
    M, n = x.shape
    S = sp.shape[1]
    out = np.empty((M, 2 * S))
    H = np.zeros((M, 2 * S, n))
    for t in nb.prange(M):  # the prange index is unsigned: pass int64, as the serial driver does
        _pr_prr_h_H_into(x, sp, sv, ip, iv, ib, idr, out, H, np.int64(t))
    return out, H


@nb.njit(**_jit)
def pr_prr_h_H_ser(x, sp, sv, ip, iv, ib, idr):
    M, n = x.shape
    S = sp.shape[1]
    out = np.empty((M, 2 * S))
    H = np.zeros((M, 2 * S, n))
    for t in range(M):
        _pr_prr_h_H_into(x, sp, sv, ip, iv, ib, idr, out, H, t)
    return out, H


@nb.njit(parallel=True, **_jit)
def mahalanobis_sq(v, C):
    """v' C^-1 v per row for v (N, k) and SPD C (N, k, k); NaN where C is not PD."""
    N, k = v.shape
    out = np.empty(N)
    nb_ = min(N, N_BLOCKS)
    for blk in nb.prange(nb_):
        L = np.zeros((k, k))
        w = np.empty(k)
        for t in range(blk * N // nb_, (blk + 1) * N // nb_):
            if not _chol_lower(C, t, L):
                out[t] = np.nan
                continue
            acc = 0.0
            for a in range(k):
                s = v[t, a]
                for b_ in range(a):
                    s -= L[a, b_] * w[b_]
                w[a] = s / L[a, a]
                acc += w[a] * w[a]
            out[t] = acc
    return out
