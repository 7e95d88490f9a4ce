"""The lag window shared by the beacon locator and the sonde tracker: the history of the steps
of the last ``lag_window_s`` seconds (each with the state before it, its inputs and the counters
it added) and the re-run from the earliest step a late (out-of-sequence) message completed.

Each component keeps its own history entries (a NamedTuple with at least ``t``) and says how to
restore a state, take a step's counters back and re-run a step; the bookkeeping is here.
"""
from __future__ import annotations

from collections.abc import Callable


def prune(hist: list, t: float, lag_s: float, tol: float) -> None:
    """Drop the steps older than the window (t - lag_s, with tolerance tol) from the front."""
    cut = 0
    while cut < len(hist) and hist[cut].t < t - lag_s - tol:
        cut += 1
    if cut:
        del hist[:cut]


def rerun(hist: list, t0: float, tol: float, *, restore: Callable, uncount: Callable, run: Callable,
          events=None) -> int:
    """Re-run the steps of ``hist`` from the first at or after t0 (tolerance tol): the state goes
    back to before it (``restore(entry)``), the counters of the steps re-run are taken back
    (``uncount(entry)``, each), and ``run(entry)`` re-runs each in order (it appends to ``hist``
    again). ``events`` (an integrity-event publisher, or None) is muted meanwhile: events of past
    steps went out already. Returns the number of steps re-run (0: none in the history)."""
    i = next((j for j, e in enumerate(hist) if e.t >= t0 - tol), None)
    if i is None:
        return 0
    redo = hist[i:]
    del hist[i:]
    restore(redo[0])
    for e in redo:
        uncount(e)
    keep = None if events is None else events.transport
    if events is not None:
        events.transport = None
    try:
        for e in redo:
            run(e)
    finally:
        if events is not None:
            events.transport = keep
    return len(redo)
