"""A vehicle's endpoint sending: the destinations of what it sends (the GCS, recent peers, a
requester), the tlog, and the streams that fall due at a step."""
from __future__ import annotations

import functools
import math
import subprocess
from pathlib import Path

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from .. import telemetry as tm
from .constants import (ATTITUDE, AUTOPILOT_VERSION, CAPABILITIES, FLIGHT_SW_VERSION, FRAME_REJECT_REASONS,
                        GLOBAL_POSITION_INT, GPS_RAW_INT, HEARTBEAT, HOME_POSITION, STREAMS, SYS_STATUS, SYSTEM_TIME,
                        _DUE_TOL_S, _SENSORS)


#: the fastest stream: one message per vehicle epoch (run.rate_hz); an endpoint may set epoch_s
DEFAULT_EPOCH_S = 0.1


@functools.cache
def flight_custom_version() -> list[int]:
    """flight_custom_version: the first 8 bytes of the source's git commit hash (as ArduPilot
    puts its git hash there), zeros outside a git checkout. Read once, at the first use."""
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).resolve().parent,
                             capture_output=True, text=True, timeout=2.0).stdout.strip()
        return list(bytes.fromhex(out[:16])) if len(out) >= 16 else [0] * 8
    except (OSError, ValueError, subprocess.SubprocessError):
        return [0] * 8


class StreamOutput:
    """VehicleEndpoint's output side (a part of VehicleEndpoint, not usable alone)."""

    def write(self, buf: bytes) -> None:
        """pymavlink's MAVLink.send writes here: to every current destination, and the tlog."""
        # the frame was signed with timestamp - 1: nothing above the persisted bound leaves unsaved
        if self._state_file is not None and self.mav.signing.timestamp > self._reserved + 1:
            self._reserve()
        for addr in self._dest:
            try:
                self.sock.sendto(buf, addr)
            except OSError:  # full socket buffer, unreachable: a lost datagram, as on a radio
                self.counters["send_errors"] += 1
                continue
            self.counters["sent"] += 1
            self.counters["tx_bytes"] += len(buf)
        if self._tlog is not None:
            self._tlog.write(self._unix_s, buf)

    def _send_to(self, addr, send_name: str, *args) -> None:
        self._dest = (addr,)
        try:
            getattr(self.mav, send_name)(*args)
        finally:
            self._dest = self._stream_dest()

    def _send_message_to(self, addr, msgid: int) -> bool:
        self._dest = (addr,)
        try:
            return self._send_message(msgid)
        finally:
            self._dest = self._stream_dest()

    def _stream_dest(self) -> tuple:
        return (self.gcs, *[a for a in self._peers if a != self.gcs])

    # ------------------------------------------------------------------ streams
    def _send_streams(self, t: float) -> None:
        if t < self._next_due - _DUE_TOL_S:  # most steps at 10 Hz: nothing due
            return
        self._dest = self._stream_dest()
        nxt = math.inf
        for msgid in STREAMS:
            iv = self._interval.get(msgid)
            if iv is None:
                continue
            due = self._due.get(msgid)
            if due is None or t >= due - _DUE_TOL_S:
                if self._send_message(msgid):
                    # keep the phase; if we fell more than an interval behind, restart from now
                    if due is None:  # first send: now, the next one spread by the vehicle's phase
                        due = t + iv * (1.0 - self._phase_frac)
                    else:
                        due = t + iv if t - due >= iv else due + iv
                    self._due[msgid] = due
                else:
                    due = t  # nothing to send yet (no telemetry): try again next step
            nxt = min(nxt, due)
        self._next_due = nxt

    # ------------------------------------------------------------------ stream requests
    def set_interval(self, msg_id, interval_us) -> int:
        """MAV_CMD_SET_MESSAGE_INTERVAL / SET_MESSAGE_INTERVAL semantics -> MAV_RESULT.
        interval_us: -1 stops the stream, 0 restores its default, > 0 sets it (us), clamped to
        one vehicle epoch (``epoch_s``, 0.1 s unless set). NaN, other negatives: DENIED; a message
        id that is not a stream: UNSUPPORTED; both counted. Never raises."""
        try:
            msgid = int(msg_id) if math.isfinite(float(msg_id)) else -1
            iv_us = float(interval_us)
        except (TypeError, ValueError, OverflowError):
            self._count("interval_bad")
            return mavlink.MAV_RESULT_DENIED
        if msgid not in STREAMS:
            self._count("cmd_unsupported")
            return mavlink.MAV_RESULT_UNSUPPORTED
        if not math.isfinite(iv_us) or (iv_us < 0 and iv_us != -1):
            self._count("interval_bad")
            return mavlink.MAV_RESULT_DENIED
        if iv_us == -1:
            self._interval[msgid] = None
        elif iv_us == 0:
            self._interval[msgid] = self._default_interval[msgid]
        else:
            self._interval[msgid] = max(iv_us * 1e-6, getattr(self, "epoch_s", DEFAULT_EPOCH_S))
        self._streams_changed(msgid)
        return mavlink.MAV_RESULT_ACCEPTED

    def request_message(self, msg_id, addr=None) -> int:
        """MAV_CMD_REQUEST_MESSAGE -> MAV_RESULT; on ACCEPTED the message is sent at once (to addr,
        or to the stream destinations). Unknown id: UNSUPPORTED (counted); no data yet (no
        telemetry, no home): TEMPORARILY_REJECTED. Never raises."""
        try:
            msgid = int(msg_id) if math.isfinite(float(msg_id)) else -1
        except (TypeError, ValueError, OverflowError):
            msgid = -1
        if msgid not in STREAMS and msgid not in (AUTOPILOT_VERSION, HOME_POSITION):
            self._count("cmd_unsupported")
            return mavlink.MAV_RESULT_UNSUPPORTED
        if addr is None:
            self._dest = self._stream_dest()
            ok = self._send_message(msgid)
        else:
            ok = self._send_message_to(addr, msgid)
        return mavlink.MAV_RESULT_ACCEPTED if ok else mavlink.MAV_RESULT_TEMPORARILY_REJECTED

    def _streams_changed(self, msgid: int) -> None:
        self._due.pop(msgid, None)
        self._next_due = -math.inf

    def _send_message(self, msgid: int) -> bool:
        """Send one message now to the current destinations; False if we cannot (no data)."""
        mav, tel = self.mav, self.telemetry
        if msgid == HEARTBEAT:
            armed = tel is None or tel.armed
            base = mavlink.MAV_MODE_FLAG_AUTO_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED
                                                         if tel is not None and armed else 0)
            status = mavlink.MAV_STATE_ACTIVE if tel is not None and armed else mavlink.MAV_STATE_STANDBY
            mav.heartbeat_send(self._mav_type, mavlink.MAV_AUTOPILOT_GENERIC, base, 0, status)
        elif msgid == SYSTEM_TIME:
            mav.system_time_send(int(round(self._unix_s * 1e6)), self.time_boot_ms & tm.UINT32_MAX)
        elif msgid == SYS_STATUS:
            mv, pct = tm.battery_fields(tel) if tel is not None else (tm.UINT16_MAX, -1)
            gps_ok = tel is not None and tel.fix_type >= mavlink.GPS_FIX_TYPE_2D_FIX
            errors = sum(self.counters[r] for r in FRAME_REJECT_REASONS) + self.datagrams["kernel_dropped"]
            mav.sys_status_send(_SENSORS, _SENSORS, _SENSORS if gps_ok else 0, 0, mv, -1, pct, 0,
                                min(errors, tm.UINT16_MAX), 0, 0, 0, 0)
        elif msgid == AUTOPILOT_VERSION:
            mav.autopilot_version_send(CAPABILITIES, FLIGHT_SW_VERSION, 0, 0, 0, flight_custom_version(), [0] * 8,
                                       [0] * 8, 0, 0, 0x534B_5946_0000_0000 | self.sysid)
        elif msgid == HOME_POSITION:
            if self.home is None:
                return False
            la, lo, h = self.home
            mav.home_position_send(tm.deg_e7(la), tm.deg_e7(lo), tm.mm(h), 0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0],
                                   0.0, 0.0, 0.0, int(round(self._unix_s * 1e6)))
        elif tel is None:
            return False
        elif msgid == GPS_RAW_INT:
            mav.gps_raw_int_send(*tm.gps_raw_int_fields(tel, int(round(self._unix_s * 1e6))))
        elif msgid == GLOBAL_POSITION_INT:
            mav.global_position_int_send(*tm.global_position_int_fields(tel, self.time_boot_ms,
                                                                         self.home_alt_msl_m or 0.0))
        elif msgid == ATTITUDE:
            mav.attitude_send(*tm.attitude_fields(tel, self.time_boot_ms))
        else:
            return False
        return True
