"""`skyfuse experiment faults` (issue 8): network faults on the measurement links of the batch
beacon and sonde experiments, scored in real time against a same-seed baseline."""
from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sitl.bus import InMemoryTransport, Truth
from sitl.app.experiments import beacon as be
from sitl.app.experiments import network_faults as fx
from sitl.app.experiments import sonde as so
from sitl.app.experiments.common import MeasurementFaults, measurement_faults

netfault = pytest.importorskip("sitl.netfault")

T0 = 1_400_000_000.0
# short runs (the beacon's locator starts from the prior at epoch 0; its formation resolves by ~30 s)
TINY_BEACON = fx.Setup("beacon", 80.0, 20.0, 40.0, margin_s=20.0)
TINY_SONDE = fx.Setup("sonde", 90.0, 30.0, 50.0, margin_s=20.0)


def _truth(t):
    return Truth(t_gps_s=t, source_id="truth", seq=0, kind="beacon", pos_ecef_m=np.zeros(3), vel_ecef_m_s=np.zeros(3))


def _drop_all(key, payload, t):
    return []


# ------------------------------------------------------------------ the fault layer
def test_faults_reach_the_measurement_keys_only():
    keys = {"r/uav/1/beacon/b1": True, "r/uav/2/beacon/b1": True, "r/uav/1/nav": False,
            "r/truth/beacon/b1": False, "r/gs/estimate/beacon/b1": False, "r/gs/link/uav1": False}
    for faults in ([_drop_all], [("**", "loss=100%")]):
        fl, mf = measurement_faults(faults, be.MEASUREMENT_KEYS, seed=1, t0_gps_s=T0)
        bus = InMemoryTransport(faults=fl, start_t_gps_s=T0)
        got = []
        bus.subscribe("**", lambda k, m, got=got: got.append(k))
        for k in keys:
            bus.publish(k, _truth(T0 + 1.0))
        bus.drain()
        assert sorted(got) == sorted(k for k, meas in keys.items() if not meas)
        assert mf.faulted == 2 and mf.passed == 4
    # sonde: relay and radar faulted, truth and estimates not
    mf = MeasurementFaults([_drop_all], so.MEASUREMENT_KEYS)
    assert mf.is_measurement(f"{so.RUN_ID}/sonde/s0000/relay")
    assert mf.is_measurement(f"{so.RUN_ID}/radar/{so.RADAR_ID}/sonde/s0003")
    assert not mf.is_measurement(f"{so.RUN_ID}/truth/sonde/s0000")
    assert not mf.is_measurement(f"{so.RUN_ID}/gs/estimate/sonde/s0000")
    assert measurement_faults(None, be.MEASUREMENT_KEYS) == ([], None)
    with pytest.raises(TypeError, match="bus_faults"):
        MeasurementFaults([42], be.MEASUREMENT_KEYS)


def test_filters_see_time_since_the_start_and_delays_map_back():
    seen = []

    def late(key, payload, t):
        seen.append(t)
        return [(t + 2.5, payload)]

    fl, _ = measurement_faults([late], be.MEASUREMENT_KEYS, t0_gps_s=T0)
    bus = InMemoryTransport(faults=fl, start_t_gps_s=T0)
    got = []
    bus.subscribe("**", lambda k, m: got.append(bus.now_s - T0))
    bus.publish("r/uav/1/beacon/b1", _truth(T0 + 10.0))
    assert bus.drain(T0 + 12.4) == 0
    assert bus.drain(T0 + 12.5) == 1
    assert seen == [10.0] and got == [12.5]


@settings(max_examples=25, deadline=None)
@given(a=st.integers(0, 50), length=st.integers(1, 40), n=st.integers(1, 100), links=st.integers(1, 3))
def test_a_partition_drops_exactly_what_is_sent_inside_it(a, length, n, links):
    fl, mf = measurement_faults([("**", f"partition={a}-{a + length}")], be.MEASUREMENT_KEYS, seed=3, t0_gps_s=T0)
    bus = InMemoryTransport(faults=fl, start_t_gps_s=T0)
    got = []
    bus.subscribe("**", lambda k, m: got.append((k, m.t_gps_s - T0)))
    for k in range(n):
        for i in range(links):
            bus.publish(f"r/uav/{i + 1}/beacon/b1", _truth(T0 + k))
        bus.publish("r/truth/beacon/b1", _truth(T0 + k))  # never partitioned
    bus.drain()
    inside = [k for k in range(n) if a <= k < a + length]
    tot = mf.totals()
    assert tot["dropped_partition"] == links * len(inside)
    assert tot["sent"] == links * n and tot["links"] == links
    meas = sorted(t for key, t in got if "/beacon/" in key and "/uav/" in key)
    assert meas == sorted(float(k) for k in range(n) if k not in inside for _ in range(links))
    assert sorted(t for key, t in got if key.startswith("r/truth/")) == [float(k) for k in range(n)]


# ------------------------------------------------------------------ specs and metrics
@pytest.mark.parametrize("value", [0.1, 0.2, 0.3, 0.5])
@pytest.mark.parametrize("burst_len", [2.0, 4.0])
def test_burst_spec_has_the_stationary_loss_and_the_mean_burst(value, burst_len):
    plan = fx.Plan(burst_len=burst_len)
    ge = netfault.parse_spec(fx.spec_for("burst_loss", value, plan, fx.SETUPS["beacon"])).ge
    p, r, one_minus_h, one_minus_k = ge
    assert math.isclose(p / (p + r), value, rel_tol=1e-5)
    assert math.isclose(1.0 / r, burst_len, rel_tol=1e-5)
    assert (one_minus_h, one_minus_k) == (1.0, 0.0)
    spec = netfault.parse_spec(fx.spec_for("delay_s", 2.0, plan, fx.SETUPS["beacon"]))
    assert math.isclose(spec.delay_s, 2.0) and math.isclose(spec.jitter_s, 2.0 * plan.jitter_frac)
    spec = netfault.parse_spec(fx.spec_for("partition_s", 30.0, plan, fx.SETUPS["sonde"]))
    assert spec.partitions == ((fx.SETUPS["sonde"].partition_at_s, fx.SETUPS["sonde"].partition_at_s + 30.0),)


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 30), st.integers(1, 4), st.integers(1, 12), st.integers(0, 2**32 - 1))
def test_windowed_mse_is_the_mean_over_the_window(K, T, w, seed):
    rng = np.random.default_rng(seed)
    e2 = rng.exponential(size=(K, T))
    e2[rng.random((K, T)) < 0.2] = np.nan
    got = fx.windowed_mse(e2, w)
    for k in range(K):
        blk = e2[k:k + w]
        fin = blk[np.isfinite(blk)]
        if k + w > K or not fin.size:
            assert np.isnan(got[k])
        else:
            assert math.isclose(got[k], fin.mean(), rel_tol=1e-9)


def test_recovery_of_a_synthetic_error_burst():
    K, h, bad = 120, 50, 5
    t = np.arange(K, dtype=float)
    base = np.ones((K, 2))
    err = base.copy()
    err[h:h + bad] = 100.0  # 10x the baseline error for 5 epochs after the heal
    r = fx.recovery(t, err, base, heal_s=float(h), window_s=10.0, factor=2.0)
    # a 10-epoch window holding one epoch of 100 has mean 10.9 > 2^2: clean from h + 5 on;
    # the window ending at h + s holds a bad epoch while h + s - 9 <= h + 4
    assert r["recovery_s"] == bad and r["recovery_trailing_s"] == bad + 9
    assert math.isclose(r["max_error_after_heal_m"], 10.0)
    never = base.copy()
    never[h:] = 9.0  # 3x to the end
    assert fx.recovery(t, never, base, heal_s=float(h), window_s=10.0, factor=2.0)["recovery_s"] is None
    assert fx.recovery(t, base, base, heal_s=float(h), window_s=10.0, factor=2.0)["recovery_s"] == 0


def test_summary_of_synthetic_runs_targets_and_outliers():
    K, T = 240, 4
    t = np.arange(K, dtype=float)
    setup = fx.Setup("beacon", float(K - 1), 100.0, 150.0, margin_s=10.0)
    fresh = np.ones((K, T), dtype=bool)

    def run(e2):
        return fx.RunResult(t, e2, fresh, {"sent": 10, "dropped_loss": 2, "links": 1}, {}, 0.0)

    base = np.ones((K, T))
    base[:, 3] = 1e4  # trial 3 diverged: 100 m against 1 m
    part = base.copy()
    part[150:180] *= 100.0  # 10x the error while partitioned (150-180 s), the baseline's after
    raw = {"beacon": {"setup": setup, "baseline": run(base), "checks": {},
                      "runs": {("loss", 0.2): ("loss=20%", run(base * 1.44)),
                               ("partition_s", 30.0): ("partition=150-180", run(part))}}}
    s = fx.summarise(raw, fx.Plan(loss=(0.2,), burst_loss=(), delay_s=(), partition_s=(30.0,)))
    loss = next(c for c in s["conditions"] if c["fault"] == "loss" and c["value"] == 0.2)
    assert math.isclose(loss["ratio"], 1.2) and math.isclose(loss["per_trial"]["ratio_median"], 1.2)
    assert loss["link"]["lost_fraction"] == 0.2
    p = next(c for c in s["conditions"] if c["fault"] == "partition_s")
    assert math.isclose(p["rmse_during_partition_m"] / p["baseline_rmse_during_partition_m"], 10.0)
    assert math.isclose(p["rmse_after_heal_m"], p["baseline_rmse_after_heal_m"])
    (rec,) = s["recovery"]
    # windows from the heal on hold no partition epoch; one ending at heal + s holds one while s <= 8
    assert rec["recovery_s"] == 0 and rec["recovery_trailing_s"] == 9 and rec["heal_s"] == 180.0
    assert len(s["targets"]) == 2 and all(tg["met"] for tg in s["targets"])
    assert math.isclose(s["targets"][0]["measured_ratio"], 1.2)
    assert s["baselines"][0]["outlier_trials"] == [3] and s["targets"][0]["baseline_outlier_trials"] == 1


# ------------------------------------------------------------------ the scenarios with faults
@pytest.fixture(scope="module")
def beacon_runner():
    return fx.BeaconRunner(TINY_BEACON, 1, 5)


@pytest.fixture(scope="module")
def beacon_baseline(beacon_runner):
    return beacon_runner(None)


def test_beacon_runs_are_deterministic_for_a_seed(beacon_runner):
    rules = [("**", "gemodel=10%,25%,100%,0% duplicate=10% partition=50-55")]
    a = beacon_runner(rules)
    b = fx.BeaconRunner(TINY_BEACON, 1, 5)(rules)
    assert np.array_equal(a.err2, b.err2, equal_nan=True) and a.link == b.link and a.gs == b.gs
    assert a.link["dropped_loss"] > 0 and a.link["duplicated"] > 0 and a.link["dropped_partition"] > 0


def test_beacon_partition_changes_nothing_before_it_and_drops_its_measurements(beacon_runner, beacon_baseline):
    a, length = TINY_BEACON.partition_at_s, 10.0
    r = beacon_runner([("**", f"partition={a:g}-{a + length:g}")])
    before = beacon_baseline.t_s < a
    assert np.array_equal(r.err2[before], beacon_baseline.err2[before])  # bit for bit
    assert not np.array_equal(r.err2[~before], beacon_baseline.err2[~before])
    # every link sends one measurement per epoch here: L s x 3 UAVs, and exactly those are not accepted
    assert r.link["dropped_partition"] == length * fx.BEACON_UAVS  # one trial
    assert beacon_baseline.gs["accepted"] - r.gs["accepted"] == r.link["dropped_partition"]
    assert r.link["dropped_loss"] == 0 and r.link["sent"] == beacon_baseline.gs["accepted"]


def test_faults_from_leaves_the_run_untouched_before(beacon_runner, beacon_baseline):
    plan = fx.Plan(faults_from_s=30.0)
    r = beacon_runner(fx.bus_faults_for("loss", "loss=100%", plan, 5))
    before = beacon_baseline.t_s < 30.0
    assert np.array_equal(r.err2[before], beacon_baseline.err2[before])
    # from 30 s on nothing arrives: the link truth counts exactly the measurements sent from then
    assert r.link["sent"] == r.link["dropped_loss"] == (TINY_BEACON.duration_s - 30.0 + 1) * fx.BEACON_UAVS
    assert r.gs["accepted"] == beacon_baseline.gs["accepted"] - r.link["sent"]
    # partitions keep their own times
    assert fx.bus_faults_for("partition_s", "partition=40-45", plan, 5) == [("**", "partition=40-45")]


def test_total_loss_leaves_truth_and_estimates_alone(beacon_runner, beacon_baseline):
    r = beacon_runner([("**", "loss=100%")])
    assert r.gs.get("accepted", 0) == 0 and r.link["dropped_loss"] == r.link["sent"] > 0
    # the locator (started from the prior) still publishes every epoch and the truth still arrives
    assert r.fresh.all() and np.isfinite(r.err2).all()
    assert r.gs["published"] == beacon_baseline.gs["published"]


@pytest.mark.slow
def test_sonde_faults_are_seeded_and_apply_to_relay_and_radar():
    scn = so.SondeScenario(duration_s=60.0, white_baseline=False)
    rules = [("**", "loss=30%")]
    a = so.run_trials(scn, 2, [0], modes=("fused",), bus_faults=rules)
    b = so.run_trials(scn, 2, [0], modes=("fused",), bus_faults=rules)
    c = so.run_trials(scn, 2, [0], modes=("fused",), bus_faults=rules, fault_seed=99)
    assert np.array_equal(a["pos"], b["pos"], equal_nan=True) and a["bus_faults"] == b["bus_faults"]
    assert a["bus_faults"] != c["bus_faults"]
    assert a["bus_faults"]["links"] == 2  # the relay and the radar track of the one sonde
    assert a["counters"]["fused"]["messages"] == a["bus_faults"]["delivered"]
    assert np.isfinite(a["truth_pos"]).all()  # the truth is never faulted


# ------------------------------------------------------------------ the command
def _parse(argv):
    p = argparse.ArgumentParser()
    fx.add_args(p)
    return p.parse_args(argv)


@pytest.mark.slow
def test_result_json_on_a_tiny_run(tmp_path, monkeypatch):
    plan = fx.Plan(loss=(0.5,), burst_loss=(), delay_s=(1.0,), partition_s=(5.0,))
    monkeypatch.setattr(fx, "QUICK_PLAN", plan)
    monkeypatch.setattr(fx, "QUICK_SETUPS", {"beacon": TINY_BEACON, "sonde": TINY_SONDE})
    out = tmp_path / "f"
    assert fx.main(_parse(["--out", str(out), "--quick", "--trials", "1", "--quiet"])) == 0
    doc = json.loads((out / "result.json").read_text())
    for key in ("conditions", "recovery", "targets", "checks", "baselines", "seed", "trials", "scenarios", "figures",
                "wall_s"):
        assert key in doc
    assert doc["trials"] == 1 and set(doc["scenarios"]) == {"beacon", "sonde"}
    for c in doc["conditions"]:
        assert {"scenario", "fault", "value", "rmse_m", "baseline_rmse_m"} <= set(c)
        assert c["scenario"] in fx.SCENARIOS and c["fault"] in fx.FAULTS
    for name in fx.SCENARIOS:
        rows = [c for c in doc["conditions"] if c["scenario"] == name]
        assert len(rows) == 3 + len(plan.conditions())  # the fault-free point of three curves + the faults
        base = {c["baseline_rmse_m"] for c in rows}
        assert len(base) == 1 and all(c["rmse_m"] == c["baseline_rmse_m"] for c in rows if c["value"] == 0)
        rec = [r for r in doc["recovery"] if r["scenario"] == name]
        assert [r["partition_s"] for r in rec] == [5.0] and {"recovery_s"} <= set(rec[0])
        loss = next(c for c in rows if c["fault"] == "loss" and c["value"] == 0.5)
        assert loss["link"]["lost"] > 0 and loss["link"]["sent"] > loss["link"]["lost"]
    assert all(c["passed"] for c in doc["checks"])  # duplicates discarded, each counted once
    assert len(doc["targets"]) == 1 and doc["targets"][0]["met"] is None  # no 20 % loss, no 30 s partition run
    for f in doc["figures"]:
        assert (out / f).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert set(doc["figures"]) == set(fx.FIGURES)


@pytest.mark.parametrize("argv, text", [
    (["--scenarios", "beacon,radar"], "--scenarios"),
    (["--scenarios", ","], "--scenarios"),
    (["--duration", "200"], "--duration"),
    (["--burst-len", "0.5"], "--burst-len"),
    (["--faults-from", "5000"], "--duration"),
])
def test_usage_errors(tmp_path, argv, text):
    from sitl.app.args import UsageError

    with pytest.raises(UsageError, match=text):
        fx.run(_parse(["--out", str(tmp_path / "x"), "--quiet", *argv]))
