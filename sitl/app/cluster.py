"""Monte Carlo chunks as Dask tasks: ``--dask local[:N]`` or ``--dask tcp://HOST:PORT``.

An experiment whose trials are independent (each trial's random streams are its own: a
``numpy.random.SeedSequence`` child per trial, or a seed per trial) already runs them in
chunks, one after the other, in one process. ``TrialPool.map(fn, chunks)`` runs the same
chunks as Dask tasks instead -- the same function on the same arguments, each chunk computed
exactly as the one-process loop computes it -- and gives their results back in chunk order,
so that the experiment merges and scores them as before: the result is the one-process
result, bit for bit (tests/app/experiments/test_dask.py compares result.json).

* ``local`` / ``local:N``: a ``distributed.LocalCluster`` of N worker processes (default: one
  per core) with one thread each, started and shut down by the command (no dashboard; the
  scheduler on a free loopback port). Each worker's numba kernels get ``cores // N`` threads
  (at least 1), so the N workers do not oversubscribe the cores the one-process run shares
  among its numba threads.
* ``tcp://HOST:PORT``: an existing scheduler (``dask scheduler`` and ``dask worker`` on the
  hosts, each with this project installed at the same version: a chunk runs the worker's copy
  of the code). The command connects, runs its chunks and disconnects; the cluster stays.

A chunk that raises on a worker, or whose worker dies (the worker is restarted by its nanny
and the chunk retried once elsewhere), stops the run with one line naming the chunk, its
trials, the worker and the error (``ClusterError``: the command exits 1). Progress: one step per
finished chunk (sitl.app.progress, tqdm's rate and ETA). Dask is an optional extra
(``pip install '.[dask]'``); without it ``--dask`` is a usage error before anything starts.

What a cluster gains: the chunks are independent, so N idle cores (on any number of hosts)
run N chunks at once; the wall time of a campaign of C equal chunks goes from C x t_chunk to
about ceil(C / N) x t_chunk plus the transfer of each chunk's result (the experiment's raw
arrays, pickled over TCP) and the workers' start-up (imports, the numba cache). On one machine
already using its cores (numba threads, another user) there is nothing to gain.
"""
from __future__ import annotations

import importlib.util
import os
import re
import uuid
from dataclasses import dataclass

from sitl.params import Check, ParamError, param

#: `--dask` values: local, local:N, tcp://HOST:PORT
_SPEC_RE = re.compile(r"^(?:local(?::(?P<n>\d+))?|(?P<addr>tcp://[^\s:/]+:\d{1,5}))$")
#: how long connecting to an existing scheduler may take, s
CONNECT_TIMEOUT_S = 10.0
#: a chunk whose worker dies is tried on this many workers in all before the run stops
ATTEMPTS_PER_CHUNK = 2


class ClusterError(RuntimeError):
    """A run on Dask could not go on: a chunk failed, a worker died, the scheduler is unreachable
    (one line; the command exits 1)."""


class ChunkFailed(RuntimeError):
    """Raised on the worker: a chunk's function raised (message: the worker and the error)."""


@dataclass(frozen=True)
class DaskSpec:
    """A parsed ``--dask`` value: ``workers`` local worker processes, or an existing scheduler at ``address``."""

    text: str
    workers: int | None = None  # local: the number of worker processes
    address: str | None = None  # tcp://HOST:PORT

    @property
    def local(self) -> bool:
        return self.address is None


def parse_spec(text: str) -> DaskSpec:
    """``local``, ``local:N`` (N >= 1) or ``tcp://HOST:PORT``; a ParamError (one line) otherwise."""
    m = _SPEC_RE.match(str(text).strip())
    if m is None:
        raise ParamError("", f"expected local, local:N or tcp://HOST:PORT, got {text!r}")
    if m["addr"]:
        port = int(m["addr"].rsplit(":", 1)[1])
        if not 0 < port < 65536:
            raise ParamError("", f"expected a port in 1..65535, got {port} in {text!r}")
        return DaskSpec(text, address=m["addr"])
    n = int(m["n"]) if m["n"] else (os.cpu_count() or 1)
    if n < 1:
        raise ParamError("", f"expected local:N with N >= 1 worker processes, got {text!r}")
    return DaskSpec(text, workers=n)


def available() -> bool:
    """Whether dask.distributed can be imported (the optional extra ``dask``)."""
    return importlib.util.find_spec("dask") is not None and importlib.util.find_spec("distributed") is not None


def _dask_check() -> Check:
    def test(v):
        if v is None:
            return None
        if not isinstance(v, str):
            raise ParamError("", f"expected local, local:N or tcp://HOST:PORT, got {v!r}")
        parse_spec(v)
        if not available():
            raise ParamError("", "needs dask and distributed, the optional extra: pip install '.[dask]'")
        return v

    return Check(test)


def dask_option():
    """The ``--dask SPEC`` option of an experiment whose chunks run as Dask tasks (a fresh field per class)."""
    return param(None, check=_dask_check(), metavar="SPEC",
                 doc="run the Monte Carlo chunks as Dask tasks: local[:N] (a local cluster of N worker "
                     "processes, started and stopped by the command) or tcp://HOST:PORT (an existing "
                     "scheduler); the result equals the one-process run's",
                 default_help="default: in this process")


# ------------------------------------------------------------------ on the worker
def _run_chunk(fn, args, kwargs):
    """The task: ``fn(*args, **kwargs)`` with BLAS on one thread (as the command runs it); an
    exception comes back as ChunkFailed naming the worker and the error."""
    from sitl.runtime import batch_mode

    try:
        with batch_mode():
            return fn(*args, **kwargs)
    except Exception as exc:  # every error of the chunk, named in one line
        try:
            from distributed import get_worker

            where = get_worker().address
        except Exception:
            where = "?"
        reason = " ".join(str(exc).split()) or "(no message)"
        raise ChunkFailed(f"on worker {where}: {type(exc).__name__}: {reason}") from None


# ------------------------------------------------------------------ on the client
class TrialPool:
    """Runs chunks as Dask tasks (module doc). A context manager: entering starts the local
    cluster or connects to the scheduler; leaving closes the client and the local cluster (its
    worker processes and ports)."""

    def __init__(self, spec: DaskSpec | str, *, progress=None):
        self.spec = parse_spec(spec) if isinstance(spec, str) else spec
        self.progress = progress
        self.cluster = None
        self.client = None

    # -------------------------------------------------------------- start and stop
    def __enter__(self) -> "TrialPool":
        import logging

        import dask
        from distributed import Client, LocalCluster

        self._config = dask.config.set({"distributed.scheduler.allowed-failures": ATTEMPTS_PER_CHUNK - 1,
                                        "distributed.worker.daemon": False})
        self._config.__enter__()
        try:
            if self.spec.local:
                n = self.spec.workers
                threads = max(1, (os.cpu_count() or 1) // n)
                self.cluster = LocalCluster(
                    n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1", scheduler_port=0,
                    # no dashboard; the scheduler's HTTP routes (always served) on a free loopback port, not 8787
                    dashboard_address=None, scheduler_kwargs={"dashboard": False, "dashboard_address": "127.0.0.1:0"},
                    silence_logs=logging.CRITICAL,
                    env={"NUMBA_NUM_THREADS": str(threads), "PYTHONPATH": self._pythonpath()})
                self.client = Client(self.cluster, timeout=CONNECT_TIMEOUT_S)
            else:
                try:
                    self.client = Client(self.spec.address, timeout=CONNECT_TIMEOUT_S)
                except (OSError, TimeoutError) as exc:
                    raise ClusterError(f"dask: cannot connect to the scheduler {self.spec.address}: "
                                       f"{' '.join(str(exc).split())}") from None
        except BaseException:
            self._close()
            raise
        if self.progress:
            self.progress(f"dask: {self.describe()}")
        return self

    @staticmethod
    def _pythonpath() -> str:
        """The workers import this copy of the project (sitl.runtime.child_env's PYTHONPATH)."""
        from sitl.runtime import child_env

        return child_env()["PYTHONPATH"]

    def describe(self) -> str:
        """Where the chunks run: the scheduler's address and its workers."""
        info = self.client.scheduler_info()
        workers = info.get("workers", {})
        threads = sum(w.get("nthreads", 0) for w in workers.values())
        kind = "local cluster" if self.spec.local else "scheduler"
        return f"{kind} {info.get('address', '?')}, {len(workers)} worker(s), {threads} thread(s)"

    def __exit__(self, *exc) -> None:
        self._close()

    def _close(self) -> None:
        client, cluster, self.client, self.cluster = self.client, self.cluster, None, None
        try:
            if client is not None:
                client.close(timeout=CONNECT_TIMEOUT_S)
        finally:
            try:
                if cluster is not None:
                    cluster.close(timeout=CONNECT_TIMEOUT_S)
            finally:
                cfg, self._config = getattr(self, "_config", None), None
                if cfg is not None:
                    cfg.__exit__(None, None, None)

    # -------------------------------------------------------------- the chunks
    def map(self, fn, chunks, *, labels=None, kwargs=None) -> list:
        """``[fn(*args, **kwargs) for args in chunks]`` as Dask tasks, in chunk order. ``labels``:
        one text per chunk for progress and errors (e.g. "trials 10-19"). A failed chunk raises
        ClusterError (one line) after the other chunks are cancelled."""
        from distributed import as_completed
        from distributed.client import FutureCancelledError

        try:
            from distributed.scheduler import KilledWorker
        except ImportError:  # pragma: no cover - older distributed
            from distributed import KilledWorker

        if self.client is None:
            raise RuntimeError("TrialPool.map outside its with block")
        chunks = [tuple(c) for c in chunks]
        labels = list(labels) if labels is not None else [f"chunk {i}" for i in range(len(chunks))]
        kw = dict(kwargs or {})
        run = uuid.uuid4().hex[:12]  # the keys of this map: unique on a shared scheduler
        futures = [self.client.submit(_run_chunk, fn, args, kw, key=f"skyfuse-{run}-chunk-{i}", pure=False)
                   for i, args in enumerate(chunks)]
        index = {f.key: i for i, f in enumerate(futures)}
        results: list = [None] * len(chunks)
        done = 0
        if self.progress:
            self.progress(None, done=0, total=len(chunks))
        try:
            for fut in as_completed(futures):
                i = index[fut.key]
                try:
                    results[i] = fut.result()
                except ChunkFailed as exc:
                    raise ClusterError(f"dask: {labels[i]} failed {exc}") from None
                except KilledWorker as exc:
                    last = getattr(exc, "last_worker", None)
                    where = getattr(last, "address", None) or "?"
                    raise ClusterError(f"dask: {labels[i]}: its worker died ({ATTEMPTS_PER_CHUNK} attempt(s), last on "
                                       f"{where})") from None
                except FutureCancelledError:
                    raise ClusterError(f"dask: {labels[i]} was cancelled (the scheduler or its workers went "
                                       f"away)") from None
                except Exception as exc:  # the scheduler could not run it at all (e.g. unpicklable)
                    raise ClusterError(f"dask: {labels[i]} failed: {type(exc).__name__}: "
                                       f"{' '.join(str(exc).split())}") from None
                fut.release()
                done += 1
                if self.progress:
                    self.progress(f"{labels[i]} done", done=done, total=len(chunks))
        finally:
            pending = [f for f in futures if not f.done()]
            if pending:
                self.client.cancel(pending)
        return results


def trial_pool(spec: str | None, *, progress=None):
    """A TrialPool for ``spec`` (the ``--dask`` value), or a null context (None) when it is None."""
    import contextlib

    if spec is None:
        return contextlib.nullcontext(None)
    return TrialPool(spec, progress=progress)
