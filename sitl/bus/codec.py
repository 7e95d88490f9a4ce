"""Binary encoding of bus messages: one path for the live and the batch bus.

Wire format (schema version 3; version 2 had no ``incarnation`` in the header): one MessagePack map
``{"_v": 2, "_kind": "<kind tag>", "<field>": <value>, ..., "_crc": <bin 4>}`` holding every field of the message
dataclass by name: floats as float64, ints, bools, strs, tuples of str as arrays of str, and
numpy arrays as ``bin`` holding the raw little-endian float64 bytes in C order (int arrays:
int64 bytes; shapes are fixed by the schema; "n"-long arrays take n from the kind's n field,
``len(sat_ids)`` of a SondeRelay, ``len(uav_ids)`` of a UavGroupEpoch). The envelope keys start
with "_", which no message field may, so they never clash with a field (Truth has a ``kind``).

Checksum (version 2). The map's last entry is ``"_crc"``: a 4-byte ``bin`` holding the CRC-32
(zlib, little-endian) of every payload byte before those 4 (so the map header, every field,
and the ``"_crc"`` key and bin header are covered): the payload ends with the fixed 7
bytes ``a4 5f 63 72 63 c4 04`` then the 4 CRC bytes. `decode` checks it before parsing anything and rejects a
payload whose trailer or CRC does not match with reason ``"crc"``. CRC-32 detects every
error burst of up to 32 bits, so a payload with one flipped bit (the fault layer's
``corrupt``), or a few flipped bits close together, is always rejected, never accepted
with a changed float; the CRC costs ~0.1 us per message. MAVLink frames have their own CRC
(CRC-16/MCRF4XX with the message's CRC_EXTRA). Version 1 payloads (no checksum) are refused
("header._v: unsupported schema version" can only be reached by a payload whose CRC is right).

Why MessagePack and not a numpy/struct fixed layout
---------------------------------------------------
Measured on the project machine (2 cores shared with other jobs, load ~3.5; Python 3.11.7,
msgpack 1.2.4 C extension, numpy 2.4), best of 400 rounds of 100 calls, one message at a
time. "Serialisation" = dict of field values -> bytes -> dict with numpy arrays back (no
validation); json stores arrays as lists of floats, the others as raw little-endian float64:

================================  =================  =================
serialisation, encode + decode    UavNav             SondeRelay, n=10
================================  =================  =================
msgpack map with field names      9.7 µs, 449 B      17.8 µs, 1078 B
msgpack array, positional         8.8 µs, 374 B      16.4 µs,  912 B
numpy/struct fixed layout         4.9 µs, 364 B      12.7 µs,  891 B
json (reference)                  62.2 µs, 980 B     124.1 µs, 2001 B
================================  =================  =================

The full path shipped here, ``decode(encode(m))`` including building the message and
validating it (types, shapes, finiteness, ranges, covariance symmetry and Cholesky /
eigenvalues), cost 74 µs for UavNav and 105 µs for SondeRelay n=10 on the same loaded
machine (encode alone 3.2 µs and 4.7 µs): validation dominates, and it runs whatever the
format. Since then validation takes fast paths for the values components normally hand in
(plain finite floats, ints, strs, float64 arrays of the schema's shape) and checks a legal
covariance in one compiled pass (`sitl.bus._fastcheck`), every other value still going
through the same checks and rejections: ``decode(encode(m))`` is now 21 µs for UavNav (decode
17 µs, building a message 9 µs) and ~65 µs to decode a SondeRelay n=10 (load ~1.7; numbers
of ``skyfuse bench beacon``'s "bus alone" row: 38 µs per message published and delivered). The struct layout would save about 5 µs (5-7 % of the full path) and 85-190 bytes
(20 %) per message; json would cost 8-12x the time and twice the bytes.

MessagePack with field names was chosen for what matters more than those 5 µs: the payload
is self-describing (any msgpack tool in any language reads a captured payload), the
decoder names the missing or unexpected field in its errors, the variable-length parts
(``sat_ids``, the n-long arrays) need no hand-written length prefixes or offsets, a later
schema version can add fields without re-laying out every offset, and the C extension does
the bounds checking of untrusted bytes that a hand-written struct parser would have to get
right. (The timing script is not part of the repo; these numbers are its output.)

Decoding untrusted bytes
------------------------
`decode` validates everything (schema version, kind tag, exact field set, wire types,
array sizes, then the message constructor: shapes, finiteness, ranges, covariances) and
raises `BusDecodeError` (one line, naming the field) and never any other exception, for any
byte string. ``err.reason`` is short and stable (no values, no attacker-controlled text) so
it can key rejection counters; ``err.detail`` has the values.
"""

from __future__ import annotations

import zlib
from typing import Any

import msgpack
import numpy as np

from .schema import (
    F_ARRAY,
    F_BOOL,
    F_FLOAT,
    F_IARRAY,
    F_INT,
    F_STR,
    F_STRS,
    MESSAGE_TYPES,
    SCHEMA_VERSION,
    Message,
    SchemaError,
    _one_line,
)

# A payload is refused before anything is parsed when it is larger than this: the largest legal
# message (a SondeRelay of schema.N_SATS_MAX = 256 satellites) is ~22 kB, a UavNav ~470 B. A
# flood of near-1 MiB payloads (the old bound) kept the receivers' memory up by tens of MB.
MAX_PAYLOAD_BYTES = 64 << 10
_HEADER_KEYS = ("_v", "_kind", "_crc")
_LE_F8 = np.dtype("<f8")
_LE_I8 = np.dtype("<i8")
CRC_KEY = "_crc"
_CRC_PLACEHOLDER = b"\0\0\0\0"
CRC_TRAILER = b"\xa4_crc\xc4\x04"  # msgpack: fixstr "_crc", bin8 of length 4 (then the 4 CRC bytes)
_TRAILER_LEN = len(CRC_TRAILER) + 4


def seal(packed: bytes | bytearray) -> bytes:
    """Fill in the CRC of msgpack bytes that end with ``"_crc"`` + a 4-byte placeholder bin
    (what `encode` does; tests use it to build payloads that pass the checksum)."""
    b = bytearray(packed)
    if len(b) < _TRAILER_LEN or bytes(b[-_TRAILER_LEN:-4]) != CRC_TRAILER:
        raise ValueError("seal: the bytes do not end with the '_crc' entry")
    b[-4:] = zlib.crc32(memoryview(b)[:-4]).to_bytes(4, "little")
    return bytes(b)


def pack_sealed(obj: Any) -> bytes:
    """msgpack ``obj`` with a valid checksum: a map gets (or keeps, last) its ``"_crc"`` entry,
    a list gets ``"_crc"`` and the CRC as its last two items (for tests of the layers after
    the checksum)."""
    if isinstance(obj, dict):
        obj = {k: v for k, v in obj.items() if k != CRC_KEY}
        obj[CRC_KEY] = _CRC_PLACEHOLDER
    elif isinstance(obj, list):
        obj = [*obj, CRC_KEY, _CRC_PLACEHOLDER]
    else:
        raise TypeError("pack_sealed: a dict or a list")
    return seal(msgpack.packb(obj, use_bin_type=True))


class BusDecodeError(ValueError):
    """A payload that is not a valid message. ``reason`` is stable, ``detail`` has values."""

    def __init__(self, reason: str, detail: str = ""):
        self.reason = reason
        self.detail = _one_line(detail)
        super().__init__(reason + (f" ({self.detail})" if self.detail else ""))


def encode(msg: Message) -> bytes:
    """Encode a message (already valid by construction) to its wire bytes."""
    cls = type(msg)
    if not isinstance(msg, Message) or MESSAGE_TYPES.get(cls.KIND) is not cls:
        raise TypeError(f"not a bus message: {type(msg).__name__}")
    out: dict[str, Any] = {"_v": SCHEMA_VERSION, "_kind": cls.KIND}
    for spec in cls.FIELDS:
        value = getattr(msg, spec.name)
        if spec.ftype == F_ARRAY:
            out[spec.name] = value.astype(_LE_F8, copy=False).tobytes()
        elif spec.ftype == F_IARRAY:
            out[spec.name] = value.astype(_LE_I8, copy=False).tobytes()
        elif spec.ftype == F_STRS:
            out[spec.name] = list(value)
        else:
            out[spec.name] = value
    out[CRC_KEY] = _CRC_PLACEHOLDER  # last: the payload ends with the CRC (module docstring)
    b = msgpack.packb(out, use_bin_type=True)
    return b[:-4] + zlib.crc32(memoryview(b)[:-4]).to_bytes(4, "little")


_WIRE_TYPES = {F_FLOAT: (float,), F_INT: (int,), F_BOOL: (bool,), F_STR: (str,)}
_TYPE_WORD = {F_FLOAT: "float", F_INT: "int", F_BOOL: "bool", F_STR: "str",
              F_STRS: "array of str", F_ARRAY: "bin (float64 bytes)", F_IARRAY: "bin (int64 bytes)"}


def _plan(cls) -> tuple:
    """(name, ftype, exact wire type or None, fixed shape or None) of each field of cls."""
    _SHAPES[cls] = {sp.name: sp.shape for sp in cls.FIELDS if sp.ftype in (F_ARRAY, F_IARRAY)}
    out = []
    for sp in cls.FIELDS:
        wire = {F_ARRAY: bytes, F_IARRAY: bytes, F_FLOAT: float, F_INT: int, F_BOOL: bool, F_STR: str}.get(sp.ftype)
        fixed = sp.shape if sp.shape is not None and "n" not in sp.shape else None
        out.append((sp.name, sp.ftype, wire, fixed))
    return tuple(out)


_PLANS: dict[type, tuple] = {}
_SHAPES: dict[type, dict] = {}


def decode(payload: bytes | bytearray | memoryview) -> Message:
    """Decode and fully validate a payload; raise `BusDecodeError` for anything invalid."""
    try:
        return _decode(payload)
    except BusDecodeError:
        raise
    except SchemaError as e:
        raise BusDecodeError(e.reason, e.detail) from None
    except Exception as e:  # the contract: BusDecodeError and nothing else, for any bytes
        raise BusDecodeError("payload: undecodable", f"{type(e).__name__}: {e}") from None


def _decode(payload: Any) -> Message:
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise BusDecodeError("payload: not bytes", type(payload).__name__)
    size = len(payload) if not isinstance(payload, memoryview) else payload.nbytes
    if size == 0:
        raise BusDecodeError("payload: empty")
    if size > MAX_PAYLOAD_BYTES:
        raise BusDecodeError("payload: too large", f"{size} bytes")
    mv = memoryview(payload).cast("B") if isinstance(payload, memoryview) else memoryview(payload)
    if size < _TRAILER_LEN or mv[-_TRAILER_LEN:-4] != CRC_TRAILER:
        raise BusDecodeError("crc", "no checksum trailer")
    if zlib.crc32(mv[:-4]) != int.from_bytes(mv[-4:], "little"):
        raise BusDecodeError("crc", "checksum mismatch")
    try:
        obj = msgpack.unpackb(payload, raw=False, strict_map_key=True, use_list=True)
    except msgpack.ExtraData:
        raise BusDecodeError("payload: trailing bytes") from None
    except Exception as e:  # msgpack raises several types (FormatError, ValueError, ...)
        raise BusDecodeError("payload: not msgpack", f"{type(e).__name__}: {e}") from None
    if not isinstance(obj, dict):
        raise BusDecodeError("payload: not a map", type(obj).__name__)

    if "_v" not in obj:
        raise BusDecodeError("header._v: missing schema version")
    version = obj["_v"]
    if type(version) is not int:
        raise BusDecodeError("header._v: schema version not an int", type(version).__name__)
    if version != SCHEMA_VERSION:
        raise BusDecodeError("header._v: unsupported schema version",
                             f"got {version}, this build speaks {SCHEMA_VERSION}")
    kind = obj.get("_kind")
    if not isinstance(kind, str):
        raise BusDecodeError("header._kind: missing or not a str")
    cls = MESSAGE_TYPES.get(kind)
    if cls is None:
        raise BusDecodeError("header._kind: unknown message kind", repr(kind)[:40])
    name = cls.__name__

    plan = _PLANS.get(cls)
    if plan is None:
        plan = _PLANS[cls] = _plan(cls)
    expected = len(cls.FIELDS) + len(_HEADER_KEYS)
    if len(obj) != expected or CRC_KEY not in obj:
        known = {s.name for s in cls.FIELDS}.union(_HEADER_KEYS)
        for k in obj:
            if k not in known:
                raise BusDecodeError(f"{name}: unexpected field", repr(k)[:40])
        if CRC_KEY not in obj:
            raise BusDecodeError("header._crc: missing")
    # pass 1: every field present with its wire type (the first offender is reported)
    kwargs: dict[str, Any] = {}
    for fname, ft, wire, _ in plan:
        if fname not in obj:
            raise BusDecodeError(f"{name}.{fname}: missing")
        value = obj[fname]
        if wire is not None:
            ok = type(value) is wire
        elif ft == F_STRS:
            ok = type(value) is list and all(type(s) is str for s in value)
        else:
            ok = type(value) in _WIRE_TYPES[ft]
        if not ok:
            raise BusDecodeError(f"{name}.{fname}: expected {_TYPE_WORD[ft]}", type(value).__name__)
        kwargs[fname] = value

    # pass 2: the arrays' sizes, then the arrays themselves
    n = len(kwargs[cls.N_FIELD]) if cls.N_FIELD is not None else None
    for fname, ft, _, shape in plan:
        if ft != F_ARRAY and ft != F_IARRAY:
            continue
        raw = kwargs[fname]
        if shape is None:  # n-dependent
            shape = tuple(n if d == "n" else d for d in _SHAPES[cls][fname])
        count = 1
        for d in shape:
            count *= d
        if len(raw) != 8 * count:
            raise BusDecodeError(f"{name}.{fname}: wrong size",
                                 f"{len(raw)} bytes for shape {shape}")
        kwargs[fname] = np.frombuffer(raw, dtype=_LE_F8 if ft == F_ARRAY else _LE_I8).reshape(shape)
    return cls(**kwargs)


__all__ = ["CRC_KEY", "CRC_TRAILER", "MAX_PAYLOAD_BYTES", "BusDecodeError", "decode", "encode", "pack_sealed",
           "seal"]
