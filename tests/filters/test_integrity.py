"""The integrity layer (filters/integrity.py) on a linear GNSS-like problem whose healthy
innovations are exactly Gaussian, so every false-alarm rate has an analytic value."""
import numpy as np
import pytest
import scipy.stats
from hypothesis import given, settings
from hypothesis import strategies as st

from filters import kernels
from filters.ekf import ekf_predict, ekf_update
from filters.integrity import GuardedModel, IntegrityConfig, IntegrityMonitor
from filters.models import LinearGaussian
from filters.ukf import ukf_update

S = 8  # channels (one row each here)
N_STATE = 4  # position (3) + clock
SIGMA = 2.0


class RandomWalk:
    linear = True

    def __init__(self, n, q):
        self.n, self.q = n, q

    def f(self, x, dt):
        return np.asarray(x, dtype=float)

    def F(self, x, dt):
        return np.eye(self.n)

    def Q(self, dt):
        return self.q * dt * np.eye(self.n)


def _geometry(rng):
    u = rng.normal(size=(S, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return np.hstack([u, np.ones((S, 1))])


def _run(cfg, trials, epochs, seed, fault=None, noise=None, monitor=True, update=ekf_update, sigma_true=SIGMA):
    """Simulate and filter; fault(k) -> (S,) bias added to z at epoch k (or None).
    Returns (errors (epochs, trials, n), reports list, states)."""
    rng = np.random.default_rng(seed)
    H = _geometry(np.random.default_rng(1))
    model = LinearGaussian(H, SIGMA**2 * np.eye(S))
    tr = RandomWalk(N_STATE, 0.01)
    x_true = rng.normal(size=(trials, N_STATE)) * 10.0
    P = np.broadcast_to(np.eye(N_STATE) * 100.0, (trials, N_STATE, N_STATE)).copy()
    x = x_true + rng.normal(size=(trials, N_STATE)) * 10.0
    mon = IntegrityMonitor(cfg)
    ms = mon.init((trials,), S, S)
    errs, reps = [], []
    for k in range(epochs):
        if k:
            x_true = x_true + rng.normal(size=x_true.shape) * np.sqrt(0.01)
            x, P = ekf_predict(x, P, tr, 1.0)
        v = noise(rng, (trials, S)) if noise else sigma_true * rng.normal(size=(trials, S))
        z = x_true @ H.T + v
        if fault is not None:
            z = z + fault(k)
        if monitor:
            res, ms, rep = mon.step(ms, x, P, z, model, np.arange(S), update=update)
            reps.append(rep)
        else:
            res = update(x, P, z, model)
        x, P = res.x, res.P
        errs.append(x - x_true)
    return np.array(errs), reps, ms


def _binom_ci(n, p, conf=0.999):
    return scipy.stats.binom.interval(conf, n, p)


@pytest.mark.slow
def test_detect_only_monitor_equals_the_plain_filter_bit_for_bit():
    cfg = IntegrityConfig(isolate=False)
    e_mon, _reps, _ = _run(cfg, 20, 60, seed=3)
    e_plain, _, _ = _run(cfg, 20, 60, seed=3, monitor=False)
    np.testing.assert_array_equal(e_mon, e_plain)


@pytest.mark.slow
def test_healthy_false_alarm_rates_match_the_analytic_values():
    """beta ~ N(0, 1) exactly on this linear problem: jump rate 2(1 - Phi(3)); each window
    test alpha per row-epoch (non-overlapping windows taken, so the samples are independent)."""
    W = 10
    cfg = IntegrityConfig(isolate=False, window=W, window_alpha=0.01, bias_alpha=0.01)
    trials, epochs = 300, 400
    _, reps, _ = _run(cfg, trials, epochs, seed=11)
    beta = np.array([r.beta for r in reps[20:]])
    assert abs(beta.mean()) < 0.01 and abs(beta.std() - 1.0) < 0.01
    jumps = int(sum(r.jump.sum() for r in reps))
    n = epochs * trials * S
    lo, hi = _binom_ci(n, 2 * scipy.stats.norm.sf(3.0))
    assert lo <= jumps <= hi, (jumps, lo, hi)
    # window tests at the ends of disjoint full windows (after the first W + 20 epochs); with
    # no jump test, so that no sample is replaced and the statistics are exactly chi-square
    # (with it, the samples are winsorised at the threshold and the window tests are conservative)
    cfg = IntegrityConfig(isolate=False, window=W, window_alpha=0.01, bias_alpha=0.01, jump_sigma=float("inf"))
    _, reps, _ = _run(cfg, trials, epochs, seed=12)
    ends = range(W + 29, epochs, W)
    thr_ms = scipy.stats.chi2.isf(0.01, W) / W
    thr_b = scipy.stats.chi2.isf(0.01, 1)
    n_ms = sum(int((reps[k].drift_stat > thr_ms).sum()) for k in ends)
    n_b = sum(int((reps[k].bias_stat > thr_b).sum()) for k in ends)
    n_w = len(ends) * trials * S
    lo, hi = _binom_ci(n_w, 0.01)
    assert lo <= n_ms <= hi, (n_ms, lo, hi)
    assert lo <= n_b <= hi, (n_b, lo, hi)


def test_a_step_is_isolated_on_the_right_channel_within_one_epoch():
    faulty, k0, step = 3, 100, 5.0 * SIGMA

    def fault(k):
        f = np.zeros(S)
        if k >= k0:
            f[faulty] = step
        return f

    trials = 400
    cfg = IntegrityConfig()
    e_mon, reps, _ = _run(cfg, trials, 160, seed=5, fault=fault)
    e_plain, _, _ = _run(cfg, trials, 160, seed=5, fault=fault, monitor=False)
    flagged = reps[k0].jump[:, faulty] | reps[k0 + 1].jump[:, faulty]
    assert flagged.mean() >= 0.99, flagged.mean()
    excl = reps[k0 + 5].excluded
    assert excl[:, faulty].mean() >= 0.99
    others = np.delete(excl, faulty, axis=1)
    assert others.mean() < 0.01
    rms_mon = np.sqrt(np.mean(e_mon[k0 + 5:, :, :3] ** 2))
    rms_plain = np.sqrt(np.mean(e_plain[k0 + 5:, :, :3] ** 2))
    assert rms_mon < 0.6 * rms_plain, (rms_mon, rms_plain)


def test_a_slow_ramp_trips_the_bias_test_and_the_channel_comes_back_after_it():
    faulty, k0, k1, rate = 6, 80, 180, 0.2 * SIGMA  # per epoch

    def fault(k):
        f = np.zeros(S)
        if k0 <= k < k1:
            f[faulty] = rate * (k - k0)
        return f

    cfg = IntegrityConfig(window=10, readmit_after=10)
    trials = 200
    _, reps, _ = _run(cfg, trials, 260, seed=8, fault=fault)
    detected_by = np.array([[reps[k].excluded[t, faulty] for k in range(k0, k0 + 20)] for t in range(trials)])
    delay = np.argmax(detected_by, axis=1)
    assert detected_by.any(axis=1).mean() >= 0.99
    assert np.median(delay) <= 15
    # the fault ends at k1 (the bias drops to 0): readmitted once the window is clean again
    back = np.array([~reps[k].excluded[:, faulty] for k in range(k1, 260)])
    assert back[-1].mean() >= 0.95
    assert sum(int(r.readmitted[:, faulty].sum()) for r in reps[k1:]) >= 0.9 * trials


def test_huber_weights_cut_the_error_under_heavy_tailed_noise():
    def noise(rng, shape):  # 5 % of the samples from a 10x wider Gaussian
        wide = rng.random(shape) < 0.05
        return SIGMA * rng.normal(size=shape) * np.where(wide, 10.0, 1.0)

    plain, _, _ = _run(IntegrityConfig(isolate=False), 200, 200, seed=2, noise=noise)
    huber, _, _ = _run(IntegrityConfig(isolate=False, huber_c=1.5), 200, 200, seed=2, noise=noise)
    r_plain = np.sqrt(np.mean(plain[50:, :, :3] ** 2))
    r_huber = np.sqrt(np.mean(huber[50:, :, :3] ** 2))
    assert r_huber < 0.75 * r_plain, (r_huber, r_plain)


def test_innovation_based_r_finds_a_noisier_sensor():
    true_sigma = 3.0 * SIGMA
    cfg = IntegrityConfig(isolate=False, adapt_r=True, r_forget=0.02)
    _, _, ms = _run(cfg, 200, 400, seed=4, sigma_true=true_sigma)
    ratio = np.median(ms.r_est) / true_sigma**2
    assert 0.85 < ratio < 1.15, ratio
    # and with a sensor as specified the estimate stays at the nominal floor's level
    _, _, ms2 = _run(cfg, 200, 400, seed=4)
    assert 0.8 < np.median(ms2.r_est) / SIGMA**2 < 1.2


def test_missing_measurements_are_inert_not_faults():
    def fault(k):
        f = np.zeros(S)
        if k == 30:
            f[2] = np.nan
        return f

    _, reps, _ = _run(IntegrityConfig(), 10, 40, seed=6, fault=fault)
    assert not reps[30].used[:, 2].any() and not reps[30].jump[:, 2].any()
    assert not reps[30].excluded.any()


def test_the_monitor_wraps_the_ukf_too():
    """On a linear model the UKF equals the KF, so the monitored UKF must equal the monitored EKF."""
    def fault(k):
        f = np.zeros(S)
        if k >= 20:
            f[1] = 6 * SIGMA
        return f

    cfg = IntegrityConfig(huber_c=2.0)
    e_ekf, r_ekf, _ = _run(cfg, 8, 40, seed=9, fault=fault)
    e_ukf, r_ukf, _ = _run(cfg, 8, 40, seed=9, fault=fault, update=ukf_update)
    np.testing.assert_allclose(e_ukf, e_ekf, rtol=1e-7, atol=1e-8)
    np.testing.assert_array_equal(r_ukf[-1].excluded, r_ekf[-1].excluded)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.lists(st.booleans(), min_size=6, max_size=6))
def test_inert_rows_equal_removing_them(seed, inert_list):
    """GuardedModel: an update with inert rows equals the update on the other rows alone."""
    rng = np.random.default_rng(seed)
    n, m = 4, 6
    A = rng.normal(size=(n, n))
    P = A @ A.T + 0.1 * np.eye(n)
    x = rng.normal(size=n)
    H = rng.normal(size=(m, n))
    r = rng.uniform(0.5, 2.0, m)
    z = rng.normal(size=m)
    inert = np.array(inert_list)
    g = GuardedModel(LinearGaussian(H, np.diag(r)), z, inert)
    res = ekf_update(x, P, z, g)
    keep = ~inert
    if keep.any():
        ref = ekf_update(x, P, z[keep], LinearGaussian(H[keep], np.diag(r[keep])))
        np.testing.assert_allclose(res.x, ref.x, rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(res.P, ref.P, rtol=1e-9, atol=1e-10)
        assert res.nis == pytest.approx(float(ref.nis), rel=1e-9)
    else:
        np.testing.assert_allclose(res.x, x)
        np.testing.assert_allclose(res.P, P)


@pytest.mark.parametrize("kw, needle", [
    ({"jump_sigma": -1}, "jump_sigma"), ({"window": 0}, "window"), ({"window_alpha": 1.5}, "window_alpha"),
    ({"bias_alpha": 0.0}, "bias_alpha"), ({"persist": 0}, "persist"), ({"huber_c": float("nan")}, "huber_c"),
    ({"r_forget": 0.0}, "r_forget"), ({"isolate": "yes"}, "isolate"),
])
def test_bad_config_is_a_clear_error(kw, needle):
    with pytest.raises(ValueError, match=needle):
        IntegrityConfig(**kw)


def test_a_state_of_another_shape_is_a_clear_error():
    """The state's batch and rows must be the measurement's (the compiled kernel trusts them)."""
    mon = IntegrityMonitor(IntegrityConfig())
    model = LinearGaussian(np.eye(2), np.eye(2))
    for batch, m in (((6,), 2), ((5,), 3)):
        ms = mon.init(batch, m, m)
        for be in ("numpy", "numba"):
            with pytest.raises(ValueError, match="monitor state is for measurements of shape"):
                mon.step(ms, np.zeros((5, 2)), np.broadcast_to(np.eye(2), (5, 2, 2)), np.zeros((5, 2)), model,
                         np.arange(2) % m, backend=be)


def test_bad_channels_are_a_clear_error():
    mon = IntegrityMonitor()
    ms = mon.init((2,), 3, 2)
    model = LinearGaussian(np.eye(3), np.eye(3))
    x, P, z = np.zeros((2, 3)), np.broadcast_to(np.eye(3), (2, 3, 3)), np.zeros((2, 3))
    with pytest.raises(ValueError, match="channels"):
        mon.step(ms, x, P, z, model, np.array([0, 1, 2]))
    with pytest.raises(ValueError, match="channels"):
        mon.step(ms, x, P, z, model, np.array([0, 1]))


@pytest.mark.slow
def test_the_monitor_wraps_the_ud_filter_and_equals_the_ekf():
    """The U-D (Bierman-Thornton) update under the monitor, through a small adapter with the EKF
    update's signature, gives the monitored EKF's numbers (a linear model: both are exact)."""
    from filters.ekf import UpdateResult
    from filters.ud import ud_factor, ud_update

    def ud_as_update(x, P, z, model, **kw):
        U, d = ud_factor(P)
        r = ud_update(x, U, d, z, model, **kw)
        return UpdateResult(r.x, r.P, r.y, r.nis)

    def fault(k):
        f = np.zeros(S)
        if k >= 15:
            f[4] = 7 * SIGMA
        if k == 25:
            f[2] = np.nan
        return f

    cfg = IntegrityConfig(huber_c=2.0, adapt_r=True)
    e_ekf, r_ekf, _ = _run(cfg, 6, 40, seed=21, fault=fault)
    e_ud, r_ud, _ = _run(cfg, 6, 40, seed=21, fault=fault, update=ud_as_update)
    np.testing.assert_allclose(e_ud, e_ekf, rtol=1e-7, atol=1e-8)
    np.testing.assert_array_equal(r_ud[-1].excluded, r_ekf[-1].excluded)
    assert r_ekf[-1].excluded[:, 4].all()


def _random_linear(rng, trials, n, m):
    """A random well-posed linear problem: per-trial prior (P0, x0), H, a diagonal-R model, two rows a channel."""
    A = rng.normal(size=(trials, n, n))
    P0 = A @ A.transpose(0, 2, 1) + np.eye(n)
    x0 = rng.normal(size=(trials, n))
    Hm = rng.normal(size=(m, n))
    model = LinearGaussian(Hm, np.diag(rng.uniform(0.5, 2.0, m)))
    return P0, x0, Hm, model, np.arange(m) // 2


def test_compiled_and_numpy_monitor_agree():
    rng = np.random.default_rng(0)
    N, n, m = 40, 4, 8
    A = rng.normal(size=(N, n, n))
    P = A @ A.transpose(0, 2, 1) + np.eye(n)
    x = rng.normal(size=(N, n))
    model = LinearGaussian(rng.normal(size=(m, n)), np.diag(rng.uniform(1, 2, m)))
    z = rng.normal(size=(N, m)) * 3
    z[3, 2] = np.nan
    mon = IntegrityMonitor(IntegrityConfig(huber_c=1.5, adapt_r=True, window=4))
    ch = np.arange(m) // 2
    runs = {}
    for be in ("numpy", "numba"):
        ms = mon.init((N,), m, 4)
        out = []
        for k in range(9):
            r, ms, rep = mon.step(ms, x, P, z + 0.4 * k, model, ch, backend=be)
            out.append((r.x, r.P, rep))
        runs[be] = out
    for a, b in zip(runs["numpy"], runs["numba"]):
        np.testing.assert_allclose(a[0], b[0], rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(a[1], b[1], rtol=1e-10, atol=1e-10)
        for u, v in zip(a[2], b[2]):
            np.testing.assert_allclose(np.asarray(u, float), np.asarray(v, float), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("trials", [5, 300])  # the serial and the parallel driver
def test_fused_ekf_path_equals_the_generic_path(trials):
    """Around ekf_update the compiled monitor runs the update in its own kernel (fused); around any
    other update it hands a guarded model to it. Both must give the same numbers, through jumps,
    missing rows, exclusion and readmission (fresh windows), Huber weights and adaptive R."""
    rng = np.random.default_rng(7)
    n, m = 5, 8
    P0, x0, Hm, model, ch = _random_linear(rng, trials, n, m)
    cfg = IntegrityConfig(huber_c=1.5, adapt_r=True, window=4, readmit_after=3, persist=2)
    mon = IntegrityMonitor(cfg)

    def generic(*a, **kw):
        return ekf_update(*a, **kw)

    runs = {}
    for name, upd in (("fused", ekf_update), ("generic", generic)):
        ms = mon.init((trials,), m, 4)
        x, P = x0, P0
        out = []
        for k in range(16):
            z = np.random.default_rng(k).normal(size=(trials, m)) + x0 @ Hm.T
            if 3 <= k < 7:
                z[:, 2] += 25.0  # a step on channel 1 for 4 epochs: excluded, then readmitted
            if k == 9:
                z[1, 5] = np.nan
            res, ms, rep = mon.step(ms, x, P, z, model, ch, update=upd, backend="numba")
            x, P = res.x, 0.5 * (res.P + np.swapaxes(res.P, -1, -2)) + 0.1 * np.eye(n)
            out.append((res, rep))
        runs[name] = out
    assert any(r.readmitted.any() for _, r in runs["fused"]) and any(r.newly_excluded.any() for _, r in runs["fused"])
    for (ra, pa), (rb, pb) in zip(runs["fused"], runs["generic"]):
        for u, v in zip(ra, rb):
            np.testing.assert_allclose(u, v, rtol=1e-11, atol=1e-11)
        for u, v in zip(pa, pb):
            np.testing.assert_allclose(np.asarray(u, float), np.asarray(v, float), rtol=1e-11, atol=1e-11)


def test_the_fused_path_leaves_the_models_h_alone():
    """The fused update masks its own lane copy of H: an H the model hands out is not written."""
    class Owned:
        def __init__(self, H):
            self.Hm, self.last = H, None

        def h_and_H(self, x):  # a fresh, writeable, full-shape H (the in-place candidate)
            self.last = np.array(np.broadcast_to(self.Hm, x.shape[:-1] + self.Hm.shape))
            return x @ self.Hm.T, self.last

        def R_diag(self):
            return np.ones(self.Hm.shape[0])

    rng = np.random.default_rng(3)
    trials, n, m = 4, 3, 4
    model = Owned(rng.normal(size=(m, n)))
    mon = IntegrityMonitor(IntegrityConfig())
    ms = mon.init((trials,), m, m)
    z = rng.normal(size=(trials, m))
    z[:, 1] += 50.0  # a jump: the row is inert this epoch
    _, _, rep = mon.step(ms, np.zeros((trials, n)), np.broadcast_to(np.eye(n), (trials, n, n)), z, model,
                         np.arange(m))
    assert not rep.used[:, 1].any()
    np.testing.assert_array_equal(model.last, np.broadcast_to(model.Hm, (trials, m, n)))


# ---------------------------------------------------------------- redundancy: min_channels

def _step_on(ch, k0, size):
    def fault(k):
        f = np.zeros(S)
        if k >= k0:
            f[ch] = size
        return f
    return fault


def test_without_redundancy_the_monitor_detects_only_and_is_the_plain_filter():
    """min_channels = S (every channel needed): fault-free, the monitored filter is the plain one
    bit for bit although its jump test fires now and then; under a step it still reports the
    channel every faulty epoch (newly_excluded, as detect-only) and still uses it."""
    cfg = IntegrityConfig(min_channels=S)
    e_mon, reps, _ = _run(cfg, 40, 80, seed=21)
    e_plain, _, _ = _run(cfg, 40, 80, seed=21, monitor=False)
    assert sum(int(r.jump.sum()) for r in reps) > 0  # the test did fire: the rule kept the rows in
    np.testing.assert_array_equal(e_mon, e_plain)
    fault = _step_on(3, 30, 8.0 * SIGMA)
    e_mon, reps, _ = _run(cfg, 40, 60, seed=22, fault=fault)
    e_plain, _, _ = _run(cfg, 40, 60, seed=22, fault=fault, monitor=False)
    np.testing.assert_array_equal(e_mon, e_plain)
    assert all(r.used.all() and not r.excluded.any() for r in reps)
    flagged = np.array([r.newly_excluded[:, 3] for r in reps[31:]])
    assert flagged.mean() > 0.95  # persist = 2: from the second faulty epoch on, every epoch


def test_with_one_spare_channel_a_step_is_isolated_and_a_second_fault_falls_back_to_detect_only():
    """min_channels = S - 1: one faulty channel is excluded (the rest stay in); when a second
    channel steps as well, excluding both would leave S - 2: the monitor keeps its rows in
    (detect only), the first channel comes back (readmitted) and the faults are reported."""
    cfg = IntegrityConfig(min_channels=S - 1)

    def fault(k):
        f = np.zeros(S)
        if k >= 30:
            f[3] = 8.0 * SIGMA
        if k >= 50:
            f[5] = 8.0 * SIGMA
        return f

    trials = 60
    _, reps, _ = _run(cfg, trials, 70, seed=23, fault=fault)
    assert reps[40].excluded[:, 3].mean() > 0.95 and reps[40].excluded[:, [0, 1, 2, 4, 5, 6, 7]].mean() < 0.02
    assert np.array([r.used[:, 3] for r in reps[32:50]]).mean() < 0.05
    # from the second step on (persist = 2: epoch 51) nothing is left out; the first channel came back
    assert np.array([r.used[:, [3, 5]] for r in reps[52:]]).mean() > 0.98
    assert reps[51].readmitted[:, 3].mean() > 0.95
    assert np.array([r.newly_excluded[:, [3, 5]] for r in reps[52:]]).mean() > 0.95
    # the limit is on channels present: with a channel missing the same single step is not isolated
    miss = IntegrityConfig(min_channels=S - 1)

    def fault_missing(k):
        f = _step_on(3, 30, 8.0 * SIGMA)(k)
        f[6] = np.nan
        return f

    _, reps_m, _ = _run(miss, trials, 40, seed=23, fault=fault_missing)
    assert all(not r.excluded.any() for r in reps_m) and np.array([r.used[:, 3] for r in reps_m]).all()


@pytest.mark.parametrize("trials", [6, 300])  # the serial and the parallel driver
def test_compiled_and_numpy_monitor_agree_on_the_redundancy_rule(trials):
    """All three isolation modes (rows and channels out, channels only, detect only) reached:
    the compiled monitor (fused and generic paths) equals the numpy reference."""
    rng = np.random.default_rng(9)
    n, m, C = 4, 10, 5
    P0, x0, Hm, model, ch = _random_linear(rng, trials, n, m)
    mon = IntegrityMonitor(IntegrityConfig(min_channels=4, window=4, readmit_after=3, persist=2))

    def generic(*a, **kw):
        return ekf_update(*a, **kw)

    runs = {}
    for name, be, upd in (("numpy", "numpy", ekf_update), ("fused", "numba", ekf_update),
                          ("generic", "numba", generic)):
        ms = mon.init((trials,), m, C)
        x, P = x0, P0
        out = []
        for k in range(18):
            z = np.random.default_rng(100 + k).normal(size=(trials, m)) + x0 @ Hm.T
            if 2 <= k < 12:
                z[:, 2] += 30.0  # channel 1 steps: excluded (4 of 5 stay in)
            if k == 6:
                z[::2, 7] += 30.0  # a jump on channel 3 as well: its row is used (channels-only mode)
            if 8 <= k < 10:
                z[1::2, 0:2] += 30.0  # channel 0 steps too: detect only, channel 1 readmitted
            if k == 13:
                z[::3, 9] = np.nan
            res, ms, rep = mon.step(ms, x, P, z, model, ch, update=upd, backend=be)
            x, P = res.x, 0.5 * (res.P + np.swapaxes(res.P, -1, -2)) + 0.1 * np.eye(n)
            out.append((res, rep))
        runs[name] = out
    reps = [r for _, r in runs["numpy"]]
    assert any(r.excluded.any() for r in reps) and any(r.readmitted.any() for r in reps)
    # (a healthy row's occasional 3-sigma jump changes a trial's mode: most trials, not all)
    assert reps[6].used[::2, 7].mean() > 0.9 and reps[6].used[:, 2:4].mean() < 0.1  # channels only
    assert reps[9].used[1::2].mean() > 0.9  # detect only
    for other in ("fused", "generic"):
        for (ra, pa), (rb, pb) in zip(runs["numpy"], runs[other]):
            for u, v in zip(ra, rb):
                np.testing.assert_allclose(u, v, rtol=1e-10, atol=1e-10)
            for u, v in zip(pa, pb):
                np.testing.assert_allclose(np.asarray(u, float), np.asarray(v, float), rtol=1e-10, atol=1e-10)



@pytest.mark.parametrize("trials", [5, 300])  # the serial and the parallel driver
def test_compiled_and_numpy_monitor_agree_through_repeated_readmissions_and_the_exact_resum(trials, monkeypatch):
    """Channels excluded and readmitted again and again (fresh windows overlapping the ring's
    wrap-around), the running sums recomputed exactly every few epochs: the compiled monitor's
    state and Report (the window statistics its tests saw, also on readmitted rows, whose sums are
    reset) equal the numpy reference's."""
    import filters.integrity as integ

    monkeypatch.setattr(integ, "RESUM", 7)
    rng = np.random.default_rng(21)
    n, m, C = 4, 8, 4
    P0, x0, Hm, model, ch = _random_linear(rng, trials, n, m)
    mon = IntegrityMonitor(IntegrityConfig(window=5, readmit_after=2, persist=1, huber_c=2.0, adapt_r=True))
    runs = {}
    for be in ("numpy", "numba"):
        ms = mon.init((trials,), m, C)
        x, P = x0, P0
        out = []
        for k in range(40):
            z = np.random.default_rng(200 + k).normal(size=(trials, m)) + x0 @ Hm.T
            if k % 6 in (1, 2):
                z[:, 2 * (k % C)] += 40.0  # a short step, channel by channel: excluded, then readmitted
            if k % 9 == 4:
                z[::2, 5] = np.nan
            res, ms, rep = mon.step(ms, x, P, z, model, ch, backend=be)
            x, P = res.x, 0.5 * (res.P + np.swapaxes(res.P, -1, -2)) + 0.1 * np.eye(n)
            fresh = np.zeros((trials, m)) if ms.stale is None else np.maximum(ms.stale - ms.steps, 0)
            out.append((res, rep, ms, fresh))
        runs[be] = out
    n_readmit = sum(int(r.readmitted.sum()) for _, r, _, _ in runs["numpy"])
    assert n_readmit >= 5 * trials  # readmissions in most of the 6-epoch cycles
    # a readmitted row's window is fresh: sums (W, 0) right after, then for W epochs only the new
    # samples enter (each one's beta^2 replaces a healthy 1; nothing real leaves)
    W, J = mon.config.window, mon.config.jump_sigma
    out = runs["numpy"]
    checked = 0
    for k in range(len(out) - W):
        rd = out[k][1].readmitted[:, ch]  # (trials, m) rows of readmitted channels
        later = np.zeros_like(rd)
        for d in range(1, W + 1):
            later |= out[k + d][1].readmitted[:, ch]
        sel = rd & ~later
        np.testing.assert_allclose(out[k][2].sum_sq[sel], W)
        for d in range(1, W + 1):
            nb = out[k + d][2].ring_b[(out[k][2].pos + d - 1) % W]  # the sample epoch k + d wrote
            sq = np.where(np.isnan(nb), 1.0, np.clip(nb, -J, J) ** 2)
            np.testing.assert_allclose((out[k + d][2].sum_sq - out[k + d - 1][2].sum_sq)[sel], (sq - 1.0)[sel],
                                       atol=1e-9)
        checked += int(sel.sum())
    assert checked >= 3 * trials
    for (ra, pa, sa, fa), (rb, pb, sb, fb) in zip(runs["numpy"], runs["numba"]):
        for u, v in zip(ra, rb):
            np.testing.assert_allclose(u, v, rtol=1e-10, atol=1e-10)
        for u, v in zip(pa, pb):
            np.testing.assert_allclose(np.asarray(u, float), np.asarray(v, float), rtol=1e-10, atol=1e-10)
        for f in ("sum_sq", "sum_b", "jump_run", "excluded", "clean_run", "r_est"):
            np.testing.assert_allclose(np.asarray(getattr(sa, f), float), np.asarray(getattr(sb, f), float),
                                       rtol=1e-10, atol=1e-10, err_msg=f)
        np.testing.assert_array_equal(fa, fb)
        for u, v in zip(sa.ring_b, sb.ring_b):
            np.testing.assert_allclose(u, v, rtol=1e-10, atol=1e-10)


# ---------------------------------------------------------------- the compiled kernels' worker threads

_SPIN_CHILD = """
import os, sys, time
import numpy as np
from filters import kernels
P = np.broadcast_to(np.eye(4), (2 * kernels.PARALLEL_MIN_TRIALS, 4, 4)).copy()
F = Q = np.eye(4)
kernels.cov_predict(F, P, Q, backend="numba")  # the parallel driver: numba's threads start
burn = []
for _ in range(15):
    kernels.cov_predict(F, P, Q, backend="numba")
    c = time.process_time()
    time.sleep(0.01)  # the main thread sleeps: any CPU time now is the workers'
    burn.append(time.process_time() - c)
print(os.environ["OMP_WAIT_POLICY"], sorted(burn)[len(burn) // 2])
"""


@pytest.mark.slow
@pytest.mark.live
@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba not installed")
def test_the_kernels_worker_threads_do_not_spin_after_a_parallel_kernel():
    """filters/_nbkernels.py sets OMP_WAIT_POLICY=PASSIVE before numba loads libgomp: after a
    parallel kernel the workers sleep instead of spinning for milliseconds (which took a core
    from the main thread's numpy work, e.g. ekf_predict 7.9 -> 3.0 ms). A policy the user sets
    wins: ACTIVE spins through the whole sleep, which shows the measurement sees spinning."""
    import os
    import subprocess
    import sys

    def burnt(policy):
        env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
        if policy:
            env["OMP_WAIT_POLICY"] = policy
        out = subprocess.run([sys.executable, "-c", _SPIN_CHILD], env=env, capture_output=True, text=True,
                             timeout=120, check=True).stdout.split()
        return out[0], float(out[1])

    pol, passive = burnt(None)
    assert pol == "PASSIVE" and passive < 0.5e-3
    pol, active = burnt("ACTIVE")
    assert pol == "ACTIVE" and active > 1e-3  # (measured 4-10 ms)
