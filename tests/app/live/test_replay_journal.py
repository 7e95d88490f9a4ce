"""Replay equals live exactly when the live ground station's timing is not the recorder's.

A live run whose ground station's Zenoh link (``zenoh:gs``, the launcher's TCP fault proxy)
is partitioned for 20 simulated seconds (2 wall s at x10): the bytes are held, so the ground
station takes in that stretch's inputs up to 20 s after the recorder did -- beyond its hold
(10 s) and the stale limit (hold + lag window + one epoch: 16 s), so it refuses some as stale
and processes epochs without them. The recorder saw every one on time. So the replay that
re-derives the ground station's decisions on the recorder's clock gives other estimates (more
of them, and different ones after the partition), while the replay from the ground station's
own journal gives exactly the live ones: every recorded estimate matched, difference 0.0."""
from __future__ import annotations

import shutil

import pytest
from tests.procs import dead, udp_base

from sitl.app.launcher import launch, replay
from sitl.scenario import default_scenario

pytestmark = [pytest.mark.live, pytest.mark.slow]


def test_journal_replay_is_exact_where_the_recorder_clock_replay_is_not(tmp_path, capsys):
    scn = default_scenario().replace(
        run={"speed": 10.0, "duration_s": 60.0},
        mavlink={"gcs": "127.0.0.1:9", "base_port": udp_base(4)},  # discard port
        faults={"links": (("zenoh:gs", "partition=20-40"),), "enabled": True})
    report = launch(scn, tmp_path, quiet=True)
    assert report["ok"], report.get("error")
    assert all(dead(e["pid"]) for e in report["events"] if e["event"] == "start")
    gs = report["workers"]["gs"]["last"]
    # the ground station's timing was not the recorder's: it refused inputs as stale that the
    # recorder had on time (the partition's first seconds, delivered ~20 s late)
    assert gs["gs"]["node"].get("rejected_stale", 0) > 0, gs["gs"]["node"]
    jr = gs["journal"]
    assert jr["path"] == "gs_journal.log" and jr["inputs"] > 200 and jr["advances"] > 20 and not jr.get("errors")
    with capsys.disabled():
        print(f"\njournal: {jr['records']} records, {jr['bytes']} bytes, {1e3 * jr['cost_s']:.1f} ms of the GS main loop "
              f"(GS CPU {gs['cpu_s']:.2f} s)")

    exact = replay(tmp_path / "bus.log", scn)
    assert exact["decisions"] == "journal" and "gs_journal.log" in exact["decisions_note"]
    derived = replay(tmp_path / "bus.log", scn, use_journal=False)
    assert derived["decisions"] == "recorder clock"
    for kind in ("beacon", "sonde"):
        e, d = exact["vs_live"][kind], derived["vs_live"][kind]
        with capsys.disabled():
            print(f"{kind}: journal {e}\n{kind}: recorder clock {d}")
        assert e["matched"] == e["recorded"] == e["replayed"] > 30, e
        assert e["max_pos_diff_m"] == 0.0, e
        # the recorder's clock re-derives other decisions: epochs the live GS never published
        # (their inputs came too late for it), and other estimates after them (on a loaded
        # machine also the reverse: inputs the recorder stamped too late)
        assert d["recorded"] == e["recorded"], d
        assert not (d["matched"] == d["recorded"] == d["replayed"] and d["max_pos_diff_m"] == 0.0), d
    # the journal replay's scoring is the live scorer's (the same estimates against the same truth)
    for name, err in report["errors"].items():
        assert exact["errors"][name]["estimates"] == err["estimates"]
        assert exact["errors"][name]["rmse_m"] == pytest.approx(err["rmse_m"], rel=1e-9)

    # the CLI says which it used
    from sitl.app.cli import main
    capsys.readouterr()
    assert main(["replay", str(tmp_path / "bus.log")]) == 0
    out = capsys.readouterr().out
    assert "decisions: journal (1 ground-station journal: gs_journal.log" in out, out
    assert main(["replay", str(tmp_path / "bus.log"), "--no-journal"]) == 0
    assert "decisions: recorder clock (journal not used (asked))" in capsys.readouterr().out

    # a torn journal tail (a crash mid-write): one line, the valid prefix replayed, no crash; the
    # estimates published before the tear still match exactly
    cut = tmp_path / "cut"
    cut.mkdir()
    shutil.copy(tmp_path / "bus.log", cut / "bus.log")
    data = (tmp_path / "gs_journal.log").read_bytes()
    (cut / "gs_journal.log").write_bytes(data[: len(data) * 2 // 3 - 5])
    torn = replay(cut / "bus.log", scn)
    assert torn["decisions"] == "journal" and "torn tail cut" in torn["decisions_note"], torn["decisions_note"]
    j = torn["journals"][0]
    assert j["torn_tail"]["dropped_bytes"] > 0 and j["torn_tail"]["reason"].startswith("torn")
    for kind in ("beacon", "sonde"):
        c = torn["vs_live"][kind]
        assert 0 < c["matched"] < c["recorded"] and c["max_pos_diff_m"] == 0.0, c
    # garbage in place of the journal: the recorder's clock, saying why
    (cut / "gs_journal.log").write_bytes(b"\x00garbage" * 10)
    fb = replay(cut / "bus.log", scn)
    assert fb["decisions"] == "recorder clock" and "journal not usable" in fb["decisions_note"], fb["decisions_note"]
    assert "\n" not in fb["decisions_note"]
    assert fb["vs_live"]["beacon"]["matched"] > 0


def test_a_ground_station_killed_mid_run_replays_exactly_from_one_journal_per_incarnation(tmp_path):
    """kill -9 of the ground-station worker: the launcher restarts it (incarnation 1), which
    journals to gs_journal.r1.log; the replay runs each incarnation's node from its own journal
    and gives every estimate either published exactly (the first one's up to its last tick: its
    journal is written ahead of what it publishes, so the kill loses none of them)."""
    import os
    import signal
    import threading
    import time

    from ground_station.journal import find_journals

    speed = 10.0
    scn = default_scenario().replace(run={"speed": speed, "duration_s": 90.0},
                                     mavlink={"gcs": "127.0.0.1:9", "base_port": udp_base(4)})
    killed = {}

    def on_started(sup):
        def kill_later():
            time.sleep(35.0 / speed)
            c = sup.children["gs"]
            killed["pid"] = c.pid
            os.kill(c.pid, signal.SIGKILL)
        threading.Thread(target=kill_later, daemon=True).start()

    report = launch(scn, tmp_path, quiet=True, on_started=on_started)
    assert report["ok"], report.get("error")
    assert report["restarts"] == 1 and "pid" in killed
    assert all(dead(e["pid"]) for e in report["events"] if e["event"] == "start")
    assert [p.name for p in find_journals(tmp_path)] == ["gs_journal.log", "gs_journal.r1.log"]
    rep = replay(tmp_path / "bus.log", scn)
    assert rep["decisions"] == "journal" and [j["incarnation"] for j in rep["journals"]] == [0, 1], rep["journals"]
    print(rep["decisions_note"])
    # both incarnations published (the restart takes seconds of warm-up: fewer on a loaded machine)
    from sitl.bus import decode, read_bus_log_records
    incs = {decode(r.payload).incarnation for r in read_bus_log_records(tmp_path / "bus.log") if "/gs/estimate/" in r.key}
    assert incs == {0, 1}, incs
    for kind in ("beacon", "sonde"):
        c = rep["vs_live"][kind]
        print(kind, c)
        assert c["matched"] == c["recorded"] > 20 and c["max_pos_diff_m"] == 0.0, c
    # the restarted ground station resumed from the first one's journal (ground_station.journal.resume):
    # its header says so. It first publishes the epochs the first one had taken in but not yet
    # processed (they were in its journal), then nothing for the seconds it took to start (no
    # ground station subscribed: those inputs are lost to it; the recorder has them), then its own.
    # From 10 s (simulated) after its first estimate of its own on, the beacon and sonde errors
    # against the recorded truth are within 2x those of the 10 s before the kill (a cold, blind
    # start put the beacon 6.6 km RMS off: tests/ground_station/test_gs_restart.py)
    from ground_station.journal import RESUME_KEY, read_journal_header
    assert read_journal_header(tmp_path / "gs_journal.r1.log")[RESUME_KEY] == ["gs_journal.log"]
    said = [ln for p in tmp_path.rglob("gs*.stderr.log") for ln in p.read_text(errors="replace").splitlines()
            if "resumed from gs_journal.log" in ln]
    assert len(said) == 1, said
    print(said[0])
    truth, est = {}, {}
    for r in read_bus_log_records(tmp_path / "bus.log"):
        for kind in ("beacon", "sonde"):
            if f"/truth/{kind}/" in r.key:
                m = decode(r.payload)
                truth[(kind, round(m.t_gps_s, 6))] = m.pos_ecef_m
            elif f"/gs/estimate/{kind}/" in r.key:
                m = decode(r.payload)
                est[(kind, m.incarnation, round(m.t_gps_s, 6))] = m.pos_ecef_m
    import numpy as np
    for kind in ("beacon", "sonde"):
        err = {(inc, t): float(np.linalg.norm(p - truth[(kind, t)])) for (k, inc, t), p in est.items()
               if k == kind and (kind, t) in truth}
        t_kill = max(t for inc, t in err if inc == 0)
        ts = sorted(t for inc, t in err if inc == 1)
        gaps = [(b - a, b) for a, b in zip(ts, ts[1:])]
        t_back = max(gaps)[1] if gaps and max(gaps)[0] > 2.0 else ts[0]  # its first after the start-up's gap
        pre = [e for (inc, t), e in err.items() if inc == 0 and t > t_kill - 10.0]
        post = [e for (inc, t), e in err.items() if inc == 1 and t_back + 10.0 <= t]
        first10 = [e for (inc, t), e in err.items() if inc == 1 and t < t_back + 10.0]
        rms = lambda v: float(np.sqrt(np.mean(np.square(v))))  # noqa: E731
        print(f"{kind}: last GS-0 estimate t0+{t_kill - scn.run.t0_gps_s:.1f} s, first GS-1 estimate of its own "
              f"t0+{t_back - scn.run.t0_gps_s:.1f} s; error RMS 10 s before the kill {rms(pre):.1f} m, "
              f"first 10 s after {rms(first10):.1f} m, from then on {rms(post):.1f} m (max {max(post):.1f} m)")
        assert len(pre) >= 5 and len(post) >= 10, (len(pre), len(post))
        assert max(post) <= 2.0 * max(pre) and rms(post) <= 2.0 * rms(pre), (kind, rms(pre), rms(post), max(post))
