"""Measurement fault injection and Gauss-Markov sensor errors (sitl/measfault.py)."""
import math

import numpy as np
import pytest
import scipy.stats

from sitl.measfault import FAULT_KINDS, Fault, FaultInjector, GaussMarkov


def _run(faults, trials=3, C=4, epochs=50, dt=1.0, seed=0):
    rng = np.random.default_rng(seed)
    inj = FaultInjector(faults, (trials,), C)
    clean = np.arange(epochs)[:, None, None] * 10.0 + np.arange(C)[None, None, :] + np.zeros((1, trials, 1))
    out, info = [], []
    for k in range(epochs):
        z, inf = inj.step(rng, k * dt, clean[k])
        out.append(z)
        info.append(inf)
    return clean, np.array(out), info


def test_step_and_ramp_hit_only_their_channel_trial_and_window():
    faults = [Fault("step", 1, 10.0, 20.0, magnitude=7.0, trial=2), Fault("ramp", 3, 5.0, 15.0, rate=0.5)]
    clean, z, info = _run(faults)
    d = z - clean
    k = np.arange(50)
    exp_step = np.where((k >= 10) & (k < 20), 7.0, 0.0)
    np.testing.assert_array_equal(d[:, 2, 1], exp_step)
    assert not d[:, :2, 1].any()
    exp_ramp = np.where((k >= 5) & (k < 15), 0.5 * (k - 5), 0.0)
    for t in range(3):
        np.testing.assert_allclose(d[:, t, 3], exp_ramp)
    assert not d[:, :, [0, 2]].any()
    bias = np.array([i.bias for i in info])
    np.testing.assert_array_equal(bias, d)
    assert info[12].kind[2, 1] == FAULT_KINDS.index("step") + 1
    assert info[12].kind[0, 3] == FAULT_KINDS.index("ramp") + 1


def test_dropout_is_nan_and_flagged_missing():
    clean, z, info = _run([Fault("dropout", 0, 3.0, 6.0)])
    assert np.isnan(z[3:6, :, 0]).all() and np.isfinite(z[:3]).all() and np.isfinite(z[6:]).all()
    assert info[4].missing[:, 0].all() and not info[7].missing.any()


def test_delay_delivers_the_value_measured_delay_seconds_earlier():
    clean, z, _ = _run([Fault("delay", 2, 10.0, 30.0, delay_s=3.0)], dt=1.0)
    np.testing.assert_array_equal(z[10:30, :, 2], clean[7:27, :, 2])
    np.testing.assert_array_equal(z[30:, :, 2], clean[30:, :, 2])
    np.testing.assert_array_equal(z[:10], clean[:10])


def test_outliers_come_at_their_rate_with_heavy_tails():
    trials, epochs, p = 2000, 100, 0.05
    clean, z, info = _run([Fault("outlier", 0, 0.0, prob=p, scale=10.0, dof=3.0)], trials=trials, epochs=epochs)
    hits = int(sum((i.kind[:, 0] == FAULT_KINDS.index("outlier") + 1).sum() for i in info))
    lo, hi = scipy.stats.binom.interval(0.999, trials * epochs, p)
    assert lo <= hits <= hi
    d = (z - clean)[:, :, 0].ravel()
    d = d[d != 0] / 10.0
    # Student-t(3): its 99th percentile against the Gaussian's 2.33
    assert np.quantile(np.abs(d), 0.98) == pytest.approx(scipy.stats.t.ppf(0.99, 3), rel=0.1)


def test_same_seed_same_faults():
    f = [Fault("outlier", 1, 0.0, prob=0.3, scale=5.0)]
    _, z1, _ = _run(f, seed=4)
    _, z2, _ = _run(f, seed=4)
    _, z3, _ = _run(f, seed=5)
    np.testing.assert_array_equal(z1, z2)
    assert not np.array_equal(z1, z3)


def test_gauss_markov_variance_and_correlation_time():
    rng = np.random.default_rng(1)
    sigma, tau, dt = 2.0, 20.0, 1.0
    gm = GaussMarkov(sigma, tau, (20000, 1), rng)
    xs = [gm.x.copy()]
    for _ in range(30):
        xs.append(gm.step(rng, dt).copy())
    xs = np.array(xs)[..., 0]
    n = xs.shape[1]
    # stationary variance sigma^2 at every step (chi-square interval on 20000 samples)
    lo, hi = scipy.stats.chi2.interval(0.999, n)
    for k in (0, 10, 30):
        s2 = np.sum(xs[k] ** 2)
        assert lo * sigma**2 <= s2 <= hi * sigma**2
    # lag correlation exp(-k dt / tau)
    for lag in (1, 5, 20):
        r = np.corrcoef(xs[0], xs[lag])[0, 1]
        assert r == pytest.approx(math.exp(-lag * dt / tau), abs=4.0 / math.sqrt(n))
    # a different tau is told apart
    assert abs(np.corrcoef(xs[0], xs[20])[0, 1] - math.exp(-20 * dt / 10.0)) > 0.1


@pytest.mark.parametrize("kw, needle", [
    ({"kind": "glitch", "channel": 0, "t_start_s": 0.0}, "kind"),
    ({"kind": "step", "channel": -1, "t_start_s": 0.0}, "channel"),
    ({"kind": "step", "channel": 0, "t_start_s": 5.0, "t_end_s": 5.0}, "t_end_s"),
    ({"kind": "outlier", "channel": 0, "t_start_s": 0.0, "prob": 1.5}, "prob"),
    ({"kind": "delay", "channel": 0, "t_start_s": 0.0}, "delay_s"),
    ({"kind": "step", "channel": 0, "t_start_s": float("nan")}, "t_start_s"),
])
def test_bad_faults_are_clear_errors(kw, needle):
    with pytest.raises(ValueError, match=needle):
        Fault(**kw)


def test_injector_checks_channel_trial_and_shape():
    with pytest.raises(ValueError, match="channel"):
        FaultInjector([Fault("step", 5, 0.0)], (2,), 4)
    with pytest.raises(ValueError, match="trial"):
        FaultInjector([Fault("step", 0, 0.0, trial=2)], (2,), 4)
    inj = FaultInjector([], (2,), 4)
    with pytest.raises(ValueError, match="shape"):
        inj.step(np.random.default_rng(0), 0.0, np.zeros((3, 4)))
    with pytest.raises(ValueError, match="tau_s"):
        GaussMarkov(1.0, 0.0, (2, 4), np.random.default_rng(0))
