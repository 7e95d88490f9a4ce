"""A vehicle's TCP server (ArduPilot SITL's SERIAL0: 5760 + 10 x instance) beside its UDP link.

Non-blocking, several clients, stepped with the endpoint: ``poll()`` accepts new clients,
sends what is queued for each and returns the bytes each sent (a MAVLink byte stream: feed
it to a `StreamFramer` per client); ``send(addr, buf)`` queues a frame for one client,
``write(buf)`` for every client; ``close()`` closes every socket (the port is free at once:
SO_REUSEADDR). A client whose queue passes `MAX_BACKLOG_BYTES` (it does not read) is
dropped, counted; a client that closes or resets is dropped, counted. Each poll reads at most
`MAX_READ_BYTES` per client: a flooding client is slowed down by TCP's own flow control
instead of taking the vehicle's time. Never blocks, never raises on a peer's behaviour.
"""
from __future__ import annotations

import socket

from sitl.mavlink.framing import CRC_LEN, HEADER_LEN_V1, HEADER_LEN_V2, IFLAG_SIGNED, SIGNATURE_LEN, STX_V1, STX_V2, Frame

__all__ = ["TcpServer", "StreamFramer", "SERIAL0_BASE_PORT", "MAX_CLIENTS", "MAX_BACKLOG_BYTES", "MAX_READ_BYTES"]

SERIAL0_BASE_PORT = 5760
MAX_CLIENTS = 8
MAX_BACKLOG_BYTES = 4 << 20  # queued for one client and not yet taken by its socket: more, it is dropped
MAX_READ_BYTES = 256 << 10  # read from one client per poll
_RECV = 65536


class StreamFramer:
    """MAVLink frames out of a TCP byte stream: ``feed(data)`` -> the items completed so far,
    each a sitl.mavlink.framing.Frame or a reject reason ('garbage': one per run of bytes
    that start no frame); a frame cut by the end of data waits for the rest."""

    def __init__(self):
        self.buf = b""
        self._in_garbage = False  # the last read ended inside a run of garbage

    def feed(self, data: bytes) -> list:
        buf = self.buf + bytes(data)
        items: list = []
        n, i = len(buf), 0
        while i < n:
            b = buf[i]
            if b == STX_V2:
                if n - i < HEADER_LEN_V2:
                    break
                total = HEADER_LEN_V2 + buf[i + 1] + CRC_LEN + (SIGNATURE_LEN if buf[i + 2] & IFLAG_SIGNED else 0)
                if n - i < total:
                    break
                msgid = buf[i + 7] | (buf[i + 8] << 8) | (buf[i + 9] << 16)
                items.append(Frame(buf[i:i + total], 2, buf[i + 2], msgid, buf[i + 5], buf[i + 6]))
                i += total
            elif b == STX_V1:
                if n - i < HEADER_LEN_V1:
                    break
                total = HEADER_LEN_V1 + buf[i + 1] + CRC_LEN
                if n - i < total:
                    break
                items.append(Frame(buf[i:i + total], 1, 0, buf[i + 5], buf[i + 3], buf[i + 4]))
                i += total
            else:
                j2, j1 = buf.find(b"\xfd", i + 1), buf.find(b"\xfe", i + 1)
                i = min(j for j in (j2, j1, n) if j >= 0)
                if not self._in_garbage:  # one run, even when it spans reads
                    items.append("garbage")
                self._in_garbage = i == n
                continue
            self._in_garbage = False
        self.buf = buf[i:]
        return items


class _Client:
    __slots__ = ("sock", "addr", "out")

    def __init__(self, sock, addr):
        self.sock, self.addr, self.out = sock, addr, bytearray()


class TcpServer:
    """The server (module docstring). host, port: where it listens (port 0: any free one, read
    ``addr``); max_clients: more connections are accepted and closed at once (counted)."""

    def __init__(self, host: str = "127.0.0.1", port: int = SERIAL0_BASE_PORT, max_clients: int = MAX_CLIENTS):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self.sock.bind((host, int(port)))
            self.sock.listen(max_clients)
            self.sock.setblocking(False)
        except OSError:
            self.sock.close()
            raise
        self.addr = self.sock.getsockname()
        self.max_clients = int(max_clients)
        self._clients: dict[tuple, _Client] = {}
        self.counters = {"accepted": 0, "refused": 0, "closed": 0, "dropped": 0, "rx_bytes": 0, "tx_bytes": 0}

    @property
    def clients(self):
        """The connected clients' addresses (a live view: copy it to keep it)."""
        return self._clients.keys()

    def fileno(self) -> int:
        return self.sock.fileno()

    def poll(self) -> list[tuple[tuple, bytes]]:
        """Accept waiting clients, send what is queued; return [(client address, bytes received)]."""
        while True:
            try:
                c, a = self.sock.accept()
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                break
            if len(self._clients) >= self.max_clients:
                self.counters["refused"] += 1
                c.close()
                continue
            c.setblocking(False)
            try:
                c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            except OSError:
                pass
            self._clients[a] = _Client(c, a)
            self.counters["accepted"] += 1
        out = []
        for a, cl in list(self._clients.items()):
            self._flush(cl)
            if a not in self._clients:
                continue
            chunks, got = [], 0
            while got < MAX_READ_BYTES:
                try:
                    d = cl.sock.recv(_RECV)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:
                    d = b""
                if not d:  # orderly close or reset
                    self._drop(a, "closed")
                    break
                chunks.append(d)
                got += len(d)
            if chunks:
                data = b"".join(chunks)
                self.counters["rx_bytes"] += len(data)
                out.append((a, data))
        return out

    def send(self, addr, buf: bytes) -> bool:
        """Queue buf for the client at addr and send what its socket takes now; False if there
        is no such client (any more)."""
        cl = self._clients.get(tuple(addr))
        if cl is None:
            return False
        cl.out += buf
        self._flush(cl)
        return tuple(addr) in self._clients

    def write(self, buf: bytes) -> None:
        """Queue buf for every client (see send)."""
        for a in list(self._clients):
            self.send(a, buf)

    def _flush(self, cl: _Client) -> None:
        while cl.out:
            try:
                n = cl.sock.send(cl.out)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                self._drop(cl.addr, "closed")
                return
            if n <= 0:
                break
            self.counters["tx_bytes"] += n
            del cl.out[:n]
        if len(cl.out) > MAX_BACKLOG_BYTES:  # it does not read: a stuck client is let go
            self._drop(cl.addr, "dropped")

    def _drop(self, addr, reason: str) -> None:
        cl = self._clients.pop(addr, None)
        if cl is None:
            return
        self.counters[reason] += 1
        try:
            cl.sock.close()
        except OSError:
            pass

    def close(self) -> None:
        for a in list(self._clients):
            self._drop(a, "closed")
        self.sock.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
