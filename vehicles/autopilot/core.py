"""The batched autopilot: N fixed-wing UAVs' modes, arming, flight phase and missions.

Pure: simulation time in, guidance and events out.  No I/O, no clock, no sleep, never an
exception for bad input (every operation returns a code and a one-line reason, and counts a
refusal in ``counters``).  See the package docstring for the API and the conventions.

State: arrays of shape (N,) (and (N, K) for the missions, K the longest mission).  One
:meth:`Autopilot.step` evaluates every UAV's transitions with masks over the batch; the only
Python loops are over item kinds, over the few DO items a mission walk passes, and over the
UAVs that have an event to report.

Behaviour registers (per UAV): ``kind`` (the guidance kind, vehicles.autopilot.guidance),
``tgt`` (lat, lon, alt of the point flown to / circled / landed at), ``radius`` (orbit),
``leg_heading``, ``task`` (what ends the current behaviour: a waypoint reached, loiter turns
or time done, an altitude reached, a touchdown...).  Mode entries, mission items and task
completions set the registers; :meth:`step` checks the tasks and builds the guidance.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.constants import Ellipsoid, ellipsoid

from . import convention as cv
from . import guidance as gd
from .config import AutopilotConfig

# tasks: what ends the current behaviour
T_NONE, T_APPROACH, T_WP, T_TURNS, T_TIME, T_ALT, T_CLIMB, T_ROLL, T_TKOFF, T_LAND, T_ROLLOUT, T_GLIDE = range(12)

MAV_CMD = mavlink
NAV_WAYPOINT = mavlink.MAV_CMD_NAV_WAYPOINT
LOITER_UNLIM = mavlink.MAV_CMD_NAV_LOITER_UNLIM
LOITER_TURNS = mavlink.MAV_CMD_NAV_LOITER_TURNS
LOITER_TIME = mavlink.MAV_CMD_NAV_LOITER_TIME
LOITER_TO_ALT = mavlink.MAV_CMD_NAV_LOITER_TO_ALT
NAV_RTL = mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH
NAV_TAKEOFF = mavlink.MAV_CMD_NAV_TAKEOFF
NAV_LAND = mavlink.MAV_CMD_NAV_LAND
DO_JUMP = mavlink.MAV_CMD_DO_JUMP
DO_CHANGE_SPEED = mavlink.MAV_CMD_DO_CHANGE_SPEED

#: mission items the vehicles fly (any other: MAV_MISSION_UNSUPPORTED with its index)
FLYABLE_ITEMS = frozenset({NAV_WAYPOINT, LOITER_UNLIM, LOITER_TURNS, LOITER_TIME, LOITER_TO_ALT, NAV_RTL,
                           NAV_TAKEOFF, NAV_LAND, DO_JUMP, DO_CHANGE_SPEED})
NAV_ITEMS = frozenset({NAV_WAYPOINT, LOITER_UNLIM, LOITER_TURNS, LOITER_TIME, LOITER_TO_ALT, NAV_RTL, NAV_TAKEOFF,
                       NAV_LAND})
POSITION_ITEMS = frozenset({NAV_WAYPOINT, LOITER_UNLIM, LOITER_TURNS, LOITER_TIME, LOITER_TO_ALT, NAV_TAKEOFF,
                            NAV_LAND})
_NAV_ARR = np.array(sorted(NAV_ITEMS))
ABS_FRAMES = frozenset({mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_GLOBAL_INT})
#: relative to home; the terrain frames too (the simulated world is flat at home's height)
REL_FRAMES = frozenset({mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                        mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT, mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT})

#: what a refusal is counted as (``Autopilot.counters``)
REFUSALS = ("bad_vehicle", "nonfinite", "bad_mode", "mode_unsupported", "unsupported_command", "bad_param",
            "disarmed", "in_flight", "not_in_mode", "unsupported_item", "bad_item", "bad_sequence", "no_mission",
            "bad_state", "internal_error")

_TAKEOFF_ALT_TOL_M = 2.0  # ArduPlane: take-off complete 2 m below the target altitude
_LOITER_ALT_TOL_M = 5.0
_TOUCHDOWN_M = 0.5
_FLARE_M = 2.0  # a landing aims this far below the ground, so that it crosses the touchdown height
_EPS = 1e-9


def _guarded(mission: bool = False):
    """An operation never raises: an exception is a refusal (counted 'internal_error', reason
    kept), so that a bug shows up in the counters and the ACK, not as a dead endpoint."""
    def wrap(fn):
        import functools

        @functools.wraps(fn)
        def op(self, *a, **kw):
            try:
                return fn(self, *a, **kw)
            except Exception as e:  # noqa: BLE001 - the contract: a code, never an exception
                reason = f"{fn.__name__}: {type(e).__name__}: {' '.join(str(e).split())}"
                if mission:
                    return self._refuse("internal_error", mavlink.MAV_MISSION_ERROR, reason, MissionResult)
                return self._refuse("internal_error", mavlink.MAV_RESULT_FAILED, reason)
        return op
    return wrap


class Result(NamedTuple):
    """A command's MAV_RESULT and a one-line reason ('' when accepted)."""

    code: int
    reason: str = ""

    @property
    def ok(self) -> bool:
        return self.code == mavlink.MAV_RESULT_ACCEPTED


class MissionResult(NamedTuple):
    """An upload's MAV_MISSION_RESULT, a one-line reason and the offending item's index (-1: none)."""

    code: int
    reason: str = ""
    index: int = -1

    @property
    def ok(self) -> bool:
        return self.code == mavlink.MAV_MISSION_ACCEPTED


class Event(NamedTuple):
    """Something the endpoint reports.  kind: 'mode' (value: the new custom mode), 'armed',
    'disarmed', 'item_reached' (value: seq -> MISSION_ITEM_REACHED), 'mission_current' (value:
    seq -> MISSION_CURRENT now), 'takeoff_complete', 'landed', 'mission_complete', 'text';
    severity: MAV_SEVERITY; text: the STATUSTEXT ArduPlane would send ('' for none)."""

    vehicle: int
    kind: str
    value: int
    severity: int
    text: str


class MissionStatus(NamedTuple):
    """MISSION_CURRENT's fields per UAV: seq (current item), total (items without home),
    state (MISSION_STATE_*)."""

    seq: np.ndarray
    total: np.ndarray
    state: np.ndarray


_INFO, _NOTICE, _WARNING = mavlink.MAV_SEVERITY_INFO, mavlink.MAV_SEVERITY_NOTICE, mavlink.MAV_SEVERITY_WARNING


def _wrap(a):
    return np.mod(a + np.pi, 2.0 * np.pi) - np.pi


def _finite(*v) -> bool:
    try:
        return all(math.isfinite(float(x)) for x in v)
    except (TypeError, ValueError):
        return False


def check_item(k: int, it, n: int) -> MissionResult:
    """Item k of an n-item upload: MAV_MISSION_ACCEPTED, or the code of what is wrong with it
    (pure; the MissionServer may call it item by item as they arrive)."""
    try:
        seq, frame, cmd = int(it.seq), int(it.frame), int(it.command)
        p = [float(it.param1), float(it.param2), float(it.param3), float(it.param4)]
        x, y, z = float(it.x), float(it.y), float(it.z)
    except (AttributeError, TypeError, ValueError, OverflowError):
        return MissionResult(mavlink.MAV_MISSION_ERROR, f"item {k}: not a mission item", k)
    if seq != k:
        return MissionResult(mavlink.MAV_MISSION_INVALID_SEQUENCE, f"item {k}: seq {seq}", k)
    if k == 0:
        return MissionResult(mavlink.MAV_MISSION_ACCEPTED)  # home: the vehicle's own
    if cmd not in FLYABLE_ITEMS:
        return MissionResult(mavlink.MAV_MISSION_UNSUPPORTED,
                             f"item {k}: {cv.command_name(cmd)} ({cmd}) cannot be flown", k)
    if cmd in POSITION_ITEMS:
        if frame not in ABS_FRAMES and frame not in REL_FRAMES:
            return MissionResult(mavlink.MAV_MISSION_UNSUPPORTED_FRAME, f"item {k}: frame {frame}", k)
        if not (math.isfinite(x) and -900_000_000 <= x <= 900_000_000):
            return MissionResult(mavlink.MAV_MISSION_INVALID_PARAM5_X, f"item {k}: latitude {x!r} degE7", k)
        if not (math.isfinite(y) and -1_800_000_000 <= y <= 1_800_000_000):
            return MissionResult(mavlink.MAV_MISSION_INVALID_PARAM6_Y, f"item {k}: longitude {y!r} degE7", k)
        if not math.isfinite(z):
            return MissionResult(mavlink.MAV_MISSION_INVALID_PARAM7, f"item {k}: altitude {z!r}", k)
    if cmd == LOITER_TURNS and not (math.isfinite(p[0]) and p[0] > 0):
        return MissionResult(mavlink.MAV_MISSION_INVALID_PARAM1, f"item {k}: turns {p[0]!r}", k)
    if cmd == LOITER_TIME and not (math.isfinite(p[0]) and p[0] >= 0):
        return MissionResult(mavlink.MAV_MISSION_INVALID_PARAM1, f"item {k}: time {p[0]!r} s", k)
    if cmd == DO_JUMP:
        if not (math.isfinite(p[0]) and p[0] == int(p[0]) and 1 <= p[0] < n and int(p[0]) != k):
            return MissionResult(mavlink.MAV_MISSION_INVALID_PARAM1, f"item {k}: DO_JUMP target {p[0]!r}", k)
        if not (math.isfinite(p[1]) and p[1] == int(p[1]) and p[1] >= -1):
            return MissionResult(mavlink.MAV_MISSION_INVALID_PARAM2, f"item {k}: DO_JUMP repeats {p[1]!r}", k)
    if cmd == DO_CHANGE_SPEED and not (math.isfinite(p[0]) and math.isfinite(p[1])):
        return MissionResult(mavlink.MAV_MISSION_INVALID_PARAM2, f"item {k}: speed {p[1]!r}", k)
    return MissionResult(mavlink.MAV_MISSION_ACCEPTED)


class Autopilot:
    """N UAVs' autopilots (see the module and package docstrings).

    lat_rad, lon_rad, alt_m, heading_rad: each UAV's position and heading now (N,); home: the
    same position unless given (home_*).  in_flight: (N,) bool or one bool: the UAV starts
    armed, in AUTO, flying (the seed scenarios) or disarmed in MANUAL on the ground
    (``[uavs] start = "ground"``).  scenario: (N,) bool or one bool: the UAV has a scenario
    flight pattern, which AUTO flies while no mission is loaded (guidance kind SCENARIO).
    """

    def __init__(self, lat_rad, lon_rad, alt_m, heading_rad=0.0, *, in_flight=True, scenario=None,
                 home_lat_rad=None, home_lon_rad=None, home_alt_m=None, config: AutopilotConfig | None = None,
                 t0_s: float = 0.0, ell: Ellipsoid | str | None = None):
        lat = np.atleast_1d(np.asarray(lat_rad, dtype=float))
        n = lat.shape[0]
        if lat.ndim != 1 or n < 1:
            raise ValueError(f"lat_rad must be a 1-D array of N >= 1 UAVs, got shape {np.shape(lat_rad)}")

        def vec(name, v, dtype=float):
            a = np.broadcast_to(np.asarray(v, dtype=dtype), (n,)).copy()
            if dtype is float and not np.all(np.isfinite(a)):
                raise ValueError(f"{name} must be finite, got {v!r}")
            return a

        self.n = n
        self.cfg = config if config is not None else AutopilotConfig()
        if not isinstance(self.cfg, AutopilotConfig):
            raise ValueError(f"config must be an AutopilotConfig, got {type(config).__name__}")
        self.ell = ellipsoid(ell)
        self.pos = np.stack([vec("lat_rad", lat), vec("lon_rad", lon_rad), vec("alt_m", alt_m)], axis=-1)
        self.psi = vec("heading_rad", heading_rad)
        self.t = float(t0_s)
        self.home = np.stack([vec("home_lat_rad", self.pos[:, 0] if home_lat_rad is None else home_lat_rad),
                              vec("home_lon_rad", self.pos[:, 1] if home_lon_rad is None else home_lon_rad),
                              vec("home_alt_m", self.pos[:, 2] if home_alt_m is None else home_alt_m)], axis=-1)
        fly = vec("in_flight", in_flight, bool)
        self.scenario = vec("scenario", fly if scenario is None else scenario, bool)
        self.armed = fly.copy()
        self.mode = np.where(fly, cv.AUTO, cv.MANUAL).astype(np.int64)
        self.phase = np.where(fly, cv.FLYING, cv.ON_GROUND).astype(np.int64)
        # behaviour registers
        self.kind = np.where(fly & self.scenario, gd.SCENARIO, gd.HOLD).astype(np.int64)
        self.task = np.full(n, T_NONE, dtype=np.int64)
        self.after = np.full(n, T_NONE, dtype=np.int64)  # the task after an approach
        self.tgt = self.pos.copy()
        self.prev = self.pos.copy()
        self.radius = np.full(n, self.cfg.wp_loiter_rad_m)
        self.leg_heading = self.psi.copy()
        self.accept = np.full(n, self.cfg.wp_radius_m)  # the waypoint's acceptance radius
        self.ground = self.home[:, 2].copy()  # the touchdown height of a landing / glide
        self.airspeed = np.full(n, self.cfg.airspeed_cruise_m_s)  # the navigation speed (DO_CHANGE_SPEED)
        self.speed_cmd = np.where(fly, self.cfg.airspeed_cruise_m_s, 0.0)
        self.t_stage = np.full(n, self.t)
        self.swept = np.zeros(n)
        self.last_brg = np.zeros(n)
        self.loiter_time = np.zeros(n)
        self.loiter_turns = np.zeros(n)
        self.takeoff_alt = np.zeros(n)  # absolute altitude of a running take-off
        self.takeoff_alt_req = np.full(n, np.nan)  # a take-off command's altitude above home (NaN: TKOFF_ALT)
        self.t_landed = np.full(n, -np.inf)
        self.guided = self.pos.copy()
        self.guided_radius = np.zeros(n)  # 0: WP_LOITER_RAD
        self.guided_pending = np.zeros(n, dtype=bool)
        self.pending_mode = np.full(n, -1, dtype=np.int64)  # a mode set during a take-off: entered after it
        # missions: (N, K) padded; item 0 home
        self.K = 1
        self.m_cmd = np.zeros((n, 1), dtype=np.int64)
        self.m_p = np.zeros((n, 1, 4))
        self.m_lat = np.full((n, 1), np.nan)
        self.m_lon = np.full((n, 1), np.nan)
        self.m_z = np.zeros((n, 1))
        self.m_rel = np.zeros((n, 1), dtype=bool)
        self.m_jumps = np.zeros((n, 1), dtype=np.int64)
        self.m_count = np.zeros(n, dtype=np.int64)
        self.cur = np.zeros(n, dtype=np.int64)
        self.m_state = np.full(n, mavlink.MISSION_STATE_NO_MISSION, dtype=np.int64)
        self.counters = dict.fromkeys(REFUSALS, 0)
        self.last_reason = ""
        self._events: list[Event] = []

    # ------------------------------------------------------------------ helpers
    def _refuse(self, key: str, code: int, reason: str, cls=Result, index: int | None = None):
        self.counters[key] = self.counters.get(key, 0) + 1
        self.last_reason = reason
        if cls is MissionResult:
            return MissionResult(code, reason, -1 if index is None else int(index))
        return Result(code, reason)

    def _vehicle(self, i):
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not 0 <= int(i) < self.n:
            return None
        return int(i)

    def _emit(self, i: int, kind: str, value: int = 0, text: str = "", severity: int = _INFO) -> None:
        self._events.append(Event(int(i), kind, int(value), int(severity), text))

    def _max_rate(self, speed):
        return self.cfg.max_turn_rate_rad_s(speed)

    def _orbit_radius(self, r, speed):
        """The radius flown: r, widened to 1.1 x the bank-limited turn radius at speed."""
        tight = np.asarray(speed, float) / self._max_rate(np.maximum(speed, self.cfg.airspeed_min_m_s))
        return np.maximum(r, 1.1 * tight)

    def _offsets(self, pos, tgt):
        return gd.offsets(pos[..., 0], pos[..., 1], pos[..., 2], tgt[..., 0], tgt[..., 1], self.ell)

    def _dist(self, pos, tgt):
        return np.hypot(*self._offsets(pos, tgt))

    def _project(self, lat, lon, h, heading, dist_m: float, alt: float):
        """The point dist_m from (lat, lon, h) along heading, at altitude alt (local flat metres)."""
        e = self.ell
        w2 = 1.0 - e.e2 * math.sin(lat) ** 2
        nn = e.a_m / math.sqrt(w2)
        m = nn * (1.0 - e.e2) / w2
        return np.array([lat + dist_m * math.cos(heading) / (m + h),
                         lon + dist_m * math.sin(heading) / ((nn + h) * math.cos(lat)), alt])

    def _ahead(self, i, dist_m: float, alt: float):
        """The point dist_m ahead of UAV i along its heading, at altitude alt."""
        lat, lon, h = self.pos[i]
        return self._project(lat, lon, h, self.psi[i], dist_m, alt)

    @property
    def airborne(self) -> np.ndarray:
        return np.isin(self.phase, (cv.TAKING_OFF, cv.FLYING, cv.LANDING)) & (self.task != T_ROLLOUT)

    # ------------------------------------------------------------------ behaviours
    def _set_orbit(self, i, centre, radius=None) -> None:
        self.kind[i], self.task[i] = gd.ORBIT, T_NONE
        self.tgt[i] = centre
        self.radius[i] = self.cfg.wp_loiter_rad_m if radius is None or not radius > 0 else radius

    def _set_approach(self, i, point, radius, after=T_NONE) -> None:
        """Fly to point, then circle it (radius) with task ``after``."""
        self.kind[i], self.task[i], self.after[i] = gd.GOTO, T_APPROACH, after
        self.tgt[i] = point
        self.prev[i] = self.pos[i]
        self.radius[i] = radius
        self.t_stage[i] = self.t

    def _set_leg(self, i, heading, alt, task=T_NONE) -> None:
        self.kind[i], self.task[i] = gd.LEG, task
        self.leg_heading[i] = heading
        self.tgt[i] = (self.pos[i, 0], self.pos[i, 1], alt)

    def _set_land(self, i, point) -> None:
        self.phase[i] = cv.LANDING
        self.kind[i], self.task[i] = gd.LAND, T_LAND
        self.tgt[i] = (point[0], point[1], point[2] - _FLARE_M)  # aims below the ground: it touches down
        self.prev[i] = self.pos[i]
        self.ground[i] = point[2]
        self.airspeed[i] = self.cfg.airspeed_min_m_s

    def _enter(self, i: int, mode: int, reason_text: str = "") -> None:
        """Mode entry of UAV i (mode already valid): set the behaviour registers."""
        old = int(self.mode[i])
        if old == cv.AUTO and mode != cv.AUTO and self.m_state[i] == mavlink.MISSION_STATE_ACTIVE:
            self.m_state[i] = mavlink.MISSION_STATE_PAUSED
        self.mode[i] = mode
        if old != mode:
            self._emit(i, "mode", mode, reason_text)
        ph = int(self.phase[i])
        if ph == cv.TAKING_OFF:
            self.pending_mode[i] = mode  # the take-off goes on; the mode starts when it is complete
            return
        if ph == cv.LANDING and self.task[i] == T_LAND and mode != cv.AUTOLAND:
            self.phase[i] = cv.FLYING  # a go-around
            self.airspeed[i] = self.cfg.airspeed_cruise_m_s
        if ph == cv.LANDING and self.task[i] == T_GLIDE:
            return  # motor off (a forced disarm): it glides whatever the mode
        if ph in (cv.ON_GROUND, cv.LANDED) or self.task[i] == T_ROLLOUT or not self.armed[i]:
            if mode == cv.AUTO and self.m_count[i] > 1 and self.m_state[i] != mavlink.MISSION_STATE_PAUSED:
                self._mission_restart(i, walk=True)
            return  # on the ground every mode waits (a take-off starts in step)
        pos = self.pos[i]
        if mode == cv.AUTO:
            self._auto_enter(i)
        elif mode == cv.GUIDED:
            if self.guided_pending[i]:  # a target given while it could not be flown (a take-off)
                self.guided_pending[i] = False
                self._set_approach(i, self.guided[i].copy(), self.cfg.wp_radius_m)
            else:  # ArduPlane: GUIDED without a target circles the current position
                self.guided[i] = pos
                self._set_orbit(i, pos, self.guided_radius[i] or None)
        elif mode in (cv.LOITER, cv.CIRCLE):
            self._set_orbit(i, pos)
        elif mode == cv.RTL:
            self._rtl(i)
        elif mode == cv.TAKEOFF:
            alt = self.home[i, 2] + self._takeoff_rel(i)
            self._set_orbit(i, self._ahead(i, self.cfg.tkoff_dist_m, max(alt, pos[2])))
            self._emit(i, "text", 0, "Above TKOFF alt - loitering" if pos[2] >= alt else
                       "Climbing to TKOFF alt then loitering")
        elif mode == cv.AUTOLAND:
            self._set_land(i, self.home[i].copy())
        else:  # pilot modes, centred sticks: straight and level
            self._set_leg(i, self.psi[i], pos[2])

    def _takeoff_rel(self, i) -> float:
        r = self.takeoff_alt_req[i]
        return float(r) if r == r else self.cfg.tkoff_alt_m

    def _rtl(self, i) -> None:
        alt = self.pos[i, 2] if self.cfg.rtl_altitude_m < 0 else self.home[i, 2] + self.cfg.rtl_altitude_m
        c = np.array([self.home[i, 0], self.home[i, 1], alt])
        self._set_approach(i, c, self.cfg.rtl_radius_eff_m)

    def _auto_enter(self, i) -> None:
        if self.m_count[i] <= 1:
            if self.scenario[i]:
                self.kind[i], self.task[i] = gd.SCENARIO, T_NONE
                return
            self._emit(i, "text", 0, "Mission complete, changing mode to RTL")
            self._enter(i, cv.RTL)
            return
        if self.m_state[i] == mavlink.MISSION_STATE_PAUSED:
            self.m_state[i] = mavlink.MISSION_STATE_ACTIVE
            self._goto_item(np.array([i]), self.cur[[i]])
        else:
            self._mission_restart(i, walk=True)

    # ------------------------------------------------------------------ missions
    def _mission_restart(self, i, walk=True) -> None:
        self.m_jumps[i, :] = np.where(self.m_cmd[i] == DO_JUMP, self.m_p[i, :, 1].astype(np.int64), 0)
        self.m_state[i] = mavlink.MISSION_STATE_ACTIVE if self.mode[i] == cv.AUTO else mavlink.MISSION_STATE_NOT_STARTED
        if walk:
            self._goto_item(np.array([i]), np.array([cv.FIRST_ITEM]))

    def _item_point(self, idx, cur, pos):
        """(M, 3) absolute targets of items cur of UAVs idx; 'here' (lat/lon NaN) -> pos."""
        lat = self.m_lat[idx, cur]
        lon = self.m_lon[idx, cur]
        here = ~np.isfinite(lat)
        z = self.m_z[idx, cur] + np.where(self.m_rel[idx, cur], self.home[idx, 2], 0.0)
        return np.stack([np.where(here, pos[:, 0], lat), np.where(here, pos[:, 1], lon), z], axis=-1)

    def _goto_item(self, idx, start, prev=None) -> None:
        """Walk UAVs idx from item ``start`` to the next navigation item (running DO items:
        DO_CHANGE_SPEED applies, DO_JUMP jumps while it has repeats left), then start it; past
        the last item the mission is complete (ArduPlane: RTL)."""
        idx = np.asarray(idx, dtype=np.int64)
        cur = np.asarray(start, dtype=np.int64).copy()
        count = self.m_count[idx]
        active = np.ones(idx.size, dtype=bool)
        done = np.zeros(idx.size, dtype=bool)
        for _ in range(2 * self.K + 8):
            if not active.any():
                break
            past = active & (cur >= count)
            done |= past
            active &= ~past
            c = self.m_cmd[idx, np.minimum(cur, self.K - 1)]
            active &= ~np.isin(c, _NAV_ARR)
            spd = active & (c == DO_CHANGE_SPEED)
            for j in np.flatnonzero(spd):
                self._do_change_speed(int(idx[j]), self.m_p[idx[j], cur[j]])
                self._emit(int(idx[j]), "item_reached", int(cur[j]))
            jmp = active & (c == DO_JUMP)
            left = self.m_jumps[idx, np.minimum(cur, self.K - 1)]
            take = jmp & (left != 0)
            dec = take & (left > 0)
            self.m_jumps[idx[dec], cur[dec]] -= 1
            target = self.m_p[idx, np.minimum(cur, self.K - 1), 0].astype(np.int64)
            cur = np.where(take, target, np.where(active, cur + 1, cur))
        if active.any():  # DO items jumping among themselves: no navigation item to fly
            for j in np.flatnonzero(active):
                self._emit(int(idx[j]), "text", 0, "Mission: a DO_JUMP loop without a navigation item", _WARNING)
            done |= active
        changed = cur != self.cur[idx]
        self.cur[idx] = np.minimum(cur, np.maximum(count - 1, 0))
        for j in np.flatnonzero(changed & ~done):
            self._emit(int(idx[j]), "mission_current", int(cur[j]))
        fin = idx[done]
        for i in fin.tolist():
            self._mission_complete(i)
        go = idx[~done]
        if go.size:
            self._start_item(go, self.pos[go] if prev is None else np.asarray(prev)[~done])

    def _mission_complete(self, i: int) -> None:
        self.m_state[i] = mavlink.MISSION_STATE_COMPLETE
        self._emit(i, "mission_complete", int(self.cur[i]))
        if self.mode[i] != cv.AUTO:
            return
        if self.phase[i] in (cv.FLYING, cv.LANDING) and self.task[i] != T_ROLLOUT:
            self._emit(i, "text", 0, "Mission complete, changing mode to RTL")
            self._enter(i, cv.RTL)

    def _start_item(self, idx, prev) -> None:
        """Start the navigation items cur of UAVs idx (prev: the leg's start point)."""
        cur = self.cur[idx]
        c = self.m_cmd[idx, cur]
        p = self.m_p[idx, cur]
        pts = self._item_point(idx, cur, self.pos[idx])
        self.t_stage[idx] = self.t
        self.swept[idx] = 0.0
        for k, i in enumerate(idx.tolist()):
            if self.mode[i] != cv.AUTO:
                continue
            self.prev[i] = prev[k]
            ci, pi, pt = int(c[k]), p[k], pts[k]
            if self.phase[i] in (cv.ON_GROUND, cv.LANDED) or self.task[i] == T_ROLLOUT:
                continue  # a take-off starts it (step)
            if self.phase[i] == cv.TAKING_OFF:
                continue
            if ci == NAV_WAYPOINT:
                self.kind[i], self.task[i] = gd.GOTO, T_WP
                self.tgt[i] = pt
                self.accept[i] = pi[1] if pi[1] > 0 else self.cfg.wp_radius_m
            elif ci in (LOITER_UNLIM, LOITER_TURNS, LOITER_TIME, LOITER_TO_ALT):
                r = abs(pi[1] if ci == LOITER_TO_ALT else pi[2])
                r = r if r > 0 else self.cfg.wp_loiter_rad_m
                after = {LOITER_UNLIM: T_NONE, LOITER_TURNS: T_TURNS, LOITER_TIME: T_TIME, LOITER_TO_ALT: T_ALT}[ci]
                self.loiter_turns[i] = pi[0] if ci == LOITER_TURNS else 0.0
                self.loiter_time[i] = pi[0] if ci == LOITER_TIME else 0.0
                self._set_approach(i, pt, r, after)
                self.prev[i] = prev[k]
            elif ci == NAV_TAKEOFF:  # in the air: climb along the heading to its altitude
                self._set_leg(i, self.psi[i], max(pt[2], self.pos[i, 2]) + self.cfg.climb_max_m_s / gd.K_CLIMB_1_S,
                              T_CLIMB)
                self.takeoff_alt[i] = pt[2]
            elif ci == NAV_LAND:
                here = not np.isfinite(self.m_lat[i, cur[k]])
                point = pt if not here else self._ahead(i, max(self.pos[i, 2] - pt[2], 0.0) / self.cfg.land_slope,
                                                        pt[2])
                self._set_land(i, point)
            elif ci == NAV_RTL:
                self._emit(i, "text", 0, "Mission: RTL")
                self._enter(i, cv.RTL)

    def _item_done(self, idx) -> None:
        """The current navigation items of UAVs idx are complete: MISSION_ITEM_REACHED, then the next."""
        idx = np.asarray(idx, dtype=np.int64)
        if not idx.size:
            return
        for i in idx.tolist():
            self._emit(i, "item_reached", int(self.cur[i]), f"Reached waypoint #{int(self.cur[i])}")
        prev = self.tgt[idx].copy()
        self._goto_item(idx, self.cur[idx] + 1, prev)

    def _do_change_speed(self, i: int, p) -> bool:
        """DO_CHANGE_SPEED (param1 speed type, param2 speed m/s, -1: no change, -2: default)."""
        s = float(p[1])
        if s == -2.0:
            self.airspeed[i] = self.cfg.airspeed_cruise_m_s
            return True
        if s > 0 and self.cfg.airspeed_min_m_s <= s <= self.cfg.airspeed_max_m_s:
            self.airspeed[i] = s
            self._emit(i, "text", 0, f"Set airspeed {s:.0f} m/s")
            return True
        return s == -1.0

    # ------------------------------------------------------------------ operations (each: a code, a reason)
    @_guarded()
    def arm(self, i, arm: bool = True, force: bool = False) -> Result:
        """MAV_CMD_COMPONENT_ARM_DISARM (param1 1 / 0, param2 21196: force).  Arming on the
        ground sets home to the current position (ArduPlane).  Disarming in the air is refused
        (MAV_RESULT_FAILED, as ArduPlane) unless forced: then the UAV glides down (motor off)."""
        v = self._vehicle(i)
        if v is None:
            return self._refuse("bad_vehicle", mavlink.MAV_RESULT_DENIED, f"no UAV {i!r}")
        if arm:
            if self.armed[v]:
                return Result(mavlink.MAV_RESULT_ACCEPTED)
            self.armed[v] = True
            if self.task[v] == T_GLIDE:  # motor on again in the glide: fly the mode
                self.phase[v] = cv.FLYING
                self.airspeed[v] = self.cfg.airspeed_cruise_m_s
                self._enter(v, int(self.mode[v]))
            if self.phase[v] in (cv.ON_GROUND, cv.LANDED):
                if self.m_state[v] == mavlink.MISSION_STATE_COMPLETE:
                    self.m_state[v] = mavlink.MISSION_STATE_NOT_STARTED  # arming in AUTO flies it again
                self.home[v] = self.pos[v]
                self.ground[v] = self.pos[v, 2]
                self.phase[v] = cv.ON_GROUND
            self._emit(v, "armed", 1, "Arming motors")
            return Result(mavlink.MAV_RESULT_ACCEPTED)
        if not self.armed[v]:
            return Result(mavlink.MAV_RESULT_ACCEPTED)
        if self.airborne[v] and not force:
            return self._refuse("in_flight", mavlink.MAV_RESULT_FAILED,
                                "disarm refused: flying (force with param2 = 21196)")
        self.armed[v] = False
        self._emit(v, "disarmed", 0, "Disarming motors")
        if self.airborne[v]:
            self.phase[v] = cv.LANDING
            self.ground[v] = self.home[v, 2]
            self.airspeed[v] = self.cfg.airspeed_min_m_s
            self._set_leg(v, self.psi[v], self.home[v, 2] - 1e4, T_GLIDE)
        elif self.phase[v] == cv.TAKING_OFF or self.task[v] == T_ROLLOUT:
            self.phase[v] = cv.ON_GROUND
            self.kind[v], self.task[v] = gd.HOLD, T_NONE
        return Result(mavlink.MAV_RESULT_ACCEPTED)

    @_guarded()
    def set_mode(self, i, custom_mode, base_mode: int = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED) -> Result:
        """SET_MODE / MAV_CMD_DO_SET_MODE (param1 base_mode, param2 custom_mode).  A number
        ArduPlane does not have: DENIED; one it has but these vehicles cannot fly (the
        quadplane modes, AUTOTUNE, THERMAL...): FAILED; base_mode without CUSTOM_MODE_ENABLED:
        DENIED (ArduPilot)."""
        v = self._vehicle(i)
        if v is None:
            return self._refuse("bad_vehicle", mavlink.MAV_RESULT_DENIED, f"no UAV {i!r}")
        if not _finite(custom_mode, base_mode) or float(custom_mode) != int(float(custom_mode)):
            return self._refuse("nonfinite", mavlink.MAV_RESULT_DENIED,
                                f"mode must be an integer, got {custom_mode!r}")
        if not int(float(base_mode)) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return self._refuse("bad_mode", mavlink.MAV_RESULT_DENIED,
                                f"base_mode {int(float(base_mode))} without CUSTOM_MODE_ENABLED")
        m = int(float(custom_mode))
        if m not in cv.MODE_NAMES:
            self._emit(v, "text", 0, f"No such mode {m}", _WARNING)
            return self._refuse("bad_mode", mavlink.MAV_RESULT_DENIED, f"no such mode {m} (ArduPlane)")
        if m not in cv.SUPPORTED_MODES:
            return self._refuse("mode_unsupported", mavlink.MAV_RESULT_FAILED,
                                f"mode {cv.mode_name(m)} is not flown by this vehicle")
        if m != self.mode[v] or self.phase[v] == cv.TAKING_OFF:  # ArduPlane: the same mode again changes nothing
            self._enter(v, m)
        return Result(mavlink.MAV_RESULT_ACCEPTED)

    @_guarded()
    def takeoff(self, i, alt_rel_m=None) -> Result:
        """MAV_CMD_NAV_TAKEOFF (param7 altitude above home; NaN / 0 / None: TKOFF_ALT): TAKEOFF
        mode.  Refused (FAILED) when disarmed.  (ArduPlane accepts this command only on a
        quadplane; a fixed-wing GCS user sets TAKEOFF mode and arms -- which works too.)"""
        v = self._vehicle(i)
        if v is None:
            return self._refuse("bad_vehicle", mavlink.MAV_RESULT_DENIED, f"no UAV {i!r}")
        a = math.nan if alt_rel_m is None else alt_rel_m
        if not (a != a or _finite(a)):
            return self._refuse("nonfinite", mavlink.MAV_RESULT_DENIED, f"take-off altitude {alt_rel_m!r}")
        a = float(a)
        if a == a and a < 0:
            return self._refuse("bad_param", mavlink.MAV_RESULT_DENIED, f"take-off altitude {a:g} m < 0")
        if not self.armed[v]:
            return self._refuse("disarmed", mavlink.MAV_RESULT_FAILED, "take-off refused: disarmed (arm first)")
        self.takeoff_alt_req[v] = a if a > 0 else math.nan
        self._enter(v, cv.TAKEOFF)
        return Result(mavlink.MAV_RESULT_ACCEPTED)

    @_guarded()
    def goto(self, i, lat_rad, lon_rad, alt_m, *, relative_alt: bool = True, radius_m=None, speed_m_s=None,
             change_mode: bool = True) -> Result:
        """GUIDED to a point: MAV_CMD_DO_REPOSITION (param1 speed, -1 default; param2 flags,
        MAV_DO_REPOSITION_FLAGS_CHANGE_MODE; param3 loiter radius, 0 default), MISSION_ITEM_INT
        with current = 2 (MAVProxy's ``guided`` when guided_use_reposition is off),
        SET_POSITION_TARGET_GLOBAL_INT.  alt_m above home (relative_alt) or MSL.  The UAV flies
        to the point, then circles it.  Non-finite or out-of-range position: DENIED; not in
        GUIDED and change_mode false: FAILED (ArduPlane)."""
        v = self._vehicle(i)
        if v is None:
            return self._refuse("bad_vehicle", mavlink.MAV_RESULT_DENIED, f"no UAV {i!r}")
        if not _finite(lat_rad, lon_rad, alt_m):
            return self._refuse("nonfinite", mavlink.MAV_RESULT_DENIED,
                                f"guided target not finite: {lat_rad!r}, {lon_rad!r}, {alt_m!r}")
        la, lo, al = float(lat_rad), float(lon_rad), float(alt_m)
        if abs(la) >= 0.5 * math.pi or abs(lo) > math.pi:
            return self._refuse("bad_param", mavlink.MAV_RESULT_DENIED,
                                f"guided target outside the globe: lat {math.degrees(la):g}, lon {math.degrees(lo):g}")
        if not change_mode and self.mode[v] != cv.GUIDED:
            return self._refuse("not_in_mode", mavlink.MAV_RESULT_FAILED,
                                f"reposition without CHANGE_MODE in {cv.mode_name(self.mode[v])}")
        if speed_m_s is not None and _finite(speed_m_s) and float(speed_m_s) > 0:
            s = float(speed_m_s)
            if not self.cfg.airspeed_min_m_s <= s <= self.cfg.airspeed_max_m_s:
                return self._refuse("bad_param", mavlink.MAV_RESULT_DENIED,
                                    f"speed {s:g} m/s outside AIRSPEED_MIN..AIRSPEED_MAX")
            self.airspeed[v] = s
        r = float(radius_m) if radius_m is not None and _finite(radius_m) and float(radius_m) > 0 else 0.0
        self.guided_radius[v] = r
        pt = np.array([la, lo, al + (self.home[v, 2] if relative_alt else 0.0)])
        if self.mode[v] != cv.GUIDED:
            self._enter(v, cv.GUIDED)
        self.guided[v] = pt
        if self.airborne[v] and self.phase[v] != cv.TAKING_OFF:
            self.phase[v] = cv.FLYING
            self._set_approach(v, pt, self.cfg.wp_radius_m, T_NONE)
        else:  # on the ground or taking off: flown once it flies in GUIDED
            self.guided_pending[v] = True
        return Result(mavlink.MAV_RESULT_ACCEPTED)

    def rtl(self, i) -> Result:
        """MAV_CMD_NAV_RETURN_TO_LAUNCH: RTL mode (home at RTL_ALTITUDE, then circle home)."""
        return self.set_mode(i, cv.RTL)

    def loiter(self, i) -> Result:
        """MAV_CMD_NAV_LOITER_UNLIM as a command: LOITER mode (circle the current position)."""
        return self.set_mode(i, cv.LOITER)

    @_guarded()
    def land(self, i, lat_rad=None, lon_rad=None, alt_m=None, *, relative_alt: bool = True) -> Result:
        """MAV_CMD_NAV_LAND as a command: AUTOLAND mode at the point (param5/6; NaN or None:
        straight ahead on the glide slope, MAVLink's "current position"; param7 ground altitude,
        NaN: home's).  Refused (FAILED) on the ground."""
        v = self._vehicle(i)
        if v is None:
            return self._refuse("bad_vehicle", mavlink.MAV_RESULT_DENIED, f"no UAV {i!r}")
        vals = [math.nan if x is None else x for x in (lat_rad, lon_rad, alt_m)]
        try:
            vals = [float(x) for x in vals]
        except (TypeError, ValueError):
            return self._refuse("bad_param", mavlink.MAV_RESULT_DENIED, f"landing point {vals!r}")
        la, lo, al = vals
        if math.isinf(la) or math.isinf(lo) or math.isinf(al) or ((la == la) != (lo == lo)):
            return self._refuse("nonfinite", mavlink.MAV_RESULT_DENIED, f"landing point {la!r}, {lo!r}")
        if la == la and (abs(la) >= 0.5 * math.pi or abs(lo) > math.pi):
            return self._refuse("bad_param", mavlink.MAV_RESULT_DENIED, "landing point outside the globe")
        if not self.airborne[v]:
            return self._refuse("bad_state", mavlink.MAV_RESULT_FAILED, "land refused: not flying")
        ground = self.home[v, 2] if al != al else al + (self.home[v, 2] if relative_alt else 0.0)
        if la == la:
            pt = np.array([la, lo, ground])
        else:
            pt = self._ahead(v, max(self.pos[v, 2] - ground, 0.0) / self.cfg.land_slope, ground)
        self._enter(v, cv.AUTOLAND)
        if self.phase[v] != cv.TAKING_OFF:
            self._set_land(v, pt)
        return Result(mavlink.MAV_RESULT_ACCEPTED)

    @_guarded()
    def mission_start(self, i, first=0, last=0) -> Result:
        """MAV_CMD_MISSION_START: AUTO from item 1 (first / last other than 0: DENIED, ArduPlane)."""
        v = self._vehicle(i)
        if v is None:
            return self._refuse("bad_vehicle", mavlink.MAV_RESULT_DENIED, f"no UAV {i!r}")
        if not _finite(first, last) or float(first) != 0 or float(last) != 0:
            return self._refuse("bad_param", mavlink.MAV_RESULT_DENIED, "MISSION_START first/last items unsupported")
        if self.m_count[v] > 1 and self.mode[v] != cv.AUTO:
            self.m_state[v] = mavlink.MISSION_STATE_NOT_STARTED  # start, not resume
        return self.set_mode(v, cv.AUTO)

    @_guarded()
    def change_speed(self, i, speed_type, speed_m_s) -> Result:
        """MAV_CMD_DO_CHANGE_SPEED as a command: only in AUTO / GUIDED (FAILED else, ArduPlane);
        an airspeed outside AIRSPEED_MIN..MAX: FAILED."""
        v = self._vehicle(i)
        if v is None:
            return self._refuse("bad_vehicle", mavlink.MAV_RESULT_DENIED, f"no UAV {i!r}")
        if not _finite(speed_type, speed_m_s):
            return self._refuse("nonfinite", mavlink.MAV_RESULT_DENIED, f"speed {speed_m_s!r}")
        if self.mode[v] not in (cv.AUTO, cv.GUIDED):
            return self._refuse("not_in_mode", mavlink.MAV_RESULT_FAILED,
                                f"change speed refused in {cv.mode_name(self.mode[v])}")
        if not self._do_change_speed(v, (speed_type, speed_m_s, 0.0, 0.0)):
            return self._refuse("bad_param", mavlink.MAV_RESULT_FAILED,
                                f"speed {float(speed_m_s):g} m/s outside AIRSPEED_MIN..AIRSPEED_MAX")
        return Result(mavlink.MAV_RESULT_ACCEPTED)

    @_guarded()
    def set_home(self, i, lat_rad=None, lon_rad=None, alt_m=None, use_current: bool = False) -> Result:
        """MAV_CMD_DO_SET_HOME (param1 1: the current position; else param5..7, MSL)."""
        v = self._vehicle(i)
        if v is None:
            return self._refuse("bad_vehicle", mavlink.MAV_RESULT_DENIED, f"no UAV {i!r}")
        if use_current:
            self.home[v] = self.pos[v]
        else:
            if not _finite(lat_rad, lon_rad, alt_m):
                return self._refuse("nonfinite", mavlink.MAV_RESULT_DENIED, "home not finite")
            if abs(float(lat_rad)) >= 0.5 * math.pi or abs(float(lon_rad)) > math.pi:
                return self._refuse("bad_param", mavlink.MAV_RESULT_DENIED, "home outside the globe")
            self.home[v] = (float(lat_rad), float(lon_rad), float(alt_m))
        if self.mode[v] == cv.RTL and self.airborne[v]:
            self._rtl(v)  # ArduPlane: in RTL head to the new home
        return Result(mavlink.MAV_RESULT_ACCEPTED)

    @_guarded(mission=True)
    def set_mission(self, i, items) -> MissionResult:
        """A complete uploaded mission (items with seq, frame, command, param1..4, x, y (degE7),
        z: vehicles.mavlink.mission.MissionItem or MISSION_ITEM_INT messages).  Item 0 is home
        (content ignored).  Any item not in FLYABLE_ITEMS: MAV_MISSION_UNSUPPORTED with its
        index; a bad frame / position / parameter: the MAV_MISSION_* code of that field.  The
        previous mission stays on a refusal.  Accepted: the mission restarts at item 1; in AUTO
        (in the air) the UAV flies it at once.  An empty list clears the mission."""
        v = self._vehicle(i)
        if v is None:
            return self._refuse("bad_vehicle", mavlink.MAV_MISSION_ERROR, f"no UAV {i!r}", MissionResult)
        try:
            items = list(items)
        except TypeError:
            return self._refuse("bad_item", mavlink.MAV_MISSION_ERROR, "items is not a sequence", MissionResult)
        rows = []
        n = len(items)
        for k, it in enumerate(items):
            res = self._check_item(k, it, n)
            if not res.ok:
                self.counters["unsupported_item" if res.code == mavlink.MAV_MISSION_UNSUPPORTED else "bad_item"] += 1
                self.last_reason = res.reason
                return res
            rows.append(res)
        self._store_mission(v, items)
        return MissionResult(mavlink.MAV_MISSION_ACCEPTED)

    def _check_item(self, k: int, it, n: int) -> MissionResult:
        return check_item(k, it, n)

    def _store_mission(self, v: int, items) -> None:
        n = len(items)
        if n > self.K:
            grow = n - self.K
            pad = lambda a, val: np.concatenate([a, np.full(a.shape[:1] + (grow,) + a.shape[2:], val, a.dtype)], 1)
            self.m_cmd, self.m_p, self.m_lat = pad(self.m_cmd, 0), pad(self.m_p, 0.0), pad(self.m_lat, np.nan)
            self.m_lon, self.m_z, self.m_rel = pad(self.m_lon, np.nan), pad(self.m_z, 0.0), pad(self.m_rel, False)
            self.m_jumps = pad(self.m_jumps, 0)
            self.K = n
        self.m_cmd[v] = 0
        self.m_p[v] = 0.0
        self.m_lat[v] = np.nan
        self.m_lon[v] = np.nan
        self.m_z[v] = 0.0
        self.m_rel[v] = False
        for k, it in enumerate(items):
            if k == 0:
                continue
            self.m_cmd[v, k] = int(it.command)
            self.m_p[v, k] = (float(it.param1), float(it.param2), float(it.param3), float(it.param4))
            x, y = float(it.x), float(it.y)
            if int(it.command) in POSITION_ITEMS and not (x == 0 and y == 0):  # 0, 0: here (ArduPilot)
                self.m_lat[v, k], self.m_lon[v, k] = math.radians(x * 1e-7), math.radians(y * 1e-7)
            self.m_z[v, k] = float(it.z)
            self.m_rel[v, k] = int(it.frame) in REL_FRAMES
        self.m_count[v] = n
        old = int(self.cur[v])
        self.cur[v] = cv.FIRST_ITEM if n > 1 else 0
        if n <= 1:
            self.m_state[v] = mavlink.MISSION_STATE_NO_MISSION
            if self.mode[v] == cv.AUTO and self.airborne[v] and self.phase[v] != cv.TAKING_OFF:
                self._auto_enter(v)  # the scenario's pattern, or RTL
            return
        self.cur[v] = old  # _goto_item reports the change
        self._mission_restart(v, walk=False)
        if self.mode[v] == cv.AUTO:
            self.m_state[v] = mavlink.MISSION_STATE_ACTIVE
            if self.phase[v] == cv.LANDING and self.task[v] == T_LAND:
                self.phase[v] = cv.FLYING  # a go-around into the new mission
            self._goto_item(np.array([v]), np.array([cv.FIRST_ITEM]))
        else:
            self.cur[v] = cv.FIRST_ITEM
            if old != cv.FIRST_ITEM:
                self._emit(v, "mission_current", cv.FIRST_ITEM)

    @_guarded()
    def set_current(self, i, seq, reset_jumps: bool = False) -> Result:
        """MISSION_SET_CURRENT / MAV_CMD_DO_SET_MISSION_CURRENT (param1 seq, param2 1: reset the
        DO_JUMP counters).  seq 0 (home) restarts at item 1; a seq past the mission: DENIED.  In
        AUTO the UAV flies the item at once; else AUTO resumes there."""
        v = self._vehicle(i)
        if v is None:
            return self._refuse("bad_vehicle", mavlink.MAV_RESULT_DENIED, f"no UAV {i!r}")
        if not _finite(seq) or float(seq) != int(float(seq)):
            return self._refuse("nonfinite", mavlink.MAV_RESULT_DENIED, f"seq {seq!r}")
        s = int(float(seq))
        if self.m_count[v] <= 1:
            return self._refuse("no_mission", mavlink.MAV_RESULT_DENIED, "no mission")
        if not 0 <= s < self.m_count[v]:
            return self._refuse("bad_sequence", mavlink.MAV_RESULT_DENIED,
                                f"seq {s} outside the mission (0..{int(self.m_count[v]) - 1})")
        if s == 0:
            s = cv.FIRST_ITEM
        if reset_jumps:
            self.m_jumps[v, :] = np.where(self.m_cmd[v] == DO_JUMP, self.m_p[v, :, 1].astype(np.int64), 0)
        if self.mode[v] == cv.AUTO and self.airborne[v] and self.phase[v] != cv.TAKING_OFF:
            self.m_state[v] = mavlink.MISSION_STATE_ACTIVE
            self._goto_item(np.array([v]), np.array([s]))
        else:
            if s != self.cur[v]:
                self._emit(v, "mission_current", s)
            self.cur[v] = s
            if self.m_state[v] in (mavlink.MISSION_STATE_COMPLETE, mavlink.MISSION_STATE_NOT_STARTED):
                self.m_state[v] = mavlink.MISSION_STATE_PAUSED  # entering AUTO resumes at s
        return Result(mavlink.MAV_RESULT_ACCEPTED)

    # ------------------------------------------------------------------ the generic entry points
    @_guarded()
    def command(self, i, command: int, params=(0.0,) * 7, frame: int | None = None) -> Result:
        """COMMAND_LONG / COMMAND_INT -> the operation.  params: (param1..param4, latitude deg,
        longitude deg, altitude) -- for COMMAND_INT pass x * 1e-7, y * 1e-7, z and its frame; for
        COMMAND_LONG param5..7 and frame None (ArduPilot reads them as GLOBAL_RELATIVE_ALT).
        A command the autopilot does not know: UNSUPPORTED (counted)."""
        try:
            p = [float(x) for x in params]
            c = int(command)
            frame = None if frame is None else int(frame)
        except (TypeError, ValueError, OverflowError):
            return self._refuse("bad_param", mavlink.MAV_RESULT_DENIED, f"command {command!r}, params {params!r}")
        if len(p) != 7:
            return self._refuse("bad_param", mavlink.MAV_RESULT_DENIED, f"expected 7 params, got {len(p)}")
        rel = frame is None or int(frame) in REL_FRAMES
        if frame is not None and int(frame) not in REL_FRAMES and int(frame) not in ABS_FRAMES and command in (
                mavlink.MAV_CMD_DO_REPOSITION, mavlink.MAV_CMD_NAV_LAND):
            return self._refuse("bad_param", mavlink.MAV_RESULT_DENIED, f"frame {frame} unsupported")
        if c == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            if p[0] not in (0.0, 1.0):
                return self._refuse("bad_param", mavlink.MAV_RESULT_DENIED, f"arm param1 {p[0]!r} (0 or 1)")
            return self.arm(i, p[0] == 1.0, force=p[1] == cv.FORCE_MAGIC)
        if c == mavlink.MAV_CMD_DO_SET_MODE:
            return self.set_mode(i, p[1], p[0])
        if c == mavlink.MAV_CMD_NAV_TAKEOFF:
            return self.takeoff(i, p[6])
        if c == mavlink.MAV_CMD_DO_REPOSITION:
            return self.goto(i, math.radians(p[4]) if math.isfinite(p[4]) else p[4],
                             math.radians(p[5]) if math.isfinite(p[5]) else p[5], p[6], relative_alt=rel,
                             radius_m=p[2], speed_m_s=p[0],
                             change_mode=bool(int(p[1]) & mavlink.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE)
                             if math.isfinite(p[1]) else False)
        if c == mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return self.rtl(i)
        if c == mavlink.MAV_CMD_NAV_LOITER_UNLIM:
            return self.loiter(i)
        if c == mavlink.MAV_CMD_NAV_LAND:
            la = math.radians(p[4]) if math.isfinite(p[4]) and not (p[4] == 0 and p[5] == 0) else math.nan
            lo = math.radians(p[5]) if math.isfinite(p[5]) and not (p[4] == 0 and p[5] == 0) else math.nan
            if math.isinf(p[4]) or math.isinf(p[5]):
                la = lo = math.inf
            return self.land(i, la, lo, p[6], relative_alt=rel)
        if c == mavlink.MAV_CMD_MISSION_START:
            return self.mission_start(i, p[0], p[1])
        if c == mavlink.MAV_CMD_DO_SET_MISSION_CURRENT:
            return self.set_current(i, p[0], reset_jumps=p[1] == 1.0)
        if c == mavlink.MAV_CMD_DO_CHANGE_SPEED:
            return self.change_speed(i, p[0], p[1])
        if c == mavlink.MAV_CMD_DO_SET_HOME:
            return self.set_home(i, math.radians(p[4]) if math.isfinite(p[4]) else p[4],
                                 math.radians(p[5]) if math.isfinite(p[5]) else p[5], p[6], use_current=p[0] == 1.0)
        return self._refuse("unsupported_command", mavlink.MAV_RESULT_UNSUPPORTED,
                            f"{cv.command_name(c)} ({c}) not supported")

    @_guarded(mission=True)
    def guided_item(self, i, item) -> MissionResult:
        """MISSION_ITEM_INT with current = 2 (MAVProxy ``guided LAT LON ALT`` with
        guided_use_reposition off): GUIDED to the item's position; current = 3: change the
        target's altitude only.  Answered with MISSION_ACK (ArduPilot)."""
        try:
            cur, frame = int(item.current), int(item.frame)
            x, y, z = float(item.x), float(item.y), float(item.z)
        except (AttributeError, TypeError, ValueError):
            return self._refuse("bad_item", mavlink.MAV_MISSION_ERROR, "not a mission item", MissionResult)
        if frame not in ABS_FRAMES and frame not in REL_FRAMES:
            return self._refuse("bad_item", mavlink.MAV_MISSION_UNSUPPORTED_FRAME, f"frame {frame}", MissionResult)
        if not math.isfinite(z):
            return self._refuse("nonfinite", mavlink.MAV_MISSION_INVALID_PARAM7, f"altitude {z!r}", MissionResult)
        rel = frame in REL_FRAMES
        v = self._vehicle(i)
        if cur == 3 and v is not None:
            self.guided[v, 2] = z + (self.home[v, 2] if rel else 0.0)
            if self.mode[v] == cv.GUIDED:
                self.tgt[v, 2] = self.guided[v, 2]
            return MissionResult(mavlink.MAV_MISSION_ACCEPTED)
        if cur != 2:
            return self._refuse("bad_item", mavlink.MAV_MISSION_ERROR, f"current {cur} is not a guided request",
                                MissionResult)
        if not (math.isfinite(x) and abs(x) <= 900_000_000):
            return self._refuse("nonfinite", mavlink.MAV_MISSION_INVALID_PARAM5_X, f"latitude {x!r}", MissionResult)
        if not (math.isfinite(y) and abs(y) <= 1_800_000_000):
            return self._refuse("nonfinite", mavlink.MAV_MISSION_INVALID_PARAM6_Y, f"longitude {y!r}", MissionResult)
        r = self.goto(i, math.radians(x * 1e-7), math.radians(y * 1e-7), z, relative_alt=rel)
        return MissionResult(mavlink.MAV_MISSION_ACCEPTED if r.ok else mavlink.MAV_MISSION_ERROR, r.reason)

    # ------------------------------------------------------------------ status
    def mission_status(self) -> MissionStatus:
        total = np.maximum(self.m_count - 1, 0)
        state = np.where(self.m_count <= 1, mavlink.MISSION_STATE_NO_MISSION, self.m_state)
        return MissionStatus(self.cur.copy(), total, state)

    def heartbeat(self, i: int) -> tuple:
        """(type, autopilot, base_mode, custom_mode, system_status) of UAV i for heartbeat_send."""
        return cv.heartbeat_fields(int(self.mode[i]), bool(self.armed[i]), int(self.phase[i]))

    def landed_state(self) -> np.ndarray:
        """EXTENDED_SYS_STATE.landed_state per UAV."""
        return np.array([cv.landed_state(p) for p in self.phase.tolist()], dtype=np.int64)

    # ------------------------------------------------------------------ the step
    def step(self, t_s: float, dt_s: float, lat_rad, lon_rad, alt_m, heading_rad) -> tuple[gd.Guidance, list[Event]]:
        """Evaluate every UAV at simulation time t_s from its position and heading (N,) each,
        and return (the guidance for [t_s, t_s + dt_s], the events since the last step).  A UAV
        whose state is not finite keeps its last good state (counted as 'nonfinite')."""
        t, dt = float(t_s), float(dt_s)
        if not (math.isfinite(t) and math.isfinite(dt) and dt >= 0):
            self.counters["nonfinite"] += 1
            t, dt = self.t, 0.0
        new = np.stack([np.broadcast_to(np.asarray(a, float), (self.n,)) for a in (lat_rad, lon_rad, alt_m)], -1)
        psi = np.broadcast_to(np.asarray(heading_rad, float), (self.n,))
        ok = np.all(np.isfinite(new), axis=-1) & np.isfinite(psi)
        if not ok.all():
            self.counters["nonfinite"] += int((~ok).sum())
        self.pos = np.where(ok[:, None], new, self.pos)
        self.psi = np.where(ok, psi, self.psi)
        self.t = t
        cfg = self.cfg
        pos, h = self.pos, self.pos[:, 2]

        # landed UAVs disarm after LAND_DISARMDELAY
        for i in np.flatnonzero((self.phase == cv.LANDED) & self.armed & (t - self.t_landed >= cfg.land_disarm_delay_s)):
            self.armed[i] = False
            self._emit(int(i), "disarmed", 0, "Disarming motors")
        # a take-off starts: armed on the ground in TAKEOFF, or in AUTO with a mission to fly
        ground = np.isin(self.phase, (cv.ON_GROUND, cv.LANDED)) & (self.task != T_ROLLOUT)
        has = self.m_count > 1
        flyable = has & (self.m_state != mavlink.MISSION_STATE_COMPLETE)
        start = ground & self.armed & ((self.mode == cv.TAKEOFF) | ((self.mode == cv.AUTO) & flyable))
        for i in np.flatnonzero(start).tolist():
            self._takeoff_start(i)
        # the take-off roll and climb-out
        roll = (self.task == T_ROLL) & (self.speed_cmd >= cfg.airspeed_min_m_s - _EPS)
        for i in np.flatnonzero(roll).tolist():  # rotate
            self._set_leg(i, self.leg_heading[i], self.takeoff_alt[i] + cfg.climb_max_m_s / gd.K_CLIMB_1_S, T_TKOFF)
        climbed = ((self.task == T_TKOFF) | (self.task == T_CLIMB)) & (h >= self.takeoff_alt - _TAKEOFF_ALT_TOL_M)
        for i in np.flatnonzero(climbed).tolist():
            self._takeoff_done(i)
        # approaches end within the radius (or past the finish line): circle the point
        ap = self.task == T_APPROACH
        if ap.any():
            idx = np.flatnonzero(ap)
            d = self._dist(pos[idx], self.tgt[idx])
            reach = (d < np.where(self.after[idx] == T_NONE, np.maximum(self.radius[idx], cfg.wp_radius_m),
                                  self.radius[idx])) | self._past(idx)
            for i in idx[reach].tolist():
                self._approach_done(i)
        # mission items
        wp = (self.task == T_WP) & (self.mode == cv.AUTO)
        if wp.any():
            idx = np.flatnonzero(wp)
            d = self._dist(pos[idx], self.tgt[idx])
            self._item_done(idx[(d < self.accept[idx]) | self._past(idx)])
        orbit_task = np.isin(self.task, (T_TURNS, T_TIME, T_ALT)) & (self.mode == cv.AUTO)
        if orbit_task.any():
            idx = np.flatnonzero(orbit_task)
            d_e, d_n = self._offsets(pos[idx], self.tgt[idx])
            brg = np.arctan2(-d_e, -d_n)  # the UAV's bearing from the centre
            self.swept[idx] += np.abs(_wrap(brg - self.last_brg[idx]))
            self.last_brg[idx] = brg
            tk = self.task[idx]
            done = ((tk == T_TURNS) & (self.swept[idx] >= 2.0 * np.pi * self.loiter_turns[idx])) \
                | ((tk == T_TIME) & (t - self.t_stage[idx] >= self.loiter_time[idx])) \
                | ((tk == T_ALT) & (np.abs(h[idx] - self.tgt[idx, 2]) < _LOITER_ALT_TOL_M))
            self._item_done(idx[done])
        # landings: over the landing point (or past its finish line) the final straight ahead
        ld = (self.task == T_LAND) & (self.kind == gd.LAND)
        if ld.any():
            idx = np.flatnonzero(ld)
            over = (self._dist(pos[idx], self.tgt[idx]) < cfg.wp_radius_m) | self._past(idx)
            for i in idx[over].tolist():
                self.kind[i] = gd.FINAL
                self.leg_heading[i] = self.psi[i]
                self.tgt[i, 2] = self.ground[i]
        # touchdown, roll-out, landed
        down = np.isin(self.task, (T_LAND, T_GLIDE)) & (h <= self.ground + _TOUCHDOWN_M)
        for i in np.flatnonzero(down).tolist():
            self.kind[i], self.task[i] = gd.LEG, T_ROLLOUT
            self.leg_heading[i] = self.psi[i]
            self.tgt[i] = (pos[i, 0], pos[i, 1], self.ground[i])
            self._emit(i, "text", 0, "Touchdown")
        stopped = (self.task == T_ROLLOUT) & (self.speed_cmd <= _EPS)
        for i in np.flatnonzero(stopped).tolist():
            self._landed(i)

        # the commanded speed: ramps to its target (take-off roll, roll-out, speed changes)
        target = np.where(np.isin(self.task, (T_ROLLOUT,)) | (self.kind == gd.HOLD), 0.0,
                          np.where(self.task == T_ROLL, cfg.airspeed_cruise_m_s, self.airspeed))
        target = np.where(self.task == T_GLIDE, cfg.airspeed_min_m_s, target)
        up = self.speed_cmd + cfg.takeoff_accel_m_s2 * dt
        dn = self.speed_cmd - cfg.rollout_decel_m_s2 * dt
        self.speed_cmd = np.where(target > self.speed_cmd, np.minimum(up, target), np.maximum(dn, target))
        self.speed_cmd = np.where((self.kind == gd.SCENARIO), self.airspeed, self.speed_cmd)
        self.speed_cmd = np.where(self.kind == gd.HOLD, 0.0, self.speed_cmd)
        g = self._guidance()
        ev, self._events = self._events, []
        return g, ev

    def _guidance(self) -> gd.Guidance:
        cfg, n = self.cfg, self.n
        speed = self.speed_cmd.copy()
        radius = np.where(self.kind == gd.ORBIT, self._orbit_radius(self.radius, np.maximum(speed, 1.0)), self.radius)
        rate = self._max_rate(np.maximum(speed, cfg.airspeed_min_m_s))
        rate = np.where(self.task == T_ROLL, 0.0, rate)  # the take-off roll holds the runway heading
        climb = np.where(np.isin(self.task, (T_ROLL, T_ROLLOUT)), 0.0, cfg.climb_max_m_s)
        sink = np.where(self.task == T_ROLL, 0.0, cfg.sink_max_m_s)
        return gd.Guidance(self.kind.copy(), speed, self.tgt[:, 0].copy(), self.tgt[:, 1].copy(), self.tgt[:, 2].copy(),
                           radius, self.leg_heading.copy(), rate, np.broadcast_to(climb, (n,)).copy(),
                           np.broadcast_to(sink, (n,)).copy(), np.full(n, cfg.land_slope))

    def _past(self, idx) -> np.ndarray:
        """Past the finish line: the line through the target perpendicular to prev -> target."""
        pe, pn = self._offsets(self.tgt[idx], self.pos[idx])  # the UAV from the target
        qe, qn = self._offsets(self.tgt[idx], self.prev[idx])  # the leg's start from the target
        return (pe * qe + pn * qn) < 0.0

    def _approach_done(self, i: int) -> None:
        after = int(self.after[i])
        self.kind[i], self.task[i] = gd.ORBIT, after
        self.t_stage[i] = self.t
        self.swept[i] = 0.0
        d_e, d_n = self._offsets(self.pos[[i]], self.tgt[[i]])
        self.last_brg[i] = float(np.arctan2(-d_e, -d_n)[0])
        if self.mode[i] == cv.GUIDED:
            self.radius[i] = self.guided_radius[i] or self.cfg.wp_loiter_rad_m
            self._emit(i, "text", 0, "Reached destination")
        elif self.mode[i] == cv.RTL:
            self.radius[i] = self.cfg.rtl_radius_eff_m
            self._emit(i, "text", 0, "Reached RTL location")

    def _takeoff_start(self, i: int) -> None:
        cfg = self.cfg
        rel = self._takeoff_rel(i)
        if self.mode[i] == cv.AUTO:
            if self.m_state[i] != mavlink.MISSION_STATE_ACTIVE:
                self._mission_restart(i, walk=False)
                self.m_state[i] = mavlink.MISSION_STATE_ACTIVE
                self._goto_item(np.array([i]), np.array([cv.FIRST_ITEM]))
                if self.m_state[i] != mavlink.MISSION_STATE_ACTIVE:
                    return
            c = int(self.m_cmd[i, self.cur[i]])
            if c == NAV_TAKEOFF:
                pt = self._item_point(np.array([i]), self.cur[[i]], self.pos[[i]])[0]
                rel = pt[2] - self.home[i, 2]
            else:
                self._emit(i, "text", 0, f"Auto take-off to TKOFF_ALT {rel:.0f} m (the mission has no NAV_TAKEOFF)")
        self.phase[i] = cv.TAKING_OFF
        self.pending_mode[i] = -1
        self.takeoff_alt[i] = self.home[i, 2] + rel
        self.prev[i] = self.pos[i]
        self._set_leg(i, self.psi[i], self.pos[i, 2], T_ROLL)
        self.speed_cmd[i] = 0.0
        self._emit(i, "text", 0, f"Takeoff to {rel:.0f}m for {cfg.tkoff_dist_m:.1f}m heading "
                                 f"{math.degrees(self.psi[i]) % 360:.1f} deg")

    def _takeoff_done(self, i: int) -> None:
        rel = self.pos[i, 2] - self.home[i, 2]
        was_item = self.task[i] == T_CLIMB
        self.phase[i] = cv.FLYING
        self._emit(i, "takeoff_complete", 0, f"Takeoff complete at {rel:.2f}m")
        pending, self.pending_mode[i] = int(self.pending_mode[i]), -1
        mode = int(self.mode[i])
        if pending >= 0 and pending != cv.TAKEOFF:
            self._enter(i, pending)
            return
        if mode == cv.AUTO and self.m_state[i] == mavlink.MISSION_STATE_ACTIVE:
            if was_item or int(self.m_cmd[i, self.cur[i]]) == NAV_TAKEOFF:
                self.task[i] = T_NONE
                self._item_done(np.array([i]))
            else:
                self._start_item(np.array([i]), self.pos[[i]])
        elif mode == cv.TAKEOFF:  # loiter TKOFF_DIST from the take-off point along the take-off heading
            p = self.prev[i]
            self._set_orbit(i, self._project(p[0], p[1], p[2], self.leg_heading[i], self.cfg.tkoff_dist_m,
                                             self.takeoff_alt[i]))
        else:
            self._enter(i, mode)

    def _landed(self, i: int) -> None:
        self.phase[i] = cv.LANDED
        self.kind[i], self.task[i] = gd.HOLD, T_NONE
        self.t_landed[i] = self.t
        self.speed_cmd[i] = 0.0
        self.airspeed[i] = self.cfg.airspeed_cruise_m_s
        self._emit(i, "landed", 0, "Landed")
        if self.mode[i] == cv.AUTO and self.m_state[i] == mavlink.MISSION_STATE_ACTIVE \
                and int(self.m_cmd[i, self.cur[i]]) == NAV_LAND:
            self._emit(i, "item_reached", int(self.cur[i]), f"Reached waypoint #{int(self.cur[i])}")
            self.m_state[i] = mavlink.MISSION_STATE_COMPLETE
            self._emit(i, "mission_complete", int(self.cur[i]))
