"""State-space models: analytic discretisations against numerical integration, Jacobians
against finite differences, the seed 001 state order, and parameter validation."""
import dataclasses

import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings, strategies as st
from hypothesis.extra import numpy as hnp
from scipy.integrate import quad_vec

from filters.models import (
    SINGER_CLOCK_ACC,
    SINGER_CLOCK_BIAS,
    SINGER_CLOCK_DRIFT,
    SINGER_CLOCK_N,
    SINGER_CLOCK_POS,
    SINGER_CLOCK_VEL,
    ClockGaussMarkov,
    ClockRandomWalk,
    Composite,
    ConstantAcceleration,
    ConstantVelocity,
    LinearGaussian,
    PseudorangeDoppler,
    Singer,
    singer_clock_transition,
)

I3 = np.eye(3)


# ----------------------------------------------------------------------------- references


def van_loan(A, Qc, T):
    """Van Loan (1978): F = expm(A T), Q = int_0^T e^{As} Qc e^{A's} ds, from one expm."""
    n = A.shape[0]
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -A
    M[:n, n:] = Qc
    M[n:, n:] = A.T
    E = scipy.linalg.expm(M * T)
    F = E[n:, n:].T
    return F, F @ E[:n, n:]


def quad_q(A, G, q, T):
    """Q = int_0^T e^{As} G q G' e^{A's} ds by adaptive quadrature of expm."""
    def integrand(s):
        g = scipy.linalg.expm(A * s) @ G
        return q * np.outer(g, g)

    Q, _ = quad_vec(integrand, 0.0, T, epsabs=0.0, epsrel=1e-13)
    return Q


def singer_A(alpha):
    return np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -alpha]])


E3 = np.array([0.0, 0.0, 1.0])


def assert_rel(actual, expected, rtol):
    """Elementwise relative agreement (all entries of the matrices here are nonzero)."""
    actual, expected = np.asarray(actual), np.asarray(expected)
    assert np.all(expected != 0)
    err = np.max(np.abs(actual / expected - 1.0))
    assert err < rtol, f"max relative error {err:.3g} >= {rtol:.1g}"


# ----------------------------------------------------------------------------- Singer


# moderate alpha T: Van Loan is accurate here (its -A block grows like e^{alpha T})
@pytest.mark.parametrize("alpha,T", [(0.2, 1.0), (0.2, 5.0), (1.0, 0.5), (3.0, 1.0), (0.05, 2.0)])
def test_singer_q_equals_van_loan(alpha, T):
    sigma = 2.5
    _, Q = van_loan(singer_A(alpha), 2 * alpha * sigma**2 * np.outer(E3, E3), T)
    assert_rel(Singer(alpha, sigma, 1).Q(T), Q, 1e-10)


# the whole range, including the seed's alpha T = 0.002 where the closed forms cancel
@pytest.mark.parametrize(
    "alpha,T",
    [(0.2, 0.01), (0.2, 0.1), (1e-4, 1.0), (0.7, 1.3), (0.9, 1.2), (5.0, 2.0), (50.0, 1.0)],
)
def test_singer_q_equals_quadrature(alpha, T):
    sigma = 3.0
    Q = quad_q(singer_A(alpha), E3, 2 * alpha * sigma**2, T)
    assert_rel(Singer(alpha, sigma, 1).Q(T), Q, 1e-10)


def test_singer_q_seed_step_by_scaled_van_loan():
    # T = 0.01: rescale time and state, D = diag(T^2, T, 1), so that the expm is O(1):
    # Q(T) = T * D Qt D, Qt the unit-time Van Loan Q of the model with alpha -> alpha T.
    alpha, sigma, T = 0.2, 5.0, 0.01
    _, Qt = van_loan(singer_A(alpha * T), 2 * alpha * sigma**2 * np.outer(E3, E3), 1.0)
    D = np.diag([T**2, T, 1.0])
    assert_rel(Singer(alpha, sigma, 1).Q(T), T * D @ Qt @ D, 1e-10)


@pytest.mark.parametrize("alpha,T", [(0.2, 0.01), (0.2, 1.0), (2.0, 3.0), (1e-5, 0.5)])
def test_singer_f_equals_expm(alpha, T):
    F = Singer(alpha, 1.0, 1).F(None, T)
    Fe = scipy.linalg.expm(singer_A(alpha) * T)
    nz = np.triu(np.ones((3, 3), bool))
    assert np.all(F[~nz] == 0.0)
    assert_rel(F[nz], Fe[nz], 1e-12)


def test_singer_is_derivative_major_kron_over_axes():
    m1, m3 = Singer(0.3, 2.0, 1), Singer(0.3, 2.0, 3)
    T = 0.7
    np.testing.assert_array_equal(m3.F(None, T), np.kron(m1.F(None, T), I3))
    np.testing.assert_array_equal(m3.Q(T), np.kron(m1.Q(T), I3))
    assert m3.ndim == 9 and m3.linear
    Q = m3.Q(T)
    assert Q[0, 3] == m1.Q(T)[0, 1] and Q[0, 1] == 0.0 and Q[2, 8] == m1.Q(T)[0, 2]


def test_singer_tends_to_constant_acceleration_as_alpha_to_zero():
    # with 2 alpha sigma^2 = q held fixed, Singer -> white-noise jerk (CA)
    q, T = 0.8, 1.5
    for alpha in (1e-3, 1e-6):
        s = Singer(alpha, np.sqrt(q / (2 * alpha)), 3)
        ca = ConstantAcceleration(3, q=q)
        np.testing.assert_allclose(s.F(None, T), ca.F(None, T), rtol=2 * alpha * T, atol=alpha * T)
        np.testing.assert_allclose(s.Q(T), ca.Q(T), rtol=2 * alpha * T, atol=0)
    # and it is not CA for a sizeable alpha (the check can fail)
    s = Singer(0.5, np.sqrt(q / 1.0), 3)
    assert not np.allclose(s.Q(T), ConstantAcceleration(3, q=q).Q(T), rtol=1e-2)


def test_singer_steady_acceleration_variance_is_sigma_a_squared():
    # the seed's A(k) = A e^-aT + sigma_a sqrt(1 - e^-2aT) N keeps var(A) = sigma_a^2
    s = Singer(0.2, 5.0, 1)
    F, Q = s.F(None, 0.01), s.Q(0.01)
    assert F[2, 2] ** 2 * 25.0 + Q[2, 2] == pytest.approx(25.0, rel=1e-14)


def test_zero_step_is_identity_with_no_noise():
    for m in (Singer(0.2, 5.0), ConstantVelocity(q=1.0), ConstantAcceleration(q=1.0),
              ClockGaussMarkov(0.1, 3.0), ClockGaussMarkov(0.1, 3.0, exact_bias=True),
              ClockRandomWalk(1e-20), singer_clock_transition()):
        np.testing.assert_array_equal(m.F(None, 0.0), np.eye(m.ndim))
        np.testing.assert_array_equal(m.Q(0.0), np.zeros((m.ndim, m.ndim)))


# ----------------------------------------------------------------------------- CV / CA


@pytest.mark.parametrize("T", [0.01, 0.1, 1.0, 4.0])
def test_cv_and_ca_q_equal_van_loan(T):
    q = 0.37
    A2 = np.array([[0.0, 1.0], [0.0, 0.0]])
    F, Q = van_loan(A2, q * np.diag([0.0, 1.0]), T)
    cv = ConstantVelocity(1, q=q)
    np.testing.assert_allclose(cv.F(None, T), F, rtol=1e-13, atol=1e-15)
    assert_rel(cv.Q(T), Q, 1e-10)
    A3 = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    F, Q = van_loan(A3, q * np.diag([0.0, 0.0, 1.0]), T)
    ca = ConstantAcceleration(1, q=q)
    np.testing.assert_allclose(ca.F(None, T), F, rtol=1e-13, atol=1e-15)
    assert_rel(ca.Q(T), Q, 1e-10)
    np.testing.assert_array_equal(ConstantVelocity(3, q=q).Q(T), np.kron(cv.Q(T), I3))


def test_linear_f_is_batched_matrix_product():
    rng = np.random.default_rng(0)
    for m in (ConstantVelocity(3, q=1.0), Singer(0.2, 5.0), singer_clock_transition()):
        x = rng.normal(size=(4, 5, m.ndim))
        np.testing.assert_allclose(m.f(x, 0.3), np.einsum("ij,abj->abi", m.F(None, 0.3), x),
                                   rtol=1e-14, atol=1e-14)


# ----------------------------------------------------------------------------- clocks


def test_clock_gauss_markov_paper_discretisation():
    mu, sigma, T = 0.1, 3.0, 0.01
    m = ClockGaussMarkov(mu, sigma)
    np.testing.assert_array_equal(m.F(None, T), [[1.0, T], [0.0, np.exp(-mu * T)]])
    np.testing.assert_allclose(m.Q(T), [[0.0, 0.0], [0.0, sigma**2 * (1 - np.exp(-2 * mu * T))]],
                               rtol=1e-14)


def test_clock_gauss_markov_exact_bias_equals_van_loan():
    mu, sigma, T = 0.1, 3.0, 2.0
    A = np.array([[0.0, 1.0], [0.0, -mu]])
    F, Q = van_loan(A, 2 * mu * sigma**2 * np.diag([0.0, 1.0]), T)
    m = ClockGaussMarkov(mu, sigma, exact_bias=True)
    np.testing.assert_allclose(m.F(None, T), F, rtol=1e-13)
    assert_rel(m.Q(T), Q, 1e-10)
    # the paper's form differs from it (bias row T instead of (1 - e^-muT)/mu)
    assert not np.allclose(ClockGaussMarkov(mu, sigma).F(None, T), F, rtol=1e-6)


@pytest.mark.parametrize("exact", [False, True])
def test_clock_drift_variance_is_stationary(exact):
    m = ClockGaussMarkov(0.1, 3.0, exact_bias=exact)
    F, Q = m.F(None, 0.5), m.Q(0.5)
    P = np.diag([0.0, 9.0])
    assert (F @ P @ F.T + Q)[1, 1] == pytest.approx(9.0, rel=1e-14)


def test_clock_random_walk_iono_tropo():
    N, T, c = 0.8e-20, 0.1, 299_792_458.0
    m = ClockRandomWalk(N)
    np.testing.assert_allclose(m.Q(T), c**2 * N * np.array([[T**3 / 3, T**2 / 2], [T**2 / 2, T]]),
                               rtol=1e-15)
    _, Q = van_loan(np.array([[0.0, 1.0], [0.0, 0.0]]), c**2 * N * np.diag([0.0, 1.0]), T)
    assert_rel(m.Q(T), Q, 1e-10)
    np.testing.assert_array_equal(m.F(None, T), [[1.0, T], [0.0, 1.0]])


# ----------------------------------------------------------------------------- Composite


def test_singer_clock_blocks_land_at_the_seed_indices():
    alpha, sa, mu, sd, T = 0.2, 5.0, 0.1, 3.0, 0.01
    m = singer_clock_transition(alpha, sa, mu, sd)
    assert m.ndim == SINGER_CLOCK_N == 11 and m.linear
    F, Q = m.F(None, T), m.Q(T)
    F1, Q1 = Singer(alpha, sa, 1).F(None, T), Singer(alpha, sa, 1).Q(T)
    Fc, Qc = ClockGaussMarkov(mu, sd).F(None, T), ClockGaussMarkov(mu, sd).Q(T)
    kin = [SINGER_CLOCK_POS, SINGER_CLOCK_VEL, SINGER_CLOCK_ACC]
    for i, a in enumerate(kin):
        for j, b in enumerate(kin):
            np.testing.assert_array_equal(F[a, b], F1[i, j] * I3)
            np.testing.assert_array_equal(Q[a, b], Q1[i, j] * I3)
    clk = [SINGER_CLOCK_BIAS, SINGER_CLOCK_DRIFT]
    np.testing.assert_array_equal(F[np.ix_(clk, clk)], Fc)
    np.testing.assert_array_equal(Q[np.ix_(clk, clk)], Qc)
    kin_idx = np.r_[0:3, 4:7, 8:11]
    for M in (F, Q):
        assert not np.any(M[np.ix_(kin_idx, clk)]) and not np.any(M[np.ix_(clk, kin_idx)])
    # the seed's written rows: X(k) = X + T V + ..., D'(k) = D' + T V', A(k) = A e^-aT
    assert F[0, 4] == T and F[3, 7] == T and F[8, 8] == np.exp(-alpha * T)
    assert F[7, 7] == np.exp(-mu * T)


def test_composite_f_permutes_consistently_with_F():
    m = singer_clock_transition()
    x = np.arange(11.0) + 1.0
    np.testing.assert_allclose(m.f(x, 0.01), m.F(None, 0.01) @ x, rtol=1e-15)
    # x[3] is the bias, x[7] the drift: bias moves by T * drift
    assert m.f(x, 0.01)[3] == pytest.approx(x[3] + 0.01 * x[7], rel=1e-15)


@dataclasses.dataclass(frozen=True)
class _Pendulum:
    """A small nonlinear block for the batched-Jacobian path: [theta, omega]."""

    ndim = 2
    linear = False

    def f(self, x, dt):
        return np.stack([x[..., 0] + dt * x[..., 1], x[..., 1] - dt * np.sin(x[..., 0])], -1)

    def F(self, x, dt):
        J = np.zeros(x.shape[:-1] + (2, 2))
        J[..., 0, 0] = 1.0
        J[..., 0, 1] = dt
        J[..., 1, 0] = -dt * np.cos(x[..., 0])
        J[..., 1, 1] = 1.0
        return J

    def Q(self, dt):
        return np.diag([0.0, dt])


def test_composite_with_a_nonlinear_block_batches_its_jacobian():
    m = Composite((ConstantVelocity(1, q=1.0), _Pendulum()), order=(2, 0, 3, 1))
    assert not m.linear and m.ndim == 4
    rng = np.random.default_rng(3)
    x = rng.normal(size=(5, 4))  # [theta, p, omega, v]
    dt = 0.1
    J = m.F(x, dt)
    assert J.shape == (5, 4, 4)
    eps = 1e-6
    for k in range(4):
        d = np.zeros(4)
        d[k] = eps
        np.testing.assert_allclose((m.f(x + d, dt) - m.f(x - d, dt)) / (2 * eps), J[..., :, k],
                                   atol=1e-9)
    np.testing.assert_allclose(m.f(x, dt)[:, 1], x[:, 1] + dt * x[:, 3])
    np.testing.assert_allclose(m.f(x, dt)[:, 0], x[:, 0] + dt * x[:, 2])
    Q = m.Q(dt)  # x = [theta, p, omega, v]
    assert Q[2, 2] == dt and Q[3, 3] == dt and Q[1, 1] == dt**3 / 3 and Q[0, 0] == 0.0
    with pytest.raises(ValueError, match="x must be given"):
        m.F(None, dt)


# ----------------------------------------------------------------------------- PseudorangeDoppler


def _pr_model(sp, sv, **kw):
    sigma_pr, sigma_prr = kw.pop("sigma_pr_m", 10.0), kw.pop("sigma_prr_m_s", 0.1)
    return PseudorangeDoppler(sp, sv, sigma_pr, sigma_prr, **kw)


@pytest.mark.slow
def test_pseudorange_doppler_values_and_sign_convention():
    X = np.array([6.4e6, 0.0, 0.0])
    sp = np.array([[2.6e7, 0.0, 0.0], [6.4e6, 2.0e7, 0.0]])
    sv = np.array([[100.0, 3000.0, 0.0], [0.0, 50.0, 0.0]])
    x = np.zeros(11)
    x[SINGER_CLOCK_POS] = X
    x[SINGER_CLOCK_VEL] = [10.0, 0.0, 0.0]
    x[SINGER_CLOCK_BIAS], x[SINGER_CLOCK_DRIFT] = 123.0, -4.0
    z = _pr_model(sp, sv).h(x)
    # stacked: [pr_1, pr_2, prr_1, prr_2]
    expect = [1.96e7 + 123.0, 2.0e7 + 123.0, 90.0 - 4.0, 50.0 - 4.0]
    np.testing.assert_allclose(z, expect, rtol=1e-15)
    # satellite 1 moves away along the line of sight: positive range rate


geom = st.integers(1, 8).flatmap(
    lambda S: st.tuples(
        hnp.arrays(float, (3,), elements=st.floats(-7e6, 7e6)),
        hnp.arrays(float, (3,), elements=st.floats(-400, 400)),
        hnp.arrays(float, (S, 3), elements=st.floats(-1.0, 1.0)).filter(
            lambda d: np.all(np.linalg.norm(d, axis=1) > 0.1)),
        hnp.arrays(float, (S,), elements=st.floats(2.0e7, 2.7e7)),
        hnp.arrays(float, (S, 3), elements=st.floats(-4000, 4000)),
        st.floats(-1e5, 1e5),
        st.floats(-300, 300),
    )
)


@pytest.mark.slow
@settings(max_examples=60, deadline=None, derandomize=True, database=None)
@given(geom)
def test_pseudorange_doppler_jacobian_matches_central_differences(g):
    X, V, dirs, radius, sv, bias, drift = g
    sp = X + dirs / np.linalg.norm(dirs, axis=1)[:, None] * radius[:, None]
    m = _pr_model(sp, sv)
    x = np.zeros(11)
    x[SINGER_CLOCK_POS], x[SINGER_CLOCK_VEL] = X, V
    x[SINGER_CLOCK_BIAS], x[SINGER_CLOCK_DRIFT] = bias, drift
    x[SINGER_CLOCK_ACC] = [1.0, 2.0, 3.0]
    H = m.H(x)
    assert H.shape == (2 * len(sp), 11)
    # h is linear in all but the position, where its curvature is ~1/|S - X| ~ 1e-7 /m:
    # a 1 m (1 m/s) step has negligible truncation error, and the round-off of a
    # difference of two ~3e7 m ranges is ~ulp(3e7)/2 ~ 2e-9, of two ~5e3 m/s rates ~1e-12.
    Hfd = np.empty_like(H)
    for k in range(11):
        d = np.zeros(11)
        d[k] = 1.0
        Hfd[:, k] = (m.h(x + d) - m.h(x - d)) / 2.0
    S = len(sp)
    np.testing.assert_allclose(H[:S], Hfd[:S], rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(H[S:], Hfd[S:], rtol=1e-6, atol=1e-10)
    # the explicit position row of the rates: -(V_S - V)'(I - u u')/|S - X|
    r = sp - X
    rho = np.linalg.norm(r, axis=1)
    u = r / rho[:, None]
    for i in range(len(sp)):
        expect = -(sv[i] - V) @ (np.eye(3) - np.outer(u[i], u[i])) / rho[i]
        np.testing.assert_allclose(H[len(sp) + i, SINGER_CLOCK_POS], expect, rtol=1e-12, atol=1e-18)


def test_pseudorange_doppler_batches_like_the_ukf_calls_it():
    rng = np.random.default_rng(7)
    B, S, K = 6, 4, 23
    sp = rng.normal(size=(B, S, 3)) * 1.5e7 + np.array([0.0, 0.0, 2e7])
    sv = rng.normal(size=(B, S, 3)) * 3e3
    m = _pr_model(sp, sv, sigma_pr_m=np.array([10.0, 11.0, 12.0, 13.0]))
    x = rng.normal(size=(K, B, 11)) * 1e3
    z = m.h(x)
    H = m.H(x)
    assert z.shape == (K, B, 2 * S) and H.shape == (K, B, 2 * S, 11)
    for k, b in [(0, 0), (5, 3), (22, 5)]:
        single = _pr_model(sp[b], sv[b], sigma_pr_m=np.array([10.0, 11.0, 12.0, 13.0]))
        np.testing.assert_allclose(z[k, b], single.h(x[k, b]), rtol=1e-15)
        np.testing.assert_allclose(H[k, b], single.H(x[k, b]), rtol=1e-15)
    np.testing.assert_allclose(m.R_diag(), [100.0, 121.0, 144.0, 169.0] + [0.1**2] * 4, rtol=1e-15)
    np.testing.assert_array_equal(m.R(), np.diag(m.R_diag()))


def test_pseudorange_doppler_custom_indices_and_batched_sigmas():
    sp = np.array([[2e7, 1e7, 0.0], [0.0, 2e7, 1e7]])
    sv = np.zeros((2, 3))
    m = PseudorangeDoppler(sp, sv, np.array([[3.0, 4.0], [5.0, 6.0]]), 0.5,
                           idx_pos=slice(0, 3), idx_vel=(3, 4, 5), idx_bias=6, idx_drift=7, n=8)
    x = np.zeros(8)
    x[6] = 1.0
    assert m.h(x)[0] == pytest.approx(np.linalg.norm(sp[0]) + 1.0)
    assert m.R_diag().shape == (2, 4) and m.R().shape == (2, 4, 4)
    np.testing.assert_array_equal(m.R_diag()[1], [25.0, 36.0, 0.25, 0.25])
    assert m.H(x)[0, 6] == 1.0 and m.H(x)[2, 7] == 1.0


def test_measurement_model_is_immutable_without_copying_the_caller():
    sp = np.array([[2e7, 0.0, 0.0]])
    sv = np.zeros((1, 3))
    m = _pr_model(sp, sv)
    with pytest.raises(dataclasses.FrozenInstanceError):
        m.sigma_pr_m = 3.0
    with pytest.raises(ValueError):
        m.sat_pos_ecef_m[0, 0] = 1.0
    assert np.shares_memory(m.sat_pos_ecef_m, sp) and sp.flags.writeable


def test_linear_gaussian():
    H = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    m = LinearGaussian(H, np.diag([4.0, 9.0]))
    x = np.arange(12.0).reshape(4, 3)
    np.testing.assert_array_equal(m.h(x), x @ H.T)
    assert m.H(x).shape == (4, 2, 3) and m.ndim_meas == 2 and m.ndim_state == 3
    np.testing.assert_array_equal(m.R_diag(), [4.0, 9.0])
    assert LinearGaussian(H, [[4.0, 1.0], [1.0, 9.0]]).R_diag() is None


# ----------------------------------------------------------------------------- validation


@pytest.mark.parametrize(
    "make,name",
    [
        (lambda: Singer(-0.2, 5.0), "alpha_1_s"),
        (lambda: Singer(0.0, 5.0), "alpha_1_s"),
        (lambda: Singer(0.2, float("nan")), "sigma_a_m_s2"),
        (lambda: Singer(0.2, 5.0, ndim_pos=0), "ndim_pos"),
        (lambda: ConstantVelocity(3, q=-1.0), "q"),
        (lambda: ConstantAcceleration(2.5, q=1.0), "ndim_pos"),
        (lambda: ClockGaussMarkov(0.0, 3.0), "mu_1_s"),
        (lambda: ClockGaussMarkov(0.1, -3.0), "sigma_drift_m_s"),
        (lambda: ClockRandomWalk(-1e-20), "psd_1_s"),
        (lambda: ClockRandomWalk(1e-20, c=0.0), "c"),
        (lambda: singer_clock_transition(alpha_1_s=-1.0), "alpha_1_s"),
        (lambda: Composite((Singer(0.2, 1.0), ClockRandomWalk(0.0)), order=(0, 1)), "order"),
        (lambda: Composite((Singer(0.2, 1.0), object())), "blocks"),
        (lambda: Singer(0.2, 5.0).Q(-0.01), "dt"),
        (lambda: Singer(0.2, 5.0).F(None, float("inf")), "dt"),
        (lambda: Singer(0.2, 5.0).f(np.zeros(8), 0.1), "x"),
        (lambda: _pr_model(np.zeros((4, 2)), np.zeros((4, 2))), "sat_pos_ecef_m"),
        (lambda: _pr_model(np.ones((4, 3)), np.zeros((3, 3))), "sat_vel_ecef_m_s"),
        (lambda: _pr_model(np.ones((4, 3)), np.zeros((4, 3)), sigma_pr_m=0.0), "sigma_pr_m"),
        (lambda: _pr_model(np.ones((4, 3)), np.zeros((4, 3)), sigma_prr_m_s=np.ones(3)),
         "sigma_prr_m_s"),
        (lambda: _pr_model(np.ones((4, 3)), np.zeros((4, 3)), idx_bias=11), "idx_bias"),
        (lambda: _pr_model(np.ones((4, 3)), np.zeros((4, 3)), idx_drift=4),
         "idx_pos, idx_vel, idx_bias, idx_drift"),
        (lambda: _pr_model(np.ones((4, 3)), np.zeros((4, 3)), idx_vel=(4, 5)), "idx_vel"),
        (lambda: LinearGaussian(np.ones((2, 3)), np.eye(3)), "R"),
    ],
)
def test_bad_parameters_raise_value_error_naming_them(make, name):
    with pytest.raises(ValueError, match=name.replace("(", r"\(")):
        make()


# ----------------------------------------------------------------------------- the model protocols


def _clock_free_case(rng, batch=(4,), S=5):
    sp = rng.standard_normal(batch + (S, 3)) * 2.0e7
    sv = rng.standard_normal(batch + (S, 3)) * 3.0e3
    x = np.concatenate([rng.standard_normal(batch + (3,)) * 1e5, rng.standard_normal(batch + (3,)) * 50.0], -1)
    return sp, sv, x


@pytest.mark.slow
def test_clock_free_pseudorange_doppler_is_pseudorange_doppler_without_the_clock():
    """filters.models.ClockFreePseudorangeDoppler (moved from vehicles/uav_nav.py) against
    PseudorangeDoppler on the 8-state [X, D', V, V'] with the clock states at 0: the same h and
    the same H with the clock columns removed; untracked channels give h = 0, H = 0, r = 1."""
    from filters.models import ClockFreePseudorangeDoppler

    rng = np.random.default_rng(3)
    sp, sv, x = _clock_free_case(rng)
    cf = ClockFreePseudorangeDoppler(sp, sv, 900.0, 0.04)
    pd = PseudorangeDoppler(sp, sv, 30.0, 0.2, idx_pos=(0, 1, 2), idx_vel=(4, 5, 6), idx_bias=3, idx_drift=7, n=8)
    x8 = np.zeros(x.shape[:-1] + (8,))
    x8[..., 0:3], x8[..., 4:7] = x[..., 0:3], x[..., 3:6]
    h, H = cf.h_and_H(x)
    h8, H8 = pd.h_and_H(x8)
    np.testing.assert_allclose(h, h8, rtol=1e-13)
    np.testing.assert_allclose(H, H8[..., [0, 1, 2, 4, 5, 6]], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(cf.R_diag(), np.broadcast_to(pd.R_diag(), (4, 10)), rtol=1e-12)
    np.testing.assert_array_equal(cf.R(), cf.R_diag()[..., None] * np.eye(10))
    tracked = np.ones((4, 5), bool)
    tracked[:, 2] = False
    cfm = ClockFreePseudorangeDoppler(np.where(tracked[..., None], sp, np.nan), sv, 900.0, 0.04, tracked)
    hm, Hm = cfm.h_and_H(x)
    assert np.all(hm[:, [2, 7]] == 0.0) and np.all(Hm[:, [2, 7]] == 0.0) and np.all(cfm.R_diag()[:, [2, 7]] == 1.0)
    np.testing.assert_array_equal(hm[:, [0, 1, 3, 4]], h[:, [0, 1, 3, 4]])


def test_every_filters_model_is_a_protocol_model():
    from filters.beacon import ObserverRangeDoppler
    from filters.iono_tropo import IonoTropoTransition
    from filters.models import ClockFreePseudorangeDoppler
    from filters.protocols import MeasurementModel, SigmaPointMeasurementModel, TransitionModel

    rng = np.random.default_rng(4)
    sp, sv, _ = _clock_free_case(rng)
    transitions = [ConstantVelocity(3, q=1.0), ConstantAcceleration(3, q=1.0), Singer(0.2, 5.0),
                   ClockGaussMarkov(0.1, 3.0), ClockRandomWalk(1e-20), singer_clock_transition(),
                   IonoTropoTransition()]
    measurements = [LinearGaussian(np.eye(2), np.eye(2)), PseudorangeDoppler(sp, sv, 30.0, 0.2),
                    ClockFreePseudorangeDoppler(sp, sv, 900.0, 0.04),
                    ObserverRangeDoppler(sp[..., :3, :], sv[..., :3, :], 1.0, 0.01, observer_uncertainty="ignore")]
    for m in transitions:
        assert isinstance(m, TransitionModel), m
        assert isinstance(m.linear, bool)
    for m in measurements:
        assert isinstance(m, MeasurementModel) and isinstance(m, SigmaPointMeasurementModel), m


class _NoLinear:  # a transition model that does not declare ``linear``
    def f(self, x, dt):
        return x

    def F(self, x, dt):
        return np.eye(2)

    def Q(self, dt):
        return np.eye(2)


class _HOnly:  # a measurement model with h and H but no h_and_H (and not derived from Measurement)
    def h(self, x):
        return x

    def H(self, x):
        return np.broadcast_to(np.eye(2), x.shape[:-1] + (2, 2))

    def R_diag(self):
        return np.ones(2)


class _JointOnly:  # h_and_H and R_diag only: what the EKF-type filters need, and not the UKF
    def h_and_H(self, x):
        return x, np.broadcast_to(np.eye(2), x.shape[:-1] + (2, 2))

    def R_diag(self):
        return np.ones(2)


class _FullROnlyByDiagNone(_JointOnly):  # R_diag None (a full R) but no R()
    def R_diag(self):
        return None


@pytest.mark.slow
def test_a_model_without_a_protocol_member_fails_naming_it():
    from filters.ekf import ekf_predict, ekf_step, ekf_update
    from filters.integrity import IntegrityMonitor
    from filters.ud import ud_predict, ud_update
    from filters.ukf import ukf_predict, ukf_update

    x, P = np.zeros((3, 2)), np.broadcast_to(np.eye(2), (3, 2, 2)).copy()
    U, d = np.broadcast_to(np.eye(2), (3, 2, 2)).copy(), np.ones((3, 2))
    z = np.zeros((3, 2))
    good = ConstantVelocity(1, q=1.0)
    meas = LinearGaussian(np.eye(2), np.eye(2))
    for call in (lambda: ekf_predict(x, P, _NoLinear(), 1.0), lambda: ekf_step(x, P, z, _NoLinear(), meas, 1.0),
                 lambda: ukf_predict(x, P, _NoLinear(), 1.0), lambda: ud_predict(x, U, d, _NoLinear(), 1.0)):
        with pytest.raises(TypeError, match=r"transition model _NoLinear is not a TransitionModel .*no linear"):
            call()
    mon = IntegrityMonitor()
    for call in (lambda: ekf_update(x, P, z, _HOnly()), lambda: ekf_step(x, P, z, good, _HOnly(), 1.0),
                 lambda: ud_update(x, U, d, z, _HOnly()),
                 lambda: mon.step(mon.init((3,), 2, 2), x, P, z, _HOnly(), np.arange(2))):
        with pytest.raises(TypeError, match=r"measurement model _HOnly is not a MeasurementModel .*no h_and_H"):
            call()
    with pytest.raises(TypeError, match=r"_JointOnly is not a SigmaPointMeasurementModel .*no h\b"):
        ukf_update(x, P, z, _JointOnly())
    with pytest.raises(TypeError, match=r"_FullROnlyByDiagNone returned R_diag\(\) None and has no R\(\)"):
        ekf_update(x, P, z, _FullROnlyByDiagNone())
    # the filters take the h_and_H-only model as it is
    ekf_update(x, P, z, _JointOnly())


def test_measurement_bases_complete_a_model():
    from filters.models import JointMeasurement, Measurement

    class Hh(Measurement, _HOnly):
        pass

    class Joint(JointMeasurement, _JointOnly):
        pass

    x = np.arange(6.0).reshape(3, 2)
    h, H = Hh().h_and_H(x)
    np.testing.assert_array_equal(h, x)
    np.testing.assert_array_equal(H, np.broadcast_to(np.eye(2), (3, 2, 2)))
    j = Joint()
    np.testing.assert_array_equal(j.h(x), x)
    np.testing.assert_array_equal(j.H(x), H)
    np.testing.assert_array_equal(j.R(), np.eye(2))
    np.testing.assert_array_equal(Hh().R(), np.eye(2))
    with pytest.raises(TypeError, match="R_diag.. returned None"):
        type("FullR", (JointMeasurement, _FullROnlyByDiagNone), {})().R()
