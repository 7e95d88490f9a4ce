"""sitl.bus.linkstats.LinkMonitor: the ground station's per-link statistics equal the injected
truth (sitl.netfault.KeyFaults on the in-memory bus) exactly -- loss from sequence numbers,
duplicates, reordering, gaps, latency -- and silence is flagged stale and cleared."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sitl.bus import (
    InMemoryTransport,
    LinkMonitor,
    LinkStats,
    Truth,
    UavNav,
    decode,
    encode,
    key_for,
    parse_key,
)
from sitl.netfault import KeyFaults

KEY = "r1/truth/uav/7"  # any kind of message: the monitor reads the header only


def _msg(k: int, t: float, source="uav7") -> Truth:
    return Truth(t_gps_s=t, source_id=source, seq=k, kind="uav", pos_ecef_m=[6.4e6, float(k), 0.0],
                 vel_ecef_m_s=[0.0, 0.0, 0.0])


def _run(spec: str, n: int, dt: float = 0.1, seed: int = 3, clean_tail: int = 5):
    """n messages every dt through KeyFaults(spec) (the first one, and clean_tail more at the
    end, without faults: losses before the first or after the last arrival cannot show in
    sequence numbers); the monitor fed at the transport's arrival time."""
    kf = KeyFaults([("r1/truth/**", "none")], seed=seed)
    bus = InMemoryTransport(faults=[kf])
    mon = LinkMonitor()
    arrivals = []
    bus.subscribe("r1/**", lambda key, m: (mon.observe(key, m, bus.now_s), arrivals.append((m.seq, bus.now_s))))
    for k in range(n + clean_tail):
        t = k * dt
        if k == 1:
            kf.set("r1/truth/**", spec, t)
        if k == n:
            kf.set("r1/truth/**", "none", t)
        bus.drain(t)  # before publishing at t: the clock is each delivery's own time (not t)
        bus.publish(KEY, _msg(k, t))
    bus.drain()
    return kf.truth(KEY), mon, bus, arrivals


def _gaps(truth) -> int:
    """Independent count: accepted first copies (corrupted ones rejected) in delivery order that
    jump past the highest seq so far by more than one."""
    idx, _, bad = truth.delivery_order()
    hi, gaps, seen = -1, 0, set()
    for i in idx[~bad].tolist():
        if i in seen:
            continue
        seen.add(i)
        if hi >= 0 and i > hi + 1:
            gaps += 1
        hi = max(hi, i)
    return gaps


@pytest.mark.parametrize("spec", [
    "loss=20%",
    "gemodel=5%,30%",
    "duplicate=30%",
    "delay=300ms~200ms",
    "delay=200ms reorder=25%",
    "loss=10% duplicate=10% delay=250ms~150ms",
    "partition=20-35 delay=50ms",  # (0.1 s apart: packets 200-349)
])
def test_stats_equal_the_injected_truth(spec):
    n = 800
    truth, mon, bus, _ = _run(spec, n)
    view = truth.receiver_view()
    lk = mon.state("r1", "uav7")
    assert view["highest_seq"] == n + 4 and truth.sent == n + 5  # the clean tail reaches the receiver
    assert lk.received == view["received"]
    assert lk.missing == view["missing"] == truth.dropped  # every loss below the highest seq
    assert lk.duplicates == view["duplicates"] == truth.duplicated
    assert lk.out_of_order == view["out_of_order"] == truth.reordered
    assert lk.gaps == _gaps(truth)
    assert lk.copies == truth.delivered == bus.stats.total.delivered
    # latency: arrival minus send time over every copy (rounding of t + delay - t only)
    assert lk.latency_mean_s == pytest.approx(truth.delay_s_mean, rel=1e-9, abs=1e-12)
    assert lk.latency_max_s == pytest.approx(truth.delay_s_max, rel=1e-9, abs=1e-12)
    # the scenario did something (each spec is tested against a non-trivial truth)
    assert truth.dropped + truth.duplicated + truth.reordered + (truth.delay_s_max > 0) > 0


@pytest.mark.slow
@settings(derandomize=True, database=None, deadline=None, max_examples=15,
          suppress_health_check=[HealthCheck.too_slow])
@given(loss=st.sampled_from([0, 3, 30]), dup=st.sampled_from([0, 10, 60]), delay_ms=st.sampled_from([0, 50, 400]),
       jitter=st.sampled_from([0.0, 0.5, 1.0]), reorder=st.sampled_from([0, 20]), corrupt=st.sampled_from([0, 10]),
       seed=st.integers(0, 2**16))
def test_stats_equal_the_receiver_view_for_any_spec(loss, dup, delay_ms, jitter, reorder, corrupt, seed):
    parts = [f"loss={loss}%" if loss else "", f"duplicate={dup}%" if dup else "",
             f"corrupt={corrupt}%" if corrupt else "",
             f"delay={delay_ms}ms~{jitter * delay_ms:g}ms" if delay_ms else "",
             f"reorder={reorder}%" if reorder and delay_ms else ""]
    spec = " ".join(p for p in parts if p) or "none"
    truth, mon, bus, _ = _run(spec, 300, seed=seed)
    view = truth.receiver_view(reject_corrupted=True)
    lk = mon.state("r1", "uav7")
    assert (lk.received, lk.missing, lk.duplicates, lk.out_of_order, lk.gaps) == \
        (view["received"], view["missing"], view["duplicates"], view["out_of_order"], _gaps(truth))
    assert bus.stats.total.rejected.get("crc", 0) == view["rejected_corrupt"] == truth.corrupted


def test_corrupted_copies_are_rejected_by_the_crc_and_never_counted():
    n = 1500
    truth, mon, bus, arrivals = _run("corrupt=10% duplicate=10% delay=100ms~80ms", n)
    view = truth.receiver_view(reject_corrupted=True)
    assert truth.corrupted > 50
    assert bus.stats.total.rejected == {"crc": truth.corrupted} == {"crc": view["rejected_corrupt"]}
    lk = mon.state("r1", "uav7")
    assert (lk.received, lk.missing, lk.duplicates, lk.out_of_order) == \
        (view["received"], view["missing"], view["duplicates"], view["out_of_order"])
    # latency over the accepted copies, from the schedule (send time = seq * dt)
    idx, at, bad = truth.delivery_order()
    lat = at[~bad] - idx[~bad] * 0.1
    assert lk.latency_mean_s == pytest.approx(lat.mean(), rel=1e-9)
    assert lk.latency_max_s == pytest.approx(lat.max(), rel=1e-9)
    # every accepted copy is bit-identical to what was sent (no flipped float got through)
    for seq, _ in arrivals:
        assert seq < n + 5


def test_streams_of_one_source_are_tracked_apart():
    """A UAV's nav and beacon messages carry the same epoch index: not duplicates."""
    mon = LinkMonitor()
    for k in range(10):
        t = float(k)
        nav = UavNav(t_gps_s=t, source_id="uav1", seq=k, pos_ecef_m=[6.4e6, 0, 0], vel_ecef_m_s=[0, 0, 0],
                     cov=np.eye(6), n_sats=8, fix_type=3)
        mon.observe("r1/uav/1/nav", nav, t + 0.5)
        if k != 4:
            mon.observe("r1/truth/uav/1", _msg(k, t, "uav1"), t + 0.25)
    lk = mon.state("r1", "uav1")
    assert (lk.received, lk.duplicates, lk.missing, lk.gaps, lk.out_of_order) == (19, 0, 1, 1, 0)
    assert lk.latency_max_s == 0.5 and lk.latency_mean_s == pytest.approx((10 * 0.5 + 9 * 0.25) / 19)


def test_silent_link_flagged_stale_after_stale_after_s_and_cleared_on_return():
    kf = KeyFaults([("r1/truth/**", "partition=10-20")], seed=1)
    bus = InMemoryTransport(faults=[kf])
    mon = LinkMonitor(stale_after_s=3.0)
    bus.subscribe("r1/**", lambda key, m: mon.observe(key, m, bus.now_s))
    flips = []
    for k in range(30):
        t = float(k)
        bus.publish(KEY, _msg(k, t))
        bus.drain(t)
        for lk in mon.check(t):
            flips.append((t, lk.stale))
    # last arrival at 9: silent for more than 3 s from 13 on; data back at 20
    assert flips == [(13.0, True), (20.0, False)]
    lk = mon.state("r1", "uav7")
    assert lk.missing == 10 == kf.truth(KEY).dropped_partition and lk.gaps == 1
    key, m = mon.message(lk, 29.0)
    assert key == "r1/gs/link/uav7" and parse_key(key)[1] is LinkStats
    assert decode(encode(m)) == m and (m.received, m.missing, m.stale, m.last_t_gps_s) == (20, 10, False, 29.0)


def test_link_stats_message_before_any_latency_and_bad_config():
    mon = LinkMonitor()
    with pytest.raises(ValueError, match="stale_after_s"):
        LinkMonitor(stale_after_s=0)
    mon.observe(KEY, _msg(0, 5.0), 5.0)
    _, m = mon.message(mon.state("r1", "uav7"), 5.0)
    assert m.latency_mean_s == 0.0 and m.received == 1 and not math.isnan(m.last_t_gps_s)
    assert key_for("r1", m) == "r1/gs/link/uav7"
