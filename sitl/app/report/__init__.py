"""One self-contained HTML report per run and experiment: ``OUT/report.html``.

    from sitl.app.report import write_report
    write_report(out)        # after OUT/result.json (an experiment) or OUT/report.json (a run)

The one entry point every experiment's writer and the run launcher call, once, after their
JSON document is on disk; the report is made from that file, so the numbers it shows are the
file's. It holds:

* the run's identity (the document's top-level scalars: experiment or mode, seed, trials, ...);
* a table of the key figures (`sitl.app.report.table`: RMSE, sqrt(PCRB), ANEES with its band,
  rejected inputs, faults, restarts), each row with the document's JSON path of its value;
* for a live or batch run (``mode`` live / batch) with a bus log (OUT/bus.log): a map of the
  tracks drawn without tiles (UAVs, beacon and sonde truth and estimate with the estimate's
  95 % ellipse, the radar site) and the estimates' errors against time, both also written as
  PNG beside the report (map.png, run_errors.png), and the position NEES of each estimate;
* every figure of the document (its ``figures`` list, else every PNG in OUT), embedded as
  ``data:image/png;base64`` URIs.

No script, no style sheet, font or image from the network: the file opens offline.
"""
from __future__ import annotations

import base64
import html
import json
import math
from pathlib import Path

from sitl.app.report.table import QUANTITIES, Row, key_rows

REPORT = "report.html"
DOCUMENTS = ("result.json", "report.json")

_CSS = """
body { font-family: sans-serif; margin: 16px 24px; color: #222; max-width: 1500px; }
h1 { font-size: 20px; margin: 0 0 8px 0; } h2 { font-size: 16px; margin: 20px 0 6px 0; }
table { border-collapse: collapse; font-size: 13px; } td, th { border: 1px solid #bbb; padding: 3px 8px; }
th { background: #eee; text-align: left; } td.num { text-align: right; font-family: monospace; }
figure { margin: 10px 0 18px 0; } figcaption { font-size: 12px; color: #555; }
img { max-width: 100%; border: 1px solid #ddd; } #map img { width: 1100px; max-width: 100%; }
.note { font-size: 12px; color: #555; }
"""


class ReportError(ValueError):
    """No result document in the output directory."""


def _fmt(v) -> str:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return html.escape(str(v))
    if isinstance(v, int):
        return str(v)
    if v == 0 or not math.isfinite(v):
        return str(v)
    return f"{v:.4g}" if 1e-3 <= abs(v) < 1e6 else f"{v:.3e}"


def _png_uri(path: Path) -> str:
    return "data:image/png;base64," + base64.b64encode(path.read_bytes()).decode("ascii")


def _identity(doc: dict) -> list[tuple[str, str]]:
    out = []
    for k, v in doc.items():
        if isinstance(v, (int, float, bool)) or (isinstance(v, str) and len(v) < 200):
            out.append((k, _fmt(v)))
    prov = doc.get("provenance")
    if isinstance(prov, dict):
        out += [(f"provenance.{k}", _fmt(v)) for k, v in prov.items() if isinstance(v, (str, int, float, bool))]
    return out


def _row_html(r: Row) -> str:
    attrs = f' data-quantity="{html.escape(r.quantity)}" data-value="{r.value!r}" data-source="{r.source}"'
    if r.path is not None:
        attrs += f" data-path='{html.escape(json.dumps(r.path), quote=True)}'"
    band = "" if r.band is None else f"{_fmt(r.band[0])} - {_fmt(r.band[1])}"
    if r.band_path is not None:
        attrs += f" data-band-path='{html.escape(json.dumps(r.band_path), quote=True)}'"
    where = "/".join(str(p) for p in r.path) if r.path is not None else r.source
    return (f"<tr{attrs}><td>{html.escape(r.quantity)}</td><td>{html.escape(r.label)}</td>"
            f"<td class=\"num\">{_fmt(r.value)}</td><td>{html.escape(r.unit)}</td><td>{band}</td>"
            f"<td>{html.escape(r.note)}</td><td class=\"note\">{html.escape(where)}</td></tr>")


def _figure_list(out: Path, doc: dict, extra: list[Path]) -> list[Path]:
    names = doc.get("figures")
    if isinstance(names, list) and names:
        figs = [out / Path(str(n)).name for n in names]
    else:
        figs = sorted(p for p in out.glob("*.png") if p not in extra)
    seen, files = set(), []
    for p in [*extra, *figs]:
        if p.is_file() and p.suffix == ".png" and p.name not in seen:
            seen.add(p.name)
            files.append(p)
    return files


def _run_title(doc: dict) -> str:
    if doc.get("experiment"):
        return f"skyfuse experiment {doc['experiment']}"
    run = (doc.get("scenario") or {}).get("run") or {}
    return (f"skyfuse {doc.get('mode', 'live')} run '{run.get('id', '')}' | RNG seed {run.get('seed', '?')} | "
            f"{run.get('duration_s', '?')} s simulated")


def write_report(out, *, figures=None) -> Path:
    """Write OUT/report.html (module text) from OUT/result.json or OUT/report.json; returns its
    path. ``figures``: the PNGs to embed (default: the document's ``figures``, else every PNG
    in OUT). Raises ReportError if OUT holds neither document."""
    out = Path(out)
    doc_path = next((out / n for n in DOCUMENTS if (out / n).is_file()), None)
    if doc_path is None:
        raise ReportError(f"no {' or '.join(DOCUMENTS)} in {str(out)!r}")
    doc = json.loads(doc_path.read_text(encoding="utf-8"))
    title = _run_title(doc)
    rows, left = key_rows(doc)
    made: list[Path] = []
    map_png = None
    notes = []
    if doc.get("mode") in ("live", "batch"):
        log = out / "bus.log"
        if log.is_file():
            from sitl.app.report.figures import nees_summary, plot_errors, plot_map
            from sitl.app.report.tracks import read_tracks

            tracks = read_tracks(log)
            scn = doc.get("scenario") or {}
            map_png = plot_map(tracks, scn, out, title) if tracks else None
            err_png = plot_errors(tracks, out, title, (scn.get("run") or {}).get("t0_gps_s")) if tracks else None
            made = [p for p in (map_png, err_png) if p is not None]
            for target, s in nees_summary(tracks).items():
                rows.append(Row("ANEES", f"{target}: mean position NEES over the run's {s['epochs']} epochs (3 dof)",
                                s["mean_nees_pos"], None, "1", s["band_99_one_epoch"], None, "bus.log",
                                f"band: 99 % of one epoch; {100 * s['fraction_inside']:.1f} % of epochs inside"))
            if tracks.undecodable:
                notes.append(f"bus.log: {tracks.undecodable} records did not decode (skipped)")
        else:
            notes.append("no bus.log in this run's folder (the scenario's bus.log = false): no map")
    rows.sort(key=lambda r: QUANTITIES.index(r.quantity))  # the log's NEES beside the document's ANEES
    files = _figure_list(out, doc, made) if figures is None else [Path(f) for f in figures]
    if map_png is not None and map_png not in files:
        files.insert(0, map_png)
    parts = [f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>{html.escape(title)}</title>",
             f"<style>{_CSS}</style></head><body>", f"<h1>{html.escape(title)}</h1>",
             f"<p class=\"note\">made from {html.escape(doc_path.name)}; figures also as PNG in this folder</p>"]
    if map_png is not None:
        parts.append(f"<figure id=\"map\"><img id=\"map-img\" src=\"{_png_uri(map_png)}\" "
                     f"alt=\"map of the tracks\"><figcaption>{html.escape(map_png.name)}: local east/north frames, "
                     "metres; no map tiles</figcaption></figure>")
    ident = _identity(doc)
    if ident:
        parts.append("<h2>Run</h2><table id=\"identity\">"
                     + "".join(f"<tr><th>{html.escape(k)}</th><td>{v}</td></tr>" for k, v in ident) + "</table>")
    parts.append("<h2>Key figures</h2>")
    if rows:
        parts.append("<table id=\"key-figures\"><tr><th>quantity</th><th>what</th><th>value</th><th>unit</th>"
                     "<th>band</th><th>note</th><th>where (JSON path)</th></tr>"
                     + "".join(_row_html(r) for r in rows) + "</table>")
    else:
        parts.append("<p>the document holds none of RMSE, PCRB, ANEES, rejected inputs, faults, restarts</p>")
    if left:
        parts.append("<p class=\"note\">not shown (more rows than the table holds; see the document): "
                     + ", ".join(f"{n} {q}" for q, n in left.items()) + "</p>")
    for n in notes:
        parts.append(f"<p class=\"note\">{html.escape(n)}</p>")
    parts.append("<h2>Figures</h2>")
    for p in files:
        if p == map_png:
            continue
        parts.append(f"<figure><img class=\"figure\" src=\"{_png_uri(p)}\" alt=\"{html.escape(p.name)}\">"
                     f"<figcaption>{html.escape(p.name)}</figcaption></figure>")
    parts.append("</body></html>")
    path = out / REPORT
    path.write_text("\n".join(parts), encoding="utf-8")
    return path


__all__ = ["REPORT", "ReportError", "write_report"]
