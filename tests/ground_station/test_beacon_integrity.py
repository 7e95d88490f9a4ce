"""Issue 6: the integrity monitor in the beacon locator, one channel per UAV link.

* a 5-sigma and a 100 m step on one UAV's range: a ``step`` event on that link within 2
  epochs, no other link excluded beyond the fault-free rate;
* a Doppler outlier burst that the locator's own chi-square gate lets through is caught and
  isolated on its link;
* the events arrive on the in-memory bus, decoded, keyed by the trial's run id;
* detect-only (isolate=False) leaves the estimates bit for bit those of the plain locator;
* fault-free, monitored against plain on the same data: RMSE and ANEES non-inferior;
* stepping the monitor on sub-batches and merging equals stepping the whole batch (the
  "consider" acquisition splits a batch in two calls).
The scene: test_beacon_locator's good geometry (5 UAVs, straight lines), UAV errors white,
locator "inflate" with kappa = 1 (consistent on this data), a prior start.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from tests.ground_station.test_beacon_locator import VAR_R, _scene
from tests.ground_station.test_beacon_locator import _epochs as _beacon_epochs

from filters import metrics
from filters.integrity import IntegrityConfig, IntegrityMonitor
from ground_station.beacon import INTEGRITY, BeaconLocator, LocatorConfig
from ground_station.beacon.integrity import merge_monitor_rows as _mon_merge
from ground_station.beacon.integrity import take_monitor_rows as _mon_take
from sitl.bus import InMemoryTransport, IntegrityEvent, parse_key

SIG_P, SIG_V = 10.0, 0.1  # the UAVs' navigation errors (white), per axis
K, T, K0, LINK = 60, 20, 35, 2  # epochs, trials, first faulty epoch, faulty link (column)


def _epochs(rng, scene, trials):
    return _beacon_epochs(rng, scene, trials, SIG_P, SIG_V)


@pytest.fixture(scope="module")
def data():
    scene = _scene(K)
    eps = _epochs(np.random.default_rng(2026), scene, T)
    x0 = np.concatenate([scene[1][0], scene[2][0]]) + np.array([30.0, -20.0, 10.0, 1.0, -1.0, 0.5])
    return scene, eps, x0


def _config(x0, integrity=None):
    P0 = np.diag([50.0 ** 2] * 3 + [5.0 ** 2] * 3)
    return LocatorConfig(init="prior", prior_mean=tuple(x0), prior_cov=tuple(map(tuple, P0)), uav_error_corr_s=0.0,
                         integrity=integrity)


def _run(config, eps, t):
    bus = InMemoryTransport(synchronous=True)
    got = []
    bus.subscribe("*/gs/integrity/*", lambda key, msg: got.append((key, msg)))
    loc = BeaconLocator(bus, run_ids=[f"r{k}" for k in range(T)], config=config, publish_estimates=False)
    xs, Ps = [], []
    for k, ob in enumerate(eps):
        loc.process(t[k], ob)
        x, P = loc.state_ecef()
        xs.append(x.copy())
        Ps.append(P.copy())
    return np.array(xs), np.array(Ps), loc, got


def _fault(eps, k0, k1, link, d_range=0.0, d_rate=0.0):
    out = []
    for k, ob in enumerate(eps):
        if k0 <= k < k1:
            r, rr = ob.range_m.copy(), ob.range_rate_m_s.copy()
            r[:, link] += d_range
            rr[:, link] += d_rate
            ob = ob._replace(range_m=r, range_rate_m_s=rr)
        out.append(ob)
    return out


def _by_trial(got, kinds, channel=None, other_than=None, t_from=-np.inf):
    """{trial: [times]} of the events of the given kinds."""
    out = {}
    for key, e in got:
        if e.event not in kinds or e.t_gps_s < t_from:
            continue
        if channel is not None and e.channel != channel:
            continue
        if other_than is not None and e.channel == other_than:
            continue
        out.setdefault(int(parse_key(key)[0][1:]), []).append(e.t_gps_s)
    return out


@pytest.fixture(scope="module")
def fault_free(data):
    scene, eps, x0 = data
    return _run(_config(x0), eps, scene[0]), _run(_config(x0, INTEGRITY), eps, scene[0])


@pytest.mark.parametrize("step_sigmas,step_m", [(5.0, None), (None, 100.0)])
def test_range_step_on_one_link_is_isolated_within_two_epochs(data, fault_free, step_sigmas, step_m):
    scene, eps, x0 = data
    t = scene[0]
    # the link's innovation sigma: the nominal sqrt(var_r + u' P_U u) (H P H' adds < 2 % here)
    a = math.sqrt(VAR_R + SIG_P ** 2)
    d = step_sigmas * a if step_m is None else step_m
    assert d >= 5 * a
    x, _P, _loc, got = _run(_config(x0, INTEGRITY), _fault(eps, K0, K, LINK, d_range=d), t)
    ch = f"b1.slot{LINK}"
    steps = _by_trial(got, ("step",), channel=ch, t_from=t[K0])
    delays = np.array([min(steps[k]) - t[K0] if k in steps else np.inf for k in range(T)])
    # jumps on 2 consecutive epochs exclude (persist 2): the second faulty epoch, in every trial
    # (P(|beta| >= 3) >= 0.977 per epoch at 5 sigma: >= 0.955 per trial, 20 trials)
    assert np.mean(delays <= t[K0 + 1] - t[K0]) >= 0.85, delays
    assert np.all(delays <= t[K0 + 4] - t[K0]), delays
    # the right channel: other links are excluded no more often than fault-free over the same epochs
    _, _, _, got_ff = fault_free[1]
    others = sum(len(v) for v in _by_trial(got, ("step", "ramp"), other_than=ch, t_from=t[K0]).values())
    others_ff = sum(len(v) for v in _by_trial(got_ff, ("step", "ramp"), t_from=t[K0]).values())
    assert others <= others_ff + 2, (others, others_ff)
    # the faulty link stays out: the estimate is as good as fault-free and no worse than the plain
    # one (whose own chi-square gate rejects most of a 5-sigma step and all of a 9-sigma one)
    xp, _, _, _ = _run(_config(x0), _fault(eps, K0, K, LINK, d_range=d), t)
    B = scene[1]
    err = lambda xx: float(np.sqrt(np.mean(np.sum((xx[K0:, :, 0:3] - B[K0:, None]) ** 2, axis=-1))))
    x_ff = fault_free[1][0]
    assert err(x) <= 1.1 * err(x_ff), (err(x), err(x_ff))
    assert err(x) <= 1.05 * err(xp), (err(xp), err(x))


def _innovation_sigmas(x0, eps, t, k):
    """sqrt(diag S) (T, N, 2) of epoch k as the monitor sees it (a spy on the locator's judge)."""
    loc = BeaconLocator(None, run_ids=[f"r{i}" for i in range(T)], config=_config(x0, INTEGRITY))
    seen = {}
    judge = loc._judge

    def spy(trial_of_row, n, tt, nu, s, mask, rows=None):
        seen[tt] = np.sqrt(s)
        return judge(trial_of_row, n, tt, nu, s, mask, rows)

    loc._judge = spy
    for i in range(k + 1):
        loc.process(t[i], eps[i])
    return seen[t[k]]


def test_doppler_burst_the_gate_lets_through_is_caught_on_its_link(data, fault_free):
    scene, eps, x0 = data
    t = scene[0]
    # 4.5 sigma on one Doppler for 3 epochs: NIS ~ 20 + 1, mostly under the 2-dof gate (chi2 1e-5: 23.0)
    a = _innovation_sigmas(x0, eps, t, K0)[:, 1, 1]
    bad = _fault(eps, K0, K0 + 3, 1, d_rate=4.5 * a)
    xp, _, lp, _ = _run(_config(x0), bad, t)
    x, _, _loc, got = _run(_config(x0, INTEGRITY), bad, t)
    assert lp.counters["gated"] - fault_free[0][2].counters["gated"] <= 0.5 * 3 * T  # the gate lets most in
    ch = "b1.slot1"
    hit = _by_trial(got, ("outlier", "step"), channel=ch, t_from=t[K0])
    hit = {k: [s for s in v if s <= t[K0 + 2]] for k, v in hit.items()}
    assert sum(1 for v in hit.values() if v) == T, hit
    others = sum(len(v) for v in _by_trial(got, ("step", "ramp"), other_than=ch, t_from=t[K0]).values())
    others_ff = sum(len(v) for v in _by_trial(fault_free[1][3], ("step", "ramp"), t_from=t[K0]).values())
    assert others <= others_ff + 2, (others, others_ff)
    B = scene[1]
    e = lambda xx: float(np.sqrt(np.mean(np.sum((xx[K0:K0 + 10, :, 0:3] - B[K0:K0 + 10, None]) ** 2, -1))))
    assert e(x) < e(xp), (e(x), e(xp))


def test_events_arrive_on_the_bus_decoded(data):
    scene, eps, x0 = data
    _x, _P, loc, got = _run(_config(x0, INTEGRITY), _fault(eps, K0, K, LINK, d_range=200.0), scene[0])
    assert got and loc.counters["integrity_events"] == len(got) == loc.integrity_events.published
    for key, e in got:
        assert isinstance(e, IntegrityEvent)
        run, _, ids = parse_key(key)
        assert e.source_id == "gs.integrity" and ids["channel"] == e.channel and run in loc.run_ids
        assert e.event in ("step", "ramp", "outlier", "readmit") and e.channel.startswith("b1.slot")
    # events are numbered per source from 0
    assert sorted(e.seq for _, e in got) == list(range(len(got)))


def test_detect_only_leaves_the_estimates_unchanged(data):
    scene, eps, x0 = data
    bad = _fault(eps, K0, K, LINK, d_range=200.0)
    xp, Pp, _, _ = _run(_config(x0), bad, scene[0])
    xd, Pd, _loc, got = _run(_config(x0, IntegrityConfig(bias_alpha=None, isolate=False)), bad, scene[0])
    assert np.array_equal(xp, xd) and np.array_equal(Pp, Pd)
    assert any(e.channel == f"b1.slot{LINK}" for _, e in got)


def test_fault_free_no_worse(data, fault_free):
    scene, _eps, _x0 = data
    (xp, Pp, _lp, _), (xm, Pm, lm, got) = fault_free
    B = scene[1]
    k0 = 10
    ep, em = xp[k0:, :, 0:3] - B[k0:, None], xm[k0:, :, 0:3] - B[k0:, None]
    rmse_p, rmse_m = np.sqrt(np.mean(np.sum(ep ** 2, -1))), np.sqrt(np.mean(np.sum(em ** 2, -1)))
    assert rmse_m <= 1.05 * rmse_p, (rmse_m, rmse_p)
    an_p = metrics.nees(ep, Pp[k0:, :, 0:3, 0:3]).mean()
    an_m = metrics.nees(em, Pm[k0:, :, 0:3, 0:3]).mean()
    assert abs(an_m / an_p - 1.0) <= 0.1, (an_m, an_p)
    # the jump test's false alarms: per row-epoch, within the binomial band around P(|N| >= 3)
    rows = 2 * lm.counters["used"]
    n_out = sum(1 for _, e in got if e.event == "outlier")
    p = 2 * 0.5 * math.erfc(3 / math.sqrt(2))
    assert n_out <= rows * p + 4 * math.sqrt(rows * p) + 1, (n_out, rows)


def test_sub_batches_merged_equal_the_whole_batch():
    rng = np.random.default_rng(4)
    mon = IntegrityMonitor(IntegrityConfig(window=4, readmit_after=3))
    Tn, L = 7, 3
    ch = np.repeat(np.arange(L), 2)
    whole = mon.init((Tn,), 2 * L, L)
    split = whole
    a, b = np.array([0, 3, 4]), np.array([1, 2, 5, 6])

    class M:
        def __init__(self, r):
            self.r = r

        def h_and_H(self, x):
            return np.zeros(self.r.shape), np.zeros(self.r.shape + (1,))

        def R_diag(self):
            return self.r

    def noop(x, P, z, gm, **kw):
        return None

    for k in range(20):
        z = rng.standard_normal((Tn, 2 * L))
        z[:, 1] += 6.0 * (5 <= k < 12)  # a step, excluded then readmitted
        z[rng.random((Tn, 2 * L)) < 0.1] = np.nan
        r = np.ones((Tn, 2 * L))
        _, whole, rw = mon.step(whole, np.zeros((Tn, 1)), np.zeros((Tn, 1, 1)), z, M(r), ch, update=noop)
        acc = None
        for idx in (a, b):
            _, sub, _ = mon.step(_mon_take(split, idx), np.zeros((idx.size, 1)), np.zeros((idx.size, 1, 1)), z[idx],
                                 M(r[idx]), ch, update=noop)
            acc = _mon_merge(split, acc, idx, sub)
        split = acc
        for f in ("sum_sq", "sum_b", "jump_run", "excluded", "clean_run"):
            assert np.array_equal(getattr(whole, f), getattr(split, f)), (k, f)
        assert (whole.pos, whole.count, whole.steps) == (split.pos, split.count, split.steps)
        assert all(np.array_equal(u, v) for u, v in zip(whole.ring, split.ring))
        def fresh(st):  # epochs each row's fresh window still has to fill (stale: an epoch number)
            return 0 if st.stale is None else np.maximum(st.stale - st.steps, 0)
        assert np.array_equal(np.broadcast_to(fresh(whole), whole.sum_sq.shape),
                              np.broadcast_to(fresh(split), split.sum_sq.shape)), k
    assert rw is not None


def test_config_checks():
    with pytest.raises(ValueError, match="integrity must be"):
        LocatorConfig(integrity="on")
    with pytest.raises(ValueError, match="integrity_max_links"):
        LocatorConfig(integrity_max_links=0)
    with pytest.raises(ValueError, match="integrity_common_fraction"):
        LocatorConfig(integrity_common_fraction=0.0)


# ---------------------------------------------------------------------------- the experiment


@pytest.mark.slow
def test_experiment_case_isolates_the_injected_faults_and_summarises():
    """sitl/app/experiments/beacon/ with integrity on: a 100 m range step on UAV 2's link and a
    100 m pseudorange step on one of UAV 1's satellites (GPS constellation, printed geometry):
    both isolated on their channels (locator: within 2 epochs; UAV 1's filter: within 10 s),
    the events on the bus reach the summary."""
    from sitl.app.experiments import beacon as be

    trials, dur = 2, 170.0
    tr, prior = be.scenario("printed", 3, dur, trials, np.random.default_rng([5, 77]))
    faults = {"range_step_m": 100.0, "range_step_uav": 2, "pr_step_m": 100.0, "pr_step_uav": 1, "fault_at_s": 120.0}
    res = be.run_case("constellation", tr, trials, 5, locators=(be.PRODUCTION,), central=False, prior=prior,
                      integrity="on", faults=faults)
    ig = be.integrity_summary(None, res, trials)
    assert ig["range_step_isolation"]["rate"] == 1.0 and ig["range_step_isolation"]["delay_s_max"] <= 1.0, ig
    assert ig["range_step_isolation"]["other_links_excluded_after_fault"] == 0, ig
    sat = res["faults"]["pr_step_sat"]
    assert ig["pr_step_isolation"]["channel"] == f"uav1.{sat}" and ig["pr_step_isolation"]["rate"] == 1.0, ig
    assert ig["pr_step_isolation"]["delay_s_max"] <= 10.0, ig
    # every event the locator built arrived on the bus (and the UAVs' too)
    assert res["counters"][be.PRODUCTION]["integrity_events"] == sum(ig["by_source_and_kind"]["locator"].values())
    assert sum(ig["by_source_and_kind"]["uav_nav"].values()) > 0
    with pytest.raises(ValueError, match="integrity"):
        be.run_case("constellation", tr, trials, 5, integrity="maybe")


@pytest.mark.parametrize("flags", [{"integrity": "maybe"}, {"range_step_uav": 4}, {"fault_at_s": -1.0},
                                   {"pr_step_m": math.inf}])
def test_experiment_bad_integrity_options_are_usage_errors(flags):
    import argparse

    from sitl.app.args import UsageError
    from sitl.app.experiments import beacon as be

    a = argparse.Namespace(uavs=3, duration=200.0, uav_counts=[3], **{"integrity": "off", **flags})
    with pytest.raises(UsageError):
        be.check_args(a)


def test_no_exclusion_below_min_links_detects_only(data):
    """integrity_min_links: with every exclusion leaving fewer links than that, the monitor only
    detects -- the estimates are the plain locator's bit for bit, the fault is still reported."""
    import dataclasses

    scene, eps, x0 = data
    bad = _fault(eps, K0, K, LINK, d_range=200.0)
    xp, Pp, _, _ = _run(_config(x0), bad, scene[0])
    cfg = dataclasses.replace(_config(x0, INTEGRITY), integrity_min_links=5)
    xd, Pd, loc, got = _run(cfg, bad, scene[0])
    assert np.array_equal(xp, xd) and np.array_equal(Pp, Pd)
    assert any(e.channel == f"b1.slot{LINK}" and e.event == "step" for _, e in got)
    assert loc.counters["integrity_detect_only"] > 0
    with pytest.raises(ValueError, match="integrity_min_links"):
        LocatorConfig(integrity_min_links=-1)
