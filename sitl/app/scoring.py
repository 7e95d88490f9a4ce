"""Errors of the ground station's estimates against the truth, from the bus alone
(subscribes to ``<run>/truth/**`` and ``<run>/gs/estimate/**``; nothing here feeds back).

Thread-safe: the Zenoh transport calls the callbacks from its own threads.

A truth or estimate whose time lies outside the scorer's window about its own clock
(``clock()``: the launcher's paced simulation clock, the batch bus's, the replay's recorded
one) is refused and counted (``rejected``: "future" / "stale"), so it can neither be scored
nor fill the truth table with far-future times (`sitl.bus.timeguard`)."""
from __future__ import annotations

import math
import threading
from collections import defaultdict

import numpy as np

from sitl.bus.timeguard import TimeGuard


class ErrorTracker:
    """Position error of every Estimate against the Truth of the same target at the same time."""

    def __init__(self, keep_s: float = 120.0, settle_s: float = 0.0, t0_gps_s: float | None = None, *,
                 clock=None, max_ahead_s: float = 2.0):
        self.keep_s = keep_s
        self.clock = clock  # the scorer's own clock (simulated s), or None: no time guard
        self.guard = TimeGuard(ahead_s=max_ahead_s, behind_s=keep_s)
        self.settle_s = settle_s
        self.t0 = t0_gps_s
        self._truth: dict = defaultdict(dict)  # (kind, id) -> {t: pos}
        self._pending: dict = defaultdict(dict)  # estimates that came before their truth
        self._lock = threading.Lock()
        self.latest: dict = {}  # (kind, id) -> (t, error_m)
        self.sum_sq: dict = defaultdict(float)
        self.count: dict = defaultdict(int)
        self.estimates = defaultdict(int)
        self.series: dict = defaultdict(list)  # (kind, id) -> [(t, err)]
        self.last_estimate_t: dict = {}  # (kind, id) -> time of the newest estimate received

    def subscribe(self, bus, run_id: str) -> list:
        return [bus.subscribe(f"{run_id}/truth/**", self.on_truth),
                bus.subscribe(f"{run_id}/gs/estimate/**", self.on_estimate)]

    @staticmethod
    def _target(key):
        parts = key.rsplit("/", 2)
        return parts[-2], parts[-1]

    @property
    def rejected(self) -> dict:
        return dict(self.guard.rejected)

    def _admit(self, msg) -> bool:
        return self.clock is None or self.guard.admit(float(msg.t_gps_s), self.clock())

    def on_truth(self, key, msg) -> None:
        tgt = self._target(key)
        t = round(float(msg.t_gps_s), 6)
        with self._lock:
            if not self._admit(msg):
                return
            d = self._truth[tgt]
            d[t] = np.array(msg.pos_ecef_m)
            est = self._pending[tgt].pop(t, None)
            if est is not None:
                self._score(tgt, t, est)
            if len(d) > 4 * self.keep_s + 16:
                lim = t - self.keep_s
                for k in [k for k in d if k < lim]:
                    del d[k]
                p = self._pending[tgt]
                for k in [k for k in p if k < lim]:
                    del p[k]

    def on_estimate(self, key, msg) -> None:
        tgt = self._target(key)
        t = round(float(msg.t_gps_s), 6)
        with self._lock:
            if not self._admit(msg):
                return
            self.estimates[tgt] += 1
            if not self.last_estimate_t.get(tgt, -math.inf) >= t:
                self.last_estimate_t[tgt] = t
            tr = self._truth[tgt].get(t)
            if tr is None:
                self._pending[tgt][t] = np.array(msg.pos_ecef_m)
            else:
                self._score(tgt, t, np.array(msg.pos_ecef_m))

    def _score(self, tgt, t, pos) -> None:
        e = float(np.linalg.norm(pos - self._truth[tgt][t]))
        self.latest[tgt] = (t, e)
        self.series[tgt].append((t, e))
        if self.t0 is None or t - self.t0 >= self.settle_s:
            self.sum_sq[tgt] += e * e
            self.count[tgt] += 1

    def rmse(self) -> dict:
        with self._lock:
            return {f"{k}/{i}": math.sqrt(self.sum_sq[(k, i)] / n) for (k, i), n in self.count.items() if n}

    def summary(self) -> dict:
        with self._lock:
            out = {}
            for tgt in set(self.latest) | set(self.estimates):
                name = f"{tgt[0]}/{tgt[1]}"
                n = self.count.get(tgt, 0)
                out[name] = {"estimates": self.estimates.get(tgt, 0), "scored": n,
                             "rmse_m": math.sqrt(self.sum_sq[tgt] / n) if n else None,
                             "last_error_m": self.latest[tgt][1] if tgt in self.latest else None,
                             "last_t_gps_s": self.latest[tgt][0] if tgt in self.latest else None}
            return out
