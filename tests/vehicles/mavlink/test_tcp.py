"""vehicles.mavlink.tcp.TcpServer: connect, two clients, disconnect, pymavlink framing over it (loopback)."""
from __future__ import annotations

import select
import socket

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from vehicles.mavlink.tcp import TcpServer

pytestmark = pytest.mark.live


def _poll_until(srv, cond, n=50):
    got = []
    for _ in range(n):
        select.select([srv.sock, *srv.clients], [], [], 0.02)
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
