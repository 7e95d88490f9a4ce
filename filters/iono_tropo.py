"""Seed 000 state-space model: single-frequency GPS+GLONASS receiver estimating the zenith
ionospheric and tropospheric delays (the seed 000 paper, eqs 9-38; README "The papers").

State (eq 12; eq 38 with the optional ambiguity block), n = 11 + N_amb:

    x = [x, y, z, Delta, vx, vy, vz, dDelta, Delta_A, I_g, U_g, K_1 .. K_N]

    x, y, z      receiver ECEF position, m               IDX_POS
    Delta        receiver clock offset (GLONASS time), m  IDX_CLOCK
    vx, vy, vz   receiver ECEF velocity, m/s              IDX_VEL
    dDelta       clock drift, m/s                         IDX_DRIFT
    Delta_A      GPS - GLONASS system time offset, m      IDX_GPS_GLO
    I_g          zenith iono group delay at f_ref (GPS L1), m   IDX_IONO
    U_g          zenith tropo delay, m                    IDX_TROPO
    K_j          carrier ambiguity of satellite j, m      IDX_AMB0 + j

Transition: `IonoTropoTransition` (constant velocity, two-state clock of eqs 13-15,
random walks for Delta_A, I_g, U_g, constant ambiguities). The model is linear and time
invariant with a nilpotent continuous drift matrix A (A^2 = 0), so the seed's
continuous-discrete second-order prediction x + A x T + A A x T^2/2 and Phi = I + A T are
*exact* here: they equal F x and F of this model.

Measurement: `IonoTropoGnss` (pseudoranges, pseudorange rates, optional ambiguous carrier
phases). Its mapping functions are written again here from the same equations as the
simulator's (sitl/gnss/atmosphere.py): filters/ imports no sitl, and the duplication across
the truth/estimator boundary is deliberate.

Pure numpy: no I/O, no clocks, no randomness.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .models import C_M_S, _check_dt, _check_state, _nonnegative, _positive, _readonly

__all__ = [
    "IDX_POS",
    "IDX_CLOCK",
    "IDX_VEL",
    "IDX_DRIFT",
    "IDX_GPS_GLO",
    "IDX_IONO",
    "IDX_TROPO",
    "IDX_AMB0",
    "N_BASE",
    "F_REF_HZ",
    "IONO_SHELL_HEIGHT_M",
    "EARTH_RADIUS_M",
    "CLOCK_PSD_1_S",
    "sin_elevation",
    "elevation_rad",
    "iono_mapping",
    "tropo_mapping",
    "IonoTropoTransition",
    "IonoTropoGnss",
]

# state layout (eq 12 / eq 38)
IDX_POS = slice(0, 3)
IDX_CLOCK = 3
IDX_VEL = slice(4, 7)
IDX_DRIFT = 7
IDX_GPS_GLO = 8
IDX_IONO = 9
IDX_TROPO = 10
IDX_AMB0 = 11  # K_j is x[IDX_AMB0 + j]
N_BASE = 11

F_REF_HZ = 1575.42e6  # GPS L1: the reference frequency of I_g
IONO_SHELL_HEIGHT_M = 432.5e3  # thin shell, eq 9
EARTH_RADIUS_M = 6371e3
CLOCK_PSD_1_S = 0.8e-20  # N_eps of eqs 13-15 (Rakon RTXS5032A TCXO)


# --------------------------------------------------------------------------------------
# geometry and mapping functions (same equations as sitl/gnss/atmosphere.py)


def sin_elevation(rx_pos_ecef_m, sat_pos_ecef_m):
    """Geocentric sine of elevation, eq 10: sin eta = (X_j - X) . X / (|X| |X_j - X|).

    rx (..., 3), sat (..., 3) broadcasting; returns (...).
    """
    X = np.asarray(rx_pos_ecef_m, dtype=float)
    d = np.asarray(sat_pos_ecef_m, dtype=float) - X
    rho = np.sqrt(np.sum(d * d, axis=-1))
    r = np.sqrt(np.sum(X * X, axis=-1))
    return np.sum(d * X, axis=-1) / (rho * r)


def elevation_rad(rx_pos_ecef_m, sat_pos_ecef_m):
    """Geocentric elevation (eq 10), radians."""
    return np.arcsin(np.clip(sin_elevation(rx_pos_ecef_m, sat_pos_ecef_m), -1.0, 1.0))


def iono_mapping(el_rad, h_shell_m: float = IONO_SHELL_HEIGHT_M, r_earth_m: float = EARTH_RADIUS_M):
    """Thin-shell obliquity m_I(eta) = 1 / sqrt(1 - (R_E cos eta / (R_E + h))^2) (eq 9)."""
    el = np.asarray(el_rad, dtype=float)
    s = r_earth_m * np.cos(el) / (r_earth_m + h_shell_m)
    return 1.0 / np.sqrt(1.0 - s * s)


def tropo_mapping(el_rad):
    """m_U(eta) = 1 / sin eta (eq 11)."""
    return 1.0 / np.sin(np.asarray(el_rad, dtype=float))


def _mappings_of_sin(s, a2):
    """m_I, dm_I/ds, m_U, dm_U/ds as functions of s = sin eta (cos^2 eta = 1 - s^2).

    m_I = (1 - a^2 (1 - s^2))^-1/2,  dm_I/ds = -a^2 s m_I^3,  a = R_E / (R_E + h);
    m_U = 1/s,                       dm_U/ds = -1/s^2.
    """
    mI = 1.0 / np.sqrt(1.0 - a2 * (1.0 - s * s))
    dmI = -a2 * s * mI**3
    mU = 1.0 / s
    dmU = -mU * mU
    return mI, dmI, mU, dmU


# --------------------------------------------------------------------------------------
# transition


@dataclass(frozen=True)
class IonoTropoTransition:
    """Seed 000 transition, state as in the module docstring, n = 11 + n_amb.

    position/velocity, per axis [p, v]: F = [[1, T], [0, 1]],
        Q = q_accel [[T^3/3, T^2/2], [T^2/2, T]]          (white acceleration, m^2/s^3)
    clock [Delta, dDelta] (eqs 13-15): F = [[1, T], [0, 1]],
        Q = c^2 N_eps [[T^3/3, T^2/2], [T^2/2, T]]        (N_eps two-sided PSD, 1/s)
    Delta_A, I_g, U_g: random walks, F = 1, Q = psd T     (m^2/s)
    K_j: constants, F = 1, Q = 0.

    Linear, time invariant; the seed's second-order continuous-discrete prediction is exact
    for it (A^2 = 0), so the filters may use f/F as they are.
    """

    n_amb: int = 0
    q_accel_m2_s3: float = 1.0
    clock_psd_1_s: float = CLOCK_PSD_1_S
    q_gps_glo_m2_s: float = 1e-10
    q_iono_m2_s: float = 1e-10
    q_tropo_m2_s: float = 1e-10
    c: float = C_M_S

    linear = True

    def __post_init__(self):
        n = self.n_amb
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
            raise ValueError(f"n_amb must be an integer >= 0, got {n!r}")
        object.__setattr__(self, "n_amb", int(n))
        for name in ("q_accel_m2_s3", "clock_psd_1_s", "q_gps_glo_m2_s", "q_iono_m2_s", "q_tropo_m2_s"):
            object.__setattr__(self, name, _nonnegative(name, getattr(self, name)))
        object.__setattr__(self, "c", _positive("c", self.c))

    @property
    def ndim(self) -> int:
        return N_BASE + self.n_amb

    def f(self, x, dt):
        x = _check_state(x, self.ndim)
        return x @ self.F(None, dt).T

    def F(self, x, dt):
        """Transition matrix (n, n); x is ignored (linear model)."""
        T = _check_dt(dt)
        F = np.eye(self.ndim)
        for i in range(3):
            F[i, 4 + i] = T
        F[IDX_CLOCK, IDX_DRIFT] = T
        return F

    def Q(self, dt):
        """Process noise over dt (memoised per dt: a read-only array)."""
        memo = self.__dict__.setdefault("_q_memo", {})
        key = float(dt) if isinstance(dt, (int, float, np.floating)) else None
        if key is not None and key in memo:
            return memo[key]
        out = _readonly(self._Q(dt))
        if key is not None and len(memo) < 8:
            memo[key] = out
        return out

    def _Q(self, dt):
        T = _check_dt(dt)
        Q = np.zeros((self.ndim, self.ndim))
        blk = np.array([[T**3 / 3, T**2 / 2], [T**2 / 2, T]])
        for i in range(3):
            Q[np.ix_([i, 4 + i], [i, 4 + i])] = self.q_accel_m2_s3 * blk
        Q[np.ix_([IDX_CLOCK, IDX_DRIFT], [IDX_CLOCK, IDX_DRIFT])] = self.c**2 * self.clock_psd_1_s * blk
        Q[IDX_GPS_GLO, IDX_GPS_GLO] = self.q_gps_glo_m2_s * T
        Q[IDX_IONO, IDX_IONO] = self.q_iono_m2_s * T
        Q[IDX_TROPO, IDX_TROPO] = self.q_tropo_m2_s * T
        return Q

    def A(self):
        """Continuous drift matrix dx/dt = A x (nilpotent: A @ A = 0)."""
        return self.F(None, 1.0) - np.eye(self.ndim)


# --------------------------------------------------------------------------------------
# measurement


def _sigma(name, value, S):
    s = np.asarray(value, dtype=float)
    if s.ndim > 0 and s.shape[-1] not in (1, S):
        raise ValueError(f"{name} must be a scalar or (..., {S}), got shape {s.shape}")
    if not np.all(np.isfinite(s) & (s > 0)):
        raise ValueError(f"{name} must be finite and > 0, got {value!r}")
    return _readonly(s) if s.ndim else float(s)


@dataclass(frozen=True, eq=False)
class IonoTropoGnss:
    """Seed 000 measurements to S tracked satellites (eqs 18-25, 35-37).

    z = [pr_1..pr_S, prr_1..prr_S, (phase_j for the S' satellites with a K state, if use_phase)]

        pr_j    = R_j + Delta + g_j Delta_A + U_g m_U(eta_j) + I_g k_j m_I(eta_j)
        prr_j   = u_j . (v_j - v) + dDelta         (positive when the range grows)
        phase_j = R_j + Delta + g_j Delta_A + K_j + U_g m_U(eta_j) - I_g k_j m_I(eta_j)

    R_j = |X_j - X|, u_j = (X_j - X)/R_j, g_j = 1 for GPS else 0, k_j = (f_ref/f_j)^2 (GLONASS
    FDMA: each satellite its own carrier), eta_j the geocentric elevation of eq 10. Atmosphere
    on Doppler is neglected (seed). Satellite states are in the reception-time ECEF frame
    (light time and Earth rotation already applied by the caller).

    H includes the mapping functions' dependence on the receiver position through eta:
        d eta-term / dX = (U_g m_U' +- I_g k m_I') ds/dX,  s = sin eta,
        ds/dX = (u - s e)/|X| - (e - s u)/R_j,           e = X/|X|.

    Untracked satellites (NaN positions): not handled inside; build the model on tracked
    satellites only, or call `subset(mask)` with an (S,) boolean mask common to the batch
    (the state dimension varies per epoch anyway, so the caller picks the set).

    Arguments:
        sat_pos_ecef_m, sat_vel_ecef_m_s: (..., S, 3)
        carrier_hz: (S,) > 0;  is_gps: (S,) bool
        sigma_pr_m, sigma_prr_m_s, sigma_phase_m: scalar, (S,) or (..., S)
        phase_state_index: (S,) int, the index *in x* (>= 11) of K_j, or -1 for none
        use_phase: append phase rows (needs sigma_phase_m and phase_state_index)
        n_state: state dimension; default 11, or max(phase_state_index) + 1
    x may carry more leading axes than the satellites (UKF sigma points (K, N, n) against
    satellites (N, S, 3)); batch shapes broadcast.
    """

    sat_pos_ecef_m: np.ndarray
    sat_vel_ecef_m_s: np.ndarray
    carrier_hz: np.ndarray
    is_gps: np.ndarray
    sigma_pr_m: Any
    sigma_prr_m_s: Any
    sigma_phase_m: Any = None
    phase_state_index: Any = None
    use_phase: bool = False
    n_state: int | None = None
    f_ref_hz: float = F_REF_HZ
    h_shell_m: float = IONO_SHELL_HEIGHT_M
    r_earth_m: float = EARTH_RADIUS_M

    def __post_init__(self):
        sp = np.asarray(self.sat_pos_ecef_m, dtype=float)
        sv = np.asarray(self.sat_vel_ecef_m_s, dtype=float)
        if sp.ndim < 2 or sp.shape[-1] != 3 or sp.shape[-2] < 1:
            raise ValueError(f"sat_pos_ecef_m must have shape (..., S, 3), got shape {sp.shape}")
        S = sp.shape[-2]
        if sv.ndim < 2 or sv.shape[-2:] != (S, 3):
            raise ValueError(f"sat_vel_ecef_m_s must have shape (..., {S}, 3), got shape {sv.shape}")
        fc = np.asarray(self.carrier_hz, dtype=float)
        if fc.shape != (S,) or not np.all(np.isfinite(fc) & (fc > 0)):
            raise ValueError(f"carrier_hz must be (S,) = ({S},) finite and > 0, got {self.carrier_hz!r}")
        g = np.asarray(self.is_gps)
        if g.shape != (S,) or g.dtype != np.bool_:
            raise ValueError(f"is_gps must be a ({S},) bool array, got {self.is_gps!r}")
        for name in ("f_ref_hz", "h_shell_m", "r_earth_m"):
            object.__setattr__(self, name, _positive(name, getattr(self, name)))
        object.__setattr__(self, "sigma_pr_m", _sigma("sigma_pr_m", self.sigma_pr_m, S))
        object.__setattr__(self, "sigma_prr_m_s", _sigma("sigma_prr_m_s", self.sigma_prr_m_s, S))
        if not isinstance(self.use_phase, (bool, np.bool_)):
            raise ValueError(f"use_phase must be a bool, got {self.use_phase!r}")

        if self.phase_state_index is None:
            kidx = np.full(S, -1, dtype=np.intp)
        else:
            k = np.asarray(self.phase_state_index)
            if k.shape != (S,) or not np.issubdtype(k.dtype, np.integer):
                raise ValueError(f"phase_state_index must be a ({S},) int array, got {self.phase_state_index!r}")
            kidx = k.astype(np.intp)
            used = kidx[kidx >= 0]
            if np.any((kidx < 0) & (kidx != -1)) or np.any(used < N_BASE) or len(set(used.tolist())) != used.size:
                raise ValueError(
                    f"phase_state_index must hold distinct state indices >= {N_BASE} or -1, got {self.phase_state_index!r}"
                )
        n_min = N_BASE if not np.any(kidx >= 0) else int(kidx.max()) + 1
        if self.n_state is None:
            n = n_min
        else:
            n = self.n_state
            if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < n_min:
                raise ValueError(f"n_state must be an integer >= {n_min}, got {self.n_state!r}")
            n = int(n)
        object.__setattr__(self, "n_state", n)

        if self.use_phase:
            if self.sigma_phase_m is None:
                raise ValueError("sigma_phase_m must be given when use_phase=True, got None")
            if self.phase_state_index is None or not np.any(kidx >= 0):
                raise ValueError(
                    f"phase_state_index must give at least one K state when use_phase=True, got {self.phase_state_index!r}"
                )
        if self.sigma_phase_m is not None:
            object.__setattr__(self, "sigma_phase_m", _sigma("sigma_phase_m", self.sigma_phase_m, S))

        object.__setattr__(self, "sat_pos_ecef_m", _readonly(sp))
        object.__setattr__(self, "sat_vel_ecef_m_s", _readonly(sv))
        object.__setattr__(self, "carrier_hz", _readonly(fc))
        object.__setattr__(self, "is_gps", _readonly(g))
        object.__setattr__(self, "phase_state_index", _readonly(kidx))
        object.__setattr__(self, "use_phase", bool(self.use_phase))
        # derived per-satellite constants
        object.__setattr__(self, "_k_iono", _readonly((self.f_ref_hz / fc) ** 2))
        object.__setattr__(self, "_gps", _readonly(g.astype(float)))
        ph = np.flatnonzero(kidx >= 0) if self.use_phase else np.zeros(0, dtype=np.intp)
        object.__setattr__(self, "_phase_sats", _readonly(ph))
        a = self.r_earth_m / (self.r_earth_m + self.h_shell_m)
        object.__setattr__(self, "_a2", a * a)

    # ---------------------------------------------------------------- sizes

    @property
    def n_sats(self) -> int:
        return self.sat_pos_ecef_m.shape[-2]

    @property
    def n_phase(self) -> int:
        return int(self._phase_sats.size)

    @property
    def ndim_meas(self) -> int:
        return 2 * self.n_sats + self.n_phase

    @property
    def ndim_state(self) -> int:
        return self.n_state

    @property
    def iono_factor(self) -> np.ndarray:
        """(f_ref / f_j)^2, (S,)."""
        return self._k_iono

    def subset(self, mask) -> "IonoTropoGnss":
        """The model on the satellites where mask (S,) is True (e.g. the tracked ones)."""
        S = self.n_sats
        m = np.asarray(mask)
        if m.shape != (S,) or m.dtype != np.bool_:
            raise ValueError(f"mask must be a ({S},) bool array, got {mask!r}")

        def sel(s):
            if s is None or np.ndim(s) == 0 or np.shape(s)[-1] == 1:
                return s
            return s[..., m]

        return IonoTropoGnss(
            self.sat_pos_ecef_m[..., m, :], self.sat_vel_ecef_m_s[..., m, :],
            self.carrier_hz[m], self.is_gps[m], sel(self.sigma_pr_m), sel(self.sigma_prr_m_s),
            sel(self.sigma_phase_m), self.phase_state_index[m],
            self.use_phase and bool(np.any(self.phase_state_index[m] >= 0)),
            self.n_state, self.f_ref_hz, self.h_shell_m, self.r_earth_m,
        )

    # ---------------------------------------------------------------- h, H

    def _eval(self, x, jac: bool):
        x = _check_state(x, self.n_state)
        S, P = self.n_sats, self._phase_sats
        X = x[..., 0:3]
        V = x[..., 4:7]
        d = self.sat_pos_ecef_m - X[..., None, :]  # (..., S, 3)
        rho = np.sqrt(np.sum(d * d, axis=-1))
        u = d / rho[..., None]
        r = np.sqrt(np.sum(X * X, axis=-1))[..., None]  # (..., 1)
        e = X[..., None, :] / r[..., None]  # (..., 1, 3)
        s = np.sum(u * e, axis=-1)  # sin eta (..., S)
        w = self.sat_vel_ecef_m_s - V[..., None, :]
        uw = np.sum(u * w, axis=-1)
        mI, dmI, mU, dmU = _mappings_of_sin(s, self._a2)
        Ig = x[..., IDX_IONO, None]
        Ug = x[..., IDX_TROPO, None]
        iono = Ig * self._k_iono * mI
        tropo = Ug * mU
        common = rho + x[..., IDX_CLOCK, None] + self._gps * x[..., IDX_GPS_GLO, None] + tropo
        batch = rho.shape[:-1]
        z = np.empty(batch + (self.ndim_meas,))
        z[..., :S] = common + iono
        z[..., S:2 * S] = uw + x[..., IDX_DRIFT, None]
        if P.size:
            K = x[..., self.phase_state_index[P]]
            z[..., 2 * S:] = common[..., P] - iono[..., P] + K
        if not jac:
            return z, None
        ds = (u - s[..., None] * e) / r[..., None] - (e - s[..., None] * u) / rho[..., None]
        dtropo = (Ug * dmU)[..., None] * ds  # (..., S, 3)
        diono = (Ig * self._k_iono * dmI)[..., None] * ds
        H = np.zeros(batch + (self.ndim_meas, self.n_state))
        H[..., :S, 0:3] = -u + dtropo + diono
        H[..., :S, IDX_CLOCK] = 1.0
        H[..., :S, IDX_GPS_GLO] = self._gps
        H[..., :S, IDX_TROPO] = mU
        H[..., :S, IDX_IONO] = self._k_iono * mI
        H[..., S:2 * S, 0:3] = (uw[..., None] * u - w) / rho[..., None]
        H[..., S:2 * S, 4:7] = -u
        H[..., S:2 * S, IDX_DRIFT] = 1.0
        if P.size:
            rows = 2 * S + np.arange(P.size)
            H[..., rows, 0:3] = -u[..., P, :] + dtropo[..., P, :] - diono[..., P, :]
            H[..., rows, IDX_CLOCK] = 1.0
            H[..., rows, IDX_GPS_GLO] = self._gps[P]
            H[..., rows, IDX_TROPO] = mU[..., P]
            H[..., rows, IDX_IONO] = -(self._k_iono * mI)[..., P]
            H[..., rows, self.phase_state_index[P]] = 1.0
        return z, H

    def h(self, x):
        return self._eval(x, False)[0]

    def H(self, x):
        return self._eval(x, True)[1]

    def h_and_H(self, x):
        """(h(x), H(x)) sharing one geometry evaluation."""
        return self._eval(x, True)

    def R_diag(self):
        cached = self.__dict__.get("_r_diag")
        if cached is not None:
            return cached
        S, P = self.n_sats, self._phase_sats
        parts = [np.square(self.sigma_pr_m), np.square(self.sigma_prr_m_s)]
        if P.size:
            sph = np.square(self.sigma_phase_m)
            if np.ndim(sph) and np.shape(sph)[-1] == S:
                sph = sph[..., P]
            parts.append(sph)
        sizes = [S, S, P.size]
        batch = np.broadcast_shapes(*(np.shape(p)[:-1] for p in parts))
        out = _readonly(np.concatenate(
            [np.broadcast_to(p, batch + (k,)) for p, k in zip(parts, sizes)], axis=-1
        ))
        object.__setattr__(self, "_r_diag", out)
        return out

    def R(self):
        d = self.R_diag()
        return d[..., None] * np.eye(d.shape[-1])
