"""filters/beacon.py: the beacon range/range-rate model at N observers (seed 002).

Jacobians against central finite differences; the "inflate" R against a Monte Carlo of the
measurement with perturbed observer states; a static-observer EKF run is consistent
(NEES inside the chi-square band) with "inflate" and over-confident with "ignore" when the
observers' errors are large.
"""
import numpy as np
import pytest
import scipy.stats

from filters.beacon import ObserverRangeDoppler
from filters.ekf import ekf_predict, ekf_update
from filters.models import ConstantVelocity

RNG_SEED = 21


def _observers(rng, batch=(), N=4):
    U = rng.normal(0, 20e3, batch + (N, 3)) + np.array([4.0e6, 3.0e6, 3.5e6])
    V = rng.normal(0, 100.0, batch + (N, 3))
    A = rng.normal(0, 1.0, batch + (N, 6, 6))
    s = np.r_[[30.0] * 3, [0.3] * 3]
    C = s[:, None] * (A @ np.swapaxes(A, -1, -2)) * s[None, :] / 6 + np.eye(6) * 1e-3
    return U, V, C


def _fd(f, x, eps):
    cols = []
    for j in range(x.shape[-1]):
        dx = np.zeros_like(x)
        dx[..., j] = eps[j]
        cols.append((f(x + dx) - f(x - dx)) / (2 * eps[j]))
    return np.stack(cols, axis=-1)


def test_jacobian_matches_finite_differences():
    rng = np.random.default_rng(RNG_SEED)
    U, V, C = _observers(rng, (3,))
    m = ObserverRangeDoppler(U, V, 25.0, 0.01, observer_cov=C)
    x = np.concatenate([rng.normal(0, 20e3, (3, 3)) + [4.0e6, 3.0e6, 3.5e6], rng.normal(0, 100, (3, 3))], -1)
    z, H = m.h_and_H(x)
    np.testing.assert_allclose(z, m.h(x))
    Hn = _fd(m.h, x, [1.0] * 3 + [0.01] * 3)
    np.testing.assert_allclose(H, Hn, rtol=1e-6, atol=1e-9)


def test_inflated_R_matches_monte_carlo_of_observer_errors():
    rng = np.random.default_rng(RNG_SEED + 1)
    U, V, C = _observers(rng, (), N=3)
    x = np.r_[4.01e6, 3.02e6, 3.49e6, 50.0, -30.0, 10.0]
    m = ObserverRangeDoppler(U, V, 1e-12, 1e-12, observer_cov=C)
    m.h_and_H(x)
    R = m.R()
    K = 40_000
    L = np.linalg.cholesky(C)
    e = np.einsum("nij,knj->kni", L, rng.standard_normal((K, 3, 6)))
    zs = ObserverRangeDoppler(U + e[..., 0:3], V + e[..., 3:6], 1.0, 1.0, observer_uncertainty="ignore").h(x)
    S = np.cov(zs.T)
    # block diagonal, each 2x2 block within sampling error of the first-order value
    for i in range(3):
        b = slice(2 * i, 2 * i + 2)
        np.testing.assert_allclose(S[b, b], R[b, b], rtol=0.05)
    assert abs(R[0, 2]) == 0.0


def _run(uncertainty, steps=200, trials=300, seed=5):
    """Static beacon-ish target on a CV model, 4 moving observers whose navigation errors
    are drawn fresh each step from their covariance (what 'inflate' assumes)."""
    rng = np.random.default_rng(seed)
    dt = 1.0
    cv = ConstantVelocity(ndim_pos=3, q=0.01)
    F = cv.F(None, dt)
    # ConstantVelocity(ndim_pos=3) orders its state [p (3), v (3)]: the beacon's [B, V_B]
    truth = np.zeros((trials, 6))
    truth[:, 0:3] = [4.0e6, 3.0e6, 3.5e6]
    truth[:, 3:6] = [100.0, 0.0, 0.0]
    P = np.diag([200.0**2] * 3 + [10.0**2] * 3)
    x = truth + rng.standard_normal((trials, 6)) @ np.linalg.cholesky(P).T
    P = np.broadcast_to(P, (trials, 6, 6)).copy()
    Cobs = np.diag([30.0**2] * 3 + [0.3**2] * 3)
    Lobs = np.linalg.cholesky(Cobs)
    base = np.array([[20e3, 0, 0], [0, 25e3, 0], [-15e3, -10e3, 3e3], [5e3, -20e3, -4e3]], float)
    nees = []
    for k in range(steps):
        if k:
            truth = truth @ F.T + rng.standard_normal((trials, 6)) @ np.linalg.cholesky(cv.Q(dt)).T
            x, P = ekf_predict(x, P, cv, dt)
        U = truth[:, None, 0:3] + base + 100.0 * k * np.array([0.0, 1.0, 0.0])
        Vo = np.broadcast_to([0.0, 100.0, 0.0], U.shape)
        z = ObserverRangeDoppler(U, Vo, 25.0, 0.01, observer_uncertainty="ignore").h(truth)
        z = z + rng.standard_normal(z.shape) * np.tile([5.0, 0.1], 4)
        err = np.einsum("ij,tnj->tni", Lobs, rng.standard_normal((trials, 4, 6)))
        Ue, Ve = U + err[..., 0:3], Vo + err[..., 3:6]
        m = ObserverRangeDoppler(Ue, Ve, 25.0, 0.01, observer_cov=np.broadcast_to(Cobs, (trials, 4, 6, 6)),
                                 observer_uncertainty=uncertainty)
        r = ekf_update(x, P, z, m)
        x, P = r.x, r.P
        if k >= steps // 2:
            e = x - truth
            nees.append(np.mean(np.einsum("ti,tij,tj->t", e, np.linalg.inv(P), e)))
    return float(np.mean(nees))


@pytest.mark.slow
def test_inflation_keeps_the_beacon_filter_consistent():
    lo = scipy.stats.chi2.ppf(0.0005, 6 * 300) / 300
    hi = scipy.stats.chi2.ppf(0.9995, 6 * 300) / 300
    inflated = _run("inflate")
    ignored = _run("ignore")
    assert lo < inflated < hi, (inflated, lo, hi)
    assert ignored > 3 * hi, ignored  # 30 m observer errors against 5 m ranging: over-confident


def test_bad_input_raises():
    U = np.zeros((3, 3)) + [1e6, 0, 0]
    with pytest.raises(ValueError, match="observer_uncertainty"):
        ObserverRangeDoppler(U, np.zeros((3, 3)), 1.0, 1.0, observer_uncertainty="maybe")
    with pytest.raises(ValueError, match="observer_cov must be given"):
        ObserverRangeDoppler(U, np.zeros((3, 3)), 1.0, 1.0)
    with pytest.raises(ValueError, match="var_range_m2"):
        ObserverRangeDoppler(U, np.zeros((3, 3)), -1.0, 1.0, observer_uncertainty="ignore")
    with pytest.raises(ValueError, match="observer_vel_ecef_m_s"):
        ObserverRangeDoppler(U, np.zeros((2, 3)), 1.0, 1.0, observer_uncertainty="ignore")
    with pytest.raises(ValueError, match="finite"):
        ObserverRangeDoppler(U * np.nan, np.zeros((3, 3)), 1.0, 1.0, observer_uncertainty="ignore")
