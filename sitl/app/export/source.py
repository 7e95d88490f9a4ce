"""Where an export reads from: a run's bus log (``OUT/bus.log`` of `skyfuse demo` / `skyfuse
run`, or a batch run recorded with ``sitl.app.batch.run_batch(..., record=PATH)``; the OUT of a
`skyfuse demo --batch` run, which keeps no bus log, is run again to record one: `record_batch`).

`resolve_log` takes a run's OUT directory or the log itself and checks, before any output is
written, that the file is a bus log (its magic); `read_records` streams its records with a
progress bar on a terminal (tqdm, on stderr, only when stderr is a TTY) and reports a torn or
corrupt tail once, as one line, after the records before it were read."""
from __future__ import annotations

import logging
import os
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

from sitl.app.args import UsageError
from sitl.bus.buslog import MAGIC, BusLogStats, BusRecord, read_bus_log_records

#: bytes of a record besides its key and payload (u32 length, u32 CRC, f64 t_recv_s, u16 key length)
_RECORD_OVERHEAD = 4 + 4 + 8 + 2


def resolve_log(path: str | os.PathLike, what: str = "export") -> Path:
    """The bus log of ``path`` (a run's OUT directory or the log file), checked to be one: a
    `UsageError` (one line) if there is none, or the file is not a skyfuse bus log."""
    p = Path(path)
    if p.is_dir():
        log = p / "bus.log"
        if not log.is_file():
            report = _batch_report(p)
            if report is None:
                raise UsageError(f"{what}: {str(p)!r} holds no bus.log (neither a live run's OUT nor a "
                                 "`skyfuse demo --batch` run's)")
            return record_batch(p, report, what)
        p = log
    if not p.is_file():
        raise UsageError(f"{what}: {str(p)!r}: no such file")
    try:
        with open(p, "rb") as f:
            head = f.read(len(MAGIC))
    except OSError as e:
        raise UsageError(f"{what}: cannot read {str(p)!r}: {e.strerror}") from None
    if not head:
        raise UsageError(f"{what}: {str(p)!r} is empty, not a skyfuse bus log")
    if not (MAGIC[:7].startswith(head) if len(head) < 7 else head[:7] == MAGIC[:7]):
        raise UsageError(f"{what}: {str(p)!r} is not a skyfuse bus log (bad magic)")
    if len(head) == len(MAGIC) and head != MAGIC:
        raise UsageError(f"{what}: {str(p)!r} is a bus log of version {head[7]}; this build reads "
                         f"version {MAGIC[7]}")
    return p


def _batch_report(out: Path) -> dict | None:
    """OUT/report.json of a batch run (`skyfuse demo --batch`, `run --batch`), else None."""
    import json

    try:
        doc = json.loads((out / "report.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) and doc.get("mode") == "batch" and "scenario" in doc else None


def record_batch(out: Path, report: dict, what: str = "export",
                 say: Callable[[str], None] | None = None) -> Path:
    """A batch run's bus log, made by running it again: a batch run records no bus log (its
    traffic is in memory), but it is deterministic for its scenario and seed, so the scenario of
    its report.json, run again with a recorder on its bus, gives the run's own traffic. The
    errors of the new run are checked against the report's (RMSE and scored epochs of every
    object): a difference is said (one line) and the log kept under another name,
    ``bus.rerun.log``, so that it never passes for the run's. Returns the log's path."""
    import math

    from sitl.app.batch import run_batch
    from sitl.scenario import ScenarioError, scenario_from_dict, to_toml_like

    say = say or (lambda m: print(m, file=sys.stderr))
    try:
        scn = scenario_from_dict(to_toml_like(report["scenario"]), str(out / "report.json"))
    except (ScenarioError, TypeError, ValueError) as e:
        raise UsageError(f"{what}: {out / 'report.json'}: its scenario does not load: {e}") from None
    log = out / "bus.log"
    tmp = out / "bus.log.part"
    say(f"{what}: {out} is a batch run, which records no bus log: running it again (deterministic for its "
        f"seed, {scn.run.duration_s:g} simulated s) to record {log}")
    try:
        res = run_batch(scn, record=tmp)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    before = report.get("errors") or {}
    differ = []
    for name in sorted(set(before) | set(res["errors"])):
        a, b = before.get(name) or {}, res["errors"].get(name) or {}
        ra, rb = a.get("rmse_m"), b.get("rmse_m")
        same_rmse = (ra is None and rb is None) or (ra is not None and rb is not None
                                                    and math.isclose(ra, rb, rel_tol=1e-9, abs_tol=1e-12))
        if a.get("scored") != b.get("scored") or not same_rmse:
            differ.append(name)
    if differ:
        log = out / "bus.rerun.log"
        say(f"{what}: the re-run's errors differ from report.json's for {', '.join(differ)} (another build or "
            f"seed handling?): exporting it anyway, from {log}")
    os.replace(tmp, log)
    return log


class _Quiet(logging.Filter):
    """Hold back the bus log reader's own torn-tail warning: the export says it once itself."""

    def filter(self, record: logging.LogRecord) -> bool:
        return False


def read_records(log: Path, *, stats: BusLogStats | None = None, progress: bool | None = None,
                 say: Callable[[str], None] | None = None, desc: str = "reading") -> Iterator[BusRecord]:
    """The records of bus log ``log`` in order (`read_bus_log_records`), then, if the log ends in
    a torn or corrupt tail, one line through ``say`` (default: stderr) naming what was kept.
    ``progress``: a tqdm bar over the file's bytes (None: when stderr is a terminal)."""
    st = stats if stats is not None else BusLogStats()
    if progress is None:
        progress = hasattr(sys.stderr, "isatty") and sys.stderr.isatty()
    bar = None
    try:
        from tqdm import tqdm
    except ImportError:  # the `export` extra brings it; without it no bar
        progress = False
    if progress:
        bar = tqdm(total=os.path.getsize(log), unit="B", unit_scale=True, desc=desc, leave=False,
                   file=sys.stderr)
    logger = logging.getLogger("sitl.bus.buslog")
    quiet = _Quiet()
    logger.addFilter(quiet)
    try:
        for rec in read_bus_log_records(log, stats=st):
            if bar is not None:
                bar.update(_RECORD_OVERHEAD + len(rec.key.encode("utf-8")) + len(rec.payload))
            yield rec
    finally:
        logger.removeFilter(quiet)
        if bar is not None:
            bar.close()
    if st.dropped_bytes:
        line = (f"{log}: {st.reason or 'unreadable tail'} after {st.records} records; exported those, "
                f"{st.dropped_bytes} bytes after them left out")
        (say or (lambda m: print(m, file=sys.stderr)))(line)
