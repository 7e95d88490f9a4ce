"""What every experiment command shares: strict JSON, the result document's writer (schema and
provenance), figure saving, progress (sitl.app.progress), the output directory check, network
faults on a batch run's measurement keys."""
from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

from sitl.app.progress import progress_printer  # noqa: F401  (the experiments' progress: tqdm)
from sitl.app.provenance import options_scenario  # noqa: F401  (the experiments' scenario of their options)


def strict(v):
    """A JSON-able copy: numpy to Python, inf / nan to None (json.dump(allow_nan=False) works)."""
    import numpy as np

    if isinstance(v, dict):
        return {str(k): strict(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [strict(x) for x in v]
    if isinstance(v, np.ndarray):
        return strict(v.tolist())
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(v) else None
    return v


def write_result(path: Path, doc: dict, *, seed=None, scenario=None) -> dict:
    """Write ``doc`` to ``path`` as strict JSON with the one ``schema`` version and the provenance
    record (sitl.app.provenance.write_json: version, commit, command line, seed, scenario and its
    hash, start time); returns the document written."""
    from sitl.app.provenance import write_json

    return write_json(path, doc, seed=seed, scenario=scenario)


def save_figure(fig, path: Path) -> Path:
    """Write the figure as PNG (110 dpi) and close it. ``bbox_inches="tight"`` grows the canvas to
    whatever is drawn, so no title, subtitle or figure legend is cut off at the edge."""
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=110, bbox_inches="tight", pad_inches=0.1)
    plt.close(fig)
    return path


def run_label(experiment: str, *, paper: str | None = None, seed=None, trials=None, extra: str = "") -> str:
    """The line every figure's title starts with: the experiment by name (and the paper it
    follows, as a reference), then the RNG seed and the number of trials as separate items,
    e.g. ``beacon experiment (after paper seed 002) | RNG seed 1 | 20 trials``."""
    parts = [f"{experiment} experiment" + (f" (after paper seed {paper})" if paper else "")]
    if seed is not None:
        parts.append(f"RNG seed {seed}")
    if trials is not None:
        parts.append(f"{trials} trial{'s' if trials != 1 else ''}")
    if extra:
        parts.append(extra)
    return " | ".join(parts)


def prepare_out(out: Path) -> Path:
    """Create the output directory; a usage error (exit 2, one line) if it cannot be written."""
    from sitl.app.args import UsageError

    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"cannot create output directory {str(out)!r}: {exc.strerror}") from None
    if not out.is_dir() or not os.access(out, os.W_OK | os.X_OK):
        raise UsageError(f"output directory {str(out)!r} is not writable")
    return out


# ------------------------------------------------------------------ network faults on the bus
class MeasurementFaults:
    """A `sitl.bus.transport.FaultFilter` that applies network faults to the MEASUREMENT keys of
    a batch experiment only (``exprs``: key expressions); every other key (truth, the ground
    station's estimates, its link statistics) passes untouched, at its publication time.

    ``faults``: FaultFilters ``(key, payload, t_s) -> [(deliver_at_s, bytes)]`` (e.g.
    ``sitl.netfault.KeyFaults``, ``LinkFault``), and/or KeyFaults rules ``(key_expr, spec)``
    (spec text or ``FaultSpec``), gathered into one ``sitl.netfault.KeyFaults(rules, seed)``.
    The filters see time since the run's start, ``t_s = t_gps_s - t0_gps_s`` (so that
    ``partition=150-180`` means 150 s to 180 s after the first epoch); their delivery times
    are mapped back.  Deterministic for ``seed`` (the rules' generators derive from it and the
    key; the filters given as objects carry their own)."""

    def __init__(self, faults, exprs, *, seed: int = 0, t0_gps_s: float = 0.0):
        from sitl.bus.transport import key_matches, validate_key_expr

        self._key_matches = key_matches
        self.exprs = tuple(validate_key_expr(e) for e in exprs)
        self.t0_gps_s = float(t0_gps_s)
        self.filters = []
        rules = []
        for f in faults or ():
            if isinstance(f, (tuple, list)) and len(f) == 2 and isinstance(f[0], str):
                rules.append((f[0], f[1]))
            elif callable(f):
                self.filters.append(f)
            else:
                raise TypeError(f"bus_faults: expected a FaultFilter or a (key_expr, spec) rule, got {f!r}")
        if rules:
            from sitl.netfault import KeyFaults

            self.filters.insert(0, KeyFaults(rules, seed=int(seed)))
        self._is_meas: dict[str, bool] = {}
        self.passed = 0  # payloads on other keys, untouched
        self.faulted = 0  # payloads on measurement keys handed to the filters

    def __bool__(self) -> bool:
        return bool(self.filters)

    def is_measurement(self, key: str) -> bool:
        m = self._is_meas.get(key)
        if m is None:
            m = self._is_meas[key] = any(self._key_matches(e, key) for e in self.exprs)
        return m

    def __call__(self, key: str, payload: bytes, t_gps_s: float):
        if not self.is_measurement(key):
            self.passed += 1
            return [(t_gps_s, payload)]
        self.faulted += 1
        t0 = self.t0_gps_s
        items = [(t_gps_s - t0, payload)]
        for f in self.filters:
            items = [out for t, p in items for out in f(key, p, t)]
        return [(t + t0, p) for t, p in items]

    def truths(self) -> dict:
        """The injected truth per concrete key: {key: LinkTruth} of every filter that keeps one
        (KeyFaults.truths(); a LinkFault's .truth under its name)."""
        out = {}
        for f in self.filters:
            if hasattr(f, "truths"):
                out.update(f.truths())
            elif hasattr(f, "truth"):
                out[getattr(f, "name", repr(f))] = f.truth
        return out

    def totals(self) -> dict:
        """The truth counters summed over every link (numbers only), plus ``links``."""
        tot: dict = {}
        truths = self.truths()
        for tr in truths.values():
            names = [f.name for f in dataclasses.fields(tr)] if dataclasses.is_dataclass(tr) else list(vars(tr))
            d = {k: getattr(tr, k) for k in names + ["reordered"] if hasattr(tr, k)}
            for k, v in d.items():
                if isinstance(v, bool) or not isinstance(v, (int, float)):
                    continue
                if k.endswith("_max"):
                    tot[k] = max(tot.get(k, 0), v)
                else:
                    tot[k] = tot.get(k, 0) + v
        tot["links"] = len(truths)
        return tot


def measurement_faults(bus_faults, exprs, *, seed: int = 0, t0_gps_s: float = 0.0):
    """The transport's ``faults=`` list for ``bus_faults`` (None / empty: ``[]``, no fault layer
    at all, so a run without faults is the run it always was) and the MeasurementFaults (or None)."""
    if not bus_faults:
        return [], None
    mf = MeasurementFaults(bus_faults, exprs, seed=seed, t0_gps_s=t0_gps_s)
    return ([mf] if mf else []), mf
