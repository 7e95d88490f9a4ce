"""Scenario files (TOML) for the live SITL: parsing, validation, the built-in default, and the
per-worker spec JSON the launcher hands to each worker process.

    scn = load_scenario("my.toml")        # or default_scenario(), or parse_scenario(text)
    specs = worker_specs(scn, router_endpoints, out_dir)   # [WorkerSpec]; spec.write(path)

Every validation error is a `ScenarioError` whose message is ONE line naming the key (dotted,
e.g. ``uavs.count``) and saying what was expected; the CLI turns it into exit status 2.
Unknown keys are errors too (a typo must not be silently ignored).

Layout of a scenario: the sections [run], [bus], [mavlink], [uavs], [beacon], [sonde] and
[ground_station], every key optional, each declared once below with its default, its check and
its doc (sitl.params.param); `skyfuse scenario` prints them all as the documented default
(DEFAULT_SCENARIO_TOML, generated from the declarations). And:

    [faults]       network faults, a table LINK = "SPEC" (sitl.netfault's netem-like text), e.g.
                   "mav:1" = "loss=10% delay=100ms~20ms"    (MAVLink of vehicle 1, both ways;
                                                              "mav:1:up" vehicle->GCS, "mav:1:down")
                   "zenoh:gs" = "partition=100-130"         (a worker's Zenoh session: vehicles<k>, gs)
                   "bus:*/uav/2/**" = "loss=20%"            (bus keys, at their publishers)
                   Times in a spec (partitions) are simulated seconds since the run's start.
                   None by default; `skyfuse fault set LINK SPEC` changes them while a run goes.
"""
from __future__ import annotations

import copy
import json
import math
import tomllib
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

from sitl.params import checks, param, toml_table

# GPS time of the built-in almanac's epoch + 1 h (the seed 002 start; vehicles.uav_nav
# .EXAMPLE_T0_GPS_S, which sitl may not import)
from sitl.constants import MAX_MAVLINK_VEHICLES  # system ids 1..249 of a MAVLink block
from sitl.gnss.orbits import DEFAULT_TOA_GPS_S

DEFAULT_T0_GPS_S = DEFAULT_TOA_GPS_S + 3600.0
SPEC_VERSION = 2  # 2: params (the component's parameters the composition root built)
UAV_PATTERNS = ("orbit", "north")  # [uavs].pattern (module docstring; vehicles/process.py flies them)
UAV_STARTS = ("in-flight", "ground")  # [uavs].start (vehicles/process.py: the autopilots' initial state)
BEACON_MODES = ("seed", "legs", "static", "racetrack")  # [beacon].mode (vehicles/beacon.py)
# "orbit": the UAVs' guidance turns at most this fast (vehicles.uav.Racetrack's max_turn_rate_rad_s)
ORBIT_MAX_TURN_RATE_RAD_S = math.radians(3.0)



class ScenarioError(ValueError):
    """A scenario key with a bad value (one line: ``scenario: <key>: <what was expected>``)."""


def _err(key: str, expected: str, got: Any = None, *, show_got: bool = True) -> ScenarioError:
    if not show_got:
        return ScenarioError(f"scenario: {key}: {expected}")
    g = repr(got)
    if len(g) > 60:
        g = g[:57] + "..."
    return ScenarioError(f"scenario: {key}: expected {expected}, got {g}")


# ---------------------------------------------------------------- value checks


def _number(key, v, *, lo=None, hi=None, lo_open=False, allow_int=True) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or (isinstance(v, int) and not allow_int):
        raise _err(key, "a number", v)
    v = float(v)
    what = "a finite number"
    if lo is not None:
        what += f" {'>' if lo_open else '>='} {lo:g}"
    if hi is not None:
        what += f" <= {hi:g}"
    if not math.isfinite(v) or (lo is not None and (v <= lo if lo_open else v < lo)) or (hi is not None and v > hi):
        raise _err(key, what, v)
    return v


def _int(key, v, *, lo=None, hi=None) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise _err(key, "an integer", v)
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        rng = f">= {lo}" if hi is None else f"in {lo}..{hi}"
        raise _err(key, f"an integer {rng}", v)
    return v


def _bool(key, v) -> bool:
    if not isinstance(v, bool):
        raise _err(key, "true or false", v)
    return v


def _str(key, v, *, choices=None, ident=False, allow_empty=True) -> str:
    if not isinstance(v, str):
        raise _err(key, "a string", v)
    if choices is not None and v not in choices:
        raise _err(key, f"one of {', '.join(choices)}", v)
    if ident:
        from sitl.bus import is_valid_id
        if not is_valid_id(v):
            raise _err(key, "1..64 characters of [A-Za-z0-9_.-]", v)
    if not allow_empty and not v:
        raise _err(key, "a non-empty string", v)
    return v


def _geo(key, v, n=3) -> tuple:
    names = "[lat deg, lon deg, h m]" if n == 3 else "[lat deg, lon deg]"
    if not isinstance(v, list) or len(v) != n:
        raise _err(key, f"a list {names}", v)
    lat = _number(f"{key}[0]", v[0], lo=-90, hi=90)
    lon = _number(f"{key}[1]", v[1], lo=-180, hi=180)
    if n == 2:
        return (lat, lon)
    h = _number(f"{key}[2]", v[2], lo=-500, hi=100000)
    return (lat, lon, h)


def _interval(key, v) -> tuple:
    if not isinstance(v, list) or len(v) != 2:
        raise _err(key, "a list [start s, end s]", v)
    a = _number(f"{key}[0]", v[0], lo=0)
    b = _number(f"{key}[1]", v[1], lo=0)
    if not a < b:
        raise _err(key, "start < end", v)
    return (a, b)


def _hostport(key, v) -> tuple:
    s = _str(key, v)
    host, sep, port = s.rpartition(":")
    if not sep or not host or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise _err(key, '"HOST:PORT" with a port in 1..65535', v)
    return s


def zenoh_endpoint(key, v) -> str:
    """A Zenoh endpoint "PROTO/HOST:PORT" (tcp, udp, quic, tls) named ``key``: the text, or ScenarioError."""
    s = _str(key, v)
    proto, sep, rest = s.partition("/")
    host, sep2, port = rest.rpartition(":")
    if proto not in ("tcp", "udp", "quic", "tls") or not sep or not sep2 or not host or not port.isdigit() \
            or not 0 <= int(port) <= 65535:
        raise _err(key, 'a Zenoh endpoint "tcp/HOST:PORT"', v)
    return s


# ---------------------------------------------------------------- the dataclasses
# Every key is declared once, here: its default, its check and its doc (sitl.params.param). The
# validation table, the built-in default scenario (DEFAULT_SCENARIO_TOML) and `skyfuse scenario`
# come from these declarations.


def _n(**kw):
    return lambda k, v: _number(k, v, **kw)


def _i(**kw):
    return lambda k, v: _int(k, v, **kw)


def _ident(k, v):
    return _str(k, v, ident=True)


@dataclass(frozen=True)
class RunSection:
    """The run: what it is called, its seed, its simulated duration and pace."""

    id: str = param("demo", check=_ident, doc="the run's id: the first part of every bus key (1..64 of [A-Za-z0-9_.-])")
    seed: int = param(1, check=_i(lo=0, hi=2**63 - 1), doc="seed of every random draw of the run")
    duration_s: float = param(600.0, check=_n(lo=0, lo_open=True, hi=10 * 86400), doc="simulated seconds the run lasts")
    speed: float = param(1.0, check=_n(lo=0, lo_open=True, hi=1000), doc="x real time (a live run's pace)")
    rate_hz: float = param(1.0, check=_n(lo=0, lo_open=True, hi=100), doc="epochs per second of simulated time")
    t0_gps_s: float = param(DEFAULT_T0_GPS_S, check=_n(lo=0), doc="the run's start, GPS seconds")


@dataclass(frozen=True)
class BusSection:
    """The Zenoh bus."""

    zenoh: tuple = param((), check=lambda k, v: tuple(zenoh_endpoint(f"{k}[{i}]", e) for i, e in enumerate(_list(k, v))),
                         doc='external Zenoh router endpoints ["tcp/HOST:PORT", ...]; empty: an embedded router')
    listen: str = param("tcp/127.0.0.1:0", check=zenoh_endpoint, doc="the embedded router's listen endpoint (port 0: any free)")
    log: bool = param(True, check=_bool, doc="record the bus traffic to OUT/bus.log (what `skyfuse replay` reads)")
    lease_ms: int = param(10000, check=_i(lo=100, hi=600000), doc="Zenoh session lease, ms (a dead peer is dropped after it)")


@dataclass(frozen=True)
class MavlinkSection:
    """The vehicles as MAVLink 2 endpoints over UDP (and TCP, as ArduPilot SITL's SERIAL0)."""

    enabled: bool = param(True, check=_bool, doc="vehicles speak MAVLink 2 over UDP")
    gcs: str = param("127.0.0.1:14550", check=_hostport,
                     doc='the ground-control station\'s address "HOST:PORT" (of block 1; MAVLink blocks: '
                         'sitl/mavlink/blocks.py)')
    gcs_port_step: int = param(10, check=_i(lo=0, hi=1000),
                               doc="block k's GCS port: gcs's port + gcs_port_step (k - 1) (14550, 14560, ...); "
                                   "0: every block to the one gcs address")
    block_size: int = param(MAX_MAVLINK_VEHICLES, check=_i(lo=1, hi=MAX_MAVLINK_VEHICLES),
                            doc="vehicles per MAVLink network (block: system ids 1..block_size; 250 is the ground "
                                "station on every block): vehicle v is in block (v - 1) // block_size + 1")
    base_port: int = param(5760, check=_i(lo=1024, hi=65000),
                           doc="the vehicle with system id s in block k listens on base_port + (k - 1) + 10 (s - 1) "
                               "(UDP, and TCP when tcp = true): block 1 is ArduPilot SITL's base_port + 10 i")
    rate_hz: float = param(10.0, check=_n(lo=0, lo_open=True, hi=100),
                           doc="the endpoints' epochs per second of simulated time: sockets read, replies and "
                               "streams sent (streams up to this rate; telemetry between the world's epochs is "
                               "the vehicles' state propagated by their motion); at least run.rate_hz is used")
    tcp: bool = param(True, check=_bool,
                      doc="each vehicle also serves MAVLink on TCP, on its UDP port (ArduPilot SITL's SERIAL0: "
                          "mavproxy.py --master tcp:127.0.0.1:5760)")
    signing_key_file: str = param("", check=_str, doc="a MAVLink 2 signing key file (32 raw bytes, 64 hex digits or a passphrase), "
                                                      "every block's; block k signs on link id k - 1; empty: unsigned")
    tlog: bool = param(True, check=_bool, doc="write .tlog files of the MAVLink traffic (MAVProxy's format)")


@dataclass(frozen=True)
class UavSection:
    """The UAV swarm."""

    count: int = param(3, check=_i(lo=0, hi=100000), doc="number of UAVs")
    per_process: int = param(100, check=_i(lo=1, hi=100000), doc="UAVs per vehicle worker process")
    center: tuple = param((45.15, 30.15), check=lambda k, v: _geo(k, v, 2), doc="centre of the formation [lat deg, lon deg]")
    radius_m: float = param(15000.0, check=_n(lo=0, hi=2e6), doc="radius of the ring of starts about center, m")
    alt_m: float = param(2000.0, check=_n(lo=-500, hi=100000), doc="height of the lowest UAVs, m")
    alt_step_m: float = param(2000.0, check=_n(lo=0, hi=20000),
                              doc="the ring's heights are alt_m + 0 / 1 / 2 x alt_step_m in turn (a tilted formation)")
    speed_m_s: float = param(100.0, check=_n(lo=0, hi=2000), doc="the UAVs' airspeed, m/s")
    nav_rate_hz: float = param(1.0, check=_n(lo=0, lo_open=True, hi=100),
                               doc="UavNav messages per simulated second (beacon measurements carry the nav anyway)")
    starts: tuple = param((), check=lambda k, v: tuple(_geo(f"{k}[{i}]", s) for i, s in enumerate(_list(k, v))),
                          doc="[[lat deg, lon deg, h m], ...], one per UAV; empty: a ring of radius_m about center")
    pattern: str = param("orbit", check=lambda k, v: _str(k, v, choices=UAV_PATTERNS),
                         doc='how they fly from their starts at speed_m_s: "orbit" (level clockwise circles about '
                             'center, each through its start, held by guidance, for ever) or "north" (the seed 002 '
                             'sinusoidal law heading north: the formation leaves the area at ~100 m/s)')
    start: str = param("in-flight", check=lambda k, v: _str(k, v, choices=UAV_STARTS),
                       doc='"in-flight": armed, in AUTO, flying the pattern from their starts (the seed scenarios); '
                           '"ground": disarmed in MANUAL on the ground below their starts (at ground_alt_m) until a '
                           'GCS arms them and takes them off (TAKEOFF, or AUTO with a mission)')
    ground_alt_m: float = param(0.0, check=_n(lo=-500, hi=10000),
                                doc='height of the ground the UAVs stand on with start = "ground", m')

    def start_points(self) -> list[tuple]:
        """(lat deg, lon deg, h m) of every UAV: ``starts``, or a ring of radius_m about center
        (heights alt_m + 0 / 1 / 2 x alt_step_m in turn: a formation whose plane is tilted, so
        that the mirror image of a low beacon through it is far from any plausible beacon)."""
        if self.starts:
            return [tuple(s) for s in self.starts]
        lat0, lon0 = self.center
        out = []
        for i in range(self.count):
            a = 2.0 * math.pi * i / self.count + 0.3
            dn, de = self.radius_m * math.cos(a), self.radius_m * math.sin(a)
            lat = lat0 + math.degrees(dn / 6_371_000.0)
            lon = lon0 + math.degrees(de / (6_371_000.0 * math.cos(math.radians(lat0))))
            out.append((lat, lon, self.alt_m + self.alt_step_m * (i % 3)))
        return out


@dataclass(frozen=True)
class BeaconSection:
    """The moving radio beacon the ground station locates."""

    id: str = param("b1", check=_ident, doc="the beacon's id")
    mode: str = param("racetrack", check=lambda k, v: _str(k, v, choices=BEACON_MODES),
                      doc='"racetrack" (a clockwise holding pattern at 115 m/s, 200 s legs north and south, 180 deg '
                          'turns at 1.5 deg/s, first leg north from start), "legs" (8 straight 200 s legs and 90 deg '
                          'turns, alternately right and left, first north, then straight on east), "seed" (the seed '
                          '002 geodetic law: north at 115 +- 10 m/s) or "static"')
    start: tuple = param((45.0466, 30.094, 300.0), check=_geo, doc="where it is at the run's start [lat deg, lon deg, h m]")


@dataclass(frozen=True)
class SondeSection:
    """The radiosonde, its relayed GNSS and the aerological radar."""

    enabled: bool = param(True, check=_bool, doc="fly and track a radiosonde")
    id: str = param("s0000", check=_ident, doc="the sonde's id")
    radar_id: str = param("arls1", check=_ident, doc="the aerological radar's id")
    launch: tuple = param((55.93, 37.52, 190.0), check=_geo, doc="the launch pad [lat deg, lon deg, h m]")
    gcpp_offset_m: float = param(300.0, check=_n(lo=0, lo_open=True, hi=1e5),
                                 doc="the radar and ground receiver from the launch pad, m")
    gcpp_bearing_deg: float = param(140.0, check=_n(lo=0, hi=360), doc="their bearing from the launch pad, deg")
    radar_loss_s: tuple = param((30.0, 330.0), check=_interval,
                                doc="[start, end] after launch, s: the radar's angle tracking is lost")
    gnss_outage_s: tuple = param((3600.0, 3720.0), check=_interval,
                                 doc="[start, end] after launch, s: the relay delivers nothing")
    wind_scale: float = param(1.15, check=_n(lo=0, hi=10),
                              doc="the sonde model's wind profile x this (the default winter jet x 1.15: 58 -> 67 m/s at 11 km)")


@dataclass(frozen=True)
class GroundStationSection:
    """The fusing ground station."""

    hold_wall_s: float = param(1.0, check=_n(lo=0, hi=60),
                               doc="the longest the GS waits for an epoch's messages after its time, wall seconds "
                                   "(it goes on as soon as every source has delivered it)")
    beacon_init_epochs: int = param(3, check=_i(lo=1, hi=100), doc="epochs of the beacon's blind (multilateration) start")
    integrity: bool = param(False, check=_bool,
                            doc="the sonde tracker's integrity monitor (its events go out on the bus and as STATUSTEXT)")
    lag_window_s: float = param(5.0, check=_n(lo=0, hi=600),
                                doc="late (out-of-sequence) measurements this old are re-processed (0: dropped)")
    stale_after_s: float = param(3.0, check=_n(lo=0, lo_open=True, hi=3600),
                                 doc="a source silent this long (simulated s) is flagged stale")
    link_stats_every_s: float = param(10.0, check=_n(lo=0, lo_open=True, hi=3600),
                                      doc="LinkStats of every link this often, simulated s (and on stale / back)")
    max_ahead_s: float = param(2.0, check=_n(lo=0, hi=3600),
                               doc='the time guard: an input further ahead of the GS\'s clock than this is refused '
                                   '("future"); one older than hold_wall_s x speed + lag_window_s behind it ("stale")')


def _fault_link(key: str, link) -> str:
    """A link name of the [faults] table, checked and normalised (sitl.netfault.spec.canonical_link);
    the worker / system id ranges are checked in _cross_checks."""
    from sitl.netfault.spec import LinkNameError, canonical_link

    try:
        return canonical_link(link)
    except LinkNameError as e:
        raise _err(key, e.expected, link, show_got=e.show_got) from None


def fault_spec_text(key: str, text) -> str:
    """Validate a fault spec text with sitl.netfault.parse_spec; the text as written (an error:
    ScenarioError naming the key with the FaultSpecError's message)."""
    if not isinstance(text, str):
        raise _err(key, "a fault spec string like \"loss=10% delay=100ms\"", text)
    from sitl.netfault import FaultSpecError, parse_spec
    try:
        parse_spec(text)
    except FaultSpecError as e:
        raise ScenarioError(f"scenario: {key}: {' '.join(str(e).split())}") from None
    return text


@dataclass(frozen=True)
class FaultsSection:
    """The [faults] table: ((link, spec text), ...) in the file's order."""

    links: tuple = ()
    enabled: bool = False  # the scenario has a [faults] table (even empty): the launcher starts the proxies

    def get(self, link: str, default=None):
        for k, v in self.links:
            if k == link:
                return v
        return default

    def of_kind(self, kind: str) -> list[tuple[str, str]]:
        """(link, spec) of one kind ("mav", "zenoh" or "bus")."""
        return [(k, v) for k, v in self.links if k.split(":", 1)[0] == kind]

    def __bool__(self) -> bool:
        return self.enabled


def _faults_section(value) -> FaultsSection:
    if not isinstance(value, dict):
        raise _err("faults", 'a table [faults] of LINK = "SPEC"', value)
    links = []
    seen = set()
    for link, text in value.items():
        key = f'faults."{link}"'
        name = _fault_link(key, link)
        if name in seen:
            raise ScenarioError(f"scenario: {key}: the link appears twice")
        seen.add(name)
        links.append((name, fault_spec_text(key, text)))
        if name.startswith("zenoh:"):  # a byte stream: delay, rate and partitions only
            from sitl.netfault import parse_spec
            from sitl.netfault.tcp_proxy import stream_spec
            try:
                stream_spec(parse_spec(text), name)
            except ValueError as e:
                raise ScenarioError(f"scenario: {key}: {' '.join(str(e).split())}") from None
    return FaultsSection(tuple(links), True)


@dataclass(frozen=True)
class Scenario:
    run: RunSection = field(default_factory=RunSection)
    bus: BusSection = field(default_factory=BusSection)
    mavlink: MavlinkSection = field(default_factory=MavlinkSection)
    uavs: UavSection = field(default_factory=UavSection)
    beacon: BeaconSection = field(default_factory=BeaconSection)
    sonde: SondeSection = field(default_factory=SondeSection)
    ground_station: GroundStationSection = field(default_factory=GroundStationSection)
    faults: FaultsSection = field(default_factory=FaultsSection)
    source: str = "<default>"

    @property
    def n_uav_processes(self) -> int:
        return max(1, math.ceil(self.uavs.count / self.uavs.per_process))

    def replace(self, **sections) -> Scenario:
        """A copy with some sections' fields replaced: ``replace(run={"speed": 10})``."""
        import dataclasses
        kw = {}
        for name, changes in sections.items():
            kw[name] = dataclasses.replace(getattr(self, name), **changes)
        return dataclasses.replace(self, **kw)

    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("source")
        d.pop("faults")
        if self.faults.enabled:
            d["faults"] = {k: v for k, v in self.faults.links}
        return d

    @property
    def n_vehicles(self) -> int:
        return self.uavs.count + (1 if self.sonde.enabled else 0)

    def worker_names(self) -> list[str]:
        return [f"vehicles{g}" for g in range(self.n_uav_processes)] + ["gs"]


_DEFAULT_HEADER = """\
# skyfuse built-in default scenario: 3 UAVs orbiting (15 km, clockwise) the area where a moving
# radio beacon flies its racetrack (centred on theirs), one radiosonde tracked by its relayed GNSS
# and an aerological radar.
# Every key is optional; each is shown here with its default and what it means.
"""


def default_scenario_toml() -> str:
    """The built-in default scenario as documented TOML: every section and key with its default,
    each key preceded by its doc (from the declarations)."""
    s = Scenario()
    return _DEFAULT_HEADER + "\n" + "\n\n".join(toml_table(name, getattr(s, name)) for name in _SECTIONS) + "\n"


# per section: its dataclass and {key: check(key, value) -> stored value}, from the declarations
_SECTIONS: dict[str, tuple[type, dict]] = {
    name: (cls, checks(cls)) for name, cls in (
        ("run", RunSection), ("bus", BusSection), ("mavlink", MavlinkSection), ("uavs", UavSection),
        ("beacon", BeaconSection), ("sonde", SondeSection), ("ground_station", GroundStationSection))
}


DEFAULT_SCENARIO_TOML = default_scenario_toml()


def _list(key, v) -> list:
    if not isinstance(v, list):
        raise _err(key, "a list", v)
    return v


def _near(name: str, options) -> str:
    import difflib
    close = difflib.get_close_matches(name, list(options), n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


def scenario_from_dict(doc: dict, source: str = "<dict>") -> Scenario:
    """Validate a parsed TOML document (every key checked; unknown keys are errors)."""
    if not isinstance(doc, dict):
        raise ScenarioError("scenario: expected a table at the top level")
    sections = {}
    for name, value in doc.items():
        if name == "faults":
            sections[name] = _faults_section(value)
            continue
        if name not in _SECTIONS:
            raise ScenarioError(f"scenario: unknown section [{name}]{_near(name, [*_SECTIONS, 'faults'])}; "
                                f"expected one of {', '.join(_SECTIONS)}, faults")
        cls, checks = _SECTIONS[name]
        if not isinstance(value, dict):
            raise _err(name, "a table [" + name + "]", value)
        kw = {}
        for key, v in value.items():
            full = f"{name}.{key}"
            if key not in checks:
                raise ScenarioError(f"scenario: unknown key {full}{_near(key, checks)}; expected one of "
                                    f"{', '.join(checks)}")
            kw[key] = checks[key](full, v)
        sections[name] = cls(**kw)
    scn = Scenario(**sections, source=source)
    _cross_checks(scn)
    return scn


def run_keys(scn: Scenario) -> list[str]:
    """The bus keys a run of this scenario publishes (sitl.bus.schema's key_for with the
    scenario's ids; not the ground station's per-link / per-channel keys, nor the control keys)."""
    from sitl.bus.schema import (
        BeaconMeasurement,
        Estimate,
        RadarMeasurement,
        SondeRelay,
        Truth,
        UavNav,
        key_for,  # here: sitl.bus loads numba kernels
    )
    r, b = scn.run.id, scn.beacon.id
    keys = []
    for i in range(1, scn.uavs.count + 1):
        keys += [key_for(r, UavNav, uav=i), key_for(r, BeaconMeasurement, uav=i, beacon=b),
                 key_for(r, Truth, kind="uav", id=i)]
    if scn.uavs.count:
        keys += [key_for(r, Truth, kind="beacon", id=b), key_for(r, Estimate, kind="beacon", id=b)]
    if scn.sonde.enabled:
        sid = scn.sonde.id
        keys += [key_for(r, SondeRelay, sonde=sid), key_for(r, Truth, kind="sonde", id=sid),
                 key_for(r, Estimate, kind="sonde", id=sid)]
        if scn.sonde.radar_id:
            keys.append(key_for(r, RadarMeasurement, radar=scn.sonde.radar_id, sonde=sid))
    return keys


def _ground_distance_m(a, b) -> float:
    """Great-circle distance between (lat deg, lon deg) a and b on the 6371 km sphere, m."""
    la1, lo1, la2, lo2 = (math.radians(v) for v in (a[0], a[1], b[0], b[1]))
    h = math.sin(0.5 * (la2 - la1)) ** 2 + math.cos(la1) * math.cos(la2) * math.sin(0.5 * (lo2 - lo1)) ** 2
    return 2.0 * 6_371_000.0 * math.asin(min(1.0, math.sqrt(h)))


def _cross_checks(scn: Scenario) -> None:
    u = scn.uavs
    if u.starts and len(u.starts) != u.count:
        raise ScenarioError(f"scenario: uavs.starts: expected one start per UAV (uavs.count = {u.count}), "
                            f"got {len(u.starts)}")
    if u.count and u.pattern == "orbit" and not u.speed_m_s > 0:
        raise ScenarioError(f"scenario: uavs.speed_m_s: expected > 0 with uavs.pattern = \"orbit\", "
                            f"got {u.speed_m_s:g}")
    if u.count and u.pattern == "orbit":
        # each UAV's circle: its start's distance from center (sphere: the guidance measures it on the
        # ellipsoid, within 0.5 %), at least the tightest turn at speed_m_s (5 % margin)
        r_min = 1.05 * u.speed_m_s / ORBIT_MAX_TURN_RATE_RAD_S
        for i, (lat, lon, *_) in enumerate(u.start_points()):
            r = _ground_distance_m(u.center, (lat, lon))
            if not r >= max(r_min, 1.0):
                key = f"uavs.starts[{i}]" if u.starts else "uavs.radius_m"
                raise ScenarioError(f"scenario: {key}: expected a start at least {max(r_min, 1.0):.0f} m from "
                                    f"uavs.center with uavs.pattern = \"orbit\" (a circle about center at "
                                    f"speed_m_s), got {r:.0f} m")
    if u.count and u.count < 3:
        raise ScenarioError(f"scenario: uavs.count: expected 0 or >= 3 (the beacon locator needs 3 UAVs), "
                            f"got {u.count}")
    if scn.mavlink.enabled:  # the MAVLink blocks' ids and ports (sitl.mavlink.blocks)
        from sitl.mavlink.blocks import MavlinkPlan
        proto, _, rest = scn.bus.listen.partition("/")
        lport = rest.rpartition(":")[2]
        fixed = int(lport) if proto == "tcp" and not scn.bus.zenoh and lport.isdigit() else None
        for key, expected in MavlinkPlan.of(scn).problems(bus_listen_port=fixed, tcp=scn.mavlink.tcp)[:1]:
            raise ScenarioError(f"scenario: {key}: {expected}")
    for link, _ in scn.faults.links:
        kind, _, rest = link.partition(":")
        if kind == "zenoh" and rest not in scn.worker_names():
            raise ScenarioError(f'scenario: faults."{link}": expected a worker of this scenario '
                                f"({', '.join('zenoh:' + w for w in scn.worker_names())})")
        if kind == "mav" and int(rest.split(":")[0]) > max(scn.n_vehicles, 1):
            raise ScenarioError(f'scenario: faults."{link}": expected a vehicle number in 1..{scn.n_vehicles} '
                                f"(UAVs then the sonde; in block 1 it is the system id)")
        if kind == "bus":
            keys = run_keys(scn)
            from sitl.bus.transport import (
                key_matches,  # here: sitl.bus loads numba kernels
            )
            if not any(key_matches(rest, k) for k in keys):
                sample = ", ".join([k for k in keys if "/truth/" not in k][:5])
                raise ScenarioError(f'scenario: faults."{link}": matches no key this run publishes '
                                    f"(they look like {sample})")
    if scn.run.duration_s * scn.run.rate_hz < 1:
        raise ScenarioError("scenario: run.duration_s: expected at least one epoch (duration_s x rate_hz >= 1), "
                            f"got {scn.run.duration_s}")


def parse_scenario(text: str, source: str = "<text>") -> Scenario:
    """Parse and validate a scenario TOML text."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"scenario: {source}: not valid TOML: {exc}") from None
    return scenario_from_dict(doc, source)


def load_scenario(path) -> Scenario:
    """Read, parse and validate a scenario file (missing / unreadable file: ScenarioError)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ScenarioError(f"scenario: {str(p)!r}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"scenario: {str(p)!r}: cannot read: {exc}") from None
    return parse_scenario(text, str(p))


def default_scenario() -> Scenario:
    """The built-in default (DEFAULT_SCENARIO_TOML)."""
    return parse_scenario(DEFAULT_SCENARIO_TOML, "<built-in default>")


# ---------------------------------------------------------------- worker specs


@dataclass
class WorkerSpec:
    """What one worker process needs, written as JSON and passed as its only argument."""

    name: str  # "vehicles0", "vehicles1", ..., "gs"
    module: str  # "vehicles.process" | "ground_station.process"
    role: str  # "vehicles" | "ground_station"
    scenario: dict
    zenoh_connect: list
    run_id: str
    out_dir: str
    group_index: int = 0
    n_groups: int = 1
    uav_indices: list = field(default_factory=list)  # global UAV indices (0-based) of this group
    with_beacon_truth: bool = False  # this group publishes the beacon's truth
    with_sonde: bool = False
    status_interval_wall_s: float = 1.0
    # the component's parameters that the scenario does not hold, built by the composition root
    # (JSON: e.g. the GS's sonde tracker tuning, sitl.app.components.gs_spec_params)
    params: dict = field(default_factory=dict)
    spec_version: int = SPEC_VERSION

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=1)  # in order: [faults] rules are first-match-wins

    def write(self, path) -> Path:
        p = Path(path)
        p.write_text(self.to_json(), encoding="utf-8")
        return p

    @classmethod
    def read(cls, path) -> WorkerSpec:
        d = json.loads(Path(path).read_text(encoding="utf-8"))
        if not isinstance(d, dict) or d.get("spec_version") != SPEC_VERSION:
            raise ValueError(f"{path}: not a skyfuse worker spec of version {SPEC_VERSION}")
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"{path}: unknown spec keys {sorted(unknown)}")
        return cls(**d)

    def scenario_obj(self) -> Scenario:
        return scenario_from_dict(to_toml_like(self.scenario), f"spec {self.name}")


def to_toml_like(d: dict) -> dict:
    """asdict() output back to what TOML would give (tuples -> lists)."""
    def conv(v):
        if isinstance(v, (tuple, list)):
            return [conv(x) for x in v]
        if isinstance(v, dict):
            return {k: conv(x) for k, x in v.items()}
        return v
    return conv(d)


def worker_specs(scn: Scenario, zenoh_connect, out_dir, overrides: dict | None = None) -> list[WorkerSpec]:
    """One spec per vehicle group (uavs.per_process UAVs each; the first also carries the
    beacon's truth and the sonde) and one for the ground station.

    overrides: {worker name: {"zenoh_connect": [...], "mavlink_gcs": "HOST:PORT"}} -- where
    the launcher's fault proxies sit between that worker and the router / the GCS (the GCS of
    every MAVLink block: the override sets gcs_port_step = 0)."""
    specs = _worker_specs(scn, zenoh_connect, out_dir)
    for spec in specs:
        o = (overrides or {}).get(spec.name) or {}
        if "zenoh_connect" in o:
            spec.zenoh_connect = list(o["zenoh_connect"])
        if "mavlink_gcs" in o:  # every MAVLink block to that one address (sitl.mavlink.blocks)
            spec.scenario = copy.deepcopy(spec.scenario)
            spec.scenario["mavlink"]["gcs"] = o["mavlink_gcs"]
            spec.scenario["mavlink"]["gcs_port_step"] = 0
    return specs


def _worker_specs(scn: Scenario, zenoh_connect, out_dir) -> list[WorkerSpec]:
    doc = to_toml_like(scn.to_dict())
    n = scn.uavs.count
    groups = scn.n_uav_processes
    per = scn.uavs.per_process
    specs = []
    for g in range(groups):
        idx = list(range(g * per, min(n, (g + 1) * per)))
        specs.append(WorkerSpec(name=f"vehicles{g}", module="vehicles.process", role="vehicles", scenario=doc,
                                zenoh_connect=list(zenoh_connect), run_id=scn.run.id, out_dir=str(out_dir),
                                group_index=g, n_groups=groups, uav_indices=idx, with_beacon_truth=g == 0,
                                with_sonde=g == 0 and scn.sonde.enabled))
    specs.append(WorkerSpec(name="gs", module="ground_station.process", role="ground_station", scenario=doc,
                            zenoh_connect=list(zenoh_connect), run_id=scn.run.id, out_dir=str(out_dir)))
    return specs


__all__ = [
    "DEFAULT_SCENARIO_TOML",
    "DEFAULT_T0_GPS_S",
    "FaultsSection",
    "Scenario",
    "ScenarioError",
    "WorkerSpec",
    "default_scenario",
    "fault_spec_text",
    "load_scenario",
    "parse_scenario",
    "scenario_from_dict",
    "worker_specs",
]
