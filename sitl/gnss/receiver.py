"""Single-frequency (L1) GPS+GLONASS receiver measurement generator (seed 000).

Measurements of satellite j at one epoch (seed 000, eqs. 18/19, 20-22, 35-37):

    pseudorange       D_j = R_j + Δ (+ Δ_A if GPS) + U_j + I_j + ε_D          ε_D ~ N(0, σ_D²)
    pseudorange rate  Ḋ_j = Ṙ_j + Δ̇ + ε_Ḋ                                     ε_Ḋ ~ N(0, σ_Ḋ²)
    carrier phase     G_j = R_j + Δ (+ Δ_A if GPS) + U_j − I_j + λ_j N_j + ε_G  ε_G ~ N(0, σ_G²)

R_j geometric range, Ṙ_j range rate (positive when the range grows), Δ / Δ̇ receiver clock
bias (m) and drift (m/s) against GLONASS time, Δ_A the GPS-GLONASS system-time offset (m),
U_j = U_g / sin el_j (eq. 11), I_j = I_g (f_ref/f_j)² m_I(el_j) (eq. 9), λ_j = c / f_j, and
N_j the integer carrier ambiguity. The seed's K_j = λ_j (φ0 − φ0_j + M_j) is modelled by
its integer part λ_j N_j alone: the fractional phase offsets are constant per satellite
pass and, like N_j, are absorbed by a per-satellite constant in the estimators.
Atmospheric effects on the Doppler are neglected, as in the seed.

Tracking model. The receiver works on a fixed satellite axis S (the whole constellation);
a satellite is tracked while its elevation is at or above the mask. On (re)acquisition a
fresh ambiguity N_j is drawn uniformly from the integers in [−M, M]. While tracked, a cycle
slip occurs with probability ``cycle_slip_rate_hz * T`` per satellite per epoch (T the
interval since the previous epoch) and changes N_j by a random non-zero integer in
±[1, slip_cycles_max]; slips can also be injected with ``Receiver.inject_slip``. Setting
below the mask loses lock.

Everything not tracked is NaN. Geometry arrays are (*batch, S), the leading axes being
trials; per-satellite constants (carrier, system) are (S,); the clock is (*batch,).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from filters.params import integer, number, param, require, validate
from sitl.constants import C_M_S, F_GPS_L1_HZ
from sitl.gnss.atmosphere import iono_slant_delay_m, tropo_slant_delay_m

_EL_MASK = "a number in (0, pi/2)"


@dataclass(frozen=True)
class ReceiverConfig:
    """Noise, mask, atmosphere and tracking parameters of the receiver (defaults: seed 000)."""

    sigma_pr_m: float = param(6.0, check=number(0), doc="pseudorange noise sigma_D (1 sigma), m")
    sigma_prr_m_s: float = param(0.064, check=number(0), doc="pseudorange-rate noise sigma_Ddot (1 sigma), m/s")
    sigma_phase_m: float = param(0.003, check=number(0), doc="carrier-phase noise sigma_G (1 sigma), m")
    el_mask_rad: float = param(float(np.deg2rad(5.0)), check=number(0, lo_open=True, what=_EL_MASK),
                               doc="elevation mask, rad: a satellite is tracked iff el >= mask; in (0, pi/2), "
                                   "since 1/sin el is singular at the horizon")
    iono_zenith_m: float = param(15.0, check=number(0),
                                 doc="true zenith ionospheric group delay I_g at iono_ref_hz, m")
    tropo_zenith_m: float = param(2.5, check=number(0), doc="true zenith tropospheric delay U_g, m")
    gps_glonass_offset_m: float = param(0.0, check=number(),
                                        doc="true GPS-GLONASS time offset Delta_A, m, added to GPS code and phase "
                                            "(0 disables it)")
    cycle_slip_rate_hz: float = param(0.0, check=number(0),
                                      doc="rate of random cycle slips per tracked satellite, 1/s")
    slip_cycles_max: int = param(5, check=integer(1), doc="largest |Delta N| of a random slip, cycles")
    ambiguity_max_cycles: int = param(1_000_000, check=integer(0),
                                      doc="new ambiguities are uniform integers in [-M, M], cycles")
    iono_ref_hz: float = param(F_GPS_L1_HZ, check=number(0, lo_open=True),
                               doc="reference frequency of iono_zenith_m, Hz (GPS L1)")

    def __post_init__(self):
        validate(self)
        require(self.el_mask_rad < np.pi / 2, "el_mask_rad", f"expected {_EL_MASK}, got {self.el_mask_rad!r}")


@dataclass(frozen=True, eq=False)
class Observation:
    """One epoch of receiver output. Arrays are (*batch, S) unless noted; NaN where not tracked.

    t_gps_s: epoch, GPS time, s (scalar).
    visible: bool, el >= mask (= tracked).
    pseudorange_m, pseudorange_rate_m_s, carrier_phase_m, carrier_phase_cycles:
        the measurements (phase in cycles = carrier_phase_m / λ).
    wavelength_m: (S,) carrier wavelength λ_j = c / f_j.
    lock_count: int, epochs since acquisition or the last slip (0 at that epoch, -1 when
        not tracked), like a RINEX loss-of-lock indicator.
    Truth, for scoring only (a real receiver does not output it):
    slip: bool, a cycle slip (net ΔN != 0) happened at this epoch.
    ambiguity_cycles: the integer N_j in the phase (float, NaN when not tracked).
    el_rad: elevation given to ``step`` (not masked).
    iono_slant_m, tropo_slant_m: I_j (at f_j) and U_j.
    """

    t_gps_s: float
    visible: np.ndarray
    pseudorange_m: np.ndarray
    pseudorange_rate_m_s: np.ndarray
    carrier_phase_m: np.ndarray
    carrier_phase_cycles: np.ndarray
    wavelength_m: np.ndarray
    lock_count: np.ndarray
    slip: np.ndarray
    ambiguity_cycles: np.ndarray
    el_rad: np.ndarray
    iono_slant_m: np.ndarray
    tropo_slant_m: np.ndarray


class Receiver:
    """Measurement generator holding only what a receiver tracks: per-satellite lock,
    integer ambiguity, lock count and accumulated slip count, each (*batch_shape, n_sats).
    """

    def __init__(self, n_sats: int, config: ReceiverConfig | None = None, batch_shape: tuple = ()):
        if int(n_sats) != n_sats or n_sats < 1:
            raise ValueError(f"n_sats must be a positive integer, got {n_sats!r}")
        self.n_sats = int(n_sats)
        self.config = ReceiverConfig() if config is None else config
        self.batch_shape = (int(batch_shape),) if np.isscalar(batch_shape) else tuple(int(b) for b in batch_shape)
        self.reset()

    @property
    def shape(self) -> tuple:
        return (*self.batch_shape, self.n_sats)

    def reset(self) -> None:
        """Lose lock on every satellite and forget the previous epoch."""
        self.locked = np.zeros(self.shape, dtype=bool)
        self.ambiguity_cycles = np.zeros(self.shape, dtype=np.int64)
        self.lock_count = np.full(self.shape, -1, dtype=np.int64)
        self.slip_count = np.zeros(self.shape, dtype=np.int64)
        self._pending_slip = np.zeros(self.shape, dtype=np.int64)
        self._t_prev_s: float | None = None

    def inject_slip(self, sat_index: int, cycles) -> None:
        """Schedule a cycle slip of ``cycles`` (integer, broadcast to batch_shape; 0 = none)
        on satellite ``sat_index`` at the next ``step``. It applies only if the satellite is
        tracked both before and at that epoch (a slip needs lock); otherwise it is dropped.
        """
        if int(sat_index) != sat_index or not 0 <= sat_index < self.n_sats:
            raise ValueError(f"sat_index must be an integer in [0, {self.n_sats}), got {sat_index!r}")
        c = np.asarray(cycles)
        if not np.all(np.isfinite(c)) or np.any(np.round(c) != c):
            raise ValueError(f"cycles must be integers, got {cycles!r}")
        self._pending_slip[..., int(sat_index)] += np.broadcast_to(c.astype(np.int64), self.batch_shape)

    def _full(self, name, a):
        try:
            return np.broadcast_to(np.asarray(a, dtype=float), self.shape)
        except ValueError:
            raise ValueError(f"{name} must broadcast to {self.shape}, got shape {np.shape(a)}") from None

    def step(
        self,
        rng: np.random.Generator,
        t_gps_s: float,
        range_m,
        range_rate_m_s,
        el_rad,
        carrier_hz,
        is_gps,
        clock_bias_m,
        clock_drift_m_s,
        el_atmo_rad=None,
    ) -> Observation:
        """Advance tracking to epoch t_gps_s and generate its measurements.

        range_m, range_rate_m_s, el_rad: (*batch, S) geometry (R_j, Ṙ_j, el_j); el_rad is
        the elevation above the receiver's (geodetic) horizon and sets the mask.
        el_atmo_rad: (*batch, S) elevation that the atmosphere's mapping functions use;
        default el_rad. The seed 000 thin-shell and 1/sin mappings are spherical-Earth
        models whose elevation is the geocentric one (seed 000, eq. 10), so world.observe
        passes that; using the geodetic elevation there puts up to ~0.3 m of slant-delay
        error at 55 deg latitude and low elevation into the truth.
        carrier_hz, is_gps: (S,) carrier f_j and system of each satellite.
        clock_bias_m, clock_drift_m_s: (*batch,) receiver clock Δ, Δ̇ against GLONASS time.
        """
        cfg = self.config
        t = float(t_gps_s)
        if self._t_prev_s is not None and not t > self._t_prev_s:
            raise ValueError(f"t_gps_s must increase, got {t!r} after {self._t_prev_s!r}")
        T = None if self._t_prev_s is None else t - self._t_prev_s

        range_m = self._full("range_m", range_m)
        range_rate_m_s = self._full("range_rate_m_s", range_rate_m_s)
        el_rad = self._full("el_rad", el_rad)
        el_atmo = el_rad if el_atmo_rad is None else self._full("el_atmo_rad", el_atmo_rad)
        carrier_hz = np.asarray(carrier_hz, dtype=float)
        is_gps = np.asarray(is_gps)
        if is_gps.dtype != bool:
            # e.g. the constellation's 'G'/'R' codes would all read as True
            raise ValueError(f"is_gps must be a boolean array, got dtype {is_gps.dtype}")
        if carrier_hz.shape != (self.n_sats,) or is_gps.shape != (self.n_sats,):
            raise ValueError(f"carrier_hz and is_gps must have shape ({self.n_sats},), "
                             f"got {carrier_hz.shape} and {is_gps.shape}")
        if np.any(~(carrier_hz > 0.0)):
            raise ValueError(f"carrier_hz must be > 0, got {carrier_hz!r}")
        bias = np.broadcast_to(np.asarray(clock_bias_m, dtype=float), self.batch_shape)[..., None]
        drift = np.broadcast_to(np.asarray(clock_drift_m_s, dtype=float), self.batch_shape)[..., None]

        p_slip = 0.0 if T is None else cfg.cycle_slip_rate_hz * T
        if p_slip > 1.0:
            raise ValueError(f"cycle_slip_rate_hz * T = {p_slip!r} > 1; reduce the rate or the step")

        # Noise first, always for every satellite, so the noise stream does not depend on
        # visibility or on the slip settings.
        shape = self.shape
        e_pr = cfg.sigma_pr_m * rng.standard_normal(shape)
        e_prr = cfg.sigma_prr_m_s * rng.standard_normal(shape)
        e_phase = cfg.sigma_phase_m * rng.standard_normal(shape)
        fresh = rng.integers(-cfg.ambiguity_max_cycles, cfg.ambiguity_max_cycles, size=shape, endpoint=True)

        visible = el_rad >= cfg.el_mask_rad  # NaN elevation -> not visible
        acquired = visible & ~self.locked
        kept = visible & self.locked

        slip_cycles = self._pending_slip.copy()
        if p_slip > 0.0:
            occurs = rng.random(shape) < p_slip
            size = rng.integers(1, cfg.slip_cycles_max, size=shape, endpoint=True)
            sign = np.where(rng.random(shape) < 0.5, -1, 1)
            slip_cycles += np.where(occurs, sign * size, 0)
        slip_cycles = np.where(kept, slip_cycles, 0)
        slip = slip_cycles != 0
        self._pending_slip[...] = 0

        amb = np.where(acquired, fresh, self.ambiguity_cycles) + slip_cycles
        self.ambiguity_cycles = np.where(visible, amb, 0)
        self.lock_count = np.where(visible, np.where(acquired | slip, 0, self.lock_count + 1), -1)
        self.slip_count = self.slip_count + slip
        self.locked = visible
        self._t_prev_s = t

        wavelength_m = C_M_S / carrier_hz
        with np.errstate(divide="ignore", invalid="ignore"):
            iono = iono_slant_delay_m(cfg.iono_zenith_m, el_atmo, carrier_hz, cfg.iono_ref_hz)  # seed 000, eq. (9)
            tropo = tropo_slant_delay_m(cfg.tropo_zenith_m, el_atmo)  # seed 000, eq. (11)
        iono = np.where(visible, iono, np.nan)
        tropo = np.where(visible, tropo, np.nan)
        offset = np.where(is_gps, cfg.gps_glonass_offset_m, 0.0)
        common = range_m + bias + offset + tropo
        pr = common + iono + e_pr  # seed 000, eqs. (18)/(19)
        prr = range_rate_m_s + drift + e_prr  # seed 000, eqs. (20)-(22)
        phase = common - iono + wavelength_m * self.ambiguity_cycles + e_phase  # seed 000, eq. (35)
        nan = np.nan
        phase = np.where(visible, phase, nan)
        return Observation(
            t_gps_s=t,
            visible=visible,
            pseudorange_m=np.where(visible, pr, nan),
            pseudorange_rate_m_s=np.where(visible, prr, nan),
            carrier_phase_m=phase,
            carrier_phase_cycles=phase / wavelength_m,
            wavelength_m=wavelength_m,
            lock_count=self.lock_count.copy(),
            slip=slip,
            ambiguity_cycles=np.where(visible, self.ambiguity_cycles.astype(float), nan),
            el_rad=np.array(el_rad),
            iono_slant_m=iono,
            tropo_slant_m=tropo,
        )
