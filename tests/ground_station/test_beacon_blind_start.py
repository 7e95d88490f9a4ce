"""The beacon locator's blind start at any time of the demo's run (ground_station.beacon.multilateration).

The demo's three UAVs (2, 4 and 6 km up, a tilted plane) and its beacon (300 m up): the
reflection of the beacon through the UAVs' plane has exactly the same ranges, and over the
blind start's 3 epochs the Dopplers do not tell the sides apart (the costs differ by a few
units either way, by up to ~100 while the beacon turns, sometimes in the mirror's favour). The
ground station's declared search volume in height (GsConfig.beacon_search_height_m) decides:

* with it, a cold start at every 25 s of the run starts on the beacon's side (the truth from the
  scenario's own beacon model, never given to the locator), the mirror refused and counted;
* without it (the same traffic), some starts land on the mirror, kilometres off -- what the
  band is for (and what the strict xfail of the cold restart recorded before it);
* a band that holds both sides refuses neither: the mirror is carried as a second hypothesis and
  the estimate (the two-side mixture) goes out as "ambiguous" until the likelihood test decides."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from ground_station.beacon import BeaconLocator
from ground_station.node import GsConfig, beacon_locator_config
from sitl.app.batch import vehicle_groups
from sitl.bus import BeaconMeasurement, InMemoryTransport, UavGroupEpoch, parse_key
from sitl.scenario import default_scenario

DURATION_S = 300.0
STARTS_S = np.arange(0.0, 276.0, 25.0)
TRACK_S = 30.0  # how long each cold start is followed


def _traffic(seed: int):
    """The demo's beacon measurements per epoch {t: [(key, msg)]} and the beacon's truth {t: pos}."""
    scn = default_scenario().replace(run={"duration_s": DURATION_S, "seed": seed})
    run = scn.run
    bus = InMemoryTransport(synchronous=True, start_t_gps_s=run.t0_gps_s)
    by_t, truth = {}, {}

    def take(key, msg):
        for k, m in (msg.per_uav(parse_key(key)[0]) if type(msg) is UavGroupEpoch else [(key, msg)]):
            if isinstance(m, BeaconMeasurement):
                by_t.setdefault(round(m.t_gps_s, 6), []).append((k, m))

    bus.subscribe("*/uavs/*/epoch", take)
    bus.subscribe(f"{run.id}/uav/*/beacon/*", take)
    bus.subscribe(f"{run.id}/truth/beacon/*", lambda k, m: truth.__setitem__(round(m.t_gps_s, 6),
                                                                             np.array(m.pos_ecef_m)))
    groups = vehicle_groups(scn, bus)
    dt = 1.0 / run.rate_hz
    for k in range(int(math.floor(run.duration_s * run.rate_hz + 1e-9)) + 1):
        t = run.t0_gps_s + k * dt
        for g in groups:
            g.step(t)
        bus.drain(t)
    return run, by_t, truth


@pytest.fixture(scope="module", params=[1, 2], ids=lambda s: f"seed{s}")
def traffic(request):
    return _traffic(request.param)


def _cold(traffic, start_s, config):
    """A locator started cold at t0 + start_s: (error of its first estimate, error after
    TRACK_S, the locator)."""
    run, by_t, truth = traffic
    loc = BeaconLocator(None, run_ids=[run.id], config=config)
    errs = []
    for t in sorted(by_t):
        if not run.t0_gps_s + start_s - 1e-6 <= t <= run.t0_gps_s + start_s + TRACK_S + 1e-6:
            continue
        for k, m in by_t[t]:
            loc.on_message(k, m)
        loc.step(t)
        if loc.initialised[0]:
            errs.append(float(np.linalg.norm(loc.state_ecef()[0][0, 0:3] - truth[t])))
    assert errs, f"no estimate within {TRACK_S} s of a start at t0+{start_s}"
    return errs[0], errs[-1], loc


def test_a_blind_start_at_any_time_of_the_run_is_on_the_beacons_side(traffic):
    cfg = beacon_locator_config(GsConfig())
    assert cfg.search_height_m == (-500.0, 2000.0)
    out = {s: _cold(traffic, s, cfg) for s in STARTS_S}
    print("\nfirst / after 30 s error, m: " + ", ".join(f"t0+{s:.0f}: {a:.0f}/{b:.0f}" for s, (a, b, _) in out.items()))
    for s, (first, last, loc) in out.items():
        assert first < 100.0 and last < 50.0, (s, first, last)
        assert loc.counters["mirror_outside_volume"] == 1 and loc.counters["mirror_hypotheses"] == 0, (s, loc.counters)
        assert loc.estimates()[0][1].mode == "fused"


def test_without_the_declared_band_the_ranges_do_not_decide_the_side(traffic):
    cfg = dataclasses.replace(beacon_locator_config(GsConfig()), search_height_m=())
    first = {s: _cold(traffic, s, cfg)[0] for s in STARTS_S}
    print("\nno band, first error, m: " + ", ".join(f"t0+{s:.0f}: {e:.0f}" for s, e in first.items()))
    assert sum(e > 5000.0 for e in first.values()) >= 2


def test_a_band_that_holds_both_sides_refuses_neither(traffic):
    cfg = dataclasses.replace(beacon_locator_config(GsConfig()), search_height_m=(-500.0, 20000.0))
    _, _, loc = _cold(traffic, 35.0, cfg)
    assert loc.counters["mirror_outside_volume"] == 0 and loc.counters["mirror_hypotheses"] == 1
    assert loc.alt_active[0] and loc.estimates()[0][1].mode == "ambiguous"  # the mixture, side undecided
