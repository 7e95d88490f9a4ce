"""Measurement faults and sensor errors (seed 003), injected into measurement arrays.

The seed's causes of integrity loss that live in the measurements themselves:
* ``step``: a jump that stays (a satellite clock step, a relay re-lock): + magnitude from
  t_start to t_end;
* ``ramp``: a slow drift (a satellite clock running away, a multipath build-up):
  + rate (t - t_start) from t_start to t_end;
* ``outlier``: heavy-tailed multipath outliers: at each epoch in [t_start, t_end), with
  probability ``prob``, + scale x a Student-t(dof) draw;
* ``dropout``: the measurement is missing (NaN) from t_start to t_end;
* ``delay``: from t_start to t_end the value delivered at t is the one measured at t - delay
  (the measurement arrives late and is stamped with the delivery time: an asynchronous
  measurement used as if current);
and the sensor errors of the seed's model, first-order Gauss-Markov processes
    dx/dt = -alpha x + sqrt(2 alpha sigma^2) w,   R(tau) = sigma^2 exp(-alpha |tau|),
stepped exactly: x(t + dt) = e^{-alpha dt} x(t) + sigma sqrt(1 - e^{-2 alpha dt}) N(0, 1).

Everything here is world-side (sitl): seeded by the Generator passed in, stepped in
simulation time, vectorised over a leading batch shape (trials or vehicles) and over the
measurement channels (the last axis). A Fault may hit one trial or all of them
(``trial=None``). The truth of what was injected (per epoch: which channel carries which
fault and how much) is returned for scoring; it never goes to an estimator.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from filters.params import choice, integer, number, optional, param, require, validate

__all__ = ["FAULT_KINDS", "Fault", "FaultInjector", "GaussMarkov", "Injected"]

FAULT_KINDS = ("step", "ramp", "outlier", "dropout", "delay")


_POSITIVE = number(0, lo_open=True)  # a positive scalar argument (dt_s)
_PROB = "a number in [0, 1]"


@dataclass(frozen=True)
class Fault:
    """One fault on one channel (the last axis of the measurement array)."""

    kind: str = param(check=choice(*FAULT_KINDS), doc="what the fault does: " + ", ".join(FAULT_KINDS))
    channel: int = param(check=integer(0), doc="the channel it hits: an index on the measurement array's last axis")
    t_start_s: float = param(check=number(), doc="start of the fault (inclusive), simulation s")
    t_end_s: float = param(math.inf, check=number(finite=False),
                           doc="end of the fault (exclusive), simulation s; > t_start_s (inf: it stays)")
    magnitude: float = param(0.0, check=number(), doc="step: the jump, measurement units")
    rate: float = param(0.0, check=number(), doc="ramp: the drift, measurement units per s")
    prob: float = param(0.0, check=number(0, what=_PROB), doc="outlier: probability of an outlier per epoch")
    scale: float = param(0.0, check=number(0), doc="outlier: scale of the Student-t draw, measurement units")
    dof: float = param(2.0, check=number(0, lo_open=True),
                       doc="outlier: degrees of freedom of the Student-t draw (heavy tails: small)")
    delay_s: float = param(0.0, check=number(0), doc="delay: how late the delivered value is, s (> 0 for a delay)")
    trial: int | None = param(None, check=optional(integer(0)),
                              doc="the batch index (flattened) it hits; None: every trial")

    def __post_init__(self):
        validate(self)
        require(self.t_end_s > self.t_start_s, "t_end_s",
                f"expected a number > t_start_s = {self.t_start_s!r}, got {self.t_end_s!r}")
        require(self.prob <= 1.0, "prob", f"expected {_PROB}, got {self.prob!r}")
        require(self.kind != "delay" or self.delay_s > 0, "delay_s",
                f"expected a number > 0 for a delay fault, got {self.delay_s!r}")

    def active(self, t: float) -> bool:
        return self.t_start_s <= t < self.t_end_s


class Injected:
    """What one epoch's injection did (scoring side): ``bias`` (..., C) the additive error put
    in, ``kind`` (..., C) the index into FAULT_KINDS + 1 of the fault acting (0: none;
    outliers only where one was drawn), ``missing`` (..., C) bool."""

    __slots__ = ("bias", "kind", "missing")

    def __init__(self, bias, kind, missing):
        self.bias, self.kind, self.missing = bias, kind, missing


class FaultInjector:
    """Applies a list of Faults to a measurement array (batch..., C) epoch by epoch.

    ``step(rng, t, z)`` returns (z_faulty, Injected). Delay faults keep a history of the
    clean values of their channel for ``max(delay_s)`` seconds (a small ring per fault)."""

    def __init__(self, faults, batch_shape, n_channels: int):
        self.faults = tuple(faults)
        self.batch_shape = tuple(batch_shape)
        self.C = int(n_channels)
        for f in self.faults:
            if not isinstance(f, Fault):
                raise ValueError(f"faults must be Fault objects, got {type(f).__name__}")
            if f.channel >= self.C:
                raise ValueError(f"fault channel {f.channel} out of range: {self.C} channels")
            nb = int(np.prod(self.batch_shape)) if self.batch_shape else 1
            if f.trial is not None and f.trial >= nb:
                raise ValueError(f"fault trial {f.trial} out of range: {nb} trials")
        self._hist = {i: [] for i, f in enumerate(self.faults) if f.kind == "delay"}

    def step(self, rng: np.random.Generator, t: float, z):
        z = np.array(z, dtype=float, copy=True)
        if z.shape != self.batch_shape + (self.C,):
            raise ValueError(f"z must have shape {self.batch_shape + (self.C,)}, got {z.shape}")
        flat = z.reshape(-1, self.C)
        clean = flat.copy()
        bias = np.zeros_like(flat)
        kind = np.zeros(flat.shape, dtype=np.int8)
        missing = np.zeros(flat.shape, dtype=bool)
        rows = np.arange(flat.shape[0])
        for i, f in enumerate(self.faults):
            sel = rows if f.trial is None else np.array([f.trial])
            c = f.channel
            if f.kind == "delay":
                hist = self._hist[i]
                hist.append((t, clean[:, c].copy()))
                while len(hist) > 1 and hist[1][0] <= t - f.delay_s + 1e-9:
                    hist.pop(0)
                if not f.active(t):
                    continue
                t_old, v_old = hist[0]
                if t_old <= t - f.delay_s + 1e-9:
                    d = v_old[sel] - clean[sel, c]
                    flat[sel, c] += d
                    bias[sel, c] += d
                    kind[sel, c] = FAULT_KINDS.index("delay") + 1
                continue
            if not f.active(t):
                continue
            if f.kind == "step":
                flat[sel, c] += f.magnitude
                bias[sel, c] += f.magnitude
                kind[sel, c] = FAULT_KINDS.index("step") + 1
            elif f.kind == "ramp":
                d = f.rate * (t - f.t_start_s)
                flat[sel, c] += d
                bias[sel, c] += d
                kind[sel, c] = FAULT_KINDS.index("ramp") + 1
            elif f.kind == "outlier":
                hit = rng.random(sel.size) < f.prob
                d = np.where(hit, f.scale * rng.standard_t(f.dof, sel.size), 0.0)
                flat[sel, c] += d
                bias[sel, c] += d
                kind[sel[hit], c] = FAULT_KINDS.index("outlier") + 1
            elif f.kind == "dropout":
                flat[sel, c] = np.nan
                missing[sel, c] = True
                kind[sel, c] = FAULT_KINDS.index("dropout") + 1
        shp = self.batch_shape + (self.C,)
        return flat.reshape(shp), Injected(bias.reshape(shp), kind.reshape(shp), missing.reshape(shp))


class GaussMarkov:
    """First-order Gauss-Markov errors, shape (batch..., C): sigma and tau_s = 1/alpha per
    channel (scalars or (C,)), started in steady state (N(0, sigma^2))."""

    def __init__(self, sigma, tau_s, shape, rng: np.random.Generator):
        self.sigma = np.broadcast_to(np.asarray(sigma, dtype=float), shape[-1:]).copy()
        self.tau_s = np.broadcast_to(np.asarray(tau_s, dtype=float), shape[-1:]).copy()
        if not (np.all(np.isfinite(self.sigma)) and np.all(self.sigma >= 0)):
            raise ValueError(f"sigma must be finite and >= 0, got {sigma!r}")
        if not (np.all(np.isfinite(self.tau_s)) and np.all(self.tau_s > 0)):
            raise ValueError(f"tau_s must be finite and > 0, got {tau_s!r}")
        self.x = self.sigma * rng.standard_normal(tuple(shape))

    def step(self, rng: np.random.Generator, dt_s: float):
        """Advance by dt_s and return the new error (a view of the state)."""
        dt = _POSITIVE("dt_s", dt_s)
        phi = np.exp(-dt / self.tau_s)
        self.x = phi * self.x + self.sigma * np.sqrt(1.0 - phi * phi) * rng.standard_normal(self.x.shape)
        return self.x
