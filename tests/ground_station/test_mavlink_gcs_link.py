"""The ground station's own MAVLink output (GcsLink, system 250): signed when a key is set,
with monotonic timestamps (across a restart too), and ADSB_VEHICLE never raising on an
estimate, however absurd (issue 19, item 3)."""
from __future__ import annotations

import math
import select
import socket
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as m

from ground_station.mavlink_link import GS_SYSID, GcsLink

pytestmark = pytest.mark.live

KEY = bytes(range(32))
WALL0 = 1_780_000_000.0


class FakeClock:
    def __init__(self, now: float = WALL0):
        self.now = now

    def __call__(self) -> float:
        return self.now


def _est(pos, vel=(0.0, 0.0, 0.0)):
    return SimpleNamespace(pos_ecef_m=np.asarray(pos, dtype=float), vel_ecef_m_s=np.asarray(vel, dtype=float))


class Receiver:
    """A pymavlink GCS on loopback, with the key or another one."""

    def __init__(self, key: bytes | None):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.mav = m.MAVLink(None)
        if key is not None:
            self.mav.signing.secret_key = key
        self.raw: list[bytes] = []
        self.refused = 0  # datagrams pymavlink refused (a bad signature raises MAVError)

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
            try:
                out += self.mav.parse_buffer(d) or []
            except m.MAVError:
                self.refused += 1
        return out

    def close(self):
        self.sock.close()


def _ts(buf: bytes) -> int:
    return int.from_bytes(buf[-12:-6], "little")


def test_gs_output_is_signed_and_verified_by_a_pymavlink_receiver_with_the_key():
    good, wrong = Receiver(KEY), Receiver(bytes(32))
    clock = FakeClock()
    links = [GcsLink(good.gcs, signing_key=KEY, clock=clock), GcsLink(wrong.gcs, signing_key=KEY, clock=clock)]
    try:
        for g in links:
            g.adsb("beacon", "b1", _est([4_000_000.0, 3_000_000.0, 3_500_000.0], [10.0, -5.0, 2.0]))
            g.adsb("sonde", "s0000", _est([4_100_000.0, 3_000_000.0, 3_400_000.0]))
            g.statustext("link uav2: stale")
        msgs = good.drain(3)
        assert [x.get_type() for x in msgs] == ["ADSB_VEHICLE", "ADSB_VEHICLE", "STATUSTEXT"]
        assert all(x._signed and x.get_srcSystem() == GS_SYSID for x in msgs)
        assert good.mav.signing.goodsig_count == 3 and good.mav.signing.badsig_count == 0
        assert [x.callsign for x in msgs[:2]] == ["BEAb1", "SONs0000"]
        bad = wrong.drain(3)
        assert len(wrong.raw) == 3 and wrong.refused == 3 and not [x for x in bad if x.get_type() != "BAD_DATA"]
        assert wrong.mav.signing.badsig_count == 3 and wrong.mav.signing.goodsig_count == 0
        # MAVLink 2 frames with the signed flag; timestamps from the clock, rising
        assert all(b[0] == 0xFD and b[2] & 0x01 for b in good.raw)
        ts = [_ts(b) for b in good.raw]
        assert ts == sorted(set(ts)) and ts[0] == int((WALL0 - 1_420_070_400) * 1e5)
    finally:
        for x in (*links, good, wrong):
            x.close()


def test_gs_timestamps_stay_monotonic_across_a_restart_and_follow_the_clock():
    rx = Receiver(KEY)
    clock = FakeClock()
    try:
        g = GcsLink(rx.gcs, signing_key=KEY, clock=clock)
        for _ in range(50):  # a burst: +1 per frame, ahead of a clock that does not move
            g.statustext("burst")
        clock.now += 2.0
        g.statustext("later")  # the clock is ahead now: the timestamp jumps to it
        g.close()
        clock.now += 3.0  # the worker restarts
        g = GcsLink(rx.gcs, signing_key=KEY, clock=clock)
        g.statustext("restarted")
        clock.now -= 0.5  # a small step back of the clock: still rising
        g.statustext("again")
        g.close()
        got = rx.drain(53)
        assert len(got) == 53 and all(x._signed for x in got) and rx.mav.signing.badsig_count == 0
        ts = [_ts(b) for b in rx.raw]
        assert all(b > a for a, b in zip(ts, ts[1:]))
        assert ts[50] == int((WALL0 + 2.0 - 1_420_070_400) * 1e5)
        assert ts[51] == int((WALL0 + 5.0 - 1_420_070_400) * 1e5)
    finally:
        rx.close()


def test_unsigned_without_a_key_and_a_bad_key_is_refused():
    rx = Receiver(None)
    try:
        g = GcsLink(rx.gcs)
        g.statustext("hello")
        g.close()
        (x,) = rx.drain(1)
        assert x.get_type() == "STATUSTEXT" and not x._signed and rx.raw[0][0] == 0xFD
        with pytest.raises(ValueError, match="32 bytes"):
            GcsLink(rx.gcs, signing_key=b"short")
    finally:
        rx.close()


# ---------------------------------------------------------------------------- absurd estimates
ABSURD = [
    ("31,000 km from the centre", [31_000_000.0, 0.0, 0.0], [0.0, 0.0, 0.0], "sent", {"altitude": 1}),
    ("the Earth's centre", [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], "sent", {"altitude": 1}),  # -6378 km
    ("an ordinary fix", [4_000_000.0, 3_000_000.0, 3_500_000.0], [10.0, -5.0, 2.0], "sent", {}),
    ("NaN position", [math.nan, 0.0, 0.0], [0.0, 0.0, 0.0], "non_finite_position", {}),
    ("inf position", [math.inf, 1.0, 1.0], [0.0, 0.0, 0.0], "non_finite_position", {}),
    ("1e300 m", [1e300, 1e300, 1e300], [0.0, 0.0, 0.0], "sent", {"altitude": 1}),
    ("orbital speed", [6_378_137.0, 0.0, 0.0], [0.0, 7_800.0, 0.0], "sent", {"velocity": 1}),
    ("fast climb", [6_378_137.0, 0.0, 0.0], [400.0, 0.0, 0.0], "sent", {"velocity": 1}),
    ("NaN velocity", [6_378_137.0, 0.0, 0.0], [math.nan, 0.0, 0.0], "sent", {"velocity": 1}),
    ("2-vector", [1.0, 2.0], [0.0, 0.0, 0.0], "shape", {}),
]


@pytest.mark.parametrize("name, pos, vel, outcome, clamped", ABSURD, ids=[a[0] for a in ABSURD])
def test_adsb_never_raises_on_an_absurd_estimate(name, pos, vel, outcome, clamped):
    rx = Receiver(KEY)
    g = GcsLink(rx.gcs, signing_key=KEY, clock=FakeClock())
    try:
        g.adsb("beacon", "b1", _est(pos, vel))
        assert dict(g.clamped) == clamped
        if outcome == "sent":
            (x,) = rx.drain(1)
            assert x.get_type() == "ADSB_VEHICLE" and x._signed
            assert bool(x.flags & m.ADSB_FLAGS_VALID_ALTITUDE) == ("altitude" not in clamped)
            assert bool(x.flags & m.ADSB_FLAGS_VALID_VELOCITY) == ("velocity" not in clamped)
            assert g.sent["ADSB_VEHICLE"] == 1 and not g.skipped
        else:
            assert g.skipped == {outcome: 1} and not g.sent
    finally:
        g.close()
        rx.close()


def test_adsb_skips_what_is_not_an_estimate():
    g = GcsLink("127.0.0.1:9", clock=FakeClock())
    try:
        g.adsb("beacon", "b1", None)
        g.adsb("beacon", "b1", SimpleNamespace(pos_ecef_m="abc", vel_ecef_m_s=[0, 0, 0]))
        assert sum(g.skipped.values()) == 2 and not g.sent
    finally:
        g.close()


_floats = st.floats(allow_nan=True, allow_infinity=True, width=64)


@pytest.mark.slow
@settings(max_examples=300, deadline=None, derandomize=True)
@given(st.lists(_floats, min_size=3, max_size=3), st.lists(_floats, min_size=3, max_size=3),
       st.sampled_from(["beacon", "sonde", "x"]), st.text(max_size=12))
def test_adsb_never_raises_hypothesis(pos, vel, kind, target):
    g = GcsLink("127.0.0.1:9", signing_key=KEY, clock=FakeClock())
    frames = []
    g.write = frames.append  # pymavlink writes the packed frame here: captured, not sent
    try:
        g.adsb(kind, target, _est(pos, vel))
        assert g.sent["ADSB_VEHICLE"] + sum(g.skipped.values()) == 1
        if frames:  # what is sent is a well-formed, signed ADSB_VEHICLE
            rx = m.MAVLink(None)
            rx.signing.secret_key = KEY
            (x,) = rx.parse_buffer(frames[0])
            assert x.get_type() == "ADSB_VEHICLE" and x._signed
            assert abs(x.lat) <= 900_000_000 and abs(x.lon) <= 1_800_000_000 and 0 <= x.heading < 36000
    finally:
        g.close()
