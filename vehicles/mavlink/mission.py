"""The vehicle side of the MAVLink mission protocol, driven by simulation time.

mavlink.io "Mission Protocol":
  upload    GCS MISSION_COUNT(n) -> vehicle MISSION_REQUEST_INT(0) -> GCS MISSION_ITEM_INT(0)
            -> ... -> MISSION_REQUEST_INT(n-1) -> MISSION_ITEM_INT(n-1) -> vehicle MISSION_ACK.
            A missing item is re-requested after ``timeout_s`` (simulated) up to ``retries``
            times, then the upload is cancelled (MISSION_ACK OPERATION_CANCELLED).  Nothing
            ever waits: :meth:`MissionServer.step` checks the deadline.
  download  GCS MISSION_REQUEST_LIST -> MISSION_COUNT(n); each MISSION_REQUEST_INT(seq) /
            MISSION_REQUEST(seq) is answered with the stored item (stateless, the GCS retries).
  clear     MISSION_CLEAR_ALL -> MISSION_ACK ACCEPTED.

Only the plan type MISSION is stored, and only by a vehicle that accepts missions (a UAV);
fence and rally plans, and every plan of a sonde, download as zero items and refuse uploads
with MAV_MISSION_UNSUPPORTED, so that a GCS never stalls on them.

An accepted upload is handed to ``on_mission(waypoints)``: a list of (lat_rad, lon_rad,
alt_msl_m) of the items that carry a position (NAV_WAYPOINT, LOITER_*, TAKEOFF with a
position, LAND, SPLINE_WAYPOINT), in order; relative-altitude frames are converted with the
home height.  Other items (DO_*, CONDITION_*, RETURN_TO_LAUNCH) are kept for download and not
flown.  A clear calls ``on_mission([])``.  ``on_mission`` raising ValueError rejects the
upload (MAV_MISSION_ERROR) and the previous plan stays.

With an autopilot (``on_items``, the UAVs' vehicles.autopilot: ArduPlane's convention), an
accepted upload's items themselves go to ``on_items(items) -> (code, reason)``: its code is
the MISSION_ACK type (MAV_MISSION_UNSUPPORTED for an item it cannot fly, ...), and the plan is
stored only when it is ACCEPTED.  ``item_check(k, item, n) -> (code, reason)`` checks each item
as it arrives (the autopilot's rules): an item it refuses ends the upload at once with that
MISSION_ACK (ArduPilot answers the offending item; the GCS need not send the rest), the
previous plan stays.  Item 0 is home: ``home_item()`` gives the stored item 0 on download
(ArduPilot's rule: the GCS reads home there), and a vehicle without a mission downloads one
item, home.
"""
from __future__ import annotations

import math
from typing import Callable, NamedTuple

from pymavlink.dialects.v20 import ardupilotmega as mavlink

MAX_ITEMS = 1000

# commands whose x/y/z is a position to fly to
_POSITION_COMMANDS = frozenset({
    mavlink.MAV_CMD_NAV_WAYPOINT, mavlink.MAV_CMD_NAV_LOITER_UNLIM, mavlink.MAV_CMD_NAV_LOITER_TURNS,
    mavlink.MAV_CMD_NAV_LOITER_TIME, mavlink.MAV_CMD_NAV_LAND, mavlink.MAV_CMD_NAV_TAKEOFF,
    mavlink.MAV_CMD_NAV_LOITER_TO_ALT, mavlink.MAV_CMD_NAV_SPLINE_WAYPOINT,
})
_ABS_FRAMES = frozenset({mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_GLOBAL_INT})
_REL_FRAMES = frozenset({mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT})


class MissionItem(NamedTuple):
    """A stored item in MISSION_ITEM_INT units (x, y degE7; z m)."""

    seq: int
    frame: int
    command: int
    current: int
    autocontinue: int
    param1: float
    param2: float
    param3: float
    param4: float
    x: int
    y: int
    z: float


def item_from_msg(msg) -> MissionItem:
    """MISSION_ITEM_INT as is; MISSION_ITEM (float degrees) converted to degE7."""
    if msg.get_type() == "MISSION_ITEM":
        x = int(round(msg.x * 1e7)) if math.isfinite(msg.x) else 2**31
        y = int(round(msg.y * 1e7)) if math.isfinite(msg.y) else 2**31
    else:
        x, y = msg.x, msg.y
    return MissionItem(msg.seq, msg.frame, msg.command, msg.current, msg.autocontinue,
                       msg.param1, msg.param2, msg.param3, msg.param4, x, y, msg.z)


def check_item(it: MissionItem) -> int:
    """MAV_MISSION_RESULT for one item (ACCEPTED if we can fly or skip it)."""
    if it.command not in _POSITION_COMMANDS:
        return mavlink.MAV_MISSION_ACCEPTED
    if it.command == mavlink.MAV_CMD_NAV_TAKEOFF and it.x == 0 and it.y == 0:
        return mavlink.MAV_MISSION_ACCEPTED  # take off where it is: nothing to fly to
    if it.frame not in _ABS_FRAMES and it.frame not in _REL_FRAMES:
        return mavlink.MAV_MISSION_UNSUPPORTED_FRAME
    if not -900_000_000 <= it.x <= 900_000_000:
        return mavlink.MAV_MISSION_INVALID_PARAM5_X
    if not -1_800_000_000 <= it.y <= 1_800_000_000:
        return mavlink.MAV_MISSION_INVALID_PARAM6_Y
    if not math.isfinite(it.z):
        return mavlink.MAV_MISSION_INVALID_PARAM7
    return mavlink.MAV_MISSION_ACCEPTED


def mission_result_name(code: int) -> str:
    """MAV_MISSION_RESULT's name of a code (the number if it has none)."""
    e = mavlink.enums["MAV_MISSION_RESULT"]
    return e[code].name if code in e else str(code)


def waypoints_from_items(items, home_alt_msl_m: float) -> list[tuple[float, float, float]]:
    """(lat_rad, lon_rad, alt_msl_m) of the items that carry a position, in order."""
    out = []
    for it in items:
        if it.command not in _POSITION_COMMANDS or (it.command == mavlink.MAV_CMD_NAV_TAKEOFF and it.x == 0
                                                    and it.y == 0):
            continue
        alt = float(it.z) + (home_alt_msl_m if it.frame in _REL_FRAMES else 0.0)
        out.append((math.radians(it.x * 1e-7), math.radians(it.y * 1e-7), alt))
    return out


class MissionServer:
    """Per-endpoint mission state. ``send(addr, encode_name, *args)`` sends a message to addr."""

    def __init__(self, accepts_missions: bool, send: Callable, count: Callable[[str], None],
                 on_mission: Callable | None = None, home_alt: Callable[[], float] = lambda: 0.0,
                 timeout_s: float = 1.5, retries: int = 5, on_items: Callable | None = None,
                 home_item: Callable[[], MissionItem | None] | None = None,
                 item_check: Callable[[int, MissionItem, int], tuple[int, str]] | None = None):
        if not (timeout_s > 0 and math.isfinite(timeout_s)):
            raise ValueError(f"mission timeout_s must be > 0, got {timeout_s!r}")
        if int(retries) < 0:
            raise ValueError(f"mission retries must be >= 0, got {retries!r}")
        self.accepts = bool(accepts_missions)
        self._send = send
        self._count = count
        self._on_mission = on_mission
        self._home_alt = home_alt
        self._on_items = on_items
        self._home_item = home_item
        self._item_check = item_check
        self.timeout_s = float(timeout_s)
        self.retries = int(retries)
        self.items: list[MissionItem] = []
        self.last_reason = ""  # why the last upload was refused (on_items)
        # upload in progress: (addr, sysid, compid, n, received list, deadline, retries left)
        self._up = None

    @property
    def uploading(self) -> bool:
        return self._up is not None

    def _ack(self, addr, sys_, comp, result, mission_type):
        self._send(addr, "mission_ack_send", sys_, comp, result, mission_type)

    def handle(self, msg, addr, t_s: float) -> None:
        name = msg.get_type()
        src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        mtype = getattr(msg, "mission_type", 0)
        ours = self.accepts and mtype == mavlink.MAV_MISSION_TYPE_MISSION
        if name == "MISSION_REQUEST_LIST":
            self._send(addr, "mission_count_send", src_sys, src_comp, len(self._download()) if ours else 0, mtype)
        elif name in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
            if self._up is not None and self._up[0] == addr:
                return  # a GCS that uploads does not also download; ignore crossed traffic
            items = self._download() if ours else []
            if not 0 <= msg.seq < len(items):
                self._ack(addr, src_sys, src_comp, mavlink.MAV_MISSION_INVALID_SEQUENCE, mtype)
                self._count("mission_rejected")
                return
            it = items[msg.seq]
            if name == "MISSION_REQUEST_INT":
                self._send(addr, "mission_item_int_send", src_sys, src_comp, it.seq, it.frame, it.command,
                           it.current, it.autocontinue, it.param1, it.param2, it.param3, it.param4,
                           it.x, it.y, it.z, mtype)
            else:
                self._send(addr, "mission_item_send", src_sys, src_comp, it.seq, it.frame, it.command,
                           it.current, it.autocontinue, it.param1, it.param2, it.param3, it.param4,
                           it.x * 1e-7, it.y * 1e-7, it.z, mtype)
        elif name == "MISSION_COUNT":
            if not ours:
                self._ack(addr, src_sys, src_comp, mavlink.MAV_MISSION_UNSUPPORTED, mtype)
                self._count("mission_rejected")
            elif self._up is not None and self._up[0] != addr:
                self._ack(addr, src_sys, src_comp, mavlink.MAV_MISSION_DENIED, mtype)
                self._count("mission_rejected")
            elif msg.count > MAX_ITEMS:
                self._ack(addr, src_sys, src_comp, mavlink.MAV_MISSION_NO_SPACE, mtype)
                self._count("mission_rejected")
            elif msg.count == 0:
                self._up = None
                self._commit([], addr, src_sys, src_comp)
            else:
                self._up = [addr, src_sys, src_comp, msg.count, [], t_s + self.timeout_s, self.retries]
                self._request_next()
        elif name in ("MISSION_ITEM_INT", "MISSION_ITEM"):
            up = self._up
            if up is None or up[0] != addr or not ours:
                return  # not part of an upload we run: the spec says ignore
            rx = up[4]
            if msg.seq != len(rx):
                self._request_next()  # out of sequence (a duplicate after a retry): ask again
                return
            it = item_from_msg(msg)
            if self._item_check is not None:
                res, reason = self._item_check(len(rx), it, up[3])
            else:
                res, reason = check_item(it), ""
            if res != mavlink.MAV_MISSION_ACCEPTED:
                self._up = None
                self._ack(addr, src_sys, src_comp, res, mtype)
                self._count("mission_rejected")
                self.last_reason = reason or f"item {len(rx)}: {mission_result_name(res)}"
                return
            rx.append(it)
            up[5], up[6] = t_s + self.timeout_s, self.retries
            if len(rx) == up[3]:
                self._up = None
                self._commit(rx, addr, src_sys, src_comp)
            else:
                self._request_next()
        elif name == "MISSION_CLEAR_ALL":
            if ours:
                self._up = None
                self._commit([], addr, src_sys, src_comp)
            else:
                self._ack(addr, src_sys, src_comp, mavlink.MAV_MISSION_ACCEPTED, mtype)
        # MISSION_ACK from the GCS ends a download: nothing to do (stateless)

    def _request_next(self) -> None:
        addr, sys_, comp, _n, rx = self._up[:5]
        self._send(addr, "mission_request_int_send", sys_, comp, len(rx), mavlink.MAV_MISSION_TYPE_MISSION)

    def _download(self) -> list:
        """The items a GCS downloads: the stored plan, item 0 = home now (with an autopilot)."""
        home = self._home_item() if self._home_item is not None else None
        if home is None:
            return self.items
        return [home._replace(seq=0)] + list(self.items[1:])

    def _commit(self, items, addr, sys_, comp) -> None:
        if self._on_items is not None:
            code, reason = self._on_items(list(items))
            if code != mavlink.MAV_MISSION_ACCEPTED:
                self._ack(addr, sys_, comp, code, mavlink.MAV_MISSION_TYPE_MISSION)
                self._count("mission_rejected")
                self.last_reason = reason
                return
        elif self._on_mission is not None:
            try:
                self._on_mission(waypoints_from_items(items, self._home_alt()))
            except ValueError:
                self._ack(addr, sys_, comp, mavlink.MAV_MISSION_ERROR, mavlink.MAV_MISSION_TYPE_MISSION)
                self._count("mission_rejected")
                return
        self.items = list(items)
        self._ack(addr, sys_, comp, mavlink.MAV_MISSION_ACCEPTED, mavlink.MAV_MISSION_TYPE_MISSION)

    def step(self, t_s: float) -> None:
        up = self._up
        if up is None or t_s < up[5]:
            return
        if up[6] <= 0:
            self._up = None
            self._ack(up[0], up[1], up[2], mavlink.MAV_MISSION_OPERATION_CANCELLED, mavlink.MAV_MISSION_TYPE_MISSION)
            self._count("mission_timeout")
            return
        up[6] -= 1
        up[5] = t_s + self.timeout_s
        self._request_next()
