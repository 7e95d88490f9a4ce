"""`skyfuse export geojson` / `kml`: the GeoJSON meets the rules of RFC 7946 checked here (no
JSON Schema validator is installed: the checks are written out), positions in lon, lat, h
order with the synthetic log's closed-form values; the KML parses with xml.etree and holds the
expected placemarks, every geometry at absolute altitude, and validates against the OGC KML 2.2
XML Schema (tests/data/kml, a copy of schemas.opengis.net's) with lxml (libxml2's validator)."""
from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pymap3d
import pytest

from sitl.app.cli import main

from .conftest import BEACON_LLH, EPOCHS, RADAR_LLH, SIGMA_ENU_M, T0, beacon_llh, uav_lon

GEOMETRY_TYPES = {"Point", "MultiPoint", "LineString", "MultiLineString", "Polygon", "MultiPolygon",
                  "GeometryCollection"}


def _position(p) -> None:
    assert isinstance(p, list) and len(p) in (2, 3), p  # RFC 7946 3.1.1: 2 or 3 numbers (4+ SHOULD NOT)
    assert all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in p), p
    assert -180.0 <= p[0] <= 180.0 and -90.0 <= p[1] <= 90.0, p  # longitude first, then latitude (3.1.1, 4)


def _ring_area(ring) -> float:
    """Shoelace area in lon/lat: > 0 counterclockwise."""
    return 0.5 * sum(a[0] * b[1] - b[0] * a[1] for a, b in zip(ring[:-1], ring[1:]))


def check_geometry(g) -> None:
    assert isinstance(g, dict) and g.get("type") in GEOMETRY_TYPES, g
    t = g["type"]
    if t == "GeometryCollection":
        assert "coordinates" not in g and isinstance(g["geometries"], list)
        for x in g["geometries"]:
            check_geometry(x)
        return
    c = g["coordinates"]
    if t == "Point":
        _position(c)
    elif t in ("MultiPoint", "LineString"):
        assert isinstance(c, list) and (t == "MultiPoint" or len(c) >= 2)  # 3.1.4: two or more positions
        for p in c:
            _position(p)
    elif t == "MultiLineString":
        for line in c:
            check_geometry({"type": "LineString", "coordinates": line})
    elif t == "Polygon":
        for i, ring in enumerate(c):  # 3.1.6: closed linear rings of >= 4 positions, exterior counterclockwise
            assert len(ring) >= 4 and ring[0] == ring[-1]
            for p in ring:
                _position(p)
            area = _ring_area(ring)
            assert (area > 0) if i == 0 else (area < 0)
    else:
        for poly in c:
            check_geometry({"type": "Polygon", "coordinates": poly})


def check_rfc7946(doc) -> None:
    assert doc["type"] == "FeatureCollection" and isinstance(doc["features"], list)
    assert "crs" not in doc  # 4: no crs member
    for f in doc["features"]:
        assert f["type"] == "Feature" and "geometry" in f and "properties" in f
        assert f["properties"] is None or isinstance(f["properties"], dict)
        if f["geometry"] is not None:
            check_geometry(f["geometry"])
    if "bbox" in doc:  # 5: 2n numbers, south-west then north-east
        bb = doc["bbox"]
        assert len(bb) in (4, 6)
        n = len(bb) // 2
        assert bb[1] <= bb[n + 1] and -90 <= bb[1] and bb[n + 1] <= 90


@pytest.fixture
def geojson_doc(synthetic_run, capsys):
    out = synthetic_run.path.parent / "tracks.geojson"
    assert main(["export", "geojson", str(synthetic_run.path.parent)]) == 0
    capsys.readouterr()
    text = out.read_text()
    return json.loads(text, parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))


def _feature(doc, **props):
    hits = [f for f in doc["features"] if all(f["properties"].get(k) == v for k, v in props.items())]
    assert len(hits) == 1, (props, len(hits))
    return hits[0]


def test_geojson_meets_rfc7946(geojson_doc):
    check_rfc7946(geojson_doc)


def test_geojson_positions_are_lon_lat_height(geojson_doc):
    f = _feature(geojson_doc, kind="beacon", object_id="b1", feature="track", track="truth")
    assert f["geometry"]["type"] == "LineString"
    coords = f["geometry"]["coordinates"]
    assert len(coords) == EPOCHS == len(f["properties"]["t_gps_s"])
    for k, p in enumerate(coords):
        lat, lon, h = beacon_llh(k)
        assert p == pytest.approx([lon, lat, h], abs=1e-6)
    assert f["properties"]["t_gps_s"] == [T0 + k for k in range(EPOCHS)]
    est = _feature(geojson_doc, kind="beacon", object_id="b1", feature="track", track="estimate")
    assert est["properties"]["epochs"] == EPOCHS - 1 and est["properties"]["rmse_3d_m"] == pytest.approx(5.0)
    radar = _feature(geojson_doc, kind="radar", object_id="arls1", feature="site")
    assert radar["geometry"]["coordinates"] == pytest.approx([RADAR_LLH[1], RADAR_LLH[0], RADAR_LLH[2]], abs=1e-6)
    # a single epoch is a Point (a LineString needs two positions)
    sonde = _feature(geojson_doc, kind="sonde", object_id="s0001", feature="track", track="truth")
    assert sonde["geometry"]["type"] == "Point"


def test_geojson_cuts_a_track_at_the_antimeridian(geojson_doc):
    f = _feature(geojson_doc, kind="uav", object_id="7", feature="track", track="truth")
    assert f["geometry"]["type"] == "MultiLineString"
    parts = f["geometry"]["coordinates"]
    assert [len(p) for p in parts] == [3, 2]
    assert all(p[0] > 179 for p in parts[0]) and all(p[0] < -179 for p in parts[1])
    flat = [p[0] for part in parts for p in part]
    assert flat == pytest.approx([uav_lon(k) for k in range(EPOCHS)], abs=1e-8)


def test_geojson_ellipse_is_the_95_percent_ellipse(geojson_doc):
    f = _feature(geojson_doc, kind="beacon", object_id="b1", feature="uncertainty_ellipse")
    ring = f["geometry"]["coordinates"][0]
    centre = _feature(geojson_doc, kind="beacon", object_id="b1", feature="last_estimate")["geometry"]["coordinates"]
    e, n, _ = pymap3d.geodetic2enu(np.array([p[1] for p in ring]), np.array([p[0] for p in ring]),
                                   np.array([p[2] for p in ring]), centre[1], centre[0], centre[2])
    r = np.hypot(e, n)
    k95 = math.sqrt(-2 * math.log(0.05))
    assert r.max() == pytest.approx(k95 * SIGMA_ENU_M[0], rel=1e-3)  # semi-major along east
    assert r.min() == pytest.approx(k95 * SIGMA_ENU_M[1], rel=1e-2)
    assert abs(e[np.argmax(r)]) == pytest.approx(r.max(), rel=1e-6)
    assert f["properties"]["confidence"] == 0.95


KML = "{http://www.opengis.net/kml/2.2}"


def test_kml_parses_and_holds_the_expected_placemarks(synthetic_run, capsys):
    out = synthetic_run.path.parent / "t.kml"
    assert main(["export", "kml", str(synthetic_run.path), "-o", str(out)]) == 0
    root = ET.parse(out).getroot()
    assert root.tag == f"{KML}kml"
    doc = root.find(f"{KML}Document")
    names = {pm.findtext(f"{KML}name") for pm in doc.iter(f"{KML}Placemark")}
    # (the synthetic log has no sonde relay, so no ground receiver; the sonde has no estimate)
    assert names == {"beacon b1 truth", "beacon b1 estimate", "beacon b1 last estimate", "beacon b1 95 % ellipse",
                     "uav 7 truth", "uav 7 estimate", "uav 7 last estimate", "uav 7 95 % ellipse",
                     "sonde s0001 truth", "radar arls1"}
    folders = {f.findtext(f"{KML}name") for f in doc.findall(f"{KML}Folder")}
    assert folders == {"beacon b1", "uav 7", "sonde s0001", "sites"}
    geoms = [g for tag in ("Point", "LineString", "Polygon") for g in doc.iter(f"{KML}{tag}")]
    assert geoms and all(g.findtext(f"{KML}altitudeMode") == "absolute" for g in geoms)
    truth = next(pm for pm in doc.iter(f"{KML}Placemark") if pm.findtext(f"{KML}name") == "beacon b1 truth")
    coords = [tuple(map(float, c.split(","))) for c in truth.find(f".//{KML}coordinates").text.split()]
    want = [(BEACON_LLH[1], BEACON_LLH[0], BEACON_LLH[2] + 10 * k) for k in range(EPOCHS)]
    np.testing.assert_allclose(np.array(coords), np.array(want), rtol=0, atol=1e-6)
    span = truth.find(f"{KML}TimeSpan")
    assert span.findtext(f"{KML}begin") == "2025-01-01T00:59:42.000Z"
    ring = next(pm for pm in doc.iter(f"{KML}Placemark") if pm.findtext(f"{KML}name") == "beacon b1 95 % ellipse")
    pts = ring.find(f".//{KML}outerBoundaryIs/{KML}LinearRing/{KML}coordinates").text.split()
    assert pts[0] == pts[-1] and len(pts) >= 4


KML_XSD = Path(__file__).resolve().parents[2] / "data" / "kml" / "ogckml22.xsd"


def test_kml_validates_against_the_ogc_kml_2_2_schema(synthetic_run, capsys):
    etree = pytest.importorskip("lxml.etree", reason="lxml (the XML Schema validator) is not installed")
    schema = etree.XMLSchema(etree.parse(str(KML_XSD)))  # imports atom-author-link.xsd and xAL.xsd beside it
    out = synthetic_run.path.parent / "t.kml"
    assert main(["export", "kml", str(synthetic_run.path), "-o", str(out)]) == 0
    doc = etree.parse(str(out))
    assert schema.validate(doc), "\n".join(str(e) for e in schema.error_log)
    # the validator does reject what KML 2.2 forbids: an altitudeMode outside its enumeration, and
    # a Placemark's name after its geometry (kml:FeatureType's sequence puts name first)
    bad = etree.parse(str(out))
    bad.find(f".//{KML}altitudeMode").text = "aboveEllipsoid"
    assert not schema.validate(bad)
    bad = etree.parse(str(out))
    pm = bad.find(f".//{KML}Placemark")
    name = pm.find(f"{KML}name")
    pm.remove(name)
    pm.append(name)
    assert not schema.validate(bad)
