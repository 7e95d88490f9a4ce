"""A vehicle's endpoint answering requests: the parameter protocol, missions (vehicles/mavlink/
mission.py), commands, REQUEST_DATA_STREAM, MAVLink FTP (vehicles/mavlink/ftp.py: @PARAM/param.pck)
and TIMESYNC; with an autopilot (:class:`AutopilotPort`, a UAV's vehicles.autopilot) also the
flight: COMMAND_LONG / COMMAND_INT beyond the endpoint's own, SET_MODE, MISSION_SET_CURRENT,
SET_POSITION_TARGET_GLOBAL_INT, MISSION_ITEM_INT with current = 2 / 3 (guided), missions with
home at item 0, and the autopilot's events as MISSION_ITEM_REACHED, MISSION_CURRENT, HEARTBEAT
and STATUSTEXT."""
from __future__ import annotations

import math

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from ..params import ParamError
from ..ftp import addressed_to
from ..mission import MissionItem
from .constants import (_DATA_STREAM_GROUPS, _MAX_PARAMS_PER_STEP, ATTITUDE, AUTOPILOT_VERSION, GLOBAL_POSITION_INT,
                        GPS_RAW_INT, HEARTBEAT, HOME_POSITION, MISSION_CURRENT_PERIOD_S, STREAMS)

_REL_FRAMES = frozenset({mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                         mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT, mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT})
#: SET_POSITION_TARGET_GLOBAL_INT type_mask bits that say "ignore the position"
_POS_IGNORE = (mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE
               | mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE)
_STATUSTEXT_LEN = 50


class AutopilotPort:
    """A UAV endpoint's access to its autopilot: ``source.autopilot`` (a vehicles.autopilot
    Autopilot of the UAV's group, read each time: a resumed group brings its own) and
    ``source.take_events(index, seen_epoch) -> (epoch, events)`` (the events of the group's
    last epoch for this UAV, once); index: the UAV's index in that Autopilot."""

    def __init__(self, source, index: int):
        self.source, self.index = source, int(index)
        self.seen_epoch = -1

    @property
    def ap(self):
        return self.source.autopilot

    def events(self) -> list:
        self.seen_epoch, ev = self.source.take_events(self.index, self.seen_epoch)
        return ev


def _f(v) -> float:
    """A message field as a float (NaN if it is not a number)."""
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


class RequestHandlers:
    """VehicleEndpoint's answers to requests (a part of VehicleEndpoint, not usable alone)."""

    # ------------------------------------------------------------------ params
    def _param_value(self, index: int) -> tuple:
        name = self.params.name_at(index)
        return (name.encode("ascii"), self.params[name], mavlink.MAV_PARAM_TYPE_REAL32, len(self.params), index)

    def _send_params(self) -> None:
        q = self._param_queue
        if not q:
            return
        batch, self._param_queue = q[:_MAX_PARAMS_PER_STEP], q[_MAX_PARAMS_PER_STEP:]
        for addr, index in batch:
            self._send_to(addr, "param_value_send", *self._param_value(index))

    def announce_param(self, name: str) -> None:
        """PARAM_VALUE of ``name`` to the streams' destinations (a value changed by the vehicle)."""
        self._dest = self._stream_dest()
        self.mav.param_value_send(*self._param_value(self.params.index(name)))

    def _on_param_request_list(self, msg, addr) -> None:
        queued = {(a, i) for a, i in self._param_queue}
        self._param_queue += [(addr, i) for i in range(len(self.params)) if (addr, i) not in queued]

    @staticmethod
    def _param_name(raw) -> str:
        if isinstance(raw, bytes):
            raw = raw.decode("ascii", errors="replace")
        return raw.split("\x00", 1)[0]

    def _on_param_request_read(self, msg, addr) -> None:
        try:
            if msg.param_index >= 0:
                index = msg.param_index
                self.params.name_at(index)
            else:
                index = self.params.index(self._param_name(msg.param_id))
        except (ParamError, KeyError):
            self._count("param_unknown")  # the spec: ignore the request (the GCS times out)
            return
        self._send_to(addr, "param_value_send", *self._param_value(index))

    def _on_param_set(self, msg, addr) -> None:
        name = self._param_name(msg.param_id)
        if name not in self.params:
            self._count("param_unknown")
            return
        try:
            self.params.set(name, msg.param_value)
        except ParamError as e:
            self._count(e.reason)  # answered below with the unchanged value
        index = self.params.index(name)
        # the new (or unchanged) value goes to the setter and to the GCS, as ArduPilot does
        self._send_to(addr, "param_value_send", *self._param_value(index))
        if addr != self.gcs:
            self._send_to(self.gcs, "param_value_send", *self._param_value(index))

    # ------------------------------------------------------------------ missions
    def _on_mission_msg(self, msg, addr) -> None:
        if (self.autopilot is not None and msg.get_type() in ("MISSION_ITEM_INT", "MISSION_ITEM")
                and msg.current in (2, 3) and getattr(msg, "mission_type", 0) == mavlink.MAV_MISSION_TYPE_MISSION
                and not self.mission.uploading):
            self._guided_item(msg, addr)
            return
        self.mission.handle(msg, addr, self._t if self._t is not None else 0.0)

    # ------------------------------------------------------------------ commands
    def _ack(self, addr, msg, result: int) -> None:
        self._send_to(addr, "command_ack_send", msg.command, result, 0, 0, msg.get_srcSystem(),
                      msg.get_srcComponent())

    def _on_command(self, msg, addr) -> None:
        cmd = msg.command
        if cmd == mavlink.MAV_CMD_REQUEST_MESSAGE:
            msgid = int(msg.param1) if math.isfinite(msg.param1) else -1
            if msgid not in STREAMS and msgid not in (AUTOPILOT_VERSION, HOME_POSITION):
                self._count("cmd_unsupported")
                self._ack(addr, msg, mavlink.MAV_RESULT_UNSUPPORTED)
            elif (msgid in (GPS_RAW_INT, GLOBAL_POSITION_INT, ATTITUDE) and self.telemetry is None) or \
                    (msgid == HOME_POSITION and self.home is None):
                self._ack(addr, msg, mavlink.MAV_RESULT_TEMPORARILY_REJECTED)
            else:
                self._ack(addr, msg, mavlink.MAV_RESULT_ACCEPTED)
                self._send_message_to(addr, msgid)
        elif cmd == mavlink.MAV_CMD_GET_HOME_POSITION:  # deprecated, but MAVProxy asks it every few seconds
            if self.home is None:
                self._ack(addr, msg, mavlink.MAV_RESULT_TEMPORARILY_REJECTED)
            else:
                self._ack(addr, msg, mavlink.MAV_RESULT_ACCEPTED)
                self._send_message_to(addr, HOME_POSITION)
        elif cmd == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            self._ack(addr, msg, mavlink.MAV_RESULT_ACCEPTED)
            self._send_message_to(addr, AUTOPILOT_VERSION)
        elif cmd == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            msgid = int(msg.param1) if math.isfinite(msg.param1) else -1
            iv_us = msg.param2
            if msgid not in STREAMS:
                self._count("cmd_unsupported")
                self._ack(addr, msg, mavlink.MAV_RESULT_UNSUPPORTED)
            elif not math.isfinite(iv_us) or (iv_us < 0 and iv_us != -1):
                self._ack(addr, msg, mavlink.MAV_RESULT_DENIED)
            else:
                if iv_us == -1:
                    self._interval[msgid] = None
                elif iv_us == 0:
                    self._interval[msgid] = self._default_interval[msgid]
                else:
                    self._interval[msgid] = iv_us * 1e-6
                self._streams_changed(msgid)
                self._ack(addr, msg, mavlink.MAV_RESULT_ACCEPTED)
        elif cmd == mavlink.MAV_CMD_GET_MESSAGE_INTERVAL:
            msgid = int(msg.param1) if math.isfinite(msg.param1) else -1
            if msgid not in STREAMS:
                self._count("cmd_unsupported")
                self._ack(addr, msg, mavlink.MAV_RESULT_UNSUPPORTED)
            else:
                iv = self._interval.get(msgid)
                self._ack(addr, msg, mavlink.MAV_RESULT_ACCEPTED)
                self._send_to(addr, "message_interval_send", msgid, -1 if iv is None else int(round(iv * 1e6)))
        elif self.autopilot is not None:
            self._ap_command(msg, addr)
        else:
            self._count("cmd_unsupported")
            self._ack(addr, msg, mavlink.MAV_RESULT_UNSUPPORTED)

    def _on_request_data_stream(self, msg, addr) -> None:
        ids = (STREAMS[1:] if msg.req_stream_id == mavlink.MAV_DATA_STREAM_ALL
               else _DATA_STREAM_GROUPS.get(msg.req_stream_id, ()))
        for msgid in ids:
            on = msg.start_stop and msg.req_message_rate > 0
            self._interval[msgid] = 1.0 / msg.req_message_rate if on else None
            self._streams_changed(msgid)

    def _on_ftp(self, msg, addr) -> None:
        """MAVLink FTP (vehicles/mavlink/ftp.py): @PARAM/param.pck of this vehicle's parameters."""
        if not addressed_to(msg.target_system, msg.target_component, self.sysid, self.compid):
            self.counters["not_for_us"] += 1
            return
        self.counters["ftp"] += 1
        for args in self.ftp.handle_message(msg, self._t or 0.0, peer=addr):
            self._send_to(addr, "file_transfer_protocol_send", *args)

    def _on_timesync(self, msg, addr) -> None:
        if msg.tc1 == 0:  # a request (tc1 != 0 is someone's answer)
            self._send_to(addr, "timesync_send", int(round(self._unix_s * 1e9)), msg.ts1)

    # ------------------------------------------------------------------ the autopilot (UAVs)
    def _ap_result(self, addr, command: int, res, msg=None) -> None:
        """COMMAND_ACK with the autopilot's code; a refusal counted, its reason as STATUSTEXT."""
        if res.code != mavlink.MAV_RESULT_ACCEPTED:
            self._count("cmd_unsupported" if res.code == mavlink.MAV_RESULT_UNSUPPORTED else "cmd_refused")
            self.last_error = f"command {command}: {res.reason}"
            if res.reason and res.code != mavlink.MAV_RESULT_UNSUPPORTED:
                self._statustext(mavlink.MAV_SEVERITY_WARNING, res.reason, (addr,))
        src = (msg.get_srcSystem(), msg.get_srcComponent()) if msg is not None else (0, 0)
        self._send_to(addr, "command_ack_send", command, res.code, 0, 0, *src)

    def _ap_command(self, msg, addr) -> None:
        ap, i = self.autopilot.ap, self.autopilot.index
        p = [_f(getattr(msg, f"param{k}", math.nan)) for k in range(1, 5)]
        if msg.get_type() == "COMMAND_INT":
            pos, frame = (_f(msg.x) * 1e-7, _f(msg.y) * 1e-7, _f(msg.z)), int(msg.frame)
        else:
            pos, frame = (_f(msg.param5), _f(msg.param6), _f(msg.param7)), None
        res = ap.command(i, int(msg.command), (*p, *pos), frame=frame)
        self._ap_result(addr, int(msg.command), res, msg)
        self._ap_after()

    def _on_set_mode(self, msg, addr) -> None:
        if self.autopilot is None:
            self._count("cmd_unsupported")
            self._send_to(addr, "command_ack_send", mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_RESULT_UNSUPPORTED,
                          0, 0, msg.get_srcSystem(), msg.get_srcComponent())
            return
        res = self.autopilot.ap.set_mode(self.autopilot.index, msg.custom_mode, msg.base_mode)
        # no ACK in the protocol; ArduPilot sends COMMAND_ACK for MAV_CMD_DO_SET_MODE anyway
        self._ap_result(addr, mavlink.MAV_CMD_DO_SET_MODE, res, msg)
        self._ap_after()

    def _on_mission_set_current(self, msg, addr) -> None:
        if self.autopilot is None:
            self._count("mission_rejected")
            return
        res = self.autopilot.ap.set_current(self.autopilot.index, msg.seq)
        if not res.ok:
            self._count("mission_rejected")
            self.last_error = f"MISSION_SET_CURRENT {msg.seq}: {res.reason}"
            self._statustext(mavlink.MAV_SEVERITY_WARNING, res.reason, (addr,))
        self._ap_after()

    def _on_set_position_target(self, msg, addr) -> None:
        """SET_POSITION_TARGET_GLOBAL_INT: GUIDED's target (in GUIDED only, no ACK: ArduPlane)."""
        if self.autopilot is None or (int(msg.type_mask) & _POS_IGNORE) == _POS_IGNORE:
            self._count("cmd_unsupported")
            return
        lat, lon = _f(msg.lat_int) * 1e-7, _f(msg.lon_int) * 1e-7
        res = self.autopilot.ap.goto(self.autopilot.index, math.radians(lat), math.radians(lon), _f(msg.alt),
                                     relative_alt=int(msg.coordinate_frame) in _REL_FRAMES, change_mode=False)
        if not res.ok:
            self._count("cmd_refused")
            self.last_error = f"SET_POSITION_TARGET_GLOBAL_INT: {res.reason}"
        self._ap_after()

    def _guided_item(self, msg, addr) -> None:
        """MISSION_ITEM_INT / MISSION_ITEM with current = 2 (MAVProxy's ``guided``) or 3 (altitude
        only) outside an upload: MISSION_ACK with the autopilot's code (ArduPilot)."""
        it = msg
        if msg.get_type() == "MISSION_ITEM":
            x, y = _f(msg.x), _f(msg.y)
            it = MissionItem(msg.seq, msg.frame, msg.command, msg.current, msg.autocontinue, msg.param1, msg.param2,
                             msg.param3, msg.param4, x * 1e7 if math.isfinite(x) else math.nan,
                             y * 1e7 if math.isfinite(y) else math.nan, msg.z)
        res = self.autopilot.ap.guided_item(self.autopilot.index, it)
        if res.code != mavlink.MAV_MISSION_ACCEPTED:
            self._count("mission_rejected")
            self.last_error = f"guided: {res.reason}"
        self._send_to(addr, "mission_ack_send", msg.get_srcSystem(), msg.get_srcComponent(), res.code,
                      mavlink.MAV_MISSION_TYPE_MISSION)
        self._ap_after()

    def _mission_items(self, items) -> tuple[int, str]:
        """The MissionServer's hook: a complete upload to the autopilot (item 0 home)."""
        res = self.autopilot.ap.set_mission(self.autopilot.index, items)
        if res.code != mavlink.MAV_MISSION_ACCEPTED:
            self.last_error = f"mission: {res.reason}"
            self._statustext(mavlink.MAV_SEVERITY_WARNING, res.reason)
        else:
            self._mission_current_due = -math.inf
        return res.code, res.reason

    def _mission_item_check(self, k: int, item, n: int) -> tuple[int, str]:
        """The MissionServer's per-item hook: item k of an n-item upload as it arrives, by the
        autopilot's rules; a refusal is said (last_error, STATUSTEXT naming the item) and ends
        the upload with its MISSION_ACK code."""
        res = self.autopilot.ap.check_item(k, item, n)
        if res.code != mavlink.MAV_MISSION_ACCEPTED:
            self.last_error = f"mission: {res.reason}"
            self._statustext(mavlink.MAV_SEVERITY_WARNING, res.reason)
        return res.code, res.reason

    def _home_item(self):
        """Mission item 0 for a download: home now (ArduPilot), MSL height."""
        ap = self.autopilot.ap
        la, lo, h = (float(v) for v in ap.home[self.autopilot.index])
        return MissionItem(0, mavlink.MAV_FRAME_GLOBAL_INT, mavlink.MAV_CMD_NAV_WAYPOINT, 0, 1, 0.0, 0.0, 0.0, 0.0,
                           int(round(math.degrees(la) * 1e7)), int(round(math.degrees(lo) * 1e7)), h)

    def _ap_after(self) -> None:
        """After an operation: the streams carry the new state at once (HEARTBEAT, MISSION_CURRENT)."""
        self._heartbeat_now = True
        self._mission_current_due = -math.inf

    def _statustext(self, severity: int, text: str, dest=None) -> None:
        raw = " ".join(str(text).split()).encode("ascii", "replace")[:_STATUSTEXT_LEN]
        if dest is None:
            self.mav.statustext_send(int(severity), raw)
        else:
            for a in dest:
                self._send_to(a, "statustext_send", int(severity), raw)

    def _send_mission_current(self) -> None:
        st = self.autopilot.ap.mission_status()
        i = self.autopilot.index
        self.mav.mission_current_send(int(st.seq[i]), int(st.total[i]), int(st.state[i]), 0)

    def _autopilot_out(self, t: float) -> None:
        """The autopilot's events of the last epoch, then MISSION_CURRENT when due (to the streams'
        destinations; called before the streams each step)."""
        if self.autopilot is None:
            return
        self._dest = self._stream_dest()
        for e in self.autopilot.events():
            if e.kind == "item_reached":
                self.mav.mission_item_reached_send(int(e.value))
            elif e.kind == "mission_current":
                self._mission_current_due = -math.inf
            elif e.kind in ("mode", "armed", "disarmed", "landed", "takeoff_complete"):
                self._heartbeat_now = True
            if e.text:
                self._statustext(e.severity, e.text)
        if self._heartbeat_now:
            self._heartbeat_now = False
            self._send_message(HEARTBEAT)
        if t >= self._mission_current_due - 1e-6:
            self._send_mission_current()
            self._mission_current_due = t + MISSION_CURRENT_PERIOD_S
