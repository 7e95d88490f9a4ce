"""The event loop the live fault proxies share: one thread, a selector and a heap of due actions.

Live code (it waits on sockets), but it reads no wall clock of its own: every time it handles
is simulation time from ``clock()`` (the launcher's Pacer mapping
``t_sim = t0 + speed * (wall - wall_start)``), and a wait for an action due at simulation
time ``t`` lasts ``(t - clock()) / speed`` wall seconds (selector timeout).

Any number of proxies can share one loop (``loop=`` of `UdpProxy` / `TcpProxy`): 200
vehicles need one thread, not 200. A proxy given no loop makes its own and closes it with
itself.

Threading: sockets, timers and the proxies' state are touched on the loop thread only; other
threads go through `call` (runs a function there and waits for its result). A callback that
raises is logged (rate-limited) and counted in `errors`, and the loop goes on.
"""

from __future__ import annotations

import copy
import dataclasses
import heapq
import itertools
import logging
import math
import selectors
import socket
import threading
from array import array
from collections import Counter, deque
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

log = logging.getLogger("sitl.netfault.proxy")

MAX_WAIT_S = 0.5  # longest selector wait (wall s): a clock that jumps is seen at least this often
CALL_TIMEOUT_S = 10.0


def default_clock(speed: float) -> Callable[[], float]:
    """Simulation time starting at 0 now, at ``speed`` x real time (the Pacer's mapping)."""
    from sitl.pacing import Pacer
    return Pacer(speed, 0.0).sim_now


class TimerHandle:
    __slots__ = ("cancelled", "fn", "t_s")

    def __init__(self, t_s: float, fn: Callable[[], Any]):
        self.t_s, self.fn, self.cancelled = t_s, fn, False

    def cancel(self) -> None:
        self.cancelled = True


class ProxyLoop:
    """One thread running selector callbacks and timers in simulation time.

    clock: () -> simulation time, s (default: 0 at creation, running at ``speed``);
    speed: simulation seconds per wall second (converts due times into waits)."""

    def __init__(self, clock: Callable[[], float] | None = None, speed: float = 1.0, *,
                 name: str = "netfault-proxy"):
        if not (isinstance(speed, (int, float)) and math.isfinite(speed) and speed > 0):
            raise ValueError(f"proxy loop: speed must be a finite number > 0, got {speed!r}")
        self.speed = float(speed)
        self.clock = clock if clock is not None else default_clock(self.speed)
        self.name = name
        self.errors: Counter[str] = Counter()  # exceptions raised by callbacks, by type
        self._sel = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, self._on_wake)
        self._timers: list[tuple[float, int, TimerHandle]] = []
        self._seq = itertools.count()
        self._calls: deque[tuple[Callable[[], Any], Future]] = deque()
        self._interest: dict[socket.socket, tuple[int, Callable[[int], None]]] = {}
        self._stop = False
        self._closed = False
        self._close_lock = threading.Lock()
        self._last_log: dict[str, int] = {}
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    @classmethod
    def from_pacer(cls, pacer, *, name: str = "netfault-proxy") -> ProxyLoop:
        """A loop on a `sitl.pacing.Pacer`'s time (its ``sim_now`` and ``speed``)."""
        return cls(pacer.sim_now, pacer.speed, name=name)

    # ---- used on the loop thread -------------------------------------------------------
    def now(self) -> float:
        return self.clock()

    def at(self, t_s: float, fn: Callable[[], Any]) -> TimerHandle:
        """Run fn on the loop thread once simulation time t_s is due (FIFO among equal times)."""
        h = TimerHandle(float(t_s), fn)
        heapq.heappush(self._timers, (h.t_s, next(self._seq), h))
        return h

    def next_due(self) -> float:
        """Simulation time of the earliest pending timer (inf if none)."""
        while self._timers and self._timers[0][2].cancelled:
            heapq.heappop(self._timers)
        return self._timers[0][0] if self._timers else math.inf

    def interest(self, sock: socket.socket, events: int, fn: Callable[[int], None] | None = None) -> None:
        """Watch sock for events (EVENT_READ | EVENT_WRITE; 0 = stop watching), calling fn(mask)."""
        cur = self._interest.get(sock)
        if events == 0:
            if cur is not None:
                del self._interest[sock]
                try:
                    self._sel.unregister(sock)
                except (KeyError, ValueError, OSError):
                    pass
            return
        if fn is None:
            if cur is None:
                raise ValueError("proxy loop: a first interest needs a callback")
            fn = cur[1]
        if cur is None:
            self._sel.register(sock, events, fn)
        elif cur != (events, fn):
            self._sel.modify(sock, events, fn)
        self._interest[sock] = (events, fn)

    def forget(self, sock: socket.socket) -> None:
        """Stop watching sock and close it."""
        self.interest(sock, 0)
        try:
            sock.close()
        except OSError:
            pass

    def report(self, what: str, err: BaseException | str) -> None:
        """Count an error and log it (the first, then every 100th of a kind)."""
        kind = err if isinstance(err, str) else type(err).__name__
        self.errors[kind] += 1
        n = self.errors[kind]
        if n == 1 or n % 100 == 0:
            log.warning("%s: %s: %s (%d so far)", self.name, what, err, n)

    # ---- used from any thread ------------------------------------------------------------
    @property
    def on_loop_thread(self) -> bool:
        return threading.current_thread() is self._thread

    def call(self, fn: Callable[..., Any], *args: Any) -> Any:
        """Run fn(*args) on the loop thread and return its result (raise its exception)."""
        if self.on_loop_thread:
            return fn(*args)
        if self._stop:
            raise RuntimeError(f"{self.name}: the proxy loop is closed")
        fut: Future = Future()
        self._calls.append((lambda: fn(*args), fut))
        self.wake()
        return fut.result(timeout=CALL_TIMEOUT_S)

    def wake(self) -> None:
        try:
            self._wake_w.send(b"\0")
        except (BlockingIOError, OSError):
            pass  # already awake (buffer full) or closing

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Stop the thread, join it, close the selector (idempotent). Sockets the proxies
        registered are theirs to close (before this)."""
        with self._close_lock:
            if self._closed:
                return
            self._stop = True
            self.wake()
            if not self.on_loop_thread:
                self._thread.join(timeout=CALL_TIMEOUT_S)
            self._closed = True
            for _fn, fut in self._calls:
                fut.set_exception(RuntimeError(f"{self.name}: the proxy loop is closed"))
            self._calls.clear()
            for s in (self._wake_r, self._wake_w):
                s.close()
            self._sel.close()

    def __enter__(self) -> ProxyLoop:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- the thread ------------------------------------------------------------------------
    def _on_wake(self, _mask: int) -> None:
        try:
            while self._wake_r.recv(4096):
                pass
        except (BlockingIOError, InterruptedError):
            pass

    def _run(self) -> None:
        while not self._stop:
            due = self.next_due()
            if due == math.inf:
                timeout = MAX_WAIT_S
            else:
                timeout = min(max((due - self.clock()) / self.speed, 0.0), MAX_WAIT_S)
            try:
                events = self._sel.select(timeout)
            except OSError as e:  # pragma: no cover - a socket closed under the selector
                self.report("select", e)
                events = []
            # what fell due before these events happened goes first
            now = self.clock()
            while self._timers and (self._timers[0][0] <= now or self._timers[0][2].cancelled):
                _t, _n, h = heapq.heappop(self._timers)
                if h.cancelled:
                    continue
                try:
                    h.fn()
                except Exception as e:
                    self.report("timer", e)
            for key, mask in events:
                try:
                    key.data(mask)
                except Exception as e:
                    self.report("socket callback", e)
            while self._calls:
                fn, fut = self._calls.popleft()
                if fut.set_running_or_notify_cancel():
                    try:
                        fut.set_result(fn())
                    except BaseException as e:
                        fut.set_exception(e)


def truth_copy(truth, schedule: bool = True):
    """A copy of a `LinkTruth`; without ``schedule`` its per-packet schedule is left out (as
    ``record=False`` truths: ``recorded`` False): the counters only, at a cost that does not
    grow with the packets seen."""
    if schedule or not getattr(truth, "recorded", True):
        return copy.deepcopy(truth)
    out = copy.copy(truth)
    for f in dataclasses.fields(out):
        v = getattr(out, f.name)
        if isinstance(v, array):
            setattr(out, f.name, array(v.typecode))
    if hasattr(out, "recorded"):
        out.recorded = False
    return out


__all__ = ["ProxyLoop", "TimerHandle", "default_clock", "truth_copy"]
