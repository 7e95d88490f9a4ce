"""A vehicle's MAVLink FTP server: ``@PARAM/param.pck`` read-only, pure and time-driven.

No sockets and no clock: ``handle(payload, now_s, peer)`` takes one FILE_TRANSFER_PROTOCOL
payload (the message's 251-byte ``payload`` field, or its bytes) and returns the reply
payloads (251 bytes each) to send back, in order; ``now_s`` is the simulation time, used
only for the session timeouts.  One :class:`FtpServer` per vehicle.

The endpoint (vehicles/mavlink/endpoint/vehicle.py) holds one per vehicle, answers the
FILE_TRANSFER_PROTOCOL messages addressed to it and advertises the capability bits of
:func:`advertised_capabilities` in AUTOPILOT_VERSION.

``handle_message`` returns ``(target_network, target_system, target_component, payload)``
tuples for ``file_transfer_protocol_send``: network 0, the requester's system and component
(ArduPilot's GCS_FTP::send_reply does the same; MAVProxy drops a reply whose target is not its
own source system/component).  ``peer`` keys the sessions: pass the sender's address (the
source system/component are added by handle_message), so two GCSs never share a session.
``ftp.counters`` (FTP_COUNTERS; the FTP_REJECT_REASONS are Naks or dropped inputs) can be
merged into the endpoint's counters with a ``ftp_`` prefix; ``ftp.last_reason`` is one line
about the last reject.  ``handle`` never raises.

Addressing: the endpoint's frame filter lets target_system 0 through; :func:`addressed_to`
answers FTP only when it names this vehicle (system == ours, component 0 or ours): a file
session belongs to one vehicle, and a broadcast request on a shared link would get every
vehicle's replies under the same session id.  MAVProxy fills in the vehicle's system id
(its target_system, learnt from the HEARTBEAT) and component 0 or 1.

MAVProxy 1.8.75 (mavproxy_param.py, mavproxy_ftp.py; read, and run against this server over
UDP loopback).  On connection its param module asks for ``@PARAM/param.pck?withdefaults=1``
(FTP first; it checks neither AUTOPILOT_VERSION's capabilities nor the HEARTBEAT's autopilot)
with OpenFileRO, then one BurstReadFile of 239-byte blocks, fills gaps with ReadFile, and
sends TerminateSession.  It retries an unanswered open with the same seq (1 s, then its RTT
estimate) 10 times, then gives up and sends PARAM_REQUEST_LIST (~11 s after the first try); a
Nak of the open falls back at its next 1 s check.  A file it cannot decode (bad magic, a count
that disagrees with total_params) makes it retry FTP every second without falling back: the
packer must never produce one.

The protocol (mavlink.io "File Transfer Protocol (FTP)", mavlink/mavlink-devguide
en/services/ftp.md, and ArduPilot's libraries/GCS_MAVLink/GCS_FTP.cpp, both read for this
work).  Payload header: u16 seq, u8 session, u8 opcode, u8 size, u8 req_opcode,
u8 burst_complete, u8 padding, u32 offset, data[239]; all little-endian.  A reply has
seq = request seq + 1 (u16), the request's session, req_opcode = the request's opcode, and
opcode Ack (128) or Nak (129, data[0] = error, size 1; FailErrno adds errno in data[1]).

  None (0)            Ack
  TerminateSession 1  close the session, Ack (also when nothing was open)
  ResetSessions 2     close every session of this peer, Ack
  ListDirectory 3     "" and "/" -> "D@PARAM"; "@PARAM" -> "Fparam.pck\\t<size>"; offset =
                      first entry; past the end Nak EOF; anything else Nak FileNotFound
  OpenFileRO 4        @PARAM/param.pck[?withdefaults=1&start=N&count=C]: takes a snapshot of
                      the store's values, Ack size 4, data = u32 file size.  The session id is
                      the one the client sent: MAVProxy 1.8.75 picks its own and routes the
                      replies by it; a client that lets the server choose (the spec's model)
                      takes the Ack's; ArduPilot assigns a new id to session 0 only, which
                      would strand MAVProxy's replies 1 time in 256.  Another path Nak
                      FileNotFound; a bad query, or an empty store, Nak FailErrno/EINVAL (the
                      GCS falls back to the list protocol); a session already open Nak Fail
                      (ArduPilot); no free session Nak NoSessionsAvailable
  ReadFile 5          size bytes (1..239) at offset, Ack with offset and size; at/after EOF
                      Nak EOF
  BurstReadFile 15    from offset, Acks of min(size or 239, 239) bytes with seq + 1, + 2, ...
                      until EOF (then Nak EOF, burst_complete 1, offset = file size) or
                      ``burst_packets`` packets (the last has burst_complete 1; the client asks
                      again from the next offset), as ArduPilot (2000 packets a burst)
  CalcFileCRC32 14    the file's CRC32 as ArduPilot's crc_crc32 (standard table, seed 0, no
                      final xor: MAVProxy's ``ftp crclocal``), Ack size 4
  CreateFile 6, WriteFile 7, RemoveFile 8, CreateDirectory 9, RemoveDirectory 10,
  OpenFileWO 11, Rename 13      Nak FileProtected: the file system is read-only (no param.pck
                      upload; PARAM_SET is the way to write)
  TruncateFile 12, ListDirectoryWithTime 16 and unknown opcodes   Nak UnknownCommand
                      (MAVProxy's ``ftp list`` then falls back to ListDirectory)
  Ack / Nak received  dropped, counted (answering a reply could loop two servers)

Input checks (each a Nak with a counted reason and ``last_reason``; nothing raises): size
> 239 InvalidDataSize; a path whose length disagrees with size (ArduPilot's check_name_len)
InvalidDataSize; ReadFile / BurstReadFile on a session that is not open InvalidSession.  A
payload that is not 1..251 bytes of 0..255 (a list holding NaN, a str, ...) cannot be
answered (no trustworthy seq): counted ``malformed`` and dropped.  A payload shorter than
251 bytes is zero-extended first: MAVLink 2 strips trailing zero bytes on the wire.

Retransmission (the spec: "the drone must re-send its response if a request with the same
sequence number is received").  Per (peer, session) the last request and its replies are
kept; the same request again (same seq and same bytes) gets the same replies without being
executed again (counted ``retransmits``): a lost OpenFileRO Ack retried by MAVProxy with the
same seq gets its Ack, not "already open".  ArduPilot keeps one reply for all sessions.

Sessions: at most ``max_sessions`` (5, ArduPilot's AP_MAVLINK_FTP_MAX_SESSIONS) open files;
one idle for ``session_timeout_s`` (3 s, ArduPilot's FTP_SESSION_TIMEOUT) may be taken over
by a new open, one idle for ``session_kill_s`` (20 s, FTP_SESSION_KILL_TIMEOUT) is closed.
Idle is measured in the ``now_s`` given to handle(); a non-finite or backwards now_s is
replaced by the last good one.

Snapshots: OpenFileRO copies the store's values; the bytes are built at the first read, with
the padding laid out against that read's size (ArduPilot's rule, see param_pck.py), and are
then fixed for the session, so every re-read of a lost block returns the same bytes (any
read size is served; ArduPilot refuses a second size).  The size in the open Ack is that of
the file for 239-byte reads (ArduPilot sends an estimate, 12 bytes per parameter).  A
PARAM_SET during a download changes the next open, not the file being read.
"""
from __future__ import annotations

import math
import struct
import zlib
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Hashable, Mapping, Sequence

from . import param_pck

# opcodes (mavlink.io FTP "OpCodes")
OP_NONE, OP_TERMINATE_SESSION, OP_RESET_SESSIONS, OP_LIST_DIRECTORY = 0, 1, 2, 3
OP_OPEN_FILE_RO, OP_READ_FILE, OP_CREATE_FILE, OP_WRITE_FILE, OP_REMOVE_FILE = 4, 5, 6, 7, 8
OP_CREATE_DIRECTORY, OP_REMOVE_DIRECTORY, OP_OPEN_FILE_WO, OP_TRUNCATE_FILE = 9, 10, 11, 12
OP_RENAME, OP_CALC_FILE_CRC32, OP_BURST_READ_FILE, OP_LIST_DIRECTORY_WITH_TIME = 13, 14, 15, 16
OP_ACK, OP_NAK = 128, 129
# Nak error codes (mavlink.io FTP "NAK Error Information")
ERR_NONE, ERR_FAIL, ERR_FAIL_ERRNO, ERR_INVALID_DATA_SIZE, ERR_INVALID_SESSION = 0, 1, 2, 3, 4
ERR_NO_SESSIONS_AVAILABLE, ERR_EOF, ERR_UNKNOWN_COMMAND, ERR_FILE_EXISTS = 5, 6, 7, 8
ERR_FILE_PROTECTED, ERR_FILE_NOT_FOUND = 9, 10
EINVAL = 22

PAYLOAD_LEN = 251
HEADER_LEN = 12
DATA_LEN = PAYLOAD_LEN - HEADER_LEN  # 239
PARAM_DIR = "@PARAM"
PARAM_PATH = PARAM_DIR + "/" + param_pck.PACKED_NAME

MAV_PROTOCOL_CAPABILITY_FTP = 32  # pymavlink's mavlink.MAV_PROTOCOL_CAPABILITY_FTP (common.xml)

_WRITE_OPS = (OP_CREATE_FILE, OP_WRITE_FILE, OP_REMOVE_FILE, OP_CREATE_DIRECTORY, OP_REMOVE_DIRECTORY,
              OP_OPEN_FILE_WO, OP_RENAME)

#: inputs Nak'd or dropped, by reason
FTP_REJECT_REASONS = ("malformed", "bad_size", "bad_name", "not_found", "bad_query", "already_open",
                      "no_sessions", "invalid_session", "read_only", "unknown_opcode", "stray_reply",
                      "bad_time")
#: traffic
FTP_TRAFFIC_COUNTERS = ("requests", "replies", "retransmits", "opened", "closed", "expired", "taken_over",
                        "eof", "bytes_served")
FTP_COUNTERS = FTP_TRAFFIC_COUNTERS + FTP_REJECT_REASONS


def advertised_capabilities(capabilities: int) -> int:
    """AUTOPILOT_VERSION.capabilities with MAV_PROTOCOL_CAPABILITY_FTP set: the spec's
    discovery rule (mavlink.io FTP, "Protocol Discovery").  MAVProxy 1.8.75 does not look at
    it: its param module tries ``@PARAM/param.pck?withdefaults=1`` first whenever its ftp
    module is loaded (the default) and falls back to PARAM_REQUEST_LIST only after a Nak or
    ~11 s of silence (10 retries of the open)."""
    return int(capabilities) | MAV_PROTOCOL_CAPABILITY_FTP


def addressed_to(target_system: int, target_component: int, sysid: int, compid: int) -> bool:
    """Whether a FILE_TRANSFER_PROTOCOL request is this vehicle's to answer (no broadcast)."""
    return target_system == sysid and target_component in (0, compid)


@dataclass
class FtpOp:
    """One FTP payload, decoded (or to encode): the header fields and ``data[:size]``."""

    seq: int = 0
    session: int = 0
    opcode: int = OP_NONE
    size: int = 0
    req_opcode: int = 0
    burst_complete: int = 0
    offset: int = 0
    data: bytes = b""
    #: on unpack: the whole data area (239 bytes), for the path checks
    buffer: bytes = field(default=b"", repr=False, compare=False)

    def pack(self) -> bytes:
        """The 251-byte payload (data zero-padded)."""
        hdr = struct.pack("<HBBBBBBI", self.seq & 0xFFFF, self.session, self.opcode, self.size,
                          self.req_opcode, self.burst_complete, 0, self.offset & 0xFFFFFFFF)
        return (hdr + bytes(self.data)[:DATA_LEN]).ljust(PAYLOAD_LEN, b"\x00")

    @classmethod
    def unpack(cls, payload: bytes) -> "FtpOp":
        p = bytes(payload).ljust(PAYLOAD_LEN, b"\x00")
        seq, session, opcode, size, req, burst, _pad, offset = struct.unpack("<HBBBBBBI", p[:HEADER_LEN])
        return cls(seq, session, opcode, size, req, burst, offset, p[HEADER_LEN:HEADER_LEN + min(size, DATA_LEN)],
                   p[HEADER_LEN:])


@dataclass
class _Session:
    query: param_pck.Query
    entries: list
    opened_s: float
    last_s: float
    prebuilt: bytes  # the file for 239-byte reads, built at the open for its size
    file: bytes | None = None  # fixed at the first read

    def data(self, block: int) -> bytes:
        if self.file is None:
            self.file = self.prebuilt if block == param_pck.BLOCK else param_pck.pack(self.entries, self.query, block)
        return self.file


@dataclass
class _Last:
    request: bytes
    replies: list = field(default_factory=list)


class FtpServer:
    """One vehicle's FTP server over its parameter store (see the module docstring)."""

    def __init__(self, params: Mapping[str, float], *, max_sessions: int = 5, session_timeout_s: float = 3.0,
                 session_kill_s: float = 20.0, burst_packets: int = 2000):
        if not isinstance(params, Mapping):
            raise ValueError(f"params must be a mapping (a ParamStore), got {type(params).__name__}")
        if not 1 <= int(max_sessions) <= 255:
            raise ValueError(f"max_sessions must be 1..255, got {max_sessions!r}")
        if not (0 < float(session_timeout_s) <= float(session_kill_s)):
            raise ValueError("need 0 < session_timeout_s <= session_kill_s, got "
                             f"{session_timeout_s!r}, {session_kill_s!r}")
        if not 1 <= int(burst_packets) <= 65535:
            raise ValueError(f"burst_packets must be 1..65535, got {burst_packets!r}")
        self.params = params
        self.max_sessions = int(max_sessions)
        self.session_timeout_s = float(session_timeout_s)
        self.session_kill_s = float(session_kill_s)
        self.burst_packets = int(burst_packets)
        self.counters = dict.fromkeys(FTP_COUNTERS, 0)
        self.last_reason: str | None = None
        self._sessions: dict[tuple, _Session] = {}
        self._last: OrderedDict[tuple, _Last] = OrderedDict()  # retransmission cache
        self._now = 0.0

    # ------------------------------------------------------------------ entry points
    @property
    def sessions_open(self) -> int:
        return len(self._sessions)

    def handle_message(self, msg, now_s: float, peer: Hashable = None) -> list[tuple[int, int, int, list[int]]]:
        """A pymavlink FILE_TRANSFER_PROTOCOL message -> ``file_transfer_protocol_send`` args."""
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        replies = self.handle(msg.payload, now_s, peer=(peer, src))
        return [(0, src[0], src[1], list(r)) for r in replies]

    def handle(self, payload, now_s: float, peer: Hashable = None) -> list[bytes]:
        """One request payload -> the reply payloads (251 bytes each), never raises."""
        try:
            return self._handle(payload, now_s, peer)
        except Exception as e:  # a bug met by some input: count it, answer nothing
            return self._drop("malformed", f"internal error on this request: {type(e).__name__}: {e}")

    # ------------------------------------------------------------------ internals
    def _reject(self, reason: str, line: str) -> None:
        self.counters[reason] += 1
        self.last_reason = line

    def _drop(self, reason: str, line: str) -> list[bytes]:
        self._reject(reason, line)
        return []

    def _clock(self, now_s) -> None:
        try:
            t = float(now_s)
        except (TypeError, ValueError):
            t = math.nan
        if not math.isfinite(t) or t < self._now:
            self._reject("bad_time", f"now_s {now_s!r} is not finite or goes back; using {self._now}")
            return
        self._now = t

    @staticmethod
    def _as_bytes(payload) -> bytes | None:
        if isinstance(payload, (bytes, bytearray, memoryview)):
            b = bytes(payload)
        else:
            try:
                items = list(payload)
            except TypeError:
                return None
            if not all(isinstance(x, int) and not isinstance(x, bool) and 0 <= x <= 255 for x in items):
                return None
            b = bytes(items)
        return b if 1 <= len(b) <= PAYLOAD_LEN else None

    def _handle(self, payload, now_s, peer) -> list[bytes]:
        raw = self._as_bytes(payload)
        if raw is None:
            return self._drop("malformed", f"payload is not 1..{PAYLOAD_LEN} bytes of 0..255: "
                                           f"{type(payload).__name__} {str(payload)[:40]}")
        self._clock(now_s)
        self._expire()
        req = FtpOp.unpack(raw)
        if req.opcode in (OP_ACK, OP_NAK):
            return self._drop("stray_reply", f"an FTP {'Ack' if req.opcode == OP_ACK else 'Nak'} "
                                             f"(seq {req.seq}) is not a request")
        self.counters["requests"] += 1
        key = (peer, req.session)
        identity = raw.ljust(PAYLOAD_LEN, b"\x00")[:HEADER_LEN + min(req.size, DATA_LEN)]
        last = self._last.get(key)
        if last is not None and last.request == identity:
            self.counters["retransmits"] += 1
            replies = last.replies
        else:
            replies = [r.pack() for r in self._execute(req, peer)]
            self._last[key] = _Last(identity, replies)
            self._last.move_to_end(key)
            while len(self._last) > 4 * self.max_sessions:
                self._last.popitem(last=False)
        s = self._sessions.get(key)
        if s is not None:
            s.last_s = self._now
        self.counters["replies"] += len(replies)
        return list(replies)

    def _expire(self) -> None:
        for key in [k for k, s in self._sessions.items() if self._now - s.last_s > self.session_kill_s]:
            self._close(key)
            self.counters["expired"] += 1

    def _close(self, key) -> None:
        """Forget a session that times out or is taken over, and its cached replies: a late
        retry of its open must not get an Ack for a file that is no longer open."""
        del self._sessions[key]
        self._last.pop(key, None)

    def _reply(self, req: FtpOp, opcode=OP_ACK, data=b"", offset=0, seq_add=1, burst_complete=0) -> FtpOp:
        return FtpOp(req.seq + seq_add, req.session, opcode, len(data), req.opcode, burst_complete, offset, data)

    def _nak(self, req: FtpOp, err: int, reason: str | None = None, line: str = "", errno: int | None = None,
             **kw) -> FtpOp:
        if reason is not None:
            self._reject(reason, line)
        return self._reply(req, OP_NAK, bytes([err]) if errno is None else bytes([err, errno]), **kw)

    def _path(self, req: FtpOp) -> str | None:
        """The request's path, or None when its length disagrees with size (ArduPilot's
        check_name_len: the NUL-terminated string of the data area is size bytes long, or
        size - 1 with the NUL counted)."""
        data = req.buffer or req.data
        n = data.find(b"\x00")
        n = len(data) if n < 0 else n
        if req.size == 0 or not (n == req.size or n == req.size - 1):
            return None
        return data[:n].decode("latin-1")

    def _execute(self, req: FtpOp, peer) -> list[FtpOp]:
        op = req.opcode
        if req.size > DATA_LEN:
            return [self._nak(req, ERR_INVALID_DATA_SIZE, "bad_size",
                              f"opcode {op}: size {req.size} > {DATA_LEN}")]
        if op == OP_NONE:
            return [self._reply(req)]
        if op == OP_TERMINATE_SESSION:
            if self._sessions.pop((peer, req.session), None) is not None:
                self.counters["closed"] += 1
            return [self._reply(req)]
        if op == OP_RESET_SESSIONS:
            for key in [k for k in self._sessions if k[0] == peer]:
                del self._sessions[key]
                self.counters["closed"] += 1
            return [self._reply(req)]
        if op == OP_LIST_DIRECTORY:
            return [self._list(req)]
        if op == OP_OPEN_FILE_RO:
            return [self._open(req, peer)]
        if op in (OP_READ_FILE, OP_BURST_READ_FILE):
            return self._read(req, peer)
        if op == OP_CALC_FILE_CRC32:
            return [self._crc(req)]
        if op in _WRITE_OPS:
            return [self._nak(req, ERR_FILE_PROTECTED, "read_only",
                              f"opcode {op}: the FTP file system is read-only (@PARAM/param.pck)")]
        return [self._nak(req, ERR_UNKNOWN_COMMAND, "unknown_opcode", f"opcode {op} is not supported")]

    def _resolve(self, req: FtpOp) -> tuple[param_pck.Query | None, FtpOp | None]:
        """(query, None) for a param.pck path, else (None, the Nak)."""
        path = self._path(req)
        if path is None:
            return None, self._nak(req, ERR_INVALID_DATA_SIZE, "bad_name",
                                   f"opcode {req.opcode}: path length disagrees with size {req.size}")
        name, _, qtext = path.lstrip("/").partition("?")
        if name != PARAM_PATH:
            return None, self._nak(req, ERR_FILE_NOT_FOUND, "not_found",
                                   f"opcode {req.opcode}: no file {path[:60]!r} (only {PARAM_PATH})")
        try:
            query = param_pck.parse_query(qtext)
        except ValueError as e:
            return None, self._nak(req, ERR_FAIL_ERRNO, "bad_query", str(e), errno=EINVAL)
        return query, None

    def _snapshot(self, query: param_pck.Query) -> tuple[list, bytes]:
        """(entries, bytes for 239-byte reads); ValueError when nothing is selected."""
        entries = param_pck.store_entries(self.params)
        return entries, param_pck.pack(entries, query)

    def _open(self, req: FtpOp, peer) -> FtpOp:
        query, nak = self._resolve(req)
        if nak is not None:
            return nak
        key = (peer, req.session)
        if key in self._sessions:
            if self._now - self._sessions[key].last_s <= self.session_timeout_s:
                return self._nak(req, ERR_FAIL, "already_open", f"session {req.session} already has a file open")
            self._close(key)  # the client gave up on it (ArduPilot: 3 s idle)
            self.counters["taken_over"] += 1
        try:
            entries, data = self._snapshot(query)
        except ValueError as e:
            return self._nak(req, ERR_FAIL_ERRNO, "bad_query", f"{PARAM_PATH}: {e}", errno=EINVAL)
        if len(self._sessions) >= self.max_sessions:
            oldest = min(self._sessions, key=lambda k: self._sessions[k].last_s)
            if self._now - self._sessions[oldest].last_s <= self.session_timeout_s:
                return self._nak(req, ERR_NO_SESSIONS_AVAILABLE, "no_sessions",
                                 f"all {self.max_sessions} FTP sessions are in use")
            self._close(oldest)
            self.counters["taken_over"] += 1
        self._sessions[key] = _Session(query, entries, self._now, self._now, data)
        self.counters["opened"] += 1
        return self._reply(req, data=struct.pack("<I", len(data)))

    def _read(self, req: FtpOp, peer) -> list[FtpOp]:
        s = self._sessions.get((peer, req.session))
        burst = req.opcode == OP_BURST_READ_FILE
        if s is None:
            return [self._nak(req, ERR_INVALID_SESSION, "invalid_session",
                              f"opcode {req.opcode}: session {req.session} has no open file",
                              burst_complete=int(burst))]
        chunk = (req.size or DATA_LEN) if burst else req.size
        if chunk == 0:
            return [self._nak(req, ERR_INVALID_DATA_SIZE, "bad_size", "ReadFile of 0 bytes")]
        data = s.data(chunk)
        out, offset = [], req.offset
        while True:
            piece = data[offset:offset + chunk] if offset < len(data) else b""
            if not piece:
                self.counters["eof"] += 1
                out.append(self._nak(req, ERR_EOF, offset=offset, seq_add=len(out) + 1,
                                     burst_complete=int(burst)))
                break
            self.counters["bytes_served"] += len(piece)
            out.append(self._reply(req, data=piece, offset=offset, seq_add=len(out) + 1))
            offset += len(piece)
            if not burst:
                break
            if len(out) == self.burst_packets:
                out[-1].burst_complete = 1
                break
        return out

    def _list(self, req: FtpOp) -> FtpOp:
        path = self._path(req)
        if path is None:
            return self._nak(req, ERR_INVALID_DATA_SIZE, "bad_name", "ListDirectory: path length disagrees with size",
                             offset=req.offset)
        d = path.strip("/")
        if d == "":
            entries = [b"D" + PARAM_DIR.encode()]
        elif d == PARAM_DIR:
            try:
                size = len(self._snapshot(param_pck.Query())[1])
            except ValueError:
                size = 0
            entries = [b"F%s\t%d" % (param_pck.PACKED_NAME.encode(), size)]
        else:
            return self._nak(req, ERR_FILE_NOT_FOUND, "not_found", f"ListDirectory: no directory {path[:60]!r}",
                             offset=req.offset)
        picked, used = [], 0
        for e in entries[req.offset:]:
            if used + len(e) + 1 > DATA_LEN:
                break
            picked.append(e + b"\x00")
            used += len(e) + 1
        if not picked:
            self.counters["eof"] += 1
            return self._nak(req, ERR_EOF, offset=req.offset)
        return self._reply(req, data=b"".join(picked), offset=req.offset)

    def _crc(self, req: FtpOp) -> FtpOp:
        query, nak = self._resolve(req)
        if nak is not None:
            return nak
        try:
            data = self._snapshot(query)[1]
        except ValueError as e:
            return self._nak(req, ERR_FAIL_ERRNO, "bad_query", f"{PARAM_PATH}: {e}", errno=EINVAL)
        return self._reply(req, data=struct.pack("<I", crc32_ardupilot(data)))


def crc32_ardupilot(data: bytes) -> int:
    """ArduPilot's crc_crc32(0, data): the reflected CRC-32 table, seed 0, no final xor."""
    return zlib.crc32(data, 0xFFFFFFFF) ^ 0xFFFFFFFF


def decode_replies(payloads: Sequence[bytes]) -> list[FtpOp]:
    """Reply payloads -> FtpOp (for callers that log or test)."""
    return [FtpOp.unpack(p) for p in payloads]
