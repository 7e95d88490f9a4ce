"""A simple battery for a UAV's BATTERY_STATUS / SYS_STATUS: charge drawn in simulation time.

Current draw: ``cruise_current_a * (airspeed / cruise_airspeed) ** exponent`` while armed (power
of a propeller aircraft ~ v^3 at constant voltage: exponent 3; 0: a constant cruise draw), plus
``idle_current_a``. Voltage falls linearly from ``voltage_full_v`` to ``voltage_empty_v`` with the
charge used, less ``internal_resistance_ohm`` x current. SI inside; mAh and % only as names say.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from filters.params import number, param, validate

__all__ = ["BatteryParams", "Battery"]


@dataclass(frozen=True)
class BatteryParams:
    capacity_mah: float = param(3300.0, check=number(0, lo_open=True),
                                doc="battery capacity, mAh (ArduPilot BATT_CAPACITY)")
    voltage_full_v: float = param(12.6, check=number(0, lo_open=True), doc="open-circuit voltage when full, V")
    voltage_empty_v: float = param(10.5, check=number(0, lo_open=True), doc="open-circuit voltage when empty, V")
    cruise_current_a: float = param(10.0, check=number(0), doc="current drawn at cruise_airspeed_m_s, A")
    cruise_airspeed_m_s: float = param(100.0, check=number(0, lo_open=True),
                                       doc="the airspeed at which cruise_current_a is drawn, m/s")
    exponent: float = param(3.0, check=number(0, hi=4),
                            doc="current ~ airspeed ** exponent (3: propeller power ~ v^3; 0: constant draw)")
    idle_current_a: float = param(0.5, check=number(0), doc="avionics current, armed or not, A")
    internal_resistance_ohm: float = param(0.01, check=number(0), doc="internal resistance, ohm")

    def __post_init__(self):
        validate(self)
        if self.voltage_empty_v >= self.voltage_full_v:
            raise ValueError(f"battery: voltage_empty_v ({self.voltage_empty_v}) must be below voltage_full_v "
                             f"({self.voltage_full_v})")


class Battery:
    """One battery, stepped in simulated time: ``step(t_s, airspeed_m_s, armed)``."""

    def __init__(self, params: BatteryParams | None = None):
        self.p = params if params is not None else BatteryParams()
        self.consumed_mah = 0.0
        self.consumed_wh = 0.0
        self.current_a = self.p.idle_current_a
        self._t: float | None = None

    def step(self, t_s: float, airspeed_m_s: float, armed: bool = True) -> None:
        p = self.p
        v = float(airspeed_m_s) if math.isfinite(airspeed_m_s) and airspeed_m_s > 0 else 0.0
        i = p.idle_current_a + (p.cruise_current_a * (v / p.cruise_airspeed_m_s) ** p.exponent if armed else 0.0)
        if self._t is not None and t_s > self._t:
            dt_h = (t_s - self._t) / 3600.0
            self.consumed_mah += self.current_a * dt_h * 1000.0  # the previous step's current over the interval
            self.consumed_wh += self.current_a * self.voltage_v * dt_h
        self._t = float(t_s)
        self.current_a = i

    @property
    def remaining_frac(self) -> float:
        return max(0.0, 1.0 - self.consumed_mah / self.p.capacity_mah)

    @property
    def remaining_pct(self) -> float:
        return 100.0 * self.remaining_frac

    @property
    def voltage_v(self) -> float:
        p = self.p
        ocv = p.voltage_empty_v + (p.voltage_full_v - p.voltage_empty_v) * self.remaining_frac
        return max(0.0, ocv - p.internal_resistance_ohm * self.current_a)
