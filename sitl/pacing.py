"""Wall-clock pacing of step functions of simulation time: the ONLY module of the project
that reads the wall clock or sleeps (components never do: they are step functions of simulation time).

Simulation time and wall time are tied by one line, shared by every process of a run:

    t_sim = t0_sim_s + speed * (wall - wall_start_s)

``wall_start_s`` is Unix time (``time.time``) chosen by the launcher and sent to every
worker, so that processes started at different moments (or restarted) agree on "now".
"""
from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator


def wall_now() -> float:
    """Unix time, s (the launcher stamps the run's start with it)."""
    return time.time()


def perf_now() -> float:
    """A monotonic clock for measuring durations (latency, CPU shares), s."""
    return time.perf_counter()


def cpu_now() -> float:
    """CPU time of this process, s (benchmarks: CPU per vehicle)."""
    return time.process_time()


def thread_cpu_now() -> float:
    """CPU time of the calling thread, s (a tick's own work, without the time it was preempted)."""
    return time.thread_time()


class Pacer:
    """Maps simulation time to wall time at ``speed`` x real time and waits for it.

    clock: the wall clock (Unix seconds; tests pass a fake); wait(timeout) -> bool: how to
    sleep (default: ``stop.wait``, so a stop request interrupts the sleep at once).
    """

    def __init__(self, speed: float, t0_sim_s: float, wall_start_s: float | None = None, *,
                 stop: threading.Event | None = None, clock: Callable[[], float] = time.time):
        if not (isinstance(speed, (int, float)) and math.isfinite(speed) and speed > 0):
            raise ValueError(f"speed must be a finite number > 0, got {speed!r}")
        self.speed = float(speed)
        self.t0_sim_s = float(t0_sim_s)
        self.clock = clock
        self.wall_start_s = float(clock() if wall_start_s is None else wall_start_s)
        self.stop = stop if stop is not None else threading.Event()
        self.late_epochs = 0  # epochs that were already due when asked for
        self.skipped_epochs = 0  # epochs jumped over to catch up
        self.max_lag_s = 0.0  # largest lag seen (simulated s)

    def sim_now(self) -> float:
        return self.t0_sim_s + self.speed * (self.clock() - self.wall_start_s)

    def wall_at(self, t_sim_s: float) -> float:
        return self.wall_start_s + (float(t_sim_s) - self.t0_sim_s) / self.speed

    def wait_until(self, t_sim_s: float) -> bool:
        """Sleep until simulation time t_sim_s is due; False if a stop was requested."""
        while not self.stop.is_set():
            dt = self.wall_at(t_sim_s) - self.clock()
            if dt <= 0:
                return True
            self.stop.wait(min(dt, 0.5))
        return False

    def epochs(self, t_first_s: float, dt_s: float, t_end_s: float, *, max_lag_s: float = math.inf) -> Iterator[float]:
        """Yield the epochs t_first, t_first + dt, ... <= t_end, each when it is due.

        An epoch already due is yielded at once (counted late); when the run is behind by more
        than max_lag_s (simulated), the epochs in between are skipped (counted) and the next
        one yielded is the latest due. Stops early when ``stop`` is set."""
        if not dt_s > 0:
            raise ValueError(f"dt_s must be > 0, got {dt_s!r}")
        k = 0
        while not self.stop.is_set():
            t = t_first_s + k * dt_s
            if t > t_end_s + 1e-9:
                return
            lag = self.sim_now() - t
            if lag > 0:
                self.max_lag_s = max(self.max_lag_s, lag)
                if lag > max_lag_s:
                    jump = int(math.floor(lag / dt_s))
                    k += jump
                    self.skipped_epochs += jump
                    continue
                self.late_epochs += lag > dt_s
            elif not self.wait_until(t):
                return
            yield t
            k += 1
