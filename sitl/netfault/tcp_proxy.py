"""A live TCP fault proxy for a Zenoh session's link to the router (or any byte stream).

    zenoh client --connect--> [listen] TcpProxy --connect--> router (target)

Each accepted connection gets its own connection to ``target`` and bytes are copied both ways
(``up`` = client -> target, ``down`` = target -> client). Only the faults that make sense on
a stream apply:

* delay (+ jitter, any distribution of `FaultSpec`) and rate limit: each chunk read gets its
  delivery time from the direction's `LinkFault` (simulation time), and is released at
  max(its delivery time, the previous chunk's) so the byte order is kept. A direction holding
  more than ``max_buffer`` bytes stops reading (back-pressure; TCP never loses bytes), so a
  queue ``limit`` is not used.
* partitions (``partition=T1-T2`` in the spec, or `down()` / `up()` by hand): from T1 to T2
  the proxy forwards nothing in either direction, reads nothing and accepts nothing, but keeps
  every socket open -- a SILENT partition, which Zenoh only notices through its lease; after T2
  the held bytes flow again and waiting connections are accepted. With ``mode="reset"``
  the connections are reset (RST) at T1 instead and new ones are reset at once until T2 (a
  hard failure; the client reconnects after T2).

loss, duplicate, corrupt and reorder make no sense on a byte stream: a spec with them is
refused (ValueError).

    with TcpProxy("127.0.0.1:7447", spec="delay=20ms", name="zenoh:gs") as p:
        ... ZenohTransport(connect=[p.endpoint]) ...
        p.down(); ...; p.up()                    # a manual silent partition
        p.set("partition=30-32")                 # at run time

Time as in `UdpProxy`: ``clock()`` is simulation time, waits are (t - clock()) / speed; many
proxies (UDP and TCP) share one thread with ``loop=ProxyLoop(clock, speed)``.
"""

from __future__ import annotations

import copy
import dataclasses
import errno
import math
import selectors
import socket
import struct
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .proxyloop import ProxyLoop, TimerHandle, truth_copy
from .udp_proxy import as_rng, as_spec, parse_addr

MODES = ("silent", "reset")
READ_SIZE = 16384
DEFAULT_MAX_BUFFER = 4 << 20  # bytes held per direction and connection before reading stops
_R, _W = selectors.EVENT_READ, selectors.EVENT_WRITE

# FaultSpec fields a byte stream cannot honour, with their "no fault" value
_PACKET_ONLY = ("loss", "gemodel", "reorder", "gap", "duplicate", "corrupt")


def stream_spec(spec, name: str):
    """(spec for the timing model: no partitions, no queue limit; partition windows)."""
    fields = {f.name for f in dataclasses.fields(spec)}
    default = type(spec)()
    bad = [f for f in fields if f.startswith(_PACKET_ONLY) and getattr(spec, f) != getattr(default, f)]
    if bad:
        raise ValueError(f"{name}: {', '.join(sorted(bad))} cannot apply to a TCP stream "
                         "(use delay, rate and partition)")
    windows = tuple((float(a), float(b)) for a, b in (spec.partitions or ()))
    timing = dataclasses.replace(spec, partitions=default.partitions, limit=default.limit)
    return timing, windows


@dataclass
class TcpProxyStats:
    """accepted: connections accepted; active: open now; refused: connections reset because
    the target refused or a reset partition was on; resets: connections reset by a reset
    partition; bytes_up/down_in: read from client / target; bytes_up/down_out: written;
    partitioned: a partition is on now; partitions: partitions begun; truth_up/down: the
    timing models' `LinkTruth` (one "packet" per chunk read)."""

    accepted: int = 0
    active: int = 0
    refused: int = 0
    resets: int = 0
    bytes_up_in: int = 0
    bytes_up_out: int = 0
    bytes_down_in: int = 0
    bytes_down_out: int = 0
    partitioned: bool = False
    partitions: int = 0
    truth_up: object = None
    truth_down: object = None
    loop_errors: dict | None = None


class _Pipe:
    """One direction of one connection: src -> dst."""

    __slots__ = ("dst", "eof", "last_due", "out", "q", "queued", "shut", "src", "timer", "up")

    def __init__(self, src: socket.socket, dst: socket.socket, up: bool):
        self.src, self.dst, self.up = src, dst, up
        self.q: deque[tuple[float, bytes]] = deque()  # (release time, chunk), release times nondecreasing
        self.queued = 0  # bytes in q
        self.out = bytearray()  # released, not yet written
        self.last_due = -math.inf
        self.eof = False  # src has no more data
        self.shut = False  # dst shut down for writing
        self.timer: TimerHandle | None = None

    @property
    def held(self) -> int:
        return self.queued + len(self.out)


class _Conn:
    __slots__ = ("client", "closed", "connecting", "down", "on_client", "on_server", "server", "up")

    def __init__(self, client: socket.socket, server: socket.socket):
        self.client, self.server = client, server
        self.connecting = True
        self.up = _Pipe(client, server, True)
        self.down = _Pipe(server, client, False)
        self.closed = False


class TcpProxy:
    """TCP fault proxy (see the module doc).

    target: the server ("HOST:PORT", a tuple, or a Zenoh endpoint "tcp/HOST:PORT"); listen:
    where clients connect (port 0: a free port; ``addr`` / ``endpoint`` give it); spec:
    FaultSpec or its text (delay, jitter, rate, partition); mode: "silent" or "reset" for the
    spec's partitions; rng: numpy Generator or int seed (jitter); clock / speed / loop as
    `UdpProxy`; max_buffer: bytes held per direction and connection before reading stops;
    record: keep the timing models' per-chunk schedule (off: counters only)."""

    def __init__(self, target: str | tuple[str, int], *, listen: str | tuple[str, int] = ("127.0.0.1", 0),
                 spec=None, mode: str = "silent", rng: np.random.Generator | int | None = None,
                 clock: Callable[[], float] | None = None, speed: float = 1.0, loop: ProxyLoop | None = None,
                 name: str = "tcp", max_buffer: int = DEFAULT_MAX_BUFFER, backlog: int = 128,
                 record: bool = False):
        self.name = name
        self.target = parse_addr(_strip_endpoint(target), f"{name}: target")
        listen = parse_addr(_strip_endpoint(listen), f"{name}: listen")
        if mode not in MODES:
            raise ValueError(f"{name}: mode: expected one of {', '.join(MODES)}, got {mode!r}")
        if not isinstance(max_buffer, int) or max_buffer < 1:
            raise ValueError(f"{name}: max_buffer: expected an int >= 1, got {max_buffer!r}")
        self.mode = mode
        self.max_buffer = max_buffer
        timing, self._windows = stream_spec(as_spec(spec), name)
        from sitl.netfault import LinkFault
        r_up, r_down = as_rng(rng).spawn(2)
        self._lf_up = LinkFault(timing, rng=r_up, name=f"{name}:up", record=record)
        self._lf_down = LinkFault(timing, rng=r_down, name=f"{name}:down", record=record)
        self._manual: str | None = None  # mode of a manual partition, None if none
        self._part: str | None = None  # mode of the partition on now
        self._window_timers: list[TimerHandle] = []
        self._conns: set[_Conn] = set()
        self._st = TcpProxyStats()
        self._closed = False
        self._own_loop = loop is None
        self.loop = loop if loop is not None else ProxyLoop(clock, speed, name=f"proxy-{name}")
        self._lsock: socket.socket | None = None
        try:
            s = self._lsock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind(listen)
            s.listen(backlog)
            self._backlog = backlog
            s.setblocking(False)
            self.addr: tuple[str, int] = s.getsockname()
            self.loop.call(self._start)
        except BaseException as e:
            if self._lsock is not None:
                self._lsock.close()
            if self._own_loop:
                self.loop.close()
            if isinstance(e, OSError):
                raise OSError(e.errno, f"{name}: cannot listen on {listen[0]}:{listen[1]}: {e.strerror}") from None
            raise

    @property
    def endpoint(self) -> str:
        """The Zenoh endpoint to connect to the proxy: "tcp/HOST:PORT"."""
        return f"tcp/{self.addr[0]}:{self.addr[1]}"

    # ---- public -------------------------------------------------------------------------------
    def set(self, spec, mode: str | None = None) -> None:
        """Replace the fault (text or FaultSpec) from now on (simulation time ``clock()``);
        its partitions are simulation-time windows. mode: change the partition mode too."""
        if mode is not None and mode not in MODES:
            raise ValueError(f"{self.name}: mode: expected one of {', '.join(MODES)}, got {mode!r}")
        timing, windows = stream_spec(as_spec(spec), self.name)

        def apply():
            t = self.loop.now()
            if mode is not None:
                self.mode = mode
            self._lf_up.set(timing, t)
            self._lf_down.set(timing, t)
            self._windows = windows
            self._schedule_windows()
            self._update_partition()
        self.loop.call(apply)

    def down(self, mode: str = "silent") -> None:
        """Partition by hand until `up` (mode "silent" or "reset")."""
        if mode not in MODES:
            raise ValueError(f"{self.name}: mode: expected one of {', '.join(MODES)}, got {mode!r}")

        def apply():
            self._manual = mode
            self._update_partition()
        self.loop.call(apply)

    def up(self) -> None:
        """End a manual partition (a spec window still on stays on)."""
        def apply():
            self._manual = None
            self._update_partition()
        self.loop.call(apply)

    def stats(self, schedule: bool = True) -> TcpProxyStats:
        """A consistent snapshot, also after `close` (schedule: as `UdpProxy.stats`)."""
        def snap():
            st = copy.copy(self._st)
            st.active = len(self._conns)
            st.partitioned = self._part is not None
            st.truth_up = truth_copy(self._lf_up.truth, schedule)
            st.truth_down = truth_copy(self._lf_down.truth, schedule)
            st.loop_errors = dict(self.loop.errors)
            return st
        # after close (and its loop's) nothing changes any more: the final figures
        return snap() if self.loop.closed else self.loop.call(snap)

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Close every connection and the listening socket (and the loop if it is this
        proxy's own). Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            if not self.loop.closed:
                self.loop.call(self._shutdown)
        finally:
            if self._lsock is not None and self._lsock.fileno() >= 0:
                self._lsock.close()
            if self._own_loop:
                self.loop.close()

    def __enter__(self) -> TcpProxy:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return (f"TcpProxy({self.name} {self.addr[0]}:{self.addr[1]} -> "
                f"{self.target[0]}:{self.target[1]}{' closed' if self._closed else ''})")

    # ---- loop thread: partitions -----------------------------------------------------------------
    def _start(self) -> None:
        self.loop.interest(self._lsock, _R, self._on_accept)
        self._schedule_windows()
        self._update_partition()

    def _schedule_windows(self) -> None:
        for h in self._window_timers:
            h.cancel()
        now = self.loop.now()
        self._window_timers = [self.loop.at(t, self._update_partition)
                               for w in self._windows for t in w if t > now]

    def _update_partition(self) -> None:
        if self._closed:
            return
        now = self.loop.now()
        in_window = any(a <= now < b for a, b in self._windows)
        part = self._manual if self._manual is not None else (self.mode if in_window else None)
        if part == self._part:
            return
        self._part = part
        if part is not None:
            self._st.partitions += 1
            if part == "reset":
                for c in list(self._conns):
                    self._st.resets += 1
                    self._close_conn(c, reset=True)
        self.loop.interest(self._lsock, 0 if part == "silent" else _R, self._on_accept)
        try:  # silent: a full accept queue makes the kernel drop SYNs (the client retries them)
            self._lsock.listen(0 if part == "silent" else self._backlog)
        except OSError as e:
            self.loop.report(f"{self.name}: listen", e)
        for c in list(self._conns):
            self._pump(c, c.up)
            self._pump(c, c.down)

    # ---- loop thread: connections ----------------------------------------------------------------
    def _on_accept(self, _mask: int) -> None:
        self._update_partition()  # a window may have begun or ended since its timer ran
        if self._part == "silent":
            return
        for _ in range(64):
            try:
                cs, _addr = self._lsock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as e:
                self.loop.report(f"{self.name}: accept", e)
                return
            self._st.accepted += 1
            cs.setblocking(False)
            if self._part == "reset":
                self._st.refused += 1
                _reset(cs)
                continue
            ss = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            ss.setblocking(False)
            for s in (cs, ss):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            err = ss.connect_ex(self.target)
            if err not in (0, errno.EINPROGRESS, errno.EWOULDBLOCK):
                self._st.refused += 1
                self.loop.report(f"{self.name}: connect {self.target[0]}:{self.target[1]}", os_error(err))
                ss.close()
                _reset(cs)
                continue
            c = _Conn(cs, ss)
            c.on_client = lambda m, c=c: self._on_client(c, m)
            c.on_server = lambda m, c=c: self._on_server(c, m)
            self._conns.add(c)
            self._interest(c)

    def _interest(self, c: _Conn) -> None:
        if c.closed:
            return
        live = self._part is None
        ev_c = ev_s = 0
        if c.connecting:
            ev_s = _W
        else:
            if live and not c.down.eof and c.down.held < self.max_buffer:
                ev_s |= _R
            if live and c.up.out:
                ev_s |= _W
            if live and c.down.out:
                ev_c |= _W
        if live and not c.up.eof and c.up.held < self.max_buffer:
            ev_c |= _R
        self.loop.interest(c.client, ev_c, c.on_client)
        self.loop.interest(c.server, ev_s, c.on_server)

    def _on_client(self, c: _Conn, mask: int) -> None:
        if c.closed:  # closed by an earlier event of the same select round
            return
        if mask & _R:
            self._read(c, c.up)
        if mask & _W and not c.closed:
            self._pump(c, c.down)

    def _on_server(self, c: _Conn, mask: int) -> None:
        if c.closed:  # closed by an earlier event of the same select round
            return
        if c.connecting:
            err = c.server.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
            if err:
                self._st.refused += 1
                self.loop.report(f"{self.name}: connect {self.target[0]}:{self.target[1]}", os_error(err))
                self._close_conn(c, reset=True)
                return
            c.connecting = False
            self._pump(c, c.up)
            self._interest(c)
            return
        if mask & _R:
            self._read(c, c.down)
        if mask & _W and not c.closed:
            self._pump(c, c.up)

    def _read(self, c: _Conn, p: _Pipe) -> None:
        if self._windows:
            self._update_partition()
            if c.closed or self._part is not None:
                return
        try:
            data = p.src.recv(READ_SIZE)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:  # reset by the peer
            self._close_conn(c, reset=True)
            return
        if not data:
            p.eof = True
        else:
            t = self.loop.now()
            if p.up:
                self._st.bytes_up_in += len(data)
            else:
                self._st.bytes_down_in += len(data)
            lf = self._lf_up if p.up else self._lf_down
            for t_due, chunk in lf.process(t, data):
                due = max(t_due, p.last_due)
                p.last_due = due
                p.q.append((due, chunk))
                p.queued += len(chunk)
        self._pump(c, p)

    def _pump(self, c: _Conn, p: _Pipe) -> None:
        """Release the due chunks, write what the socket takes, propagate the end of stream,
        and arrange to be called again (timer for the next chunk, socket interest)."""
        if c.closed:
            return
        if self._part is None:
            now = self.loop.now()
            while p.q and p.q[0][0] <= now:
                _t, chunk = p.q.popleft()
                p.queued -= len(chunk)
                p.out += chunk
            if p.out and not c.connecting:
                try:
                    n = p.dst.send(p.out)
                except (BlockingIOError, InterruptedError):
                    n = 0
                except OSError:
                    self._close_conn(c, reset=True)
                    return
                del p.out[:n]
                if p.up:
                    self._st.bytes_up_out += n
                else:
                    self._st.bytes_down_out += n
            if p.eof and not p.held and not p.shut and not c.connecting:
                p.shut = True
                try:
                    p.dst.shutdown(socket.SHUT_WR)
                except OSError:
                    pass
                if c.up.shut and c.down.shut:
                    self._close_conn(c)
                    return
            if p.q and (p.timer is None or p.timer.t_s != p.q[0][0]):
                if p.timer is not None:
                    p.timer.cancel()
                p.timer = self.loop.at(p.q[0][0], lambda c=c, p=p: self._on_timer(c, p))
        self._interest(c)

    def _on_timer(self, c: _Conn, p: _Pipe) -> None:
        p.timer = None
        self._pump(c, p)

    def _close_conn(self, c: _Conn, reset: bool = False) -> None:
        if c.closed:
            return
        c.closed = True
        self._conns.discard(c)
        for p in (c.up, c.down):
            if p.timer is not None:
                p.timer.cancel()
        for s in (c.client, c.server):
            self.loop.interest(s, 0)
            if reset:
                _reset(s)
            else:
                s.close()

    def _shutdown(self) -> None:
        for h in self._window_timers:
            h.cancel()
        for c in list(self._conns):
            self._close_conn(c, reset=True)
        if self._lsock is not None:
            self.loop.forget(self._lsock)


def _strip_endpoint(addr):
    if isinstance(addr, str) and addr.startswith("tcp/"):
        return addr[4:]
    return addr


def os_error(err: int) -> OSError:
    import os
    return OSError(err, os.strerror(err))


def _reset(s: socket.socket) -> None:
    """Close with an RST (SO_LINGER 0), not a FIN."""
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    except OSError:
        pass
    try:
        s.close()
    except OSError:
        pass


__all__ = ["MODES", "TcpProxy", "TcpProxyStats"]
