"""vehicles.mavlink.tcp (TcpServer, StreamFramer) and a VehicleEndpoint's TCP server (ArduPilot
SITL's SERIAL0) against pymavlink over loopback: two clients, disconnect, frames split across
reads, requests answered on the connection, streams to every connected client, ports freed."""
from __future__ import annotations

import select
import socket
import time

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mav

from sitl.mavlink.framing import Frame
from tests.mavlink_peer import T0_GPS_S, Peer, telemetry
from tests.procs import tcp_free
from vehicles.mavlink import EndpointGroup, ParamStore, VehicleEndpoint
from vehicles.mavlink.params import ParamSpec
from vehicles.mavlink.tcp import StreamFramer, TcpServer

pytestmark = pytest.mark.live


def _poll_until(srv, cond, n=50):
    got = []
    for _ in range(n):
        time.sleep(0.02)
        got += srv.poll()
        if cond(got):
            break
    return got


def test_two_clients_heartbeat_and_disconnect():
    with TcpServer(port=0) as srv:
        a = socket.create_connection(srv.addr, timeout=2)
        b = socket.create_connection(srv.addr, timeout=2)
        _poll_until(srv, lambda g: len(srv.clients) == 2)
        assert srv.counters["accepted"] == 2
        m = mav.MAVLink(None, srcSystem=1, srcComponent=1)
        srv.write(m.heartbeat_encode(mav.MAV_TYPE_FIXED_WING, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4).pack(m))
        for s in (a, b):
            peer = mav.MAVLink(None)
            msgs = peer.parse_buffer(s.recv(4096))
            assert [x.get_type() for x in msgs] == ["HEARTBEAT"]
        g = mav.MAVLink(None, srcSystem=255, srcComponent=190)
        a.sendall(g.heartbeat_encode(6, 8, 0, 0, 0).pack(g))
        got = _poll_until(srv, lambda g: g)
        assert [x.get_type() for x in mav.MAVLink(None).parse_buffer(got[0][1])] == ["HEARTBEAT"]
        a.close()
        _poll_until(srv, lambda g: len(srv.clients) == 1)
        assert len(srv.clients) == 1 and srv.counters["closed"] == 1
        srv.write(b"\xfd")  # the remaining client still served
        assert b.recv(10) == b"\xfd"
        b.close()
    assert srv.sock.fileno() == -1


def test_port_in_use_raises_at_bind():
    with TcpServer(port=0) as srv:
        with pytest.raises(OSError):
            TcpServer(port=srv.addr[1])


def test_framer_reassembles_frames_cut_anywhere_and_counts_garbage():
    m = mav.MAVLink(None, srcSystem=255, srcComponent=190)
    frames = [m.heartbeat_encode(6, 8, 0, 0, 0).pack(m),
              m.param_request_read_encode(1, 1, b"WP_RADIUS", -1).pack(m),
              m.command_long_encode(1, 1, 512, 0, 148, 0, 0, 0, 0, 0, 0).pack(m)]
    stream = b"\x00\x01junk" + b"".join(frames)
    for cut in range(1, len(stream)):  # every split point of one stream over two reads
        f = StreamFramer()
        items = f.feed(stream[:cut]) + f.feed(stream[cut:])
        got = [x for x in items if isinstance(x, Frame)]
        assert [bytes(x.buf) for x in got] == frames, cut
        assert [x for x in items if isinstance(x, str)] == ["garbage"]
        assert f.buf == b""
    decoded = [mav.MAVLink(None).decode(bytearray(fr)) for fr in frames]
    assert [d.get_type() for d in decoded] == ["HEARTBEAT", "PARAM_REQUEST_READ", "COMMAND_LONG"]


def _endpoint(**kw):
    params = ParamStore([ParamSpec("WP_RADIUS", 90.0, min=1.0, max=1000.0, doc="waypoint radius, m")])
    peer = Peer()
    ep = VehicleEndpoint(1, "uav", gcs=peer.addr, listen=("127.0.0.1", 0), tcp_listen=("127.0.0.1", 0),
                         params=params, **kw)
    return ep, peer


def _recv_tcp(conn, until, ep, steps=40, t=None):
    got, k = [], 0
    for k in range(steps):
        ep.step(T0_GPS_S + 0.1 * (k + (t or 0)), telemetry())
        r, _, _ = select.select([conn.port], [], [], 0.02)
        if r:
            m = conn.recv_msg()
            while m is not None:
                got.append(m)
                m = conn.recv_msg()
        if until(got):
            break
    return got


def test_endpoint_tcp_client_gets_streams_and_replies_on_its_connection():
    ep, peer = _endpoint()
    try:
        port = ep.tcp_addr[1]
        conn = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=255, source_component=190)
        got = _recv_tcp(conn, lambda g: any(m.get_type() == "HEARTBEAT" for m in g), ep)
        hb = [m for m in got if m.get_type() == "HEARTBEAT"]
        assert hb and hb[0].get_srcSystem() == 1 and hb[0].type == mav.MAV_TYPE_FIXED_WING
        # a request over TCP: answered over TCP, not sent to the UDP GCS
        peer.drain(0.05)
        conn.mav.param_request_read_send(1, 1, b"WP_RADIUS", -1)
        got = _recv_tcp(conn, lambda g: any(m.get_type() == "PARAM_VALUE" for m in g), ep, t=50)
        pv = [m for m in got if m.get_type() == "PARAM_VALUE"]
        assert pv and pv[0].param_id == "WP_RADIUS" and pv[0].param_value == pytest.approx(90.0)
        assert not [m for m in peer.drain(0.05) if m.get_type() == "PARAM_VALUE"]
        # a second client sees the streams too; the first closes and is let go
        conn2 = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=254, source_component=190)
        got2 = _recv_tcp(conn2, lambda g: any(m.get_type() == "HEARTBEAT" for m in g), ep, t=100)
        assert any(m.get_type() == "HEARTBEAT" for m in got2)
        conn.close()
        for k in range(20):
            ep.step(T0_GPS_S + 20 + 0.1 * k, telemetry())
            if len(ep.tcp.clients) == 1:
                break
            time.sleep(0.02)
        assert len(ep.tcp.clients) == 1 and ep.tcp.counters["closed"] >= 1
        conn2.close()
    finally:
        ep.close()
        peer.close()
    assert tcp_free(port)  # the port is free at once after close


def test_group_serves_tcp_listeners_and_port_taken_is_one_line():
    peer = Peer()
    eps = [VehicleEndpoint(i + 1, "uav", gcs=peer.addr, listen=("127.0.0.1", 0), tcp_listen=("127.0.0.1", 0))
           for i in range(3)]
    g = EndpointGroup(eps)
    try:
        port = eps[2].tcp_addr[1]
        with pytest.raises(ValueError, match=f"sysid 9: cannot listen on tcp 127.0.0.1:{port}"):
            VehicleEndpoint(9, "uav", gcs=peer.addr, listen=("127.0.0.1", 0), tcp_listen=("127.0.0.1", port))
        conn = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=255, source_component=190)
        seen = set()
        for k in range(40):
            g.step(T0_GPS_S + 0.1 * k, [telemetry()] * 3)
            if select.select([conn.port], [], [], 0.02)[0]:
                m = conn.recv_msg()
                while m is not None:
                    seen.add((m.get_type(), m.get_srcSystem()))
                    m = conn.recv_msg()
            if ("HEARTBEAT", 3) in seen:
                break
        assert ("HEARTBEAT", 3) in seen and not {s for t, s in seen} - {3}  # only vehicle 3's own link
        conn.close()
    finally:
        g.close()
        peer.close()
    assert all(tcp_free(ep.tcp_addr[1]) for ep in eps)
