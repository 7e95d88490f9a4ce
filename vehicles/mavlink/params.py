"""A vehicle's parameter store, as the MAVLink parameter protocol sees it.

The store holds the values of a vehicle's real simulation parameters (SI units, the unit in
the doc), each declared once by a :class:`ParamSpec` (name <= 16 characters, as PARAM_VALUE's
``param_id`` allows; bounds; doc).  ``store.set(name, value)`` validates (known name, finite,
inside the bounds), stores and calls the change callbacks, so the simulation picks the new
value up; a callback that raises ``ValueError`` vetoes the change (the old value is kept).

Every value travels as MAV_PARAM_TYPE_REAL32 (a float32).  The store keeps the simulation's
exact values (a default 0.035 stays 0.035, not its float32 neighbour) and treats a PARAM_SET
whose float32 equals the current value's float32 as no change: a value read back and set
again changes nothing, and the simulation never moves by float32 rounding.

:func:`uav_param_specs` and :func:`sonde_param_specs` declare the parameters of a UAV
(its waypoint guidance and onboard GNSS navigation) and of a radiosonde (its flight model),
with the defaults read from the simulation objects themselves.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Callable, Iterable, Iterator

import numpy as np

from filters import params as declared
from filters.params import number, optional, param, require, string, validate

PARAM_ID_LEN = 16
_F32_MAX = float(np.finfo(np.float32).max)


class ParamError(ValueError):
    """A rejected parameter read/write (unknown name, NaN, out of bounds, vetoed)."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


def _f32(x: float) -> float:
    return float(np.float32(x))


def _param_id(key: str, value) -> str:
    """A MAVLink parameter name: 1..16 characters of A-Z, 0-9 and _."""
    if not (isinstance(value, str) and 1 <= len(value) <= PARAM_ID_LEN
            and all(c.isascii() and (c.isupper() or c.isdigit() or c == "_") for c in value)):
        raise declared.ParamError(key, f"expected 1..{PARAM_ID_LEN} characters of A-Z, 0-9 and _, got {value!r}")
    return value


_BOUND = number(finite=False)  # a float, +-inf allowed, not NaN


@dataclass(frozen=True)
class ParamSpec:
    """One parameter of a vehicle's store, as PARAM_VALUE carries it."""

    name: str = param(check=_param_id,
                      doc="the MAVLink name (PARAM_VALUE's param_id): 1..16 characters of A-Z, 0-9 and _")
    default: float = param(check=number(), doc="the value before any PARAM_SET, in the unit of ``doc`` (finite)")
    min: float = param(-math.inf, check=_BOUND, doc="lower bound of the value, inclusive (-inf: none)")
    max: float = param(math.inf, check=_BOUND, doc="upper bound of the value, inclusive (inf: none)")
    doc: str = param("", check=string(), doc="what the parameter is, with its unit")
    field: str | None = param(None, check=optional(string()),
                              doc="the attribute of the simulation object it mirrors (see ParamStore.replace_into), "
                                  "or None")

    def __post_init__(self):
        validate(self)
        require(self.min <= self.max, "max", f"expected >= min {self.min} (param {self.name}), got {self.max}")
        require(self.min <= self.default <= self.max, "default",
                f"expected a value in [{self.min}, {self.max}] (param {self.name}), got {self.default!r}")


class ParamStore(Mapping):
    """Mapping name -> float (read-only as a Mapping; write with :meth:`set`).

    Index order is the order of the specs (PARAM_VALUE.param_index).
    """

    def __init__(self, specs: Iterable[ParamSpec], values: Mapping[str, float] | None = None):
        self._specs: dict[str, ParamSpec] = {}
        for s in specs:
            if not isinstance(s, ParamSpec):
                raise ValueError(f"specs must be ParamSpec objects, got {type(s).__name__}")
            if s.name in self._specs:
                raise ValueError(f"duplicate param name {s.name!r}")
            self._specs[s.name] = s
        self._names = list(self._specs)
        self._index = {n: i for i, n in enumerate(self._names)}
        self._values = {n: float(s.default) for n, s in self._specs.items()}
        self._callbacks: list[Callable[[str, float], None]] = []
        for name, v in (values or {}).items():
            self.set(name, v)

    # Mapping
    def __getitem__(self, name: str) -> float:
        return self._values[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._names)

    def __len__(self) -> int:
        return len(self._names)

    def spec(self, name: str) -> ParamSpec:
        return self._specs[name]

    def index(self, name: str) -> int:
        return self._index[name]

    def name_at(self, index: int) -> str:
        if not 0 <= int(index) < len(self._names):
            raise ParamError("param_unknown", f"param index {index} out of range [0, {len(self._names)})")
        return self._names[int(index)]

    def on_change(self, callback: Callable[[str, float], None]) -> None:
        """Call ``callback(name, value)`` after every accepted change; raise ValueError to veto."""
        self._callbacks.append(callback)

    def set(self, name: str, value) -> float:
        """Validate and store; returns the stored value. Raises ParamError."""
        spec = self._specs.get(name)
        if spec is None:
            raise ParamError("param_unknown", f"unknown parameter {name!r}")
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise ParamError("param_rejected", f"{name}: value {value!r} is not a number") from None
        if not math.isfinite(v) or abs(v) > _F32_MAX:
            raise ParamError("param_rejected", f"{name}: value {v!r} is not a finite float32")
        if not spec.min <= v <= spec.max:
            raise ParamError("param_rejected", f"{name}: value {v} outside [{spec.min}, {spec.max}]")
        old = self._values[name]
        if _f32(v) == _f32(old):  # the same number on the wire: keep the exact value
            return old
        self._values[name] = v
        try:
            for cb in self._callbacks:
                cb(name, v)
        except ValueError as e:
            self._values[name] = old
            for cb in self._callbacks:  # put the simulation back on the old value
                try:
                    cb(name, old)
                except ValueError:
                    pass
            raise ParamError("param_rejected", f"{name}: value {v} vetoed by the simulation: {e}") from None
        return v

    def assign(self, name: str, value) -> None:
        """Store a value the simulation already uses (a group-wide quantity set through another
        vehicle's store): no checks beyond the bounds, no callbacks."""
        spec = self._specs[name]
        v = float(value)
        if not (math.isfinite(v) and spec.min <= v <= spec.max):
            raise ParamError("param_rejected", f"{name}: value {v!r} outside [{spec.min}, {spec.max}]")
        self._values[name] = v

    def replace_into(self, obj):
        """``dataclasses.replace(obj, field=value, ...)`` for every spec mirroring a field of obj."""
        names = {f.name for f in dataclasses.fields(obj)}
        changes = {s.field: self._values[s.name] for s in self._specs.values() if s.field in names}
        return dataclasses.replace(obj, **changes)


def _scalar(x, i: int = 0) -> float:
    a = np.asarray(x, dtype=float)
    return float(a.reshape(-1)[i] if a.ndim else a)


def uav_param_specs(mission=None, nav=None, i: int = 0) -> list[ParamSpec]:
    """Parameters of UAV i: its waypoint guidance (a vehicles.uav.WaypointMission, per-vehicle
    values at index i) and its onboard GNSS navigation (a vehicles.uav_nav.NavConfig).

    Defaults are read from the given objects (their class defaults when None).
    """
    from vehicles.uav_nav import GnssNoise, NavConfig

    specs = []
    if mission is not None:
        specs += [
            ParamSpec("WP_SPEED", _scalar(mission.speed_m_s, i), 1.0, 400.0,
                      "commanded airspeed on a mission, m/s", "speed_m_s"),
            ParamSpec("WP_RADIUS", _scalar(mission.accept_radius_m, i), 1.0, 1.0e5,
                      "waypoint acceptance radius, m", "accept_radius_m"),
            ParamSpec("WP_TURN_RATE", _scalar(mission.max_turn_rate_rad_s, i), 1e-4, 2.0,
                      "maximum turn rate, rad/s", "max_turn_rate_rad_s"),
            ParamSpec("WP_CLIMB_MAX", _scalar(mission.max_climb_m_s, i), 0.01, 100.0,
                      "maximum climb/sink rate, m/s (< WP_SPEED)", "max_climb_m_s"),
        ]
    nav = nav if nav is not None else NavConfig()
    noise = nav.noise if nav.noise is not None else GnssNoise()
    specs += [
        ParamSpec("GNSS_PSD_PR", noise.psd_pr_m2_s, 1e-6, 1e8,
                  "pseudorange noise PSD, m^2 s", "psd_pr_m2_s"),
        ParamSpec("GNSS_PSD_PRR", noise.psd_prr_m2_s, 1e-9, 1e4,
                  "Doppler (range-rate) noise PSD, m^2/s", "psd_prr_m2_s"),
        ParamSpec("GNSS_EL_MASK", nav.el_mask_rad, -math.pi / 2, 1.5,
                  "satellite elevation mask, rad", "el_mask_rad"),
        ParamSpec("NAV_Q", nav.q_m2_s3, 0.0, 1e4,
                  "onboard filter acceleration PSD, m^2/s^3", "q_m2_s3"),
    ]
    return specs


def autopilot_param_specs(config=None, sysid: int | None = None) -> list[ParamSpec]:
    """Parameters of a UAV's autopilot (vehicles.autopilot.config.AutopilotConfig: ArduPlane's
    names where ArduPlane has the quantity, SF_* otherwise), with the values of ``config``;
    SYSID_THISMAV (the MAVLink system id, read-only: the endpoint vetoes a set) when sysid is
    given.  The bounds here are the plain ones; AutopilotConfig's checks (AIRSPEED_MIN <=
    AIRSPEED_CRUISE <= AIRSPEED_MAX, ...) veto the rest when a set is applied."""
    from vehicles.autopilot.config import AutopilotConfig, param_rows
    cfg = config if config is not None else AutopilotConfig()
    specs = []
    for name, value, unit, doc, _ardupilot in param_rows(cfg):
        lo = -1.0 if name == "RTL_ALTITUDE" else 0.0  # RTL_ALTITUDE -1: return at the current height
        specs.append(ParamSpec(name, value, lo, math.inf, f"{doc}, {unit}" if unit else doc))
    if sysid is not None:
        specs.append(ParamSpec("SYSID_THISMAV", float(sysid), 1.0, 255.0,
                               "this vehicle's MAVLink system id (read-only: the UAV's index + 1)"))
    return specs


def sonde_param_specs(params=None) -> list[ParamSpec]:
    """Parameters of a radiosonde: its flight model (a vehicles.sonde.SondeParams)."""
    from vehicles.sonde import SondeParams

    p = params if params is not None else SondeParams()
    return [
        ParamSpec("SND_ASCENT", p.ascent_rate_m_s, 0.1, 50.0, "balloon ascent rate, m/s", "ascent_rate_m_s"),
        ParamSpec("SND_DESCENT_SL", p.descent_rate_sl_m_s, 0.1, 100.0,
                  "parachute terminal speed at sea level, m/s", "descent_rate_sl_m_s"),
        ParamSpec("SND_P1", p.p1_1_s, 1e-4, 10.0, "aerodynamic response rate p1, 1/s", "p1_1_s"),
        ParamSpec("SND_P2", p.p2_1_s, 1e-5, 10.0, "wind-fluctuation spectrum width p2, 1/s", "p2_1_s"),
        ParamSpec("SND_SIGMA_A", p.sigma_a_m_s2, 0.0, 10.0,
                  "horizontal gust acceleration std, m/s^2", "sigma_a_m_s2"),
        ParamSpec("SND_SIGMA_AV", p.sigma_a_vertical_m_s2, 0.0, 10.0,
                  "vertical gust acceleration std, m/s^2", "sigma_a_vertical_m_s2"),
    ]


def apply_uav_params(store: ParamStore, nav=None, mission=None, i: int = 0):
    """(NavConfig, WaypointMission) with the store's current values: the objects a UAV's
    simulation is rebuilt from after a PARAM_SET (call it from an ``on_change`` callback).

    nav: the NavConfig the specs were read from (None: skipped, returned as None); its GNSS
    noise is replaced too.  mission: the swarm's WaypointMission (None: skipped); only vehicle
    i's entries of its per-vehicle arrays change.  Both are frozen: new objects come back.
    The constructors validate: a ValueError raised here vetoes the change (the store
    restores the old value).
    """
    new_nav = None
    if nav is not None:
        new_nav = dataclasses.replace(store.replace_into(nav), noise=store.replace_into(nav.noise))
    new_mission = None
    if mission is not None:
        changes = {}
        for s in store._specs.values():
            if s.field is not None and s.field in {f.name for f in dataclasses.fields(mission)} \
                    and s.field != "waypoints_rad_m":
                arr = np.array(getattr(mission, s.field), dtype=float, copy=True)
                arr[int(i)] = store[s.name]
                changes[s.field] = arr
        new_mission = dataclasses.replace(mission, waypoints_rad_m=list(mission.waypoints_rad_m), **changes)
    return new_nav, new_mission
