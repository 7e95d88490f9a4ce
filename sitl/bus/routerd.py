"""A Zenoh router as a process (the role of zenohd, which is not installed here).

    python -m sitl.bus.routerd [--lease-ms MS] [--multicast-scouting] [ENDPOINT ...]

Listens on the endpoints (default ``tcp/127.0.0.1:0``: a free loopback port), prints one JSON
line ``{"zid": ..., "endpoints": [...]}`` on stdout once it routes, then routes until SIGINT
or SIGTERM and exits 0. Bad arguments or an endpoint that cannot be bound: one line on
stderr, exit 2.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys

from .zconfig import ZenohConfigError
from .router import DEFAULT_LISTEN, Router, RouterError


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2, no traceback
        self.print_usage(sys.stderr)
        print(f"error: {message}", file=sys.stderr)
        raise SystemExit(2)


def main(argv: list[str] | None = None) -> int:
    ap = _Parser(prog="python -m sitl.bus.routerd", description=__doc__.split("\n")[0])
    ap.add_argument("endpoints", nargs="*", metavar="ENDPOINT",
                    help="Zenoh endpoints to listen on (default tcp/127.0.0.1:0)")
    ap.add_argument("--lease-ms", type=int, default=None,
                    help="link lease in ms (Zenoh default 10000)")
    ap.add_argument("--multicast-scouting", action="store_true",
                    help="answer multicast scouting (off by default)")
    args = ap.parse_args(argv)
    # Zenoh's threads may take the signal: the C-level handler still writes its number to
    # the wakeup pipe, on which the main thread waits.
    rfd, wfd = os.pipe()
    os.set_blocking(wfd, False)
    signal.set_wakeup_fd(wfd)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: None)
    try:
        router = Router(args.endpoints or DEFAULT_LISTEN, lease_ms=args.lease_ms,
                        multicast_scouting=args.multicast_scouting)
    except (RouterError, ZenohConfigError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    with router:
        print(json.dumps({"zid": router.zid, "endpoints": router.endpoints}), flush=True)
        while os.read(rfd, 1)[0] not in (signal.SIGINT, signal.SIGTERM):
            pass
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
