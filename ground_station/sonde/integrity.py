"""The integrity monitor around the sonde tracker's updates (filters.integrity, Moroz et al. seed 003;
opt-in): per epoch it judges every sonde's rows at its predicted state, one channel per relayed
satellite and one per radar axis, and the rows it leaves out are masked out of every update of the
epoch; its events go on the bus (sitl.integrity_events)."""
from __future__ import annotations

import numpy as np

from .epoch_model import MixedSites
from .measurements import SondeMeasurement

__all__ = ["IntegrityGuard"]


class IntegrityGuard:
    """SondeTracker's part: the integrity monitor's verdict on each epoch's rows."""

    def _channel(self, sat_id: str) -> int:
        """The monitor channel of a relayed satellite (-1: none free). A new satellite takes the
        least recently used channel that has been unused for ``window + readmit_after`` epochs
        (its window then holds only healthy values and it is not excluded any more)."""
        c = self._chan_of.get(sat_id)
        if c is not None:
            return c
        c = int(np.argmin(self._chan_last))
        if self._mon_k - self._chan_last[c] < self._chan_age:
            return -1
        old = self._chan_sat[c]
        if old is not None:
            del self._chan_of[old]
        self._chan_of[sat_id], self._chan_sat[c] = c, sat_id
        return c

    def _channel_name(self, c: int) -> str:
        S = self._mon_S
        if c < S:
            return f"relay.{self._chan_sat[c]}"
        return f"{self.radar_id or 'radar'}.{('range', 'az', 'el')[c - S]}"

    def _integrity(self, upd, t: float) -> None:
        """Judge the epoch's measurements of the sondes in ``upd`` with the integrity monitor
        (at their predicted state), publish its events and keep, per sonde, which rows it
        leaves out and the variances it uses (applied by _guarded to every update of the epoch)."""
        L, c = self.layout, self.counters
        S, R = self._mon_S, self._mon_R
        m, n = 2 * S + R, L.n
        N = len(self._ids)
        end = self._cohorts[-1][1] if self._cohorts else 0
        if end < N:  # sondes seen for the first time: a cohort of their own (the monitor steps a batch together)
            self._cohorts.append([end, N, self._mon.init((N - end,), m, S + R)])
        self._mon_k += 1
        Z = np.full((N, m), np.nan)
        Hm = np.zeros((N, m, n))
        hm = np.zeros((N, m))
        rm = np.ones((N, m))
        X = np.where(np.isfinite(self._x), self._x, 0.0)
        P = np.where(np.isfinite(self._P), self._P, 0.0)
        dts = [t - float(self._t[u[1]]) for u in upd]
        self._mon_models = {}
        for dt in sorted(set(dts)):
            group = upd if len(dts) == 1 else [u for u, d in zip(upd, dts) if d == dt]
            try:
                models = [(group, self._measurement(group, dt, t))]
            except MixedSites:
                models = [([g], self._measurement([g], dt, t)) for g in group]
            for grp, mdl in models:
                self._mon_models[(dt, tuple(g[1] for g in grp))] = mdl
            slots = np.array([g[1] for g in group])
            for lnd in (False, True):  # after _measurement: a new satellite's error state is reset
                ss = slots[self._landed[slots] == lnd]
                if ss.size:
                    X[ss], P[ss] = self._propagate(ss, dt, lnd)
            for grp, model in models:
                sl = np.array([g[1] for g in grp])
                h, H = model.h_and_H(X[sl])
                U = model.U
                rows = np.full(model.z.shape[1], -1, dtype=np.int64)
                if U:
                    for u, sid in enumerate(model.sat_ids):
                        if not model.relay_mask[:, u].any():
                            continue
                        ch = self._channel(sid)
                        if ch < 0:
                            c.integrity_unmonitored += int(model.relay_mask[:, u].sum())
                            continue
                        self._chan_last[ch] = self._mon_k
                        rows[u], rows[U + u] = ch, S + ch
                if R:
                    rows[2 * U:] = 2 * S + np.arange(R)
                ok = rows >= 0
                src, dst = np.flatnonzero(ok), rows[ok]
                mk = model.mask[:, src]
                zz = np.where(mk, model.z[:, src], np.nan)
                Z[sl[:, None], dst[None, :]] = zz
                hm[sl[:, None], dst[None, :]] = np.where(mk, h[:, src], 0.0)
                Hm[sl[:, None], dst[None, :]] = np.where(mk[..., None], H[:, src], 0.0)
                rm[sl[:, None], dst[None, :]] = np.where(mk, model.R_diag()[:, src], 1.0)
        # not judged (their rows enter the monitor as missing, the tracker's own gating and manoeuvre
        # logic handles them): a track in its warm-up, and a sonde whose rows mostly jump at once -- a
        # manoeuvre (the burst) or a track error moves every channel, a channel fault only its own
        p = self.params
        cfg = p.integrity
        sl = np.array([u[1] for u in upd])
        young = (t - self._t_init[sl]) < p.integrity_warmup_s
        has = np.isfinite(Z[sl])
        nu = np.where(has, Z[sl] - hm[sl], 0.0)
        Hs = Hm[sl]
        hph = np.sum((Hs @ P[sl]) * Hs, axis=-1)
        jumps = (np.abs(nu) >= cfg.jump_sigma * np.sqrt(hph + rm[sl])) & has
        common = jumps.sum(axis=1) > p.integrity_common_fraction * np.maximum(has.sum(axis=1), 1)
        skip = young | common
        c.integrity_warmup += int(young.sum())
        c.integrity_common_mode += int((common & ~young).sum())
        Z[sl[skip]] = np.nan
        judged = set(sl[~skip].tolist())
        self._guard = {}
        for co in self._cohorts:
            a, b = co[0], co[1]
            got = {}

            def judge(x, P_, z, gm, **kw):  # the monitor's verdict only: the tracker's own update follows
                got["inert"], got["r"] = np.asarray(gm.inert), np.asarray(gm.R_diag())

            _, co[2], rep = self._mon.step(co[2], X[a:b], P[a:b], Z[a:b], _Prepared(hm[a:b], Hm[a:b], rm[a:b]),
                                           self._mon_ch, update=judge, backend=self.params.backend)
            c.integrity_epochs += 1
            has = np.isfinite(Z[a:b])
            c.integrity_rows_left_out += int((has & got["inert"]).sum())
            c.integrity_exclusions += int(rep.newly_excluded.sum())
            c.integrity_readmissions += int(rep.readmitted.sum())
            evs = self._events(rep, self._mon_ch, t, lambda bi, ch, a=a: f"{self._ids[a + bi[0]]}.{self._channel_name(ch)}",
                               cfg)
            c.integrity_events += len(evs)
            for u in upd:
                if a <= u[1] < b and u[1] in judged:
                    self._guard[u[1]] = (got["inert"][u[1] - a], got["r"][u[1] - a])

    def _guarded(self, model: SondeMeasurement, group) -> SondeMeasurement:
        """The group's measurement model with the monitor's verdict of this epoch applied: the
        rows it left out masked (z = 0, r = 1: no information, no NIS), the others with the
        variance it used (the nominal one, or its robust / adaptive inflation)."""
        S = self._mon_S
        U = model.U
        z, r = model.z.copy(), model._r.copy()
        keep = np.ones(z.shape, dtype=bool)
        rows = np.full(z.shape[1], -1, dtype=np.int64)
        for u in range(U):
            ch = self._chan_of.get(model.sat_ids[u], -1)
            if ch >= 0:
                rows[u], rows[U + u] = ch, S + ch
        if self._mon_R:
            rows[2 * U:] = 2 * S + np.arange(self._mon_R)
        ok = rows >= 0
        src, dst = np.flatnonzero(ok), rows[ok]
        for b, g in enumerate(group):
            gd = self._guard.get(g[1])
            if gd is None:
                continue
            inert, rr = gd[0][dst], gd[1][dst]
            keep[b, src] = ~inert
            r[b, src] = np.where(inert, r[b, src], rr)
        if keep.all() and np.array_equal(r, model._r):
            return model
        z = np.where(keep, z, 0.0)
        r = np.where(keep, r, 1.0)
        kw = {"row_mask": keep}
        if model.relay:
            kw.update(sat_pos=model.sat_pos, sat_vel=model.sat_vel, relay_mask=model.relay_mask, ground=model.ground,
                      bias_col=model.bias_col, bias_scale=model.bias_scale, sat_ids=model.sat_ids)
        if model.radar:
            kw.update(site=model.site, rot=model.rot, radar_mask=model.radar_mask)
        return SondeMeasurement(self.layout, z, r, **kw)

class _Prepared:
    """A measurement model already evaluated at the monitor's prior: h (N, m), H (N, m, n) and
    the R diagonal (N, m) of the monitor's fixed row layout."""

    def __init__(self, h, H, r):
        self._h, self._H, self._r = h, H, r

    def h_and_H(self, x):
        return self._h, self._H.copy()

    def R_diag(self):
        return self._r
