"""Building eclipse-zenoh configurations for the bus (shared by the router and the transport).

Only what the live bus needs: mode, listen/connect endpoints, multicast scouting (off by
default: runs on one machine meet through an explicit router, and tests must not discover
each other's sessions), the link lease, and free-form extra keys for anything else.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Mapping
from typing import Any

import zenoh

MODES = ("router", "peer", "client")


class ZenohConfigError(ValueError):
    """A bad Zenoh setting (mode, endpoint, lease, extra key): one line, names the setting."""


_RUST_WHERE = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")


def zenoh_error_text(err: BaseException) -> str:
    """A Zenoh error on one line, without the Rust source locations it carries."""
    return _RUST_WHERE.sub("", " ".join(str(err).split())).strip() or type(err).__name__


def _endpoints(value: Iterable[str] | str | None, what: str) -> list[str]:
    if value is None:
        return []
    if isinstance(value, str):
        value = [value]
    out = []
    for e in value:
        if not isinstance(e, str) or "/" not in e or not e.split("/", 1)[1]:
            raise ZenohConfigError(f"{what}: {e!r} is not a Zenoh endpoint "
                                   "(expected e.g. 'tcp/127.0.0.1:7447')")
        out.append(e)
    return out


def make_config(mode: str, *, listen: Iterable[str] | str | None = None,
                connect: Iterable[str] | str | None = None, multicast_scouting: bool = False,
                lease_ms: int | None = None, adminspace_read: bool = False,
                extra: Mapping[str, Any] | None = None) -> zenoh.Config:
    """A `zenoh.Config`. ``lease_ms``: link lease (Zenoh default 10000 ms; a silent peer is
    declared gone after it); ``extra``: ``{"path/of/key": python value}`` inserted as JSON."""
    if mode not in MODES:
        raise ZenohConfigError(f"mode: {mode!r} is not one of {', '.join(MODES)}")
    cfg = zenoh.Config()
    items: list[tuple[str, Any]] = [("mode", mode)]
    lst = _endpoints(listen, "listen")
    con = _endpoints(connect, "connect")
    if lst:
        items.append(("listen/endpoints", lst))
    if con:
        items.append(("connect/endpoints", con))
    elif mode == "client":
        raise ZenohConfigError("connect: a client needs at least one router endpoint")
    items.append(("scouting/multicast/enabled", bool(multicast_scouting)))
    # do not wait for scouting answers at open (Zenoh waits 500 ms by default)
    items.append(("scouting/delay", 0))
    if lease_ms is not None:
        if isinstance(lease_ms, bool) or not isinstance(lease_ms, int) or lease_ms < 100:
            raise ZenohConfigError(f"lease_ms: expected an int >= 100, got {lease_ms!r}")
        items.append(("transport/link/tx/lease", lease_ms))
    if adminspace_read:
        items.append(("adminspace", {"enabled": True,
                                     "permissions": {"read": True, "write": False}}))
    for k, v in (extra or {}).items():
        items.append((str(k), v))
    for k, v in items:
        try:
            cfg.insert_json5(k, json.dumps(v))
        except Exception as e:  # zenoh.ZError, with a multi-line text
            raise ZenohConfigError(f"zenoh config {k}={json.dumps(v)}: "
                                   f"{zenoh_error_text(e)}") from None
    return cfg


__all__ = ["MODES", "ZenohConfigError", "make_config", "zenoh_error_text"]
