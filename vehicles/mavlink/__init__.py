"""Vehicles as MAVLink 2 endpoints over UDP: what QGroundControl and MAVProxy see.

    from vehicles.mavlink import VehicleEndpoint, EndpointGroup, VehicleTelemetry, ParamStore
    ep = VehicleEndpoint(sysid=1, kind="uav", gcs=("127.0.0.1", 14550), listen=("127.0.0.1", 5760),
                         params=ParamStore(uav_param_specs(mission, nav, i)), on_mission=cb,
                         signing_key=None, tlog="uav1.tlog")
    ep.step(t_gps_s, VehicleTelemetry(lat_rad=..., lon_rad=..., alt_msl_m=..., vel_ned_m_s=(vn, ve, vd), ...))
    ep.counters        # rejected frames / requests by reason (REJECT_REASONS) and traffic counts
    ep.datagrams       # one verdict per datagram: accepted, rejected {reason: n}, kernel_dropped
    ep.close()

Modules: telemetry (SI -> MAVLink units), params (the parameter store), mission (the mission
protocol), framing (datagram framing, signing checks, key files, .tlog), endpoint (sockets,
streams, commands, the group).

What a GCS asks at connection, and how each is answered without a stall
------------------------------------------------------------------------
QGroundControl's InitialConnectStateMachine (src/Vehicle/InitialConnectStateMachine.cc,
read for this work) runs, per vehicle, in order:
  1. REQUEST_MESSAGE(AUTOPILOT_VERSION) (MAV_CMD_REQUEST_MESSAGE, param1 = 148); without an
     answer it retries, then assumes capabilities (QGC PR #9644, #8506: "ArduPilot takes a
     full 5 seconds") -> we ACK ACCEPTED and send AUTOPILOT_VERSION at once, capabilities
     MAVLINK2 | PARAM_FLOAT | PARAM_ENCODE_C_CAST | MISSION_INT | MISSION_FLOAT | COMMAND_INT
     (no MISSION_FENCE / MISSION_RALLY, so QGC skips the fence and rally loads; no FTP, so
     it uses the parameter protocol).  MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES likewise.
  2. component information: REQUEST_MESSAGE(COMPONENT_METADATA = 397), then the deprecated
     COMPONENT_INFORMATION = 395 (RequestMetaDataTypeStateMachine.cc); a non-ACCEPTED ACK
     moves it on at once, silence costs its timeout -> we ACK MAV_RESULT_UNSUPPORTED.
     Same for AVAILABLE_MODES (435, standard modes) and PROTOCOL_VERSION (300: not in
     pymavlink 2.4.50's dialects, so UNSUPPORTED; QGC then keeps MAVLink 2 as seen on the link)
     and for every other REQUEST_MESSAGE id we cannot send.
  3. PARAM_REQUEST_LIST: every PARAM_VALUE with param_count / param_index (QGC does not show
     the vehicle as ready before the list is complete; QGC issue #2334) -> streamed, at most
     64 per step.
  4. MISSION_REQUEST_LIST (mission type) -> MISSION_COUNT and items; fence and rally types
     (asked only when the capability bits say so; MAVProxy's fence/rally modules ask anyway)
     -> MISSION_COUNT 0.
MAVProxy (sim_vehicle.py's GCS) sends REQUEST_DATA_STREAM (its ``streamrate``, 4 Hz by
default) -> honoured per data-stream group; PARAM_REQUEST_LIST; MISSION_REQUEST_LIST.
Every unsupported COMMAND_LONG / COMMAND_INT gets MAV_RESULT_UNSUPPORTED at once.
HEARTBEAT's autopilot is MAV_AUTOPILOT_GENERIC: claiming ARDUPILOTMEGA would make the GCS
expect ArduPilot's modes, parameters and MAVLink-FTP parameter download.

Ports: ArduPilot SITL's ``-I N`` adds 10 x N to every port (Tools/completion/zsh/_ap_bin:
"set instance of SITL (adds 10*instance to all port numbers)"; SERIAL0 is tcp 5760); the
GCS listens on udp 14550.  Here instance N listens on udp 5760 + 10 N with sysid N + 1 -- in
MAVLink block 1; a run of more than 249 vehicles has several blocks (networks), each with its
own GCS port (14550, 14560, ...), system ids 1..249 and ports base + (k - 1) + 10 (s - 1), the
ground station (250) on every one: sitl/mavlink/blocks.py.
"""
from .endpoint import (
    BASE_PORT,
    CAPABILITIES,
    DATAGRAM_REJECT_REASONS,
    DEFAULT_GCS,
    DEFAULT_STREAM_RATES_HZ,
    FUTURE_WINDOW_S,
    KINDS,
    REJECT_REASONS,
    TRAFFIC_COUNTERS,
    EndpointGroup,
    VehicleEndpoint,
    listen_port,
)
from sitl.mavlink.framing import SigningStateFile, TlogWriter, frame_datagram, load_signing_key, split_datagram
from .mission import MissionServer
from .params import ParamError, ParamSpec, ParamStore, apply_uav_params, sonde_param_specs, uav_param_specs
from .telemetry import VehicleTelemetry, gps_from_unix_s, unix_s_from_gps

__all__ = [
    "BASE_PORT",
    "CAPABILITIES",
    "DATAGRAM_REJECT_REASONS",
    "DEFAULT_GCS",
    "DEFAULT_STREAM_RATES_HZ",
    "FUTURE_WINDOW_S",
    "KINDS",
    "REJECT_REASONS",
    "TRAFFIC_COUNTERS",
    "EndpointGroup",
    "MissionServer",
    "ParamError",
    "ParamSpec",
    "ParamStore",
    "SigningStateFile",
    "TlogWriter",
    "VehicleEndpoint",
    "VehicleTelemetry",
    "apply_uav_params",
    "frame_datagram",
    "gps_from_unix_s",
    "listen_port",
    "load_signing_key",
    "sonde_param_specs",
    "split_datagram",
    "uav_param_specs",
    "unix_s_from_gps",
]
