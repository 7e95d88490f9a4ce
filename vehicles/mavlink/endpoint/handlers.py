"""A vehicle's endpoint answering requests: the parameter protocol, missions (vehicles/mavlink/
mission.py), commands, REQUEST_DATA_STREAM, MAVLink FTP (refused) and TIMESYNC."""
from __future__ import annotations

import math

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from ..params import ParamError
from .constants import (_DATA_STREAM_GROUPS, _FTP_ACK, _FTP_ERR_FILE_NOT_FOUND, _FTP_ERR_UNKNOWN_COMMAND,
                        _FTP_LIST_DIRECTORY, _FTP_NAK, _FTP_OPEN_FILE_RO, _FTP_RESET_SESSIONS,
                        _FTP_TERMINATE_SESSION, _MAX_PARAMS_PER_STEP, ATTITUDE, AUTOPILOT_VERSION,
                        GLOBAL_POSITION_INT, GPS_RAW_INT, HOME_POSITION, STREAMS)


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
        """No MAVLink FTP here: NAK every request at once, so that a GCS that tries FTP first
        (MAVProxy's parameter download: OpenFileRO @PARAM/param.pck) falls back to the
        parameter protocol without waiting for its timeouts."""
        p = bytes(msg.payload)
        if len(p) < 12:
            self._count("malformed")
            return
        seq, session, opcode = int.from_bytes(p[0:2], "little"), p[2], p[3]
        if opcode in (_FTP_TERMINATE_SESSION, _FTP_RESET_SESSIONS):
            op, size, data = _FTP_ACK, 0, b""
        else:
            err = _FTP_ERR_FILE_NOT_FOUND if opcode in (_FTP_LIST_DIRECTORY, _FTP_OPEN_FILE_RO) else _FTP_ERR_UNKNOWN_COMMAND
            op, size, data = _FTP_NAK, 1, bytes([err])
        reply = ((seq + 1) & 0xFFFF).to_bytes(2, "little") + bytes([session, op, size, opcode, 0, 0]) \
            + bytes(4) + data
        self.counters["ftp_refused"] += 1
        self._send_to(addr, "file_transfer_protocol_send", 0, msg.get_srcSystem(), msg.get_srcComponent(),
                      list(reply.ljust(251, b"\x00")))

    def _on_timesync(self, msg, addr) -> None:
        if msg.tc1 == 0:  # a request (tc1 != 0 is someone's answer)
            self._send_to(addr, "timesync_send", int(round(self._unix_s * 1e9)), msg.ts1)
