"""Seed 000 model (filters/iono_tropo.py): Jacobian against finite differences including the
mapping functions' position derivatives, h against an independent scalar computation,
GLONASS FDMA scaling, UKF-style broadcasting, clock Q, parameter validation."""
import math

import numpy as np
import pytest

from filters.iono_tropo import (
    CLOCK_PSD_1_S,
    F_REF_HZ,
    IDX_AMB0,
    IDX_CLOCK,
    IDX_DRIFT,
    IDX_GPS_GLO,
    IDX_IONO,
    IDX_TROPO,
    N_BASE,
    IonoTropoGnss,
    IonoTropoTransition,
    elevation_rad,
    iono_mapping,
    tropo_mapping,
)
from filters.models import C_M_S
from sitl.gnss import atmosphere as atm

R_E = 6371e3
F_GLO = lambda k: 1602e6 + k * 0.5625e6  # noqa: E731


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def random_geometry(rng, S, min_el_deg=8.0, batch=()):
    """Receiver near the surface, S satellites at ~26,560 km above min_el (geocentric)."""
    rx = _unit(rng.normal(size=batch + (3,))) * (R_E + rng.uniform(0, 10e3, size=batch + (1,)))
    up = _unit(rx)
    sats = np.empty(batch + (S, 3))
    for idx in np.ndindex(*batch) if batch else [()]:
        X, e = rx[idx], up[idx]
        j = 0
        while j < S:
            p = _unit(rng.normal(size=3)) * rng.uniform(19.1e6, 26.6e6)
            d = p - X
            if d @ e / np.linalg.norm(d) > math.sin(math.radians(min_el_deg)):
                sats[idx + (j,)] = p
                j += 1
    sat_vel = rng.normal(scale=3e3, size=sats.shape)
    return rx, sats, sat_vel


def random_state(rng, rx, n, batch=()):
    x = np.zeros(batch + (n,))
    x[..., 0:3] = rx
    x[..., IDX_CLOCK] = rng.normal(scale=1e3, size=batch)
    x[..., 4:7] = rng.normal(scale=50.0, size=batch + (3,))
    x[..., IDX_DRIFT] = rng.normal(scale=10.0, size=batch)
    x[..., IDX_GPS_GLO] = rng.normal(scale=30.0, size=batch)
    x[..., IDX_IONO] = rng.uniform(5.0, 20.0, size=batch)
    x[..., IDX_TROPO] = rng.uniform(2.0, 3.0, size=batch)
    x[..., N_BASE:] = rng.normal(scale=100.0, size=batch + (n - N_BASE,))
    return x


def make_model(rng, S=8, batch=(), use_phase=True):
    rx, sp, sv = random_geometry(rng, S, batch=batch)
    is_gps = rng.random(S) < 0.5
    fc = np.where(is_gps, F_REF_HZ, F_GLO(rng.integers(-7, 7, size=S)))
    kidx = np.where(rng.random(S) < 0.75, N_BASE + np.arange(S), -1)
    kidx[0] = N_BASE  # at least one phase row
    m = IonoTropoGnss(sp, sv, fc, is_gps, 6.0, 0.064, 0.003, kidx, use_phase, n_state=N_BASE + S)
    return m, rx


def fd_jacobian(fun, x, step=1.0, pos_step=100.0):
    """Central differences; a large position step keeps round-off (eps * 2e7 m / step) far
    below the mapping-derivative terms while truncation stays negligible (|X| ~ 6.4e6 m)."""
    n = x.shape[-1]
    cols = []
    for i in range(n):
        dx = np.zeros(n)
        dx[i] = pos_step if i < 3 else step
        cols.append((fun(x + dx) - fun(x - dx)) / (2 * dx[i]))
    return np.stack(cols, axis=-1)


# ------------------------------------------------------------------------- Jacobian


def los_only_H(model, x, H):
    """H with the mapping functions' position derivatives dropped (line of sight only)."""
    Hl = H.copy()
    S = model.n_sats
    u = _unit(model.sat_pos_ecef_m - x[..., None, 0:3])
    Hl[..., :S, 0:3] = -u
    Hl[..., 2 * S:, 0:3] = -u[..., model._phase_sats, :]
    return Hl


def test_jacobian_against_central_differences_random_geometries():
    rng = np.random.default_rng(0)
    worst_ablated = np.inf
    for trial in range(25):
        model, rx = make_model(rng, S=int(rng.integers(1, 13)))
        x = random_state(rng, rx, model.n_state)
        H = model.H(x)
        H_fd = fd_jacobian(model.h, x)
        assert H.shape == (model.ndim_meas, model.n_state)
        # position columns carry the mapping derivatives (~1e-5 .. 1e-7 per metre); all
        # entries are O(1) or smaller, so an absolute tolerance; FD error here < 2e-9
        np.testing.assert_allclose(H, H_fd, rtol=0, atol=1e-8)
        z2, H2 = model.h_and_H(x)
        np.testing.assert_array_equal(z2, model.h(x))
        np.testing.assert_array_equal(H2, H)
        # the same check rejects an H without the mapping position terms
        Hl = los_only_H(model, x, H)
        worst_ablated = min(worst_ablated, np.max(np.abs(Hl - H_fd)))
        assert not np.allclose(Hl, H_fd, rtol=0, atol=1e-8)
    assert worst_ablated > 3e-8  # every geometry: dropping the terms misses by > 3x the tolerance


def test_mapping_position_derivative_low_elevation_magnitude():
    """At low elevation the tropo term alone moves d pr/dX by well over the FD tolerance."""
    rx = np.array([R_E, 0.0, 0.0])
    el = math.radians(10.0)
    sat = rx + 2.2e7 * np.array([math.sin(el), math.cos(el), 0.0])
    m = IonoTropoGnss(sat[None], np.zeros((1, 3)), [F_REF_HZ], [True], 6.0, 0.1)
    x = np.zeros(11)
    x[0:3] = rx
    x[IDX_TROPO] = 2.5
    H = m.H(x)
    u = _unit(sat - rx)
    extra = H[0, 0:3] + u
    assert np.linalg.norm(extra) > 1e-5
    # moving up raises elevation: slant delay shrinks; d/dz (north-ish) as well
    np.testing.assert_allclose(H, fd_jacobian(m.h, x), rtol=1e-7, atol=1e-10)


# ------------------------------------------------------------------------- h


def test_h_against_scalar_computation_one_satellite():
    rng = np.random.default_rng(1)
    for is_gps, fc in ((True, F_REF_HZ), (False, F_GLO(-5)), (False, F_GLO(6))):
        rx, sp, sv = random_geometry(rng, 1)
        x = random_state(rng, rx, N_BASE + 1)
        m = IonoTropoGnss(sp, sv, [fc], [is_gps], 6.0, 0.064, 0.003, [N_BASE], True)
        z = m.h(x)
        X, V, P, W = x[0:3], x[4:7], sp[0], sv[0]
        R = math.dist(P, X)
        sin_el = float(np.dot(P - X, X)) / (math.hypot(*X) * R)
        el = math.asin(sin_el)
        I = float(atm.iono_slant_delay_m(x[IDX_IONO], el, fc))
        U = float(atm.tropo_slant_delay_m(x[IDX_TROPO], el))
        dA = x[IDX_GPS_GLO] if is_gps else 0.0
        pr = R + x[IDX_CLOCK] + dA + U + I
        prr = sum((P[i] - X[i]) * (W[i] - V[i]) for i in range(3)) / R + x[IDX_DRIFT]
        ph = R + x[IDX_CLOCK] + dA + x[IDX_AMB0] + U - I
        np.testing.assert_allclose(z, [pr, prr, ph], rtol=1e-14, atol=1e-6)
        # filter-side mapping functions agree with the simulator's
        np.testing.assert_allclose(iono_mapping(el), atm.iono_mapping(el), rtol=1e-14)
        np.testing.assert_allclose(tropo_mapping(el), atm.tropo_mapping(el), rtol=1e-14)
        np.testing.assert_allclose(elevation_rad(X, P), el, rtol=1e-13)


def test_range_rate_positive_when_range_grows():
    rx = np.array([R_E, 0, 0.0])
    sat = np.array([[R_E + 2e7, 0, 0.0]])
    m = IonoTropoGnss(sat, [[1000.0, 0, 0]], [F_REF_HZ], [True], 6.0, 0.1)
    x = np.zeros(11)
    x[0:3] = rx
    assert m.h(x)[1] == pytest.approx(1000.0)


# ------------------------------------------------------------------------- FDMA


def test_glonass_fdma_iono_scaling_per_satellite():
    rng = np.random.default_rng(2)
    rx, sp, sv = random_geometry(rng, 1)
    ks = np.array([-7, -1, 0, 6])
    fc = np.concatenate([[F_REF_HZ], F_GLO(ks)])
    S = fc.size
    sp = np.repeat(sp, S, axis=0)  # same geometry: only the carrier differs
    sv = np.repeat(sv, S, axis=0)
    is_gps = np.array([True] + [False] * (S - 1))
    m = IonoTropoGnss(sp, sv, fc, is_gps, 6.0, 0.064, 0.003, N_BASE + np.arange(S), True)
    x0 = random_state(rng, rx, m.n_state)
    x0[IDX_IONO] = 0.0
    x1 = x0.copy()
    x1[IDX_IONO] = 10.0
    dz = m.h(x1) - m.h(x0)
    fac = (F_REF_HZ / fc) ** 2
    mI = float(iono_mapping(elevation_rad(rx, sp[0])))
    np.testing.assert_allclose(dz[:S], 10.0 * fac * mI, rtol=1e-9)
    np.testing.assert_allclose(dz[S:2 * S], 0.0, atol=1e-9)  # no atmosphere on Doppler
    np.testing.assert_allclose(dz[2 * S:], -10.0 * fac * mI, rtol=1e-9)  # phase advance
    np.testing.assert_allclose(m.iono_factor, fac, rtol=1e-15)
    assert fac[0] == 1.0 and fac[1] > fac[-1]  # lower GLONASS channel: larger delay
    H = m.H(x1)
    np.testing.assert_allclose(H[:S, IDX_IONO], fac * mI, rtol=1e-12)
    np.testing.assert_allclose(H[:S, IDX_GPS_GLO], is_gps.astype(float))


# ------------------------------------------------------------------------- batching


def test_ukf_broadcasting_sigma_points_against_per_trial_loop():
    rng = np.random.default_rng(3)
    N, S, K = 4, 6, 5
    m, rx = make_model(rng, S=S, batch=(N,))
    n = m.n_state
    x = random_state(rng, rx[None], n, batch=(K, N))
    z, H = m.h_and_H(x)
    assert z.shape == (K, N, m.ndim_meas) and H.shape == (K, N, m.ndim_meas, n)
    np.testing.assert_array_equal(m.h(x), z)
    np.testing.assert_array_equal(m.H(x), H)
    for i in range(N):
        mi = IonoTropoGnss(m.sat_pos_ecef_m[i], m.sat_vel_ecef_m_s[i], m.carrier_hz, m.is_gps,
                           6.0, 0.064, 0.003, m.phase_state_index, True, n_state=n)
        for k in range(K):
            zi, Hi = mi.h_and_H(x[k, i])
            np.testing.assert_allclose(z[k, i], zi, rtol=1e-15, atol=1e-9)
            np.testing.assert_allclose(H[k, i], Hi, rtol=1e-13, atol=1e-15)
    assert m.R_diag().shape == (m.ndim_meas,)


def test_R_layout_and_subset():
    rng = np.random.default_rng(4)
    S = 5
    rx, sp, sv = random_geometry(rng, S)
    kidx = np.array([11, -1, 12, 13, -1])
    sig_pr = np.arange(1.0, S + 1)
    m = IonoTropoGnss(sp, sv, np.full(S, F_REF_HZ), np.ones(S, bool), sig_pr, 0.1,
                      np.full(S, 0.003), kidx, True)
    assert m.n_state == 14 and m.n_phase == 3 and m.ndim_meas == 13
    np.testing.assert_allclose(m.R_diag(), np.r_[sig_pr**2, np.full(S, 0.01), np.full(3, 0.003**2)])
    np.testing.assert_allclose(m.R(), np.diag(m.R_diag()))
    sp2 = sp.copy()
    sp2[1] = np.nan  # untracked
    tracked = np.all(np.isfinite(sp2), axis=-1)
    m2 = IonoTropoGnss(sp2, sv, np.full(S, F_REF_HZ), np.ones(S, bool), sig_pr, 0.1,
                       0.003, kidx, True).subset(tracked)
    x = random_state(rng, rx, 14)
    assert m2.n_sats == 4 and m2.n_state == 14
    z = m.h(x)
    keep = np.r_[np.flatnonzero(tracked), S + np.flatnonzero(tracked), 2 * S + np.arange(3)]
    np.testing.assert_allclose(m2.h(x), z[keep], rtol=1e-15)
    np.testing.assert_allclose(m2.R_diag(), m.R_diag()[keep])
    assert np.all(np.isfinite(m2.H(x)))
    # without phase: z = [pr, prr]
    m3 = IonoTropoGnss(sp, sv, np.full(S, F_REF_HZ), np.ones(S, bool), 6.0, 0.1)
    assert m3.n_state == 11 and m3.h(x[:11]).shape == (2 * S,)


# ------------------------------------------------------------------------- transition


def test_transition_clock_Q_and_exact_second_order_prediction():
    tr = IonoTropoTransition(n_amb=3, q_accel_m2_s3=2.0, q_iono_m2_s=1e-6)
    assert tr.ndim == 14 and tr.linear
    for T in (0.1, 1.0, 7.3):
        Q = tr.Q(T)
        cb = Q[np.ix_([IDX_CLOCK, IDX_DRIFT], [IDX_CLOCK, IDX_DRIFT])]
        want = C_M_S**2 * CLOCK_PSD_1_S * np.array([[T**3 / 3, T**2 / 2], [T**2 / 2, T]])
        np.testing.assert_allclose(cb, want, rtol=1e-15)
        assert Q[0, 4] == pytest.approx(2.0 * T**2 / 2) and Q[4, 4] == pytest.approx(2.0 * T)
        assert Q[IDX_IONO, IDX_IONO] == pytest.approx(1e-6 * T)
        assert Q[IDX_TROPO, IDX_TROPO] > 0 and Q[IDX_GPS_GLO, IDX_GPS_GLO] > 0
        np.testing.assert_array_equal(Q[N_BASE:, :], 0.0)
        np.testing.assert_allclose(Q, Q.T)
        assert np.all(np.linalg.eigvalsh(Q) >= -1e-12 * np.abs(Q).max())
        F = tr.F(None, T)
        x = np.random.default_rng(5).normal(size=(2, 14))
        np.testing.assert_allclose(tr.f(x, T), x @ F.T)
        A = tr.A()
        np.testing.assert_array_equal(A @ A, 0.0)
        # the seed's x + f T + A f T^2/2 with f = A x is exactly F x
        second = x + (x @ A.T) * T + (x @ A.T @ A.T) * T**2 / 2
        np.testing.assert_allclose(second, tr.f(x, T), rtol=1e-14, atol=1e-12)
        assert F[0, 4] == T and F[IDX_CLOCK, IDX_DRIFT] == T


# ------------------------------------------------------------------------- validation


def _base(**kw):
    S = 2
    args = dict(sat_pos_ecef_m=np.array([[2e7, 0, 0], [0, 2e7, 0.0]]), sat_vel_ecef_m_s=np.zeros((S, 3)),
                carrier_hz=np.full(S, F_REF_HZ), is_gps=np.array([True, False]),
                sigma_pr_m=6.0, sigma_prr_m_s=0.1)
    args.update(kw)
    return IonoTropoGnss(**args)


@pytest.mark.parametrize(
    "kw, name",
    [
        (dict(sigma_pr_m=-1.0), "sigma_pr_m"),
        (dict(sigma_prr_m_s=np.nan), "sigma_prr_m_s"),
        (dict(sigma_pr_m=np.ones(3)), "sigma_pr_m"),
        (dict(carrier_hz=np.array([F_REF_HZ, 0.0])), "carrier_hz"),
        (dict(carrier_hz=np.full(3, F_REF_HZ)), "carrier_hz"),
        (dict(is_gps=np.array([1, 0])), "is_gps"),
        (dict(sat_pos_ecef_m=np.zeros((2, 2))), "sat_pos_ecef_m"),
        (dict(sat_vel_ecef_m_s=np.zeros((3, 3))), "sat_vel_ecef_m_s"),
        (dict(use_phase=True, phase_state_index=np.array([11, 12])), "sigma_phase_m"),
        (dict(use_phase=True, sigma_phase_m=0.003), "phase_state_index"),
        (dict(phase_state_index=np.array([5, -1])), "phase_state_index"),
        (dict(phase_state_index=np.array([11, 11])), "phase_state_index"),
        (dict(phase_state_index=np.array([11, -2])), "phase_state_index"),
        (dict(sigma_phase_m=0.0), "sigma_phase_m"),
        (dict(phase_state_index=np.array([11, 12]), n_state=12), "n_state"),
        (dict(use_phase=1), "use_phase"),
        (dict(f_ref_hz=-1.0), "f_ref_hz"),
        (dict(h_shell_m=0.0), "h_shell_m"),
    ],
)
def test_measurement_bad_parameters(kw, name):
    with pytest.raises(ValueError, match=name):
        _base(**kw)


@pytest.mark.parametrize(
    "kw, name",
    [
        (dict(n_amb=-1), "n_amb"),
        (dict(n_amb=1.5), "n_amb"),
        (dict(q_accel_m2_s3=-1.0), "q_accel_m2_s3"),
        (dict(clock_psd_1_s=np.inf), "clock_psd_1_s"),
        (dict(q_iono_m2_s=-1e-9), "q_iono_m2_s"),
        (dict(q_tropo_m2_s=np.nan), "q_tropo_m2_s"),
        (dict(q_gps_glo_m2_s=-1.0), "q_gps_glo_m2_s"),
        (dict(c=0.0), "c"),
    ],
)
def test_transition_bad_parameters(kw, name):
    with pytest.raises(ValueError, match=name):
        IonoTropoTransition(**kw)


def test_bad_state_and_dt():
    m = _base()
    with pytest.raises(ValueError, match="x"):
        m.h(np.zeros(10))
    with pytest.raises(ValueError, match="dt"):
        IonoTropoTransition().Q(-1.0)
    with pytest.raises(ValueError, match="mask"):
        m.subset([True, False, True])
