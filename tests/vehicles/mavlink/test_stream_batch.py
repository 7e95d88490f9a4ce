"""The batched stream framing (vehicles/mavlink/endpoint/batch.py) against pymavlink, the
reference: every stream message type, random field values (many zero, to exercise MAVLink 2's
trailing-zero truncation), random sequence numbers and ids -- the frames must be pymavlink's
bytes exactly; a group stepped with batching must deliver the same messages, in the same order
with the same sequence numbers, in fewer datagrams, and write the same tlog."""
import numpy as np
import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from tests.mavlink_peer import Peer
from vehicles.mavlink import TlogWriter
from vehicles.mavlink.endpoint import EndpointGroup, VehicleEndpoint
from vehicles.mavlink.endpoint import batch as bt
from vehicles.mavlink.telemetry import VehicleTelemetry

STREAM_MESSAGES = ("heartbeat", "sys_status", "system_time", "gps_raw_int", "attitude", "global_position_int",
                   "vfr_hud", "extended_sys_state", "battery_status", "home_position", "nav_controller_output",
                   "ekf_status_report", "autopilot_version")
_INT = {"uint8_t": (0, 255), "int8_t": (-128, 127), "uint16_t": (0, 65535), "int16_t": (-32768, 32767),
        "uint32_t": (0, 2**32 - 1), "int32_t": (-2**31, 2**31 - 1), "uint64_t": (0, 2**63 - 1), "int64_t": (-2**62, 2**62)}


def _value(rng, t):
    if rng.random() < 0.35:
        return 0.0 if t in ("float", "double") else 0
    if t in ("float", "double"):
        return float(np.float32(rng.normal(0, 1e3))) if t == "float" else float(rng.normal(0, 1e6))
    lo, hi = _INT[t]
    return int(rng.integers(lo, hi, endpoint=True))


def random_args(rng, cls, zero=False):
    args = []
    for t, n in zip(cls.fieldtypes, [cls.array_lengths[cls.ordered_fieldnames.index(f)] for f in cls.fieldnames]):
        if zero:
            args.append([0] * n if n and t != "char" else (b"" if t == "char" else 0))
        elif t == "char":
            args.append(bytes(rng.integers(65, 90, n or 1).astype(np.uint8)))
        elif n:
            args.append([_value(rng, t) for _ in range(n)])
        else:
            args.append(_value(rng, t))
    return args


def _pymavlink_frame(name, args, seq, sysid, compid):
    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    mav.seq = seq
    return getattr(mav, f"{name}_encode")(*args).pack(mav)


@pytest.mark.parametrize("name", STREAM_MESSAGES)
def test_frames_are_pymavlinks_bytes(name):
    rng = np.random.default_rng(sum(map(ord, name)))
    cls = bt._message_class(name)
    rows = [random_args(rng, cls) for _ in range(60)] + [random_args(rng, cls, zero=True)]
    seq = rng.integers(0, 256, len(rows))
    sysid = rng.integers(1, 256, len(rows))
    compid = rng.integers(0, 256, len(rows))
    got = bt.frames(cls, [bt.payload(cls, a) for a in rows], seq, sysid, compid)
    want = [_pymavlink_frame(name, a, int(s), int(i), int(c)) for a, s, i, c in zip(rows, seq, sysid, compid)]
    assert got == want
    assert len(want[-1]) == 12 + 1  # an all-zero payload keeps one byte


def test_default_arguments_are_filled_in_as_pymavlinks_encode_does():
    assert bt.encode_args("heartbeat", (1, 0, 132, 0, 4)) == (1, 0, 132, 0, 4, 3)
    full = bt.encode_args("gps_raw_int", tuple(range(10)), {"h_acc": 7})
    assert full == (*range(10), 0, 7, 0, 0, 0, 0)
    with pytest.raises(TypeError, match="expected 2 arguments, got 1"):
        bt.encode_args("system_time", (1,))


def test_datagrams_hold_whole_frames_in_order_up_to_the_limit():
    rng = np.random.default_rng(3)
    fl = [bytes(rng.integers(0, 255, int(n)).astype(np.uint8)) for n in rng.integers(12, 280, 40)]
    dgs = bt.pack_datagrams(fl, 600)
    assert b"".join(d for d, _ in dgs) == b"".join(fl)
    assert sum(n for _, n in dgs) == len(fl)
    assert all(len(d) <= 600 or n == 1 for d, n in dgs)
    big = bt.pack_datagrams([b"x" * 700, b"y" * 10], 600)
    assert big == [(b"x" * 700, 1), (b"y" * 10, 1)]


def _telemetry(i, k):
    return VehicleTelemetry(np.radians(45 + 1e-3 * i), np.radians(30 + 1e-4 * k), 3000.0 + i, (100.0, 5.0 * i, -1.0),
                            satellites_visible=9, hdop=0.9, eph_m=2.0, yaw_rad=0.1 * k)


def _run_group(tmp_path, batch, n=6, steps=25):
    peer = Peer()
    path = tmp_path / f"g{int(batch)}.tlog"
    msgs = []
    try:
        with TlogWriter(path) as w:
            eps = [VehicleEndpoint(i + 1, "uav", gcs=peer.addr, listen=("127.0.0.1", 0), tlog=w) for i in range(n)]
            with EndpointGroup(eps, batch_streams=batch) as g:
                for k in range(steps):
                    g.step(1_400_000_000.0 + 0.1 * k, [_telemetry(i, k) for i in range(n)])
                    msgs += peer.drain(0.05)  # each step's, so no socket buffer overflows
                counters = g.counters
        msgs += peer.drain(0.1)
        datagrams = peer.datagrams
    finally:
        peer.close()
    log = mavutil.mavlink_connection(str(path))
    tlog = []
    while (m := log.recv_match()) is not None:
        tlog.append(m.get_msgbuf())
    log.close()
    return msgs, datagrams, counters, tlog


def test_a_batched_group_sends_what_the_per_frame_path_sends_in_fewer_datagrams(tmp_path):
    m0, d0, c0, t0 = _run_group(tmp_path, batch=False)
    m1, d1, c1, t1 = _run_group(tmp_path, batch=True)
    by_sys = lambda ms: {s: [(m.get_type(), m.get_seq(), m.get_msgbuf()) for m in ms if m.get_srcSystem() == s]  # noqa: E731
                         for s in {m.get_srcSystem() for m in ms}}
    # each vehicle's messages in its own order with its own sequence numbers, byte for byte
    # (the order between vehicles may differ: each vehicle's frames of a step leave together)
    assert by_sys(m1) == by_sys(m0) and len(m1) == len(m0) > 6 * 25
    assert c1["sent"] == c0["sent"] == len(m0) and c1["tx_bytes"] == c0["tx_bytes"]
    assert d1 < d0 / 2, (d0, d1)
    assert c1["tx_datagrams"] == d1
    assert sorted(t1) == sorted(t0) and len(t0) == len(m0)


def test_pymavlinks_own_udp_link_reads_every_frame_of_a_packed_datagram():
    """The GCS side as MAVProxy reads it: mavutil's udpin connection, recv_match."""
    rx = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255)
    try:
        addr = rx.port.getsockname()
        ep = VehicleEndpoint(7, "uav", gcs=addr, listen=("127.0.0.1", 0))
        with EndpointGroup([ep], batch_streams=True) as g:
            g.step(1_400_000_000.0, [_telemetry(7, 0)])
            sent = g.counters["sent"]
        assert g.counters["tx_datagrams"] < sent
        got = []
        for _ in range(200):
            m = rx.recv_match(blocking=True, timeout=0.2)
            if m is None:
                break
            got.append(m.get_type())
        assert len(got) == sent and "HEARTBEAT" in got and "GLOBAL_POSITION_INT" in got
    finally:
        rx.close()


def test_the_python_framing_loop_is_the_compiled_ones_code():
    """Without numba the same function runs in Python: same frames."""
    rng = np.random.default_rng(11)
    cls = bt._message_class("global_position_int")
    rows = [random_args(rng, cls) for _ in range(30)]
    p = np.frombuffer(b"".join(bt.payload(cls, a) for a in rows), np.uint8).reshape(30, -1)
    seq, ids = rng.integers(0, 256, 30), rng.integers(1, 256, 30)
    outs = []
    for fn in (bt._frame_rows_py, bt.ready(bt._frame_rows_nb)):
        out, n = np.zeros((30, p.shape[1] + 12), np.uint8), np.zeros(30, np.int64)
        fn(p, seq, ids, ids, int(cls.id), int(cls.crc_extra), out, n)
        outs.append([bytes(out[r, :n[r]]) for r in range(30)])
    assert outs[0] == outs[1] == [_pymavlink_frame("global_position_int", a, int(s), int(i), int(i))
                                  for a, s, i in zip(rows, seq, ids)]
