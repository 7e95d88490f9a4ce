"""Is numba's on-disk cache of the project's kernels warm? (the launcher's start-up).

numba keeps each ``cache=True`` kernel it compiled beside its source, in the module's
``__pycache__`` (``NAME.FUNC-LINE.py311.nbi`` index + ``.nbc`` code), or under
``$NUMBA_CACHE_DIR`` when that is set (or in ``~/.cache/numba`` when the tree is read-only).
A cold cache (a fresh install, the caches deleted, a kernel's source changed) costs a minute
or so of compiling on the first run; a warm one costs a second of loading.

The launcher used to run a batch warm-up in a subprocess beside the workers at every start
(2.5 s of CPU on a 2-core machine, competing with the workers' own start). Now a stamp
records a warm cache: after a warm-up that succeeded, ``mark_warm`` writes the fingerprint of
the sources (every ``.py`` file of the packages: path, size, mtime), numba's and Python's
versions and the number of index files; ``is_warm`` compares them (a stat of each source:
milliseconds). Any difference -- a source edited, the caches deleted, another numba -- and
the launcher warms up again, saying so at once, with progress (index files written so far
against those the last cold warm-up wrote) and an estimate (that warm-up's duration, else
`DEFAULT_COLD_S`).
"""
from __future__ import annotations

import hashlib
import json
import os
import sys
from pathlib import Path

#: the packages whose kernels the live run uses (their sources fingerprint the cache)
PACKAGES = ("sitl", "filters", "vehicles", "ground_station")
STAMP_NAME = "skyfuse_kernels_warm.json"
#: a cold warm-up's duration when none was measured here yet (measured: 26 s for 22 kernels on this 2-core machine, idle)
DEFAULT_COLD_S = 30.0
#: index files a cold warm-up of the demo writes when none was measured here yet
DEFAULT_KERNELS = 22


def _roots() -> list[Path]:
    import importlib.util
    out = []
    for name in PACKAGES:
        spec = importlib.util.find_spec(name)
        if spec is not None and spec.submodule_search_locations:
            out.extend(Path(p) for p in spec.submodule_search_locations)
    return out


def cache_dirs() -> list[Path]:
    """Where numba keeps the project's kernels: $NUMBA_CACHE_DIR, else each package's tree
    (its __pycache__ directories), plus ~/.cache/numba (numba's fallback for a read-only tree)."""
    env = os.environ.get("NUMBA_CACHE_DIR")
    if env:
        return [Path(env)]
    return [*_roots(), Path.home() / ".cache" / "numba"]


def _index_files(since_s: float | None = None) -> int:
    n = 0
    for d in cache_dirs():
        if not d.is_dir():
            continue
        for p in d.rglob("*.nbi"):
            if since_s is None:
                n += 1
            else:
                try:
                    n += p.stat().st_mtime >= since_s
                except OSError:
                    pass
    return n


def fingerprint() -> str:
    """A digest of the project's sources (path, size, mtime of every .py), numba's and Python's
    versions, and the interpreter."""
    try:
        import numba
        nb = numba.__version__
    except ImportError:
        nb = "none"
    h = hashlib.sha256(f"{nb}|{sys.version}|{sys.executable}|{os.environ.get('NUMBA_CACHE_DIR', '')}".encode())
    for root in _roots():
        for p in sorted(root.rglob("*.py")):
            try:
                st = p.stat()
            except OSError:
                continue
            h.update(f"{p}|{st.st_size}|{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


def stamp_path() -> Path:
    env = os.environ.get("NUMBA_CACHE_DIR")
    if env:
        return Path(env) / STAMP_NAME
    roots = _roots()
    d = roots[0] / "__pycache__" if roots else Path.home() / ".cache" / "skyfuse"
    if not os.access(d if d.is_dir() else d.parent, os.W_OK):
        d = Path.home() / ".cache" / "skyfuse"
    return d / STAMP_NAME


def _read_stamp() -> dict:
    try:
        return json.loads(stamp_path().read_text())
    except (OSError, ValueError):
        return {}


def is_warm() -> bool:
    """The stamp matches the sources and the cache still holds its index files."""
    st = _read_stamp()
    return bool(st) and st.get("fingerprint") == fingerprint() and _index_files() >= int(st.get("index_files", 1 << 30))


def estimate() -> tuple[float, int]:
    """(seconds, index files) a cold warm-up took here last time (else the defaults)."""
    st = _read_stamp()
    return float(st.get("cold_s") or DEFAULT_COLD_S), int(st.get("cold_kernels") or DEFAULT_KERNELS)


def written_since(t_unix_s: float) -> int:
    """Index files written since t (a warm-up's progress)."""
    return _index_files(since_s=t_unix_s)


def mark_warm(elapsed_s: float, written: int) -> None:
    """Record a warm cache after a warm-up that succeeded (elapsed_s, index files written: the
    next cold start's estimate when this one compiled most kernels)."""
    old = _read_stamp()
    cold = written >= 0.5 * estimate()[1]
    doc = {"fingerprint": fingerprint(), "index_files": _index_files(),
           "cold_s": round(elapsed_s, 1) if cold else old.get("cold_s"),
           "cold_kernels": written if cold else old.get("cold_kernels")}
    p = stamp_path()
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp = p.with_suffix(".tmp")
        tmp.write_text(json.dumps(doc))
        os.replace(tmp, p)
    except OSError:
        pass  # not recorded: the next start warms up again


__all__ = ["cache_dirs", "estimate", "fingerprint", "is_warm", "mark_warm", "stamp_path", "written_since"]
