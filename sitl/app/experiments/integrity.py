"""`skyfuse experiment integrity`: seed 003, the integrity layer on faulty GNSS data.

World (sitl, truth): a GPS L1 receiver on a vehicle flying a great circle at constant speed
(seed 000's trajectory style: 55 N 37 E, 1 km, 50 m/s, heading 90 deg), 10 Hz, white noise
sigma_pr = 6 m, sigma_prr = 0.064 m/s (seed 000). The channels are the satellites above the
elevation mask all through the run (>= ``MIN_CHANNELS`` so that one faulty channel leaves
redundancy for isolation); a channel is one satellite's pseudorange and rate rows.
Sensor errors (seed 003's model): on top of the white noise, one first-order Gauss-Markov
pseudorange error per satellite (sitl.measfault.GaussMarkov), sigma ``gm_sigma_m`` = 2 m,
tau ``gm_tau_s`` = 100 s: the slowly varying residual of the broadcast ionosphere / troposphere
corrections, the satellite clock and ephemeris (SISRE) and code multipath on a moving
airframe, lumped (typical L1 C/A budgets: iono residual 1-5 m over tens of minutes, SISRE
~1 m over hours, multipath 0.5-2 m over seconds to minutes; 2 m / 100 s sits in between). The
simulated receiver's own atmosphere is switched off (its delays are what this residual
models); the receiver clock is seed 000's TCXO.
Faults (seed 003's instrumental causes; sitl.measfault.FaultInjector, drawn per trial from
the seeded Generator): a step on one random satellite's pseudorange (|magnitude| uniform in
``step_sigma`` x sigma_ref, sigma_ref = sqrt(sigma_pr^2 + gm_sigma^2), random sign, lasting
``step_duration_s``), a pseudorange-only ramp on another satellite (|rate| uniform in
``ramp_rate_m_s``, random sign, to the end of the run), heavy-tailed multipath outliers on
every pseudorange (probability ``outlier_prob`` per epoch, scale sigma_pr x Student-t with
``outlier_dof`` degrees of freedom) and a dropout (both rows of one random satellite missing
for ``dropout_s``); onsets uniform in [``onset_min_s``, ``onset_max_frac`` x duration].

Filters, all on the same faulty data (truth never enters a filter; the satellite states come
from world.ephemeris_for_filter at the measured transit time):
* ``plain``: EKF, PseudorangeDoppler on x = [p(3), clock bias, v(3), clock drift] with a
  constant-velocity + random-walk-clock transition; R = white + GM variance, the GM error
  treated as white noise. Missing rows are skipped (the monitor in detect-only mode, which
  is bitwise the plain filter otherwise).
* ``adaptive_robust``: the same EKF wrapped by filters.integrity.IntegrityMonitor (jump and
  window tests, isolation per channel, Huber weights, innovation-based R) with seed 000's
  eq 7 adaptive Q (filters.adaptive) on the dynamic states.
* ``adaptive_robust_with_bias_estimation``: that plus one GM pseudorange-bias state per
  channel (sigma, tau as the world's: the filter knows the error model, not its values), so
  the slow errors are estimated and compensated rather than treated as white noise; R is
  then the white noise only.
Beside them, on the fault-free data of the same world (before injection): the plain EKF
with and without the monitor (same IntegrityConfig), to show that the monitor costs nothing
when nothing is wrong (``fault_free``: paired per-trial comparison).

Scoring (result.json ``detection`` is the monitor of the adaptive-robust filter with bias
estimation: its model matches the world, so its healthy innovations are white N(0, 1) as the
seed's tests assume; the plain-model adaptive-robust filter's monitor, whose innovations carry
the unmodelled GM errors (correlated over the window: its window tests over-alarm), is beside it
under ``detection_by_filter``): an alarm on a channel-epoch is a jump or window-test alarm on
any of its rows.
* step: detected if an alarm on its channel at the onset epoch or the next;
* ramp: an alarm on its channel within ``ramp_detect_s`` of the onset;
* outlier: outliers of >= 5 sigma_ref (on channels with no step or ramp) alarmed at their epoch;
* pfa: alarms per channel-epoch with no fault of any kind on that channel now or within the
  last ``window`` epochs (the window statistics remember a fault that long), after the
  warm-up; with the exact (Clopper-Pearson) 95 % interval.
* mean_delay_s: over the detected events, onset to the first alarm.
* ramp.oracle (code-only ramps): the bound on any detector, ramp_oracle_pd: the Pd within
  ``ramp_detect_s`` of an oracle that knows the faulty channel, the onset and the receiver's state,
  testing at every epoch at the Pfa target; averaged over the same ramps as ``ramp.pd``.
* position_rmse_m: 3-D position error, RMS over trials and the epochs after the warm-up.
ROC: the statistics of the adaptive-robust run (jump: the channel's max |beta|; window: the
channel's max of bias_stat / its threshold and drift_stat / its threshold) swept over
thresholds offline, Pd per fault kind against Pfa per channel-epoch of that statistic alone;
the operating point (the chosen thresholds) is marked. The sweep is open-loop: the run's
exclusions happened at the operating point.
"""
from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.stats

from filters.adaptive import AdaptiveQ
from filters.ekf import ekf_predict
from filters.integrity import IntegrityConfig, IntegrityMonitor
from filters.models import (
    ClockRandomWalk,
    Composite,
    ConstantVelocity,
    JointMeasurement,
    PseudorangeDoppler,
)
from sitl import geodesy
from sitl.app.experiments.common import prepare_out, progress_printer, save_figure, strict
from sitl.gnss import orbits
from sitl.gnss.clock import ClockModel
from sitl.gnss.receiver import Receiver, ReceiverConfig
from sitl.gnss.world import elevation_grid, ephemeris_for_filter, geometry_track
from sitl.measfault import FAULT_KINDS, Fault, FaultInjector, GaussMarkov
from sitl.app.args import OUTPUT_DIR
from sitl.app.experiments.ranges import within
from sitl.params import (
    ParamError, add_flags, backend_option, choice, default_of, integer, number, optional, param, quiet_option,
    require, switch, validate,
)

__all__ = ["IntegrityScenario", "run", "FILTERS", "MIN_CHANNELS", "main"]

MIN_CHANNELS = 7
FILTERS = ("plain", "adaptive_robust", "adaptive_robust_with_bias_estimation")
# fault-free pairs (the same world before injection): each EKF without and with the monitor
CLEAN = ("plain_fault_free", "monitored_fault_free", "bias_states_fault_free", "bias_states_monitored_fault_free")
MONITORED = ("adaptive_robust", "adaptive_robust_with_bias_estimation", "monitored_fault_free",
             "bias_states_monitored_fault_free")
BIASED = ("adaptive_robust_with_bias_estimation", "bias_states_fault_free", "bias_states_monitored_fault_free")
N_BASE = 8  # [p(3), clock bias, v(3), clock drift]
IDX_BIAS, IDX_DRIFT = 3, 7
ORDER = (0, 1, 2, 6, 3, 4, 5, 7)  # x = s[ORDER], s = [CV p(3) v(3), clock bias, drift]
DYNAMIC = tuple(range(N_BASE))
# the filter whose monitor `detection` reports: the one whose model matches the world (the GM errors are
# states), so its healthy innovations are white N(0, 1) as the seed's tests assume; the plain-model
# adaptive-robust filter's monitor is reported beside it (detection_by_filter)
DETECTION_FILTER = "adaptive_robust_with_bias_estimation"
FIGURES = ("integrity_roc.png", "integrity_position_error.png")
RAMP_KINDS = ("code", "clock")
K_STEP, K_RAMP, K_OUT, K_DROP = (FAULT_KINDS.index(k) + 1 for k in ("step", "ramp", "outlier", "dropout"))

# scenario field -> command-line flag, to name the flag in a usage error
FLAGS = {"duration_s": "--duration", "sigma_pr_m": "--sigma-pr", "sigma_prr_m_s": "--sigma-prr",
         "el_mask_deg": "--el-mask-deg", "gm_sigma_m": "--gm-sigma", "gm_tau_s": "--gm-tau",
         "jump_sigma": "--jump-sigma", "window": "--window", "window_alpha": "--window-alpha",
         "bias_alpha": "--bias-alpha", "huber_c": "--huber-c", "outlier_prob": "--outlier-prob",
         "onset_min_s": "--duration", "warmup_s": "--duration"}


class GaussMarkovBank:
    """Transition of ``n`` independent first-order Gauss-Markov states (the filter's model of
    the per-satellite pseudorange biases): F = e^(-dt/tau) I, Q = sigma^2 (1 - e^(-2dt/tau)) I."""

    linear = True

    def __init__(self, n: int, sigma: float, tau_s: float):
        self.ndim, self.sigma, self.tau_s = int(n), float(sigma), float(tau_s)

    def f(self, x, dt):
        return np.asarray(x, dtype=float) * math.exp(-dt / self.tau_s)

    def F(self, x, dt):
        return math.exp(-dt / self.tau_s) * np.eye(self.ndim)

    def Q(self, dt):
        return self.sigma**2 * -math.expm1(-2.0 * dt / self.tau_s) * np.eye(self.ndim)


class BiasedPseudorangeDoppler(JointMeasurement):
    """PseudorangeDoppler with the pseudorange of satellite i biased by the state x[col0 + i]
    (h += b_i, dh/db_i = 1); R is the white noise only."""

    def __init__(self, base: PseudorangeDoppler, col0: int):
        self.base, self.col0 = base, int(col0)
        self.S = base.n_sats

    def h_and_H(self, x):
        hx, H = self.base.h_and_H(x)
        hx = np.array(hx, dtype=float)
        H = np.array(H, dtype=float)
        cols = self.col0 + np.arange(self.S)
        hx[..., : self.S] += x[..., cols]
        H[..., np.arange(self.S), cols] = 1.0
        return hx, H

    def R_diag(self):
        return self.base.R_diag()

    def R(self):
        d = self.R_diag()
        return d[..., None] * np.eye(d.shape[-1])


_POSITIVE = number(0, lo_open=True)
_NON_NEGATIVE = number(0)
_FINITE = number()
_PROBABILITY_OPEN = within(0, 1, lo_open=True, hi_open=True)


def _pair(lo_open: bool = False):
    """A (low, high) pair of finite numbers, 0 <= low <= high (0 < low if lo_open), stored as a tuple
    of floats: a uniform draw's range."""
    what = f"a pair 0 {'<' if lo_open else '<='} low <= high"
    end = number(0, lo_open=lo_open, what=what)

    def check(key, v):
        try:
            a, b = v
        except (TypeError, ValueError):
            raise ParamError(key, f"expected a (low, high) pair, got {v!r}") from None
        try:
            a, b = end("", a), end("", b)
        except ParamError:
            a = b = None
        if a is None or not a <= b:
            raise ParamError(key, f"expected {what}, got {v!r}")
        return (a, b)

    return check


@dataclass(frozen=True)
class IntegrityScenario:
    """Seed 003 integrity scenario (documented choices in the module docstring)."""

    duration_s: float = param(300.0, check=_POSITIVE, doc="simulated time, s")
    dt_s: float = param(0.1, check=_POSITIVE, doc="epoch interval of the receiver and the filters, s (10 Hz)")
    sigma_pr_m: float = param(6.0, check=_POSITIVE, doc="pseudorange white noise (1 sigma), m (seed 000)")
    sigma_prr_m_s: float = param(0.064, check=_POSITIVE, doc="pseudorange-rate white noise (1 sigma), m/s (seed 000)")
    el_mask_deg: float = param(10.0, check=within(5, 90, hi_open=True),
                               doc="elevation mask, deg; the channels are the satellites above it all through "
                                   f"the run (>= {MIN_CHANNELS} needed)")
    systems: str = param("G", check=choice("G", "R", "GR"), doc="constellations: G (GPS), R (GLONASS) or GR")
    lat_deg: float = param(55.0, check=_FINITE, doc="latitude of the trajectory's start, deg")
    lon_deg: float = param(37.0, check=_FINITE, doc="longitude of the trajectory's start, deg")
    h_m: float = param(1000.0, check=_FINITE, doc="height of the trajectory above the ellipsoid, m")
    speed_m_s: float = param(50.0, check=_POSITIVE, doc="ground speed along the great circle, m/s")
    heading_deg: float = param(90.0, check=_FINITE, doc="initial heading of the great circle from north, deg")
    t0_gps_s: float = param(orbits.DEFAULT_TOA_GPS_S + 3600.0, check=_FINITE,
                            doc="GPS time of the first epoch, s (an hour after the almanac's reference time)")
    # sensor errors: per-satellite GM pseudorange errors
    gm_sigma_m: float = param(2.0, check=_NON_NEGATIVE,
                              doc="sigma of the per-satellite Gauss-Markov pseudorange error (the lumped residual "
                                  "of iono/tropo corrections, SISRE and multipath), m")
    gm_tau_s: float = param(100.0, check=_POSITIVE, doc="correlation time of that Gauss-Markov error, s")
    # faults
    faults: bool = param(True, check=switch(), doc="inject the faults (step, ramp, outliers, dropout); false: the "
                                                  "same world without them")
    step_sigma: tuple = param((5.0, 20.0), check=_pair(),
                              doc="range of the step's |magnitude| (uniform), in units of sigma_ref = "
                                  "sqrt(sigma_pr^2 + gm_sigma^2)")
    step_duration_s: tuple = param((30.0, 120.0), check=_pair(lo_open=True),
                                   doc="range of the step's duration (uniform), s")
    ramp_rate_m_s: tuple = param((0.5, 2.0), check=_pair(), doc="range of the ramp's |rate| (uniform), m/s")
    ramp_kind: str = param("code", check=choice(*RAMP_KINDS),
                           doc="code: the pseudorange alone drifts (code multipath / signal distortion: no Doppler "
                               "trace); clock: a satellite clock frequency fault, so the pseudorange rate carries "
                               "the rate too")
    outlier_prob: float = param(0.002, check=within(0, 1),
                                doc="probability of a multipath outlier per pseudorange-epoch")
    outlier_dof: float = param(2.0, check=_POSITIVE,
                               doc="degrees of freedom of the outliers' Student-t (scale sigma_pr_m)")
    dropout_s: tuple = param((1.0, 5.0), check=_pair(lo_open=True),
                             doc="range of the dropout's length (uniform; both rows of one satellite missing), s")
    onset_min_s: float = param(60.0, check=_NON_NEGATIVE, doc="earliest fault onset, s")
    onset_max_frac: float = param(0.7, check=within(0, 1, lo_open=True),
                                  doc="latest fault onset as a fraction of duration_s")
    warmup_s: float = param(30.0, check=_NON_NEGATIVE, doc="warm-up before the scoring starts, s")
    ramp_detect_s: float = param(10.0, check=_POSITIVE, doc="a ramp counts as detected within this time of "
                                                           "its onset, s")
    # filter
    q_accel_m2_s3: float = param(0.01, check=_NON_NEGATIVE,
                                 doc="white-acceleration PSD of the filters' constant-velocity model, m^2/s^3")
    sigma0_pos_m: float = param(30.0, check=_POSITIVE, doc="prior position sigma per axis (a coarse fix), m")
    sigma0_vel_m_s: float = param(1.0, check=_POSITIVE, doc="prior velocity sigma per axis, m/s")
    sigma0_clock_bias_m: float = param(300.0, check=_POSITIVE,
                                       doc="receiver clock bias sigma (the truth's draw and the prior), m")
    sigma0_clock_drift_m_s: float = param(3.0, check=_POSITIVE,
                                          doc="receiver clock drift sigma (the truth's draw and the prior), m/s")
    adaptive_q_decay: float = param(0.1, check=within(0, 1, hi_open=True),
                                    doc="decay of the eq 7 adaptive Q (filters.adaptive) on the dynamic states")
    adaptive_q_gain: float = param(0.7, check=_NON_NEGATIVE, doc="gain of the eq 7 adaptive Q")
    # the monitor (IntegrityConfig)
    jump_sigma: float = param(3.3, check=number(0, lo_open=True, finite=False, what="a positive number"),
                              doc="the monitor's jump test threshold on |beta| (inf: no jump test)")
    window: int = param(50, check=integer(lo=1), doc="window of the monitor's drift tests, epochs")
    window_alpha: float = param(1e-4, check=_PROBABILITY_OPEN,
                                doc="false-alarm probability of the mean-square window test per row-epoch")
    bias_alpha: float | None = param(2e-4, check=optional(_PROBABILITY_OPEN),
                                     doc="false-alarm probability of the bias window test per row-epoch "
                                         "(None: no bias test)")
    persist: int = param(2, check=integer(lo=1), doc="consecutive jump epochs that exclude a channel")
    # 10 s of quarantine without a jump: a pseudorange ramp that is still there (and that the
    # bias-state filter partly absorbs) grows into a jump before the channel comes back. Picked
    # from 20 / 100 / 300 / 450 epochs on 60 trials (seed 3): bias-state RMSE 8.97 / 3.47 / 3.41 /
    # 3.41 m, adaptive-robust 3.88 / 3.99 / 4.49 / 5.09 m, Pfa 1.0e-3 / 1.3e-3 / 3.2e-3 / 5.6e-3
    readmit_after: int = param(100, check=integer(lo=1),
                               doc="consecutive clean epochs before an excluded channel comes back")
    huber_c: float | None = param(2.0, check=optional(_POSITIVE),
                                  doc="Huber threshold on |beta| (None: plain quadratic update)")
    r_forget: float = param(0.02, check=within(0, 1, lo_open=True),
                            doc="forgetting factor of the monitor's innovation-based R estimate")

    def __post_init__(self):
        validate(self)
        require(self.dt_s <= self.duration_s, "duration_s", f"must be >= dt_s = {self.dt_s!r}, got {self.duration_s!r}")
        require(not self.faults or self.onset_min_s < self.onset_max_frac * self.duration_s, "duration_s",
                f"must leave room for the fault onsets: onset_min_s {self.onset_min_s:g} s >= "
                f"{self.onset_max_frac:g} x duration_s {self.duration_s:g} s")
        require(self.warmup_s < self.duration_s, "duration_s",
                f"must be > warmup_s = {self.warmup_s:g} s, got {self.duration_s:g}")
        self.monitor_config()  # its own validation; messages name the field
        n = len(self.channel_sats())
        require(n >= MIN_CHANNELS, "el_mask_deg",
                f"{self.el_mask_deg!r} leaves only {n} satellites in view all through the run "
                f"(>= {MIN_CHANNELS} needed for isolation with redundancy)")

    # ------------------------------------------------------------------ derived
    @property
    def n_epochs(self) -> int:
        return round(self.duration_s / self.dt_s) + 1

    @property
    def sigma_ref_m(self) -> float:
        """The pseudorange's total nominal error sigma (white + GM): the unit of step sizes."""
        return math.hypot(self.sigma_pr_m, self.gm_sigma_m)

    def times(self) -> np.ndarray:
        return np.arange(self.n_epochs) * self.dt_s

    def constellation(self):
        return orbits.default_constellation(self.systems)

    def receiver_config(self) -> ReceiverConfig:
        # the atmosphere's residual is in the GM errors; the receiver adds only white noise
        return ReceiverConfig(sigma_pr_m=self.sigma_pr_m, sigma_prr_m_s=self.sigma_prr_m_s,
                              el_mask_rad=math.radians(self.el_mask_deg), iono_zenith_m=0.0, tropo_zenith_m=0.0,
                              gps_glonass_offset_m=0.0)

    def monitor_config(self) -> IntegrityConfig:
        return IntegrityConfig(jump_sigma=self.jump_sigma, window=self.window, window_alpha=self.window_alpha,
                               bias_alpha=self.bias_alpha, persist=self.persist, readmit_after=self.readmit_after,
                               huber_c=self.huber_c, adapt_r=True, r_forget=self.r_forget, isolate=True)

    def trajectory(self, t_rel_s):
        """True ECEF position and velocity (..., 3): a great circle at constant speed."""
        return geodesy.great_circle_track(self.lat_deg, self.lon_deg, self.h_m, self.speed_m_s, self.heading_deg,
                                          t_rel_s)

    def channel_sats(self) -> np.ndarray:
        """Constellation indices of the satellites above the mask all through the run (10 s grid)."""
        t = np.unique(np.append(np.arange(0.0, self.duration_s, 10.0), self.duration_s))
        pos, _ = self.trajectory(t)
        el = elevation_grid(self.constellation(), self.t0_gps_s + t, pos)
        # a margin: the receiver masks on the light-time geometry
        return np.flatnonzero(np.all(el >= math.radians(self.el_mask_deg) + math.radians(0.5), axis=0))

    # ------------------------------------------------------------------ filter models
    def transition(self, n_bias: int = 0):
        blocks = [ConstantVelocity(3, q=self.q_accel_m2_s3), ClockRandomWalk(ClockModel().psd_1_s)]
        order = ORDER
        if n_bias:
            blocks.append(GaussMarkovBank(n_bias, self.gm_sigma_m, self.gm_tau_s))
            order = ORDER + tuple(range(N_BASE, N_BASE + n_bias))
        return Composite(tuple(blocks), order)


def _faults(scn: IntegrityScenario, rng, trials: int, S: int):
    """The per-trial fault draws: (list of Fault on the (2S,) measurement columns, dict of truth)."""
    T_end = scn.duration_s
    lo, hi = scn.onset_min_s, scn.onset_max_frac * T_end
    dt = scn.dt_s

    def onset(n):  # on the epoch grid, so that onset epochs are exact
        return np.round(rng.uniform(lo, hi, n) / dt) * dt

    step_ch = rng.integers(0, S, trials)
    ramp_ch = (step_ch + rng.integers(1, S, trials)) % S  # another satellite
    drop_ch = rng.integers(0, S, trials)
    step_t0, ramp_t0, drop_t0 = onset(trials), onset(trials), onset(trials)
    step_mag = rng.uniform(*scn.step_sigma, trials) * scn.sigma_ref_m * rng.choice([-1.0, 1.0], trials)
    step_len = rng.uniform(*scn.step_duration_s, trials)
    ramp_rate = rng.uniform(*scn.ramp_rate_m_s, trials) * rng.choice([-1.0, 1.0], trials)
    drop_len = rng.uniform(*scn.dropout_s, trials)
    faults = []
    for i in range(trials):
        faults.append(Fault("step", int(step_ch[i]), float(step_t0[i]), float(step_t0[i] + step_len[i]),
                            magnitude=float(step_mag[i]), trial=i))
        faults.append(Fault("ramp", int(ramp_ch[i]), float(ramp_t0[i]), rate=float(ramp_rate[i]), trial=i))
        if scn.ramp_kind == "clock":  # the clock's frequency error shows in the pseudorange rate
            faults.append(Fault("step", S + int(ramp_ch[i]), float(ramp_t0[i]), magnitude=float(ramp_rate[i]),
                                trial=i))
    for c in range(S):
        if scn.outlier_prob > 0:
            faults.append(Fault("outlier", c, 0.0, prob=scn.outlier_prob, scale=scn.sigma_pr_m,
                                dof=scn.outlier_dof))
    for i in range(trials):  # last: a dropout overrides everything on its rows
        for col in (int(drop_ch[i]), S + int(drop_ch[i])):
            faults.append(Fault("dropout", col, float(drop_t0[i]), float(drop_t0[i] + drop_len[i]), trial=i))
    truth = {"step_ch": step_ch, "step_k0": np.round(step_t0 / dt).astype(int),
             "step_k1": np.round((step_t0 + step_len) / dt).astype(int), "step_mag": step_mag,
             "ramp_ch": ramp_ch, "ramp_k0": np.round(ramp_t0 / dt).astype(int), "ramp_rate": ramp_rate}
    return faults, truth


# ------------------------------------------------------------------ scoring helpers
J_GRID = np.linspace(0.0, 12.0, 601)  # thresholds on |beta|
W_GRID = np.logspace(-2, 4, 601)  # thresholds on the normalised window statistic (1 = operating point)


class _Score:
    """Detection bookkeeping of one monitored filter (scoring side: uses the injected truth)."""

    def __init__(self, scn, trials, S, truth):
        self.scn, self.N, self.S, self.tr = scn, trials, S, truth
        self.rows = np.arange(trials)
        self.n_healthy = 0
        self.n_fa = 0
        self.h_j = np.zeros(J_GRID.size, dtype=np.int64)  # healthy counts with stat > threshold
        self.h_w = np.zeros(W_GRID.size, dtype=np.int64)
        self.step_hit = np.zeros(trials, dtype=bool)
        self.step_stat = np.zeros(trials)
        self.step_first = np.full(trials, -1)
        self.ramp_hit = np.zeros(trials, dtype=bool)
        self.ramp_stat = np.zeros(trials)
        self.ramp_first = np.full(trials, -1)
        self.out_n = 0
        self.out_hit = 0
        self.out_stats = []
        self.out_first_k = []
        self.step_valid = np.ones(trials, dtype=bool)
        self.ramp_valid = np.ones(trials, dtype=bool)

    def epoch(self, k, rep, count, healthy, out_mask, missing_ch):
        scn, S = self.scn, self.S
        cfg_thr_b = scipy.stats.chi2.isf(scn.bias_alpha, 1)
        thr_ms = scipy.stats.chi2.isf(scn.window_alpha, count) / count
        alarm_rows = rep.jump | rep.drift
        alarm = alarm_rows[:, :S] | alarm_rows[:, S:]
        ab = np.abs(rep.beta)
        jstat = np.maximum(ab[:, :S], ab[:, S:])
        wr = np.maximum(rep.bias_stat / cfg_thr_b, rep.drift_stat / thr_ms)
        wstat = np.maximum(wr[:, :S], wr[:, S:])
        # healthy channel-epochs
        self.n_healthy += int(healthy.sum())
        self.n_fa += int((alarm & healthy).sum())
        self.h_j += np.searchsorted(np.sort(jstat[healthy]), J_GRID, side="right").astype(np.int64) * -1 \
            + int(healthy.sum())
        self.h_w += np.searchsorted(np.sort(wstat[healthy]), W_GRID, side="right").astype(np.int64) * -1 \
            + int(healthy.sum())
        r = self.rows
        tr = self.tr
        # steps: onset epoch and the next
        c = tr["step_ch"]
        for d in (0, 1):
            at = tr["step_k0"] + d == k
            if at.any():
                miss = missing_ch[r[at], c[at]]
                if d == 0:
                    self.step_valid[at] &= ~miss
                self.step_hit[at] |= alarm[r[at], c[at]]
                self.step_stat[at] = np.maximum(self.step_stat[at], jstat[r[at], c[at]])
        active = (k >= tr["step_k0"]) & (k < tr["step_k1"]) & (self.step_first < 0)
        first = active & alarm[r, c]
        self.step_first[first] = k
        # ramps: within ramp_detect_s of the onset
        c = tr["ramp_ch"]
        kd = round(scn.ramp_detect_s / scn.dt_s)
        win = (k >= tr["ramp_k0"]) & (k <= tr["ramp_k0"] + kd)
        if win.any():
            self.ramp_hit[win] |= alarm[r[win], c[win]]
            self.ramp_stat[win] = np.maximum(self.ramp_stat[win], wstat[r[win], c[win]])
            at0 = tr["ramp_k0"] == k
            self.ramp_valid[at0] &= ~missing_ch[r[at0], c[at0]]
        first = (k >= tr["ramp_k0"]) & (self.ramp_first < 0) & alarm[r, c]
        self.ramp_first[first] = k
        # outliers of >= 5 sigma_ref
        if out_mask.any():
            self.out_n += int(out_mask.sum())
            self.out_hit += int((alarm & out_mask).sum())
            self.out_stats.append(jstat[out_mask])

    def result(self):
        scn = self.scn
        dt = scn.dt_s
        tr = self.tr
        op_j = scn.jump_sigma

        def rate(k, n):
            lo, hi = (scipy.stats.binomtest(k, n).proportion_ci(0.95, method="exact") if n else (math.nan, math.nan))
            return {"value": k / n if n else math.nan, "ci95": [lo, hi], "count": int(k), "of": int(n)}

        sv, rv = self.step_valid, self.ramp_valid
        step_delay = (self.step_first - tr["step_k0"]) * dt
        ramp_delay = (self.ramp_first - tr["ramp_k0"]) * dt
        ds = self.step_hit & sv
        dr = self.ramp_hit & rv
        pfa = rate(self.n_fa, self.n_healthy)
        mag = np.abs(tr["step_mag"]) / scn.sigma_ref_m
        rr = np.abs(tr["ramp_rate"])
        step_bins = [(5.0, 10.0), (10.0, 20.0 + 1e-9)]
        ramp_bins = [(0.5, 1.0), (1.0, 2.0 + 1e-9)]
        out = {
            "step": {"pd": rate(int(ds.sum()), int(sv.sum())), "pfa": pfa,
                     "mean_delay_s": float(np.mean(step_delay[ds])) if ds.any() else None,
                     "by_magnitude_sigma": {f"{a:g}-{min(b, 20):g}": rate(int((ds & (mag >= a) & (mag < b)).sum()),
                                                                          int((sv & (mag >= a) & (mag < b)).sum()))
                                            for a, b in step_bins}},
            "ramp": {"pd": rate(int(dr.sum()), int(rv.sum())), "pfa": pfa,
                     "mean_delay_s": float(np.mean(ramp_delay[dr])) if dr.any() else None,
                     "by_rate_m_s": {f"{a:g}-{min(b, 2):g}": rate(int((dr & (rr >= a) & (rr < b)).sum()),
                                                                  int((rv & (rr >= a) & (rr < b)).sum()))
                                     for a, b in ramp_bins},
                     "detected_ever": rate(int(((self.ramp_first >= 0) & rv).sum()), int(rv.sum()))},
            "outlier": {"pd": rate(self.out_hit, self.out_n), "pfa": pfa, "mean_delay_s": 0.0 if self.out_hit else None},
        }
        # ROC (open loop over the recorded statistics)
        pfa_j = self.h_j / max(self.n_healthy, 1)
        pfa_w = self.h_w / max(self.n_healthy, 1)
        outs = np.concatenate(self.out_stats) if self.out_stats else np.zeros(0)
        roc = {
            "step": {"threshold": J_GRID, "pfa": pfa_j,
                     "pd": (self.step_stat[sv][None, :] > J_GRID[:, None]).mean(axis=1) if sv.any() else None,
                     "operating_threshold": op_j, "statistic": "max |beta| of the channel at onset and onset + 1"},
            "outlier": {"threshold": J_GRID, "pfa": pfa_j,
                        "pd": (outs[None, :] > J_GRID[:, None]).mean(axis=1) if outs.size else None,
                        "operating_threshold": op_j, "statistic": "max |beta| of the channel at the outlier"},
            "ramp": {"threshold": W_GRID, "pfa": pfa_w,
                     "pd": (self.ramp_stat[rv][None, :] > W_GRID[:, None]).mean(axis=1) if rv.any() else None,
                     "operating_threshold": 1.0,
                     "statistic": "max over the first ramp_detect_s of the channel's window statistic / threshold"},
        }
        return out, roc


# ------------------------------------------------------------------ the ramp detection bound
def ramp_signature(sigma_w_m: float, gm_sigma_m: float, gm_tau_s: float, dt_s: float, n: int):
    """What a code-only pseudorange ramp of unit rate (1 m/s, zero at the onset epoch, j dt at the
    j-th epoch after it) does to the innovations of the best filter of that channel's errors:
    the steady-state Kalman filter of the world's error model, white noise ``sigma_w_m`` plus a
    first-order Gauss-Markov error (``gm_sigma_m``, ``gm_tau_s``), run long before the onset.
    Its innovations are white with variance S; the ramp adds the deterministic signature g_j
    (the Willsky-Jones failure signature). Returns (g_j / sqrt(S) for j = 0..n-1, the cumulative
    signal-to-noise ratio sqrt(sum_{i<=j} g_i^2 / S) per unit rate)."""
    import scipy.linalg

    a = math.exp(-dt_s / gm_tau_s)
    q = gm_sigma_m**2 * -math.expm1(-2.0 * dt_s / gm_tau_s)
    r = sigma_w_m**2
    # the prior variance of the filter's steady state: the filtering Riccati equation (the DARE's dual)
    p_prior = float(scipy.linalg.solve_discrete_are(np.array([[a]]), np.array([[1.0]]), np.array([[q]]),
                                                    np.array([[r]]))[0, 0]) if gm_sigma_m > 0 else 0.0
    s = p_prior + r
    k = p_prior / s
    g = np.empty(n)
    est = 0.0  # the filter's estimate of the fault's own contribution (linear: the faulty run minus the healthy one)
    for j in range(n):
        pred = a * est
        g[j] = j * dt_s - pred
        est = pred + k * g[j]
    gn = g / math.sqrt(s)
    return gn, np.sqrt(np.cumsum(gn * gn))


def ramp_oracle_pd(rates_m_s, scn: IntegrityScenario, pfa: float, rng, draws: int = 20_000) -> np.ndarray:
    """Detection probability, within ``scn.ramp_detect_s`` of the onset, of a code-only pseudorange
    ramp of each |rate| in ``rates_m_s``, for an oracle: it knows the faulty channel, the onset
    and everything about the receiver (position, clock, the other satellites), and it has the
    channel's whole history; it does not know the rate or its sign. At every epoch after the onset
    it runs the most powerful test of "a ramp since the onset" against "no fault" on that channel's
    innovations (the matched filter of the failure signature, ramp_signature), two-sided at the
    per-epoch false-alarm probability ``pfa``; it alarms when any of them fires. No detector with less
    knowledge, at that false-alarm rate per epoch, can do better (it only ignores the other
    channels' nuisance, which would lower it). Monte Carlo with common random numbers over the rates."""
    n = int(round(scn.ramp_detect_s / scn.dt_s)) + 1  # the onset epoch (zero) to onset + ramp_detect_s
    gn, snr = ramp_signature(scn.sigma_pr_m, scn.gm_sigma_m, scn.gm_tau_s, scn.dt_s, n)
    live = snr > 0
    e = rng.standard_normal((draws, n))
    z = np.cumsum(e * gn, axis=1)[:, live] / snr[live]  # N(0, 1) per epoch under no fault
    thr = scipy.stats.norm.isf(pfa / 2.0)
    return np.array([float((np.abs(z + abs(float(rt)) * snr[live]) > thr).any(axis=1).mean()) for rt in rates_m_s])


def _ramp_oracle(scn: IntegrityScenario, seed: int, rates: np.ndarray, valid: np.ndarray, pfa: float) -> dict:
    """The oracle's Pd (ramp_oracle_pd) for this run's code-only ramps: overall and per rate bin, the
    mean over the trials of the oracle's Pd at each trial's rate (the same trials as ``ramp.pd``)."""
    grid = np.linspace(scn.ramp_rate_m_s[0], scn.ramp_rate_m_s[1], 61)
    rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(4)[3])  # not one of the run's streams
    pd_grid = ramp_oracle_pd(grid, scn, pfa, rng)
    rr = np.abs(rates)
    per = np.interp(rr, grid, pd_grid)
    bins = [(0.5, 1.0), (1.0, 2.0 + 1e-9)]

    def mean(sel):
        return float(per[sel].mean()) if sel.any() else None

    return {"pd": mean(valid), "by_rate_m_s": {f"{a:g}-{min(b, 2):g}": mean(valid & (rr >= a) & (rr < b))
                                               for a, b in bins},
            "pd_at_rate_m_s": {f"{v:g}": float(np.interp(v, grid, pd_grid)) for v in (0.5, 0.75, 1.0)
                               if grid[0] <= v <= grid[-1]},
            "pfa_per_epoch": pfa,
            "assumes": "knows the channel, the onset and the receiver's state; the channel's white noise "
                       "(sigma_pr_m) and Gauss-Markov error (gm_sigma_m, gm_tau_s) as in the world; a most "
                       "powerful test at every epoch, two-sided; code-only ramp"}


def _pfa_only(n_fa, n):
    lo, hi = scipy.stats.binomtest(n_fa, n).proportion_ci(0.95, method="exact") if n else (math.nan, math.nan)
    return {"value": n_fa / n if n else math.nan, "ci95": [lo, hi], "count": int(n_fa), "of": int(n)}


# ------------------------------------------------------------------ the run
def run(scn: IntegrityScenario, trials: int, seed: int, progress=None, backend=None, clean=True) -> dict:
    """All filters on the same simulated data; returns a dict (numpy arrays for the series)."""
    trials = integer(lo=1)("trials", trials)
    t_wall = time.perf_counter()
    ss = np.random.SeedSequence(seed)
    rng_w, rng_f, rng_p = (np.random.default_rng(s) for s in ss.spawn(3))
    const = scn.constellation()
    sats = scn.channel_sats()
    S = sats.size
    sub = const.subset(sats)
    carrier = sub.carrier_l1_hz
    is_gps = sub.system == "G"
    receiver = Receiver(S, scn.receiver_config(), (trials,))
    clock = ClockModel()
    dt = scn.dt_s
    T = scn.n_epochs
    t_rel = scn.times()
    pos_true, vel_true = scn.trajectory(t_rel)
    k_warm = int(np.searchsorted(t_rel, scn.warmup_s - 1e-9))

    # truth clock, GM errors, faults
    bias = scn.sigma0_clock_bias_m * rng_w.standard_normal(trials)
    drift = scn.sigma0_clock_drift_m_s * rng_w.standard_normal(trials)
    gm = GaussMarkov(scn.gm_sigma_m, scn.gm_tau_s, (trials, S), rng_w)
    if scn.faults:
        fault_list, ftruth = _faults(scn, rng_f, trials, S)
    else:
        fault_list, ftruth = [], None
    injector = FaultInjector(fault_list, (trials,), 2 * S)

    # filters
    channels = np.concatenate([np.arange(S), np.arange(S)])
    sd0 = np.array([scn.sigma0_pos_m] * 3 + [scn.sigma0_clock_bias_m] + [scn.sigma0_vel_m_s] * 3
                   + [scn.sigma0_clock_drift_m_s])
    x0 = np.zeros((trials, N_BASE))
    x0[:, 0:3] = pos_true[0] + scn.sigma0_pos_m * rng_p.standard_normal((trials, 3))
    x0[:, 4:7] = vel_true[0] + scn.sigma0_vel_m_s * rng_p.standard_normal((trials, 3))
    P0 = np.broadcast_to(np.diag(sd0**2), (trials, N_BASE, N_BASE)).copy()
    nb = N_BASE + S
    xb0 = np.zeros((trials, nb))
    xb0[:, :N_BASE] = x0
    Pb0 = np.zeros((trials, nb, nb))
    Pb0[:, :N_BASE, :N_BASE] = P0
    Pb0[:, np.arange(N_BASE, nb), np.arange(N_BASE, nb)] = scn.gm_sigma_m**2
    tr_base, tr_bias = scn.transition(), scn.transition(S)
    cfg = scn.monitor_config()
    detect_only = IntegrityMonitor(dataclasses.replace(cfg, isolate=False, huber_c=None, adapt_r=False))
    mon = IntegrityMonitor(cfg)
    aq = AdaptiveQ(scn.adaptive_q_decay, scn.adaptive_q_gain, DYNAMIC)
    var_white_gm = scn.sigma_pr_m**2 + scn.gm_sigma_m**2

    names = FILTERS + (CLEAN if clean else ())
    st = {}
    for name in names:
        biased = name in BIASED
        m = mon if name in MONITORED else detect_only
        st[name] = {"x": (xb0 if biased else x0).copy(), "P": (Pb0 if biased else P0).copy(),
                    "mon": m, "ms": m.init((trials,), 2 * S, S), "biased": biased,
                    "aq": name in FILTERS[1:], "aqs": aq.init((trials,), nb if biased else N_BASE),
                    "tr": tr_bias if biased else tr_base, "se": np.zeros(trials), "err0": np.empty(T),
                    "excl": 0}
    scores = {n: _Score(scn, trials, S, ftruth) for n in FILTERS[1:]} if scn.faults else {}
    clean_fa = {n: {"n": 0, "fa": 0} for n in ("monitored_fault_free", "bias_states_monitored_fault_free")}
    last_fault = np.full((trials, S), -10**9)
    n_missing_mask = 0
    report_every = max(1, T // 10)
    geom = geometry_track(scn.t0_gps_s + t_rel, pos_true, vel_true, sub)
    for k in range(T):
        t = scn.t0_gps_s + t_rel[k]
        # ---------------- world (truth)
        if k > 0:
            bias, drift = clock.step(rng_w, bias, drift, dt)
            e_gm = gm.step(rng_w, dt)
        else:
            e_gm = gm.x
        eg = next(geom)
        geo = eg.geometry
        obs = receiver.step(rng_w, t, geo.range_m, geo.range_rate_m_s, eg.el_rad, carrier, is_gps, bias, drift,
                            el_atmo_rad=eg.el_atmo_rad)
        z_clean = np.concatenate([obs.pseudorange_m + e_gm, obs.pseudorange_rate_m_s], axis=1)
        n_missing_mask += int(np.isnan(z_clean).sum())
        z, inj = injector.step(rng_f, t_rel[k], z_clean)

        # ---------------- filters (measurements + ephemeris only)
        data = {}
        for which, zz in (("faulty", z), ("clean", z_clean)):
            if which == "clean" and not clean:
                continue
            pr, prr = zz[:, :S], zz[:, S:]
            sp, sv = ephemeris_for_filter(t, pr, sub, pseudorange_rate_m_s=np.where(np.isfinite(pr), prr, np.nan))
            data[which] = (zz, sp, sv)
        for name, s in st.items():
            zz, sp, sv = data["clean" if name in CLEAN else "faulty"]
            if s["biased"]:
                meas = BiasedPseudorangeDoppler(PseudorangeDoppler(sp, sv, scn.sigma_pr_m, scn.sigma_prr_m_s, n=nb),
                                                N_BASE)
            else:
                meas = PseudorangeDoppler(sp, sv, math.sqrt(var_white_gm), scn.sigma_prr_m_s, n=N_BASE)
            x, P = s["x"], s["P"]
            if k > 0:
                if s["aq"]:
                    x_pred, P_pred = ekf_predict(x, P, aq.transition(s["tr"], s["aqs"]), dt, backend=backend)
                    P_pred = aq.add_diag(P_pred, s["aqs"])
                else:
                    x_pred, P_pred = ekf_predict(x, P, s["tr"], dt, backend=backend)
            else:
                x_pred, P_pred = x, P
            res, s["ms"], rep = s["mon"].step(s["ms"], x_pred, P_pred, zz, meas, channels, backend=backend)
            if s["aq"]:
                s["aqs"] = aq.next(s["aqs"], res.x - x_pred)
            s["x"], s["P"] = res.x, res.P
            e2 = np.sum((res.x[:, 0:3] - pos_true[k]) ** 2, axis=1)
            s["err0"][k] = math.sqrt(e2[0])
            if k >= k_warm:
                s["se"] += e2
            s["excl"] += int(rep.newly_excluded.sum())
            s["rep"] = rep

        # ---------------- scoring (truth side)
        if scn.faults:
            kind, missing = inj.kind, inj.missing
            fault_now = (kind[:, :S] > 0) | (kind[:, S:] > 0)
            tr = ftruth
            r = np.arange(trials)
            step_on = (k >= tr["step_k0"]) & (k < tr["step_k1"])
            ramp_on = k >= tr["ramp_k0"]
            fault_now[r[step_on], tr["step_ch"][step_on]] = True
            fault_now[r[ramp_on], tr["ramp_ch"][ramp_on]] = True
            last_fault[fault_now] = k
            missing_ch = missing[:, :S] | missing[:, S:] | np.isnan(z[:, :S]) | np.isnan(z[:, S:])
            healthy = (k - last_fault > scn.window) & ~missing_ch & (k >= k_warm)
            big = (kind[:, :S] == K_OUT) & (np.abs(inj.bias[:, :S]) >= 5.0 * scn.sigma_ref_m) & ~missing_ch
            big[r[step_on], tr["step_ch"][step_on]] = False
            big[r[ramp_on], tr["ramp_ch"][ramp_on]] = False
            count = min(k + 1, scn.window)
            for name, sc in scores.items():
                sc.epoch(k, st[name]["rep"], count, healthy, big, missing_ch)
        if clean and k >= k_warm + scn.window:
            ok = np.isfinite(z_clean[:, :S]) & np.isfinite(z_clean[:, S:])
            for name in ("monitored_fault_free", "bias_states_monitored_fault_free"):
                rep = st[name]["rep"]
                alarm_rows = rep.jump | rep.drift
                clean_fa[name]["n"] += int(ok.sum())
                clean_fa[name]["fa"] += int(((alarm_rows[:, :S] | alarm_rows[:, S:]) & ok).sum())
        if progress and (k % report_every == 0 or k == T - 1):
            rms = {n: math.sqrt(np.mean(np.sum((st[n]["x"][:, :3] - pos_true[k]) ** 2, axis=1))) for n in FILTERS}
            progress(f"t {t_rel[k]:6.1f} s  position error rms: " + "  ".join(f"{n} {v:7.2f} m" for n, v in rms.items())
                     + f"  ({time.perf_counter() - t_wall:.1f} s)")

    n_scored = T - k_warm
    rmse = {n: float(math.sqrt(st[n]["se"].sum() / (trials * n_scored))) for n in st}
    per_trial = {n: np.sqrt(st[n]["se"] / n_scored) for n in st}
    out = {
        "trials": trials, "seed": seed, "epochs": T, "channels": int(S), "sat_ids": np.array(sub.sat_id).tolist(),
        "t_s": t_rel, "position_rmse_m": {n: rmse[n] for n in FILTERS},
        "rmse_ratio": {"plain_over_adaptive_robust": rmse["plain"] / rmse["adaptive_robust"],
                       "plain_over_adaptive_robust_with_bias_estimation":
                           rmse["plain"] / rmse["adaptive_robust_with_bias_estimation"],
                       "adaptive_robust_over_with_bias_estimation":
                           rmse["adaptive_robust"] / rmse["adaptive_robust_with_bias_estimation"]},
        "position_rmse_per_trial_m": per_trial,
        "position_error_trial0_m": {n: st[n]["err0"] for n in st},
        "exclusions": {n: st[n]["excl"] for n in FILTERS[1:]},
        "missing_by_mask": n_missing_mask,
    }
    if scn.faults:
        det, roc = {}, {}
        for n, sc in scores.items():
            det[n], roc[n] = sc.result()
        # the best any detector could do on these ramps at the false-alarm target (code-only ramps; a clock ramp
        # also moves the pseudorange rate, sigma_prr: its bound is 1 to many digits)
        oracle = (_ramp_oracle(scn, seed, ftruth["ramp_rate"], scores[DETECTION_FILTER].ramp_valid, TARGETS["pfa_max"])
                  if scn.ramp_kind == "code" else None)
        for n in det:
            det[n]["ramp"]["oracle"] = oracle
        out["detection"] = det[DETECTION_FILTER]
        out["detection_by_filter"] = det
        out["roc"] = roc
        out["fault_onsets_trial0_s"] = {"step": float(ftruth["step_k0"][0] * dt),
                                        "step_end": float(ftruth["step_k1"][0] * dt),
                                        "ramp": float(ftruth["ramp_k0"][0] * dt),
                                        "step_channel": int(ftruth["step_ch"][0]),
                                        "ramp_channel": int(ftruth["ramp_ch"][0]),
                                        "step_sigma": float(ftruth["step_mag"][0] / scn.sigma_ref_m),
                                        "ramp_rate_m_s": float(ftruth["ramp_rate"][0])}
    if clean:
        out["fault_free"] = {}
        for key, a_name, b_name in (("plain_model", "plain_fault_free", "monitored_fault_free"),
                                    ("bias_state_model", "bias_states_fault_free", "bias_states_monitored_fault_free")):
            a, b = per_trial[a_name], per_trial[b_name]
            d = b - a
            se = float(d.std(ddof=1) / math.sqrt(trials)) if trials > 1 else math.nan
            out["fault_free"][key] = {
                "position_rmse_m": {"without_monitor": rmse[a_name], "with_monitor": rmse[b_name]},
                "paired_difference_m": {"mean": float(d.mean()), "standard_error": se,
                                        "upper_95": float(d.mean() + 1.645 * se) if trials > 1 else None},
                "pfa": _pfa_only(clean_fa[b_name]["fa"], clean_fa[b_name]["n"]),
            }
    out["wall_s"] = time.perf_counter() - t_wall
    return out


# ------------------------------------------------------------------ targets, result.json
TARGETS = {"pd_min": 0.99, "pfa_max": 0.003, "rmse_ratio_adaptive_robust_min": 2.0,
           "rmse_ratio_with_bias_estimation_about": 10.0}


def targets_check(res: dict) -> dict:
    det = res.get("detection")
    out = {}
    if det:
        st, rp = det["step"], det["ramp"]
        out["step_pd_ge_0.99"] = st["pd"]["value"] >= TARGETS["pd_min"]
        out["ramp_pd_ge_0.99_within_10s"] = rp["pd"]["value"] >= TARGETS["pd_min"]
        if rp.get("oracle"):  # can any detector meet it on these ramps?
            out["ramp_pd_ge_0.99_possible_at_all"] = rp["oracle"]["pd"] >= TARGETS["pd_min"]
        out["pfa_le_0.003"] = st["pfa"]["value"] <= TARGETS["pfa_max"]
    r = res["rmse_ratio"]
    out["adaptive_robust_cuts_rmse_more_than_2x"] = r["plain_over_adaptive_robust"] > 2.0
    out["with_bias_estimation_ratio"] = r["plain_over_adaptive_robust_with_bias_estimation"]
    for key, ff in res.get("fault_free", {}).items():
        d = ff["paired_difference_m"]
        if d["upper_95"] is None:
            continue
        # not significantly worse (one-sided 95 %) and non-inferior within 2 % of the RMSE
        out[f"fault_free_{key}_monitor_not_significantly_worse"] = d["mean"] - 1.645 * d["standard_error"] <= 0.0
        out[f"fault_free_{key}_monitor_noninferior_2pct"] = \
            d["upper_95"] <= 0.02 * ff["position_rmse_m"]["without_monitor"]
    return out


def result_document(scn, trials, seed, res, figures) -> dict:
    keep = ("trials", "seed", "epochs", "channels", "sat_ids", "position_rmse_m", "rmse_ratio", "exclusions",
            "detection", "detection_by_filter", "fault_free", "fault_onsets_trial0_s", "missing_by_mask", "wall_s")
    doc = {"experiment": "integrity", "schema": 1, "scenario": dataclasses.asdict(scn),
           "monitor_config": dataclasses.asdict(scn.monitor_config()), "sigma_ref_m": scn.sigma_ref_m}
    doc.update({k: res[k] for k in keep if k in res})
    if "roc" in res:  # thinned to keep the file small
        doc["roc"] = {f: {kind: {kk: (np.asarray(v)[::10] if isinstance(v, np.ndarray) else v) for kk, v in c.items()}
                          for kind, c in r.items()} for f, r in res["roc"].items()}
    doc["targets"] = TARGETS
    doc["targets_met"] = targets_check(res)
    doc["paper"] = {"adaptive_robust_rmse_cut": "more than 2x", "with_bias_estimation": "about 10x (an order of magnitude)"}
    doc["figures"] = [Path(f).name for f in figures]
    return strict(doc)


def plot(res: dict, scn, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    sub = f"{res['trials']} trials, seed {res['seed']}, {scn.duration_s:g} s at {1 / scn.dt_s:g} Hz, {res['channels']} satellites"
    # ROC
    fig, axes = plt.subplots(1, 3, figsize=(15, 5), constrained_layout=True)
    if "roc" in res:
        for ax, kind in zip(axes, ("step", "ramp", "outlier")):
            for name, ls in (("adaptive_robust", "-"), ("adaptive_robust_with_bias_estimation", "--")):
                c = res["roc"][name][kind]
                if c["pd"] is None:
                    continue
                pfa = np.maximum(np.asarray(c["pfa"], dtype=float), 1e-8)
                ax.plot(pfa, c["pd"], ls, label=name.replace("_", " "))
                i = int(np.argmin(np.abs(np.asarray(c["threshold"]) - c["operating_threshold"])))
                ax.plot(pfa[i], c["pd"][i], "o", ms=8, mfc="none", mew=2, color=ax.lines[-1].get_color(),
                        label=f"operating point ({c['operating_threshold']:g})")
            orc = res.get("detection", {}).get("ramp", {}).get("oracle") if kind == "ramp" else None
            if orc:
                ax.plot(orc["pfa_per_epoch"], orc["pd"], "*", ms=12, color="k",
                        label=f"bound: oracle knowing the onset ({orc['pd']:.3f})")
            ax.axvline(TARGETS["pfa_max"], color="k", ls=":", lw=1, label="Pfa target 0.003")
            ax.axhline(TARGETS["pd_min"], color="0.5", ls=":", lw=1, label="Pd target 0.99")
            ax.set_xscale("log")
            ax.set_xlim(1e-7, 1)
            ax.set_ylim(0, 1.02)
            ax.set_xlabel("Pfa per channel-epoch (this statistic alone)")
            ax.set_ylabel("Pd")
            ax.set_title({"step": "steps (|beta|, onset or next epoch)", "ramp": f"ramps (window statistic, within "
                          f"{scn.ramp_detect_s:g} s)", "outlier": "outliers >= 5 sigma (|beta|, at the epoch)"}[kind],
                         fontsize=10)
            ax.grid(alpha=0.3, which="both")
            ax.legend(fontsize=7, loc="lower right")
    fig.suptitle(f"Seed 003 integrity monitor: ROC per fault kind\n{sub}")
    files.append(save_figure(fig, out / FIGURES[0]))
    # position error vs time, trial 0
    fig, ax = plt.subplots(figsize=(11, 5), constrained_layout=True)
    t = res["t_s"]
    for name in FILTERS:
        ax.plot(t, res["position_error_trial0_m"][name], lw=1.0,
                label=f"{name.replace('_', ' ')} (RMSE all trials {res['position_rmse_m'][name]:.2f} m)")
    fo = res.get("fault_onsets_trial0_s")
    if fo:
        ax.axvline(fo["step"], color="r", ls="--", lw=1, label=f"step onset (sat ch {fo['step_channel']}, "
                   f"{fo['step_sigma']:+.1f} sigma)")
        ax.axvline(fo["step_end"], color="r", ls=":", lw=1, label="step end")
        ax.axvline(fo["ramp"], color="m", ls="--", lw=1, label=f"ramp onset (ch {fo['ramp_channel']}, "
                   f"{fo['ramp_rate_m_s']:+.2f} m/s)")
    ax.axvline(scn.warmup_s, color="0.5", ls=":", lw=1, label="end of warm-up (scoring starts)")
    ax.set_yscale("log")
    ax.set_xlabel("time, s")
    ax.set_ylabel("3-D position error, m (trial 0)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    ax.set_title(f"Seed 003: position error of the three filters on the same faulty data, trial 0\n{sub}", fontsize=10)
    files.append(save_figure(fig, out / FIGURES[1]))
    return files


def summary(res: dict) -> str:
    lines = []
    r = res["position_rmse_m"]
    lines.append("position RMSE: " + ", ".join(f"{n} {v:.2f} m" for n, v in r.items()))
    q = res["rmse_ratio"]
    lines.append(f"ratios: plain / adaptive-robust {q['plain_over_adaptive_robust']:.2f}x, plain / with bias "
                 f"estimation {q['plain_over_adaptive_robust_with_bias_estimation']:.2f}x (paper: > 2x, ~10x)")
    for name, det in res.get("detection_by_filter", {}).items():
        parts = []
        for kind in ("step", "ramp", "outlier"):
            d = det[kind]
            lo, hi = d["pd"]["ci95"]
            md = d["mean_delay_s"]
            parts.append(f"{kind} Pd {d['pd']['value']:.4f} [{lo:.4f}, {hi:.4f}] delay "
                         f"{'-' if md is None else f'{md:.2f} s'}")
        p = det["step"]["pfa"]
        lines.append(f"{name}: " + "; ".join(parts) + f"; Pfa {p['value']:.2e} [{p['ci95'][0]:.2e}, {p['ci95'][1]:.2e}]")
    orc = res.get("detection", {}).get("ramp", {}).get("oracle")
    if orc:
        lines.append(f"ramp bound (oracle that knows the onset, Pfa {orc['pfa_per_epoch']:g} per epoch): Pd "
                     f"{orc['pd']:.4f} on these ramps; " + ", ".join(f"{k} m/s {v:.4f}" for k, v in
                                                                      orc["by_rate_m_s"].items() if v is not None)
                     + "; at " + ", ".join(f"{k} m/s {v:.3f}" for k, v in orc["pd_at_rate_m_s"].items()))
    for key, ff in res.get("fault_free", {}).items():
        d = ff["paired_difference_m"]
        lines.append(f"fault-free ({key}): without monitor {ff['position_rmse_m']['without_monitor']:.3f} m, with "
                     f"{ff['position_rmse_m']['with_monitor']:.3f} m; paired difference {d['mean']:+.4f} +- "
                     f"{d['standard_error']:.4f} m; monitor Pfa {ff['pfa']['value']:.2e}")
    lines.append(f"wall {res['wall_s']:.1f} s")
    return "\n".join(lines)


# ------------------------------------------------------------------ the command
# ------------------------------------------------------------------ the command's options
def _scn(name):
    return lambda: default_of(IntegrityScenario, name)  # the default a None option stands for


@dataclass(frozen=True)
class IntegrityOptions:
    """`skyfuse experiment integrity`'s options, declared once (sitl.params). A None option keeps
    IntegrityScenario's default (shown in --help); the scenario's checks are usage errors before
    any run."""

    trials: int = param(200, check=integer(lo=1), doc="Monte Carlo trials")
    seed: int = param(3, check=integer(lo=0), doc="seed of the numpy SeedSequence")
    out: Path = param(Path("out/integrity"), check=OUTPUT_DIR, metavar="DIR",
                      doc="output directory for result.json and PNG figures")
    duration: float = param(default_of(IntegrityScenario, "duration_s"), check=number(0, lo_open=True), metavar="S",
                            doc="simulated time, s at 10 Hz; faults start between 60 s and 0.7 x this")
    sigma_pr: float | None = param(None, check=optional(number(0, lo_open=True)), metavar="M",
                                   doc="pseudorange white noise", shown=_scn("sigma_pr_m"))
    sigma_prr: float | None = param(None, check=optional(number(0, lo_open=True)), metavar="M_S", doc="rate noise",
                                    shown=_scn("sigma_prr_m_s"))
    el_mask_deg: float | None = param(None, check=optional(number()), metavar="DEG",
                                      doc="elevation mask in [5, 90); >= 7 satellites must stay in view",
                                      shown=_scn("el_mask_deg"))
    gm_sigma: float | None = param(None, check=optional(number(0)), metavar="M",
                                   doc="Gauss-Markov pseudorange error sigma per satellite", shown=_scn("gm_sigma_m"))
    gm_tau: float | None = param(None, check=optional(number(0, lo_open=True)), metavar="S",
                                 doc="its correlation time", shown=_scn("gm_tau_s"))
    jump_sigma: float | None = param(None, check=optional(number(0, lo_open=True)), metavar="X",
                                     doc="jump test threshold on |beta|", shown=_scn("jump_sigma"))
    window: int | None = param(None, check=optional(integer(lo=1)), doc="window of the drift tests, epochs",
                               shown=_scn("window"))
    window_alpha: float | None = param(None, check=optional(number(0, lo_open=True)), metavar="A",
                                       doc="mean-square test alpha", shown=_scn("window_alpha"))
    bias_alpha: float | None = param(None, check=optional(number(0, lo_open=True)), metavar="A",
                                     doc="bias test alpha", shown=_scn("bias_alpha"))
    huber_c: float | None = param(None, check=optional(number(0, lo_open=True)), metavar="X",
                                  doc="Huber threshold on |beta|", shown=_scn("huber_c"))
    outlier_prob: float | None = param(None, check=optional(number(0)), metavar="P",
                                       doc="outlier probability per pseudorange-epoch", shown=_scn("outlier_prob"))
    ramp_kind: str | None = param(None, check=optional(choice("code", "clock")),
                                  doc="code: the pseudorange alone drifts (no Doppler trace); clock: a satellite clock "
                                      "frequency fault, the pseudorange rate carries the ramp's rate too",
                                  shown=_scn("ramp_kind"))
    no_faults: bool = param(False, check=switch(), doc="the same world with no faults injected")
    backend: str = backend_option("filter kernels")
    quiet: bool = quiet_option()

    __post_init__ = validate


def add_args(p) -> None:
    add_flags(p, IntegrityOptions)


def scenario_from_args(args) -> IntegrityScenario:
    kw = {"duration_s": args.duration}
    for flag, field in (("sigma_pr", "sigma_pr_m"), ("sigma_prr", "sigma_prr_m_s"), ("el_mask_deg", "el_mask_deg"),
                        ("gm_sigma", "gm_sigma_m"), ("gm_tau", "gm_tau_s"), ("jump_sigma", "jump_sigma"),
                        ("window", "window"), ("window_alpha", "window_alpha"), ("bias_alpha", "bias_alpha"),
                        ("huber_c", "huber_c"), ("outlier_prob", "outlier_prob"), ("ramp_kind", "ramp_kind")):
        v = getattr(args, flag, None)
        if v is not None:
            kw[field] = v
    if getattr(args, "no_faults", False):
        kw["faults"] = False
    try:
        return IntegrityScenario(**kw)
    except ValueError as exc:
        msg = " ".join(str(exc).split())
        flag = next((f for name, f in FLAGS.items() if msg.startswith((name + " ", name + ":", name + " ="))), None)
        raise ValueError(f"{flag}: {msg}" if flag else msg) from None


def main(args) -> int:
    from sitl.app.args import UsageError

    try:
        scn = scenario_from_args(args)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    out = prepare_out(Path(args.out))
    backend = None if getattr(args, "backend", default_of(IntegrityOptions, "backend")) == "auto" else args.backend
    res = run(scn, args.trials, args.seed, progress=progress_printer(args.quiet), backend=backend)
    figures = plot(res, scn, out)
    doc = result_document(scn, args.trials, args.seed, res, figures)
    (out / "result.json").write_text(json.dumps(doc, indent=1, allow_nan=False))
    print(summary(res))
    print("wrote " + ", ".join(str(f) for f in [out / "result.json", *figures]))
    return 0
