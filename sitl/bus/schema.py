"""Bus message schema, version 3 (version 2 plus the sender's incarnation in the header and
declared plausibility bounds on every value): one definition for the live (Zenoh) and batch
(in-memory) bus.

Every message is a frozen dataclass whose constructor validates everything (types, shapes,
finiteness, ranges, covariances), so an invalid message cannot exist in memory, whether it
was built by a component or decoded from the wire (`sitl.bus.codec.decode` builds messages
through the same constructors).

Header, common to every kind:
  ``t_gps_s``     simulation time in GPS seconds, 0 <= t <= `T_GPS_MAX_S` (1e10 s, ~2300 AD)
  ``source_id``   publisher id, 1..64 chars of ``[A-Za-z0-9_.-]``
  ``seq``         per-source sequence number, 0 <= seq < 2**63
  ``incarnation`` which life of the publishing process sent it, 0 <= incarnation < 2**63
                  (default 0): a restarted process publishes with a new incarnation, so a
                  receiver takes its messages as a new stream (its ``seq`` starts over)
                  instead of dropping them as repeats of the old one's; duplicates are
                  (source_id, incarnation, seq) repeats
and the schema version (`SCHEMA_VERSION`) travels in every encoded payload.

Plausibility (version 3): besides being finite, every value lies in a declared physical range,
so that a schema-valid but absurd value (a time 1e6 s ahead, a position beyond the Moon, a
variance of 1e300) is rejected at decode with a stable reason (``"<Kind>.<field>: out of
range ..."``), counted like any other bad input, and never reaches an estimator: positions
|x| <= `POS_MAX_M` per ECEF component (1e8 m: beyond the GNSS orbits), velocities <=
`VEL_MAX_M_S` (2e4 m/s), covariance and variance entries <= `VAR_MAX` (1e16: sigma 1e8 m),
ranges <= `POS_MAX_M`, range rates and Dopplers <= `VEL_MAX_M_S`, at most `N_SATS_MAX`
satellites per relay epoch. A consumer still guards the TIME against its own clock
(`sitl.bus.timeguard`): the schema only knows what is possible, not what is now.

Columnar epochs (version 3, an added kind: no other kind's wire changed, so the version did
not): `UavGroupEpoch` carries up to `UAV_GROUP_MAX` UAVs' UavNav / BeaconMeasurement / Truth
of one epoch as arrays (int64 array fields for its counts and flags), with the same header
and the same rules on every present value; ``per_uav`` gives back the per-UAV messages.

Units are SI and appear in the field names; frames are ECEF (WGS-84). Arrays are float64,
stored as read-only copies. Covariances are 6x6 over [position, velocity] and must be
symmetric (max |C - C^T| <= 1e-9 max |C|), with a non-negative diagonal and eigenvalues
>= -1e-9 max |diag| (positive semi-definite up to rounding).

Keys: ``<run_id>/<kind path>``, see `KEY_TEMPLATES`, `key_for` and `parse_key`. The ids that
only live in the key (beacon id, sonde id, radar id, ...) are recovered with `parse_key`;
the transports hand the key to every callback together with the message.

Equality (``==``) compares kind and every field, arrays element-wise, NaN equal to NaN (so
``decode(encode(m)) == m`` also holds for a NaN NIS or invalid radar angles).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import numbers
import re
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from ._fastcheck import cov_code as _cov_code
from ._fastcheck import within as _within

SCHEMA_VERSION = 3

ID_MAX_LEN = 64
_ID_RE = re.compile(r"[A-Za-z0-9_.\-]{1,64}\Z")
KINDS = ("uav", "beacon", "sonde")
SEQ_LIMIT = 2**63
_F8 = np.dtype(np.float64)

# Plausibility bounds (module docstring)
T_GPS_MAX_S = 1e10
POS_MAX_M = 1e8
VEL_MAX_M_S = 2e4
VAR_MAX = 1e16
N_SATS_MAX = 256

# Wire/field types.
F_FLOAT = "float"
F_INT = "int"
F_BOOL = "bool"
F_STR = "str"
F_STRS = "strs"  # tuple of str
F_ARRAY = "array"  # float64 array of a fixed (or n-dependent) shape
F_IARRAY = "iarray"  # int64 array of a fixed (or n-dependent) shape, each element in [lo, hi]
_ARRAY_TYPES = (F_ARRAY, F_IARRAY)


class SchemaError(ValueError):
    """A message field breaks the schema.

    ``reason`` is short and stable (``"<Kind>.<field>: <problem>"``, never containing
    values), so it can key rejection counters; ``detail`` carries the values; ``str(err)``
    is the one-line combination.
    """

    def __init__(self, where: str, problem: str, detail: str = ""):
        self.where = where
        self.problem = problem
        self.detail = _one_line(detail)
        self.reason = f"{where}: {problem}"
        super().__init__(self.reason + (f" ({self.detail})" if self.detail else ""))


def _one_line(text: str, limit: int = 160) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def is_valid_id(value: Any) -> bool:
    """True for a source id / key id: 1..64 chars of [A-Za-z0-9_.-]."""
    return isinstance(value, str) and _ID_RE.match(value) is not None


def check_id(value: Any, where: str) -> str:
    if not isinstance(value, str):
        raise SchemaError(where, "expected a str", f"got {type(value).__name__}")
    if not value:
        raise SchemaError(where, "empty")
    if len(value) > ID_MAX_LEN:
        raise SchemaError(where, f"longer than {ID_MAX_LEN} chars", f"{len(value)} chars")
    if _ID_RE.match(value) is None:
        raise SchemaError(where, "only [A-Za-z0-9_.-] allowed", repr(value))
    return value


# ----------------------------------------------------------------------------------------
# Field descriptors


def _arr(*shape: int | str, max_abs: float, nan_ok: bool = False) -> Any:
    """An array field of the given shape whose elements lie in [-max_abs, max_abs]; "n" is
    the per-message length (len(sat_ids))."""
    return field(metadata={"shape": tuple(shape), "nan_ok": nan_ok, "max_abs": float(max_abs)})


def _iarr(*shape: int | str, lo: int, hi: int) -> Any:
    """An int64 array field of the given shape whose elements lie in [lo, hi]."""
    return field(metadata={"shape": tuple(shape), "int": True, "lo": int(lo), "hi": int(hi)})


def _num(lo: float | None = None, hi: float | None = None, *, nan_ok: bool = False, default: Any = dataclasses.MISSING
         ) -> Any:
    """A float field in [lo, hi] (None: unbounded on that side); ``nan_ok``: NaN allowed too."""
    return field(default=default, metadata={"nan_ok": nan_ok, "lo": lo, "hi": hi})


def _nan_ok() -> Any:
    return field(metadata={"nan_ok": True})


@dataclass(frozen=True)
class FieldSpec:
    name: str
    ftype: str
    shape: tuple[int | str, ...] | None = None
    nan_ok: bool = False
    max_abs: float | None = None  # arrays: |element| <= max_abs
    lo: float | None = None  # floats: lo <= value <= hi
    hi: float | None = None


_TYPE_MAP = {float: F_FLOAT, int: F_INT, bool: F_BOOL, str: F_STR, np.ndarray: F_ARRAY,
             "float": F_FLOAT, "int": F_INT, "bool": F_BOOL, "str": F_STR,
             "np.ndarray": F_ARRAY, "tuple[str, ...]": F_STRS}


def _field_specs(cls: type) -> tuple[FieldSpec, ...]:
    specs = []
    for f in dataclasses.fields(cls):
        if f.name.startswith("_"):
            raise TypeError(f"{cls.__name__}.{f.name}: field names may not start with '_'")
        ftype = _TYPE_MAP.get(f.type)
        if ftype is None:
            raise TypeError(f"{cls.__name__}.{f.name}: unsupported annotation {f.type!r}")
        shape = f.metadata.get("shape")
        if ftype == F_ARRAY and f.metadata.get("int"):
            ftype = F_IARRAY
        if (ftype in _ARRAY_TYPES) != (shape is not None):
            raise TypeError(f"{cls.__name__}.{f.name}: array fields need a shape")
        md = f.metadata
        specs.append(FieldSpec(f.name, ftype, shape, bool(md.get("nan_ok", False)), md.get("max_abs"),
                               md.get("lo"), md.get("hi")))
    return tuple(specs)


# ----------------------------------------------------------------------------------------
# Coercion and checks


def _coerce(cls_name: str, spec: FieldSpec, value: Any, n: int | None) -> Any:
    ft = spec.ftype
    if ft == F_FLOAT:
        t = type(value)
        if t is not float:
            if t is bool or isinstance(value, np.bool_) or not isinstance(value, numbers.Real):
                raise SchemaError(f"{cls_name}.{spec.name}", "expected a float",
                                  f"got {t.__name__}")
            try:
                value = float(value)
            except (OverflowError, ValueError, TypeError) as e:
                raise SchemaError(f"{cls_name}.{spec.name}", "expected a float", str(e)) from None
        if not math.isfinite(value) and not (spec.nan_ok and math.isnan(value)):
            raise SchemaError(f"{cls_name}.{spec.name}", "not finite", repr(value))
        if (spec.lo is not None and value < spec.lo) or (spec.hi is not None and value > spec.hi):
            raise SchemaError(f"{cls_name}.{spec.name}", _range_text(spec.lo, spec.hi), repr(value))
        return value
    if ft == F_INT:
        t = type(value)
        if t is int:
            return value
        if t is bool or isinstance(value, np.bool_) or not isinstance(value, numbers.Integral):
            raise SchemaError(f"{cls_name}.{spec.name}", "expected an int", f"got {t.__name__}")
        return int(value)
    where = f"{cls_name}.{spec.name}"
    if ft == F_BOOL:
        if not isinstance(value, (bool, np.bool_)):
            raise SchemaError(where, "expected a bool", f"got {type(value).__name__}")
        return bool(value)
    if ft == F_STR:
        if type(value) is not str and not isinstance(value, str):
            raise SchemaError(where, "expected a str", f"got {type(value).__name__}")
        return str(value)
    if ft == F_STRS:
        # numpy str arrays (how sitl.gnss holds satellite ids) are accepted too
        if isinstance(value, np.ndarray) and value.ndim == 1 and value.dtype.kind == "U":
            value = value.tolist()
        if isinstance(value, (str, bytes)) or not isinstance(value, (tuple, list)):
            raise SchemaError(where, "expected a tuple of str", f"got {type(value).__name__}")
        for i, s in enumerate(value):
            if not isinstance(s, str):
                raise SchemaError(where, "expected a tuple of str",
                                  f"item {i} is {type(s).__name__}")
        return tuple(s if type(s) is str else str(s) for s in value)
    if ft == F_IARRAY:
        return _coerce_int_array(where, spec, value, n)
    # F_ARRAY
    if isinstance(value, (str, bytes)):
        raise SchemaError(where, "expected a float array", f"got {type(value).__name__}")
    try:
        if type(value) is np.ndarray and value.dtype == np.float64:
            a = value.copy()
        else:
            a = np.array(value, dtype=np.float64, copy=True)
    except Exception as e:  # any conversion failure is a schema error
        raise SchemaError(where, "expected a float array", f"{type(e).__name__}: {e}") from None
    shape = spec.shape if n is None else tuple(n if d == "n" else d for d in spec.shape)
    if a.shape != shape:
        raise SchemaError(where, "wrong shape", f"expected {shape}, got {a.shape}")
    if not np.isfinite(a).all():
        bad = np.isinf(a) if spec.nan_ok else ~np.isfinite(a)
        if bad.any():
            raise SchemaError(where, "not finite", f"{int(bad.sum())} non-finite values")
    if spec.max_abs is not None and a.size:
        with np.errstate(invalid="ignore"):
            big = np.abs(a) > spec.max_abs
        if big.any():
            raise SchemaError(where, f"out of range (|x| <= {spec.max_abs:g})",
                              f"max |x| = {float(np.nanmax(np.abs(a))):.3g}")
    a.flags.writeable = False
    return a


def _coerce_int_array(where: str, spec: FieldSpec, value: Any, n: int | None) -> np.ndarray:
    """An int64 array of the spec's shape, every element in [spec.lo, spec.hi] (bools, floats and
    other non-integer elements are refused, not rounded)."""
    if isinstance(value, (str, bytes)):
        raise SchemaError(where, "expected an int array", f"got {type(value).__name__}")
    try:
        a = value if type(value) is np.ndarray else np.array(value)
    except Exception as e:
        raise SchemaError(where, "expected an int array", f"{type(e).__name__}: {e}") from None
    if a.dtype.kind not in "iu" and not (a.size == 0 and a.dtype.kind == "f"):  # [] is float64 to numpy
        raise SchemaError(where, "expected an int array", f"dtype {a.dtype}")
    if a.dtype.kind == "u" and a.size and a.max() > np.iinfo(np.int64).max:
        raise SchemaError(where, _range_text(spec.lo, spec.hi), "beyond int64")
    a = a.astype(np.int64, copy=True)
    shape = spec.shape if n is None else tuple(n if d == "n" else d for d in spec.shape)
    if a.shape != shape:
        raise SchemaError(where, "wrong shape", f"expected {shape}, got {a.shape}")
    if a.size and (a.min() < spec.lo or a.max() > spec.hi):
        raise SchemaError(where, _range_text(spec.lo, spec.hi), f"min {a.min()}, max {a.max()}")
    a.flags.writeable = False
    return a


def _range_text(lo: float | None, hi: float | None) -> str:
    return f"out of range [{'-inf' if lo is None else f'{lo:g}'}, {'inf' if hi is None else f'{hi:g}'}]"


def _check_cov(where: str, c: np.ndarray) -> None:
    """Symmetric (relative 1e-9), non-negative diagonal, eigenvalues >= -1e-9 max diag."""
    # the legal case in one compiled pass (sitl/bus/_fastcheck.py); anything else is decided
    # (and reported) by the numpy reference below
    if _cov_code is not None and _cov_code(c) == 0:
        return
    # Comparisons are written so that a NaN (from an overflow) fails them.
    with np.errstate(over="ignore", invalid="ignore"):
        scale = np.abs(c).max()
        asym = np.abs(c - c.T).max()
    if not asym <= 1e-9 * scale:
        raise SchemaError(where, "not symmetric", f"max |C-C^T| = {asym:.3g}, max |C| = {scale:.3g}")
    diag = c.diagonal()
    dmin = diag.min()
    if not dmin >= 0:
        raise SchemaError(where, "negative diagonal", f"min diag = {dmin:.3g}")
    # A successful Cholesky proves positive definiteness (backward stable: the smallest
    # eigenvalue is then >= -O(n eps max|C|), far inside the tolerance); otherwise decide by
    # the eigenvalues (singular covariances, e.g. a zero block, are legal).
    try:
        np.linalg.cholesky(c)
        return
    except np.linalg.LinAlgError:
        pass
    dmax = diag.max()
    with np.errstate(over="ignore", invalid="ignore"):
        lam = np.linalg.eigvalsh(c).min()
    if not lam >= -1e-9 * dmax:
        raise SchemaError(where, "not positive semi-definite",
                          f"min eigenvalue = {lam:.3g}, max diag = {dmax:.3g}")


def _check_positive(where: str, v: float) -> None:
    if not v > 0:
        raise SchemaError(where, "must be > 0", repr(v))


def _check_token(where: str, v: str) -> None:
    check_id(v, where)


# ----------------------------------------------------------------------------------------
# Messages


@dataclass(frozen=True, kw_only=True, eq=False)
class Message:
    """Base of every bus message: the header and the generic validation."""

    KIND: ClassVar[str] = ""
    KEY_TEMPLATE: ClassVar[str] = ""
    FIELDS: ClassVar[tuple[FieldSpec, ...]] = ()
    N_FIELD: ClassVar[str | None] = None  # str-tuple field whose length is "n" in shapes

    t_gps_s: float = _num(0.0, T_GPS_MAX_S)
    source_id: str
    seq: int
    incarnation: int = 0

    def __post_init__(self) -> None:
        cls = type(self)
        name = cls.__name__
        if not cls.KIND:
            raise TypeError("Message is abstract; build one of its kinds")
        d = self.__dict__  # frozen: fields are set here, as object.__setattr__ would
        n = None
        if cls.N_FIELD is not None:
            spec = next(s for s in cls.FIELDS if s.name == cls.N_FIELD)
            v = _coerce(name, spec, d[spec.name], None)
            d[spec.name] = v
            n = len(v)
        # fast paths for the values components normally hand in (a finite float, an int, a
        # str, a float64 array of the right shape); anything else goes through _coerce, which
        # accepts or rejects it exactly as before
        for spec, shape in cls._PLAN:
            value = d[spec.name]
            ft = spec.ftype
            if ft == F_ARRAY:
                if shape is None and n is not None:  # an "n"-long array: its shape for this message
                    shape = tuple(n if dim == "n" else dim for dim in spec.shape)
                if (shape is not None and type(value) is np.ndarray and value.dtype == _F8
                        and value.shape == shape and _within is not None):
                    a = value.copy()
                    if _within(a, spec.max_abs):
                        a.flags.writeable = False
                        d[spec.name] = a
                        continue
            elif ft == F_FLOAT:
                if type(value) is float and value - value == 0.0 and (spec.lo is None or spec.lo <= value) \
                        and (spec.hi is None or value <= spec.hi):
                    continue
            elif ft == F_INT:
                if type(value) is int:
                    continue
            elif ft == F_STR:
                if type(value) is str:
                    continue
            d[spec.name] = _coerce(name, spec, value, n)
        sid = d["source_id"]
        if not (type(sid) is str and _ID_RE.match(sid) is not None):
            check_id(sid, f"{name}.source_id")
        if not 0 <= self.seq < SEQ_LIMIT:
            raise SchemaError(f"{name}.seq", "out of range [0, 2**63)", repr(self.seq))
        if not 0 <= self.incarnation < SEQ_LIMIT:
            raise SchemaError(f"{name}.incarnation", "out of range [0, 2**63)", repr(self.incarnation))
        self._validate()

    def _validate(self) -> None:  # per-kind rules
        pass

    def _where(self, fname: str) -> str:
        return f"{type(self).__name__}.{fname}"

    def _check_cov(self, fname: str) -> None:
        """_check_cov on a field; the field's name is only formatted when it fails."""
        c = getattr(self, fname)
        if _cov_code is None or _cov_code(c) != 0:
            _check_cov(self._where(fname), c)

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        for spec in self.FIELDS:
            a, b = getattr(self, spec.name), getattr(other, spec.name)
            if spec.ftype in _ARRAY_TYPES:
                if not np.array_equal(a, b, equal_nan=spec.ftype == F_ARRAY):
                    return False
            elif spec.ftype == F_FLOAT:
                if not (a == b or (math.isnan(a) and math.isnan(b))):
                    return False
            elif a != b:
                return False
        return True

    __hash__ = None  # type: ignore[assignment]  # arrays inside: not hashable


def _message(kind: str, key_template: str, n_field: str | None = None):
    """Class decorator: make a frozen message dataclass and register it."""

    def wrap(cls):
        cls = dataclass(frozen=True, kw_only=True, eq=False)(cls)
        cls.KIND = kind
        cls.KEY_TEMPLATE = key_template
        cls.N_FIELD = n_field
        cls.FIELDS = _field_specs(cls)
        # (spec, fixed shape or None) of every field but the n-field, for __post_init__
        cls._PLAN = tuple((sp, sp.shape if sp.shape is not None and "n" not in sp.shape else None)
                          for sp in cls.FIELDS if sp.name != n_field)
        cls.__hash__ = None
        if kind in MESSAGE_TYPES:
            raise TypeError(f"duplicate message kind {kind!r}")
        MESSAGE_TYPES[kind] = cls
        return cls

    return wrap


MESSAGE_TYPES: dict[str, type[Message]] = {}


@_message("uav_nav", "uav/{uav}/nav")
class UavNav(Message):
    """A UAV's onboard navigation estimate (ECEF) and its covariance over [pos, vel]."""

    pos_ecef_m: np.ndarray = _arr(3, max_abs=POS_MAX_M)
    vel_ecef_m_s: np.ndarray = _arr(3, max_abs=VEL_MAX_M_S)
    cov: np.ndarray = _arr(6, 6, max_abs=VAR_MAX)
    n_sats: int
    fix_type: int  # MAVLink GPS_FIX_TYPE: 0 no GPS .. 6 RTK fixed

    def _validate(self) -> None:
        self._check_cov("cov")
        if not 0 <= self.n_sats <= N_SATS_MAX:
            raise SchemaError(self._where("n_sats"), f"out of range 0..{N_SATS_MAX}", repr(self.n_sats))
        if not 0 <= self.fix_type <= 6:
            raise SchemaError(self._where("fix_type"), "out of range 0..6", repr(self.fix_type))


@_message("beacon_meas", "uav/{uav}/beacon/{beacon}")
class BeaconMeasurement(Message):
    """Range and range rate of a beacon measured by a UAV, self-contained: it carries the
    UAV's own navigation estimate at the same time (so a lossy link cannot pair it with the
    wrong nav message)."""

    range_m: float = _num(0.0, POS_MAX_M)
    range_rate_m_s: float = _num(-VEL_MAX_M_S, VEL_MAX_M_S)
    var_range_m2: float = _num(0.0, VAR_MAX)
    var_range_rate_m2_s2: float = _num(0.0, VAR_MAX)
    uav_pos_ecef_m: np.ndarray = _arr(3, max_abs=POS_MAX_M)
    uav_vel_ecef_m_s: np.ndarray = _arr(3, max_abs=VEL_MAX_M_S)
    uav_cov: np.ndarray = _arr(6, 6, max_abs=VAR_MAX)

    def _validate(self) -> None:
        for f in ("range_m", "var_range_m2", "var_range_rate_m2_s2"):
            if not getattr(self, f) > 0:
                _check_positive(self._where(f), getattr(self, f))
        self._check_cov("uav_cov")


UAV_GROUP_MAX = 100  # UAVs per UavGroupEpoch (a payload of ~50 kB, under the codec's 64 KiB bound)
PART_NAV, PART_BEACON, PART_TRUTH = 1, 2, 4  # UavGroupEpoch.parts bits


@_message("uav_group", "uavs/{group}/epoch", n_field="uav_ids")
class UavGroupEpoch(Message):
    """One epoch of a vehicle group's UAVs as arrays: what the group would otherwise publish
    as up to three messages per UAV (its `UavNav`, its `BeaconMeasurement` of beacon
    ``beacon_id``, its `Truth`) in one payload per group (of at most `UAV_GROUP_MAX` UAVs) per
    epoch. The per-UAV view is `per_uav` (the messages, keys and order the group would have
    published; ground_station.node and the bus recorder use it, so consumers and bus logs see
    per-UAV messages as before).

    Row j is UAV ``uav_ids[j]`` (its key id: ``<run>/uav/<id>/...``), publishing as
    ``uav_source_ids[j]``; every per-UAV message has the header's time, sequence number and
    incarnation. ``parts[j]``: which of its messages the epoch holds (bits `PART_NAV`,
    `PART_BEACON`, `PART_TRUTH`). ``pos_ecef_m`` / ``vel_ecef_m_s`` / ``cov``: the UAV's onboard
    estimate (the UavNav, and the nav snapshot every BeaconMeasurement carries), present for
    every row, with ``n_sats`` / ``fix_type``; the beacon columns hold the BeaconMeasurement
    where ``parts`` has PART_BEACON and are NaN elsewhere; the truth columns (``truth_*``,
    source ``truth_source_id``) likewise with PART_TRUTH. Every present value obeys the rule
    of its per-UAV message (ranges, finiteness, covariance symmetric PSD), so each per-UAV
    message of `per_uav` is valid by construction; an absent value must be NaN (no hidden data)."""

    group: str
    beacon_id: str
    truth_source_id: str
    uav_ids: tuple[str, ...]
    uav_source_ids: tuple[str, ...]
    parts: np.ndarray = _iarr("n", lo=0, hi=PART_NAV | PART_BEACON | PART_TRUTH)
    n_sats: np.ndarray = _iarr("n", lo=0, hi=N_SATS_MAX)
    fix_type: np.ndarray = _iarr("n", lo=0, hi=6)
    pos_ecef_m: np.ndarray = _arr("n", 3, max_abs=POS_MAX_M)
    vel_ecef_m_s: np.ndarray = _arr("n", 3, max_abs=VEL_MAX_M_S)
    cov: np.ndarray = _arr("n", 6, 6, max_abs=VAR_MAX)
    range_m: np.ndarray = _arr("n", max_abs=POS_MAX_M, nan_ok=True)
    range_rate_m_s: np.ndarray = _arr("n", max_abs=VEL_MAX_M_S, nan_ok=True)
    var_range_m2: np.ndarray = _arr("n", max_abs=VAR_MAX, nan_ok=True)
    var_range_rate_m2_s2: np.ndarray = _arr("n", max_abs=VAR_MAX, nan_ok=True)
    truth_pos_ecef_m: np.ndarray = _arr("n", 3, max_abs=POS_MAX_M, nan_ok=True)
    truth_vel_ecef_m_s: np.ndarray = _arr("n", 3, max_abs=VEL_MAX_M_S, nan_ok=True)

    _BEACON_COLS = ("range_m", "range_rate_m_s", "var_range_m2", "var_range_rate_m2_s2")
    _TRUTH_COLS = ("truth_pos_ecef_m", "truth_vel_ecef_m_s")

    def _validate(self) -> None:
        n = len(self.uav_ids)
        if n > UAV_GROUP_MAX:
            raise SchemaError(self._where("uav_ids"), f"more than {UAV_GROUP_MAX} UAVs", f"{n}")
        for f in ("group", "beacon_id", "truth_source_id"):
            check_id(getattr(self, f), self._where(f))
        for f in ("uav_ids", "uav_source_ids"):
            ids = getattr(self, f)
            if len(ids) != n:
                raise SchemaError(self._where(f), "not one per UAV", f"{len(ids)} for {n} UAVs")
            for s in ids:
                if not is_valid_id(s):
                    check_id(s, self._where(f))
        if len(set(self.uav_ids)) != n:
            raise SchemaError(self._where("uav_ids"), "duplicate UAV id")
        for j in range(n):  # the legal case: one compiled pass per matrix
            c = self.cov[j]
            if _cov_code is None or _cov_code(c) != 0:
                try:
                    _check_cov(self._where("cov"), c)
                except SchemaError as e:
                    raise SchemaError(self._where("cov"), e.problem, f"UAV {self.uav_ids[j]}: {e.detail}") from None
        parts = self.parts
        for cols, bit in ((self._BEACON_COLS, PART_BEACON), (self._TRUTH_COLS, PART_TRUTH)):
            has = (parts & bit) != 0
            for f in cols:
                a = getattr(self, f)
                if a.ndim == 1:
                    nan_any = nan_all = np.isnan(a)
                else:
                    m = np.isnan(a)  # (n, 3)
                    nan_any, nan_all = m.any(axis=1), m.all(axis=1)
                bad = nan_any & has
                if bad.any():
                    raise SchemaError(self._where(f), "NaN where present", f"UAV {self.uav_ids[int(np.argmax(bad))]}")
                bad = ~nan_all & ~has
                if bad.any():
                    raise SchemaError(self._where(f), "a value where absent (must be NaN)",
                                      f"UAV {self.uav_ids[int(np.argmax(bad))]}")
        has = (parts & PART_BEACON) != 0
        if has.any():
            for f in ("range_m", "var_range_m2", "var_range_rate_m2_s2"):
                v = getattr(self, f)[has]
                if not (v > 0).all():
                    raise SchemaError(self._where(f), "must be > 0", f"min {v.min():.3g}")

    def per_uav(self, run_id: str, want=None) -> list:
        """[(key, message)] the per-UAV messages this epoch holds, in the order the group
        publishes them one by one (each UAV's UavNav, BeaconMeasurement, Truth). ``want``:
        None (all), or a predicate on the key: only the messages whose key it accepts are built.

        The messages are made without re-running each one's checks: this message passed the
        same checks on every present value (class text), so they are the messages the
        constructors would make (tests/sitl/bus/test_uav_group.py checks it against them)."""
        check_id(run_id, "run_id")
        hdr = {"t_gps_s": self.t_gps_s, "seq": self.seq, "incarnation": self.incarnation}
        parts = self.parts.tolist()
        nsat, fix = self.n_sats.tolist(), self.fix_type.tolist()
        P, V, C = self.pos_ecef_m, self.vel_ecef_m_s, self.cov
        r, rr, vr, vrr = (getattr(self, f).tolist() for f in self._BEACON_COLS)
        TP, TV = self.truth_pos_ecef_m, self.truth_vel_ecef_m_s
        b = self.beacon_id
        out = []
        for j, (uid, src, p) in enumerate(zip(self.uav_ids, self.uav_source_ids, parts)):
            if p & PART_NAV:
                key = f"{run_id}/uav/{uid}/nav"
                if want is None or want(key):
                    out.append((key, _made(UavNav, hdr, source_id=src, pos_ecef_m=P[j], vel_ecef_m_s=V[j], cov=C[j],
                                           n_sats=nsat[j], fix_type=fix[j])))
            if p & PART_BEACON:
                key = f"{run_id}/uav/{uid}/beacon/{b}"
                if want is None or want(key):
                    out.append((key, _made(BeaconMeasurement, hdr, source_id=src, range_m=r[j], range_rate_m_s=rr[j],
                                           var_range_m2=vr[j], var_range_rate_m2_s2=vrr[j], uav_pos_ecef_m=P[j],
                                           uav_vel_ecef_m_s=V[j], uav_cov=C[j])))
            if p & PART_TRUTH:
                key = f"{run_id}/truth/uav/{uid}"
                if want is None or want(key):
                    out.append((key, _made(Truth, hdr, source_id=self.truth_source_id, kind="uav",
                                           pos_ecef_m=TP[j], vel_ecef_m_s=TV[j])))
        return out


def _made(cls, header: dict, **fields):
    """A message of cls from values already checked by the constructor's rules (UavGroupEpoch
    .per_uav): the fields set as the constructor sets them (arrays read-only float64 rows of
    the checked arrays), without running the checks again."""
    m = object.__new__(cls)
    d = m.__dict__
    d.update(header)
    d.update(fields)
    return m


PSEUDORANGE_MAX_M = 1e8


@_message("sonde_relay", "sonde/{sonde}/relay", n_field="sat_ids")
class SondeRelay(Message):
    """One epoch of a radiosonde's raw GNSS observables relayed to a ground receiver.

    n = len(sat_ids) >= 0; an empty epoch (GNSS outage) is legal."""

    sat_ids: tuple[str, ...]
    pseudorange_m: np.ndarray = _arr("n", max_abs=PSEUDORANGE_MAX_M)
    pseudo_doppler_m_s: np.ndarray = _arr("n", max_abs=VEL_MAX_M_S)
    var_pseudorange_m2: np.ndarray = _arr("n", max_abs=VAR_MAX)
    var_pseudo_doppler_m2_s2: np.ndarray = _arr("n", max_abs=VAR_MAX)
    sat_pos_ecef_m: np.ndarray = _arr("n", 3, max_abs=POS_MAX_M)
    sat_vel_ecef_m_s: np.ndarray = _arr("n", 3, max_abs=VEL_MAX_M_S)
    ground_pos_ecef_m: np.ndarray = _arr(3, max_abs=POS_MAX_M)

    def _validate(self) -> None:
        if len(self.sat_ids) > N_SATS_MAX:
            raise SchemaError(self._where("sat_ids"), f"more than {N_SATS_MAX} satellites", f"{len(self.sat_ids)}")
        for i, s in enumerate(self.sat_ids):
            if not is_valid_id(s):
                check_id(s, self._where("sat_ids"))
        if len(set(self.sat_ids)) != len(self.sat_ids):
            raise SchemaError(self._where("sat_ids"), "duplicate satellite id")
        pr = self.pseudorange_m
        if pr.size and not ((pr > 0).all() and (pr < PSEUDORANGE_MAX_M).all()):
            raise SchemaError(self._where("pseudorange_m"), "out of range (0, 1e8) m",
                              f"min {pr.min():.6g}, max {pr.max():.6g}")
        for f in ("var_pseudorange_m2", "var_pseudo_doppler_m2_s2"):
            v = getattr(self, f)
            if v.size and not (v > 0).all():
                raise SchemaError(self._where(f), "must be > 0", f"min {v.min():.3g}")

    @property
    def n(self) -> int:
        return len(self.sat_ids)


SLANT_RANGE_MAX_M = 1e6
VAR_ANGLE_MAX_RAD2 = 100.0  # sigma 10 rad: no information, but not absurd


@_message("radar_meas", "radar/{radar}/sonde/{sonde}")
class RadarMeasurement(Message):
    """A tracking radar's slant range, azimuth and elevation of a sonde.

    ``angles_valid`` False: angular auto-tracking is lost; ``az_rad``/``el_rad`` may then be
    NaN and must be ignored (range stays valid). Finite angles are range-checked always.
    An azimuth of exactly 2pi (what ``np.mod(x, 2pi)`` returns for a tiny negative x) is
    stored as 0.0. No message is published for an epoch without a valid range."""

    slant_range_m: float
    az_rad: float = _nan_ok()
    el_rad: float = _nan_ok()
    var_range_m2: float = _num(0.0, VAR_MAX)
    var_az_rad2: float = _num(0.0, VAR_ANGLE_MAX_RAD2)
    var_el_rad2: float = _num(0.0, VAR_ANGLE_MAX_RAD2)
    angles_valid: bool
    radar_pos_ecef_m: np.ndarray = _arr(3, max_abs=POS_MAX_M)

    def _validate(self) -> None:
        if self.az_rad == 2 * math.pi:
            object.__setattr__(self, "az_rad", 0.0)
        r = self.slant_range_m
        if not 0 < r <= SLANT_RANGE_MAX_M:
            raise SchemaError(self._where("slant_range_m"), "out of range (0, 1e6] m", repr(r))
        for f in ("var_range_m2", "var_az_rad2", "var_el_rad2"):
            if not getattr(self, f) > 0:
                _check_positive(self._where(f), getattr(self, f))
        az, el = self.az_rad, self.el_rad
        for f, v in (("az_rad", az), ("el_rad", el)):
            if math.isnan(v) and self.angles_valid:
                raise SchemaError(self._where(f), "NaN while angles_valid")
        if not math.isnan(az) and not 0.0 <= az < 2 * math.pi:
            raise SchemaError(self._where("az_rad"), "out of range [0, 2pi)", repr(az))
        if not math.isnan(el) and not -math.pi / 2 <= el <= math.pi / 2:
            raise SchemaError(self._where("el_rad"), "out of range [-pi/2, pi/2]", repr(el))


def _check_kind(where: str, kind: str) -> None:
    if kind not in KINDS:
        raise SchemaError(where, f"must be one of {'|'.join(KINDS)}", repr(kind)[:40])


@_message("truth", "truth/{kind}/{id}")
class Truth(Message):
    """True state of a vehicle, for scoring only (never read by an estimator)."""

    kind: str
    pos_ecef_m: np.ndarray = _arr(3, max_abs=POS_MAX_M)
    vel_ecef_m_s: np.ndarray = _arr(3, max_abs=VEL_MAX_M_S)

    def _validate(self) -> None:
        _check_kind(self._where("kind"), self.kind)


@_message("estimate", "gs/estimate/{kind}/{id}")
class Estimate(Message):
    """The ground station's estimate of a target. ``nis``: normalised innovation squared of
    the last update, NaN when none was computed (finite values must be >= 0)."""

    kind: str
    pos_ecef_m: np.ndarray = _arr(3, max_abs=POS_MAX_M)
    vel_ecef_m_s: np.ndarray = _arr(3, max_abs=VEL_MAX_M_S)
    cov: np.ndarray = _arr(6, 6, max_abs=VAR_MAX)
    nis: float = _nan_ok()
    mode: str  # e.g. "fused", "radar_only"

    def _validate(self) -> None:
        _check_kind(self._where("kind"), self.kind)
        self._check_cov("cov")
        if self.nis < 0:
            raise SchemaError(self._where("nis"), "must be >= 0 or NaN", repr(self.nis))
        _check_token(self._where("mode"), self.mode)


@_message("integrity", "gs/integrity/{channel}")
class IntegrityEvent(Message):
    """An integrity-monitor event on a measurement channel. ``statistic``: the test
    statistic that triggered it, NaN for events without one (e.g. a readmission)."""

    channel: str
    event: str  # e.g. "step", "ramp", "outlier", "readmit"
    statistic: float = _nan_ok()

    def _validate(self) -> None:
        _check_token(self._where("channel"), self.channel)
        _check_token(self._where("event"), self.event)


@_message("link_stats", "gs/link/{link}")
class LinkStats(Message):
    """The ground station's statistics of one input link (the messages of one source id),
    from sequence numbers and arrival times (``sitl.bus.linkstats.LinkMonitor``). Cumulative
    since the GS started. ``missing``: sequence numbers skipped and not (yet) arrived late
    (loss); ``gaps``: runs of skipped numbers; ``out_of_order``: arrivals below the highest
    number seen; ``duplicates``: copies of a number already seen (discarded); latency: arrival
    (simulation time) minus ``t_gps_s`` of the message, over every copy received (NaN before
    any); ``stale``: the source has been silent for more than the monitor's ``stale_after_s``;
    ``last_t_gps_s``: the newest message time heard from it (NaN: none); ``restarts``: new
    incarnations of the source after the first heard (a restarted process: its numbering starts
    over, a new stream, never duplicates), ``source_incarnation`` the latest; ``rejected_future``
    / ``rejected_stale``: its messages the receiver's time guard refused (ahead of the
    receiver's clock / older than its window), counted here and nowhere used."""

    link: str  # the monitored source id
    received: int
    missing: int
    duplicates: int
    out_of_order: int
    gaps: int
    restarts: int = 0  # new incarnations of the source after its first
    source_incarnation: int = 0  # the source's latest incarnation heard
    rejected_future: int = 0  # refused by the receiver's time guard: ahead of its clock
    rejected_stale: int = 0  # refused by the receiver's time guard: older than its window
    latency_mean_s: float = _num(-T_GPS_MAX_S, T_GPS_MAX_S, nan_ok=True)
    latency_max_s: float = _num(-T_GPS_MAX_S, T_GPS_MAX_S, nan_ok=True)
    stale: bool
    last_t_gps_s: float = _num(0.0, T_GPS_MAX_S, nan_ok=True)

    def _validate(self) -> None:
        check_id(self.link, self._where("link"))
        for f in ("received", "missing", "duplicates", "out_of_order", "gaps", "restarts", "source_incarnation",
                  "rejected_future", "rejected_stale"):
            if getattr(self, f) < 0:
                raise SchemaError(self._where(f), "must be >= 0", repr(getattr(self, f)))


FAULT_TEXT_MAX = 1000


@_message("fault_control", "ctl/fault")
class FaultControl(Message):
    """A run-time change of a network fault: ``link`` names it (``mav:<sysid>``,
    ``zenoh:<worker>``, ``bus:<key expression>``), ``spec`` is the netem-like text of
    ``sitl.netfault.parse_spec`` ("" or "none": no fault). Parsed by the receiver (the
    schema checks only that both are printable one-line text of bounded length)."""

    link: str
    spec: str

    def _validate(self) -> None:
        for f in ("link", "spec"):
            v = getattr(self, f)
            if len(v) > FAULT_TEXT_MAX:
                raise SchemaError(self._where(f), f"longer than {FAULT_TEXT_MAX} chars", f"{len(v)} chars")
            if not v.isprintable():
                raise SchemaError(self._where(f), "not printable one-line text")
        if not self.link.strip():
            raise SchemaError(self._where("link"), "empty")


# ----------------------------------------------------------------------------------------
# Keys

KEY_TEMPLATES: dict[type[Message], str] = {cls: cls.KEY_TEMPLATE for cls in MESSAGE_TYPES.values()}
_FIELD_IDS = {"kind", "channel", "link", "group"}  # key ids that the message itself carries
_TEMPLATE_RE = re.compile(r"\{(\w+)\}")


def _template_ids(template: str) -> list[str]:
    return _TEMPLATE_RE.findall(template)


def key_for(run_id: str, msg: Message | type[Message], **ids: str | int) -> str:
    """The bus key of ``msg`` in run ``run_id``, e.g. ``key_for("r1", nav, uav=3)`` ->
    ``"r1/uav/3/nav"``.

    Ids named in the template (uav, beacon, sonde, radar, id) are given as keywords (ints
    are formatted); ``kind`` (Truth, Estimate) and ``channel`` (IntegrityEvent) are taken from
    the message when a message instance is given. Every id is validated like a source id.
    """
    cls = msg if isinstance(msg, type) else type(msg)
    if cls not in KEY_TEMPLATES:
        raise TypeError(f"not a bus message kind: {cls!r}")
    template = cls.KEY_TEMPLATE
    names = _template_ids(template)
    values: dict[str, str] = {}
    for name in names:
        if name in ids:
            v = ids[name]
        elif name in _FIELD_IDS and not isinstance(msg, type):
            v = getattr(msg, name)
        else:
            raise ValueError(f"key_for({cls.__name__}): missing id {name!r} for {template!r}")
        if isinstance(v, (int, np.integer)) and not isinstance(v, bool):
            v = str(int(v))
        values[name] = check_id(v, f"key id {name}")
    extra = set(ids) - set(names)
    if extra:
        raise ValueError(f"key_for({cls.__name__}): unexpected ids {sorted(extra)} for {template!r}")
    if not isinstance(msg, type):
        for name in set(names) & _FIELD_IDS:
            if values[name] != getattr(msg, name):
                raise ValueError(f"key_for({cls.__name__}): {name}={values[name]!r} "
                                 f"contradicts the message's {getattr(msg, name)!r}")
    if "kind" in values:
        _check_kind("key id kind", values["kind"])
    return f"{check_id(run_id, 'run_id')}/" + template.format(**values)


def key_pattern(run_id: str, cls: type[Message], **ids: str | int) -> str:
    """A subscription key expression for ``cls`` in ``run_id``: ids not given become ``*``.

    ``key_pattern("r1", BeaconMeasurement, uav=3)`` -> ``"r1/uav/3/beacon/*"``."""
    if cls not in KEY_TEMPLATES:
        raise TypeError(f"not a bus message kind: {cls!r}")
    names = _template_ids(cls.KEY_TEMPLATE)
    extra = set(ids) - set(names)
    if extra:
        raise ValueError(f"key_pattern({cls.__name__}): unexpected ids {sorted(extra)}")
    values = {}
    for name in names:
        if name in ids:
            v = ids[name]
            values[name] = check_id(str(v) if isinstance(v, int) else v, f"key id {name}")
        else:
            values[name] = "*"
    return f"{check_id(run_id, 'run_id')}/" + cls.KEY_TEMPLATE.format(**values)


_KEY_PARSERS = [
    (cls, re.compile("^" + _TEMPLATE_RE.sub(lambda m: f"(?P<{m.group(1)}>[^/]+)",
                                            cls.KEY_TEMPLATE) + r"\Z"))
    for cls in MESSAGE_TYPES.values()
]


def parse_key(key: str) -> tuple[str, type[Message], dict[str, str]] | None:
    """Split a bus key into (run_id, message class, ids), or None if it fits no template.

    ``parse_key("r1/uav/3/beacon/b7")`` -> ``("r1", BeaconMeasurement, {"uav": "3",
    "beacon": "b7"})``."""
    if type(key) is not str:
        return _parse_key(key)
    hit = _parse_key_cached(key)  # the same keys recur every epoch
    return None if hit is None else (hit[0], hit[1], dict(hit[2]))


@functools.lru_cache(maxsize=8192)
def _parse_key_cached(key: str):
    return _parse_key(key)


def _parse_key(key):
    run_id, sep, rest = key.partition("/")
    if not sep or not is_valid_id(run_id):
        return None
    for cls, rx in _KEY_PARSERS:
        m = rx.match(rest)
        if m and all(is_valid_id(v) for v in m.groupdict().values()):
            return run_id, cls, m.groupdict()
    return None


__all__ = [
    "KEY_TEMPLATES",
    "N_SATS_MAX",
    "POS_MAX_M",
    "T_GPS_MAX_S",
    "VAR_MAX",
    "VEL_MAX_M_S",
    "KINDS",
    "MESSAGE_TYPES",
    "SCHEMA_VERSION",
    "BeaconMeasurement",
    "Estimate",
    "FaultControl",
    "FieldSpec",
    "IntegrityEvent",
    "LinkStats",
    "Message",
    "RadarMeasurement",
    "SchemaError",
    "SondeRelay",
    "Truth",
    "UAV_GROUP_MAX",
    "UavGroupEpoch",
    "UavNav",
    "check_id",
    "is_valid_id",
    "key_for",
    "key_pattern",
    "parse_key",
]
