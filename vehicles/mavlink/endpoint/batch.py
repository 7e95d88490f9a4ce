"""The stream messages of many endpoints framed together, and each endpoint's frames of a step
packed into few UDP datagrams.

Sending a stream message through pymavlink costs ~50 us of Python per frame (the message
object, the payload, the header, the X.25 checksum byte by byte, one ``sendto``): at 200 UAVs
and ~19 stream messages per UAV per second that was the largest part of the vehicle worker's
tick (`skyfuse bench live`'s tick breakdown). Here a group's due stream messages are recorded
during the step (``StreamBatch.recorder(ep)`` stands in for the endpoint's ``mav`` while its
streams run: every ``<message>_send(*args)`` is recorded, with the sequence number it takes),
then framed per message type at once -- the payload by the message's own ``struct`` packer,
MAVLink 2's trailing-zero truncation, the header and the checksum as array operations over all
the frames of that type -- and each endpoint's frames go out concatenated in datagrams of at
most ``MAX_DATAGRAM_BYTES``, in the order they were sent, as ArduPilot's UDP links do (a
datagram holds what the link's buffer held; pymavlink, MAVProxy, MAVSDK and QGroundControl
parse every frame of a datagram). The frames are byte for byte what pymavlink sends
(tests/vehicles/mavlink/test_stream_batch.py checks each stream message type against it).

Only unsigned output is framed here: a signing endpoint's frames each carry a SHA-256
signature and a timestamp that must rise frame by frame, so it keeps pymavlink's path.
"""
from __future__ import annotations

import functools
import inspect

import numpy as np

try:  # the framing loop compiled; the same python function without numba
    import numba as _nb
except ImportError:  # pragma: no cover
    _nb = None
from pymavlink.dialects.v20 import ardupilotmega as mavlink

#: the largest datagram a step's frames are packed into: an Ethernet MTU (1500 B) less the IPv4
#: and UDP headers, so a packed datagram is never fragmented on a real link
MAX_DATAGRAM_BYTES = 1472

_STX_V2 = 0xFD


@functools.cache
def _message_class(name: str):
    """pymavlink's message class of ``<name>_send`` / ``<name>_encode``."""
    cls = getattr(mavlink, f"MAVLink_{name}_message", None)
    if cls is None:
        raise AttributeError(f"pymavlink has no message {name!r}")
    return cls


@functools.cache
def _encode_signature(name: str) -> tuple:
    """(signature, defaults) of pymavlink's ``<name>_encode``: its arguments are the message's
    fields in ``fieldnames`` order, the trailing ones (extension fields) with defaults."""
    sig = inspect.signature(getattr(mavlink.MAVLink, f"{name}_encode"))
    params = list(sig.parameters.values())[1:]  # without self
    return sig, tuple(p.default for p in params)


def encode_args(name: str, args: tuple, kwargs: dict | None = None) -> tuple:
    """The full field tuple (``fieldnames`` order) of ``<name>_send(*args, **kwargs)``: defaults
    filled in as pymavlink's encode fills them."""
    sig, defaults = _encode_signature(name)
    if kwargs:
        b = sig.bind(None, *args, **kwargs)
        b.apply_defaults()
        return tuple(b.arguments.values())[1:]
    if len(args) < len(defaults):
        rest = defaults[len(args):]
        if any(d is inspect.Parameter.empty for d in rest):
            raise TypeError(f"{name}_send: expected {len(defaults)} arguments, got {len(args)}")
        return (*args, *rest)
    return tuple(args)


@functools.cache
def _wire_plan(cls) -> tuple:
    """How the encode arguments (``fieldnames`` order) become the packer's arguments (wire order,
    numeric arrays spread element by element, char arrays passed whole): a tuple of (argument
    index, array length or 0)."""
    plan = []
    for name, n in zip(cls.ordered_fieldnames, cls.array_lengths):
        i = cls.fieldnames.index(name)
        spread = n if n and cls.fieldtypes[i] != "char" else 0
        plan.append((i, spread))
    return tuple(plan)


def payload(cls, args) -> bytes:
    """The full (untruncated) payload of one message, as pymavlink's ``pack`` builds it."""
    vals = []
    for i, n in _wire_plan(cls):
        if n:
            vals.extend(args[i][:n])
        else:
            vals.append(args[i])
    return cls.unpacker.pack(*vals)


def _frame_rows_py(p, seq, sysid, compid, msgid, crc_extra, out, out_len):
    """Frame row r of the payloads p (n, size) into out[r] (n, size + 12), its length in
    out_len[r]: STX, the 9 header bytes, the payload without its trailing zero bytes (at least
    one byte stays), the X.25 (CRC-16/MCRF4XX) checksum over the header after STX, that payload
    and CRC_EXTRA. (Plain loops: numba compiles this same function.)"""
    n, size = p.shape
    for r in range(n):
        plen = size
        while plen > 1 and p[r, plen - 1] == 0:
            plen -= 1
        o = out[r]
        o[0] = 0xFD
        o[1] = plen
        o[2] = 0  # incompat flags: unsigned
        o[3] = 0  # compat flags
        o[4] = seq[r] & 0xFF
        o[5] = sysid[r] & 0xFF
        o[6] = compid[r] & 0xFF
        o[7] = msgid & 0xFF
        o[8] = (msgid >> 8) & 0xFF
        o[9] = (msgid >> 16) & 0xFF
        for j in range(plen):
            o[10 + j] = p[r, j]
        crc = 0xFFFF
        for j in range(1, 11 + plen):
            b = crc_extra if j == 10 + plen else int(o[j])
            tmp = (b ^ (crc & 0xFF)) & 0xFF
            tmp = (tmp ^ (tmp << 4)) & 0xFF
            crc = ((crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)) & 0xFFFF
        o[10 + plen] = crc & 0xFF
        o[11 + plen] = crc >> 8
        out_len[r] = 12 + plen


if _nb is not None:  # compiled; the python function is the same code (a machine without numba)
    from filters.nbdispatch import declare, ready, ro, rw

    _frame_rows_nb = declare(ro(2, dtype=_nb.uint8), ro(1, dtype=_nb.int64), ro(1, dtype=_nb.int64),
                             ro(1, dtype=_nb.int64), _nb.int64, _nb.int64, rw(2, _nb.uint8),
                             rw(1, _nb.int64))(_nb.njit(cache=True, nogil=True)(_frame_rows_py))


def warm() -> None:
    """The framing kernel compiled or loaded from numba's cache now (the worker's warm-up), not
    at the first step of a live run."""
    if _nb is not None:
        ready(_frame_rows_nb)


def frames(cls, payloads: list[bytes], seq, sysid, compid) -> list[bytes]:
    """MAVLink 2 frames (unsigned) of n messages of one type: payloads (n, each the class's full
    payload length), seq / sysid / compid (n,) each. Trailing zero bytes of a payload are cut
    (at least one byte stays), as MAVLink 2 does; checksum over the header after STX, the
    truncated payload and the message's CRC_EXTRA."""
    n = len(payloads)
    if n == 0:
        return []
    size = cls.unpacker.size
    p = np.frombuffer(b"".join(payloads), np.uint8).reshape(n, size)
    out = np.empty((n, size + 12), np.uint8)
    out_len = np.empty(n, np.int64)
    args = (p, np.asarray(seq, np.int64), np.asarray(sysid, np.int64), np.asarray(compid, np.int64),
            int(cls.id), int(cls.crc_extra), out, out_len)
    if _nb is not None:
        ready(_frame_rows_nb)(*args)
    else:  # pragma: no cover
        _frame_rows_py(*args)
    raw = out.tobytes()
    w = size + 12
    lens = out_len.tolist()
    return [raw[r * w:r * w + lens[r]] for r in range(n)]


def pack_datagrams(frame_list, max_bytes: int = MAX_DATAGRAM_BYTES) -> list[tuple[bytes, int]]:
    """Consecutive frames joined into datagrams of at most max_bytes (a frame is never split;
    one larger than max_bytes goes alone): (datagram, number of frames in it) each."""
    out, cur, size = [], [], 0
    for f in frame_list:
        if cur and size + len(f) > max_bytes:
            out.append((b"".join(cur), len(cur)))
            cur, size = [], 0
        cur.append(f)
        size += len(f)
    if cur:
        out.append((b"".join(cur), len(cur)))
    return out


class _Recorder:
    """Stands in for an endpoint's pymavlink ``mav`` while its streams run: ``<name>_send(*args)``
    is recorded in the batch with the next sequence number; everything else is the real one's."""

    __slots__ = ("_batch", "_ep", "_mav")

    def __init__(self, batch, ep, mav):
        self._batch, self._ep, self._mav = batch, ep, mav

    def __getattr__(self, name):
        if name.endswith("_send"):
            return functools.partial(self._batch.add, self._ep, self._mav, name[:-5])
        return getattr(self._mav, name)


class StreamBatch:
    """One step's stream messages of a group of endpoints (module docstring).

    ``recorder(ep)``: the stand-in for ep.mav; ``flush()``: frame what was recorded and send
    each endpoint's frames, in its own order, packed, to the destinations each message had when
    it was recorded (the stream destinations); the endpoint's counters (``sent``, ``tx_bytes``,
    ``tx_datagrams``, ``send_errors``), its pymavlink totals and its tlog as pymavlink's path
    keeps them."""

    def __init__(self, max_datagram_bytes: int = MAX_DATAGRAM_BYTES):
        self.max_datagram_bytes = int(max_datagram_bytes)
        self._rec: list = []  # (ep, dest, class, args, seq, sysid, compid) in send order
        self.frames_sent = 0
        self.datagrams_sent = 0

    def recorder(self, ep, mav):
        return _Recorder(self, ep, mav)

    def add(self, ep, mav, name: str, *args, **kwargs) -> None:
        cls = _message_class(name)
        self._rec.append((ep, ep._dest, cls, encode_args(name, args, kwargs), mav.seq, mav.srcSystem,
                          mav.srcComponent))
        mav.seq = (mav.seq + 1) % 256

    def flush(self) -> None:
        rec, self._rec = self._rec, []
        if not rec:
            return
        by_cls: dict = {}
        for i, r in enumerate(rec):
            by_cls.setdefault(r[2], []).append(i)
        framed = [b""] * len(rec)
        for cls, idx in by_cls.items():
            fr = frames(cls, [payload(cls, rec[i][3]) for i in idx], [rec[i][4] for i in idx],
                        [rec[i][5] for i in idx], [rec[i][6] for i in idx])
            for i, f in zip(idx, fr):
                framed[i] = f
        per_ep: dict = {}
        for i, r in enumerate(rec):
            per_ep.setdefault(id(r[0]), (r[0], []))[1].append((r[1], framed[i]))
        for ep, items in per_ep.values():
            self._send(ep, items)

    def _send(self, ep, items) -> None:
        c = ep.counters
        mav = ep.mav
        tlog = ep._tlog
        by_dest: dict = {}
        for dest, f in items:
            mav.total_packets_sent += 1
            mav.total_bytes_sent += len(f)
            if tlog is not None:
                tlog.write(ep._unix_s, f)
            for addr in dest:
                by_dest.setdefault(addr, []).append(f)
        for addr, fl in by_dest.items():
            if len(addr) == 3:  # a TCP client of the endpoint's server (vehicle.py): one write of the step's frames
                data = b"".join(fl)
                if ep.tcp is not None and ep.tcp.send(addr[1:], data):
                    c["sent"] += len(fl)
                    c["tx_bytes"] += len(data)
                else:
                    c["send_errors"] += len(fl)
                continue
            for dg, n in pack_datagrams(fl, self.max_datagram_bytes):
                try:
                    ep.sock.sendto(dg, addr)
                except OSError:  # full socket buffer, unreachable: lost datagrams, as on a radio
                    c["send_errors"] += n
                    continue
                c["sent"] += n
                c["tx_bytes"] += len(dg)
                c["tx_datagrams"] += 1
                self.frames_sent += n
                self.datagrams_sent += 1
