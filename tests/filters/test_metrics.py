"""Metrics: RMSE, NEES/NIS with chi2 bounds, and the posterior Cramér-Rao bound
(Tichavsky, Muravchik & Nehorai 1998) against the Kalman filter Riccati recursion."""
import numpy as np
import pytest
import scipy.stats

from filters.metrics import anees, anis, chi2_bounds, nees, nis, pcrb, rmse
from filters.models import (
    SINGER_CLOCK_POS,
    SINGER_CLOCK_VEL,
    ConstantVelocity,
    PseudorangeDoppler,
    singer_clock_transition,
)
from tests.helpers import random_gram_spd as random_spd


# ----------------------------------------------------------------------------- RMSE, NEES, NIS


def test_rmse():
    e = np.array([[3.0, 4.0], [0.0, 0.0], [-3.0, 4.0], [1.0, -1.0]])
    np.testing.assert_allclose(rmse(e), np.sqrt([19 / 4, 33 / 4]))
    # spherical error |e| per row, RMS over rows
    assert rmse(e, axis=0, norm_axis=-1) == pytest.approx(np.sqrt((25 + 0 + 25 + 2) / 4))
    err = np.ones((10, 7, 3))
    assert rmse(err, axis=0, norm_axis=-1).shape == (7,)
    assert rmse(err, axis=None, norm_axis=-1) == pytest.approx(np.sqrt(3.0))


def test_nees_and_nis_equal_the_explicit_quadratic_form():
    rng = np.random.default_rng(1)
    P = random_spd(rng, 5, (4, 6))
    e = rng.normal(size=(4, 6, 5))
    expect = np.einsum("...i,...ij,...j->...", e, np.linalg.inv(P), e)
    np.testing.assert_allclose(nees(e, P), expect, rtol=1e-10)
    np.testing.assert_allclose(nis(e, P), expect, rtol=1e-10)
    # one covariance broadcast over a batch of errors
    np.testing.assert_allclose(nees(e, P[0, 0]), np.einsum("...i,ij,...j->...", e,
                                                           np.linalg.inv(P[0, 0]), e), rtol=1e-10)
    with pytest.raises(ValueError, match="P"):
        nees(e, -P)
    with pytest.raises(ValueError, match="S"):
        nis(e, P[..., :4, :4])


@pytest.mark.parametrize(
    "dof,n_runs,p", [(1, 1, 0.95), (3, 50, 0.99), (11, 10000, 0.99), (8, 200, 0.9)]
)
def test_chi2_bounds_against_scipy(dof, n_runs, p):
    lo, hi = chi2_bounds(dof, n_runs, p)
    k = dof * n_runs
    assert lo == pytest.approx(scipy.stats.chi2.ppf((1 - p) / 2, k) / n_runs, rel=1e-12)
    assert hi == pytest.approx(scipy.stats.chi2.isf((1 - p) / 2, k) / n_runs, rel=1e-12)
    assert scipy.stats.chi2.cdf(hi * n_runs, k) - scipy.stats.chi2.cdf(lo * n_runs, k) == \
        pytest.approx(p, rel=1e-9)
    assert lo < dof < hi


def test_anees_of_exact_covariance_samples_is_consistent_and_the_check_can_fail():
    rng = np.random.default_rng(2024)
    n, runs, steps = 6, 200, 40
    P = random_spd(rng, n, (steps,))
    e = np.einsum("kij,rkj->rki", np.linalg.cholesky(P), rng.normal(size=(runs, steps, n)))
    a = anees(e, P, axis=0)
    assert a.shape == (steps,)
    lo, hi = chi2_bounds(n, runs, 0.99)
    assert np.mean((a > lo) & (a < hi)) >= 0.95
    lo_all, hi_all = chi2_bounds(n, runs * steps, 0.999)
    assert lo_all < a.mean() < hi_all
    # an overconfident (P too small) and an underconfident filter both leave the bounds
    assert np.all(anees(e, 0.7 * P, axis=0) > hi)
    assert np.all(anees(e, 1.5 * P, axis=0) < lo)
    assert not lo_all < anees(e, 0.95 * P, axis=0).mean() < hi_all
    # NIS is the same statistic on innovations
    np.testing.assert_allclose(anis(e, P, axis=0), a)


def test_chi2_bounds_reject_bad_arguments():
    for args, name in [((0, 10), "dof"), ((3, 0), "n_runs"), ((3, 10, 1.0), "p")]:
        with pytest.raises(ValueError, match=name):
            chi2_bounds(*args)


# ----------------------------------------------------------------------------- PCRB


def kalman_riccati(P0, F, Q, Hs, R, first_meas_at_0):
    """The covariance of the Kalman filter, written the textbook way (Joseph form)."""
    P = P0.copy()
    out = []
    for j, H in enumerate(Hs):
        if not (first_meas_at_0 and j == 0):
            P = F @ P @ F.T + Q
        S = H @ P @ H.T + R
        K = P @ H.T @ np.linalg.inv(S)
        I_KH = np.eye(len(P)) - K @ H
        P = I_KH @ P @ I_KH.T + K @ R @ K.T
        out.append(P)
    return np.array(out)


@pytest.mark.parametrize("first_meas_at_0", [False, True])
def test_pcrb_of_a_linear_gaussian_model_is_the_kalman_covariance(first_meas_at_0):
    rng = np.random.default_rng(5)
    cv = ConstantVelocity(2, q=0.3)
    dt, steps = 0.5, 30
    F, Q = cv.F(None, dt), cv.Q(dt)
    P0 = random_spd(rng, 4)
    Hs = rng.normal(size=(steps, 3, 4))  # time-varying but deterministic H
    R = random_spd(rng, 3)
    B = pcrb(np.linalg.inv(P0), cv, dt, steps, Hs, R, first_meas_at_0=first_meas_at_0)
    P = kalman_riccati(P0, F, Q, Hs, R, first_meas_at_0)
    np.testing.assert_allclose(B, P, rtol=1e-9, atol=1e-12)
    # the same with the deterministic H given as N_mc identical samples
    B4 = pcrb(np.linalg.inv(P0), cv, dt, steps, np.repeat(Hs[:, None], 5, axis=1), R,
              first_meas_at_0=first_meas_at_0)
    np.testing.assert_allclose(B4, P, rtol=1e-9, atol=1e-12)


def singer_clock_geometry(rng, steps, n_mc, n_sats, dt=0.01):
    """True states on a straight accelerating path under fixed satellites, Jacobians H."""
    r_e = 6.371e6
    sat_dir = rng.normal(size=(n_sats, 3)) + np.array([3.0, 0.0, 0.0])
    sat_dir /= np.linalg.norm(sat_dir, axis=1)[:, None]
    sp = 2.66e7 * sat_dir
    sv = rng.normal(size=(n_sats, 3)) * 3e3
    x0 = np.zeros((n_mc, 11))
    x0[:, SINGER_CLOCK_POS] = np.array([r_e, 0.0, 0.0]) + rng.normal(size=(n_mc, 3)) * 50.0
    x0[:, SINGER_CLOCK_VEL] = np.array([0.0, 100.0, 0.0]) + rng.normal(size=(n_mc, 3))
    t = dt * np.arange(1, steps + 1)
    xs = np.repeat(x0[None], steps, axis=0)
    xs[..., SINGER_CLOCK_POS] += t[:, None, None] * x0[None, :, SINGER_CLOCK_VEL]
    return sp, sv, xs


def test_pcrb_singer_clock_deterministic_geometry_matches_riccati_despite_singular_q():
    # seed 001 model: Q is singular (paper clock) and badly scaled (T = 0.01)
    rng = np.random.default_rng(11)
    m = singer_clock_transition()
    dt, steps = 0.01, 200
    sp, sv, xs = singer_clock_geometry(rng, steps, 1, 4)
    Hs = PseudorangeDoppler(sp, sv, 10.0, np.sqrt(15.0)).H(xs[:, 0])
    R = np.diag([100.0] * 4 + [15.0] * 4)
    P0 = np.diag([50.0**2] * 3 + [1e4] + [10.0**2] * 3 + [9.0] + [5.0**2] * 3)
    B = pcrb(np.linalg.inv(P0), m, dt, steps, Hs, R)
    P = kalman_riccati(P0, m.F(None, dt), m.Q(dt), Hs, R, False)
    np.testing.assert_allclose(B, P, rtol=1e-6, atol=1e-9)
    assert np.all(np.linalg.eigvalsh(B) > 0)


def loewner_leq(A, B, tol=1e-9):
    """A <= B in the Loewner order (B - A PSD), batched."""
    D = B - A
    w = np.linalg.eigvalsh(0.5 * (D + np.swapaxes(D, -1, -2)))
    scale = np.abs(np.linalg.eigvalsh(B)).max(axis=-1, keepdims=True)
    return bool(np.all(w >= -tol * scale))


@pytest.mark.slow
def test_pcrb_with_more_measurements_is_smaller():
    rng = np.random.default_rng(3)
    m = singer_clock_transition()
    dt, steps, n_mc = 0.01, 100, 500
    sp, sv, xs = singer_clock_geometry(rng, steps, n_mc, 6)
    H6 = PseudorangeDoppler(sp, sv, 10.0, np.sqrt(15.0)).H(xs)  # (steps, n_mc, 12, 11)
    R6 = np.diag([100.0] * 6 + [15.0] * 6)
    keep = [0, 1, 2, 3, 6, 7, 8, 9]  # satellites 1-4 only
    H4, R4 = H6[:, :, keep], R6[np.ix_(keep, keep)]
    J0 = np.linalg.inv(np.diag([50.0**2] * 3 + [1e4] + [10.0**2] * 3 + [9.0] + [5.0**2] * 3))
    B6 = pcrb(J0, m, dt, steps, H6, R6)
    B4 = pcrb(J0, m, dt, steps, H4, R4)
    assert loewner_leq(B6, B4)
    pos_trace = lambda B: np.trace(B[:, :3, :3], axis1=1, axis2=2)  # noqa: E731
    assert np.all(pos_trace(B6) < pos_trace(B4))
    # and the bound shrinks as measurements accumulate
    assert pos_trace(B6)[-1] < 0.5 * pos_trace(B6)[0]
    # a callable H and per-sample R give the same answer
    B6c = pcrb(J0, m, dt, steps, lambda j: H6[j], np.broadcast_to(R6, (steps, n_mc, 12, 12)))
    np.testing.assert_allclose(B6c, B6, rtol=1e-10, atol=1e-14)
    # the expectation over samples is not the value at one sample: geometry matters
    B6_one = pcrb(J0, m, dt, steps, H6[:, :1], R6)
    assert not np.allclose(B6_one, B6, rtol=1e-8)


def tichavsky_information_form(J0, F_samples, Q, H_samples, R):
    """TMN (1998) recursion verbatim: J+ = D22 - D21 (J + D11)^-1 D12 (test reference)."""
    Qi, Ri = np.linalg.inv(Q), np.linalg.inv(R)
    J = J0
    out = []
    for Fs, Hs in zip(F_samples, H_samples):
        D11 = np.mean(np.swapaxes(Fs, -1, -2) @ Qi @ Fs, axis=0)
        D12 = -np.mean(np.swapaxes(Fs, -1, -2), axis=0) @ Qi
        D22 = Qi + np.mean(np.swapaxes(Hs, -1, -2) @ Ri @ Hs, axis=0)
        J = D22 - D12.T @ np.linalg.solve(J + D11, D12)
        out.append(np.linalg.inv(J))
    return np.array(out)


class _RandomJacobianModel:
    """Stands in for a nonlinear transition: only Q (and linear=False) are used by pcrb."""

    linear = False
    ndim = 3

    def __init__(self, Q):
        self._Q = Q

    def Q(self, dt):
        return self._Q


def test_pcrb_nonlinear_form_equals_the_verbatim_tichavsky_recursion():
    rng = np.random.default_rng(8)
    n, m, steps, n_mc = 3, 2, 25, 40
    Fbar = np.array([[1.0, 0.1, 0.0], [0.0, 0.9, 0.2], [0.1, 0.0, 0.95]])
    F_samples = Fbar + 0.2 * rng.normal(size=(steps, n_mc, n, n))
    H_samples = rng.normal(size=(steps, n_mc, m, n))
    Q = random_spd(rng, n) * 0.3
    R = random_spd(rng, m)
    J0 = np.linalg.inv(random_spd(rng, n))
    B = pcrb(J0, _RandomJacobianModel(Q), 1.0, steps, H_samples, R, F_samples=F_samples)
    B_ref = tichavsky_information_form(J0, F_samples, Q, H_samples, R)
    np.testing.assert_allclose(B, B_ref, rtol=1e-9, atol=1e-12)
    # the F spread adds information-loss: it differs from using E[F] alone
    B_mean_F = pcrb(J0, _RandomJacobianModel(Q), 1.0, steps, H_samples, R,
                    F_samples=np.broadcast_to(F_samples.mean(1, keepdims=True), F_samples.shape))
    assert not np.allclose(B, B_mean_F, rtol=1e-3)


def test_pcrb_identical_f_samples_reduce_to_the_linear_path():
    m = ConstantVelocity(1, q=0.5)
    dt, steps = 0.2, 10
    H = np.broadcast_to(np.array([[[1.0, 0.0]]]), (steps, 1, 2))
    R = np.array([[4.0]])
    J0 = np.eye(2) * 0.01
    Fs = np.broadcast_to(m.F(None, dt), (steps, 7, 2, 2))
    np.testing.assert_allclose(pcrb(J0, m, dt, steps, H, R, F_samples=Fs),
                               pcrb(J0, m, dt, steps, H, R), rtol=1e-12)


def test_pcrb_rejects_bad_inputs():
    m = ConstantVelocity(1, q=0.5)
    H = np.ones((5, 1, 2))
    R = np.eye(1)
    with pytest.raises(ValueError, match="J0"):
        pcrb(-np.eye(2), m, 0.1, 5, H, R)
    with pytest.raises(ValueError, match="J0"):
        pcrb(np.eye(3)[:2], m, 0.1, 5, H, R)
    with pytest.raises(ValueError, match="steps"):
        pcrb(np.eye(2), m, 0.1, 0, H, R)
    with pytest.raises(ValueError, match="H"):
        pcrb(np.eye(2), m, 0.1, 6, H, R)
    with pytest.raises(ValueError, match="R"):
        pcrb(np.eye(2), m, 0.1, 5, H, -np.eye(1))
    with pytest.raises(ValueError, match="F_samples"):
        pcrb(np.eye(3), _RandomJacobianModel(np.eye(3)), 0.1, 5, np.ones((5, 1, 3)), R)
    # the seed 001 clock Q is singular: a varying F needs Q^-1
    s = singer_clock_transition()
    Fs = s.F(None, 0.01) + np.random.default_rng(0).normal(size=(3, 4, 11, 11)) * 1e-3
    with pytest.raises(ValueError, match="singular"):
        pcrb(np.eye(11), s, 0.01, 3, np.ones((3, 1, 11)), R, F_samples=Fs)
