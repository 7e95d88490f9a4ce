"""Receiver clock two-state model (seed 000, eqs. 13-15)."""
import numpy as np
import pytest
from scipy import stats

from sitl.constants import C_M_S
from sitl.gnss.clock import TCXO_PSD_1_S, ClockModel

T = 0.1


def cov_lr_statistic(e, Q):
    """Likelihood-ratio statistic of H0: cov(e) = Q for zero-mean Gaussian e of shape (n, p).

    λ = n (tr A − ln det A − p),  A = Q⁻¹ S,  S = e'e / n;  λ ~ χ²(p(p+1)/2) under H0.
    """
    n, p = e.shape
    S = e.T @ e / n
    A = np.linalg.solve(Q, S)
    return n * (np.trace(A) - np.log(np.linalg.det(A)) - p)


def increments(bias, drift, T):
    """Process noise realisations ξ(i) = x(i+1) − F x(i), pooled over trials and steps."""
    xi_b = bias[..., 1:] - bias[..., :-1] - T * drift[..., :-1]
    xi_d = drift[..., 1:] - drift[..., :-1]
    return np.stack([xi_b.ravel(), xi_d.ravel()], axis=-1)


def test_F_and_Q_analytic():
    m = ClockModel()
    assert m.psd_1_s == TCXO_PSD_1_S == 0.8e-20
    np.testing.assert_array_equal(m.F(T), [[1.0, T], [0.0, 1.0]])
    q = C_M_S**2 * 0.8e-20
    np.testing.assert_allclose(m.Q(T), q * np.array([[T**3 / 3, T**2 / 2], [T**2 / 2, T]]), rtol=1e-15)
    Q = m.Q(T)
    assert np.allclose(Q, Q.T) and np.all(np.linalg.eigvalsh(Q) > 0)
    L = m.Q_cholesky(T)
    np.testing.assert_allclose(L @ L.T, Q, rtol=1e-12)
    np.testing.assert_allclose(L, np.linalg.cholesky(Q), rtol=1e-12)


def test_Q_is_the_integral_of_the_continuous_model():
    # Q = ∫0^T Φ(s) G q G' Φ(s)' ds with Φ(s) = [[1, s], [0, 1]], G = [0, 1]'
    m = ClockModel(psd_1_s=2e-20)
    s = np.linspace(0.0, 0.7, 20001)
    g = np.stack([s, np.ones_like(s)])  # Φ(s) G
    integrand = g[:, None, :] * g[None, :, :] * m.q_m2_s3
    Qn = np.trapezoid(integrand, s, axis=-1)
    np.testing.assert_allclose(Qn, m.Q(0.7), rtol=1e-7)


def test_simulated_increments_match_Q_and_a_wrong_Q_is_rejected():
    m = ClockModel()
    rng = np.random.default_rng(20240601)
    bias, drift = m.simulate(rng, n_steps=100, T=T, bias0_m=1e3, drift0_m_s=0.5, batch_shape=(200,))
    e = increments(bias, drift, T)
    assert e.shape == (20000, 2)
    crit = stats.chi2.ppf(0.999, df=3)
    assert cov_lr_statistic(e, m.Q(T)) < crit
    # the same test rejects a wrong PSD, a 20 % error in it, and a Q without the correlation
    assert cov_lr_statistic(e, ClockModel(psd_1_s=1.2 * TCXO_PSD_1_S).Q(T)) > crit
    assert cov_lr_statistic(e, ClockModel(psd_1_s=TCXO_PSD_1_S / 1.2).Q(T)) > crit
    assert cov_lr_statistic(e, np.diag(np.diag(m.Q(T)))) > crit


def test_long_horizon_variance_is_exact_for_any_step():
    # from x(0) = 0: var Δ(t) = q t³/3, var Δ̇(t) = q t, whatever the step T (exact discretisation)
    m = ClockModel()
    n_trials, t_end = 4000, 10.0
    for T_step, n in ((1.0, 10), (0.1, 100)):
        bias, drift = m.simulate(np.random.default_rng(7), n, T_step, batch_shape=(n_trials,))
        for x, var in ((bias[:, -1], m.q_m2_s3 * t_end**3 / 3), (drift[:, -1], m.q_m2_s3 * t_end)):
            stat = np.sum(x**2) / var  # ~ χ²(n_trials)
            lo, hi = stats.chi2.ppf([0.0005, 0.9995], df=n_trials)
            assert lo < stat < hi
            assert not lo < np.sum(x**2) / (1.2 * var) < hi  # a 20 % wrong variance fails


def test_simulate_shapes_initial_state_and_determinism():
    m = ClockModel()
    b0 = np.array([[0.0], [10.0]])
    bias, drift = m.simulate(np.random.default_rng(1), 5, T, bias0_m=b0, drift0_m_s=2.0, batch_shape=(2, 3))
    assert bias.shape == drift.shape == (2, 3, 6)
    np.testing.assert_array_equal(bias[..., 0], np.broadcast_to(b0, (2, 3)))
    np.testing.assert_array_equal(drift[..., 0], 2.0)
    b2, d2 = m.simulate(np.random.default_rng(1), 5, T, bias0_m=b0, drift0_m_s=2.0, batch_shape=(2, 3))
    np.testing.assert_array_equal(bias, b2)
    s, d = m.simulate(np.random.default_rng(1), 3, T)
    assert s.shape == (4,)
    # no noise: deterministic ramp
    b, d = ClockModel(psd_1_s=0.0).simulate(np.random.default_rng(0), 4, 0.5, bias0_m=1.0, drift0_m_s=2.0)
    np.testing.assert_allclose(b, 1.0 + 2.0 * 0.5 * np.arange(5))
    np.testing.assert_allclose(d, 2.0)


def test_step_matches_simulate_in_distribution_and_shape():
    m = ClockModel()
    b, d = m.step(np.random.default_rng(3), np.zeros(50000), 1.0, T)
    assert b.shape == (50000,)
    e = np.stack([b - T * 1.0, d - 1.0], axis=-1)
    assert cov_lr_statistic(e, m.Q(T)) < stats.chi2.ppf(0.999, df=3)


@pytest.mark.parametrize("bad", [-1e-20, np.nan, np.inf, "x"])
def test_invalid_psd_raises_naming_parameter(bad):
    with pytest.raises(ValueError, match="psd_1_s"):
        ClockModel(psd_1_s=bad)


@pytest.mark.parametrize("bad", [0.0, -0.1, np.nan])
def test_invalid_step_raises(bad):
    with pytest.raises(ValueError, match="T must"):
        ClockModel().Q(bad)
