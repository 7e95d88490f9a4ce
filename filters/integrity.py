"""Integrity layer (seed 003): fault detection, isolation and robust, adaptive updates,
wrapped around any filter's update (EKF, UKF, U-D).

Per measurement row j, against the prior (x-, P-) of the epoch:

    nu_j = z_j - h_j(x-),   a_j = sqrt((H P- H' + R)_jj),   beta_j = nu_j / a_j

Healthy: beta_j ~ N(0, 1). Tests (the seed's):
* jumps and outliers: the 3-sigma rule |beta_j| >= ``jump_sigma`` (P = 0.9973 inside);
* gradual faults (drifts, ramps), over a sliding window of ``window`` epochs (k = the epochs
  in the window so far):
  - the seed's test: the mean of beta_j^2 against the chi-square tolerance chi2_{1-a}(k)/k
    (a = ``window_alpha``); it sees a growing spread as well as a bias;
  - a bias test: (sum of beta_j)^2 / k ~ chi2(1) against chi2_{1-a}(1) (a = ``bias_alpha``).
    The innovations of a consistent filter are white, so this is exact; for a slow ramp it
    is far more powerful than the mean square (a bias b in beta moves the sum by k b, the
    sum of squares only by k b^2).
  Samples enter the windows winsorised at the jump threshold J (beta clipped to [-J, J],
  beta^2 to J^2), so one outlier does not read as a drift while a ramp that has already grown
  past J still counts fully toward it; missing epochs enter as healthy values (1 and 0).
Isolation is per *channel*, a group of rows (a satellite's pseudorange and rate, a UAV link's
range and Doppler, one radar axis), given by ``channels`` (m,) ints:
* a row failing the jump test is not used this epoch (its channel's other rows still are);
* a channel with a drift alarm, or with jumps on ``persist`` consecutive epochs (a step that
  stays), is excluded until it passes every test for ``readmit_after`` consecutive epochs;
  its innovations are still computed (against the prior) while it is out.
Excluded rows are made inert (H row = 0, nu = 0: no information and no NIS) -- per batch
member, so each trial or vehicle isolates its own channels.
Robust update (Huber-type M-estimation): admitted rows with |beta_j| > ``huber_c`` get the
weight w = huber_c / |beta_j| applied as R_jj / w (quadratic inside the threshold, linear
outside), one reweighting at the prior.
Adaptive R (innovation-based, Mehra): r_j <- (1 - lam) r_j + lam (nu_j^2 - (H P- H')_jj) on
admitted rows, and the update uses max(R_jj, r_j) (the nominal R is a floor: the estimate
can only say the sensor is worse than specified). Adaptive Q is filters.adaptive (eq 7),
a layer on the prediction.

Everything is a pure function of a MonitorState (NamedTuple of arrays with the batch
axes); `step` returns the update result, the new state and a Report of the epoch's
statistics, alarms, exclusions and readmissions (the caller turns those into bus events).
The monitor linearises the model at x- for beta (H from the model); the wrapped update
(``update``) then runs unchanged on the masked, reweighted model -- for a UKF the betas use
the linearised innovation variance, the update its own unscented one.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.stats

from .ekf import ekf_update, measure

__all__ = ["GuardedModel", "IntegrityConfig", "IntegrityMonitor", "MonitorState", "Report"]


def _pos(name, v, allow_inf=False):
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or math.isnan(v) \
            or (math.isinf(v) and not allow_inf) or v <= 0:
        raise ValueError(f"{name} must be a positive number, got {v!r}")
    return float(v)


def _count(name, v, lo=1):
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
        raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}")
    return int(v)


@dataclass(frozen=True)
class IntegrityConfig:
    jump_sigma: float = 3.0  # |beta| at or above: jump / outlier (inf: no jump test)
    window: int = 10  # epochs of the sliding chi-square drift test
    window_alpha: float = 1e-3  # false-alarm probability of the mean-square test per row-epoch (0 < a < 1)
    bias_alpha: float | None = 1e-3  # the same for the bias test (None: no bias test)
    persist: int = 2  # consecutive jump epochs that exclude the channel (a step that stays)
    readmit_after: int = 10  # consecutive clean epochs before an excluded channel comes back
    huber_c: float | None = None  # Huber threshold on |beta| (None: plain quadratic update)
    adapt_r: bool = False  # innovation-based R estimate (nominal R is the floor)
    r_forget: float = 0.02  # its exponential forgetting factor lam, 0 < lam <= 1
    isolate: bool = True  # False: detect and report only, use every row as the plain filter

    def __post_init__(self):
        _pos("jump_sigma", self.jump_sigma, allow_inf=True)
        _count("window", self.window)
        for name in ("window_alpha", "bias_alpha"):
            a = getattr(self, name)
            if a is None and name == "bias_alpha":
                continue
            if isinstance(a, bool) or not isinstance(a, (int, float, np.floating)) or not 0.0 < a < 1.0:
                raise ValueError(f"{name} must be in (0, 1), got {a!r}")
        _count("persist", self.persist)
        _count("readmit_after", self.readmit_after)
        if self.huber_c is not None:
            _pos("huber_c", self.huber_c)
        lam = self.r_forget
        if isinstance(lam, bool) or not isinstance(lam, (int, float, np.floating)) or not 0.0 < lam <= 1.0:
            raise ValueError(f"r_forget must be in (0, 1], got {lam!r}")
        for name in ("adapt_r", "isolate"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"{name} must be true or false, got {getattr(self, name)!r}")

    def drift_thresholds(self) -> np.ndarray:
        """(window,) tolerance on the mean of beta^2 over k = 1..window epochs."""
        k = np.arange(1, self.window + 1)
        return scipy.stats.chi2.isf(self.window_alpha, k) / k


class MonitorState(NamedTuple):
    ring: np.ndarray  # (..., m, window) the last beta^2 per row (winsorised; missing: 1)
    ring_b: np.ndarray  # (..., m, window) the last beta per row (winsorised; missing: 0)
    pos: int  # next ring slot
    count: int  # epochs seen, for the partial-window tolerance
    jump_run: np.ndarray  # (..., C) consecutive epochs with a jump on the channel
    excluded: np.ndarray  # (..., C) bool
    clean_run: np.ndarray  # (..., C) consecutive clean epochs (for readmission)
    r_est: np.ndarray  # (..., m) innovation-based R estimate (NaN until the first sample)


class Report(NamedTuple):
    beta: np.ndarray  # (..., m) normalised innovations at the prior
    jump: np.ndarray  # (..., m) bool: |beta| >= jump_sigma
    drift_stat: np.ndarray  # (..., m) windowed mean of beta^2
    bias_stat: np.ndarray  # (..., m) (windowed sum of beta)^2 / k
    drift: np.ndarray  # (..., m) bool: either window statistic above its tolerance
    used: np.ndarray  # (..., m) bool: the row entered the update
    weight: np.ndarray  # (..., m) Huber weight of the row (1 inside the threshold, 0 if unused)
    excluded: np.ndarray  # (..., C) bool after this epoch
    newly_excluded: np.ndarray  # (..., C) bool
    readmitted: np.ndarray  # (..., C) bool


class GuardedModel:
    """A measurement model with rows made inert (``inert`` (..., m) bool: h = z, H = 0) and
    R_jj scaled by ``r_scale`` (..., m) (>= 1: down-weighting), optionally floored by
    ``r_floor`` (..., m). Works for the EKF (h_and_H) and for sigma points (h on (K, ..., n):
    the batch axes align on the right)."""

    def __init__(self, base, z, inert, r_scale=None, r_floor=None):
        self.base = base
        self.z = np.asarray(z, dtype=float)
        self.inert = np.asarray(inert, dtype=bool)
        self.r_scale = r_scale
        self.r_floor = r_floor
        self.linear = getattr(base, "linear", False)

    def h(self, x):
        return np.where(self.inert, self.z, self.base.h(x))

    def H(self, x):
        return self.h_and_H(x)[1]

    def h_and_H(self, x):
        hx, H = measure(self.base, x)
        H = np.where(self.inert[..., None], 0.0, H)
        return np.where(self.inert, self.z, hx), H

    def _r(self):
        rd = self.base.R_diag()
        if rd is None:
            raise ValueError("the integrity monitor needs a measurement model with a diagonal R (R_diag)")
        r = np.asarray(rd, dtype=float)
        if self.r_floor is not None:
            r = np.maximum(r, self.r_floor)
        if self.r_scale is not None:
            r = r * self.r_scale
        return r

    def R_diag(self):
        return self._r()

    def R(self):
        r = self._r()
        return r[..., :, None] * np.eye(r.shape[-1])


@dataclass(frozen=True)
class IntegrityMonitor:
    """The integrity layer; ``channels`` (m,) maps each measurement row to its channel."""

    config: IntegrityConfig = IntegrityConfig()

    def init(self, batch_shape, m: int, n_channels: int) -> MonitorState:
        b = tuple(batch_shape)
        W = self.config.window
        return MonitorState(np.ones(b + (int(m), W)), np.zeros(b + (int(m), W)), 0, 0, np.zeros(b + (n_channels,), dtype=np.int64),
                            np.zeros(b + (n_channels,), dtype=bool), np.zeros(b + (n_channels,), dtype=np.int64),
                            np.full(b + (int(m),), np.nan))

    def innovations(self, x, P, z, model):
        """(nu, a^2, HPH'_jj) at the prior, (..., m) each, by linearisation."""
        hx, H = measure(model, x)
        rd = model.R_diag()
        if rd is None:
            raise ValueError("the integrity monitor needs a measurement model with a diagonal R (R_diag)")
        H = np.asarray(H, dtype=float)
        hph = np.einsum("...mi,...ij,...mj->...m", H, P, H)
        return np.asarray(z, dtype=float) - hx, hph + np.asarray(rd, dtype=float), hph

    def step(self, state: MonitorState, x, P, z, model, channels, update=ekf_update, **update_kw):
        """One monitored update: (UpdateResult, MonitorState, Report).

        channels: (m,) int in [0, C) with C = state.excluded.shape[-1]. NaN measurements are
        treated as missing (inert this epoch, not counted as a fault)."""
        cfg = self.config
        x = np.asarray(x, dtype=float)
        P = np.asarray(P, dtype=float)
        z = np.asarray(z, dtype=float)
        ch = np.asarray(channels)
        m = z.shape[-1]
        C = state.excluded.shape[-1]
        if ch.shape != (m,) or not np.issubdtype(ch.dtype, np.integer) or ch.min() < 0 or ch.max() >= C:
            raise ValueError(f"channels must be ({m},) ints in [0, {C}), got {channels!r}")
        if state.ring.shape[-2] != m:
            raise ValueError(f"the monitor state has {state.ring.shape[-2]} rows, the measurement {m}")
        missing = ~np.isfinite(z)
        z_f = np.where(missing, 0.0, z)
        nu, a2, hph = self.innovations(x, P, z_f, model)
        r_nom = np.broadcast_to(np.asarray(model.R_diag(), dtype=float), nu.shape)
        r_floor = None
        if cfg.adapt_r:
            r_floor = np.where(np.isfinite(state.r_est), np.maximum(state.r_est, r_nom), r_nom)
            a2 = hph + r_floor
        beta = np.where(missing, 0.0, nu / np.sqrt(a2))
        jump = (np.abs(beta) >= cfg.jump_sigma) & ~missing

        # sliding window of beta^2 (jump and missing epochs enter as the healthy mean 1)
        ring = state.ring.copy()
        W = cfg.window
        J = cfg.jump_sigma
        ring[..., state.pos] = np.where(missing, 1.0, np.minimum(beta * beta, J * J))
        ring_b = state.ring_b.copy()
        ring_b[..., state.pos] = np.where(missing, 0.0, np.clip(beta, -J, J))
        count = min(state.count + 1, W)
        drift_stat = ring.sum(axis=-1) / W if count == W else \
            (ring.sum(axis=-1) - (W - count)) / count  # unfilled slots hold 1
        drift = drift_stat > cfg.drift_thresholds()[count - 1]
        bias_stat = ring_b.sum(axis=-1) ** 2 / count  # unfilled slots hold 0
        if cfg.bias_alpha is not None:
            drift = drift | (bias_stat > scipy.stats.chi2.isf(cfg.bias_alpha, 1))

        # channel logic
        onehot = ch[:, None] == np.arange(C)[None, :]  # (m, C)

        def any_ch(rows):
            return (rows[..., :, None] & onehot).any(axis=-2)

        jump_ch = any_ch(jump)
        drift_ch = any_ch(drift)
        jump_run = np.where(jump_ch, state.jump_run + 1, 0)
        fault_ch = drift_ch | (jump_run >= cfg.persist)
        clean = ~(jump_ch | drift_ch)
        clean_run = np.where(clean, state.clean_run + 1, 0)
        excluded = state.excluded.copy()
        newly = fault_ch & ~excluded
        readmit = excluded & (clean_run >= cfg.readmit_after)
        if cfg.isolate:
            excluded = (excluded | fault_ch) & ~readmit
        else:
            excluded[...] = False
            readmit = np.zeros_like(readmit)

        excl_rows = excluded[..., ch]
        if cfg.isolate:
            inert = missing | jump | excl_rows
        else:
            inert = missing
        w = np.ones_like(beta)
        if cfg.huber_c is not None:
            ab = np.abs(beta)
            w = np.where(ab > cfg.huber_c, cfg.huber_c / np.maximum(ab, 1e-300), 1.0)
        w = np.where(inert, 0.0, w)
        r_scale = np.where(inert, 1.0, 1.0 / np.where(w > 0, w, 1.0)) if cfg.huber_c is not None else None
        gm = GuardedModel(model, z_f, inert, r_scale=r_scale, r_floor=r_floor)
        res = update(x, P, z_f, gm, **update_kw)

        r_est = state.r_est
        if cfg.adapt_r:
            sample = nu * nu - hph
            lam = cfg.r_forget
            upd = np.where(np.isfinite(r_est), (1.0 - lam) * r_est + lam * sample, sample)
            r_est = np.where(inert, r_est, upd)

        new_state = MonitorState(ring, ring_b, (state.pos + 1) % W, count, jump_run, excluded, clean_run, r_est)
        report = Report(beta, jump, drift_stat, bias_stat, drift, ~inert, w, excluded, newly if cfg.isolate else fault_ch,
                        readmit)
        return res, new_state, report
