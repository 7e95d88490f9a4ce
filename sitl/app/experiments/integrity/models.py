"""The filter-side models of the seed 003 integrity experiment that filters.models does not have:
the per-satellite Gauss-Markov pseudorange-bias states and the pseudorange-rate measurement that
carries them."""
from __future__ import annotations

import math

import numpy as np

from filters.models import JointMeasurement, PseudorangeDoppler

__all__ = ["GaussMarkovBank", "BiasedPseudorangeDoppler"]


class GaussMarkovBank:
    """Transition of ``n`` independent first-order Gauss-Markov states (the filter's model of
    the per-satellite pseudorange biases): F = e^(-dt/tau) I, Q = sigma^2 (1 - e^(-2dt/tau)) I."""

    linear = True

    def __init__(self, n: int, sigma: float, tau_s: float):
        self.ndim, self.sigma, self.tau_s = int(n), float(sigma), float(tau_s)

    def f(self, x, dt):
        return np.asarray(x, dtype=float) * math.exp(-dt / self.tau_s)

    def F(self, x, dt):
        return math.exp(-dt / self.tau_s) * np.eye(self.ndim)

    def Q(self, dt):
        return self.sigma**2 * -math.expm1(-2.0 * dt / self.tau_s) * np.eye(self.ndim)


class BiasedPseudorangeDoppler(JointMeasurement):
    """PseudorangeDoppler with the pseudorange of satellite i biased by the state x[col0 + i]
    (h += b_i, dh/db_i = 1); R is the white noise only."""

    def __init__(self, base: PseudorangeDoppler, col0: int):
        self.base, self.col0 = base, int(col0)
        self.S = base.n_sats

    def h_and_H(self, x):
        hx, H = self.base.h_and_H(x)
        hx = np.array(hx, dtype=float)
        H = np.array(H, dtype=float)
        cols = self.col0 + np.arange(self.S)
        hx[..., : self.S] += x[..., cols]
        H[..., np.arange(self.S), cols] = 1.0
        return hx, H

    def R_diag(self):
        return self.base.R_diag()

    def R(self):
        d = self.R_diag()
        return d[..., None] * np.eye(d.shape[-1])
