"""The landing of a descending sonde track (relaxed kinematics): the track is at rest on flat ground
at the site's height from then on, its height's uncertainty turned into horizontal uncertainty along
its trajectory, and the published covariance carries its possible remaining descent for a while."""
from __future__ import annotations

import math

import numpy as np

from sitl.constants import WGS84
from sitl.geodesy import ecef_to_geodetic, geodetic_to_ecef

from .transition import E2, enu_rotations

__all__ = ["Landing", "curvature_drop_cov"]

_NORMAL_SCALE = np.array([1.0, 1.0, 1.0 / (1.0 - E2)])  # grad of x^2 + y^2 + z^2 / (1 - e^2): the ellipsoid's normal


def curvature_drop_cov(pos_ecef_m, pos_cov) -> np.ndarray:
    """The ground curves away under a wide horizontal spread: a sonde d away horizontally at the
    estimate's height lies |d|^2 / 2R below the estimate's tangent plane, which a Gaussian in ECEF
    cannot follow. This is the vertical second moment of that drop over the horizontal part of
    pos_cov (E |d|^4 / 4R^2 = (tr C^2 + 2 tr C C) / 4R^2, C the covariance in the tangent plane):
    ~90 m at a 20 km sigma per axis, 1e-10 m at a kilometre -- the published covariance gets it
    (not the filter's state, whose updates are linear anyway), as does a landed track's."""
    p = np.asarray(pos_ecef_m, dtype=float)
    n = p * _NORMAL_SCALE  # the vertical: the normal of the ellipsoid through p (~1e-6 rad off the geodetic
    n /= math.sqrt(float(n @ n))  # one at 10 km: nothing for this term, and no ecef_to_geodetic per Estimate)
    T = np.eye(3) - np.outer(n, n)
    C = T @ pos_cov @ T
    return ((np.trace(C) ** 2 + 2.0 * np.trace(C @ C)) / (4.0 * float(p @ p))) * np.outer(n, n)


class Landing:
    """SondeTracker's part: landing a descending track and its published covariance meanwhile."""

    def _land(self) -> None:
        """Relaxed kinematics with ``landing``: a descending track (its target vertical speed -- the
        wind state's component along the local vertical -- below 0) whose height has reached the
        ground's (the site's: flat terrain, as in the sonde model) has landed and is at rest from then
        on (velocity, gust, wind and shear zero; the landed transition), counted ``landings``; a
        re-initialisation takes it up again.

        The landing keeps what the track does not know. The estimate reaches the ground when its
        height does; the sonde, dh higher or lower (the height's uncertainty), lands dh / |V_up|
        later or earlier, carried on along its trajectory meanwhile. So the landing point is the
        estimate moved along its velocity V to the ground, and its error is the position error
        projected onto the ground along V: J = I - a n' with a = V / (V . n), n the local vertical --
        the height's uncertainty becomes horizontal uncertainty (V_h / |V_up| per metre), it is not
        dropped. The landed covariance adds, vertically, the second moment of the ground's drop
        below the tangent plane over that horizontal spread (|d|^2 / 2R: at a 30 km sigma ~70 m)
        and a 1 m^2 floor. Until the sonde has surely come down (its remaining height
        max(dh - |V_up| tau, 0) after tau) the published covariance also carries its possible
        remaining descent (``_landing_spread``)."""
        w = self.layout.wind
        if w is None or not self.params.landing or self._ground_h_m is None or not self._landed.size:
            return
        cand = np.flatnonzero(np.isfinite(self._t) & ~self._landed)
        if not cand.size:
            return
        pos = self._x[cand, 0:3]  # (a first cut: descending along the geocentric vertical, within 1 km of the ground)
        r = np.sqrt(np.einsum("ij,ij->i", pos, pos))
        near = (np.einsum("ij,ij->i", self._x[cand, w:w + 3], pos) < 0.0) & (r < WGS84.a_m + self._ground_h_m + 1000.0)
        cand = cand[near]
        if not cand.size:
            return
        lat, lon, h = (np.atleast_1d(v) for v in ecef_to_geodetic(self._x[cand, 0:3]))
        up = enu_rotations(lat, lon)[:, 2]  # the local vertical at each estimate
        hit = (np.einsum("ij,ij->i", self._x[cand, w:w + 3], up) < 0.0) & (h <= self._ground_h_m)
        k = self.layout.n_kin
        n = self.layout.n
        for i in np.flatnonzero(hit):
            slot, nrm = cand[i], up[i]
            x, P0 = self._x[slot], self._P[slot].copy()  # (P0: the pre-landing covariance, kept below)
            v_up = float(x[3:6] @ nrm)
            a = x[3:6] / v_up if v_up < -0.1 else nrm  # back up the trajectory, 1 m per metre of height
            pos = x[0:3] - a * (h[i] - self._ground_h_m)  # to the ground along the trajectory
            la, lo, _ = ecef_to_geodetic(pos)
            x[0:3] = geodetic_to_ecef(float(la), float(lo), self._ground_h_m)
            x[3:k] = 0.0
            T = np.eye(n)
            T[0:3, 0:3] -= np.outer(a, nrm)
            T[3:k, 3:k] = 0.0
            P = T @ P0 @ T.T
            P[0:3, 0:3] += curvature_drop_cov(x[0:3], P[0:3, 0:3]) + np.outer(nrm, nrm)  # and a 1 m^2 floor
            P[3:k, 3:k] += 1e-8 * np.eye(k - 3)
            self._P[slot] = 0.5 * (P + P.T)
            self._landed[slot] = True
            self._land_t[slot] = self._t[slot] if v_up < -0.1 else np.nan
            self._land_a[slot], self._land_b[slot] = a, P0[0:3, 0:3] @ nrm
            self._land_var[slot], self._land_v[slot] = float(nrm @ P0[0:3, 0:3] @ nrm), -v_up
            self.counters.landings += 1

    def _landing_spread(self, slot: int, t: float):
        """The published position covariance's excess over the landed state's while the sonde may
        still be coming down (None once negligible): with dh ~ N(0, s^2) its height above the
        estimate at the landing, the error at tau after it is e - a g, g = min(dh, |V_up| tau) (lower:
        landed earlier, at its own landing point; higher: still descending towards it), whose second
        moment is P - Phi(z) (a b' + b a') + a a' s^2 (Phi(z) - z phi(z) + z^2 (1 - Phi(z))),
        z = |V_up| tau / s; at tau -> oo this is the landed J P J'. The excess over that."""
        t0, var = self._land_t[slot], self._land_var[slot]
        if not (math.isfinite(t0) and var > 0.0):
            return None
        s = math.sqrt(var)
        z = self._land_v[slot] * (t - t0) / s
        if z > 8.0:
            return None
        q = 0.5 * math.erfc(z / math.sqrt(2.0))  # 1 - Phi(z)
        phi = math.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)
        a, b = self._land_a[slot], self._land_b[slot]
        ab = np.outer(a, b)
        return q * (ab + ab.T) - var * (q * (1.0 - z * z) + z * phi) * np.outer(a, a)
