"""Compiled fast path of the covariance check (`sitl.bus.schema._check_cov`).

``cov_code(c)`` walks a square float64 matrix once and returns 0 when it is legal:
symmetric (max |C - C^T| <= 1e-9 max |C|), non-negative diagonal, and a Cholesky
factorisation of its lower triangle succeeds (every pivot > 0); 1 = not symmetric,
2 = a negative diagonal, 3 = the Cholesky did not succeed (singular or indefinite). For
codes 1-3 the schema runs its reference numpy check, which accepts or raises with the same
reason and detail as ever: this module only makes the common, legal case cheap (about
1 us instead of ~25 us of numpy calls per 6x6 covariance).

A pivot this factorisation finds <= 0 where LAPACK's would not (or the reverse) can only
occur for a matrix singular to rounding; such a matrix is then decided by the eigenvalue
test, whose tolerance (-1e-9 max diag) it passes, so the verdict is the same.

``cov_code`` is None without numba (the numpy check alone then runs).
"""
from __future__ import annotations

import math

try:
    import numba as nb
except ImportError:  # pragma: no cover - numba is a dependency
    nb = None

cov_code = None

if nb is not None:
    @nb.njit(cache=True, nogil=True)
    def cov_code(c):  # noqa: F811
        n = c.shape[0]
        scale = 0.0
        asym = 0.0
        for i in range(n):
            for j in range(n):
                a = abs(c[i, j])
                if a > scale:
                    scale = a
                d = abs(c[i, j] - c[j, i])
                if d != d:  # NaN (from an overflow): fails, as the reference's NaN max does
                    return 1
                if d > asym:
                    asym = d
        if not asym <= 1e-9 * scale:
            return 1
        for i in range(n):
            if not c[i, i] >= 0.0:
                return 2
        low = c.copy()
        for j in range(n):
            s = low[j, j]
            for k in range(j):
                s -= low[j, k] * low[j, k]
            if not s > 0.0:  # also NaN / inf trouble: the reference check decides
                return 3
            d = math.sqrt(s)
            if not d < math.inf:
                return 3
            low[j, j] = d
            for i in range(j + 1, n):
                s = low[i, j]
                for k in range(j):
                    s -= low[i, k] * low[j, k]
                low[i, j] = s / d
        for i in range(n):
            for j in range(i + 1):
                if not abs(low[i, j]) < math.inf:
                    return 3
        return 0

within = None

if nb is not None:
    @nb.njit(cache=True, nogil=True)
    def within(a, bound):  # noqa: F811
        """True if every element of a float array is finite and |x| <= bound (a NaN bound, or
        a NaN / inf element, fails)."""
        for x in a.flat:
            if not abs(x) <= bound:
                return False
        return True
