"""Adaptive process noise (seed 000, eq 7), a layer around any predict/update filter.

    Q(i+1) = Q_min + a Q(i) + b diag( (W nu)(W nu)' )

W nu = x(i|i) - x(i|i-1) is the state correction of the update at step i (gain times
innovation), Q_min the model's nominal process noise, a = ``decay`` (seed: 0.1) and
b = ``gain`` (seed: 0.7), both chosen experimentally in the seed and parameters here.
Large corrections mean the model under-predicts the state's wander (a mismodelled clock, a
manoeuvre); the next prediction then widens P where the corrections were, so the filter
does not lock itself out of its own measurements (divergence).

Unrolled, Q(i) = s_i Q_min + diag(q_i), with the scalar s_{i+1} = 1 + a s_i (shared by the
whole batch, s -> 1/(1 - a)) and the per-trial diagonal q_{i+1} = a q_i + b (W nu)^2. So the
layer needs no batched Q: the wrapped filter predicts with the shared s Q_min, and q is
added to the predicted diagonal afterwards -- the same P- = F P F' + Q(i), exactly.

Pure functions on an AdaptiveQState; nothing here keeps state between calls.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .params import Check, ParamError, number, optional, param, require, reworded, validate
from .protocols import TransitionModel
from .protocols import require as require_model

__all__ = ["AdaptiveQ", "AdaptiveQState", "ScaledTransition"]


class AdaptiveQState(NamedTuple):
    scale: float  # s_i: Q(i) = s_i Q_min + diag(q_i)
    q_diag: np.ndarray  # (..., n) the adaptive diagonal per batch member


class ScaledTransition:
    """A transition model whose Q is ``scale`` x the wrapped model's (f and F unchanged)."""

    def __init__(self, base: TransitionModel, scale: float):
        self.base = require_model(base, TransitionModel, "transition model")
        self.scale = float(scale)
        self.linear = base.linear

    def f(self, x, dt):
        return self.base.f(x, dt)

    def F(self, x, dt):
        return self.base.F(x, dt)

    def Q(self, dt):
        return self.scale * np.asarray(self.base.Q(dt), dtype=float)


_COEFFICIENT = reworded(number(numpy=True), "must be a finite number")


def _state_indices(v):
    """State indices: anything whose items int() takes, as a tuple of ints."""
    try:
        return tuple(int(i) for i in v)
    except (TypeError, ValueError):
        raise ParamError("", f"expected state indices, got {v!r}") from None


@dataclass(frozen=True)
class AdaptiveQ:
    """Eq 7 with its coefficients; ``states`` limits the adaptation to some state indices
    (None: every state, as in the seed)."""

    decay: float = param(0.1, check=_COEFFICIENT,
                         doc="a, the weight of the previous adaptive Q in the next one (seed: 0.1); < 1, or Q grows "
                             "without bound")
    gain: float = param(0.7, check=_COEFFICIENT,
                        doc="b, the weight of this step's squared state correction (W nu)^2 (seed: 0.7)")
    states: tuple | None = param(None, check=optional(Check(_state_indices)),
                                 doc="the state indices whose process noise adapts (None: every state, as in the "
                                     "seed)")

    def __post_init__(self):
        validate(self)
        for key in ("decay", "gain"):
            require(getattr(self, key) >= 0.0, key, f"{key} must be >= 0, got {getattr(self, key)!r}")
        require(self.decay < 1.0, "decay", f"decay must be < 1 (Q would grow without bound), got {self.decay!r}")

    def init(self, batch_shape, n: int) -> AdaptiveQState:
        """Q(0) = Q_min: scale 1, no adaptive diagonal."""
        return AdaptiveQState(1.0, np.zeros(tuple(batch_shape) + (int(n),)))

    def transition(self, base: TransitionModel, state: AdaptiveQState) -> ScaledTransition:
        """The wrapped transition with Q = s Q_min (add ``state.q_diag`` to P- after predicting)."""
        return ScaledTransition(base, state.scale)

    @staticmethod
    def add_diag(P_pred, state: AdaptiveQState):
        """P- + diag(q) (a new array)."""
        P = np.array(P_pred, dtype=float, copy=True)
        n = P.shape[-1]
        if state.q_diag.shape[-1] != n:
            raise ValueError(f"adaptive Q has {state.q_diag.shape[-1]} states, P has {n}")
        i = np.arange(n)
        P[..., i, i] += state.q_diag
        return P

    def next(self, state: AdaptiveQState, correction) -> AdaptiveQState:
        """Q(i+1) from Q(i) and this step's correction W nu = x(i|i) - x(i|i-1), (..., n)."""
        d = np.asarray(correction, dtype=float)
        if d.shape != state.q_diag.shape:
            raise ValueError(f"correction must have shape {state.q_diag.shape}, got {d.shape}")
        d2 = np.where(np.isfinite(d), d * d, 0.0)
        if self.states is not None:
            keep = np.zeros(d2.shape[-1], dtype=bool)
            keep[list(self.states)] = True
            d2 = np.where(keep, d2, 0.0)
        return AdaptiveQState(1.0 + self.decay * state.scale, self.decay * state.q_diag + self.gain * d2)
