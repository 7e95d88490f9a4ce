"""The live ground station's journal: exactly what it consumed, in order, for an exact replay.

Deterministic replay the way record/replay systems do it: the live process writes down its
non-deterministic inputs -- what arrived when, as it saw it -- and a replay feeds the same
node the same inputs in the same order, so it makes the same decisions bit for bit, whatever
the load on the machine was. `skyfuse replay` re-deriving them from the bus recorder's receive
times cannot be exact: the recorder and the ground station are two processes with their own
arrival order and clock (under CPU load their epochs' inputs are split differently).

The journal is a bus log (`sitl.bus.buslog`: append-safe, each record CRC-checked, a torn
tail cut cleanly), one per ground-station incarnation: ``OUT/gs_journal.log`` for the first
(incarnation 0), ``OUT/gs_journal.r<N>.log`` for incarnation N (a restart). Its records, in the
order the ground station consumed them (``t_recv_s``: its paced simulation clock when it took
them in):

* first, ``!gs-journal``: a JSON header: format version, run id, the node's incarnation and its
  full configuration (``GsConfig``, the sonde tracker's parameters included) -- everything
  besides the inputs that its decisions depend on;
* ``<bus key>``: one input payload as received (raw bytes, valid or not: the replay's
  transport rejects and counts the same ones), on a key the node subscribes to;
* ``!advance``: one ``GroundStationNode.advance(t_until, early_window_s=, now_s=)`` call, its
  three arguments as little-endian f64 (NaN: the argument was not given).

Write-ahead: every tick's records are handed to the kernel (``os.write``) before
``advance`` runs, so anything the node published was journaled first, and a kill -9 loses
no decision that reached the bus (fsync follows from the writer's flusher thread within
``flush_interval_s``). Keys starting with ``!`` are not valid bus keys, so control records
cannot be confused with inputs.

A restarted ground station (incarnation N > 0) resumes: before its first tick it runs the
earlier incarnations' journals (0 .. N-1, each holding what its incarnation consumed after its
own resume) through its new node with the output muted (`resume`), so its beacon locator, sonde
tracker, lag windows, time guard and link monitors are where the dead one left them, and the
inputs that one had taken in but not yet processed are queued. Its header lists them
(``resumed_from``), and the replay resumes the same way, so it stays exact. Why not start cold:
the beacon locator's blind start mid-run lands, on the demo geometry, on the mirror of the beacon
through the three UAVs' plane at some start times (tests/ground_station/test_gs_restart.py).
What no ground station was subscribed to while the new one started is lost to it.

    jr = open_journal(out_dir, incarnation, header)    # live (ground_station.process)
    node = GroundStationNode(JournalingTransport(bus, jr), ...)
    for ev in read_journal(path, stats): ...           # replay (sitl.app.launcher.replay)
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import struct
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

from sitl.bus.buslog import BusLogError, BusLogStats, BusLogWriter, read_bus_log_records
from sitl.bus.codec import MAX_PAYLOAD_BYTES
from sitl.bus.transport import key_matches

FORMAT = "skyfuse ground-station journal"
VERSION = 1
HEADER_KEY = "!gs-journal"
ADVANCE_KEY = "!advance"
_ADVANCE = struct.Struct("<ddd")
JOURNAL_NAME = "gs_journal.log"
_RESTART_NAME = re.compile(r"^gs_journal\.r(\d+)\.log$")


def journal_name(incarnation: int) -> str:
    """The journal's file name for a ground-station incarnation (module text)."""
    return JOURNAL_NAME if int(incarnation) == 0 else f"gs_journal.r{int(incarnation)}.log"


def find_journals(out_dir: str | os.PathLike) -> list[Path]:
    """The journals in a run's output directory, by incarnation (0 first)."""
    d = Path(out_dir)
    found = []
    if (d / JOURNAL_NAME).is_file():
        found.append((0, d / JOURNAL_NAME))
    try:
        names = os.listdir(d)
    except OSError:
        names = []
    for name in names:
        m = _RESTART_NAME.match(name)
        if m and (d / name).is_file():
            found.append((int(m.group(1)), d / name))
    return [p for _, p in sorted(found)]


# ---------------------------------------------------------------------------------- writing


class JournalWriter:
    """The live side: `input` (during the transport's drain), `advance` (then the tick's records
    go to the kernel: write-ahead), `close`. ``cost_s``: time spent journaling on the caller's
    thread (``clock``: a perf counter, given by the process: this module reads no clock)."""

    def __init__(self, path: str | os.PathLike, header: dict, *, t_s: float = 0.0,
                 clock=None, fsync: bool = True, flush_interval_s: float = 0.25):
        self.path = Path(path)
        self.t_s = float(t_s)  # the clock the next inputs are stamped with (the tick's)
        self._clock = clock
        self.cost_s = 0.0
        self.inputs = 0
        self.advances = 0
        self.truncated = 0  # payloads over the codec's bound, journaled cut (rejected the same)
        self.errors = Counter()
        self.writer = BusLogWriter(self.path, append=False, fsync=fsync, flush_interval_s=flush_interval_s)
        hdr = {"format": FORMAT, "version": VERSION, **header}
        self.writer.append(HEADER_KEY, json.dumps(hdr, allow_nan=False, sort_keys=True).encode(), self.t_s)
        self.writer.flush()

    def _timed(self, fn, *a):
        c = self._clock
        if c is None:
            return fn(*a)
        w0 = c()
        try:
            return fn(*a)
        finally:
            self.cost_s += c() - w0

    def input(self, key: str, payload: bytes) -> None:
        """One payload the node's transport took in (raw, as received)."""
        self._timed(self._input, key, payload)

    def _input(self, key, payload):
        if len(payload) > MAX_PAYLOAD_BYTES:  # rejected for its size either way: bounded cost
            payload = bytes(payload[:MAX_PAYLOAD_BYTES + 1])
            self.truncated += 1
        try:
            self.writer.append(key, payload, self.t_s)
            self.inputs += 1
        except (BusLogError, RuntimeError) as e:  # counted; never stops the ground station
            self.errors[type(e).__name__] += 1

    def advance(self, t_until_s: float, early_window_s: float | None, now_s: float | None) -> None:
        """One advance() call with its arguments, then the tick's records to the kernel."""
        self._timed(self._advance, t_until_s, early_window_s, now_s)

    def _advance(self, t_until_s, early_window_s, now_s):
        body = _ADVANCE.pack(float(t_until_s), math.nan if early_window_s is None else float(early_window_s),
                             math.nan if now_s is None else float(now_s))
        try:
            self.writer.append(ADVANCE_KEY, body, self.t_s if now_s is None else float(now_s))
            self.advances += 1
            self.writer.flush(fsync=False)  # write-ahead: in the kernel before the outputs leave
        except (BusLogError, RuntimeError) as e:
            self.errors[type(e).__name__] += 1

    def status(self) -> dict:
        w = self.writer
        d = {"path": self.path.name, "records": w.records, "inputs": self.inputs, "advances": self.advances,
             "bytes": w.bytes_written, "cost_s": self.cost_s, "write_errors": w.write_errors}
        if self.truncated:
            d["truncated"] = self.truncated
        if self.errors:
            d["errors"] = dict(self.errors)
        return d

    def close(self) -> None:
        self.writer.close()


def open_journal(out_dir: str | os.PathLike, incarnation: int, header: dict, **kw) -> JournalWriter:
    """The journal of this incarnation in ``out_dir``. The first incarnation of a run (0) also
    removes the restarts' journals a previous run in the same directory left (its own file it
    truncates), so that a replay never mixes two runs."""
    d = Path(out_dir)
    d.mkdir(parents=True, exist_ok=True)
    if int(incarnation) == 0:
        for name in os.listdir(d):
            if _RESTART_NAME.match(name):
                try:
                    (d / name).unlink()
                except OSError:
                    pass
    return JournalWriter(d / journal_name(incarnation), {**header, "incarnation": int(incarnation)}, **kw)


class JournalingTransport:
    """The node's transport in a live ground station: the real one, whose every subscription
    also journals each raw payload it takes in, in the order they are taken in (the raw
    callback runs on the drain just before the decoded delivery). Where two of the node's key
    expressions match one key, the payload is journaled once (by the first expression)."""

    def __init__(self, transport, journal: JournalWriter):
        self._t = transport
        self.journal = journal
        self._exprs: list[str] = []
        self._first: dict[str, str | None] = {}
        self._raw = []

    def subscribe(self, key_expr, callback):
        sub = self._t.subscribe(key_expr, callback)
        if key_expr not in self._exprs:
            self._exprs.append(key_expr)
            self._first.clear()
            self._raw.append(self._t.subscribe_raw(key_expr, lambda k, p, e=key_expr: self._on_raw(e, k, p)))
        return sub

    def _on_raw(self, expr: str, key: str, payload: bytes) -> None:
        first = self._first.get(key, "")
        if first == "":
            first = next((e for e in self._exprs if key_matches(e, key)), None)
            if len(self._first) >= 65536:
                self._first.clear()
            self._first[key] = first
        if first == expr:
            self.journal.input(key, payload)

    def close_journaling(self) -> None:
        for s in self._raw:
            s.close()
        self._raw.clear()

    def __getattr__(self, name):  # publish, stats, ...: the real transport's
        return getattr(self._t, name)


# ---------------------------------------------------------------------------------- reading


class JournalInput(NamedTuple):
    t_s: float
    key: str
    payload: bytes


class JournalAdvance(NamedTuple):
    t_s: float
    t_until_s: float
    early_window_s: float | None
    now_s: float | None


class JournalError(ValueError):
    """Not a usable journal (not a bus log, no or a bad header, another format version)."""


@dataclass
class JournalStats:
    """What reading a journal found: its records, the bus-log reader's torn-tail / corruption
    verdict (``log``), and records that are framed right but make no sense (``bad``, by reason:
    skipped, counted)."""

    path: str = ""
    header: dict = field(default_factory=dict)
    inputs: int = 0
    advances: int = 0
    bad: Counter = field(default_factory=Counter)
    log: BusLogStats = field(default_factory=BusLogStats)

    def as_dict(self) -> dict:
        return {"path": self.path, "incarnation": self.header.get("incarnation"), "inputs": self.inputs,
                "advances": self.advances, "bad_records": dict(self.bad),
                "torn_tail": {"dropped_bytes": self.log.dropped_bytes, "reason": self.log.reason}}


def read_journal_header(path: str | os.PathLike, stats: JournalStats | None = None) -> dict:
    """The header of a journal; raises `JournalError` (one line) if it is not a usable one."""
    st = stats if stats is not None else JournalStats(path=str(path))
    it = read_bus_log_records(path, stats=st.log)
    try:
        first = next(it, None)
    except BusLogError as e:
        raise JournalError(f"{os.fspath(path)}: {e}") from None
    finally:
        it.close()
    if first is None:
        raise JournalError(f"{os.fspath(path)}: no header record ({st.log.reason or 'empty'})")
    if first.key != HEADER_KEY:
        raise JournalError(f"{os.fspath(path)}: first record is {first.key[:40]!r}, not the journal header")
    try:
        hdr = json.loads(first.payload)
        if not isinstance(hdr, dict):
            raise ValueError("not an object")
    except (ValueError, UnicodeDecodeError) as e:
        raise JournalError(f"{os.fspath(path)}: bad header: {e}") from None
    if hdr.get("format") != FORMAT or hdr.get("version") != VERSION:
        raise JournalError(f"{os.fspath(path)}: journal format {hdr.get('format')!r} version {hdr.get('version')!r} "
                           f"is not this build's ({FORMAT!r} version {VERSION})")
    for k, tp in (("run_id", str), ("incarnation", int), ("config", dict)):
        if not isinstance(hdr.get(k), tp):
            raise JournalError(f"{os.fspath(path)}: header without a valid {k!r}")
    st.header = hdr
    return hdr


def read_journal(path: str | os.PathLike, stats: JournalStats):
    """Yield the journal's events (`JournalInput`, `JournalAdvance`) after its header, in order;
    a record that is framed right but makes no sense is skipped and counted in ``stats.bad``;
    a torn or corrupt tail ends the events (``stats.log``). Raises `JournalError` if the file
    is not a usable journal at all (checked before the first event)."""
    stats.path = str(path)
    read_journal_header(path, stats)
    stats.log = BusLogStats()
    first = True
    for rec in read_bus_log_records(path, stats=stats.log):
        if first:
            first = False
            continue
        t = rec.t_recv_s
        if not math.isfinite(t):
            stats.bad["time not finite"] += 1
            continue
        if rec.key == ADVANCE_KEY:
            if len(rec.payload) != _ADVANCE.size:
                stats.bad["advance of the wrong size"] += 1
                continue
            until, early, now = _ADVANCE.unpack(rec.payload)
            if math.isnan(until) or (not math.isnan(early) and not early >= 0) or (not math.isnan(now) and not math.isfinite(now)):
                stats.bad["advance arguments out of range"] += 1
                continue
            stats.advances += 1
            yield JournalAdvance(t, until, None if math.isnan(early) else early, None if math.isnan(now) else now)
        elif rec.key.startswith("!"):
            stats.bad["unknown control record"] += 1
        else:
            stats.inputs += 1
            yield JournalInput(t, rec.key, rec.payload)


# ---------------------------------------------------------------------------------- resuming


RESUME_KEY = "resumed_from"  # the header's list of the earlier journals a restarted node was resumed from


def resume_sources(out_dir: str | os.PathLike, incarnation: int, run_id: str) -> list[str]:
    """The names of the earlier incarnations' journals in ``out_dir`` a restarted ground station
    (incarnation > 0) resumes from: every one below ``incarnation`` that is a usable journal of
    ``run_id``, in incarnation order (an unusable one is left out: the header says which were used)."""
    names = []
    for i in range(int(incarnation)):
        p = Path(out_dir) / journal_name(i)
        try:
            hdr = read_journal_header(p)
        except (JournalError, OSError):
            continue
        if hdr.get("run_id") == run_id and int(hdr.get("incarnation", -1)) == i:
            names.append(p.name)
    return names


def resume(node, paths) -> dict:
    """Bring a restarted ground station's node to where its earlier incarnations left off: their
    journals (``paths``, in incarnation order; each one's inputs and advance() calls after the
    resume it did itself) run through ``node`` with its output muted (nothing is published, no
    link statistics go out; the locator's and tracker's state, their lag windows, the time
    guard's clock and the link monitors are theirs at the last journaled tick). Inputs journaled
    after that tick stay queued for the node's next advance. The live restart and the replay
    call this on the same journals (the restart's header names them, RESUME_KEY), so the replay
    stays exact. Returns counts: journals, inputs, advances, undecodable, step_errors."""
    from sitl.bus import BusDecodeError, decode

    out = Counter()
    node.bus.muted = True
    try:
        for path in paths:
            st = JournalStats(path=str(path))
            for ev in read_journal(path, st):
                if isinstance(ev, JournalAdvance):
                    out["advances"] += 1
                    try:  # as live: a failing step is counted and the node goes on
                        node.advance(ev.t_until_s, early_window_s=ev.early_window_s, now_s=ev.now_s)
                    except Exception:
                        out["step_errors"] += 1
                else:
                    out["inputs"] += 1
                    try:
                        msg = decode(ev.payload)
                    except (BusDecodeError, ValueError):
                        out["undecodable"] += 1  # the live transport refused it too
                        continue
                    node.bus.feed_as_transport(ev.key, msg)
            out["journals"] += 1
    finally:
        node.bus.muted = False
        node.events.clear()
        node.link_changes.clear()
        node.link_messages.clear()
    for k, v in out.items():
        node.counters[f"resumed_{k}"] += v
    return dict(out)


# ---------------------------------------------------------------------------------- the configuration


def config_to_json(config) -> dict:
    """A GsConfig as JSON (floats round-trip exactly)."""
    d = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)}
    st = d.get("sonde_tracker")
    if st is not None:
        d["sonde_tracker"] = dataclasses.asdict(st)
    return d


def config_from_json(d: dict):
    """The GsConfig a journal's header holds (the live node's own)."""
    from ground_station.node import GsConfig
    from ground_station.process import _dataclass_from_json
    from ground_station.sonde import SondeTrackerParams

    d = dict(d)
    known = {f.name for f in dataclasses.fields(GsConfig)}
    extra = set(d) - known
    if extra:
        raise JournalError(f"journal configuration has unknown fields {sorted(extra)}")
    st = d.pop("sonde_tracker", None)
    try:
        return GsConfig(**d, sonde_tracker=None if st is None else _dataclass_from_json(SondeTrackerParams, st))
    except (TypeError, ValueError) as e:
        raise JournalError(f"journal configuration: {' '.join(str(e).split())}") from None


__all__ = ["ADVANCE_KEY", "HEADER_KEY", "JOURNAL_NAME", "RESUME_KEY", "resume", "resume_sources", "JournalAdvance", "JournalError", "JournalInput",
           "JournalStats", "JournalWriter", "JournalingTransport", "config_from_json", "config_to_json",
           "find_journals", "journal_name", "open_journal", "read_journal", "read_journal_header"]
