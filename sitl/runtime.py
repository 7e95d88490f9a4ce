"""Process-wide settings for batch runs (experiments, benchmarks).

* BLAS to one thread: the batched kernels parallelise over trials with numba's threads,
  and an OpenBLAS pool spinning after every small matrix product competes with them for
  the cores (measured: it halves the speed of a 10,000-trial filter step).
"""
from __future__ import annotations

import contextlib

@contextlib.contextmanager
def batch_mode():
    """BLAS on one thread for the duration of a `with` block."""
    # threadpoolctl can only limit BLAS libraries that are already loaded, and scipy
    # ships its own OpenBLAS beside numpy's: load both first.
    import numpy  # noqa: F401
    import scipy.linalg  # noqa: F401
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield
