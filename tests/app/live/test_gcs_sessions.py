"""Real ground-control clients fly the live demo (issue 21): a scripted headless MAVProxy session
against ``launch`` at x10, loopback only, every process stopped (MAVProxy and the workers).

MAVProxy (its own process, commands on stdin, what it received read back from its tlog with
pymavlink): connect, parameters by FTP ("Received N parameters (ftp)"), the list protocol for
comparison, a waypoint file with home at item 0, ``mode AUTO``, MISSION_CURRENT advancing and
MISSION_ITEM_REACHED for every item where the waypoints are, the end of the mission (RTL,
ArduPlane's rule), ``guided LAT LON ALT`` reached, ``rtl`` circling home.  pymavlink beside it
measures COMMAND_LONG -> COMMAND_ACK.  The figures (parameter download by FTP vs the list
protocol, the 4-item upload, the ACK latency; wall seconds at x10) are printed as one JSON line
(``-s``) and kept in ``OUT/figures.json``."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import threading
import time

import pytest
from tests.procs import LiveDemo, udp_base as _base_port

from sitl.scenario import default_scenario

pytestmark = [pytest.mark.live, pytest.mark.slow]

SPEED = 10.0


def Demo(tmp_path, gcs_port: int, duration_s: float = 4000.0, **uavs) -> LiveDemo:
    """The demo at x10 with 3 UAVs and no sonde, MAVLink to ``gcs_port``; ``.stop()`` ends it."""
    scn = default_scenario().replace(run={"speed": SPEED, "duration_s": duration_s, "rate_hz": 10.0},
                                     mavlink={"gcs": f"127.0.0.1:{gcs_port}", "base_port": _base_port(4)},
                                     uavs={"count": 3, **uavs}, sonde={"enabled": False})
    d = LiveDemo(scn, tmp_path / "demo")
    d.base = scn.mavlink.base_port
    return d


def _free_udp_port() -> int:
    import socket
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class MavProxy:
    """mavproxy.py as a GCS: commands on stdin, its printed lines collected with wall times."""

    def __init__(self, master: str, state_dir):
        try:
            import MAVProxy  # noqa: F401
        except ImportError:
            pytest.skip("MAVProxy is not installed (the test extras)")
        self.state_dir = state_dir
        self.p = subprocess.Popen(
            [sys.executable, "-u", "-m", "MAVProxy.mavproxy", f"--master={master}", "--source-system=255",
             "--target-system=1", "--nowait", "--default-modules=param,wp,mode,cmdlong,ftp,misc,rally,fence",
             f"--state-basedir={state_dir}"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
        self.lines: list[tuple[float, str]] = []
        self._t = threading.Thread(target=self._read, daemon=True)
        self._t.start()
        self.send("set flushlogs 1")  # the tlog is read back while MAVProxy runs

    def _read(self):
        for line in self.p.stdout:
            self.lines.append((time.monotonic(), line.rstrip()))

    def send(self, cmd: str) -> float:
        self.p.stdin.write(cmd + "\n")
        self.p.stdin.flush()
        return time.monotonic()

    def wait(self, text: str, timeout_s: float = 30.0, after: float = 0.0) -> tuple[float, str]:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            for t, line in list(self.lines):
                if t >= after and text in line:
                    return t, line
            if self.p.poll() is not None:
                break
            time.sleep(0.05)
        raise AssertionError(f"MAVProxy did not say {text!r} in {timeout_s} s; last lines: "
                             + " | ".join(line for _, line in self.lines[-15:]))

    def close(self):
        if self.p.poll() is None:
            try:  # end of input stops MAVProxy ("exit" does only with requireexit set)
                self.p.stdin.close()
            except (BrokenPipeError, OSError):
                pass
            try:
                self.p.wait(5)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait(5)
        self._t.join(2)
        assert self.p.poll() is not None, "MAVProxy did not stop"

    def tlog(self):
        from pymavlink import mavutil
        path = os.path.join(self.state_dir, "mav.tlog")
        m = mavutil.mavlink_connection(path)
        out = []
        while True:
            msg = m.recv_match()
            if msg is None:
                break
            out.append(msg)
        m.close()
        return out


def _dist_m(lat1, lon1, lat2, lon2) -> float:
    la1, lo1, la2, lo2 = (math.radians(v) for v in (lat1, lon1, lat2, lon2))
    h = math.sin(0.5 * (la2 - la1)) ** 2 + math.cos(la1) * math.cos(la2) * math.sin(0.5 * (lo2 - lo1)) ** 2
    return 2 * 6_371_000.0 * math.asin(math.sqrt(h))


def _after(msgs, kind: str, t_unix: float, src: int = 1) -> list:
    """The tlog's messages of a type from system src logged at or after t_unix (MAVProxy's clock)."""
    return [m for m in msgs if m.get_type() == kind and m.get_srcSystem() == src and m._timestamp >= t_unix]


def _near(msgs, t_unix: float):
    """The GLOBAL_POSITION_INT of UAV 1 logged nearest to t_unix."""
    pos = [m for m in msgs if m.get_type() == "GLOBAL_POSITION_INT" and m.get_srcSystem() == 1]
    return min(pos, key=lambda m: abs(m._timestamp - t_unix))


def _param_list_s(msgs, t_unix: float, n: int) -> float:
    """The list protocol's download time: the GCS's last PARAM_REQUEST_LIST after t_unix to the
    PARAM_VALUE that completes the n distinct indices (tlog stamps)."""
    req = [m for m in msgs if m.get_type() == "PARAM_REQUEST_LIST" and m.get_srcSystem() == 255
           and m._timestamp >= t_unix]
    t0 = req[0]._timestamp
    seen = set()
    for m in msgs:
        if m.get_type() == "PARAM_VALUE" and m.get_srcSystem() == 1 and m._timestamp >= t0:
            seen.add(m.param_index)
            if len(seen) >= n:
                return m._timestamp - t0
    raise AssertionError(f"the list protocol gave {len(seen)} of {n} parameters")


def _ftp_s(msgs) -> float:
    """The FTP parameter download's time: MAVProxy's first FILE_TRANSFER_PROTOCOL to the vehicle's
    last reply before the GCS's next request burst ends (the first download at connection)."""
    ftp = [m for m in msgs if m.get_type() == "FILE_TRANSFER_PROTOCOL"]
    t0 = next(m._timestamp for m in ftp if m.get_srcSystem() == 255)
    replies = [m._timestamp for m in ftp if m.get_srcSystem() == 1 and m._timestamp - t0 < 30.0]
    return max(replies) - t0


def _command_ack_latency_s(port: int, n: int = 12) -> list[float]:
    """pymavlink as a second GCS (system 254): COMMAND_LONG MAV_CMD_DO_SET_MODE to the mode the
    UAV is in (RTL: ArduPlane changes nothing) n times, wall time from send to its COMMAND_ACK."""
    from pymavlink import mavutil
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from vehicles.autopilot import convention as cv
    conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=254, source_component=190,
                                      dialect="ardupilotmega")
    out = []
    try:
        for _ in range(n):
            t0 = time.perf_counter()
            conn.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0,
                                       mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, cv.RTL, 0, 0, 0, 0, 0)
            end = t0 + 5.0
            while True:
                ack = conn.recv_match(type="COMMAND_ACK", blocking=True, timeout=max(end - time.perf_counter(), 0.01))
                if ack is None:
                    raise AssertionError("no COMMAND_ACK for MAV_CMD_DO_SET_MODE within 5 s")
                if ack.get_srcSystem() == 1 and ack.command == mavlink.MAV_CMD_DO_SET_MODE:
                    break
            out.append(time.perf_counter() - t0)
            assert ack.result == mavlink.MAV_RESULT_ACCEPTED, ack
            assert (ack.target_system, ack.target_component) == (254, 190), ack
            time.sleep(0.05)
    finally:
        conn.close()
    return out


def test_mavproxy_session_ftp_params_mission_guided_rtl(tmp_path):
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from vehicles.autopilot import AutopilotConfig
    from vehicles.autopilot import convention as cv
    cfg = AutopilotConfig()
    gcs_port = _free_udp_port()
    demo = Demo(tmp_path, gcs_port)
    # UAV 1's home: where the scenario starts it (in flight; ArduPlane's home is where it armed)
    home_lat, home_lon, home_alt = demo.scn.uavs.start_points()[0]
    mp = None
    figures = {"speed": SPEED}
    try:
        mp = MavProxy(f"udpout:127.0.0.1:{demo.base}", str(tmp_path / "mp"))
        mp.wait("Detected vehicle 1:1", 60)
        _, line = mp.wait("parameters (ftp)", 30)
        n_params = int(line.split("Received ")[1].split()[0])
        assert n_params >= 20
        # the list protocol, for comparison
        mp.send("set param_ftp 0")
        t_unix = time.time()
        t0 = mp.send("param fetch")
        mp.wait(f"Received {n_params} parameters", 60, after=t0)
        mp.send("set param_ftp 1")
        msgs = mp.tlog()
        figures["params"] = n_params
        figures["param_ftp_s"] = _ftp_s(msgs)
        figures["param_list_s"] = _param_list_s(msgs, t_unix, n_params)

        # a mission with home at item 0 (MAVProxy's, ignored: home stays the UAV's) and three
        # waypoints ~3.2 km apart, 1500 m above home, north-east of where UAV 1 is
        time.sleep(1.0)
        gp = [m for m in mp.tlog() if m.get_type() == "GLOBAL_POSITION_INT" and m.get_srcSystem() == 1][-1]
        lat, lon = gp.lat * 1e-7, gp.lon * 1e-7
        wps = [(lat + 0.027 * k, lon + 0.01 * k) for k in (1, 2, 3)]
        wpfile = tmp_path / "mission.txt"
        rows = ["QGC WPL 110", f"0\t1\t0\t16\t0\t0\t0\t0\t{lat:.7f}\t{lon:.7f}\t0\t1"]
        rows += [f"{k}\t0\t3\t16\t0\t0\t0\t0\t{a:.7f}\t{o:.7f}\t1500\t1" for k, (a, o) in enumerate(wps, 1)]
        wpfile.write_text("\n".join(rows) + "\n")
        t = mp.send("mode LOITER")
        mp.wait("LOITER>", 20, after=t)
        t_unix = time.time()
        t = mp.send(f"wp load {wpfile}")
        mp.wait("Sent all 4 waypoints", 30, after=t)
        mp.wait("MISSION_ACK: TYPE_MISSION: ACCEPTED", 30, after=t)
        msgs = mp.tlog()
        count = _after(msgs, "MISSION_COUNT", t_unix, src=255)[0]
        ack = _after(msgs, "MISSION_ACK", t_unix)[0]
        assert count.count == 4 and ack.type == mavlink.MAV_MISSION_ACCEPTED
        figures["mission_upload_4_items_s"] = ack._timestamp - count._timestamp
        # the download: item 0 is the UAV's home (where the scenario started it), not the file's
        # home row; items 1..3 as uploaded
        t_unix = time.time()
        t = mp.send("wp list")
        mp.wait("Saved 4 waypoints", 30, after=t)
        msgs = mp.tlog()
        got = {m.seq: m for m in _after(msgs, "MISSION_ITEM_INT", t_unix)}
        assert sorted(got) == [0, 1, 2, 3], sorted(got)
        h = got[0]
        assert _dist_m(h.x * 1e-7, h.y * 1e-7, home_lat, home_lon) < 0.05 and abs(h.z - home_alt) < 0.01, h
        for k, (a, o) in enumerate(wps, 1):
            m = got[k]
            assert (m.command, m.frame, m.z) == (mavlink.MAV_CMD_NAV_WAYPOINT, 3, 1500.0), m
            # pymavlink's mavwp (MAVProxy's `wp load`) truncates, int(lat * 1e7): up to one degE7
            # below, and a float product a hair under the integer may lose one more ulp
            assert abs(m.x - a * 1e7) < 1 + 1e-6 and abs(m.y - o * 1e7) < 1 + 1e-6, m
        # not flown outside AUTO: still circling in LOITER
        assert _after(msgs, "MISSION_ITEM_REACHED", t_unix) == []

        # AUTO: MISSION_CURRENT 1 -> 2 -> 3, MISSION_ITEM_REACHED 1, 2, 3 where the waypoints are,
        # then the declared end of a mission: RTL (ArduPlane, vehicles.autopilot.convention)
        t_auto = time.time()
        t = mp.send("mode AUTO")
        mp.wait("AUTO>", 20, after=t)
        for k in (1, 2, 3):
            mp.wait(f"Reached waypoint #{k}", 120, after=t)
        mp.wait("Mission complete, changing mode to RTL", 30, after=t)
        mp.wait("RTL>", 20, after=t)
        time.sleep(1.0)  # MAVProxy's tlog catches up
        msgs = mp.tlog()
        reached = _after(msgs, "MISSION_ITEM_REACHED", t_auto)
        assert [m.seq for m in reached] == [1, 2, 3], [m.seq for m in reached]
        for m, (a, o) in zip(reached, wps):
            p = _near(msgs, m._timestamp)
            # WP_RADIUS, plus a 4 Hz position sample's travel at cruise and the onboard estimate's error
            d = _dist_m(p.lat * 1e-7, p.lon * 1e-7, a, o)
            assert d < cfg.wp_radius_m + 0.25 * cfg.airspeed_cruise_m_s + 50.0, (m.seq, d)
        cur = [m for m in _after(msgs, "MISSION_CURRENT", t_auto)]
        seqs = [m.seq for m in cur]
        assert {1, 2, 3} <= set(seqs) and seqs == sorted(seqs), seqs
        assert all(m.total == 3 for m in cur)
        assert cur[-1].mission_state == mavlink.MISSION_STATE_COMPLETE, cur[-1]
        modes = [m.custom_mode for m in _after(msgs, "HEARTBEAT", t_auto)]
        assert cv.AUTO in modes and modes[-1] == cv.RTL, modes

        # guided to a point 5 km east of home, reached (then circled at WP_LOITER_RAD)
        g_lat, g_lon = home_lat, home_lon + 0.064
        t = mp.send(f"guided {g_lat:.7f} {g_lon:.7f} 1200")
        mp.wait("GUIDED>", 20, after=t)
        t_unix = time.time()
        mp.wait("Reached destination", 120, after=t)
        time.sleep(3.0)
        pos = _after(mp.tlog(), "GLOBAL_POSITION_INT", t_unix)
        best = min(_dist_m(m.lat * 1e-7, m.lon * 1e-7, g_lat, g_lon) for m in pos)
        assert best < cfg.wp_loiter_rad_m + 300.0, best

        # rtl: back home, circling it at RTL_RADIUS (0: WP_LOITER_RAD)
        t = mp.send("rtl")
        mp.wait("RTL>", 20, after=t)
        mp.wait("Reached RTL location", 120, after=t)
        # it enters the circle heading for home and cuts inside it (the bank limit's turn radius
        # ~1 km at cruise): one circle to settle, then more than one circle on it
        circle_wall_s = 2 * math.pi * cfg.rtl_radius_eff_m / cfg.airspeed_cruise_m_s / SPEED
        time.sleep(circle_wall_s)
        t_unix = time.time()
        time.sleep(1.2 * circle_wall_s)
        pos = _after(mp.tlog(), "GLOBAL_POSITION_INT", t_unix)
        d = [_dist_m(m.lat * 1e-7, m.lon * 1e-7, home_lat, home_lon) for m in pos]
        assert len(d) >= 20 and abs(max(d) - cfg.rtl_radius_eff_m) < 300.0 \
            and abs(min(d) - cfg.rtl_radius_eff_m) < 300.0, (len(d), min(d, default=None), max(d, default=None))

        # mode changes by MAVProxy (SET_MODE / DO_SET_MODE): wall time to MAVProxy's new prompt
        lat_wall = []
        for mode in ("LOITER", "RTL"):
            t = mp.send(f"mode {mode}")
            t_ack, _ = mp.wait(f"{mode}>", 20, after=t)
            lat_wall.append(round(t_ack - t, 3))
        figures["mode_change_prompt_wall_s"] = lat_wall
        # COMMAND_LONG -> COMMAND_ACK by pymavlink beside MAVProxy (one vehicle epoch: 0.1 s
        # simulated = 10 ms wall at x10, plus the loopback and the worker's step)
        lat_s = sorted(_command_ack_latency_s(demo.base))
        figures["command_ack_wall_ms"] = {"n": len(lat_s), "median": round(1e3 * lat_s[len(lat_s) // 2], 1),
                                          "max": round(1e3 * lat_s[-1], 1)}
        msgs = mp.tlog()
        hb_modes = {m.custom_mode for m in msgs if m.get_type() == "HEARTBEAT" and m.get_srcSystem() == 1}
        assert {cv.AUTO, cv.GUIDED, cv.RTL, cv.LOITER} <= hb_modes, hb_modes
    finally:
        if mp is not None:
            mp.close()
        demo.stop()
    (tmp_path / "figures.json").write_text(json.dumps(figures))
    print(json.dumps({"mavproxy_session": figures}))
