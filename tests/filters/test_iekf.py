"""The iterated EKF update (filters/iekf.py).

* a linear measurement: the iterations reproduce the EKF update (and the innovation rule
  stops them at once);
* a nonlinear one (ranges from known anchors): the fixed point is the maximum a posteriori
  state, found independently by scipy.optimize.least_squares, and the plain EKF update is not
  (so the comparison can fail);
* the stopping rules: the step rule in the caller's coordinates, the innovation rule on the
  used rows only, the iteration cap;
* batched: a (2, 3) batch equals its rows stepped one at a time (without stopping rules).
"""
from __future__ import annotations

import numpy as np
import pytest
import scipy.optimize

from filters import kernels
from filters.iekf import iterated_update, relinearized_innovation

ANCHORS = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])


def _ranges(x):
    """Ranges from the anchors to the 2-D position x (..., 2): h (..., 3), H (..., 3, 2)."""
    d = x[..., None, :] - ANCHORS
    r = np.sqrt(np.sum(d * d, axis=-1))
    return r, d / r[..., None]


def _joseph(x, P, R):
    """update(nu, H) of the prior x (T, n), P (T, n, n) with R (m, m): kernels.joseph_update (numpy)."""
    def update(nu, H):
        return kernels.joseph_update(x, P, nu, np.broadcast_to(H, nu.shape + x.shape[-1:]), R=R, backend="numpy")
    return update


def _range_case():
    x0 = np.array([[4.0, 3.0]])  # the prior mean, far from the truth (7, 6) for its spread
    P0 = np.diag([9.0, 9.0])[None]
    R = np.diag([0.01, 0.01, 0.01])
    z = _ranges(np.array([7.0, 6.0]))[0][None] + np.array([0.05, -0.03, 0.02])
    return x0, P0, R, z


def _linearize(z, x0):
    def linearize(xi):
        hx, H = _ranges(xi)
        return relinearized_innovation(z, hx, H, x0, xi), H
    return linearize


def test_linear_measurement_the_iterations_repeat_the_ekf_update():
    rng = np.random.default_rng(1)
    H = rng.standard_normal((4, 3))
    x0 = rng.standard_normal((1, 3))
    A = rng.standard_normal((3, 3))
    P0 = (A @ A.T + np.eye(3))[None]
    R = np.diag([0.5, 0.2, 1.0, 0.3])
    z = rng.standard_normal((1, 4))
    update = _joseph(x0, P0, R)
    nu0 = z - x0 @ H.T
    first = update(nu0, H[None])

    def linearize(xi):
        return relinearized_innovation(z, xi @ H.T, H[None], x0, xi), H[None]

    it = iterated_update(x0, first[0], linearize, update, 6)
    assert it.updates == 6
    np.testing.assert_allclose(it.result[0], first[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(it.result[1], first[1], rtol=0, atol=1e-12)
    # relinearising a linear h changes no innovation: the innovation rule stops before any update
    it = iterated_update(x0, first[0], linearize, update, 6, innovation_tol=1e-9, nu_prior=nu0,
                         sigma=np.sqrt(np.diag(R)))
    assert it.result is None and it.updates == 1


def test_nonlinear_fixed_point_is_the_map_estimate_and_the_ekf_is_not():
    x0, P0, R, z = _range_case()
    update = _joseph(x0, P0, R)
    hx, H = _ranges(x0)
    first = update(z - hx, H)
    it = iterated_update(x0, first[0], _linearize(z, x0), update, 20, step_tol=1e-12)
    assert it.updates < 20  # converged before the cap

    Li_P = np.linalg.inv(np.linalg.cholesky(P0[0]))
    Li_R = np.linalg.inv(np.linalg.cholesky(R))

    def residuals(x):  # the MAP cost as whitened residuals
        return np.concatenate([Li_P @ (x - x0[0]), Li_R @ (z[0] - _ranges(x)[0])])

    map_x = scipy.optimize.least_squares(residuals, x0[0], xtol=1e-15, ftol=1e-15, gtol=1e-15).x
    np.testing.assert_allclose(it.result[0][0], map_x, rtol=0, atol=1e-9)
    assert np.max(np.abs(first[0][0] - map_x)) > 1e-3  # one linearisation at the prior is off
    # the posterior covariance is the Joseph form at the last linearisation point
    xl = it.result[0]
    Hl = _ranges(xl)[1][0]
    P_map = np.linalg.inv(np.linalg.inv(P0[0]) + Hl.T @ np.linalg.inv(R) @ Hl)
    np.testing.assert_allclose(it.result[1][0], P_map, rtol=1e-3)


def test_step_rule_is_judged_in_the_callers_coordinates():
    x0, P0, R, z = _range_case()
    update = _joseph(x0, P0, R)
    hx, H = _ranges(x0)
    first = update(z - hx, H)
    lin = _linearize(z, x0)
    n_id = iterated_update(x0, first[0], lin, update, 20, step_tol=1e-4).updates
    n_scaled = iterated_update(x0, first[0], lin, update, 20, step_tol=1e-4, point=lambda x: 1e6 * x).updates
    assert 1 < n_id < n_scaled  # the same tolerance on a finer scale needs more iterations
    # the first step is measured from point_prior when given: a prior point at the first iterate
    # itself stops at once
    it = iterated_update(x0, first[0], lin, update, 20, step_tol=1e-4, point_prior=first[0])
    assert it.result is None and it.updates == 1
    # the cap: iterations - 1 updates after the first at most
    assert iterated_update(x0, first[0], lin, update, 3).updates == 3


def test_innovation_rule_reads_the_used_rows_only():
    x0, P0, R, z = _range_case()
    update = _joseph(x0, P0, R)
    hx, H = _ranges(x0)
    nu0 = z - hx
    first = update(nu0, H)
    sigma = np.sqrt(np.diag(R))
    kw = dict(innovation_tol=1e-3, nu_prior=nu0, sigma=sigma)
    assert iterated_update(x0, first[0], _linearize(z, x0), update, 5, **kw).updates > 1
    # with every row unused nothing counts as a change: the rule stops at once
    it = iterated_update(x0, first[0], _linearize(z, x0), update, 5, innovation_rows=np.zeros(3, bool), **kw)
    assert it.result is None
    with pytest.raises(ValueError, match="nu_prior and sigma"):
        iterated_update(x0, first[0], _linearize(z, x0), update, 5, innovation_tol=1e-3)


def test_a_batch_equals_its_rows_one_at_a_time():
    rng = np.random.default_rng(4)
    T = 6
    x0 = np.array([4.0, 3.0]) + rng.standard_normal((T, 2))
    P0 = np.broadcast_to(np.diag([9.0, 4.0]), (T, 2, 2)).copy()
    R = np.diag([0.01, 0.04, 0.01])
    z = _ranges(np.array([7.0, 6.0]))[0] + 0.1 * rng.standard_normal((T, 3))
    update = _joseph(x0, P0, R)
    hx, H = _ranges(x0)
    first = update(z - hx, H)
    whole = iterated_update(x0, first[0], _linearize(z, x0), update, 4).result
    for t in range(T):
        upd = _joseph(x0[t:t + 1], P0[t:t + 1], R)
        h1, H1 = _ranges(x0[t:t + 1])
        f1 = upd(z[t:t + 1] - h1, H1)
        one = iterated_update(x0[t:t + 1], f1[0], _linearize(z[t:t + 1], x0[t:t + 1]), upd, 4).result
        np.testing.assert_allclose(whole[0][t], one[0][0], rtol=0, atol=1e-12)
        np.testing.assert_allclose(whole[1][t], one[1][0], rtol=0, atol=1e-12)
    # a multi-axis batch: relinearized_innovation broadcasts over (2, 3) and per-observer axes
    Hb = rng.standard_normal((2, 3, 4, 2, 5))  # (batch, observers, rows, state)
    xa, xb = rng.standard_normal((2, 3, 1, 5)), rng.standard_normal((2, 3, 1, 5))
    hb, zb = rng.standard_normal((2, 3, 4, 2)), rng.standard_normal((2, 3, 4, 2))
    nu = relinearized_innovation(zb, hb, Hb, xa, xb)
    np.testing.assert_allclose(nu, zb - hb - (Hb @ (xa - xb)[..., None])[..., 0], rtol=0, atol=1e-12)
