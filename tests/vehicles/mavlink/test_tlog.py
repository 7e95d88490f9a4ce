"""The .tlog files as MAVProxy writes them: each record stamped with the WALL clock (us since the
Unix epoch) while the simulated time stays inside the messages; one new file per run per link
(created, never appended to; a restart inside a run gets its own .r<k> file; a re-used output
directory loses the previous run's tlogs). Read back with pymavlink (mavutil.mavlink_connection)
and MAVProxy's mavlogdump, the tools the files are for."""
from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import pytest
from pymavlink import mavutil
from tests.mavlink_peer import Peer
from tests.procs import udp_base

from sitl.bus import InMemoryTransport
from sitl.mavlink.framing import TlogWriter, fresh_tlog_path
from sitl.scenario import default_scenario
from vehicles.process import VehicleGroup, _mav_telemetry, build_endpoints

SIM_UNIX_S = 1_735_689_600.0  # 2025-01-01T00:00:00Z, the default scenario's day


def _read(path):
    log = mavutil.mavlink_connection(str(path))
    msgs = []
    while (m := log.recv_match()) is not None:
        msgs.append(m)
    log.close()
    return msgs


def test_fresh_path_never_reuses_a_file(tmp_path):
    p = tmp_path / "mav_x.tlog"
    assert fresh_tlog_path(p) == str(p)
    p.write_bytes(b"")
    assert fresh_tlog_path(p) == str(tmp_path / "mav_x.r1.tlog")
    (tmp_path / "mav_x.r1.tlog").write_bytes(b"")
    assert fresh_tlog_path(p) == str(tmp_path / "mav_x.r2.tlog")


def test_writer_stamps_with_its_clock_and_truncates(tmp_path):
    from pymavlink.dialects.v20 import ardupilotmega as mav

    enc = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    path = tmp_path / "a.tlog"
    path.write_bytes(b"junk from an older run")
    t0 = time.time()
    with TlogWriter(path, stamp_clock=time.time) as w:
        for k in range(3):
            w.write(SIM_UNIX_S + k, enc.system_time_encode(int((SIM_UNIX_S + k) * 1e6), k * 1000).pack(enc))
    msgs = _read(path)
    assert [m.get_type() for m in msgs] == ["SYSTEM_TIME"] * 3  # the junk is gone: a new file
    assert all(t0 - 1 <= m._timestamp <= time.time() + 1 for m in msgs)  # wall clock
    assert [m.time_unix_usec for m in msgs] == [int((SIM_UNIX_S + k) * 1e6) for k in range(3)]  # simulated inside
    with pytest.raises(ValueError, match="stamp_clock"):
        TlogWriter(tmp_path / "b.tlog", stamp_clock=5.0)


def test_the_vehicle_workers_tlog_is_wall_clock_stamped_and_a_restart_gets_its_own_file(tmp_path):
    peer = Peer()
    base = udp_base(2)
    scn = default_scenario().replace(sonde={"enabled": False}, uavs={"count": 2, "start": "in-flight"},
                                     mavlink={"gcs": f"127.0.0.1:{peer.addr[1]}", "base_port": base, "tlog": True})
    dt = 1.0 / scn.run.rate_hz
    paths = []
    for start in range(2):  # a worker and its restart, in the same output directory
        g = VehicleGroup(scn, [0, 1], InMemoryTransport(), np.random.SeedSequence(7), with_sonde=False)
        eg = build_endpoints(g, scn, tmp_path, "vehicles0", clock=time.time)  # the live worker's clock
        t_wall0 = time.time()
        try:
            for k in range(30):
                t = scn.run.t0_gps_s + k * dt
                g.step(t)
                eg.step(t, _mav_telemetry(g.telemetry(), len(eg)))
                peer.drain(0.0)
        finally:
            eg.close()
            eg.tlog_writer.close()
        paths.append(eg.tlog_writer.path)
        msgs = _read(eg.tlog_writer.path)
        assert len(msgs) > 20 and {m.get_srcSystem() for m in msgs} >= {1, 2}
        assert all(t_wall0 - 1 <= m._timestamp <= time.time() + 1 for m in msgs), start
        st = [m for m in msgs if m.get_type() == "SYSTEM_TIME"]
        assert st and all(abs(m.time_unix_usec / 1e6 - SIM_UNIX_S) < 86400 for m in st)  # simulated: 2025-01-01
    assert [os.path.basename(p) for p in paths] == ["mav_vehicles0.tlog", "mav_vehicles0.r1.tlog"]
    peer.close()
    import pymavlink
    tool = os.path.join(os.path.dirname(pymavlink.__file__), "tools", "mavlogdump.py")
    out = subprocess.run([sys.executable, tool, "--types", "SYSTEM_TIME", paths[0]], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0 and out.stdout.count("SYSTEM_TIME") == len(
        [m for m in _read(paths[0]) if m.get_type() == "SYSTEM_TIME"])
    # mavlogdump prints the record stamps as local wall-clock dates of today, not 2025-01-01
    assert time.strftime("%Y-%m-%d") in out.stdout or time.strftime("%Y-%m-%d", time.gmtime()) in out.stdout


def test_the_ground_stations_tlog_is_new_per_start_and_wall_clock_stamped(tmp_path):
    from ground_station.mavlink_link import GcsLink

    peer = Peer()
    path = tmp_path / "mav_gs.tlog"
    t_wall0 = time.time()
    for _ in range(2):
        gs = GcsLink(f"127.0.0.1:{peer.addr[1]}", str(path))
        try:
            gs.tick(SIM_UNIX_S)  # simulated time: the heartbeat falls due
            gs.heartbeat()
        finally:
            gs.close()
    first, second = _read(path), _read(tmp_path / "mav_gs.r1.tlog")
    assert [m.get_type() for m in first] == [m.get_type() for m in second] and first  # not appended
    assert all(m.get_type() == "HEARTBEAT" for m in first)
    assert all(t_wall0 - 1 <= m._timestamp <= time.time() + 1 for m in first + second)
    peer.close()


def test_a_reused_output_directory_loses_the_previous_runs_tlogs(tmp_path):
    from sitl.app.launcher import clear_previous_tlogs

    for name in ("mav_vehicles0.tlog", "mav_vehicles0.r1.tlog", "mav_gs.tlog"):
        (tmp_path / name).write_bytes(b"old")
    (tmp_path / "mav_signing_1.json").write_text("{}")  # signing state: kept (replay protection)
    (tmp_path / "bus.log").write_bytes(b"x")
    gone = clear_previous_tlogs(tmp_path)
    assert sorted(p.name for p in gone) == ["mav_gs.tlog", "mav_vehicles0.r1.tlog", "mav_vehicles0.tlog"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bus.log", "mav_signing_1.json"]
