"""Seed 000 variant 2 (plus code-minus-carrier increments over 90 s, eqs 29-33) against
variant 1 on the same simulated data."""
import numpy as np
import pytest
import scipy.stats

from sitl.app.experiments import iono_tropo_filters
from sitl.app.experiments.iono_tropo_filters import (
    IonoTropoScenario,
    run_cmc_increments,
    run_code_doppler,
    run_streamed,
)

TRIALS = 8
DURATION = 400.0
SLIP_RATE = 0.002  # per tracked satellite, 1/s: ~0.8 slips per satellite in 400 s


@pytest.fixture(scope="module")
def runs():
    scn = IonoTropoScenario(duration_s=DURATION)
    return run_code_doppler(scn, TRIALS, seed=0), run_cmc_increments(scn, TRIALS, seed=0)


@pytest.fixture(scope="module")
def slip_run():
    return run_cmc_increments(IonoTropoScenario(duration_s=DURATION, cycle_slip_rate_hz=SLIP_RATE), TRIALS, seed=0)


def _nees_band():
    # two-sided 99.9 % band of the mean over 8 trials of a chi2(2) NEES (see variant-1 test)
    return (scipy.stats.chi2.ppf(0.0005, 2 * TRIALS) / TRIALS, scipy.stats.chi2.ppf(0.9995, 2 * TRIALS) / TRIALS)


@pytest.mark.slow
def test_same_simulated_data(runs):
    v1, v2 = runs
    assert v1["variant"] == 1 and v2["variant"] == 2
    np.testing.assert_array_equal(v1["n_visible"], v2["n_visible"])
    assert v1["prior_error"] == v2["prior_error"]
    # identical until the first increment can be formed (after one window)
    t = np.asarray(v1["t_s"])
    early = t < 90.0
    # (the code noise at the window start is a state with R = 0 on its pr row: the same
    # numbers up to round-off)
    np.testing.assert_allclose(np.asarray(v1["iono_err_rms_m"])[early], np.asarray(v2["iono_err_rms_m"])[early],
                               rtol=1e-7)


@pytest.mark.slow
def test_increments_help_on_the_same_data(runs):
    v1, v2 = runs
    inc = v2["increments"]
    assert inc["used"] > 0 and inc["rejected_slip"] == 0 and inc["spanning_true_slip"] == 0
    assert v2["final_error_m"]["iono_zenith"] < v1["final_error_m"]["iono_zenith"]
    assert v2["time_to_1m_s"] < v1["time_to_1m_s"]
    assert np.sum(np.isinf(v2["time_to_1m_s_per_trial"])) <= np.sum(np.isinf(v1["time_to_1m_s_per_trial"]))


@pytest.mark.slow
@pytest.mark.parametrize("which", ["no_slips", "slips"])
def test_iono_tropo_block_nees_is_consistent(runs, slip_run, which):
    r = runs[1] if which == "no_slips" else slip_run
    lo, hi = _nees_band()
    nees_window = 2.0 * r["anees"]
    assert lo < nees_window < hi, nees_window
    t = np.asarray(r["t_s"])
    assert np.all(np.asarray(r["nees_atmo_mean"])[t > 60.0] < 3.0 * hi)
    assert r["final_error_m"]["iono_zenith"] < 2.0 and r["final_error_m"]["tropo_zenith"] < 1.0


@pytest.mark.slow
def test_increments_spanning_a_slip_are_not_used(slip_run):
    inc = slip_run["increments"]
    assert inc["detector_slips"] > 0
    assert inc["spanning_true_slip"] > 0
    assert inc["rejected_slip"] >= inc["spanning_true_slip"]
    assert inc["used_spanning_true_slip"] == 0
    assert inc["used"] + inc["rejected_slip"] == inc["candidates"]
    assert inc["used"] > 0


def test_detector_gets_phase_and_doppler_only(monkeypatch):
    calls = []
    real = iono_tropo_filters.CycleSlipDetector.update

    def update(self, *a, **kw):
        calls.append((a, kw))
        return real(self, *a, **kw)

    monkeypatch.setattr(iono_tropo_filters.CycleSlipDetector, "update", update)
    run_streamed(IonoTropoScenario(duration_s=1.0, cmc_window_s=0.5), 2, seed=1, variant=2)
    assert len(calls) == 11
    for a, kw in calls:
        assert len(a) == 3 and not kw  # (t, phase, prr): no lock_count, no expected_m


def test_bad_variant_and_window_raise():
    with pytest.raises(ValueError, match="variant"):
        run_streamed(IonoTropoScenario(duration_s=1.0), 1, seed=0, variant=4)
    with pytest.raises(ValueError, match="cmc_window_s"):
        IonoTropoScenario(duration_s=10.0, cmc_window_s=0.05)


# ---------------------------------------------------------------- exact noise model ("states")
class _LinearBase:
    """A linear stand-in for IonoTropoGnss: z = [pr (S rows), prr (S rows)] = H0 x, diagonal R."""

    def __init__(self, H0, r):
        self.H0, self.r = H0, r

    def h_and_H(self, x):
        n = x.shape[-1]
        H = np.zeros(x.shape[:-1] + (self.H0.shape[0], n))
        H[..., : self.H0.shape[1]] = self.H0
        return np.einsum("...mn,...n->...m", H, x), H

    def R_diag(self):
        return self.r


def test_code_noise_states_equal_batch_gls_with_the_full_noise_covariance():
    """Two epochs, no dynamics: pr(s) and pr(k) of two satellites plus the increments
    E = B(k) - B(s) = 2 c_j I + eps(k) - eps(s) + eta. Processing them through
    _CodeNoiseStateModel (code noise at s and at k as states, pr rows with R = 0, then the
    states marginalised) must give the posterior of one batch generalised-least-squares
    solve with the full, correlated noise covariance of [pr(s), prr(s), pr(k), prr(k), E]."""
    from filters.ekf import ekf_update
    from filters.iono_tropo import IDX_IONO, N_BASE

    rng = np.random.default_rng(7)
    nb, S = N_BASE, 2
    H0 = rng.normal(size=(2 * S, nb))
    H0[:S, IDX_IONO] = [1.3, 1.7]  # pr sees I_g through the mapping
    sd, sdd, sph = 6.0, 0.064, 0.003
    r = np.r_[np.full(S, sd**2), np.full(S, sdd**2)]
    coef = np.array([[0.04, -0.03]])
    P0 = np.diag(rng.uniform(1.0, 50.0, nb))
    x0 = rng.normal(size=(1, nb))
    z_s = rng.normal(size=(1, 2 * S)) * 5
    z_k = rng.normal(size=(1, 2 * S)) * 5
    E = rng.normal(size=(1, S))
    base = _LinearBase(H0, r)

    # sequential, with the code noises as states
    x, P = x0, P0[None]
    x, P = iono_tropo_filters._append_states(x, P, S)
    P[:, nb:, nb:] = np.eye(S) * sd**2
    m_s = iono_tropo_filters._CodeNoiseStateModel(base, nb + np.arange(S), np.zeros(0, int), np.zeros(0, int),
                                       np.zeros(0, int), np.zeros((1, 0)), np.zeros((1, 0), bool), 0.0)
    res = ekf_update(x, P, z_s, m_s)
    x, P = iono_tropo_filters._append_states(res.x, res.P, S)
    P[:, nb + S:, nb + S:] = np.eye(S) * sd**2
    new = nb + S + np.arange(S)
    m_k = iono_tropo_filters._CodeNoiseStateModel(base, new, np.arange(S), new, nb + np.arange(S), coef,
                                       np.ones((1, S), bool), 2 * sph**2)
    res = ekf_update(x, P, np.concatenate([z_k, E], axis=1), m_k)
    x_seq, P_seq = iono_tropo_filters._drop_states(res.x, res.P, list(range(nb, nb + 2 * S)))

    # batch GLS on the base state: z = [z_s, z_k, E], noise covariance written out by hand
    Hb = np.zeros((5 * S, nb))
    Hb[: 2 * S] = H0
    Hb[2 * S: 4 * S] = H0
    Hb[4 * S:, IDX_IONO] = coef[0]
    Rb = np.diag(np.r_[r, r, np.full(S, 2 * sph**2 + 2 * sd**2)])
    for j in range(S):
        e_row = 4 * S + j
        Rb[e_row, j] = Rb[j, e_row] = -sd**2  # eps(s) enters pr_j(s) and -E_j
        Rb[e_row, 2 * S + j] = Rb[2 * S + j, e_row] = sd**2  # eps(k) enters pr_j(k) and E_j
    zb = np.concatenate([z_s, z_k, E], axis=1)[0]
    Pinv = np.linalg.inv(P0) + Hb.T @ np.linalg.solve(Rb, Hb)
    P_gls = np.linalg.inv(Pinv)
    x_gls = P_gls @ (np.linalg.solve(P0, x0[0]) + Hb.T @ np.linalg.solve(Rb, zb))
    np.testing.assert_allclose(x_seq[0], x_gls, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(P_seq[0], P_gls, rtol=1e-6, atol=1e-10)


@pytest.mark.slow
def test_code_noise_states_settle_sooner_than_the_whitened_increments(runs):
    """On the same data: the exact noise model makes the increment carry the carrier-phase
    change (3 mm) instead of only 2 I_g dm against 6 m code noise."""
    v1, v2 = runs
    wh = run_cmc_increments(IonoTropoScenario(duration_s=DURATION, cmc_noise="whitened"), TRIALS, seed=0)
    assert v2["scenario"]["cmc_noise"] == "states"
    assert v2["time_to_1m_s"] < wh["time_to_1m_s"]
    assert v2["final_error_m"]["iono_zenith"] < 0.5 * wh["final_error_m"]["iono_zenith"]
    lo, hi = _nees_band()
    assert lo < 2.0 * wh["anees"] < hi


def test_code_noise_states_never_adapt_even_with_eq7_on_every_state(monkeypatch):
    """The e_j states are samples of measurement noise, not part of the seed's state vector:
    eq 7 on "all" states must adapt the 11 base states only."""
    from filters.iono_tropo import N_BASE

    seen = []
    real = iono_tropo_filters.AdaptiveQ

    def spy(*a, **k):
        q = real(*a, **k)
        seen.append(q.states)
        return q

    monkeypatch.setattr(iono_tropo_filters, "AdaptiveQ", spy)
    r = run_streamed(IonoTropoScenario(duration_s=100.0, adaptive_q=True, adaptive_q_scope="all"), 2, seed=0,
                     variant=2)
    assert seen == [tuple(range(N_BASE))]
    assert r["increments"]["used"] > 0
    r1 = run_streamed(IonoTropoScenario(duration_s=1.0, adaptive_q=True, adaptive_q_scope="all"), 2, seed=0,
                      variant=1)
    assert seen[-1] is None and r1["variant"] == 1
