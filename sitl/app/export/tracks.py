"""A run's tracks from its bus log: per object (beacon, sondes, UAVs) and epoch, the truth
(``<run>/truth/<kind>/<id>``), the estimate (the ground station's, ``<run>/gs/estimate/<kind>/<id>``;
for a UAV its own onboard navigation, ``<run>/uav/<id>/nav``), the estimate's covariance and its
error against the truth of the same object at the same time -- paired as `sitl.app.scoring`
pairs them (time rounded to the microsecond), so the errors here are the run's scored errors.

`collect_tracks` reads the log once; `track_table` lays the tracks out as one row per object and
epoch (the outer join of the truth's and the estimate's epochs: a side that has no value at an
epoch is null), every column declared once in `COLUMNS` with its unit and description (the
units are also in the names). The fixed sites seen in the log (the radars, the sondes' ground
receivers) are kept for the maps.

Coordinates: ECEF WGS-84 and geodetic WGS-84 (latitude, longitude, ellipsoidal height); local
errors and sigmas in east-north-up about the truth (the estimate when there is no truth).
"""
from __future__ import annotations

import math
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sitl.bus import BusDecodeError, Estimate, RadarMeasurement, SondeRelay, Truth, UavNav, decode, parse_key
from sitl.bus.buslog import BusLogStats, BusRecord
from sitl.constants import GPS_UTC_LEAP_S
from sitl.geodesy import ecef_to_geodetic, enu_rotation

TABLE_SCHEMA = "skyfuse.export.tracks/1"
#: GPS epoch (1980-01-06T00:00:00Z) in Unix seconds
GPS_EPOCH_UNIX_S = 315_964_800
#: sqrt of the chi-square 95 % quantile with 2 degrees of freedom: the 95 % horizontal ellipse
CHI2_2DOF_95_SQRT = math.sqrt(-2.0 * math.log(0.05))

ESTIMATOR_GS = "ground_station"
ESTIMATOR_ONBOARD = "onboard_nav"


@dataclass
class Series:
    """One object's epochs of one side (truth or estimate), keyed by t_gps_s (rounded to 1 us)."""

    pos: dict = field(default_factory=dict)  # t -> (3,) ECEF m
    vel: dict = field(default_factory=dict)  # t -> (3,) ECEF m/s
    cov: dict = field(default_factory=dict)  # t -> (6, 6) (estimates)
    nis: dict = field(default_factory=dict)  # t -> float (GS estimates; NaN: none)
    mode: dict = field(default_factory=dict)  # t -> str (GS estimates)
    t_recv: dict = field(default_factory=dict)  # t -> the record's receive time, s
    repeats: int = 0  # epochs received more than once (the last copy is kept)

    def put(self, t: float, t_recv: float, pos, vel, cov=None, nis=math.nan, mode=None) -> None:
        if t in self.pos:
            self.repeats += 1
        self.pos[t], self.vel[t], self.t_recv[t] = pos, vel, t_recv
        if cov is not None:
            self.cov[t] = cov
        self.nis[t] = nis
        if mode is not None:
            self.mode[t] = mode


@dataclass
class TrackedObject:
    run_id: str
    kind: str  # uav | beacon | sonde
    object_id: str
    truth: Series = field(default_factory=Series)
    estimate: Series = field(default_factory=Series)
    estimator: str = ""  # ground_station | onboard_nav | "" (none)


@dataclass
class Tracks:
    """What `collect_tracks` found: the objects, the fixed sites, and the log's counters."""

    source: str
    objects: dict = field(default_factory=dict)  # (run_id, kind, id) -> TrackedObject
    sites: dict = field(default_factory=dict)  # (run_id, site kind, id) -> (3,) ECEF m
    records: int = 0
    undecodable: int = 0
    stats: BusLogStats = field(default_factory=BusLogStats)

    def sorted_objects(self) -> list:
        return [self.objects[k] for k in sorted(self.objects)]


def _obj(tr: Tracks, run_id: str, kind: str, oid: str) -> TrackedObject:
    k = (run_id, kind, oid)
    o = tr.objects.get(k)
    if o is None:
        o = tr.objects[k] = TrackedObject(run_id, kind, oid)
    return o


def collect_tracks(records: Iterable[BusRecord], source: str | os.PathLike = "",
                   stats: BusLogStats | None = None) -> Tracks:
    """The tracks of a bus log's records (`sitl.app.export.source.read_records`). A payload that
    does not decode is counted (``undecodable``) and skipped, as the live scorer skips it."""
    tr = Tracks(source=os.fspath(source), stats=stats if stats is not None else BusLogStats())
    for rec in records:
        tr.records += 1
        parsed = parse_key(rec.key)
        if parsed is None:
            continue
        run_id, cls, ids = parsed
        if cls not in (Truth, Estimate, UavNav, RadarMeasurement, SondeRelay):
            continue
        try:
            msg = decode(rec.payload)
        except BusDecodeError:
            tr.undecodable += 1
            continue
        if type(msg) is not cls:  # a payload of another kind on this key: not this key's data
            tr.undecodable += 1
            continue
        t = round(float(msg.t_gps_s), 6)
        if cls is Truth:
            _obj(tr, run_id, msg.kind, ids["id"]).truth.put(t, rec.t_recv_s, msg.pos_ecef_m, msg.vel_ecef_m_s)
        elif cls is Estimate:
            o = _obj(tr, run_id, msg.kind, ids["id"])
            o.estimator = ESTIMATOR_GS
            o.estimate.put(t, rec.t_recv_s, msg.pos_ecef_m, msg.vel_ecef_m_s, msg.cov, float(msg.nis), msg.mode)
        elif cls is UavNav:
            o = _obj(tr, run_id, "uav", ids["uav"])
            if o.estimator != ESTIMATOR_GS:
                o.estimator = ESTIMATOR_ONBOARD
                o.estimate.put(t, rec.t_recv_s, msg.pos_ecef_m, msg.vel_ecef_m_s, msg.cov)
        elif cls is RadarMeasurement:
            tr.sites[(run_id, "radar", ids["radar"])] = msg.radar_pos_ecef_m
        else:  # SondeRelay: the ground receiver the sonde's GNSS is relayed to
            tr.sites[(run_id, "ground_receiver", ids["sonde"])] = msg.ground_pos_ecef_m
    return tr


def read_tracks(log: str | os.PathLike, *, progress: bool | None = None, say=None) -> Tracks:
    """`collect_tracks` of bus log ``log`` (a torn tail: the records before it, said once)."""
    from sitl.app.export.source import read_records

    st = BusLogStats()
    return collect_tracks(read_records(Path(log), stats=st, progress=progress, say=say), log, st)


# ---------------------------------------------------------------------------- the table

@dataclass(frozen=True)
class Column:
    name: str
    dtype: str  # "f8" | "i8" | "str" | "utc"
    unit: str  # "" for none
    description: str


_AX = ("x", "y", "z")
_STATE = ("px", "py", "pz", "vx", "vy", "vz")


def _cov_unit(a: str, b: str) -> str:
    n = (a[0] == "v") + (b[0] == "v")
    return ("m2", "m2_s", "m2_s2")[n]


def _columns() -> tuple:
    c = [Column("run_id", "str", "", "run id (the first part of every bus key)"),
         Column("kind", "str", "", "object kind: uav, beacon or sonde"),
         Column("object_id", "str", "", "object id within its kind (the last part of its bus keys)"),
         Column("t_gps_s", "f8", "s", "epoch: GPS time, seconds since 1980-01-06T00:00:00Z"),
         Column("t_utc", "utc", "UTC", "the epoch as UTC (GPS time - 18 s leap seconds)"),
         Column("estimator", "str", "",
                "what made the estimate: ground_station (the fusing ground station) or onboard_nav "
                "(a UAV's own navigation solution); null when the row has no estimate")]
    for side, what in (("truth", "true"), ("est", "estimated")):
        c += [Column(f"{side}_pos_ecef_{a}_m", "f8", "m", f"{what} position, ECEF WGS-84 {a}") for a in _AX]
        c += [Column(f"{side}_vel_ecef_{a}_m_s", "f8", "m/s", f"{what} velocity, ECEF WGS-84 {a}") for a in _AX]
        c += [Column(f"{side}_lat_deg", "f8", "deg", f"{what} geodetic latitude, WGS-84"),
              Column(f"{side}_lon_deg", "f8", "deg", f"{what} longitude, WGS-84, in (-180, 180]"),
              Column(f"{side}_h_m", "f8", "m", f"{what} height above the WGS-84 ellipsoid")]
    c += [Column("est_mode", "str", "", "the ground station's estimate mode (fused, radar_only, ...)"),
          Column("est_nis", "f8", "1", "normalised innovation squared of the estimate's last update "
                                       "(null: none computed)"),
          Column("est_t_recv_s", "f8", "s", "when the estimate was recorded (the recorder's simulated "
                                            "clock, GPS seconds)")]
    for i, a in enumerate(_STATE):
        for b in _STATE[i:]:
            u = _cov_unit(a, b)
            c.append(Column(f"cov_{a}_{b}_{u}", "f8", u.replace("_", "/"),
                            f"estimate covariance over ECEF [position, velocity]: entry ({a}, {b})"))
    c += [Column(f"sigma_{d}_m", "f8", "m", f"estimate 1-sigma position uncertainty, local {name}")
          for d, name in (("e", "east"), ("n", "north"), ("u", "up"))]
    c += [Column("ellipse95_semi_major_m", "f8", "m", "horizontal 95 % error ellipse of the estimate: semi-major axis"),
          Column("ellipse95_semi_minor_m", "f8", "m", "horizontal 95 % error ellipse of the estimate: semi-minor axis"),
          Column("ellipse95_azimuth_deg", "f8", "deg",
                 "horizontal 95 % error ellipse: azimuth of the semi-major axis, from north towards east, [0, 180)")]
    c += [Column(f"err_ecef_{a}_m", "f8", "m", f"estimate - truth, ECEF {a}") for a in _AX]
    c += [Column(f"err_{d}_m", "f8", "m", f"estimate - truth, local {name} (about the truth)")
          for d, name in (("e", "east"), ("n", "north"), ("u", "up"))]
    c += [Column("err_horiz_m", "f8", "m", "horizontal position error |(err_e, err_n)|"),
          Column("err_3d_m", "f8", "m", "3-D position error |estimate - truth| (the run's scored error)"),
          Column("err_vel_3d_m_s", "f8", "m/s", "3-D velocity error |estimate - truth|"),
          Column("nees_pos", "f8", "1", "position NEES: err^T P_pos^-1 err, 3 degrees of freedom"),
          Column("nees", "f8", "1", "state NEES over [position, velocity]: 6 degrees of freedom")]
    return tuple(c)


COLUMNS: tuple = _columns()
COLUMN_NAMES = tuple(c.name for c in COLUMNS)


def _stack(d: dict, ts: list, shape: tuple) -> np.ndarray:
    out = np.full((len(ts),) + shape, np.nan)
    for i, t in enumerate(ts):
        v = d.get(t)
        if v is not None:
            out[i] = v
    return out


def _geodetic(pos: np.ndarray):
    lat, lon, h = ecef_to_geodetic(np.where(np.isnan(pos), 1.0, pos))  # NaN rows: filled, then masked
    bad = np.isnan(pos).any(axis=-1)
    lat, lon, h = (np.where(bad, np.nan, v) for v in (np.degrees(lat), np.degrees(lon), h))
    return lat, lon, h


def _ellipse(p_en: np.ndarray):
    """95 % ellipse of 2x2 horizontal covariances (..., 2, 2): semi-axes (m) and azimuth of
    the major axis from north towards east (deg, [0, 180))."""
    ok = np.isfinite(p_en).all(axis=(-1, -2))
    p = np.where(ok[..., None, None], p_en, np.eye(2))
    w, v = np.linalg.eigh(p)  # ascending
    w = np.clip(w, 0.0, None)
    major = v[..., :, 1]  # (east, north) of the major axis
    az = np.degrees(np.arctan2(major[..., 0], major[..., 1])) % 180.0
    k = CHI2_2DOF_95_SQRT
    a, b = k * np.sqrt(w[..., 1]), k * np.sqrt(w[..., 0])
    return tuple(np.where(ok, x, np.nan) for x in (a, b, az))


def object_arrays(o: TrackedObject) -> dict:
    """The table's columns (numpy arrays; NaN / None where a side has no value) of one object."""
    ts = sorted(set(o.truth.pos) | set(o.estimate.pos))
    n = len(ts)
    t = np.array(ts, dtype=float)
    tp, tv = _stack(o.truth.pos, ts, (3,)), _stack(o.truth.vel, ts, (3,))
    ep, ev = _stack(o.estimate.pos, ts, (3,)), _stack(o.estimate.vel, ts, (3,))
    cov = _stack(o.estimate.cov, ts, (6, 6))
    has_est = ~np.isnan(ep).any(axis=1)
    cols: dict = {"run_id": [o.run_id] * n, "kind": [o.kind] * n, "object_id": [o.object_id] * n, "t_gps_s": t,
                  "estimator": [o.estimator if h else None for h in has_est]}
    for side, p, v in (("truth", tp, tv), ("est", ep, ev)):
        for j, a in enumerate(_AX):
            cols[f"{side}_pos_ecef_{a}_m"] = p[:, j]
            cols[f"{side}_vel_ecef_{a}_m_s"] = v[:, j]
        cols[f"{side}_lat_deg"], cols[f"{side}_lon_deg"], cols[f"{side}_h_m"] = _geodetic(p)
    cols["est_mode"] = [o.estimate.mode.get(x) for x in ts]
    cols["est_nis"] = np.array([o.estimate.nis.get(x, math.nan) for x in ts], dtype=float)
    cols["est_t_recv_s"] = np.array([o.estimate.t_recv.get(x, math.nan) for x in ts], dtype=float)
    for i, a in enumerate(_STATE):
        for j in range(i, 6):
            cols[f"cov_{a}_{_STATE[j]}_{_cov_unit(a, _STATE[j])}"] = cov[:, i, j]
    # the local frame: about the truth, or the estimate where there is no truth
    ref = np.where(np.isnan(tp), ep, tp)
    lat, lon, _ = ecef_to_geodetic(np.where(np.isnan(ref), 1.0, ref))
    r = enu_rotation(lat, lon)  # (n, 3, 3)
    p_enu = r @ cov[:, :3, :3] @ np.swapaxes(r, -1, -2)
    for k, d in enumerate("enu"):
        cols[f"sigma_{d}_m"] = np.sqrt(np.clip(p_enu[:, k, k], 0.0, None))
    cols["ellipse95_semi_major_m"], cols["ellipse95_semi_minor_m"], cols["ellipse95_azimuth_deg"] = \
        _ellipse(p_enu[:, :2, :2])
    e = ep - tp
    ev_err = ev - tv
    e_enu = (r @ np.where(np.isnan(e), 0.0, e)[..., None])[..., 0]
    e_enu[np.isnan(e).any(axis=1)] = np.nan
    for j, a in enumerate(_AX):
        cols[f"err_ecef_{a}_m"] = e[:, j]
    for k, d in enumerate("enu"):
        cols[f"err_{d}_m"] = e_enu[:, k]
    cols["err_horiz_m"] = np.hypot(e_enu[:, 0], e_enu[:, 1])
    cols["err_3d_m"] = np.linalg.norm(e, axis=1)
    cols["err_vel_3d_m_s"] = np.linalg.norm(ev_err, axis=1)
    cols["nees_pos"] = _nees(e, cov[:, :3, :3])
    cols["nees"] = _nees(np.concatenate([e, ev_err], axis=1), cov)
    return cols


def _nees(e: np.ndarray, p: np.ndarray) -> np.ndarray:
    out = np.full(len(e), np.nan)
    ok = np.isfinite(e).all(axis=1) & np.isfinite(p).all(axis=(1, 2))
    if not ok.any():
        return out
    try:
        x = np.linalg.solve(p[ok], e[ok][..., None])[..., 0]
        out[ok] = np.einsum("ij,ij->i", e[ok], x)
        return out
    except np.linalg.LinAlgError:  # a singular covariance among them: row by row
        pass
    for i in np.flatnonzero(ok):
        try:
            out[i] = float(e[i] @ np.linalg.solve(p[i], e[i]))
        except np.linalg.LinAlgError:  # a singular covariance: no NEES
            pass
    return out


def _require_pyarrow():
    try:
        import pyarrow as pa
    except ImportError:
        from sitl.app.args import UsageError

        raise UsageError("export: tables need pyarrow: pip install 'skyfuse[export]'") from None
    return pa


def arrow_schema(metadata: dict | None = None):
    """The table's pyarrow schema: every column of `COLUMNS` with its unit and description as
    field metadata (``unit``, ``description``); ``metadata``: the table's own (str -> str)."""
    pa = _require_pyarrow()
    types = {"f8": pa.float64(), "i8": pa.int64(), "str": pa.string(), "utc": pa.timestamp("us", tz="UTC")}
    fields = [pa.field(c.name, types[c.dtype], nullable=True,
                       metadata={"unit": c.unit, "description": c.description}) for c in COLUMNS]
    return pa.schema(fields, metadata={k: str(v) for k, v in (metadata or {}).items()})


def table_metadata(tracks: Tracks) -> dict:
    """The table's metadata: its schema id, the skyfuse version, the source log and its counters."""
    import json

    from sitl.app.export import skyfuse_version

    from sitl.app.export import export_provenance

    return {"schema": TABLE_SCHEMA, "skyfuse_version": skyfuse_version(), "source": tracks.source,
            "provenance": json.dumps(export_provenance(tracks.source)),
            "run_ids": json.dumps(sorted({o.run_id for o in tracks.objects.values()})),
            "records": str(tracks.records), "undecodable": str(tracks.undecodable),
            "torn_tail": json.dumps({"dropped_bytes": tracks.stats.dropped_bytes, "reason": tracks.stats.reason}),
            "frames": "ECEF WGS-84; geodetic WGS-84 (ellipsoidal heights); local ENU about the truth",
            "time": "t_gps_s: GPS seconds since 1980-01-06T00:00:00Z; t_utc = GPS - 18 s"}


def track_table(tracks: Tracks):
    """The tracks as one pyarrow Table, one row per object and epoch, sorted by run, kind,
    object and time; NaN of a float column is stored as null (no value)."""
    pa = _require_pyarrow()
    schema = arrow_schema(table_metadata(tracks))
    parts: dict = {c.name: [] for c in COLUMNS}
    for o in tracks.sorted_objects():
        arr = object_arrays(o)
        for c in COLUMNS:
            if c.name != "t_utc":
                parts[c.name].append(arr[c.name])
    arrays = []
    for c in COLUMNS:
        if c.dtype == "utc":
            t = np.concatenate(parts["t_gps_s"]) if parts["t_gps_s"] else np.zeros(0)
            us = np.round((t + (GPS_EPOCH_UNIX_S - GPS_UTC_LEAP_S)) * 1e6).astype(np.int64)
            arrays.append(pa.array(us, type=pa.timestamp("us", tz="UTC")))
        elif c.dtype == "f8":
            v = np.concatenate(parts[c.name]).astype(float) if parts[c.name] else np.zeros(0)
            arrays.append(pa.array(v, type=pa.float64(), mask=np.isnan(v)))
        else:
            v = [x for p in parts[c.name] for x in p]
            arrays.append(pa.array(v, type=schema.field(c.name).type))
    return pa.Table.from_arrays(arrays, schema=schema)


def write_table(table, path: str | os.PathLike, fmt: str = "parquet") -> Path:
    """Write ``table`` as Parquet (the schema's units and descriptions travel in the file) or as
    CSV plus its W3C "CSV on the Web" metadata file ``<path>-metadata.json`` (the same units and
    descriptions, and the table's metadata). Written to a temporary name, then renamed."""
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    if fmt == "parquet":
        import pyarrow.parquet as pq

        pq.write_table(table, tmp, compression="zstd")
    elif fmt == "csv":
        import json

        import pyarrow.csv as pcsv

        pcsv.write_csv(table, tmp)
        meta = {"@context": "http://www.w3.org/ns/csvw", "url": path.name,
                "dc:conformsTo": TABLE_SCHEMA,
                "notes": {k.decode(): v.decode() for k, v in (table.schema.metadata or {}).items()},
                "tableSchema": {"columns": [
                    {"name": c.name, "titles": c.name, "dc:description": c.description,
                     "datatype": {"f8": "double", "i8": "integer", "str": "string", "utc": "dateTime"}[c.dtype],
                     **({"unit": c.unit} if c.unit else {})} for c in COLUMNS]}}
        mpath = path.with_name(path.name + "-metadata.json")
        mpath.write_text(json.dumps(meta, indent=1), encoding="utf-8")
    else:
        raise ValueError(f"write_table: unknown format {fmt!r} (parquet or csv)")
    os.replace(tmp, path)
    return path
