"""A simple battery for a UAV's BATTERY_STATUS / SYS_STATUS: charge drawn in simulation time.

Current draw: ``cruise_current_a * (airspeed / cruise_airspeed) ** exponent`` while armed (power
of a propeller aircraft ~ v^3 at constant voltage: exponent 3; 0: a constant cruise draw), plus
``idle_current_a``. Voltage falls linearly from ``voltage_full_v`` to ``voltage_empty_v`` with the
charge used, less ``internal_resistance_ohm`` x current. SI inside; mAh and % only as names say.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from filters.params import number, param, validate

__all__ = ["BatteryParams", "Battery", "BatteryBank", "BatteryCell"]


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


class BatteryBank:
    """N batteries as arrays (a vehicle group's UAVs), stepped in simulated time by their owner:
    ``step(t_s, airspeed_m_s (N,), armed (N,), capacity_mah=None (N,))``, the model of
    :class:`Battery` element-wise (the previous step's current over the interval).  capacity_mah:
    each UAV's capacity now (its BATT_CAPACITY parameter; None: params.capacity_mah).
    ``cell(j)`` is battery j as the endpoint reads it (voltage_v, current_a, consumed_mah,
    consumed_wh, remaining_pct); it has no ``step``: the endpoint does not step it."""

    def __init__(self, n: int, params: BatteryParams | None = None):
        self.p = params if params is not None else BatteryParams()
        self.n = int(n)
        self.consumed_mah = np.zeros(self.n)
        self.consumed_wh = np.zeros(self.n)
        self.current_a = np.full(self.n, self.p.idle_current_a)
        self.capacity_mah = np.full(self.n, self.p.capacity_mah)
        self._t: float | None = None

    def step(self, t_s: float, airspeed_m_s, armed, capacity_mah=None) -> None:
        p = self.p
        v = np.broadcast_to(np.asarray(airspeed_m_s, float), (self.n,))
        v = np.where(np.isfinite(v) & (v > 0), v, 0.0)
        on = np.broadcast_to(np.asarray(armed, bool), (self.n,))
        i = p.idle_current_a + np.where(on, p.cruise_current_a * (v / p.cruise_airspeed_m_s) ** p.exponent, 0.0)
        if capacity_mah is not None:
            cap = np.broadcast_to(np.asarray(capacity_mah, float), (self.n,))
            self.capacity_mah = np.where(np.isfinite(cap) & (cap > 0), cap, self.capacity_mah)
        t = float(t_s)
        if self._t is not None and t > self._t:
            dt_h = (t - self._t) / 3600.0
            self.consumed_wh = self.consumed_wh + self.current_a * self.voltage_v * dt_h
            self.consumed_mah = self.consumed_mah + self.current_a * dt_h * 1000.0
        self._t = t
        self.current_a = i

    @property
    def remaining_frac(self) -> np.ndarray:
        return np.maximum(0.0, 1.0 - self.consumed_mah / self.capacity_mah)

    @property
    def voltage_v(self) -> np.ndarray:
        p = self.p
        ocv = p.voltage_empty_v + (p.voltage_full_v - p.voltage_empty_v) * self.remaining_frac
        return np.maximum(0.0, ocv - p.internal_resistance_ohm * self.current_a)

    def cell(self, j: int) -> "BatteryCell":
        if not 0 <= int(j) < self.n:
            raise ValueError(f"battery index {j!r} outside 0..{self.n - 1}")
        return BatteryCell(self, int(j))


class BatteryCell:
    """Battery j of a :class:`BatteryBank`, read only (what BATTERY_STATUS and SYS_STATUS report)."""

    __slots__ = ("bank", "j")

    def __init__(self, bank: BatteryBank, j: int):
        self.bank, self.j = bank, j

    @property
    def p(self) -> BatteryParams:
        return self.bank.p

    @property
    def consumed_mah(self) -> float:
        return float(self.bank.consumed_mah[self.j])

    @property
    def consumed_wh(self) -> float:
        return float(self.bank.consumed_wh[self.j])

    @property
    def current_a(self) -> float:
        return float(self.bank.current_a[self.j])

    @property
    def remaining_pct(self) -> float:
        return 100.0 * max(0.0, 1.0 - self.consumed_mah / float(self.bank.capacity_mah[self.j]))

    @property
    def voltage_v(self) -> float:
        p = self.bank.p
        ocv = p.voltage_empty_v + (p.voltage_full_v - p.voltage_empty_v) * self.remaining_pct / 100.0
        return max(0.0, ocv - p.internal_resistance_ohm * self.current_a)
