"""What a long command says while it works, on stderr, through tqdm.

``Progress(desc)`` is the ``progress`` callback every experiment, bench and batch run takes:
``progress(msg)`` says one line; ``progress(msg, done=k, total=n)`` advances the run's bar
(its rate and ETA are tqdm's) and shows ``msg`` beside it. A ``done`` below the last starts a
new phase (a new bar: the next case, the next variant); a new ``total`` corrects the phase's. On a terminal the bar
redraws in place; when stderr is not a TTY (a log file, CI) there is no bar: one line per ~10 %
of each phase instead, and every plain message as a line. Quiet: ``progress_printer(True)`` is
None, nothing is said.

``KernelCompileNotice``: while a command runs, if numba writes new kernels into its on-disk
cache (the first run after an install or a source change), a line at once says so --
"compiling the estimation kernels (first run only, about N s)" -- and a bar counts the kernels
against the last cold warm-up's count (sitl.app.kernel_cache), until the run's own progress
starts.

Why tqdm and not rich: one small pure-Python dependency with no dependencies of its own, made
for exactly this (a counted loop, its rate and ETA), that degrades to plain text on a pipe;
rich brings a whole terminal-rendering stack (and pygments, markdown-it) for a bar and a line.
"""
from __future__ import annotations

import sys
import threading

#: a non-TTY stream gets a line each time a phase passes another tenth
LINE_EVERY_FRACTION = 0.1
#: a KernelCompileNotice says the count of kernels compiled at most this often
LINE_EVERY_S = 5.0
_current = None  # the latest Progress made (a KernelCompileNotice's lines go through it)


def _elapsed_clock() -> float:
    from sitl.pacing import perf_now  # the one module that reads the wall clock

    return perf_now()


def _is_tty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


class Progress:
    """The progress of one command (module doc). ``stream``: stderr unless given; ``tty``: draw
    a bar (default: whether ``stream`` is a terminal)."""

    def __init__(self, desc: str = "", *, stream=None, tty: bool | None = None, unit: str = "it"):
        self.desc, self.unit = desc, unit
        self.stream = stream if stream is not None else sys.stderr
        self.tty = _is_tty(self.stream) if tty is None else bool(tty)
        self._bar = None
        self._total = None
        self._done = 0
        self._next_line_frac = LINE_EVERY_FRACTION
        self._lock = threading.Lock()
        global _current
        _current = self  # where a KernelCompileNotice says its lines (above this bar)

    # ------------------------------------------------------------------ the callback
    def __call__(self, msg: str | None = None, *, done: float | None = None, total: float | None = None) -> None:
        if done is not None and (total if total is not None else self._total or 0) >= 10:
            done = int(round(done))  # whole units (simulated seconds, epochs) read better
            total = None if total is None else int(round(total))
        with self._lock:
            if done is None:
                if msg:
                    self._line(msg)
                return
            if self._bar is None or done < self._done:
                self._new_phase(total, initial=done)
            elif total is not None and total != self._total:  # a better estimate of the same phase
                self._total = self._bar.total = total
            self._advance(done, msg)

    def _line(self, msg: str) -> None:

        if self._bar is not None:
            self._bar.write(msg, file=self.stream)  # above the bar, which redraws below
        else:
            print(msg, file=self.stream, flush=True)

    def _new_phase(self, total, initial=0) -> None:
        from tqdm import tqdm

        self._close_bar()
        self._total, self._done, self._initial = total, initial, initial
        self._next_line_frac = LINE_EVERY_FRACTION
        # a phase's first report (step 10 of 100, say) is its start: its rate and ETA count from there
        self._bar = tqdm(total=total, initial=initial, desc=self.desc or None, unit=self.unit, file=self.stream,
                         disable=not self.tty, leave=True, dynamic_ncols=True, smoothing=0.1,
                         bar_format=None if total else "{desc}: {n_fmt} {unit} [{elapsed}, {rate_fmt}]")
        self._t0 = _elapsed_clock()

    def _advance(self, done, msg) -> None:
        from tqdm import tqdm

        step = done - self._done
        self._done = done
        if self.tty:
            if msg:
                self._bar.set_postfix_str(msg, refresh=False)
            self._bar.update(step)
            return
        # no terminal: one line per tenth of the phase, tqdm's meter (rate and ETA) and the message
        if not self._total:
            return
        frac = done / self._total
        if frac + 1e-12 >= self._next_line_frac or done >= self._total:
            while self._next_line_frac <= frac + 1e-12:
                self._next_line_frac += LINE_EVERY_FRACTION
            meter = tqdm.format_meter(done, self._total, _elapsed_clock() - self._t0, prefix=self.desc or "",
                                      unit=self.unit, ncols=0, initial=self._initial)
            print(meter + (f"  {msg}" if msg else ""), file=self.stream, flush=True)

    def _close_bar(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def close(self) -> None:
        with self._lock:
            self._close_bar()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def progress_printer(quiet: bool, desc: str = "", *, stream=None):
    """None when quiet, else a Progress on stderr (the ``progress`` callback of every run)."""
    if quiet:
        return None
    return Progress(desc, stream=stream)


class KernelCompileNotice:
    """Says so when numba compiles kernels into its cache during a command (module doc): a
    watcher thread counts the cache's index files written since the start every ``poll_s``; at
    the first it says what is happening and how long it takes, then the count as it grows
    (through the command's Progress once there is one, so the lines go above its bar; else on
    ``stream``). ``enabled`` False (quiet): nothing."""

    def __init__(self, enabled: bool = True, *, stream=None, poll_s: float = 1.0):
        self.enabled = bool(enabled)
        self.stream = stream
        self.poll_s = float(poll_s)
        self._stop = threading.Event()
        self._thread = None
        self.compiled = 0

    def __enter__(self):
        if not self.enabled:
            return self
        from sitl.pacing import wall_now

        self._t0 = wall_now() - 1.0  # index files carry the file system's (wall) time
        self._thread = threading.Thread(target=self._watch, name="kernel-compile-notice", daemon=True)
        self._thread.start()
        return self

    def _say(self, msg: str) -> None:
        p = _current
        if p is not None and (self.stream is None or p.stream is self.stream):
            with p._lock:
                p._line(msg)
        else:
            print(msg, file=self.stream if self.stream is not None else sys.stderr, flush=True)

    def _watch(self) -> None:
        from sitl.app import kernel_cache as kc

        est_s, est_n = kc.estimate()
        said = 0  # kernels the last count line said
        polls = 0
        while not self._stop.wait(self.poll_s):
            polls += 1
            n = kc.written_since(self._t0)
            if n and not self.compiled:
                self._say(f"compiling the estimation kernels (first run only, about {est_s:.0f} s)")
            self.compiled = n
            if n > said and polls * self.poll_s >= LINE_EVERY_S:  # the count, every few seconds
                polls, said = 0, n
                self._say(f"compiling the estimation kernels: {n}/~{max(n, est_n)} compiled")

    def __exit__(self, *exc):
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        if self.compiled:
            self._say(f"compiled {self.compiled} kernels (cached: later runs skip this)")
