"""The sliding-window manoeuvre test of the sonde tracker: the NIS summed over the last
``manoeuvre_window`` epochs against the chi-square quantile of the summed dof catches a slow drift
from the model that no single epoch's gate sees."""
from __future__ import annotations

import math

import numpy as np

__all__ = ["ManoeuvreWindow"]


class ManoeuvreWindow:
    """SondeTracker's part: the window test."""

    def _window_test(self, slots, nis, m, dt: float) -> None:
        """Sliding-window manoeuvre test: the NIS summed over the last ``manoeuvre_window``
        epochs against the chi-square quantile of its summed dof catches a slow drift away
        from the model (e.g. the radar alone after the burst) that no single epoch's gate
        sees; then the manoeuvre covariance is added to the posterior and the window restarts."""
        W = self.params.manoeuvre_window
        if W is None or self.params.gate_prob is None:
            return
        if slots.size == 1:  # one sonde: plain floats, the same arithmetic
            slot, v, mi = int(slots[0]), float(nis[0]), int(m[0])
            if not math.isfinite(v):
                v, mi = 0.0, 0
            k = int(self._win_k[slot]) % W
            self._win_S[slot] += v - self._win_nis[slot, k]
            self._win_M[slot] += mi - self._win_m[slot, k]
            self._win_nis[slot, k], self._win_m[slot, k] = v, mi
            self._win_k[slot] += 1
            S, M = float(self._win_S[slot]), int(self._win_M[slot])
            if self._win_k[slot] < W or not S > M or not S > self._gate(np.array([M]))[0]:
                return
            self._P[slot] += (S / M) * self._transition.boost(dt)
            self._t_init[slot] = self._t[slot]  # a manoeuvre: the monitor waits (integrity_warmup_s)
            self._win_nis[slot], self._win_m[slot], self._win_k[slot] = 0.0, 0, 0
            self._win_S[slot], self._win_M[slot] = 0.0, 0
            self.counters.window_manoeuvre += 1
            return
        ok = np.isfinite(nis)
        nis, m = np.where(ok, nis, 0.0), np.where(ok, m, 0)
        k = self._win_k[slots] % W
        self._win_S[slots] += nis - self._win_nis[slots, k]  # running sums over the window
        self._win_M[slots] += m - self._win_m[slots, k]
        self._win_nis[slots, k], self._win_m[slots, k] = nis, m
        self._win_k[slots] += 1
        S, M = self._win_S[slots], self._win_M[slots]
        cand = (self._win_k[slots] >= W) & (S > M)  # the quantile is above M: test only these
        if not cand.any():
            return
        hit = np.zeros(slots.size, dtype=bool)
        hit[cand] = S[cand] > self._gate(M[cand])
        if hit.any():
            hs = slots[hit]
            # scaled by how far the window's NIS exceeds its expectation (a burst seen by the
            # radar alone is a 40 m/s surprise, not one acceleration step)
            scale = (S[hit] / M[hit])[:, None, None]
            self._P[hs] += scale * self._transition.boost(dt)
            self._t_init[hs] = self._t[hs]
            self._win_nis[hs], self._win_m[hs], self._win_k[hs] = 0.0, 0, 0
            self._win_S[hs], self._win_M[hs] = 0.0, 0
            self.counters.window_manoeuvre += int(hit.sum())
