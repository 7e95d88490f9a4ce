"""Cycle-slip detection for a single-frequency (L1) receiver, batched over (..., S).

Seed 000, variant 2 uses code-minus-carrier increments over a 90 s window and may only use
satellites whose carrier phase had no cycle slip over that window. This module provides an
epoch-by-epoch detector with explicit state (no hidden globals) and a window query.

Test used: Doppler-aided phase prediction
-----------------------------------------
Measurements (sitl.gnss.receiver, eqs. 20-22, 35), phase in metres with the sign of the range:

    Ḋ_k = Ṙ(t_k) + Δ̇(t_k) + ε_k                      ε_k ~ N(0, σ_Ḋ²), white per epoch
    G_k = R(t_k) + Δ(t_k) + U_k − I_k + λ N_k + e_k    e_k ~ N(0, σ_G²),  white per epoch

The phase change over T = t_k − t_{k−1} is predicted by integrating the pseudorange rate
with the trapezoidal rule, and the residual is

    r_k = (G_k − G_{k−1}) − T (Ḋ_{k−1} + Ḋ_k) / 2 − m_k
        = λ ΔN_k + (e_k − e_{k−1}) − (T/2)(ε_{k−1} + ε_k) + δ_k

where m_k is an optional caller-supplied expected mean (e.g. a-priori troposphere /
ionosphere change) and δ_k the unmodelled part: the trapezoidal-rule error −T³ R⃛/12
(range jerk), the troposphere rate (not in the Doppler: U_g cos(el)/sin²(el)·ėl, ≈ 0.047 m/s
at 5° elevation for a GNSS satellite's ėl ≈ 1.45e-4 rad/s), the ionosphere divergence
(−İ, ≲ 0.004 m/s at 5° for I_g = 15 m) and the clock-drift random walk (error variance
c² N_ε T³/12, σ ≈ 0.24 mm at T = 0.1 s). δ_k is bounded by a rate σ_model (m/s) times T.

Residual standard deviation (noise terms independent):

    σ_r(T)² = 2 σ_G² + (T²/2) σ_Ḋ² + (σ_model T)²

With the seed values σ_Ḋ = 0.064 m/s, σ_G = 0.003 m, T = 0.1 s, σ_model = 0.05 m/s:
Doppler term T σ_Ḋ / √2 = 4.53 mm, phase term √2 σ_G = 4.24 mm, model term 5.0 mm,
σ_r = 8.0 mm. A slip is flagged when |r_k| > k σ_r with k = Φ⁻¹(1 − P_fa/2), the two-sided
Gaussian quantile of the per satellite-epoch false-alarm probability P_fa (default 1e-6 →
k = 4.89, threshold 39 mm). The threshold follows from the noise model only.

Detectability: a one-cycle slip shifts r_k by λ ≈ 0.187–0.190 m (GPS L1 / GLONASS L1)
≈ 23 σ_r; it is missed only if the noise exceeds λ − kσ_r ≈ 0.15 m ≈ 18.6 σ_r (σ_r here
already includes the model allowance; the pure-noise σ is 6.2 mm, so it is ~24 pure-noise σ):
the miss probability is negligible (< 1e-70). A slip affects only the residual of the epoch
at which it occurs (the next difference G_{k+1} − G_k no longer contains it), so the detector
needs no repair step. Slips of consecutive epochs are each seen on their own epoch.

Code-minus-carrier (CMC) test, considered and not used: pr − phase = 2I − λN + ε_D − e,
and its epoch-to-epoch jump has σ = √2 σ_D = 8.5 m for σ_D = 6 m, i.e. only slips of
≳ 5·8.5/0.19 ≈ 220 cycles would be detectable; every such slip is also caught by the
Doppler test. (Averaging CMC over many epochs is what variant 2 does *after* the window is
known to be slip-free, not a slip detector.)

Tracking / reset rules (no flag is ever raised by a reset):
* a satellite is *tested* at epoch k iff phase and pseudorange rate are finite at k and
  k−1, it was not reset at k, and T <= max_dt_s;
* NaN (untracked) at k → its state is cleared (slip_free_since = NaN);
* finite at k but not tested (newly (re)acquired, NaN at k−1, lock_count == 0, or a gap
  T > max_dt_s) → reset: slip_free_since = t_k;
* a flagged slip → slip_free_since = t_k (the carrier arc restarts there).

``slip_free(state, window_s)`` then answers "tracked now and no slip/reset in the last
window_s seconds", e.g. window_s = 90 for variant 2.

Caveat on lock_count: ``sitl.gnss.receiver`` sets lock_count = 0 both at acquisition and at
every slip it generates (a truth-aware loss-of-lock indicator). Passing it as ``lock_count``
is correct for a real receiver's LLI, but turns generated slips into resets; to evaluate
the detector itself leave ``lock_count`` out (acquisition is then seen as NaN → finite).

Pure numpy/scipy; no I/O.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtri

from .params import number, optional, param, validate

__all__ = [
    "CycleSlipConfig",
    "CycleSlipState",
    "CycleSlipResult",
    "init_state",
    "step",
    "slip_free",
    "CycleSlipDetector",
]


@dataclass(frozen=True)
class CycleSlipConfig:
    """Noise model and decision rule of the Doppler-aided cycle-slip test.

    sigma_prr_m_s: pseudorange-rate (Doppler) noise σ_Ḋ, m/s, white per epoch.
    sigma_phase_m: carrier-phase noise σ_G, m, white per epoch.
    sigma_model_m_s: bound (1σ) on the unmodelled rate of phase minus integrated Doppler
        (troposphere rate at low elevation, trapezoid error from range jerk, ionosphere
        divergence, clock random walk), m/s; contributes σ_model·T to σ_r.
    pfa: per satellite-epoch false-alarm probability under Gaussian noise, in (0, 1); sets
        the threshold k = Φ⁻¹(1 − pfa/2) in units of σ_r.
    threshold_sigma: explicit k overriding pfa (None = derive from pfa).
    max_dt_s: epochs further apart than this are not tested (the arc is reset instead).
    """

    sigma_prr_m_s: float = param(0.064, check=number(0, numpy=True),
                                 doc="pseudorange-rate (Doppler) noise sigma_D (1 sigma, white per epoch), m/s")
    sigma_phase_m: float = param(0.003, check=number(0, numpy=True),
                                 doc="carrier-phase noise sigma_G (1 sigma, white per epoch), m")
    sigma_model_m_s: float = param(0.05, check=number(0, numpy=True),
                                   doc="bound (1 sigma) on the unmodelled rate of phase minus integrated Doppler "
                                       "(adds sigma_model T to sigma_r), m/s")
    pfa: float = param(1e-6, check=number(0, lo_open=True, hi=1, hi_open=True, numpy=True),
                       doc="per satellite-epoch false-alarm probability under Gaussian noise; sets "
                           "k = Phi^-1(1 - pfa/2)")
    threshold_sigma: float | None = param(None, check=optional(number(0, lo_open=True, numpy=True)),
                                          doc="explicit decision threshold k in units of sigma_r, overriding pfa "
                                              "(None: derived from pfa)")
    max_dt_s: float = param(1.0, check=number(0, lo_open=True, numpy=True),
                            doc="epochs further apart than this are not tested (the arc is reset instead), s")

    def __post_init__(self):
        validate(self)

    @property
    def k_sigma(self) -> float:
        """Decision threshold in units of σ_r: threshold_sigma or Φ⁻¹(1 − pfa/2)."""
        if self.threshold_sigma is not None:
            return float(self.threshold_sigma)
        return float(-ndtri(self.pfa / 2.0))

    def residual_sigma_m(self, dt_s: float) -> float:
        """σ_r(T) = sqrt(2 σ_G² + T² σ_Ḋ² / 2 + (σ_model T)²), metres."""
        T = float(dt_s)
        return float(np.sqrt(2.0 * self.sigma_phase_m**2 + 0.5 * (T * self.sigma_prr_m_s) ** 2
                             + (self.sigma_model_m_s * T) ** 2))


@dataclass(frozen=True, eq=False)
class CycleSlipState:
    """Detector state, arrays (*batch, S).

    t_s: time of the last processed epoch (NaN before the first), scalar.
    phase_m, prr_m_s: previous epoch's carrier phase (m) and pseudorange rate (m/s); NaN
        where not tracked.
    slip_free_since_s: start time of the current continuous, slip-free carrier arc (time of
        the last acquisition/reset/detected slip); NaN where not tracked.
    """

    t_s: float
    phase_m: np.ndarray
    prr_m_s: np.ndarray
    slip_free_since_s: np.ndarray

    @property
    def shape(self) -> tuple:
        return self.phase_m.shape


@dataclass(frozen=True, eq=False)
class CycleSlipResult:
    """Output of one ``step``, arrays (*batch, S).

    slip: bool, a cycle slip was detected at this epoch.
    tested: bool, the test was evaluated (tracked at both epochs, no reset).
    reset: bool, the arc was (re)started without a test (acquisition, lock_count == 0, gap).
    residual_m: r_k (NaN where not tested).
    statistic: r_k / σ_r (NaN where not tested).
    sigma_m: σ_r(T) used (scalar; NaN at the first epoch).
    threshold_m: k σ_r (scalar; NaN at the first epoch).
    """

    slip: np.ndarray
    tested: np.ndarray
    reset: np.ndarray
    residual_m: np.ndarray
    statistic: np.ndarray
    sigma_m: float
    threshold_m: float


def _shape_arg(name, shape) -> tuple:
    try:
        shp = tuple(int(s) for s in ((shape,) if np.isscalar(shape) else shape))
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a shape tuple, got {shape!r}") from None
    if len(shp) < 1 or any(s < 1 for s in shp):
        raise ValueError(f"{name} must be a non-empty shape of positive sizes (..., S), got {shape!r}")
    return shp


def init_state(shape) -> CycleSlipState:
    """Empty state for arrays of ``shape`` = (*batch, S): nothing tracked yet."""
    shp = _shape_arg("shape", shape)
    nan = np.full(shp, np.nan)
    return CycleSlipState(t_s=np.nan, phase_m=nan.copy(), prr_m_s=nan.copy(), slip_free_since_s=nan.copy())


def _array(name, value, shape) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a numeric array, got {type(value).__name__}") from None
    if a.shape != shape:
        try:
            a = np.broadcast_to(a, shape)
        except ValueError:
            raise ValueError(f"{name} must broadcast to {shape}, got shape {a.shape}") from None
    if np.any(np.isinf(a)):
        raise ValueError(f"{name} must be finite or NaN (untracked), got inf")
    return a


def step(config: CycleSlipConfig, state: CycleSlipState, t_s, phase_m, prr_m_s,
         lock_count=None, expected_m=None) -> tuple[CycleSlipState, CycleSlipResult]:
    """Process one epoch; returns (new_state, result). Pure: ``state`` is not modified.

    t_s: epoch time, s (scalar, strictly increasing).
    phase_m: (*batch, S) carrier phase in metres, sign of the range (G in the receiver
        model); NaN where not tracked.
    prr_m_s: (*batch, S) pseudorange rate, m/s, positive when the range grows; NaN where
        not tracked.
    lock_count: optional (*batch, S) receiver lock count; 0 → (re)acquisition: reset, no
        flag; < 0 → not tracked.
    expected_m: optional (*batch, S) expected mean of the residual (e.g. a-priori change of
        troposphere minus ionosphere over the step), m; subtracted from r_k.
    """
    if not isinstance(config, CycleSlipConfig):
        raise ValueError(f"config must be a CycleSlipConfig, got {type(config).__name__}")
    if not isinstance(state, CycleSlipState):
        raise ValueError(f"state must be a CycleSlipState, got {type(state).__name__}")
    try:
        t = float(t_s)
    except (TypeError, ValueError):
        raise ValueError(f"t_s must be a scalar time in s, got {t_s!r}") from None
    if not np.isfinite(t):
        raise ValueError(f"t_s must be finite, got {t_s!r}")
    if np.isfinite(state.t_s) and not t > state.t_s:
        raise ValueError(f"t_s must increase, got {t!r} after {state.t_s!r}")
    shape = state.shape
    phase = _array("phase_m", phase_m, shape)
    prr = _array("prr_m_s", prr_m_s, shape)
    expected = None if expected_m is None else _array("expected_m", expected_m, shape)
    if expected is not None and np.any(np.isnan(expected) & np.isfinite(phase)):
        raise ValueError("expected_m must be finite where phase_m is finite")

    valid = np.isfinite(phase) & np.isfinite(prr)
    if lock_count is not None:
        lc = np.asarray(lock_count)
        if not (np.issubdtype(lc.dtype, np.integer) or
                (np.issubdtype(lc.dtype, np.floating) and np.all(np.round(lc) == lc))):
            raise ValueError(f"lock_count must be an integer array, got dtype {lc.dtype}")
        try:
            lc = np.broadcast_to(lc, shape)
        except ValueError:
            raise ValueError(f"lock_count must broadcast to {shape}, got shape {lc.shape}") from None
        valid = valid & (lc >= 0)
        reacquired = lc == 0
    else:
        reacquired = np.zeros(shape, dtype=bool)

    if np.isfinite(state.t_s):
        dt = t - state.t_s
        gap = dt > config.max_dt_s
    else:
        dt = np.nan
        gap = True
    prev_valid = np.isfinite(state.phase_m) & np.isfinite(state.prr_m_s)
    tested = valid & prev_valid & ~reacquired & (not gap)
    reset = valid & ~tested

    if gap:
        sigma = thr = np.nan
        resid = np.full(shape, np.nan)
    else:
        sigma = config.residual_sigma_m(dt)
        thr = config.k_sigma * sigma
        with np.errstate(invalid="ignore"):
            resid = (phase - state.phase_m) - 0.5 * dt * (state.prr_m_s + prr)
            if expected is not None:
                resid = resid - expected
        resid = np.where(tested, resid, np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        stat = resid / sigma if sigma > 0.0 else np.where(resid == 0.0, 0.0, np.sign(resid) * np.inf)
        slip = tested & (np.abs(resid) > thr)

    since = np.where(valid, np.where(reset | slip, t, state.slip_free_since_s), np.nan)
    new_state = CycleSlipState(
        t_s=t,
        phase_m=np.where(valid, phase, np.nan),
        prr_m_s=np.where(valid, prr, np.nan),
        slip_free_since_s=since,
    )
    return new_state, CycleSlipResult(slip=slip, tested=tested, reset=reset, residual_m=resid,
                                      statistic=np.where(tested, stat, np.nan),
                                      sigma_m=sigma, threshold_m=thr)


def slip_free(state: CycleSlipState, window_s, t_s=None) -> np.ndarray:
    """(*batch, S) bool: tracked at the last epoch and no slip/reset in the last window_s s.

    True iff t − slip_free_since >= window_s, t = t_s or the state's last epoch, i.e. the
    current carrier arc spans the whole window [t − window_s, t] (window_s = 90 s for seed
    000 variant 2). An arc started at the window's first epoch counts as slip-free (its
    first phase is the window's reference).
    """
    if not isinstance(state, CycleSlipState):
        raise ValueError(f"state must be a CycleSlipState, got {type(state).__name__}")
    try:
        w = float(window_s)
    except (TypeError, ValueError):
        raise ValueError(f"window_s must be a number of seconds, got {window_s!r}") from None
    if not (np.isfinite(w) and w >= 0.0):
        raise ValueError(f"window_s must be finite and >= 0, got {window_s!r}")
    t = state.t_s if t_s is None else float(t_s)
    if not np.isfinite(t):
        raise ValueError(f"t_s must be finite (or the state must have processed an epoch), got {t!r}")
    with np.errstate(invalid="ignore"):
        # tolerance against float accumulation of the epoch times
        return np.isfinite(state.slip_free_since_s) & (t - state.slip_free_since_s >= w - 1e-9)


class CycleSlipDetector:
    """Convenience wrapper holding a config and a state: ``update`` = ``step`` in place."""

    def __init__(self, shape, config: CycleSlipConfig | None = None):
        self.config = CycleSlipConfig() if config is None else config
        if not isinstance(self.config, CycleSlipConfig):
            raise ValueError(f"config must be a CycleSlipConfig, got {type(config).__name__}")
        self.state = init_state(shape)

    def update(self, t_s, phase_m, prr_m_s, lock_count=None, expected_m=None) -> CycleSlipResult:
        self.state, res = step(self.config, self.state, t_s, phase_m, prr_m_s, lock_count, expected_m)
        return res

    def slip_free(self, window_s, t_s=None) -> np.ndarray:
        return slip_free(self.state, window_s, t_s)
