"""The ground station's journal (ground_station.journal) and the exact replay from it.

No process is started: a ground station is run in-process the way ground_station.process runs
it (a tick: the journal's clock, drain, advance journaled, advance), on a transport that hands
each raw payload to the raw subscribers before the decoded delivery (as the Zenoh transport's
drain does), fed from a batch run's bus log with some inputs arriving late at the ground
station only -- its timing is not the recorder's. The estimates it publishes are written into a
copy of the log, as the launcher's recorder would. Then `replay` from the journal gives those
estimates exactly and the recorder-clock replay does not."""
from __future__ import annotations

import json
import math
import struct

import pytest

from ground_station.journal import (
    ADVANCE_KEY,
    HEADER_KEY,
    JournalAdvance,
    JournalError,
    JournalInput,
    JournalStats,
    JournalWriter,
    JournalingTransport,
    config_from_json,
    config_to_json,
    find_journals,
    journal_name,
    open_journal,
    read_journal,
)
from sitl.bus import encode, key_matches
from sitl.bus.buslog import BusLogWriter, read_bus_log_records
from sitl.bus.codec import MAX_PAYLOAD_BYTES
from sitl.scenario import default_scenario
from tests.helpers import RawTapTransport as _Tap

HEADER = {"run_id": "demo", "worker": "gs", "config": {}}


def _events(path):
    st = JournalStats()
    return list(read_journal(path, st)), st


# ------------------------------------------------------------------ the format


def test_what_is_written_reads_back_in_order_with_exact_arguments(tmp_path):
    p = tmp_path / "gs_journal.log"
    ticks = []
    jw = JournalWriter(p, {**HEADER, "incarnation": 0}, t_s=100.0, clock=lambda: ticks.append(1) or 0.0)
    jw.input("demo/uav/1/beacon/b1", b"abc")
    jw.t_s = 100.1
    jw.input("demo/sonde/s0/relay", b"")  # an empty payload is an input too (rejected on replay)
    jw.input("demo/uav/1/beacon/b1", b"x" * (MAX_PAYLOAD_BYTES + 5000))  # over the codec's bound
    jw.advance(0.1 + 0.2, 2.5, 100.30000000000001)
    jw.advance(math.pi, None, None)
    jw.close()
    ev, st = _events(p)
    assert st.header["incarnation"] == 0 and st.header["run_id"] == "demo"
    assert ev[0] == JournalInput(100.0, "demo/uav/1/beacon/b1", b"abc")
    assert ev[1] == JournalInput(100.1, "demo/sonde/s0/relay", b"")
    assert ev[2].payload == b"x" * (MAX_PAYLOAD_BYTES + 1)  # cut, still over the bound: rejected the same
    assert ev[3] == JournalAdvance(100.30000000000001, 0.1 + 0.2, 2.5, 100.30000000000001)
    assert ev[4] == JournalAdvance(100.1, math.pi, None, None)
    assert (st.inputs, st.advances, dict(st.bad)) == (3, 2, {})
    assert jw.status()["truncated"] == 1 and len(ticks) == 2 * 5  # every call timed


def test_advance_is_in_the_kernel_before_it_returns(tmp_path):
    """Write-ahead: what the node will publish after advance() was journaled first (a kill -9
    right after loses nothing: the reader sees it while the writer is still open)."""
    p = tmp_path / "gs_journal.log"
    jw = JournalWriter(p, {**HEADER, "incarnation": 0}, flush_interval_s=1.0)
    jw.input("demo/uav/1/beacon/b1", b"abc")
    jw.advance(1.0, None, 2.0)
    ev, st = _events(p)
    assert [type(e).__name__ for e in ev] == ["JournalInput", "JournalAdvance"] and not st.log.dropped_bytes
    jw.close()


def test_a_torn_tail_ends_the_events_cleanly_at_every_cut(tmp_path):
    p = tmp_path / "gs_journal.log"
    jw = JournalWriter(p, {**HEADER, "incarnation": 0})
    for i in range(5):
        jw.input("demo/uav/1/beacon/b1", bytes([i]) * 40)
        jw.advance(float(i), 2.5, float(i))
    jw.close()
    data = p.read_bytes()
    full, _ = _events(p)
    hdr_end = next(read_bus_log_records(tmp_path / "gs_journal.log"))  # the header record's end:
    hdr_end = 8 + 8 + 8 + 10 + len(HEADER_KEY) + len(hdr_end.payload)  # magic, framing, t + key length
    seen = set()
    for cut in range(len(data) - 1, hdr_end, -7):
        q = tmp_path / "cut.log"
        q.write_bytes(data[:cut])
        ev, st = _events(q)
        assert ev == full[:len(ev)] and len(ev) < len(full)
        assert st.log.valid_bytes + st.log.dropped_bytes == cut
        if st.log.dropped_bytes:  # else the cut fell between two records
            assert st.log.torn_tail and st.log.reason.startswith("torn")
        seen.add(len(ev))
    assert len(seen) >= 8


@pytest.mark.parametrize("content, why", [
    (b"", "no header record"),
    (b"\x00garbage" * 5, "not a skyfuse bus log"),
    (b"SKYFBUS\x07", "version 7"),
])
def test_a_file_that_is_no_journal_is_refused_in_one_line(tmp_path, content, why):
    p = tmp_path / "gs_journal.log"
    p.write_bytes(content)
    with pytest.raises(JournalError, match=why) as ei:
        _events(p)
    assert "\n" not in str(ei.value)


def test_a_bus_log_without_header_or_a_bad_header_is_refused(tmp_path):
    p = tmp_path / "gs_journal.log"
    with BusLogWriter(p, append=False) as w:
        w.append("demo/uav/1/beacon/b1", b"abc", 1.0)
    with pytest.raises(JournalError, match="not the journal header"):
        _events(p)
    for hdr, why in ((b"{not json", "bad header"), (b"[1]", "bad header"),
                     (json.dumps({"format": "skyfuse ground-station journal", "version": 99}).encode(), "version 99"),
                     (json.dumps({"format": "skyfuse ground-station journal", "version": 1, "run_id": "demo",
                                  "incarnation": "0", "config": {}}).encode(), "'incarnation'")):
        with BusLogWriter(p, append=False) as w:
            w.append(HEADER_KEY, hdr, 1.0)
        with pytest.raises(JournalError, match=why):
            _events(p)


def test_framed_records_that_make_no_sense_are_skipped_and_counted(tmp_path):
    p = tmp_path / "gs_journal.log"
    jw = JournalWriter(p, {**HEADER, "incarnation": 0})
    w = jw.writer
    jw.input("demo/uav/1/beacon/b1", b"good")
    w.append(ADVANCE_KEY, b"\x00" * 5, 1.0)  # wrong size
    w.append(ADVANCE_KEY, struct.pack("<ddd", math.nan, 1.0, 1.0), 1.0)  # no t_until
    w.append(ADVANCE_KEY, struct.pack("<ddd", 1.0, -1.0, 1.0), 1.0)  # a negative window
    w.append(ADVANCE_KEY, struct.pack("<ddd", 1.0, 1.0, math.inf), 1.0)  # an infinite clock
    w.append("!what", b"", 1.0)
    w.append("demo/uav/1/beacon/b1", b"late", math.nan)
    jw.advance(2.0, None, 3.0)
    jw.close()
    ev, st = _events(p)
    assert ev == [JournalInput(0.0, "demo/uav/1/beacon/b1", b"good"), JournalAdvance(3.0, 2.0, None, 3.0)]
    assert dict(st.bad) == {"advance of the wrong size": 1, "advance arguments out of range": 3,
                            "unknown control record": 1, "time not finite": 1}


def test_names_per_incarnation_and_a_new_run_removes_the_old_restarts(tmp_path):
    assert journal_name(0) == "gs_journal.log" and journal_name(3) == "gs_journal.r3.log"
    for inc in (0, 2, 10, 1):
        open_journal(tmp_path, inc, HEADER).close()
    (tmp_path / "gs_journal.rx.log").write_bytes(b"")  # not a journal name
    assert [p.name for p in find_journals(tmp_path)] == ["gs_journal.log", "gs_journal.r1.log", "gs_journal.r2.log",
                                                          "gs_journal.r10.log"]
    open_journal(tmp_path, 0, HEADER).close()  # the next run's first ground station
    assert [p.name for p in find_journals(tmp_path)] == ["gs_journal.log"]
    _, st = _events(tmp_path / "gs_journal.log")
    assert st.header["incarnation"] == 0 and st.inputs == 0


def test_the_configuration_round_trips_exactly_through_json():
    from sitl.app.components import gs_config
    for scn in (default_scenario(), default_scenario().replace(sonde={"enabled": False})):
        c = gs_config(scn)
        back = config_from_json(json.loads(json.dumps(config_to_json(c), allow_nan=False)))
        assert back == c
    with pytest.raises(JournalError, match="unknown fields"):
        config_from_json({"nonsense": 1})


def test_journaling_transport_records_each_payload_once_in_delivery_order(tmp_path):
    tap = _Tap()
    jw = JournalWriter(tmp_path / "j.log", {**HEADER, "incarnation": 0})
    jt = JournalingTransport(tap, jw)
    got = []
    jt.subscribe("demo/uav/*/beacon/*", lambda k, m: got.append(k))
    jt.subscribe("demo/uav/1/**", lambda k, m: got.append(k))  # overlaps the first on uav 1
    jt.subscribe("demo/uav/*/beacon/*", lambda k, m: None)  # the same expression again
    payloads = [("demo/uav/1/beacon/b1", b"junk"), ("demo/uav/2/beacon/b1", b"\x93\x01"),
                ("demo/uav/1/nav", b"n"), ("demo/truth/uav/1", b"not ours")]
    for k, p in payloads:
        tap.publish_raw(k, p, 1.0)
    tap.drain()
    jt.close_journaling()
    tap.publish_raw("demo/uav/3/beacon/b1", b"after", 2.0)
    tap.drain()
    jw.close()
    ev, _ = _events(tmp_path / "j.log")
    assert [(e.key, e.payload) for e in ev] == payloads[:3]
    assert jt.stats is tap.stats  # everything else is the real transport's
    assert got == []  # nothing valid was delivered: every payload was junk


# ------------------------------------------------------------------ exact replay of a ground station whose timing is not the recorder's


@pytest.fixture(scope="module")
def batch_log(tmp_path_factory):
    """A batch run's bus log: the world's inputs and truth, stamped with their simulation time."""
    from sitl.app.batch import run_batch
    scn = default_scenario().replace(run={"duration_s": 40.0}, mavlink={"enabled": False})
    d = tmp_path_factory.mktemp("batch")
    run_batch(scn, record=d / "bus.log")
    return scn, d / "bus.log"


def _live_gs_emulated(scn, log, out, *, late_expr, late_window_s, late_by_s, restart_at_s=None):
    """Run ground stations in-process as ground_station.process does (a tick every 0.5 s of its
    clock: journal clock, drain, journaled advance, advance), fed the log's inputs at the
    recorder's times except those on ``late_expr`` inside ``late_window_s`` (since the start),
    which reach the ground station ``late_by_s`` later; ``restart_at_s``: the first ground
    station stops there (its journal closed, no final step) and a second incarnation takes
    over. Writes OUT/bus.log: the log's records plus the estimates the ground stations published,
    at their tick's time (what the launcher's recorder would have). Returns the estimates."""
    from ground_station.node import GroundStationNode
    from sitl.app.components import gs_config

    run, t0 = scn.run, scn.run.t0_gps_s
    inputs = (f"{run.id}/uav/*/beacon/*", f"{run.id}/sonde/*/relay", f"{run.id}/radar/*/sonde/*")
    records = [r for r in read_bus_log_records(log) if not key_matches(f"{run.id}/gs/**", r.key)]  # the batch GS's out
    hold = scn.ground_station.hold_wall_s * run.speed
    t_end = t0 + run.duration_s
    early_window = 2.5 / run.rate_hz
    config = gs_config(scn)
    published = []

    def start(inc, from_s=-math.inf):  # a ground station started at from_s gets what arrives from then on
        tap = _Tap(start_t_gps_s=t0)
        for r in records:
            if any(key_matches(e, r.key) for e in inputs):
                late = key_matches(late_expr, r.key) and late_window_s[0] <= r.t_recv_s - t0 < late_window_s[1]
                arrival = r.t_recv_s + (late_by_s if late else 0.0)
                if arrival >= from_s:
                    tap.publish_raw(r.key, r.payload, arrival)
        jw = open_journal(out, inc, {"run_id": run.id, "worker": "gs", "config": config_to_json(config)}, t_s=t0)
        return tap, jw, GroundStationNode(JournalingTransport(tap, jw), run.id, config, incarnation=inc)

    tap, jw, node = start(0)
    k, inc = 0, 0
    while True:
        clock = t0 + 0.5 * k + 0.25
        k += 1
        if restart_at_s is not None and inc == 0 and clock - t0 >= restart_at_s:
            node.close()
            jw.close()  # killed: no final step
            tap, jw, node = start(1, clock)
            inc = 1
        jw.t_s = clock
        tap.drain(clock)
        now = min(clock, t_end + hold)
        jw.advance(now - hold, early_window, now)
        for key, est in node.advance(now - hold, early_window_s=early_window, now_s=now):
            published.append((clock, key, est))
        if now - hold >= t_end:
            break
    jw.t_s = clock
    tap.drain()
    jw.advance(t_end, None, None)
    for key, est in node.advance(t_end):
        published.append((clock, key, est))
    node.close()
    jw.close()
    merged = sorted([(r.t_recv_s, 0, i, r.key, r.payload) for i, r in enumerate(records)]
                    + [(t, 1, i, key, encode(est)) for i, (t, key, est) in enumerate(published)])
    with BusLogWriter(out / "bus.log", append=False) as w:
        for t, _, _, key, payload in merged:
            w.append(key, payload, t)
    return published


@pytest.mark.slow
def test_replay_from_the_journal_is_exact_where_the_recorder_clock_is_not(batch_log, tmp_path):
    """UAV 3's beacon messages between 10 s and 20 s reach the ground station 8 s after the
    recorder (beyond the hold of 1 s, and beyond the stale limit: hold + lag window 5 s + one
    epoch): it refuses them, the recorder-clock replay uses them."""
    from sitl.app.launcher import replay
    scn, log = batch_log
    pub = _live_gs_emulated(scn, log, tmp_path, late_expr=f"{scn.run.id}/uav/3/beacon/*", late_window_s=(10.0, 20.0),
                            late_by_s=8.0)
    assert len(pub) > 60
    exact = replay(tmp_path / "bus.log", scn)
    derived = replay(tmp_path / "bus.log", scn, use_journal=False)
    assert exact["decisions"] == "journal" and derived["decisions"] == "recorder clock"
    assert exact["ground_station"]["node"]["rejected_stale"] > 0  # as the emulated live one
    for kind in ("beacon", "sonde"):
        e, d = exact["vs_live"][kind], derived["vs_live"][kind]
        assert e["matched"] == e["recorded"] == e["replayed"] > 30 and e["max_pos_diff_m"] == 0.0, e
        assert d["matched"] == d["recorded"], d
    assert derived["vs_live"]["beacon"]["max_pos_diff_m"] > 0.0  # the late UAV's measurements used


@pytest.mark.slow
def test_replay_of_a_restarted_ground_station_uses_one_journal_per_incarnation(batch_log, tmp_path):
    from sitl.app.launcher import replay
    scn, log = batch_log
    pub = _live_gs_emulated(scn, log, tmp_path, late_expr=f"{scn.run.id}/uav/3/beacon/*", late_window_s=(5.0, 15.0),
                            late_by_s=8.0, restart_at_s=22.0)
    assert {est.incarnation for _, _, est in pub} == {0, 1}
    assert [p.name for p in find_journals(tmp_path)] == ["gs_journal.log", "gs_journal.r1.log"]
    exact = replay(tmp_path / "bus.log", scn)
    assert exact["decisions"] == "journal" and [j["incarnation"] for j in exact["journals"]] == [0, 1]
    assert "2 ground-station journals" in exact["decisions_note"]
    for kind in ("beacon", "sonde"):
        e = exact["vs_live"][kind]
        assert e["matched"] == e["recorded"] == e["replayed"] > 30 and e["max_pos_diff_m"] == 0.0, e


@pytest.mark.slow
def test_a_journal_of_another_run_or_garbage_falls_back_to_the_recorder_clock_saying_why(batch_log, tmp_path):
    from sitl.app.launcher import replay
    scn, log = batch_log
    (tmp_path / "bus.log").write_bytes(log.read_bytes())
    open_journal(tmp_path, 0, {"run_id": "another", "worker": "gs", "config": {}}).close()
    r = replay(tmp_path / "bus.log", scn)
    assert r["decisions"] == "recorder clock" and r["decisions_note"] == "journal gs_journal.log is of run 'another', not 'demo'"
    (tmp_path / "gs_journal.log").write_bytes(b"SKYFBUS\x02" + b"\xff" * 30)  # a bus log whose only record is junk
    r = replay(tmp_path / "bus.log", scn)
    assert r["decisions"] == "recorder clock" and r["decisions_note"].startswith("journal not usable: ")
    assert r["vs_live"]["beacon"]["matched"] == r["vs_live"]["beacon"]["recorded"] > 30
    (tmp_path / "gs_journal.log").unlink()
    r = replay(tmp_path / "bus.log", scn)
    assert r["decisions_note"] == "no ground-station journal beside the log"
