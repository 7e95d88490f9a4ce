"""The autopilot's parameters, declared once (filters.params: default, check, doc per field).

Each field has its MAVLink parameter name in :data:`PARAM_NAMES` (ArduPlane's name where
ArduPlane has the same quantity, so a GCS finds WP_RADIUS, WP_LOITER_RAD, RTL_ALTITUDE,
AIRSPEED_CRUISE ... where it looks; ``SF_*`` for the few that are this simulation's own) and
its unit in :data:`PARAM_UNITS`.  :func:`param_rows` gives the MAVLink parameter layer
(name, value, unit, doc, is ArduPlane's) per field; :func:`with_param` sets one by its MAVLink
name and re-validates the whole configuration (a bad value or combination: ParamError, one line).

The defaults are ArduPlane's where they fit a 100 m/s UAV; the distances that scale with speed
are not (ArduPlane's 90 m waypoint radius and 60 m loiter radius are for ~20 m/s airframes; a
bank-limited turn at 100 m/s and 45 deg has a radius v^2 / (g tan 45) ~ 1 km).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from filters.params import ParamError, docs, number, param, require, validate

__all__ = ["AutopilotConfig", "PARAM_NAMES", "PARAM_UNITS", "ARDUPILOT_NAMES", "param_rows", "with_param",
           "field_of", "G_M_S2"]

G_M_S2 = 9.80665


@dataclass(frozen=True)
class AutopilotConfig:
    """One UAV type's autopilot parameters (every UAV of an :class:`Autopilot` shares them)."""

    wp_radius_m: float = param(200.0, check=number(0, lo_open=True),
                               doc="a mission waypoint is reached within this horizontal distance, m (ArduPlane "
                                   "WP_RADIUS; its 90 m default is for ~20 m/s airframes); passing the waypoint's "
                                   "finish line counts too")
    wp_loiter_rad_m: float = param(1500.0, check=number(0, lo_open=True),
                                   doc="loiter circle radius, m (WP_LOITER_RAD); a radius the bank limit cannot fly "
                                       "at the airspeed is widened to 1.1 x the tightest turn")
    rtl_radius_m: float = param(0.0, check=number(0),
                                doc="RTL loiter radius about home, m; 0: WP_LOITER_RAD (RTL_RADIUS)")
    rtl_altitude_m: float = param(100.0, check=number(-1.0),
                                  doc="RTL altitude above home, m; -1: return at the current altitude (RTL_ALTITUDE)")
    airspeed_cruise_m_s: float = param(100.0, check=number(0, lo_open=True),
                                       doc="cruise airspeed of the navigation modes, m/s (AIRSPEED_CRUISE)")
    airspeed_min_m_s: float = param(50.0, check=number(0, lo_open=True),
                                    doc="minimum airspeed, m/s: the take-off roll rotates at it, DO_CHANGE_SPEED "
                                        "below it is refused (AIRSPEED_MIN)")
    airspeed_max_m_s: float = param(150.0, check=number(0, lo_open=True),
                                    doc="maximum airspeed, m/s: DO_CHANGE_SPEED above it is refused (AIRSPEED_MAX)")
    tkoff_alt_m: float = param(50.0, check=number(0, lo_open=True),
                               doc="TAKEOFF mode's altitude above the take-off point, m (TKOFF_ALT)")
    tkoff_dist_m: float = param(200.0, check=number(0),
                                doc="TAKEOFF mode loiters about the point this far from the take-off point along "
                                    "the take-off heading, m (TKOFF_DIST)")
    climb_max_m_s: float = param(5.0, check=number(0, lo_open=True),
                                 doc="maximum climb rate, m/s (TECS_CLMB_MAX)")
    sink_max_m_s: float = param(5.0, check=number(0, lo_open=True),
                                doc="maximum sink rate, m/s (TECS_SINK_MAX)")
    roll_limit_deg: float = param(45.0, check=number(0, lo_open=True),
                                  doc="bank limit, deg (ROLL_LIMIT_DEG): the turn rate is at most g tan(limit) / "
                                      "airspeed (5.6 deg/s at 100 m/s)")
    land_disarm_delay_s: float = param(20.0, check=number(0),
                                       doc="a landed UAV disarms after this long, s (LAND_DISARMDELAY)")
    batt_capacity_mah: float = param(3300.0, check=number(0, lo_open=True),
                                     doc="battery capacity, mAh (BATT_CAPACITY)")
    takeoff_accel_m_s2: float = param(3.0, check=number(0, lo_open=True),
                                      doc="take-off roll acceleration, m/s^2 (SF_TKOFF_ACC: the roll to AIRSPEED_MIN "
                                          "before rotating)")
    land_slope: float = param(0.05, check=number(0, lo_open=True),
                              doc="landing glide slope, height / distance to the landing point (SF_LAND_SLOPE; "
                                  "0.05 = 5 m/s sink at 100 m/s)")
    rollout_decel_m_s2: float = param(4.0, check=number(0, lo_open=True),
                                      doc="landing roll-out deceleration to a stop, m/s^2 (SF_ROLLOUT_DEC)")

    def __post_init__(self):
        validate(self)
        require(self.airspeed_min_m_s <= self.airspeed_cruise_m_s <= self.airspeed_max_m_s, "airspeed_cruise_m_s",
                f"expected AIRSPEED_MIN <= AIRSPEED_CRUISE <= AIRSPEED_MAX, got {self.airspeed_min_m_s:g} / "
                f"{self.airspeed_cruise_m_s:g} / {self.airspeed_max_m_s:g}")
        require(self.climb_max_m_s < 0.5 * self.airspeed_min_m_s, "climb_max_m_s",
                f"expected < AIRSPEED_MIN / 2 (a 30 deg climb), got {self.climb_max_m_s:g}")
        require(self.sink_max_m_s < 0.5 * self.airspeed_min_m_s, "sink_max_m_s",
                f"expected < AIRSPEED_MIN / 2, got {self.sink_max_m_s:g}")
        require(self.roll_limit_deg < 85.0, "roll_limit_deg", f"expected < 85 deg, got {self.roll_limit_deg:g}")

    def max_turn_rate_rad_s(self, speed_m_s):
        """The bank-limited turn rate at speed_m_s (array-friendly; infinite at speed 0 is avoided)."""
        import numpy as np
        return G_M_S2 * math.tan(math.radians(self.roll_limit_deg)) / np.maximum(speed_m_s, 1.0)

    @property
    def rtl_radius_eff_m(self) -> float:
        return self.rtl_radius_m if self.rtl_radius_m > 0 else self.wp_loiter_rad_m


#: field -> MAVLink parameter name (<= 16 characters)
PARAM_NAMES = {
    "wp_radius_m": "WP_RADIUS", "wp_loiter_rad_m": "WP_LOITER_RAD", "rtl_radius_m": "RTL_RADIUS",
    "rtl_altitude_m": "RTL_ALTITUDE", "airspeed_cruise_m_s": "AIRSPEED_CRUISE", "airspeed_min_m_s": "AIRSPEED_MIN",
    "airspeed_max_m_s": "AIRSPEED_MAX", "tkoff_alt_m": "TKOFF_ALT", "tkoff_dist_m": "TKOFF_DIST",
    "climb_max_m_s": "TECS_CLMB_MAX", "sink_max_m_s": "TECS_SINK_MAX", "roll_limit_deg": "ROLL_LIMIT_DEG",
    "land_disarm_delay_s": "LAND_DISARMDELAY", "batt_capacity_mah": "BATT_CAPACITY",
    "takeoff_accel_m_s2": "SF_TKOFF_ACC", "land_slope": "SF_LAND_SLOPE", "rollout_decel_m_s2": "SF_ROLLOUT_DEC",
}
#: field -> unit (ArduPilot's unit names)
PARAM_UNITS = {
    "wp_radius_m": "m", "wp_loiter_rad_m": "m", "rtl_radius_m": "m", "rtl_altitude_m": "m",
    "airspeed_cruise_m_s": "m/s", "airspeed_min_m_s": "m/s", "airspeed_max_m_s": "m/s", "tkoff_alt_m": "m",
    "tkoff_dist_m": "m", "climb_max_m_s": "m/s", "sink_max_m_s": "m/s", "roll_limit_deg": "deg",
    "land_disarm_delay_s": "s", "batt_capacity_mah": "mAh", "takeoff_accel_m_s2": "m/s/s", "land_slope": "",
    "rollout_decel_m_s2": "m/s/s",
}
#: the names that are ArduPlane's own parameters (same quantity, same unit)
ARDUPILOT_NAMES = frozenset(n for n in PARAM_NAMES.values() if not n.startswith("SF_"))


def field_of(name: str) -> str:
    """The field of a MAVLink parameter name (KeyError if the autopilot has no such parameter)."""
    for f, n in PARAM_NAMES.items():
        if n == name:
            return f
    raise KeyError(name)


def param_rows(cfg: AutopilotConfig) -> list[tuple[str, float, str, str, bool]]:
    """(MAVLink name, value, unit, doc, is ArduPlane's) of every parameter, in declaration order."""
    d = docs(AutopilotConfig)
    return [(PARAM_NAMES[f.name], float(getattr(cfg, f.name)), PARAM_UNITS[f.name], d[f.name],
             PARAM_NAMES[f.name] in ARDUPILOT_NAMES) for f in dataclasses.fields(AutopilotConfig)]


def with_param(cfg: AutopilotConfig, name: str, value) -> AutopilotConfig:
    """A new configuration with MAVLink parameter ``name`` set (ParamError: unknown name, bad value
    or a combination the checks refuse; the old configuration stays)."""
    try:
        f = field_of(name)
    except KeyError:
        raise ParamError(name, "not a parameter of the autopilot") from None
    try:
        return dataclasses.replace(cfg, **{f: value})
    except ParamError as e:
        raise ParamError(name, e.reason) from None
