"""MAVLink 2 signing across restarts and the time guard (issue 19, items 3 and 8).

A vehicle endpoint keeps its signing state in a file (OUT/mav_signing_<sysid>.json in a live
run): frames captured before a restart -- clean or a crash between two saves -- are rejected
after it, while a GCS's fresh frames pass; a validly signed frame far ahead of the vehicle's
own clock is rejected (``future``) and moves nothing; TIMESYNC / SYSTEM_TIME never move the
clock.  The endpoints here run on a fake wall clock (the composition root's injected clock),
the live test on the real one in a process that is SIGKILLed.
"""
from __future__ import annotations

import json
import os
import select
import signal
import socket
import subprocess
import sys
import time

import pytest
from tests.procs import dead, udp_base, udp_free
from pymavlink.dialects.v20 import ardupilotmega as mav

from vehicles.mavlink import FUTURE_WINDOW_S, SigningStateFile, VehicleEndpoint
from sitl.mavlink.framing import SIGNING_EPOCH_UNIX_S

pytestmark = pytest.mark.live

KEY = bytes(range(32))
QUIET = {k: 0 for k in (0, 1, 2, 24, 30, 33)}  # no streams: only what a test asks for is sent
HEARTBEAT_ONLY = {**QUIET, 0: 1.0}
WALL0 = 1_780_000_000.0  # the fake wall clock's start (2026-05-28), unix s
T0_GPS_S = 1_400_000_000.0  # simulated time: far behind the wall clock, as in a live run


class FakeClock:
    """The wall clock a worker main injects: unix seconds, moved by the test only."""

    def __init__(self, now: float = WALL0):
        self.now = now

    def __call__(self) -> float:
        return self.now

    def ts(self, ahead_s: float = 0.0) -> int:
        return int((self.now + ahead_s - SIGNING_EPOCH_UNIX_S) * 100_000)


class Gcs:
    """A signing GCS on the same wall clock (timestamp max(+1 per frame, clock)) that, as the C
    library and pymavlink do, follows the timestamps of the signed frames it accepts
    (``follow``); frames packed and sent by the test."""

    def __init__(self, clock: FakeClock, key: bytes = KEY, sysid: int = 255, compid: int = 190, link_id: int = 1):
        self.clock = clock
        self.mav = mav.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        s = self.mav.signing
        s.secret_key, s.sign_outgoing, s.link_id, s.timestamp = key, True, link_id, clock.ts()
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))

    def pack(self, msg=None, timestamp: int | None = None) -> bytes:
        s = self.mav.signing
        s.timestamp = max(s.timestamp, self.clock.ts()) if timestamp is None else timestamp
        if msg is None:
            msg = self.mav.heartbeat_encode(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        buf = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        return buf

    def send(self, bufs, to) -> None:
        for b in bufs:
            self.sock.sendto(b, to)

    @property
    def addr(self):
        return self.sock.getsockname()

    def follow(self, wait_s: float = 2.0, until=lambda msgs: True) -> list:
        """Read what the vehicle sent (at most wait_s for until(msgs)); pymavlink checks each
        signature and takes a timestamp ahead of ours."""
        msgs = []
        end = time.monotonic() + wait_s
        while True:
            done = until(msgs)
            r, _, _ = select.select([self.sock], [], [], 0.0 if done else max(0.0, end - time.monotonic()))
            if r:
                msgs += [m for m in self.mav.parse_buffer(self.sock.recv(65535)) or [] if m.get_type() != "BAD_DATA"]
            if (done and not r) or time.monotonic() >= end:
                return msgs

    def close(self) -> None:
        self.sock.close()


def _endpoint(clock, state, gcs, rates=HEARTBEAT_ONLY) -> VehicleEndpoint:
    return VehicleEndpoint(1, "uav", gcs=gcs, listen=("127.0.0.1", 0), signing_key=KEY, clock=clock,
                           signing_state=state, stream_rates_hz=rates)


class Stepper:
    """Steps an endpoint in simulated time until it has read n more datagrams (bounded)."""

    def __init__(self, ep: VehicleEndpoint):
        self.ep = ep
        self.k = 0

    def step(self) -> None:
        self.ep.step(T0_GPS_S + 0.1 * self.k, None)
        self.k += 1

    def until_read(self, n: int, max_wait_s: float = 10.0) -> None:
        target = self.ep.counters["rx_datagrams"] + n
        end = time.monotonic() + max_wait_s
        while self.ep.counters["rx_datagrams"] < target and time.monotonic() < end:
            select.select([self.ep.sock], [], [], 0.05)
            self.step()
        assert self.ep.counters["rx_datagrams"] == target, (self.ep.counters["rx_datagrams"], target)


def _verdicts(ep) -> dict:
    d = ep.datagrams
    return {"accepted": d["accepted"], **{r: n for r, n in d["rejected"].items() if n}}


def _send_fresh(gcs: Gcs, st: Stepper, n: int, batch: int = 500) -> None:
    """n fresh frames in batches, each read before the next (no kernel drop)."""
    for i in range(0, n, batch):
        m = min(batch, n - i)
        gcs.send([gcs.pack() for _ in range(m)], st.ep.listen_addr)
        st.until_read(m)


# ---------------------------------------------------------------------------- restarts
@pytest.mark.parametrize("how", ["clean", "crash"])
def test_frames_captured_before_a_restart_are_all_rejected_after_it(tmp_path, how):
    clock = FakeClock()
    state = tmp_path / "mav_signing_1.json"
    gcs = Gcs(clock)
    ep = _endpoint(clock, state, gcs.addr)
    try:
        st = Stepper(ep)
        st.step()  # the first step writes the state (the bound a few seconds ahead)
        assert state.exists() and ep.counters["signing_saves"] == 1
        captured = [gcs.pack() for _ in range(100)]
        gcs.send(captured, ep.listen_addr)
        st.until_read(100)
        assert _verdicts(ep) == {"accepted": 100}
        if how == "crash":
            # what a SIGKILL leaves: the file as last saved, which does not hold these 100 frames
            # (they were accepted after the save, below the bound it reserved)
            on_disk = SigningStateFile(state, 1).load()
            assert ep.counters["signing_saves"] == 1 and on_disk["streams"] == {}
            snapshot = state.read_bytes()
        ep.close()
        if how == "crash":
            state.write_bytes(snapshot)
        else:
            assert SigningStateFile(state, 1).load()["streams"] == {(1, 255, 190): ep._signer.streams[(1, 255, 190)]}
        clock.now += 3.0  # a restart takes some seconds

        ep = _endpoint(clock, state, gcs.addr)
        st = Stepper(ep)
        st.step()  # its first heartbeat: the GCS follows its timestamp
        assert ep.signing_timestamp > max(int.from_bytes(b[-12:-6], "little") for b in captured)
        assert gcs.follow(until=lambda m: any(x.get_type() == "HEARTBEAT" for x in m))
        gcs.send(captured, ep.listen_addr)
        st.until_read(100)
        assert _verdicts(ep) == {"accepted": 0, "replayed": 100}  # 100 % rejected
        _send_fresh(gcs, st, 10_000)
        assert _verdicts(ep) == {"accepted": 10_000, "replayed": 100}  # 0 fresh frame rejected
        assert ep.datagrams["kernel_dropped"] == 0
    finally:
        ep.close()
        gcs.close()


def test_without_the_state_file_a_restart_accepts_the_replay(tmp_path):
    """The control: what the state file prevents (issue 19 item 3 as reproduced on main)."""
    clock = FakeClock()
    gcs = Gcs(clock)
    ep = _endpoint(clock, None, gcs.addr)
    try:
        st = Stepper(ep)
        captured = [gcs.pack() for _ in range(100)]
        gcs.send(captured, ep.listen_addr)
        st.until_read(100)
        ep.close()
        clock.now += 3.0
        ep = _endpoint(clock, None, gcs.addr)
        st = Stepper(ep)
        gcs.send(captured, ep.listen_addr)
        st.until_read(100)
        assert _verdicts(ep) == {"accepted": 100}
    finally:
        ep.close()
        gcs.close()


def test_the_state_is_renewed_before_the_clock_passes_it_and_a_restart_never_signs_below_it(tmp_path):
    clock = FakeClock()
    gcs = Gcs(clock)
    state = tmp_path / "mav_signing_1.json"
    ep = _endpoint(clock, state, gcs.addr)
    try:
        st = Stepper(ep)
        sent, saved_at = [], []
        for _ in range(300):  # 30 s of wall clock at 10 Hz, a heartbeat every step
            clock.now += 0.1
            n = ep.counters["signing_saves"]
            st.step()
            ep._send_message(0)
            if ep.counters["signing_saves"] > n:
                saved_at.append(clock.now)
            sent.append(ep.signing_timestamp - 1)  # the timestamp the heartbeat carried
            on_disk = SigningStateFile(state, 1).load()
            assert on_disk["reserved"] >= sent[-1]  # on disk before it was sent
        # renewed every few seconds of clock (far more often than the spec's once a minute), not every step
        gaps = [b - a for a, b in zip(saved_at, saved_at[1:])]
        assert len(saved_at) >= 4 and all(3.0 <= g <= 10.0 for g in gaps), saved_at
        # within a step too: a frame signed past the bound (here: the bound just reached) is
        # preceded by a save that covers it
        ep._reserved = ep.signing_timestamp - 1
        ep._save_signing_state(ep._reserved)
        ep._send_message(0)
        sent.append(ep.signing_timestamp - 1)
        assert SigningStateFile(state, 1).load()["reserved"] >= sent[-1]
        snapshot = state.read_bytes()
    finally:
        ep.close()
    state.write_bytes(snapshot)  # a crash
    clock.now -= 20.0  # and a wall clock set back: our timestamps still rise
    ep = _endpoint(clock, state, gcs.addr)
    try:
        Stepper(ep).step()
        assert ep.signing_timestamp > max(sent)
    finally:
        ep.close()
        gcs.close()


def test_a_corrupt_or_foreign_state_file_is_counted_and_the_clock_is_the_floor(tmp_path):
    clock = FakeClock()
    gcs = Gcs(clock)
    old = [gcs.pack(timestamp=clock.ts(-30.0))]  # 30 s old: a new stream would take it
    for content in (b"{not json", json.dumps({"format": "skyfuse.mavlink.signing/1", "sysid": 7, "timestamp": 1,
                                              "reserved": 1, "streams": []}).encode()):
        state = tmp_path / "mav_signing_1.json"
        state.write_bytes(content)
        (tmp_path / "mav_signing_1.json.tmp").write_bytes(b"half a write")  # a crash mid-save: ignored
        ep = _endpoint(clock, state, gcs.addr)
        try:
            assert ep.counters["signing_state_errors"] == 1 and "signing state" in ep.last_error
            st = Stepper(ep)
            st.step()
            gcs.send(old, ep.listen_addr)
            st.until_read(1)
            assert _verdicts(ep) == {"accepted": 0, "replayed": 1}
            assert SigningStateFile(state, 1).load() is not None  # rewritten, valid
        finally:
            ep.close()
    gcs.close()


def test_signing_state_file_round_trip_and_validation(tmp_path):
    f = SigningStateFile(tmp_path / "s.json", 3)
    assert f.load() is None
    f.save(123, 456, {(1, 255, 190): 100, (0, 250, 191): 7})
    assert f.load() == {"timestamp": 123, "reserved": 456, "streams": {(1, 255, 190): 100, (0, 250, 191): 7}}
    assert not (tmp_path / "s.json.tmp").exists()
    with pytest.raises(ValueError, match="system id"):
        SigningStateFile(tmp_path / "s.json", 4).load()
    (tmp_path / "s.json").write_text(json.dumps({"format": "skyfuse.mavlink.signing/1", "sysid": 3,
                                                 "timestamp": 1 << 48, "reserved": 0, "streams": []}))
    with pytest.raises(ValueError, match="48 bits"):
        f.load()


# ---------------------------------------------------------------------------- time guard
def test_a_far_future_signed_frame_is_rejected_counted_and_moves_no_clock(tmp_path):
    clock = FakeClock()
    gcs = Gcs(clock)
    ep = _endpoint(clock, tmp_path / "mav_signing_1.json", gcs.addr, QUIET)
    try:
        st = Stepper(ep)
        st.step()
        ts0 = ep.signing_timestamp
        assert ts0 == clock.ts()
        w = int(FUTURE_WINDOW_S * 100_000)
        far = gcs.pack(timestamp=clock.ts() + w + 100_000)  # 301 s ahead, validly signed
        gcs.send([far], ep.listen_addr)
        st.until_read(1)
        assert _verdicts(ep) == {"accepted": 0, "future": 1} and ep.counters["future"] == 1
        assert ep.signing_timestamp == ts0  # not dragged
        assert ep._signer.streams == {}  # nor recorded: the stream is not locked out
        gcs.mav.signing.timestamp = clock.ts()  # the same GCS, back on the clock
        gcs.send([gcs.pack()], ep.listen_addr)
        st.until_read(1)
        assert _verdicts(ep) == {"accepted": 1, "future": 1}
        # within the window a peer ahead is followed (a GCS a few minutes off, as the spec says) ...
        near = gcs.pack(timestamp=clock.ts() + w - 100_000)  # 299 s ahead
        gcs.send([near], ep.listen_addr)
        st.until_read(1)
        assert ep.signing_timestamp == clock.ts() + w - 100_000
        # ... but the window is measured from our own clock, not from what we followed
        further = gcs.pack(timestamp=clock.ts() + w + 50_000)
        gcs.send([further], ep.listen_addr)
        st.until_read(1)
        assert _verdicts(ep) == {"accepted": 2, "future": 2}
        assert ep.signing_timestamp == clock.ts() + w - 100_000
        # and the persisted state never held a timestamp beyond the window
        assert SigningStateFile(ep._state_file.path, 1).load()["timestamp"] <= clock.ts() + w
    finally:
        ep.close()
        gcs.close()


def test_timesync_and_system_time_from_outside_never_move_the_clock():
    clock = FakeClock()
    gcs = Gcs(clock)
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    ep = _endpoint(clock, None, sink.getsockname(), QUIET)
    try:
        st = Stepper(ep)
        st.step()
        t_sim, unix_s, ts0 = ep._t, ep._unix_s, ep.signing_timestamp
        far_ns = int((WALL0 + 10 * 365 * 86400) * 1e9)  # ten years ahead
        msgs = [gcs.mav.timesync_encode(0, far_ns), gcs.mav.timesync_encode(far_ns, far_ns),
                gcs.mav.system_time_encode(far_ns // 1000, 2**31)]
        # signed 10 ms behind our clock: accepted (a new stream within the minute), nothing to follow
        gcs.send([gcs.pack(m, timestamp=ts0 - 1000 + i) for i, m in enumerate(msgs)], ep.listen_addr)
        select.select([ep.sock], [], [], 0.5)
        time.sleep(0.05)  # loopback: the three datagrams queued
        ep.poll()  # handled at the same simulated time
        assert _verdicts(ep) == {"accepted": 3}
        assert (ep._t, ep._unix_s) == (t_sim, unix_s)
        assert ep.signing_timestamp == ts0 + 1  # the one TIMESYNC answer signed, nothing followed
        # the answer (to the requester) carries our simulated time, the request's ts1 echoed
        got = gcs.follow(2.0, until=lambda m: any(x.get_type() == "TIMESYNC" for x in m))
        reply = [m for m in got if m.get_type() == "TIMESYNC"]
        assert len(reply) == 1 and reply[0]._signed
        assert reply[0].tc1 == int(round(unix_s * 1e9)) and reply[0].ts1 == far_ns
    finally:
        ep.close()
        gcs.close()
        sink.close()


# ---------------------------------------------------------------------------- worker restart (live)
_WORKER = r"""
import json, sys, time
from vehicles.mavlink import VehicleEndpoint
port, state, gcs_port = int(sys.argv[1]), sys.argv[2], int(sys.argv[3])
ep = VehicleEndpoint(1, "uav", gcs=("127.0.0.1", gcs_port), listen=("127.0.0.1", port), signing_key=bytes(range(32)),
                     clock=time.time, signing_state=state, stream_rates_hz={0: 1.0, 1: 0, 2: 0, 24: 0, 30: 0, 33: 0})
t, k = 1.4e9, 0
print(json.dumps({"ready": True}), flush=True)
end = time.monotonic() + 60
while time.monotonic() < end:
    ep.step(t + 0.1 * k, None, budget_s=0.02)
    k += 1
    d = ep.datagrams
    print(json.dumps({"accepted": d["accepted"], "rejected": {r: n for r, n in d["rejected"].items() if n},
                      "kernel_dropped": d["kernel_dropped"], "saves": ep.counters["signing_saves"]}), flush=True)
    time.sleep(0.02)
"""


class _Worker:
    def __init__(self, port, state, gcs_port):
        self.p = subprocess.Popen([sys.executable, "-c", _WORKER, str(port), str(state), str(gcs_port)],
                                  stdout=subprocess.PIPE,
                                  text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        self.last = {}
        assert json.loads(self._line(10.0)) == {"ready": True}

    def _line(self, wait_s):
        r, _, _ = select.select([self.p.stdout], [], [], wait_s)
        assert r, "worker silent"
        return self.p.stdout.readline()

    def until(self, pred, wait_s=20.0):
        end = time.monotonic() + wait_s
        while time.monotonic() < end:
            line = self._line(max(0.1, end - time.monotonic()))
            if line:
                self.last = json.loads(line)
                if pred(self.last):
                    return self.last
        raise AssertionError(f"timed out; last status {self.last}")

    def kill(self):
        if self.p.poll() is None:
            os.kill(self.p.pid, signal.SIGKILL)
        self.p.wait(10)
        self.p.stdout.close()


@pytest.mark.slow
@pytest.mark.live
def test_replay_after_a_sigkilled_worker_restart_is_rejected(tmp_path):
    """A process on the real wall clock, killed with SIGKILL (no close, no final save) and
    started again on the same port and state file: the 100 frames it accepted before are all
    rejected, 10,000 fresh ones all accepted."""
    new_pid = None
    port = udp_base(1)
    state = tmp_path / "mav_signing_1.json"
    clock = FakeClock()
    clock.now = time.time()
    gcs = Gcs(clock)
    w = _Worker(port, state, gcs.addr[1])
    try:
        captured = [gcs.pack() for _ in range(100)]
        gcs.send(captured, ("127.0.0.1", port))
        w.until(lambda s: s["accepted"] + sum(s["rejected"].values()) >= 100)
        assert w.last["accepted"] == 100 and not w.last["rejected"]
        pid = w.p.pid
        w.kill()
        assert dead(pid) and udp_free(port)
        w = _Worker(port, state, gcs.addr[1])
        gcs.send(captured, ("127.0.0.1", port))  # replayed at once, before the GCS has heard the new process
        s = w.until(lambda s: sum(s["rejected"].values()) + s["accepted"] >= 100)
        assert s["rejected"] == {"replayed": 100} and s["accepted"] == 0
        # the GCS hears the restarted vehicle's heartbeat and follows its timestamp (pymavlink
        # and the C library do), then sends on
        new_pid = w.p.pid
        assert gcs.follow(5.0, until=lambda m: any(x.get_type() == "HEARTBEAT" for x in m)
                          and gcs.mav.signing.timestamp > clock.ts())
        for i in range(20):  # 10,000 fresh frames, 500 at a time, on the wall clock
            clock.now = time.time()
            gcs.send([gcs.pack() for _ in range(500)], ("127.0.0.1", port))
            s = w.until(lambda s, n=500 * (i + 1): s["accepted"] + s["kernel_dropped"] >= n)
        assert s["accepted"] == 10_000 and s["rejected"] == {"replayed": 100} and s["kernel_dropped"] == 0
    finally:
        w.kill()
        gcs.close()
    assert new_pid is not None and dead(new_pid) and udp_free(port)


# ---------------------------------------------------------------------------- the worker's wiring
def test_build_endpoints_keeps_each_vehicles_signing_state_in_the_run_directory(tmp_path):
    """vehicles.process.build_endpoints (what a (re)started worker calls): with a key, each
    vehicle's state in OUT/mav_signing_<sysid>.json, on the injected clock; a second build (a
    restarted worker) loads them and signs above them."""
    import numpy as np

    from sitl.bus import InMemoryTransport
    from sitl.scenario import default_scenario
    from vehicles.process import VehicleGroup, _mav_telemetry, build_endpoints

    key = tmp_path / "signing.key"
    key.write_bytes(KEY)
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    scn = default_scenario().replace(mavlink={"gcs": f"127.0.0.1:{sink.getsockname()[1]}", "base_port": udp_base(4),
                                              "tlog": False, "signing_key_file": str(key)})
    clock = FakeClock()
    g = VehicleGroup(scn, [0, 1, 2], InMemoryTransport(), np.random.SeedSequence(1))
    last = {}
    try:
        for incarnation in range(2):
            eps = build_endpoints(g, scn, tmp_path, clock=clock)
            try:
                if incarnation:
                    assert all(ep.signing_timestamp > last[ep.sysid] for ep in eps.endpoints)
                t = scn.run.t0_gps_s + 10.0 * incarnation
                g.step(t)
                eps.step(t, _mav_telemetry(g.telemetry(), len(eps)), budget_s=0.05)
                assert sorted(p.name for p in tmp_path.glob("mav_signing_*.json")) == \
                    [f"mav_signing_{i}.json" for i in (1, 2, 3, 4)]  # 3 UAVs and the sonde
                assert all(ep.signing_timestamp >= clock.ts() for ep in eps.endpoints)  # the wall clock, not 2024
            finally:
                last = {ep.sysid: ep.signing_timestamp for ep in eps.endpoints}
                eps.close()
            clock.now += 5.0
    finally:
        sink.close()
