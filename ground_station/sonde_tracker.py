"""Radiosonde tracker (seed 004): relayed GNSS fused with an aerological radar, EKF or UKF.

The ground complex-processing point (GCPP) receives, per sonde and epoch, a `SondeRelay`
(relayed pseudoranges and pseudo-Dopplers of the delivered satellites) and a
`RadarMeasurement` (slant range, azimuth, elevation; angles invalid while the angular
auto-tracking is lost) from the bus, and publishes an `Estimate` per sonde and epoch on
``<run>/gs/estimate/sonde/<id>``. Three modes run the same code on the same messages:
``fused`` (both sources), ``radar_only`` and ``relay_only``. Truth never reaches it.

State (ECEF, SI), per mode
--------------------------
The seed's vector is X = [x, y, z, Vx, Vy, Vz, ax, ay, az, dd, phi, Dw] (eq 15). Here:

====================  =====================================================  =========
index                 meaning                                                modes
====================  =====================================================  =========
0-2  pos_ecef_m       sonde position P (true ECEF, at the epoch)             all
3-5  vel_ecef_m_s     its velocity V
6-8  acc_ecef_m_s2    the gust acceleration a_g (Gauss-Markov, eq 20); with
                      ``kinematics="singer"`` the acceleration itself
9-11 wind_ecef_m_s    the wind the sonde meets, u: the velocity it relaxes    all
                      to (vertically its target speed: + ascent rate, or      (relaxed)
                      - the parachute's terminal speed)
12-14 wind_shear      du/dh, Gauss-Markov in height (the wind changes at it x climb rate)
dd   delta_d_m        the lumped path offset dd of eq 22 (relay delay         fused,
                      c tau_ret + GCPP clock offset): constant (eq 21), here   relay_only
                      a random walk of PSD ``delta_d_rw_psd_m2_s`` (tiny)
osc  osc_m_s          the relay LO frequency offset Dw of eq 17, carried in    fused,
                      m/s: (c / omega_L1) Dw, the term it adds to every        relay_only
                      pseudo-Doppler; Gauss-Markov with the relay's gamma
                      and stationary std ``osc_sigma_m_s``
err  radar_err        the radar's AR(1) errors [range m, az rad, el rad]       fused,
                      (eqs 12-14, 31-33), only with ``radar_noise="colored"``  radar_only
====================  =====================================================  =========

so n = 20 (fused), 18 (radar_only), 17 (relay_only) with coloured radar noise, and 17 / 15 /
17 with the naive white treatment, plus the relay's per-satellite error states (``bias_slots``);
6 fewer without the wind states (``kinematics="singer"``: the model before issue 19).

* phi, the relay oscillator phase (eq 16), is **dropped**: it is unobservable here. It
  enters no measurement (the relay delivers pseudoranges and pseudo-Dopplers, no carrier
  phase; eq 24's phase observation is not produced) and no other state depends on it
  (phi' = Dw + ..., nothing is driven by phi), so keeping it would change no other
  estimate (its H column and its F row into the other states are zero) while its variance
  grows without bound (~2 sigma_w^2 T / gamma).
* dd is unobservable from the radar, so ``radar_only`` has neither dd nor Dw (Dw enters
  only the pseudo-Dopplers).
* In ``relay_only`` dd is observable together with the position: d pr_i / dP = K_i + K
  with K = (P - G)/|P - G| common to every satellite, so K.dP + d(dd) acts like a
  receiver clock and the position is fixed by the K_i geometry, as in ordinary GNSS.

Dynamics ("the filter may know the model's parameters, not the truth's state")
    ``kinematics="relaxed"`` (default): the sonde model's own structure (vehicles.sonde), per
    ENU axis at the GCPP (R its rotation; k = p1 horizontally, k_v vertically)
        p' = V,  V' = k (u - V) + a_g,  a_g' = -(p1 + p2) a_g + sqrt(2 (p1 + p2)) sigma_a n,
        u' = w s,  s' = -(|w| / L) s + sqrt(2 |w| / L) sigma_s n_s      (w the vertical speed)
    -- the velocity relaxes to the wind it meets, driven by eq 20's gust; the wind u (the mean
    wind at the sonde's height, which the tracker does not know) is a state and changes as the
    sonde crosses the profile, at the shear s = du/dh times its vertical speed, the shear
    Gauss-Markov in height with the std and correlation height of the wind profile
    (sitl.app.experiments.sonde.wind_shear_statistics; in time the old Gauss-Markov rate, tuned on the
    5 m/s ascent, was ~3x too confident in the descent). Per sonde, in the local ENU frame at its
    estimate (SondeTransition.kinematic), exact discretisation (relaxed_axis_discretisation: expm
    and Van Loan) at its vertical speed.
    ``kinematics="singer"``: eq 20 as printed, p' = V, V' = a, a' = -(p1 + p2) a + w, i.e.
    Singer's model (filters.models.Singer) with the stationary acceleration covariance
    Sigma_a = R' diag(s_h^2, s_h^2, s_v^2) R, Q = kron(Q_singer_unit(p1 + p2, T), Sigma_a).
    Why relaxed (issue 19, item 5): Singer's velocity is a random walk, so a coast's position
    variance grows as T^3 -- ~470 m after the 120 s GNSS outage, where the world's sonde
    (whose velocity stays within ~1 m/s of the wind) coasts to ~100-250 m: the fused filter
    then trusted the radar's angles (~280 m an axis at 160 km) more than its own prediction and
    could end worse than relayed GNSS coasting alone (seed 1: 10.1 m against 4.1 m). With the
    relaxed model the coast is consistent (tests/test_sonde_seed_study.py) and seed 1 gives
    5.8 m against 6.8 m. A descending sonde's target vertical speed follows the parachute's law
    -v_d(h) (US76 density) as a known input (``descent_rate_sl_m_s``), and a descending track that
    reaches the ground (flat, at the site's height) lands: at rest from then on (``landing``; without
    it a track beyond the radar's and the relay's range coasted on through the ground at the last
    wind: 407 km off after the default demo's 6 h, now ~35 km, where it came down). dd: random walk. Dw: Gauss-Markov,
F = e^{-gamma T}, Q = s^2 (1 - e^{-2 gamma T}). Radar errors: AR(1) per axis with
mu = e^{-gamma T}, Q = sigma^2 (1 - mu^2) (eqs 12-14).

Measurements
    relay, per delivered satellite i (eqs 22-23; relay.py's sign convention):
        pr_i  = |S_i - P'| + |P' - G| + dd
        prr_i = K_i.(V - W_i) + K.V + osc,     K_i = (P' - S_i)/|P' - S_i|,  K = (P' - G)/|P' - G|
      with P' = `relay_frame_point`(P, V): the point the relay's observables locate, the
      sonde at the downlink emission (P - V tau, tau = |P - G|/c) rotated into the ECEF
      frame of reception by w_e tau (sitl.radio.relay); 0.1-0.4 m from P at 50-250 km,
      which matters against a ~0.6 m relay track (H is taken at P: the map is the identity
      to ~1e-7). R = diag(the message's variances). The number of satellites varies per
      epoch (none during a GNSS outage); the rows of a batch of sondes are padded to a
      common satellite set with zero rows (H = 0, y = 0, r = 1), which leave a Kalman
      update exactly unchanged.
    radar (spherical at the radar site, geodetic horizon, azimuth clockwise from north):
        [D, az, el] = aer(P - site) + err          (coloured: err in the state, R tiny)
                    = aer(P - site) + v,  R = diag(sigma^2)   (naive "white")
      The coloured treatment augments the state with the three AR(1) errors; its R is a
      white part of ``radar_white_fraction`` x sigma^2 (default 1e-3, numerical
      regularisation: a zero R makes P singular after each update). The naive treatment
      takes the errors as white, which over-weights the radar by about (1+mu)/(1-mu)
      (~20 at mu = e^{-0.1}) and makes the filter over-confident (see the experiment's
      NEES comparison). With ``angles_valid`` False only the range row is used (the
      angle rows are zero-padded: a range-only update). Azimuth wrap-around: h returns
      the representative of the predicted azimuth nearest the measured one,
      h_az = z_az - wrap(z_az - az(x)), wrap to [-pi, pi), so the innovation is always
      the short way round (a sonde crossing north gives no 2 pi jump); the same h serves
      the UKF's sigma points.
    The rows are computed by a compiled kernel (numba) when available; the numpy code in
    `SondeMeasurement` is the reference (they agree to rounding, tested).

Per epoch (all messages of one time together): initialise new sondes; then one joint
predict + update with every relay and radar row of the epoch (the fused EKF kernel
filters.kernels.predict_joseph_update; the UKF: predict, then ukf_update), gated: the NIS
y' S^-1 y over the sonde's real rows against the chi-square quantile ``gate_prob``.
A sonde failing it is redone block by block from its prediction -- relay, then radar
(linearised at the relay-updated state) -- each block gated on its own and, if it fails,
retried once under a manoeuvre hypothesis: the covariance of an unknown acceleration step
a ~ N(0, manoeuvre_sigma_acc^2 I) at the start of the step, [dP, dV, da] = [dt^2/2, dt, 1] a,
and (relaxed) an unknown step of the wind u ~ N(0, manoeuvre_sigma_wind^2 I) -- the target speed
jumps at the burst (e.g. the balloon burst: the vertical speed goes from +5 to about -40 m/s in ~10 s); accepted
then, it is counted a manoeuvre, else rejected and counted (``relay_gated`` /
``radar_gated``), never silently dropped. A sliding-window test (the NIS summed over the
last ``manoeuvre_window`` epochs against the chi-square quantile of the summed dof) catches
the slow drift no single epoch's gate sees (the radar alone after the burst) and adds the
same covariance (``window_manoeuvre``). After ``reacquire_after`` rejections of a block in
a row the track is re-initialised from that epoch's fix (``reacquired``).

Initialisation
    * from the first radar fix with valid angles (fused, radar_only): P = aer -> ECEF
      (sitl.radio.radar.radar_aer_to_ecef), cov(P) = J Sigma J' (aer_cov_to_ecef); with
      coloured noise the fix is P = g(z - err - v) (v the small white part), so
      cov(P) = J (Sigma + R_w) J' and cov(P, err) = -J Sigma (R_w keeps the joint covariance
      positive definite, which the UKF's Cholesky needs);
    * from a least-squares fix on the first relay epoch (relay_only, and fused when no radar
      fix with angles has come yet): Gauss-Newton on pr_i = |S_i - P| + |P - G| + dd with
      4 unknowns (P, dd), which needs >= 4 satellites (epochs with fewer are skipped,
      counted ``init_waiting``), started 1 km above G; then the velocity and the oscillator
      term from the pseudo-Dopplers by linear least squares (4 unknowns again); the
      covariances are the least-squares ones (H' W H)^-1.
    Unknown parts get wide priors: V ~ N(0, prior_sigma_vel^2 I), a ~ N(0, Sigma_a), the
    wind u = V + d with d ~ N(0, prior_sigma_wind_offset^2 I) (the sonde leaves the launcher at
    rest into the surface wind), its rate s at its stationary prior,
    dd ~ N(0, prior_sigma_delta_d^2), osc ~ N(0, osc_sigma^2), err ~ N(0, Sigma_radar).

Bus: `SondeTracker.attach(transport)` subscribes to ``<run>/sonde/*/relay`` and
``<run>/radar/*/sonde/*`` (or the given sondes); ``on_message(key, msg)`` only buffers
(duplicates by (source, seq), stale messages older than the sonde's filter time, other
radars and wrong runs are counted and dropped); ``step(t)`` processes every buffered
epoch <= t in time order, predicts every initialised sonde to t and publishes one
`Estimate` per sonde (covariance over [pos, vel], ``nis`` the summed block NIS of this
epoch or NaN, ``mode`` the tracker's label) -- an estimate every epoch, measurements or
not. The driver calls ``step(t)`` once per epoch after delivering that epoch's messages
(batch mode: ``bus.drain(t)`` then ``step(t)``).

Batching: one tracker follows any number of sondes (e.g. Monte Carlo trials) as one
batch: the per-epoch predict and updates run over all sondes with data at that epoch
(filters.kernels), and a sonde's numbers do not depend on the others (to rounding, tested).

Integrity (seed 003, opt-in: ``SondeTrackerParams(integrity=IntegrityConfig(...))``): before the
epoch's updates, filters.integrity.IntegrityMonitor judges every sonde's rows at its predicted
state, one channel per relayed satellite (its pseudorange and pseudo-Doppler; up to
``integrity_sat_channels``, a satellite keeps its channel while seen, a new one takes a channel
unused for window + readmit_after epochs) and one per radar axis (range, az, el). The rows it
leaves out (a jump this epoch; every row of an excluded channel) are masked out of every
update of the epoch (z = 0, r = 1, H = 0: no information and no NIS, so the gate's dof drop
too), the others take the variance it used. The monitor assumes single-channel faults, so it
does not judge a sonde whose rows mostly jump at once (more than ``integrity_common_fraction``:
a manoeuvre such as the burst, or a track error, which the gate and the manoeuvre hypothesis
handle) nor a track within ``integrity_warmup_s`` of its (re)initialisation or of a manoeuvre
(accepted under the manoeuvre hypothesis, or found by the window test); those are counted. Its events
(sitl.integrity_events: step, ramp, outlier, readmit) go on ``<run>/gs/integrity/<channel>``
from ``<source_id>.integrity``, channel ``<sonde>.relay.<sat>`` or ``<sonde>.<radar>.<axis>``.
The monitor's batch is a cohort of sondes that joined together (its window position is common
to the batch); every cohort is stepped at every processed epoch, absent sondes as missing.
Measured (issue 6's report; sitl/app/experiments/sonde.py ``integrity="compare"``: the same messages
through a plain and a monitored tracker): fault-free, fused and relay-only are no worse (the 2 h
flight with the burst, 2 trials: fused 12.579 -> 12.580 m, ANEES 4.91 -> 4.92; 700 s, 6 trials:
9.738 -> 9.737 m); a 60 m clock step on one relayed satellite, a radar azimuth outlier burst or a
1 deg azimuth step is excluded on its own channel within 2 epochs and the fused RMSE during the
fault drops from 12.4 / 84 / 130 m to 5.1 / 1.3 / 1.7 m. With the radar alone (three rows) one
axis is a third of the rows, so the common-mode rule leaves its jumps to the tracker's gate: the
monitor only catches drifts there (no redundancy to isolate an axis). Opt-in (None by default):
it about doubles the tracker's time (10 sondes x 400 s: 2.7 -> 5.7 s, load ~7).

EKF or UKF: the same models; the EKF suits the relay (pseudoranges to satellites 20,000 km
away are linear to millimetres); the UKF copes better with a radar-only track coasting on
range alone close to the radar, where the cross-range uncertainty reaches the range itself
and the EKF's linearisation breaks (NEES ~10^3 there with the EKF, ~5 with the UKF).
``filter="auto"`` picks per sonde and epoch: the UKF while sqrt(trace P_pos) exceeds
``auto_ukf_ratio`` (2 %) of the distance to the radar (or G), the EKF otherwise.

Late messages and duplicates (issue 8). A relay or radar message for an epoch a step has
already covered is used while it is at most ``lag_window_s`` (5 s) older than the last step:
each step keeps a copy of what it writes (the per-sonde arrays, the satellites' error-state
maps, the integrity monitor's bookkeeping) and the epochs it processed; the late message joins
the step that would have processed it, and the next step restores the state from before that
step and re-runs it and the later ones (only the new step's Estimates are published: what went
out at t is what had arrived by t). Counters ``late_accepted``, ``reprocess_runs``,
``reprocessed_epochs``; older ones ``too_late``; ``lag_window_s = 0``: dropped as ``stale`` (the
behaviour before). Duplicates are discarded by (key, source id, seq), per stream. Measured
(``sitl.app.experiments.faults``' sonde runs: fused tracker, 8 trials, 600 s, relay and radar links
down from 360 s): after a 30 s or a 60 s partition the 10 s RMSE is within 2x the fault-free
run's from the heal on (per epoch after 3 s; 9 s with the window ending at the time), nothing
gated, no re-acquisition; delay 1 / 2 s (+-20 % jitter): RMSE 1.84 / 2.19 m against 1.73 m
(the real-time estimate predicts over the delay); 20 % loss: 1.63 m.
"""
from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np
import scipy.linalg
from scipy.stats import chi2

try:  # compiled measurement rows (numba); the numpy path in SondeMeasurement is the reference
    import numba as _nb
except ImportError:  # pragma: no cover
    _nb = None

from filters import kernels
from filters.ekf import ekf_update
from filters.integrity import IntegrityConfig, IntegrityMonitor
from filters.models import Singer
from filters.ukf import SigmaPoints, ukf_update
from ground_station import _lagwindow
from sitl.bus import (
    Estimate,
    RadarMeasurement,
    SequenceTracker,
    SondeRelay,
    is_valid_id,
    key_for,
    key_pattern,
    parse_key,
)
from sitl.atmosphere_std import RHO0_KG_M3, Z_MAX_M, Z_MIN_M, us76_density
from sitl.constants import C_M_S, WGS84
from sitl.geodesy import ecef_to_geodetic, enu_rotation, geodetic_to_ecef
from sitl.integrity_events import IntegrityEventPublisher
from sitl.radio import relay as _relay
from sitl.radio.radar import (
    RadarParams,
    aer_cov_to_ecef,
    aer_to_ecef_jacobian,
    radar_aer_to_ecef,
)
from sitl.radio.relay import RelayErrorBudget, RelayParams

__all__ = [
    "KINEMATICS",
    "MODES",
    "RADAR_NOISE",
    "Layout",
    "RelayFix",
    "SondeMeasurement",
    "SondeTracker",
    "SondeTrackerParams",
    "SondeTransition",
    "TrackerCounters",
    "layout_for",
    "relay_fix",
    "relay_frame_point",
    "wrap_pi",
]

MODES = ("fused", "radar_only", "relay_only")
RADAR_NOISE = ("colored", "white")
KINEMATICS = ("relaxed", "singer")
TWO_PI = 2.0 * math.pi

_RADAR_DEFAULT = RadarParams()
_RELAY_DEFAULT = RelayParams()


def _descent_speed(h_m, v_sl_m_s):
    """The parachute's terminal descent speed at heights h_m, v_sl sqrt(rho0 / rho(h)) with the US76
    density (the sonde model's law, vehicles.sonde.descent_speed_m_s; ground_station does not import
    vehicles)."""
    h = np.clip(np.asarray(h_m, dtype=float), Z_MIN_M, Z_MAX_M)
    return v_sl_m_s * np.sqrt(RHO0_KG_M3 / us76_density(h))


def wrap_pi(a):
    """Angle(s) wrapped to [-pi, pi)."""
    return np.mod(np.asarray(a, dtype=float) + math.pi, TWO_PI) - math.pi


# ---------------------------------------------------------------------------
# parameters and state layout


def _finite(name, value, lo=None, lo_open=False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v) or (lo is not None and (v <= lo if lo_open else v < lo)):
        raise ValueError(f"{name} must be a finite number {'>' if lo_open else '>='} {lo}, got {value!r}")
    return v


@dataclass(frozen=True)
class SondeTrackerParams:
    """The tracker's model of the sonde, the relay and the radar, and its gating (SI units).

    The defaults are the world models' parameters (vehicles.sonde.SondeParams,
    sitl.radio.relay.RelayParams, sitl.radio.radar.RadarParams): the filter knows the
    models, not the truth's state.
    """

    mode: str = "fused"  # one of MODES
    radar_noise: str = "colored"  # "colored": AR(1) errors in the state; "white": naive
    filter: str = "ekf"  # "ekf", "ukf" (same models) or "auto" (per sonde and epoch, see below)
    auto_ukf_ratio: float = 0.02  # auto: the UKF when sqrt(trace P_pos) > this x the distance to the site
    # the sonde's motion: "relaxed" (vehicles.sonde's model: the velocity relaxes with the aerodynamic
    # rate to the wind it meets, driven by the Gauss-Markov gust acceleration of eq 20; the wind and its
    # rate of change are states) or "singer" (eq 20 as printed: the acceleration Gauss-Markov, the
    # velocity its integral -- a random walk, which over a coast grows the position variance as T^3)
    kinematics: str = "relaxed"
    accel_rate_1_s: float = 0.12  # p1 + p2 (seed eq 20): the gust acceleration's (singer: the acceleration's) rate
    sigma_acc_horizontal_m_s2: float = 0.15  # its stationary std (relaxed: the gust a_g; singer: the acceleration)
    sigma_acc_vertical_m_s2: float = 0.10
    velocity_relax_rate_horizontal_1_s: float = 0.1  # relaxed: p1, the velocity relaxes to the wind in 1/p1
    velocity_relax_rate_vertical_1_s: float = 0.2  # relaxed: k_v, the vertical speed to its target
    # relaxed: the wind the sonde meets is the wind profile at its height, so it changes at the shear
    # du/dh times the sonde's vertical speed: the shear is a state, Gauss-Markov in height, with a
    # stationary std per horizontal axis and a correlation height; vertically, the shear of the target
    # vertical speed left once the descent law (descent_rate_sl_m_s) is applied. The defaults are
    # sitl.app.experiments.sonde.wind_shear_statistics of the experiment's sonde (the default jet profile
    # x 1.15 between the launch and the burst height); its target vertical speed is the constant ascent
    # rate, then the descent law itself: no vertical residual
    wind_shear_sigma_horizontal_1_s: float = 2.93e-3
    wind_shear_sigma_vertical_1_s: float = 0.0
    wind_shear_corr_height_m: float = 4430.0
    delta_d_rw_psd_m2_s: float = 1e-6  # dd random walk (eq 21: constant; tiny slack)
    osc_gamma_1_s: float = _RELAY_DEFAULT.osc_gamma_1_s
    osc_sigma_m_s: float = _RELAY_DEFAULT.osc_sigma_hz * _RELAY_DEFAULT.osc_doppler_scale_m_s_per_rad_s * TWO_PI
    radar_sigma: tuple = tuple(float(s) for s in _RADAR_DEFAULT.sigma)  # (m, rad, rad), AR(1) stationary std
    radar_gamma_1_s: tuple = tuple(float(g) for g in _RADAR_DEFAULT.gamma_1_s)  # AR(1) spectrum widths
    radar_white_fraction: float = 1e-3  # coloured model: white part of R, fraction of sigma^2
    gate_prob: float | None = 1.0 - 1e-4  # chi-square gate per block; None: no gating
    manoeuvre_sigma_acc_m_s2: float = 10.0  # unknown acceleration step of the manoeuvre hypothesis
    manoeuvre_sigma_wind_m_s: float = 30.0  # relaxed: and an unknown step of the wind / target speed (the burst)
    # relaxed: the parachute's terminal speed at sea level, v_d(h) = v_sl sqrt(rho0 / rho(h)) (vehicles.sonde,
    # US76): a descending sonde's target vertical speed -v_d(h) follows its height as a known input; None: off
    descent_rate_sl_m_s: float | None = 5.0
    # relaxed: the sonde lands on flat ground at the site's height (the radar's, else the ground receiver's)
    # and stays there (vehicles.sonde's LANDED phase): a descending track whose height reaches it is
    # landed -- at rest from then on, until a re-initialisation. False: the track coasts on
    landing: bool = True
    # a track with no accepted measurement (a relay or radar block that passed the gate, or a fix that
    # (re)initialised it) for longer than this is lost: its Estimate is no longer published (counted
    # ``lost``) and the next measurement initialises it again, as at its acquisition. None: never lost
    max_coast_s: float | None = 300.0
    manoeuvre_window: int | None = 10  # epochs of the sliding-window NIS test (None: off)
    reacquire_after: int | None = 5  # re-initialise after this many rejected blocks in a row
    prior_sigma_vel_m_s: float = 20.0
    prior_sigma_wind_offset_m_s: float = 10.0  # relaxed: the wind's offset from the velocity at initialisation
    prior_sigma_delta_d_m: float = 3000.0
    relay_errors: RelayErrorBudget | None = _RELAY_DEFAULT.errors  # the relay's error budget; None: white only
    bias_slots: int = 24  # per-satellite error states (relay modes with relay_errors); >= satellites in view
    bias_tau_s: float | None = None  # their correlation time; None: relay_errors' variance-weighted one
    label: str | None = None  # Estimate.mode; default: mode (+ "_white" for naive radar noise)
    backend: str | None = None  # filters.kernels backend (None: default)
    integrity: IntegrityConfig | None = None  # the integrity monitor (filters.integrity) around the updates; None: off
    integrity_sat_channels: int = 48  # relayed-satellite channels of the monitor (>= satellites seen in its memory)
    integrity_warmup_s: float = 10.0  # a track is not judged this long after its (re)initialisation or a manoeuvre
    integrity_common_fraction: float = 0.25  # jumps on more than this fraction of a sonde's rows: a manoeuvre
    lag_window_s: float = 5.0  # out-of-sequence messages this old are used by re-processing (0: dropped as stale)

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        if self.kinematics not in KINEMATICS:
            raise ValueError(f"kinematics must be one of {KINEMATICS}, got {self.kinematics!r}")
        if self.radar_noise not in RADAR_NOISE:
            raise ValueError(f"radar_noise must be one of {RADAR_NOISE}, got {self.radar_noise!r}")
        if self.filter not in ("ekf", "ukf", "auto"):
            raise ValueError(f"filter must be 'ekf', 'ukf' or 'auto', got {self.filter!r}")
        _finite("auto_ukf_ratio", self.auto_ukf_ratio, 0.0, lo_open=True)
        for name in ("accel_rate_1_s", "osc_gamma_1_s", "osc_sigma_m_s", "prior_sigma_vel_m_s",
                     "prior_sigma_delta_d_m", "velocity_relax_rate_horizontal_1_s", "velocity_relax_rate_vertical_1_s",
                     "wind_shear_corr_height_m"):
            _finite(name, getattr(self, name), 0.0, lo_open=True)
        if self.descent_rate_sl_m_s is not None:
            _finite("descent_rate_sl_m_s", self.descent_rate_sl_m_s, 0.0, lo_open=True)
        if self.max_coast_s is not None:
            if isinstance(self.max_coast_s, bool):
                raise ValueError(f"max_coast_s must be a finite number > 0 or None, got {self.max_coast_s!r}")
            _finite("max_coast_s", self.max_coast_s, 0.0, lo_open=True)
        for name in ("sigma_acc_horizontal_m_s2", "sigma_acc_vertical_m_s2", "delta_d_rw_psd_m2_s",
                     "manoeuvre_sigma_acc_m_s2", "manoeuvre_sigma_wind_m_s", "wind_shear_sigma_horizontal_1_s",
                     "wind_shear_sigma_vertical_1_s", "prior_sigma_wind_offset_m_s"):
            _finite(name, getattr(self, name), 0.0)
        _finite("radar_white_fraction", self.radar_white_fraction, 0.0, lo_open=True)
        for name in ("radar_sigma", "radar_gamma_1_s"):
            v = getattr(self, name)
            try:
                t = tuple(float(a) for a in v)
            except (TypeError, ValueError):
                raise ValueError(f"{name} must be 3 numbers (range, az, el), got {v!r}") from None
            if len(t) != 3 or not all(math.isfinite(a) and a > 0 for a in t):
                raise ValueError(f"{name} must be 3 finite numbers > 0 (range, az, el), got {v!r}")
            object.__setattr__(self, name, t)
        if self.gate_prob is not None:
            g = _finite("gate_prob", self.gate_prob, 0.0, lo_open=True)
            if not g < 1.0:
                raise ValueError(f"gate_prob must lie in (0, 1) or be None, got {self.gate_prob!r}")
        for name in ("reacquire_after", "manoeuvre_window"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
                raise ValueError(f"{name} must be an integer >= 1 or None, got {v!r}")
        if self.label is not None and not is_valid_id(self.label):
            raise ValueError(f"label must be 1..64 chars of [A-Za-z0-9_.-], got {self.label!r}")
        if self.relay_errors is not None and not isinstance(self.relay_errors, RelayErrorBudget):
            raise ValueError(f"relay_errors must be a RelayErrorBudget or None, got {self.relay_errors!r}")
        if isinstance(self.bias_slots, bool) or not isinstance(self.bias_slots, int) or self.bias_slots < 1:
            raise ValueError(f"bias_slots must be an integer >= 1, got {self.bias_slots!r}")
        if self.bias_tau_s is not None:
            _finite("bias_tau_s", self.bias_tau_s, 0.0, lo_open=True)
        if self.backend not in (None, "auto", "numpy", "numba"):
            raise ValueError(f"backend must be None, 'auto', 'numpy' or 'numba', got {self.backend!r}")
        if self.integrity is not None and not isinstance(self.integrity, IntegrityConfig):
            raise ValueError(f"integrity must be a filters.integrity.IntegrityConfig or None, got {self.integrity!r}")
        v = self.integrity_sat_channels
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"integrity_sat_channels must be an integer >= 1, got {v!r}")
        _finite("integrity_warmup_s", self.integrity_warmup_s, 0.0)
        _finite("lag_window_s", self.lag_window_s, 0.0)
        f = _finite("integrity_common_fraction", self.integrity_common_fraction, 0.0, lo_open=True)
        if f > 1.0:
            raise ValueError(f"integrity_common_fraction must lie in (0, 1], got {self.integrity_common_fraction!r}")

    @property
    def relay_bias_states(self) -> int:
        """Per-satellite error states in the layout (0 without an error budget or relay)."""
        return self.bias_slots if (self.relay_errors is not None and self.mode != "radar_only") else 0

    @property
    def slow_tau_s(self) -> float:
        """The per-satellite error states' correlation time: ``bias_tau_s``, else the
        relay_errors' components' times weighted by their variances for a GPS satellite at
        30 deg seen from the ground (the ionosphere dominates)."""
        if self.bias_tau_s is not None:
            return float(self.bias_tau_s)
        e = self.relay_errors or RelayErrorBudget()
        v = e.slow_sigmas_m(False, math.radians(30.0), 0.0) ** 2
        return float(np.sum(v * e.slow_tau_s) / np.sum(v))

    @property
    def mode_label(self) -> str:
        if self.label is not None:
            return self.label
        white = self.radar_noise == "white" and self.mode != "relay_only"
        return self.mode + ("_white" if white else "")


class Layout(NamedTuple):
    """Where each part of the state lives for a mode (None: absent)."""

    n: int
    dd: int | None
    osc: int | None
    err: int | None  # first of the three radar error states
    uses_relay: bool
    uses_radar: bool
    bias: int | None = None  # first of the per-satellite relay error states
    nb: int = 0  # how many
    wind: int | None = None  # relaxed kinematics: first of the 3 wind states (their rates follow at wind + 3)
    n_kin: int = 9  # kinematic states (position, velocity, acceleration [, wind, wind shear])


def layout_for(mode: str, radar_noise: str = "colored", bias_slots: int = 0, kinematics: str = "relaxed") -> Layout:
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if kinematics not in KINEMATICS:
        raise ValueError(f"kinematics must be one of {KINEMATICS}, got {kinematics!r}")
    relay = mode != "radar_only"
    radar = mode != "relay_only"
    wind = 9 if kinematics == "relaxed" else None
    n = n_kin = 15 if kinematics == "relaxed" else 9
    dd = osc = err = None
    if relay:
        dd, osc, n = n, n + 1, n + 2
    if radar and radar_noise == "colored":
        err, n = n, n + 3
    bias, nb = None, 0
    if relay and bias_slots:
        bias, nb, n = n, int(bias_slots), n + int(bias_slots)
    return Layout(n, dd, osc, err, relay, radar, bias, nb, wind, n_kin)


# ---------------------------------------------------------------------------
# transition


def relaxed_axis_discretisation(relax_rate_1_s: float, gust_rate_1_s: float, sigma_gust_m_s2: float,
                                sigma_shear_1_s: float, shear_corr_height_m: float, vertical_speed_m_s: float,
                                dt_s: float):
    """Exact discretisation (F, Q), 5 x 5, of one local axis of the relaxed sonde model over
    [position p, velocity v, gust acceleration g, wind u, wind shear s = du/dh], for a sonde whose
    height changes at the vertical speed w over the step:

        p' = v,  v' = k (u - v) + g,  g' = -beta g + sqrt(2 beta) sigma_g n_g,
        u' = w s,  s' = -(|w| / L) s + sqrt(2 |w| / L) sigma_s n_s

    (vehicles.sonde's axis, dv/dt = k (w(h) - v) + a_g, with the wind met by the sonde -- the mean
    wind at its height, or the target vertical speed -- unknown: a state that changes as the sonde
    crosses the profile, du/dt = (du/dh) dh/dt, the shear du/dh Gauss-Markov in height with std
    sigma_s and correlation height L). At w = 0 the wind does not change. F = expm(A dt), Q by Van
    Loan's method."""
    k, beta = float(relax_rate_1_s), float(gust_rate_1_s)
    w = float(vertical_speed_m_s)
    lam = abs(w) / float(shear_corr_height_m)
    a = np.zeros((5, 5))
    a[0, 1] = 1.0
    a[1, 1], a[1, 2], a[1, 3] = -k, 1.0, k
    a[2, 2] = -beta
    a[3, 4] = w
    a[4, 4] = -lam
    qc = np.diag([0.0, 0.0, 2.0 * beta * sigma_gust_m_s2**2, 0.0, 2.0 * lam * sigma_shear_1_s**2])
    m = np.zeros((10, 10))
    m[:5, :5], m[:5, 5:], m[5:, 5:] = -a, qc, a.T
    e = scipy.linalg.expm(m * dt_s)
    F = e[5:, 5:].T
    Q = F @ e[:5, 5:]
    return F, 0.5 * (Q + Q.T)


#: the vertical speed is rounded to this relative step (and to 0 below 1 cm/s) for the memo of the
#: per-axis discretisation (relaxed): its noise and decay scale with |w|, so a 0.5 % step is a 0.5 %
#: change of the shear's variance per step at most
VERTICAL_SPEED_REL_STEP = 0.005
#: the vertical shear's std is at least this (keeps P positive definite for the UKF's Cholesky when the
#: model has no vertical residual: over a 30 km descent it moves the target vertical speed by ~0.02 m/s)
SHEAR_SIGMA_FLOOR_1_S = 1e-6
_E2 = WGS84.f * (2.0 - WGS84.f)
_NORMAL_SCALE = np.array([1.0, 1.0, 1.0 / (1.0 - _E2)])  # grad of x^2 + y^2 + z^2 / (1 - e^2): the ellipsoid's normal


def _quantised_speed(w):
    """w (N,) rounded on the relative grid VERTICAL_SPEED_REL_STEP (0 below 1 cm/s)."""
    a = np.abs(w)
    k = np.round(np.log(np.maximum(a, 0.01) / 0.01) / VERTICAL_SPEED_REL_STEP)
    return np.where(a < 0.01, 0.0, np.sign(w) * 0.01 * np.exp(k * VERTICAL_SPEED_REL_STEP))


def _enu_rotations(lat, lon):
    """enu_rotation for (N,) latitudes and longitudes, (N, 3, 3), without the general broadcasting."""
    sp, cp, sl, cl = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    r = np.empty((lat.shape[0], 3, 3))
    r[:, 0, 0], r[:, 0, 1], r[:, 0, 2] = -sl, cl, 0.0
    r[:, 1, 0], r[:, 1, 1], r[:, 1, 2] = -sp * cl, -sp * sl, cp
    r[:, 2, 0], r[:, 2, 1], r[:, 2, 2] = cp * cl, cp * sl, sp
    return r


def _step_geodetic(lat, lon, h, d_enu):
    """(lat, lon, h) after a small local displacement d_enu (N, 3) from (lat, lon, h) (N,): the
    meridian and prime-vertical radii of curvature (a 50 m step: ~1e-10 rad, 0.2 mm off the exact
    transform)."""
    s2 = np.sin(lat) ** 2
    w = np.sqrt(1.0 - _E2 * s2)
    Nr = WGS84.a_m / w
    Mr = WGS84.a_m * (1.0 - _E2) / (w * w * w)
    return (lat + d_enu[:, 1] / (Mr + h), lon + d_enu[:, 0] / ((Nr + h) * np.cos(lat)), h + d_enu[:, 2])


def _descent_speed_slope(h_m, v_sl_m_s):
    """d v_d / dh (1/s, > 0: the descent slows as the air thickens) of _descent_speed, central
    difference over +-1 m."""
    h = np.asarray(h_m, dtype=float)
    return 0.5 * (_descent_speed(h + 1.0, v_sl_m_s) - _descent_speed(h - 1.0, v_sl_m_s))


def _curvature_drop_cov(pos_ecef_m, pos_cov) -> np.ndarray:
    """The ground curves away under a wide horizontal spread: a sonde d away horizontally at the
    estimate's height lies |d|^2 / 2R below the estimate's tangent plane, which a Gaussian in ECEF
    cannot follow. This is the vertical second moment of that drop over the horizontal part of
    pos_cov (E |d|^4 / 4R^2 = (tr C^2 + 2 tr C C) / 4R^2, C the covariance in the tangent plane):
    ~90 m at a 20 km sigma per axis, 1e-10 m at a kilometre -- the published covariance gets it
    (not the filter's state, whose updates are linear anyway), as does a landed track's."""
    p = np.asarray(pos_ecef_m, dtype=float)
    n = p * _NORMAL_SCALE  # the vertical: the normal of the ellipsoid through p (~1e-6 rad off the geodetic
    n /= math.sqrt(float(n @ n))  # one at 10 km: nothing for this term, and no ecef_to_geodetic per Estimate)
    T = np.eye(3) - np.outer(n, n)
    C = T @ pos_cov @ T
    return ((np.trace(C) ** 2 + 2.0 * np.trace(C @ C)) / (4.0 * float(p @ p))) * np.outer(n, n)


class SondeTransition:
    """x(k+1) = F x(k) + w: the sonde kinematics, dd random walk, oscillator and radar errors
    first-order Gauss-Markov.

    ``relaxed``: per sonde and step, in the local east-north-up frame at the sonde's estimated
    position (vehicles.sonde's frame: the wind is horizontal there, the descent is along its
    vertical), relaxed_axis_discretisation with p1 horizontally and k_v vertically at the
    estimate's vertical speed; the velocity-like states (velocity, gust, wind, shear) keep their
    local components from one step's frame to the next (the frame turns by ~|v| dt / R_E as the
    sonde moves); a descending sonde's target vertical speed follows the descent law as an input,
    with its Jacobian. Beyond a few km from the site this matters: at 300 km the site's vertical is
    2.7 deg off the sonde's (a 30 km descent along the site's vertical lands 1.4 km off, and a
    65 m/s wind "horizontal" at the site climbs 3 m/s at the sonde). ``kinematic`` gives these
    per-sonde blocks; the other states' transition is shared and diagonal (``rest``).
    ``singer``: Singer's model with rate p1 + p2 and covariance Sigma_a at the site, shared (F, Q).
    ``enu_rot``: the ENU rotation at the site (singer's split)."""

    linear = True

    def __init__(self, layout: Layout, params: SondeTrackerParams, enu_rot: np.ndarray):
        self.layout = layout
        self.ndim = layout.n
        self.params = params
        p = params
        self.enu_rot = np.array(enu_rot, dtype=float)
        self.acc_cov_ecef = self.acc_cov_at(None)
        self._unit = Singer(params.accel_rate_1_s, 1.0, ndim_pos=1)
        self._memo: dict = {}
        self._axis_memo: dict = {}
        self._shear_sigma_v = max(p.wind_shear_sigma_vertical_1_s, SHEAR_SIGMA_FLOOR_1_S)

    def _local(self, pos_ecef):
        """The ENU rotation at pos (3,) (None: the site's)."""
        if pos_ecef is None:
            return self.enu_rot
        lat, lon, _ = ecef_to_geodetic(np.asarray(pos_ecef, dtype=float))
        return enu_rotation(float(lat), float(lon))

    def acc_cov_at(self, pos_ecef) -> np.ndarray:
        """Stationary covariance of the gust (relaxed) / acceleration (singer) in ECEF, split at pos
        (relaxed; None or singer: at the site)."""
        p = self.params
        r = self.enu_rot if self.layout.wind is None else self._local(pos_ecef)
        return r.T @ np.diag([p.sigma_acc_horizontal_m_s2**2, p.sigma_acc_horizontal_m_s2**2,
                              p.sigma_acc_vertical_m_s2**2]) @ r

    def shear_cov_at(self, pos_ecef) -> np.ndarray:
        """Stationary covariance of the wind-shear states (relaxed) in ECEF, split at pos."""
        p, r = self.params, self._local(pos_ecef)
        return r.T @ np.diag([p.wind_shear_sigma_horizontal_1_s**2, p.wind_shear_sigma_horizontal_1_s**2,
                              self._shear_sigma_v**2]) @ r

    def _axes_to_ecef(self, per_axis):
        """(3, q, q) per-ENU-axis blocks [e, n, u] over q quantities -> (3q, 3q) in ECEF,
        quantity-major (index 3 i + c: quantity i, ECEF axis c)."""
        r = self.enu_rot
        q = per_axis.shape[-1]
        return np.einsum("ca,cij,cb->iajb", r, per_axis, r).reshape(3 * q, 3 * q)

    def _build(self, dt: float):
        """The shared (F, Q): singer's kinematics and every other state; relaxed: the kinematic
        block is left zero (it is per sonde: ``kinematic``)."""
        L, p = self.layout, self.params
        n = L.n
        F, Q = np.zeros((n, n)), np.zeros((n, n))
        if L.wind is None:
            F[:9, :9] = np.kron(self._unit.F(None, dt), np.eye(3))
            Q[:9, :9] = np.kron(self._unit.Q(dt), self.acc_cov_ecef)
        if L.dd is not None:
            F[L.dd, L.dd] = 1.0
            Q[L.dd, L.dd] = p.delta_d_rw_psd_m2_s * dt
            if p.relay_errors is not None:  # the relay path variation (GM) as a random walk of its PSD 2 s^2 / tau
                e = p.relay_errors
                Q[L.dd, L.dd] += 2.0 * e.path_sigma_m**2 / e.path_tau_s * dt
            e = math.exp(-p.osc_gamma_1_s * dt)
            F[L.osc, L.osc] = e
            Q[L.osc, L.osc] = p.osc_sigma_m_s**2 * -math.expm1(-2.0 * p.osc_gamma_1_s * dt)
        if L.err is not None:
            for j, (s, g) in enumerate(zip(p.radar_sigma, p.radar_gamma_1_s)):
                F[L.err + j, L.err + j] = math.exp(-g * dt)
                Q[L.err + j, L.err + j] = s * s * -math.expm1(-2.0 * g * dt)
        if L.nb:  # unit-variance Gauss-Markov per satellite slot
            tau = p.slow_tau_s
            b = np.arange(L.bias, L.bias + L.nb)
            F[b, b] = math.exp(-dt / tau)
            Q[b, b] = -math.expm1(-2.0 * dt / tau)
        Q = 0.5 * (Q + Q.T)
        F.flags.writeable = Q.flags.writeable = False
        return F, Q

    def _get(self, dt):
        key = float(dt)
        out = self._memo.get(key)
        if out is None:
            if len(self._memo) > 64:
                self._memo.clear()
            out = self._memo[key] = self._build(key)
        return out

    def rest(self, dt):
        """(f, q): the diagonal transition and noise of the states after the kinematic block (relaxed)."""
        key = ("rest", float(dt))
        out = self._memo.get(key)
        if out is None:
            F, Q = self._get(dt)
            k = self.layout.n_kin
            out = self._memo[key] = (np.diag(F)[k:].copy(), np.diag(Q)[k:].copy())
        return out

    def _axes(self, dt: float, w: float):
        """Per-axis (F, Q) 5 x 5, horizontal and vertical, at vertical speed w (memoised)."""
        key = (dt, w)
        out = self._axis_memo.get(key)
        if out is None:
            p = self.params
            if len(self._axis_memo) > 8192:
                self._axis_memo.clear()
            h = relaxed_axis_discretisation(p.velocity_relax_rate_horizontal_1_s, p.accel_rate_1_s,
                                            p.sigma_acc_horizontal_m_s2, p.wind_shear_sigma_horizontal_1_s,
                                            p.wind_shear_corr_height_m, w, dt)
            v = relaxed_axis_discretisation(p.velocity_relax_rate_vertical_1_s, p.accel_rate_1_s,
                                            p.sigma_acc_vertical_m_s2, self._shear_sigma_v,
                                            p.wind_shear_corr_height_m, w, dt)
            out = self._axis_memo[key] = (h[0], h[1], v[0], v[1])
        return out

    def kinematic(self, xk, dt: float):
        """Relaxed kinematics of N sondes over dt: xk (N, 15) = [p, v, a_g, u, s] (ECEF) ->
        (the predicted means (N, 15), F (N, 15, 15), Q (N, 15, 15)).

        In the local ENU frame R0 at each estimate: the per-axis models at its vertical speed w
        (rounded on the grid of VERTICAL_SPEED_REL_STEP); the position goes back to ECEF through R0, the
        velocity-like quantities through the frame R1 at the predicted position (they keep their
        local components), and so do the errors, the position's included (F's position block is the
        frame's turn R1' R0, not I). A descending sonde's (target vertical speed below 0) target follows the
        parachute's law, + v_d(h0) - v_d(h1) along the vertical, with its Jacobian in F (the target
        changes by -v_d'(h) per metre of descent); and F has the Jacobian of the bilinear u' = w s
        in the vertical speed (ds/dw: s dt). The mean uses the law itself (not its linearisation)."""
        p = self.params
        xk = np.asarray(xk, dtype=float)
        N = xk.shape[0]
        X = xk.reshape(N, 5, 3)
        lat0, lon0, h0 = (np.atleast_1d(v) for v in ecef_to_geodetic(X[:, 0]))
        R0 = _enu_rotations(lat0, lon0)
        Y = np.einsum("nca,nia->nci", R0, X)  # (N, axis, quantity): local components
        w = Y[:, 2, 1]
        wq = _quantised_speed(w)
        Phi = np.empty((N, 3, 5, 5))
        Qa = np.empty((N, 3, 5, 5))
        for val in np.unique(wq):
            sel = wq == val
            Fh, Qh, Fv, Qv = self._axes(float(dt), float(val))
            Phi[sel, 0], Phi[sel, 1], Phi[sel, 2] = Fh, Fh, Fv
            Qa[sel, 0], Qa[sel, 1], Qa[sel, 2] = Qh, Qh, Qv
        Y1 = np.einsum("ncij,ncj->nci", Phi, Y)
        p1 = np.einsum("nca,nc->na", R0, Y1[:, :, 0])
        lat1, lon1, h1 = _step_geodetic(lat0, lon0, h0, Y1[:, :, 0] - Y[:, :, 0])
        R1 = _enu_rotations(lat1, lon1)
        # the local matrix, quantity-major (N, quantity, axis, quantity, axis)
        M = np.zeros((N, 5, 3, 5, 3))
        for c in range(3):
            M[:, :, c, :, c] = Phi[:, c]
        lam_dt = np.abs(wq) * (float(dt) / p.wind_shear_corr_height_m)
        M[:, 3, :, 1, 2] += Y[:, :, 4] * (float(dt) * np.exp(-lam_dt))[:, None]  # d(w s (1 - e^-lam dt)/lam)/dw
        v_sl = p.descent_rate_sl_m_s
        if v_sl is not None:
            down = np.flatnonzero(Y[:, 2, 3] < 0.0)
            if down.size:
                hd0, hd1 = h0[down], h1[down]
                Y1[down, 2, 3] += _descent_speed(hd0, v_sl) - _descent_speed(hd1, v_sl)
                # d(target)/d(state) = -v_d'(h1) d(h1 - h0)/d(state), h1 - h0 the local vertical displacement
                dh = Phi[down, 2, 0, :].copy()
                dh[:, 0] -= 1.0
                M[down, 3, 2, :, 2] += -_descent_speed_slope(hd1, v_sl)[:, None] * dh
        x1 = np.empty((N, 5, 3))
        x1[:, 0] = p1
        x1[:, 1:] = np.einsum("nca,nci->nia", R1, Y1[:, :, 1:])
        x1 = x1.reshape(N, 15)
        # the errors turn with the frame, the position's too: the sonde and its estimate both move on the
        # curved Earth (a rotation about its centre, R1' R0 over the step), so a horizontal position error
        # stays horizontal at the estimate (kept fixed in ECEF it would tilt up by the distance / R_E)
        R1T = np.swapaxes(R1, -1, -2)[:, None, None]
        F = (R1T @ M.transpose(0, 1, 3, 2, 4) @ R0[:, None, None]).transpose(0, 1, 3, 2, 4).reshape(N, 15, 15)
        Qf = np.zeros((N, 5, 3, 5, 3))
        for c in range(3):
            Qf[:, :, c, :, c] = Qa[:, c]
        Q = (R1T @ Qf.transpose(0, 1, 3, 2, 4) @ R1[:, None, None]).transpose(0, 1, 3, 2, 4).reshape(N, 15, 15)
        return x1, F, 0.5 * (Q + np.swapaxes(Q, -1, -2))

    def F(self, x, dt, landed: bool = False):
        """The transition matrix: shared (n, n) for singer or a landed sonde; relaxed in flight,
        per sonde at the states x (N, n) or (n,): (N, n, n) or (n, n)."""
        if landed:
            return self._get_landed(dt)[0]
        if self.layout.wind is None:
            return self._get(dt)[0]
        return self._full(x, dt)[1]

    def _full(self, x, dt):
        """Relaxed, in flight: (means, F, Q) over the whole state for x (N, n) or (n,)."""
        x = np.asarray(x, dtype=float)
        one = x.ndim == 1
        xx = x[None] if one else x
        k = self.layout.n_kin
        xk, Fk, Qk = self.kinematic(xx[:, :k], dt)
        f, q = self.rest(dt)
        N, n = xx.shape
        F = np.zeros((N, n, n))
        Q = np.zeros((N, n, n))
        F[:, :k, :k], Q[:, :k, :k] = Fk, Qk
        r = np.arange(k, n)
        F[:, r, r], Q[:, r, r] = f, q
        xp = np.concatenate([xk, xx[:, k:] * f], axis=1)
        return (xp[0], F[0], Q[0]) if one else (xp, F, Q)

    def _get_landed(self, dt):
        """(F, Q) of a landed sonde (relaxed): at rest -- position held, velocity, gust, wind and
        shear zero (their Q a numerical floor, 1e-8 in SI, keeping P positive definite); the
        other states as in flight."""
        key = ("landed", float(dt))
        out = self._memo.get(key)
        if out is None:
            F, Q = (a.copy() for a in self._get(dt))
            k = self.layout.n_kin
            F[:k, :] = 0.0
            F[:, :k] = 0.0
            F[0:3, 0:3] = np.eye(3)
            Q[:k, :] = 0.0
            Q[:, :k] = 0.0
            Q[3:k, 3:k] = 1e-8 * np.eye(k - 3)
            F.flags.writeable = Q.flags.writeable = False
            out = self._memo[key] = (F, Q)
        return out

    def boost(self, dt):
        """Covariance added under the manoeuvre hypothesis over a step dt: an unknown
        acceleration step a ~ N(0, s^2 I) at its start, [dp, dV, da] = [dt^2/2, dt, 1] a, and
        (relaxed kinematics) an unknown step of the wind, N(0, manoeuvre_sigma_wind^2 I)."""
        key = ("boost", float(dt))
        out = self._memo.get(key)
        if out is None:
            g = np.array([0.5 * dt * dt, dt, 1.0])
            out = np.zeros((self.ndim, self.ndim))
            out[:9, :9] = self.params.manoeuvre_sigma_acc_m_s2**2 * np.kron(np.outer(g, g), np.eye(3))
            w = self.layout.wind
            if w is not None:  # and an unknown step of the wind / target speed (the burst: +5 -> -40 m/s)
                out[w:w + 3, w:w + 3] = self.params.manoeuvre_sigma_wind_m_s**2 * np.eye(3)
            out.flags.writeable = False
            self._memo[key] = out
        return out

    def Q(self, dt, landed: bool = False, x=None):
        """The process noise: shared for singer or a landed sonde; relaxed in flight, per sonde at x."""
        if landed:
            return self._get_landed(dt)[1]
        if self.layout.wind is None:
            return self._get(dt)[1]
        if x is None:
            raise ValueError("relaxed kinematics: Q depends on the state (its vertical speed and frame); pass x")
        return self._full(x, dt)[2]

    def predict(self, x, P, dt, landed: bool = False, backend=None):
        """(x-, P-) of N sondes (x (N, n), P (N, n, n)) over dt. Relaxed in flight: the per-sonde
        kinematic block and the shared diagonal rest, block by block (the rest's F is diagonal and
        the kinematic block is not coupled to it)."""
        x = np.asarray(x, dtype=float)
        if landed or self.layout.wind is None:
            F, Q = self.F(None, dt, landed), self.Q(dt, landed)
            return x @ F.T, kernels.cov_predict(F, P, Q, backend=backend)
        k = self.layout.n_kin
        xk, Fk, Qk = self.kinematic(x[:, :k], dt)
        f, q = self.rest(dt)
        Pp = np.empty_like(P)
        FkT = np.swapaxes(Fk, -1, -2)
        Pp[:, :k, :k] = Fk @ P[:, :k, :k] @ FkT + Qk
        kr = (Fk @ P[:, :k, k:]) * f
        Pp[:, :k, k:] = kr
        Pp[:, k:, :k] = np.swapaxes(kr, -1, -2)
        Pp[:, k:, k:] = P[:, k:, k:] * (f[:, None] * f[None, :]) + np.diag(q)
        Pp = 0.5 * (Pp + np.swapaxes(Pp, -1, -2))
        return np.concatenate([xk, x[:, k:] * f], axis=1), Pp

    def f(self, x, dt):
        x = np.asarray(x, dtype=float)
        if self.layout.wind is None:
            return x @ self._get(dt)[0].T
        return self._full(x, dt)[0]


# ---------------------------------------------------------------------------
# the measurement model: relay rows then radar rows, batched over sondes


OMEGA_E = float(WGS84.omega_rad_s)


def relay_frame_point(pos_ecef_m, vel_ecef_m_s, ground_pos_ecef_m):
    """The point the relay's measurements locate: the sonde at the downlink emission,
    P - V tau, rotated into the ECEF frame of reception at G (the Earth turns by w_e tau
    meanwhile), tau = |P - G| / c (sitl.radio.relay). It lies 0.1-0.4 m from P between 50
    and 250 km, not negligible against a relay fix of ~0.6 m. (..., 3) arrays."""
    P, V = np.asarray(pos_ecef_m, float), np.asarray(vel_ecef_m_s, float)
    tau = np.linalg.norm(P - ground_pos_ecef_m, axis=-1, keepdims=True) / C_M_S
    o = P - V * tau
    th = OMEGA_E * tau[..., 0]
    ct, st = np.cos(th), np.sin(th)
    return np.stack([ct * o[..., 0] + st * o[..., 1], ct * o[..., 1] - st * o[..., 0], o[..., 2]], axis=-1)


def _rows_py(x, sat_pos, sat_vel, ground, relay_mask, site, rot, z_az, radar_mask, dd, osc, err, bias_col, bias_scale,
            h, H):
    """h (N, m) and H (N, m, n) at states x (N, n), row by row (the compiled path; H must come
    in zeroed). Rows: U pseudoranges, U pseudo-Dopplers (if U > 0), then [range, az, el]
    (if h has 2U + 3 columns). dd, osc, err: state indices, -1 when absent; bias_col (N, U)
    the state index of each satellite's error state (-1: none), bias_scale (N, U) its std."""
    N = x.shape[0]
    U = sat_pos.shape[1]
    radar = h.shape[1] == 2 * U + 3
    for b in range(N):
        px, py, pz = x[b, 0], x[b, 1], x[b, 2]
        vx, vy, vz = x[b, 3], x[b, 4], x[b, 5]
        if U > 0:
            # the relay measures the downlink-emission point in the ECEF frame of reception
            tau = math.sqrt((px - ground[0]) ** 2 + (py - ground[1]) ** 2 + (pz - ground[2]) ** 2) / C_M_S
            ox, oy, oz = px - vx * tau, py - vy * tau, pz - vz * tau
            th = OMEGA_E * tau
            ct, st = math.cos(th), math.sin(th)
            px, py, pz = ct * ox + st * oy, ct * oy - st * ox, oz
            gx, gy, gz = px - ground[0], py - ground[1], pz - ground[2]
            rg = max(math.sqrt(gx * gx + gy * gy + gz * gz), 1e-3)
            kx, ky, kz = gx / rg, gy / rg, gz / rg
            kv = kx * vx + ky * vy + kz * vz
            for u in range(U):
                if not relay_mask[b, u]:
                    h[b, u] = 0.0
                    h[b, U + u] = 0.0
                    continue
                dx, dy, dz = px - sat_pos[b, u, 0], py - sat_pos[b, u, 1], pz - sat_pos[b, u, 2]
                rho = math.sqrt(dx * dx + dy * dy + dz * dz)
                ix, iy, iz = dx / rho, dy / rho, dz / rho
                wx, wy, wz = vx - sat_vel[b, u, 0], vy - sat_vel[b, u, 1], vz - sat_vel[b, u, 2]
                uw = ix * wx + iy * wy + iz * wz
                bh = 0.0
                j = bias_col[b, u]
                if j >= 0:
                    bh = bias_scale[b, u] * x[b, j]
                    H[b, u, j] = bias_scale[b, u]
                h[b, u] = rho + rg + x[b, dd] + bh
                h[b, U + u] = uw + kv + x[b, osc]
                H[b, u, 0], H[b, u, 1], H[b, u, 2] = ix + kx, iy + ky, iz + kz
                H[b, u, dd] = 1.0
                H[b, U + u, 0] = (wx - ix * uw) / rho + (vx - kx * kv) / rg
                H[b, U + u, 1] = (wy - iy * uw) / rho + (vy - ky * kv) / rg
                H[b, U + u, 2] = (wz - iz * uw) / rho + (vz - kz * kv) / rg
                H[b, U + u, 3], H[b, U + u, 4], H[b, U + u, 5] = ix + kx, iy + ky, iz + kz
                H[b, U + u, osc] = 1.0
        if radar:
            r0 = 2 * U
            qx, qy, qz = x[b, 0] - site[0], x[b, 1] - site[1], x[b, 2] - site[2]
            e = rot[0, 0] * qx + rot[0, 1] * qy + rot[0, 2] * qz
            n = rot[1, 0] * qx + rot[1, 1] * qy + rot[1, 2] * qz
            u_ = rot[2, 0] * qx + rot[2, 1] * qy + rot[2, 2] * qz
            rho2 = max(e * e + n * n, 1e-6)
            rho = math.sqrt(rho2)
            d2 = rho2 + u_ * u_
            d = math.sqrt(d2)
            D, az, el = d, math.atan2(e, n), math.atan2(u_, rho)
            if err >= 0:
                D += x[b, err]
                az += x[b, err + 1]
                el += x[b, err + 2]
            # the representative of az nearest the measured azimuth (no 2 pi jump)
            a = z_az[b] - az + math.pi
            az = z_az[b] - (a - 2.0 * math.pi * math.floor(a / (2.0 * math.pi)) - math.pi)
            vals = (D, az, el)
            jac = ((e / d, n / d, u_ / d), (n / rho2, -e / rho2, 0.0),
                   (-e * u_ / (rho * d2), -n * u_ / (rho * d2), rho / d2))
            for j in range(3):
                if not radar_mask[b, j]:
                    h[b, r0 + j] = 0.0
                    continue
                h[b, r0 + j] = vals[j]
                j0, j1, j2 = jac[j]
                for c in range(3):
                    H[b, r0 + j, c] = j0 * rot[0, c] + j1 * rot[1, c] + j2 * rot[2, c]
                if err >= 0:
                    H[b, r0 + j, err + j] = 1.0


_rows_nb = None if _nb is None else _nb.njit(cache=True, nogil=True)(_rows_py)


def _relay_err_py(pos, sat_pos, glonass, prm, h_tab, lnp_tab, scale, white):
    """The relay error model's per-satellite numbers (SondeTracker._relay_error_model), loop by loop
    for the compiled path: scale (Bs, U) the slow errors' std, white (Bs, U) the multipath's
    PSD-equivalent variance. prm: [sisre GPS, sisre GLONASS, iono zenith, R/(R + h_I), tropo zenith,
    mp a, mp b, mp el0 (rad), (1 + mu)/(1 - mu), 1/a^2, 1/b^2]; the pressure table of
    sitl.radio.relay.pressure_ratio."""
    Bs, U = scale.shape
    for b in range(Bs):
        x, y, z = pos[b, 0], pos[b, 1], pos[b, 2]
        nx, ny, nz = x * prm[9], y * prm[9], z * prm[10]
        nn = math.sqrt(nx * nx + ny * ny + nz * nz)
        nx, ny, nz = nx / nn, ny / nn, nz / nn
        r = math.sqrt(x * x + y * y + z * z)
        h = r - r / math.sqrt((x * x + y * y) * prm[9] + z * z * prm[10])
        pr = math.exp(np.interp(h, h_tab, lnp_tab))
        for u in range(U):
            dx, dy, dz = sat_pos[b, u, 0] - x, sat_pos[b, u, 1] - y, sat_pos[b, u, 2] - z
            d = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1.0)
            se = min(max((dx * nx + dy * ny + dz * nz) / d, -1.0), 1.0)
            el = max(math.asin(se), 0.0)
            sp = math.sin(el)
            c = prm[3] * math.cos(el)
            iono = prm[2] / math.sqrt(1.0 - c * c)
            tropo = prm[4] * pr * 1.001 / math.sqrt(0.002001 + sp * sp)
            sis = prm[1] if glonass[u] else prm[0]
            scale[b, u] = math.sqrt(sis * sis + iono * iono + tropo * tropo)
            mp = prm[5] + prm[6] * math.exp(-el / prm[7])
            white[b, u] = mp * mp * prm[8]


_relay_err_nb = None if _nb is None else _nb.njit(cache=True, nogil=True)(_relay_err_py)


class SondeMeasurement:
    """Relayed pseudoranges, pseudo-Dopplers (U satellite slots) and the radar's [range, az,
    el] for Bs sondes, as one measurement model (rows: U pr, U prr, then 3 radar rows; either
    part may be absent).

    relay part: sat_pos, sat_vel (Bs, U, 3), relay_mask (Bs, U), ground (3,) G, and bias_col (Bs, U)
    the state index of each satellite's error state (-1: none) with bias_scale (Bs, U) its std
    (the pseudorange gets bias_scale x that unit state);
    radar part: site (3,), rot (3, 3) its ENU rotation, radar_mask (Bs, 3);
    z (Bs, m) the measurements (held for the azimuth unwrap), r (Bs, m) the variances.
    Padded rows (mask False) have h = 0 and H = 0; the caller sets z = 0 and r = 1 there.
    ``h`` is numpy and broadcasts over leading sigma-point axes (UKF); ``h_and_H`` runs the
    compiled row kernel when numba is there (x (Bs, n)), else the numpy reference.
    """

    def __init__(self, layout: Layout, z, r, *, sat_pos=None, sat_vel=None, relay_mask=None, ground=None,
                 site=None, rot=None, radar_mask=None, bias_col=None, bias_scale=None, row_mask=None, sat_ids=None):
        self.layout = layout
        self.row_mask = row_mask  # (Bs, m) bool: rows left out (the integrity monitor's), None: none
        self.sat_ids = sat_ids  # the satellite of each relay slot (the union), when known
        self.z, self._r = z, r
        Bs = z.shape[0]
        self.relay = sat_pos is not None
        self.radar = site is not None
        if not self.relay:
            sat_pos = sat_vel = np.zeros((Bs, 0, 3))
            relay_mask = np.zeros((Bs, 0), dtype=bool)
            ground = np.zeros(3)
        if bias_col is None:
            bias_col = np.full(relay_mask.shape, -1, dtype=np.int64)
            bias_scale = np.zeros(relay_mask.shape)
        self.bias_col, self.bias_scale = bias_col, bias_scale
        if not self.radar:
            site, rot, radar_mask = np.zeros(3), np.eye(3), np.zeros((Bs, 0), dtype=bool)
        self.sat_pos, self.sat_vel, self.relay_mask, self.ground = sat_pos, sat_vel, relay_mask, ground
        self.site, self.rot, self.radar_mask = site, rot, radar_mask
        self.U = sat_pos.shape[1]
        self.mask = np.concatenate([relay_mask, relay_mask, radar_mask], axis=-1)
        if row_mask is not None:
            self.mask = self.mask & row_mask
        if self.mask.shape != z.shape or r.shape != z.shape:
            raise ValueError(f"z {z.shape} and r {r.shape} must have the rows of the mask {self.mask.shape}")

    @property
    def m_eff(self) -> np.ndarray:
        """Real (unpadded) rows per sonde."""
        return self.mask.sum(axis=-1)

    def _part(self, relay: bool, idx=slice(None)) -> SondeMeasurement:
        U = self.U
        if relay:
            cols = slice(0, 2 * U)
            kw = {"sat_pos": self.sat_pos[idx], "sat_vel": self.sat_vel[idx], "relay_mask": self.relay_mask[idx],
                  "ground": self.ground, "bias_col": self.bias_col[idx], "bias_scale": self.bias_scale[idx],
                  "sat_ids": self.sat_ids}
        else:
            cols = slice(2 * U, None)
            kw = {"site": self.site, "rot": self.rot, "radar_mask": self.radar_mask[idx]}
        if self.row_mask is not None:
            kw["row_mask"] = self.row_mask[idx][:, cols]
        return SondeMeasurement(self.layout, self.z[idx][:, cols], self._r[idx][:, cols], **kw)

    def relay_part(self, idx=slice(None)) -> SondeMeasurement | None:
        return self._part(True, idx) if self.relay else None

    def radar_part(self, idx=slice(None)) -> SondeMeasurement | None:
        return self._part(False, idx) if self.radar else None

    def subset(self, idx) -> SondeMeasurement:
        kw = {}
        if self.row_mask is not None:
            kw["row_mask"] = self.row_mask[idx]
        if self.relay:
            kw.update(sat_pos=self.sat_pos[idx], sat_vel=self.sat_vel[idx], relay_mask=self.relay_mask[idx],
                      ground=self.ground, bias_col=self.bias_col[idx], bias_scale=self.bias_scale[idx],
                      sat_ids=self.sat_ids)
        if self.radar:
            kw.update(site=self.site, rot=self.rot, radar_mask=self.radar_mask[idx])
        return SondeMeasurement(self.layout, self.z[idx], self._r[idx], **kw)

    # -- numpy reference (any leading axes before the sonde axis) --------------

    def _relay_np(self, x):
        L = self.layout
        P, V = relay_frame_point(x[..., 0:3], x[..., 3:6], self.ground), x[..., 3:6]
        dS = P[..., None, :] - self.sat_pos
        rho = np.sqrt(np.sum(dS * dS, axis=-1))
        Ki = dS / rho[..., None]
        dG = P - self.ground
        rG = np.maximum(np.sqrt(np.sum(dG * dG, axis=-1)), 1e-3)
        K = dG / rG[..., None]
        w = V[..., None, :] - self.sat_vel
        uw = np.sum(Ki * w, axis=-1)
        KV = np.sum(K * V, axis=-1)
        col = np.broadcast_to(np.maximum(self.bias_col, 0), x.shape[:-1] + self.bias_col.shape[-1:])
        bias = self.bias_scale * np.take_along_axis(x, col, axis=-1)  # scale 0 where there is no state
        h = np.concatenate([rho + bias + (rG + x[..., L.dd])[..., None], uw + (KV + x[..., L.osc])[..., None]],
                           axis=-1)
        return h, (Ki, K, rho, rG, w, uw, V, KV)

    def _radar_np(self, x):
        L = self.layout
        enu = (x[..., 0:3] - self.site) @ self.rot.T
        e, n, u = enu[..., 0], enu[..., 1], enu[..., 2]
        rho2 = np.maximum(e * e + n * n, 1e-6)
        rho = np.sqrt(rho2)
        d2 = rho2 + u * u
        d = np.sqrt(d2)
        D, az, el = d, np.arctan2(e, n), np.arctan2(u, rho)
        if L.err is not None:
            D, az, el = D + x[..., L.err], az + x[..., L.err + 1], el + x[..., L.err + 2]
        az = self.z[:, 2 * self.U + 1] - wrap_pi(self.z[:, 2 * self.U + 1] - az)
        return np.stack([D, az, el], axis=-1), (e, n, u, rho, rho2, d2, d)

    def h(self, x):
        x = np.asarray(x, dtype=float)
        parts = []
        if self.relay:
            parts.append(self._relay_np(x)[0])
        if self.radar:
            parts.append(self._radar_np(x)[0])
        h = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=-1)
        return np.where(self.mask, h, 0.0)

    def h_and_H_numpy(self, x):
        L = self.layout
        x = np.asarray(x, dtype=float)
        Bs, m = self.z.shape
        h = np.zeros((Bs, m))
        H = np.zeros((Bs, m, L.n))
        U = self.U
        if self.relay:
            hr, (Ki, K, rho, rG, w, uw, V, KV) = self._relay_np(x)
            h[:, :2 * U] = hr
            KiK = Ki + K[:, None, :]
            H[:, :U, 0:3] = KiK
            H[:, :U, L.dd] = 1.0
            H[:, U:2 * U, 0:3] = ((w - Ki * uw[..., None]) / rho[..., None]
                                  + ((V - K * KV[:, None]) / rG[:, None])[:, None, :])
            H[:, U:2 * U, 3:6] = KiK
            H[:, U:2 * U, L.osc] = 1.0
            bb, uu = np.nonzero(self.bias_col >= 0)
            H[bb, uu, self.bias_col[bb, uu]] = self.bias_scale[bb, uu]
        if self.radar:
            hd, (e, n, u, rho, rho2, d2, d) = self._radar_np(x)
            h[:, 2 * U:] = hd
            z0 = np.zeros_like(e)
            # rows d/d(enu) of range, azimuth, elevation (sitl.radio.radar.ecef_to_aer_jacobian)
            J = np.stack([np.stack([e / d, n / d, u / d], -1),
                          np.stack([n / rho2, -e / rho2, z0], -1),
                          np.stack([-e * u / (rho * d2), -n * u / (rho * d2), rho / d2], -1)], -2)
            H[:, 2 * U:, 0:3] = J @ self.rot
            if L.err is not None:
                for j in range(3):
                    H[:, 2 * U + j, L.err + j] = 1.0
        h *= self.mask
        H *= self.mask[..., None]
        return h, H

    def h_and_H(self, x):
        x = np.asarray(x, dtype=float)
        if _rows_nb is None or x.ndim != 2:
            return self.h_and_H_numpy(x)
        L = self.layout
        Bs, m = self.z.shape
        h = np.empty((Bs, m))
        H = np.zeros((Bs, m, L.n))
        z_az = self.z[:, 2 * self.U + 1] if self.radar else np.zeros(Bs)
        _rows_nb(np.ascontiguousarray(x), self.sat_pos, self.sat_vel, self.ground, self.relay_mask, self.site,
                 self.rot, np.ascontiguousarray(z_az), self.radar_mask, -1 if L.dd is None else L.dd,
                 -1 if L.osc is None else L.osc, -1 if L.err is None else L.err, self.bias_col, self.bias_scale, h, H)
        if self.row_mask is not None:
            h *= self.mask
            H *= self.mask[..., None]
        return h, H

    def H(self, x):
        return self.h_and_H(x)[1]

    def R_diag(self):
        return self._r

    def R(self):
        return self._r[..., None] * np.eye(self._r.shape[-1])


# ---------------------------------------------------------------------------
# relay least-squares fix (relay-only initialisation)


class RelayFix(NamedTuple):
    pos_ecef_m: np.ndarray  # (3,)
    delta_d_m: float
    vel_ecef_m_s: np.ndarray  # (3,)
    osc_m_s: float
    cov_pos_dd: np.ndarray  # (4, 4) over [P, dd]
    cov_vel_osc: np.ndarray  # (4, 4) over [V, osc]
    iterations: int


def relay_fix(sat_pos, sat_vel, pr, prr, var_pr, var_prr, ground, *, max_iter: int = 30,
              tol_m: float = 1e-4) -> RelayFix | None:
    """Least-squares fix from one relay epoch, or None (< 4 satellites, singular geometry or no
    convergence).

    Gauss-Newton on pr_i = |S_i - P| + |P - G| + dd (4 unknowns: P and dd) weighted by
    1/var_pr, started 1 km above G (never on G itself, where K = (P - G)/|P - G| is
    undefined); then prr_i + K_i.W_i = (K_i + K).V + osc, linear in (V, osc), weighted by
    1/var_prr. Covariances (A' W A)^-1.
    """
    sp, sv = np.asarray(sat_pos, float), np.asarray(sat_vel, float)
    pr, prr = np.asarray(pr, float), np.asarray(prr, float)
    wp, wv = 1.0 / np.asarray(var_pr, float), 1.0 / np.asarray(var_prr, float)
    G = np.asarray(ground, float)
    if pr.size < 4:
        return None
    up = G / np.linalg.norm(G)
    P, dd = G + 1000.0 * up, 0.0
    A = np.empty((pr.size, 4))
    A[:, 3] = 1.0
    it = 0
    for it in range(1, max_iter + 1):
        dS = P - sp
        rho = np.linalg.norm(dS, axis=1)
        Ki = dS / rho[:, None]
        dG = P - G
        rG = max(float(np.linalg.norm(dG)), 1e-3)
        A[:, :3] = Ki + dG / rG
        res = pr - (rho + rG + dd)
        N = A.T @ (A * wp[:, None])
        try:
            step = np.linalg.solve(N, A.T @ (wp * res))
        except np.linalg.LinAlgError:
            return None
        P, dd = P + step[:3], dd + step[3]
        if not np.all(np.isfinite(step)):
            return None
        if np.linalg.norm(step) < tol_m:
            break
    else:
        return None
    dS = P - sp
    rho = np.linalg.norm(dS, axis=1)
    Ki = dS / rho[:, None]
    K = (P - G) / max(float(np.linalg.norm(P - G)), 1e-3)
    A[:, :3] = Ki + K
    try:
        cov_pd = np.linalg.inv(A.T @ (A * wp[:, None]))
        Nv = A.T @ (A * wv[:, None])
        cov_vo = np.linalg.inv(Nv)
    except np.linalg.LinAlgError:
        return None
    sol = cov_vo @ (A.T @ (wv * (prr + np.sum(Ki * sv, axis=1))))
    # back from the relay's frame point to the sonde (relay_frame_point, inverted to first order)
    P = P + (P - relay_frame_point(P, sol[:3], G))
    return RelayFix(P, float(dd), sol[:3], float(sol[3]), 0.5 * (cov_pd + cov_pd.T), 0.5 * (cov_vo + cov_vo.T), it)


# ---------------------------------------------------------------------------
# the tracker


@dataclass
class TrackerCounters:
    """What the tracker took in, and what it refused or could not use (counted, not hidden)."""

    messages: int = 0  # bus messages handed to on_message
    ignored: int = 0  # other runs, kinds or sondes this tracker does not follow, other radars
    duplicates: int = 0  # (source, seq) seen before
    stale: int = 0  # older than (or at) the sonde's filter time (lag_window_s = 0)
    late_accepted: int = 0  # out of sequence, within the lag window: used by re-processing
    too_late: int = 0  # out of sequence, older than the lag window: dropped
    reprocess_runs: int = 0  # steps that went back to re-run epochs completed by late messages
    reprocessed_epochs: int = 0  # steps re-run (their Estimates are not published again)
    superseded: int = 0  # a second message of the same kind, sonde and epoch (the later wins)
    epochs: int = 0  # sonde-epochs processed
    relay_updates: int = 0
    relay_empty: int = 0  # relay epochs with no satellite (GNSS outage, out of range)
    relay_gated: int = 0  # relay blocks rejected at the chi-square gate
    relay_manoeuvre: int = 0  # relay blocks accepted only under the manoeuvre hypothesis
    radar_updates: int = 0
    range_only_updates: int = 0  # angles_valid False: range row only
    radar_gated: int = 0
    radar_manoeuvre: int = 0
    init_radar: int = 0
    init_relay: int = 0
    init_waiting: int = 0  # epochs of a sonde that could not initialise it
    reacquired: int = 0  # tracks re-initialised after reacquire_after rejections in a row
    landings: int = 0  # tracks that reached the ground descending (relaxed kinematics, landing): at rest since
    lost: int = 0  # tracks declared lost: no accepted measurement for max_coast_s (no Estimate until re-initialised)
    window_manoeuvre: int = 0  # manoeuvres found by the sliding-window NIS test
    ukf_updates: int = 0  # sonde-epochs updated by the UKF (filter "ukf", or "auto" when needed)
    bias_assigned: int = 0  # satellites given a (fresh) error state
    bias_overflow: int = 0  # satellite-epochs with no free error state (their error taken as white)
    estimates: int = 0
    integrity_epochs: int = 0  # epochs judged by the integrity monitor (params.integrity)
    integrity_rows_left_out: int = 0  # measurement rows the monitor kept out of an update (jump or excluded channel)
    integrity_exclusions: int = 0  # channels excluded (a step that stays, or a drift)
    integrity_readmissions: int = 0
    integrity_events: int = 0  # IntegrityEvents built (and published when attached)
    integrity_unmonitored: int = 0  # satellite-epochs with no free monitor channel (used unjudged)
    integrity_common_mode: int = 0  # sonde-epochs not judged: jumps on most rows at once (a manoeuvre, not a channel)
    integrity_warmup: int = 0  # sonde-epochs not judged: the track was (re)initialised less than the warm-up ago

    def as_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}


class _Step(NamedTuple):
    """One step in the lag window: its time, the previous step's, the tracker's state before
    it, the epochs it processed ({tau: {sonde: [relay, radar]}}) and the counters it added."""

    t: float
    t_prev: float
    snap: dict
    epochs: dict
    added: dict


class SondeTracker:
    """EKF/UKF radiosonde tracker on the bus, for one mode and any number of sondes.

    run_id : the bus run prefix. params : SondeTrackerParams (mode, models, gating).
    source_id : the publisher id of its Estimates (default ``sonde_tracker.<label>``).
    sonde_ids : follow only these sondes (default: every sonde seen).
    radar_id : follow only this radar (default: the first radar heard).
    """

    def __init__(self, run_id: str, params: SondeTrackerParams | None = None, *, source_id: str | None = None,
                 sonde_ids=None, radar_id: str | None = None):
        if not is_valid_id(run_id):
            raise ValueError(f"run_id must be 1..64 chars of [A-Za-z0-9_.-], got {run_id!r}")
        self.params = p = SondeTrackerParams() if params is None else params
        if not isinstance(p, SondeTrackerParams):
            raise TypeError(f"params: expected a SondeTrackerParams, got {type(p).__name__}")
        self.run_id = run_id
        self.label = p.mode_label
        self.source_id = source_id or f"sonde_tracker.{self.label}"
        if not is_valid_id(self.source_id):
            raise ValueError(f"source_id must be 1..64 chars of [A-Za-z0-9_.-], got {self.source_id!r}")
        self.sonde_ids = None if sonde_ids is None else tuple(str(s) for s in sonde_ids)
        self.radar_id = radar_id
        self.layout = layout_for(p.mode, p.radar_noise, p.relay_bias_states, p.kinematics)
        self.counters = TrackerCounters()
        self._seqtrack = SequenceTracker()
        self._transport = None
        self._subs: list = []
        self._seq = 0
        self._transition: SondeTransition | None = None
        self._radar_sites: dict = {}
        self._points = SigmaPoints(self.layout.n, alpha=1.0, beta=2.0, kappa=0.0)
        n = self.layout.n
        self._slots: dict[str, int] = {}
        self._ids: list[str] = []
        self._keys: list[str] = []
        self._x = np.zeros((0, n))
        self._P = np.zeros((0, n, n))
        self._t = np.zeros(0)  # filter time per sonde (NaN before initialisation)
        self._t_init = np.zeros(0)  # time of the track's last (re)initialisation
        self._t_meas = np.zeros(0)  # time of the track's last accepted measurement (params.max_coast_s)
        self._landed = np.zeros(0, dtype=bool)  # the track has landed (relaxed kinematics, params.landing)
        # the landing's uncertain time (_land): when, the direction back up the trajectory a = V / V_up, the
        # covariance of the position with its height b = P n, the height's variance and the descent speed
        self._land_t = np.zeros(0)
        self._land_a, self._land_b = np.zeros((0, 3)), np.zeros((0, 3))
        self._land_var, self._land_v = np.zeros(0), np.zeros(0)
        self._ground_h_m = None  # the ground's height (the site's), for the landing
        self._nis = np.zeros(0)  # summed block NIS of the last processed epoch
        self._rejects = np.zeros((0, 2), dtype=np.int64)  # consecutive rejections [relay, radar]
        W = p.manoeuvre_window or 1
        self._win_nis, self._win_m = np.zeros((0, W)), np.zeros((0, W), dtype=np.int64)  # NIS window
        self._win_k = np.zeros(0, dtype=np.int64)
        self._win_S, self._win_M = np.zeros(0), np.zeros(0, dtype=np.int64)
        self._pending: dict[float, dict[str, list]] = defaultdict(dict)
        # lag window (params.lag_window_s): per step, the state before it, the epochs it processed
        # ({tau: {sonde: [relay, radar]}}, completed by late messages) and the counters it added
        self._hist: list[_Step] = []
        self._dirty: float | None = None  # the earliest step a late message completed
        self._t_last = -math.inf  # the last step's time
        self._gates: dict[int, float] = {}
        # per-satellite error states, per sonde: sat_id -> slot, slot -> sat_id, last use, last epoch's columns
        self._bias_map: list[dict] = []
        self._bias_owner: list[list] = []
        self._bias_last = np.zeros((0, self.layout.nb))
        self._bias_prev: list = []
        self._err_prm = None
        # the integrity monitor: rows [pr of S satellite channels, their prr, radar range, az, el]
        self._mon = None if p.integrity is None else IntegrityMonitor(p.integrity)
        self._events = None
        if self._mon is not None:
            S = p.integrity_sat_channels if self.layout.uses_relay else 0
            R = 3 if self.layout.uses_radar else 0
            a = np.arange(S)
            self._mon_S, self._mon_R = S, R
            self._mon_ch = np.concatenate([a, a, S + np.arange(R)]).astype(np.int64)
            self._chan_of: dict = {}  # satellite id -> channel
            self._chan_sat: list = [None] * S
            self._chan_last = np.full(S, -(10**9), dtype=np.int64)  # monitor epoch of each channel's last use
            self._mon_k = 0  # monitor epochs so far
            self._cohorts: list = []  # [first slot, end slot, MonitorState]: sondes that joined together
            self._guard: dict = {}  # slot -> (inert (m_mon,), r used (m_mon,)) of the current epoch
            self._mon_models: dict = {}  # (dt, slots) -> the epoch's measurement model, built once
            self._events = IntegrityEventPublisher(run_id, f"{self.source_id}.integrity")
            # a readmitted or long-unused channel has a fresh window: reuse after this many epochs
            self._chan_age = p.integrity.window + p.integrity.readmit_after + 1

    # -- bus ---------------------------------------------------------------

    def attach(self, transport) -> list:
        """Subscribe to the relay and radar messages of the run (and publish Estimates there)."""
        self._transport = transport
        if self._events is not None:
            self._events.transport = transport
        sondes = self.sonde_ids or ("*",)
        for s in sondes:
            ids = {} if s == "*" else {"sonde": s}
            if self.layout.uses_relay:
                self._subs.append(transport.subscribe(key_pattern(self.run_id, SondeRelay, **ids), self.on_message))
            if self.layout.uses_radar:
                self._subs.append(transport.subscribe(key_pattern(self.run_id, RadarMeasurement, **ids),
                                                      self.on_message))
        return list(self._subs)

    def close(self) -> None:
        for s in self._subs:
            s.close()
        self._subs.clear()

    def on_message(self, key: str, msg) -> None:
        """Buffer one bus message for its epoch (processed by ``step``)."""
        c = self.counters
        c.messages += 1
        parsed = parse_key(key) if isinstance(key, str) else None
        if parsed is None or parsed[0] != self.run_id or "sonde" not in parsed[2]:
            c.ignored += 1
            return
        _, cls, ids = parsed
        sonde = ids["sonde"]
        if self.sonde_ids is not None and sonde not in self.sonde_ids:
            c.ignored += 1
            return
        if isinstance(msg, SondeRelay) and cls is SondeRelay and self.layout.uses_relay:
            kind = 0
        elif isinstance(msg, RadarMeasurement) and cls is RadarMeasurement and self.layout.uses_radar:
            if self.radar_id is None:
                self.radar_id = ids["radar"]
            if ids["radar"] != self.radar_id:
                c.ignored += 1
                return
            kind = 1
        else:
            c.ignored += 1
            return
        if self._seqtrack.update(f"{key}|{msg.source_id}#{msg.incarnation}", msg.seq).duplicate:  # per stream
            c.duplicates += 1
            return
        t = float(msg.t_gps_s)
        slot = self._slots.get(sonde)
        lag = self.params.lag_window_s
        if lag > 0 and self._hist and (t <= self._hist[-1].t and (slot is None or not self._t[slot] < t)):
            # out of sequence (a step at or after t has run): re-processed at the next step
            e = self._hist_for(t) if t >= self._hist[-1].t - lag - 1e-9 else None
            if e is None:
                c.too_late += 1
                return
            entry = e.epochs.setdefault(t, {}).setdefault(sonde, [None, None])
            if entry[kind] is not None:
                c.superseded += 1
            entry[kind] = msg
            c.late_accepted += 1
            self._dirty = e.t if self._dirty is None else min(self._dirty, e.t)
            return
        if slot is not None and self._t[slot] >= t:  # NaN (not initialised yet) compares False
            c.stale += 1
            return
        entry = self._pending[t].setdefault(sonde, [None, None])
        if entry[kind] is not None:
            c.superseded += 1
        entry[kind] = msg

    def step(self, t_gps_s: float) -> list[Estimate]:
        """Process every buffered epoch <= t, predict every initialised sonde to t and publish
        (and return) one Estimate per sonde. Late messages taken in since the last step (lag
        window) are used first: the state goes back to before the step that would have
        processed them and the steps since are re-run (their Estimates not published again)."""
        t = float(t_gps_s)
        if not math.isfinite(t):
            raise ValueError(f"t_gps_s must be finite, got {t_gps_s!r}")
        if self._dirty is not None:
            self._reprocess()
        epochs = {tau: self._pending.pop(tau) for tau in sorted(k for k in self._pending if k <= t)}
        self._run_step(t, epochs)
        out = []
        for slot in np.flatnonzero(self._t == t):
            out.append(self._estimate(int(slot), t))
        return out

    def _step_core(self, t: float, epochs: dict) -> None:
        for tau in sorted(epochs):  # (a late message may have added an earlier epoch)
            self._process(tau, epochs[tau])
        live = np.flatnonzero(self._t < t)  # initialised and behind (NaN excluded)
        if live.size:
            self._predict(live, t)
            self._nis[live] = np.nan
        self._land()
        mc = self.params.max_coast_s
        if mc is not None:
            gone = np.flatnonzero(np.isfinite(self._t) & (t - self._t_meas > mc))
            if gone.size:
                self._lose(gone)

    def _lose(self, slots) -> None:
        """Tracks with no accepted measurement for longer than ``max_coast_s``: lost. They are
        uninitialised again (no Estimate is published; the next relay or radar epoch that can fix
        the sonde initialises it as at its acquisition), their bookkeeping reset. Counted ``lost``."""
        for slot in slots:
            self._t[slot] = self._t_init[slot] = self._t_meas[slot] = np.nan
            self._nis[slot] = np.nan
            self._landed[slot] = False
            self._land_t[slot] = np.nan
            self._rejects[slot] = 0
            self._win_nis[slot], self._win_m[slot], self._win_k[slot] = 0.0, 0, 0
            self._win_S[slot], self._win_M[slot] = 0.0, 0
            if self.layout.nb:
                self._bias_clear(slot)
        self.counters.lost += len(slots)

    def _land(self) -> None:
        """Relaxed kinematics with ``landing``: a descending track (its target vertical speed -- the
        wind state's component along the local vertical -- below 0) whose height has reached the
        ground's (the site's: flat terrain, as in the sonde model) has landed and is at rest from then
        on (velocity, gust, wind and shear zero; the landed transition), counted ``landings``; a
        re-initialisation takes it up again.

        The landing keeps what the track does not know. The estimate reaches the ground when its
        height does; the sonde, dh higher or lower (the height's uncertainty), lands dh / |V_up|
        later or earlier, carried on along its trajectory meanwhile. So the landing point is the
        estimate moved along its velocity V to the ground, and its error is the position error
        projected onto the ground along V: J = I - a n' with a = V / (V . n), n the local vertical --
        the height's uncertainty becomes horizontal uncertainty (V_h / |V_up| per metre), it is not
        dropped. The landed covariance adds, vertically, the second moment of the ground's drop
        below the tangent plane over that horizontal spread (|d|^2 / 2R: at a 30 km sigma ~70 m)
        and a 1 m^2 floor. Until the sonde has surely come down (its remaining height
        max(dh - |V_up| tau, 0) after tau) the published covariance also carries its possible
        remaining descent (``_landing_spread``)."""
        w = self.layout.wind
        if w is None or not self.params.landing or self._ground_h_m is None or not self._landed.size:
            return
        cand = np.flatnonzero(np.isfinite(self._t) & ~self._landed)
        if not cand.size:
            return
        pos = self._x[cand, 0:3]  # (a first cut: descending along the geocentric vertical, within 1 km of the ground)
        r = np.sqrt(np.einsum("ij,ij->i", pos, pos))
        near = (np.einsum("ij,ij->i", self._x[cand, w:w + 3], pos) < 0.0) & (r < WGS84.a_m + self._ground_h_m + 1000.0)
        cand = cand[near]
        if not cand.size:
            return
        lat, lon, h = (np.atleast_1d(v) for v in ecef_to_geodetic(self._x[cand, 0:3]))
        up = _enu_rotations(lat, lon)[:, 2]  # the local vertical at each estimate
        hit = (np.einsum("ij,ij->i", self._x[cand, w:w + 3], up) < 0.0) & (h <= self._ground_h_m)
        k = self.layout.n_kin
        n = self.layout.n
        for i in np.flatnonzero(hit):
            slot, nrm = cand[i], up[i]
            x, P0 = self._x[slot], self._P[slot].copy()  # (P0: the pre-landing covariance, kept below)
            v_up = float(x[3:6] @ nrm)
            a = x[3:6] / v_up if v_up < -0.1 else nrm  # back up the trajectory, 1 m per metre of height
            pos = x[0:3] - a * (h[i] - self._ground_h_m)  # to the ground along the trajectory
            la, lo, _ = ecef_to_geodetic(pos)
            x[0:3] = geodetic_to_ecef(float(la), float(lo), self._ground_h_m)
            x[3:k] = 0.0
            T = np.eye(n)
            T[0:3, 0:3] -= np.outer(a, nrm)
            T[3:k, 3:k] = 0.0
            P = T @ P0 @ T.T
            P[0:3, 0:3] += _curvature_drop_cov(x[0:3], P[0:3, 0:3]) + np.outer(nrm, nrm)  # and a 1 m^2 floor
            P[3:k, 3:k] += 1e-8 * np.eye(k - 3)
            self._P[slot] = 0.5 * (P + P.T)
            self._landed[slot] = True
            self._land_t[slot] = self._t[slot] if v_up < -0.1 else np.nan
            self._land_a[slot], self._land_b[slot] = a, P0[0:3, 0:3] @ nrm
            self._land_var[slot], self._land_v[slot] = float(nrm @ P0[0:3, 0:3] @ nrm), -v_up
            self.counters.landings += 1

    def _landing_spread(self, slot: int, t: float):
        """The published position covariance's excess over the landed state's while the sonde may
        still be coming down (None once negligible): with dh ~ N(0, s^2) its height above the
        estimate at the landing, the error at tau after it is e - a g, g = min(dh, |V_up| tau) (lower:
        landed earlier, at its own landing point; higher: still descending towards it), whose second
        moment is P - Phi(z) (a b' + b a') + a a' s^2 (Phi(z) - z phi(z) + z^2 (1 - Phi(z))),
        z = |V_up| tau / s; at tau -> oo this is the landed J P J'. The excess over that."""
        t0, var = self._land_t[slot], self._land_var[slot]
        if not (math.isfinite(t0) and var > 0.0):
            return None
        s = math.sqrt(var)
        z = self._land_v[slot] * (t - t0) / s
        if z > 8.0:
            return None
        q = 0.5 * math.erfc(z / math.sqrt(2.0))  # 1 - Phi(z)
        phi = math.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)
        a, b = self._land_a[slot], self._land_b[slot]
        ab = np.outer(a, b)
        return q * (ab + ab.T) - var * (q * (1.0 - z * z) + z * phi) * np.outer(a, a)

    def _run_step(self, t: float, epochs: dict) -> None:
        """One step's filtering (no output); with a lag window, recorded in the history."""
        lag = self.params.lag_window_s
        if lag <= 0:
            self._step_core(t, epochs)
            return
        snap = self._snapshot()
        before = self.counters.as_dict()
        t_prev = self._t_last
        self._step_core(t, epochs)
        self._t_last = t
        after = self.counters.as_dict()
        self._hist.append(_Step(t, t_prev, snap, epochs, {k: after[k] - before[k] for k in after if after[k] != before[k]}))
        _lagwindow.prune(self._hist, t, lag, 1e-9)

    def _hist_for(self, tau: float):
        """The step of the history that processes epoch tau (t_prev < tau <= t), or None."""
        for e in self._hist:
            if e.t_prev < tau <= e.t:
                return e
        return None

    def _reprocess(self) -> None:
        t0, self._dirty = self._dirty, None
        c = self.counters

        def restore(e):
            self._restore(e.snap)
            self._t_last = e.t_prev

        def uncount(e):
            for k, v in e.added.items():
                setattr(c, k, getattr(c, k) - v)

        n = _lagwindow.rerun(self._hist, t0, 0.0, restore=restore, uncount=uncount,
                             run=lambda e: self._run_step(e.t, e.epochs), events=self._events)
        if n:
            c.reprocess_runs += 1
            c.reprocessed_epochs += n

    _SNAP_ARRAYS = ("_x", "_P", "_t", "_t_init", "_t_meas", "_landed", "_land_t", "_land_a", "_land_b", "_land_var",
                    "_land_v", "_nis", "_rejects", "_win_nis", "_win_m", "_win_k", "_win_S", "_win_M", "_bias_last")

    def _snapshot(self) -> dict:
        """Copies of what a step writes (the per-sonde arrays, the sondes' satellite error-state
        maps, the integrity monitor's bookkeeping); caches and the model are kept."""
        d = {name: getattr(self, name).copy() for name in self._SNAP_ARRAYS}
        d["_slots"], d["_ids"], d["_keys"] = dict(self._slots), list(self._ids), list(self._keys)
        d["_bias_map"] = [dict(m) for m in self._bias_map]
        d["_bias_owner"] = [list(o) for o in self._bias_owner]
        d["_bias_prev"] = list(self._bias_prev)
        if self._mon is not None:
            d["_chan_of"], d["_chan_sat"] = dict(self._chan_of), list(self._chan_sat)
            d["_chan_last"], d["_mon_k"] = self._chan_last.copy(), self._mon_k
            d["_cohorts"] = [list(co) for co in self._cohorts]  # each state is replaced by a step, not written
        return d

    def _restore(self, d: dict) -> None:
        for name, v in d.items():
            setattr(self, name, v)

    def _estimate(self, slot: int, t: float) -> Estimate:
        x, P = self._x[slot], self._P[slot]
        cov = P[:6, :6]
        if self._landed[slot]:
            extra = self._landing_spread(slot, t)
            if extra is not None:
                cov = cov.copy()
                cov[0:3, 0:3] += extra
        elif self.layout.wind is not None and P[0, 0] + P[1, 1] + P[2, 2] > 1e6:  # a long coast (> 1 km)
            cov = cov.copy()
            cov[0:3, 0:3] += _curvature_drop_cov(x[0:3], cov[0:3, 0:3])
        est = Estimate(t_gps_s=t, source_id=self.source_id, seq=self._seq, kind="sonde", pos_ecef_m=x[0:3],
                       vel_ecef_m_s=x[3:6], cov=0.5 * (cov + cov.T), nis=float(self._nis[slot]), mode=self.label)
        self._seq += 1
        self.counters.estimates += 1
        if self._transport is not None:
            self._transport.publish(self._keys[slot], est)
        return est

    # -- state access ------------------------------------------------------

    @property
    def sondes(self) -> list[str]:
        return list(self._ids)

    def state(self, sonde: str):
        """(t, x, P) of a sonde (copies), or None before its initialisation."""
        slot = self._slots.get(sonde)
        if slot is None or not math.isfinite(self._t[slot]):
            return None
        return float(self._t[slot]), self._x[slot].copy(), self._P[slot].copy()

    # -- internals ---------------------------------------------------------

    def _slot(self, sonde: str) -> int:
        slot = self._slots.get(sonde)
        if slot is None:
            n = self.layout.n
            slot = self._slots[sonde] = len(self._ids)
            self._ids.append(sonde)
            self._keys.append(key_for(self.run_id, Estimate, kind="sonde", id=sonde))
            self._x = np.concatenate([self._x, np.zeros((1, n))])
            self._P = np.concatenate([self._P, np.zeros((1, n, n))])
            self._t = np.append(self._t, np.nan)
            self._t_init = np.append(self._t_init, np.nan)
            self._t_meas = np.append(self._t_meas, np.nan)
            self._landed = np.append(self._landed, False)
            self._land_t = np.append(self._land_t, np.nan)
            self._land_a = np.concatenate([self._land_a, np.zeros((1, 3))])
            self._land_b = np.concatenate([self._land_b, np.zeros((1, 3))])
            self._land_var = np.append(self._land_var, 0.0)
            self._land_v = np.append(self._land_v, 0.0)
            self._nis = np.append(self._nis, np.nan)
            self._rejects = np.concatenate([self._rejects, np.zeros((1, 2), dtype=np.int64)])
            W = self.params.manoeuvre_window or 1
            self._win_nis = np.concatenate([self._win_nis, np.zeros((1, W))])
            self._win_m = np.concatenate([self._win_m, np.zeros((1, W), dtype=np.int64)])
            self._win_k = np.append(self._win_k, 0)
            self._win_S = np.append(self._win_S, 0.0)
            self._win_M = np.append(self._win_M, 0)
            self._bias_map.append({})
            self._bias_owner.append([None] * self.layout.nb)
            self._bias_last = np.concatenate([self._bias_last, np.full((1, self.layout.nb), -np.inf)])
            self._bias_prev.append(None)
        return slot

    # -- per-satellite relay error states -----------------------------------

    def _bias_clear(self, slot: int) -> None:
        self._bias_map[slot].clear()
        self._bias_owner[slot] = [None] * self.layout.nb
        self._bias_last[slot] = -np.inf
        self._bias_prev[slot] = None

    def _bias_cols(self, slot: int, sat_ids: tuple, t: float) -> np.ndarray:
        """The state index of each satellite's error state for one sonde (-1: no free state).
        A satellite keeps its state while it is tracked and after (a GNSS outage, a short
        loss); a new one takes the least recently used state not needed now, reset to its
        prior (0, unit variance, uncorrelated)."""
        L = self.layout
        prev = self._bias_prev[slot]
        if prev is not None and prev[0] == sat_ids:
            cols = prev[1]
            self._bias_last[slot, cols[cols >= 0] - L.bias] = t
            return cols
        mp, owner, last = self._bias_map[slot], self._bias_owner[slot], self._bias_last[slot]
        used = {mp[sid] for sid in sat_ids if sid in mp}
        cols = np.empty(len(sat_ids), dtype=np.int64)
        order = None
        for i, sid in enumerate(sat_ids):
            j = mp.get(sid)
            if j is None:
                if order is None:
                    order = np.argsort(last, kind="stable").tolist()
                free = [k for k in order if k not in used]
                if not free:
                    cols[i] = -1
                    self.counters.bias_overflow += 1
                    continue
                j = free[0]
                if owner[j] is not None:
                    del mp[owner[j]]
                mp[sid], owner[j] = j, sid
                k = L.bias + j
                self._x[slot, k] = 0.0
                self._P[slot, k, :] = 0.0
                self._P[slot, :, k] = 0.0
                self._P[slot, k, k] = 1.0
                used.add(j)
                self.counters.bias_assigned += 1
            cols[i] = L.bias + j
            last[j] = t
        self._bias_prev[slot] = (sat_ids, cols)
        return cols

    def _relay_error_model(self, pos, sat_pos, glonass, dt: float):
        """(scale, white) (Bs, U): the per-satellite slow error's std (SISRE + ionosphere +
        troposphere, at the satellites' elevations from the estimated sonde position and its
        height) and the multipath's PSD-equivalent white variance sigma_mp^2 (1 + mu)/(1 - mu),
        mu = e^{-dt/tau_mp} (its correlation time is short against the filter's memory, so it
        goes into R, sized to the same low-frequency power)."""
        e = self.params.relay_errors
        mu = math.exp(-(dt if dt > 0.0 else 1.0) / e.multipath_tau_s)  # dt = 0: a fix's own epoch, 1 Hz
        if _relay_err_nb is not None and np.ndim(pos) == 2 and self.params.backend != "numpy":
            if self._err_prm is None:
                a2, b2 = 1.0 / WGS84.a_m**2, 1.0 / (WGS84.a_m * (1.0 - WGS84.f)) ** 2
                self._err_prm = np.array([e.sisre_gps_m, e.sisre_glonass_m, e.iono_zenith_m,
                                          WGS84.a_m / (WGS84.a_m + e.iono_shell_h_m), e.tropo_zenith_m,
                                          e.multipath_a_m, e.multipath_b_m, math.radians(e.multipath_el0_deg), 0.0,
                                          a2, b2])
            self._err_prm[8] = (1.0 + mu) / (1.0 - mu)
            Bs, U = sat_pos.shape[:2]
            scale, white = np.empty((Bs, U)), np.empty((Bs, U))
            _relay_err_nb(np.ascontiguousarray(pos, dtype=float), np.ascontiguousarray(sat_pos, dtype=float),
                          np.ascontiguousarray(glonass), self._err_prm, _relay.P_TABLE_H_M, _relay.LN_P_TABLE,
                          scale, white)
            return scale, white
        # the geodetic vertical and height, to well below the model's needs for h < 100 km (the
        # ellipsoid's normal at the point, and the distance above the ellipsoid along the radius)
        ax2, bx2 = 1.0 / WGS84.a_m**2, 1.0 / (WGS84.a_m * (1.0 - WGS84.f)) ** 2
        nrm = pos * np.array([ax2, ax2, bx2])
        up = nrm / np.linalg.norm(nrm, axis=-1, keepdims=True)
        r = np.linalg.norm(pos, axis=-1)
        hgt = r - 1.0 / np.sqrt((pos[..., 0] ** 2 + pos[..., 1] ** 2) * ax2 + pos[..., 2] ** 2 * bx2) * r
        d = sat_pos - pos[..., None, :]
        el = np.arcsin(np.clip(np.sum(d * up[..., None, :], axis=-1)
                               / np.maximum(np.linalg.norm(d, axis=-1), 1.0), -1.0, 1.0))
        sig = e.slow_sigmas_m(glonass, el, np.asarray(hgt)[..., None])
        return np.sqrt(np.sum(sig * sig, axis=-1)), e.multipath_sigma_m(el) ** 2 * ((1.0 + mu) / (1.0 - mu))

    def _ensure_transition(self, site_ecef) -> None:
        if self._transition is not None:
            return
        p = self.params
        lat, lon, site_h = ecef_to_geodetic(np.asarray(site_ecef, float))
        r = enu_rotation(lat, lon)  # the model's horizontal / vertical split at the site
        self._transition = SondeTransition(self.layout, p, r)
        self._ground_h_m = float(site_h)  # flat terrain at the site's height (the landing)

    def _radar_site(self, pos):
        key = np.asarray(pos, float).tobytes()
        out = self._radar_sites.get(key)
        if out is None:
            lat, lon, _ = ecef_to_geodetic(np.asarray(pos, float))
            out = self._radar_sites[key] = (np.array(pos, float), enu_rotation(lat, lon))
        return out

    def _gate(self, m: np.ndarray) -> np.ndarray:
        if self.params.gate_prob is None:
            return np.full(m.shape, np.inf)
        out = np.empty(m.shape)
        for i, mi in enumerate(m.tolist()):
            g = self._gates.get(mi)
            if g is None:
                g = self._gates[mi] = float(chi2.ppf(self.params.gate_prob, mi))
            out[i] = g
        return out

    def _predict(self, slots: np.ndarray, t: float) -> None:
        """x- = f(x), P- = F P F' + Q for the sondes in slots, to time t."""
        dts = t - self._t[slots]
        for dt in (dts[:1] if np.all(dts == dts[0]) else np.unique(dts)):
            sel = slots if dts.size == 1 or np.all(dts == dt) else slots[dts == dt]
            landed = self._landed[sel]
            for lnd in ((False, True) if landed.any() else (False,)):
                ss = sel if not landed.any() else sel[landed == lnd]
                if not ss.size:
                    continue
                self._x[ss], self._P[ss] = self._propagate(ss, float(dt), lnd)
        self._t[slots] = t

    def _propagate(self, slots, dt: float, landed: bool):
        """(x-, P-) of the sondes in slots over dt (SondeTransition.predict: relaxed kinematics per
        sonde in its local frame with the descent law as an input; shared F for singer or landed)."""
        return self._transition.predict(self._x[slots], self._P[slots], dt, landed, backend=self.params.backend)

    def _update(self, x, P, z, model, filt: str):
        if filt == "ukf":
            return ukf_update(x, P, z, model, points=self._points, backend=self.params.backend)
        return ekf_update(x, P, z, model, backend=self.params.backend)

    def _gated_update(self, slots: np.ndarray, x, P, model, what: str, dt: float, filt: str) -> np.ndarray:
        """One block update (prior x, P of the sondes in slots) with the chi-square gate and the
        manoeuvre retry; writes the posteriors (or the prior, where rejected) back and returns
        the NIS (NaN where rejected)."""
        c = self.counters
        z = model.z
        res = self._update(x, P, z, model, filt)
        gate = self._gate(model.m_eff)
        nis = np.array(res.nis, dtype=float)
        xo, Po = np.array(res.x), np.array(res.P)
        bad = np.flatnonzero(~(nis <= gate))
        if bad.size:
            res2 = self._update(x[bad], P[bad] + self._transition.boost(dt), z[bad], model.subset(bad), filt)
            ok2 = np.asarray(res2.nis) <= gate[bad]
            acc, rej = bad[ok2], bad[~ok2]
            self._t_init[slots[acc]] = self._t[slots[acc]]  # (already the epoch) a manoeuvre: the monitor waits
            xo[acc], Po[acc], nis[acc] = np.asarray(res2.x)[ok2], np.asarray(res2.P)[ok2], np.asarray(res2.nis)[ok2]
            xo[rej], Po[rej], nis[rej] = x[rej], P[rej], np.nan
            setattr(c, f"{what}_manoeuvre", getattr(c, f"{what}_manoeuvre") + int(acc.size))
            setattr(c, f"{what}_gated", getattr(c, f"{what}_gated") + int(rej.size))
        j = 0 if what == "relay" else 1
        self._rejects[slots, j] = np.where(np.isfinite(nis), 0, self._rejects[slots, j] + 1)
        self._x[slots], self._P[slots] = xo, 0.5 * (Po + np.swapaxes(Po, -1, -2))
        return nis

    # -- initialisation ----------------------------------------------------

    def _prior(self) -> tuple[np.ndarray, np.ndarray]:
        L, p = self.layout, self.params
        x, P = np.zeros(L.n), np.zeros((L.n, L.n))
        P[3:6, 3:6] = np.eye(3) * p.prior_sigma_vel_m_s**2
        P[6:9, 6:9] = self._transition.acc_cov_ecef
        if L.dd is not None:
            P[L.dd, L.dd] = p.prior_sigma_delta_d_m**2
            P[L.osc, L.osc] = p.osc_sigma_m_s**2
        if L.err is not None:
            P[L.err:L.err + 3, L.err:L.err + 3] = np.diag(np.square(p.radar_sigma))
        if L.nb:
            b = np.arange(L.bias, L.bias + L.nb)
            P[b, b] = 1.0
        return x, P

    def _with_wind(self, x, P):
        """Relaxed kinematics: the wind states of a new track, set once the rest of (x, P) is --
        the wind is the velocity plus an offset d ~ N(0, prior_sigma_wind_offset^2 I) independent
        of everything else (so its rows are the velocity's), and its shear is at its stationary prior;
        the gust's and the shear's priors split horizontal / vertical at the new track's position."""
        w = self.layout.wind
        if w is None:
            return x, P
        tr = self._transition
        P[6:9, 6:9] = tr.acc_cov_at(x[0:3])  # (the prior's gust block is independent of the rest)
        x[w:w + 3] = x[3:6]
        x[w + 3:w + 6] = 0.0
        P[w:w + 6, :] = 0.0
        P[:, w:w + 6] = 0.0
        P[w:w + 3, :] = P[3:6, :]
        P[:, w:w + 3] = P[:, 3:6]
        P[w:w + 3, w:w + 3] = P[3:6, 3:6] + self.params.prior_sigma_wind_offset_m_s**2 * np.eye(3)
        P[w + 3:w + 6, w + 3:w + 6] = tr.shear_cov_at(x[0:3])
        return x, P

    def _init_from_radar(self, slot: int, m: RadarMeasurement, count: bool = True) -> bool:
        if not m.angles_valid:
            return False
        self._ensure_transition(m.radar_pos_ecef_m)
        site = np.asarray(m.radar_pos_ecef_m)
        L = self.layout
        if L.nb:
            self._bias_clear(slot)
        x, P = self._prior()
        x[0:3] = radar_aer_to_ecef(m.az_rad, m.el_rad, m.slant_range_m, site)
        var = np.array([m.var_az_rad2, m.var_el_rad2, m.var_range_m2])  # radar.py's column order
        P[0:3, 0:3] = aer_cov_to_ecef(m.az_rad, m.el_rad, m.slant_range_m, site, var)
        if L.err is not None:
            J = aer_to_ecef_jacobian(m.az_rad, m.el_rad, m.slant_range_m, site)[:, [2, 0, 1]]  # [D, az, el]
            S = P[L.err:L.err + 3, L.err:L.err + 3]
            Rw = self.params.radar_white_fraction * np.diag([m.var_range_m2, m.var_az_rad2, m.var_el_rad2])
            # P = g(z - err - v), v the white part: cov(P) = J (S + Rw) J', cov(P, err) = -J S
            # (without Rw the joint covariance is singular: P would be a function of err)
            P[0:3, 0:3] = J @ (S + Rw) @ J.T
            P[0:3, L.err:L.err + 3] = -J @ S
            P[L.err:L.err + 3, 0:3] = -(J @ S).T
        x, P = self._with_wind(x, P)
        self._x[slot], self._P[slot] = x, 0.5 * (P + P.T)
        self._landed[slot] = False
        self.counters.init_radar += count
        return True

    def _init_from_relay(self, slot: int, m: SondeRelay, count: bool = True) -> bool:
        fix = relay_fix(m.sat_pos_ecef_m, m.sat_vel_ecef_m_s, m.pseudorange_m, m.pseudo_doppler_m_s,
                        m.var_pseudorange_m2, m.var_pseudo_doppler_m2_s2, m.ground_pos_ecef_m)
        if fix is None:
            return False
        L = self.layout
        cross = None
        if L.nb:
            # the fix again, weighted by the whole error budget; its error G (b + v) is correlated
            # with the satellites' slow errors b = s u: cov(fix error, u error) = -G diag(s)
            glon = np.fromiter((sid[:1] == "R" for sid in m.sat_ids), dtype=bool, count=m.n)
            scale, white = self._relay_error_model(fix.pos_ecef_m, m.sat_pos_ecef_m, glon, 1.0)
            var = m.var_pseudorange_m2 + white + scale * scale
            fix2 = relay_fix(m.sat_pos_ecef_m, m.sat_vel_ecef_m_s, m.pseudorange_m, m.pseudo_doppler_m_s, var,
                             m.var_pseudo_doppler_m2_s2, m.ground_pos_ecef_m)
            if fix2 is None:
                return False
            fix = fix2
            G = m.ground_pos_ecef_m
            dS = fix.pos_ecef_m - m.sat_pos_ecef_m
            A = np.empty((m.n, 4))
            A[:, :3] = (dS / np.linalg.norm(dS, axis=1)[:, None]
                        + (fix.pos_ecef_m - G) / max(float(np.linalg.norm(fix.pos_ecef_m - G)), 1e-3))
            A[:, 3] = 1.0
            gain = fix.cov_pos_dd @ (A.T / var)  # (4, n)
            self._bias_clear(slot)
            cols = self._bias_cols(slot, m.sat_ids, float(m.t_gps_s))
            cross = (cols, -gain * np.where(cols >= 0, scale, 0.0))
        self._ensure_transition(m.ground_pos_ecef_m)
        x, P = self._prior()
        x[0:3], x[3:6], x[L.dd], x[L.osc] = fix.pos_ecef_m, fix.vel_ecef_m_s, fix.delta_d_m, fix.osc_m_s
        ip, iv = [0, 1, 2, L.dd], [3, 4, 5, L.osc]
        P[np.ix_(ip, ip)] = fix.cov_pos_dd
        P[np.ix_(iv, iv)] = fix.cov_vel_osc
        if cross is not None:
            cols, c = cross
            ok = cols >= 0
            P[np.ix_(ip, cols[ok])] = c[:, ok]
            P[np.ix_(cols[ok], ip)] = c[:, ok].T
        x, P = self._with_wind(x, P)
        self._x[slot], self._P[slot] = x, P
        self._landed[slot] = False
        self.counters.init_relay += count
        return True

    # -- one epoch -----------------------------------------------------------

    def _process(self, t: float, items: dict) -> None:
        L, c = self.layout, self.counters
        upd = []  # (sonde, slot, relay msg or None, radar msg or None) to update at t
        idle = []  # initialised sondes with nothing usable at t: predicted only
        for sonde, (rel, rad) in items.items():
            slot = self._slot(sonde)
            c.epochs += 1
            if math.isfinite(self._t[slot]):
                if not self._t[slot] < t:  # the filter is already at t (step called before)
                    c.stale += (rel is not None) + (rad is not None)
                    continue
            else:  # initialisation: the radar fix first, else a relay least-squares fix
                if L.uses_radar and rad is not None and self._init_from_radar(slot, rad):
                    rad = None
                elif L.uses_relay and rel is not None and rel.n >= 4 and self._init_from_relay(slot, rel):
                    rel = None
                else:
                    c.init_waiting += 1
                    continue
                self._t[slot] = t
                self._t_init[slot] = t
                self._t_meas[slot] = t
                self._nis[slot] = np.nan
            if rel is not None and rel.n == 0:
                c.relay_empty += 1
                rel = None
            if rel is None and rad is None:
                idle.append(slot)
            else:
                upd.append((sonde, slot, rel, rad))
        if idle:
            self._predict(np.array(idle), t)
            self._nis[idle] = np.nan
        if not upd:
            return
        if self._mon is not None:
            self._integrity(upd, t)
        dts = [t - float(self._t[u[1]]) for u in upd]
        for dt in sorted(set(dts)):
            group = upd if len(dts) == 1 else [u for u, d in zip(upd, dts) if d == dt]
            self._epoch_update(group, dt, t)

    def _measurement(self, group, dt: float = 1.0, t: float = 0.0) -> SondeMeasurement:
        """The joint measurement model of a group of sondes (padded to common rows)."""
        L, p = self.layout, self.params
        Bs = len(group)
        kw = {}
        cols = []
        U = 0
        if L.uses_relay:
            rels = [g[2] for g in group if g[2] is not None]
            if len(rels) == 1:  # one sonde: its satellites as they come
                union = rels[0].sat_ids
            else:  # satellite slots in order of first appearance
                union = list(dict.fromkeys(s for m in rels for s in m.sat_ids))
            U = len(union)
            col = None
            sat_pos, sat_vel = np.zeros((Bs, U, 3)), np.zeros((Bs, U, 3))
            mask = np.zeros((Bs, U), dtype=bool)
            zr, rr = np.zeros((Bs, 2 * U)), np.ones((Bs, 2 * U))
            ground = rels[0].ground_pos_ecef_m if rels else np.zeros(3)
            for b, g in enumerate(group):
                m = g[2]
                if m is None:
                    continue
                if m is not rels[0] and not np.array_equal(m.ground_pos_ecef_m, ground):
                    raise _MixedSites
                if m.sat_ids == union:
                    j = slice(0, U)
                else:
                    if col is None:
                        col = {sid: k for k, sid in enumerate(union)}
                    j = np.fromiter((col[s] for s in m.sat_ids), dtype=np.intp, count=m.n)
                sat_pos[b, j], sat_vel[b, j], mask[b, j] = m.sat_pos_ecef_m, m.sat_vel_ecef_m_s, True
                jj = j if isinstance(j, slice) else None
                if jj is not None:
                    zr[b, :U], zr[b, U:] = m.pseudorange_m, m.pseudo_doppler_m_s
                    rr[b, :U], rr[b, U:] = m.var_pseudorange_m2, m.var_pseudo_doppler_m2_s2
                else:
                    zr[b, j], zr[b, U + j] = m.pseudorange_m, m.pseudo_doppler_m_s
                    rr[b, j], rr[b, U + j] = m.var_pseudorange_m2, m.var_pseudo_doppler_m2_s2
            if L.nb and U:
                glon = np.fromiter((sid[:1] == "R" for sid in union), dtype=bool, count=U)
                slots = [g[1] for g in group]
                scale, white = self._relay_error_model(self._x[slots, 0:3], sat_pos, glon, dt)
                rr[:, :U] += np.where(mask, white, 0.0)
                bcol = np.full((Bs, U), -1, dtype=np.int64)
                for b, g in enumerate(group):
                    m = g[2]
                    if m is None or not m.n:
                        continue
                    c = self._bias_cols(g[1], m.sat_ids, t)
                    if m.sat_ids == union:
                        bcol[b] = c
                    else:
                        if col is None:
                            col = {sid: k for k, sid in enumerate(union)}
                        bcol[b, [col[sid] for sid in m.sat_ids]] = c
                over = mask & (bcol < 0)
                if over.any():  # no state left: the slow error taken as white
                    rr[:, :U] += np.where(over, scale * scale, 0.0)
                scale = np.where(bcol >= 0, scale, 0.0)
                kw.update(bias_col=bcol, bias_scale=scale)
            kw.update(sat_pos=sat_pos, sat_vel=sat_vel, relay_mask=mask, ground=np.asarray(ground), sat_ids=tuple(union))
            cols.append((zr, rr))
        if L.uses_radar:
            rads = [g[3] for g in group if g[3] is not None]
            site0 = rads[0].radar_pos_ecef_m if rads else None
            zd, rd = np.zeros((Bs, 3)), np.ones((Bs, 3))
            dmask = np.zeros((Bs, 3), dtype=bool)
            frac = p.radar_white_fraction if L.err is not None else 1.0
            for b, g in enumerate(group):
                m = g[3]
                if m is None:
                    continue
                if not np.array_equal(m.radar_pos_ecef_m, site0):
                    raise _MixedSites
                zd[b, 0], rd[b, 0] = m.slant_range_m, frac * m.var_range_m2
                dmask[b, 0] = True
                if m.angles_valid:
                    zd[b, 1], zd[b, 2] = m.az_rad, m.el_rad
                    rd[b, 1], rd[b, 2] = frac * m.var_az_rad2, frac * m.var_el_rad2
                    dmask[b, 1:] = True
            site, rot = self._radar_site(site0) if site0 is not None else (np.zeros(3), np.eye(3))
            kw.update(site=site, rot=rot, radar_mask=dmask)
            cols.append((zd, rd))
        z = np.concatenate([a for a, _ in cols], axis=-1)
        r = np.concatenate([b for _, b in cols], axis=-1)
        return SondeMeasurement(L, z, r, **kw)

    def _filter_for(self, group) -> list[str]:
        """The filter of each sonde's update; "auto": the UKF while the position is uncertain on
        the scale of its distance to the radar (or G) -- sqrt(trace P_pos) above
        ``auto_ukf_ratio`` x that distance, where the measurement functions curve within the
        uncertainty (a range-only coast near the radar) -- the EKF otherwise."""
        p = self.params
        if p.filter != "auto":
            return [p.filter] * len(group)
        if len(group) == 1:  # one sonde: plain floats
            _, slot, rel, rad = group[0]
            site = rad.radar_pos_ecef_m if rad is not None else rel.ground_pos_ecef_m
            x, P = self._x[slot], self._P[slot]
            d2 = (x[0] - site[0]) ** 2 + (x[1] - site[1]) ** 2 + (x[2] - site[2]) ** 2
            return ["ukf" if P[0, 0] + P[1, 1] + P[2, 2] > p.auto_ukf_ratio**2 * d2 else "ekf"]
        slots = [g[1] for g in group]
        sites = np.array([g[3].radar_pos_ecef_m if g[3] is not None else g[2].ground_pos_ecef_m for g in group])
        dx = self._x[slots, 0:3] - sites
        P = self._P[slots]
        spread2 = P[:, 0, 0] + P[:, 1, 1] + P[:, 2, 2]
        ukf = spread2 > p.auto_ukf_ratio**2 * np.sum(dx * dx, axis=1)
        return ["ukf" if u else "ekf" for u in ukf.tolist()]

    def _epoch_update(self, group, dt: float, t: float) -> None:
        """Predict the group over dt and update it with all its measurements of the epoch: one
        joint update, gated on its NIS; sondes failing the gate are redone block by block
        (relay, then radar), each block gated with the manoeuvre retry."""
        landed = [bool(self._landed[g[1]]) for g in group]
        if any(landed) and not all(landed):  # one transition per joint update
            for lnd in (False, True):
                self._epoch_update([g for g, x in zip(group, landed) if x == lnd], dt, t)
            return
        filts = self._filter_for(group)
        if len(set(filts)) > 1:
            for f in ("ekf", "ukf"):
                sub = [g for g, fi in zip(group, filts) if fi == f]
                if sub:
                    self._joint_update(sub, dt, t, f)
            return
        self._joint_update(group, dt, t, filts[0])

    def _joint_update(self, group, dt: float, t: float, filt: str) -> None:
        c, p = self.counters, self.params
        try:
            model = None
            if self._mon is not None:  # the monitor built this very group's model already
                model = self._mon_models.pop((dt, tuple(g[1] for g in group)), None)
            if model is None:
                model = self._measurement(group, dt, t)
        except _MixedSites:  # different ground receivers / radar sites: one sonde at a time
            for g in group:
                self._joint_update([g], dt, t, filt)
            return
        if self._mon is not None:
            model = self._guarded(model, group)
        if filt == "ukf":
            c.ukf_updates += len(group)
        slots = np.array([g[1] for g in group])
        c.relay_updates += sum(g[2] is not None for g in group)
        n_rad = sum(g[3] is not None for g in group)
        c.radar_updates += n_rad
        c.range_only_updates += sum(g[3] is not None and not g[3].angles_valid for g in group)
        lnd = bool(self._landed[slots[0]])
        tr = self._transition
        shared = lnd or self.layout.wind is None  # one (F, Q) for the group: the fused predict + update kernel
        x, P = self._x[slots], self._P[slots]
        if shared:
            F, Q = tr.F(None, dt, lnd), tr.Q(dt, lnd)
            x_pred, P_pred = x @ F.T, None
        else:
            x_pred, P_pred = self._propagate(slots, dt, lnd)
        if filt == "ekf":
            h, H = model.h_and_H(x_pred)
            if shared:
                xo, Po, nis = kernels.predict_joseph_update(F, Q, x_pred, P, model.z - h, H, model.R_diag(),
                                                            backend=p.backend)
            else:
                xo, Po, nis = kernels.joseph_update(x_pred, P_pred, model.z - h, H, r_diag=model.R_diag(),
                                                    backend=p.backend)
        else:
            if P_pred is None:
                P_pred = kernels.cov_predict(F, P, Q, backend=p.backend)
            xo, Po, _, nis = ukf_update(x_pred, P_pred, model.z, model, points=self._points, backend=p.backend)
        gate = self._gate(model.m_eff)
        bad = np.flatnonzero(~(np.asarray(nis) <= gate))
        self._x[slots], self._P[slots] = xo, Po
        self._t[slots] = t
        self._nis[slots] = nis
        if not bad.size:
            self._rejects[slots] = 0
            self._t_meas[slots[model.m_eff > 0]] = t  # an accepted measurement (rows left: not all masked out)
            self._window_test(slots, np.asarray(nis, dtype=float), model.m_eff, dt)
            return
        good = np.ones(slots.size, dtype=bool)
        good[bad] = False
        self._rejects[slots[good]] = 0
        self._t_meas[slots[good & (model.m_eff > 0)]] = t
        # block by block for the sondes that failed the joint gate
        bs = slots[bad]
        if P_pred is None:
            P_pred = kernels.cov_predict(F, P[bad], Q, backend=p.backend)
        else:
            P_pred = P_pred[bad]
        self._x[bs], self._P[bs] = x_pred[bad], P_pred
        total, used = np.zeros(bad.size), np.zeros(bad.size, dtype=bool)
        m_used = np.zeros(bad.size, dtype=np.int64)
        for part in (model.relay_part(bad), model.radar_part(bad)):
            if part is None:
                continue
            has = np.flatnonzero(part.m_eff > 0)
            if not has.size:
                continue
            sub = part.subset(has) if has.size < bad.size else part
            v = self._gated_update(bs[has], self._x[bs[has]], self._P[bs[has]], sub,
                                   "relay" if part.relay else "radar", dt, filt)
            total[has] += np.where(np.isfinite(v), v, 0.0)
            used[has] |= np.isfinite(v)
            m_used[has] += np.where(np.isfinite(v), sub.m_eff, 0)
        self._nis[bs] = np.where(used, total, np.nan)
        self._t_meas[bs[used & (m_used > 0)]] = t  # a block accepted (possibly under the manoeuvre hypothesis)
        m_all = model.m_eff.copy()
        m_all[bad] = m_used
        nis_all = np.asarray(nis, dtype=float).copy()
        nis_all[bad] = total
        self._window_test(slots, nis_all, m_all, dt)
        self._reacquire(bs, [group[i] for i in bad])

    # -- the integrity monitor (params.integrity) ------------------------------

    def _channel(self, sat_id: str) -> int:
        """The monitor channel of a relayed satellite (-1: none free). A new satellite takes the
        least recently used channel that has been unused for ``window + readmit_after`` epochs
        (its window then holds only healthy values and it is not excluded any more)."""
        c = self._chan_of.get(sat_id)
        if c is not None:
            return c
        c = int(np.argmin(self._chan_last))
        if self._mon_k - self._chan_last[c] < self._chan_age:
            return -1
        old = self._chan_sat[c]
        if old is not None:
            del self._chan_of[old]
        self._chan_of[sat_id], self._chan_sat[c] = c, sat_id
        return c

    def _channel_name(self, c: int) -> str:
        S = self._mon_S
        if c < S:
            return f"relay.{self._chan_sat[c]}"
        return f"{self.radar_id or 'radar'}.{('range', 'az', 'el')[c - S]}"

    def _integrity(self, upd, t: float) -> None:
        """Judge the epoch's measurements of the sondes in ``upd`` with the integrity monitor
        (at their predicted state), publish its events and keep, per sonde, which rows it
        leaves out and the variances it uses (applied by _guarded to every update of the epoch)."""
        L, c = self.layout, self.counters
        S, R = self._mon_S, self._mon_R
        m, n = 2 * S + R, L.n
        N = len(self._ids)
        end = self._cohorts[-1][1] if self._cohorts else 0
        if end < N:  # sondes seen for the first time: a cohort of their own (the monitor steps a batch together)
            self._cohorts.append([end, N, self._mon.init((N - end,), m, S + R)])
        self._mon_k += 1
        Z = np.full((N, m), np.nan)
        Hm = np.zeros((N, m, n))
        hm = np.zeros((N, m))
        rm = np.ones((N, m))
        X = np.where(np.isfinite(self._x), self._x, 0.0)
        P = np.where(np.isfinite(self._P), self._P, 0.0)
        dts = [t - float(self._t[u[1]]) for u in upd]
        self._mon_models = {}
        for dt in sorted(set(dts)):
            group = upd if len(dts) == 1 else [u for u, d in zip(upd, dts) if d == dt]
            try:
                models = [(group, self._measurement(group, dt, t))]
            except _MixedSites:
                models = [([g], self._measurement([g], dt, t)) for g in group]
            for grp, mdl in models:
                self._mon_models[(dt, tuple(g[1] for g in grp))] = mdl
            slots = np.array([g[1] for g in group])
            for lnd in (False, True):  # after _measurement: a new satellite's error state is reset
                ss = slots[self._landed[slots] == lnd]
                if ss.size:
                    X[ss], P[ss] = self._propagate(ss, dt, lnd)
            for grp, model in models:
                sl = np.array([g[1] for g in grp])
                h, H = model.h_and_H(X[sl])
                U = model.U
                rows = np.full(model.z.shape[1], -1, dtype=np.int64)
                if U:
                    for u, sid in enumerate(model.sat_ids):
                        if not model.relay_mask[:, u].any():
                            continue
                        ch = self._channel(sid)
                        if ch < 0:
                            c.integrity_unmonitored += int(model.relay_mask[:, u].sum())
                            continue
                        self._chan_last[ch] = self._mon_k
                        rows[u], rows[U + u] = ch, S + ch
                if R:
                    rows[2 * U:] = 2 * S + np.arange(R)
                ok = rows >= 0
                src, dst = np.flatnonzero(ok), rows[ok]
                mk = model.mask[:, src]
                zz = np.where(mk, model.z[:, src], np.nan)
                Z[sl[:, None], dst[None, :]] = zz
                hm[sl[:, None], dst[None, :]] = np.where(mk, h[:, src], 0.0)
                Hm[sl[:, None], dst[None, :]] = np.where(mk[..., None], H[:, src], 0.0)
                rm[sl[:, None], dst[None, :]] = np.where(mk, model.R_diag()[:, src], 1.0)
        # not judged (their rows enter the monitor as missing, the tracker's own gating and manoeuvre
        # logic handles them): a track in its warm-up, and a sonde whose rows mostly jump at once -- a
        # manoeuvre (the burst) or a track error moves every channel, a channel fault only its own
        p = self.params
        cfg = p.integrity
        sl = np.array([u[1] for u in upd])
        young = (t - self._t_init[sl]) < p.integrity_warmup_s
        has = np.isfinite(Z[sl])
        nu = np.where(has, Z[sl] - hm[sl], 0.0)
        Hs = Hm[sl]
        hph = np.sum((Hs @ P[sl]) * Hs, axis=-1)
        jumps = (np.abs(nu) >= cfg.jump_sigma * np.sqrt(hph + rm[sl])) & has
        common = jumps.sum(axis=1) > p.integrity_common_fraction * np.maximum(has.sum(axis=1), 1)
        skip = young | common
        c.integrity_warmup += int(young.sum())
        c.integrity_common_mode += int((common & ~young).sum())
        Z[sl[skip]] = np.nan
        judged = set(sl[~skip].tolist())
        self._guard = {}
        for co in self._cohorts:
            a, b = co[0], co[1]
            got = {}

            def judge(x, P_, z, gm, **kw):  # the monitor's verdict only: the tracker's own update follows
                got["inert"], got["r"] = np.asarray(gm.inert), np.asarray(gm.R_diag())

            _, co[2], rep = self._mon.step(co[2], X[a:b], P[a:b], Z[a:b], _Prepared(hm[a:b], Hm[a:b], rm[a:b]),
                                           self._mon_ch, update=judge, backend=self.params.backend)
            c.integrity_epochs += 1
            has = np.isfinite(Z[a:b])
            c.integrity_rows_left_out += int((has & got["inert"]).sum())
            c.integrity_exclusions += int(rep.newly_excluded.sum())
            c.integrity_readmissions += int(rep.readmitted.sum())
            evs = self._events(rep, self._mon_ch, t, lambda bi, ch, a=a: f"{self._ids[a + bi[0]]}.{self._channel_name(ch)}",
                               cfg)
            c.integrity_events += len(evs)
            for u in upd:
                if a <= u[1] < b and u[1] in judged:
                    self._guard[u[1]] = (got["inert"][u[1] - a], got["r"][u[1] - a])

    def _guarded(self, model: SondeMeasurement, group) -> SondeMeasurement:
        """The group's measurement model with the monitor's verdict of this epoch applied: the
        rows it left out masked (z = 0, r = 1: no information, no NIS), the others with the
        variance it used (the nominal one, or its robust / adaptive inflation)."""
        S = self._mon_S
        U = model.U
        z, r = model.z.copy(), model._r.copy()
        keep = np.ones(z.shape, dtype=bool)
        rows = np.full(z.shape[1], -1, dtype=np.int64)
        for u in range(U):
            ch = self._chan_of.get(model.sat_ids[u], -1)
            if ch >= 0:
                rows[u], rows[U + u] = ch, S + ch
        if self._mon_R:
            rows[2 * U:] = 2 * S + np.arange(self._mon_R)
        ok = rows >= 0
        src, dst = np.flatnonzero(ok), rows[ok]
        for b, g in enumerate(group):
            gd = self._guard.get(g[1])
            if gd is None:
                continue
            inert, rr = gd[0][dst], gd[1][dst]
            keep[b, src] = ~inert
            r[b, src] = np.where(inert, r[b, src], rr)
        if keep.all() and np.array_equal(r, model._r):
            return model
        z = np.where(keep, z, 0.0)
        r = np.where(keep, r, 1.0)
        kw = {"row_mask": keep}
        if model.relay:
            kw.update(sat_pos=model.sat_pos, sat_vel=model.sat_vel, relay_mask=model.relay_mask, ground=model.ground,
                      bias_col=model.bias_col, bias_scale=model.bias_scale, sat_ids=model.sat_ids)
        if model.radar:
            kw.update(site=model.site, rot=model.rot, radar_mask=model.radar_mask)
        return SondeMeasurement(self.layout, z, r, **kw)

    def _window_test(self, slots, nis, m, dt: float) -> None:
        """Sliding-window manoeuvre test: the NIS summed over the last ``manoeuvre_window``
        epochs against the chi-square quantile of its summed dof catches a slow drift away
        from the model (e.g. the radar alone after the burst) that no single epoch's gate
        sees; then the manoeuvre covariance is added to the posterior and the window restarts."""
        W = self.params.manoeuvre_window
        if W is None or self.params.gate_prob is None:
            return
        if slots.size == 1:  # one sonde: plain floats, the same arithmetic
            slot, v, mi = int(slots[0]), float(nis[0]), int(m[0])
            if not math.isfinite(v):
                v, mi = 0.0, 0
            k = int(self._win_k[slot]) % W
            self._win_S[slot] += v - self._win_nis[slot, k]
            self._win_M[slot] += mi - self._win_m[slot, k]
            self._win_nis[slot, k], self._win_m[slot, k] = v, mi
            self._win_k[slot] += 1
            S, M = float(self._win_S[slot]), int(self._win_M[slot])
            if self._win_k[slot] < W or not S > M or not S > self._gate(np.array([M]))[0]:
                return
            self._P[slot] += (S / M) * self._transition.boost(dt)
            self._t_init[slot] = self._t[slot]  # a manoeuvre: the monitor waits (integrity_warmup_s)
            self._win_nis[slot], self._win_m[slot], self._win_k[slot] = 0.0, 0, 0
            self._win_S[slot], self._win_M[slot] = 0.0, 0
            self.counters.window_manoeuvre += 1
            return
        ok = np.isfinite(nis)
        nis, m = np.where(ok, nis, 0.0), np.where(ok, m, 0)
        k = self._win_k[slots] % W
        self._win_S[slots] += nis - self._win_nis[slots, k]  # running sums over the window
        self._win_M[slots] += m - self._win_m[slots, k]
        self._win_nis[slots, k], self._win_m[slots, k] = nis, m
        self._win_k[slots] += 1
        S, M = self._win_S[slots], self._win_M[slots]
        cand = (self._win_k[slots] >= W) & (S > M)  # the quantile is above M: test only these
        if not cand.any():
            return
        hit = np.zeros(slots.size, dtype=bool)
        hit[cand] = S[cand] > self._gate(M[cand])
        if hit.any():
            hs = slots[hit]
            # scaled by how far the window's NIS exceeds its expectation (a burst seen by the
            # radar alone is a 40 m/s surprise, not one acceleration step)
            scale = (S[hit] / M[hit])[:, None, None]
            self._P[hs] += scale * self._transition.boost(dt)
            self._t_init[hs] = self._t[hs]
            self._win_nis[hs], self._win_m[hs], self._win_k[hs] = 0.0, 0, 0
            self._win_S[hs], self._win_M[hs] = 0.0, 0
            self.counters.window_manoeuvre += int(hit.sum())

    def _reacquire(self, slots, group) -> None:
        """Re-initialise sondes whose relay or radar block was rejected ``reacquire_after``
        epochs in a row (a lost track: e.g. after a long range-only coast), from this epoch's fix."""
        n = self.params.reacquire_after
        if n is None:
            return
        for slot, (_, _, rel, rad) in zip(slots, group):
            k = self._rejects[slot]
            if k.max() < n:
                continue
            ok = False
            if k[1] >= n and rad is not None:
                ok = self._init_from_radar(slot, rad, count=False)
            if not ok and k[0] >= n and rel is not None and rel.n >= 4:
                ok = self._init_from_relay(slot, rel, count=False)
            if ok:
                self.counters.reacquired += 1
                self._rejects[slot] = 0
                self._t_init[slot] = self._t_meas[slot] = self._t[slot]


class _Prepared:
    """A measurement model already evaluated at the monitor's prior: h (N, m), H (N, m, n) and
    the R diagonal (N, m) of the monitor's fixed row layout."""

    def __init__(self, h, H, r):
        self._h, self._H, self._r = h, H, r

    def h_and_H(self, x):
        return self._h, self._H.copy()

    def R_diag(self):
        return self._r


class _MixedSites(Exception):
    """Sondes of one epoch heard through different ground receivers or radar sites."""
