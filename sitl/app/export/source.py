"""Where an export reads from: a run's bus log (``OUT/bus.log`` of `skyfuse demo` / `skyfuse
run`, or a batch run recorded with ``sitl.app.batch.run_batch(..., record=PATH)``).

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
            hint = ""
            if (p / "report.json").is_file():
                hint = (" (a `skyfuse demo --batch` run records none; a live `skyfuse demo` / `skyfuse run` "
                        "writes OUT/bus.log)")
            raise UsageError(f"{what}: {str(p)!r} holds no bus.log{hint}")
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
