"""What every worker process of a live run shares (vehicles.process, ground_station.process):
its spec, the protocol with the launcher, stopping, status lines, the bus session.

Protocol (one JSON object per line):
  worker -> launcher (stdout): ``{"event": "ready", ...}`` once built, then
      ``{"event": "status", "worker": NAME, "t_sim_s": ..., "sent": ..., "rejected": {...}, ...}``
      about once per wall second, and ``{"event": "done", ...}`` at the end.
  launcher -> worker (stdin): ``{"cmd": "start", "wall_start_s": UNIX_S}`` (the run's common
      time origin), ``{"cmd": "stop"}``. End of stdin (the launcher died) stops the worker too,
      so a worker never outlives its launcher.
SIGTERM and SIGINT stop the worker cleanly (sessions closed, logs flushed).

Network faults: when the scenario has a [faults] table, `open_bus` gives the
worker's session a publisher fault filter (`sitl.netfault.KeyFaults` with the scenario's
``bus:`` rules) and listens on ``<run>/ctl/fault`` for run-time changes of them; the status
and done lines then carry ``"netfault"``: per rule the summed truth counters of the keys it
took, and the filter's publish counters.
"""
from __future__ import annotations

import json
import signal
import sys
import threading
from collections import Counter
from pathlib import Path

from sitl.pacing import Pacer, perf_now
from sitl.scenario import WorkerSpec

NETFAULT_STATUS_WALL_S = 5.0  # the status lines carry the bus-fault truths at most this often


class WorkerRuntime:
    """Spec, stop event, start command and status lines of one worker process."""

    def __init__(self, spec_path, *, out=None, stdin=None, install_signals: bool = True):
        self.spec = WorkerSpec.read(spec_path)
        self.scenario = self.spec.scenario_obj()
        self.name = self.spec.name
        self.incarnation = worker_incarnation()
        self.stop = threading.Event()
        self.out = out if out is not None else sys.stdout
        self._stdin = stdin if stdin is not None else sys.stdin
        self._started = threading.Event()
        self.wall_start_s: float | None = None
        self.bad_commands = Counter()
        self._out_lock = threading.Lock()
        self._last_status = -1e18
        self.fault_control = None  # a sitl.netfault.control.WorkerFaultControl (open_bus sets it)
        self._next_netfault = 0.0
        self.bus = None
        global _RUNTIME
        _RUNTIME = self
        if install_signals:
            for sig in (signal.SIGTERM, signal.SIGINT):
                signal.signal(sig, lambda *_: self.stop.set())
        threading.Thread(target=self._read_commands, name="stdin-commands", daemon=True).start()

    # -- launcher -> worker
    def _read_commands(self) -> None:
        try:
            for line in self._stdin:
                line = line.strip()
                if not line:
                    continue
                try:
                    cmd = json.loads(line)
                    if not isinstance(cmd, dict):
                        raise ValueError("not an object")
                    kind = cmd.get("cmd")
                    if kind == "start":
                        w = float(cmd["wall_start_s"])
                        if self.wall_start_s is None:
                            self.wall_start_s = w
                        self._started.set()
                    elif kind == "stop":
                        self.stop.set()
                    else:
                        raise ValueError(f"unknown cmd {kind!r}")
                except (ValueError, KeyError, TypeError) as e:
                    self.bad_commands[type(e).__name__] += 1
                    print(f"{self.name}: bad command from the launcher ignored: {e}", file=sys.stderr)
        except (OSError, ValueError):
            pass
        self.stop.set()  # EOF: the launcher is gone

    # -- worker -> launcher
    def emit(self, obj: dict) -> None:
        obj.setdefault("worker", self.name)
        ev = obj.get("event")
        if self.fault_control is not None and (ev == "done" or (ev == "status" and perf_now() >= self._next_netfault)):
            self._next_netfault = perf_now() + NETFAULT_STATUS_WALL_S  # truths cost O(packets): not every line
            try:
                obj["netfault"] = {"truth": self.fault_control.truths(),
                                   "filter": dict(self.bus.fault_stats) if self.bus is not None else {},
                                   "control_applied": self.fault_control.applied,
                                   "control_bad": dict(self.fault_control.bad)}
            except Exception as e:  # the status line must go out anyway
                obj["netfault"] = {"error": f"{type(e).__name__}: {e}"}
        line = json.dumps(obj, allow_nan=False, default=_jsonable)
        with self._out_lock:
            try:
                self.out.write(line + "\n")
                self.out.flush()
            except (OSError, ValueError):  # the launcher closed our stdout: stop
                self.stop.set()

    def wait_start(self, timeout_s: float = 600.0) -> bool:
        """Report ready and wait for the start command; False if stopped first."""
        self.emit({"event": "ready"})
        while not self.stop.is_set():
            if self._started.wait(0.2):
                return True
            timeout_s -= 0.2
            if timeout_s <= 0:
                print(f"{self.name}: no start command from the launcher, stopping", file=sys.stderr)
                self.stop.set()
        return False

    def pacer(self) -> Pacer:
        run = self.scenario.run
        return Pacer(run.speed, run.t0_gps_s, self.wall_start_s, stop=self.stop)

    def status_due(self) -> bool:
        """True about once per status interval (wall)."""
        now = perf_now()
        if now - self._last_status >= self.spec.status_interval_wall_s:
            self._last_status = now
            return True
        return False


INCARNATION_ENV = "SKYFUSE_INCARNATION"


def worker_incarnation() -> int:
    """This worker process's incarnation: ``$SKYFUSE_INCARNATION`` (the supervisor sets it to
    the worker's restart count: 0, 1, 2, ...), else the start time in microseconds since the
    Unix epoch (a worker started by hand: unique per start, and a later start is larger)."""
    import os
    import time
    v = os.environ.get(INCARNATION_ENV, "")
    if v.isdigit() and int(v) < 2**63:
        return int(v)
    return time.time_ns() // 1000


def _jsonable(v):
    import math

    import numpy as np
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating, float)):
        f = float(v)
        return f if math.isfinite(f) else None
    if isinstance(v, Counter):
        return dict(v)
    return str(v)


_RUNTIME: WorkerRuntime | None = None  # this process's runtime (open_bus attaches the fault control to it)


def open_bus(spec: WorkerSpec, lease_ms: int | None = None):
    """The worker's Zenoh session (a client of the run's routers; through the launcher's fault
    proxy when the scenario has faults: ``spec.zenoh_connect`` says where). With a [faults]
    table: the bus-key fault filter and its run-time control (module text)."""
    from sitl.bus.zenoh_transport import ZenohTransport
    scn = spec.scenario_obj()
    if not scn.faults:
        return ZenohTransport(connect=list(spec.zenoh_connect), mode="client", lease_ms=lease_ms)
    from sitl.netfault import KeyFaults
    from sitl.netfault.control import WorkerFaultControl, control_key
    rules = [(link[4:], text) for link, text in scn.faults.of_kind("bus")]
    kf = KeyFaults(rules, seed=fault_seed(scn.run.seed, spec.name), record=False)  # counters only: a long run
    bus = ZenohTransport(connect=list(spec.zenoh_connect), mode="client", lease_ms=lease_ms, faults=[kf],
                         fault_t0_s=scn.run.t0_gps_s, speed=scn.run.speed)
    ctl = WorkerFaultControl(bus, spec.run_id, kf)
    bus.subscribe_async(control_key(spec.run_id), ctl.on_control)
    if _RUNTIME is not None and _RUNTIME.spec.name == spec.name:
        _RUNTIME.fault_control, _RUNTIME.bus = ctl, bus
    return bus


def fault_seed(run_seed: int, worker: str) -> int:
    """The seed of a worker's bus-key fault draws (its keys are its own: KeyFaults derives one
    generator per key from it)."""
    import zlib
    return (int(run_seed) * 1_000_003 + zlib.crc32(b"netfault:" + worker.encode())) % 2**63


def bus_counters(bus) -> dict:
    """sent / received / rejected of a transport (for the status line)."""
    s = bus.stats
    return {"sent": int(s.published), "received": int(s.total.delivered), "rejected": dict(s.total.rejected),
            "callback_errors": int(s.total.callback_errors)}


def out_path(spec: WorkerSpec, name: str) -> Path:
    p = Path(spec.out_dir)
    p.mkdir(parents=True, exist_ok=True)
    return p / name
