"""The value checks of the guidance laws' fields (filters.params checks), and their broadcast to
the batch shape: an array field holds finite numbers (a scalar, or one value per vehicle),
stored as a read-only float array of the law's batch shape; a bad value is one line naming
the field."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from filters.params import Check, ParamError, array, number


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.flags.writeable = False
    return a


def _shown(v) -> str:
    """A value as one short line of text (an array by its first numbers and its shape)."""
    if isinstance(v, np.ndarray):
        if v.size <= 8:
            return repr(v.tolist())
        return f"[{', '.join(f'{x:g}' for x in v.ravel()[:8])}, ...] (shape {v.shape})"
    return repr(v)


def _values(lo: float | None = None, *, lo_open: bool = False, what: str = "finite values") -> Check:
    """Finite numbers as a read-only float array (a scalar, or an array the law broadcasts to
    its batch shape), each >= lo (> lo if lo_open) when lo is given."""
    base = array()

    def test(v):
        try:
            a = base("", v)
        except ParamError:
            a = None
        if a is None or (lo is not None and np.any(a <= lo if lo_open else a < lo)):
            raise ParamError("", f"expected {what}, got {_shown(v)}")
        return a

    return Check(test)


_FINITE = _values()
_NONNEG = _values(0.0, what="finite values >= 0")
_POSITIVE = _values(0.0, lo_open=True, what="finite values > 0")
_GAIN = number(0.0, lo_open=True)  # a positive finite scalar
_STEP = number(0.0, lo_open=True)  # an integration step, s


def _real(key: str, value) -> float:
    """A finite scalar argument (a time, s) as a float."""
    return float(_FINITE(key, value))


def _latitudes(key: str, value) -> np.ndarray:
    """Geodetic latitudes strictly inside (-pi/2, pi/2) rad, as a read-only float array."""
    a = _FINITE(key, value)
    if np.any(np.abs(a) >= np.pi / 2):
        raise ParamError(key, f"expected latitudes in (-pi/2, pi/2) rad (degrees passed?), got {_shown(value)}")
    return a


def _common_shape(named_shapes) -> tuple:
    """The broadcast shape of (field name, shape) pairs; ParamError names the first field whose
    shape does not broadcast with those before it."""
    shape = ()
    for n, s in named_shapes:
        try:
            shape = np.broadcast_shapes(shape, s)
        except ValueError:
            raise ParamError(n, f"expected a shape that broadcasts to {shape} (the fields before it), "
                                f"got shape {s}") from None
    return shape


def _broadcast(obj, names: Sequence[str]) -> tuple:
    """Broadcast the named (checked) array fields to one batch shape, stored read-only."""
    arrays = [getattr(obj, n) for n in names]
    shape = _common_shape((n, a.shape) for n, a in zip(names, arrays))
    for n, a in zip(names, arrays):
        object.__setattr__(obj, n, _readonly(np.broadcast_to(a, shape)))
    return shape
