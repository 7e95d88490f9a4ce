"""The autopilot's operations (arm, set_mode, takeoff, goto, rtl, loiter, land, missions,
command, guided_item, the status reads): :class:`Operations`, the half of
:class:`vehicles.autopilot.core.Autopilot` that the MAVLink endpoint calls.  Each returns a
code and a one-line reason and counts a refusal; none raises (``_guarded``)."""
from __future__ import annotations

import math

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from . import convention as cv
from . import guidance as gd
from .rules import (ABS_FRAMES, DO_JUMP, MissionResult, MissionStatus, POSITION_ITEMS,
    REL_FRAMES, Result, T_GLIDE, T_LAND, T_NONE, T_ROLLOUT, _WARNING, _finite, _guarded, check_item)


class Operations:
    """The operations of :class:`vehicles.autopilot.core.Autopilot` (a mixin over its state)."""

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
                self.airspeed[v] = self.cfgs[v].airspeed_cruise_m_s
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
            self.airspeed[v] = self.cfgs[v].airspeed_min_m_s
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
            if not self.cfgs[v].airspeed_min_m_s <= s <= self.cfgs[v].airspeed_max_m_s:
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
            self._set_approach(v, pt, self.cfgs[v].wp_radius_m, T_NONE)
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
            pt = self._ahead(v, max(self.pos[v, 2] - ground, 0.0) / self.cfgs[v].land_slope, ground)
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

    @_guarded(mission=True)
    def check_item(self, k, item, n) -> MissionResult:
        """Item k of an n-item upload, checked as it arrives (the MissionServer's per-item hook):
        MAV_MISSION_ACCEPTED, or the code and reason set_mission would give for it (counted as
        set_mission counts it: 'unsupported_item' / 'bad_item')."""
        res = self._check_item(int(k), item, int(n))
        if not res.ok:
            self.counters["unsupported_item" if res.code == mavlink.MAV_MISSION_UNSUPPORTED else "bad_item"] += 1
            self.last_reason = res.reason
        return res

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
