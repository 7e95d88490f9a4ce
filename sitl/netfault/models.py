"""Link fault models with netem's parameters and semantics, seeded and in simulation time.

One `LinkFault` is one direction of one link: ``process(t_s, payload)`` returns the copies
the link delivers, ``[(deliver_at_s, bytes), ...]`` (``[]``: dropped; two items: duplicated;
changed bytes: corrupted). Every random draw comes from the numpy Generator passed in; the
time is the caller's simulation time (no clock, no sleeping). The per-packet steps follow
linux ``net/sched/sch_netem.c`` ``netem_enqueue``, in its order:

1. partition (ours; netem has none): sent at T1 <= t < T2 -> dropped, no random draws;
2. duplicate (``duplicate >= crandom``) adds a copy, then the loss model removes one:
   a duplicated packet that is "lost" still goes out once; an undisturbed duplicate is a
   clone that is enqueued again (duplication off) *before* the original, so it takes its
   own loss, corruption, queue and delay draws;
3. corrupt: one random bit of one random byte flipped (``data[rand % len] ^= 1 << rand % 8``);
   the clone is taken before the corruption;
4. queue limit: a packet finding ``limit`` or more packets in the link (sent, not yet
   delivered) is dropped with its clone (netem: ``qlen >= limit``); netem's default limit is
   1000 packets, ours is none (a simulated bus with a 2 s delay would hit it); the link
   counts its packets while it has a limit (one set at run time starts from an empty count);
5. reorder / delay: unless reordering, ``delay = tabledist(latency, jitter)``; with a rate,
   ``deliver = max(link busy until, t + delay) + len * 8 / rate`` (netem's "last packet in
   queue is the reference" rule: one packet on the wire at a time); otherwise
   ``deliver = t + delay``. A reordered packet (``gap`` counter reached and
   ``crandom <= reorder``, netem's ``q->counter < q->gap - 1`` rule) goes out at once,
   bypassing delay and rate, and resets the counter. Delays below 0 are clipped to 0.

Correlated draws are netem's ``get_crandom``: ``u_n = (1 - rho) v_n + rho u_{n-1}`` with v
uniform (the kernel's fixed-point version, in floating point), computed in blocks with
`scipy.signal.lfilter`. As in netem this makes u less spread than uniform, so a correlated
loss rate is not ``loss`` (netem's known flaw, reproduced): loss=20%,25% loses 10.2 %,
loss=10%,25% 1.75 %, loss=10%,50% 0.11 % (exact values of the chain; use gemodel for bursty
loss at a given rate); the tests check the chain's exact values, not the nominal ones.
Likewise a correlated delay jitter is narrower than the uncorrelated one.

Delay distributions (netem's tables, table-free: the inverse CDF applied to the correlated
uniform, as netem indexes its table with it; ``sigma`` = jitter; t clipped to netem's int16
table range, |t| <= 32767/8192 ~ 4):

=========================  ==========================================================
uniform (kernel default)   ``mu + sigma (2u - 1)``  (kernel: ``rnd % 2 sigma - sigma + mu``)
normal                     ``mu + sigma Phi^-1(u)``  (iproute2 normal table, continuous)
pareto                     ``mu + sigma min(4/3 ((1-u)^(-1/3) - 1.5), 4)``: iproute2 pareto.c
                           (shape a = 3, x_m = 1, shifted by its mean 1.5, scaled by 4/3)
paretonormal               ``mu + sigma (Phi^-1(u) + 3 pareto(u)) / 4``: iproute2
                           paretonormal.c (a quantile-wise 25 % normal + 75 % pareto mix)
=========================  ==========================================================

Gilbert-Elliott (``gemodel p r 1-h 1-k``): the loss of packet n uses the state it finds
(good: loss prob 1-k, bad: 1-h), then the state moves (good->bad p, bad->good r), starting
good, as the kernel's ``loss_gilb_ell``; stationary loss ``(r (1-k) + p (1-h)) / (p + r)``;
with 1-h = 1, 1-k = 0 bursts are geometric with mean 1/r packets and gaps with mean 1/p.
Defaults as tc-netem(8) (and iproute2's q_netem.c): r = 1-p (Bernoulli), 1-h = 100 %, 1-k = 0.

Rate: ``len(payload) * 8 / rate`` per packet, the payload as given (netem counts the L2
frame and optional overheads; a caller that wants headers counted adds them to the rate).
Pareto's t has standard deviation 2/sqrt(3) ~ 1.15 (netem's table is not unit-variance).

The models, their parameters, their netem equivalent and what tests/sitl/netfault/test_models.py
checks (100,000 packets for each model's statistics, 50,000 for some of the rules):

==============  =====================  ======================  ===============================
model           spec text              netem                   test
==============  =====================  ======================  ===============================
random loss     loss=P                 loss random P           fraction in binomial 99.9 % CI
correlated      loss=P,C               loss random P C         rate and lag-1 autocorrelation vs
loss                                                           the crandom chain's exact values
Gilbert-        gemodel=p,r,1-h,1-k    loss gemodel p r 1-h    stationary loss, mean burst 1/r,
Elliott                                1-k                     mean gap 1/p, in CI
delay+jitter    delay=D~J,C            delay D J C             normal mean/sd; pareto KS test vs
                distribution=X         distribution X          scipy; uniform bounds; corr
reorder         reorder=P,C gap=N      reorder P C gap N       fraction sent at once; gap rule
duplicate       duplicate=P,C          duplicate P C           fraction in CI
corrupt         corrupt=P,C            corrupt P C             fraction in CI; one bit differs
rate + queue    rate=R limit=N         rate R limit N          throughput = R saturated; drops
                                                               only above the limit
partition       partition=T1-T2        (none)                  nothing sent in [T1, T2) arrives,
                                                               all else does
==============  =====================  ======================  ===============================

`LinkTruth` keeps the counters and the delivery schedule (packet index = order of the
``process`` calls) so that a receiver's sequence-number statistics can be compared exactly:
`LinkTruth.receiver_view` computes what a receiver sees. `KeyFaults` applies rules per bus
key (a `sitl.bus.transport.FaultFilter`).
"""
from __future__ import annotations

import heapq
import math
import zlib
from array import array
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from sitl.bus.transport import key_matches, validate_key, validate_key_expr

from .spec import DISTRIBUTIONS, FaultSpec, parse_spec

__all__ = ["KeyFaults", "LinkFault", "LinkTruth", "crandom_block", "delay_quantile"]

_PARETO_A = 3.0
_CLIP = 32767 / 8192  # netem tables are int16 scaled by NETEM_DIST_SCALE = 8192: |t| <= ~4


def crandom_block(v: np.ndarray, rho: float, last: float) -> np.ndarray:
    """netem's get_crandom over a block of uniforms v: u_n = (1-rho) v_n + rho u_{n-1},
    u_{-1} = last."""
    if rho == 0.0:
        return v
    from scipy import signal  # here: importing scipy.signal costs 3-7 s, paid only by correlated draws

    y, _ = signal.lfilter([1.0 - rho], [1.0, -rho], v, zi=[rho * last])
    return y


def _pareto_std(u: np.ndarray) -> np.ndarray:
    x = (1.0 - u) ** (-1.0 / _PARETO_A)
    return np.minimum((4.0 / 3.0) * (x - 1.5), _CLIP)


def delay_quantile(distribution: str, u: np.ndarray) -> np.ndarray:
    """The standardised delay offset t(u) of a netem distribution: delay = mu + sigma t(u)."""
    from scipy import special  # scipy.special is light; imported here like scipy.signal above

    u = np.asarray(u, dtype=float)
    if distribution == "uniform":
        return 2.0 * u - 1.0
    if distribution == "normal":
        return np.clip(special.ndtri(u), -_CLIP, _CLIP)
    if distribution == "pareto":
        return _pareto_std(u)
    if distribution == "paretonormal":
        # iproute2 paretonormal.c: (normal + 3 pareto) / 4 at the same quantile, int16-clipped
        return np.clip(0.25 * special.ndtri(u) + 0.75 * _pareto_std(u), -_CLIP - 1 / 8192, _CLIP)
    raise ValueError(f"unknown distribution {distribution!r}")


class _Stream:
    """A correlated (or plain) uniform stream (netem's crndstate), drawn in blocks; ``fn``
    maps the uniforms to the values handed out (a delay quantile), also per block."""

    __slots__ = ("buf", "fn", "i", "last0", "n", "raw", "rho", "rng", "u")

    def __init__(self, rng: np.random.Generator, rho: float, fn=None):
        self.rng = rng
        self.rho = float(rho)
        self.fn = fn
        self.last0 = float(rng.random())  # netem init_crandom: last = a random value
        self.raw = self.u = np.empty(0)
        self.buf: list[float] = []
        self.i = 0
        self.n = 32

    def _last(self) -> float:
        return float(self.u[self.i - 1]) if self.i > 0 else self.last0

    def _values(self, u: np.ndarray) -> list[float]:
        return (self.fn(u) if self.fn is not None else u).tolist()

    def next(self) -> float:
        i = self.i
        if i >= len(self.buf):
            self.last0 = self._last()
            self.raw = self.rng.random(self.n)
            self.n = min(self.n * 2, 8192)
            self.u = crandom_block(self.raw, self.rho, self.last0)
            self.buf = self._values(self.u)
            i = 0
        self.i = i + 1
        return self.buf[i]

    def change(self, rho: float, fn=None) -> None:
        """New correlation / value map for the draws not yet handed out."""
        rho = float(rho)
        if rho == self.rho and fn is self.fn:
            return
        i = self.i
        if i < self.raw.size:
            last = self._last()
            u = crandom_block(self.raw[i:], rho, last)
            self.u = np.concatenate([self.u[:i], u])
            self.buf[i:] = (fn(u) if fn is not None else u).tolist()
        self.rho, self.fn = rho, fn


_QUANTILES = {d: (lambda u, d=d: delay_quantile(d, u)) for d in DISTRIBUTIONS}


@dataclass
class LinkTruth:
    """What a link did (the injected truth). Packet index = order of ``process`` calls.

    Counters: ``sent`` packets offered; ``delivered`` copies handed out; ``dropped_loss``,
    ``dropped_partition``, ``dropped_queue`` packets that produced no copy, by cause;
    ``duplicated`` packets delivered twice; ``corrupted`` copies handed out with a flipped
    bit; ``sent_at_once`` packets the reorder rule sent without delay; ``clone_lost``,
    ``clone_queue`` duplicate clones removed by the loss model / queue limit (their packet
    went out once); ``delay_s_sum`` / ``delay_s_max`` over delivered copies.
    ``reordered``: packets whose first delivered copy arrives after a copy of a packet sent
    later (ties: delivered in the order handed out), counted online (equal to
    ``reordered_indices().size``, which reads it from the delivery schedule).

    The schedule (``copy_*``, ``drop_*`` arrays: the index lists and `receiver_view`) is kept
    unless the link was made with ``record=False`` (long live runs: ~34 bytes a packet);
    ``recorded`` says which.
    """

    sent: int = 0
    delivered: int = 0
    dropped_loss: int = 0
    dropped_partition: int = 0
    dropped_queue: int = 0
    duplicated: int = 0
    corrupted: int = 0
    sent_at_once: int = 0
    clone_lost: int = 0
    clone_queue: int = 0
    delay_s_sum: float = 0.0
    delay_s_max: float = 0.0
    reordered: int = 0
    recorded: bool = True
    # schedule: one entry per delivered copy, in the order handed out
    copy_index: array = field(default_factory=lambda: array("q"), repr=False)
    copy_at_s: array = field(default_factory=lambda: array("d"), repr=False)
    copy_corrupt: array = field(default_factory=lambda: array("b"), repr=False)
    sent_at_s: array = field(default_factory=lambda: array("d"), repr=False)  # per packet
    drop_index: array = field(default_factory=lambda: array("q"), repr=False)
    drop_cause: array = field(default_factory=lambda: array("b"), repr=False)

    CAUSES = ("loss", "partition", "queue")

    @property
    def dropped(self) -> int:
        return self.dropped_loss + self.dropped_partition + self.dropped_queue

    @property
    def delay_s_mean(self) -> float:
        return self.delay_s_sum / self.delivered if self.delivered else math.nan

    def counters(self) -> dict:
        """The counters as a plain dict (for result files and messages)."""
        return {"sent": self.sent, "delivered": self.delivered, "dropped": self.dropped,
                "dropped_loss": self.dropped_loss, "dropped_partition": self.dropped_partition,
                "dropped_queue": self.dropped_queue, "duplicated": self.duplicated,
                "corrupted": self.corrupted, "reordered": self.reordered,
                "sent_at_once": self.sent_at_once, "clone_lost": self.clone_lost,
                "clone_queue": self.clone_queue, "delay_s_sum": self.delay_s_sum,
                "delay_s_max": self.delay_s_max}

    # ---- index lists ----------------------------------------------------------------
    def dropped_indices(self, cause: str | None = None) -> np.ndarray:
        """Indices of packets that produced no copy (of one cause, or all), ascending."""
        self._need_schedule()
        idx = np.frombuffer(self.drop_index, dtype=np.int64) if self.drop_index else np.zeros(0, np.int64)
        if cause is not None:
            c = np.frombuffer(self.drop_cause, dtype=np.int8) if self.drop_cause else np.zeros(0, np.int8)
            idx = idx[c == self.CAUSES.index(cause)]
        return idx.copy()

    def _need_schedule(self) -> None:
        if not self.recorded:
            raise ValueError("link truth: the per-packet schedule was not recorded (record=False)")

    def _copies(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        self._need_schedule()
        n = len(self.copy_index)
        if n == 0:
            return np.zeros(0, np.int64), np.zeros(0), np.zeros(0, bool)
        return (np.frombuffer(self.copy_index, dtype=np.int64),
                np.frombuffer(self.copy_at_s, dtype=np.float64),
                np.frombuffer(self.copy_corrupt, dtype=np.int8).astype(bool))

    def duplicated_indices(self) -> np.ndarray:
        """Indices of packets delivered more than once."""
        idx, _, _ = self._copies()
        u, c = np.unique(idx, return_counts=True)
        return u[c > 1]

    def corrupted_indices(self) -> np.ndarray:
        """Indices of packets with at least one corrupted copy delivered."""
        idx, _, bad = self._copies()
        return np.unique(idx[bad])

    def delivery_order(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(index, deliver_at_s, corrupted) of every delivered copy in delivery order
        (deliver time; ties in the order handed out, as InMemoryTransport delivers)."""
        idx, at, bad = self._copies()
        o = np.argsort(at, kind="stable")
        return idx[o], at[o], bad[o]

    @staticmethod
    def _late_first(idx_in_order: np.ndarray) -> np.ndarray:
        """Packet indices whose first arrival comes after an arrival of a higher index."""
        if idx_in_order.size == 0:
            return idx_in_order
        prev_max = np.concatenate([[-1], np.maximum.accumulate(idx_in_order)[:-1]])
        _, first = np.unique(idx_in_order, return_index=True)
        late = prev_max[first] > idx_in_order[first]
        return np.sort(idx_in_order[first][late])

    def reordered_indices(self) -> np.ndarray:
        """Indices of packets whose first delivered copy comes after a copy of a later one."""
        idx, _, _ = self.delivery_order()
        return self._late_first(idx)


    def receiver_view(self, reject_corrupted: bool = True, until_s: float = math.inf) -> dict:
        """What a receiver counting sequence numbers (seq = packet index) sees of the copies
        delivered by ``until_s``, as `sitl.bus.transport.SequenceTracker` counts them; with
        ``reject_corrupted`` corrupted copies are discarded first (a CRC check).

        received: distinct packets accepted; duplicates: accepted copies beyond the first;
        out_of_order: packets whose first accepted copy arrives after an accepted copy of a
        higher seq ("late"); gaps: arrivals beyond the highest seq so far that skip seqs;
        missing: seqs skipped and never accepted, counted from the first accepted seq
        (``highest - first + 1 - received``, as the tracker counts: leading losses are not
        seen); missing_total: ``sent - received`` (leading and trailing losses included);
        rejected_corrupt: corrupted copies discarded; copies, latency_s_sum, latency_s_max:
        accepted copies (duplicates included) and their arrival minus send time."""
        idx, at, bad = self.delivery_order()
        keep = at <= until_s
        rejected = int(np.count_nonzero(bad & keep)) if reject_corrupted else 0
        if reject_corrupted:
            keep &= ~bad
        idx, at = idx[keep], at[keep]
        lat = at - np.frombuffer(self.sent_at_s, dtype=np.float64)[idx] if idx.size else at
        n_distinct = int(np.unique(idx).size)
        if idx.size == 0:
            return {"received": 0, "duplicates": 0, "out_of_order": 0, "gaps": 0, "missing": 0,
                    "missing_total": self.sent, "rejected_corrupt": rejected, "highest_seq": -1,
                    "copies": 0, "latency_s_sum": 0.0, "latency_s_max": math.nan}
        prev_max = np.concatenate([[idx[0] - 1], np.maximum.accumulate(idx)[:-1]])
        gaps = int(np.count_nonzero(idx - prev_max > 1))
        highest = int(idx.max())
        return {"received": n_distinct, "duplicates": int(idx.size - n_distinct),
                "out_of_order": int(self._late_first(idx).size), "gaps": gaps,
                "missing": highest - int(idx[0]) + 1 - n_distinct,
                "missing_total": int(self.sent - n_distinct), "rejected_corrupt": rejected,
                "highest_seq": highest, "copies": int(idx.size),
                "latency_s_sum": float(lat.sum()), "latency_s_max": float(lat.max())}


class LinkFault:
    """One direction of one link with a `FaultSpec` (see the module docstring).

    ``process(t_s, payload) -> [(deliver_at_s, bytes)]``; also callable as a bus
    ``FaultFilter`` ``(key, payload, t_s)``. ``set(spec, t_s)`` changes the spec for packets
    sent at or after ``t_s``."""

    def __init__(self, spec: FaultSpec | str | None = None, *, rng: np.random.Generator,
                 name: str = "", record: bool = True):
        if not isinstance(rng, np.random.Generator):
            raise TypeError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
        self.name = name
        self.rng = rng
        self.spec = parse_spec(spec)
        self.record = bool(record)
        self.truth = LinkTruth(recorded=self.record)
        s = self.spec
        # one child generator per random stream (numpy's spawn, deterministic from rng): a
        # model's draws do not depend on which other models are on (common random numbers:
        # loss=20% drops a subset of what loss=30% drops, with or without a delay jitter)
        try:
            children = rng.spawn(7)
        except TypeError:  # a bit generator without a SeedSequence: seed children from it
            children = [np.random.default_rng(int(x)) for x in rng.integers(2**63, size=7)]
        g_loss, g_dup, g_corrupt, g_reorder, g_delay, g_ge, self._bit_rng = children
        self._loss = _Stream(g_loss, s.loss_corr)
        self._dup = _Stream(g_dup, s.duplicate_corr)
        self._corrupt = _Stream(g_corrupt, s.corrupt_corr)
        self._reorder = _Stream(g_reorder, s.reorder_corr)
        self._delay = _Stream(g_delay, s.delay_corr, _QUANTILES[s.distribution])
        self._ge_u = _Stream(g_ge, 0.0)
        self._ge_bad = False
        self._counter = 0
        self._busy_until = -math.inf
        self._inflight: list[float] = []  # deliver times of queued packets (limit only)
        self._pending: list[tuple[float, int, FaultSpec]] = []
        self._pending_n = 0
        self._last_t = -math.inf
        self._identity = self.spec.is_identity
        # online reorder count: max-heap of (-first delivery time, index) of packets not
        # (yet) overtaken; pruned of entries no later packet can overtake (monotone times)
        self._waiting: list[tuple[float, int]] = []
        self._prune_at = 1024
        self._monotone = True

    def __repr__(self) -> str:
        return f"LinkFault({self.name!r}, {self.spec.to_text()!r})"

    # ---- run-time change ---------------------------------------------------------------
    def set(self, spec: FaultSpec | str | None, t_s: float | None = None) -> None:
        """Use ``spec`` for packets sent at ``t_s`` or later (None: from now on)."""
        spec = parse_spec(spec)
        if t_s is None or t_s <= self._last_t:
            self._apply(spec)
        else:
            self._pending_n += 1
            heapq.heappush(self._pending, (float(t_s), self._pending_n, spec))

    def _apply(self, spec: FaultSpec) -> None:
        old = self.spec
        self.spec = spec
        self._identity = spec.is_identity
        self._loss.change(spec.loss_corr)
        self._dup.change(spec.duplicate_corr)
        self._corrupt.change(spec.corrupt_corr)
        self._reorder.change(spec.reorder_corr)
        self._delay.change(spec.delay_corr, _QUANTILES[spec.distribution])
        if spec.ge != old.ge:
            self._ge_bad = False  # netem: a new gemodel starts in the good state
        if (spec.gap, spec.reorder) != (old.gap, old.reorder):
            self._counter = 0  # netem_change resets the reorder counter

    # ---- the per-packet path -----------------------------------------------------------
    def __call__(self, key: str, payload: bytes, t_s: float) -> list[tuple[float, bytes]]:
        return self.process(t_s, payload)

    def process(self, t_s: float, payload: bytes) -> list[tuple[float, bytes]]:
        """The copies the link delivers for a packet sent at ``t_s``: [(deliver_at_s, bytes)]."""
        t = float(t_s)
        if not math.isfinite(t):
            raise ValueError(f"link {self.name!r}: send time must be finite, got {t_s!r}")
        if type(payload) is not bytes:
            if isinstance(payload, (bytes, bytearray, memoryview)):
                payload = bytes(payload)
            else:
                raise TypeError(f"link {self.name!r}: payload must be bytes, got "
                                f"{type(payload).__name__}")
        if self._pending and self._pending[0][0] <= t:
            while self._pending and self._pending[0][0] <= t:
                self._apply(heapq.heappop(self._pending)[2])
        if t >= self._last_t:
            self._last_t = t
        else:
            self._monotone = False
        tr = self.truth
        idx = tr.sent
        tr.sent = idx + 1
        if self.record:
            tr.sent_at_s.append(t)
        spec = self.spec
        if spec.partitions and spec.down(t):
            self._drop(idx, 1)
            return []
        if self._identity:
            out = [(t, payload, False)]
        else:
            out, cause = self._enqueue(t, payload, spec, True)
            if not out:
                self._drop(idx, cause)
                return []
        # the truth: counters, schedule, online reorder count
        record = self.record
        first = math.inf
        for at, _p, bad in out:
            tr.delivered += 1
            if record:
                tr.copy_index.append(idx)
                tr.copy_at_s.append(at)
                tr.copy_corrupt.append(bad)
            if bad:
                tr.corrupted += 1
            d = at - t
            tr.delay_s_sum += d
            tr.delay_s_max = max(tr.delay_s_max, d)
            first = min(first, at)
        w = self._waiting
        while w and -w[0][0] > first:
            heapq.heappop(w)
            tr.reordered += 1
        heapq.heappush(w, (-first, idx))
        if len(w) > self._prune_at and self._monotone:
            w[:] = [e for e in w if -e[0] > t]  # later packets are sent at >= t
            heapq.heapify(w)
            self._prune_at = max(1024, 2 * len(w))
        if len(out) == 1:
            return [(out[0][0], out[0][1])]
        tr.duplicated += 1
        return [(at, p) for at, p, _ in out]

    def _drop(self, idx: int, cause: int) -> None:
        tr = self.truth
        if self.record:
            tr.drop_index.append(idx)
            tr.drop_cause.append(cause)
        if cause == 0:
            tr.dropped_loss += 1
        elif cause == 1:
            tr.dropped_partition += 1
        else:
            tr.dropped_queue += 1

    def _loss_event(self, spec: FaultSpec) -> bool:
        if spec.ge is not None:
            p, r, one_h, one_k = spec.ge
            # kernel loss_gilb_ell: transition draw, then the loss draw of the state it found
            was_bad = self._ge_bad
            if was_bad:
                if self._ge_u.next() < r:
                    self._ge_bad = False
                return self._ge_u.next() < one_h
            if self._ge_u.next() < p:
                self._ge_bad = True
            return self._ge_u.next() < one_k
        return spec.loss > 0 and self._loss.next() < spec.loss

    def _qlen(self, t: float) -> int:
        q = self._inflight
        while q and q[0] <= t:
            heapq.heappop(q)
        return len(q)

    def _enqueue(self, t: float, payload: bytes, spec: FaultSpec, allow_dup: bool
                 ) -> tuple[list[tuple[float, bytes, bool]], int]:
        """netem_enqueue for one packet: (copies as (at, bytes, corrupted), drop cause)."""
        count = 1
        if allow_dup and spec.duplicate > 0 and self._dup.next() < spec.duplicate:
            count += 1
        if self._loss_event(spec):
            count -= 1
        if count == 0:
            if not allow_dup:
                self.truth.clone_lost += 1
            return [], 0
        clone = payload if count > 1 else None
        bad = False
        if spec.corrupt > 0 and self._corrupt.next() < spec.corrupt and payload:
            b = bytearray(payload)
            bit = int(self._bit_rng.integers(len(b) * 8))
            b[bit >> 3] ^= 1 << (bit & 7)
            payload = bytes(b)
            bad = True
        if spec.limit is not None and self._qlen(t) >= spec.limit:
            if not allow_dup:
                self.truth.clone_queue += 1
            return [], 2
        out: list[tuple[float, bytes, bool]] = []
        if clone is not None:
            c_out, _ = self._enqueue(t, clone, spec, False)
            out.extend(c_out)
        if spec.gap == 0 or self._counter < spec.gap - 1 or spec.reorder < self._reorder.next():
            delay = spec.delay_s
            if spec.jitter_s > 0:
                delay += spec.jitter_s * self._delay.next()
                delay = max(delay, 0.0)
            at = t + delay
            if spec.rate_bps > 0:
                at = max(self._busy_until, at) + len(payload) * 8.0 / spec.rate_bps
                self._busy_until = at
            self._counter += 1
        else:
            at = t
            self._counter = 0
            self.truth.sent_at_once += 1
        if spec.limit is not None and at > t:
            heapq.heappush(self._inflight, at)
        out.append((at, payload, bad))
        return out, 0


class KeyFaults:
    """Per-key faults for a bus: ``rules`` [(key expression, spec)], first match wins; one
    independent `LinkFault` per concrete key, its rng ``default_rng([seed, crc32(key)])``.
    Keys matching no rule pass untouched (and get no truth). A ``FaultFilter``:
    ``InMemoryTransport(faults=[kf])``. ``record=False``: counters only (see `LinkTruth`).

    ``set(key_expr, spec, t_s)`` changes that rule, or adds it ahead of the others, for
    packets sent at ``t_s`` or later (None: now): links that exist then switch to the spec
    their key now matches first (the identity if none), and keys seen later follow the new
    rules."""

    def __init__(self, rules: Iterable[tuple[str, FaultSpec | str]] = (), *, seed: int = 0,
                 record: bool = True):
        self.seed = int(seed)
        self.record = bool(record)
        self._rules: list[tuple[str, FaultSpec]] = []
        for expr, spec in rules:
            self._rules.append((validate_key_expr(expr), parse_spec(spec)))
        self._links: dict[str, LinkFault] = {}
        self._nomatch: set[str] = set()
        self._pending: list[tuple[float, int, str, FaultSpec]] = []
        self._pending_n = 0
        self._last_t = -math.inf

    def __repr__(self) -> str:
        rules = ", ".join(f"{e}: {s.to_text()}" for e, s in self._rules)
        return f"KeyFaults([{rules}], seed={self.seed})"

    @property
    def rules(self) -> list[tuple[str, FaultSpec]]:
        return list(self._rules)

    def _match(self, key: str) -> FaultSpec | None:
        for expr, spec in self._rules:
            if key_matches(expr, key):
                return spec
        return None

    def link(self, key: str) -> LinkFault | None:
        """The LinkFault of a concrete key (created on first use), None if no rule matches."""
        lf = self._links.get(key)
        if lf is not None or key in self._nomatch:
            return lf
        spec = self._match(validate_key(key))
        if spec is None:
            self._nomatch.add(key)
            return None
        rng = np.random.default_rng([self.seed, zlib.crc32(key.encode())])
        lf = self._links[key] = LinkFault(spec, rng=rng, name=key, record=self.record)
        return lf

    def __call__(self, key: str, payload: bytes, t_s: float) -> list[tuple[float, bytes]]:
        if self._pending and self._pending[0][0] <= t_s:
            while self._pending and self._pending[0][0] <= t_s:
                t_c, _, expr, spec = heapq.heappop(self._pending)
                self._apply(expr, spec, t_c)
        self._last_t = max(self._last_t, t_s)
        lf = self._links.get(key)
        if lf is None:
            lf = self.link(key)
            if lf is None:
                return [(t_s, payload)]
        return lf.process(t_s, payload)

    def set(self, key_expr: str, spec: FaultSpec | str | None, t_s: float | None = None) -> None:
        """Change the rule ``key_expr`` (or add it ahead of the others) from ``t_s`` on."""
        expr = validate_key_expr(key_expr)
        spec = parse_spec(spec)
        if t_s is None or t_s <= self._last_t:
            self._apply(expr, spec, t_s)
        else:
            self._pending_n += 1
            heapq.heappush(self._pending, (float(t_s), self._pending_n, expr, spec))

    def _apply(self, expr: str, spec: FaultSpec, t_s: float | None) -> None:
        for i, (e, _) in enumerate(self._rules):
            if e == expr:
                self._rules[i] = (expr, spec)
                break
        else:
            self._rules.insert(0, (expr, spec))
        for key, lf in self._links.items():
            new = self._match(key)
            lf.set(new if new is not None else FaultSpec(), t_s)
        self._nomatch.clear()  # keys that matched nothing may match now

    def truth(self, key: str) -> LinkTruth:
        lf = self._links.get(key)
        if lf is None:
            raise KeyError(f"no fault link for key {key!r} (no packet seen or no rule matches)")
        return lf.truth

    def truths(self) -> dict[str, LinkTruth]:
        return {k: lf.truth for k, lf in self._links.items()}
