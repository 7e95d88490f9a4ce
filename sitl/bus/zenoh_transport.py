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
Zenoh calls its subscriber handlers on its own threads.

* ``"queue"`` (default, like `InMemoryTransport`): the handler only appends
  ``(key, payload)`` to a thread-safe queue; `drain` decodes and delivers everything
  received so far **on the caller's thread**, in arrival order. This is what a step-function
  node wants: ``bus.drain(t); node.step(t)`` as in batch mode, with no locking in the node.
  ``drain(until_t_gps_s)`` takes the time argument for interface parity and ignores it: on
  a live bus a message is due when it has arrived. ``max_queue`` bounds the queue; beyond
  it the oldest entry is dropped and counted under the rejection reason ``"queue:
  overflow"`` (default: unbounded, nothing dropped).
* ``"callback"``: callbacks run on Zenoh's threads as soon as a sample arrives. Deliveries
  are serialised by a lock (two callbacks never run at once), but they run concurrently
  with the rest of the program: the consumer must guard its own state.

Reliability
-----------
Publications are RELIABLE with congestion control BLOCK (a full transmit queue waits rather
than silently dropping, see FAULTS_REFERENCE.md section 3) and not express (express was
measured ~10x slower in throughput); both are settable. Reliability is hop to hop over TCP:
a sample published while a link is down (partition, router restart) is lost, the sequence
numbers in the payload show the gap (`SequenceTracker`).

Overlapping subscriptions
-------------------------
One Zenoh subscriber is declared per distinct key expression. Zenoh hands a sample to every
subscriber it matches, so when two expressions of one transport overlap, the sample is
delivered (decoded, counted) only through the first-declared expression that matches its
key: ``stats.total`` counts each payload once, as `InMemoryTransport` does. While a
subscription whose expression overlaps another is being closed, a sample in flight in that
instant may be missed by the other subscription.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import zenoh

from ._zconfig import ZenohConfigError, make_config
from .transport import (
    Callback,
    KeyExprError,
    Subscription,
    Transport,
    key_matches,
    validate_key,
    validate_key_expr,
)

log = logging.getLogger("sitl.bus")

DELIVERY_MODES = ("queue", "callback")
MAX_PUBLISHERS = 4096  # declared publishers kept (per key); further keys use session.put

RawCallback = Callable[[str, bytes], None]


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
    "queue" or "callback"; ``congestion_control``: "block" (default) or "drop";
    ``express``: send without batching; ``multicast_scouting``: off by default;
    ``extra``: more Zenoh config keys ``{"path/of/key": value}``."""

    def __init__(self, connect: Iterable[str] | str | None = None, *, mode: str = "client",
                 listen: Iterable[str] | str | None = None, lease_ms: int | None = None,
                 delivery: str = "queue", max_queue: int | None = None,
                 congestion_control: str = "block", express: bool = False,
                 multicast_scouting: bool = False, extra: Mapping[str, Any] | None = None):
        super().__init__()
        if delivery not in DELIVERY_MODES:
            raise ZenohConfigError(f"delivery: {delivery!r} is not one of "
                                   f"{', '.join(DELIVERY_MODES)}")
        cc = {"block": zenoh.CongestionControl.BLOCK, "drop": zenoh.CongestionControl.DROP}
        if congestion_control not in cc:
            raise ZenohConfigError(f"congestion_control: {congestion_control!r} is not "
                                   "'block' or 'drop'")
        if max_queue is not None and (isinstance(max_queue, bool) or not isinstance(max_queue, int)
                                      or max_queue < 1):
            raise ZenohConfigError(f"max_queue: expected an int >= 1 or None, got {max_queue!r}")
        cfg = make_config(mode, listen=listen, connect=connect,
                          multicast_scouting=multicast_scouting, lease_ms=lease_ms, extra=extra)
        self.delivery = delivery
        self.express = bool(express)
        self._cc = cc[congestion_control]
        self.max_queue = max_queue
        # _lock guards subscriptions, delivery and stats (RLock: a callback may subscribe,
        # unsubscribe or publish); _pub_lock guards the publisher cache and publish stats
        self._lock = threading.RLock()
        self._pub_lock = threading.Lock()
        self._queue: collections.deque[tuple[str, bytes]] = collections.deque()
        self._zsubs: dict[str, _ZSub] = {}
        self._zorder = 0
        self._owner: dict[str, str | None] = {}  # key -> expression that delivers it
        self._publishers: dict[str, Any] = {}
        self._raw: dict[int, Subscription] = {}  # raw (undecoded) subscriptions by id
        self._draining = False
        try:
            self._session = zenoh.open(cfg)
        except Exception as e:
            raise ZenohTransportError(f"zenoh session ({mode}, connect={connect!r}) did not "
                                      f"open: {' '.join(str(e).split())}") from None
        self.zid = str(self._session.zid())

    # ------------------------------------------------------------------ publishing
    def _publish_bytes(self, key: str, payload: bytes, t_gps_s: float | None) -> None:
        self._check_open()
        validate_key(key)
        with self._pub_lock:
            pub = self._publishers.get(key)
            if pub is None and len(self._publishers) < MAX_PUBLISHERS:
                pub = self._publishers[key] = self._session.declare_publisher(
                    key, congestion_control=self._cc, express=self.express,
                    reliability=zenoh.Reliability.RELIABLE)
            self.stats.published += 1
            self.stats.published_bytes += len(payload)
        if pub is not None:
            pub.put(payload)
        else:
            self._session.put(key, payload, congestion_control=self._cc, express=self.express)

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
        not, before and without decoding (recorders). Not counted in ``stats``. Raw
        callbacks run on Zenoh's thread in both delivery modes (under the delivery lock)."""
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
            z.zsub = self._session.declare_subscriber(expr, self._make_handler(expr))
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
                key = str(sample.key_expr)
                if sample.kind != zenoh.SampleKind.PUT:
                    payload = b""  # a DELETE carries no message: rejected as empty
                else:
                    payload = sample.payload.to_bytes()
                self._on_sample(expr, key, payload)
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

    def _on_sample(self, expr: str, key: str, payload: bytes) -> None:
        with self._lock:
            if self._closed:
                return
            try:
                owner = self._owner_of(key)
            except KeyExprError as e:
                self.stats.total.rejected["key: invalid"] += 1
                self._ratelog(logging.WARNING, "reject:key", f"bus: rejected key {key!r}: {e}")
                return
            if owner != expr:  # another declared expression delivers this key
                return
            for rsub in list(self._raw.values()):
                if key_matches(rsub.key_expr, key):
                    try:
                        rsub.raw_callback(key, payload)
                    except Exception as e:
                        self.stats.total.callback_errors += 1
                        self._ratelog(logging.ERROR, f"rawcb:{type(e).__name__}",
                                      f"bus: raw callback raised on {key!r}: "
                                      f"{type(e).__name__}: {e}")
            if not self._subs:
                return
            if self.delivery == "callback":
                self._deliver(key, payload)
                return
            if self.max_queue is not None and len(self._queue) >= self.max_queue:
                self._queue.popleft()
                self.stats.total.rejected["queue: overflow"] += 1
                self._ratelog(logging.WARNING, "reject:overflow",
                              f"bus: receive queue full ({self.max_queue}); oldest dropped")
            self._queue.append((key, payload))

    @property
    def pending(self) -> int:
        """Payloads received and waiting for `drain` (queue mode)."""
        return len(self._queue)

    def drain(self, until_t_gps_s: float | None = None, max_items: int | None = None) -> int:
        """Queue mode: decode and deliver, on this thread, everything received so far (at
        most ``max_items``). ``until_t_gps_s`` is accepted for parity with
        `InMemoryTransport.drain` and ignored (live: a message is due when it arrives).
        Returns the number of payloads handed to the receive path. In callback mode: 0."""
        count = 0
        with self._lock:
            if self._draining:
                return 0
            self._draining = True
            try:
                limit = len(self._queue) if max_items is None else min(max_items, len(self._queue))
                while count < limit and not self._closed:
                    key, payload = self._queue.popleft()
                    self._deliver(key, payload)
                    count += 1
            finally:
                self._draining = False
        return count

    # ------------------------------------------------------------------ helpers
    def wait_for_subscribers(self, key: str, timeout_s: float = 5.0) -> bool:
        """Block (wall clock; launcher and tests only, never in a step function) until a
        subscriber somewhere matches ``key``; return whether one did before the timeout."""
        self._check_open()
        validate_key(key)
        with self._pub_lock:
            pub = self._publishers.get(key)
            if pub is None and len(self._publishers) < MAX_PUBLISHERS:
                pub = self._publishers[key] = self._session.declare_publisher(
                    key, congestion_control=self._cc, express=self.express,
                    reliability=zenoh.Reliability.RELIABLE)
        if pub is None:
            raise RuntimeError("too many publishers declared to watch one more key")
        deadline = time.monotonic() + timeout_s
        while True:
            if pub.matching_status.matching:
                return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.005)

    def routers(self) -> list[str]:
        """Zenoh ids of the routers this session is connected to now."""
        return [str(z) for z in self._session.info.routers_zid()]

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Undeclare every subscriber and publisher, then close the session (idempotent).
        A process whose session still has a callback subscriber can hang at exit: close."""
        with self._lock:
            if self._closed:
                return
            super().close()  # closes every subscription -> undeclares the zenoh subscribers
            for rsub in list(self._raw.values()):
                rsub.close()
            for z in list(self._zsubs.values()):
                try:
                    z.zsub.undeclare()
                except Exception:
                    pass
            self._zsubs.clear()
            self._queue.clear()
        with self._pub_lock:
            for pub in self._publishers.values():
                try:
                    pub.undeclare()
                except Exception:
                    pass
            self._publishers.clear()
        try:
            self._session.close()
        except Exception as e:  # e.g. "close operation timed out" (zenoh#2675)
            log.warning("bus: zenoh session close: %s", " ".join(str(e).split()))

    def __del__(self) -> None:
        try:
            if not self._closed and not self._session.is_closed():
                self.close()
        except Exception:
            pass

    def __repr__(self) -> str:
        return (f"ZenohTransport({self.zid[:8]} {self.delivery}"
                f"{' closed' if self._closed else ''})")


def _never_called(key: str, msg: object) -> None:  # pragma: no cover
    raise AssertionError("raw subscription got a decoded delivery")


__all__ = ["DELIVERY_MODES", "ZenohConfigError", "ZenohTransport", "ZenohTransportError"]
