"""A vehicle's endpoint sending: the destinations of what it sends (the GCS, recent peers, a
requester), the tlog, and the streams that fall due at a step."""
from __future__ import annotations

import functools
import math
import subprocess
from pathlib import Path

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from .. import telemetry as tm
from .constants import (_DATA_STREAM_GROUPS, ATTITUDE, AUTOPILOT_VERSION, CAPABILITIES, FLIGHT_SW_VERSION, FRAME_REJECT_REASONS,
                        GLOBAL_POSITION_INT, GPS_RAW_INT, HEARTBEAT, HOME_POSITION, STREAMS, SYS_STATUS, SYSTEM_TIME,
                        _DUE_TOL_S)


VFR_HUD, EXTENDED_SYS_STATE, BATTERY_STATUS = 74, 245, 147
NAV_CONTROLLER_OUTPUT, EKF_STATUS_REPORT = 62, 193
#: streams beside constants.STREAMS, with their default rates, Hz (ArduPilot's REQUEST_DATA_STREAM
#: group of each: VFR_HUD EXTRA2, EXTENDED_SYS_STATE and NAV_CONTROLLER_OUTPUT EXTENDED_STATUS,
#: BATTERY_STATUS and EKF_STATUS_REPORT EXTRA3; HOME_POSITION none, MAVProxy asks for it)
EXTRA_STREAM_RATES_HZ = {VFR_HUD: 2.0, EXTENDED_SYS_STATE: 1.0, BATTERY_STATUS: 1.0, HOME_POSITION: 0.2,
                         NAV_CONTROLLER_OUTPUT: 1.0, EKF_STATUS_REPORT: 1.0}
EXTRA_DATA_STREAM_GROUPS = {mavlink.MAV_DATA_STREAM_EXTENDED_STATUS: (EXTENDED_SYS_STATE, NAV_CONTROLLER_OUTPUT),
                            mavlink.MAV_DATA_STREAM_EXTRA2: (VFR_HUD,),
                            mavlink.MAV_DATA_STREAM_EXTRA3: (BATTERY_STATUS, EKF_STATUS_REPORT)}
#: SYS_STATUS: sensors present and enabled; GEOFENCE is not present, but its health bit is set
#: (ArduPilot sets it unless breached: MAVProxy's fence module says "fence breach" when it is clear)
SENSORS_PRESENT = mavlink.MAV_SYS_STATUS_SENSOR_GPS | mavlink.MAV_SYS_STATUS_AHRS
#: the fastest stream: one message per vehicle epoch (run.rate_hz); an endpoint may set epoch_s
DEFAULT_EPOCH_S = 0.1


#: EKF_STATUS_REPORT flags that say the filter navigates (position and velocity known)
_EKF_NAV_FLAGS = mavlink.EKF_VELOCITY_HORIZ | mavlink.EKF_POS_HORIZ_ABS


def sensor_health(tel, battery_ok: bool) -> int:
    """SYS_STATUS onboard_control_sensors_health, consistent with what the other messages say:
    GPS healthy with a 3D fix (GPS_RAW_INT.fix_type >= 3); AHRS healthy when the onboard filter
    navigates (EKF_STATUS_REPORT has velocity and absolute horizontal position, and not every
    test ratio fails its gate: NavEKF3_core::healthy), or, without a filter status, when there is
    telemetry; the battery while it has charge left; GEOFENCE always (no fence: never breached,
    as ArduPilot reports it)."""
    h = mavlink.MAV_SYS_STATUS_GEOFENCE
    if tel is None:
        return h
    if tel.fix_type >= mavlink.GPS_FIX_TYPE_3D_FIX:
        h |= mavlink.MAV_SYS_STATUS_SENSOR_GPS
    ekf = getattr(tel, "ekf", None)
    if ekf is None:
        h |= mavlink.MAV_SYS_STATUS_AHRS
    elif (ekf.flags & _EKF_NAV_FLAGS) == _EKF_NAV_FLAGS and not (ekf.flags & mavlink.EKF_UNINITIALIZED) and \
            not (ekf.vel_test_ratio > 1 and ekf.pos_test_ratio > 1 and ekf.hgt_test_ratio > 1):
        h |= mavlink.MAV_SYS_STATUS_AHRS
    if battery_ok:
        h |= mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
    return h


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
    """VehicleEndpoint's output side (a part of VehicleEndpoint, not usable alone).

    Hooks the vehicle worker may set on an endpoint: ``landed_state_fn()`` -> MAV_LANDED_STATE
    (None: IN_AIR when armed with telemetry, ON_GROUND otherwise), ``battery`` (a
    vehicles.mavlink.battery.Battery, stepped here with the telemetry's airspeed (its ground
    speed without one); or a battery stepped by its owner, e.g. a BatteryBank's ``cell(j)``,
    which has no ``step`` and is only read), ``epoch_s`` (the fastest stream interval).

    COMMAND_LONG / COMMAND_INT MAV_CMD_SET_MESSAGE_INTERVAL, MAV_CMD_GET_MESSAGE_INTERVAL and
    MAV_CMD_REQUEST_MESSAGE are answered here (:meth:`_on_command`, ahead of RequestHandlers'
    in VehicleEndpoint's MRO), so they reach every stream, the extra ones included, with the
    epoch clamp; every other command goes on to RequestHandlers."""

    landed_state_fn = None
    battery = None
    _extras_ready = False

    def _ensure_extras(self) -> None:
        if self._extras_ready:
            return
        self._extras_ready = True
        for k, hz in EXTRA_STREAM_RATES_HZ.items():
            self._default_interval.setdefault(k, 1.0 / hz)
            self._interval.setdefault(k, self._default_interval[k])

    def _streams_all(self) -> tuple:
        return (*STREAMS, *[k for k in EXTRA_STREAM_RATES_HZ if k not in STREAMS])

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
            self.counters["sent"] += 1  # frames (a packed stream datagram holds several: batch.py)
            self.counters["tx_datagrams"] += 1
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
    def _send_streams(self, t: float, batch=None) -> None:
        """The streams due at t, sent now, or recorded in batch (a StreamBatch: framed and sent
        with the group's at the end of its step) when the output is unsigned."""
        self._ensure_extras()
        tel = self.telemetry
        if self.battery is not None and tel is not None and hasattr(self.battery, "step"):
            v = getattr(tel, "airspeed_m_s", None)
            self.battery.step(t, math.hypot(*tel.vel_ned_m_s[:2]) if v is None else v, tel.armed)
        if t < self._next_due - _DUE_TOL_S:  # most steps at 10 Hz: nothing due
            return
        self._dest = self._stream_dest()
        nxt = math.inf
        real = self.mav
        if batch is not None and not real.signing.sign_outgoing:
            self.mav = batch.recorder(self, real)  # every <message>_send below is recorded
        try:
            nxt = self._stream_pass(t, nxt)
        finally:
            self.mav = real
        self._next_due = nxt

    def _stream_pass(self, t: float, nxt: float) -> float:
        for msgid in self._streams_all():
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
        return nxt

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
        self._ensure_extras()
        if msgid not in self._streams_all():
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

    def request_data_stream(self, stream_id, rate_hz, start_stop) -> None:
        """REQUEST_DATA_STREAM (MAVProxy's ``streamrate``): every stream of the group (ALL: every
        stream but HEARTBEAT) at rate_hz, at most one per vehicle epoch; stop: off. Bad input
        (a NaN rate, an unknown group) changes nothing and is counted."""
        self._ensure_extras()
        try:
            sid, hz = int(stream_id), float(rate_hz)
        except (TypeError, ValueError, OverflowError):
            self._count("interval_bad")
            return
        if sid == mavlink.MAV_DATA_STREAM_ALL:
            ids = [k for k in self._streams_all() if k != HEARTBEAT]
        else:
            ids = [*_DATA_STREAM_GROUPS.get(sid, ()), *EXTRA_DATA_STREAM_GROUPS.get(sid, ())]
        if not ids or not math.isfinite(hz) or hz < 0:
            self._count("interval_bad")
            return
        on = bool(start_stop) and hz > 0
        for msgid in ids:
            self._interval[msgid] = max(1.0 / hz, getattr(self, "epoch_s", DEFAULT_EPOCH_S)) if on else None
            self._streams_changed(msgid)

    def _on_command(self, msg, addr) -> None:
        """The stream commands (class docstring); COMMAND_ACK with the MAV_RESULT, counted when
        refused, never raises; anything else: RequestHandlers._on_command."""
        cmd = msg.command
        if cmd == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            self._ack(addr, msg, self.set_interval(msg.param1, msg.param2))
        elif cmd == mavlink.MAV_CMD_GET_MESSAGE_INTERVAL:
            try:
                msgid = int(msg.param1) if math.isfinite(float(msg.param1)) else -1
            except (TypeError, ValueError, OverflowError):
                msgid = -1
            self._ensure_extras()
            if msgid not in self._streams_all():
                self._count("cmd_unsupported")
                self._ack(addr, msg, mavlink.MAV_RESULT_UNSUPPORTED)
                return
            iv = self._interval.get(msgid)
            self._ack(addr, msg, mavlink.MAV_RESULT_ACCEPTED)
            self._send_to(addr, "message_interval_send", msgid, -1 if iv is None else int(round(iv * 1e6)))
        elif cmd == mavlink.MAV_CMD_REQUEST_MESSAGE:
            # the message first, then the ACK (ArduPilot's order: it sends while handling)
            self._ack(addr, msg, self.request_message(msg.param1, addr))
        else:
            super()._on_command(msg, addr)

    def _on_request_data_stream(self, msg, addr) -> None:
        """REQUEST_DATA_STREAM: this one (StreamOutput precedes RequestHandlers in VehicleEndpoint's
        MRO) knows the extra streams and the epoch clamp."""
        self.request_data_stream(msg.req_stream_id, msg.req_message_rate, msg.start_stop)

    def request_message(self, msg_id, addr=None) -> int:
        """MAV_CMD_REQUEST_MESSAGE -> MAV_RESULT; on ACCEPTED the message is sent at once (to addr,
        or to the stream destinations). Unknown id: UNSUPPORTED (counted); no data yet (no
        telemetry, no home): TEMPORARILY_REJECTED. Never raises."""
        try:
            msgid = int(msg_id) if math.isfinite(float(msg_id)) else -1
        except (TypeError, ValueError, OverflowError):
            msgid = -1
        self._ensure_extras()
        if msgid not in self._streams_all() and msgid != AUTOPILOT_VERSION:
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
            errors = sum(self.counters[r] for r in FRAME_REJECT_REASONS) + self.datagrams["kernel_dropped"]
            present = SENSORS_PRESENT | (mavlink.MAV_SYS_STATUS_SENSOR_BATTERY if self.battery is not None else 0)
            ma = -1
            batt_ok = False
            if self.battery is not None:
                b = self.battery
                mv, pct = min(int(round(b.voltage_v * 1000)), tm.UINT16_MAX - 1), int(round(b.remaining_pct))
                ma = min(int(round(b.current_a * 100)), tm.INT16_MAX)  # cA
                batt_ok = b.remaining_pct > 0.0
            mav.sys_status_send(present, present, sensor_health(tel, batt_ok), 0, mv, ma, pct, 0,
                                min(errors, tm.UINT16_MAX), 0, 0, 0, 0)
        elif msgid == AUTOPILOT_VERSION:
            mav.autopilot_version_send(CAPABILITIES, FLIGHT_SW_VERSION, 0, 0, 0, flight_custom_version(), [0] * 8,
                                       [0] * 8, 0, 0, 0x534B_5946_0000_0000 | (self.instance + 1))  # unique in the fleet
        elif msgid == HOME_POSITION:
            if self.home is None:
                return False
            la, lo, h = self.home
            mav.home_position_send(tm.deg_e7(la), tm.deg_e7(lo), tm.mm(h), 0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0],
                                   0.0, 0.0, 0.0, int(round(self._unix_s * 1e6)))
        elif tel is None:
            return False
        elif msgid == VFR_HUD:
            vn, ve, vd = tel.vel_ned_m_s
            gs = math.hypot(vn, ve)
            air = getattr(tel, "airspeed_m_s", None)
            # airspeed, groundspeed m/s; heading deg 0..359; throttle %; alt MSL m; climb m/s (up)
            mav.vfr_hud_send(float(gs if air is None else air), float(gs),
                             int(round(math.degrees(tel.yaw_rad))) % 360, 0 if not tel.armed else 50,
                             float(tel.alt_msl_m), float(-vd))
        elif msgid == EXTENDED_SYS_STATE:
            fn = self.landed_state_fn
            if fn is not None:
                landed = int(fn())
            else:
                landed = mavlink.MAV_LANDED_STATE_IN_AIR if tel.armed else mavlink.MAV_LANDED_STATE_ON_GROUND
            mav.extended_sys_state_send(mavlink.MAV_VTOL_STATE_UNDEFINED, landed)
        elif msgid == BATTERY_STATUS:
            b = self.battery
            if b is None:
                return False
            # voltages mV (cell 0: the pack; the rest UINT16_MAX), current cA, consumed mAh, energy hJ, %
            mav.battery_status_send(0, mavlink.MAV_BATTERY_FUNCTION_ALL, mavlink.MAV_BATTERY_TYPE_LIPO, tm.INT16_MAX,
                                    [min(int(round(b.voltage_v * 1000)), tm.UINT16_MAX - 1)] + [tm.UINT16_MAX] * 9,
                                    min(int(round(b.current_a * 100)), tm.INT16_MAX), int(round(b.consumed_mah)),
                                    int(round(b.consumed_wh * 36.0)), int(round(b.remaining_pct)))
        elif msgid == NAV_CONTROLLER_OUTPUT:
            nav = getattr(tel, "nav", None)
            if nav is None:  # no guidance to report (the sonde; ArduPlane in MANUAL)
                return False
            mav.nav_controller_output_send(*tm.nav_controller_output_fields(nav))
        elif msgid == EKF_STATUS_REPORT:
            ekf = getattr(tel, "ekf", None)
            if ekf is None:
                return False
            mav.ekf_status_report_send(*tm.ekf_status_report_fields(ekf))
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
