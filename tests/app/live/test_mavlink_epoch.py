"""The vehicles' MAVLink side runs at its own epoch ([mavlink] rate_hz, 10 Hz) while the world
steps at run.rate_hz (1 Hz, the demo's), and each vehicle serves TCP like ArduPilot SITL's
SERIAL0: live, against ``launch`` at x1, with pymavlink and MAVProxy as the peers, loopback
only, every process stopped and every port freed.

Time is read from the vehicles' own messages (time_boot_ms: simulated time), never from the
wall clock: a reply comes within one MAVLink epoch when at most two 10 Hz ATTITUDE messages
arrive between the request and its answer (at 1 Hz world epochs a reply waited up to ten).
The wall-clock figures (ACK latency, mission upload time) are printed (``-s``) for the record."""
from __future__ import annotations

import math
import socket
import statistics
import threading
import time

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mav
from tests.procs import tcp_free, udp_base, udp_free

from sitl.scenario import default_scenario

pytestmark = [pytest.mark.live, pytest.mark.slow]

ATTITUDE, GPI = 30, 33


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Demo:
    """``launch`` of the demo scenario (run.rate_hz 1, x1; 3 UAVs, no sonde) in a thread."""

    def __init__(self, tmp_path, **mavlink):
        from sitl.app.launcher import launch
        self.base = udp_base(4)
        while not all(tcp_free(self.base + 10 * i) for i in range(4)):
            self.base += 1
        self.scn = default_scenario().replace(
            run={"duration_s": 600.0}, uavs={"count": 3}, sonde={"enabled": False},
            mavlink={"gcs": f"127.0.0.1:{_free_udp_port()}", "base_port": self.base, **mavlink})
        assert self.scn.run.rate_hz == 1.0 and self.scn.mavlink.rate_hz == 10.0
        self.out = tmp_path / "demo"
        self.out.mkdir()
        self.started, self.stop_ev, self.report = threading.Event(), threading.Event(), None

        def run():
            self.report = launch(self.scn, self.out, quiet=True, stop=self.stop_ev,
                                 on_started=lambda sup: self.started.set())
        self.thread = threading.Thread(target=run, daemon=True)
        self.thread.start()
        if not self.started.wait(240):
            self.stop()
            pytest.fail("the demo did not start within 240 s")

    def stop(self):
        self.stop_ev.set()
        self.thread.join(60)
        assert not self.thread.is_alive(), "the demo did not stop"


class Gcs:
    """A pymavlink GCS talking to vehicle 1 on its UDP port; every message kept in order."""

    def __init__(self, port: int):
        self.c = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
        self.log: list = []

    def recv(self, until, timeout_s: float = 10.0):
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            m = self.c.recv_match(blocking=True, timeout=0.2)
            if m is None or m.get_srcSystem() != 1:
                continue
            self.log.append(m)
            if until(m):
                return m
        raise AssertionError(f"no answer in {timeout_s} s; last: {[x.get_type() for x in self.log[-10:]]}")

    def drain(self):
        """Take in what has arrived (so that what is counted next came after this)."""
        while True:
            m = self.c.recv_match(blocking=False)
            if m is None:
                return
            if m.get_srcSystem() == 1:
                self.log.append(m)

    def set_interval(self, msgid: int, hz: float):
        self.c.mav.command_long_send(1, 1, mav.MAV_CMD_SET_MESSAGE_INTERVAL, 0, msgid, 1e6 / hz, 0, 0, 0, 0, 0)
        self.recv(lambda m: m.get_type() == "COMMAND_ACK" and m.command == mav.MAV_CMD_SET_MESSAGE_INTERVAL)

    def close(self):
        self.c.close()


def _between(log, i0: int, name: str) -> int:
    return sum(1 for m in log[i0:] if m.get_type() == name)


def test_replies_within_one_mavlink_epoch_and_streams_at_10_hz_over_1_hz_world_epochs(tmp_path):
    demo = Demo(tmp_path)
    g = Gcs(demo.base)
    figures = {}
    try:
        g.c.mav.heartbeat_send(6, 8, 0, 0, 0)
        g.recv(lambda m: m.get_type() == "HEARTBEAT")
        g.set_interval(ATTITUDE, 10.0)
        g.set_interval(GPI, 10.0)
        # 1. COMMAND_LONG -> COMMAND_ACK, 25 times at scattered phases
        between, lat_ms = [], []
        for k in range(25):
            time.sleep(0.037 * (k % 7))
            g.drain()
            i0 = len(g.log)
            t0 = time.monotonic()
            g.c.mav.command_long_send(1, 1, mav.MAV_CMD_REQUEST_MESSAGE, 0, mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
                                      0, 0, 0, 0, 0, 0)
            g.recv(lambda m: m.get_type() == "COMMAND_ACK" and m.command == mav.MAV_CMD_REQUEST_MESSAGE)
            lat_ms.append(1e3 * (time.monotonic() - t0))
            between.append(_between(g.log, i0, "ATTITUDE"))
        figures["ack_latency_wall_ms_median"] = statistics.median(lat_ms)
        figures["attitude_between_request_and_ack_max"] = max(between)
        assert max(between) <= 2, between  # answered within one 0.1 s epoch of simulated time
        # 2. a 4-item mission (home at item 0 + 3 waypoints): every request answered at once
        gpi = g.recv(lambda m: m.get_type() == "GLOBAL_POSITION_INT")
        g.drain()
        i0, t0 = len(g.log), time.monotonic()
        g.c.mav.mission_count_send(1, 1, 4, 0)
        while True:
            m = g.recv(lambda m: m.get_type() in ("MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"))
            if m.get_type() == "MISSION_ACK":
                break
            s = m.seq
            g.c.mav.mission_item_int_send(1, 1, s, 0 if s == 0 else 3, 16, 0, 1, 0, 0, 0, 0,
                                          gpi.lat + 270000 * s, gpi.lon + 100000 * s, 1500, 0)
        figures["mission4_upload_wall_s"] = time.monotonic() - t0
        assert m.type == mav.MAV_MISSION_ACCEPTED
        att = [x.time_boot_ms for x in g.log[i0:] if x.get_type() == "ATTITUDE"]
        figures["mission4_upload_sim_s"] = (att[-1] - att[0]) * 1e-3 if len(att) > 1 else 0.0
        assert len(att) <= 6, att  # 4 requests + the ACK, each within one epoch (at 1 Hz: >= 4 s, 40 of them)
        # 3. the streams at 10 Hz of simulated time; positions between world epochs carried along
        i0 = len(g.log)
        g.recv(lambda m: False if m.get_type() != "ATTITUDE" else len(
            [x for x in g.log[i0:] if x.get_type() == "ATTITUDE"]) >= 51, timeout_s=30)
        att = [x.time_boot_ms for x in g.log[i0:] if x.get_type() == "ATTITUDE"]
        dt_ms = [b - a for a, b in zip(att, att[1:])]
        figures["attitude_interval_ms_median"] = statistics.median(dt_ms)
        assert statistics.median(dt_ms) == pytest.approx(100, abs=1), dt_ms
        assert 50 / ((att[-1] - att[0]) * 1e-3) == pytest.approx(10.0, rel=0.05)
        pos = [x for x in g.log[i0:] if x.get_type() == "GLOBAL_POSITION_INT"]
        assert len(pos) >= 45 and len({(p.lat, p.lon) for p in pos}) == len(pos)  # every one moved: no hold
        # each step's displacement against the reported velocity x dt: within ~0 m inside a world
        # epoch; at each world epoch the new onboard estimate (an independent fix) lands within
        # the EKF's noise of where the propagation had carried it (a hold would leave v x 1 s ~ 100 m)
        dev = []
        for a, b in zip(pos, pos[1:]):
            dt = (b.time_boot_ms - a.time_boot_ms) * 1e-3
            dn = math.radians((b.lat - a.lat) * 1e-7) * 6378137.0
            de = math.radians((b.lon - a.lon) * 1e-7) * 6378137.0 * math.cos(math.radians(a.lat * 1e-7))
            vn, ve = 0.5 * (a.vx + b.vx) / 100, 0.5 * (a.vy + b.vy) / 100
            dev.append(math.hypot(dn - vn * dt, de - ve * dt))
        speed = math.hypot(pos[0].vx, pos[0].vy) / 100
        figures["gpi_step_dev_m"] = {"median": statistics.median(dev), "max": max(dev), "speed_m_s": speed}
        assert speed > 50
        assert statistics.median(dev) < 1.0 and max(dev) < 0.25 * speed, dev
    finally:
        g.close()
        demo.stop()
    print("MAVLink epoch figures:", figures)
    assert demo.report["ok"], demo.report.get("error")
    assert all(udp_free(demo.base + 10 * i) and tcp_free(demo.base + 10 * i) for i in range(3))


def test_mavproxy_over_tcp_serial0_detects_the_vehicle_and_gets_its_parameters(tmp_path):
    from tests.app.live.test_gcs_sessions import MavProxy
    demo = Demo(tmp_path)
    mp = None
    try:
        mp = MavProxy(f"tcp:127.0.0.1:{demo.base}", str(tmp_path / "mp"))  # vehicle 1's SERIAL0
        mp.wait("Detected vehicle 1:1", 60)
        _, line = mp.wait("parameters (ftp)", 60)
        n = int(line.split("Received ")[1].split()[0])
        assert n >= 20
        t = mp.send("param show WP_RADIUS")
        _, line = mp.wait("WP_RADIUS", 20, after=t)
        assert float(line.split()[-1]) > 0
    finally:
        if mp is not None:
            mp.close()
        demo.stop()
    assert demo.report["ok"], demo.report.get("error")
    assert all(tcp_free(demo.base + 10 * i) for i in range(3))  # closed cleanly: the ports are free
