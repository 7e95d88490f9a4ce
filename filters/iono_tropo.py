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

Real data (sitl.app.gnss.solve_filter): ``iono_obliquity`` / ``tropo_obliquity`` replace m_I / m_U by
fixed per-satellite values (a shape with the ionosphere's horizontal gradient, another tropo
mapping); left None, as the simulated experiment does, the arithmetic is the seed's.

Pure numpy: no I/O, no clocks, no randomness.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .models import (_COUNT, _NONNEGATIVE, _POSITIVE, _SAT_STATES, _SIGMAS, C_M_S, _check_dt, _check_state,
                     _per_satellite, _readonly)
from .params import Check, ParamError, array, integer, optional, param, require, switch, validate

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

    n_amb: int = param(0, check=integer(0, numpy=True), doc="carrier-phase ambiguity states K_j (n = 11 + n_amb)")
    q_accel_m2_s3: float = param(1.0, check=_NONNEGATIVE, doc="white-acceleration PSD of the receiver, m^2/s^3")
    clock_psd_1_s: float = param(CLOCK_PSD_1_S, check=_NONNEGATIVE,
                                 doc="two-sided PSD N_eps of the clock's forming noise (eqs 13-15), 1/s")
    q_gps_glo_m2_s: float = param(1e-10, check=_NONNEGATIVE,
                                  doc="random-walk PSD of the GPS-GLONASS offset Delta_A, m^2/s")
    q_iono_m2_s: float = param(1e-10, check=_NONNEGATIVE, doc="random-walk PSD of the zenith ionosphere I_g, m^2/s")
    q_tropo_m2_s: float = param(1e-10, check=_NONNEGATIVE,
                                doc="random-walk PSD of the zenith troposphere U_g, m^2/s")
    c: float = param(C_M_S, check=_POSITIVE, doc="speed of light (the clock states are in m and m/s), m/s")

    linear = True

    def __post_init__(self):
        validate(self)

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


def _strict_bools(v) -> np.ndarray:
    """A bool array (dtype bool already: 0/1 integers are not taken)."""
    g = np.asarray(v)
    if g.dtype != np.bool_:
        raise ParamError("", f"expected a bool array, got {v!r}")
    return _readonly(g)


def _ints(v) -> np.ndarray:
    """An integer array."""
    k = np.asarray(v)
    if not np.issubdtype(k.dtype, np.integer):
        raise ParamError("", f"expected an int array, got {v!r}")
    return k


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

    sat_pos_ecef_m: np.ndarray = param(check=_SAT_STATES,
                                       doc="satellite positions (reception-time ECEF), (..., S, 3), m")
    sat_vel_ecef_m_s: np.ndarray = param(check=_SAT_STATES,
                                         doc="satellite velocities (reception-time ECEF), (..., S, 3), m/s")
    carrier_hz: np.ndarray = param(check=array((-1,), lo=0, lo_open=True, copy=False, what="(S,) finite and > 0"),
                                   doc="each satellite's carrier frequency (GLONASS FDMA: its own), (S,), Hz")
    is_gps: np.ndarray = param(check=Check(_strict_bools), doc="GPS (True) or GLONASS (False) per satellite, (S,) bool")
    sigma_pr_m: Any = param(check=_SIGMAS, doc="pseudorange noise (1 sigma): a scalar, (S,) or (..., S), m")
    sigma_prr_m_s: Any = param(check=_SIGMAS,
                               doc="pseudorange-rate noise (1 sigma): a scalar, (S,) or (..., S), m/s")
    sigma_phase_m: Any = param(None, check=optional(_SIGMAS),
                               doc="carrier-phase noise (1 sigma): a scalar, (S,) or (..., S), m (needed with "
                                   "use_phase)")
    phase_state_index: Any = param(None, check=optional(Check(_ints)),
                                   doc="the index in x (>= 11) of each satellite's K_j, or -1 for none, (S,) int "
                                       "(None: no K state)")
    use_phase: bool = param(False, check=switch(numpy=True),
                            doc="append the phase rows (needs sigma_phase_m and phase_state_index)")
    n_state: int | None = param(None, check=optional(_COUNT),
                                doc="state dimension (None: 11, or max(phase_state_index) + 1)")
    f_ref_hz: float = param(F_REF_HZ, check=_POSITIVE, doc="reference frequency of I_g (GPS L1), Hz")
    h_shell_m: float = param(IONO_SHELL_HEIGHT_M, check=_POSITIVE, doc="height of the thin ionosphere shell (eq 9), m")
    r_earth_m: float = param(EARTH_RADIUS_M, check=_POSITIVE, doc="Earth radius of the mapping functions, m")
    iono_obliquity: Any = param(None, check=optional(_SIGMAS),
                                doc="slant-to-zenith ratio of the ionosphere per line of sight, (S,) or (..., S), "
                                    "replacing the thin-shell m_I(eta) of eq 9 (None: eq 9); given, it is held "
                                    "fixed (no position dependence in H). Real data: a shape with the "
                                    "ionosphere's horizontal gradient, e.g. broadcast Klobuchar's slant over "
                                    "its vertical")
    tropo_obliquity: Any = param(None, check=optional(_SIGMAS),
                                 doc="slant-to-zenith ratio of the troposphere per line of sight, (S,) or (..., S), "
                                     "replacing m_U = 1/sin(eta) of eq 11 on the geocentric elevation (None: eq 11); "
                                     "given, it is held fixed (no position dependence in H). Real data: 1/sin of "
                                     "the elevation above the ellipsoid's normal, which the air follows")

    def __post_init__(self):
        validate(self)
        sp, sv, fc, g = self.sat_pos_ecef_m, self.sat_vel_ecef_m_s, self.carrier_hz, self.is_gps
        S = sp.shape[-2]
        require(S >= 1, "sat_pos_ecef_m", f"expected (..., S, 3) with S >= 1, got shape {sp.shape}")
        require(sv.shape[-2:] == (S, 3), "sat_vel_ecef_m_s", f"expected shape (..., {S}, 3), got shape {sv.shape}")
        require(fc.shape == (S,), "carrier_hz", f"expected (S,) = ({S},) finite and > 0, got shape {fc.shape}")
        require(g.shape == (S,), "is_gps", f"expected a ({S},) bool array, got shape {g.shape}")
        for name in ("sigma_pr_m", "sigma_prr_m_s"):
            object.__setattr__(self, name, _per_satellite(name, getattr(self, name), S))

        if self.phase_state_index is None:
            kidx = np.full(S, -1, dtype=np.intp)
        else:
            k = self.phase_state_index
            require(k.shape == (S,), "phase_state_index", f"expected a ({S},) int array, got shape {k.shape}")
            kidx = k.astype(np.intp)
            used = kidx[kidx >= 0]
            require(not (np.any((kidx < 0) & (kidx != -1)) or np.any(used < N_BASE)
                         or len(set(used.tolist())) != used.size), "phase_state_index",
                    f"expected distinct state indices >= {N_BASE} or -1, got {k!r}")
        n_min = N_BASE if not np.any(kidx >= 0) else int(kidx.max()) + 1
        if self.n_state is None:
            object.__setattr__(self, "n_state", n_min)
        require(self.n_state >= n_min, "n_state", f"expected an integer >= {n_min}, got {self.n_state}")

        if self.use_phase:
            require(self.sigma_phase_m is not None, "sigma_phase_m", "expected a value when use_phase=True, got None")
            require(self.phase_state_index is not None and np.any(kidx >= 0), "phase_state_index",
                    f"expected at least one K state when use_phase=True, got {self.phase_state_index!r}")
        if self.sigma_phase_m is not None:
            object.__setattr__(self, "sigma_phase_m", _per_satellite("sigma_phase_m", self.sigma_phase_m, S))
        for name in ("iono_obliquity", "tropo_obliquity"):
            ob = getattr(self, name)
            require(ob is None or (ob.ndim >= 1 and ob.shape[-1] == S), name,
                    f"expected (S,) or (..., {S}), got shape {np.shape(ob)}")

        object.__setattr__(self, "phase_state_index", _readonly(kidx))
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
            None if self.iono_obliquity is None else self.iono_obliquity[..., m],
            None if self.tropo_obliquity is None else self.tropo_obliquity[..., m],
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
        if self.iono_obliquity is not None:
            mI, dmI = self.iono_obliquity, 0.0
        if self.tropo_obliquity is not None:
            mU, dmU = self.tropo_obliquity, 0.0
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
