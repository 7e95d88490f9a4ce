"""The key figures of a result document (result.json / report.json): RMSE, sqrt(PCRB), ANEES
with its band, rejected inputs, faults, restarts -- found by their names wherever the document
holds them, each row with its JSON path so that a reader (and the tests) can find the value
the report shows."""
from __future__ import annotations

import math
from dataclasses import dataclass

QUANTITIES = ("RMSE", "sqrt PCRB", "ANEES", "rejected inputs", "faults", "restarts")
# branches that hold inputs, series or bookkeeping, not key figures
SKIP = {"scenario", "timing_s", "figures", "locator", "prior", "per_seed", "series", "error_series", "bus_payloads",
        "workers", "events", "shutdown", "provenance", "paper", "targets", "bus_cost_per_message_us",
        "history", "specs", "argv", "command"}
MAX_LIST = 6  # lists of at most this many entries are walked (e.g. a sweep over UAV counts)
MAX_PER_QUANTITY = 30
MAX_DEPTH = 6


@dataclass
class Row:
    quantity: str
    label: str
    value: float | int
    path: list | None  # JSON path in the document; None: computed by the report (``source``)
    unit: str = ""
    band: list | None = None
    band_path: list | None = None
    source: str = "result"
    note: str = ""


def _quantity(key: str) -> str | None:
    k = key.lower()
    if k.startswith("wall") or k.startswith("timing"):
        return None
    if any(w in k for w in ("bounds", "band", "stderr", "ratio", "over_sqrt", "diff", "rel_", "per_trial")):
        return None
    if "rmse" in k:
        return "RMSE"
    if "pcrb" in k:
        return "sqrt PCRB"
    if k == "anees" or k.startswith("anees"):
        return "ANEES"
    if "rejected" in k:
        return "rejected inputs"
    if "fault" in k:
        return "faults"
    if k == "restarts":
        return "restarts"
    return None


def _unit(path: list) -> str:
    for k in reversed(path):
        if isinstance(k, str):
            if k.endswith("_m") or k.endswith("_rmse_m"):
                return "m"
            if k.endswith("_m_s"):
                return "m/s"
            if k.endswith("_s"):
                return "s"
    return ""


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _band_of(d: dict):
    for k, v in d.items():
        if ("bounds" in k or "band" in k) and isinstance(v, list) and len(v) == 2 and all(_is_number(x) for x in v):
            return k, v
    return None, None


def key_rows(doc: dict) -> tuple[list[Row], dict]:
    """The document's key-figure rows, and per quantity how many were left out (over the cap)."""
    rows: list[Row] = []
    left: dict = {}

    def add(row: Row):
        if sum(r.quantity == row.quantity for r in rows) >= MAX_PER_QUANTITY:
            left[row.quantity] = left.get(row.quantity, 0) + 1
        else:
            rows.append(row)

    def label(path, qkey_index):
        return " / ".join(str(p) for p in path)

    def walk(node, path, quantity, qi, parent):
        if len(path) > MAX_DEPTH:
            return
        if quantity == "ANEES" and isinstance(node, dict):
            v = node.get("value", node.get("mean"))
            if _is_number(v):
                bk, band = _band_of(node)
                vk = "value" if "value" in node else "mean"
                add(Row(quantity, label(path, qi), float(v), path + [vk], "1", band,
                        path + [bk] if bk else None))
                return
        counts = quantity in ("rejected inputs", "faults", "restarts")  # counters: integers, not times
        if counts and isinstance(path[-1], str) and path[-1].endswith("_s"):
            return
        if _is_number(node) and quantity is not None and (not counts or isinstance(node, int)):
            band = band_path = None
            if quantity == "ANEES" and isinstance(parent, dict):
                bk, band = _band_of({k: v for k, v in parent.items() if k.startswith(str(path[-1])) or k == "band"})
                band_path = path[:-1] + [bk] if bk else None
            add(Row(quantity, label(path, qi), node, path,
                    "1" if quantity in ("ANEES",) else ("" if quantity in ("rejected inputs", "faults", "restarts")
                                                        else _unit(path)), band, band_path))
            return
        if (counts and isinstance(node, dict) and qi == len(path) - 1
                and all(isinstance(v, int) and not isinstance(v, bool) for v in node.values())):
            # a counter by reason ({"stale": 2, ...}, or {} when nothing was rejected): its total first
            add(Row(quantity, label(path, qi) + " (total over reasons)", sum(node.values()), path, "",
                    note=", ".join(f"{k} {v}" for k, v in node.items()) or "none"))
        if isinstance(node, dict):
            for k, v in node.items():
                if k in SKIP:
                    continue
                q, i = _quantity(str(k)), len(path)  # the innermost named quantity
                if q is None:
                    q, i = quantity, qi
                walk(v, path + [k], q, i, node)
        elif isinstance(node, list) and len(node) <= MAX_LIST:
            for j, v in enumerate(node):
                if not isinstance(v, dict):  # a list of numbers is a series (per trial, per epoch)
                    continue
                walk(v, path + [j], quantity, qi, node)

    walk(doc, [], None, None, None)
    order = {q: i for i, q in enumerate(QUANTITIES)}
    rows.sort(key=lambda r: order[r.quantity])
    return rows, left


def lookup(doc, path):
    """The value at a JSON path (a list of keys and indexes)."""
    for p in path:
        doc = doc[p]
    return doc
