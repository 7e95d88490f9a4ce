"""A pymavlink peer (the GCS side) for the MAVLink endpoint tests, on loopback, bounded waits (no tests here)."""
from __future__ import annotations

import math
import select

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from vehicles.mavlink import VehicleEndpoint, VehicleTelemetry

T0_GPS_S = 1_400_000_000.0  # 2024-05-18: a fixed simulated epoch, far from the test's wall clock


def telemetry(**kw) -> VehicleTelemetry:
    base = dict(lat_rad=math.radians(45.1234567), lon_rad=math.radians(30.7654321), alt_msl_m=3012.345,
                vel_ned_m_s=(101.23, -4.56, 1.5), roll_rad=0.05, pitch_rad=-0.02, yaw_rad=math.radians(357.3),
                fix_type=3, satellites_visible=9, hdop=0.87, vdop=1.31, eph_m=2.345, epv_m=4.56, armed=True)
    base.update(kw)
    return VehicleTelemetry(**base)


class Peer:
    """The GCS: a pymavlink connection listening on an ephemeral loopback port."""

    def __init__(self, signing_key: bytes | None = None, sysid: int = 255, compid: int = 190):
        self.conn = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=sysid, source_component=compid)
        self.addr = self.conn.port.getsockname()
        self.datagrams = 0  # datagrams drained so far (a datagram may hold several frames)
        # MAVLink 2 parsing/encoding (mavutil switches to it on the first 0xFD byte of recv_msg;
        # we read the socket ourselves)
        self.mav = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        if signing_key is not None:
            s = self.mav.signing
            s.secret_key, s.sign_outgoing, s.link_id = signing_key, True, 1
            # a fixed timestamp (10 us since 2015) 100 s ahead of the endpoint's simulated clock
            s.timestamp = int((T0_GPS_S + 315964800 - 18 - 1420070400 + 100) * 1e5)

    def send_raw(self, data: bytes, to) -> None:
        self.conn.port.sendto(data, to)

    def pack(self, msg) -> bytes:
        buf = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        return buf

    def send(self, msg, to) -> bytes:
        buf = self.pack(msg)
        self.conn.port.sendto(buf, to)
        return buf

    def drain(self, wait_s: float = 0.0) -> list:
        """Every message waiting now (after at most wait_s for the first datagram)."""
        out = []
        r, _, _ = select.select([self.conn.port], [], [], wait_s)
        while r:
            try:
                data, _addr = self.conn.port.recvfrom(65535)
            except BlockingIOError:
                break
            self.datagrams += 1
            out += self.mav.parse_buffer(data) or []
            r, _, _ = select.select([self.conn.port], [], [], 0)
        return out

    def close(self) -> None:
        self.conn.close()


class Link:
    """An endpoint and its peer; ``exchange`` steps the endpoint in simulated time."""

    def __init__(self, kind="uav", signing_key=None, peer_key="same", tel=None, **ep_kw):
        self.peer = Peer(signing_key if peer_key == "same" else peer_key)
        self.ep = VehicleEndpoint(ep_kw.pop("sysid", 1), kind, gcs=self.peer.addr, listen=("127.0.0.1", 0),
                                  signing_key=signing_key, **ep_kw)
        self.k = 0  # steps taken; t = T0 + sum of dt (kept exact for dt = 0.1 by counting)
        self.t = T0_GPS_S
        self.tel = telemetry() if tel is None else tel

    @property
    def to(self):
        return self.ep.listen_addr

    def step(self, n: int = 1, dt: float = 0.1) -> list:
        """n endpoint steps of dt simulated seconds; returns what the peer received."""
        out = []
        for _ in range(n):
            self.ep.step(self.t, self.tel)
            self.k += 1
            self._dt_sum = getattr(self, "_dt_sum", 0) + round(dt * 1000)
            self.t = T0_GPS_S + self._dt_sum / 1000.0
            out += self.peer.drain(0.0)
        return out

    def exchange(self, msg, until, max_steps: int = 20) -> list:
        """Send msg (a message or raw bytes), step until until(received) is true (bounded)."""
        if isinstance(msg, (bytes, bytearray)):
            self.peer.send_raw(bytes(msg), self.to)
        elif msg is not None:
            self.peer.send(msg, self.to)
        got = []
        for _ in range(max_steps):
            select.select([self.ep.sock], [], [], 0.02)  # loopback delivery: bounded wait
            got += self.step(1)
            got += self.peer.drain(0.005)
            if until(got):
                return got
        return got

    def close(self) -> None:
        self.ep.close()
        self.peer.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def of_type(msgs, name: str) -> list:
    return [m for m in msgs if m.get_type() == name]
