"""The time guard a bus consumer puts in front of its inputs: a message is taken only inside a
window around the consumer's OWN simulation clock.

Simulation time travels in every payload (``t_gps_s``), and a consumer orders its work by it:
epochs, filter predictions, lag windows, link silence, log time bases. One schema-valid
message far in the future (t + 1e6 s) would otherwise move all of that at once -- the
ground station's epochs jumped past every real input, which then counted as late forever.
So every consumer with a clock (the ground-station node, the launcher's scorer, a worker's
fault control) asks its `TimeGuard` first:

    guard = TimeGuard(ahead_s=2.0, behind_s=6.0)
    if guard.admit(msg.t_gps_s, now_s):   # now_s: the consumer's clock (live: its pacer)
        ...use msg...

``future``: ``t_gps_s > now_s + ahead_s`` -- ahead of the consumer's clock by more than the
clock skew between processes can explain; ``stale``: ``t_gps_s < now_s - behind_s`` -- older
than anything the consumer could still use (for the ground station: its hold plus its lag
window). A refused message is counted by reason in ``rejected`` and goes nowhere else: it
never moves a clock, a filter or a log's time base. The clock is the consumer's and only
moves forward (`TimeGuard.now_s` is the latest clock seen); before the consumer has a clock
(``now_s`` never given, or not finite) everything is admitted.
"""
from __future__ import annotations

import math
from collections import Counter

FUTURE = "future"
STALE = "stale"


def _window_value(name: str, v) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
        raise ValueError(f"{name} must be a finite number >= 0 (seconds), got {v!r}")
    return float(v)


class TimeGuard:
    """Admit messages whose time lies in [now - behind_s, now + ahead_s] (module docstring)."""

    __slots__ = ("ahead_s", "behind_s", "now_s", "rejected")

    def __init__(self, ahead_s: float, behind_s: float):
        self.ahead_s = _window_value("ahead_s", ahead_s)
        self.behind_s = _window_value("behind_s", behind_s)
        self.now_s = -math.inf
        self.rejected: Counter = Counter()  # reason ("future" / "stale") -> count

    def tick(self, now_s: float) -> float:
        """Move the clock to now_s (never back; a non-finite value is ignored); returns it."""
        if now_s > self.now_s and math.isfinite(now_s):
            self.now_s = float(now_s)
        return self.now_s

    def verdict(self, t_gps_s: float, now_s: float | None = None) -> str | None:
        """None if admitted, else the reason ("future" / "stale"); counts nothing."""
        now = self.now_s if now_s is None else self.tick(now_s)
        if now == -math.inf:
            return None
        if t_gps_s > now + self.ahead_s:
            return FUTURE
        if t_gps_s < now - self.behind_s:
            return STALE
        return None

    def admit(self, t_gps_s: float, now_s: float | None = None) -> bool:
        """True if the message may be used; a refusal is counted under its reason."""
        reason = self.verdict(t_gps_s, now_s)
        if reason is None:
            return True
        self.rejected[reason] += 1
        return False


__all__ = ["FUTURE", "STALE", "TimeGuard"]
