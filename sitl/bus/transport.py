"""Bus transports: the interface, Zenoh key expressions, the in-memory transport, and a
per-source sequence tracker.

Every transport moves *encoded bytes*: `Transport.publish` encodes with `sitl.bus.codec` and
every delivery decodes (and so fully validates) the payload before a callback sees it, so a
batch run exercises exactly the path a live run does. A payload that fails to decode is
counted under its `BusDecodeError.reason`, logged once per reason (then at the 10th, 100th,
... occurrence) and dropped: it never reaches a callback and never raises into the
publisher or the consumer. An exception raised by a callback is caught, counted
(``callback_errors``), logged the same rate-limited way, and delivery to the other
subscribers goes on.

Callbacks are called as ``callback(key, msg)``: the key carries ids that the message does
not (see `sitl.bus.schema.parse_key`).

Key expressions follow Zenoh (eclipse-zenoh key-expression RFC): keys are ``/``-separated
non-empty chunks; in an expression ``*`` is exactly one chunk and ``**`` is zero or more
chunks; both are whole chunks only; chunks starting with ``@`` are verbatim (matched only by
the identical chunk, never by a wildcard). Expressions must be in Zenoh's canon form
(``**/**`` and ``**/*`` are refused, as a Zenoh session refuses them). Zenoh's sub-chunk
wildcard ``$*`` is not used on this bus and is refused.
"""

from __future__ import annotations

import abc
import functools
import heapq
import itertools
import logging
import math
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from .codec import BusDecodeError, decode, encode
from .schema import Message

log = logging.getLogger("sitl.bus")

Callback = Callable[[str, Message], None]
FaultFilter = Callable[[str, bytes, float], "list[tuple[float, bytes]]"]

# ----------------------------------------------------------------------------------------
# Key expressions

_FORBIDDEN = set("?#$")


class KeyExprError(ValueError):
    """An invalid key or key expression."""


def _split(text: str, what: str) -> list[str]:
    if not isinstance(text, str):
        raise KeyExprError(f"{what} must be a str, got {type(text).__name__}")
    if not text:
        raise KeyExprError(f"{what} is empty")
    chunks = text.split("/")
    if any(not c for c in chunks):
        raise KeyExprError(f"{what} {text!r}: empty chunk (leading, trailing or double '/')")
    bad = _FORBIDDEN.intersection(text)
    if bad:
        raise KeyExprError(f"{what} {text!r}: forbidden characters {''.join(sorted(bad))!r}")
    return chunks


@functools.lru_cache(maxsize=4096)
def validate_key(key: str) -> str:
    """Check a concrete key (no wildcards); return it."""
    _split(key, "key")
    if "*" in key:
        raise KeyExprError(f"key {key!r}: wildcards are not allowed in a published key")
    return key


@functools.lru_cache(maxsize=4096)
def validate_key_expr(expr: str) -> str:
    """Check a key expression (``*`` and ``**`` whole chunks, canon form); return it."""
    chunks = _split(expr, "key expression")
    for c in chunks:
        if "*" in c and c not in ("*", "**"):
            raise KeyExprError(f"key expression {expr!r}: '*' and '**' must be whole chunks")
    for a, b in zip(chunks, chunks[1:]):
        if a == "**" and b in ("*", "**"):
            raise KeyExprError(f"key expression {expr!r}: not canon ('**/{b}' must be "
                               f"written '{'*/**' if b == '*' else '**'}')")
    return expr


@functools.lru_cache(maxsize=65536)
def key_matches(expr: str, key: str) -> bool:
    """True if the concrete ``key`` belongs to the set ``expr`` denotes (Zenoh semantics)."""
    pats = validate_key_expr(expr).split("/")
    chunks = validate_key(key).split("/")
    nk = len(chunks)
    # reach[j]: pattern prefix pats[:i] matches chunks[:j]; dynamic programming over i.
    reach = [False] * (nk + 1)
    reach[0] = True
    for p in pats:
        new = [False] * (nk + 1)
        if p == "**":
            for j in range(nk + 1):
                # ** takes zero chunks, or one more non-verbatim chunk
                new[j] = reach[j] or (j > 0 and new[j - 1] and not chunks[j - 1].startswith("@"))
        else:
            for j in range(1, nk + 1):
                if reach[j - 1]:
                    c = chunks[j - 1]
                    new[j] = (c == p) if (p != "*" or c.startswith("@")) else True
        reach = new
        if not any(reach):
            return False
    return reach[nk]


# ----------------------------------------------------------------------------------------
# Statistics


@dataclass
class LinkCounters:
    """Counters of one subscription, or of a whole transport (``Transport.stats.total``).

    ``bytes`` counts every payload that reached the subscription (delivered or rejected)."""

    delivered: int = 0
    bytes: int = 0
    rejected: Counter = field(default_factory=Counter)  # reason -> count
    callback_errors: int = 0

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())


@dataclass
class TransportStats:
    """``total``: counted once per payload (a payload matching two subscriptions is one
    delivery here, two in ``per_subscription``). ``published``/``published_bytes``: what
    the publishers handed in, before any fault layer."""

    published: int = 0
    published_bytes: int = 0
    total: LinkCounters = field(default_factory=LinkCounters)
    per_subscription: dict[int, LinkCounters] = field(default_factory=dict)


class _RateLimitedLog:
    """Log a condition the 1st, 10th, 100th, ... time it happens."""

    def __init__(self) -> None:
        self._counts: Counter = Counter()

    def __call__(self, level: int, key: str, text: str) -> None:
        self._counts[key] += 1
        n = self._counts[key]
        if n == 1 or (n >= 10 and math.log10(n).is_integer()):
            log.log(level, "%s%s", text, "" if n == 1 else f" [{n} times so far]")


# ----------------------------------------------------------------------------------------
# Interface


class Subscription:
    """A live subscription; ``close()`` stops its deliveries (idempotent)."""

    _ids = itertools.count(1)

    def __init__(self, transport: Transport, key_expr: str, callback: Callback):
        self.id = next(Subscription._ids)
        self.key_expr = key_expr
        self.callback = callback
        self.stats = LinkCounters()
        self.closed = False
        self._transport = transport

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._transport._unsubscribe(self)

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Subscription(#{self.id} {self.key_expr!r}{' closed' if self.closed else ''})"


class Transport(abc.ABC):
    """What every bus transport offers (in-memory here; Zenoh in live mode)."""

    def __init__(self) -> None:
        self.stats = TransportStats()
        self._subs: list[Subscription] = []
        self._matching: dict[str, list[Subscription]] = {}  # key -> its subscriptions (cache)
        self._closed = False
        self._ratelog = _RateLimitedLog()

    # -- publishing
    def publish(self, key: str, msg: Message) -> None:
        """Encode ``msg`` and publish it on the concrete ``key``."""
        self._publish_bytes(key, encode(msg), msg.t_gps_s)

    def publish_raw(self, key: str, payload: bytes, t_gps_s: float | None = None) -> None:
        """Publish bytes as they are (tests, fault layer): receivers validate them as usual.
        ``t_gps_s``: simulation time of publication where the transport keeps one."""
        if not isinstance(payload, (bytes, bytearray, memoryview)):
            raise TypeError(f"payload must be bytes, got {type(payload).__name__}")
        self._publish_bytes(key, bytes(payload), t_gps_s)

    @abc.abstractmethod
    def _publish_bytes(self, key: str, payload: bytes, t_gps_s: float | None) -> None: ...

    # -- subscribing
    def subscribe(self, key_expr: str, callback: Callback) -> Subscription:
        """Call ``callback(key, msg)`` for every valid message on keys matching ``key_expr``."""
        self._check_open()
        validate_key_expr(key_expr)
        if not callable(callback):
            raise TypeError("callback must be callable")
        sub = Subscription(self, key_expr, callback)
        self._subs.append(sub)
        self._matching.clear()
        self.stats.per_subscription[sub.id] = sub.stats
        return sub

    def _unsubscribe(self, sub: Subscription) -> None:
        if sub in self._subs:
            self._subs.remove(sub)
        self._matching.clear()

    def close(self) -> None:
        """Close every subscription; later publish/subscribe calls raise RuntimeError."""
        for sub in list(self._subs):
            sub.close()
        self._closed = True

    def __enter__(self) -> Transport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError(f"{type(self).__name__} is closed")

    # -- the shared receive path (the Zenoh transport calls it from its handler)
    def _deliver(self, key: str, payload: bytes) -> None:
        """Decode once, then hand the message to every open matching subscription."""
        subs = self._matching.get(key)
        if subs is None:
            # which subscriptions a key reaches changes only with (un)subscribing
            if len(self._matching) >= 65536:
                self._matching.clear()
            subs = self._matching[key] = [s for s in self._subs if not s.closed and key_matches(s.key_expr, key)]
        if not subs:
            return
        total = self.stats.total
        size = len(payload)
        total.bytes += size
        try:
            msg = decode(payload)
        except BusDecodeError as e:
            total.rejected[e.reason] += 1
            for s in subs:
                s.stats.bytes += size
                s.stats.rejected[e.reason] += 1
            self._ratelog(logging.WARNING, "reject:" + e.reason,
                          f"bus: rejected a payload on {key!r}: {e}")
            return
        total.delivered += 1
        for s in subs:
            if s.closed:  # closed by an earlier callback of this same delivery
                continue
            s.stats.bytes += size
            s.stats.delivered += 1
            try:
                s.callback(key, msg)
            except Exception as e:  # isolate consumers from each other
                s.stats.callback_errors += 1
                total.callback_errors += 1
                self._ratelog(logging.ERROR, f"cb:{s.id}:{type(e).__name__}",
                              f"bus: callback of {s!r} raised on {key!r}: "
                              f"{type(e).__name__}: {e}")


# ----------------------------------------------------------------------------------------
# In-memory transport


class InMemoryTransport(Transport):
    """Deterministic in-process bus for batch runs and tests.

    Publishing encodes to bytes and queues; delivery decodes and validates, like the live
    bus. **Default: queued delivery.** Nothing is delivered until `drain` is called; batch
    mode steps every component to time t, then calls ``drain(t)``. Queued items are
    delivered in order of (delivery time, publish order). Without faults an item's delivery
    time is its publication time: ``msg.t_gps_s`` for `publish`, the ``t_gps_s`` argument or
    the transport clock `now_s` for `publish_raw`; so within one drain messages arrive in
    time order, and in publish order among equal times. ``synchronous=True`` instead drains
    everything due (up to the publication time) inside each publish call, so messages reach
    subscribers in publish order before publish returns (handy for unit tests of a single
    component). Messages published from inside a callback are queued and delivered by the
    same drain, after the current one (no re-entrant delivery).

    Fault layer hook: ``faults`` is a list of callables ``(key, payload, t_gps_s) -> list of
    (deliver_at_t_gps_s, payload)``, applied in order at publish time (each filter sees every
    item the previous one produced, with that item's delivery time as ``t_gps_s``). An
    empty list drops the message, two items duplicate it, a later time delays it, changed
    bytes corrupt it (the receivers then reject it). Default: no faults.
    """

    def __init__(self, *, synchronous: bool = False, faults: Iterable[FaultFilter] = (),
                 start_t_gps_s: float = 0.0):
        super().__init__()
        self.synchronous = synchronous
        self.faults: list[FaultFilter] = list(faults)
        self.now_s = float(start_t_gps_s)
        self._queue: list[tuple[float, int, str, bytes]] = []
        self._counter = itertools.count()
        self._draining = False

    @property
    def pending(self) -> int:
        """Number of queued deliveries."""
        return len(self._queue)

    def next_delivery_t(self) -> float | None:
        """Delivery time of the earliest queued item, or None."""
        return self._queue[0][0] if self._queue else None

    def _publish_bytes(self, key: str, payload: bytes, t_gps_s: float | None) -> None:
        self._check_open()
        validate_key(key)
        t = self.now_s if t_gps_s is None else float(t_gps_s)
        if not math.isfinite(t):
            raise ValueError(f"publication time must be finite, got {t!r}")
        self.stats.published += 1
        self.stats.published_bytes += len(payload)
        self.now_s = max(self.now_s, t)
        items = [(t, payload)]
        for fault in self.faults:
            out: list[tuple[float, bytes]] = []
            for t_item, p_item in items:
                produced = fault(key, p_item, t_item)
                for item in produced:
                    at, p = item
                    at = float(at)
                    if not math.isfinite(at) or not isinstance(p, (bytes, bytearray)):
                        raise TypeError(f"fault filter {fault!r} produced {item!r}: expected "
                                        "(finite deliver_at_t_gps_s, bytes)")
                    out.append((at, bytes(p)))
            items = out
        for at, p in items:
            heapq.heappush(self._queue, (at, next(self._counter), key, p))
        if self.synchronous:
            self.drain(t)

    def drain(self, until_t_gps_s: float | None = None) -> int:
        """Deliver queued items due at or before ``until_t_gps_s`` (all of them when None),
        including those published by callbacks meanwhile; advance the clock `now_s` to
        ``until_t_gps_s``. Return the number of payloads handed to the receive path."""
        if self._draining:  # called from a callback: the running drain picks things up
            return 0
        until = math.inf if until_t_gps_s is None else float(until_t_gps_s)
        count = 0
        self._draining = True
        try:
            while self._queue and self._queue[0][0] <= until and not self._closed:
                at, _, key, payload = heapq.heappop(self._queue)
                self.now_s = max(self.now_s, at)
                self._deliver(key, payload)
                count += 1
        finally:
            self._draining = False
        if until_t_gps_s is not None:
            self.now_s = max(self.now_s, until)
        return count

    def close(self) -> None:
        super().close()
        self._queue.clear()


# ----------------------------------------------------------------------------------------
# Sequence tracking


@dataclass(frozen=True)
class SeqResult:
    """Verdict on one (source_id, seq).

    status: "new" (beyond every seq seen; ``gap`` = how many were skipped), "late" (below the
    highest seen but not seen before: out of order, fills an earlier gap), "duplicate",
    "restart" (far below the highest seen: the source restarted and its numbering with it;
    the tracker starts over from this seq)."""

    status: str
    gap: int = 0

    @property
    def fresh(self) -> bool:
        """True if this seq had not been seen: the message should be processed."""
        return self.status != "duplicate"

    @property
    def duplicate(self) -> bool:
        return self.status == "duplicate"

    @property
    def out_of_order(self) -> bool:
        return self.status == "late"


@dataclass
class SeqCounters:
    received: int = 0
    new: int = 0
    duplicates: int = 0
    out_of_order: int = 0
    gaps: int = 0  # gap events
    missing: int = 0  # seqs skipped and not (yet) arrived late
    restarts: int = 0


class _SourceState:
    __slots__ = ("counters", "max_seq", "seen")

    def __init__(self) -> None:
        self.max_seq = -1
        self.seen = 0  # bit i set: seq (max_seq - i) has been seen
        self.counters = SeqCounters()


class SequenceTracker:
    """Per-source sequence bookkeeping: new / duplicate / gap size / out-of-order.

    Remembers which of the last ``window`` seqs below the highest one were seen. A seq more
    than ``window`` below the highest is taken as a restart of the source (a crashed and
    restarted process counts again from 0), not as a duplicate."""

    def __init__(self, window: int = 4096):
        if window < 1:
            raise ValueError("window must be >= 1")
        self.window = window
        self._mask = (1 << window) - 1
        self._sources: dict[str, _SourceState] = {}
        self.total = SeqCounters()

    def update(self, source_id: str, seq: int) -> SeqResult:
        st = self._sources.get(source_id)
        if st is None:
            st = self._sources[source_id] = _SourceState()
        c, tot = st.counters, self.total
        c.received += 1
        tot.received += 1
        if st.max_seq < 0:
            result = SeqResult("new")
            st.max_seq, st.seen = seq, 1
        elif seq > st.max_seq:
            gap = seq - st.max_seq - 1
            shift = seq - st.max_seq
            st.seen = ((st.seen << shift) | 1) & self._mask if shift <= self.window else 1
            st.max_seq = seq
            result = SeqResult("new", gap)
        elif st.max_seq - seq >= self.window:
            st.max_seq, st.seen = seq, 1
            result = SeqResult("restart")
        else:
            bit = 1 << (st.max_seq - seq)
            if st.seen & bit:
                result = SeqResult("duplicate")
            else:
                st.seen |= bit
                result = SeqResult("late")
        for cnt in (c, tot):
            if result.status == "new":
                cnt.new += 1
                if result.gap:
                    cnt.gaps += 1
                    cnt.missing += result.gap
            elif result.status == "duplicate":
                cnt.duplicates += 1
            elif result.status == "late":
                cnt.out_of_order += 1
                cnt.missing -= 1
            else:
                cnt.restarts += 1
        return result

    def __call__(self, source_id: str, seq: int) -> SeqResult:
        return self.update(source_id, seq)

    def counters(self, source_id: str) -> SeqCounters:
        """Counters of one source (zeros for an unknown one)."""
        st = self._sources.get(source_id)
        return st.counters if st is not None else SeqCounters()

    @property
    def sources(self) -> list[str]:
        return list(self._sources)


__all__ = [
    "Callback",
    "FaultFilter",
    "InMemoryTransport",
    "KeyExprError",
    "LinkCounters",
    "SeqCounters",
    "SeqResult",
    "SequenceTracker",
    "Subscription",
    "Transport",
    "TransportStats",
    "key_matches",
    "validate_key",
    "validate_key_expr",
]
