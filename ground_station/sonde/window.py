"""The sliding-window manoeuvre test of the sonde tracker: the NIS summed over the last
``manoeuvre_window`` epochs against the chi-square quantile of the summed dof catches a slow drift
from the model (e.g. the radar alone after the burst) that no single epoch's gate sees."""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

__all__ = ["ManoeuvreWindow"]


class ManoeuvreWindow:
    """Per sonde slot, the NIS and the dof of the last ``size`` epochs (a ring) and their running
    sums. ``push`` takes one epoch's NIS of some slots and returns the slots whose window fails the
    test, with the factor S / M by which their window's NIS exceeds its expectation."""

    def __init__(self, size: int):
        self.size = int(size)
        self.nis, self.m = np.zeros((0, self.size)), np.zeros((0, self.size), dtype=np.int64)
        self.k = np.zeros(0, dtype=np.int64)  # epochs pushed since the last restart
        self.S, self.M = np.zeros(0), np.zeros(0, dtype=np.int64)  # the window's summed NIS and dof

    def add_slot(self) -> None:
        """Room for one more sonde, with an empty window."""
        self.nis = np.concatenate([self.nis, np.zeros((1, self.size))])
        self.m = np.concatenate([self.m, np.zeros((1, self.size), dtype=np.int64)])
        self.k = np.append(self.k, 0)
        self.S = np.append(self.S, 0.0)
        self.M = np.append(self.M, 0)

    def reset(self, slots) -> None:
        """Restart the windows of these slots (a manoeuvre found, a track lost)."""
        self.nis[slots], self.m[slots], self.k[slots] = 0.0, 0, 0
        self.S[slots], self.M[slots] = 0.0, 0

    def copy(self) -> ManoeuvreWindow:
        out = ManoeuvreWindow.__new__(ManoeuvreWindow)
        out.size = self.size
        out.nis, out.m, out.k, out.S, out.M = (a.copy() for a in (self.nis, self.m, self.k, self.S, self.M))
        return out

    def push(self, slots: np.ndarray, nis, m, gate: Callable[[np.ndarray], np.ndarray]):
        """One epoch's NIS (NaN: nothing used, counted as 0 with 0 dof) and dof m of the sondes in
        slots. Returns (slots whose summed NIS exceeds ``gate`` of the summed dof over a full
        window, S / M of each), their windows restarted; None when there is none."""
        W = self.size
        ok = np.isfinite(nis)
        nis, m = np.where(ok, nis, 0.0), np.where(ok, m, 0)
        k = self.k[slots] % W
        self.S[slots] += nis - self.nis[slots, k]  # running sums over the window
        self.M[slots] += m - self.m[slots, k]
        self.nis[slots, k], self.m[slots, k] = nis, m
        self.k[slots] += 1
        S, M = self.S[slots], self.M[slots]
        cand = (self.k[slots] >= W) & (S > M)  # the quantile is above M: test only these
        if not cand.any():
            return None
        hit = np.zeros(slots.size, dtype=bool)
        hit[cand] = S[cand] > gate(M[cand])
        if not hit.any():
            return None
        hs = slots[hit]
        scale = S[hit] / M[hit]
        self.reset(hs)
        return hs, scale
