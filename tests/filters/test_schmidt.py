"""The Schmidt (consider) update (filters/schmidt.py).

* against a direct dense implementation: the full Kalman update of the joint state [x, eps_1,
  ..., eps_N] in Joseph form with the consider states' gain rows set to zero (x, P, the
  cross-covariances C, and Pc left as it was), with some sensors unused;
* with no cross-covariance it is the ordinary update with R_g + J_g Pc_g J_g' (FilterPy's
  kalman.update as the peer);
* Monte Carlo: the errors of the Schmidt update have the covariance it reports (NEES inside
  the chi-square band, and the empirical Cov(error, eps) equals C+), while the update that
  drops the cross-covariances is over-confident on the same draws (the check can fail);
* a multi-axis batch equals the flat one; nis is NaN where no sensor is used.
"""
from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import scipy.stats
from filterpy.kalman import update as filterpy_update

from filters.schmidt import schmidt_innovation, schmidt_update


def _case(rng, T, n=5, N=3, r=2, k=4):
    """A joint covariance over [x (n), eps_1 (k), ..., eps_N (k)] with the eps_g independent of
    each other, and the sensors' H (T, N, r, n), J (T, N, r, k), R (T, N, r, r), nu (T, N, r)."""
    d = n + N * k
    A = rng.standard_normal((T, d, d))
    Pj = A @ np.swapaxes(A, -1, -2) + d * np.eye(d)
    for g in range(N):  # no correlation between two sensors' consider states
        for h in range(N):
            if g != h:
                Pj[:, n + g * k:n + (g + 1) * k, n + h * k:n + (h + 1) * k] = 0.0
    P = Pj[:, :n, :n]
    C = np.stack([Pj[:, :n, n + g * k:n + (g + 1) * k] for g in range(N)], axis=1)
    Pc = np.stack([Pj[:, n + g * k:n + (g + 1) * k, n + g * k:n + (g + 1) * k] for g in range(N)], axis=1)
    H = rng.standard_normal((T, N, r, n))
    J = rng.standard_normal((T, N, r, k))
    B = rng.standard_normal((T, N, r, r))
    R = B @ np.swapaxes(B, -1, -2) + np.eye(r)
    nu = rng.standard_normal((T, N, r))
    x = rng.standard_normal((T, n))
    return x, P, C, Pc, H, J, R, nu, Pj


def _dense(x, Pj, H, J, R, nu, used, n, k):
    """The joint update in Joseph form, consider gain rows zeroed, used sensors' rows only."""
    N, r = H.shape[0], H.shape[1]
    d = Pj.shape[0]
    rows = [g for g in range(N) if used[g]]
    Hj = np.zeros((len(rows) * r, d))
    for a, g in enumerate(rows):
        Hj[a * r:(a + 1) * r, :n] = H[g]
        Hj[a * r:(a + 1) * r, n + g * k:n + (g + 1) * k] = J[g]
    Rj = scipy.linalg.block_diag(*[R[g] for g in rows])
    S = Hj @ Pj @ Hj.T + Rj
    K = Pj @ Hj.T @ np.linalg.inv(S)
    K[n:] = 0.0  # the consider states are not estimated
    v = np.concatenate([nu[g] for g in rows])
    IKH = np.eye(d) - K @ Hj
    Pn = IKH @ Pj @ IKH.T + K @ Rj @ K.T
    return x + K[:n] @ v, Pn, v @ np.linalg.solve(S, v)


@pytest.mark.parametrize("used_pattern", ["all", "some"])
def test_equals_the_joint_update_with_zero_consider_gain(used_pattern):
    rng = np.random.default_rng(3)
    T, n, N, r, k = 4, 5, 3, 2, 4
    x, P, C, Pc, H, J, R, nu, Pj = _case(rng, T, n, N, r, k)
    used = np.ones((T, N), bool) if used_pattern == "all" else rng.random((T, N)) < 0.6
    used[:, 0] = True
    inn = schmidt_innovation(P, C, H, J, Pc, R)
    out = schmidt_update(x, P, C, nu, H, J, Pc, inn, used)
    for t in range(T):
        xd, Pd, nis_d = _dense(x[t], Pj[t], H[t], J[t], R[t], nu[t], used[t], n, k)
        np.testing.assert_allclose(out.x[t], xd, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(out.P[t], Pd[:n, :n], rtol=1e-10, atol=1e-9)
        for g in range(N):
            np.testing.assert_allclose(out.C[t, g], Pd[:n, n + g * k:n + (g + 1) * k], rtol=1e-10, atol=1e-9)
            # the joint Joseph update leaves the consider covariance as it was
            np.testing.assert_allclose(Pd[n + g * k:n + (g + 1) * k, n + g * k:n + (g + 1) * k], Pc[t, g],
                                       rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(out.nis[t], nis_d, rtol=1e-10)
        # each sensor's own block of S is the joint S's
        for g in range(N):
            hg = np.zeros((r, Pj.shape[-1]))
            hg[:, :n], hg[:, n + g * k:n + (g + 1) * k] = H[t, g], J[t, g]
            np.testing.assert_allclose(inn.S_blocks[t, g], hg @ Pj[t] @ hg.T + R[t, g], rtol=1e-10)


def test_without_cross_covariance_it_is_the_update_with_the_consider_term_in_R():
    rng = np.random.default_rng(5)
    T, n, N, r, k = 3, 5, 3, 2, 4
    x, P, C, Pc, H, J, R, nu, _ = _case(rng, T, n, N, r, k)
    C = np.zeros_like(C)
    out = schmidt_update(x, P, C, nu, H, J, Pc, schmidt_innovation(P, C, H, J, Pc, R), np.ones((T, N), bool))
    for t in range(T):
        Re = scipy.linalg.block_diag(*[R[t, g] + J[t, g] @ Pc[t, g] @ J[t, g].T for g in range(N)])
        Hs = H[t].reshape(N * r, n)
        xf, Pf = filterpy_update(x[t], P[t], nu[t].reshape(-1) + Hs @ x[t], Re, Hs)  # z = nu + H x-
        np.testing.assert_allclose(out.x[t], xf, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(out.P[t], Pf, rtol=1e-9, atol=1e-9)


def test_monte_carlo_errors_have_the_reported_covariance_and_dropping_C_does_not():
    """One prior (x-, P, C, Pc) and M draws of the truth [x, eps] from it and of the noise: the
    errors of x+ have covariance P+ and cross-covariance C+ with eps. Each sensor's consider state
    took up some components of the state's error (sensor 0: e_0, sensor 1: e_1 and e_2; eps_g =
    0.9 E_g e + w_g: an observer's navigation error the state's error has followed; independent
    across sensors, as the model holds) and J_g = -H_g: the update that drops C misjudges what
    the measurements say, on the same draws."""
    rng = np.random.default_rng(11)
    n, N, r, M = 3, 2, 2, 20000
    s0 = np.array([3.0, 2.0, 1.0])
    P0 = np.diag(s0**2)
    E = np.stack([np.diag([1.0, 0.0, 0.0]), np.diag([0.0, 1.0, 1.0])])  # the components sensor g took up
    C = (0.9 * P0 @ E)[None]  # Cov(e, eps_g)
    Pc = (0.81 * E @ P0 @ E + 0.09 * np.eye(n))[None]
    H = rng.standard_normal((1, N, r, n))
    J = -H
    R = np.broadcast_to(0.01 * np.eye(r), (1, N, r, r)).copy()
    x, P = np.zeros((1, n)), P0[None]
    e = rng.standard_normal((M, n)) * s0
    eps = 0.9 * np.einsum("gij,mj->mgi", E, e) + 0.3 * rng.standard_normal((M, N, n))
    v = 0.1 * rng.standard_normal((M, N, r))
    nu = np.einsum("gai,mi->mga", H[0], e) + np.einsum("gab,mgb->mga", J[0], eps) + v  # z - h(x-)
    xb = np.broadcast_to(x[0], (M, n))

    def run(Cp):
        Pb, Cb, Hb, Jb, Pcb, Rb = (np.broadcast_to(a[0], (M,) + a.shape[1:]) for a in (P, Cp, H, J, Pc, R))
        inn = schmidt_innovation(Pb, Cb, Hb, Jb, Pcb, Rb)
        return schmidt_update(xb, Pb, Cb, nu, Hb, Jb, Pcb, inn, np.ones((M, N), bool))

    lo, hi = scipy.stats.chi2.ppf([0.0005, 0.9995], M * n) / M  # (2.94, 3.06)
    good, bad = run(C), run(np.zeros_like(C))
    nees = [np.einsum("mi,mij,mj->m", e - out.x, np.linalg.inv(out.P), e - out.x).mean() for out in (good, bad)]
    assert lo <= nees[0] <= hi, (nees[0], lo, hi)
    assert nees[1] > hi + 0.3, (nees[1], lo, hi)  # (3.69)
    Cemp = np.einsum("mi,mgb->gib", e - good.x, eps) / M
    np.testing.assert_allclose(Cemp, good.C[0], atol=0.03 * np.sqrt(np.max(np.diag(good.P[0])) * np.max(Pc)))


def test_batch_shapes_and_unused_sensors():
    rng = np.random.default_rng(8)
    x, P, C, Pc, H, J, R, nu, _ = _case(rng, 6)
    used = np.array([[0, 0, 0], [1, 0, 1], [1, 1, 0], [1, 1, 1], [0, 1, 0], [1, 0, 0]], bool)
    flat = schmidt_update(x, P, C, nu, H, J, Pc, schmidt_innovation(P, C, H, J, Pc, R), used)
    b = (2, 3)
    sh = [a.reshape(b + a.shape[1:]) for a in (x, P, C, nu, H, J, Pc, R)]
    xs, Ps, Cs, nus, Hs, Js, Pcs, Rs = sh
    multi = schmidt_update(xs, Ps, Cs, nus, Hs, Js, Pcs, schmidt_innovation(Ps, Cs, Hs, Js, Pcs, Rs),
                           used.reshape(b + (3,)))
    for a, m in zip(flat, multi):
        np.testing.assert_array_equal(a, m.reshape(a.shape))
    assert np.isnan(flat.nis[0])
    np.testing.assert_array_equal(flat.x[0], x[0])
    np.testing.assert_array_equal(flat.C[0], C[0])
    # an unused sensor's rows change nothing: the same as dropping them (its own C still moves
    # with the state's correction)
    for t in (1, 2):
        keep = np.flatnonzero(used[t])
        Cs1, nus1, Hs1, Js1, Pcs1, Rs1 = (a[t:t + 1][:, keep] for a in (C, nu, H, J, Pc, R))
        one = schmidt_update(x[t:t + 1], P[t:t + 1], Cs1, nus1, Hs1, Js1, Pcs1,
                             schmidt_innovation(P[t:t + 1], Cs1, Hs1, Js1, Pcs1, Rs1), np.ones((1, 2), bool))
        np.testing.assert_allclose(flat.x[t], one.x[0], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(flat.P[t], one.P[0], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(flat.C[t][keep], one.C[0], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(flat.nis[t], one.nis[0], rtol=1e-12)
