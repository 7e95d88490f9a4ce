"""Checks the live tests share: is a process gone, is a loopback port free."""
from __future__ import annotations

import socket


def dead(pid: int) -> bool:
    """True once the process has exited (gone, or a zombie awaiting its parent)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] in ("Z", "X")
    except FileNotFoundError:
        return True


def _bindable(kind: int, port: int) -> bool:
    with socket.socket(socket.AF_INET, kind) as s:
        if kind == socket.SOCK_STREAM:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
            return True
        except OSError:
            return False


def tcp_free(port: int) -> bool:
    """Nothing listens on 127.0.0.1:port (TCP; TIME_WAIT ignored)."""
    return _bindable(socket.SOCK_STREAM, port)


def udp_free(port: int) -> bool:
    """No socket is bound to 127.0.0.1:port (UDP)."""
    return _bindable(socket.SOCK_DGRAM, port)
