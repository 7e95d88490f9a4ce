"""The seed 003 integrity scenario: the world, the faults' draws, the filters' and the monitor's
settings, each field declared with its check and doc (sitl.params); the documented choices are
the package docstring's (sitl.app.experiments.integrity)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from filters.integrity import IntegrityConfig
from filters.models import ClockRandomWalk, Composite, ConstantVelocity
from sitl import geodesy
from sitl.app.experiments.integrity.models import GaussMarkovBank
from sitl.gnss import orbits
from sitl.gnss.clock import ClockModel
from sitl.gnss.receiver import ReceiverConfig
from sitl.gnss.world import elevation_grid
from sitl.params import ParamError, choice, integer, number, optional, param, require, switch, validate

__all__ = ["IntegrityScenario", "MIN_CHANNELS", "N_BASE", "IDX_BIAS", "IDX_DRIFT", "ORDER", "RAMP_KINDS"]

MIN_CHANNELS = 7
N_BASE = 8  # [p(3), clock bias, v(3), clock drift]
IDX_BIAS, IDX_DRIFT = 3, 7
ORDER = (0, 1, 2, 6, 3, 4, 5, 7)  # x = s[ORDER], s = [CV p(3) v(3), clock bias, drift]
RAMP_KINDS = ("code", "clock")

_POSITIVE = number(0, lo_open=True)
_NON_NEGATIVE = number(0)
_FINITE = number()
_PROBABILITY_OPEN = number(0, hi=1, lo_open=True, hi_open=True)


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
            ok = a <= b
        except ParamError:
            ok = False
        if not ok:
            raise ParamError(key, f"expected {what}, got {v!r}")
        return (a, b)

    return check


@dataclass(frozen=True)
class IntegrityScenario:
    """Seed 003 integrity scenario (documented choices in sitl.app.experiments.integrity's docstring)."""

    duration_s: float = param(300.0, check=_POSITIVE, doc="simulated time, s")
    dt_s: float = param(0.1, check=_POSITIVE, doc="epoch interval of the receiver and the filters, s (10 Hz)")
    sigma_pr_m: float = param(6.0, check=_POSITIVE, doc="pseudorange white noise (1 sigma), m (seed 000)")
    sigma_prr_m_s: float = param(0.064, check=_POSITIVE, doc="pseudorange-rate white noise (1 sigma), m/s (seed 000)")
    el_mask_deg: float = param(10.0, check=number(5, hi=90, hi_open=True),
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
    outlier_prob: float = param(0.002, check=number(0, hi=1),
                                doc="probability of a multipath outlier per pseudorange-epoch")
    outlier_dof: float = param(2.0, check=_POSITIVE,
                               doc="degrees of freedom of the outliers' Student-t (scale sigma_pr_m)")
    dropout_s: tuple = param((1.0, 5.0), check=_pair(lo_open=True),
                             doc="range of the dropout's length (uniform; both rows of one satellite missing), s")
    onset_min_s: float = param(60.0, check=_NON_NEGATIVE, doc="earliest fault onset, s")
    onset_max_frac: float = param(0.7, check=number(0, hi=1, lo_open=True),
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
    adaptive_q_decay: float = param(0.1, check=number(0, hi=1, hi_open=True),
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
    r_forget: float = param(0.02, check=number(0, hi=1, lo_open=True),
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
