"""One vehicle's MAVLink endpoint: its socket, its state, and the step that reads, answers and
sends (the parts: signing.py, receive.py, streams.py, handlers.py)."""
from __future__ import annotations

import math
import socket
import time
from typing import Callable, Sequence

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.mavlink.framing import SIGNING_TICKS_PER_S, SignatureChecker, SigningStateFile, TlogWriter

from .. import telemetry as tm
from ..ftp import FtpServer
from ..mission import MissionServer
from ..params import ParamStore
from ..telemetry import VehicleTelemetry
from .constants import (_FUTURE_TICKS, _PEER_TIMEOUT_S, _SO_RXQ_OVFL, DATAGRAM_REJECT_REASONS, DEFAULT_GCS,
                        DEFAULT_RCVBUF_BYTES, DEFAULT_STREAM_RATES_HZ, KINDS, REJECT_REASONS, SIGNING_RESERVE_S,
                        HEARTBEAT, STREAMS, TRAFFIC_COUNTERS, _check_addr, listen_port)
from .handlers import AutopilotPort, RequestHandlers
from .receive import DatagramInput, _drain
from ..tcp import StreamFramer, TcpServer
from .signing import SigningClock
from .streams import StreamOutput


class VehicleEndpoint(SigningClock, DatagramInput, StreamOutput, RequestHandlers):
    """One vehicle's MAVLink endpoint (see the docstring of vehicles.mavlink.endpoint).

    sysid: 1..255; kind: "uav" (MAV_TYPE_FIXED_WING, takes missions) or "sonde"
    (MAV_TYPE_FREE_BALLOON, zero mission items).  gcs: where the streams go.  listen: our
    address (default 127.0.0.1 : 5760 + 10 x instance; port 0 picks a free port, read
    ``listen_addr``).  params: a ParamStore (None: no parameters).  on_mission: called with
    an uploaded mission's waypoints (see vehicles/mavlink/mission.py).  signing_key: 32 bytes to sign
    everything we send and require valid signatures on everything we accept.  tlog: a path
    or a shared TlogWriter for all our traffic (a path: stamped by ``clock``, else simulated unix time).
    stream_rates_hz: {msgid: Hz} overriding DEFAULT_STREAM_RATES_HZ (0: off).
    clock: our signing clock, unix seconds (None: the simulated clock); signing_state: the
    file that keeps the signing state across restarts (None: kept in memory only); see
    signing.py.  rcvbuf_bytes: the receive buffer to ask for (None: the OS default).
    autopilot: a UAV's handlers.AutopilotPort (its vehicles.autopilot): HEARTBEAT, home, the
    flight commands and missions are the autopilot's (None: no flight control, missions go to
    on_mission).
    tcp_listen: (host, port) of a TCP server beside the UDP socket (ArduPilot SITL's SERIAL0;
    vehicles.mavlink.tcp): each connected client is a peer like a UDP one (its requests answered
    on its connection, the streams sent to it while it is connected); None: UDP only.
    """

    def __init__(self, sysid: int, kind: str = "uav", gcs=DEFAULT_GCS, listen=None, params: ParamStore | None = None,
                 on_mission: Callable | None = None, signing_key: bytes | None = None, tlog=None, *,
                 instance: int | None = None, compid: int = mavlink.MAV_COMP_ID_AUTOPILOT1, link_id: int = 0,
                 stream_rates_hz: dict | None = None, mission_timeout_s: float = 1.5, mission_retries: int = 5,
                 clock: Callable[[], float] | None = None, signing_state=None,
                 rcvbuf_bytes: int | None = DEFAULT_RCVBUF_BYTES, autopilot: AutopilotPort | None = None,
                 tcp_listen=None):
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
        if autopilot is not None and not isinstance(autopilot, AutopilotPort):
            raise ValueError(f"autopilot must be an AutopilotPort or None, got {type(autopilot).__name__}")
        self.sysid, self.compid, self.kind = int(sysid), int(compid), kind
        self.link_id = int(link_id) & 0xFF  # its MAVLink network's (sitl.mavlink.blocks: block - 1)
        self.autopilot = autopilot
        self._heartbeat_now = False
        self._mission_current_due = -math.inf
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
        self._tlog = TlogWriter(tlog, stamp_clock=clock) if own_tlog else tlog  # stamped as the signing clock
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
        self.tcp = None
        self._framers: dict = {}  # TCP client address -> its StreamFramer
        if tcp_listen is not None:
            host, tport = _check_addr("tcp_listen", tcp_listen)
            try:
                self.tcp = TcpServer(host, tport)
            except OSError as e:
                self.sock.close()
                if self._own_tlog:
                    self._tlog.close()
                raise ValueError(f"sysid {sysid}: cannot listen on tcp {host}:{tport}: {e.strerror}") from None
            self.tcp_addr = self.tcp.addr
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
        self._reserved = 0  # the persisted bound (see signing.py)
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
                                     timeout_s=mission_timeout_s, retries=mission_retries,
                                     on_items=self._mission_items if autopilot is not None else None,
                                     home_item=self._home_item if autopilot is not None else None,
                                     item_check=self._mission_item_check if autopilot is not None else None)
        self.ftp = FtpServer(self.params)
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
            "SET_MODE": self._on_set_mode,
            "MISSION_SET_CURRENT": self._on_mission_set_current,
            "SET_POSITION_TARGET_GLOBAL_INT": self._on_set_position_target,
        }
        for name in ("MISSION_REQUEST_LIST", "MISSION_COUNT", "MISSION_REQUEST_INT", "MISSION_REQUEST",
                     "MISSION_ITEM_INT", "MISSION_ITEM", "MISSION_CLEAR_ALL", "MISSION_ACK"):
            self._handlers[name] = self._on_mission_msg
        self._closed = False

    # ------------------------------------------------------------------ plumbing
    def fileno(self) -> int:
        return self.sock.fileno()

    # ------------------------------------------------------------------ TCP (SERIAL0)
    def poll_tcp(self) -> int:
        """Accept TCP clients, send what is queued for them, handle the frames they sent (their
        address is ("tcp", host, port)); returns the bytes read."""
        if self.tcp is None:
            return 0
        got = 0
        for addr, data in self.tcp.poll():
            got += len(data)
            self.counters["rx_bytes"] += len(data)
            peer = ("tcp", *addr)
            for item in self._framers.setdefault(addr, StreamFramer()).feed(data):
                if isinstance(item, str):
                    self._count(item)
                else:
                    self._handle_frame(item, peer)
        if len(self._framers) > len(self.tcp.clients):
            live = set(self.tcp.clients)
            for a in [a for a in self._framers if a not in live]:
                del self._framers[a]
        return got

    def _stream_dest(self) -> tuple:
        dest = super()._stream_dest()
        if self.tcp is None or not self.tcp.clients:
            return dest
        return (*dest, *[("tcp", *a) for a in self.tcp.clients])

    def write(self, buf: bytes) -> None:
        """pymavlink's MAVLink.send writes here: UDP destinations (streams.py), TCP clients here."""
        dest = self._dest
        if self.tcp is None or not self.tcp.clients or not any(len(a) == 3 for a in dest):
            return super().write(buf)
        self._dest = tuple(a for a in dest if len(a) != 3)
        try:
            super().write(buf)  # the UDP destinations, the signing reserve, the tlog
        finally:
            self._dest = dest
        for a in dest:
            if len(a) == 3:
                if self.tcp.send(a[1:], buf):
                    self.counters["sent"] += 1
                    self.counters["tx_bytes"] += len(buf)
                else:
                    self.counters["send_errors"] += 1

    def _count(self, reason: str) -> None:
        self.counters[reason] = self.counters.get(reason, 0) + 1

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

    @property
    def time_boot_ms(self) -> int:
        return int(round((self._t - self._t_boot) * 1000.0)) if self._t is not None else 0

    # ------------------------------------------------------------------ step
    def step(self, t_gps_s: float, telemetry: VehicleTelemetry | None, budget_s: float | None = None) -> None:
        """Handle what arrived, run timeouts, send what is due at simulated time t_gps_s.
        budget_s: wall seconds the input may take (None: read until the socket is empty)."""
        self._update_clock(t_gps_s)
        _drain((self,), budget_s, time.perf_counter, 0)
        self.poll_tcp()
        self._advance(telemetry)

    def _advance(self, telemetry, batch=None) -> None:
        """batch: None, or the group's StreamBatch, which frames and sends this step's stream
        messages with the other endpoints' (batch.py; unsigned output only)."""
        self.telemetry = telemetry  # None: nothing to report now (never a stale position)
        if self.autopilot is not None:  # home: the autopilot's (ArduPilot: set at arming, DO_SET_HOME)
            la, lo, h = (float(v) for v in self.autopilot.ap.home[self.autopilot.index])
            self.home, self.home_alt_msl_m = (la, lo, h), h
        elif telemetry is not None and self.home is None:  # home: the first position reported
            self.home = (float(telemetry.lat_rad), float(telemetry.lon_rad), float(telemetry.alt_msl_m))
            self.home_alt_msl_m = self.home[2]
        t = self._t
        if self._peers:
            for a in [a for a, seen in self._peers.items() if t - seen > _PEER_TIMEOUT_S]:
                del self._peers[a]
            self._dest = self._stream_dest()
        self.mission.step(t)
        self._send_params()
        self._autopilot_out(t)
        self._send_streams(t, batch)

    def _send_message(self, msgid: int) -> bool:
        """The streams' messages; HEARTBEAT from the autopilot when there is one (ArduPlane's
        type, autopilot, base_mode, custom mode and system status)."""
        if msgid == HEARTBEAT and self.autopilot is not None:
            self.mav.heartbeat_send(*self.autopilot.ap.heartbeat(self.autopilot.index))
            return True
        return super()._send_message(msgid)

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
        if self.tcp is not None:
            self.tcp.close()
        if self._tlog is not None:
            if self._own_tlog:
                self._tlog.close()
            else:
                self._tlog.flush()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
