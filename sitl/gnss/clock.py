"""Receiver clock: two-state (bias, drift) model driven by white frequency-rate noise.

Seed 000, eqs. 13-15, with x = [Δ, Δ̇] (bias in metres, drift in m/s):

    Δ(i+1)  = Δ(i) + T Δ̇(i) + ξ_Δ          x(i+1) = F x(i) + ξ,   F = [[1, T], [0, 1]]
    Δ̇(i+1) = Δ̇(i) + ξ_Δ̇
    E[ξ ξ'] = Q = c² N_ε [[T³/3, T²/2], [T²/2, T]]

N_ε is the PSD of the noise forming the fractional frequency rate; the seed reads
N_ε = 0.8e-20 1/s and calls it two-sided (a Rakon RTXS5032A TCXO). The seed's Q is used
literally: c² N_ε multiplies the integrals of the continuous white-noise model, so
"two-sided" adds no factor 1/2 here. Q is the exact discretisation of the continuous
model, so ``simulate`` is exact for any step T (no Euler error).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from filters.params import number, param, validate
from sitl.constants import C_M_S

TCXO_PSD_1_S = 0.8e-20  # seed 000: N_ε of a Rakon RTXS5032A TCXO


def _check_step(T: float) -> float:
    T = float(T)
    if not (np.isfinite(T) and T > 0.0):
        raise ValueError(f"T must be a positive finite step in seconds, got {T!r}")
    return T


def _as_shape(batch_shape) -> tuple:
    if isinstance(batch_shape, (int, np.integer)):
        return (int(batch_shape),)
    return tuple(int(b) for b in batch_shape)


@dataclass(frozen=True)
class ClockModel:
    """Receiver clock bias/drift model of seed 000 (eqs. 13-15)."""

    psd_1_s: float = param(TCXO_PSD_1_S, check=number(0, what="a finite PSD >= 0 in 1/s"),
                           doc="N_epsilon, the PSD of the noise forming the fractional frequency rate, 1/s "
                               "(seed 000: 0.8e-20, a Rakon RTXS5032A TCXO)")

    def __post_init__(self):
        validate(self)

    @property
    def q_m2_s3(self) -> float:
        """c² N_ε: the continuous process-noise intensity of the drift in metres, m²/s³."""
        return C_M_S**2 * float(self.psd_1_s)

    def F(self, T: float) -> np.ndarray:
        """State transition over T seconds: F = [[1, T], [0, 1]] (seed 000, eq. 13)."""
        T = _check_step(T)
        return np.array([[1.0, T], [0.0, 1.0]])

    def Q(self, T: float) -> np.ndarray:
        """Discrete process noise Q = c² N_ε [[T³/3, T²/2], [T²/2, T]] (seed 000, eq. 15)."""
        T = _check_step(T)
        return self.q_m2_s3 * np.array([[T**3 / 3.0, T**2 / 2.0], [T**2 / 2.0, T]])

    def Q_cholesky(self, T: float) -> np.ndarray:
        """Lower-triangular L with L L' = Q(T), in closed form.

        L = sqrt(c² N_ε) [[sqrt(T³/3), 0], [sqrt(3T)/2, sqrt(T)/2]]
        (also valid, all zeros, when N_ε = 0, where a numerical Cholesky would fail).
        """
        T = _check_step(T)
        s = np.sqrt(self.q_m2_s3)
        return s * np.array([[np.sqrt(T**3 / 3.0), 0.0], [np.sqrt(3.0 * T) / 2.0, np.sqrt(T) / 2.0]])

    def step(self, rng: np.random.Generator, bias_m, drift_m_s, T: float):
        """One exact step x(i+1) = F x(i) + L w, w ~ N(0, I). Returns (bias_m, drift_m_s)."""
        L = self.Q_cholesky(T)
        bias_m = np.asarray(bias_m, dtype=float)
        drift_m_s = np.asarray(drift_m_s, dtype=float)
        shape = np.broadcast_shapes(bias_m.shape, drift_m_s.shape)
        w = rng.standard_normal((2, *shape))
        new_bias = bias_m + T * drift_m_s + L[0, 0] * w[0]
        new_drift = drift_m_s + L[1, 0] * w[0] + L[1, 1] * w[1]
        return new_bias, new_drift

    def simulate(
        self,
        rng: np.random.Generator,
        n_steps: int,
        T: float,
        bias0_m=0.0,
        drift0_m_s=0.0,
        batch_shape: tuple = (),
    ):
        """Exact discrete-time trajectories of (bias, drift).

        bias0_m, drift0_m_s: initial state, broadcastable to batch_shape.
        Returns (bias_m, drift_m_s), each of shape (*batch_shape, n_steps + 1), index 0
        being the initial state. The noise ξ(i) = L w(i), L L' = Q(T), w(i) ~ N(0, I).
        """
        n_steps = int(n_steps)
        if n_steps < 0:
            raise ValueError(f"n_steps must be >= 0, got {n_steps!r}")
        T = _check_step(T)
        batch_shape = _as_shape(batch_shape)
        L = self.Q_cholesky(T)
        b0 = np.broadcast_to(np.asarray(bias0_m, dtype=float), batch_shape)[..., None]
        d0 = np.broadcast_to(np.asarray(drift0_m_s, dtype=float), batch_shape)[..., None]

        w = rng.standard_normal((2, *batch_shape, n_steps))
        xi_b = L[0, 0] * w[0]
        xi_d = L[1, 0] * w[0] + L[1, 1] * w[1]

        zeros = np.zeros((*batch_shape, 1))
        # drift(k) = d0 + sum_{i<k} ξ_d(i)
        drift = d0 + np.concatenate([zeros, np.cumsum(xi_d, axis=-1)], axis=-1)
        # bias(k) = b0 + sum_{i<k} (T drift(i) + ξ_b(i))
        bias_inc = T * drift[..., :-1] + xi_b
        bias = b0 + np.concatenate([zeros, np.cumsum(bias_inc, axis=-1)], axis=-1)
        return bias, drift
