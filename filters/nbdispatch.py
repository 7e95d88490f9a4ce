"""One compiled version per numba kernel called from Python.

numba compiles a new version of a kernel for every distinct tuple of argument types, and a
read-only array (a broadcast view, an array its owner froze) or a non-contiguous one is a
different type from a writable C array. Left to itself numba compiled the large EKF/UKF
kernels up to 8 times each in the test suite (5-10 s per version on a cold cache), for
versions that differ only in those flags. Here a kernel declares ONE signature whose input
arrays are read-only (and, where a caller passes a broadcast view, of any layout): numba
converts a writable or C-contiguous array to it at dispatch without a copy, so one version
serves every caller; outputs stay writable. The signature is compiled (or loaded from the
on-disk cache) on the kernel's first use, not at import: a process pays only for the kernels
it calls. After that the kernel compiles nothing else, so an argument of another dtype or
rank is a TypeError (the wrappers convert dtypes before calling).

Only the drivers called from Python need a declared signature: the functions they call are
compiled for the driver's argument types, once, provided the drivers pass them the same
types (a literal ``0`` is typed Literal[int](0), a different type from int64: the serial
drivers pass ``np.int64(0)``).
"""
from __future__ import annotations

import threading

from numba import types

_SIGS: dict = {}
_READY: set = set()
_LOCK = threading.Lock()


def ro(ndim, layout="C", dtype=types.float64):
    """A read-only input array type; layout "A" also takes strided and broadcast views."""
    return types.Array(dtype, ndim, layout, readonly=True)


def rw(ndim, dtype=types.float64):
    """A writable C-contiguous array type (outputs, arrays updated in place)."""
    return types.Array(dtype, ndim, "C")


def declare(*argtypes):
    """Decorator (outside nb.njit): the one signature of a kernel, compiled by ready()."""
    def deco(disp):
        _SIGS[disp] = tuple(argtypes)
        return disp
    return deco


def ready(disp):
    """disp compiled for its declared signature, with further compilation disabled."""
    if disp not in _READY:
        with _LOCK:
            if disp not in _READY:
                disp.compile(_SIGS[disp])
                disp.disable_compile()
                _READY.add(disp)
    return disp
