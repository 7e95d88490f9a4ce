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
  missions      see vehicles/mavlink/mission.py
  MAVLink FTP   refused at once (NAK), so that MAVProxy falls back to the parameter protocol
  TIMESYNC      tc1 = our (simulated unix) time in ns, ts1 echoed; no timestamp a peer sends
                (TIMESYNC, SYSTEM_TIME, a signature's) ever moves the simulated clock
  signing       optional; unsigned / wrongly signed / replayed / far-future packets rejected
                (see "Signing timestamps" in signing.py)

The parts: constants.py (ports, reasons, streams, limits), vehicle.py (VehicleEndpoint: socket,
state, step), signing.py (the signing clock and its persisted state), receive.py (input and
counters), streams.py (output), handlers.py (the answers to requests), group.py (EndpointGroup).
"""
from __future__ import annotations

from .constants import (ATTITUDE, AUTOPILOT_VERSION, BASE_PORT, CAPABILITIES, DATAGRAM_REJECT_REASONS, DEFAULT_GCS,
                        DEFAULT_RCVBUF_BYTES, DEFAULT_STREAM_RATES_HZ, FLIGHT_SW_VERSION, FRAME_REJECT_REASONS,
                        FUTURE_WINDOW_S, GLOBAL_POSITION_INT, GPS_RAW_INT, HEARTBEAT, HOME_POSITION, KINDS, PORT_STRIDE,
                        PROTOCOL_REJECT_REASONS, REJECT_REASONS, SIGNING_RESERVE_S, STREAMS, SYS_STATUS, SYSTEM_TIME,
                        TRAFFIC_COUNTERS, listen_port)
from .group import EndpointGroup
from .vehicle import VehicleEndpoint

__all__ = ["ATTITUDE", "AUTOPILOT_VERSION", "BASE_PORT", "CAPABILITIES", "DATAGRAM_REJECT_REASONS", "DEFAULT_GCS",
           "DEFAULT_RCVBUF_BYTES", "DEFAULT_STREAM_RATES_HZ", "FLIGHT_SW_VERSION", "FRAME_REJECT_REASONS",
           "FUTURE_WINDOW_S", "GLOBAL_POSITION_INT", "GPS_RAW_INT", "HEARTBEAT", "HOME_POSITION", "KINDS", "PORT_STRIDE",
           "PROTOCOL_REJECT_REASONS", "REJECT_REASONS", "SIGNING_RESERVE_S", "STREAMS", "SYS_STATUS", "SYSTEM_TIME",
           "TRAFFIC_COUNTERS", "EndpointGroup", "VehicleEndpoint", "listen_port"]
