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

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.constants import Ellipsoid, ellipsoid

from . import convention as cv
from . import guidance as gd
from .config import AutopilotConfig
from .rules import (ABS_FRAMES, DO_CHANGE_SPEED, DO_JUMP, Event, FLYABLE_ITEMS, LOITER_TIME, LOITER_TO_ALT,
    LOITER_TURNS, LOITER_UNLIM, MAV_CMD, MissionResult, MissionStatus, NAV_ITEMS, NAV_LAND, NAV_RTL,
    NAV_TAKEOFF, NAV_WAYPOINT, POSITION_ITEMS, REFUSALS, REL_FRAMES, Result, T_ALT, T_APPROACH, T_CLIMB,
    T_GLIDE, T_LAND, T_NONE, T_ROLL, T_ROLLOUT, T_TIME, T_TKOFF, T_TURNS, T_WP, _EPS, _FLARE_M, _INFO,
    _LOITER_ALT_TOL_M, _NAV_ARR, _TAKEOFF_ALT_TOL_M, _TOUCHDOWN_M, _WARNING, _wrap, check_item)
from .operations import Operations

__all__ = ['Autopilot', 'Operations', 'ABS_FRAMES', 'DO_CHANGE_SPEED', 'DO_JUMP', 'Event', 'FLYABLE_ITEMS', 'LOITER_TIME', 'LOITER_TO_ALT', 'LOITER_TURNS', 'LOITER_UNLIM', 'MAV_CMD', 'MissionResult', 'MissionStatus', 'NAV_ITEMS', 'NAV_LAND', 'NAV_RTL', 'NAV_TAKEOFF', 'NAV_WAYPOINT', 'POSITION_ITEMS', 'REFUSALS', 'REL_FRAMES', 'Result', 'T_ALT', 'T_APPROACH', 'T_CLIMB', 'T_GLIDE', 'T_LAND', 'T_NONE', 'T_ROLL', 'T_ROLLOUT', 'T_TIME', 'T_TKOFF', 'T_TURNS', 'T_WP', 'check_item']


class Autopilot(Operations):
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
        config = config if config is not None else AutopilotConfig()
        if not isinstance(config, AutopilotConfig):
            raise ValueError(f"config must be an AutopilotConfig, got {type(config).__name__}")
        self.cfgs: list[AutopilotConfig] = [config] * n
        self._config_arrays()
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

    # ------------------------------------------------------------------ configuration (per UAV)
    @property
    def cfg(self) -> AutopilotConfig:
        """UAV 0's configuration (every UAV's unless :meth:`set_config` gave one its own);
        assigning it configures every UAV."""
        return self.cfgs[0]

    @cfg.setter
    def cfg(self, config: AutopilotConfig) -> None:
        self.set_config(None, config)

    def set_config(self, i, config: AutopilotConfig) -> None:
        """UAV i's configuration (its parameters: WP_RADIUS, ...; i None: every UAV's), from its
        next step; ValueError for something that is not an AutopilotConfig or no such UAV."""
        if not isinstance(config, AutopilotConfig):
            raise ValueError(f"config must be an AutopilotConfig, got {type(config).__name__}")
        if i is None:
            self.cfgs = [config] * self.n
        else:
            v = self._vehicle(i)
            if v is None:
                raise ValueError(f"no UAV {i!r}")
            self.cfgs[v] = config
        self._config_arrays()

    def _config_arrays(self) -> None:
        """(N,) arrays of every configuration field (the batched step reads them)."""
        import dataclasses
        import types
        self.C = types.SimpleNamespace(**{f.name: np.array([float(getattr(c, f.name)) for c in self.cfgs])
                                          for f in dataclasses.fields(AutopilotConfig)})

    def _max_rate(self, speed, idx=slice(None)):
        """The bank-limited turn rate of UAVs idx at speed (vehicles.autopilot.config)."""
        c = self.cfgs[0]
        if all(x is c for x in self.cfgs):
            return c.max_turn_rate_rad_s(speed)
        from .config import G_M_S2
        return G_M_S2 * np.tan(np.radians(self.C.roll_limit_deg[idx])) / np.maximum(speed, 1.0)

    def _orbit_radius(self, r, speed):
        """The radius flown: r, widened to 1.1 x the bank-limited turn radius at speed."""
        c = self.cfgs[0]
        v_min = c.airspeed_min_m_s if all(x is c for x in self.cfgs) else self.C.airspeed_min_m_s
        tight = np.asarray(speed, float) / self._max_rate(np.maximum(speed, v_min))
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
        self.radius[i] = self.cfgs[i].wp_loiter_rad_m if radius is None or not radius > 0 else radius

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
        self.airspeed[i] = self.cfgs[i].airspeed_min_m_s

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
            self.airspeed[i] = self.cfgs[i].airspeed_cruise_m_s
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
                self._set_approach(i, self.guided[i].copy(), self.cfgs[i].wp_radius_m)
            else:  # ArduPlane: GUIDED without a target circles the current position
                self.guided[i] = pos
                self._set_orbit(i, pos, self.guided_radius[i] or None)
        elif mode in (cv.LOITER, cv.CIRCLE):
            self._set_orbit(i, pos)
        elif mode == cv.RTL:
            self._rtl(i)
        elif mode == cv.TAKEOFF:
            alt = self.home[i, 2] + self._takeoff_rel(i)
            self._set_orbit(i, self._ahead(i, self.cfgs[i].tkoff_dist_m, max(alt, pos[2])))
            self._emit(i, "text", 0, "Above TKOFF alt - loitering" if pos[2] >= alt else
                       "Climbing to TKOFF alt then loitering")
        elif mode == cv.AUTOLAND:
            self._set_land(i, self.home[i].copy())
        else:  # pilot modes, centred sticks: straight and level
            self._set_leg(i, self.psi[i], pos[2])

    def _takeoff_rel(self, i) -> float:
        r = self.takeoff_alt_req[i]
        return float(r) if r == r else self.cfgs[i].tkoff_alt_m

    def _rtl(self, i) -> None:
        alt = self.pos[i, 2] if self.cfgs[i].rtl_altitude_m < 0 else self.home[i, 2] + self.cfgs[i].rtl_altitude_m
        c = np.array([self.home[i, 0], self.home[i, 1], alt])
        self._set_approach(i, c, self.cfgs[i].rtl_radius_eff_m)

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
                self.accept[i] = pi[1] if pi[1] > 0 else self.cfgs[i].wp_radius_m
            elif ci in (LOITER_UNLIM, LOITER_TURNS, LOITER_TIME, LOITER_TO_ALT):
                r = abs(pi[1] if ci == LOITER_TO_ALT else pi[2])
                r = r if r > 0 else self.cfgs[i].wp_loiter_rad_m
                after = {LOITER_UNLIM: T_NONE, LOITER_TURNS: T_TURNS, LOITER_TIME: T_TIME, LOITER_TO_ALT: T_ALT}[ci]
                self.loiter_turns[i] = pi[0] if ci == LOITER_TURNS else 0.0
                self.loiter_time[i] = pi[0] if ci == LOITER_TIME else 0.0
                self._set_approach(i, pt, r, after)
                self.prev[i] = prev[k]
            elif ci == NAV_TAKEOFF:  # in the air: climb along the heading to its altitude
                self._set_leg(i, self.psi[i], max(pt[2], self.pos[i, 2]) + self.cfgs[i].climb_max_m_s / gd.K_CLIMB_1_S,
                              T_CLIMB)
                self.takeoff_alt[i] = pt[2]
            elif ci == NAV_LAND:
                here = not np.isfinite(self.m_lat[i, cur[k]])
                point = pt if not here else self._ahead(i, max(self.pos[i, 2] - pt[2], 0.0) / self.cfgs[i].land_slope,
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
            self.airspeed[i] = self.cfgs[i].airspeed_cruise_m_s
            return True
        if s > 0 and self.cfgs[i].airspeed_min_m_s <= s <= self.cfgs[i].airspeed_max_m_s:
            self.airspeed[i] = s
            self._emit(i, "text", 0, f"Set airspeed {s:.0f} m/s")
            return True
        return s == -1.0

    # ------------------------------------------------------------------ operations (each: a code, a reason)
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
        cfg = self.C  # (N,) per UAV
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
            self._set_leg(i, self.leg_heading[i], self.takeoff_alt[i] + cfg.climb_max_m_s[i] / gd.K_CLIMB_1_S, T_TKOFF)
        climbed = ((self.task == T_TKOFF) | (self.task == T_CLIMB)) & (h >= self.takeoff_alt - _TAKEOFF_ALT_TOL_M)
        for i in np.flatnonzero(climbed).tolist():
            self._takeoff_done(i)
        # approaches end within the radius (or past the finish line): circle the point
        ap = self.task == T_APPROACH
        if ap.any():
            idx = np.flatnonzero(ap)
            d = self._dist(pos[idx], self.tgt[idx])
            reach = (d < np.where(self.after[idx] == T_NONE, np.maximum(self.radius[idx], cfg.wp_radius_m[idx]),
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
            over = (self._dist(pos[idx], self.tgt[idx]) < cfg.wp_radius_m[idx]) | self._past(idx)
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
        cfg, n = self.C, self.n
        speed = self.speed_cmd.copy()
        radius = np.where(self.kind == gd.ORBIT, self._orbit_radius(self.radius, np.maximum(speed, 1.0)), self.radius)
        rate = self._max_rate(np.maximum(speed, cfg.airspeed_min_m_s))
        rate = np.where(self.task == T_ROLL, 0.0, rate)  # the take-off roll holds the runway heading
        climb = np.where(np.isin(self.task, (T_ROLL, T_ROLLOUT)), 0.0, cfg.climb_max_m_s)
        sink = np.where(self.task == T_ROLL, 0.0, cfg.sink_max_m_s)
        return gd.Guidance(self.kind.copy(), speed, self.tgt[:, 0].copy(), self.tgt[:, 1].copy(), self.tgt[:, 2].copy(),
                           radius, self.leg_heading.copy(), rate, np.broadcast_to(climb, (n,)).copy(),
                           np.broadcast_to(sink, (n,)).copy(), cfg.land_slope.copy())

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
            self.radius[i] = self.guided_radius[i] or self.cfgs[i].wp_loiter_rad_m
            self._emit(i, "text", 0, "Reached destination")
        elif self.mode[i] == cv.RTL:
            self.radius[i] = self.cfgs[i].rtl_radius_eff_m
            self._emit(i, "text", 0, "Reached RTL location")

    def _takeoff_start(self, i: int) -> None:
        cfg = self.cfgs[i]
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
            self._set_orbit(i, self._project(p[0], p[1], p[2], self.leg_heading[i], self.cfgs[i].tkoff_dist_m,
                                             self.takeoff_alt[i]))
        else:
            self._enter(i, mode)

    def _landed(self, i: int) -> None:
        self.phase[i] = cv.LANDED
        self.kind[i], self.task[i] = gd.HOLD, T_NONE
        self.t_landed[i] = self.t
        self.speed_cmd[i] = 0.0
        self.airspeed[i] = self.cfgs[i].airspeed_cruise_m_s
        self._emit(i, "landed", 0, "Landed")
        if self.mode[i] == cv.AUTO and self.m_state[i] == mavlink.MISSION_STATE_ACTIVE \
                and int(self.m_cmd[i, self.cur[i]]) == NAV_LAND:
            self._emit(i, "item_reached", int(self.cur[i]), f"Reached waypoint #{int(self.cur[i])}")
            self.m_state[i] = mavlink.MISSION_STATE_COMPLETE
            self._emit(i, "mission_complete", int(self.cur[i]))
