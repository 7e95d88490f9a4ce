"""The integrity monitor (filters.integrity) wired into the locator, per UAV link (opt-in:
``LocatorConfig(integrity=IntegrityConfig(...))``; recommended settings ``INTEGRITY``).

Each UAV link (channel: its range and Doppler rows) is judged once per epoch, on each primary
track's prior: right after the epoch's innovations nu and their covariance S are built (S = H P
H' + R; "consider": the Schmidt S, with the cross-covariances), the monitor gets z = nu, h = 0,
H = 0, R = diag(S) (InnovationModel), so beta = nu / sqrt(S) exactly.  A link with a row failing
the jump test, or excluded (jumps on ``persist`` epochs, or a window test), is left out of the
update (neither used nor counted as gated) and out of the mirror hypothesis's update and score;
iterated updates keep that set; the per-link chi-square gate stays.  Each UAV id keeps a fixed
observer slot (its monitor column; at most ``integrity_max_links`` judged, the others used
unjudged and counted).  A trial whose links mostly jump at once (more than
``integrity_common_fraction`` of its present links) is not judged that epoch: the track moved,
not a link.  Links are left out only while at least ``integrity_min_links`` (3) of a trial's
present links stay in (three UAVs fix the 6 states with no redundancy: below that the monitor
only detects).  Events (sitl.integrity_events) go on ``<run>/gs/integrity/<channel>`` from
``<source_id>.integrity``, channel ``<beacon_id>.uav<uav id>`` (``.slot<i>`` when fed through
``process`` without UAV ids); counters ``integrity_*``.
"""
from __future__ import annotations

import numpy as np

from filters.integrity import IntegrityMonitor
from sitl.integrity_events import IntegrityEventPublisher

from .config import LocatorConfig

__all__ = ["InnovationModel", "LinkIntegrity", "take_monitor_rows", "merge_monitor_rows"]


class InnovationModel:
    """The integrity monitor's model of the locator's innovations: z = nu, h = 0, H = 0 and
    R_diag = diag(S) (S at the prior), so that beta = nu / sqrt(S) exactly."""

    def __init__(self, r):
        self._r = r

    def h_and_H(self, x):
        k, m = self._r.shape
        return np.zeros((k, m)), np.zeros((k, m, 1))

    def R_diag(self):
        return self._r


def take_monitor_rows(st, idx):
    """The monitor state of batch rows idx (a copy): filters.integrity.MonitorState.take."""
    return st.take(idx)


def merge_monitor_rows(prev, acc, idx, sub):
    """The epoch's new monitor state: acc (None: prev) with rows idx from sub, the state those
    rows stepped to from prev this epoch: filters.integrity.MonitorState.merge."""
    return prev.merge(acc, idx, sub)


class LinkIntegrity:
    """The monitor of one locator: its state over the trials (T,) and 2 x ``integrity_max_links``
    rows, the event publisher (``events``) and the state being built this epoch (``next``: merged
    per filter call, made the state by ``end_epoch``).  The state is replaced per epoch, never
    written in place, so the locator's lag window keeps it by reference."""

    def __init__(self, config: LocatorConfig, run_ids, beacon_id: str, source_id: str, transport=None):
        L = int(config.integrity_max_links)
        self.config = config
        self.beacon_id = beacon_id
        self.n_trials = len(run_ids)
        self.monitor = IntegrityMonitor(config.integrity)
        self.state = self.monitor.init((self.n_trials,), 2 * L, L)
        self.channels = np.repeat(np.arange(L), 2)
        self.next = None  # the state being built this epoch (merged per filter call)
        self._ev_trials = None  # trial of each row of the report being turned into events
        self.events = IntegrityEventPublisher(lambda b: run_ids[self._ev_trials[b[0]]], f"{source_id}.integrity",
                                              transport)

    def begin_epoch(self) -> None:
        self.next = None

    def end_epoch(self) -> None:
        if self.next is not None:
            self.state, self.next = self.next, None

    def judge(self, counters, slots, trial_of_row, n_primary, t, nu, s_diag, mask, rows=None):
        """The monitor's verdict on one filter call's rows (module docstring): the primary tracks'
        rows are judged (beta = nu / sqrt(S), S at the prior), their mirror hypotheses (rows of the
        same trials) take the same verdict.  trial_of_row: the trial of each stacked row, the
        first n_primary rows the tracks; rows: the stacked rows of this call (None: all);
        counters: the locator's (integrity_* counted there); slots: {UAV id: observer slot}.
        Returns mask less the links left out this epoch."""
        c = self.config
        cfg = c.integrity
        L = int(c.integrity_max_links)
        idx = np.arange(len(trial_of_row)) if rows is None else np.asarray(rows)
        trial = trial_of_row[idx]
        prim = np.flatnonzero(idx < n_primary)
        if prim.size == 0:
            return mask
        tr = trial[prim]
        k, N = tr.size, mask.shape[1]
        Nm = min(N, L)
        cnt = counters
        if N > L:
            cnt["integrity_unmonitored"] += int(mask[prim, L:].sum())
        mp = mask[prim, :Nm]
        nup, sp = nu[prim, :Nm], s_diag[prim, :Nm]
        Z = np.full((k, 2 * L), np.nan)
        R = np.ones((k, 2 * L))
        Z[:, :2 * Nm] = np.where(mp[..., None], nup, np.nan).reshape(k, 2 * Nm)
        R[:, :2 * Nm] = np.where(mp[..., None], sp, 1.0).reshape(k, 2 * Nm)
        # a trial whose links mostly jump at once is not judged: its track moved, not one link
        jl = ((np.abs(nup) >= cfg.jump_sigma * np.sqrt(sp)).any(axis=-1) & mp).sum(axis=-1)
        common = jl > c.integrity_common_fraction * np.maximum(mp.sum(axis=-1), 1)
        Z[common] = np.nan
        cnt["integrity_common_mode"] += int(common.sum())
        got = {}

        def verdict(x, P, z, gm, **kw):  # the monitor's verdict only: the locator's own update follows
            got["inert"] = np.asarray(gm.inert)

        prev = self.state
        _, sub, rep = self.monitor.step(prev.take(tr), np.zeros((k, 1)), np.zeros((k, 1, 1)), Z,
                                        InnovationModel(R), self.channels, update=verdict, backend=c.backend)
        self.next = prev.merge(self.next, tr, sub)
        cnt["integrity_epochs"] += 1
        out_link = got["inert"].reshape(k, L, 2).any(axis=-1)[:, :Nm] & mp  # present links left out
        # no redundancy left (fewer than integrity_min_links would stay): detect only
        short = (mp.sum(axis=-1) - out_link.sum(axis=-1)) < c.integrity_min_links
        cnt["integrity_detect_only"] += int((short & out_link.any(axis=-1)).sum())
        out_link[short] = False
        cnt["integrity_links_left_out"] += int(out_link.sum())
        cnt["integrity_exclusions"] += int(rep.newly_excluded.sum())
        cnt["integrity_readmissions"] += int(rep.readmitted.sum())
        uid = {s: u for u, s in slots.items()}
        self._ev_trials = tr
        evs = self.events(rep, self.channels, t, lambda b, ch: f"{self.beacon_id}.uav{uid[ch]}" if ch in uid
                          else f"{self.beacon_id}.slot{ch}", cfg)
        cnt["integrity_events"] += len(evs)
        bad = np.zeros((self.n_trials, N), bool)
        bad[tr, :Nm] = out_link
        return mask & ~bad[trial]
