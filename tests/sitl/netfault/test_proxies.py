"""Live fault proxies (issue 8) on loopback, bounded in time: the UDP proxy on MAVLink links
(pymavlink as the peer, the fault model's truth and an offline replay of it as references)
and the TCP proxy on a Zenoh session's link (an embedded router, silent partitions)."""
from __future__ import annotations

import os
import socket
import threading
import time

import numpy as np
import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.bus.zconfig import make_config
from sitl.bus.router import Router
from sitl.pacing import Pacer
from sitl.netfault import FaultSpecError, LinkFault
from sitl.netfault.proxyloop import ProxyLoop
from sitl.netfault.tcp_proxy import TcpProxy
from sitl.netfault.udp_proxy import UdpProxy, parse_addr
from tests.procs import tcp_free, udp_free

pytestmark = pytest.mark.live

LO = "127.0.0.1"


# ---- helpers ---------------------------------------------------------------------------------

def udp() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind((LO, 0))
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
    return s


def recv_n(sock: socket.socket, n: int, timeout_s: float = 2.0, quiet_s: float | None = None) -> list:
    """Up to n datagrams (data, addr, perf time); stops at n, at the deadline, or after
    quiet_s without a datagram."""
    out = []
    deadline = time.perf_counter() + timeout_s
    while len(out) < n:
        left = deadline - time.perf_counter()
        if left <= 0:
            break
        sock.settimeout(min(left, quiet_s) if quiet_s else left)
        try:
            data, addr = sock.recvfrom(65535)
        except TimeoutError:
            break
        out.append((data, addr, time.perf_counter()))
    return out


def wait_for(pred, timeout_s: float = 3.0, step_s: float = 0.005) -> bool:
    deadline = time.perf_counter() + timeout_s
    while time.perf_counter() < deadline:
        if pred():
            return True
        time.sleep(step_s)
    return pred()


def proxy_threads() -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith("proxy-") or t.name == "netfault-proxy"]


def heartbeat(mav, i: int) -> bytes:
    """The next HEARTBEAT of mav (its seq advances, as MAVLink.send does), custom_mode = i
    (distinct bytes when the uint8 seq wraps)."""
    buf = mav.heartbeat_encode(mavlink.MAV_TYPE_FIXED_WING, mavlink.MAV_AUTOPILOT_GENERIC, 0, i,
                               mavlink.MAV_STATE_ACTIVE).pack(mav)
    mav.seq = (mav.seq + 1) % 256
    return buf


def peer_parse(data: bytes) -> list:
    """What a pymavlink receiver accepts from one datagram (its CRC check rejects the rest)."""
    m = mavlink.MAVLink(None)
    m.robust_parsing = True
    return [x for x in (m.parse_buffer(data) or [])
            if not isinstance(x, (mavlink.MAVLink_bad_data, mavlink.MAVLink_unknown))]


def send_paced(sock, bufs, dest, proxy, direction: str, batch: int = 40) -> None:
    """Send in batches, each once the proxy has read the previous (no kernel buffer drops)."""
    base = getattr(proxy.stats(), direction).received
    for k in range(0, len(bufs), batch):
        for b in bufs[k:k + batch]:
            sock.sendto(b, dest)
        n = base + min(k + batch, len(bufs))
        assert wait_for(lambda n=n: getattr(proxy.stats(), direction).received >= n), "proxy did not read"


# ---- UDP ---------------------------------------------------------------------------------------

def test_udp_no_fault_passes_every_datagram_byte_identical_both_ways():
    gcs, veh = udp(), udp()
    try:
        with UdpProxy(gcs.getsockname(), rng=1, name="mav:1") as p:
            @settings(max_examples=25, deadline=None, derandomize=True,
                      suppress_health_check=[HealthCheck.too_slow])
            @given(st.lists(st.binary(max_size=1400), min_size=1, max_size=10),
                   st.lists(st.binary(max_size=1400), max_size=10))
            def law(ups, downs):
                for b in ups:
                    veh.sendto(b, p.addr)
                got = recv_n(gcs, len(ups))
                assert [d for d, _, _ in got] == ups
                assert {a for _, a, _ in got} == {p.upstream_addr}  # one upstream address per link
                for b in downs:
                    gcs.sendto(b, p.upstream_addr)
                got = recv_n(veh, len(downs))
                assert [d for d, _, _ in got] == downs  # back to the last client, from the listen port
                assert all(a == p.addr for _, a, _ in got)

            law()
            s = p.stats()
            assert s.client == veh.getsockname()
            for d in (s.up, s.down):
                assert d.received == d.forwarded == d.truth.sent == d.truth.delivered > 0
                assert d.send_errors == d.no_client == d.pending == 0
    finally:
        gcs.close()
        veh.close()


@pytest.mark.parametrize("up,down", [("loss=15% duplicate=10%", "loss=10%,25% duplicate=5%"),
                                     ("gemodel=5%,30%", "none")])
def test_udp_seeded_loss_duplicates_equal_truth_replay_and_mavlink_tap(up, down):
    n, seed = 400, 11
    gcs, veh = udp(), udp()
    vmav = mavlink.MAVLink(None, srcSystem=7, srcComponent=1)
    gmav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    sent = {"up": [heartbeat(vmav, i) for i in range(n + 1)],
            "down": [heartbeat(gmav, i) for i in range(n + 1)]}
    try:
        with UdpProxy(gcs.getsockname(), rng=seed, name="mav:7") as p:
            # a first packet each way on a clean link (the client is known from here, and a receiver
            # sees no losses before the first packet it gets), then the faults
            send_paced(veh, sent["up"][:1], p.addr, p, "up")
            send_paced(gcs, sent["down"][:1], p.upstream_addr, p, "down")
            p.set(up=up, down=down)
            send_paced(veh, sent["up"][1:n], p.addr, p, "up")
            send_paced(gcs, sent["down"][1:n], p.upstream_addr, p, "down")
            # a last packet each way on a clean link: losses at the end become visible gaps
            p.set(up="none", down="none")
            send_paced(veh, sent["up"][n:], p.addr, p, "up")
            send_paced(gcs, sent["down"][n:], p.upstream_addr, p, "down")
            s = p.stats()
            arrived = {"up": recv_n(gcs, s.up.forwarded, quiet_s=0.3),
                       "down": recv_n(veh, s.down.forwarded, quiet_s=0.3)}
            s = p.stats()
            light = p.stats(schedule=False)  # counters only (cheap on a long run)
        for full, cheap in ((s.up.truth, light.up.truth), (s.down.truth, light.down.truth)):
            assert len(full.copy_index) == full.delivered and len(cheap.copy_index) == 0
            assert cheap.counters() == full.counters()
            with pytest.raises(ValueError, match="not recorded"):
                cheap.receiver_view()
        replay_rngs = np.random.default_rng(seed).spawn(2)
        for k, (d, spec, rng) in enumerate([(s.up, up, replay_rngs[0]), (s.down, down, replay_rngs[1])]):
            name = ("up", "down")[k]
            index = {b: i for i, b in enumerate(sent[name])}
            got = [index[data] for data, _, _ in arrived[name]]  # every datagram is one that was sent
            tr = d.truth
            # the proxy's counters equal its truth, and what arrived is exactly what it forwarded
            assert d.received == tr.sent == n + 1
            assert d.forwarded == tr.delivered == len(got)
            assert d.send_errors == d.no_client == d.pending == 0
            # packet by packet: what arrived is the model's schedule, and an offline replay of the
            # same seeded model (independent of the proxy and of time) drops/duplicates the same ones
            assert got == list(tr.delivery_order()[0])
            lf = LinkFault(spec, rng=rng)
            expect = [0] + [i for i, b in enumerate(sent[name][1:n], 1) for _ in lf.process(0.0, b)] + [n]
            assert got == expect
            if spec != "none":  # the spec did act (the model's rates are tested in tests/sitl/netfault/test_models.py)
                assert tr.dropped_loss > 0
            if "duplicate" in spec:
                assert tr.duplicated > 0
            # the receiver-side tap (pymavlink, uint8 seqs unwrapped) sees exactly the truth
            tap = d.tap
            assert tap.messages == tap.datagrams == tr.delivered
            assert tap.bad_crc == tap.bad_other == tap.unknown == tap.truncated == 0
            assert tap.seq.missing == tr.dropped_loss
            assert tap.seq.duplicates == tr.duplicated
            assert tap.seq.out_of_order == 0 == tr.reordered
            src = (7, 1) if name == "up" else (255, 190)
            assert list(tap.sources) == [src] and tap.sources[src] == tap.seq
            view = tr.receiver_view()
            assert (tap.seq.missing, tap.seq.duplicates) == (view["missing"], view["duplicates"])
    finally:
        gcs.close()
        veh.close()


def test_udp_corrupted_packets_are_rejected_by_pymavlink_crc():
    n = 300
    gcs, veh = udp(), udp()
    vmav = mavlink.MAVLink(None, srcSystem=3, srcComponent=1)
    sent = [heartbeat(vmav, i) for i in range(n)]
    try:
        with UdpProxy(gcs.getsockname(), up="corrupt=40%", rng=5, name="mav:3") as p:
            send_paced(veh, sent, p.addr, p, "up")
            s = p.stats()
            arrived = recv_n(gcs, s.up.forwarded, quiet_s=0.3)
        tr, tap = s.up.truth, s.up.tap
        assert len(arrived) == s.up.forwarded == tr.delivered == n and tr.corrupted > 0
        accepted = rejected = 0
        for data, _, _ in arrived:
            good = peer_parse(data)
            rejected += not good
            for m in good:  # nothing accepted that differs from what was sent
                accepted += 1
                assert bytes(m.get_msgbuf()) == sent[m.custom_mode]
        assert rejected == tr.corrupted
        assert accepted == tr.delivered - tr.corrupted
        assert tap.rejected_datagrams == tr.corrupted and tap.messages == accepted
        assert tap.bad_crc > 0 and tap.bad_crc + tap.bad_other + tap.unknown + tap.truncated >= tr.corrupted
        # a corrupted packet is a seq gap for the receiver, except before the first and after the
        # last one it accepted (it cannot know of those)
        bad = tr.corrupted_indices()
        ok = [m.custom_mode for data, _, _ in arrived for m in peer_parse(data)]
        inside = int(np.count_nonzero((bad > min(ok)) & (bad < max(ok))))
        assert tap.seq.missing == inside == tr.receiver_view()["missing"]
    finally:
        gcs.close()
        veh.close()


def test_udp_delay_wall_latency_is_delay_over_speed():
    speed, delay_s, n = 4.0, 0.2, 15
    gcs, veh = udp(), udp()
    try:
        with UdpProxy(gcs.getsockname(), up=f"delay={delay_s}s", rng=2, speed=speed, name="mav:2") as p:
            veh.sendto(b"hello", p.addr)
            assert recv_n(gcs, 1, timeout_s=1.0)
            lat_up, lat_down = [], []
            for i in range(n):
                t0 = time.perf_counter()
                veh.sendto(b"u%d" % i, p.addr)
                (_, _, t1), = recv_n(gcs, 1, timeout_s=1.0)
                lat_up.append(t1 - t0)
                t0 = time.perf_counter()
                gcs.sendto(b"d%d" % i, p.upstream_addr)  # no fault: the baseline in the same run
                (_, _, t1), = recv_n(veh, 1, timeout_s=1.0)
                lat_down.append(t1 - t0)
            s = p.stats()
        want = delay_s / speed
        extra = np.median(lat_up) - np.median(lat_down)
        assert min(lat_up) >= want - 0.002  # never early
        assert abs(extra - want) < 0.012, (np.median(lat_up), np.median(lat_down))
        assert s.up.truth.delay_s_max == pytest.approx(delay_s)
    finally:
        gcs.close()
        veh.close()


def test_udp_partition_window_in_simulation_time():
    """A partition given in simulation seconds (GPS-like epoch, 5x real time) drops exactly
    what the proxy received inside it, in that direction only."""
    speed = 5.0
    pacer = Pacer(speed, 1_400_000_000.0)
    gcs, veh = udp(), udp()
    try:
        with UdpProxy(gcs.getsockname(), rng=0, clock=pacer.sim_now, speed=speed, name="mav:4") as p:
            veh.sendto(b"first", p.addr)
            assert recv_n(gcs, 1)
            t1 = pacer.sim_now() + 0.6
            t2 = t1 + 1.0  # 0.2 s of wall time
            p.set(up=f"partition={t1}-{t2}", down=f"partition={t1}-{t2}")
            sent = []
            for i in range(50):  # 0.4 s of wall time around the window
                t = pacer.sim_now()
                veh.sendto(b"%d" % i, p.addr)
                sent.append(t)
                time.sleep(0.008)
            got = {int(d) for d, _, _ in recv_n(gcs, 50, quiet_s=0.3)}
            s = p.stats()
        sent = np.array(sent)
        lost = sorted(set(range(50)) - got)
        tr = s.up.truth
        assert tr.dropped_partition == len(lost) > 0 and tr.dropped == len(lost)
        assert [i + 1 for i in lost] == tr.dropped_indices("partition").tolist()  # index 0 = "first"
        slack = 0.05 * speed  # sent-to-received time (simulated s), generous
        assert all(t1 - slack <= sent[i] < t2 for i in lost)
        assert all(i in lost for i in np.flatnonzero((sent >= t1) & (sent < t2 - slack)))
        assert s.down.truth.sent == 0  # the other direction saw nothing (and dropped nothing)
    finally:
        gcs.close()
        veh.close()


def test_udp_many_proxies_share_one_thread_and_close_clean():
    n = 40
    before = proxy_threads()
    fds = len(os.listdir("/proc/self/fd"))
    gcs = udp()
    clients = [udp() for _ in range(n)]
    loop = ProxyLoop.from_pacer(Pacer(1.0, 0.0))
    try:
        proxies = [UdpProxy(gcs.getsockname(), down="delay=5ms", rng=i, loop=loop, name=f"mav:{i + 1}")
                   for i in range(n)]
        assert len(proxy_threads()) == len(before) + 1
        ports = [p.addr[1] for p in proxies] + [p.upstream_addr[1] for p in proxies]
        for i, (c, p) in enumerate(zip(clients, proxies)):
            c.sendto(b"v%d" % i, p.addr)
        got = recv_n(gcs, n)
        assert sorted(d for d, _, _ in got) == sorted(b"v%d" % i for i in range(n))
        for data, addr, _ in got:  # each reply reaches the vehicle behind that upstream address
            gcs.sendto(b"r" + data, addr)
        for i, c in enumerate(clients):
            (data, addr, _), = recv_n(c, 1)
            assert data == b"rv%d" % i and addr == proxies[i].addr
        assert not loop.errors
        for p in proxies:
            p.close()
        assert all(udp_free(port) for port in ports)
        assert not loop.closed  # a shared loop outlives its proxies
    finally:
        loop.close()
        gcs.close()
        for c in clients:
            c.close()
    assert wait_for(lambda: proxy_threads() == before, 2.0)
    assert len(os.listdir("/proc/self/fd")) == fds  # every socket closed (the loop's wake-up pair too)


def test_udp_bad_input_is_counted_not_fatal():
    gcs, veh = udp(), udp()
    before = proxy_threads()
    try:
        with pytest.raises(ValueError, match="target"):
            UdpProxy("no-port-here", name="mav:9")
        with pytest.raises(FaultSpecError):
            UdpProxy(gcs.getsockname(), up="loss=120%")
        with UdpProxy(gcs.getsockname(), rng=0, name="mav:9") as p:
            with pytest.raises(OSError, match="mav:9"):
                UdpProxy(gcs.getsockname(), listen=p.addr, name="mav:9")
            gcs.sendto(b"early", p.upstream_addr)  # before any client: nowhere to send it
            assert wait_for(lambda: p.stats().down.no_client == 1)
            junk = [b"\xfd\x09garbage", b"not mavlink at all", b""]
            for b in junk:
                veh.sendto(b, p.addr)
            assert [d for d, _, _ in recv_n(gcs, len(junk))] == junk  # forwarded untouched
            s = p.stats()
            assert s.up.tap.messages == 0 and s.up.tap.rejected_datagrams == len(junk)
            assert s.up.tap.bad_other + s.up.tap.truncated >= 2
        assert udp_free(p.addr[1]) and udp_free(p.upstream_addr[1]) and p.closed
        assert p.stats().up.tap.rejected_datagrams == len(junk)  # the final figures stay readable
        assert parse_addr("127.0.0.1:14550") == ("127.0.0.1", 14550)
        assert proxy_threads() == before  # the failed constructors left no loop running
    finally:
        gcs.close()
        veh.close()


# ---- TCP ---------------------------------------------------------------------------------------

class Server:
    """A loopback TCP server (echo, or sink recording arrival times), stopped by close()."""

    def __init__(self, echo: bool = True):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.bind((LO, 0))
        self.sock.listen()
        self.sock.settimeout(0.1)
        self.addr = self.sock.getsockname()
        self.echo = echo
        self.arrivals: list[tuple[float, int]] = []  # sink: (perf time, bytes)
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._accept, daemon=True)]
        self._threads[0].start()

    def _accept(self):
        while not self._stop.is_set():
            try:
                c, _ = self.sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            t = threading.Thread(target=self._serve, args=(c,), daemon=True)
            self._threads.append(t)
            t.start()

    def _serve(self, c):
        c.settimeout(0.1)
        with c:
            while not self._stop.is_set():
                try:
                    d = c.recv(65536)
                except TimeoutError:
                    continue
                except OSError:
                    return
                if not d:
                    return
                if self.echo:
                    c.sendall(d)
                else:
                    self.arrivals.append((time.perf_counter(), len(d)))

    def close(self):
        self._stop.set()
        self.sock.close()
        for t in self._threads:
            t.join(2.0)


def connect(p: TcpProxy) -> socket.socket:
    c = socket.create_connection(p.addr, timeout=2)
    c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return c


def recv_exact(c: socket.socket, n: int, timeout_s: float = 3.0) -> bytes:
    c.settimeout(timeout_s)
    buf = bytearray()
    while len(buf) < n:
        d = c.recv(n - len(buf))
        if not d:
            break
        buf += d
    return bytes(buf)


def test_tcp_delay_jitter_keeps_byte_order_and_latency():
    srv = Server()
    rng = np.random.default_rng(3)
    data = rng.integers(0, 256, 300_000, dtype=np.uint8).tobytes()
    try:
        with TcpProxy(srv.addr, spec="delay=30ms~25ms distribution=normal", rng=4, speed=2.0,
                      name="zenoh:t1") as p, connect(p) as c:
            cuts = np.sort(rng.integers(0, len(data), 40))
            for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(data)]):  # ragged writes
                c.sendall(data[a:b])
                time.sleep(0.002)
            assert recv_exact(c, len(data)) == data  # jittered chunks never overtake each other
            st = p.stats()
            assert st.truth_up.sent > 1 and st.truth_up.reordered > 0  # the model's times did cross
        with TcpProxy(srv.addr, spec="delay=100ms", speed=2.0, name="zenoh:t2") as p, connect(p) as c:
            rtts = []
            for _ in range(4):
                t0 = time.perf_counter()
                c.sendall(b"p")
                assert recv_exact(c, 1) == b"p"
                rtts.append(time.perf_counter() - t0)
        want = 2 * 0.1 / 2.0
        assert min(rtts) >= want - 0.002 and np.median(rtts) < want + 0.02, rtts
    finally:
        srv.close()


def test_tcp_rate_limit_throughput():
    srv = Server(echo=False)
    rate_bps, n = 4e6, 100_000
    try:
        with TcpProxy(srv.addr, spec=f"rate={rate_bps / 1e6:g}mbit", name="zenoh:rate") as p, connect(p) as c:
            t0 = time.perf_counter()
            c.sendall(b"x" * n)
            assert wait_for(lambda: sum(b for _, b in srv.arrivals) >= n, 3.0)
            took = srv.arrivals[-1][0] - t0
        want = n * 8 / rate_bps
        assert 0.9 * want <= took <= want + 0.08, (took, want)
    finally:
        srv.close()


def test_tcp_back_pressure_bounds_what_the_proxy_holds_and_the_end_of_stream_flushes_all():
    max_buffer = 1 << 20
    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.bind((LO, 0))
    srv.listen()
    try:
        with TcpProxy(srv.getsockname(), spec="delay=10ms", max_buffer=max_buffer, name="zenoh:bp") as p:
            c = socket.create_connection(p.addr, timeout=2)
            conn, _ = srv.accept()  # a server that does not read for a while
            with conn:
                c.setblocking(False)
                sent, blob, t0 = 0, b"x" * 65536, time.perf_counter()
                while time.perf_counter() - t0 < 0.5:
                    try:
                        sent += c.send(blob)
                    except BlockingIOError:
                        time.sleep(0.01)
                st = p.stats()
                assert 0 < st.bytes_up_in - st.bytes_up_out <= max_buffer + 16384  # + one read
                assert sent > st.bytes_up_in  # the rest waits in the sockets, not in the proxy
                c.close()  # the end of stream reaches the server after every byte
                conn.settimeout(3)
                got = 0
                while d := conn.recv(1 << 20):
                    got += len(d)
                assert got == sent
    finally:
        srv.close()


def test_tcp_manual_silent_partition_holds_bytes_and_keeps_the_connection():
    srv = Server()
    try:
        with TcpProxy(srv.addr, name="zenoh:m") as p, connect(p) as c:
            c.sendall(b"before")
            assert recv_exact(c, 6) == b"before"
            p.down()
            c.sendall(b"during")
            c.settimeout(0.3)
            with pytest.raises((TimeoutError, socket.timeout)):
                c.recv(10)
            assert p.stats().partitioned
            p.up()
            assert recv_exact(c, 6) == b"during"  # held, then delivered on the same connection
            st = p.stats()
            assert (st.accepted, st.active, st.resets, st.partitions, st.partitioned) == (1, 1, 0, 1, False)
    finally:
        srv.close()


def test_tcp_reset_partition_from_spec_window_then_new_connections_work():
    srv = Server()
    clock = Pacer(1.0, 0.0).sim_now
    try:
        with TcpProxy(srv.addr, mode="reset", clock=clock, name="zenoh:r") as p:
            c1 = socket.create_connection(p.addr, timeout=2)
            c1.sendall(b"one")
            assert recv_exact(c1, 3) == b"one"
            t1 = clock() + 0.2
            p.set(f"partition={t1}-{t1 + 0.5}")
            c1.settimeout(2.0)
            with pytest.raises(ConnectionResetError):
                c1.recv(10)
            assert clock() >= t1
            c1.close()
            with pytest.raises(ConnectionResetError), connect(p) as c2:  # during the window: reset at
                c2.settimeout(2.0)                                           # once (connect or first read)
                c2.recv(10)
            assert wait_for(lambda: clock() >= t1 + 0.5, 2.0)
            with socket.create_connection(p.addr, timeout=2) as c3:
                c3.sendall(b"three")
                assert recv_exact(c3, 5) == b"three"
            st = p.stats()
            assert st.resets == 1 and st.refused == 1 and st.accepted == 3 and st.partitions == 1
            port = p.addr[1]
        assert tcp_free(port)
        final = p.stats()  # the final figures stay readable after close
        assert (final.accepted, final.resets, final.refused, final.active) == (3, 1, 1, 0)
        with pytest.raises(ValueError, match="cannot apply to a TCP stream"):
            TcpProxy(srv.addr, spec="loss=1%")
    finally:
        srv.close()


@pytest.mark.slow
def test_zenoh_session_through_proxy_loses_link_in_silent_partition_and_recovers_by_itself():
    """A client session (lease 1 s, router lease 1 s) publishing through the proxy; a subscriber
    connected to the router directly. A 2 s silent partition: the session is lost (its router
    link drops after ~ the lease), what is published during it is lost (a seq gap), and after
    it heals the client reconnects by itself and messages flow again."""
    before = proxy_threads()
    clock = Pacer(1.0, 0.0).sim_now
    lease_ms, part_s = 1000, 2.0
    sub_s = pub_s = sub = pub = None
    with Router(lease_ms=lease_ms) as r, TcpProxy(r.endpoints[0], clock=clock, name="zenoh:pub") as p:
        try:
            sub_s = zenoh.open(make_config("client", connect=r.endpoints, lease_ms=lease_ms))
            pub_s = zenoh.open(make_config("client", connect=[p.endpoint], lease_ms=lease_ms))
            sub = sub_s.declare_subscriber("nf/test/seq")
            pub = pub_s.declare_publisher("nf/test/seq", reliability=zenoh.Reliability.RELIABLE)
            # the route exists once a first message gets through (the subscription has to reach
            # the publisher's session first)
            deadline = time.perf_counter() + 5.0
            while sub.try_recv() is None:
                assert time.perf_counter() < deadline, "no route from the publisher to the subscriber"
                pub.put(b"-1")
                time.sleep(0.02)
            time.sleep(0.1)
            while sub.try_recv() is not None:
                pass
            t1 = clock() + 0.8
            t2 = t1 + part_s
            p.set(f"partition={t1}-{t2}")
            sent, got = [], {}
            link_lost_at = recovered_at = None
            i = 0
            while clock() < t2 + 8.0:  # bounded: recovery must come well before
                now = clock()
                pub.put(b"%d" % i)
                sent.append(now)
                i += 1
                while (smp := sub.try_recv()) is not None:
                    got[int(smp.payload.to_bytes())] = clock()
                if link_lost_at is None and t1 <= now < t2 and not list(pub_s.info.routers_zid()):
                    link_lost_at = now
                after = [k for k in got if sent[k] >= t2]
                if after:
                    recovered_at = min(got[k] for k in after)
                    if len(after) >= 10:
                        break
                time.sleep(0.02)
            time.sleep(0.2)
            while (smp := sub.try_recv()) is not None:
                got[int(smp.payload.to_bytes())] = clock()
        finally:
            for x in (sub, pub):
                if x is not None:
                    x.undeclare()
            for s in (pub_s, sub_s):
                if s is not None:
                    s.close()
        st = p.stats()
    sent = np.array(sent)
    missing = sorted(set(range(len(sent))) - set(got))
    # a message put just before t1 can still be in the session's batch or the socket when the
    # partition starts, and is lost with it (seen once in 6 CI runs: the first loss sent < t1):
    # what was sent more than ``inflight`` before must all arrive
    inflight = 0.1
    assert all(k in got for k in np.flatnonzero(sent < t1 - inflight))  # everything before the partition
    assert missing and missing == list(range(missing[0], missing[-1] + 1))  # one gap ...
    assert t1 - inflight <= sent[missing[0]] and sent[missing[-1]] < t2 + 0.1  # ... of what was sent during it
    assert len(missing) >= 0.8 * part_s / 0.02 * 0.5
    assert link_lost_at is not None and link_lost_at - t1 < 2.0 * lease_ms / 1000  # noticed by the lease
    assert recovered_at is not None, "no message flowed after the partition healed"
    recovery_s = recovered_at - t2
    assert recovery_s < 3.0, recovery_s
    assert st.partitions == 1 and st.resets == 0 and st.accepted >= 2  # the client reconnected itself
    print(f"zenoh: link lost {link_lost_at - t1:.2f} s into the partition, recovered "
          f"{recovery_s:.3f} s after it healed, {len(missing)} messages lost")
    assert wait_for(lambda: proxy_threads() == before, 2.0)
    assert tcp_free(p.addr[1])
