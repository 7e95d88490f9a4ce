"""The seed 000 scenario (variants 1-3): the world (receiver, atmosphere, trajectory), the filter's
prior and process noise, the variant-2 and variant-3 settings and eq 7's, each field declared with
its check and doc (sitl.params). The documented choices are sitl.app.experiments.iono_tropo_filters'
module docstring."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from filters.iono_tropo import (
    IDX_CLOCK,
    IDX_DRIFT,
    IDX_GPS_GLO,
    IDX_IONO,
    IDX_TROPO,
    N_BASE,
    IonoTropoTransition,
)
from sitl import geodesy
from sitl.gnss import orbits
from sitl.gnss.receiver import ReceiverConfig
from sitl.gnss.world import elevation_grid
from sitl.params import choice, integer, number, param, require, switch, validate

__all__ = ["IonoTropoScenario", "MIN_SATS", "ADAPTIVE_Q_SCOPES", "CMC_NOISE"]

MIN_SATS = 4  # position + clock need at least 4 satellites at every epoch
_CHECK_EVERY_S = 10.0  # visibility pre-check grid
IB = [IDX_IONO, IDX_TROPO]
ADAPTIVE_Q_SCOPES = {"all": None, "dynamic": (0, 1, 2, IDX_CLOCK, 4, 5, 6, IDX_DRIFT)}
CB = [IDX_CLOCK, IDX_DRIFT]
CMC_NOISE = ("states", "whitened")


_POSITIVE = number(0, lo_open=True)
_NON_NEGATIVE = number(0)
_FINITE = number()


@dataclass(frozen=True)
class IonoTropoScenario:
    """Seed 000 variant-1 scenario (defaults: the seed's experiment)."""

    duration_s: float = param(1200.0, check=_POSITIVE, doc="observation time, s")
    dt_s: float = param(0.1, check=_POSITIVE, doc="epoch interval of the receiver and the filter, s (10 Hz)")
    # receiver (seed 000)
    sigma_pr_m: float = param(6.0, check=_POSITIVE, doc="pseudorange noise (1 sigma), m (seed 000)")
    sigma_prr_m_s: float = param(0.064, check=_POSITIVE, doc="pseudorange-rate noise (1 sigma), m/s (seed 000)")
    sigma_phase_m: float = param(0.003, check=_POSITIVE,
                                 doc="carrier-phase noise (1 sigma), m; not used by variant 1, passed to the receiver")
    iono_zenith_m: float = param(15.0, check=_NON_NEGATIVE, doc="true zenith ionospheric delay I_g at L1, m")
    tropo_zenith_m: float = param(2.5, check=_NON_NEGATIVE, doc="true zenith tropospheric delay U_g, m")
    gps_glonass_offset_m: float = param(5.0, check=_FINITE, doc="true GPS-GLONASS receiver bias Delta_A, m")
    el_mask_deg: float = param(10.0, check=number(5, hi=90, hi_open=True,
                                                  what="a number in [5, 90) (the seed's 1/sin(el) troposphere "
                                                       "mapping, eq 11, does not hold nearer the horizon)"),
                               doc=f"elevation mask, deg; >= {MIN_SATS} satellites must stay in view all along the run")
    # trajectory: great circle at constant speed from (lat, lon, h), heading from north
    lat_deg: float = param(55.0, check=number(-90, hi=90, lo_open=True, hi_open=True),
                           doc="latitude of the trajectory's start, deg")
    lon_deg: float = param(37.0, check=_FINITE, doc="longitude of the trajectory's start, deg")
    h_m: float = param(1000.0, check=number(-500, hi=1e5, what="a number in [-500, 1e5] (a receiver near the ground)"),
                       doc="height of the trajectory above the ellipsoid, m")
    speed_m_s: float = param(50.0, check=_NON_NEGATIVE, doc="ground speed along the great circle, m/s")
    heading_deg: float = param(90.0, check=_FINITE, doc="initial heading of the great circle from north, deg")
    t0_gps_s: float = param(orbits.DEFAULT_TOA_GPS_S + 3600.0, check=_FINITE,
                            doc="GPS time of the first epoch, s (an hour after the almanac's reference time)")
    systems: str = param("GR", check=choice("GR", "RG", "G", "R"),
                         doc="constellations, in this order: G (GPS) and/or R (GLONASS)")
    # prior (1-sigma) and filter process noise
    sigma0_pos_m: float = param(100.0, check=_POSITIVE,
                                doc="prior position sigma per axis (the prior mean is the truth plus such a draw), m")
    sigma0_vel_m_s: float = param(5.0, check=_POSITIVE, doc="prior velocity sigma per axis (likewise), m/s")
    sigma0_clock_bias_m: float = param(300.0, check=_POSITIVE,
                                       doc="receiver clock bias sigma (the truth's draw; the prior is 0 with it), m")
    sigma0_clock_drift_m_s: float = param(3.0, check=_POSITIVE,
                                          doc="receiver clock drift sigma (the truth's draw; the prior is 0 with it), "
                                              "m/s")
    sigma0_gps_glo_m: float = param(10.0, check=_POSITIVE, doc="prior sigma of Delta_A (prior mean 0), m")
    iono_prior_m: float = param(0.0, check=_FINITE, doc="prior mean of I_g, m")
    sigma0_iono_m: float = param(20.0, check=_POSITIVE, doc="prior sigma of I_g, m")
    tropo_prior_m: float = param(0.0, check=_FINITE, doc="prior mean of U_g, m")
    sigma0_tropo_m: float = param(5.0, check=_POSITIVE, doc="prior sigma of U_g, m")
    q_accel_m2_s3: float = param(0.01, check=_NON_NEGATIVE,
                                 doc="white-acceleration PSD of the filter's motion model, m^2/s^3")
    q_atmo_m2_s: float = param(1e-10, check=_NON_NEGATIVE,
                               doc="random-walk PSD of Delta_A, I_g and U_g in the filter (constant in the truth), "
                                   "m^2/s")
    final_window_s: float = param(60.0, check=_POSITIVE,
                                  doc="the final errors and ANEES are scored over the last this many seconds")
    # variant 2: code-minus-carrier increments (eqs 29-33)
    cmc_window_s: float = param(90.0, check=_POSITIVE,
                                doc="variant 2: the increment interval W, s (seed: 90 s); a multiple of dt_s")
    cycle_slip_rate_hz: float = param(0.0, check=_NON_NEGATIVE,
                                      doc="random cycle slips per tracked satellite in the simulated receiver, 1/s")
    # how E_j's code noise is handled: "states" (exact: eps_D,j at the window start is a state,
    # see sitl.app.experiments.iono_tropo_models) or "whitened" (against the same epoch's pr_j only; the
    # correlation with the already-used pr_j(t - W) ignored)
    cmc_noise: str = param("states", check=choice(*CMC_NOISE),
                           doc="variant 2, the code noise of the increments: states (exact: the code noise at the "
                               "window start is a filter state) or whitened (decorrelated from the same epoch's "
                               "pseudorange only)")
    # variant 3: carrier-phase ambiguity states
    sigma0_amb_m: float = param(1000.0, check=_POSITIVE,
                                doc="variant 3: prior / reset sigma of a new ambiguity state K_j (flat), m")
    phase_max_sats: int = param(0, check=integer(lo=0, what="an integer >= 0 (0: every satellite)"),
                                doc="variant 3: the carrier phase of at most this many satellites (0: every tracked "
                                    "one)")
    # adaptive process noise (eq 7): Q(i+1) = Q_min + decay Q(i) + gain diag((W nu)(W nu)')
    adaptive_q: bool = param(False, check=switch(), doc="the adaptive process noise of the seed's eq 7")
    adaptive_q_decay: float = param(0.1, check=number(0, hi=1, hi_open=True,
                                                      what="a number in [0, 1) (Q would grow without bound)"),
                                    doc="eq 7's decay of the previous Q")
    adaptive_q_gain: float = param(0.7, check=_NON_NEGATIVE, doc="eq 7's gain on diag((W nu)(W nu)')")
    # which states adapt: "all" (the seed: diag over the whole state) or "dynamic" (position,
    # velocity, clock bias and drift only; Delta_A, I_g, U_g and K_j are constants)
    adaptive_q_scope: str = param("all", check=choice(*ADAPTIVE_Q_SCOPES),
                                  doc="which states adapt: all (the seed) or dynamic (position, velocity, clock bias "
                                      "and drift only)")
    # truth clock: N_eps of the simulated clock = truth_clock_psd_scale x the filter's N_eps
    # (1 = correctly modelled; > 1 a mismodelled, noisier clock than the filter assumes)
    truth_clock_psd_scale: float = param(1.0, check=_POSITIVE,
                                         doc="the simulated clock's PSD / the filter's (1: correctly modelled)")

    def __post_init__(self):
        validate(self)
        require(self.dt_s <= self.duration_s, "dt_s", f"must be <= duration_s, got {self.dt_s!r} > {self.duration_s!r}")
        w = self.cmc_window_s / self.dt_s
        require(abs(w - round(w)) <= 1e-6 * max(1.0, w) and round(w) >= 1, "cmc_window_s",
                f"must be a positive multiple of dt_s = {self.dt_s!r}, got {self.cmc_window_s!r}")
        # the receiver's own validation (sigma, mask, atmosphere), message names the field
        self.receiver_config()
        # visibility: at least MIN_SATS satellites above the mask all along the run
        n = self.visible_counts()
        require(n.min() >= MIN_SATS, "el_mask_deg",
                f"{self.el_mask_deg!r} leaves only {int(n.min())} satellites in view at some epoch "
                f"(>= {MIN_SATS} needed all along the run)")

    # ------------------------------------------------------------------ the world
    @property
    def cmc_window_epochs(self) -> int:
        """The increment interval in epochs (cmc_window_s / dt_s)."""
        return round(self.cmc_window_s / self.dt_s)

    @property
    def n_epochs(self) -> int:
        return round(self.duration_s / self.dt_s) + 1

    def times(self) -> np.ndarray:
        """Epoch times relative to the start, s (epoch 0 at 0)."""
        return np.arange(self.n_epochs) * self.dt_s

    def constellation(self):
        return orbits.default_constellation(self.systems)

    def receiver_config(self) -> ReceiverConfig:
        return ReceiverConfig(sigma_pr_m=self.sigma_pr_m, sigma_prr_m_s=self.sigma_prr_m_s,
                              sigma_phase_m=self.sigma_phase_m, el_mask_rad=math.radians(self.el_mask_deg),
                              iono_zenith_m=self.iono_zenith_m, tropo_zenith_m=self.tropo_zenith_m,
                              gps_glonass_offset_m=self.gps_glonass_offset_m,
                              cycle_slip_rate_hz=self.cycle_slip_rate_hz)

    def trajectory(self, t_rel_s):
        """True ECEF position and velocity (..., 3) at t_rel_s: a great circle at constant
        speed on the geocentric sphere through the start point."""
        return geodesy.great_circle_track(self.lat_deg, self.lon_deg, self.h_m, self.speed_m_s, self.heading_deg,
                                          t_rel_s)

    def visible_counts(self, every_s: float = _CHECK_EVERY_S) -> np.ndarray:
        """Satellites above the mask (geodetic horizon, no light time) on a coarse grid."""
        t = np.unique(np.append(np.arange(0.0, self.duration_s, every_s), self.duration_s))
        pos, _ = self.trajectory(t)
        el = elevation_grid(self.constellation(), self.t0_gps_s + t, pos)
        return np.sum(el >= math.radians(self.el_mask_deg), axis=1)

    # ------------------------------------------------------------------ the filter
    def transition(self, n_amb: int = 0) -> IonoTropoTransition:
        q = self.q_atmo_m2_s
        return IonoTropoTransition(n_amb=n_amb, q_accel_m2_s3=self.q_accel_m2_s3, q_gps_glo_m2_s=q,
                                   q_iono_m2_s=q, q_tropo_m2_s=q)

    def prior_sigmas(self) -> np.ndarray:
        sd = np.empty(N_BASE)
        sd[0:3] = self.sigma0_pos_m
        sd[IDX_CLOCK] = self.sigma0_clock_bias_m
        sd[4:7] = self.sigma0_vel_m_s
        sd[IDX_DRIFT] = self.sigma0_clock_drift_m_s
        sd[IDX_GPS_GLO] = self.sigma0_gps_glo_m
        sd[IDX_IONO] = self.sigma0_iono_m
        sd[IDX_TROPO] = self.sigma0_tropo_m
        return sd
