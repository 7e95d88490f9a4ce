"""The sonde tracker's filter step over an epoch: predict, one joint update of all the rows gated
on its NIS (chi-square), and for the sondes that fail it the relay and radar blocks redone one by
one, each retried once under the manoeuvre hypothesis; EKF, UKF or per sonde ("auto")."""
from __future__ import annotations

import numpy as np
from scipy.special import gammaincinv  # chi2.ppf(q, k) = 2 gammaincinv(k / 2, q), without scipy.stats

from filters import kernels
from filters.ekf import ekf_predicted_step, ekf_update
from filters.ukf import ukf_update

from .epoch_model import MixedSites

__all__ = ["Updates"]


class Updates:
    """SondeTracker's part: the gated predict and update of an epoch."""

    def _gate(self, m: np.ndarray) -> np.ndarray:
        if self.params.gate_prob is None:
            return np.full(m.shape, np.inf)
        out = np.empty(m.shape)
        for i, mi in enumerate(m.tolist()):
            g = self._gates.get(mi)
            if g is None:
                g = self._gates[mi] = float(2.0 * gammaincinv(0.5 * mi, self.params.gate_prob))
            out[i] = g
        return out

    def _predict(self, slots: np.ndarray, t: float) -> None:
        """x- = f(x), P- = F P F' + Q for the sondes in slots, to time t."""
        dts = t - self._t[slots]
        for dt in (dts[:1] if np.all(dts == dts[0]) else np.unique(dts)):
            sel = slots if dts.size == 1 or np.all(dts == dt) else slots[dts == dt]
            landed = self._landed[sel]
            for lnd in ((False, True) if landed.any() else (False,)):
                ss = sel if not landed.any() else sel[landed == lnd]
                if not ss.size:
                    continue
                self._x[ss], self._P[ss] = self._propagate(ss, float(dt), lnd)
        self._t[slots] = t

    def _propagate(self, slots, dt: float, landed: bool):
        """(x-, P-) of the sondes in slots over dt (SondeTransition.predict: relaxed kinematics per
        sonde in its local frame with the descent law as an input; shared F for singer or landed)."""
        return self._transition.predict(self._x[slots], self._P[slots], dt, landed, backend=self.params.backend)

    def _update(self, x, P, z, model, filt: str):
        if filt == "ukf":
            return ukf_update(x, P, z, model, points=self._points, backend=self.params.backend)
        return ekf_update(x, P, z, model, backend=self.params.backend)

    def _gated_update(self, slots: np.ndarray, x, P, model, what: str, dt: float, filt: str) -> np.ndarray:
        """One block update (prior x, P of the sondes in slots) with the chi-square gate and the
        manoeuvre retry; writes the posteriors (or the prior, where rejected) back and returns
        the NIS (NaN where rejected)."""
        c = self.counters
        z = model.z
        res = self._update(x, P, z, model, filt)
        gate = self._gate(model.m_eff)
        nis = np.array(res.nis, dtype=float)
        xo, Po = np.array(res.x), np.array(res.P)
        bad = np.flatnonzero(~(nis <= gate))
        if bad.size:
            res2 = self._update(x[bad], P[bad] + self._transition.boost(dt), z[bad], model.subset(bad), filt)
            ok2 = np.asarray(res2.nis) <= gate[bad]
            acc, rej = bad[ok2], bad[~ok2]
            self._t_init[slots[acc]] = self._t[slots[acc]]  # (already the epoch) a manoeuvre: the monitor waits
            xo[acc], Po[acc], nis[acc] = np.asarray(res2.x)[ok2], np.asarray(res2.P)[ok2], np.asarray(res2.nis)[ok2]
            xo[rej], Po[rej], nis[rej] = x[rej], P[rej], np.nan
            setattr(c, f"{what}_manoeuvre", getattr(c, f"{what}_manoeuvre") + int(acc.size))
            setattr(c, f"{what}_gated", getattr(c, f"{what}_gated") + int(rej.size))
        j = 0 if what == "relay" else 1
        self._rejects[slots, j] = np.where(np.isfinite(nis), 0, self._rejects[slots, j] + 1)
        self._x[slots], self._P[slots] = xo, 0.5 * (Po + np.swapaxes(Po, -1, -2))
        return nis

    def _filter_for(self, group) -> list[str]:
        """The filter of each sonde's update; "auto": the UKF while the position is uncertain on
        the scale of its distance to the radar (or G) -- sqrt(trace P_pos) above
        ``auto_ukf_ratio`` x that distance, where the measurement functions curve within the
        uncertainty (a range-only coast near the radar) -- the EKF otherwise."""
        p = self.params
        if p.filter != "auto":
            return [p.filter] * len(group)
        if len(group) == 1:  # one sonde: plain floats
            _, slot, rel, rad = group[0]
            site = rad.radar_pos_ecef_m if rad is not None else rel.ground_pos_ecef_m
            x, P = self._x[slot], self._P[slot]
            d2 = (x[0] - site[0]) ** 2 + (x[1] - site[1]) ** 2 + (x[2] - site[2]) ** 2
            return ["ukf" if P[0, 0] + P[1, 1] + P[2, 2] > p.auto_ukf_ratio**2 * d2 else "ekf"]
        slots = [g[1] for g in group]
        sites = np.array([g[3].radar_pos_ecef_m if g[3] is not None else g[2].ground_pos_ecef_m for g in group])
        dx = self._x[slots, 0:3] - sites
        P = self._P[slots]
        spread2 = P[:, 0, 0] + P[:, 1, 1] + P[:, 2, 2]
        ukf = spread2 > p.auto_ukf_ratio**2 * np.sum(dx * dx, axis=1)
        return ["ukf" if u else "ekf" for u in ukf.tolist()]

    def _epoch_update(self, group, dt: float, t: float) -> None:
        """Predict the group over dt and update it with all its measurements of the epoch: one
        joint update, gated on its NIS; sondes failing the gate are redone block by block
        (relay, then radar), each block gated with the manoeuvre retry."""
        landed = [bool(self._landed[g[1]]) for g in group]
        if any(landed) and not all(landed):  # one transition per joint update
            for lnd in (False, True):
                self._epoch_update([g for g, x in zip(group, landed) if x == lnd], dt, t)
            return
        filts = self._filter_for(group)
        if len(set(filts)) > 1:
            for f in ("ekf", "ukf"):
                sub = [g for g, fi in zip(group, filts) if fi == f]
                if sub:
                    self._joint_update(sub, dt, t, f)
            return
        self._joint_update(group, dt, t, filts[0])

    def _joint_update(self, group, dt: float, t: float, filt: str) -> None:
        c, p = self.counters, self.params
        try:
            model = None
            if self._mon is not None:  # the monitor built this very group's model already
                model = self._mon_models.pop((dt, tuple(g[1] for g in group)), None)
            if model is None:
                model = self._measurement(group, dt, t)
        except MixedSites:  # different ground receivers / radar sites: one sonde at a time
            for g in group:
                self._joint_update([g], dt, t, filt)
            return
        if self._mon is not None:
            model = self._guarded(model, group)
        if filt == "ukf":
            c.ukf_updates += len(group)
        slots = np.array([g[1] for g in group])
        c.relay_updates += sum(g[2] is not None for g in group)
        n_rad = sum(g[3] is not None for g in group)
        c.radar_updates += n_rad
        c.range_only_updates += sum(g[3] is not None and not g[3].angles_valid for g in group)
        lnd = bool(self._landed[slots[0]])
        tr = self._transition
        shared = lnd or self.layout.wind is None  # one (F, Q) for the group: the fused predict + update kernel
        x, P = self._x[slots], self._P[slots]
        if shared:
            F, Q = tr.F(None, dt, lnd), tr.Q(dt, lnd)
            x_pred, P_pred = x @ F.T, None
        else:
            x_pred, P_pred = self._propagate(slots, dt, lnd)
        if filt == "ekf":
            # shared (F, Q): the fused covariance predict + Joseph update (ekf_predicted_step, the mean
            # predicted above); per-sonde transitions: the update at the prediction
            res = (ekf_predicted_step(x_pred, P, model.z, F, Q, model, backend=p.backend) if shared
                   else ekf_update(x_pred, P_pred, model.z, model, backend=p.backend))
            xo, Po, nis = res.x, res.P, res.nis
        else:
            if P_pred is None:
                P_pred = kernels.cov_predict(F, P, Q, backend=p.backend)
            xo, Po, _, nis = ukf_update(x_pred, P_pred, model.z, model, points=self._points, backend=p.backend)
        gate = self._gate(model.m_eff)
        bad = np.flatnonzero(~(np.asarray(nis) <= gate))
        self._x[slots], self._P[slots] = xo, Po
        self._t[slots] = t
        self._nis[slots] = nis
        if not bad.size:
            self._rejects[slots] = 0
            self._t_meas[slots[model.m_eff > 0]] = t  # an accepted measurement (rows left: not all masked out)
            self._window_manoeuvre(slots, np.asarray(nis, dtype=float), model.m_eff, dt)
            return
        good = np.ones(slots.size, dtype=bool)
        good[bad] = False
        self._rejects[slots[good]] = 0
        self._t_meas[slots[good & (model.m_eff > 0)]] = t
        # block by block for the sondes that failed the joint gate
        bs = slots[bad]
        if P_pred is None:
            P_pred = kernels.cov_predict(F, P[bad], Q, backend=p.backend)
        else:
            P_pred = P_pred[bad]
        self._x[bs], self._P[bs] = x_pred[bad], P_pred
        total, used = np.zeros(bad.size), np.zeros(bad.size, dtype=bool)
        m_used = np.zeros(bad.size, dtype=np.int64)
        for part in (model.relay_part(bad), model.radar_part(bad)):
            if part is None:
                continue
            has = np.flatnonzero(part.m_eff > 0)
            if not has.size:
                continue
            sub = part.subset(has) if has.size < bad.size else part
            v = self._gated_update(bs[has], self._x[bs[has]], self._P[bs[has]], sub,
                                   "relay" if part.relay else "radar", dt, filt)
            total[has] += np.where(np.isfinite(v), v, 0.0)
            used[has] |= np.isfinite(v)
            m_used[has] += np.where(np.isfinite(v), sub.m_eff, 0)
        self._nis[bs] = np.where(used, total, np.nan)
        self._t_meas[bs[used & (m_used > 0)]] = t  # a block accepted (possibly under the manoeuvre hypothesis)
        m_all = model.m_eff.copy()
        m_all[bad] = m_used
        nis_all = np.asarray(nis, dtype=float).copy()
        nis_all[bad] = total
        self._window_manoeuvre(slots, nis_all, m_all, dt)
        self._reacquire(bs, [group[i] for i in bad])

    def _window_manoeuvre(self, slots, nis, m, dt: float) -> None:
        """The sliding-window manoeuvre test (ManoeuvreWindow) on this epoch's NIS; where it fails,
        the manoeuvre covariance scaled by how far the window's NIS exceeds its expectation (a burst
        seen by the radar alone is a 40 m/s surprise, not one acceleration step) is added to the
        posterior, and the integrity monitor waits (integrity_warmup_s)."""
        if self.params.manoeuvre_window is None or self.params.gate_prob is None:
            return
        out = self._window.push(slots, nis, m, self._gate)
        if out is None:
            return
        hs, scale = out
        self._P[hs] += scale[:, None, None] * self._transition.boost(dt)
        self._t_init[hs] = self._t[hs]
        self.counters.window_manoeuvre += int(hs.size)
