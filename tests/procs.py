"""Checks the live tests share: is a process gone, is a loopback port free."""
from __future__ import annotations

import os
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


def worker_index() -> int:
    """This pytest-xdist worker's number (gw0 -> 0, gw1 -> 1); 0 without xdist."""
    w = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    return int(w[2:]) if w.startswith("gw") and w[2:].isdigit() else 0


def udp_base(n: int) -> int:
    """A base port with 127.0.0.1:base + 10 i (i < n) free for UDP, searched in a window of
    this worker's own (worker k: 20000 + 6000 k .. + 6000, below Linux's ephemeral range for
    workers 0 and 1), so tests on two workers never pick the same ports, and no port the
    OS hands out for bind(0) lands there."""
    first = 20000 + 6000 * worker_index()
    for base in range(first, min(first + 6000, 65000) - 10 * n, 97):
        if all(udp_free(base + 10 * i) for i in range(n)):
            return base
    raise RuntimeError("no free UDP port range")


class LiveDemo:
    """``sitl.app.launcher.launch(scn, out)`` in a thread, for live tests that act as a GCS
    against it: the constructor returns once the workers are up (the launcher's own start-up
    bound plus a margin for a cold kernel cache), ``stop()`` ends the run, joins it and checks
    that every worker it started is gone.  ``report``: the launcher's report once stopped."""

    def __init__(self, scn, out):
        import threading
        import time

        import pytest

        from sitl.app.launcher import READY_TIMEOUT_S, launch
        self.scn, self.out = scn, out
        self.out.mkdir(parents=True, exist_ok=True)
        self.started = threading.Event()
        self.stop_ev = threading.Event()
        self.report = None

        def run():
            self.report = launch(scn, out, quiet=True, stop=self.stop_ev, on_started=lambda sup: self.started.set())
        self.thread = threading.Thread(target=run, daemon=True)
        self.thread.start()
        end = time.monotonic() + READY_TIMEOUT_S + 30.0
        while not self.started.wait(1.0) and self.thread.is_alive() and time.monotonic() < end:
            pass
        if not self.started.is_set():
            self.stop()
            pytest.fail(f"the demo did not start: {(self.report or {}).get('error', 'timed out')}")

    def stop(self):
        self.stop_ev.set()
        self.thread.join(60)
        assert not self.thread.is_alive(), "the demo did not stop"
        pids = [e["pid"] for e in (self.report or {}).get("events", []) if e.get("event") == "start"]
        assert all(dead(p) for p in pids), f"workers left running: {[p for p in pids if not dead(p)]}"
