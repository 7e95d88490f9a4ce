"""A run's tracks for maps: GeoJSON (RFC 7946) and KML 2.2.

What is drawn, per object (UAVs, the beacon, sondes): its true track and its estimated track
(the ground station's; a UAV's own onboard navigation), its last estimate as a point with its
95 % horizontal uncertainty ellipse, and the fixed sites (radars, the sondes' ground receivers).

GeoJSON (RFC 7946): one FeatureCollection; positions are [longitude, latitude, height] in
decimal degrees WGS-84 and metres above the WGS-84 ellipsoid (sec. 3.1.1, 4); a track is a
LineString (a MultiLineString when it crosses the antimeridian: cut there, sec. 3.1.9; a Point
when it has a single epoch); ellipses are Polygons whose exterior ring is closed and
counterclockwise (sec. 3.1.6). Each feature's properties name the object and track; a track's
``t_gps_s`` lists its epochs in the order of its positions.

KML 2.2 (OGC 07-147r2): a Document with a Folder per object; Placemarks with LineString / Point /
Polygon, ``altitudeMode`` absolute, coordinates ``lon,lat,height``; a TimeSpan per track.
KML's absolute altitude is above mean sea level, ours is above the ellipsoid: the two differ by
the geoid undulation (-106..+85 m; not applied here, said in the Document's description).
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np

from sitl.app.export.tracks import CHI2_2DOF_95_SQRT, GPS_EPOCH_UNIX_S, Tracks, object_arrays
from sitl.constants import GPS_UTC_LEAP_S
from sitl.geodesy import ecef_to_geodetic, enu_rotation

GEOJSON_SCHEMA = "skyfuse.export.geojson/1"
KML_NS = "http://www.opengis.net/kml/2.2"
ELLIPSE_POINTS = 48  # vertices of an ellipse ring (plus the closing one)


def _utc_text(t_gps_s: float) -> str:
    from datetime import datetime, timezone

    return datetime.fromtimestamp(t_gps_s + GPS_EPOCH_UNIX_S - GPS_UTC_LEAP_S, tz=timezone.utc) \
        .isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _pos(lon: float, lat: float, h: float) -> list:
    return [round(float(lon), 8), round(float(lat), 8), round(float(h), 3)]


def _split_antimeridian(lon: np.ndarray) -> list:
    """Index ranges [i, j) of a track cut where consecutive longitudes jump by more than 180 deg."""
    cuts = np.flatnonzero(np.abs(np.diff(lon)) > 180.0) + 1
    bounds = [0, *cuts.tolist(), len(lon)]
    return [(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


def _track_geometry(t: np.ndarray, lat: np.ndarray, lon: np.ndarray, h: np.ndarray):
    ok = np.isfinite(lat) & np.isfinite(lon) & np.isfinite(h)
    t, lat, lon, h = t[ok], lat[ok], lon[ok], h[ok]
    if len(t) == 0:
        return None, t
    if len(t) == 1:
        return {"type": "Point", "coordinates": _pos(lon[0], lat[0], h[0])}, t
    parts = [(a, b) for a, b in _split_antimeridian(lon) if b - a >= 2]  # a lone point between two crossings
    lines = [[_pos(lon[i], lat[i], h[i]) for i in range(a, b)] for a, b in parts]  # is dropped
    kept = np.concatenate([t[a:b] for a, b in parts]) if parts else t[:0]
    if not lines:
        return None, kept
    if len(lines) == 1:
        return {"type": "LineString", "coordinates": lines[0]}, kept
    return {"type": "MultiLineString", "coordinates": lines}, kept


def ellipse_ring(pos_ecef_m: np.ndarray, cov_pos: np.ndarray, k: float = CHI2_2DOF_95_SQRT,
                 n: int = ELLIPSE_POINTS) -> list:
    """The horizontal uncertainty ellipse of a position estimate (k sigma; default 95 %) as a
    closed counterclockwise ring of [lon, lat, h] (east-north plane at the estimate)."""
    lat, lon, h = (float(v) for v in ecef_to_geodetic(pos_ecef_m))
    r = enu_rotation(lat, lon)
    p_en = (r @ cov_pos @ r.T)[:2, :2]
    w, v = np.linalg.eigh(p_en)
    if np.linalg.det(v) < 0:  # a reflection would run the ring clockwise
        v = v * np.array([1.0, -1.0])
    a = np.linspace(0.0, 2 * math.pi, n, endpoint=False)  # increasing angle: counterclockwise in E-N
    circle = np.stack([np.cos(a), np.sin(a)], axis=1)
    en = k * circle @ (v * np.sqrt(np.clip(w, 0.0, None))).T  # (n, 2): v diag(sqrt w) c
    enu = np.concatenate([en, np.zeros((n, 1))], axis=1)
    ecef = pos_ecef_m + enu @ r  # R^T enu
    la, lo, hh = ecef_to_geodetic(ecef)
    ring = [_pos(x, y, z) for x, y, z in zip(np.degrees(lo), np.degrees(la), hh)]
    ring.append(list(ring[0]))
    return ring


def _shapes(tracks: Tracks) -> list:
    """Every drawable thing once, for both formats: dicts with geometry and properties."""
    out = []
    for o in tracks.sorted_objects():
        cols = object_arrays(o)
        t = cols["t_gps_s"]
        base = {"run_id": o.run_id, "kind": o.kind, "object_id": o.object_id}
        for side, label in (("truth", "truth"), ("est", "estimate")):
            geom, ts = _track_geometry(t, cols[f"{side}_lat_deg"], cols[f"{side}_lon_deg"], cols[f"{side}_h_m"])
            if geom is None:
                continue
            props = {**base, "feature": "track", "track": label,
                     "estimator": o.estimator if label == "estimate" else None,
                     "epochs": int(len(ts)), "t_start_gps_s": float(ts[0]), "t_end_gps_s": float(ts[-1]),
                     "t_start_utc": _utc_text(float(ts[0])), "t_end_utc": _utc_text(float(ts[-1])),
                     "t_gps_s": [float(x) for x in ts]}
            if label == "estimate":
                e = cols["err_3d_m"][np.isfinite(cols["err_3d_m"])]
                props["rmse_3d_m"] = float(np.sqrt(np.mean(e * e))) if e.size else None
                props["scored_epochs"] = int(e.size)
            out.append({"geometry": geom, "properties": props})
        if o.estimate.cov:
            t_last = max(o.estimate.cov)
            p = np.asarray(o.estimate.pos[t_last])
            c = np.asarray(o.estimate.cov[t_last])
            lat, lon, h = (float(v) for v in ecef_to_geodetic(p))
            props = {**base, "estimator": o.estimator, "t_gps_s": float(t_last), "t_utc": _utc_text(float(t_last))}
            out.append({"geometry": {"type": "Point", "coordinates": _pos(math.degrees(lon), math.degrees(lat), h)},
                        "properties": {**props, "feature": "last_estimate"}})
            if np.isfinite(c[:3, :3]).all():
                out.append({"geometry": {"type": "Polygon", "coordinates": [ellipse_ring(p, c[:3, :3])]},
                            "properties": {**props, "feature": "uncertainty_ellipse", "confidence": 0.95}})
    for (run_id, site, sid), p in sorted(tracks.sites.items()):
        lat, lon, h = (float(v) for v in ecef_to_geodetic(np.asarray(p)))
        out.append({"geometry": {"type": "Point", "coordinates": _pos(math.degrees(lon), math.degrees(lat), h)},
                    "properties": {"run_id": run_id, "kind": site, "object_id": sid, "feature": "site"}})
    return out


def _bbox(shapes: list) -> list | None:
    pts = []

    def walk(c):
        if isinstance(c[0], (int, float)):
            pts.append(c)
        else:
            for x in c:
                walk(x)
    for s in shapes:
        walk(s["geometry"]["coordinates"])
    if not pts:
        return None
    a = np.array(pts, dtype=float)
    lo, hi = a.min(axis=0), a.max(axis=0)
    return [*(round(float(x), 8) for x in lo), *(round(float(x), 8) for x in hi)]


def geojson(tracks: Tracks) -> dict:
    """The tracks as an RFC 7946 FeatureCollection (a dict ready for json.dump)."""
    from sitl.app.export import export_provenance, skyfuse_version

    shapes = _shapes(tracks)
    doc = {"type": "FeatureCollection",
           "features": [{"type": "Feature", "geometry": s["geometry"], "properties": s["properties"]}
                        for s in shapes]}
    bb = _bbox(shapes)
    if bb is not None and bb[0] <= bb[3]:  # (a bbox across the antimeridian would need west > east)
        doc["bbox"] = bb
    # a foreign member (RFC 7946 sec. 6.1): what made the file
    doc["skyfuse"] = {"schema": GEOJSON_SCHEMA, "skyfuse_version": skyfuse_version(), "source": tracks.source,
                      "heights": "metres above the WGS-84 ellipsoid",
                      "ellipses": "95 % horizontal uncertainty of the last estimate",
                      "provenance": export_provenance(tracks.source)}
    return doc


def _atomic_write(path: Path, text: str) -> Path:
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)
    return path


def write_geojson(tracks: Tracks, path: str | os.PathLike) -> Path:
    return _atomic_write(Path(path), json.dumps(geojson(tracks), allow_nan=False, separators=(",", ":")))


# ------------------------------------------------------------------------------------- KML

# KML colours are aabbggrr
_STYLES = {
    "truth": ("ff00c000", 2.0),  # green
    "estimate": ("ff0050ff", 2.0),  # orange-red
    "ellipse": ("ff0050ff", 1.5),
}
_KIND_ICON = {"uav": "ffff8000", "beacon": "ff0000ff", "sonde": "ffff00ff", "radar": "ff00ffff",
              "ground_receiver": "ff00ffff"}


def _coords(c) -> str:
    return " ".join(f"{x[0]:.8f},{x[1]:.8f},{x[2]:.3f}" for x in c)


def _geometry_kml(g: dict) -> str:
    am = "<altitudeMode>absolute</altitudeMode>"
    if g["type"] == "Point":
        return f"<Point>{am}<coordinates>{_coords([g['coordinates']])}</coordinates></Point>"
    if g["type"] == "LineString":
        return f"<LineString><tessellate>0</tessellate>{am}<coordinates>{_coords(g['coordinates'])}</coordinates></LineString>"
    if g["type"] == "MultiLineString":
        return "<MultiGeometry>" + "".join(_geometry_kml({"type": "LineString", "coordinates": c})
                                           for c in g["coordinates"]) + "</MultiGeometry>"
    if g["type"] == "Polygon":
        return (f"<Polygon>{am}<outerBoundaryIs><LinearRing><coordinates>{_coords(g['coordinates'][0])}"
                "</coordinates></LinearRing></outerBoundaryIs></Polygon>")
    raise ValueError(f"no KML for {g['type']}")


def _extended(props: dict) -> str:
    rows = "".join(f'<Data name="{escape(k)}"><value>{escape(str(v))}</value></Data>'
                   for k, v in props.items() if v is not None and k != "t_gps_s")
    return f"<ExtendedData>{rows}</ExtendedData>"


def kml(tracks: Tracks) -> str:
    """The tracks as a KML 2.2 document (text)."""
    from sitl.app.export import export_provenance, skyfuse_version

    shapes = _shapes(tracks)
    styles = []
    for name, (color, width) in _STYLES.items():
        poly = "<PolyStyle><fill>0</fill><outline>1</outline></PolyStyle>" if name == "ellipse" else ""
        styles.append(f'<Style id="{name}"><LineStyle><color>{color}</color><width>{width}</width></LineStyle>'
                      f"{poly}</Style>")
    for kind, color in _KIND_ICON.items():
        styles.append(f'<Style id="point_{kind}"><IconStyle><color>{color}</color><scale>0.8</scale>'
                      "<Icon><href>http://maps.google.com/mapfiles/kml/shapes/placemark_circle.png</href></Icon>"
                      "</IconStyle></Style>")
    folders: dict = {}
    for s in shapes:
        p = s["properties"]
        folder = f"{p['kind']} {p['object_id']}" + (f" ({p['run_id']})" if len({o.run_id for o in tracks.objects.values()}) > 1 else "")
        feat = p["feature"]
        if feat == "track":
            name, style = f"{p['kind']} {p['object_id']} {p['track']}", p["track"]
            when = f"<TimeSpan><begin>{p['t_start_utc']}</begin><end>{p['t_end_utc']}</end></TimeSpan>"
        elif feat == "last_estimate":
            name, style = f"{p['kind']} {p['object_id']} last estimate", f"point_{p['kind']}"
            when = f"<TimeStamp><when>{p['t_utc']}</when></TimeStamp>"
        elif feat == "uncertainty_ellipse":
            name, style = f"{p['kind']} {p['object_id']} 95 % ellipse", "ellipse"
            when = f"<TimeStamp><when>{p['t_utc']}</when></TimeStamp>"
        else:
            name, style, when = f"{p['kind']} {p['object_id']}", f"point_{p['kind']}", ""
        pm = (f"<Placemark><name>{escape(name)}</name>{when}<styleUrl>#{style}</styleUrl>{_extended(p)}"
              f"{_geometry_kml(s['geometry'])}</Placemark>")
        folders.setdefault("sites" if feat == "site" else folder, []).append(pm)
    body = "".join(f"<Folder><name>{escape(name)}</name>{''.join(pms)}</Folder>" for name, pms in folders.items())
    desc = (f"skyfuse {skyfuse_version()} export of {tracks.source}: true and estimated tracks, last estimates "
            "with their 95 % horizontal uncertainty ellipse, fixed sites. Heights are above the WGS-84 "
            "ellipsoid (KML's absolute altitude is above mean sea level: the geoid undulation is not applied).")
    prov = export_provenance(tracks.source)
    run = prov["run"] or {}
    desc += (f" Exported {prov['export']['started_utc']} by {' '.join(prov['export']['command_line'])!s}"
             f" (commit {prov['export'].get('git_commit') or 'none'}); run seed {run.get('seed')}, scenario "
             f"SHA-256 {run.get('scenario_sha256')}.")
    return (f'<?xml version="1.0" encoding="UTF-8"?>\n<kml xmlns="{KML_NS}"><Document>'
            f"<name>{escape(Path(tracks.source).parent.name or 'skyfuse run')} tracks</name>"
            f"<description>{escape(desc)}</description>{''.join(styles)}{body}</Document></kml>\n")


def write_kml(tracks: Tracks, path: str | os.PathLike) -> Path:
    return _atomic_write(Path(path), kml(tracks))
