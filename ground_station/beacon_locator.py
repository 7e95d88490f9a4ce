"""Seed 002 ground-station beacon locator: a filter on the beacon from range and Doppler at N UAVs.

The decomposition the seed requires (eqs 10-11): every UAV navigates on board (its own GNSS
EKF) and sends, with each beacon measurement, its own estimate [U_i, V_i] and covariance
P_i (``sitl.bus.BeaconMeasurement`` carries that snapshot); this one computer estimates the
beacon from those messages alone.  It never sees the truth nor the UAVs' raw GNSS.

Why the filter does not run in ECEF
-----------------------------------
On the seed's geometry the beacon is ~230 km from three UAVs that are 15-45 km apart and
nearly collinear.  The ranges then fix the beacon's distance from the UAVs' line and its
position along it to metres, but hardly its angle phi about the line: turning the beacon on
that circle (radius ~230 km; the turn is mostly a change of height) changes the ranges
only through the UAVs' small departures from a line.  Its information is ~1-3 km per
epoch, a million times weaker (in variance) than the radial one.  An EKF in ECEF fails on
this banana: linearised at an estimate a few km round the circle, its range normal is
tilted by (a few km)/(230 km) and the strong radial information leaks into the weak
direction at every update -- measured here on the seed run, the ECEF EKF's height sigma fell
to ~500 m while its error grew to 20-50 km (NEES ~1e6), and an ECEF UKF did no better;
with the Jacobians taken at the truth (an oracle) the same filter stayed consistent.  The
curvature is removed by coordinates in which the circle is a coordinate line:

    formation-cylindrical coordinates of the beacon (per trial, rebuilt every epoch):
    c the centroid of the present UAVs' estimates, a their principal axis, e1 the unit
    normal from the axis towards the predicted beacon, e2 = a x e1;
    B = c + s a + rho (cos phi e1 + sin phi e2),  y = [s, rho, phi, v_s, v_rho, v_phi],
    the velocity in the local basis (a, e_rho, e_phi) at B.

With collinear UAVs the ranges depend on (s, rho) only and the beacon's own velocity enters
the Doppler without phi (u has no e_phi component), so the weak pair (phi, v_phi) is
separated from the strong ones and no product of two uncertain quantities (phi and an
ECEF velocity) appears in the Doppler.  The frame changes a little between epochs (the
formation moves ~100 m and turns ~1 mrad per second); the state is carried across by the
exact conversion (mean) and its Jacobian (covariance).  A formation that is not line-like
(second singular value > ``axis_ratio`` of the first) keeps the previous axis.  Whether a
track uses these coordinates is decided when it starts (:func:`formation_frame`): only for a
line-like formation with the beacon more than 3 formation lengths from its axis (the seed's
case); otherwise (UAVs spread in two dimensions, as in the experiment's 5-30 UAV runs, or a
beacon near or inside the formation, where the coordinates would be singular) the state
stays plain ECEF [B, V_B] and the filter is an ordinary EKF.

Motion model: constant velocity in ECEF with white acceleration of PSD ``q_m2_s3``
(isotropic, so the same in any rotated basis), mapped into the cylindrical state by the
conversion's Jacobians.  q = 1 m^2/s^3 by default: the beacon's acceleration is
deterministic (speed, heading and climb sinusoids, up to ~0.3 m/s^2, periods 314 s) and
the weak direction is corrected only slowly, so the model must allow a vertical speed
change of ~10 m/s in ~80 s; with the UAVs' positions exact (so that only the beacon model
is tested) the time-averaged 6-state NEES in the filter's coordinates over 10 trials was
~13 at q = 0.1, ~9 at 0.3, ~5.4 at 1 and ~5 at 3 (6 is consistent).

Output: the Gaussian the filter carries lives in the cylindrical coordinates; its image in
ECEF is a banana whose bend along the weak direction (delta^2 / 2 rho = 35 m for delta =
4 km) dwarfs the ~3 m radial sigma.  The published ECEF mean and covariance are therefore
the unscented transform of (y, P) (sigma points at +-sqrt(6) sigma, W0 = 0), i.e. the
moments of that banana to second order, not the linearised image.

``motion="position"`` keeps the seed's own beacon filter for comparison
(:func:`position_only_step`, ECEF): predict B+ = B + T V_hat_B with V_hat_B the weighted
least-squares Doppler solution at the prior (eq 8, any N >= 3), F = I + T dV_hat/dB (central
differences, the seed's dPsi^-1 U1/dX term), process noise T^2 Cov(V_hat_B) (eq 11's
Psi^-1 U2 D U2' Psi^-T); update with the ranges only.  On the seed geometry its Doppler
velocity solve is ill-conditioned (nearly parallel lines of sight: the velocity across them,
mostly vertical, is amplified from 0.1 m/s Doppler noise to tens of m/s).

Measurements and the UAVs' own uncertainty
------------------------------------------
``filters.beacon.ObserverRangeDoppler`` at the UAVs' estimates, z_i = [r_i, rdot_i].
``observer_uncertainty="inflate"`` (default): R_i = diag(var_r, var_v) + kappa J_i P_i J_i',
the first-order effect of UAV i's navigation error (a consider term, white by construction);
``"ignore"``: R_i = diag(var_r, var_v), the UAVs taken as exact.  kappa = 1 + 2 tau / dt
with tau = ``uav_error_corr_s``: the UAVs' errors are the outputs of their own filters and
persist for tens of seconds (seed run, three satellites: position-error autocorrelation
0.9 at 10 s, 0.6 at 50 s; velocity 0.67 at 1 s, 0.3 at 10-50 s), and K samples of an error
with correlation time tau carry the information of only ~K / (1 + 2 tau / dt) independent
ones -- treated as white with kappa = 1 the filter is over-confident by that factor
(measured on the seed run, 20 trials, position ANEES after 100 s, 99 % band 1.8-4.6:
223 (three satellites) and 5e4 (GPS constellation) at kappa = 1, 4.5 and 3.2 at kappa = 101).  ``uav_error_corr_s``
= 0 gives the plain consider term R + J P J'.

kappa = 1 + 2 tau / dt assumes the filter averages over much longer than tau.  On the printed
geometry (a prior start, the beacon among the UAVs) its memory is short and the filter is
over-cautious (ANEES 0.57 against the band 1.78-4.60, 20 trials).  A kappa from the filter's
own memory along each measured direction (retention = posterior / predicted variance of H x)
was tried and is not enough: the Doppler rows have a one-epoch memory (kappa ~1) but their
correlated errors enter the position through the dynamics, and on the geodetic geometry the
km-wide weak direction is built from many epochs while the radial one has a short memory
(measured: 1 of 20 printed trials lost, geodetic ANEES 124 / 2131 against 9 / 112).
``observer_uncertainty="consider"`` (opt-in; the live ground station's locator,
ground_station.node.beacon_locator_config) does it exactly for a Gauss-Markov model of the
UAVs' errors: they are Schmidt states (correlation times ``uav_error_corr_s`` for position,
``uav_vel_error_corr_s`` for velocity, covariance P_i from each message), the filter carries
their cross-covariance with its state per UAV (:func:`_consider_step`; fixed observer slots
per UAV id), so each direction of the state has its own memory.  With both times 0 it equals
"inflate" with kappa = 1 (test).  The UAVs' error transition is Gauss-Markov in each UAV's
whitened error (its Cholesky factors at the two epochs), so that the joint covariance stays
consistent with the P_i each message carries while the UAVs' own filters converge (their
covariance halves in the first second of the seed run).  A track's first ``acquire_s``
(50 s) run as "inflate" (cross-covariances 0), then the Schmidt states take over: started
at once, 1-2 of 20 printed trials locked onto the reflection through the three UAVs' plane
in the first ~20 s (kappa = 101 is sluggish enough there to keep the prior's velocity); the
centralised filter is started the same way (from the locator's estimate at 50 s).  Hypotheses
(the blind start's mirror) are scored as by "inflate", the UAVs' errors white with their
per-epoch variance: with the Schmidt S the log det term favours whichever side projects less
of the UAVs' covariance.  Measured on the printed run (``skyfuse experiment beacon``, 20
trials, tau 50 / 50 s, 99 % band of the 20-trial average 1.78-4.60), position ANEES after
100 s, three satellites / constellation: seed 1 2.60 / 2.63 (inflate 0.57 / 0.59), RMSE 15.2
/ 10.3 m (inflate 16.3 / 10.4); seed 2 3.14 / 2.61 (inflate 0.70 / 0.61), RMSE 17.3 / 10.8 m
(inflate 17.4 / 11.8) -- the experiment's locator.  Its largest errors per axis are larger
than inflate's (median of trial max, seed 1, three satellites: 35 / 33 / 14 m against 32 / 25
/ 13 m), mostly at 100-200 s.  On the geodetic reading (blind start, 5 trials) both are
over-confident: ANEES 24 / 113 (inflate 9.1 / 112), RMSE 6.9 / 9.1 km (inflate 7.8 / 11.1).  The
UAVs' errors are not first-order Gauss-Markov (printed run, constellation:
range-projected position error rho 0.93 at 10 s, 0.66 at 50 s, 0.39 at 100 s; Doppler-
projected velocity error rho 0.4 at 1 s then ~0.1 up to 50 s); correlation times far from
the UAVs' own filters' behaviour (tau_v = 1 s) can make the joint covariance inconsistent
with the P_i the UAVs send and the update lose positive definiteness.

A restarted UAV (its onboard filter re-initialised by a least-squares fix) is a new
incarnation of its source (the bus header's ``incarnation``, schema 3): its navigation error
has nothing to do with the dead process's, so when a slot's UAV sends a later incarnation than
before, the slot's cross-covariances with the track (and the mirror hypothesis) and its last
covariance are reset -- the slot then starts as a UAV never seen would (test); counted as
``uav_incarnations``.

Each observer's 2x2 R block is whitened by its Cholesky factor and the update runs as a
scalar sequential Joseph update (``filters.kernels.joseph_update``) batched over trials;
absent or rejected observers have zero rows (gain exactly 0), so every trial may have its
own N.

What the locator takes in, and what it rejects (``rejected``, ``counters``)
--------------------------------------------------------------------------
The transport has already rejected malformed / NaN payloads (counted by the transport).
``on_message`` rejects and counts: a message for another beacon, a range or range rate
outside plausible limits, a UAV position off the Earth's neighbourhood, a UAV covariance
with a position sigma above ``max_uav_pos_sigma_m`` or a velocity sigma above
``max_uav_vel_sigma_m_s`` (an absurd navigation solution would be believed otherwise),
a message older than the lag window (``too_late``); ``counters`` has duplicates ((source,
seq) seen before) and messages of runs it does not track.  ``step`` gates each observer by its own 2-dof
normalised innovation (chi-square tail ``gate_prob``) and counts the rejections.

Initialisation
--------------
A single epoch is a poor fix on this geometry: ``sitl.radio.beacon_link.multilaterate``
errs by 10-200 km (the circle above, and the mirror: three UAVs are coplanar, and the
beacon's reflection through their plane has exactly the same ranges).  The locator
accumulates ``init_epochs`` epochs with >= 3 valid observers, takes the closed-form
multilateration of each (UAV estimates as anchors) and the component-wise median as the
start, then solves for [B(t_K), V_B] by Levenberg-Marquardt on all ranges and Dopplers of
the window (constant velocity across it, so the window must stay short: the beacon
accelerates) with two weak priors: the beacon's height within ``init_height_sigma_m`` of the
UAVs' mean height (an emitter in the same airspace: a few km, not hundreds -- without it
the first minutes are spent on the circle) and each velocity component ~ N(0,
``init_vel_sigma_m_s``^2).  The circle is handled by scanning the height (pinned) over
+-3 sigma and keeping the best fit; the mirror by doing that from the start and from the
start turned by 180 deg about the UAVs' axis.  The better of the two is the track, the
other a mirror hypothesis carried along as a second filter: the reflection of a track
through the formation's turning plane accelerates, so the two tracks' summed -2
log-likelihoods (every present observer, gated or not) drift apart; the likelier is kept as
soon as they differ by ``init_resolve_llr`` (a sequential likelihood-ratio test), at the
latest after ``init_resolve_s``.  Until then the published estimate is the two-track
mixture (weights from the likelihoods, moments matched: the MMSE estimate, whose covariance
spans both sides while they are undecided).  Measured on 20
trials of the seed run (10 three-satellite, 10 constellation): the scores part by 150 within
27-99 s in 19 trials and 332 s in one, whose true track had first drifted 132 towards the
mirror (hence the high threshold); the largest excursion of any other trial towards the
wrong side was 16.  The start covariance
is the window's inverse information times ``init_cov_scale``.

Initialisation from a prior (``init="prior"``)
-----------------------------------------------
When the scenario gives the beacon's prior -- the seed's filter starts from
X(0)^ = M[X(0)] with P(0) = M[(X(0) - X(0)^)(X(0) - X(0)^)'] -- every trial starts at the
first epoch it sees from ``prior_mean`` (6,) [B, V_B] (ECEF) and ``prior_cov`` (6, 6), and
that epoch's measurements are the first update: no window, no multilateration, no mirror
hypothesis.  The state is then plain ECEF: the cylindrical coordinates serve the blind
start (a km-wide banana far from a line-like formation); a prior of tens of metres needs
none, and on the seed's printed geometry the beacon starts inside the formation, where
those coordinates are singular.  Nothing else changes (gating, modes, UAVs joining and
leaving).  The prior is the scenario's, never the truth: the experiment draws each trial's
true start from it.  ``init="multilateration"`` (default) is the blind start above.

Formation too small for its own errors (``min_formation_sigmas``)
------------------------------------------------------------------
In a track in plain ECEF (the prior start; a formation spread in two dimensions; a beacon
near the formation), an epoch whose >= 3 present UAVs span less than ``min_formation_sigmas``
(12) times their own RMS per-axis position sigma (second singular value of their estimated
positions) gives no beacon measurement: their plane, hence the side of it the beacon is on,
is noise (12: the plane's orientation known to ~5 deg).  (Not in the formation-cylindrical coordinates, made for a line-like formation far
from the beacon: applied there, to the geodetic reading's nearly collinear UAVs, it delayed
the blind start and took the three-satellite RMSE from 7.8 to 13.4 km, 5 trials.)  On the
printed geometry all vehicles leave one point and the UAVs' filters start cold (52 m error
at t = 0, 17 m at 10 s), so for the first ~11-16 s the estimated formation is a few metres
wide with tens of metres of error; updating then drove the velocity away from the prior's
(steadily, 8 m/s in 10 s) and the track onto the beacon's reflection through the UAVs' plane.
Measured (printed run, 20 trials per seed and case, 200 s, lost = error > 300 m after 100 s):
without the limit "inflate" lost 9 of 200 trials in seeds 1-5; with 5 sigmas 2 of 200 (seed
4's trial 11, whose beacon starts 2 sigma off and crosses the UAVs' plane just as the
formation resolves) and 7 of 280 in seeds 1-7; with 8, 2 of 280; with 12, none of 400 in
seeds 1-10 (12 was chosen on seeds 2, 4 and 7 among 3, 5, 8, 12, 20; seeds 8-10 held out),
"consider" and "inflate" alike.  The track coasts on the prior meanwhile (printed run: the
first ~20 s with the GPS constellation, ~28 s with three satellites; mode "coast"), counted
in ``counters["epochs_formation_unresolved"]``; the estimates after 100 s are unchanged to
the reported digits where no trial is lost.  A two-sided start was tried first and dropped:
the prior split in its two halves by the side of the UAVs' plane the beacon is on at 60 s,
one track per half; decided by the summed -2 log-likelihoods it picked the mirror in 17-20 of
20 trials (the two tracks are mirror images with the same ranges and Dopplers, and the log
det term favours one geometry), by the Mahalanobis sums in 1-8, by the prior's density at
each track's RTS-smoothed start it kept the right half, but in the lost trials both halves'
tracks crossed to the mirror side, so it rescued none that the limit does not.

Fewer than three UAVs
---------------------
UAVs may join and leave: each epoch uses the observers present.  With fewer than 3 the
update still uses what is there (one or two ranges and Dopplers are valid information)
while the covariance grows in the unobserved directions; with none the filter only
predicts.  The Estimate's ``mode`` says which: "fused" (>= 3 observers used), "degraded"
(1-2), "coast" (0), and "lost" once ``coast_s`` (time since the last epoch with >= 3)
exceeds ``max_coast_s`` -- the estimate is still published, with its large covariance.
Before initialisation nothing is published.

Bus
---
``BeaconLocator(transport, run_ids=[...], beacon_id="b1")`` subscribes once to
``*/uav/*/beacon/<beacon_id>``; each run id is one Monte Carlo trial (runs share a bus by
their key prefix) and one row of the batch.  ``on_message(key, msg)`` collects an epoch's
measurements; ``step(t_gps_s)`` processes the epoch for every trial at once and publishes
one ``Estimate`` per initialised trial on ``<run>/gs/estimate/beacon/<beacon_id>``.
``process(t_gps_s, obs)`` is the same filter step on arrays (:class:`ObserverEpoch`).

Integrity (issue 6, opt-in: ``LocatorConfig(integrity=IntegrityConfig(...))``)
--------------------------------------------------------------------------------
filters.integrity.IntegrityMonitor judges each UAV link (channel: its range and Doppler rows)
once per epoch, on each primary track's prior: right after the epoch's innovations nu and
their covariance S are built (S = H P H' + R; "consider": the Schmidt S of the batched update,
with the cross-covariances), the monitor gets z = nu, h = 0, H = 0, R = diag(S), so beta =
nu / sqrt(S) exactly.  A link with a row failing the jump test, or excluded (jumps on
``persist`` epochs, or a window test), is left out of the update (neither used nor counted as
gated) and out of the mirror hypothesis's update and score; iterated updates keep that set.
The per-link chi-square gate stays.  Each UAV id keeps a fixed observer slot (its monitor
column; at most ``integrity_max_links`` judged, the others used unjudged and counted).  A
trial whose links mostly jump at once (more than ``integrity_common_fraction`` of its present
links) is not judged that epoch: the track moved, not a link.  Links are left out only while at
least ``integrity_min_links`` (3) of a trial's present links stay in: three UAVs' ranges and
Dopplers fix the 6 states with no redundancy, and on the printed run (3 UAVs, 20 trials) leaving
one out let the track drift until the faulty link looked clean and was readmitted (a 30 m range
step: RMSE 230 m against the plain locator's 125 m); there the monitor only detects.  Events
(sitl.integrity_events: step, ramp, outlier, readmit) go on ``<run>/gs/integrity/<channel>``
from ``<source_id>.integrity``, channel ``<beacon_id>.uav<uav id>`` (``.slot<i>`` when fed
through ``process`` without UAV ids); counters ``integrity_*``.  Recommended settings: no
bias test, no Huber, no adaptive R (``INTEGRITY``): the UAVs' navigation errors are
correlated over tens of seconds, so the innovations are not white and the bias test would
over-alarm.

Late measurements, duplicates, a bad network (issue 8)
------------------------------------------------------
A measurement that arrives after its epoch was processed is used, not dropped, while it is at
most ``lag_window_s`` (5 s) old: every step keeps a snapshot of what a step writes (the track
and hypothesis arrays, the consider states with "consider", the start windows while a trial
has not started; the integrity monitor's state is replaced per epoch, so kept by reference)
and the epoch's inputs; a late measurement is added to its epoch's inputs and the next step
restores the state from before that epoch and re-runs it and the later ones, every trial of
the batch together (an untouched trial re-runs to the identical numbers), then processes the
new epoch.  Only that epoch's Estimates are published: what went out at t used what had
arrived by t (a fixed-lag filter's real-time output), re-runs publish nothing and their
integrity events are not sent again (counted: ``late_accepted``, ``reprocess_runs``,
``reprocessed_epochs``); the counters of the re-run epochs are taken back first, so each is
counted once.  Older than the window: ``rejected["too_late"]``.  ``lag_window_s = 0`` keeps no
history and drops a late one as ``stale`` (the behaviour before).  Cost: a snapshot is ~43 us
(20 trials, "consider"; a step of that batch ~10 ms).  On the bench's case (run_case as
``skyfuse bench beacon`` runs it, three satellites, locator stage, best of interleaved rounds,
load ~5 on 2 cores): 1 trial x 500 s, 4.54 ms/epoch with the 5 s window against 4.65 without
(same estimates bit for bit), 11.6 ms/epoch (2.5x) with every measurement 2 s late (2-3
epochs re-run per step); 20 trials x 200 s, 9.35 against 9.74 ms/epoch, 21.6 (2.2x) 2 s late.
Duplicates are discarded by (run/source id, seq) (``counters["duplicate"]``, each copy once)
after the run and beacon checks, before the plausibility ones; a different message for a UAV
and epoch already held counts ``duplicate_epoch``.  After a partition (every UAV link silent)
the tracks coast (mode "coast", "lost" after ``max_coast_s``) with the covariance growing, and
re-converge on the first epochs back: the per-observer gate is judged with that grown
covariance, so the returning data are not refused.  Measured (``sitl.app.experiments.network_faults``'
beacon runs: printed geometry, three satellites, 3 UAVs, 8 trials, 300 s, links down from 150
s): after a 30 s partition the 10 s RMSE is within 2x the fault-free run's from the heal on
(8 s with the window ending at the time instead of starting there; nothing gated), after 60 s
likewise (9 s); 20 % loss: RMSE 25.6 m against 25.2 m; delay 1 / 2 s (+-20 % jitter): 25.4 /
25.7 m.

numpy/scipy plus sitl (bus, geodesy, multilateration, integrity events) and filters; never
imports vehicles.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from collections import Counter
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.stats

from filters import kernels
from filters.beacon import OBSERVER_UNCERTAINTY
from filters.integrity import IntegrityConfig, IntegrityMonitor
from filters.models import ConstantVelocity
from ground_station import _lagwindow
from sitl.bus import BeaconMeasurement, Estimate, SequenceTracker, key_for, parse_key
from sitl.geodesy import ecef_to_geodetic
from sitl.integrity_events import IntegrityEventPublisher
from sitl.radio.beacon_link import multilaterate

__all__ = [
    "LocatorConfig",
    "ObserverEpoch",
    "Frame",
    "formation_frame",
    "cyl_to_ecef",
    "ecef_to_cyl",
    "ut_to_ecef",
    "InitFix",
    "init_fix",
    "uav_error_transition",
    "cyl_step",
    "position_only_step",
    "BeaconLocator",
    "MOTIONS",
    "INITS",
    "INTEGRITY",
]

MOTIONS = ("cv", "position")
# the integrity settings for the locator (module docstring, "Integrity")
INTEGRITY = IntegrityConfig(bias_alpha=None, huber_c=None, adapt_r=False)
INITS = ("multilateration", "prior")
_EARTH_R_MIN_M, _EARTH_R_MAX_M = 6.2e6, 7.0e6  # a UAV position outside this shell is absurd
_UT_C2 = 6.0  # n + lambda of the sigma points (alpha = 1, kappa = 0): +-sqrt(6) sigma, W0 = 0


@functools.lru_cache(maxsize=64)
def _chi2_isf(p: float, dof: int) -> float:
    return float(scipy.stats.chi2.isf(p, dof))


@functools.lru_cache(maxsize=64)
def _cv_matrices(q: float, dt: float):
    """(F, Q) of the constant-velocity model (memoised: built every step otherwise)."""
    m = ConstantVelocity(3, q=q)
    F, Q = np.asarray(m.F(None, dt), float), np.asarray(m.Q(dt), float)
    F.flags.writeable = False
    Q.flags.writeable = False
    return F, Q


def _pos(name, v):
    v = float(v)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
    return v


def _nonneg(name, v):
    v = float(v)
    if not (math.isfinite(v) and v >= 0):
        raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
    return v


@dataclass(frozen=True)
class LocatorConfig:
    """Settings of the beacon locator (module docstring).

    q_m2_s3: acceleration PSD of the beacon's constant-velocity model, m^2/s^3.
    observer_uncertainty: "inflate" (R + kappa J P_i J'), "ignore" (R only) or "consider" (the
        UAVs' errors as Schmidt states, motion "cv" only; module docstring).
    uav_error_corr_s: correlation time tau of the UAVs' navigation errors; kappa = 1 + 2 tau / dt
        ("consider": of their position errors).
    uav_vel_error_corr_s: "consider" only: correlation time of the UAVs' velocity errors.
    motion: "cv" (the cylindrical [B, V_B] filter) or "position" (the seed's position-only filter).
    init_epochs: epochs with >= 3 observers accumulated before the first estimate.
    init_height_sigma_m: prior sigma of the beacon's height about the UAVs' mean height, m
        (inf: no height prior, no height scan).
    init_vel_sigma_m_s: prior sigma of each beacon velocity component, m/s.
    init_cov_scale: the initial covariance is the window's inverse information times this.
    init_resolve_s: the longest the mirror hypothesis is carried, s (0: not carried).
    init_resolve_llr: the mirror is resolved as soon as the two tracks' summed -2 log-likelihoods
        differ by this much (a likelihood ratio of exp(llr / 2)), else at init_resolve_s.
    gate_prob: an observer whose NIS exceeds the chi-square (1 - gate_prob) quantile is
        rejected (2 dof; 1 dof for the position-only ranges).
    max_uav_pos_sigma_m, max_uav_vel_sigma_m_s: a UAV snapshot whose largest position
        (velocity) standard deviation exceeds this is rejected.
    max_range_m, max_range_rate_m_s: plausibility limits of a beacon measurement.
    max_coast_s: time without >= 3 observers after which the mode reads "lost".
    axis_ratio: a formation whose second singular value exceeds this fraction of the first
        is not line-like; it keeps the previous axis.
    position_q_m2_s3: extra process noise PSD of the position-only filter (numerical floor).
    backend: covariance kernels (None: the default, numba when installed).
    init: "multilateration" (blind start from a window of epochs) or "prior" (start from
        prior_mean (6,) and prior_cov (6, 6) over ECEF [B, V_B] at the first epoch).
    update_iterations: 1 (EKF) or more: an iterated EKF update (Gauss-Newton on the epoch's
        ranges and Dopplers, relinearised at each iterate; the gate decided at the first).
        For ranges comparable with the state's uncertainty (a beacon that starts among the
        UAVs), where one linearisation at the prediction is poor.  At most this many: the
        iterations stop once no row's ECEF iterate moves by 1 mm (mm/s) or more, or once
        relinearising changes no used innovation by 1e-3 of its noise sigma.
    acquire_s: "consider" only: a track's first acquire_s run as "inflate" (module docstring).
    min_formation_sigmas: an epoch whose >= 3 UAVs span less than this many times their RMS
        position sigma gives no beacon measurement (0: off; module docstring).
    integrity: the integrity monitor (filters.integrity) on each UAV link's range and Doppler
        (module docstring, "Integrity"); None: off.
    integrity_max_links: monitor channels (UAV ids beyond this many are used unjudged, counted).
    integrity_common_fraction: an epoch of a trial whose links mostly jump at once (more than
        this fraction of its present links) is not judged: the track moved, not one link.
    integrity_min_links: the verdict leaves links out of a trial's update only while at least this
        many of its present links stay in (3: ranges and Dopplers of 3 UAVs fix the 6 states with
        no redundancy; below that an exclusion makes the track unobservable and the monitor
        detect-only for that trial and epoch).
    lag_window_s: out-of-sequence measurements (module docstring, "Late measurements"): a
        measurement for an epoch already processed and at most this old (simulation time)
        is used by re-processing from that epoch; older ones are dropped (``too_late``).
        0: the old behaviour (no history kept; a late measurement is dropped as ``stale``).
    second_order_r: add the variance of the ranges' and Dopplers' second-order terms
        (:func:`second_order_var`, at the predicted state and covariance) to R -- for the
        same case; off by default (in the cylindrical coordinates the curvature is the
        coordinates' business).
    """

    q_m2_s3: float = 1.0
    observer_uncertainty: str = "inflate"
    uav_error_corr_s: float = 50.0
    uav_vel_error_corr_s: float = 50.0
    motion: str = "cv"
    init_epochs: int = 3
    init_height_sigma_m: float = 5000.0
    init_vel_sigma_m_s: float = 300.0
    init_cov_scale: float = 4.0
    init_resolve_s: float = 600.0
    init_resolve_llr: float = 150.0
    gate_prob: float = 1e-5
    max_uav_pos_sigma_m: float = 1000.0
    max_uav_vel_sigma_m_s: float = 50.0
    max_range_m: float = 1.0e6
    max_range_rate_m_s: float = 3000.0
    max_coast_s: float = 60.0
    axis_ratio: float = 0.5
    position_q_m2_s3: float = 1e-3
    backend: str | None = None
    init: str = "multilateration"
    update_iterations: int = 1
    second_order_r: bool = False
    prior_mean: tuple = ()
    prior_cov: tuple = ()
    acquire_s: float = 50.0
    min_formation_sigmas: float = 12.0
    integrity: IntegrityConfig | None = None
    integrity_max_links: int = 32
    integrity_common_fraction: float = 0.5
    integrity_min_links: int = 3
    lag_window_s: float = 5.0

    def __post_init__(self):
        if self.integrity is not None and not isinstance(self.integrity, IntegrityConfig):
            raise ValueError(f"integrity must be a filters.integrity.IntegrityConfig or None, got {self.integrity!r}")
        v = self.integrity_max_links
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise ValueError(f"integrity_max_links must be an integer >= 1, got {v!r}")
        v = self.integrity_min_links
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
            raise ValueError(f"integrity_min_links must be an integer >= 0, got {v!r}")
        f = self.integrity_common_fraction
        if isinstance(f, bool) or not isinstance(f, (int, float)) or not 0.0 < f <= 1.0:
            raise ValueError(f"integrity_common_fraction must lie in (0, 1], got {f!r}")
        _nonneg("q_m2_s3", self.q_m2_s3)
        _nonneg("uav_vel_error_corr_s", self.uav_vel_error_corr_s)
        if self.observer_uncertainty == "consider" and self.motion != "cv":
            raise ValueError('observer_uncertainty="consider" needs motion="cv"')
        if self.observer_uncertainty not in OBSERVER_UNCERTAINTY + ("consider",):
            raise ValueError(f"observer_uncertainty must be one of {OBSERVER_UNCERTAINTY + ('consider',)}, "
                             f"got {self.observer_uncertainty!r}")
        if self.motion not in MOTIONS:
            raise ValueError(f"motion must be one of {MOTIONS}, got {self.motion!r}")
        if isinstance(self.init_epochs, bool) or int(self.init_epochs) != self.init_epochs or self.init_epochs < 1:
            raise ValueError(f"init_epochs must be an integer >= 1, got {self.init_epochs!r}")
        if not float(self.init_height_sigma_m) > 0:
            raise ValueError(f"init_height_sigma_m must be > 0 (inf: no prior), got {self.init_height_sigma_m!r}")
        for name in ("init_vel_sigma_m_s", "init_cov_scale", "max_uav_pos_sigma_m", "max_uav_vel_sigma_m_s",
                     "max_range_m", "max_range_rate_m_s", "max_coast_s", "position_q_m2_s3"):
            _pos(name, getattr(self, name))
        _nonneg("uav_error_corr_s", self.uav_error_corr_s)
        _nonneg("init_resolve_s", self.init_resolve_s)
        _nonneg("acquire_s", self.acquire_s)
        _nonneg("min_formation_sigmas", self.min_formation_sigmas)
        _nonneg("lag_window_s", self.lag_window_s)
        _pos("init_resolve_llr", self.init_resolve_llr)
        if not 0.0 < float(self.gate_prob) < 1.0:
            raise ValueError(f"gate_prob must lie in (0, 1), got {self.gate_prob!r}")
        if not 0.0 < float(self.axis_ratio) <= 1.0:
            raise ValueError(f"axis_ratio must lie in (0, 1], got {self.axis_ratio!r}")
        kernels.resolve_backend(self.backend)
        if isinstance(self.update_iterations, bool) or int(self.update_iterations) != self.update_iterations \
                or not 1 <= self.update_iterations <= 20:
            raise ValueError(f"update_iterations must be an integer in 1..20, got {self.update_iterations!r}")
        if self.init not in INITS:
            raise ValueError(f"init must be one of {INITS}, got {self.init!r}")
        if self.init == "prior":
            m = np.asarray(self.prior_mean, dtype=float)
            C = np.asarray(self.prior_cov, dtype=float)
            if m.shape != (6,) or not np.all(np.isfinite(m)):
                raise ValueError(f"prior_mean must be 6 finite numbers [B, V_B] (ECEF), got {self.prior_mean!r}")
            if C.shape != (6, 6) or not np.all(np.isfinite(C)) or not np.allclose(C, C.T, rtol=1e-12, atol=0.0):
                raise ValueError(f"prior_cov must be a finite symmetric 6 x 6 matrix, got shape {C.shape}")
            try:
                np.linalg.cholesky(C)
            except np.linalg.LinAlgError:
                raise ValueError("prior_cov must be positive definite") from None
            object.__setattr__(self, "prior_mean", tuple(float(v) for v in m))
            object.__setattr__(self, "prior_cov", tuple(tuple(float(v) for v in row) for row in C))
        elif len(self.prior_mean) or len(self.prior_cov):
            raise ValueError('prior_mean / prior_cov are used only with init="prior"')

    @property
    def n_state(self) -> int:
        return 6 if self.motion == "cv" else 3

    @property
    def gate_chi2(self) -> float:
        return _chi2_isf(float(self.gate_prob), 2 if self.motion == "cv" else 1)

    def kappa(self, dt_s: float) -> float:
        """Inflation of the UAVs' covariance for their errors' time correlation."""
        if self.observer_uncertainty not in ("inflate", "consider"):
            return 0.0
        return 1.0 + 2.0 * float(self.uav_error_corr_s) / (dt_s if dt_s > 0 else 1.0)


class ObserverEpoch(NamedTuple):
    """One epoch of beacon measurements for a batch of trials, padded to N observers.

    pos (T, N, 3), vel (T, N, 3): the UAVs' own estimates; cov (T, N, 6, 6) their covariance
    over [U, V]; range_m, range_rate_m_s, var_range_m2, var_range_rate_m2_s2 (T, N);
    mask (T, N) True where an observer is present.  Absent slots hold finite fillers.
    """

    pos: np.ndarray
    vel: np.ndarray
    cov: np.ndarray
    range_m: np.ndarray
    range_rate_m_s: np.ndarray
    var_range_m2: np.ndarray
    var_range_rate_m2_s2: np.ndarray
    mask: np.ndarray

    @property
    def n_trials(self) -> int:
        return self.pos.shape[0]

    def take(self, idx) -> "ObserverEpoch":
        return ObserverEpoch(*(a[idx] for a in self))

    @staticmethod
    def empty(n_trials: int, n_obs: int) -> "ObserverEpoch":
        cov = np.broadcast_to(np.eye(6), (n_trials, n_obs, 6, 6)).copy()
        z = np.zeros((n_trials, n_obs))
        return ObserverEpoch(np.zeros((n_trials, n_obs, 3)), np.zeros((n_trials, n_obs, 3)), cov, z + 1.0, z.copy(),
                             z + 1.0, z + 1.0, np.zeros((n_trials, n_obs), bool))


def _fill_absent(obs: ObserverEpoch, anchor) -> ObserverEpoch:
    """Absent observers moved to a harmless finite place (1000 km from ``anchor`` along x,
    unit covariance) so that the geometry stays finite; their rows are zeroed anyway."""
    m = obs.mask
    if m.all():
        return obs
    filler = np.asarray(anchor, float)[..., None, 0:3] + np.array([1.0e6, 0.0, 0.0])
    one = np.ones_like(obs.range_m)
    return ObserverEpoch(np.where(m[..., None], obs.pos, filler), np.where(m[..., None], obs.vel, 0.0),
                         np.where(m[..., None, None], obs.cov, np.eye(6)), np.where(m, obs.range_m, one),
                         np.where(m, obs.range_rate_m_s, 0.0), np.where(m, obs.var_range_m2, one),
                         np.where(m, obs.var_range_rate_m2_s2, one), m)


def _chol2(S):
    """Cholesky factors of 2x2 blocks (..., 2, 2): (l11, l21, l22)."""
    l11 = np.sqrt(S[..., 0, 0])
    l21 = S[..., 1, 0] / l11
    l22 = np.sqrt(np.maximum(S[..., 1, 1] - l21 * l21, 1e-300))
    return l11, l21, l22


def _solve2(l11, l21, l22, v):
    """L^-1 v for lower-triangular 2x2 factors; v (..., 2, k)."""
    a = v[..., 0, :] / l11[..., None]
    b = (v[..., 1, :] - l21[..., None] * a) / l22[..., None]
    shape = np.broadcast_shapes(a.shape, b.shape)
    out = np.empty(shape[:-1] + (2,) + shape[-1:])
    out[..., 0, :] = a
    out[..., 1, :] = b
    return out


def range_doppler_blocks(x, obs: ObserverEpoch, kappa: float):
    """(zhat (T, N, 2), H (T, N, 2, 6) wrt ECEF [B, V_B], R (T, N, 2, 2)) at x (T, 6).

    R = diag(var_r, var_v) + kappa J_i P_i J_i' (kappa 0: the UAVs taken as exact), J_i the
    Jacobian wrt UAV i's [U_i, V_i] -- which is minus the Jacobian wrt [B, V_B] (d r/dU = u =
    -d r/dB, d rdot/dU = -d rdot/dB, d rdot/dV_i = u = -d rdot/dV_B): the same numbers as
    ``ObserverRangeDoppler.R`` with "inflate", without forming the full 2N x 2N matrix."""
    T, N = obs.mask.shape
    # ObserverRangeDoppler's checks and formulas (_geometry, _jac, h_and_H), written out
    # here to spare building the model object every epoch: the same numbers
    if not (np.isfinite(obs.pos).all() and np.isfinite(obs.vel).all()):
        raise ValueError("observer_pos_ecef_m and observer_vel_ecef_m_s must be finite")
    for name in ("var_range_m2", "var_range_rate_m2_s2"):
        v = getattr(obs, name)
        if not ((v > 0).all() and np.isfinite(v).all()):
            raise ValueError(f"{name} must be finite and > 0")
    x = np.asarray(x, dtype=float)
    d_pos = obs.pos - x[..., None, 0:3]
    r = np.sqrt(_sum(d_pos * d_pos, axis=-1))
    u = d_pos / r[..., None]
    dv = obs.vel - x[..., None, 3:6]
    rdot = _sum(u * dv, axis=-1)
    g = (dv - rdot[..., None] * u) / r[..., None]
    zhat = np.empty(r.shape + (2,))
    zhat[..., 0] = r
    zhat[..., 1] = rdot
    H = np.zeros(r.shape + (2, 6))
    H[..., 0, 0:3] = -u
    H[..., 1, 0:3] = -g
    H[..., 1, 3:6] = -u
    R = np.zeros((T, N, 2, 2))
    if kappa > 0:
        R += kappa * np.einsum("tnai,tnij,tnbj->tnab", H, obs.cov, H)
    R[..., 0, 0] += obs.var_range_m2
    R[..., 1, 1] += obs.var_range_rate_m2_s2
    return zhat, H, R


def second_order_var(x, upos, uvel, P_rel):
    """Variance of the second-order terms of each range and range rate, 0.5 tr((Hess P)^2),
    with Hess the Hessian wrt the beacon's position and P_rel (T, N, 3, 3) the covariance of
    the beacon-UAV relative position: (var_r, var_v) (T, N).  Added to R it keeps an EKF
    honest where the ranges are comparable with that uncertainty (one linearisation is then
    poor, the Doppler's most: its position Jacobian scales as 1 / r).

        Hess r    = (I - u u') / r
        Hess rdot = -(rdot (I - u u') / r^2 + (u g' + g u') / r),  g = (I - u u') dv / r
    (u = (U - B) / r, dv = V - V_B, rdot = u . dv)."""
    d = upos - x[..., None, 0:3]
    r = np.sqrt(_sum(d * d, axis=-1))
    u = d / r[..., None]
    dv = uvel - x[..., None, 3:6]
    rdot = _sum(u * dv, axis=-1)
    g = (dv - rdot[..., None] * u) / r[..., None]
    M = np.eye(3) - u[..., :, None] * u[..., None, :]
    Hr = M / r[..., None, None]
    Hv = -(rdot[..., None, None] * M / (r * r)[..., None, None]
           + (u[..., :, None] * g[..., None, :] + g[..., :, None] * u[..., None, :]) / r[..., None, None])
    A, B = Hr @ P_rel, Hv @ P_rel
    return 0.5 * np.einsum("...ij,...ji->...", A, A), 0.5 * np.einsum("...ij,...ji->...", B, B)


def _m2ll(yw, Hw, P, logdet_r):
    """-2 log-likelihood (without 2 pi) of whitened innovations yw (T, M) with whitened
    Jacobians Hw (T, M, n) (zero rows for absent observers): nu' S^-1 nu + log det S,
    S = Hw P Hw' + I, plus log det R (logdet_r (T,))."""
    S = np.einsum("tai,tij,tbj->tab", Hw, P, Hw) + np.eye(yw.shape[-1])
    L = np.linalg.cholesky(S)
    w = np.linalg.solve(L, yw[..., None])[..., 0]
    return np.sum(w * w, axis=-1) + 2.0 * np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1) + logdet_r


# --------------------------------------------------------------------------- coordinates


class Frame(NamedTuple):
    """Formation-cylindrical frames, one per row: origin c, axis a, normals e1, e2 (T, 3);
    cart (T,) True where the row's state is plain ECEF instead (see formation_frame)."""

    c: np.ndarray
    a: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    cart: np.ndarray

    def take(self, idx) -> "Frame":
        return Frame(*(v[idx] for v in self))


# The geometry below runs every epoch on small arrays, where numpy's per-call overhead is
# the cost: reductions call np.add.reduce directly (what np.sum calls) and results are
# written into preallocated arrays instead of np.stack -- the same operations on the same
# numbers, so the same results bit for bit.
_sum = np.add.reduce


def _unit(v):
    return v / np.sqrt(_sum(v * v, axis=-1, keepdims=True))


def _cross(a, b):
    out = np.empty(np.broadcast_shapes(np.shape(a), np.shape(b)))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def formation_frame(upos, mask, beacon_pos, prev: Frame | None = None, axis_ratio: float = 0.5) -> Frame:
    """The frame of each row: centroid and principal axis of the present UAVs (previous
    frame's where fewer than 2 are present, previous axis where the formation is not
    line-like), e1 towards ``beacon_pos`` (so that phi = 0 there).

    Which rows use the cylindrical coordinates is decided once, when a track starts (no
    ``prev``), and kept: those whose formation is line-like (second singular value <=
    axis_ratio x the first) with the beacon more than 3 formation lengths from its axis.
    The others -- a formation spread in two dimensions, or a beacon near or inside the
    formation, where the coordinates would be singular -- keep plain ECEF (cart True)."""
    m = mask[..., None]
    n = mask.sum(axis=-1)
    c = _sum(upos * m, axis=-2) / np.maximum(n, 1)[:, None]
    d = (upos - c[:, None, :]) * m
    w2, vec = np.linalg.eigh(np.swapaxes(d, -1, -2) @ d)  # ascending eigenvalues (singular values^2)
    a = vec[..., :, 2]
    line_like = w2[:, 1] <= axis_ratio ** 2 * w2[:, 2]
    if prev is not None:
        a = np.where((_sum(a * prev.a, axis=-1) < 0)[:, None], -a, a)
        keep_c = n < 2
        keep_a = keep_c | ~line_like
        c = np.where(keep_c[:, None], prev.c, c)
        a = np.where(keep_a[:, None], prev.a, a)
    w = beacon_pos - c
    w = w - _sum(w * a, axis=-1, keepdims=True) * a
    rho = np.sqrt(_sum(w * w, axis=-1))
    if prev is None:
        extent = np.max(np.sqrt(_sum(d * d, axis=-1)), axis=-1)
        cart = ~(line_like & (rho > 3.0 * extent) & (n >= 2))
    else:
        cart = np.asarray(prev.cart, bool)
    pos = rho > 0
    if pos.all():  # the usual case: _any_normal's values would all be discarded
        e1 = w / rho[:, None]
    else:
        e1 = np.where(pos[:, None], w / np.where(pos, rho, 1.0)[:, None], _any_normal(a))
    return Frame(c, a, e1, _cross(a, e1), cart)


def _any_normal(a):
    """A unit vector normal to each a (..., 3)."""
    t = np.where((np.abs(a[..., 0]) < 0.9)[..., None], np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    return _unit(t - _sum(t * a, axis=-1, keepdims=True) * a)


def _basis(phi, fr: Frame):
    cp, sp = np.cos(phi)[..., None], np.sin(phi)[..., None]
    return cp * fr.e1 + sp * fr.e2, -sp * fr.e1 + cp * fr.e2


def cyl_to_ecef(y, fr: Frame, jacobian: bool = False):
    """ECEF [B, V] (..., 6) of states y (..., 6) (frames broadcast against the last batch
    axis; rows with fr.cart are ECEF already); with ``jacobian`` also d x / d y (..., 6, 6)."""
    s, rho = y[..., 0:1], y[..., 1:2]
    er, ep = _basis(y[..., 2], fr)
    a = fr.a
    cart = fr.cart[..., None]
    x = np.concatenate([fr.c + s * a + rho * er, y[..., 3:4] * a + y[..., 4:5] * er + y[..., 5:6] * ep], axis=-1)
    any_cart = bool(fr.cart.any())
    if any_cart:
        x = np.where(cart, y, x)
    if not jacobian:
        return x
    J = np.zeros(y.shape[:-1] + (6, 6))
    J[..., 0:3, 0] = a
    J[..., 0:3, 1] = er
    J[..., 0:3, 2] = rho * ep
    J[..., 3:6, 2] = y[..., 4:5] * ep - y[..., 5:6] * er
    J[..., 3:6, 3] = a
    J[..., 3:6, 4] = er
    J[..., 3:6, 5] = ep
    return x, (np.where(cart[..., None], np.eye(6), J) if any_cart else J)


def ecef_to_cyl(x, fr: Frame, jacobian: bool = False):
    """States (..., 6) of ECEF [B, V] (..., 6) (unchanged in rows with fr.cart); with
    ``jacobian`` also (d y / d x, d x / d y) (..., 6, 6) at that point (exact inverses)."""
    d = x[..., 0:3] - fr.c
    s = _sum(d * fr.a, axis=-1)
    w = d - s[..., None] * fr.a
    rho = np.sqrt(_sum(w * w, axis=-1))
    rho_s = np.where(rho > 0, rho, 1.0)
    phi = np.arctan2(_sum(w * fr.e2, axis=-1), _sum(w * fr.e1, axis=-1))
    er = w / rho_s[..., None]
    ep = _cross(fr.a, er)
    v = x[..., 3:6]
    vr, vp = _sum(v * er, axis=-1), _sum(v * ep, axis=-1)
    y = np.empty(s.shape + (6,))
    y[..., 0], y[..., 1], y[..., 2], y[..., 3], y[..., 4], y[..., 5] = s, rho, phi, _sum(v * fr.a, axis=-1), vr, vp
    cart = fr.cart[..., None]
    y = np.where(cart, x, y)
    if not jacobian:
        return y
    a = np.broadcast_to(fr.a, er.shape)
    J = np.zeros(y.shape[:-1] + (6, 6))
    J[..., 0:3, 0], J[..., 0:3, 1], J[..., 0:3, 2] = a, er, rho[..., None] * ep
    J[..., 3:6, 2] = vr[..., None] * ep - vp[..., None] * er
    J[..., 3:6, 3], J[..., 3:6, 4], J[..., 3:6, 5] = a, er, ep
    # inverse: position rows a', er', ep'/rho; velocity rows R' = [a, er, ep]' plus the phi coupling
    Ji = np.zeros_like(J)
    Ji[..., 0, 0:3], Ji[..., 1, 0:3], Ji[..., 2, 0:3] = a, er, ep / rho_s[..., None]
    Ji[..., 3, 3:6], Ji[..., 4, 3:6], Ji[..., 5, 3:6] = a, er, ep
    # v = R(phi)' V: d v / d B = (dR'/dphi V) dphi/dB = [0, v_phi, -v_rho]' ep' / rho
    Ji[..., 4, 0:3] = vp[..., None] * ep / rho_s[..., None]
    Ji[..., 5, 0:3] = -vr[..., None] * ep / rho_s[..., None]
    eye = np.eye(6)
    return y, np.where(cart[..., None], eye, Ji), np.where(cart[..., None], eye, J)


def _sigma_points(y, P):
    n = y.shape[-1]
    L = np.linalg.cholesky(P) * math.sqrt(_UT_C2)
    Lt = np.moveaxis(L, -1, 0)  # (n, T, n): the columns
    return np.concatenate([y[None], y[None] + Lt, y[None] - Lt]), _ut_weights(n)


@functools.lru_cache(maxsize=8)
def _ut_weights(n: int) -> np.ndarray:
    w = np.r_[0.0, np.full(2 * n, 0.5 / _UT_C2)]
    w.flags.writeable = False
    return w


def ut_to_ecef(y, P, fr: Frame):
    """ECEF mean (T, 6) and covariance (T, 6, 6) of the cylindrical Gaussian (y, P): the
    unscented transform (sigma points +-sqrt(6) sigma, W0 = 0): the banana's moments."""
    X, W = _sigma_points(y, P)
    xs = cyl_to_ecef(X, fr)
    m = np.einsum("k,kti->ti", W, xs)
    d = xs - m
    C = np.einsum("k,kti,ktj->tij", W, d, d)
    return m, 0.5 * (C + np.swapaxes(C, -1, -2))


# --------------------------------------------------------------------------- filter steps


_IEKF_TOL = 1e-3  # m, m/s: iterated updates stop once no row's ECEF iterate moved by more


def _converged(x, x_last) -> bool:
    """The iterated update has converged: no row's ECEF [B, V] moved by _IEKF_TOL or more since
    the last relinearisation (a further one would relinearise at the same point)."""
    return bool(np.max(np.abs(x - x_last)) < _IEKF_TOL)


def _same_innovation(nu, nu_last, sigma, used) -> bool:
    """Relinearising changed no used innovation by 1e-3 of its noise sigma or more: the next
    update would repeat the last one (the measurements are linear enough over the step)."""
    d = np.abs(nu - nu_last) / sigma
    return bool(np.max(np.where(used[..., None], d, 0.0), initial=0.0) < 1e-3)


def cyl_step(y, P, fr: Frame, obs: ObserverEpoch, config: LocatorConfig, dt_s: float, loglik: bool = False,
             C=None, Pu_prev=None, judge=None):
    """One predict (over dt_s, skipped when 0) + update of the cylindrical filter, batched.

    y (T, 6), P (T, 6, 6) in the frames ``fr``; obs with T rows.  Returns (y, P, frame,
    nis (T,), used (T, N), gated (T, N), m2ll (T,) or None); the new frame is the epoch's;
    nis is NaN where no observer was used; m2ll (``loglik``) is -2 log p(z | past) of every
    present observer, gated or not (it scores hypotheses).  judge: None, or a callable
    (nu (T, N, 2), diag S (T, N, 2), mask (T, N)) -> mask (T, N) called once at the prior (the
    integrity monitor's verdict: the links it returns False for are neither used nor scored).
    """
    y = np.asarray(y, float)
    P = np.asarray(P, float)
    x, G = cyl_to_ecef(y, fr, jacobian=True)
    F6, Q = _cv_matrices(float(config.q_m2_s3), float(dt_s))
    xp = x @ F6.T
    fr = formation_frame(obs.pos, obs.mask, xp[:, 0:3], fr, config.axis_ratio)
    y, Gi, G2 = ecef_to_cyl(xp, fr, jacobian=True)
    if dt_s > 0:
        F = Gi @ F6 @ G
        P = F @ P @ np.swapaxes(F, -1, -2) + Gi @ Q @ np.swapaxes(Gi, -1, -2)
        P = 0.5 * (P + np.swapaxes(P, -1, -2))
    if config.observer_uncertainty == "consider":
        return _consider_step(y, P, C, fr, xp, Gi @ F6 @ G if dt_s > 0 else None, obs, config, dt_s, loglik,
                              Pu_prev, judge)
    obs = _fill_absent(obs, xp)
    T, N = obs.mask.shape
    kappa = config.kappa(dt_s)
    zhat, H, R = range_doppler_blocks(xp, obs, kappa)
    if config.second_order_r:
        Pb = (G2 @ P @ np.swapaxes(G2, -1, -2))[:, None, 0:3, 0:3]
        var_r2, var_v2 = second_order_var(xp, obs.pos, obs.vel, Pb + obs.cov[..., 0:3, 0:3])
        R[..., 0, 0] += var_r2
        R[..., 1, 1] += var_v2
    H = H @ G2[:, None]  # wrt the cylindrical state
    nu = np.stack([obs.range_m, obs.range_rate_m_s], axis=-1) - zhat  # (T, N, 2)
    R_score = None
    if loglik and kappa > 1.0:
        # hypotheses are scored with the UAVs' per-epoch error variance (kappa = 1): kappa > 1
        # discounts their information for the update, and as a noise model its log det term
        # would favour whichever hypothesis projects less of the UAVs' covariance (measured:
        # it picked the mirror in 10 of 10 constellation trials)
        R0 = np.zeros_like(R)
        R0[..., 0, 0], R0[..., 1, 1] = obs.var_range_m2, obs.var_range_rate_m2_s2
        R_score = R0 + (R - R0) / kappa
    out = _update(y, P, nu, H, R, obs.mask, config, loglik, R_score, judge)
    if config.update_iterations > 1:  # iterated EKF: relinearise at the updated state
        z = np.stack([obs.range_m, obs.range_rate_m_s], axis=-1)
        used0, yi = out[3], out[0]
        x_last, it, nu_last = xp, None, nu
        sr = np.sqrt(np.diagonal(R, axis1=-2, axis2=-1))
        for _ in range(int(config.update_iterations) - 1):
            xi, Gi_ = cyl_to_ecef(yi, fr, jacobian=True)
            if _converged(xi, x_last):
                break
            x_last = xi
            zh, Hi, _ = range_doppler_blocks(xi, obs, kappa)  # (R kept at the prediction's)
            Hi = Hi @ Gi_[:, None]
            nui = z - zh - np.einsum("tnai,ti->tna", Hi, y - yi)
            if _same_innovation(nui, nu_last, sr, used0):
                break
            nu_last = nui
            it = _update(y, P, nui, Hi, R, used0, config, False)
            yi = it[0]
        if it is not None:
            out = (it[0], it[1], it[2], it[3], (out[3] | out[4]) & ~it[3], out[5])  # (judged mask: used | gated)
    return out + (fr,)


def uav_error_transition(P_prev, P_now, rho):
    """Transition A (..., 6, 6) of a UAV's navigation error between two epochs at which it
    sent covariances P_prev and P_now (..., 6, 6): first-order Gauss-Markov with
    correlations rho (6,) in its whitened error, A = L_now diag(rho) L_prev^-1 (L the Cholesky
    factors).  Then eps_now = A eps_prev + w with Cov(w) = L_now (I - diag(rho)^2) L_now' >= 0,
    so Cov(eps_now) = P_now exactly, however fast the UAV's filter shrank its covariance."""
    Ln, Lp = np.linalg.cholesky(P_now), np.linalg.cholesky(P_prev)
    # A' = L_prev^-T diag(rho) L_now'
    At = np.linalg.solve(np.swapaxes(Lp, -1, -2), np.asarray(rho, float)[:, None] * np.swapaxes(Ln, -1, -2))
    return np.swapaxes(At, -1, -2)


def _consider_step(y, P, C, fr, xp, F, obs, config, dt_s, loglik, Pu_prev=None, judge=None):
    """observer_uncertainty="consider": the UAVs' navigation errors eps_i = U_i - U^_i as
    Schmidt (consider) states, first-order Gauss-Markov with correlation times
    uav_error_corr_s (position) and uav_vel_error_corr_s (velocity), covariance P_i (the
    UAV's own, sent with each message).  The filter carries C_i = Cov(state error, eps_i)
    (T, N, n, 6) per observer slot: predicted C_i <- F C_i A_i' with the transition
    eps_i(k) = A_i eps_i(k-1) + w, A_i = L_k diag(rho_p, rho_v) L_{k-1}^-1 (L the Cholesky
    factors of the UAV's covariance sent at the two epochs, Pu_prev (T, N, 6, 6) the previous
    ones): Gauss-Markov in the UAV's whitened error, so that Cov(eps_i(k)) is exactly the P_i
    sent now whatever the UAV's filter did meanwhile (a plain eps(k) = diag(rho) eps(k-1) + w
    needs Var(w) = P_k - rho^2 P_{k-1}, negative while the UAV's filter converges -- its
    covariance shrinks by half in the first second of the seed run -- and the joint covariance
    is then over-confident); the
    update is one batched update of the epoch's 2N rows with S = H P H' + H X + X' H' +
    blockdiag(J_i P_i J_i' + R_i), X_i = C_i J_i' (J_i = d z_i / d U_i = -H_i in ECEF),
    gain K = (P H' + X) S^-1, P -= K S K', C_i -= K (H C_i + E_i J_i P_i): the memory of
    the UAVs' errors in each direction of the state is the filter's own (no kappa).
    Returns (y, P, nis, used, gated, m2ll, frame, C)."""
    T = y.shape[0]
    n = y.shape[-1]
    obs = _fill_absent(obs, xp)
    N = obs.mask.shape[1]
    if C is None or C.shape[1] != N:
        C0 = np.zeros((T, N, n, 6))
        if C is not None:
            C0[:, :C.shape[1]] = C[:, :N]
        C = C0
    if F is not None:
        tp, tv = float(config.uav_error_corr_s), float(config.uav_vel_error_corr_s)
        rp = math.exp(-dt_s / tp) if tp > 0 else 0.0
        rv = math.exp(-dt_s / tv) if tv > 0 else 0.0
        A = np.array([rp] * 3 + [rv] * 3)
        C = np.einsum("tij,tnjb->tnib", F, C)
        if Pu_prev is None:
            C = C * A
        else:
            # absent slots and new ones: the covariance kept
            seen = (Pu_prev[..., 0, 0] > 0)[..., None, None]
            Pn = np.where(obs.mask[..., None, None], obs.cov, np.where(seen, Pu_prev, np.eye(6)))
            C = C @ np.swapaxes(uav_error_transition(np.where(seen, Pu_prev, Pn), Pn, A), -1, -2)
    zhat, He, R0 = range_doppler_blocks(xp, obs, 0.0)
    _, G2 = cyl_to_ecef(y, fr, jacobian=True)
    if config.second_order_r:
        var_r2, var_v2 = second_order_var(xp, obs.pos, obs.vel, (G2 @ P @ np.swapaxes(G2, -1, -2))[:, None, 0:3, 0:3]
                                          + obs.cov[..., 0:3, 0:3])
        R0[..., 0, 0] += var_r2
        R0[..., 1, 1] += var_v2
    z = np.stack([obs.range_m, obs.range_rate_m_s], axis=-1)
    Hy = He @ G2[:, None]
    J = -He  # d z / d U_i (wrt UAV i's [U, V])
    out = _consider_update(y, P, C, z - zhat, Hy, J, obs.cov, R0, obs.mask, config, False, None, judge)
    present = out[3] | out[4]  # obs.mask less the links the integrity monitor left out (judge)
    if config.update_iterations > 1:
        used0, yi = out[3], out[0]
        x_last, it, nu_last = xp, None, z - zhat
        sr = np.sqrt(np.diagonal(R0, axis1=-2, axis2=-1))
        for _ in range(int(config.update_iterations) - 1):
            xi, Gi_ = cyl_to_ecef(yi, fr, jacobian=True)
            if _converged(xi, x_last):
                break
            x_last = xi
            zh, Hi, _ = range_doppler_blocks(xi, obs, 0.0)
            Hyi = Hi @ Gi_[:, None]
            nui = z - zh - np.einsum("tnai,ti->tna", Hyi, y - yi)
            if _same_innovation(nui, nu_last, sr, used0):
                break
            nu_last = nui
            it = _consider_update(y, P, C, nui, Hyi, -Hi, obs.cov, R0, obs.mask, config, False, used0)
            yi = it[0]
        if it is not None:
            out = (it[0], it[1], it[2], it[3], present & ~it[3], out[5], it[6])
    y1, P1, nis, used, gated, _, C1 = out
    m2ll = None
    if loglik:
        # hypotheses are scored as by "inflate": the UAVs' errors white with their per-epoch
        # variance (R0 + J P_i J', no cross-covariances).  With the Schmidt S the log det term
        # favours whichever side projects less of the UAVs' covariance -- measured on the
        # printed run with the prior split in two halves by the side of the UAVs' plane: the
        # mirror was chosen in 18 of 20 three-satellite trials
        R1 = R0 + np.einsum("tnai,tnij,tnbj->tnab", He, obs.cov, He)
        l11, l21, l22 = _chol2(R1)
        pm = present[..., None]
        T, N = obs.mask.shape
        yw = _solve2(l11, l21, l22, (z - zhat)[..., None])[..., 0]
        Hw = _solve2(l11, l21, l22, Hy)
        m2ll = _m2ll((yw * pm).reshape(T, 2 * N), (Hw * pm[..., None]).reshape(T, 2 * N, n), P,
                     2.0 * np.sum(np.log(l11 * l22) * present, axis=-1))
    return y1, P1, nis, used, gated, m2ll, fr, C1


def _consider_update(y, P, C, nu, Hy, J, Pe, R0, mask, config, loglik, used_fixed=None, judge=None):
    """The batched Schmidt update of _consider_step; returns (y, P, nis, used, gated, m2ll, C)."""
    T, N = mask.shape
    n = y.shape[-1]
    m = 2 * N
    X = np.einsum("tnia,tnba->tinb", C, J).reshape(T, n, m)  # C_i J_i'
    Hs = Hy.reshape(T, m, n)
    D = np.einsum("tnai,tnij,tnbj->tnab", J, Pe, J) + R0
    S = Hs @ P @ np.swapaxes(Hs, -1, -2) + Hs @ X
    S = np.ascontiguousarray(S + np.swapaxes(Hs @ X, -1, -2))
    idx = np.arange(N)
    Sb = S.reshape(T, N, 2, N, 2)
    Sb[:, idx, :, idx, :] += np.moveaxis(D, 1, 0)
    Sjj = Sb[:, idx, :, idx, :]  # (N, T, 2, 2)
    Sjj = np.moveaxis(Sjj, 0, 1)
    if judge is not None and used_fixed is None:
        mask = judge(nu, np.stack([Sjj[..., 0, 0], Sjj[..., 1, 1]], axis=-1), mask)
    # absent slots (a lost message) keep their cross-covariances with the state, and their
    # filler geometry can make their block indefinite: they are not used, so not factored
    s11, s21, s22 = _chol2(np.where(mask[..., None, None], Sjj, np.eye(2)))
    w = _solve2(s11, s21, s22, nu[..., None])[..., 0]
    d = np.sum(w * w, axis=-1)
    if used_fixed is None:
        gated = mask & ~(d <= config.gate_chi2)
        used = mask & ~gated
    else:
        used = used_fixed
        gated = mask & ~used
    m2ll = None
    if loglik:
        um = np.repeat(mask, 2, axis=1).astype(float)
        Sm = S * um[:, :, None] * um[:, None, :] + np.eye(m) * (1.0 - um)[:, None, :]
        num = nu.reshape(T, m) * um
        L = np.linalg.cholesky(Sm)
        wv = np.linalg.solve(L, num[..., None])[..., 0]
        m2ll = np.sum(wv * wv, axis=-1) + 2.0 * np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1)
    u = np.repeat(used, 2, axis=1).astype(float)
    Su = S * u[:, :, None] * u[:, None, :] + np.eye(m) * (1.0 - u)[:, None, :]
    M = (P @ np.swapaxes(Hs, -1, -2) + X) * u[:, None, :]
    nuu = nu.reshape(T, m) * u
    Si_nu = np.linalg.solve(Su, nuu[..., None])[..., 0]
    K = np.swapaxes(np.linalg.solve(Su, np.swapaxes(M, -1, -2)), -1, -2)  # M S^-1 (S symmetric)
    y1 = y + np.einsum("tij,tj->ti", M, Si_nu)
    P1 = P - K @ np.swapaxes(M, -1, -2)
    P1 = 0.5 * (P1 + np.swapaxes(P1, -1, -2))
    # Cov(nu, eps_i) (T, N, m, 6): H C_i, plus J_i P_i in observer i's own rows; used rows only
    G = np.ascontiguousarray(np.einsum("tmk,tnkb->tnmb", Hs * u[..., None], C))
    Gb = G.reshape(T, N, N, 2, 6)
    Gb[:, idx, idx] += np.einsum("tnai,tnib->tnab", J, Pe) * used[..., None, None]
    C1 = C - np.einsum("tkm,tnmb->tnkb", K, G)
    nis = np.where(used.any(axis=-1), np.sum(nuu * Si_nu, axis=-1), np.nan)
    return y1, P1, nis, used, gated, m2ll, C1


def _update(y, P, nu, H, R, mask, config, loglik, R_score=None, judge=None):
    """Gate per observer, whiten the 2x2 blocks, Joseph update.  Returns (y, P, nis, used,
    gated, m2ll); m2ll (``loglik``) with R_score in place of R when given."""
    T, N = mask.shape
    n = y.shape[-1]
    S = np.einsum("tnai,tij,tnbj->tnab", H, P, H) + R
    if judge is not None:
        mask = judge(nu, np.diagonal(S, axis1=-2, axis2=-1), mask)
    s11, s21, s22 = _chol2(S)
    w = _solve2(s11, s21, s22, nu[..., None])[..., 0]
    d = np.sum(w * w, axis=-1)
    gated = mask & ~(d <= config.gate_chi2)
    used = mask & ~gated
    l11, l21, l22 = _chol2(R)
    yw_all = _solve2(l11, l21, l22, nu[..., None])[..., 0]
    Hw_all = _solve2(l11, l21, l22, H)
    m2ll = None
    if loglik:
        pm = mask[..., None]
        f11, f21, f22 = (l11, l21, l22) if R_score is None else _chol2(R_score)
        yw_s = yw_all if R_score is None else _solve2(f11, f21, f22, nu[..., None])[..., 0]
        Hw_s = Hw_all if R_score is None else _solve2(f11, f21, f22, H)
        m2ll = _m2ll((yw_s * pm).reshape(T, 2 * N), (Hw_s * pm[..., None]).reshape(T, 2 * N, n), P,
                     2.0 * np.sum(np.log(f11 * f22) * mask, axis=-1))
    yo, Po, nis = kernels.joseph_update(np.ascontiguousarray(y), np.ascontiguousarray(P),
                                        (yw_all * used[..., None]).reshape(T, 2 * N),
                                        (Hw_all * used[..., None, None]).reshape(T, 2 * N, n),
                                        r_diag=np.ones((T, 2 * N)), backend=config.backend)
    nis = np.where(used.any(axis=-1), nis, np.nan)
    return yo, Po, nis, used, gated, m2ll


def _doppler_velocity(B, obs: ObserverEpoch, kappa: float):
    """Weighted least-squares beacon velocity from the Dopplers (seed eq 8, any N >= 3).

    rdot_i = u_i . (V_i - V_B)  ->  u_i' V_B = u_i' V_i - rdot_i,  u_i = (U_i - B)/|U_i - B|;
    weight 1 / (var_v + kappa u_i' P_Vi u_i).  Returns (V (T, 3), Cov (T, 3, 3)); absent
    observers weigh 0 (a tiny ridge keeps fewer than 3 finite)."""
    d = obs.pos - B[..., None, :]
    u = d / np.linalg.norm(d, axis=-1, keepdims=True)
    b = np.sum(u * obs.vel, axis=-1) - obs.range_rate_m_s
    var = obs.var_range_rate_m2_s2 + kappa * np.einsum("tni,tnij,tnj->tn", u, obs.cov[..., 3:6, 3:6], u)
    wgt = np.where(obs.mask, 1.0 / var, 0.0)
    A = np.einsum("tni,tn,tnj->tij", u, wgt, u) + 1e-12 * np.eye(3)
    C = np.linalg.inv(A)
    return np.einsum("tij,tj->ti", C, np.einsum("tni,tn,tn->ti", u, wgt, b)), C


def position_only_step(x, P, obs: ObserverEpoch, config: LocatorConfig, dt_s: float, loglik: bool = False,
                       judge=None):
    """The seed's beacon filter (eq 11) on B only (ECEF), batched (module docstring).

    x (T, 3), P (T, 3, 3).  Returns (x, P, nis, used, gated, m2ll, V_hat (T, 3), Cov_V (T, 3, 3)).
    """
    x = np.asarray(x, float)
    P = np.asarray(P, float)
    obs = _fill_absent(obs, x)
    T, N = obs.mask.shape
    kappa = config.kappa(dt_s)
    V, CV = _doppler_velocity(x, obs, kappa)
    if dt_s > 0:
        eps = 10.0  # m: central differences of V_hat(B)
        J = np.empty((T, 3, 3))
        for k in range(3):
            e = np.zeros(3)
            e[k] = eps
            J[..., k] = (_doppler_velocity(x + e, obs, kappa)[0] - _doppler_velocity(x - e, obs, kappa)[0]) / (2 * eps)
        F = np.eye(3) + dt_s * J
        x = x + dt_s * V
        P = F @ P @ np.swapaxes(F, -1, -2) + dt_s * dt_s * CV + config.position_q_m2_s3 * dt_s * np.eye(3)
        P = 0.5 * (P + np.swapaxes(P, -1, -2))
    d = obs.pos - x[..., None, :]
    r = np.linalg.norm(d, axis=-1)
    u = d / r[..., None]
    R = obs.var_range_m2 + kappa * np.einsum("tni,tnij,tnj->tn", u, obs.cov[..., 0:3, 0:3], u)
    # ranges only, as 2x2 blocks with a dummy unit second row so that _update applies
    H = np.zeros((T, N, 2, 3))
    H[..., 0, :] = -u
    R2 = np.zeros((T, N, 2, 2))
    R2[..., 0, 0] = R
    R2[..., 1, 1] = 1.0
    nu = np.stack([obs.range_m - r, np.zeros_like(r)], axis=-1)
    # (the dummy rows add nothing: zero innovation, zero Jacobian, unit variance)
    xo, Po, nis, used, gated, m2ll = _update(x, P, nu, H, R2, obs.mask, config, loglik, judge=judge)
    return xo, Po, nis, used, gated, m2ll, V, CV


# --------------------------------------------------------------------------- initialisation


class InitFix(NamedTuple):
    """The initial estimate of one trial (ECEF): x (6,) [B, V_B] at the last window epoch,
    P (6, 6), the closed-form start (3,), the number of epochs, the final weighted cost and
    LM iterations; mirror_x, mirror_P, mirror_cost: the best solution on the other side of
    the UAVs' axis."""

    x: np.ndarray
    P: np.ndarray
    start_pos_ecef_m: np.ndarray
    n_epochs: int
    cost: float
    iterations: int
    mirror_x: np.ndarray
    mirror_P: np.ndarray
    mirror_cost: float


def _up(pos):
    lat, lon, h = ecef_to_geodetic(pos)
    return np.array([math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)]), float(h)


def init_fix(epochs, config: LocatorConfig = LocatorConfig(), iterations: int = 30) -> InitFix:
    """Initial [B, V_B] of one trial from a window of epochs (module docstring).

    epochs: list of (t_gps_s, ObserverEpoch with one row) -- at least one, each with >= 3
    present observers.  Closed-form multilateration per epoch (UAV estimates as anchors,
    range variance inflated by the UAV position variance), component-wise median as the
    start, then Levenberg-Marquardt on ranges, Dopplers and the height / velocity priors,
    with the height scanned on both sides of the UAVs' axis.
    """
    if not epochs:
        raise ValueError("epochs must hold at least one epoch")
    tK = float(epochs[-1][0])
    fixes, hs, rows = [], [], []
    # the UAVs' errors barely change across a short window: fully correlated, so their
    # consider term counts once for the window (kappa = number of epochs)
    kappa = float(len(epochs)) if config.observer_uncertainty == "inflate" else 0.0
    for t, ob in epochs:
        m = ob.mask[0]
        if m.sum() < 3:
            raise ValueError(f"epoch t={t}: a fix needs >= 3 observers, got {int(m.sum())}")
        pos, vel, cov = ob.pos[0, m], ob.vel[0, m], ob.cov[0, m]
        r, rd = ob.range_m[0, m], ob.range_rate_m_s[0, m]
        vr, vv = ob.var_range_m2[0, m], ob.var_range_rate_m2_s2[0, m]
        try:
            fixes.append(multilaterate(r, pos, vr + np.trace(cov[:, 0:3, 0:3], axis1=-2, axis2=-1) / 3.0).pos_ecef_m)
        except ValueError:  # collinear anchors: no closed-form fix from this epoch
            pass
        hs.append(ecef_to_geodetic(pos)[2])
        rows.append((float(t), ObserverEpoch(pos[None], vel[None], cov[None], r[None], rd[None], vr[None], vv[None],
                                             np.ones((1, r.size), bool))))
    if not fixes:
        raise ValueError("no epoch of the window gives a closed-form fix (collinear anchors)")
    start = np.median(np.array(fixes), axis=0)
    h_prior = float(np.mean(np.concatenate(hs)))
    sig_h = float(config.init_height_sigma_m)
    sig_v = float(config.init_vel_sigma_m_s)
    # the window's epochs stacked as rows (padded to the largest N; absent rows zeroed)
    K, Nm = len(rows), max(r[1].mask.shape[1] for r in rows)
    win = ObserverEpoch.empty(K, Nm)
    for j, (_, ob) in enumerate(rows):
        n = ob.mask.shape[1]
        for dst, src in zip(win, ob):
            dst[j, :n] = src[0]
    dts = np.array([t for t, _ in rows]) - tK
    pres = win.mask[..., None]

    def residuals(s, h_target=None, sig=sig_h):
        """Whitened residuals and Jacobian wrt s = [B(tK), V_B]."""
        xj = np.concatenate([s[0:3] + dts[:, None] * s[3:6], np.broadcast_to(s[3:6], (K, 3))], axis=-1)
        ob = _fill_absent(win, xj)
        zhat, H, R = range_doppler_blocks(xj, ob, kappa)
        nu = (np.stack([ob.range_m, ob.range_rate_m_s], axis=-1) - zhat) * pres
        Hs = np.concatenate([H[..., 0:3], dts[:, None, None, None] * H[..., 0:3] + H[..., 3:6]], axis=-1)
        l11, l21, l22 = _chol2(R)
        res = [_solve2(l11, l21, l22, nu[..., None])[..., 0].ravel()]
        jac = [(_solve2(l11, l21, l22, Hs) * pres[..., None]).reshape(-1, 6)]
        if math.isfinite(sig):
            up, h = _up(s[0:3])
            res.append(np.array([((h_prior if h_target is None else h_target) - h) / sig]))
            jac.append(np.concatenate([up, np.zeros(3)])[None] / sig)
        res.append(-s[3:6] / sig_v)
        jac.append(np.concatenate([np.zeros((3, 3)), np.eye(3)], axis=1) / sig_v)
        return np.concatenate(res), np.concatenate(jac)

    def solve(s, **kw):
        """Levenberg-Marquardt from s; returns (s, J, cost, iterations)."""
        y, J = residuals(s, **kw)
        cost = float(y @ y)
        lam, it = 1e-3, 0
        for it in range(1, iterations + 1):
            A, g = J.T @ J, J.T @ y
            accepted = done = False
            for _ in range(20):
                step = np.linalg.solve(A + lam * np.diag(np.diag(A)), g)
                y2, J2 = residuals(s + step, **kw)
                c2 = float(y2 @ y2)
                if c2 < cost:
                    done = cost - c2 < 1e-10 * max(cost, 1.0) or bool(np.all(np.abs(step[0:3]) < 1e-3))
                    s, y, J, cost, lam = s + step, y2, J2, c2, max(lam / 10.0, 1e-12)
                    accepted = True
                    break
                lam *= 10.0
            if not accepted or done:
                break
        return s, J, cost, it

    def best_from(p0):
        """Scan the height (pinned) over the prior's +-3 sigma from p0 (each pinned solve
        starts from the previous one), then release it from the best."""
        s0 = np.concatenate([p0, np.zeros(3)])
        if math.isfinite(sig_h):
            best, sc = None, s0
            for hc in h_prior + sig_h * np.arange(-3.0, 3.01, 1.0):
                sc = solve(sc, h_target=hc, sig=1.0)[0]
                yc, _ = residuals(sc)
                if best is None or float(yc @ yc) < best[1]:
                    best = (sc, float(yc @ yc))
            s0 = best[0]
        s, J, cost, it = solve(s0)
        P = np.linalg.inv(J.T @ J) * float(config.init_cov_scale)
        return s, 0.5 * (P + P.T), cost, it

    # the mirror: the solution turned by 180 deg about the last epoch's principal axis (same
    # distance from the axis, so near the other side's ring), refined the same way
    one = best_from(start)
    last = rows[-1][1].pos[0]
    c = last.mean(axis=0)
    a = np.linalg.svd(last - c)[2][0]
    d = one[0][0:3] - c
    two = best_from(c + 2.0 * (d @ a) * a - d)
    if two[2] < one[2]:
        one, two = two, one
    return InitFix(one[0], one[1], start, len(rows), one[2], one[3], two[0], two[1], two[2])


# --------------------------------------------------------------------------- the bus component


class _ZeroModel:
    """The integrity monitor's model of the locator's innovations: z = nu, h = 0, H = 0 and
    R_diag = diag(S) (S at the prior), so that beta = nu / sqrt(S) exactly."""

    def __init__(self, r):
        self._r = r

    def h_and_H(self, x):
        k, m = self._r.shape
        return np.zeros((k, m)), np.zeros((k, m, 1))

    def R_diag(self):
        return self._r


def _mon_take(st, idx):
    """The monitor state of batch rows idx (a copy): filters.integrity.MonitorState.take."""
    return st.take(idx)


def _mon_merge(prev, acc, idx, sub):
    """The epoch's new monitor state: acc (None: prev) with rows idx from sub, the state those
    rows stepped to from prev this epoch: filters.integrity.MonitorState.merge."""
    return prev.merge(acc, idx, sub)


class _Epoch(NamedTuple):
    """One processed epoch in the lag window: its time, the locator's state before it, its
    inputs (per trial {uav id: msg}; late messages are added here) and the counters it added."""

    t: float
    snap: dict
    inputs: list
    added: Counter


class BeaconLocator:
    """Bus component: collects BeaconMeasurements, steps the batched filter, publishes Estimates.

    transport: a ``sitl.bus.Transport`` (None: no bus; feed ``process`` directly).
    run_ids: one run id per Monte Carlo trial (the trial axis of the batch).
    beacon_id: the beacon tracked (key id).
    ``rejected``: messages refused by reason; ``counters``: accepted, duplicate, other_run,
    gated, used, epochs_fused / _degraded / _coast / _lost (summed over trials),
    initialised, mirror_hypotheses / _chosen / _dropped, published.
    """

    def __init__(self, transport=None, *, run_ids=("run",), beacon_id: str = "b1",
                 config: LocatorConfig = LocatorConfig(), source_id: str = "gs", publish_estimates: bool = True):
        if not isinstance(config, LocatorConfig):
            raise ValueError(f"config must be a LocatorConfig, got {type(config).__name__}")
        run_ids = list(run_ids)
        if not run_ids or len(set(run_ids)) != len(run_ids):
            raise ValueError(f"run_ids must be non-empty and distinct, got {run_ids!r}")
        self.config = config
        # "consider": the acquisition's filter (the first acquire_s seconds of each track)
        self._acquire_config = dataclasses.replace(config, observer_uncertainty="inflate") \
            if config.observer_uncertainty == "consider" else None
        self.transport = transport
        self.run_ids = run_ids
        self.beacon_id = beacon_id
        self.source_id = source_id
        self.publish_estimates = bool(publish_estimates)
        self._trial = {r: k for k, r in enumerate(run_ids)}
        T, n = len(run_ids), config.n_state
        self.t_gps_s: float | None = None  # time of the filters' state (shared by the batch)
        self.y = np.zeros((T, n))  # cylindrical state ("cv") or ECEF position ("position")
        self.P = np.broadcast_to(np.eye(n), (T, n, n)).copy()
        self.frame = Frame(*(np.tile(v, (T, 1)) for v in np.eye(3)[[0, 0, 1, 2]]), np.ones(T, bool))
        self.initialised = np.zeros(T, bool)
        self.init_t_gps_s = np.full(T, np.nan)  # when each trial's track started
        self.nis = np.full(T, np.nan)
        self.n_used = np.zeros(T, int)
        self.coast_s = np.zeros(T)
        self.mode = np.array(["init"] * T, dtype=object)
        self.vel_doppler = np.zeros((T, 3))  # position-only mode: the Doppler velocity
        self.vel_doppler_cov = np.broadcast_to(np.eye(3) * 1e6, (T, 3, 3)).copy()
        self.init_info: list[InitFix | None] = [None] * T
        self.init_window_last: list[ObserverEpoch | None] = [None] * T  # the frame's UAVs at the start
        self.start_side = np.zeros(T, bool)  # True: the mirror of init_info was kept
        # min_formation_sigmas: the verdict of the last epoch with >= 3 UAVs (True: resolved); while
        # False, epochs with 1-2 UAVs use nothing either
        self.formation_resolved = np.zeros(T, bool)
        # the mirror hypothesis of each trial while it is alive (see _initialise)
        self.alt_active = np.zeros(T, bool)
        self.alt_y = np.zeros((T, n))
        self.alt_P = np.broadcast_to(np.eye(n), (T, n, n)).copy()
        self.alt_frame = Frame(*(v.copy() for v in self.frame))
        self.alt_vel = np.zeros((T, 3))
        self.score = np.zeros(T)
        self.alt_score = np.zeros(T)
        # observer_uncertainty="consider": Cov(state error, UAV i's error) per observer slot;
        # slots are fixed per UAV id (_collect), so that slot i is always the same UAV
        self.C = np.zeros((T, 0, n, 6))
        self.alt_C = np.zeros((T, 0, n, 6))
        self.uav_cov_prev = np.zeros((T, 0, 6, 6))  # the last covariance each slot's UAV sent (0: none yet)
        self.uav_incarnation = np.full((T, 0), -1, dtype=np.int64)  # the incarnation each slot's UAV sent (-1: none)
        self._C_out = None
        self._slot: dict = {}
        self.resolve_at = np.full(T, np.inf)
        self._window: list[list] = [[] for _ in range(T)]
        self._pending: list[dict] = [dict() for _ in range(T)]  # per trial {(uav, t): msg}
        self._seqtrack = SequenceTracker()  # duplicates by (run/source id, incarnation, seq)
        # lag window (config.lag_window_s): per processed epoch, the state before it, its inputs
        # (per trial {uav: msg}, completed by late messages) and the counters it added
        self._hist: list[_Epoch] = []
        self._dirty: float | None = None  # the earliest epoch a late message completed
        self._seq: dict[int, int] = {}
        self._keys: dict[str, str] = {}  # run id -> the key its Estimates go out on
        self._report = None  # cached ECEF moments of the current state
        self.counters = Counter()
        self.rejected = Counter()
        # the integrity monitor (config.integrity): one channel (range, Doppler) per UAV id, the
        # column of its fixed observer slot (_collect); batch (T,): judged on each primary track
        self._mon = None
        self.integrity_events = None
        if config.integrity is not None:
            L = int(config.integrity_max_links)
            self._mon = IntegrityMonitor(config.integrity)
            self._mon_state = self._mon.init((T,), 2 * L, L)
            self._mon_ch = np.repeat(np.arange(L), 2)
            self._mon_next = None  # the state being built this epoch (merged per filter call)
            self._ev_trials = None  # trial of each row of the report being turned into events
            self.integrity_events = IntegrityEventPublisher(lambda b: self.run_ids[self._ev_trials[b[0]]],
                                                            f"{source_id}.integrity", transport)
        self._sub = None
        if transport is not None:
            self._sub = transport.subscribe(f"*/uav/*/beacon/{beacon_id}", self.on_message)

    # ---------------------------------------------------------------- input
    @property
    def n_trials(self) -> int:
        return len(self.run_ids)

    def on_message(self, key: str, msg) -> None:
        """Bus callback: check and collect one BeaconMeasurement (counted either way)."""
        parsed = parse_key(key)
        if parsed is None or parsed[1] is not BeaconMeasurement or not isinstance(msg, BeaconMeasurement):
            self.rejected["not_a_beacon_measurement"] += 1
            return
        run, _, ids = parsed
        if ids.get("beacon") != self.beacon_id:
            self.rejected["other_beacon"] += 1
            return
        k = self._trial.get(run)
        if k is None:
            self.counters["other_run"] += 1
            return
        if self._seqtrack.update(f"{run}/{msg.source_id}#{msg.incarnation}", msg.seq).duplicate:
            self.counters["duplicate"] += 1  # a copy of a message seen already (source, seq): once only
            return
        c = self.config
        if not (msg.range_m <= c.max_range_m and abs(msg.range_rate_m_s) <= c.max_range_rate_m_s):
            self.rejected["range_out_of_limits"] += 1
            return
        if not (_EARTH_R_MIN_M <= float(np.linalg.norm(msg.uav_pos_ecef_m)) <= _EARTH_R_MAX_M):
            self.rejected["uav_position_implausible"] += 1
            return
        dg = np.diagonal(msg.uav_cov)
        if not (dg[0:3].max() <= c.max_uav_pos_sigma_m ** 2 and dg[3:6].max() <= c.max_uav_vel_sigma_m_s ** 2):
            self.rejected["uav_covariance_absurd"] += 1
            return
        t = float(msg.t_gps_s)
        lag = c.lag_window_s
        if lag > 0 and self.t_gps_s is not None and t <= self.t_gps_s + 1e-6:
            # out of sequence: an epoch processed already -- re-processed at the next step
            e = self._hist_at(t) if t >= self.t_gps_s - lag - 1e-6 else None
            if e is None:
                self.rejected["too_late"] += 1
                return
            inputs = e.inputs[k]
            if ids["uav"] in inputs:
                self.counters["duplicate_epoch"] += 1
                return
            inputs[ids["uav"]] = msg
            self._dirty = e.t if self._dirty is None else min(self._dirty, e.t)
            self.counters["accepted"] += 1
            self.counters["late_accepted"] += 1
            return
        if self.t_gps_s is not None and t < self.t_gps_s - 1e-9:
            self.rejected["stale"] += 1
            return
        slot = (ids["uav"], t)
        pend = self._pending[k]
        if slot in pend:
            self.counters["duplicate_epoch"] += 1  # another message of the same UAV and epoch
            return
        pend[slot] = msg
        self.counters["accepted"] += 1

    def _hist_at(self, t: float, tol: float = 1e-6):
        """The history entry of the processed epoch t (None: no step at t in the window)."""
        for e in reversed(self._hist):
            if abs(e.t - t) <= tol:
                return e
            if e.t < t - tol:
                return None
        return None

    def _collect(self, t: float, tol: float = 1e-6) -> ObserverEpoch:
        """The pending measurements of epoch t as padded arrays (older ones dropped, counted)."""
        return self._observations(self._take(t, tol))

    def _take(self, t: float, tol: float = 1e-6) -> list[dict]:
        """The pending measurements of epoch t, per trial {uav id: msg} (older ones dropped,
        counted as stale)."""
        per = []
        for k, pend in enumerate(self._pending):
            now, keep = {}, {}
            for slot, msg in pend.items():
                if abs(slot[1] - t) <= tol:
                    now[slot[0]] = msg
                elif slot[1] < t:
                    self.rejected["stale"] += 1
                else:
                    keep[slot] = msg
            self._pending[k] = keep
            per.append(now)
        return per

    def _new_incarnations(self, inputs: list[dict]):
        """(T, N) bool: the slots whose UAV's message this epoch carries a later incarnation than
        its last ones (a restarted UAV: its onboard filter re-initialised from a least-squares fix,
        so its navigation error is a new one), "consider" only; None when there are none.  Reads
        ``getattr(msg, "incarnation", 0)`` (bus schema 3; 0 before it).  A message of an earlier
        incarnation than the slot's (a dead process's, delayed) changes nothing (counted)."""
        if self.config.observer_uncertainty != "consider":
            return None
        T, N = self.n_trials, len(self._slot)
        if self.uav_incarnation.shape[1] < N:
            grown = np.full((T, N), -1, dtype=np.int64)
            grown[:, :self.uav_incarnation.shape[1]] = self.uav_incarnation
            self.uav_incarnation = grown
        new = None
        for k, now in enumerate(inputs):
            for uid, m in now.items():
                i = self._slot[uid]
                inc, last = int(getattr(m, "incarnation", 0)), int(self.uav_incarnation[k, i])
                if inc > last:
                    if last >= 0:
                        new = np.zeros((T, N), bool) if new is None else new
                        new[k, i] = True
                    self.uav_incarnation[k, i] = inc
                elif inc < last:
                    self.counters["uav_incarnation_older"] += 1
        return new

    def _reset_slots(self, new) -> None:
        """"consider": forget what the state knows of the UAV errors of the slots ``new`` (T, N):
        their cross-covariances with the track and the mirror hypothesis, and the covariance last
        sent (so the Gauss-Markov transition starts afresh from the new incarnation's) -- the new
        incarnation's navigation error is independent of the old one's, as a new UAV's would be."""
        N = new.shape[1]
        self._grow_C(N)
        self.C[:, :N][new] = 0.0
        self.alt_C[:, :N][new] = 0.0
        self.uav_cov_prev[:, :N][new] = 0.0
        self.counters["uav_incarnations"] += int(new.sum())

    def _observations(self, inputs: list[dict]) -> ObserverEpoch:
        """Per trial {uav id: msg} -> padded arrays (UAVs in id order; fixed slots per UAV id
        with "consider" or the integrity monitor)."""
        per = [sorted(d.items(), key=lambda a: a[0]) for d in inputs]
        # one fixed slot per UAV id: the consider states and the integrity channels follow the UAV
        consider = self.config.observer_uncertainty == "consider" or self.config.integrity is not None
        if consider:
            for now in per:
                for uid, _ in now:
                    self._slot.setdefault(uid, len(self._slot))
        N = max(1, len(self._slot) if consider else max(len(p) for p in per))
        obs = ObserverEpoch.empty(self.n_trials, N)
        for k, now in enumerate(per):
            for j, (uid, m) in enumerate(now):
                i = self._slot[uid] if consider else j
                obs.pos[k, i] = m.uav_pos_ecef_m
                obs.vel[k, i] = m.uav_vel_ecef_m_s
                obs.cov[k, i] = m.uav_cov
                obs.range_m[k, i] = m.range_m
                obs.range_rate_m_s[k, i] = m.range_rate_m_s
                obs.var_range_m2[k, i] = m.var_range_m2
                obs.var_range_rate_m2_s2[k, i] = m.var_range_rate_m2_s2
                obs.mask[k, i] = True
        return obs

    # ---------------------------------------------------------------- processing
    def step(self, t_gps_s: float):
        """Process the epoch t_gps_s for every trial and publish the Estimates; returns self.
        Late measurements taken in since the last step (lag window) are used first: the
        state goes back to before their epoch and the epochs since are re-run (not
        published again)."""
        t = float(t_gps_s)
        if self._dirty is not None:
            self._reprocess()
        self._run_epoch(t, self._take(t))
        if self.transport is not None and self.publish_estimates:
            self.publish()
        return self

    def _run_epoch(self, t: float, inputs: list[dict]) -> None:
        lag = self.config.lag_window_s
        if lag <= 0:
            obs = self._observations(inputs)
            self.process(t, obs, self._new_incarnations(inputs))
            return
        if self.t_gps_s is not None and t < self.t_gps_s:
            raise ValueError(f"t_gps_s must not go back: {t} < {self.t_gps_s}")
        snap = self._snapshot()
        before = self.counters.copy()
        obs = self._observations(inputs)  # (assigns new UAVs their slots first)
        self.process(t, obs, self._new_incarnations(inputs))
        self._hist.append(_Epoch(t, snap, inputs, self.counters - before))
        _lagwindow.prune(self._hist, t, lag, 1e-6)

    def _reprocess(self) -> None:
        """Back to the state before the earliest epoch completed by late messages, then re-run
        that epoch and the later ones of the history with their (completed) inputs -- every
        trial of the batch together (an untouched trial re-runs to the identical result)."""
        t0, self._dirty = self._dirty, None
        n = _lagwindow.rerun(self._hist, t0, 1e-6, restore=lambda e: self._restore(e.snap),
                             uncount=lambda e: self.counters.subtract(e.added),
                             run=lambda e: self._run_epoch(e.t, e.inputs), events=self.integrity_events)
        if n:
            self.counters["reprocess_runs"] += 1
            self.counters["reprocessed_epochs"] += n

    _SNAP = ("y", "P", "initialised", "init_t_gps_s", "nis", "n_used", "coast_s", "mode", "vel_doppler",
             "vel_doppler_cov", "start_side", "formation_resolved")
    _SNAP_ALT = ("alt_active", "alt_y", "alt_P", "alt_vel", "score", "alt_score", "resolve_at")
    _SNAP_CONSIDER = ("C", "alt_C", "uav_cov_prev", "uav_incarnation")

    def _snapshot(self) -> dict:
        """The state the next epoch changes, copied (only what a step writes: the arrays of the
        filters, the mirror hypotheses while any is alive, the consider states with "consider",
        the start windows; the integrity monitor's state is replaced, never written, per epoch)."""
        d = {name: getattr(self, name).copy() for name in self._SNAP}
        d["t_gps_s"] = self.t_gps_s
        d["frame"] = Frame(*(u.copy() for u in self.frame))
        if self.alt_active.any():  # rows of inactive hypotheses are never read
            for name in self._SNAP_ALT:
                d[name] = getattr(self, name).copy()
            d["alt_frame"] = Frame(*(u.copy() for u in self.alt_frame))
        else:
            d["alt_active"] = self.alt_active.copy()
        if self.config.observer_uncertainty == "consider":
            for name in self._SNAP_CONSIDER:
                d[name] = getattr(self, name).copy()
        if not self.initialised.all():
            d["_window"] = [list(w) for w in self._window]
            d["init_info"] = list(self.init_info)
            d["init_window_last"] = list(self.init_window_last)
        if self._mon is not None:
            d["_mon_state"] = self._mon_state
        return d

    def _restore(self, d: dict) -> None:
        for name, v in d.items():
            setattr(self, name, v)
        self._report = None

    def _filter(self, y, P, fr, obs, dt, loglik, C=None, Pu=None, acq=None, judge=None):
        """One filter step on stacked rows; returns (y, P, frame, nis, used, gated, m2ll, V)
        (and sets self._C_out: the consider cross-covariances, "consider" only).  acq (rows,)
        bool: "consider" rows still in their acquisition (``acquire_s``), stepped by "inflate"
        with their cross-covariances kept at 0.  judge: the integrity verdict (cyl_step), as
        judge(nu, s_diag, mask, rows=None) with rows the stacked rows of a subset."""
        c = self.config
        if c.motion == "cv":
            if c.observer_uncertainty == "consider":
                if acq is None or not acq.any():
                    y, P, nis, used, gated, m2ll, fr, self._C_out = cyl_step(y, P, fr, obs, c, dt, loglik, C, Pu,
                                                                             judge)
                    return y, P, fr, nis, used, gated, m2ll, None
                ca = self._acquire_config
                if acq.all():
                    self._C_out = np.zeros_like(C)
                    y, P, nis, used, gated, m2ll, fr = cyl_step(y, P, fr, obs, ca, dt, loglik, judge=judge)
                    return y, P, fr, nis, used, gated, m2ll, None
                a, b = np.flatnonzero(acq), np.flatnonzero(~acq)
                ja = jb = None
                if judge is not None:
                    def ja(nu, s, m):
                        return judge(nu, s, m, a)

                    def jb(nu, s, m):
                        return judge(nu, s, m, b)
                ra = cyl_step(y[a], P[a], fr.take(a), obs.take(a), ca, dt, loglik, judge=ja)
                rb = cyl_step(y[b], P[b], fr.take(b), obs.take(b), c, dt, loglik, C[b], Pu[b], jb)
                self._C_out = np.zeros_like(C)
                self._C_out[b] = rb[7]
                out = []
                for i in range(6):  # y, P, nis, used, gated, m2ll
                    if ra[i] is None:
                        out.append(None)
                        continue
                    v = np.empty((y.shape[0],) + ra[i].shape[1:], ra[i].dtype)
                    v[a], v[b] = ra[i], rb[i]
                    out.append(v)
                frame = Frame(*(np.empty((y.shape[0],) + u.shape[1:], u.dtype) for u in ra[6]))
                for full, pa, pb in zip(frame, ra[6], rb[6]):
                    full[a], full[b] = pa, pb
                y, P, nis, used, gated, m2ll = out
                return y, P, frame, nis, used, gated, m2ll, None
            else:
                y, P, nis, used, gated, m2ll, fr = cyl_step(y, P, fr, obs, c, dt, loglik, judge=judge)
            return y, P, fr, nis, used, gated, m2ll, None
        y, P, nis, used, gated, m2ll, V, CV = position_only_step(y, P, obs, c, dt, loglik, judge)
        return y, P, fr, nis, used, gated, m2ll, (V, CV)

    def process(self, t_gps_s: float, obs: ObserverEpoch, new_incarnation=None):
        """The filter step of epoch t on arrays (T trials): predict + update the initialised
        trials (and their mirror hypotheses while alive), initialise those whose window is
        complete.  new_incarnation (T, N) bool or None ("consider"): observer slots whose UAV
        restarted (a new incarnation of its source) since its last message -- their consider
        cross-covariances are reset first (:meth:`_reset_slots`)."""
        t = float(t_gps_s)
        if obs.n_trials != self.n_trials:
            raise ValueError(f"obs has {obs.n_trials} trials, the locator {self.n_trials}")
        if self.t_gps_s is not None and t < self.t_gps_s:
            raise ValueError(f"t_gps_s must not go back: {t} < {self.t_gps_s}")
        dt = 0.0 if self.t_gps_s is None else t - self.t_gps_s
        c = self.config
        self._report = None
        if new_incarnation is not None and c.observer_uncertainty == "consider":
            self._reset_slots(np.asarray(new_incarnation, bool))
        if c.init == "prior":  # start from the scenario's prior; this epoch is the first update
            for k in np.flatnonzero(~self.initialised):
                self._initialise(k, self._prior_fix(), t, obs.take(slice(k, k + 1)))
        if c.min_formation_sigmas > 0:
            obs = self._drop_unresolved(obs)
        on = np.flatnonzero(self.initialised)
        alt = np.flatnonzero(self.alt_active)
        self.nis[:] = np.nan
        self.n_used[:] = 0
        if on.size:
            n = on.size
            if alt.size == 0 and n == self.n_trials:  # every row, in order: plain copies
                sub = obs
                y0, P0 = self.y.copy(), self.P.copy()
                fr0 = Frame(*(u.copy() for u in self.frame))
                C0 = self._grow_C(obs.mask.shape[1])[0]
                Pu0 = self.uav_cov_prev[:, :obs.mask.shape[1]]
            else:
                rows = np.concatenate([on, alt])
                sub = obs.take(rows)
                y0 = np.concatenate([self.y[on], self.alt_y[alt]])
                P0 = np.concatenate([self.P[on], self.alt_P[alt]])
                fr0 = Frame(*(np.concatenate([u[on], v[alt]]) for u, v in zip(self.frame, self.alt_frame)))
                Cm, Ca = self._grow_C(obs.mask.shape[1])
                C0 = np.concatenate([Cm[on], Ca[alt]])
                Pu = self.uav_cov_prev[:, :obs.mask.shape[1]]
                Pu0 = np.concatenate([Pu[on], Pu[alt]])
            acq = None
            if c.observer_uncertainty == "consider" and c.acquire_s > 0:
                started = self.init_t_gps_s[np.concatenate([on, alt])]
                acq = t - started < c.acquire_s - 1e-9
            judge = None
            if self._mon is not None:
                judge = functools.partial(self._judge, np.concatenate([on, alt]), n, t)
                self._mon_next = None
            y, P, fr, nis, used, gated, m2ll, vel = self._filter(y0, P0, fr0, sub, dt, alt.size > 0, C0, Pu0, acq,
                                                                 judge)
            if self._mon is not None and self._mon_next is not None:
                self._mon_state, self._mon_next = self._mon_next, None
            self.y[on], self.P[on], self.nis[on] = y[:n], P[:n], nis[:n]
            self.alt_y[alt], self.alt_P[alt] = y[n:], P[n:]
            if c.observer_uncertainty == "consider":
                self.C[on], self.alt_C[alt] = self._C_out[:n], self._C_out[n:]
            for full, part, fa in zip(self.frame, fr, self.alt_frame):
                full[on] = part[:n]
                fa[alt] = part[n:]
            if vel is not None:
                self.vel_doppler[on], self.vel_doppler_cov[on] = vel[0][:n], vel[1][:n]
                self.alt_vel[alt] = vel[0][n:]
            if alt.size:
                row_of = {k: i for i, k in enumerate(on)}
                self.score[alt] += m2ll[[row_of[k] for k in alt]]
                self.alt_score[alt] += m2ll[n:]
            used, gated = used[:n], gated[:n]
            n_used = used.sum(axis=-1)
            self.n_used[on] = n_used
            self.counters["gated"] += int(gated.sum())
            self.counters["used"] += int(used.sum())
            self.coast_s[on] = np.where(n_used >= 3, 0.0, self.coast_s[on] + dt)
            mode = np.where(n_used >= 3, "fused", np.where(n_used > 0, "degraded", "coast"))
            mode = np.where(self.coast_s[on] > c.max_coast_s, "lost", mode)
            self.mode[on] = mode
            modes = mode.tolist()
            for name in ("fused", "degraded", "coast", "lost"):
                self.counters[f"epochs_{name}"] += modes.count(name)
            # resolve the mirror hypotheses that are decided or whose time is up: keep the likelier
            done = (t >= self.resolve_at[alt] - 1e-9) | (np.abs(self.alt_score[alt] - self.score[alt])
                                                         >= c.init_resolve_llr)
            for k in alt[done]:
                self.alt_active[k] = False
                if self.alt_score[k] < self.score[k]:
                    self.y[k], self.P[k] = self.alt_y[k], self.alt_P[k]
                    self.C[k] = self.alt_C[k]
                    for full, fa in zip(self.frame, self.alt_frame):
                        full[k] = fa[k]
                    self.vel_doppler[k] = self.alt_vel[k]
                    self.start_side[k] = True
                    self.counters["mirror_chosen"] += 1
                else:
                    self.counters["mirror_dropped"] += 1
        if c.observer_uncertainty == "consider":  # the UAVs' covariances sent this epoch, per slot
            self._grow_C(obs.mask.shape[1])
            Pu = self.uav_cov_prev[:, :obs.mask.shape[1]]
            Pu[obs.mask] = obs.cov[obs.mask]
        for k in np.flatnonzero(~self.initialised):  # (none left with a prior)
            if obs.mask[k].sum() >= 3:
                self._window[k].append((t, obs.take(slice(k, k + 1))))
            if len(self._window[k]) >= c.init_epochs:
                self._initialise(k, init_fix(self._window[k], c), t)
        self.t_gps_s = t
        return self

    # ---------------------------------------------------------------- integrity
    def _judge(self, trial_of_row, n_primary, t, nu, s_diag, mask, rows=None):
        """The integrity monitor's verdict on one filter call's rows (module docstring,
        "Integrity"): the primary tracks' rows are judged (beta = nu / sqrt(S), S at the prior),
        their mirror hypotheses (rows of the same trials) take the same verdict.  Returns mask
        less the links left out this epoch."""
        c = self.config
        cfg = c.integrity
        L = int(c.integrity_max_links)
        idx = np.arange(len(trial_of_row)) if rows is None else np.asarray(rows)
        trial = trial_of_row[idx]
        prim = np.flatnonzero(idx < n_primary)
        if prim.size == 0:
            return mask
        tr = trial[prim]
        k, N = tr.size, mask.shape[1]
        Nm = min(N, L)
        cnt = self.counters
        if N > L:
            cnt["integrity_unmonitored"] += int(mask[prim, L:].sum())
        mp = mask[prim, :Nm]
        nup, sp = nu[prim, :Nm], s_diag[prim, :Nm]
        Z = np.full((k, 2 * L), np.nan)
        R = np.ones((k, 2 * L))
        Z[:, :2 * Nm] = np.where(mp[..., None], nup, np.nan).reshape(k, 2 * Nm)
        R[:, :2 * Nm] = np.where(mp[..., None], sp, 1.0).reshape(k, 2 * Nm)
        # a trial whose links mostly jump at once is not judged: its track moved, not one link
        jl = ((np.abs(nup) >= cfg.jump_sigma * np.sqrt(sp)).any(axis=-1) & mp).sum(axis=-1)
        common = jl > c.integrity_common_fraction * np.maximum(mp.sum(axis=-1), 1)
        Z[common] = np.nan
        cnt["integrity_common_mode"] += int(common.sum())
        got = {}

        def verdict(x, P, z, gm, **kw):  # the monitor's verdict only: the locator's own update follows
            got["inert"] = np.asarray(gm.inert)

        prev = self._mon_state
        _, sub, rep = self._mon.step(prev.take(tr), np.zeros((k, 1)), np.zeros((k, 1, 1)), Z,
                                     _ZeroModel(R), self._mon_ch, update=verdict, backend=c.backend)
        self._mon_next = prev.merge(self._mon_next, tr, sub)
        cnt["integrity_epochs"] += 1
        out_link = got["inert"].reshape(k, L, 2).any(axis=-1)[:, :Nm] & mp  # present links left out
        # no redundancy left (fewer than integrity_min_links would stay): detect only
        short = (mp.sum(axis=-1) - out_link.sum(axis=-1)) < c.integrity_min_links
        cnt["integrity_detect_only"] += int((short & out_link.any(axis=-1)).sum())
        out_link[short] = False
        cnt["integrity_links_left_out"] += int(out_link.sum())
        cnt["integrity_exclusions"] += int(rep.newly_excluded.sum())
        cnt["integrity_readmissions"] += int(rep.readmitted.sum())
        uid = {s: u for u, s in self._slot.items()}
        self._ev_trials = tr
        evs = self.integrity_events(rep, self._mon_ch, t, lambda b, ch: f"{self.beacon_id}.uav{uid[ch]}" if ch in uid
                                    else f"{self.beacon_id}.slot{ch}", cfg)
        cnt["integrity_events"] += len(evs)
        bad = np.zeros((self.n_trials, N), bool)
        bad[tr, :Nm] = out_link
        return mask & ~bad[trial]

    def _drop_unresolved(self, obs: ObserverEpoch) -> ObserverEpoch:
        """Tracks in plain ECEF whose >= 3 present UAVs form a formation smaller than their own
        position errors (second singular value of the estimated positions below
        min_formation_sigmas x their RMS per-axis position sigma) use no beacon measurement
        this epoch (counted).  Not before a track starts (the blind start's window takes its
        own epochs) nor in the formation-cylindrical coordinates (a line-like formation far
        from the beacon: there the UAVs' plane is the coordinates' business)."""
        m = obs.mask
        n = m.sum(axis=-1)
        live = self.initialised & self.frame.cart
        cand = (n >= 3) & live
        # fewer than 3 UAVs present (lost or late links) while the last epoch with >= 3 showed an
        # unresolved formation (or none has yet): their ranges cannot tell the side of the UAVs'
        # plane either -- used, 20 % random loss took 2 of 40 printed-geometry trials onto the
        # mirror (seeds 1-5, 300 s), none with this rule
        bad = (n > 0) & (n < 3) & live & ~self.formation_resolved
        if cand.any():
            c = _sum(obs.pos * m[..., None], axis=-2) / np.maximum(n, 1)[:, None]
            d = (obs.pos - c[:, None]) * m[..., None]
            sv2 = np.sqrt(np.maximum(np.linalg.eigvalsh(np.swapaxes(d, -1, -2) @ d)[:, 1], 0.0))
            var = np.trace(obs.cov[..., 0:3, 0:3], axis1=-2, axis2=-1) / 3.0
            sig = np.sqrt(_sum(var * m, axis=-1) / np.maximum(n, 1))
            small = cand & (sv2 < self.config.min_formation_sigmas * sig)
            self.formation_resolved[cand] = ~small[cand]
            bad |= small
        if not bad.any():
            return obs
        self.counters["epochs_formation_unresolved"] += int(bad.sum())
        return obs._replace(mask=m & ~bad[:, None])

    def _grow_C(self, N: int):
        """The consider cross-covariances (T, N, n, 6) of the tracks and of the mirror hypotheses,
        grown to N observer slots (zeros for new ones), and the UAVs' last covariances with them."""
        if self.C.shape[1] < N:
            T, n = self.y.shape
            for name, m in (("C", n), ("alt_C", n), ("uav_cov_prev", 6)):
                old = getattr(self, name)
                new = np.zeros((T, N, m, 6))
                new[:, :old.shape[1]] = old
                setattr(self, name, new)
        return self.C[:, :N], self.alt_C[:, :N]

    def _to_state(self, x, P, ob: ObserverEpoch):
        """ECEF (x (6,), P (6, 6)) -> (state, covariance, frame) of this locator's model."""
        if self.config.motion == "position":
            return x[0:3].copy(), P[0:3, 0:3].copy(), None
        fr = formation_frame(ob.pos, ob.mask, x[None, 0:3], None, self.config.axis_ratio)
        if self.config.init == "prior":  # plain ECEF (module docstring)
            fr = fr._replace(cart=np.ones(1, bool))
        y, Gi, _ = ecef_to_cyl(x[None], fr, jacobian=True)
        Py = Gi[0] @ P @ Gi[0].T
        return y[0], 0.5 * (Py + Py.T), fr

    def _prior_fix(self) -> InitFix:
        """The configured prior as an InitFix (no mirror)."""
        m = np.array(self.config.prior_mean, dtype=float)
        C = np.array(self.config.prior_cov, dtype=float)
        return InitFix(m, C, m[0:3].copy(), 0, 0.0, 0, m.copy(), C.copy(), math.inf)

    def _initialise(self, k: int, fix: InitFix, t: float, ob: ObserverEpoch | None = None) -> None:
        c = self.config
        ob = self._window[k][-1][1] if ob is None else ob
        self.init_t_gps_s[k] = t
        self.init_info[k] = fix
        self.init_window_last[k] = ob
        self._window[k] = []
        self.initialised[k] = True
        self.formation_resolved[k] = False
        y, P, fr = self._to_state(fix.x, fix.P, ob)
        self.y[k], self.P[k] = y, P
        if fr is not None:
            for full, part in zip(self.frame, fr):
                full[k] = part[0]
        self.vel_doppler[k] = fix.x[3:6]
        self.vel_doppler_cov[k] = fix.P[3:6, 3:6]
        self.mode[k] = "fused"
        self.coast_s[k] = 0.0
        self.C[k] = 0.0
        self.alt_C[k] = 0.0
        self.counters["initialised"] += 1
        d = fix.mirror_x[0:3] - fix.x[0:3]
        if c.init_resolve_s > 0 and d @ np.linalg.solve(fix.P[0:3, 0:3], d) > 9.0:
            y, P, fr = self._to_state(fix.mirror_x, fix.mirror_P, ob)
            self.alt_active[k] = True
            self.alt_y[k], self.alt_P[k] = y, P
            if fr is not None:
                for full, part in zip(self.alt_frame, fr):
                    full[k] = part[0]
            self.alt_vel[k] = fix.mirror_x[3:6]
            self.score[k] = fix.cost
            self.alt_score[k] = fix.mirror_cost
            self.resolve_at[k] = t + c.init_resolve_s
            self.counters["mirror_hypotheses"] += 1

    # ---------------------------------------------------------------- output
    def _moments(self, y, P, fr, vel_doppler, vel_cov, on=None):
        """ECEF moments of states (rows where ``on``, default: initialised)."""
        T = y.shape[0]
        on = self.initialised if on is None else on
        if self.config.motion == "cv":
            if on.all():  # every row (the steady state): no gather / scatter copies
                return ut_to_ecef(y, P, fr)
            x = np.zeros((T, 6))
            Px = np.broadcast_to(np.eye(6), (T, 6, 6)).copy()
            rows = np.flatnonzero(on)
            if rows.size:
                x[rows], Px[rows] = ut_to_ecef(y[rows], P[rows], fr.take(rows))
            return x, Px
        x = np.concatenate([y, vel_doppler], axis=-1)
        Px = np.zeros((T, 6, 6))
        Px[:, 0:3, 0:3] = P
        Px[:, 3:6, 3:6] = vel_cov
        return x, Px

    def state_ecef(self):
        """(x (T, 6), P (T, 6, 6)) over ECEF [B, V_B] of every trial (meaningful where
        ``initialised``): the unscented moments of the cylindrical state, or for the
        position-only filter its position with the Doppler velocity (cross-covariance 0)."""
        if self._report is not None:
            return self._report
        x, P = self._moments(self.y, self.P, self.frame, self.vel_doppler, self.vel_doppler_cov)
        alt = np.flatnonzero(self.alt_active)
        if alt.size:
            # while the mirror hypothesis is alive the posterior is the two-component mixture:
            # weights from the summed likelihoods, moments matched (the MMSE estimate)
            xa, Pa = self._moments(self.alt_y[alt], self.alt_P[alt], self.alt_frame.take(alt), self.alt_vel[alt],
                                   self.vel_doppler_cov[alt], np.ones(alt.size, bool))
            w = 1.0 / (1.0 + np.exp(np.clip(0.5 * (self.alt_score[alt] - self.score[alt]), -700, 700)))
            w0 = 1.0 - w
            xm = w0[:, None] * x[alt] + w[:, None] * xa
            d0, d1 = x[alt] - xm, xa - xm
            P[alt] = (w0[:, None, None] * (P[alt] + d0[:, :, None] * d0[:, None, :])
                      + w[:, None, None] * (Pa + d1[:, :, None] * d1[:, None, :]))
            x[alt] = xm
        self._report = (x, P)
        return self._report

    def estimates(self):
        """One ``Estimate`` per initialised trial: [(run_id, Estimate)]."""
        x, P = self.state_ecef()
        out = []
        for k in np.flatnonzero(self.initialised):
            seq = self._seq.get(k, 0)
            self._seq[k] = seq + 1
            out.append((self.run_ids[k], Estimate(t_gps_s=self.t_gps_s, source_id=self.source_id, seq=seq,
                                                  kind="beacon", pos_ecef_m=x[k, 0:3], vel_ecef_m_s=x[k, 3:6],
                                                  cov=0.5 * (P[k] + P[k].T), nis=float(self.nis[k]),
                                                  mode=str(self.mode[k]))))
        return out

    def publish(self) -> int:
        n = 0
        keys = self._keys
        for run, est in self.estimates():
            key = keys.get(run)
            if key is None:
                key = keys[run] = key_for(run, est, kind="beacon", id=self.beacon_id)
            self.transport.publish(key, est)
            n += 1
        self.counters["published"] += n
        return n

    def close(self) -> None:
        if self._sub is not None:
            self._sub.close()
            self._sub = None
