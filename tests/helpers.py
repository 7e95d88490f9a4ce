"""Helpers several test files share (one definition each; they were copied before).

Statistical checks of simulated errors, random SPD matrices and a linear transition model.
Each is the function its copies were, draw for draw and operation for operation."""
from __future__ import annotations

import math

import numpy as np
import scipy.stats
from scipy import stats

from sitl.bus import InMemoryTransport, key_matches


def chi2_ok(resid, sigma, alpha=1e-3):
    """Is sum(resid^2)/sigma^2 inside the two-sided 1-alpha interval of chi2(n)? (NaNs dropped)"""
    resid = resid[np.isfinite(resid)]
    stat = np.sum(resid**2) / sigma**2
    lo, hi = stats.chi2.ppf([alpha / 2, 1 - alpha / 2], df=resid.size)
    return lo < stat < hi


def variance_ok(x, var, alpha=1e-3):
    """Is sum(x^2)/var inside the two-sided chi2(n) interval (zero-mean x)?"""
    stat = np.sum(x**2) / var
    lo, hi = stats.chi2.ppf([alpha / 2, 1 - alpha / 2], df=x.size)
    return lo < stat < hi


def fisher_z_ok(x, y, rho, alpha=1e-3):
    """Is the sample correlation of paired x, y consistent with rho (Fisher z, two-sided)?"""
    r = np.corrcoef(x, y)[0, 1]
    z = (np.arctanh(r) - np.arctanh(rho)) * math.sqrt(x.size - 3)
    return abs(z) < stats.norm.ppf(1 - alpha / 2)


def chi2_var_bounds(n, p=0.999):
    """Bounds on s^2 / sigma^2 for a sample of n normal draws: chi2(n-1)/(n-1)."""
    return (scipy.stats.chi2.ppf((1 - p) / 2, n - 1) / (n - 1), scipy.stats.chi2.ppf((1 + p) / 2, n - 1) / (n - 1))


def random_spd(rng, n, batch=(), lo=0.2, hi=5.0):
    """Random SPD matrices with eigenvalues in [lo, hi] (condition number <= hi/lo)."""
    A = rng.standard_normal(batch + (n, n))
    U, _ = np.linalg.qr(A)
    w = rng.uniform(lo, hi, batch + (n,))
    return (U * w[..., None, :]) @ np.swapaxes(U, -1, -2)


def random_gram_spd(rng, n, batch=()):
    """Random SPD matrices A A' + 0.5 I, A standard normal: another draw than random_spd's
    (test_metrics' figures were drawn this way, so it keeps its own)."""
    A = rng.normal(size=batch + (n, n))
    return A @ np.swapaxes(A, -1, -2) + 0.5 * np.eye(n)


def rot_z(theta, v):
    """Frame rotation R3(theta) applied to vectors v (..., 3)."""
    c, s = np.cos(theta), np.sin(theta)
    return np.stack([c * v[..., 0] + s * v[..., 1], -s * v[..., 0] + c * v[..., 1], v[..., 2]], axis=-1)


class LinearTransition:
    """x(k+1) = F x(k) + w, w ~ N(0, Q): a transition model with a shared (n, n) F."""

    linear = True

    def __init__(self, F, Q):
        self._F, self._Q = np.asarray(F, float), np.asarray(Q, float)
        self.ndim = self._F.shape[0]

    def f(self, x, dt):
        return np.asarray(x) @ self._F.T

    def F(self, x, dt):
        return self._F

    def Q(self, dt):
        return self._Q


class RawTapTransport(InMemoryTransport):
    """An in-memory transport whose raw subscribers (``subscribe_raw``, as ZenohTransport has)
    see each payload in the drain before the decoded delivery, as the Zenoh transport's drain
    does: what a ground_station.journal.JournalingTransport journals."""

    def __init__(self, **kw):
        super().__init__(**kw)
        self.raw = []

    def subscribe_raw(self, expr, cb):
        class Sub:
            closed = False

            def close(self):
                self.closed = True
        s = Sub()
        self.raw.append((expr, cb, s))
        return s

    def _deliver(self, key, payload):
        for expr, cb, s in self.raw:
            if not s.closed and key_matches(expr, key):
                cb(key, payload)
        return super()._deliver(key, payload)
