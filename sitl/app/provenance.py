"""Where an output came from: the record every result.json, report.json and bench output carries.

``provenance(argv, seed, scenario)`` is a JSON-able dict: the skyfuse version (the installed
distribution), the git commit of the checkout the running ``sitl`` package sits in (and whether it
has uncommitted changes; null when not run from a checkout or git is absent -- never an error),
the command line, the seed, the scenario (the SHA-256 of its canonical JSON, and the dict itself),
the start time (UTC, ISO 8601) and the python/numpy/numba versions.

``SCHEMA`` is the one schema version of every output document; ``stamp(doc, ...)`` puts it and the
provenance record into a document (``doc["schema"]``, ``doc["provenance"]``).

The start time is the one wall-clock read here: it records when an output was made, it never
drives a simulation (sitl.pacing stays the only module that paces by the wall clock).
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import hashlib
import json
import math
import platform
import subprocess
import sys
from importlib import metadata
from pathlib import Path

# The schema version of every output document (result.json of each experiment, gnss commands'
# result.json / export.json / rtklib.json, the live runs' report.json, bench JSON). Before it the
# experiments wrote 1 (beacon 2, ekf-vs-ukf none); 3 is the first with the provenance record.
SCHEMA = 3

GIT_TIMEOUT_S = 2.0


def _version(dist: str) -> str | None:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def _package_root() -> Path:
    import sitl

    return Path(sitl.__file__).resolve().parent.parent


def _git(root: Path, *args: str) -> str | None:
    try:
        p = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True,
                           timeout=GIT_TIMEOUT_S, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    return p.stdout.strip() if p.returncode == 0 else None


def git_state(root: Path | None = None) -> dict:
    """``{"commit": sha or None, "dirty": bool or None}`` of the checkout holding ``root`` (default:
    the directory the running ``sitl`` package is in). None when that directory is not the top of
    a git work tree (an installed package inside some other repository reports no commit)."""
    root = Path(root) if root is not None else _package_root()
    top = _git(root, "rev-parse", "--show-toplevel")
    if top is None or Path(top).resolve() != root.resolve():
        return {"commit": None, "dirty": None}
    commit = _git(root, "rev-parse", "HEAD")
    status = _git(root, "status", "--porcelain", "--untracked-files=no")
    return {"commit": commit, "dirty": None if status is None else bool(status)}


def _canonical(v):
    """A JSON-able copy with a single spelling: to_dict() objects and dataclasses as dicts, numpy
    as Python, tuples as lists, paths as strings, non-finite floats as strings."""
    if hasattr(v, "to_dict") and callable(v.to_dict):  # its own canonical form (sitl.scenario.Scenario)
        v = v.to_dict()
    elif dataclasses.is_dataclass(v) and not isinstance(v, type):
        v = {f.name: getattr(v, f.name) for f in dataclasses.fields(v)}
    if isinstance(v, dict):
        return {str(k): _canonical(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, set, frozenset)):
        items = [_canonical(x) for x in v]
        return sorted(items, key=repr) if isinstance(v, (set, frozenset)) else items
    if hasattr(v, "tolist") and callable(v.tolist):  # numpy arrays and scalars
        return _canonical(v.tolist())
    if isinstance(v, bool) or v is None or isinstance(v, (int, str)):
        return v
    if isinstance(v, float):
        return v if math.isfinite(v) else repr(v)
    if isinstance(v, Path):
        return str(v)
    return repr(v)


def scenario_record(scenario) -> dict:
    """``{"sha256": hex, "dict": canonical dict}`` of a scenario (a dict, a dataclass or an object
    with to_dict()); the hash is over its JSON with sorted keys and no spaces; None -> nulls."""
    if scenario is None:
        return {"sha256": None, "dict": None}
    d = _canonical(scenario)
    text = json.dumps(d, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return {"sha256": hashlib.sha256(text.encode("utf-8")).hexdigest(), "dict": d}


# option fields that say where and how a run reports, not what it simulates: left out of the
# scenario a command records (its hash is the same wherever it writes)
NOT_SCENARIO = frozenset({"out", "quiet", "json", "backend", "dask"})


def options_scenario(options, cls=None) -> dict:
    """The scenario of a command made of its options, without NOT_SCENARIO: the fields of an
    options dataclass instance, or those of ``cls`` read from a parsed namespace, or (neither)
    every plain attribute of the namespace (not callables or the subcommand names)."""
    if dataclasses.is_dataclass(options) and not isinstance(options, type):
        names = [f.name for f in dataclasses.fields(options)]
    elif cls is not None:
        names = [f.name for f in dataclasses.fields(cls)]
    else:
        names = [k for k, v in vars(options).items()
                 if not callable(v) and k not in ("command", "experiment", "bench", "gnss")]
    return {k: getattr(options, k) for k in names if k not in NOT_SCENARIO and hasattr(options, k)}


def utc_now_iso() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


_started_utc: str | None = None
_command_line: list[str] | None = None


def mark_started(argv=None) -> str:
    """Record now as the start of this command and ``argv`` as its command line (``skyfuse``'s
    main and ``experiments.run`` call it): the ``started_utc`` and ``command_line`` of every output
    written after it, unless given to provenance()."""
    global _started_utc, _command_line
    _started_utc = utc_now_iso()
    _command_line = None if argv is None else [str(a) for a in argv]
    return _started_utc


def provenance(argv=None, seed=None, scenario=None, *, started_utc: str | None = None) -> dict:
    """The provenance record of one output (see the module doc). ``argv``: the command line
    (default: mark_started()'s, else sys.argv); ``started_utc``: the run's start (default: mark_started()'s, else now)."""
    if argv is None:
        argv = _command_line if _command_line is not None else sys.argv
    sc = scenario_record(scenario)
    return {
        "skyfuse_version": _version("skyfuse"),
        **{f"git_{k}": v for k, v in git_state().items()},
        "command_line": [str(a) for a in argv],
        "seed": None if seed is None else _canonical(seed),
        "scenario_sha256": sc["sha256"],
        "scenario": sc["dict"],
        "started_utc": started_utc or _started_utc or utc_now_iso(),
        "python_version": platform.python_version(),
        "numpy_version": _version("numpy"),
        "numba_version": _version("numba"),
    }


def stamp(doc: dict, *, argv=None, seed=None, scenario=None, started_utc: str | None = None) -> dict:
    """``doc`` with ``schema`` = SCHEMA and ``provenance`` set (in place; returned)."""
    doc["schema"] = SCHEMA
    doc["provenance"] = provenance(argv, seed, scenario, started_utc=started_utc)
    return doc


def write_json(path, doc: dict, *, seed=None, scenario=None, indent: int = 1) -> dict:
    """Write ``doc`` to ``path`` as strict JSON (numpy as Python, inf / nan as null) after
    stamp(): the one ``schema`` version and the provenance record. Returns the document written."""
    from sitl.app.experiments.common import strict

    doc = strict(stamp(doc, seed=seed, scenario=scenario))
    Path(path).write_text(json.dumps(doc, indent=indent, allow_nan=False) + "\n", encoding="utf-8")
    return doc
