"""The sonde's motion model: SondeTransition (x(k+1) = F x(k) + w over the tracker's state), the
exact discretisation of one axis of the relaxed sonde model (relaxed_axis_discretisation: expm and
Van Loan), the parachute's descent law and small geodetic steps. Singer's model (filters.models)
for ``kinematics="singer"`` (Moroz et al., seed 004, eq 20)."""
from __future__ import annotations

import math

import numpy as np
import scipy.linalg

from filters import kernels
from filters.models import Singer
from sitl.atmosphere_std import RHO0_KG_M3, Z_MAX_M, Z_MIN_M, us76_density
from sitl.constants import WGS84
from sitl.geodesy import ecef_to_geodetic, enu_rotation

from .params import Layout, SondeTrackerParams

__all__ = ["SHEAR_SIGMA_FLOOR_1_S", "VERTICAL_SPEED_REL_STEP", "SondeTransition", "descent_speed", "enu_rotations",
           "relaxed_axis_discretisation"]


def descent_speed(h_m, v_sl_m_s):
    """The parachute's terminal descent speed at heights h_m, v_sl sqrt(rho0 / rho(h)) with the US76
    density (the sonde model's law, vehicles.sonde.descent_speed_m_s; ground_station does not import
    vehicles)."""
    h = np.clip(np.asarray(h_m, dtype=float), Z_MIN_M, Z_MAX_M)
    return v_sl_m_s * np.sqrt(RHO0_KG_M3 / us76_density(h))


def relaxed_axis_discretisation(relax_rate_1_s: float, gust_rate_1_s: float, sigma_gust_m_s2: float,
                                sigma_shear_1_s: float, shear_corr_height_m: float, vertical_speed_m_s: float,
                                dt_s: float):
    """Exact discretisation (F, Q), 5 x 5, of one local axis of the relaxed sonde model over
    [position p, velocity v, gust acceleration g, wind u, wind shear s = du/dh], for a sonde whose
    height changes at the vertical speed w over the step:

        p' = v,  v' = k (u - v) + g,  g' = -beta g + sqrt(2 beta) sigma_g n_g,
        u' = w s,  s' = -(|w| / L) s + sqrt(2 |w| / L) sigma_s n_s

    (vehicles.sonde's axis, dv/dt = k (w(h) - v) + a_g, with the wind met by the sonde -- the mean
    wind at its height, or the target vertical speed -- unknown: a state that changes as the sonde
    crosses the profile, du/dt = (du/dh) dh/dt, the shear du/dh Gauss-Markov in height with std
    sigma_s and correlation height L). At w = 0 the wind does not change. F = expm(A dt), Q by Van
    Loan's method."""
    k, beta = float(relax_rate_1_s), float(gust_rate_1_s)
    w = float(vertical_speed_m_s)
    lam = abs(w) / float(shear_corr_height_m)
    a = np.zeros((5, 5))
    a[0, 1] = 1.0
    a[1, 1], a[1, 2], a[1, 3] = -k, 1.0, k
    a[2, 2] = -beta
    a[3, 4] = w
    a[4, 4] = -lam
    qc = np.diag([0.0, 0.0, 2.0 * beta * sigma_gust_m_s2**2, 0.0, 2.0 * lam * sigma_shear_1_s**2])
    m = np.zeros((10, 10))
    m[:5, :5], m[:5, 5:], m[5:, 5:] = -a, qc, a.T
    e = scipy.linalg.expm(m * dt_s)
    F = e[5:, 5:].T
    Q = F @ e[:5, 5:]
    return F, 0.5 * (Q + Q.T)


#: the vertical speed is rounded to this relative step (and to 0 below 1 cm/s) for the memo of the
#: per-axis discretisation (relaxed): its noise and decay scale with |w|, so a 0.5 % step is a 0.5 %
#: change of the shear's variance per step at most
VERTICAL_SPEED_REL_STEP = 0.005
#: the vertical shear's std is at least this (keeps P positive definite for the UKF's Cholesky when the
#: model has no vertical residual: over a 30 km descent it moves the target vertical speed by ~0.02 m/s)
SHEAR_SIGMA_FLOOR_1_S = 1e-6
E2 = WGS84.f * (2.0 - WGS84.f)  # the WGS-84 first eccentricity squared


def _quantised_speed(w):
    """w (N,) rounded on the relative grid VERTICAL_SPEED_REL_STEP (0 below 1 cm/s)."""
    a = np.abs(w)
    k = np.round(np.log(np.maximum(a, 0.01) / 0.01) / VERTICAL_SPEED_REL_STEP)
    return np.where(a < 0.01, 0.0, np.sign(w) * 0.01 * np.exp(k * VERTICAL_SPEED_REL_STEP))


def enu_rotations(lat, lon):
    """enu_rotation for (N,) latitudes and longitudes, (N, 3, 3), without the general broadcasting."""
    sp, cp, sl, cl = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    r = np.empty((lat.shape[0], 3, 3))
    r[:, 0, 0], r[:, 0, 1], r[:, 0, 2] = -sl, cl, 0.0
    r[:, 1, 0], r[:, 1, 1], r[:, 1, 2] = -sp * cl, -sp * sl, cp
    r[:, 2, 0], r[:, 2, 1], r[:, 2, 2] = cp * cl, cp * sl, sp
    return r


def _step_geodetic(lat, lon, h, d_enu):
    """(lat, lon, h) after a small local displacement d_enu (N, 3) from (lat, lon, h) (N,): the
    meridian and prime-vertical radii of curvature (a 50 m step: ~1e-10 rad, 0.2 mm off the exact
    transform)."""
    s2 = np.sin(lat) ** 2
    w = np.sqrt(1.0 - E2 * s2)
    Nr = WGS84.a_m / w
    Mr = WGS84.a_m * (1.0 - E2) / (w * w * w)
    return (lat + d_enu[:, 1] / (Mr + h), lon + d_enu[:, 0] / ((Nr + h) * np.cos(lat)), h + d_enu[:, 2])


def burst_variance(h, target, w, dt, burst_alt_range_m, v_sl_m_s):
    """The mean square of the target vertical speed's step at a burst over one step dt of N sondes
    (relaxed; heights h (N,), target vertical speeds (N,), vertical speeds w (N,)): the sonde model
    bursts at a height uniform in burst_alt_range_m = (lo, hi), so a sonde that has not burst by h
    bursts within the next dh with probability dh / (hi - h) (the uniform law's hazard; 1 from hi on),
    and its target then steps to the descent law's -v_d(h). Over the step the sonde moves
    dh = max(target, |w|) dt, p = (dh inside the range) / (the height left to hi) (<= 1), and the
    prediction that keeps the target has the mean square error p (target + v_d(h))^2: the burst's
    mode change in one Gaussian. It applies while the target lies above the law (the climb, or a
    track still on its way from the climb to the law after a burst, whose remaining step it
    is); 0 below the range and for a target on the law (the descent)."""
    lo, hi = burst_alt_range_m
    h, target = np.asarray(h, dtype=float), np.asarray(target, dtype=float)
    a = np.maximum(h, lo)
    climb = np.minimum(h + np.maximum(target, np.abs(w)) * dt, hi) - a
    with np.errstate(divide="ignore", invalid="ignore"):
        p = np.where(h >= hi, 1.0, np.where(climb > 0.0, climb / np.maximum(hi - a, 1e-9), 0.0))
    step = np.maximum(target + descent_speed(h, v_sl_m_s), 0.0)
    return np.clip(p, 0.0, 1.0) * step * step


def _descent_speed_slope(h_m, v_sl_m_s):
    """d v_d / dh (1/s, > 0: the descent slows as the air thickens) of descent_speed, central
    difference over +-1 m."""
    h = np.asarray(h_m, dtype=float)
    return 0.5 * (descent_speed(h + 1.0, v_sl_m_s) - descent_speed(h - 1.0, v_sl_m_s))


class SondeTransition:
    """x(k+1) = F x(k) + w: the sonde kinematics, dd random walk, oscillator and radar errors
    first-order Gauss-Markov.

    ``relaxed``: per sonde and step, in the local east-north-up frame at the sonde's estimated
    position (vehicles.sonde's frame: the wind is horizontal there, the descent is along its
    vertical), relaxed_axis_discretisation with p1 horizontally and k_v vertically at the
    estimate's vertical speed; the velocity-like states (velocity, gust, wind, shear) keep their
    local components from one step's frame to the next (the frame turns by ~|v| dt / R_E as the
    sonde moves); a descending sonde's target vertical speed follows the descent law as an input,
    with its Jacobian. Beyond a few km from the site this matters: at 300 km the site's vertical is
    2.7 deg off the sonde's (a 30 km descent along the site's vertical lands 1.4 km off, and a
    65 m/s wind "horizontal" at the site climbs 3 m/s at the sonde). ``kinematic`` gives these
    per-sonde blocks; the other states' transition is shared and diagonal (``rest``).
    ``singer``: Singer's model with rate p1 + p2 and covariance Sigma_a at the site, shared (F, Q).
    ``enu_rot``: the ENU rotation at the site (singer's split)."""

    linear = True

    def __init__(self, layout: Layout, params: SondeTrackerParams, enu_rot: np.ndarray):
        self.layout = layout
        self.ndim = layout.n
        self.params = params
        p = params
        self.enu_rot = np.array(enu_rot, dtype=float)
        self.acc_cov_ecef = self.acc_cov_at(None)
        self._unit = Singer(params.accel_rate_1_s, 1.0, ndim_pos=1)
        self._memo: dict = {}
        self._axis_memo: dict = {}
        self._shear_sigma_v = max(p.wind_shear_sigma_vertical_1_s, SHEAR_SIGMA_FLOOR_1_S)

    def _local(self, pos_ecef):
        """The ENU rotation at pos (3,) (None: the site's)."""
        if pos_ecef is None:
            return self.enu_rot
        lat, lon, _ = ecef_to_geodetic(np.asarray(pos_ecef, dtype=float))
        return enu_rotation(float(lat), float(lon))

    def acc_cov_at(self, pos_ecef) -> np.ndarray:
        """Stationary covariance of the gust (relaxed) / acceleration (singer) in ECEF, split at pos
        (relaxed; None or singer: at the site)."""
        p = self.params
        r = self.enu_rot if self.layout.wind is None else self._local(pos_ecef)
        return r.T @ np.diag([p.sigma_acc_horizontal_m_s2**2, p.sigma_acc_horizontal_m_s2**2,
                              p.sigma_acc_vertical_m_s2**2]) @ r

    def shear_cov_at(self, pos_ecef) -> np.ndarray:
        """Stationary covariance of the wind-shear states (relaxed) in ECEF, split at pos."""
        p, r = self.params, self._local(pos_ecef)
        return r.T @ np.diag([p.wind_shear_sigma_horizontal_1_s**2, p.wind_shear_sigma_horizontal_1_s**2,
                              self._shear_sigma_v**2]) @ r

    def _axes_to_ecef(self, per_axis):
        """(3, q, q) per-ENU-axis blocks [e, n, u] over q quantities -> (3q, 3q) in ECEF,
        quantity-major (index 3 i + c: quantity i, ECEF axis c)."""
        r = self.enu_rot
        q = per_axis.shape[-1]
        return np.einsum("ca,cij,cb->iajb", r, per_axis, r).reshape(3 * q, 3 * q)

    def _build(self, dt: float):
        """The shared (F, Q): singer's kinematics and every other state; relaxed: the kinematic
        block is left zero (it is per sonde: ``kinematic``)."""
        L, p = self.layout, self.params
        n = L.n
        F, Q = np.zeros((n, n)), np.zeros((n, n))
        if L.wind is None:
            F[:9, :9] = np.kron(self._unit.F(None, dt), np.eye(3))
            Q[:9, :9] = np.kron(self._unit.Q(dt), self.acc_cov_ecef)
        if L.dd is not None:
            F[L.dd, L.dd] = 1.0
            Q[L.dd, L.dd] = p.delta_d_rw_psd_m2_s * dt
            if p.relay_errors is not None:  # the relay path variation (GM) as a random walk of its PSD 2 s^2 / tau
                e = p.relay_errors
                Q[L.dd, L.dd] += 2.0 * e.path_sigma_m**2 / e.path_tau_s * dt
            e = math.exp(-p.osc_gamma_1_s * dt)
            F[L.osc, L.osc] = e
            Q[L.osc, L.osc] = p.osc_sigma_m_s**2 * -math.expm1(-2.0 * p.osc_gamma_1_s * dt)
        if L.err is not None:
            for j, (s, g) in enumerate(zip(p.radar_sigma, p.radar_gamma_1_s)):
                F[L.err + j, L.err + j] = math.exp(-g * dt)
                Q[L.err + j, L.err + j] = s * s * -math.expm1(-2.0 * g * dt)
        if L.nb:  # unit-variance Gauss-Markov per satellite slot
            tau = p.slow_tau_s
            b = np.arange(L.bias, L.bias + L.nb)
            F[b, b] = math.exp(-dt / tau)
            Q[b, b] = -math.expm1(-2.0 * dt / tau)
        Q = 0.5 * (Q + Q.T)
        F.flags.writeable = Q.flags.writeable = False
        return F, Q

    def _get(self, dt):
        key = float(dt)
        out = self._memo.get(key)
        if out is None:
            if len(self._memo) > 64:
                self._memo.clear()
            out = self._memo[key] = self._build(key)
        return out

    def rest(self, dt):
        """(f, q): the diagonal transition and noise of the states after the kinematic block (relaxed)."""
        key = ("rest", float(dt))
        out = self._memo.get(key)
        if out is None:
            F, Q = self._get(dt)
            k = self.layout.n_kin
            out = self._memo[key] = (np.diag(F)[k:].copy(), np.diag(Q)[k:].copy())
        return out

    def _axes(self, dt: float, w: float):
        """Per-axis (F, Q) 5 x 5, horizontal and vertical, at vertical speed w (memoised)."""
        key = (dt, w)
        out = self._axis_memo.get(key)
        if out is None:
            p = self.params
            if len(self._axis_memo) > 8192:
                self._axis_memo.clear()
            h = relaxed_axis_discretisation(p.velocity_relax_rate_horizontal_1_s, p.accel_rate_1_s,
                                            p.sigma_acc_horizontal_m_s2, p.wind_shear_sigma_horizontal_1_s,
                                            p.wind_shear_corr_height_m, w, dt)
            v = relaxed_axis_discretisation(p.velocity_relax_rate_vertical_1_s, p.accel_rate_1_s,
                                            p.sigma_acc_vertical_m_s2, self._shear_sigma_v,
                                            p.wind_shear_corr_height_m, w, dt)
            out = self._axis_memo[key] = (h[0], h[1], v[0], v[1])
        return out

    def kinematic(self, xk, dt: float):
        """Relaxed kinematics of N sondes over dt: xk (N, 15) = [p, v, a_g, u, s] (ECEF) ->
        (the predicted means (N, 15), F (N, 15, 15), Q (N, 15, 15)).

        In the local ENU frame R0 at each estimate: the per-axis models at its vertical speed w
        (rounded on the grid of VERTICAL_SPEED_REL_STEP); the position goes back to ECEF through R0, the
        velocity-like quantities through the frame R1 at the predicted position (they keep their
        local components), and so do the errors, the position's included (F's position block is the
        frame's turn R1' R0, not I). A descending sonde's (target vertical speed below 0) target follows the
        parachute's law, + v_d(h0) - v_d(h1) along the vertical, with its Jacobian in F (the target
        changes by -v_d'(h) per metre of descent); and F has the Jacobian of the bilinear u' = w s
        in the vertical speed (ds/dw: s dt). The mean uses the law itself (not its linearisation).
        A climbing sonde inside the burst range (burst_alt_range_m) may burst in the step: its target's
        vertical Q has the step's mean square (burst_variance; the mean keeps the climb)."""
        p = self.params
        xk = np.asarray(xk, dtype=float)
        N = xk.shape[0]
        X = xk.reshape(N, 5, 3)
        lat0, lon0, h0 = (np.atleast_1d(v) for v in ecef_to_geodetic(X[:, 0]))
        R0 = enu_rotations(lat0, lon0)
        Y = np.einsum("nca,nia->nci", R0, X)  # (N, axis, quantity): local components
        w = Y[:, 2, 1]
        wq = _quantised_speed(w)
        Phi = np.empty((N, 3, 5, 5))
        Qa = np.empty((N, 3, 5, 5))
        for val in np.unique(wq):
            sel = wq == val
            Fh, Qh, Fv, Qv = self._axes(float(dt), float(val))
            Phi[sel, 0], Phi[sel, 1], Phi[sel, 2] = Fh, Fh, Fv
            Qa[sel, 0], Qa[sel, 1], Qa[sel, 2] = Qh, Qh, Qv
        Y1 = np.einsum("ncij,ncj->nci", Phi, Y)
        p1 = np.einsum("nca,nc->na", R0, Y1[:, :, 0])
        lat1, lon1, h1 = _step_geodetic(lat0, lon0, h0, Y1[:, :, 0] - Y[:, :, 0])
        R1 = enu_rotations(lat1, lon1)
        # the local matrix, quantity-major (N, quantity, axis, quantity, axis)
        M = np.zeros((N, 5, 3, 5, 3))
        for c in range(3):
            M[:, :, c, :, c] = Phi[:, c]
        lam_dt = np.abs(wq) * (float(dt) / p.wind_shear_corr_height_m)
        M[:, 3, :, 1, 2] += Y[:, :, 4] * (float(dt) * np.exp(-lam_dt))[:, None]  # d(w s (1 - e^-lam dt)/lam)/dw
        v_sl = p.descent_rate_sl_m_s
        if v_sl is not None:
            down = np.flatnonzero(Y[:, 2, 3] < 0.0)
            if down.size:
                hd0, hd1 = h0[down], h1[down]
                Y1[down, 2, 3] += descent_speed(hd0, v_sl) - descent_speed(hd1, v_sl)
                # d(target)/d(state) = -v_d'(h1) d(h1 - h0)/d(state), h1 - h0 the local vertical displacement
                dh = Phi[down, 2, 0, :].copy()
                dh[:, 0] -= 1.0
                M[down, 3, 2, :, 2] += -_descent_speed_slope(hd1, v_sl)[:, None] * dh
        x1 = np.empty((N, 5, 3))
        x1[:, 0] = p1
        x1[:, 1:] = np.einsum("nca,nci->nia", R1, Y1[:, :, 1:])
        x1 = x1.reshape(N, 15)
        # the errors turn with the frame, the position's too: the sonde and its estimate both move on the
        # curved Earth (a rotation about its centre, R1' R0 over the step), so a horizontal position error
        # stays horizontal at the estimate (kept fixed in ECEF it would tilt up by the distance / R_E)
        R1T = np.swapaxes(R1, -1, -2)[:, None, None]
        F = (R1T @ M.transpose(0, 1, 3, 2, 4) @ R0[:, None, None]).transpose(0, 1, 3, 2, 4).reshape(N, 15, 15)
        Qf = np.zeros((N, 5, 3, 5, 3))
        for c in range(3):
            Qf[:, :, c, :, c] = Qa[:, c]
        if p.burst_alt_range_m is not None and v_sl is not None:  # a climbing sonde may burst in the step
            Qf[:, 3, 2, 3, 2] += burst_variance(h0, Y[:, 2, 3], w, float(dt), p.burst_alt_range_m, v_sl)
        Q = (R1T @ Qf.transpose(0, 1, 3, 2, 4) @ R1[:, None, None]).transpose(0, 1, 3, 2, 4).reshape(N, 15, 15)
        return x1, F, 0.5 * (Q + np.swapaxes(Q, -1, -2))

    def F(self, x, dt, landed: bool = False):
        """The transition matrix: shared (n, n) for singer or a landed sonde; relaxed in flight,
        per sonde at the states x (N, n) or (n,): (N, n, n) or (n, n)."""
        if landed:
            return self._get_landed(dt)[0]
        if self.layout.wind is None:
            return self._get(dt)[0]
        return self._full(x, dt)[1]

    def _full(self, x, dt):
        """Relaxed, in flight: (means, F, Q) over the whole state for x (N, n) or (n,)."""
        x = np.asarray(x, dtype=float)
        one = x.ndim == 1
        xx = x[None] if one else x
        k = self.layout.n_kin
        xk, Fk, Qk = self.kinematic(xx[:, :k], dt)
        f, q = self.rest(dt)
        N, n = xx.shape
        F = np.zeros((N, n, n))
        Q = np.zeros((N, n, n))
        F[:, :k, :k], Q[:, :k, :k] = Fk, Qk
        r = np.arange(k, n)
        F[:, r, r], Q[:, r, r] = f, q
        xp = np.concatenate([xk, xx[:, k:] * f], axis=1)
        return (xp[0], F[0], Q[0]) if one else (xp, F, Q)

    def _get_landed(self, dt):
        """(F, Q) of a landed sonde (relaxed): at rest -- position held, velocity, gust, wind and
        shear zero (their Q a numerical floor, 1e-8 in SI, keeping P positive definite); the
        other states as in flight."""
        key = ("landed", float(dt))
        out = self._memo.get(key)
        if out is None:
            F, Q = (a.copy() for a in self._get(dt))
            k = self.layout.n_kin
            F[:k, :] = 0.0
            F[:, :k] = 0.0
            F[0:3, 0:3] = np.eye(3)
            Q[:k, :] = 0.0
            Q[:, :k] = 0.0
            Q[3:k, 3:k] = 1e-8 * np.eye(k - 3)
            F.flags.writeable = Q.flags.writeable = False
            out = self._memo[key] = (F, Q)
        return out

    def boost(self, dt):
        """Covariance added under the manoeuvre hypothesis over a step dt: an unknown
        acceleration step a ~ N(0, s^2 I) at its start, [dp, dV, da] = [dt^2/2, dt, 1] a, and
        (relaxed kinematics) an unknown step of the wind, N(0, manoeuvre_sigma_wind^2 I)."""
        key = ("boost", float(dt))
        out = self._memo.get(key)
        if out is None:
            g = np.array([0.5 * dt * dt, dt, 1.0])
            out = np.zeros((self.ndim, self.ndim))
            out[:9, :9] = self.params.manoeuvre_sigma_acc_m_s2**2 * np.kron(np.outer(g, g), np.eye(3))
            w = self.layout.wind
            if w is not None:  # and an unknown step of the wind / target speed (the burst: +5 -> -40 m/s)
                out[w:w + 3, w:w + 3] = self.params.manoeuvre_sigma_wind_m_s**2 * np.eye(3)
            out.flags.writeable = False
            self._memo[key] = out
        return out

    def Q(self, dt, landed: bool = False, x=None):
        """The process noise: shared for singer or a landed sonde; relaxed in flight, per sonde at x."""
        if landed:
            return self._get_landed(dt)[1]
        if self.layout.wind is None:
            return self._get(dt)[1]
        if x is None:
            raise ValueError("relaxed kinematics: Q depends on the state (its vertical speed and frame); pass x")
        return self._full(x, dt)[2]

    def predict(self, x, P, dt, landed: bool = False, backend=None):
        """(x-, P-) of N sondes (x (N, n), P (N, n, n)) over dt. Relaxed in flight: the per-sonde
        kinematic block and the shared diagonal rest, block by block (the rest's F is diagonal and
        the kinematic block is not coupled to it)."""
        x = np.asarray(x, dtype=float)
        if landed or self.layout.wind is None:
            F, Q = self.F(None, dt, landed), self.Q(dt, landed)
            return x @ F.T, kernels.cov_predict(F, P, Q, backend=backend)
        k = self.layout.n_kin
        xk, Fk, Qk = self.kinematic(x[:, :k], dt)
        f, q = self.rest(dt)
        Pp = np.empty_like(P)
        FkT = np.swapaxes(Fk, -1, -2)
        Pp[:, :k, :k] = Fk @ P[:, :k, :k] @ FkT + Qk
        kr = (Fk @ P[:, :k, k:]) * f
        Pp[:, :k, k:] = kr
        Pp[:, k:, :k] = np.swapaxes(kr, -1, -2)
        Pp[:, k:, k:] = P[:, k:, k:] * (f[:, None] * f[None, :]) + np.diag(q)
        Pp = 0.5 * (Pp + np.swapaxes(Pp, -1, -2))
        return np.concatenate([xk, x[:, k:] * f], axis=1), Pp

    def f(self, x, dt):
        x = np.asarray(x, dtype=float)
        if self.layout.wind is None:
            return x @ self._get(dt)[0].T
        return self._full(x, dt)[0]
