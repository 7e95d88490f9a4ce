"""A vehicle's MAVLink 2 endpoint over UDP, and a group of them stepped in one process.

Each endpoint is one non-blocking UDP socket bound to its listen address; it sends its
telemetry to the ground-control endpoint (default 127.0.0.1:14550) and to every peer that
has sent it an accepted packet lately (a GCS that connects straight to the vehicle's port,
as ``mavproxy.py --master udpout:127.0.0.1:5760`` does); replies go to the requester.

Ports (ArduPilot SITL's convention: ``-I N`` "adds 10*instance to all port numbers", the
first MAVLink port being 5760): by default vehicle instance N listens on UDP
``5760 + 10 N`` (:func:`listen_port`), with system id N + 1.  UDP rather than SITL's TCP
because the vehicle also talks first (to 14550), as a real radio link does.

Everything is a step function of SIMULATION time: ``step(t_gps_s, telemetry)`` reads what
has arrived (never blocks), answers it, runs the mission-upload timeouts and sends the
streams that are due.  Never a sleep, never the wall clock.

What a GCS gets (ArduPilot SITL's behaviour, and what QGroundControl's initial-connect
state machine asks for, see vehicles/mavlink/__init__.py):
  streams       HEARTBEAT 1 Hz, SYS_STATUS, SYSTEM_TIME, GPS_RAW_INT, GLOBAL_POSITION_INT,
                ATTITUDE at ``stream_rates_hz``; changed by SET_MESSAGE_INTERVAL and
                REQUEST_DATA_STREAM (MAVProxy's ``streamrate``)
  commands      COMMAND_LONG / COMMAND_INT -> COMMAND_ACK: REQUEST_MESSAGE (the streams,
                AUTOPILOT_VERSION, HOME_POSITION), SET_MESSAGE_INTERVAL, GET_MESSAGE_INTERVAL,
                REQUEST_AUTOPILOT_CAPABILITIES, GET_HOME_POSITION ACCEPTED (+ the message);
                every other command, and REQUEST_MESSAGE of anything else, UNSUPPORTED at once
  params        PARAM_REQUEST_LIST / _READ / PARAM_SET over a ParamStore
  missions      see mission.py
  MAVLink FTP   refused at once (NAK), so that MAVProxy falls back to the parameter protocol
  TIMESYNC      tc1 = our (simulated unix) time in ns, ts1 echoed
  signing       optional; unsigned / wrongly signed / replayed packets rejected.  Our
                signing timestamps follow the simulated clock and jump to any accepted peer's
                timestamp that is ahead (as pymavlink does), so a GCS on the wall clock
                accepts our replies; until a GCS has sent us a signed packet, a simulated
                date more than a minute behind its clock makes it drop our streams as an
                old stream (it recovers with its first heartbeat)

Counters (``counters``): REJECT_REASONS count rejected inputs; TRAFFIC_COUNTERS the rest.
An exception inside a handler is counted (``handler_errors``, ``last_error``), never raised.
"""
from __future__ import annotations

import math
import selectors
import socket
from typing import Callable, Iterable, Sequence

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from . import telemetry as tm
from .framing import SignatureChecker, TlogWriter, split_datagram
from .mission import MissionServer
from .params import ParamError, ParamStore
from .telemetry import VehicleTelemetry

BASE_PORT = 5760
PORT_STRIDE = 10
DEFAULT_GCS = ("127.0.0.1", 14550)

#: counters that count rejected inputs (the rest count traffic)
REJECT_REASONS = ("garbage", "truncated", "bad_crc", "unknown_msgid", "malformed", "unsupported_flags",
                  "unsigned", "bad_signature", "replayed", "param_unknown", "param_rejected",
                  "mission_rejected", "mission_timeout")
TRAFFIC_COUNTERS = ("rx_datagrams", "rx_bytes", "received", "not_for_us", "sent", "tx_bytes", "send_errors",
                    "cmd_unsupported", "ftp_refused", "handler_errors")

KINDS = {
    "uav": mavlink.MAV_TYPE_FIXED_WING,
    "sonde": mavlink.MAV_TYPE_FREE_BALLOON,
}

# MAVLink units / ids of the streams an endpoint can send
HEARTBEAT, SYS_STATUS, SYSTEM_TIME = 0, 1, 2
GPS_RAW_INT, ATTITUDE, GLOBAL_POSITION_INT = 24, 30, 33
AUTOPILOT_VERSION = 148
HOME_POSITION = 242
STREAMS = (HEARTBEAT, SYS_STATUS, SYSTEM_TIME, GPS_RAW_INT, ATTITUDE, GLOBAL_POSITION_INT)
DEFAULT_STREAM_RATES_HZ = {HEARTBEAT: 1.0, SYS_STATUS: 1.0, SYSTEM_TIME: 1.0, GPS_RAW_INT: 2.0,
                           ATTITUDE: 4.0, GLOBAL_POSITION_INT: 4.0}
# REQUEST_DATA_STREAM groups (ArduPilot's assignment of our streams)
_DATA_STREAM_GROUPS = {
    mavlink.MAV_DATA_STREAM_EXTENDED_STATUS: (SYS_STATUS, GPS_RAW_INT),
    mavlink.MAV_DATA_STREAM_POSITION: (GLOBAL_POSITION_INT,),
    mavlink.MAV_DATA_STREAM_EXTRA1: (ATTITUDE,),
    mavlink.MAV_DATA_STREAM_EXTRA3: (SYSTEM_TIME,),
}

CAPABILITIES = (mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
                | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT)
#: skyfuse 0.1.0, FIRMWARE_VERSION_TYPE_DEV (major << 24 | minor << 16 | patch << 8 | type)
FLIGHT_SW_VERSION = (0 << 24) | (1 << 16) | (0 << 8) | mavlink.FIRMWARE_VERSION_TYPE_DEV

_SENSORS = mavlink.MAV_SYS_STATUS_SENSOR_GPS
# MAVLink FTP (mavlink.io "File Transfer Protocol"): opcodes and errors used to refuse it
_FTP_TERMINATE_SESSION, _FTP_RESET_SESSIONS, _FTP_LIST_DIRECTORY, _FTP_OPEN_FILE_RO = 1, 2, 3, 4
_FTP_ACK, _FTP_NAK = 128, 129
_FTP_ERR_UNKNOWN_COMMAND, _FTP_ERR_FILE_NOT_FOUND = 7, 10
_MAX_DATAGRAMS_PER_STEP = 256
_MAX_PARAMS_PER_STEP = 64
_MAX_PEERS = 8
_PEER_TIMEOUT_S = 60.0
_RECV_SIZE = 65535
# GPS seconds ~1.4e9 carry ~2.4e-7 s of float rounding: a stream is due 1 us early
_DUE_TOL_S = 1e-6


def listen_port(instance: int, base_port: int = BASE_PORT) -> int:
    """ArduPilot SITL's convention: base port + 10 x instance."""
    if isinstance(instance, bool) or int(instance) != instance or instance < 0:
        raise ValueError(f"instance must be an integer >= 0, got {instance!r}")
    port = int(base_port) + PORT_STRIDE * int(instance)
    if not 0 < port < 65536:
        raise ValueError(f"listen port {port} (base {base_port} + 10 x {instance}) is not a valid UDP port")
    return port


def _check_addr(name: str, addr) -> tuple[str, int]:
    try:
        host, port = addr
        port = int(port)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a (host, port) pair, got {addr!r}") from None
    if not isinstance(host, str) or not 0 <= port < 65536:
        raise ValueError(f"{name} must be a (host str, port 0..65535) pair, got {addr!r}")
    return host, port


class VehicleEndpoint:
    """One vehicle's MAVLink endpoint (see the module docstring).

    sysid: 1..255; kind: "uav" (MAV_TYPE_FIXED_WING, takes missions) or "sonde"
    (MAV_TYPE_FREE_BALLOON, zero mission items).  gcs: where the streams go.  listen: our
    address (default 127.0.0.1 : 5760 + 10 x instance; port 0 picks a free port, read
    ``listen_addr``).  params: a ParamStore (None: no parameters).  on_mission: called with
    an uploaded mission's waypoints (see mission.py).  signing_key: 32 bytes to sign
    everything we send and require valid signatures on everything we accept.  tlog: a path
    or a shared TlogWriter for all our traffic (simulated unix time stamps).
    stream_rates_hz: {msgid: Hz} overriding DEFAULT_STREAM_RATES_HZ (0: off).
    """

    def __init__(self, sysid: int, kind: str = "uav", gcs=DEFAULT_GCS, listen=None, params: ParamStore | None = None,
                 on_mission: Callable | None = None, signing_key: bytes | None = None, tlog=None, *,
                 instance: int | None = None, compid: int = mavlink.MAV_COMP_ID_AUTOPILOT1, link_id: int = 0,
                 stream_rates_hz: dict | None = None, mission_timeout_s: float = 1.5, mission_retries: int = 5):
        if isinstance(sysid, bool) or int(sysid) != sysid or not 1 <= sysid <= 255:
            raise ValueError(f"sysid must be an integer in 1..255, got {sysid!r}")
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {sorted(KINDS)}, got {kind!r}")
        if params is not None and not isinstance(params, ParamStore):
            raise ValueError(f"params must be a ParamStore or None, got {type(params).__name__}")
        if on_mission is not None and not callable(on_mission):
            raise ValueError("on_mission must be callable or None")
        self.sysid, self.compid, self.kind = int(sysid), int(compid), kind
        self.instance = int(sysid) - 1 if instance is None else int(instance)
        self.gcs = _check_addr("gcs", gcs)
        listen = ("127.0.0.1", listen_port(self.instance)) if listen is None else _check_addr("listen", listen)
        self.params = params if params is not None else ParamStore([])
        self._mav_type = KINDS[kind]

        rates = dict(DEFAULT_STREAM_RATES_HZ)
        for k, v in (stream_rates_hz or {}).items():
            if k not in STREAMS:
                raise ValueError(f"stream_rates_hz: message id {k!r} is not a stream (one of {STREAMS})")
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"stream_rates_hz[{k}] must be a rate >= 0 Hz, got {v!r}")
            rates[k] = float(v)
        self._default_interval = {k: (1.0 / r if r > 0 else None) for k, r in rates.items()}
        self._interval = dict(self._default_interval)
        self._due: dict[int, float] = {}
        self._next_due = -math.inf  # earliest due time of any stream
        # each stream's first interval is shortened by this fraction (golden-ratio spread by
        # instance), so the streams of many vehicles stepped together do not all fall due in
        # the same epoch (at 200 UAVs that made every tenth 10 Hz step several times the others)
        self._phase_frac = (self.instance * 0.6180339887498949) % 1.0

        self.counters = dict.fromkeys(TRAFFIC_COUNTERS + REJECT_REASONS, 0)

        self._signer = None
        if signing_key is not None:
            self._signer = SignatureChecker(signing_key)  # validates the key
        own_tlog = tlog is not None and not isinstance(tlog, TlogWriter)
        self._tlog = TlogWriter(tlog) if own_tlog else tlog
        self._own_tlog = own_tlog

        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.setblocking(False)
            self.sock.bind(listen)
        except OSError as e:
            self.sock.close()
            if self._own_tlog:
                self._tlog.close()
            raise ValueError(f"sysid {sysid}: cannot listen on udp {listen[0]}:{listen[1]}: {e.strerror}") from None
        self.listen_addr = self.sock.getsockname()

        # encoder (signs when a key is given) and a separate decoder that never checks
        # signatures itself (SignatureChecker does, in the right order)
        self.mav = mavlink.MAVLink(self, srcSystem=self.sysid, srcComponent=self.compid)
        if self._signer is not None:
            self.mav.signing.secret_key = self._signer.key
            self.mav.signing.link_id = int(link_id) & 0xFF
            self.mav.signing.sign_outgoing = True
        self._decoder = mavlink.MAVLink(None)

        self._peers: dict[tuple, float] = {}  # address -> last accepted packet (sim s)
        self._dest: Sequence[tuple] = (self.gcs,)
        self._param_queue: list[tuple[tuple, int]] = []
        self.mission = MissionServer(kind == "uav", self._send_to, self._count, on_mission,
                                     home_alt=lambda: self.home_alt_msl_m or 0.0,
                                     timeout_s=mission_timeout_s, retries=mission_retries)
        self._t = None
        self._t_boot = None
        self._unix_s = 0.0
        self.telemetry: VehicleTelemetry | None = None
        self.home_alt_msl_m: float | None = None
        self.home: tuple[float, float, float] | None = None  # (lat_rad, lon_rad, alt_msl_m)
        self._handlers = {
            "PARAM_REQUEST_LIST": self._on_param_request_list,
            "PARAM_REQUEST_READ": self._on_param_request_read,
            "PARAM_SET": self._on_param_set,
            "COMMAND_LONG": self._on_command,
            "COMMAND_INT": self._on_command,
            "TIMESYNC": self._on_timesync,
            "REQUEST_DATA_STREAM": self._on_request_data_stream,
            "FILE_TRANSFER_PROTOCOL": self._on_ftp,
        }
        for name in ("MISSION_REQUEST_LIST", "MISSION_COUNT", "MISSION_REQUEST_INT", "MISSION_REQUEST",
                     "MISSION_ITEM_INT", "MISSION_ITEM", "MISSION_CLEAR_ALL", "MISSION_ACK"):
            self._handlers[name] = self._on_mission_msg
        self.last_error: str | None = None  # the last handler error, one line
        self._closed = False

    # ------------------------------------------------------------------ plumbing
    def fileno(self) -> int:
        return self.sock.fileno()

    def _count(self, reason: str) -> None:
        self.counters[reason] = self.counters.get(reason, 0) + 1

    def write(self, buf: bytes) -> None:
        """pymavlink's MAVLink.send writes here: to every current destination, and the tlog."""
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

    def _update_clock(self, t_gps_s: float) -> None:
        t = float(t_gps_s)
        if not math.isfinite(t):
            raise ValueError(f"t_gps_s must be finite, got {t_gps_s!r}")
        if self._t_boot is None:
            self._t_boot = t
        self._t = t
        self._unix_s = tm.unix_s_from_gps(t)
        if self._signer is not None:  # 10 us since 2015-01-01, never backwards
            ts = int((self._unix_s - tm.SIGNING_EPOCH_UNIX_S) * 1e5)
            if ts > self.mav.signing.timestamp:
                self.mav.signing.timestamp = ts

    @property
    def time_boot_ms(self) -> int:
        return int(round((self._t - self._t_boot) * 1000.0)) if self._t is not None else 0

    # ------------------------------------------------------------------ step
    def step(self, t_gps_s: float, telemetry: VehicleTelemetry | None) -> None:
        """Handle what arrived, run timeouts, send what is due at simulated time t_gps_s."""
        self._update_clock(t_gps_s)
        self.poll()
        self._advance(telemetry)

    def _advance(self, telemetry) -> None:
        self.telemetry = telemetry  # None: nothing to report now (never a stale position)
        if telemetry is not None and self.home is None:  # home: the first position reported
            self.home = (float(telemetry.lat_rad), float(telemetry.lon_rad), float(telemetry.alt_msl_m))
            self.home_alt_msl_m = self.home[2]
        t = self._t
        if self._peers:
            for a in [a for a, seen in self._peers.items() if t - seen > _PEER_TIMEOUT_S]:
                del self._peers[a]
            self._dest = self._stream_dest()
        self.mission.step(t)
        self._send_params()
        self._send_streams(t)

    def poll(self) -> int:
        """Read and handle every datagram waiting (at most a bounded number); returns how many."""
        n = 0
        while n < _MAX_DATAGRAMS_PER_STEP:
            try:
                data, addr = self.sock.recvfrom(_RECV_SIZE)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:  # e.g. ICMP errors queued on the socket: not our input, skip
                self.counters["send_errors"] += 1
                continue
            n += 1
            self.handle_datagram(data, addr)
        return n

    def handle_datagram(self, data: bytes, addr) -> None:
        self.counters["rx_datagrams"] += 1
        self.counters["rx_bytes"] += len(data)
        frames, rejects = split_datagram(data)
        for r in rejects:
            self._count(r)
        for fr in frames:
            self._handle_frame(fr, addr)

    def _handle_frame(self, fr, addr) -> None:
        if fr.incompat_flags & ~mavlink.MAVLINK_IFLAG_SIGNED:
            self._count("unsupported_flags")  # the spec: drop frames with unknown incompat flags
            return
        if fr.msgid not in mavlink.mavlink_map:
            # the CRC cannot be checked without the message's CRC_EXTRA: unknown is unknown
            self._count("unknown_msgid")
            return
        try:
            msg = self._decoder.decode(bytearray(fr.buf))
        except mavlink.MAVError as e:
            self._count("bad_crc" if "CRC" in str(e) else "malformed")
            return
        except Exception:  # pymavlink on hostile bytes: never let it take the process down
            self._count("malformed")
            return
        if self._signer is not None:
            reason = self._signer.check(fr, self.mav.signing.timestamp)
            if reason is not None:
                self._count(reason)
                return
            ts = int.from_bytes(fr.buf[-12:-6], "little")
            if ts > self.mav.signing.timestamp:  # a peer whose clock is ahead: follow it
                self.mav.signing.timestamp = ts
        self.counters["received"] += 1
        if self._tlog is not None:
            self._tlog.write(self._unix_s, fr.buf)
        ts_ = getattr(msg, "target_system", 0)
        tc_ = getattr(msg, "target_component", 0)
        if (ts_ not in (0, self.sysid)) or (tc_ not in (0, self.compid)):
            self.counters["not_for_us"] += 1
            return
        if addr not in self._peers and addr != self.gcs and len(self._peers) >= _MAX_PEERS:
            oldest = min(self._peers, key=self._peers.get)
            del self._peers[oldest]
        self._peers[addr] = self._t if self._t is not None else 0.0
        h = self._handlers.get(msg.get_type())
        if h is not None:
            try:
                h(msg, addr)
            except Exception as e:  # a bug met by some input must not stop the vehicle: count, keep one line
                self.counters["handler_errors"] += 1
                self.last_error = f"{msg.get_type()} from {addr[0]}:{addr[1]}: {type(e).__name__}: {e}"

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
            errors = sum(self.counters[r] for r in REJECT_REASONS[:9])
            mav.sys_status_send(_SENSORS, _SENSORS, _SENSORS if gps_ok else 0, 0, mv, -1, pct, 0,
                                min(errors, tm.UINT16_MAX), 0, 0, 0, 0)
        elif msgid == AUTOPILOT_VERSION:
            mav.autopilot_version_send(CAPABILITIES, FLIGHT_SW_VERSION, 0, 0, 0, list(b"skyfuse\x00"), [0] * 8,
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

    # ------------------------------------------------------------------ close
    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.sock.close()
        if self._tlog is not None:
            if self._own_tlog:
                self._tlog.close()
            else:
                self._tlog.flush()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class EndpointGroup:
    """Many endpoints stepped together: one selector (epoll) poll per step over all sockets.

    ``step(t_gps_s, telemetry_list)``: telemetry_list[i] (or None) for endpoints[i].
    ``counters``: the endpoints' counters summed.
    """

    def __init__(self, endpoints: Iterable[VehicleEndpoint]):
        self.endpoints = list(endpoints)
        ids = [ep.sysid for ep in self.endpoints]
        if len(set(ids)) != len(ids):
            raise ValueError(f"endpoints must have distinct system ids, got {ids}")
        self._sel = selectors.DefaultSelector()
        for ep in self.endpoints:
            self._sel.register(ep.sock, selectors.EVENT_READ, ep)

    def __len__(self) -> int:
        return len(self.endpoints)

    def step(self, t_gps_s: float, telemetry_list: Sequence[VehicleTelemetry | None]) -> None:
        if len(telemetry_list) != len(self.endpoints):
            raise ValueError(f"telemetry_list must have one entry per endpoint ({len(self.endpoints)}), "
                             f"got {len(telemetry_list)}")
        for ep in self.endpoints:
            ep._update_clock(t_gps_s)
        for key, _ in self._sel.select(0):
            key.data.poll()
        for ep, tel in zip(self.endpoints, telemetry_list):
            ep._advance(tel)

    @property
    def counters(self) -> dict:
        out: dict[str, int] = {}
        for ep in self.endpoints:
            for k, v in ep.counters.items():
                out[k] = out.get(k, 0) + v
        return out

    def close(self) -> None:
        self._sel.close()
        for ep in self.endpoints:
            ep.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
