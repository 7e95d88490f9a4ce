"""Parameter checks shared by the world models (sitl/, vehicles/): each returns the value as a
float or float array, or raises ValueError with a one-line message naming the parameter.
(filters/ keeps its own copies in filters/models.py: it imports only numpy and scipy.)
Being replaced by filters.params (declared checks, ParamError): sitl/ and ground_station/ no longer
use this module; it goes once vehicles/ has moved too."""
from __future__ import annotations

import math

import numpy as np

__all__ = ["finite_array", "nonnegative", "positive", "vec3"]


def _number(name: str, value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None


def positive(name: str, value) -> float:
    v = _number(name, value)
    if not (math.isfinite(v) and v > 0.0):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return v


def nonnegative(name: str, value) -> float:
    v = _number(name, value)
    if not (math.isfinite(v) and v >= 0.0):
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    return v


def finite_array(name: str, value) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numeric, got {value!r}") from None
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return a


def vec3(name: str, value) -> np.ndarray:
    """A finite (..., 3) float array."""
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numeric (..., 3), got {value!r}") from None
    if a.ndim < 1 or a.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite")
    return a
