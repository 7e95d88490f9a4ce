"""Counting every bus payload of a run, valid or not, on every key -- also keys no component
decodes (a transport decodes a payload only for the subscriptions that match its key, so a
malformed ``uav/3/nav`` payload, which the ground station never subscribes to, was counted by
nobody).

`PayloadAudit` is a raw callback (``transport.subscribe_raw(f"{run}/**", audit)``, or called
with each recorded payload): it decodes the payload with the bus codec and counts it once,
per key kind (the key's template with its ids as ``*``: ``uav/*/nav``, ``sonde/*/relay``, ...;
``?`` for a key that fits no template) and verdict (accepted, or rejected under the codec's
stable reason). Its counts are per payload, so they can be compared with what was published.
"""
from __future__ import annotations

import threading
from collections import Counter, defaultdict

from .codec import BusDecodeError, decode
from .schema import _template_ids, parse_key

UNKNOWN_KIND = "?"


def key_kind(key: str) -> str:
    """The key's template with its ids as ``*`` (``r1/uav/3/beacon/b1`` -> ``uav/*/beacon/*``);
    ``?`` for a key that fits no template of the schema."""
    hit = parse_key(key)
    if hit is None:
        return UNKNOWN_KIND
    _, cls, _ = hit
    return cls.KEY_TEMPLATE.format(**{name: "*" for name in _template_ids(cls.KEY_TEMPLATE)})


class PayloadAudit:
    """Counts of every payload handed to it, by key kind and verdict (module docstring).
    Thread-safe (the Zenoh transport may call it from its own thread)."""

    def __init__(self) -> None:
        self.accepted: Counter = Counter()  # kind -> payloads
        self.rejected: dict[str, Counter] = defaultdict(Counter)  # kind -> reason -> payloads
        self.bytes = 0
        self._kinds: dict[str, str] = {}
        self._lock = threading.Lock()

    def __call__(self, key: str, payload: bytes) -> None:
        kind = self._kinds.get(key)
        if kind is None:
            kind = key_kind(key)
            if len(self._kinds) < 65536:
                self._kinds[key] = kind
        try:
            decode(payload)
            reason = None
        except BusDecodeError as e:
            reason = e.reason
        with self._lock:
            self.bytes += len(payload)
            if reason is None:
                self.accepted[kind] += 1
            else:
                self.rejected[kind][reason] += 1

    @property
    def rejected_total(self) -> int:
        with self._lock:
            return sum(sum(c.values()) for c in self.rejected.values())

    def rejected_by_reason(self) -> Counter:
        """reason -> payloads, over every kind."""
        out: Counter = Counter()
        with self._lock:
            for c in self.rejected.values():
                out.update(c)
        return out

    def as_dict(self) -> dict:
        """{kind: {"accepted": n, "rejected": {reason: n}}} for report.json."""
        with self._lock:
            kinds = sorted(set(self.accepted) | set(self.rejected))
            return {k: {"accepted": int(self.accepted.get(k, 0)),
                        "rejected": {r: int(n) for r, n in sorted(self.rejected.get(k, {}).items())}}
                    for k in kinds}


__all__ = ["UNKNOWN_KIND", "PayloadAudit", "key_kind"]
