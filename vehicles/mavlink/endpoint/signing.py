"""The signing clock of a vehicle's endpoint and its state kept across restarts.

Signing timestamps (mavlink.io "Message Signing", "Timestamp Handling").  Our own clock is
``clock()`` (unix seconds) when the composition root injects one -- the live worker passes
the wall clock, so that a GCS on the wall clock accepts our frames as a new stream and our
timestamps keep rising across a restart -- else the simulated clock (tests, batch).  The
timestamp we sign with is max(previous + 1 per frame, own clock, an accepted peer's
timestamp that is ahead), as the spec and pymavlink do, except that a validly signed frame
more than FUTURE_WINDOW_S (300 s) ahead of our own clock is rejected as ``future`` and moves
nothing.  300 s: a GCS whose clock is a few minutes off (no NTP), or a pymavlink peer whose
+1 per frame ran ahead in a burst, is still followed; a key holder with a clock hours or years
off (or a recorded frame of one) cannot drag our clock there -- which would make the new
streams of every GCS on the true clock more than the spec's one minute behind us, and would be
persisted into every later restart.  The window is measured from our own clock, not from the
timestamp we already followed, so no chain of frames drags us further than 300 s.
With ``signing_state`` (a path: OUT/mav_signing_<sysid>.json in a live run) the state
survives a restart (framing.SigningStateFile): the spec asks to store the timestamp at least
once a minute and to start from max(clock, stored); we store our timestamp and every stream's
last timestamp, written atomically whenever the signing clock passes the bound ``reserved``
(renewed 5-10 s ahead, i.e. a save every few seconds), on the first step and at close.
Nothing above ``reserved`` is sent or accepted before it is on disk, so after a crash the
restarted endpoint signs from above it and rejects, on every stream, any timestamp at or
below it: a replay of anything captured before the restart is ``replayed``.  (A GCS that
neither follows our timestamps -- pymavlink and the C library do -- nor keeps its own above
that bound is rejected for the few seconds the bound lies ahead of the crash.)
"""
from __future__ import annotations

import math

from sitl.mavlink.framing import SIGNING_TICKS_PER_S

from .. import telemetry as tm
from .constants import _FUTURE_TICKS, _MAX_TS, _SIGNING_LOOKAHEAD


class SigningClock:
    """VehicleEndpoint's signing clock and state (a part of VehicleEndpoint, not usable alone)."""

    # ------------------------------------------------------------------ signing clock and state
    def _own_signing_ts(self) -> int | None:
        """Our own clock in signing units (10 us since 2015-01-01): the injected clock, else the
        simulated one; None if there is no reading yet (or the clock gave a non-finite value)."""
        if self._clock is not None:
            u = float(self._clock())
        elif self._t is not None:
            u = self._unix_s
        else:
            return None
        if not math.isfinite(u):
            return None
        return min(_MAX_TS, max(0, int((u - tm.SIGNING_EPOCH_UNIX_S) * SIGNING_TICKS_PER_S)))

    def _clock_signing(self) -> None:
        """Once per step: our timestamp follows our clock (never backwards), the future window
        moves with the clock, and the persisted bound is renewed when the clock nears it."""
        own = self._own_signing_ts()
        s = self.mav.signing
        if own is not None:
            if self._floor_from_clock:
                self._signer.floor = max(self._signer.floor, own)
                self._floor_from_clock = False
            if own > s.timestamp:
                s.timestamp = own
            self._future_limit = max(own, self._restart_ts) + _FUTURE_TICKS
        if self._state_file is not None and (not self._state_ok or s.timestamp + _SIGNING_LOOKAHEAD > self._reserved):
            self._reserve()

    def _load_signing_state(self) -> None:
        try:
            st = self._state_file.load()
        except ValueError as e:  # corrupt: best effort, nothing older than our clock passes
            self.counters["signing_state_errors"] += 1
            self.last_error = " ".join(str(e).split())
            self._floor_from_clock = True
            return
        if st is None:  # the first start of this vehicle in this run
            return
        self._signer.restore(st["streams"], floor=st["reserved"])
        self._restart_ts = min(_MAX_TS, max(st["timestamp"], st["reserved"]) + 1)
        self.mav.signing.timestamp = max(self.mav.signing.timestamp, self._restart_ts)
        self._reserved = st["reserved"]
        self._future_limit = self._restart_ts + _FUTURE_TICKS

    def _reserve(self, ts: int = 0) -> None:
        """Persist a new bound, some seconds above max(ts, our timestamp), before going past the old one."""
        s = self.mav.signing
        target = min(_MAX_TS, max(ts, s.timestamp) + self._reserve_ticks)
        self._reserved = target  # even if the write fails: retried at the next step, not per frame
        self._save_signing_state(target)

    def _save_signing_state(self, reserved: int) -> None:
        try:
            self._state_file.save(self.mav.signing.timestamp, reserved, self._signer.streams)
        except OSError as e:
            self._state_ok = False
            self.counters["signing_state_errors"] += 1
            self.last_error = f"signing state {self._state_file.path}: {e.strerror or e}"
            return
        self._state_ok = True
        self.counters["signing_saves"] += 1

    @property
    def signing_timestamp(self) -> int | None:
        """The timestamp our next signed frame carries (None: not signing)."""
        return self.mav.signing.timestamp if self._signer is not None else None
