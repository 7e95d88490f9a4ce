"""Onboard GNSS navigation of each UAV (seed 002, eqs 1-6 and 10): receiver + EKF, batched.

Each UAV has a GNSS receiver and runs its own EKF; the filters of all UAVs (and of all
Monte Carlo trials) are stepped together as one batch.  Each publishes its estimate
x = [pos_ecef_m, vel_ecef_m_s] (..., 6) and covariance P (..., 6, 6): the decomposition the
seed requires (UAVs navigate on board; the single computer locates the beacon from their
estimates).

Measurements (seed 002 eqs 1-2), satellite S_j with velocity V_S_j, UAV U with V_U, ECEF:

    pseudorange       Z_R = |S_j - U| + W_R
    Doppler velocity  Z_V = (S_j - U) . (V_S_j - V_U) / |S_j - U| + W_V

with NO receiver clock, as in the seed (a real receiver would add a clock bias and drift;
that is not modelled here -- the choice is the seed's, and with it three satellites fix
the position).  Sign: Z_V as printed is d|S_j - U|/dt, the range rate, positive when the
range grows (the standard convention).  W_R, W_V are white noises with two-sided PSDs
N_R = (30 m)^2 s and N_V = (0.2 m/s)^2 s (seed example); a receiver reporting once per
dt_s averages them to variances N / dt_s (``sitl.radio.beacon_link.psd_to_variance``):
sigma 30 m and 0.2 m/s at dt_s = 1 s.

Geometry: by default the truth uses the light-time solution with the Earth's rotation
during the flight (``sitl.gnss.ranging.light_time_geometry``), and the filter evaluates the
ephemeris at the transit time measured by its own pseudorange
(``sitl.gnss.world.ephemeris_for_filter``): no truth enters the estimator.  With
``light_time=False`` both use the instantaneous satellite state at t (the seed's
equations literally).

Satellites:
  (a) the seed's case -- three satellites on unperturbed Keplerian orbits
      (:func:`example_three_satellites`).  The seed's printed initial state vectors lost
      their exponents in the OCR; read digit for digit, two of the three give hyperbolic
      orbits (|V| above the escape speed), so they cannot be used.  The three satellites are
      instead three GPS satellites of the built-in almanac (least clock-free PDOP, above the
      mask for the whole run) with the secular node drift removed (OmegaDot = 0): the pure
      two-body orbit, propagated by the analytic Kepler solution
      (``sitl.gnss.orbits.sat_state_ecef``), which the tests check against an RK4 and a
      solve_ivp integration of the two-body ODE.
  (b) the real GPS constellation (``sitl.gnss.orbits.gps_constellation``), every satellite
      above the elevation mask; clock-free as well.

The measurement vector has a fixed layout over all S satellites of the constellation
[pr_1..pr_S, prr_1..prr_S]; untracked channels (below the mask) carry no information
(H row 0, innovation 0, variance 1: the Kalman gain column is exactly 0).

EKF (filters.ekf.ekf_step): state [pos (3), vel (3)] ECEF, constant-velocity transition
(continuous white-noise acceleration, filters.models.ConstantVelocity):
F = [[I, T I], [0, I]], Q = q [[T^3/3 I, T^2/2 I], [T^2/2 I, T I]], q the acceleration PSD
(m^2/s^3).  Default q = 0.035 m^2/s^3 (sqrt(q T) = 0.19 m/s per 1 s step).  The seed's UAVs
accelerate by up to ~0.25-0.27 m/s^2 (speed and climb sinusoids, periods 314-628 s, in both
the geodetic and the printed reading), deterministically, so the lag it causes is the same
in every Monte Carlo trial and is not averaged out: q was set by the NEES over Monte Carlo
on the seed trajectories (three satellites, 1 s epochs, 100 trials x 3 UAVs, 200 s; 99 %
band of the time-averaged ANEES 5.50-6.53): geodetic reading 6.89 at q = 0.02, 5.98 at
0.03, 5.78 at 0.035, 5.65 at 0.04, 5.50 at 0.05; printed reading 6.61, 5.84, 5.67, 5.56,
5.44. A constant-velocity model cannot follow a sinusoidal acceleration epoch by epoch:
the per-epoch NEES swings around its mean (about 75 % of epochs inside the per-epoch band
on the geodetic reading, 55 % on the printed one at q = 0.035); a Singer (or
sinusoid-aware) model would be the step up.  The first epoch
initialises the filter with a least-squares fix (Gauss-Newton on the same measurement
model, P0 = (H' R^-1 H)^-1).

Integrity (seed 003, opt-in: ``NavConfig(integrity=IntegrityConfig(...))``): the EKF update
runs under filters.integrity.IntegrityMonitor with one channel per satellite (its pseudorange
and rate rows; :func:`nav_step_monitored`); OnboardNav keeps the Report and, given a
sitl.integrity_events.IntegrityEventPublisher, publishes the events (channel
``<uav id>.<satellite id>``). Off by default, measured (tests/app/test_integrity_wiring.py and
the integrity experiment's report): with the seed's three satellites there is no redundancy -- excluding
one satellite leaves the position unobservable (fault-free RMSE 6.0 m -> 42 m, 100 trials x 3
UAVs, 300 s, before the rule below); :data:`RECOMMENDED_INTEGRITY` therefore has
``min_channels=3``: a UAV leaves a satellite (or a row) out only while three tracked
satellites stay in, and detects and reports only below that -- with three satellites the
monitored filter is the plain one bit for bit, fault-free or not (tested), and still publishes
the events. With the GPS constellation and :data:`RECOMMENDED_INTEGRITY` the fault-free
RMSE moves by +0.4 % (+0.014 +- 0.006 m on 3.74 m, 300 UAV runs of 300 s; on another seed
-0.003 +- 0.009 m on 3.78 m, 90 runs: non-inferior within 2 %, not always "no worse" at one-sided
95 %), while a 150 m pseudorange step on one satellite is excluded within 1-3 epochs in every
run and a 2 m/s ramp within 21-59 s (median 32 s: without the bias test the window sees it once
it nears 2 sigma), the RMSE over such a run dropping from 30.5 m to 4.4 m. The
monitor's bias test is left out there: the constant-velocity model's lag under the seed's
accelerations (up to ~0.27 m/s^2) biases the Doppler innovations for tens of seconds, so the
bias test excludes healthy satellites (fault-free RMSE +5 %).
"""
from __future__ import annotations

import functools
import itertools
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from filters.ekf import ekf_predict, ekf_step, ekf_update
from filters.integrity import IntegrityConfig, IntegrityMonitor
from filters.models import ClockFreePseudorangeDoppler, ConstantVelocity
from filters.params import ParamError, integer, number, param, instance_of, switch, validate
from sitl import geodesy
from sitl.gnss import orbits, ranging, world
from sitl.gnss.orbits import Constellation
from sitl.radio.beacon_link import psd_to_variance

__all__ = [
    "DEFAULT_PSD_PR_M2_S",
    "DEFAULT_PSD_PRR_M2_S",
    "EXAMPLE_T0_GPS_S",
    "RECOMMENDED_INTEGRITY",
    "GnssNoise",
    "NavConfig",
    "GnssEpoch",
    "NavEstimate",
    "NavTrack",
    "unperturbed",
    "pdop_clock_free",
    "example_three_satellites",
    "TruthGeometry",
    "truth_geometry",
    "gnss_measure",
    "filter_sat_states",
    "nav_measurement_model",
    "ls_fix",
    "nav_init",
    "nav_step",
    "nav_step_monitored",
    "sat_channels",
    "OnboardNav",
    "nav_track",
    "EKF_INNOVATION_GATE_SIGMA",
    "dops_clock_free",
    "ned_rotation",
    "ned_covariances",
    "InnovationTestRatios",
    "innovation_test_ratios",
]

#: Seed 002 GNSS noise intensities (two-sided PSDs): range (30 m)^2 s, Doppler (0.2 m/s)^2 s.
DEFAULT_PSD_PR_M2_S = 30.0**2
DEFAULT_PSD_PRR_M2_S = 0.2**2
#: The integrity monitor's settings for the onboard EKF (module docstring): jumps at 3.5 sigma, the
#: mean-square window test over 30 epochs at 1e-4, no bias test, isolation only while three tracked
#: satellites stay in (the clock-free fix needs three; below that, detect only).
RECOMMENDED_INTEGRITY = IntegrityConfig(jump_sigma=3.5, window=30, window_alpha=1e-4, bias_alpha=None, min_channels=3)
#: Start of the seed 002 run in GPS time: one hour after the built-in almanac's epoch.
EXAMPLE_T0_GPS_S = orbits.DEFAULT_TOA_GPS_S + 3600.0

_EARTH_RADIUS_M = 6_371_000.0
_N = 6


def _check_constellation(constellation) -> Constellation:
    if not isinstance(constellation, Constellation):
        raise ValueError(f"constellation must be a sitl.gnss.orbits.Constellation, got {type(constellation).__name__}")
    return constellation


# --------------------------------------------------------------------------- configuration

_POSITIVE = number(0.0, lo_open=True)


def _elevation(key, value) -> float:
    """An elevation angle in [-pi/2, pi/2) rad, as a float."""
    el = number()(key, value)
    if not -math.pi / 2 <= el < math.pi / 2:
        raise ParamError(key, f"expected an elevation in [-pi/2, pi/2) rad, got {value!r}")
    return el


@dataclass(frozen=True)
class GnssNoise:
    """GNSS measurement noise: two-sided PSDs and the receiver's output interval."""

    psd_pr_m2_s: float = param(DEFAULT_PSD_PR_M2_S, check=_POSITIVE,
                               doc="pseudorange noise PSD (two-sided), m^2 s (seed: 900)")
    psd_prr_m2_s: float = param(DEFAULT_PSD_PRR_M2_S, check=_POSITIVE,
                                doc="Doppler (range-rate) noise PSD (two-sided), (m/s)^2 s (seed: 0.04)")
    dt_s: float = param(1.0, check=_POSITIVE, doc="interval over which a reported measurement averages the noise, s")

    def __post_init__(self):
        validate(self)

    # computed once per (frozen) instance: read several times every epoch
    @functools.cached_property
    def var_pr_m2(self) -> float:
        return float(psd_to_variance(self.psd_pr_m2_s, self.dt_s))

    @functools.cached_property
    def var_prr_m2_s2(self) -> float:
        return float(psd_to_variance(self.psd_prr_m2_s, self.dt_s))


@dataclass(frozen=True)
class NavConfig:
    """Receiver and onboard-filter settings."""

    noise: GnssNoise = param(default_factory=GnssNoise, check=instance_of(GnssNoise),
                             doc="the receiver's noise (and the variances the filter assumes: the same numbers)")
    q_m2_s3: float = param(0.035, check=number(0.0),
                           doc="acceleration PSD of the constant-velocity model, m^2/s^3 (see the module docstring)")
    el_mask_rad: float = param(math.radians(10.0), check=_elevation,
                               doc="satellites below this geodetic elevation are not tracked, rad")
    light_time: bool = param(True, check=switch(),
                             doc="light-time geometry with Earth rotation (True) or instantaneous (False)")
    ls_iterations: int = param(10, check=integer(1), doc="Gauss-Newton iterations of the initial least-squares fix")
    integrity: IntegrityConfig | None = param(None, check=instance_of(IntegrityConfig, none=True),
                                              doc="the integrity monitor around the EKF update (filters.integrity, one "
                                                  "channel per satellite: its pseudorange and rate rows), or None for "
                                                  "the plain EKF")

    def __post_init__(self):
        validate(self)

    def transition(self) -> ConstantVelocity:
        return ConstantVelocity(3, q=self.q_m2_s3)


@functools.lru_cache(maxsize=64)
def _cv_matrices(q: float, dt: float):
    """(F, Q) of ConstantVelocity(3, q) over dt, built once per (q, dt)."""
    m = ConstantVelocity(3, q=q)
    return np.asarray(m.F(None, dt), dtype=float), np.asarray(m.Q(dt), dtype=float)


class _MemoTransition:
    """NavConfig.transition() with F and Q (and f's F) memoised per step length (the same
    numbers, without rebuilding them from Kronecker products every epoch); every other
    attribute is the ConstantVelocity model's."""

    linear = True  # (filters.protocols.TransitionModel)

    def __init__(self, q: float):
        self.q = float(q)
        self._model = ConstantVelocity(3, q=self.q)

    def F(self, x, dt):
        return _cv_matrices(self.q, float(dt))[0].copy()

    def Q(self, dt):
        return _cv_matrices(self.q, float(dt))[1].copy()

    def f(self, x, dt):
        # ConstantVelocity.f's arithmetic (x @ F.T) without rebuilding F: ekf_predict calls it every
        # monitored step
        x = np.asarray(x, dtype=float)
        if x.ndim < 1 or x.shape[-1] != _N:
            raise ValueError(f"x must have shape (..., {_N}), got {x.shape}")
        return x @ _cv_matrices(self.q, float(dt))[0].T

    def __getattr__(self, name):
        return getattr(self._model, name)


@functools.lru_cache(maxsize=16)
def _transition(q: float) -> _MemoTransition:
    return _MemoTransition(q)


# --------------------------------------------------------------------------- satellites


def unperturbed(constellation: Constellation) -> Constellation:
    """The constellation with its secular node drift removed (OmegaDot = 0) and no harmonic
    corrections: each satellite on its unperturbed two-body (Keplerian) orbit."""
    c = _check_constellation(constellation)
    zero = np.zeros(len(c))
    return c.replace(OmegaDot_rad_s=zero, delta_n_rad_s=zero, idot_rad_s=zero, cuc_rad=zero, cus_rad=zero,
                     crc_m=zero, crs_m=zero, cic_rad=zero, cis_rad=zero)


def pdop_clock_free(rx_pos_ecef_m, sat_pos_ecef_m) -> np.ndarray:
    """Position DOP without a clock: sqrt(trace((G'G)^-1)), G rows the unit vectors receiver
    -> satellite.  rx (..., 3), sats (..., S, 3), S >= 3."""
    los = np.asarray(sat_pos_ecef_m, float) - np.asarray(rx_pos_ecef_m, float)[..., None, :]
    los = los / np.linalg.norm(los, axis=-1, keepdims=True)
    G = np.swapaxes(los, -1, -2) @ los
    return np.sqrt(np.trace(np.linalg.inv(G), axis1=-2, axis2=-1))


def example_three_satellites(rx_pos_ecef_m, t0_gps_s: float = EXAMPLE_T0_GPS_S, duration_s: float = 1000.0,
                             el_min_rad: float = math.radians(15.0),
                             constellation: Constellation | None = None) -> Constellation:
    """Three satellites on unperturbed Keplerian orbits for the seed's case (module docstring).

    Among the satellites of ``constellation`` (default: the built-in GPS almanac) above
    el_min_rad at rx_pos_ecef_m (3,) both at t0_gps_s and at t0_gps_s + duration_s, the
    triple with the least clock-free PDOP at t0 (worst of the two ends), with OmegaDot = 0.
    """
    c = _check_constellation(orbits.gps_constellation() if constellation is None else constellation)
    rx = np.asarray(rx_pos_ecef_m, dtype=float)
    if rx.shape != (3,) or not np.all(np.isfinite(rx)):
        raise ValueError(f"rx_pos_ecef_m must be one finite ECEF position (3,), got shape {rx.shape}")
    _POSITIVE("duration_s", duration_s)
    cu = unperturbed(c)
    pos, _ = orbits.sat_state_ecef(cu, np.array([t0_gps_s, t0_gps_s + duration_s]))
    _, el, _ = geodesy.ecef_to_aer(rx, pos)
    vis = np.flatnonzero(np.all(el >= el_min_rad, axis=0))
    if vis.size < 3:
        raise ValueError(f"el_min_rad: only {vis.size} satellites stay above {math.degrees(el_min_rad):.1f} deg "
                         "for the whole run; 3 are needed")
    best, best_pdop = None, np.inf
    for combo in itertools.combinations(vis.tolist(), 3):
        try:
            pdop = float(np.max(pdop_clock_free(rx, pos[:, combo])))
        except np.linalg.LinAlgError:
            continue
        if pdop < best_pdop:
            best, best_pdop = combo, pdop
    return cu.subset(np.array(best))


# --------------------------------------------------------------------------- receiver (truth side)


class GnssEpoch(NamedTuple):
    """One epoch of receiver output for a batch of receivers (..., S).

    pseudorange_m, pseudorange_rate_m_s: NaN where the satellite is not tracked.
    var_pr_m2, var_prr_m2_s2: per-sample noise variances (scalars: N / dt_s).
    tracked: (..., S) bool.
    """

    t_gps_s: float
    pseudorange_m: np.ndarray
    pseudorange_rate_m_s: np.ndarray
    var_pr_m2: float
    var_prr_m2_s2: float
    tracked: np.ndarray


class TruthGeometry(NamedTuple):
    """What the receivers measure before noise, (..., S): true range, range rate and the
    satellites' geodetic elevation at the true receiver position."""

    range_m: np.ndarray
    range_rate_m_s: np.ndarray
    el_rad: np.ndarray

    def at(self, k) -> "TruthGeometry":
        """The k-th entry of a leading (epoch) axis."""
        return TruthGeometry(self.range_m[k], self.range_rate_m_s[k], self.el_rad[k])


def truth_geometry(t_gps_s, pos_ecef_m, vel_ecef_m_s, constellation: Constellation,
                   config: NavConfig = NavConfig()) -> TruthGeometry:
    """The receivers' noise-free geometry (truth side), batched: t_gps_s broadcast against
    pos_ecef_m.shape[:-1], so many epochs go in one call (t (K, 1), positions (K, N, 3)).

    The geometry of :func:`gnss_measure`; the same numbers epoch by epoch as one epoch per
    call for epochs >= 1 s apart (one call then interpolates the ephemeris on the same
    nodes; its light-time iteration may run one round more for some receivers, which moves
    tau by less than one ulp once it has converged to 1e-12 s).
    """
    c = _check_constellation(constellation)
    r = np.asarray(pos_ecef_m, dtype=float)
    v = np.asarray(vel_ecef_m_s, dtype=float)
    if r.ndim < 1 or r.shape[-1] != 3 or v.shape != r.shape:
        raise ValueError(f"pos_ecef_m and vel_ecef_m_s must have the same shape (..., 3), got {r.shape}, {v.shape}")
    if config.light_time:
        geo = ranging.light_time_geometry(t_gps_s, r, v, c)
        _, el = world.look_angles(r, geo)
        return TruthGeometry(geo.range_m, geo.range_rate_m_s, el)
    t = np.asarray(t_gps_s, dtype=float)
    sp, sv = orbits.sat_state_ecef(c, float(t) if t.ndim == 0 else t)  # (S, 3) or (..., S, 3)
    d = sp - r[..., None, :]
    rho = np.linalg.norm(d, axis=-1)
    rate = np.sum(d * (sv - v[..., None, :]), axis=-1) / rho
    _, el, _ = geodesy.ecef_to_aer(r[..., None, :], sp)
    return TruthGeometry(rho, rate, el)


def gnss_measure(rng: np.random.Generator, t_gps_s: float, pos_ecef_m, vel_ecef_m_s, constellation: Constellation,
                 config: NavConfig = NavConfig(), trials_shape: tuple = (),
                 geometry: TruthGeometry | None = None) -> GnssEpoch:
    """The receivers' clock-free pseudoranges and Doppler range rates at t_gps_s (truth in).

    pos_ecef_m, vel_ecef_m_s (..., 3): the true receiver states (e.g. (n_uav, 3)).
    trials_shape prepends axes of independent noise on the same truth: output
    trials_shape + (..., S).  A satellite is tracked when its geodetic elevation at the true
    receiver position is >= config.el_mask_rad.  geometry: this epoch's
    :func:`truth_geometry` when already computed (batch runs compute many epochs at once);
    the same random draws either way.
    """
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    if not isinstance(config, NavConfig):
        raise ValueError(f"config must be a NavConfig, got {type(config).__name__}")
    c = _check_constellation(constellation)
    t = float(t_gps_s)
    if geometry is None:
        geometry = truth_geometry(t, pos_ecef_m, vel_ecef_m_s, c, config)
    elif not isinstance(geometry, TruthGeometry) or geometry.range_m.shape[-1] != len(c):
        raise ValueError(f"geometry must be a TruthGeometry over the constellation's {len(c)} satellites")
    rho, rate, el = geometry
    tracked = np.broadcast_to(el >= config.el_mask_rad, tuple(trials_shape) + rho.shape)
    shape = tracked.shape
    vr, vv = config.noise.var_pr_m2, config.noise.var_prr_m2_s2
    pr = rho + math.sqrt(vr) * rng.standard_normal(shape)
    prr = rate + math.sqrt(vv) * rng.standard_normal(shape)
    return GnssEpoch(t, np.where(tracked, pr, np.nan), np.where(tracked, prr, np.nan), vr, vv, tracked.copy())


# --------------------------------------------------------------------------- estimator side


def filter_sat_states(epochs, constellation: Constellation, config: NavConfig = NavConfig()):
    """The satellite states the filters use, for many epochs at once: (sat_pos, sat_vel)
    (K, ..., S, 3), entry k what :func:`nav_measurement_model` computes for epochs[k] from
    the receiver output and the ephemeris alone (one call for all; the same numbers for
    epochs >= 1 s apart, see :func:`truth_geometry`).  epochs: GnssEpochs of one shape."""
    c = _check_constellation(constellation)
    pr = np.stack([e.pseudorange_m for e in epochs])
    if pr.shape[-1] != len(c):
        raise ValueError(f"epochs have {pr.shape[-1]} satellite columns, constellation has {len(c)}")
    t = np.array([e.t_gps_s for e in epochs], dtype=float).reshape((-1,) + (1,) * (pr.ndim - 2))
    if config.light_time:
        prr = np.stack([e.pseudorange_rate_m_s for e in epochs])
        return world.ephemeris_for_filter(np.broadcast_to(t, pr.shape[:-1]), pr, c, pseudorange_rate_m_s=prr)
    sp, sv = orbits.sat_state_ecef(c, t.reshape(-1))
    shape = pr.shape + (3,)
    return (np.broadcast_to(sp.reshape((-1,) + (1,) * (pr.ndim - 2) + sp.shape[-2:]), shape),
            np.broadcast_to(sv.reshape((-1,) + (1,) * (pr.ndim - 2) + sv.shape[-2:]), shape))


def nav_measurement_model(epoch: GnssEpoch, constellation: Constellation,
                          config: NavConfig = NavConfig(),
                          sat_states=None) -> tuple[ClockFreePseudorangeDoppler, np.ndarray]:
    """(model, z) for the filter from one epoch of receiver output and the ephemeris only.

    Satellite states: the ephemeris at the transit time measured by the pseudorange
    (light_time=True) or at t (light_time=False); sat_states: those (sat_pos, sat_vel)
    when already computed (:func:`filter_sat_states`).  z = [pr, prr] with 0 where
    untracked.  The variances are the filter's own model (config.noise), not the receiver's
    report."""
    c = _check_constellation(constellation)
    pr, prr, tr = epoch.pseudorange_m, epoch.pseudorange_rate_m_s, epoch.tracked
    if pr.shape[-1] != len(c):
        raise ValueError(f"epoch has {pr.shape[-1]} satellite columns, constellation has {len(c)}")
    if sat_states is not None:
        sp, sv = sat_states
    elif config.light_time:
        sp, sv = world.ephemeris_for_filter(epoch.t_gps_s, pr, c, pseudorange_rate_m_s=prr)
    else:
        sp, sv = orbits.sat_state_ecef(c, epoch.t_gps_s)
    model = ClockFreePseudorangeDoppler(sp, sv, config.noise.var_pr_m2, config.noise.var_prr_m2_s2, tr)
    z = np.concatenate([np.where(tr, pr, 0.0), np.where(tr, prr, 0.0)], axis=-1)
    return model, z


class NavEstimate(NamedTuple):
    """A batch of onboard estimates at t_gps_s: x (..., 6) [pos, vel] ECEF, P (..., 6, 6),
    nis (...) of the last update (NaN at initialisation), n_tracked (...)."""

    t_gps_s: float
    x: np.ndarray
    P: np.ndarray
    nis: np.ndarray
    n_tracked: np.ndarray

    @property
    def pos_ecef_m(self) -> np.ndarray:
        return self.x[..., 0:3]

    @property
    def vel_ecef_m_s(self) -> np.ndarray:
        return self.x[..., 3:6]


def ls_fix(epoch: GnssEpoch, constellation: Constellation, config: NavConfig = NavConfig()):
    """Least-squares fix (x (..., 6), P (..., 6, 6)) from one epoch, batched.

    Weighted Gauss-Newton on the clock-free model (config.ls_iterations steps) from a point
    on the Earth's surface under the mean direction of the tracked satellites, velocity 0:
    x += (H'WH)^-1 H'W (z - h(x)), P = (H'WH)^-1 at the solution.  With three satellites
    the fix is exact (zero residual); the mirror solution lies on the far side of the
    satellites' plane, far from the Earth, and the start point avoids it.
    Raises ValueError where fewer than 3 satellites are tracked.
    """
    n_tr = epoch.tracked.sum(axis=-1)
    if np.any(n_tr < 3):
        raise ValueError(f"epoch: a fix needs >= 3 tracked satellites, some receivers have {int(n_tr.min())}")
    model, z = nav_measurement_model(epoch, constellation, config)
    tr = model.tracked
    sp = np.where(tr[..., None], model.sat_pos_ecef_m, 0.0).sum(axis=-2)
    x = np.zeros(z.shape[:-1] + (_N,))
    x[..., 0:3] = _EARTH_RADIUS_M * sp / np.linalg.norm(sp, axis=-1, keepdims=True)
    W = 1.0 / model.R_diag()
    for k in range(int(config.ls_iterations) + 1):
        hx, H = model.h_and_H(x)
        A = np.einsum("...ki,...k,...kj->...ij", H, W, H)
        if k == config.ls_iterations:
            break
        g = np.einsum("...ki,...k->...i", H, W * (z - hx))
        x = x + np.linalg.solve(A, g[..., None])[..., 0]
    P = np.linalg.inv(A)
    return x, 0.5 * (P + np.swapaxes(P, -1, -2))


def nav_init(epoch: GnssEpoch, constellation: Constellation, config: NavConfig = NavConfig()) -> NavEstimate:
    """The filters' initial estimate: the least-squares fix of the first epoch."""
    x, P = ls_fix(epoch, constellation, config)
    return NavEstimate(epoch.t_gps_s, x, P, np.full(x.shape[:-1], np.nan), epoch.tracked.sum(axis=-1))


def nav_step(est: NavEstimate, epoch: GnssEpoch, constellation: Constellation,
             config: NavConfig = NavConfig(), backend=None, sat_states=None) -> NavEstimate:
    """One EKF predict (to epoch.t_gps_s) + update with the epoch's measurements, batched.
    sat_states: the epoch's :func:`filter_sat_states` when already computed."""
    dt = epoch.t_gps_s - est.t_gps_s
    if not dt > 0:
        raise ValueError(f"epoch.t_gps_s must be after the estimate's time {est.t_gps_s}, got {epoch.t_gps_s}")
    model, z = nav_measurement_model(epoch, constellation, config, sat_states)
    res = ekf_step(est.x, est.P, z, _transition(float(config.q_m2_s3)), model, dt, backend=backend)
    return NavEstimate(epoch.t_gps_s, res.x, res.P, res.nis, epoch.tracked.sum(axis=-1))


def sat_channels(n_sats: int) -> np.ndarray:
    """The monitor's row -> channel map of the measurement layout [pr_1..pr_S, prr_1..prr_S]:
    one channel per satellite (its pseudorange and rate)."""
    a = np.arange(int(n_sats))
    return np.concatenate([a, a])


def nav_step_monitored(est: NavEstimate, epoch: GnssEpoch, constellation: Constellation, monitor: IntegrityMonitor,
                       state, config: NavConfig = NavConfig(), backend=None, sat_states=None):
    """:func:`nav_step` with the integrity monitor around the update: (NavEstimate,
    MonitorState, Report). Untracked satellites enter the monitor as missing (NaN), so
    they count as healthy in its windows; a satellite whose rows fail the monitor's tests
    is left out of the update (a jump: that row this epoch; a persistent step or a drift:
    the whole channel until it is readmitted)."""
    dt = epoch.t_gps_s - est.t_gps_s
    if not dt > 0:
        raise ValueError(f"epoch.t_gps_s must be after the estimate's time {est.t_gps_s}, got {epoch.t_gps_s}")
    model, z = nav_measurement_model(epoch, constellation, config, sat_states)
    tr = np.asarray(epoch.tracked, dtype=bool)
    z = np.where(np.concatenate([tr, tr], axis=-1), z, np.nan)
    x_pred, P_pred = ekf_predict(est.x, est.P, _transition(float(config.q_m2_s3)), dt, backend=backend)
    res, state, rep = monitor.step(state, x_pred, P_pred, z, model, sat_channels(tr.shape[-1]), update=ekf_update,
                                   backend=backend)
    return NavEstimate(epoch.t_gps_s, res.x, res.P, res.nis, tr.sum(axis=-1)), state, rep



class OnboardNav:
    """The onboard navigation of a batch of UAVs: ``update(epoch)`` initialises from the
    first epoch's least-squares fix, then runs one EKF step per epoch; ``estimate`` is the
    latest :class:`NavEstimate` (what the UAV publishes, with its covariance).

    With ``config.integrity`` set, each step runs under the integrity monitor (one channel
    per satellite); ``report`` is the last epoch's filters.integrity.Report and, when an
    ``events`` publisher (sitl.integrity_events.IntegrityEventPublisher) is given, the
    epoch's integrity events go out through it (``last_events``), their channels named
    ``<uav id>.<satellite id>`` (uav_ids: the ids along the last batch axis, default
    uav1, uav2, ...; a single UAV without a batch axis: uav_ids[0]). The first epoch's
    least-squares fix is not monitored (it uses every tracked satellite).
    """

    def __init__(self, constellation: Constellation, config: NavConfig = NavConfig(), backend=None, *,
                 events=None, uav_ids=None):
        self.constellation = _check_constellation(constellation)
        if not isinstance(config, NavConfig):
            raise ValueError(f"config must be a NavConfig, got {type(config).__name__}")
        self.config = config
        self.backend = backend
        self.estimate: NavEstimate | None = None
        self.monitor = None if config.integrity is None else IntegrityMonitor(config.integrity)
        self.monitor_state = None
        self.report = None
        self.events = events
        self.last_events: list = []
        self.uav_ids = None if uav_ids is None else [str(u) for u in uav_ids]
        self._sat_ids = [str(s) for s in np.asarray(self.constellation.sat_id)]

    def channel_name(self, b: tuple, c: int) -> str:
        """The bus channel of satellite c of batch member b: ``<uav id>.<satellite id>``."""
        i = b[-1] if b else 0
        uav = self.uav_ids[i] if self.uav_ids is not None else f"uav{i + 1}"
        return f"{uav}.{self._sat_ids[c]}"

    def update(self, epoch: GnssEpoch, sat_states=None) -> NavEstimate:
        """sat_states: the epoch's :func:`filter_sat_states` when already computed."""
        if self.estimate is None:
            self.estimate = nav_init(epoch, self.constellation, self.config)
            if self.monitor is not None:
                S = len(self.constellation)
                self.monitor_state = self.monitor.init(self.estimate.x.shape[:-1], 2 * S, S)
        elif self.monitor is None:
            self.estimate = nav_step(self.estimate, epoch, self.constellation, self.config, self.backend,
                                     sat_states)
        else:
            self.estimate, self.monitor_state, self.report = nav_step_monitored(
                self.estimate, epoch, self.constellation, self.monitor, self.monitor_state, self.config,
                self.backend, sat_states)
            if self.events is not None:
                self.last_events = self.events(self.report, sat_channels(len(self.constellation)), epoch.t_gps_s,
                                               self.channel_name, self.config.integrity)
        return self.estimate


class NavTrack(NamedTuple):
    """A run of the onboard filters: epochs on the leading axis T.

    t_gps_s (T,); x (T, ..., 6); P (T, ..., 6, 6); nis (T, ...); n_tracked (T, ...)."""

    t_gps_s: np.ndarray
    x: np.ndarray
    P: np.ndarray
    nis: np.ndarray
    n_tracked: np.ndarray


def nav_track(rng: np.random.Generator, t_gps_s, pos_ecef_m, vel_ecef_m_s, constellation: Constellation,
              config: NavConfig = NavConfig(), trials_shape: tuple = (), backend=None,
              filter_config: NavConfig | None = None) -> NavTrack:
    """Receivers and onboard EKFs along given truth trajectories (batch mode).

    t_gps_s (T,) epochs; pos_ecef_m, vel_ecef_m_s (T, ..., 3) the UAVs' truth at them.
    trials_shape prepends independent Monte Carlo trials.  Only the receiver sees the truth.
    config drives the receivers; filter_config (default: the same) the filters, e.g. to
    run a filter whose noise model does not match the world.
    """
    t = np.asarray(t_gps_s, dtype=float)
    pos = np.asarray(pos_ecef_m, dtype=float)
    vel = np.asarray(vel_ecef_m_s, dtype=float)
    if t.ndim != 1 or t.size < 1 or pos.shape[:1] != t.shape or vel.shape != pos.shape:
        raise ValueError(f"t_gps_s (T,), pos_ecef_m and vel_ecef_m_s (T, ..., 3) must agree, got {t.shape}, "
                         f"{pos.shape}, {vel.shape}")
    nav = OnboardNav(constellation, config if filter_config is None else filter_config, backend)
    xs, Ps, nis, ntr = [], [], [], []
    for k in range(t.size):
        est = nav.update(gnss_measure(rng, t[k], pos[k], vel[k], constellation, config, trials_shape))
        xs.append(est.x)
        Ps.append(est.P)
        nis.append(est.nis)
        ntr.append(est.n_tracked)
    return NavTrack(t.copy(), np.stack(xs), np.stack(Ps), np.stack(nis), np.stack(ntr))


# --------------------------------------------------------------------------- read-only views (telemetry)
# What a receiver / an autopilot reports about the estimate (vehicles/process.py -> MAVLink):
# computed from the receivers' and the filters' own state, nothing of the truth.

#: ArduPlane's EK3_VEL_I_GATE / EK3_POS_I_GATE / EK3_HGT_I_GATE default, 500 (centi-sigma): 5 sigma
EKF_INNOVATION_GATE_SIGMA = 5.0


def dops_clock_free(rx_pos_ecef_m, sat_pos_ecef_m, tracked) -> tuple[np.ndarray, np.ndarray]:
    """(HDOP, VDOP) of each receiver (...,) from the satellites it tracks, in the local
    east-north-up frame at the receiver: Q = (G'G)^-1 with G the unit lines of sight of the
    tracked satellites (three unknowns: this receiver has no clock), HDOP = sqrt(Q_ee + Q_nn),
    VDOP = sqrt(Q_uu).  rx (..., 3); sats (S, 3) or (..., S, 3); tracked (..., S).  NaN where
    fewer than three satellites are tracked (no fix)."""
    rx = np.asarray(rx_pos_ecef_m, float)
    tr = np.asarray(tracked, bool)
    los = np.asarray(sat_pos_ecef_m, float) - rx[..., None, :]
    los = los / np.linalg.norm(los, axis=-1, keepdims=True)
    lat, lon, _ = geodesy.ecef_to_geodetic(rx)
    R = geodesy.enu_rotation(lat, lon)  # (..., 3, 3): enu = R d
    g = np.where(tr[..., None], np.einsum("...ij,...sj->...si", R, los), 0.0)
    A = np.einsum("...si,...sj->...ij", g, g)
    ok = tr.sum(axis=-1) >= 3
    A = np.where(ok[..., None, None], A, np.eye(3))
    Q = np.linalg.inv(A)
    hdop = np.sqrt(np.maximum(Q[..., 0, 0] + Q[..., 1, 1], 0.0))
    vdop = np.sqrt(np.maximum(Q[..., 2, 2], 0.0))
    return np.where(ok, hdop, np.nan), np.where(ok, vdop, np.nan)


def ned_rotation(pos_ecef_m) -> np.ndarray:
    """(..., 3, 3) R with ned = R d_ecef at the geodetic position of pos_ecef_m."""
    lat, lon, _ = geodesy.ecef_to_geodetic(np.asarray(pos_ecef_m, float))
    enu = geodesy.enu_rotation(lat, lon)
    return np.stack([enu[..., 1, :], enu[..., 0, :], -enu[..., 2, :]], axis=-2)


def ned_covariances(est: NavEstimate) -> tuple[np.ndarray, np.ndarray]:
    """The estimate's position and velocity covariances in the local north-east-down frame at
    the estimated position: (P_pos (..., 3, 3) m^2, P_vel (..., 3, 3) m^2/s^2), R P R'."""
    R = ned_rotation(est.x[..., 0:3])
    P = 0.5 * (est.P + np.swapaxes(est.P, -1, -2))
    rot = lambda B: R @ B @ np.swapaxes(R, -1, -2)  # noqa: E731
    return rot(P[..., 0:3, 0:3]), rot(P[..., 3:6, 3:6])


class InnovationTestRatios(NamedTuple):
    """ArduPilot's EKF innovation test ratios (NavEKF3 FuseVelPosNED: innovation^2 / (gate^2 x
    innovation variance); < 1 passes the gate) for this filter, whose measurements are
    pseudoranges and range rates, not NED positions: the update's correction of the state,
    dx = x_post - x_pred = K nu, in NED, against its own covariance K S K' = P_pred - P_post, so
    that E[ratio] = 1 / gate^2 as for ArduPilot's.  vel: |dv|^2 / (gate^2 tr(dP_vel));
    pos: (dn^2 + de^2) / (gate^2 (dP_nn + dP_ee)); hgt: dd^2 / (gate^2 dP_dd)."""

    vel: np.ndarray
    pos: np.ndarray
    hgt: np.ndarray


def innovation_test_ratios(prior: NavEstimate, est: NavEstimate, config: NavConfig = NavConfig(),
                           gate_sigma: float = EKF_INNOVATION_GATE_SIGMA) -> InnovationTestRatios:
    """The test ratios (:class:`InnovationTestRatios`) of the update that took ``prior`` to
    ``est`` (one :func:`nav_step`): the prediction is the filter's own (the same linear
    transition F, Q), so x_pred, P_pred are the ones the update started from.  NaN where the
    update corrected nothing (no satellite tracked: dP = 0)."""
    dt = float(est.t_gps_s) - float(prior.t_gps_s)
    tr = _transition(float(config.q_m2_s3))
    F, Q = tr.F(None, dt), tr.Q(dt)
    x_pred = np.einsum("ij,...j->...i", F, prior.x)
    P_pred = F @ prior.P @ F.T + Q
    dx = est.x - x_pred
    dP = P_pred - est.P
    R = ned_rotation(est.x[..., 0:3])
    Rt = np.swapaxes(R, -1, -2)
    dp = np.einsum("...ij,...j->...i", R, dx[..., 0:3])
    dv = np.einsum("...ij,...j->...i", R, dx[..., 3:6])
    dPp = R @ dP[..., 0:3, 0:3] @ Rt
    dPv = R @ dP[..., 3:6, 3:6] @ Rt
    g2 = float(gate_sigma) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        vel = np.sum(dv * dv, axis=-1) / (g2 * np.trace(dPv, axis1=-2, axis2=-1))
        pos = (dp[..., 0] ** 2 + dp[..., 1] ** 2) / (g2 * (dPp[..., 0, 0] + dPp[..., 1, 1]))
        hgt = dp[..., 2] ** 2 / (g2 * dPp[..., 2, 2])
    fix = lambda r: np.where(np.isfinite(r) & (r >= 0), r, np.nan)  # noqa: E731
    return InnovationTestRatios(fix(vel), fix(pos), fix(hgt))
