"""Compiled (numba) kernels behind filters/ud.py; imported only when the numba backend is used.

The same algorithms as ud.mwgs / ud.bierman_update, written as plain per-trial loops
(Thornton's MWGS and Bierman's scalar update as published), one trial at a time on one
thread. A prange driver over blocks of trials was measured slower than this serial loop
on the shared 2-core machine (1000 trials, 11 states: 11-15 ms against 2-4 ms), so there
is none. Kept apart from _nbkernels.py so
that editing one does not invalidate the other's on-disk compile cache.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from .nbdispatch import declare, ready, ro, rw

_jit = dict(cache=True, nogil=True, error_model="numpy")


@nb.njit(**_jit)
def _mwgs_one(F, U, d, G, dq, Uo, do, W, Dw):
    """One trial: W = [F U | G], Dw = [d | dq]; MWGS into Uo (unit upper), do."""
    n = U.shape[0]
    r = G.shape[1]
    for i in range(n):
        for k in range(n):
            s = 0.0
            for l in range(k + 1):  # U is upper triangular
                s += F[i, l] * U[l, k]
            W[i, k] = s
        for k in range(r):
            W[i, n + k] = G[i, k]
    for k in range(n):
        Dw[k] = d[k]
    for k in range(r):
        Dw[n + k] = dq[k]
    M = n + r
    for i in range(n):
        for j in range(n):
            Uo[i, j] = 0.0
        Uo[i, i] = 1.0
    for j in range(n - 1, -1, -1):
        dj = 0.0
        for k in range(M):
            dj += W[j, k] * W[j, k] * Dw[k]
        do[j] = dj
        if dj <= 0.0:
            continue
        for i in range(j):
            s = 0.0
            for k in range(M):
                s += W[i, k] * W[j, k] * Dw[k]
            u = s / dj
            Uo[i, j] = u
            for k in range(M):
                W[i, k] -= u * W[j, k]


@declare(ro(3), ro(3), ro(2), ro(3), ro(2), rw(3), rw(2), nb.int64, nb.int64)
@nb.njit(**_jit)
def _mwgs_range(F, U, d, G, dq, Uo, do, lo, hi):
    n = U.shape[1]
    M = n + G.shape[2]
    W = np.empty((n, M))
    Dw = np.empty(M)
    for t in range(lo, hi):
        tf = t if F.shape[0] > 1 else 0
        tg = t if G.shape[0] > 1 else 0
        _mwgs_one(F[tf], U[t], d[t], G[tg], dq[tg], Uo[t], do[t], W, Dw)


@nb.njit(**_jit)
def _bierman_one(x, U, d, y, H, r, xo, Uo, do, b, f, v):
    """One trial: sequential scalar updates linearised at x (xo starts as a copy of x)."""
    n = x.shape[0]
    m = y.shape[0]
    for i in range(n):
        xo[i] = x[i]
        do[i] = d[i]
        for j in range(n):
            Uo[i, j] = U[i, j]
    nis = 0.0
    for k in range(m):
        yk = y[k]
        for i in range(n):
            yk -= H[k, i] * (xo[i] - x[i])
        for j in range(n):  # f = U' h
            s = 0.0
            for i in range(j + 1):
                s += Uo[i, j] * H[k, i]
            f[j] = s
            v[j] = do[j] * s
        alpha = r[k] + f[0] * v[0]
        do[0] = do[0] * r[k] / alpha
        b[0] = v[0]
        for j in range(1, n):
            a_prev = alpha
            alpha = a_prev + f[j] * v[j]
            do[j] = do[j] * a_prev / alpha
            lam = -f[j] / a_prev
            for i in range(j):
                u = Uo[i, j]
                Uo[i, j] = u + lam * b[i]
                b[i] += u * v[j]
            b[j] = v[j]
        g = yk / alpha
        for i in range(n):
            xo[i] += b[i] * g
        nis += yk * g
    return nis


@declare(ro(2), ro(3), ro(2), ro(2), ro(3), ro(2), rw(2), rw(3), rw(2), rw(1), nb.int64, nb.int64)
@nb.njit(**_jit)
def _bierman_range(x, U, d, y, H, r, xo, Uo, do, nis, lo, hi):
    n = x.shape[1]
    b = np.empty(n)
    f = np.empty(n)
    v = np.empty(n)
    for t in range(lo, hi):
        nis[t] = _bierman_one(x[t], U[t], d[t], y[t], H[t], r[t], xo[t], Uo[t], do[t], b, f, v)


def _c(a):
    return np.ascontiguousarray(a, dtype=float)


def mwgs_predict(F, U, d, G, dq):
    """(U-, d-) of F U diag(d) U' F' + G diag(dq) G'.

    F (n, n) or (N, n, n); U (N, n, n); d (N, n); G (1 | N, n, r); dq (1 | N, r)."""
    N, n, _ = U.shape
    F = _c(F)
    if F.ndim == 2:
        F = F[None]
    Uo = np.empty((N, n, n))
    do = np.empty((N, n))
    args = (F, _c(U), _c(d), _c(G), _c(dq), Uo, do)
    ready(_mwgs_range)(*args, 0, N)
    return Uo, do


def bierman_update(x, U, d, y, H, r):
    """Compiled ud.bierman_update: (x+, U+, d+, nis); same arguments and shapes."""
    N, n = x.shape
    xo = np.empty((N, n))
    Uo = np.empty((N, n, n))
    do = np.empty((N, n))
    nis = np.empty(N)
    args = (_c(x), _c(U), _c(d), _c(y), _c(H), _c(r), xo, Uo, do, nis)
    ready(_bierman_range)(*args, 0, N)
    return xo, Uo, do, nis
