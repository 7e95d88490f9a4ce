"""The interfaces the filters call on their models, as typing.Protocol classes.

A transition model (``TransitionModel``):

    linear   bool: f(x) = F x with an F that does not depend on x (F(None, dt) is then valid,
             and the filters use F directly: ekf_step's fused kernel, ukf_predict's exact
             linear prediction); False for any other model
    f(x, dt) -> (..., n)                  x(k+1) = f(x(k)) + w,  w ~ N(0, Q)
    F(x, dt) -> (n, n) | (..., n, n)      Jacobian df/dx at x
    Q(dt)    -> (n, n)

A measurement model (``MeasurementModel``), what the EKF, the U-D filter, the iterated
update and the integrity monitor call:

    h_and_H(x) -> (h(x) (..., m), H(x) (..., m, n))    z = h(x) + v,  v ~ N(0, R); H = dh/dx
    R_diag()   -> (m,) | (..., m) when R is diagonal, else None
    R()        -> (m, m) | (..., m, m): called only when R_diag() is None

The UKF evaluates h at its sigma points instead (``SigmaPointMeasurementModel``): h(x) and
R_diag() (and R() when R_diag() is None).

filters.models.Measurement completes a model written with h and H (h_and_H from them) and
filters.models.JointMeasurement one written with h_and_H (h and H from it); both give R()
from R_diag(). A filter checks its model once per model class (``require``): a model that
lacks a member fails with a TypeError naming it, instead of being probed for what it has.
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

__all__ = ["TransitionModel", "MeasurementModel", "SigmaPointMeasurementModel", "require", "full_R"]


@runtime_checkable
class TransitionModel(Protocol):
    """x(k+1) = f(x(k)) + w,  w ~ N(0, Q(dt))."""

    linear: bool

    def f(self, x: np.ndarray, dt: float) -> np.ndarray: ...

    def F(self, x: np.ndarray | None, dt: float) -> np.ndarray: ...

    def Q(self, dt: float) -> np.ndarray: ...


@runtime_checkable
class MeasurementModel(Protocol):
    """z = h(x) + v,  v ~ N(0, R), linearised: h and its Jacobian H at x in one call."""

    def h_and_H(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...

    def R_diag(self) -> np.ndarray | None: ...


@runtime_checkable
class SigmaPointMeasurementModel(Protocol):
    """z = h(x) + v,  v ~ N(0, R), evaluated at sigma points (K, ..., n)."""

    def h(self, x: np.ndarray) -> np.ndarray: ...

    def R_diag(self) -> np.ndarray | None: ...


_MEMBERS = {
    TransitionModel: ("linear", "f", "F", "Q"),
    MeasurementModel: ("h_and_H", "R_diag"),
    SigmaPointMeasurementModel: ("h", "R_diag"),
}
_CONFORMING: set = set()  # (model class, protocol) pairs already checked


def require(model, protocol, role: str = "model"):
    """``model`` itself when it has every member of ``protocol``, else a TypeError naming the
    missing members. Checked once per model class (filters step single trials too, where an
    isinstance check against a Protocol would cost more than the step's own overhead)."""
    key = (type(model), protocol)
    if key in _CONFORMING:
        return model
    missing = [name for name in _MEMBERS[protocol] if not hasattr(model, name)]
    if missing:
        raise TypeError(f"{role} {type(model).__name__} is not a {protocol.__name__} "
                        f"(filters.protocols): it has no {', '.join(missing)}")
    if "linear" in _MEMBERS[protocol] and not isinstance(model.linear, (bool, np.bool_)):
        raise TypeError(f"{role} {type(model).__name__}.linear must be a bool, got {model.linear!r}")
    _CONFORMING.add(key)
    return model


def full_R(model, role: str = "measurement model"):
    """model.R() for a model whose R_diag() returned None (R is then not diagonal)."""
    if not hasattr(model, "R"):
        raise TypeError(f"{role} {type(model).__name__} returned R_diag() None and has no R() "
                        f"(filters.protocols.MeasurementModel)")
    return model.R()
