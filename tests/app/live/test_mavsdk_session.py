"""A MAVSDK session flies the live demo (issue 21): MAVSDK's native binding (``pip install mavsdk``,
v4: the MAVSDK C++ core through ctypes) as the ground station against ``launch`` at x10, three UAVs
started on the ground, loopback only, every process and thread stopped.

The session: discover every vehicle, get_all_params, upload a mission (item 0 a placeholder for
home: ArduPilot's rule, which MAVSDK's Mission plugin does not apply itself), arm, start_mission,
progress reaches n/n and is_mission_finished is true, action.return_to_launch.  What MAVSDK reports is then
compared with the simulation: its flight modes with the HEARTBEATs the vehicles sent (the run's
tlog), its in-air state and positions with the run's truth (the bus log), its GPS info with the
satellites above the receivers' mask at the true position (pymap3d's look angles), its parameters
with the PARAM_VALUEs the vehicles sent."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest
from tests.procs import LiveDemo, udp_base as _base_port

from sitl.scenario import default_scenario

pytestmark = [pytest.mark.live, pytest.mark.slow]

mavsdk = pytest.importorskip("mavsdk", reason="mavsdk (MAVSDK's Python binding, the test extras) is not installed")
if not hasattr(mavsdk, "Mavsdk"):  # mavsdk < 4: the gRPC wrapper, another API
    pytest.skip(f"mavsdk {getattr(mavsdk, '__version__', '?')} is the gRPC wrapper (< 4); this session uses the "
                "native binding (mavsdk >= 4)", allow_module_level=True)

from mavsdk import ComponentType, Configuration, ConnectionResult, Mavsdk  # noqa: E402
from mavsdk.plugins.action import Action  # noqa: E402
from mavsdk.plugins.mission import Mission  # noqa: E402
from mavsdk.plugins.mission.mission import MissionItem, MissionPlan  # noqa: E402
from mavsdk.plugins.param import Param  # noqa: E402
from mavsdk.plugins.telemetry import Telemetry  # noqa: E402
from mavsdk.plugins.telemetry.telemetry import FixType, FlightMode  # noqa: E402

SPEED = 10.0
N_UAV = 3


def _free_udp_port() -> int:
    import socket
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def Demo(tmp_path, gcs_port: int) -> LiveDemo:
    """The demo at x10 with N_UAV UAVs on the ground, no sonde, 10 Hz epochs; ``.stop()`` ends it."""
    scn = default_scenario().replace(run={"speed": SPEED, "duration_s": 4000.0, "rate_hz": 10.0},
                                     mavlink={"gcs": f"127.0.0.1:{gcs_port}", "base_port": _base_port(N_UAV + 1)},
                                     uavs={"count": N_UAV, "start": "ground"}, sonde={"enabled": False})
    d = LiveDemo(scn, tmp_path / "demo")
    d.base = scn.mavlink.base_port
    return d


def _wait(pred, timeout_s: float, what: str, poll_s: float = 0.1):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        v = pred()
        if v:
            return v
        time.sleep(poll_s)
    raise AssertionError(f"{what}: not within {timeout_s} s")


def _tlog(path):
    from pymavlink import mavutil
    m = mavutil.mavlink_connection(str(path))
    out = []
    while True:
        msg = m.recv_match()
        if msg is None:
            break
        out.append(msg)
    m.close()
    return out


def _truth(bus_log, run_id: str, n: int) -> dict:
    """{sysid: (t_gps_s (K,), pos_ecef_m (K, 3))} of the UAVs' truth in the bus log."""
    from sitl.bus import decode, read_bus_log_records
    rows = {s: [] for s in range(1, n + 1)}
    for rec in read_bus_log_records(bus_log):
        if "/truth/uav/" not in rec.key:
            continue
        m = decode(rec.payload)
        s = int(rec.key.rsplit("/", 1)[1])
        if s in rows:
            rows[s].append((m.t_gps_s, *np.asarray(m.pos_ecef_m, float)))
    out = {}
    for s, r in rows.items():
        a = np.array(sorted(set(r)))
        out[s] = (a[:, 0], a[:, 1:4])
    return out


def _truth_at(truth, sysid: int, t_gps_s: float) -> np.ndarray:
    t, p = truth[sysid]
    return np.array([np.interp(t_gps_s, t, p[:, k]) for k in range(3)])


#: MAVSDK's flight mode of each ArduPlane custom mode the session passes through
_MODE_OF = {0: FlightMode.MANUAL, 10: FlightMode.MISSION, 11: FlightMode.RETURN_TO_LAUNCH,
            13: FlightMode.TAKEOFF}


def test_mavsdk_session_discover_params_mission_rtl_and_telemetry_matches_the_simulation(tmp_path):
    import pymap3d

    from sitl.gnss.orbits import gps_constellation, sat_state_ecef
    from vehicles.mavlink.telemetry import gps_from_unix_s

    gcs = _free_udp_port()
    demo = Demo(tmp_path, gcs)
    sdk = None
    progress: dict = {}
    samples = {s: [] for s in range(1, N_UAV + 1)}  # (sysid: [(wall, flight mode, in_air, Position, GpsInfo)])
    try:
        sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        assert sdk.add_any_connection(f"udpin://127.0.0.1:{gcs}") == ConnectionResult.SUCCESS

        # -- discover every vehicle (the ground station, system 250, is no autopilot)
        def autopilots():
            sy = {s.get_system_id(): s for s in sdk.get_systems() if s.has_autopilot() and s.is_connected()}
            return sy if set(sy) >= set(range(1, N_UAV + 1)) else None
        systems = _wait(autopilots, 30, "MAVSDK discovers the three UAVs")
        assert set(systems) == set(range(1, N_UAV + 1))
        tel = {s: Telemetry(systems[s]) for s in systems}
        act = {s: Action(systems[s]) for s in systems}
        mis = {s: Mission(systems[s]) for s in systems}

        def sample(s):
            t = tel[s]
            samples[s].append((time.monotonic(), t.flight_mode(), t.in_air(), t.position(), t.gps_info()))

        # -- every parameter of every vehicle
        params = {}
        for s in systems:
            ap = Param(systems[s]).get_all_params()
            params[s] = {p.name: p.value for p in ap.float_params} | {p.name: p.value for p in ap.int_params}
            assert "SYSID_THISMAV" in params[s] and params[s]["SYSID_THISMAV"] == s
            assert "WP_RADIUS" in params[s] and "BATT_CAPACITY" in params[s]

        # -- on the ground: MANUAL, not in the air, a 3D fix
        _wait(lambda: all(tel[s].flight_mode() == FlightMode.MANUAL for s in systems), 10, "MANUAL on the ground")
        _wait(lambda: all(tel[s].gps_info().fix_type != FixType.NO_GPS for s in systems), 10, "the first GPS_RAW_INT")
        for s in systems:
            assert not tel[s].in_air() and not tel[s].armed()
            sample(s)

        # -- a mission per UAV: three waypoints 150 m above home, 1.1 km apart to the north. MAVSDK's
        # Mission plugin sends the items as they are (seq 0 = the first; its convert_to_int_items
        # adds no home), and ArduPilot -- the convention the vehicles follow -- takes item 0 as home,
        # so item 0 is a placeholder for home, as MAVSDK's users of ArduPilot write it
        for s in systems:
            p = tel[s].position()
            items = [MissionItem(latitude_deg=p.latitude_deg, longitude_deg=p.longitude_deg, relative_altitude_m=0.0,
                                 is_fly_through=True)]
            items += [MissionItem(latitude_deg=p.latitude_deg + 0.01 * k, longitude_deg=p.longitude_deg,
                                  relative_altitude_m=150.0, is_fly_through=True, acceptance_radius_m=200.0)
                      for k in (1, 2, 3)]
            mis[s].upload_mission(MissionPlan(items))
        for s in systems:
            act[s].arm()
        _wait(lambda: all(tel[s].armed() for s in systems), 10, "armed")
        for s in systems:
            mis[s].start_mission()
        progress.update({s: [] for s in systems})

        def finished():
            for s in systems:
                pr = mis[s].mission_progress()
                if not progress[s] or progress[s][-1] != (pr.current, pr.total):
                    progress[s].append((pr.current, pr.total))
                sample(s)
            return all(mis[s].is_mission_finished() for s in systems)
        _wait(finished, 120, "every mission finished", poll_s=0.25)
        for s in systems:
            cur = [c for c, _ in progress[s]]
            assert progress[s][-1] == (4, 4), progress[s]
            assert cur == sorted(cur), progress[s]  # progress only goes forward

        # -- return to launch
        for s in systems:
            act[s].return_to_launch()
        _wait(lambda: all(tel[s].flight_mode() == FlightMode.RETURN_TO_LAUNCH for s in systems), 10, "RTL")
        for _ in range(10):
            for s in systems:
                sample(s)
            time.sleep(0.2)
    finally:
        if sdk is not None:
            sdk.destroy()
        demo.stop()

    # -- what MAVSDK said against the simulation (the run's tlog and truth)
    msgs = _tlog(demo.out / "mav_vehicles0.tlog")
    truth = _truth(demo.out / "bus.log", demo.scn.run.id, N_UAV)
    ground = demo.scn.uavs.ground_alt_m
    const = gps_constellation()
    mask_deg = 10.0
    for s in range(1, N_UAV + 1):
        mine = [m for m in msgs if m.get_srcSystem() == s]
        # the mission: all four items requested in the upload, each waypoint reached, in order
        assert sorted({m.seq for m in mine if m.get_type() == "MISSION_REQUEST_INT"}) == [0, 1, 2, 3]
        assert [m.seq for m in mine if m.get_type() == "MISSION_ITEM_REACHED"] == [1, 2, 3]
        # parameters: exactly those the vehicle announced
        sent = {m.param_id for m in mine if m.get_type() == "PARAM_VALUE"}
        assert set(params[s]) == sent
        # flight modes: each one MAVSDK showed is one the HEARTBEATs carried
        hb_modes = {m.custom_mode for m in mine if m.get_type() == "HEARTBEAT"}
        assert {0, 10, 11} <= hb_modes
        seen = {fm for _, fm, _, _, _ in samples[s]}
        assert {FlightMode.MANUAL, FlightMode.MISSION, FlightMode.RETURN_TO_LAUNCH} <= seen
        assert seen <= {_MODE_OF[c] for c in hb_modes if c in _MODE_OF}, (seen, hb_modes)
        # positions: each MAVSDK sample is a GLOBAL_POSITION_INT the vehicle sent (to the degE7 and
        # the mm), and that one is within 30 m (~10 sigma of the onboard filter) of the truth then
        gpi = [m for m in mine if m.get_type() == "GLOBAL_POSITION_INT"]
        # the simulated time of a message: its time_boot_ms on the vehicle's boot clock, which
        # SYSTEM_TIME ties to simulated Unix time (the tlog's own stamps are the wall clock's, as
        # MAVProxy writes them)
        st = [m for m in mine if m.get_type() == "SYSTEM_TIME"]
        offsets = np.array([m.time_unix_usec * 1e-6 - m.time_boot_ms * 1e-3 for m in st])
        assert st and np.ptp(offsets) < 2e-3, "SYSTEM_TIME's boot clock drifts from its Unix time"
        boot_to_unix_s = float(np.median(offsets))
        lat = np.array([m.lat for m in gpi]) * 1e-7
        lon = np.array([m.lon for m in gpi]) * 1e-7
        checked_air = checked_ground = 0
        for _, fm, in_air, pos, gps in samples[s]:
            k = int(np.argmin(np.abs(lat - pos.latitude_deg) + np.abs(lon - pos.longitude_deg)))
            m = gpi[k]
            assert abs(m.lat * 1e-7 - pos.latitude_deg) < 1e-9 and abs(m.lon * 1e-7 - pos.longitude_deg) < 1e-9
            assert pos.absolute_altitude_m == pytest.approx(m.alt * 1e-3, abs=1e-3)
            assert pos.relative_altitude_m == pytest.approx(m.relative_alt * 1e-3, abs=1e-3)
            t = gps_from_unix_s(m.time_boot_ms * 1e-3 + boot_to_unix_s)
            tx, ty, tz = _truth_at(truth, s, t)
            tla, tlo, th = pymap3d.ecef2geodetic(tx, ty, tz)
            n, e, d = pymap3d.geodetic2ned(pos.latitude_deg, pos.longitude_deg, pos.absolute_altitude_m, tla, tlo, th)
            assert math.hypot(n, e) < 30.0 and abs(d) < 30.0, (s, n, e, d)
            # in the air: MAVSDK's flag (EXTENDED_SYS_STATE) against the truth's height above the ground
            if th > ground + 30.0:
                assert in_air
                checked_air += 1
            elif th < ground + 1.0 and fm == FlightMode.MANUAL:
                assert not in_air
                checked_ground += 1
            # GPS info: a 3D fix, the satellites above the mask at the true position (+-1: one
            # may cross the mask between the receiver's epoch and this one)
            sp, _ = sat_state_ecef(const, t)
            _az, el, _r = pymap3d.ecef2aer(sp[:, 0], sp[:, 1], sp[:, 2], tla, tlo, th)
            assert gps.fix_type == FixType.FIX_3D
            assert abs(gps.num_satellites - int((el >= mask_deg).sum())) <= 1
        assert checked_air >= 3 and checked_ground >= 1, (checked_air, checked_ground)
