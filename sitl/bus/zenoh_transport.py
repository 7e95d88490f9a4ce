"""The live bus transport: the `Transport` interface over an eclipse-zenoh session.

Same interface and semantics as `InMemoryTransport` (see `sitl.bus.transport`): `publish`
encodes with the bus codec, every delivery decodes and validates the payload first, a
malformed payload is counted under its reason in `stats` (and logged, rate-limited) and
never reaches a callback, a callback that raises is counted and isolated, callbacks are
called as ``callback(key, msg)``. Simulation time travels in the payload; Zenoh timestamps
are not used.

    bus = ZenohTransport(connect=router.endpoints)          # mode "client"
    bus.subscribe("run1/uav/*/nav", on_nav)
    bus.publish(key_for("run1", nav, uav=3), nav)
    bus.drain()                                             # queue mode (the default)
    bus.close()

Delivery modes (``delivery=``)
------------------------------
* ``"queue"`` (default, like `InMemoryTransport`): received samples wait in Zenoh's own
  FIFO channel (no Python code runs on Zenoh's threads); `drain` takes everything received
  so far and decodes and delivers it **on the caller's thread**. This is what a
  step-function node wants: ``bus.drain(t); node.step(t)`` as in batch mode, with no
  locking in the node. ``drain(until_t_gps_s)`` takes the time argument for parity with
  `InMemoryTransport` and ignores it: on a live bus a message is due when it has arrived.
  Order: arrival order per subscribed key expression (so per publisher and key); the
  expressions are drained one after the other. The channel holds ``queue_capacity``
  samples per expression; when it is full Zenoh waits (back-pressure, nothing is dropped),
  and a publisher blocked more than 5 s (Zenoh's ``wait_before_close``) loses its link: call
  `drain` at least every few hundred milliseconds.
* ``"callback"``: callbacks run as soon as a sample arrives, on a Python thread that Zenoh
  starts per subscription. Deliveries are serialised by a lock (two callbacks never run at
  once) but run concurrently with the rest of the program: the consumer guards its state.

`subscribe_raw` (recorders) gets the payload bytes before decoding, valid or not, in the
same mode.

Reliability
-----------
Publications are RELIABLE with congestion control BLOCK (a full transmit queue waits rather
than silently dropping: a slow subscriber slows its publisher, nothing is lost) and not express (express batches
nothing and was measured ~10x slower in throughput); both are settable. Reliability is hop
to hop over TCP: a sample published while a link is down (partition, router restart) is
lost, and the sequence numbers in the payload show the gap (`SequenceTracker`).

Leases, router restarts, closing
--------------------------------
Each side of a link declares its lease; a side is declared gone when it has been silent for
the lease *it* declared. So a client notices a silent (frozen, partitioned) router after the
router's lease: give ``lease_ms`` to the `Router` as well as to the clients (tested: 1 s
lease, frozen router noticed after ~1.0 s). Clients reconnect by themselves to a router
restarted on the same endpoint and re-declare their subscriptions (tested, ~0.6 s).
Measured caveat: closing a session right after publishing into a receiver that is behind
can lose what is still in flight (socket buffers, several MB; the session is gone before
the router has read it). A publisher whose last messages matter stays open until the
receivers have them (their sequence numbers tell).

Overlapping subscriptions
-------------------------
One Zenoh subscriber is declared per distinct key expression. Zenoh hands a sample to every
subscriber it matches, so when two expressions of one transport overlap, the sample is
taken (decoded, counted, delivered to every matching subscription) only through the
first-declared expression that matches its key: ``stats.total`` counts each payload once,
as `InMemoryTransport` does. While a subscription whose expression overlaps another one is
being closed, a sample in flight in that instant may be missed by the other one.

Fault filters at the publisher
----------------------------------------
``faults=[f, ...]``: `sitl.bus.transport.FaultFilter` callables ``(key, payload, t_s) ->
[(deliver_at_s, payload), ...]`` (e.g. a `sitl.netfault.KeyFaults`), applied at publish time
in order as `InMemoryTransport` applies them: [] drops the message, two items duplicate it,
changed bytes corrupt it, a later time delays it. The filters see simulation time relative to
``fault_t0_s`` (the run's start: a spec's ``partition=100-130`` means 100-130 s into the run),
the publication's ``msg.t_gps_s`` (or the latest one seen, for `publish_raw` without a time).
A delayed copy waits in a small scheduler thread (one per transport, started on the first
delay) for ``(deliver_at - t) / speed`` wall seconds and is then published; `close` publishes
what is still pending at once (``fault_stats["flushed_at_close"]``) so nothing handed out by a
filter is silently lost. ``fault_stats``: offered (publications through the filters), sent
(copies put on the wire, at once or later), dropped (publications with no copy), duplicated
(copies beyond the first), delayed (copies scheduled for later), flushed_at_close, pending.
``stats.published`` stays what the publishers handed in. `with_faults(fn)` runs ``fn()``
(e.g. ``lambda: kf.set(expr, spec, t)``) under the lock the filters run under, so a control
thread may change a filter while the publisher runs; `fault_now_s` is the filters' current
time (the latest publication's, relative to ``fault_t0_s``).

`subscribe_async(key_expr, callback)`: ``callback(key, msg)`` on Zenoh's thread as soon as a
message arrives, whatever the delivery mode, outside the drain path (control keys that a
worker which never drains must still hear: ``<run>/ctl/fault``). Bad payloads are counted in
``async_rejected``; the subscription is undeclared by `close`.

Exit
----
A process that exits with a Zenoh callback subscriber still declared hangs (Zenoh's callback
thread is never joined). `close` undeclares everything; transports still open when the
interpreter shuts down are closed by a hook that runs before Python joins its threads.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import math
import threading
import time
import weakref
from collections import Counter
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import zenoh

from .zconfig import ZenohConfigError, make_config, zenoh_error_text
from .codec import BusDecodeError, decode
from .transport import (
    Callback,
    FaultFilter,
    KeyExprError,
    Subscription,
    Transport,
    key_matches,
    validate_key,
    validate_key_expr,
)

log = logging.getLogger("sitl.bus")

DELIVERY_MODES = ("queue", "callback")
MAX_PUBLISHERS = 4096  # declared publishers kept (one per key); further keys use session.put
DEFAULT_QUEUE_CAPACITY = 1 << 16

RawCallback = Callable[[str, bytes], None]

_OPEN: weakref.WeakSet = weakref.WeakSet()  # transports to close at interpreter exit


def _close_all_at_exit() -> None:
    for t in list(_OPEN):
        try:
            t.close()
        except Exception as e:
            log.debug("bus: closing %r at exit: %s", t, e)


# threading._register_atexit runs before the interpreter joins non-daemon threads (which is
# where an open Zenoh callback subscriber hangs the exit); atexit would run too late.
_register = getattr(threading, "_register_atexit", None)
if _register is not None:
    _register(_close_all_at_exit)
else:  # pragma: no cover
    import atexit

    atexit.register(_close_all_at_exit)


class ZenohTransportError(RuntimeError):
    """The session could not be opened (router unreachable, bad config): one line."""


class _ZSub:
    """One declared Zenoh subscriber, shared by every subscription with the same expression."""

    __slots__ = ("expr", "order", "users", "zsub")

    def __init__(self, expr: str, order: int):
        self.expr = expr
        self.order = order
        self.users = 0
        self.zsub: Any = None


class ZenohTransport(Transport):
    """The bus over a Zenoh session (see the module text).

    ``connect``: router endpoints (``Router.endpoints``); ``mode``: "client" (default: all
    traffic through the router), "peer" or "router"; ``listen``: endpoints to listen on
    (peer/router); ``lease_ms``: link lease (Zenoh default 10 s when None); ``delivery``:
    "queue" or "callback"; ``queue_capacity``: samples held per subscribed expression in
    queue mode; ``congestion_control``: "block" (default) or "drop"; ``express``: send
    without batching; ``multicast_scouting``: off by default; ``extra``: more Zenoh config
    keys ``{"path/of/key": value}``; ``faults``, ``fault_t0_s``, ``speed``: publisher fault
    filters (module text)."""

    def __init__(self, connect: Iterable[str] | str | None = None, *, mode: str = "client",
                 listen: Iterable[str] | str | None = None, lease_ms: int | None = None,
                 delivery: str = "queue", queue_capacity: int = DEFAULT_QUEUE_CAPACITY,
                 congestion_control: str = "block", express: bool = False,
                 multicast_scouting: bool = False, extra: Mapping[str, Any] | None = None,
                 faults: Iterable[FaultFilter] = (), fault_t0_s: float = 0.0, speed: float = 1.0):
        super().__init__()
        if not (isinstance(speed, (int, float)) and math.isfinite(speed) and speed > 0):
            raise ZenohConfigError(f"speed: expected a finite number > 0, got {speed!r}")
        self.faults: list[FaultFilter] = list(faults)
        self.fault_t0_s = float(fault_t0_s)
        self.speed = float(speed)
        self.fault_stats: Counter = Counter()
        self.async_rejected: Counter = Counter()
        self._fault_lock = threading.RLock()
        self._fault_t: float | None = None  # latest publication time seen (relative to fault_t0_s)
        self._sched: list = []  # heap of (due perf_counter, seq, key, payload)
        self._sched_seq = itertools.count()
        self._sched_cv = threading.Condition(threading.Lock())
        self._sched_thread: threading.Thread | None = None
        self._sched_stop = False
        self._async: list[Any] = []  # callback-mode zenoh subscribers of subscribe_async
        if delivery not in DELIVERY_MODES:
            raise ZenohConfigError(f"delivery: {delivery!r} is not one of "
                                   f"{', '.join(DELIVERY_MODES)}")
        cc = {"block": zenoh.CongestionControl.BLOCK, "drop": zenoh.CongestionControl.DROP}
        if congestion_control not in cc:
            raise ZenohConfigError(f"congestion_control: {congestion_control!r} is not "
                                   "'block' or 'drop'")
        if (isinstance(queue_capacity, bool) or not isinstance(queue_capacity, int)
                or queue_capacity < 1):
            raise ZenohConfigError(f"queue_capacity: expected an int >= 1, got {queue_capacity!r}")
        cfg = make_config(mode, listen=listen, connect=connect,
                          multicast_scouting=multicast_scouting, lease_ms=lease_ms, extra=extra)
        self.delivery = delivery
        self.queue_capacity = queue_capacity
        self.express = bool(express)
        self._cc = cc[congestion_control]
        # _lock guards subscriptions, delivery and receive stats (an RLock: a callback may
        # subscribe, unsubscribe or publish); _pub_lock guards publishers and publish stats
        self._lock = threading.RLock()
        self._pub_lock = threading.Lock()
        self._zsubs: dict[str, _ZSub] = {}
        self._zorder = 0
        self._owner: dict[str, str | None] = {}  # key -> expression that takes it
        self._publishers: dict[str, Any] = {}
        self._raw: dict[int, Subscription] = {}  # raw (undecoded) subscriptions by id
        self._draining = False
        try:
            self._session = zenoh.open(cfg)
        except Exception as e:
            raise ZenohTransportError(f"zenoh session ({mode}, connect={connect!r}) did not "
                                      f"open: {zenoh_error_text(e)}") from None
        self.zid = str(self._session.zid())
        _OPEN.add(self)

    # ------------------------------------------------------------------ publishing
    def _publisher(self, key: str) -> Any:
        with self._pub_lock:
            pub = self._publishers.get(key)
            if pub is None and len(self._publishers) < MAX_PUBLISHERS:
                pub = self._publishers[key] = self._session.declare_publisher(
                    key, congestion_control=self._cc, express=self.express,
                    reliability=zenoh.Reliability.RELIABLE)
            return pub

    def _put(self, key: str, payload: bytes) -> None:
        pub = self._publishers.get(key)
        if pub is None:
            pub = self._publisher(key)
        if pub is not None:
            pub.put(payload)
        else:
            self._session.put(key, payload, congestion_control=self._cc, express=self.express)

    def _publish_bytes(self, key: str, payload: bytes, t_gps_s: float | None) -> None:
        self._check_open()
        validate_key(key)
        if self.faults:
            self._publish_faulty(key, payload, t_gps_s)
        else:
            self._put(key, payload)
        with self._pub_lock:
            self.stats.published += 1
            self.stats.published_bytes += len(payload)

    # ------------------------------------------------------------------ fault filters
    @property
    def fault_now_s(self) -> float:
        """The filters' clock: the latest publication's time relative to ``fault_t0_s`` (0
        before the first)."""
        return 0.0 if self._fault_t is None else self._fault_t

    def with_faults(self, fn: Callable[[], Any]) -> Any:
        """Run ``fn()`` under the filters' lock (change a filter while publishers run)."""
        with self._fault_lock:
            return fn()

    def _publish_faulty(self, key: str, payload: bytes, t_gps_s: float | None) -> None:
        with self._fault_lock:
            if t_gps_s is not None and math.isfinite(t_gps_s):
                t = float(t_gps_s) - self.fault_t0_s
                self._fault_t = t if self._fault_t is None else max(self._fault_t, t)
            else:
                t = self.fault_now_s
            items = [(t, payload)]
            for fault in self.faults:
                out = []
                for t_item, p_item in items:
                    for at, p in fault(key, p_item, t_item):
                        at = float(at)
                        if not math.isfinite(at) or not isinstance(p, (bytes, bytearray)):
                            raise TypeError(f"fault filter {fault!r} produced ({at!r}, "
                                            f"{type(p).__name__}): expected (finite time, bytes)")
                        out.append((at, bytes(p)))
                items = out
            self.fault_stats["offered"] += 1
            if not items:
                self.fault_stats["dropped"] += 1
            self.fault_stats["duplicated"] += max(0, len(items) - 1)
        now = time.perf_counter()
        for at, p in items:
            if at <= t:
                self._put(key, p)
                with self._fault_lock:
                    self.fault_stats["sent"] += 1
            else:
                self._schedule(now + (at - t) / self.speed, key, p)

    def _schedule(self, due: float, key: str, payload: bytes) -> None:
        with self._sched_cv:
            heapq.heappush(self._sched, (due, next(self._sched_seq), key, payload))
            with self._fault_lock:
                self.fault_stats["delayed"] += 1
                self.fault_stats["pending"] = len(self._sched)
            if self._sched_thread is None:
                self._sched_thread = threading.Thread(target=self._run_scheduler,
                                                      name="bus-fault-delay", daemon=True)
                self._sched_thread.start()
            self._sched_cv.notify()

    def _run_scheduler(self) -> None:
        while True:
            with self._sched_cv:
                while not self._sched_stop:
                    if self._sched:
                        wait = self._sched[0][0] - time.perf_counter()
                        if wait <= 0:
                            break
                        self._sched_cv.wait(min(wait, 0.5))
                    else:
                        self._sched_cv.wait(0.5)
                if self._sched_stop:
                    return
                _, _, key, payload = heapq.heappop(self._sched)
                with self._fault_lock:
                    self.fault_stats["pending"] = len(self._sched)
            try:
                self._put(key, payload)
                with self._fault_lock:
                    self.fault_stats["sent"] += 1
            except Exception as e:  # the session closed under us: counted, never raised
                with self._fault_lock:
                    self.fault_stats["send_errors"] += 1
                self._ratelog(logging.WARNING, f"delayed:{type(e).__name__}",
                              f"bus: a delayed publication on {key!r} failed: {e}")

    def _stop_scheduler(self) -> None:
        """Stop the delay thread, then put what was pending at once (in due order)."""
        with self._sched_cv:
            self._sched_stop = True
            self._sched_cv.notify_all()
            th = self._sched_thread
        if th is not None:
            th.join(5.0)
        with self._sched_cv:
            pending = [heapq.heappop(self._sched) for _ in range(len(self._sched))]
        for _, _, key, payload in pending:
            try:
                self._put(key, payload)
                with self._fault_lock:
                    self.fault_stats["sent"] += 1
                    self.fault_stats["flushed_at_close"] += 1
            except Exception:
                with self._fault_lock:
                    self.fault_stats["send_errors"] += 1
        with self._fault_lock:
            self.fault_stats["pending"] = 0

    # ------------------------------------------------------------------ async (control) subscriptions
    def subscribe_async(self, key_expr: str, callback: Callback) -> None:
        """``callback(key, msg)`` on Zenoh's thread for every valid message on matching keys,
        in any delivery mode (module text); undeclared by `close`."""
        self._check_open()
        validate_key_expr(key_expr)
        if not callable(callback):
            raise TypeError("callback must be callable")

        def handler(sample: zenoh.Sample) -> None:
            try:
                if self._closed:
                    return
                key = str(sample.key_expr)
                payload = sample.payload.to_bytes() if sample.kind == zenoh.SampleKind.PUT else b""
                try:
                    msg = decode(payload)
                except BusDecodeError as e:
                    self.async_rejected[e.reason] += 1
                    self._ratelog(logging.WARNING, "async-reject:" + e.reason,
                                  f"bus: rejected a payload on {key!r}: {e}")
                    return
                callback(key, msg)
            except Exception as e:  # never raise into Zenoh's thread
                self.async_rejected["callback_error"] += 1
                self._ratelog(logging.ERROR, f"async:{type(e).__name__}",
                              f"bus: async callback on {key_expr!r}: {type(e).__name__}: {e}")

        try:
            zsub = self._session.declare_subscriber(key_expr, handler)
        except Exception as e:
            raise KeyExprError(f"zenoh refused key expression {key_expr!r}: "
                               f"{zenoh_error_text(e)}") from None
        with self._lock:
            self._async.append(zsub)

    # ------------------------------------------------------------------ subscribing
    def subscribe(self, key_expr: str, callback: Callback) -> Subscription:
        with self._lock:
            sub = super().subscribe(key_expr, callback)
            try:
                self._use_expr(key_expr)
            except Exception:
                Transport._unsubscribe(self, sub)
                self.stats.per_subscription.pop(sub.id, None)
                sub.closed = True
                raise
            return sub

    def subscribe_raw(self, key_expr: str, callback: RawCallback) -> Subscription:
        """Call ``callback(key, payload_bytes)`` for every payload on matching keys, valid or
        not, before and without decoding (recorders); in queue mode from `drain`, in
        callback mode from Zenoh's thread. Not counted in ``stats`` (an exception it raises
        is, under ``callback_errors``)."""
        self._check_open()
        validate_key_expr(key_expr)
        if not callable(callback):
            raise TypeError("callback must be callable")
        with self._lock:
            sub = Subscription(self, key_expr, _never_called)
            sub.raw_callback = callback  # type: ignore[attr-defined]
            self._use_expr(key_expr)
            self._raw[sub.id] = sub
            return sub

    def _use_expr(self, expr: str) -> None:
        z = self._zsubs.get(expr)
        if z is None:
            z = _ZSub(expr, self._zorder)
            self._zorder += 1
            if self.delivery == "queue":
                handler: Any = zenoh.handlers.FifoChannel(self.queue_capacity)
            else:
                handler = self._make_handler(expr)
            try:
                z.zsub = self._session.declare_subscriber(expr, handler)
            except Exception as e:
                raise KeyExprError(f"zenoh refused key expression {expr!r}: "
                                   f"{zenoh_error_text(e)}") from None
            self._zsubs[expr] = z
            self._owner.clear()
        z.users += 1

    def _release_expr(self, expr: str) -> None:
        z = self._zsubs.get(expr)
        if z is None:
            return
        z.users -= 1
        if z.users <= 0:
            del self._zsubs[expr]
            self._owner.clear()
            try:
                z.zsub.undeclare()
            except Exception as e:  # session already closed
                log.debug("zenoh undeclare of %r: %s", expr, e)

    def _unsubscribe(self, sub: Subscription) -> None:
        with self._lock:
            if sub.id in self._raw:
                del self._raw[sub.id]
                self._release_expr(sub.key_expr)
                return
            was = sub in self._subs
            super()._unsubscribe(sub)
            if was:
                self._release_expr(sub.key_expr)

    # ------------------------------------------------------------------ receiving
    def _make_handler(self, expr: str) -> Callable[[zenoh.Sample], None]:
        def handler(sample: zenoh.Sample) -> None:
            try:
                with self._lock:
                    if not self._closed:
                        self._on_sample(expr, sample)
            except Exception as e:  # never raise into Zenoh's thread
                self._ratelog(logging.ERROR, f"handler:{type(e).__name__}",
                              f"bus: zenoh handler on {expr!r}: {type(e).__name__}: {e}")
        return handler

    def _owner_of(self, key: str) -> str | None:
        owner = self._owner.get(key, "")
        if owner == "":
            owner = None
            best = None
            for z in self._zsubs.values():
                if (best is None or z.order < best) and key_matches(z.expr, key):
                    owner, best = z.expr, z.order
            if len(self._owner) >= 65536:
                self._owner.clear()
            self._owner[key] = owner
        return owner

    def _on_sample(self, expr: str, sample: zenoh.Sample) -> bool:
        """One sample that reached the Zenoh subscriber of ``expr`` (lock held); True if it
        was taken through this expression (not left to an overlapping one)."""
        key = str(sample.key_expr)
        try:
            owner = self._owner_of(key)
        except KeyExprError as e:
            self.stats.total.rejected["key: invalid"] += 1
            self._ratelog(logging.WARNING, "reject:key", f"bus: rejected key {key!r}: {e}")
            return True
        if owner != expr:  # another declared expression takes this key
            return False
        # a DELETE carries no message: it is rejected as an empty payload
        payload = sample.payload.to_bytes() if sample.kind == zenoh.SampleKind.PUT else b""
        for rsub in list(self._raw.values()):
            if not rsub.closed and key_matches(rsub.key_expr, key):
                try:
                    rsub.raw_callback(key, payload)  # type: ignore[attr-defined]
                except Exception as e:
                    self.stats.total.callback_errors += 1
                    self._ratelog(logging.ERROR, f"rawcb:{rsub.id}:{type(e).__name__}",
                                  f"bus: raw callback of {rsub!r} raised on {key!r}: "
                                  f"{type(e).__name__}: {e}")
        self._deliver(key, payload)
        return True

    def drain(self, until_t_gps_s: float | None = None, max_items: int | None = None) -> int:
        """Queue mode: take what has been received so far from Zenoh's channels (at most
        ``max_items`` samples in all, and at most ``queue_capacity`` per expression, so a
        drain ends even under a flood) and decode and deliver it on this thread.
        ``until_t_gps_s`` is accepted for parity with `InMemoryTransport.drain` and ignored
        (live: a message is due when it arrives). Returns the number of payloads handed to
        the receive path (a sample that two overlapping expressions received counts once).
        In callback mode, or when called from one of this transport's callbacks: 0."""
        if self.delivery != "queue":
            return 0
        count = taken = 0
        limit = float("inf") if max_items is None else max_items
        with self._lock:
            if self._draining or self._closed:
                return 0
            self._draining = True
            try:
                for z in sorted(self._zsubs.values(), key=lambda z: z.order):
                    per_expr = 0
                    while (taken < limit and per_expr < self.queue_capacity
                           and not self._closed and z.expr in self._zsubs):
                        sample = z.zsub.try_recv()
                        if sample is None:
                            break
                        taken += 1
                        per_expr += 1
                        count += self._on_sample(z.expr, sample)
            finally:
                self._draining = False
        return count

    # ------------------------------------------------------------------ helpers
    def wait_for_subscribers(self, key: str, timeout_s: float = 5.0) -> bool:
        """Block (wall clock: launcher and tests only, never in a step function) until some
        subscriber on the bus matches ``key``; return whether one did before the timeout."""
        self._check_open()
        validate_key(key)
        pub = self._publisher(key)
        if pub is None:
            raise RuntimeError("too many publishers declared to watch one more key")
        deadline = time.monotonic() + timeout_s
        while not pub.matching_status.matching:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.005)
        return True

    def routers(self) -> list[str]:
        """Zenoh ids of the routers this session is connected to now."""
        return [str(z) for z in self._session.info.routers_zid()]

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Undeclare every subscriber and publisher, then close the session (idempotent)."""
        self._stop_scheduler()  # before closing: what a fault filter delayed goes out now
        with self._lock:
            if self._closed:
                return
            _OPEN.discard(self)
            for zsub in self._async:
                try:
                    zsub.undeclare()
                except Exception as e:
                    log.debug("zenoh undeclare of an async subscriber: %s", e)
            self._async.clear()
            super().close()  # closes every subscription -> undeclares its zenoh subscriber
            for rsub in list(self._raw.values()):
                rsub.close()
            for z in list(self._zsubs.values()):
                try:
                    z.zsub.undeclare()
                except Exception as e:
                    log.debug("zenoh undeclare of %r: %s", z.expr, e)
            self._zsubs.clear()
        with self._pub_lock:
            for pub in self._publishers.values():
                try:
                    pub.undeclare()
                except Exception as e:
                    log.debug("zenoh publisher undeclare: %s", e)
            self._publishers.clear()
        try:
            self._session.close()
        except Exception as e:  # e.g. "close operation timed out" (zenoh#2675)
            log.warning("bus: zenoh session close: %s", zenoh_error_text(e))

    def __repr__(self) -> str:
        return (f"ZenohTransport({self.zid[:8]} {self.delivery}"
                f"{' closed' if self._closed else ''})")


def _never_called(key: str, msg: object) -> None:  # pragma: no cover
    raise AssertionError("raw subscription got a decoded delivery")


__all__ = ["DELIVERY_MODES", "ZenohConfigError", "ZenohTransport", "ZenohTransportError"]
