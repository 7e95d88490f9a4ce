"""What `skyfuse run` / `demo` check before they start anything, so that an operator's mistake
costs one line and exit status 2 at once, never a half-started run or lost data:

* the output directory is not in use by another run: a run holds an exclusive lock on
  ``OUT/.skyfuse.lock`` (``fcntl.flock``: released by the kernel when the process ends, even
  by kill -9) for as long as it writes there, so a second run into the same directory is
  refused instead of truncating the first one's bus log;
* every port the run will bind is free: each vehicle's MAVLink UDP port and, with ``[mavlink]
  tcp``, its TCP port (``[mavlink] base_port`` + 10 x instance) and the embedded Zenoh router's listen port (``[bus] listen``,
  unless it asks for port 0);
* the MAVLink signing key file (``[mavlink] signing_key_file``) can be read and is not empty
  (every other content is a valid key: 32 raw bytes, 64 hex characters, or a passphrase).

Each failure is a `PreflightError` whose text is one line naming the thing, the flag or
scenario key that changes it, and what to do.
"""
from __future__ import annotations

import errno
import fcntl
import os
import socket
from pathlib import Path

LOCK_NAME = ".skyfuse.lock"


class PreflightError(Exception):
    """A run cannot start (module docstring); one line."""


class OutDirLock:
    """An exclusive lock on an output directory for the life of a run (module docstring)."""

    def __init__(self, out: Path):
        self.path = Path(out) / LOCK_NAME
        self._fd: int | None = None

    def acquire(self) -> OutDirLock:
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
        except OSError as e:
            raise PreflightError(f"cannot lock output directory {str(self.path.parent)!r}: {e.strerror}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            owner = _read_owner(fd)
            os.close(fd)
            if e.errno in (errno.EWOULDBLOCK, errno.EACCES):
                raise PreflightError(
                    f"output directory {str(self.path.parent)!r} is in use by another skyfuse run"
                    f"{f' (pid {owner})' if owner else ''}; give this run another --out DIR") from None
            raise PreflightError(f"cannot lock output directory {str(self.path.parent)!r}: {e.strerror}") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            try:
                fcntl.flock(self._fd, fcntl.LOCK_UN)
            finally:
                os.close(self._fd)
                self._fd = None

    def __enter__(self) -> OutDirLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def _read_owner(fd: int) -> str:
    try:
        return os.pread(fd, 32, 0).decode("ascii", "replace").strip()
    except OSError:
        return ""


def _bind_error(kind: int, host: str, port: int) -> str | None:
    """None if (host, port) can be bound now, else the reason."""
    with socket.socket(socket.AF_INET, kind) as s:
        if kind == socket.SOCK_STREAM:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the router does: TIME_WAIT is fine
        try:
            s.bind((host, port))
        except OSError as e:
            return e.strerror or str(e)
    return None


def check_ports(scn) -> None:
    """Every port the run binds is free (module docstring); PreflightError naming the first taken."""
    m = scn.mavlink
    if m.enabled:
        from sitl.mavlink.blocks import MavlinkPlan
        plan = MavlinkPlan.of(scn)
        for i in range(scn.n_vehicles):
            port = plan.listen_port(i)
            for kind, proto in ((socket.SOCK_DGRAM, "UDP"), (socket.SOCK_STREAM, "TCP")):
                if kind == socket.SOCK_STREAM and not m.tcp:
                    continue
                why = _bind_error(kind, "127.0.0.1", port)
                if why is not None:
                    sid = f"system id {plan.sysid_of(i)}" + (f" of MAVLink block {plan.block_of(i)}"
                                                               if plan.n_blocks > 1 else "")
                    what = f"vehicle {i} ({sid})" if i < scn.uavs.count else f"the sonde ({sid})"
                    raise PreflightError(
                        f"{proto} port {port} ({what}'s MAVLink) cannot be bound: {why}; vehicle i listens on "
                        f"[mavlink] base_port + 10 i (base_port = {m.base_port}; block k's system id s on base_port "
                        f"+ (k - 1) + 10 (s - 1)): --instance N or --base-port P moves them, or --no-mavlink")
    if not scn.bus.zenoh:
        proto, _, rest = scn.bus.listen.partition("/")
        host, _, port = rest.rpartition(":")
        if proto == "tcp" and port.isdigit() and int(port) != 0:
            why = _bind_error(socket.SOCK_STREAM, host.strip("[]") or "127.0.0.1", int(port))
            if why is not None:
                raise PreflightError(
                    f"TCP port {port} (the embedded Zenoh router's [bus] listen = {scn.bus.listen!r}) cannot be "
                    f"bound: {why}; set [bus] listen to another port (port 0: any free one), or --zenoh "
                    "tcp/HOST:PORT to use a running router")


def check_signing_key(scn) -> None:
    """The signing key file can be read and is not empty (module docstring)."""
    path = scn.mavlink.signing_key_file
    if not (scn.mavlink.enabled and path):
        return
    try:
        with open(path, "rb") as f:
            data = f.read(4096)
    except OSError as e:
        raise PreflightError(f"[mavlink] signing_key_file {path!r} cannot be read: {e.strerror}; give a file with "
                             "the 32-byte key (raw, 64 hex characters, or a passphrase)") from None
    if len(data) != 32 and not data.strip():  # 32 raw bytes are a key whatever they are
        raise PreflightError(f"[mavlink] signing_key_file {path!r} is empty; give a file with the 32-byte key "
                             "(raw, 64 hex characters, or a passphrase)")


def preflight(scn, *, live: bool) -> None:
    """The checks of a run about to start (the lock is taken separately, `OutDirLock`)."""
    if live:
        check_signing_key(scn)
        check_ports(scn)


__all__ = ["LOCK_NAME", "OutDirLock", "PreflightError", "check_ports", "check_signing_key", "preflight"]
