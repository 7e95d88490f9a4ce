"""The sonde tracker's measurement model: relayed pseudoranges and pseudo-Dopplers, then the
radar's [range, az, el], batched over sondes (SondeMeasurement; Moroz et al., seed 004, eqs 22-23
and 31-33). The rows are computed by a compiled kernel (numba) when available; the numpy code is
the reference (they agree to rounding, tested)."""
from __future__ import annotations

import math

import numpy as np

try:  # compiled measurement rows (numba); the numpy path in SondeMeasurement is the reference
    import numba as _nb
except ImportError:  # pragma: no cover
    _nb = None

from sitl.constants import C_M_S, WGS84

from .params import TWO_PI, Layout

__all__ = ["OMEGA_E", "SondeMeasurement", "relay_frame_point", "wrap_pi"]


def wrap_pi(a):
    """Angle(s) wrapped to [-pi, pi)."""
    return np.mod(np.asarray(a, dtype=float) + math.pi, TWO_PI) - math.pi



OMEGA_E = float(WGS84.omega_rad_s)


def relay_frame_point(pos_ecef_m, vel_ecef_m_s, ground_pos_ecef_m):
    """The point the relay's measurements locate: the sonde at the downlink emission,
    P - V tau, rotated into the ECEF frame of reception at G (the Earth turns by w_e tau
    meanwhile), tau = |P - G| / c (sitl.radio.relay). It lies 0.1-0.4 m from P between 50
    and 250 km, not negligible against a relay fix of ~0.6 m. (..., 3) arrays."""
    P, V = np.asarray(pos_ecef_m, float), np.asarray(vel_ecef_m_s, float)
    tau = np.linalg.norm(P - ground_pos_ecef_m, axis=-1, keepdims=True) / C_M_S
    o = P - V * tau
    th = OMEGA_E * tau[..., 0]
    ct, st = np.cos(th), np.sin(th)
    return np.stack([ct * o[..., 0] + st * o[..., 1], ct * o[..., 1] - st * o[..., 0], o[..., 2]], axis=-1)


def _rows_py(x, sat_pos, sat_vel, ground, relay_mask, site, rot, z_az, radar_mask, dd, osc, err, bias_col, bias_scale,
            h, H):
    """h (N, m) and H (N, m, n) at states x (N, n), row by row (the compiled path; H must come
    in zeroed). Rows: U pseudoranges, U pseudo-Dopplers (if U > 0), then [range, az, el]
    (if h has 2U + 3 columns). dd, osc, err: state indices, -1 when absent; bias_col (N, U)
    the state index of each satellite's error state (-1: none), bias_scale (N, U) its std."""
    N = x.shape[0]
    U = sat_pos.shape[1]
    radar = h.shape[1] == 2 * U + 3
    for b in range(N):
        px, py, pz = x[b, 0], x[b, 1], x[b, 2]
        vx, vy, vz = x[b, 3], x[b, 4], x[b, 5]
        if U > 0:
            # the relay measures the downlink-emission point in the ECEF frame of reception
            tau = math.sqrt((px - ground[0]) ** 2 + (py - ground[1]) ** 2 + (pz - ground[2]) ** 2) / C_M_S
            ox, oy, oz = px - vx * tau, py - vy * tau, pz - vz * tau
            th = OMEGA_E * tau
            ct, st = math.cos(th), math.sin(th)
            px, py, pz = ct * ox + st * oy, ct * oy - st * ox, oz
            gx, gy, gz = px - ground[0], py - ground[1], pz - ground[2]
            rg = max(math.sqrt(gx * gx + gy * gy + gz * gz), 1e-3)
            kx, ky, kz = gx / rg, gy / rg, gz / rg
            kv = kx * vx + ky * vy + kz * vz
            for u in range(U):
                if not relay_mask[b, u]:
                    h[b, u] = 0.0
                    h[b, U + u] = 0.0
                    continue
                dx, dy, dz = px - sat_pos[b, u, 0], py - sat_pos[b, u, 1], pz - sat_pos[b, u, 2]
                rho = math.sqrt(dx * dx + dy * dy + dz * dz)
                ix, iy, iz = dx / rho, dy / rho, dz / rho
                wx, wy, wz = vx - sat_vel[b, u, 0], vy - sat_vel[b, u, 1], vz - sat_vel[b, u, 2]
                uw = ix * wx + iy * wy + iz * wz
                bh = 0.0
                j = bias_col[b, u]
                if j >= 0:
                    bh = bias_scale[b, u] * x[b, j]
                    H[b, u, j] = bias_scale[b, u]
                h[b, u] = rho + rg + x[b, dd] + bh
                h[b, U + u] = uw + kv + x[b, osc]
                H[b, u, 0], H[b, u, 1], H[b, u, 2] = ix + kx, iy + ky, iz + kz
                H[b, u, dd] = 1.0
                H[b, U + u, 0] = (wx - ix * uw) / rho + (vx - kx * kv) / rg
                H[b, U + u, 1] = (wy - iy * uw) / rho + (vy - ky * kv) / rg
                H[b, U + u, 2] = (wz - iz * uw) / rho + (vz - kz * kv) / rg
                H[b, U + u, 3], H[b, U + u, 4], H[b, U + u, 5] = ix + kx, iy + ky, iz + kz
                H[b, U + u, osc] = 1.0
        if radar:
            r0 = 2 * U
            qx, qy, qz = x[b, 0] - site[0], x[b, 1] - site[1], x[b, 2] - site[2]
            e = rot[0, 0] * qx + rot[0, 1] * qy + rot[0, 2] * qz
            n = rot[1, 0] * qx + rot[1, 1] * qy + rot[1, 2] * qz
            u_ = rot[2, 0] * qx + rot[2, 1] * qy + rot[2, 2] * qz
            rho2 = max(e * e + n * n, 1e-6)
            rho = math.sqrt(rho2)
            d2 = rho2 + u_ * u_
            d = math.sqrt(d2)
            D, az, el = d, math.atan2(e, n), math.atan2(u_, rho)
            if err >= 0:
                D += x[b, err]
                az += x[b, err + 1]
                el += x[b, err + 2]
            # the representative of az nearest the measured azimuth (no 2 pi jump)
            a = z_az[b] - az + math.pi
            az = z_az[b] - (a - 2.0 * math.pi * math.floor(a / (2.0 * math.pi)) - math.pi)
            vals = (D, az, el)
            jac = ((e / d, n / d, u_ / d), (n / rho2, -e / rho2, 0.0),
                   (-e * u_ / (rho * d2), -n * u_ / (rho * d2), rho / d2))
            for j in range(3):
                if not radar_mask[b, j]:
                    h[b, r0 + j] = 0.0
                    continue
                h[b, r0 + j] = vals[j]
                j0, j1, j2 = jac[j]
                for c in range(3):
                    H[b, r0 + j, c] = j0 * rot[0, c] + j1 * rot[1, c] + j2 * rot[2, c]
                if err >= 0:
                    H[b, r0 + j, err + j] = 1.0


_rows_nb = None if _nb is None else _nb.njit(cache=True, nogil=True)(_rows_py)


class SondeMeasurement:
    """Relayed pseudoranges, pseudo-Dopplers (U satellite slots) and the radar's [range, az,
    el] for Bs sondes, as one measurement model (rows: U pr, U prr, then 3 radar rows; either
    part may be absent).

    relay part: sat_pos, sat_vel (Bs, U, 3), relay_mask (Bs, U), ground (3,) G, and bias_col (Bs, U)
    the state index of each satellite's error state (-1: none) with bias_scale (Bs, U) its std
    (the pseudorange gets bias_scale x that unit state);
    radar part: site (3,), rot (3, 3) its ENU rotation, radar_mask (Bs, 3);
    z (Bs, m) the measurements (held for the azimuth unwrap), r (Bs, m) the variances.
    Padded rows (mask False) have h = 0 and H = 0; the caller sets z = 0 and r = 1 there.
    ``h`` is numpy and broadcasts over leading sigma-point axes (UKF); ``h_and_H`` runs the
    compiled row kernel when numba is there (x (Bs, n)), else the numpy reference.
    """

    def __init__(self, layout: Layout, z, r, *, sat_pos=None, sat_vel=None, relay_mask=None, ground=None,
                 site=None, rot=None, radar_mask=None, bias_col=None, bias_scale=None, row_mask=None, sat_ids=None):
        self.layout = layout
        self.row_mask = row_mask  # (Bs, m) bool: rows left out (the integrity monitor's), None: none
        self.sat_ids = sat_ids  # the satellite of each relay slot (the union), when known
        self.z, self._r = z, r
        Bs = z.shape[0]
        self.relay = sat_pos is not None
        self.radar = site is not None
        if not self.relay:
            sat_pos = sat_vel = np.zeros((Bs, 0, 3))
            relay_mask = np.zeros((Bs, 0), dtype=bool)
            ground = np.zeros(3)
        if bias_col is None:
            bias_col = np.full(relay_mask.shape, -1, dtype=np.int64)
            bias_scale = np.zeros(relay_mask.shape)
        self.bias_col, self.bias_scale = bias_col, bias_scale
        if not self.radar:
            site, rot, radar_mask = np.zeros(3), np.eye(3), np.zeros((Bs, 0), dtype=bool)
        self.sat_pos, self.sat_vel, self.relay_mask, self.ground = sat_pos, sat_vel, relay_mask, ground
        self.site, self.rot, self.radar_mask = site, rot, radar_mask
        self.U = sat_pos.shape[1]
        self.mask = np.concatenate([relay_mask, relay_mask, radar_mask], axis=-1)
        if row_mask is not None:
            self.mask = self.mask & row_mask
        if self.mask.shape != z.shape or r.shape != z.shape:
            raise ValueError(f"z {z.shape} and r {r.shape} must have the rows of the mask {self.mask.shape}")

    @property
    def m_eff(self) -> np.ndarray:
        """Real (unpadded) rows per sonde."""
        return self.mask.sum(axis=-1)

    def _part(self, relay: bool, idx=slice(None)) -> SondeMeasurement:
        U = self.U
        if relay:
            cols = slice(0, 2 * U)
            kw = {"sat_pos": self.sat_pos[idx], "sat_vel": self.sat_vel[idx], "relay_mask": self.relay_mask[idx],
                  "ground": self.ground, "bias_col": self.bias_col[idx], "bias_scale": self.bias_scale[idx],
                  "sat_ids": self.sat_ids}
        else:
            cols = slice(2 * U, None)
            kw = {"site": self.site, "rot": self.rot, "radar_mask": self.radar_mask[idx]}
        if self.row_mask is not None:
            kw["row_mask"] = self.row_mask[idx][:, cols]
        return SondeMeasurement(self.layout, self.z[idx][:, cols], self._r[idx][:, cols], **kw)

    def relay_part(self, idx=slice(None)) -> SondeMeasurement | None:
        return self._part(True, idx) if self.relay else None

    def radar_part(self, idx=slice(None)) -> SondeMeasurement | None:
        return self._part(False, idx) if self.radar else None

    def subset(self, idx) -> SondeMeasurement:
        kw = {}
        if self.row_mask is not None:
            kw["row_mask"] = self.row_mask[idx]
        if self.relay:
            kw.update(sat_pos=self.sat_pos[idx], sat_vel=self.sat_vel[idx], relay_mask=self.relay_mask[idx],
                      ground=self.ground, bias_col=self.bias_col[idx], bias_scale=self.bias_scale[idx],
                      sat_ids=self.sat_ids)
        if self.radar:
            kw.update(site=self.site, rot=self.rot, radar_mask=self.radar_mask[idx])
        return SondeMeasurement(self.layout, self.z[idx], self._r[idx], **kw)

    # -- numpy reference (any leading axes before the sonde axis) --------------

    def _relay_np(self, x):
        L = self.layout
        P, V = relay_frame_point(x[..., 0:3], x[..., 3:6], self.ground), x[..., 3:6]
        dS = P[..., None, :] - self.sat_pos
        rho = np.sqrt(np.sum(dS * dS, axis=-1))
        Ki = dS / rho[..., None]
        dG = P - self.ground
        rG = np.maximum(np.sqrt(np.sum(dG * dG, axis=-1)), 1e-3)
        K = dG / rG[..., None]
        w = V[..., None, :] - self.sat_vel
        uw = np.sum(Ki * w, axis=-1)
        KV = np.sum(K * V, axis=-1)
        col = np.broadcast_to(np.maximum(self.bias_col, 0), x.shape[:-1] + self.bias_col.shape[-1:])
        bias = self.bias_scale * np.take_along_axis(x, col, axis=-1)  # scale 0 where there is no state
        h = np.concatenate([rho + bias + (rG + x[..., L.dd])[..., None], uw + (KV + x[..., L.osc])[..., None]],
                           axis=-1)
        return h, (Ki, K, rho, rG, w, uw, V, KV)

    def _radar_np(self, x):
        L = self.layout
        enu = (x[..., 0:3] - self.site) @ self.rot.T
        e, n, u = enu[..., 0], enu[..., 1], enu[..., 2]
        rho2 = np.maximum(e * e + n * n, 1e-6)
        rho = np.sqrt(rho2)
        d2 = rho2 + u * u
        d = np.sqrt(d2)
        D, az, el = d, np.arctan2(e, n), np.arctan2(u, rho)
        if L.err is not None:
            D, az, el = D + x[..., L.err], az + x[..., L.err + 1], el + x[..., L.err + 2]
        az = self.z[:, 2 * self.U + 1] - wrap_pi(self.z[:, 2 * self.U + 1] - az)
        return np.stack([D, az, el], axis=-1), (e, n, u, rho, rho2, d2, d)

    def h(self, x):
        x = np.asarray(x, dtype=float)
        parts = []
        if self.relay:
            parts.append(self._relay_np(x)[0])
        if self.radar:
            parts.append(self._radar_np(x)[0])
        h = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=-1)
        return np.where(self.mask, h, 0.0)

    def h_and_H_numpy(self, x):
        L = self.layout
        x = np.asarray(x, dtype=float)
        Bs, m = self.z.shape
        h = np.zeros((Bs, m))
        H = np.zeros((Bs, m, L.n))
        U = self.U
        if self.relay:
            hr, (Ki, K, rho, rG, w, uw, V, KV) = self._relay_np(x)
            h[:, :2 * U] = hr
            KiK = Ki + K[:, None, :]
            H[:, :U, 0:3] = KiK
            H[:, :U, L.dd] = 1.0
            H[:, U:2 * U, 0:3] = ((w - Ki * uw[..., None]) / rho[..., None]
                                  + ((V - K * KV[:, None]) / rG[:, None])[:, None, :])
            H[:, U:2 * U, 3:6] = KiK
            H[:, U:2 * U, L.osc] = 1.0
            bb, uu = np.nonzero(self.bias_col >= 0)
            H[bb, uu, self.bias_col[bb, uu]] = self.bias_scale[bb, uu]
        if self.radar:
            hd, (e, n, u, rho, rho2, d2, d) = self._radar_np(x)
            h[:, 2 * U:] = hd
            z0 = np.zeros_like(e)
            # rows d/d(enu) of range, azimuth, elevation (sitl.radio.radar.ecef_to_aer_jacobian)
            J = np.stack([np.stack([e / d, n / d, u / d], -1),
                          np.stack([n / rho2, -e / rho2, z0], -1),
                          np.stack([-e * u / (rho * d2), -n * u / (rho * d2), rho / d2], -1)], -2)
            H[:, 2 * U:, 0:3] = J @ self.rot
            if L.err is not None:
                for j in range(3):
                    H[:, 2 * U + j, L.err + j] = 1.0
        h *= self.mask
        H *= self.mask[..., None]
        return h, H

    def h_and_H(self, x):
        x = np.asarray(x, dtype=float)
        if _rows_nb is None or x.ndim != 2:
            return self.h_and_H_numpy(x)
        L = self.layout
        Bs, m = self.z.shape
        h = np.empty((Bs, m))
        H = np.zeros((Bs, m, L.n))
        z_az = self.z[:, 2 * self.U + 1] if self.radar else np.zeros(Bs)
        _rows_nb(np.ascontiguousarray(x), self.sat_pos, self.sat_vel, self.ground, self.relay_mask, self.site,
                 self.rot, np.ascontiguousarray(z_az), self.radar_mask, -1 if L.dd is None else L.dd,
                 -1 if L.osc is None else L.osc, -1 if L.err is None else L.err, self.bias_col, self.bias_scale, h, H)
        if self.row_mask is not None:
            h *= self.mask
            H *= self.mask[..., None]
        return h, H

    def H(self, x):
        return self.h_and_H(x)[1]

    def R_diag(self):
        return self._r

    def R(self):
        return self._r[..., None] * np.eye(self._r.shape[-1])
