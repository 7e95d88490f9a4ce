"""The blind start: a window of epochs -> [B, V_B] and its mirror hypothesis (InitFix).

Closed-form multilateration of each epoch (UAV estimates as anchors), the component-wise median
as the start, then Levenberg-Marquardt on all ranges and Dopplers of the window (constant
velocity) with weak height and velocity priors; the height is scanned on both sides of the UAVs'
axis (the circle about their line and the reflection through their plane have nearly or exactly
the same ranges: ground_station.beacon)."""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from sitl.geodesy import ecef_to_geodetic
from sitl.radio.beacon_link import multilaterate

from .config import LocatorConfig
from .measurements import ObserverEpoch, cholesky_2x2, fill_absent, range_doppler_blocks, solve_lower_2x2

__all__ = ["InitFix", "init_fix", "local_up"]


class InitFix(NamedTuple):
    """The initial estimate of one trial (ECEF): x (6,) [B, V_B] at the last window epoch,
    P (6, 6), the closed-form start (3,), the number of epochs, the final weighted cost and
    LM iterations; mirror_x, mirror_P, mirror_cost: the best solution on the other side of
    the UAVs' plane or axis; mirror_outside: the mirror lies outside the declared search
    heights (config.search_height_m) and is refused."""

    x: np.ndarray
    P: np.ndarray
    start_pos_ecef_m: np.ndarray
    n_epochs: int
    cost: float
    iterations: int
    mirror_x: np.ndarray
    mirror_P: np.ndarray
    mirror_cost: float
    mirror_outside: bool = False


def local_up(pos):
    """The geodetic up unit vector (3,) at the ECEF point pos, and its height (m)."""
    lat, lon, h = ecef_to_geodetic(pos)
    return np.array([math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)]), float(h)


def init_fix(epochs, config: LocatorConfig = LocatorConfig(), iterations: int = 30) -> InitFix:
    """Initial [B, V_B] of one trial from a window of epochs (module docstring).

    epochs: list of (t_gps_s, ObserverEpoch with one row) -- at least one, each with >= 3
    present observers.  Closed-form multilateration per epoch (UAV estimates as anchors,
    range variance inflated by the UAV position variance), component-wise median as the
    start, then Levenberg-Marquardt on ranges, Dopplers and the height / velocity priors,
    with the height scanned on both sides of the UAVs' axis.
    """
    if not epochs:
        raise ValueError("epochs must hold at least one epoch")
    tK = float(epochs[-1][0])
    fixes, hs, rows = [], [], []
    # the UAVs' errors barely change across a short window: fully correlated, so their
    # consider term counts once for the window (kappa = number of epochs); "consider" too (its
    # track starts as "inflate", acquire_s): without it a few metres of UAV error against
    # decimetre range noise make the costs of the two sides of the UAVs' plane meaningless
    kappa = float(len(epochs)) if config.observer_uncertainty in ("inflate", "consider") else 0.0
    for t, ob in epochs:
        m = ob.mask[0]
        if m.sum() < 3:
            raise ValueError(f"epoch t={t}: a fix needs >= 3 observers, got {int(m.sum())}")
        pos, vel, cov = ob.pos[0, m], ob.vel[0, m], ob.cov[0, m]
        r, rd = ob.range_m[0, m], ob.range_rate_m_s[0, m]
        vr, vv = ob.var_range_m2[0, m], ob.var_range_rate_m2_s2[0, m]
        try:
            fixes.append(multilaterate(r, pos, vr + np.trace(cov[:, 0:3, 0:3], axis1=-2, axis2=-1) / 3.0).pos_ecef_m)
        except ValueError:  # collinear anchors: no closed-form fix from this epoch
            pass
        hs.append(ecef_to_geodetic(pos)[2])
        rows.append((float(t), ObserverEpoch(pos[None], vel[None], cov[None], r[None], rd[None], vr[None], vv[None],
                                             np.ones((1, r.size), bool))))
    if not fixes:
        raise ValueError("no epoch of the window gives a closed-form fix (collinear anchors)")
    start = np.median(np.array(fixes), axis=0)
    h_prior = float(np.mean(np.concatenate(hs)))
    sig_h = float(config.init_height_sigma_m)
    sig_v = float(config.init_vel_sigma_m_s)
    # the window's epochs stacked as rows (padded to the largest N; absent rows zeroed)
    K, Nm = len(rows), max(r[1].mask.shape[1] for r in rows)
    win = ObserverEpoch.empty(K, Nm)
    for j, (_, ob) in enumerate(rows):
        n = ob.mask.shape[1]
        for dst, src in zip(win, ob):
            dst[j, :n] = src[0]
    dts = np.array([t for t, _ in rows]) - tK
    pres = win.mask[..., None]

    def residuals(s, h_target=None, sig=sig_h):
        """Whitened residuals and Jacobian wrt s = [B(tK), V_B]."""
        xj = np.concatenate([s[0:3] + dts[:, None] * s[3:6], np.broadcast_to(s[3:6], (K, 3))], axis=-1)
        ob = fill_absent(win, xj)
        zhat, H, R = range_doppler_blocks(xj, ob, kappa)
        nu = (np.stack([ob.range_m, ob.range_rate_m_s], axis=-1) - zhat) * pres
        Hs = np.concatenate([H[..., 0:3], dts[:, None, None, None] * H[..., 0:3] + H[..., 3:6]], axis=-1)
        l11, l21, l22 = cholesky_2x2(R)
        res = [solve_lower_2x2(l11, l21, l22, nu[..., None])[..., 0].ravel()]
        jac = [(solve_lower_2x2(l11, l21, l22, Hs) * pres[..., None]).reshape(-1, 6)]
        if math.isfinite(sig):
            up, h = local_up(s[0:3])
            res.append(np.array([((h_prior if h_target is None else h_target) - h) / sig]))
            jac.append(np.concatenate([up, np.zeros(3)])[None] / sig)
        res.append(-s[3:6] / sig_v)
        jac.append(np.concatenate([np.zeros((3, 3)), np.eye(3)], axis=1) / sig_v)
        return np.concatenate(res), np.concatenate(jac)

    def solve(s, **kw):
        """Levenberg-Marquardt from s; returns (s, J, cost, iterations)."""
        y, J = residuals(s, **kw)
        cost = float(y @ y)
        lam, it = 1e-3, 0
        for it in range(1, iterations + 1):
            A, g = J.T @ J, J.T @ y
            accepted = done = False
            for _ in range(20):
                step = np.linalg.solve(A + lam * np.diag(np.diag(A)), g)
                y2, J2 = residuals(s + step, **kw)
                c2 = float(y2 @ y2)
                if c2 < cost:
                    done = cost - c2 < 1e-10 * max(cost, 1.0) or bool(np.all(np.abs(step[0:3]) < 1e-3))
                    s, y, J, cost, lam = s + step, y2, J2, c2, max(lam / 10.0, 1e-12)
                    accepted = True
                    break
                lam *= 10.0
            if not accepted or done:
                break
        return s, J, cost, it

    def best_from(p0):
        """Scan the height (pinned) over the prior's +-3 sigma from p0 (each pinned solve
        starts from the previous one), then release it from the best."""
        s0 = np.concatenate([p0, np.zeros(3)])
        if math.isfinite(sig_h):
            best, sc = None, s0
            for hc in h_prior + sig_h * np.arange(-3.0, 3.01, 1.0):
                sc = solve(sc, h_target=hc, sig=1.0)[0]
                yc, _ = residuals(sc)
                if best is None or float(yc @ yc) < best[1]:
                    best = (sc, float(yc @ yc))
            s0 = best[0]
        s, J, cost, it = solve(s0)
        P = np.linalg.inv(J.T @ J) * float(config.init_cov_scale)
        return s, 0.5 * (P + P.T), cost, it

    # the other side: (a) the solution reflected through the last epoch's UAV plane (best fit;
    # for 3 UAVs every range is the same there), refined where it lands, without the height
    # scan (the scan would walk back over to the deeper minimum); (b) the solution turned by
    # 180 deg about the UAVs' principal axis (a line-like formation: the far side of the circle
    # about their line), refined with the scan.  The mirror is the cheaper of those that did not
    # come back to the solution (further than 3 sigma of its covariance); the cheaper of the two
    # sides is the solution.
    one = best_from(start)
    last = rows[-1][1].pos[0]
    c = last.mean(axis=0)
    vt = np.linalg.svd(last - c)[2]
    a, nrm = vt[0], vt[-1]
    d = one[0][0:3] - c
    v = one[0][3:6]
    s, J, cost, it = solve(np.concatenate([one[0][0:3] - 2.0 * (d @ nrm) * nrm, v - 2.0 * (v @ nrm) * nrm]))
    P = np.linalg.inv(J.T @ J) * float(config.init_cov_scale)
    cands = [(s, 0.5 * (P + P.T), cost, it), best_from(c + 2.0 * (d @ a) * a - d)]
    Pi = np.linalg.inv(one[1][0:3, 0:3])
    apart = [q for q in cands if (q[0][0:3] - one[0][0:3]) @ Pi @ (q[0][0:3] - one[0][0:3]) > 9.0]
    two = min(apart or cands, key=lambda q: q[2])
    if two[2] < one[2]:
        one, two = two, one
    outside = False
    if config.search_height_m:  # the declared search volume decides where the ranges cannot
        lo, hi = config.search_height_m
        ins = []
        for q in (one, two):
            up, h = local_up(q[0][0:3])
            sig = 3.0 * math.sqrt(max(float(up @ q[1][0:3, 0:3] @ up), 0.0))
            ins.append(lo - sig <= h <= hi + sig)
        if not ins[0] and ins[1]:
            one, two = two, one
        outside = ins[0] != ins[1]
    return InitFix(one[0], one[1], start, len(rows), one[2], one[3], two[0], two[1], two[2], outside)
