"""Relayed GNSS measurements at the ground complex-processing point G (seed 004, eqs 5-7, 16-27).

The radiosonde carries a wideband analogue relay: it receives the GNSS L1 signals,
shifts them to the sonde band (1680 MHz) with its local oscillator and re-radiates
them after a known internal delay tau_ret.  The ground receiver at G (known position)
tracks every relayed satellite and forms, per satellite i,

    pseudorange     d_Si  = |S_i - P| + |P - G| + dd + noise                   (eq 22)
    pseudo-Doppler  d'_Si = (K_i + K).V_P - K_i.W_i + (c / omega) Dw + noise   (eqs 16, 23)

with K_i = (P - S_i)/|P - S_i|, K = (P - G)/|P - G| (eqs 26-27), V_P the sonde velocity,
W_i the satellite velocity.  Sign convention: the pseudo-Doppler is the rate of the
path length, positive when the path grows (receding), in m/s: d/dt|S_i - P| =
K_i.(V_P - W_i) and d/dt|P - G| = K.V_P (G fixed in ECEF).

dd lumps the relay delay c tau_ret and the offset of the GCPP clock from system time:
dd = c (relay_delay_s + gcpp_clock_offset_s), constant over the flight (eq 21) and NOT
known to the estimator (it is reported only among the truth fields).

Relay oscillator (eqs 16-17).  The LO frequency offset Dw (rad/s) is a first-order
Gauss-Markov process and the oscillator phase integrates it:

    dDw/dt = -gamma Dw + sqrt(2 gamma sigma_w^2) n_w,   dphi/dt = Dw + sqrt(N/2) n_phi,

discretised exactly for any step (phi, Dw are an integrated Ornstein-Uhlenbeck pair:
F = [[1, (1 - e^{-gT})/g], [0, e^{-gT}]], Q = sigma_w^2 [[2/g (T - 2(1-e^{-gT})/g +
(1-e^{-2gT})/(2g)), (1-e^{-gT})^2/g], [., 1 - e^{-2gT}]] + diag(N/2 T, 0)), stationary
start Dw(0) ~ N(0, sigma_w^2), phi(0) = 0.  The seed's phase equation phi' = Dw +
(omega/c) d'_S + ... means that the measured carrier frequency, converted to m/s with
c/omega, is d'_S + (c/omega) Dw: the LO offset expressed in m/s, c Df / f_carrier,
adds to every satellite's pseudo-Doppler of that sonde (a common term, like a receiver
clock drift).  omega is the L1 carrier: the seed treats the relayed band as L1
("because 1680 MHz is close to L1 we take the relay to re-radiate at this frequency");
the real downlink at 1680 MHz would scale the K.V_P term by 1680/1575.42, not modelled.
The white phase noise N/2 is reported in the phase only; the white frequency noise of
the tracking loop is the pseudo-Doppler noise sigma_prr.

Geometry.  The ground reception time is t.  The signal left the sonde at t - tau_down
(tau_down = |P - G|/c <= 0.84 ms) and entered the relay tau_ret earlier.  The satellite
leg uses the light-time solution of ``sitl.gnss.ranging.light_time_geometry`` with the
sonde as receiver at t_in = t - tau_down - tau_ret (satellite at emission, Earth
rotation during the flight, exact range rate); the sonde position there is P - V_P
(tau_down + tau_ret) (a few cm).  The downlink is |R3(w_e tau_down) P - G| (the Earth
turns during the downlink too; the Sagnac term (w_e/c)(x_P y_G - y_P x_G) is < 0.5 m,
switchable with ``downlink_sagnac``).  The rates are derivatives with respect to
t_in; d t_in/dt = 1 - K.V_P/c changes them by < 2e-4 m/s.

What the ground receiver reports as satellite states (``sat_pos_ecef_m``,
``sat_vel_ecef_m_s``): the ephemeris at its measured transit time d_S/c, rotated into
the ECEF frame of t (``sitl.gnss.world.ephemeris_for_filter``).  Against those states the
model above holds with P read as the sonde's downlink-emission point in that frame,
which is within ~0.5 m (the Sagnac rotation) of the true ECEF position; the dd/c error
in the transit time moves the satellites by ~4 mm per microsecond of dd.  Both are far
below sigma_pr.  The truth fields give the exact geometry for scoring and tests.

Delivery.  Satellite i is delivered at an epoch when (a) it is above ``sat_el_mask_rad``
at the sonde (geodetic horizon of the sonde), (b) the sonde is visible from G: its
elevation above G's horizon is >= ``ground_el_mask_rad`` and |P - G| <=
``max_range_m`` (the 250 km operating radius of seed 004), and (c) t is not inside
an outage interval of ``outage_schedule`` ((t_start, t_end), closed-open), during
which the relay delivers nothing.

Noise: white, N(0, sigma_pr^2) and N(0, sigma_prr^2) per satellite and epoch (the ground
receiver's code and frequency tracking noise on the weak relayed signal; the seed gives no
values, the defaults (5 m, 0.1 m/s) suit a relayed C/A-code signal).  These are the only
variances the receiver reports (``var_pr_m2``, ``var_prr_m2_s2``): it cannot know the
propagation errors below.

Error budget (``RelayParams.errors``, a :class:`RelayErrorBudget`; ``errors=None`` is the
white-noise-only world of before, bitwise).  Seed eq 4 writes the pseudorange to a satellite
as d = d_i + Dd_ion + Dd_trop + Dd_eph + Dd_phi + Dd_t (ionospheric and tropospheric delays,
ephemeris error, random fluctuations of the satellite clock, time-scale offset); eq 7 adds
for the relayed path the relay LO fluctuations, the GCPP clock offset and the relay delay
c tau_ret; eqs 21-22 lump everything into ONE dd, common to all satellites and "constant over
an interval [t_k, t_k + T]" (which "presupposes a sufficiently stable LO").  The seed gives
no magnitudes.  The terms of eqs 4 and 7 that are not common to all satellites, or not
constant, are modelled here with standard single-frequency GNSS values, each a first-order
Gauss-Markov process of unit variance, u(k) = mu u(k-1) + sqrt(1 - mu^2) n(k), mu =
e^{-T/tau}, stationary start u(0) = n(0), scaled by its standard deviation at the current
geometry (so the variance follows the elevation and the sonde's height, the correlation
time is tau):

  * Dd_eph + Dd_phi, broadcast orbit and clock (signal-in-space range error, SISRE):
    ``sisre_gps_m`` 0.6 m, ``sisre_glonass_m`` 1.5 m, ``sisre_tau_s`` 3600 s  [1, 2, 4];
  * Dd_ion, the ionosphere left after the broadcast (Klobuchar) model: ``iono_zenith_m``
    1.5 m x the thin-shell obliquity F(el) = 1/sqrt(1 - (R cos el/(R + h_I))^2), h_I =
    ``iono_shell_h_m`` 350 km (F = 1 at zenith, 3.0 at 5 deg, 3.1 at the horizon), ``iono_tau_s`` 1800 s  [3, 4, 5];
    the sonde (< 40 km) is below the ionosphere, so its satellite leg has the whole delay;
  * Dd_trop, the troposphere left after a standard-atmosphere model: ``tropo_zenith_m``
    0.05 m x p(h)/p0 (US-76 pressure at the sonde's height: the delay comes from the air
    above it) x m(el) = 1.001/sqrt(0.002001 + sin^2 el), ``tropo_tau_s`` 3600 s  [4, 5];
  * multipath at the sonde's antenna, the airborne model sigma(el) = ``multipath_a_m`` 0.13 m
    + ``multipath_b_m`` 0.53 m e^{-el/``multipath_el0_deg`` 10 deg}, ``multipath_tau_s`` 5 s
    (the sonde swings under the balloon with a period of ~10 s)  [5];
  * relay-path variations, common to every satellite of a sonde (added to dd, which stops
    being constant): the relay's group delay changes with its temperature (+20 to -60 C in
    the ascent) and the GCPP clock wanders: ``path_sigma_m`` 1.5 m (5 ns), ``path_tau_s``
    1200 s.  No published value exists for this relay: an assumption, stated as such.

[1] GPS SPS Performance Standard, 5th ed. (2020), and the measured SISRE of ~0.5-0.6 m RMS
(Montenbruck, Steigenberger, Hauschild, "Broadcast versus precise ephemerides", GPS Solutions
19, 2015); [2] same paper: GLONASS broadcast SISRE ~1.5-2 m; [3] Klobuchar, IEEE Trans. AES
23 (1987): the broadcast model removes ~50 % RMS of the delay; a mid-latitude L1 vertical
delay of ~3 m (~20 TECU) leaves ~1.5 m; [4] Misra and Enge, "GPS: Signals, Measurements, and
Performance", 2nd ed. (2006), ch. 5: error budget, residuals as first-order Gauss-Markov
processes with correlation times of tens of minutes to hours; [5] RTCA DO-229 (WAAS MOPS),
appendix J: thin-shell obliquity, tropospheric mapping function and residual (0.12 m zenith
at sea level for a climatological model, 0.05 m here with the GCPP's surface weather),
airborne multipath model.

The propagation errors sit on the pseudoranges only: their rates (mm/s for real
ionosphere, troposphere and orbit drift) are far below the pseudo-Doppler noise, and a
first-order Gauss-Markov process has no rate to give.  The per-satellite sum (multipath
included) is reported as ``pr_error_m`` and the common path variation is inside
``delta_d_m``, among the truth fields.  Every process runs at every epoch, delivered or not
(outages, satellites below the mask), so a satellite that returns keeps its error.

Randomness: ``rng`` is one Generator for the batch, or one per sonde (then a sonde's
numbers depend only on its own stream).  Per sonde and epoch the relay draws 2 S + 2
normals (S pseudorange noises, S pseudo-Doppler noises, 2 oscillator innovations --
the first epoch uses the first for Dw(0)), then, with an error budget, 4 S + 1 more (S each
for the SISRE, ionosphere, troposphere and multipath processes, then 1 for the path
variation; the first epoch uses them for the stationary start), whatever is delivered.

Stepping: :meth:`Relay.step` one epoch at a time, or :meth:`Relay.track` a whole
trajectory (the same numbers, a block of epochs per light-time call: ~10x faster).

Shapes: the satellites sit on a fixed last axis S (the constellation order); not
delivered entries are NaN; the leading batch axes (...) are sondes.  :func:`compact`
extracts the delivered satellites of one sonde.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from filters.params import instance_of, number, param, require, switch, validate
from sitl.constants import C_M_S, F_GPS_L1_HZ, WGS84
from sitl.geodesy import ecef_to_aer, ecef_to_geodetic
from sitl.gnss.orbits import Constellation
from sitl.gnss.ranging import finite_vec3 as _vec3
from sitl.gnss.ranging import light_time_geometry
from sitl.gnss.world import ephemeris_for_filter, look_angles
from sitl.radio import relay_error_model
from sitl.radio.radar import (
    _EL_MASK,
    MAX_RANGE_M,
    _el_mask_below_zenith,
    _in_schedule,
    _intervals,
    _site,
    _Streams,
    _time,
)
from sitl.radio.relay_error_model import LN_P_TABLE, P_TABLE_H_M, pressure_ratio  # noqa: F401 (re-exported)

__all__ = ["Relay", "RelayEpoch", "RelayErrorBudget", "RelayParams", "RelayTrack", "compact", "gauss_markov_step",
           "oscillator_discretisation"]


def _phi_var_factor(x: float) -> float:
    """x - 2 (1 - e^-x) + (1 - e^-2x) / 2, without cancellation for small x."""
    if x < 0.05:
        # sum_{k>=3} (-1)^(k+1) (2^(k-1) - 2) x^k / k!
        return sum((-1) ** (k + 1) * (2.0 ** (k - 1) - 2.0) * x**k / math.factorial(k) for k in range(3, 12))
    return x - 2.0 * (-math.expm1(-x)) + 0.5 * (-math.expm1(-2.0 * x))


def oscillator_discretisation(gamma_1_s: float, sigma_w_rad_s: float, phase_psd_rad2_s: float, dt_s: float):
    """Exact F (2, 2) and Q (2, 2) of [phi, Dw] over dt_s (see the module docstring)."""
    g, s2, T = gamma_1_s, sigma_w_rad_s**2, dt_s
    x = g * T
    e1 = -math.expm1(-x)  # 1 - e^-gT
    F = np.array([[1.0, e1 / g], [0.0, 1.0 - e1]])
    q_pp = 2.0 * s2 / g**2 * _phi_var_factor(x) + phase_psd_rad2_s * T
    q_pw = s2 * e1 * e1 / g
    q_ww = s2 * (-math.expm1(-2.0 * x))
    return F, np.array([[q_pp, q_pw], [q_pw, q_ww]])


def _sqrt_psd(q: np.ndarray) -> np.ndarray:
    w, v = np.linalg.eigh(q)
    return v * np.sqrt(np.clip(w, 0.0, None))


def gauss_markov_step(u: np.ndarray, n: np.ndarray, dt_s: float, tau_s) -> np.ndarray:
    """One step of unit-variance first-order Gauss-Markov processes: mu u + sqrt(1 - mu^2) n,
    mu = e^{-dt/tau} (tau scalar or broadcasting against u)."""
    mu = np.exp(-dt_s / np.asarray(tau_s, dtype=float))
    return mu * u + np.sqrt(-np.expm1(-2.0 * dt_s / np.asarray(tau_s, dtype=float))) * n


@dataclass(frozen=True)
class RelayErrorBudget:
    """The relayed pseudoranges' propagation and relay errors (see the module docstring for
    the values and their sources). Standard deviations in m, correlation times in s."""

    sisre_gps_m: float = param(0.6, check=number(0), doc="broadcast orbit and clock error (SISRE) of a GPS satellite (1 sigma), m")
    sisre_glonass_m: float = param(1.5, check=number(0),
                                   doc="broadcast orbit and clock error (SISRE) of a GLONASS satellite (1 sigma), m")
    sisre_tau_s: float = param(3600.0, check=number(0, lo_open=True), doc="correlation time of the SISRE, s")
    iono_zenith_m: float = param(1.5, check=number(0),
                                 doc="zenith ionospheric delay left after the broadcast model (1 sigma), m, times the "
                                     "thin-shell obliquity")
    iono_shell_h_m: float = param(350e3, check=number(0, lo_open=True), doc="height of the ionosphere's thin shell, m")
    iono_tau_s: float = param(1800.0, check=number(0, lo_open=True), doc="correlation time of the ionospheric error, s")
    tropo_zenith_m: float = param(0.05, check=number(0),
                                  doc="zenith tropospheric delay left after a standard-atmosphere model at sea level "
                                      "(1 sigma), m, times p(h)/p0 and the mapping m(el)")
    tropo_tau_s: float = param(3600.0, check=number(0, lo_open=True),
                               doc="correlation time of the tropospheric error, s")
    multipath_a_m: float = param(0.13, check=number(0), doc="airborne multipath std a of a + b e^(-el / el0), m")
    multipath_b_m: float = param(0.53, check=number(0), doc="airborne multipath std b of a + b e^(-el / el0), m")
    multipath_el0_deg: float = param(10.0, check=number(0, lo_open=True),
                                     doc="elevation scale el0 of the multipath std a + b e^(-el / el0), deg")
    multipath_tau_s: float = param(5.0, check=number(0, lo_open=True), doc="correlation time of the multipath, s")
    path_sigma_m: float = param(1.5, check=number(0),
                                doc="relay-path variation common to a sonde's satellites (the relay's group delay, the "
                                    "GCPP clock; 1 sigma), m: an assumption, no published value")
    path_tau_s: float = param(1200.0, check=number(0, lo_open=True), doc="correlation time of the path error, s")

    def __post_init__(self):
        validate(self)

    @property
    def slow_tau_s(self) -> np.ndarray:
        """(3,) correlation times of [SISRE, ionosphere, troposphere]."""
        return np.array([self.sisre_tau_s, self.iono_tau_s, self.tropo_tau_s])

    @property
    def iono_shell_ratio(self) -> float:
        """R / (R + h_I): the thin shell's radius ratio of the obliquity factor."""
        return WGS84.a_m / (WGS84.a_m + self.iono_shell_h_m)

    def iono_obliquity(self, el_rad):
        """Thin-shell obliquity factor F(el) = 1/sqrt(1 - (R cos el / (R + h_I))^2)."""
        return relay_error_model.iono_obliquity(self.iono_shell_ratio, el_rad)

    @staticmethod
    def tropo_mapping(el_rad):
        """m(el) = 1.001 / sqrt(0.002001 + sin^2 el) (RTCA DO-229)."""
        return relay_error_model.tropo_mapping(el_rad)

    def slow_sigmas_m(self, glonass, el_rad, h_m) -> np.ndarray:
        """(..., 3) std of [SISRE, ionosphere, troposphere] for satellites seen at elevation
        el_rad (...) from a sonde at height h_m (broadcasting against el_rad); glonass (...)
        bool: the satellite is a GLONASS one."""
        el = np.asarray(el_rad, dtype=float)
        sisre = np.where(glonass, self.sisre_glonass_m, self.sisre_gps_m) * np.ones_like(el)
        iono = relay_error_model.iono_sigma_m(self.iono_zenith_m, self.iono_shell_ratio, el)
        tropo = relay_error_model.tropo_sigma_m(self.tropo_zenith_m, pressure_ratio(h_m), el)
        return np.stack(np.broadcast_arrays(sisre, iono, tropo), axis=-1)

    def multipath_sigma_m(self, el_rad):
        """Airborne multipath std: a + b e^{-el / el0}."""
        return relay_error_model.multipath_sigma_m(self.multipath_a_m, self.multipath_b_m, self.multipath_el0_deg,
                                                   np.asarray(el_rad, dtype=float))


_GCPP_OFFSET = "a finite number below 1 ms in size"


@dataclass(frozen=True)
class RelayParams:
    """Relay / ground-receiver parameters (SI units, angles in radians)."""

    sigma_pr_m: float = param(5.0, check=number(0), doc="white pseudorange noise of the relayed code (1 sigma), m")
    sigma_prr_m_s: float = param(0.1, check=number(0), doc="white pseudo-Doppler noise (1 sigma), m/s")
    sat_el_mask_rad: float = param(math.radians(5.0), check=_EL_MASK,
                                   doc="elevation mask of the satellites at the sonde, rad")
    ground_el_mask_rad: float = param(0.0, check=_EL_MASK,
                                      doc="elevation mask of the sonde seen from the ground receiver G, rad")
    max_range_m: float = param(MAX_RANGE_M, check=number(0, lo_open=True), doc="radio range G - sonde, m")
    relay_delay_s: float = param(1.5e-6, check=number(0), doc="the relay's retransmission delay tau_ret, s")
    gcpp_clock_offset_s: float = param(100e-9, check=number(what=_GCPP_OFFSET),
                                       doc="the ground receiver's (GCPP) clock minus system time, s (|offset| < 1 ms)")
    osc_sigma_hz: float = param(10.0, check=number(0), doc="stationary std of the relay LO's frequency offset, Hz")
    osc_gamma_1_s: float = param(1e-3, check=number(0, lo_open=True),
                                 doc="spectrum width of the LO frequency offset, 1/s (correlation time 1/gamma)")
    osc_phase_psd_rad2_s: float = param(0.0, check=number(0), doc="white phase noise PSD N/2 of eq 16, rad^2 s")
    carrier_hz: float = param(F_GPS_L1_HZ, check=number(0, lo_open=True),
                              doc="carrier that converts the LO offset to m/s, Hz")
    outage_schedule: tuple = param((), check=_intervals,
                                   doc="((t_start, t_end), ...) GPS s: nothing is delivered in these intervals")
    downlink_sagnac: bool = param(True, check=switch(),
                                  doc="the Sagnac correction of the sonde-to-ground downlink is in the simulated delay")
    errors: RelayErrorBudget | None = param(RelayErrorBudget(), check=instance_of(RelayErrorBudget, none=True, what="a RelayErrorBudget or None"),
                                            doc="the propagation and relay error budget; None: white noise only "
                                                "(the old world)")

    def __post_init__(self):
        validate(self)
        for key in ("sat_el_mask_rad", "ground_el_mask_rad"):
            _el_mask_below_zenith(self, key)
        require(abs(self.gcpp_clock_offset_s) < 1e-3, "gcpp_clock_offset_s",
                f"expected {_GCPP_OFFSET}, got {self.gcpp_clock_offset_s!r}")

    @property
    def delta_d_m(self) -> float:
        """dd = c (tau_ret + GCPP clock offset)."""
        return C_M_S * (self.relay_delay_s + self.gcpp_clock_offset_s)

    @property
    def osc_doppler_scale_m_s_per_rad_s(self) -> float:
        """c / omega_carrier: the LO offset Dw (rad/s) expressed in m/s."""
        return C_M_S / (2.0 * math.pi * self.carrier_hz)


class RelayEpoch(NamedTuple):
    """One epoch at the ground receiver for a batch of sondes (...) and S satellites."""

    t_gps_s: float
    sat_id: np.ndarray  # (S,) constellation order
    delivered: np.ndarray  # (..., S) bool
    pseudorange_m: np.ndarray  # (..., S), NaN where not delivered
    pseudo_doppler_m_s: np.ndarray  # (..., S)
    var_pr_m2: np.ndarray  # (..., S)
    var_prr_m2_s2: np.ndarray  # (..., S)
    sat_pos_ecef_m: np.ndarray  # (..., S, 3) ground receiver's ephemeris (frame of t)
    sat_vel_ecef_m_s: np.ndarray  # (..., S, 3)
    ground_pos_ecef_m: np.ndarray  # (3,) G
    sonde_visible: np.ndarray  # (...) elevation from G >= mask and within max_range_m
    outage: bool  # t inside an outage interval
    # truth for scoring and tests only:
    true_path_m: np.ndarray  # (..., S) |S_i - P| + downlink (every satellite)
    true_path_rate_m_s: np.ndarray  # (..., S) its rate
    true_sat_pos_ecef_m: np.ndarray  # (..., S, 3) satellite at emission, frame of t_in
    true_sat_vel_ecef_m_s: np.ndarray
    true_sonde_pos_ecef_m: np.ndarray  # (..., 3) P at t_in
    sat_el_at_sonde_rad: np.ndarray  # (..., S)
    delta_d_m: np.ndarray  # (...) dd: the constant c (tau_ret + clock) + the path variation
    osc_freq_rad_s: np.ndarray  # (...) Dw
    osc_phase_rad: np.ndarray  # (...) phi
    osc_doppler_m_s: np.ndarray  # (...) (c/omega) Dw, in every pseudo-Doppler
    pr_error_m: np.ndarray  # (..., S) per-satellite error budget (SISRE + iono + tropo + multipath)


def compact(epoch: RelayEpoch, index=()) -> dict:
    """The delivered satellites of one sonde (index into the batch axes) as compact arrays:
    sat_id, pseudorange_m, pseudo_doppler_m_s, var_pr_m2, var_prr_m2_s2, sat_pos_ecef_m,
    sat_vel_ecef_m_s (n delivered rows) and ground_pos_ecef_m."""
    idx = index if isinstance(index, tuple) else (index,)
    m = epoch.delivered[idx]
    out = {"t_gps_s": epoch.t_gps_s, "sat_id": epoch.sat_id[m], "ground_pos_ecef_m": epoch.ground_pos_ecef_m}
    for f in ("pseudorange_m", "pseudo_doppler_m_s", "var_pr_m2", "var_prr_m2_s2", "sat_pos_ecef_m",
              "sat_vel_ecef_m_s"):
        out[f] = getattr(epoch, f)[idx][m]
    return out


class Relay:
    """The sonde relays + the ground receiver at G, for a batch of sondes.

    Parameters
    ----------
    rng : Generator, or a sequence of one Generator per sonde.
    constellation : the GNSS satellites (sitl.gnss.orbits).
    ground_lat_rad, ground_lon_rad, ground_h_m : G (geodetic, WGS-84).
    params : RelayParams.
    batch_shape : sonde batch shape (default () or (len(rng),)).
    """

    def __init__(self, rng, constellation: Constellation, *, ground_lat_rad, ground_lon_rad, ground_h_m,
                 params: RelayParams | None = None, batch_shape=None):
        self.params = RelayParams() if params is None else params
        if not isinstance(self.params, RelayParams):
            raise ValueError(f"params: expected a RelayParams, got {type(self.params).__name__}")
        if not isinstance(constellation, Constellation):
            raise ValueError(f"constellation: expected a Constellation, got {type(constellation).__name__}")
        self.constellation = constellation
        self.ground_geodetic, self.ground_pos_ecef_m = _site(ground_lat_rad, ground_lon_rad, ground_h_m, "ground")
        self._streams = _Streams.for_batch(rng, batch_shape)
        self.batch_shape = batch_shape = self._streams.batch_shape
        self._t = None
        self._osc = np.zeros(batch_shape + (2,))  # [phi, Dw]
        self._sigma_w = 2.0 * math.pi * self.params.osc_sigma_hz
        S = len(constellation)
        self._glonass = np.char.startswith(constellation.sat_id.astype(str), "R")
        self._u = np.zeros(batch_shape + (S, 4))  # unit GM: SISRE, iono, tropo, multipath
        self._g = np.zeros(batch_shape)  # unit GM: relay path variation
        self._t_err = None

    def step(self, t_gps_s, sonde_pos_ecef_m, sonde_vel_ecef_m_s) -> RelayEpoch:
        """The relayed measurements received at G at time t_gps_s (strictly increasing).

        sonde_pos_ecef_m, sonde_vel_ecef_m_s : (..., 3) the sondes' true state at t.
        """
        t = _time("t_gps_s", t_gps_s)
        if self._t is not None and not t > self._t:
            raise ValueError(f"t_gps_s must increase from step to step: {t} after {self._t}")
        shape = self.batch_shape + (3,)
        pos = self._state("sonde_pos_ecef_m", sonde_pos_ecef_m, shape)
        vel = self._state("sonde_vel_ecef_m_s", sonde_vel_ecef_m_s, shape)
        out = self._compute(np.array([t]), pos[None], vel[None])
        return RelayEpoch(*(v if f in ("sat_id", "ground_pos_ecef_m") else (float(v[0]) if f == "t_gps_s" else
                                                                             (bool(v[0]) if f == "outage" else v[0]))
                            for f, v in zip(RelayEpoch._fields, out)))

    def track(self, t_gps_s, sonde_pos_ecef_m, sonde_vel_ecef_m_s, *, block: int = 128) -> RelayTrack:
        """Many epochs at once: t (T,) strictly increasing, states (T, ..., 3).

        The same numbers as T calls of :meth:`step` (the same draws in the same order; the
        light-time solution agrees to ~1e-7 m), computed a block of epochs per call.
        """
        t = np.asarray(t_gps_s, dtype=float)
        if t.ndim != 1 or t.size == 0 or not np.all(np.isfinite(t)):
            raise ValueError(f"t_gps_s must be a non-empty 1-D array of finite GPS times, got shape {t.shape}")
        if np.any(np.diff(t) <= 0.0) or (self._t is not None and not t[0] > self._t):
            raise ValueError("t_gps_s must increase strictly (and follow the previous step)")
        shape = (t.size,) + self.batch_shape + (3,)
        pos = self._state("sonde_pos_ecef_m", sonde_pos_ecef_m, shape)
        vel = self._state("sonde_vel_ecef_m_s", sonde_vel_ecef_m_s, shape)
        if isinstance(block, bool) or not isinstance(block, (int, np.integer)) or block < 1:
            raise ValueError(f"block must be an integer >= 1, got {block!r}")
        parts = [self._compute(t[k:k + block], pos[k:k + block], vel[k:k + block]) for k in range(0, t.size, block)]
        cols = []
        for f, *vals in zip(RelayEpoch._fields, *parts):
            cols.append(vals[0] if f in ("sat_id", "ground_pos_ecef_m") else np.concatenate(vals))
        return RelayTrack(*cols)

    @staticmethod
    def _state(name, value, shape) -> np.ndarray:
        a = _vec3(name, value)
        if a.shape != shape:
            raise ValueError(f"{name} must have shape {shape}, got {a.shape}")
        return a

    def _oscillator(self, t: np.ndarray, n_osc: np.ndarray) -> np.ndarray:
        """[phi, Dw] (K, ..., 2) at the epochs t (K,) from the innovations (K, ..., 2)."""
        p = self.params
        out = np.empty(n_osc.shape)
        cache = {}
        for k in range(t.size):
            if self._t is None:
                self._osc = np.zeros(self.batch_shape + (2,))
                self._osc[..., 1] = self._sigma_w * n_osc[k, ..., 0]
            else:
                dt = float(t[k] - self._t)
                if dt not in cache:
                    F, Q = oscillator_discretisation(p.osc_gamma_1_s, self._sigma_w, p.osc_phase_psd_rad2_s, dt)
                    cache[dt] = (F.T, _sqrt_psd(Q).T)
                ft, lt = cache[dt]
                # elementwise (not matmul): a sonde's numbers do not depend on the batch size
                ph, w, n0, n1 = self._osc[..., 0], self._osc[..., 1], n_osc[k, ..., 0], n_osc[k, ..., 1]
                self._osc = np.stack([ph + ft[1, 0] * w + (lt[0, 0] * n0 + lt[1, 0] * n1),
                                      ft[1, 1] * w + (lt[0, 1] * n0 + lt[1, 1] * n1)], -1)
            self._t = float(t[k])
            out[k] = self._osc
        return out

    def _errors(self, t: np.ndarray, n_err: np.ndarray, sig_slow: np.ndarray, sig_mp: np.ndarray):
        """Per-satellite error (K, ..., S) and common path variation (K, ...) at the epochs t (K,)
        from the innovations n_err (K, ..., 4 S + 1) and the current stds (K, ..., S, 3), (K, ..., S)."""
        e = self.params.errors
        S = sig_mp.shape[-1]
        taus = np.array([e.sisre_tau_s, e.iono_tau_s, e.tropo_tau_s, e.multipath_tau_s])
        pr_err = np.empty(sig_mp.shape)
        path = np.empty(n_err.shape[:-1])
        for k in range(t.size):
            nu = np.moveaxis(n_err[k, ..., :4 * S].reshape(self.batch_shape + (4, S)), -2, -1)
            ng = n_err[k, ..., 4 * S]
            if self._t_err is None:
                self._u, self._g = nu, ng
            else:
                dt = float(t[k] - self._t_err)
                self._u = gauss_markov_step(self._u, nu, dt, taus)
                self._g = gauss_markov_step(self._g, ng, dt, e.path_tau_s)
            self._t_err = float(t[k])
            pr_err[k] = np.sum(sig_slow[k] * self._u[..., :3], axis=-1) + sig_mp[k] * self._u[..., 3]
            path[k] = e.path_sigma_m * self._g
        return pr_err, path

    def _compute(self, t: np.ndarray, pos: np.ndarray, vel: np.ndarray) -> tuple:
        """RelayEpoch fields with a leading epoch axis K (t (K,), pos/vel (K, ..., 3))."""
        p, c = self.params, self.constellation
        S, K = len(c), t.size
        tb = t.reshape((K,) + (1,) * len(self.batch_shape))  # broadcasts against (K, ...)
        nd = 2 * S + 2 + (0 if p.errors is None else 4 * S + 1)
        normals = np.stack([self._streams.normal(nd) for _ in range(K)]) if self._streams.single is None \
            else self._streams.single.standard_normal((K, self._streams.n, nd)).reshape(
                (K,) + self.batch_shape + (nd,))
        n_pr, n_prr, n_osc = normals[..., :S], normals[..., S:2 * S], normals[..., 2 * S:2 * S + 2]
        osc = self._oscillator(t, n_osc)
        osc_dopp = p.osc_doppler_scale_m_s_per_rad_s * osc[..., 1]

        g = self.ground_pos_ecef_m
        # downlink: emission point rotated into the frame of t (Sagnac), light time
        tau_down = np.linalg.norm(pos - g, axis=-1) / C_M_S
        p_out = pos - vel * tau_down[..., None]
        if p.downlink_sagnac:
            th = WGS84.omega_rad_s * tau_down
            ct, st = np.cos(th), np.sin(th)
            p_rot = np.stack([ct * p_out[..., 0] + st * p_out[..., 1], ct * p_out[..., 1] - st * p_out[..., 0],
                              p_out[..., 2]], axis=-1)
        else:
            p_rot = p_out
        d_down = p_rot - g
        down = np.linalg.norm(d_down, axis=-1)
        # K = (P - G)/|P - G|; undefined with the sonde on G itself (launch from G): K.V := 0
        down_rate = np.divide(np.sum(d_down * vel, axis=-1), down, out=np.zeros_like(down), where=down > 0.0)

        # satellite leg: light time with the sonde as receiver at t_in
        t_in = tb - tau_down - p.relay_delay_s
        p_in = pos - vel * (tau_down + p.relay_delay_s)[..., None]
        geo = light_time_geometry(t_in, p_in, vel, c)
        _, sat_el = look_angles(p_in, geo)
        true_path = geo.range_m + down[..., None]
        true_rate = geo.range_rate_m_s + down_rate[..., None]

        _, el_g, _ = ecef_to_aer(g, pos)
        visible = (el_g >= p.ground_el_mask_rad) & (down <= p.max_range_m)
        outage = np.array([_in_schedule(p.outage_schedule, float(x)) for x in t])
        delivered = ((sat_el >= p.sat_el_mask_rad) & visible[..., None]
                     & ~outage.reshape(tb.shape + (1,)))

        dd = np.full((K,) + self.batch_shape, p.delta_d_m)
        if p.errors is None:
            pr_err = np.zeros(true_path.shape)
        else:
            _, _, h_son = ecef_to_geodetic(p_in)
            sig_slow = p.errors.slow_sigmas_m(self._glonass, sat_el, h_son[..., None])
            pr_err, path = self._errors(t, normals[..., 2 * S + 2:], sig_slow, p.errors.multipath_sigma_m(sat_el))
            dd = dd + path
        pr = np.where(delivered, true_path + dd[..., None] + pr_err + p.sigma_pr_m * n_pr, np.nan)
        prr = np.where(delivered, true_rate + osc_dopp[..., None] + p.sigma_prr_m_s * n_prr, np.nan)
        sat_pos, sat_vel = ephemeris_for_filter(tb, pr, c, pseudorange_rate_m_s=prr)
        var_pr = np.where(delivered, p.sigma_pr_m**2, np.nan)
        var_prr = np.where(delivered, p.sigma_prr_m_s**2, np.nan)
        return (t.copy(), c.sat_id, delivered, pr, prr, var_pr, var_prr, sat_pos, sat_vel, g.copy(), visible, outage,
                true_path, true_rate, geo.sat_pos_ecef_m, geo.sat_vel_ecef_m_s, p_in, sat_el, dd,
                osc[..., 1], osc[..., 0], osc_dopp, pr_err)


class RelayTrack(NamedTuple):
    """RelayEpoch fields stacked on a leading epoch axis T (sat_id and ground_pos_ecef_m
    are shared; t_gps_s and outage are (T,))."""

    t_gps_s: np.ndarray
    sat_id: np.ndarray
    delivered: np.ndarray
    pseudorange_m: np.ndarray
    pseudo_doppler_m_s: np.ndarray
    var_pr_m2: np.ndarray
    var_prr_m2_s2: np.ndarray
    sat_pos_ecef_m: np.ndarray
    sat_vel_ecef_m_s: np.ndarray
    ground_pos_ecef_m: np.ndarray
    sonde_visible: np.ndarray
    outage: np.ndarray
    true_path_m: np.ndarray
    true_path_rate_m_s: np.ndarray
    true_sat_pos_ecef_m: np.ndarray
    true_sat_vel_ecef_m_s: np.ndarray
    true_sonde_pos_ecef_m: np.ndarray
    sat_el_at_sonde_rad: np.ndarray
    delta_d_m: np.ndarray
    osc_freq_rad_s: np.ndarray
    osc_phase_rad: np.ndarray
    osc_doppler_m_s: np.ndarray
    pr_error_m: np.ndarray

    def epoch(self, k: int) -> RelayEpoch:
        return RelayEpoch(*(v if f in ("sat_id", "ground_pos_ecef_m") else
                            (float(v[k]) if f == "t_gps_s" else (bool(v[k]) if f == "outage" else v[k]))
                            for f, v in zip(RelayEpoch._fields, self)))
