"""Crash-safe, append-only record of bus messages, and its reader.

File format (version 2, little-endian)::

    header  : b"SKYFBUS" + bytes([2])                       8 bytes
    record  : u32 body_len | u32 crc32(body_len bytes + body) | body
    body    : f64 t_recv_s | u16 key_len | key (UTF-8) | payload (the bus bytes as received)

``t_recv_s`` is the receive time the writer was given (the recorder's clock: in a run's
bus.log the launcher's paced SIMULATION clock when the payload arrived -- version 1 logs held
wall time -- so a replay can guard the messages' times against the clock the live ground
station had, not against the messages themselves); the message's own simulation time is
inside the payload. Each record carries its own length
and CRC-32 (covering the length too), so a reader keeps the longest valid prefix: it stops
cleanly at a torn tail (a record cut by a crash) or at a corrupt record, and counts the
bytes it left (`BusLogStats`). Like Kafka's log segments, a record is either wholly there
and checked, or not there.

Durability: `BusLogWriter.append` only adds to an in-memory buffer. The buffer goes to the
kernel (``os.write``) and to the disk (``os.fsync``) from a small flusher thread every
``flush_interval_s`` (0.25 s by default), also from `append` itself when a flush is overdue
or the buffer holds ``max_buffer_bytes``, and at `close`. Data handed to the kernel survives
a kill -9 of the process; fsync makes it survive an OS crash. So after a kill -9 (or a
power loss, barring disk caches that lie) at most the records of the last
``flush_interval_s`` plus one fsync are lost, well under the 1 s promised, and the file
still reads. Reopening an existing log for append first cuts a torn tail off, so records
appended after a crash are readable.

    with BusLogWriter("run.buslog") as w:
        w.append("run1/uav/3/nav", payload)
    for key, payload in read_bus_log("run.buslog"): ...

`BusRecorder` subscribes to a transport and appends every payload on a key expression.
"""

from __future__ import annotations

import logging
import os
import struct
import threading
import time
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, BinaryIO, NamedTuple

from .codec import MAX_PAYLOAD_BYTES, BusDecodeError, decode, encode
from .schema import UavGroupEpoch, parse_key

log = logging.getLogger("sitl.bus.buslog")

MAGIC = b"SKYFBUS\x02"
_HEAD = struct.Struct("<II")  # body_len, crc32
_BODY_HEAD = struct.Struct("<dH")  # t_recv_s, key_len
MAX_RECORD_BYTES = 16 << 20  # a record claiming more is corrupt (bus payloads are <= 1 MiB)
MAX_KEY_BYTES = 0xFFFF


class BusLogError(ValueError):
    """Not a bus log (wrong magic or version), or a record that cannot be written."""


class BusRecord(NamedTuple):
    t_recv_s: float
    key: str
    payload: bytes


@dataclass
class BusLogStats:
    """What a read found: ``records`` read; ``valid_bytes`` the length of the valid prefix;
    ``dropped_bytes`` after it; ``torn_tail`` True if the last record is cut short (a crash
    while writing); ``corrupt`` True if a complete record failed its CRC or framing."""

    records: int = 0
    valid_bytes: int = 0
    dropped_bytes: int = 0
    torn_tail: bool = False
    corrupt: bool = False
    reason: str = ""


def _encode_record(key: str, payload: bytes, t_recv_s: float) -> bytes:
    kb = key.encode("utf-8")
    if len(kb) > MAX_KEY_BYTES:
        raise BusLogError(f"key of {len(kb)} bytes is longer than {MAX_KEY_BYTES}")
    body = _BODY_HEAD.pack(t_recv_s, len(kb)) + kb + payload
    if len(body) > MAX_RECORD_BYTES:
        raise BusLogError(f"record of {len(body)} bytes is larger than {MAX_RECORD_BYTES}")
    n = struct.pack("<I", len(body))
    return n + struct.pack("<I", zlib.crc32(body, zlib.crc32(n))) + body


def _scan(f: BinaryIO, stats: BusLogStats) -> Iterator[BusRecord]:
    """Yield the records of an open bus log from its start, streaming; fill ``stats``."""
    head = f.read(len(MAGIC))
    size = len(head)
    if size < len(MAGIC):
        if head != MAGIC[:size]:
            raise BusLogError("not a skyfuse bus log (bad magic)")
        stats.torn_tail = size > 0
        stats.dropped_bytes = size
        stats.reason = "torn header" if size else "empty file"
        return
    if head != MAGIC:
        if head[:7] == MAGIC[:7]:
            raise BusLogError(f"bus log version {head[7]} is not supported (this build reads {MAGIC[7]})")
        raise BusLogError("not a skyfuse bus log (bad magic)")
    pos = stats.valid_bytes = len(MAGIC)
    while True:
        rh = f.read(_HEAD.size)
        if not rh:
            break
        if len(rh) < _HEAD.size:
            stats.torn_tail, stats.reason = True, "torn record header"
            size = pos + len(rh)
            break
        n, crc = _HEAD.unpack(rh)
        if n < _BODY_HEAD.size or n > MAX_RECORD_BYTES:
            stats.corrupt, stats.reason = True, f"bad record length {n}"
            size = pos + _HEAD.size + len(f.read())
            break
        body = f.read(n)
        if len(body) < n:
            stats.torn_tail, stats.reason = True, "torn record"
            size = pos + _HEAD.size + len(body)
            break
        if zlib.crc32(body, zlib.crc32(rh[:4])) != crc:
            stats.corrupt, stats.reason = True, "bad CRC"
            size = pos + _HEAD.size + n + len(f.read())
            break
        t, klen = _BODY_HEAD.unpack_from(body, 0)
        if _BODY_HEAD.size + klen > n:
            stats.corrupt, stats.reason = True, "key longer than its record"
            size = pos + _HEAD.size + n + len(f.read())
            break
        try:
            key = body[_BODY_HEAD.size:_BODY_HEAD.size + klen].decode("utf-8")
        except UnicodeDecodeError:
            stats.corrupt, stats.reason = True, "key not UTF-8"
            size = pos + _HEAD.size + n + len(f.read())
            break
        stats.records += 1
        pos += _HEAD.size + n
        stats.valid_bytes = size = pos
        yield BusRecord(t, key, body[_BODY_HEAD.size + klen:])
    stats.dropped_bytes = size - stats.valid_bytes


def read_bus_log_records(path: str | os.PathLike, *,
                         stats: BusLogStats | None = None) -> Iterator[BusRecord]:
    """Yield every valid record ``(t_recv_s, key, payload)`` of a bus log, in order; stop
    cleanly at a torn or corrupt tail (counted in ``stats`` and logged once). Raises
    `BusLogError` only if the file is not a bus log at all."""
    st = stats if stats is not None else BusLogStats()
    with open(path, "rb", buffering=1 << 16) as f:
        yield from _scan(f, st)
    if st.dropped_bytes:
        log.warning("bus log %s: %s after %d records; %d bytes dropped", os.fspath(path),
                    st.reason, st.records, st.dropped_bytes)


def read_bus_log(path: str | os.PathLike, *,
                 stats: BusLogStats | None = None) -> Iterator[tuple[str, bytes]]:
    """Yield ``(key, payload)`` of every valid record (see `read_bus_log_records`)."""
    for rec in read_bus_log_records(path, stats=stats):
        yield rec.key, rec.payload


class BusLogWriter:
    """Append-only bus log writer (see the module text for the durability promise).

    ``append=True`` (default) continues an existing log after cutting its torn tail off (a
    file that is not a bus log raises `BusLogError`); ``append=False`` starts a new file.
    ``clock``: gives ``t_recv_s`` when `append` is not handed one (default: wall time,
    ``time.time``). Thread-safe."""

    def __init__(self, path: str | os.PathLike, *, append: bool = True,
                 flush_interval_s: float = 0.25, max_buffer_bytes: int = 1 << 20,
                 fsync: bool = True, clock: Callable[[], float] = time.time):
        if not (0 < flush_interval_s <= 1.0):
            raise ValueError(f"flush_interval_s must be in (0, 1], got {flush_interval_s!r}")
        self.path = os.fspath(path)
        self.flush_interval_s = float(flush_interval_s)
        self.max_buffer_bytes = int(max_buffer_bytes)
        self.fsync = bool(fsync)
        self.clock = clock
        self.recovered = BusLogStats()  # what reopening found (append mode)
        self.records = 0
        self.bytes_written = 0
        self.flushes = 0
        self.write_errors = 0
        self._buf = bytearray()
        self._lock = threading.Lock()
        self._fsync_lock = threading.Lock()
        self._closed = False
        self._fd = self._open(append)
        self._last_flush = time.monotonic()
        self._wake = threading.Event()
        self._thread = threading.Thread(target=self._flusher, name=f"buslog:{self.path}",
                                        daemon=True)
        self._thread.start()

    def _open(self, append: bool) -> int:
        flags = os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0)
        fd = os.open(self.path, flags | (0 if append else os.O_TRUNC), 0o644)
        try:
            size = os.fstat(fd).st_size
            if size:
                with os.fdopen(os.dup(fd), "rb", buffering=1 << 16) as f:
                    for _ in _scan(f, self.recovered):
                        pass
                if self.recovered.dropped_bytes:
                    log.warning("bus log %s: %s after %d records; cut %d bytes before "
                                "appending", self.path, self.recovered.reason,
                                self.recovered.records, self.recovered.dropped_bytes)
                keep = self.recovered.valid_bytes
                if keep < len(MAGIC):
                    keep = 0
                os.ftruncate(fd, keep)
                os.lseek(fd, keep, os.SEEK_SET)
                if keep == 0:
                    self._write_all(fd, MAGIC)
            else:
                self._write_all(fd, MAGIC)
            os.fsync(fd)
            _fsync_dir(self.path)
        except BaseException:
            os.close(fd)
            raise
        return fd

    @staticmethod
    def _write_all(fd: int, data: bytes | bytearray | memoryview) -> None:
        view = memoryview(data)
        while view:
            n = os.write(fd, view)
            view = view[n:]

    def append(self, key: str, payload: bytes | bytearray | memoryview,
               t_recv_s: float | None = None) -> None:
        """Add one record. Raises `BusLogError` for a key/payload too large to frame and
        RuntimeError after `close`."""
        if not isinstance(key, str):
            raise TypeError(f"key must be a str, got {type(key).__name__}")
        if not isinstance(payload, (bytes, bytearray, memoryview)):
            raise TypeError(f"payload must be bytes, got {type(payload).__name__}")
        t = self.clock() if t_recv_s is None else float(t_recv_s)
        rec = _encode_record(key, bytes(payload), t)
        with self._lock:
            if self._closed:
                raise RuntimeError("BusLogWriter is closed")
            self._buf += rec
            self.records += 1
            due = (len(self._buf) >= self.max_buffer_bytes
                   or time.monotonic() - self._last_flush >= self.flush_interval_s)
        if due:
            self.flush()

    def flush(self, fsync: bool | None = None) -> None:
        """Hand the buffer to the kernel now (and fsync it, by default)."""
        with self._lock:
            self._write_buffer_locked()
        if self.fsync if fsync is None else fsync:
            with self._fsync_lock:
                if self._fd >= 0:
                    try:
                        os.fsync(self._fd)
                    except OSError as e:
                        self.write_errors += 1
                        log.error("bus log %s: fsync failed: %s", self.path, e)

    def _write_buffer_locked(self) -> None:
        self._last_flush = time.monotonic()
        if not self._buf or self._fd < 0:
            return
        data, self._buf = self._buf, bytearray()
        try:
            self._write_all(self._fd, data)
            self.bytes_written += len(data)
            self.flushes += 1
        except OSError as e:  # disk full, ...: counted, logged, the process goes on
            self.write_errors += 1
            log.error("bus log %s: write failed, %d bytes lost: %s", self.path, len(data), e)

    def _flusher(self) -> None:
        while not self._wake.wait(self.flush_interval_s / 2):
            with self._lock:
                due = bool(self._buf) and (time.monotonic() - self._last_flush
                                           >= self.flush_interval_s / 2)
            if due:
                self.flush()

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Write and fsync everything, stop the flusher thread, close the file (idempotent)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._wake.set()
        self._thread.join()
        self.flush(fsync=self.fsync)
        with self._fsync_lock, self._lock:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> BusLogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"BusLogWriter({self.path!r}, {self.records} records{' closed' if self._closed else ''})"


def _fsync_dir(path: str) -> None:
    """fsync the directory holding a new file, so the file's name survives an OS crash."""
    try:
        dfd = os.open(os.path.dirname(os.path.abspath(path)), os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(dfd)
    except OSError:
        pass
    finally:
        os.close(dfd)


class BusRecorder:
    """Record every payload a transport receives on ``key_expr`` into a bus log.

    With a transport that offers ``subscribe_raw`` (`ZenohTransport`), payloads are recorded
    as received, malformed ones included (replay rejects them again, and counts them);
    otherwise (`InMemoryTransport`) every valid message is re-encoded, which gives the same
    bytes (the codec is deterministic). ``writer``: a `BusLogWriter` or a path. A payload larger
    than the codec's bound (`sitl.bus.codec.MAX_PAYLOAD_BYTES`: no message can be that large) is
    not written, only counted (``oversize``): a flood of huge junk must not fill the disk.

    A vehicle group's columnar epoch (`UavGroupEpoch`, key ``<run>/uavs/<group>/epoch``) is
    recorded as the per-UAV messages it holds (``UavGroupEpoch.per_uav``: the keys, payloads and
    order the group publishes without it), so a log reads the same whichever way the group
    published (``group_epochs`` counts them); a malformed one is recorded as received."""

    def __init__(self, transport: Any, path_or_writer: str | os.PathLike | BusLogWriter,
                 key_expr: str = "**", **writer_kw: Any):
        self.writer = (path_or_writer if isinstance(path_or_writer, BusLogWriter)
                       else BusLogWriter(path_or_writer, **writer_kw))
        self.key_expr = key_expr
        self.errors = 0
        self.oversize = 0
        self.group_epochs = 0
        self.raw = hasattr(transport, "subscribe_raw")
        try:
            if self.raw:
                self._sub = transport.subscribe_raw(key_expr, self._on_raw)
            else:
                self._sub = transport.subscribe(key_expr, self._on_message)
        except Exception:
            self.writer.close()
            raise

    def _on_message(self, key: str, msg: Any) -> None:
        if type(msg) is UavGroupEpoch:
            self._on_group(key, msg)
        else:
            self._append(key, encode(msg))

    def _on_raw(self, key: str, payload: bytes) -> None:
        if len(payload) > MAX_PAYLOAD_BYTES:
            self.oversize += 1
            return
        hit = parse_key(key)
        if hit is not None and hit[1] is UavGroupEpoch:
            try:
                msg = decode(payload)
            except BusDecodeError:
                msg = None
            if type(msg) is UavGroupEpoch:
                self._on_group(key, msg, hit[0])
                return
        self._append(key, payload)

    def _on_group(self, key: str, msg: UavGroupEpoch, run_id: str | None = None) -> None:
        if run_id is None:
            hit = parse_key(key)
            if hit is None:
                self._append(key, encode(msg))
                return
            run_id = hit[0]
        self.group_epochs += 1
        for k, m in msg.per_uav(run_id):
            self._append(k, encode(m))

    def _append(self, key: str, payload: bytes) -> None:
        try:
            self.writer.append(key, payload)
        except (BusLogError, RuntimeError) as e:
            self.errors += 1
            log.error("bus recorder: %s", e)

    @property
    def records(self) -> int:
        return self.writer.records

    def close(self) -> None:
        """Stop recording and close the log (idempotent)."""
        self._sub.close()
        self.writer.close()

    def __enter__(self) -> BusRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["MAGIC", "BusLogError", "BusLogStats", "BusLogWriter", "BusRecord", "BusRecorder",
           "read_bus_log", "read_bus_log_records"]
