"""MAVLink framing of UDP datagrams, MAVLink 2 signing checks, signing keys and .tlog files.

Pure byte-level helpers of the endpoint (no sockets), each testable alone.

Framing: a datagram may carry several packets back to back.  :func:`split_datagram` walks
it: a MAVLink 2 frame starts with 0xFD (10-byte header, payload, 2-byte CRC, 13-byte
signature when incompat flag 0x01 is set), a MAVLink 1 frame with 0xFE (6-byte header,
payload, CRC).  Bytes that are not a frame start are skipped up to the next start byte and
counted once per run as ``garbage``; a frame that runs past the datagram's end is
``truncated``.  The CRC (with the message's CRC_EXTRA) is checked later, by pymavlink's
decode, on each frame.  :func:`frame_datagram` gives frames and rejects in datagram order
(the endpoint's one verdict per datagram is its first failure).

Signing (mavlink.io "Message Signing"): signature = first 6 bytes of
SHA-256(secret_key + frame[:-6]) (the frame up to and including link id and the 48-bit
timestamp in units of 10 us since 2015-01-01).  :class:`SignatureChecker` verifies the
signature BEFORE it records the stream's timestamp, so that a forged frame cannot move a
stream's timestamp forward and lock out the real sender (pymavlink 2.4's check_signature
records it first); a frame more than the future window ahead of our own clock is
``future`` (checked before anything is recorded: it neither moves a stream nor our clock); a
stream (link id, sysid, compid) must then rise strictly (``replayed`` otherwise), a new
stream is accepted if its timestamp is at most one minute behind ours, and no stream at all
at or below the checker's ``floor`` (the bound restored after a restart, see
:class:`SigningStateFile`).

Signing state across restarts (:class:`SigningStateFile`, ``OUT/mav_signing_<sysid>.json``):
mavlink.io "Timestamp Handling" asks that the timestamp be stored in persistent storage
(ideally at least once a minute) and that the timestamp used at start-up be the maximum of
the system clock's and the stored one.  The file holds our last timestamp, the per-stream
timestamps seen, and ``reserved``: a bound written BEFORE any timestamp above it is sent or
accepted (the endpoint renews it a few seconds ahead), so that after a crash between two
saves every frame accepted before it is still at or below ``reserved``.  At start the
endpoint sends from above ``reserved`` and makes ``reserved`` the floor of every stream.

Key files (:func:`load_signing_key`): 32 raw bytes, or 64 hex characters, or else a
passphrase whose SHA-256 is the key (what MAVProxy's ``signing setup PASSPHRASE`` uses).

.tlog (pymavlink's telemetry log): each record is an 8-byte big-endian unix time in
microseconds followed by the raw packet; mavutil.mavlink_connection(path) and
mavlogdump.py read it.
"""
from __future__ import annotations

import hashlib
import os
import struct
from typing import NamedTuple

STX_V2 = 0xFD
STX_V1 = 0xFE
HEADER_LEN_V2 = 10
HEADER_LEN_V1 = 6
CRC_LEN = 2
SIGNATURE_LEN = 13
IFLAG_SIGNED = 0x01
#: a new stream's timestamp may lag ours by at most one minute (10 us units)
NEW_STREAM_MAX_LAG = 60 * 100_000
#: signing timestamps: 10 us units (100,000 per second)
#: unix seconds of 2015-01-01T00:00:00 UTC, the epoch of MAVLink 2 signing timestamps
SIGNING_EPOCH_UNIX_S = 1_420_070_400.0
SIGNING_TICKS_PER_S = 100_000
SIGNING_STATE_FORMAT = "skyfuse.mavlink.signing/1"

_TLOG_TIME = struct.Struct(">Q")


class Frame(NamedTuple):
    """One framed packet: raw bytes, MAVLink version (1/2), incompat flags, msgid, sender."""

    buf: bytes
    version: int
    incompat_flags: int
    msgid: int
    sysid: int
    compid: int

    @property
    def signed(self) -> bool:
        return bool(self.incompat_flags & IFLAG_SIGNED)


def frame_datagram(data: bytes) -> list:
    """What a datagram holds, in order: each item a :class:`Frame` or a reject reason (str).

    Never raises on any bytes. Reasons: 'garbage' (one per run of non-frame bytes),
    'truncated' (a frame running past the end: the rest of the datagram).
    """
    items: list = []
    n = len(data)
    i = 0
    while i < n:
        b = data[i]
        if b == STX_V2:
            if n - i < HEADER_LEN_V2 + CRC_LEN:
                items.append("truncated")
                break
            plen, flags = data[i + 1], data[i + 2]
            total = HEADER_LEN_V2 + plen + CRC_LEN + (SIGNATURE_LEN if flags & IFLAG_SIGNED else 0)
            if n - i < total:
                items.append("truncated")
                break
            msgid = data[i + 7] | (data[i + 8] << 8) | (data[i + 9] << 16)
            items.append(Frame(bytes(data[i:i + total]), 2, flags, msgid, data[i + 5], data[i + 6]))
            i += total
        elif b == STX_V1:
            if n - i < HEADER_LEN_V1 + CRC_LEN:
                items.append("truncated")
                break
            total = HEADER_LEN_V1 + data[i + 1] + CRC_LEN
            if n - i < total:
                items.append("truncated")
                break
            items.append(Frame(bytes(data[i:i + total]), 1, 0, data[i + 5], data[i + 3], data[i + 4]))
            i += total
        else:
            j2, j1 = data.find(b"\xfd", i + 1), data.find(b"\xfe", i + 1)
            nxt = min(j for j in (j2, j1, n) if j >= 0)
            items.append("garbage")
            i = nxt
    return items


def split_datagram(data: bytes) -> tuple[list[Frame], list[str]]:
    """Frames found in a datagram and the reasons of what was rejected on the way
    (:func:`frame_datagram` split in two lists). Never raises on any bytes."""
    items = frame_datagram(data)
    return [x for x in items if not isinstance(x, str)], [x for x in items if isinstance(x, str)]


def signature_ok(buf: bytes, key: bytes) -> bool:
    """True if the 6-byte signature at the end of a signed MAVLink 2 frame matches key."""
    return hashlib.sha256(key + buf[:-6]).digest()[:6] == buf[-6:]


def signature_timestamp(buf: bytes) -> int:
    """The 48-bit signing timestamp (10 us since 2015-01-01) of a signed frame."""
    return int.from_bytes(buf[-12:-6], "little")


class SignatureChecker:
    """Accept/reject incoming frames when signing is on (see the module docstring).

    ``floor``: no timestamp at or below it is accepted on any stream (0: none; set from the
    persisted ``reserved`` bound after a restart).  ``streams``: {(link id, sysid, compid):
    last accepted timestamp}."""

    def __init__(self, key: bytes):
        if not isinstance(key, (bytes, bytearray)) or len(key) != 32:
            raise ValueError(f"signing key must be 32 bytes, got {type(key).__name__} of length "
                             f"{len(key) if hasattr(key, '__len__') else '?'}")
        self.key = bytes(key)
        self._streams: dict[tuple[int, int, int], int] = {}
        self.floor = 0

    @property
    def streams(self) -> dict[tuple[int, int, int], int]:
        return dict(self._streams)

    def restore(self, streams: dict, floor: int = 0) -> None:
        """Take back the streams' timestamps and the floor saved before a restart (never lowers
        what is already known)."""
        for k, ts in streams.items():
            k = tuple(int(v) for v in k)
            self._streams[k] = max(int(ts), self._streams.get(k, 0))
        self.floor = max(self.floor, int(floor))

    def check(self, frame: Frame, our_timestamp: int, future_limit: int | None = None) -> str | None:
        """None if accepted, else the reject reason ('unsigned', 'bad_signature', 'future',
        'replayed'). future_limit: the largest timestamp accepted (None: no limit)."""
        if frame.version != 2 or not frame.signed:
            return "unsigned"
        buf = frame.buf
        if not signature_ok(buf, self.key):
            return "bad_signature"
        ts = signature_timestamp(buf)
        if future_limit is not None and ts > future_limit:
            return "future"
        if ts <= self.floor:
            return "replayed"
        stream = (buf[-13], frame.sysid, frame.compid)
        last = self._streams.get(stream)
        if last is not None:
            if ts <= last:
                return "replayed"
        elif ts + NEW_STREAM_MAX_LAG < our_timestamp:
            return "replayed"
        self._streams[stream] = ts
        return None


class SigningStateFile:
    """One endpoint's signing state on disk (JSON), written atomically (a temporary file in the
    same directory, then ``os.replace``: a reader, or a restart after a crash, sees the old
    file or the new one, never a mix; no fsync -- it survives the process, not a power cut)::

        {"format": "skyfuse.mavlink.signing/1", "sysid": 1,
         "timestamp": T,        # our signing timestamp at the save (10 us since 2015-01-01)
         "reserved": B,         # nothing above B was sent or accepted before the next save
         "streams": [[link_id, sysid, compid, last_timestamp], ...]}
    """

    def __init__(self, path: str | os.PathLike, sysid: int):
        self.path = os.fspath(path)
        self.sysid = int(sysid)

    def load(self) -> dict | None:
        """{"timestamp", "reserved", "streams": {(l, s, c): ts}} or None if there is no file;
        ValueError if it cannot be read or is not a state of this system id."""
        import json
        try:
            with open(self.path, encoding="utf-8") as f:
                d = json.load(f)
        except FileNotFoundError:
            return None
        except (OSError, ValueError) as e:
            raise ValueError(f"signing state {self.path!r} unreadable: {e}") from None
        try:
            if d.get("format") != SIGNING_STATE_FORMAT or int(d["sysid"]) != self.sysid:
                raise ValueError("not a signing state of this system id")
            out = {"timestamp": int(d["timestamp"]), "reserved": int(d["reserved"]),
                   "streams": {(int(a), int(b), int(c)): int(t) for a, b, c, t in d["streams"]}}
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            raise ValueError(f"signing state {self.path!r} invalid: {e}") from None
        if not all(0 <= v < 1 << 48 for v in (out["timestamp"], out["reserved"], *out["streams"].values())):
            raise ValueError(f"signing state {self.path!r} invalid: a timestamp outside 48 bits")
        return out

    def save(self, timestamp: int, reserved: int, streams: dict) -> None:
        """Write the state atomically (OSError if the directory cannot be written)."""
        import json
        d = {"format": SIGNING_STATE_FORMAT, "sysid": self.sysid, "timestamp": int(timestamp),
             "reserved": int(reserved), "streams": [[*k, int(t)] for k, t in sorted(streams.items())]}
        tmp = f"{self.path}.tmp"
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(d, f, separators=(",", ":"))
        os.replace(tmp, self.path)


def load_signing_key(path: str | os.PathLike) -> bytes:
    """A 32-byte signing key from a key file (raw 32 bytes, 64 hex chars, or a passphrase)."""
    try:
        with open(path, "rb") as f:
            data = f.read(4096)
    except OSError as e:
        raise ValueError(f"cannot read signing key file {os.fspath(path)!r}: {e.strerror}") from None
    if len(data) == 32:
        return data
    text = data.strip()
    if not text:
        raise ValueError(f"signing key file {os.fspath(path)!r} is empty")
    if len(text) == 64:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    return hashlib.sha256(text).digest()


def fresh_tlog_path(path: str | os.PathLike) -> str:
    """``path`` if no file is there, else the first free ``<stem>.r<k>.tlog`` (k = 1, 2, ...): a
    worker restarted inside a run gets its own file and never overwrites nor appends to what its
    previous start recorded. (The launcher clears a previous run's tlogs from a re-used output
    directory before its workers start, so a run's first file is always ``path``.)"""
    path = os.fspath(path)
    stem = path[:-5] if path.endswith(".tlog") else path
    k, p = 0, path
    while os.path.exists(p):
        k += 1
        p = f"{stem}.r{k}.tlog"
    return p


class TlogWriter:
    """Write MAVLink packets to a new .tlog, as MAVProxy does: each record an 8-byte big-endian
    time stamp in microseconds since the Unix epoch, then the raw packet. The file is created
    (truncated if there), never appended to.

    ``stamp_clock`` (unix s) stamps the records: the live workers pass the WALL clock, as MAVProxy
    stamps its tlogs (the simulated time stays inside the messages: SYSTEM_TIME, GPS_RAW_INT ...);
    None stamps each record with the unix time its writer gives (offline runs: simulated time).
    Several endpoints may share one writer (mavlogdump separates them by system id).
    ``flush_interval_s`` of stamp time between flushes to the OS (and at close).
    """

    def __init__(self, path: str | os.PathLike, flush_interval_s: float = 1.0, *, stamp_clock=None):
        if stamp_clock is not None and not callable(stamp_clock):
            raise ValueError("stamp_clock must be callable (unix seconds) or None")
        try:
            self._f = open(path, "wb")
        except OSError as e:
            raise ValueError(f"cannot open tlog {os.fspath(path)!r}: {e.strerror}") from None
        self.path = os.fspath(path)
        self._stamp_clock = stamp_clock
        self._flush_interval_s = float(flush_interval_s)
        self._next_flush_s = None
        self.records = 0

    def write(self, unix_s: float, packet: bytes) -> None:
        """Record ``packet``; ``unix_s``: its simulated unix time (the stamp without a stamp_clock)."""
        if self._f is None:
            return
        t = self._stamp_clock() if self._stamp_clock is not None else unix_s
        self._f.write(_TLOG_TIME.pack(max(0, int(t * 1e6))) + packet)
        self.records += 1
        if self._next_flush_s is None:
            self._next_flush_s = t + self._flush_interval_s
        elif t >= self._next_flush_s:
            self._f.flush()
            self._next_flush_s = t + self._flush_interval_s

    def flush(self) -> None:
        if self._f is not None:
            self._f.flush()

    def close(self) -> None:
        if self._f is not None:
            self._f.close()
            self._f = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
