"""`skyfuse export`: a run's data in the formats other tools read.

- ``table``: per object and epoch, truth, estimate, covariance and error as Parquet (pyarrow;
  pandas, polars, DuckDB, R read it) or CSV with its W3C CSVW metadata file
  (`sitl.app.export.tracks`);
- ``geojson`` / ``kml``: the tracks for a map (RFC 7946 GeoJSON; KML 2.2 for Google Earth and
  QGroundControl) (`sitl.app.export.geo`);
- ``mcap``: the bus log as MCAP, one channel per bus key, a JSON schema per message type, for
  Foxglove and the ``mcap`` CLI (`sitl.app.export.to_mcap`);
- ``all``: the four beside the run's bus log.

The source is a run's bus log (`sitl.app.export.source`). pyarrow and mcap are the optional
extra ``skyfuse[export]``.
"""
from __future__ import annotations


def skyfuse_version() -> str:
    """The installed skyfuse's version ("unknown" when it is not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("skyfuse")
    except PackageNotFoundError:
        return "unknown"


def export_provenance(source) -> dict:
    """What made an exported file: the export command's provenance record (sitl.app.provenance:
    version, commit, command line, start time, schema) and, when the run's report.json lies beside
    its bus log, the run's own record (``run``: seed, scenario hash, the run's command line)."""
    import json
    from pathlib import Path

    from sitl.app.provenance import SCHEMA, provenance

    doc = {"schema": SCHEMA, "export": provenance(), "run": None}
    rep = Path(source).parent / "report.json"
    try:
        doc["run"] = json.loads(rep.read_text()).get("provenance")
    except (OSError, ValueError, AttributeError):
        pass
    return doc
