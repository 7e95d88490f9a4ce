"""Aerological radar (seed 004, eqs 10-14 and 30-33): slant range, azimuth, elevation.

The radar sits at a known site (geodetic -> ECEF, WGS-84) -- in seed 004 the ground
complex-processing point (GCPP) -- and tracks the sonde by secondary radar (range from
the transponder's reply, D = c (tau_sum - tau_ans) / 2 + dD) and by angular
auto-tracking of its antenna.  It measures, in the spherical frame centred on the
radar (``sitl.geodesy.ecef_to_aer``: azimuth clockwise from north in [0, 2 pi),
elevation above the *geodetic* horizon, slant range = |P - radar|):

    xi_D(k) = D(k) + eps_D(k),  xi_az(k) = az(k) + eps_az(k),  xi_el(k) = el(k) + eps_el(k)

with first-order Markov errors per axis (eqs 12-14)

    eps(k) = mu eps(k-1) + v n(k),  mu = exp(-gamma T),  v = sqrt(sigma^2 (1 - mu^2)),

T the time since the previous measurement (any spacing), stationary start
eps(0) ~ N(0, sigma^2), so that var eps(k) = sigma^2 and corr(eps(k), eps(k+j)) = mu^j.
The measured azimuth is wrapped into [0, 2 pi).  The transponder delay tau_ans is
known and removed, the slant range is the instantaneous geometric distance (the
sonde moves < 0.1 m during the ~2 ms round trip) and refraction (dD) is left out.

Seed values.  Seed 004 gives the model but no accuracies; it states the operating
radius, 250 km (used: ``max_range_m``).  The default accuracies are those of an
aerological radar of the AVK / Vektor-M / MARL-A class: sigma_D = 15 m,
sigma_az = sigma_el = 0.1 deg, correlation time 1/gamma = 10 s on every axis.

Coverage.  Beyond ``max_range_m`` or below ``el_mask_rad`` there is no measurement
(all NaN, ``in_range`` / ``range_valid`` False).  The error processes keep running
meanwhile (they are the radar's, not the target's).

Loss of angular auto-tracking (the radar method's weakness, "in strong side wind at
launch"): the angles are NaN (``angles_valid`` False) while the range stays valid.
Losses come from a fixed schedule of (t_start, t_end) intervals (closed on the left,
open on the right) and/or a random process: while tracking, a loss starts within a
step T with probability 1 - exp(-lambda T), lambda = loss_rate_1_s (1 + (omega /
loss_ang_rate_ref_rad_s)^2), omega = |v_perp| / D the true angular rate of the line of
sight (large near launch in a side wind); a loss ends within a step with probability
1 - exp(-T / loss_mean_duration_s).  ``loss_rate_1_s = 0`` (default) switches the
random process off.

Randomness: ``rng`` is one Generator for the batch, or one per target (then each
target's numbers depend only on its stream).  Per target and step the radar always
draws 3 normals (range, azimuth, elevation errors) then 1 uniform (the loss process),
whatever the state, so the streams stay aligned; the first step draws the 3
stationary initial errors instead of the 3 innovations.

Also here: :func:`radar_aer_to_ecef` (radar site + AER -> ECEF) with its Jacobian
:func:`aer_to_ecef_jacobian`, the inverse Jacobian :func:`ecef_to_aer_jacobian` (for
a filter that uses the raw AER measurements), and :func:`aer_cov_to_ecef`.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from filters.params import ParamError, number, param, require, validate
from sitl.geodesy import aer_to_ecef, ecef_to_aer, enu_rotation, geodetic_to_ecef
from sitl.gnss.ranging import finite_vec3 as _vec3

__all__ = [
    "MAX_RANGE_M",
    "Radar",
    "RadarMeasurement",
    "RadarParams",
    "aer_cov_to_ecef",
    "aer_to_ecef_jacobian",
    "ar1_coefficients",
    "ecef_to_aer_jacobian",
    "radar_aer_to_ecef",
]

MAX_RANGE_M = 250_000.0


# ---------------------------------------------------------------------------
# helpers shared with sitl.radio.relay


def _intervals(key, value) -> tuple:
    """A schedule: a sequence of (t_start, t_end) pairs with t_start < t_end (GPS s), as a tuple
    of float pairs; a check (key, value) -> value of the filters.params kind."""
    try:
        out = tuple((float(a), float(b)) for a, b in value)
    except (TypeError, ValueError):
        raise ParamError(key, f"expected a sequence of (t_start, t_end) pairs of GPS seconds, got {value!r}") from None
    for a, b in out:
        if not (math.isfinite(a) and math.isfinite(b) and a < b):
            raise ParamError(key, f"expected finite t_start < t_end in every interval, got ({a}, {b})")
    return out


#: the elevation masks' range (a mask at the zenith would see nothing)
EL_MASK_TEXT = "a number in [-pi/2, pi/2)"
_EL_MASK = number(-math.pi / 2, what=EL_MASK_TEXT)


def _el_mask_below_zenith(obj, key: str) -> None:
    """The rule after validate(): the mask named ``key`` lies below pi/2."""
    v = getattr(obj, key)
    require(v < math.pi / 2, key, f"expected {EL_MASK_TEXT}, got {v!r}")


def _in_schedule(schedule: tuple, t: float) -> bool:
    return any(a <= t < b for a, b in schedule)


def _site(lat_rad, lon_rad, h_m, what: str):
    vals = []
    for name, v in ((f"{what}_lat_rad", lat_rad), (f"{what}_lon_rad", lon_rad), (f"{what}_h_m", h_m)):
        try:
            x = float(v)
        except (TypeError, ValueError):
            raise ValueError(f"{name} must be a number, got {v!r}") from None
        if not math.isfinite(x):
            raise ValueError(f"{name} must be finite, got {v!r}")
        vals.append(x)
    if abs(vals[0]) > math.pi / 2:
        raise ValueError(f"{what}_lat_rad must lie in [-pi/2, pi/2] (degrees passed?)")
    return vals, geodetic_to_ecef(*vals)


def _check_rng(rng):
    """-> (single Generator or None, list of Generators or None)."""
    if isinstance(rng, np.random.Generator):
        return rng, None
    if isinstance(rng, (str, bytes)) or not isinstance(rng, Sequence):
        raise ValueError(f"rng: expected a numpy.random.Generator or a sequence of them, got {type(rng).__name__}")
    gens = list(rng)
    if not gens or not all(isinstance(g, np.random.Generator) for g in gens):
        raise ValueError("rng: a sequence must hold one numpy.random.Generator per target")
    return None, gens


class _Streams:
    """Draws for a batch of B targets from one Generator or one Generator per target."""

    def __init__(self, rng, batch_shape: tuple):
        self.single, self.gens = _check_rng(rng)
        self.batch_shape = tuple(batch_shape)
        self.n = int(np.prod(self.batch_shape, dtype=int))
        if self.gens is not None and len(self.gens) != self.n:
            raise ValueError(f"rng: expected one Generator per target ({self.n}), got {len(self.gens)}")

    @classmethod
    def for_batch(cls, rng, batch_shape=None) -> "_Streams":
        """Streams for ``batch_shape``; None: () for one Generator, (len(rng),) for a sequence."""
        if batch_shape is None:
            batch_shape = () if isinstance(rng, np.random.Generator) else (len(_check_rng(rng)[1]),)
        try:
            batch_shape = tuple(int(n) for n in batch_shape)
        except (TypeError, ValueError):
            raise ValueError(f"batch_shape must be a tuple of ints, got {batch_shape!r}") from None
        return cls(rng, batch_shape)

    def normal(self, k: int) -> np.ndarray:
        if self.single is not None:
            return self.single.standard_normal((self.n, k)).reshape(self.batch_shape + (k,))
        return np.stack([g.standard_normal(k) for g in self.gens]).reshape(self.batch_shape + (k,))

    def uniform(self, k: int) -> np.ndarray:
        if self.single is not None:
            return self.single.random((self.n, k)).reshape(self.batch_shape + (k,))
        return np.stack([g.random(k) for g in self.gens]).reshape(self.batch_shape + (k,))


def _time(name, value) -> float:
    try:
        t = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number of GPS seconds, got {value!r}") from None
    if not math.isfinite(t):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return t


def ar1_coefficients(sigma, gamma_1_s, dt_s):
    """(mu, v) of the discrete first-order Markov error: mu = exp(-gamma T), v = sigma sqrt(1 - mu^2)."""
    mu = np.exp(-np.asarray(gamma_1_s, float) * dt_s)
    return mu, np.asarray(sigma, float) * np.sqrt(1.0 - mu * mu)


# ---------------------------------------------------------------------------
# conversions


def radar_aer_to_ecef(az_rad, el_rad, range_m, site_pos_ecef_m) -> np.ndarray:
    """Target ECEF (..., 3) from radar azimuth, elevation, slant range and the site's ECEF."""
    return aer_to_ecef(az_rad, el_rad, range_m, site_pos_ecef_m)


def _site_rotation(site_pos_ecef_m):
    from sitl.geodesy import ecef_to_geodetic

    lat, lon, _ = ecef_to_geodetic(_vec3("site_pos_ecef_m", site_pos_ecef_m))
    return enu_rotation(lat, lon)


def aer_to_ecef_jacobian(az_rad, el_rad, range_m, site_pos_ecef_m) -> np.ndarray:
    """d pos_ecef / d [az, el, range], (..., 3, 3) (columns az, el, range).

    enu = D (cos el sin az, cos el cos az, sin el), pos = site + R^T enu:
        d/daz = R^T D (cos el cos az, -cos el sin az, 0)
        d/del = R^T D (-sin el sin az, -sin el cos az, cos el)
        d/dD  = R^T (cos el sin az, cos el cos az, sin el)
    """
    az, el, d = np.broadcast_arrays(*(np.asarray(v, float) for v in (az_rad, el_rad, range_m)))
    sa, ca, se, ce = np.sin(az), np.cos(az), np.sin(el), np.cos(el)
    z = np.zeros_like(az)
    j_enu = np.stack([np.stack([d * ce * ca, -d * se * sa, ce * sa], -1),
                      np.stack([-d * ce * sa, -d * se * ca, ce * ca], -1),
                      np.stack([z, d * ce, se], -1)], -2)  # rows e, n, u; columns az, el, D
    rt = np.swapaxes(_site_rotation(site_pos_ecef_m), -1, -2)
    return rt @ j_enu


def ecef_to_aer_jacobian(pos_ecef_m, site_pos_ecef_m) -> np.ndarray:
    """d [az, el, range] / d pos_ecef, (..., 3, 3) (rows az, el, range): the inverse of
    :func:`aer_to_ecef_jacobian` at the same point (for a filter measuring AER directly).

    With (e, n, u) = R (pos - site), rho = hypot(e, n), D = |pos - site|:
        d az = (n, -e, 0) / rho^2,  d el = (-e u, -n u, rho^2) / (rho D^2),  d D = (e, n, u) / D
    each then times R.  Singular at the zenith (rho = 0).
    """
    site = _vec3("site_pos_ecef_m", site_pos_ecef_m)
    r = _site_rotation(site)
    enu = (r @ (_vec3("pos_ecef_m", pos_ecef_m) - site)[..., None])[..., 0]
    e, n, u = enu[..., 0], enu[..., 1], enu[..., 2]
    rho2 = e * e + n * n
    rho, d2 = np.sqrt(rho2), rho2 + u * u
    d = np.sqrt(d2)
    z = np.zeros_like(e)
    j = np.stack([np.stack([n / rho2, -e / rho2, z], -1),
                  np.stack([-e * u / (rho * d2), -n * u / (rho * d2), rho / d2], -1),
                  np.stack([e / d, n / d, u / d], -1)], -2)
    return j @ r


def aer_cov_to_ecef(az_rad, el_rad, range_m, site_pos_ecef_m, var_aer) -> np.ndarray:
    """ECEF covariance (..., 3, 3) J diag(var_az, var_el, var_range) J^T of a radar fix."""
    j = aer_to_ecef_jacobian(az_rad, el_rad, range_m, site_pos_ecef_m)
    v = np.asarray(var_aer, float)
    return (j * v[..., None, :]) @ np.swapaxes(j, -1, -2)


# ---------------------------------------------------------------------------
# the radar


@dataclass(frozen=True)
class RadarParams:
    """Radar error and coverage parameters (SI units; angles in radians)."""

    sigma_range_m: float = param(15.0, check=number(0), doc="stationary std of the range error (AR(1)), m")
    sigma_az_rad: float = param(math.radians(0.1), check=number(0),
                                doc="stationary std of the azimuth error (AR(1)), rad")
    sigma_el_rad: float = param(math.radians(0.1), check=number(0),
                                doc="stationary std of the elevation error (AR(1)), rad")
    gamma_range_1_s: float = param(0.1, check=number(0, lo_open=True),
                                   doc="spectrum width of the range error, 1/s (correlation time 1/gamma)")
    gamma_az_1_s: float = param(0.1, check=number(0, lo_open=True),
                                doc="spectrum width of the azimuth error, 1/s (correlation time 1/gamma)")
    gamma_el_1_s: float = param(0.1, check=number(0, lo_open=True),
                                doc="spectrum width of the elevation error, 1/s (correlation time 1/gamma)")
    max_range_m: float = param(MAX_RANGE_M, check=number(0, lo_open=True),
                               doc="largest true slant range measured, m")
    el_mask_rad: float = param(0.0, check=_EL_MASK,
                               doc="no measurement below this elevation above the geodetic horizon, rad")
    loss_schedule: tuple = param((), check=_intervals,
                                 doc="((t_start, t_end), ...) GPS s: angular auto-tracking lost in these intervals")
    loss_rate_1_s: float = param(0.0, check=number(0),
                                 doc="base hazard of a random tracking loss, 1/s (0: no random losses)")
    loss_ang_rate_ref_rad_s: float = param(math.radians(1.0), check=number(0, lo_open=True),
                                           doc="angular rate of the target that doubles the loss hazard, rad/s "
                                               "(hazard x (1 + (omega / ref)^2))")
    loss_mean_duration_s: float = param(30.0, check=number(0, lo_open=True),
                                        doc="mean duration of a random tracking loss, s")

    def __post_init__(self):
        validate(self)
        _el_mask_below_zenith(self, "el_mask_rad")

    @property
    def sigma(self) -> np.ndarray:
        return np.array([self.sigma_range_m, self.sigma_az_rad, self.sigma_el_rad])

    @property
    def gamma_1_s(self) -> np.ndarray:
        return np.array([self.gamma_range_1_s, self.gamma_az_1_s, self.gamma_el_1_s])


class RadarMeasurement(NamedTuple):
    """One radar epoch for a batch of targets (...)."""

    t_gps_s: float
    slant_range_m: np.ndarray  # NaN when not range_valid
    az_rad: np.ndarray  # NaN when not angles_valid
    el_rad: np.ndarray
    var_range_m2: np.ndarray  # stationary error variances sigma^2 per axis
    var_az_rad2: np.ndarray
    var_el_rad2: np.ndarray
    range_valid: np.ndarray  # in_range and above the elevation mask
    angles_valid: np.ndarray  # range_valid and angular auto-tracking on
    in_range: np.ndarray  # true slant range <= max_range_m
    tracking_lost: np.ndarray  # angular auto-tracking lost (schedule or random)
    site_pos_ecef_m: np.ndarray  # (3,)
    # truth for scoring only (never for an estimator):
    true_range_m: np.ndarray
    true_az_rad: np.ndarray
    true_el_rad: np.ndarray
    error: np.ndarray  # (..., 3) current AR(1) errors [range, az, el]


class Radar:
    """An aerological radar tracking a batch of targets, stepped in simulation time.

    Parameters
    ----------
    rng : Generator, or a sequence of one Generator per target.
    site_lat_rad, site_lon_rad, site_h_m : radar site (geodetic, WGS-84).
    params : RadarParams.
    batch_shape : shape of the target batch (default () one target; or (len(rng),)).
    """

    def __init__(self, rng, *, site_lat_rad, site_lon_rad, site_h_m, params: RadarParams | None = None,
                 batch_shape=None):
        self.params = RadarParams() if params is None else params
        if not isinstance(self.params, RadarParams):
            raise ValueError(f"params: expected a RadarParams, got {type(self.params).__name__}")
        self.site_geodetic, self.site_pos_ecef_m = _site(site_lat_rad, site_lon_rad, site_h_m, "site")
        self._streams = _Streams.for_batch(rng, batch_shape)
        self.batch_shape = batch_shape = self._streams.batch_shape
        self._t = None
        self._err = np.zeros(batch_shape + (3,))
        self._lost = np.zeros(batch_shape, dtype=bool)

    def step(self, t_gps_s, pos_ecef_m, vel_ecef_m_s=None) -> RadarMeasurement:
        """Measure the targets at time t_gps_s (strictly after the previous step).

        pos_ecef_m, vel_ecef_m_s : (..., 3) true target state (the batch shape).  The
        velocity is needed only for the random tracking-loss hazard (angular rate);
        None means zero.
        """
        p = self.params
        t = _time("t_gps_s", t_gps_s)
        if self._t is not None and not t > self._t:
            raise ValueError(f"t_gps_s must increase from step to step: {t} after {self._t}")
        pos = _vec3("pos_ecef_m", pos_ecef_m)
        vel = np.zeros_like(pos) if vel_ecef_m_s is None else _vec3("vel_ecef_m_s", vel_ecef_m_s)
        shape = self.batch_shape + (3,)
        if pos.shape != shape or vel.shape != shape:
            raise ValueError(f"pos_ecef_m and vel_ecef_m_s must have shape {shape}, got {pos.shape}, {vel.shape}")

        # AR(1) errors: stationary start, then eps = mu eps + v n
        n = self._streams.normal(3)
        if self._t is None:
            self._err = n * p.sigma
        else:
            mu, v = ar1_coefficients(p.sigma, p.gamma_1_s, t - self._t)
            self._err = mu * self._err + v * n
        u = self._streams.uniform(1)[..., 0]

        az, el, d = ecef_to_aer(self.site_pos_ecef_m, pos)
        in_range = d <= p.max_range_m
        range_valid = in_range & (el >= p.el_mask_rad)

        # angular auto-tracking: random losses (hazard grows with the angular rate)
        if p.loss_rate_1_s > 0.0 and self._t is not None:
            dt = t - self._t
            los = (pos - self.site_pos_ecef_m) / d[..., None]
            v_perp = vel - np.sum(vel * los, axis=-1, keepdims=True) * los
            omega = np.linalg.norm(v_perp, axis=-1) / d
            lam = p.loss_rate_1_s * (1.0 + (omega / p.loss_ang_rate_ref_rad_s) ** 2)
            start = ~self._lost & (u < -np.expm1(-lam * dt))
            end = self._lost & (u < -np.expm1(-dt / p.loss_mean_duration_s))
            self._lost = (self._lost | start) & ~end
        self._t = t
        lost = self._lost | _in_schedule(p.loss_schedule, t)
        angles_valid = range_valid & ~lost

        meas_d = np.where(range_valid, d + self._err[..., 0], np.nan)
        meas_az = np.where(angles_valid, np.mod(az + self._err[..., 1], 2.0 * math.pi), np.nan)
        meas_el = np.where(angles_valid, el + self._err[..., 2], np.nan)
        ones = np.ones(self.batch_shape)
        return RadarMeasurement(
            t, meas_d[()], meas_az[()], meas_el[()], ones * p.sigma_range_m**2, ones * p.sigma_az_rad**2,
            ones * p.sigma_el_rad**2, range_valid, angles_valid, in_range, np.broadcast_to(lost, self.batch_shape).copy(),
            self.site_pos_ecef_m.copy(), d, az, el, self._err.copy())

    def track(self, t_gps_s, pos_ecef_m, vel_ecef_m_s=None) -> RadarMeasurement:
        """Many steps at once: t (T,) strictly increasing (after the previous step), states
        (T, ..., 3). The same numbers as T calls of :meth:`step` (the same draws in the same
        order), as a RadarMeasurement whose fields carry a leading epoch axis (t_gps_s (T,);
        site_pos_ecef_m shared); the geometry is computed for all epochs in one call."""
        p = self.params
        t = np.asarray(t_gps_s, dtype=float)
        if t.ndim != 1 or t.size == 0 or not np.all(np.isfinite(t)):
            raise ValueError(f"t_gps_s must be a non-empty 1-D array of finite GPS times, got shape {t.shape}")
        if np.any(np.diff(t) <= 0.0) or (self._t is not None and not t[0] > self._t):
            raise ValueError("t_gps_s must increase strictly (and follow the previous step)")
        shape = (t.size,) + self.batch_shape + (3,)
        pos = _vec3("pos_ecef_m", pos_ecef_m)
        vel = np.zeros_like(pos) if vel_ecef_m_s is None else _vec3("vel_ecef_m_s", vel_ecef_m_s)
        if pos.shape != shape or vel.shape != shape:
            raise ValueError(f"pos_ecef_m and vel_ecef_m_s must have shape {shape}, got {pos.shape}, {vel.shape}")
        K = t.size
        az, el, d = ecef_to_aer(self.site_pos_ecef_m, pos)  # (T, ...)
        in_range = d <= p.max_range_m
        range_valid = in_range & (el >= p.el_mask_rad)
        if p.loss_rate_1_s > 0.0:
            los = (pos - self.site_pos_ecef_m) / d[..., None]
            v_perp = vel - np.sum(vel * los, axis=-1, keepdims=True) * los
            lam = p.loss_rate_1_s * (1.0 + (np.linalg.norm(v_perp, axis=-1) / d / p.loss_ang_rate_ref_rad_s) ** 2)
        err = np.empty(shape)
        lost = np.empty((K,) + self.batch_shape, dtype=bool)
        sigma = p.sigma
        coef = {}
        for k in range(K):
            n = self._streams.normal(3)
            u = self._streams.uniform(1)[..., 0]
            tk = float(t[k])
            if self._t is None:
                self._err = n * sigma
            else:
                dt = tk - self._t
                c = coef.get(dt)
                if c is None:
                    c = coef[dt] = ar1_coefficients(sigma, p.gamma_1_s, dt)
                self._err = c[0] * self._err + c[1] * n
                if p.loss_rate_1_s > 0.0:
                    start = ~self._lost & (u < -np.expm1(-lam[k] * dt))
                    end = self._lost & (u < -np.expm1(-dt / p.loss_mean_duration_s))
                    self._lost = (self._lost | start) & ~end
            self._t = tk
            err[k] = self._err
            lost[k] = self._lost | _in_schedule(p.loss_schedule, tk)
        angles_valid = range_valid & ~lost
        meas_d = np.where(range_valid, d + err[..., 0], np.nan)
        meas_az = np.where(angles_valid, np.mod(az + err[..., 1], 2.0 * math.pi), np.nan)
        meas_el = np.where(angles_valid, el + err[..., 2], np.nan)
        ones = np.ones(d.shape)
        return RadarMeasurement(
            t.copy(), meas_d, meas_az, meas_el, ones * p.sigma_range_m**2, ones * p.sigma_az_rad**2,
            ones * p.sigma_el_rad**2, range_valid, angles_valid, in_range, lost, self.site_pos_ecef_m.copy(), d, az, el,
            err)
