"""The live bus over real Zenoh sessions on loopback: an embedded router, client sessions,
the same semantics as InMemoryTransport (the reference: the same publications through both
must give the same deliveries and the same counters), no loss under a burst with BLOCK,
clean exit, and the lease."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from tests.sitl.bus.test_bus import FACTORIES, nav, relay

from sitl.bus import (
    BusDecodeError,
    InMemoryTransport,
    KeyExprError,
    Router,
    RouterError,
    ZenohConfigError,
    ZenohTransport,
    ZenohTransportError,
    decode,
    encode,
    key_matches,
)

pytestmark = pytest.mark.live

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir, os.pardir, os.pardir))  # the checkout
ENV = {**os.environ, "PYTHONPATH": REPO + os.pathsep + os.environ.get("PYTHONPATH", "")}


@pytest.fixture(scope="module")
def router():
    with Router(listen=["tcp/127.0.0.1:0"]) as r:
        yield r


@pytest.fixture
def pair(router):
    """A publishing and a receiving client session (queue mode) through the router."""
    a = ZenohTransport(connect=router.endpoints)
    b = ZenohTransport(connect=router.endpoints)
    yield a, b
    a.close()
    b.close()


def _drain_until(bus, done, timeout_s=5.0):
    """Drain until done() or the timeout (bounded)."""
    deadline = time.monotonic() + timeout_s
    while not done() and time.monotonic() < deadline:
        if not bus.drain():
            time.sleep(0.002)
    bus.drain()
    return done()


def _sync(pub, sub_bus, key):
    """Wait until pub sees sub_bus's subscribers on key (declarations travel via the router)."""
    assert pub.wait_for_subscribers(key, timeout_s=5.0)


# ----------------------------------------------------------------------------------------
# Router


def test_router_port_zero_gives_distinct_bound_loopback_ports_freed_on_close():
    with Router() as r1, Router(["tcp/127.0.0.1:0"]) as r2:
        ports = []
        for r in (r1, r2):
            assert len(r.endpoints) == 1 and r.endpoints[0].startswith("tcp/127.0.0.1:")
            port = int(r.endpoints[0].rsplit(":", 1)[1])
            assert port > 0
            with socket.create_connection(("127.0.0.1", port), timeout=2):
                pass  # something listens there
            ports.append(port)
        assert ports[0] != ports[1]
        with pytest.raises(RouterError, match="Address already in use"):
            Router(r1.endpoints)
    assert r1.closed and r2.closed
    for port in ports:  # closed: the ports are free again
        with socket.socket() as s:
            s.bind(("127.0.0.1", port))
    r1.close()  # idempotent


@pytest.mark.parametrize("bad, err", [(["nonsense"], ZenohConfigError),
                                      (["tcp/"], ZenohConfigError),
                                      (["foo/127.0.0.1:1"], RouterError)])
def test_router_bad_endpoint_is_one_clear_line(bad, err):
    with pytest.raises(err) as ei:
        Router(bad)
    text = str(ei.value)
    assert "\n" not in text and ".rs:" not in text and bad[0] in text


def test_client_to_no_router_fails_fast_with_one_line():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.monotonic()
    with pytest.raises(ZenohTransportError) as ei:
        ZenohTransport(connect=[f"tcp/127.0.0.1:{port}"])
    assert time.monotonic() - t0 < 5.0
    assert "\n" not in str(ei.value) and str(port) in str(ei.value)


@pytest.mark.parametrize("kw", [dict(delivery="later"), dict(congestion_control="maybe"),
                                dict(queue_capacity=0), dict(lease_ms=5), dict(mode="boss"),
                                dict(connect=None)])
def test_bad_settings_rejected_before_opening(router, kw):
    kw = {"connect": router.endpoints, **kw}
    with pytest.raises(ZenohConfigError):
        ZenohTransport(**kw)


# ----------------------------------------------------------------------------------------
# Round trips and parity with InMemoryTransport


def test_every_kind_round_trips_between_two_client_sessions(pair):
    a, b = pair
    got = []
    b.subscribe("rt/**", lambda k, m: got.append((k, m)))
    _sync(a, b, "rt/x")
    sent = [(f"rt/{name}/{i}", make(seq=i)) for i, (name, make) in enumerate(FACTORIES.items())]
    for key, msg in sent:
        a.publish(key, msg)
    assert _drain_until(b, lambda: len(got) == len(sent))
    assert got == sent  # one publisher: publish order kept
    assert all(type(m) is type(s) for (_, m), (_, s) in zip(got, sent, strict=True))
    assert a.stats.published == len(sent)
    assert a.stats.published_bytes == sum(len(encode(m)) for _, m in sent)
    assert b.stats.total.delivered == len(sent) and not b.stats.total.rejected


def _garbage(rng, payload):
    """A malformed variant of a valid payload (truncated, bit-flipped or foreign)."""
    choice = rng.integers(4)
    if choice == 0:
        return payload[: rng.integers(0, len(payload))]
    if choice == 1:
        b = bytearray(payload)
        b[rng.integers(len(b))] ^= 1 << int(rng.integers(8))
        return bytes(b)
    if choice == 2:
        return payload + b"\x00"
    return bytes(rng.integers(0, 256, rng.integers(1, 40), dtype=np.uint8))


@pytest.mark.parametrize("seed", [0, 1])
def test_same_deliveries_and_counters_as_in_memory_transport(router, seed):
    """Random overlapping key expressions, valid and malformed payloads, a raising callback:
    the Zenoh transport must deliver per subscription what InMemoryTransport delivers and
    count the same things (each payload once in the totals)."""
    rng = np.random.default_rng(seed)
    exprs = ["p/uav/*/nav", "p/**", "p/uav/**", "p/*/3/*", "p/gs/estimate/**", "p/@v/*",
             "p/uav/3/nav"]
    keys = ["p/uav/3/nav", "p/uav/4/nav", "p/uav/3/beacon/1", "p/sonde/3/relay",
            "p/gs/estimate/beacon", "p/@v/x", "p/x/3/y"]
    makers = list(FACTORIES.values())
    pubs = []
    for i in range(150):
        key = keys[rng.integers(len(keys))]
        msg = makers[rng.integers(len(makers))](seq=i, t_gps_s=1000.0 + i)
        payload = encode(msg)
        if rng.random() < 0.25:
            payload = _garbage(rng, payload)
        pubs.append((key, payload, 1000.0 + i))

    ref = InMemoryTransport()
    a = ZenohTransport(connect=router.endpoints)
    b = ZenohTransport(connect=router.endpoints)
    try:
        got = {"ref": {}, "z": {}}
        subs = {"ref": [], "z": []}
        for name, bus in (("ref", ref), ("z", b)):
            for j, e in enumerate(exprs):
                sink = got[name].setdefault(j, [])
                if j == 3:  # a consumer that raises on every message: isolated, counted
                    def cb(k, m, sink=sink):
                        sink.append((k, m.seq))
                        raise RuntimeError("consumer bug")
                else:
                    def cb(k, m, sink=sink):
                        sink.append((k, m.seq))
                subs[name].append(bus.subscribe(e, cb))
        for key in keys:
            _sync(a, b, key)
        for key, payload, t in pubs:
            ref.publish_raw(key, payload, t)
            a.publish_raw(key, payload)
        ref.drain()
        n_expected = ref.stats.total.delivered + ref.stats.total.rejected_total
        assert _drain_until(b, lambda: (b.stats.total.delivered + b.stats.total.rejected_total
                                        >= n_expected))
        time.sleep(0.05)
        b.drain()
        for j, e in enumerate(exprs):
            want, have = got["ref"][j], got["z"][j]
            assert sorted(have) == sorted(want), e
            for key in keys:  # per key, arrival order is publish order
                assert [s for k, s in have if k == key] == [s for k, s in want if k == key]
            assert {k for k, _ in have} <= {k for k in keys if key_matches(e, k)}
        assert b.stats.total == ref.stats.total
        for sz, sr in zip(subs["z"], subs["ref"], strict=True):
            assert b.stats.per_subscription[sz.id] == ref.stats.per_subscription[sr.id]
        # the rejection reasons are the codec's own, per payload
        want_reasons = {}
        for _key, payload, _ in pubs:
            try:
                decode(payload)
            except BusDecodeError as e:
                want_reasons[e.reason] = want_reasons.get(e.reason, 0) + 1
        assert dict(b.stats.total.rejected) == want_reasons and want_reasons
        assert b.stats.total.callback_errors == len(got["z"][3]) > 0
    finally:
        a.close()
        b.close()
        ref.close()


def test_callback_mode_delivers_without_drain_and_is_serialised(router):
    a = ZenohTransport(connect=router.endpoints)
    b = ZenohTransport(connect=router.endpoints, delivery="callback")
    try:
        got, active, overlap = [], [0], [0]

        def cb(k, m):
            active[0] += 1
            overlap[0] = max(overlap[0], active[0])
            got.append(m.seq)
            time.sleep(0.0002)
            active[0] -= 1

        b.subscribe("cb/a/*", cb)
        b.subscribe("cb/b/*", cb)  # a second Zenoh subscriber: its own thread
        _sync(a, b, "cb/a/x")
        _sync(a, b, "cb/b/x")
        for i in range(200):
            a.publish(f"cb/{'ab'[i % 2]}/x", nav(seq=i))
        deadline = time.monotonic() + 5
        while len(got) < 200 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert sorted(got) == list(range(200))
        assert overlap[0] == 1  # never two callbacks at once
        assert b.drain() == 0
    finally:
        a.close()
        b.close()


def test_raw_subscription_sees_every_payload_before_decoding(pair):
    a, b = pair
    raw, dec = [], []
    b.subscribe_raw("raw/**", lambda k, p: raw.append((k, p)))
    b.subscribe("raw/uav/*", lambda k, m: dec.append(m.seq))
    _sync(a, b, "raw/uav/1")
    good = encode(nav(seq=7))
    a.publish_raw("raw/uav/1", good)
    a.publish_raw("raw/uav/1", b"\xc1junk")
    a.publish_raw("raw/other", good)
    assert _drain_until(b, lambda: len(raw) == 3)
    assert raw == [("raw/uav/1", good), ("raw/uav/1", b"\xc1junk"), ("raw/other", good)]
    assert dec == [7]
    assert b.stats.total.delivered == 1 and b.stats.total.rejected_total == 1


def test_unsubscribe_stops_delivery_and_close_is_final(pair):
    a, b = pair
    got = []
    s = b.subscribe("u/*", lambda k, m: got.append(m.seq))
    _sync(a, b, "u/x")
    a.publish("u/x", nav(seq=1))
    assert _drain_until(b, lambda: got == [1])
    s.close()
    deadline = time.monotonic() + 5
    while a.wait_for_subscribers("u/x", timeout_s=0.01) and time.monotonic() < deadline:
        pass
    a.publish("u/x", nav(seq=2))
    time.sleep(0.1)
    b.drain()
    assert got == [1]
    b.close()
    b.close()
    with pytest.raises(RuntimeError):
        b.publish("u/x", nav())
    with pytest.raises(RuntimeError):
        b.subscribe("u/*", lambda k, m: None)
    with pytest.raises(KeyExprError):
        a.publish("u/*", nav())
    with pytest.raises(KeyExprError):
        a.subscribe("u/**/**", lambda k, m: None)


# ----------------------------------------------------------------------------------------
# Burst, exit, lease (subprocesses: never fork a process holding a Zenoh session)

PUBLISHER = """
    import sys
    sys.path.insert(0, "tests")
    import msgpack
    from sitl.bus import ZenohTransport
    from sitl.bus.codec import pack_sealed
    bus = ZenohTransport(connect=[sys.argv[1]], congestion_control=sys.argv[3])
    with open(sys.argv[4], "rb") as f:  # one encoded SondeRelay; each copy gets its seq (and its CRC)
        wire = msgpack.unpackb(f.read())
    payloads = [pack_sealed({**wire, "seq": i}) for i in range(int(sys.argv[2]))]
    assert bus.wait_for_subscribers("burst/sonde/1/relay", 10.0)
    for p in payloads:
        bus.publish_raw("burst/sonde/1/relay", p)
    print("published", flush=True)
    sys.stdin.readline()  # closing with data still in flight can lose it: wait for the test
    bus.close()
"""


@pytest.mark.slow
def test_burst_into_a_stalled_receiver_loses_nothing_with_block(router, tmp_path):
    """3000 messages of 5.3 kB (16 MB, more than the socket buffers hold) as fast as another
    process can publish, into a receiver that stops draining for 0.5 s and whose queue holds
    64: BLOCK back-pressure must make the publisher wait, not drop (DROP loses most here)."""
    n = 3000
    template = tmp_path / "relay.bin"
    template.write_bytes(encode(relay(60)))  # 5.3 kB
    b = ZenohTransport(connect=router.endpoints, queue_capacity=64)
    seqs = []
    b.subscribe("burst/**", lambda k, m: seqs.append(m.seq))
    proc = subprocess.Popen([sys.executable, "-c", textwrap.dedent(PUBLISHER),
                             router.endpoints[0], str(n), "block", str(template)],
                            env=ENV, cwd=REPO,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert _drain_until(b, lambda: len(seqs) > 0, timeout_s=20.0)
        time.sleep(0.5)  # the receiver stalls: everything behind it must wait
        assert _drain_until(b, lambda: len(seqs) >= n, timeout_s=20.0), len(seqs)
        out, err = proc.communicate("\n", timeout=10)
        assert proc.returncode == 0 and "published" in out, err
        b.drain()
        assert seqs == list(range(n))  # all, once, in order
        assert b.stats.total.delivered == n
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        b.close()


EXITER = """
    import sys, time
    from sitl.bus import ZenohTransport
    bus = ZenohTransport(connect=[sys.argv[1]], delivery=sys.argv[2])
    bus.subscribe("exit/**", lambda k, m: None)
    bus.subscribe_raw("exit/raw/**", lambda k, p: None)
    bus.publish_raw("exit/x", b"junk")
    print("up", flush=True)
    # no close: the interpreter's exit must still end the process
"""


def test_processes_exit_promptly_with_subscribers_left_declared(router):
    """Zenoh callback subscribers left declared used to hang the interpreter's exit."""
    t0 = time.monotonic()
    procs = [subprocess.Popen([sys.executable, "-c", textwrap.dedent(EXITER),
                               router.endpoints[0], delivery], env=ENV, cwd=REPO,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for delivery in ("callback", "queue")]  # in parallel
    try:
        for p in procs:
            out, err = p.communicate(timeout=20)
            assert p.returncode == 0 and "up" in out, err
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    assert time.monotonic() - t0 < 15.0


def test_routerd_process_and_the_lease_find_a_silent_router(tmp_path):
    """A router process frozen with SIGSTOP (a silent partition: the TCP link stays up) is
    declared gone after its 1 s lease, not Zenoh's default 10 s."""
    proc = subprocess.Popen([sys.executable, "-m", "sitl.bus.routerd", "--lease-ms", "1000"],
                            env=ENV, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    bus = None
    try:
        info = json.loads(proc.stdout.readline())
        bus = ZenohTransport(connect=info["endpoints"], lease_ms=1000)
        assert len(bus.routers()) == 1
        os.kill(proc.pid, signal.SIGSTOP)
        t0 = time.monotonic()
        while bus.routers() and time.monotonic() - t0 < 6.0:
            time.sleep(0.02)
        gone_after = time.monotonic() - t0
        assert not bus.routers(), "the silent router was not noticed"
        assert 0.5 < gone_after < 4.0
        os.kill(proc.pid, signal.SIGCONT)
        proc.terminate()
        assert proc.wait(timeout=10) == 0  # SIGTERM: clean exit
    finally:
        if bus is not None:
            bus.close()
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGCONT)
            proc.kill()
            proc.wait()
        proc.stdout.close()
        proc.stderr.close()


@pytest.mark.parametrize("argv", [["--lease-ms", "x"], ["--nope"], ["--lease-ms", "5"],
                                  ["udp-ish"]])
def test_routerd_bad_arguments_exit_2_with_one_line(argv, capsys):
    from sitl.bus import routerd

    with pytest.raises(SystemExit) as ei:
        raise SystemExit(routerd.main(argv))
    assert ei.value.code == 2
    err = capsys.readouterr().err
    assert "error:" in err and "Traceback" not in err


def test_router_restart_clients_reconnect_and_the_gap_shows_in_the_sequence():
    """Clients re-attach to a router restarted on the same endpoint and re-declare their
    subscriptions by themselves; what was published while it was down is lost (hop-to-hop
    reliability), and the sequence numbers show exactly that gap."""
    from sitl.bus import SequenceTracker

    r = Router(lease_ms=1000)
    a = ZenohTransport(connect=r.endpoints, lease_ms=1000)
    b = ZenohTransport(connect=r.endpoints, lease_ms=1000)
    tracker, got = SequenceTracker(), []

    def on_nav(k, m):
        got.append(m.seq)
        tracker.update(m.source_id, m.seq)

    try:
        b.subscribe("rs/uav/*/nav", on_nav)
        _sync(a, b, "rs/uav/1/nav")
        a.publish("rs/uav/1/nav", nav(seq=0))
        assert _drain_until(b, lambda: got == [0])
        r.close()
        deadline = time.monotonic() + 5
        while (a.routers() or b.routers()) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert not a.routers() and not b.routers()
        for seq in (1, 2, 3):
            a.publish("rs/uav/1/nav", nav(seq=seq))  # nowhere to go: lost, no error
        r = Router(r.endpoints, lease_ms=1000)
        deadline = time.monotonic() + 15
        while not (a.routers() and b.routers()) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert a.routers() and b.routers(), "the clients did not come back"
        _sync(a, b, "rs/uav/1/nav")  # b's subscription was declared again
        a.publish("rs/uav/1/nav", nav(seq=4))
        assert _drain_until(b, lambda: len(got) == 2)
        assert got == [0, 4]
        c = tracker.counters("uav-3")
        assert (c.gaps, c.missing) == (1, 3)
    finally:
        a.close()
        b.close()
        r.close()


# ----------------------------------------------------------------------------------------
# Publisher fault filters (issue 8): what reaches a receiver is exactly the injected truth


def _faulty_pair(router, kf, **kw):
    a = ZenohTransport(connect=router.endpoints, faults=[kf], **kw)
    b = ZenohTransport(connect=router.endpoints)
    return a, b


@pytest.mark.parametrize("seed", [3, 4])
def test_publisher_filter_drops_duplicates_and_corrupts_exactly_the_truth(router, seed):
    """KeyFaults at the publisher over a real router: a receiver's SequenceTracker sees the
    loss, duplicates and (through the CRC) corruption that the LinkTruth of each key says,
    key by key; a key no rule matches passes untouched."""
    from sitl.bus import SequenceTracker
    from sitl.netfault import KeyFaults
    t0 = 1_400_000_000.0
    kf = KeyFaults([("fz/uav/*/nav", "loss=15% duplicate=10% corrupt=5%")], seed=seed)
    a, b = _faulty_pair(router, kf, fault_t0_s=t0)
    try:
        tracker = SequenceTracker()
        b.subscribe("fz/**", lambda k, m: tracker.update(k, m.seq))
        _sync(a, b, "fz/uav/1/nav")
        keys = ["fz/uav/1/nav", "fz/uav/2/nav", "fz/other/x"]
        n = 600
        for i in range(n):
            for k in keys:
                a.publish(k, nav(seq=i, t_gps_s=t0 + 0.1 * i, source_id="uav-1"))
        expect_valid = n  # the untouched key
        expect_bad = 0
        for k in keys[:2]:
            v = kf.truth(k).receiver_view()
            expect_valid += v["received"] + v["duplicates"]
            expect_bad += v["rejected_corrupt"]
        done = lambda: b.stats.total.delivered + b.stats.total.rejected_total >= expect_valid + expect_bad
        assert _drain_until(b, done, 10.0)
        for k in keys[:2]:
            tr = kf.truth(k)
            assert tr.sent == n and tr.dropped_loss > 0 and tr.duplicated > 0 and tr.corrupted > 0
            v = tr.receiver_view()  # what a CRC-checking receiver counting seqs must see
            c = tracker.counters(k)
            assert (c.new + c.out_of_order, c.duplicates, c.missing) == (v["received"], v["duplicates"],
                                                                          v["missing"]), k
        other = tracker.counters("fz/other/x")
        assert (other.new, other.duplicates, other.missing) == (n, 0, 0)
        assert b.stats.total.rejected.get("crc", 0) == expect_bad
        assert b.stats.total.rejected_total == expect_bad
        fs = a.fault_stats
        assert fs["offered"] == 3 * n and a.stats.published == 3 * n
        assert fs["dropped"] == sum(kf.truth(k).dropped for k in keys[:2])
        assert fs["duplicated"] == sum(kf.truth(k).duplicated for k in keys[:2])
        assert fs["sent"] == n + sum(kf.truth(k).delivered for k in keys[:2])
    finally:
        a.close()
        b.close()


def test_publisher_filter_delay_waits_in_wall_time_scaled_by_speed_and_close_flushes(router):
    """delay=400ms at speed 2 is ~0.2 s of wall time; a copy still waiting when the publisher
    closes is put at once (counted), nothing is lost; a run-time change (with_faults) applies
    to what is published after it; the scheduler thread is gone after close."""
    import threading

    from sitl.netfault import KeyFaults
    kf = KeyFaults([("fd/**", "delay=400ms")], seed=1)
    a, b = _faulty_pair(router, kf, speed=2.0)
    try:
        got = []
        b.subscribe("fd/**", lambda k, m: got.append((m.seq, time.perf_counter())))
        _sync(a, b, "fd/x")
        t_pub = time.perf_counter()
        a.publish("fd/x", nav(seq=0, t_gps_s=10.0))
        assert a.fault_stats["delayed"] == 1 and a.fault_stats["sent"] == 0
        assert _drain_until(b, lambda: len(got) == 1, 5.0)
        lat = got[0][1] - t_pub
        assert 0.17 <= lat <= 0.6, lat
        # a long delay, then close at once: flushed, not lost
        a.with_faults(lambda: kf.set("fd/**", "delay=100s", a.fault_now_s))
        a.publish("fd/x", nav(seq=1, t_gps_s=11.0))
        assert a.fault_stats["pending"] == 1
        a.close()
        assert a.fault_stats["flushed_at_close"] == 1 and a.fault_stats["pending"] == 0
        assert _drain_until(b, lambda: len(got) == 2, 5.0)
        assert [s for s, _ in got] == [0, 1]
        assert not any(t.name == "bus-fault-delay" and t.is_alive() for t in threading.enumerate())
    finally:
        a.close()
        b.close()


def test_publisher_filter_partition_in_run_time_and_async_control_subscription(router):
    """Filter times are relative to fault_t0_s (the run's start): partition=2-4 drops exactly
    the messages of seconds 2..4 of the run. subscribe_async delivers on Zenoh's thread to a
    worker that never drains, and counts a bad payload instead of raising."""
    import threading

    from sitl.netfault import KeyFaults
    t0 = 1_400_000_000.0
    kf = KeyFaults([("fp/**", "partition=2-4")], seed=2)
    a, b = _faulty_pair(router, kf, fault_t0_s=t0)
    c = ZenohTransport(connect=router.endpoints)
    try:
        got = []
        b.subscribe("fp/**", lambda k, m: got.append(m.seq))
        heard = threading.Event()
        ctl = []
        a.subscribe_async("fp-ctl/**", lambda k, m: (ctl.append((k, m.seq)), heard.set()))
        _sync(a, b, "fp/x")
        _sync(c, a, "fp-ctl/x")
        for i in range(60):
            a.publish("fp/x", nav(seq=i, t_gps_s=t0 + 0.1 * i))
        assert _drain_until(b, lambda: len(got) == 40, 5.0)
        assert got == [i for i in range(60) if not 20 <= i < 40]
        assert kf.truth("fp/x").dropped_partition == 20
        c.publish_raw("fp-ctl/x", b"\x00junk")
        c.publish("fp-ctl/x", nav(seq=7))
        assert heard.wait(5.0)  # a never-draining transport: no drain call anywhere
        assert ctl == [("fp-ctl/x", 7)] and a.async_rejected.total() == 1
    finally:
        a.close()
        b.close()
        c.close()
