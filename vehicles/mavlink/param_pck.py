"""``@PARAM/param.pck``: a parameter table in ArduPilot's packed format (pure, no I/O).

The format is ArduPilot's (libraries/AP_Filesystem/AP_Filesystem_Param.cpp, read for this
work; MAVProxy's MAVProxy/modules/lib/param_ftp.py ``ftp_param_decode`` decodes it):

    header   u16 magic      0x671b, or 0x671c when the file carries defaults (?withdefaults=1)
             u16 num_params the entries in this file (total - start, at most count)
             u16 total_params every parameter of the vehicle
    entry    u8  type | flags << 4     type: 1 INT8, 2 INT16, 3 INT32, 4 FLOAT (AP_Param's
                                       ap_var_type); flags bit 0: a default value follows
             u8  common | (len - 1) << 4   common: name bytes shared with the previous entry's
                                       name (0..15); len: the bytes that follow (1..16)
             len bytes                 the rest of the name
             value                     little-endian, the type's width (1, 2, 4, 4 bytes)
             [default]                 same width, only when flags bit 0 is set
    pad      zero bytes before an entry so that its last value (type width > 1) does not
             straddle a read-block boundary: a re-read of one lost block never gets half a
             value.  (With a default, only the default is guarded, as in ArduPilot.)  A
             decoder skips zero bytes between entries (a type byte is never 0).

ArduPilot pads against the first read's size (every later read must use that size); here
the bytes are built once per open session against one block size (:data:`BLOCK`, 239, the
largest FTP read and MAVProxy's burst size), and then frozen.

Query string (``@PARAM/param.pck?withdefaults=1&start=N&count=C``, as ArduPilot):
``withdefaults`` 0/1; ``start`` the first index; ``count`` at most this many (0: all).
Unknown keys are ignored (ArduPilot's parser skips them too); a bad value is a
``ValueError`` (the FTP server NAKs the open with FailErrno / EINVAL, as ArduPilot does).

Every skyfuse parameter is a MAV_PARAM_TYPE_REAL32 (see params.py), so every entry is a
FLOAT whose 4 bytes are the float32 of the store's value: the same number PARAM_VALUE
carries.  A spec with a ``param_type`` attribute (MAV_PARAM_TYPE_INT8/16/32) is packed as that
integer type, should the store ever declare one.
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Iterable, Mapping

MAGIC = 0x671B
MAGIC_WITH_DEFAULTS = 0x671C
HEADER_LEN = 6
#: the FTP data field: the largest read, and the block the padding is laid out against
BLOCK = 239
NAME_MAX = 16
PACKED_NAME = "param.pck"

# AP_Param's ap_var_type -> (width, struct format)
AP_INT8, AP_INT16, AP_INT32, AP_FLOAT = 1, 2, 3, 4
_WIDTH = {AP_INT8: (1, "b"), AP_INT16: (2, "h"), AP_INT32: (4, "i"), AP_FLOAT: (4, "f")}
# MAV_PARAM_TYPE (PARAM_VALUE.param_type) -> ap_var_type
_FROM_MAV_TYPE = {2: AP_INT8, 4: AP_INT16, 6: AP_INT32, 9: AP_FLOAT}
_INT_RANGE = {AP_INT8: (-2**7, 2**7 - 1), AP_INT16: (-2**15, 2**15 - 1), AP_INT32: (-2**31, 2**31 - 1)}


@dataclass(frozen=True)
class Entry:
    """One parameter as packed: name, value, default, ap_var_type (1..4)."""

    name: str
    value: float
    default: float
    ap_type: int = AP_FLOAT


@dataclass(frozen=True)
class Query:
    """What ``param.pck?...`` asks for."""

    with_defaults: bool = False
    start: int = 0
    count: int = 0


def _encode_value(ap_type: int, x: float, name: str) -> bytes:
    width, fmt = _WIDTH[ap_type]
    if ap_type == AP_FLOAT:
        if not math.isfinite(x):
            raise ValueError(f"param {name}: value {x!r} is not finite")
        try:
            return struct.pack("<f", x)
        except OverflowError:
            raise ValueError(f"param {name}: value {x!r} is outside float32") from None
    lo, hi = _INT_RANGE[ap_type]
    if not (math.isfinite(x) and lo <= round(x) <= hi):
        raise ValueError(f"param {name}: value {x!r} does not fit type {ap_type}")
    return struct.pack("<" + fmt, int(round(x)))


def store_entries(store: Mapping[str, float]) -> list[Entry]:
    """The entries of a ParamStore (or any name -> value mapping), in its index order (the
    order PARAM_VALUE.param_index counts, so MAVProxy's FTP indices are the store's).
    Defaults come from ``store.spec(name).default`` when the mapping has specs."""
    spec_of = getattr(store, "spec", None)
    out = []
    for name in store:
        value = float(store[name])
        spec = spec_of(name) if spec_of is not None else None
        default = float(spec.default) if spec is not None else value
        ap_type = _FROM_MAV_TYPE.get(getattr(spec, "param_type", 9), None)
        if ap_type is None:
            raise ValueError(f"param {name}: MAV_PARAM_TYPE {spec.param_type} has no packed form")
        out.append(Entry(name, value, default, ap_type))
    return out


def parse_query(text: str) -> Query:
    """``"withdefaults=1&start=3"`` -> Query; ValueError for a bad value."""
    q = {"withdefaults": 0, "start": 0, "count": 0}
    for item in text.split("&") if text else ():
        key, sep, val = item.partition("=")
        if key not in q:
            continue  # ArduPilot ignores what it does not know
        if not sep or not val.isdigit() or not val.isascii():
            raise ValueError(f"param.pck query: {item!r} needs a decimal value")
        v = int(val)
        if key == "withdefaults" and v > 1:
            raise ValueError(f"param.pck query: withdefaults={v} (0 or 1)")
        if v >= 0xFFFF:
            raise ValueError(f"param.pck query: {key}={v} (< 65535)")
        q[key] = v
    return Query(with_defaults=bool(q["withdefaults"]), start=q["start"], count=q["count"])


def pack(entries: Iterable[Entry], query: Query = Query(), block: int = BLOCK) -> bytes:
    """The whole file for ``entries`` (every parameter of the vehicle, in index order).

    ValueError: no entry selected (ArduPilot fails the read: EINVAL), a bad name or a value
    that does not fit its type, ``block`` outside 1..239.
    """
    entries = list(entries)
    if not 1 <= int(block) <= BLOCK:
        raise ValueError(f"block must be 1..{BLOCK}, got {block!r}")
    total = len(entries)
    if total > 0xFFFF:
        raise ValueError(f"{total} parameters do not fit the u16 header")
    if query.start >= total:
        raise ValueError(f"param.pck: start={query.start} with {total} parameters")
    chosen = entries[query.start:]
    if query.count:
        chosen = chosen[:query.count]
    out = bytearray(struct.pack("<HHH", MAGIC_WITH_DEFAULTS if query.with_defaults else MAGIC,
                                len(chosen), total))
    last = b""
    for e in chosen:
        name = e.name.encode("ascii") if e.name.isascii() else b""
        if not 1 <= len(name) <= NAME_MAX or b"\x00" in name:
            raise ValueError(f"param name {e.name!r} must be 1..{NAME_MAX} ASCII characters")
        if e.ap_type not in _WIDTH:
            raise ValueError(f"param {e.name}: ap_var_type {e.ap_type} is not 1..4")
        width = _WIDTH[e.ap_type][0]
        common, limit = 0, min(len(name), len(last), 15)
        while common < limit and name[common] == last[common]:
            common += 1
        if common == len(name):  # a repeated name: keep one byte to send (ArduPilot's rule)
            common -= 1
        suffix = name[common:]
        value = _encode_value(e.ap_type, e.value, e.name)
        has_default = query.with_defaults and value != _encode_value(e.ap_type, e.default, e.name)
        body = bytes([e.ap_type | (int(has_default) << 4), common | ((len(suffix) - 1) << 4)]) + suffix + value
        if has_default:
            body += _encode_value(e.ap_type, e.default, e.name)
        if width > 1:
            end_mod = (len(out) + len(body)) % block
            if 0 < end_mod < width:  # the value would straddle a block boundary: end it on one
                out += bytes(width - end_mod)
        out += body
        last = name
    return bytes(out)
