"""Per-link statistics of what a receiver takes in: loss from sequence numbers, duplicates,
reordering, gaps, latency and silence.

A *link* is one publisher as a receiver sees it: ``(run id, source id)`` (the run is the
key's first chunk; the source id is the message header's). A source may publish several
streams with their own numbering (a UAV's nav and beacon messages both carry its epoch
index): sequence numbers are tracked per stream (the concrete key and the sender's
incarnation, by `sitl.bus.transport.SequenceTracker`) and the counts summed per link. A
restarted sender is a new incarnation of the same link: its numbering starts over in new
streams, so its messages count as received, never as duplicates of its earlier life's
(``restarts``).

What each count means (what ``sitl.netfault.LinkTruth.receiver_view`` computes from the
injected schedule, with seq = packet index):

* ``received``: distinct messages accepted (first copies; a restart's first seq included);
* ``duplicates``: copies of a sequence number already seen (the receiver discards them);
* ``out_of_order``: messages whose first copy arrives after a higher sequence number of the
  same stream;
* ``missing``: numbers below the highest seen that never arrived (loss; a message that
  arrives late leaves this count again); trailing losses are invisible until a later
  message arrives;
* ``gaps``: arrivals that skipped one or more numbers (runs of missing numbers at the time);
* latency: arrival time minus the message's ``t_gps_s``, both simulation time, over every
  copy received (duplicates included), mean and max;
* ``stale``: nothing arrived from the link for more than ``stale_after_s``; set and
  cleared by `check` (which returns the links that changed), so every transition is seen;
* ``restarts``: incarnations heard after the first (``incarnation``: the latest);
* ``rejected_future`` / ``rejected_stale``: its messages the receiver's time guard refused
  (`refused`); they are not received, and do not keep the link from turning stale.

No wall clock: the caller passes the arrival time (``InMemoryTransport.now_s`` during a
delivery; the live ground station its paced simulation clock).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from .schema import LinkStats, Message, key_for
from .transport import SeqResult, SequenceTracker


@dataclass
class LinkState:
    """The counts of one link (see the module docstring)."""

    run_id: str
    source_id: str
    received: int = 0
    missing: int = 0
    duplicates: int = 0
    out_of_order: int = 0
    gaps: int = 0
    restarts: int = 0
    incarnation: int = 0  # the latest incarnation heard
    rejected_future: int = 0
    rejected_stale: int = 0
    copies: int = 0  # every copy with a latency (duplicates included)
    latency_sum_s: float = 0.0
    latency_max_s: float = math.nan
    last_t_gps_s: float = math.nan
    last_arrival_s: float = math.nan
    stale: bool = False
    incarnations: set = field(default_factory=set)

    @property
    def latency_mean_s(self) -> float:
        return self.latency_sum_s / self.copies if self.copies else math.nan


class LinkMonitor:
    """Counts per link; `observe` every message received, `check` the silence now and then.

    stale_after_s: a link with no arrival for longer than this is flagged stale (default 3 s:
    three epochs at 1 Hz). window: the sequence tracker's memory (see SequenceTracker)."""

    def __init__(self, stale_after_s: float = 3.0, window: int = 4096):
        if not (isinstance(stale_after_s, (int, float)) and stale_after_s > 0 and math.isfinite(stale_after_s)):
            raise ValueError(f"stale_after_s must be a finite number > 0, got {stale_after_s!r}")
        self.stale_after_s = float(stale_after_s)
        self._seq = SequenceTracker(window)
        self._links: dict[tuple[str, str], LinkState] = {}
        self._out_seq = 0

    @property
    def links(self) -> list[tuple[str, str]]:
        """(run id, source id) of every link heard, in the order first heard."""
        return list(self._links)

    def states(self) -> list[LinkState]:
        return list(self._links.values())

    def state(self, run_id: str, source_id: str) -> LinkState:
        return self._links[(run_id, source_id)]

    def _link(self, key: str, msg: Message) -> LinkState:
        run = key.split("/", 1)[0]
        lk = self._links.get((run, msg.source_id))
        if lk is None:
            lk = self._links[(run, msg.source_id)] = LinkState(run, msg.source_id)
        return lk

    def observe(self, key: str, msg: Message, arrival_t_s: float) -> SeqResult:
        """Count one received message (a valid, decoded one) arriving at ``arrival_t_s``."""
        lk = self._link(key, msg)
        inc = msg.incarnation
        if inc not in lk.incarnations:
            if lk.incarnations:
                lk.restarts += 1
            lk.incarnations.add(inc)
            lk.incarnation = max(lk.incarnation, inc)
        res = self._seq.update(f"{key}\0{msg.source_id}\0{inc}", msg.seq)
        st = res.status
        if st == "duplicate":
            lk.duplicates += 1
        else:
            lk.received += 1
            if st == "new":
                if res.gap:
                    lk.gaps += 1
                    lk.missing += res.gap
            elif st == "late":
                lk.out_of_order += 1
                lk.missing -= 1
            # "restart" (a number far below the stream's highest): counted as received; a
            # restart proper is a new incarnation (above)
        lat = float(arrival_t_s) - float(msg.t_gps_s)
        lk.copies += 1
        lk.latency_sum_s += lat
        lk.latency_max_s = lat if not lk.latency_max_s >= lat else lk.latency_max_s
        if not lk.last_t_gps_s >= msg.t_gps_s:
            lk.last_t_gps_s = float(msg.t_gps_s)
        if not lk.last_arrival_s >= arrival_t_s:
            lk.last_arrival_s = float(arrival_t_s)
        return res

    def refused(self, key: str, msg: Message, reason: str) -> None:
        """Count a message of this link that the receiver's time guard refused ("future" /
        "stale", `sitl.bus.timeguard`): not received, and no sign of life."""
        lk = self._link(key, msg)
        if reason == "future":
            lk.rejected_future += 1
        else:
            lk.rejected_stale += 1

    def check(self, now_s: float) -> list[LinkState]:
        """Flag the links silent for more than stale_after_s at ``now_s`` (and clear the others);
        returns the links whose flag changed (stale or back)."""
        out = []
        for lk in self._links.values():
            stale = now_s - lk.last_arrival_s > self.stale_after_s
            if stale != lk.stale:
                lk.stale = stale
                out.append(lk)
        return out

    def message(self, lk: LinkState, t_gps_s: float, source_id: str = "gs") -> tuple[str, LinkStats]:
        """(key, LinkStats) of one link at ``t_gps_s``, published as ``source_id``."""
        m = LinkStats(t_gps_s=float(t_gps_s), source_id=source_id, seq=self._out_seq, link=lk.source_id,
                      received=lk.received, missing=max(lk.missing, 0), duplicates=lk.duplicates,
                      out_of_order=lk.out_of_order, gaps=lk.gaps, restarts=lk.restarts,
                      source_incarnation=lk.incarnation, rejected_future=lk.rejected_future,
                      rejected_stale=lk.rejected_stale, latency_mean_s=lk.latency_mean_s,
                      latency_max_s=lk.latency_max_s, stale=lk.stale, last_t_gps_s=lk.last_t_gps_s)
        self._out_seq += 1
        return key_for(lk.run_id, m), m

    def as_dict(self) -> dict:
        """{"<run>/<source>": counts} for status lines and result files."""
        return {f"{lk.run_id}/{lk.source_id}": {
            "received": lk.received, "missing": lk.missing, "duplicates": lk.duplicates,
            "out_of_order": lk.out_of_order, "gaps": lk.gaps, "restarts": lk.restarts,
            "incarnation": lk.incarnation, "rejected_future": lk.rejected_future,
            "rejected_stale": lk.rejected_stale,
            "latency_mean_s": lk.latency_mean_s, "latency_max_s": lk.latency_max_s, "stale": lk.stale,
            "last_t_gps_s": lk.last_t_gps_s} for lk in self._links.values()}


__all__ = ["LinkMonitor", "LinkState"]
