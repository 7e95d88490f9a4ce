"""A bus log as MCAP (https://mcap.dev), for Foxglove and the ``mcap`` CLI.

Layout:
- one channel per bus key (topic = the key as on the bus, e.g. ``demo/truth/uav/1``), message
  encoding ``json``;
- one schema per message type (``skyfuse.bus.v<N>.<Type>``, encoding ``jsonschema``): a JSON
  Schema generated from the bus schema's field declarations (`sitl.bus.schema`), with each
  field's unit (from its name) as its description. JSON was chosen over a binary encoding so
  that Foxglove shows and plots every field without a custom decoder (no protobuf or ROS
  definitions to keep in step with the bus schema);
- a message is the decoded bus message as a JSON object, its fields by name; arrays nested as
  the schema shapes them (a covariance as 6 rows of 6); a NaN (a radar's lost angle, an
  estimate without NIS) is ``null``;
- ``log_time``: the record's receive time (the recorder's simulated clock, GPS seconds),
  ``publish_time``: the message's own simulated time ``t_gps_s``; both in nanoseconds of UTC
  since the Unix epoch (GPS - 18 s: the leap seconds of `sitl.constants`), so viewers show
  the simulated date; a record received before the recorder's clock started (no finite receive
  time) gets its publish time as log time, counted;
- a payload that does not decode goes, with its key, the decoder's reason and its bytes
  (base64), to the one channel ``skyfuse/undecodable``: the counts of the bus log are kept;
- a metadata record ``skyfuse`` says where the file came from and the time base.
"""
from __future__ import annotations

import base64
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sitl.bus import MESSAGE_TYPES, SCHEMA_VERSION, BusDecodeError, decode
from sitl.bus.buslog import BusLogStats
from sitl.bus.schema import F_ARRAY, F_BOOL, F_FLOAT, F_INT, F_STR, F_STRS
from sitl.constants import GPS_UTC_LEAP_S

MCAP_SCHEMA = "skyfuse.export.mcap/1"
UNDECODABLE_TOPIC = "skyfuse/undecodable"
GPS_EPOCH_UNIX_NS = 315_964_800 * 10**9
LEAP_NS = int(round(GPS_UTC_LEAP_S * 1e9))

# the unit a field's name ends with (the house rule: names carry units)
_UNIT_SUFFIXES = (("_m2_s2", "m^2/s^2"), ("_m_s", "m/s"), ("_m2", "m^2"), ("_rad2", "rad^2"), ("_rad", "rad"),
                  ("_deg", "deg"), ("_m", "m"), ("_s", "s"))


def schema_name(cls) -> str:
    return f"skyfuse.bus.v{SCHEMA_VERSION}.{cls.__name__}"


def _unit(name: str) -> str:
    for suffix, unit in _UNIT_SUFFIXES:
        if name.endswith(suffix):
            return unit
    return ""


def _array_schema(shape: tuple) -> dict:
    if not shape:
        return {"type": ["number", "null"]}
    d, rest = shape[0], shape[1:]
    s: dict = {"type": "array", "items": _array_schema(rest)}
    if d != "n":
        s["minItems"] = s["maxItems"] = int(d)
    return s


def json_schema(cls) -> dict:
    """The JSON Schema (draft 2020-12) of bus message class ``cls``'s JSON form."""
    props = {}
    for spec in cls.FIELDS:
        if spec.ftype == F_FLOAT:
            s: dict = {"type": ["number", "null"] if spec.nan_ok else "number"}
        elif spec.ftype == F_INT:
            s = {"type": "integer"}
        elif spec.ftype == F_BOOL:
            s = {"type": "boolean"}
        elif spec.ftype == F_STR:
            s = {"type": "string"}
        elif spec.ftype == F_STRS:
            s = {"type": "array", "items": {"type": "string"}}
        elif spec.ftype == F_ARRAY:
            s = _array_schema(spec.shape)
        else:  # pragma: no cover - the schema has no other field types
            raise TypeError(f"{cls.__name__}.{spec.name}: field type {spec.ftype!r}")
        u = _unit(spec.name)
        if spec.name == "cov" or spec.name.endswith("_cov"):
            s["description"] = "covariance over ECEF [position (m), velocity (m/s)], 6x6"
        elif u:
            s["description"] = f"unit: {u}"
        props[spec.name] = s
    doc = (cls.__doc__ or "").strip().split("\n\n")[0]
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": schema_name(cls),
            "description": " ".join(doc.split()), "type": "object", "properties": props,
            "required": [s.name for s in cls.FIELDS], "additionalProperties": False}


_UNDECODABLE_SCHEMA = {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": "skyfuse.bus.Undecodable",
                       "description": "a bus log record whose payload did not decode",
                       "type": "object", "required": ["key", "reason", "t_recv_s", "payload_base64"],
                       "properties": {"key": {"type": "string"}, "reason": {"type": "string"},
                                      "t_recv_s": {"type": ["number", "null"], "description": "unit: s"},
                                      "payload_base64": {"type": "string"}}}


def _jsonable(v):
    if isinstance(v, np.ndarray):
        return [_jsonable(x) for x in v] if v.ndim > 1 else [None if math.isnan(x) else x for x in v.tolist()]
    if isinstance(v, float) and math.isnan(v):
        return None
    if isinstance(v, tuple):
        return list(v)
    return v


def message_json(msg) -> dict:
    """A bus message as the JSON object its schema describes."""
    return {spec.name: _jsonable(getattr(msg, spec.name)) for spec in msg.FIELDS}


def utc_ns(t_gps_s: float) -> int:
    """GPS seconds -> integer nanoseconds of UTC since the Unix epoch (microsecond resolution)."""
    return GPS_EPOCH_UNIX_NS - LEAP_NS + int(round(t_gps_s * 1e6)) * 1000


@dataclass
class McapResult:
    path: Path
    records: int = 0
    undecodable: int = 0
    no_receive_time: int = 0
    per_key: dict = field(default_factory=dict)  # key -> messages written on its channel
    stats: BusLogStats = field(default_factory=BusLogStats)


def export_mcap(log: str | os.PathLike, out: str | os.PathLike, *, progress: bool | None = None,
                say=None) -> McapResult:
    """Write bus log ``log`` as MCAP file ``out`` (module doc); a temporary name, then renamed.
    The log must be known to be a bus log (`sitl.app.export.source.resolve_log`)."""
    try:
        from mcap.writer import CompressionType, Writer
    except ImportError:
        from sitl.app.args import UsageError

        raise UsageError("export mcap: needs the mcap library: pip install 'skyfuse[export]'") from None
    from sitl.app.export import export_provenance, skyfuse_version
    from sitl.app.export.source import read_records

    out = Path(out)
    res = McapResult(out)
    tmp = out.with_name(out.name + ".part")
    schemas: dict = {}
    channels: dict = {}  # (topic, schema name) -> channel id
    seqs: dict = {}
    try:
        with open(tmp, "wb") as f:
            w = Writer(f, compression=CompressionType.ZSTD)
            w.start(profile="", library=f"skyfuse {skyfuse_version()}")

            def channel(topic: str, sname: str, sdoc: dict) -> int:
                cid = channels.get((topic, sname))
                if cid is None:
                    sid = schemas.get(sname)
                    if sid is None:
                        sid = schemas[sname] = w.register_schema(
                            name=sname, encoding="jsonschema", data=json.dumps(sdoc).encode())
                    cid = channels[(topic, sname)] = w.register_channel(topic=topic, message_encoding="json",
                                                                        schema_id=sid)
                return cid

            for rec in read_records(Path(log), stats=res.stats, progress=progress, say=say, desc="mcap"):
                res.records += 1
                try:
                    msg = decode(rec.payload)
                except BusDecodeError as e:
                    res.undecodable += 1
                    t = rec.t_recv_s if math.isfinite(rec.t_recv_s) else 0.0
                    cid = channel(UNDECODABLE_TOPIC, "skyfuse.bus.Undecodable", _UNDECODABLE_SCHEMA)
                    data = {"key": rec.key, "reason": e.reason,
                            "t_recv_s": rec.t_recv_s if math.isfinite(rec.t_recv_s) else None,
                            "payload_base64": base64.b64encode(rec.payload).decode("ascii")}
                    seqs[cid] = seqs.get(cid, 0) + 1
                    w.add_message(cid, log_time=utc_ns(t), publish_time=utc_ns(t),
                                  data=json.dumps(data).encode(), sequence=seqs[cid] & 0xFFFFFFFF)
                    continue
                cls = type(msg)
                cid = channel(rec.key, schema_name(cls), json_schema(cls))
                pub = utc_ns(float(msg.t_gps_s))
                if math.isfinite(rec.t_recv_s):
                    log_ns = utc_ns(rec.t_recv_s)
                else:
                    res.no_receive_time += 1
                    log_ns = pub
                seqs[cid] = seqs.get(cid, 0) + 1
                w.add_message(cid, log_time=max(log_ns, 0), publish_time=max(pub, 0),
                              data=json.dumps(message_json(msg), allow_nan=False).encode(),
                              sequence=seqs[cid] & 0xFFFFFFFF)
                res.per_key[rec.key] = res.per_key.get(rec.key, 0) + 1
            w.add_metadata("skyfuse", {
                "provenance": json.dumps(export_provenance(log)),
                "schema": MCAP_SCHEMA, "skyfuse_version": skyfuse_version(), "source": os.fspath(log),
                "bus_schema_version": str(SCHEMA_VERSION), "records": str(res.records),
                "undecodable": str(res.undecodable),
                "torn_tail": json.dumps({"dropped_bytes": res.stats.dropped_bytes, "reason": res.stats.reason}),
                "log_time": "the record's receive time (recorder's simulated clock), as UTC ns since 1970",
                "publish_time": "the message's t_gps_s, as UTC ns since 1970 (UTC = GPS - 18 s)",
                "message_types": ",".join(sorted(MESSAGE_TYPES))})
            w.finish()
        if res.records == 0:  # nothing to export: no file (the caller says so)
            tmp.unlink()
            return res
        os.replace(tmp, out)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return res
