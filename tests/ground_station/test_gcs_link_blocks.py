"""The ground station on several MAVLink blocks (sitl.mavlink.blocks): GcsLink given one GCS
address per block sends every message to each, as its own MAVLink stream (sequence numbers
from 0 on each), signed on the block's link id with the block's own persisted state; a
pymavlink receiver with the key verifies each block's frames."""
from __future__ import annotations

import json
import select
import socket
from types import SimpleNamespace

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as m

from ground_station.mavlink_link import GS_SYSID, GcsLink

pytestmark = pytest.mark.live  # loopback sockets

KEY = bytes(range(32))


class Receiver:
    def __init__(self):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.mav = m.MAVLink(None)
        self.mav.signing.secret_key = KEY
        self.raw: list[bytes] = []

    @property
    def gcs(self) -> str:
        return "127.0.0.1:%d" % self.sock.getsockname()[1]

    def drain(self, n: int, wait_s: float = 2.0) -> list:
        out = []
        while len(self.raw) < n:
            r, _, _ = select.select([self.sock], [], [], wait_s)
            if not r:
                break
            d = self.sock.recv(65535)
            self.raw.append(d)
            out += self.mav.parse_buffer(d) or []
        return out

    def close(self):
        self.sock.close()


def test_every_block_gets_every_message_on_its_own_stream_and_link_id(tmp_path):
    rx = [Receiver() for _ in range(3)]
    states = [tmp_path / f"s{k}.json" for k in range(3)]
    g = GcsLink([r.gcs for r in rx], signing_key=KEY, clock=lambda: 1_780_000_000.0, link_id=[0, 1, 2],
                signing_state=[str(p) for p in states])
    try:
        g.tick(100.0)  # HEARTBEAT
        g.adsb("beacon", "b1", SimpleNamespace(pos_ecef_m=np.array([4.0e6, 3.0e6, 3.5e6]),
                                               vel_ecef_m_s=np.array([10.0, -5.0, 2.0])))
        g.statustext("link uav2: stale")
        for k, r in enumerate(rx):
            got = r.drain(3)
            assert [x.get_type() for x in got] == ["HEARTBEAT", "ADSB_VEHICLE", "STATUSTEXT"]
            assert all(x.get_srcSystem() == GS_SYSID and x._signed for x in got)
            assert [x.get_seq() for x in got] == [0, 1, 2]  # the block's own sequence
            assert r.mav.signing.goodsig_count == 3 and r.mav.signing.badsig_count == 0
            assert {b[10 + b[1] + 2] for b in r.raw} == {k}  # the signature's link id byte
            assert got[1].callsign == "BEAb1"
        assert g.sent["HEARTBEAT"] == 1 and g.sent["ADSB_VEHICLE"] == 1  # messages, once
        assert g.status()["block_frames"] == [3, 3, 3]
    finally:
        g.close()
        for r in rx:
            r.close()
    for p in states:  # each block's signing state of its own
        assert json.loads(p.read_text())["sysid"] == GS_SYSID


def test_one_address_is_one_block_and_mismatched_lists_are_refused():
    r = Receiver()
    try:
        g = GcsLink(r.gcs)
        assert "block_frames" not in g.status()
        g.close()
        with pytest.raises(ValueError, match="one per block"):
            GcsLink([r.gcs, r.gcs], link_id=[0, 1, 2])
        with pytest.raises(ValueError, match="HOST:PORT"):
            GcsLink(["127.0.0.1:x"])
        with pytest.raises(ValueError, match="at least one"):
            GcsLink([])
    finally:
        r.close()
