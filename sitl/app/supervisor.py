"""Starts, watches, restarts and stops the worker processes of a live run.

Workers are started with `subprocess` (never fork: a Zenoh session does not survive it),
each in its own session / process group (``start_new_session``), with pipes for the line
protocol of `sitl.live.worker` (JSON lines on stdout, commands on stdin) and its stderr to a
log file. The launcher's Ctrl-C therefore reaches only the launcher, which stops every group
in order: a ``stop`` command, SIGTERM to the process group after ``grace_s``, SIGKILL after
``term_timeout_s`` -- grandchildren included, no orphan left. If the launcher itself dies,
each worker sees the end of its stdin and stops by itself.

A worker that dies (non-zero exit, or exit before its ``done`` line) is reported and, if it
was added with ``restart=True``, started again (at most ``max_restarts`` times); a restarted
worker is sent the run's start command as soon as it reports ready, and joins at the
current epoch. A worker that reports ``{"event": "fatal", "error": ...}`` and exits with 2 (a
configuration error: a port taken, a bad key file) is not restarted.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from sitl.pacing import perf_now


@dataclass
class Child:
    name: str
    argv: list
    restart: bool = True
    proc: subprocess.Popen | None = None
    ready: threading.Event = field(default_factory=threading.Event)
    done: bool = False  # the worker said it finished its run
    finished: bool = False  # exited and will not be restarted
    status: dict = field(default_factory=dict)  # its latest status line
    last_done: dict = field(default_factory=dict)
    restarts: int = 0
    exits: list = field(default_factory=list)  # return codes, in order
    bad_lines: int = 0
    started_at: float = 0.0
    reader: threading.Thread | None = None
    stderr_path: Path | None = None
    history: list = field(default_factory=list)  # status lines of earlier incarnations (last of each)
    fatal: str | None = None  # a configuration error the worker reported (exit 2): not restarted
    netfault: dict = field(default_factory=dict)  # incarnation -> its latest "netfault" block (bus-fault truths)

    @property
    def pid(self):
        return None if self.proc is None else self.proc.pid

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None


class Supervisor:
    """See the module docstring. ``events``: what happened (start, exit, restart), in order."""

    def __init__(self, log_dir, *, max_restarts: int = 5, grace_s: float = 1.0, term_timeout_s: float = 5.0,
                 env: dict | None = None, on_event=None):
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.max_restarts = max_restarts
        self.grace_s = grace_s
        self.term_timeout_s = term_timeout_s
        from sitl.runtime import child_env
        self.env = child_env(env)  # the children import this copy of the packages (not the cwd's)
        self.env["PYTHONUNBUFFERED"] = "1"
        self.children: dict[str, Child] = {}
        self.events: list[dict] = []
        self.counters = Counter()
        self._start_cmd: dict | None = None
        self._lock = threading.RLock()
        self._stopping = False
        self.on_event = on_event

    # -------------------------------------------------------------- starting
    def add(self, name: str, argv: list, *, restart: bool = True) -> Child:
        if name in self.children:
            raise ValueError(f"duplicate worker name {name!r}")
        c = self.children[name] = Child(name, list(argv), restart)
        return c

    def add_module(self, name: str, module: str, *args: str, restart: bool = True) -> Child:
        return self.add(name, [sys.executable, "-m", module, *args], restart=restart)

    def start_all(self) -> None:
        for c in self.children.values():
            self._spawn(c)

    def _event(self, kind: str, child: Child, **kw) -> None:
        ev = {"event": kind, "worker": child.name, "t_wall_s": round(perf_now(), 3), **kw}
        with self._lock:
            self.events.append(ev)
        self.counters[kind] += 1
        if self.on_event is not None:
            try:
                self.on_event(ev)
            except Exception:
                pass

    def _spawn(self, c: Child) -> None:
        c.stderr_path = self.log_dir / f"{c.name}.stderr.log"
        err = open(c.stderr_path, "ab")
        try:
            # the worker's incarnation (sitl.live.worker.worker_incarnation): its restart count
            env = {**self.env, "SKYFUSE_INCARNATION": str(c.restarts)}
            c.proc = subprocess.Popen(c.argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err,
                                      start_new_session=True, env=env, text=True, bufsize=1,
                                      close_fds=True)
        finally:
            err.close()
        c.ready.clear()
        c.done = False
        c.started_at = perf_now()
        c.reader = threading.Thread(target=self._read, args=(c, c.proc), name=f"read-{c.name}", daemon=True)
        c.reader.start()
        self._event("start", c, pid=c.proc.pid, incarnation=c.restarts)

    def _read(self, c: Child, proc: subprocess.Popen) -> None:
        for line in proc.stdout:
            try:
                obj = json.loads(line)
                if not isinstance(obj, dict):
                    raise ValueError
            except ValueError:
                c.bad_lines += 1
                continue
            ev = obj.get("event")
            if isinstance(obj.get("netfault"), dict):
                c.netfault[c.restarts] = obj["netfault"]
            if ev == "ready":
                c.ready.set()
                with self._lock:
                    cmd = self._start_cmd
                if cmd is not None:
                    self._send(c, cmd)
            elif ev == "status":
                c.status = obj
            elif ev == "fatal":
                c.fatal = str(obj.get("error", "fatal error"))[:300]
            elif ev == "done":
                c.status = obj
                c.last_done = obj
                c.done = True

    def _send(self, c: Child, obj: dict) -> bool:
        p = c.proc
        if p is None or p.stdin is None or p.poll() is not None:
            return False
        try:
            p.stdin.write(json.dumps(obj) + "\n")
            p.stdin.flush()
            return True
        except (OSError, ValueError):
            return False

    def wait_ready(self, timeout_s: float, stop: threading.Event | None = None) -> bool:
        """Wait until every worker reported ready (False: timeout, a stop, or one died)."""
        t_end = perf_now() + timeout_s
        for c in self.children.values():
            while not c.ready.wait(0.1):
                if (stop is not None and stop.is_set()) or perf_now() > t_end or not c.alive():
                    return False
        return True

    def broadcast_start(self, wall_start_s: float) -> None:
        """Send the run's start command to every worker (and to every restarted one later)."""
        cmd = {"cmd": "start", "wall_start_s": wall_start_s}
        with self._lock:
            self._start_cmd = cmd
        for c in self.children.values():
            if c.ready.is_set():
                self._send(c, cmd)

    # -------------------------------------------------------------- watching
    def poll(self) -> list[dict]:
        """Reap exited workers, restart those that died; returns the new events."""
        n0 = len(self.events)
        for c in self.children.values():
            p = c.proc
            if p is None or c.finished or p.poll() is None:
                continue
            rc = p.returncode
            if c.reader is not None:
                c.reader.join(timeout=1.0)  # take the last lines (its done line)
            c.exits.append(rc)
            # whatever the dead worker left in its process group goes with it (no orphans)
            self._signal_group(p, signal.SIGKILL)
            ok = rc == 0 and c.done
            self._event("exit", c, pid=p.pid, returncode=rc, clean=ok)
            self._close_pipes(p)
            if c.status:
                c.history.append(c.status)
            if ok or self._stopping or not c.restart:
                c.finished = True
                continue
            if c.fatal is not None and rc == 2:  # restarting would fail the same way
                c.finished = True
                self._event("fatal", c, error=c.fatal)
                continue
            if c.restarts >= self.max_restarts:
                c.finished = True
                self._event("gave_up", c, restarts=c.restarts)
                continue
            c.restarts += 1
            self.counters["restarts"] += 1
            self._event("restart", c, incarnation=c.restarts, after_returncode=rc)
            c.status = {}
            self._spawn(c)
        return self.events[n0:]

    def all_finished(self) -> bool:
        return all(c.finished for c in self.children.values())

    def alive(self) -> list[str]:
        return [c.name for c in self.children.values() if c.alive()]

    # -------------------------------------------------------------- stopping
    def stop(self) -> dict:
        """Stop every worker (stop command, SIGTERM to its group, SIGKILL); returns how each ended."""
        self._stopping = True
        procs = [(c, c.proc) for c in self.children.values() if c.proc is not None]
        for c, p in procs:
            if p.poll() is None:
                self._send(c, {"cmd": "stop"})
        self._wait(procs, self.grace_s)
        how = {}
        for c, p in procs:
            if p.poll() is None:
                self._signal_group(p, signal.SIGTERM)
                how[c.name] = "SIGTERM"
        self._wait(procs, self.term_timeout_s)
        for c, p in procs:
            if p.poll() is None:
                self._signal_group(p, signal.SIGKILL)
                how[c.name] = "SIGKILL"
        for c, p in procs:
            try:
                p.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                how[c.name] = "unkillable"
            # the group may hold grandchildren even after the leader is gone
            self._signal_group(p, signal.SIGKILL)
            how.setdefault(c.name, "exited")
        self.poll()
        for c, p in procs:
            self._close_pipes(p)
            if c.reader is not None:
                c.reader.join(timeout=1.0)
        return how

    @staticmethod
    def _wait(procs, timeout_s: float) -> None:
        t_end = perf_now() + timeout_s
        for _, p in procs:
            left = t_end - perf_now()
            if left <= 0:
                break
            try:
                p.wait(timeout=left)
            except subprocess.TimeoutExpired:
                pass

    @staticmethod
    def _signal_group(p: subprocess.Popen, sig) -> None:
        try:
            os.killpg(p.pid, sig)  # start_new_session: the worker's pid is its group id
        except (ProcessLookupError, PermissionError):
            pass

    @staticmethod
    def _close_pipes(p: subprocess.Popen) -> None:
        for f in (p.stdin,):
            try:
                if f is not None and not f.closed:
                    f.close()
            except (OSError, ValueError):
                pass

    def __enter__(self) -> Supervisor:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
