"""Beacon -> UAV radio link (seed 002): range and range rate with white noise; multilateration.

Measurements (seed 002, eq. 9 for the range; the Doppler as in eq. 7), UAV i at U_i with
velocity V_U, beacon at B with velocity V_B, ECEF:

    range_m        = |U_i - B| + W_r
    range_rate_m_s = (U_i - B) . (V_U - V_B) / |U_i - B| + W_v     (= d|U_i - B|/dt: > 0 when the range grows)

W_r, W_v are white noises with two-sided power spectral densities N_r = (5 m)^2 s and
N_v = (0.1 m/s)^2 s (the seed's example).  A sampled link reports the noise averaged over
its measurement interval dt_s, whose variance is N / dt_s (:func:`psd_to_variance`); the
variances travel with the measurements.

Light time is neglected: the signal received at t left the beacon at t - tau,
tau = range / c < 1 ms for ranges below 300 km.  The range then errs by at most
|V_B| tau ~ 115 m/s x 1 ms ~ 0.12 m, and the Earth's rotation during the flight (Sagnac,
(w_e / c) |(U x B)_z|) adds at most ~0.4 m for a 300 km baseline at 30 deg latitude; the
range rate errs by ~|V|^2 / c + |A| tau ~ 1e-4 m/s.  Both are below 0.1 sigma of the noise
at dt_s = 1 s (5 m, 0.1 m/s).  Both ends are assumed time-synchronised (as the seed states).

:func:`multilaterate` is the closed-form initial fix of the beacon position from ranges at
N >= 3 known (or estimated) UAV positions, for the ground-station locator to start from.

Pure numpy; randomness only from the ``numpy.random.Generator`` passed in.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from filters.params import number, param, validate
from sitl.constants import Ellipsoid
from sitl.geodesy import ecef_to_geodetic
from sitl.gnss.ranging import finite_vec3 as _vec3

__all__ = [
    "psd_to_variance",
    "BeaconLinkConfig",
    "BeaconLinkMeasurement",
    "range_and_rate",
    "measure",
    "MultilaterationFix",
    "multilaterate",
    "DEFAULT_PSD_RANGE_M2_S",
    "DEFAULT_PSD_RANGE_RATE_M2_S",
]

#: Seed 002 beacon-link noise intensities (two-sided PSDs): range (5 m)^2 s, Doppler (0.1 m/s)^2 s.
DEFAULT_PSD_RANGE_M2_S = 5.0**2
DEFAULT_PSD_RANGE_RATE_M2_S = 0.1**2

_POSITIVE = number(0, lo_open=True)  # the check of a positive scalar argument (dt_s, a sigma)


def psd_to_variance(psd_two_sided, dt_s):
    """Variance of one sample of white noise with two-sided PSD N, averaged over dt_s: N / dt_s.

    White noise w(t) with two-sided PSD N (units^2 / Hz = units^2 s) has the autocorrelation
    E[w(t) w(s)] = N delta(t - s).  A sampled sensor reports the mean over its interval,
    w_k = (1/dt) int_0^dt w(t) dt, so

        var(w_k) = (1/dt^2) int_0^dt int_0^dt N delta(t - s) ds dt = N / dt,

    and samples of disjoint intervals are uncorrelated.  E.g. N = (30 m)^2 s at dt = 1 s gives
    sigma = 30 m; at dt = 0.1 s, sigma = 94.9 m.  (For a one-sided PSD N0 = 2 N the same
    variance reads N0 / (2 dt).)

    psd_two_sided: scalar or array, >= 0.  dt_s: scalar > 0.  Returns an array like psd.
    """
    dt = _POSITIVE("dt_s", dt_s)
    try:
        n = np.asarray(psd_two_sided, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"psd_two_sided must be numeric, got {psd_two_sided!r}") from None
    if not np.all(np.isfinite(n) & (n >= 0.0)):
        raise ValueError(f"psd_two_sided must be finite and >= 0, got {psd_two_sided!r}")
    return n / dt


@dataclass(frozen=True)
class BeaconLinkConfig:
    """Noise of the beacon link: two-sided PSDs and the measurement interval."""

    psd_range_m2_s: float = param(DEFAULT_PSD_RANGE_M2_S, check=number(0),
                                  doc="two-sided PSD of the range noise, m^2 s (seed 002: (5 m)^2 s = 25)")
    psd_range_rate_m2_s: float = param(DEFAULT_PSD_RANGE_RATE_M2_S, check=number(0),
                                       doc="two-sided PSD of the range-rate noise, (m/s)^2 s "
                                           "(seed 002: (0.1 m/s)^2 s = 0.01)")
    dt_s: float = param(1.0, check=number(0, lo_open=True),
                        doc="measurement interval over which the noise is averaged, s")

    def __post_init__(self):
        validate(self)

    @property
    def var_range_m2(self) -> float:
        return float(psd_to_variance(self.psd_range_m2_s, self.dt_s))

    @property
    def var_range_rate_m2_s2(self) -> float:
        return float(psd_to_variance(self.psd_range_rate_m2_s, self.dt_s))


class BeaconLinkMeasurement(NamedTuple):
    """Beacon-link measurements and their per-sample noise variances, shape (...)."""

    range_m: np.ndarray
    range_rate_m_s: np.ndarray
    var_range_m2: np.ndarray
    var_range_rate_m2_s2: np.ndarray


def range_and_rate(uav_pos_ecef_m, uav_vel_ecef_m_s, beacon_pos_ecef_m, beacon_vel_ecef_m_s):
    """Noise-free (range_m, range_rate_m_s) from the beacon to each UAV; arrays broadcast.

    range = |U - B|,  range_rate = (U - B).(V_U - V_B) / |U - B|  (positive when receding).
    Raises ValueError where U = B.
    """
    d = _vec3("uav_pos_ecef_m", uav_pos_ecef_m) - _vec3("beacon_pos_ecef_m", beacon_pos_ecef_m)
    w = _vec3("uav_vel_ecef_m_s", uav_vel_ecef_m_s) - _vec3("beacon_vel_ecef_m_s", beacon_vel_ecef_m_s)
    rng = np.sqrt(np.sum(d * d, axis=-1))
    if np.any(rng == 0.0):
        raise ValueError("uav_pos_ecef_m must differ from beacon_pos_ecef_m (range 0: direction undefined)")
    d, w = np.broadcast_arrays(d, w)
    return rng, np.sum(d * w, axis=-1) / rng


def measure(rng: np.random.Generator, uav_pos_ecef_m, uav_vel_ecef_m_s, beacon_pos_ecef_m, beacon_vel_ecef_m_s,
            config: BeaconLinkConfig = BeaconLinkConfig(), trials_shape: tuple = ()) -> BeaconLinkMeasurement:
    """Noisy range and range rate from the beacon at each UAV (see the module docstring).

    The geometry broadcasts over leading axes (e.g. UAVs (N, 3) against one beacon (3,) -> (N,)).
    trials_shape prepends axes of independent noise draws on the same truth (Monte Carlo):
    the output shape is trials_shape + geometry shape.  Returns the measurements with their
    per-sample variances N / dt_s broadcast to the same shape.
    """
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    if not isinstance(config, BeaconLinkConfig):
        raise ValueError(f"config must be a BeaconLinkConfig, got {type(config).__name__}")
    r, rr = range_and_rate(uav_pos_ecef_m, uav_vel_ecef_m_s, beacon_pos_ecef_m, beacon_vel_ecef_m_s)
    shape = tuple(trials_shape) + r.shape
    vr, vv = config.var_range_m2, config.var_range_rate_m2_s2
    z_r = r + math.sqrt(vr) * rng.standard_normal(shape)
    z_v = rr + math.sqrt(vv) * rng.standard_normal(shape)
    return BeaconLinkMeasurement(z_r, z_v, np.full(shape, vr), np.full(shape, vv))


# --------------------------------------------------------------------------- multilateration


class MultilaterationFix(NamedTuple):
    """Beacon position from ranges: the chosen solution, its covariance and the other mirror.

    pos_ecef_m (..., 3); cov_m2 (..., 3, 3) = (J' W J)^-1 at the solution (J the unit
    vectors anchor -> beacon, W = diag(1/var)); residual_m (..., N) range - |x - U_i|;
    mirror_pos_ecef_m (..., 3) the rejected candidate (reflection about the anchors' plane,
    refined); cost (..., 2) the selection cost of [chosen, mirror].
    """

    pos_ecef_m: np.ndarray
    cov_m2: np.ndarray
    residual_m: np.ndarray
    mirror_pos_ecef_m: np.ndarray
    cost: np.ndarray


def _gauss_newton(x, p, r, w, iterations):
    """Weighted Gauss-Newton on sum w_i (r_i - |x - p_i|)^2; returns x, (J'WJ)^-1, residual."""
    n = p.shape[-1]
    eye = np.eye(n)
    for k in range(iterations + 1):
        d = x[..., None, :] - p
        rho = np.sqrt(np.sum(d * d, axis=-1))
        J = d / rho[..., None]
        res = r - rho
        A = np.einsum("...ki,...k,...kj->...ij", J, w, J)
        # A tiny ridge keeps a beacon lying exactly in the plane of three anchors (where the
        # out-of-plane direction is unobservable to first order) finite instead of singular.
        A = A + eye * (1e-12 * np.trace(A, axis1=-2, axis2=-1)[..., None, None])
        if k == iterations:
            return x, np.linalg.inv(A), res
        g = np.einsum("...ki,...k->...i", J, w * res)
        x = x + np.linalg.solve(A, g[..., None])[..., 0]


def multilaterate(range_m, anchors_pos_ecef_m, var_range_m2: Any = DEFAULT_PSD_RANGE_M2_S, *,
                  prior_h_m=None, prior_sigma_h_m: float = 1000.0, gauss_newton_iterations: int = 1,
                  ell: Ellipsoid | str | None = None) -> MultilaterationFix:
    """Closed-form beacon position from ranges at N >= 3 anchors, refined by Gauss-Newton.

    Closed form (linearised difference of squares).  With the anchors centred on their
    centroid c (p_i = U_i - c, sum p_i = 0) and x = B - c, the spheres |x - p_i|^2 = r_i^2
    minus their mean over i are linear:

        2 p_i . x = d_i,   d_i = (|p_i|^2 - mean |p|^2) - (r_i^2 - mean r^2).

    With the SVD p = W S V' (rows v_1, v_2, v_3 of V', s_1 >= s_2 >= s_3) the least-squares
    in-plane coordinates are a_k = (w_k . d) / (2 s_k), k = 1, 2 -- exact for noise-free data
    whatever the out-of-plane spread, since the w_k are orthogonal.  The component along the
    anchors' plane normal v_3 follows from the mean of the spheres:

        c^2 = mean_i (r_i^2 - |a - p_i,12|^2) - mean_i (p_i . v_3)^2,

    two mirror solutions x = a_1 v_1 + a_2 v_2 +- c v_3 (c = 0 if noise makes c^2 < 0).  With
    exactly 3 anchors (always coplanar) both fit the ranges exactly; with N >= 4 non-coplanar
    anchors the wrong mirror leaves residuals.  Each candidate gets ``gauss_newton_iterations``
    weighted Gauss-Newton steps; the one with the smaller

        cost = sum_i (r_i - |x - p_i|)^2 / var_i + ((h(x) - prior_h_m) / prior_sigma_h_m)^2

    is returned (h the geodetic height).  prior_h_m defaults to the anchors' mean height: for
    UAVs flying near the beacon's height the mirror is kilometres away in height (the UAVs'
    plane, extended 200 km, already rises ~3 km above the ground through the Earth's
    curvature alone).  The Doppler could also separate the mirrors but needs the beacon's
    velocity, which a first fix does not have.

    Conditioning: the seed's start geometry is poor for a single epoch -- the three UAVs
    (30.0/45.0, 30.1/45.1, 30.3/45.3 deg) are nearly collinear and the beacon is 200-250 km
    away, so with 5 m ranges the one-epoch fix has sigma ~20-30 km and its linearised
    covariance is not reliable (the errors are non-Gaussian).  It is exact on noise-free data;
    a locator should treat it as a coarse start (or use several epochs as anchors).

    range_m (..., N); anchors_pos_ecef_m (..., N, 3); var_range_m2 scalar, (N,) or (..., N).
    Returns a :class:`MultilaterationFix`.
    """
    try:
        r = np.asarray(range_m, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"range_m must be numeric (..., N), got {range_m!r}") from None
    U = _vec3("anchors_pos_ecef_m", anchors_pos_ecef_m)
    if U.ndim < 2 or U.shape[-2] < 3:
        raise ValueError(f"anchors_pos_ecef_m must have shape (..., N >= 3, 3), got {U.shape}")
    N = U.shape[-2]
    if r.ndim < 1 or r.shape[-1] != N:
        raise ValueError(f"range_m must have shape (..., {N}) (one range per anchor), got {r.shape}")
    if not np.all(np.isfinite(r) & (r > 0)):
        raise ValueError("range_m must be finite and > 0")
    var = np.asarray(var_range_m2, dtype=float)
    if not np.all(np.isfinite(var) & (var > 0)):
        raise ValueError(f"var_range_m2 must be finite and > 0, got {var_range_m2!r}")
    if isinstance(gauss_newton_iterations, bool) or int(gauss_newton_iterations) != gauss_newton_iterations \
            or gauss_newton_iterations < 0:
        raise ValueError(f"gauss_newton_iterations must be an integer >= 0, got {gauss_newton_iterations!r}")
    sig_h = _POSITIVE("prior_sigma_h_m", prior_sigma_h_m)
    try:
        batch = np.broadcast_shapes(r.shape[:-1], U.shape[:-2], var.shape[:-1] if var.ndim else ())
    except ValueError:
        raise ValueError(f"range_m {r.shape}, anchors_pos_ecef_m {U.shape} and var_range_m2 {var.shape} "
                         "do not broadcast") from None
    r = np.broadcast_to(r, batch + (N,))
    U = np.broadcast_to(U, batch + (N, 3))
    w = np.broadcast_to(1.0 / var, batch + (N,))
    if prior_h_m is None:
        prior_h = np.mean(ecef_to_geodetic(U, ell)[2], axis=-1)
    else:
        prior_h = np.broadcast_to(np.asarray(prior_h_m, dtype=float), batch)
        if not np.all(np.isfinite(prior_h)):
            raise ValueError(f"prior_h_m must be finite, got {prior_h_m!r}")

    c = U.mean(axis=-2)
    p = U - c[..., None, :]
    Wm, s, Vt = np.linalg.svd(p, full_matrices=False)  # p = Wm diag(s) Vt
    if np.any(s[..., 1] <= 1e-9 * s[..., 0]):
        raise ValueError("anchors_pos_ecef_m are collinear: the beacon position is not determined")
    pp = np.sum(p * p, axis=-1)
    d = (pp - pp.mean(axis=-1, keepdims=True)) - (r * r - np.mean(r * r, axis=-1, keepdims=True))
    a = np.einsum("...nk,...n->...k", Wm[..., :, :2], d) / (2.0 * s[..., :2])  # in-plane coordinates
    x_plane = np.einsum("...k,...ki->...i", a, Vt[..., :2, :])
    normal = Vt[..., 2, :]
    p_n = np.einsum("...ni,...i->...n", p, normal)
    q = x_plane[..., None, :] - p
    q_plane = q - np.einsum("...ni,...i->...n", q, normal)[..., None] * normal[..., None, :]
    c2 = np.mean(r * r - np.sum(q_plane * q_plane, axis=-1), axis=-1) - np.mean(p_n * p_n, axis=-1)
    c_n = np.sqrt(np.maximum(c2, 0.0))

    sols, covs, ress, costs = [], [], [], []
    for sign in (1.0, -1.0):
        x0 = x_plane + sign * c_n[..., None] * normal
        x, P, res = _gauss_newton(x0, p, r, w, int(gauss_newton_iterations))
        h = ecef_to_geodetic(x + c, ell)[2]
        sols.append(x + c)
        covs.append(P)
        ress.append(res)
        costs.append(np.sum(w * res * res, axis=-1) + ((h - prior_h) / sig_h) ** 2)
    pick = costs[1] < costs[0]  # True: the minus candidate wins
    pk3, pk33 = pick[..., None], pick[..., None, None]
    pos = np.where(pk3, sols[1], sols[0])
    return MultilaterationFix(
        pos_ecef_m=pos,
        cov_m2=np.where(pk33, covs[1], covs[0]),
        residual_m=np.where(pk3, ress[1], ress[0]),
        mirror_pos_ecef_m=np.where(pk3, sols[0], sols[1]),
        cost=np.stack([np.where(pick, costs[1], costs[0]), np.where(pick, costs[0], costs[1])], axis=-1),
    )
