"""The `export` command group: ``add_parser(subparsers)`` registers it on the `skyfuse` parser
(``export_main`` runs the chosen subcommand).

    skyfuse export table   OUT|LOG [-o FILE] [--format parquet|csv]
    skyfuse export geojson OUT|LOG [-o FILE]
    skyfuse export kml     OUT|LOG [-o FILE]
    skyfuse export mcap    OUT|LOG [-o FILE]
    skyfuse export all     OUT|LOG [--format parquet|csv]

OUT is a run's output directory (its bus.log is read; a `demo --batch` run's, which keeps no bus
log, is run again from its report.json's scenario with a recorder, and checked against the
report's errors: `sitl.app.export.source.record_batch`), LOG a bus log. Without -o a file goes
beside the log (tracks.parquet / tracks.csv, tracks.geojson, tracks.kml, bus.mcap). Bad input
(no such file, not a bus log, a log without records) is one line on stderr, exit 2, before
anything is written; a torn tail is exported up to it and said once."""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from sitl.app.args import OUTPUT_FILE, Parser, UsageError, add_positional, options_of
from sitl.params import add_flags, choice, from_text, optional, param, validate

_SOURCE_DOC = "a run's output directory (OUT, holding bus.log) or a bus log"


def _source():
    return param(check=from_text(Path), cli=False, metavar="OUT|LOG", doc=_SOURCE_DOC)


def _output(default_name: str):
    return param(None, check=optional(OUTPUT_FILE), flag="-o", metavar="FILE", doc="output file",
                 default_help=f"default: {default_name} beside the bus log")


def _format():
    return param("parquet", check=choice("parquet", "csv"),
                 doc="the table's format: Parquet (units and descriptions in its schema) or CSV (with a CSVW "
                     "FILE-metadata.json holding them)")


@dataclass(frozen=True, kw_only=True)
class TableOptions:
    """`skyfuse export table`'s options."""

    source: Path = _source()
    output: Path | None = _output("tracks.parquet (tracks.csv)")
    format: str = _format()

    __post_init__ = validate


@dataclass(frozen=True, kw_only=True)
class GeojsonOptions:
    """`skyfuse export geojson`'s options."""

    source: Path = _source()
    output: Path | None = _output("tracks.geojson")

    __post_init__ = validate


@dataclass(frozen=True, kw_only=True)
class KmlOptions:
    """`skyfuse export kml`'s options."""

    source: Path = _source()
    output: Path | None = _output("tracks.kml")

    __post_init__ = validate


@dataclass(frozen=True, kw_only=True)
class McapOptions:
    """`skyfuse export mcap`'s options."""

    source: Path = _source()
    output: Path | None = _output("bus.mcap")

    __post_init__ = validate


@dataclass(frozen=True, kw_only=True)
class AllOptions:
    """`skyfuse export all`'s options."""

    source: Path = _source()
    format: str = _format()

    __post_init__ = validate


def _say(line: str) -> None:
    print(line, file=sys.stderr)


def _tracks(log: Path, what: str):
    from sitl.app.export.tracks import read_tracks

    tr = read_tracks(log, say=_say)
    if tr.records == 0:
        raise UsageError(f"{what}: {str(log)!r} holds no records"
                         + (f" ({tr.stats.reason})" if tr.stats.reason else ""))
    return tr


def _require(module: str, what: str) -> None:
    import importlib.util

    if importlib.util.find_spec(module) is None:
        raise UsageError(f"{what}: needs {module}: pip install 'skyfuse[export]'")


def _table(log: Path, out: Path | None, fmt: str, tr=None) -> Path:
    from sitl.app.export.tracks import track_table, write_table

    _require("pyarrow", "export table")
    tr = tr if tr is not None else _tracks(log, "export table")
    out = out if out is not None else log.parent / f"tracks.{fmt}"
    table = track_table(tr)
    write_table(table, out, fmt)
    objs = len(tr.objects)
    print(f"export table: {table.num_rows} rows ({objs} objects x epochs), {table.num_columns} columns -> {out}"
          + (f" (+ {out.name}-metadata.json)" if fmt == "csv" else ""))
    return out


def _geo(log: Path, out: Path | None, kind: str, tr=None) -> Path:
    from sitl.app.export import geo

    tr = tr if tr is not None else _tracks(log, f"export {kind}")
    out = out if out is not None else log.parent / f"tracks.{kind}"
    (geo.write_geojson if kind == "geojson" else geo.write_kml)(tr, out)
    print(f"export {kind}: {len(tr.objects)} objects' tracks, {len(tr.sites)} sites -> {out}")
    return out


def _mcap(log: Path, out: Path | None) -> Path:
    from sitl.app.export.to_mcap import export_mcap

    _require("mcap", "export mcap")
    out = out if out is not None else log.parent / "bus.mcap"
    res = export_mcap(log, out, say=_say)
    if res.records == 0:
        raise UsageError(f"export mcap: {str(log)!r} holds no records"
                         + (f" ({res.stats.reason})" if res.stats.reason else ""))
    print(f"export mcap: {res.records} records on {len(res.per_key)} channels (one per bus key)"
          + (f", {res.undecodable} undecodable on skyfuse/undecodable" if res.undecodable else "")
          + (f", {res.no_receive_time} without a receive time (log time = publish time)" if res.no_receive_time
             else "") + f" -> {out}")
    return out


def _run_table(args) -> int:
    from sitl.app.export.source import resolve_log

    o = options_of(TableOptions, args)
    _table(resolve_log(o.source, "export table"), o.output, o.format)
    return 0


def _run_geojson(args) -> int:
    from sitl.app.export.source import resolve_log

    o = options_of(GeojsonOptions, args)
    _geo(resolve_log(o.source, "export geojson"), o.output, "geojson")
    return 0


def _run_kml(args) -> int:
    from sitl.app.export.source import resolve_log

    o = options_of(KmlOptions, args)
    _geo(resolve_log(o.source, "export kml"), o.output, "kml")
    return 0


def _run_mcap(args) -> int:
    from sitl.app.export.source import resolve_log

    o = options_of(McapOptions, args)
    _mcap(resolve_log(o.source, "export mcap"), o.output)
    return 0


def _run_all(args) -> int:
    from sitl.app.export.source import resolve_log

    o = options_of(AllOptions, args)
    log = resolve_log(o.source, "export all")
    _require("pyarrow", "export all")
    _require("mcap", "export all")
    tr = _tracks(log, "export all")
    _table(log, None, o.format, tr)
    _geo(log, None, "geojson", tr)
    _geo(log, None, "kml", tr)
    _mcap(log, None)
    return 0


def _adder(cls):
    def add(p) -> None:
        add_positional(p, cls, "source")
        add_flags(p, cls)
    return add


# name -> (options, runner, one-line help)
SUBCOMMANDS = {
    "table": (TableOptions, _run_table, "per object and epoch: truth, estimate, covariance, error (Parquet or CSV)"),
    "geojson": (GeojsonOptions, _run_geojson, "the tracks, last estimates with 95 % ellipses and sites as RFC 7946 "
                                              "GeoJSON"),
    "kml": (KmlOptions, _run_kml, "the same as KML 2.2 (Google Earth, QGroundControl)"),
    "mcap": (McapOptions, _run_mcap, "the bus log as MCAP (Foxglove, the mcap CLI): a channel per bus key, "
                                     "a JSON schema per message type"),
    "all": (AllOptions, _run_all, "table, geojson, kml and mcap beside the bus log"),
}


def add_parser(subparsers) -> None:
    """Add `export` and its subcommands to the `skyfuse` subparsers."""
    e = subparsers.add_parser("export", help="a run's data for other tools: Parquet/CSV tables, GeoJSON, KML, MCAP",
                              description="Export a run (its OUT directory or bus log) for other tools.")
    e.set_defaults(export_main=export_main)
    sub = e.add_subparsers(dest="export_command", metavar="FORMAT", parser_class=Parser)
    sub.required = True
    for name, (cls, _run, doc) in SUBCOMMANDS.items():
        sub.add_parser(name, help=doc.replace("%", "%%"), description=doc, flags=_adder(cls))


def export_main(args) -> int:
    entry = SUBCOMMANDS.get(getattr(args, "export_command", None))
    if entry is None:
        raise UsageError(f"skyfuse export: unknown subcommand {args.export_command!r}")
    return entry[1](args)
