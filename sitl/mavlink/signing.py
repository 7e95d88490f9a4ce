"""The signing clock of a MAVLink 2 sender that only sends (the ground station's output).

The timestamp rules are the vehicles' (vehicles/mavlink/endpoint/signing.py, "Signing timestamps"),
minus the receiving side: mavlink.io "Message Signing" / "Timestamp Handling" --

* a timestamp is 10 us since 2015-01-01 (framing.SIGNING_EPOCH_UNIX_S), 48 bits;
* it never goes back: max(previous + 1 per frame -- pymavlink's ``sign_packet`` adds it --,
  our own clock), read before every frame;
* with a state file (framing.SigningStateFile, OUT/mav_signing_<sysid>.json) it survives a
  restart even if the clock steps back: the file holds our last timestamp and a bound
  ``reserved`` that is written BEFORE any frame carries a timestamp above it (renewed
  ``reserve_s`` ahead, i.e. a save every few seconds of frames), and a restarted sender starts
  above max(timestamp, reserved).  Without a file the clock alone carries it (the wall clock of
  the launcher, which a worker restart does not set back).

A sender that never reads has no peer timestamp to follow and no streams to keep: the file's
``streams`` stay empty.  Nothing here opens a socket; :class:`OutgoingSigning` drives the
``signing`` state of a pymavlink ``MAVLink`` object.
"""
from __future__ import annotations

import math
from typing import Callable

from .framing import SIGNING_EPOCH_UNIX_S, SIGNING_TICKS_PER_S, SigningStateFile

__all__ = ["MAX_SIGNING_TS", "OutgoingSigning", "signing_ticks"]

#: the largest 48-bit timestamp
MAX_SIGNING_TS = (1 << 48) - 1


def signing_ticks(unix_s: float) -> int | None:
    """Unix seconds in signing units (10 us since 2015-01-01), clamped to 0..2**48-1; None when
    the value is not a finite number."""
    try:
        u = float(unix_s)
    except (TypeError, ValueError):
        return None
    if not math.isfinite(u):
        return None
    return min(MAX_SIGNING_TS, max(0, int((u - SIGNING_EPOCH_UNIX_S) * SIGNING_TICKS_PER_S)))


class OutgoingSigning:
    """Signs everything ``mav`` (a pymavlink MAVLink) sends with ``key`` (32 bytes) on
    ``link_id``; call :meth:`before_send` before each frame (it moves the timestamp up to the
    clock and renews the persisted bound).  clock: unix seconds; state_file: a
    framing.SigningStateFile or None.  ``saves`` / ``errors`` count state writes and failures
    (a failed write is retried at the next frame, never raised); ``last_error``: one line."""

    def __init__(self, mav, key: bytes, *, clock: Callable[[], float], link_id: int = 0,
                 state_file: SigningStateFile | None = None, reserve_s: float = 5.0):
        if not isinstance(key, (bytes, bytearray)) or len(key) != 32:
            raise ValueError("signing_key must be 32 bytes")
        if not callable(clock):
            raise ValueError("clock must be callable (unix seconds)")
        if not (math.isfinite(reserve_s) and reserve_s > 0):
            raise ValueError(f"reserve_s must be > 0, got {reserve_s!r}")
        self._mav, self._clock, self._state = mav, clock, state_file
        self._reserve_ticks = int(reserve_s * SIGNING_TICKS_PER_S)
        self._reserved = 0
        self.saves = self.errors = 0
        self.last_error: str | None = None
        s = mav.signing
        s.secret_key, s.link_id, s.sign_outgoing = bytes(key), int(link_id) & 0xFF, True
        s.timestamp = 1
        if state_file is not None:
            try:
                st = state_file.load()
            except ValueError as e:  # unreadable: the clock alone, the file rewritten at the first frame
                self.errors += 1
                self.last_error = " ".join(str(e).split())
                st = None
            if st is not None:
                s.timestamp = min(MAX_SIGNING_TS, max(st["timestamp"], st["reserved"]) + 1)
        self.before_send()

    @property
    def timestamp(self) -> int:
        """The timestamp the next frame carries."""
        return int(self._mav.signing.timestamp)

    def before_send(self) -> None:
        s = self._mav.signing
        own = signing_ticks(self._clock())
        if own is not None and own > s.timestamp:
            s.timestamp = own
        if self._state is not None and s.timestamp >= self._reserved:
            self._save(min(MAX_SIGNING_TS, s.timestamp + self._reserve_ticks))

    def _save(self, reserved: int) -> None:
        self._reserved = reserved  # even if the write fails: nothing above it is signed unsaved...
        try:
            self._state.save(self._mav.signing.timestamp, reserved, {})
        except OSError as e:
            self._reserved = 0  # ...so retried at the next frame
            self.errors += 1
            self.last_error = f"signing state {self._state.path}: {e.strerror or e}"
            return
        self.saves += 1

    def close(self) -> None:
        """Persist the final timestamp (the bound stays: a restart starts above both)."""
        if self._state is not None and self._reserved:
            self._save(self._reserved)
