"""The beacon locator's settings (LocatorConfig) and its recommended integrity settings."""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import scipy.special  # chi2.isf(p, k) is chdtri(k, p), without scipy.stats' ~1 s import

from filters import kernels
from filters.beacon import OBSERVER_UNCERTAINTY
from filters.integrity import IntegrityConfig
from filters.params import ParamError, choice, instance_of, integer, number, param, require, switch, validate
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
    return float(scipy.special.chdtri(dof, p))


_POSITIVE = number(0, lo_open=True)
_NONNEGATIVE = number(0)
_FRACTION_OPEN = "a number in (0, 1)"
_FRACTION_HALF_OPEN = "a number in (0, 1]"
_PRIOR_MEAN = "6 finite numbers [B, V_B] (ECEF)"
_PRIOR_COV = "a finite symmetric positive definite 6 x 6 matrix"


def _backend(key, value):
    """A filters.kernels backend name or None (what kernels.resolve_backend takes)."""
    try:
        kernels.resolve_backend(value)
    except ValueError as exc:
        raise ParamError(key, str(exc)) from None
    return value


def _height_band(key, value) -> tuple:
    """() or (lowest, highest) finite heights, m, lowest < highest, as a tuple of floats."""
    if isinstance(value, (tuple, list)) and not len(value):
        return ()
    try:
        b = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        b = None
    if b is None or b.shape != (2,) or not np.all(np.isfinite(b)) or not b[0] < b[1]:
        raise ParamError(key, f"expected () or [lowest, highest] finite heights in m, lowest < highest, got {value!r}")
    return (float(b[0]), float(b[1]))


def _prior_mean(key, value) -> tuple:
    """() or 6 finite numbers, as a tuple of floats."""
    if isinstance(value, (tuple, list)) and not len(value):
        return ()
    try:
        m = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        m = None
    if m is None or m.shape != (6,) or not np.all(np.isfinite(m)):
        raise ParamError(key, f"expected {_PRIOR_MEAN}, got {value!r}")
    return tuple(float(v) for v in m)


def _prior_cov(key, value) -> tuple:
    """() or a finite symmetric positive definite 6 x 6 matrix, as a tuple of 6 tuples of floats."""
    if isinstance(value, (tuple, list)) and not len(value):
        return ()
    try:
        C = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ParamError(key, f"expected {_PRIOR_COV}, got {value!r}") from None
    if C.shape != (6, 6) or not np.all(np.isfinite(C)) or not np.allclose(C, C.T, rtol=1e-12, atol=0.0):
        raise ParamError(key, f"expected {_PRIOR_COV}, got shape {C.shape}")
    try:
        np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        raise ParamError(key, f"expected {_PRIOR_COV}, got one that is not positive definite") from None
    return tuple(tuple(float(v) for v in row) for row in C)


@dataclass(frozen=True)
class LocatorConfig:
    """Settings of the beacon locator (ground_station.beacon)."""

    q_m2_s3: float = param(1.0, check=_NONNEGATIVE, doc="acceleration PSD of the beacon's constant-velocity model, "
                                                        "m^2/s^3")
    observer_uncertainty: str = param(
        "inflate", check=choice(*OBSERVER_UNCERTAINTY, "consider"),
        doc='"inflate" (R + kappa J P_i J\'), "ignore" (R only) or "consider" (the UAVs\' errors as Schmidt states, '
            'motion "cv" only; ground_station.beacon)')
    uav_error_corr_s: float = param(50.0, check=_NONNEGATIVE,
                                    doc="correlation time tau of the UAVs' navigation errors, s; kappa = 1 + 2 tau / dt "
                                        '("consider": of their position errors)')
    uav_vel_error_corr_s: float = param(50.0, check=_NONNEGATIVE,
                                        doc='"consider" only: correlation time of the UAVs\' velocity errors, s')
    motion: str = param("cv", check=choice(*MOTIONS),
                        doc='"cv" (the cylindrical [B, V_B] filter) or "position" (the seed\'s position-only filter)')
    init_epochs: int = param(3, check=integer(1), doc="epochs with >= 3 observers accumulated before the first estimate")
    init_height_sigma_m: float = param(5000.0, check=number(0, lo_open=True, finite=False,
                                                            what="a number > 0 (inf: no prior)"),
                                       doc="prior sigma of the beacon's height about the UAVs' mean height, m "
                                           "(inf: no height prior, no height scan)")
    search_height_m: tuple = param(
        (), check=_height_band,
        doc="(lowest, highest) height above the ellipsoid the beacon can have, m: the search volume the ground "
            "station declares (what it knows of the emitter, not where it is). The blind start's two sides of the "
            "UAVs' plane have the same ranges; a side whose height lies outside the band by more than 3 of its "
            "sigmas is refused (mirror_outside_volume), so the other is the start. (): no band")
    init_vel_sigma_m_s: float = param(300.0, check=_POSITIVE, doc="prior sigma of each beacon velocity component, m/s")
    init_cov_scale: float = param(4.0, check=_POSITIVE,
                                  doc="the initial covariance is the window's inverse information times this")
    init_resolve_s: float = param(600.0, check=_NONNEGATIVE,
                                  doc="the longest the mirror hypothesis is carried, s (0: not carried)")
    init_resolve_llr: float = param(150.0, check=_POSITIVE,
                                    doc="the mirror is resolved as soon as the two tracks' summed -2 log-likelihoods "
                                        "differ by this much (a likelihood ratio of exp(llr / 2)), else at "
                                        "init_resolve_s")
    gate_prob: float = param(1e-5, check=number(0, lo_open=True, what=_FRACTION_OPEN),
                             doc="an observer whose NIS exceeds the chi-square (1 - gate_prob) quantile is rejected "
                                 "(2 dof; 1 dof for the position-only ranges)")
    max_uav_pos_sigma_m: float = param(1000.0, check=_POSITIVE,
                                       doc="a UAV snapshot whose largest position standard deviation exceeds this is "
                                           "rejected, m")
    max_uav_vel_sigma_m_s: float = param(50.0, check=_POSITIVE,
                                         doc="a UAV snapshot whose largest velocity standard deviation exceeds this is "
                                             "rejected, m/s")
    max_range_m: float = param(1.0e6, check=_POSITIVE, doc="plausibility limit of a beacon range, m")
    max_range_rate_m_s: float = param(3000.0, check=_POSITIVE, doc="plausibility limit of a beacon range rate, m/s")
    max_coast_s: float = param(60.0, check=_POSITIVE,
                               doc='time without >= 3 observers after which the mode reads "lost", s')
    axis_ratio: float = param(0.5, check=number(0, lo_open=True, what=_FRACTION_HALF_OPEN),
                              doc="a formation whose second singular value exceeds this fraction of the first is not "
                                  "line-like; it keeps the previous axis")
    position_q_m2_s3: float = param(1e-3, check=_POSITIVE,
                                    doc="extra process noise PSD of the position-only filter (numerical floor), "
                                        "m^2/s^3")
    backend: str | None = param(None, check=_backend,
                                doc="covariance kernels (None: the default, numba when installed)")
    init: str = param("multilateration", check=choice(*INITS),
                      doc='"multilateration" (blind start from a window of epochs) or "prior" (start from prior_mean '
                          "and prior_cov at the first epoch)")
    update_iterations: int = param(
        1, check=integer(1, 20),
        doc="1 (EKF) or more: an iterated EKF update (Gauss-Newton on the epoch's ranges and Dopplers, relinearised "
            "at each iterate; the gate decided at the first). For ranges comparable with the state's uncertainty (a "
            "beacon that starts among the UAVs), where one linearisation at the prediction is poor. At most this "
            "many: the iterations stop once no row's ECEF iterate moves by 1 mm (mm/s) or more, or once "
            "relinearising changes no used innovation by 1e-3 of its noise sigma")
    second_order_r: bool = param(
        False, check=switch(),
        doc="add the variance of the ranges' and Dopplers' second-order terms (second_order_var, at the predicted "
            "state and covariance) to R -- for the same case; off by default (in the cylindrical coordinates the "
            "curvature is the coordinates' business)")
    prior_mean: tuple = param((), check=_prior_mean,
                              doc='init "prior": the prior mean (6,) over ECEF [B, V_B], m and m/s; () otherwise')
    prior_cov: tuple = param((), check=_prior_cov,
                             doc='init "prior": the prior covariance (6, 6) over ECEF [B, V_B]; () otherwise')
    acquire_s: float = param(50.0, check=_NONNEGATIVE,
                             doc='"consider" only: a track\'s first acquire_s run as "inflate", s')
    min_formation_sigmas: float = param(12.0, check=_NONNEGATIVE,
                                        doc="an epoch whose >= 3 UAVs span less than this many times their RMS "
                                            "position sigma gives no beacon measurement (0: off)")
    integrity: IntegrityConfig | None = param(
        None, check=instance_of(IntegrityConfig, none=True, what="a filters.integrity.IntegrityConfig or None "
                                                     "(integrity must be a monitor's settings or off)"),
        doc="the integrity monitor (filters.integrity) on each UAV link's range and Doppler "
            "(ground_station.beacon.integrity); None: off")
    integrity_max_links: int = param(32, check=integer(1),
                                     doc="monitor channels (UAV ids beyond this many are used unjudged, counted)")
    integrity_common_fraction: float = param(
        0.5, check=number(0, lo_open=True, what=_FRACTION_HALF_OPEN),
        doc="an epoch of a trial whose links mostly jump at once (more than this fraction of its present links) is "
            "not judged: the track moved, not one link")
    integrity_min_links: int = param(
        3, check=integer(0),
        doc="the verdict leaves links out of a trial's update only while at least this many of its present links "
            "stay in (3: ranges and Dopplers of 3 UAVs fix the 6 states with no redundancy; below that an exclusion "
            "makes the track unobservable and the monitor detect-only for that trial and epoch)")
    lag_window_s: float = param(
        GroundStationSection.lag_window_s, check=_NONNEGATIVE,
        doc="out-of-sequence measurements (ground_station.beacon.locator): a measurement for an epoch already "
            "processed and at most this old (simulation time, s) is used by re-processing from that epoch; older "
            "ones are dropped (too_late). 0: no history kept; a late measurement is dropped as stale")

    def __post_init__(self):
        validate(self)
        require(self.observer_uncertainty != "consider" or self.motion == "cv", "observer_uncertainty",
                '"consider" needs motion="cv"')
        require(self.gate_prob < 1.0, "gate_prob", f"expected {_FRACTION_OPEN}, got {self.gate_prob!r}")
        for key in ("axis_ratio", "integrity_common_fraction"):
            require(getattr(self, key) <= 1.0, key, f"expected {_FRACTION_HALF_OPEN}, got {getattr(self, key)!r}")
        if self.init == "prior":
            require(len(self.prior_mean) == 6, "prior_mean", f'expected {_PRIOR_MEAN} with init="prior", got ()')
            require(len(self.prior_cov) == 6, "prior_cov", f'expected {_PRIOR_COV} with init="prior", got ()')
        else:
            require(not (self.prior_mean or self.prior_cov), "prior_mean" if self.prior_mean else "prior_cov",
                    'used only with init="prior"')

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
