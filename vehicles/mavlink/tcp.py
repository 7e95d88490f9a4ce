"""A vehicle's TCP server (ArduPilot SITL's SERIAL0: 5760 + 10 x instance) beside its UDP link.

Non-blocking, several clients, stepped with the endpoint: ``poll()`` accepts new clients and
returns the bytes each sent (a MAVLink byte stream, to parse per client); ``write(buf)`` sends a
frame to every client (a client whose socket is full or gone is dropped, counted); ``close()``.
Never blocks, never raises on a peer's behaviour.
"""
from __future__ import annotations

import socket

__all__ = ["TcpServer", "SERIAL0_BASE_PORT", "MAX_CLIENTS"]

SERIAL0_BASE_PORT = 5760
MAX_CLIENTS = 8
_RECV = 65536


class TcpServer:
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
        self.clients: dict[socket.socket, tuple] = {}
        self.counters = {"accepted": 0, "refused": 0, "closed": 0, "dropped": 0, "rx_bytes": 0, "tx_bytes": 0}

    def poll(self) -> list[tuple[tuple, bytes]]:
        """Accept waiting clients; return [(client address, bytes received)] (nothing blocks)."""
        while True:
            try:
                c, a = self.sock.accept()
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                break
            if len(self.clients) >= self.max_clients:
                self.counters["refused"] += 1
                c.close()
                continue
            c.setblocking(False)
            c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.clients[c] = a
            self.counters["accepted"] += 1
        out = []
        for c, a in list(self.clients.items()):
            chunks = []
            while True:
                try:
                    d = c.recv(_RECV)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:
                    d = b""
                if not d:  # orderly close or reset
                    self._drop(c, "closed")
                    break
                chunks.append(d)
            if chunks:
                data = b"".join(chunks)
                self.counters["rx_bytes"] += len(data)
                out.append((a, data))
        return out

    def write(self, buf: bytes) -> None:
        for c in list(self.clients):
            try:
                n = c.send(buf)
            except (BlockingIOError, InterruptedError):
                n = 0
            except OSError:
                self._drop(c, "closed")
                continue
            if n < len(buf):  # a partial frame would corrupt the stream: a slow client is dropped
                self._drop(c, "dropped")
                continue
            self.counters["tx_bytes"] += n

    def _drop(self, c, reason: str) -> None:
        self.clients.pop(c, None)
        self.counters[reason] += 1
        try:
            c.close()
        except OSError:
            pass

    def close(self) -> None:
        for c in list(self.clients):
            self._drop(c, "closed")
        self.sock.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
