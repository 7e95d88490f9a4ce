"""The relayed pseudoranges' error model in the sonde tracker: per satellite, the slow errors
(SISRE, ionosphere, troposphere) as Gauss-Markov states of unit variance scaled by their std at the
estimated geometry, each satellite keeping its state while seen, and the multipath as white noise
of the same low-frequency power (the world's budget: sitl.radio.relay.RelayErrorBudget)."""
from __future__ import annotations

import math

import numpy as np

try:  # the compiled per-satellite loop (numba); the numpy path is the reference
    import numba as _nb
except ImportError:  # pragma: no cover
    _nb = None

from sitl.constants import WGS84
from sitl.radio import relay_error_model as rem

__all__ = ["RelayErrorStates"]


def _relay_err_py(pos, sat_pos, glonass, prm, scale, white):
    """The relay error model's per-satellite numbers (RelayErrorStates._relay_error_model), loop by
    loop for the compiled path: scale (Bs, U) the slow errors' std, white (Bs, U) the multipath's
    PSD-equivalent variance, from the formulas of sitl.radio.relay_error_model at the geometry of
    the estimated positions. prm: [sisre GPS, sisre GLONASS, iono zenith, R/(R + h_I), tropo zenith,
    mp a, mp b, mp el0 (deg), (1 + mu)/(1 - mu), 1/a^2, 1/b^2]."""
    Bs, U = scale.shape
    for b in range(Bs):
        x, y, z = pos[b, 0], pos[b, 1], pos[b, 2]
        nx, ny, nz = x * prm[9], y * prm[9], z * prm[10]
        nn = math.sqrt(nx * nx + ny * ny + nz * nz)
        nx, ny, nz = nx / nn, ny / nn, nz / nn
        r = math.sqrt(x * x + y * y + z * z)
        h = r - r / math.sqrt((x * x + y * y) * prm[9] + z * z * prm[10])
        pr = _pressure_ratio(h)
        for u in range(U):
            dx, dy, dz = sat_pos[b, u, 0] - x, sat_pos[b, u, 1] - y, sat_pos[b, u, 2] - z
            d = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1.0)
            se = min(max((dx * nx + dy * ny + dz * nz) / d, -1.0), 1.0)
            el = math.asin(se)
            iono = _iono_sigma(prm[2], prm[3], el)
            tropo = _tropo_sigma(prm[4], pr, el)
            sis = prm[1] if glonass[u] else prm[0]
            scale[b, u] = math.sqrt(sis * sis + iono * iono + tropo * tropo)
            mp = _multipath_sigma(prm[5], prm[6], prm[7], el)
            white[b, u] = mp * mp * prm[8]


if _nb is None:  # pragma: no cover
    _relay_err_nb = None
else:  # the shared formulas compiled for the loop (the same source as the world's relay)
    _jit = _nb.njit(cache=True, nogil=True)
    _pressure_ratio = _jit(rem.pressure_ratio)
    _iono_sigma = _jit(rem.iono_sigma_m)
    _tropo_sigma = _jit(rem.tropo_sigma_m)
    _multipath_sigma = _jit(rem.multipath_sigma_m)
    _relay_err_nb = _jit(_relay_err_py)


class RelayErrorStates:
    """SondeTracker's part: the per-satellite relay error states and their stds."""

    def _bias_clear(self, slot: int) -> None:
        self._bias_map[slot].clear()
        self._bias_owner[slot] = [None] * self.layout.nb
        self._bias_last[slot] = -np.inf
        self._bias_prev[slot] = None

    def _bias_cols(self, slot: int, sat_ids: tuple, t: float) -> np.ndarray:
        """The state index of each satellite's error state for one sonde (-1: no free state).
        A satellite keeps its state while it is tracked and after (a GNSS outage, a short
        loss); a new one takes the least recently used state not needed now, reset to its
        prior (0, unit variance, uncorrelated)."""
        L = self.layout
        prev = self._bias_prev[slot]
        if prev is not None and prev[0] == sat_ids:
            cols = prev[1]
            self._bias_last[slot, cols[cols >= 0] - L.bias] = t
            return cols
        mp, owner, last = self._bias_map[slot], self._bias_owner[slot], self._bias_last[slot]
        used = {mp[sid] for sid in sat_ids if sid in mp}
        cols = np.empty(len(sat_ids), dtype=np.int64)
        order = None
        for i, sid in enumerate(sat_ids):
            j = mp.get(sid)
            if j is None:
                if order is None:
                    order = np.argsort(last, kind="stable").tolist()
                free = [k for k in order if k not in used]
                if not free:
                    cols[i] = -1
                    self.counters.bias_overflow += 1
                    continue
                j = free[0]
                if owner[j] is not None:
                    del mp[owner[j]]
                mp[sid], owner[j] = j, sid
                k = L.bias + j
                self._x[slot, k] = 0.0
                self._P[slot, k, :] = 0.0
                self._P[slot, :, k] = 0.0
                self._P[slot, k, k] = 1.0
                used.add(j)
                self.counters.bias_assigned += 1
            cols[i] = L.bias + j
            last[j] = t
        self._bias_prev[slot] = (sat_ids, cols)
        return cols

    def _relay_error_model(self, pos, sat_pos, glonass, dt: float):
        """(scale, white) (Bs, U): the per-satellite slow error's std (SISRE + ionosphere +
        troposphere, at the satellites' elevations from the estimated sonde position and its
        height) and the multipath's PSD-equivalent white variance sigma_mp^2 (1 + mu)/(1 - mu),
        mu = e^{-dt/tau_mp} (its correlation time is short against the filter's memory, so it
        goes into R, sized to the same low-frequency power)."""
        e = self.params.relay_errors
        mu = math.exp(-(dt if dt > 0.0 else 1.0) / e.multipath_tau_s)  # dt = 0: a fix's own epoch, 1 Hz
        if _relay_err_nb is not None and np.ndim(pos) == 2 and self.params.backend != "numpy":
            if self._err_prm is None:
                a2, b2 = 1.0 / WGS84.a_m**2, 1.0 / (WGS84.a_m * (1.0 - WGS84.f)) ** 2
                self._err_prm = np.array([e.sisre_gps_m, e.sisre_glonass_m, e.iono_zenith_m,
                                          e.iono_shell_ratio, e.tropo_zenith_m,
                                          e.multipath_a_m, e.multipath_b_m, e.multipath_el0_deg, 0.0,
                                          a2, b2])
            self._err_prm[8] = (1.0 + mu) / (1.0 - mu)
            Bs, U = sat_pos.shape[:2]
            scale, white = np.empty((Bs, U)), np.empty((Bs, U))
            _relay_err_nb(np.ascontiguousarray(pos, dtype=float), np.ascontiguousarray(sat_pos, dtype=float),
                          np.ascontiguousarray(glonass), self._err_prm, scale, white)
            return scale, white
        # the geodetic vertical and height, to well below the model's needs for h < 100 km (the
        # ellipsoid's normal at the point, and the distance above the ellipsoid along the radius)
        ax2, bx2 = 1.0 / WGS84.a_m**2, 1.0 / (WGS84.a_m * (1.0 - WGS84.f)) ** 2
        nrm = pos * np.array([ax2, ax2, bx2])
        up = nrm / np.linalg.norm(nrm, axis=-1, keepdims=True)
        r = np.linalg.norm(pos, axis=-1)
        hgt = r - 1.0 / np.sqrt((pos[..., 0] ** 2 + pos[..., 1] ** 2) * ax2 + pos[..., 2] ** 2 * bx2) * r
        d = sat_pos - pos[..., None, :]
        el = np.arcsin(np.clip(np.sum(d * up[..., None, :], axis=-1)
                               / np.maximum(np.linalg.norm(d, axis=-1), 1.0), -1.0, 1.0))
        sig = e.slow_sigmas_m(glonass, el, np.asarray(hgt)[..., None])
        return np.sqrt(np.sum(sig * sig, axis=-1)), e.multipath_sigma_m(el) ** 2 * ((1.0 + mu) / (1.0 - mu))
