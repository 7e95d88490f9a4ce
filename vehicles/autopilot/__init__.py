"""A small autopilot per UAV, stepped in simulation time and batched over the swarm (issue 21).

Pure step functions: simulation time and each UAV's state in, guidance and events out; no I/O,
no sockets, no clock, no sleep; bad input is answered with a code and a one-line reason and
counted, never raised.  The convention (ArduPlane's modes, base_mode, home at mission item 0,
end of mission = RTL) is :mod:`vehicles.autopilot.convention`; the parameters are
:mod:`vehicles.autopilot.config` (filters.params declarations, ArduPlane names).

Modules
-------
convention  the identity: MAV_AUTOPILOT_ARDUPILOTMEGA / MAV_TYPE_FIXED_WING, mode numbers from
            pymavlink's table, base_mode / system_status / landed_state, mission_total
config      AutopilotConfig (WP_RADIUS, WP_LOITER_RAD, RTL_ALTITUDE, AIRSPEED_*, TKOFF_*, ...),
            param_rows / with_param for the MAVLink parameter layer
rules       the vocabulary: task codes, item kinds, REFUSALS, Result, MissionResult, Event,
            MissionStatus, check_item (one mission item's check)
core        Autopilot: the batched state, its mode / mission sequencing and the step
operations  Operations (Autopilot's base): arm, set_mode, goto, set_mission, command, ... (the API below)
guidance    Guidance (per-UAV kind + targets), AutopilotLaw (a vehicles.uav guidance law)
swarm       AutopilotSwarm: the scenario's swarm + the autopilots, bit-for-bit the scenario's
            flight until a GCS commands

The API the MAVLink endpoint calls (i = the UAV's index in the group's Autopilot)
------------------------------------------------------------------------------
COMMAND_LONG / COMMAND_INT      ap.command(i, msg.command, (p1, p2, p3, p4, lat_deg, lon_deg, alt),
                                frame=None | msg.frame) -> Result(code, reason); send COMMAND_ACK
                                with result=code.  For COMMAND_INT pass x * 1e-7, y * 1e-7, z.
                                Covers ARM_DISARM (incl. force 21196), DO_SET_MODE, NAV_TAKEOFF,
                                DO_REPOSITION, NAV_RETURN_TO_LAUNCH, NAV_LOITER_UNLIM, NAV_LAND,
                                MISSION_START, DO_SET_MISSION_CURRENT, DO_CHANGE_SPEED,
                                DO_SET_HOME; anything else -> MAV_RESULT_UNSUPPORTED.
                                (The endpoint keeps answering its own REQUEST_MESSAGE,
                                SET_MESSAGE_INTERVAL ... first.)
SET_MODE                        ap.set_mode(i, msg.custom_mode, msg.base_mode) -> Result (no ACK in
                                the protocol; ArduPilot sends COMMAND_ACK for command 11 anyway)
MISSION upload complete         ap.set_mission(i, items) -> MissionResult(code, reason, index):
                                the MISSION_ACK type (the MissionServer's on_mission hook gets the
                                items, not waypoints; accepted -> store for download)
MISSION_CLEAR_ALL               ap.set_mission(i, [])
MISSION_SET_CURRENT             ap.set_current(i, msg.seq) -> Result; then MISSION_CURRENT
MISSION_ITEM_INT current = 2/3  ap.guided_item(i, msg) -> MissionResult -> MISSION_ACK
SET_POSITION_TARGET_GLOBAL_INT  ap.goto(i, radians(lat_int * 1e-7), radians(lon_int * 1e-7), alt,
                                relative_alt=frame is relative, change_mode=False) (no ACK)
HEARTBEAT                       ap.heartbeat(i) -> (type, autopilot, base_mode, custom_mode, system_status)
MISSION_CURRENT (stream)        ap.mission_status() -> MissionStatus(seq, total, state) arrays (N,)
EXTENDED_SYS_STATE              ap.landed_state()[i]  (vtol_state MAV_VTOL_STATE_UNDEFINED)
HOME_POSITION                   ap.home[i] (lat_rad, lon_rad, alt_m)
the parameters                  config.param_rows(ap.cfg); a PARAM_SET: ap.cfg = with_param(ap.cfg, name, v)
refusal counters                ap.counters (REFUSALS), ap.last_reason

The events (vehicles.autopilot.core.Event: vehicle, kind, value, severity, text), returned by
``step`` (and by ``AutopilotSwarm.step`` in ``.events``), after the operations of the epoch:
  'item_reached' value=seq  -> MISSION_ITEM_REACHED(seq)
  'mission_current' value=seq -> MISSION_CURRENT now (besides the stream)
  'mode' value=custom mode  -> HEARTBEAT now
  'armed' / 'disarmed' / 'takeoff_complete' / 'landed' / 'mission_complete' / 'text'
  every event with a text -> STATUSTEXT(severity, text) (ArduPlane's wording where it has one)

The API the vehicle process calls
---------------------------------
  fleet = AutopilotSwarm(swarm, Autopilot(lat, lon, h, heading, in_flight=..., scenario=...))
  truth = fleet.step(t_rel_s)      # instead of swarm.step(t_rel_s) and VehicleGroup.missions
  fleet.events                     # -> the endpoints (above)
  fleet.ap                         # the operations' target
An in-flight start (the seed scenarios): ``Autopilot(..., in_flight=True)``: armed, AUTO,
flying, the scenario's pattern is AUTO's flight while no mission is loaded (bit-for-bit the
current run).  A ground start: ``in_flight=False``: disarmed, MANUAL, on the ground, speed 0,
until armed and taken off (TAKEOFF mode, or AUTO with a mission).
"""
from . import convention
from .config import AutopilotConfig, param_rows, with_param
from .core import Autopilot, Event, MissionResult, MissionStatus, Result
from .guidance import AutopilotLaw, Guidance
from .swarm import AutopilotSwarm

__all__ = ["convention", "AutopilotConfig", "param_rows", "with_param", "Autopilot", "Event", "MissionResult",
           "MissionStatus", "Result", "AutopilotLaw", "Guidance", "AutopilotSwarm"]
