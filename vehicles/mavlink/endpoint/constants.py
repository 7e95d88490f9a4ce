"""What a vehicle's MAVLink endpoint speaks and its limits: ports (ArduPilot SITL's convention),
the reject reasons and traffic counters, the vehicle kinds, the stream message ids and rates,
the capabilities it claims, the signing window, the socket's receive settings."""
from __future__ import annotations

import socket

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.mavlink.framing import SIGNING_TICKS_PER_S

BASE_PORT = 5760
PORT_STRIDE = 10
DEFAULT_GCS = ("127.0.0.1", 14550)

#: why a frame (or a run of bytes) is rejected
FRAME_REJECT_REASONS = ("garbage", "truncated", "bad_crc", "unknown_msgid", "malformed", "unsupported_flags",
                        "unsigned", "bad_signature", "replayed", "future")
#: a valid request refused
#: (cmd_refused: the autopilot answered a command / SET_MODE / guided request with a code other
#: than ACCEPTED; its reason goes out as STATUSTEXT and stays in ``last_error``)
PROTOCOL_REJECT_REASONS = ("param_unknown", "param_rejected", "mission_rejected", "mission_timeout", "cmd_refused")
#: counters that count rejected inputs (the rest count traffic)
REJECT_REASONS = FRAME_REJECT_REASONS + PROTOCOL_REJECT_REASONS
#: a datagram's verdict when it is not accepted: its first failure ("empty": zero bytes)
DATAGRAM_REJECT_REASONS = ("empty",) + FRAME_REJECT_REASONS
TRAFFIC_COUNTERS = ("rx_datagrams", "rx_bytes", "received", "not_for_us", "sent", "tx_datagrams", "tx_bytes", "send_errors",
                    "cmd_unsupported", "ftp", "handler_errors", "input_deferred", "signing_saves",
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
                | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT | mavlink.MAV_PROTOCOL_CAPABILITY_FTP)
#: MISSION_CURRENT at least this often (s) from a vehicle with an autopilot, and at every change
MISSION_CURRENT_PERIOD_S = 1.0
#: skyfuse 0.1.0, FIRMWARE_VERSION_TYPE_DEV (major << 24 | minor << 16 | patch << 8 | type)
FLIGHT_SW_VERSION = (0 << 24) | (1 << 16) | (0 << 8) | mavlink.FIRMWARE_VERSION_TYPE_DEV

_SENSORS = mavlink.MAV_SYS_STATUS_SENSOR_GPS
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
