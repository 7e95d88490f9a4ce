"""The crash-safe bus log: round trips, the longest valid prefix after any truncation or
corruption, appending after a crash, the kill -9 promise (a real SIGKILL), the recorder."""

from __future__ import annotations

import os
import signal
import struct
import subprocess
import sys
import textwrap
import threading
import time
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from tests.sitl.bus.test_bus import FACTORIES, nav

from sitl.bus import (
    BusLogError,
    BusLogStats,
    BusLogWriter,
    BusRecorder,
    InMemoryTransport,
    decode,
    encode,
    read_bus_log,
    read_bus_log_records,
)
from sitl.bus.buslog import MAGIC

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir, os.pardir, os.pardir))  # the checkout
ENV = {**os.environ, "PYTHONPATH": REPO + os.pathsep + os.environ.get("PYTHONPATH", "")}
FAST = settings(derandomize=True, database=None, deadline=None, max_examples=60,
                suppress_health_check=[HealthCheck.too_slow,
                                       HealthCheck.function_scoped_fixture])


def _records(seed: int, n: int, sizes=(0, 1, 7, 300, 5000)) -> list[tuple[float, str, bytes]]:
    rng = np.random.default_rng(seed)
    keys = ["r/uav/1/nav", "r/sonde/é/relay", "r/gs/estimate/beacon", "k"]
    out = []
    for i in range(n):
        size = int(rng.choice(sizes))
        out.append((float(rng.uniform(0, 2e9)), keys[i % len(keys)] + f"/{i}",
                    rng.integers(0, 256, size, dtype=np.uint8).tobytes()))
    return out


def _frame(t: float, key: str, payload: bytes) -> bytes:
    """The documented record layout, written independently of the writer."""
    kb = key.encode()
    body = struct.pack("<dH", t, len(kb)) + kb + payload
    n = struct.pack("<I", len(body))
    return n + struct.pack("<I", zlib.crc32(n + body)) + body


def _write(path, recs, **kw):
    with BusLogWriter(path, append=False, **kw) as w:
        for t, k, p in recs:
            w.append(k, p, t_recv_s=t)
    return w


def test_round_trip_and_the_documented_byte_layout(tmp_path):
    recs = _records(0, 200)
    path = tmp_path / "a.buslog"
    w = _write(path, recs)
    assert w.records == 200 and w.write_errors == 0
    st_ = BusLogStats()
    assert [tuple(r) for r in read_bus_log_records(path, stats=st_)] == recs
    assert list(read_bus_log(path)) == [(k, p) for _, k, p in recs]
    assert st_.records == 200 and st_.dropped_bytes == 0 and not st_.torn_tail
    assert path.read_bytes() == MAGIC + b"".join(_frame(*r) for r in recs)


def _boundaries(recs):
    """File offsets at which each record ends (from the independent framing)."""
    ends, pos = [], len(MAGIC)
    for r in recs:
        pos += len(_frame(*r))
        ends.append(pos)
    return ends


def test_every_truncation_keeps_the_longest_valid_prefix(tmp_path):
    recs = _records(1, 4, sizes=(0, 1, 7, 90))
    path = tmp_path / "t.buslog"
    _write(path, recs)
    data = path.read_bytes()
    ends = _boundaries(recs)
    cut = tmp_path / "cut.buslog"
    for size in range(len(data) + 1):
        cut.write_bytes(data[:size])
        if size < len(MAGIC):
            st_ = BusLogStats()
            assert list(read_bus_log(cut, stats=st_)) == []
            assert st_.torn_tail == (size > 0)
            continue
        st_ = BusLogStats()
        got = [tuple(r) for r in read_bus_log_records(cut, stats=st_)]
        whole = sum(e <= size for e in ends)
        assert got == recs[:whole], size
        valid = ends[whole - 1] if whole else len(MAGIC)
        assert st_.valid_bytes == valid and st_.dropped_bytes == size - valid
        assert st_.torn_tail == (size > valid) and not st_.corrupt


@FAST
@given(pos=st.integers(0, 10_000), bit=st.integers(0, 7), seed=st.integers(0, 3))
def test_a_flipped_bit_never_crashes_the_reader_and_leaves_a_prefix(tmp_path, pos, bit, seed):
    recs = _records(seed, 8)
    path = tmp_path / f"f{seed}.buslog"
    if not path.exists():
        _write(path, recs)
    data = bytearray(path.read_bytes())
    pos %= len(data)
    data[pos] ^= 1 << bit
    bad = tmp_path / "flipped.buslog"
    bad.write_bytes(bytes(data))
    if pos < len(MAGIC):
        with pytest.raises(BusLogError):
            list(read_bus_log(bad))
        return
    st_ = BusLogStats()
    got = [tuple(r) for r in read_bus_log_records(bad, stats=st_)]
    whole = sum(e <= pos for e in _boundaries(recs))  # records wholly before the flip
    assert got == recs[:whole]  # CRC-32 catches every single-bit error
    assert st_.corrupt or st_.torn_tail  # a flipped length may claim bytes past the end
    assert st_.dropped_bytes == len(data) - st_.valid_bytes > 0


def test_not_a_bus_log_is_refused_in_one_line(tmp_path):
    other = tmp_path / "other.bin"
    other.write_bytes(b"PK\x03\x04 not ours at all")
    with pytest.raises(BusLogError, match="not a skyfuse bus log"):
        list(read_bus_log(other))
    with pytest.raises(BusLogError, match="not a skyfuse bus log"):
        BusLogWriter(other)
    assert other.read_bytes().startswith(b"PK")  # left untouched
    newer = tmp_path / "v9.buslog"
    newer.write_bytes(MAGIC[:7] + b"\x09")
    with pytest.raises(BusLogError, match="version 9"):
        list(read_bus_log(newer))


def test_reopening_cuts_a_torn_tail_then_appends_readably(tmp_path):
    recs = _records(2, 10)
    path = tmp_path / "c.buslog"
    _write(path, recs[:7])
    whole = path.read_bytes()
    path.write_bytes(whole[:-5])  # a crash in the middle of the 7th record
    with BusLogWriter(path) as w:
        assert w.recovered.records == 6 and w.recovered.torn_tail
        for t, k, p in recs[7:]:
            w.append(k, p, t_recv_s=t)
    assert [tuple(r) for r in read_bus_log_records(path)] == recs[:6] + recs[7:]
    with BusLogWriter(path, append=False):
        pass
    assert path.read_bytes() == MAGIC


def test_concurrent_appends_are_whole_records(tmp_path):
    path = tmp_path / "mt.buslog"
    per = 500
    with BusLogWriter(path, append=False, max_buffer_bytes=4096) as w:
        def run(j):
            for i in range(per):
                w.append(f"mt/{j}", struct.pack("<II", j, i), t_recv_s=float(i))
        threads = [threading.Thread(target=run, args=(j,)) for j in range(4)]
        for th in threads:
            th.start()
        for th in threads:
            th.join()
    st_ = BusLogStats()
    got = list(read_bus_log(path, stats=st_))
    assert st_.dropped_bytes == 0 and len(got) == 4 * per
    for j in range(4):  # each thread's records complete and in its order
        assert [struct.unpack("<II", p)[1] for k, p in got if k == f"mt/{j}"] == list(range(per))


def test_bad_appends_raise_clearly_and_close_is_final(tmp_path):
    w = BusLogWriter(tmp_path / "b.buslog", append=False)
    with pytest.raises(TypeError):
        w.append("k", "not bytes")  # type: ignore[arg-type]
    with pytest.raises(BusLogError):
        w.append("k" * 70_000, b"")
    w.close()
    w.close()
    with pytest.raises(RuntimeError):
        w.append("k", b"x")
    with pytest.raises(ValueError):
        BusLogWriter(tmp_path / "c.buslog", flush_interval_s=2.0)


def test_idle_records_reach_the_file_without_close(tmp_path):
    """The flusher thread writes a quiet writer's buffer within the interval."""
    path = tmp_path / "idle.buslog"
    w = BusLogWriter(path, append=False, flush_interval_s=0.2)
    try:
        w.append("idle/a", b"1")
        w.append("idle/b", b"2")
        deadline = time.monotonic() + 1.0
        while time.monotonic() < deadline and len(list(read_bus_log(path))) < 2:
            time.sleep(0.02)
        assert list(read_bus_log(path)) == [("idle/a", b"1"), ("idle/b", b"2")]
        assert w.flushes >= 1
    finally:
        w.close()


KILLED_WRITER = """
    import sys, time
    from sitl.bus.buslog import BusLogWriter
    w = BusLogWriter(sys.argv[1], append=False)
    i = 0
    start = time.monotonic()
    while time.monotonic() - start < 0.5:  # busy: a record a millisecond
        w.append("kill/seq", i.to_bytes(8, "little"), t_recv_s=time.monotonic())
        i += 1
        if i == 50:
            print("writing", flush=True)
        time.sleep(0.001)
    print("idle", i, flush=True)
    time.sleep(60)  # then quiet, the records still buffered
"""


def _kill_writer(path, when):
    proc = subprocess.Popen([sys.executable, "-c", textwrap.dedent(KILLED_WRITER), str(path)],
                            env=ENV, cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "writing"
        n_idle = None
        if when == "busy":
            time.sleep(0.5)
        else:
            n_idle = int(proc.stdout.readline().split()[1])
            time.sleep(1.1)
        t_kill = time.monotonic()
        os.kill(proc.pid, signal.SIGKILL)
        assert proc.wait(timeout=10) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()
        proc.stderr.close()
    return t_kill, n_idle


@pytest.mark.slow
@pytest.mark.live
@pytest.mark.parametrize("when", ["busy", "idle"])
def test_kill_9_loses_at_most_the_last_second_and_the_file_reads(tmp_path, when):
    """A real SIGKILL of a writing process: the log reads, holds records 0..k in order, and
    nothing written more than 1 s before the kill is missing (CLOCK_MONOTONIC is shared by
    the processes of the machine). Killed 1.1 s into a quiet spell, every record is there."""
    path = tmp_path / "k.buslog"
    t_kill, n_idle = _kill_writer(path, when)
    st_ = BusLogStats()
    recs = list(read_bus_log_records(path, stats=st_))
    assert len(recs) >= 50
    assert [int.from_bytes(r.payload, "little") for r in recs] == list(range(len(recs)))
    if n_idle is None:  # killed while writing: what is missing is from the last second
        assert t_kill - recs[-1].t_recv_s <= 1.0
    else:  # killed 1.1 s into a quiet spell: nothing is missing
        assert len(recs) == n_idle
    assert st_.dropped_bytes == 0  # whole buffers are written: a kill tears no record


def test_recorder_on_in_memory_bus_records_the_wire_bytes_and_replays(tmp_path):
    path = tmp_path / "rec.buslog"
    bus = InMemoryTransport()
    clock = iter(np.arange(100.0, 200.0, 0.5)).__next__
    rec = BusRecorder(bus, path, "run/**", clock=clock)
    sent = [(f"run/{name}/{i}", make(seq=i)) for i, (name, make) in enumerate(FACTORIES.items())]
    for k, m in sent:
        bus.publish(k, m)
    bus.publish("other/x", nav())  # outside the expression: not recorded
    bus.publish_raw("run/bad", b"\x00")  # malformed: rejected by the bus, so not seen
    bus.drain()
    rec.close()
    rows = list(read_bus_log_records(path))
    assert [(r.key, r.payload) for r in rows] == [(k, encode(m)) for k, m in sent]
    assert [r.t_recv_s for r in rows] == [100.0 + 0.5 * i for i in range(len(sent))]
    # replay through a fresh bus gives the same messages
    replay = InMemoryTransport()
    got = []
    replay.subscribe("run/**", lambda k, m: got.append((k, m)))
    for k, p in read_bus_log(path):
        replay.publish_raw(k, p)
    replay.drain()
    assert got == sent and all(decode(p) == m for (_, p), (_, m) in
                               zip(read_bus_log(path), sent, strict=True))


@pytest.mark.live
def test_recorder_on_zenoh_records_malformed_payloads_too(tmp_path):
    from sitl.bus import Router, ZenohTransport

    path = tmp_path / "z.buslog"
    with Router() as r:
        a = ZenohTransport(connect=r.endpoints)
        b = ZenohTransport(connect=r.endpoints)
        try:
            rec = BusRecorder(b, path, "zr/**")
            assert rec.raw
            assert a.wait_for_subscribers("zr/x", 5.0)
            payloads = [encode(nav(seq=1)), b"\xc1", encode(nav(seq=2))]
            for p in payloads:
                a.publish_raw("zr/x", p)
            deadline = time.monotonic() + 5
            while rec.records < 3 and time.monotonic() < deadline:
                b.drain() or time.sleep(0.005)
            rec.close()
        finally:
            a.close()
            b.close()
    assert list(read_bus_log(path)) == [("zr/x", p) for p in payloads]


def test_recorder_counts_but_does_not_write_payloads_larger_than_any_message(tmp_path):
    """A flood of huge junk must not fill the disk: over the codec's bound it is counted only."""
    from sitl.bus import MAX_PAYLOAD_BYTES, BusRecorder

    class RawOnly:
        def subscribe_raw(self, expr, cb):
            self.cb = cb
            return self

        def close(self):
            pass

    t = RawOnly()
    rec = BusRecorder(t, tmp_path / "b.log", append=False)
    t.cb("r/uav/1/nav", b"x" * MAX_PAYLOAD_BYTES)  # at the bound: recorded (and rejected by replay)
    for _ in range(20):
        t.cb("r/uav/1/nav", b"x" * (MAX_PAYLOAD_BYTES + 1))
    rec.close()
    assert rec.records == 1 and rec.oversize == 20
    assert (tmp_path / "b.log").stat().st_size < 2 * MAX_PAYLOAD_BYTES
