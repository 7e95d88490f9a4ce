"""The initialisation of a sonde track: from the first radar fix with valid angles (aer -> ECEF,
its covariance through the Jacobian; with coloured radar noise correlated with the radar's error
states), else from a least-squares fix of a relay epoch, wide priors for the rest; and the
re-acquisition of a track whose blocks were rejected too many epochs in a row."""
from __future__ import annotations

import numpy as np

from sitl.bus import RadarMeasurement, SondeRelay
from sitl.geodesy import ecef_to_geodetic, enu_rotation
from sitl.radio.radar import aer_cov_to_ecef, aer_to_ecef_jacobian, radar_aer_to_ecef

from .relay_fix import relay_fix
from .transition import SondeTransition

__all__ = ["Initialisation"]


class Initialisation:
    """SondeTracker's part: starting (and restarting) a track."""

    def _ensure_transition(self, site_ecef) -> None:
        if self._transition is not None:
            return
        p = self.params
        lat, lon, site_h = ecef_to_geodetic(np.asarray(site_ecef, float))
        r = enu_rotation(lat, lon)  # the model's horizontal / vertical split at the site
        self._transition = SondeTransition(self.layout, p, r)
        self._ground_h_m = float(site_h)  # flat terrain at the site's height (the landing)

    def _prior(self) -> tuple[np.ndarray, np.ndarray]:
        L, p = self.layout, self.params
        x, P = np.zeros(L.n), np.zeros((L.n, L.n))
        P[3:6, 3:6] = np.eye(3) * p.prior_sigma_vel_m_s**2
        P[6:9, 6:9] = self._transition.acc_cov_ecef
        if L.dd is not None:
            P[L.dd, L.dd] = p.prior_sigma_delta_d_m**2
            P[L.osc, L.osc] = p.osc_sigma_m_s**2
        if L.err is not None:
            P[L.err:L.err + 3, L.err:L.err + 3] = np.diag(np.square(p.radar_sigma))
        if L.nb:
            b = np.arange(L.bias, L.bias + L.nb)
            P[b, b] = 1.0
        return x, P

    def _with_wind(self, x, P):
        """Relaxed kinematics: the wind states of a new track, set once the rest of (x, P) is --
        the wind is the velocity plus an offset d ~ N(0, prior_sigma_wind_offset^2 I) independent
        of everything else (so its rows are the velocity's), and its shear is at its stationary prior;
        the gust's and the shear's priors split horizontal / vertical at the new track's position."""
        w = self.layout.wind
        if w is None:
            return x, P
        tr = self._transition
        P[6:9, 6:9] = tr.acc_cov_at(x[0:3])  # (the prior's gust block is independent of the rest)
        x[w:w + 3] = x[3:6]
        x[w + 3:w + 6] = 0.0
        P[w:w + 6, :] = 0.0
        P[:, w:w + 6] = 0.0
        P[w:w + 3, :] = P[3:6, :]
        P[:, w:w + 3] = P[:, 3:6]
        P[w:w + 3, w:w + 3] = P[3:6, 3:6] + self.params.prior_sigma_wind_offset_m_s**2 * np.eye(3)
        P[w + 3:w + 6, w + 3:w + 6] = tr.shear_cov_at(x[0:3])
        return x, P

    def _init_from_radar(self, slot: int, m: RadarMeasurement, count: bool = True) -> bool:
        if not m.angles_valid:
            return False
        self._ensure_transition(m.radar_pos_ecef_m)
        site = np.asarray(m.radar_pos_ecef_m)
        L = self.layout
        if L.nb:
            self._bias_clear(slot)
        x, P = self._prior()
        x[0:3] = radar_aer_to_ecef(m.az_rad, m.el_rad, m.slant_range_m, site)
        var = np.array([m.var_az_rad2, m.var_el_rad2, m.var_range_m2])  # radar.py's column order
        P[0:3, 0:3] = aer_cov_to_ecef(m.az_rad, m.el_rad, m.slant_range_m, site, var)
        if L.err is not None:
            J = aer_to_ecef_jacobian(m.az_rad, m.el_rad, m.slant_range_m, site)[:, [2, 0, 1]]  # [D, az, el]
            S = P[L.err:L.err + 3, L.err:L.err + 3]
            Rw = self.params.radar_white_fraction * np.diag([m.var_range_m2, m.var_az_rad2, m.var_el_rad2])
            # P = g(z - err - v), v the white part: cov(P) = J (S + Rw) J', cov(P, err) = -J S
            # (without Rw the joint covariance is singular: P would be a function of err)
            P[0:3, 0:3] = J @ (S + Rw) @ J.T
            P[0:3, L.err:L.err + 3] = -J @ S
            P[L.err:L.err + 3, 0:3] = -(J @ S).T
        x, P = self._with_wind(x, P)
        self._x[slot], self._P[slot] = x, 0.5 * (P + P.T)
        self._landed[slot] = False
        self.counters.init_radar += count
        return True

    def _init_from_relay(self, slot: int, m: SondeRelay, count: bool = True) -> bool:
        fix = relay_fix(m.sat_pos_ecef_m, m.sat_vel_ecef_m_s, m.pseudorange_m, m.pseudo_doppler_m_s,
                        m.var_pseudorange_m2, m.var_pseudo_doppler_m2_s2, m.ground_pos_ecef_m)
        if fix is None:
            return False
        L = self.layout
        cross = None
        if L.nb:
            # the fix again, weighted by the whole error budget; its error G (b + v) is correlated
            # with the satellites' slow errors b = s u: cov(fix error, u error) = -G diag(s)
            glon = np.fromiter((sid[:1] == "R" for sid in m.sat_ids), dtype=bool, count=m.n)
            scale, white = self._relay_error_model(fix.pos_ecef_m, m.sat_pos_ecef_m, glon, 1.0)
            var = m.var_pseudorange_m2 + white + scale * scale
            fix2 = relay_fix(m.sat_pos_ecef_m, m.sat_vel_ecef_m_s, m.pseudorange_m, m.pseudo_doppler_m_s, var,
                             m.var_pseudo_doppler_m2_s2, m.ground_pos_ecef_m)
            if fix2 is None:
                return False
            fix = fix2
            G = m.ground_pos_ecef_m
            dS = fix.pos_ecef_m - m.sat_pos_ecef_m
            A = np.empty((m.n, 4))
            A[:, :3] = (dS / np.linalg.norm(dS, axis=1)[:, None]
                        + (fix.pos_ecef_m - G) / max(float(np.linalg.norm(fix.pos_ecef_m - G)), 1e-3))
            A[:, 3] = 1.0
            gain = fix.cov_pos_dd @ (A.T / var)  # (4, n)
            self._bias_clear(slot)
            cols = self._bias_cols(slot, m.sat_ids, float(m.t_gps_s))
            cross = (cols, -gain * np.where(cols >= 0, scale, 0.0))
        self._ensure_transition(m.ground_pos_ecef_m)
        x, P = self._prior()
        x[0:3], x[3:6], x[L.dd], x[L.osc] = fix.pos_ecef_m, fix.vel_ecef_m_s, fix.delta_d_m, fix.osc_m_s
        ip, iv = [0, 1, 2, L.dd], [3, 4, 5, L.osc]
        P[np.ix_(ip, ip)] = fix.cov_pos_dd
        P[np.ix_(iv, iv)] = fix.cov_vel_osc
        if cross is not None:
            cols, c = cross
            ok = cols >= 0
            P[np.ix_(ip, cols[ok])] = c[:, ok]
            P[np.ix_(cols[ok], ip)] = c[:, ok].T
        x, P = self._with_wind(x, P)
        self._x[slot], self._P[slot] = x, P
        self._landed[slot] = False
        self.counters.init_relay += count
        return True

    def _reacquire(self, slots, group) -> None:
        """Re-initialise sondes whose relay or radar block was rejected ``reacquire_after``
        epochs in a row (a lost track: e.g. after a long range-only coast), from this epoch's fix."""
        n = self.params.reacquire_after
        if n is None:
            return
        for slot, (_, _, rel, rad) in zip(slots, group):
            k = self._rejects[slot]
            if k.max() < n:
                continue
            ok = False
            if k[1] >= n and rad is not None:
                ok = self._init_from_radar(slot, rad, count=False)
            if not ok and k[0] >= n and rel is not None and rel.n >= 4:
                ok = self._init_from_relay(slot, rel, count=False)
            if ok:
                self.counters.reacquired += 1
                self._rejects[slot] = 0
                self._t_init[slot] = self._t_meas[slot] = self._t[slot]
