"""The joint measurement model of one epoch's messages for a group of sondes: relay rows padded to
a common satellite set, the radar rows, the relay error model's variances and state columns."""
from __future__ import annotations

import numpy as np

from sitl.geodesy import ecef_to_geodetic, enu_rotation

from .measurements import SondeMeasurement

__all__ = ["EpochModel", "MixedSites"]


class MixedSites(Exception):
    """Sondes of one epoch heard through different ground receivers or radar sites."""


class EpochModel:
    """SondeTracker's part: building the measurement model of an epoch."""

    def _radar_site(self, pos):
        key = np.asarray(pos, float).tobytes()
        out = self._radar_sites.get(key)
        if out is None:
            lat, lon, _ = ecef_to_geodetic(np.asarray(pos, float))
            out = self._radar_sites[key] = (np.array(pos, float), enu_rotation(lat, lon))
        return out

    def _measurement(self, group, dt: float = 1.0, t: float = 0.0) -> SondeMeasurement:
        """The joint measurement model of a group of sondes (padded to common rows)."""
        L, p = self.layout, self.params
        Bs = len(group)
        kw = {}
        cols = []
        U = 0
        if L.uses_relay:
            rels = [g[2] for g in group if g[2] is not None]
            if len(rels) == 1:  # one sonde: its satellites as they come
                union = rels[0].sat_ids
            else:  # satellite slots in order of first appearance
                union = list(dict.fromkeys(s for m in rels for s in m.sat_ids))
            U = len(union)
            col = None
            sat_pos, sat_vel = np.zeros((Bs, U, 3)), np.zeros((Bs, U, 3))
            mask = np.zeros((Bs, U), dtype=bool)
            zr, rr = np.zeros((Bs, 2 * U)), np.ones((Bs, 2 * U))
            ground = rels[0].ground_pos_ecef_m if rels else np.zeros(3)
            for b, g in enumerate(group):
                m = g[2]
                if m is None:
                    continue
                if m is not rels[0] and not np.array_equal(m.ground_pos_ecef_m, ground):
                    raise MixedSites
                if m.sat_ids == union:
                    j = slice(0, U)
                else:
                    if col is None:
                        col = {sid: k for k, sid in enumerate(union)}
                    j = np.fromiter((col[s] for s in m.sat_ids), dtype=np.intp, count=m.n)
                sat_pos[b, j], sat_vel[b, j], mask[b, j] = m.sat_pos_ecef_m, m.sat_vel_ecef_m_s, True
                jj = j if isinstance(j, slice) else None
                if jj is not None:
                    zr[b, :U], zr[b, U:] = m.pseudorange_m, m.pseudo_doppler_m_s
                    rr[b, :U], rr[b, U:] = m.var_pseudorange_m2, m.var_pseudo_doppler_m2_s2
                else:
                    zr[b, j], zr[b, U + j] = m.pseudorange_m, m.pseudo_doppler_m_s
                    rr[b, j], rr[b, U + j] = m.var_pseudorange_m2, m.var_pseudo_doppler_m2_s2
            if L.nb and U:
                glon = np.fromiter((sid[:1] == "R" for sid in union), dtype=bool, count=U)
                slots = [g[1] for g in group]
                scale, white = self._relay_error_model(self._x[slots, 0:3], sat_pos, glon, dt)
                rr[:, :U] += np.where(mask, white, 0.0)
                bcol = np.full((Bs, U), -1, dtype=np.int64)
                for b, g in enumerate(group):
                    m = g[2]
                    if m is None or not m.n:
                        continue
                    c = self._bias_cols(g[1], m.sat_ids, t)
                    if m.sat_ids == union:
                        bcol[b] = c
                    else:
                        if col is None:
                            col = {sid: k for k, sid in enumerate(union)}
                        bcol[b, [col[sid] for sid in m.sat_ids]] = c
                over = mask & (bcol < 0)
                if over.any():  # no state left: the slow error taken as white
                    rr[:, :U] += np.where(over, scale * scale, 0.0)
                scale = np.where(bcol >= 0, scale, 0.0)
                kw.update(bias_col=bcol, bias_scale=scale)
            kw.update(sat_pos=sat_pos, sat_vel=sat_vel, relay_mask=mask, ground=np.asarray(ground), sat_ids=tuple(union))
            cols.append((zr, rr))
        if L.uses_radar:
            rads = [g[3] for g in group if g[3] is not None]
            site0 = rads[0].radar_pos_ecef_m if rads else None
            zd, rd = np.zeros((Bs, 3)), np.ones((Bs, 3))
            dmask = np.zeros((Bs, 3), dtype=bool)
            frac = p.radar_white_fraction if L.err is not None else 1.0
            for b, g in enumerate(group):
                m = g[3]
                if m is None:
                    continue
                if not np.array_equal(m.radar_pos_ecef_m, site0):
                    raise MixedSites
                zd[b, 0], rd[b, 0] = m.slant_range_m, frac * m.var_range_m2
                dmask[b, 0] = True
                if m.angles_valid:
                    zd[b, 1], zd[b, 2] = m.az_rad, m.el_rad
                    rd[b, 1], rd[b, 2] = frac * m.var_az_rad2, frac * m.var_el_rad2
                    dmask[b, 1:] = True
            site, rot = self._radar_site(site0) if site0 is not None else (np.zeros(3), np.eye(3))
            kw.update(site=site, rot=rot, radar_mask=dmask)
            cols.append((zd, rd))
        z = np.concatenate([a for a, _ in cols], axis=-1)
        r = np.concatenate([b for _, b in cols], axis=-1)
        return SondeMeasurement(L, z, r, **kw)
