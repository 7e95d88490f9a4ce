"""A ground station restarted mid-run (ground_station.journal.resume), in-process.

The demo scenario's traffic (batch: the vehicle groups on the in-memory bus) feeds a ground
station run the way ground_station.process runs it (journal clock, drain, advance journaled,
advance). At t0 + 35 s it is dropped (a kill -9: nothing of it survives but its journal) and a
new incarnation is built:

* resumed from the first one's journal it publishes, from its first tick on, exactly the
  estimates a ground station that was never killed publishes (the reference: that peer, run
  on the same traffic) -- and the replay of its journals (the header names the one it resumed
  from) gives them again;
* started cold (a blind start mid-run), it converges as well: the reflection of the beacon
  through the three UAVs' plane has exactly the same ranges (over the blind start's 3 epochs the
  Dopplers tell the sides apart by less than the noise), and the side is decided by the search
  volume the ground station declares (GsConfig.beacon_search_height_m: the mirror is some 9 km
  up at t0 + 35 s). Before that band it landed on the mirror (RMSE 9,258 m against 11.7 m).
  tests/ground_station/test_beacon_blind_start.py starts it at many more times."""
from __future__ import annotations

import math

import numpy as np

from ground_station import node as gn
from ground_station.journal import (RESUME_KEY, JournalAdvance, JournalStats, JournalingTransport, config_to_json,
                                    open_journal, read_journal, resume, resume_sources)
from sitl.app.batch import vehicle_groups
from sitl.app.components import gs_config
from sitl.bus import InMemoryTransport
from sitl.scenario import default_scenario
from tests.helpers import RawTapTransport as _Tap

KILL_S = 35.0
DURATION_S = 60.0


class _Gs:
    """One ground-station incarnation on the bus, journaled as ground_station.process does."""

    def __init__(self, bus, scn, out_dir, incarnation, *, resumed: bool):
        self.config = gs_config(scn)
        earlier = resume_sources(out_dir, incarnation, scn.run.id) if resumed else []
        self.journal = open_journal(out_dir, incarnation, {"run_id": scn.run.id, "worker": "gs",
                                                           "config": config_to_json(self.config), RESUME_KEY: earlier},
                                    t_s=scn.run.t0_gps_s, fsync=False)
        self.node = gn.GroundStationNode(JournalingTransport(bus, self.journal), scn.run.id, self.config,
                                         incarnation=incarnation)
        self.resumed = resume(self.node, [out_dir / n for n in earlier]) if earlier else {}
        self.published = []

    def tick(self, t):
        self.journal.advance(t, None, None)
        self.published += [(k, e) for k, e in self.node.advance(t)]

    def close(self):
        self.node.close()
        self.journal.close()


def _run(tmp_path, resumed: bool):
    """The demo's traffic to a never-killed ground station (the reference) and to one killed at
    KILL_S and restarted (resumed or cold), both on one bus; their estimates and the truth."""
    scn = default_scenario().replace(run={"duration_s": DURATION_S})
    run = scn.run
    bus = _Tap(start_t_gps_s=run.t0_gps_s)
    truth = {}
    bus.subscribe(f"{run.id}/truth/beacon/*", lambda k, m: truth.__setitem__(round(m.t_gps_s, 6), np.array(m.pos_ecef_m)))
    ref_dir, dut_dir = tmp_path / "ref", tmp_path / "dut"
    ref_dir.mkdir(), dut_dir.mkdir()
    groups = vehicle_groups(scn, bus)
    ref = _Gs(bus, scn, ref_dir, 0, resumed=False)
    first, second = _Gs(bus, scn, dut_dir, 0, resumed=False), None
    dt = 1.0 / run.rate_hz
    for k in range(int(math.floor(run.duration_s * run.rate_hz + 1e-9)) + 1):
        t = run.t0_gps_s + k * dt
        if first is not None and k * dt >= KILL_S - 1e-9:
            first.close()  # a kill -9: its journal is all that is left of it
            killed, first = first, None
            second = _Gs(bus, scn, dut_dir, 1, resumed=resumed)
        for g in groups:
            g.step(t)
        for gs in (ref, first, second):
            if gs is not None:
                gs.journal.t_s = t
        bus.drain(t)
        for gs in (ref, first, second):
            if gs is not None:
                gs.tick(t)
        bus.drain(t)
    for gs in (ref, second):
        gs.close()
    return scn, ref, killed, second, truth, dut_dir


def _beacon(pub):
    return {round(e.t_gps_s, 6): e for k, e in pub if "/estimate/beacon/" in k}


def _sonde(pub):
    return {round(e.t_gps_s, 6): e for k, e in pub if "/estimate/sonde/" in k}


def test_a_ground_station_resumed_from_its_journal_publishes_what_one_never_killed_does(tmp_path):
    scn, ref, killed, second, truth, out = _run(tmp_path, resumed=True)
    t0 = scn.run.t0_gps_s
    assert second.resumed["journals"] == 1 and second.resumed["advances"] > 30 and not second.resumed.get("step_errors")
    for pick in (_beacon, _sonde):
        want, got = pick(ref.published), pick(second.published)
        after = {t: e for t, e in want.items() if t >= t0 + KILL_S}
        assert len(after) >= 20 and set(got) == set(after), (sorted(set(after) ^ set(got))[:5])
        for t, e in after.items():  # the same estimates, bit for bit (another incarnation, another seq)
            assert np.array_equal(got[t].pos_ecef_m, e.pos_ecef_m) and np.array_equal(got[t].cov, e.cov), t
            assert got[t].incarnation == 1 and e.incarnation == 0
    # the estimate is as good as before the kill: the errors after the restart against the truth
    err = {t: float(np.linalg.norm(e.pos_ecef_m - truth[t])) for t, e in _beacon(second.published).items()}
    pre = [float(np.linalg.norm(e.pos_ecef_m - truth[t])) for t, e in _beacon(killed.published).items()
           if t >= t0 + KILL_S - 10]
    post = [v for t, v in err.items() if t <= min(err) + 10]
    print(f"\nbeacon error: 10 s before the kill RMS {np.sqrt(np.mean(np.square(pre))):.1f} m, "
          f"10 s after the restart's first estimate RMS {np.sqrt(np.mean(np.square(post))):.1f} m")
    assert max(post) <= 2.0 * max(pre)

    # the restart's journal names the journal it resumed from, and a replay that resumes the same
    # way gives the same estimates (what sitl.app.launcher.replay does per incarnation)
    st = JournalStats()
    events = list(read_journal(out / "gs_journal.r1.log", st))
    assert st.header[RESUME_KEY] == ["gs_journal.log"]
    bus = InMemoryTransport(synchronous=True, start_t_gps_s=scn.run.t0_gps_s)
    node = gn.GroundStationNode(bus, scn.run.id, second.config, incarnation=1)
    resume(node, [out / n for n in st.header[RESUME_KEY]])
    replayed = []
    for ev in events:
        if isinstance(ev, JournalAdvance):
            replayed += node.advance(ev.t_until_s, early_window_s=ev.early_window_s, now_s=ev.now_s)
        else:
            bus.publish_raw(ev.key, ev.payload, max(ev.t_s, bus.now_s))
    node.close()
    for pick in (_beacon, _sonde):
        a, b = pick(replayed), pick(second.published)
        assert set(a) == set(b) and all(np.array_equal(a[t].pos_ecef_m, b[t].pos_ecef_m) for t in a)


def test_a_cold_blind_start_mid_run_converges(tmp_path):
    scn, ref, killed, second, truth, _ = _run(tmp_path, resumed=False)
    err = [float(np.linalg.norm(e.pos_ecef_m - truth[t])) for t, e in _beacon(second.published).items()]
    ref_err = [float(np.linalg.norm(e.pos_ecef_m - truth[t])) for t, e in _beacon(ref.published).items()
               if t >= scn.run.t0_gps_s + KILL_S]
    print(f"\ncold start at t0+{KILL_S:.0f} s: beacon RMSE {np.sqrt(np.mean(np.square(err))):.0f} m "
          f"(never killed: {np.sqrt(np.mean(np.square(ref_err))):.1f} m)")
    assert np.sqrt(np.mean(np.square(err))) <= 2.0 * np.sqrt(np.mean(np.square(ref_err)))
