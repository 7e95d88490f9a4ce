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


def child_env(base=None) -> dict:
    """The environment for a Python child process (a worker, the kernel warm-up, a bench peer)
    that must import *this* copy of the project's packages.

    ``python -m module`` puts the current directory first on ``sys.path``: run from a checkout
    with the package installed elsewhere (CI: a non-editable install in a venv), the children
    imported the checkout's sources while the launcher imported the installed ones, and each
    copy kept its own numba cache (the warm-up's stamp said warm while the workers compiled
    inside the run). ``PYTHONSAFEPATH`` (Python 3.11) drops that entry; the directory holding the
    imported ``sitl`` goes first on ``PYTHONPATH`` instead."""
    import os
    from pathlib import Path

    env = dict(os.environ if base is None else base)
    root = str(Path(__file__).resolve().parent.parent)
    env["PYTHONSAFEPATH"] = "1"
    old = env.get("PYTHONPATH")
    env["PYTHONPATH"] = root if not old else os.pathsep.join([root, old])
    return env
