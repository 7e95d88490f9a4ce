"""The ground-station node: the batch ground-station components on any bus, stepped by epoch.

``GroundStationNode(transport, run_id, config)`` runs the SAME objects as batch mode -- the
beacon locator (ground_station.beacon.BeaconLocator) and the fused sonde tracker
(ground_station.sonde.SondeTracker, parameters from the sonde experiment) -- and
publishes their Estimates on ``<run>/gs/estimate/{beacon,sonde}/<id>``.

The components subscribe and publish through a small deferred bus (`_DeferredBus`): what
the real transport delivers (on its own threads, for Zenoh) is queued, and handed to the
components in the caller's thread by `pump` / `advance`, so the components never run
concurrently with themselves. ``advance(t)`` processes every epoch seen up to t (in time
order): the live process calls it with its paced clock minus a hold time (the longest an
epoch waits for its messages) and processes an epoch sooner once every source that is
publishing has delivered it (each source's messages arrive in order); replay calls it with the
recorded messages' times.
Messages for an epoch already processed are counted (``late``) and passed on: the
components re-process them within their lag window (``lag_window_s``) or count them too late.

Time guard: every input is first checked against the node's own clock (the ``now_s`` given
to `advance`: live, the paced clock; replay, the recorded clock; batch, the epoch), never
against the messages' times: one more than ``max_ahead_s`` ahead of it (``future``) or older
than the hold plus the lag window behind it (``stale``) is refused and counted
(``counters["rejected_future"]`` / ``["rejected_stale"]``, and per link), before it can add an
epoch, move ``t_done``, reach a filter or count as a link's sign of life
(`sitl.bus.timeguard`). The clock only moves forward.

Restarts: a restarted publisher sends with a new ``incarnation`` (bus schema 3); its messages
are a new stream for the link statistics and the components' duplicate checks. The node's
own output goes out with its ``incarnation``.

Link statistics: every input message is counted per link ((run, source id)) by a
`sitl.bus.LinkMonitor` -- received, missing from sequence numbers, duplicates, out of order,
gaps, latency (arrival minus ``t_gps_s``; the arrival clock is ``now_s`` given to `advance`,
else its ``t_until``) -- and a link silent for more than ``stale_after_s`` is flagged stale.
`LinkStats` go out on ``<run>/gs/link/<source id>`` every ``link_stats_every_s`` and at once
when a link turns stale or comes back (those also in ``link_changes`` for the caller).
"""
from __future__ import annotations

import dataclasses
import math
import threading
from collections import Counter, deque
from dataclasses import dataclass

from sitl.bus import Estimate, LinkMonitor, UavGroupEpoch, key_matches, parse_key
from sitl.bus.timeguard import TimeGuard
from sitl.scenario import BeaconSection, GroundStationSection, RunSection, SondeSection


@dataclass(frozen=True)
class GsConfig:
    """The node's settings; the defaults are the scenario's (sitl.scenario's declarations), once."""

    beacon_id: str = BeaconSection.id
    beacon_init_epochs: int = GroundStationSection.beacon_init_epochs
    sonde: bool = SondeSection.enabled
    radar_id: str | None = SondeSection.radar_id
    sonde_dt_s: float = 1.0 / RunSection.rate_hz
    gcpp_offset_m: float = SondeSection.gcpp_offset_m
    gcpp_bearing_deg: float = SondeSection.gcpp_bearing_deg
    sonde_integrity: bool = GroundStationSection.integrity
    stale_after_s: float = GroundStationSection.stale_after_s  # a link silent this long (simulation time) is flagged stale
    link_stats_every_s: float = GroundStationSection.link_stats_every_s  # LinkStats of every link this often
    lag_window_s: float = GroundStationSection.lag_window_s  # late measurements this old are re-processed (0: dropped)
    max_ahead_s: float = GroundStationSection.max_ahead_s  # an input further ahead of the node's clock is refused
    hold_s: float = GroundStationSection.hold_wall_s * RunSection.speed  # the longest an epoch waits (simulated s)
    # the beacon's declared search volume in height (LocatorConfig.search_height_m), m: a ground or
    # low-altitude emitter (a vehicle, a boat, a low-flying aircraft), between the lowest land
    # (-430 m, the Dead Sea, less the geoid) and 2 km. It decides the blind start's side of the
    # UAVs' plane: on the demo's geometry the mirror was 3.1-11.5 km up in blind starts every 20 s
    # over an hour (seed 1; 5 km let 33 of 180 through, carried as a second hypothesis), the
    # beacon's side 239-355 m (tests/ground_station/test_beacon_blind_start.py)
    beacon_search_height_m: tuple = (-500.0, 2000.0)
    # the sonde tracker's parameters (SondeTrackerParams; required with ``sonde``): the composition
    # root derives them from the world's models (sitl.app.components.sonde_tracker_params); the
    # node applies its own lag window to them
    sonde_tracker: object | None = None

    def __post_init__(self):
        band = self.beacon_search_height_m
        if isinstance(band, list):  # from a journal's JSON header
            object.__setattr__(self, "beacon_search_height_m", tuple(float(v) for v in band))

    @classmethod
    def from_scenario(cls, scn, sonde_tracker=None) -> GsConfig:
        """The scenario's settings; ``sonde_tracker``: the tracker's parameters (with a sonde)."""
        return cls(sonde_tracker=sonde_tracker, beacon_id=scn.beacon.id, beacon_init_epochs=scn.ground_station.beacon_init_epochs,
                   sonde=scn.sonde.enabled, radar_id=scn.sonde.radar_id, sonde_dt_s=1.0 / scn.run.rate_hz,
                   gcpp_offset_m=scn.sonde.gcpp_offset_m, gcpp_bearing_deg=scn.sonde.gcpp_bearing_deg,
                   sonde_integrity=scn.ground_station.integrity,
                   stale_after_s=scn.ground_station.stale_after_s,
                   link_stats_every_s=scn.ground_station.link_stats_every_s,
                   lag_window_s=scn.ground_station.lag_window_s, max_ahead_s=scn.ground_station.max_ahead_s,
                   hold_s=scn.ground_station.hold_wall_s * scn.run.speed)

    @property
    def max_behind_s(self) -> float:
        """The oldest an input may be, behind the node's clock: the hold, the lag window and one epoch."""
        return self.hold_s + self.lag_window_s + self.sonde_dt_s


class _Sub:
    def __init__(self, bus, expr, cb):
        self.bus, self.key_expr, self.callback, self.closed = bus, expr, cb, False

    def close(self):
        self.closed = True


#: the vehicle groups' columnar epochs (sitl.bus.UavGroupEpoch), of any run
GROUP_EPOCH_EXPR = "*/uavs/*/epoch"


class _DeferredBus:
    """What the components see as their transport: subscribe / publish; deliveries queued.

    A vehicle group's columnar epoch (UavGroupEpoch) is taken apart on arrival into the per-UAV
    messages it holds (UavGroupEpoch.per_uav: the messages, keys and order the group would have
    published one by one), of which only those a component subscribes to are made and queued:
    the components, the time guard and the link statistics see per-UAV messages either way."""

    def __init__(self, transport, on_input, incarnation: int = 0):
        self.transport = transport
        self.incarnation = int(incarnation)
        self._subs: list[_Sub] = []
        self._real = []
        self._queue: deque = deque()
        self._on_input = on_input
        self.published: list = []  # (key, Estimate) published since the last take_published()
        self._wanted: dict[str, bool] = {}  # per-UAV key -> some subscription takes it (keys recur)
        self.group_epochs = 0  # columnar epochs taken apart
        self.muted = False  # True while resuming from journals: nothing published (`resume`)
        self._exprs: list[str] = []  # the key expressions subscribed on the transport, in order
        if transport is not None:
            self._real.append(transport.subscribe(GROUP_EPOCH_EXPR, self._enqueue))
            self._exprs.append(GROUP_EPOCH_EXPR)

    def subscribe(self, key_expr, callback):
        sub = _Sub(self, key_expr, callback)
        self._subs.append(sub)
        self._wanted.clear()
        if self.transport is not None:
            self._real.append(self.transport.subscribe(key_expr, self._enqueue))
            self._exprs.append(key_expr)
        return sub

    def _enqueue(self, key, msg):  # any thread
        if type(msg) is UavGroupEpoch:
            self._queue.extend(self._per_uav(key, msg))
        else:
            self._queue.append((key, msg))

    def feed(self, key, msg):
        """Deliver a message directly (no transport: replay and tests)."""
        self._enqueue(key, msg)

    def feed_as_transport(self, key, msg):
        """Deliver a message as the transport would: once per subscribed expression it matches."""
        for expr in self._exprs:
            if key_matches(expr, key):
                self._enqueue(key, msg)

    def _per_uav(self, key, msg) -> list:
        parsed = parse_key(key)
        if parsed is None or parsed[1] is not UavGroupEpoch:
            return []  # a group epoch on a key not of its kind: nothing for a component
        self.group_epochs += 1
        return msg.per_uav(parsed[0], want=self._takes)

    def _takes(self, key) -> bool:
        hit = self._wanted.get(key)
        if hit is None:
            hit = self._wanted[key] = any(not s.closed and key_matches(s.key_expr, key) for s in self._subs)
        return hit

    def pump(self) -> int:
        n = 0
        q = self._queue
        while q:
            key, msg = q.popleft()
            if not self._on_input(key, msg):
                continue  # refused by the time guard
            for s in self._subs:
                if not s.closed and key_matches(s.key_expr, key):
                    s.callback(key, msg)
            n += 1
        return n

    def publish(self, key, msg):
        if self.muted:
            return
        if msg.incarnation != self.incarnation:
            msg = dataclasses.replace(msg, incarnation=self.incarnation)
        self.published.append((key, msg))
        if self.transport is not None:
            self.transport.publish(key, msg)

    def close(self):
        for s in self._real:
            s.close()
        self._real.clear()


def beacon_locator_config(c: GsConfig):
    """The live ground station's beacon locator: "consider" (the UAVs' navigation errors as
    Schmidt states, per UAV slot, after a 50 s "inflate" acquisition; ground_station/
    beacon/), the locator `skyfuse experiment beacon` scores, with a blind
    (multilateration) start of beacon_init_epochs epochs.  Checked against "inflate" on this
    scenario's geometry, old and new, and on the seed's geodetic blind start (numbers in
    sitl/app/experiments/long_run.py's docstring)."""
    from ground_station.beacon import LocatorConfig

    return LocatorConfig(observer_uncertainty="consider", init_epochs=c.beacon_init_epochs,
                         lag_window_s=c.lag_window_s, search_height_m=c.beacon_search_height_m)


class GroundStationNode:
    """Beacon locator + sonde tracker on a bus (module docstring).

    transport: a sitl.bus Transport (None: feed messages with ``feed``); run_id: the run's
    key prefix; config: GsConfig; incarnation: this node's (its process's) incarnation, stamped
    on what it publishes. ``estimates``: the latest Estimate per (kind, id)."""

    def __init__(self, transport, run_id: str, config: GsConfig | None = None, incarnation: int = 0):
        from ground_station.beacon import BeaconLocator
        from ground_station.sonde import SondeTracker

        self.config = c = config or GsConfig()
        self.run_id = run_id
        self._run_prefix = run_id + "/"
        self.counters = Counter()
        self._epochs: set[float] = set()
        self._src_times: dict[str, deque] = {}  # the latest distinct input times per source id
        self._t_first: float | None = None  # earliest input time seen
        self.t_done = -math.inf
        self._lock = threading.Lock()
        self.guard = TimeGuard(ahead_s=c.max_ahead_s, behind_s=c.max_behind_s)
        self.bus = _DeferredBus(transport, self._on_input, incarnation)
        self.locator = BeaconLocator(self.bus, run_ids=[run_id], beacon_id=c.beacon_id,
                                     config=beacon_locator_config(c),
                                     source_id="gs")
        self.tracker = None
        if c.sonde:
            if c.sonde_tracker is None:
                raise ValueError("GsConfig.sonde_tracker: the sonde tracker's parameters are required with sonde on "
                                 "(sitl.app.components.gs_config builds them from the scenario)")
            params = dataclasses.replace(c.sonde_tracker, lag_window_s=c.lag_window_s)
            self.tracker = SondeTracker(run_id, params, radar_id=c.radar_id, source_id="gs")
            self.tracker.attach(self.bus)
        self.estimates: dict[tuple[str, str], Estimate] = {}
        self.events: list = []  # (key, IntegrityEvent) published by the components; the caller takes them
        self.links = LinkMonitor(stale_after_s=c.stale_after_s)
        self.link_changes: list = []  # (key, LinkStats) of links that turned stale or came back; the caller takes them
        self.link_messages: list = []  # (key, LinkStats) published; the caller takes them
        self._arrival_s = -math.inf  # the arrival clock of what the next pump takes in
        self.last_error: str | None = None  # the last component step that failed, one line
        self._links_due = -math.inf

    def _on_input(self, key, msg) -> bool:
        """Count one input; False if the time guard refuses it (it then goes nowhere)."""
        t = float(msg.t_gps_s)
        self.counters["inputs"] += 1
        if not key.startswith(self._run_prefix):  # another run on a shared router: not ours to step
            self.counters["other_run"] += 1
            return False
        reason = self.guard.verdict(t, self._arrival_s)
        if reason is not None:
            self.counters[f"rejected_{reason}"] += 1
            self.links.refused(key, msg, reason)
            return False
        self.links.observe(key, msg, self._arrival_s if math.isfinite(self._arrival_s) else t)
        if self._t_first is None or t < self._t_first:
            self._t_first = t
        times = self._src_times.get(msg.source_id)
        if times is None:
            times = self._src_times[msg.source_id] = deque(maxlen=8)
        if not times or t > times[-1]:
            times.append(t)
        if t <= self.t_done:
            self.counters["late"] += 1
        else:
            self._epochs.add(round(t, 6))
        return True

    def _complete(self, tau: float, window_s: float) -> bool:
        """Every source heard within window_s before tau has delivered tau or later (each
        source's messages arrive in order, so its epoch-tau message is in). False when no source
        was heard in that window (the run's start, or the first epoch after every source fell
        silent -- a restart): which sources will deliver tau is unknown then, so the epoch waits
        for the hold, rather than being processed with whichever message happened to come first
        (which would make the result depend on arrival jitter: live and replay would differ)."""
        if self._t_first is None or tau < self._t_first + window_s:
            return False  # the sources are not all known yet
        lo, hi = tau - window_s - 1e-9, tau - 1e-9
        heard = False
        for times in self._src_times.values():
            if any(lo <= x < hi for x in times):
                heard = True
                if times[-1] < hi:
                    return False
        return heard

    def feed(self, key: str, msg) -> None:
        self.bus.feed(key, msg)

    def pending_epochs(self) -> int:
        return len(self._epochs)

    def advance(self, t_until_gps_s: float, *, early_window_s: float | None = None,
                now_s: float | None = None) -> list:
        """Take in what has arrived and process every epoch <= t_until; returns the
        (key, Estimate) published meanwhile (other messages they published, integrity events,
        are appended to ``events``).

        early_window_s (live): also process, in time order, the later epochs that are complete
        already: every input source heard within early_window_s before the epoch has delivered
        it (or a later one). t_until is then only the longest an epoch waits for a silent source.

        now_s: the simulation time now (live: the paced clock), the arrival time of what is
        taken in and the clock of the links' silence; default t_until."""
        now = t_until_gps_s if now_s is None else now_s
        with self._lock:
            self._arrival_s = self.guard.tick(now)
            self.bus.pump()
            for tau in sorted(self._epochs):
                if tau > t_until_gps_s and (early_window_s is None or not self._complete(tau, early_window_s)):
                    break  # epochs are processed in time order only
                self._epochs.discard(tau)
                self._step(tau)
                if tau > t_until_gps_s:
                    self.counters["epochs_early"] += 1
            published, self.bus.published = self.bus.published, []
            out = []
            for key, msg in published:
                if isinstance(msg, Estimate):
                    parts = key.rsplit("/", 2)
                    self.estimates[(parts[-2], parts[-1])] = msg
                    out.append((key, msg))
                else:  # integrity events of the trackers' monitors (opt-in)
                    self.events.append((key, msg))
            self.counters["estimates"] += len(out)
            if math.isfinite(now):
                self._link_stats(now)
            return out

    def _link_stats(self, now: float) -> None:
        """LinkStats of the links that turned stale or came back, and of every link when due."""
        changed = self.links.check(now)
        due = now >= self._links_due
        if due:
            self._links_due = now + self.config.link_stats_every_s
        if not (due or changed):
            return
        ids = {id(lk) for lk in changed}
        for lk in (self.links.states() if due else changed):
            key, m = self.links.message(lk, now, source_id="gs")
            if self.bus.muted:
                continue
            if self.bus.transport is not None:
                self.bus.transport.publish(key, m)
            self.link_messages.append((key, m))
            self.counters["link_stats"] += 1
            if id(lk) in ids:
                self.link_changes.append((key, m))
                self.counters["links_stale" if lk.stale else "links_back"] += 1

    def _step(self, tau: float) -> None:
        # each component alone: one that fails on an epoch (counted, its last error kept) does
        # not take the other's estimate of that epoch with it
        for name, comp in (("beacon_locator", self.locator), ("sonde_tracker", self.tracker)):
            if comp is None:
                continue
            try:
                comp.step(tau)  # publishes through self.bus
            except Exception as e:
                self.counters[f"step_errors.{name}"] += 1
                self.last_error = f"{name} at t = {tau:.3f}: {type(e).__name__}: {' '.join(str(e).split())}"
        self.t_done = max(self.t_done, tau)
        self.counters["epochs"] += 1

    def flush(self) -> list:
        """Process every epoch still pending (end of a replay)."""
        return self.advance(math.inf)

    def stats(self) -> dict:
        d = {"node": dict(self.counters), "beacon_locator": dict(self.locator.counters),
             "beacon_rejected": dict(self.locator.rejected), "links": self.links.as_dict()}
        if self.tracker is not None:
            d["sonde_tracker"] = self.tracker.counters.as_dict()
        return d

    def close(self) -> None:
        self.locator.close()
        if self.tracker is not None:
            self.tracker.close()
        self.bus.close()
