"""A vehicle's endpoint reading its socket: datagrams, frames, signature checks, the kernel's
drop counter, and the drain of many sockets under one time budget.

Input: each step drains the socket (no fixed cap; EndpointGroup.step takes a time budget
and shares it over the sockets in rounds of a few datagrams); the socket asks the kernel for a
large receive buffer and for its drop counter (SO_RXQ_OVFL on every datagram, SO_MEMINFO after
each drain), so datagrams the kernel dropped are counted too.

Counters.  ``datagrams``: one verdict per datagram received -- ``accepted`` (nothing in it
failed), or ``rejected[reason]`` (the first reason, in datagram order, one of
DATAGRAM_REJECT_REASONS) -- and ``kernel_dropped``: accepted + sum(rejected) + kernel_dropped
is every datagram sent to us once the socket is drained.  ``counters``: per frame / per
request (REJECT_REASONS: frame and protocol rejects, e.g. 5 garbage runs in one datagram count
5 there and 1 in ``datagrams``), TRAFFIC_COUNTERS the rest.  An exception inside a handler is
counted (``handler_errors``, ``last_error``), never raised.
"""
from __future__ import annotations

import socket
import sys
from typing import Callable, Sequence

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.mavlink.framing import frame_datagram, signature_timestamp

from .constants import (_ANC_SIZE, _FAIR_BATCH, _MAX_PEERS, _MAX_RECV_ERRORS, _RECV_SIZE, _SK_MEMINFO_DROPS,
                        _SO_MEMINFO, _SO_RXQ_OVFL)


class DatagramInput:
    """VehicleEndpoint's input side (a part of VehicleEndpoint, not usable alone)."""

    def poll(self, max_datagrams: int | None = None) -> int:
        """Read and handle the datagrams waiting, at most max_datagrams (None: until the socket
        is empty); returns how many were read.  ``_drained``: the socket was read empty."""
        n = errors = 0
        recv, sock_level = self.sock.recvmsg, socket.SOL_SOCKET
        self._drained = False
        while max_datagrams is None or n < max_datagrams:
            try:
                data, anc, _flags, addr = recv(_RECV_SIZE, _ANC_SIZE)
            except (BlockingIOError, InterruptedError):
                self._drained = True
                break
            except OSError:  # e.g. ICMP errors of our own sends queued on the socket: not input
                self.counters["send_errors"] += 1
                errors += 1
                if errors >= _MAX_RECV_ERRORS:
                    break
                continue
            for level, kind, v in anc:
                if kind == _SO_RXQ_OVFL and level == sock_level and len(v) >= 4:
                    self._note_drops(int.from_bytes(v[:4], sys.byteorder))
            n += 1
            self.handle_datagram(data, addr)
        return n

    def _note_drops(self, count: int) -> None:
        """The socket's drop counter (u32, cumulative, stamped on each datagram as it was queued:
        an older stamp can come after a newer reading, and is ignored)."""
        d = (count - self._drops_seen) & 0xFFFFFFFF
        if 0 < d < 0x80000000:
            self._drops_seen = count & 0xFFFFFFFF
            self.datagrams["kernel_dropped"] += d

    def read_kernel_drops(self) -> None:
        """Catch up with the kernel's drop counter now (SO_MEMINFO; datagrams dropped after the
        last one queued carry no SO_RXQ_OVFL stamp until another arrives)."""
        if not self._drops_readable or self._closed:
            return
        try:
            v = self.sock.getsockopt(socket.SOL_SOCKET, _SO_MEMINFO, 4 * (_SK_MEMINFO_DROPS + 1))
        except OSError:
            self._drops_readable = False
            return
        if len(v) >= 4 * (_SK_MEMINFO_DROPS + 1):
            self._note_drops(int.from_bytes(v[4 * _SK_MEMINFO_DROPS:4 * (_SK_MEMINFO_DROPS + 1)], sys.byteorder))

    def handle_datagram(self, data: bytes, addr) -> str:
        """Handle one datagram; returns its one verdict ("accepted", or the first reason it failed),
        counted in ``datagrams``.  Its frames and rejects are counted one by one in ``counters``."""
        c = self.counters
        c["rx_datagrams"] += 1
        c["rx_bytes"] += len(data)
        verdict = None if data else "empty"
        for item in frame_datagram(data):
            if isinstance(item, str):
                self._count(item)
                r = item
            else:
                r = self._handle_frame(item, addr)
            if verdict is None and r is not None:
                verdict = r
        if verdict is None:
            self.datagrams["accepted"] += 1
            return "accepted"
        self.datagrams["rejected"][verdict] += 1
        return verdict

    def _reject(self, reason: str) -> str:
        self.counters[reason] += 1
        return reason

    def _handle_frame(self, fr, addr) -> str | None:
        """None if the frame is accepted (then handled), else why it was rejected (counted)."""
        if fr.incompat_flags & ~mavlink.MAVLINK_IFLAG_SIGNED:
            return self._reject("unsupported_flags")  # the spec: drop frames with unknown incompat flags
        if fr.msgid not in mavlink.mavlink_map:
            # the CRC cannot be checked without the message's CRC_EXTRA: unknown is unknown
            return self._reject("unknown_msgid")
        try:
            msg = self._decoder.decode(bytearray(fr.buf))
        except mavlink.MAVError as e:
            return self._reject("bad_crc" if "CRC" in str(e) else "malformed")
        except Exception:  # pymavlink on hostile bytes: never let it take the process down
            return self._reject("malformed")
        if self._signer is not None:
            reason = self._signer.check(fr, self.mav.signing.timestamp, self._future_limit)
            if reason is not None:
                return self._reject(reason)
            ts = signature_timestamp(fr.buf)
            if self._state_file is not None and ts > self._reserved:  # on disk before it counts
                self._reserve(ts)
            if ts > self.mav.signing.timestamp:  # a peer ahead, within the future window: follow it
                self.mav.signing.timestamp = ts
        self.counters["received"] += 1
        if self._tlog is not None:
            self._tlog.write(self._unix_s, fr.buf)
        ts_ = getattr(msg, "target_system", 0)
        tc_ = getattr(msg, "target_component", 0)
        if (ts_ not in (0, self.sysid)) or (tc_ not in (0, self.compid)):
            self.counters["not_for_us"] += 1  # valid traffic, for someone else: accepted, not acted on
            return None
        if len(addr) == 2:  # UDP; a TCP client ("tcp", host, port) is a peer while it is connected
            if addr not in self._peers and addr != self.gcs and len(self._peers) >= _MAX_PEERS:
                oldest = min(self._peers, key=self._peers.get)
                del self._peers[oldest]
            self._peers[addr] = self._t if self._t is not None else 0.0
        h = self._handlers.get(msg.get_type())
        if h is not None:
            try:
                h(msg, addr)
            except Exception as e:  # a bug met by some input must not stop the vehicle: count, keep one line
                self.counters["handler_errors"] += 1
                self.last_error = f"{msg.get_type()} from {addr[0]}:{addr[1]}: {type(e).__name__}: {e}"
        return None


def _drain(endpoints: Sequence[DatagramInput], budget_s: float | None, timer: Callable[[], float],
           start: int) -> None:
    """Read the endpoints' sockets until each is empty or the budget is spent: in rounds of
    _FAIR_BATCH datagrams per socket, starting at endpoints[start % n], so a flooded port takes
    its share and no more; then catch up with each socket's kernel drop counter."""
    n = len(endpoints)
    if not n:
        return
    k = start % n
    active = list(endpoints[k:]) + list(endpoints[:k])
    deadline = None if budget_s is None else timer() + max(0.0, float(budget_s))
    batch = None if deadline is None and n == 1 else _FAIR_BATCH
    out_of_time = False
    while active and not out_of_time:
        nxt = []
        for ep in active:
            ep.poll(batch)
            if not ep._drained:
                nxt.append(ep)
            if deadline is not None and timer() >= deadline:
                out_of_time = True
                break
        active = nxt
    for ep in endpoints:
        if not ep._drained:
            ep.counters["input_deferred"] += 1  # left for the next step (the kernel queue holds it, or drops and counts)
        ep.read_kernel_drops()
