"""The pieces a consumer guards its input with: the time window on its own clock
(sitl.bus.timeguard), incarnations in the link statistics, and the run-wide payload audit that
counts every key (sitl.bus.audit)."""
from __future__ import annotations

import dataclasses
import math
import time

import pytest
from tests.sitl.bus.test_bus import beacon, nav

from sitl.bus import InMemoryTransport, LinkMonitor, Router, ZenohTransport, encode, key_for, pack_sealed
from sitl.bus.audit import PayloadAudit, key_kind
from sitl.bus.timeguard import TimeGuard


def test_the_window_is_on_the_consumers_clock_and_its_edges_are_inside():
    g = TimeGuard(ahead_s=2.0, behind_s=6.0)
    assert g.admit(1e12, None)  # no clock yet: nothing to judge by
    now = 1_000.0
    assert g.admit(now + 2.0, now) and g.admit(now - 6.0, now) and g.admit(now, now)
    assert not g.admit(now + 2.0 + 1e-9, now) and not g.admit(now - 6.0 - 1e-9, now)
    assert g.verdict(now + 1e6) == "future" and g.verdict(0.0) == "stale"
    assert g.rejected == {"future": 1, "stale": 1}  # admit counts, verdict does not


def test_the_clock_only_moves_forward_and_never_from_a_message():
    g = TimeGuard(ahead_s=2.0, behind_s=6.0)
    g.tick(100.0)
    assert g.tick(50.0) == 100.0 and g.tick(math.inf) == 100.0 and g.tick(math.nan) == 100.0
    for _ in range(5):
        assert not g.admit(1e9)  # a future message, offered again and again...
    assert g.now_s == 100.0 and g.admit(101.0)  # ...never moved the clock


@pytest.mark.parametrize("bad", [-1.0, math.inf, math.nan, "2", True])
def test_a_bad_window_is_refused(bad):
    with pytest.raises(ValueError, match="ahead_s"):
        TimeGuard(ahead_s=bad, behind_s=1.0)


def test_a_restarted_source_is_a_new_incarnation_not_duplicates():
    mon = LinkMonitor(stale_after_s=3.0)
    key = key_for("r1", nav(), uav=3)
    for seq in range(10):
        assert not mon.observe(key, nav(seq=seq, t_gps_s=1e9 + seq), 1e9 + seq).duplicate
    # the restarted process counts from 0 again, with a new incarnation
    for seq in range(5):
        assert not mon.observe(key, nav(seq=seq, incarnation=1, t_gps_s=1e9 + 20 + seq), 1e9 + 20 + seq).duplicate
    # a repeat within an incarnation is still a duplicate
    assert mon.observe(key, nav(seq=4, incarnation=1, t_gps_s=1e9 + 24), 1e9 + 24.5).duplicate
    lk = mon.state("r1", "uav-3")
    assert (lk.received, lk.duplicates, lk.restarts, lk.incarnation) == (15, 1, 1, 1)
    m = mon.message(lk, 1e9 + 25)[1]
    assert (m.restarts, m.source_incarnation, m.duplicates) == (1, 1, 1)


def test_the_same_numbers_without_a_new_incarnation_are_duplicates():
    """The control: what the ground station did before incarnations."""
    mon = LinkMonitor()
    key = key_for("r1", nav(), uav=3)
    for seq in range(10):
        mon.observe(key, nav(seq=seq), 1e9)
    for seq in range(5):
        mon.observe(key, nav(seq=seq), 1e9)
    assert mon.state("r1", "uav-3").duplicates == 5


def test_refused_messages_are_counted_per_link_and_are_no_sign_of_life():
    mon = LinkMonitor(stale_after_s=3.0)
    key = key_for("r1", nav(), uav=3)
    mon.observe(key, nav(t_gps_s=1e9), 1e9)
    for _ in range(3):
        mon.refused(key, nav(t_gps_s=2e9), "future")
    mon.refused(key, nav(t_gps_s=1.0), "stale")
    changed = mon.check(1e9 + 10.0)
    lk = mon.state("r1", "uav-3")
    assert changed == [lk] and lk.stale  # the far-future copies did not keep it alive
    assert (lk.rejected_future, lk.rejected_stale, lk.received) == (3, 1, 1)
    assert math.isclose(lk.last_t_gps_s, 1e9)


def test_key_kinds():
    assert key_kind("r1/uav/3/nav") == "uav/*/nav"
    assert key_kind("r1/uav/3/beacon/b1") == "uav/*/beacon/*"
    assert key_kind("r1/gs/estimate/sonde/s1") == "gs/estimate/*/*"
    assert key_kind("r1/no/such/thing") == "?"


def test_the_audit_counts_every_payload_once_by_kind_and_reason():
    audit = PayloadAudit()
    good = encode(nav())
    bad_value = pack_sealed({**_wire(nav()), "pos_ecef_m": (b"\x00" * 16 + b"\x00\x00\x00\x00\x00\x00\xf0\x7f")})
    for _ in range(3):
        audit("r1/uav/3/nav", good)
    audit("r1/uav/3/nav", b"\x00garbage")
    audit("r1/uav/3/nav", bad_value)  # +inf in the last component, CRC valid
    audit("r1/uav/1/beacon/b1", encode(beacon()))
    d = audit.as_dict()
    assert d["uav/*/nav"]["accepted"] == 3 and d["uav/*/beacon/*"] == {"accepted": 1, "rejected": {}}
    assert d["uav/*/nav"]["rejected"] == {"crc": 1, "UavNav.pos_ecef_m: not finite": 1}
    assert audit.rejected_total == 2


def _wire(m):
    import msgpack
    return msgpack.unpackb(encode(m), raw=False)


@pytest.mark.live
def test_the_audit_on_a_live_bus_counts_keys_no_component_decodes():
    """The issue's case: malformed payloads on uav/N/nav (which the ground station never
    subscribes to) were counted by nobody."""
    with Router(listen=["tcp/127.0.0.1:0"]) as r:
        sub = ZenohTransport(connect=r.endpoints, lease_ms=2000)
        pub = ZenohTransport(connect=r.endpoints, lease_ms=2000)
        try:
            audit = PayloadAudit()
            sub.subscribe_raw("r1/**", audit)
            key = key_for("r1", nav(), uav=3)
            assert pub.wait_for_subscribers(key, 5.0)
            n_bad, n_good = 50, 20
            for i in range(n_good):
                pub.publish(key, nav(seq=i))
            for _ in range(n_bad):
                pub.publish_raw(key, b"\x93\x01\x02")
            deadline = time.monotonic() + 10.0
            while time.monotonic() < deadline:
                sub.drain()
                if audit.rejected_total + sum(audit.accepted.values()) >= n_bad + n_good:
                    break
                time.sleep(0.02)
            assert audit.as_dict()["uav/*/nav"] == {"accepted": n_good, "rejected": {"crc": n_bad}}
        finally:
            pub.close()
            sub.close()


def test_the_in_memory_transport_clock_is_not_moved_by_a_payloads_time():
    """Replay publishes at the record's time: a far-future message inside the payload leaves the
    in-memory bus's clock (and the delivery order of everything after it) alone."""
    bus = InMemoryTransport(start_t_gps_s=100.0)
    got = []
    bus.subscribe("r1/**", lambda k, m: got.append(m.t_gps_s))
    bus.publish_raw("r1/uav/3/nav", encode(dataclasses.replace(nav(), t_gps_s=1e9)), 101.0)
    bus.publish_raw("r1/uav/3/nav", encode(dataclasses.replace(nav(), t_gps_s=102.0)), 102.0)
    bus.drain(101.5)
    assert got == [1e9] and bus.now_s == 102.0  # the latest publication time, not the payload's 1e9
