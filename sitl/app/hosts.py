"""Where a live run's workers run: ``--host WORKERS=COMMAND`` puts the workers whose names match
the pattern (fnmatch: ``vehicles*``, ``gs``) on another host by starting them through COMMAND,
e.g. ``vehicles*=ssh -T hostB`` or ``vehicles*=ip netns exec hostB``.

The launcher supervises such a worker as any other: the line protocol of sitl.live.worker runs
over the command's stdin and stdout (ssh and ``ip netns exec`` pass them through), the stop
command and the end of stdin reach it there, so shutdown reaches every host; its stderr is the
launcher's log file. What the other host needs: this project at the same version, the same
Python path as the launcher's (``sys.executable``), the run's OUT directory at the same path (the
worker reads its spec from OUT/specs/ and writes its logs there: a shared file system; network
namespaces share the launcher's), and a route to the Zenoh endpoints of the run -- give
``--zenoh tcp/ROUTER:PORT`` an address both hosts reach (the embedded router listens on the
scenario's ``[bus] listen``, loopback by default). ssh does not pass the environment
(PYTHONPATH): install the project there. MAVLink goes to ``--gcs`` from the host the vehicles
run on.
"""
from __future__ import annotations

import fnmatch
import shlex
from dataclasses import dataclass

from sitl.params import Check, ParamError


@dataclass(frozen=True)
class Placement:
    """Workers matching ``pattern`` run through ``command`` (argv words before the worker's own)."""

    pattern: str
    command: tuple

    def matches(self, worker: str) -> bool:
        return fnmatch.fnmatchcase(worker, self.pattern)


def parse_placement(text: str) -> Placement:
    """``WORKERS=COMMAND``; a ParamError (one line) otherwise."""
    if not isinstance(text, str) or "=" not in text:
        raise ParamError("", f"expected WORKERS=COMMAND (e.g. 'vehicles*=ssh -T hostB'), got {text!r}")
    pattern, command = (s.strip() for s in text.split("=", 1))
    if not pattern:
        raise ParamError("", f"expected a worker name or pattern before '=', got {text!r}")
    try:
        words = tuple(shlex.split(command))
    except ValueError as exc:
        raise ParamError("", f"cannot split the command of {text!r}: {exc}") from None
    if not words:
        raise ParamError("", f"expected a command after '=', got {text!r}")
    return Placement(pattern, words)


def placement_check() -> Check:
    def test(v):
        parse_placement(v)
        return v

    return Check(test)


class Placements:
    """The ``--host`` values of a run, the first match winning."""

    def __init__(self, texts=None):
        self.items = [parse_placement(t) for t in (texts or ())]

    def __bool__(self) -> bool:
        return bool(self.items)

    def command_for(self, worker: str) -> tuple:
        """The argv words to start ``worker`` through (empty: this host)."""
        return next((p.command for p in self.items if p.matches(worker)), ())

    def unmatched(self, workers) -> list[str]:
        """The patterns that match none of ``workers``."""
        workers = list(workers)
        return [p.pattern for p in self.items if not any(p.matches(w) for w in workers)]
