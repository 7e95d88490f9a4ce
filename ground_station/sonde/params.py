"""The sonde tracker's parameters (SondeTrackerParams) and the state layout of each mode
(Layout, layout_for). The defaults are the world models' parameters: the filter knows the models,
not the truth's state (Moroz et al., seed 004: the state vector of eq 15, the Gauss-Markov
acceleration of eq 20, the radar's AR(1) errors of eqs 12-14)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from filters.integrity import IntegrityConfig
from sitl.atmosphere_std import Z_MAX_M
from sitl.bus import is_valid_id
from sitl.radio.radar import RadarParams
from sitl.radio.relay import RelayErrorBudget, RelayParams
from sitl.scenario import GroundStationSection

__all__ = ["KINEMATICS", "MODES", "RADAR_NOISE", "Layout", "SondeTrackerParams", "layout_for"]

MODES = ("fused", "radar_only", "relay_only")
RADAR_NOISE = ("colored", "white")
KINEMATICS = ("relaxed", "singer")
TWO_PI = 2.0 * math.pi

_RADAR_DEFAULT = RadarParams()
_RELAY_DEFAULT = RelayParams()


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
    # relaxed: the burst height's range (vehicles.sonde's burst_alt_range_m: uniform, low to high, m). A
    # climbing track (target vertical speed > 0) may burst in any step inside it, with the model's hazard:
    # the probability p = its climb over the step / the height left to the top (1 at the top); its target
    # then steps to -v_d(h), and Q carries that step's mean square, p (target + v_d(h))^2 (burst_variance).
    # None (or no descent law): no burst in the model, left to the manoeuvre hypothesis alone. The range is
    # the world's (vehicles.sonde.SondeParams); the composition root (sitl.app) hands it over, so it has no
    # default of its own here
    burst_alt_range_m: tuple | None = None
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
    lag_window_s: float = GroundStationSection.lag_window_s  # out-of-sequence messages this old are used by re-processing (0: dropped as stale)

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
        if self.burst_alt_range_m is not None:
            try:
                lo, hi = (float(a) for a in self.burst_alt_range_m)
            except (TypeError, ValueError):
                raise ValueError(f"burst_alt_range_m must be (low, high) in m or None, got {self.burst_alt_range_m!r}") from None
            if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo < hi <= Z_MAX_M):
                raise ValueError(f"burst_alt_range_m must satisfy 0 <= low < high <= {Z_MAX_M:g} m, "
                                 f"got {self.burst_alt_range_m!r}")
            object.__setattr__(self, "burst_alt_range_m", (lo, hi))
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
