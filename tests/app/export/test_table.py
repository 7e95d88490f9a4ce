"""`skyfuse export table`: the Parquet table reads back in pyarrow with the declared columns and
units, one row per object and epoch, and its values are the closed-form ones of the synthetic
log (tests/app/export/conftest.py); CSV comes with its CSVW metadata."""
from __future__ import annotations

import csv
import json
import math
from datetime import datetime, timedelta, timezone

import numpy as np
import pyarrow.parquet as pq
import pytest
from pymap3d import ecef2geodetic

from sitl.app.cli import main
from sitl.app.export.tracks import COLUMNS

from .conftest import EPOCHS, ERR_ENU_M, NIS, SIGMA_ENU_M, T0, VEL_ERR_M_S, beacon_llh, uav_lon

# the unit a column's name ends with (the house rule) -> the unit its metadata must declare
SUFFIX_UNITS = [("_m2_s2", "m2/s2"), ("_m2_s", "m2/s"), ("_m2", "m2"), ("_m_s", "m/s"), ("_deg", "deg"),
                ("_m", "m"), ("_s", "s")]


def _read(synthetic_run, capsys, *extra):
    out = synthetic_run.path.parent / "t.parquet"
    assert main(["export", "table", str(synthetic_run.path.parent), "-o", str(out), *extra]) == 0
    return pq.read_table(out), capsys.readouterr()


def test_parquet_has_the_declared_columns_and_units(synthetic_run, capsys):
    t, _ = _read(synthetic_run, capsys)
    assert t.column_names == [c.name for c in COLUMNS]
    for f in t.schema:
        md = {k.decode(): v.decode() for k, v in f.metadata.items()}
        assert md["description"], f.name
        unit = next((u for s, u in SUFFIX_UNITS if f.name.endswith(s)), None)
        if unit is not None:
            assert md["unit"] == unit, f.name
    meta = {k.decode(): v.decode() for k, v in t.schema.metadata.items()}
    assert meta["schema"] == "skyfuse.export.tracks/1"
    assert json.loads(meta["run_ids"]) == ["r1"]
    assert int(meta["records"]) == synthetic_run.records and int(meta["undecodable"]) == 1


def test_one_row_per_object_and_epoch(synthetic_run, capsys):
    t, _ = _read(synthetic_run, capsys)
    rows = t.select(["kind", "object_id", "t_gps_s"]).to_pylist()
    keys = [(r["kind"], r["object_id"], r["t_gps_s"]) for r in rows]
    assert len(keys) == len(set(keys))
    want = ({("beacon", "b1", T0 + k) for k in range(EPOCHS)} | {("uav", "7", T0 + k) for k in range(EPOCHS)}
            | {("sonde", "s0001", T0 + 2)})
    assert set(keys) == want


def test_values_are_the_closed_form_ones(synthetic_run, capsys):
    t, _ = _read(synthetic_run, capsys)
    b = [r for r in t.to_pylist() if r["kind"] == "beacon"]
    first, rest = b[0], b[1:]
    # no estimate at the first epoch: the estimate's side is null, not NaN or 0
    assert first["truth_lat_deg"] is not None and first["est_pos_ecef_x_m"] is None and first["err_3d_m"] is None
    assert first["estimator"] is None and first["cov_px_px_m2"] is None
    sx, sy, su = SIGMA_ENU_M
    for r in rest:
        k = round(r["t_gps_s"] - T0)
        lat, lon, h = beacon_llh(k)
        assert r["truth_lat_deg"] == pytest.approx(lat, abs=1e-9)
        assert r["truth_lon_deg"] == pytest.approx(lon, abs=1e-9)
        assert r["truth_h_m"] == pytest.approx(h, abs=1e-6)
        # the estimate's geodetic position from pymap3d, an independent implementation
        elat, elon, eh = ecef2geodetic(r["est_pos_ecef_x_m"], r["est_pos_ecef_y_m"], r["est_pos_ecef_z_m"])
        assert (r["est_lat_deg"], r["est_lon_deg"], r["est_h_m"]) == pytest.approx((elat, elon, eh), abs=1e-6)
        assert (r["err_e_m"], r["err_n_m"], r["err_u_m"]) == pytest.approx(tuple(ERR_ENU_M), abs=1e-6)
        assert r["err_horiz_m"] == pytest.approx(5.0, abs=1e-6)
        assert r["err_3d_m"] == pytest.approx(5.0, abs=1e-6)
        assert r["err_vel_3d_m_s"] == pytest.approx(float(np.linalg.norm(VEL_ERR_M_S)), abs=1e-12)
        assert (r["sigma_e_m"], r["sigma_n_m"], r["sigma_u_m"]) == pytest.approx((sx, sy, su), abs=1e-6)
        # 95 % ellipse: sqrt(chi2_2(0.95)) = sqrt(-2 ln 0.05) sigmas; major axis along east
        k95 = math.sqrt(-2 * math.log(0.05))
        assert r["ellipse95_semi_major_m"] == pytest.approx(k95 * sx, rel=1e-9)
        assert r["ellipse95_semi_minor_m"] == pytest.approx(k95 * sy, rel=1e-9)
        assert r["ellipse95_azimuth_deg"] == pytest.approx(90.0, abs=1e-6)
        nees_pos = (ERR_ENU_M[0] / sx) ** 2 + (ERR_ENU_M[1] / sy) ** 2
        assert r["nees_pos"] == pytest.approx(nees_pos, rel=1e-6)
        assert r["nees"] == pytest.approx(nees_pos + float(VEL_ERR_M_S @ VEL_ERR_M_S), rel=1e-6)
        assert r["cov_vx_vx_m2_s2"] == 1.0 and r["cov_px_vx_m2_s"] == 0.0
        assert r["est_nis"] == NIS and r["est_mode"] == "fused" and r["estimator"] == "ground_station"
        assert r["est_t_recv_s"] == r["t_gps_s"] + 0.25
        utc = datetime(1980, 1, 6, tzinfo=timezone.utc) + timedelta(seconds=r["t_gps_s"] - 18)
        assert r["t_utc"] == utc


def test_uav_rows_hold_the_onboard_navigation(synthetic_run, capsys):
    t, _ = _read(synthetic_run, capsys)
    u = [r for r in t.to_pylist() if r["kind"] == "uav"]
    assert [r["estimator"] for r in u] == ["onboard_nav"] * EPOCHS
    assert [r["err_3d_m"] for r in u] == pytest.approx([1.0] * EPOCHS, abs=1e-9)  # +1 m ECEF x
    assert [r["truth_lon_deg"] for r in u] == pytest.approx([uav_lon(k) for k in range(EPOCHS)], abs=1e-9)
    assert all(r["est_mode"] is None and r["est_nis"] is None for r in u)


def test_csv_on_request_with_its_csvw_metadata(synthetic_run, capsys):
    out = synthetic_run.path.parent / "t.csv"
    assert main(["export", "table", str(synthetic_run.path), "--format", "csv", "-o", str(out)]) == 0
    with open(out, newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == [c.name for c in COLUMNS]
    assert len(rows) == 2 * EPOCHS + 1
    meta = json.loads((out.parent / "t.csv-metadata.json").read_text())
    assert meta["@context"] == "http://www.w3.org/ns/csvw" and meta["url"] == "t.csv"
    cols = {c["name"]: c for c in meta["tableSchema"]["columns"]}
    assert cols["err_3d_m"]["unit"] == "m" and cols["t_gps_s"]["datatype"] == "double"
    beacon = [r for r in rows if r["kind"] == "beacon" and r["err_3d_m"]]
    assert [float(r["err_3d_m"]) for r in beacon] == pytest.approx([5.0] * (EPOCHS - 1), abs=1e-6)


@pytest.mark.slow
def test_table_matches_the_batch_runs_own_scores(tmp_path, capsys):
    """A short batch run of the default scenario recorded to a bus log (as a live run records
    it), then `skyfuse export all`: the table's errors, squared and averaged, are the RMSE the
    run's scorer (sitl.app.scoring, the live and batch runs' own) reported, epoch for epoch."""
    pytest.importorskip("numba")
    from sitl.app.batch import run_batch
    from sitl.scenario import default_scenario

    out = tmp_path / "batch"
    out.mkdir()
    scn = default_scenario().replace(run={"duration_s": 8.0})
    res = run_batch(scn, record=out / "bus.log")
    assert main(["export", "all", str(out)]) == 0
    t = pq.read_table(out / "tracks.parquet").to_pylist()
    for name, e in res["errors"].items():
        kind, oid = name.split("/")
        err = [r["err_3d_m"] for r in t if r["kind"] == kind and r["object_id"] == oid and r["err_3d_m"] is not None]
        assert len(err) == e["scored"]
        assert math.sqrt(sum(x * x for x in err) / len(err)) == pytest.approx(e["rmse_m"], rel=1e-12)
    assert {r["object_id"] for r in t if r["kind"] == "uav"} == {str(i + 1) for i in range(scn.uavs.count)}
    # the same run's MCAP: every key of the log a channel with the log's count
    from collections import Counter

    from mcap.reader import make_reader

    from sitl.bus.buslog import read_bus_log

    want = Counter(k for k, _ in read_bus_log(out / "bus.log"))
    from .test_mcap import conforms

    got: Counter = Counter()
    with open(out / "bus.mcap", "rb") as f:
        for sch, c, m in make_reader(f).iter_messages():
            got[c.topic] += 1
            assert conforms(json.loads(m.data), json.loads(sch.data)), c.topic
    assert got == want and sum(want.values()) == res["recorded"]
    from .test_geo import check_rfc7946

    check_rfc7946(json.loads((out / "tracks.geojson").read_text()))
    import xml.etree.ElementTree as ET

    assert ET.parse(out / "tracks.kml").getroot().tag == "{http://www.opengis.net/kml/2.2}kml"



@pytest.mark.slow
def test_a_demo_batch_run_is_exported_from_its_report(tmp_path, capsys):
    """`skyfuse demo --batch` records its bus log as a live run does: export reads it, and the
    table's RMSE is the report's. An older OUT without a bus log is run again from report.json's
    scenario (deterministic for its seed) with a recorder: the same table."""
    pytest.importorskip("numba")
    out = tmp_path / "b"
    assert main(["demo", "--batch", "--duration", "6", "--out", str(out), "--quiet"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert (out / "bus.log").is_file()
    capsys.readouterr()

    def rmse_match(parquet):
        t = pq.read_table(parquet).to_pylist()
        for name, e in report["errors"].items():
            kind, oid = name.split("/")
            err_m = [r["err_3d_m"] for r in t if r["kind"] == kind and r["object_id"] == oid and r["err_3d_m"] is not None]
            assert len(err_m) == e["scored"] > 0
            assert math.sqrt(sum(x * x for x in err_m) / len(err_m)) == pytest.approx(e["rmse_m"], rel=1e-9)
    assert main(["export", "table", str(out), "-o", str(tmp_path / "a.parquet")]) == 0
    assert "running it again" not in capsys.readouterr().err
    rmse_match(tmp_path / "a.parquet")
    (out / "bus.log").unlink()
    assert main(["export", "table", str(out), "-o", str(tmp_path / "b.parquet")]) == 0
    err = capsys.readouterr().err
    assert "running it again" in err and "differ" not in err and len(err.strip().splitlines()) == 1
    rmse_match(tmp_path / "b.parquet")
    assert (out / "bus.log").is_file() and not (out / "bus.log.part").exists()


def test_every_export_carries_the_provenance_record(synthetic_run, capsys):
    """The table's metadata, the GeoJSON's foreign member, the KML's description and the MCAP's
    metadata hold the export's provenance record (version, command line, start time, schema) and
    the run's own record from the report.json beside the log."""
    import json
    import xml.etree.ElementTree as ET

    import pyarrow.parquet as pq
    from mcap.reader import make_reader

    from sitl.app.cli import main
    from sitl.app.provenance import SCHEMA

    out = synthetic_run.path.parent
    run_record = {"seed": 17, "scenario_sha256": "ab" * 32, "command_line": ["skyfuse", "demo"]}
    (out / "report.json").write_text(json.dumps({"provenance": run_record}))
    assert main(["export", "all", str(out)]) == 0
    capsys.readouterr()

    def check(doc):
        assert doc["schema"] == SCHEMA and doc["run"] == run_record
        e = doc["export"]
        assert e["command_line"] and e["started_utc"].endswith(("Z", "+00:00")) and "skyfuse_version" in e
    meta = pq.read_schema(out / "tracks.parquet").metadata
    check(json.loads(meta[b"provenance"]))
    check(json.loads((out / "tracks.geojson").read_text())["skyfuse"]["provenance"])
    with open(out / "bus.mcap", "rb") as f:
        md = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    check(json.loads(md["skyfuse"]["provenance"]))
    ns = {"k": "http://www.opengis.net/kml/2.2"}
    desc = ET.parse(out / "tracks.kml").getroot().find("k:Document/k:description", ns).text
    assert "seed 17" in desc and "ab" * 32 in desc and "Exported " in desc
