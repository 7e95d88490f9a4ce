"""The beacon locator as a bus component: BeaconLocator collects the UAVs' BeaconMeasurements
(``*/uav/*/beacon/<beacon_id>``), steps the batched filter of every trial (one run id, one row) at
once and publishes one Estimate per started trial on ``<run>/gs/estimate/beacon/<beacon_id>``;
``process(t_gps_s, obs)`` is the same step on arrays (ObserverEpoch).

``on_message`` refuses (``rejected``) a message for another beacon, a range or range rate out of
limits, a UAV position off the Earth's neighbourhood, a UAV sigma above ``max_uav_pos_sigma_m`` /
``max_uav_vel_sigma_m_s``, one older than the lag window (``too_late``); copies ((source,
incarnation, seq) seen before) count once as ``duplicate``.  Modes: "fused" (>= 3 observers
used), "degraded" (1-2), "coast" (0), "lost" after ``max_coast_s`` without 3; published as
"ambiguous" (unless lost) while the blind start's mirror hypothesis is carried.  Late measurements
(``lag_window_s``): the epoch they complete is re-run with the later ones (ground_station.beacon).
"""
from __future__ import annotations

import dataclasses
import functools
import math
from collections import Counter
from typing import NamedTuple

import numpy as np

from ground_station import lag_window
from sitl.bus import BeaconMeasurement, Estimate, SequenceTracker, key_for, parse_key

from .config import LocatorConfig
from .estimate import ecef_moments, mixture_moments
from .frame import Frame, ecef_to_cyl, formation_frame
from .integrity import LinkIntegrity
from .measurements import ObserverEpoch, epoch_from_messages, formation_spread
from .multilateration import InitFix, init_fix
from .step import filter_rows

__all__ = ["BeaconLocator"]

_EARTH_R_MIN_M, _EARTH_R_MAX_M = 6.2e6, 7.0e6  # a UAV position outside this shell is absurd


class _Epoch(NamedTuple):
    """One processed epoch in the lag window: its time, the locator's state before it, its
    inputs (per trial {uav id: msg}; late messages are added here) and the counters it added."""

    t: float
    snap: dict
    inputs: list
    added: Counter


class BeaconLocator:
    """Bus component: collects BeaconMeasurements, steps the batched filter, publishes Estimates.

    transport: a ``sitl.bus.Transport`` (None: no bus; feed ``process`` directly).
    run_ids: one run id per Monte Carlo trial (the trial axis of the batch).
    beacon_id: the beacon tracked (key id).
    ``rejected``: messages refused by reason; ``counters``: accepted, duplicate, other_run,
    gated, used, epochs_fused / _degraded / _coast / _lost (summed over trials),
    initialised, mirror_hypotheses / _chosen / _dropped, mirror_outside_volume (the blind start's
    other side refused by ``search_height_m``), published.
    """

    def __init__(self, transport=None, *, run_ids=("run",), beacon_id: str = "b1",
                 config: LocatorConfig = LocatorConfig(), source_id: str = "gs", publish_estimates: bool = True):
        if not isinstance(config, LocatorConfig):
            raise ValueError(f"config must be a LocatorConfig, got {type(config).__name__}")
        run_ids = list(run_ids)
        if not run_ids or len(set(run_ids)) != len(run_ids):
            raise ValueError(f"run_ids must be non-empty and distinct, got {run_ids!r}")
        self.config = config
        # "consider": the acquisition's filter (the first acquire_s seconds of each track)
        self._acquire_config = dataclasses.replace(config, observer_uncertainty="inflate") \
            if config.observer_uncertainty == "consider" else None
        self.transport = transport
        self.run_ids = run_ids
        self.beacon_id = beacon_id
        self.source_id = source_id
        self.publish_estimates = bool(publish_estimates)
        self._trial = {r: k for k, r in enumerate(run_ids)}
        T, n = len(run_ids), config.n_state
        self.t_gps_s: float | None = None  # time of the filters' state (shared by the batch)
        self.y = np.zeros((T, n))  # cylindrical state ("cv") or ECEF position ("position")
        self.P = np.broadcast_to(np.eye(n), (T, n, n)).copy()
        self.frame = Frame(*(np.tile(v, (T, 1)) for v in np.eye(3)[[0, 0, 1, 2]]), np.ones(T, bool))
        self.initialised = np.zeros(T, bool)
        self.init_t_gps_s = np.full(T, np.nan)  # when each trial's track started
        self.nis = np.full(T, np.nan)
        self.n_used = np.zeros(T, int)
        self.coast_s = np.zeros(T)
        self.mode = np.array(["init"] * T, dtype=object)
        self.vel_doppler = np.zeros((T, 3))  # position-only mode: the Doppler velocity
        self.vel_doppler_cov = np.broadcast_to(np.eye(3) * 1e6, (T, 3, 3)).copy()
        self.init_info: list[InitFix | None] = [None] * T
        self.init_window_last: list[ObserverEpoch | None] = [None] * T  # the frame's UAVs at the start
        self.start_side = np.zeros(T, bool)  # True: the mirror of init_info was kept
        # min_formation_sigmas: the verdict of the last epoch with >= 3 UAVs (True: resolved); while
        # False, epochs with 1-2 UAVs use nothing either
        self.formation_resolved = np.zeros(T, bool)
        # the mirror hypothesis of each trial while it is alive (see _initialise)
        self.alt_active = np.zeros(T, bool)
        self.alt_y = np.zeros((T, n))
        self.alt_P = np.broadcast_to(np.eye(n), (T, n, n)).copy()
        self.alt_frame = Frame(*(v.copy() for v in self.frame))
        self.alt_vel = np.zeros((T, 3))
        self.score = np.zeros(T)
        self.alt_score = np.zeros(T)
        # observer_uncertainty="consider": Cov(state error, UAV i's error) per observer slot;
        # slots are fixed per UAV id (_observations), so that slot i is always the same UAV
        self.C = np.zeros((T, 0, n, 6))
        self.alt_C = np.zeros((T, 0, n, 6))
        self.uav_cov_prev = np.zeros((T, 0, 6, 6))  # the last covariance each slot's UAV sent (0: none yet)
        self.uav_incarnation = np.full((T, 0), -1, dtype=np.int64)  # the incarnation each slot's UAV sent (-1: none)
        self._slot: dict = {}
        self.resolve_at = np.full(T, np.inf)
        self._window: list[list] = [[] for _ in range(T)]
        self._pending: list[dict] = [dict() for _ in range(T)]  # per trial {(uav, t): msg}
        self._seqtrack = SequenceTracker()  # duplicates by (run/source id, incarnation, seq)
        # lag window (config.lag_window_s): per processed epoch, the state before it, its inputs
        # (per trial {uav: msg}, completed by late messages) and the counters it added
        self._hist: list[_Epoch] = []
        self._dirty: float | None = None  # the earliest epoch a late message completed
        self._seq: dict[int, int] = {}
        self._keys: dict[str, str] = {}  # run id -> the key its Estimates go out on
        self._report = None  # cached ECEF moments of the current state
        self.counters = Counter()
        self.rejected = Counter()
        # the integrity monitor (config.integrity): one channel (range, Doppler) per UAV id, the
        # column of its fixed observer slot (_observations); batch (T,): judged on each primary track
        self._integrity = None
        self.integrity_events = None
        if config.integrity is not None:
            self._integrity = LinkIntegrity(config, self.run_ids, beacon_id, source_id, transport)
            self.integrity_events = self._integrity.events
        self._sub = None
        if transport is not None:
            self._sub = transport.subscribe(f"*/uav/*/beacon/{beacon_id}", self.on_message)

    # ---------------------------------------------------------------- input
    @property
    def n_trials(self) -> int:
        return len(self.run_ids)

    def on_message(self, key: str, msg) -> None:
        """Bus callback: check and collect one BeaconMeasurement (counted either way)."""
        parsed = parse_key(key)
        if parsed is None or parsed[1] is not BeaconMeasurement or not isinstance(msg, BeaconMeasurement):
            self.rejected["not_a_beacon_measurement"] += 1
            return
        run, _, ids = parsed
        if ids.get("beacon") != self.beacon_id:
            self.rejected["other_beacon"] += 1
            return
        k = self._trial.get(run)
        if k is None:
            self.counters["other_run"] += 1
            return
        if self._seqtrack.update(f"{run}/{msg.source_id}#{msg.incarnation}", msg.seq).duplicate:
            self.counters["duplicate"] += 1  # a copy of a message seen already (source, seq): once only
            return
        c = self.config
        if not (msg.range_m <= c.max_range_m and abs(msg.range_rate_m_s) <= c.max_range_rate_m_s):
            self.rejected["range_out_of_limits"] += 1
            return
        if not (_EARTH_R_MIN_M <= float(np.linalg.norm(msg.uav_pos_ecef_m)) <= _EARTH_R_MAX_M):
            self.rejected["uav_position_implausible"] += 1
            return
        dg = np.diagonal(msg.uav_cov)
        if not (dg[0:3].max() <= c.max_uav_pos_sigma_m ** 2 and dg[3:6].max() <= c.max_uav_vel_sigma_m_s ** 2):
            self.rejected["uav_covariance_absurd"] += 1
            return
        t = float(msg.t_gps_s)
        lag = c.lag_window_s
        if lag > 0 and self.t_gps_s is not None and t <= self.t_gps_s + 1e-6:
            # out of sequence: an epoch processed already -- re-processed at the next step
            e = self._hist_at(t) if t >= self.t_gps_s - lag - 1e-6 else None
            if e is None:
                self.rejected["too_late"] += 1
                return
            inputs = e.inputs[k]
            if ids["uav"] in inputs:
                self.counters["duplicate_epoch"] += 1
                return
            inputs[ids["uav"]] = msg
            self._dirty = e.t if self._dirty is None else min(self._dirty, e.t)
            self.counters["accepted"] += 1
            self.counters["late_accepted"] += 1
            return
        if self.t_gps_s is not None and t < self.t_gps_s - 1e-9:
            self.rejected["stale"] += 1
            return
        slot = (ids["uav"], t)
        pend = self._pending[k]
        if slot in pend:
            self.counters["duplicate_epoch"] += 1  # another message of the same UAV and epoch
            return
        pend[slot] = msg
        self.counters["accepted"] += 1

    def _hist_at(self, t: float, tol: float = 1e-6):
        """The history entry of the processed epoch t (None: no step at t in the window)."""
        for e in reversed(self._hist):
            if abs(e.t - t) <= tol:
                return e
            if e.t < t - tol:
                return None
        return None

    def _take(self, t: float, tol: float = 1e-6) -> list[dict]:
        """The pending measurements of epoch t, per trial {uav id: msg} (older ones dropped,
        counted as stale)."""
        per = []
        for k, pend in enumerate(self._pending):
            now, keep = {}, {}
            for slot, msg in pend.items():
                if abs(slot[1] - t) <= tol:
                    now[slot[0]] = msg
                elif slot[1] < t:
                    self.rejected["stale"] += 1
                else:
                    keep[slot] = msg
            self._pending[k] = keep
            per.append(now)
        return per

    def _new_incarnations(self, inputs: list[dict]):
        """(T, N) bool: the slots whose UAV's message this epoch carries a later incarnation than
        its last ones (a restarted UAV: its onboard filter re-initialised from a least-squares fix,
        so its navigation error is a new one), "consider" only; None when there are none.  Reads
        ``getattr(msg, "incarnation", 0)`` (bus schema 3; 0 before it).  A message of an earlier
        incarnation than the slot's (a dead process's, delayed) changes nothing (counted)."""
        if self.config.observer_uncertainty != "consider":
            return None
        T, N = self.n_trials, len(self._slot)
        if self.uav_incarnation.shape[1] < N:
            grown = np.full((T, N), -1, dtype=np.int64)
            grown[:, :self.uav_incarnation.shape[1]] = self.uav_incarnation
            self.uav_incarnation = grown
        new = None
        for k, now in enumerate(inputs):
            for uid, m in now.items():
                i = self._slot[uid]
                inc, last = int(getattr(m, "incarnation", 0)), int(self.uav_incarnation[k, i])
                if inc > last:
                    if last >= 0:
                        new = np.zeros((T, N), bool) if new is None else new
                        new[k, i] = True
                    self.uav_incarnation[k, i] = inc
                elif inc < last:
                    self.counters["uav_incarnation_older"] += 1
        return new

    def _reset_slots(self, new) -> None:
        """"consider": forget what the state knows of the UAV errors of the slots ``new`` (T, N):
        their cross-covariances with the track and the mirror hypothesis, and the covariance last
        sent (so the Gauss-Markov transition starts afresh from the new incarnation's) -- the new
        incarnation's navigation error is independent of the old one's, as a new UAV's would be."""
        N = new.shape[1]
        self._grow_C(N)
        self.C[:, :N][new] = 0.0
        self.alt_C[:, :N][new] = 0.0
        self.uav_cov_prev[:, :N][new] = 0.0
        self.counters["uav_incarnations"] += int(new.sum())

    def _observations(self, inputs: list[dict]) -> ObserverEpoch:
        """Per trial {uav id: msg} -> padded arrays (UAVs in id order; fixed slots per UAV id
        with "consider" or the integrity monitor: the consider states and the integrity channels
        follow the UAV)."""
        fixed = self.config.observer_uncertainty == "consider" or self.config.integrity is not None
        return epoch_from_messages(inputs, self.n_trials, self._slot if fixed else None)

    # ---------------------------------------------------------------- processing
    def step(self, t_gps_s: float):
        """Process the epoch t_gps_s for every trial and publish the Estimates; returns self.
        Late measurements taken in since the last step (lag window) are used first: the
        state goes back to before their epoch and the epochs since are re-run (not
        published again)."""
        t = float(t_gps_s)
        if self._dirty is not None:
            self._reprocess()
        self._run_epoch(t, self._take(t))
        if self.transport is not None and self.publish_estimates:
            self.publish()
        return self

    def _run_epoch(self, t: float, inputs: list[dict]) -> None:
        lag = self.config.lag_window_s
        if lag <= 0:
            obs = self._observations(inputs)
            self.process(t, obs, self._new_incarnations(inputs))
            return
        if self.t_gps_s is not None and t < self.t_gps_s:
            raise ValueError(f"t_gps_s must not go back: {t} < {self.t_gps_s}")
        snap = self._snapshot()
        before = self.counters.copy()
        obs = self._observations(inputs)  # (assigns new UAVs their slots first)
        self.process(t, obs, self._new_incarnations(inputs))
        self._hist.append(_Epoch(t, snap, inputs, self.counters - before))
        lag_window.prune(self._hist, t, lag, 1e-6)

    def _reprocess(self) -> None:
        """Back to the state before the earliest epoch completed by late messages, then re-run
        that epoch and the later ones of the history with their (completed) inputs -- every
        trial of the batch together (an untouched trial re-runs to the identical result)."""
        t0, self._dirty = self._dirty, None
        n = lag_window.rerun(self._hist, t0, 1e-6, restore=lambda e: self._restore(e.snap),
                             uncount=lambda e: self.counters.subtract(e.added),
                             run=lambda e: self._run_epoch(e.t, e.inputs), events=self.integrity_events)
        if n:
            self.counters["reprocess_runs"] += 1
            self.counters["reprocessed_epochs"] += n

    _SNAP = ("y", "P", "initialised", "init_t_gps_s", "nis", "n_used", "coast_s", "mode", "vel_doppler",
             "vel_doppler_cov", "start_side", "formation_resolved")
    _SNAP_ALT = ("alt_active", "alt_y", "alt_P", "alt_vel", "score", "alt_score", "resolve_at")
    _SNAP_CONSIDER = ("C", "alt_C", "uav_cov_prev", "uav_incarnation")

    def _snapshot(self) -> dict:
        """The state the next epoch changes, copied (only what a step writes: the arrays of the
        filters, the mirror hypotheses while any is alive, the consider states with "consider",
        the start windows; the integrity monitor's state is replaced, never written, per epoch)."""
        d = {name: getattr(self, name).copy() for name in self._SNAP}
        d["t_gps_s"] = self.t_gps_s
        d["frame"] = Frame(*(u.copy() for u in self.frame))
        if self.alt_active.any():  # rows of inactive hypotheses are never read
            for name in self._SNAP_ALT:
                d[name] = getattr(self, name).copy()
            d["alt_frame"] = Frame(*(u.copy() for u in self.alt_frame))
        else:
            d["alt_active"] = self.alt_active.copy()
        if self.config.observer_uncertainty == "consider":
            for name in self._SNAP_CONSIDER:
                d[name] = getattr(self, name).copy()
        if not self.initialised.all():
            d["_window"] = [list(w) for w in self._window]
            d["init_info"] = list(self.init_info)
            d["init_window_last"] = list(self.init_window_last)
        if self._integrity is not None:
            d["integrity_state"] = self._integrity.state
        return d

    def _restore(self, d: dict) -> None:
        for name, v in d.items():
            if name == "integrity_state":
                self._integrity.state = v
            else:
                setattr(self, name, v)
        self._report = None

    def process(self, t_gps_s: float, obs: ObserverEpoch, new_incarnation=None):
        """The filter step of epoch t on arrays (T trials): predict + update the initialised
        trials (and their mirror hypotheses while alive), initialise those whose window is
        complete.  new_incarnation (T, N) bool or None ("consider"): observer slots whose UAV
        restarted (a new incarnation of its source) since its last message -- their consider
        cross-covariances are reset first (:meth:`_reset_slots`)."""
        t = float(t_gps_s)
        if obs.n_trials != self.n_trials:
            raise ValueError(f"obs has {obs.n_trials} trials, the locator {self.n_trials}")
        if self.t_gps_s is not None and t < self.t_gps_s:
            raise ValueError(f"t_gps_s must not go back: {t} < {self.t_gps_s}")
        dt = 0.0 if self.t_gps_s is None else t - self.t_gps_s
        c = self.config
        self._report = None
        if new_incarnation is not None and c.observer_uncertainty == "consider":
            self._reset_slots(np.asarray(new_incarnation, bool))
        if c.init == "prior":  # start from the scenario's prior; this epoch is the first update
            for k in np.flatnonzero(~self.initialised):
                self._initialise(k, self._prior_fix(), t, obs.take(slice(k, k + 1)))
        if c.min_formation_sigmas > 0:
            obs = self._drop_unresolved(obs)
        on = np.flatnonzero(self.initialised)
        alt = np.flatnonzero(self.alt_active)
        self.nis[:] = np.nan
        self.n_used[:] = 0
        if on.size:
            n = on.size
            if alt.size == 0 and n == self.n_trials:  # every row, in order: plain copies
                sub = obs
                y0, P0 = self.y.copy(), self.P.copy()
                fr0 = Frame(*(u.copy() for u in self.frame))
                C0 = self._grow_C(obs.mask.shape[1])[0]
                Pu0 = self.uav_cov_prev[:, :obs.mask.shape[1]]
            else:
                rows = np.concatenate([on, alt])
                sub = obs.take(rows)
                y0 = np.concatenate([self.y[on], self.alt_y[alt]])
                P0 = np.concatenate([self.P[on], self.alt_P[alt]])
                fr0 = Frame(*(np.concatenate([u[on], v[alt]]) for u, v in zip(self.frame, self.alt_frame)))
                Cm, Ca = self._grow_C(obs.mask.shape[1])
                C0 = np.concatenate([Cm[on], Ca[alt]])
                Pu = self.uav_cov_prev[:, :obs.mask.shape[1]]
                Pu0 = np.concatenate([Pu[on], Pu[alt]])
            acq = None
            if c.observer_uncertainty == "consider" and c.acquire_s > 0:
                started = self.init_t_gps_s[np.concatenate([on, alt])]
                acq = t - started < c.acquire_s - 1e-9
            judge = None
            if self._integrity is not None:
                judge = functools.partial(self._judge, np.concatenate([on, alt]), n, t)
                self._integrity.begin_epoch()
            y, P, fr, nis, used, gated, m2ll, vel, C_out = filter_rows(c, self._acquire_config, y0, P0, fr0, sub, dt,
                                                                       alt.size > 0, C0, Pu0, acq, judge)
            if self._integrity is not None:
                self._integrity.end_epoch()
            self.y[on], self.P[on], self.nis[on] = y[:n], P[:n], nis[:n]
            self.alt_y[alt], self.alt_P[alt] = y[n:], P[n:]
            if c.observer_uncertainty == "consider":
                self.C[on], self.alt_C[alt] = C_out[:n], C_out[n:]
            for full, part, fa in zip(self.frame, fr, self.alt_frame):
                full[on] = part[:n]
                fa[alt] = part[n:]
            if vel is not None:
                self.vel_doppler[on], self.vel_doppler_cov[on] = vel[0][:n], vel[1][:n]
                self.alt_vel[alt] = vel[0][n:]
            if alt.size:
                row_of = {k: i for i, k in enumerate(on)}
                self.score[alt] += m2ll[[row_of[k] for k in alt]]
                self.alt_score[alt] += m2ll[n:]
            used, gated = used[:n], gated[:n]
            n_used = used.sum(axis=-1)
            self.n_used[on] = n_used
            self.counters["gated"] += int(gated.sum())
            self.counters["used"] += int(used.sum())
            self.coast_s[on] = np.where(n_used >= 3, 0.0, self.coast_s[on] + dt)
            mode = np.where(n_used >= 3, "fused", np.where(n_used > 0, "degraded", "coast"))
            mode = np.where(self.coast_s[on] > c.max_coast_s, "lost", mode)
            self.mode[on] = mode
            modes = mode.tolist()
            for name in ("fused", "degraded", "coast", "lost"):
                self.counters[f"epochs_{name}"] += modes.count(name)
            # resolve the mirror hypotheses that are decided or whose time is up: keep the likelier
            done = (t >= self.resolve_at[alt] - 1e-9) | (np.abs(self.alt_score[alt] - self.score[alt])
                                                         >= c.init_resolve_llr)
            for k in alt[done]:
                self.alt_active[k] = False
                if self.alt_score[k] < self.score[k]:
                    self.y[k], self.P[k] = self.alt_y[k], self.alt_P[k]
                    self.C[k] = self.alt_C[k]
                    for full, fa in zip(self.frame, self.alt_frame):
                        full[k] = fa[k]
                    self.vel_doppler[k] = self.alt_vel[k]
                    self.start_side[k] = True
                    self.counters["mirror_chosen"] += 1
                else:
                    self.counters["mirror_dropped"] += 1
        if c.observer_uncertainty == "consider":  # the UAVs' covariances sent this epoch, per slot
            self._grow_C(obs.mask.shape[1])
            Pu = self.uav_cov_prev[:, :obs.mask.shape[1]]
            Pu[obs.mask] = obs.cov[obs.mask]
        for k in np.flatnonzero(~self.initialised):  # (none left with a prior)
            if obs.mask[k].sum() >= 3:
                self._window[k].append((t, obs.take(slice(k, k + 1))))
            if len(self._window[k]) >= c.init_epochs:
                self._initialise(k, init_fix(self._window[k], c), t)
        self.t_gps_s = t
        return self

    # ---------------------------------------------------------------- integrity
    def _judge(self, trial_of_row, n_primary, t, nu, s_diag, mask, rows=None):
        """The integrity monitor's verdict on one filter call's rows (LinkIntegrity.judge)."""
        return self._integrity.judge(self.counters, self._slot, trial_of_row, n_primary, t, nu, s_diag, mask, rows)

    def _drop_unresolved(self, obs: ObserverEpoch) -> ObserverEpoch:
        """Tracks in plain ECEF whose >= 3 present UAVs form a formation smaller than their own
        position errors (second singular value of the estimated positions below
        min_formation_sigmas x their RMS per-axis position sigma) use no beacon measurement
        this epoch (counted).  Not before a track starts (the blind start's window takes its
        own epochs) nor in the formation-cylindrical coordinates (a line-like formation far
        from the beacon: there the UAVs' plane is the coordinates' business)."""
        m = obs.mask
        n = m.sum(axis=-1)
        live = self.initialised & self.frame.cart
        cand = (n >= 3) & live
        # fewer than 3 UAVs present (lost or late links) while the last epoch with >= 3 showed an
        # unresolved formation (or none has yet): their ranges cannot tell the side of the UAVs'
        # plane either -- used, 20 % random loss took 2 of 40 printed-geometry trials onto the
        # mirror (seeds 1-5, 300 s), none with this rule
        bad = (n > 0) & (n < 3) & live & ~self.formation_resolved
        if cand.any():
            sv2, sig = formation_spread(obs)
            small = cand & (sv2 < self.config.min_formation_sigmas * sig)
            self.formation_resolved[cand] = ~small[cand]
            bad |= small
        if not bad.any():
            return obs
        self.counters["epochs_formation_unresolved"] += int(bad.sum())
        return obs._replace(mask=m & ~bad[:, None])

    def _grow_C(self, N: int):
        """The consider cross-covariances (T, N, n, 6) of the tracks and of the mirror hypotheses,
        grown to N observer slots (zeros for new ones), and the UAVs' last covariances with them."""
        if self.C.shape[1] < N:
            T, n = self.y.shape
            for name, m in (("C", n), ("alt_C", n), ("uav_cov_prev", 6)):
                old = getattr(self, name)
                new = np.zeros((T, N, m, 6))
                new[:, :old.shape[1]] = old
                setattr(self, name, new)
        return self.C[:, :N], self.alt_C[:, :N]

    def to_state(self, x, P, ob: ObserverEpoch):
        """ECEF (x (6,), P (6, 6)) -> (state, covariance, frame) of this locator's model."""
        if self.config.motion == "position":
            return x[0:3].copy(), P[0:3, 0:3].copy(), None
        fr = formation_frame(ob.pos, ob.mask, x[None, 0:3], None, self.config.axis_ratio)
        if self.config.init == "prior":  # plain ECEF (ground_station.beacon)
            fr = fr._replace(cart=np.ones(1, bool))
        y, Gi, _ = ecef_to_cyl(x[None], fr, jacobian=True)
        Py = Gi[0] @ P @ Gi[0].T
        return y[0], 0.5 * (Py + Py.T), fr

    def _prior_fix(self) -> InitFix:
        """The configured prior as an InitFix (no mirror)."""
        m = np.array(self.config.prior_mean, dtype=float)
        C = np.array(self.config.prior_cov, dtype=float)
        return InitFix(m, C, m[0:3].copy(), 0, 0.0, 0, m.copy(), C.copy(), math.inf)

    def _initialise(self, k: int, fix: InitFix, t: float, ob: ObserverEpoch | None = None) -> None:
        c = self.config
        ob = self._window[k][-1][1] if ob is None else ob
        self.init_t_gps_s[k] = t
        self.init_info[k] = fix
        self.init_window_last[k] = ob
        self._window[k] = []
        self.initialised[k] = True
        self.formation_resolved[k] = False
        y, P, fr = self.to_state(fix.x, fix.P, ob)
        self.y[k], self.P[k] = y, P
        if fr is not None:
            for full, part in zip(self.frame, fr):
                full[k] = part[0]
        self.vel_doppler[k] = fix.x[3:6]
        self.vel_doppler_cov[k] = fix.P[3:6, 3:6]
        self.mode[k] = "fused"
        self.coast_s[k] = 0.0
        self.C[k] = 0.0
        self.alt_C[k] = 0.0
        self.counters["initialised"] += 1
        d = fix.mirror_x[0:3] - fix.x[0:3]
        if fix.mirror_outside:  # the other side is outside the declared search volume: refused
            self.counters["mirror_outside_volume"] += 1
        elif c.init_resolve_s > 0 and d @ np.linalg.solve(fix.P[0:3, 0:3], d) > 9.0:
            y, P, fr = self.to_state(fix.mirror_x, fix.mirror_P, ob)
            self.alt_active[k] = True
            self.alt_y[k], self.alt_P[k] = y, P
            if fr is not None:
                for full, part in zip(self.alt_frame, fr):
                    full[k] = part[0]
            self.alt_vel[k] = fix.mirror_x[3:6]
            self.score[k] = fix.cost
            self.alt_score[k] = fix.mirror_cost
            self.resolve_at[k] = t + c.init_resolve_s
            self.counters["mirror_hypotheses"] += 1

    # ---------------------------------------------------------------- output
    def state_ecef(self):
        """(x (T, 6), P (T, 6, 6)) over ECEF [B, V_B] of every trial (meaningful where
        ``initialised``): the unscented moments of the cylindrical state, or for the
        position-only filter its position with the Doppler velocity (cross-covariance 0)."""
        if self._report is not None:
            return self._report
        motion = self.config.motion
        x, P = ecef_moments(motion, self.y, self.P, self.frame, self.vel_doppler, self.vel_doppler_cov,
                            self.initialised)
        alt = np.flatnonzero(self.alt_active)
        if alt.size:
            # while the mirror hypothesis is alive the posterior is the two-component mixture
            xa, Pa = ecef_moments(motion, self.alt_y[alt], self.alt_P[alt], self.alt_frame.take(alt),
                                  self.alt_vel[alt], self.vel_doppler_cov[alt], np.ones(alt.size, bool))
            x[alt], P[alt] = mixture_moments(x[alt], P[alt], xa, Pa, self.score[alt], self.alt_score[alt])
        self._report = (x, P)
        return self._report

    def estimates(self):
        """One ``Estimate`` per initialised trial: [(run_id, Estimate)]."""
        x, P = self.state_ecef()
        out = []
        for k in np.flatnonzero(self.initialised):
            seq = self._seq.get(k, 0)
            self._seq[k] = seq + 1
            out.append((self.run_ids[k], Estimate(t_gps_s=self.t_gps_s, source_id=self.source_id, seq=seq,
                                                  kind="beacon", pos_ecef_m=x[k, 0:3], vel_ecef_m_s=x[k, 3:6],
                                                  cov=0.5 * (P[k] + P[k].T), nis=float(self.nis[k]),
                                                  mode=self._published_mode(k))))
        return out

    def _published_mode(self, k: int) -> str:
        """The mode an Estimate carries: "ambiguous" while trial k's mirror hypothesis is alive
        (the estimate is the two-side mixture, its side not decided yet) unless "lost"."""
        m = str(self.mode[k])
        return "ambiguous" if self.alt_active[k] and m != "lost" else m

    def publish(self) -> int:
        n = 0
        keys = self._keys
        for run, est in self.estimates():
            key = keys.get(run)
            if key is None:
                key = keys[run] = key_for(run, est, kind="beacon", id=self.beacon_id)
            self.transport.publish(key, est)
            n += 1
        self.counters["published"] += n
        return n

    def close(self) -> None:
        if self._sub is not None:
            self._sub.close()
            self._sub = None
