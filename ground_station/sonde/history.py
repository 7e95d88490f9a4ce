"""The sonde tracker's lag window: per step, a copy of what it writes and the epochs it processed,
so that a late (out-of-sequence) message re-runs the steps since the one that would have processed
it (the bookkeeping is ground_station.lag_window's, shared with the beacon locator)."""
from __future__ import annotations

from typing import NamedTuple

from ground_station import lag_window

__all__ = ["HistoryStep", "LagWindow"]


class HistoryStep(NamedTuple):
    """One step in the lag window: its time, the previous step's, the tracker's state before
    it, the epochs it processed ({tau: {sonde: [relay, radar]}}) and the counters it added."""

    t: float
    t_prev: float
    snap: dict
    epochs: dict
    added: dict


class LagWindow:
    """SondeTracker's part: the steps of the lag window, their re-run and the state snapshots."""

    def _run_step(self, t: float, epochs: dict) -> None:
        """One step's filtering (no output); with a lag window, recorded in the history."""
        lag = self.params.lag_window_s
        if lag <= 0:
            self._step_core(t, epochs)
            return
        snap = self._snapshot()
        before = self.counters.as_dict()
        t_prev = self._t_last
        self._step_core(t, epochs)
        self._t_last = t
        after = self.counters.as_dict()
        self._hist.append(HistoryStep(t, t_prev, snap, epochs, {k: after[k] - before[k] for k in after if after[k] != before[k]}))
        lag_window.prune(self._hist, t, lag, 1e-9)

    def _hist_for(self, tau: float):
        """The step of the history that processes epoch tau (t_prev < tau <= t), or None."""
        for e in self._hist:
            if e.t_prev < tau <= e.t:
                return e
        return None

    def _reprocess(self) -> None:
        t0, self._dirty = self._dirty, None
        c = self.counters

        def restore(e):
            self._restore(e.snap)
            self._t_last = e.t_prev

        def uncount(e):
            for k, v in e.added.items():
                setattr(c, k, getattr(c, k) - v)

        n = lag_window.rerun(self._hist, t0, 0.0, restore=restore, uncount=uncount,
                             run=lambda e: self._run_step(e.t, e.epochs), events=self._events)
        if n:
            c.reprocess_runs += 1
            c.reprocessed_epochs += n

    _SNAP_ARRAYS = ("_x", "_P", "_t", "_t_init", "_t_meas", "_landed", "_land_t", "_land_a", "_land_b", "_land_var",
                    "_land_v", "_nis", "_rejects", "_bias_last")

    def _snapshot(self) -> dict:
        """Copies of what a step writes (the per-sonde arrays, the sondes' satellite error-state
        maps, the integrity monitor's bookkeeping); caches and the model are kept."""
        d = {name: getattr(self, name).copy() for name in self._SNAP_ARRAYS}
        d["_window"] = self._window.copy()
        d["_slots"], d["_ids"], d["_keys"] = dict(self._slots), list(self._ids), list(self._keys)
        d["_bias_map"] = [dict(m) for m in self._bias_map]
        d["_bias_owner"] = [list(o) for o in self._bias_owner]
        d["_bias_prev"] = list(self._bias_prev)
        if self._mon is not None:
            d["_chan_of"], d["_chan_sat"] = dict(self._chan_of), list(self._chan_sat)
            d["_chan_last"], d["_mon_k"] = self._chan_last.copy(), self._mon_k
            d["_cohorts"] = [list(co) for co in self._cohorts]  # each state is replaced by a step, not written
        return d

    def _restore(self, d: dict) -> None:
        for name, v in d.items():
            setattr(self, name, v)
