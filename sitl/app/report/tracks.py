"""The tracks of a run, read back from its bus log: every truth (``<run>/truth/<kind>/<id>``)
and every ground-station estimate (``<run>/gs/estimate/<kind>/<id>``) as arrays per target.

A record that does not decode is counted (``Tracks.undecodable``) and skipped; a torn or
corrupt tail ends the read as `sitl.bus.buslog.read_bus_log_records` does."""
from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass
class Track:
    """One target's positions over time (ECEF, m); ``cov_pos_m2`` (T, 3, 3) for estimates."""

    kind: str
    id: str
    t_gps_s: np.ndarray
    pos_ecef_m: np.ndarray
    cov_pos_m2: np.ndarray | None = None


@dataclass
class Tracks:
    truth: dict = field(default_factory=dict)  # (kind, id) -> Track
    estimate: dict = field(default_factory=dict)  # (kind, id) -> Track
    records: int = 0
    undecodable: int = 0

    def __bool__(self) -> bool:
        return bool(self.truth or self.estimate)


def read_tracks(bus_log: Path) -> Tracks:
    """Truth and estimate tracks of every target in ``bus_log`` (see the module text)."""
    from sitl.bus import BusDecodeError, decode
    from sitl.bus.buslog import read_bus_log_records

    rows: dict = {"truth": defaultdict(list), "estimate": defaultdict(list)}
    out = Tracks()
    for rec in read_bus_log_records(bus_log):
        out.records += 1
        parts = rec.key.split("/")
        if len(parts) == 4 and parts[1] == "truth":
            which = "truth"
        elif len(parts) == 5 and parts[1:3] == ["gs", "estimate"]:
            which = "estimate"
        else:
            continue
        try:
            msg = decode(rec.payload)
        except (BusDecodeError, ValueError):
            out.undecodable += 1
            continue
        cov = np.asarray(msg.cov)[0:3, 0:3] if which == "estimate" else None
        rows[which][(parts[-2], parts[-1])].append((float(msg.t_gps_s), np.asarray(msg.pos_ecef_m, float), cov))
    for which, per in rows.items():
        dest = getattr(out, which)
        for (kind, tid), items in per.items():
            items.sort(key=lambda r: r[0])
            t = np.array([r[0] for r in items])
            _, first = np.unique(t, return_index=True)  # one sample per epoch (a re-sent estimate: the first)
            items = [items[i] for i in first]
            dest[(kind, tid)] = Track(kind, tid, t[first], np.array([r[1] for r in items]),
                                      np.array([r[2] for r in items]) if which == "estimate" else None)
    return out


def errors_at_common_epochs(truth: Track, est: Track):
    """(t_gps_s, error (T, 3) ECEF m, cov_pos (T, 3, 3)) at the epochs both tracks hold."""
    tt = np.round(truth.t_gps_s, 6)
    te = np.round(est.t_gps_s, 6)
    common, it, ie = np.intersect1d(tt, te, return_indices=True)
    return est.t_gps_s[ie], est.pos_ecef_m[ie] - truth.pos_ecef_m[it], est.cov_pos_m2[ie]
