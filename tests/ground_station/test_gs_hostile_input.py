"""The ground station against hostile and surprising bus input: a time guard on its own clock,
plausibility checks at decode, other runs' and duplicate messages, and restarted publishers
(bus schema 3's incarnation).

The reference is the same ground station fed the same real inputs without the junk: whatever
the guard and the decoder refuse must leave every published estimate bit-identical."""
from __future__ import annotations

import dataclasses
import math

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from ground_station.node import GroundStationNode, GsConfig
from sitl.app.components import gs_config
from sitl.bus import BusLogWriter, InMemoryTransport, decode, encode, key_matches, pack_sealed
from sitl.bus.schema import POS_MAX_M, T_GPS_MAX_S
from sitl.app.scoring import ErrorTracker
from sitl.scenario import default_scenario
from vehicles.process import VehicleGroup

DURATION_S = 60.0
SCN = default_scenario().replace(run={"duration_s": DURATION_S})
RUN = SCN.run.id
INPUTS = (f"{RUN}/uav/*/beacon/*", f"{RUN}/sonde/*/relay", f"{RUN}/radar/*/sonde/*")  # what the GS takes in


def _capture(records):
    """A fault filter that records what is published (t, key, payload) and lets it through."""
    def f(key, payload, t):
        records.append((t, key, payload))
        return [(t, payload)]
    return f


def _epoch_times(scn):
    dt = 1.0 / scn.run.rate_hz
    return [scn.run.t0_gps_s + k * dt for k in range(int(scn.run.duration_s * scn.run.rate_hz) + 1)]


@pytest.fixture(scope="module")
def clean():
    """One run of the default scenario's vehicles: every payload it published, by epoch."""
    recs = []
    bus = InMemoryTransport(start_t_gps_s=SCN.run.t0_gps_s, faults=[_capture(recs)])
    g = VehicleGroup(SCN, list(range(SCN.uavs.count)), bus, np.random.SeedSequence([SCN.run.seed, 1000]))
    for t in _epoch_times(SCN):
        g.step(t)
        bus.drain(t)
    bus.close()
    by_epoch: dict = {}
    for t, key, payload in recs:
        by_epoch.setdefault(round(t, 6), []).append((key, payload))
    return by_epoch


def _gs(by_epoch, junk=(), *, scn=SCN):
    """The ground station node on an in-memory bus fed each epoch's payloads, then the junk of
    that epoch ((epoch index, key, payload) items), stepped under the live rule (an epoch is
    processed once complete, or hold_wall_s x speed after its time; ground_station.process);
    returns (estimates [(key, t, pos, cov)], node stats)."""
    bus = InMemoryTransport(start_t_gps_s=scn.run.t0_gps_s)
    cfg = gs_config(scn)
    node = GroundStationNode(bus, scn.run.id, cfg)
    early = 2.5 / scn.run.rate_hz
    got = []
    bus.subscribe(f"{scn.run.id}/gs/estimate/**", lambda k, m: got.append((k, m.t_gps_s, m.pos_ecef_m, m.cov)))
    extra: dict = {}
    for k, key, payload in junk:
        extra.setdefault(k, []).append((key, payload))
    for k, t in enumerate(_epoch_times(scn)):
        for key, payload in by_epoch.get(round(t, 6), ()):
            bus.publish_raw(key, payload, t)
        for key, payload in extra.get(k, ()):
            bus.publish_raw(key, payload, t)
        bus.drain(t)
        node.advance(t - cfg.hold_s, early_window_s=early, now_s=t)
        bus.drain(t)
    node.flush()
    bus.drain()
    stats = node.stats()
    node.close()
    bus.close()
    return got, stats


def _same(a, b) -> bool:
    return len(a) == len(b) and all(ka == kb and ta == tb and np.array_equal(pa, pb) and np.array_equal(ca, cb)
                                    for (ka, ta, pa, ca), (kb, tb, pb, cb) in zip(a, b))


@pytest.fixture(scope="module")
def reference(clean):
    est, stats = _gs(clean)
    kinds = {k.rsplit("/", 2)[-2] for k, *_ in est}
    assert kinds == {"beacon", "sonde"} and len(est) > 100  # both targets tracked
    return est


def _inputs_of(by_epoch, k):
    t = _epoch_times(SCN)[k]
    return [(key, payload) for key, payload in by_epoch.get(round(t, 6), ()) if any(key_matches(e, key) for e in INPUTS)]


def _retimed(payload: bytes, t: float, seq_offset: int = 10**9) -> bytes:
    """The same message at another time with a sequence number never used (not a duplicate)."""
    m = decode(payload)
    return encode(dataclasses.replace(m, t_gps_s=t, seq=m.seq + seq_offset))


def _with_field(payload: bytes, name: str, value) -> bytes:
    """The payload with one field replaced on the wire, CRC re-sealed (so that only the schema
    can refuse it)."""
    obj = msgpack.unpackb(payload, raw=False)
    if isinstance(value, np.ndarray):
        value = value.astype("<f8").tobytes()
    obj[name] = value
    return pack_sealed(obj)


# ---------------------------------------------------------------------------------------- the case


def test_a_far_future_message_changes_nothing_and_is_counted(clean, reference):
    k = 30
    key, payload = next((kk, p) for kk, p in _inputs_of(clean, k) if "/uav/1/beacon/" in kk)
    t = _epoch_times(SCN)[k]
    junk = [(k, key, _retimed(payload, t + 1e6))]
    est, stats = _gs(clean, junk)
    assert _same(est, reference)  # every later estimate still published, bit for bit
    assert stats["node"]["rejected_future"] == 1
    assert stats["links"][f"{RUN}/uav1"]["rejected_future"] == 1


def test_without_a_time_guard_the_far_future_message_blinds_the_ground_station(clean, reference):
    """The control: with the window opened wide, the issue's failure comes back (estimates stop)."""
    k = 30
    key, payload = next((kk, p) for kk, p in _inputs_of(clean, k) if "/uav/1/beacon/" in kk)
    t = _epoch_times(SCN)[k]
    scn = SCN.replace(ground_station={"max_ahead_s": 3600.0})
    junk = [(k, key, _retimed(payload, t + 1000.0))]
    est, stats = _gs(clean, junk, scn=scn)
    assert not _same(est, reference)
    # the junk became an epoch of its own: a beacon estimate 1000 s past the run (before the guard
    # the live rule also processed it at once, and every real input after it counted as late)
    t_end = SCN.run.t0_gps_s + SCN.run.duration_s
    assert any(t > t_end + 900.0 for _, t, *_ in est)


# ---------------------------------------------------------------------------------------- the property

KINDS = ("future", "past", "absurd", "nonfinite", "other_run", "duplicate")
junk_specs = st.tuples(st.integers(5, int(DURATION_S) - 5), st.integers(0, 10**6), st.sampled_from(KINDS),
                       st.floats(1e-3, 1e9), st.integers(0, 10**6), st.integers(0, 3))


def _junk(by_epoch, spec):
    """One piece of junk: a real input of epoch k turned into something the ground station must
    refuse -- far ahead of its clock, far behind it, an absurd or non-finite value sealed with a
    valid CRC, another run's copy, or a changed duplicate of a message already taken (later)."""
    k, pick, kind, d, where, later = spec
    inputs = _inputs_of(by_epoch, k)
    key, payload = inputs[pick % len(inputs)]
    t = _epoch_times(SCN)[k]
    cfg = GsConfig.from_scenario(SCN)
    if kind == "future":
        return k, key, _retimed(payload, min(t + cfg.max_ahead_s + d, T_GPS_MAX_S))
    if kind == "past":
        return k, key, _retimed(payload, max(t - cfg.max_behind_s - d, 0.0))
    m = decode(payload)
    if kind in ("absurd", "nonfinite"):
        arrays = [s.name for s in m.FIELDS if s.ftype == "array" and getattr(m, s.name).size]
        name = arrays[where % len(arrays)]
        bad = ((1.0001, 10.0, 1e100)[where % 3] * POS_MAX_M if kind == "absurd"
               else (math.nan, math.inf, -math.inf)[where % 3])
        a = np.array(getattr(m, name), dtype=float)
        a.flat[where % a.size] = bad
        return k, key, _with_field(payload, name, a)
    if kind == "other_run":
        return k, "other" + key[len(RUN):], payload
    # a changed duplicate: same source, incarnation and seq, another value, at most 3 epochs later
    changed = dataclasses.replace(m, range_m=m.range_m + 500.0) if hasattr(m, "range_m") else m
    return min(k + later, int(DURATION_S)), key, encode(changed)


FAST = settings(derandomize=True, database=None, deadline=None, max_examples=10, phases=[Phase.generate],
                suppress_health_check=[HealthCheck.too_slow])


@pytest.mark.slow
def test_refused_junk_never_changes_a_published_estimate(clean, reference):
    @FAST
    @given(st.lists(junk_specs, min_size=1, max_size=12))
    def check(specs):
        junk = [_junk(clean, s) for s in specs]
        est, stats = _gs(clean, junk)
        assert _same(est, reference)
        n, kinds = stats["node"], [s[2] for s in specs]
        assert n.get("rejected_future", 0) == kinds.count("future")  # each counted once, by reason
        assert n.get("rejected_stale", 0) == kinds.count("past")
    check()


# ---------------------------------------------------------------------------------------- replay


def test_replay_of_a_log_with_a_far_future_record_gives_the_clean_estimates(clean, tmp_path):
    from sitl.app.batch import run_batch
    from sitl.app.launcher import replay
    log = tmp_path / "bus.log"
    run_batch(SCN, record=log)
    ref = replay(log, SCN)
    # a far-future beacon measurement recorded at t0 + 30 s (the clock the launcher had)
    k = 30
    key, payload = next((kk, p) for kk, p in _inputs_of(clean, k) if "/uav/2/beacon/" in kk)
    t = _epoch_times(SCN)[k]
    with BusLogWriter(log, append=True, clock=lambda: t) as w:
        w.append(key, _retimed(payload, t + 1e6))
    # appended at the end: the replay reads it last; put one in the middle too
    bad = tmp_path / "bad.log"
    from sitl.bus import read_bus_log_records
    with BusLogWriter(bad, append=False) as w:
        for i, rec in enumerate(read_bus_log_records(log)):
            w.append(rec.key, rec.payload, rec.t_recv_s)
            if i == 200:
                w.append(key, _retimed(payload, rec.t_recv_s + 1e6), rec.t_recv_s)
    res = replay(bad, SCN)
    assert res["ground_station"]["node"]["rejected_future"] == 2
    for kind in ("beacon", "sonde"):
        assert res["errors"][f"{kind}/{'b1' if kind == 'beacon' else 's0000'}"] == \
            ref["errors"][f"{kind}/{'b1' if kind == 'beacon' else 's0000'}"]
        assert res["vs_live"][kind]["max_pos_diff_m"] == 0.0
        assert res["vs_live"][kind]["matched"] == res["vs_live"][kind]["recorded"]


# ---------------------------------------------------------------------------------------- restarts


def _run_with_restart(kill_k: int, gap: int, new_incarnation: bool):
    """The default scenario's vehicle group dies at epoch kill_k and a new one (the restarted
    worker: same seeds, its epoch count and sequence numbers from 0) joins gap epochs later;
    the ground station and a scorer on the same bus. Returns (errors {kind: [(t, e)]}, node stats)."""
    scn = SCN.replace(run={"duration_s": 120.0})
    bus = InMemoryTransport(start_t_gps_s=scn.run.t0_gps_s)
    scorer = ErrorTracker(keep_s=1e9, t0_gps_s=scn.run.t0_gps_s, clock=lambda: bus.now_s)
    scorer.subscribe(bus, scn.run.id)
    node = GroundStationNode(bus, scn.run.id, gs_config(scn))
    seq = lambda: np.random.SeedSequence([scn.run.seed, 1000])  # noqa: E731  (the worker's own)
    idx = list(range(scn.uavs.count))
    g = VehicleGroup(scn, idx, bus, seq())
    for k, t in enumerate(_epoch_times(scn)):
        if k == kill_k:
            g = None
        if k == kill_k + gap:
            g = VehicleGroup(scn, idx, bus, seq(), incarnation=1 if new_incarnation else 0)
        if g is not None:
            g.step(t)
        bus.drain(t)
        node.advance(t)
        bus.drain(t)
    out = {kind: [(t - scn.run.t0_gps_s, e) for t, e in pts] for (kind, _), pts in scorer.series.items()}
    stats = node.stats()
    node.close()
    bus.close()
    return out, stats


def _rms(pts, lo, hi):
    e = [e for t, e in pts if lo <= t < hi]
    return math.sqrt(sum(x * x for x in e) / len(e))


def test_a_restarted_vehicle_group_is_a_new_stream_and_the_estimates_recover():
    kill, gap = 60, 8
    errs, stats = _run_with_restart(kill, gap, new_incarnation=True)
    back = kill + gap
    for kind in ("beacon", "sonde"):
        before = _rms(errs[kind], kill - 10, kill)
        after = _rms(errs[kind], back + 10, back + 20)  # 10 s after the restart
        assert after <= 2.0 * before, (kind, before, after)
    assert stats["beacon_locator"].get("duplicate", 0) == 0
    assert stats["sonde_tracker"]["duplicates"] == 0
    links = stats["links"]
    assert links[f"{RUN}/uav1"]["restarts"] == 1 and links[f"{RUN}/uav1"]["incarnation"] == 1
    assert links[f"{RUN}/uav1"]["duplicates"] == 0


def test_without_a_new_incarnation_the_restarted_groups_messages_are_dropped_as_duplicates():
    """The control (the issue's failure): the same restart with the old incarnation."""
    kill, gap = 60, 8
    errs, stats = _run_with_restart(kill, gap, new_incarnation=False)
    assert stats["beacon_locator"]["duplicate"] > 100
    assert stats["sonde_tracker"]["duplicates"] > 50
