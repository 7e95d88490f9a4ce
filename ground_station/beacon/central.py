"""The yardstick of the decomposition (seed 002): one centralised filter on the beacon and every
UAV, and the PCRB.

The seed requires the decomposition (each UAV navigates on board; the ground computer
locates the beacon from their estimates: ``ground_station.beacon.locator``).  This module is
what the decomposition gives up, measured on the same data:

``CentralFilter``: one EKF whose state holds the beacon (in the locator's formation-
cylindrical coordinates, for the reason given there: the ECEF EKF spuriously gains
information along the circle about the UAVs' line) and every UAV's [U_i, V_i] (ECEF), fed
the raw GNSS pseudoranges / Dopplers of every UAV and the beacon links.  The UAVs' errors
are then states, correlated in time as they really are, instead of the locator's
consider term.  UAV blocks: the onboard model (constant velocity, PSD ``q_uav_m2_s3``);
beacon block: the locator's model.  The GNSS measurement models are passed in (objects with
``h_and_H(x (T, 6))`` and ``R_diag()``, e.g. ``vehicles.uav_nav.nav_measurement_model``'s)
so that ground_station does not import vehicles.  Every R is diagonal (the UAVs' positions
are states, nothing is inflated): the update is the scalar sequential Joseph update,
batched over trials.  No gating: it is the yardstick on clean data.  It is not a bus
component -- the schema carries no raw UAV GNSS (only SondeRelay for sondes), and the
decomposition is the point of the bus design.

Initialisation: it starts at the epoch where the locator initialised, from the same beacon
prior (the side the locator kept) and, for the UAV blocks, the onboard filters' estimates
at that epoch -- which equal what the central filter's own UAV blocks would be: before the
beacon is included the blocks are uncoupled and each is exactly the onboard EKF (same
model, same data, same start).

``pcrb_central``: the posterior Cramer-Rao bound (Tichavsky, Muravchik & Nehorai 1998) for
the centralised model at the TRUE states, so that it includes the UAVs' navigation
uncertainty (the decomposed model with the inflated R is not a bound: it treats the UAV
errors as white and forgets their correlation -- it can be optimistic or pessimistic).
Linear transition (constant velocity, ECEF, for beacon and UAVs), additive Gaussian noise,
so the TMN recursion is the information filter at the true states (``filters.metrics.pcrb``'s
docstring):

    B(k|k-1) = F B(k-1) F' + Q,   B(k) = (B(k|k-1)^-1 + sum_j H_j' R_j^-1 H_j)^-1

with H_j the GNSS Jacobians of each UAV (clock-free pseudoranges and Dopplers) and the
beacon-link Jacobians over [B, V_B, U_i, V_i], all at the true states.  Written here rather
than calling filters.metrics.pcrb because R is diagonal and H sparse: the information is
assembled per block (the generic routine forms a Cholesky of the full m x m R at every step,
m = 30 UAVs x 62 GNSS channels + 60, which does not fit the time budget); a test checks the
two agree on a small case.  The bound is for the filters' model (a beacon with white
acceleration); the truth's deterministic sinusoids are one sample path of it.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from filters import kernels
from filters.beacon import ObserverRangeDoppler
from filters.iekf import iterated_update, relinearized_innovation

from .config import LocatorConfig
from .frame import Frame, cyl_to_ecef, ecef_to_cyl, formation_frame, ut_to_ecef
from .measurements import second_order_var
from .motion import cv_matrices

__all__ = ["CentralFilter", "LinkEpoch", "pcrb_central", "link_information"]


class LinkEpoch(NamedTuple):
    """Beacon-link measurements of one epoch: range_m, range_rate_m_s (T, N); var_range_m2,
    var_range_rate_m2_s2 (T, N) or scalars; mask (T, N) bool (None: all present)."""

    range_m: np.ndarray
    range_rate_m_s: np.ndarray
    var_range_m2: object
    var_range_rate_m2_s2: object
    mask: np.ndarray | None = None


class CentralFilter:
    """State per trial: [y_B (6) cylindrical beacon, U_1, V_1, ..., U_N, V_N] (6 + 6N).

    ``start(t, y_B, P_B, frame, uav_x (T, N, 6), uav_P (T, N, 6, 6))``, then
    ``step(t, gnss, link)`` with gnss a list of N (model, z) pairs (model over (T, 6) UAV
    states) and link a :class:`LinkEpoch`.  ``beacon_ecef()`` gives the beacon's ECEF
    moments (unscented, as the locator publishes them).
    """

    def __init__(self, n_uavs: int, config: LocatorConfig = LocatorConfig(), q_uav_m2_s3: float = 0.02,
                 backend=None):
        if int(n_uavs) < 1:
            raise ValueError(f"n_uavs must be >= 1, got {n_uavs!r}")
        self.N = int(n_uavs)
        self.n = 6 + 6 * self.N
        self.config = config
        self.q_uav = float(q_uav_m2_s3)
        self.backend = backend
        self.t_gps_s = None
        self.y = self.P = self.frame = None

    def start(self, t_gps_s, y_b, P_b, frame: Frame, uav_x, uav_P):
        T = y_b.shape[0]
        N, n = self.N, self.n
        if uav_x.shape != (T, N, 6) or uav_P.shape != (T, N, 6, 6):
            raise ValueError(f"uav_x / uav_P must be (T, {N}, 6) / (T, {N}, 6, 6), got {uav_x.shape}, {uav_P.shape}")
        self.y = np.concatenate([y_b, uav_x.reshape(T, 6 * N)], axis=-1)
        self.P = np.zeros((T, n, n))
        self.P[:, 0:6, 0:6] = P_b
        for i in range(N):
            self.P[:, 6 + 6 * i:12 + 6 * i, 6 + 6 * i:12 + 6 * i] = uav_P[:, i]
        self.frame = Frame(*(np.array(v) for v in frame))
        self.t_gps_s = float(t_gps_s)
        return self

    def uav_states(self):
        T = self.y.shape[0]
        return self.y[:, 6:].reshape(T, self.N, 6)

    def _predict(self, dt):
        c = self.config
        T, N, n = self.y.shape[0], self.N, self.n
        x, G = cyl_to_ecef(self.y[:, 0:6], self.frame, jacobian=True)
        F6, Qb = cv_matrices(float(c.q_m2_s3), float(dt))
        _, Qu = cv_matrices(self.q_uav, float(dt))
        xp = x @ F6.T
        U = self.uav_states() @ F6.T
        mask = np.ones((T, N), bool)
        fr = formation_frame(U[..., 0:3], mask, xp[:, 0:3], self.frame, c.axis_ratio)
        yb, Gi, _ = ecef_to_cyl(xp, fr, jacobian=True)
        F = np.zeros((T, n, n))
        F[:, 0:6, 0:6] = Gi @ F6 @ G
        Q = np.zeros((T, n, n))
        Q[:, 0:6, 0:6] = Gi @ Qb @ np.swapaxes(Gi, -1, -2)
        for i in range(N):
            s = slice(6 + 6 * i, 12 + 6 * i)
            F[:, s, s] = F6
            Q[:, s, s] = Qu
        P = F @ self.P @ np.swapaxes(F, -1, -2) + Q
        self.P = 0.5 * (P + np.swapaxes(P, -1, -2))
        self.y = np.concatenate([yb, U.reshape(T, 6 * N)], axis=-1)
        self.frame = fr

    def step(self, t_gps_s, gnss, link: LinkEpoch):
        """Predict to t_gps_s, then one update with every UAV's GNSS and the beacon links."""
        t = float(t_gps_s)
        dt = t - self.t_gps_s
        if dt > 0:
            self._predict(dt)
        self.t_gps_s = t
        T, N, n = self.y.shape[0], self.N, self.n
        if len(gnss) != N:
            raise ValueError(f"gnss must hold {N} (model, z) pairs, got {len(gnss)}")
        ys, Hs = [], []
        Ux = self.uav_states()
        for i, (model, z) in enumerate(gnss):
            hx, Hi = model.h_and_H(Ux[:, i])
            sr = np.sqrt(np.broadcast_to(np.asarray(model.R_diag(), float), hx.shape))
            H = np.zeros((T, hx.shape[-1], n))
            H[:, :, 6 + 6 * i:12 + 6 * i] = Hi / sr[..., None]
            ys.append((np.asarray(z, float) - hx) / sr)
            Hs.append(H)
        # beacon links: ranges and Dopplers at the filter's own UAV states
        xb, G = cyl_to_ecef(self.y[:, 0:6], self.frame, jacobian=True)
        vr = np.broadcast_to(np.asarray(link.var_range_m2, float), (T, N))
        vv = np.broadcast_to(np.asarray(link.var_range_rate_m2_s2, float), (T, N))
        model = ObserverRangeDoppler(Ux[..., 0:3], Ux[..., 3:6], vr, vv, observer_uncertainty="ignore")
        zhat, HB = model.h_and_H(xb)  # (T, 2N), (T, 2N, 6) wrt ECEF [B, V_B]
        mask = np.ones((T, N), bool) if link.mask is None else np.asarray(link.mask, bool)
        if getattr(self.config, "second_order_r", False):  # as the locator (LocatorConfig.second_order_r)
            Pr = self.P[:, 0:6, 0:6]
            Pb = (G @ Pr @ np.swapaxes(G, -1, -2))[:, 0:3, 0:3]
            Pu = np.stack([self.P[:, 6 + 6 * i:9 + 6 * i, 6 + 6 * i:9 + 6 * i] for i in range(N)], axis=1)
            v_r2, v_v2 = second_order_var(xb, Ux[..., 0:3], Ux[..., 3:6], Pb[:, None] + Pu)
            vr, vv = vr + v_r2, vv + v_v2
        z = np.empty((T, 2 * N))
        z[:, 0::2], z[:, 1::2] = link.range_m, link.range_rate_m_s
        sr = np.sqrt(np.stack([vr, vv], axis=-1).reshape(T, 2 * N))
        w = np.repeat(mask, 2, axis=-1) / sr
        H = np.zeros((T, 2 * N, n))
        H[:, :, 0:6] = HB @ G
        for i in range(N):
            rows = slice(2 * i, 2 * i + 2)
            # d/dU_i = -d/dB (positions), d rdot/dV_i = -d rdot/dV_B
            H[:, rows, 6 + 6 * i:12 + 6 * i] = -HB[:, rows, :]
        ys.append((z - zhat) * w)
        Hs.append(H * w[..., None])
        y = np.concatenate(ys, axis=-1)
        H = np.concatenate(Hs, axis=-2)
        y0, P0 = np.ascontiguousarray(self.y), np.ascontiguousarray(self.P)

        def update(nu, Hl):
            return kernels.joseph_update(y0, P0, np.ascontiguousarray(nu), np.ascontiguousarray(Hl),
                                         r_diag=np.ones(nu.shape), backend=self.backend)

        first = update(y, H)
        # iterated EKF (config.update_iterations > 1, as the locator's): the beacon links
        # relinearised at the updated state (the GNSS rows are already linear enough: ~20000 km ranges)
        ng = sum(a.shape[-1] for a in ys[:-1])

        def linearize(yi):
            xb, G = cyl_to_ecef(yi[:, 0:6], self.frame, jacobian=True)
            Ui = yi[:, 6:].reshape(T, N, 6)
            zhat, HB = ObserverRangeDoppler(Ui[..., 0:3], Ui[..., 3:6], vr, vv,
                                            observer_uncertainty="ignore").h_and_H(xb)
            H2 = np.zeros((T, 2 * N, n))
            H2[:, :, 0:6] = HB @ G
            for i in range(N):
                rows = slice(2 * i, 2 * i + 2)
                H2[:, rows, 6 + 6 * i:12 + 6 * i] = -HB[:, rows, :]
            # the GNSS rows kept at their first linearisation: their first innovation
            return (np.concatenate([y[:, :ng], relinearized_innovation(z, zhat, H2, y0, yi) * w], axis=-1),
                    np.concatenate([H[:, :ng], H2 * w[..., None]], axis=-2))

        it = iterated_update(y0, first[0], linearize, update, int(getattr(self.config, "update_iterations", 1)))
        yi, Pi, nis = first if it.result is None else it.result
        self.y, self.P = yi, Pi
        return self

    def beacon_ecef(self):
        """(x (T, 6), P (T, 6, 6)): the beacon's ECEF moments (unscented transform)."""
        return ut_to_ecef(self.y[:, 0:6], self.P[:, 0:6, 0:6], self.frame)


# --------------------------------------------------------------------------- PCRB


def link_information(B, VB, U, V, var_range_m2, var_range_rate_m2_s2):
    """Fisher information of one epoch's beacon links over [B, V_B, U_1, V_1, ...] at the
    true states: B, VB (3,), U, V (N, 3) -> (6 + 6N, 6 + 6N)."""
    N = U.shape[0]
    n = 6 + 6 * N
    _, HB = ObserverRangeDoppler(U, V, var_range_m2, var_range_rate_m2_s2,
                                 observer_uncertainty="ignore").h_and_H(np.concatenate([B, VB]))
    H = np.zeros((2 * N, n))
    H[:, 0:6] = HB
    for i in range(N):
        H[2 * i:2 * i + 2, 6 + 6 * i:12 + 6 * i] = -HB[2 * i:2 * i + 2]
    w = np.empty(2 * N)
    w[0::2] = 1.0 / np.broadcast_to(var_range_m2, (N,))
    w[1::2] = 1.0 / np.broadcast_to(var_range_rate_m2_s2, (N,))
    return H.T @ (w[:, None] * H)


def _inv_spd(A):
    """Inverse of a symmetric positive-definite matrix, equilibrated (its diagonal spans
    ~12 orders of magnitude here: km^2 for the beacon's height, (cm/s)^2 for UAV velocities)."""
    A = 0.5 * (A + A.T)
    d = 1.0 / np.sqrt(np.diag(A))
    L = np.linalg.cholesky(A * d[:, None] * d[None, :])
    Li = np.linalg.inv(L)
    Ai = (Li.T @ Li) * d[:, None] * d[None, :]
    return 0.5 * (Ai + Ai.T)


def pcrb_central(t_s, B, VB, U, V, gnss_info, var_range_m2, var_range_rate_m2_s2, J0_beacon, *,
                 q_beacon_m2_s3: float, q_uav_m2_s3: float = 0.02, return_full: bool = False):
    """PCRB of the centralised model at the true states (module docstring).

    t_s (K,) epochs (uniform or not); B, VB (K, 3); U, V (K, N, 3) the truth;
    gnss_info (K, N, 6, 6): each UAV's GNSS Fisher information H' R^-1 H at its true state
    (at epoch 0 it is also the UAVs' prior: the least-squares fix the onboard filters start
    from); J0_beacon (6, 6): the beacon's prior information at epoch 0.
    Returns (K, 3, 3) beacon position bounds (or (K, n, n) with ``return_full``).
    """
    t = np.asarray(t_s, float)
    K, N = U.shape[0], U.shape[1]
    n = 6 + 6 * N
    J = np.zeros((n, n))
    J[0:6, 0:6] = J0_beacon
    out = np.empty((K, n, n) if return_full else (K, 3, 3))
    Bk = None
    for k in range(K):
        I = link_information(B[k], VB[k], U[k], V[k], var_range_m2, var_range_rate_m2_s2)
        for i in range(N):
            s = slice(6 + 6 * i, 12 + 6 * i)
            I[s, s] += gnss_info[k, i]
        if k == 0:
            Jk = J + I
        else:
            dt = t[k] - t[k - 1]
            F6, Qb = cv_matrices(float(q_beacon_m2_s3), float(dt))
            _, Qu = cv_matrices(float(q_uav_m2_s3), float(dt))
            F = np.zeros((n, n))
            Q = np.zeros((n, n))
            F[0:6, 0:6], Q[0:6, 0:6] = F6, Qb
            for i in range(N):
                s = slice(6 + 6 * i, 12 + 6 * i)
                F[s, s], Q[s, s] = F6, Qu
            Jk = _inv_spd(F @ Bk @ F.T + Q) + I
        Bk = _inv_spd(Jk)
        out[k] = Bk if return_full else Bk[0:3, 0:3]
    return out
