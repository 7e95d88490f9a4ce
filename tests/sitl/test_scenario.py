"""Scenario files: validation (one line naming the key), the default, worker specs."""
from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sitl.scenario import (
    SPEC_VERSION,
    DEFAULT_SCENARIO_TOML,
    Scenario,
    ScenarioError,
    WorkerSpec,
    default_scenario,
    load_scenario,
    parse_scenario,
    scenario_from_dict,
    worker_specs,
)

# (TOML text, the key the error must name, a word of what was expected)
BAD = [
    ("[run]\nid = 'a b'", "run.id", "[A-Za-z0-9_.-]"),
    ("[run]\nseed = -1", "run.seed", "integer"),
    ("[run]\nseed = 1.5", "run.seed", "integer"),
    ("[run]\nduration_s = 0", "run.duration_s", "> 0"),
    ("[run]\nduration_s = 'long'", "run.duration_s", "number"),
    ("[run]\nspeed = -2.0", "run.speed", "> 0"),
    ("[run]\nspeed = nan", "run.speed", "finite"),
    ("[run]\nrate_hz = 0", "run.rate_hz", "> 0"),
    ("[run]\nt0_gps_s = -5", "run.t0_gps_s", ">= 0"),
    ("[bus]\nzenoh = 'tcp/127.0.0.1:7447'", "bus.zenoh", "a list"),
    ("[bus]\nzenoh = ['127.0.0.1:7447']", "bus.zenoh[0]", "tcp/HOST:PORT"),
    ("[bus]\nlisten = 'tcp/127.0.0.1:99999'", "bus.listen", "tcp/HOST:PORT"),
    ("[bus]\nlog = 'yes'", "bus.log", "true or false"),
    ("[bus]\nlease_ms = 5", "bus.lease_ms", "integer"),
    ("[mavlink]\ngcs = 'localhost'", "mavlink.gcs", "HOST:PORT"),
    ("[mavlink]\nbase_port = 80", "mavlink.base_port", "integer"),
    ("[mavlink]\nenabled = 1", "mavlink.enabled", "true or false"),
    ("[uavs]\ncount = -3", "uavs.count", "integer"),
    ("[uavs]\ncount = 2", "uavs.count", ">= 3"),
    ("[uavs]\nper_process = 0", "uavs.per_process", "integer"),
    ("[uavs]\ncount = 2490", "uavs.count", "at most 10 x mavlink.block_size = 2490 vehicles"),  # + the sonde
    ("[uavs]\ncenter = [45.0]", "uavs.center", "[lat deg, lon deg]"),
    ("[uavs]\ncenter = [95.0, 30.0]", "uavs.center[0]", "<= 90"),
    ("[uavs]\nradius_m = -1.0", "uavs.radius_m", ">= 0"),
    ("[uavs]\ncount = 3\nstarts = [[45.0, 30.0, 1000.0]]", "uavs.starts", "one start per UAV"),
    ("[uavs]\nstarts = [[45.0, 300.0, 1000.0]]", "uavs.starts[0][1]", "<= 180"),
    ("[beacon]\nmode = 'zigzag'", "beacon.mode", "seed, legs, static"),
    ("[beacon]\nstart = [45.0, 30.0]", "beacon.start", "[lat deg, lon deg, h m]"),
    ("[beacon]\nid = ''", "beacon.id", "[A-Za-z0-9_.-]"),
    ("[sonde]\nradar_loss_s = [300.0, 30.0]", "sonde.radar_loss_s", "start < end"),
    ("[sonde]\ngnss_outage_s = [1.0]", "sonde.gnss_outage_s", "[start s, end s]"),
    ("[sonde]\ngcpp_bearing_deg = 400", "sonde.gcpp_bearing_deg", "<= 360"),
    ("[ground_station]\nhold_wall_s = -0.1", "ground_station.hold_wall_s", ">= 0"),
    ("[uavs]\ncout = 3", "uavs.cout", "did you mean 'count'"),
    ("[uavz]\ncount = 3", "[uavz]", "did you mean 'uavs'"),
    ("run = 3", "run", "a table"),
    ("[run\nid = 'x'", "not valid TOML", "TOML"),
]


@pytest.mark.parametrize("text, key, expected", BAD, ids=[b[1] + ":" + b[0].split("\n")[-1][:20] for b in BAD])
def test_bad_key_is_one_line_naming_the_key(text, key, expected):
    with pytest.raises(ScenarioError) as exc:
        parse_scenario(text)
    msg = str(exc.value)
    assert "\n" not in msg
    assert msg.startswith("scenario: ")
    assert key in msg, msg
    assert expected in msg, msg


def test_default_scenario_is_the_documented_one():
    scn = default_scenario()
    assert scn.uavs.count == 3 and scn.sonde.enabled
    assert scn.uavs.pattern == "orbit" and scn.beacon.mode == "racetrack"  # a geometry that stays (issue 19)
    assert scn == parse_scenario(DEFAULT_SCENARIO_TOML, "<built-in default>")
    # everything optional: an empty file is the dataclass defaults, which are the default's
    assert parse_scenario("").to_dict() == scn.to_dict()


def test_round_trip_through_the_spec(tmp_path):
    scn = default_scenario().replace(run={"speed": 7.5, "seed": 11}, uavs={"count": 5, "per_process": 2})
    specs = worker_specs(scn, ["tcp/127.0.0.1:7447"], tmp_path)
    for s in specs:
        back = WorkerSpec.read(s.write(tmp_path / f"{s.name}.json"))
        assert back == s
        assert back.scenario_obj().to_dict() == scn.to_dict()
    assert [s.role for s in specs] == ["vehicles"] * 3 + ["ground_station"]
    assert sum(s.with_beacon_truth for s in specs) == 1 and sum(s.with_sonde for s in specs) == 1


def test_spec_with_unknown_keys_is_refused(tmp_path):
    p = tmp_path / "s.json"
    p.write_text(json.dumps({"spec_version": SPEC_VERSION, "name": "x", "surprise": 1}))
    with pytest.raises(ValueError, match="surprise"):
        WorkerSpec.read(p)


@settings(max_examples=60, deadline=None)
@given(count=st.integers(3, 400), per=st.integers(1, 120))
def test_worker_specs_partition_the_uavs(count, per):
    scn = Scenario().replace(uavs={"count": count, "per_process": per})
    groups = [s.uav_indices for s in worker_specs(scn, [], "out") if s.role == "vehicles"]
    assert len(groups) == math.ceil(count / per) == scn.n_uav_processes
    flat = [i for g in groups for i in g]
    assert flat == list(range(count))
    assert all(1 <= len(g) <= per for g in groups)


@settings(max_examples=30, deadline=None)
@given(n=st.integers(3, 50), radius=st.floats(100.0, 1e5), lat=st.floats(-60, 60), lon=st.floats(-179, 179))
def test_ring_start_points_lie_on_the_ring(n, radius, lat, lon):
    from sitl.geodesy import geodetic_to_ecef
    u = Scenario().uavs.__class__(count=n, center=(lat, lon), radius_m=radius, alt_m=0.0, alt_step_m=0.0)
    pts = u.start_points()
    assert len(pts) == n
    c = geodetic_to_ecef(math.radians(lat), math.radians(lon), 0.0)
    for p in pts:
        d = math.dist(geodetic_to_ecef(math.radians(p[0]), math.radians(p[1]), 0.0), c)
        assert d == pytest.approx(radius, rel=0.01)  # spherical offsets on the ellipsoid


def test_load_scenario_file_errors(tmp_path):
    with pytest.raises(ScenarioError, match="no such file"):
        load_scenario(tmp_path / "nope.toml")
    p = tmp_path / "s.toml"
    p.write_text("[run]\nspeed = 3.0\n")
    assert load_scenario(p).run.speed == 3.0
    assert scenario_from_dict({"run": {"speed": 2}}).run.speed == 2.0


@pytest.mark.slow
@pytest.mark.live
def test_cli_usage_error_exits_2_with_one_line(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text("[uavs]\ncount = 'many'\n")
    r = subprocess.run([sys.executable, "-m", "sitl.app", "run", str(p), "--out", str(tmp_path / "o")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "uavs.count" in lines[0] and "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, "-m", "sitl.app", "demo", "--zenoh", "nonsense", "--out",
                        str(tmp_path / "o")], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "--zenoh" in r.stderr and len(r.stderr.strip().splitlines()) == 1


# ------------------------------------------------------------------ [faults] (issue 8)

FAULTS_TOML = """
[faults]
"mav:1" = "loss=10% delay=100ms~20ms"
"mav:2:up" = "duplicate=5%"
"bus:*/uav/2/**" = "loss=20%"
"zenoh:gs" = "partition=100-130"
"zenoh:vehicles0" = "delay=50ms rate=1mbit"
"""

BAD_FAULTS = [
    ('"mav:x" = "loss=1%"', 'faults."mav:x"', "mav:SYSID"),
    ('"mav:1:sideways" = "loss=1%"', 'faults."mav:1:sideways"', "up|down"),
    ('"mav:9" = "loss=1%"', 'faults."mav:9"', "vehicle number in 1..4"),
    ('"zenoh:vehicles3" = "delay=1s"', 'faults."zenoh:vehicles3"', "zenoh:vehicles0, zenoh:gs"),
    ('"zenoh:foo" = "delay=1s"', 'faults."zenoh:foo"', "zenoh:gs"),
    ('"zenoh:gs" = "loss=1%"', 'faults."zenoh:gs"', "TCP stream"),
    ('"bus:a/**/*" = "loss=1%"', 'faults."bus:a/**/*"', "key expression"),
    ('"bus:*/uav/uav2/**" = "loss=1%"', 'faults."bus:*/uav/uav2/**"', "matches no key this run publishes"),
    ('"mav:1" = "loss=120%"', 'faults."mav:1"', "loss=120%"),
    ('"mav:1" = "delay=fast"', 'faults."mav:1"', "delay"),
    ('"mav:1" = 3', 'faults."mav:1"', "fault spec"),
    ('"tcp:1" = "loss=1%"', 'faults."tcp:1"', "mav:SYSID"),
    ('"mav:1" = "loss=1%"\n"mav:01" = "loss=2%"', 'faults."mav:01"', "twice"),
]


def test_faults_section_parsed_in_order_and_validated_with_the_netfault_parser():
    from sitl.netfault import parse_spec
    scn = parse_scenario(FAULTS_TOML)
    assert scn.faults.enabled and bool(scn.faults)
    assert [k for k, _ in scn.faults.links] == ["mav:1", "mav:2:up", "bus:*/uav/2/**", "zenoh:gs",
                                                "zenoh:vehicles0"]
    assert parse_spec(scn.faults.get("mav:1")) == parse_spec("delay=100ms~20ms loss=10%")
    assert parse_spec(scn.faults.get("zenoh:gs")).partitions == ((100.0, 130.0),)
    assert [k for k, _ in scn.faults.of_kind("zenoh")] == ["zenoh:gs", "zenoh:vehicles0"]
    # default: none, and no [faults] in the dict (a scenario without the table stays without it)
    assert not default_scenario().faults and "faults" not in default_scenario().to_dict()
    # an empty table is "faults on, none yet": the launcher starts the proxies
    empty = parse_scenario("[faults]\n")
    assert empty.faults.enabled and empty.faults.links == ()
    from sitl.scenario import to_toml_like
    assert scenario_from_dict(to_toml_like(empty.to_dict())).faults.enabled


@pytest.mark.parametrize("line, key, expected", BAD_FAULTS, ids=[b[0][:24] for b in BAD_FAULTS])
def test_bad_fault_entry_is_one_line_naming_the_key(line, key, expected):
    with pytest.raises(ScenarioError) as exc:
        parse_scenario("[faults]\n" + line)
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith("scenario: ")
    assert key in msg, msg
    assert expected in msg, msg


def test_faults_round_trip_through_the_worker_spec_json(tmp_path):
    scn = parse_scenario(FAULTS_TOML)
    over = {"vehicles0": {"zenoh_connect": ["tcp/127.0.0.1:1111"], "mavlink_gcs": "127.0.0.1:2222"},
            "gs": {"zenoh_connect": ["tcp/127.0.0.1:3333"]}}
    specs = worker_specs(scn, ["tcp/127.0.0.1:7447"], tmp_path, over)
    for s in specs:
        back = WorkerSpec.read(s.write(tmp_path / f"{s.name}.json"))
        obj = back.scenario_obj()
        assert obj.faults == scn.faults
        assert back.zenoh_connect == over[s.name]["zenoh_connect"]
        # only the vehicles talk MAVLink through the front; the GS keeps the real GCS
        assert obj.mavlink.gcs == ("127.0.0.1:2222" if s.name == "vehicles0" else scn.mavlink.gcs)
    assert scn.mavlink.gcs == "127.0.0.1:14550"  # the scenario object itself is untouched


_LINKS = st.one_of(st.builds(lambda i, d: f"mav:{i}{d}", st.integers(1, 4), st.sampled_from(["", ":up", ":down"])),
                   st.sampled_from(["zenoh:gs", "zenoh:vehicles0"]),
                   st.builds(lambda a, b: f"bus:{a}/{b}", st.sampled_from(["*", "demo"]),
                             st.sampled_from(["uav/**", "uav/2/**", "uav/*/nav", "sonde/**", "radar/**", "gs/**"])))
_SPECS = st.builds(lambda d, j, p: f"delay={d}ms~{j}ms partition={p}-{p + 5}", st.integers(0, 500),
                   st.integers(0, 50), st.integers(0, 100))


@settings(max_examples=25, deadline=None)
@given(entries=st.lists(st.tuples(_LINKS, _SPECS), max_size=6, unique_by=lambda e: e[0]))
def test_any_faults_table_survives_the_spec_json_in_order(tmp_path_factory, entries):
    """Whatever valid [faults] table: the worker sees the same entries in the same order
    (first matching bus rule wins, so the order is part of the meaning)."""
    import json as _json
    doc = {"faults": dict(entries)}
    scn = scenario_from_dict(doc)
    assert list(scn.faults.links) == entries
    d = tmp_path_factory.mktemp("spec")
    for s in worker_specs(scn, ["tcp/127.0.0.1:7447"], d):
        back = WorkerSpec.read(s.write(d / f"{s.name}.json")).scenario_obj()
        assert list(back.faults.links) == entries
        assert _json.loads((d / f"{s.name}.json").read_text())["scenario"]["faults"] == dict(entries)


def test_ground_station_link_keys_reach_the_components():
    """[ground_station] lag_window_s / stale_after_s / link_stats_every_s reach the GS node's
    locator, tracker and link monitor; out-of-range values are one-line errors."""
    from ground_station.node import GroundStationNode
    from sitl.app.components import gs_config

    scn = parse_scenario("[ground_station]\nlag_window_s = 2.5\nstale_after_s = 7.0\nlink_stats_every_s = 4.0\n")
    cfg = gs_config(scn)
    assert (cfg.lag_window_s, cfg.stale_after_s, cfg.link_stats_every_s) == (2.5, 7.0, 4.0)
    node = GroundStationNode(None, "r", cfg)
    try:
        assert node.locator.config.lag_window_s == 2.5 and node.tracker.params.lag_window_s == 2.5
        assert node.links.stale_after_s == 7.0
    finally:
        node.close()
    for text in ("lag_window_s = -1", "stale_after_s = 0", "link_stats_every_s = 'x'"):
        with pytest.raises(ScenarioError) as e:
            parse_scenario(f"[ground_station]\n{text}\n")
        assert "\n" not in str(e.value) and "ground_station." + text.split(" ")[0] in str(e.value)
