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
  TIMESYNC      tc1 = our (simulated unix) time in ns, ts1 echoed; no timestamp a peer sends
                (TIMESYNC, SYSTEM_TIME, a signature's) ever moves the simulated clock
  signing       optional; unsigned / wrongly signed / replayed / far-future packets rejected
                (see "Signing timestamps" below)

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

Input: each step drains the socket (no fixed cap; EndpointGroup.step takes a time budget
and shares it over the sockets in rounds of a few datagrams); the socket asks the kernel for a
large receive buffer and for its drop counter (SO_RXQ_OVFL on every datagram, SO_MEMINFO after
each drain), so datagrams the kernel dropped are counted too.

Counters.  ``datagrams``: one verdict per datagram received -- ``accepted`` (nothing in it
failed), or ``rejected[reason]`` (the first reason, in datagram order, one of
DATAGRAM_REJECT_REASONS) -- and ``kernel_dropped``: accepted + sum(rejected) + kernel_dropped
is every datagram sent to us once the socket is drained.  ``counters``: per frame / per
request (REJECT_REASONS: frame and protocol rejects, e.g. 5 garbage runs in one datagram count
5 there and 1 in ``datagrams``), TRAFFIC_COUNTERS the rest.  An exception inside a handler is
counted (``handler_errors``, ``last_error``), never raised.
"""
from __future__ import annotations

import math
import selectors
import socket
import sys
import time
from typing import Callable, Iterable, Sequence

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from . import telemetry as tm
from sitl.mavlink.framing import (SIGNING_TICKS_PER_S, SignatureChecker, SigningStateFile, TlogWriter, frame_datagram,
                      signature_timestamp)
from .mission import MissionServer
from .params import ParamError, ParamStore
from .telemetry import VehicleTelemetry

BASE_PORT = 5760
PORT_STRIDE = 10
DEFAULT_GCS = ("127.0.0.1", 14550)

#: why a frame (or a run of bytes) is rejected
FRAME_REJECT_REASONS = ("garbage", "truncated", "bad_crc", "unknown_msgid", "malformed", "unsupported_flags",
                        "unsigned", "bad_signature", "replayed", "future")
#: a valid request refused
PROTOCOL_REJECT_REASONS = ("param_unknown", "param_rejected", "mission_rejected", "mission_timeout")
#: counters that count rejected inputs (the rest count traffic)
REJECT_REASONS = FRAME_REJECT_REASONS + PROTOCOL_REJECT_REASONS
#: a datagram's verdict when it is not accepted: its first failure ("empty": zero bytes)
DATAGRAM_REJECT_REASONS = ("empty",) + FRAME_REJECT_REASONS
TRAFFIC_COUNTERS = ("rx_datagrams", "rx_bytes", "received", "not_for_us", "sent", "tx_bytes", "send_errors",
                    "cmd_unsupported", "ftp_refused", "handler_errors", "input_deferred", "signing_saves",
                    "signing_state_errors")

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
_MAX_PARAMS_PER_STEP = 64
_MAX_PEERS = 8
_PEER_TIMEOUT_S = 60.0
_RECV_SIZE = 65535
#: a peer's signing timestamp up to this far ahead of our own clock is followed; beyond: "future"
FUTURE_WINDOW_S = 300.0
#: the persisted signing bound is renewed this far ahead of the clock (x 1..2, spread by instance)
SIGNING_RESERVE_S = 5.0
_SIGNING_LOOKAHEAD = SIGNING_TICKS_PER_S  # renew at a step when the bound is less than 1 s ahead
_FUTURE_TICKS = int(FUTURE_WINDOW_S * SIGNING_TICKS_PER_S)
_MAX_TS = (1 << 48) - 1
#: receive buffer asked for (the kernel grants min(this, net.core.rmem_max), doubled): ~2,500
#: small datagrams; the default ~208 KiB holds ~250, fewer than a 4,000/s flood brings per 10 Hz epoch
DEFAULT_RCVBUF_BYTES = 1 << 20
_SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40)  # Linux: per-datagram cmsg, the socket's drop count
_SO_MEMINFO = getattr(socket, "SO_MEMINFO", 55)  # Linux: u32[SK_MEMINFO_VARS], SK_MEMINFO_DROPS = 8
_SK_MEMINFO_DROPS = 8
_ANC_SIZE = socket.CMSG_SPACE(4)
_FAIR_BATCH = 16  # datagrams per socket per round when a group shares its budget
_MAX_RECV_ERRORS = 64  # per poll: queued ICMP errors are read one by one
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
    clock: our signing clock, unix seconds (None: the simulated clock); signing_state: the
    file that keeps the signing state across restarts (None: kept in memory only); see the
    module docstring.  rcvbuf_bytes: the receive buffer to ask for (None: the OS default).
    """

    def __init__(self, sysid: int, kind: str = "uav", gcs=DEFAULT_GCS, listen=None, params: ParamStore | None = None,
                 on_mission: Callable | None = None, signing_key: bytes | None = None, tlog=None, *,
                 instance: int | None = None, compid: int = mavlink.MAV_COMP_ID_AUTOPILOT1, link_id: int = 0,
                 stream_rates_hz: dict | None = None, mission_timeout_s: float = 1.5, mission_retries: int = 5,
                 clock: Callable[[], float] | None = None, signing_state=None,
                 rcvbuf_bytes: int | None = DEFAULT_RCVBUF_BYTES):
        if isinstance(sysid, bool) or int(sysid) != sysid or not 1 <= sysid <= 255:
            raise ValueError(f"sysid must be an integer in 1..255, got {sysid!r}")
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {sorted(KINDS)}, got {kind!r}")
        if params is not None and not isinstance(params, ParamStore):
            raise ValueError(f"params must be a ParamStore or None, got {type(params).__name__}")
        if on_mission is not None and not callable(on_mission):
            raise ValueError("on_mission must be callable or None")
        if clock is not None and not callable(clock):
            raise ValueError("clock must be callable (unix seconds) or None")
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
        self.last_error: str | None = None  # the last handler / signing-state error, one line
        self.datagrams = {"accepted": 0, "rejected": dict.fromkeys(DATAGRAM_REJECT_REASONS, 0), "kernel_dropped": 0}
        self._drops_seen = 0  # the kernel's drop counter of our socket (u32) as last read
        self._drops_readable = True
        self._drained = True  # the last poll read the socket until it was empty

        self._signer = None
        if signing_key is not None:
            self._signer = SignatureChecker(signing_key)  # validates the key
        own_tlog = tlog is not None and not isinstance(tlog, TlogWriter)
        self._tlog = TlogWriter(tlog) if own_tlog else tlog
        self._own_tlog = own_tlog

        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.setblocking(False)
            if rcvbuf_bytes is not None:
                try:
                    self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, int(rcvbuf_bytes))
                except OSError:
                    pass  # the OS default
            try:
                self.sock.setsockopt(socket.SOL_SOCKET, _SO_RXQ_OVFL, 1)
            except OSError:  # not Linux: SO_MEMINFO (below) may still read the counter
                pass
            self.sock.bind(listen)
        except OSError as e:
            self.sock.close()
            if self._own_tlog:
                self._tlog.close()
            raise ValueError(f"sysid {sysid}: cannot listen on udp {listen[0]}:{listen[1]}: {e.strerror}") from None
        self.listen_addr = self.sock.getsockname()
        self.rcvbuf_bytes = self.sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)

        # encoder (signs when a key is given) and a separate decoder that never checks
        # signatures itself (SignatureChecker does, in the right order)
        self.mav = mavlink.MAVLink(self, srcSystem=self.sysid, srcComponent=self.compid)
        if self._signer is not None:
            self.mav.signing.secret_key = self._signer.key
            self.mav.signing.link_id = int(link_id) & 0xFF
            self.mav.signing.sign_outgoing = True
            self.mav.signing.timestamp = 0
        self._decoder = mavlink.MAVLink(None)
        self._clock = clock
        self._state_file = (SigningStateFile(signing_state, self.sysid)
                            if signing_state is not None and self._signer is not None else None)
        self._reserved = 0  # the persisted bound (see the module docstring)
        self._state_ok = False
        self._reserve_ticks = int(SIGNING_RESERVE_S * (1.0 + self._phase_frac) * SIGNING_TICKS_PER_S)
        self._restart_ts = 0  # where a restarted endpoint's timestamps start (above the bound)
        self._floor_from_clock = False  # an unreadable state file: the floor is the first clock reading
        self._future_limit = _FUTURE_TICKS  # until the first clock reading: nothing in the future passes
        if self._state_file is not None:
            self._load_signing_state()
        if self._signer is not None and clock is not None:
            self._clock_signing()

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
        self._closed = False

    # ------------------------------------------------------------------ plumbing
    def fileno(self) -> int:
        return self.sock.fileno()

    def _count(self, reason: str) -> None:
        self.counters[reason] = self.counters.get(reason, 0) + 1

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

    def _update_clock(self, t_gps_s: float) -> None:
        t = float(t_gps_s)
        if not math.isfinite(t):
            raise ValueError(f"t_gps_s must be finite, got {t_gps_s!r}")
        if self._t_boot is None:
            self._t_boot = t
        self._t = t
        self._unix_s = tm.unix_s_from_gps(t)
        if self._signer is not None:
            self._clock_signing()

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

    @property
    def time_boot_ms(self) -> int:
        return int(round((self._t - self._t_boot) * 1000.0)) if self._t is not None else 0

    # ------------------------------------------------------------------ step
    def step(self, t_gps_s: float, telemetry: VehicleTelemetry | None, budget_s: float | None = None) -> None:
        """Handle what arrived, run timeouts, send what is due at simulated time t_gps_s.
        budget_s: wall seconds the input may take (None: read until the socket is empty)."""
        self._update_clock(t_gps_s)
        _drain((self,), budget_s, time.perf_counter, 0)
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

    def poll(self, max_datagrams: int | None = None) -> int:
        """Read and handle the datagrams waiting, at most max_datagrams (None: until the socket
        is empty); returns how many were read.  ``_drained``: the socket was read empty."""
        n = errors = 0
        recv, sock_level = self.sock.recvmsg, socket.SOL_SOCKET
        self._drained = False
        while max_datagrams is None or n < max_datagrams:
            try:
                data, anc, _flags, addr = recv(_RECV_SIZE, _ANC_SIZE)
            except (BlockingIOError, InterruptedError):
                self._drained = True
                break
            except OSError:  # e.g. ICMP errors of our own sends queued on the socket: not input
                self.counters["send_errors"] += 1
                errors += 1
                if errors >= _MAX_RECV_ERRORS:
                    break
                continue
            for level, kind, v in anc:
                if kind == _SO_RXQ_OVFL and level == sock_level and len(v) >= 4:
                    self._note_drops(int.from_bytes(v[:4], sys.byteorder))
            n += 1
            self.handle_datagram(data, addr)
        return n

    def _note_drops(self, count: int) -> None:
        """The socket's drop counter (u32, cumulative, stamped on each datagram as it was queued:
        an older stamp can come after a newer reading, and is ignored)."""
        d = (count - self._drops_seen) & 0xFFFFFFFF
        if 0 < d < 0x80000000:
            self._drops_seen = count & 0xFFFFFFFF
            self.datagrams["kernel_dropped"] += d

    def read_kernel_drops(self) -> None:
        """Catch up with the kernel's drop counter now (SO_MEMINFO; datagrams dropped after the
        last one queued carry no SO_RXQ_OVFL stamp until another arrives)."""
        if not self._drops_readable or self._closed:
            return
        try:
            v = self.sock.getsockopt(socket.SOL_SOCKET, _SO_MEMINFO, 4 * (_SK_MEMINFO_DROPS + 1))
        except OSError:
            self._drops_readable = False
            return
        if len(v) >= 4 * (_SK_MEMINFO_DROPS + 1):
            self._note_drops(int.from_bytes(v[4 * _SK_MEMINFO_DROPS:4 * (_SK_MEMINFO_DROPS + 1)], sys.byteorder))

    def handle_datagram(self, data: bytes, addr) -> str:
        """Handle one datagram; returns its one verdict ("accepted", or the first reason it failed),
        counted in ``datagrams``.  Its frames and rejects are counted one by one in ``counters``."""
        c = self.counters
        c["rx_datagrams"] += 1
        c["rx_bytes"] += len(data)
        verdict = None if data else "empty"
        for item in frame_datagram(data):
            if isinstance(item, str):
                self._count(item)
                r = item
            else:
                r = self._handle_frame(item, addr)
            if verdict is None and r is not None:
                verdict = r
        if verdict is None:
            self.datagrams["accepted"] += 1
            return "accepted"
        self.datagrams["rejected"][verdict] += 1
        return verdict

    def _reject(self, reason: str) -> str:
        self.counters[reason] += 1
        return reason

    def _handle_frame(self, fr, addr) -> str | None:
        """None if the frame is accepted (then handled), else why it was rejected (counted)."""
        if fr.incompat_flags & ~mavlink.MAVLINK_IFLAG_SIGNED:
            return self._reject("unsupported_flags")  # the spec: drop frames with unknown incompat flags
        if fr.msgid not in mavlink.mavlink_map:
            # the CRC cannot be checked without the message's CRC_EXTRA: unknown is unknown
            return self._reject("unknown_msgid")
        try:
            msg = self._decoder.decode(bytearray(fr.buf))
        except mavlink.MAVError as e:
            return self._reject("bad_crc" if "CRC" in str(e) else "malformed")
        except Exception:  # pymavlink on hostile bytes: never let it take the process down
            return self._reject("malformed")
        if self._signer is not None:
            reason = self._signer.check(fr, self.mav.signing.timestamp, self._future_limit)
            if reason is not None:
                return self._reject(reason)
            ts = signature_timestamp(fr.buf)
            if self._state_file is not None and ts > self._reserved:  # on disk before it counts
                self._reserve(ts)
            if ts > self.mav.signing.timestamp:  # a peer ahead, within the future window: follow it
                self.mav.signing.timestamp = ts
        self.counters["received"] += 1
        if self._tlog is not None:
            self._tlog.write(self._unix_s, fr.buf)
        ts_ = getattr(msg, "target_system", 0)
        tc_ = getattr(msg, "target_component", 0)
        if (ts_ not in (0, self.sysid)) or (tc_ not in (0, self.compid)):
            self.counters["not_for_us"] += 1  # valid traffic, for someone else: accepted, not acted on
            return None
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
        return None

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
            errors = sum(self.counters[r] for r in FRAME_REJECT_REASONS) + self.datagrams["kernel_dropped"]
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
        if self._state_file is not None:
            # the streams as they are now; nothing was sent at or above our timestamp, nothing
            # accepted above it (we follow every accepted frame): the exact bound
            self._save_signing_state(self.mav.signing.timestamp)
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


def _drain(endpoints: Sequence[VehicleEndpoint], budget_s: float | None, timer: Callable[[], float],
           start: int) -> None:
    """Read the endpoints' sockets until each is empty or the budget is spent: in rounds of
    _FAIR_BATCH datagrams per socket, starting at endpoints[start % n], so a flooded port takes
    its share and no more; then catch up with each socket's kernel drop counter."""
    n = len(endpoints)
    if not n:
        return
    k = start % n
    active = list(endpoints[k:]) + list(endpoints[:k])
    deadline = None if budget_s is None else timer() + max(0.0, float(budget_s))
    batch = None if deadline is None and n == 1 else _FAIR_BATCH
    out_of_time = False
    while active and not out_of_time:
        nxt = []
        for ep in active:
            ep.poll(batch)
            if not ep._drained:
                nxt.append(ep)
            if deadline is not None and timer() >= deadline:
                out_of_time = True
                break
        active = nxt
    for ep in endpoints:
        if not ep._drained:
            ep.counters["input_deferred"] += 1  # left for the next step (the kernel queue holds it, or drops and counts)
        ep.read_kernel_drops()


class EndpointGroup:
    """Many endpoints stepped together: one selector (epoll) poll per step over all sockets.

    ``step(t_gps_s, telemetry_list, budget_s=None)``: telemetry_list[i] (or None) for
    endpoints[i]; budget_s: the wall seconds the group's input may take this step, shared over
    the sockets that have input (None: every socket read until it is empty).  timer: the
    duration clock the budget is measured with (seconds; default time.perf_counter).
    ``counters``, ``datagrams``: the endpoints' summed.
    """

    def __init__(self, endpoints: Iterable[VehicleEndpoint], *, timer: Callable[[], float] | None = None):
        self.endpoints = list(endpoints)
        ids = [ep.sysid for ep in self.endpoints]
        if len(set(ids)) != len(ids):
            raise ValueError(f"endpoints must have distinct system ids, got {ids}")
        self._timer = time.perf_counter if timer is None else timer
        self._round = 0
        self._sel = selectors.DefaultSelector()
        for ep in self.endpoints:
            self._sel.register(ep.sock, selectors.EVENT_READ, ep)

    def __len__(self) -> int:
        return len(self.endpoints)

    def step(self, t_gps_s: float, telemetry_list: Sequence[VehicleTelemetry | None],
             budget_s: float | None = None) -> None:
        if len(telemetry_list) != len(self.endpoints):
            raise ValueError(f"telemetry_list must have one entry per endpoint ({len(self.endpoints)}), "
                             f"got {len(telemetry_list)}")
        if budget_s is not None and not (isinstance(budget_s, (int, float)) and budget_s >= 0):
            raise ValueError(f"budget_s must be None or >= 0 s, got {budget_s!r}")
        for ep in self.endpoints:
            ep._update_clock(t_gps_s)
        ready = [key.data for key, _ in self._sel.select(0)]
        if ready:
            _drain(ready, budget_s, self._timer, self._round)
            self._round += 1
        for ep, tel in zip(self.endpoints, telemetry_list):
            ep._advance(tel)

    @property
    def counters(self) -> dict:
        out: dict[str, int] = {}
        for ep in self.endpoints:
            for k, v in ep.counters.items():
                out[k] = out.get(k, 0) + v
        return out

    @property
    def datagrams(self) -> dict:
        rej = dict.fromkeys(DATAGRAM_REJECT_REASONS, 0)
        acc = dropped = 0
        for ep in self.endpoints:
            d = ep.datagrams
            acc += d["accepted"]
            dropped += d["kernel_dropped"]
            for r, v in d["rejected"].items():
                rej[r] = rej.get(r, 0) + v
        return {"accepted": acc, "rejected": rej, "kernel_dropped": dropped}

    def close(self) -> None:
        self._sel.close()
        for ep in self.endpoints:
            ep.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
