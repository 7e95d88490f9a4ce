"""A live UDP fault proxy for a MAVLink link (vehicle endpoint <-> GCS), both directions.

    vehicle endpoint --(up)--> [listen]  UdpProxy  [upstream] --(up)--> GCS (target)
    vehicle endpoint <-(down)- [listen]            [upstream] <-(down)- GCS

The vehicle sends to ``proxy.addr`` instead of the GCS; the proxy forwards each datagram to
``target`` from its own upstream socket (one per proxy, so the GCS sees one address per
vehicle) and sends what comes back on that socket to the last address that sent to
``listen`` (or to a fixed ``client``). Each direction has its own `LinkFault`: ``up`` =
client -> target (vehicle -> GCS), ``down`` = target -> client (GCS -> vehicle). Every
datagram goes through ``LinkFault.process(t_sim, payload)`` and each copy it returns is sent
when its delivery time (simulation time) is due.

    with UdpProxy(("127.0.0.1", 14550), up="loss=10%", down="delay=50ms", rng=7) as p:
        ... vehicle endpoint with gcs=p.addr ...
        p.set(up="loss=30%")                        # at run time
        st = p.stats()                              # st.up.received, st.up.forwarded, st.up.truth, st.up.tap

Time: ``clock()`` gives simulation time (the launcher passes its Pacer's ``sim_now``), and a
send due at simulation time t waits ``(t - clock()) / speed`` wall seconds. Many proxies
share one thread with ``loop=ProxyLoop(clock, speed)`` (see `sitl.netfault.proxyloop`).

The receiver-side tap (``tap=True``) parses each forwarded datagram as the receiver would
(pymavlink, MAVLink 2 ardupilotmega dialect) and keeps, per (sysid, compid), the sequence
statistics of the uint8 MAVLink seq (unwrapped, then `sitl.bus.transport.SequenceTracker`):
received, missing (loss), duplicates, out_of_order, and the packets its CRC rejected. So the
link statistics a receiver can see are comparable with the injected `LinkTruth`. It parses
one datagram at a time, as the vehicle endpoint does; a receiver whose parser runs across
datagrams (mavutil's) can lose good packets after a corrupted one (measured: at corrupt=20 %
mavutil accepted 759 of the 792 intact HEARTBEATs), never accept a corrupted one.

Cost (measured, 200 proxies on one loop at 20 Hz each = 4000 datagrams/s, one direction,
load ~5 on 2 cores): ~27 us of CPU per datagram without the tap, ~50 us with
"loss=10% delay=50ms~10ms", ~80 us with the tap (pymavlink's pure-Python parse and CRC):
10 %, 17 % and 28 % of a core. For large swarms pass ``tap=False``.
"""

from __future__ import annotations

import copy
import ipaddress
import logging
import selectors
import socket
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from sitl.bus.transport import SeqCounters, SequenceTracker

from .proxyloop import ProxyLoop, truth_copy

log = logging.getLogger("sitl.netfault.proxy")

MAX_DATAGRAM = 65535
READ_BATCH = 64  # datagrams read per readiness event (fairness between proxies on one loop)
RCVBUF = 1 << 20  # asked for (the kernel caps it at net.core.rmem_max): bursts wait, not drop


def parse_addr(addr: str | tuple[str, int], what: str = "address") -> tuple[str, int]:
    """("host", port) from "HOST:PORT" or a tuple; ValueError (one line) otherwise."""
    if isinstance(addr, str):
        host, sep, port = addr.rpartition(":")
        if not sep or not host:
            raise ValueError(f"{what}: expected HOST:PORT, got {addr!r}")
        addr = (host.strip("[]"), port)
    try:
        host, port = addr
        port = int(port)
    except (TypeError, ValueError):
        raise ValueError(f"{what}: expected HOST:PORT, got {addr!r}") from None
    if not isinstance(host, str) or not 0 <= port <= 65535:
        raise ValueError(f"{what}: expected HOST:PORT with a port 0..65535, got {addr!r}")
    return host, port


def _bind_host_for(host: str) -> str:
    """Where to bind a socket that sends to host: loopback for a loopback host (nothing
    outside sees it), any interface otherwise."""
    try:
        return "127.0.0.1" if ipaddress.ip_address(socket.gethostbyname(host)).is_loopback else "0.0.0.0"
    except (OSError, ValueError):
        return "0.0.0.0"


def as_spec(spec):
    """A FaultSpec from a FaultSpec, its text, or None (no fault)."""
    from sitl.netfault import FaultSpec, parse_spec
    if spec is None:
        return FaultSpec()
    if isinstance(spec, str):
        return parse_spec(spec)
    if isinstance(spec, FaultSpec):
        return spec
    raise TypeError(f"expected a FaultSpec or its text, got {type(spec).__name__}")


def as_rng(rng: np.random.Generator | int | None) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    if rng is None or (isinstance(rng, (int, np.integer)) and not isinstance(rng, bool)):
        return np.random.default_rng(0 if rng is None else int(rng))
    raise TypeError(f"rng: expected a numpy Generator or an int seed, got {type(rng).__name__}")


# ---- the receiver-side MAVLink tap ---------------------------------------------------------

@dataclass
class TapStats:
    """What a MAVLink receiver sees of a link. ``seq``: totals over every (sysid, compid);
    ``sources``: per (sysid, compid). ``missing`` counts seqs skipped and not (yet) arrived:
    losses at the very end of a stream are invisible until a later packet arrives."""

    datagrams: int = 0
    messages: int = 0  # accepted by the parser (CRC good, known message)
    bad_crc: int = 0  # rejected by the CRC check
    bad_other: int = 0  # other framing errors (prefix, length, flags)
    unknown: int = 0  # unknown message id (pymavlink cannot check their CRC)
    truncated: int = 0  # datagrams ending inside a packet
    rejected_datagrams: int = 0  # datagrams from which no message was accepted
    seq: SeqCounters = field(default_factory=SeqCounters)
    sources: dict[tuple[int, int], SeqCounters] = field(default_factory=dict)


class MavlinkTap:
    """Parses datagrams as a MAVLink receiver does, one datagram at a time, and keeps the
    sequence statistics of what it accepted."""

    def __init__(self) -> None:
        from pymavlink.dialects.v20 import ardupilotmega as mavlink
        self._mavlink = mavlink
        self._mav = mavlink.MAVLink(None)
        self._mav.robust_parsing = True
        self._tracker = SequenceTracker(window=256)
        self._max_ext: dict[tuple[int, int], int] = {}
        self.stats = TapStats()

    def _reset_parser(self) -> None:
        m = self._mav
        m.buf = bytearray()
        m.buf_index = 0
        m.expected_length = self._mavlink.HEADER_LEN_V1 + 2

    def feed(self, data: bytes) -> list:
        """Parse one datagram; returns the messages accepted."""
        st = self.stats
        st.datagrams += 1
        try:
            msgs = self._mav.parse_buffer(data) or []
        except Exception as e:  # robust parsing should not raise; never let the tap break a link
            log.debug("mavlink tap: %s", e)
            msgs = []
        if self._mav.buf_len() > 0:
            st.truncated += 1
        self._reset_parser()
        good = []
        for m in msgs:
            if isinstance(m, self._mavlink.MAVLink_bad_data):
                if "CRC" in m.reason:
                    st.bad_crc += 1
                else:
                    st.bad_other += 1
            elif isinstance(m, self._mavlink.MAVLink_unknown):
                st.unknown += 1
            else:
                good.append(m)
        if not good:
            st.rejected_datagrams += 1
        for m in good:
            st.messages += 1
            src = (m.get_srcSystem(), m.get_srcComponent())
            seq = m.get_seq()
            last = self._max_ext.get(src)
            # unwrap the uint8 seq to the value nearest the highest seen
            ext = seq if last is None else last + ((seq - last + 128) % 256) - 128
            if last is None or ext > last:
                self._max_ext[src] = ext
            self._tracker.update(f"{src[0]}/{src[1]}", ext)
        return good

    def snapshot(self) -> TapStats:
        st = copy.deepcopy(self.stats)
        st.seq = copy.copy(self._tracker.total)
        st.sources = {k: copy.copy(self._tracker.counters(f"{k[0]}/{k[1]}")) for k in self._max_ext}
        return st


# ---- the proxy -------------------------------------------------------------------------------

@dataclass
class DirectionStats:
    """One direction of a proxy. received: datagrams read; forwarded: copies sent;
    send_errors: copies the socket refused; no_client: down datagrams with no client address
    yet (not offered to the fault model); pending: copies waiting for their delivery time.
    truth: the `LinkTruth` of the direction's fault model; tap: what the receiver sees."""

    received: int = 0
    forwarded: int = 0
    send_errors: int = 0
    no_client: int = 0
    pending: int = 0
    truth: object = None
    tap: TapStats | None = None


@dataclass
class UdpProxyStats:
    up: DirectionStats
    down: DirectionStats
    client: tuple[str, int] | None
    loop_errors: dict[str, int]


class _Direction:
    def __init__(self, name: str, spec, rng: np.random.Generator, tap: bool, record: bool):
        from sitl.netfault import LinkFault
        self.fault = LinkFault(spec, rng=rng, name=name, record=record)
        self.tap = MavlinkTap() if tap else None
        self.received = self.forwarded = self.send_errors = self.no_client = self.pending = 0

    def stats(self, schedule: bool) -> DirectionStats:
        return DirectionStats(self.received, self.forwarded, self.send_errors, self.no_client, self.pending,
                              truth_copy(self.fault.truth, schedule), self.tap.snapshot() if self.tap else None)


class UdpProxy:
    """UDP fault proxy (see the module doc).

    target: where ``up`` traffic goes ("HOST:PORT" or a tuple); listen: the address clients
    send to (port 0: a free port, read ``addr``); up / down: FaultSpec or its text (None: no
    fault); client: a fixed address for ``down`` traffic (default: the last sender);
    rng: a numpy Generator or an int seed (each direction gets its own child stream);
    clock / speed: simulation time and its speed (default: 0 now, real time), or
    loop: a shared `ProxyLoop` (its clock and speed are used); name: the link name
    (e.g. "mav:3"); tap: keep the receiver-side MAVLink statistics; record: keep the truths'
    per-packet schedule (``LinkFault(record=)``: ~26 bytes a packet; False for long runs)."""

    def __init__(self, target: str | tuple[str, int], *, listen: str | tuple[str, int] = ("127.0.0.1", 0),
                 up=None, down=None, client: str | tuple[str, int] | None = None,
                 rng: np.random.Generator | int | None = None, clock: Callable[[], float] | None = None,
                 speed: float = 1.0, loop: ProxyLoop | None = None, name: str = "udp", tap: bool = True,
                 record: bool = True):
        self.name = name
        self.target = parse_addr(target, f"{name}: target")
        self.client = parse_addr(client, f"{name}: client") if client is not None else None
        self._fixed_client = client is not None
        listen = parse_addr(listen, f"{name}: listen")
        up, down = as_spec(up), as_spec(down)
        r_up, r_down = as_rng(rng).spawn(2)
        self._up = _Direction(f"{name}:up", up, r_up, tap, record)
        self._down = _Direction(f"{name}:down", down, r_down, tap, record)
        self._own_loop = loop is None
        self.loop = loop if loop is not None else ProxyLoop(clock, speed, name=f"proxy-{name}")
        self._closed = False
        self._sock = self._up_sock = None
        try:
            self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._sock.bind(listen)
            self._up_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._up_sock.bind((_bind_host_for(self.target[0]), 0))
            for s in (self._sock, self._up_sock):
                s.setblocking(False)
                try:
                    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF)
                except OSError:
                    pass
            self.addr: tuple[str, int] = self._sock.getsockname()
            self.upstream_addr: tuple[str, int] = self._up_sock.getsockname()
            self.loop.call(self._register)
        except BaseException as e:
            self._release()
            if self._own_loop:
                self.loop.close()
            if isinstance(e, OSError):
                raise OSError(e.errno, f"{name}: cannot listen on {listen[0]}:{listen[1]}: {e.strerror}") from None
            raise

    # ---- public ---------------------------------------------------------------------------
    def set(self, up=None, down=None) -> None:
        """Change the fault of one or both directions (text or FaultSpec); applies to
        datagrams received from now on (simulation time ``clock()``)."""
        specs = [(d, as_spec(s)) for d, s in ((self._up, up), (self._down, down)) if s is not None]

        def apply():
            t = self.loop.now()
            for d, s in specs:
                d.fault.set(s, t)
        self.loop.call(apply)

    def stats(self, schedule: bool = True) -> UdpProxyStats:
        """A consistent snapshot (also after `close`: the final figures). schedule=False: the
        truths without their per-packet schedule (counters only), cheap however long the run."""
        def snap():
            return UdpProxyStats(self._up.stats(schedule), self._down.stats(schedule), self.client,
                                 dict(self.loop.errors))
        # after close (and its loop's) nothing changes any more: the final figures
        return snap() if self.loop.closed else self.loop.call(snap)

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Stop forwarding, close both sockets (and the loop if it is this proxy's own);
        copies still waiting for their delivery time are discarded. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            if not self.loop.closed:
                self.loop.call(self._release)
        finally:
            self._release()
            if self._own_loop:
                self.loop.close()

    def __enter__(self) -> UdpProxy:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return (f"UdpProxy({self.name} {self.addr[0]}:{self.addr[1]} -> "
                f"{self.target[0]}:{self.target[1]}{' closed' if self._closed else ''})")

    # ---- loop thread ---------------------------------------------------------------------------
    def _register(self) -> None:
        self.loop.interest(self._sock, selectors.EVENT_READ, self._on_client)
        self.loop.interest(self._up_sock, selectors.EVENT_READ, self._on_target)

    def _release(self) -> None:
        for s in (self._sock, self._up_sock):
            if s is None:
                continue
            if self.loop.on_loop_thread and not self.loop.closed:
                self.loop.forget(s)
            else:
                try:
                    s.close()
                except OSError:
                    pass

    def _read(self, sock: socket.socket):
        for _ in range(READ_BATCH):
            try:
                yield sock.recvfrom(MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as e:  # e.g. ECONNREFUSED reported by an earlier ICMP
                if self._closed:
                    return
                self.loop.report(f"{self.name}: recv", e)
                return

    def _on_client(self, _mask: int) -> None:
        for data, addr in self._read(self._sock):
            self._up.received += 1
            if not self._fixed_client:
                self.client = addr
            self._offer(self._up, data, self._up_sock, self.target)

    def _on_target(self, _mask: int) -> None:
        for data, _addr in self._read(self._up_sock):
            d = self._down
            d.received += 1
            if self.client is None:
                d.no_client += 1
                continue
            self._offer(d, data, self._sock, None)

    def _offer(self, d: _Direction, data: bytes, sock: socket.socket, dest) -> None:
        t = self.loop.now()
        out = d.fault.process(t, data)
        first_due = self.loop.next_due()
        for t_due, payload in out:
            if t_due <= t and t_due < first_due:
                self._send(d, sock, dest, payload)
            else:
                d.pending += 1
                self.loop.at(t_due, lambda p=payload: self._due(d, sock, dest, p))

    def _due(self, d: _Direction, sock, dest, payload: bytes) -> None:
        d.pending -= 1
        if not self._closed:
            self._send(d, sock, dest, payload)

    def _send(self, d: _Direction, sock: socket.socket, dest, payload: bytes) -> None:
        dest = dest if dest is not None else self.client
        try:
            sock.sendto(payload, dest)
        except OSError as e:
            d.send_errors += 1
            self.loop.report(f"{self.name}: send to {dest[0]}:{dest[1]}", e)
            return
        d.forwarded += 1
        if d.tap is not None:
            d.tap.feed(payload)


__all__ = ["DirectionStats", "MavlinkTap", "TapStats", "UdpProxy", "UdpProxyStats", "parse_addr"]
