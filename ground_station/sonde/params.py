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
from filters.params import Check, ParamError, choice, instance_of, integer, number, optional, param, require, several, switch, validate
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


_POSITIVE = number(0, lo_open=True)
_NONNEGATIVE = number(0)


def _label(value):
    if not is_valid_id(value):
        raise ParamError("", f"expected 1..64 chars of [A-Za-z0-9_.-], got {value!r}")
    return value


_FRACTION_OPEN = "a number in (0, 1)"
_FRACTION_HALF_OPEN = "a number in (0, 1]"


@dataclass(frozen=True)
class SondeTrackerParams:
    """The tracker's model of the sonde, the relay and the radar, and its gating (SI units).

    The defaults are the world models' parameters (vehicles.sonde.SondeParams,
    sitl.radio.relay.RelayParams, sitl.radio.radar.RadarParams): the filter knows the
    models, not the truth's state.
    """

    mode: str = param("fused", check=choice(*MODES), doc="which measurements the tracker uses: " + ", ".join(MODES))
    radar_noise: str = param("colored", check=choice(*RADAR_NOISE),
                             doc='"colored": the radar\'s AR(1) errors are states; "white": the naive white model')
    filter: str = param("ekf", check=choice("ekf", "ukf", "auto"),
                        doc='"ekf", "ukf" (the same models) or "auto" (per sonde and epoch, see auto_ukf_ratio)')
    auto_ukf_ratio: float = param(0.02, check=_POSITIVE,
                                  doc="auto: the UKF when sqrt(trace P_pos) exceeds this times the distance to the site")
    kinematics: str = param(
        "relaxed", check=choice(*KINEMATICS),
        doc='the sonde\'s motion: "relaxed" (vehicles.sonde\'s model: the velocity relaxes with the aerodynamic '
            "rate to the wind it meets, driven by the Gauss-Markov gust acceleration of eq 20; the wind and its rate "
            'of change are states) or "singer" (eq 20 as printed: the acceleration Gauss-Markov, the velocity its '
            "integral -- a random walk, which over a coast grows the position variance as T^3)")
    accel_rate_1_s: float = param(0.12, check=_POSITIVE,
                                  doc="p1 + p2 (seed eq 20): the rate of the gust acceleration (singer: of the "
                                      "acceleration), 1/s")
    sigma_acc_horizontal_m_s2: float = param(0.15, check=_NONNEGATIVE,
                                             doc="its stationary std per horizontal axis (relaxed: the gust a_g; "
                                                 "singer: the acceleration), m/s^2")
    sigma_acc_vertical_m_s2: float = param(0.10, check=_NONNEGATIVE, doc="its stationary std vertically, m/s^2")
    velocity_relax_rate_horizontal_1_s: float = param(0.1, check=_POSITIVE,
                                                      doc="relaxed: p1, the velocity relaxes to the wind in 1/p1, 1/s")
    velocity_relax_rate_vertical_1_s: float = param(0.2, check=_POSITIVE,
                                                    doc="relaxed: k_v, the vertical speed relaxes to its target, 1/s")
    wind_shear_sigma_horizontal_1_s: float = param(
        2.93e-3, check=_NONNEGATIVE,
        doc="relaxed: stationary std of the wind shear du/dh per horizontal axis, 1/s: the wind the sonde meets "
            "is the profile at its height, so it changes at the shear times the vertical speed; the shear is a "
            "state, Gauss-Markov in height (the default: sitl.app.experiments.sonde.wind_shear_statistics of the "
            "experiment's sonde, the default jet profile x 1.15 between the launch and the burst height)")
    wind_shear_sigma_vertical_1_s: float = param(
        0.0, check=_NONNEGATIVE,
        doc="relaxed: stationary std of the shear of the target vertical speed left once the descent law "
            "(descent_rate_sl_m_s) is applied, 1/s (the default: none, the ascent rate is constant)")
    wind_shear_corr_height_m: float = param(4430.0, check=_POSITIVE, doc="relaxed: the shear's correlation height, m")
    delta_d_rw_psd_m2_s: float = param(1e-6, check=_NONNEGATIVE,
                                       doc="PSD of the dd random walk (eq 21: a constant; a tiny slack), m^2/s")
    osc_gamma_1_s: float = param(_RELAY_DEFAULT.osc_gamma_1_s, check=_POSITIVE,
                                 doc="spectrum width of the relay LO's frequency offset, 1/s (the relay's)")
    osc_sigma_m_s: float = param(
        _RELAY_DEFAULT.osc_sigma_hz * _RELAY_DEFAULT.osc_doppler_scale_m_s_per_rad_s * TWO_PI, check=_POSITIVE,
        doc="stationary std of the relay LO's frequency offset as a pseudo-Doppler, m/s (the relay's)")
    radar_sigma: tuple = param(tuple(float(s) for s in _RADAR_DEFAULT.sigma), check=several(_POSITIVE, 3),
                               doc="stationary std of the radar's AR(1) errors (range m, az rad, el rad)")
    radar_gamma_1_s: tuple = param(tuple(float(g) for g in _RADAR_DEFAULT.gamma_1_s), check=several(_POSITIVE, 3),
                                   doc="spectrum widths of the radar's AR(1) errors (range, az, el), 1/s")
    radar_white_fraction: float = param(1e-3, check=_POSITIVE,
                                        doc="coloured radar model: the white part of R, a fraction of sigma^2")
    gate_prob: float | None = param(1.0 - 1e-4, check=optional(number(0, lo_open=True, what=_FRACTION_OPEN)),
                                    doc="probability of the chi-square gate per block, in (0, 1); None: no gating")
    manoeuvre_sigma_acc_m_s2: float = param(10.0, check=_NONNEGATIVE,
                                            doc="the unknown acceleration step of the manoeuvre hypothesis, m/s^2")
    manoeuvre_sigma_wind_m_s: float = param(30.0, check=_NONNEGATIVE,
                                            doc="relaxed: and the unknown step of the wind / target speed (the "
                                                "burst), m/s")
    descent_rate_sl_m_s: float | None = param(
        5.0, check=optional(_POSITIVE),
        doc="relaxed: the parachute's terminal speed at sea level, m/s, v_d(h) = v_sl sqrt(rho0 / rho(h)) "
            "(vehicles.sonde, US76): a descending sonde's target vertical speed -v_d(h) follows its height as a "
            "known input; None: off")
    burst_alt_range_m: tuple | None = param(
        None, check=optional(several(number(0), 2)),
        doc="relaxed: the burst height's range (low, high), m, 0 <= low < high <= the atmosphere's top "
            "(vehicles.sonde's burst_alt_range_m). A climbing track may burst in any step inside it, with the "
            "model's hazard p = its climb over the step / the height left to the top (1 at the top); its target "
            "then steps to -v_d(h), and Q carries that step's mean square, p (target + v_d(h))^2. None (or no "
            "descent law): no burst in the model, left to the manoeuvre hypothesis. The composition root "
            "(sitl.app) hands over the world's range: no default of its own here")
    landing: bool = param(True, check=switch(),
                          doc="relaxed: the sonde lands on flat ground at the site's height (the radar's, else the "
                              "ground receiver's) and stays there: a descending track whose height reaches it is "
                              "at rest from then on, until a re-initialisation; False: the track coasts on")
    max_coast_s: float | None = param(
        300.0, check=optional(_POSITIVE),
        doc="a track with no accepted measurement (a relay or radar block that passed the gate, or a fix that "
            "(re)initialised it) for longer than this is lost, s: its Estimate is no longer published (counted "
            "lost) and the next measurement initialises it again; None: never lost")
    manoeuvre_window: int | None = param(10, check=optional(integer(1)),
                                         doc="epochs of the sliding-window NIS test (None: off)")
    reacquire_after: int | None = param(5, check=optional(integer(1)),
                                        doc="re-initialise after this many rejected blocks in a row (None: never)")
    prior_sigma_vel_m_s: float = param(20.0, check=_POSITIVE, doc="prior std of the velocity at initialisation, m/s")
    prior_sigma_wind_offset_m_s: float = param(10.0, check=_NONNEGATIVE,
                                               doc="relaxed: prior std of the wind's offset from the velocity at "
                                                   "initialisation, m/s")
    prior_sigma_delta_d_m: float = param(3000.0, check=_POSITIVE, doc="prior std of dd at initialisation, m")
    relay_errors: RelayErrorBudget | None = param(_RELAY_DEFAULT.errors,
                                                  check=instance_of(RelayErrorBudget, none=True, what="a RelayErrorBudget or None"),
                                                  doc="the relay's error budget; None: white noise only")
    bias_slots: int = param(24, check=integer(1),
                            doc="per-satellite error states (relay modes with relay_errors); >= satellites in view")
    bias_tau_s: float | None = param(None, check=optional(_POSITIVE),
                                     doc="their correlation time, s; None: relay_errors' variance-weighted one")
    label: str | None = param(None, check=optional(Check(_label)),
                              doc='the Estimate\'s mode; None: mode (+ "_white" for the naive radar noise)')
    backend: str | None = param(None, check=optional(choice("auto", "numpy", "numba")),
                                doc="the filters.kernels backend (None: the default)")
    integrity: IntegrityConfig | None = param(
        None, check=instance_of(IntegrityConfig, none=True),
        doc="the integrity monitor (filters.integrity) around the updates; None: off")
    integrity_sat_channels: int = param(48, check=integer(1),
                                        doc="relayed-satellite channels of the monitor (>= satellites seen in its "
                                            "memory)")
    integrity_warmup_s: float = param(10.0, check=_NONNEGATIVE,
                                      doc="a track is not judged this long after its (re)initialisation or a "
                                          "manoeuvre, s")
    integrity_common_fraction: float = param(0.25, check=number(0, lo_open=True, what=_FRACTION_HALF_OPEN),
                                             doc="jumps on more than this fraction of a sonde's rows: a manoeuvre")
    lag_window_s: float = param(GroundStationSection.lag_window_s, check=_NONNEGATIVE,
                                doc="out-of-sequence messages this old are used by re-processing, s (0: dropped as "
                                    "stale)")

    def __post_init__(self):
        validate(self)
        for name in ("radar_sigma", "radar_gamma_1_s"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        if self.burst_alt_range_m is not None:
            lo, hi = self.burst_alt_range_m
            object.__setattr__(self, "burst_alt_range_m", (lo, hi))
            require(lo < hi <= Z_MAX_M, "burst_alt_range_m",
                    f"expected 0 <= low < high <= {Z_MAX_M:g} m, got {self.burst_alt_range_m!r}")
        require(self.gate_prob is None or self.gate_prob < 1.0, "gate_prob",
                f"expected {_FRACTION_OPEN} or None, got {self.gate_prob!r}")
        require(self.integrity_common_fraction <= 1.0, "integrity_common_fraction",
                f"expected {_FRACTION_HALF_OPEN}, got {self.integrity_common_fraction!r}")

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
