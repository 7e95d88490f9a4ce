"""An embedded Zenoh router: eclipse-zenoh opened in mode "router" inside this process.

There is no zenohd binary here; a router is a Zenoh session in router mode, which routes
between every client session connected to it (the launcher's vehicle and ground-station
processes). Port 0 asks the OS for a free port; `Router.endpoints` gives the endpoints
actually bound, read back from the router's own admin space (read-only; written to never).

    with Router(listen=["tcp/127.0.0.1:0"]) as r:
        print(r.endpoints)          # ['tcp/127.0.0.1:40123']
        ... ZenohTransport(connect=r.endpoints) in other processes ...

Multicast scouting is off by default (runs meet through explicit endpoints; two test runs on
one machine must not find each other). Open it before starting worker processes with
`subprocess` (never fork a process that holds an open Zenoh session).

``python -m sitl.bus.routerd`` runs one as a process (see there).
"""

from __future__ import annotations

import atexit
import json
import logging
import threading
import weakref
from collections.abc import Iterable, Mapping
from typing import Any

import zenoh

from .zconfig import make_config, zenoh_error_text

log = logging.getLogger("sitl.bus.router")

DEFAULT_LISTEN = ("tcp/127.0.0.1:0",)


_OPEN: weakref.WeakSet = weakref.WeakSet()  # routers to close at interpreter exit


def _close_all_at_exit() -> None:
    for r in list(_OPEN):
        try:
            r.close()
        except Exception as e:
            log.debug("closing %r at exit: %s", r, e)


# before the interpreter joins its threads (see sitl.bus.zenoh_transport)
getattr(threading, "_register_atexit", atexit.register)(_close_all_at_exit)


class RouterError(RuntimeError):
    """The router could not start (port taken, bad endpoint): one line."""


class Router:
    """An embedded Zenoh router. ``listen``: endpoints to bind (port 0 = a free port);
    ``lease_ms``: link lease (default Zenoh's 10 s; lower it in partition tests);
    ``extra``: further Zenoh config keys ``{"path/of/key": value}``."""

    def __init__(self, listen: Iterable[str] | str = DEFAULT_LISTEN, *,
                 multicast_scouting: bool = False, lease_ms: int | None = None,
                 extra: Mapping[str, Any] | None = None, timeout_s: float = 5.0):
        cfg = make_config("router", listen=listen, multicast_scouting=multicast_scouting,
                          lease_ms=lease_ms, adminspace_read=True, extra=extra)
        try:
            self._session = zenoh.open(cfg)
        except Exception as e:
            raise RouterError(f"zenoh router on {listen!r} did not start: "
                              f"{zenoh_error_text(e)}") from None
        self._lock = threading.Lock()
        self.zid = str(self._session.zid())
        try:
            self.endpoints: list[str] = self._read_locators(timeout_s)
        except Exception:
            self._session.close()
            raise
        _OPEN.add(self)
        log.info("zenoh router %s listening on %s", self.zid, ", ".join(self.endpoints))

    def _read_locators(self, timeout_s: float) -> list[str]:
        for reply in self._session.get(f"@/{self.zid}/router", timeout=timeout_s):
            if reply.ok is not None:
                return list(json.loads(reply.ok.payload.to_string())["locators"])
        raise RouterError("zenoh router: its admin space did not report its endpoints")

    @property
    def closed(self) -> bool:
        return self._session.is_closed()

    def sessions(self) -> list[str]:
        """Zenoh ids of the sessions connected to this router right now."""
        return [str(t.zid) for t in self._session.info.transports()]

    def close(self) -> None:
        """Close the router (idempotent); connected clients lose their link."""
        with self._lock:
            _OPEN.discard(self)
            if not self._session.is_closed():
                self._session.close()

    def __enter__(self) -> Router:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self.closed else ", ".join(self.endpoints)
        return f"Router({self.zid[:8]} {state})"


__all__ = ["DEFAULT_LISTEN", "Router", "RouterError"]
