"""A live run beyond one MAVLink network's system ids (issue 22): 260 UAVs and the sonde in two
MAVLink blocks (sitl.mavlink.blocks), loopback only, every process stopped.

A GCS on block 2's port hears exactly block 2's vehicles -- system ids 1..12, each from the port
the convention gives it (base + 1 + 10 (s - 1)), the sonde (the run's last vehicle) as system 12
with its balloon type -- and the ground station (system 250: HEARTBEAT, ADSB_VEHICLE of its
estimates); a GCS on block 1's port hears block 1's 249 and the ground station, and nothing
from a block-2 port.  Then MAVProxy (the test extras) connects to block 2's port and detects a
vehicle; its tlog holds block 2's systems only.

Block 1's traffic (~249 x 15 messages/s) is read with a header-only parse of each frame
(MAVLink 2: system id byte 5, message id bytes 7-9), not pymavlink, to keep the test's own CPU
small on a loaded 2-core machine; block 2's is parsed with pymavlink."""
from __future__ import annotations

import socket
import threading
import time

import pytest
from tests.procs import LiveDemo, udp_free

from sitl.mavlink.blocks import MavlinkPlan
from sitl.scenario import default_scenario

pytestmark = [pytest.mark.live, pytest.mark.slow]

N_UAV = 260
HEARTBEAT, ADSB_VEHICLE = 0, 246


def _frames(data: bytes):
    """(sysid, msgid) of each MAVLink 2 frame of a datagram (header only; a frame of another
    kind ends the walk)."""
    i = 0
    while i + 12 <= len(data) and data[i] == 0xFD:
        n, flags = data[i + 1], data[i + 2]
        yield data[i + 5], int.from_bytes(data[i + 7:i + 10], "little")
        i += 12 + n + (13 if flags & 1 else 0)


class RawGcs(threading.Thread):
    """A UDP socket on a block's GCS port: HEARTBEAT / ADSB_VEHICLE senders by (port, sysid)."""

    def __init__(self, port: int):
        super().__init__(daemon=True)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", port))
        self.sock.settimeout(0.2)
        self.heartbeats: dict[tuple[int, int], int] = {}  # (source port, sysid) -> count
        self.adsb_from: set = set()
        self.datagrams = 0
        self.stop = threading.Event()

    def run(self):
        while not self.stop.is_set():
            try:
                data, (_, sport) = self.sock.recvfrom(65535)
            except TimeoutError:
                continue
            except OSError:
                return
            self.datagrams += 1
            for sysid, msgid in _frames(data):
                if msgid == HEARTBEAT:
                    self.heartbeats[(sport, sysid)] = self.heartbeats.get((sport, sysid), 0) + 1
                elif msgid == ADSB_VEHICLE:
                    self.adsb_from.add(sysid)

    def close(self):
        self.stop.set()
        self.join(2.0)
        self.sock.close()


class PymavlinkGcs(threading.Thread):
    """A UDP socket on a block's GCS port parsed by pymavlink: HEARTBEAT type per sysid and the
    source ports it came from, ADSB callsigns from the ground station."""

    def __init__(self, port: int, key: bytes | None = None):
        from pymavlink.dialects.v20 import common as m
        super().__init__(daemon=True)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", port))
        self.sock.settimeout(0.2)
        self.mav = m.MAVLink(None)
        if key is not None:  # verify: only validly signed frames parse, their link id kept
            self.mav.signing.secret_key = key
            self.mav.signing.allow_unsigned_callback = lambda mav, msgid: False
        self.link_ids: dict[int, set] = {}
        self.types: dict[int, int] = {}
        self.ports: dict[int, set] = {}
        self.adsb: dict[str, int] = {}
        self.stop = threading.Event()

    def run(self):
        while not self.stop.is_set():
            try:
                data, (_, sport) = self.sock.recvfrom(65535)
            except TimeoutError:
                continue
            except OSError:
                return
            try:
                msgs = self.mav.parse_buffer(data) or []
            except Exception:  # a frame refused (bad signature): not counted as heard
                continue
            for msg in msgs:
                if getattr(msg, "_signed", False):
                    self.link_ids.setdefault(msg.get_srcSystem(), set()).add(msg._link_id)
                if msg.get_type() == "HEARTBEAT":
                    s = msg.get_srcSystem()
                    self.types[s] = msg.type
                    self.ports.setdefault(s, set()).add(sport)
                elif msg.get_type() == "ADSB_VEHICLE" and msg.get_srcSystem() == 250:
                    self.adsb[msg.callsign] = self.adsb.get(msg.callsign, 0) + 1

    def close(self):
        self.stop.set()
        self.join(2.0)
        self.sock.close()


def _ports(n_vehicles: int):
    """A vehicle base port and a GCS port whose plans' ports are all free (this worker's window)."""
    from tests.procs import worker_index
    first = 20000 + 6000 * worker_index()
    for base in range(first, first + 3000, 97):
        plan = MavlinkPlan(n_vehicles=n_vehicles, base_port=base, gcs_port=base + 2600)
        if all(udp_free(plan.listen_port(i)) for i in range(n_vehicles)) and all(
                udp_free(p) for _, p in plan.gcs_addrs()):
            return plan
    raise RuntimeError("no free UDP port range")


def test_260_uavs_in_two_mavlink_blocks_each_gcs_sees_its_own(tmp_path):
    from pymavlink.dialects.v20 import common as m
    from tests.app.live.test_gcs_sessions import MavProxy

    plan = _ports(N_UAV + 1)
    assert plan.n_blocks == 2
    (_, g1), (_, g2) = plan.gcs_addrs()
    scn = default_scenario().replace(
        run={"speed": 1.0, "duration_s": 600.0, "rate_hz": 2.0},
        bus={"log": False},
        mavlink={"gcs": f"127.0.0.1:{g1}", "base_port": plan.base_port, "tcp": False, "tlog": False,
                 "rate_hz": 2.0},
        uavs={"count": N_UAV, "radius_m": 150.0 * N_UAV})
    assert MavlinkPlan.of(scn) == plan
    block1, block2 = RawGcs(g1), PymavlinkGcs(g2)
    block1.start()
    block2.start()
    demo = None
    mp = None
    try:
        demo = LiveDemo(scn, tmp_path / "run")
        want2 = set(range(1, 13)) | {250}
        end = time.monotonic() + 120.0
        while time.monotonic() < end:  # every block-2 system heard, and an estimate as ADSB
            if want2 <= set(block2.types) and block2.adsb and len({s for _, s in block1.heartbeats}) >= 250:
                break
            time.sleep(0.5)
        block2.close()
        block1.close()
        # block 2: its 12 vehicles (11 UAVs, the sonde last) and the ground station, nothing else
        assert set(block2.types) == want2, sorted(block2.types)
        for s in range(1, 13):
            assert block2.ports[s] == {plan.listen_port(plan.index_of(2, s))} == {plan.base_port + 1 + 10 * (s - 1)}
        assert all(block2.types[s] == m.MAV_TYPE_FIXED_WING for s in range(1, 12))
        assert block2.types[12] == m.MAV_TYPE_FREE_BALLOON and block2.types[250] == m.MAV_TYPE_GCS
        assert block2.adsb, "no ADSB_VEHICLE from the ground station on block 2"
        # block 1: its 249 vehicles from block-1 ports, the ground station, no block-2 port
        vehicle_ports = {p for p, s in block1.heartbeats if s != 250}
        seen = {plan.vehicle_at_port(p) for p in vehicle_ports}
        assert seen == set(range(249)), f"{len(seen)} block-1 vehicles, extra: {sorted(seen - set(range(249)))[:5]}"
        assert all(plan.sysid_of(plan.vehicle_at_port(p)) == s for p, s in block1.heartbeats if s != 250)
        assert 250 in {s for _, s in block1.heartbeats} and 250 in block1.adsb_from
        assert not any(plan.block_of(i) == 2 for i in seen if i is not None)

        # MAVProxy on block 2's port: it detects the block's vehicle 1, and its tlog holds block 2 only
        mp = MavProxy(f"udpin:127.0.0.1:{g2}", str(tmp_path / "mp"))
        mp.wait("Detected vehicle 1:1", timeout_s=60.0)
        mp.wait("Detected vehicle 12:1", timeout_s=30.0)
        time.sleep(3.0)
        mp.close()
        msgs = mp.tlog()
        mp = None
        beat = {x.get_srcSystem() for x in msgs if x.get_type() == "HEARTBEAT"} - {255}  # MAVProxy's own
        assert beat <= want2 and {1, 12, 250} <= beat, sorted(beat)
        assert any(x.get_type() == "ADSB_VEHICLE" and x.get_srcSystem() == 250 for x in msgs)
    finally:
        if mp is not None:
            mp.close()
        block1.close()
        block2.close()
        if demo is not None:
            demo.stop()
    for i in range(N_UAV + 1):
        assert udp_free(plan.listen_port(i)), f"port {plan.listen_port(i)} still bound"


def test_small_blocks_signed_and_through_the_fault_proxies(tmp_path):
    """block_size 2: 4 UAVs and the sonde in 3 blocks, signed, with the launcher's fault proxies
    (every block's vehicles through the one front, each proxy to its own block's GCS) and the
    sonde's uplink (vehicle 5 = block 3, system id 1) cut: blocks 1 and 2 hear their two UAVs,
    each block's frames signed on link id block - 1, the ground station on all three, block 3
    nothing of the sonde; the signing states are one file per (block, system id)."""
    from pymavlink.dialects.v20 import common as m

    from sitl.scenario import scenario_from_dict, to_toml_like
    key = bytes(range(32))
    (tmp_path / "key").write_bytes(key)
    plan = None
    from tests.procs import worker_index
    for base in range(20000 + 6000 * worker_index() + 3100, 20000 + 6000 * worker_index() + 5900, 97):
        plan = MavlinkPlan(n_vehicles=5, base_port=base, gcs_port=base + 500, block_size=2)
        if all(udp_free(plan.listen_port(i)) for i in range(5)) and all(udp_free(p) for _, p in plan.gcs_addrs()):
            break
    d = to_toml_like(default_scenario().to_dict())
    d["run"].update(speed=2.0, duration_s=600.0)
    d["bus"]["log"] = False
    d["uavs"]["count"] = 4
    d["mavlink"].update(gcs=f"127.0.0.1:{plan.gcs_port}", base_port=plan.base_port, block_size=2, tcp=False,
                        tlog=False, signing_key_file=str(tmp_path / "key"))
    d["faults"] = {"mav:5:up": "loss=100%"}
    scn = scenario_from_dict(d, "test")
    assert MavlinkPlan.of(scn) == plan and plan.n_blocks == 3
    rx = [PymavlinkGcs(p, key) for _, p in plan.gcs_addrs()]
    for r in rx:
        r.start()
    demo = None
    try:
        demo = LiveDemo(scn, tmp_path / "run")
        end = time.monotonic() + 60.0
        while time.monotonic() < end and not ({1, 2, 250} <= set(rx[0].types) and {1, 2, 250} <= set(rx[1].types)
                                              and 250 in rx[2].types):
            time.sleep(0.5)
        time.sleep(3.0)  # the sonde has had its chances to be heard on block 3
    finally:
        for r in rx:
            r.close()
        if demo is not None:
            demo.stop()
    assert set(rx[0].types) == {1, 2, 250} and set(rx[1].types) == {1, 2, 250}, (rx[0].types, rx[1].types)
    assert set(rx[2].types) == {250}, rx[2].types  # the sonde's uplink is cut
    assert rx[0].types[1] == rx[1].types[2] == m.MAV_TYPE_FIXED_WING
    for k, r in enumerate(rx):
        assert all(ids == {k} for ids in r.link_ids.values()), (k, r.link_ids)
    names = {p.name for p in (tmp_path / "run").glob("mav_signing_*.json")}
    assert {"mav_signing_1.json", "mav_signing_2.json", "mav_signing_b2_1.json", "mav_signing_b2_2.json",
            "mav_signing_b3_1.json", "mav_signing_250.json", "mav_signing_b2_250.json",
            "mav_signing_b3_250.json"} <= names, sorted(names)
    assert demo.report is not None and demo.report.get("faults")
