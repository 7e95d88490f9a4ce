"""The beacon locator's settings (LocatorConfig) and its recommended integrity settings."""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import scipy.stats

from filters import kernels
from filters.beacon import OBSERVER_UNCERTAINTY
from filters.integrity import IntegrityConfig
from sitl.checks import nonnegative as _nonneg
from sitl.checks import positive as _pos
from sitl.scenario import GroundStationSection

__all__ = ["LocatorConfig", "MOTIONS", "INITS", "INTEGRITY"]

MOTIONS = ("cv", "position")
# the integrity settings for the locator (ground_station.beacon.integrity): no bias test, no
# Huber, no adaptive R -- the UAVs' navigation errors are correlated over tens of seconds, so the
# innovations are not white and the bias test would over-alarm
INTEGRITY = IntegrityConfig(bias_alpha=None, huber_c=None, adapt_r=False)
INITS = ("multilateration", "prior")


@functools.lru_cache(maxsize=64)
def _chi2_isf(p: float, dof: int) -> float:
    return float(scipy.stats.chi2.isf(p, dof))


@dataclass(frozen=True)
class LocatorConfig:
    """Settings of the beacon locator (ground_station.beacon).

    q_m2_s3: acceleration PSD of the beacon's constant-velocity model, m^2/s^3.
    observer_uncertainty: "inflate" (R + kappa J P_i J'), "ignore" (R only) or "consider" (the
        UAVs' errors as Schmidt states, motion "cv" only; ground_station.beacon).
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
    acquire_s: "consider" only: a track's first acquire_s run as "inflate" (ground_station.beacon).
    min_formation_sigmas: an epoch whose >= 3 UAVs span less than this many times their RMS
        position sigma gives no beacon measurement (0: off; ground_station.beacon).
    integrity: the integrity monitor (filters.integrity) on each UAV link's range and Doppler
        (ground_station.beacon.integrity); None: off.
    integrity_max_links: monitor channels (UAV ids beyond this many are used unjudged, counted).
    integrity_common_fraction: an epoch of a trial whose links mostly jump at once (more than
        this fraction of its present links) is not judged: the track moved, not one link.
    integrity_min_links: the verdict leaves links out of a trial's update only while at least this
        many of its present links stay in (3: ranges and Dopplers of 3 UAVs fix the 6 states with
        no redundancy; below that an exclusion makes the track unobservable and the monitor
        detect-only for that trial and epoch).
    lag_window_s: out-of-sequence measurements (ground_station.beacon.locator): a
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
    lag_window_s: float = GroundStationSection.lag_window_s  # the scenario's declared default

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
