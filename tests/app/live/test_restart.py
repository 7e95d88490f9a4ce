"""A vehicle worker killed with SIGKILL in the middle of a live run (issue 19): the launcher
restarts it, the restarted worker is a new incarnation whose messages (sequence numbers from 0
again) the ground station takes as new streams, the beacon and sonde estimates are back within
twice their pre-kill error 10 s after the restart (or within twice the error of the same run
never killed, where the run's own error moves more than that), and a replay of the bus log gives
exactly the live estimates."""
from __future__ import annotations

import math
import os
import signal
import threading
import time

import pytest
from tests.procs import dead, udp_base

from sitl.bus import decode, read_bus_log_records
from sitl.app.launcher import launch, replay
from sitl.scenario import default_scenario

pytestmark = [pytest.mark.live, pytest.mark.slow]

pytestmark = [pytest.mark.live, pytest.mark.slow]

SPEED = 8.0
KILL_AT_S = 40.0  # simulated seconds into the run: both estimates have converged


def _rms(series, lo, hi):
    e = [err for t, err in series if lo <= t < hi]
    assert e, (lo, hi)
    return math.sqrt(sum(x * x for x in e) / len(e))


def test_kill_9_of_the_vehicle_worker_restart_recovery_and_exact_replay(tmp_path):
    base = udp_base(4)
    scn = default_scenario().replace(run={"speed": SPEED, "duration_s": 120.0},
                                     mavlink={"gcs": "127.0.0.1:9", "base_port": base})  # discard port
    killed = {}

    def on_started(sup):
        def kill_later():
            time.sleep(KILL_AT_S / SPEED)
            c = sup.children["vehicles0"]  # the UAVs, the beacon and the sonde: every input at once
            killed["pid"] = c.pid
            os.kill(c.pid, signal.SIGKILL)
        threading.Thread(target=kill_later, daemon=True).start()

    report = launch(scn, tmp_path, quiet=True, on_started=on_started)
    assert report["ok"], report.get("error")
    assert report["restarts"] == 1 and "pid" in killed
    assert all(dead(e["pid"]) for e in report["events"] if e["event"] == "start")

    # when the first incarnation fell silent and when the second one spoke (simulated time)
    t0 = scn.run.t0_gps_s
    last_old = first_new = None
    for rec in read_bus_log_records(tmp_path / "bus.log"):
        m = decode(rec.payload)
        if m.source_id == "gs":  # the ground station's own output (never restarted)
            continue
        if m.incarnation == 0:
            last_old = max(last_old or -math.inf, m.t_gps_s - t0)
        elif first_new is None:
            first_new = m.t_gps_s - t0
    assert last_old is not None and first_new is not None and first_new > last_old
    print(f"vehicles0 silent after t = {last_old:.0f} s, its restart publishes from t = {first_new:.0f} s")

    # the ground station took the new incarnation as new streams: no duplicates, one restart per link
    gs = report["workers"]["gs"]["last"]["gs"]
    for src in ("uav1", "uav2", "uav3", "gcpp", "arls1"):
        lk = gs["links"][f"{scn.run.id}/{src}"]
        assert lk["restarts"] == 1 and lk["duplicates"] == 0, (src, lk)
    assert gs["beacon_locator"].get("duplicate", 0) == 0 and gs["sonde_tracker"]["duplicates"] == 0

    # 10 s after the restart both estimates are back within twice their error before the kill --
    # or, where the error of the run itself moves more than that between two 10 s windows (the
    # beacon's 10 s RMS varies 4 m .. 18 m along its racetrack), within twice what the same run
    # never killed has over the same window (batch mode: the same components, seed and world)
    from sitl.app.batch import run_batch
    t0_gps = scn.run.t0_gps_s
    ref = {k: [(t - t0_gps, e) for t, e in v] for k, v in run_batch(scn)["series"].items()}
    for kind in ("beacon/b1", "sonde/s0000"):
        series = report["error_series"][kind]
        before = _rms(series, last_old - 10.0, last_old + 0.5)
        after = _rms(series, first_new + 10.0, first_new + 20.0)
        never_killed = _rms(ref[kind], first_new + 10.0, first_new + 20.0)
        print(f"{kind}: RMS error {before:.2f} m in the 10 s before the kill, {after:.2f} m 10-20 s after the "
              f"restart (never killed: {never_killed:.2f} m)")
        assert after <= 2.0 * max(before, never_killed), (kind, before, after, never_killed)

    # the bus log replays to exactly the live estimates; the GS published an estimate at (nearly) every
    # second its inputs existed: all but the silence between the kill and the restart's first message
    # (which is longer on a loaded machine) and the ~10 s the estimators take to be published again
    rep = replay(tmp_path / "bus.log", scn)
    expected = scn.run.duration_s - (first_new - last_old) - 10.0
    for kind in ("beacon", "sonde"):
        c = rep["vs_live"][kind]
        assert c["matched"] == c["recorded"] >= min(100.0, expected) > 60.0, (c, expected)
        assert c["max_pos_diff_m"] == 0.0, c
