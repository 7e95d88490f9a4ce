"""The radiosonde tracker on the bus (Moroz et al., seed 004): relayed GNSS fused with an
aerological radar, EKF or UKF, for one mode ("fused", "radar_only", "relay_only") and any number of
sondes as one batch. It buffers the relay and radar messages, processes each epoch in time order
(initialise, predict, gated update, landing, loss) and publishes an Estimate per sonde and step."""
from __future__ import annotations

import math
from collections import defaultdict

import numpy as np

from filters.integrity import IntegrityMonitor
from filters.ukf import SigmaPoints
from sitl.bus import (
    Estimate,
    RadarMeasurement,
    SequenceTracker,
    SondeRelay,
    is_valid_id,
    key_for,
    key_pattern,
    parse_key,
)
from sitl.integrity_events import IntegrityEventPublisher

from .counters import TrackerCounters
from .epoch_model import EpochModel
from .history import HistoryStep, LagWindow
from .initialise import Initialisation
from .integrity import IntegrityGuard
from .landing import Landing, curvature_drop_cov
from .params import SondeTrackerParams, layout_for
from .relay_errors import RelayErrorStates
from .transition import SondeTransition
from .update import Updates
from .window import ManoeuvreWindow

__all__ = ["SondeTracker"]


class SondeTracker(Updates, EpochModel, Initialisation, RelayErrorStates, IntegrityGuard, Landing, LagWindow):
    """EKF/UKF radiosonde tracker on the bus, for one mode and any number of sondes.

    run_id : the bus run prefix. params : SondeTrackerParams (mode, models, gating).
    source_id : the publisher id of its Estimates (default ``sonde_tracker.<label>``).
    sonde_ids : follow only these sondes (default: every sonde seen).
    radar_id : follow only this radar (default: the first radar heard).
    """

    def __init__(self, run_id: str, params: SondeTrackerParams | None = None, *, source_id: str | None = None,
                 sonde_ids=None, radar_id: str | None = None):
        if not is_valid_id(run_id):
            raise ValueError(f"run_id must be 1..64 chars of [A-Za-z0-9_.-], got {run_id!r}")
        self.params = p = SondeTrackerParams() if params is None else params
        if not isinstance(p, SondeTrackerParams):
            raise TypeError(f"params: expected a SondeTrackerParams, got {type(p).__name__}")
        self.run_id = run_id
        self.label = p.mode_label
        self.source_id = source_id or f"sonde_tracker.{self.label}"
        if not is_valid_id(self.source_id):
            raise ValueError(f"source_id must be 1..64 chars of [A-Za-z0-9_.-], got {self.source_id!r}")
        self.sonde_ids = None if sonde_ids is None else tuple(str(s) for s in sonde_ids)
        self.radar_id = radar_id
        self.layout = layout_for(p.mode, p.radar_noise, p.relay_bias_states, p.kinematics)
        self.counters = TrackerCounters()
        self._seqtrack = SequenceTracker()
        self._transport = None
        self._subs: list = []
        self._seq = 0
        self._transition: SondeTransition | None = None
        self._radar_sites: dict = {}
        self._points = SigmaPoints(self.layout.n, alpha=1.0, beta=2.0, kappa=0.0)
        n = self.layout.n
        self._slots: dict[str, int] = {}
        self._ids: list[str] = []
        self._keys: list[str] = []
        self._x = np.zeros((0, n))
        self._P = np.zeros((0, n, n))
        self._t = np.zeros(0)  # filter time per sonde (NaN before initialisation)
        self._t_init = np.zeros(0)  # time of the track's last (re)initialisation
        self._t_meas = np.zeros(0)  # time of the track's last accepted measurement (params.max_coast_s)
        self._landed = np.zeros(0, dtype=bool)  # the track has landed (relaxed kinematics, params.landing)
        # the landing's uncertain time (_land): when, the direction back up the trajectory a = V / V_up, the
        # covariance of the position with its height b = P n, the height's variance and the descent speed
        self._land_t = np.zeros(0)
        self._land_a, self._land_b = np.zeros((0, 3)), np.zeros((0, 3))
        self._land_var, self._land_v = np.zeros(0), np.zeros(0)
        self._ground_h_m = None  # the ground's height (the site's), for the landing
        self._nis = np.zeros(0)  # summed block NIS of the last processed epoch
        self._rejects = np.zeros((0, 2), dtype=np.int64)  # consecutive rejections [relay, radar]
        self._window = ManoeuvreWindow(p.manoeuvre_window or 1)  # the sliding-window NIS test's memory
        self._pending: dict[float, dict[str, list]] = defaultdict(dict)
        # lag window (params.lag_window_s): per step, the state before it, the epochs it processed
        # ({tau: {sonde: [relay, radar]}}, completed by late messages) and the counters it added
        self._hist: list[HistoryStep] = []
        self._dirty: float | None = None  # the earliest step a late message completed
        self._t_last = -math.inf  # the last step's time
        self._gates: dict[int, float] = {}
        # per-satellite error states, per sonde: sat_id -> slot, slot -> sat_id, last use, last epoch's columns
        self._bias_map: list[dict] = []
        self._bias_owner: list[list] = []
        self._bias_last = np.zeros((0, self.layout.nb))
        self._bias_prev: list = []
        self._err_prm = None
        # the integrity monitor: rows [pr of S satellite channels, their prr, radar range, az, el]
        self._mon = None if p.integrity is None else IntegrityMonitor(p.integrity)
        self._events = None
        if self._mon is not None:
            S = p.integrity_sat_channels if self.layout.uses_relay else 0
            R = 3 if self.layout.uses_radar else 0
            a = np.arange(S)
            self._mon_S, self._mon_R = S, R
            self._mon_ch = np.concatenate([a, a, S + np.arange(R)]).astype(np.int64)
            self._chan_of: dict = {}  # satellite id -> channel
            self._chan_sat: list = [None] * S
            self._chan_last = np.full(S, -(10**9), dtype=np.int64)  # monitor epoch of each channel's last use
            self._mon_k = 0  # monitor epochs so far
            self._cohorts: list = []  # [first slot, end slot, MonitorState]: sondes that joined together
            self._guard: dict = {}  # slot -> (inert (m_mon,), r used (m_mon,)) of the current epoch
            self._mon_models: dict = {}  # (dt, slots) -> the epoch's measurement model, built once
            self._events = IntegrityEventPublisher(run_id, f"{self.source_id}.integrity")
            # a readmitted or long-unused channel has a fresh window: reuse after this many epochs
            self._chan_age = p.integrity.window + p.integrity.readmit_after + 1

    # -- bus ---------------------------------------------------------------

    def attach(self, transport) -> list:
        """Subscribe to the relay and radar messages of the run (and publish Estimates there)."""
        self._transport = transport
        if self._events is not None:
            self._events.transport = transport
        sondes = self.sonde_ids or ("*",)
        for s in sondes:
            ids = {} if s == "*" else {"sonde": s}
            if self.layout.uses_relay:
                self._subs.append(transport.subscribe(key_pattern(self.run_id, SondeRelay, **ids), self.on_message))
            if self.layout.uses_radar:
                self._subs.append(transport.subscribe(key_pattern(self.run_id, RadarMeasurement, **ids),
                                                      self.on_message))
        return list(self._subs)

    def close(self) -> None:
        for s in self._subs:
            s.close()
        self._subs.clear()

    def on_message(self, key: str, msg) -> None:
        """Buffer one bus message for its epoch (processed by ``step``)."""
        c = self.counters
        c.messages += 1
        parsed = parse_key(key) if isinstance(key, str) else None
        if parsed is None or parsed[0] != self.run_id or "sonde" not in parsed[2]:
            c.ignored += 1
            return
        _, cls, ids = parsed
        sonde = ids["sonde"]
        if self.sonde_ids is not None and sonde not in self.sonde_ids:
            c.ignored += 1
            return
        if isinstance(msg, SondeRelay) and cls is SondeRelay and self.layout.uses_relay:
            kind = 0
        elif isinstance(msg, RadarMeasurement) and cls is RadarMeasurement and self.layout.uses_radar:
            if self.radar_id is None:
                self.radar_id = ids["radar"]
            if ids["radar"] != self.radar_id:
                c.ignored += 1
                return
            kind = 1
        else:
            c.ignored += 1
            return
        if self._seqtrack.update(f"{key}|{msg.source_id}#{msg.incarnation}", msg.seq).duplicate:  # per stream
            c.duplicates += 1
            return
        t = float(msg.t_gps_s)
        slot = self._slots.get(sonde)
        lag = self.params.lag_window_s
        if lag > 0 and self._hist and (t <= self._hist[-1].t and (slot is None or not self._t[slot] < t)):
            # out of sequence (a step at or after t has run): re-processed at the next step
            e = self._hist_for(t) if t >= self._hist[-1].t - lag - 1e-9 else None
            if e is None:
                c.too_late += 1
                return
            entry = e.epochs.setdefault(t, {}).setdefault(sonde, [None, None])
            if entry[kind] is not None:
                c.superseded += 1
            entry[kind] = msg
            c.late_accepted += 1
            self._dirty = e.t if self._dirty is None else min(self._dirty, e.t)
            return
        if slot is not None and self._t[slot] >= t:  # NaN (not initialised yet) compares False
            c.stale += 1
            return
        entry = self._pending[t].setdefault(sonde, [None, None])
        if entry[kind] is not None:
            c.superseded += 1
        entry[kind] = msg

    def step(self, t_gps_s: float) -> list[Estimate]:
        """Process every buffered epoch <= t, predict every initialised sonde to t and publish
        (and return) one Estimate per sonde. Late messages taken in since the last step (lag
        window) are used first: the state goes back to before the step that would have
        processed them and the steps since are re-run (their Estimates not published again)."""
        t = float(t_gps_s)
        if not math.isfinite(t):
            raise ValueError(f"t_gps_s must be finite, got {t_gps_s!r}")
        if self._dirty is not None:
            self._reprocess()
        epochs = {tau: self._pending.pop(tau) for tau in sorted(k for k in self._pending if k <= t)}
        self._run_step(t, epochs)
        out = []
        for slot in np.flatnonzero(self._t == t):
            out.append(self._estimate(int(slot), t))
        return out

    def _step_core(self, t: float, epochs: dict) -> None:
        for tau in sorted(epochs):  # (a late message may have added an earlier epoch)
            self._process(tau, epochs[tau])
        live = np.flatnonzero(self._t < t)  # initialised and behind (NaN excluded)
        if live.size:
            self._predict(live, t)
            self._nis[live] = np.nan
        self._land()
        mc = self.params.max_coast_s
        if mc is not None:
            gone = np.flatnonzero(np.isfinite(self._t) & (t - self._t_meas > mc))
            if gone.size:
                self._lose(gone)

    def _lose(self, slots) -> None:
        """Tracks with no accepted measurement for longer than ``max_coast_s``: lost. They are
        uninitialised again (no Estimate is published; the next relay or radar epoch that can fix
        the sonde initialises it as at its acquisition), their bookkeeping reset. Counted ``lost``."""
        for slot in slots:
            self._t[slot] = self._t_init[slot] = self._t_meas[slot] = np.nan
            self._nis[slot] = np.nan
            self._landed[slot] = False
            self._land_t[slot] = np.nan
            self._rejects[slot] = 0
            self._window.reset(slot)
            if self.layout.nb:
                self._bias_clear(slot)
        self.counters.lost += len(slots)


    def _estimate(self, slot: int, t: float) -> Estimate:
        x, P = self._x[slot], self._P[slot]
        cov = P[:6, :6]
        if self._landed[slot]:
            extra = self._landing_spread(slot, t)
            if extra is not None:
                cov = cov.copy()
                cov[0:3, 0:3] += extra
        elif self.layout.wind is not None and P[0, 0] + P[1, 1] + P[2, 2] > 1e6:  # a long coast (> 1 km)
            cov = cov.copy()
            cov[0:3, 0:3] += curvature_drop_cov(x[0:3], cov[0:3, 0:3])
        est = Estimate(t_gps_s=t, source_id=self.source_id, seq=self._seq, kind="sonde", pos_ecef_m=x[0:3],
                       vel_ecef_m_s=x[3:6], cov=0.5 * (cov + cov.T), nis=float(self._nis[slot]), mode=self.label)
        self._seq += 1
        self.counters.estimates += 1
        if self._transport is not None:
            self._transport.publish(self._keys[slot], est)
        return est

    # -- state access ------------------------------------------------------

    @property
    def sondes(self) -> list[str]:
        return list(self._ids)

    def state(self, sonde: str):
        """(t, x, P) of a sonde (copies), or None before its initialisation."""
        slot = self._slots.get(sonde)
        if slot is None or not math.isfinite(self._t[slot]):
            return None
        return float(self._t[slot]), self._x[slot].copy(), self._P[slot].copy()

    # -- internals ---------------------------------------------------------

    def _slot(self, sonde: str) -> int:
        slot = self._slots.get(sonde)
        if slot is None:
            n = self.layout.n
            slot = self._slots[sonde] = len(self._ids)
            self._ids.append(sonde)
            self._keys.append(key_for(self.run_id, Estimate, kind="sonde", id=sonde))
            self._x = np.concatenate([self._x, np.zeros((1, n))])
            self._P = np.concatenate([self._P, np.zeros((1, n, n))])
            self._t = np.append(self._t, np.nan)
            self._t_init = np.append(self._t_init, np.nan)
            self._t_meas = np.append(self._t_meas, np.nan)
            self._landed = np.append(self._landed, False)
            self._land_t = np.append(self._land_t, np.nan)
            self._land_a = np.concatenate([self._land_a, np.zeros((1, 3))])
            self._land_b = np.concatenate([self._land_b, np.zeros((1, 3))])
            self._land_var = np.append(self._land_var, 0.0)
            self._land_v = np.append(self._land_v, 0.0)
            self._nis = np.append(self._nis, np.nan)
            self._rejects = np.concatenate([self._rejects, np.zeros((1, 2), dtype=np.int64)])
            self._window.add_slot()
            self._bias_map.append({})
            self._bias_owner.append([None] * self.layout.nb)
            self._bias_last = np.concatenate([self._bias_last, np.full((1, self.layout.nb), -np.inf)])
            self._bias_prev.append(None)
        return slot

    def _process(self, t: float, items: dict) -> None:
        L, c = self.layout, self.counters
        upd = []  # (sonde, slot, relay msg or None, radar msg or None) to update at t
        idle = []  # initialised sondes with nothing usable at t: predicted only
        for sonde, (rel, rad) in items.items():
            slot = self._slot(sonde)
            c.epochs += 1
            if math.isfinite(self._t[slot]):
                if not self._t[slot] < t:  # the filter is already at t (step called before)
                    c.stale += (rel is not None) + (rad is not None)
                    continue
            else:  # initialisation: the radar fix first, else a relay least-squares fix
                if L.uses_radar and rad is not None and self._init_from_radar(slot, rad):
                    rad = None
                elif L.uses_relay and rel is not None and rel.n >= 4 and self._init_from_relay(slot, rel):
                    rel = None
                else:
                    c.init_waiting += 1
                    continue
                self._t[slot] = t
                self._t_init[slot] = t
                self._t_meas[slot] = t
                self._nis[slot] = np.nan
            if rel is not None and rel.n == 0:
                c.relay_empty += 1
                rel = None
            if rel is None and rad is None:
                idle.append(slot)
            else:
                upd.append((sonde, slot, rel, rad))
        if idle:
            self._predict(np.array(idle), t)
            self._nis[idle] = np.nan
        if not upd:
            return
        if self._mon is not None:
            self._integrity(upd, t)
        dts = [t - float(self._t[u[1]]) for u in upd]
        for dt in sorted(set(dts)):
            group = upd if len(dts) == 1 else [u for u, d in zip(upd, dts) if d == dt]
            self._epoch_update(group, dt, t)
